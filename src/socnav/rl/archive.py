"""The safe archive both socnav files are (`socnav.rl.persistence`'s policy files, `socnav.rl.checkpoints`' training
checkpoints): a zip of a JSON header and tensors, no pickled objects. Nothing in a file can execute code, and a
crafted file gets a one-line error, never a traceback.

Reading is bounded: only stored or deflated, unencrypted members, each with a size cap checked on the declared size
and again while decompressing; the header is validated (known presets, network sizes within limits) and the
tensors' shapes are compared with the shapes the header's network would have (built on torch's ``meta`` device,
which allocates nothing) before the real network is built; NaN/Inf weights are refused. SB3's own ``model.save``
format pickles objects (``cloudpickle``), so loading one from an untrusted source can run arbitrary code; socnav
never reads it.
"""

from __future__ import annotations

import difflib
import io
import math
import struct
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch as th
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictInt,
    ValidationError,
    field_validator,
)

from socnav.rl.policy import ODVActorCriticPolicy
from socnav.rl.presets import AlgoConfig, AlgoName, policy_kwargs_for

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


def check_network_size(config: AlgoConfig) -> AlgoConfig:
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


class ArchiveHeader(BaseModel):
    model_config = ConfigDict(extra="forbid")

    algo: AlgoName
    algo_config: AlgoConfig
    env_config: dict[str, Any]
    seed: StrictInt | None = Field(None, ge=0)

    @field_validator("algo_config")
    @classmethod
    def _network_size(cls, config: AlgoConfig) -> AlgoConfig:
        return check_network_size(config)


def validation_message(error: ValidationError) -> str:
    """pydantic's errors as one line naming each field and the value it got (as `ConfigError` names them)."""
    parts = []
    for item in error.errors()[:5]:
        field = ".".join(str(p) for p in item["loc"]) or "<root>"
        got = repr(item.get("input"))
        parts.append(f"{field}: {item['msg']} (got {got if len(got) <= 60 else got[:57] + '...'})")
    return "; ".join(parts)


_END_OF_CENTRAL_DIRECTORY = b"PK\x05\x06"


_ZIP64_LOCATOR = b"PK\x06\x07"


_EOCD_SIZE = 22


def check_central_directory(path: Path, error: type[Exception], what: str) -> None:
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


def read_members(path: Path, limits: dict[str, int], error: type[Exception], what: str,
                  shipped: Sequence[str] = ()) -> dict[str, bytes]:
    """The named members of the zip at `path`, refusing encryption, unknown compression and anything over its cap;
    a missing file close to a `shipped` name gets a did-you-mean."""
    if path.is_dir():
        raise error(f"{path} is a directory, not a {what} file")
    if not path.is_file():
        near = difflib.get_close_matches(str(path), shipped, n=1)
        hint = f"; did you mean the shipped {what} {near[0]!r}?" if near else ""
        raise error(f"no {what} file at {path}{hint}")
    if path.stat().st_size > MAX_FILE_BYTES:
        raise error(f"{path} is {path.stat().st_size} bytes, more than a {what} file can be ({MAX_FILE_BYTES})")
    contents: dict[str, bytes] = {}
    try:
        check_central_directory(path, error, what)
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


def parse_member_json(data: bytes, path: Path, name: str, error: type[Exception]) -> Any:
    """A header member as JSON, bounded in nesting (`socnav.io.parse_json`); `error` with one line otherwise."""
    from socnav.io import UntrustedInputError, parse_json

    try:
        return parse_json(data, f"{path}: {name}")
    except UntrustedInputError as exc:
        raise error(str(exc)) from None


def write_archive(path: Path, members: dict[str, bytes]) -> Path:
    """Write a zip atomically, with fixed timestamps: the same content always gives the same bytes."""
    from socnav.io import atomic_path

    with atomic_path(path) as temporary, zipfile.ZipFile(temporary, "w") as archive:
        for name, data in members.items():
            info = zipfile.ZipInfo(name, date_time=_FIXED_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, data)
    return path


def load_tensors(data: bytes, path: Path, name: str, error: type[Exception]) -> Any:
    try:
        return th.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupted / non-tensor payloads
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise error(f"{path}: {name} is not a tensors-only state dict ({type(exc).__name__}: {first[:200]})") from None


#: What the network of a header has: per state-dict entry, its shape and dtype.
Expected = dict[str, tuple[tuple[int, ...], th.dtype]]


def policy_for(config: AlgoConfig, env_config: Any, learning_rate: float = 0.0) -> ODVActorCriticPolicy:
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


def check_scan_fov(policy: ODVActorCriticPolicy, env_config: dict[str, Any]) -> None:
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


def expected_shapes(config: AlgoConfig, env_config: Any) -> Expected:
    """Shapes and dtypes of the state dict of the network `config` describes in the world `env_config`, computed on
    the meta device (nothing allocated)."""
    with th.device("meta"):
        policy = policy_for(config, env_config)
    return {key: (tuple(value.shape), value.dtype) for key, value in policy.state_dict().items()}


def tensor_kind_problem(tensor: th.Tensor) -> str | None:
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


def check_state_dict(state: Any, expected: Expected, path: Path, name: str,
                      error: type[Exception]) -> dict[str, th.Tensor]:
    """`state` must be exactly the expected tensors (names, shapes and dtypes), dense, on the cpu and finite."""
    if not isinstance(state, dict) or not all(isinstance(v, th.Tensor) for v in state.values()):
        raise error(f"{path}: {name} does not hold a state dict of tensors")
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        raise error(f"{path}: weights do not fit the recorded network (missing {missing[:3]}, unexpected {extra[:3]})")
    for key, (shape, dtype) in expected.items():
        problem = tensor_kind_problem(state[key])
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

