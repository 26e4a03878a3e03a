"""The probability-of-collision rule of the safety layer (paper eq. (10), IV-C) and its thresholds.

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

The proximity inputs (``d``, ``dv``, ``d(t-1)``) come from an observation (see :func:`nearest_human`); which one is
``Thresholds.sensing``: ``perceived`` (default) -- the robot's own observation, observation noise included, the
only thing a robot without a separate safety sensor has -- or ``true`` -- the simulator's noise-free observation
of the same step, as a separate safety sensor (e.g. a lidar proximity field) would give. With ``true`` the cautious
controller reads it too, while the policy and the uncertainty estimates still see the noisy observation
(:class:`~socnav.safety.SafePolicy`). ``perceived`` is the default: it is what the paper's formulation reads and
what a deployment without such a sensor can run (a threshold file without the field reads as ``perceived``).

**Holding the fallback** (``Thresholds.hold_steps``, an extension; 0 = the paper's per-step rule): once the rule
fires, the cautious controller keeps control for the next ``hold_steps`` steps whatever the rule says
(:func:`held_fallback`). Why: evaluated step by step, the rule can *chatter*. A fallback step stops the gap from
shrinking, so ``c_ap`` turns False, the policy takes control back and closes the gap again; in Table 3 a collision
ended that way with the rule firing on every other step of its last 2 s. A minimum dwell time is the usual cure of
such switching between two controllers. The calibration searches it by replays (``socnav.safety.calibration``).

**Which conditions the rule combines** (``Thresholds.conditions``, an ablation of eq. (10); ``paper`` is the
default and eq. (10) itself):

- ``paper``: ``(c_ep or c_feat) and c_prox and c_ap``;
- ``proximity-only``: ``c_prox and c_ap`` -- the uncertainty condition removed: the layer hands over whenever the
  robot closes in on a person, however certain the policy is (``lambda_ep`` and ``lambda_feat`` are ignored);
- ``uncertainty-only``: ``(c_ep or c_feat) and c_ap`` -- the proximity condition removed (``lambda_prox`` and
  ``beta1`` are ignored). ``c_ap`` stays: it is not a distance test but the paper's "once the robot is moving away
  from the human, the risky scenario was averted", so keeping it removes exactly one condition and the rule still
  leaves a receding robot alone. (Without any human, ``c_ap`` holds -- there is no previous gap -- so this rule
  can fire on uncertainty alone there; in the Table 3 worlds a human is always present.)

The rule variants answer whether the uncertainty condition changes any hand-over at all: Table 3's ablation
calibrates each under the same false-activation budget and compares them episode by episode.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numba
import numpy as np
import yaml
from pydantic import ConfigDict, Field, StrictInt, ValidationError, field_validator, model_serializer

from socnav.config import StrictModel, format_validation_error, read_mapping_file
from socnav.io import write_text_atomic

__all__ = [
    "PROXIMITY_VARIANTS",
    "RULE_CONDITIONS",
    "SENSING_CHOICES",
    "THRESHOLD_PRESETS",
    "NearestHuman",
    "RuleConditions",
    "Thresholds",
    "ThresholdsError",
    "check_conditions",
    "check_proximity",
    "collision_probability",
    "held_fallback",
    "load_thresholds",
    "nearest_human",
    "proximity_score",
    "rule_conditions",
    "save_thresholds",
    "shipped_layers",
]

SPEED, HEADING = 0, 1  # action dimensions of `Uncertainty.u_ep`

Proximity = Literal["abs-relative-speed", "closing-speed"]
PROXIMITY_VARIANTS: tuple[str, ...] = ("abs-relative-speed", "closing-speed")
Sensing = Literal["perceived", "true"]
#: What the proximity terms and the cautious controller read: the (noisy) observation or the true state.
SENSING_CHOICES: tuple[str, ...] = ("perceived", "true")
Conditions = Literal["paper", "proximity-only", "uncertainty-only"]
#: Which conditions the rule combines: eq. (10) as printed, or one of its two ablations (module docstring).
RULE_CONDITIONS: tuple[str, ...] = ("paper", "proximity-only", "uncertainty-only")

#: Paper thresholds (lambda_ep, lambda_feat, lambda_prox, beta1) per estimator kind (paper V-B.3).
THRESHOLD_PRESETS: dict[str, tuple[float, float, float, float]] = {
    "mc": (0.03, 0.3, 0.9, 0.5),
    "ensemble": (0.08, 0.0033, 0.9, 0.5),
}


class ThresholdsError(ValueError):
    """Thresholds are invalid; the message names the field and what is allowed."""


class Thresholds(StrictModel):
    """Constants of the collision-probability rule (immutable, validated, unknown fields rejected).

    ``lambda_ep``, ``lambda_feat``: uncertainty thresholds (>= 0; ``inf`` switches that condition off, NaN is
    refused); ``lambda_prox``: proximity threshold in metres (finite, 0 ... 1000); ``beta1``: weight of the speed
    term (finite, 0 ... 100 s);
    ``proximity``: ``abs-relative-speed`` (``d + beta1 |dv|``, as printed in the paper) or ``closing-speed``
    (``d - beta1 v_close``); ``sensing``: ``perceived`` (the observation, noise included) or ``true`` (the
    simulator's noise-free state) for the proximity terms and the cautious controller; ``hold_steps``: steps the
    fallback keeps control after the rule last fired (0 ... 1000; 0: the paper's per-step rule); ``conditions``:
    which conditions the rule combines, ``paper`` (eq. (10)), ``proximity-only`` or ``uncertainty-only`` (the
    parameters of a removed condition are kept but ignored); see the module docstring.

    ``model_dump()`` leaves ``conditions`` out while it is ``paper``, so files and records of the paper's rule
    carry no ``conditions`` field (and files without it read as ``paper``).
    """

    model_config = ConfigDict(frozen=True)

    # inf is meaningful here (the condition never holds: `Thresholds.never`, calibration's "off"); NaN is not
    lambda_ep: float = Field(..., ge=0, allow_inf_nan=True,
                             description="windowed epistemic heading uncertainty threshold (inf: off)")
    lambda_feat: float = Field(..., ge=0, allow_inf_nan=True,
                               description="windowed predictive feature uncertainty threshold (inf: off)")
    lambda_prox: float = Field(..., ge=0, le=1000, description="metres: d + beta1 * speed below this is 'close'")
    beta1: float = Field(..., ge=0, le=100, description="seconds: weight of the speed term")
    proximity: Proximity = Field("abs-relative-speed", description="speed term of c_prox")
    sensing: Sensing = Field("perceived", description="what c_prox, c_ap and the cautious controller read")
    hold_steps: StrictInt = Field(0, ge=0, le=1000, description="steps the fallback keeps control after the rule last "
                                                          "fired (0: the paper's per-step rule)")
    conditions: Conditions = Field("paper", description="which conditions the rule combines: paper (eq. (10)), "
                                                        "proximity-only (c_prox and c_ap) or uncertainty-only "
                                                        "((c_ep or c_feat) and c_ap)")

    @field_validator("lambda_ep", "lambda_feat")
    @classmethod
    def _not_nan(cls, value: float) -> float:
        if math.isnan(value):
            raise ValueError("must be a number (inf allowed), not NaN")
        return value

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        if data.get("conditions") == "paper":  # the default, eq. (10): left out of files and records
            del data["conditions"]
        return data

    @property
    def uses_uncertainty(self) -> bool:
        """Whether the rule reads the uncertainty (``c_ep or c_feat``): not for ``proximity-only``."""
        return self.conditions != "proximity-only"

    @property
    def uses_proximity(self) -> bool:
        """Whether the rule reads ``c_prox``: not for ``uncertainty-only``."""
        return self.conditions != "uncertainty-only"

    @classmethod
    def create(cls, data: Mapping[str, Any] | None = None, **fields: Any) -> Thresholds:
        """Validate ``data`` / keyword fields; raise :class:`ThresholdsError` naming the bad field."""
        merged = {**dict(data or {}), **fields}
        try:
            return cls.model_validate(merged)
        except ValidationError as exc:
            raise ThresholdsError(format_validation_error(exc, "invalid safety thresholds:", cls)) from None

    @classmethod
    def preset(cls, name: str, proximity: Proximity = "abs-relative-speed",
               sensing: Sensing = "perceived") -> Thresholds:
        """The paper's thresholds for ``mc`` (MC-dropout) or ``ensemble``."""
        if name not in THRESHOLD_PRESETS:
            raise ThresholdsError(f"unknown thresholds preset {name!r}; allowed: {', '.join(THRESHOLD_PRESETS)}")
        lambda_ep, lambda_feat, lambda_prox, beta1 = THRESHOLD_PRESETS[name]
        return cls.create(lambda_ep=lambda_ep, lambda_feat=lambda_feat, lambda_prox=lambda_prox, beta1=beta1,
                          proximity=proximity, sensing=sensing)

    @classmethod
    def never(cls) -> Thresholds:
        """Thresholds whose uncertainty conditions never hold: the rule never fires (a plain policy)."""
        return cls.create(lambda_ep=math.inf, lambda_feat=math.inf, lambda_prox=0.0, beta1=0.0)


# ------------------------------------------------------------------------------------------------ files

def shipped_layers() -> dict[str, Path]:
    """The safety layers shipped beside the pretrained policies (socnav/data/*.yaml, socnav/data/README.md), by the
    name ``--safety`` and ``--thresholds`` take them by: the file's stem (``pretrained-maps_time-to-collision``)."""
    from importlib.resources import files

    data = Path(str(files("socnav") / "data"))
    return {path.stem: path for path in sorted(data.glob("*.yaml"))}


def load_thresholds(path_or_name: str | Path | Mapping[str, Any] | Thresholds) -> Thresholds:
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
        if path.is_dir():
            raise ThresholdsError(f"{path} is a directory, not a thresholds file (a YAML or JSON file, or a preset "
                                  f"name: {', '.join(THRESHOLD_PRESETS)})")
        raise ThresholdsError(
            f"thresholds file not found: {path} (or use a preset name: {', '.join(THRESHOLD_PRESETS)}; or a layer "
            f"shipped with a pretrained policy: {', '.join(shipped_layers())})"
        )
    data = read_mapping_file(path, "thresholds", ThresholdsError, allow_json=True)
    if isinstance(data.get("thresholds"), dict):
        data = data["thresholds"]
    try:
        return Thresholds.create(data)
    except ThresholdsError as exc:
        raise ThresholdsError(f"{exc} [file: {path}]") from None


def save_thresholds(thresholds: Thresholds, path: str | Path) -> Path:
    """Write thresholds atomically: JSON for a ``.json`` suffix, YAML otherwise. ``inf`` round-trips."""
    path = Path(path)
    data = thresholds.model_dump()
    # JSON writes inf as Infinity, which json.loads reads back
    text = json.dumps(data, indent=2) + "\n" if path.suffix == ".json" else yaml.safe_dump(data, sort_keys=False)
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
        check_proximity(proximity)
        return self.relative_speed if proximity == "abs-relative-speed" else self.closing_speed


def nearest_human(observation: Mapping[str, np.ndarray]) -> NearestHuman:
    """Read the nearest human of each environment from a batched observation (the environment's layout,
    `socnav.envs.spaces`).

    Rows are real humans first, sorted farthest to closest, so the nearest human is the LAST real row
    (``humans_mask`` is a prefix). Environments without humans get ``gap = inf`` and zero speeds.
    """
    humans = np.asarray(observation["humans"])
    mask = np.asarray(observation["humans_mask"])
    if humans.ndim == 2:
        humans, mask = humans[None], mask[None]
    gap, relative_speed, closing_speed, present = _nearest_kernel(humans, mask)
    return NearestHuman(gap=gap, relative_speed=relative_speed, closing_speed=closing_speed, present=present)


@numba.njit(cache=True)
def _nearest_kernel(humans: np.ndarray,
                    mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """`nearest_human`'s arrays in one compiled pass (float64 arithmetic): per environment, the last real row's
    gap (column 6), ``|dv|`` and ``-(p_rel . v_rel) / max(|p_rel|, 1e-9)``; ``inf``, 0, 0 without a human."""
    batch = humans.shape[0]
    gap, relative_speed, closing_speed = np.empty(batch), np.empty(batch), np.empty(batch)
    present = np.empty(batch, dtype=np.bool_)
    for env in range(batch):
        count = 0
        for row in range(mask.shape[1]):
            if mask[env, row] > 0.5:
                count += 1
        present[env] = count > 0
        if count == 0:
            gap[env], relative_speed[env], closing_speed[env] = np.inf, 0.0, 0.0
            continue
        nearest = humans[env, count - 1]
        px, py = np.float64(nearest[0]), np.float64(nearest[1])
        vx, vy = np.float64(nearest[2]), np.float64(nearest[3])
        distance = np.sqrt(px * px + py * py)
        relative_speed[env] = np.sqrt(vx * vx + vy * vy)
        closing_speed[env] = -(px * vx + py * vy) / max(distance, 1e-9)
        gap[env] = np.float64(nearest[6])
    return gap, relative_speed, closing_speed, present


def check_proximity(proximity: str) -> None:
    """Raise :class:`ThresholdsError` naming the allowed values unless ``proximity`` is one of
    :data:`PROXIMITY_VARIANTS`."""
    if proximity not in PROXIMITY_VARIANTS:
        raise ThresholdsError(f"unknown proximity variant {proximity!r}; allowed: {', '.join(PROXIMITY_VARIANTS)}")


def check_conditions(conditions: str) -> None:
    """Raise ``ValueError`` naming the allowed values unless ``conditions`` is one of :data:`RULE_CONDITIONS`."""
    if conditions not in RULE_CONDITIONS:
        raise ValueError(f"unknown rule conditions {conditions!r}; allowed: {', '.join(RULE_CONDITIONS)}")


def proximity_score(gap: Any, speed: Any, beta1: float, proximity: Proximity = "abs-relative-speed") -> np.ndarray:
    """The left side of ``c_prox``: ``d + beta1 * |speed|`` (abs-relative-speed, ``speed = |dv|``) or
    ``d - beta1 * speed`` (closing-speed, ``speed = v_close``: the gap extrapolated ``beta1`` seconds ahead)."""
    check_proximity(proximity)
    speed = np.asarray(speed, dtype=np.float64)
    term = np.abs(speed) if proximity == "abs-relative-speed" else -speed
    return np.asarray(gap, dtype=np.float64) + beta1 * term


@dataclass(frozen=True)
class RuleConditions:
    """The rule's conditions for a batch (bool (B,) arrays) and the collision probability ``p_col`` of the rule
    ``conditions`` names (``Thresholds.conditions``; every condition is evaluated whichever the rule combines)."""

    c_ep: np.ndarray
    c_feat: np.ndarray
    c_prox: np.ndarray
    c_ap: np.ndarray
    conditions: Conditions = "paper"

    @property
    def c_uncertain(self) -> np.ndarray:
        """The uncertainty condition ``c_ep or c_feat``."""
        return self.c_ep | self.c_feat

    @property
    def p_col(self) -> np.ndarray:
        """Where the cautious controller takes over: ``(c_ep or c_feat) and c_prox and c_ap`` (``paper``), ``c_prox
        and c_ap`` (``proximity-only``) or ``(c_ep or c_feat) and c_ap`` (``uncertainty-only``)."""
        if self.conditions == "proximity-only":
            return self.c_prox & self.c_ap
        if self.conditions == "uncertainty-only":
            return self.c_uncertain & self.c_ap
        # paper eq. (10): P(col) = 1 iff (c_ep or c_feat) and c_prox and c_ap
        return self.c_uncertain & self.c_prox & self.c_ap

    @property
    def vetoed(self) -> np.ndarray:
        """Where the proximity terms fire (``c_prox and c_ap``) but the uncertainty condition does not: the hand-overs
        the uncertainty condition of eq. (10) holds back (False everywhere unless the rule combines both)."""
        if self.conditions != "paper":
            return np.zeros_like(self.c_prox)
        return self.c_prox & self.c_ap & ~self.c_uncertain

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"c_ep": self.c_ep, "c_feat": self.c_feat, "c_prox": self.c_prox, "c_ap": self.c_ap,
                "p_col": self.p_col}


def rule_conditions(
    u_ep_heading: Any, u_feat: Any, gap: Any, relative_speed: Any, previous_gap: Any, thresholds: Thresholds
) -> RuleConditions:
    """Evaluate every condition of the rule (``thresholds.conditions`` says which of them ``p_col`` combines).
    Inputs are (B,) arrays (or scalars):

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
    rule = thresholds.conditions
    if c_ep.ndim and c_ep.shape == c_feat.shape == c_prox.shape == c_ap.shape:
        return RuleConditions(c_ep, c_feat, c_prox, c_ap, rule)  # fresh arrays already (the common, batched case)
    c_ep, c_feat, c_prox, c_ap = np.broadcast_arrays(c_ep, c_feat, c_prox, c_ap)
    return RuleConditions(c_ep.copy(), c_feat.copy(), c_prox.copy(), c_ap.copy(), rule)


def collision_probability(
    u_ep_heading: Any, u_feat: Any, gap: Any, relative_speed: Any, previous_gap: Any, thresholds: Thresholds,
    return_conditions: bool = False,
) -> np.ndarray | tuple[np.ndarray, RuleConditions]:
    """``P(col)`` as a bool array of the rule ``thresholds.conditions`` names (see :func:`rule_conditions` for the
    inputs); with ``return_conditions`` also
    the individual conditions, ``(p_col, RuleConditions)``."""
    conditions = rule_conditions(u_ep_heading, u_feat, gap, relative_speed, previous_gap, thresholds)
    return (conditions.p_col, conditions) if return_conditions else conditions.p_col


def held_fallback(p_col: np.ndarray, steps_left: np.ndarray, hold_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Where the fallback drives this step, with a hold: ``p_col`` now, or the rule fired within the last
    ``hold_steps`` steps. ``steps_left`` (int (B,)): held steps still owed from earlier firings (0 at an episode's
    start). Returns ``(fallback, steps_left)``, the latter to pass in at the next step: ``hold_steps`` where the
    rule fired now, else one fewer (not below 0)."""
    p_col = np.asarray(p_col, dtype=bool)
    fallback = p_col | (steps_left > 0)
    return fallback, np.where(p_col, hold_steps, np.maximum(steps_left - 1, 0))
