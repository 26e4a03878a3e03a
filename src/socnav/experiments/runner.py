"""Running an experiment: its units of work in a run directory of plain files, on a local process pool or on Ray,
skipping finished units, redoing half-written or corrupt ones, and recording every failure without stopping others.

Run directory (``socnav run`` writes it, ``socnav report`` reads it)::

    experiment.yaml                       the experiment file as given
    resolved.json                         the experiment with its budget applied (what runs), socnav version
    units.json                            the plan: every unit's id, kind, parameters, dependencies, spec hash
    .lock                                 held (flock) while a runner works in the directory
    train/<scenario>/<algo>/seed<k>/      one training unit (socnav.rl.training.train's run directory):
        unit.json                         what the unit was asked to do (with its spec hash)
        model.zip curve.csv eval.csv run.json tb/ checkpoints/
        done.json                         the completion marker (below); error.txt when the unit failed
    eval/<train scenario>/<algo>/seed<k>/<eval scenario>/   one evaluation of that policy:
        unit.json  episodes.parquet (one row per test episode)  summary.json  done.json  [error.txt]

A unit is finished iff its ``done.json`` -- written last, atomically -- parses, carries the unit's current spec
hash, lists outputs whose sizes and SHA-256 digests match the files, and records the digests of the inputs it
read (an evaluation: its training unit's model.zip) equal to those inputs' current digests. Anything else is
redone: a training unit that has no marker but a sound checkpoint resumes from it; a corrupt, stale or
half-written unit is wiped first. Every file a unit writes is written atomically and rewritten, never appended,
so a sweep killed at any moment and run again ends with each unit's results exactly once.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from socnav.config import YAML_MAX_BYTES

# The executors of the `uncertainty` kind register on import: here, so that every process running units (pool and
# Ray workers too) knows them.
from socnav.experiments import safety_benchmark_units, uncertainty_units  # noqa: F401
from socnav.experiments.registry import (
    EXECUTORS,
    PROGRESS_FILE,
    RESUMABLE,
    ExecutorResult,
    UnitProgress,
    file_digest,
    json_safe,
    read_progress,
    register_executor,
    single_threaded_torch,
    unit_dir,
)
from socnav.experiments.spec import Experiment, Unit, plan_units
from socnav.extras import install_hint
from socnav.io import (
    UntrustedInputError,
    file_lock,
    first_link,
    read_bounded,
    read_json,
    real_directory,
    refuse_links,
    remove_links,
    remove_stale_temporaries,
    write_text_atomic,
)

__all__ = [
    "RunSummary", "RunnerError", "UnitOutcome", "check_run_dir", "execute_unit", "mark_done", "prepare_run_dir",
    "prepare_unit_dir",
    "read_plan", "run_experiment", "unit_lock_path", "unit_state", "unit_states",
]

DONE_FILE = "done.json"
UNIT_FILE = "unit.json"
ERROR_FILE = "error.txt"
UnitState = Literal["done", "pending", "partial", "corrupt", "stale"]


class RunnerError(RuntimeError):
    """The run cannot start (busy or foreign run directory, missing backend); the message says why."""


# --------------------------------------------------------------------------------------------------------------
# Files and markers
# --------------------------------------------------------------------------------------------------------------

#: A unit's own small files (unit.json, done.json) are a few KB; the plan (units.json) can reach megabytes.
MARKER_MAX_BYTES = 1 << 20
PLAN_MAX_BYTES = 64 << 20


def _read_json(path: Path, max_bytes: int = MARKER_MAX_BYTES) -> Any:
    """The JSON of one of the run's own files, or None when it is missing, a symbolic link (never followed), too
    large, nested too deeply or not JSON: whatever cannot be read counts as absent, and its unit is redone."""
    try:
        return read_json(path, max_bytes=max_bytes, follow_links=False)
    except (OSError, UntrustedInputError):
        return None


def mark_done(root: Path, unit: Unit, outputs: list[str], inputs: dict[str, dict[str, Any]] | None = None,
              extra: dict[str, Any] | None = None) -> Path:
    """Write the unit's completion marker (last, atomically): digests of its `outputs` (paths relative to the unit
    directory) and of the `inputs` it read (``{"<unit id>/<file>": digest}``)."""
    directory = unit_dir(root, unit)
    refuse_links(root, directory)  # the marker goes where the unit's directory really is, never through a link
    marker = {
        "unit": unit.id, "kind": unit.kind, "spec_hash": unit.spec_hash,
        "outputs": {name: file_digest(directory / name) for name in outputs},
        "inputs": inputs or {}, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "host": socket.gethostname(),
        **(extra or {}),
    }
    return write_text_atomic(directory / DONE_FILE, json.dumps(json_safe(marker), indent=2, sort_keys=True))


def _marker(root: Path, unit_id: str) -> dict[str, Any] | None:
    path = unit_dir(root, unit_id) / DONE_FILE
    if first_link(root, path) is not None:  # a unit reached through a link is not the run's own
        return None
    marker = _read_json(path)
    return marker if isinstance(marker, dict) else None


def unit_state(root: Path, unit: Unit, check_inputs: bool = True) -> UnitState:
    """done | pending (nothing there) | partial (started, no marker) | corrupt (marker or outputs damaged) |
    stale (finished for other parameters, or its inputs changed since). A symbolic link on the way to the unit or
    to one of its outputs makes it corrupt: it is redone in a real directory, never read through the link."""
    directory = unit_dir(root, unit)
    if first_link(root, directory / DONE_FILE) is not None:
        return "corrupt"
    if not (directory / DONE_FILE).exists():
        return "partial" if directory.exists() else "pending"
    marker = _marker(root, unit.id)
    if marker is None or not isinstance(marker.get("outputs"), dict) or not isinstance(marker.get("inputs"), dict):
        return "corrupt"
    if marker.get("spec_hash") != unit.spec_hash:
        return "stale"
    for name, expected in marker["outputs"].items():
        path = directory / name
        if not isinstance(name, str) or not isinstance(expected, dict) or not _inside(directory, path):
            return "corrupt"
        if first_link(directory, path) is not None or not path.is_file():
            return "corrupt"
        if path.stat().st_size != expected.get("size") or file_digest(path) != expected:
            return "corrupt"
    if check_inputs:
        for name, expected in marker["inputs"].items():
            dep_id, _, file_name = str(name).rpartition("/")
            dep_marker = _marker(root, dep_id) if _plain_unit_id(dep_id) else None
            dep_outputs = dep_marker.get("outputs") if dep_marker is not None else None
            if not isinstance(dep_outputs, dict) or dep_outputs.get(file_name) != expected:
                return "stale"
    return "done"


def _inside(directory: Path, path: Path) -> bool:
    """Whether `path` (a name a marker lists) stays inside `directory`: relative, without '..'."""
    relative = path.relative_to(directory) if path.is_relative_to(directory) else None
    return relative is not None and ".." not in relative.parts and relative.parts != ()


def _plain_unit_id(unit_id: str) -> bool:
    """Whether `unit_id` names a directory inside the run (relative, no '..', as the planners make them)."""
    parts = Path(unit_id).parts
    return bool(parts) and not Path(unit_id).is_absolute() and ".." not in parts


def unit_states(root: Path, units: list[Unit]) -> dict[str, UnitState]:
    """State of every unit; a unit whose dependency is not done is not done either."""
    states: dict[str, UnitState] = {}
    for unit in units:
        state = unit_state(root, unit)
        if state == "done" and any(states.get(dep) != "done" for dep in unit.deps):
            state = "stale"
        states[unit.id] = state
    return states


# --------------------------------------------------------------------------------------------------------------
# Executors of the table1 kind: training and evaluation units
# --------------------------------------------------------------------------------------------------------------

def _sound_checkpoint(directory: Path) -> bool:
    """Whether `train(resume=True)` can continue the training unit in `directory` (or start it: no checkpoint yet):
    its state.json and the checkpoint it names validate and agree (read safely, nothing unpickled)."""
    from socnav.rl.training import can_resume

    return can_resume(directory)


@register_executor("train", resumable=_sound_checkpoint)
def _execute_train(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.rl.training import train

    p = unit.params
    single_threaded_torch()
    bar = UnitProgress(directory, p["timesteps"], "steps")
    # resume=True: a kept partial unit passed _sound_checkpoint, so train continues from its checkpoint (or starts
    # afresh when there is none) and never discards one.
    result = train(p["env"], p["algo"], p["seed"], p["timesteps"], directory, n_envs=p["n_envs"],
                   overrides=p["overrides"], eval_every=p["eval_every"], eval_episodes=p["validation_episodes"],
                   resume=True, progress=lambda steps, _: bar.update(steps), tensorboard=True)
    return ExecutorResult(["model.zip", "curve.csv", "eval.csv", "run.json"],
                          extra={"timesteps": result.timesteps, "train_wall_time_s": result.wall_time_s,
                                 "resumed": result.resumed_from > 0, "final_validation": result.final_eval})


@register_executor("eval")
def _execute_eval(root: Path, unit: Unit, directory: Path) -> ExecutorResult:
    from socnav.envs.rollout import rollout_episodes, summarize
    from socnav.io import write_table_atomic
    from socnav.rl.persistence import load_policy

    p = unit.params
    single_threaded_torch()
    (train_id,) = unit.deps
    model = unit_dir(root, train_id) / "model.zip"
    model_digest = file_digest(model)
    bar = UnitProgress(directory, p["episodes"], "episodes")
    records = rollout_episodes(load_policy(model), p["env"], p["episodes"], seed=p["seed"], n_envs=p["n_envs"],
                               deterministic=p["deterministic"], progress=bar.advance)
    summary = summarize(records)
    records.insert(0, "eval_scenario", p["eval_scenario"])
    records.insert(0, "train_seed", p["train_seed"])
    records.insert(0, "algo", p["algo"])
    records.insert(0, "train_scenario", p["train_scenario"])
    write_table_atomic(records, directory / "episodes.parquet")
    write_text_atomic(directory / "summary.json", json.dumps(json_safe(summary), indent=2, sort_keys=True))
    return ExecutorResult(["episodes.parquet", "summary.json"], inputs={f"{train_id}/model.zip": model_digest})


# --------------------------------------------------------------------------------------------------------------
# One unit, in whatever process runs it
# --------------------------------------------------------------------------------------------------------------

def unit_lock_path(root: Path, unit: Unit) -> Path:
    """The lock file a unit's worker holds while it works on the unit (``.locks/<unit id>.lock``)."""
    return Path(root) / ".locks" / (unit.id.replace("/", "__") + ".lock")


