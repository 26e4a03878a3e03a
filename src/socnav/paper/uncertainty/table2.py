"""Table 2 of the paper from the perturbation study: the normalised sensitivity of each uncertainty to each
perturbation type, per estimator, next to the paper's Table II; its report section and the study's metrics.

**Table 2** (normalised sensitivity): ``dU/dsigma = (u(sigma_max) - u(sigma_0)) / (u(sigma_0) (sigma_max -
sigma_0))`` per uncertainty, perturbation and estimator, ``u(sigma)`` the mean over the episodes at strength
``sigma`` of each episode's mean per-step RAW uncertainty; ``sigma_0`` / ``sigma_max`` the smallest / largest
strength in the records. ``u(sigma_0) = 0`` leaves the ratio undefined (shown as ``—``). The claims the paper draws
from it are tested in `socnav.paper.uncertainty.table2_claims`.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from socnav.envs.perturbations import PERTURBATIONS, strength_zero
from socnav.experiments.registry import ReportContext
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.labels import (
    ESTIMATOR_ORDER,
    ESTIMATOR_SHORT,
    MISSING,
    PAPER_COLUMN_LABELS,
    PERTURBATION_ORDER,
    TABLE2_ROWS,
    ZERO,
    estimator_label,
    perturbation_label,
    present_in_order,
)
from socnav.paper.published import PAPER_TABLE2, paper_table2
from socnav.paper.uncertainty.records import (
    RAW_COLUMNS,
    calibrations,
    safety_records,
    study_episode_records,
    study_summaries,
)
from socnav.paper.uncertainty.table2_claims import mc_vs_ensemble_sentence, table2_claims
from socnav.sim.metrics import ALL_METRICS, summarize_groups

__all__ = ["STUDY_METRIC_KEYS", "TABLE2_COLUMNS", "study_metrics_frame", "table2_frame", "table2_markdown",
           "table2_section"]


TABLE2_COLUMNS = ["estimator", "perturbation", "uncertainty", "sigma0", "sigma_max", "episodes_sigma0",
                  "episodes_sigma_max", "u_sigma0", "u_sigma_max", "sensitivity", "note", "paper"]


def table2_frame(episode_means: pd.DataFrame) -> pd.DataFrame:
    """Table 2 in long form: one row per (estimator, perturbation, uncertainty) with u(sigma_0), u(sigma_max) and
    the normalised sensitivity (NaN with ``note`` ``zero baseline`` where u(sigma_0) = 0, ``single strength``
    where only one strength was recorded)."""
    rows = []
    if episode_means.empty:
        return pd.DataFrame(columns=TABLE2_COLUMNS)
    for (estimator, perturbation), group in episode_means.groupby(["estimator", "perturbation"], sort=False):
        strengths = group["strength"].to_numpy(float)
        sigma0, sigma_max = float(strengths.min()), float(strengths.max())
        first, last = group[np.isclose(strengths, sigma0)], group[np.isclose(strengths, sigma_max)]
        for uncertainty in RAW_COLUMNS:
            if uncertainty not in group:
                continue
            u0, u_max = float(first[uncertainty].mean()), float(last[uncertainty].mean())
            note = ""
            if math.isclose(sigma0, sigma_max):
                value, note = math.nan, "single strength"
            elif u0 == 0:
                value, note = math.nan, "zero baseline"
            else:
                value = (u_max - u0) / (u0 * (sigma_max - sigma0))
            rows.append({"estimator": estimator, "perturbation": perturbation, "uncertainty": uncertainty,
                         "sigma0": sigma0, "sigma_max": sigma_max, "episodes_sigma0": len(first),
                         "episodes_sigma_max": len(last), "u_sigma0": u0, "u_sigma_max": u_max,
                         "sensitivity": value, "note": note,
                         "paper": paper_table2(uncertainty, perturbation, estimator)})
    return pd.DataFrame(rows, columns=TABLE2_COLUMNS)


def _sensitivity_text(value: float) -> str:
    if value == 0 or abs(value) >= 0.01:
        return f"{value:.2f}"
    return f"{value:.1e}"


def table2_markdown(table: pd.DataFrame) -> str:
    """Rows: the five uncertainties; a column per perturbation type and estimator. Per (uncertainty, perturbation)
    the larger sensitivity of the estimators is bold (ties all bold; only where two or more are defined);
    ``—``: u(sigma_0) = 0, ``n/a``: not recorded or a single strength."""
    perturbations = present_in_order(table["perturbation"], PERTURBATION_ORDER)
    estimators = present_in_order(table["estimator"], ESTIMATOR_ORDER)
    header = ["Uncertainty"] + [f"{perturbation_label(p)}: {ESTIMATOR_SHORT.get(e, e)}"
                                for p in perturbations for e in estimators]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--"] + ["--:"] * (len(header) - 1)) + "|"]
    indexed = table.set_index(["uncertainty", "perturbation", "estimator"])
    for uncertainty, label in TABLE2_ROWS.items():
        if uncertainty not in set(table["uncertainty"]):
            continue
        row = [label]
        for perturbation in perturbations:
            cells = {}
            for estimator in estimators:
                key = (uncertainty, perturbation, estimator)
                cells[estimator] = indexed.loc[key] if key in indexed.index else None
            defined = [float(c["sensitivity"]) for c in cells.values()
                       if c is not None and math.isfinite(float(c["sensitivity"]))]
            best = max(defined) if len(defined) >= 2 else None
            for estimator in estimators:
                cell = cells[estimator]
                if cell is None or cell["note"] == "single strength":
                    row.append(MISSING)
                elif cell["note"] == "zero baseline":
                    row.append(ZERO)
                else:
                    value = float(cell["sensitivity"])
                    text = _sensitivity_text(value)
                    row.append(f"**{text}**" if best is not None and value == best else text)
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _paper_table2_markdown() -> str:
    columns = list(PAPER_COLUMN_LABELS)
    header = ["Uncertainty"] + [f"{PAPER_COLUMN_LABELS[c]}: {s}" for c in columns for s in ("MC", "Ens")]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--"] + ["--:"] * (len(header) - 1)) + "|"]
    for uncertainty, label in TABLE2_ROWS.items():
        row = [label]
        for column in columns:
            mc, ens = PAPER_TABLE2[uncertainty][column]
            row += [f"**{mc:.2f}**" if mc > ens else f"{mc:.2f}", f"**{ens:.2f}**" if ens > mc else f"{ens:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


#: The groups of table2_metrics.csv.
STUDY_METRIC_KEYS = ["estimator", "perturbation", "strength"]


def study_metrics_frame(context: ReportContext) -> pd.DataFrame:
    """Every registry metric (`socnav.sim.metrics`) of the study's episode records, per (estimator, perturbation,
    strength); empty without episode records."""
    records = study_episode_records(context)
    if records.empty:
        return pd.DataFrame()
    return summarize_groups(records, STUDY_METRIC_KEYS, ALL_METRICS)


def _strength_notes(table: pd.DataFrame) -> list[str]:
    lines = []
    for perturbation in present_in_order(table["perturbation"], PERTURBATION_ORDER):
        rows = table[table["perturbation"] == perturbation]
        parts = []
        for estimator in present_in_order(rows["estimator"], ESTIMATOR_ORDER):
            first = rows[rows["estimator"] == estimator].iloc[0]
            parts.append(f"{estimator_label(estimator)} σ(0) = {first['sigma0']:g} ({first['episodes_sigma0']} "
                         f"episode(s)), σ(max) = {first['sigma_max']:g} ({first['episodes_sigma_max']} episode(s))")
            if perturbation in PERTURBATIONS and not math.isclose(first["sigma0"], strength_zero(perturbation)):
                parts[-1] += f" — note: the unperturbed strength {strength_zero(perturbation):g} was not recorded"
        line = f"- {perturbation_label(perturbation)}: " + "; ".join(parts)
        sigma_max = float(rows["sigma_max"].max())
        if perturbation == "speed_noise" and sigma_max > 1:
            # the speed factor U(1 - s, 1) cannot go below 0: every s > 1 is applied as s = 1
            line += (f" — note: s > 1 acts as s = 1, so ΔU/Δσ divides by σ(max) − σ(0) = "
                     f"{sigma_max - float(rows['sigma0'].min()):g} while the applied strength changed by "
                     f"{1 - float(rows['sigma0'].min()):g}")
        lines.append(line)
    return [*lines, ""] if lines else []


def table2_section(context: ReportContext) -> str:
    """Table 2's section: table2.md/csv, table2_metrics.csv and the paper's Table II (a note when the run has no records
    at all)."""
    episode_means, _ = study_summaries(context)
    if episode_means.empty:
        if safety_records(context).empty and not calibrations(context):
            return "## Perturbation study and safety layer\n\nNo study, safety or calibration records yet."
        return ""
    table = table2_frame(episode_means)
    write_table_atomic(table, context.out_dir / "table2.csv")
    markdown = table2_markdown(table)
    write_text_atomic(context.out_dir / "table2.md", markdown + "\n")
    lines = [
        "## Table 2: normalised sensitivity of the uncertainties to perturbations",
        "",
        "ΔU/Δσ = (u_σ(max) − u_σ(0)) / (u_σ(0) · (σ(max) − σ(0))), u_σ the mean over the episodes at strength σ of "
        "each episode's mean per-step (raw) uncertainty. Bold: the larger point value of MC-dropout (MC) and "
        "ensemble (Ens) per uncertainty and perturbation, whether or not the difference is resolved (see the claims "
        f"below for intervals). {ZERO}: u_σ(0) = 0, the ratio is undefined (the estimator reports no "
        f"uncertainty of that kind in the least perturbed world); {MISSING}: not recorded, or a single strength.",
        "",
        markdown,
        "",
    ]
    lines += _strength_notes(table)
    compared = mc_vs_ensemble_sentence(table2_claims(context)[0])
    if compared:
        lines += [compared, ""]
    lines += [
        "The paper's Table II for comparison (its *action noise* is our heading and speed noise, *velocity* our "
        "faster humans, *new humans* our more humans; bold: larger of the two):",
        "",
        _paper_table2_markdown(),
        "",
        "Data: [table2.csv](table2.csv) (also u_σ(0), u_σ(max), episode counts and the paper's value per cell).",
    ]
    metrics = study_metrics_frame(context)
    if not metrics.empty:
        write_table_atomic(metrics, context.out_dir / "table2_metrics.csv")
        lines.append("Every metric of docs/metrics.md of the study's episodes per estimator, perturbation and "
                     "strength: [table2_metrics.csv](table2_metrics.csv).")
    return "\n".join(lines)
