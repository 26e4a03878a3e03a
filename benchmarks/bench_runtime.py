"""Benchmark: latency per decision of the torch-free runtime (`SafeNavigator`) beside the torch `SafePolicy`.

    python benchmarks/bench_runtime.py               # the shipped policy, full run (about a minute)
    python benchmarks/bench_runtime.py --quick       # fewer repeats
    python benchmarks/bench_runtime.py --model runs/swap/model.zip
    python benchmarks/bench_runtime.py --breakdown   # also: where one MC-dropout decision's time goes

What is measured (batch 1, ONE thread: onnxruntime with one intra-op thread, `torch.set_num_threads(1)`; CPU),
for circle-crossing scenes with 1, 5 and 10 humans, the median over repeats. Time is the process's CPU time by
default (`time.process_time`: on an idle machine the same as wall time for this single-threaded work, and on a
shared one it leaves out the time spent waiting for a core); `--clock wall` measures wall time.

* deterministic: runtime = the observation from the state arrays + the exported network + the command;
  torch = `policy.predict(obs, deterministic=True)` on the environment's observation;
* MC-dropout + rule + fallback, K = 20, the paper's MC-dropout thresholds: runtime = `SafeNavigator.act(robot,
  humans)` (input checks, observation, ONE onnxruntime call on 1 + K rows, window, rule, fallback where it fires,
  command); torch = `SafePolicy(policy, MCDropoutEstimator(policy, k=20), "mc").predict(obs)`;
* the same with thresholds that make the rule fire on every step (the cautious ORCA controller always computes).

Target: <= 300 µs per MC-dropout decision with 5 humans and >= 5x faster than the torch path.
Memory: the resident set (RSS) of a fresh process that imports only `socnav.runtime`, loads the navigator and
decides, beside that of a process that loads the torch policy and its SafePolicy.
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / torch load

_bench.single_thread()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

import socnav  # noqa: E402
from socnav.controllers import OrcaController  # noqa: E402
from socnav.runtime import SafeNavigator  # noqa: E402
from socnav.safety import SafePolicy, Thresholds  # noqa: E402
from socnav.sim.observation import observe_robot, robot_command  # noqa: E402
from socnav.sim.world import CrowdWorld  # noqa: E402
from socnav.uncertainty import MCDropoutEstimator  # noqa: E402

K = 20
TARGET_US = 300.0
TARGET_SPEEDUP = 5.0
ALWAYS = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=100.0, beta1=0.0)  # fires on every step

#: Run in a fresh interpreter: the runtime's own footprint (nothing but socnav.runtime imported).
RUNTIME_MEMORY = """
import json, resource, sys
from socnav.runtime import SafeNavigator
navigator = SafeNavigator.load(sys.argv[1], seed=0)
robot, humans = json.loads(sys.argv[2])
for _ in range(200):
    navigator.act(robot, humans)
print(json.dumps({"rss_mib": int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20,
                  "torch": "torch" in sys.modules}))
"""
TORCH_MEMORY = """
import json, sys, torch
import socnav
from socnav.safety import SafePolicy
from socnav.uncertainty import MCDropoutEstimator
torch.set_num_threads(1)
policy = socnav.load_policy(sys.argv[1])
safe = SafePolicy(policy, MCDropoutEstimator(policy, k=20), "mc", policy.socnav_metadata["env_config"], n_envs=1)
obs = {k: __import__("numpy").asarray(v, dtype="float32") for k, v in json.loads(sys.argv[2]).items()}
for _ in range(200):
    safe.predict(obs)
