"""The socnav navigator file format: an ONNX graph of the policy network plus a JSON metadata record, sealed with a
sha256 checksum. Shared by the exporter (`socnav.export`, torch) and the runtime (`socnav.runtime`, no torch).

Graph inputs (``N`` rows, ``L`` human rows, dynamic both; ``L`` may be trimmed to the real rows)::

    robot (N, 5)   humans (N, L, 7)   humans_mask (N, L)   [scan (N, beams)]   keep_* : one keep-mask per dropout layer

``scan`` (the range scan's ranges in metres, as the environment observes them) only for a policy trained with one
(``env_config.scan`` set); its encoder's keep masks (``keep_scan_0``, ...) follow the one on ``h``.

Each ``keep_*`` input multiplies its layer's input: ``keep = [u >= p] / (1 - p)`` for MC-dropout (``u`` uniform in
[0, 1)), all ones for the deterministic network. They are listed in ``metadata["dropout_inputs"]`` in forward order
(``per_human``: shaped (N, L, width), else (N, width)), the order of ``policy.dropout_layers()``.
Outputs: ``h`` (N, H) the LSTM state before dropout, ``mean`` (N, 2), ``log_std`` (N, 2), optionally ``value`` (N, 1).

The metadata (ONNX ``metadata_props`` key :data:`METADATA_KEY`, JSON) also carries the observation layout, the
action limits, the env config, ``p_test``, ``K``, the feature range, the safety thresholds and the socnav version;
in a world with walls also ``walls``, their polygons in the map frame (RVO2's orientation; metres, every coordinate
finite and within :data:`socnav.sim.maps.MAX_COORDINATE`, also checked at export), the map the cautious
fallback keeps off (a ``map`` file is stored as its polygons, without its path: the env config's ``map`` is null).
:class:`NavigatorMetadata` is its schema, with the bounds and the consistency rules the runtime relies on.

The checksum (``metadata_props`` key :data:`CHECKSUM_KEY`, 64 lowercase hex digits) is the sha256 of the whole file
with those 64 digits read as ``0``: it covers the graph, its weights and the metadata, so that a file damaged on its
way to the robot (a flipped bit, a truncated copy) is refused at load instead of driving it (:func:`seal`,
:func:`verify`). It is no signature: anyone can recompute it.

Format versions: 2 carries the checksum (a version-1 file, which has none, is refused with a request to re-export
it); 3 also has the ``scan`` input and the ``walls`` record; 4 also a score trigger (``safety.trigger``) that decides
the hand-over instead of the rule; 5 a policy that observes its route (``env_config.planner.observe`` among walls: the
runtime plans the path and hands the policy the goal along it, `socnav.sim.route`), with or without a trigger. The
exporter writes version 5 for a route-observing policy, 4 for a navigator with a trigger, 3 for a world with walls or
a scan, version 2 otherwise; the runtime reads all four, and a socnav that reads only up to 4 refuses a version-5 file
by its version instead of handing its policy the goal itself.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import re
from collections.abc import Iterator
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from socnav.config import EnvConfig, short_repr
from socnav.envs.spaces import ACTION_NAMES, HUMAN_FEATURE_NAMES, ROBOT_FEATURE_NAMES
from socnav.safety.rule import Thresholds
from socnav.sim.maps import MAX_COORDINATE, MAX_TOTAL_VERTICES, validate_polygons
from socnav.sim.scenarios import get_scenario
from socnav.sim.walls import SCAN_KEY, world_polygons

__all__ = [
    "CHECKSUM_KEY",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MAX_DROPOUT_INPUTS",
    "MAX_HUMANS",
    "MAX_K",
    "MAX_WIDTH",
    "MAX_WINDOW",
    "METADATA_KEY",
    "METADATA_MAX_BYTES",
    "METADATA_MAX_DEPTH",
    "NAVIGATOR_MAX_BYTES",
    "OBSERVATION_INPUTS",
    "OUTPUTS",
    "ROUTE_VERSION",
    "SCAN_INPUT",
    "SCAN_KEEP_PREFIX",
    "SUPPORTED_VERSIONS",
    "TRIGGER_VERSION",
    "VALUE_OUTPUT",
    "WALL_FREE_VERSION",
    "NavigatorLoadError",
    "NavigatorMetadata",
    "TriggerRecord",
    "metadata_entries",
    "metadata_message",
    "seal",
    "verify",
]

#: The metadata's ``format`` and ``version`` values (as types: what the schema accepts; as constants below).
FormatName = Literal["socnav-navigator"]
FormatVersion = Literal[2, 3, 4, 5]
FORMAT_NAME: FormatName = "socnav-navigator"
#: 3: a world with walls (``walls``) or a range scan (the ``scan`` input). 2: the file carries a sha256 checksum
#: (:data:`CHECKSUM_KEY`); version-1 files (none) must be re-exported.
FORMAT_VERSION: FormatVersion = 3
#: The version of a navigator without walls and without a scan.
WALL_FREE_VERSION: FormatVersion = 2
#: The version of a navigator whose hand-over a score trigger decides (``safety.trigger``; socnav.safety.triggers),
#: a risk model embedded: older socnav versions refuse it by its version instead of deciding with the rule.
TRIGGER_VERSION: FormatVersion = 4
#: The version of a navigator whose policy observes its route (``env_config.planner.observe`` in a world with walls):
#: older socnav versions refuse it by its version instead of handing the policy the goal itself.
ROUTE_VERSION: FormatVersion = 5
SUPPORTED_VERSIONS: tuple[FormatVersion, ...] = (WALL_FREE_VERSION, FORMAT_VERSION, TRIGGER_VERSION, ROUTE_VERSION)
#: An embedded risk model (base64 of its .npz): the shipped size is ~150 KB; the metadata's whole bound is 1 MiB.
MAX_EMBEDDED_MODEL_CHARS = 800_000
METADATA_KEY = "socnav"
CHECKSUM_KEY = "socnav_sha256"
OBSERVATION_INPUTS = ("robot", "humans", "humans_mask")
#: The graph input of the range scan, after the observation inputs (a policy trained with a scan only).
SCAN_INPUT = SCAN_KEY
#: Names of the scan encoder's keep masks: keep_scan_0, keep_scan_1, ... in forward order.
SCAN_KEEP_PREFIX = "keep_scan_"
OUTPUTS = ("h", "mean", "log_std")
VALUE_OUTPUT = "value"

# Bounds of the metadata (and of `socnav export`'s options): well above anything socnav trains or the paper uses
# (K = 20, window 4, 10 human rows, 64 LSTM units), low enough that a crafted value cannot make the runtime allocate
# gigabytes at its first decision. The widths are the training presets' (`socnav.rl.presets`).
MAX_K = 1000
MAX_WINDOW = 10_000
MAX_HUMANS = 1000
MAX_WIDTH = 4096
MAX_DROPOUT_INPUTS = 64
MAX_RADIUS_SCALE = 10.0
#: The largest navigator file read (the shipped policy's is ~0.4 MB; a 4096-wide network a few hundred MB).
NAVIGATOR_MAX_BYTES = 512 << 20
#: The metadata's JSON text: a few KB, mostly the feature range (two lists of H numbers); nesting 3 deep.
METADATA_MAX_BYTES = 1 << 20
METADATA_MAX_DEPTH = 16


class NavigatorLoadError(ValueError):
    """A file that is not a usable socnav navigator: missing, unreadable, not ONNX, foreign, corrupted (checksum),
    incompatible or with invalid metadata. The message is one line naming the file."""


# --------------------------------------------------------------------------------------------------------------
# The checksum: a minimal reader of the ONNX file's top-level protobuf fields (no `onnx` package in the runtime)
# --------------------------------------------------------------------------------------------------------------

_METADATA_PROPS = 14  # ModelProto.metadata_props: repeated StringStringEntryProto {key = 1, value = 2}
_UNSEALED = b"0" * 64
#: More top-level fields (or fields of one metadata entry) than any ONNX file has (a dozen or so): refused rather
#: than walked, so that a crafted file of millions of tiny fields costs no more than reading it.
_MAX_FIELDS = 100_000
_DIGEST = re.compile(rb"[0-9a-f]{64}")


class _Malformed(ValueError):
    """The bytes are not a protobuf message (this reader's own error; callers turn it into theirs)."""


def _varint(data: bytes, position: int, end: int) -> tuple[int, int]:
    """The varint at `position` and the position after it."""
    value = shift = 0
    while True:
        if position >= end or shift > 63:
            raise _Malformed("a truncated or overlong varint")
        byte = data[position]
        position += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, position
        shift += 7


def _fields(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int, int]]:
    """``(field number, wire type, value start, value end)`` of every field of the message ``data[start:end]``."""
    position, count = start, 0
    while position < end:
        count += 1
        if count > _MAX_FIELDS:
            raise _Malformed(f"more than {_MAX_FIELDS:,} fields")
        tag, position = _varint(data, position, end)
        number, wire = tag >> 3, tag & 7
        if number == 0:
            raise _Malformed("field number 0")
        if wire == 0:
            _, after = _varint(data, position, end)
        elif wire == 1:
            after = position + 8
        elif wire == 2:
            length, position = _varint(data, position, end)
            after = position + length
        elif wire == 5:
            after = position + 4
        else:  # groups (3, 4) are not used by ONNX; 6 and 7 do not exist
            raise _Malformed(f"wire type {wire}")
        if after > end:
            raise _Malformed("a field runs past the end")
        yield number, wire, position, after
        position = after


