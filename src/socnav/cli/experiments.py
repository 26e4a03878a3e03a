"""`socnav run`, `socnav report` and `socnav tune`: added to the main `socnav` app by ``register(app)``.

Heavy modules (torch, ray, optuna, matplotlib) load inside the commands, so `socnav --help` stays fast.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from socnav._console import console, fail
from socnav.cli.options import (
    algo_option,
    config_option,
    eval_episodes_option,
    eval_every_option,
    force_option,
    humans_option,
    n_envs_option,
    n_humans_option,
    scenario_option,
    seed_option,
    timesteps_option,
)
from socnav.extras import install_hint

__all__ = ["register"]

if TYPE_CHECKING:
    from socnav.experiments.runner import Reporter
else:  # the runner (pandas, pyarrow) loads inside `socnav run`: the progress display is a Reporter by its methods
    Reporter = object


class _ProgressReporter(Reporter):
    """Rich progress: one bar for the sweep (units done / running / failed) and a bar per running unit, fed by the
    unit's own progress file (a spinner until its first report, e.g. while a model loads)."""

    def __init__(self) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        self.progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn(), TextColumn("{task.fields[counts]}"), TimeElapsedColumn(),
                                 console=console, transient=False)
        self.sweep: Any = None
        self.tasks: dict[str, Any] = {}
        self.counts = {"done": 0, "skipped": 0, "failed": 0}

    def _counts(self) -> str:
        return (f"[green]done {self.counts['done']}[/] · running {len(self.tasks)} · "
                f"[red]failed {self.counts['failed']}[/] · skipped {self.counts['skipped']}")

    def start(self, total: int, already_done: int, redo: dict[str, int]) -> None:
        self.counts["skipped"] = already_done
        if already_done:
            console.print(f"{already_done} of {total} units already done: skipped")
        notes = {"partial": "half-done (resumed or redone)", "corrupt": "corrupt (redone)",
                 "stale": "stale: parameters or inputs changed (redone)"}
        for state, count in redo.items():
            if state in notes:
                console.print(f"{count} unit(s) {notes[state]}")
        self.sweep = self.progress.add_task("units", total=total, completed=already_done, counts=self._counts())
        self.progress.start()

    def unit_started(self, unit: Any) -> None:
        self.tasks[unit.id] = self.progress.add_task(f"  [cyan]{unit.id}[/]", total=None, counts="")
        self.progress.update(self.sweep, counts=self._counts())

    def unit_progress(self, unit: Any, done: int, total: int, what: str) -> None:
        task = self.tasks.get(unit.id)
        if task is not None:
            self.progress.update(task, completed=done, total=total, counts=what)

    def unit_finished(self, unit: Any, outcome: Any) -> None:
        task = self.tasks.pop(unit.id, None)
        if task is not None:
            self.progress.remove_task(task)
        if outcome.status in ("failed", "blocked"):
            self.counts["failed"] += 1
            where = f" (see {unit.id}/error.txt)" if outcome.status == "failed" else ""
            self.progress.console.print(f"[bold red]✗ {outcome.status}[/] {unit.id}: {outcome.error}{where}",
                                        highlight=False)
        else:
            self.counts["done" if outcome.status == "done" else "skipped"] += 1
            self.progress.console.print(f"[green]✓[/] {unit.id} ({outcome.wall_time_s:.0f} s)", highlight=False)
        self.progress.update(self.sweep, advance=1, counts=self._counts())

    def stop(self) -> None:
        self.progress.stop()


