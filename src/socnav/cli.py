"""The `socnav` command line: train, evaluate, animate, calibrate, convert, run experiments, report, tune, demo.

Every command validates its options up front and reports bad input as one clear line, never a traceback.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from socnav._console import console, fail
from socnav.config import ConfigError, EnvConfig, describe_world, load_config
from socnav.experiments.cli import register as add_experiment_commands
from socnav.experiments.cli_options import (
    ACTING_MODEL_HELP,
    SCENARIOS,
    SINGLE_AGENT_MAX_HUMANS_HELP,
    SINGLE_AGENT_N_HUMANS_HELP,
    SINGLE_AGENT_SCENARIO_HELP,
    algo_option,
    config_option,
    episodes_option,
    estimator_option,
    eval_episodes_option,
    eval_every_option,
    force_option,
    humans_option,
    max_humans_option,
    mc_samples_option,
    members_option,
    model_option,
    n_envs_option,
    n_humans_option,
    perturb_option,
    safety_option,
    scenario_option,
    seed_option,
    sensing_option,
    timesteps_option,
)
from socnav.sim.metrics import PV_PER

if TYPE_CHECKING:  # pandas, torch and SB3 load inside the commands: `socnav --help` stays fast
    import pandas as pd

    from socnav.envs.rollout import RolloutInterrupted
    from socnav.rl.training import RunInfo, TrainResult
    from socnav.safety import SafePolicy

# Plain click help: typer's rich help panels label every flag (and --help itself) with a `<bool>` type.
app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__.splitlines()[0], rich_markup_mode=None)


def _version(value: bool) -> None:
    if value:
        from socnav import __version__

        console.print(f"socnav {__version__}")
        raise typer.Exit()


def _deprecated_alias(old: str, new: str) -> Callable[[Any], Any]:
    """Callback of a hidden option kept under its old name: warns when it is used and passes its value on (the
    command takes it as the value of `new`)."""

    def warn(value: Any) -> Any:
        if value is not None:
            console.print(f"[yellow]warning:[/] {old} is deprecated: use {new}", highlight=False)
        return value

    return warn


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="print the version and exit"),
) -> None:
    """Uncertainty-aware social robot navigation: simulate, train, evaluate, calibrate, run experiments."""


def _check_n_envs(n_envs: int, env_config: EnvConfig) -> None:
    """Refuse --n-envs whose environments cannot fit in memory, before anything is built or written."""
    from socnav.envs.env import check_env_count

    try:
        check_env_count(n_envs, env_config, "--n-envs")
    except ConfigError as exc:
        fail(str(exc))


def _env_config(scenario: str | None, config_file: Path | None, n_humans: int | None,
                max_humans: int | None = None, base: Any = None, observes: int | None = None,
                humans: str | None = None) -> EnvConfig:
    """The env config of a command: `base` (a config file, or e.g. a model's stored config), then the options.

    :param observes: the max_humans of the model the command runs, if any: raising max_humans is then no way out
        (a model runs only with the observation size it was trained with), fewer humans are.
    :param humans: --humans, the human model (checked by `_check_human_model`).
    """
    import re

    overrides: dict[str, Any] = {}
    if scenario is not None:
        overrides["scenario"] = scenario
    if humans is not None:  # one model for every human: a mixed crowd of the base world is replaced, not kept
        overrides["humans"] = {"model": humans, "mix": None}
    if n_humans is not None:
        overrides["n_humans"] = n_humans
    if max_humans is not None:
        overrides["max_humans"] = max_humans
    try:
        return load_config(config_file if base is None else base, **overrides)
    except ConfigError as exc:
        message = str(exc)
        needed = re.search(r"raise max_humans to at least (\d+)", message)
        limit = EnvConfig.model_fields["max_humans"].metadata  # the field's bounds, e.g. Le(le=64)
        most = min((bound.le for bound in limit if getattr(bound, "le", None) is not None), default=None)
        if needed and observes is not None:
            message += (f"\n  the model observes at most {observes} humans (it was trained with max_humans="
                        f"{observes}): use --n-humans {observes} or fewer")
        elif needed and most is not None and int(needed.group(1)) > most:
            message += f"\n  at most {most} humans are supported (max_humans <= {most})"
        elif needed and max_humans is None:
            message += f"\n  from the command line: --max-humans {needed.group(1)}"
        fail(message)
        raise  # unreachable, keeps type checkers happy


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )


@contextmanager
def _progress_bar(label: str, total: int) -> Iterator[Callable[[int], None]]:
    """One progress bar of `total` episodes, shown while the block runs; yields its `advance(n)` (a library step's
    ``progress``, e.g. `socnav.experiments.demo.ProgressBar`)."""
    with _progress() as progress:
        task = progress.add_task(escape(label), total=total)
        yield lambda n: progress.advance(task, n)


def metrics_table(rows: list[tuple[str, dict[str, float]]], title: str) -> Table:
    """The paper's metrics as a rich table: Goal %, Collision %, Time-out %, PV per 200 episodes, navigation time
    (mean time to the goal of the successful episodes, CrowdNav's "nav time"), Return mean ± std, and the share of
    steps where the safety fallback acted when the rows have ``fallback_pct``."""
    import math

    table = Table(title=title, caption=f"PV: personal-space violations (intrusion events) per {PV_PER} episodes; "
                  "nav time of the episodes reaching the goal")
    fallback = any("fallback_pct" in m for _, m in rows)
    walls = any("collision_obstacle_pct" in m for _, m in rows)  # worlds with walls: wall collisions, apart
    columns = ["run", "episodes", "Goal %", "Col. %", "TO %", f"PV/{PV_PER} ep.", "nav time (s)", "Return"]
    if walls:
        columns.insert(4, "Wall %")
    for column in columns + (["fallback % steps"] if fallback else []):
        table.add_column(column, justify="right" if column != "run" else "left", no_wrap=column != "run")
    for name, m in rows:
        nav_time = m.get("time_to_goal_mean", float("nan"))
        cells = [escape(name), str(m["episodes"]), f"{m['goal_pct']:.1f}", f"{m['collision_pct']:.1f}",
                 f"{m['timeout_pct']:.1f}", f"{m['pv']:.0f}", "–" if math.isnan(nav_time) else f"{nav_time:.1f}",
                 f"{m['return_mean']:.2f} ± {m['return_std']:.2f}"]
        if walls:
            cells.insert(4, f"{m['collision_obstacle_pct']:.1f}" if "collision_obstacle_pct" in m else "–")
        if fallback:
            cells.append(f"{m['fallback_pct']:.1f}" if "fallback_pct" in m else "–")
        table.add_row(*cells)
    return table


def _evaluate(policy: Any, config: EnvConfig, episodes: int, seed: int, n_envs: int, label: str,
              deterministic: bool = True, observer: Any = None) -> pd.DataFrame:
    from socnav.envs.rollout import rollout_episodes

    with _progress_bar(label, episodes) as advance:
        return rollout_episodes(policy, config, episodes, seed=seed, n_envs=n_envs, deterministic=deterministic,
                                progress=advance, observer=observer)


def _yaml(option: str, text: str) -> Any:
    """A YAML value given on the command line, read with socnav's bounded loader; bad or oversized YAML (or an
    integer of thousands of digits) is a one-line error naming the option."""
    import yaml

    from socnav.config import safe_load_yaml, yaml_problem

    shown = repr(text if len(text) <= 60 else text[:57] + "...")
    try:
        return safe_load_yaml(text)
    except yaml.YAMLError as exc:
        fail(f"{option} {shown} {' '.join(yaml_problem(exc).split())}")
    except ValueError as exc:  # YAML parses it, Python will not build it, e.g. an integer of 5,000 digits
        import sys

        digits = sys.get_int_max_str_digits()
        reason = (f"an integer of more than {digits:,} digits" if "integer string conversion" in str(exc)
                  else " ".join(str(exc).split())[:200])
        fail(f"{option} {shown} is refused: {reason}")


def _algo_overrides(algo: str, algo_config: Path | None, settings: list[str]) -> dict[str, Any]:
    """Hyperparameter overrides from a YAML file, then `--set key=value` pairs (values parsed as YAML)."""
    from socnav.rl.presets import ALGOS, describe_override_error, resolve_config

    if algo not in ALGOS:
        fail(f"--algo {algo!r} is not known; allowed: {', '.join(ALGOS)}")
    overrides: dict[str, Any] = {}
    if algo_config is not None:
        from socnav.config import read_mapping_file

        try:
            overrides.update(read_mapping_file(algo_config, "--algo-config"))
        except ConfigError as exc:
            fail(str(exc))
    for setting in settings:
        key, sep, value = setting.partition("=")
        if not sep or not key:
            fail(f"--set expects key=value, got {setting!r}")
        overrides[key.strip()] = _yaml("--set", value)
    try:
        resolve_config(algo, overrides)
    except ValueError as exc:
        fail(" ".join(describe_override_error(algo, exc).split()))
    return overrides


@app.command()
def train(
    ctx: typer.Context,
    scenario: str | None = scenario_option(None, help=f"training scenario, one of: {SCENARIOS}"),
    algo: str = algo_option("odv-ppo-drop"),
    seed: int = seed_option("seed of the run (network init, dropout, training episodes)", most=2**28 - 1),
    timesteps: int = timesteps_option(200_000, help="total environment steps"),
    n_envs: int = n_envs_option(16),
    n_humans: int | None = n_humans_option(),
    max_humans: int | None = max_humans_option("observation rows (default 10; at least the most humans per "
                                                "episode)"),
    config: Path | None = config_option(),
    algo_config: Path | None = typer.Option(None, help="YAML of hyperparameter overrides for the preset"),
    settings: list[str] = typer.Option([], "--set", help="hyperparameter override key=value (repeatable)"),
    eval_every: int | None = eval_every_option("timesteps between evaluations/checkpoints"),
    eval_episodes: int = eval_episodes_option(50),
    out: Path | None = typer.Option(None, help="run directory (default runs/train/<scenario>_<algo>_seed<k>); "
                                                  "must be new or empty unless --force"),
    resume: Path | None = typer.Option(None, help="continue the run in this directory from its last checkpoint"),
    force: bool = typer.Option(False, "--force", help="move an existing --out directory aside to "
                                                      "OUT.old-<timestamp> (never deleted) and start afresh"),
    humans: str | None = humans_option(),
) -> None:
    """Train a policy: progress with live success rate, TensorBoard in OUT/tb, checkpoints, final OUT/model.zip."""
    if resume is not None:
        _refuse_options_resume_ignores(ctx)
        asked, env_config = _read_resumed_run(resume)
        algo, seed, timesteps, n_envs = asked.algo, asked.seed, asked.timesteps, asked.n_envs
        overrides, out = asked.overrides, resume
        start = _resume_start(resume, algo, timesteps)
        if start is None:  # the run is complete: reported, nothing to train
            return
    else:
        _check_human_model(humans)
        env_config = _env_config(scenario, config, n_humans, max_humans, humans=humans)
        overrides = _algo_overrides(algo, algo_config, settings)
        out = _new_run_directory(out or Path("runs") / "train" / f"{env_config.scenario}_{algo}_seed{seed}", force)
        start = 0
    _check_n_envs(n_envs, env_config)
    if start:
        console.print(f"resuming {algo} on {env_config.scenario} (seed {seed}) from step {start:,} of "
                      f"{timesteps:,} -> {out}", highlight=False)
    else:
        console.print(f"training {algo} on {env_config.scenario} (seed {seed}, {timesteps:,} steps) -> {out}",
                      highlight=False)
    _explain_rounding(timesteps, algo, overrides, n_envs)
    if resume is not None:
        result = _run_training(out, lambda: _resume_training(resume))
    else:
        result = _run_training(out, lambda: _start_training(env_config, algo, seed, timesteps, out, n_envs, overrides,
                                                            eval_every, eval_episodes))
    console.print(metrics_table([(f"{algo} (validation)", result.final_eval)],
                                f"{result.timesteps:,} steps in {result.wall_time_s:.0f} s"))
    console.print(f"model: {result.model_path}   TensorBoard: tensorboard --logdir {out / 'tb'}")


def _read_resumed_run(resume: Path) -> tuple[RunInfo, EnvConfig]:
    """What the run in `resume` was asked to do (its run.json) and its env config, or a clear error."""
    from socnav.rl.training import check_run_links, read_run_info

    if resume.exists() and not resume.is_dir():
        fail(f"--resume {resume} is a file; name a run directory (the --out of an earlier socnav train)")
    if not resume.is_dir():
        fail(f"--resume {resume}: no such run directory")
    try:
        check_run_links(resume)
        asked = read_run_info(resume)
        env_config = load_config(asked.env_config)
    except (ConfigError, OSError) as exc:
        fail(f"--resume {resume}: {exc}")
    return asked, env_config


def _resume_start(resume: Path, algo: str, timesteps: int) -> int | None:
    """The step the run in `resume` continues from; None (after showing its result) when it is already complete."""
    from socnav.rl.training import CheckpointError, finished_result, resume_step

    finished = finished_result(resume)
    if finished is not None:
        _report_complete(resume, algo, timesteps, finished)
        return None
    try:
        return resume_step(resume)
    except CheckpointError as exc:
        fail(f"--resume {resume}: {exc}")


def _new_run_directory(out: Path, force: bool) -> Path:
    """`out`, checked as the directory of a new run: new or empty, else moved aside with --force; writable."""
    from socnav.rl.training import RunDirectoryBusy, move_run_aside

    if out.exists() and not out.is_dir():
        fail(f"--out {out} is an existing file; name a run directory")
    if out.is_dir() and any(out.iterdir()):
        if not force:
            fail(f"--out {out} already holds files (an earlier run?); continue it with --resume {out}, or pass "
                 f"--force to move it aside to {out}.old-<timestamp> and start afresh")
        try:
            console.print(f"moved the existing {out} aside to {move_run_aside(out)}")
        except (RunDirectoryBusy, OSError) as exc:
            fail(f"--force: {exc}")
    _check_out_writable("--out", out)
    return out


def _start_training(env_config: EnvConfig, algo: str, seed: int, timesteps: int, out: Path, n_envs: int,
                    overrides: dict[str, Any], eval_every: int | None, eval_episodes: int) -> TrainResult:
    """A new training run in `out`, with a progress bar."""
    from socnav.rl.training import train as train_run

    return train_run(env_config, algo, seed, timesteps, out, n_envs=n_envs, overrides=overrides,
                     eval_every=eval_every, eval_episodes=eval_episodes, progress=True)


def _resume_training(resume: Path) -> TrainResult:
    """The run in `resume` continued from its last checkpoint, with a progress bar."""
    from socnav.rl.training import resume as resume_run

    return resume_run(resume, progress=True)


def _run_training(out: Path, run: Callable[[], TrainResult]) -> TrainResult:
    """The result of `run()`, a training run in `out`; its failures (and Ctrl-C) as one clear line."""
    from socnav.rl.training import CheckpointError, RunDirectoryBusy, TrainingInterrupted

    try:
        return run()
    except TrainingInterrupted as exc:
        fail(str(exc), code=1)
    except CheckpointError as exc:
        fail(f"--resume {out}: {exc}")
    except (RunDirectoryBusy, OSError) as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        _report_interrupted(out)


#: What `train --resume` takes from the run's own run.json: giving any of these with it would be ignored.
_RESUME_IGNORES = ("scenario", "algo", "seed", "timesteps", "n_envs", "n_humans", "max_humans", "config",
                   "algo_config", "settings", "eval_every", "eval_episodes", "out", "force", "humans")


def _refuse_options_resume_ignores(ctx: typer.Context) -> None:
    """`train --resume DIR` continues the run with the settings in its run.json: refuse options it would ignore."""
    # By the source's name: typer may hand back its own copy of click's ParameterSource enum.
    given = [name for name in _RESUME_IGNORES
             if getattr(ctx.get_parameter_source(name), "name", None) in ("COMMANDLINE", "ENVIRONMENT", "PROMPT")]
    if given:
        flags = ", ".join("--" + ("set" if name == "settings" else name.replace("_", "-")) for name in given)
        fail(f"--resume continues the run with the settings recorded in its run.json; {flags} would be ignored: "
             "drop them (or start a new run with --out)")


def _report_interrupted(out: Path) -> NoReturn:
    """Ctrl-C during `socnav train`: where the run stopped and how to continue it (exit code 130)."""
    from socnav.rl.training import CheckpointError, resume_step

    try:
        step = resume_step(out)
    except CheckpointError:
        step = None
    where = ("no checkpoint yet: --resume starts it from step 0" if step == 0 else
             f"its last checkpoint is at step {step:,}" if step is not None else "its checkpoint cannot be continued")
    console.print(f"[yellow]interrupted[/]: the run in {escape(str(out))} stopped; {where}. Continue it with: "
                  f"socnav train --resume {escape(str(out))}", highlight=False)
    raise typer.Exit(code=130)


def _check_out_file(option: str, path: Path, force: bool = False, create_parent: bool = False) -> None:
    """A clear error, before any work, when the output file `path` cannot or may not be written
    (`socnav.io.check_output_file`): an existing file without --force, a directory, FIFO or device, a path in
    /proc, /sys or /dev, a directory that does not exist (a typo is never created silently; `create_parent` only
    for a command's own default directory, e.g. runs/evaluate) or that cannot be written."""
    from socnav.io import OutputPathError, check_output_file

    try:
        check_output_file(path, what=option, force=force, create_parent=create_parent)
    except OutputPathError as exc:
        fail(str(exc))
    # Probed as well: root passes the permission check above where no file can be created (a read-only mount).
    _check_out_writable(option, path, directory=False)


def _check_human_model(humans: str | None) -> None:
    """--humans names a registered human model (`socnav.sim.humans`), or a one-line error with did-you-mean."""
    if humans is None:
        return
    from socnav.config import unknown_name_message
    from socnav.sim.humans import human_model_names

    if humans not in human_model_names():
        fail(f"--humans: {unknown_name_message('human model', humans, human_model_names())}")


def _check_choice(option: str, value: str | None, allowed: Any) -> None:
    """A one-line error naming `option` and the `allowed` values when `value` (None: not given) is not one."""
    if value is not None and value not in allowed:
        fail(f"{option} {value!r} is not known; allowed: {', '.join(allowed)}")


def _check_members(members: str | None) -> None:
    """--members matches at least two policy files (checked before any of them loads)."""
    import glob

    if members is None:
        return
    paths = sorted(glob.glob(members))
    if len(paths) < 2:
        fail(f"--members {members!r} matches {len(paths)} policy file(s); an ensemble needs at least 2")


def _check_perturbations(settings: list[str]) -> None:
    """The --perturb settings parse and name known perturbation fields with valid values, before a model loads
    (the world they apply to is known only after)."""
    if not settings:
        return
    try:
        load_config(None, perturbation=_perturbation_overrides(settings))
    except ConfigError as exc:
        fail(str(exc))


def _note_other_world(trained: Any, env_config: EnvConfig, label: str) -> None:
    """One line when a policy plays outside the world it was trained in (`trained`: the env config its file
    records): another scenario, walls it never saw (or none of those it learned with), another human model. The
    numbers then measure how the policy generalises, which a user may not have meant to measure."""
    from socnav.sim.walls import has_walls

    try:
        world = load_config(trained)
    except ConfigError:  # validated when the policy loaded; a note is not worth an error
        return

    def walls(config: EnvConfig) -> str:
        return "walls" if has_walls(config) else "no walls"

    changes = []
    if world.scenario != env_config.scenario:
        changes.append(f"scenario {world.scenario} -> {env_config.scenario}")
    if has_walls(world) != has_walls(env_config):
        changes.append(f"{walls(world)} -> {walls(env_config)}")
    elif has_walls(world) and (world.obstacles, world.map) != (env_config.obstacles, env_config.map):
        changes.append("other walls")
    if (world.humans.model, world.humans.mix) != (env_config.humans.model, env_config.humans.mix):
        changes.append(f"humans {world.humans.model} -> {env_config.humans.model}")
    if changes:
        console.print(f"note: {escape(label)} runs outside the world it was trained in ({escape('; '.join(changes))}"
                      "): the results measure how it generalises", highlight=False)


def _check_out_writable(option: str, path: Path, directory: bool = True) -> None:
    """A clear error, before any work, when `path` (a directory to create, or a file whose directory it is) cannot
    be written: a parent that is a file, a dangling link, or a place where no file can be created (no permission,
    a read-only or virtual filesystem such as /proc). Probed by creating and removing a temporary file in the
    nearest existing directory, which also holds for root, whom permission bits do not stop."""
    import os
    import tempfile

    existing = path if directory else path.parent
    while not existing.exists():
        if existing.is_symlink():
            fail(f"{option} {path}: {existing} is a dangling symbolic link")
        if existing == existing.parent:
            break
        existing = existing.parent
    if not existing.is_dir():
        fail(f"{option} {path}: {existing} is a file, not a directory")
    try:
        handle, probe = tempfile.mkstemp(prefix=".socnav-write-probe.", dir=existing)
    except OSError as exc:
        fail(f"{option} {path}: cannot write in {existing} ({exc.strerror or exc})")
    os.close(handle)
    os.unlink(probe)


def _report_complete(run_dir: Path, algo: str, asked: int, result: TrainResult) -> None:
    """`train --resume` of a run that already finished: say so and show its result instead of training again."""
    console.print(f"the run in {escape(str(run_dir))} is already complete ({result.timesteps:,} steps "
                  f"trained for the {asked:,} asked): nothing to resume. Its final validation:", highlight=False)
    if "goal_pct" in result.final_eval:
        console.print(metrics_table([(f"{algo} (validation)", result.final_eval)], f"{result.timesteps:,} steps"))
    console.print(f"model: {escape(str(result.model_path))}  (train longer: a new run with more --timesteps)",
                  highlight=False)


def _explain_rounding(asked: int, algo: str, overrides: dict[str, Any], n_envs: int) -> None:
    """Before training: SB3 collects whole rollouts (n_steps per environment x n_envs), so a run can end past the
    steps asked -- a rollout larger than the whole budget above all."""
    from socnav.rl.presets import resolve_config

    rollout = resolve_config(algo, overrides).n_steps * n_envs
    trained = -(-asked // rollout) * rollout
    if trained <= asked:
        return
    larger = f"one rollout ({rollout:,} steps = n_steps x n_envs) is more than" if rollout > asked else \
        f"rollouts of {rollout:,} steps (n_steps x n_envs) do not divide"
    console.print(f"note: {larger} the {asked:,} asked: SB3 collects whole rollouts, so {trained:,} steps will be "
                  "trained (lower --n-envs or n_steps to stay closer)", highlight=False)


def _single_agent_env_config(scenario: str | None, config_file: Path | None, n_humans: int | None,
                             max_humans: int | None = None, humans: str | None = None) -> EnvConfig:
    """`_env_config` for animate / calibrate: without --config, position swap with one human unless given."""
    if config_file is None:
        scenario = "position_swap" if scenario is None else scenario
        n_humans = 1 if n_humans is None else n_humans
    return _env_config(scenario, config_file, n_humans, max_humans, humans=humans)


def _check_observation_size(policies: list[Any], env_config: EnvConfig) -> None:
    """A clear error (not a reshape traceback) when a policy observes a different max_humans than the env, with
    the option that fixes it."""
    for policy in policies:
        observed = policy.observation_space["humans"].shape[0]
        if observed != env_config.max_humans:
            _, most = env_config.humans_range()
            fix = (f"--max-humans {observed}" if most <= observed else
                   f"--max-humans {observed} with at most {observed} humans (--n-humans {observed} or fewer)")
            fail(f"the model observes max_humans={observed} but the env config has "
                 f"max_humans={env_config.max_humans}; a model runs only with the value it was trained with: "
                 f"use {fix}")


def _model_world(model: str | None, scenario: str | None, config: Path | None, n_humans: int | None,
                 max_humans: int | None, default: Callable[[], EnvConfig], humans: str | None = None) -> EnvConfig:
    """The world a command plays: with --model and without --config, the world the model was trained in (as
    `evaluate` does; --scenario, --n-humans, --max-humans, --humans change it), else `default()`. Prints which
    world, and a note when the model plays outside its training world."""
    if model is None or config is not None:  # (with --config the user chose the world: no note)
        env_config = default()
        origin = f"--config {config}" if config is not None else "defaults"
    else:
        from socnav.rl.persistence import training_world

        policy = _load_learned_policy(model)
        base, origin = training_world(policy, scenario, n_humans, max_humans)
        origin += ", changed by the options" if humans is not None and "changed" not in origin else ""
        env_config = _env_config(scenario, None, n_humans, max_humans, base=base,
                                 observes=policy.observation_space["humans"].shape[0], humans=humans)
    console.print(f"world: {escape(describe_world(env_config))} ({escape(origin)})", highlight=False)
    if model is not None and config is None:
        _note_other_world(policy.socnav_metadata["env_config"], env_config, _model_label(model))
    return env_config


def _load_learned_policy(model: str) -> Any:
    if _is_navigator_file(model):  # else "corrupted or not a zip archive" for a valid export
        fail(f"--model {model} is an exported navigator (ONNX): socnav evaluate scores it; this command needs the "
             "policy file it was exported from (socnav train's model.zip, or pretrained)")
    import torch

    from socnav.rl.persistence import PolicyLoadError, load_policy

    # Batched inference on small matrices: one thread is faster than torch's intra-op pool, which also collapses
    # when the cores are shared.
    torch.set_num_threads(1)
    try:
        return load_policy(model)
    except PolicyLoadError as exc:
        fail(str(exc))


def _model_label(model: str) -> str:
    """How a model file is named in tables and default output names: its path as given (`runs/swap/model.zip`),
    so that two runs' `model.zip` files stay apart; the name of a shipped policy ('pretrained', 'pretrained-maps',
    'pretrained-ppo')."""
    from socnav.rl.persistence import PRETRAINED_FILES

    return model if model in PRETRAINED_FILES else str(Path(model))


def _default_records_path(label: str, config: EnvConfig, seed: int, episodes: int, extra: dict[str, Any]) -> Path:
    """runs/evaluate/<label>_<scenario>_<hash>_seed<k>_<n>ep.csv: unique per (policy or model file, env config,
    seed, episodes, and the other options that change the records), so two evaluations never share a file."""
    import hashlib
    import json
    import re

    identity = json.dumps({"label": label, "env": config.model_dump(mode="json"), **extra}, sort_keys=True)
    digest = hashlib.sha1(identity.encode()).hexdigest()[:8]
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", label.removesuffix(".zip")).strip("-")
    return Path("runs") / "evaluate" / f"{slug}_{config.scenario}_{digest}_seed{seed}_{episodes}ep.csv"


@app.command()
def evaluate(
    controller: str = typer.Option("orca", help="non-learned baseline controller: orca | straight (ignored with "
                                                "--model, which evaluates a trained policy)"),
    policy: str | None = typer.Option(None, "--policy", hidden=True,
                                         callback=_deprecated_alias("--policy", "--controller"),
                                         help="deprecated name of --controller"),
    model: str | None = model_option("trained policy file, or 'pretrained' / 'pretrained-maps' / "
                                                  "'pretrained-ppo' for a shipped one"),
    stochastic: bool = typer.Option(False, help="sample actions instead of the mean action"),
    scenario: str | None = scenario_option(None, help=f"one of: {SCENARIOS} (default: the model's training world "
                                                       "with --model, else circle_crossing)"),
    episodes: int = episodes_option(200, help="number of evaluation episodes"),
    seed: int = seed_option("episode k uses seed + k"),
    n_humans: int | None = n_humans_option(),
    max_humans: int | None = max_humans_option("observation rows (default 10; a model needs the value it was "
                                                "trained with)"),
    config: Path | None = config_option(),
    perturb: list[str] = perturb_option(),
    safety: str | None = safety_option("wrap the model in the safety layer with these thresholds: mc | ensemble | "
                                       "FILE (from socnav calibrate)"),
    estimator: str | None = estimator_option(None, help="uncertainty estimator of --safety: mc | ensemble (default: "
                                                        "ensemble for --safety ensemble, else mc)"),
    sensing: str | None = sensing_option(),
    members: str | None = members_option(),
    k: int = mc_samples_option("MC-dropout samples, for --estimator mc"),
    n_envs: int = n_envs_option(32),
    out: Path | None = typer.Option(None, help="per-episode records (.csv or .parquet; default a name unique "
                                                  "to the policy, world, seed and episodes under runs/evaluate)"),
    metrics: str = typer.Option("default", "--metrics", help="default (Goal %, Col. %, TO %, PV, nav time, "
                                                             "Return) | all | NAME,... (docs/metrics.md); other than "
                                                             "default, the records also hold every metric's "
                                                             "per-episode column"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --out records file"),
) -> None:
    """Evaluate a controller: Goal %, Collision %, Time-out %, PV, nav time, Return (--metrics: more); records to
    a file."""
    from socnav.controllers import CONTROLLERS, make_controller
    from socnav.envs.rollout import RolloutInterrupted
    from socnav.io import TABLE_FORMATS, write_table_atomic

    # Every option is checked before a model loads (18-24 s for the shipped one on a loaded machine).
    chosen = _chosen_metrics(metrics)
    controller = policy if policy is not None else controller
    if model is None and controller not in CONTROLLERS:
        fail(f"--controller {controller!r} is not known; allowed: {', '.join(CONTROLLERS)}")
    if out is not None and out.suffix not in TABLE_FORMATS:
        fail(f"--out must end in one of {', '.join(TABLE_FORMATS)}, got {out.name!r}")
    if safety is not None and model is None and members is None:
        fail("--safety needs a learned policy: --model PATH (or --model pretrained), or --estimator ensemble "
             "--members GLOB")
    exported = model is not None and _is_navigator_file(model)
    if exported and (safety is not None or stochastic):
        fail(f"--model {model} is an exported navigator: evaluate scores its policy's deterministic action alone; "
             f"for {'--safety' if safety is not None else '--stochastic'} evaluate the policy file it was exported "
             "from (model.zip or pretrained)")
    if safety is not None:
        _check_safety_options(safety, sensing, estimator, model, members)
    _check_perturbations(perturb)
    _check_human_model(humans)
    if out is not None:
        _check_out_file("--out", out, force=force)
    actor: Any = None if model is None else _load_navigator(model) if exported else _load_learned_policy(model)
    env_config = _evaluation_world(actor, scenario, config, n_humans, max_humans, perturb, humans)
    name = _model_label(model) if model is not None else controller
    if model is not None and config is None:
        _note_other_world(actor.socnav_metadata["env_config"], env_config, name)
    observer = None
    if safety is not None:
        from socnav.safety import FallbackCounter

        actor = _safe_policy_option(safety, sensing, estimator, model, members, k, env_config)
        observer = FallbackCounter(actor)
        name = (name if model is not None else "ensemble") + f" + safety ({safety})"
    elif actor is not None:
        _check_observation_size([actor], env_config)
    else:
        actor = make_controller(controller, env_config)
    if out is None:  # the command's own directory (runs/evaluate) is created, a --out directory never is
        out = _default_records_path(name, env_config, seed, episodes,
                                    {"stochastic": stochastic, "k": k, "estimator": estimator,
                                     "members": members, "sensing": sensing,
                                     **({"metrics": chosen} if chosen is not None else {})})
        _check_out_file("--out", out, force=force, create_parent=True)
    if stochastic:
        import torch

        # Sampled actions come from torch's generator: seeded, a run repeats; they still depend on --n-envs (the
        # order in which the batch draws them), unlike the deterministic mean action.
        torch.manual_seed(seed)
    _check_n_envs(min(n_envs, episodes), env_config)  # a rollout never steps more environments than episodes
    try:
        records = _evaluate(actor, env_config, episodes, seed, n_envs, f"{name} / {env_config.scenario}",
                            deterministic=not stochastic, observer=observer)
    except RolloutInterrupted as stopped:
        _save_interrupted_records(stopped, env_config, chosen, observer, out)
    records, summary = _evaluation_summary(records, env_config, chosen, observer)
    try:
        write_table_atomic(records, out)
    except OSError as exc:  # e.g. the disk filled up while the episodes ran
        fail(f"--out {out}: cannot write the records ({exc.strerror or exc})")
    title = f"{describe_world(env_config)}, seeds {seed}..{seed + episodes - 1}"
    if chosen is not None:
        console.print(_all_metrics_table(summary, chosen, f"{escape(name)}: {title}"))
    else:
        console.print(metrics_table([(name, summary)], title))
    console.print(f"per-episode records: {escape(str(out))}", highlight=False)


def _save_interrupted_records(stopped: RolloutInterrupted, env_config: EnvConfig, chosen: list[str] | None,
                              observer: Any, out: Path) -> NoReturn:
    """Ctrl-C during `evaluate`: the episodes finished by then are written to `out` (atomically: a second Ctrl-C
    leaves the file whole or absent), said in one line; exit code 130."""
    from socnav.io import write_table_atomic

    finished = len(stopped.records)
    if not finished:
        console.print("[yellow]interrupted[/] before any episode finished: nothing written", highlight=False)
        raise typer.Exit(code=130)
    records, _ = _evaluation_summary(stopped.records, env_config, chosen, observer)
    try:
        write_table_atomic(records, out)
    except OSError as exc:
        fail(f"interrupted; --out {out}: cannot write the {finished:,} finished episodes ({exc.strerror or exc})",
             code=130)
    console.print(f"[yellow]interrupted[/]: wrote the {finished:,} finished episodes (of {stopped.asked:,}) to "
                  f"{escape(str(out))}", highlight=False)
    raise typer.Exit(code=130)


def _is_navigator_file(model: str) -> bool:
    """Whether --model names an exported navigator (`socnav export`'s ONNX file) rather than a policy file."""
    return Path(model).suffix.lower() == ".onnx"


class _ExportedActor:
    """An exported navigator's policy as `evaluate` plays it: the deterministic action of its ONNX graph for the
    whole batch (`socnav.runtime.ExportedPolicy.predict`, what the torch policy it came from gives), with what
    `evaluate` reads of a loaded policy file: the world it was trained in and the rows it observes."""

    def __init__(self, network: Any) -> None:
        from types import SimpleNamespace

        from socnav.envs.spaces import HUMAN_FEATURE_NAMES

        record = network.record
        self.network = network
        self.socnav_metadata = {"algo": record.policy.algo, "env_config": record.env_config.model_dump(mode="json")}
        self.observation_space = {"humans": SimpleNamespace(shape=(network.max_humans, len(HUMAN_FEATURE_NAMES)))}

    def predict(self, observation: dict[str, Any], state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[Any, Any]:
        return self.network.predict(observation, state, episode_start, deterministic)


def _load_navigator(model: str) -> _ExportedActor:
    """The policy of the navigator file `model` (torch-free, onnxruntime), or a one-line error."""
    import importlib.util

    from socnav.extras import install_hint

    if importlib.util.find_spec("onnxruntime") is None:
        fail(f"--model {model} is an exported navigator; running it needs onnxruntime: {install_hint('runtime')}")
    from socnav.runtime import ExportedPolicy, NavigatorLoadError

    try:
        return _ExportedActor(ExportedPolicy.load(model))
    except NavigatorLoadError as exc:
        fail(str(exc))


def _check_safety_options(safety: str, sensing: str | None, estimator: str | None, model: str | None,
                          members: str | None) -> None:
    """--safety and the options that go with it, checked before any model loads: the thresholds file or preset,
    --sensing, --estimator (by default the one the thresholds were made for) and what it needs."""
    from socnav.safety.assembly import default_estimator_kind

    _load_thresholds_option(safety, sensing)
    _check_estimator_options(estimator or default_estimator_kind(safety), model, members)


def _check_estimator_options(kind: str, model: str | None, members: str | None) -> None:
    """--estimator `kind` is known and has what it estimates with (--model for mc, --members for ensemble), checked
    before any model loads (`_estimator_policies` loads them)."""
    from socnav.uncertainty import ESTIMATOR_KINDS

    _check_choice("--estimator", kind, ESTIMATOR_KINDS)
    if kind == "mc" and model is None:
        fail("--estimator mc needs --model PATH (or --model pretrained)")
    if kind == "ensemble" and members is None:
        fail("--estimator ensemble needs --members GLOB, e.g. 'runs/ensemble-quick/units/*/model.zip'")
    _check_members(members)


def _chosen_metrics(metrics: str) -> list[str] | None:
    """The metrics `evaluate --metrics` names, None for the default table's (then the records keep only the world's
    episode columns)."""
    from socnav.sim.metrics import DEFAULT_METRICS, select_metrics

    try:
        chosen = select_metrics(metrics)
    except ValueError as exc:
        fail(f"--metrics: {exc}")
    return None if tuple(chosen) == DEFAULT_METRICS else chosen


def _evaluation_world(actor: Any, scenario: str | None, config: Path | None, n_humans: int | None,
                      max_humans: int | None, perturb: list[str], humans: str | None = None) -> EnvConfig:
    """The world `evaluate` plays, printed: a learned `actor` without --config plays the world it was trained in
    (the world options change it), anything else --config's or the defaults; then the --perturb settings."""
    base: Path | dict[str, Any] | None = config
    origin = f"--config {config}" if config is not None else "defaults"
    if actor is not None and config is None:
        from socnav.rl.persistence import training_world

        base, origin = training_world(actor, scenario, n_humans, max_humans)
        origin += ", changed by the options" if humans is not None and "changed" not in origin else ""
    observes = None if actor is None else actor.observation_space["humans"].shape[0]
    env_config = _perturbed_config(_env_config(scenario, config, n_humans, max_humans, base=base,
                                               observes=observes, humans=humans), perturb)
    console.print(f"world: {escape(describe_world(env_config))} ({escape(origin)})", highlight=False)
    return env_config


def _evaluation_summary(records: pd.DataFrame, env_config: EnvConfig, chosen: list[str] | None,
                        observer: Any) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The records `evaluate` writes and their summary: the `chosen` metrics (None: the default table's, and
    only the world's episode columns kept), the wall collisions in a world with walls, and the share of steps the
    safety fallback drove when an `observer` (`FallbackCounter`) counted them."""
    from socnav.envs.rollout import EPISODE_COLUMNS, summarize
    from socnav.sim.metrics import DEFAULT_METRICS
    from socnav.sim.walls import has_walls

    walls = has_walls(env_config)  # a world with walls also counts the episodes that ended against a wall
    if chosen is None:
        records = records[list(EPISODE_COLUMNS) + (["collision_obstacle"] if walls else [])].copy()
    defaults = DEFAULT_METRICS + (("collision_obstacle_pct",) if walls else ())
    summary = summarize(records, pv_per=PV_PER, metrics=chosen if chosen is not None else defaults)
    if observer is not None:
        from socnav.safety import fallback_percent

        records["fallback_steps"] = observer.per_episode(records["episode"])
        summary["fallback_pct"] = fallback_percent(records)
    return records, summary


def _all_metrics_table(summary: dict[str, Any], chosen: list[str], title: str) -> Table:
    """`evaluate --metrics` other than default: one row per chosen metric, with its unit and which way is better."""
    from socnav.sim.metrics import metric_table_rows

    table = Table(title=title, caption=f"{summary['episodes']} episodes; definitions, units and sources: "
                                       "docs/metrics.md")
    for column in ("metric", "", "value", "unit", "better"):
        table.add_column(column, justify="right" if column == "value" else "left", no_wrap=True)
    for row in metric_table_rows(summary, chosen):
        table.add_row(*row)
    if "fallback_pct" in summary:
        table.add_row("fallback_pct", "fallback % steps", f"{summary['fallback_pct']:.1f}", "%", "–")
    return table


def _load_thresholds_option(safety: str, sensing: str | None = None) -> Any:
    """`--safety mc | ensemble | FILE` (with `--sensing perceived | true` if given) as `Thresholds` or, for a
    trigger file (socnav.safety.triggers), a `TriggerSpec`; or a clear error."""
    from socnav.safety import SENSING_CHOICES, Thresholds, ThresholdsError
    from socnav.safety.triggers import TriggerError, TriggerSpec, load_safety

    if Path(safety).is_dir():
        fail(f"--safety {safety} is a directory; name a thresholds or trigger file (.yaml or .json, from socnav "
             "calibrate) or a preset: mc, ensemble")
    try:
        decision = load_safety(safety)
    except (ThresholdsError, TriggerError, OSError) as exc:
        fail(f"--safety: {exc}")
    if sensing is None:
        return decision
    if sensing not in SENSING_CHOICES:
        fail(f"--sensing {sensing!r} is not known; allowed: {', '.join(SENSING_CHOICES)}")
    if isinstance(decision, TriggerSpec):
        return TriggerSpec.create(decision.model_dump(), sensing=sensing)
    return Thresholds.create(decision.model_dump(), sensing=sensing)


def _perturbed_config(env_config: EnvConfig, settings: list[str]) -> EnvConfig:
    """`env_config` with the `--perturb key=value` settings on top of its own perturbation."""
    if not settings:
        return env_config
    perturbation = _perturbation_overrides(settings)
    try:
        return load_config(env_config, perturbation={**env_config.perturbation.model_dump(), **perturbation})
    except ConfigError as exc:
        fail(str(exc))
        raise


def _safe_policy_option(safety: str, sensing: str | None, estimator: str | None, model: str | None,
                        members: str | None, k: int, env_config: EnvConfig) -> SafePolicy:
    """`evaluate --safety`: the model (or, without one, the ensemble's first member) in the safety layer with the
    --safety thresholds, reading --estimator's uncertainty (by default the one the thresholds were made for)."""
    from socnav.safety.assembly import assemble_safe_policy, default_estimator_kind

    thresholds = _load_thresholds_option(safety, sensing)
    kind = estimator or default_estimator_kind(safety)
    policy, ensemble = _estimator_policies(kind, model, members, env_config)
    if kind == "mc":
        _has_mc_dropout(str(model), policy, required=True)
    return assemble_safe_policy(policy, thresholds, env_config, estimator=kind, members=ensemble, k=k)


def _estimator(kind: str, model: str | None, members: str | None, k: int,
               env_config: EnvConfig, required: bool = True) -> tuple[Any, Any]:
    """(policy that acts, uncertainty estimator) for `--estimator mc|ensemble`.

    :param required: whether the command needs the estimate (a safety layer, a calibration): then a model without
        dropout layers under ``mc`` is an error; else its estimator is None (nothing to estimate), with a note.
    """
    from socnav.safety.assembly import make_safety_estimator

    policy, ensemble = _estimator_policies(kind, model, members, env_config)
    if kind == "mc" and not _has_mc_dropout(str(model), policy, required):
        return policy, None
    # MC dropout draws from a private, seeded mask stream (as the experiment units do): the same command gives the
    # same thresholds and the same animation, instead of drawing from torch's unseeded global RNG.
    return policy, make_safety_estimator(kind, policy, ensemble, k)


def _estimator_policies(kind: str, model: str | None, members: str | None,
                        env_config: EnvConfig) -> tuple[Any, list[Any]]:
    """(policy that acts, the ensemble's members: none under mc) of `--estimator kind`, loaded and checked against
    the world's observation size."""
    import glob

    from socnav.uncertainty import ESTIMATOR_KINDS

    if kind not in ESTIMATOR_KINDS:
        fail(f"--estimator {kind!r} is not known; allowed: {', '.join(ESTIMATOR_KINDS)}")
    if kind == "mc":
        if model is None:
            fail("--estimator mc needs --model PATH (or --model pretrained)")
        policy = _load_learned_policy(model)
        _check_observation_size([policy], env_config)
        return policy, []
    if members is None:
        fail("--estimator ensemble needs --members GLOB, e.g. 'runs/ensemble-quick/units/*/model.zip'")
    paths = sorted(glob.glob(members))
    if len(paths) < 2:
        fail(f"--members {members!r} matches {len(paths)} policy file(s); an ensemble needs at least 2")
    policies = [_load_learned_policy(path) for path in paths]
    policy = _load_learned_policy(model) if model is not None else policies[0]
    _check_observation_size([policy, *policies], env_config)
    return policy, policies


def _has_mc_dropout(model: str, policy: Any, required: bool) -> bool:
    """Whether MC dropout can sample `policy` (of --model `model`); if not, an error when the command needs the
    estimate (`required`), else a note that there is no uncertainty to draw."""
    from socnav.safety.assembly import has_mc_dropout

    if has_mc_dropout(policy):
        return True
    algo = policy.socnav_metadata.get("algo", "?")
    if required:
        fail(f"--estimator mc needs a model trained with dropout (odv-ppo-drop, ppo-drop); {model} is "
             f"{algo}, trained without: use --estimator ensemble --members GLOB")
    console.print(f"note: no uncertainty bars: {escape(model)} ({escape(algo)}) was trained without dropout, "
                  "so MC-dropout has nothing to sample (--estimator ensemble --members GLOB estimates with "
                  "an ensemble)", highlight=False)
    return False


def _perturbation_overrides(settings: list[str]) -> dict[str, Any]:
    perturbation: dict[str, Any] = {}
    for setting in settings:
        key, sep, value = setting.partition("=")
        if not sep or not key:
            fail(f"--perturb expects key=value (e.g. observation_noise=0.6), got {setting!r}")
        perturbation[key.strip()] = _yaml("--perturb", value)
    return perturbation


#: The default files of `animate` and `calibrate`: their directories are the commands' own, created when missing
#: (a --out directory that does not exist is refused: a typo).
ANIMATION_OUT = Path("runs") / "animate" / "episode.gif"
THRESHOLDS_OUT = Path("runs") / "calibration" / "thresholds.yaml"


@app.command()
def animate(
    model: str | None = model_option(ACTING_MODEL_HELP),
    estimator: str = estimator_option("mc"),
    members: str | None = members_option(),
    k: int = mc_samples_option(),
    scenario: str | None = scenario_option(None, help=SINGLE_AGENT_SCENARIO_HELP),
    n_humans: int | None = n_humans_option(SINGLE_AGENT_N_HUMANS_HELP),
    max_humans: int | None = max_humans_option(SINGLE_AGENT_MAX_HUMANS_HELP),
    config: Path | None = config_option(),
    perturb: list[str] = perturb_option(),
    safety: str | None = safety_option("thresholds (mc | ensemble | FILE): wrap the policy in SafePolicy"),
    sensing: str | None = sensing_option(),
    seed: int = seed_option("episode seed"),
    out: Path = typer.Option(ANIMATION_OUT, help="output .gif or .mp4"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --out animation"),
) -> None:
    """Animate one episode with the windowed uncertainties drawn live (and the safety fallback coloured)."""
    from socnav.experiments.animate import animate_episode
    from socnav.viz import check_animation_path

    if out.suffix not in (".gif", ".mp4"):
        fail(f"--out must end in .gif or .mp4, got {out.name!r}")
    try:
        check_animation_path(out)  # before the episode is played: .mp4 without the [video] extra
    except ImportError as exc:
        fail(f"--out {out}: {exc}")
    _check_out_file("--out", out, force=force, create_parent=out == ANIMATION_OUT)
    # Every option is checked before a model loads.
    _check_estimator_options(estimator, model, members)
    if safety is not None:
        _load_thresholds_option(safety, sensing)
    _check_perturbations(perturb)
    _check_human_model(humans)
    env_config = _perturbed_config(_model_world(
        model, scenario, config, n_humans, max_humans,
        default=lambda: _single_agent_env_config(scenario, config, n_humans, max_humans, humans),
        humans=humans), perturb)
    # Without a safety layer the bars are only drawn when there is an uncertainty to draw: a model without dropout
    # has no MC-dropout samples (all zero bars would say "certain").
    policy, uncertainty = _estimator(estimator, model, members, k, env_config, required=safety is not None)
    thresholds = None if safety is None else _load_thresholds_option(safety, sensing)
    label = _model_label(model) if model is not None else f"ensemble of {members}"
    path, summary = animate_episode(policy, uncertainty, env_config, out, seed=seed, thresholds=thresholds,
                                    policy_label=label, safety_label=safety)
    fallback = "" if safety is None else f", safety fallback on {summary['fallback_steps']} steps"
    console.print(f"{summary.get('outcome', 'running')} after {summary.get('length', '?')} steps{fallback}: "
                  f"{escape(str(path))}", highlight=False)


def _calibration_report_path(out: Path) -> Path:
    """The report `save_calibration` writes next to the thresholds file `out` (every candidate and its scores)."""
    return out.with_suffix(".report.json")


#: Fewer calibration collisions than this and `socnav calibrate` warns that the prevented share is rough.
FEW_COLLISIONS = 10


def calibration_table(thresholds: Any, report: dict[str, Any], title: str) -> Table:
    """The chosen thresholds and their measured scores (`calibrate_thresholds` report) as one table row."""
    import math

    table = Table(title=title)
    for column in ("λ_ep", "λ_f", "λ_prox", "β1", "c_prox", "hold", "prevented", "collisions", "false act."):
        table.add_column(column, justify="right", no_wrap=True)
    values = thresholds.model_dump()
    table.add_row(*(f"{values[key]:.4g}" for key in ("lambda_ep", "lambda_feat", "lambda_prox", "beta1")),
                  values["proximity"], str(values["hold_steps"]),
                  "–" if math.isnan(report["prevented_fraction"]) else f"{report['prevented_fraction']:.0%}",
                  str(report["n_collisions"]),
                  f"{report['false_activation_rate']:.1%}"
                  + (f" (≤ {report['false_activation_upper']:.1%})" if "false_activation_upper" in report else ""))
    return table


@app.command()
def calibrate(
    model: str | None = model_option(ACTING_MODEL_HELP),
    estimator: str = estimator_option("mc"),
    members: str | None = members_option(),
    k: int = mc_samples_option(),
    scenario: str | None = scenario_option(None, help=SINGLE_AGENT_SCENARIO_HELP),
    n_humans: int | None = n_humans_option(SINGLE_AGENT_N_HUMANS_HELP),
    max_humans: int | None = max_humans_option(SINGLE_AGENT_MAX_HUMANS_HELP),
    config: Path | None = config_option(),
    episodes: int = episodes_option(40, help="episodes per calibration configuration"),
    false_activation_budget: float = typer.Option(
        0.05, min=0.0, max=1.0, help="allowed false-activation rate: the share of unperturbed steps on which the "
                                     "fallback may act (the experiment's safety.false_activation_budget)"),
    budget: float | None = typer.Option(None, "--budget", min=0.0, max=1.0, hidden=True,
                                           callback=_deprecated_alias("--budget", "--false-activation-budget"),
                                           help="deprecated name of --false-activation-budget"),
    proximity: str = typer.Option("both", help="c_prox readings to search: both | abs-relative-speed | closing-speed"),
    sensing: str = sensing_option("perceived", help="what the proximity terms and fallback read: perceived (the "
                                                    "noisy observation) | true (the simulator's state)"),
    confidence: float = typer.Option(0.95, min=0.5, max=0.999, help="the budget must hold at this one-sided "
                                                                     "confidence (0.5: the point estimate)"),
    out: Path = typer.Option(THRESHOLDS_OUT, help="threshold file (.yaml/.json)"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --out threshold file (and its report)"),
    trigger: str = typer.Option("paper", help="what decides the hand-over: the rule (paper | proximity-only | "
                                              "uncertainty-only) or a score trigger (time-to-collision | closing-gap "
                                              "| predicted-clearance | conformal | risk-model | "
                                              "risk-model+uncertainty; docs/uncertainty-safety.md)"),
) -> None:
    """Choose the safety thresholds on calibration episodes (perturbations and seeds disjoint from evaluation)."""
    from socnav.safety import PROXIMITY_VARIANTS, calibrate_thresholds, save_calibration
    from socnav.safety.rule import RULE_CONDITIONS

    false_activation_budget = budget if budget is not None else false_activation_budget
    _check_trigger_name(trigger)
    if proximity != "both" and proximity not in PROXIMITY_VARIANTS:
        fail(f"--proximity {proximity!r} is not known; allowed: both, {', '.join(PROXIMITY_VARIANTS)}")
    if sensing not in ("perceived", "true"):
        fail(f"--sensing {sensing!r} is not known; allowed: perceived, true")
    if out.is_dir() or out.suffix not in (".yaml", ".yml", ".json"):
        fail(f"--out must be a .yaml or .json file path, got {str(out)!r}")
    _check_out_file("--out", out, force=force, create_parent=out == THRESHOLDS_OUT)
    _check_out_file("--out", _calibration_report_path(out), force=force, create_parent=out == THRESHOLDS_OUT)
    if trigger.startswith("risk-model"):
        from socnav.safety.calibration.trigger_search import risk_model_path

        _check_out_file("--out", risk_model_path(out.parent, trigger, f"{out.stem}."), force=force,
                        create_parent=out == THRESHOLDS_OUT)
    _check_estimator_options(estimator, model, members)  # before a model loads
    _check_human_model(humans)
    env_config = _model_world(model, scenario, config, n_humans, max_humans,
                              default=lambda: _single_agent_env_config(scenario, config, n_humans, max_humans,
                                                                       humans),
                              humans=humans)
    policy, uncertainty = _estimator(estimator, model, members, k, env_config)
    if trigger not in RULE_CONDITIONS:
        _calibrate_score_trigger(trigger, policy, uncertainty, env_config, episodes, false_activation_budget,
                                 sensing, confidence, out)
        return
    with _progress() as progress:
        task = progress.add_task("calibration episodes (collect, then replay each candidate)", total=None)
        thresholds, report = calibrate_thresholds(
            policy, None if trigger == "proximity-only" else uncertainty, env_config.model_dump(mode="json"), episodes,
            false_activation_budget, proximity, confidence=confidence,
            progress=lambda done, total: progress.update(task, completed=done, total=total), sensing=sensing,
            conditions=trigger)
    report_path = save_calibration(thresholds, report, out)
    console.print(calibration_table(thresholds, report, f"calibrated thresholds ({estimator}, false-activation "
                                                        f"budget {false_activation_budget:.0%})"))
    console.print("prevented: share of the plain policy's calibration collisions prevented in the replayed episodes "
                  "(mean over perturbation types); false act.: share of unperturbed steps where the fallback acted "
                  f"(≤ its one-sided {confidence:.0%} upper bound); every candidate in "
                  f"{escape(str(report_path))}", highlight=False)
    if report["n_collisions"] and report["n_collisions"] < FEW_COLLISIONS:
        console.print(f"[yellow]warning:[/] the prevented share rests on only {report['n_collisions']} calibration "
                      f"collision(s) (< {FEW_COLLISIONS}); it is a rough estimate: use more --episodes",
                      highlight=False)
    if "note" in report:
        console.print(escape(report["note"]), highlight=False)
    console.print(f"thresholds: {out}  (use with --safety {out})")


def _check_trigger_name(trigger: str) -> None:
    """`--trigger`: a registered trigger or ``risk-model+uncertainty`` (did-you-mean otherwise)."""
    from socnav.safety.triggers import TriggerError, trigger_class, trigger_names

    if trigger in (*trigger_names(), "risk-model+uncertainty"):
        return
    try:
        trigger_class(trigger)
    except TriggerError as exc:
        fail(f"--trigger: {exc}")


def _calibrate_score_trigger(trigger: str, policy: Any, uncertainty: Any, env_config: EnvConfig, episodes: int,
                             budget: float, sensing: str, confidence: float, out: Path) -> None:
    """`calibrate --trigger NAME` of a score trigger: prepared (the conformal bound fitted, the risk model trained
    on its own seeds), its threshold chosen by replays, written to `out` (with the risk model beside it)."""
    from socnav.safety.calibration.trigger_search import calibrate_score_triggers, prepare_triggers
    from socnav.safety.triggers import save_trigger_spec

    env = env_config.model_dump(mode="json")
    n_envs = min(episodes, 40)
    notes: list[str] = []
    with console.status("calibration episodes (prepare, record, then replay each candidate)") as status:
        def log(message: str) -> None:
            notes.append(message)
            status.update(message)

        specs = prepare_triggers([trigger], policy, uncertainty, env, episodes, 3 * episodes, sensing, 4, n_envs,
                                 out.parent, log, prefix=f"{out.stem}.")
        if trigger not in specs:
            fail(f"--trigger {trigger}: {notes[-1]}")
        chosen = calibrate_score_triggers(specs, policy, uncertainty, env, episodes, [budget], sensing, 4, n_envs,
                                          confidence, log)[trigger][budget]
    save_trigger_spec(chosen, out, extra={"false_activation_budget": budget, "confidence": confidence,
                                          "episodes_per_configuration": episodes})
    state = "never fires: no threshold kept the budget" if chosen.threshold == float("inf") else (
        f"threshold {chosen.threshold:.4g}")
    console.print(f"{trigger}: {state} (false-activation budget {budget:.0%} at {confidence:.0%} confidence)",
                  highlight=False)
    console.print(f"trigger: {out}  (use with --safety {out})", highlight=False)


@app.command()
def convert(
    model: str = typer.Argument(..., help="socnav policy file (from socnav train), or 'pretrained' / "
                                          "'pretrained-maps' / 'pretrained-ppo'"),
    to_sb3: Path = typer.Option(..., "--to-sb3", help="write a Stable-Baselines3 model zip here "
                                                       "(ODVPPO.load reads it)"),
    force: bool = force_option("the --to-sb3 file"),
) -> None:
    """Turn a socnav policy file into a full Stable-Baselines3 model (for fine-tuning with model.learn)."""
    from socnav.rl.convert import to_sb3 as convert_to_sb3
    from socnav.rl.persistence import PolicyLoadError

    if to_sb3.suffix != ".zip":
        fail(f"--to-sb3 must be a .zip path, got {to_sb3.name!r}")
    _check_out_file("--to-sb3", to_sb3, force=force)
    try:
        sb3_model = convert_to_sb3(model, n_envs=1)
    except PolicyLoadError as exc:
        fail(str(exc))
        return
    to_sb3.parent.mkdir(parents=True, exist_ok=True)
    sb3_model.save(to_sb3)
    console.print(f"SB3 model: {escape(str(to_sb3))}  (from socnav.rl import ODVPPO; ODVPPO.load({str(to_sb3)!r}, "
                  "env=...); SB3's format is pickled: load only files you trust)", highlight=False)


@app.command()
def demo(
    out: Path = typer.Option(Path("runs") / "demo", help="output directory"),
    episodes: int = episodes_option(100, help="episodes per scenario and controller"),
    seed: int = seed_option("first episode seed"),
    train_steps: int = typer.Option(0, min=0, help="train a fresh ODV-PPO-Drop policy for this many steps "
                                                    "(0: use the pretrained one shipped with socnav)"),
) -> None:
    """Baselines in every scenario, an ODV-PPO-Drop policy, then that policy under heading noise with and without
    the safety layer: metrics and animations (GIF)."""
    from socnav.experiments import demo as steps

    if out.exists() and not out.is_dir():
        fail(f"--out {out} is an existing file; name a directory for the demo's tables and animations")
    _check_out_writable("--out", out)
    rows = steps.baseline_rows(out, episodes, seed, progress=_progress_bar)
    console.print(metrics_table(rows, f"Baseline controllers, {episodes} episodes each (seeds {seed}..)"))
    gif, summary = steps.animate_baseline(out, seed)
    console.print(f"animation of one ORCA episode ({summary.get('outcome')}): {escape(str(gif))}", highlight=False)
    gif, summary = steps.animate_map_baseline(out, seed)
    console.print(f"animation of one ORCA episode among walls, its planned path and subgoal drawn "
                  f"({summary.get('outcome')}): {escape(str(gif))}", highlight=False)

    world, rows = steps.map_policy_rows(out, episodes, seed, progress=_progress_bar)
    console.print(metrics_table(rows, f"{describe_world(world)}, the shipped map policy alone and inside its safety "
                                      f"layer, {episodes} episodes (seeds {seed}..)"))
    gif, summary = steps.animate_map_policy(world, out, seed)
    console.print(f"animation of one {steps.MAP_POLICY} episode inside its safety layer, its planned path and "
                  f"subgoal drawn ({summary.get('outcome')}, fallback on {summary.get('fallback_steps')} steps): "
                  f"{escape(str(gif))}", highlight=False)

    if train_steps:
        from socnav.rl.training import TrainingInterrupted

        console.print(f"training ODV-PPO-Drop on position swap with one human for {train_steps:,} steps")
        try:
            trained = steps.train_policy(out, seed, train_steps)
        except TrainingInterrupted as exc:
            fail(str(exc), code=1)
        model_path, label = str(trained.model_path), "odv-ppo-drop (trained now)"
    else:
        model_path, label = "pretrained", "odv-ppo-drop (pretrained)"
    policy = _load_learned_policy(model_path)
    world, row = steps.learned_policy_row(policy, label, out, episodes, seed, progress=_progress_bar)
    console.print(metrics_table([row], f"{describe_world(world)}, {episodes} episodes"))
    gif, summary = steps.animate_learned_policy(policy, world, out, seed, label)
    console.print(f"animation of one learned-policy episode ({summary.get('outcome')}): {escape(str(gif))}",
                  highlight=False)

    # The point of the project: under a perturbation, the safety layer hands over to a cautious controller when
    # the policy is uncertain and a human is close.
    console.print(f"[bold]safety layer[/]: {label} under {steps.PERTURBATION}, the same episodes without and with "
                  "the layer (MC-dropout, the paper's thresholds), and with " + " and ".join(steps.COMPARISONS)
                  + " (calibrated for the shipped policy at the 5 % budget)")
    with _progress() as progress:
        def tick(what: str, total: int) -> Any:
            task = progress.add_task(f"{what} / {world.scenario}", total=total)
            return lambda n: progress.advance(task, n)

        result = steps.safety_demo(policy, world, episodes, seed, progress=tick)
    steps.write_safety_records(result, out)
    console.print(metrics_table(steps.summary_rows(result, label), f"{describe_world(result.config)}, "
                                                                   f"{episodes} episodes"))
    for line in steps.describe(result):
        console.print(line, highlight=False)
    saved_seed = steps.find_saved_episode(policy, result.config, result.saved) if result.saved else None
    if saved_seed is not None:
        without, with_layer = steps.animate_saved_episode(policy, result.config, saved_seed, out, label)
        console.print(f"an episode the safety layer saves (seed {saved_seed}): without it {escape(str(without))}, "
                      f"with it {escape(str(with_layer))}", highlight=False)
    elif result.saved:
        console.print("no animation: the saved episodes are not saved when replayed alone (the MC-dropout masks "
                      "differ for a batch of one)", highlight=False)


@app.command()
def export(
    model: str = typer.Argument(..., help="policy file (socnav train's model.zip) or 'pretrained' / "
                                          "'pretrained-maps' / 'pretrained-ppo'"),
    out: Path = typer.Option(Path("navigator.onnx"), help="the ONNX navigator file to write"),
    thresholds: str = typer.Option("mc", help="safety thresholds: mc | ensemble | a `socnav calibrate` FILE (a "
                                              "trigger file too: the navigator then decides with that trigger)"),
    # k, p-test and window are read as text and checked by socnav.export.check_settings: one line naming the
    # option and its allowed range (socnav.runtime.format's MAX_K, MAX_WINDOW) for any bad value, 1e9 included.
    # typer does not enforce min / max on text: they document the range (docs/configuration_table.py reads them).
    k: str = typer.Option("20", min=2, max=1000, metavar="INTEGER", help="MC-dropout samples per decision"),
    p_test: str | None = typer.Option(None, metavar="FLOAT", help="MC-dropout p, in (0, 1) (default: the "
                                                                     "policy's; 0 would disable the uncertainty)"),
    window: str = typer.Option("4", min=1, max=10_000, metavar="INTEGER", help="uncertainty window in steps"),
    value: bool = typer.Option(False, "--value", help="also export the critic (output 'value')"),
    force: bool = force_option("the --out navigator file"),
) -> None:
    """Export a policy, its MC-dropout settings and safety thresholds as ONNX for the torch-free socnav.runtime."""
    import importlib.util

    from socnav.extras import install_hint

    missing = [name for name in ("onnx", "onnxruntime") if importlib.util.find_spec(name) is None]
    if missing:
        fail(f"socnav export needs {' and '.join(missing)}: {install_hint('export')}")
    from socnav.export import ExportError, check_settings, export_onnx
    from socnav.safety import ThresholdsError
    from socnav.safety.triggers import TriggerError, load_safety

    try:
        k_value, p_test_value, window_value = check_settings(
            k, p_test, window, names={"k": "--k", "p_test": "--p-test", "window": "--window"})
    except ExportError as exc:
        fail(str(exc))
    _check_out_file("--out", out, force=force)
    if Path(thresholds).is_dir():
        fail(f"--thresholds {thresholds} is a directory; name a thresholds file (from socnav calibrate) or a preset: "
             "mc, ensemble")
    try:  # before the policy loads
        load_safety(thresholds)
    except (ThresholdsError, TriggerError, OSError) as exc:
        fail(f"--thresholds: {exc}")

    policy = _load_learned_policy(model)
    try:
        path = export_onnx(policy, out, thresholds=thresholds, k=k_value, p_test=p_test_value, window=window_value,
                           with_value=value)
    except (ExportError, ThresholdsError, TriggerError, OSError) as exc:
        fail(str(exc))
    console.print(f"navigator: {path}  (run it with socnav.runtime.SafeNavigator.load({str(path)!r}))")


@app.command()
def plot(
    run_dir: Path = typer.Argument(..., help="training run directory (socnav train --out), holding curve.csv"),
    out: Path | None = typer.Option(None, help="the PNG to write (default RUN_DIR/curve.png)"),
    force: bool = force_option("the --out picture"),
) -> None:
    """Draw a training run's curve (return, goal and collision rates against timesteps) as a PNG."""
    if run_dir.exists() and not run_dir.is_dir():
        fail(f"{run_dir} is a file; name a training run directory (the --out of socnav train)")
    if not run_dir.is_dir():
        fail(f"no such run directory: {run_dir}")
    if not (run_dir / "curve.csv").is_file():
        fail(f"{run_dir} has no curve.csv: not a socnav train run directory, or its first rollout has not finished")
    out = run_dir / "curve.png" if out is None else out
    if out.suffix.lower() != ".png":
        fail(f"--out must end in .png, got {out.name!r}")
    _check_out_file("--out", out, force=force)
    from socnav.viz.curves import TrainingCurveError, plot_training_curve  # matplotlib: loaded only here

    try:
        path = plot_training_curve(run_dir, out)
    except TrainingCurveError as exc:
        fail(str(exc))
    except OSError as exc:  # a full disk, a directory gone meanwhile
        fail(f"--out {out}: cannot write the picture ({exc.strerror or exc})")
    console.print(f"training curve: {escape(str(path))}", highlight=False)


add_experiment_commands(app)  # socnav run / report / tune, listed after the commands above

from socnav.ros2.cli import app as ros2_app  # noqa: E402 -- imports no rclpy: each ros2 command loads it

app.add_typer(ros2_app, name="ros2")  # socnav ros2 navigator / sim


def _terminate_as_interrupt() -> None:
    """SIGTERM does what the first Ctrl-C does (a service manager, `kill`, a job scheduler send it): the command's own
    SIGINT handling runs -- `train` saves a checkpoint, `evaluate` writes its finished episodes, `run` stops its units
    -- instead of the process dying with its work unsaved. The ROS 2 nodes install their own handlers for both."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    signal.signal(signal.SIGTERM, lambda signum, frame: signal.raise_signal(signal.SIGINT))


def main() -> None:
    """Entry point of the `socnav` command and of `python -m socnav` (the usage line names `socnav`).

    A configuration error found only when a world is built (e.g. walls that cover every start of a scenario, found
    when episodes are drawn) is one line, as the errors found when the options are read; anything else keeps its
    traceback. SIGTERM is handled as the first Ctrl-C (`_terminate_as_interrupt`)."""
    _terminate_as_interrupt()
    try:
        app(prog_name="socnav")  # exits (SystemExit) unless a command raised: typer re-raises it
    except ConfigError as exc:
        console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
