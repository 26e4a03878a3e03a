"""One unit of work, in whatever process runs it (this one, a pool worker, a Ray node): under its own lock, skipped
when done, prepared, executed by its kind's executor and marked done -- or its failure recorded, never raised.
"""

from __future__ import annotations

import contextlib
import time
import traceback
from pathlib import Path
from typing import Any

from socnav.experiments.registry import EXECUTORS, PROGRESS_FILE, load_kinds, unit_dir
from socnav.experiments.run_directory import ERROR_FILE, RunnerError, mark_done, prepare_unit_dir, unit_state
from socnav.experiments.units import Unit
from socnav.io import file_lock, real_directory, refuse_links, remove_links, remove_stale_temporaries, write_text_atomic

__all__ = ["execute_unit", "unit_lock_path"]


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
        problems = load_kinds() if unit.kind not in EXECUTORS else []  # a fresh worker has imported no kind yet
        if unit.kind not in EXECUTORS:
            raise RunnerError(f"no executor for unit kind {unit.kind!r}; known: {', '.join(sorted(EXECUTORS))}"
                              + "".join(f"; {problem}" for problem in problems))
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
