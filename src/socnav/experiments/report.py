"""Reports of finished (or partly finished) experiments: tables as Markdown + CSV, figures as PNG + SVG, and one
Markdown page, ``report.md``, that holds them.

The page is assembled from *sections* registered per experiment kind (``@register_section("table1", ...)``,
:mod:`socnav.experiments.registry`): each section gets a :class:`~socnav.experiments.registry.ReportContext` (the run
directory, its resolved experiment, the finished units and their records), writes its own files into the report
directory and returns its Markdown. This module holds the table1 kind's sections; the uncertainty kind's are in
:mod:`socnav.experiments.uncertainty_report`, imported here so that a report knows every kind.

Table 1 metrics, per (training scenario, algorithm, evaluation scenario), each the mean over seeds of the per-seed
value computed from that seed's test episodes:
Goal %, Col. %, TO %  -- share of episodes ending at the goal / in a collision / in a time-out;
PV                    -- personal-space violations (intrusion events: entering a human's personal space) per 200
                         episodes;
Return                -- mean over seeds of the per-seed mean episode return, +- the standard deviation over all
                         test episodes of all seeds (population std, ddof=0: the spread a user sees per episode).
The CSV adds ``return_seed_std`` (std over seeds of the per-seed mean return) and the seed / episode counts.

Statistics (:mod:`socnav.experiments.statistics`): a trained policy (training scenario, algorithm, seed) is one unit
in every evaluation cell it appears in, and every verdict comes from a test that keeps its error rate at 3 seeds.
``table1_ci.md/csv``: per cell and metric the mean over seeds with a 95 % Student t-interval over seeds (descriptive,
not adjusted for the number of cells). ``aggregate.png/svg/csv``: per algorithm the IQM of the goal rate over
policies x cells with a cluster-bootstrap interval (policies resampled within training scenarios; descriptive).
``comparisons.csv``: ODV-PPO-Drop against each other algorithm on the goal rate over all cells, one family: stratified
Welch t-test on per-policy means (strata: training scenarios), intervals at the Bonferroni level, verdicts by Holm
(holds / does not hold / cannot tell at this budget), and the probability of improvement (descriptive).
``claims.md/csv``: the paper's Table 1 claims (dropout improves PPO; ODV without the variance loss fails to converge
in random; ODV-PPO-Drop generalizes best; circle-interaction training converges fastest with the lowest variance
across seeds), one family, with the statistic, test, estimate, adjusted interval, Holm p-value and verdict of each
part (:func:`claims_frame`); ``training_runs.csv``: the per-run training-curve statistics they read
(:func:`training_run_frame`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

# The sections of the `uncertainty` and `safety_benchmark` kinds register on import.
from socnav.experiments import safety_benchmark_units, uncertainty_report  # noqa: F401
from socnav.experiments.labels import algo_label, preferred_then_seen, scenario_label
from socnav.experiments.paper_tables import PAPER_BUDGET, paper_table1
from socnav.experiments.registry import SECTIONS, ReportContext, register_section
from socnav.experiments.runner import read_plan, unit_states
from socnav.io import save_figure, write_table_atomic, write_text_atomic
from socnav.sim.metrics import ALL_METRICS, PV_PER, summarize_groups

if TYPE_CHECKING:
    from socnav.experiments.statistics import VarianceRatioTest, WelchTest

__all__ = [
    "aggregate_frame", "build_report", "claims_frame", "comparison_frame", "paired_policy_strata", "plot_aggregate",
    "plot_training_curves", "policy_strata", "table1_ci_frame", "table1_ci_markdown", "table1_frame",
    "table1_markdown", "table1_seed_frame", "training_curve_frame", "training_curves_figure", "training_run_frame",
]

ID_COLUMNS = ["train_scenario", "algo", "eval_scenario"]
TABLE1_COLUMNS = [*ID_COLUMNS, "n_seeds", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv",
                  "return_mean", "return_std", "return_seed_std"]
#: Table 1's per-seed metrics (registry names, `socnav.sim.metrics.METRICS`), in their column order.
TABLE1_SEED_METRICS = ["goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean"]
#: Every other metric of the registry, appended to table1.csv (Table 1's return spread is over all episodes, so a
#: per-seed return_std is not one of them).
EXTRA_METRICS = [name for name in ALL_METRICS if name not in TABLE1_SEED_METRICS and name != "return_std"]


# --------------------------------------------------------------------------------------------------------------
# The page
# --------------------------------------------------------------------------------------------------------------

def build_report(results_dir: str | Path, out_dir: str | Path | None = None) -> Path:
    """Write every section of the run directory's experiment kind and ``report.md``; returns report.md's path."""
    results_dir = Path(results_dir)
    experiment, units = read_plan(results_dir)
    out_dir = Path(out_dir) if out_dir is not None else results_dir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    context = ReportContext(results_dir, out_dir, experiment, units, unit_states(results_dir, units))
    kind = experiment.get("kind", "table1")
    if kind not in SECTIONS:
        raise ValueError(f"no report sections for experiment kind {kind!r}; known kinds: {', '.join(sorted(SECTIONS))}")
    parts = [_header(context)]
    for _, section in SECTIONS[kind]:
        parts.append(section(context).strip())
    return write_text_atomic(out_dir / "report.md", "\n\n".join(parts) + "\n")


def _header(context: ReportContext) -> str:
    experiment = context.experiment
    budget = experiment.get("budget") or "as written"
    lines = [f"# Experiment `{experiment['name']}` (budget: {budget})", ""]
    if experiment.get("description"):
        lines += [" ".join(str(experiment["description"]).split()), ""]
    done, total = len(context.done()), len(context.units)
    lines.append(f"Units finished: {done} of {total}.")
    missing = context.missing()
    if missing:
        lines.append(f"**Partial results**: {len(missing)} unit(s) not finished (numbers below leave them out):")
        lines += [f"- `{u.id}` ({context.states[u.id]})" for u in missing[:20]]
        if len(missing) > 20:
            lines.append(f"- ... and {len(missing) - 20} more")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Table 1
# --------------------------------------------------------------------------------------------------------------

def table1_seed_frame(records: pd.DataFrame, pv_per: int = PV_PER) -> pd.DataFrame:
    """Table 1's metrics per training seed: one row per (training scenario, algorithm, evaluation scenario,
    train_seed) with episodes, goal_pct, collision_pct, timeout_pct, pv and return_mean of that seed's episodes,
    then every other registry metric whose record column the records hold (:data:`EXTRA_METRICS`; computed by
    `socnav.sim.metrics.summarize_groups`)."""
    columns = [*ID_COLUMNS, "train_seed", "episodes", *TABLE1_SEED_METRICS]
    if records.empty:
        return pd.DataFrame(columns=columns)
    per_seed = summarize_groups(records, [*ID_COLUMNS, "train_seed"], TABLE1_SEED_METRICS + EXTRA_METRICS, pv_per)
    return per_seed[columns + [name for name in EXTRA_METRICS if name in per_seed]]


def table1_frame(records: pd.DataFrame, pv_per: int = PV_PER) -> pd.DataFrame:
    """Table 1 in long form from per-episode records (columns train_scenario, algo, train_seed, eval_scenario,
    outcome, return, intrusion_events): one row per (training scenario, algorithm, evaluation scenario), with
    :data:`TABLE1_COLUMNS` and then, as means over seeds, the :data:`EXTRA_METRICS` the records hold."""
    if records.empty:
        return pd.DataFrame(columns=TABLE1_COLUMNS)
    per_seed = table1_seed_frame(records, pv_per)
    extra = [name for name in EXTRA_METRICS if name in per_seed]
    table = per_seed.groupby(ID_COLUMNS, sort=False).agg(
        n_seeds=("train_seed", "nunique"), episodes=("episodes", "sum"), goal_pct=("goal_pct", "mean"),
        collision_pct=("collision_pct", "mean"), timeout_pct=("timeout_pct", "mean"), pv=("pv", "mean"),
        return_mean=("return_mean", "mean"),
        return_seed_std=("return_mean", lambda values: float(np.std(values, ddof=0))),
        **{name: (name, "mean") for name in extra},
    ).reset_index()
    spread = records.groupby(ID_COLUMNS, sort=False)["return"].std(ddof=0).rename("return_std").reset_index()
    table = table.merge(spread, on=ID_COLUMNS, how="left")
    return table[TABLE1_COLUMNS + extra]


#: metric column -> (header, "max" | "min" is best, decimals)
TABLE1_METRICS = {
    "goal_pct": ("Goal (%)", "max", 2), "collision_pct": ("Col. (%)", "min", 2), "timeout_pct": ("TO (%)", "min", 2),
    "pv": ("PV", "min", 0), "return_mean": ("Return (μ ± σ)", "max", 2),
}


def table1_markdown(table: pd.DataFrame, algorithms: list[str] | None = None,
                    train_scenarios: list[str] | None = None, eval_scenarios: list[str] | None = None) -> str:
    """The paper's Table I layout: rows training scenario x algorithm, a column group per evaluation scenario;
    the best value of each column within each training scenario in bold (ties all bold)."""
    algorithms = preferred_then_seen(table["algo"], algorithms or [])
    train_scenarios = preferred_then_seen(table["train_scenario"], train_scenarios or [])
    eval_scenarios = preferred_then_seen(table["eval_scenario"], eval_scenarios or [])
    header = ["Training scenario", "Approach"]
    for scenario in eval_scenarios:
        header += [f"{scenario_label(scenario)}: {title}" for title, _, _ in TABLE1_METRICS.values()]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * (len(header) - 2)) + "|"]
    indexed = table.set_index(ID_COLUMNS)
    for train_scenario in train_scenarios:
        block = table[table["train_scenario"] == train_scenario]
        best: dict[tuple[str, str], float] = {}
        for scenario in eval_scenarios:
            cells = block[block["eval_scenario"] == scenario]
            for column, (_, direction, decimals) in TABLE1_METRICS.items():
                shown = cells[column].dropna().round(decimals)
                if len(shown):
                    best[(scenario, column)] = shown.max() if direction == "max" else shown.min()
        for index, algo in enumerate(algorithms):
            row = [scenario_label(train_scenario) if index == 0 else "", algo_label(algo)]
            for scenario in eval_scenarios:
                key = (train_scenario, algo, scenario)
                if key not in indexed.index:
                    row += ["–"] * len(TABLE1_METRICS)
                    continue
                values = indexed.loc[key]
                for column, (_, _, decimals) in TABLE1_METRICS.items():
                    value = float(values[column])
                    text = _number(value, decimals)
                    if column == "return_mean":
                        text = f"{text} ± {_number(float(values['return_std']), 2)}"
                    is_best = not math.isnan(value) and round(value, decimals) == best.get((scenario, column))
                    row.append(f"**{text}**" if is_best else text)
            lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _number(value: float, decimals: int) -> str:
    if math.isnan(value):
        return "–"
    return f"{value:.{decimals}f}"


@register_section("table1", "table1")
def table1_section(context: ReportContext) -> str:
    """Table 1's section: table1.md/csv."""
    experiment = context.experiment
    table = table1_frame(context.episode_records())
    write_table_atomic(table, context.out_dir / "table1.csv")
    markdown = table1_markdown(table, experiment["grid"]["algorithms"], experiment["grid"]["train_scenarios"],
                               experiment["evaluation"]["scenarios"])
    write_text_atomic(context.out_dir / "table1.md", markdown + "\n")
    seeds = len(experiment["grid"]["seeds"])
    episodes = experiment["evaluation"]["episodes"]
    return "\n".join([
        "## Table 1: training and generalization",
        "",
        f"Every policy ({seeds} seed(s) per training scenario and algorithm) evaluated on {episodes} test episodes "
        f"(seeds {experiment['evaluation']['seed']}..{experiment['evaluation']['seed'] + episodes - 1}) in every "
        "evaluation scenario; values are means over seeds. Goal, Return: higher is better; Col., TO (time-out), "
        f"PV (personal-space violations: intrusion events per {PV_PER} episodes): lower is better. Return: mean ± "
        "standard deviation over all test episodes. Bold: best per column within a training scenario.",
        "",
        markdown,
        "",
        "Data: [table1.csv](table1.csv) (also `return_seed_std`, the spread of the mean return over seeds, and, as "
        "means over seeds, every other metric of docs/metrics.md the records hold).",
    ])


