"""Experiment kinds plug into the engine by name: socnav's own (the paper's, in socnav.paper) register a planner, the
executors of every unit they plan and a report page; another package's kind, found through its entry point, runs and
reports like them; the paper's modules still import by their names from before they moved, with a warning."""

from __future__ import annotations

import importlib
import importlib.metadata
import sys
import warnings
from pathlib import Path

import pytest

from socnav.experiments import registry
from socnav.experiments.report import build_report
from socnav.experiments.runner import run_experiment
from socnav.experiments.spec import ExperimentError, load_experiment, parse_experiment, plan_units

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "experiments"


@pytest.mark.parametrize(("config", "kind"), [("table1", "table1"), ("table2", "uncertainty"),
                                              ("table3", "uncertainty"), ("safety_benchmark", "safety_benchmark")])
def test_every_shipped_kind_registers_its_planner_executors_and_page(config, kind):
    experiment = load_experiment(CONFIGS / f"{config}.yaml", "check")
    assert experiment.kind == kind and registry.KIND_MODULES[kind].startswith("socnav.paper.")
    units = plan_units(experiment)  # loads the kind by its name
    assert kind in registry.PLANNERS and kind in registry.UNIT_COUNTS
    assert {unit.kind for unit in units} <= set(registry.EXECUTORS)
    assert registry.SECTIONS[kind], f"kind {kind} has no report section"


def test_an_unknown_kind_names_the_known_ones():
    data = {"name": "x", "kind": "table7", "grid": {"algorithms": ["ppo"], "train_scenarios": ["random"],
                                                     "seeds": [0], "timesteps": 100},
            "evaluation": {"scenarios": ["random"], "episodes": 1}}
    with pytest.raises(ExperimentError, match="kind: unknown experiment kind 'table7'; allowed: table1, "
                                              "uncertainty, safety_benchmark"):
        parse_experiment(data, "test")
    with pytest.raises(ValueError, match="unknown experiment kind 'table7'; known kinds: table1"):
        registry.load_kind("table7")


@pytest.fixture
def plugin_entry_point(monkeypatch):
    """``install(kind, module)``: an installed package's entry point of the group, for this test only."""
    real = importlib.metadata.entry_points
    entries: list[importlib.metadata.EntryPoint] = []
    monkeypatch.setattr(importlib.metadata, "entry_points",
                        lambda **kw: entries if kw.get("group") == registry.ENTRY_POINT_GROUP else real(**kw))

    def install(kind: str, module: str) -> None:
        entries.append(importlib.metadata.EntryPoint(kind, module, registry.ENTRY_POINT_GROUP))
        registry._kind_modules.cache_clear()

    yield install
    registry._kind_modules.cache_clear()


def _experiment(name: str, kind: str, seeds: list[int]):
    return parse_experiment({
        "name": name, "kind": kind,
        "grid": {"algorithms": ["ppo"], "train_scenarios": ["random"], "seeds": seeds, "timesteps": 100},
        "evaluation": {"scenarios": ["random"], "episodes": 1}}, "test")


PLUGIN = '''
from socnav.experiments.registry import ExecutorResult, register_executor, register_planner, register_section
from socnav.experiments.units import Unit


def plan(experiment):
    return [Unit(f"greet/seed{seed}", "greet", {"seed": seed}) for seed in experiment.grid.seeds]


@register_executor("greet")
def greet(root, unit, directory):
    (directory / "greeting.txt").write_text(f"hello from seed {unit.params['seed']}")
    return ExecutorResult(["greeting.txt"])


register_planner("greetings", count=lambda experiment: len(experiment.grid.seeds))(plan)
register_section("greetings", "greetings")(lambda context: f"{len(context.done('greet'))} greetings")
'''


def test_a_plugin_kind_found_through_its_entry_point_runs_and_reports(tmp_path, monkeypatch, plugin_entry_point):
    (tmp_path / "greetings_kind.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    plugin_entry_point("greetings", "greetings_kind")
    try:
        assert registry.experiment_kinds() == [*registry.KIND_MODULES, "greetings"]
        experiment = _experiment("hello", "greetings", [0, 1])
        summary = run_experiment(experiment, tmp_path / "run", workers=0)
        assert summary.ok and summary.count("done") == 2
        assert (tmp_path / "run" / "greet" / "seed1" / "greeting.txt").read_text() == "hello from seed 1"
        assert "2 greetings" in build_report(tmp_path / "run").read_text()
    finally:
        sys.modules.pop("greetings_kind", None)
        for table in (registry.PLANNERS, registry.UNIT_COUNTS, registry.SECTIONS):
            table.pop("greetings", None)
        registry.EXECUTORS.pop("greet", None)


def test_the_moved_modules_and_names_import_from_their_old_places_with_a_warning():
    with pytest.warns(DeprecationWarning, match="socnav.experiments.uncertainty_table3 moved to "
                                                "socnav.paper.uncertainty.table3"):
        old = importlib.import_module("socnav.experiments.uncertainty_table3")
    assert old is importlib.import_module("socnav.paper.uncertainty.table3")
    with pytest.warns(DeprecationWarning, match="socnav.experiments.report.table1_frame moved to "
                                                "socnav.paper.table1.tables.table1_frame"):
        from socnav.experiments.report import table1_frame
    from socnav.paper.table1.tables import table1_frame as moved
    assert table1_frame is moved
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # what never moved imports without a warning
        from socnav.experiments.spec import Unit  # noqa: F401
    with pytest.raises(ImportError, match="cannot import name 'no_such_name'"):
        from socnav.experiments.report import no_such_name  # noqa: F401
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("socnav.experiments.uncertainty_nothing")


def test_a_plugin_kind_that_cannot_be_imported_is_one_line_naming_it(plugin_entry_point):
    plugin_entry_point("broken", "no_such_plugin_module")
    with pytest.raises(ExperimentError, match="experiment 'b': experiment kind 'broken': its module "
                                              "no_such_plugin_module cannot be imported"):
        plan_units(_experiment("b", "broken", [0]))


def test_a_kind_without_a_unit_counter_is_bounded_once_planned(monkeypatch):
    import socnav.experiments.spec as spec

    monkeypatch.setitem(registry.PLANNERS, "uncounted", lambda experiment: [
        registry.Unit(f"u/{index}", "greet", {}) for index in range(3)])
    experiment = _experiment("u", "uncounted", [0])
    assert spec.planned_unit_count(experiment) is None and len(plan_units(experiment)) == 3
    monkeypatch.setattr(spec, "MAX_UNITS", 2)
    with pytest.raises(ExperimentError, match="the plan has 3 units, above the bound of 2"):
        plan_units(experiment)


def test_a_broken_plugin_does_not_stop_the_other_kinds_in_a_worker(tmp_path, plugin_entry_point):
    from socnav.experiments.execution import execute_unit

    plugin_entry_point("broken", "no_such_plugin_module")
    problems = registry.load_kinds()  # what a fresh worker does: every kind that loads is there
    assert problems == ["experiment kind 'broken': its module no_such_plugin_module cannot be imported "
                        "(No module named 'no_such_plugin_module')"]
    assert {"train", "eval", "calibrate", "safety_benchmark"} <= set(registry.EXECUTORS)
    result = execute_unit(registry.Unit("orphan/a", "orphan", {}).to_json(), str(tmp_path))
    assert result["status"] == "failed" and "no executor for unit kind 'orphan'" in result["error"]
    assert "no_such_plugin_module cannot be imported" in result["error"]
