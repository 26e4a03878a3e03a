"""Table 1 of the paper: per (training scenario, algorithm, evaluation scenario) the mean over seeds of each per-seed
metric, as Markdown and CSV (the metrics are described in `socnav.paper.table1.report`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.labels import algo_label, preferred_then_seen, scenario_label
from socnav.sim.metrics import ALL_METRICS, PV_PER, summarize_groups

if TYPE_CHECKING:
    pass


ID_COLUMNS = ["train_scenario", "algo", "eval_scenario"]
TABLE1_COLUMNS = [*ID_COLUMNS, "n_seeds", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv",
                  "return_mean", "return_std", "return_seed_std"]
#: Table 1's per-seed metrics (registry names, `socnav.sim.metrics.METRICS`), in their column order.
TABLE1_SEED_METRICS = ["goal_pct", "collision_pct", "timeout_pct", "pv", "return_mean"]
#: Every other metric of the registry, appended to table1.csv (Table 1's return spread is over all episodes, so a
#: per-seed return_std is not one of them).
EXTRA_METRICS = [name for name in ALL_METRICS if name not in TABLE1_SEED_METRICS and name != "return_std"]



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
