"""Triggers: the one plug point for what decides the hand-over to the fallback. A trigger turns what the robot
senses (and, where it wants them, the policy's action and the uncertainty estimates) into a per-step risk score.

Every trigger scores each environment of a batch; HIGHER means riskier, and the layer hands over where
``score > threshold``. The threshold is what the calibration chooses (docs/uncertainty-safety.md, "Triggers"): a
quantile of the scores on unperturbed calibration steps, checked by replays against the false-activation budget.
The paper's rule (eq. (10)) and its ablations are triggers too (:class:`RuleTrigger`): their decision is the
rule's boolean, their thresholds the rule's (`socnav.safety.rule.Thresholds`, calibrated by its own stages).

A new trigger is a subclass of :class:`ScoreTrigger` with a ``name``, a pydantic ``Params`` model (its parameters,
validated) and :meth:`ScoreTrigger.score`, registered with :func:`register_trigger`. What a deployment stores is a
:class:`TriggerSpec` (name, parameters, threshold, sensing, hold): an immutable description from which
:func:`make_trigger` builds a fresh, stateful trigger for every rollout.

Analytic triggers here (the robot's intended velocity is the policy's action, as the simulator would apply it
without action noise; every human keeps its observed velocity):

- ``time-to-collision``: minus the earliest time at which any human's disc touches the robot's (``-inf``: never);
- ``closing-gap``: ``-(d - beta * v_close)`` of the nearest human, the gap extrapolated ``beta`` seconds ahead;
- ``predicted-clearance``: minus the smallest gap to any human over the next ``horizon`` seconds.

The conformal shield (`socnav.safety.conformal`) and the learned collision-risk model (`socnav.safety.risk_model`)
register themselves the same way (`socnav.safety` imports both, so every import of a trigger module finds them).
"""

from __future__ import annotations

import difflib
import json
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import yaml
from pydantic import ConfigDict, Field, StrictInt, ValidationError

from socnav.config import StrictModel, format_validation_error, read_mapping_file
from socnav.io import write_text_atomic
from socnav.safety.rule import (
    RULE_CONDITIONS,
    NearestHuman,
    Thresholds,
    ThresholdsError,
    rule_conditions,
)

__all__ = [
    "TRIGGERS",
    "ClosingGapTrigger",
    "PredictedClearanceTrigger",
    "RuleTrigger",
    "SafetyDecision",
    "ScoreTrigger",
    "TimeToCollisionTrigger",
    "Trigger",
    "TriggerError",
    "TriggerInputs",
    "TriggerSpec",
    "decision_fields",
    "intended_relative_motion",
    "load_safety",
    "make_trigger",
    "never_fires",
    "register_trigger",
    "save_trigger_spec",
    "trigger_names",
]

SPEED, HEADING = 0, 1
#: Columns of a human row (socnav.envs.spaces.HUMAN_FEATURE_NAMES) the triggers read.
REL_X, REL_Y, REL_VX, REL_VY, COMBINED_RADIUS, GAP = 0, 1, 2, 3, 5, 6


class TriggerError(ValueError):
    """A trigger name, its parameters, its threshold or its file is invalid; the message names the field."""


@dataclass
class TriggerInputs:
    """What a trigger may read for one step of a batch of B environments.

    ``observation``: the SENSED batched observation (the robot's own, or the noise-free one with ``sensing: true``);
    ``actions``: (B, 2) the policy's actions in [-1, 1]^2; ``uncertainty``: windowed (B,) arrays ``u_ep_speed``,
    ``u_ep_heading``, ``u_al_speed``, ``u_al_heading``, ``u_feat`` (zeros when nothing estimates them);
    ``nearest``: the nearest human; ``previous_gap``: (B,) its gap at the previous step, NaN at an episode's first;
    ``time_step`` (s), ``max_heading_change`` (rad per step): the world's.
    """

    observation: Mapping[str, np.ndarray]
    actions: np.ndarray
    uncertainty: Mapping[str, np.ndarray]
    nearest: NearestHuman
    previous_gap: np.ndarray
    time_step: float
    max_heading_change: float


