"""Observation and action spaces shared by the single and the vectorised environment (docs/world.md, "Observation
and action").

The observation is a Dict: `robot` (5), `humans` (max_humans x 7, closest real row last, zero padding after),
`humans_mask`; in a world with walls also `pose` (3), and with a range scan `scan` (beams).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from socnav.sim.walls import POSE_KEY, SCAN_KEY
from socnav.sim.world import HUMAN_FEATURES, ROBOT_FEATURES

ROBOT_FEATURE_NAMES = ("goal_distance", "goal_heading", "speed", "preferred_speed", "radius")
HUMAN_FEATURE_NAMES = ("rel_x", "rel_y", "rel_vx", "rel_vy", "radius", "combined_radius", "gap")
ACTION_NAMES = ("speed", "heading")  # action dimension 0 maps to speed, 1 to heading change


def observation_space(max_humans: int, pose: bool = False, scan: Any = None) -> spaces.Dict:
    """The Dict observation space for `max_humans` padded human rows; with walls, `pose` (x, y, yaw in the map
    frame); with a range scan (`scan`: beams, range), `scan` (beams ranges in [0, range] m)."""
    keys: dict[str, spaces.Space[Any]] = {
        "robot": spaces.Box(-np.inf, np.inf, (ROBOT_FEATURES,), np.float32),
        "humans": spaces.Box(-np.inf, np.inf, (max_humans, HUMAN_FEATURES), np.float32),
        "humans_mask": spaces.Box(0.0, 1.0, (max_humans,), np.float32),
    }
    if pose:
        keys[POSE_KEY] = spaces.Box(-np.inf, np.inf, (3,), np.float32)
    if scan is not None:
        keys[SCAN_KEY] = spaces.Box(0.0, float(scan.range), (int(scan.beams),), np.float32)
    return spaces.Dict(keys)


def world_observation_space(world: Any) -> spaces.Dict:
    """The observation space of a `socnav.sim.world.CrowdWorld`'s observations."""
    return observation_space(world.config.max_humans, pose=world.walls is not None, scan=world.config.scan)


def action_space() -> spaces.Box:
    """[-1, 1]^2: speed v = v_pref (a0 + 1) / 2 and heading change = max_heading_change * a1."""
    return spaces.Box(-1.0, 1.0, (2,), np.float32)