print(json.dumps({"rss_mib": int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20}))
"""


def scene(n_humans: int) -> tuple[dict[str, Any], dict[str, Any], dict[str, np.ndarray]]:
    """A circle-crossing scene after a few ORCA steps (everyone moving): robot and human state, observation."""
    config = socnav.load_config({"scenario": "circle_crossing", "n_humans": n_humans})
    world = CrowdWorld(config, n_envs=1)
    world.seed(0, 0)
    world.reset()
    for _ in range(8):
        world.step(OrcaController(config).predict(world.observe())[0])
    humans = np.flatnonzero(world.active[0, 1:]) + 1
    robot = {"position": world.positions[0, 0].tolist(), "velocity": world.velocities[0, 0].tolist(),
             "heading": float(world.heading[0]), "goal": world.goals[0, 0].tolist(),
             "v_pref": float(world.preferred_speeds[0, 0]), "radius": float(world.radii[0, 0])}
    crowd = {"positions": world.positions[0, humans].tolist(), "velocities": world.velocities[0, humans].tolist(),
             "radii": world.radii[0, humans].tolist()}
    return robot, crowd, world.observe()


def breakdown(navigator: SafeNavigator, robot: dict[str, Any], crowd: dict[str, Any], repeats: int, min_time: float,
              clock: Callable[[], float]) -> list[tuple[str, float]]:
    """Seconds per call of each stage of `SafeNavigator.act` (each timed alone, so warm in the caches: their sum
    is below the whole decision's time, which also pays the stages evicting each other's data)."""
    from socnav.runtime.navigator import HumansState, RobotState
    from socnav.safety.rule import nearest_human, rule_conditions

    network, uniforms = navigator.network, navigator.uniforms
    state, humans = RobotState.parse(robot), HumansState.parse(crowd)
    observation = observe_robot(state.position, state.velocity, state.heading, state.goal, state.v_pref,
                                state.radius, humans.positions, humans.velocities, humans.radii, network.max_humans)
    decision = navigator.act(robot, crowd)  # builds the MC batch of this many humans
    batch = next(b for b in navigator._batches.values() if b.steps == network.trim(observation)[1].shape[1])
    window = navigator._window
    nearest = nearest_human(observation)

    def rule() -> None:
        found = nearest_human(observation)
        rule_conditions(decision.uncertainty.u_ep_heading, decision.uncertainty.u_feat, found.gap,
                        found.speed(navigator.thresholds.proximity), nearest.gap, navigator.thresholds)
        robot_command(decision.action, state.v_pref, navigator.config.max_heading_change)

    stages = [
        ("input checks (RobotState / HumansState.parse)", lambda: (RobotState.parse(robot), HumansState.parse(crowd))),
        ("observation (the environment's kernel)", lambda: observe_robot(
            state.position, state.velocity, state.heading, state.goal, state.v_pref, state.radius, humans.positions,
            humans.velocities, humans.radii, network.max_humans)),
        (f"dropout uniforms (one draw) + keep masks, K = {navigator.k}",
         lambda: batch.draw_masks(uniforms, network.p_test)),
        (f"onnxruntime call on 1 + K = {1 + navigator.k} rows (IO binding)",
         lambda: network.session.run_with_iobinding(batch.binding)),
        ("uncertainty statistics (eqs. 5, 6, 8)",
         lambda: network.summarise(batch.h[1:, None], batch.mean[1:, None], batch.log_std[1:, None])),
        ("uncertainty window", lambda: window.update(decision.uncertainty)),
        ("nearest human + rule + command", rule),
        ("whole decision: SafeNavigator.act", lambda: navigator.act(robot, crowd)),
    ]
    return [(label, _bench.time_call(fn, repeats, min_time, clock)) for label, fn in stages]


def decisions(policy: Any, navigator_file: Path, robot: dict[str, Any], crowd: dict[str, Any],
              obs: dict[str, np.ndarray]) -> list[tuple[str, Callable[[], Any], Callable[[], Any]]]:
    """(label, one runtime decision, the same decision on the torch path) of each row, on one scene."""
    config = policy.socnav_metadata["env_config"]
    network = SafeNavigator.load(navigator_file, seed=0).network
    v_pref, max_turn = robot["v_pref"], socnav.load_config(config).max_heading_change

    def deterministic() -> tuple[float, float]:
        observation = observe_robot(np.asarray(robot["position"]), np.asarray(robot["velocity"]),
                                    robot["heading"], np.asarray(robot["goal"]), v_pref, robot["radius"],
                                    np.asarray(crowd["positions"]), np.asarray(crowd["velocities"]),
                                    np.asarray(crowd["radii"]), network.max_humans)
        return robot_command(network.predict(observation)[0][0], v_pref, max_turn)

    rows = [("deterministic", deterministic, lambda: policy.predict(obs, deterministic=True))]
    for label, thresholds in (("MC + rule + fallback", "mc"), ("MC + rule + fallback acting", ALWAYS)):
        navigator = SafeNavigator.load(navigator_file, thresholds=thresholds, seed=0)
        safe = SafePolicy(policy, MCDropoutEstimator(policy, k=K, seed=0), thresholds, config, n_envs=1)
        rows.append((label, lambda nav=navigator: nav.act(robot, crowd), lambda s=safe: s.predict(obs)))
    return rows


def memory(code: str, *args: str) -> dict[str, Any]:
    result = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="pretrained", help="policy file or 'pretrained'")
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--clock", choices=("cpu", "wall"), default="cpu", help="process CPU time or wall time")
    parser.add_argument("--breakdown", action="store_true",
                        help="also time each stage of one MC-dropout decision with 5 humans")
    args = parser.parse_args()
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    repeats, min_time = (3, 0.1) if args.quick else (5, 0.25)
    th.set_num_threads(1)
    console = Console(width=150)

    policy = socnav.load_policy(args.model)
    navigator_file = Path(tempfile.mkdtemp()) / "navigator.onnx"
    socnav.export_onnx(policy, navigator_file, thresholds="mc", k=K)
    console.print(f"torch {th.__version__} (1 thread), onnxruntime 1 thread, K = {K}, batch 1, "
                  f"median of {repeats} blocks, {args.clock} time, os.cpu_count() = {os.cpu_count()}, "
                  f"load average {os.getloadavg()[0]:.1f}, model: {args.model}")

    table = Table(title=f"Per-decision latency: socnav.runtime (ONNX) vs torch (K = {K}, 1 thread, batch 1)")
    for column in ("decision", "humans", "runtime µs", "torch µs", "speed-up", "target", "result"):
        table.add_column(column, justify="left" if column in ("decision", "target") else "right")
    for n_humans in (1, 5, 10):
        for label, runtime_fn, torch_fn in decisions(policy, navigator_file, *scene(n_humans)):
            runtime_s = _bench.time_call(runtime_fn, repeats, min_time, clock)
            torch_s = _bench.time_call(torch_fn, repeats, min_time, clock)
            speedup = torch_s / runtime_s
            if label == "MC + rule + fallback" and n_humans == 5:
                target = f"≤{TARGET_US:.0f} µs, ≥{TARGET_SPEEDUP:.0f}x"
                ok = runtime_s * 1e6 <= TARGET_US and speedup >= TARGET_SPEEDUP
                result = "[green]PASS[/]" if ok else "[red]FAIL[/]"
            else:
                target, result = "— (info)", ""
            table.add_row(label, str(n_humans), f"{runtime_s * 1e6:,.0f}", f"{torch_s * 1e6:,.0f}",
                          f"{speedup:.1f}x", target, result)
    console.print(table)

    robot, crowd, obs = scene(5)
    if args.breakdown:
        stages = Table(title=f"Where one MC-dropout decision goes (5 humans, K = {K}, {args.clock} time)")
        stages.add_column("stage")
        stages.add_column("µs", justify="right")
        navigator = SafeNavigator.load(navigator_file, seed=0)
        for label, seconds in breakdown(navigator, robot, crowd, repeats, min_time, clock):
            stages.add_row(label, f"{seconds * 1e6:,.1f}")
        console.print(stages)
    runtime_memory = memory(RUNTIME_MEMORY, str(navigator_file), json.dumps([robot, crowd]))
    torch_memory = memory(TORCH_MEMORY, args.model, json.dumps({k: v[0].tolist() for k, v in obs.items()}))
    console.print(f"memory (RSS after 200 decisions, 5 humans): runtime process {runtime_memory['rss_mib']:.0f} MiB "
                  f"(torch imported: {runtime_memory['torch']}), torch SafePolicy process "
                  f"{torch_memory['rss_mib']:.0f} MiB")


if __name__ == "__main__":
    main()