def execute_unit(unit_json: dict[str, Any], root: str) -> dict[str, Any]:
    """Do one unit unless it is already done; never raises for the unit's own errors.

    Returns ``{"id", "status": "done" | "skipped" | "failed", "wall_time_s", "error"?}``; a failure leaves the
    traceback in the unit's ``error.txt``. Holds a per-unit lock, so a stray copy of the same unit (a worker of a
    killed runner, a retried Ray task) never writes the unit at the same time. ``done.json`` records the state the
    unit was found in (``previous_state``: ``pending``, or ``partial`` / ``corrupt`` / ``stale`` when an earlier
    attempt -- e.g. on a worker or Ray node that died -- was continued or redone).
    """
    unit, run_root = Unit.from_json(unit_json), Path(root)
    started = time.perf_counter()
    try:
        real_directory(run_root, run_root / ".locks")  # never a lock file made through a planted link
        with file_lock(unit_lock_path(run_root, unit)):
            return _execute_locked(unit, run_root, started)
    except OSError as exc:  # a planted link or file where the unit's lock goes: the unit fails, the sweep goes on
        return {"id": unit.id, "status": "failed", "wall_time_s": time.perf_counter() - started,
                "error": f"{type(exc).__name__}: {exc}".strip()}


def _execute_locked(unit: Unit, run_root: Path, started: float) -> dict[str, Any]:
    """`execute_unit` once the unit's lock is held; never raises for the unit's own errors."""
    directory = unit_dir(run_root, unit)
    try:
        # A symbolic link on the way to the unit (or the unit's directory itself) is removed before anything is
        # read, deleted or written there: the unit is redone in a real directory, the link's target untouched.
        remove_links(run_root, directory)
        remove_stale_temporaries(directory)  # a killed writer's half-written files; the unit lock is ours
        state = unit_state(run_root, unit)
        if state == "done":
            return {"id": unit.id, "status": "skipped", "wall_time_s": 0.0}
        if unit.kind not in EXECUTORS:
            raise RunnerError(f"no executor for unit kind {unit.kind!r}; known: {', '.join(sorted(EXECUTORS))}")
        prepare_unit_dir(run_root, unit, state)
        result = EXECUTORS[unit.kind](run_root, unit, directory)
        elapsed = time.perf_counter() - started
        (directory / PROGRESS_FILE).unlink(missing_ok=True)
        mark_done(run_root, unit, result.outputs, result.inputs,
                  {"wall_time_s": elapsed, "previous_state": state, **result.extra})
        return {"id": unit.id, "status": "done", "wall_time_s": elapsed}
    except Exception as exc:  # the unit's own failure: recorded, reported, the sweep goes on
        text = traceback.format_exc()
        with contextlib.suppress(OSError):
            refuse_links(run_root, directory)
            write_text_atomic(directory / ERROR_FILE, text)
        return {"id": unit.id, "status": "failed", "wall_time_s": time.perf_counter() - started,
                "error": f"{type(exc).__name__}: {exc}".strip()}