# --------------------------------------------------------------------------------------------------------------
# Table 1 with confidence intervals over seeds, aggregate scores and ODV-PPO-Drop's comparisons
# --------------------------------------------------------------------------------------------------------------

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
                    row.append(_interval_text(cell["mean"], cell["ci_low"], cell["ci_high"], decimals))
            lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _interval_text(mean: float, low: float, high: float, decimals: int) -> str:
    from socnav.experiments.statistics import Interval

    return Interval(float(mean), float(low), float(high)).text(decimals)


Cell = tuple[str, str]  # (training scenario, evaluation scenario)


def _cells(per_seed: pd.DataFrame, *algos: str) -> list[Cell]:
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
        cells = _cells(per_seed, algo)
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
        cells = _cells(per_seed, reference, baseline)
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


def _p_text(p_value: float) -> str:
    if math.isnan(p_value):
        return "–"
    return "< 0.001" if p_value < 0.001 else f"{p_value:.3f}"


@register_section("table1", "table1_ci")
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
        lines.append(f"| {algo_label(row['algo'])} | {_interval_text(row['iqm'], row['iqm_low'], row['iqm_high'], 1)}"
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
                f"| {_interval_text(row['difference'], row['difference_low'], row['difference_high'], 1)} "
                f"| {_p_text(row['p_holm'])} "
                f"| {_interval_text(row['improvement'], row['improvement_low'], row['improvement_high'], 2)} "
                f"| {row['verdict']} |")
    lines += ["", "Vector version: [aggregate.svg](aggregate.svg); data: [table1_ci.csv](table1_ci.csv), "
              "[aggregate.csv](aggregate.csv), [comparisons.csv](comparisons.csv)."]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Training curves
