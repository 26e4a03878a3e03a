"""Benchmark: ORCA cost per agent-step of the batched numba kernel vs RVO2's own doStep (pyrvo), same states, same run.

Run `python benchmarks/bench_orca.py` for the table; other benchmarks import `measure_orca_cost` (with benchmarks/
on sys.path).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import _bench  # benchmarks/_bench.py (benchmarks/ is on sys.path: the script's directory, or bench_env.py's)
import numpy as np

try:
    from socnav.sim.orca import default_social_arrays, orca_velocities, orca_velocities_kernel
except ImportError:  # running from a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from socnav.sim.orca import default_social_arrays, orca_velocities, orca_velocities_kernel

import pyrvo

TIME_HORIZON, NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_STEP = 5.0, 10.0, 10, 0.25
DEFAULT_CONFIGS = ((1, 6), (256, 6), (256, 12))


def _circle_crossing(n_envs: int, n_agents: int, seed: int = 0) -> dict:
    """Agents on a 4 m circle heading for the opposite side, mid-way into the crossing: everyone interacts."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, (n_envs, n_agents))
    start = 4.0 * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    goal = -start + rng.normal(0, 0.3, start.shape)
    max_speeds = rng.uniform(0.8, 1.2, (n_envs, n_agents))
    heading = (goal - start) / np.linalg.norm(goal - start, axis=-1, keepdims=True)
    preferred = heading * max_speeds[..., None]
    positions = start + 2.5 * heading + rng.normal(0, 0.2, start.shape)  # converging on the centre
    state = dict(
        positions=positions,
        velocities=preferred * rng.uniform(0.5, 1.0, (n_envs, n_agents, 1)),
        radii=rng.uniform(0.25, 0.35, (n_envs, n_agents)),
        preferred_velocities=preferred,
        max_speeds=max_speeds,
    )
    # Float32-representable, so RVO2 solves the same problem.
    return {key: value.astype(np.float32).astype(np.float64) for key, value in state.items()}


def _time_ours(state: dict, repeats: int) -> tuple[float, float]:
    """Best seconds per call of (the njit kernel with preallocated output, the validating Python wrapper)."""
    n_envs, n_agents = state["radii"].shape
    pad, share, sees = default_social_arrays(n_envs, n_agents)
    mask = np.ones((n_envs, n_agents), dtype=bool)
    arrays = (
        state["positions"],
        state["velocities"],
        state["radii"],
        state["preferred_velocities"],
        state["max_speeds"],
        mask,
        mask,
        pad,
        share,
        sees,
    )
    scalars = (TIME_HORIZON, NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_STEP)
    out = np.empty((n_envs, n_agents, 2))
    orca_velocities(*arrays, *scalars)  # compile / load the numba cache outside the timing
    kernel = _bench.best_of(lambda: orca_velocities_kernel(*arrays, *scalars, out), repeats, n_envs * n_agents)
    wrapper = _bench.best_of(lambda: orca_velocities(*arrays, *scalars), repeats, n_envs * n_agents)
    return kernel, wrapper


def _time_pyrvo(state: dict, repeats: int) -> float:
    """Best seconds for one doStep of every env's RVO2 simulator, each reset to the benchmark state before timing."""
    n_envs, n_agents = state["radii"].shape
    # doStep moves the agents, so every timed step must start from a reset (untimed) state; for small batches, time
    # identical copies of each simulator in one sample so the sample stays far above the timer's resolution.
    copies = max(1, 256 // n_envs)
    sims = []
    for e in range(n_envs):
        for _ in range(copies):
            sim = pyrvo.RVOSimulator(TIME_STEP, NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_HORIZON, TIME_HORIZON, 0.3, 1.0)
            for i in range(n_agents):
                sim.add_agent(
                    tuple(state["positions"][e, i]),
                    NEIGHBOR_DIST,
                    MAX_NEIGHBORS,
                    TIME_HORIZON,
                    TIME_HORIZON,
                    float(state["radii"][e, i]),
                    float(state["max_speeds"][e, i]),
                    tuple(state["velocities"][e, i]),
                )
                sim.set_agent_pref_velocity(i, tuple(state["preferred_velocities"][e, i]))
            sims.append((e, sim))

    def reset() -> None:
        for e, sim in sims:
            for i in range(n_agents):
                sim.set_agent_position(i, tuple(state["positions"][e, i]))
                sim.set_agent_velocity(i, tuple(state["velocities"][e, i]))

    best = float("inf")
    for _ in range(repeats):
        reset()
        start = time.perf_counter()
        for _, sim in sims:
            sim.do_step()
        best = min(best, (time.perf_counter() - start) / copies)
    return best


def measure_orca_cost(configs=DEFAULT_CONFIGS, repeats: int = 20) -> list[dict]:
    """ORCA microseconds per agent-step for each (n_envs, n_agents): numba kernel, its wrapper, and pyrvo doStep."""
    rows = []
    for n_envs, n_agents in configs:
        state = _circle_crossing(n_envs, n_agents)
        kernel_s, wrapper_s = _time_ours(state, repeats)
        pyrvo_s = _time_pyrvo(state, repeats)
        agent_steps = n_envs * n_agents
        rows.append(
            dict(
                n_envs=n_envs,
                n_agents=n_agents,
                kernel_us=1e6 * kernel_s / agent_steps,
                wrapper_us=1e6 * wrapper_s / agent_steps,
                pyrvo_us=1e6 * pyrvo_s / agent_steps,
                speedup=pyrvo_s / wrapper_s,  # > 1: our wrapped call is faster than pyrvo
            )
        )
    return rows


def main() -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="ORCA cost per agent-step (us), single thread; speedup = pyrvo / ours (wrapper)")
    for column in ("envs x agents", "numba kernel", "numba wrapper", "pyrvo doStep", "speedup"):
        table.add_column(column, justify="right")
    for row in measure_orca_cost():
        table.add_row(
            f"{row['n_envs']} x {row['n_agents']}",
            f"{row['kernel_us']:.3f}",
            f"{row['wrapper_us']:.3f}",
            f"{row['pyrvo_us']:.3f}",
            f"{row['speedup']:.1f}x",
        )
    Console().print(table)
    print("pyrvo doStep also builds its k-d tree and integrates positions (both negligible next to the ORCA solve);")
    print("its Python loop over per-env simulators is included, as a batched caller would pay it.")


if __name__ == "__main__":
    main()
