"""The smooth-driving ablation (docs/training.md, "Smooth driving"): policies trained with and without the
training-time costs of `socnav.rl.smoothing`, and the ORCA robot, on the same held-out episodes.

    python docs/analysis/smoothness_table.py none=runs/smooth/none/model.zip turn=runs/smooth/turn/model.zip \
        --episodes 200 --seed 5000

Prints a Markdown table: goal and collision rates with 95 % Clopper-Pearson intervals, jerk and path irregularity
(`socnav.sim.metrics`), and each one's ratio to the ORCA robot's on the same episodes.
"""

from __future__ import annotations

import argparse

from scipy.stats import binomtest

from socnav.config import load_config
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes
from socnav.rl.persistence import load_policy

WORLD = {"scenario": "position_swap", "n_humans": 1}  # the shipped policy's world


def _rate(hits: int, n: int) -> str:
    interval = binomtest(hits, n).proportion_ci(0.95, method="exact")
    return f"{100 * hits / n:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policies", nargs="+", help="label=model.zip (or label=pretrained)")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=5000)
    args = parser.parse_args()
    config = load_config(WORLD)
    actors = {"ORCA robot": make_controller("orca", config)}
    for item in args.policies:
        label, _, path = item.partition("=")
        actors[label] = load_policy(path)
    rows = {label: rollout_episodes(actor, config, args.episodes, seed=args.seed, n_envs=50)
            for label, actor in actors.items()}
    orca = rows["ORCA robot"]
    print("| policy | Goal % [95 % CI] | Collision % [95 % CI] | jerk (m/s³) | x ORCA | path irregularity (rad) "
          "| x ORCA |")
    print("|---|---|---|---|---|---|---|")
    for label, records in rows.items():
        n = len(records)
        jerk, irregularity = records["jerk_mean"].mean(), records["path_irregularity"].mean()
        print(f"| {label} | {_rate(int((records['outcome'] == 'goal').sum()), n)} | "
              f"{_rate(int((records['outcome'] == 'collision').sum()), n)} | {jerk:.2f} | "
              f"{jerk / orca['jerk_mean'].mean():.1f} | {irregularity:.3f} | "
              f"{irregularity / orca['path_irregularity'].mean():.1f} |")


if __name__ == "__main__":
    main()