def prepare_unit_dir(root: Path, unit: Unit, state: UnitState) -> None:
    """Wipe what cannot be continued; keep a partial unit of the same spec whose kind can resume."""
    directory = unit_dir(root, unit)
    keep = False
    if state == "partial":
        recorded = _read_json(directory / UNIT_FILE)
        same_spec = isinstance(recorded, dict) and recorded.get("spec_hash") == unit.spec_hash
        keep = same_spec and unit.kind in RESUMABLE and RESUMABLE[unit.kind](directory)
    if directory.exists() and not keep:
        refuse_links(root, directory)  # rmtree removes links inside without following them; never one above
        shutil.rmtree(directory)
    real_directory(root, directory)
    for name in (ERROR_FILE, DONE_FILE, PROGRESS_FILE):
        (directory / name).unlink(missing_ok=True)
    write_text_atomic(directory / UNIT_FILE, json.dumps(unit.to_json(), indent=2, sort_keys=True))


# --------------------------------------------------------------------------------------------------------------
# The run directory
# --------------------------------------------------------------------------------------------------------------

def prepare_run_dir(root: Path, experiment: Experiment, source: Path | None = None) -> list[Unit]:
    """Create/check the run directory, write the plan; refuse a directory holding another experiment or budget."""
    import socnav

    units = plan_units(experiment)
    root.mkdir(parents=True, exist_ok=True)
    _check_same_experiment(root, experiment)
    if source is not None:
        # within the limit load_experiment read it with (a path such as /proc reports no size)
        write_text_atomic(root / "experiment.yaml", read_bounded(source, YAML_MAX_BYTES).decode())
    write_text_atomic(root / "resolved.json", json.dumps(
        {"experiment": experiment.to_json(), "socnav_version": socnav.__version__}, indent=2, sort_keys=True))
    write_text_atomic(root / "units.json", json.dumps([unit.to_json() for unit in units], indent=2))
    return units


