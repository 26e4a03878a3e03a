"""Training curves of Table 1's runs: the mean validation reward against training steps, per algorithm and
training scenario.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import save_figure, write_table_atomic
from socnav.paper.labels import algo_label, preferred_then_seen, scenario_label

if TYPE_CHECKING:
    pass


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
