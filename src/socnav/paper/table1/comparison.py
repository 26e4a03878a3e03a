"""Table 1 next to the paper's: goal and collision rates, and whether its ranking of algorithms holds."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import write_table_atomic
from socnav.paper.labels import algo_label, preferred_then_seen, scenario_label
from socnav.paper.published import PAPER_BUDGET, paper_table1
from socnav.paper.table1.tables import ID_COLUMNS, table1_frame

if TYPE_CHECKING:
    pass


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
