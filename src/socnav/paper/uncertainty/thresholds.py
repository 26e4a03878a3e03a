"""The calibrated safety thresholds next to the paper's: the report section listing what `socnav calibrate` chose
per estimator, rule, sensing and budget, with their scores in the calibration rollouts.
"""

from __future__ import annotations

import math
from typing import Any

import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import write_table_atomic
from socnav.paper.labels import ESTIMATOR_ORDER, SENSING_LABELS, SENSING_ORDER, estimator_label, present_in_order
from socnav.paper.uncertainty.plan import NO_ESTIMATOR
from socnav.paper.uncertainty.records import calibrations
from socnav.safety.rule import THRESHOLD_PRESETS

__all__ = ["RULE_LABELS", "calibration_section"]


#: How the calibration table names each rule variant's calibrated thresholds.
RULE_LABELS = {"paper": "calibrated", "proximity-only": "calibrated, proximity only",
               "uncertainty-only": "calibrated, uncertainty only"}


def _number_text(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return "–" if value is None else str(value)
    if isinstance(value, (int, float)):
        return "∞" if value == math.inf else f"{value:.4g}"
    return str(value)


def calibration_section(context: ReportContext) -> str:
    """The thresholds' section: calibration.csv and its table, the paper's thresholds after each estimator's calibrated
    ones."""
    from socnav.safety.calibration import SEARCHED_KEYS

    found = calibrations(context)
    if not found:
        return ""
    keys = ["lambda_ep", "lambda_feat", "lambda_prox", "beta1"]
    rows = []
    for estimator in present_in_order((key[0] for key in found), [NO_ESTIMATOR, *ESTIMATOR_ORDER]):
        mine = [key for key in found if key[0] == estimator]
        for rule in present_in_order((key[2] for key in mine), list(RULE_LABELS)):
            for sensing in present_in_order((key[1] for key in mine if key[2] == rule), SENSING_ORDER):
                budgets = sorted((key[3] for key in mine if key[1:3] == (sensing, rule)),
                                 key=lambda b: (not math.isnan(b), b))  # the main budget first
                for budget in budgets:
                    data = found[(estimator, sensing, rule, budget)]
                    recorded = data.get("thresholds")
                    thresholds = dict(recorded) if isinstance(recorded, dict) else {}
                    for key in ("lambda_ep", "lambda_feat"):  # JSON has no infinity: null is a condition that is off
                        if key in thresholds and thresholds[key] is None:
                            thresholds[key] = math.inf
                    # a rule variant ignores the parameters of the condition it removed (not shown); a rule that
                    # never fires (no candidate within the budget) is the paper's rule with infinite thresholds
                    used = SEARCHED_KEYS.get(thresholds.get("conditions", "paper"), keys)
                    source = RULE_LABELS.get(rule, rule)
                    if sensing != "perceived":
                        source += f" ({SENSING_LABELS.get(sensing, sensing)})"
                    if not math.isnan(budget):
                        source += f", {100 * budget:g} % budget" + (", light search" if data.get("search") == "light"
                                                                    else "")
                    rows.append({"estimator": estimator, "source": source, "sensing": sensing, "rule": rule,
                                 "budget": data.get("false_activation_budget"),
                                 **{k: thresholds.get(k) if k in used else None for k in keys},
                                 # no c_prox, no reading of it
                                 "proximity": (thresholds.get("proximity") if "lambda_prox" in used else "–"),
                                 # thresholds without a hold: the paper's per-step rule
                                 "hold_steps": thresholds.get("hold_steps", 0) if thresholds else None,
                                 "prevented_fraction": data.get("prevented_fraction"),
                                 "false_activation_rate": data.get("false_activation_rate")})
        if estimator in THRESHOLD_PRESETS:
            rows.append({"estimator": estimator, "source": "paper", "sensing": None, "rule": "paper", "budget": None,
                         **dict(zip(keys, THRESHOLD_PRESETS[estimator], strict=True)), "proximity": None,
                         "hold_steps": 0,
                         "prevented_fraction": None, "false_activation_rate": None})
    table = pd.DataFrame(rows)
    write_table_atomic(table, context.out_dir / "calibration.csv")
    lines = [
        "## Calibrated safety thresholds",
        "",
        "Thresholds chosen by `socnav calibrate` (on strengths and seeds disjoint from the evaluation) next to the "
        "paper's, with their scores in the calibration rollouts: the share of the plain policy's collisions the "
        "safety layer prevented and the share of unperturbed steps where it fired (Table 3, on held-out seeds and "
        "strengths, is the real test).",
        "",
        "Hold: steps the fallback keeps control after the rule last fired (0: the paper's per-step rule). Rules "
        "of the ablation (proximity only, uncertainty only) ignore the parameters of the condition they drop "
        "('–'); a budget named in the label is one of the trade-off curve's (the others: the run's budget).",
        "",
        "| Approach | Thresholds | λ_ep | λ_f | λ_prox | β1 | c_prox | Hold | Calibration prevented "
        "| Calibration false activation |",
        "|:--|:--|--:|--:|--:|--:|:--|--:|--:|--:|",
    ]
    for row in rows:
        approach = "–" if row["estimator"] == NO_ESTIMATOR else estimator_label(row["estimator"])
        lines.append("| " + " | ".join([approach, row["source"]]
                                       + [_number_text(row[k]) for k in keys]
                                       + [row["proximity"] or "abs-relative-speed", _number_text(row["hold_steps"])]
                                       + [_number_text(row["prevented_fraction"]),
                                          _number_text(row["false_activation_rate"])]) + " |")
    lines += ["", "Data: [calibration.csv](calibration.csv)."]
    return "\n".join(lines)
