"""How the reports name and order what they show: algorithms, scenarios, estimators, perturbation types and the
columns they fall into, uncertainties, safety variants; and the ordering helpers every report section sorts with.

Perturbation types, their order and labels come from the registry (`socnav.envs.perturbations.PERTURBATIONS`); the
paper's column of each type follows its Tables II-III (its *action noise* is our heading and speed noise pooled, its
*velocity* our faster humans, its *new humans* our more humans).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import pandas as pd

from socnav.envs.perturbations import PERTURBATIONS

__all__ = [
    "ALGO_LABELS",
    "BEYOND_PAPER",
    "CURVE_UNCERTAINTIES",
    "ESTIMATOR_LABELS",
    "ESTIMATOR_ORDER",
    "ESTIMATOR_SHORT",
    "MEASURE_LABELS",
    "MISSING",
    "OWN_TABLE3_COLUMNS",
    "PAPER_COLUMN",
    "PAPER_COLUMN_LABELS",
    "PAPER_TABLE3_COLUMNS",
    "PERTURBATION_LABELS",
    "PERTURBATION_ORDER",
    "POOLED",
    "POOLED_LABELS",
    "SCENARIO_LABELS",
    "SENSING_LABELS",
    "SENSING_ORDER",
    "STRENGTH_LABELS",
    "TABLE2_ROWS",
    "TABLE3_COLUMN_LABELS",
    "UNCERTAINTY_LABELS",
    "VARIANT_LABELS",
    "ZERO",
    "algo_label",
    "estimator_label",
    "order_rank",
    "perturbation_label",
    "preferred_then_seen",
    "present_in_order",
    "scenario_label",
    "variant_label",
]

# --------------------------------------------------------------------------------------------------------------
# Table 1: algorithms and scenarios
# --------------------------------------------------------------------------------------------------------------

ALGO_LABELS = {"ppo": "PPO", "ppo-drop": "PPO-Drop", "odv-ppo-noloss": "ODV-PPO no Loss", "odv-ppo": "ODV-PPO",
               "odv-ppo-drop": "ODV-PPO-Drop"}
SCENARIO_LABELS = {"circle_interaction": "Circle Interaction", "circle_crossing": "Circle Crossing",
                   "random": "Random", "position_swap": "Position Swap"}


def algo_label(name: str) -> str:
    """The paper's name of an algorithm (``odv-ppo-drop`` -> ``ODV-PPO-Drop``), the name itself if unknown."""
    return ALGO_LABELS.get(name, name)


def scenario_label(name: str) -> str:
    """The paper's name of a scenario (``circle_crossing`` -> ``Circle Crossing``), else the name in title case."""
    return SCENARIO_LABELS.get(name, name.replace("_", " ").title())


# --------------------------------------------------------------------------------------------------------------
# The uncertainty study and the safety layer: estimators, perturbations, uncertainties, variants
# --------------------------------------------------------------------------------------------------------------

ESTIMATOR_LABELS = {"mc": "MC-dropout", "ensemble": "Ensemble"}
ESTIMATOR_SHORT = {"mc": "MC", "ensemble": "Ens"}
ESTIMATOR_ORDER = ["mc", "ensemble"]
PERTURBATION_ORDER = list(PERTURBATIONS)
#: Report columns that pool perturbation types (`Perturbation.pooled`) -> their label.
POOLED_LABELS = {"action_noise": "Action noise (heading + speed)"}
#: Pooled column -> the perturbation types it pools, in registry order.
POOLED: dict[str, list[str]] = {
    pool: [name for name, p in PERTURBATIONS.items() if p.pooled == pool]
    for pool in dict.fromkeys(p.pooled for p in PERTURBATIONS.values() if p.pooled is not None)
}
PERTURBATION_LABELS = {**{name: p.label for name, p in PERTURBATIONS.items()}, **POOLED_LABELS}
STRENGTH_LABELS = {name: p.strength_label for name, p in PERTURBATIONS.items()}
#: Perturbation types beyond the paper (labelled "(ours)"): the paper's Table 2 claims do not cover them.
BEYOND_PAPER = [name for name, p in PERTURBATIONS.items() if p.ours]
VARIANT_LABELS = {"none": "none (plain policy)", "paper": "paper thresholds", "calibrated": "calibrated thresholds"}
SENSING_ORDER = ["perceived", "true"]
SENSING_LABELS = {"perceived": "perceived", "true": "true state"}

