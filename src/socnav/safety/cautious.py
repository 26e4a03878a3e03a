"""The cautious fallback controller of the safety layer (paper IV-C).

ORCA for the robot towards its goal, from the observation it is given (by :class:`~socnav.safety.SafePolicy`: the
robot's observation, or with ``sensing: true`` the simulator's noise-free one), with every human's radius taken
``radius_scale`` (1.5) times its OBSERVED value (the human row's field 4; the robot's own radius is unchanged), the
ORCA velocity turned into ``(v, dtheta)`` within the robot's limits (``holonomic_to_unicycle``: speed in
``[0, v_pref]``, turn within ``max_heading_change``), i.e. an action in ``[-1, 1]^2``.

It reuses :class:`socnav.controllers.OrcaController` (same ORCA code as the humans). As there, the robot
takes the config's ``robot_orca_share`` of the avoidance (default 1: it assumes nothing of the humans, which is the
cautious choice when humans may not yield) and adds ``robot_orca_safety_margin`` metres to each (scaled) radius.
In a world with walls it also keeps off them (RVO2's obstacle constraints, planned in the map frame from the
observation's ``pose``): the config's walls, or the polygons given as ``walls`` (the deployed navigator's map),
and with the config's ``planner`` on it heads for the subgoal of its path around them, as the ORCA controller does.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from socnav.config import ConfigLike, load_config
from socnav.controllers import OrcaController

__all__ = ["CAUTIOUS_RADIUS_SCALE", "CautiousController"]

CAUTIOUS_RADIUS_SCALE = 1.5


class CautiousController(OrcaController):
    """``OrcaController`` with human radii scaled by ``radius_scale`` (default 1.5); actions clipped to [-1, 1]^2.

    ``predict(observation, state=None, episode_start=None, deterministic=True) -> (actions, None)`` accepts a
    single or a batched observation, like the other controllers; with walls the observation must hold ``pose``.

    :param walls: the walls to keep off, polygons of (x, y) vertices in the map frame in RVO2's convention (as
        `socnav.sim.walls.world_polygons` gives them; validated by the caller); None: the config's (its
        scenario's map, ``obstacles`` and ``map``); an empty list: none.
    """

    def __init__(self, config: ConfigLike = None, radius_scale: float = CAUTIOUS_RADIUS_SCALE,
                 share: float | None = None, safety_margin: float | None = None,
                 walls: Sequence[np.ndarray] | None = None):
        super().__init__(load_config(config), radius_scale=radius_scale, share=share, safety_margin=safety_margin,
                         walls=walls)

    def predict(self, observation: dict[str, np.ndarray], state: Any = None, episode_start: Any = None,
                deterministic: bool = True):
        actions, _ = super().predict(observation, state, episode_start, deterministic)
        actions = np.array(actions, dtype=np.float32)
        bad = ~np.isfinite(actions)
        if bad.any():  # never hand the env a NaN: stop (speed -1) and keep the heading (turn 0)
            actions[..., 0][bad[..., 0]] = -1.0
            actions[..., 1][bad[..., 1]] = 0.0
        return np.clip(actions, -1.0, 1.0), None
