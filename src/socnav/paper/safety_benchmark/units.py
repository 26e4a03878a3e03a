"""The `safety_benchmark` experiment kind: its unit executor (one training seed's policy through the whole benchmark)
and its report section (every layer against proximity-only, across the training seeds' acting policies)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from socnav.envs.perturbations import strength_zero
from socnav.experiments.registry import (
    ExecutorResult,
    ReportContext,
    file_digest,
    register_executor,
    register_section,
    single_threaded_torch,
    unit_dir,
)
from socnav.experiments.spec import Unit
from socnav.io import read_table, write_table_atomic, write_text_atomic
from socnav.paper.safety_benchmark.benchmark import (
    BENCHMARK_ROWS,
    CALIBRATION_SCORES,
    HELD_OUT_SHIFTS,
    LAYERS_FILE,
    REFERENCE_ROWS,
    BenchmarkSetup,
    Layer,
    load_layers,
    replay_shift,
    run_safety_benchmark,
    summarize_layers,
)

__all__ = ["benchmark_markdown", "calibration_table", "deployment_choice", "seed_differences", "verdicts"]

SHIFT_TYPES = ("behaviour_shift",)  # perturbation types that are held-out shifts, not the paper's


@register_executor("safety_benchmark", resumable=lambda directory: (directory / LAYERS_FILE).is_file())
def _execute_benchmark(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.rl.persistence import load_policy
    from socnav.uncertainty import MC_SEED, MCDropoutEstimator

    p = unit.params
    single_threaded_torch()
    train = next(dep for dep in unit.deps if dep.startswith("train/"))
    model = unit_dir(root, train) / "model.zip"
    policy = load_policy(model)
    estimator = MCDropoutEstimator(policy, k=p["k"], seed=MC_SEED)
    paper_types = {kind: [s for s in strengths if s != strength_zero(kind)]
                   for kind, strengths in p["perturbations"].items() if kind not in SHIFT_TYPES}
    setup = BenchmarkSetup(env=p["env"], budgets=p["budgets"], calibration_episodes=p["calibration_episodes"],
                           risk_training_episodes=3 * p["calibration_episodes"], eval_episodes=p["episodes"],
                           eval_seed=p["seed"], sensing=p["sensing"], window=p["window"],
                           n_envs=min(p["n_envs"], 40), paper_types={k: v for k, v in paper_types.items() if v},
                           shifts={**HELD_OUT_SHIFTS, **replay_shift(p.get("replay_files", []))},
                           rows=tuple(p["triggers"]) or BENCHMARK_ROWS)
    log_lines: list[str] = []

    def log(message: str) -> None:
        log_lines.append(message)
        write_text_atomic(directory / "log.txt", "\n".join(log_lines) + "\n")

    run_safety_benchmark(policy, estimator, setup, directory, log)
    episodes = read_table(directory / "episodes.csv")
    episodes.insert(0, "train_seed", p["train_seed"])
    write_table_atomic(episodes, directory / "episodes.parquet")
    (directory / "episodes.csv").unlink()
    outputs = ["episodes.parquet", "summary.csv", "layers.yaml", "log.txt"]
    outputs += sorted(path.name for path in directory.glob("*.npz"))
    return ExecutorResult(outputs=outputs, inputs={f"{train}/model.zip": file_digest(model)})


def seed_differences(episodes: pd.DataFrame) -> pd.DataFrame:
    """Per training seed and layer: the collision rate over the paper's perturbation types minus proximity-only's
    at the same budget (cautious fallback), the false activation on the unperturbed episodes, and the collision rate
    in the unperturbed world and each shift minus proximity-only's."""
    rows = []
    episodes = episodes.assign(fallback=episodes["fallback"].fillna(""))  # a CSV reads the references' '' as NaN
    for seed, mine in episodes.groupby("train_seed"):
        paper = ~mine["group"].isin(["unperturbed", "shift"])
        for (name, budget, fallback), layer in mine.groupby(["layer", "budget", "fallback"]):
            if name in REFERENCE_ROWS:
                continue
            base = mine[(mine["layer"] == "proximity-only") & np.isclose(mine["budget"], budget)
                        & (mine["fallback"] == "cautious")]
            unperturbed = layer[layer["group"] == "unperturbed"]
            row = {"train_seed": seed, "layer": name, "budget": budget, "fallback": fallback,
                   "false_activation_pct": 100.0 * unperturbed["fallback_steps"].sum()
                   / max(unperturbed["length"].sum(), 1)}
            for label, select in [("paper_types", paper), ("unperturbed", mine["group"] == "unperturbed")] + [
                    (world, mine["world"] == world) for world in sorted(mine.loc[mine["group"] == "shift", "world"]
                                                                        .unique())]:
                ours = layer.loc[select.loc[layer.index], "collided"].mean()
                theirs = base.loc[select.loc[base.index], "collided"].mean() if len(base) else math.nan
                row[f"collision_pct_{label}"] = 100.0 * ours
                row[f"diff_pct_{label}"] = 100.0 * (ours - theirs)
            rows.append(row)
    return pd.DataFrame(rows)


