"""The experiment engine: YAML experiment files expanded into units of work, run locally or on Ray, resumable, and
reported as one page per run. `socnav run`, `socnav report`, `socnav tune` are its command-line front ends.

    from socnav.experiments import load_experiment, run_experiment, build_report
    experiment = load_experiment("configs/experiments/table1.yaml", budget="quick")
    summary = run_experiment(experiment, "runs/table1-quick")
    build_report("runs/table1-quick")

What an experiment *kind* plans, runs and reports -- the paper's Tables 1-3 and the safety benchmark -- is in
`socnav.paper`; the engine finds a kind by its name (`socnav.experiments.registry`).
"""

from __future__ import annotations

from typing import Any

from socnav.experiments.moved import install_moved_modules

__all__ = ["ExperimentError", "build_report", "load_experiment", "plan_units", "run_experiment"]


def __getattr__(name: str) -> Any:
    # Loaded on first use: the spec validates algorithm names against socnav.rl (torch), the report needs matplotlib.
    if name in ("ExperimentError", "load_experiment", "plan_units"):
        from socnav.experiments import spec

        return getattr(spec, name)
    if name == "run_experiment":
        from socnav.experiments.runner import run_experiment

        return run_experiment
    if name == "build_report":
        from socnav.experiments.report import build_report

        return build_report
    raise AttributeError(f"module 'socnav.experiments' has no attribute {name!r}")


install_moved_modules()  # the paper's modules that moved to socnav.paper still import by their old names
