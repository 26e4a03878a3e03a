"""Saving and loading trained socnav policies and training checkpoints in a safe format: no pickled objects, only
JSON and tensors. Nothing in a file can execute code, and a crafted file gets a one-line error, never a traceback.

A policy file (`save_policy`, `socnav.load_policy`) is a zip archive holding
    socnav.json  {"format": "socnav-policy", "version": 1, "algo": ..., "algo_config": {...}, "env_config": {...}, ...}
    policy.pt    the policy's ``state_dict`` (tensors only, read with ``torch.load(weights_only=True)``).
A training checkpoint (`save_checkpoint`, `load_checkpoint`, what ``socnav train --resume`` continues from) holds
    checkpoint.json  {"format": "socnav-checkpoint", "version": 1, algo, algo_config, env_config, seed, the counters
                     (num_timesteps, n_updates, total_timesteps, progress), the schedules as data
                     ({"kind": "constant", "value": ...}), the episode-statistics buffers and the run's own counters}
    state.pt         {"policy": state_dict, "optimizer": optimizer state_dict} (tensors and plain numbers only).
SB3's own ``model.save`` format pickles objects (``cloudpickle``), so loading one from an untrusted source can run
arbitrary code; socnav never reads it.

Reading is bounded: only stored or deflated, unencrypted members, each with a size cap checked on the declared size
and again while decompressing; the header is validated (known presets, network sizes within limits) and the
tensors' shapes are compared with the shapes the header's network would have (built on torch's ``meta`` device,
which allocates nothing) before the real network is built; NaN/Inf weights are refused.
"""

from __future__ import annotations

import difflib
import io
import json
import math
import struct
import zipfile
from collections import deque
from importlib import resources
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
    field_validator,
    model_validator,
)

from socnav.rl.policy import ODVActorCriticPolicy
from socnav.rl.presets import AlgoConfig, AlgoName, policy_kwargs_for

FORMAT_NAME = "socnav-policy"
FORMAT_VERSION = 1
METADATA_FILE = "socnav.json"
WEIGHTS_FILE = "policy.pt"
PRETRAINED = "pretrained"
PRETRAINED_MAPS = "pretrained-maps"
PRETRAINED_PPO = "pretrained-ppo"
#: name -> file in socnav/data of each shipped policy (socnav/data/README.md says how each was made and measured)
PRETRAINED_FILES = {PRETRAINED: "pretrained_odv_ppo_drop_position_swap.zip",
                    PRETRAINED_MAPS: "pretrained_odv_ppo_drop_maps.zip",
                    PRETRAINED_PPO: "pretrained_odv_ppo_drop_position_swap_ppo.zip"}
CHECKPOINT_FORMAT = "socnav-checkpoint"
CHECKPOINT_VERSION = 1
CHECKPOINT_HEADER = "checkpoint.json"
CHECKPOINT_STATE = "state.pt"

#: Caps on what a file may make us read or allocate. The shipped policy's weights are 0.4 MB, its header 2 KB.
MAX_FILE_BYTES = 512 << 20
MAX_HEADER_BYTES = 1 << 20
MAX_TENSOR_BYTES = 256 << 20
MAX_MEMBERS = 16
MAX_CENTRAL_DIRECTORY_BYTES = 64 << 10  # MAX_MEMBERS entries with names and extras far longer than socnav writes
MAX_LAYER_SIZE = 4096
MAX_LAYERS = 8
MAX_TORCH_THREADS = 256  # make_model applies a checkpoint's torch_threads process-wide
_ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}
_FIXED_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # timestamps would make two saves of the same state differ

__all__ = [
    "CheckpointError", "PolicyLoadError", "entry_is_finite", "load_checkpoint", "load_policy", "pretrained_path",
    "read_checkpoint_header", "save_checkpoint", "save_policy", "training_world", "validation_message",
    "verify_checkpoint",
]


class PolicyLoadError(ValueError):
    """A file that is not a readable socnav policy (missing, corrupted, foreign or from an incompatible version)."""


class CheckpointError(RuntimeError):
    """A training checkpoint that cannot be continued from (missing, unreadable, crafted, or not the one the run's
    state names); the message says which file and why."""