# --------------------------------------------------------------------------------------------------------------

def training_curve_frame(curves: pd.DataFrame, value: str = "ep_rew_mean") -> pd.DataFrame:
    """Mean and std over seeds of `value` vs timesteps per (training scenario, algorithm).

    Each seed's curve (rows with a value) is interpolated onto the timesteps of the seed with the most points,
    within the range every seed covers, so seeds with different logging steps still average point by point.
    """
    rows = []
    for (scenario, algo), group in curves.groupby(["train_scenario", "algo"], sort=False):
        per_seed = [g.dropna(subset=[value]).sort_values("timesteps") for _, g in group.groupby("seed")]
        per_seed = [g for g in per_seed if len(g)]
        if not per_seed:
            continue
        low = max(g["timesteps"].iloc[0] for g in per_seed)
        high = min(g["timesteps"].iloc[-1] for g in per_seed)
        grid = max(per_seed, key=len)["timesteps"].to_numpy(dtype=float)
        grid = grid[(grid >= low) & (grid <= high)]
        if not len(grid):
            continue
        stacked = np.stack([np.interp(grid, g["timesteps"].to_numpy(float), g[value].to_numpy(float))
                            for g in per_seed])
        rows.append(pd.DataFrame({"train_scenario": scenario, "algo": algo, "timesteps": grid,
                                  "mean": stacked.mean(axis=0), "std": stacked.std(axis=0),
                                  "n_seeds": len(per_seed)}))
    columns = ["train_scenario", "algo", "timesteps", "mean", "std", "n_seeds"]
    return pd.concat(rows, ignore_index=True)[columns] if rows else pd.DataFrame(columns=columns)


