"""Table 1 with confidence intervals over seeds, the aggregate score of each algorithm and ODV-PPO-Drop's
comparisons with every other algorithm, one family of tests (`socnav.experiments.statistics`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import save_figure, write_table_atomic, write_text_atomic
from socnav.paper.labels import algo_label, preferred_then_seen, scenario_label
from socnav.paper.table1.tables import ID_COLUMNS, TABLE1_METRICS, table1_seed_frame

if TYPE_CHECKING:
    pass


#: Metrics shown with intervals in table1_ci.md (table1_ci.csv has every Table 1 metric) -> decimals.
CI_MARKDOWN_METRICS = {"goal_pct": 1, "collision_pct": 1, "return_mean": 2}
#: The aggregate score: a policy's goal (success) rate in %, per training seed and (training, evaluation) scenario
#: cell. It is what the paper ranks its algorithms by, and unlike the return its scale is the same in every scenario.
AGGREGATE_SCORE = "goal_pct"
#: The paper's method, compared with every other algorithm of the run (PPO first).
REFERENCE_ALGO = "odv-ppo-drop"
#: Family-wise confidence of every table of verdicts (comparisons, claims): 1 - the family-wise error rate.
FAMILY_CONFIDENCE = 0.95
CI_COLUMNS = [*ID_COLUMNS, "metric", "n_seeds", "mean", "ci_low", "ci_high"]
COMPARISON_COLUMNS = ["algo", "baseline", "n_tasks", "n_policies", "n_policies_baseline", "difference",
                      "difference_low", "difference_high", "confidence", "df", "p_value", "p_holm", "improvement",
                      "improvement_low", "improvement_high", "verdict"]


def table1_ci_frame(per_seed: pd.DataFrame, confidence: float = 0.95) -> pd.DataFrame:
    """Per (training scenario, algorithm, evaluation scenario) and Table 1 metric: the mean over seeds and its
    Student t-interval over seeds (descriptive, not adjusted for the number of cells; NaN bounds with a single
    seed); ``per_seed`` from :func:`table1_seed_frame`."""
    from socnav.experiments.statistics import mean_interval

    rows = []
    for key, group in per_seed.groupby(ID_COLUMNS, sort=False):
        for metric in TABLE1_METRICS:
            interval = mean_interval(group[metric].to_numpy(float), confidence)
            rows.append({**dict(zip(ID_COLUMNS, key, strict=True)), "metric": metric, "n_seeds": len(group),
                         "mean": interval.estimate, "ci_low": interval.low, "ci_high": interval.high})
    return pd.DataFrame(rows, columns=CI_COLUMNS)


def table1_ci_markdown(ci: pd.DataFrame, algorithms: list[str] | None = None,
                       train_scenarios: list[str] | None = None, eval_scenarios: list[str] | None = None) -> str:
    """Table 1's layout with ``mean [low, high]`` cells for :data:`CI_MARKDOWN_METRICS` (nothing bold: which
    algorithm is best is the question the claims answer)."""
    algorithms = preferred_then_seen(ci["algo"], algorithms or [])
    train_scenarios = preferred_then_seen(ci["train_scenario"], train_scenarios or [])
    eval_scenarios = preferred_then_seen(ci["eval_scenario"], eval_scenarios or [])
    header = ["Training scenario", "Approach"]
    for scenario in eval_scenarios:
        header += [f"{scenario_label(scenario)}: {TABLE1_METRICS[m][0].replace(' (μ ± σ)', '')}"
                   for m in CI_MARKDOWN_METRICS]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * (len(header) - 2)) + "|"]
    indexed = ci.set_index([*ID_COLUMNS, "metric"])
    for train_scenario in train_scenarios:
        for index, algo in enumerate(algorithms):
            row = [scenario_label(train_scenario) if index == 0 else "", algo_label(algo)]
            for scenario in eval_scenarios:
                for metric, decimals in CI_MARKDOWN_METRICS.items():
                    key = (train_scenario, algo, scenario, metric)
                    if key not in indexed.index:
                        row.append("–")
                        continue
                    cell = indexed.loc[key]
                    row.append(interval_text(cell["mean"], cell["ci_low"], cell["ci_high"], decimals))
            lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def interval_text(mean: float, low: float, high: float, decimals: int) -> str:
    from socnav.experiments.statistics import Interval

    return Interval(float(mean), float(low), float(high)).text(decimals)


Cell = tuple[str, str]  # (training scenario, evaluation scenario)


def policy_cells(per_seed: pd.DataFrame, *algos: str) -> list[Cell]:
    """(training scenario, evaluation scenario) cells where every one of `algos` has at least one seed."""
    cells = [set(map(tuple, per_seed.loc[per_seed["algo"] == algo, ["train_scenario", "eval_scenario"]]
                     .drop_duplicates().to_numpy().tolist())) for algo in algos]
    common = set.intersection(*cells) if cells else set()
    order = per_seed[["train_scenario", "eval_scenario"]].drop_duplicates().itertuples(index=False, name=None)
    return [cell for cell in order if cell in common]


def policy_strata(per_seed: pd.DataFrame, algo: str, cells: list[Cell], score: str = AGGREGATE_SCORE
                  ) -> dict[str, np.ndarray]:
    """``algo``'s scores as strata of clusters: per training scenario of ``cells``, an array (policies, cells) --
    one row per training seed evaluated in every one of that scenario's cells (a seed missing a cell is left out:
    a policy is one unit, scored on the same cells as the others)."""
    strata = {}
    mine = per_seed[per_seed["algo"] == algo]
    for train_scenario in dict.fromkeys(train for train, _ in cells):
        evals = [evaluation for train, evaluation in cells if train == train_scenario]
        block = mine[mine["train_scenario"] == train_scenario].pivot_table(
            index="train_seed", columns="eval_scenario", values=score)
        if not set(evals) <= set(block.columns):
            continue
        block = block[evals].dropna()
        if len(block):
            strata[train_scenario] = block.to_numpy(float)
    return strata


def paired_policy_strata(per_seed: pd.DataFrame, algo_x: str, algo_y: str, cells: list[Cell],
                         score: str = AGGREGATE_SCORE) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """:func:`policy_strata` of two algorithms on the training scenarios both have policies in (same order)."""
    strata_x = policy_strata(per_seed, algo_x, cells, score)
    strata_y = policy_strata(per_seed, algo_y, cells, score)
    shared = [scenario for scenario in strata_x if scenario in strata_y]
    return [strata_x[s] for s in shared], [strata_y[s] for s in shared]


def aggregate_frame(per_seed: pd.DataFrame, algorithms: list[str] | None = None, score: str = AGGREGATE_SCORE,
                    confidence: float = 0.95, seed: int = 0) -> pd.DataFrame:
    """Per algorithm: the interquartile mean of ``score`` over all seeds x (training, evaluation) scenario cells and
    its cluster-bootstrap interval (policies resampled within each training scenario, each with all its cells;
    descriptive)."""
    from socnav.experiments.statistics import iqm_interval

    rows = []
    for algo in preferred_then_seen(per_seed["algo"], algorithms or []):
        cells = policy_cells(per_seed, algo)
        strata = list(policy_strata(per_seed, algo, cells, score).values())
        if not strata:
            continue
        interval = iqm_interval(strata, confidence, seed=seed)
        rows.append({"algo": algo, "score": score, "n_tasks": sum(s.shape[1] for s in strata),
                     "n_runs": sum(s.size for s in strata), "iqm": interval.estimate, "iqm_low": interval.low,
                     "iqm_high": interval.high,
                     "mean": float(np.mean(np.concatenate([s.mean(axis=0) for s in strata])))})
    return pd.DataFrame(rows, columns=["algo", "score", "n_tasks", "n_runs", "iqm", "iqm_low", "iqm_high", "mean"])


def comparison_frame(per_seed: pd.DataFrame, reference: str = REFERENCE_ALGO, algorithms: list[str] | None = None,
                     score: str = AGGREGATE_SCORE, confidence: float = FAMILY_CONFIDENCE, seed: int = 0
                     ) -> pd.DataFrame:
    """The claims "``reference`` scores higher than B" for every other algorithm B (PPO first), over the cells both
    were evaluated in, as one family: stratified Welch test on per-policy means (strata: training scenarios), the
    difference of ``score`` (points) with its Bonferroni-level interval, Holm-adjusted verdicts, and the probability
    of improvement with its cluster-bootstrap interval (descriptive)."""
    from socnav.experiments.statistics import compare_family

    if reference not in set(per_seed["algo"]):
        return pd.DataFrame(columns=COMPARISON_COLUMNS)
    others = [a for a in preferred_then_seen(per_seed["algo"], ["ppo", *(algorithms or [])]) if a != reference]
    pairs, rows = [], []
    for baseline in others:
        cells = policy_cells(per_seed, reference, baseline)
        strata_x, strata_y = paired_policy_strata(per_seed, reference, baseline, cells, score)
        if not strata_x:
            continue
        pairs.append((strata_x, strata_y))
        rows.append({"algo": reference, "baseline": baseline, "n_tasks": sum(s.shape[1] for s in strata_x),
                     "n_policies": sum(map(len, strata_x)), "n_policies_baseline": sum(map(len, strata_y))})
    for row, result in zip(rows, compare_family(pairs, confidence, seed=seed), strict=True):
        row.update({"difference": result.difference.estimate, "difference_low": result.difference.low,
                    "difference_high": result.difference.high, "confidence": result.confidence, "df": result.df,
                    "p_value": result.p_value, "p_holm": result.p_adjusted,
                    "improvement": result.improvement.estimate, "improvement_low": result.improvement.low,
                    "improvement_high": result.improvement.high, "verdict": result.verdict})
    return pd.DataFrame(rows, columns=COMPARISON_COLUMNS)


def plot_aggregate(aggregate: pd.DataFrame, comparisons: pd.DataFrame, out_base: Path) -> list[Path]:
    """Left: IQM goal rate per algorithm with its 95 % cluster-bootstrap interval; right: probability that the
    reference algorithm's policy beats another's in the same cell, with its interval (0.5: no difference). PNG, SVG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 0.5 * max(len(aggregate), len(comparisons), 2) + 1.6))
    labels = [algo_label(a) for a in aggregate["algo"]]
    y = np.arange(len(aggregate))[::-1]
    iqm = aggregate["iqm"].to_numpy(float)
    error = np.nan_to_num(np.abs(np.vstack([iqm - aggregate["iqm_low"].to_numpy(float),
                                            aggregate["iqm_high"].to_numpy(float) - iqm])))
    left.errorbar(iqm, y, xerr=error, fmt="o", color="tab:blue", capsize=4)
    left.set_yticks(y, labels)
    left.set_ylim(-0.6, len(aggregate) - 0.4)
    left.set_xlabel("IQM goal rate (%), 95 % CI (descriptive)")
    left.set_title("Aggregate over policies × scenario cells")
    left.grid(alpha=0.3, axis="x")
    if len(comparisons):
        y = np.arange(len(comparisons))[::-1]
        poi = comparisons["improvement"].to_numpy(float)
        error = np.nan_to_num(np.abs(np.vstack([poi - comparisons["improvement_low"].to_numpy(float),
                                                comparisons["improvement_high"].to_numpy(float) - poi])))
        right.errorbar(poi, y, xerr=error, fmt="o", color="tab:green", capsize=4)
        right.set_yticks(y, [algo_label(b) for b in comparisons["baseline"]])
        right.axvline(0.5, color="grey", linestyle="--", linewidth=1)
        right.set_xlim(-0.03, 1.03)  # room for points at 0 and 1
        right.set_ylim(-0.6, len(comparisons) - 0.4)
        right.set_title(f"P({algo_label(comparisons['algo'].iloc[0])} > Y)")
    else:
        right.set_title(f"P({algo_label(REFERENCE_ALGO)} > Y): not in this run")
    right.set_xlabel("probability of improvement, 95 % CI (descriptive)")
    right.grid(alpha=0.3, axis="x")
    figure.tight_layout()
    return save_figure(figure, out_base)