def metadata_entries(data: bytes) -> dict[str, tuple[int, int]]:
    """Where the value of each ``metadata_props`` entry lies in the ONNX file ``data``: ``{key: (start, end)}``.
    Walks the top-level fields only (linear time, nothing decoded but the keys).

    :raises NavigatorLoadError: not a protobuf message, or a key that is not UTF-8 or occurs twice (message
        without the file's name: the caller adds it).
    """
    entries: dict[str, tuple[int, int]] = {}
    try:
        for number, wire, start, end in _fields(data, 0, len(data)):
            if number != _METADATA_PROPS:
                continue
            if wire != 2:
                raise _Malformed("metadata_props is not a message")
            key, value = b"", (end, end)
            for inner, inner_wire, inner_start, inner_end in _fields(data, start, end):
                if inner in (1, 2) and inner_wire != 2:
                    raise _Malformed("a metadata entry's key or value is not a string")
                if inner == 1:
                    key = data[inner_start:inner_end]
                elif inner == 2:
                    value = (inner_start, inner_end)
            name = key.decode("utf-8")
            if name in entries:
                raise _Malformed(f"the metadata key {short_repr(name, 60)} occurs twice")
            entries[name] = value
    except (_Malformed, UnicodeDecodeError) as exc:
        raise NavigatorLoadError(f"not a readable ONNX model ({exc})") from None
    return entries