def pretrained_path(name: str = PRETRAINED) -> Path:
    """Path of a policy shipped inside the package (socnav/data/README.md): ``"pretrained"``, ODV-PPO-Drop's network
    taught the open plane's position swap by imitation of the ORCA robot (DAgger; it drives smoothly),
    ``"pretrained-maps"``, the map policy (DAgger on the four map scenarios), or ``"pretrained-ppo"``, ODV-PPO-Drop
    trained by PPO on position swap as in the paper (it turns bang-bang; `pretrained` until DAgger
    replaced it)."""
    if name not in PRETRAINED_FILES:
        raise PolicyLoadError(f"no shipped policy named {name!r}; the shipped ones are {', '.join(PRETRAINED_FILES)}")
    return Path(str(resources.files("socnav") / "data" / PRETRAINED_FILES[name]))


# ---------------------------------------------------------------------------------------------------------------
# Headers
# ---------------------------------------------------------------------------------------------------------------

def _check_network_size(config: AlgoConfig) -> AlgoConfig:
    """Refuse networks larger than any socnav preset by orders of magnitude (and absurd thread counts): a header
    must not make us allocate."""
    sizes = {"lstm_hidden_size": [config.lstm_hidden_size], "net_arch_pi": list(config.net_arch_pi),
             "net_arch_vf": list(config.net_arch_vf)}
    for name, values in sizes.items():
        if any(not 0 < value <= MAX_LAYER_SIZE for value in values):
            raise ValueError(f"{name} {values} outside the allowed layer sizes 1..{MAX_LAYER_SIZE}")
    for name, count in (("n_lstm_layers", config.n_lstm_layers), ("net_arch_pi", len(config.net_arch_pi)),
                        ("net_arch_vf", len(config.net_arch_vf))):
        if count > MAX_LAYERS:
            raise ValueError(f"{name}: {count} layers, at most {MAX_LAYERS} allowed")
    if config.torch_threads is not None and config.torch_threads > MAX_TORCH_THREADS:
        raise ValueError(f"torch_threads {config.torch_threads} above the allowed {MAX_TORCH_THREADS}")
    return config


class _Header(BaseModel):
    model_config = ConfigDict(extra="forbid")

    algo: AlgoName
    algo_config: AlgoConfig
    env_config: dict[str, Any]
    seed: StrictInt | None = Field(None, ge=0)

    @field_validator("algo_config")
    @classmethod
    def _network_size(cls, config: AlgoConfig) -> AlgoConfig:
        return _check_network_size(config)


class PolicyHeader(_Header):
    """``socnav.json`` of a policy file."""

    format: Literal["socnav-policy"]
    version: Literal[1]
    timesteps: StrictInt | None = Field(None, ge=0)


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


class CheckpointHeader(_Header):
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


def validation_message(error: ValidationError) -> str:
    """pydantic's errors as one line naming each field and the value it got (as `ConfigError` names them)."""
    parts = []
    for item in error.errors()[:5]:
        field = ".".join(str(p) for p in item["loc"]) or "<root>"
        got = repr(item.get("input"))
        parts.append(f"{field}: {item['msg']} (got {got if len(got) <= 60 else got[:57] + '...'})")
    return "; ".join(parts)


# ---------------------------------------------------------------------------------------------------------------
# Bounded archive reading
# ---------------------------------------------------------------------------------------------------------------

_END_OF_CENTRAL_DIRECTORY = b"PK\x05\x06"
_ZIP64_LOCATOR = b"PK\x06\x07"
_EOCD_SIZE = 22


