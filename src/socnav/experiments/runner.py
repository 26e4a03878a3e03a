"""Running an experiment: its units of work in a run directory of plain files (`socnav.experiments.run_directory`),
on a local process pool or on Ray (`socnav.experiments.backends`), skipping finished units, redoing half-written or
corrupt ones, and recording every failure without stopping others.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from socnav.experiments.backends import LocalBackend, RayBackend, WorkerLost
from socnav.experiments.execution import execute_unit, unit_lock_path
from socnav.experiments.registry import read_progress, unit_dir
from socnav.experiments.run_directory import (
    ERROR_FILE,
    RunnerError,
    check_run_dir,
    mark_done,
    prepare_run_dir,
    prepare_unit_dir,
    read_plan,
    unit_state,
    unit_states,
)
from socnav.experiments.spec import Experiment
from socnav.experiments.units import Unit
from socnav.io import file_lock, real_directory, remove_stale_temporaries, write_text_atomic

__all__ = [
    "RunSummary", "RunnerError", "UnitOutcome", "check_run_dir", "execute_unit", "mark_done", "prepare_run_dir",
    "prepare_unit_dir",
    "read_plan", "run_experiment", "unit_lock_path", "unit_state", "unit_states",
]


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
        return LocalBackend(workers)
    if name == "ray":
        return RayBackend(address, workers, retries)
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