def _digest(data: bytes, start: int) -> str:
    """The sha256 of ``data`` with the 64 checksum digits at ``start`` read as ``0``."""
    hasher = hashlib.sha256()
    view = memoryview(data)
    hasher.update(view[:start])
    hasher.update(_UNSEALED)
    hasher.update(view[start + 64:])
    return hasher.hexdigest()


def seal(data: bytes) -> bytes:
    """``data`` (a serialized ONNX model with a :data:`CHECKSUM_KEY` entry of 64 ``0``, as the exporter writes it)
    with its checksum filled in."""
    entries = metadata_entries(data)
    if CHECKSUM_KEY not in entries:
        raise ValueError(f"the model has no {CHECKSUM_KEY!r} metadata entry to fill")
    start, end = entries[CHECKSUM_KEY]
    if end - start != 64:
        raise ValueError(f"the {CHECKSUM_KEY!r} entry must hold 64 characters, has {end - start}")
    return data[:start] + _digest(data, start).encode() + data[end:]


def verify(data: bytes, entries: dict[str, tuple[int, int]]) -> None:
    """Check the checksum of the ONNX file ``data`` (``entries``: :func:`metadata_entries` of it).

    :raises NavigatorLoadError: no checksum (an older format, or not written by `socnav export`), a malformed one,
        or one that does not match the contents (message without the file's name: the caller adds it).
    """
    if CHECKSUM_KEY not in entries:
        raise NavigatorLoadError(f"no {CHECKSUM_KEY!r} checksum (navigator format {FORMAT_VERSION} carries one)")
    start, end = entries[CHECKSUM_KEY]
    stored = data[start:end]
    if end - start != 64 or not _DIGEST.fullmatch(stored):
        raise NavigatorLoadError(f"its {CHECKSUM_KEY!r} checksum is malformed (not 64 lowercase hex digits): "
                                 "the file is corrupted; export or copy it again")
    if not hmac.compare_digest(stored, _digest(data, start).encode()):
        raise NavigatorLoadError("the file is corrupted: its sha256 checksum does not match its contents; export "
                                 "or copy it again")


