"""Benchmark: end-to-end training env-steps/s of every preset, and where the time goes, beside plain SB3 PPO.

    python benchmarks/bench_train.py            # 8 rollouts per run after one warm-up rollout (~2 min)
    python benchmarks/bench_train.py --quick    # 3 rollouts per run
    python benchmarks/bench_train.py --scenario circle_crossing --humans 5   # a crowd instead of one human
    python benchmarks/bench_train.py --maps     # odv-ppo-drop among walls (scan + route) beside the open plane

Every run trains on the same env (default: position swap, one human, 16 environments, n_steps 128 => 2,048 steps per
rollout) in this process, one after another. Time is split by wrapping the VecEnv's `step_wait` (simulation) and
the algorithm's `train` (gradient updates); the rest of `learn` is rollout inference (policy forward passes,
buffer writes, SB3 bookkeeping). References, measured in the same run:

* `SB3 PPO + MLP`: stable-baselines3's PPO with its `MultiInputPolicy` (flatten + MLP 64x64), SB3 defaults except
  n_steps 128 / batch 128 so that the number of gradient steps per env-step equals the presets';
* `SB3 PPO + packed LSTM`: the same PPO with a comparable LSTM extractor written the common way (below:
  `nn.LSTM(num_layers=2)` over `pack_padded_sequence` of the humans, final hidden state + robot features), plugged in
  with `policy_kwargs=dict(features_extractor_class=...)`, torch's default thread count and SB3's default Adam —
  what a user gets without socnav's training path.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch as th
from rich.console import Console
from rich.table import Table

try:
    import socnav
except ImportError:  # a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    import socnav
from stable_baselines3 import PPO
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from socnav.rl import ALGOS, make_model

ENV = {"scenario": "position_swap", "n_humans": 1}
N_ENVS = 16
#: ``--maps``: the world of docs/maps.md's learned policies (72-beam scan, the route observed) and its open plane
MAP_WORLD = Path(__file__).resolve().parents[1] / "configs" / "env" / "doorway_route.yaml"
OPEN_PLANE = {"scenario": "circle_crossing"}
TARGET_ALGO, TARGET_STEPS_PER_S = "odv-ppo-drop", 2000


def _instrument(model: Any) -> dict[str, float]:
    """Accumulate wall time of simulation (`step_wait`) and gradient updates (`train`) on `model`."""
    timers = {"sim": 0.0, "grad": 0.0}
    env = model.get_env()
    step_wait, train = env.step_wait, model.train

    def timed(function: Callable[[], Any], key: str) -> Callable[[], Any]:
        def wrapper():
            start = time.perf_counter()
            try:
                return function()
            finally:
                timers[key] += time.perf_counter() - start

        return wrapper

    env.step_wait = timed(step_wait, "sim")
    model.train = timed(train, "grad")
    return timers


def measure(name: str, build: Callable[[], Any], rollouts: int) -> dict[str, Any]:
    model = build()
    rollout_size = model.n_steps * model.n_envs
    model.learn(rollout_size)  # warm-up: numba compile / cache load, first allocations
    timers = _instrument(model)
    start = time.perf_counter()
    model.learn(rollouts * rollout_size, reset_num_timesteps=False)
    total = time.perf_counter() - start
    steps = rollouts * rollout_size
    return {"name": name, "steps_per_s": steps / total, "total": total, "sim": timers["sim"] / total,
            "grad": timers["grad"] / total, "inference": 1 - (timers["sim"] + timers["grad"]) / total,
            "grad_steps": model.n_epochs * rollout_size // model.batch_size * rollouts}


class PackedLSTMExtractor(BaseFeaturesExtractor):
    """The reference's extractor: a 2-layer LSTM over the packed human rows, as commonly written."""

    def __init__(self, observation_space, hidden_size: int = 64):
        super().__init__(observation_space, features_dim=hidden_size + observation_space["robot"].shape[0])
        self.lstm = nn.LSTM(observation_space["humans"].shape[-1], hidden_size, num_layers=2, batch_first=True)

    def forward(self, observations):
        lengths = observations["humans_mask"].sum(dim=1).clamp(min=1).long().cpu()
        packed = nn.utils.rnn.pack_padded_sequence(observations["humans"], lengths, batch_first=True,
                                                   enforce_sorted=False)
        _, (hidden, _) = self.lstm(packed)
        return th.cat([hidden[-1], observations["robot"]], dim=1)


def _sb3_mlp() -> PPO:
    env = socnav.make_vec_env(ENV, n_envs=N_ENVS)
    th.set_num_threads(1)
    return PPO("MultiInputPolicy", env, n_steps=128, batch_size=128, seed=0, device="cpu")


