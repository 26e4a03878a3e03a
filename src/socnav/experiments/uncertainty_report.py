"""Report sections of the perturbation study and of the safety layer (experiment kind ``uncertainty``): the paper's
Table 2 and Figs. 5-6 from the study records, Table 3 and the cost of the safety layer from the safety records.

Records read (Parquet, found by globbing the run directory; files inside a planned unit that is not finished are
left out, as the report header says):

- ``study/<estimator>/<perturbation>/steps.parquet``: one row per environment step (raw ``u_*`` and windowed
  ``w_u_*`` uncertainties, ``nearest_gap``, ``outcome`` on an episode's last step), keyed by ``strength`` and
  ``episode`` (episode ids restart at every strength);
- ``safety/<estimator>/<perturbation>/episodes.parquet``: one row per episode, keyed by ``strength``, ``repeat``
  (an independent block of episode seeds), ``variant`` (``none`` = plain policy, ``paper`` / ``calibrated`` =
  the safety layer with those thresholds; every variant plays the same episode seeds as ``none``) and
  ``sensing`` (``perceived`` / ``true``: what the layer's proximity terms and fallback read; empty for ``none``;
  records without the column were written before the choice existed and read as ``perceived``); with the
  ablation also ``rule`` (``Thresholds.conditions`` of the rule played; records without it: ``paper``),
  ``budget`` (the false-activation budget a calibrated rule was chosen for; NaN for the paper's thresholds) and
  the per-episode ``proximity_steps``, ``vetoed_steps`` and ``fallback_digest`` (`socnav.safety.FallbackCounter`);
  ``safety/none/<perturbation>/`` holds the proximity-only rule, which reads no uncertainty (``estimator``
  ``none``);
- ``calibrate/<estimator>/calibration.json`` (``calibrate-true/<estimator>/`` for ``true`` sensing,
  ``.../<estimator>-uncertainty-only/`` and ``.../proximity-only/`` for the ablation, ``calibration-budget<b>.json``
  for a trade-off budget): the thresholds ``socnav calibrate`` chose and their scores.

Each section writes nothing and returns an empty string when its records are absent (a Table 2 run has no safety
records, a Table 3 run may have no study records).

Definitions:

- **Table 2** (normalised sensitivity): ``dU/dsigma = (u(sigma_max) - u(sigma_0)) / (u(sigma_0) (sigma_max -
  sigma_0))`` per uncertainty, perturbation and estimator, ``u(sigma)`` the mean over the episodes at strength
  ``sigma`` of each episode's mean per-step RAW uncertainty; ``sigma_0`` / ``sigma_max`` the smallest / largest
  strength in the records. ``u(sigma_0) = 0`` leaves the ratio undefined (shown as ``—``).
- **Fig. 5** (``uncertainty_vs_strength``): ``u(sigma) / u(sigma_0)`` of the epistemic and aleatoric heading and
  speed uncertainty vs strength, with the collision rate per strength.
- **Fig. 6** (``feature_uncertainty_collisions``): windowed feature uncertainty ``w_u_feat`` on the row of a
  collision episode's last step (the observation one step before the collision) vs on the row of the closest
  approach (minimum ``nearest_gap``) of the other episodes, all strengths pooled.
- **Table 3** (prevented collisions): per repeat, ``100 (C_none - C_variant) / C_none`` with ``C`` the collisions
  over every PERTURBED strength (``strength != sigma_0``, the unperturbed strength of the perturbation type) of
  that type; mean +- std (ddof=0) over the repeats where ``C_none > 0``. The paper's columns, each compared once
  with the paper's value: observation noise, action noise (heading and speed noise pooled), velocity (faster
  humans), new humans (more humans); heading and speed noise alone in a separate table, as ours. Only the paper's
  rule at the run's budget (:func:`main_records`).
- **Ablation** (``table3_ablation``): the paper's rule with the paper's thresholds, proximity-only,
  uncertainty-only and the paper's rule calibrated, each row against proximity-only paired by episode seed: the
  discordant episodes give the difference in prevented collisions with an exact conditional interval
  (:func:`mcnemar_exact`, Bonferroni over the rows compared); the hand-overs the uncertainty condition vetoed and
  the episodes whose hand-overs differ from proximity-only's.
- **Trade-off** (``table3_tradeoff``): prevented collisions vs the measured false activation of each rule
  calibrated at several budgets.
- **Cost**: fallback activation rate (fallback steps / steps) in perturbed episodes, false-activation rate (the
  same in unperturbed episodes), success and collision rates, mean time to goal of successful episodes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from socnav.envs.perturbations import CALIBRATION_SEED, CALIBRATION_SET, PERTURBATIONS, strength_zero
from socnav.experiments.registry import ReportContext, register_section, unit_dir
from socnav.experiments.spec import NO_ESTIMATOR
from socnav.experiments.statistics import Interval
from socnav.io import (
    UntrustedInputError,
    read_json,
    read_table,
    save_figure,
    write_table_atomic,
    write_text_atomic,
)
from socnav.sim.metrics import ALL_METRICS, METRIC_RECORD_COLUMNS, summarize_episodes, summarize_groups

__all__ = [
    "KIND", "ablation_markdown", "ablation_records", "cost_frame", "cost_markdown", "decisions_frame",
    "main_records", "mcnemar_exact", "paired_frame", "plot_feature_collisions", "plot_tradeoff",
    "plot_uncertainty_vs_strength", "prevented_frame", "prevented_markdown", "safety_metrics_frame",
    "safety_records", "strength_curves", "study_metrics_frame", "study_summaries", "summarise_steps", "table2_frame",
    "table2_markdown", "tradeoff_frame",
]

KIND = "uncertainty"

ESTIMATOR_LABELS = {"mc": "MC-dropout", "ensemble": "Ensemble"}
ESTIMATOR_SHORT = {"mc": "MC", "ensemble": "Ens"}
ESTIMATOR_ORDER = ["mc", "ensemble"]
# Perturbation types, their order, labels and columns: the registry (socnav.envs.perturbations.PERTURBATIONS).
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

#: Table 2 rows: raw uncertainty column -> label.
TABLE2_ROWS = {"u_feat": "Predictive feature", "u_al_heading": "Aleatoric heading", "u_al_speed": "Aleatoric speed",
               "u_ep_heading": "Epistemic heading", "u_ep_speed": "Epistemic speed"}
RAW_COLUMNS = list(TABLE2_ROWS)
#: Fig. 5 curves: uncertainty column -> label.
CURVE_UNCERTAINTIES = {"u_ep_heading": "epistemic heading", "u_ep_speed": "epistemic speed",
                       "u_al_heading": "aleatoric heading", "u_al_speed": "aleatoric speed"}
STEP_COLUMNS = ["estimator", "perturbation", "strength", "episode", "step", *RAW_COLUMNS, "w_u_feat", "nearest_gap",
                "outcome"]
SAFETY_COLUMNS = ["estimator", "perturbation", "strength", "repeat", "variant", "sensing", "seed", "outcome",
                  "length", "time_to_goal", "duration", "fallback_steps",
                  # with the ablation (socnav.experiments.uncertainty_units.ABLATION_COLUMNS)
                  "rule", "budget", "proximity_steps", "vetoed_steps", "fallback_digest",
                  # every metric's record columns (socnav.sim.metrics; records written before them lack them)
                  "return", "path_length", "min_gap", "intrusion_events", "disturbance", *METRIC_RECORD_COLUMNS]
#: The study's per-episode record columns the metrics read (table2_metrics.csv).
STUDY_EPISODE_COLUMNS = ["estimator", "perturbation", "strength", "episode", "outcome", "return", "length",
                         "duration", "time_to_goal", "path_length", "min_gap", "intrusion_steps", "intrusion_events",
                         "disturbance", *METRIC_RECORD_COLUMNS]
#: The groups of table2_metrics.csv and table3_metrics.csv.
STUDY_METRIC_KEYS = ["estimator", "perturbation", "strength"]
SAFETY_METRIC_KEYS = ["estimator", "variant", "sensing", "perturbed"]
SENSING_ORDER = ["perceived", "true"]
SENSING_LABELS = {"perceived": "perceived", "true": "true state"}

ZERO = "—"      # undefined ratio: zero denominator
MISSING = "n/a"  # no records for this cell

# The paper's Table II: uncertainty -> paper column -> (MC-dropout, ensemble).
_PAPER_TABLE2 = {
    "u_feat": {"obs": (1.84, 0.11), "action": (0.87, 0.03), "velocity": (0.20, 0.0), "humans": (0.65, 0.38)},
    "u_al_heading": {"obs": (0.57, 0.28), "action": (0.22, 0.26), "velocity": (0.04, 0.0), "humans": (0.90, 0.47)},
    "u_ep_heading": {"obs": (2.00, 0.18), "action": (0.67, 0.16), "velocity": (0.25, 0.0), "humans": (1.99, 0.82)},
    "u_al_speed": {"obs": (0.71, 0.19), "action": (0.31, 0.18), "velocity": (0.03, 0.0), "humans": (0.49, 0.17)},
    "u_ep_speed": {"obs": (4.08, 0.49), "action": (1.46, 0.64), "velocity": (0.39, 0.02), "humans": (3.01, 0.30)},
}
#: The paper's Table III: paper column -> estimator -> (mean, std) of prevented collisions (%).
_PAPER_TABLE3 = {"obs": {"mc": (100.0, 0.0), "ensemble": (79.0, 11.0)},
                 "action": {"mc": (6.0, 5.0), "ensemble": (0.0, 0.0)},
                 "velocity": {"mc": (56.0, 2.0), "ensemble": (16.0, 1.0)},
                 "humans": {"mc": (81.0, 8.0), "ensemble": (59.0, 13.0)}}
#: Our perturbation type (or pooled column) -> the paper's column ("action noise" is heading and speed noise,
#: "velocity" faster humans); types beyond the paper have none.
PAPER_COLUMN = {name: p.paper_column for name, p in PERTURBATIONS.items() if not p.ours}
PAPER_COLUMN.update({pool: PERTURBATIONS[kinds[0]].paper_column for pool, kinds in POOLED.items()})
PAPER_COLUMN_LABELS = {"obs": "Observation noise", "action": "Action noise", "velocity": "Velocity",
                       "humans": "New humans"}
#: Paper thresholds (lambda_ep, lambda_feat, lambda_prox, beta1), as in socnav.safety.rule.THRESHOLD_PRESETS.
_PAPER_THRESHOLDS = {"mc": (0.03, 0.3, 0.9, 0.5), "ensemble": (0.08, 0.0033, 0.9, 0.5)}


def estimator_label(name: str) -> str:
    return ESTIMATOR_LABELS.get(name, name)


def perturbation_label(name: str) -> str:
    return PERTURBATION_LABELS.get(name, name.replace("_", " ").capitalize())


def _ordered(values: Iterable[Any], preferred: Sequence[Any]) -> list[Any]:
    """The values present, those in `preferred` first (in its order), then the others in order of appearance."""
    present = list(dict.fromkeys(values))
    return [v for v in preferred if v in present] + [v for v in present if v not in preferred]


def paper_table2(uncertainty: str, perturbation: str, estimator: str) -> float:
    """The paper's Table II value for our (uncertainty, perturbation type, estimator), NaN where it has none."""
    column = PAPER_COLUMN.get(perturbation)
    index = {"mc": 0, "ensemble": 1}.get(estimator)
    if column is None or index is None or uncertainty not in _PAPER_TABLE2:
        return math.nan
    return _PAPER_TABLE2[uncertainty][column][index]


def paper_table3(column: str, estimator: str) -> tuple[float, float]:
    """The paper's Table III (mean, std) for our column (perturbation type or action_noise), NaN where none."""
    entry = _PAPER_TABLE3.get(PAPER_COLUMN.get(column, ""), {}).get(estimator)
    return entry if entry is not None else (math.nan, math.nan)


# --------------------------------------------------------------------------------------------------------------
# Reading the records
# --------------------------------------------------------------------------------------------------------------

def _record_files(context: ReportContext, pattern: str) -> list[Path]:
    """Files matching `pattern` under the run directory, without those inside a planned unit not (yet) done."""
    root = context.results_dir
    unfinished = [unit_dir(root, unit).resolve() for unit in context.missing()]
    files = []
    for path in sorted(root.glob(pattern)):
        resolved = path.resolve()
        if any(directory in resolved.parents for directory in unfinished):
            continue
        files.append(path)
    return files


