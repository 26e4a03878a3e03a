"""Benchmark: the global planner's cost -- per shortest-path query on each map, and in env-steps/s of the map
scenarios with the planner on against off, same run.

    python benchmarks/bench_planner.py            # full run (a few minutes)
    python benchmarks/bench_planner.py --quick    # shorter samples, fewer repeats

What is measured (everything on ONE core: thread pools capped to 1, the process pinned to CPU 0, as bench_env.py):

* per map (the four map scenarios' walls at their default layout, circle crossing with five pillars as
  `obstacles` (bench_walls.py's map), and a 10 x 10 m office read from a map_server-style occupancy grid at 5 cm):
  the visibility graph's nodes and edges and its build time (a fresh `GlobalPlanner`, once per map), and the
  median cost of one shortest-path query (`GlobalPlanner.shortest_path`) between random free points that do NOT
  see each other (the queries the followers make: an agent with a clear view of its goal makes none), against the
  REFERENCE measured alongside: the per-step check every agent makes (`GlobalPlanner.clear`, one segment against
  every wall, compiled), per agent in a batch of 1,536 (256 environments x 6 humans);
* env-steps/s of each map scenario at 256 environments, the ORCA robot driving (`make_controller("orca", config)`)
  among the scenario's default humans, with ``planner.enabled: false`` (the REFERENCE: today's straight legs) and
  with the planner on (the default: the humans' planner in the world, the robot's in the controller), samples
  interleaved; ratio on / off, target >= 0.90 (the planner adds at most 10 %). Timed: one step of the loop the
  VecEnv runs -- `CrowdWorld.observe`, the controller's `predict`, `CrowdWorld.step` -- for all 256 environments;
  not timed: drawing the next episode of the environments whose episode ended (`CrowdWorld.reset`, the same work
  with or without the planner, and in doorway about 13 ms an episode: left in, it would make the ratio a count of
  how many episodes ended, which the planner changes).
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / numba load

_bench.single_thread()
PINNED = _bench.pin_to_one_core()

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from bench_humans import _spread, _verdict  # noqa: E402  (same verdicts)
from bench_walls import PILLARS  # noqa: E402  (its 20-edge map)
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from socnav.config import load_config  # noqa: E402
from socnav.controllers import make_controller  # noqa: E402
from socnav.sim.maps import occupancy_to_polygons  # noqa: E402
from socnav.sim.planning import GlobalPlanner  # noqa: E402
from socnav.sim.scenarios import get_scenario  # noqa: E402
from socnav.sim.walls import world_polygons  # noqa: E402
from socnav.sim.world import CrowdWorld  # noqa: E402

N_ENVS = 256
CHECK_BATCH = 256 * 6
TARGET_RATIO = 0.90
MAP_SCENARIOS = ("corridor", "doorway", "intersection", "room")


def office_grid(resolution: float = 0.05) -> list[np.ndarray]:
    """A 10 x 10 m office as a map_server grid would give it: 20 cm walls, a corridor wall with two doors, two rooms
    split by a wall with a door, three desks; read into polygons as `socnav.sim.maps` reads a grid."""
    cells = round(10.0 / resolution)
    blocked = np.zeros((cells, cells), dtype=bool)

    def fill(x0: float, y0: float, x1: float, y1: float) -> None:  # metres, y up (row 0 at the top)
        rows = slice(cells - round(y1 / resolution), cells - round(y0 / resolution))
        blocked[rows, round(x0 / resolution): round(x1 / resolution)] = True

    for wall in ((0, 0, 10, 0.2), (0, 9.8, 10, 10), (0, 0, 0.2, 10), (9.8, 0, 10, 10)):  # outer walls
        fill(*wall)
    fill(6.0, 0.2, 6.2, 2.0)  # the corridor wall x = 6, doors at y in [2, 3] and [7, 8]
    fill(6.0, 3.0, 6.2, 7.0)
    fill(6.0, 8.0, 6.2, 9.8)
    fill(0.2, 5.0, 2.5, 5.2)  # the wall between the two rooms, a door at x in [2.5, 3.5]
    fill(3.5, 5.0, 6.0, 5.2)
    for desk in ((1.0, 1.0, 2.6, 1.8), (3.2, 2.4, 4.8, 3.2), (1.2, 7.0, 2.8, 7.8)):
        fill(*desk)
    return occupancy_to_polygons(blocked, resolution)


def maps() -> dict[str, list[np.ndarray]]:
    """The benchmark's maps, by name."""
    found = {}
    for scenario in MAP_SCENARIOS:
        config = load_config({"scenario": scenario})
        found[scenario] = world_polygons(config, get_scenario(scenario))
    pillars = load_config({"scenario": "circle_crossing", "obstacles": PILLARS})
    found["5 pillars (obstacles)"] = world_polygons(pillars, get_scenario("circle_crossing"))
    found["office grid (map_server, 5 cm)"] = office_grid()
    return found