def verdicts(differences: pd.DataFrame, confidence: float = 0.95) -> pd.DataFrame:
    """Per layer: the mean over training seeds (the clusters) of the difference in collision rate against
    proximity-only over the paper's types, its t interval, and a verdict at the family-wise error rate: Holm over
    the rows of each budget (both fallbacks), one-sided (``fewer`` only when the Holm-adjusted p is below
    1 - confidence)."""
    from scipy import stats

    from socnav.experiments.statistics import holm_adjust

    rows = []
    for (name, budget, fallback), group in differences.groupby(["layer", "budget", "fallback"]):
        values = group["diff_pct_paper_types"].dropna().to_numpy()
        n = len(values)
        mean = float(values.mean()) if n else math.nan
        sd = float(values.std(ddof=1)) if n > 1 else math.nan
        half = float(stats.t.ppf(0.5 + confidence / 2, n - 1)) * sd / math.sqrt(n) if n > 1 else math.nan
        # H0: no fewer collisions than proximity-only; H1: fewer (one-sided t over the seeds)
        p = float(stats.t.cdf(mean / (sd / math.sqrt(n)), n - 1)) if n > 1 and sd > 0 else math.nan
        rows.append({"layer": name, "budget": budget, "fallback": fallback, "seeds": n, "diff_pct": mean,
                     "sd": sd,
                     "low": mean - half, "high": mean + half, "p_fewer": p,
                     "unperturbed_diff_pct": float(group["diff_pct_unperturbed"].mean()),
                     "false_activation_pct": float(group["false_activation_pct"].mean())})
    table = pd.DataFrame(rows)
    if table.empty:
        return table
    table["p_holm"] = math.nan
    for _budget, block in table.groupby("budget"):
        tested = block[~((block["layer"] == "proximity-only") & (block["fallback"] == "cautious"))
                       & block["p_fewer"].notna()]
        if len(tested):
            table.loc[tested.index, "p_holm"] = holm_adjust(tested["p_fewer"].to_numpy())
    alpha = 1.0 - confidence
    table["detectable_pct"] = _detectable(table, alpha)
    beaten = (table["layer"] == "proximity-only") & (table["fallback"] == "cautious")
    table["verdict"] = np.where(table["p_holm"] < alpha, "fewer collisions",
                                np.where(beaten, "(the row to beat)", "not established"))
    return table


def _detectable(table: pd.DataFrame, alpha: float, power: float = 0.8) -> pd.Series:
    """The power of each row's verdict: the smallest true difference (percentage points, fewer collisions) its
    one-sided t test over the seeds detects with probability ``power`` at the strictest Holm level of its budget
    (alpha / the rows tested there), given the spread of its per-seed differences:
    ``(t_{1 - alpha/m} + t_{power}) * sd / sqrt(n)``."""
    from scipy import stats

    tested = table["p_fewer"].notna()
    rows = tested.groupby(table["budget"]).transform("sum").clip(lower=1)
    n = table["seeds"].astype(float)
    sd = table["sd"]
    quantiles = stats.t.ppf(1 - alpha / rows, np.maximum(n - 1, 1)) + stats.t.ppf(power, np.maximum(n - 1, 1))
    return pd.Series(np.where(tested, quantiles * sd / np.sqrt(n), np.nan), index=table.index)


@register_section("safety_benchmark", "safety_benchmark")
def _section(context: ReportContext) -> str:
    done = context.done("safety_benchmark")
    if not done:
        return "## Safety-layer benchmark\n\nNo benchmark unit has finished yet.\n"
    episodes = pd.concat([read_table(unit_dir(context.results_dir, unit) / "episodes.parquet") for unit in done],
                         ignore_index=True)
    planned = len([unit for unit in context.units if unit.kind == "safety_benchmark"])
    layers = [load_layers(unit_dir(context.results_dir, unit) / LAYERS_FILE) for unit in done]
    return benchmark_markdown(episodes, context.out_dir, f"{len(done)} of {planned} training seeds' acting policies",
                              layers=layers)


def calibration_table(layers: Sequence[Sequence[Layer]]) -> pd.DataFrame:
    """Per row (layer, budget, fallback): what the calibration measured of it on the calibration episodes, in
    percent, averaged over the acting policies (one list of layers each)."""
    names = [f"calibration_{key}" for key in CALIBRATION_SCORES]
    rows = [{"layer": layer.name, "budget": layer.budget, "fallback": layer.fallback,
             **{name: 100.0 * layer.calibration.get(key, math.nan) for name, key in zip(names, CALIBRATION_SCORES,
                                                                                           strict=True)}}
            for policy in layers for layer in policy]
    if not rows:
        return pd.DataFrame(columns=["layer", "budget", "fallback", *names])
    return pd.DataFrame(rows).groupby(["layer", "budget", "fallback"], as_index=False, sort=False)[names].mean()


