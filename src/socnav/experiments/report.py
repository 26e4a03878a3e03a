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
PV                    -- proxemic-violation events (entering a human's personal space) per 200 episodes;
Return                -- mean over seeds of the per-seed mean episode return, +- the standard deviation over all
                         test episodes of all seeds (population std, ddof=0: the spread a user sees per episode).
The CSV adds ``return_seed_std`` (std over seeds of the per-seed mean return) and the seed / episode counts.

Table 1 with confidence intervals (``table1_ci.md/csv``) and the aggregate (``aggregate.png/svg/csv``,
``comparisons.csv``): per cell the mean over seeds with a 95 % bootstrap interval over seeds; per algorithm the IQM
of the goal rate over seeds x (training, evaluation) scenario cells; ODV-PPO-Drop against each other algorithm:
difference of mean goal rates and probability of improvement with stratified bootstrap intervals, and the verdict
(holds / does not hold / cannot tell at this budget). See :mod:`socnav.experiments.statistics`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pandas as pd

# The sections of the `uncertainty` kind register on import.
from socnav.experiments import uncertainty_report  # noqa: F401
from socnav.experiments.registry import SECTIONS, ReportContext, register_section
from socnav.experiments.runner import read_plan, unit_states
from socnav.io import save_figure, write_table_atomic, write_text_atomic

__all__ = [
    "aggregate_frame", "build_report", "comparison_frame", "plot_aggregate", "table1_ci_frame", "table1_ci_markdown",
    "table1_frame", "table1_markdown", "table1_seed_frame", "training_curve_frame", "plot_training_curves",
]

ALGO_LABELS = {"ppo": "PPO", "ppo-drop": "PPO-Drop", "odv-ppo-noloss": "ODV-PPO no Loss", "odv-ppo": "ODV-PPO",
               "odv-ppo-drop": "ODV-PPO-Drop"}
SCENARIO_LABELS = {"circle_interaction": "Circle Interaction", "circle_crossing": "Circle Crossing",
                   "random": "Random", "position_swap": "Position Swap"}
ID_COLUMNS = ["train_scenario", "algo", "eval_scenario"]
TABLE1_COLUMNS = ID_COLUMNS + ["n_seeds", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv",
                               "return_mean", "return_std", "return_seed_std"]
PV_PER = 200


def algo_label(name: str) -> str:
    return ALGO_LABELS.get(name, name)


def scenario_label(name: str) -> str:
    return SCENARIO_LABELS.get(name, name.replace("_", " ").title())


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
    train_seed) with episodes, goal_pct, collision_pct, timeout_pct, pv and return_mean of that seed's episodes."""
    columns = ID_COLUMNS + ["train_seed", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean"]
    if records.empty:
        return pd.DataFrame(columns=columns)
    outcome = records["outcome"]
    per_episode = records.assign(goal=(outcome == "goal") * 100.0, collision=(outcome == "collision") * 100.0,
                                 timeout=(outcome == "timeout") * 100.0)
    per_seed = per_episode.groupby(ID_COLUMNS + ["train_seed"], sort=False).agg(
        episodes=("return", "size"), goal_pct=("goal", "mean"), collision_pct=("collision", "mean"),
        timeout_pct=("timeout", "mean"), events=("intrusion_events", "sum"), return_mean=("return", "mean"),
    ).reset_index()
    per_seed["pv"] = per_seed["events"] * pv_per / per_seed["episodes"]
    return per_seed[columns]


def table1_frame(records: pd.DataFrame, pv_per: int = PV_PER) -> pd.DataFrame:
    """Table 1 in long form from per-episode records (columns train_scenario, algo, train_seed, eval_scenario,
    outcome, return, intrusion_events): one row per (training scenario, algorithm, evaluation scenario)."""
    if records.empty:
        return pd.DataFrame(columns=TABLE1_COLUMNS)
    per_seed = table1_seed_frame(records, pv_per)
    table = per_seed.groupby(ID_COLUMNS, sort=False).agg(
        n_seeds=("train_seed", "nunique"), episodes=("episodes", "sum"), goal_pct=("goal_pct", "mean"),
        collision_pct=("collision_pct", "mean"), timeout_pct=("timeout_pct", "mean"), pv=("pv", "mean"),
        return_mean=("return_mean", "mean"),
        return_seed_std=("return_mean", lambda values: float(np.std(values, ddof=0))),
    ).reset_index()
    spread = records.groupby(ID_COLUMNS, sort=False)["return"].std(ddof=0).rename("return_std").reset_index()
    table = table.merge(spread, on=ID_COLUMNS, how="left")
    return table[TABLE1_COLUMNS]


#: metric column -> (header, "max" | "min" is best, decimals)
TABLE1_METRICS = {
    "goal_pct": ("Goal (%)", "max", 2), "collision_pct": ("Col. (%)", "min", 2), "timeout_pct": ("TO (%)", "min", 2),
    "pv": ("PV", "min", 0), "return_mean": ("Return (μ ± σ)", "max", 2),
}


def _ordered(values: Iterable[str], preferred: list[str]) -> list[str]:
    """`preferred` (all of it: planned rows without results show as missing), then any other values seen."""
    return list(dict.fromkeys([*preferred, *values]))


def table1_markdown(table: pd.DataFrame, algorithms: list[str] | None = None,
                    train_scenarios: list[str] | None = None, eval_scenarios: list[str] | None = None) -> str:
    """The paper's Table I layout: rows training scenario x algorithm, a column group per evaluation scenario;
    the best value of each column within each training scenario in bold (ties all bold)."""
    algorithms = _ordered(table["algo"], algorithms or [])
    train_scenarios = _ordered(table["train_scenario"], train_scenarios or [])
    eval_scenarios = _ordered(table["eval_scenario"], eval_scenarios or [])
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
        f"PV (proxemic-violation events per {PV_PER} episodes): lower is better. Return: mean ± standard deviation "
        "over all test episodes. Bold: best per column within a training scenario.",
        "",
        markdown,
        "",
        "Data: [table1.csv](table1.csv) (also `return_seed_std`, the spread of the mean return over seeds).",
    ])


