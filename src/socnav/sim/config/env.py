"""The simulated world's configuration, validated as a whole (`EnvConfig`, docs/world.md; every field on
docs/configuration.md), `load_config` and the world described in words.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    Field,
    StrictInt,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from socnav.sim.config.humans import HumansConfig
from socnav.sim.config.sections import (
    LayoutConfig,
    OrcaConfig,
    PerturbationConfig,
    PlannerConfig,
    Range,
    RewardConfig,
    ScanConfig,
    Section,
    check_range,
)
from socnav.validation import ConfigError, deep_merge, format_validation_error, read_mapping_file, short_repr


class EnvConfig(Section):
    """Everything that defines a socnav world and its Gymnasium environment."""

    scenario: str = Field(default="circle_crossing", description="registered scenario name")
    n_humans: StrictInt | tuple[StrictInt, StrictInt] | None = Field(
        default=None,
        description="humans per episode: an int, a [min, max] range drawn per episode, or null for the scenario default"
    )
    max_humans: StrictInt = Field(default=10, ge=1, le=64, description="rows of the padded 'humans' observation")
    time_step: float = Field(default=0.25, ge=0.01, le=1.0, description="seconds per step (0.01 s ... 1 s)")

    robot_radius: float = Field(default=0.3, gt=0, le=2, description="metres")
    human_radius: float = Field(default=0.3, gt=0, le=2, description="metres")
    preferred_speed: Range = Field(default=(0.5, 1.0), description="v_pref ~ U[min, max] m/s for every agent")
    personal_space: Range = Field(default=(0.3, 0.7), description="r_prox ~ U[min, max] m, from the body boundary")
    cooperation: Range = Field(
        default=(0.25, 0.5), description="human share of avoidance w.r.t. the robot ~ U[min, max]"
    )
    robot_visible: bool = Field(
        default=True, description="False: humans ignore the robot (out-of-distribution variant)"
    )
    inattentive_share: float = Field(
        default=0.3, ge=0, le=1,
        description="probability that a human, drawn per human and episode, plans as if the robot were not there",
    )
    human_fov_deg: float = Field(
        default=200.0, gt=0, le=360,
        description="attentive humans react to the robot once it enters this view cone (degrees; 360 = always)",
    )
    max_heading_change: float = Field(default=math.pi / 6, gt=0, le=math.pi, description="rad per step")
    initial_heading: Literal["random", "goal"] = Field(
        default="random", description="robot heading at the start: uniform in [-pi, pi) or pointing at its goal"
    )

    circle_radius: float = Field(default=7.0, gt=0, le=100, description="metres, circle scenarios and position swap")
    circle_jitter: float = Field(
        default=0.5, ge=0, le=10, description="circle crossing: start/goal jitter (uniform +- m)"
    )
    swap_jitter: float = Field(default=0.0, ge=0, le=10, description="position swap: std (m) of start/goal jitter")
    square_size: float = Field(default=14.0, gt=0, le=200, description="random scenario: side of the square (m)")

    goal_tolerance: float = Field(
        default=0.3, gt=0, le=10, description="success when the robot centre is this close to its goal"
    )
    timeout_factor: float = Field(
        default=2.0, gt=0, le=100, description="time limit = factor * |start - goal| / v_pref + margin"
    )
    timeout_margin: float = Field(default=10.0, ge=0, le=3600, description="seconds")
    robot_orca_share: float = Field(
        default=1.0, ge=0, le=1,
        description="share of avoidance the ORCA robot takes (1: assumes nothing of the humans)"
    )
    robot_orca_safety_margin: float = Field(
        default=0.1, ge=0, le=2, description="metres the ORCA robot adds to human radii"
    )

    orca: OrcaConfig = Field(default_factory=OrcaConfig)
    humans: HumansConfig = Field(default_factory=HumansConfig)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    perturbation: PerturbationConfig = Field(default_factory=PerturbationConfig)
    obstacles: list[list[tuple[float, float]]] = Field(
        default_factory=list, description="static obstacles: polygons of [x, y] vertices in metres, RVO2's "
        "convention (counter-clockwise: solid; clockwise: encloses free space; two vertices: a wall segment); at "
        "most 512 vertices each, 4096 in all (with the map's and the scenario's)",
    )
    map: str | None = Field(
        default=None,
        description="a map file: a YAML of polygons (obstacles:, boundaries:) or a ROS map_server occupancy "
        "grid (YAML with image, resolution, origin, negate, occupied_thresh, free_thresh); stored absolute",
    )
    occlusion: bool | None = Field(
        default=None,
        description="walls hide people: the robot does not observe a human it cannot see (null: on in the map "
        "scenarios, off elsewhere); humans never notice the robot through a wall",
    )
    scan: ScanConfig | None = Field(
        default=None, description="the robot's range scan of the walls, an observation key 'scan' (null: no scan)",
    )
    layout: LayoutConfig = Field(default_factory=LayoutConfig)
    planner: PlannerConfig = Field(
        default_factory=PlannerConfig, description="the global planner of worlds with walls: paths around them "
        "for the robot and the humans (on by default where there are walls; no effect without)",
    )

    @field_validator("obstacles")
    @classmethod
    def _valid_polygons(cls, value: list[list[tuple[float, float]]]) -> list[list[tuple[float, float]]]:
        from socnav.sim.maps import validate_polygons

        validate_polygons(value, name="obstacles")  # a MapError is a ValueError naming the polygon
        return value

    @field_validator("map")
    @classmethod
    def _readable_map(cls, value: str | None) -> str | None:
        import os

        from socnav.sim.maps import load_map

        if value is None:
            return value
        path = Path(os.path.expanduser(value))
        if not path.is_file():
            raise ValueError(f"map file not found: {short_repr(value)}")
        load_map(path)  # a MapError names the file and what is wrong with it
        return str(path.resolve())

    @field_validator("preferred_speed")
    @classmethod
    def _speed_range(cls, value: Range) -> Range:
        check_range(value, 0.0, 10.0)  # m/s: a running human is ~3-5 m/s
        if value[0] <= 0:
            raise ValueError("preferred speeds must be > 0")
        return value

    @field_validator("personal_space")
    @classmethod
    def _space_range(cls, value: Range) -> Range:
        return check_range(value, 0.0, 5.0)  # metres beyond the body: proxemics' public zone starts at ~3.7 m

    @field_validator("cooperation")
    @classmethod
    def _coop_range(cls, value: Range) -> Range:
        return check_range(value, 0.0, 1.0)

    @field_validator("scenario")
    @classmethod
    def _known_scenario(cls, value: str) -> str:
        from socnav.sim.scenarios import scenario_names

        if value not in scenario_names():
            raise ValueError(f"unknown scenario {short_repr(value)}; allowed: {', '.join(scenario_names())}")
        return value

    @field_validator("n_humans")
    @classmethod
    def _humans_count(cls, value: int | tuple[int, int] | None) -> int | tuple[int, int] | None:
        if value is None:
            return value
        lo, hi = (value, value) if isinstance(value, int) else value
        if lo < 0 or lo > hi:
            raise ValueError("must be >= 0, and a range [min, max] needs min <= max")
        return value

    @model_validator(mode="after")
    def _replay_needs_its_scenario(self) -> EnvConfig:
        # Recorded people need the scene the replay scenario builds around them, and that scene has no goals for
        # reactive humans: the two go together, in both directions (a behaviour shift to replay included).
        replayed = {"humans.model": self.humans.model == "replay",
                    "perturbation.human_model": self.perturbation.human_model == "replay"}
        for field, uses in replayed.items():
            if uses and self.scenario != "replay":
                raise ValueError(f"{field}: replay humans need scenario: replay (got scenario {self.scenario!r})")
        if self.scenario == "replay" and self.humans.model != "replay":
            raise ValueError(f"scenario: replay needs humans.model: replay (got {self.humans.model!r}); the "
                             "recorded pedestrians are the humans of that scenario")
        if self.scenario == "replay" and self.perturbation.human_model not in (None, "replay"):
            raise ValueError("perturbation.human_model: the replay scenario's humans are recorded, they cannot walk "
                             f"by {self.perturbation.human_model!r}")
        return self

    @model_validator(mode="after")
    def _replay_positions_are_bounded(self) -> EnvConfig:
        # The positions the recorded tracks give at this time_step are counted (not interpolated) here, so that a
        # short file spanning frames 0 ... 10^9 is refused as the config is read rather than when a world is built.
        if self.humans.model == "replay" and self.humans.replay.files:
            from socnav.sim.humans import trajectories  # lazily: socnav.sim imports this module

            try:
                trajectories.check_positions(self.humans.replay, self.time_step)
            except OSError as exc:
                raise ValueError(f"humans.replay.files: a trajectory file cannot be read: {exc}") from None
            except trajectories.TrajectoryFileError as exc:
                raise ValueError(f"humans.replay.files: {exc}") from None
        return self

    @model_validator(mode="after")
    def _robot_goals_are_reachable(self) -> EnvConfig:
        # Where the robot's routes are fixed by the config (the circle scenarios' four diameters), a goal the planner
        # cannot reach among the config's obstacles or map is known now: refused here rather than left to a robot
        # that would head straight at it.
        from socnav.sim.scenarios import FixedRouteScenario, get_scenario

        scenario = get_scenario(self.scenario)
        if not self.planner.enabled or not isinstance(scenario, FixedRouteScenario):
            return self
        from socnav.sim.planning import planner_for, unreachable_route
        from socnav.sim.walls import world_polygons

        polygons = world_polygons(self, scenario)
        if not polygons:
            return self
        clearance = self.robot_radius + self.planner.margin
        route = unreachable_route(planner_for(polygons, clearance), scenario.robot_routes(self), self.robot_radius)
        if route is not None:
            start, goal = (f"({x + 0.0:g}, {y + 0.0:g})" for x, y in route)  # + 0.0: no "-0" shown
            raise ValueError(
                f"planner: the robot's goal {goal} cannot be reached from its start {start} (scenario "
                f"{self.scenario!r}): among the walls no way at least {2 * clearance:g} m wide (2 x (robot_radius "
                f"{self.robot_radius:g} + planner.margin {self.planner.margin:g})) leads there; move the obstacles "
                "or the map, lower planner.margin, or set planner.enabled: false")
        return self

    @model_validator(mode="after")
    def _humans_fit_observation(self) -> EnvConfig:
        most = self.humans_range()[1]
        if most > self.max_humans:
            raise ValueError(
                f"max_humans={self.max_humans} is smaller than the largest number of humans ({most}); "
                f"raise max_humans to at least {most}"
            )
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        # The default humans (ORCA) are left out, so that a world of ORCA humans dumps -- model metadata, record-file
        # names, unit hashes -- without a humans section.
        if data.get("humans") == HumansConfig().model_dump(mode=getattr(handler, "mode", "python")):
            del data["humans"]
        # Likewise the walls' settings, so that a world without walls dumps without them.
        for key, default in (("obstacles", []), ("map", None), ("occlusion", None), ("scan", None)):
            if key in data and data[key] == default:
                del data[key]
        if data.get("layout") == LayoutConfig().model_dump(mode=getattr(handler, "mode", "python")):
            del data["layout"]
        if data.get("planner") == PlannerConfig().model_dump(mode=getattr(handler, "mode", "python")):
            del data["planner"]
        return data

    def humans_range(self) -> tuple[int, int]:
        """Inclusive [min, max] number of humans per episode, after perturbations and scenario defaults."""
        if self.perturbation.total_agents is not None:
            n = self.perturbation.total_agents - 1
            return n, n
        from socnav.sim.scenarios import get_scenario

        value = self.n_humans if self.n_humans is not None else get_scenario(self.scenario).default_humans
        return (value, value) if isinstance(value, int) else (int(value[0]), int(value[1]))


ConfigLike = EnvConfig | Mapping[str, Any] | str | Path | None


def load_config(config: ConfigLike = None, **overrides: Any) -> EnvConfig:
    """Build a validated `EnvConfig` from a config object, a (partial) dict, a YAML path or None (defaults).

    Keyword overrides are applied on top (nested dicts merge). Raises `ConfigError` naming the bad field.
    """
    source = "defaults"
    if isinstance(config, EnvConfig):
        if not overrides:  # validated already (assignments too): a copy, not a second validation
            return config.model_copy(deep=True)
        data: dict[str, Any] = config.model_dump()
        source = "EnvConfig"
    elif config is None:
        data = {}
    elif isinstance(config, (str, Path)):
        data = read_mapping_file(config, "config")
        data = data.get("env", data) if "env" in data and isinstance(data["env"], dict) else data
        source = str(Path(config))
    elif isinstance(config, Mapping):
        data = dict(config)
        source = "dict"
    else:
        raise ConfigError(f"config must be an EnvConfig, a dict, a YAML path or None, got {type(config).__name__}")
    data = deep_merge(data, overrides)
    try:
        return EnvConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, f"invalid socnav config ({source}):", EnvConfig)) from None


def perturbation_text(config: EnvConfig) -> str:
    """The perturbations switched on, as 'heading_noise=0.4, human_speed_factor=1.5' ('' for none)."""
    defaults = PerturbationConfig()
    return ", ".join(f"{key}={value}" for key, value in config.perturbation.model_dump().items()
                     if value != getattr(defaults, key))


def describe_world(config: EnvConfig, with_perturbation: bool = True) -> str:
    """A world in words, as tables and animation titles name it: 'position_swap, 1 human, humans ignore the robot,
    perturbed: heading_noise=0.4'."""
    low, high = config.humans_range()
    parts = [config.scenario, f"{low} human{'s' if low != 1 else ''}" if low == high else f"{low}-{high} humans"]
    if config.humans.mix is not None:
        shares = ", ".join(f"{name} {100 * share:g} %" for name, share in config.humans.mix.items())
        parts.append(f"mixed humans ({shares})")
    elif config.humans.model != "orca":
        parts.append(f"{config.humans.model} humans")
    if not config.robot_visible:
        parts.append("humans ignore the robot")
    perturbed = perturbation_text(config)
    if with_perturbation and perturbed:
        parts.append(f"perturbed: {perturbed}")
    return ", ".join(parts)