#: Each algorithm's mark on the training curves (in the order of the algorithms): a curve of one point (a run that
#: logged once) shows as its mark, and the lines stay apart in grey print.
CURVE_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
#: Up to this many points a curve marks every point; above, about this many evenly spaced ones.
CURVE_MARKED_POINTS = 12


def training_curves_figure(frame: pd.DataFrame, algorithms: list[str] | None = None,
                           scenarios: list[str] | None = None, ylabel: str = "training reward (episode mean)") -> Any:
    """The figure `plot_training_curves` writes: one panel per training scenario, one line per algorithm (mean over
    seeds, with its own mark; band mean ± std, an error bar where the curve is one point)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    scenarios = preferred_then_seen(frame["train_scenario"], scenarios or []) or ["(no finished training)"]
    algorithms = preferred_then_seen(frame["algo"], algorithms or [])
    colors = {algo: plt.get_cmap("tab10")(index % 10) for index, algo in enumerate(algorithms)}
    markers = {algo: CURVE_MARKERS[index % len(CURVE_MARKERS)] for index, algo in enumerate(algorithms)}
    figure, axes = plt.subplots(1, len(scenarios), figsize=(4.6 * len(scenarios), 3.6), squeeze=False)
    for axis, scenario in zip(axes[0], scenarios, strict=True):
        for algo in algorithms:
            data = frame[(frame["train_scenario"] == scenario) & (frame["algo"] == algo)]
            if data.empty:
                continue
            x, mean, std = (data[c].to_numpy(float) for c in ("timesteps", "mean", "std"))
            every = max(1, round(len(x) / CURVE_MARKED_POINTS)) if len(x) > CURVE_MARKED_POINTS else 1
            axis.plot(x, mean, color=colors[algo], label=algo_label(algo), linewidth=1.6, marker=markers[algo],
                      markersize=5 if len(x) > 1 else 7, markevery=every)
            if len(x) > 1:
                axis.fill_between(x, mean - std, mean + std, color=colors[algo], alpha=0.2, linewidth=0)
            else:  # a band of one point is invisible: its spread as an error bar
                axis.errorbar(x, mean, yerr=std, fmt="none", ecolor=colors[algo], alpha=0.5, capsize=3)
        axis.set_title(scenario_label(scenario))
        axis.set_xlabel("timesteps")
        axis.xaxis.set_major_formatter(FuncFormatter(_steps_label))
        axis.grid(alpha=0.3)
    axes[0][0].set_ylabel(ylabel)
    handles, labels = axes[0][0].get_legend_handles_labels()
    for axis in axes[0][1:]:
        more = axis.get_legend_handles_labels()
        for handle, label in zip(*more, strict=True):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    # as many legend columns as the figure's width holds (about 2 inches each), in as many rows as needed
    columns = max(1, min(len(labels), 5, int(4.6 * len(scenarios) / 2.0)))
    rows = -(-len(labels) // columns)
    if handles:
        figure.legend(handles, labels, loc="lower center", ncol=columns, frameon=False)
    figure.tight_layout(rect=(0, 0.03 + 0.075 * rows if handles else 0, 1, 1))
    return figure


def plot_training_curves(frame: pd.DataFrame, out_base: Path, algorithms: list[str] | None = None,
                         scenarios: list[str] | None = None, ylabel: str = "training reward (episode mean)"
                         ) -> list[Path]:
    """One panel per training scenario, one line per algorithm (`training_curves_figure`); PNG and SVG."""
    return save_figure(training_curves_figure(frame, algorithms, scenarios, ylabel), out_base)


def _steps_label(value: float, _position: Any = None) -> str:
    if abs(value) >= 1e6:
        return f"{value / 1e6:g}M"
    return f"{value / 1e3:g}k" if abs(value) >= 1e3 else f"{value:g}"


@register_section("table1", "training_curves")
def training_curves_section(context: ReportContext) -> str:
    """The training curves' section: training_curves.png/svg/csv."""
    experiment = context.experiment
    frame = training_curve_frame(context.training_curves())
    write_table_atomic(frame, context.out_dir / "training_curves.csv")
    plot_training_curves(frame, context.out_dir / "training_curves", experiment["grid"]["algorithms"],
                         experiment["grid"]["train_scenarios"])
    seeds = len(experiment["grid"]["seeds"])
    return "\n".join([
        "## Training curves",
        "",
        f"Training reward (mean return of the last 100 training episodes) vs timesteps; line: mean over {seeds} "
        "seed(s), band: ± one standard deviation over seeds.",
        "",
        "![training curves](training_curves.png)",
        "",
        "Vector version: [training_curves.svg](training_curves.svg); data: [training_curves.csv](training_curves.csv).",
    ])


