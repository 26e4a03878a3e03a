"""Experiments: YAML grids of training + evaluation units, run locally or on Ray, resumable, and reported as the
paper's tables and figures. `socnav run`, `socnav report`, `socnav tune` are the command-line front ends.

    from socnav.experiments import load_experiment, run_experiment, build_report
    experiment = load_experiment("configs/experiments/table1.yaml", budget="quick")
    summary = run_experiment(experiment, "runs/table1-quick")
    build_report("runs/table1-quick")
"""

from __future__ import annotations

from typing import Any

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