# --------------------------------------------------------------------------------------------------------------
# The metadata's schema
# --------------------------------------------------------------------------------------------------------------

Name = Annotated[str, Field(max_length=200)]
Text = Annotated[str, Field(max_length=2000)]
# The feature range may hold the "nothing seen" sentinel (h_min = +inf where h_max = -inf); never NaN.
Bound = Annotated[float, Field(allow_inf_nan=True)]


class _Record(BaseModel):
    """Strict: unknown fields refused, no type coercion (``"0.5"`` and ``true`` are not numbers), floats finite."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)


class ObservationRecord(_Record):
    robot: list[Name] = Field(max_length=64)
    human: list[Name] = Field(max_length=64)
    max_humans: int = Field(ge=1, le=MAX_HUMANS)
    layout: Text

    @model_validator(mode="after")
    def _layout(self) -> ObservationRecord:
        # The runtime builds the observation with this socnav's kernel: the file must expect that very layout.
        if tuple(self.robot) != ROBOT_FEATURE_NAMES or tuple(self.human) != HUMAN_FEATURE_NAMES:
            raise ValueError(f"the observation features {self.robot} / {self.human} are not this socnav's "
                             f"{list(ROBOT_FEATURE_NAMES)} / {list(HUMAN_FEATURE_NAMES)}")
        return self


class ActionRecord(_Record):
    names: list[Name] = Field(max_length=16)
    low: float
    high: float
    command: Text
    max_heading_change: float = Field(gt=0, le=math.pi)
    time_step: float = Field(gt=0, le=10)

    @model_validator(mode="after")
    def _unit_box(self) -> ActionRecord:
        if tuple(self.names) != ACTION_NAMES or (self.low, self.high) != (-1.0, 1.0):
            raise ValueError(f"the action must be {list(ACTION_NAMES)} in [-1, 1], got {self.names} in "
                             f"[{self.low}, {self.high}]")
        return self


class PolicyRecord(_Record):
    algo: Name | None
    timesteps: int | None = Field(ge=0, le=10**15)
    seed: int | None = Field(ge=-(2**63), lt=2**64)
    odv: bool
    dropout_p: float = Field(ge=0, lt=1)
    lstm_hidden_size: int = Field(ge=1, le=MAX_WIDTH)


class MCDropoutRecord(_Record):
    k: int = Field(ge=2, le=MAX_K, description="MC-dropout samples per decision")
    # 0 would keep every unit: K identical samples, an uncertainty that is always 0 (the safety rule blind)
    p_test: float = Field(gt=0, lt=1, description="MC-dropout probability")


class DropoutInput(_Record):
    name: str = Field(pattern=r"^keep_[a-z0-9_]{1,64}$")
    per_human: bool
    width: int = Field(ge=1, le=MAX_WIDTH)


class FeatureRange(_Record):
    h_min: list[Bound] = Field(max_length=MAX_WIDTH)
    h_max: list[Bound] = Field(max_length=MAX_WIDTH)

    @model_validator(mode="after")
    def _pairs(self) -> FeatureRange:
        if len(self.h_min) != len(self.h_max):
            raise ValueError(f"h_min has {len(self.h_min)} values, h_max {len(self.h_max)}")
        for index, (low, high) in enumerate(zip(self.h_min, self.h_max, strict=True)):
            unseen = low == math.inf and high == -math.inf
            if not unseen and not (math.isfinite(low) and math.isfinite(high) and low <= high):
                raise ValueError(f"element {index} is [{low}, {high}]: a finite range (h_min <= h_max) or the "
                                 "unseen sentinel [inf, -inf] required")
        return self


class SafetyRecord(_Record):
    thresholds: Thresholds
    source: Text
    window: int = Field(ge=1, le=MAX_WINDOW, description="uncertainty window in steps")
    radius_scale: float = Field(gt=0, le=MAX_RADIUS_SCALE, description="the cautious controller's radius scale")
    trigger: TriggerRecord | None = Field(None, description="a score trigger deciding instead of the rule")

    @field_validator("thresholds", mode="before")
    @classmethod
    def _thresholds_mapping(cls, value: Any) -> Any:
        # Never a preset name or a path: the runtime would read whatever file the metadata names.
        if not isinstance(value, dict):
            raise ValueError(f"must be a mapping of the threshold fields, got {type(value).__name__}")
        return value


class TriggerRecord(_Record):
    """A score trigger that decides the hand-over instead of the rule (`socnav.safety.triggers.TriggerSpec` without
    its file path; a risk model's weights embedded as base64 of its ``.npz``)."""

    trigger: Name
    params: dict[Name, float] = Field(default_factory=dict, max_length=32)
    threshold: float
    sensing: Literal["perceived", "true"]
    hold_steps: int = Field(ge=0, le=1000)
    risk_model: str | None = Field(None, max_length=MAX_EMBEDDED_MODEL_CHARS)

    @model_validator(mode="after")
    def _known_trigger(self) -> TriggerRecord:
        from socnav.safety.triggers import TriggerSpec

        TriggerSpec.create(trigger=self.trigger, params=self.params, threshold=self.threshold,
                           sensing=self.sensing, hold_steps=self.hold_steps)  # its one-line error otherwise
        if (self.trigger == "risk-model") != (self.risk_model is not None):
            raise ValueError("a risk-model trigger embeds its model (risk_model), no other trigger does")
        if self.risk_model is not None:  # checked here, so a broken model fails the load, not the first decision
            import base64
            import binascii

            from socnav.safety.risk_model import risk_model_from_bytes

            try:
                raw = base64.b64decode(self.risk_model, validate=True)
            except binascii.Error:
                raise ValueError("risk_model is not base64 text") from None
            risk_model_from_bytes(raw, "the embedded risk model")
        return self


#: One polygon: [x, y] vertices (checked by `socnav.sim.maps.validate_polygons`: finite, within
#: `socnav.sim.maps.MAX_COORDINATE` metres of the map frame's origin, the polygon and vertex-count rules).
Vertex = Annotated[list[float], Field(min_length=2, max_length=2)]
Polygon = Annotated[list[Vertex], Field(max_length=MAX_TOTAL_VERTICES)]


class NavigatorMetadata(_Record):
    """The metadata record of a navigator file, validated: every field bounded and the parts consistent with
    each other (the graph's inputs and outputs are checked against it by `ExportedPolicy`)."""

    format: FormatName
    version: FormatVersion
    socnav_version: Name
    observation: ObservationRecord
    action: ActionRecord
    env_config: EnvConfig
    policy: PolicyRecord
    mc_dropout: MCDropoutRecord
    dropout_inputs: list[DropoutInput] = Field(min_length=2, max_length=MAX_DROPOUT_INPUTS)
    outputs: list[Name] = Field(max_length=8)
    feature_range: FeatureRange
    safety: SafetyRecord
    walls: list[Polygon] | None = Field(None, min_length=1, max_length=MAX_TOTAL_VERTICES,
                                           description="the world's walls, polygons in the map frame (metres, "
                                           f"every coordinate within +-{MAX_COORDINATE:g})")

    @field_validator("walls")
    @classmethod
    def _valid_walls(cls, value: list[list[list[float]]] | None) -> list[list[list[float]]] | None:
        if value is not None:  # a MapError (ValueError) names the polygon and the rule, e.g. a vertex of 1e308 m:
            validate_polygons(value, name="walls")  # beyond MAX_COORDINATE, refused before any geometry
        return value

    @model_validator(mode="after")
    def _consistent(self) -> NavigatorMetadata:
        env = self.env_config
        if self.observation.max_humans != env.max_humans:
            raise ValueError(f"observation.max_humans={self.observation.max_humans} but "
                             f"env_config.max_humans={env.max_humans}")
        if (self.action.max_heading_change, self.action.time_step) != (env.max_heading_change, env.time_step):
            raise ValueError("action.max_heading_change / time_step differ from the env config's")
        if self.outputs not in (list(OUTPUTS), [*OUTPUTS, VALUE_OUTPUT]):
            raise ValueError(f"outputs must be {list(OUTPUTS)}, optionally followed by {VALUE_OUTPUT!r}; got "
                             f"{self.outputs}")
        hidden = self.policy.lstm_hidden_size
        names = [spec.name for spec in self.dropout_inputs]
        if len(set(names)) != len(names):
            raise ValueError(f"dropout_inputs: repeated names in {names}")
        # Forward order: the LSTM layers' inputs (the human features, then H wide), then h (H), then the actor's.
        lstm = [spec for spec in self.dropout_inputs if spec.per_human]
        rest = self.dropout_inputs[len(lstm):]
        if not lstm or any(spec.per_human for spec in rest) or not rest:
            raise ValueError("dropout_inputs: the per-human (LSTM input) masks come first, then at least the one "
                             "on h")
        widths = [spec.width for spec in lstm]
        if widths != [len(HUMAN_FEATURE_NAMES)] + [hidden] * (len(lstm) - 1) or rest[0].width != hidden:
            raise ValueError(f"dropout_inputs: widths {[spec.width for spec in self.dropout_inputs]} do not fit "
                             f"{len(HUMAN_FEATURE_NAMES)} human features and lstm_hidden_size={hidden}")
        scan = [spec for spec in rest[1:] if spec.name.startswith(SCAN_KEEP_PREFIX)]
        if [spec.name for spec in rest[1:len(scan) + 1]] != [f"{SCAN_KEEP_PREFIX}{i}" for i in range(len(scan))]:
            raise ValueError(f"dropout_inputs: the scan encoder's masks {[spec.name for spec in scan]} must follow "
                             f"the one on h, numbered from 0")
        beams = None if env.scan is None else env.scan.beams
        if (beams is None) != (not scan) or (scan and scan[0].width != beams):
            raise ValueError(f"dropout_inputs: {len(scan)} scan masks (first width "
                             f"{scan[0].width if scan else None}) for env_config.scan {short_repr(env.scan, 80)}")
        if self.walls is None and world_polygons(env, get_scenario(env.scenario)):
            raise ValueError(f"env_config describes a world with walls (scenario {env.scenario!r} or obstacles) but "
                             "the metadata holds no walls")
        if self.version == WALL_FREE_VERSION and (env.scan is not None or self.walls is not None):
            raise ValueError(f"version {WALL_FREE_VERSION} has neither a scan nor walls; a navigator with them is "
                             f"version {FORMAT_VERSION}")
        route = bool(env.planner.observe and self.walls is not None)
        if (self.version == ROUTE_VERSION) != route:
            raise ValueError(f"version {ROUTE_VERSION} is the version of a navigator whose policy observes its route "
                             "(env_config.planner.observe with walls), and only of one")
        if not route and (self.version == TRIGGER_VERSION) != (self.safety.trigger is not None):
            raise ValueError(f"version {TRIGGER_VERSION} is the version of a navigator with a safety.trigger, and "
                             "only of one")
        if len(self.feature_range.h_min) != hidden:
            raise ValueError(f"feature_range has {len(self.feature_range.h_min)} values per bound, "
                             f"lstm_hidden_size={hidden}")
        return self


def metadata_message(error: ValidationError) -> str:
    """pydantic's errors as one line naming each field and the value it got (the first five)."""
    parts = []
    for item in error.errors()[:5]:
        field = ".".join(str(part) for part in item["loc"]) or "<root>"
        got = "" if item["type"] == "missing" else f" (got {short_repr(item.get('input'), 60)})"
        parts.append(f"{field}: {item['msg'].removeprefix('Value error, ')}{got}")
    more = len(error.errors()) - 5
    return "; ".join(parts) + (f"; and {more} more" if more > 0 else "")