# --------------------------------------------------------------------------------------------------------------
# Table 1's claims, each tested
# --------------------------------------------------------------------------------------------------------------

#: The training-curve value the convergence and seed-spread claims read (what the training-curve figure shows).
CURVE_VALUE = "ep_rew_mean"
#: A run has converged when its curve first reaches this fraction of the way from its first to its final value.
CONVERGENCE_FRACTION = 0.9
#: The final value of a run: the mean of the last share of its logged points (the plateau, not one noisy point).
FINAL_SHARE = 0.1
TRAINING_RUN_COLUMNS = ["train_scenario", "algo", "seed", "points", "total_steps", "start_reward", "final_reward",
                        "steps_to_converge"]
CLAIM_COLUMNS = ["claim", "part", "statistic", "test", "n_x", "n_y", "estimate", "ci_low", "ci_high", "confidence",
                 "p_value", "p_holm", "verdict", "claim_verdict"]
FAST_SCENARIO = "circle_interaction"


def training_run_frame(curves: pd.DataFrame, value: str = CURVE_VALUE, fraction: float = CONVERGENCE_FRACTION,
                       final_share: float = FINAL_SHARE) -> pd.DataFrame:
    """Per training run (training scenario, algorithm, seed), from its curve of ``value`` vs timesteps (rows with a
    value): ``start_reward`` (the first point), ``final_reward`` (mean of the last ``final_share`` of the points,
    at least one) and ``steps_to_converge``, the first timestep at which the curve reaches
    ``start + fraction (final - start)`` -- the last timestep if the run never improved (final <= start). Scale
    free: every run is measured against its own start and plateau, so scenarios with other reward scales compare."""
    rows = []
    for (scenario, algo, seed), group in curves.groupby(["train_scenario", "algo", "seed"], sort=False):
        points = group.dropna(subset=[value]).sort_values("timesteps")
        steps, values = points["timesteps"].to_numpy(float), points[value].to_numpy(float)
        row = {"train_scenario": scenario, "algo": algo, "seed": seed, "points": len(points),
               "total_steps": steps[-1] if len(steps) else np.nan, "start_reward": np.nan, "final_reward": np.nan,
               "steps_to_converge": np.nan}
        if len(points) >= 2:
            start, final = values[0], values[-max(1, math.ceil(final_share * len(values))):].mean()
            reached = values >= start + fraction * (final - start)
            converged_at = steps[np.argmax(reached)] if final > start else steps[-1]
            row.update(start_reward=start, final_reward=final, steps_to_converge=converged_at)
        rows.append(row)
    return pd.DataFrame(rows, columns=TRAINING_RUN_COLUMNS)


@dataclass
class _Part:
    claim: str
    part: str
    statistic: str
    test: WelchTest | VarianceRatioTest
    n_x: int
    n_y: int


def _goal_part(per_seed: pd.DataFrame, claim: str, part: str, statistic: str, algo_x: str, algo_y: str,
               cells: list[Cell]) -> _Part:
    from socnav.experiments.statistics import welch_test

    evaluated = set(_cells(per_seed, algo_x, algo_y))
    cells = [cell for cell in cells if cell in evaluated]
    strata_x, strata_y = paired_policy_strata(per_seed, algo_x, algo_y, cells)
    if not strata_x:
        return _Part(claim, part, statistic, _untestable(), 0, 0)
    return _Part(claim, part, statistic, welch_test(strata_x, strata_y), sum(map(len, strata_x)),
                 sum(map(len, strata_y)))


def _untestable() -> WelchTest:
    from socnav.experiments.statistics import WelchTest

    return WelchTest(np.nan, np.nan, np.nan, np.nan)


def _run_groups(runs: pd.DataFrame, scenario: str, column: str, algorithms: list[str]) -> list[np.ndarray]:
    """``column`` of the runs trained on ``scenario``, one array per algorithm (in ``algorithms`` order)."""
    mine = runs[(runs["train_scenario"] == scenario)].dropna(subset=[column])
    return [mine.loc[mine["algo"] == algo, column].to_numpy(float) for algo in algorithms]


