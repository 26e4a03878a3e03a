"""The `humans` section of the world's configuration: the human model (or a mixed crowd), social force's parameters
and the replayed recordings.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import (
    Field,
    StrictInt,
    field_validator,
    model_serializer,
    model_validator,
)

from socnav.sim.config.sections import Section
from socnav.validation import short_repr, unknown_name_message


class SocialForceConfig(Section):
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


class ReplayConfig(Section):
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

        from socnav.sim.humans import trajectories

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
            if size > trajectories.MAX_FILE_BYTES:
                raise ValueError(f"trajectory file {shown} has {size:,} bytes; socnav reads trajectory files of at "
                                 f"most {trajectories.MAX_FILE_BYTES:,}")
            try:
                trajectories.check_trajectory_file(path)  # its content: the first bad line is named
            except OSError as exc:
                raise ValueError(f"trajectory file {shown} cannot be read: {exc.strerror or exc}") from None
            checked.append(str(path.resolve()))
        trajectories.check_total_size(checked)  # all of them together (`MAX_TOTAL_BYTES`), from their sizes
        return checked


class HumansConfig(Section):
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