def _check_same_experiment(root: Path, experiment: Experiment) -> None:
    """:raises RunnerError: `root` holds the plan of another experiment or budget."""
    existing = _read_json(root / "resolved.json", PLAN_MAX_BYTES)
    recorded = existing.get("experiment") if isinstance(existing, dict) else None
    if isinstance(recorded, dict):
        before = (recorded.get("name"), recorded.get("budget"))
        now = (experiment.name, experiment.budget)
        if before != now:
            raise RunnerError(
                f"{root} holds experiment {before[0]!r} with budget {before[1]!r}, not {now[0]!r} with budget "
                f"{now[1]!r}; choose another --out (units of a different budget would overwrite its results)"
            )


def check_run_dir(root: str | Path, experiment: Experiment) -> None:
    """What `run_experiment` would refuse about the run directory `root`, checked without writing anything (``socnav
    run --dry-run``, so that it never lists units the real run then refuses): a file where the directory goes, a
    directory that cannot be created, a linked or held ``.lock``, another experiment or budget in it.

    :raises RunnerError: as `run_experiment` would, with its message.
    """
    root = Path(root).resolve()
    existing = next((path for path in (root, *root.parents) if path.exists()), None)
    if existing is not None and not existing.is_dir():
        raise RunnerError(f"cannot create the run directory {root}: {existing} is a file, not a directory")
    if existing is not None and existing != root and not os.access(existing, os.W_OK | os.X_OK):
        raise RunnerError(f"cannot create the run directory {root}: {existing} is not writable")
    if not root.is_dir():
        return  # a new run directory: nothing in it to refuse
    lock = root / ".lock"
    if lock.is_symlink():
        raise RunnerError(f"{lock} is a symbolic link; socnav never follows a link inside a run directory (remove it)")
    if lock.is_file():  # opened without creating anything: it exists
        with file_lock(lock, blocking=False) as locked:
            if not locked:
                raise RunnerError(f"another socnav run is working in {root} (its .lock is held)")
    _check_same_experiment(root, experiment)