def claims_frame(per_seed: pd.DataFrame, runs: pd.DataFrame, confidence: float = FAMILY_CONFIDENCE
                 ) -> pd.DataFrame:
    """The paper's Table 1 claims, one row per tested part, as one family (Holm verdicts, Bonferroni intervals):

    - *Dropout improves PPO*: PPO-Drop - PPO, goal rate (points) over all cells;
    - *ODV without the variance loss is unstable (fails to converge in the random scenario)*: ODV-PPO - ODV-PPO
      no Loss, goal rate of the policies trained on random, in random;
    - *ODV-PPO-Drop is best in generalization*: ODV-PPO-Drop - each other algorithm, goal rate over the cells with
      training != evaluation scenario;
    - *circle-interaction training converges fastest*: steps to converge (:func:`training_run_frame`, in thousands)
      of each other training scenario - circle interaction's, strata: algorithms;
    - *... with the lowest variance across seeds*: variance over seeds (pooled within algorithms) of the final
      training reward, each other training scenario / circle interaction's (F-test).

    Goal-rate parts: stratified Welch test on per-policy means (``per_seed`` from :func:`table1_seed_frame`); curve
    parts read ``runs`` from :func:`training_run_frame`. A claim with several parts holds if every part holds, does
    not hold if one does not, and otherwise cannot be told.
    """
    from socnav.experiments.statistics import (
        CANNOT_TELL,
        DOES_NOT_HOLD,
        HOLDS,
        adjust_family,
        variance_ratio_test,
        welch_test,
    )

    all_cells = list(dict.fromkeys(map(tuple, per_seed[["train_scenario", "eval_scenario"]].drop_duplicates()
                                       .to_numpy().tolist())))
    off_diagonal = [(train, evaluation) for train, evaluation in all_cells if train != evaluation]
    goal = "goal rate (%)"
    parts = [
        _goal_part(per_seed, "Dropout improves PPO", "PPO-Drop > PPO", f"{goal}, all cells: difference (points)",
                   "ppo-drop", "ppo", all_cells),
        _goal_part(per_seed, "ODV without the variance loss is unstable (fails to converge in the random scenario)",
                   "ODV-PPO > ODV-PPO no Loss, trained and evaluated in Random",
                   f"{goal} in Random of policies trained on Random: difference (points)", "odv-ppo",
                   "odv-ppo-noloss", [("random", "random")]),
    ]
    for baseline in ["ppo", "ppo-drop", "odv-ppo-noloss", "odv-ppo"]:
        parts.append(_goal_part(per_seed, "ODV-PPO-Drop is best in generalization",
                                f"ODV-PPO-Drop > {algo_label(baseline)}",
                                f"{goal}, training ≠ evaluation scenario: difference (points)", "odv-ppo-drop",
                                baseline, off_diagonal))
    algorithms = list(dict.fromkeys(runs["algo"]))
    in_thousands = runs.assign(steps_to_converge=runs["steps_to_converge"] / 1000)
    fast = _run_groups(in_thousands, FAST_SCENARIO, "steps_to_converge", algorithms)
    for other in ["circle_crossing", "random"]:
        slow = _run_groups(in_thousands, other, "steps_to_converge", algorithms)
        # strata: the algorithms with runs in both scenarios (each algorithm is compared with itself)
        both = [(s, f) for s, f in zip(slow, fast, strict=True) if len(s) and len(f)]
        test = welch_test([s for s, _ in both], [f for _, f in both]) if both else _untestable()
        parts.append(_Part("Circle-interaction training converges fastest", f"faster than {scenario_label(other)}",
                           f"steps to {100 * CONVERGENCE_FRACTION:.0f} % of the final training reward (thousands): "
                           f"{scenario_label(other)} − Circle Interaction", test,
                           sum(len(s) for s, _ in both), sum(len(f) for _, f in both)))
    fast = _run_groups(runs, FAST_SCENARIO, "final_reward", algorithms)
    for other in ["circle_crossing", "random"]:
        slow = _run_groups(runs, other, "final_reward", algorithms)
        parts.append(_Part("Circle-interaction training has the lowest variance across seeds",
                           f"lower than {scenario_label(other)}",
                           f"variance over seeds of the final training reward: {scenario_label(other)} / "
                           "Circle Interaction", variance_ratio_test(slow, fast), sum(map(len, slow)),
                           sum(map(len, fast))))

    adjusted = adjust_family([part.test for part in parts], confidence)
    rows: list[dict[str, Any]] = [
        {"claim": part.claim, "part": part.part, "statistic": part.statistic, "test": part.test.method,
         "n_x": part.n_x, "n_y": part.n_y, "estimate": part.test.estimate, "ci_low": result.interval.low,
         "ci_high": result.interval.high, "confidence": result.confidence, "p_value": result.p_value,
         "p_holm": result.p_adjusted, "verdict": result.verdict}
        for part, result in zip(parts, adjusted, strict=True)]
    overall: dict[str, set[str]] = {}
    for row in rows:
        overall.setdefault(row["claim"], set()).add(row["verdict"])
    for row in rows:
        verdicts = overall[row["claim"]]
        row["claim_verdict"] = (DOES_NOT_HOLD if DOES_NOT_HOLD in verdicts
                                else HOLDS if verdicts == {HOLDS} else CANNOT_TELL)
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def _power_note(per_seed: pd.DataFrame, n_claims: int) -> list[str]:
    """What this run could have told (a paragraph and a blank line; nothing without 2+ seeds): the goal-rate
    differences its rule detects with 80 % power at its budget and measured seed variation (simulated,
    :func:`socnav.experiments.power.min_detectable_difference`, at the Bonferroni level: Holm's first step), and the
    normal-theory sizes for the two training-curve claims."""
    from socnav.experiments.power import (
        estimate_design,
        min_detectable_difference,
        min_detectable_standardised_difference,
        min_detectable_variance_ratio,
    )

    try:
        design = estimate_design(per_seed)
    except ValueError:
        return []
    sizes = {}
    for cells, strata in ((3, 3), (2, 3), (1, 1)):
        size = min_detectable_difference(replace(design, cells_per_policy=cells, train_scenarios=strata),
                                         n_claims=n_claims, replicates=1000, tolerance=0.25)
        sizes[cells] = "no difference the base rate allows" if math.isnan(size) else f"about {size:.1f} points"
    ratio = min_detectable_variance_ratio(design.seeds, n_claims=n_claims)
    standardised = min_detectable_standardised_difference(design.seeds, n_claims=n_claims)
    return [
        f"**Power at this budget** ({design.seeds} seeds, {design.episodes} episodes; measured in this run: "
        f"between-seed SD {design.seed_sd_pct:.1f} points beyond the binomial noise, correlation "
        f"{design.cell_correlation:.2f} between a policy's cells, mean goal rate {design.base_goal_pct:.0f} %): in a "
        f"family of {n_claims} claim(s), the rule says *holds* with 80 % power from {sizes[3]} over all cells, "
        f"{sizes[2]} over "
        f"the generalization cells and {sizes[1]} in one cell (simulated); smaller differences are mostly *cannot "
        f"tell*. The convergence parts need about {standardised:.1f} between-seed SDs, the variance parts a ratio "
        f"of about {ratio:.1f} (normal theory; `docs/analysis/power_table.py`).",
        "",
    ]