def p_text(p_value: float) -> str:
    if math.isnan(p_value):
        return "–"
    return "< 0.001" if p_value < 0.001 else f"{p_value:.3f}"


def table1_ci_section(context: ReportContext) -> str:
    """Table 1 with intervals over seeds, the aggregate scores and ODV-PPO-Drop's comparisons: their files and
    section."""
    experiment = context.experiment
    algorithms = experiment["grid"]["algorithms"]
    per_seed = table1_seed_frame(context.episode_records())
    ci = table1_ci_frame(per_seed)
    write_table_atomic(ci, context.out_dir / "table1_ci.csv")
    markdown = table1_ci_markdown(ci, algorithms, experiment["grid"]["train_scenarios"],
                                  experiment["evaluation"]["scenarios"])
    write_text_atomic(context.out_dir / "table1_ci.md", markdown + "\n")
    aggregate = aggregate_frame(per_seed, algorithms)
    comparisons = comparison_frame(per_seed, REFERENCE_ALGO, algorithms)
    write_table_atomic(aggregate, context.out_dir / "aggregate.csv")
    write_table_atomic(comparisons, context.out_dir / "comparisons.csv")
    plot_aggregate(aggregate, comparisons, context.out_dir / "aggregate")
    seeds = per_seed["train_seed"].nunique() if len(per_seed) else 0
    family_level = comparisons["confidence"].iloc[0] if len(comparisons) else FAMILY_CONFIDENCE
    lines = [
        "## Table 1 with 95 % confidence intervals over seeds",
        "",
        f"Mean over the training seeds ({seeds} here) [95 % Student t-interval over seeds] of the goal rate (%), "
        "collision rate (%) and mean return; every Table 1 metric in the CSV. The intervals describe one cell each "
        "and are not adjusted for the number of cells: verdicts come from the tests below and in the claims "
        "section. One seed gives no interval (`n/a`).",
        "",
        markdown,
        "",
        "### Aggregate goal rate and ODV-PPO-Drop's comparisons",
        "",
        "Score: the goal (success) rate (%) of each policy (training scenario, algorithm, seed) in each evaluation "
        "scenario — the paper ranks algorithms by it, and its scale is the same in every scenario. A policy is one "
        "unit in every cell it is evaluated in. IQM: interquartile mean over all policies × cells, with a 95 % "
        "cluster-bootstrap interval (policies resampled within each training scenario, with all their cells; "
        "descriptive, too narrow with few seeds). Claim *ODV-PPO-Drop reaches the goal more often than Y*: "
        "difference of the mean goal rates (points, averaged over cells), stratified Welch t-test on per-policy "
        f"means (strata: training scenarios); intervals at the Bonferroni level ({100 * family_level:.2f} % for "
        f"{len(comparisons)} claim(s)), verdicts by Holm (family-wise error ≤ 5 %): **holds** if the "
        "Holm-adjusted p ≤ 0.05 and the difference is above 0, **does not hold** if below, otherwise **cannot "
        "tell at this budget**. P(improvement): probability that an ODV-PPO-Drop policy beats a policy of Y in "
        "the same cell, with a 95 % cluster-bootstrap interval (descriptive).",
        "",
        "![aggregate](aggregate.png)",
        "",
        "| Approach | IQM goal (%) [95 % CI] | Mean goal (%) | Policies × cells |",
        "|:--|--:|--:|--:|",
    ]
    for row in aggregate.to_dict("records"):
        lines.append(f"| {algo_label(row['algo'])} | {interval_text(row['iqm'], row['iqm_low'], row['iqm_high'], 1)}"
                     f" | {row['mean']:.1f} | {row['n_runs']} |")
    lines.append("")
    if comparisons.empty:
        lines.append(f"No comparison: {algo_label(REFERENCE_ALGO)} and another algorithm are not both in this run.")
    else:
        lines += ["| Claim | Goal difference (points) [adjusted CI] | p (Holm) | P(improvement) [95 % CI] | Verdict |",
                  "|:--|--:|--:|--:|:--|"]
        for row in comparisons.to_dict("records"):
            lines.append(
                f"| {algo_label(row['algo'])} > {algo_label(row['baseline'])} "
                f"| {interval_text(row['difference'], row['difference_low'], row['difference_high'], 1)} "
                f"| {p_text(row['p_holm'])} "
                f"| {interval_text(row['improvement'], row['improvement_low'], row['improvement_high'], 2)} "
                f"| {row['verdict']} |")
    lines += ["", "Vector version: [aggregate.svg](aggregate.svg); data: [table1_ci.csv](table1_ci.csv), "
              "[aggregate.csv](aggregate.csv), [comparisons.csv](comparisons.csv)."]
    return "\n".join(lines)