def read_plan(root: Path) -> tuple[dict[str, Any], list[Unit]]:
    """The resolved experiment and the units of a run directory."""
    files = {}
    for name in ("resolved.json", "units.json"):
        try:
            files[name] = read_json(root / name, max_bytes=PLAN_MAX_BYTES, follow_links=False)
        except FileNotFoundError:
            raise RunnerError(f"{root} is not a socnav run directory (it has no {name})") from None
        except (OSError, UntrustedInputError) as exc:
            raise RunnerError(f"{root} is not a readable socnav run directory: {exc}") from None
    resolved, plan = files["resolved.json"], files["units.json"]
    if not isinstance(resolved, dict) or not isinstance(resolved.get("experiment"), dict) or not isinstance(plan, list):
        raise RunnerError(f"{root} is not a socnav run directory (resolved.json or units.json has the wrong shape)")
    try:
        units = [Unit.from_json(item) for item in plan]
    except (TypeError, KeyError, ValueError, AttributeError) as exc:
        raise RunnerError(f"{root}/units.json lists an invalid unit ({type(exc).__name__}: {exc})") from None
    bad = [unit.id for unit in units if not isinstance(unit.id, str) or not _plain_unit_id(unit.id)]
    if bad:
        raise RunnerError(f"{root}/units.json lists a unit outside the run directory: {bad[0]!r}")
    return resolved["experiment"], units


# --------------------------------------------------------------------------------------------------------------
# Backends
# --------------------------------------------------------------------------------------------------------------

class WorkerLost(RuntimeError):
    """The process running a unit died (killed, out of memory) before reporting."""


def _worker_init(parent_pid: int) -> None:
    """Pool worker start: exit as soon as the runner is gone, so a killed sweep leaves no unit running."""

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(3)
            time.sleep(0.5)

    threading.Thread(target=watch, name="socnav-parent-watch", daemon=True).start()


class _LocalBackend:
    """A pool of spawned processes (one unit each at a time); workers=0 runs units in this process."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool: Any = None
        self.inline_results: dict[int, dict[str, Any]] = {}

    @property
    def capacity(self) -> int:
        return max(1, self.workers)

    def _pool(self) -> Any:
        if self.pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_worker_init, initargs=(os.getpid(),))
        return self.pool

    def submit(self, unit: Unit, root: Path) -> Any:
        if self.workers == 0:
            handle = len(self.inline_results)
            self.inline_results[handle] = execute_unit(unit.to_json(), str(root))
            return handle
        return self._pool().submit(execute_unit, unit.to_json(), str(root))

    def wait(self, handles: list[Any], timeout: float) -> list[Any]:
        if self.workers == 0:
            return list(handles)
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(handles, timeout=timeout, return_when=FIRST_COMPLETED)
        return list(done)

    def result(self, handle: Any) -> dict[str, Any]:
        if self.workers == 0:
            return self.inline_results.pop(handle)
        from concurrent.futures.process import BrokenProcessPool

        try:
            return handle.result()
        except BrokenProcessPool:
            self._reset()
            raise WorkerLost("the worker process died (killed or out of memory)") from None

    def _reset(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = None

    def close(self, cancel: bool = False) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=not cancel, cancel_futures=cancel)
            self.pool = None


#: Seconds to wait for a Ray head's port to accept a connection, and for a whole `ray.init` to connect, before
#: giving up on the address.
RAY_CONNECT_TIMEOUT_S = 10.0
RAY_INIT_TIMEOUT_S = 90.0


def _check_ray_connects(address: str, timeout: float = RAY_INIT_TIMEOUT_S) -> None:
    """Connect to `address` once in a child process that is killed after `timeout` seconds: ``ray.init`` retries an
    address where no Ray answers for a long time, inside native code that neither a timeout nor Ctrl-C reaches, so
    the sweep's own ``ray.init`` only runs once a connection is known to succeed. Ctrl-C stops the child too."""
    import subprocess
    import sys

    code = ("import sys, ray; ray.init(address=sys.argv[1], log_to_driver=False, configure_logging=False); "
            "ray.shutdown()")
    try:
        done = subprocess.run([sys.executable, "-c", code, address], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: no Ray answered within {timeout:.0f} s "
                          "(is it the head's address, and does the head run?)") from None
    if done.returncode != 0:
        lines = [line.strip() for line in done.stderr.splitlines() if line.strip()]
        last = lines[-1][:300] if lines else f"exit code {done.returncode}"
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: {last}")


