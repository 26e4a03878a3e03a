"""Validated configuration of the simulated world (docs/world.md; every field on docs/configuration.md) and what
every socnav config shares: the strict base model, the bounded YAML reader, the deep merge and the one formatter of
validation errors.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, Union

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictInt,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

# YAML input is bounded by `socnav.io` (the lowest layer: the simulator's map reader uses it too); re-exported here.
from socnav.io import YAML_MAX_BYTES as YAML_MAX_BYTES
from socnav.io import YAML_MAX_DEPTH as YAML_MAX_DEPTH
from socnav.io import YAML_MAX_NODES as YAML_MAX_NODES
from socnav.io import YAMLTooLargeError as YAMLTooLargeError
from socnav.io import file_size_problem as file_size_problem
from socnav.io import read_yaml_file as read_yaml_file
from socnav.io import safe_load_yaml as safe_load_yaml
from socnav.io import yaml_problem as yaml_problem


class ConfigError(ValueError):
    """A configuration value is wrong; the message names the field and what is allowed."""


def read_mapping_file(path: str | Path, what: str, error: type[Exception] = ConfigError,
                      allow_json: bool = False) -> dict[str, Any]:
    """The mapping of fields a YAML file holds (an empty file is an empty mapping), read with the bounded loader;
    with `allow_json` a ``.json`` file is read as JSON (which writes inf as ``Infinity``, unlike YAML), bounded in
    nesting (`socnav.io.parse_json`).

    :raises error: one line naming the file: '<what> file not found: PATH', '<what> file PATH is a directory, not a
        file', '<what> file PATH is not valid YAML: ...' (or '... is refused: ...' for an oversized, deeply nested or
        binary input, or an integer of thousands of digits), '<what> file PATH must hold a mapping of fields, got list'.
    """
    from socnav.io import UntrustedInputError, parse_json, read_bounded

    path = Path(path)
    if path.is_dir():
        raise error(f"{what} file {path} is a directory, not a file")
    if not path.exists():
        raise error(f"{what} file not found: {path}")
    too_large = file_size_problem(path, YAML_MAX_BYTES)  # from the size: a sparse 1 TB file costs nothing
    if too_large:
        raise error(f"{what} file {path} {too_large}")
    try:
        # Read within the limit whatever the filesystem reports (a /proc file claims 0 bytes), never a device or pipe.
        raw = read_bounded(path, YAML_MAX_BYTES)
        if allow_json and path.suffix == ".json":
            data = parse_json(raw, f"{what} file {path}")
        else:
            data = safe_load_yaml(raw.decode())
    except OSError as exc:
        raise error(f"{what} file {path} cannot be read: {exc.strerror or exc}") from None
    except UntrustedInputError as exc:
        message = str(exc)
        raise error(message if message.startswith(what) else f"{what} file {message}") from None
    except UnicodeDecodeError:
        raise error(f"{what} file {path} is refused: it is not UTF-8 text (a binary file?)") from None
    except yaml.YAMLError as exc:
        raise error(f"{what} file {path} {' '.join(yaml_problem(exc).split())}") from None
    except ValueError as exc:  # a value YAML parses but Python will not build, e.g. an integer of 5,000 digits
        import sys

        digits = sys.get_int_max_str_digits()
        reason = (f"it holds an integer of more than {digits:,} digits" if "integer string conversion" in str(exc)
                  else " ".join(str(exc).split())[:200])
        raise error(f"{what} file {path} is refused: {reason}") from None
    if data is None:  # an empty file (or only comments)
        return {}
    if not isinstance(data, dict):
        raise error(f"{what} file {path} must hold a mapping of fields, got {type(data).__name__}")
    return data


def short_repr(value: Any, limit: int = 200) -> str:
    """A repr for error messages of at most `limit` characters; `reprlib` elides the inside of large containers
    without building their full repr, so a huge input costs nothing to report."""
    import reprlib

    shortener = reprlib.Repr()
    shortener.maxstring = shortener.maxother = limit
    text = shortener.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class StrictModel(BaseModel):
    """Base of socnav's validated settings (env, experiments, thresholds, hyperparameters): unknown fields are
    rejected and every float must be finite (NaN and +-inf are refused by pydantic with the field named). Counts
    are declared ``StrictInt``, so ``true`` is not read as 1 and ``2.5`` is not truncated."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ------------------------------------------------------------------------------------------- validation errors

#: Fields that were renamed: an old name in a file gets "renamed: write <new name>" instead of "unknown field".
RENAMED_FIELDS: dict[str, str] = {"dropout_p": "p_train"}  # the paper's name (Table I)

