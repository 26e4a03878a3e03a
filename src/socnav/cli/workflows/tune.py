"""Optuna search of the PPO hyperparameters of a preset: each trial trains with sampled values, reports its periodic
validation results to Optuna (median pruning stops poor trials early), and the best values become a preset YAML
that `socnav train --algo-config`, and experiment files (``grid.algo_overrides.<algo>: preset.yaml``), read.

Searched (SB3 names, as in ``socnav.rl.presets.AlgoConfig``)::

    learning_rate  log-uniform [1e-5, 1e-3]        gamma       {0.95, 0.98, 0.99, 0.995, 0.999}
    n_steps        {64, 128, 256, 512} per env     gae_lambda  {0.8, 0.9, 0.92, 0.95, 0.98, 1.0}
    batch_size     {64, 128, 256, 512}             clip_range  {0.1, 0.2, 0.3, 0.4}
    n_epochs       {3, 5, 10, 20}                  ent_coef    log-uniform [1e-8, 1e-1]

A batch larger than one rollout (n_steps x n_envs) is cut to the rollout. Studies live in an Optuna RDB storage
(SQLite by default), so a search can be continued, inspected with optuna-dashboard, or run by several
``socnav tune`` processes at once on the same storage and study name.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from socnav.config import ConfigLike, load_config
from socnav.extras import install_hint
from socnav.io import read_table, write_text_atomic

__all__ = ["SEARCHED", "StudyMismatchError", "TuneResult", "sample_params", "tune", "write_preset"]

DEFAULT_STORAGE = "sqlite:///runs/tune.db"
SEARCHED = ("learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "clip_range", "ent_coef")
METRICS = {"return_mean": "maximize", "goal_pct": "maximize", "collision_pct": "minimize"}


def _optuna() -> Any:
    try:
        import optuna
    except ImportError:
        raise RuntimeError(f"socnav tune needs Optuna: {install_hint('tune')}") from None
    return optuna


def sample_params(trial: Any, n_envs: int) -> dict[str, Any]:
    """One point of the search space (AlgoConfig field -> value)."""
    params = {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "n_steps": trial.suggest_categorical("n_steps", [64, 128, 256, 512]),
        "batch_size": trial.suggest_categorical("batch_size", [64, 128, 256, 512]),
        "n_epochs": trial.suggest_categorical("n_epochs", [3, 5, 10, 20]),
        "gamma": trial.suggest_categorical("gamma", [0.95, 0.98, 0.99, 0.995, 0.999]),
        "gae_lambda": trial.suggest_categorical("gae_lambda", [0.8, 0.9, 0.92, 0.95, 0.98, 1.0]),
        "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2, 0.3, 0.4]),
        "ent_coef": trial.suggest_float("ent_coef", 1e-8, 1e-1, log=True),
    }
    params["batch_size"] = min(params["batch_size"], params["n_steps"] * n_envs)
    return params


class StudyMismatchError(ValueError):
    """An existing study was created with other settings (algo, env, timesteps, ...): its trials are not
    comparable with new ones."""


def _check_settings(study: Any, settings: dict[str, Any]) -> None:
    """Refuse to extend a study whose recorded settings differ from `settings`; record them on a new study.

    Only the settings a study recorded are compared (studies of older socnav versions recorded fewer)."""
    recorded = study.user_attrs
    differing = [key for key, value in settings.items() if key in recorded and recorded[key] != value]
    if differing:
        def show(value: Any) -> str:
            if isinstance(value, dict):  # an env config: its scenario, the rest is too long for one line
                return f"{value.get('scenario', '?')} env (other fields may differ)"
            return repr(value)

        details = "; ".join(f"{key}: study {show(recorded[key])}, now {show(settings[key])}" for key in differing)
        raise StudyMismatchError(
            f"study {study.study_name!r} was created with other settings ({details}); its trials would not be "
            "comparable: pass a new --study-name (study_name=...) or repeat the study's settings")
    for key, value in settings.items():
        if key not in recorded:
            study.set_user_attr(key, value)


def _check_storage(storage: str) -> None:
    """Refuse a storage that is not a database URL before Optuna gets it (SQLAlchemy's parse error is a traceback),
    and create the directory of a SQLite file.

    :raises ValueError: not a URL, or a SQLite file whose directory cannot be created (one line, with an example).
    """
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        url = make_url(storage)
    except ArgumentError:
        raise ValueError(f"storage {storage!r} is not a database URL; e.g. {DEFAULT_STORAGE} (a SQLite file) or any "
                         "Optuna RDB URL (postgresql://user@host/db, mysql://...)") from None
    if url.get_backend_name() == "sqlite" and url.database not in (None, "", ":memory:"):
        directory = Path(url.database).parent
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"storage {storage!r}: cannot create the directory {directory} ({exc.strerror or exc})") \
                from None


@dataclass
class TuneResult:
    """The best trial of a study so far: its `metric` value and hyperparameters, and the study's trial counts."""

    study_name: str
    storage: str
    best_value: float
    best_params: dict[str, Any]
    best_trial: int
    counts: dict[str, int]
    metric: str


def tune(
    config: ConfigLike,
    algo: str,
    trials: int,
    timesteps: int = 100_000,
    storage: str = DEFAULT_STORAGE,
    study_name: str | None = None,
    out_dir: str | Path | None = None,
    n_envs: int = 16,
    eval_every: int | None = None,
    eval_episodes: int = 20,
    seed: int = 0,
    metric: str = "return_mean",
    timeout: float | None = None,
    n_startup_trials: int = 3,
    on_trial: Callable[[Any, Any], None] | None = None,
) -> TuneResult:
    """Run `trials` more trials of the study (created or continued) and return its best so far.

    A study is continued only with the settings it was created with (else `StudyMismatchError`); new trials
    draw new parameters (the sampler is seeded with `seed` plus the number of trials already in the study).
    Every trial trains `algo` for `timesteps` steps on env `config` (seed `seed`, so trials differ only in their
    hyperparameters) in ``out_dir/trial_<n>``, evaluating every `eval_every` steps on `eval_episodes` validation
    episodes; each evaluation's `metric` is reported to Optuna and a MedianPruner stops trials below the median.
    The objective is the final validation `metric` (return_mean / goal_pct: maximized; collision_pct: minimized).
    """
    optuna = _optuna()
    from socnav.rl.presets import resolve_config

    if metric not in METRICS:
        raise ValueError(f"unknown metric {metric!r}; allowed: {', '.join(METRICS)}")
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    env_config = load_config(config)
    resolve_config(algo)  # unknown algo: fail before creating a study
    study_name = study_name or f"{algo}_{env_config.scenario}"
    out_dir = Path(out_dir) if out_dir is not None else Path("runs") / "tune" / study_name
    _check_storage(storage)
    try:  # before the first trial: a place that cannot hold the trials' runs is one line, not a failed trial
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"out_dir {out_dir}: cannot create it ({exc.strerror or exc})") from None
    eval_every = eval_every or max(1, timesteps // 5)
    settings = {"algo": algo, "env_config": env_config.model_dump(mode="json"), "timesteps": timesteps,
                "metric": metric, "n_envs": n_envs, "eval_every": eval_every, "eval_episodes": eval_episodes,
                "seed": seed}
    study = _open_study(optuna, study_name, storage, metric, n_startup_trials, settings)
    objective = _Objective(env_config, algo, seed, timesteps, out_dir, n_envs, eval_every, eval_episodes, metric)
    callbacks = [on_trial] if on_trial is not None else None
    study.optimize(objective, n_trials=trials, timeout=timeout, callbacks=callbacks, gc_after_trial=True)
    return _best_result(study, storage, metric, n_envs)


def _open_study(optuna: Any, study_name: str, storage: str, metric: str, n_startup_trials: int,
                settings: dict[str, Any]) -> Any:
    """The study `study_name` in `storage`, created or continued (only with the `settings` it was created with),
    with median pruning and a sampler whose seed moves on with the trials already in it."""
    from sqlalchemy.exc import SQLAlchemyError

    try:
        study = optuna.create_study(
            study_name=study_name, storage=storage, load_if_exists=True, direction=METRICS[metric],
            pruner=optuna.pruners.MedianPruner(n_startup_trials=n_startup_trials, n_warmup_steps=0),
        )
    except (SQLAlchemyError, ModuleNotFoundError) as exc:  # unreachable server, missing driver, unwritable file
        first = " ".join(str(exc).split())[:200]
        raise RuntimeError(f"cannot open the Optuna storage {storage!r}: {type(exc).__name__}: {first}") from None
    _check_settings(study, settings)
    # A sampler seeded by `seed` alone would replay the same parameters each time the study is continued (trial
    # n + k = trial k): the seed moves on with the trials already in the study, so new trials explore and a
    # continued study is still reproducible.
    study.sampler = optuna.samplers.TPESampler(seed=settings["seed"] + len(study.trials))
    return study


@dataclass(frozen=True)
class _Objective:
    """One trial: train with sampled hyperparameters in ``out_dir/trial_<n>``, report every periodic validation to
    Optuna (which may prune the trial), return the final validation `metric` (NaN for a failed training)."""

    env_config: Any
    algo: str
    seed: int
    timesteps: int
    out_dir: Path
    n_envs: int
    eval_every: int
    eval_episodes: int
    metric: str

    def __call__(self, trial: Any) -> float:
        from socnav.rl.training import TrainingInterrupted, train

        params = sample_params(trial, self.n_envs)
        run_dir = self.out_dir / f"trial_{trial.number}"
        try:
            # force: a trial of this number left by an earlier study (a deleted storage) is moved aside, not mixed in
            result = train(self.env_config, self.algo, self.seed, self.timesteps, run_dir, n_envs=self.n_envs,
                           overrides=params, eval_every=self.eval_every, eval_episodes=self.eval_episodes,
                           progress=self._validation_reporter(trial, run_dir), tensorboard=False, force=True)
        except TrainingInterrupted as exc:
            trial.set_user_attr("error", str(exc))
            return float("nan")  # Optuna records the trial as failed and goes on
        value = float(result.final_eval[self.metric])
        trial.set_user_attr("final_eval", {k: float(v) for k, v in result.final_eval.items()})
        return value if math.isfinite(value) else float("nan")

    def _validation_reporter(self, trial: Any, run_dir: Path) -> Callable[[int, float | None], None]:
        """A `train` progress callback that reports the validations new in ``run_dir/eval.csv`` and prunes."""
        optuna = _optuna()
        evals = run_dir / "eval.csv"
        reported: set[int] = set()

        def report_validations(_timesteps: int, _success: float | None) -> None:
            # train() appends a row to eval.csv at every periodic validation: report the new ones, maybe prune.
            if not evals.is_file():
                return
            try:
                rows = read_table(evals)
            except Exception:
                return
            for row in rows.itertuples(index=False):
                step = int(row.timesteps)
                if step in reported or step >= self.timesteps:
                    continue
                reported.add(step)
                value = getattr(row, self.metric)
                trial.report(float(value), step)
                if trial.should_prune():
                    raise optuna.TrialPruned(f"pruned at {step} timesteps ({self.metric}={value:.3f})")

        return report_validations


def _best_result(study: Any, storage: str, metric: str, n_envs: int) -> TuneResult:
    """The study's best trial so far and its trial counts (RuntimeError when no trial completed yet)."""
    states = _optuna().trial.TrialState
    counts = {name.lower(): len(study.get_trials(deepcopy=False, states=(state,)))
              for name, state in (("COMPLETE", states.COMPLETE), ("PRUNED", states.PRUNED), ("FAIL", states.FAIL))}
    try:
        best = study.best_trial
    except ValueError:
        raise RuntimeError(f"study {study.study_name!r} has no completed trial yet (pruned: {counts['pruned']}, "
                           f"failed: {counts['fail']}); run more trials or longer ones") from None
    params = dict(best.params)
    params["batch_size"] = min(params["batch_size"], params["n_steps"] * n_envs)
    return TuneResult(study.study_name, storage, float(best.value), params, best.number, counts, metric)


def write_preset(path: str | Path, result: TuneResult, algo: str, scenario: str, timesteps: int) -> Path:
    """Write the best hyperparameters as a preset YAML (a mapping of AlgoConfig fields; provenance in comments)."""
    header = (
        f"# socnav preset: Optuna study {result.study_name!r} ({result.storage})\n"
        f"# algo {algo}, scenario {scenario}, {timesteps:,} timesteps per trial; best trial #{result.best_trial}\n"
        f"# {result.metric} = {result.best_value:.4f}; trials: {result.counts}\n"
        f"# use: socnav train --algo {algo} --algo-config THIS_FILE, or grid.algo_overrides.{algo}: THIS_FILE\n"
    )
    values = {key: (float(value) if isinstance(value, float) else value) for key, value in result.best_params.items()}
    return write_text_atomic(path, header + yaml.safe_dump(values, sort_keys=False))
