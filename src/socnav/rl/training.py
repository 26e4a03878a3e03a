"""Training runs: one preset on one scenario, with progress, TensorBoard, periodic evaluation and resumable checkpoints.
`train(...)` is what `socnav train` and the experiment engine call; everything it writes lands atomically in `out_dir`.

Run directory::

    run.json                 what was asked (env config, algo, overrides, seed, timesteps) and the status
    checkpoints/step_N.zip   SB3 checkpoint (optimizer state included); checkpoints/state.json names it (written
                             last: a kill at any moment leaves a state naming an intact zip and its log rows)
    curve.csv                training curve: timesteps, wall_time_s, ep_rew_mean, ep_len_mean, success_rate
    eval.csv                 periodic evaluation on validation seeds (goal/collision/timeout %, PV, return)
    model.zip                the final policy in socnav's safe format (`socnav.load_policy`)
    tb/                      TensorBoard logs (SB3's, plus eval/*)

Seeds: training environment i of run seed s starts from seed ``TRAIN_SEED_BASE + s * 4096 + i`` and the periodic
evaluation plays episodes ``VALIDATION_SEED_BASE + k``; both are far from the small seeds (0, 1, ...) that
`socnav evaluate` and the experiments use for test episodes, so training, validation and test never share an episode.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from socnav.config import ConfigLike, load_config
from socnav.envs.rollout import rollout_episodes, summarize
from socnav.envs.vec_env import make_vec_env
from socnav.io import atomic_path, read_table, write_table_atomic, write_text_atomic
from socnav.rl.odv_ppo import ODVPPO
from socnav.rl.persistence import save_policy
from socnav.rl.policy import NonFiniteError
from socnav.rl.presets import make_model, resolve_config

TRAIN_SEED_BASE = 2**40
VALIDATION_SEED_BASE = 2**41
RESUME_SEED_BASE = 2**42
MAX_SEED = 2**28  # run seeds below this keep training environments (2**40 + seed * 4096 + i) under 2**41
CURVE_COLUMNS = ["timesteps", "wall_time_s", "ep_rew_mean", "ep_len_mean", "success_rate"]
EVAL_COLUMNS = ["timesteps", "wall_time_s", "episodes", "goal_pct", "collision_pct", "timeout_pct", "pv",
                "return_mean", "return_std"]

__all__ = ["CheckpointError", "TrainResult", "TrainingInterrupted", "train", "training_env_seed"]


class TrainingInterrupted(RuntimeError):
    """Training stopped early (non-finite values); the last checkpoint in the run directory is intact."""


class CheckpointError(RuntimeError):
    """`resume=True` found a checkpoint it cannot continue from (unreadable, or not the step state.json names)."""


@dataclass
class TrainResult:
    model_path: Path
    timesteps: int
    wall_time_s: float
    final_eval: dict[str, float] = field(default_factory=dict)


def training_env_seed(seed: int) -> int:
    """Seed of training environment 0 of run `seed` (environment i gets this + i), in [2**40, 2**41)."""
    return TRAIN_SEED_BASE + seed * 4096


def _resume_seeds(seed: int, step: int) -> tuple[int, int]:
    """(environment seed, torch seed) of run `seed` resumed at `step`: hashed, environments in [2**42, 2**43)."""
    env_hash, torch_hash = np.random.SeedSequence([seed, step]).generate_state(2, np.uint64)
    return RESUME_SEED_BASE + int(env_hash >> np.uint64(22)), int(torch_hash >> np.uint64(33))


class _RunMonitor(BaseCallback):
    """Records the training curve, evaluates and checkpoints on schedule, and drives the progress display."""

    def __init__(self, run: "_Run"):
        super().__init__()
        self.run = run

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # Between two updates: the model has learned from every step counted in num_timesteps, so a checkpoint
        # taken here resumes exactly where it stands.
        self.run.maybe_checkpoint(self.model)

    def _on_rollout_end(self) -> None:
        self.run.record_curve(self.model)


class _Run:
    """State of one training run directory."""

    def __init__(self, out_dir: Path, env_config: Any, algo: str, seed: int, timesteps: int, eval_every: int,
                 eval_episodes: int, progress: Callable[[int, float | None], None] | None):
        self.out_dir = out_dir
        self.env_config = env_config
        self.algo = algo
        self.seed = seed
        self.timesteps = timesteps
        self.eval_every = eval_every
        self.eval_episodes = eval_episodes
        self.progress = progress
        self.curve: list[dict[str, float]] = []
        self.evals: list[dict[str, float]] = []
        self.elapsed_before = 0.0  # wall time of earlier (interrupted) sessions of this run
        self.started = time.perf_counter()
        self.next_eval = eval_every
        self.checkpoint = self.checkpoint_dir / "step_0.zip"  # the checkpoint state.json names, once there is one

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
        episodes = list(model.ep_info_buffer)
        successes = list(model.ep_success_buffer)
        row = {
            "timesteps": int(model.num_timesteps),
            "wall_time_s": self.wall_time(),
            "ep_rew_mean": float(np.mean([e["r"] for e in episodes])) if episodes else float("nan"),
            "ep_len_mean": float(np.mean([e["l"] for e in episodes])) if episodes else float("nan"),
            "success_rate": float(np.mean(successes)) if successes else float("nan"),
        }
        self.curve.append(row)
        if self.progress is not None:
            self.progress(row["timesteps"], row["success_rate"])

    def evaluate(self, model: ODVPPO, log: bool = True) -> dict[str, float]:
        """Validation episodes at the model's current step; `log=False` skips TensorBoard (no logger before
        `learn`, e.g. when resuming a run that had already reached its total)."""
        records = rollout_episodes(model.policy, self.env_config, self.eval_episodes, seed=VALIDATION_SEED_BASE,
                                   n_envs=min(self.eval_episodes, 64))
        metrics = summarize(records)
        row = {"timesteps": int(model.num_timesteps), "wall_time_s": self.wall_time(),
               **{key: metrics[key] for key in EVAL_COLUMNS[2:]}}
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
        write_table_atomic(pd.DataFrame(self.evals, columns=EVAL_COLUMNS), self.out_dir / "eval.csv")

    # ---- checkpoints ----
    def maybe_checkpoint(self, model: ODVPPO) -> None:
        if model.num_timesteps >= self.next_eval:
            while self.next_eval <= model.num_timesteps:
                self.next_eval += self.eval_every
            self.evaluate(model)
            self.save_checkpoint(model)

    def save_checkpoint(self, model: ODVPPO) -> None:
        """A new step-named zip (model + optimizer), the logs, then the state naming both (written last), then the
        older zips go: until the state is replaced, the previous state still names an intact zip."""
        checkpoint = self.checkpoint_dir / f"step_{int(model.num_timesteps)}.zip"
        with atomic_path(checkpoint) as temporary:
            model.save(temporary)
        self.write_logs()
        state = {"num_timesteps": int(model.num_timesteps), "wall_time_s": self.wall_time(),
                 "next_eval": self.next_eval, "curve_rows": len(self.curve), "eval_rows": len(self.evals),
                 "checkpoint": checkpoint.name}
        write_text_atomic(self.checkpoint_state, json.dumps(state, indent=2))
        self.checkpoint = checkpoint
        for old in self.checkpoint_dir.glob("*.zip"):
            if old.name != checkpoint.name:
                old.unlink(missing_ok=True)

    def discard_checkpoints(self) -> None:
        """Forget any checkpoint in the run directory (state first: it is what names a zip)."""
        self.checkpoint_state.unlink(missing_ok=True)
        for old in self.checkpoint_dir.glob("*.zip"):
            old.unlink(missing_ok=True)

    def restore(self) -> dict[str, Any] | None:
        """Logs and counters of the last checkpoint (rows logged after it are dropped: they will be redone)."""
        if not self.checkpoint_state.is_file():
            return None
        try:
            state = json.loads(self.checkpoint_state.read_text())
            for key in ("num_timesteps", "next_eval", "curve_rows", "eval_rows", "wall_time_s"):
                float(state[key])
        except (ValueError, TypeError, KeyError) as exc:
            raise CheckpointError(f"{self.checkpoint_state} is unreadable ({exc}); delete {self.checkpoint_dir} "
                                  "to restart the run") from None
        self.checkpoint = self.checkpoint_dir / str(state.get("checkpoint", "latest.zip"))
        if not self.checkpoint.is_file():
            raise CheckpointError(f"{self.checkpoint_state} names {self.checkpoint.name}, which is missing; delete "
                                  f"{self.checkpoint_dir} to restart the run")
        if (self.out_dir / "curve.csv").is_file():
            self.curve = read_table(self.out_dir / "curve.csv").to_dict("records")[: state["curve_rows"]]
        if (self.out_dir / "eval.csv").is_file():
            self.evals = read_table(self.out_dir / "eval.csv").to_dict("records")[: state["eval_rows"]]
        self.elapsed_before = float(state["wall_time_s"])
        self.next_eval = int(state["next_eval"])
        return state


def _write_run_json(out_dir: Path, info: dict[str, Any]) -> None:
    write_text_atomic(out_dir / "run.json", json.dumps(info, indent=2, sort_keys=True, default=str))


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
) -> TrainResult:
    """Train preset `algo` for `timesteps` environment steps on the env `config`; write everything to `out_dir`.

    :param config: env config (EnvConfig, partial dict or YAML path), e.g. ``{"scenario": "position_swap", "n_humans": 1}``.
    :param algo: one of ``socnav.rl.ALGOS``; `overrides` replaces any of its hyperparameters (AlgoConfig fields).
    :param eval_every: timesteps between evaluations + checkpoints (default: a tenth of the run, >= one rollout).
    :param eval_episodes: validation episodes per periodic evaluation (seeds disjoint from training and test).
    :param resume: continue from ``out_dir/checkpoints`` if a checkpoint is there (else start fresh); the run
        reaches the same total `timesteps`, and its curve/eval logs continue from the checkpoint.
    :param progress: True for a rich progress bar with the live success rate, or a callable
        ``progress(timesteps_done, success_rate)``.
    :raises TrainingInterrupted: a NaN/Inf in a loss or an output; the message names the step and the tensor.
    """
    if timesteps < 1:
        raise ValueError(f"timesteps must be >= 1, got {timesteps}")
    if not 0 <= seed < MAX_SEED:
        raise ValueError(f"seed must lie in [0, {MAX_SEED}), got {seed}")
    out_dir = Path(out_dir)
    env_config = load_config(config)
    algo_config = resolve_config(algo, overrides)  # validates before any work starts
    rollout_size = algo_config.n_steps * n_envs
    eval_every = max(int(eval_every or timesteps // 10), rollout_size)
    out_dir.mkdir(parents=True, exist_ok=True)
    info = {"env_config": env_config.model_dump(mode="json"), "algo": algo, "algo_config": algo_config.model_dump(mode="json"),
            "overrides": overrides or {}, "seed": seed, "timesteps": timesteps, "n_envs": n_envs,
            "eval_every": eval_every, "eval_episodes": eval_episodes}

    bar, callback_progress = _progress_display(progress, timesteps)
    run = _Run(out_dir, env_config, algo, seed, timesteps, eval_every, eval_episodes, callback_progress)
    env = make_vec_env(env_config, n_envs=n_envs)
    tensorboard_log = str(out_dir / "tb") if tensorboard else None
    state = run.restore() if resume else None
    if state is None:
        # A fresh start: drop an earlier run's checkpoint left in out_dir, or a `--resume` after a kill before this
        # run's first checkpoint would continue *that* run under this run's run.json (state first: it names the zip).
        run.discard_checkpoints()
    if state is not None:
        if algo_config.torch_threads is not None:  # as make_model does for a fresh run
            th.set_num_threads(algo_config.torch_threads)
        try:
            model = ODVPPO.load(run.checkpoint, env=env, device=algo_config.device, tensorboard_log=tensorboard_log)
        except Exception as exc:  # SB3 raises many types for a torn or foreign zip
            env.close()
            raise CheckpointError(f"{run.checkpoint} cannot be loaded ({type(exc).__name__}: {exc}); delete "
                                  f"{run.checkpoint.parent} to restart the run") from exc
        if model.num_timesteps != state["num_timesteps"]:
            env.close()
            raise CheckpointError(f"{run.checkpoint} (step {model.num_timesteps}) does not match "
                                  f"{run.checkpoint_state} (step {state['num_timesteps']}); delete both to restart")
        model.algo_name, model.algo_config = algo, algo_config.model_dump(mode="json")  # type: ignore[attr-defined]
        # SB3's load does not reseed torch, and the environments restart: seed both from (seed, step), so a resumed
        # run is reproducible from its checkpoint (it is not bit-identical to an uninterrupted run, whose
        # environments were mid-episode) and never replays another run's training episodes.
        env_seed, torch_seed = _resume_seeds(seed, int(model.num_timesteps))
        model.set_random_seed(torch_seed)
        env.seed(env_seed)  # applied at the next reset
    else:
        model = make_model(algo, env, seed, overrides=overrides, tensorboard_log=tensorboard_log, verbose=verbose)
        env.seed(training_env_seed(seed))  # after make_model, whose set_random_seed seeded the env with `seed`
    remaining = timesteps - int(model.num_timesteps)
    _write_run_json(out_dir, {**info, "status": "running"})

    try:
        with bar:
            if remaining > 0:
                model.learn(remaining, callback=_RunMonitor(run), reset_num_timesteps=state is None,
                            tb_log_name="run")
    except NonFiniteError as exc:
        _write_run_json(out_dir, {**info, "status": "failed", "error": str(exc)})
        raise TrainingInterrupted(
            f"training stopped: {exc}. The last good checkpoint is {run.checkpoint} (resume with --resume)."
        ) from None
    finally:
        env.close()

    final_eval = run.evaluate(model, log=remaining > 0)
    run.save_checkpoint(model)
    metadata = {"algo": algo, "algo_config": algo_config.model_dump(mode="json"),
                "env_config": env_config.model_dump(mode="json"), "seed": seed, "timesteps": int(model.num_timesteps)}
    model_path = save_policy(model.policy, out_dir / "model.zip", metadata)
    result = TrainResult(model_path, int(model.num_timesteps), run.wall_time(), final_eval)
    _write_run_json(out_dir, {**info, "status": "complete", "wall_time_s": result.wall_time_s,
                              "final_eval": final_eval, "num_timesteps": result.timesteps})
    return result


class _NoDisplay:
    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        return None


def _progress_display(progress: bool | Callable[[int, float | None], None], total: int):
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
