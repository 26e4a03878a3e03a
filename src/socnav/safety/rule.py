"""The probability-of-collision rule of the safety layer (paper eq. (10), SPEC section 5) and its thresholds.

    P(col) = 1  iff  (c_ep or c_feat) and c_prox and c_ap,   else 0

- ``c_ep   = [windowed u_ep(heading) > lambda_ep]``
- ``c_feat = [windowed u_feat > lambda_feat]``
- ``c_prox`` with ``d`` the gap to the nearest human, in one of two variants (``Thresholds.proximity``):
  ``abs-relative-speed`` (default, as printed in the paper): ``[d + beta1 * |dv| < lambda_prox]``, ``|dv|`` the
  norm of the relative velocity. Note that, as printed, a FASTER relative motion makes the condition HARDER to
  meet (with the paper's ``lambda_prox = 0.9, beta1 = 0.5`` a head-on encounter closing at 2 m/s is flagged only
  at ``d < -0.1``, i.e. never before contact): fast encounters are left to the policy.
  ``closing-speed`` (option): ``[d - beta1 * v_close < lambda_prox]`` with ``v_close = -dd/dt`` the rate at
  which the gap shrinks: the gap extrapolated ``beta1`` seconds ahead (the printed formula with a SIGNED
  ``dv = dd/dt``), so approaching fast makes it easier to meet and receding harder.
- ``c_ap   = [d(t) <= d(t-1)]``: the robot is approaching. The paper prints ``d(t-1) <= d(t)`` but describes
  "once the robot is moving away from the human, the risky scenario was averted", i.e. approaching; we implement
  the described meaning. ``d(t-1)`` is the nearest-human gap of the previous step of the same episode (the
  nearest human may have changed: then the rule asks whether the crowd's nearest gap is shrinking). At the first
  step of an episode there is no previous gap (pass NaN): we take ``c_ap = True`` -- the conservative choice, the
  rule must not be blinded for a step; at that step all velocities are zero anyway and the proximity condition
  decides.

All inputs are taken from the robot's own (possibly noisy) observation; see :func:`nearest_human`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from socnav.io import write_text_atomic

__all__ = [
    "PROXIMITY_VARIANTS",
    "THRESHOLD_PRESETS",
    "NearestHuman",
    "RuleConditions",
    "Thresholds",
    "ThresholdsError",
    "collision_probability",
    "load_thresholds",
    "nearest_human",
    "proximity_score",
    "rule_conditions",
    "save_thresholds",
]

SPEED, HEADING = 0, 1  # action dimensions of `Uncertainty.u_ep`

Proximity = Literal["abs-relative-speed", "closing-speed"]
PROXIMITY_VARIANTS: tuple[str, ...] = ("abs-relative-speed", "closing-speed")

#: Paper thresholds (lambda_ep, lambda_feat, lambda_prox, beta1) per estimator kind (paper V-B.3).
THRESHOLD_PRESETS: dict[str, tuple[float, float, float, float]] = {
    "mc": (0.03, 0.3, 0.9, 0.5),
    "ensemble": (0.08, 0.0033, 0.9, 0.5),
}


class ThresholdsError(ValueError):
    """Thresholds are invalid; the message names the field and what is allowed."""


class Thresholds(BaseModel):
    """Constants of the collision-probability rule (immutable, validated, unknown fields rejected).

    ``lambda_ep``, ``lambda_feat``: uncertainty thresholds (>= 0; ``inf`` switches that condition off);
    ``lambda_prox``: proximity threshold in metres (>= 0); ``beta1``: weight of the speed term (>= 0, s);
    ``proximity``: ``abs-relative-speed`` (``d + beta1 |dv|``, as printed in the paper) or ``closing-speed``
    (``d - beta1 v_close``); see the module docstring.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    lambda_ep: float = Field(..., ge=0, description="windowed epistemic heading uncertainty threshold")
    lambda_feat: float = Field(..., ge=0, description="windowed predictive feature uncertainty threshold")
    lambda_prox: float = Field(..., ge=0, description="metres: d + beta1 * speed below this is 'close'")
    beta1: float = Field(..., ge=0, allow_inf_nan=False, description="seconds: weight of the speed term")
    proximity: Proximity = Field("abs-relative-speed", description="speed term of c_prox")

    @field_validator("lambda_ep", "lambda_feat", "lambda_prox")
    @classmethod
    def _not_nan(cls, value: float) -> float:
        if math.isnan(value):
            raise ValueError("must be a number (inf allowed), not NaN")
        return value

    @classmethod
    def create(cls, data: Mapping[str, Any] | None = None, **fields: Any) -> "Thresholds":
        """Validate ``data`` / keyword fields; raise :class:`ThresholdsError` naming the bad field."""
        merged = {**dict(data or {}), **fields}
        try:
            return cls.model_validate(merged)
        except ValidationError as exc:
            raise ThresholdsError(_format_error(exc)) from None

    @classmethod
    def preset(cls, name: str, proximity: Proximity = "abs-relative-speed") -> "Thresholds":
        """The paper's thresholds for ``mc`` (MC-dropout) or ``ensemble``."""
        if name not in THRESHOLD_PRESETS:
            raise ThresholdsError(f"unknown thresholds preset {name!r}; allowed: {', '.join(THRESHOLD_PRESETS)}")
        lambda_ep, lambda_feat, lambda_prox, beta1 = THRESHOLD_PRESETS[name]
        return cls.create(lambda_ep=lambda_ep, lambda_feat=lambda_feat, lambda_prox=lambda_prox, beta1=beta1,
                          proximity=proximity)

    @classmethod
    def never(cls) -> "Thresholds":
        """Thresholds whose uncertainty conditions never hold: the rule never fires (a plain policy)."""
        return cls.create(lambda_ep=math.inf, lambda_feat=math.inf, lambda_prox=0.0, beta1=0.0)