class Trigger(ABC):
    """A stateful per-step hand-over decision for a batch of environments (built by :func:`make_trigger`)."""

    reads_uncertainty: bool = False

    def allocate(self, n_envs: int) -> None:  # noqa: B027 -- stateless triggers keep nothing
        """Make room for ``n_envs`` environments (called once, before the first step)."""

    def reset(self, envs: np.ndarray) -> None:  # noqa: B027 -- stateless triggers keep nothing
        """Environments ``envs`` (indices) start new episodes."""

    @abstractmethod
    def fires(self, inputs: TriggerInputs) -> np.ndarray:
        """(B,) bool: where the fallback takes over this step. Called once per step, in order."""


# ------------------------------------------------------------------------------------------------ specs

Sensing = Literal["perceived", "true"]


class TriggerSpec(StrictModel):
    """An immutable, validated description of a score trigger: what a calibration chooses and a file stores.

    ``trigger``: a registered name (:func:`trigger_names`); ``params``: its parameters (checked against its
    ``Params``); ``threshold``: it fires where its score exceeds this (``inf``: never); ``sensing``: what the
    trigger and the fallback read (the observation or the simulator's noise-free one); ``hold_steps``: steps the
    fallback keeps control after the trigger last fired; ``model``: a file the trigger loads (the risk model's
    weights), relative to the spec's own file when read from one.
    """

    model_config = ConfigDict(frozen=True)

    trigger: str = Field(..., description="registered trigger name")
    params: dict[str, float] = Field(default_factory=dict, description="the trigger's parameters")
    threshold: float = Field(..., allow_inf_nan=True, description="fires where the score exceeds this (inf: never)")
    sensing: Sensing = Field("perceived", description="what the trigger and the fallback read")
    hold_steps: StrictInt = Field(0, ge=0, le=1000, description="steps the fallback keeps control after firing")
    model: str | None = Field(None, description="file of the trigger's learned model (risk-model)")

    def __hash__(self) -> int:  # dict fields make pydantic's frozen hash fail: hash the canonical JSON
        return hash(self.model_dump_json())

    @property
    def uses_uncertainty(self) -> bool:
        """Whether the trigger reads the uncertainty estimates (the layer then needs an estimator)."""
        return trigger_class(self.trigger).spec_reads_uncertainty(self)

    @classmethod
    def create(cls, data: Mapping[str, Any] | None = None, **fields: Any) -> TriggerSpec:
        """Validate ``data`` / keyword fields (the name against the registry, the parameters against the trigger's
        ``Params``); raise :class:`TriggerError` naming the bad field."""
        merged = {**dict(data or {}), **fields}
        try:
            spec = cls.model_validate(merged)
        except ValidationError as exc:
            raise TriggerError(format_validation_error(exc, "invalid trigger:", cls)) from None
        if math.isnan(spec.threshold):
            raise TriggerError("invalid trigger: threshold must be a number (inf allowed), not NaN")
        trigger = trigger_class(spec.trigger)
        trigger.checked_params(spec.params)
        return spec

    def with_threshold(self, threshold: float) -> TriggerSpec:
        """The same trigger with another threshold."""
        return TriggerSpec.create(self.model_dump(), threshold=float(threshold))


# ------------------------------------------------------------------------------------------------ registry

TRIGGERS: dict[str, type[ScoreTrigger]] = {}


def register_trigger(cls: type[ScoreTrigger]) -> type[ScoreTrigger]:
    """Class decorator: make ``cls`` available under ``cls.name`` (the name must be new)."""
    if cls.name in TRIGGERS or cls.name in RULE_CONDITIONS:
        raise ValueError(f"trigger {cls.name!r} is registered already")
    TRIGGERS[cls.name] = cls
    return cls


def trigger_names() -> tuple[str, ...]:
    """Every trigger a layer can use: the rule's (``paper``, ``proximity-only``, ``uncertainty-only``) and the
    registered score triggers."""
    return (*RULE_CONDITIONS, *TRIGGERS)


