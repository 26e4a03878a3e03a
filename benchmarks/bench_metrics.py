"""Benchmark: the cost of the navigation metrics (socnav.sim.metrics) in the batched world, metrics off vs on, same run.

    python benchmarks/bench_metrics.py            # full run (about a minute)
    python benchmarks/bench_metrics.py --quick    # shorter samples, fewer repeats

What is measured (everything on ONE core: thread pools capped to 1, the process pinned to CPU 0, as bench_env.py):

* env-steps/s of the loop a rollout runs on `CrowdWorld(config, n_envs, metrics=...)` (circle_crossing, 5 humans,
  the default reward with its disturbance term): step all environments with random actions (drawn up front), write
  the episode summary of every environment whose episode ended, reset those. Off: the world's own summary; on: the
  per-step accumulators of every metric and their per-episode values.
* the same through `socnav.envs.rollout.rollout_episodes` with the `straight` controller (observation, controller,
  records), episodes per second, off vs on, as a user's `socnav evaluate` pays it.

Rates are per second of the thread's CPU time (`time.thread_time`), so that time spent waiting for a shared core does
not count; samples are taken in pairs (off, on), and the ratio on / off is the median over pairs (two samples taken
one after the other share the machine's load). Target: >= 0.90 at 256 environments (the metrics cost <= 10 %).
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / numba load

_bench.single_thread()
PINNED = _bench.pin_to_one_core()

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

try:
    import socnav  # noqa: F401
except ImportError:  # a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
from socnav.config import load_config  # noqa: E402
from socnav.controllers import make_controller  # noqa: E402
from socnav.envs.rollout import rollout_episodes  # noqa: E402
from socnav.sim.world import CrowdWorld  # noqa: E402

ENV_CONFIG = {"scenario": "circle_crossing", "n_humans": 5}
N_ENVS = (16, 256)
TARGET_N_ENVS = 256
TARGET_RATIO = 0.90


def world_loop(n_envs: int, metrics: bool, steps: int, seed: int = 0) -> Callable[[], float]:
    """A timed sample: `steps` batched steps of the rollout loop (step, summaries of ended episodes, resets);
    returns env-steps per second of this thread's CPU time (`time.thread_time`: time spent waiting for a shared core
    does not count). The world is built and warmed up once; each sample continues its episodes."""
    config = load_config(ENV_CONFIG)
    world = CrowdWorld(config, n_envs, metrics=metrics)
    for env in range(n_envs):
        world.seed(env, seed + env)
    world.reset()
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, size=(steps, n_envs, 2))

    def run() -> float:
        records = []
        start = time.thread_time()
        for k in range(steps):
            result = world.step(actions[k])
            done = np.flatnonzero(result.terminated | result.truncated)
            for env in done:
                records.append(world.episode_summary(env, int(result.outcome[env])))
            if len(done):
                world.reset(done)
        return steps * n_envs / (time.thread_time() - start)

    run()  # compile / warm the caches
    return run


def rollout_sample(metrics: bool, episodes: int, n_envs: int) -> Callable[[], float]:
    """A timed sample: `episodes` episodes of the straight controller through `rollout_episodes`; episodes per second
    of this thread's CPU time."""
    config = load_config(ENV_CONFIG)
    controller = make_controller("straight", config)

    def run() -> float:
        start = time.thread_time()
        rollout_episodes(controller, config, episodes, seed=0, n_envs=n_envs, metrics=metrics)
        return episodes / (time.thread_time() - start)

    run()
    return run


def interleaved(off: Callable[[], float], on: Callable[[], float], repeats: int) -> tuple[float, float, float]:
    """(median off, median on, median of the on / off ratios of adjacent pairs) over `repeats` pairs of samples
    taken off, on, off, on, ...: two samples taken one after the other share the machine's load, so the ratio of a
    pair is steadier than the ratio of two medians on a shared machine."""
    offs, ons = [], []
    for _ in range(repeats):
        offs.append(off())
        ons.append(on())
    ratios = [b / a for a, b in zip(offs, ons, strict=True)]
    return statistics.median(offs), statistics.median(ons), statistics.median(ratios)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter samples and fewer repeats")
    args = parser.parse_args(argv)
    steps, repeats, episodes = (50, 15, 128) if args.quick else (50, 61, 512)
    console = Console()
    console.print(PINNED)
    table = Table(title="Navigation metrics in the batched world: metrics off vs on (same run, interleaved; per "
                  "second of CPU time, medians)")
    for column in ("loop", "n_envs", "off", "on", "on / off (paired)", "target"):
        table.add_column(column, justify="left" if column == "loop" else "right")
    verdict = True
    for n_envs in N_ENVS:
        off, on, ratio = interleaved(world_loop(n_envs, False, steps), world_loop(n_envs, True, steps), repeats)
        target = f">= {TARGET_RATIO:.2f}" if n_envs == TARGET_N_ENVS else "–"
        if n_envs == TARGET_N_ENVS:
            verdict = ratio >= TARGET_RATIO
        table.add_row("world step + summaries + resets (env-steps/s)", str(n_envs), f"{off:,.0f}", f"{on:,.0f}",
                      f"{ratio:.3f}", target)
    off, on, ratio = interleaved(rollout_sample(False, episodes, TARGET_N_ENVS),
                                 rollout_sample(True, episodes, TARGET_N_ENVS), max(3, repeats // 6))
    table.add_row("rollout_episodes, straight controller (episodes/s)", str(TARGET_N_ENVS), f"{off:,.1f}",
                  f"{on:,.1f}", f"{ratio:.3f}", "–")
    console.print(table)
    console.print(f"target at {TARGET_N_ENVS} environments (metrics cost <= 10 %): "
                  + ("[green]met[/green]" if verdict else "[red]NOT met[/red]"))
    return 0 if verdict else 1


if __name__ == "__main__":
    sys.exit(main())