@register_section("table1", "claims")
def claims_section(context: ReportContext) -> str:
    """Table 1's claims, each tested: claims.md/csv, training_runs.csv."""
    per_seed = table1_seed_frame(context.episode_records())
    runs = training_run_frame(context.training_curves())
    claims = claims_frame(per_seed, runs)
    write_table_atomic(runs, context.out_dir / "training_runs.csv")
    write_table_atomic(claims, context.out_dir / "claims.csv")
    n_claims = int(claims["p_value"].notna().sum())
    level = claims["confidence"].iloc[0] if len(claims) else FAMILY_CONFIDENCE
    table = ["| Claim (paper) | Part | Statistic | Test | n | Estimate [adjusted CI] | p (Holm) | Verdict |",
             "|:--|:--|:--|:--|--:|--:|--:|:--|"]
    previous = None
    for row in claims.to_dict("records"):
        decimals = 2 if "variance" in row["statistic"] else 1
        table.append(
            f"| {row['claim'] if row['claim'] != previous else ''} | {row['part']} | {row['statistic']} "
            f"| {row['test']} | {row['n_x']} vs {row['n_y']} "
            f"| {_interval_text(row['estimate'], row['ci_low'], row['ci_high'], decimals)} "
            f"| {_p_text(row['p_holm'])} | {row['verdict']} |")
        previous = row["claim"]
    write_text_atomic(context.out_dir / "claims.md", "\n".join(table) + "\n")
    overall = claims.drop_duplicates("claim")
    lines = [
        "## Table 1's claims",
        "",
        "The paper's claims about Table 1 and its training curves, each tested. Goal-rate claims: a policy "
        "(training scenario, algorithm, seed) is one unit, its goal rate averaged over the claim's cells; stratified "
        "Welch t-test (strata: training scenarios), estimate = difference of the mean goal rates in points. "
        f"Convergence: per training run, the first step at which its training reward ({CURVE_VALUE}) reaches "
        f"{100 * CONVERGENCE_FRACTION:.0f} % of the way from its first to its final value (mean of the last "
        f"{100 * FINAL_SHARE:.0f} % of its points), in thousands of steps; stratified Welch test with the algorithms "
        "as "
        "strata (positive: circle interaction is faster). Variance across seeds: the final training reward's "
        "variance over seeds, pooled within algorithms, as a ratio (above 1: circle interaction spreads less); "
        "F-test, which assumes normal per-seed values (one diverging seed can decide it). "
        f"All {n_claims} testable part(s) are one family: intervals at the Bonferroni level ({100 * level:.2f} %), "
        "verdicts by Holm's step-down (family-wise error ≤ 5 %): **holds** if the Holm-adjusted p ≤ 0.05 and the "
        "estimate is on the claim's side, **does not hold** if it is significantly on the other side, otherwise "
        "**cannot tell at this budget**. Holm may be decisive where the Bonferroni interval still touches the null "
        "(never the reverse). A claim with several parts holds if all hold and does not hold if one does not.",
        "",
        *_power_note(per_seed, max(n_claims, 1)),
        "\n".join(table),
        "",
        "Claim by claim:",
        *[f"- **{row['claim']}**: {row['claim_verdict']}" for row in overall.to_dict("records")],
        "",
        "Data: [claims.csv](claims.csv), [training_runs.csv](training_runs.csv) (per run: start and final training "
        "reward, steps to converge).",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# Comparison with the paper
# --------------------------------------------------------------------------------------------------------------

def budget_note(experiment: dict[str, Any]) -> str:
    """A sentence saying how this run's budget differs from the paper's Table I ('' when it is the same)."""
    seeds = experiment["grid"]["seeds"]
    ours = {"timesteps": int(experiment["grid"]["timesteps"]),
            "seeds": len(seeds) if isinstance(seeds, (list, tuple)) else int(seeds),
            "episodes": int(experiment["evaluation"]["episodes"])}
    if ours == PAPER_BUDGET:
        return ""
    return (f"**The budgets differ:** this run trained {ours['timesteps']:,} steps per policy with {ours['seeds']} "
            f"seed(s) and tested {ours['episodes']} episodes per cell; the paper's Table I: "
            f"{PAPER_BUDGET['timesteps']:,} steps, {PAPER_BUDGET['seeds']} seeds, {PAPER_BUDGET['episodes']} episodes. "
            "Rates from another budget are not expected to match the paper's: compare orderings at most.")


def _leaders(values: pd.Series) -> str:
    """The algorithm(s) with the highest value (to one decimal; ties joined with '=')."""
    rounded = values.round(1)
    return " = ".join(algo_label(algo) for algo in rounded.index[rounded == rounded.max()])


@register_section("table1", "paper_comparison")
def paper_comparison_section(context: ReportContext) -> str:
    """Goal and collision rates next to the paper's, and whether the paper's ranking of algorithms by goal rate
    holds per (training scenario, evaluation scenario)."""
    ours = table1_frame(context.episode_records())
    paper = paper_table1()
    merged = ours.merge(paper, on=ID_COLUMNS, how="inner", suffixes=("", "_paper"))
    write_table_atomic(merged[[*ID_COLUMNS, "goal_pct", "goal_pct_paper", "collision_pct", "collision_pct_paper",
                               "timeout_pct", "timeout_pct_paper", "pv", "pv_paper"]],
                       context.out_dir / "table1_vs_paper.csv")
    lines = ["## Comparison with the paper (Table I)", ""]
    note = budget_note(context.experiment)
    if note:
        lines += [note, ""]
    if merged.empty:
        return "\n".join([*lines, "No finished cell of this experiment is in the paper's Table I."])
    lines += ["Goal and collision rates (%) of ours / the paper's; *best* = the algorithm with the highest goal rate "
              "per training and evaluation scenario (ours / the paper's, among the algorithms run here). Returns are "
              "not compared (our reward instantiation is our own).", "",
              "| Training scenario | Evaluation scenario | " + " | ".join(
                  algo_label(a) for a in preferred_then_seen(merged["algo"], context.experiment["grid"]["algorithms"])
              ) + " | Best (ours / paper) |"]
    algorithms = preferred_then_seen(merged["algo"], context.experiment["grid"]["algorithms"])
    lines.append("|" + "|".join([":--", ":--"] + ["--:"] * len(algorithms) + [":--"]) + "|")
    for (train_scenario, eval_scenario), group in merged.groupby(["train_scenario", "eval_scenario"], sort=False):
        by_algo = group.set_index("algo")
        cells = []
        for algo in algorithms:
            if algo in by_algo.index:
                row = by_algo.loc[algo]
                cells.append(f"{row['goal_pct']:.1f} / {row['goal_pct_paper']:.1f} goal, "
                             f"{row['collision_pct']:.1f} / {row['collision_pct_paper']:.1f} col.")
            else:
                cells.append("–")
        best = f"{_leaders(by_algo['goal_pct'])} / {_leaders(by_algo['goal_pct_paper'])}"
        lines.append(f"| {scenario_label(train_scenario)} | {scenario_label(eval_scenario)} | "
                     + " | ".join(cells) + f" | {best} |")
    lines += ["", "Data: [table1_vs_paper.csv](table1_vs_paper.csv)."]
    return "\n".join(lines)