def _sb3_lstm() -> PPO:
    env = socnav.make_vec_env(ENV, n_envs=N_ENVS)
    th.set_num_threads(_default_threads)
    return PPO("MultiInputPolicy", env, n_steps=128, batch_size=128, seed=0, device="cpu",
               policy_kwargs=dict(features_extractor_class=PackedLSTMExtractor,
                                  net_arch=dict(pi=[128, 128], vf=[128, 128])))


_default_threads = th.get_num_threads()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 rollouts per run instead of 8")
    parser.add_argument("--scenario", default=ENV["scenario"])
    parser.add_argument("--humans", type=int, default=ENV["n_humans"])
    parser.add_argument("--maps", action="store_true",
                        help="only odv-ppo-drop in the doorway with scan and route, beside the open plane")
    args = parser.parse_args()
    if args.maps:
        maps_beside_open_plane(3 if args.quick else 8, Console(width=150))
        return
    ENV.update(scenario=args.scenario, n_humans=args.humans)
    rollouts = 3 if args.quick else 8
    console = Console(width=150)
    console.print(f"env {ENV}, n_envs={N_ENVS}, {rollouts} rollouts of 2,048 steps per run after a warm-up rollout; "
                  f"torch {th.__version__}, {_default_threads} default threads")

    rows = []
    for algo in ALGOS:
        rows.append(measure(algo, lambda algo=algo: make_model(algo, socnav.make_vec_env(ENV, n_envs=N_ENVS), seed=0),
                            rollouts))
        console.print(f"  measured {algo}")
    rows.append(measure("SB3 PPO + MLP (reference)", _sb3_mlp, rollouts))
    console.print("  measured SB3 PPO + MLP")
    rows.append(measure("SB3 PPO + packed LSTM (reference)", _sb3_lstm, rollouts))
    console.print("  measured SB3 PPO + packed LSTM")

    mlp = next(row for row in rows if row["name"].startswith("SB3 PPO + MLP"))
    table = Table(title="End-to-end training throughput (env-steps/s) and time shares")
    for column in ("run", "env-steps/s", "vs SB3 MLP", "simulation", "rollout inference", "gradient updates",
                   "grad steps"):
        table.add_column(column, justify="left" if column == "run" else "right")
    for row in rows:
        table.add_row(row["name"], f"{row['steps_per_s']:,.0f}", f"{row['steps_per_s'] / mlp['steps_per_s']:.2f}x",
                      f"{100 * row['sim']:.1f}%", f"{100 * row['inference']:.1f}%", f"{100 * row['grad']:.1f}%",
                      str(row["grad_steps"]))
    console.print(table)
    target = next(row for row in rows if row["name"] == TARGET_ALGO)
    verdict = "PASS" if target["steps_per_s"] >= TARGET_STEPS_PER_S else "FAIL"
    lstm = rows[-1]
    console.print(f"target: {TARGET_ALGO} >= {TARGET_STEPS_PER_S:,} env-steps/s end to end: "
                  f"{target['steps_per_s']:,.0f} -> {verdict}; "
                  f"{target['steps_per_s'] / lstm['steps_per_s']:.1f}x SB3 PPO + packed LSTM")


def maps_beside_open_plane(rollouts: int, console: Console) -> None:
    """odv-ppo-drop's end-to-end env-steps/s in `MAP_WORLD` (walls, occlusion, the planner, a 72-beam scan and its
    encoder, the route) and in the open plane of circle crossing (same crowd size), measured one after the other."""
    from socnav.sim.scenarios import get_scenario

    walls = socnav.load_config(MAP_WORLD)
    humans = walls.n_humans if walls.n_humans is not None else get_scenario(walls.scenario).default_humans
    plane = socnav.load_config(OPEN_PLANE, n_humans=humans)
    rows = [measure(f"odv-ppo-drop, {name}", lambda world=world: make_model(
        "odv-ppo-drop", socnav.make_vec_env(world, n_envs=N_ENVS), seed=0), rollouts)
        for name, world in (("open plane (circle crossing)", plane), ("doorway + scan + route", walls))]
    table = Table(title=f"Training among walls beside the open plane ({humans} humans, {N_ENVS} envs)")
    for column in ("run", "env-steps/s", "vs open plane", "simulation", "rollout inference", "gradient updates"):
        table.add_column(column, justify="left" if column == "run" else "right")
    for row in rows:
        table.add_row(row["name"], f"{row['steps_per_s']:,.0f}", f"{row['steps_per_s'] / rows[0]['steps_per_s']:.2f}x",
                      f"{100 * row['sim']:.1f}%", f"{100 * row['inference']:.1f}%", f"{100 * row['grad']:.1f}%")
    console.print(table)


if __name__ == "__main__":
    main()
