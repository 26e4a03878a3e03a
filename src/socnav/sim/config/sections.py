"""The small sections of the world's configuration (docs/configuration.md): ORCA, the start/goal layout, the range
scan, the global planner, the reward and the perturbations; `Section` is the base of every section.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import (
    ConfigDict,
    Field,
    StrictInt,
    field_validator,
    model_serializer,
)

from socnav.validation import StrictModel, unknown_name_message


class Section(StrictModel):
    model_config = ConfigDict(validate_assignment=True, frozen=False)


Range = tuple[float, float]


def check_range(value: Range, low: float, high: float | None = None) -> Range:
    lo, hi = value
    if lo > hi:
        raise ValueError(f"lower bound {lo} must be <= upper bound {hi}")
    if lo < low or (high is not None and hi > high):
        upper = "inf" if high is None else high
        raise ValueError(f"bounds must lie in [{low}, {upper}]")
    return value


class OrcaConfig(Section):
    """ORCA parameters shared by humans and the ORCA robot controller (RVO2 semantics)."""

    time_horizon: float = Field(default=5.0, gt=0, le=60, description="seconds")
    neighbor_dist: float = Field(default=10.0, gt=0, le=1000, description="metres")
    max_neighbors: StrictInt = Field(default=10, ge=0, le=1000)
    time_horizon_obst: float = Field(
        default=2.0, gt=0, le=60,
        description="seconds: how far ahead velocities are safe with respect to walls (RVO2's "
        "timeHorizonObst); read only where there are obstacles",
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        # Left out at its default, so that a world without walls dumps -- and names and hashes its records -- by the
        # fields it uses only.
        if data.get("time_horizon_obst") == 2.0:
            del data["time_horizon_obst"]
        return data


class LayoutConfig(Section):
    """The geometry of the map scenarios (corridor, doorway, intersection; room reads circle_radius)."""

    corridor_width: float = Field(
        default=3.0, ge=1.0, le=20, description="m: corridor and intersection arms (2.5-3.5: a building corridor)"
    )
    corridor_length: float = Field(
        default=16.0, ge=6.0, le=200, description="m: the corridor; the intersection's span (each arm half of it)"
    )
    door_width: float = Field(
        default=1.1, ge=0.7, le=5, description="m: the doorway between the two rooms (1.0-1.2: a building door)"
    )
    room_size: float = Field(
        default=8.0, ge=4.0, le=100, description="m: side of each of the doorway scenario's two rooms"
    )


class ScanConfig(Section):
    """The robot's range scan (a 2-D lidar's sensor_msgs/LaserScan): beams from -fov/2 to +fov/2 about its heading,
    each the distance to the first wall (or person, with `people`), `range` where none is within reach."""

    beams: StrictInt = Field(default=72, ge=1, le=1024, description="number of beams")
    range: float = Field(
        default=8.0, gt=0, le=100, description="m: maximum range (what a beam reads when it hits nothing)"
    )
    fov: float = Field(
        default=360.0, gt=0, le=360, description="degrees: field of view, centred on the robot's heading"
    )
    people: bool = Field(
        default=False, description="the beams also stop at the humans' bodies (discs of their radius), as a real "
        "lidar's do; false: the walls only (the humans are observed apart)",
    )


class PlannerConfig(Section):
    """The global planner of worlds with walls (docs/maps.md, "Global planner"): the robot's ORCA controller, the
    cautious fallback and the ORCA and social force humans steer towards a subgoal on their shortest path to the
    goal, a path that keeps `margin` metres beyond their radius from every wall. Read only where there are walls."""

    enabled: bool = Field(
        default=True, description="plan paths around the walls (false: every agent heads straight at its goal, "
        "as without a planner)",
    )
    margin: float = Field(
        default=0.1, ge=0, le=5, description="m: clearance a path keeps from every wall beyond the agent's radius; "
        "a gap narrower than 2 x (radius + margin) is closed to the planner",
    )
    lookahead: float = Field(
        default=1.0, gt=0, le=50, description="m: the subgoal lies this far along the path (pure pursuit)",
    )
    replan_distance: float = Field(
        default=0.5, gt=0, le=50, description="m: an agent farther than this from its path plans again (also when "
        "it loses sight of the path's next vertex or its goal changes)",
    )
    observe: bool = Field(
        default=False, description="the robot's observed goal lies along its path: the direction to its subgoal at "
        "the goal's distance, so a learned policy follows the route (false: the goal itself, as a policy trained in "
        "the open plane saw it)",
    )


class RewardConfig(Section):
    """Weights of the socially integrated reward (Flögel et al., IROS 2024, as the paper trains with it, Sec. III-A;
    docs/world.md); every term can be switched off with 0."""

    goal: float = Field(default=5.0, ge=0, le=1000, description="+goal when the robot reaches its goal")
    collision: float = Field(default=5.0, ge=0, le=1000, description="-collision on contact with a human")
    time: float = Field(default=0.5, ge=0, le=1000, description="-time * dt every step (per second of episode)")
    progress: float = Field(default=1.0, ge=0, le=1000, description="progress * (d_goal(t-1) - d_goal(t)), per metre")
    personal_space: float = Field(default=0.5, ge=0, le=1000, description="-w * (1 - gap / r_prox) per intruded human")
    disturbance: float = Field(
        default=0.25, ge=0, le=1000, description="-w * |v_i - v_i^without robot| / v_pref_i per human"
    )
    social_radius: float = Field(default=3.0, ge=0, le=100, description="metres; humans farther than this do not score")


class PerturbationConfig(Section):
    """The paper's perturbations (Sec. V-A: observation noise, action noise, faster humans, more humans) and the
    behaviour shift; all zero / one means an unperturbed world."""

    observation_noise: float = Field(
        default=0.0, ge=0, le=10, description="std of N(0, s^2) added to every real observation element"
    )
    heading_noise: float = Field(
        default=0.0, ge=0, le=2 * math.pi,
        description="std (rad) of N(0, s^2) added to the heading change; beyond 2 pi the heading is random anyway",
    )
    speed_noise: float = Field(
        default=0.0, ge=0,
        description="speed multiplied by U(1 - s, 1); values above 1 are clipped to 1 (paper Sec. V-A: sigma_vel <= 1)",
    )
    human_speed_factor: float = Field(
        default=1.0, gt=0, le=20, description="every human's v_pref multiplied by this factor"
    )
    total_agents: StrictInt | None = Field(
        default=None, ge=2, le=65,
        description="'more humans': position swap becomes circle crossing with this many agents in total",
    )
    human_model: str | None = Field(
        default=None,
        description="'behaviour shift': the humans walk by this model (`socnav.sim.humans` registry) instead "
        "of humans.model, e.g. social_force humans for a policy trained with ORCA humans (null: humans.model)",
    )

    @field_validator("speed_noise")
    @classmethod
    def _clip_speed_noise(cls, value: float) -> float:
        # The paper draws U(1 - sigma_vel, 1) with sigma_vel <= 1 (Sec. V-A): clipped to [0, 1], its grid 0 ... 2 is
        # valid (s > 1 acts as s = 1).
        return min(value, 1.0)

    @field_validator("human_model")
    @classmethod
    def _known_human_model(cls, value: str | None) -> str | None:
        from socnav.sim.humans import human_model_names

        if value is not None and value not in human_model_names():
            raise ValueError(unknown_name_message("human model", value, human_model_names()))
        return value

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        # No behaviour shift is left out, so that an unshifted world dumps -- model metadata, record-file names, unit
        # hashes -- by the fields it uses only.
        if data.get("human_model") is None:
            data.pop("human_model", None)
        return data

