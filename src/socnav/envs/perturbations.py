"""Perturbed worlds (paper section V-B): one perturbation type at one strength as an env config, the strengths Table 2
and Table 3 sweep, and the disjoint set `socnav calibrate` tunes the safety thresholds on.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from socnav.config import EnvConfig, load_config

#: Perturbation type -> config field of `socnav.config.PerturbationConfig`.
PERTURBATION_FIELDS = {
    "observation_noise": "observation_noise",
    "heading_noise": "heading_noise",
    "speed_noise": "speed_noise",
    "faster_humans": "human_speed_factor",
    "more_humans": "total_agents",
}

#: The paper's strengths: noise sigma in {0, 0.2, ..., 2} (speed noise is a factor U(1 - s, 1), so s stops at 1),
#: human speed factor l_vel in {1, ..., 8}, N in {2, ..., 7} agents in total (2 = the unperturbed position swap).
PAPER_GRIDS: dict[str, list[float]] = {
    "observation_noise": [round(float(x), 1) for x in np.arange(0.0, 2.01, 0.2)],
    "heading_noise": [round(float(x), 1) for x in np.arange(0.0, 2.01, 0.2)],
    # the paper's 0 ... 2 (SPEC section 2): the world clips s to [0, 1], so s > 1 plays as s = 1
    "speed_noise": [round(float(x), 1) for x in np.arange(0.0, 2.01, 0.2)],
    "faster_humans": [float(x) for x in range(1, 9)],
    "more_humans": [float(x) for x in range(2, 8)],
}

#: Strengths for threshold calibration, off the evaluation grids where the grid leaves room (the number of humans
#: is an integer, so `more_humans` is disjoint by its episode seeds only).
CALIBRATION_SET: dict[str, list[float]] = {
    "observation_noise": [0.5, 1.3],
    "heading_noise": [0.5, 1.3],
    "speed_noise": [0.5, 0.9],
    "faster_humans": [2.5, 5.5],
    "more_humans": [4.0, 6.0],
}

#: Episode seeds: evaluation uses seed + k from 0; calibration starts here, so no episode is shared.
CALIBRATION_SEED = 500_000


def perturbation_override(kind: str, strength: float) -> dict[str, Any]:
    """The `perturbation` config mapping of one perturbation type at one strength (unperturbed values are exact)."""
    if kind not in PERTURBATION_FIELDS:
        raise ValueError(f"unknown perturbation {kind!r}; allowed: {', '.join(PERTURBATION_FIELDS)}")
    field = PERTURBATION_FIELDS[kind]
    if kind == "more_humans":
        return {} if strength <= 2 else {field: int(strength)}
    return {field: float(strength)}


def perturbed_config(env: dict[str, Any], kind: str, strength: float) -> EnvConfig:
    """The validated `EnvConfig` of the (partial) env config `env` with one perturbation at one strength.

    :raises socnav.config.ConfigError: the strength puts a field out of its range (the message names it).
    """
    perturbation = {**env.get("perturbation", {}), **perturbation_override(kind, strength)}
    return load_config({**env, "perturbation": perturbation})


def strength_zero(kind: str) -> float:
    """The unperturbed strength of a perturbation type (the sigma(0) of the sensitivity ratio)."""
    return PAPER_GRIDS[kind][0]
