"""Table 3's trade-off curve: prevented collisions vs the measured false activation of each rule calibrated at
several false-activation budgets, with the paper's thresholds as reference points; its table, figure and section.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import save_figure, write_table_atomic
from socnav.paper.labels import ESTIMATOR_ORDER, PAPER_TABLE3_COLUMNS, SENSING_LABELS, estimator_label
from socnav.paper.uncertainty.ablation import ablation_sensing
from socnav.paper.uncertainty.figures import LINESTYLES, MARKERS, pyplot
from socnav.paper.uncertainty.plan import NO_ESTIMATOR
from socnav.paper.uncertainty.records import perturbed_rows, safety_records, with_rule
from socnav.paper.uncertainty.table3 import decimal_text, episode_rates, table3_groups

__all__ = ["TRADEOFF_COLUMNS", "TRADEOFF_LABELS", "plot_tradeoff", "table3_tradeoff_section", "tradeoff_frame"]


TRADEOFF_COLUMNS = ["estimator", "rule", "thresholds", "budget", "false_activation_pct", "activation_pct",
                    "prevented_pct", "prevented_pct_pooled", "prevented_pct_worst", "collisions_none", "collisions",
                    "columns"]
TRADEOFF_LABELS = {(NO_ESTIMATOR, "proximity-only"): "Proximity only", ("mc", "paper"): "MC-dropout-gated",
                   ("ensemble", "paper"): "Ensemble-gated"}


def tradeoff_frame(safety: pd.DataFrame, sensing: str) -> pd.DataFrame:
    """The trade-off curve: per (estimator, rule, budget) of the rules calibrated at several budgets with `sensing`
    (the paper's rule per estimator, proximity-only) and the paper's thresholds as printed (``thresholds`` =
    ``paper``, no budget): the MEASURED false activation (% of unperturbed steps) and the prevented collisions
    of the evaluation episodes -- ``prevented_pct`` the mean over the paper's columns with a plain-policy
    collision (each column pooled over its repeats and strengths), ``_pooled`` over every perturbed episode,
    ``_worst`` the worst column -- and ``prevented_pct_<column>`` per column; only on the repeats that every
    calibrated point played (``Safety.tradeoff_repeats``)."""
    safety = with_rule(safety)
    curve = safety[(safety["sensing"] == sensing) & (safety["variant"] == "calibrated")
                   & (safety["rule"] != "uncertainty-only")]
    # every point on the repeats all of them played (a trade-off budget may be played on the first repeats only)
    played = [set(rows["repeat"]) for _, rows in curve.groupby(["estimator", "rule", "budget"])]
    if played:
        safety = safety[safety["repeat"].isin(set.intersection(*played))]
    mine = safety[(safety["sensing"] == sensing) & (safety["variant"] != "none")]
    groups = {c: k for c, k in table3_groups(safety["perturbation"]).items() if c in PAPER_TABLE3_COLUMNS}
    rows = []
    keyed = mine.assign(budget=mine["budget"].fillna(-1.0))
    for (estimator, rule, variant, budget), frame in keyed.groupby(["estimator", "rule", "variant", "budget"],
                                                                    sort=False):
        if variant == "calibrated" and rule == "uncertainty-only":
            continue
        plain_rows = safety[(safety["estimator"] == estimator) & (safety["variant"] == "none")]
        runs = safety.loc[frame.index]
        hot = perturbed_rows(runs)
        plain_hot = plain_rows[perturbed_rows(plain_rows)]
        per_column = {}
        c_none_all = c_all = 0
        for column, kinds in groups.items():
            plain_hit = plain_hot[plain_hot["perturbation"].isin(kinds)]
            run_hit = runs[hot & runs["perturbation"].isin(kinds).to_numpy()]
            c_none = int((plain_hit["outcome"] == "collision").sum())
            c_var = int((run_hit["outcome"] == "collision").sum())
            c_none_all, c_all = c_none_all + c_none, c_all + c_var
            per_column[column] = 100.0 * (c_none - c_var) / c_none if c_none else math.nan
        defined = [v for v in per_column.values() if math.isfinite(v)]
        cold = episode_rates(runs[~hot], True)
        rows.append({"estimator": estimator, "rule": rule, "thresholds": variant,
                     "budget": math.nan if budget < 0 else float(budget),
                     "false_activation_pct": cold["activation"],
                     "activation_pct": episode_rates(runs[hot], True)["activation"],
                     "prevented_pct": float(np.mean(defined)) if defined else math.nan,
                     "prevented_pct_pooled": 100.0 * (c_none_all - c_all) / c_none_all if c_none_all else math.nan,
                     "prevented_pct_worst": float(np.min(defined)) if defined else math.nan,
                     "collisions_none": c_none_all, "collisions": c_all, "columns": len(defined),
                     **{f"prevented_pct_{column}": value for column, value in per_column.items()}})
    frame = pd.DataFrame(rows)
    if frame.empty:
        return pd.DataFrame(columns=TRADEOFF_COLUMNS)
    # only curves with more than one point, plus the paper's thresholds of those estimators as reference points
    curves = frame[frame["thresholds"] == "calibrated"].groupby(["estimator", "rule"])["budget"].transform("size")
    keep = (frame["thresholds"] == "paper") | (curves.reindex(frame.index).fillna(0) > 1)
    frame = frame[keep]
    extra = [c for c in frame.columns if c not in TRADEOFF_COLUMNS]
    order = frame.assign(_e=frame["estimator"].map({e: i for i, e in enumerate([NO_ESTIMATOR, *ESTIMATOR_ORDER])}))
    return order.sort_values(["_e", "thresholds", "budget"], kind="stable")[TRADEOFF_COLUMNS + extra].reset_index(
        drop=True)


def plot_tradeoff(frame: pd.DataFrame, out_base: Path) -> list[Path]:
    """Prevented collisions (mean over the paper's columns) vs measured false activation, one line per rule over
    its calibration budgets (points labelled with the budget); the paper's thresholds as printed as open markers."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.4, 4.6))
    colours = {NO_ESTIMATOR: "0.25", "mc": "tab:blue", "ensemble": "tab:orange"}
    for (estimator, rule), curve in frame[frame["thresholds"] == "calibrated"].groupby(["estimator", "rule"],
                                                                                        sort=False):
        curve = curve.sort_values("false_activation_pct")
        label = TRADEOFF_LABELS.get((estimator, rule), f"{estimator_label(estimator)}, {rule}")
        axis.plot(curve["false_activation_pct"], curve["prevented_pct"], marker=MARKERS.get(estimator, "s"),
                  linestyle=LINESTYLES.get(estimator, "-."), color=colours.get(estimator), label=label)
        for row in curve.itertuples():
            axis.annotate(f"{100 * row.budget:g} %", (row.false_activation_pct, row.prevented_pct), fontsize=7,
                          textcoords="offset points", xytext=(4, -9), color=colours.get(estimator))
    for row in frame[frame["thresholds"] == "paper"].itertuples():
        axis.plot([row.false_activation_pct], [row.prevented_pct], linestyle="none", marker="D",
                  markerfacecolor="none", color=colours.get(row.estimator),
                  label=f"paper's thresholds as printed, {estimator_label(row.estimator)}")
    axis.set_xlabel("false activation, measured (% of unperturbed steps)")
    axis.set_ylabel("prevented collisions (%, mean of the paper's columns)")
    lowest = float(frame["prevented_pct"].min())  # NaN without any collision to prevent
    axis.set_ylim(bottom=min(0.0, lowest) if math.isfinite(lowest) else 0.0)
    axis.set_xlim(left=0.0)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8, frameon=False)
    figure.tight_layout()
    return save_figure(figure, out_base)


def _tradeoff_markdown(frame: pd.DataFrame) -> str:
    header = ["Rule", "Calibration budget", "False activation (% steps)", "Prevented (%, mean of columns)",
              "Prevented (%, all perturbed pooled)", "Worst column (%)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--"] + ["--:"] * (len(header) - 1)) + "|"]
    for row in frame.to_dict("records"):
        label = (TRADEOFF_LABELS.get((row["estimator"], row["rule"]), row["rule"]) if row["thresholds"] == "calibrated"
                 else f"Paper's thresholds as printed, {estimator_label(row['estimator'])}")
        budget = "–" if not math.isfinite(row["budget"]) else f"{100 * row['budget']:g} %"
        cells = [label, budget, decimal_text(row["false_activation_pct"], 2), decimal_text(row["prevented_pct"], 1),
                 decimal_text(row["prevented_pct_pooled"], 1), decimal_text(row["prevented_pct_worst"], 1)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _tradeoff_protocol(context: ReportContext, frame: pd.DataFrame) -> str:
    """How the curve's points other than the run's budget were calibrated and played (`Safety.tradeoff_*`)."""
    safety = context.experiment.get("safety") or {}
    search, repeats = safety.get("tradeoff_search", "full"), safety.get("tradeoff_repeats")
    text = ("The points other than the run's budget were calibrated like it" if search == "full" else
            "The points other than the run's budget were calibrated by a lighter search (one proxy budget, the c_prox "
            "reading chosen at the run's budget, no refinement stage), every rule alike")
    text += (", and every point is shown on all repeats." if repeats is None else
             f"; every point is shown on the first {repeats} repeat(s), the ones all were played on.")
    return text


def table3_tradeoff_section(context: ReportContext) -> str:
    """The trade-off's section: table3_tradeoff.png/svg/csv (empty without a curve of two or more budgets)."""
    safety = safety_records(context)
    if safety.empty:
        return ""
    safety = with_rule(safety)
    sensing = ablation_sensing(safety, context)
    if sensing is None:  # no rule of the ablation, so no curve
        return ""
    frame = tradeoff_frame(safety, sensing)
    if frame.empty or not (frame["thresholds"] == "calibrated").any():
        return ""
    write_table_atomic(frame, context.out_dir / "table3_tradeoff.csv")
    plot_tradeoff(frame, context.out_dir / "table3_tradeoff")
    return "\n".join([
        "## Table 3 trade-off: prevented collisions vs false activation",
        "",
        "Each rule calibrated at several false-activation budgets (the same calibration episodes; the budget bounds "
        "the calibration's one-sided 95 % upper bound), then played on Table 3's evaluation episodes "
        f"({SENSING_LABELS.get(sensing, sensing)} sensing): the false activation MEASURED there (% of unperturbed "
        "steps) against the prevented collisions (each of the paper's columns pooled over its strengths and "
        "repeats, then their mean). If the uncertainty condition made the hand-over decision better, the gated "
        "rules' curves would lie above the proximity-only curve. " + _tradeoff_protocol(context, frame),
        "",
        "![trade-off](table3_tradeoff.png)",
        "",
        _tradeoff_markdown(frame),
        "",
        "Vector version: [table3_tradeoff.svg](table3_tradeoff.svg); data: [table3_tradeoff.csv](table3_tradeoff.csv) "
        "(also each column's prevented share).",
    ])