def _read_columns(path: Path, wanted: Sequence[str]) -> pd.DataFrame:
    """The `wanted` columns the file has (all of a CSV), with estimator / perturbation taken from the path
    (``<kind>/<estimator>/<perturbation>/<file>``) when the records lack them."""
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        names = set(pq.read_schema(path).names)
        frame = pd.read_parquet(path, columns=[c for c in wanted if c in names])
    else:
        frame = read_table(path)
    if "estimator" not in frame:
        frame.insert(0, "estimator", path.parent.parent.name)
    if "perturbation" not in frame:
        frame.insert(1, "perturbation", path.parent.name)
    return frame


def summarise_steps(steps: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per-step records (one or more estimator / perturbation / strength) -> ``(episode_means, critical)``.

    ``episode_means``: one row per (estimator, perturbation, strength, episode) with the episode's mean of every
    raw uncertainty column and its number of steps; ``critical``: one row per episode with ``collided`` and
    ``value`` = ``w_u_feat`` at the step before the collision / at the closest approach
    (`socnav.uncertainty.recording.critical_steps`, applied per strength since episode ids restart there).
    """
    from socnav.uncertainty.recording import critical_steps

    keys = ["estimator", "perturbation", "strength"]
    raw = [c for c in RAW_COLUMNS if c in steps]
    steps = steps.sort_values(keys + ["episode", "step"], kind="stable", ignore_index=True)
    grouped = steps.groupby(keys + ["episode"], sort=True)
    means = grouped[raw].mean()
    means["steps"] = grouped.size()
    episode_means = means.reset_index()
    critical = []
    if "w_u_feat" in steps and "nearest_gap" in steps:
        for key, group in steps.groupby(keys, sort=True):
            group = group.reset_index(drop=True)
            group["nearest_gap"] = group["nearest_gap"].astype(float).fillna(np.inf)
            rows = critical_steps(group, column="w_u_feat")
            critical.append(rows.assign(**dict(zip(keys, key)))[keys + ["episode", "collided", "value"]])
    columns = keys + ["episode", "collided", "value"]
    critical_frame = pd.concat(critical, ignore_index=True) if critical else pd.DataFrame(columns=columns)
    return episode_means, critical_frame


def study_summaries(context: ReportContext) -> tuple[pd.DataFrame, pd.DataFrame]:
    """`summarise_steps` of every study file (read one at a time, so only the summaries are held), cached."""
    if "uncertainty_study" not in context._cache:
        means, critical = [], []
        for path in _record_files(context, "study/*/*/steps.parquet"):
            steps = _read_columns(path, STEP_COLUMNS)
            if steps.empty:
                continue
            episode_means, rows = summarise_steps(steps)
            means.append(episode_means)
            critical.append(rows)
        context._cache["uncertainty_study"] = (
            pd.concat(means, ignore_index=True) if means else pd.DataFrame(),
            pd.concat(critical, ignore_index=True) if critical else pd.DataFrame(),
        )
    return context._cache["uncertainty_study"]


def safety_records(context: ReportContext) -> pd.DataFrame:
    """Every safety episode record (estimator, perturbation, strength, repeat, variant, outcome, ...), cached."""
    if "uncertainty_safety" not in context._cache:
        frames = [_read_columns(path, SAFETY_COLUMNS)
                  for path in _record_files(context, "safety/*/*/episodes.parquet")]
        frames = [frame for frame in frames if not frame.empty]
        context._cache["uncertainty_safety"] = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    return context._cache["uncertainty_safety"]


def _sigma_zero(perturbation: str, strengths: Iterable[float]) -> float:
    """The unperturbed strength of a registered perturbation type, or the smallest strength of an unknown type."""
    if perturbation in PERTURBATIONS:
        return strength_zero(perturbation)
    return float(min(strengths))


def _perturbed(frame: pd.DataFrame) -> np.ndarray:
    """Rows whose strength is not the unperturbed strength of their perturbation type."""
    mask = np.ones(len(frame), dtype=bool)
    for perturbation, index in frame.groupby("perturbation", sort=False).indices.items():
        strengths = frame["strength"].to_numpy(float)[index]
        mask[index] = ~np.isclose(strengths, _sigma_zero(perturbation, strengths))
    return mask


# --------------------------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------------------------

def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(n_panels: int, columns: int = 3, width: float = 4.4, height: float = 3.4) -> tuple[Any, list[Any]]:
    plt = _pyplot()
    ncols = max(1, min(n_panels, columns))
    nrows = max(1, math.ceil(n_panels / ncols))
    figure, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, height * nrows), squeeze=False)
    flat = list(axes.ravel())
    for axis in flat[n_panels:]:
        axis.set_visible(False)
    return figure, flat[:n_panels]


LINESTYLES = {"mc": "-", "ensemble": "--"}
MARKERS = {"mc": "o", "ensemble": "x"}


# --------------------------------------------------------------------------------------------------------------
# Table 2
# --------------------------------------------------------------------------------------------------------------

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
    perturbations = _ordered(table["perturbation"], PERTURBATION_ORDER)
    estimators = _ordered(table["estimator"], ESTIMATOR_ORDER)
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
            mc, ens = _PAPER_TABLE2[uncertainty][column]
            row += [f"**{mc:.2f}**" if mc > ens else f"{mc:.2f}", f"**{ens:.2f}**" if ens > mc else f"{ens:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


@register_section(KIND, "table2")
def table2_section(context: ReportContext) -> str:
    episode_means, _ = study_summaries(context)
    if episode_means.empty:
        if safety_records(context).empty and not _calibrations(context):
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
    compared = _mc_vs_ensemble(_table2_claims(context)[0])
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


def study_metrics_frame(context: ReportContext) -> pd.DataFrame:
    """Every registry metric (`socnav.sim.metrics`) of the study's episode records, per (estimator, perturbation,
    strength); empty without episode records."""
    frames = [_read_columns(path, STUDY_EPISODE_COLUMNS)
              for path in _record_files(context, "study/*/*/episodes.parquet")]
    frames = [frame for frame in frames if not frame.empty]
    if not frames:
        return pd.DataFrame()
    return summarize_groups(pd.concat(frames, ignore_index=True), STUDY_METRIC_KEYS, ALL_METRICS)


def _strength_notes(table: pd.DataFrame) -> list[str]:
    lines = []
    for perturbation in _ordered(table["perturbation"], PERTURBATION_ORDER):
        rows = table[table["perturbation"] == perturbation]
        parts = []
        for estimator in _ordered(rows["estimator"], ESTIMATOR_ORDER):
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
    return lines + [""] if lines else []


def _mc_vs_ensemble(claims: pd.DataFrame) -> str:
    """One sentence: in how many cells MC-dropout's |ΔU/Δσ| is larger than the ensemble's with an interval
    excluding 0, in how many we cannot tell and in how many the ensemble's is larger (the paper: MC larger in 19 of
    its 20 cells, point values)."""
    from socnav.experiments.statistics import CANNOT_TELL, DOES_NOT_HOLD, HOLDS

    cells = claims[claims["claim"] == CLAIM_MC_STRONGER] if not claims.empty else claims
    if cells.empty:
        return ""
    count = cells["verdict"].value_counts()
    return (f"MC-dropout vs ensemble, |ΔU/Δσ| of MC − |ΔU/Δσ| of the ensemble per cell with a bootstrap interval "
            f"over paired episodes ({cells['confidence'].iloc[0]:.1%} per cell, Bonferroni over {len(cells)} "
            f"cells): MC-dropout larger in {count.get(HOLDS, 0)}, cannot tell in {count.get(CANNOT_TELL, 0)}, "
            f"ensemble larger in {count.get(DOES_NOT_HOLD, 0)} of the {len(cells)} cells where both are defined "
            "(the paper: MC larger in 19 of its 20, point values). Details: the Table 2 claims below.")


# --------------------------------------------------------------------------------------------------------------
# Table 2 claims, with magnitudes and intervals
# --------------------------------------------------------------------------------------------------------------

#: Resamples of the Table 2 claims: a Bonferroni level over ~25 tests leaves 0.1 % per tail, ~10 draws there.
TABLE2_RESAMPLES = 10_000
TABLE2_CONFIDENCE = 0.95  # family-wise, per claim
CLAIM_MC_STRONGER = "MC-dropout responds to perturbations more strongly than the ensemble, for every uncertainty"
CLAIM_HEADING_RISES = "Heading uncertainty rises with the perturbation while speed uncertainty stays flat"
CLAIM_MORE_HUMANS = "More humans cause the highest uncertainty"
CLAIM_TESTS = {
    CLAIM_MC_STRONGER: "abs(ΔU/Δσ) of MC-dropout − abs(ΔU/Δσ) of the ensemble (same episodes)",
    CLAIM_HEADING_RISES: "rise of the heading uncertainty − abs(rise of the speed uncertainty), rise = u_σ(max) − u_σ(0)",
    CLAIM_MORE_HUMANS: "u at the most humans − the largest u at the strongest other perturbation",
}
CLAIM_COLUMNS = ["claim", "test", "estimator", "perturbation", "uncertainty", "estimate", "low", "high",
                 "confidence", "episodes", "verdict", "detail"]
UNCERTAINTY_KINDS = {"epistemic": ("u_ep_heading", "u_ep_speed"), "aleatoric": ("u_al_heading", "u_al_speed")}


def _episode_values(episode_means: pd.DataFrame, estimator: str, perturbation: str, strength: float,
                    column: str) -> pd.Series:
    """Episode id -> the episode's mean of `column` at one (estimator, perturbation, strength)."""
    rows = episode_means[(episode_means["estimator"] == estimator) & (episode_means["perturbation"] == perturbation)
                         & np.isclose(episode_means["strength"].to_numpy(float), strength)]
    return rows.set_index("episode")[column].astype(float)


def _paired(series: Sequence[pd.Series]) -> tuple[int, list[np.ndarray]]:
    """The episode ids present in every series (each (estimator, strength) plays episodes 0 ... n-1 from the same
    seeds) and every series' values on them, in the same order."""
    common = sorted(set.intersection(*(set(s.index) for s in series))) if series else []
    return len(common), [s.loc[common].to_numpy(float) for s in series]


def _sensitivity(u0: np.ndarray, u_max: np.ndarray, span: float, counts: np.ndarray) -> np.ndarray:
    """``(u(sigma_max) - u(sigma_0)) / (u(sigma_0) span)`` of the episode means under each row of `counts`
    (episode weights; ones: the point estimate); NaN where ``u(sigma_0) = 0``."""
    mean0, mean_max = counts @ u0 / counts.sum(axis=1), counts @ u_max / counts.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(mean0 != 0, (mean_max - mean0) / (mean0 * span), np.nan)


