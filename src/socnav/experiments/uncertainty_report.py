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
  records without the column were written before the choice existed and read as ``perceived``);
- ``calibrate/<estimator>/calibration.json`` (``calibrate-true/<estimator>/`` for ``true`` sensing): the thresholds
  ``socnav calibrate`` chose and their proxy scores.

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
  that type; mean +- std (ddof=0) over the repeats where ``C_none > 0``.
- **Cost**: fallback activation rate (fallback steps / steps) in perturbed episodes, false-activation rate (the
  same in unperturbed episodes), success and collision rates, mean time to goal of successful episodes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import pandas as pd

from socnav.envs.perturbations import PAPER_GRIDS, PERTURBATION_FIELDS, strength_zero
from socnav.experiments.registry import ReportContext, register_section, unit_dir
from socnav.io import read_table, save_figure, write_table_atomic, write_text_atomic

__all__ = [
    "KIND", "cost_frame", "cost_markdown", "plot_feature_collisions", "plot_uncertainty_vs_strength",
    "prevented_frame", "prevented_markdown", "safety_records", "strength_curves", "study_summaries",
    "summarise_steps", "table2_frame", "table2_markdown",
]

KIND = "uncertainty"

ESTIMATOR_LABELS = {"mc": "MC-dropout", "ensemble": "Ensemble"}
ESTIMATOR_SHORT = {"mc": "MC", "ensemble": "Ens"}
ESTIMATOR_ORDER = ["mc", "ensemble"]
PERTURBATION_ORDER = list(PERTURBATION_FIELDS)
PERTURBATION_LABELS = {"observation_noise": "Observation noise", "heading_noise": "Heading noise",
                       "speed_noise": "Speed noise", "faster_humans": "Faster humans", "more_humans": "More humans",
                       "action_noise": "Action noise (heading + speed)"}
STRENGTH_LABELS = {"observation_noise": "observation noise σ_obs", "heading_noise": "heading noise σ_head",
                   "speed_noise": "speed noise s (factor U(1 − s, 1))", "faster_humans": "human speed factor l_vel",
                   "more_humans": "agents N (robot included)"}
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
                  "length", "time_to_goal", "duration", "fallback_steps"]
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
#: Our perturbation type -> the paper's column ("action noise" is heading and speed noise, "velocity" faster humans).
PAPER_COLUMN = {"observation_noise": "obs", "heading_noise": "action", "speed_noise": "action",
                "action_noise": "action", "faster_humans": "velocity", "more_humans": "humans"}
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
    """The unperturbed strength of a perturbation type (PAPER_GRIDS), or the smallest strength of an unknown type."""
    if perturbation in PAPER_GRIDS:
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
        "each episode's mean per-step (raw) uncertainty. Bold: the larger of MC-dropout (MC) and ensemble (Ens) per "
        f"uncertainty and perturbation. {ZERO}: u_σ(0) = 0, the ratio is undefined (the estimator reports no "
        f"uncertainty of that kind in the least perturbed world); {MISSING}: not recorded, or a single strength.",
        "",
        markdown,
        "",
    ]
    lines += _strength_notes(table)
    compared = _mc_vs_ensemble(table)
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
    return "\n".join(lines)


def _strength_notes(table: pd.DataFrame) -> list[str]:
    lines = []
    for perturbation in _ordered(table["perturbation"], PERTURBATION_ORDER):
        rows = table[table["perturbation"] == perturbation]
        parts = []
        for estimator in _ordered(rows["estimator"], ESTIMATOR_ORDER):
            first = rows[rows["estimator"] == estimator].iloc[0]
            parts.append(f"{estimator_label(estimator)} σ(0) = {first['sigma0']:g} ({first['episodes_sigma0']} "
                         f"episode(s)), σ(max) = {first['sigma_max']:g} ({first['episodes_sigma_max']} episode(s))")
            if perturbation in PAPER_GRIDS and not math.isclose(first["sigma0"], strength_zero(perturbation)):
                parts[-1] += f" — note: the unperturbed strength {strength_zero(perturbation):g} was not recorded"
        lines.append(f"- {perturbation_label(perturbation)}: " + "; ".join(parts))
    return lines + [""] if lines else []


def _mc_vs_ensemble(table: pd.DataFrame) -> str:
    """How often MC-dropout's sensitivity exceeds the ensemble's (the paper: 19 of its 20 cells)."""
    if not {"mc", "ensemble"} <= set(table["estimator"]):
        return ""
    pivot = table.pivot_table(index=["uncertainty", "perturbation"], columns="estimator", values="sensitivity",
                              aggfunc="first").dropna(subset=["mc", "ensemble"])
    if pivot.empty:
        return ""
    larger = int((pivot["mc"] > pivot["ensemble"]).sum())
    return (f"MC-dropout responds more strongly than the ensemble in {larger} of {len(pivot)} cells where both are "
            "defined (paper: 19 of 20).")


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