def deployment_choice(calibration: pd.DataFrame, budget: float) -> str | None:
    """The row to deploy at ``budget``, chosen on the calibration episodes alone, as the calibration chooses within a
    trigger: the most prevented on the worst perturbation type, then on the mean over types (None: no row measured)."""
    rows = calibration[np.isclose(calibration["budget"], budget) & (calibration["fallback"] == "cautious")
                       & calibration["calibration_prevented_worst"].notna()]
    if rows.empty:
        return None
    best = rows.sort_values(["calibration_prevented_worst", "calibration_prevented_fraction"], ascending=False,
                            kind="stable").iloc[0]
    return str(best["layer"])


def benchmark_markdown(episodes: pd.DataFrame, out_dir: Path, policies: str, level: str = "##",
                       title: str = "Safety-layer benchmark", layers: Sequence[Sequence[Layer]] = ()) -> str:
    """The benchmark's table (one row per layer) and trade-off figure, written to ``out_dir`` with its CSV files.

    With two or more training seeds, the verdict against proximity-only treats the seeds as the clusters
    (:func:`verdicts`); with one, it pairs the episodes (the exact McNemar test of `summarize_layers`); either way
    Holm-adjusted over the rows of each budget (both fallbacks), one-sided for fewer collisions. ``layers`` (one list
    per acting policy): the calibration's own scores are shown beside, and the row to deploy is chosen on them
    alone."""
    pooled = summarize_layers(episodes)
    attrs = dict(pooled.attrs)  # a merge drops them
    calibration = calibration_table(layers)
    pooled = pooled.merge(calibration, on=["layer", "budget", "fallback"], how="left")
    pooled.attrs = attrs
    seeds = episodes["train_seed"].nunique() if "train_seed" in episodes else 1
    write_table_atomic(pooled, out_dir / "safety_benchmark_pooled.csv")
    if seeds >= 2:
        differences = seed_differences(episodes)
        table = verdicts(differences)
        write_table_atomic(differences, out_dir / "safety_benchmark_seeds.csv")
    else:
        table = _episode_verdicts(pooled)
    write_table_atomic(table, out_dir / "safety_benchmark_verdicts.csv")
    _tradeoff_figure(pooled, out_dir / "safety_benchmark_tradeoff")
    unit = "seeds" if seeds >= 2 else "episodes"
    shown = ("prevented_paper_types_pct", "prevented_unperturbed_pct")
    shift_columns = [c.removeprefix("prevented_").removesuffix("_pct") for c in pooled.columns
                     if c.startswith("prevented_") and c not in shown]
    lines = [f"{level} {title}", "",
             f"{policies}; collisions of the plain policy over the paper's perturbation types: "
             f"{pooled.attrs['plain_collisions_paper_types']}. Prevented: share of the plain policy's collisions "
             "that the layer prevents on the same episodes (negative: it causes more); false activation: share of "
             "held-out unperturbed steps on which the fallback drove; the difference in collision rate against "
             f"proximity-only at the same budget (percentage points; 95 % interval over the {unit}), and its "
             "Holm-adjusted one-sided p for fewer collisions. `stand-still`: a robot that never moves (the "
             "collisions no robot avoids by stopping); unavoidable: those of the paper's types in episodes where "
             "the robot that never moves is hit too; collisions with the fallback driving: those of the paper's "
             "types whose last step the fallback drove (with the brake: the robot had stopped when the trigger "
             "fired and was still hit)."
             + (" Detectable: the smallest difference the row's test finds with 80 % power at the strictest Holm "
                "level of its budget, from the spread of its per-seed differences." if seeds >= 2 else ""), "",
             "| layer | budget | fallback | calibration: prevented, worst type / mean % | false act. % | "
             "collisions, paper's types | unavoidable | prevented, paper's types % | "
             "unperturbed % | " + " | ".join(f"{name} %" for name in shift_columns)
             + " | collisions with the fallback driving | vs proximity-only, pp [95 % CI] | "
             + ("detectable, pp | " if seeds >= 2 else "") + "Holm p | verdict |",
             "|---|---|---|---|---|---|---|---|---|" + "---|" * len(shift_columns) + "---|---|---|---|"
             + ("---|" if seeds >= 2 else "")]
    for row in pooled[pooled["layer"] != "plain"].itertuples(index=False):
        match = table[(table["layer"] == row.layer) & np.isclose(table["budget"], row.budget)
                      & (table["fallback"] == row.fallback)]
        verdict = match.iloc[0] if len(match) else None
        interval = ("" if verdict is None or not np.isfinite(verdict.diff_pct) else
                    f"{verdict.diff_pct:+.1f} [{verdict.low:+.1f}, {verdict.high:+.1f}]")
        shifts = " | ".join(_share(getattr(row, f"prevented_{name}_pct"), 0) for name in shift_columns)
        detectable = "" if seeds < 2 else (
            "| " if verdict is None or not np.isfinite(verdict.detectable_pct) else f"{verdict.detectable_pct:.1f} | ")
        reference = row.layer in REFERENCE_ROWS
        lines.append(f"| {row.layer} | {'–' if reference else f'{row.budget:.0%}'} | "
                     f"{'–' if reference else row.fallback} | "
                     f"{_share(row.calibration_prevented_worst, 0)} / "
                     f"{_share(row.calibration_prevented_fraction, 0)} | "
                     f"{row.false_activation_pct:.2f} | "
                     f"{row.collisions_paper_types} | {row.collisions_unavoidable} | "
                     f"{_share(row.prevented_paper_types_pct, 1)} | "
                     f"{_share(row.prevented_unperturbed_pct, 0)} | {shifts} | {row.collisions_fallback_driving} | "
                     f"{interval} | {detectable}{_p_value(verdict)} | "
                     f"{'' if verdict is None else verdict.verdict} |")
    for budget in sorted(calibration["budget"].unique()):
        choice = deployment_choice(calibration, budget)
        if choice is not None:
            lines += ["", f"Chosen on the calibration episodes alone at the {budget:.0%} budget (the most prevented on "
                          f"the worst perturbation type, then on the mean; cautious fallback): **{choice}**."]
    lines += ["", "![trade-off](safety_benchmark_tradeoff.png)", ""]
    return "\n".join(lines)


