"""Training checkpoints in socnav's safe format (`socnav.rl.archive`): what ``socnav train --resume`` continues from.
A checkpoint (`save_checkpoint`, `load_checkpoint`) holds
    checkpoint.json  {"format": "socnav-checkpoint", "version": 1, algo, algo_config, env_config, seed, the counters
                     (num_timesteps, n_updates, total_timesteps, progress), the schedules as data
                     ({"kind": "constant", "value": ...}), the episode-statistics buffers and the run's own counters}
    state.pt         {"policy": state_dict, "optimizer": optimizer state_dict} (tensors and plain numbers only);
the optimizer's state is checked against the network it will drive before it is loaded.
"""

from __future__ import annotations

import io
import json
import math
from collections import deque
from pathlib import Path
from typing import Any, Literal

import torch as th
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    ValidationError,
    model_validator,
)

from socnav.rl.archive import (
    MAX_HEADER_BYTES,
    MAX_TENSOR_BYTES,
    ArchiveHeader,
    check_scan_fov,
    check_state_dict,
    expected_shapes,
    load_tensors,
    parse_member_json,
    policy_for,
    read_members,
    tensor_kind_problem,
    validation_message,
    write_archive,
)

CHECKPOINT_FORMAT = "socnav-checkpoint"


CHECKPOINT_VERSION = 1


CHECKPOINT_HEADER = "checkpoint.json"


CHECKPOINT_STATE = "state.pt"


class CheckpointError(RuntimeError):
    """A training checkpoint that cannot be continued from (missing, unreadable, crafted, or not the one the run's
    state names); the message says which file and why."""


class ScheduleData(BaseModel):
    """A schedule stored as data and rebuilt on load (socnav's presets only use constant ones)."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["constant"]
    value: float = Field(gt=0, allow_inf_nan=False)


class EpisodeInfo(BaseModel):
    """One entry of SB3's episode-statistics buffer (return, length, duration), as the training curve reads it."""

    model_config = ConfigDict(extra="forbid")

    r: float = Field(allow_inf_nan=False)
    l: StrictInt = Field(ge=0)  # noqa: E741 (SB3's key)
    t: float = Field(ge=0, allow_inf_nan=False)


class CheckpointHeader(ArchiveHeader):
    """``checkpoint.json`` of a training checkpoint: everything besides tensors that a resumed run needs."""

    format: Literal["socnav-checkpoint"]
    version: Literal[1]
    seed: StrictInt = Field(ge=0)
    num_timesteps: StrictInt = Field(ge=0)
    n_updates: StrictInt = Field(ge=0)
    total_timesteps: StrictInt = Field(ge=0)
    progress_remaining: float = Field(allow_inf_nan=False)
    learning_rate: ScheduleData
    clip_range: ScheduleData
    clip_range_vf: ScheduleData | None
    ep_info_buffer: list[EpisodeInfo] = Field(max_length=10_000)
    ep_success_buffer: list[StrictBool] = Field(max_length=10_000)
    run: dict[str, Any] = Field(default_factory=dict, description="the training run's own counters (opaque here)")

    @model_validator(mode="after")
    def _schedules_are_the_config(self) -> CheckpointHeader:
        """The stored schedules must be the constants of the header's own hyperparameters (what training uses)."""
        config = self.algo_config
        for name, schedule, value in (("learning_rate", self.learning_rate, config.learning_rate),
                                      ("clip_range", self.clip_range, config.clip_range),
                                      ("clip_range_vf", self.clip_range_vf, config.clip_range_vf)):
            stored = None if schedule is None else schedule.value
            if stored != value:
                raise ValueError(f"the {name} schedule ({stored}) is not the algo_config's {name} ({value})")
        return self


def _schedule_data(schedule: Any, name: str) -> dict[str, Any] | None:
    """A schedule as data: SB3 wraps our constant hyperparameters in FloatSchedule(ConstantSchedule(value))."""
    from stable_baselines3.common.utils import ConstantSchedule, FloatSchedule

    if schedule is None:
        return None
    inner = schedule.value_schedule if isinstance(schedule, FloatSchedule) else schedule
    if not isinstance(inner, ConstantSchedule):
        raise ValueError(f"cannot checkpoint the {name} schedule {schedule!r}: only constant schedules are stored")
    return {"kind": "constant", "value": float(inner.val)}