def mc_vs_ensemble_frame(episode_means: pd.DataFrame, n_resamples: int = TABLE2_RESAMPLES, seed: int = 0,
                         confidence: float = TABLE2_CONFIDENCE) -> pd.DataFrame:
    """Claim rows "MC-dropout responds more strongly than the ensemble": per (perturbation, uncertainty) where both
    sensitivities are defined, ``|dU/dsigma|_MC - |dU/dsigma|_ensemble`` (magnitudes: a response in either
    direction counts) with a percentile bootstrap interval over EPISODES: both estimators estimate the uncertainty
    along the same episodes of the same acting policy, and every strength plays the same episode seeds, so one
    resample of episode ids serves sigma_0, sigma_max and both estimators (paired). Bonferroni over the cells: each
    interval at level ``1 - (1 - confidence) / cells``. Verdict ``holds``: MC larger, ``does not hold``: the
    ensemble larger, else ``cannot tell``. The intervals are over episodes for ONE acting policy (training seed);
    how the numbers vary between policies only the replication with other training seeds shows."""
    from socnav.experiments.statistics import verdict
    from socnav.experiments.uncertainty_information import bonferroni_confidence, cluster_counts, percentile_interval

    cells = []
    for perturbation in _ordered(episode_means["perturbation"], PERTURBATION_ORDER):
        rows = episode_means[episode_means["perturbation"] == perturbation]
        if not {"mc", "ensemble"} <= set(rows["estimator"]):
            continue
        strengths = rows["strength"].to_numpy(float)
        sigma0, sigma_max = float(strengths.min()), float(strengths.max())
        if math.isclose(sigma0, sigma_max):
            continue
        for uncertainty in RAW_COLUMNS:
            if uncertainty not in rows:
                continue
            n, values = _paired([_episode_values(rows, e, perturbation, s, uncertainty)
                                 for e in ("mc", "ensemble") for s in (sigma0, sigma_max)])
            if n == 0:
                continue
            span = sigma_max - sigma0
            ones = np.ones((1, n))
            mc, ens = (float(_sensitivity(u0, u_max, span, ones)[0]) for u0, u_max in (values[:2], values[2:]))
            if math.isfinite(mc) and math.isfinite(ens):
                cells.append((perturbation, uncertainty, n, span, values, mc, ens))
    level = bonferroni_confidence(confidence, len(cells))
    rows = []
    for perturbation, uncertainty, n, span, values, mc, ens in cells:
        counts = cluster_counts(np.zeros(n), n_resamples, seed)
        draws = (np.abs(_sensitivity(values[0], values[1], span, counts))
                 - np.abs(_sensitivity(values[2], values[3], span, counts)))
        interval = percentile_interval(abs(mc) - abs(ens), draws, level)
        rows.append(_claim_row(CLAIM_MC_STRONGER, "", perturbation, uncertainty, interval, level, n,
                               verdict(interval), f"ΔU/Δσ MC {mc:.3g}, ensemble {ens:.3g}"))
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def heading_vs_speed_frame(episode_means: pd.DataFrame, n_resamples: int = TABLE2_RESAMPLES, seed: int = 0,
                           confidence: float = TABLE2_CONFIDENCE) -> pd.DataFrame:
    """Claim rows "heading uncertainty rises while speed uncertainty stays flat", for every uncertainty with a
    heading and a speed part (epistemic, aleatoric), estimator and perturbation: ``rise_heading - |rise_speed|``,
    ``rise = u(sigma_max) - u(sigma_0)`` of the episode means (absolute: both are variances of the normalised action,
    and the paper's claim is about levels -- its own normalised Table II has speed above heading), with a paired
    bootstrap interval over episodes (Bonferroni over the rows). ``holds``: heading rises by more than speed moves
    (hence heading rises). Intervals over episodes for one acting policy."""
    from socnav.experiments.statistics import verdict
    from socnav.experiments.uncertainty_information import bonferroni_confidence, cluster_counts, percentile_interval

    tests = []
    for estimator in _ordered(episode_means["estimator"], ESTIMATOR_ORDER):
        mine = episode_means[episode_means["estimator"] == estimator]
        for kind, (heading, speed) in UNCERTAINTY_KINDS.items():
            if heading not in mine or speed not in mine:
                continue
            for perturbation in _ordered(mine["perturbation"], PERTURBATION_ORDER):
                strengths = mine.loc[mine["perturbation"] == perturbation, "strength"].to_numpy(float)
                sigma0, sigma_max = float(strengths.min()), float(strengths.max())
                if math.isclose(sigma0, sigma_max):
                    continue
                n, (h0, h_max, s0, s_max) = _paired([_episode_values(mine, estimator, perturbation, s, c)
                                                     for c in (heading, speed) for s in (sigma0, sigma_max)])
                if n:
                    tests.append((estimator, kind, perturbation, n, h_max - h0, s_max - s0))
    level = bonferroni_confidence(confidence, len(tests))
    rows = []
    for estimator, kind, perturbation, n, heading_rise, speed_rise in tests:
        counts = cluster_counts(np.zeros(n), n_resamples, seed)
        draws = counts @ heading_rise / n - np.abs(counts @ speed_rise / n)
        rise_h, rise_s = float(heading_rise.mean()), float(speed_rise.mean())
        interval = percentile_interval(rise_h - abs(rise_s), draws, level)
        rows.append(_claim_row(CLAIM_HEADING_RISES, estimator, perturbation, kind, interval, level, n,
                               verdict(interval), f"rise heading {rise_h:.3g}, speed {rise_s:.3g}"))
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def more_humans_frame(episode_means: pd.DataFrame, n_resamples: int = TABLE2_RESAMPLES, seed: int = 0,
                      confidence: float = TABLE2_CONFIDENCE) -> pd.DataFrame:
    """Claim rows "more humans cause the highest uncertainty", per estimator and uncertainty: u at the largest
    number of agents minus the largest u at the strongest strength of any other perturbation type (all start from
    the same unperturbed world, so levels and ratios to u_sigma(0) rank alike), with a bootstrap interval over
    episodes (each perturbation type's episodes resampled on their own; Bonferroni over the rows). Intervals over
    episodes for one acting policy."""
    from socnav.experiments.statistics import verdict
    from socnav.experiments.uncertainty_information import bonferroni_confidence, cluster_counts, percentile_interval

    tests = []
    for estimator in _ordered(episode_means["estimator"], ESTIMATOR_ORDER):
        mine = episode_means[episode_means["estimator"] == estimator]
        perturbations = _ordered(mine["perturbation"], PERTURBATION_ORDER)
        if "more_humans" not in perturbations or len(perturbations) < 2:
            continue
        for uncertainty in RAW_COLUMNS:
            if uncertainty not in mine:
                continue
            groups = {}
            for perturbation in perturbations:
                strongest = mine.loc[mine["perturbation"] == perturbation, "strength"].max()
                groups[perturbation] = _episode_values(mine, estimator, perturbation, strongest,
                                                       uncertainty).to_numpy()
            tests.append((estimator, uncertainty, groups))
    level = bonferroni_confidence(confidence, len(tests))
    rows = []
    for estimator, uncertainty, groups in tests:
        names = list(groups)
        values = np.concatenate([groups[name] for name in names])
        stratum = np.concatenate([np.full(len(groups[name]), i) for i, name in enumerate(names)])
        counts = cluster_counts(stratum, n_resamples, seed)
        means = np.column_stack([counts[:, stratum == i] @ groups[name] / len(groups[name])
                                 for i, name in enumerate(names)])  # (resamples, perturbation types)
        point = np.array([groups[name].mean() for name in names])
        humans = names.index("more_humans")
        others = [i for i in range(len(names)) if i != humans]
        estimate = float(point[humans] - point[others].max())
        draws = means[:, humans] - means[:, others].max(axis=1)
        interval = percentile_interval(estimate, draws, level)
        runner_up = names[others[int(np.argmax(point[others]))]]
        rows.append(_claim_row(CLAIM_MORE_HUMANS, estimator, "more_humans", uncertainty, interval, level,
                               len(groups["more_humans"]), verdict(interval),
                               f"u more humans {point[humans]:.3g}, next {perturbation_label(runner_up).lower()} "
                               f"{point[others].max():.3g}"))
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def _claim_row(claim: str, estimator: str, perturbation: str, uncertainty: str, interval: Any, level: float,
               episodes: int, verdict: str, detail: str) -> dict[str, Any]:
    return {"claim": claim, "test": CLAIM_TESTS[claim], "estimator": estimator, "perturbation": perturbation,
            "uncertainty": uncertainty, "estimate": interval.estimate, "low": interval.low, "high": interval.high,
            "confidence": level, "episodes": episodes, "verdict": verdict, "detail": detail}


def table2_claims_frame(episode_means: pd.DataFrame, n_resamples: int = TABLE2_RESAMPLES,
                        seed: int = 0) -> pd.DataFrame:
    """Every Table 2 claim test (one row each): MC vs ensemble per cell, heading vs speed per estimator, kind and
    perturbation, more humans per estimator and uncertainty. The paper's claims are about its perturbations: the
    types beyond the paper (:data:`BEYOND_PAPER`, the behaviour shift) are left out."""
    episode_means = episode_means[~episode_means["perturbation"].isin(BEYOND_PAPER)]
    frames = [f(episode_means, n_resamples, seed) for f in (mc_vs_ensemble_frame, heading_vs_speed_frame,
                                                            more_humans_frame)]
    frames = [frame for frame in frames if not frame.empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=CLAIM_COLUMNS)


def claims_summary(claims: pd.DataFrame) -> pd.DataFrame:
    """One row per claim (and estimator, and kind for heading vs speed): how many tests hold, cannot tell, do not
    hold, and the verdict on the claim as the paper states it (for every cell): ``holds`` if every test holds,
    ``does not hold`` if one does not, else ``cannot tell``."""
    from socnav.experiments.statistics import CANNOT_TELL, DOES_NOT_HOLD, HOLDS

    rows = []
    for (claim, estimator), group in claims.groupby(["claim", "estimator"], sort=False):
        parts = [("", group)]
        if claim == CLAIM_HEADING_RISES:
            parts = list(group.groupby("uncertainty", sort=False))
        for kind, tests in parts:
            count = tests["verdict"].value_counts()
            holds, fails = int(count.get(HOLDS, 0)), int(count.get(DOES_NOT_HOLD, 0))
            overall = HOLDS if holds == len(tests) else DOES_NOT_HOLD if fails else CANNOT_TELL
            who = " ".join(part for part in (estimator_label(estimator) if estimator else "", kind) if part)
            rows.append({"claim": claim, "scope": who or "all cells", "tests": len(tests), "holds": holds,
                         "cannot_tell": int(count.get(CANNOT_TELL, 0)), "does_not_hold": fails,
                         "verdict": overall})
    return pd.DataFrame(rows, columns=["claim", "scope", "tests", "holds", "cannot_tell", "does_not_hold",
                                       "verdict"])


def _table2_claims(context: ReportContext) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(claim tests, summary) of the run's study records, cached (table2 and table2_claims both use them)."""
    if "table2_claims" not in context._cache:
        episode_means, _ = study_summaries(context)
        claims = table2_claims_frame(episode_means) if not episode_means.empty else pd.DataFrame(
            columns=CLAIM_COLUMNS)
        context._cache["table2_claims"] = (claims, claims_summary(claims))
    return context._cache["table2_claims"]


def _interval_text(row: dict[str, Any]) -> str:
    if not (math.isfinite(row["low"]) and math.isfinite(row["high"])):
        return "n/a"
    return f"[{row['low']:.3g}, {row['high']:.3g}]"


CLAIM_SHORT = {CLAIM_MC_STRONGER: "MC > ensemble", CLAIM_HEADING_RISES: "heading rises, speed flat",
               CLAIM_MORE_HUMANS: "more humans highest"}


def table2_claims_markdown(claims: pd.DataFrame, summary: pd.DataFrame) -> str:
    """The summary per claim (claim, test, scope, counts, verdict), then every test (estimate, interval,
    verdict)."""
    lines = ["| Claim (paper) | Test | Scope | Holds / cannot tell / does not hold | Verdict |",
             "|:--|:--|:--|:--|:--|"]
    for row in summary.to_dict("records"):
        lines.append(f"| {row['claim']} | {CLAIM_TESTS.get(row['claim'], '')} | {row['scope']} | {row['holds']} / "
                     f"{row['cannot_tell']} / {row['does_not_hold']} of {row['tests']} | {row['verdict']} |")
    lines += ["", "| Claim | Estimator | Perturbation | Uncertainty | Estimate | Interval (level) | Verdict | Detail |",
              "|:--|:--|:--|:--|--:|:--|:--|:--|"]
    for row in claims.to_dict("records"):
        lines.append("| " + " | ".join([
            CLAIM_SHORT.get(row["claim"], row["claim"]),
            estimator_label(row["estimator"]) if row["estimator"] else "both",
            perturbation_label(row["perturbation"]), TABLE2_ROWS.get(row["uncertainty"], row["uncertainty"]),
            f"{row['estimate']:.3g}", f"{_interval_text(row)} ({row['confidence']:.1%})", row["verdict"],
            row["detail"]]) + " |")
    return "\n".join(lines)


@register_section(KIND, "table2_claims")
def table2_claims_section(context: ReportContext) -> str:
    claims, summary = _table2_claims(context)
    if claims.empty:
        return ""
    write_table_atomic(claims, context.out_dir / "table2_claims.csv")
    markdown = table2_claims_markdown(claims, summary)
    write_text_atomic(context.out_dir / "table2_claims.md", markdown + "\n")
    return "\n".join([
        "## Table 2 claims, with magnitudes and intervals",
        "",
        "The paper's Table 2 claims tested on the study records. Each estimate comes with a percentile bootstrap "
        "interval over episodes (both estimators and every strength play the same episode seeds with the same "
        "acting policy, so resamples are paired by episode); the intervals of a claim are Bonferroni-adjusted over "
        "its tests (level in brackets), so together they cover at 95 %. Verdict: *holds* if the interval lies above "
        "0, *does not hold* if below (for MC vs ensemble: the ensemble responds more strongly), else *cannot tell "
        "at this budget*. A claim made for every cell holds only if every test holds. The intervals are over "
        "episodes for ONE acting policy (training seed): variation between policies is covered only by the "
        "replication with other training seeds. Perturbations beyond the paper (marked (ours)) are left out: the "
        "paper claims nothing about them.",
        "",
        markdown,
        "",
        "Data: [table2_claims.csv](table2_claims.csv).",
    ])


