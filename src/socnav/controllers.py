"""The robot's non-learned controllers: the baselines and the ORCA controller the safety layer's cautious fallback
extends. Both (`orca`, `straight`) act from the observation alone with SB3's `predict(...) -> (actions, None)`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from socnav.config import EnvConfig
from socnav.sim.obstacles import ObstacleBatch, ObstacleMap
from socnav.sim.orca import orca_velocities
from socnav.sim.planning import GlobalPlanner, PathFollower, planner_for, redirect_to_subgoals
from socnav.sim.scenarios import get_scenario
from socnav.sim.walls import POSE_KEY, world_polygons

Observation = dict[str, np.ndarray]


def _batched(observation: Observation) -> tuple[Observation, bool]:
    single = observation["robot"].ndim == 1
    if single:
        observation = {key: value[None] for key, value in observation.items()}
    return observation, single


#: How a robot that a velocity behind it has stopped turns (`holonomic_to_unicycle`'s ``stopped_turn``).
STOPPED_TURNS = ("velocity", "goal", "goal-if-behind")
#: ``"goal-if-behind"``: the velocities this close to straight behind the robot (rad) have no clear side.
NO_CLEAR_SIDE = np.pi / 4


def holonomic_to_unicycle(
    desired: np.ndarray, observation: Observation, max_heading_change: float, stopped_turn: str = "velocity"
) -> np.ndarray:
    """Turn desired velocities (goal frame, (E, 2)) into actions in [-1, 1]^2 within the robot's limits.

    Turn towards the desired direction by at most `max_heading_change`; drive at |u| cos(remaining heading error)
    so the robot never moves sideways of where ORCA allows, and stops while it is still facing away. Stopped so,
    it turns towards the desired velocity (``stopped_turn="velocity"``) or to face the goal (``"goal"``, the path's
    subgoal when the observation follows the planner): near a wall ORCA's answer is a slow velocity away from it,
    whose side changes between similar states, and a policy imitating those labels averages them to driving on
    (docs/maps.md, "Why DAgger hits walls").
    ``"goal-if-behind"`` faces the goal only while the velocity is within :data:`NO_CLEAR_SIDE` of straight behind,
    and turns towards a velocity with a clear side (away from a person walking at the robot, say).
    """
    if stopped_turn not in STOPPED_TURNS:
        raise ValueError(f"stopped_turn must be one of {list(STOPPED_TURNS)}, got {stopped_turn!r}")
    robot = observation["robot"].astype(np.float64)
    heading, preferred_speed = robot[:, 1], np.maximum(robot[:, 3], 1e-6)
    speed = np.linalg.norm(desired, axis=1)
    target = np.where(speed > 1e-6, np.arctan2(desired[:, 1], desired[:, 0]), 0.0)  # at rest: face the goal
    error = np.remainder(target - heading + np.pi, 2 * np.pi) - np.pi
    turn = np.clip(error, -max_heading_change, max_heading_change)
    forward = np.minimum(speed, preferred_speed) * np.maximum(np.cos(error - turn), 0.0)
    if stopped_turn != "velocity":
        to_goal = np.clip(np.remainder(-heading + np.pi, 2 * np.pi) - np.pi, -max_heading_change, max_heading_change)
        stopped = np.cos(error - turn) <= 0.0
        if stopped_turn == "goal-if-behind":
            stopped &= np.abs(error) > np.pi - NO_CLEAR_SIDE
        turn = np.where(stopped, to_goal, turn)
    actions = np.stack([2.0 * forward / preferred_speed - 1.0, turn / max_heading_change], axis=1)
    return np.clip(actions, -1.0, 1.0).astype(np.float32)


def _goal_velocity(observation: Observation, time_step: float) -> np.ndarray:
    """v_pref towards the goal (the +x axis of the goal frame), slowing down to stop on it."""
    robot = observation["robot"].astype(np.float64)
    speed = np.minimum(np.maximum(robot[:, 3], 0.0), np.maximum(robot[:, 0], 0.0) / time_step)
    return np.stack([speed, np.zeros_like(speed)], axis=1)


def _rotate(vectors: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Vectors (E, K, 2) rotated counter-clockwise by `angle` (E,)."""
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    x, y = vectors[..., 0], vectors[..., 1]
    return np.stack([cos * x - sin * y, sin * x + cos * y], axis=-1)


