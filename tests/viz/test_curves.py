"""Training curves: one run's (`socnav.viz.curves.plot_training_curve`, what `socnav plot` draws) and the report's
panels (`socnav.experiments.report.training_curves_figure`), where a curve of one point shows as its mark."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from PIL import Image

from socnav.paper.labels import algo_label
from socnav.paper.table1.curves import training_curve_frame, training_curves_figure
from socnav.rl.training import CURVE_COLUMNS, EVAL_COLUMNS
from socnav.viz.curves import TrainingCurveError, plot_training_curve, training_curve_figure


def write_run(run_dir: Path, steps: list[int], evals: bool = True, rewards: list[float] | None = None) -> Path:
    """A run directory as `socnav train` leaves it: curve.csv (a row per rollout) and eval.csv."""
    run_dir.mkdir(parents=True, exist_ok=True)
    n = len(steps)
    rewards = rewards if rewards is not None else list(np.linspace(-20.0, 5.0, n))
    pd.DataFrame({"timesteps": steps, "wall_time_s": np.arange(1, n + 1) * 2.0, "ep_rew_mean": rewards,
                  "ep_len_mean": np.full(n, 40.0), "success_rate": np.linspace(0.0, 0.8, n)},
                 columns=CURVE_COLUMNS).to_csv(run_dir / "curve.csv", index=False)
    if evals:
        pd.DataFrame({"timesteps": steps, "wall_time_s": np.arange(1, n + 1) * 2.5, "episodes": 10,
                      "goal_pct": np.linspace(0.0, 90.0, n), "collision_pct": np.linspace(50.0, 10.0, n),
                      "timeout_pct": np.linspace(50.0, 0.0, n), "pv": 3.0, "return_mean": np.linspace(-18, 6, n),
                      "return_std": 1.5}, columns=EVAL_COLUMNS).to_csv(run_dir / "eval.csv", index=False)
    return run_dir


def lines_by_label(figure: Figure) -> dict[str, Line2D]:
    """The labelled lines of every panel (error bars' caps aside)."""
    return {line.get_label(): line for axis in figure.axes for line in axis.get_lines()
            if not line.get_label().startswith("_")}


def test_the_run_curve_is_a_png_of_return_and_rates(tmp_path):
    run = write_run(tmp_path / "run", [256, 512, 768, 1024])
    out = plot_training_curve(run, tmp_path / "plots" / "curve.png")
    assert out == tmp_path / "plots" / "curve.png"
    with Image.open(out) as image:
        assert image.format == "PNG" and image.size[0] > image.size[1] > 300
    assert [p.name for p in out.parent.iterdir()] == ["curve.png"], "no temporary file left"

    figure = training_curve_figure(run)
    lines = lines_by_label(figure)
    training, validation = lines["training episodes (mean of the last 100)"], lines["validation episodes (± std)"]
    assert list(training.get_xdata()) == [256, 512, 768, 1024]
    assert np.allclose(training.get_ydata(), np.linspace(-20.0, 5.0, 4))
    assert np.allclose(validation.get_ydata(), np.linspace(-18, 6, 4))
    goal = lines["goal, training episodes (last 100)"]
    assert np.allclose(goal.get_ydata(), np.linspace(0.0, 80.0, 4)), "the training success rate, in %"
    assert np.allclose(lines["collision (human), validation episodes"].get_ydata(), np.linspace(50.0, 10.0, 4))
    assert "collision (wall), validation episodes" not in lines, "eval.csv has no wall column: no line"
    assert [axis.get_xlabel() for axis in figure.axes] == ["timesteps", "timesteps"]


def test_a_curve_of_one_point_shows(tmp_path):
    run = write_run(tmp_path / "run", [256])
    figure = training_curve_figure(run)
    figure.canvas.draw()
    for label, line in lines_by_label(figure).items():
        assert line.get_marker() not in (None, "", "None", " "), label
        box = line.get_window_extent(figure.canvas.get_renderer())
        axes = line.axes.get_window_extent(figure.canvas.get_renderer())
        assert box.width > 3 and box.height > 3 and axes.contains(*box.get_points().mean(axis=0)), label


def test_a_run_whose_episodes_have_not_ended_says_so(tmp_path):
    run = write_run(tmp_path / "run", [256, 512], evals=False, rewards=[float("nan")] * 2)
    (run / "curve.csv").write_text("timesteps,wall_time_s,ep_rew_mean,ep_len_mean,success_rate\n256,1.0,,,\n")
    figure = training_curve_figure(run)
    texts = [text.get_text() for axis in figure.axes for text in axis.texts]
    assert texts == ["no training episode has ended yet"] * 2
    assert plot_training_curve(run, tmp_path / "c.png").is_file()


@pytest.mark.parametrize("make, words", [
    (lambda d: d, "curve.csv is missing"),  # an empty directory
    (lambda d: d / "absent", "is not a directory"),
    (lambda d: (d / "file.txt").write_text("x") and d / "file.txt", "is not a directory"),
    (lambda d: (d / "curve.csv").write_text("step,reward\n1,2\n") and d, "has no column timesteps"),
    (lambda d: (d / "curve.csv").write_bytes(b"") is not None and d, "unreadable"),
])
def test_a_directory_without_a_curve_is_one_line(tmp_path, make, words):
    run_dir = make(tmp_path)
    with pytest.raises(TrainingCurveError) as error:
        plot_training_curve(run_dir, tmp_path / "c.png")
    message = str(error.value)
    assert words in message and "\n" not in message and str(run_dir) in message
    assert not (tmp_path / "c.png").exists()


def test_only_a_png_is_written_and_a_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    run = write_run(tmp_path / "run", [256, 512])
    with pytest.raises(TrainingCurveError, match="PNG"):
        plot_training_curve(run, tmp_path / "c.svg")
    out = tmp_path / "c.png"
    out.write_bytes(b"old")

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(OSError, match="disk full"):
        plot_training_curve(run, out)
    assert out.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["c.png", "run"]


# ---------------------------------------------------------------------------- the report's training-curve panels

def report_curves() -> pd.DataFrame:
    """Five algorithms, two seeds each, on one scenario; three of them logged once (a curve of one point)."""
    rows = []
    for algo, steps in (("ppo", [1000, 2000, 3000]), ("ppo-drop", [1000]), ("odv-ppo-noloss", [2000]),
                        ("odv-ppo", [1000, 2000, 3000]), ("odv-ppo-drop", [3000])):
        for seed in (0, 1):
            for step in steps:
                rows.append({"train_scenario": "random", "algo": algo, "seed": seed, "timesteps": step,
                             "ep_rew_mean": step / 1000 + seed + len(algo)})
    return pd.DataFrame(rows)


def test_every_algorithm_of_the_report_curves_is_a_visible_mark():
    frame = training_curve_frame(report_curves())
    algorithms = ["ppo", "ppo-drop", "odv-ppo-noloss", "odv-ppo", "odv-ppo-drop"]
    assert frame.groupby("algo").size().to_dict() == {"ppo": 3, "ppo-drop": 1, "odv-ppo-noloss": 1, "odv-ppo": 3,
                                                      "odv-ppo-drop": 1}
    figure = training_curves_figure(frame, algorithms, ["random"])
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    (axis,) = figure.axes
    lines = {line.get_label(): line for line in axis.get_lines() if not line.get_label().startswith("_")}
    assert set(lines) == {algo_label(algo) for algo in algorithms}
    panel = axis.get_window_extent(renderer)
    markers = set()
    for label, line in lines.items():
        assert line.get_visible() and line.get_marker() not in (None, "", "None", " "), label
        markers.add(line.get_marker())
        box = line.get_window_extent(renderer)
        assert box.width >= 4 and box.height >= 4, f"{label}: drawn {box.width:.1f} x {box.height:.1f} px"
        x, y = axis.transData.transform(np.column_stack([line.get_xdata(), line.get_ydata()])).T
        assert all(panel.contains(a, b) for a, b in zip(x, y, strict=True)), f"{label} lies outside the panel"
    assert len(markers) == 5, "each algorithm its own mark"
    legend = [text.get_text() for text in figure.legends[0].get_texts()]
    assert legend == [algo_label(algo) for algo in algorithms]
    whole, legend_box = figure.bbox, figure.legends[0].get_window_extent(renderer)
    assert whole.x0 <= legend_box.x0 and legend_box.x1 <= whole.x1 and whole.y0 <= legend_box.y0, "legend cut off"
    assert legend_box.y1 <= panel.y0 - axis.xaxis.get_tightbbox(renderer).height + 2, "legend under the axis"
    import matplotlib.pyplot as plt

    plt.close(figure)
