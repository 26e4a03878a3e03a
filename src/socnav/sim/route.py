"""The route a policy observes (``planner.observe``): the goal turned towards its path's subgoal, and the subgoal on
a path given from outside (a nav_msgs/Path). Shared by the world (training) and the deployed navigator.

DRL-VO's sub-goal from the global planner, in the layout of the open plane: the observed goal keeps the goal's
distance and takes the subgoal's direction, so a policy reads "how far" and "which way" as it always did.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from socnav.sim.planning_kernels import follow_path

__all__ = ["observed_goals", "subgoal_on_path", "validate_path"]

#: A subgoal nearer than this to the robot gives no direction: the goal itself is observed.
_NO_DIRECTION = 1e-9


def observed_goals(positions: np.ndarray, subgoals: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """The goals a route-observing policy sees ((E, 2) each): ``position + |goal - position| * unit(subgoal -
    position)``; the goal itself where the subgoal coincides with the position (nothing to point at)."""
    toward = subgoals - positions
    length = np.linalg.norm(toward, axis=1, keepdims=True)
    distance = np.linalg.norm(goals - positions, axis=1, keepdims=True)
    unit = np.divide(toward, length, out=np.zeros_like(toward), where=length > _NO_DIRECTION)
    return np.where(length > _NO_DIRECTION, positions + unit * distance, goals)


def validate_path(path: Any, name: str = "path") -> np.ndarray:
    """A path of (x, y) waypoints as a float64 (M, 2) array, M >= 1, every coordinate finite; a ValueError names
    the field and the rule otherwise."""
    if isinstance(path, (str, bytes)) or not isinstance(path, (Sequence, np.ndarray)):
        raise ValueError(f"{name}: expected a list of (x, y) waypoints, got {type(path).__name__}")
    try:
        array = np.asarray(path, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a list of (x, y) waypoints of numbers") from None
    if array.ndim != 2 or array.shape[1] != 2 or len(array) == 0:
        raise ValueError(f"{name}: expected shape (M, 2) with M >= 1 waypoints, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name}: waypoint {int(np.flatnonzero(~np.isfinite(array).all(axis=1))[0])} is not finite")
    return array


def subgoal_on_path(path: np.ndarray, position: np.ndarray, lookahead: float) -> np.ndarray:
    """The point `lookahead` metres along `path` ((M, 2), validated) beyond its point nearest to `position` (its last
    waypoint at most): pure pursuit on a path the robot is given, the rule `PathFollower` applies to its own."""
    if len(path) == 1:
        return path[0].copy()
    return follow_path(np.ascontiguousarray(path), np.asarray(position, dtype=np.float64), float(lookahead))
