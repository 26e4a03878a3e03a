"""Perturbed worlds (paper section V-B): the registry of perturbation types (:data:`PERTURBATIONS`), one
perturbation type at one strength as an env config, the strengths Table 2 and Table 3 sweep, and the disjoint set
`socnav calibrate` tunes the safety thresholds on.

Every perturbation type is defined once, as a :class:`Perturbation` in :data:`PERTURBATIONS`: the config field of
`socnav.config.PerturbationConfig` it sets and that field's unperturbed value, how a strength maps to a value, its
evaluation grid (the paper's where it has one), its calibration strengths, its labels and the paper's column. The
env (through the config), the experiment specs (names, default grids), the calibration (its configurations and
whether an episode is perturbed) and the report sections (order, labels, columns) all read the registry. Adding a
perturbation type is one entry here plus its config field and its effect in the simulator
(`socnav.sim.world` / `socnav.sim.humans`).

Strengths are numbers for every type, so the specs' grids (``perturbation -> strengths, sigma(0) first``) and the
records' ``strength`` column stay numeric. A categorical type (``levels``, e.g. the behaviour shift to another
human model) reads strength 0 as unperturbed and strength k = 1, 2, ... as its k-th level.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Literal

import numpy as np

from socnav.config import ConfigError, EnvConfig, load_config

__all__ = [
    "CALIBRATION_SEED", "CALIBRATION_SET", "DEFAULT_GRIDS", "PAPER_GRIDS", "PERTURBATIONS", "PERTURBATION_FIELDS",
    "Perturbation", "get_perturbation", "is_perturbed", "perturbation_override", "perturbed_config",
    "strength_zero",
]

Scale = Literal["continuous", "count", "categorical"]


@dataclass(frozen=True)
class Perturbation:
    """One perturbation type: everything the env, the studies, the calibration and the reports need to know.

    ``name``: the key of study / safety grids, the record directories (``study/<estimator>/<name>``) and the
    records' ``perturbation`` column. ``field``: the `socnav.config.PerturbationConfig` field it sets;
    ``unperturbed``: that field's value in an unperturbed world (its default). ``scale``: how a strength becomes the
    field's value -- ``continuous``: the strength itself; ``count``: an int, strengths up to ``grid[0]`` leave the
    field unset (the world's own count); ``categorical``: strength 0 is ``unperturbed``, k >= 1 ``levels[k - 1]``.
    ``grid``: the evaluation strengths (the paper's where it has them), sigma(0) (unperturbed) first.
    ``calibration``: the strengths `socnav calibrate` tunes the safety thresholds on, off the evaluation grid where
    it leaves room; empty: held out, the calibration never sees this type. ``default``: in the default grids of
    `socnav.experiments.spec.Study` / ``Safety``. ``label`` / ``strength_label``: report headings and the strength
    axis. ``paper_column``: the paper's Table II/III column this type stands for (``obs``, ``action``,
    ``velocity``, ``humans``; None: beyond the paper, its labels say "(ours)"). ``pooled``: the report column that
    pools it with the other types of the same ``pooled`` (the paper's action noise is our heading and speed noise),
    each of them then being our own column alone. ``table3_label``: its Table 3 column heading.
    """

    name: str
    field: str
    unperturbed: Any
    grid: tuple[float, ...]
    calibration: tuple[float, ...]
    label: str
    strength_label: str
    table3_label: str
    paper_column: str | None = None
    pooled: str | None = None
    scale: Scale = "continuous"
    levels: tuple[str, ...] = ()
    default: bool = True

    def __post_init__(self) -> None:
        if len(self.grid) < 2 or sorted(self.grid) != list(self.grid):
            raise ValueError(f"perturbation {self.name}: grid must be increasing, sigma(0) first")
        if (self.scale == "categorical") != bool(self.levels):
            raise ValueError(f"perturbation {self.name}: levels go with (and only with) a categorical scale")
        self.check_strengths(self.grid)
        self.check_strengths(self.calibration)

    @property
    def strength_zero(self) -> float:
        """The unperturbed strength (the sigma(0) of the sensitivity ratio)."""
        return self.grid[0]

    @property
    def ours(self) -> bool:
        """A perturbation beyond the paper (it has no column for it)."""
        return self.paper_column is None

    def check_strengths(self, strengths: Any) -> None:
        """ValueError unless every strength means something for this type (a categorical one: 0 ... len(levels))."""
        if self.scale != "categorical":
            return
        for strength in strengths:
            if not (float(strength).is_integer() and 0 <= strength <= len(self.levels)):
                levels = ", ".join(f"{k + 1} = {level}" for k, level in enumerate(self.levels))
                raise ValueError(f"{self.name}: strength {strength!r} names no level; allowed: 0 (unperturbed), "
                                 f"{levels}")

    def override(self, strength: float) -> dict[str, Any]:
        """The ``perturbation`` config mapping of this type at `strength` (unperturbed values are exact)."""
        if self.scale == "count":
            return {} if strength <= self.strength_zero else {self.field: int(strength)}
        if self.scale == "categorical":
            self.check_strengths([strength])
            return {self.field: self.unperturbed if strength == 0 else self.levels[int(strength) - 1]}
        return {self.field: float(strength)}

    def active(self, perturbation: Any) -> bool:
        """Whether a `socnav.config.PerturbationConfig` has this type switched on."""
        return getattr(perturbation, self.field) != self.unperturbed


def _register(*perturbations: Perturbation) -> Mapping[str, Perturbation]:
    names = [p.name for p in perturbations]
    fields = [p.field for p in perturbations]
    if len(set(names)) != len(names) or len(set(fields)) != len(fields):
        raise ValueError(f"perturbation names and config fields must be unique: {names}, {fields}")
    return MappingProxyType({p.name: p for p in perturbations})


def _steps(stop: float) -> tuple[float, ...]:
    return tuple(round(float(x), 1) for x in np.arange(0.0, stop + 0.01, 0.2))


#: The perturbation types, in report order. The paper's strengths: noise sigma in {0, 0.2, ..., 2} (speed noise is
#: a factor U(1 - s, 1): the world clips s to [0, 1], so s > 1 plays as s = 1; paper Sec. V-A), human speed factor
#: l_vel in {1, ..., 8}, N in {2, ..., 7} agents in total (2 = the unperturbed position swap). Calibration strengths
#: lie off the evaluation grids where the grid leaves room (the number of humans is an integer, so ``more_humans``
#: is disjoint by its episode seeds only). The behaviour shift (ours) is held out of the calibration and of the
#: default grids.
PERTURBATIONS: Mapping[str, Perturbation] = _register(
    Perturbation("observation_noise", "observation_noise", 0.0, _steps(2.0), (0.5, 1.3),
                 label="Observation noise", strength_label="observation noise σ_obs",
                 table3_label="Observation noise", paper_column="obs"),
    Perturbation("heading_noise", "heading_noise", 0.0, _steps(2.0), (0.5, 1.3),
                 label="Heading noise", strength_label="heading noise σ_head",
                 table3_label="Heading noise alone (ours)", paper_column="action", pooled="action_noise"),
    Perturbation("speed_noise", "speed_noise", 0.0, _steps(2.0), (0.5, 0.9),
                 label="Speed noise", strength_label="speed noise s (factor U(1 − s, 1))",
                 table3_label="Speed noise alone (ours)", paper_column="action", pooled="action_noise"),
    Perturbation("faster_humans", "human_speed_factor", 1.0, tuple(float(x) for x in range(1, 9)), (2.5, 5.5),
                 label="Faster humans", strength_label="human speed factor l_vel",
                 table3_label="Velocity (faster humans)", paper_column="velocity"),
    Perturbation("more_humans", "total_agents", None, tuple(float(x) for x in range(2, 8)), (4.0, 6.0),
                 label="More humans", strength_label="agents N (robot included)",
                 table3_label="New humans (more humans)", paper_column="humans", scale="count"),
    Perturbation("behaviour_shift", "human_model", None, (0.0, 1.0), (),
                 label="Behaviour shift (ours)",
                 strength_label="human model (0: as trained; 1: social force, 2: ORCA humans)",
                 table3_label="Behaviour shift (ours)", scale="categorical", levels=("social_force", "orca"),
                 default=False),
)

#: Perturbation type -> config field of `socnav.config.PerturbationConfig`.
PERTURBATION_FIELDS: dict[str, str] = {name: p.field for name, p in PERTURBATIONS.items()}

#: The paper's perturbation types -> their evaluation strengths, sigma(0) first.
PAPER_GRIDS: dict[str, list[float]] = {name: list(p.grid) for name, p in PERTURBATIONS.items() if not p.ours}

#: The default grids of the studies (`socnav.experiments.spec.Study`, ``Safety``): the types marked ``default``.
DEFAULT_GRIDS: dict[str, list[float]] = {name: list(p.grid) for name, p in PERTURBATIONS.items() if p.default}

#: Strengths for threshold calibration per type; types without any (held out) are not in it.
CALIBRATION_SET: dict[str, list[float]] = {name: list(p.calibration) for name, p in PERTURBATIONS.items()
                                           if p.calibration}

#: Episode seeds: evaluation uses seed + k from 0; calibration starts here, so no episode is shared.
CALIBRATION_SEED = 500_000


def get_perturbation(kind: str) -> Perturbation:
    """The registered perturbation type `kind` (ValueError naming the allowed ones)."""
    try:
        return PERTURBATIONS[kind]
    except KeyError:
        raise ValueError(f"unknown perturbation {kind!r}; allowed: {', '.join(PERTURBATIONS)}") from None


def perturbation_override(kind: str, strength: float) -> dict[str, Any]:
    """The `perturbation` config mapping of one perturbation type at one strength (unperturbed values are exact)."""
    return get_perturbation(kind).override(strength)


def perturbed_config(env: dict[str, Any], kind: str, strength: float) -> EnvConfig:
    """The validated `EnvConfig` of the (partial) env config `env` with one perturbation at one strength.

    :raises socnav.config.ConfigError: the strength puts a field out of its range (the message names it), or a
        behaviour shift names the world's own human model (no shift at all).
    """
    perturbation = {**env.get("perturbation", {}), **perturbation_override(kind, strength)}
    config = load_config({**env, "perturbation": perturbation})
    if config.perturbation.human_model is not None and config.perturbation.human_model == config.humans.model:
        raise ConfigError(f"invalid perturbation {kind} at strength {strength:g}: perturbation.human_model "
                          f"{config.perturbation.human_model!r} is the world's own humans.model, so nothing shifts")
    return config


def strength_zero(kind: str) -> float:
    """The unperturbed strength of a perturbation type (the sigma(0) of the sensitivity ratio)."""
    return get_perturbation(kind).strength_zero


def is_perturbed(config: EnvConfig) -> bool:
    """Whether any registered perturbation type is switched on in `config` (each compared with its unperturbed
    value, so a newly registered type cannot be forgotten)."""
    return any(p.active(config.perturbation) for p in PERTURBATIONS.values())

