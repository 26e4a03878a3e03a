"""Benchmark: social force humans against ORCA humans in the VecEnv, and against PySocialForce's own step, same run.

    python benchmarks/bench_humans.py            # full run (about a minute)
    python benchmarks/bench_humans.py --quick    # shorter samples, fewer repeats

What is measured (everything on ONE core: thread pools capped to 1, the process pinned to CPU 0, as bench_env.py):

* env-steps/s of `socnav.make_vec_env({"scenario": "circle_crossing", "n_humans": 5, "humans": ...}, n_envs=256)`
  (1 robot + 5 humans, the default reward with its disturbance term) stepped with random actions: ORCA humans (the
  REFERENCE, the default) and social force humans, samples interleaved; ratio social force / ORCA, target >= 0.5x.
  A 50/50 mixed crowd (``humans.mix``) is measured alongside, without a target, and so are replayed humans
  (``scenario: replay``, ``humans.model: replay``) on a recording written by the benchmark (ETH/UCY format, 40
  pedestrians crossing a 14 m square at 2.5 Hz) or on your own files (``--replay-files``); their crowd size is the
  recording's, so that row is a cost, not a like-for-like ratio.
* social force cost per agent-step: our batched numba kernel (`SocialForceHumans.velocities`: one call computes
  every agent of every environment) vs PySocialForce 1.1.2's own `Simulator.step()` (one simulator per environment,
  stepped one after another, as a caller of PySocialForce would), on the same crowds; ratio PySocialForce / ours
  (wrapper), target >= 20x at 256 x 6. PySocialForce's step also integrates positions (negligible next to its
  forces). Before timing, one step of each is compared: they must agree (the oracle tests hold them to 1e-5).
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / numba load

_bench.single_thread()
PINNED = _bench.pin_to_one_core()

import argparse  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

try:
    import socnav
except ImportError:  # a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    import socnav
from socnav.config import load_config  # noqa: E402
from socnav.sim.humans import Crowd, SocialForceHumans  # noqa: E402

ENV_CONFIG: dict[str, Any] = {"scenario": "circle_crossing", "n_humans": 5}
HUMANS = {
    "ORCA (reference)": {"humans": {"model": "orca"}},
    "social force": {"humans": {"model": "social_force"}},
    "mix 50/50": {"humans": {"mix": {"orca": 0.5, "social_force": 0.5}}},
}
REPLAY_LABEL = "replay (recording)"
N_ENVS = 256
TARGET_ENV_RATIO = 0.5
KERNEL_CONFIGS = ((1, 6), (256, 6), (256, 12))
TARGET_KERNEL = (256, 6)
TARGET_KERNEL_RATIO = 20.0
TIME_STEP = 0.25


def import_pysocialforce():
    """pysocialforce, imported from a temporary directory: on import it writes ``file.log`` into the working
    directory and sets the root logger to DEBUG with a console handler; both are undone here."""
    root = logging.getLogger()
    level, handlers, cwd = root.level, list(root.handlers), os.getcwd()
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        logging.disable(logging.INFO)  # what its import logs at DEBUG (matplotlib's font cache, ...) is not shown
        try:
            import pysocialforce
        except ImportError:
            sys.exit('error: benchmarks/bench_humans.py compares against PySocialForce: pip install '
                     '"pysocialforce==1.1.2" (or the test extras: pip install -e ".[test]")')
        finally:
            logging.disable(logging.NOTSET)
            os.chdir(cwd)
            for handler in [h for h in root.handlers if h not in handlers]:
                root.removeHandler(handler)
                handler.close()
            root.setLevel(level)
    return pysocialforce


# ---------------------------------------------------------------------------------------------------- env-steps/s


def write_recording(path: Path, n_pedestrians: int = 40, side: float = 14.0, speed: float = 1.2,
                    sample_rate: float = 2.5, seed: int = 0) -> Path:
    """An ETH/UCY-format file (``frame_id ped_id x y``, frame ids 10 apart): pedestrians entering one after another
    on a side of a square and walking straight across it."""
    rng = np.random.default_rng(seed)
    lines = []
    for pedestrian in range(1, n_pedestrians + 1):
        angle = rng.uniform(0.0, 2.0 * np.pi)
        start = 0.5 * side * np.array([np.cos(angle), np.sin(angle)])
        end = -start + rng.normal(0.0, 1.0, 2)
        n_samples = int(np.linalg.norm(end - start) / speed * sample_rate) + 1
        first = int(rng.integers(0, 400))
        for k in range(n_samples):
            x, y = start + (end - start) * k / max(1, n_samples - 1)
            lines.append((first + k, pedestrian, x, y))
    lines.sort()
    path.write_text("".join(f"{10 * frame}\t{pedestrian}.0\t{x:.3f}\t{y:.3f}\n" for frame, pedestrian, x, y in lines))
    return path


def warmed_vec_env(overrides: dict, n_envs: int, warmup_steps: int):
    """A VecEnv of ENV_CONFIG with these overrides, reset and stepped `warmup_steps` times (numba cache load; episode
    phases spread)."""
    vec = socnav.make_vec_env({**ENV_CONFIG, **overrides}, n_envs=n_envs)
    vec.seed(0)
    vec.reset()
    for action in np.random.default_rng(1).uniform(-1.0, 1.0, (warmup_steps, n_envs, 2)).astype(np.float32):
        vec.step(action)
    return vec


def measure_interleaved(steppers: dict[str, Callable[[np.ndarray], Any]], n_envs: int, seconds: float,
                        repeats: int, seed: int = 2) -> dict[str, dict]:
    """Env-steps/s of each warmed-up `step(actions)`: samples of ~`seconds` alternate between the steppers (A B C A B
    C ...), so drift of the machine hits all alike. Returns {label: {median, min, max}}."""
    rng = np.random.default_rng(seed)
    calls = {}
    for label, step in steppers.items():  # calls per sample, from a short calibration
        start, n = time.perf_counter(), 0
        while time.perf_counter() - start < seconds / 5:
            step(rng.uniform(-1.0, 1.0, (n_envs, 2)).astype(np.float32))
            n += 1
        calls[label] = max(1, int(n * 5))
    rates: dict[str, list[float]] = {label: [] for label in steppers}
    for _ in range(repeats):
        for label, step in steppers.items():
            actions = rng.uniform(-1.0, 1.0, (calls[label], n_envs, 2)).astype(np.float32)
            start = time.perf_counter()
            for action in actions:
                step(action)
            rates[label].append(calls[label] * n_envs / (time.perf_counter() - start))
    return {label: {"median": statistics.median(r), "min": min(r), "max": max(r)} for label, r in rates.items()}


# ---------------------------------------------------------------------------------------------------- the kernel


def crossing_crowds(n_envs: int, n_agents: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Agents on a 4 m circle heading for the opposite side, mid-way into the crossing (everyone interacts), walking
    at up to 1.3 v_pref, v_pref ~ U(0.5, 1)."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, (n_envs, n_agents))
    start = 4.0 * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    goals = -start + rng.normal(0, 0.3, start.shape)
    heading = (goals - start) / np.linalg.norm(goals - start, axis=-1, keepdims=True)
    v_pref = rng.uniform(0.5, 1.0, (n_envs, n_agents))
    positions = start + 2.5 * heading + rng.normal(0, 0.2, start.shape)
    velocities = heading * (v_pref * rng.uniform(0.5, 1.3, (n_envs, n_agents)))[..., None]
    return {"positions": positions, "velocities": velocities, "goals": goals, "v_pref": v_pref}


def crowd_of(state: dict[str, np.ndarray]) -> tuple[Crowd, np.ndarray]:
    n_envs, n_agents = state["v_pref"].shape
    active = np.ones((n_envs, n_agents), dtype=bool)
    crowd = Crowd(positions=state["positions"], velocities=state["velocities"], goals=state["goals"],
                  radii=np.full((n_envs, n_agents), 0.3), max_speeds=state["v_pref"], active=active,
                  radius_pad=np.zeros((n_envs, n_agents, n_agents)),
                  avoidance_share=np.full((n_envs, n_agents, n_agents), 0.5),
                  sees=np.ones((n_envs, n_agents, n_agents), dtype=bool))
    return crowd, active


def pysocialforce_simulators(psf, state: dict[str, np.ndarray]) -> list[tuple[Any, np.ndarray]]:
    """One PySocialForce simulator per environment, stepping by TIME_STEP, max speeds 1.3 v_pref (as the tests)."""
    sims = []
    for env in range(state["v_pref"].shape[0]):
        initial = np.concatenate([state["positions"][env], state["velocities"][env], state["goals"][env]], axis=1)
        sim = psf.Simulator(initial.copy())
        sim.peds.step_width = TIME_STEP
        sim.peds.initial_speeds = state["v_pref"][env].copy()
        sim.peds.state = initial.copy()  # recomputes max speeds from the initial speeds
        sims.append((sim, initial))
    return sims


def reset(sims) -> None:
    for sim, initial in sims:
        sim.peds.state = initial.copy()
        sim.peds.ped_states = sim.peds.ped_states[-1:]  # its history list would grow with every step


def measure_kernel(psf, configs=KERNEL_CONFIGS, repeats: int = 20) -> list[dict]:
    """Social force microseconds per agent-step: our kernel, its wrapper, PySocialForce's step; and the largest
    velocity difference after one step from the same state."""
    model = SocialForceHumans.from_config(load_config({"time_step": TIME_STEP, "humans": {"model": "social_force"}}))
    rows = []
    for n_envs, n_agents in configs:
        state = crossing_crowds(n_envs, n_agents)
        crowd, compute = crowd_of(state)
        agent_steps = n_envs * n_agents
        out = np.empty_like(crowd.velocities)
        no_walls = (np.zeros((n_envs, 0, 2)), np.zeros((n_envs, 0, 2)), np.zeros(n_envs, dtype=np.int64))
        arguments = (crowd.positions, crowd.velocities, crowd.goals, crowd.radii, crowd.max_speeds, crowd.active,
                     compute, crowd.radius_pad, crowd.sees, *no_walls, model.time_step, *model._arguments, out)
        ours_velocities = model.velocities(crowd, compute)  # loads the numba cache outside the timing
        from socnav.sim.humans.social_force import social_force_velocities_kernel as kernel

        kernel_s = _bench.best_of(lambda arguments=arguments: kernel(*arguments), repeats, agent_steps)
        wrapper_s = _bench.best_of(lambda crowd=crowd, compute=compute: model.velocities(crowd, compute), repeats,
                                   agent_steps)

        sims = pysocialforce_simulators(psf, state)
        reset(sims)
        for sim, _ in sims:
            sim.step()
        difference = max(np.abs(sim.peds.vel() - ours_velocities[env]).max() for env, (sim, _) in enumerate(sims))
        copies = max(1, 256 // n_envs)  # small batches: several passes per sample, far above the timer's resolution
        best = math.inf
        for _ in range(max(3, repeats // 4)):
            total = 0.0
            for _ in range(copies):
                reset(sims)
                start = time.perf_counter()
                for sim, _ in sims:
                    sim.step()
                total += time.perf_counter() - start
            best = min(best, total / copies)
        rows.append({"n_envs": n_envs, "n_agents": n_agents, "kernel_us": 1e6 * kernel_s / agent_steps,
                     "wrapper_us": 1e6 * wrapper_s / agent_steps, "psf_us": 1e6 * best / agent_steps,
                     "ratio": best / wrapper_s, "difference": difference})
    return rows


# ---------------------------------------------------------------------------------------------------- report


def _verdict(ok: bool) -> str:
    return "[bold green]PASS[/]" if ok else "[bold red]FAIL[/]"


def _spread(result: dict) -> str:
    return f"{result['median']:,.0f} [{result['min']:,.0f}-{result['max']:,.0f}]"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter samples and fewer repeats")
    parser.add_argument("--replay-files", nargs="+", metavar="FILE",
                        help="ETH/UCY-format recordings for the replay row (default: one the benchmark writes)")
    args = parser.parse_args(argv)
    seconds, repeats, kernel_repeats, warmup = (0.5, 3, 5, 100) if args.quick else (1.0, 7, 20, 300)
    console = Console(width=max(Console().width, 120))
    psf = import_pysocialforce()
    import numba

    console.print(f"[bold]socnav human models benchmark[/] ({'quick' if args.quick else 'full'} run)")
    console.print("single thread: " + ", ".join(f"{v}={os.environ[v]}" for v in _bench.THREAD_VARIABLES)
                  + f" (numba.config.NUMBA_NUM_THREADS={numba.config.NUMBA_NUM_THREADS})")
    console.print(f"single core:   {PINNED}")
    console.print(f"python {sys.version.split()[0]}, numpy {np.__version__}, numba {numba.__version__}, "
                  f"pysocialforce {psf.__version__}")
    t_start = time.perf_counter()

    # ---- table 1: the VecEnv with each human model ---------------------------------------------------------------
    scratch = tempfile.TemporaryDirectory()
    replay_files = args.replay_files or [str(write_recording(Path(scratch.name) / "crossing.txt"))]
    worlds = {**HUMANS, REPLAY_LABEL: {"scenario": "replay", "n_humans": None,
                                       "humans": {"model": "replay", "replay": {"files": replay_files}}}}
    vecs = {label: warmed_vec_env(overrides, N_ENVS, warmup) for label, overrides in worlds.items()}
    measured = measure_interleaved({label: vec.step for label, vec in vecs.items()}, N_ENVS, seconds, repeats)
    for vec in vecs.values():
        vec.close()
    scratch.cleanup()
    reference = measured["ORCA (reference)"]["median"]
    table = Table(title=f"Env-steps/s, one core, {N_ENVS} envs of {ENV_CONFIG['scenario']} (1 robot + "
                        f"{ENV_CONFIG['n_humans']} humans): median \\[min-max] of {repeats} interleaved samples")
    for column in ("humans", "env-steps/s", "ratio to ORCA", f"target >= {TARGET_ENV_RATIO:g}x"):
        table.add_column(column, justify="right")
    for label, result in measured.items():
        ratio = result["median"] / reference
        target = ("[dim]reference[/]" if label.startswith("ORCA") else
                  _verdict(ratio >= TARGET_ENV_RATIO) if label == "social force" else "[dim]no target[/]")
        table.add_row(label, _spread(result), f"{ratio:.2f}x", target)
    console.print(table)
    console.print(f"replay: {', '.join(Path(name).name for name in replay_files)} (the recording's crowd, robot "
                  "path through the scene centre); not a like-for-like ratio")

    # ---- table 2: the social force step against PySocialForce's ----------------------------------------------
    table = Table(title="Social force cost per agent-step (us), one core; ratio = PySocialForce step / ours (wrapper)")
    for column in ("envs x agents", "numba kernel", "numba wrapper", "PySocialForce step", "ratio",
                   f"target >= {TARGET_KERNEL_RATIO:g}x", "max |dv| after 1 step"):
        table.add_column(column, justify="right")
    for row in measure_kernel(psf, repeats=kernel_repeats):
        at_target = (row["n_envs"], row["n_agents"]) == TARGET_KERNEL
        table.add_row(f"{row['n_envs']} x {row['n_agents']}", f"{row['kernel_us']:.3f}", f"{row['wrapper_us']:.3f}",
                      f"{row['psf_us']:.2f}", f"{row['ratio']:.0f}x",
                      _verdict(row["ratio"] >= TARGET_KERNEL_RATIO) if at_target else "[dim]at 256 x 6[/]",
                      f"{row['difference']:.1e}")
    console.print(table)
    console.print("PySocialForce: one Simulator per environment (its step: forces, velocity cap, integration), "
                  "reset to the benchmark state before each timing sample; ours: one call for all environments.")
    console.print(f"total {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