def _probe_ray_address(address: str, timeout: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Refuse a ``host:port`` (or ``ray://host:port``) Ray address at which nothing accepts a connection, within
    `timeout` seconds: ``ray.init`` itself retries such an address without end, inside native code that Ctrl-C
    cannot interrupt. ``auto`` and ``local`` are Ray's to resolve (they fail fast without a cluster)."""
    if address in ("auto", "local"):
        return
    target = address.removeprefix("ray://")
    host, _, port = target.rpartition(":")
    host = host.strip("[]")  # [::1]:6379
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RunnerError(f"--address {address!r} is not a Ray address; allowed: auto, HOST:PORT (the head's GCS "
                          "port, e.g. 10.0.0.5:6379) or ray://HOST:PORT (Ray Client)")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout) as connection:
            answers = _answers_http2(connection, timeout)
    except OSError as exc:
        reason = (f"no answer within {timeout:.0f} s" if isinstance(exc, TimeoutError)
                  else (exc.strerror or type(exc).__name__).lower())
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: nothing accepts connections at "
                          f"{host}:{port} ({reason}); start its head with `ray start --head --port {port}` or check "
                          "the address") from None
    if not answers:
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: {host}:{port} accepts connections but "
                          f"does not answer as Ray's (gRPC) server within {timeout:.0f} s; is it the head's port "
                          "(`ray start --head --port PORT`, or ray://HOST:10001 for Ray Client)?")


# What an HTTP/2 client sends first (RFC 9113 section 3.4): the preface, then its SETTINGS frame (empty here).
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def _answers_http2(connection: socket.socket, timeout: float) -> bool:
    """Whether the server on `connection` speaks HTTP/2, as Ray's gRPC servers (GCS, Ray Client) do: its first
    frame must be SETTINGS (type 4). Skipped (True) with TLS on (``RAY_USE_TLS``), where the handshake comes first.
    """
    if os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
        return True
    connection.settimeout(timeout)
    try:
        connection.sendall(_HTTP2_PREFACE)
        header = b""
        deadline = time.monotonic() + timeout
        while len(header) < 9 and time.monotonic() < deadline:
            chunk = connection.recv(9 - len(header))
            if not chunk:
                break
            header += chunk
    except OSError:
        return False
    return len(header) == 9 and header[3] == 4


class _RayBackend:
    """Units as Ray tasks (1 CPU each, retried on worker/node failure); the run directory must be on a filesystem
    every Ray node sees (or the cluster is this machine)."""

    def __init__(self, address: str | None, workers: int, retries: int):
        try:
            import ray
        except ImportError:
            raise RunnerError(f"the ray backend needs Ray: {install_hint('ray')}") from None
        self.ray = ray
        self.started_here = False
        if not ray.is_initialized():
            if address is None:  # a Ray of our own on this machine, quiet
                ray.init(log_to_driver=False, configure_logging=False, include_dashboard=False)
            else:  # an existing cluster ("auto", "host:6379") or a Ray Client address ("ray://host:10001")
                _probe_ray_address(address)
                _check_ray_connects(address)
                try:
                    ray.init(address=address, log_to_driver=False)
                except (ConnectionError, RuntimeError, ValueError) as exc:
                    raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: {exc}") from None
            self.started_here = True
        self.workers = workers
        self.task = ray.remote(num_cpus=1, max_retries=retries, retry_exceptions=False)(execute_unit)

    @property
    def capacity(self) -> int:
        if self.workers > 0:
            return self.workers
        return max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    def submit(self, unit: Unit, root: Path) -> Any:
        return self.task.options(name=unit.id).remote(unit.to_json(), str(root))

    def wait(self, handles: list[Any], timeout: float) -> list[Any]:
        done, _ = self.ray.wait(handles, num_returns=1, timeout=timeout)
        return list(done)

    def result(self, handle: Any) -> dict[str, Any]:
        try:
            return self.ray.get(handle)
        except self.ray.exceptions.RayError as exc:
            raise WorkerLost(f"Ray task failed after retries: {type(exc).__name__}: {exc}") from None

    def close(self, cancel: bool = False) -> None:
        if self.started_here:
            self.ray.shutdown()