class StraightController:
    """Head for the goal at the preferred speed, ignoring humans."""

    def __init__(self, config: EnvConfig):
        self.config = config

    def predict(self, observation: Observation, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """SB3's `predict`: the actions of a (batch of) observation(s), no recurrent state."""
        observation, single = _batched(observation)
        actions = holonomic_to_unicycle(
            _goal_velocity(observation, self.config.time_step), observation, self.config.max_heading_change
        )
        return (actions[0] if single else actions), None


class OrcaController:
    """The robot driven by the same ORCA code as the humans, from its observation, in the goal-aligned frame.

    `radius_scale` inflates every observed human radius (1.5 for the safety layer's cautious controller); `share` is
    the robot's share of the avoidance effort and `safety_margin` metres are added to every human's radius
    (defaults: the config's `robot_orca_share` and `robot_orca_safety_margin`). `walls`: the polygons to keep off
    (RVO2's convention, validated by the caller); None: the config's (its scenario's map, ``obstacles``, ``map``).
    `stopped_turn`: how the robot turns while ORCA's velocity, behind it, stops it (`holonomic_to_unicycle`).

    Among walls, with the config's ``planner`` on (the default), ORCA's preferred velocity points at the subgoal of
    the robot's shortest path to its goal (`socnav.sim.planning`), planned from the observation's ``pose`` and goal;
    it is the goal itself, as without a planner, whenever the straight line to the goal keeps the robot's radius from
    every wall.
    """

    def __init__(self, config: EnvConfig, radius_scale: float = 1.0, share: float | None = None,
                 safety_margin: float | None = None, walls: Sequence[np.ndarray] | None = None,
                 stopped_turn: str = "velocity"):
        if radius_scale <= 0:
            raise ValueError(f"radius_scale must be > 0, got {radius_scale}")
        if stopped_turn not in STOPPED_TURNS:
            raise ValueError(f"stopped_turn must be one of {list(STOPPED_TURNS)}, got {stopped_turn!r}")
        self.stopped_turn = stopped_turn
        self.config = config
        self.radius_scale = radius_scale
        self.share = config.robot_orca_share if share is None else share
        self.safety_margin = config.robot_orca_safety_margin if safety_margin is None else safety_margin
        polygons = world_polygons(config, get_scenario(config.scenario)) if walls is None else list(walls)
        #: the walls' polygons (map frame; empty in the open plane) and the form ORCA reads them in (None: none)
        self.wall_polygons = polygons
        self.walls = ObstacleMap.from_polygons(polygons) if polygons else None
        self._wall_batches: dict[int, ObstacleBatch] = {}
        #: the robot's global planner (None in the open plane or with ``planner.enabled: false``)
        self.planner: GlobalPlanner | None = None
        if polygons and config.planner.enabled:
            self.planner = planner_for(polygons, config.robot_radius + config.planner.margin)
        self._followers: dict[int, PathFollower] = {}
        #: reuse a robot's path from one call to the next (rows are environments that `on_episode_start` names);
        #: False plans afresh at every call, for a caller whose rows change from call to call (the safety layer
        #: hands the fallback only the rows where it drives), so that no row inherits another robot's path
        self.keep_paths = True

    def _follower(self, n_envs: int) -> PathFollower:
        """The paths of a batch of `n_envs` robots, kept per batch size (a path is reused only while it fits the
        robot's pose and goal, so a batch of other robots, or in another order, is safe, if slower)."""
        follower = self._followers.get(n_envs)
        if follower is None and self.planner is not None:
            planner = self.config.planner
            # The goal is read back from the float32 observation (and its noise): it moves a little every step.
            follower = PathFollower(self.planner, n_envs, planner.lookahead, planner.replan_distance,
                                    goal_tolerance=planner.replan_distance, direct_clearance=self.config.robot_radius)
            self._followers[n_envs] = follower
        assert follower is not None
        return follower

    def _steer_to_subgoals(self, preferred: np.ndarray, pose: np.ndarray, distance: np.ndarray,
                           goal_angle: np.ndarray) -> None:
        """Turn the robot's preferred velocity (map frame, `preferred` (E, N, 2), slot 0) towards its path's subgoal,
        at the same speed, where the straight line to the goal does not keep the robot's radius from every wall (in
        place; `socnav.sim.planning.PathFollower`)."""
        position = np.ascontiguousarray(pose[:, :2])
        goals = position + distance[:, None] * np.column_stack((np.cos(goal_angle), np.sin(goal_angle)))
        follower = self._follower(len(pose))
        if not self.keep_paths:
            follower.forget(slice(None))
        subgoals, direct = follower.update(position, goals)
        redirect_to_subgoals(preferred[:, 0], position, subgoals, direct)

    def _obstacles(self, walls: ObstacleMap, n_envs: int) -> ObstacleBatch:
        """The map's walls once per environment, built once per batch size."""
        if n_envs not in self._wall_batches:
            self._wall_batches[n_envs] = ObstacleBatch.from_maps([walls] * n_envs)
        return self._wall_batches[n_envs]

    def desired_velocity(self, observation: Observation) -> np.ndarray:
        """ORCA's new holonomic velocity for the robot of each environment, in the goal frame, (E, 2)."""
        robot = observation["robot"].astype(np.float64)
        humans = observation["humans"].astype(np.float64)
        n_envs, max_humans, _ = humans.shape
        n_agents = 1 + max_humans
        heading, speed = robot[:, 1], robot[:, 2]
        robot_velocity = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=1)

        positions = np.zeros((n_envs, n_agents, 2))
        velocities = np.zeros((n_envs, n_agents, 2))
        radii = np.zeros((n_envs, n_agents))
        positions[:, 1:] = humans[:, :, 0:2]
        velocities[:, 0] = robot_velocity
        velocities[:, 1:] = humans[:, :, 2:4] + robot_velocity[:, None, :]  # observed velocities are relative
        radii[:, 0] = np.maximum(robot[:, 4], 0.0)
        radii[:, 1:] = np.maximum(humans[:, :, 4], 0.0) * self.radius_scale
        active = np.concatenate([np.ones((n_envs, 1), bool), observation["humans_mask"] > 0.5], axis=1)
        compute = np.zeros_like(active)
        compute[:, 0] = True
        preferred = np.zeros((n_envs, n_agents, 2))
        preferred[:, 0] = _goal_velocity(observation, self.config.time_step)
        max_speeds = np.zeros((n_envs, n_agents))
        max_speeds[:, 0] = np.maximum(robot[:, 3], 0.0)
        # ORCA plans tangent to the velocity obstacle; a margin keeps the discretised unicycle off the human's body.
        pad = np.zeros((n_envs, n_agents, n_agents))
        pad[:, 0, :] = self.safety_margin
        share = np.full((n_envs, n_agents, n_agents), 0.5)
        share[:, 0, :] = self.share
        orca = self.config.orca
        obstacles: ObstacleBatch | None = None
        if self.walls is not None:
            # Walls are known in the map frame: plan there, from the robot's pose (x, y, yaw), and turn the answer
            # back into the goal frame, whose x axis points at the angle yaw - (heading relative to the goal).
            if POSE_KEY not in observation:
                raise ValueError(f"the ORCA controller of a world with walls needs the observation's {POSE_KEY!r}")
            pose = observation[POSE_KEY].astype(np.float64)
            goal_angle = pose[:, 2] - heading
            positions, velocities, preferred = (_rotate(array, goal_angle) for array in (positions, velocities,
                                                                                          preferred))
            positions += pose[:, None, :2]
            if self.planner is not None:
                self._steer_to_subgoals(preferred, pose, np.maximum(robot[:, 0], 0.0), goal_angle)
            # The margin moves from the humans' radii to the robot's own, so that it keeps off walls as well.
            radii[:, 0] += self.safety_margin
            pad[:, 0, :] = 0.0
            obstacles = self._obstacles(self.walls, n_envs)
        velocities = orca_velocities(
            positions, velocities, radii, preferred, max_speeds, active, compute,
            pad, share, np.ones((n_envs, n_agents, n_agents), bool),
            orca.time_horizon, orca.neighbor_dist, orca.max_neighbors, self.config.time_step,
            obstacles=obstacles, time_horizon_obst=None if obstacles is None else orca.time_horizon_obst,
        )
        if self.walls is not None:
            return _rotate(velocities[:, :1], -goal_angle)[:, 0]
        return velocities[:, 0]

    def on_episode_start(self, envs: np.ndarray) -> None:
        """`socnav.envs.rollout.rollout_episodes` hook: environments `envs` start new episodes, so no path of the
        last episode in those rows is followed (an episode's play does not depend on which episode ran before it in
        its row, nor on the batch size)."""
        rows = np.asarray(envs, dtype=np.int64)
        for size, follower in self._followers.items():
            follower.forget(rows[rows < size])

    def predict(self, observation: Observation, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """SB3's `predict`: the actions of a (batch of) observation(s), no recurrent state."""
        observation, single = _batched(observation)
        actions = holonomic_to_unicycle(self.desired_velocity(observation), observation,
                                        self.config.max_heading_change, self.stopped_turn)
        return (actions[0] if single else actions), None


CONTROLLERS = {"orca": OrcaController, "straight": StraightController}


def make_controller(name: str, config: EnvConfig) -> OrcaController | StraightController:
    """A baseline controller by name: one of `orca`, `straight`."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; allowed: {', '.join(CONTROLLERS)}")
    return CONTROLLERS[name](config)