#: Raw uncertainty columns of the study's step records -> what they measure.
UNCERTAINTY_LABELS = {"u_ep_heading": "epistemic heading", "u_ep_speed": "epistemic speed",
                      "u_al_heading": "aleatoric heading", "u_al_speed": "aleatoric speed", "u_feat": "feature"}
#: Raw and windowed (the mean of the last w steps, "w_" prefix) uncertainty columns -> label.
MEASURE_LABELS = {**UNCERTAINTY_LABELS,
                  **{f"w_{name}": f"windowed {label}" for name, label in UNCERTAINTY_LABELS.items()}}
#: Fig. 5 curves: uncertainty column -> label.
CURVE_UNCERTAINTIES = {name: UNCERTAINTY_LABELS[name]
                       for name in ("u_ep_heading", "u_ep_speed", "u_al_heading", "u_al_speed")}
#: Table 2 rows, in the paper's order: raw uncertainty column -> label.
TABLE2_ROWS = {"u_feat": "Predictive feature", "u_al_heading": "Aleatoric heading", "u_al_speed": "Aleatoric speed",
               "u_ep_heading": "Epistemic heading", "u_ep_speed": "Epistemic speed"}

#: Our perturbation type (or pooled column) -> the paper's column; types beyond the paper have none.
PAPER_COLUMN = {name: p.paper_column for name, p in PERTURBATIONS.items() if not p.ours}
PAPER_COLUMN.update({pool: PERTURBATIONS[kinds[0]].paper_column for pool, kinds in POOLED.items()})
PAPER_COLUMN_LABELS = {"obs": "Observation noise", "action": "Action noise", "velocity": "Velocity",
                       "humans": "New humans"}
#: The paper's Table III columns, in its order: observation noise, action noise (our heading and speed noise
#: pooled: the paper perturbs the action), velocity (our faster humans), new humans (our more humans).
PAPER_TABLE3_COLUMNS = list(dict.fromkeys(p.pooled or name for name, p in PERTURBATIONS.items() if not p.ours))
#: Our columns that the paper has no column for: heading and speed noise alone (it reports them only pooled, as
#: action noise) and the perturbations beyond the paper (the behaviour shift).
OWN_TABLE3_COLUMNS = [name for name, p in PERTURBATIONS.items() if p.ours or p.pooled is not None]
TABLE3_COLUMN_LABELS = {**{name: p.table3_label for name, p in PERTURBATIONS.items()}, **POOLED_LABELS}

ZERO = "—"      # undefined ratio: zero denominator
MISSING = "n/a"  # no records for this cell


def estimator_label(name: str) -> str:
    """``MC-dropout`` / ``Ensemble``, the name itself if unknown."""
    return ESTIMATOR_LABELS.get(name, name)


def perturbation_label(name: str) -> str:
    """The registry's label of a perturbation type or pooled column, else the name capitalised."""
    return PERTURBATION_LABELS.get(name, name.replace("_", " ").capitalize())


def variant_label(variant: str, sensing: str, show_sensing: bool) -> str:
    """``paper thresholds`` etc., with the sensing appended (``, true state``) when `show_sensing`."""
    label = VARIANT_LABELS.get(variant, variant)
    return f"{label}, {SENSING_LABELS.get(sensing, sensing)}" if show_sensing and variant != "none" else label


# --------------------------------------------------------------------------------------------------------------
# Ordering
# --------------------------------------------------------------------------------------------------------------

def present_in_order(values: Iterable[Any], preferred: Sequence[Any]) -> list[Any]:
    """The values present, those in `preferred` first (in its order), then the others in order of appearance."""
    present = list(dict.fromkeys(values))
    return [v for v in preferred if v in present] + [v for v in present if v not in preferred]


def preferred_then_seen(values: Iterable[Any], preferred: Sequence[Any]) -> list[Any]:
    """All of `preferred` (planned rows without results show as missing), then any other values seen."""
    return list(dict.fromkeys([*preferred, *values]))


def order_rank(values: pd.Series, preferred: Sequence[Any]) -> pd.Series:
    """Each value's position in :func:`present_in_order` of `values`: a sort key putting `preferred` first."""
    return values.map({value: i for i, value in enumerate(present_in_order(values, preferred))})