def run(
    experiment: Path = typer.Argument(..., help="experiment YAML (e.g. configs/experiments/table1.yaml)"),
    budget: str | None = typer.Option(None, help="named budget of the experiment, e.g. quick | paper "
                                                    "(default: the grid as written)"),
    backend: str = typer.Option("local", help="local (process pool on this machine) | ray (Ray cluster)"),
    address: str | None = typer.Option(None, help="Ray cluster address (e.g. auto or ray://head:10001); "
                                                     "default: start a local Ray"),
    workers: int | None = typer.Option(None, min=0, help="units at a time (local default: CPU count; "
                                                            "0 runs in this process; ray default: cluster CPUs)"),
    retries: int = typer.Option(1, min=0, help="retries of a unit whose worker died (Ray: max_retries)"),
    out: Path | None = typer.Option(None, help="run directory (default runs/<name>-<budget>, or runs/<name> "
                                                  "without --budget)"),
    dry_run: bool = typer.Option(False, "--dry-run", help="validate and list the units and their state; run nothing"),
) -> None:
    """Run an experiment: train and evaluate every unit not yet done; resumable, failures reported per unit."""
    from socnav.experiments.runner import RunnerError, check_run_dir, run_experiment, unit_states
    from socnav.experiments.spec import ExperimentError, load_experiment, plan_units

    if backend not in ("local", "ray"):
        fail(f"--backend {backend!r} is not known; allowed: local, ray")
    if address is not None and backend != "ray":
        fail("--address is for --backend ray")
    try:
        resolved = load_experiment(experiment, budget)
        units = plan_units(resolved)
    except ExperimentError as exc:
        fail(str(exc))
        return
    root = out or Path("runs") / (resolved.name + (f"-{resolved.budget}" if resolved.budget else ""))
    n_train = sum(unit.kind == "train" for unit in units)
    console.print(f"experiment [bold]{resolved.name}[/] (budget {resolved.budget or 'as written'}): {len(units)} "
                  f"units ({n_train} trainings of {resolved.grid.timesteps:,} steps) -> {root}", highlight=False)
    if dry_run:
        try:  # what the real run would refuse, refused here too (nothing is written)
            check_run_dir(root, resolved)
        except RunnerError as exc:
            fail(str(exc))
        states = unit_states(root, units) if root.exists() else {u.id: "pending" for u in units}
        for unit in units:
            console.print(f"  {states[unit.id]:8s} {unit.id}", highlight=False)
        return
    if backend == "ray":
        try:
            import ray  # noqa: F401  (takes seconds: a Ctrl-C meanwhile is an interruption, not a traceback)
        except ImportError:
            fail(f"--backend ray needs Ray: {install_hint('ray')}")
        except KeyboardInterrupt:
            console.print("[yellow]interrupted[/] before any unit started")
            raise typer.Exit(code=130) from None
    reporter = _ProgressReporter()
    started = time.perf_counter()
    try:
        summary = run_experiment(resolved, root, backend="ray" if backend == "ray" else "local",  # checked above
                                 workers=workers, address=address, retries=retries, source=experiment,
                                 reporter=reporter)
    except RunnerError as exc:
        reporter.stop()
        fail(str(exc))
        return
    except KeyboardInterrupt:
        reporter.stop()
        console.print("[yellow]interrupted[/]: finished units are kept; run the same command again to continue")
        raise typer.Exit(code=130) from None
    reporter.stop()
    elapsed = time.perf_counter() - started
    console.print(f"{summary.count('done')} done, {summary.count('skipped')} already done, "
                  f"{len(summary.failed)} failed in {elapsed:.0f} s; results in {root}", highlight=False)
    if summary.failed:
        for outcome in summary.failed:
            console.print(f"  [red]{outcome.status}[/] {outcome.id}: {outcome.error}", highlight=False)
        console.print("run the same command again to retry the failed units (finished ones are skipped)")
        raise typer.Exit(code=1)
    console.print(f"report: socnav report {root}", highlight=False)


def report(
    results_dir: Path = typer.Argument(..., help="run directory written by `socnav run`"),
    out: Path | None = typer.Option(None, help="report directory (default RESULTS_DIR/report)"),
    force: bool = force_option("an earlier report in the --out directory"),
) -> None:
    """Tables (Markdown + CSV), figures (PNG + SVG) and report.md from an experiment's run directory."""
    from socnav.experiments.report import build_report
    from socnav.experiments.runner import RunnerError
    from socnav.io import OutputPathError, check_output_file

    if not results_dir.is_dir():
        fail(f"no such run directory: {results_dir}")
    target = results_dir / "report" if out is None else out
    if target.exists() and not target.is_dir():
        fail(f"--out {target} is an existing file; name a directory for the report")
    if target.is_dir():  # an earlier report (report.md, its tables and figures) is replaced only when told
        try:
            check_output_file(target / "report.md", what="--out", force=force)
        except OutputPathError as exc:
            fail(str(exc))
    try:
        page = build_report(results_dir, out)
    except (RunnerError, ValueError) as exc:
        fail(str(exc))
        return
    except OSError as exc:  # --out under a file, unwritable, a full disk: one line naming the path
        where = f" {exc.filename}" if exc.filename else ""
        fail(f"cannot write the report{where}: {exc.strerror or exc} (choose another --out)")
        return
    console.print(f"report: {page}", highlight=False)
    for name in sorted(p.name for p in page.parent.iterdir() if p.is_file() and p.name != page.name):
        console.print(f"  {page.parent / name}", highlight=False)


