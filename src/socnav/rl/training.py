"""Training runs: one preset on one scenario, with progress, TensorBoard, periodic evaluation and resumable checkpoints.
`train(...)` is what `socnav train` and the experiment engine call; everything it writes lands atomically in its run
directory (`socnav.rl.run_directory`: what each file holds, and how a run is resumed).

Seeds: training environment i of run seed s starts from seed ``TRAIN_SEED_BASE + s * 4096 + i`` and the periodic
evaluation plays episodes ``VALIDATION_SEED_BASE + k``; both are far from the small seeds (0, 1, ...) that
`socnav evaluate` and the experiments use for test episodes, so training, validation and test never share an episode.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from stable_baselines3.common.callbacks import BaseCallback

from socnav.config import ConfigError, ConfigLike, EnvConfig, load_config
from socnav.envs.rollout import rollout_episodes, summarize
from socnav.envs.vec_env import make_vec_env
from socnav.io import (
    file_lock,
    remove_stale_temporaries,
    write_table_atomic,
    write_text_atomic,
)
from socnav.rl.checkpoints import CheckpointError, load_checkpoint, save_checkpoint
from socnav.rl.odv_ppo import ODVPPO
from socnav.rl.persistence import save_policy
from socnav.rl.policy import NonFiniteError
from socnav.rl.presets import AlgoConfig, make_model, resolve_config
from socnav.rl.run_directory import (
    CHECKPOINT_NAME,
    CURVE_COLUMNS,
    EVAL_COLUMNS,
    MAX_SEED,
    WALL_EVAL_COLUMNS,
    CheckpointState,
    RunCounters,
    RunDirectoryBusy,
    RunDirectoryExists,
    RunInfo,
    TrainResult,
    can_resume,
    check_run_links,
    check_same_run,
    finished_result,
    holds_files,
    move_run_aside,
    read_run_info,
    resume_point,
    resume_step,
    write_run_json,
)
from socnav.sim.metrics import DEFAULT_METRICS
from socnav.sim.walls import has_walls

__all__ = ["CheckpointError", "CheckpointState", "RunDirectoryBusy", "RunDirectoryExists", "RunInfo", "TrainResult",
           "TrainingInterrupted", "can_resume", "check_run_links", "finished_result", "move_run_aside", "read_run_info",
           "resume", "resume_step", "train", "training_env_seed"]


TRAIN_SEED_BASE = 2**40


VALIDATION_SEED_BASE = 2**41


RESUME_SEED_BASE = 2**42




class TrainingInterrupted(RuntimeError):
    """Training stopped early (non-finite values); the last checkpoint in the run directory is intact."""


def training_env_seed(seed: int) -> int:
    """Seed of training environment 0 of run `seed` (environment i gets this + i), in [2**40, 2**41)."""
    return TRAIN_SEED_BASE + seed * 4096


def _resume_seeds(seed: int, step: int) -> tuple[int, int]:
    """(environment seed, torch seed) of run `seed` resumed at `step`: hashed, environments in [2**42, 2**43)."""
    env_hash, torch_hash = np.random.SeedSequence([seed, step]).generate_state(2, np.uint64)
    return RESUME_SEED_BASE + int(env_hash >> np.uint64(22)), int(torch_hash >> np.uint64(33))


class _CheckpointOnInterrupt:
    """Ctrl-C while a run learns: the first one asks for a checkpoint at the next rollout boundary (the only point
    where the model has learned from every step it counts, so `--resume` continues exactly there), after which the
    run stops with KeyboardInterrupt; a second one stops at once (the steps since the last checkpoint are lost).

    Without it a Ctrl-C before the first scheduled checkpoint lost every step (12,288 in 31 s). Installed only in
    the main thread over Python's default handler: a caller's own SIGINT handling (or an ignored SIGINT) is left
    alone.
    """

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None

    def __enter__(self) -> _CheckpointOnInterrupt:
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, self._previous)  # the next Ctrl-C raises KeyboardInterrupt at once
        print("\ninterrupted: saving a checkpoint when the current rollout ends, then stopping (Ctrl-C again to "
              "stop now and lose the steps since the last checkpoint)", file=sys.stderr, flush=True)

    def __exit__(self, *exc: Any) -> None:
        if self._previous is not None and not self.requested:
            signal.signal(signal.SIGINT, self._previous)


class _RunMonitor(BaseCallback):
    """Records the training curve, evaluates and checkpoints on schedule, and drives the progress display."""

    model: ODVPPO  # the model whose learn() runs the callback

    def __init__(self, run: _Run, interrupt: _CheckpointOnInterrupt | None = None) -> None:
        super().__init__()
        self.run = run
        self.interrupt = interrupt

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # Between two updates: the model has learned from every step counted in num_timesteps, so a checkpoint
        # taken here resumes exactly where it stands.
        if self.interrupt is not None and self.interrupt.requested:
            if self.run.checkpoint_step != int(self.model.num_timesteps):  # no evaluation: the user waits
                self.run.save_checkpoint(self.model)
            raise KeyboardInterrupt
        self.run.maybe_checkpoint(self.model)

    def _on_rollout_end(self) -> None:
        self.run.record_curve(self.model)


class _Run:
    """State of one training run directory."""

    def __init__(self, out_dir: Path, env_config: EnvConfig, algo: str, algo_config: AlgoConfig, seed: int,
                 timesteps: int, eval_every: int, eval_episodes: int) -> None:
        self.out_dir = out_dir
        self.env_config = env_config
        # a world with walls also reports the episodes that ended against a wall (apart from collisions with people)
        self.eval_columns = EVAL_COLUMNS + (WALL_EVAL_COLUMNS if has_walls(env_config) else [])
        self.algo = algo
        self.algo_config = algo_config
        self.seed = seed
        self.timesteps = timesteps
        self.eval_every = eval_every
        self.eval_episodes = eval_episodes
        self.progress: Callable[[int, float | None], None] | None = None  # set when training starts
        self.curve: list[dict[str, float]] = []
        self.evals: list[dict[str, float]] = []
        self.elapsed_before = 0.0  # wall time of earlier (interrupted) sessions of this run
        self.started = time.perf_counter()
        self.next_eval = eval_every
        self.checkpoint = self.checkpoint_dir / "step_0.zip"  # the checkpoint state.json names, once there is one
        self.checkpoint_step: int | None = None  # the step of the checkpoint saved or restored (None: none yet)

    @property
    def checkpoint_dir(self) -> Path:
        return self.out_dir / "checkpoints"

    @property
    def checkpoint_state(self) -> Path:
        return self.out_dir / "checkpoints" / "state.json"

    def wall_time(self) -> float:
        return self.elapsed_before + time.perf_counter() - self.started

    # ---- logs ----
    def record_curve(self, model: ODVPPO) -> None:
        episodes = list(model.ep_info_buffer or ())  # (None only before learn() sets the buffers up)
        successes = list(model.ep_success_buffer or ())
        timesteps = int(model.num_timesteps)
        row = {
            "timesteps": timesteps,
            "wall_time_s": self.wall_time(),
            "ep_rew_mean": float(np.mean([e["r"] for e in episodes])) if episodes else float("nan"),
            "ep_len_mean": float(np.mean([e["l"] for e in episodes])) if episodes else float("nan"),
            "success_rate": float(np.mean(successes)) if successes else float("nan"),
        }
        self.curve.append(row)
        if self.progress is not None:
            self.progress(timesteps, row["success_rate"])

    def evaluate(self, model: ODVPPO, log: bool = True) -> dict[str, float]:
        """Validation episodes at the model's current step; `log=False` skips TensorBoard (no logger before
        `learn`, e.g. when resuming a run that had already reached its total)."""
        records = rollout_episodes(model.policy, self.env_config, self.eval_episodes, seed=VALIDATION_SEED_BASE,
                                   n_envs=min(self.eval_episodes, 64))
        metrics = summarize(records, metrics=DEFAULT_METRICS + tuple(self.eval_columns[len(EVAL_COLUMNS):]))
        row = {"timesteps": int(model.num_timesteps), "wall_time_s": self.wall_time(),
               **{key: metrics[key] for key in self.eval_columns[2:]}}
        if self.evals and int(self.evals[-1]["timesteps"]) == row["timesteps"]:
            self.evals[-1] = row  # the same step evaluated again (a finished run resumed): one row, not two
        else:
            self.evals.append(row)
        if log:
            for key in ("goal_pct", "collision_pct", "timeout_pct", "return_mean"):
                model.logger.record(f"eval/{key}", metrics[key])
            model.logger.dump(model.num_timesteps)
        return metrics

    def write_logs(self) -> None:
        write_table_atomic(pd.DataFrame(self.curve, columns=CURVE_COLUMNS), self.out_dir / "curve.csv")
        write_table_atomic(pd.DataFrame(self.evals, columns=self.eval_columns), self.out_dir / "eval.csv")

    # ---- checkpoints ----
    def maybe_checkpoint(self, model: ODVPPO) -> None:
        if model.num_timesteps >= self.next_eval:
            while self.next_eval <= model.num_timesteps:
                self.next_eval += self.eval_every
            self.evaluate(model)
            self.save_checkpoint(model)

    def save_checkpoint(self, model: ODVPPO) -> None:
        """A new step-named checkpoint (model, optimizer, counters), the logs, then the state naming both (written
        last), then the older checkpoints go: until the state is replaced, the previous state still names an intact
        checkpoint."""
        checkpoint = self.checkpoint_dir / f"step_{int(model.num_timesteps)}.zip"
        counters = RunCounters(wall_time_s=self.wall_time(), next_eval=self.next_eval, curve_rows=len(self.curve),
                               eval_rows=len(self.evals))
        save_checkpoint(model, checkpoint, self.env_config.model_dump(mode="json"), self.seed, counters.model_dump())
        self.write_logs()
        state = CheckpointState(num_timesteps=int(model.num_timesteps), checkpoint=checkpoint.name,
                                **counters.model_dump())
        write_text_atomic(self.checkpoint_state, state.model_dump_json(indent=2))
        self.checkpoint = checkpoint
        self.checkpoint_step = int(model.num_timesteps)
        self._remove_checkpoints(keep=checkpoint.name)

    def _remove_checkpoints(self, keep: str | None = None) -> None:
        """Delete this run's step_N.zip files (other files in checkpoints/ are not ours to delete)."""
        for old in self.checkpoint_dir.glob("step_*.zip"):
            if CHECKPOINT_NAME.match(old.name) and old.name != keep:
                old.unlink(missing_ok=True)

    def discard_checkpoints(self) -> None:
        """Forget any checkpoint in the run directory (state first: it is what names a zip)."""
        self.checkpoint_state.unlink(missing_ok=True)
        self._remove_checkpoints()

    def restore(self) -> CheckpointState | None:
        """Logs and counters of the last checkpoint (rows logged after it are dropped: they will be redone); None
        when the run has no checkpoint."""
        point = resume_point(self.out_dir)
        if point is None:
            return None
        state, self.checkpoint, header = point.state, point.checkpoint, point.header
        self.checkpoint_step = state.num_timesteps
        asked = {"algo": self.algo, "algo_config": self.algo_config, "seed": self.seed, "env_config": self.env_config}
        try:
            found = {"algo": header.algo, "algo_config": header.algo_config, "seed": header.seed,
                     "env_config": load_config(header.env_config)}
        except ConfigError as exc:
            raise CheckpointError(f"{self.checkpoint}: invalid env_config: {' '.join(str(exc).split())}") from None
        differ = [key for key in asked if asked[key] != found[key]]
        if differ:  # checked before anything is built from the header
            raise CheckpointError(f"{self.checkpoint} belongs to another run (its {', '.join(differ)} differ from "
                                  "run.json); delete checkpoints/ or choose another directory")
        # resume_point checked that rows past the checkpoint's are of later steps: dropped here, they are redone
        self.curve = point.curve[: state.curve_rows]
        self.evals = point.evals[: state.eval_rows]
        self.elapsed_before = state.wall_time_s
        self.next_eval = state.next_eval
        return state