def _p_value(verdict: Any) -> str:
    """The Holm-adjusted p of a verdict row for the table ('' where none was tested)."""
    return "" if verdict is None or not np.isfinite(verdict.p_holm) else f"{verdict.p_holm:.3g}"


def _share(value: float, decimals: int) -> str:
    """A prevented share for the table: '–' where the plain policy had no collision to prevent."""
    return "–" if not np.isfinite(value) else f"{value:.{decimals}f}"


def _episode_verdicts(pooled: pd.DataFrame, confidence: float = 0.95) -> pd.DataFrame:
    """One acting policy: the paired episode differences of `summarize_layers` as verdicts (McNemar, one-sided for
    fewer collisions: half the two-sided p when the difference is negative), Holm over the rows of each budget (both
    fallbacks: the same family as :func:`verdicts` across seeds)."""
    from socnav.experiments.statistics import holm_adjust

    rows = pooled[~pooled["layer"].isin(REFERENCE_ROWS)].copy()
    table = pd.DataFrame({"layer": rows["layer"], "budget": rows["budget"], "fallback": rows["fallback"],
                          "diff_pct": 100.0 * rows["vs_proximity_difference"],
                          "low": 100.0 * rows["vs_proximity_low"], "high": 100.0 * rows["vs_proximity_high"],
                          "p_fewer": np.where(rows["vs_proximity_difference"] < 0, rows["vs_proximity_p"] / 2,
                                              1.0 - rows["vs_proximity_p"] / 2)})
    table["p_holm"] = math.nan
    for _budget, block in table.groupby("budget"):
        tested = block[~((block["layer"] == "proximity-only") & (block["fallback"] == "cautious"))]
        if len(tested):
            table.loc[tested.index, "p_holm"] = holm_adjust(tested["p_fewer"].to_numpy())
    table["verdict"] = np.where(table["p_holm"] < 1.0 - confidence, "fewer collisions",
                                np.where((table["layer"] == "proximity-only") & (table["fallback"] == "cautious"),
                                         "(the row to beat)", "not established"))
    return table.reset_index(drop=True)


def _tradeoff_figure(pooled: pd.DataFrame, out_base: Path) -> list[Path]:
    """Prevented share over the paper's types against false activation, one line per trigger (cautious fallback)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from socnav.io import save_figure

    figure, axes = plt.subplots(figsize=(6.5, 4.2))
    rows = pooled[(pooled["layer"] != "plain") & (pooled["fallback"] == "cautious")]
    for name, group in rows.groupby("layer", sort=False):
        group = group.sort_values("false_activation_pct")  # a trade-off curve: along its x axis
        axes.plot(group["false_activation_pct"], group["prevented_paper_types_pct"], marker="o", label=name)
    axes.set_xlabel("false activation (% of unperturbed steps, held out)")
    axes.set_ylabel("collisions prevented (%, paper's types)")
    axes.legend(fontsize=8, loc="lower right")
    axes.grid(alpha=0.3)
    figure.tight_layout()
    paths = save_figure(figure, out_base)
    plt.close(figure)
    return paths



