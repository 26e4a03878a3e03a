"""Safe action selection as a policy wrapper (paper IV-C).

At every step, for every environment of the batch:

1. the wrapped policy's own action: ``policy.predict(obs, state, episode_start, deterministic)`` -- NOT the
   estimator's mean action (for MC-dropout that is the mean over dropout masks, which is not what the plain policy
   does); so with a rule that never fires the wrapper is exactly the wrapped policy;
2. the uncertainty ``estimator(obs)`` (any object with ``u_ep`` (B, 2; index 1 = heading change), ``u_al`` and
   ``u_feat`` (B,) attributes, e.g. ``socnav.uncertainty.Uncertainty``), windowed per environment over the last
   ``window`` steps of the current episode (mean of ``min(window, steps so far)`` values, as
   ``socnav.uncertainty.WindowedUncertainty``; a simple ring buffer kept here);
3. the nearest human's gap and speed term and the previous step's gap of the same episode, read from the *sensed*
   observation: with ``thresholds.sensing == "perceived"`` the observation itself (noise included), with ``"true"``
   the simulator's noise-free observation of the same step (``true_observation``: passed to ``predict`` or given
   before it with :meth:`SafePolicy.sense`; ``socnav.envs.rollout.rollout_episodes`` does the latter for every
   policy whose ``needs_true_observation`` is True). The policy and the estimator always see the observation;
4. the rule ``P(col) = (c_ep or c_feat) and c_prox and c_ap`` (paper eq. (10); or one of its ablations,
   ``thresholds.conditions``: ``c_prox and c_ap`` or ``(c_ep or c_feat) and c_ap``); where it fires -- or, with
   ``thresholds.hold_steps = k > 0``, fired at one of the last ``k`` steps of the episode
   (:func:`~socnav.safety.rule.held_fallback`) -- the action is replaced by the
   :class:`~socnav.safety.cautious.CautiousController`'s, computed from the sensed observation;
5. in a world with walls, the wall stop (:class:`~socnav.safety.wall_stop.WallStop`, ``wall_stop=True``): an action
   whose step would bring the robot's disc onto a wall -- the policy's or the fallback's -- stands still instead
   (speed action -1, its turn kept), from the sensed observation's ``pose``.

Episode boundaries: call :meth:`SafePolicy.reset` with the environments whose episode ended (before the next
``predict`` sees their new first observation), or pass SB3's ``episode_start`` to ``predict``. Without either,
windows, the previous gap and a hold run on across episodes.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from socnav.config import ConfigLike, load_config
from socnav.safety.cautious import CAUTIOUS_RADIUS_SCALE, CautiousController
from socnav.safety.rule import (
    NearestHuman,
    RuleConditions,
    Thresholds,
    held_fallback,
    nearest_human,
)
from socnav.safety.triggers import RuleTrigger, TriggerInputs, TriggerSpec, load_safety, make_trigger
from socnav.safety.wall_stop import WallStop
from socnav.sim.walls import POSE_KEY

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["BRAKE_ACTION", "FALLBACKS", "FallbackCounter", "SafePolicy", "fallback_percent", "no_uncertainty"]

SPEED, HEADING = 0, 1
#: What drives where the trigger fires: the paper's cautious ORCA controller, or a brake (stop at once, keep the
#: heading: the action (-1, 0), speed 0), the fallback that takes full responsibility for not moving into anyone.
FALLBACKS = ("cautious", "brake")
BRAKE_ACTION = np.array([-1.0, 0.0], dtype=np.float32)


def no_uncertainty(observation: Mapping[str, np.ndarray]) -> Any:
    """An estimator that estimates nothing: zero uncertainties for every observation of the batch (for rules and
    records that do not read them, without the cost of an estimate)."""
    batch = np.atleast_2d(np.asarray(observation["robot"])).shape[0]
    return SimpleNamespace(u_ep=np.zeros((batch, 2)), u_al=np.zeros((batch, 2)), u_feat=np.zeros(batch))


class SafePolicy:
    """Wrap ``policy`` so that a cautious ORCA controller takes over when the collision rule fires.

    :param policy: anything with ``predict(obs, state=None, episode_start=None, deterministic=True)``, batched.
    :param estimator: callable ``estimator(obs) -> Uncertainty``-like (``u_ep``, ``u_al``, ``u_feat``); None only
        for a rule that reads no uncertainty (``thresholds.conditions == "proximity-only"``): the windows then hold
        zeros and no estimate is computed (its cost is the point: K forward passes per step for MC-dropout).
    :param thresholds: a :class:`Thresholds`, a preset name (``mc``, ``ensemble``), a file path or a mapping;
        its ``sensing`` says what the proximity terms and the cautious controller read (module docstring).
    :param config: the env config (limits for the cautious controller).
    :param window: uncertainty window ``w`` in steps (paper: 4).
    :param n_envs: batch size; None: taken from the first ``predict``. The batch size must stay fixed.
    :param radius_scale: human radius inflation of the cautious controller (paper: 1.5).
    :param fallback: ``cautious`` (the paper's ORCA controller) or ``brake`` (:data:`BRAKE_ACTION`).
    :param wall_stop: in a world with walls, stand still rather than take a step onto a wall (module docstring, 5);
        False: the paper's layer, which acts for people only.

    After each ``predict``: ``last_fallback`` (B,) bool (the fallback drove: the rule fired or a hold was on),
    ``last_wall_stop`` (B,) bool (the wall stop stood the robot still),
    ``last_conditions`` (:class:`RuleConditions`), ``last_uncertainty`` (dict of windowed (B,) arrays
    ``u_ep_heading``, ``u_ep_speed``, ``u_al_heading``, ``u_al_speed``, ``u_feat``), ``last_nearest``
    (:class:`NearestHuman`), ``last_previous_gap`` (B,), and ``episode_fallbacks`` (n_envs,) -- fallback steps in
    the current episode (zeroed by :meth:`reset`).
    """

    def __init__(
        self,
        policy: Any,
        estimator: Any,
        thresholds: Thresholds | TriggerSpec | str | Mapping[str, Any],
        config: ConfigLike = None,
        window: int = 4,
        n_envs: int | None = None,
        radius_scale: float = CAUTIOUS_RADIUS_SCALE,
        fallback: str = "cautious",
        wall_stop: bool = True,
    ):
        if int(window) < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if n_envs is not None and int(n_envs) < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        self.policy = policy
        self.estimator = estimator
        self.thresholds: Thresholds | TriggerSpec = load_safety(thresholds)
        if estimator is None and self.thresholds.uses_uncertainty:
            what = (f"trigger {self.thresholds.trigger!r} reads it" if isinstance(self.thresholds, TriggerSpec)
                    else f"these thresholds, with conditions={self.thresholds.conditions!r}, read it")
            raise ValueError(f"estimator=None: only a trigger that reads no uncertainty (e.g. thresholds.conditions="
                             f"'proximity-only', time-to-collision) runs without an estimator; {what}")
        self.trigger = make_trigger(self.thresholds)
        self.last_inputs: TriggerInputs | None = None
        self.config = load_config(config)
        self.window = int(window)
        if fallback not in FALLBACKS:
            raise ValueError(f"unknown fallback {fallback!r}; allowed: {', '.join(FALLBACKS)}")
        self.fallback = fallback
        self.cautious = CautiousController(self.config, radius_scale=radius_scale)
        self.cautious.keep_paths = False  # it is handed only the rows where it drives, a different set each step
        polygons = self.cautious.wall_polygons
        self.wall_stop = (WallStop(polygons, self.config.time_step, self.config.max_heading_change)
                          if wall_stop and polygons else None)
        self.last_wall_stop = np.zeros(0, dtype=bool)
        self.n_envs: int | None = None
        self.last_fallback = np.zeros(0, dtype=bool)
        self.last_conditions: RuleConditions | None = None
        self.last_uncertainty: dict[str, np.ndarray] = {}
        self.last_nearest: NearestHuman | None = None
        self.last_previous_gap = np.zeros(0)
        self._sensed: dict[str, np.ndarray] | None = None
        if n_envs is not None:
            self._allocate(int(n_envs))

    # ------------------------------------------------------------------------------------------- state

    def _allocate(self, n_envs: int) -> None:
        self.n_envs = n_envs
        # per environment and window slot: u_ep speed, u_ep heading, u_al speed, u_al heading, u_feat
        self._buffer = np.zeros((n_envs, self.window, 5))
        self._count = np.zeros(n_envs, dtype=np.int64)
        self._pos = np.zeros(n_envs, dtype=np.int64)
        self._previous_gap = np.full(n_envs, np.nan)
        self.episode_fallbacks = np.zeros(n_envs, dtype=np.int64)
        self._hold_left = np.zeros(n_envs, dtype=np.int64)  # held fallback steps still owed (hold_steps)
        self.trigger.allocate(n_envs)

    def _index(self, envs: Any) -> np.ndarray:
        assert self.n_envs is not None
        if envs is None:
            return np.arange(self.n_envs)
        index = np.asarray(envs)
        if index.dtype == bool:
            return np.flatnonzero(index)
        return np.atleast_1d(index).astype(np.int64)

    def on_episode_start(self, envs: Any) -> None:
        """`socnav.envs.rollout.rollout_episodes` hook: environments `envs` start new episodes."""
        self.reset(envs)

    def reset(self, envs: Any = None) -> None:
        """Start new episodes in ``envs`` (indices, a boolean mask, or None for all): empty their uncertainty
        windows, forget their previous gap (so ``c_ap`` is True at their first step), end a hold and zero their
        ``episode_fallbacks``."""
        if self.n_envs is None:
            return
        index = self._index(envs)
        self._count[index] = 0
        self._pos[index] = 0
        self._buffer[index] = 0.0
        self._previous_gap[index] = np.nan
        self.episode_fallbacks[index] = 0
        self._hold_left[index] = 0
        self.trigger.reset(index)

    def _push(self, values: np.ndarray) -> np.ndarray:
        assert self.n_envs is not None  # allocated by the first predict
        rows = np.arange(self.n_envs)
        self._buffer[rows, self._pos] = values
        self._pos = (self._pos + 1) % self.window
        self._count = np.minimum(self._count + 1, self.window)
        valid = np.arange(self.window)[None, :] < self._count[:, None]  # filled slots (writes start at slot 0)
        return (self._buffer * valid[:, :, None]).sum(axis=1) / self._count[:, None]

    # ------------------------------------------------------------------------------------------- acting

    @property
    def needs_true_observation(self) -> bool:
        """Whether ``predict`` needs the simulator's noise-free observation (``thresholds.sensing == "true"``)."""
        return self.thresholds.sensing == "true"

    def sense(self, true_observation: Mapping[str, np.ndarray]) -> None:
        """Give the noise-free observation of the step the next ``predict`` acts on (used once, then dropped)."""
        self._sensed = {key: np.asarray(value) for key, value in true_observation.items()}

    def _sensed_observation(self, obs: dict[str, np.ndarray], true_observation: Any, single: bool
                            ) -> dict[str, np.ndarray]:
        """What the proximity terms and the cautious controller read this step (batched)."""
        sensed = true_observation if true_observation is not None else self._sensed
        self._sensed = None  # a stale true state must never be read on a later step
        if not self.needs_true_observation:
            return obs
        if sensed is None:
            raise ValueError("thresholds.sensing='true': the safety layer reads the simulator's noise-free "
                             "observation; pass predict(..., true_observation=world.observe(noisy=False)) or call "
                             "sense() before predict (socnav.envs.rollout.rollout_episodes does), or use "
                             "sensing='perceived'")
        sensed = {key: np.asarray(value)[None] if single else np.asarray(value) for key, value in sensed.items()}
        if sensed["robot"].shape != obs["robot"].shape or sensed["humans"].shape != obs["humans"].shape:
            raise ValueError(f"true_observation has shapes robot {sensed['robot'].shape}, humans "
                             f"{sensed['humans'].shape}; the observation has {obs['robot'].shape}, "
                             f"{obs['humans'].shape}")
        return sensed

    def predict(self, observation: Mapping[str, np.ndarray], state: Any = None, episode_start: Any = None,
                deterministic: bool = True, true_observation: Mapping[str, np.ndarray] | None = None
                ) -> tuple[np.ndarray, Any]:
        """Batched safe actions (a single observation gives a single action); returns ``(actions, state)``.

        ``true_observation``: the same step's noise-free observation, read instead of ``observation`` by the
        proximity terms and the cautious controller when ``thresholds.sensing == "true"`` (ignored otherwise)."""
        single = np.asarray(observation["robot"]).ndim == 1
        obs = {key: np.asarray(value)[None] if single else np.asarray(value) for key, value in observation.items()}
        sensed = self._sensed_observation(obs, true_observation, single)
        batch = obs["robot"].shape[0]
        if self.n_envs is None:
            self._allocate(batch)
        elif batch != self.n_envs:
            raise ValueError(f"SafePolicy keeps per-environment windows for {self.n_envs} environments but got a "
                             f"batch of {batch}; create it with n_envs={batch} (the batch size must stay fixed)")
        if episode_start is not None:
            self.reset(np.asarray(episode_start, dtype=bool).reshape(-1))

        actions, state = self.policy.predict(observation, state=state, episode_start=episode_start,
                                             deterministic=deterministic)
        actions = np.array(actions, dtype=np.float32).reshape(batch, -1)

        if self.estimator is None:  # a proximity-only rule: nothing reads the uncertainty
            values = np.zeros((batch, 5))
        else:
            u = self.estimator(obs)
            u_ep, u_al = np.asarray(u.u_ep, dtype=np.float64), np.asarray(u.u_al, dtype=np.float64)
            values = np.column_stack([u_ep[:, SPEED], u_ep[:, HEADING], u_al[:, SPEED], u_al[:, HEADING],
                                      np.asarray(u.u_feat, dtype=np.float64).reshape(batch)])
        windowed = self._push(values)
        self.last_uncertainty = {"u_ep_speed": windowed[:, 0], "u_ep_heading": windowed[:, 1],
                                 "u_al_speed": windowed[:, 2], "u_al_heading": windowed[:, 3],
                                 "u_feat": windowed[:, 4]}

        nearest = nearest_human(sensed)
        previous_gap = self._previous_gap.copy()
        self.last_inputs = TriggerInputs(observation=sensed, actions=actions.copy(),
                                         uncertainty=self.last_uncertainty, nearest=nearest, previous_gap=previous_gap,
                                         time_step=self.config.time_step,
                                         max_heading_change=self.config.max_heading_change)
        fires = self.trigger.fires(self.last_inputs)
        conditions = self.trigger.last_conditions if isinstance(self.trigger, RuleTrigger) else None
        # No human this step: nothing to compare with next step either.
        self._previous_gap = np.where(nearest.present, nearest.gap, np.nan)
        fallback, self._hold_left = held_fallback(fires, self._hold_left, self.thresholds.hold_steps)
        if fallback.any():
            chosen = np.flatnonzero(fallback)
            if self.fallback == "brake":
                actions[chosen] = BRAKE_ACTION
            else:
                cautious, _ = self.cautious.predict({key: value[chosen] for key, value in sensed.items()})
                actions[chosen] = cautious
        self.last_wall_stop = (self.wall_stop.apply(actions, sensed) if self.wall_stop is not None
                               and POSE_KEY in sensed else np.zeros(batch, dtype=bool))
        self.episode_fallbacks += fallback
        self.last_fallback, self.last_conditions, self.last_nearest = fallback, conditions, nearest
        self.last_previous_gap = previous_gap
        return (actions[0] if single else actions), state

    def __repr__(self) -> str:
        return (f"SafePolicy(policy={type(self.policy).__name__}, estimator={type(self.estimator).__name__}, "
                f"thresholds={self.thresholds!r}, window={self.window})")


class FallbackCounter:
    """Rollout observer (``socnav.envs.rollout.rollout_episodes(..., observer=...)``) counting, per episode id,
    the steps on which ``safe_policy`` handed over to the fallback and what the rule's conditions did there.

    Per episode (:meth:`columns`): ``fallback_steps`` (the fallback drove), ``proximity_steps`` (the proximity
    terms ``c_prox and c_ap`` held), ``vetoed_steps`` (they held but the uncertainty condition did not, so eq. (10)
    left the policy in control: :attr:`~socnav.safety.RuleConditions.vetoed`; 0 for the rule's ablations) and
    ``fallback_digest``, a digest of the step indices where the fallback drove: two rollouts of the same episode
    seed made the same hand-over decisions iff their digests are equal.
    """

    def __init__(self, safe_policy: SafePolicy) -> None:
        self.safe_policy = safe_policy
        self.counts: dict[int, int] = {}
        self.proximity: dict[int, int] = {}
        self.vetoed: dict[int, int] = {}
        self._fallback_steps: dict[int, list[int]] = {}
        self._steps: np.ndarray | None = None  # step index of each environment's current episode

    def on_episode_start(self, envs: np.ndarray) -> None:
        if self._steps is None:  # the first call names every environment of the rollout
            self._steps = np.zeros(len(envs), dtype=np.int64)
        self._steps[envs] = 0

    def on_step(self, observation: Any, actions: Any, result: Any, episodes: np.ndarray) -> None:
        live = episodes >= 0
        conditions = self.safe_policy.last_conditions
        for env in np.flatnonzero(live & self.safe_policy.last_fallback):
            episode = int(episodes[env])
            self.counts[episode] = self.counts.get(episode, 0) + 1
            if self._steps is not None:
                self._fallback_steps.setdefault(episode, []).append(int(self._steps[env]))
        if conditions is not None:
            for counts, fired in ((self.proximity, conditions.c_prox & conditions.c_ap),
                                  (self.vetoed, conditions.vetoed)):
                for env in np.flatnonzero(live & fired):
                    counts[int(episodes[env])] = counts.get(int(episodes[env]), 0) + 1
        if self._steps is not None:
            self._steps += 1

    def per_episode(self, episodes: Any) -> list[int]:
        """Fallback steps of each of ``episodes`` (ids), 0 where it never acted."""
        return [self.counts.get(int(e), 0) for e in episodes]

    def drove_at(self, episode: int, step: int) -> bool:
        """Whether the fallback drove at step ``step`` (0-based) of ``episode``."""
        return int(step) in self._fallback_steps.get(int(episode), ())

    def digest(self, episode: int) -> str:
        """16 hex digits identifying the step indices where the fallback drove in ``episode`` (the same for the same
        indices; an episode without a fallback step has the digest of the empty list)."""
        steps = np.asarray(self._fallback_steps.get(int(episode), []), dtype="<i4")
        return hashlib.blake2b(steps.tobytes(), digest_size=8).hexdigest()

    def columns(self, episodes: Any) -> dict[str, list[Any]]:
        """The per-episode columns (class docstring) of ``episodes`` (ids), in their order."""
        episodes = [int(e) for e in episodes]
        return {"fallback_steps": self.per_episode(episodes),
                "proximity_steps": [self.proximity.get(e, 0) for e in episodes],
                "vetoed_steps": [self.vetoed.get(e, 0) for e in episodes],
                "fallback_digest": [self.digest(e) for e in episodes]}


def fallback_percent(records: pd.DataFrame) -> float:
    """Share of all steps of the rollout ``records`` on which the fallback drove, in percent: the
    ``fallback_steps`` column (:meth:`FallbackCounter.per_episode`) over the ``length`` column, pooled over the
    episodes (a long episode weighs more than a short one)."""
    return 100.0 * float(records["fallback_steps"].sum() / records["length"].sum())
