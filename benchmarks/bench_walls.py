"""Benchmark: env-steps/s of a world with walls (a 20-segment map, occlusion, a 72-beam scan) against the same world
in the open plane, same run.

    python benchmarks/bench_walls.py            # full run (about a minute)
    python benchmarks/bench_walls.py --quick    # shorter samples, fewer repeats

What is measured (everything on ONE core: thread pools capped to 1, the process pinned to CPU 0, as bench_env.py):
env-steps/s of `socnav.make_vec_env(config, n_envs=256)` for circle crossing with 1 robot + 5 humans stepped with
random actions, samples interleaved:

* open plane (REFERENCE): the default world;
* 20-segment map + scan (the TARGET row): five square pillars (4 edges each) off the robot's paths given as
  `obstacles`, `scan: {beams: 72}` (the humans avoid the pillars with RVO2's obstacle half-planes and notice the
  robot only in line of sight, the robot's swept disc is checked against every edge, 72 beams are cast every step);
  occlusion stays at its default for `obstacles` (off);
* the same with `occlusion: true` (the map scenarios' default: the robot observes only the humans in sight);
* the same map without scan and occlusion (the cost of the humans' wall avoidance and the wall collisions alone).

Target: the 20-segment map with the 72-beam scan at >= 0.5x the open plane's env-steps/s. The obstacle ORCA
kernel against pyrvo's `do_step` on the same map is in benchmarks/bench_obstacles.py.
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / numba load

_bench.single_thread()
PINNED = _bench.pin_to_one_core()

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

from bench_humans import _verdict, measure_interleaved, warmed_vec_env  # noqa: E402  (same sampling and verdicts)
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

N_ENVS = 256
TARGET_RATIO = 0.5


def pillar(x: float, y: float, half: float = 0.4) -> list[list[float]]:
    """A square pillar, counter-clockwise (solid)."""
    return [[x - half, y - half], [x + half, y - half], [x + half, y + half], [x - half, y + half]]


#: five pillars between the robot's four crossing diameters (circle crossing: the axes), 20 edges in all
PILLARS = [pillar(3.0, 3.0), pillar(-3.0, 3.0), pillar(-3.0, -3.0), pillar(3.0, -3.0), pillar(1.8, 4.8)]
BASE: dict[str, Any] = {"scenario": "circle_crossing", "n_humans": 5}
#: the target row: the 20-segment map with the 72-beam scan, as an `obstacles` config has it (occlusion off, its
#: default outside the map scenarios)
TARGET_WORLD = "20-segment map + 72-beam scan"
WORLDS = {
    "open plane (reference)": {},
    TARGET_WORLD: {"obstacles": PILLARS, "scan": {"beams": 72}},
    "20-segment map + 72-beam scan + occlusion": {"obstacles": PILLARS, "occlusion": True, "scan": {"beams": 72}},
    "20-segment map only": {"obstacles": PILLARS},
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter samples and fewer repeats")
    args = parser.parse_args(argv)
    seconds, repeats, warmup = (0.5, 3, 100) if args.quick else (1.0, 7, 300)
    console = Console(width=max(Console().width, 120))
    console.print(f"[bold]socnav walls benchmark[/] ({'quick' if args.quick else 'full'} run); single core: {PINNED}")
    start = time.perf_counter()
    vecs = {label: warmed_vec_env({**BASE, **overrides}, N_ENVS, warmup) for label, overrides in WORLDS.items()}
    measured = measure_interleaved({label: vec.step for label, vec in vecs.items()}, N_ENVS, seconds, repeats)
    for vec in vecs.values():
        vec.close()
    reference = measured["open plane (reference)"]["median"]
    table = Table(title=f"Env-steps/s, one core, {N_ENVS} envs of circle crossing (1 robot + 5 humans): median "
                        f"\\[min-max] of {repeats} interleaved samples")
    for column in ("world", "env-steps/s", "ratio to the open plane", f"target >= {TARGET_RATIO:g}x"):
        table.add_column(column, justify="right")
    for label, result in measured.items():
        ratio = result["median"] / reference
        target = ("[dim]reference[/]" if label.startswith("open") else
                  _verdict(ratio >= TARGET_RATIO) if label == TARGET_WORLD else "[dim]no target[/]")
        table.add_row(label, f"{result['median']:,.0f} [{result['min']:,.0f}-{result['max']:,.0f}]", f"{ratio:.2f}x",
                      target)
    console.print(table)
    console.print(f"total {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
