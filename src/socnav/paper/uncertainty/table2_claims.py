"""The paper's Table 2 claims tested on the study records, each with a magnitude and a bootstrap interval over
episodes; the claims' table and report section.

The claims: MC-dropout responds to perturbations more strongly than the ensemble, heading uncertainty rises while
speed uncertainty stays flat, more humans cause the highest uncertainty. The intervals come from the episode-cluster
bootstrap of `socnav.paper.uncertainty.information` (``cluster_counts``, ``percentile_interval``),
Bonferroni-adjusted over each claim's tests.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.experiments.statistics import CANNOT_TELL, DOES_NOT_HOLD, HOLDS, verdict
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.labels import (
    BEYOND_PAPER,
    ESTIMATOR_ORDER,
    PERTURBATION_ORDER,
    TABLE2_ROWS,
    estimator_label,
    perturbation_label,
    present_in_order,
)
from socnav.paper.uncertainty.information import bonferroni_confidence, cluster_counts, percentile_interval
from socnav.paper.uncertainty.records import RAW_COLUMNS, study_summaries

__all__ = [
    "CLAIM_COLUMNS", "CLAIM_HEADING_RISES", "CLAIM_MC_STRONGER", "CLAIM_MORE_HUMANS", "CLAIM_SHORT", "CLAIM_TESTS",
    "TABLE2_CONFIDENCE", "TABLE2_RESAMPLES", "UNCERTAINTY_KINDS", "claims_summary", "heading_vs_speed_frame",
    "mc_vs_ensemble_frame", "mc_vs_ensemble_sentence", "more_humans_frame", "table2_claims", "table2_claims_frame",
    "table2_claims_markdown", "table2_claims_section",
]


#: Resamples of the Table 2 claims: a Bonferroni level over ~25 tests leaves 0.1 % per tail, ~10 draws there.
TABLE2_RESAMPLES = 10_000
TABLE2_CONFIDENCE = 0.95  # family-wise, per claim
CLAIM_MC_STRONGER = "MC-dropout responds to perturbations more strongly than the ensemble, for every uncertainty"
CLAIM_HEADING_RISES = "Heading uncertainty rises with the perturbation while speed uncertainty stays flat"
CLAIM_MORE_HUMANS = "More humans cause the highest uncertainty"
CLAIM_TESTS = {
    CLAIM_MC_STRONGER: "abs(ΔU/Δσ) of MC-dropout − abs(ΔU/Δσ) of the ensemble (same episodes)",
    CLAIM_HEADING_RISES: "rise of the heading uncertainty − abs(rise of the speed uncertainty), "
                         "rise = u_σ(max) − u_σ(0)",
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
    cells = []
    for perturbation in present_in_order(episode_means["perturbation"], PERTURBATION_ORDER):
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
    tests = []
    for estimator in present_in_order(episode_means["estimator"], ESTIMATOR_ORDER):
        mine = episode_means[episode_means["estimator"] == estimator]
        for kind, (heading, speed) in UNCERTAINTY_KINDS.items():
            if heading not in mine or speed not in mine:
                continue
            for perturbation in present_in_order(mine["perturbation"], PERTURBATION_ORDER):
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
    tests = []
    for estimator in present_in_order(episode_means["estimator"], ESTIMATOR_ORDER):
        mine = episode_means[episode_means["estimator"] == estimator]
        perturbations = present_in_order(mine["perturbation"], PERTURBATION_ORDER)
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
               episodes: int, verdict_text: str, detail: str) -> dict[str, Any]:
    return {"claim": claim, "test": CLAIM_TESTS[claim], "estimator": estimator, "perturbation": perturbation,
            "uncertainty": uncertainty, "estimate": interval.estimate, "low": interval.low, "high": interval.high,
            "confidence": level, "episodes": episodes, "verdict": verdict_text, "detail": detail}


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


def _claims_of_run(context: ReportContext) -> tuple[pd.DataFrame, pd.DataFrame]:
    episode_means, _ = study_summaries(context)
    claims = table2_claims_frame(episode_means) if not episode_means.empty else pd.DataFrame(columns=CLAIM_COLUMNS)
    return claims, claims_summary(claims)


def table2_claims(context: ReportContext) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(claim tests, summary) of the run's study records, cached (table2 and table2_claims both use them)."""
    result: tuple[pd.DataFrame, pd.DataFrame] = context.cached("table2_claims", lambda: _claims_of_run(context))
    return result


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


def mc_vs_ensemble_sentence(claims: pd.DataFrame) -> str:
    """One sentence: in how many cells MC-dropout's |ΔU/Δσ| is larger than the ensemble's with an interval
    excluding 0, in how many we cannot tell and in how many the ensemble's is larger (the paper: MC larger in 19 of
    its 20 cells, point values)."""
    cells = claims[claims["claim"] == CLAIM_MC_STRONGER] if not claims.empty else claims
    if cells.empty:
        return ""
    count = cells["verdict"].value_counts()
    return (f"MC-dropout vs ensemble, |ΔU/Δσ| of MC − |ΔU/Δσ| of the ensemble per cell with a bootstrap interval "
            f"over paired episodes ({cells['confidence'].iloc[0]:.1%} per cell, Bonferroni over {len(cells)} "
            f"cells): MC-dropout larger in {count.get(HOLDS, 0)}, cannot tell in {count.get(CANNOT_TELL, 0)}, "
            f"ensemble larger in {count.get(DOES_NOT_HOLD, 0)} of the {len(cells)} cells where both are defined "
            "(the paper: MC larger in 19 of its 20, point values). Details: the Table 2 claims below.")


def table2_claims_section(context: ReportContext) -> str:
    """The claims' section: table2_claims.md/csv (empty without study records)."""
    claims, summary = table2_claims(context)
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