# --------------------------------------------------------------------------------------------------------------
# The sweep
# --------------------------------------------------------------------------------------------------------------

@dataclass
class UnitOutcome:
    """How one unit of a sweep ended: done, skipped (already done), failed or blocked, its time and error."""

    id: str
    status: Literal["done", "skipped", "failed", "blocked"]
    wall_time_s: float = 0.0
    error: str | None = None


@dataclass
class RunSummary:
    """The outcome of every unit of a run directory's sweep, in plan order."""

    root: Path
    outcomes: dict[str, UnitOutcome]

    def count(self, status: str) -> int:
        return sum(outcome.status == status for outcome in self.outcomes.values())

    @property
    def failed(self) -> list[UnitOutcome]:
        return [o for o in self.outcomes.values() if o.status in ("failed", "blocked")]

    @property
    def ok(self) -> bool:
        return not self.failed


class Reporter:
    """What the sweep tells its observer (the CLI's progress display); every method may be left as is."""

    def start(self, total: int, already_done: int, redo: dict[str, int]) -> None: ...
    def unit_started(self, unit: Unit) -> None: ...
    def unit_finished(self, unit: Unit, outcome: UnitOutcome) -> None: ...
    def unit_progress(self, unit: Unit, done: int, total: int, what: str) -> None: ...


def run_experiment(
    experiment: Experiment,
    root: str | Path,
    backend: Literal["local", "ray"] = "local",
    workers: int | None = None,
    address: str | None = None,
    retries: int = 1,
    source: Path | None = None,
    reporter: Reporter | None = None,
) -> RunSummary:
    """Run every unit of `experiment` not yet done in `root`; returns each unit's outcome.

    :param workers: units at a time (local default: the number of CPUs; 0 runs them in this process);
        with Ray, the most tasks in flight (default: the cluster's CPUs).
    :param retries: times a unit is retried after its worker died (Ray: ``max_retries``); a unit raising an
        error is not retried, it fails with ``error.txt``.
    :raises RunnerError: another runner holds `root`, `root` holds another experiment, or Ray is missing.
    """
    root = Path(root).resolve()
    reporter = reporter or Reporter()
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file among its parents, no permission: one line, before any work
        raise RunnerError(f"cannot create the run directory {root}: {exc.strerror or exc}") from None
    if (root / ".lock").is_symlink():  # file_lock would refuse it too, as an OSError
        raise RunnerError(f"{root / '.lock'} is a symbolic link; socnav never follows a link inside a run directory "
                          "(remove it)")
    with file_lock(root / ".lock", blocking=False) as locked:
        if not locked:
            raise RunnerError(f"another socnav run is working in {root} (its .lock is held)")
        remove_stale_temporaries(root, recursive=False)  # the units' own are removed under their unit locks
        real_directory(root, root / ".locks")  # the units' locks: a planted link there is replaced, not followed
        units = prepare_run_dir(root, experiment, source)
        return _sweep(units, root, backend, workers, address, retries, reporter)