# --------------------------------------------------------------------------------------------------------------
# Table 1 with confidence intervals over seeds, aggregate scores and claims
# --------------------------------------------------------------------------------------------------------------

#: Metrics shown with intervals in table1_ci.md (table1_ci.csv has every Table 1 metric) -> decimals.
CI_MARKDOWN_METRICS = {"goal_pct": 1, "collision_pct": 1, "return_mean": 2}
#: The aggregate score: a policy's goal (success) rate in %, per training seed and (training, evaluation) scenario
#: cell. It is what the paper ranks its algorithms by, and unlike the return its scale is the same in every scenario.
AGGREGATE_SCORE = "goal_pct"
#: The paper's method, compared with every other algorithm of the run (PPO first).
REFERENCE_ALGO = "odv-ppo-drop"
CI_COLUMNS = ID_COLUMNS + ["metric", "n_seeds", "mean", "ci_low", "ci_high"]
COMPARISON_COLUMNS = ["algo", "baseline", "n_tasks", "difference", "difference_low", "difference_high",
                      "improvement", "improvement_low", "improvement_high", "verdict"]


def table1_ci_frame(per_seed: pd.DataFrame, confidence: float = 0.95, seed: int = 0) -> pd.DataFrame:
    """Per (training scenario, algorithm, evaluation scenario) and Table 1 metric: the mean over seeds and its
    bootstrap confidence interval over seeds (NaN bounds with a single seed); ``per_seed`` from
    :func:`table1_seed_frame`."""
    from socnav.experiments.statistics import mean_interval

    rows = []
    for key, group in per_seed.groupby(ID_COLUMNS, sort=False):
        for metric in TABLE1_METRICS:
            interval = mean_interval(group[metric].to_numpy(float), confidence, seed=seed)
            rows.append({**dict(zip(ID_COLUMNS, key)), "metric": metric, "n_seeds": len(group),
                         "mean": interval.estimate, "ci_low": interval.low, "ci_high": interval.high})
    return pd.DataFrame(rows, columns=CI_COLUMNS)