def _check_central_directory(path: Path, error: type[Exception], what: str) -> None:
    """Read the zip's end-of-central-directory record the way `zipfile` finds it (at the very end, else the last one
    within the final 64 KiB) and refuse an archive declaring more than `MAX_MEMBERS` entries, a central directory
    larger than `MAX_CENTRAL_DIRECTORY_BYTES`, or the zip64 extensions (socnav never writes them): `zipfile` builds
    an object per entry of the whole central directory as soon as it opens an archive, before any check of ours."""
    with open(path, "rb") as stream:
        size = stream.seek(0, 2)
        start = max(0, size - (1 << 16) - _EOCD_SIZE)
        stream.seek(start)
        tail = stream.read()
    if tail[-_EOCD_SIZE:-_EOCD_SIZE + 4] == _END_OF_CENTRAL_DIRECTORY and tail[-2:] == b"\0\0":
        offset = len(tail) - _EOCD_SIZE  # no archive comment: zipfile's first guess
    else:
        offset = tail.rfind(_END_OF_CENTRAL_DIRECTORY)
    if offset < 0 or len(tail) - offset < _EOCD_SIZE:
        raise error(f"{path} is not a readable socnav {what} (corrupted or not a zip archive: no end of central "
                    "directory)")
    disk, cd_disk, entries_here, entries, cd_size, cd_offset = struct.unpack_from("<HHHHII", tail, offset + 4)
    zip64 = offset >= 20 and tail[offset - 20:offset - 16] == _ZIP64_LOCATOR
    if zip64 or 0xFFFF in (entries_here, entries) or 0xFFFFFFFF in (cd_size, cd_offset):
        raise error(f"{path} uses the zip64 format; socnav {what} files never do")
    if disk or cd_disk or entries_here != entries:
        raise error(f"{path} is a multi-disk zip archive; socnav {what} files never are")
    if entries > MAX_MEMBERS:
        raise error(f"{path} holds {entries} entries; a {what} file has at most {MAX_MEMBERS}")
    if cd_size > MAX_CENTRAL_DIRECTORY_BYTES:
        raise error(f"{path}: its central directory declares {cd_size} bytes, over the limit of "
                    f"{MAX_CENTRAL_DIRECTORY_BYTES} for {MAX_MEMBERS} entries")


def _read_members(path: Path, limits: dict[str, int], error: type[Exception], what: str) -> dict[str, bytes]:
    """The named members of the zip at `path`, refusing encryption, unknown compression and anything over its cap."""
    if path.is_dir():
        raise error(f"{path} is a directory, not a {what} file")
    if not path.is_file():
        near = difflib.get_close_matches(str(path), PRETRAINED_FILES, n=1) if what == "policy" else []
        hint = f"; did you mean the shipped policy {near[0]!r}?" if near else ""
        raise error(f"no {what} file at {path}{hint}")
    if path.stat().st_size > MAX_FILE_BYTES:
        raise error(f"{path} is {path.stat().st_size} bytes, more than a {what} file can be ({MAX_FILE_BYTES})")
    contents: dict[str, bytes] = {}
    try:
        _check_central_directory(path, error, what)
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            if len(infos) > MAX_MEMBERS:
                raise error(f"{path} holds {len(infos)} entries; a {what} file has at most {MAX_MEMBERS}")
            by_name = {info.filename: info for info in infos}
            missing = [name for name in limits if name not in by_name]
            if missing:
                sb3 = "data" in by_name
                hint = " (an SB3 model zip? socnav writes its own format, never SB3's pickles)" if sb3 else ""
                raise error(f"{path} is not a socnav {what}: it lacks {' and '.join(missing)}{hint}")
            for name, limit in limits.items():
                info = by_name[name]
                if info.flag_bits & 0x1:
                    raise error(f"{path}: {name} is encrypted; socnav files never are")
                if info.compress_type not in _ZIP_METHODS:
                    raise error(f"{path}: {name} uses zip compression method {info.compress_type}; allowed: "
                                + ", ".join(f"{code} ({label})" for code, label in _ZIP_METHODS.items()))
                if info.file_size > limit:
                    raise error(f"{path}: {name} declares {info.file_size} bytes, over the limit of {limit}")
                with archive.open(info) as stream:
                    # At most the declared size (already within the cap): a member lying about its size is cut
                    # there, and its checksum then fails, so a small file never decompresses into a large buffer.
                    data = stream.read(info.file_size + 1)
                if len(data) != info.file_size:
                    raise error(f"{path}: {name} does not decompress to its declared size ({info.file_size} bytes)")
                contents[name] = data
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, NotImplementedError, RuntimeError) as exc:
        raise error(f"{path} is not a readable socnav {what} (corrupted or not a zip archive: {exc})") from None
    return contents


def _parse_json(data: bytes, path: Path, name: str, error: type[Exception]) -> Any:
    """A header member as JSON, bounded in nesting (`socnav.io.parse_json`); `error` with one line otherwise."""
    from socnav.io import UntrustedInputError, parse_json

    try:
        return parse_json(data, f"{path}: {name}")
    except UntrustedInputError as exc:
        raise error(str(exc)) from None


def _write_archive(path: Path, members: dict[str, bytes]) -> Path:
    """Write a zip atomically, with fixed timestamps: the same content always gives the same bytes."""
    from socnav.io import atomic_path

    with atomic_path(path) as temporary, zipfile.ZipFile(temporary, "w") as archive:
        for name, data in members.items():
            info = zipfile.ZipInfo(name, date_time=_FIXED_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, data)
    return path