def _format_error(error: ValidationError) -> str:
    allowed = ", ".join(Thresholds.model_fields)
    lines = ["invalid safety thresholds:"]
    for item in error.errors():
        field = ".".join(str(p) for p in item["loc"]) or "<root>"
        message = item["msg"]
        if item["type"] == "extra_forbidden":
            message = f"unknown field; allowed fields: {allowed}"
        elif item["type"] == "missing":
            message = "missing; required fields: lambda_ep, lambda_feat, lambda_prox, beta1 (optional: proximity)"
        lines.append(f"  - {field}: {message} (got {item.get('input')!r})")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ files

def load_thresholds(path_or_name: Union[str, Path, Mapping[str, Any], Thresholds]) -> Thresholds:
    """Thresholds from a preset name (``mc``, ``ensemble``), a YAML/JSON file, a mapping or a Thresholds.

    A file holds the fields at its top level or under a ``thresholds`` key. A name that is both a preset and an
    existing file is read as the file.
    """
    if isinstance(path_or_name, Thresholds):
        return path_or_name
    if isinstance(path_or_name, Mapping):
        return Thresholds.create(path_or_name)
    path = Path(path_or_name)
    if not path.is_file():
        if isinstance(path_or_name, str) and path_or_name in THRESHOLD_PRESETS:
            return Thresholds.preset(path_or_name)
        raise ThresholdsError(
            f"thresholds file not found: {path} (or use a preset name: {', '.join(THRESHOLD_PRESETS)})"
        )
    text = path.read_text()
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ThresholdsError(f"thresholds file {path} is not valid {path.suffix.lstrip('.') or 'YAML'}: {exc}") from exc
    if isinstance(data, dict) and isinstance(data.get("thresholds"), dict):
        data = data["thresholds"]
    if not isinstance(data, dict):
        raise ThresholdsError(f"thresholds file {path} must hold a mapping of fields, got {type(data).__name__}")
    try:
        return Thresholds.create(data)
    except ThresholdsError as exc:
        raise ThresholdsError(f"{exc} [file: {path}]") from None


def save_thresholds(thresholds: Thresholds, path: Union[str, Path]) -> Path:
    """Write thresholds atomically: JSON for a ``.json`` suffix, YAML otherwise. ``inf`` round-trips."""
    path = Path(path)
    data = thresholds.model_dump()
    if path.suffix == ".json":
        text = json.dumps(data, indent=2) + "\n"  # inf is written as Infinity, which json.loads reads back
    else:
        text = yaml.safe_dump(data, sort_keys=False)
    return write_text_atomic(path, text)


# ------------------------------------------------------------------------------------------------ the rule

@dataclass(frozen=True)
class NearestHuman:
    """The nearest human of each environment, from the observation (all (B,) arrays).

    ``gap``: centre distance minus combined radius (``inf`` without humans); ``relative_speed``: ``|dv|``;
    ``closing_speed``: ``-d(gap)/dt = -(p_rel . v_rel) / |p_rel|`` (positive when approaching); ``present``.
    """

    gap: np.ndarray
    relative_speed: np.ndarray
    closing_speed: np.ndarray
    present: np.ndarray

    def speed(self, proximity: Proximity) -> np.ndarray:
        """The speed input of ``c_prox`` for the given variant: ``|dv|`` or ``v_close``."""
        _check_proximity(proximity)
        return self.relative_speed if proximity == "abs-relative-speed" else self.closing_speed


