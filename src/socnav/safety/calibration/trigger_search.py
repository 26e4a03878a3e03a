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

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pandas as pd

from socnav.safety.calibration.rollout_selection import CalibrationRun, select_by_rollouts
from socnav.safety.rule import Thresholds
from socnav.safety.triggers import ScoreTrigger, TriggerSpec, make_trigger

__all__ = [
    "BUDGET_SHARES",
    "RISK_TRAINING_SEED",
    "TriggerScoreRecorder",
    "calibrate_trigger",
    "collect_trigger_records",
    "collision_labels",
    "threshold_candidates",
]

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