# ---------------------------------------------------------------------------------------------------------------
# Tensors
# ---------------------------------------------------------------------------------------------------------------

def _load_tensors(data: bytes, path: Path, name: str, error: type[Exception]) -> Any:
    try:
        return th.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupted / non-tensor payloads
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise error(f"{path}: {name} is not a tensors-only state dict ({type(exc).__name__}: {first[:200]})") from None


#: What the network of a header has: per state-dict entry, its shape and dtype.
Expected = dict[str, tuple[tuple[int, ...], th.dtype]]


def _policy_for(config: AlgoConfig, env_config: Any, learning_rate: float = 0.0) -> ODVActorCriticPolicy:
    """The (untrained) network `config` describes for the observations of the world `env_config` (an `EnvConfig`):
    its ``scan`` and, in a world with walls, its ``pose`` key, as `world_observation_space` gives them."""
    from socnav.envs.spaces import action_space, observation_space
    from socnav.sim.scenarios import get_scenario
    from socnav.sim.walls import world_polygons

    walls = bool(world_polygons(env_config, get_scenario(env_config.scenario)))
    space = observation_space(env_config.max_humans, pose=walls, scan=env_config.scan)
    kwargs = policy_kwargs_for(config)
    if env_config.scan is not None:
        kwargs["features_extractor_kwargs"] = {**kwargs["features_extractor_kwargs"], "scan_fov": env_config.scan.fov}
    return ODVActorCriticPolicy(space, action_space(), lambda _: learning_rate, **kwargs)


def _check_scan_fov(policy: ODVActorCriticPolicy, env_config: dict[str, Any]) -> None:
    """Refuse to save a scan policy whose encoder assumed another field of view than its env config's: loaded, it
    would be rebuilt for the config's and act differently (`ScanEncoder`'s padding)."""
    from socnav.config import load_config

    encoder = getattr(policy.features_extractor, "scan_encoder", None)
    if encoder is None:
        return
    scan = load_config(env_config).scan
    if scan is None:
        raise ValueError("the policy reads a range scan but its env config has none (scan: null): give the env "
                         "config of the world it was built for")
    fov = scan.fov
    if encoder.fov != fov:
        raise ValueError(f"the policy's scan encoder was built for a {encoder.fov:g}-degree scan but its env config "
                         f"has scan.fov={fov:g}: build the policy with features_extractor_kwargs="
                         f"{{'scan_fov': {fov:g}}}")


def _expected_shapes(config: AlgoConfig, env_config: Any) -> Expected:
    """Shapes and dtypes of the state dict of the network `config` describes in the world `env_config`, computed on
    the meta device (nothing allocated)."""
    with th.device("meta"):
        policy = _policy_for(config, env_config)
    return {key: (tuple(value.shape), value.dtype) for key, value in policy.state_dict().items()}


def _tensor_kind_problem(tensor: th.Tensor) -> str | None:
    """Why `tensor` is not a plain dense CPU tensor holding its values, None if it is one: sparse, quantized or
    nested layouts, and meta tensors (no values at all), break the checks and the network they would be loaded in."""
    if tensor.is_meta:
        return "a meta tensor (it holds no values)"
    if tensor.layout != th.strided:
        return f"a {str(tensor.layout).removeprefix('torch.')} tensor, not a dense one"
    if tensor.is_quantized:
        return "a quantized tensor"
    if tensor.device.type != "cpu":
        return f"a tensor on {tensor.device.type}, not on the cpu"
    return None


def entry_is_finite(name: str, tensor: th.Tensor, state: dict[str, th.Tensor]) -> bool:
    """Whether `tensor`, the entry `name` of the state dict `state`, holds only finite values, apart from the
    feature-range sentinel: h_min = +inf where h_max = -inf (nothing seen yet).
    Floating AND complex tensors are checked (`torch.isfinite` of a complex value checks its real and imaginary
    parts); integer and bool tensors hold no NaN or inf (their dtype is checked against the network's apart)."""
    if not (tensor.is_floating_point() or tensor.is_complex()):
        return True
    if name.endswith("features_extractor.h_min") or name.endswith("features_extractor.h_max"):
        prefix = name.rsplit(".", 1)[0]
        h_min, h_max = state.get(f"{prefix}.h_min"), state.get(f"{prefix}.h_max")
        if isinstance(h_min, th.Tensor) and isinstance(h_max, th.Tensor) and h_min.shape == h_max.shape:
            unseen = (h_min == math.inf) & (h_max == -math.inf)
            return bool((th.isfinite(tensor) | unseen).all())
    return bool(th.isfinite(tensor).all())


