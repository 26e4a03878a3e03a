"""Reports of finished (or partly finished) experiments: tables as Markdown + CSV, figures as PNG + SVG, and one
Markdown page, ``report.md``, that holds them.

The page is assembled from *sections* registered per experiment kind (``@register_section("table1", ...)``): each
section gets a :class:`ReportContext` (the run directory, its resolved experiment, the finished units and their
records), writes its own files into the report directory and returns its Markdown. Later experiments (uncertainty
vs perturbation, prevented collisions) add their sections for their own kinds without touching this module.

Table 1 metrics, per (training scenario, algorithm, evaluation scenario), each the mean over seeds of the per-seed
value computed from that seed's test episodes:
Goal %, Col. %, TO %  -- share of episodes ending at the goal / in a collision / in a time-out;
PV                    -- proxemic-violation events (entering a human's personal space) per 200 episodes;
Return                -- mean over seeds of the per-seed mean episode return, +- the standard deviation over all
                         test episodes of all seeds (population std, ddof=0: the spread a user sees per episode).
The CSV adds ``return_seed_std`` (std over seeds of the per-seed mean return) and the seed / episode counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import pandas as pd

from socnav.experiments.runner import read_plan, unit_dir, unit_states
from socnav.experiments.spec import Unit
from socnav.io import atomic_path, read_table, write_table_atomic, write_text_atomic

__all__ = [
    "ReportContext", "SECTIONS", "build_report", "register_section", "table1_frame", "table1_markdown",
    "training_curve_frame", "plot_training_curves",
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
# Context and section registry
# --------------------------------------------------------------------------------------------------------------

@dataclass
class ReportContext:
    """What a section sees: the run directory, its resolved experiment, its units and which of them are done."""

    results_dir: Path
    out_dir: Path
    experiment: dict[str, Any]
    units: list[Unit]
    states: dict[str, str]
    _cache: dict[str, Any] = field(default_factory=dict)

    def done(self, kind: str | None = None) -> list[Unit]:
        return [u for u in self.units if self.states[u.id] == "done" and (kind is None or u.kind == kind)]

    def missing(self, kind: str | None = None) -> list[Unit]:
        return [u for u in self.units if self.states[u.id] != "done" and (kind is None or u.kind == kind)]

    def episode_records(self) -> pd.DataFrame:
        """All finished evaluation units' per-episode records (with train_scenario, algo, train_seed, eval_scenario)."""
        if "episodes" not in self._cache:
            frames = [read_table(unit_dir(self.results_dir, u) / "episodes.parquet") for u in self.done("eval")]
            self._cache["episodes"] = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(
                columns=["train_scenario", "algo", "train_seed", "eval_scenario", "episode", "outcome", "return",
                         "intrusion_events"])
        return self._cache["episodes"]

    def training_curves(self) -> pd.DataFrame:
        """All finished training units' curve.csv rows with train_scenario, algo and seed columns."""
        if "curves" not in self._cache:
            frames = []
            for unit in self.done("train"):
                curve = read_table(unit_dir(self.results_dir, unit) / "curve.csv")
                curve.insert(0, "seed", unit.params["seed"])
                curve.insert(0, "algo", unit.params["algo"])
                curve.insert(0, "train_scenario", unit.params["train_scenario"])
                frames.append(curve)
            self._cache["curves"] = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(
                columns=["train_scenario", "algo", "seed", "timesteps", "ep_rew_mean"])
        return self._cache["curves"]


Section = Callable[[ReportContext], str]
#: experiment kind -> [(section name, function writing its files and returning its Markdown)], in page order.
SECTIONS: dict[str, list[tuple[str, Section]]] = {}


def register_section(kind: str, name: str) -> Callable[[Section], Section]:
    """Decorator adding a report section for experiments of `kind` (sections appear in registration order)."""

    def decorate(function: Section) -> Section:
        sections = SECTIONS.setdefault(kind, [])
        sections[:] = [(n, f) for n, f in sections if n != name] + [(name, function)]
        return function

    return decorate


def build_report(results_dir: str | Path, out_dir: str | Path | None = None) -> Path:
    """Write every section of the run directory's experiment kind and ``report.md``; returns report.md's path."""
    results_dir = Path(results_dir)
    experiment, units = read_plan(results_dir)
    out_dir = Path(out_dir) if out_dir is not None else results_dir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    context = ReportContext(results_dir, out_dir, experiment, units, unit_states(results_dir, units))
    kind = experiment.get("kind", "table1")
    if kind not in SECTIONS:
        raise ValueError(f"no report sections for experiment kind {kind!r}; known kinds: {', '.join(SECTIONS)}")
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

def table1_frame(records: pd.DataFrame, pv_per: int = PV_PER) -> pd.DataFrame:
    """Table 1 in long form from per-episode records (columns train_scenario, algo, train_seed, eval_scenario,
    outcome, return, intrusion_events): one row per (training scenario, algorithm, evaluation scenario)."""
    if records.empty:
        return pd.DataFrame(columns=TABLE1_COLUMNS)
    keys = ID_COLUMNS + ["train_seed"]
    outcome = records["outcome"]
    per_episode = records.assign(goal=(outcome == "goal") * 100.0, collision=(outcome == "collision") * 100.0,
                                 timeout=(outcome == "timeout") * 100.0)
    per_seed = per_episode.groupby(keys, sort=False).agg(
        episodes=("return", "size"), goal_pct=("goal", "mean"), collision_pct=("collision", "mean"),
        timeout_pct=("timeout", "mean"), events=("intrusion_events", "sum"), return_mean=("return", "mean"),
    ).reset_index()
    per_seed["pv"] = per_seed["events"] * pv_per / per_seed["episodes"]
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
    paths = []
    for suffix in (".png", ".svg"):
        path = out_base.with_suffix(suffix)
        with atomic_path(path) as temporary:
            figure.savefig(temporary, format=suffix[1:], dpi=150)
        paths.append(path)
    plt.close(figure)
    return paths


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


from socnav.experiments import uncertainty_report  # noqa: E402,F401
