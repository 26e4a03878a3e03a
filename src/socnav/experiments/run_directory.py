"""The run directory of an experiment: its plan, one directory per unit of work, and the completion markers that
say, from the files alone, which units are finished, half-written, corrupt or stale.


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

import json
import os
import shutil
import socket
import time
from pathlib import Path
from typing import Any, Literal

from socnav.config import YAML_MAX_BYTES
from socnav.experiments.registry import PROGRESS_FILE, RESUMABLE, file_digest, json_safe, unit_dir
from socnav.experiments.spec import Experiment, plan_units
from socnav.experiments.units import Unit
from socnav.io import (
    UntrustedInputError,
    file_lock,
    first_link,
    read_bounded,
    read_json,
    real_directory,
    refuse_links,
    write_text_atomic,
)

__all__ = [
    "DONE_FILE", "ERROR_FILE", "UNIT_FILE", "RunnerError", "UnitState", "check_run_dir", "mark_done",
    "prepare_run_dir", "prepare_unit_dir", "read_plan", "unit_state", "unit_states",
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
# The plan
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