def _check_state_dict(state: Any, expected: Expected, path: Path, name: str,
                      error: type[Exception]) -> dict[str, th.Tensor]:
    """`state` must be exactly the expected tensors (names, shapes and dtypes), dense, on the cpu and finite."""
    if not isinstance(state, dict) or not all(isinstance(v, th.Tensor) for v in state.values()):
        raise error(f"{path}: {name} does not hold a state dict of tensors")
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        raise error(f"{path}: weights do not fit the recorded network (missing {missing[:3]}, unexpected {extra[:3]})")
    for key, (shape, dtype) in expected.items():
        problem = _tensor_kind_problem(state[key])
        if problem is not None:
            raise error(f"{path}: {name} holds {problem} in {key}")
        if state[key].dtype != dtype:
            raise error(f"{path}: {key} is {str(state[key].dtype).removeprefix('torch.')}, the network's is "
                        f"{str(dtype).removeprefix('torch.')}")
        if tuple(state[key].shape) != shape:
            raise error(f"{path}: weights do not fit the recorded network ({key} has shape "
                        f"{tuple(state[key].shape)}, the header's network needs {shape})")
        if not entry_is_finite(key, state[key], state):
            raise error(f"{path}: {name} holds NaN or Inf values in {key}")
    return state


# ---------------------------------------------------------------------------------------------------------------
# Policies
# ---------------------------------------------------------------------------------------------------------------