# --------------------------------------------------------------------------------------------------------------
# Fig. 5: uncertainty vs perturbation strength
# --------------------------------------------------------------------------------------------------------------

CURVE_COLUMNS = ["estimator", "perturbation", "strength", "uncertainty", "u_mean", "u_normalised", "episodes",
                 "collision_rate"]


def strength_curves(episode_means: pd.DataFrame, critical: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, perturbation, strength, uncertainty): u(sigma) (mean over episodes of the episode means),
    u(sigma) / u(sigma_0) (NaN where u(sigma_0) = 0) and the share of episodes ending in a collision."""
    if episode_means.empty:
        return pd.DataFrame(columns=CURVE_COLUMNS)
    keys = ["estimator", "perturbation", "strength"]
    uncertainties = [c for c in CURVE_UNCERTAINTIES if c in episode_means]
    means = episode_means.groupby(keys, sort=True)[uncertainties].mean()
    counts = episode_means.groupby(keys, sort=True).size().rename("episodes")
    if not critical.empty:
        rates = critical.groupby(keys, sort=True)["collided"].mean().rename("collision_rate")
    else:
        rates = pd.Series(np.nan, index=means.index, name="collision_rate")
    long = means.reset_index().melt(id_vars=keys, value_vars=uncertainties, var_name="uncertainty",
                                    value_name="u_mean")
    long = long.merge(counts.reset_index(), on=keys).merge(rates.reset_index(), on=keys, how="left")
    baseline = long.loc[long.groupby(["estimator", "perturbation", "uncertainty"])["strength"].idxmin()]
    baseline = baseline.set_index(["estimator", "perturbation", "uncertainty"])["u_mean"].rename("u0")
    long = long.join(baseline, on=["estimator", "perturbation", "uncertainty"])
    long["u_normalised"] = np.where(long["u0"] != 0, long["u_mean"] / long["u0"].where(long["u0"] != 0), np.nan)
    return long.sort_values(["estimator", "perturbation", "uncertainty", "strength"], ignore_index=True)[CURVE_COLUMNS]


def plot_uncertainty_vs_strength(curves: pd.DataFrame, out_base: Path) -> list[Path]:
    """One panel per perturbation type: u(sigma)/u(sigma_0) of each uncertainty (colour) and estimator (MC solid,
    ensemble dashed); grey markers on a right axis: collision rate (%) per strength and estimator."""
    from matplotlib.lines import Line2D

    plt = _pyplot()
    perturbations = _ordered(curves["perturbation"], PERTURBATION_ORDER)
    estimators = _ordered(curves["estimator"], ESTIMATOR_ORDER)
    colours = {u: plt.get_cmap("tab10")(i) for i, u in enumerate(CURVE_UNCERTAINTIES)}
    figure, axes = _grid(len(perturbations))
    for axis, perturbation in zip(axes, perturbations):
        data = curves[curves["perturbation"] == perturbation]
        twin = axis.twinx()
        for estimator in estimators:
            rows = data[data["estimator"] == estimator]
            for uncertainty in CURVE_UNCERTAINTIES:
                line = rows[rows["uncertainty"] == uncertainty]
                if line.empty or line["u_normalised"].isna().all():
                    continue
                axis.plot(line["strength"], line["u_normalised"], color=colours[uncertainty],
                          linestyle=LINESTYLES.get(estimator, ":"), linewidth=1.5, marker=".", markersize=4)
            rates = rows.drop_duplicates("strength")
            if rates["collision_rate"].notna().any():
                twin.plot(rates["strength"], 100 * rates["collision_rate"], linestyle="none", color="0.55",
                          marker=MARKERS.get(estimator, "s"), markersize=4, alpha=0.8, clip_on=False)
        axis.axhline(1.0, color="0.8", linewidth=0.8, zorder=0)
        axis.set_title(perturbation_label(perturbation))
        axis.set_xlabel(STRENGTH_LABELS.get(perturbation, "strength"))
        axis.set_ylabel("u_σ / u_σ(0)")
        twin.set_ylabel("collisions (%)", color="0.45")
        twin.tick_params(axis="y", colors="0.45")
        twin.set_ylim(bottom=0)
        axis.grid(alpha=0.3)
    handles = [Line2D([], [], color=colours[u], label=label) for u, label in CURVE_UNCERTAINTIES.items()]
    handles += [Line2D([], [], color="black", linestyle=LINESTYLES.get(e, ":"), label=estimator_label(e))
                for e in estimators]
    handles += [Line2D([], [], color="0.55", linestyle="none", marker=MARKERS.get(e, "s"),
                       label=f"collisions, {estimator_label(e)}") for e in estimators]
    figure.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), frameon=False)
    legend_inches = 0.25 * math.ceil(len(handles) / 4) + 0.15
    figure.tight_layout(rect=(0, min(0.5, legend_inches / figure.get_figheight()), 1, 1))
    return save_figure(figure, out_base)


@register_section(KIND, "uncertainty_vs_strength")
def uncertainty_vs_strength_section(context: ReportContext) -> str:
    episode_means, critical = study_summaries(context)
    if episode_means.empty:
        return ""
    curves = strength_curves(episode_means, critical)
    write_table_atomic(curves, context.out_dir / "uncertainty_vs_strength.csv")
    plot_uncertainty_vs_strength(curves, context.out_dir / "uncertainty_vs_strength")
    return "\n".join([
        "## Uncertainty vs perturbation strength (Fig. 5)",
        "",
        "Normalised episodic mean u_σ / u_σ(0) of the epistemic and aleatoric heading and speed uncertainty vs the "
        "perturbation strength; MC-dropout solid, ensemble dashed. Grey markers (right axis): share of episodes "
        "ending in a collision at that strength (circles MC-dropout, crosses ensemble). A curve is left out where "
        "u_σ(0) = 0.",
        "",
        "![uncertainty vs strength](uncertainty_vs_strength.png)",
        "",
        "Vector version: [uncertainty_vs_strength.svg](uncertainty_vs_strength.svg); data: "
        "[uncertainty_vs_strength.csv](uncertainty_vs_strength.csv) (also the unnormalised means).",
    ])


# --------------------------------------------------------------------------------------------------------------
# Fig. 6: feature uncertainty before a collision vs at the closest approach
# --------------------------------------------------------------------------------------------------------------

def plot_feature_collisions(critical: pd.DataFrame, out_base: Path) -> list[Path]:
    """Rows: estimators; columns: perturbation types. Each panel: box + jittered points of ``w_u_feat`` one step
    before a collision and at the closest approach of the episodes without one (all strengths pooled)."""
    plt = _pyplot()
    perturbations = _ordered(critical["perturbation"], PERTURBATION_ORDER)
    estimators = _ordered(critical["estimator"], ESTIMATOR_ORDER)
    ncols, nrows = len(perturbations), len(estimators)
    figure, axes = plt.subplots(nrows, ncols, figsize=(3.2 * ncols, 3.3 * nrows), squeeze=False)
    rng = np.random.default_rng(0)
    colours = {True: "tab:red", False: "tab:blue"}
    for r, estimator in enumerate(estimators):
        for c, perturbation in enumerate(perturbations):
            axis = axes[r][c]
            data = critical[(critical["estimator"] == estimator) & (critical["perturbation"] == perturbation)]
            labels = []
            if data.empty:
                axis.text(0.5, 0.5, "no records", transform=axis.transAxes, ha="center", va="center",
                          color="0.5")
            for position, collided in ((1, True), (2, False)):
                values = data.loc[data["collided"].astype(bool) == collided, "value"].to_numpy(float)
                values = values[np.isfinite(values)]
                name = "before collision" if collided else "closest approach"
                labels.append(f"{name}\n(n={len(values)})")
                if not len(values):
                    continue
                axis.boxplot([values], positions=[position], widths=0.5, showfliers=False,
                             medianprops={"color": colours[collided]})
                jitter = rng.uniform(-0.15, 0.15, len(values))
                axis.scatter(position + jitter, values, s=8, color=colours[collided], alpha=0.5, linewidths=0)
            axis.set_xticks([1, 2])
            axis.set_xticklabels(labels, fontsize=8)
            axis.set_xlim(0.4, 2.6)
            axis.set_title(f"{perturbation_label(perturbation)} — {ESTIMATOR_SHORT.get(estimator, estimator)}",
                           fontsize=9)
            axis.grid(alpha=0.3, axis="y")
            if c == 0:
                axis.set_ylabel(f"{estimator_label(estimator)}\nwindowed feature uncertainty")
    figure.tight_layout()
    return save_figure(figure, out_base)


CRITICAL_SUMMARY_COLUMNS = ["estimator", "perturbation", "collisions", "episodes", "median_before_collision",
                            "median_closest_approach", "mean_before_collision", "mean_closest_approach"]


def critical_summary(critical: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for (estimator, perturbation), group in critical.groupby(["estimator", "perturbation"], sort=False):
        hit = group["collided"].astype(bool)
        before, closest = group.loc[hit, "value"].astype(float), group.loc[~hit, "value"].astype(float)
        rows.append({"estimator": estimator, "perturbation": perturbation, "collisions": int(hit.sum()),
                     "episodes": len(group),
                     "median_before_collision": before.median() if len(before) else math.nan,
                     "median_closest_approach": closest.median() if len(closest) else math.nan,
                     "mean_before_collision": before.mean() if len(before) else math.nan,
                     "mean_closest_approach": closest.mean() if len(closest) else math.nan})
    return pd.DataFrame(rows, columns=CRITICAL_SUMMARY_COLUMNS)


def _g(value: float) -> str:
    return MISSING if not math.isfinite(value) else f"{value:.3g}"


@register_section(KIND, "feature_uncertainty_collisions")
def feature_uncertainty_collisions_section(context: ReportContext) -> str:
    _, critical = study_summaries(context)
    if critical.empty:
        return ""
    write_table_atomic(critical, context.out_dir / "feature_uncertainty_collisions.csv")
    plot_feature_collisions(critical, context.out_dir / "feature_uncertainty_collisions")
    summary = critical_summary(critical)
    lines = [
        "## Feature uncertainty before a collision vs at the closest approach (Fig. 6)",
        "",
        "Windowed (w = 4) predictive feature uncertainty on the step before a collision (collision episodes: the "
        "uncertainty of the observation the colliding action was chosen from) and at the closest approach to a "
        "human (minimum gap; episodes without a collision), every strength of each perturbation pooled.",
        "",
        "![feature uncertainty before collisions](feature_uncertainty_collisions.png)",
        "",
        "| Estimator | Perturbation | Collisions / episodes | Median before collision | Median at closest approach |",
        "|:--|:--|--:|--:|--:|",
    ]
    ordered = summary.assign(
        _e=summary["estimator"].map({e: i for i, e in enumerate(_ordered(summary["estimator"], ESTIMATOR_ORDER))}),
        _p=summary["perturbation"].map(
            {p: i for i, p in enumerate(_ordered(summary["perturbation"], PERTURBATION_ORDER))}),
    ).sort_values(["_e", "_p"])
    for row in ordered.to_dict("records"):
        lines.append(f"| {estimator_label(row['estimator'])} | {perturbation_label(row['perturbation'])} | "
                     f"{row['collisions']} / {row['episodes']} | {_g(row['median_before_collision'])} | "
                     f"{_g(row['median_closest_approach'])} |")
    lines += ["", "Vector version: [feature_uncertainty_collisions.svg](feature_uncertainty_collisions.svg); data: "
                  "[feature_uncertainty_collisions.csv](feature_uncertainty_collisions.csv) (one row per episode)."]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Table 3: prevented collisions
# --------------------------------------------------------------------------------------------------------------

TABLE3_COLUMNS = ["estimator", "variant", "sensing", "column", "repeats", "repeats_defined", "collisions_none",
                  "collisions_variant", "prevented_mean", "prevented_std", "paper_mean", "paper_std"]
#: The paper's Table III columns, in its order: observation noise, action noise (our heading and speed noise
#: pooled: the paper perturbs the action), velocity (our faster humans), new humans (our more humans).
PAPER_TABLE3_COLUMNS = list(dict.fromkeys(p.pooled or name for name, p in PERTURBATIONS.items() if not p.ours))
#: Our columns that the paper has no column for: heading and speed noise alone (it reports them only pooled, as
#: action noise) and the perturbations beyond the paper (the behaviour shift).
OWN_TABLE3_COLUMNS = [name for name, p in PERTURBATIONS.items() if p.ours or p.pooled is not None]
TABLE3_COLUMN_LABELS = {**{name: p.table3_label for name, p in PERTURBATIONS.items()}, **POOLED_LABELS}
#: Episode seeds the development of Table 3 looked at before the held-out range: the earlier evaluations (seeds
#: 0-999, the paper budget's 5 x 200) and the fresh-episodes check (100,000-100,449). The calibration's seeds
#: (CALIBRATION_SEED...) are added per run.
DEVELOPMENT_SEEDS = ((0, 999), (100_000, 100_449))
#: The false-activation budget of the main rows when the run does not name one (`Safety.false_activation_budget`).
DEFAULT_BUDGET = 0.05


def _table3_groups(perturbations: Iterable[str]) -> dict[str, list[str]]:
    """Table 3 columns: each perturbation type, plus each pooled column (:data:`POOLED`; the paper's action noise =
    heading and speed noise) after the last of its types when all of them are there."""
    present = _ordered(perturbations, PERTURBATION_ORDER)
    groups: dict[str, list[str]] = {}
    for perturbation in present:
        groups[perturbation] = [perturbation]
        pool = PERTURBATIONS[perturbation].pooled if perturbation in PERTURBATIONS else None
        if pool is not None and all(kind in present for kind in POOLED[pool]) and \
                perturbation == [kind for kind in present if kind in POOLED[pool]][-1]:
            groups[pool] = list(POOLED[pool])
    return groups


def _with_sensing(safety: pd.DataFrame) -> pd.DataFrame:
    """The records with a ``sensing`` column: records from before the choice existed read the observation."""
    if "sensing" in safety:
        return safety
    return safety.assign(sensing=np.where(safety["variant"] == "none", "", "perceived"))


def _with_rule(safety: pd.DataFrame) -> pd.DataFrame:
    """The records with ``sensing``, ``rule`` and ``budget`` columns: records of units without the ablation are
    the paper's rule (eq. (10)) and carry no budget (NaN)."""
    safety = _with_sensing(safety)
    if "rule" not in safety:
        safety = safety.assign(rule=np.where(safety["variant"] == "none", "", "paper"))
    if "budget" not in safety:
        safety = safety.assign(budget=np.nan)
    return safety


