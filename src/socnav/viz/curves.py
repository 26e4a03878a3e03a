"""The training curve of one run, as a PNG: what `socnav plot RUN_DIR` draws.

A training run's directory (`socnav train --out DIR`, `socnav.rl.training`) holds ``curve.csv`` (the training
episodes: ``timesteps, wall_time_s, ep_rew_mean, ep_len_mean, success_rate``, a row per rollout) and, once the
periodic evaluation has run, ``eval.csv`` (validation episodes: ``goal_pct, collision_pct, timeout_pct, pv,
return_mean, return_std`` and, in worlds with walls, ``collision_obstacle_pct``). The figure has two panels against
timesteps: the return (training episodes; validation episodes with ± one standard deviation) and the rates in %
(goal rate of the training episodes; goal and collision rates of the validation episodes). Every line carries
markers, so a curve of one point (a run of one rollout) shows.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from socnav.io import atomic_path, read_json, read_table

if TYPE_CHECKING:  # pandas loads with the first curve read: `import socnav.viz` stays light
    import pandas as pd

__all__ = ["CURVE_FILE", "EVAL_FILE", "TrainingCurveError", "plot_training_curve", "training_curve_figure"]

CURVE_FILE = "curve.csv"
EVAL_FILE = "eval.csv"
#: curve.csv's columns the figure reads (`socnav.rl.training.CURVE_COLUMNS`)
CURVE_NEEDS = ("timesteps", "ep_rew_mean", "success_rate")
TRAIN_COLOR, GOAL_COLOR, COLLISION_COLOR, WALL_COLOR = "#3a6ea5", "#2a9d8f", "#d62828", "#6c5b7b"


class TrainingCurveError(ValueError):
    """A directory without a readable training curve (one line: which directory, what is missing)."""


def _steps_label(value: float, _position: Any = None) -> str:
    """12000 -> 12k, 1500000 -> 1.5M."""
    if abs(value) >= 1e6:
        return f"{value / 1e6:g}M"
    return f"{value / 1e3:g}k" if abs(value) >= 1e3 else f"{value:g}"


def _read(path: Path, needs: tuple[str, ...]) -> pd.DataFrame:
    """The table at `path`, its rows sorted by timesteps; TrainingCurveError if unreadable or a column is missing."""
    import pandas as pd

    try:
        table = read_table(path)
    except (OSError, ValueError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise TrainingCurveError(f"{path} is unreadable ({type(exc).__name__}): not a training curve") from None
    missing = [column for column in needs if column not in table.columns]
    if missing:
        raise TrainingCurveError(f"{path} has no column {', '.join(missing)}: not a training curve of socnav train")
    return table.sort_values("timesteps", kind="stable")


def _title(run_dir: Path) -> str:
    """'odv-ppo-drop on position_swap, seed 0 (run DIR)' from run.json, else the directory's name."""
    try:
        run = read_json(run_dir / "run.json")
        scenario = run["env_config"]["scenario"]
        return f"{run['algo']} on {scenario}, seed {run['seed']} ({run_dir.name})"
    except (OSError, ValueError, KeyError, TypeError):
        return f"training run {run_dir.name}"


def _line(axis: Axes, table: pd.DataFrame, column: str, scale: float = 1.0, **style: Any) -> bool:
    """Plot `column` vs timesteps (rows with a value), markers on every point; False when it has no value."""
    data = table.dropna(subset=[column]) if column in table.columns else table.iloc[:0]
    if data.empty:
        return False
    x, y = data["timesteps"].to_numpy(float), data[column].to_numpy(float) * scale
    axis.plot(x, y, markersize=4 if len(x) > 1 else 7, linewidth=1.6, **style)
    return True


def training_curve_figure(run_dir: str | Path) -> Figure:
    """The figure `plot_training_curve` writes (a headless Agg figure, no pyplot): return and rates vs timesteps.

    :raises TrainingCurveError: `run_dir` is not a directory, or holds no readable ``curve.csv``.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise TrainingCurveError(f"{run_dir} is not a directory: give a training run's directory "
                                 f"(socnav train --out DIR), which holds {CURVE_FILE}")
    if not (run_dir / CURVE_FILE).is_file():
        raise TrainingCurveError(f"no training curve in {run_dir}: {CURVE_FILE} is missing (socnav train writes it "
                                 "into its --out directory at the first rollout)")
    curve = _read(run_dir / CURVE_FILE, CURVE_NEEDS)
    evals = _read(run_dir / EVAL_FILE, ("timesteps",)) if (run_dir / EVAL_FILE).is_file() else None

    figure = Figure(figsize=(10.0, 4.0), dpi=100, facecolor="white")
    FigureCanvasAgg(figure)
    returns, rates = figure.subplots(1, 2)
    drawn = _line(returns, curve, "ep_rew_mean", color=TRAIN_COLOR, marker="o",
                  label="training episodes (mean of the last 100)")
    drawn_rates = _line(rates, curve, "success_rate", 100.0, color=GOAL_COLOR, marker="o",
                        label="goal, training episodes (last 100)")
    if evals is not None:
        if _line(returns, evals, "return_mean", color="black", marker="s", linestyle="--",
                 label="validation episodes (± std)"):
            drawn = True
            if "return_std" in evals.columns:
                data = evals.dropna(subset=["return_mean", "return_std"])
                returns.errorbar(data["timesteps"].to_numpy(float), data["return_mean"].to_numpy(float),
                                 yerr=data["return_std"].to_numpy(float), fmt="none", ecolor="black", alpha=0.4,
                                 capsize=3)
        for column, color, marker, words in (("goal_pct", GOAL_COLOR, "s", "goal"),
                                             ("collision_pct", COLLISION_COLOR, "^", "collision (human)"),
                                             ("collision_obstacle_pct", WALL_COLOR, "v", "collision (wall)")):
            drawn_rates |= _line(rates, evals, column, color=color, marker=marker, linestyle="--",
                                 label=f"{words}, validation episodes")
    for axis, ylabel, shown in ((returns, "episode return", drawn), (rates, "share of episodes (%)", drawn_rates)):
        axis.set_xlabel("timesteps")
        axis.set_ylabel(ylabel)
        axis.xaxis.set_major_formatter(FuncFormatter(_steps_label))
        axis.grid(alpha=0.3)
        if shown:
            axis.legend(fontsize=8, loc="best")
        else:
            axis.text(0.5, 0.5, "no training episode has ended yet", transform=axis.transAxes, ha="center",
                      va="center", color="#555555")
    returns.set_title("return")
    rates.set_title("goal and collision rates")
    rates.set_ylim(-3.0, 103.0)
    figure.suptitle(_title(run_dir), fontsize=11)
    figure.tight_layout()
    return figure


def plot_training_curve(run_dir: Path, out: Path) -> Path:
    """Draw the training curve of the run in `run_dir` (its ``curve.csv``, and ``eval.csv`` when there) as the PNG
    `out`, written atomically (a temporary sibling moved into place; parent directories are created); returns `out`.

    :raises TrainingCurveError: `run_dir` holds no readable training curve, or `out` is not a ``.png`` (one line).
    """
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise TrainingCurveError(f"the training-curve picture is a PNG: give a .png file, not {out}")
    figure = training_curve_figure(run_dir)
    with atomic_path(out) as temporary:
        figure.savefig(temporary, format="png", dpi=120)
    figure.clear()
    return out