def _json_number(value: Any) -> Any:
    return value.item() if hasattr(value, "item") else value


def save_checkpoint(model: Any, path: str | Path, env_config: dict[str, Any], seed: int,
                    run: dict[str, Any] | None = None) -> Path:
    """Write a resumable checkpoint of the ODVPPO `model` (built by `make_model`) atomically.

    :param env_config: the training env config (JSON dict); `seed`: the run seed.
    :param run: the training run's own counters, stored as given (JSON-safe values).
    """
    check_scan_fov(model.policy, env_config)
    header = {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "algo": model.algo_name,
        "algo_config": model.algo_config, "env_config": env_config, "seed": seed,
        "num_timesteps": int(model.num_timesteps), "n_updates": int(model._n_updates),
        "total_timesteps": int(model._total_timesteps), "progress_remaining": float(model._current_progress_remaining),
        "learning_rate": _schedule_data(model.lr_schedule, "learning_rate"),
        "clip_range": _schedule_data(model.clip_range, "clip_range"),
        "clip_range_vf": _schedule_data(model.clip_range_vf, "clip_range_vf"),
        "ep_info_buffer": [{key: _json_number(info[key]) for key in ("r", "l", "t")}
                           for info in (model.ep_info_buffer or [])],
        "ep_success_buffer": [bool(success) for success in (model.ep_success_buffer or [])],
        "run": run or {},
    }
    state = io.BytesIO()
    th.save({"policy": {name: tensor.detach().cpu() for name, tensor in model.policy.state_dict().items()},
             "optimizer": model.policy.optimizer.state_dict()}, state)
    text = json.dumps(header, indent=2, sort_keys=True, allow_nan=False)
    return write_archive(Path(path), {CHECKPOINT_HEADER: text.encode(), CHECKPOINT_STATE: state.getvalue()})


def read_checkpoint_header(path: str | Path) -> CheckpointHeader:
    """The validated header of the checkpoint at `path`, after reading every member within its size cap (so a torn
    file fails here); the tensors are not unpacked.

    :raises CheckpointError: missing, torn, foreign (e.g. SB3's pickled zips), crafted or invalid file.
    """
    path = Path(path)
    members = read_members(path, {CHECKPOINT_HEADER: MAX_HEADER_BYTES, CHECKPOINT_STATE: MAX_TENSOR_BYTES},
                            CheckpointError, "checkpoint")
    return _validate_checkpoint_header(parse_member_json(members[CHECKPOINT_HEADER], path, CHECKPOINT_HEADER,
                                                   CheckpointError), path)


def _validate_checkpoint_header(data: Any, path: Path) -> CheckpointHeader:
    try:
        return CheckpointHeader.model_validate(data)
    except ValidationError as exc:
        raise CheckpointError(f"{path}: invalid {CHECKPOINT_HEADER}: {validation_message(exc)}") from None


def _same_setting(saved: Any, fresh: Any) -> bool:
    """Whether an optimizer setting from a checkpoint is the fresh optimizer's: equal and of the same type (True is
    not 1, a tuple's items compared one by one)."""
    if isinstance(fresh, (tuple, list)):
        return isinstance(saved, (tuple, list)) and len(saved) == len(fresh) and all(
            _same_setting(a, b) for a, b in zip(saved, fresh, strict=True))
    return type(saved) is type(fresh) and saved == fresh


def _check_optimizer_state(saved: dict[str, Any], optimizer: th.optim.Optimizer, path: Path) -> None:
    """The optimizer state of a checkpoint must be what training with its header's hyperparameters produces, checked
    before torch loads it: the settings of every parameter group (learning rate, betas, eps, weight_decay,
    maximize, amsgrad, ...) equal to those of the optimizer the header builds -- a crafted ``maximize: true`` or a
    huge ``weight_decay`` would silently wreck the resumed training -- and per parameter exactly the moment
    tensors Adam keeps (dense, cpu, the parameter's dtype and shape, finite, second moments >= 0) with a scalar,
    whole, non-negative ``step``.

    :raises CheckpointError: naming the group or parameter and the setting.
    """
    fresh = optimizer.state_dict()
    groups, state = saved["param_groups"], saved["state"]
    _check_parameter_groups(groups, fresh["param_groups"], path)
    _check_moments(state, optimizer, path)