def _sweep(units: list[Unit], root: Path, backend_name: str, workers: int | None, address: str | None,
           retries: int, reporter: Reporter) -> RunSummary:
    states = unit_states(root, units)
    outcomes: dict[str, UnitOutcome] = {u.id: UnitOutcome(u.id, "skipped") for u in units if states[u.id] == "done"}
    todo = [unit for unit in units if states[unit.id] != "done"]
    redo: dict[str, int] = {}
    for unit in todo:
        redo[states[unit.id]] = redo.get(states[unit.id], 0) + 1
    reporter.start(len(units), len(outcomes), redo)
    if not todo:
        return RunSummary(root, outcomes)

    backend = _open_backend(backend_name, workers, address, retries)
    by_id = {unit.id: unit for unit in units}
    waiting = list(todo)
    running: dict[Any, Unit] = {}
    attempts: dict[str, int] = {}
    cancelled = True
    try:
        while waiting or running:
            _block_unrunnable(waiting, outcomes, reporter)
            ready = [u for u in waiting if all(dep in outcomes and outcomes[dep].status in ("done", "skipped")
                                               for dep in u.deps)]
            for unit in ready[: max(0, backend.capacity - len(running))]:
                waiting.remove(unit)
                reporter.unit_started(unit)
                running[backend.submit(unit, root)] = unit
            if not running:
                if waiting:  # cannot happen with a valid plan; never spin
                    raise RunnerError(f"units wait for dependencies that are not planned: {[u.id for u in waiting]}")
                break
            finished = backend.wait(list(running), timeout=0.5)
            for unit in running.values():  # the running units' own progress files (`UnitProgress`)
                progress = read_progress(unit_dir(root, unit))
                if progress is not None:
                    reporter.unit_progress(unit, *progress)
            for handle in finished:
                if handle not in running:  # put back after its pool broke (below)
                    continue
                unit = running.pop(handle)
                local_retries = retries if backend_name == "local" else 0
                outcome = _unit_outcome(backend, handle, unit, root, local_retries, attempts)
                if outcome is None:  # its local worker died and it may be retried: the whole pool went down with it
                    waiting.insert(0, unit)
                    for other_handle, other in list(running.items()):
                        running.pop(other_handle)
                        waiting.insert(0, other)
                    continue
                outcomes[unit.id] = outcome
                reporter.unit_finished(unit, outcome)
        cancelled = False
    finally:
        backend.close(cancel=cancelled)
    ordered = {unit.id: outcomes[unit.id] for unit in by_id.values() if unit.id in outcomes}
    return RunSummary(root, ordered)


def _open_backend(name: str, workers: int | None, address: str | None, retries: int) -> Any:
    """The local process pool or the Ray cluster; `workers` None: every local CPU, or the cluster's."""
    if workers is None:
        workers = (os.cpu_count() or 1) if name == "local" else 0
    if name == "local":
        return _LocalBackend(workers)
    if name == "ray":
        return _RayBackend(address, workers, retries)
    raise RunnerError(f"unknown backend {name!r}; allowed: local, ray")


def _block_unrunnable(waiting: list[Unit], outcomes: dict[str, UnitOutcome], reporter: Reporter) -> None:
    """Take the units whose dependencies failed (they can never run) off `waiting`, as ``blocked``."""
    for unit in list(waiting):
        bad = [dep for dep in unit.deps if dep in outcomes and outcomes[dep].status in ("failed", "blocked")]
        if bad:
            waiting.remove(unit)
            outcome = UnitOutcome(unit.id, "blocked", error=f"dependency {bad[0]} failed")
            outcomes[unit.id] = outcome
            reporter.unit_finished(unit, outcome)


def _unit_outcome(backend: Any, handle: Any, unit: Unit, root: Path, retries: int,
                  attempts: dict[str, int]) -> UnitOutcome | None:
    """The outcome of a finished unit; None when its worker died and it may be retried (`retries` times, counted
    in `attempts`; 0 with Ray, which retries its tasks itself), ``failed`` (with ``error.txt``) when it may not."""
    try:
        result = backend.result(handle)
        return UnitOutcome(unit.id, result["status"], result.get("wall_time_s", 0.0), result.get("error"))
    except WorkerLost as exc:
        attempts[unit.id] = attempts.get(unit.id, 0) + 1
        if attempts[unit.id] <= retries:
            return None
        with contextlib.suppress(OSError):
            write_text_atomic(unit_dir(root, unit) / ERROR_FILE, f"{exc}\n")
        return UnitOutcome(unit.id, "failed", error=str(exc))
