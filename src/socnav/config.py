"""Validated configuration of the simulated world and the environment (SPEC sections 1 and 2).

One pydantic model, loadable from a dict or a YAML file; unknown or out-of-range fields raise `ConfigError` naming the field.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal, Mapping, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class ConfigError(ValueError):
    """A configuration value is wrong; the message names the field and what is allowed."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


Range = tuple[float, float]


def _check_range(value: Range, low: float, high: float | None = None) -> Range:
    lo, hi = value
    if lo > hi:
        raise ValueError(f"lower bound {lo} must be <= upper bound {hi}")
    if lo < low or (high is not None and hi > high):
        upper = "inf" if high is None else high
        raise ValueError(f"bounds must lie in [{low}, {upper}]")
    return value


class OrcaConfig(_Strict):
    """ORCA parameters shared by humans and the ORCA robot controller (RVO2 semantics)."""

    time_horizon: float = Field(5.0, gt=0, description="seconds")
    neighbor_dist: float = Field(10.0, gt=0, description="metres")
    max_neighbors: int = Field(10, ge=0)


class RewardConfig(_Strict):
    """Weights of the socially integrated reward (SPEC section 2); every term can be switched off with 0."""

    goal: float = Field(5.0, ge=0, description="+goal when the robot reaches its goal")
    collision: float = Field(5.0, ge=0, description="-collision on contact with a human")
    time: float = Field(0.5, ge=0, description="-time * dt every step (per second of episode)")
    progress: float = Field(1.0, ge=0, description="progress * (d_goal(t-1) - d_goal(t)), per metre")
    personal_space: float = Field(0.5, ge=0, description="-w * (1 - gap / r_prox) per intruded human")
    disturbance: float = Field(0.25, ge=0, description="-w * |v_i - v_i^without robot| / v_pref_i per human")
    social_radius: float = Field(3.0, ge=0, description="metres; humans farther than this do not score")


class PerturbationConfig(_Strict):
    """Perturbations of SPEC section 2; all zero / one means an unperturbed world."""

    observation_noise: float = Field(0.0, ge=0, description="std of N(0, s^2) added to every real observation element")
    heading_noise: float = Field(0.0, ge=0, description="std (rad) of N(0, s^2) added to the heading change")
    speed_noise: float = Field(0.0, ge=0, le=1, description="speed multiplied by U(1 - s, 1); s in [0, 1]")
    human_speed_factor: float = Field(1.0, gt=0, description="every human's v_pref multiplied by this factor")
    total_agents: int | None = Field(
        None, ge=2, description="'more humans': position swap becomes circle crossing with this many agents in total"
    )


