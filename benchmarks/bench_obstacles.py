"""Benchmark: ORCA with static obstacles, cost per agent-step of the batched numba kernel vs RVO2's own doStep (pyrvo)
on the same 20-edge map and crowds, and of the kernel with vs without the map.

Run `python benchmarks/bench_obstacles.py` for the tables (about 20 s).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import _bench  # benchmarks/_bench.py (benchmarks/ is on sys.path: the script's directory)
import numpy as np

try:
    from socnav.sim.obstacles import ObstacleBatch, ObstacleMap
    from socnav.sim.orca import default_social_arrays, orca_velocities
except ImportError:  # running from a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from socnav.sim.obstacles import ObstacleBatch, ObstacleMap
    from socnav.sim.orca import default_social_arrays, orca_velocities

import pyrvo

TIME_HORIZON, TIME_HORIZON_OBST, NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_STEP = 5.0, 2.0, 10.0, 10, 0.25
PYRVO_CONFIGS = ((1, 6), (256, 6), (16, 30))
WITH_WITHOUT_CONFIG = (256, 6)


def twenty_edge_map() -> list[np.ndarray]:
    """Four 0.8 m boxes around the centre (16 edges) and two 1.5 m walls (2 edges each): 20 obstacle edges."""
    box = np.array([[-0.4, -0.4], [0.4, -0.4], [0.4, 0.4], [-0.4, 0.4]])  # counter-clockwise: solid
    boxes = [box + centre for centre in ([1.5, 1.5], [-1.5, 1.5], [-1.5, -1.5], [1.5, -1.5])]
    walls = [np.array([[-0.75, 2.5], [0.75, 2.5]]), np.array([[-0.75, -2.5], [0.75, -2.5]])]
    return boxes + walls


def _crowds(n_envs: int, n_agents: int, seed: int = 0) -> dict:
    """Agents on a 4 m circle crossing to the opposite side through the map, mid-way, float32-representable."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, (n_envs, n_agents))
    start = 4.0 * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    goal = -start + rng.normal(0, 0.3, start.shape)
    max_speeds = rng.uniform(0.8, 1.2, (n_envs, n_agents))
    heading = (goal - start) / np.linalg.norm(goal - start, axis=-1, keepdims=True)
    preferred = heading * max_speeds[..., None]
    state = dict(
        positions=start + rng.uniform(1.0, 3.0, (n_envs, n_agents, 1)) * heading,  # converging among the obstacles
        velocities=preferred * rng.uniform(0.5, 1.0, (n_envs, n_agents, 1)),
        radii=rng.uniform(0.25, 0.35, (n_envs, n_agents)),
        preferred_velocities=preferred,
        max_speeds=max_speeds,
    )
    return {key: value.astype(np.float32).astype(np.float64) for key, value in state.items()}


def time_ours(state: dict, obstacles: ObstacleBatch | None, repeats: int) -> float:
    """Best seconds per `orca_velocities` call (the validating wrapper) on the batch."""
    n_envs, n_agents = state["radii"].shape
    pad, share, sees = default_social_arrays(n_envs, n_agents)
    mask = np.ones((n_envs, n_agents), dtype=bool)
    arrays = (state["positions"], state["velocities"], state["radii"], state["preferred_velocities"],
              state["max_speeds"], mask, mask, pad, share, sees)  # fmt: skip
    scalars = (TIME_HORIZON, NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_STEP)
    keywords = {} if obstacles is None else dict(obstacles=obstacles, time_horizon_obst=TIME_HORIZON_OBST)
    orca_velocities(*arrays, *scalars, **keywords)  # compile / load the numba cache outside the timing
    return _bench.best_of(lambda: orca_velocities(*arrays, *scalars, **keywords), repeats, n_envs * n_agents)