def _check_parameter_groups(groups: Any, expected_groups: list[dict[str, Any]], path: Path) -> None:
    """The saved parameter groups are the fresh optimizer's: as many, each with exactly its settings."""
    if not isinstance(groups, list) or len(groups) != len(expected_groups):
        raise CheckpointError(f"{path}: the optimizer state has {len(groups) if isinstance(groups, list) else 'no'} "
                              f"parameter group(s); the network's optimizer has {len(expected_groups)}")
    for number, (group, expected) in enumerate(zip(groups, expected_groups, strict=True)):
        if not isinstance(group, dict):
            raise CheckpointError(f"{path}: optimizer parameter group {number} is not a mapping")
        unknown = sorted(str(key) for key in set(group) - set(expected))
        if unknown:
            raise CheckpointError(f"{path}: optimizer parameter group {number} has unknown settings {unknown[:3]}; "
                                  f"allowed: {', '.join(sorted(expected))}")
        for key, value in group.items():
            if not _same_setting(value, expected[key]):
                shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
                raise CheckpointError(f"{path}: optimizer setting {key} is {shown}; training with the checkpoint's "
                                      f"hyperparameters uses {expected[key]!r}")


def _check_moments(state: Any, optimizer: th.optim.Optimizer, path: Path) -> None:
    """The saved per-parameter state holds, for parameters of `optimizer` only, exactly Adam's moment tensors."""
    parameters = [parameter for group in optimizer.param_groups for parameter in group["params"]]
    amsgrad = any(group.get("amsgrad") for group in optimizer.param_groups)
    slots = {"step", "exp_avg", "exp_avg_sq"} | ({"max_exp_avg_sq"} if amsgrad else set())
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: the optimizer state is not a mapping of parameters")
    for index, slot in state.items():
        if not (type(index) is int and 0 <= index < len(parameters)) or not isinstance(slot, dict):
            raise CheckpointError(f"{path}: the optimizer state does not fit the network (entry {index!r})")
        if set(slot) != slots or not all(isinstance(value, th.Tensor) for value in slot.values()):
            raise CheckpointError(f"{path}: optimizer entry {index} must hold exactly the tensors "
                                  f"{', '.join(sorted(slots))}; it holds {sorted(map(str, slot))[:5]}")
        parameter = parameters[index]
        for key, value in slot.items():
            problem = _moment_problem(key, value, parameter)
            if problem is not None:
                raise CheckpointError(f"{path}: optimizer entry {index} {key}: {problem}")


def _moment_problem(key: str, value: th.Tensor, parameter: th.Tensor) -> str | None:
    """What is wrong with Adam's state tensor `key` of `parameter`, None if nothing: ``step`` a whole, non-negative
    float scalar; a moment dense, of the parameter's shape and dtype, finite, and (but the first) non-negative."""
    problem = tensor_kind_problem(value)
    if problem is not None:
        return problem
    if key == "step":
        if value.shape != () or not value.is_floating_point():
            return f"shape {tuple(value.shape)} and dtype {value.dtype}, not a float scalar"
        if not (math.isfinite(float(value)) and float(value) >= 0 and float(value).is_integer()):
            return f"{float(value)!r}, not a whole number of steps"
        return None
    if value.shape != parameter.shape or value.dtype != parameter.dtype:
        return (f"shape {tuple(value.shape)} and dtype {value.dtype}; the parameter's are "
                f"{tuple(parameter.shape)} and {parameter.dtype}")
    if not bool(th.isfinite(value).all()):
        return "NaN or Inf values"
    if key != "exp_avg" and bool((value < 0).any()):
        return "negative values (a mean of squares)"
    return None


