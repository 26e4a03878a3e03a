"""A training run's directory: what was asked (run.json), its checkpoints and logs, and how far a run can be
resumed from what it left; `socnav.rl.training` trains in it.

Run directory::


    run.json                 what was asked (env config, algo, overrides, seed, timesteps) and the status
    checkpoints/step_N.zip   safe checkpoint (tensors + JSON, `socnav.rl.persistence.save_checkpoint`: network,
                             optimizer state, counters, schedules as data); checkpoints/state.json names it (written
                             last: a kill at any moment leaves a state naming an intact zip and its log rows)
    .lock                    held (flock) while a training works in the directory
    curve.csv                training curve: timesteps, wall_time_s, ep_rew_mean, ep_len_mean, success_rate
    eval.csv                 periodic evaluation on validation seeds (goal/collision/timeout %, PV, return)
    model.zip                the final policy in socnav's safe format (`socnav.load_policy`)
    tb/                      TensorBoard logs (SB3's, plus eval/*)
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from socnav.config import ConfigError, load_config
from socnav.io import (
    UnsafePathError,
    UntrustedInputError,
    file_lock,
    find_links,
    read_json,
    read_table,
    write_text_atomic,
)
from socnav.rl.archive import MAX_HEADER_BYTES, validation_message
from socnav.rl.checkpoints import CheckpointError, CheckpointHeader, read_checkpoint_header, verify_checkpoint
from socnav.rl.presets import AlgoConfig, AlgoName, resolve_config

MAX_SEED = 2**28  # run seeds below this keep training environments (2**40 + seed * 4096 + i) under 2**41

CURVE_COLUMNS = ["timesteps", "wall_time_s", "ep_rew_mean", "ep_len_mean", "success_rate"]


EVAL_COLUMNS = ["timesteps", "wall_time_s", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv",
                "return_mean", "return_std"]


WALL_EVAL_COLUMNS = ["collision_obstacle_pct"]  # eval.csv of a world with walls (maps, obstacles, map scenarios)


CHECKPOINT_NAME = re.compile(r"^step_(\d+)\.zip$")  # the only files of checkpoints/ a run writes or deletes


class RunDirectoryBusy(RuntimeError):
    """Another training holds the run directory's lock."""


class RunDirectoryExists(FileExistsError):
    """`train` without `resume` or `force` was given a directory that already holds files (an earlier run?)."""


@dataclass
class TrainResult:
    model_path: Path
    timesteps: int
    wall_time_s: float
    final_eval: dict[str, float] = field(default_factory=dict)
    resumed_from: int = 0  # the checkpoint step the run continued from (0: it started afresh)


