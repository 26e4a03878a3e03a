"""The safety layer's wall stop: a step that would bring the robot's disc onto a wall of its map is not taken.

Like the stop zone of nav2's collision monitor, but from the map and the robot's pose rather than a scan: the
command's straight move (the simulator's: turn first, then drive along the new heading for one step) is swept with
the robot's radius against the walls, and where it touches one the speed action becomes -1 (stand still; the turn is
kept, so the robot can turn away). Whoever chose the action -- the policy or the cautious fallback -- the layer
never drives into a wall it knows (docs/maps.md, "The policy, the safety layer and the deployed navigator").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from socnav.sim.walls import POSE_KEY, Walls

__all__ = ["WallStop"]


class WallStop:
    """Stops the steps that would touch a wall.

    :param polygons: the walls, polygons of (x, y) vertices in the map frame (RVO2's convention, validated by the
        caller), as `socnav.sim.walls.world_polygons` gives them.
    :param time_step: seconds per step (the config's ``time_step``).
    :param max_heading_change: radians turned by a turn action of 1 (the config's ``max_heading_change``).
    """

    def __init__(self, polygons: Sequence[np.ndarray], time_step: float, max_heading_change: float):
        if not polygons:
            raise ValueError("WallStop needs at least one wall polygon")
        self.polygons = [np.asarray(vertices, dtype=np.float64) for vertices in polygons]
        self.time_step = float(time_step)
        self.max_heading_change = float(max_heading_change)
        self._walls: Walls | None = None

    def _walls_for(self, n_rows: int) -> Walls:
        """The walls in the batched form `Walls` keeps (one copy per row), grown when a larger batch comes."""
        if self._walls is None or len(self._walls.n_segments) < n_rows:
            self._walls = Walls(self.polygons, n_rows)
        return self._walls

    def touches(self, actions: np.ndarray, observation: Mapping[str, np.ndarray],
                v_pref: np.ndarray | float | None = None) -> np.ndarray:
        """(B,) bool: the rows whose action (B, 2), taken from the observation's ``pose`` (B, 3: x, y, yaw in the map
        frame) at the speed ``v_pref (a0 + 1) / 2`` and turn ``max_heading_change a1``, would sweep the robot's disc
        (radius: ``robot`` row field 4) over a wall within the step. `v_pref`: the preferred speed(s) at full
        precision (None: the observation's, ``robot`` field 3)."""
        pose = np.asarray(observation[POSE_KEY], dtype=np.float64).reshape(-1, 3)
        robot = np.asarray(observation["robot"], dtype=np.float64).reshape(len(pose), -1)
        speed_limit = robot[:, 3] if v_pref is None else np.broadcast_to(np.asarray(v_pref, np.float64), len(pose))
        clipped = np.clip(np.asarray(actions, dtype=np.float64).reshape(len(pose), 2), -1.0, 1.0)
        heading = pose[:, 2] + self.max_heading_change * clipped[:, 1]
        distance = speed_limit * (clipped[:, 0] + 1.0) / 2.0 * self.time_step
        before = np.ascontiguousarray(pose[:, :2])
        after = before + distance[:, None] * np.column_stack((np.cos(heading), np.sin(heading)))
        return self._walls_for(len(pose)).robot_hit(before, np.ascontiguousarray(after), robot[:, 4])

    def apply(self, actions: np.ndarray, observation: Mapping[str, np.ndarray],
              v_pref: np.ndarray | float | None = None) -> np.ndarray:
        """Set the speed action of the rows whose step would touch a wall (:meth:`touches`) to -1, in place;
        returns those rows, (B,) bool."""
        stopped = self.touches(actions, observation, v_pref)
        actions[stopped, 0] = -1.0
        return stopped