def main_records(safety: pd.DataFrame, budget: float = DEFAULT_BUDGET) -> pd.DataFrame:
    """The records of Table 3 and its cost: the plain policy, the paper's thresholds and the paper's rule calibrated
    at `budget` -- not the ablation's rules, the trade-off budgets, nor the units of the rule without estimator."""
    safety = _with_rule(safety)
    budgets = safety["budget"].to_numpy(np.float64)
    keep = ((safety["estimator"] != NO_ESTIMATOR) & safety["rule"].isin(["", "paper"])
            & (np.isnan(budgets) | np.isclose(budgets, budget)))
    return safety[keep]


def _run_budget(context: ReportContext) -> float:
    """The false-activation budget of the run's main calibrated rows (:data:`DEFAULT_BUDGET` if it names none)."""
    safety = context.experiment.get("safety") or {}
    return float(safety.get("false_activation_budget", DEFAULT_BUDGET))


def _safe_variants(safety: pd.DataFrame) -> list[tuple[str, str]]:
    """The (variant, sensing) pairs of the safety layer in the records, paper before calibrated, perceived first."""
    pairs = safety.loc[safety["variant"] != "none", ["variant", "sensing"]].drop_duplicates()
    variants = _ordered(pairs["variant"], ["paper", "calibrated"])
    sensings = _ordered(pairs["sensing"], SENSING_ORDER)
    present = set(pairs.itertuples(index=False, name=None))
    return [(v, s) for v in variants for s in sensings if (v, s) in present]


def variant_label(variant: str, sensing: str, show_sensing: bool) -> str:
    """``paper thresholds`` etc., with the sensing appended (``, true state``) when `show_sensing`."""
    label = VARIANT_LABELS.get(variant, variant)
    return f"{label}, {SENSING_LABELS.get(sensing, sensing)}" if show_sensing and variant != "none" else label


def _show_sensing(pairs: Iterable[tuple[str, str]]) -> bool:
    """Name the sensing in labels unless every safe variant read the observation (as before the choice)."""
    return any(sensing != "perceived" for variant, sensing in pairs if variant != "none")


def prevented_frame(safety: pd.DataFrame) -> pd.DataFrame:
    """Prevented collisions per (estimator, safe variant, sensing, Table 3 column): per repeat ``100 (C_none -
    C_variant) / C_none`` over the perturbed strengths, then mean and population std over the repeats with
    ``C_none > 0`` (NaN if there is none). ``collisions_*`` are the totals over the repeats used. One rule and
    budget per (estimator, variant, sensing): pass :func:`main_records` (or the ablation's view)."""
    if safety.empty:
        return pd.DataFrame(columns=TABLE3_COLUMNS)
    safety = _with_sensing(safety)
    perturbed = safety[_perturbed(safety)]
    keys = ["estimator", "perturbation", "repeat", "variant", "sensing"]
    collisions = (perturbed["outcome"] == "collision").groupby([perturbed[k] for k in keys]).sum()
    plain = ("none", "")  # the plain policy has no safety layer, so no sensing
    rows = []
    groups = _table3_groups(safety["perturbation"])
    for estimator in _ordered(safety["estimator"], ESTIMATOR_ORDER):
        mine = safety[safety["estimator"] == estimator]
        for variant, sensing in _safe_variants(mine):
            for column, kinds in groups.items():
                kinds = [k for k in kinds if (mine["perturbation"] == k).any()]
                if not kinds:
                    continue
                repeats = sorted(set(mine["repeat"]))
                used = [r for r in repeats if all((estimator, k, r, *v) in collisions.index
                                                  for k in kinds for v in (plain, (variant, sensing)))]
                if not used:
                    continue
                c_none = np.array([sum(collisions[(estimator, k, r, *plain)] for k in kinds) for r in used])
                c_var = np.array([sum(collisions[(estimator, k, r, variant, sensing)] for k in kinds) for r in used])
                defined = c_none > 0
                prevented = 100.0 * (c_none[defined] - c_var[defined]) / c_none[defined]
                paper_mean, paper_std = paper_table3(column, estimator)
                rows.append({"estimator": estimator, "variant": variant, "sensing": sensing, "column": column,
                             "repeats": len(used), "repeats_defined": int(defined.sum()),
                             "collisions_none": int(c_none.sum()), "collisions_variant": int(c_var.sum()),
                             "prevented_mean": float(prevented.mean()) if len(prevented) else math.nan,
                             "prevented_std": float(prevented.std(ddof=0)) if len(prevented) else math.nan,
                             "paper_mean": paper_mean, "paper_std": paper_std})
    return pd.DataFrame(rows, columns=TABLE3_COLUMNS)


def _prevented_cell(indexed: pd.DataFrame, key: tuple[Any, ...]) -> str:
    """``mean ± std`` of one Table 3 cell (``(k of n)`` when only k repeats had a collision to prevent)."""
    if key not in indexed.index:
        return MISSING
    cell = indexed.loc[key]
    if cell["repeats_defined"] == 0:
        return ZERO
    text = f"{cell['prevented_mean']:.1f} ± {cell['prevented_std']:.1f}"
    if cell["repeats_defined"] < cell["repeats"]:
        text += f" ({int(cell['repeats_defined'])} of {int(cell['repeats'])})"
    return text