def table1_ci_markdown(ci: pd.DataFrame, algorithms: list[str] | None = None,
                       train_scenarios: list[str] | None = None, eval_scenarios: list[str] | None = None) -> str:
    """Table 1's layout with ``mean [low, high]`` cells for :data:`CI_MARKDOWN_METRICS` (nothing bold: which
    algorithm is best is the question the intervals answer, see the comparisons)."""
    algorithms = _ordered(ci["algo"], algorithms or [])
    train_scenarios = _ordered(ci["train_scenario"], train_scenarios or [])
    eval_scenarios = _ordered(ci["eval_scenario"], eval_scenarios or [])
    header = ["Training scenario", "Approach"]
    for scenario in eval_scenarios:
        header += [f"{scenario_label(scenario)}: {TABLE1_METRICS[m][0].replace(' (μ ± σ)', '')}"
                   for m in CI_MARKDOWN_METRICS]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * (len(header) - 2)) + "|"]
    indexed = ci.set_index(ID_COLUMNS + ["metric"])
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


def _task_scores(per_seed: pd.DataFrame, algo: str, tasks: list[tuple[str, str]],
                 score: str = AGGREGATE_SCORE) -> list[np.ndarray]:
    mine = per_seed[per_seed["algo"] == algo].groupby(["train_scenario", "eval_scenario"])[score]
    return [mine.get_group(task).to_numpy(float) for task in tasks]


def _tasks(per_seed: pd.DataFrame, *algos: str) -> list[tuple[str, str]]:
    """(training scenario, evaluation scenario) cells where every one of `algos` has at least one seed."""
    cells = [set(map(tuple, per_seed.loc[per_seed["algo"] == algo, ["train_scenario", "eval_scenario"]]
                     .drop_duplicates().to_numpy().tolist())) for algo in algos]
    common = set.intersection(*cells) if cells else set()
    order = per_seed[["train_scenario", "eval_scenario"]].drop_duplicates().itertuples(index=False, name=None)
    return [task for task in order if task in common]


def aggregate_frame(per_seed: pd.DataFrame, algorithms: list[str] | None = None, score: str = AGGREGATE_SCORE,
                    confidence: float = 0.95, seed: int = 0) -> pd.DataFrame:
    """Per algorithm: the interquartile mean of ``score`` over all seeds x (training, evaluation) scenario cells
    and its stratified bootstrap interval (seeds resampled within each cell)."""
    from socnav.experiments.statistics import iqm_interval

    rows = []
    for algo in _ordered(per_seed["algo"], algorithms or []):
        tasks = _tasks(per_seed, algo)
        if not tasks:
            continue
        scores = _task_scores(per_seed, algo, tasks, score)
        interval = iqm_interval(scores, confidence, seed=seed)
        rows.append({"algo": algo, "score": score, "n_tasks": len(tasks), "n_runs": sum(map(len, scores)),
                     "iqm": interval.estimate, "iqm_low": interval.low, "iqm_high": interval.high,
                     "mean": float(np.mean([s.mean() for s in scores]))})
    return pd.DataFrame(rows, columns=["algo", "score", "n_tasks", "n_runs", "iqm", "iqm_low", "iqm_high", "mean"])