def tune(
    algo: str = algo_option(...),
    scenario: str = scenario_option(..., help="training scenario"),
    trials: int = typer.Option(..., min=1, max=100_000, help="trials to run (added to the study if it exists)"),
    storage: str = typer.Option("sqlite:///runs/tune.db", help="Optuna storage URL (any Optuna RDB URL)"),
    timesteps: int = timesteps_option(100_000, help="training timesteps per trial"),
    study_name: str | None = typer.Option(None, help="study name (default <algo>_<scenario>)"),
    n_envs: int = n_envs_option(16, help="training environments per trial"),
    eval_every: int | None = eval_every_option("timesteps between validations reported to the pruner (default a "
                                               "fifth of the trial)"),
    eval_episodes: int = eval_episodes_option(20),
    metric: str = typer.Option("return_mean", help="objective: return_mean | goal_pct | collision_pct"),
    # A seed as Optuna's sampler takes it, unbounded below.
    seed: int = seed_option("training seed of every trial (and the sampler's seed)", least=None),
    n_humans: int | None = n_humans_option(),
    config: Path | None = config_option(),
    out: Path | None = typer.Option(None, help="trial run directories (default runs/tune/<study>)"),
    timeout: float | None = typer.Option(None, min=1, help="stop starting trials after this many seconds"),
    write_preset: Path | None = typer.Option(None, "--write-preset", help="write the best values as a "
                                                                            "preset YAML here"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --write-preset file"),
) -> None:
    """Optuna search of PPO hyperparameters with median pruning; prints the best values, writes a preset YAML."""
    from rich.table import Table

    from socnav.config import ConfigError, load_config
    from socnav.rl.presets import ALGOS

    if algo not in ALGOS:
        fail(f"--algo {algo!r} is not known; allowed: {', '.join(ALGOS)}")
    from socnav.cli.workflows.tune import METRICS
    from socnav.cli.workflows.tune import tune as run_tune
    from socnav.cli.workflows.tune import write_preset as save_preset

    if metric not in METRICS:
        fail(f"--metric {metric!r} is not known; allowed: {', '.join(METRICS)}")
    if write_preset is not None:  # checked now, not after hours of trials
        from socnav.io import OutputPathError, check_output_file

        try:
            check_output_file(write_preset, what="--write-preset", force=force)
        except OutputPathError as exc:
            fail(str(exc))
    overrides: dict[str, Any] = {"scenario": scenario}
    if n_humans is not None:
        overrides["n_humans"] = n_humans
    if humans is not None:
        from socnav.config import unknown_name_message
        from socnav.sim.humans import human_model_names

        if humans not in human_model_names():
            fail(f"--humans: {unknown_name_message('human model', humans, human_model_names())}")
        overrides["humans"] = {"model": humans, "mix": None}
    try:
        env_config = load_config(config, **overrides)
    except ConfigError as exc:
        fail(str(exc))
        return
    try:
        import optuna
    except ImportError:
        fail(f"socnav tune needs Optuna: {install_hint('tune')}")
        return
    optuna.logging.set_verbosity(optuna.logging.WARNING)

    def on_trial(study: Any, trial: Any) -> None:
        value = "-" if trial.value is None else f"{trial.value:.3f}"
        console.print(f"trial {trial.number}: {trial.state.name.lower()} {metric}={value} {trial.params}",
                      highlight=False)

    console.print(f"tuning {algo} on {env_config.scenario}: {trials} trial(s) of {timesteps:,} steps, "
                  f"storage {storage}", highlight=False)
    try:
        result = run_tune(env_config, algo, trials, timesteps=timesteps, storage=storage, study_name=study_name,
                          out_dir=out, n_envs=n_envs, eval_every=eval_every, eval_episodes=eval_episodes,
                          seed=seed, metric=metric, timeout=timeout, on_trial=on_trial)
    except (RuntimeError, ValueError) as exc:
        fail(str(exc), code=1)
        return
    table = Table(title=f"best of study {result.study_name!r}: trial #{result.best_trial}, "
                        f"{metric} = {result.best_value:.4f}")
    table.add_column("hyperparameter")
    table.add_column("value", justify="right")
    for key, value in result.best_params.items():
        table.add_row(key, f"{value:.3g}" if isinstance(value, float) else str(value))
    console.print(table)
    console.print(f"trials: {result.counts}", highlight=False)
    if write_preset is not None:
        path = save_preset(write_preset, result, algo, env_config.scenario, timesteps)
        console.print(f"preset: {path} (socnav train --algo {algo} --algo-config {path})", highlight=False)


def register(app: typer.Typer) -> None:
    """Add the experiment commands (run, report, tune) to the `socnav` app."""
    app.command("run")(run)
    app.command("report")(report)
    app.command("tune")(tune)
