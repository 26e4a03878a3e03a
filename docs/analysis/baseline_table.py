"""The reference baseline table of docs/metrics.md: every metric of the registry (socnav.sim.metrics) for the ORCA
robot, `straight`, a shipped policy and the same policy with the safety layer, in every self-contained scenario,
with 95 % intervals from a bootstrap over episodes.

    python docs/analysis/baseline_table.py                              # 200 episodes each (1-3 min, 1 core)
    python docs/analysis/baseline_table.py --episodes 20 --out /tmp/b   # a quick look
    python docs/analysis/baseline_table.py --scenarios corridor doorway intersection room --out runs/baselines-maps
    python docs/analysis/baseline_table.py --model pretrained-ppo    # the PPO policy (the paper's method) instead

What is played: per scenario the default world (``socnav.load_config(scenario=...)``, the shipped policy's training
world with that scenario, as ``socnav evaluate --model pretrained --scenario ...`` plays it), episodes ``seed``..
``seed + episodes - 1`` (the same episodes for every controller): ``orca`` and ``straight`` (socnav.controllers),
the shipped policy ``--model`` (deterministic mean action; its column is named by it) and the same policy wrapped
in the safety layer with the paper's MC-dropout thresholds (``--safety mc``: 20 MC-dropout samples, the seeded mask stream of ``socnav
evaluate``). Intervals: the percentile bootstrap over episodes (`socnav.experiments.statistics.
cluster_bootstrap_interval` with every episode its own cluster, 2,000 resamples, seed 0) of each metric's statistic
(`socnav.sim.metrics.episode_values`: a mean, or for ``return_std`` the population std), per (scenario,
controller), not adjusted for the number of cells. Metrics defined on some episodes only (time to goal and path
ratio: the successful ones) are resampled over those.

Writes ``<out>/baseline_table.csv`` (long: scenario, controller, metric, episodes, estimate, low, high) and
``<out>/baseline_table.md`` (one Markdown table per scenario: metrics x controllers, ``estimate [low, high]``), and
prints the Markdown.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

import socnav
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes
from socnav.experiments.statistics import cluster_bootstrap_interval
from socnav.safety import FallbackCounter, SafePolicy
from socnav.sim.metrics import ALL_METRICS, METRICS, STD, episode_values
from socnav.uncertainty import MC_SEED, MCDropoutEstimator

SCENARIOS = ("circle_crossing", "circle_interaction", "position_swap", "random")
MAP_SCENARIOS = ("corridor", "doorway", "intersection", "room")  # walls (docs/maps.md): --scenarios to play them
MC_SAMPLES = 20  # socnav evaluate's --k default
RESAMPLES = 2000
CONFIDENCE = 0.95


def interval(values: np.ndarray, kind: str) -> tuple[float, float, float]:
    """(estimate, low, high) of the mean of `values` (their population std for a STD metric), percentile bootstrap
    over episodes; NaN without values, NaN bounds with one."""
    if len(values) == 0:
        return np.nan, np.nan, np.nan
    if kind == STD:
        statistic = lambda arrays: arrays[0].std(axis=(1, 2))  # noqa: E731
    else:
        statistic = lambda arrays: arrays[0].mean(axis=(1, 2))  # noqa: E731
    result = cluster_bootstrap_interval([values], statistic, CONFIDENCE, RESAMPLES, seed=0)
    return result.estimate, result.low, result.high


def play(scenario: str, episodes: int, seed: int, n_envs: int, model: str) -> dict[str, pd.DataFrame]:
    """Per controller, its episode records in `scenario` (every metric's columns)."""
    config = socnav.load_config({}, scenario=scenario)
    policy = socnav.load_policy(model)
    safe = SafePolicy(policy, MCDropoutEstimator(policy, k=MC_SAMPLES, seed=MC_SEED), "mc", config)
    actors = {"orca": (make_controller("orca", config), None), "straight": (make_controller("straight", config), None),
              model: (policy, None), f"{model} + safety (mc)": (safe, FallbackCounter(safe))}
    played = {}
    for name, (actor, observer) in actors.items():
        began = time.perf_counter()
        played[name] = rollout_episodes(actor, config, episodes, seed=seed, n_envs=n_envs, observer=observer)
        print(f"  {scenario} / {name}: {episodes} episodes in {time.perf_counter() - began:.0f} s", flush=True)
    return played


def table(records: dict[tuple[str, str], pd.DataFrame]) -> pd.DataFrame:
    rows = []
    for (scenario, controller), frame in records.items():
        for name in ALL_METRICS:
            values = episode_values(frame, name)
            estimate, low, high = interval(values, METRICS[name].kind)
            rows.append({"scenario": scenario, "controller": controller, "metric": name, "episodes": len(values),
                         "estimate": estimate, "low": low, "high": high})
    return pd.DataFrame(rows)


def _cell(row: pd.Series, decimals: int) -> str:
    if np.isnan(row["estimate"]):
        return "–"
    if np.isnan(row["low"]):
        return f"{row['estimate']:.{decimals}f}"
    return f"{row['estimate']:.{decimals}f} [{row['low']:.{decimals}f}, {row['high']:.{decimals}f}]"


def markdown(frame: pd.DataFrame, episodes: int) -> str:
    parts = []
    for scenario, block in frame.groupby("scenario", sort=False):
        controllers = list(dict.fromkeys(block["controller"]))
        lines = [f"**{scenario}** ({episodes} episodes per controller)", "",
                 "| metric | unit | better | " + " | ".join(controllers) + " |",
                 "|:--|:--|:--|" + "--:|" * len(controllers)]
        indexed = block.set_index(["metric", "controller"])
        for name in ALL_METRICS:
            metric = METRICS[name]
            cells = [_cell(indexed.loc[(name, controller)], metric.decimals) for controller in controllers]
            lines.append(f"| `{name}` | {metric.unit} | {metric.direction} | " + " | ".join(cells) + " |")
        parts.append("\n".join(lines))
    return "\n\n".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-envs", type=int, default=50)
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS + MAP_SCENARIOS))
    parser.add_argument("--model", default="pretrained", help="the learned policy: 'pretrained', 'pretrained-ppo' or "
                                                               "a policy file")
    parser.add_argument("--out", type=Path, default=Path("runs/baselines"))
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)  # small batched matrices: one thread is fastest, and the cores are shared
    began = time.perf_counter()
    records = {}
    for scenario in args.scenarios:
        for controller, frame in play(scenario, args.episodes, args.seed, args.n_envs, args.model).items():
            records[(scenario, controller)] = frame
    frame = table(records)
    args.out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(args.out / "baseline_table.csv", index=False)
    text = markdown(frame, args.episodes)
    (args.out / "baseline_table.md").write_text(text + "\n")
    print(text)
    print(f"\nwall time {time.perf_counter() - began:.0f} s; {args.out / 'baseline_table.csv'}")


if __name__ == "__main__":
    main()
