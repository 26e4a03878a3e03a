"""Where the paper's experiments went when they left the engine for `socnav.paper` (during 0.1.0's development):
the old module and attribute names still import, with a DeprecationWarning naming the new place. socnav uses none.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from types import ModuleType
from typing import Any

__all__ = ["MOVED_MODULES", "MOVED_NAMES", "install_moved_modules", "moved_attribute"]

#: Old module of socnav.experiments -> the module it became.
MOVED_MODULES: dict[str, str] = {
    "socnav.experiments.labels": "socnav.paper.labels",
    "socnav.experiments.paper_tables": "socnav.paper.published",
    "socnav.experiments.safety_benchmark": "socnav.paper.safety_benchmark.benchmark",
    "socnav.experiments.safety_benchmark_units": "socnav.paper.safety_benchmark.units",
    **{f"socnav.experiments.uncertainty_{name}": f"socnav.paper.uncertainty.{name}" for name in (
        "ablation", "figures", "information", "records", "report", "table2", "table2_claims", "table3", "thresholds",
        "tradeoff", "units")},
}


def _names(module: str, names: str) -> dict[str, str]:
    return dict.fromkeys(names.split(), module)


#: Engine module -> {name it no longer defines: the module that does}.
MOVED_NAMES: dict[str, dict[str, str]] = {
    "socnav.experiments.report": {
        **_names("socnav.paper.table1.tables", "ID_COLUMNS TABLE1_COLUMNS TABLE1_SEED_METRICS EXTRA_METRICS "
                 "TABLE1_METRICS table1_seed_frame table1_frame table1_markdown table1_section"),
        **_names("socnav.paper.table1.intervals", "CI_MARKDOWN_METRICS AGGREGATE_SCORE REFERENCE_ALGO "
                 "FAMILY_CONFIDENCE CI_COLUMNS COMPARISON_COLUMNS Cell table1_ci_frame table1_ci_markdown "
                 "policy_strata paired_policy_strata aggregate_frame comparison_frame plot_aggregate "
                 "table1_ci_section"),
        **_names("socnav.paper.table1.curves", "CURVE_MARKERS CURVE_MARKED_POINTS training_curve_frame "
                 "training_curves_figure plot_training_curves training_curves_section"),
        **_names("socnav.paper.table1.claims", "CURVE_VALUE CONVERGENCE_FRACTION FINAL_SHARE TRAINING_RUN_COLUMNS "
                 "CLAIM_COLUMNS FAST_SCENARIO training_run_frame claims_frame claims_section"),
        **_names("socnav.paper.table1.comparison", "budget_note paper_comparison_section"),
    },
    "socnav.experiments.spec": {
        **_names("socnav.paper.uncertainty.plan", "NO_ESTIMATOR calibration_unit_id tradeoff_thresholds_file "
                 "plan_uncertainty"),
        **_names("socnav.paper.train_eval", "train_unit_id eval_unit_id"),
        **_names("socnav.paper.table1.plan", "plan_train_eval"),
        **_names("socnav.paper.safety_benchmark.plan", "plan_safety_benchmark"),
        **_names("socnav.experiments.units", "SPEC_VERSION"),
    },
}


def _warn(old: str, new: str, stacklevel: int) -> None:
    warnings.warn(f"{old} moved to {new}; import it from there (the old name will be removed)", DeprecationWarning,
                  stacklevel=stacklevel + 1)


def moved_attribute(module: str, name: str) -> Any:
    """What a module's ``__getattr__`` returns for a `name` it no longer defines (with a DeprecationWarning).

    :raises AttributeError: `name` never was in `module`.
    """
    target = MOVED_NAMES.get(module, {}).get(name)
    if target is None:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    _warn(f"{module}.{name}", f"{target}.{name}", stacklevel=3)  # the importing line
    return getattr(importlib.import_module(target), name)


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old module name of `MOVED_MODULES` (after every other finder failed) as its new module."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        return importlib.util.spec_from_loader(fullname, self) if fullname in MOVED_MODULES else None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        _warn(spec.name, MOVED_MODULES[spec.name], stacklevel=2)  # importlib's frames are skipped
        return importlib.import_module(MOVED_MODULES[spec.name])

    def exec_module(self, module: ModuleType) -> None:
        """The new module is already executed."""


def install_moved_modules() -> None:
    """Let the old module names import (last on `sys.meta_path`: only names nothing else finds)."""
    if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.append(_MovedModuleFinder())