class RunCounters(BaseModel):
    """The run's own counters at a checkpoint (stored in the checkpoint and in state.json)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    wall_time_s: float = Field(ge=0, allow_inf_nan=False)
    next_eval: int = Field(ge=1)
    curve_rows: int = Field(ge=0)
    eval_rows: int = Field(ge=0)


class CheckpointState(RunCounters):
    """``checkpoints/state.json``: the checkpoint to resume from (a plain file name inside checkpoints/)."""

    num_timesteps: int = Field(ge=0)
    checkpoint: str

    @field_validator("checkpoint")
    @classmethod
    def _plain_name(cls, name: str) -> str:
        if not CHECKPOINT_NAME.match(name):
            raise ValueError("must be a checkpoint file name inside checkpoints/, step_<N>.zip (no directories)")
        return name


class RunInfo(BaseModel):
    """What a training run was asked to do (``run.json``); the status fields written later are kept as extras."""

    model_config = ConfigDict(extra="allow")

    env_config: dict[str, Any]
    algo: AlgoName
    overrides: dict[str, Any] = Field(default_factory=dict)
    seed: int = Field(ge=0, lt=MAX_SEED, strict=True)
    timesteps: int = Field(ge=1, strict=True)
    n_envs: int = Field(ge=1, strict=True)
    eval_every: int = Field(ge=1, strict=True)
    eval_episodes: int = Field(ge=1, strict=True)


def read_run_info(out_dir: str | Path) -> RunInfo:
    """The validated ``run.json`` of a training run directory.

    :raises ConfigError: missing or unreadable file, or a field of the wrong type or out of range (named).
    """
    path = Path(out_dir) / "run.json"
    if not path.is_file() and not path.is_symlink():
        raise ConfigError(f"no run.json in {out_dir} (not a socnav training run directory)")
    try:
        data = _read_run_json(path)
    except (OSError, UntrustedInputError) as exc:
        raise ConfigError(str(exc)) from None
    try:
        info = RunInfo.model_validate(data)
        resolve_config(info.algo, info.overrides)
        load_config(info.env_config)
    except ValidationError as exc:
        raise ConfigError(f"invalid {path}: {validation_message(exc)}") from None
    except ConfigError as exc:
        raise ConfigError(f"{path}: env_config: {exc}") from None
    except ValueError as exc:  # resolve_config: an unknown or invalid override
        raise ConfigError(f"{path}: overrides: {exc}") from None
    return info


def finished_result(out_dir: str | Path) -> TrainResult | None:
    """The recorded result of the training run in `out_dir` if it finished (its run.json says complete and model.zip
    is there), None if it is still to finish or run.json is unreadable."""
    out_dir = Path(out_dir)
    try:
        info = _read_run_json(out_dir / "run.json")
    except (OSError, UntrustedInputError):
        return None
    if not isinstance(info, dict) or info.get("status") != "complete" or not (out_dir / "model.zip").is_file():
        return None
    if find_links(out_dir):  # not this run's own files: `train(resume=True)` refuses the directory, naming the link
        return None
    final_eval = info.get("final_eval")
    return TrainResult(out_dir / "model.zip", info.get("num_timesteps", 0), info.get("wall_time_s", 0.0),
                       final_eval if isinstance(final_eval, dict) else {})


def _read_run_json(path: Path) -> Any:
    """A run-metadata file (run.json, state.json): bounded in size and depth, never read through a symbolic link.

    :raises UntrustedInputError: a link, too large, too deep or not JSON; OSError: missing or unreadable.
    """
    return read_json(path, max_bytes=MAX_HEADER_BYTES, follow_links=False)


def _read_state(path: Path) -> CheckpointState:
    try:
        return CheckpointState.model_validate(_read_run_json(path))
    except (OSError, UntrustedInputError) as exc:
        raise CheckpointError(f"{exc}; delete {path.parent} to restart the run") from None
    except ValidationError as exc:
        raise CheckpointError(f"invalid {path}: {validation_message(exc)}; delete {path.parent} to restart "
                              "the run") from None


def _read_log(out_dir: Path, name: str) -> list[dict[str, Any]]:
    """The rows of a run's curve.csv / eval.csv (none if it is missing)."""
    path = out_dir / name
    if not path.is_file():
        return []
    try:
        return read_table(path).to_dict("records")
    except (OSError, ValueError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise CheckpointError(f"{path} is unreadable ({type(exc).__name__}); the logs cannot be continued") from None


def _logs_mismatch(state: CheckpointState, curve: list[dict[str, Any]], evals: list[dict[str, Any]]) -> str | None:
    """Why the logs cannot continue from the checkpoint `state` describes, None when they can: each log holds at
    least the checkpoint's rows, the last of them logged at the checkpoint's step, and after them only rows of later
    steps (what a run killed between writing its logs and its state.json logged past its last checkpoint: dropped
    on resume, and redone)."""
    for name, rows, count in (("curve.csv", curve, state.curve_rows), ("eval.csv", evals, state.eval_rows)):
        if len(rows) < count:
            return f"{name} holds {len(rows)} rows, fewer than the {count} the checkpoint counts"
        steps = [_step(row) for row in rows]
        if count and steps[count - 1] != state.num_timesteps:
            return (f"row {count} of {name} is at step {steps[count - 1]}, not at the checkpoint's step "
                    f"{state.num_timesteps}")
        if any(step is None or step <= state.num_timesteps for step in steps[count:]):
            return f"{name} holds rows after the checkpoint's {count} that are not of later steps"
    return None


def _step(row: dict[str, Any]) -> int | None:
    """The `timesteps` of a log row as an int, None if it is not a whole number."""
    value: Any = row.get("timesteps")  # whatever the CSV held
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return int(number) if number.is_integer() else None


def _recover_state(out_dir: Path) -> CheckpointState | None:
    """With state.json gone, the newest checkpoint that the logs continue (its own header records its counters);
    None if checkpoints/ holds no checkpoint. Never deletes anything.

    :raises CheckpointError: checkpoints are there but none can be continued consistently.
    """
    directory = out_dir / "checkpoints"
    named = sorted(((int(m.group(1)), path) for path in directory.glob("step_*.zip")
                    if (m := CHECKPOINT_NAME.match(path.name))), reverse=True)
    if not named:
        return None
    curve, evals = _read_log(out_dir, "curve.csv"), _read_log(out_dir, "eval.csv")
    reasons = []
    for _, path in named:
        try:
            header = read_checkpoint_header(path)
            counters = RunCounters.model_validate(header.run)
        except (CheckpointError, ValidationError) as exc:
            reasons.append(f"{path.name}: {' '.join(str(exc).split())[:200]}")
            continue
        state = CheckpointState(num_timesteps=header.num_timesteps, checkpoint=path.name, **counters.model_dump())
        problem = _logs_mismatch(state, curve, evals)
        if problem is None:
            return state
        reasons.append(f"{path.name}: {problem}")
    raise CheckpointError(
        f"{directory / 'state.json'} is missing and no checkpoint there can be continued consistently "
        f"({'; '.join(reasons)}); move {directory} aside to restart the run from step 0"
    )


@dataclass
class ResumePoint:
    """Where a run continues: its state, the checkpoint file it names with that file's header, and the logs."""

    state: CheckpointState
    checkpoint: Path
    header: CheckpointHeader
    curve: list[dict[str, Any]]
    evals: list[dict[str, Any]]


def resume_point(out_dir: Path) -> ResumePoint | None:
    """Where to continue the run in `out_dir` from, None if it has no checkpoint. state.json, the checkpoint it
    names and the logs are cross-checked: the same step and counters in state.json and in the checkpoint's own
    header, and logs that continue from it (`_logs_mismatch`).

    :raises CheckpointError: the state is invalid, names a missing or unreadable checkpoint, or one whose counters
        or logs disagree with it (nothing is truncated or deleted: the message says what to do).
    """
    state_file = out_dir / "checkpoints" / "state.json"
    state = _read_state(state_file) if state_file.exists() or state_file.is_symlink() else _recover_state(out_dir)
    if state is None:
        return None
    checkpoint = out_dir / "checkpoints" / state.checkpoint
    if not checkpoint.is_file():
        raise CheckpointError(f"{state_file} names {state.checkpoint}, which is missing; delete "
                              f"{checkpoint.parent} to restart the run")
    header = read_checkpoint_header(checkpoint)
    if header.num_timesteps != state.num_timesteps:
        raise CheckpointError(f"{checkpoint} (step {header.num_timesteps}) does not match {state_file} "
                              f"(step {state.num_timesteps}); delete both to restart")
    try:
        own = RunCounters.model_validate(header.run)
    except ValidationError as exc:
        raise CheckpointError(f"{checkpoint}: invalid run counters: {validation_message(exc)}") from None
    recorded = RunCounters.model_validate(state.model_dump(include=set(RunCounters.model_fields)))
    if own != recorded:
        differ = [key for key in RunCounters.model_fields if getattr(own, key) != getattr(recorded, key)]
        raise CheckpointError(
            f"{state_file} does not match {checkpoint}: " + ", ".join(
                f"{key} {getattr(recorded, key)} vs the checkpoint's {getattr(own, key)}" for key in differ)
            + f"; move {checkpoint.parent} aside to restart the run")
    curve, evals = _read_log(out_dir, "curve.csv"), _read_log(out_dir, "eval.csv")
    problem = _logs_mismatch(state, curve, evals)
    if problem is not None:
        raise CheckpointError(f"the logs of {out_dir} do not continue {checkpoint} ({problem}); they cannot be "
                              f"continued consistently: move {out_dir} aside to restart the run")
    return ResumePoint(state, checkpoint, header, curve, evals)


def resume_step(out_dir: str | Path) -> int:
    """The step `train(..., resume=True)` would continue the run in `out_dir` from (0: it has no checkpoint yet).

    :raises CheckpointError: its checkpoint cannot be continued (as `train` would raise).
    """
    point = resume_point(Path(out_dir))
    return 0 if point is None else point.state.num_timesteps


def check_run_links(out_dir: str | Path) -> None:
    """Refuse a run directory holding a symbolic link anywhere (checkpoints/, tb/, a log, a lock): a training never
    reads, writes or deletes through one.

    :raises UnsafePathError: naming the first link.
    """
    links = find_links(out_dir)
    if links:
        more = f" (and {len(links) - 1} more)" if len(links) > 1 else ""
        raise UnsafePathError(f"{links[0]} is a symbolic link{more}; socnav never follows a link inside a run "
                              "directory: remove it, or move the run aside (--force, train(force=True))")


def can_resume(out_dir: str | Path) -> bool:
    """Whether `train(..., resume=True)` can continue the run in `out_dir` (or start it: no checkpoint there): no
    symbolic link inside, a readable run.json if there is one, and a consistent checkpoint if there is one."""
    out_dir = Path(out_dir)
    try:
        check_run_links(out_dir)
        if (out_dir / "run.json").exists():
            read_run_info(out_dir)
        point = resume_point(out_dir)
        if point is not None:  # the tensors too: a checkpoint that would fail on load is redone, not kept failing
            verify_checkpoint(point.checkpoint)
    except (CheckpointError, ConfigError, OSError):
        return False
    return True


def move_run_aside(out_dir: str | Path) -> Path:
    """Rename the run directory `out_dir` to ``<out_dir>.old-<UTC timestamp>`` (never deleting it); returns the new
    path. Holds its lock while renaming, so a training still working in it is never moved.

    :raises RunDirectoryBusy: a training holds the directory.
    """
    out_dir = Path(out_dir)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target = out_dir.with_name(f"{out_dir.name}.old-{stamp}")
    suffix = 1
    while target.exists():
        target = out_dir.with_name(f"{out_dir.name}.old-{stamp}-{suffix}")
        suffix += 1
    with file_lock(out_dir / ".lock", blocking=False) as locked:
        if not locked:
            raise RunDirectoryBusy(f"another socnav train is working in {out_dir} (its .lock is held)")
        out_dir.rename(target)
    return target


def write_run_json(out_dir: Path, info: dict[str, Any]) -> None:
    write_text_atomic(out_dir / "run.json", json.dumps(info, indent=2, sort_keys=True, default=str))


def holds_files(out_dir: Path) -> bool:
    """Whether `out_dir` holds anything besides a lock file (a lock alone is no run: nothing to move aside)."""
    return out_dir.is_dir() and any(entry.name != ".lock" for entry in out_dir.iterdir())


#: What makes a run the same run: a directory resumed with other values holds another run.
_RUN_IDENTITY = ("env_config", "algo", "algo_config", "seed")


def _same_value(key: str, recorded: Any, asked: Any) -> bool:
    """Whether run.json's `key` is the value asked (configs compared once validated, as a checkpoint's are)."""
    try:
        if key == "env_config":
            return load_config(recorded) == load_config(asked)
        if key == "algo_config":
            return AlgoConfig.model_validate(recorded) == AlgoConfig.model_validate(asked)
    except (ConfigError, ValidationError, TypeError):
        return False
    return type(recorded) is type(asked) and recorded == asked


def check_same_run(out_dir: Path, info: dict[str, Any]) -> None:
    """With `resume`, the run.json in `out_dir` (if any) must record the run asked for, or `train` would continue or
    overwrite another run.

    :raises CheckpointError: run.json is unreadable or records another run (the differing fields are named).
    """
    if not (out_dir / "run.json").exists():
        return
    try:
        recorded = _read_run_json(out_dir / "run.json")
    except (OSError, UntrustedInputError) as exc:
        raise CheckpointError(f"{exc}; move {out_dir} aside to start afresh") from None
    if not isinstance(recorded, dict):
        raise CheckpointError(f"{out_dir / 'run.json'} is not a run's record; move {out_dir} aside to start afresh")
    differ = [key for key in _RUN_IDENTITY if not _same_value(key, recorded.get(key), info[key])]
    if differ:
        raise CheckpointError(f"{out_dir} holds another run (its run.json's {', '.join(differ)} differ from the "
                              "ones asked); resume it with its own settings (socnav train --resume), or move it "
                              "aside with force=True (--force)")