#: Allowed names are listed in full up to this many; a longer list is only worth reading when nothing is close.
_SHORT_LIST = 8


def close_names(name: str, allowed: Sequence[str]) -> list[str]:
    """The allowed names closest to `name`, best first (difflib, ignoring case; at most 3): every did-you-mean of
    socnav."""
    import difflib

    by_lower = {option.lower(): option for option in allowed}
    return [by_lower[match] for match in difflib.get_close_matches(name.lower(), list(by_lower), n=3, cutoff=0.6)]


def unknown_name_message(what: str, name: Any, allowed: Sequence[str]) -> str:
    """The message for a value that must be one of the registered names `allowed`, e.g. unknown human model
    'socail_force'; allowed: orca, social_force; did you mean social_force? (the validation error names the field)."""
    close = close_names(name, allowed) if isinstance(name, str) else []
    message = f"unknown {what} {short_repr(name)}; allowed: {', '.join(allowed)}"
    return f"{message}; did you mean {' or '.join(close)}?" if close else message


def unknown_field_message(name: str, allowed: Sequence[str]) -> str:
    """'unknown field; allowed fields: a, b, c; did you mean b?' (difflib's closest allowed names). A long list of
    allowed names is left out when a close one exists (not what a user with a typo wants to read)."""
    allowed = list(allowed)
    if RENAMED_FIELDS.get(name) in allowed:
        return f"renamed: write {RENAMED_FIELDS[name]} ({name} is its old name)"
    close = close_names(name, allowed)
    hint = f"did you mean {' or '.join(close)}?"
    if close and len(allowed) > _SHORT_LIST:
        return f"unknown field; {hint}"
    listing = f"unknown field; allowed fields: {', '.join(allowed)}"
    return f"{listing}; {hint}" if close else listing


def format_validation_error(error: ValidationError, headline: str, model: type[BaseModel]) -> str:
    """socnav's one message for a pydantic error of `model`: `headline`, then a line per problem naming the field
    path, what is wrong with the allowed values, and the bad value (capped: see `short_repr`)::

        invalid socnav config (env.yaml):
          - reward.gaol: unknown field; allowed fields: goal, collision, ...; did you mean goal?
          - time_step: Input should be less than or equal to 1 (got 5)
    """
    lines = [headline]
    for item in error.errors():
        loc = tuple(item["loc"])
        parent = _model_at(model, loc[:-1])
        if item["type"] == "extra_forbidden":
            message = (unknown_field_message(str(loc[-1]), list(parent.model_fields)) if parent is not None
                       else "unknown field")
        elif item["type"] == "missing":
            required = [name for name, info in parent.model_fields.items() if info.is_required()] if parent else []
            message = "required field is missing" + (f" (required here: {', '.join(required)})" if required else "")
        else:
            message = item["msg"].removeprefix("Value error, ")
        got = "" if item["type"] == "missing" else f" (got {short_repr(item.get('input'))})"
        lines.append(f"  - {'.'.join(str(part) for part in loc) or '<root>'}: {message}{got}")
    return "\n".join(lines)


