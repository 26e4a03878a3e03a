"""The smooth-driving ablation (docs/training.md, "Smooth driving"): policies trained with and without the
training-time costs of `socnav.rl.smoothing`, and the ORCA robot, on the same held-out episodes.

    python docs/analysis/smoothness_table.py none=runs/smooth/none/model.zip turn=runs/smooth/turn/model.zip \
        --episodes 200 --seed 5000
    python docs/analysis/smoothness_table.py pretrained=pretrained --scenarios position_swap circle_crossing \
        circle_interaction random --episodes 200 --seed 100000     # one table per scenario, its default crowd

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
SCENARIOS = ("position_swap", "circle_crossing", "circle_interaction", "random")  # the open plane's


def _rate(hits: int, n: int) -> str:
    interval = binomtest(hits, n).proportion_ci(0.95, method="exact")
    return f"{100 * hits / n:.1f} [{100 * interval.low:.1f}, {100 * interval.high:.1f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policies", nargs="+", help="label=model.zip (or label=pretrained)")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--scenarios", nargs="+", choices=SCENARIOS, default=["position_swap"],
                        help="one table each: position swap with one human, the others with their default crowd")
    args = parser.parse_args()
    policies = {}
    for item in args.policies:
        label, _, path = item.partition("=")
        policies[label] = load_policy(path)
    for scenario in args.scenarios:
        if len(args.scenarios) > 1:
            print(f"\n**{scenario}** ({args.episodes} episodes, seeds {args.seed}-{args.seed + args.episodes - 1})\n")
        config = load_config(WORLD if scenario == "position_swap" else {"scenario": scenario})
        print_table(config, {"ORCA robot": make_controller("orca", config), **policies}, args)


def print_table(config, actors: dict, args: argparse.Namespace) -> None:
    """One Markdown table: each actor on the same episodes of `config`, beside the ORCA robot's (the first)."""
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
