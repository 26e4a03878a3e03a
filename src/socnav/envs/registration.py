"""Gymnasium ids for the paper's four scenarios and the four with walls: `gymnasium.make("socnav/CircleCrossing-v0")`.

Keyword arguments of `gymnasium.make` become config overrides (e.g. `n_humans=3`, `config="my.yaml"`).
"""

from __future__ import annotations

import gymnasium as gym

GYM_IDS = {
    "socnav/PositionSwap-v0": "position_swap",
    "socnav/CircleCrossing-v0": "circle_crossing",
    "socnav/CircleInteraction-v0": "circle_interaction",
    "socnav/Random-v0": "random",
    "socnav/Corridor-v0": "corridor",
    "socnav/Doorway-v0": "doorway",
    "socnav/Intersection-v0": "intersection",
    "socnav/Room-v0": "room",
}


def register_envs() -> None:
    """Register every socnav id with Gymnasium (idempotent)."""
    for env_id, scenario in GYM_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="socnav.envs.env:SocialNavEnv", kwargs={"scenario": scenario})
