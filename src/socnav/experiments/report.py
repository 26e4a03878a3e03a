"""Reports of finished (or partly finished) experiments: tables as Markdown + CSV, figures as PNG + SVG, and one
Markdown page, ``report.md``, that holds them.

The page is assembled from *sections* registered per experiment kind (``register_section(kind, name)``,
:mod:`socnav.experiments.registry`): each section gets a :class:`~socnav.experiments.registry.ReportContext` (the run
directory, its resolved experiment, the finished units and their records), writes its own files into the report
directory and returns its Markdown. The paper's kinds and their pages are in `socnav.paper`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from socnav.experiments.moved import moved_attribute
from socnav.experiments.registry import SECTIONS, ReportContext, experiment_kinds, load_kind
from socnav.experiments.run_directory import read_plan, unit_states
from socnav.io import write_text_atomic

__all__ = ["build_report"]


def build_report(results_dir: str | Path, out_dir: str | Path | None = None) -> Path:
    """Write every section of the run directory's experiment kind and ``report.md``; returns report.md's path."""
    results_dir = Path(results_dir)
    experiment, units = read_plan(results_dir)
    out_dir = Path(out_dir) if out_dir is not None else results_dir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    context = ReportContext(results_dir, out_dir, experiment, units, unit_states(results_dir, units))
    kind = experiment.get("kind", "table1")
    if kind in experiment_kinds():
        load_kind(kind)
    if kind not in SECTIONS:
        raise ValueError(f"no report sections for experiment kind {kind!r}; known kinds: "
                         f"{', '.join(experiment_kinds())}")
    parts = [_header(context)]
    for _, section in SECTIONS[kind]:
        parts.append(section(context).strip())
    return write_text_atomic(out_dir / "report.md", "\n\n".join(parts) + "\n")


def _header(context: ReportContext) -> str:
    experiment = context.experiment
    budget = experiment.get("budget") or "as written"
    lines = [f"# Experiment `{experiment['name']}` (budget: {budget})", ""]
    if experiment.get("description"):
        lines += [" ".join(str(experiment["description"]).split()), ""]
    done, total = len(context.done()), len(context.units)
    lines.append(f"Units finished: {done} of {total}.")
    missing = context.missing()
    if missing:
        lines.append(f"**Partial results**: {len(missing)} unit(s) not finished (numbers below leave them out):")
        lines += [f"- `{u.id}` ({context.states[u.id]})" for u in missing[:20]]
        if len(missing) > 20:
            lines.append(f"- ... and {len(missing) - 20} more")
    return "\n".join(lines)


def __getattr__(name: str) -> Any:
    # names that moved to socnav.paper: still importable from here, with a DeprecationWarning
    return moved_attribute('socnav.experiments.report', name)