def save_policy(policy: ODVActorCriticPolicy, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write `policy` and JSON-safe `metadata` (must hold ``algo``, ``algo_config``, ``env_config``) atomically."""
    for key in ("algo", "algo_config", "env_config"):
        if key not in metadata:
            raise ValueError(f"policy metadata needs {key!r}; got keys {sorted(metadata)}")
    _check_scan_fov(policy, metadata["env_config"])
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **metadata}
    weights = io.BytesIO()
    th.save({name: tensor.detach().cpu() for name, tensor in policy.state_dict().items()}, weights)
    return _write_archive(Path(path), {METADATA_FILE: json.dumps(header, indent=2, sort_keys=True).encode(),
                                       WEIGHTS_FILE: weights.getvalue()})


def _read_archive(path: Path) -> tuple[dict[str, Any], PolicyHeader, bytes]:
    members = _read_members(path, {METADATA_FILE: MAX_HEADER_BYTES, WEIGHTS_FILE: MAX_TENSOR_BYTES},
                            PolicyLoadError, "policy")
    header = _parse_json(members[METADATA_FILE], path, METADATA_FILE, PolicyLoadError)
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise PolicyLoadError(f"{path}: {METADATA_FILE} does not declare format {FORMAT_NAME!r}")
    if header.get("version") != FORMAT_VERSION:
        raise PolicyLoadError(
            f"{path}: policy format version {header.get('version')!r} is not supported; allowed: {FORMAT_VERSION}"
        )
    try:
        return header, PolicyHeader.model_validate(header), members[WEIGHTS_FILE]
    except ValidationError as exc:
        raise PolicyLoadError(f"{path}: invalid policy metadata: {validation_message(exc)}") from None


def load_policy(path: str | Path) -> ODVActorCriticPolicy:
    """Load a policy written by `save_policy` / `socnav train`, or a shipped one by name: ``"pretrained"`` (the open
    plane), ``"pretrained-maps"`` (walls and the open plane) or ``"pretrained-ppo"`` (the open plane, trained by PPO
    as in the paper; socnav/data/README.md says how each was made).

    The returned SB3 policy is in eval mode (dropout off); ``policy.predict(obs, deterministic=True)`` gives the
    mean action. Its metadata is on ``policy.socnav_metadata`` (algo, algo_config, env_config, timesteps, ...).

    :raises PolicyLoadError: missing, corrupted, foreign, crafted or incompatible file (one line). Nothing is
        unpickled: the header is JSON and the weights are read with ``torch.load(weights_only=True)``.
    """
    from socnav.config import ConfigError, load_config

    path = pretrained_path(str(path)) if str(path) in PRETRAINED_FILES else Path(path)
    raw_header, header, weights = _read_archive(path)
    try:
        env_config = load_config(header.env_config)
    except ConfigError as exc:
        raise PolicyLoadError(f"{path}: invalid policy metadata: {' '.join(str(exc).split())}") from None
    state = _load_tensors(weights, path, WEIGHTS_FILE, PolicyLoadError)
    _check_state_dict(state, _expected_shapes(header.algo_config, env_config), path, WEIGHTS_FILE, PolicyLoadError)
    policy = _policy_for(header.algo_config, env_config)
    policy.load_state_dict(state, strict=True)  # names and shapes checked above
    policy.set_training_mode(False)
    policy.socnav_metadata = raw_header  # validated above
    return policy


def training_world(policy: Any, scenario: str | None = None, n_humans: int | None = None,
                   max_humans: int | None = None) -> tuple[dict[str, Any], str]:
    """The env config a loaded policy is evaluated in unless told otherwise: the world it was trained in (its
    ``socnav_metadata["env_config"]``), and where that world comes from in words.

    `scenario`, `n_humans` and `max_humans` are the overrides the caller applies on top (``load_config(world,
    **overrides)``); they are not applied here. A scenario other than the training one drops the stored
    ``n_humans``, so that the new scenario starts from its own number of humans.

    :returns: (the env config as a JSON dict, to build with ``load_config``; "the model's training world", with
        ", changed by the options" when any override is given).
    """
    world = dict(policy.socnav_metadata["env_config"])  # a copy: the policy's metadata stays as loaded
    if scenario is not None and scenario != world.get("scenario"):
        world["n_humans"] = None
    changed = scenario is not None or n_humans is not None or max_humans is not None
    return world, "the model's training world" + (", changed by the options" if changed else "")


# ---------------------------------------------------------------------------------------------------------------
# Training checkpoints
# ---------------------------------------------------------------------------------------------------------------

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
    _check_scan_fov(model.policy, env_config)
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
    return _write_archive(Path(path), {CHECKPOINT_HEADER: text.encode(), CHECKPOINT_STATE: state.getvalue()})


def read_checkpoint_header(path: str | Path) -> CheckpointHeader:
    """The validated header of the checkpoint at `path`, after reading every member within its size cap (so a torn
    file fails here); the tensors are not unpacked.

    :raises CheckpointError: missing, torn, foreign (e.g. SB3's pickled zips), crafted or invalid file.
    """
    path = Path(path)
    members = _read_members(path, {CHECKPOINT_HEADER: MAX_HEADER_BYTES, CHECKPOINT_STATE: MAX_TENSOR_BYTES},
                            CheckpointError, "checkpoint")
    return _validate_checkpoint_header(_parse_json(members[CHECKPOINT_HEADER], path, CHECKPOINT_HEADER,
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
    problem = _tensor_kind_problem(value)
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

    members = _read_members(path, {CHECKPOINT_HEADER: MAX_HEADER_BYTES, CHECKPOINT_STATE: MAX_TENSOR_BYTES},
                            CheckpointError, "checkpoint")
    header = _validate_checkpoint_header(_parse_json(members[CHECKPOINT_HEADER], path, CHECKPOINT_HEADER,
                                                     CheckpointError), path)
    try:
        env_config = load_config(header.env_config)
    except ConfigError as exc:
        raise CheckpointError(f"{path}: invalid env_config: {' '.join(str(exc).split())}") from None
    payload = _load_tensors(members[CHECKPOINT_STATE], path, CHECKPOINT_STATE, CheckpointError)
    if not isinstance(payload, dict) or set(payload) != {"policy", "optimizer"}:
        raise CheckpointError(f"{path}: {CHECKPOINT_STATE} must hold exactly 'policy' and 'optimizer'")
    weights = _check_state_dict(payload["policy"], _expected_shapes(header.algo_config, env_config), path,
                                CHECKPOINT_STATE, CheckpointError)
    optimizer_state = payload["optimizer"]
    if not isinstance(optimizer_state, dict) or set(optimizer_state) != {"state", "param_groups"}:
        raise CheckpointError(f"{path}: {CHECKPOINT_STATE} holds no optimizer state")
    # The optimizer the header's network trains with, as SB3 builds it (learning rate from the schedule at start);
    # the network is small and bounded by the header checks.
    policy = _policy_for(header.algo_config, env_config, learning_rate=header.algo_config.learning_rate)
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