def _table3_groups(perturbations: Iterable[str]) -> dict[str, list[str]]:
    """Table 3 columns: each perturbation type, plus the paper's pooled action noise (after speed noise) when both
    heading and speed noise are there."""
    present = _ordered(perturbations, PERTURBATION_ORDER)
    groups: dict[str, list[str]] = {}
    for perturbation in present:
        groups[perturbation] = [perturbation]
        if perturbation == "speed_noise" and "heading_noise" in present:
            groups["action_noise"] = ["heading_noise", "speed_noise"]
    return groups


def _with_sensing(safety: pd.DataFrame) -> pd.DataFrame:
    """The records with a ``sensing`` column: records from before the choice existed read the observation."""
    if "sensing" in safety:
        return safety
    return safety.assign(sensing=np.where(safety["variant"] == "none", "", "perceived"))


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
    ``C_none > 0`` (NaN if there is none). ``collisions_*`` are the totals over the repeats used."""
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


def prevented_markdown(table: pd.DataFrame) -> str:
    """Rows: estimator x thresholds (x sensing, named when not only ``perceived``), then the paper's row of that
    estimator; a column per perturbation type (and pooled action noise). ``—``: no collision without the safety
    layer; ``(k of n)``: only k repeats had one."""
    table = table if "sensing" in table else table.assign(sensing="perceived")
    columns = _ordered(table["column"], PERTURBATION_ORDER[:3] + ["action_noise"] + PERTURBATION_ORDER[3:])
    header = ["Approach", "Thresholds"] + [perturbation_label(c) for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * len(columns)) + "|"]
    indexed = table.set_index(["estimator", "variant", "sensing", "column"])
    show_sensing = _show_sensing(table[["variant", "sensing"]].itertuples(index=False, name=None))
    for estimator in _ordered(table["estimator"], ESTIMATOR_ORDER):
        for variant, sensing in _safe_variants(table[table["estimator"] == estimator]):
            row = [estimator_label(estimator), variant_label(variant, sensing, show_sensing)]
            for column in columns:
                key = (estimator, variant, sensing, column)
                if key not in indexed.index:
                    row.append(MISSING)
                    continue
                cell = indexed.loc[key]
                if cell["repeats_defined"] == 0:
                    row.append(ZERO)
                    continue
                text = f"{cell['prevented_mean']:.1f} ± {cell['prevented_std']:.1f}"
                if cell["repeats_defined"] < cell["repeats"]:
                    text += f" ({int(cell['repeats_defined'])} of {int(cell['repeats'])})"
                row.append(text)
            lines.append("| " + " | ".join(row) + " |")
        paper = [paper_table3(column, estimator) for column in columns]
        if any(math.isfinite(mean) for mean, _ in paper):
            cells = [f"*{mean:.0f} ± {std:.0f}*" if math.isfinite(mean) else MISSING for mean, std in paper]
            lines.append(f"| {estimator_label(estimator)} | *paper's Table III* | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _unpaired_groups(safety: pd.DataFrame) -> int:
    """(estimator, perturbation, strength, repeat, variant) groups whose episode seeds differ from 'none''s."""
    if "seed" not in safety or safety.empty:
        return 0
    keys = ["estimator", "perturbation", "strength", "repeat"]
    mismatches = 0
    # each sensing of a variant is its own run of the episodes: compare each with the plain policy's seeds
    variant_keys = ["variant", "sensing"] if "sensing" in safety else ["variant"]
    for _, group in safety.groupby(keys, sort=False):
        plain = group[group["variant"] == "none"]
        if plain.empty:
            continue
        reference = sorted(plain["seed"].tolist())
        for _, runs in group[group["variant"] != "none"].groupby(variant_keys):
            mismatches += sorted(runs["seed"].tolist()) != reference
    return mismatches


