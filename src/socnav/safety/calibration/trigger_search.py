"""Calibrating a score trigger (`socnav.safety.triggers`): its scores on the plain policy's calibration steps
propose thresholds, and replays choose among them within the false-activation budget, as for the rule.

1. records (:func:`collect_trigger_records`): the plain policy plays the calibration runs; every trigger scores
   every step (and the risk model's features are kept). Nothing else is fitted on these episodes' outcomes except
   what the trigger itself learns (the risk model trains on its own range of calibration seeds,
   :data:`RISK_TRAINING_SEED`);
2. proposals (:func:`threshold_candidates`): for a budget ``b``, the thresholds above which a share ``s * b`` of
   the UNPERTURBED steps score, for shares ``s`` in :data:`BUDGET_SHARES` (the fallback changes the trajectories,
   so the replays, not the records, decide which share keeps the budget);
3. selection: :func:`~socnav.safety.calibration.rollout_selection.select_by_rollouts`, the stage the rule goes
   through: the candidate preventing the most on the worst perturbation type whose false-activation upper bound
   is within the budget.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from socnav.safety.calibration.rollout_selection import CalibrationRun, rollout_scores, select_by_rollouts
from socnav.safety.rule import Thresholds
from socnav.safety.triggers import ScoreTrigger, TriggerSpec, make_trigger, trigger_class

__all__ = [
    "ANALYTIC_TRIGGERS",
    "BUDGET_SHARES",
    "RISK_HORIZON_STEPS",
    "RISK_TRAINING_SEED",
    "NoCollisionsError",
    "TriggerScoreRecorder",
    "calibrate_score_triggers",
    "calibrate_trigger",
    "calibration_scores",
    "collect_trigger_records",
    "collision_labels",
    "fit_conformal_start",
    "prepare_triggers",
    "risk_model_path",
    "threshold_candidates",
    "train_risk_models",
]

#: The built-in triggers that need no preparation but the conformal shield's starting bound.
ANALYTIC_TRIGGERS = ("time-to-collision", "closing-gap", "predicted-clearance", "conformal")
#: A collision "within the next second" at the default 0.25 s step: the risk model's label.
RISK_HORIZON_STEPS = 4
#: Shares of the budget whose unperturbed score quantiles are replayed as candidate thresholds.
BUDGET_SHARES = (0.25, 0.5, 0.75, 1.0, 1.5)
#: Episode seeds the risk model trains on: calibration seeds (500,000...) far from the calibration runs' own.
RISK_TRAINING_SEED = 700_000


class TriggerScoreRecorder:
    """Rollout observer: every step of the probe (a :class:`~socnav.safety.SafePolicy` that never fires), each
    trigger's score, and with ``features`` the risk model's features (``uncertainty``: with the estimates)."""

    def __init__(self, probe: Any, specs: Sequence[TriggerSpec], features: bool = False,
                 uncertainty: bool = False) -> None:
        self.probe = probe
        self.specs = list(specs)
        self.triggers: list[ScoreTrigger] = []
        self.features, self.uncertainty = features, uncertainty
        self.steps: np.ndarray | None = None
        self._rows: dict[str, list[np.ndarray]] = {"episode": [], "step": []}
        self._features: list[np.ndarray] = []

    def on_episode_start(self, envs: np.ndarray) -> None:
        if self.steps is None:
            self.steps = np.zeros(len(envs), dtype=np.int64)
            for spec in self.specs:
                trigger = make_trigger(spec)
                assert isinstance(trigger, ScoreTrigger)
                trigger.allocate(len(envs))
                self.triggers.append(trigger)
        self.steps[envs] = 0
        for trigger in self.triggers:
            trigger.reset(np.asarray(envs))

    def on_step(self, observation: Any, actions: Any, result: Any, episodes: np.ndarray) -> None:
        assert self.steps is not None
        live = episodes >= 0
        inputs = self.probe.last_inputs
        self._rows["episode"].append(episodes[live])
        self._rows["step"].append(self.steps[live])
        for spec, trigger in zip(self.specs, self.triggers, strict=True):
            self._rows.setdefault(f"score_{spec.trigger}", []).append(trigger.score(inputs)[live])
        if self.features:
            from socnav.safety.risk_model import risk_features

            self._features.append(risk_features(inputs, self.uncertainty)[live])
        self.steps += 1

    def frame(self) -> tuple[pd.DataFrame, np.ndarray | None]:
        """The recorded steps and, with ``features``, their feature rows (same order)."""
        frame = pd.DataFrame({key: np.concatenate(values) for key, values in self._rows.items()})
        return frame, (np.concatenate(self._features) if self.features else None)


def collect_trigger_records(policy: Any, estimator: Any, runs: Sequence[CalibrationRun],
                            specs: Sequence[TriggerSpec], window: int = 4, n_envs: int = 40, sensing: str = "perceived",
                            features: bool = False, uncertainty: bool = False,
                            progress: Callable[[int], None] | None = None) -> tuple[pd.DataFrame, np.ndarray | None]:
    """Per-step scores of every trigger of ``specs`` over the plain policy's episodes of ``runs``, with the columns
    ``episode`` (unique over the runs), ``step``, ``perturbed``, ``group``, ``collided``, ``length`` and
    ``score_<trigger>``; with ``features`` also the risk model's feature rows."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import SafePolicy, no_uncertainty

    frames, feature_parts, offset = [], [], 0
    for run in runs:
        probe = SafePolicy(policy, no_uncertainty if estimator is None else estimator,
                           Thresholds.create(Thresholds.never().model_dump(), sensing=sensing), run.config,
                           window=window)
        recorder = TriggerScoreRecorder(probe, specs, features, uncertainty)
        restart = getattr(estimator, "restart", None)
        if callable(restart):
            restart()
        episodes = rollout_episodes(probe, run.config, run.n_episodes, seed=run.seed, n_envs=n_envs,
                                    observer=recorder, progress=progress, metrics=False)
        frame, rows = recorder.frame()
        by_episode = episodes.set_index("episode")
        frame["collided"] = frame["episode"].map(by_episode["outcome"] == "collision").astype(bool)
        frame["length"] = frame["episode"].map(by_episode["length"]).astype(np.int64)
        frame["episode"] += offset
        frame["perturbed"], frame["group"] = run.perturbed, run.group
        offset += run.n_episodes
        frames.append(frame)
        if rows is not None:
            feature_parts.append(rows)
    return pd.concat(frames, ignore_index=True), (np.concatenate(feature_parts) if features else None)


