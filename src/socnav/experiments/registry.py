"""What an experiment kind plugs into the engine -- its unit planner (`socnav run`), unit executors and report sections
(`socnav report`) -- and what they are given: the unit directories of a run, the report context, strict JSON.

A kind is a module that registers, when imported, its planner with ``@register_planner("kind", count=...)``, the
executors of its units with ``@register_executor("unit kind")`` and its page with ``register_section("kind",
"name")``. The engine finds a kind by its name in `KIND_MODULES` (socnav's own: the paper's experiments in
`socnav.paper`) or in the entry points of the group ``socnav.experiment_kinds`` (another package's), and imports its
module on first use -- as Gymnasium's registry finds an environment by its entry point's name -- so the engine never
imports the kinds built on it.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.metadata
import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from socnav.experiments.units import Unit
from socnav.io import json_safe, read_json, read_table, write_text_atomic

__all__ = [
    "ENTRY_POINT_GROUP", "EXECUTORS", "KIND_MODULES", "PLANNERS", "PROGRESS_FILE", "RESUMABLE", "SECTIONS",
    "UNIT_COUNTS", "Executor", "ExecutorResult", "Planner", "ReportContext", "Section", "UnitCounter", "UnitProgress",
    "experiment_kinds", "file_digest", "json_safe", "load_kind", "load_kinds", "read_progress", "register_executor",
    "register_planner", "register_section", "single_threaded_torch", "unit_dir",
]


# --------------------------------------------------------------------------------------------------------------
# Experiment kinds: found by name, imported on first use
# --------------------------------------------------------------------------------------------------------------

#: socnav's own experiment kinds -> the module registering each (the paper's Table 1, Tables 2-3, the safety
#: benchmark); listed in the order `socnav run` names them.
KIND_MODULES: dict[str, str] = {
    "table1": "socnav.paper.table1",
    "uncertainty": "socnav.paper.uncertainty",
    "safety_benchmark": "socnav.paper.safety_benchmark",
}
#: The entry-point group through which another installed package adds experiment kinds (name = kind, value = module).
ENTRY_POINT_GROUP = "socnav.experiment_kinds"


@functools.cache
def _kind_modules() -> dict[str, str]:
    """Every known experiment kind -> its module: socnav's own, then those of installed plugins (read once)."""
    plugins = {entry.name: entry.module for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    return {**KIND_MODULES, **{name: module for name, module in plugins.items() if name not in KIND_MODULES}}


def experiment_kinds() -> list[str]:
    """The names of every known experiment kind (nothing imported): those found by name, then those registered in
    this process by other means (a script or notebook calling `register_planner` itself)."""
    return list(dict.fromkeys([*_kind_modules(), *PLANNERS]))


def load_kind(kind: str) -> None:
    """Import the module of experiment kind `kind`, which registers its planner, executors and sections.

    :raises ValueError: `kind` is unknown (the message names the known kinds), or its module cannot be imported or
        registers no planner.
    """
    if kind in PLANNERS:
        return
    modules = _kind_modules()
    if kind not in modules:
        raise ValueError(f"unknown experiment kind {kind!r}; known kinds: {', '.join(modules)}")
    try:
        importlib.import_module(modules[kind])
    except ImportError as error:  # a plugin not installed, or broken: one line naming the kind and its module
        raise ValueError(f"experiment kind {kind!r}: its module {modules[kind]} cannot be imported ({error})") from None
    if kind not in PLANNERS:
        raise ValueError(f"experiment kind {kind!r}: its module {modules[kind]} registers no planner")


def load_kinds() -> list[str]:
    """Import every experiment kind known by name: what a process running units of any kind needs. A kind that
    cannot be loaded does not stop the others; returns why each such kind could not (empty: all loaded)."""
    problems = []
    for kind in _kind_modules():
        try:
            load_kind(kind)
        except ValueError as error:
            problems.append(str(error))
    return problems


# --------------------------------------------------------------------------------------------------------------
# Planners: the units of an experiment
# --------------------------------------------------------------------------------------------------------------

#: (resolved experiment) -> its units, every unit after those it depends on.
Planner = Callable[[Any], list[Unit]]
#: (resolved experiment) -> an upper bound of its units from the grid's sizes alone, counted before any is built.
UnitCounter = Callable[[Any], int]
#: experiment kind -> its planner, and the counter of its units.
PLANNERS: dict[str, Planner] = {}
UNIT_COUNTS: dict[str, UnitCounter] = {}


def register_planner(kind: str, count: UnitCounter | None = None) -> Callable[[Planner], Planner]:
    """Decorator registering the unit planner of an experiment kind and the counter of its units (without one, a plan
    is bounded only once it is built)."""

    def decorate(function: Planner) -> Planner:
        PLANNERS[kind] = function
        if count is not None:
            UNIT_COUNTS[kind] = count
        return function

    return decorate


# --------------------------------------------------------------------------------------------------------------
# The run directory, as executors and sections see it
# --------------------------------------------------------------------------------------------------------------

def unit_dir(root: Path, unit: Unit | str) -> Path:
    """The directory of `unit` (a Unit or its id) in the run directory `root`."""
    return Path(root) / (unit if isinstance(unit, str) else unit.id)


def file_digest(path: Path) -> dict[str, Any]:
    """``{"size", "sha256"}`` of a file: what completion markers record of the outputs and inputs of a unit."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return {"size": path.stat().st_size, "sha256": digest.hexdigest()}


def single_threaded_torch() -> None:
    """One torch thread: units run side by side, one per core."""
    import torch

    torch.set_num_threads(1)


# --------------------------------------------------------------------------------------------------------------
# Executors: what a unit kind does
# --------------------------------------------------------------------------------------------------------------

@dataclass
class ExecutorResult:
    """What an executor wrote: its output files (relative to the unit directory), the digests of the inputs it read
    (``{"<unit id>/<file>": digest}``) and extra fields for the completion marker."""

    outputs: list[str]
    inputs: dict[str, dict[str, Any]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


Executor = Callable[[Path, Unit, Path], ExecutorResult]  # (run root, unit, unit directory) -> result
#: A running unit's progress, read by the runner for its per-unit bars (removed when the unit is done).
PROGRESS_FILE = "progress.json"


class UnitProgress:
    """How far a running unit is, in its own `unit` (steps, episodes, replays), written to ``progress.json`` in
    its directory: the worker is another process (or a Ray node sharing the directory), so a small file is the
    channel. Written atomically, at most every `every` seconds and once more when the work is complete."""

    def __init__(self, directory: Path, total: int, unit: str, every: float = 1.0):
        self.path, self.total, self.unit, self.every = Path(directory) / PROGRESS_FILE, int(total), unit, every
        self.done, self._written = 0, -math.inf

    def update(self, done: int, total: int | None = None) -> None:
        """Set the work done (and, when it became known, the total)."""
        self.done, self.total = int(done), int(total) if total is not None else self.total
        now = time.monotonic()
        if now - self._written >= self.every or self.done >= self.total:
            self._written = now
            write_text_atomic(self.path, json.dumps({"done": self.done, "total": self.total, "unit": self.unit}))

    def advance(self, count: int = 1) -> None:
        self.update(self.done + count)


def read_progress(directory: Path) -> tuple[int, int, str] | None:
    """``(done, total, unit)`` of a running unit's ``progress.json``; None when there is none or it is not sound
    (the display then shows a spinner; a unit's correctness never depends on this file)."""
    try:
        data = read_json(Path(directory) / PROGRESS_FILE, max_bytes=4096, follow_links=False)
        done, total, unit = data["done"], data["total"], str(data["unit"])[:20]
    except Exception:  # absent, half-read, a link, a wrong shape: no progress to show
        return None
    if not (isinstance(done, int) and isinstance(total, int) and 0 <= done <= total and total > 0):
        return None
    return done, total, unit
#: unit kind -> function doing the unit's work in its (prepared) directory.
EXECUTORS: dict[str, Executor] = {}
#: unit kind -> function(unit directory) telling whether a partial unit may be continued (else it is wiped).
RESUMABLE: dict[str, Callable[[Path], bool]] = {}


def register_executor(kind: str, resumable: Callable[[Path], bool] | None = None) -> Callable[[Executor], Executor]:
    """Decorator making a function the executor of unit `kind`; `resumable(unit directory)` says whether a unit
    left half-done may be continued (without it, such a unit is wiped and redone)."""

    def decorate(function: Executor) -> Executor:
        EXECUTORS[kind] = function
        if resumable is not None:
            RESUMABLE[kind] = resumable
        return function

    return decorate


# --------------------------------------------------------------------------------------------------------------
# Report sections: what a report shows per experiment kind
# --------------------------------------------------------------------------------------------------------------

@dataclass
class ReportContext:
    """What a section sees: the run directory, its resolved experiment, its units and which of them are done."""

    results_dir: Path
    out_dir: Path
    experiment: dict[str, Any]
    units: list[Unit]
    states: Mapping[str, str]
    _cache: dict[str, Any] = field(default_factory=dict)

    def done(self, kind: str | None = None) -> list[Unit]:
        return [u for u in self.units if self.states[u.id] == "done" and (kind is None or u.kind == kind)]

    def missing(self, kind: str | None = None) -> list[Unit]:
        return [u for u in self.units if self.states[u.id] != "done" and (kind is None or u.kind == kind)]

    def cached(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()``, run once per report: sections that read the same records share them under `key`."""
        if key not in self._cache:
            self._cache[key] = compute()
        return self._cache[key]

    def episode_records(self) -> pd.DataFrame:
        """All finished evaluation units' per-episode records (with train_scenario, algo, train_seed, eval_scenario)."""
        if "episodes" not in self._cache:
            frames = [read_table(unit_dir(self.results_dir, u) / "episodes.parquet") for u in self.done("eval")]
            self._cache["episodes"] = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(
                columns=["train_scenario", "algo", "train_seed", "eval_scenario", "episode", "outcome", "return",
                         "intrusion_events"])
        return self._cache["episodes"]

    def training_curves(self) -> pd.DataFrame:
        """All finished training units' curve.csv rows with train_scenario, algo and seed columns."""
        if "curves" not in self._cache:
            frames = []
            for unit in self.done("train"):
                curve = read_table(unit_dir(self.results_dir, unit) / "curve.csv")
                curve.insert(0, "seed", unit.params["seed"])
                curve.insert(0, "algo", unit.params["algo"])
                curve.insert(0, "train_scenario", unit.params["train_scenario"])
                frames.append(curve)
            self._cache["curves"] = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(
                columns=["train_scenario", "algo", "seed", "timesteps", "ep_rew_mean"])
        return self._cache["curves"]


Section = Callable[[ReportContext], str]
#: experiment kind -> [(section name, function writing its files and returning its Markdown)], in page order.
SECTIONS: dict[str, list[tuple[str, Section]]] = {}


def register_section(kind: str, name: str) -> Callable[[Section], Section]:
    """Decorator adding a report section for experiments of `kind` (sections appear in registration order)."""

    def decorate(function: Section) -> Section:
        sections = SECTIONS.setdefault(kind, [])
        sections[:] = [(n, f) for n, f in sections if n != name] + [(name, function)]
        return function

    return decorate
