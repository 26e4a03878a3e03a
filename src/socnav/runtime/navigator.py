"""`SafeNavigator`: the deployable safe navigator — observation, policy, MC-dropout, safety rule and fallback.
Plain arrays in (the robot's state and its tracked humans), a command ``(v, dtheta)`` out; no torch anywhere.

One decision:

1. the observation, built by the environment's own kernel (`socnav.sim.observation.observe_robot`);
2. ONE onnxruntime call on ``1 + K`` rows: row 0 with all-ones keep masks (the deterministic action the policy
   executes), rows 1..K with MC-dropout masks drawn from a `DropoutStream` (the uncertainty samples);
3. the safety layer's own parts: the uncertainty window (`WindowedUncertainty`), the nearest human and the
   collision-probability rule (`socnav.safety.rule`: eq. (10), or the ablation the thresholds' ``conditions``
   name, exactly as `socnav.safety.SafePolicy` applies it) and, where it fires (or fired within the last
   ``hold_steps`` steps), the cautious ORCA controller (`CautiousController`) in place of the policy — what
   `socnav.safety.SafePolicy` does for one robot (tested step for step against it), without its batch bookkeeping;
4. the action turned into ``(v, dtheta)`` by the simulator's own command kernel.

The humans handed to :meth:`SafeNavigator.act` are the robot's tracked state: the policy, the rule's proximity
terms and the fallback all read them (the runtime counterpart of the safety layer's ``perceived`` sensing; a
thresholds file's ``sensing`` field therefore changes nothing here).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from socnav.config import load_config
from socnav.runtime.network import DropoutStream, ExportedPolicy, MCBatch, Uniforms, keep_from_uniforms
from socnav.safety.cautious import CautiousController
from socnav.safety.rule import (RuleConditions, Thresholds, held_fallback, load_thresholds, nearest_human,
                                rule_conditions)
from socnav.sim.observation import observe_robot, robot_command
from socnav.uncertainty.stats import Uncertainty
from socnav.uncertainty.window import WindowedUncertainty

__all__ = ["Decision", "HumansState", "InputError", "RobotState", "SafeNavigator"]


class InputError(ValueError):
    """A robot or human state that the navigator cannot act on (wrong shape, NaN / inf, impossible value)."""


def _vector(owner: str, name: str, value: Any, size: int) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{owner}.{name} must be numeric, got {value!r} ({exc})") from None
    if array.shape != (size,):
        raise InputError(f"{owner}.{name} must have shape ({size},), got {array.shape}")
    if not _finite(array):
        raise InputError(f"{owner}.{name} must be finite, got {array.tolist()}")
    return array


def _finite(array: np.ndarray) -> bool:
    """Every element finite. One cheap test first (a NaN / inf anywhere makes the sum of squares NaN / inf); the
    exact element-wise test only where that sum is not finite (a bad value, or an overflow of huge values)."""
    return math.isfinite(np.vdot(array, array)) or bool(np.isfinite(array).all())


def _scalar(owner: str, name: str, value: Any, minimum: float = -math.inf, strict: bool = False) -> float:
    try:
        if type(value) is float or type(value) is int:  # the common case, without NumPy's per-call overhead
            number = float(value)
        else:
            number = float(value) if np.ndim(value) == 0 else math.nan
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    if not math.isfinite(number):
        raise InputError(f"{owner}.{name} must be a finite number, got {value!r}")
    if number < minimum or (strict and number == minimum):
        raise InputError(f"{owner}.{name} must be {'>' if strict else '>='} {minimum}, got {number}")
    return number


@dataclass(frozen=True)
class RobotState:
    """The robot's state in any fixed world frame (metres, seconds, radians).

    :param position: (2,) position. :param velocity: (2,) current velocity. :param heading: yaw (rad).
    :param goal: (2,) goal position. :param v_pref: preferred (maximum) speed, > 0. :param radius: body radius, >= 0.
    """

    position: Any
    velocity: Any
    heading: float
    goal: Any
    v_pref: float
    radius: float

    @classmethod
    def parse(cls, robot: RobotState | Mapping[str, Any]) -> RobotState:
        """A validated copy with float64 arrays; :class:`InputError` names the bad field."""
        fields = robot if isinstance(robot, Mapping) else robot.__dict__
        missing = {"position", "velocity", "heading", "goal", "v_pref", "radius"} - fields.keys()
        if missing:
            raise InputError(f"robot state lacks {sorted(missing)}")
        return cls(
            position=_vector("robot", "position", fields["position"], 2),
            velocity=_vector("robot", "velocity", fields["velocity"], 2),
            heading=_scalar("robot", "heading", fields["heading"]),
            goal=_vector("robot", "goal", fields["goal"], 2),
            v_pref=_scalar("robot", "v_pref", fields["v_pref"], minimum=0.0, strict=True),
            radius=_scalar("robot", "radius", fields["radius"], minimum=0.0),
        )


@dataclass(frozen=True)
class HumansState:
    """The tracked humans, same world frame: ``positions`` (n, 2), ``velocities`` (n, 2), ``radii`` (n,); n >= 0."""

    positions: Any = field(default_factory=lambda: np.zeros((0, 2)))
    velocities: Any = field(default_factory=lambda: np.zeros((0, 2)))
    radii: Any = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def parse(cls, humans: HumansState | Mapping[str, Any] | None) -> HumansState:
        """A validated copy with float64 arrays; :class:`InputError` says which array and row is wrong."""
        if humans is None:
            return cls()
        fields = humans if isinstance(humans, Mapping) else humans.__dict__
        unknown = fields.keys() - {"positions", "velocities", "radii"}
        if unknown:
            raise InputError(f"unknown human fields {sorted(unknown)}; allowed: positions, velocities, radii")
        arrays = {}
        for name, width in (("positions", 2), ("velocities", 2), ("radii", 0)):
            try:
                array = np.asarray(fields.get(name, ()), dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise InputError(f"humans.{name} must be numeric ({exc})") from None
            if array.size == 0:
                array = array.reshape((0, width) if width else (0,))
            expected = f"(n, {width})" if width else "(n,)"
            if array.ndim != (2 if width else 1) or (width and array.shape[1] != width):
                raise InputError(f"humans.{name} must have shape {expected}, got {array.shape}")
            if not _finite(array):
                bad = ~np.isfinite(array).all(axis=tuple(range(1, array.ndim)))
                raise InputError(f"humans.{name} is not finite in rows {np.flatnonzero(bad).tolist()}")
            arrays[name] = array
        positions, velocities, radii = arrays["positions"], arrays["velocities"], arrays["radii"]
        if not len(positions) == len(velocities) == len(radii):
            counts = {name: len(array) for name, array in arrays.items()}
            raise InputError(f"humans.positions, velocities and radii must have one row per human, got {counts}")
        if len(radii) and radii.min() < 0.0:
            raise InputError(f"humans.radii must be >= 0, got {radii.tolist()}")
        return cls(positions, velocities, radii)


@dataclass(frozen=True)
class Decision:
    """What the navigator decided for one control step.

    :param speed: commanded speed ``v`` (m/s, in [0, v_pref]). :param turn: heading change ``dtheta`` (rad) over
        the next control step. :param action: the normalised action in [-1, 1]^2 (the environment's action).
    :param fallback: the cautious ORCA controller acted (the collision rule fired, or fired within the last
        ``thresholds.hold_steps`` steps).
    :param uncertainty: this step's MC-dropout estimate (batch of one; ``mean_action`` is the sample mean).
    :param windowed: the windowed values the rule read: ``u_ep_speed``, ``u_ep_heading``, ``u_al_speed``,
        ``u_al_heading``, ``u_feat``. :param conditions: the rule's conditions (``c_ep``, ... as (1,) arrays).
    :param observation: the observation the network saw (batch of one).
    """

    speed: float
    turn: float
    action: np.ndarray
    fallback: bool
    uncertainty: Uncertainty
    windowed: dict[str, float]
    conditions: RuleConditions
    observation: dict[str, np.ndarray]

    @property
    def command(self) -> tuple[float, float]:
        """``(v, dtheta)``."""
        return self.speed, self.turn


class SafeNavigator:
    """Decide ``(v, dtheta)`` from the robot's state and the tracked humans with the exported policy, MC-dropout
    uncertainty, the collision-probability rule and the cautious ORCA fallback.

    Keeps the episode's state (uncertainty window, previous nearest gap): call :meth:`reset` at the start of every
    new navigation task. Build it with :meth:`load`.

    :param network: the exported policy network (`ExportedPolicy.load`).
    :param thresholds: safety thresholds (None: the file's; else a preset name, a `socnav calibrate` file, a
        mapping or a `Thresholds`).
    :param k: MC-dropout samples per decision (None: the file's K).
    :param uniforms: the dropout-uniform stream (None: ``DropoutStream(seed)``).
    :param seed: seed of the default stream (None: fresh entropy).
    """

    def __init__(self, network: ExportedPolicy, thresholds: Thresholds | str | Path | Mapping[str, Any] | None = None,
                 k: int | None = None, uniforms: Uniforms | None = None, seed: int | None = None) -> None:
        metadata = network.metadata
        self.network = network
        self.config = load_config(metadata["env_config"])
        safety = metadata["safety"]
        self.thresholds = load_thresholds(safety["thresholds"] if thresholds is None else thresholds)
        self.k = network.k if k is None else int(k)
        if self.k < 2:
            raise ValueError(f"MC-dropout needs k >= 2 samples, got k={self.k}")
        self.uniforms = DropoutStream(seed) if uniforms is None else uniforms
        self._window = WindowedUncertainty(1, window=int(safety["window"]))
        self.cautious = CautiousController(self.config, radius_scale=float(safety["radius_scale"]))
        self._previous_gap = np.full(1, np.nan)  # d(t-1) of this episode; NaN: none yet (c_ap holds)
        self._hold_left = np.zeros(1, dtype=np.int64)  # held fallback steps still owed (thresholds.hold_steps)
        self._batches: dict[tuple[int, int, bool], MCBatch] = {}  # per (K, human rows, any human)
        self._warm_up()

    def _warm_up(self) -> None:
        """Compile (or load) the numba kernels and prepare the onnxruntime session now, not at the first decision:
        the first fallback would otherwise stall the control loop. Touches neither the episode state nor the
        dropout stream."""
        observation = observe_robot(np.zeros(2), np.zeros(2), 0.0, np.ones(2), 1.0, 0.3, np.full((1, 2), 2.0),
                                    np.zeros((1, 2)), np.full(1, 0.3), self.network.max_humans)
        output = self.network.run(*self.network.trim(observation)[:3])
        self.cautious.predict(observation)
        robot_command(np.zeros(2), 1.0, self.config.max_heading_change)
        h, mean = np.zeros((1 + self.k, output.h.shape[1]), np.float32), np.zeros((1 + self.k, 2), np.float32)
        estimate = self.network.summarise(h[1:, None], mean[1:, None], mean[1:, None])  # a decision's layouts
        WindowedUncertainty(1, window=1).update(estimate)
        nearest_human(observation)
        keep_from_uniforms(np.ones(1, np.float32), self.network.p_test, np.ones(1, np.float32))

    @classmethod
    def load(cls, path: str | Path, thresholds: Thresholds | str | Path | Mapping[str, Any] | None = None,
             k: int | None = None, seed: int | None = None, uniforms: Uniforms | None = None,
             threads: int = 1) -> SafeNavigator:
        """Open a navigator file written by ``socnav export`` (onnxruntime with ``threads`` intra-op threads).

        :raises socnav.runtime.NavigatorLoadError: a missing, unreadable, non-ONNX, foreign or incompatible file.
        :raises socnav.safety.ThresholdsError: invalid ``thresholds``.
        """
        return cls(ExportedPolicy.load(path, threads=threads), thresholds=thresholds, k=k, uniforms=uniforms,
                   seed=seed)

    @property
    def max_humans(self) -> int:
        """Human rows of the observation; with more tracked humans the closest ones are kept."""
        return self.network.max_humans

    def reset(self) -> None:
        """Start a new episode: empty the uncertainty window, forget the previous nearest-human gap, end a hold."""
        self._window.reset()
        self._previous_gap[:] = np.nan
        self._hold_left[:] = 0

    def act(self, robot: RobotState | Mapping[str, Any],
            humans: HumansState | Mapping[str, Any] | None = None) -> Decision:
        """One control decision.

        :param robot: a :class:`RobotState` or a mapping with its fields (position, velocity, heading, goal,
            v_pref, radius), world frame.
        :param humans: a :class:`HumansState` or a mapping (positions (n, 2), velocities (n, 2), radii (n,)), or
            None for nobody around. With more than :attr:`max_humans` humans, the ``max_humans`` closest (by gap
            to the robot) are kept — the simulator's own rule; the others are ignored by the policy, the rule
            and the fallback alike.
        :raises InputError: a wrong shape, a NaN / inf, ``v_pref <= 0`` or a negative radius (nothing reaches
            onnxruntime).
        """
        robot = RobotState.parse(robot)
        humans = HumansState.parse(humans)
        observation = observe_robot(robot.position, robot.velocity, robot.heading, robot.goal, robot.v_pref,
                                    robot.radius, humans.positions, humans.velocities, humans.radii,
                                    self.network.max_humans)
        return self.act_observation(observation)

    def act_observation(self, observation: Mapping[str, np.ndarray]) -> Decision:
        """One decision from an observation already in the environment's layout (batch of one, float32), e.g.
        one from :func:`socnav.sim.observation.observe_robot`; unlike :meth:`act` it is not checked."""
        action, estimate = self._policy_and_uncertainty(observation)
        windowed = self._window.update(estimate)
        nearest = nearest_human(observation)
        conditions = rule_conditions(windowed.u_ep_heading, windowed.u_feat, nearest.gap,
                                     nearest.speed(self.thresholds.proximity), self._previous_gap, self.thresholds)
        self._previous_gap = np.where(nearest.present, nearest.gap, np.nan)  # no human: nothing to compare next
        held, self._hold_left = held_fallback(conditions.p_col, self._hold_left, self.thresholds.hold_steps)
        fallback = bool(held[0])
        if fallback:
            action = self.cautious.predict(observation)[0][0]
        speed, turn = robot_command(action, float(observation["robot"][0, 3]), self.config.max_heading_change)
        (u_ep_speed, u_ep_heading), (u_al_speed, u_al_heading) = windowed.u_ep[0].tolist(), windowed.u_al[0].tolist()
        values = {"u_ep_speed": u_ep_speed, "u_ep_heading": u_ep_heading, "u_al_speed": u_al_speed,
                  "u_al_heading": u_al_heading, "u_feat": float(windowed.u_feat[0])}
        return Decision(speed=speed, turn=turn, action=action, fallback=fallback, uncertainty=estimate,
                        windowed=values, conditions=conditions, observation=dict(observation))

    def _policy_and_uncertainty(self, observation: Mapping[str, np.ndarray]) -> tuple[np.ndarray, Uncertainty]:
        """ONE graph call on ``1 + K`` rows: row 0 without dropout (the action, clipped to [-1, 1]), rows 1..K with
        MC-dropout masks from the stream (this step's uncertainty)."""
        network = self.network
        robot, humans, mask, any_human = network.trim(observation)
        key = (self.k, humans.shape[1], any_human)
        batch = self._batches.get(key)
        if batch is None:  # first decision with this many humans: buffers + IO binding, kept for the next ones
            batch = self._batches[key] = network.mc_batch(self.k, humans.shape[1], any_human, deterministic_rows=1)
        batch.run(robot, humans, mask, self.uniforms, network.p_test)
        estimate = network.summarise(batch.h[1:, None], batch.mean[1:, None], batch.log_std[1:, None])
        return np.minimum(np.maximum(batch.mean[0], -1.0), 1.0), estimate  # np.clip costs more at this size

    def __repr__(self) -> str:
        return f"SafeNavigator({self.network!r}, K={self.k}, thresholds={self.thresholds!r})"