def collision_labels(records: pd.DataFrame, horizon_steps: int) -> np.ndarray:
    """1 for the steps whose episode ends in a collision within ``horizon_steps`` steps (the step whose action led
    to the collision and the ``horizon_steps - 1`` before it), else 0."""
    steps_left = records["length"].to_numpy() - 1 - records["step"].to_numpy()
    return (records["collided"].to_numpy() & (steps_left < horizon_steps)).astype(np.float64)


def threshold_candidates(unperturbed_scores: np.ndarray, budget: float,
                         shares: Sequence[float] = BUDGET_SHARES) -> list[float]:
    """Distinct thresholds above which a share ``s * budget`` of the unperturbed steps score, for ``s`` in
    ``shares`` (order statistics: the ``ceil(n (1 - s b))``-th smallest score); ``inf`` if no step is scored."""
    scores = np.sort(np.asarray(unperturbed_scores, dtype=np.float64))
    if len(scores) == 0:
        return [float("inf")]
    out = []
    for share in shares:
        rank = int(np.ceil(len(scores) * (1.0 - min(share * budget, 1.0)))) - 1
        out.append(float(scores[min(max(rank, 0), len(scores) - 1)]))
    return sorted(set(out), reverse=True)


def calibrate_trigger(spec: TriggerSpec, records: pd.DataFrame, policy: Any, estimator: Any,
                      runs: Sequence[CalibrationRun], budget: float, window: int = 4, n_envs: int = 40,
                      confidence: float = 0.95, plain_collisions: dict[str, int] | None = None,
                      progress: Callable[[int], None] | None = None,
                      cache: dict[Any, dict[str, Any]] | None = None) -> tuple[TriggerSpec, pd.DataFrame]:
    """The threshold of ``spec``'s trigger for ``budget``: candidates from the unperturbed records' scores, the
    choice by replays on ``runs`` (``threshold = inf`` -- never firing -- if none keeps the budget).
    ``plain_collisions`` and ``cache`` as in `select_by_rollouts` (measured once, replays shared by budgets)."""
    unperturbed = records.loc[~records["perturbed"].astype(bool), f"score_{spec.trigger}"].to_numpy()
    candidates = [spec.with_threshold(threshold) for threshold in threshold_candidates(unperturbed, budget)]
    chosen, table = select_by_rollouts(candidates, policy, estimator, list(runs), budget, window, n_envs,
                                       confidence, progress, plain_collisions, cache)
    if isinstance(chosen, Thresholds):  # nothing within the budget: the layer stays off
        chosen = spec.with_threshold(float("inf"))
    table.attrs["budget"] = budget
    return chosen, table