def comparison_frame(per_seed: pd.DataFrame, reference: str = REFERENCE_ALGO, algorithms: list[str] | None = None,
                     score: str = AGGREGATE_SCORE, confidence: float = 0.95, seed: int = 0) -> pd.DataFrame:
    """The claim "``reference`` scores higher than B" for every other algorithm B (PPO first), over the cells both
    were evaluated in: the mean difference of ``score`` (points) and the probability of improvement, each with
    its stratified bootstrap interval, and the verdict from the difference's interval."""
    from socnav.experiments.statistics import compare

    rows = []
    if reference not in set(per_seed["algo"]):
        return pd.DataFrame(columns=COMPARISON_COLUMNS)
    others = [a for a in _ordered(per_seed["algo"], ["ppo", *(algorithms or [])]) if a != reference]
    for baseline in others:
        tasks = _tasks(per_seed, reference, baseline)
        if not tasks:
            continue
        result = compare(_task_scores(per_seed, reference, tasks, score), _task_scores(per_seed, baseline, tasks, score),
                         confidence, seed=seed)
        rows.append({"algo": reference, "baseline": baseline, "n_tasks": len(tasks),
                     "difference": result.difference.estimate, "difference_low": result.difference.low,
                     "difference_high": result.difference.high, "improvement": result.improvement.estimate,
                     "improvement_low": result.improvement.low, "improvement_high": result.improvement.high,
                     "verdict": result.verdict})
    return pd.DataFrame(rows, columns=COMPARISON_COLUMNS)


def plot_aggregate(aggregate: pd.DataFrame, comparisons: pd.DataFrame, out_base: Path) -> list[Path]:
    """Left: IQM goal rate per algorithm with its 95 % interval; right: probability that the reference algorithm
    improves on each other one, with its interval (0.5: no difference). PNG and SVG."""
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
    left.set_xlabel("IQM goal rate (%), 95 % CI")
    left.set_title("Aggregate over seeds × scenario cells")
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
    right.set_xlabel("probability of improvement, 95 % CI")
    right.grid(alpha=0.3, axis="x")
    figure.tight_layout()
    return save_figure(figure, out_base)


