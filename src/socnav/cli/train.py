"""`socnav train` (a new run, or `--resume` of an interrupted one) and `socnav plot` (a run's training curve).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import typer
from rich.markup import escape

from socnav._console import console, fail
from socnav.cli.options import (
    SCENARIOS,
    algo_option,
    config_option,
    eval_episodes_option,
    eval_every_option,
    force_option,
    humans_option,
    max_humans_option,
    n_envs_option,
    n_humans_option,
    scenario_option,
    seed_option,
    timesteps_option,
)
from socnav.config import ConfigError, EnvConfig, load_config

if TYPE_CHECKING:  # pandas, torch and SB3 load inside the commands: `socnav --help` stays fast

    from socnav.rl.training import RunInfo, TrainResult

from socnav.cli.common import (
    check_human_model,
    check_n_envs,
    check_out_file,
    check_out_writable,
    command_env_config,
    metrics_table,
    yaml_value,
)


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
        overrides[key.strip()] = yaml_value("--set", value)
    try:
        resolve_config(algo, overrides)
    except ValueError as exc:
        fail(" ".join(describe_override_error(algo, exc).split()))
    return overrides


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
        check_human_model(humans)
        env_config = command_env_config(scenario, config, n_humans, max_humans, humans=humans)
        overrides = _algo_overrides(algo, algo_config, settings)
        out = _new_run_directory(out or Path("runs") / "train" / f"{env_config.scenario}_{algo}_seed{seed}", force)
        start = 0
    check_n_envs(n_envs, env_config)
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
    check_out_writable("--out", out)
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
    check_out_file("--out", out, force=force)
    from socnav.viz.curves import TrainingCurveError, plot_training_curve  # matplotlib: loaded only here

    try:
        path = plot_training_curve(run_dir, out)
    except TrainingCurveError as exc:
        fail(str(exc))
    except OSError as exc:  # a full disk, a directory gone meanwhile
        fail(f"--out {out}: cannot write the picture ({exc.strerror or exc})")
    console.print(f"training curve: {escape(str(path))}", highlight=False)