class NoCollisionsError(ValueError):
    """The episodes a learned trigger trains on hold no collision: there is nothing to learn from."""


def _calibration_runs(env: dict[str, Any], episodes: int, seed: int | None = None) -> list[CalibrationRun]:
    """The calibration configurations (`socnav.safety.calibration.workflow.calibration_runs`), from ``seed`` on
    when given (the risk model's own seeds)."""
    from socnav.safety.calibration.workflow import calibration_runs

    runs = calibration_runs(env, episodes)
    if seed is None:
        return runs
    return [CalibrationRun(run.config, run.perturbed, run.n_episodes, seed + index * episodes, run.group)
            for index, run in enumerate(runs)]


def _probe(policy: Any, config: Any, sensing: str, window: int) -> Any:
    """A SafePolicy that never fires and estimates nothing: it plays ``policy`` and computes the triggers' inputs."""
    from socnav.safety.safe_policy import SafePolicy, no_uncertainty

    return SafePolicy(policy, no_uncertainty, Thresholds.create(Thresholds.never().model_dump(), sensing=sensing),
                      config, window=window)


def fit_conformal_start(spec: TriggerSpec, policy: Any, env: dict[str, Any], episodes: int, window: int = 4,
                        n_envs: int = 40) -> TriggerSpec:
    """``spec`` with ``initial_quantile`` the ``1 - alpha`` quantile of the shield's forecast errors on the
    unperturbed calibration episodes (the bound it starts each episode with)."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.conformal import ConformalShieldTrigger

    run = _calibration_runs(env, episodes)[0]
    probe = _probe(policy, run.config, spec.sensing, window)
    shield = ConformalShieldTrigger(spec)
    errors: list[np.ndarray] = []

    class _Errors:
        allocated = False

        def on_episode_start(self, envs: np.ndarray) -> None:
            if not self.allocated:  # the first call names every environment of the rollout
                shield.allocate(len(envs))
                self.allocated = True
            shield.reset(np.asarray(envs))

        def on_step(self, observation: Any, actions: Any, result: Any, episodes: np.ndarray) -> None:
            shield.score(probe.last_inputs)
            errors.append(shield.last_errors[episodes >= 0])

    rollout_episodes(probe, run.config, run.n_episodes, seed=run.seed, n_envs=n_envs, observer=_Errors(),
                     metrics=False)
    values = np.concatenate(errors)
    values = values[np.isfinite(values)]
    start = float(np.quantile(values, 1.0 - shield.params.alpha)) if len(values) else 0.0
    return TriggerSpec.create(spec.model_dump(), params={**spec.params, "initial_quantile": round(start, 4)})


def risk_model_path(out: Path, name: str, prefix: str = "") -> Path:
    """Where :func:`train_risk_models` writes the model ``name``: ``out/<prefix><name>.npz``."""
    return Path(out) / f"{prefix}{name}.npz"


def train_risk_models(policy: Any, estimator: Any, env: dict[str, Any], episodes: int, sensing: str, out: Path,
                      window: int = 4, n_envs: int = 40,
                      names: Sequence[str] = ("risk-model", "risk-model+uncertainty"),
                      prefix: str = "") -> dict[str, TriggerSpec]:
    """The risk model without (``risk-model``) and with (``risk-model+uncertainty``) the uncertainty inputs, trained
    on ``episodes`` per calibration configuration from :data:`RISK_TRAINING_SEED` on and written to
    :func:`risk_model_path`; name -> spec (threshold ``inf``: to be calibrated)."""
    from socnav.safety.risk_model import save_risk_model, train_risk_model

    reads = "risk-model+uncertainty" in names
    records, features = collect_trigger_records(policy, estimator if reads else None,
                                                _calibration_runs(env, episodes, RISK_TRAINING_SEED), [], window,
                                                n_envs, sensing, features=True, uncertainty=reads)
    assert features is not None
    labels = collision_labels(records, RISK_HORIZON_STEPS)
    if not labels.any():
        raise NoCollisionsError(f"no collision in the {len(records['episode'].unique())} risk-training episodes "
                                "(seeds 700,000...): play more episodes")
    geometry = len(features[0]) - (5 if reads else 0)
    specs = {}
    for name in names:
        with_uncertainty = name == "risk-model+uncertainty"
        columns = slice(None) if with_uncertainty else slice(0, geometry)
        model = train_risk_model(features[:, columns], labels, records["episode"].to_numpy(), with_uncertainty,
                                 RISK_HORIZON_STEPS)
        path = save_risk_model(model, risk_model_path(out, name, prefix))
        specs[name] = TriggerSpec.create(trigger="risk-model", threshold=math.inf, model=str(path), sensing=sensing)
    return specs


def prepare_triggers(names: Sequence[str], policy: Any, estimator: Any, env: dict[str, Any], episodes: int,
                     risk_episodes: int, sensing: str, window: int, n_envs: int, out: Path,
                     log: Callable[[str], None] = print, prefix: str = "") -> dict[str, TriggerSpec]:
    """Specs (threshold ``inf``) of the score triggers ``names``: the conformal shield's starting bound fitted, the
    risk models trained (``risk-model``, ``risk-model+uncertainty``), any other registered trigger as it is."""
    specs = {}
    risk = [name for name in names if name.startswith("risk-model")]
    for name in names:
        if name not in risk:
            trigger_class(name)  # a clear error for an unknown name, before any episode is played
            specs[name] = TriggerSpec.create(trigger=name, threshold=math.inf, sensing=sensing)
    if "conformal" in specs:
        log("fitting the conformal shield's starting bound")
        specs["conformal"] = fit_conformal_start(specs["conformal"], policy, env, episodes, window, n_envs)
    if risk:
        log("training the risk model(s)")
        try:
            specs.update(train_risk_models(policy, estimator, env, risk_episodes, sensing, out, window, n_envs, risk,
                                           prefix))
        except NoCollisionsError as exc:  # nothing to learn from: the rows are left out, and said so
            log(f"{', '.join(risk)} left out: {exc}")
    return {name: specs[name] for name in names if name in specs}


def calibrate_score_triggers(specs: dict[str, TriggerSpec], policy: Any, estimator: Any, env: dict[str, Any],
                             episodes: int, budgets: Sequence[float], sensing: str, window: int = 4,
                             n_envs: int = 40, confidence: float = 0.95,
                             log: Callable[[str], None] = print,
                             scores: dict[str, dict[float, dict[str, float]]] | None = None,
                             ) -> dict[str, dict[float, TriggerSpec]]:
    """Every trigger of ``specs`` calibrated at every budget on the same calibration episodes: the records scored
    once, the plain policy's collisions measured once, each trigger's replays shared by its budgets. ``scores``,
    when given, receives name -> budget -> :func:`calibration_scores` of each choice."""
    runs = _calibration_runs(env, episodes)
    plain = rollout_scores(None, policy, None, runs, window, n_envs)["collisions"]
    shared = [spec for spec in specs.values() if not spec.uses_uncertainty and spec.model is None]
    records, _ = collect_trigger_records(policy, None, runs, shared, window, n_envs, sensing)
    chosen: dict[str, dict[float, TriggerSpec]] = {}
    for name, spec in specs.items():
        if spec not in shared:  # learned or uncertainty-reading triggers (two may share a name): one at a time
            one, _ = collect_trigger_records(policy, estimator if spec.uses_uncertainty else None, runs, [spec],
                                             window, n_envs, sensing)
            records[f"score_{spec.trigger}"] = one[f"score_{spec.trigger}"].to_numpy()
        replayed: dict[Any, dict[str, Any]] = {}  # a threshold proposed at two budgets is replayed once
        chosen[name] = {}
        for budget in budgets:
            log(f"calibrating {name} at {budget:.0%}")
            chosen[name][budget], table = calibrate_trigger(
                spec, records, policy, estimator if spec.uses_uncertainty else None, runs, budget, window, n_envs,
                confidence, plain_collisions=plain, cache=replayed)
            if scores is not None:
                scores.setdefault(name, {})[budget] = calibration_scores(table)
    return chosen


def calibration_scores(table: pd.DataFrame) -> dict[str, float]:
    """What the calibration measured of its choice (a `select_by_rollouts` table): the prevented share of the worst
    perturbation type and the mean over types, and the false activation's upper bound, on the CALIBRATION
    episodes (NaN where nothing was chosen: the layer is off)."""
    chosen = table[table["chosen"]] if "chosen" in table else table.iloc[0:0]
    if chosen.empty:
        return {"prevented_worst": math.nan, "prevented_fraction": math.nan, "false_activation_upper": 0.0}
    row = chosen.iloc[0]
    return {key: float(row[key]) for key in ("prevented_worst", "prevented_fraction", "false_activation_upper")}
