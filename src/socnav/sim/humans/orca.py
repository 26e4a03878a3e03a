"""ORCA humans: each walks at its preferred speed towards its goal and takes the closest collision-free velocity
(RVO2 semantics, `socnav.sim.orca`), with the robot padded by its personal space and its own share of avoidance.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from socnav.sim.humans.base import Crowd, HumanSettings
from socnav.sim.orca import orca_velocities


@numba.njit(cache=True)
def preferred_velocities(positions, goals, max_speeds, active, time_step):
    """v_pref * unit(goal - p) for humans, slowing down to stop exactly on the goal; zero for the robot slot."""
    n_envs, n_agents = active.shape
    preferred = np.zeros((n_envs, n_agents, 2))
    for env in range(n_envs):
        for agent in range(1, n_agents):
            if not active[env, agent]:
                continue
            dx = goals[env, agent, 0] - positions[env, agent, 0]
            dy = goals[env, agent, 1] - positions[env, agent, 1]
            distance = math.sqrt(dx * dx + dy * dy)
            if distance < 1e-9:
                continue
            speed = min(max_speeds[env, agent], distance / time_step)
            preferred[env, agent, 0] = speed * dx / distance
            preferred[env, agent, 1] = speed * dy / distance
    return preferred


class OrcaHumans:
    """`HumanModel` "orca": every input of the `Crowd` is used as ORCA's own.

    Attention: a robot a human does not see (``sees``) takes no neighbour slot and adds no ORCA half-plane.
    Walls: RVO2's obstacle half-planes (``orca.time_horizon_obst``), before the agents' ones.
    Personal space: ``radius_pad`` enlarges the robot's radius in that human's ORCA. Cooperation:
    ``avoidance_share`` is the human's share of the velocity correction (RVO2's 0.5 between humans).
    """

    name = "orca"
    arrival_distance = 0.0  # a human slows down to stop exactly on its goal

    def __init__(self, time_horizon: float, neighbor_dist: float, max_neighbors: int, time_step: float,
                 time_horizon_obst: float = 2.0):
        self.time_horizon = float(time_horizon)
        self.time_horizon_obst = float(time_horizon_obst)
        self.neighbor_dist = float(neighbor_dist)
        self.max_neighbors = int(max_neighbors)
        self.time_step = float(time_step)
        self.interaction_range = self.neighbor_dist  # the robot counts once it is an ORCA neighbour candidate

    @classmethod
    def from_config(cls, config: HumanSettings) -> OrcaHumans:
        orca = config.orca
        return cls(orca.time_horizon, orca.neighbor_dist, orca.max_neighbors, config.time_step,
                   orca.time_horizon_obst)

    def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
        preferred = preferred_velocities(crowd.positions, crowd.goals, crowd.max_speeds, crowd.active,
                                         self.time_step)
        return orca_velocities(
            crowd.positions, crowd.velocities, crowd.radii, preferred, crowd.max_speeds, crowd.active, compute,
            crowd.radius_pad, crowd.avoidance_share, crowd.sees,
            self.time_horizon, self.neighbor_dist, self.max_neighbors, self.time_step,
            **({} if crowd.obstacles is None else {"obstacles": crowd.obstacles,
                                                    "time_horizon_obst": self.time_horizon_obst}),
        )