def _model_at(model: type[BaseModel], loc: Sequence[Any]) -> type[BaseModel] | None:
    """The model holding the fields at `loc` inside `model` (through nested models, Optional and dict values)."""
    import types
    import typing

    def plain(annotation: Any) -> Any:  # Optional[X] -> X
        if typing.get_origin(annotation) in (Union, types.UnionType):
            members = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
            return members[0] if len(members) == 1 else annotation
        return annotation

    current: Any = model
    for part in loc:
        if isinstance(current, type) and issubclass(current, BaseModel):
            info = current.model_fields.get(str(part))
            current = None if info is None else plain(info.annotation)
        elif typing.get_origin(current) is dict:  # `part` is a key, e.g. budgets.<name>
            current = plain(typing.get_args(current)[1])
        else:
            return None
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def deep_merge(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    """`base` updated with `extra`, nested mappings merged key by key (neither input is modified)."""
    merged = dict(base)
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


# ------------------------------------------------------------------------------------------------ the env config

class _Strict(StrictModel):
    model_config = ConfigDict(validate_assignment=True, frozen=False)


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


class LayoutConfig(_Strict):
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


class ScanConfig(_Strict):
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


class PlannerConfig(_Strict):
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


class RewardConfig(_Strict):
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


class PerturbationConfig(_Strict):
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


class SocialForceConfig(_Strict):
    """Extended social force humans (``humans.model: social_force``; Helbing & Molnár 1995, Moussaïd et al. 2009),
    as PySocialForce 1.1.2 implements them; the defaults are its published ones (its default.toml section in
    brackets). Its step width is the env's ``time_step``; walls push humans by its obstacle force, groups are left
    out."""

    relaxation_time: float = Field(
        default=0.5, gt=0, le=10, description="s: tau of the desired force (desired_force.relaxation_time)"
    )
    goal_threshold: float = Field(
        default=0.2, ge=0, le=10, description="m: within this of its goal the desired force brakes, -v / tau "
        "(desired_force.goal_threshold)"
    )
    desired_force_factor: float = Field(
        default=1.0, ge=0, le=100, description="weight of the desired force (desired_force.factor)"
    )
    social_force_factor: float = Field(
        default=5.1, ge=0, le=100, description="weight of the social force (social_force.factor)"
    )
    lambda_importance: float = Field(
        default=2.0, ge=0, le=100,
        description="weight of the relative velocity in the interaction vector D (social_force)"
    )
    gamma: float = Field(
        default=0.35, gt=0, le=10, description="range B = gamma |D| of the social force (social_force)"
    )
    n: float = Field(default=2.0, ge=0, le=100, description="angular narrowness of the turning term (social_force)")
    n_prime: float = Field(
        default=3.0, ge=0, le=100, description="angular narrowness of the slowing term (social_force)"
    )
    wrap_theta: bool = Field(
        default=False,
        description="wrap the interaction angle theta to [-pi, pi) as in Moussaid et al.; PySocialForce does "
        "not, so a pair whose t and p_i - p_j straddle the -x direction loses most of its force (false: as it)"
    )
    max_speed_multiplier: float = Field(
        default=1.3, gt=0, le=10,
        description="max speed = this x v_pref; humans walk at it (scene.max_speed_multiplier)"
    )
    stop_distance: float = Field(
        default=0.5, ge=0, le=10, description="m: a human this close to its goal stops (fixed in PySocialForce's step)"
    )
    field_of_view: bool = Field(
        default=False,
        description="weight forces from outside the view cone by fov_factor (PySocialForce's simulator: off)"
    )
    fov_phi: float = Field(
        default=100.0, gt=0, le=180, description="degrees: half-angle of that view cone (ped_repulsive_force.fov_phi)"
    )
    fov_factor: float = Field(
        default=0.5, ge=0, le=1,
        description="weight of forces from outside the view cone (ped_repulsive_force.fov_factor)"
    )
    obstacle_force_factor: float = Field(
        default=10.0, ge=0, le=100, description="weight of the walls' force (obstacle_force.factor)"
    )
    obstacle_sigma: float = Field(
        default=0.2, gt=0, le=10,
        description="m: decay length of each wall point's push exp(-(|p - q| - r) / sigma), r the "
        "human's radius (obstacle_force.sigma)"
    )
    obstacle_threshold: float = Field(
        default=3.0, ge=0, le=100, description="m: wall points q push while |p - q| - r < threshold + r "
        "(obstacle_force.threshold)"
    )
    obstacle_resolution: float = Field(
        default=10.0, gt=0, le=1000, description="points per metre along each wall segment, int(length x resolution) "
        "evenly spaced from end to end; shorter segments than 1 / resolution get none (scene.resolution)"
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        # Left out at their defaults, so that a world without walls dumps by the fields it uses only.
        for key in ("obstacle_force_factor", "obstacle_sigma", "obstacle_threshold", "obstacle_resolution"):
            if data.get(key) == type(self).model_fields[key].default:
                del data[key]
        return data


#: At most this many trajectory files in ``humans.replay.files``.
REPLAY_MAX_FILES = 1000


class ReplayConfig(_Strict):
    """Replayed humans (``humans.model: replay`` with ``scenario: replay``): pedestrians follow recorded trajectories
    and do not react (docs/humans.md). The files are ETH/UCY-style text, one ``frame_id ped_id x y`` per line."""

    files: list[str] = Field(
        default_factory=list, description="trajectory files (frame_id ped_id x y per line, whitespace-separated), "
        "checked line by line when the config is read; relative paths are taken from the working directory and "
        "stored absolute",
    )
    sample_rate: float = Field(default=2.5, gt=0, le=1000, description="Hz: recorded samples per second (ETH/UCY: 2.5)")
    frame_step: StrictInt | None = Field(
        default=None, ge=1, le=10**9,
        description="frame ids between two samples; null: inferred per file (the greatest "
        "common divisor of its frame id steps; ETH/UCY: 10)",
    )
    robot_distance: float = Field(
        default=10.0, gt=0, le=200,
        description="m: the robot's start-goal distance, its path through the centre of the "
        "recorded scene in a direction drawn per episode",
    )

    @field_validator("files")
    @classmethod
    def _files_exist(cls, value: list[str]) -> list[str]:
        import os

        from socnav.sim.humans import replay

        if len(value) > REPLAY_MAX_FILES:
            raise ValueError(f"{len(value):,} files; at most {REPLAY_MAX_FILES:,}")
        checked = []
        for name in value:
            path = Path(os.path.expanduser(name))
            shown = short_repr(name)
            if not path.exists():
                raise ValueError(f"trajectory file not found: {shown}")
            if not path.is_file():
                raise ValueError(f"trajectory file {shown} is not a regular file")
            size = path.stat().st_size
            if size > replay.MAX_FILE_BYTES:
                raise ValueError(f"trajectory file {shown} has {size:,} bytes; socnav reads trajectory files of at "
                                 f"most {replay.MAX_FILE_BYTES:,}")
            try:
                replay.check_trajectory_file(path)  # its content: the first bad line is named
            except OSError as exc:
                raise ValueError(f"trajectory file {shown} cannot be read: {exc.strerror or exc}") from None
            checked.append(str(path.resolve()))
        replay.check_total_size(checked)  # all of them together (`MAX_TOTAL_BYTES`), from their sizes
        return checked


class HumansConfig(_Strict):
    """How the humans walk: the model (`socnav.sim.humans` registry) and its parameters, or a mix of models. ORCA
    humans read the ``orca`` section, shared with the ORCA robot controller."""

    model: str = Field(
        default="orca",
        description="human model: orca (RVO2), social_force, replay (recorded trajectories, with scenario: "
        "replay), a registered one, or mix (set by humans.mix)",
    )
    social_force: SocialForceConfig = Field(default_factory=SocialForceConfig)
    mix: dict[str, float] | None = Field(
        default=None, description="a mixed crowd: each human's model drawn per episode with these shares, e.g. "
        "{orca: 0.5, social_force: 0.5} (shares >= 0 summing to 1; sets model: mix)",
    )
    replay: ReplayConfig = Field(default_factory=ReplayConfig)

    @model_validator(mode="before")
    @classmethod
    def _mix_sets_the_model(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("mix") is not None and "model" not in data:
            data = {**data, "model": "mix"}
        return data

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        from socnav.sim.humans import MIX, human_model_names

        allowed = [*human_model_names(), MIX]
        if value not in allowed:
            raise ValueError(unknown_name_message("human model", value, allowed))
        return value

    @field_validator("mix")
    @classmethod
    def _valid_shares(cls, value: dict[str, float] | None) -> dict[str, float] | None:
        from socnav.sim.humans import human_model_names

        if value is None:
            return value
        if not value:
            raise ValueError("give at least one model and its share, e.g. {orca: 0.5, social_force: 0.5}")
        mixable = [name for name in human_model_names() if name != "replay"]
        for name, share in value.items():
            if name == "replay":
                raise ValueError("replay cannot be mixed: replayed humans need the replay scenario")
            if name not in mixable:
                raise ValueError(unknown_name_message("human model", name, mixable))
            if share < 0:
                raise ValueError(f"the share of {name} is {share}; shares must be >= 0")
        total = sum(value.values())
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"the shares sum to {total:g}; they must sum to 1")
        return value

    @model_validator(mode="after")
    def _model_fits_its_settings(self) -> HumansConfig:
        if self.model == "mix" and self.mix is None:
            raise ValueError("model: mix needs humans.mix, the share of each model, e.g. {orca: 0.5, social_force: "
                             "0.5}")
        if self.mix is not None and self.model != "mix":
            raise ValueError(f"humans.mix mixes models per human; leave humans.model out (or write mix), not "
                             f"{self.model!r}")
        if self.model == "replay" and not self.replay.files:
            raise ValueError("model: replay needs humans.replay.files, the recorded trajectories to replay")
        return self


class EnvConfig(_Strict):
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
        _check_range(value, 0.0, 10.0)  # m/s: a running human is ~3-5 m/s
        if value[0] <= 0:
            raise ValueError("preferred speeds must be > 0")
        return value

    @field_validator("personal_space")
    @classmethod
    def _space_range(cls, value: Range) -> Range:
        return _check_range(value, 0.0, 5.0)  # metres beyond the body: proxemics' public zone starts at ~3.7 m

    @field_validator("cooperation")
    @classmethod
    def _coop_range(cls, value: Range) -> Range:
        return _check_range(value, 0.0, 1.0)

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
            from socnav.sim.humans import replay  # lazily: socnav.sim imports this module

            try:
                replay.check_positions(self.humans.replay, self.time_step)
            except OSError as exc:
                raise ValueError(f"humans.replay.files: a trajectory file cannot be read: {exc}") from None
            except replay.TrajectoryFileError as exc:
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
