"""The records the uncertainty kind's report reads from a run directory -- study steps and episodes, safety episodes,
calibrated thresholds -- found by globbing, read once per report, with the columns every section relies on.

Records read (Parquet; files inside a planned unit that is not finished are left out, as the report header says):

- ``study/<estimator>/<perturbation>/steps.parquet``: one row per environment step (raw ``u_*`` and windowed
  ``w_u_*`` uncertainties, ``nearest_gap``, ``outcome`` on an episode's last step), keyed by ``strength`` and
  ``episode`` (episode ids restart at every strength); ``episodes.parquet`` next to it: one row per episode;
- ``safety/<estimator>/<perturbation>/episodes.parquet``: one row per episode, keyed by ``strength``, ``repeat``
  (an independent block of episode seeds), ``variant`` (``none`` = plain policy, ``paper`` / ``calibrated`` =
  the safety layer with those thresholds; every variant plays the same episode seeds as ``none``) and
  ``sensing`` (``perceived`` / ``true``: what the layer's proximity terms and fallback read; empty for ``none``;
  records without the column read as ``perceived``); with the ablation also ``rule`` (``Thresholds.conditions``
  of the rule played; records without it: ``paper``), ``budget`` (the false-activation budget a calibrated rule
  was chosen for; NaN for the paper's thresholds) and the per-episode ``proximity_steps``, ``vetoed_steps`` and
  ``fallback_digest`` (`socnav.safety.FallbackCounter`); ``safety/none/<perturbation>/`` holds the proximity-only
  rule, which reads no uncertainty (``estimator`` ``none``);
- ``calibrate/<estimator>/calibration.json`` (``calibrate-true/<estimator>/`` for ``true`` sensing,
  ``.../<estimator>-uncertainty-only/`` and ``.../proximity-only/`` for the ablation, ``calibration-budget<b>.json``
  for a trade-off budget): the thresholds ``socnav calibrate`` chose and their scores.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from socnav.envs.perturbations import PERTURBATIONS, strength_zero
from socnav.experiments.registry import ReportContext, unit_dir
from socnav.io import UntrustedInputError, read_json, read_table
from socnav.paper.labels import TABLE2_ROWS
from socnav.sim.metrics import METRIC_RECORD_COLUMNS

__all__ = [
    "RAW_COLUMNS", "SAFETY_COLUMNS", "STEP_COLUMNS", "STUDY_EPISODE_COLUMNS", "Calibrations", "calibrations",
    "perturbed_rows", "read_record_columns", "record_files", "safety_records", "sigma_zero", "study_episode_records",
    "study_summaries", "summarise_steps", "with_rule", "with_sensing",
]

#: Raw uncertainty columns of the study's step records, in Table 2's row order.
RAW_COLUMNS = list(TABLE2_ROWS)
STEP_COLUMNS = ["estimator", "perturbation", "strength", "episode", "step", *RAW_COLUMNS, "w_u_feat", "nearest_gap",
                "outcome"]
SAFETY_COLUMNS = ["estimator", "perturbation", "strength", "repeat", "variant", "sensing", "seed", "outcome",
                  "length", "time_to_goal", "duration", "fallback_steps",
                  # with the ablation (socnav.paper.uncertainty.units.ABLATION_COLUMNS)
                  "rule", "budget", "proximity_steps", "vetoed_steps", "fallback_digest",
                  # every metric's record columns (socnav.sim.metrics; a record file may hold only some of them)
                  "return", "path_length", "min_gap", "intrusion_events", "disturbance", *METRIC_RECORD_COLUMNS]
#: The study's per-episode record columns the metrics read (table2_metrics.csv).
STUDY_EPISODE_COLUMNS = ["estimator", "perturbation", "strength", "episode", "outcome", "return", "length",
                         "duration", "time_to_goal", "path_length", "min_gap", "intrusion_steps", "intrusion_events",
                         "disturbance", *METRIC_RECORD_COLUMNS]
#: (estimator, sensing, rule, budget) -> the calibration report of that unit and budget.
Calibrations = dict[tuple[str, str, str, float], dict[str, Any]]


def record_files(context: ReportContext, pattern: str) -> list[Path]:
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


def read_record_columns(path: Path, wanted: Sequence[str]) -> pd.DataFrame:
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
    steps = steps.sort_values([*keys, "episode", "step"], kind="stable", ignore_index=True)
    grouped = steps.groupby([*keys, "episode"], sort=True)
    means = grouped[raw].mean()
    means["steps"] = grouped.size()
    episode_means = means.reset_index()
    critical = []
    if "w_u_feat" in steps and "nearest_gap" in steps:
        for key, group in steps.groupby(keys, sort=True):
            group = group.reset_index(drop=True)
            group["nearest_gap"] = group["nearest_gap"].astype(float).fillna(np.inf)
            rows = critical_steps(group, column="w_u_feat")
            critical.append(rows.assign(**dict(zip(keys, key, strict=True)))[[*keys, "episode", "collided", "value"]])
    columns = [*keys, "episode", "collided", "value"]
    critical_frame = pd.concat(critical, ignore_index=True) if critical else pd.DataFrame(columns=columns)
    return episode_means, critical_frame


def _summarise_study(context: ReportContext) -> tuple[pd.DataFrame, pd.DataFrame]:
    means, critical = [], []
    for path in record_files(context, "study/*/*/steps.parquet"):
        steps = read_record_columns(path, STEP_COLUMNS)
        if steps.empty:
            continue
        episode_means, rows = summarise_steps(steps)
        means.append(episode_means)
        critical.append(rows)
    return (pd.concat(means, ignore_index=True) if means else pd.DataFrame(),
            pd.concat(critical, ignore_index=True) if critical else pd.DataFrame())


def study_summaries(context: ReportContext) -> tuple[pd.DataFrame, pd.DataFrame]:
    """`summarise_steps` of every study file (read one at a time, so only the summaries are held), cached."""
    result: tuple[pd.DataFrame, pd.DataFrame] = context.cached("uncertainty_study",
                                                               lambda: _summarise_study(context))
    return result


def study_episode_records(context: ReportContext) -> pd.DataFrame:
    """Every study episode record (:data:`STUDY_EPISODE_COLUMNS` the files hold); empty without any."""
    frames = [read_record_columns(path, STUDY_EPISODE_COLUMNS)
              for path in record_files(context, "study/*/*/episodes.parquet")]
    frames = [frame for frame in frames if not frame.empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _read_safety(context: ReportContext) -> pd.DataFrame:
    frames = [read_record_columns(path, SAFETY_COLUMNS)
              for path in record_files(context, "safety/*/*/episodes.parquet")]
    frames = [frame for frame in frames if not frame.empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def safety_records(context: ReportContext) -> pd.DataFrame:
    """Every safety episode record (estimator, perturbation, strength, repeat, variant, outcome, ...), cached."""
    result: pd.DataFrame = context.cached("uncertainty_safety", lambda: _read_safety(context))
    return result


def _read_calibrations(context: ReportContext) -> Calibrations:
    found = {}
    for pattern in ("calibrate*/*/calibration.json", "calibrate*/*/calibration-budget*.json"):
        for path in record_files(context, pattern):
            try:  # bounded (size, depth), never through a link: an unsound file is left out, the report goes on
                data = read_json(path, follow_links=False)
                budget = (math.nan if path.name == "calibration.json"
                          else float(data.get("false_activation_budget", math.nan)))
            except (OSError, UntrustedInputError, AttributeError, TypeError, ValueError):
                continue
            found[(str(data.get("estimator", path.parent.name)), str(data.get("sensing", "perceived")),
                   str(data.get("conditions", "paper")), budget)] = data
    return found


def calibrations(context: ReportContext) -> Calibrations:
    """(estimator, sensing, rule, budget) -> calibration report: each unit's ``calibration.json`` (its main budget,
    NaN in the key) and ``calibration-budget<b>.json`` (the trade-off budgets), cached. A file without
    ``sensing`` is ``perceived``, without ``conditions`` the paper's rule, without ``estimator`` named by its
    directory."""
    result: Calibrations = context.cached("uncertainty_calibration", lambda: _read_calibrations(context))
    return result


def with_sensing(safety: pd.DataFrame) -> pd.DataFrame:
    """The records with a ``sensing`` column: records without one are the layer reading the observation."""
    if "sensing" in safety:
        return safety
    return safety.assign(sensing=np.where(safety["variant"] == "none", "", "perceived"))


def with_rule(safety: pd.DataFrame) -> pd.DataFrame:
    """The records with ``sensing``, ``rule`` and ``budget`` columns: records of units without the ablation are
    the paper's rule (eq. (10)) and carry no budget (NaN)."""
    safety = with_sensing(safety)
    if "rule" not in safety:
        safety = safety.assign(rule=np.where(safety["variant"] == "none", "", "paper"))
    if "budget" not in safety:
        safety = safety.assign(budget=np.nan)
    return safety


def sigma_zero(perturbation: str, strengths: Iterable[float]) -> float:
    """The unperturbed strength of a registered perturbation type, or the smallest strength of an unknown type."""
    if perturbation in PERTURBATIONS:
        return strength_zero(perturbation)
    return float(min(strengths))


def perturbed_rows(frame: pd.DataFrame) -> np.ndarray:
    """Rows whose strength is not the unperturbed strength of their perturbation type."""
    mask = np.ones(len(frame), dtype=bool)
    for perturbation, index in frame.groupby("perturbation", sort=False).indices.items():
        strengths = frame["strength"].to_numpy(float)[index]
        mask[index] = ~np.isclose(strengths, sigma_zero(perturbation, strengths))
    return mask