class EnvConfig(_Strict):
    """Everything that defines a socnav world and its Gymnasium environment."""

    scenario: str = Field("circle_crossing", description="registered scenario name")
    n_humans: Union[int, tuple[int, int], None] = Field(
        None, description="humans per episode: an int, a [min, max] range drawn per episode, or null for the scenario default"
    )
    max_humans: int = Field(10, ge=1, le=64, description="rows of the padded 'humans' observation")
    time_step: float = Field(0.25, gt=0, le=1.0, description="seconds per step")

    robot_radius: float = Field(0.3, gt=0)
    human_radius: float = Field(0.3, gt=0)
    preferred_speed: Range = Field((0.5, 1.0), description="v_pref ~ U[min, max] m/s for every agent")
    personal_space: Range = Field((0.3, 0.7), description="r_prox ~ U[min, max] m, from the body boundary")
    cooperation: Range = Field((0.25, 0.5), description="human share of avoidance w.r.t. the robot ~ U[min, max]")
    robot_visible: bool = Field(True, description="False: humans ignore the robot (out-of-distribution variant)")
    max_heading_change: float = Field(math.pi / 6, gt=0, le=math.pi, description="rad per step")
    initial_heading: Literal["random", "goal"] = Field(
        "random", description="robot heading at the start: uniform in [-pi, pi) or pointing at its goal"
    )

    circle_radius: float = Field(7.0, gt=0, description="metres, circle scenarios and position swap")
    circle_jitter: float = Field(0.5, ge=0, description="circle crossing: start/goal jitter (uniform +- m)")
    swap_jitter: float = Field(0.0, ge=0, description="position swap: std (m) of start/goal jitter")
    square_size: float = Field(14.0, gt=0, description="random scenario: side of the square (m)")

    goal_tolerance: float = Field(0.3, gt=0, description="success when the robot centre is this close to its goal")
    timeout_factor: float = Field(2.0, gt=0, description="time limit = factor * |start - goal| / v_pref + margin")
    timeout_margin: float = Field(10.0, ge=0, description="seconds")
    robot_orca_share: float = Field(
        1.0, ge=0, le=1, description="share of avoidance the ORCA robot takes (1: assumes nothing of the humans)"
    )
    robot_orca_safety_margin: float = Field(0.1, ge=0, description="metres the ORCA robot adds to human radii")

    orca: OrcaConfig = Field(default_factory=OrcaConfig)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    perturbation: PerturbationConfig = Field(default_factory=PerturbationConfig)

    @field_validator("preferred_speed")
    @classmethod
    def _speed_range(cls, value: Range) -> Range:
        _check_range(value, 0.0)
        if value[0] <= 0:
            raise ValueError("preferred speeds must be > 0")
        return value

    @field_validator("personal_space")
    @classmethod
    def _space_range(cls, value: Range) -> Range:
        return _check_range(value, 0.0)

    @field_validator("cooperation")
    @classmethod
    def _coop_range(cls, value: Range) -> Range:
        return _check_range(value, 0.0, 1.0)

    @field_validator("scenario")
    @classmethod
    def _known_scenario(cls, value: str) -> str:
        from socnav.sim.scenarios import scenario_names

        if value not in scenario_names():
            raise ValueError(f"unknown scenario {value!r}; allowed: {', '.join(scenario_names())}")
        return value

    @field_validator("n_humans")
    @classmethod
    def _humans_count(cls, value: Union[int, tuple[int, int], None]) -> Union[int, tuple[int, int], None]:
        if value is None:
            return value
        lo, hi = (value, value) if isinstance(value, int) else value
        if lo < 0 or lo > hi:
            raise ValueError("must be >= 0, and a range [min, max] needs min <= max")
        return value

    @model_validator(mode="after")
    def _humans_fit_observation(self) -> "EnvConfig":
        most = self.humans_range()[1]
        if most > self.max_humans:
            raise ValueError(
                f"max_humans={self.max_humans} is smaller than the largest number of humans ({most}); "
                f"raise max_humans to at least {most}"
            )
        return self

    def humans_range(self) -> tuple[int, int]:
        """Inclusive [min, max] number of humans per episode, after perturbations and scenario defaults."""
        if self.perturbation.total_agents is not None:
            n = self.perturbation.total_agents - 1
            return n, n
        from socnav.sim.scenarios import get_scenario

        value = self.n_humans if self.n_humans is not None else get_scenario(self.scenario).default_humans
        return (value, value) if isinstance(value, int) else (int(value[0]), int(value[1]))


ConfigLike = Union[EnvConfig, Mapping[str, Any], str, Path, None]


def _format_validation_error(error: ValidationError, source: str) -> str:
    lines = [f"invalid socnav config ({source}):"]
    for item in error.errors():
        field = ".".join(str(p) for p in item["loc"]) or "<root>"
        message = item["msg"]
        if item["type"] == "extra_forbidden":
            parent = _model_at(EnvConfig, item["loc"][:-1])
            allowed = ", ".join(parent.model_fields) if parent is not None else "see the docs"
            message = f"unknown field; allowed fields here: {allowed}"
        lines.append(f"  - {field}: {message} (got {item.get('input')!r})")
    return "\n".join(lines)


def _model_at(model: type[BaseModel], path: tuple) -> type[BaseModel] | None:
    for name in path:
        field = model.model_fields.get(str(name))
        if field is None or not (isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)):
            return None
        model = field.annotation
    return model


def load_config(config: ConfigLike = None, **overrides: Any) -> EnvConfig:
    """Build a validated `EnvConfig` from a config object, a (partial) dict, a YAML path or None (defaults).

    Keyword overrides are applied on top (nested dicts merge). Raises `ConfigError` naming the bad field.
    """
    source = "defaults"
    if isinstance(config, EnvConfig):
        data: dict[str, Any] = config.model_dump()
        source = "EnvConfig"
    elif config is None:
        data = {}
    elif isinstance(config, (str, Path)):
        path = Path(config)
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"config file {path} is not valid YAML: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"config file {path} must hold a mapping of fields, got {type(data).__name__}")
        data = data.get("env", data) if "env" in data and isinstance(data["env"], dict) else data
        source = str(path)
    elif isinstance(config, Mapping):
        data = dict(config)
        source = "dict"
    else:
        raise ConfigError(f"config must be an EnvConfig, a dict, a YAML path or None, got {type(config).__name__}")
    data = _deep_merge(data, overrides)
    try:
        return EnvConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, source)) from None


def _deep_merge(base: dict[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = _deep_merge(dict(merged[key]), value)
        else:
            merged[key] = value
    return merged