def time_pyrvo(state: dict, polygons: list[np.ndarray], repeats: int) -> float:
    """Best seconds for one doStep of every env's RVO2 simulator (obstacles processed once, untimed), each reset to the
    benchmark state before timing."""
    n_envs, n_agents = state["radii"].shape
    copies = max(1, 256 // n_envs)  # small batches: time identical copies so a sample stays >> timer resolution
    sims = []
    for e in range(n_envs):
        for _ in range(copies):
            sim = pyrvo.RVOSimulator(TIME_STEP, NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_HORIZON, TIME_HORIZON_OBST, 0.3, 1.0)
            for polygon in polygons:
                sim.add_obstacle([tuple(map(float, vertex)) for vertex in polygon])
            sim.process_obstacles()
            for i in range(n_agents):
                sim.add_agent(
                    tuple(state["positions"][e, i]), NEIGHBOR_DIST, MAX_NEIGHBORS, TIME_HORIZON, TIME_HORIZON_OBST,
                    float(state["radii"][e, i]), float(state["max_speeds"][e, i]), tuple(state["velocities"][e, i]),
                )  # fmt: skip
                sim.set_agent_pref_velocity(i, tuple(state["preferred_velocities"][e, i]))
            sims.append((e, sim))

    best = float("inf")
    for _ in range(repeats):
        for e, sim in sims:
            for i in range(n_agents):
                sim.set_agent_position(i, tuple(state["positions"][e, i]))
                sim.set_agent_velocity(i, tuple(state["velocities"][e, i]))
        start = time.perf_counter()
        for _, sim in sims:
            sim.do_step()
        best = min(best, (time.perf_counter() - start) / copies)
    return best


def measure(repeats: int = 10) -> tuple[list[dict], dict]:
    """(ours vs pyrvo per config, ours with vs without the map), in microseconds per agent-step."""
    polygons = twenty_edge_map()
    obstacle_map = ObstacleMap.from_polygons(polygons)
    vs_pyrvo = []
    for n_envs, n_agents in PYRVO_CONFIGS:
        state = _crowds(n_envs, n_agents)
        ours = time_ours(state, ObstacleBatch.from_maps([obstacle_map] * n_envs), repeats)
        rvo2 = time_pyrvo(state, polygons, repeats)
        agent_steps = n_envs * n_agents
        vs_pyrvo.append(dict(n_envs=n_envs, n_agents=n_agents, ours_us=1e6 * ours / agent_steps,
                             pyrvo_us=1e6 * rvo2 / agent_steps, speedup=rvo2 / ours))  # fmt: skip
    n_envs, n_agents = WITH_WITHOUT_CONFIG
    state = _crowds(n_envs, n_agents)
    with_map = time_ours(state, ObstacleBatch.from_maps([obstacle_map] * n_envs), repeats)
    without = time_ours(state, None, repeats)
    agent_steps = n_envs * n_agents
    with_without = dict(n_envs=n_envs, n_agents=n_agents, with_us=1e6 * with_map / agent_steps,
                        without_us=1e6 * without / agent_steps, ratio=with_map / without)  # fmt: skip
    return vs_pyrvo, with_without


def main() -> None:
    from rich.console import Console
    from rich.table import Table

    vs_pyrvo, with_without = measure()
    console = Console()
    table = Table(title="ORCA with a 20-edge map, us per agent-step, single thread; speedup = pyrvo / ours")
    for column in ("envs x agents", "ours (orca_velocities)", "pyrvo doStep", "speedup"):
        table.add_column(column, justify="right")
    for row in vs_pyrvo:
        table.add_row(f"{row['n_envs']} x {row['n_agents']}", f"{row['ours_us']:.3f}", f"{row['pyrvo_us']:.3f}",
                      f"{row['speedup']:.1f}x")  # fmt: skip
    console.print(table)
    table = Table(title="Ours with vs without the map, us per agent-step")
    for column in ("envs x agents", "with map", "without", "with / without"):
        table.add_column(column, justify="right")
    row = with_without
    table.add_row(f"{row['n_envs']} x {row['n_agents']}", f"{row['with_us']:.3f}", f"{row['without_us']:.3f}",
                  f"{row['ratio']:.2f}x")  # fmt: skip
    console.print(table)
    print("pyrvo doStep also rebuilds its agent k-d tree and integrates positions; its Python loop over per-env")
    print("simulators is included, as a batched caller would pay it. Map processing (both) is outside the timing.")


if __name__ == "__main__":
    main()