def prevented_markdown(table: pd.DataFrame, columns: Sequence[str] | None = None, paper_rows: bool = True) -> str:
    """Rows: estimator x thresholds (x sensing, named when not only ``perceived``), then (`paper_rows`) the paper's
    row of that estimator, each of its values once; `columns` (default: the paper's Table III columns present,
    :data:`PAPER_TABLE3_COLUMNS`). ``—``: no collision without the safety layer; ``(k of n)``: only k repeats had
    one."""
    table = table if "sensing" in table else table.assign(sensing="perceived")
    wanted = PAPER_TABLE3_COLUMNS if columns is None else list(columns)
    columns = [c for c in wanted if c in set(table["column"])]
    header = ["Approach", "Thresholds"] + [TABLE3_COLUMN_LABELS.get(c, perturbation_label(c)) for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * len(columns)) + "|"]
    indexed = table.set_index(["estimator", "variant", "sensing", "column"])
    show_sensing = _show_sensing(table[["variant", "sensing"]].itertuples(index=False, name=None))
    for estimator in _ordered(table["estimator"], ESTIMATOR_ORDER):
        for variant, sensing in _safe_variants(table[table["estimator"] == estimator]):
            row = [estimator_label(estimator), variant_label(variant, sensing, show_sensing)]
            row += [_prevented_cell(indexed, (estimator, variant, sensing, column)) for column in columns]
            lines.append("| " + " | ".join(row) + " |")
        paper = [paper_table3(column, estimator) for column in columns]
        if paper_rows and any(math.isfinite(mean) for mean, _ in paper):
            cells = [f"*{mean:.0f} ± {std:.0f}*" if math.isfinite(mean) else MISSING for mean, std in paper]
            lines.append(f"| {estimator_label(estimator)} | *paper's Table III* | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _unpaired_groups(safety: pd.DataFrame) -> int:
    """(estimator, perturbation, strength, repeat, variant) groups whose episode seeds differ from 'none''s."""
    if "seed" not in safety or safety.empty:
        return 0
    keys = ["estimator", "perturbation", "strength", "repeat"]
    mismatches = 0
    # each sensing, rule and budget of a variant is its own run of the episodes: compare each with the plain
    # policy's seeds
    variant_keys = [key for key in ("variant", "sensing", "rule", "budget") if key in safety]
    for _, group in safety.groupby(keys, sort=False):
        plain = group[group["variant"] == "none"]
        if plain.empty:
            continue
        reference = sorted(plain["seed"].tolist())
        for _, runs in group[group["variant"] != "none"].groupby(variant_keys, dropna=False):
            mismatches += sorted(runs["seed"].tolist()) != reference
    return mismatches


def _seed_ranges_text(context: ReportContext) -> str:
    """Which episode seeds the evaluation played, and whether any development step looked at them."""
    evaluation, safety = context.experiment.get("evaluation") or {}, context.experiment.get("safety") or {}
    seed, episodes, repeats = evaluation.get("seed"), evaluation.get("episodes"), safety.get("repeats")
    if not all(isinstance(value, int) for value in (seed, episodes, repeats)):
        return ""
    last = seed + repeats * episodes - 1
    configurations = 1 + sum(len(strengths) for strengths in CALIBRATION_SET.values())  # unperturbed + perturbed
    calibration = (CALIBRATION_SEED, CALIBRATION_SEED + configurations * int(safety.get("calibration_episodes", 0)) - 1)
    looked = [*DEVELOPMENT_SEEDS, calibration]
    seen = [f"{a:,}–{b:,}" for a, b in looked if a <= last and seed <= b]
    ranges = ", ".join(f"{a:,}–{b:,}" for a, b in looked)
    verdict = (f"held out: no development step looked at them (the earlier Table 3 evaluations and checks played "
               f"seeds {', '.join(f'{a:,}–{b:,}' for a, b in DEVELOPMENT_SEEDS)}, the calibration "
               f"{calibration[0]:,}–{calibration[1]:,})" if not seen else
               f"**not held out**: they overlap seeds development looked at ({', '.join(seen)} of {ranges})")
    return (f"Evaluation episodes: seeds {seed:,}–{last:,} (repeat r, episode k: seed + r · {episodes} + k), "
            f"{verdict}.")


@register_section(KIND, "table3")
def table3_section(context: ReportContext) -> str:
    safety = safety_records(context)
    if safety.empty:
        return ""
    safety = main_records(safety, _run_budget(context))
    table = prevented_frame(safety)
    write_table_atomic(table, context.out_dir / "table3.csv")
    if table.empty:
        markdown = own = "No safe variant with its plain-policy runs yet."
    else:
        markdown = prevented_markdown(table)
        own = prevented_markdown(table, OWN_TABLE3_COLUMNS, paper_rows=False)
    has_own = not table.empty and bool(set(table["column"]) & set(OWN_TABLE3_COLUMNS))
    write_text_atomic(context.out_dir / "table3.md", markdown + ("\n\n" + own if has_own else "") + "\n")
    repeats = safety["repeat"].nunique()
    lines = [
        "## Table 3: prevented collisions with safe action selection",
        "",
        "Prevented collisions (%) = 100 · (C_none − C_safe) / C_none per column, C the collisions over all "
        "perturbed strengths of its perturbation type(s) (the unperturbed strength left out), the plain policy and "
        f"the safety layer on identical episode seeds; mean ± standard deviation over {repeats} repeat(s) "
        f"(independent seed blocks). {ZERO}: the plain policy did not collide, nothing to prevent; (k of n): only k "
        "repeats had a collision to prevent. The paper's four columns, each compared once with the paper's value "
        "(italic): observation noise; action noise = our heading and speed noise pooled (the paper perturbs the "
        "action); velocity = our faster humans; new humans = our more humans.",
        "",
    ]
    seeds = _seed_ranges_text(context)
    if seeds:
        lines += [seeds, ""]
    if _show_sensing(table[["variant", "sensing"]].itertuples(index=False, name=None)):
        lines += ["*Perceived* / *true state*: what the layer's proximity terms (c_prox, c_ap) and cautious fallback "
                  "read — the robot's observation, observation noise included, or the simulator's noise-free state "
                  "(a separate safety sensor); the policy and the uncertainty estimates always see the observation. "
                  "Without observation noise both read the same.", ""]
    lines += [markdown, ""]
    if has_own:
        lines += ["Our own columns (the paper has none for them: it reports heading and speed noise only pooled, "
                  "as action noise above, and has no behaviour shift — humans of another model than the policy "
                  "was trained with, never seen by the calibration):", "", own, ""]
    unpaired = _unpaired_groups(safety_records(context))
    if unpaired:
        lines += [f"**Warning**: in {unpaired} (estimator, perturbation, strength, repeat) group(s) a safe variant "
                  "played other episode seeds than the plain policy; those comparisons are not paired.", ""]
    lines.append("Data: [table3.csv](table3.csv) (also the collision totals and repeat counts per cell).")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# The cost of the safety layer
# --------------------------------------------------------------------------------------------------------------

COST_COLUMNS = ["estimator", "variant", "sensing", "episodes_perturbed", "episodes_unperturbed", "activation_pct",
                "false_activation_pct", "success_pct_perturbed", "success_pct_unperturbed",
                "collision_pct_perturbed", "collision_pct_unperturbed", "time_to_goal_perturbed",
                "time_to_goal_unperturbed"]


def _rates(frame: pd.DataFrame, layer: bool) -> dict[str, float]:
    """Fallback activation (% of steps), and the registry's success and collision rates and mean time to goal of
    the successful episodes (`socnav.sim.metrics`)."""
    n = len(frame)
    goal = frame["outcome"] == "goal"
    if "time_to_goal" not in frame and "duration" in frame:  # a successful episode's duration is its time to goal
        frame = frame.assign(time_to_goal=frame["duration"])
    activation = math.nan
    if layer and n and "fallback_steps" in frame and frame["length"].sum() > 0:
        activation = 100.0 * float(frame["fallback_steps"].sum()) / float(frame["length"].sum())
    rates = summarize_episodes(frame, ["goal_pct", "collision_pct"]) if n else {}
    timed = "time_to_goal" in frame and goal.any()
    return {
        "episodes": n,
        "activation": activation,
        "success": rates.get("goal_pct", math.nan),
        "collision": rates.get("collision_pct", math.nan),
        "time": summarize_episodes(frame[goal], ["time_to_goal_mean"])["time_to_goal_mean"] if timed else math.nan,
    }


def safety_metrics_frame(safety: pd.DataFrame) -> pd.DataFrame:
    """Every registry metric the safety records hold (`socnav.sim.metrics`), per (estimator, variant, sensing,
    perturbed): the plain policy and each safety layer in perturbed and unperturbed (strength σ(0)) episodes."""
    if safety.empty:
        return pd.DataFrame(columns=SAFETY_METRIC_KEYS + ["episodes"])
    safety = _with_sensing(safety).assign(perturbed=_perturbed(safety))
    return summarize_groups(safety, SAFETY_METRIC_KEYS, ALL_METRICS)


def cost_frame(safety: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, variant incl. none, sensing): fallback activation rate (% of steps) in perturbed episodes,
    false activation rate (% of steps) in unperturbed ones (NaN for the plain policy), success and collision rates
    (%) and mean time to goal of successful episodes, in perturbed and unperturbed episodes."""
    if safety.empty:
        return pd.DataFrame(columns=COST_COLUMNS)
    safety = _with_sensing(safety)
    perturbed = _perturbed(safety)
    rows = []
    for estimator in _ordered(safety["estimator"], ESTIMATOR_ORDER):
        mine = safety["estimator"] == estimator
        pairs = ([("none", "")] if (safety.loc[mine, "variant"] == "none").any() else []) \
            + _safe_variants(safety[mine])
        for variant, sensing in pairs:
            chosen = mine & (safety["variant"] == variant) & (safety["sensing"] == sensing)
            layer = variant != "none"
            hot, cold = _rates(safety[chosen & perturbed], layer), _rates(safety[chosen & ~perturbed], layer)
            rows.append({"estimator": estimator, "variant": variant, "sensing": sensing,
                         "episodes_perturbed": hot["episodes"],
                         "episodes_unperturbed": cold["episodes"], "activation_pct": hot["activation"],
                         "false_activation_pct": cold["activation"], "success_pct_perturbed": hot["success"],
                         "success_pct_unperturbed": cold["success"], "collision_pct_perturbed": hot["collision"],
                         "collision_pct_unperturbed": cold["collision"], "time_to_goal_perturbed": hot["time"],
                         "time_to_goal_unperturbed": cold["time"]})
    return pd.DataFrame(rows, columns=COST_COLUMNS)


def _f(value: float, decimals: int) -> str:
    return "–" if not math.isfinite(value) else f"{value:.{decimals}f}"


def cost_markdown(table: pd.DataFrame) -> str:
    header = ["Approach", "Safety layer", "Episodes (pert. / unpert.)", "Fallback activation (% steps, pert.)",
              "False activation (% steps, unpert.)", "Success % (pert. / unpert.)", "Collision % (pert. / unpert.)",
              "Time to goal s (pert. / unpert.)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * 6) + "|"]
    table = table if "sensing" in table else table.assign(sensing=np.where(table["variant"] == "none", "", "perceived"))
    show_sensing = _show_sensing(table[["variant", "sensing"]].itertuples(index=False, name=None))
    for row in table.to_dict("records"):
        lines.append("| " + " | ".join([
            estimator_label(row["estimator"]), variant_label(row["variant"], row["sensing"], show_sensing),
            f"{row['episodes_perturbed']} / {row['episodes_unperturbed']}",
            _f(row["activation_pct"], 2), _f(row["false_activation_pct"], 2),
            f"{_f(row['success_pct_perturbed'], 1)} / {_f(row['success_pct_unperturbed'], 1)}",
            f"{_f(row['collision_pct_perturbed'], 1)} / {_f(row['collision_pct_unperturbed'], 1)}",
            f"{_f(row['time_to_goal_perturbed'], 2)} / {_f(row['time_to_goal_unperturbed'], 2)}",
        ]) + " |")
    return "\n".join(lines)


@register_section(KIND, "table3_cost")
def table3_cost_section(context: ReportContext) -> str:
    safety = safety_records(context)
    if safety.empty:
        return ""
    main = main_records(safety, _run_budget(context))  # the ablation's rows: its own section
    table = cost_frame(main)
    write_table_atomic(table, context.out_dir / "table3_cost.csv")
    write_table_atomic(safety_metrics_frame(main), context.out_dir / "table3_metrics.csv")
    markdown = cost_markdown(table)
    write_text_atomic(context.out_dir / "table3_cost.md", markdown + "\n")
    lines = [
        "## The cost of the safety layer",
        "",
        "Over all perturbation types of the safety runs: fallback activation = steps where the cautious controller "
        "acted / all steps, in perturbed episodes; false activation = the same in unperturbed episodes (strength "
        "σ(0)), where there is little to prevent. Success and collision rates over episodes; time to goal: mean over "
        "successful episodes (seconds). '–': no such episodes (or no safety layer).",
        "",
        markdown,
        "",
    ]
    if (table["episodes_unperturbed"] == 0).all():
        lines += ["No unperturbed (σ(0)) episodes in the safety runs: the false-activation rate is not measured.", ""]
    lines.append("Data: [table3_cost.csv](table3_cost.csv); every metric of docs/metrics.md per approach, safety "
                 "layer and perturbed / unperturbed episodes: [table3_metrics.csv](table3_metrics.csv).")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Table 3's ablation: does the uncertainty condition change the safety decision?
# --------------------------------------------------------------------------------------------------------------

#: Rows of the ablation (variant of its view -> label): the paper's rule with the paper's thresholds as printed,
#: the two ablated rules and the paper's rule calibrated (gated by that estimator's uncertainty).
ABLATION_ROWS = {"paper": "Paper's rule, paper's thresholds (as printed)",
                 "proximity-only": "Proximity only: c_prox ∧ c_ap (calibrated)",
                 "uncertainty-only": "Uncertainty only: (c_ep ∨ c_feat) ∧ c_ap (calibrated)",
                 "calibrated": "Paper's rule (c_ep ∨ c_feat) ∧ c_prox ∧ c_ap, calibrated: uncertainty-gated"}
#: The reference every other row is compared with, episode by episode.
REFERENCE = "proximity-only"
ABLATION_CONFIDENCE = 0.95  # family-wise, Bonferroni over the rows compared (or rows x columns)
KEYS = ["perturbation", "strength", "repeat", "seed"]
#: The paired comparison's column of the unperturbed episodes (ours: the paper's columns are all perturbed).
UNPERTURBED_COLUMN = "unperturbed"
PAIRED_COLUMNS = ["estimator", "row", "column", "episodes", "collisions_none", "collisions_reference",
                  "collisions_row", "row_only_prevented", "reference_only_prevented", "difference",
                  "difference_pct", "low_pct", "high_pct", "p_value", "p_adjusted", "comparisons", "confidence",
                  "verdict"]
DECISION_COLUMNS = ["estimator", "row", "episodes", "activation_pct", "false_activation_pct", "proximity_steps",
                    "vetoed_steps", "vetoed_pct", "paired_episodes", "episodes_other_decisions"]


def _ablation_sensing(safety: pd.DataFrame, context: ReportContext | None = None) -> str | None:
    """The sensing of the ablation: that of the proximity-only rows (or the run's `ablation_sensing`)."""
    rows = safety.loc[safety["rule"] == REFERENCE, "sensing"]
    if len(rows):
        return str(rows.iloc[0])
    chosen = ((context.experiment.get("safety") or {}).get("ablation_sensing") if context is not None else None)
    ablated = safety.loc[safety["rule"] == "uncertainty-only", "sensing"]
    return chosen if chosen is not None else (str(ablated.iloc[0]) if len(ablated) else None)


def ablation_records(safety: pd.DataFrame, sensing: str, budget: float = DEFAULT_BUDGET) -> pd.DataFrame:
    """The ablation's view of the records: the plain policy and, for `sensing` and the main `budget`, every row of
    :data:`ABLATION_ROWS` -- ``variant`` renamed to the row (``paper``: the paper's thresholds; ``calibrated``: the
    paper's rule calibrated; ``proximity-only``, ``uncertainty-only``: the ablated rules, calibrated)."""
    safety = _with_rule(safety)
    budgets = safety["budget"].to_numpy(np.float64)
    plain = safety["variant"] == "none"
    mine = (safety["sensing"] == sensing) & ~plain
    as_printed = mine & (safety["variant"] == "paper")
    calibrated = mine & (safety["variant"] == "calibrated") & np.isclose(budgets, budget)
    view = safety[plain | as_printed | calibrated].copy()
    ablated = view["rule"].isin(["proximity-only", "uncertainty-only"])
    view.loc[ablated, "variant"] = view.loc[ablated, "rule"]
    return view


def mcnemar_exact(row_only: int, reference_only: int, confidence: float) -> tuple[float, float, float]:
    """Exact paired comparison of two rules on the same episodes from their discordant episodes: ``row_only``
    episodes where only the reference collided (the row prevented a collision the reference did not),
    ``reference_only`` where only the row collided. Returns ``(low, high, p)``: the conditional interval of the
    difference in prevented collisions ``D = row_only - reference_only`` given the ``n`` discordant episodes --
    ``n (2 pi - 1)`` at the ends of the central Clopper-Pearson interval of ``pi``, the share of discordant episodes
    the row wins -- and the exact two-sided McNemar p-value (binomial test of ``pi = 1/2``). ``n = 0``: the rules
    decided alike in every episode, ``(0, 0, 1)``."""
    from scipy.stats import beta, binomtest

    b, n = int(row_only), int(row_only) + int(reference_only)
    if n == 0:
        return 0.0, 0.0, 1.0
    alpha = 1.0 - confidence
    low = 0.0 if b == 0 else float(beta.ppf(alpha / 2, b, n - b + 1))
    high = 1.0 if b == n else float(beta.ppf(1 - alpha / 2, b + 1, n - b))
    return n * (2 * low - 1), n * (2 * high - 1), float(binomtest(b, n, 0.5).pvalue)


def _paper_column_kinds(perturbations: Iterable[str]) -> dict[str, list[str]]:
    """The paper's Table III columns present (column -> our perturbation types), after ``all`` (every type of the
    paper's columns: the pre-specified pooled comparison, which a column of ours must not change), then each
    perturbation beyond the paper as its own column (e.g. the behaviour shift)."""
    present = _ordered(perturbations, PERTURBATION_ORDER)
    paper = [kind for kind in present if kind not in PERTURBATIONS or not PERTURBATIONS[kind].ours]
    groups = {"all": paper} if paper else {}
    groups.update({c: kinds for c, kinds in _table3_groups(present).items() if c in PAPER_TABLE3_COLUMNS})
    groups.update({kind: [kind] for kind in present if kind in PERTURBATIONS and PERTURBATIONS[kind].ours})
    return groups


def _outcomes(view: pd.DataFrame, estimator: str, variant: str) -> pd.DataFrame:
    rows = view[(view["estimator"] == estimator) & (view["variant"] == variant)]
    return rows.drop_duplicates(KEYS).set_index(KEYS)


def _compared_rows(view: pd.DataFrame) -> list[tuple[str, str]]:
    """(estimator, row) of every row compared with the reference, in the ablation table's order."""
    rows = []
    for variant in ("paper", "uncertainty-only", "calibrated"):
        for estimator in _ordered(view.loc[view["variant"] == variant, "estimator"], ESTIMATOR_ORDER):
            rows.append((estimator, variant))
    return rows


def paired_frame(view: pd.DataFrame, confidence: float = ABLATION_CONFIDENCE) -> pd.DataFrame:
    """Every row of the ablation's `view` (:func:`ablation_records`) against the proximity-only rule, paired by
    episode (perturbation, strength, repeat, seed), over the perturbed episodes of each of the paper's columns, of
    ``all`` of them and over the unperturbed episodes (:data:`UNPERTURBED_COLUMN`): discordant episodes, the difference in prevented collisions ``D`` (row minus reference; in
    points of the plain policy's collisions on those episodes: ``difference_pct``) with its exact conditional
    interval and McNemar p (:func:`mcnemar_exact`). Bonferroni: the ``all`` comparisons at ``1 - (1 - confidence) /
    m`` with m the rows compared, the per-column ones with m = rows x columns; ``p_adjusted = min(1, m p)``.
    Verdict of "the row prevents more collisions than proximity-only": holds / does not hold when the interval
    lies above / below 0, cannot tell when it contains 0."""
    from socnav.experiments.statistics import verdict

    if view.empty or not (view["variant"] == REFERENCE).any():
        return pd.DataFrame(columns=PAIRED_COLUMNS)
    reference = _outcomes(view, NO_ESTIMATOR, REFERENCE)
    groups = _paper_column_kinds(view.loc[_perturbed(view), "perturbation"])
    compared = _compared_rows(view)
    results = []
    for estimator, variant in compared:
        row = _outcomes(view, estimator, variant)
        plain = _outcomes(view, estimator, "none")
        if plain.empty:
            plain = _outcomes(view, NO_ESTIMATOR, "none")
        paired = row[["outcome"]].join(reference["outcome"].rename("outcome_reference"), how="inner").join(
            plain["outcome"].rename("outcome_none"), how="left")
        shifted = _perturbed(paired.index.to_frame(index=False))
        # the paper's columns (perturbed episodes) and, as ours, the unperturbed episodes: where the false
        # activation is measured, so where a gate that keeps within budget by vetoing costs protection
        cells = [(column, shifted & paired.index.get_level_values("perturbation").isin(kinds))
                 for column, kinds in groups.items()] + [(UNPERTURBED_COLUMN, ~shifted)]
        for column, chosen in cells:
            cell = paired[chosen]
            if cell.empty:
                continue
            hit_row = (cell["outcome"] == "collision").to_numpy()
            hit_reference = (cell["outcome_reference"] == "collision").to_numpy()
            hit_none = int((cell["outcome_none"] == "collision").sum())
            results.append({"estimator": estimator, "row": variant, "column": column, "episodes": len(cell),
                            "collisions_none": hit_none, "collisions_reference": int(hit_reference.sum()),
                            "collisions_row": int(hit_row.sum()),
                            "row_only_prevented": int((hit_reference & ~hit_row).sum()),
                            "reference_only_prevented": int((hit_row & ~hit_reference).sum())})
    frame = pd.DataFrame(results, columns=PAIRED_COLUMNS[:9])
    if frame.empty:
        return pd.DataFrame(columns=PAIRED_COLUMNS)
    pooled = frame["column"] == "all"
    frame["comparisons"] = np.where(pooled, int(pooled.sum()), int((~pooled).sum()))
    frame["confidence"] = 1.0 - (1.0 - confidence) / frame["comparisons"]
    stats = [mcnemar_exact(b, c, level) for b, c, level in
             zip(frame["row_only_prevented"], frame["reference_only_prevented"], frame["confidence"])]
    frame["difference"] = frame["row_only_prevented"] - frame["reference_only_prevented"]
    scale = np.where(frame["collisions_none"] > 0, 100.0 / frame["collisions_none"].clip(lower=1), np.nan)
    frame["difference_pct"] = frame["difference"] * scale
    frame["low_pct"] = np.array([low for low, _, _ in stats]) * scale
    frame["high_pct"] = np.array([high for _, high, _ in stats]) * scale
    frame["p_value"] = [p for _, _, p in stats]
    frame["p_adjusted"] = np.minimum(1.0, frame["p_value"] * frame["comparisons"])
    frame["verdict"] = [verdict(Interval(d, low, high)) for d, low, high in
                        zip(frame["difference"], [s[0] for s in stats], [s[1] for s in stats])]
    return frame[PAIRED_COLUMNS]


def decisions_frame(view: pd.DataFrame) -> pd.DataFrame:
    """What the uncertainty condition changed, per row of the ablation's `view` over all its episodes (perturbed and
    unperturbed): fallback activation (% of perturbed steps) and false activation (% of unperturbed steps); the
    steps where the rule's proximity terms fired (``c_prox and c_ap``) and those of them the uncertainty condition
    vetoed (eq. (10)'s rows only; with a hold the fallback may still drive there); and in how many episodes the
    fallback drove on other steps than the proximity-only rule's on the same episode (the rules' hand-over
    decisions differ: ``fallback_digest``)."""
    if view.empty:
        return pd.DataFrame(columns=DECISION_COLUMNS)
    perturbed = _perturbed(view)
    reference = _outcomes(view, NO_ESTIMATOR, REFERENCE) if (view["variant"] == REFERENCE).any() else None
    rows = []
    for variant in ("paper", REFERENCE, "uncertainty-only", "calibrated"):
        for estimator in _ordered(view.loc[view["variant"] == variant, "estimator"], ESTIMATOR_ORDER):
            chosen = (view["estimator"] == estimator) & (view["variant"] == variant)
            hot, cold = _rates(view[chosen & perturbed], True), _rates(view[chosen & ~perturbed], True)
            mine = view[chosen]
            proximity = int(mine["proximity_steps"].sum()) if "proximity_steps" in mine else 0
            vetoed = int(mine["vetoed_steps"].sum()) if "vetoed_steps" in mine else 0
            paired, other = 0, 0
            if reference is not None and variant != REFERENCE and "fallback_digest" in mine:
                joined = mine.drop_duplicates(KEYS).set_index(KEYS)[["fallback_digest"]].join(
                    reference["fallback_digest"].rename("fallback_digest_reference"), how="inner")
                paired = len(joined)
                other = int((joined["fallback_digest"] != joined["fallback_digest_reference"]).sum())
            rows.append({"estimator": estimator, "row": variant, "episodes": int(chosen.sum()),
                         "activation_pct": hot["activation"], "false_activation_pct": cold["activation"],
                         "proximity_steps": proximity, "vetoed_steps": vetoed,
                         "vetoed_pct": 100.0 * vetoed / proximity if variant in ("paper", "calibrated") and proximity
                         else math.nan,
                         "paired_episodes": paired, "episodes_other_decisions": other})
    return pd.DataFrame(rows, columns=DECISION_COLUMNS)


def _paired_text(row: Mapping[str, Any]) -> str:
    if not math.isfinite(row["difference_pct"]):
        return f"{int(row['difference']):+d} collisions (no plain-policy collision)"
    return (f"{row['difference_pct']:+.1f} [{row['low_pct']:+.1f}, {row['high_pct']:+.1f}] "
            f"({int(row['row_only_prevented'])} vs {int(row['reference_only_prevented'])})")


def ablation_markdown(prevented: pd.DataFrame, paired: pd.DataFrame, decisions: pd.DataFrame) -> str:
    """The ablation table: a row per rule (and estimator), the paper's columns (prevented %, mean ± std over the
    repeats), false activation, the uncertainty condition's vetoes, the episodes whose hand-overs differ from the
    proximity-only rule's, and the paired difference with proximity-only over all perturbed episodes."""
    columns = [c for c in PAPER_TABLE3_COLUMNS if c in set(prevented["column"])]
    header = (["Rule", "Estimator"] + [TABLE3_COLUMN_LABELS[c] for c in columns]
              + ["False activation (% steps)", "Vetoed by uncertainty (% of proximity firings)",
                 "Episodes with other hand-overs than proximity-only",
                 "Δ prevented vs proximity-only, all perturbed (points [CI]; episodes won vs lost)", "Verdict"])
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * (len(header) - 3) + [":--"])
             + "|"]
    indexed = prevented.set_index(["estimator", "variant", "column"])
    decided = decisions.set_index(["estimator", "row"])
    compared = paired[paired["column"] == "all"].set_index(["estimator", "row"])
    for variant in ("paper", REFERENCE, "uncertainty-only", "calibrated"):
        for estimator in _ordered(decisions.loc[decisions["row"] == variant, "estimator"], ESTIMATOR_ORDER):
            cells = [ABLATION_ROWS[variant], "–" if estimator == NO_ESTIMATOR else estimator_label(estimator)]
            for column in columns:
                key = (estimator, variant, column)
                cells.append(_prevented_cell(indexed, key) if key in indexed.index else MISSING)
            decision = decided.loc[(estimator, variant)]
            cells.append(_f(decision["false_activation_pct"], 2))
            cells.append("–" if not math.isfinite(decision["vetoed_pct"]) else
                         f"{decision['vetoed_pct']:.1f} ({int(decision['vetoed_steps'])} of "
                         f"{int(decision['proximity_steps'])})")
            cells.append("reference" if variant == REFERENCE else
                         f"{int(decision['episodes_other_decisions'])} of {int(decision['paired_episodes'])}")
            if (estimator, variant) in compared.index:
                row = compared.loc[(estimator, variant)]
                cells += [_paired_text(row), row["verdict"]]
            else:
                cells += ["–", "–"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def paired_markdown(paired: pd.DataFrame) -> str:
    """Per paper column and the unperturbed episodes: the paired difference with proximity-only of every compared
    row (points [CI])."""
    ours = [name for name, p in PERTURBATIONS.items() if p.ours]
    columns = [c for c in [*PAPER_TABLE3_COLUMNS, *ours, UNPERTURBED_COLUMN] if c in set(paired["column"])]
    labels = {**TABLE3_COLUMN_LABELS, UNPERTURBED_COLUMN: "Unperturbed (ours)"}
    header = ["Rule", "Estimator"] + [labels[c] for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * len(columns)) + "|"]
    indexed = paired.set_index(["estimator", "row", "column"])
    for estimator, variant in dict.fromkeys(zip(paired["estimator"], paired["row"])):
        cells = [ABLATION_ROWS[variant], estimator_label(estimator)]
        for column in columns:
            key = (estimator, variant, column)
            cells.append(_paired_text(indexed.loc[key]) + f", {indexed.loc[key, 'verdict']}"
                         if key in indexed.index else MISSING)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def vetoes_frame(view: pd.DataFrame) -> pd.DataFrame:
    """Where the uncertainty condition vetoes, per uncertainty-gated row of the ablation's `view` (the paper's rule,
    calibrated and as printed) and per setting: the steps its proximity terms fired, those the uncertainty
    condition vetoed, and their share. ``setting`` is ``unperturbed`` for every unperturbed episode (the ones the
    false activation is measured on), else ``<perturbation> <strength>``. A gate that vetoes mostly where nothing
    is perturbed spends the false-activation budget on the perturbed settings: what it knows is the shift, not the
    collision (docs/reproduction.md)."""
    columns = ["estimator", "row", "setting", "perturbation", "strength", "proximity_steps", "vetoed_steps",
               "vetoed_pct"]
    gated = view[view["variant"].isin(["paper", "calibrated"])]
    if gated.empty or "vetoed_steps" not in gated:
        return pd.DataFrame(columns=columns)
    gated = gated.assign(setting=np.where(_perturbed(gated), gated["perturbation"] + " " + gated["strength"].map(
        "{:g}".format), "unperturbed"))
    gated.loc[gated["setting"] == "unperturbed", ["perturbation", "strength"]] = ["", math.nan]
    totals = gated.groupby(["estimator", "variant", "setting", "perturbation", "strength"], dropna=False, sort=False)[
        ["proximity_steps", "vetoed_steps"]].sum().reset_index().rename(columns={"variant": "row"})
    totals["vetoed_pct"] = 100.0 * totals["vetoed_steps"] / totals["proximity_steps"].where(
        totals["proximity_steps"] > 0)
    order = {"row": {"paper": 0, "calibrated": 1}, "estimator": {name: i for i, name in enumerate(ESTIMATOR_ORDER)}}
    return totals.sort_values(["row", "estimator", "perturbation", "strength"], ignore_index=True, key=lambda c: (
        c.map(order[c.name]).fillna(len(order[c.name])) if c.name in order else c))[columns]