@register_section(KIND, "table3")
def table3_section(context: ReportContext) -> str:
    safety = safety_records(context)
    if safety.empty:
        return ""
    table = prevented_frame(safety)
    write_table_atomic(table, context.out_dir / "table3.csv")
    markdown = prevented_markdown(table) if not table.empty else "No safe variant with its plain-policy runs yet."
    write_text_atomic(context.out_dir / "table3.md", markdown + "\n")
    repeats = safety["repeat"].nunique()
    lines = [
        "## Table 3: prevented collisions with safe action selection",
        "",
        "Prevented collisions (%) = 100 · (C_none − C_safe) / C_none per perturbation type, C the collisions over "
        "all perturbed strengths of that type (the unperturbed strength left out), the plain policy and the safety "
        f"layer on identical episode seeds; mean ± standard deviation over {repeats} repeat(s) (independent seed "
        f"blocks). {ZERO}: the plain policy did not collide, nothing to prevent; (k of n): only k repeats had a "
        "collision to prevent. Action noise (heading + speed) pools both noise types, as the paper's *action noise* "
        "column; the paper's *velocity* is our faster humans. Italic: the paper's values.",
        "",
    ]
    if _show_sensing(table[["variant", "sensing"]].itertuples(index=False, name=None)):
        lines += ["*Perceived* / *true state*: what the layer's proximity terms (c_prox, c_ap) and cautious fallback "
                  "read — the robot's observation, observation noise included, or the simulator's noise-free state "
                  "(a separate safety sensor); the policy and the uncertainty estimates always see the observation. "
                  "Without observation noise both read the same.", ""]
    lines += [markdown, ""]
    unpaired = _unpaired_groups(safety)
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
    n = len(frame)
    goal = frame["outcome"] == "goal"
    time = frame["time_to_goal"] if "time_to_goal" in frame else frame.get("duration")
    activation = math.nan
    if layer and n and "fallback_steps" in frame and frame["length"].sum() > 0:
        activation = 100.0 * float(frame["fallback_steps"].sum()) / float(frame["length"].sum())
    return {
        "episodes": n,
        "activation": activation,
        "success": 100.0 * float(goal.mean()) if n else math.nan,
        "collision": 100.0 * float((frame["outcome"] == "collision").mean()) if n else math.nan,
        "time": float(time[goal].astype(float).mean()) if time is not None and goal.any() else math.nan,
    }


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
    table = cost_frame(safety)
    write_table_atomic(table, context.out_dir / "table3_cost.csv")
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
    lines.append("Data: [table3_cost.csv](table3_cost.csv).")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Calibrated thresholds
# --------------------------------------------------------------------------------------------------------------

def _calibrations(context: ReportContext) -> dict[tuple[str, str], dict[str, Any]]:
    """(estimator, sensing) -> calibration report; files from before the sensing choice are ``perceived``."""
    if "uncertainty_calibration" not in context._cache:
        found = {}
        for path in _record_files(context, "calibrate*/*/calibration.json"):
            try:
                data = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
            if isinstance(data, dict):
                found[(path.parent.name, str(data.get("sensing", "perceived")))] = data
        context._cache["uncertainty_calibration"] = found
    return context._cache["uncertainty_calibration"]


def _number_text(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return "–" if value is None else str(value)
    if isinstance(value, (int, float)):
        return "∞" if value == math.inf else f"{value:.4g}"
    return str(value)


@register_section(KIND, "calibration")
def calibration_section(context: ReportContext) -> str:
    found = _calibrations(context)
    if not found:
        return ""
    keys = ["lambda_ep", "lambda_feat", "lambda_prox", "beta1"]
    rows = []
    for estimator in _ordered((e for e, _ in found), ESTIMATOR_ORDER):
        for sensing in _ordered((s for e, s in found if e == estimator), SENSING_ORDER):
            data = found[(estimator, sensing)]
            thresholds = dict(data.get("thresholds")) if isinstance(data.get("thresholds"), dict) else {}
            for key in ("lambda_ep", "lambda_feat"):  # JSON has no infinity: null is a condition that is off
                if key in thresholds and thresholds[key] is None:
                    thresholds[key] = math.inf
            source = "calibrated" if sensing == "perceived" else f"calibrated ({SENSING_LABELS.get(sensing, sensing)})"
            rows.append({"estimator": estimator, "source": source, "sensing": sensing,
                         **{k: thresholds.get(k) for k in keys}, "proximity": thresholds.get("proximity"),
                         # files from before the hold have none: the per-step rule
                         "hold_steps": thresholds.get("hold_steps", 0) if thresholds else None,
                         "prevented_fraction": data.get("prevented_fraction"),
                         "false_activation_rate": data.get("false_activation_rate")})
        if estimator in _PAPER_THRESHOLDS:
            rows.append({"estimator": estimator, "source": "paper", "sensing": None,
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
        "Hold: steps the fallback keeps control after the rule last fired (0: the paper's per-step rule).",
        "",
        "| Approach | Thresholds | λ_ep | λ_f | λ_prox | β1 | c_prox | Hold | Calibration prevented | Calibration false activation |",
        "|:--|:--|--:|--:|--:|--:|:--|--:|--:|--:|",
    ]
    for row in rows:
        lines.append("| " + " | ".join([estimator_label(row["estimator"]), row["source"]]
                                       + [_number_text(row[k]) for k in keys]
                                       + [row["proximity"] or "abs-relative-speed", _number_text(row["hold_steps"])]
                                       + [_number_text(row["prevented_fraction"]),
                                          _number_text(row["false_activation_rate"])]) + " |")
    lines += ["", "Data: [calibration.csv](calibration.csv)."]
    return "\n".join(lines)