def _validated_checkpoint(path: Path) -> tuple[CheckpointHeader, dict[str, th.Tensor], dict[str, Any]]:
    """(header, policy weights, optimizer state) of the checkpoint at `path`, every part checked: the header, the
    weights against the header's network, the optimizer state against the optimizer that network trains with.

    :raises CheckpointError: one line naming what is wrong.
    """
    from socnav.config import ConfigError, load_config

    members = read_members(path, {CHECKPOINT_HEADER: MAX_HEADER_BYTES, CHECKPOINT_STATE: MAX_TENSOR_BYTES},
                            CheckpointError, "checkpoint")
    header = _validate_checkpoint_header(parse_member_json(members[CHECKPOINT_HEADER], path, CHECKPOINT_HEADER,
                                                     CheckpointError), path)
    try:
        env_config = load_config(header.env_config)
    except ConfigError as exc:
        raise CheckpointError(f"{path}: invalid env_config: {' '.join(str(exc).split())}") from None
    payload = load_tensors(members[CHECKPOINT_STATE], path, CHECKPOINT_STATE, CheckpointError)
    if not isinstance(payload, dict) or set(payload) != {"policy", "optimizer"}:
        raise CheckpointError(f"{path}: {CHECKPOINT_STATE} must hold exactly 'policy' and 'optimizer'")
    weights = check_state_dict(payload["policy"], expected_shapes(header.algo_config, env_config), path,
                                CHECKPOINT_STATE, CheckpointError)
    optimizer_state = payload["optimizer"]
    if not isinstance(optimizer_state, dict) or set(optimizer_state) != {"state", "param_groups"}:
        raise CheckpointError(f"{path}: {CHECKPOINT_STATE} holds no optimizer state")
    # The optimizer the header's network trains with, as SB3 builds it (learning rate from the schedule at start);
    # the network is small and bounded by the header checks.
    policy = policy_for(header.algo_config, env_config, learning_rate=header.algo_config.learning_rate)
    _check_optimizer_state(optimizer_state, policy.optimizer, path)
    return header, weights, optimizer_state


def verify_checkpoint(path: str | Path) -> CheckpointHeader:
    """Everything `load_checkpoint` checks, without building a model: whether a training can resume from the
    checkpoint at `path`. Returns its header.

    :raises CheckpointError: one line naming what is wrong.
    """
    return _validated_checkpoint(Path(path))[0]


def load_checkpoint(path: str | Path, env: Any, tensorboard_log: str | None = None,
                    verbose: int = 0) -> tuple[Any, CheckpointHeader]:
    """Rebuild the ODVPPO of a checkpoint on `env`: network, optimizer state, counters, schedules and episode
    statistics as they were saved (saving the result again gives the same bytes). The caller reseeds it.

    :raises CheckpointError: missing, foreign, crafted or invalid file; nothing in it is unpickled.
    """
    from stable_baselines3.common.utils import FloatSchedule

    from socnav.rl.presets import make_model

    path = Path(path)
    header, weights, optimizer_state = _validated_checkpoint(path)
    model = make_model(header.algo, env, header.seed, overrides=header.algo_config.model_dump(),
                       tensorboard_log=tensorboard_log, verbose=verbose)
    model.policy.load_state_dict(weights, strict=True)  # names and shapes checked above
    _check_optimizer_state(optimizer_state, model.policy.optimizer, path)  # the very optimizer it goes into
    try:
        model.policy.optimizer.load_state_dict(optimizer_state)
    except (ValueError, KeyError, TypeError, RuntimeError, IndexError) as exc:
        raise CheckpointError(f"{path}: the optimizer state does not fit the network ({exc})") from None
    model.learning_rate = header.learning_rate.value
    model.lr_schedule = FloatSchedule(header.learning_rate.value)
    model.clip_range = FloatSchedule(header.clip_range.value)
    model.clip_range_vf = None if header.clip_range_vf is None else FloatSchedule(header.clip_range_vf.value)
    model.num_timesteps = header.num_timesteps
    model._n_updates = header.n_updates
    model._total_timesteps = header.total_timesteps
    model._current_progress_remaining = header.progress_remaining
    model.ep_info_buffer = deque((info.model_dump() for info in header.ep_info_buffer), maxlen=model._stats_window_size)
    model.ep_success_buffer = deque(header.ep_success_buffer, maxlen=model._stats_window_size)
    return model, header