def vetoes_markdown(vetoes: pd.DataFrame) -> str:
    """One row per gated rule, one column per setting: the vetoed share of its proximity firings (%)."""
    if vetoes.empty:
        return ""
    settings = list(dict.fromkeys(["unperturbed", *vetoes["setting"]]))
    names = {"calibrated": "calibrated", "paper": "paper's thresholds"}
    lines = ["| Rule | " + " | ".join(settings) + " |", "|:--|" + "--:|" * len(settings)]
    for (row, estimator), rows in vetoes.groupby(["row", "estimator"], sort=False):
        share = dict(zip(rows["setting"], rows["vetoed_pct"]))
        cells = ["–" if not math.isfinite(share.get(name, math.nan)) else f"{share[name]:.1f}" for name in settings]
        lines.append(f"| {estimator_label(estimator)}, {names.get(row, row)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


@register_section(KIND, "table3_ablation")
def table3_ablation_section(context: ReportContext) -> str:
    safety = safety_records(context)
    if safety.empty:
        return ""
    safety = _with_rule(safety)
    if not safety["rule"].isin(["proximity-only", "uncertainty-only"]).any():
        return ""
    sensing = _ablation_sensing(safety, context)
    view = ablation_records(safety, sensing, _run_budget(context))
    prevented = prevented_frame(view)
    paired = paired_frame(view)
    decisions = decisions_frame(view)
    write_table_atomic(prevented, context.out_dir / "table3_ablation.csv")
    write_table_atomic(paired, context.out_dir / "table3_ablation_paired.csv")
    write_table_atomic(decisions, context.out_dir / "table3_ablation_decisions.csv")
    vetoes = vetoes_frame(view)
    write_table_atomic(vetoes, context.out_dir / "table3_ablation_vetoes.csv")
    markdown = ablation_markdown(prevented, paired, decisions)
    write_text_atomic(context.out_dir / "table3_ablation.md", markdown + "\n")
    pooled = paired[paired["column"] == "all"]
    lines = [
        "## Table 3 ablation: does the uncertainty condition change the safety decision?",
        "",
        "The paper's rule (eq. (10)) hands control to the cautious controller when the policy is uncertain AND "
        "close to a person AND approaching. Each rule below is calibrated under the same false-activation budget "
        f"({100 * _run_budget(context):g} % of unperturbed steps) on the same calibration episodes, and all play "
        f"the same evaluation episodes as Table 3, with the {SENSING_LABELS.get(sensing, sensing)} sensing (Table "
        "3's primary row). Proximity only drops the uncertainty condition, uncertainty only drops c_prox (c_ap stays: "
        "it is no distance test but the paper's 'moving away averts the risk'); the paper's thresholds as printed "
        "are shown uncalibrated.",
        "",
        "Prevented collisions: as in Table 3 (mean ± std over the repeats). *Vetoed by uncertainty*: steps where "
        "the rule's own proximity terms fired (c_prox ∧ c_ap) but its uncertainty condition did not, so eq. (10) "
        "left the policy in control. *Episodes with other hand-overs*: episodes where the fallback drove on other "
        "steps than proximity-only's on the same episode seed. *Δ prevented*: paired by episode over all perturbed "
        "episodes, (collisions only proximity-only had − collisions only this rule had) in points of the plain "
        "policy's collisions, with the exact conditional (McNemar / Clopper-Pearson) interval, Bonferroni-adjusted "
        f"over the {len(pooled)} rows compared ({ABLATION_CONFIDENCE:.0%} family-wise). Verdict of 'this rule "
        "prevents more collisions than proximity-only': holds / does not hold when the interval lies above / below "
        "0, cannot tell at this budget when it contains 0.",
        "",
        markdown,
        "",
    ]
    if not paired.empty and (paired["column"] != "all").any():
        lines += ["Per column, and over the unperturbed episodes, where the false activation is measured (ours; "
                  "Bonferroni over rows × columns; cells: Δ points [CI] (won vs lost), verdict):", "",
                  paired_markdown(paired[paired["column"] != "all"]), ""]
    if not vetoes.empty:
        lines += ["Where the uncertainty condition vetoes (% of the rule's proximity firings it vetoed, per setting; "
                  "the false activation is measured on the unperturbed episodes):", "", vetoes_markdown(vetoes), ""]
    lines.append("Data: [table3_ablation.csv](table3_ablation.csv) (prevented per column), "
                 "[table3_ablation_paired.csv](table3_ablation_paired.csv) (paired comparisons, p-values), "
                 "[table3_ablation_decisions.csv](table3_ablation_decisions.csv) (hand-over decisions), "
                 "[table3_ablation_vetoes.csv](table3_ablation_vetoes.csv) (vetoes per setting).")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Table 3's trade-off curve: prevented collisions vs false activation over the calibration budget
# --------------------------------------------------------------------------------------------------------------

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
    safety = _with_rule(safety)
    curve = safety[(safety["sensing"] == sensing) & (safety["variant"] == "calibrated")
                   & (safety["rule"] != "uncertainty-only")]
    # every point on the repeats all of them played (a trade-off budget may be played on the first repeats only)
    played = [set(rows["repeat"]) for _, rows in curve.groupby(["estimator", "rule", "budget"])]
    if played:
        safety = safety[safety["repeat"].isin(set.intersection(*played))]
    mine = safety[(safety["sensing"] == sensing) & (safety["variant"] != "none")]
    groups = {c: k for c, k in _table3_groups(safety["perturbation"]).items() if c in PAPER_TABLE3_COLUMNS}
    rows = []
    keyed = mine.assign(budget=mine["budget"].fillna(-1.0))
    for (estimator, rule, variant, budget), frame in keyed.groupby(["estimator", "rule", "variant", "budget"],
                                                                    sort=False):
        if variant == "calibrated" and rule == "uncertainty-only":
            continue
        plain_rows = safety[(safety["estimator"] == estimator) & (safety["variant"] == "none")]
        runs = safety.loc[frame.index]
        hot = _perturbed(runs)
        plain_hot = plain_rows[_perturbed(plain_rows)]
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
        cold = _rates(runs[~hot], True)
        rows.append({"estimator": estimator, "rule": rule, "thresholds": variant,
                     "budget": math.nan if budget < 0 else float(budget),
                     "false_activation_pct": cold["activation"],
                     "activation_pct": _rates(runs[hot], True)["activation"],
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
    plt = _pyplot()
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
        lines.append("| " + " | ".join([label, budget, _f(row["false_activation_pct"], 2), _f(row["prevented_pct"], 1),
                                        _f(row["prevented_pct_pooled"], 1), _f(row["prevented_pct_worst"], 1)]) + " |")
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


@register_section(KIND, "table3_tradeoff")
def table3_tradeoff_section(context: ReportContext) -> str:
    safety = safety_records(context)
    if safety.empty:
        return ""
    safety = _with_rule(safety)
    sensing = _ablation_sensing(safety, context)
    frame = tradeoff_frame(safety, sensing) if sensing is not None else pd.DataFrame()
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


# --------------------------------------------------------------------------------------------------------------
# Calibrated thresholds
# --------------------------------------------------------------------------------------------------------------

def _calibrations(context: ReportContext) -> dict[tuple[str, str, str, float], dict[str, Any]]:
    """(estimator, sensing, rule, budget) -> calibration report: each unit's ``calibration.json`` (its main budget,
    NaN in the key) and ``calibration-budget<b>.json`` (the trade-off budgets). Files from before the sensing
    choice are ``perceived``, from before the rule variants the paper's rule, named by their directory."""
    if "uncertainty_calibration" not in context._cache:
        found = {}
        for pattern in ("calibrate*/*/calibration.json", "calibrate*/*/calibration-budget*.json"):
            for path in _record_files(context, pattern):
                try:  # bounded (size, depth), never through a link: an unsound file is left out, the report goes on
                    data = read_json(path, follow_links=False)
                    budget = (math.nan if path.name == "calibration.json"
                              else float(data.get("false_activation_budget", math.nan)))
                except (OSError, UntrustedInputError, AttributeError, TypeError, ValueError):
                    continue
                found[(str(data.get("estimator", path.parent.name)), str(data.get("sensing", "perceived")),
                       str(data.get("conditions", "paper")), budget)] = data
        context._cache["uncertainty_calibration"] = found
    return context._cache["uncertainty_calibration"]


#: How the calibration table names each rule variant's calibrated thresholds.
RULE_LABELS = {"paper": "calibrated", "proximity-only": "calibrated, proximity only",
               "uncertainty-only": "calibrated, uncertainty only"}


def _number_text(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return "–" if value is None else str(value)
    if isinstance(value, (int, float)):
        return "∞" if value == math.inf else f"{value:.4g}"
    return str(value)


@register_section(KIND, "calibration")
def calibration_section(context: ReportContext) -> str:
    from socnav.safety.calibration import SEARCHED_KEYS

    found = _calibrations(context)
    if not found:
        return ""
    keys = ["lambda_ep", "lambda_feat", "lambda_prox", "beta1"]
    rows = []
    for estimator in _ordered((key[0] for key in found), [NO_ESTIMATOR, *ESTIMATOR_ORDER]):
        mine = [key for key in found if key[0] == estimator]
        for rule in _ordered((key[2] for key in mine), list(RULE_LABELS)):
            for sensing in _ordered((key[1] for key in mine if key[2] == rule), SENSING_ORDER):
                budgets = sorted((key[3] for key in mine if key[1:3] == (sensing, rule)),
                                 key=lambda b: (not math.isnan(b), b))  # the main budget first
                for budget in budgets:
                    data = found[(estimator, sensing, rule, budget)]
                    thresholds = dict(data.get("thresholds")) if isinstance(data.get("thresholds"), dict) else {}
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
                                 # files from before the hold have none: the per-step rule
                                 "hold_steps": thresholds.get("hold_steps", 0) if thresholds else None,
                                 "prevented_fraction": data.get("prevented_fraction"),
                                 "false_activation_rate": data.get("false_activation_rate")})
        if estimator in _PAPER_THRESHOLDS:
            rows.append({"estimator": estimator, "source": "paper", "sensing": None, "rule": "paper", "budget": None,
                         **dict(zip(keys, _PAPER_THRESHOLDS[estimator])), "proximity": None, "hold_steps": 0,
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
        "| Approach | Thresholds | λ_ep | λ_f | λ_prox | β1 | c_prox | Hold | Calibration prevented | Calibration false activation |",
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


# Registered last, so its section follows Table 2's and Table 3's in the report.
from socnav.experiments import uncertainty_information  # noqa: E402,F401  (its section registers on import)
