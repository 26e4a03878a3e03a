"""Benchmark: how fast each preset learns position swap with one human (>= 95 % goal, <= 2 % collisions).

    python benchmarks/bench_learning.py                  # 5 presets x 3 seeds
    python benchmarks/bench_learning.py --algos odv-ppo-drop --seeds 0 1 2

Each run trains with the preset's defaults (16 environments) and, after every rollout (2,048 steps), evaluates
the deterministic policy on the 200 test episodes (seeds 0..199, never used in training). It stops at the first
evaluation meeting the criterion, or at the wall-time budget (10 minutes of training). Reported: timesteps and
training wall time (evaluation time excluded, shown separately) to reach the criterion.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import pandas as pd
from rich.console import Console
from rich.table import Table
from stable_baselines3.common.callbacks import BaseCallback

try:
    import socnav
except ImportError:  # a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    import socnav
from socnav.envs.rollout import rollout_episodes, summarize
from socnav.rl import ALGOS, make_model
from socnav.rl.training import training_env_seed

ENV = {"scenario": "position_swap", "n_humans": 1}
GOAL_PCT, COLLISION_PCT, EPISODES = 95.0, 2.0, 200
BUDGET_S = 600.0
MAX_TIMESTEPS = 2_000_000  # T of the variance-loss schedule; runs stop long before


class StopWhenLearned(BaseCallback):
    """Evaluates after every rollout; stops training once the criterion holds or the budget is spent."""

    def __init__(self) -> None:
        super().__init__()
        self.eval_time = 0.0
        self.started = time.perf_counter()
        self.reached: dict | None = None
        self.stop = False

    def training_time(self) -> float:
        return time.perf_counter() - self.started - self.eval_time

    def _on_rollout_start(self) -> None:
        if self.model.num_timesteps == 0:
            return
        start = time.perf_counter()
        metrics = summarize(rollout_episodes(self.model.policy, ENV, EPISODES, seed=0, n_envs=50))
        self.eval_time += time.perf_counter() - start
        if metrics["goal_pct"] >= GOAL_PCT and metrics["collision_pct"] <= COLLISION_PCT:
            self.reached = {"timesteps": self.model.num_timesteps, "train_s": self.training_time(), **metrics}
            self.stop = True
        elif self.training_time() > BUDGET_S:
            self.stop = True

    def _on_step(self) -> bool:
        return not self.stop


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=list(ALGOS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    args = parser.parse_args()
    console = Console(width=150)
    rows = []
    for algo in args.algos:
        for seed in args.seeds:
            env = socnav.make_vec_env(ENV, n_envs=16)
            model = make_model(algo, env, seed)
            env.seed(training_env_seed(seed))
            callback = StopWhenLearned()
            model.learn(MAX_TIMESTEPS, callback=callback)
            reached = callback.reached
            rows.append({"algo": algo, "seed": seed, "reached": reached is not None,
                         "timesteps": reached["timesteps"] if reached else None,
                         "train_s": reached["train_s"] if reached else callback.training_time(),
                         "eval_s": callback.eval_time,
                         "goal_pct": reached["goal_pct"] if reached else None,
                         "collision_pct": reached["collision_pct"] if reached else None})
            console.print(f"  {algo} seed {seed}: {rows[-1]}")
    frame = pd.DataFrame(rows)
    table = Table(title=f"Steps and training wall time to >= {GOAL_PCT:.0f} % goal and <= {COLLISION_PCT:.0f} % "
                        f"collisions on {EPISODES} test episodes (position swap, 1 human)")
    for column in ("algo", "seeds reaching", "timesteps (per seed)", "train wall s (per seed)", "max train s"):
        table.add_column(column, justify="left" if column == "algo" else "right")
    for algo, group in frame.groupby("algo", sort=False):
        table.add_row(algo, f"{int(group['reached'].sum())}/{len(group)}",
                      ", ".join("-" if pd.isna(t) else f"{int(t):,}" for t in group["timesteps"]),
                      ", ".join(f"{t:.0f}" for t in group["train_s"]), f"{group['train_s'].max():.0f}")
    console.print(table)


if __name__ == "__main__":
    main()
