"""Benchmark: the cost per decision of each trigger in the torch-free runtime (`SafeNavigator`), beside the paper's
rule in the same run.

    python benchmarks/bench_triggers.py            # the shipped policy, circle crossing with 1, 5 and 10 humans
    python benchmarks/bench_triggers.py --quick    # fewer repeats

What is measured (batch 1, one thread, CPU time of the process, median over repeats; the samples of all triggers
interleaved so that a change in the machine's load reaches every row alike): `SafeNavigator.act(robot, humans)` — the
observation, ONE onnxruntime call on 1 + K rows (K = 20), the window, the trigger, the fallback where it fires and the
command — with the paper's MC-dropout thresholds and with each score trigger (thresholds that never fire, so every
row computes the same policy path and differs only in its trigger; the fallback's own cost is bench_runtime.py's).
The ratio column is the row's time over the paper's rule's. The risk model is an untrained ensemble of the shipped
size (5 members, 2 hidden layers of 64): its cost does not depend on its weights.
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / torch load

_bench.single_thread()

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

import socnav  # noqa: E402
from socnav.controllers import OrcaController  # noqa: E402
from socnav.runtime import SafeNavigator  # noqa: E402
from socnav.safety.risk_model import (  # noqa: E402
    GEOMETRY_FEATURES,
    UNCERTAINTY_FEATURES,
    save_risk_model,
    train_risk_model,
)
from socnav.safety.triggers import TriggerSpec  # noqa: E402
from socnav.sim.world import CrowdWorld  # noqa: E402

K = 20


def scene(n_humans: int) -> tuple[dict, dict]:
    """A circle-crossing scene after a few ORCA steps (everyone moving): the robot's and the humans' states."""
    config = socnav.load_config({"scenario": "circle_crossing", "n_humans": n_humans})
    world = CrowdWorld(config, n_envs=1)
    world.seed(0, 0)
    world.reset()
    for _ in range(8):
        world.step(OrcaController(config).predict(world.observe())[0])
    humans = np.flatnonzero(world.active[0, 1:]) + 1
    robot = {"position": world.positions[0, 0], "velocity": world.velocities[0, 0],
             "heading": float(world.heading[0]), "goal": world.goals[0, 0],
             "v_pref": float(world.preferred_speeds[0, 0]), "radius": float(world.radii[0, 0])}
    return robot, {"positions": world.positions[0, humans], "velocities": world.velocities[0, humans],
                   "radii": world.radii[0, humans]}


def risk_model_file(directory: Path, uncertainty: bool) -> Path:
    """An ensemble of the shipped size, trained for one epoch on random rows (only its cost is measured)."""
    rng = np.random.default_rng(0)
    width = len(GEOMETRY_FEATURES) + (len(UNCERTAINTY_FEATURES) if uncertainty else 0)
    features = rng.normal(size=(256, width))
    model = train_risk_model(features, (features[:, 0] < 0).astype(float), np.arange(256) // 8, uncertainty, 4,
                             members=5, hidden=64, epochs=1)
    return save_risk_model(model, directory / f"risk-{uncertainty}.npz")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    repeats, block = (5, 0.05) if args.quick else (15, 0.2)
    directory = Path(tempfile.mkdtemp())
    navigator_file = directory / "navigator.onnx"
    policy = socnav.load_policy("pretrained")
    socnav.export_onnx(policy, navigator_file, thresholds="mc", k=K)
    never = math.inf
    rows: dict[str, object] = {"paper (mc)": "mc"}
    for name in ("time-to-collision", "closing-gap", "predicted-clearance", "conformal"):
        rows[name] = TriggerSpec.create(trigger=name, threshold=never)
    for uncertainty in (False, True):
        rows["risk-model" + ("+uncertainty" if uncertainty else "")] = TriggerSpec.create(
            trigger="risk-model", threshold=never, model=str(risk_model_file(directory, uncertainty)))
    console = Console()
    table = Table(title=f"SafeNavigator.act per decision (µs, K = {K}, one thread, CPU time)")
    table.add_column("trigger")
    for n in (1, 5, 10):
        table.add_column(f"{n} humans", justify="right")
        table.add_column("ratio", justify="right")
    results: dict[str, list[str]] = {name: [] for name in rows}
    for n_humans in (1, 5, 10):
        robot, humans = scene(n_humans)
        navigators = {name: SafeNavigator.load(navigator_file, thresholds=decision, seed=0)
                      for name, decision in rows.items()}
        samples: dict[str, list[float]] = {name: [] for name in rows}
        for navigator in navigators.values():  # warm-up, and the calls per block
            for _ in range(20):
                navigator.act(robot, humans)
        start, calls = time.process_time(), 0
        while time.process_time() - start < block:
            navigators["paper (mc)"].act(robot, humans)
            calls += 1
        for _ in range(repeats):
            for name, navigator in navigators.items():  # interleaved: load changes reach every row
                start = time.process_time()
                for _ in range(calls):
                    navigator.act(robot, humans)
                samples[name].append((time.process_time() - start) / calls * 1e6)
        reference = statistics.median(samples["paper (mc)"])
        for name in rows:
            median = statistics.median(samples[name])
            results[name] += [f"{median:.0f}", f"{median / reference:.2f}x"]
    for name, cells in results.items():
        table.add_row(name, *cells)
    console.print(table)


if __name__ == "__main__":
    main()