def train(
    config: ConfigLike,
    algo: str,
    seed: int,
    timesteps: int,
    out_dir: str | Path,
    n_envs: int = 16,
    overrides: dict[str, Any] | None = None,
    eval_every: int | None = None,
    eval_episodes: int = 50,
    resume: bool = False,
    progress: bool | Callable[[int, float | None], None] = False,
    tensorboard: bool = True,
    verbose: int = 0,
    force: bool = False,
) -> TrainResult:
    """Train preset `algo` for `timesteps` environment steps on the env `config`; write everything to `out_dir`.

    :param config: env config (EnvConfig, partial dict or YAML path), e.g.
        ``{"scenario": "position_swap", "n_humans": 1}``.
    :param algo: one of ``socnav.rl.ALGOS``; `overrides` replaces any of its hyperparameters (AlgoConfig fields).
    :param eval_every: timesteps between evaluations + checkpoints (default: a tenth of the run, >= one rollout).
    :param eval_episodes: validation episodes per periodic evaluation (seeds disjoint from training and test).
    :param resume: continue the run in `out_dir` from its checkpoint if there is one (else start it); the run
        reaches the same total `timesteps`, and its curve/eval logs continue from the checkpoint. The run there
        must be this one (same env config, algorithm, hyperparameters and seed). Checkpoints are read safely
        (nothing unpickled).
    :param force: without `resume`, an `out_dir` that already holds files is moved aside to
        ``<out_dir>.old-<timestamp>`` (never deleted) and the run starts afresh; without `force` it is refused.
    :param progress: True for a rich progress bar with the live success rate, or a callable
        ``progress(timesteps_done, success_rate)``.
    :raises TrainingInterrupted: a NaN/Inf in a loss or an output; the message names the step and the tensor.
    :raises RunDirectoryBusy: another training holds `out_dir` (its ``.lock``).
    :raises RunDirectoryExists: `out_dir` holds files and neither `resume` nor `force` is given.
    :raises CheckpointError: `resume` found another run, or a checkpoint it cannot continue from (the message says
        why).
    :raises UnsafePathError: `out_dir` holds a symbolic link (never followed; the message names it).
    """
    if timesteps < 1:
        raise ValueError(f"timesteps must be >= 1, got {timesteps}")
    if not 0 <= seed < MAX_SEED:
        raise ValueError(f"seed must lie in [0, {MAX_SEED}), got {seed}")
    out_dir = Path(out_dir)
    # Validated once, here: an EnvConfig passes through as a copy and the resolved AlgoConfig goes down to make_model.
    env_config = load_config(config)
    algo_config = resolve_config(algo, overrides)  # validates before any work starts
    rollout_size = algo_config.n_steps * n_envs
    eval_every = max(int(eval_every or timesteps // 10), rollout_size)
    if resume and force:
        raise ValueError("resume=True continues the run in out_dir and force=True moves it aside: pass one of them")
    if out_dir.exists() and not out_dir.is_dir():
        raise NotADirectoryError(f"{out_dir} is a file, not a run directory")
    if not resume and holds_files(out_dir):
        if not force:
            raise RunDirectoryExists(
                f"{out_dir} already holds files (an earlier run?); continue it with resume=True (socnav train "
                f"--resume {out_dir}), or pass force=True (--force) to move it aside to {out_dir}.old-<timestamp> "
                "and start afresh")
        move_run_aside(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if (out_dir / ".lock").is_symlink():
        check_run_links(out_dir)  # file_lock refuses it too; this names the way out
    with file_lock(out_dir / ".lock", blocking=False) as locked:
        if not locked:
            raise RunDirectoryBusy(f"another socnav train is working in {out_dir} (its .lock is held)")
        # Nothing is read, written or deleted through a link planted in the run (checkpoints/, tb/, a log).
        check_run_links(out_dir)
        remove_stale_temporaries(out_dir)  # a killed run's half-written files; no other writer while we hold the lock
        info = {"env_config": env_config.model_dump(mode="json"), "algo": algo,
                "algo_config": algo_config.model_dump(mode="json"), "overrides": overrides or {}, "seed": seed,
                "timesteps": timesteps, "n_envs": n_envs, "eval_every": eval_every, "eval_episodes": eval_episodes}
        run = _Run(out_dir, env_config, algo, algo_config, seed, timesteps, eval_every, eval_episodes)
        state = run.restore() if resume else None  # a checkpoint of another run is refused there
        if resume and state is None:  # no checkpoint yet: run.json says whose run the directory holds
            check_same_run(out_dir, info)
        return _train_locked(run, info, state, progress, tensorboard, verbose)


def resume(
    out_dir: str | Path,
    progress: bool | Callable[[int, float | None], None] = False,
    tensorboard: bool = True,
    verbose: int = 0,
) -> TrainResult:
    """Continue the training run in `out_dir` from its last checkpoint (or start it afresh when it has none), with
    what its run.json asked: `train(..., resume=True)` with the run's own config, algorithm, seed and budget.

    A run that already finished is evaluated and saved again without training (`finished_result` tells first).

    :raises ConfigError: run.json is missing or invalid (the message names the field); else as `train`.
    """
    info = read_run_info(out_dir)
    return train(info.env_config, info.algo, info.seed, info.timesteps, out_dir, n_envs=info.n_envs,
                 overrides=info.overrides, eval_every=info.eval_every, eval_episodes=info.eval_episodes, resume=True,
                 progress=progress, tensorboard=tensorboard, verbose=verbose)


def _train_locked(run: _Run, info: dict[str, Any], state: CheckpointState | None,
                  progress: bool | Callable[[int, float | None], None], tensorboard: bool,
                  verbose: int) -> TrainResult:
    """`train` once the run directory is locked and its checkpoint (if resuming) validated."""
    bar, run.progress = _progress_display(progress, run.timesteps)
    env = _smoothed(make_vec_env(run.env_config, n_envs=info["n_envs"]), run.algo_config)
    model = _start_model(run, state, env, str(run.out_dir / "tb") if tensorboard else None, verbose)
    remaining = run.timesteps - int(model.num_timesteps)
    write_run_json(run.out_dir, {**info, "status": "running"})

    try:
        with bar, _CheckpointOnInterrupt() as interrupt:
            if remaining > 0:
                model.learn(remaining, callback=_RunMonitor(run, interrupt), reset_num_timesteps=state is None,
                            tb_log_name="run")
    except NonFiniteError as exc:
        write_run_json(run.out_dir, {**info, "status": "failed", "error": str(exc)})
        raise TrainingInterrupted(
            f"training stopped: {exc}. The last good checkpoint is {run.checkpoint} (resume with --resume)."
        ) from None
    finally:
        env.close()
    # without steps to learn (a finished run resumed) there is no logger for TensorBoard
    return _finish(run, model, info, state, log=remaining > 0)


def _smoothed(env: Any, config: AlgoConfig) -> Any:
    """`env` behind `socnav.rl.smoothing.SmoothnessPenalty` when the run's config asks for smooth driving."""
    if not (config.turn_penalty or config.action_change_penalty):
        return env
    from socnav.rl.smoothing import SmoothnessPenalty

    return SmoothnessPenalty(env, config.turn_penalty, config.action_change_penalty)


def _start_model(run: _Run, state: CheckpointState | None, env: Any, tensorboard_log: str | None,
                 verbose: int) -> ODVPPO:
    """A fresh model, or the one of the checkpoint `state` names, with the training environments seeded."""
    if state is None:
        # A fresh start: without `resume`, an earlier run's checkpoint left in out_dir goes, or a later `--resume`
        # would continue *that* run under this run's run.json (with `resume` we only get here when there is none).
        run.discard_checkpoints()
        # the config `train` resolved (and checked against a checkpoint), not a second resolution of the overrides
        model = make_model(run.algo, env, run.seed, tensorboard_log=tensorboard_log, verbose=verbose,
                           algo_config=run.algo_config)
        env.seed(training_env_seed(run.seed))  # after make_model, whose set_random_seed seeded the env with `seed`
        return model
    try:
        model, _ = load_checkpoint(run.checkpoint, env, tensorboard_log=tensorboard_log, verbose=verbose)
    except BaseException:
        env.close()
        raise
    # The environments restart and torch is reseeded from (seed, step), so a resumed run is reproducible from its
    # checkpoint (it is not bit-identical to an uninterrupted run, whose environments were mid-episode) and never
    # replays another run's training episodes.
    env_seed, torch_seed = _resume_seeds(run.seed, int(model.num_timesteps))
    model.set_random_seed(torch_seed)
    env.seed(env_seed)  # applied at the next reset
    return model


def _finish(run: _Run, model: ODVPPO, info: dict[str, Any], state: CheckpointState | None,
            log: bool) -> TrainResult:
    """The final validation and checkpoint, the policy file, and run.json marked complete."""
    final_eval = run.evaluate(model, log=log)
    run.save_checkpoint(model)
    metadata = {"algo": run.algo, "algo_config": run.algo_config.model_dump(mode="json"),
                "env_config": run.env_config.model_dump(mode="json"), "seed": run.seed,
                "timesteps": int(model.num_timesteps)}
    model_path = save_policy(model.policy, run.out_dir / "model.zip", metadata)
    result = TrainResult(model_path, int(model.num_timesteps), run.wall_time(), final_eval,
                         resumed_from=0 if state is None else state.num_timesteps)
    write_run_json(run.out_dir, {**info, "status": "complete", "wall_time_s": result.wall_time_s,
                                  "final_eval": final_eval, "num_timesteps": result.timesteps})
    return result


class _NoDisplay:
    """The progress display of a run without one."""

    def __enter__(self) -> _NoDisplay:
        return self

    def __exit__(self, *exc: Any) -> None:
        return None


def _progress_display(progress: bool | Callable[[int, float | None], None],
                      total: int) -> tuple[AbstractContextManager[Any], Callable[[int, float | None], None] | None]:
    """A rich progress bar showing timesteps and the live success rate (over the last 100 episodes)."""
    if callable(progress):
        return _NoDisplay(), progress
    if not progress:
        return _NoDisplay(), None
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    bar = Progress(TextColumn("training"), BarColumn(), TextColumn("{task.completed:,.0f}/{task.total:,.0f} steps"),
                   TextColumn("success {task.fields[success]}"), TimeElapsedColumn(), TimeRemainingColumn())
    task = bar.add_task("train", total=total, success="  -  ")

    def update(done: int, success: float | None) -> None:
        shown = "  -  " if success is None or np.isnan(success) else f"{100 * success:5.1f}%"
        bar.update(task, completed=min(done, total), success=shown)

    return bar, update