def nearest_human(observation: Mapping[str, np.ndarray]) -> NearestHuman:
    """Read the nearest human of each environment from a batched observation (SPEC section 2 layout).

    Rows are real humans first, sorted farthest to closest, so the nearest human is the LAST real row
    (``humans_mask`` is a prefix). Environments without humans get ``gap = inf`` and zero speeds.
    """
    humans = np.asarray(observation["humans"], dtype=np.float64)
    mask = np.asarray(observation["humans_mask"])
    if humans.ndim == 2:
        humans, mask = humans[None], mask[None]
    count = (mask > 0.5).sum(axis=1)
    present = count > 0
    rows = humans[np.arange(len(humans)), np.maximum(count - 1, 0)]
    rel_pos, rel_vel = rows[:, 0:2], rows[:, 2:4]
    distance = np.linalg.norm(rel_pos, axis=1)
    relative_speed = np.linalg.norm(rel_vel, axis=1)
    closing = -np.einsum("ij,ij->i", rel_pos, rel_vel) / np.maximum(distance, 1e-9)
    return NearestHuman(
        gap=np.where(present, rows[:, 6], np.inf),
        relative_speed=np.where(present, relative_speed, 0.0),
        closing_speed=np.where(present, closing, 0.0),
        present=present,
    )


def _check_proximity(proximity: str) -> None:
    if proximity not in PROXIMITY_VARIANTS:
        raise ThresholdsError(f"unknown proximity variant {proximity!r}; allowed: {', '.join(PROXIMITY_VARIANTS)}")


def proximity_score(gap: Any, speed: Any, beta1: float, proximity: Proximity = "abs-relative-speed") -> np.ndarray:
    """The left side of ``c_prox``: ``d + beta1 * |speed|`` (abs-relative-speed, ``speed = |dv|``) or
    ``d - beta1 * speed`` (closing-speed, ``speed = v_close``: the gap extrapolated ``beta1`` seconds ahead)."""
    _check_proximity(proximity)
    speed = np.asarray(speed, dtype=np.float64)
    term = np.abs(speed) if proximity == "abs-relative-speed" else -speed
    return np.asarray(gap, dtype=np.float64) + beta1 * term


@dataclass(frozen=True)
class RuleConditions:
    """The rule's conditions for a batch (bool (B,) arrays) and the collision probability ``p_col``."""

    c_ep: np.ndarray
    c_feat: np.ndarray
    c_prox: np.ndarray
    c_ap: np.ndarray

    @property
    def p_col(self) -> np.ndarray:
        """``(c_ep or c_feat) and c_prox and c_ap`` -- where the cautious controller takes over."""
        return (self.c_ep | self.c_feat) & self.c_prox & self.c_ap

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"c_ep": self.c_ep, "c_feat": self.c_feat, "c_prox": self.c_prox, "c_ap": self.c_ap,
                "p_col": self.p_col}


def rule_conditions(
    u_ep_heading: Any, u_feat: Any, gap: Any, relative_speed: Any, previous_gap: Any, thresholds: Thresholds
) -> RuleConditions:
    """Evaluate every condition of the rule. Inputs are (B,) arrays (or scalars):

    ``u_ep_heading``, ``u_feat``: WINDOWED uncertainties; ``gap``: nearest-human gap ``d(t)`` (``inf``: no human);
    ``relative_speed``: the speed input of ``thresholds.proximity``: ``|dv|`` (abs-relative-speed) or the closing
    speed ``v_close = -dd/dt`` (closing-speed), e.g. ``nearest_human(obs).speed(thresholds.proximity)``;
    ``previous_gap``: ``d(t-1)`` of the same episode, NaN at its first step (then ``c_ap`` is True).
    """
    u_ep_heading, u_feat, gap, previous_gap = (np.asarray(a, dtype=np.float64)
                                               for a in (u_ep_heading, u_feat, gap, previous_gap))
    c_ep = u_ep_heading > thresholds.lambda_ep
    c_feat = u_feat > thresholds.lambda_feat
    score = proximity_score(gap, relative_speed, thresholds.beta1, thresholds.proximity)
    c_prox = np.isfinite(gap) & (score < thresholds.lambda_prox)  # no human: never close
    c_ap = np.isnan(previous_gap) | (gap <= previous_gap)
    c_ep, c_feat, c_prox, c_ap = np.broadcast_arrays(c_ep, c_feat, c_prox, c_ap)
    return RuleConditions(c_ep.copy(), c_feat.copy(), c_prox.copy(), c_ap.copy())


def collision_probability(
    u_ep_heading: Any, u_feat: Any, gap: Any, relative_speed: Any, previous_gap: Any, thresholds: Thresholds,
    return_conditions: bool = False,
) -> np.ndarray | tuple[np.ndarray, RuleConditions]:
    """``P(col)`` as a bool array (see :func:`rule_conditions` for the inputs); with ``return_conditions`` also
    the individual conditions, ``(p_col, RuleConditions)``."""
    conditions = rule_conditions(u_ep_heading, u_feat, gap, relative_speed, previous_gap, thresholds)
    return (conditions.p_col, conditions) if return_conditions else conditions.p_col