def trigger_class(name: str) -> type[ScoreTrigger]:
    """The registered score trigger ``name``; :class:`TriggerError` with a did-you-mean and the list otherwise."""
    if name in TRIGGERS:
        return TRIGGERS[name]
    allowed = trigger_names()
    close = difflib.get_close_matches(name, allowed, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    if name in RULE_CONDITIONS:
        raise TriggerError(f"trigger {name!r} is the paper's rule: give its thresholds (socnav.safety.Thresholds)")
    raise TriggerError(f"unknown trigger {name!r}; {hint}allowed: {', '.join(allowed)}")


def make_trigger(spec: TriggerSpec | Thresholds, base: Path | None = None) -> Trigger:
    """A fresh trigger for one rollout: a :class:`RuleTrigger` for rule thresholds, else the registered class.

    :param base: the directory a spec's ``model`` file is relative to (its own file's).
    """
    if isinstance(spec, Thresholds):
        return RuleTrigger(spec)
    return trigger_class(spec.trigger)(spec, base)


# ------------------------------------------------------------------------------------------------ triggers

class RuleTrigger(Trigger):
    """The paper's probability-of-collision rule (eq. (10)) or one of its ablations, as a trigger.

    ``last_conditions`` holds the rule's conditions of the last step (`socnav.safety.rule.RuleConditions`)."""

    def __init__(self, thresholds: Thresholds) -> None:
        self.thresholds = thresholds
        self.reads_uncertainty = thresholds.uses_uncertainty
        self.last_conditions: Any = None

    def fires(self, inputs: TriggerInputs) -> np.ndarray:
        uncertainty = inputs.uncertainty
        self.last_conditions = rule_conditions(
            uncertainty["u_ep_heading"], uncertainty["u_feat"], inputs.nearest.gap,
            inputs.nearest.speed(self.thresholds.proximity), inputs.previous_gap, self.thresholds)
        return np.asarray(self.last_conditions.p_col)


class ScoreTrigger(Trigger):
    """A trigger that fires where its risk score exceeds the spec's threshold; ``last_scores`` holds the last
    step's scores (for the calibration's records).

    Subclasses set ``name``, ``Params`` (a StrictModel of the parameters, with defaults) and implement
    :meth:`score`; stateful ones also :meth:`allocate` and :meth:`reset`."""

    name: ClassVar[str]
    Params: ClassVar[type[StrictModel]]
    description: ClassVar[str] = ""

    def __init__(self, spec: TriggerSpec, base: Path | None = None) -> None:
        self.spec = spec
        self.params = self.checked_params(spec.params)
        self.reads_uncertainty = self.spec_reads_uncertainty(spec)
        self.last_scores = np.zeros(0)

    @classmethod
    def checked_params(cls, params: Mapping[str, float]) -> Any:
        """The trigger's validated parameters (:class:`TriggerError` naming the bad one)."""
        try:
            return cls.Params.model_validate(dict(params))
        except ValidationError as exc:
            raise TriggerError(format_validation_error(exc, f"invalid parameters of trigger {cls.name!r}:",
                                                       cls.Params)) from None

    @classmethod
    def spec_reads_uncertainty(cls, spec: TriggerSpec) -> bool:
        """Whether a trigger of this spec reads the uncertainty estimates (analytic triggers: never)."""
        return False

    @abstractmethod
    def score(self, inputs: TriggerInputs) -> np.ndarray:
        """(B,) float risk scores, higher = riskier (``-inf``: no risk at all)."""

    def fires(self, inputs: TriggerInputs) -> np.ndarray:
        self.last_scores = np.asarray(self.score(inputs), dtype=np.float64)
        return self.last_scores > self.spec.threshold


def intended_relative_motion(inputs: TriggerInputs) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every human's relative position and relative velocity if the robot drove at the velocity its action asks
    for (the simulator's command without action noise, turned by the action's heading change), in the observation's
    goal frame: ``(positions (B, H, 2), velocities (B, H, 2), combined radii (B, H), mask (B, H) bool)``.

    Humans keep their observed velocities: ``v_human = v_rel + v_robot_now``, so ``v_rel' = v_rel + v_robot_now -
    v_robot_intended``."""
    observation = inputs.observation
    humans = np.asarray(observation["humans"], dtype=np.float64)
    mask = np.asarray(observation["humans_mask"]) > 0.5
    robot = np.asarray(observation["robot"], dtype=np.float64)
    heading, speed, preferred_speed = robot[:, 1], robot[:, 2], robot[:, 3]
    actions = np.clip(np.asarray(inputs.actions, dtype=np.float64), -1.0, 1.0)
    intended_speed = preferred_speed * (actions[:, SPEED] + 1.0) / 2.0
    intended_heading = heading + inputs.max_heading_change * actions[:, HEADING]
    now = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=-1)
    intended = np.stack([intended_speed * np.cos(intended_heading), intended_speed * np.sin(intended_heading)],
                        axis=-1)
    velocities = humans[:, :, REL_VX:REL_VY + 1] + (now - intended)[:, None, :]
    return humans[:, :, REL_X:REL_Y + 1], velocities, humans[:, :, COMBINED_RADIUS], mask


def time_to_contact(positions: np.ndarray, velocities: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Earliest ``t >= 0`` with ``|p + v t| = R`` for each row (0 if the discs already touch; ``inf``: never)."""
    a = (velocities ** 2).sum(-1)
    b = (positions * velocities).sum(-1)
    c = (positions ** 2).sum(-1) - radii ** 2
    discriminant = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        root = (-b - np.sqrt(np.maximum(discriminant, 0.0))) / a
    meets = (discriminant >= 0.0) & (b < 0.0) & (a > 0.0)
    ttc = np.where(meets, np.maximum(root, 0.0), np.inf)
    return np.where(c <= 0.0, 0.0, ttc)


class _HorizonParams(StrictModel):
    horizon: float = Field(3.0, gt=0, le=30, description="seconds looked ahead")


@register_trigger
class TimeToCollisionTrigger(ScoreTrigger):
    """Minus the time (s) until the robot's disc, driven at the velocity its action asks for, first touches a
    human's disc moving at its observed velocity (``-horizon`` and below: no contact within ``horizon`` s; ``-inf``:
    none at all). Fires where contact comes sooner than ``-threshold`` seconds."""

    name = "time-to-collision"
    Params = _HorizonParams
    description = "time to contact under constant velocities (the policy's intended one for the robot)"

    def score(self, inputs: TriggerInputs) -> np.ndarray:
        positions, velocities, radii, mask = intended_relative_motion(inputs)
        ttc = np.where(mask, time_to_contact(positions, velocities, radii), np.inf)
        soonest = ttc.min(axis=1) if ttc.shape[1] else np.full(len(ttc), np.inf)
        return -soonest


class _ClosingGapParams(StrictModel):
    beta: float = Field(1.0, ge=0, le=100, description="seconds the gap is extrapolated")


@register_trigger
class ClosingGapTrigger(ScoreTrigger):
    """The closing-speed gap of the nearest human: ``-(d - beta * v_close)``, the gap ``beta`` seconds ahead at the
    rate it shrinks now, negated (``-inf`` without a human). Fires where that gap is below ``-threshold`` metres."""

    name = "closing-gap"
    Params = _ClosingGapParams
    description = "nearest gap extrapolated by its closing speed"

    def score(self, inputs: TriggerInputs) -> np.ndarray:
        nearest = inputs.nearest
        gap = nearest.gap - self.params.beta * nearest.closing_speed
        return np.where(nearest.present, -gap, -np.inf)


def predicted_clearance(inputs: TriggerInputs, horizon: float) -> np.ndarray:
    """(B,) the smallest gap (m) to any human over the next ``horizon`` seconds, the robot at its intended velocity
    and every human at its observed one (``inf`` without humans; negative: the discs would overlap)."""
    positions, velocities, radii, mask = intended_relative_motion(inputs)
    speed_squared = (velocities ** 2).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        closest_time = np.where(speed_squared > 0, -(positions * velocities).sum(-1) / speed_squared, 0.0)
    closest_time = np.clip(closest_time, 0.0, horizon)
    closest = positions + velocities * closest_time[..., None]
    gaps = np.where(mask, np.sqrt((closest ** 2).sum(-1)) - radii, np.inf)
    return gaps.min(axis=1) if gaps.shape[1] else np.full(len(gaps), np.inf)


@register_trigger
class PredictedClearanceTrigger(ScoreTrigger):
    """Minus the smallest gap to any human over the next ``horizon`` seconds (:func:`predicted_clearance`). Fires
    where the clearance would fall below ``-threshold`` metres."""

    name = "predicted-clearance"
    Params = _HorizonParams
    description = "smallest gap over the horizon under constant velocities"

    def score(self, inputs: TriggerInputs) -> np.ndarray:
        return -predicted_clearance(inputs, self.params.horizon)


# ------------------------------------------------------------------------------------------------ files

#: What a safety layer decides with: the rule's thresholds or a score trigger's spec.
SafetyDecision = Thresholds | TriggerSpec


def decision_fields(decision: SafetyDecision) -> dict[str, Any]:
    """Flat fields describing ``decision`` for a table row: the thresholds' fields, or the trigger's name,
    threshold, sensing, hold and parameters."""
    if isinstance(decision, Thresholds):
        return decision.model_dump()
    return {"trigger": decision.trigger, "threshold": decision.threshold, "sensing": decision.sensing,
            "hold_steps": decision.hold_steps, **decision.params}


def never_fires(decision: SafetyDecision) -> bool:
    """Whether ``decision`` can never hand over (the rule's `Thresholds.never`, a trigger at ``threshold = inf``)."""
    if isinstance(decision, Thresholds):
        return decision == Thresholds.never()
    return decision.threshold == math.inf


def load_safety(path_or_name: str | Path | Mapping[str, Any] | Thresholds | TriggerSpec
                ) -> Thresholds | TriggerSpec:
    """What a safety layer decides with: rule thresholds (a preset name, a file or mapping without a ``trigger``
    field, or naming ``trigger: paper`` / an ablation) or a score trigger's spec (a file or mapping with a
    registered ``trigger``), or a layer shipped beside a pretrained policy by name (`shipped_layers`, e.g.
    ``pretrained-maps_time-to-collision``). A spec read from a file keeps its ``model`` path relative to the file."""
    from socnav.safety.rule import load_thresholds, shipped_layers

    if isinstance(path_or_name, (Thresholds, TriggerSpec)):
        return path_or_name
    if isinstance(path_or_name, Mapping):
        return _from_mapping(dict(path_or_name), None)
    path = Path(path_or_name)
    if not path.is_file():
        shipped = shipped_layers().get(str(path_or_name)) if not path.suffix else None
        if shipped is None:
            return load_thresholds(path_or_name)  # a preset name, or its clear error
        path = shipped
    data = read_mapping_file(path, "trigger", TriggerError, allow_json=True)
    try:
        return _from_mapping(data, path)
    except (TriggerError, ThresholdsError) as exc:
        message = str(exc)
        raise type(exc)(message if str(path) in message else f"{message} [file: {path}]") from None


def _from_mapping(data: dict[str, Any], path: Path | None) -> Thresholds | TriggerSpec:
    name = data.get("trigger")
    if name is None or name in RULE_CONDITIONS:
        fields = data.get("thresholds", data) if isinstance(data.get("thresholds"), dict) else data
        fields = {key: value for key, value in fields.items() if key != "trigger"}
        if name is not None and name != "paper":
            fields["conditions"] = name
        return Thresholds.create(fields)
    spec = TriggerSpec.create({key: value for key, value in data.items() if key != "report"})  # report: notes
    if spec.model is not None and path is not None and not Path(spec.model).is_absolute():
        spec = TriggerSpec.create(spec.model_dump(), model=str(path.parent / spec.model))
    return spec


def save_trigger_spec(spec: TriggerSpec, path: str | Path, extra: Mapping[str, Any] | None = None) -> Path:
    """Write ``spec`` (and ``extra`` report fields under ``report``) atomically: JSON for ``.json``, else YAML."""
    path = Path(path)
    data: dict[str, Any] = spec.model_dump()
    if spec.model is not None:
        model = Path(spec.model)
        data["model"] = model.name if model.parent.resolve() == path.parent.resolve() else str(model)
    if extra:
        data["report"] = dict(extra)
    text = json.dumps(data, indent=2) + "\n" if path.suffix == ".json" else yaml.safe_dump(data, sort_keys=False)
    return write_text_atomic(path, text)
