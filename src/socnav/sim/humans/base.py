"""What every model of the humans reads from the world (`Crowd`) and what it computes (`HumanModel`).

A model turns the world's arrays into the next velocity of every human of every environment in one call; the world
then moves each human by that velocity times the time step (p <- p + v dt), so a model decides velocities only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Crowd:
    """The world's arrays a human model reads: views of `socnav.sim.world.CrowdWorld`'s state, never copies.

    E environments of N agent slots; slot 0 is the robot, slots 1.. are humans, inactive slots are padding. A model
    must not write to these arrays. The last three are per pair (i, j): how agent i treats agent j. Between humans
    they are neutral (no pad, an even share, always seen); towards the robot (column 0) they carry each human's
    social traits, so every model receives attention and personal space and uses them as it can:

    * ``sees[e, i, 0]`` is False while human i ignores the robot: the robot is invisible
      (``robot_visible: false``), the human is inattentive this episode, or the robot has not yet entered its view
      cone (field of view, ``human_fov_deg``). A model must then treat the robot as absent.
    * ``radius_pad[e, i, 0]`` is human i's personal space: the free space beyond the bodies it keeps from the robot.
    * ``avoidance_share[e, i, 0]`` is human i's cooperation: its share of a reciprocal avoidance (0.5 = even).
    """

    positions: np.ndarray  # (E, N, 2) m
    velocities: np.ndarray  # (E, N, 2) m/s, those of the last step (the robot's is its unicycle velocity)
    goals: np.ndarray  # (E, N, 2) m
    radii: np.ndarray  # (E, N) m, body radii
    max_speeds: np.ndarray  # (E, N) m/s: each human's preferred speed v_pref (after `human_speed_factor`)
    active: np.ndarray  # (E, N) bool: the slot holds a real agent
    radius_pad: np.ndarray  # (E, N, N) m: extra radius agent i adds to agent j
    avoidance_share: np.ndarray  # (E, N, N): share of the avoidance agent i takes w.r.t. agent j
    sees: np.ndarray  # (E, N, N) bool: agent i responds to agent j
    #: (E, N) int: in a mixed crowd (``humans.mix``), the index of the model that moves each human (the order of
    #: `socnav.sim.humans.MixedHumans.models`); zeros otherwise. Single models ignore it.
    model_index: np.ndarray | None = None
    #: the world's static walls (`socnav.sim.obstacles.ObstacleBatch`, RVO2's processed obstacles of each env);
    #: None without walls. Models that avoid walls read it; ORCA uses RVO2's obstacle half-planes.
    obstacles: Any = None
    #: the same walls as their edges, unsplit (`socnav.sim.geometry.polygon_segments`): (seg_start (E, S, 2),
    #: seg_end (E, S, 2), n_segments (E,) int64); None without walls. The social force samples points along them.
    wall_segments: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


@runtime_checkable
class HumanModel(Protocol):
    """A model of how humans walk. `velocities` is its one batched call; the two attributes tell the world how far
    the model's humans react to a robot they have noticed, and how close to its goal a human counts as arrived."""

    name: str
    #: metres: a human that has noticed the robot (field of view) keeps reacting to it while it stays this close
    interaction_range: float
    #: metres: a human this close to its goal stops there; goals are redrawn within max(goal_tolerance, this)
    arrival_distance: float

    def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
        """New velocities (E, N, 2) float64 of the agents where `compute` (E, N) bool is True; every other slot
        keeps its current velocity (``crowd.velocities``). Results of one environment depend on it alone."""
        ...


@runtime_checkable
class ScriptedHumans(Protocol):
    """A `HumanModel` whose humans follow a script rather than the crowd (``replay``): humans may enter and leave
    mid-episode, so the world hands it its arrays at three moments. Each hook writes only the arrays it is given.

    * `attach` once, when the world is built; `start_episode` at every (re)start of environment `env`, with the
      ``script`` entry the scenario's `socnav.sim.scenarios.InitialState` carries for it;
    * `before_move` each step, before the move: humans that leave set ``active`` False (returns those slots);
    * `after_move` each step, after the move: positions set to the script's, humans that enter take an inactive
      slot (``active`` True, position, velocity, goal; returns those slots).
    """

    def attach(self, n_envs: int, n_slots: int) -> None: ...

    def start_episode(self, env: int, plan: Any, positions: np.ndarray, velocities: np.ndarray, goals: np.ndarray,
                      active: np.ndarray) -> None: ...

    def before_move(self, active: np.ndarray, velocities: np.ndarray) -> np.ndarray: ...

    def after_move(self, positions: np.ndarray, velocities: np.ndarray, goals: np.ndarray,
                   active: np.ndarray) -> np.ndarray: ...


class HumanSettings(Protocol):
    """The values of a world's config that the built-in models read; `socnav.config.EnvConfig` provides them. sim/
    sees these plain values and never imports the config layer (which imports sim/ for the model names)."""

    time_step: float
    orca: Any  # time_horizon, neighbor_dist, max_neighbors
    humans: Any  # model, social_force (its parameters), mix (shares), replay (trajectory files)