def hidden_pairs(planner: GlobalPlanner, count: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """`count` (start, goal) pairs of free points keeping the clearance, the straight line between them blocked."""
    rng = np.random.default_rng(seed)
    corners = np.concatenate(planner.polygons)
    low, high = corners.min(axis=0), corners.max(axis=0)
    pairs: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(200 * count):
        points = rng.uniform(low, high, (2, 2))
        if not planner.is_free(points).all() or (planner.wall_distance(points) < planner.clearance).any():
            continue
        if planner.clear(points[:1], points[1:])[0]:
            continue
        pairs.append((points[0], points[1]))
        if len(pairs) == count:
            break
    return pairs


def measure_queries(polygons: list[np.ndarray], clearance: float, queries: int, repeats: int) -> dict[str, Any]:
    """Build time, graph size, query cost (median of `queries` hidden pairs, best of `repeats`) and the per-agent
    cost of the per-step check (best of `repeats` batched calls)."""
    start = time.perf_counter()
    planner = GlobalPlanner(polygons, clearance)
    build = time.perf_counter() - start
    pairs = hidden_pairs(planner, queries)
    costs, reached = [], 0
    for a, b in pairs:
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            path = planner.shortest_path(a, b)
            best = min(best, time.perf_counter() - start)
        costs.append(best)
        reached += path is not None
    rng = np.random.default_rng(1)
    corners = np.concatenate(planner.polygons)
    starts = rng.uniform(corners.min(axis=0), corners.max(axis=0), (CHECK_BATCH, 2))
    ends = starts + rng.normal(0.0, 2.0, (CHECK_BATCH, 2))
    planner.clear(starts, ends)  # compiled before timing
    check = np.inf
    for _ in range(max(repeats, 5)):
        start = time.perf_counter()
        planner.clear(starts, ends)
        check = min(check, (time.perf_counter() - start) / CHECK_BATCH)
    return {"build": build, "nodes": planner.n_nodes, "edges": planner.n_edges, "segments": len(planner.seg_start),
            "query": statistics.median(costs) if costs else 0.0, "queries": len(pairs),
            "reached": reached, "check": check}


class DrivenWorld:
    """`n_envs` environments of `config` driven by the ORCA robot; `run(steps)` times `steps` steps of the loop
    (observe, predict, step), drawing the next episode of ended environments outside the timing."""

    def __init__(self, config: dict, n_envs: int, warmup_steps: int):
        self.config = load_config(config)
        self.world = CrowdWorld(self.config, n_envs)
        for env in range(n_envs):
            self.world.seed(env, env)
        self.world.reset()
        self.controller = make_controller("orca", self.config)
        self.steps = 0
        self.run(warmup_steps)

    def run(self, steps: int) -> float:
        timed = 0.0
        for _ in range(steps):
            start = time.perf_counter()
            actions, _ = self.controller.predict(self.world.observe())
            result = self.world.step(actions)
            timed += time.perf_counter() - start
            ended = np.flatnonzero(result.terminated | result.truncated)
            if ended.size:
                self.world.reset(ended)
        self.steps += steps
        return timed

    def queries(self) -> int:
        """Shortest-path queries made so far: the humans' and the robot's."""
        humans = self.world.human_paths.queries if self.world.human_paths is not None else 0
        return humans + sum(follower.queries for follower in self.controller._followers.values())


def measure_loops(loops: dict[str, DrivenWorld], n_envs: int, seconds: float, repeats: int) -> dict[str, dict]:
    """Env-steps/s of each loop: samples of ~`seconds` alternate between the loops (A B C A B C ...), so drift of
    the machine hits all alike. Returns {label: {median, min, max}}."""
    calls = {}
    for label, loop in loops.items():  # steps per sample, from a short calibration
        calls[label] = max(1, int(10 * seconds / max(loop.run(10), 1e-9)))
    rates: dict[str, list[float]] = {label: [] for label in loops}
    for _ in range(repeats):
        for label, loop in loops.items():
            rates[label].append(calls[label] * n_envs / loop.run(calls[label]))
    return {label: {"median": statistics.median(r), "min": min(r), "max": max(r)} for label, r in rates.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter samples and fewer repeats")
    args = parser.parse_args(argv)
    seconds, repeats, warmup, queries = (0.5, 3, 100, 50) if args.quick else (1.0, 7, 300, 200)
    console = Console(width=max(Console().width, 120))
    console.print(f"[bold]socnav planner benchmark[/] ({'quick' if args.quick else 'full'} run); single core: {PINNED}")
    begin = time.perf_counter()

    clearance = load_config({}).robot_radius + load_config({}).planner.margin
    table = Table(title=f"Shortest-path queries (clearance {clearance:g} m): median of {queries} start-goal pairs "
                        "that do not see each other, best of 3 runs each; the per-step check per agent alongside")
    for column in ("map", "wall edges", "nodes", "edges", "build (ms)", "query (µs)", "reached",
                   "per-step check (µs / agent, reference)", "query / check"):
        table.add_column(column, justify="right")
    for name, polygons in maps().items():
        result = measure_queries(polygons, clearance, queries, 3)
        hidden = result["queries"] > 0  # in a corridor of two walls every two points see each other
        table.add_row(name, str(result["segments"]), str(result["nodes"]), str(result["edges"]),
                      f"{1e3 * result['build']:.1f}", f"{1e6 * result['query']:.0f}" if hidden else "- (all in view)",
                      f"{result['reached']} / {result['queries']}", f"{1e6 * result['check']:.3f}",
                      f"{result['query'] / result['check']:,.0f}x" if hidden else "-")
    console.print(table)

    loops = {(scenario, enabled): DrivenWorld({"scenario": scenario, "planner": {"enabled": enabled}}, N_ENVS, warmup)
             for scenario in MAP_SCENARIOS for enabled in (False, True)}
    measured = measure_loops({f"{scenario} {enabled}": loop for (scenario, enabled), loop in loops.items()}, N_ENVS,
                             seconds, repeats)
    table = Table(title=f"Env-steps/s, one core, {N_ENVS} envs, the ORCA robot among the scenario's default humans "
                        f"(observe + predict + step; new episodes drawn untimed): median \\[min-max] of {repeats} "
                        "interleaved samples, planner off (reference) and on")
    for column in ("scenario", "planner off (reference)", "planner on", "ratio on / off",
                   f"target >= {TARGET_RATIO:g}x", "queries / step (on)"):
        table.add_column(column, justify="right")
    for scenario in MAP_SCENARIOS:
        off, on = measured[f"{scenario} False"], measured[f"{scenario} True"]
        ratio = on["median"] / off["median"]
        loop = loops[(scenario, True)]
        table.add_row(scenario, _spread(off), _spread(on), f"{ratio:.3f}x", _verdict(ratio >= TARGET_RATIO),
                      f"{loop.queries() / loop.steps:.2f}")
    console.print(table)
    console.print(f"total {time.perf_counter() - begin:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