@register_section("table1", "table1_ci")
def table1_ci_section(context: ReportContext) -> str:
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
    lines = [
        "## Table 1 with 95 % confidence intervals over seeds",
        "",
        f"Mean over the training seeds ({seeds} here) [95 % percentile bootstrap interval over seeds] of the "
        "goal rate (%), collision rate (%) and mean return; every Table 1 metric in the CSV. With 2–3 seeds an "
        "interval cannot be wider than the seeds' range and understates the uncertainty; one seed gives none "
        "(`n/a`).",
        "",
        markdown,
        "",
        "### Aggregate goal rate and claims",
        "",
        "Score: the goal (success) rate (%) of each training seed in each (training scenario, evaluation scenario) "
        "cell — the paper ranks algorithms by it, and its scale is the same in every scenario. IQM: interquartile "
        "mean over all seeds × cells; intervals: stratified bootstrap (seeds resampled within each cell), "
        "as `rliable`. Claim *ODV-PPO-Drop reaches the goal more often than Y*: difference of the mean goal rates "
        "(points, averaged over cells) and probability of improvement P(a seed of ODV-PPO-Drop beats a seed of Y in "
        "the same cell); **holds** if the difference's interval is above 0, **does not hold** if below, **cannot "
        "tell at this budget** if it contains 0.",
        "",
        "![aggregate](aggregate.png)",
        "",
        "| Approach | IQM goal (%) [95 % CI] | Mean goal (%) | Seeds × cells |",
        "|:--|--:|--:|--:|",
    ]
    for row in aggregate.to_dict("records"):
        lines.append(f"| {algo_label(row['algo'])} | {_interval_text(row['iqm'], row['iqm_low'], row['iqm_high'], 1)}"
                     f" | {row['mean']:.1f} | {row['n_runs']} |")
    lines.append("")
    if comparisons.empty:
        lines.append(f"No comparison: {algo_label(REFERENCE_ALGO)} and another algorithm are not both in this run.")
    else:
        lines += ["| Claim | Goal difference (points) [95 % CI] | P(improvement) [95 % CI] | Verdict |",
                  "|:--|--:|--:|:--|"]
        for row in comparisons.to_dict("records"):
            lines.append(
                f"| {algo_label(row['algo'])} > {algo_label(row['baseline'])} "
                f"| {_interval_text(row['difference'], row['difference_low'], row['difference_high'], 1)} "
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


def plot_training_curves(frame: pd.DataFrame, out_base: Path, algorithms: list[str] | None = None,
                         scenarios: list[str] | None = None, ylabel: str = "training reward (episode mean)"
                         ) -> list[Path]:
    """One panel per training scenario, one line per algorithm (mean over seeds, band mean ± std); PNG and SVG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    scenarios = _ordered(frame["train_scenario"], scenarios or []) or ["(no finished training)"]
    algorithms = _ordered(frame["algo"], algorithms or [])
    colors = {algo: plt.get_cmap("tab10")(index % 10) for index, algo in enumerate(algorithms)}
    figure, axes = plt.subplots(1, len(scenarios), figsize=(4.6 * len(scenarios), 3.6), squeeze=False)
    for axis, scenario in zip(axes[0], scenarios):
        for algo in algorithms:
            data = frame[(frame["train_scenario"] == scenario) & (frame["algo"] == algo)]
            if data.empty:
                continue
            x, mean, std = (data[c].to_numpy(float) for c in ("timesteps", "mean", "std"))
            axis.plot(x, mean, color=colors[algo], label=algo_label(algo), linewidth=1.6)
            axis.fill_between(x, mean - std, mean + std, color=colors[algo], alpha=0.2, linewidth=0)
        axis.set_title(scenario_label(scenario))
        axis.set_xlabel("timesteps")
        axis.xaxis.set_major_formatter(FuncFormatter(_steps_label))
        axis.grid(alpha=0.3)
    axes[0][0].set_ylabel(ylabel)
    handles, labels = axes[0][0].get_legend_handles_labels()
    for axis in axes[0][1:]:
        more = axis.get_legend_handles_labels()
        for handle, label in zip(*more):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    if handles:
        figure.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), frameon=False)
    figure.tight_layout(rect=(0, 0.1 if handles else 0, 1, 1))
    return save_figure(figure, out_base)


def _steps_label(value: float, _position: Any = None) -> str:
    if abs(value) >= 1e6:
        return f"{value / 1e6:g}M"
    return f"{value / 1e3:g}k" if abs(value) >= 1e3 else f"{value:g}"


@register_section("table1", "training_curves")
def training_curves_section(context: ReportContext) -> str:
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
# Comparison with the paper
# --------------------------------------------------------------------------------------------------------------

_PAPER_ROWS = """
circle_interaction ppo            99.80 0.20 0.00 7 4.50 0.46 | 93.30 4.37 2.33 169 3.66 2.09 | 76.80 4.70 18.50 43 2.63 3.63
circle_interaction ppo-drop       99.90 0.10 0.00 8 4.66 0.42 | 94.40 3.83 1.77 200 3.92 2.01 | 78.70 5.40 15.90 57 2.93 3.65
circle_interaction odv-ppo-noloss 99.47 0.53 0.00 18 4.25 0.65 | 88.57 8.73 2.70 195 2.94 2.64 | 79.27 7.37 13.37 69 2.22 3.59
circle_interaction odv-ppo        99.23 0.77 0.00 17 4.29 0.78 | 89.93 7.80 2.57 225 3.12 2.55 | 77.77 7.50 14.73 80 2.15 3.79
circle_interaction odv-ppo-drop   99.90 0.10 0.00 1 4.52 0.36 | 96.87 2.47 0.67 101 4.04 1.45 | 82.00 4.50 13.50 40 3.02 3.39
circle_crossing ppo               49.57 12.20 38.23 101 -1.25 5.16 | 86.10 7.07 6.83 52 2.17 3.49 | 58.90 7.83 33.27 90 -0.57 5.39
circle_crossing ppo-drop          87.80 1.13 11.07 53 3.15 2.78 | 98.13 1.57 0.30 64 3.91 1.24 | 82.33 4.07 13.60 53 2.71 3.61
circle_crossing odv-ppo-noloss    41.57 9.43 49.00 147 -2.28 4.98 | 71.47 2.03 26.50 63 0.83 4.45 | 40.80 8.63 50.57 95 -2.74 5.30
circle_crossing odv-ppo           38.37 6.67 54.97 76 -2.24 5.42 | 58.90 8.70 32.40 87 0.18 4.84 | 39.60 7.17 53.23 66 -2.51 5.87
circle_crossing odv-ppo-drop      92.90 0.67 6.43 21 3.78 2.35 | 99.10 0.83 0.07 35 4.22 0.88 | 88.07 2.10 9.83 49 3.46 3.14
random ppo                        68.03 5.60 26.37 159 1.36 4.39 | 68.40 8.60 23.00 179 1.15 4.12 | 80.40 2.37 17.23 66 2.44 3.80
random ppo-drop                   91.67 2.43 5.90 67 3.40 2.59 | 86.70 8.13 5.17 219 2.76 3.12 | 90.20 3.30 6.50 64 3.28 2.86
random odv-ppo-noloss             0.00 0.37 99.63 11 -6.53 0.37 | 0.00 0.10 99.90 11 -6.54 0.71 | 0.00 0.10 99.90 6 -6.39 0.80
random odv-ppo                    58.50 2.20 39.30 73 0.19 4.81 | 53.53 3.30 43.17 112 -0.26 4.62 | 59.53 1.17 39.30 47 0.36 4.80
random odv-ppo-drop               99.53 0.30 0.17 8 4.33 0.74 | 97.53 2.43 0.03 77 4.04 1.33 | 99.43 0.47 0.10 14 4.39 0.83
"""


#: The budget of the paper's Table I (configs/experiments/table1.yaml, budget `paper`).
PAPER_BUDGET = {"timesteps": 1_000_000, "seeds": 15, "episodes": 200}


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


def paper_table1() -> pd.DataFrame:
    """The paper's Table I (15 seeds x 200 episodes), in the long form of `table1_frame` (returns are the paper's
    reward instantiation: compare orderings, not absolute values)."""
    rows = []
    evals = ["circle_interaction", "circle_crossing", "random"]
    for line in _PAPER_ROWS.strip().splitlines():
        head, *groups = line.split("|")
        train_scenario, algo, *first = head.split()
        for eval_scenario, values in zip(evals, [first] + [g.split() for g in groups]):
            goal, collision, timeout, pv, ret, std = map(float, values)
            rows.append({"train_scenario": train_scenario, "algo": algo, "eval_scenario": eval_scenario,
                         "goal_pct": goal, "collision_pct": collision, "timeout_pct": timeout, "pv": pv,
                         "return_mean": ret, "return_std": std})
    return pd.DataFrame(rows)


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
    write_table_atomic(merged[ID_COLUMNS + ["goal_pct", "goal_pct_paper", "collision_pct", "collision_pct_paper",
                                            "timeout_pct", "timeout_pct_paper", "pv", "pv_paper"]],
                       context.out_dir / "table1_vs_paper.csv")
    lines = ["## Comparison with the paper (Table I)", ""]
    note = budget_note(context.experiment)
    if note:
        lines += [note, ""]
    if merged.empty:
        return "\n".join(lines + ["No finished cell of this experiment is in the paper's Table I."])
    lines += ["Goal and collision rates (%) of ours / the paper's; *best* = the algorithm with the highest goal rate "
              "per training and evaluation scenario (ours / the paper's, among the algorithms run here). Returns are "
              "not compared (our reward instantiation is our own).", "",
              "| Training scenario | Evaluation scenario | " + " | ".join(
                  algo_label(a) for a in _ordered(merged["algo"], context.experiment["grid"]["algorithms"])
              ) + " | Best (ours / paper) |"]
    algorithms = _ordered(merged["algo"], context.experiment["grid"]["algorithms"])
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

