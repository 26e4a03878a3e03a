"""The exported policy network run by onnxruntime: deterministic actions and MC-dropout samples, no torch.
`ExportedPolicy` reads a navigator file written by `socnav export`; `DropoutStream` draws the dropout uniforms.

Observation batches follow the environment's layout (``robot`` (B, 5), ``humans`` (B, M, 7), ``humans_mask``
(B, M), and ``scan`` (B, beams) for a network that reads a range scan). Like the torch extractor, a call trims the
human rows to the longest real sequence of the batch, so the uniforms drawn for the LSTM-input dropout have the
shapes torch's dropout draws (and none are drawn when no observation has a human): fed the same stream,
`MCDropoutEstimator(policy, uniforms=stream)` and :meth:`ExportedPolicy.samples` see the same masks.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np
import onnxruntime
from pydantic import ValidationError

from socnav.config import short_repr
from socnav.envs.spaces import HUMAN_FEATURE_NAMES, ROBOT_FEATURE_NAMES
from socnav.io import UntrustedInputError, parse_json, read_bounded
from socnav.runtime.format import (
    CHECKSUM_KEY,
    FORMAT_NAME,
    METADATA_KEY,
    METADATA_MAX_BYTES,
    METADATA_MAX_DEPTH,
    NAVIGATOR_MAX_BYTES,
    OBSERVATION_INPUTS,
    SCAN_INPUT,
    SUPPORTED_VERSIONS,
    VALUE_OUTPUT,
    WALL_FREE_VERSION,
    NavigatorLoadError,
    NavigatorMetadata,
    metadata_entries,
    metadata_message,
    verify,
)
from socnav.uncertainty.stats import Uncertainty, apply_feature_map, feature_map, summarise_samples

__all__ = ["DropoutStream", "ExportedPolicy", "MCBatch", "NavigatorLoadError", "NetworkOutput", "Uniforms",
           "read_metadata"]

#: ``uniforms(layer, shape) -> array`` of U[0, 1) samples (the hook `MCDropoutEstimator` accepts too).
Uniforms = Callable[[int, tuple[int, ...]], np.ndarray]


class DropoutStream:
    """A reproducible stream of dropout uniforms: ``stream(layer, shape)`` -> float32 U[0, 1) of ``shape``.

    One NumPy generator seeded with ``seed``; every call advances it, whatever the layer. Give a torch
    ``MCDropoutEstimator(policy, uniforms=DropoutStream(s))`` and a runtime ``DropoutStream(s)`` the same calls in
    the same order and both see identical masks.
    """

    def __init__(self, seed: int | None = None) -> None:
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def __call__(self, layer: int, shape: tuple[int, ...]) -> np.ndarray:
        return self.rng.random(shape, dtype=np.float32)

    def fill(self, out: np.ndarray) -> None:
        """Draw ``out.size`` uniforms into the float32 array ``out`` in one call: the numbers that consecutive
        calls for the pieces of ``out``, in order, would give (NumPy's generator continues its stream across
        calls), so one call can serve every dropout layer of a decision."""
        self.rng.random(out=out, dtype=np.float32)


def _uniforms_of(uniforms: Uniforms, layer: int, shape: tuple[int, ...]) -> np.ndarray:
    """``uniforms(layer, shape)`` as float32, checked to have that shape."""
    drawn = np.asarray(uniforms(layer, shape), dtype=np.float32)
    if drawn.shape != shape:
        raise ValueError(f"uniforms for dropout layer {layer}: expected shape {shape}, got {drawn.shape}")
    return drawn


def keep_from_uniforms(uniforms: np.ndarray, p: float, out: np.ndarray) -> None:
    """``out[...] = [u >= p] / (1 - p)``: the dropout keep mask of the float32 uniforms ``u`` (``u >= p`` compared
    in float32, as torch's dropout layers compare them). ``out``: a C-contiguous float32 array of ``u``'s size."""
    if out.dtype != np.float32 or not out.flags.c_contiguous or out.size != uniforms.size:
        raise ValueError("keep_from_uniforms needs a C-contiguous float32 `out` of the uniforms' size")
    _keep_kernel(np.ascontiguousarray(uniforms, dtype=np.float32).reshape(-1), np.float32(p),
                 np.float32(1.0 / (1.0 - p)), out.reshape(-1), np.array([[0, 0, out.size]], dtype=np.int64))


@numba.njit(cache=True)
def _keep_kernel(uniforms: np.ndarray, p: np.float32, scale: np.float32, out: np.ndarray,
                 segments: np.ndarray) -> None:  # pragma: no cover
    """``out[o : o + n] = [u[s : s + n] >= p] * scale`` for every segment ``(s, o, n)`` (1-D float32 arrays)."""
    for segment in range(segments.shape[0]):
        start, target, length = segments[segment, 0], segments[segment, 1], segments[segment, 2]
        drawn, keep = uniforms[start:start + length], out[target:target + length]
        for index in range(length):  # branch-free, so that it vectorises
            keep[index] = scale * np.float32(drawn[index] >= p)


@dataclass(frozen=True)
class NetworkOutput:
    """One batched pass: ``h`` (N, H), ``mean`` (N, 2), ``log_std`` (N, 2) float32; ``value`` (N, 1) or None."""

    h: np.ndarray
    mean: np.ndarray
    log_std: np.ndarray
    value: np.ndarray | None


def _session(data: bytes, path: Path, threads: int) -> onnxruntime.InferenceSession:
    """An onnxruntime session of the model ``data`` (the bytes whose checksum was verified: the file is read once)."""
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only: a navigator should not print warnings per load
    try:
        return onnxruntime.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types (InvalidProtobuf, Fail, ...)
        message = " ".join(str(exc).split())[:300]
        raise NavigatorLoadError(f"{path} is not a readable ONNX model ({type(exc).__name__}: {message})") from None


def _read_file(path: Path) -> bytes:
    """The file's bytes, at most :data:`NAVIGATOR_MAX_BYTES` of them."""
    if not path.is_file():
        raise NavigatorLoadError(f"no navigator file at {path}")
    try:
        return read_bounded(path, NAVIGATOR_MAX_BYTES)
    except UntrustedInputError as exc:
        raise NavigatorLoadError(str(exc)) from None
    except OSError as exc:
        raise NavigatorLoadError(f"{path} cannot be read ({exc.strerror or exc})") from None


def _declared_version(text: bytes) -> Any:
    """The ``version`` the metadata text declares, None when it cannot be read (best effort, for the messages
    about files of another format version; nothing else is taken from an unverified file)."""
    try:
        metadata = parse_json(text, "metadata", METADATA_MAX_DEPTH)
    except UntrustedInputError:
        return None
    return metadata.get("version") if isinstance(metadata, dict) else None


def read_metadata(data: bytes, path: Path) -> dict[str, Any]:
    """The metadata record of the navigator file ``data`` as parsed JSON, after its checksum was verified; the
    record's schema is checked by `ExportedPolicy` (:class:`socnav.runtime.format.NavigatorMetadata`).

    :raises NavigatorLoadError: not ONNX, not a navigator, another format version, no or a wrong checksum,
        metadata that is too large, too deep, not UTF-8 or not JSON.
    """
    try:
        entries = metadata_entries(data)
    except NavigatorLoadError as exc:
        raise NavigatorLoadError(f"{path}: {exc}") from None
    if METADATA_KEY not in entries:
        raise NavigatorLoadError(f"{path} is an ONNX model but not a socnav navigator (no {METADATA_KEY!r} "
                                 "metadata; write one with `socnav export`)")
    start, end = entries[METADATA_KEY]
    if end - start > METADATA_MAX_BYTES:
        raise NavigatorLoadError(f"{path}: the {METADATA_KEY!r} metadata is larger than {METADATA_MAX_BYTES:,} bytes, "
                                 "the most a navigator holds")
    text = data[start:end]
    # Another format version first: it may seal its file differently (or not at all, as version 1 did).
    version = _declared_version(text)
    allowed = ", ".join(map(str, SUPPORTED_VERSIONS))
    if type(version) is int and version not in SUPPORTED_VERSIONS:
        if version < min(SUPPORTED_VERSIONS):
            raise NavigatorLoadError(
                f"{path}: navigator format version {version} is not supported; allowed: {allowed} (version "
                f"{WALL_FREE_VERSION} adds a checksum against corrupted files): re-export it with `socnav export`")
        raise NavigatorLoadError(f"{path}: navigator format version {version} is not supported; allowed: "
                                 f"{allowed} (written by a newer socnav)")
    try:
        verify(data, entries)
    except NavigatorLoadError as exc:
        raise NavigatorLoadError(f"{path}: {exc}; re-export it with `socnav export`" if CHECKSUM_KEY not in entries
                                 else f"{path}: {exc}") from None
    try:
        metadata = parse_json(text, f"{path}: the {METADATA_KEY!r} metadata", METADATA_MAX_DEPTH)
    except UntrustedInputError as exc:
        raise NavigatorLoadError(str(exc)) from None
    if not isinstance(metadata, dict) or metadata.get("format") != FORMAT_NAME:
        raise NavigatorLoadError(f"{path}: the metadata does not declare format {FORMAT_NAME!r}")
    if type(metadata.get("version")) is not int or metadata["version"] not in SUPPORTED_VERSIONS:
        raise NavigatorLoadError(f"{path}: navigator format version {short_repr(metadata.get('version'), 40)} is "
                                 f"not supported; allowed: {allowed}")
    return metadata


def _expected_shape(spec: Mapping[str, Any]) -> tuple[int | str, ...]:
    """A keep input's shape: ``"rows"`` / ``"human_rows"`` stand for the dynamic dimensions."""
    return ("rows", "human_rows", spec["width"]) if spec["per_human"] else ("rows", spec["width"])


def _shape_fits(actual: Sequence[Any], expected: Sequence[int | str]) -> bool:
    """The graph declares ``expected``: each fixed width exactly, each dynamic dimension as not fixed."""
    return len(actual) == len(expected) and all(
        (dim == want) if isinstance(want, int) else not isinstance(dim, int)
        for dim, want in zip(actual, expected, strict=True))


class ExportedPolicy:
    """A socnav navigator file's network in an onnxruntime session (CPU, ``threads`` intra-op threads).

    :meth:`predict` gives the deterministic action (SB3-style, clipped to [-1, 1]); :meth:`samples` and
    :meth:`uncertainty` the MC-dropout samples and their uncertainty (`MCDropoutEstimator`'s equations);
    :meth:`run` is the raw graph call. ``metadata`` is the file's JSON record (see `socnav.runtime.format`),
    ``record`` the same validated (:class:`~socnav.runtime.format.NavigatorMetadata`: env config and thresholds
    as `EnvConfig` and `Thresholds`).

    :raises NavigatorLoadError: metadata that does not validate, a graph whose inputs or outputs do not match it,
        or a graph that fails or gives non-finite outputs on a test observation (all found here, at load).
    """

    def __init__(self, session: onnxruntime.InferenceSession, metadata: Mapping[str, Any], path: Path) -> None:
        self.session, self.metadata, self.path = session, dict(metadata), path
        try:
            self.record = NavigatorMetadata.model_validate(self.metadata)
        except ValidationError as exc:
            raise NavigatorLoadError(f"{path}: invalid navigator metadata: {metadata_message(exc)}") from None
        record = self.record
        self.dropout_inputs: list[dict[str, Any]] = [spec.model_dump() for spec in record.dropout_inputs]
        self.n_lstm = sum(1 for spec in self.dropout_inputs if spec["per_human"])
        self.max_humans = record.observation.max_humans
        self.k = record.mc_dropout.k
        self.p_test = record.mc_dropout.p_test
        self.output_names = list(record.outputs)
        self.hidden_size = record.policy.lstm_hidden_size
        #: the range scan the network reads (`socnav.config.ScanConfig`: beams, range, fov), None if it reads none
        self.scan = record.env_config.scan
        #: the world's walls (polygons (k, 2), map frame), None in a world without walls
        self.walls = None if record.walls is None else [np.asarray(polygon, dtype=np.float64)
                                                        for polygon in record.walls]
        scan_input = [] if self.scan is None else [SCAN_INPUT]
        self.input_names = [*OBSERVATION_INPUTS, *scan_input, *(spec["name"] for spec in self.dropout_inputs)]
        self._check_graph()
        self.feature_map = feature_map(np.asarray(record.feature_range.h_min, dtype=np.float64),
                                       np.asarray(record.feature_range.h_max, dtype=np.float64))
        self._probe()

    def _check_graph(self) -> None:
        """The graph's inputs and outputs are the metadata's: names, order, float32, shapes (fixed widths equal,
        the rows and human rows dynamic)."""
        shapes: dict[str, tuple[int | str, ...]] = {
            "robot": ("rows", len(ROBOT_FEATURE_NAMES)), "humans": ("rows", "human_rows", len(HUMAN_FEATURE_NAMES)),
            "humans_mask": ("rows", "human_rows"),
            **({} if self.scan is None else {SCAN_INPUT: ("rows", self.scan.beams)}),
            **{spec["name"]: _expected_shape(spec) for spec in self.dropout_inputs},
            "h": ("rows", self.hidden_size), "mean": ("rows", 2), "log_std": ("rows", 2), VALUE_OUTPUT: ("rows", 1)}
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        graph_inputs, graph_outputs = [node.name for node in inputs], [node.name for node in outputs]
        if graph_inputs != self.input_names or graph_outputs != self.output_names:
            raise NavigatorLoadError(f"{self.path}: the graph's inputs {graph_inputs} / outputs {graph_outputs} do "
                                     f"not match its metadata ({self.input_names} / {self.output_names})")
        for node in (*inputs, *outputs):
            if node.type != "tensor(float)" or not _shape_fits(node.shape, shapes[node.name]):
                raise NavigatorLoadError(f"{self.path}: the graph's {node.name!r} is {node.type} {node.shape}; its "
                                         f"metadata needs tensor(float) {list(shapes[node.name])}")

    def _probe(self) -> None:
        """One call on two test rows (one human, none): the graph runs, with the declared output shapes, and its
        outputs are finite. A graph with NaN weights, or one onnxruntime cannot run, is refused here rather than
        at the robot's first decision."""
        robot = np.array([[4.0, 0.5, 0.5, 1.0, 0.3]] * 2, np.float32)
        humans = np.zeros((2, 2, len(HUMAN_FEATURE_NAMES)), np.float32)
        humans[0, 0] = [1.0, 0.5, -0.5, 0.0, 0.3, 0.6, 0.5]
        mask = np.array([[1.0, 0.0], [0.0, 0.0]], np.float32)
        scan = None if self.scan is None else np.full((2, self.scan.beams), self.scan.range, np.float32)
        try:
            output = self.run(robot, humans, mask, scan=scan)
        except Exception as exc:  # onnxruntime's own exception types
            message = " ".join(str(exc).split())[:300]
            raise NavigatorLoadError(f"{self.path}: the graph fails on a test observation ({type(exc).__name__}: "
                                     f"{message})") from None
        widths = {"h": self.hidden_size, "mean": 2, "log_std": 2, VALUE_OUTPUT: 1}
        arrays = {"h": output.h, "mean": output.mean, "log_std": output.log_std, VALUE_OUTPUT: output.value}
        for name in self.output_names:
            array = arrays[name]
            if array is None or array.shape != (2, widths[name]):
                shape = None if array is None else array.shape
                raise NavigatorLoadError(f"{self.path}: the graph's {name!r} has shape {shape} for 2 rows, "
                                         f"not (2, {widths[name]})")
            if not np.isfinite(array).all():
                raise NavigatorLoadError(f"{self.path}: the graph's {name!r} is not finite (NaN or inf) on a test "
                                         "observation: its weights are damaged; re-export it")

    @classmethod
    def load(cls, path: str | Path, threads: int = 1) -> ExportedPolicy:
        """Open a navigator file: read it (bounded), verify its checksum, validate its metadata and its graph.

        :raises NavigatorLoadError: missing, unreadable, not ONNX, foreign, corrupted, of another format version,
            with invalid or inconsistent metadata, or a graph that fails a test call (one line naming the file).
        """
        path = Path(path)
        data = _read_file(path)
        metadata = read_metadata(data, path)
        return cls(_session(data, path, threads), metadata, path)

    # ---------------------------------------------------------------------------------------------- raw graph

    def run(self, robot: np.ndarray, humans: np.ndarray, humans_mask: np.ndarray,
            keep: Sequence[np.ndarray] | None = None, scan: np.ndarray | None = None) -> NetworkOutput:
        """One graph call on N rows (``humans`` (N, L, 7) with L >= 1); ``keep``: the keep masks (None: ones);
        ``scan`` (N, beams) float32: the ranges, for a network that reads a scan (and only for one)."""
        rows, steps = humans.shape[:2]
        if keep is None:
            keep = [np.ones(self._keep_shape(spec, rows, steps), np.float32) for spec in self.dropout_inputs]
        if (scan is None) != (self.scan is None):
            raise ValueError("this network reads a range scan: pass scan" if scan is None else
                             "this network reads no range scan: scan must be None")
        ranges = () if scan is None else (scan,)
        # strict=False: masks beyond the graph's keep inputs (a caller's `keep`) are not fed
        feed = dict(zip(self.input_names, (robot, humans, humans_mask, *ranges, *keep), strict=False))
        outputs = self.session.run(None, feed)
        value = outputs[3] if len(outputs) > 3 else None
        return NetworkOutput(outputs[0], outputs[1], outputs[2], value)

    @staticmethod
    def _keep_shape(spec: Mapping[str, Any], rows: int, steps: int) -> tuple[int, ...]:
        return (rows, steps, spec["width"]) if spec["per_human"] else (rows, spec["width"])

    def keep_masks(self, rows: int, steps: int, any_human: bool, uniforms: Uniforms, p: float,
                   deterministic_rows: int = 0) -> list[np.ndarray]:
        """Keep masks ``[u >= p] / (1 - p)`` for ``rows`` MC rows (uniforms drawn in forward order), after
        ``deterministic_rows`` rows of ones. Without any human the LSTM-input layers draw nothing (as in torch)."""
        masks = []
        for index, spec in enumerate(self.dropout_inputs):
            mask = np.empty(self._keep_shape(spec, deterministic_rows + rows, steps), np.float32)
            mask[:deterministic_rows] = 1.0
            if any_human or not spec["per_human"]:
                drawn = _uniforms_of(uniforms, index, self._keep_shape(spec, rows, steps))
                keep_from_uniforms(drawn, p, mask[deterministic_rows:])
            else:
                mask[deterministic_rows:] = 1.0
            masks.append(mask)
        return masks

    def mc_batch(self, k: int, steps: int, any_human: bool, deterministic_rows: int = 1) -> MCBatch:
        """Preallocated buffers and an onnxruntime IO binding for repeated decisions of ONE observation with
        ``steps`` human rows: ``deterministic_rows`` rows without dropout, then ``k`` MC-dropout rows."""
        return MCBatch(self, k, steps, any_human, deterministic_rows)

    # ---------------------------------------------------------------------------------------------- policy API

    def trim(self, observation: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """``(robot, humans, mask, any_human)`` float32, batched, human rows trimmed to the longest real sequence
        (one zero row if there is no human at all: the graph then gives ``h = 0``, as torch does)."""
        robot = np.asarray(observation["robot"], dtype=np.float32).reshape(-1, 5)
        humans = np.asarray(observation["humans"], dtype=np.float32).reshape(len(robot), -1, 7)
        mask = np.asarray(observation["humans_mask"], dtype=np.float32).reshape(len(robot), -1)
        longest = round(float(mask.sum(axis=1).max())) if len(mask) else 0  # (round is monotonic)
        longest = min(longest, mask.shape[1])  # a mask of values above 1 must not ask for rows that do not exist
        steps = max(longest, 1)
        return robot, np.ascontiguousarray(humans[:, :steps]), np.ascontiguousarray(mask[:, :steps]), longest > 0

    def scan_of(self, observation: Mapping[str, np.ndarray]) -> np.ndarray | None:
        """The observation's ``scan`` as float32 (B, beams) for a network that reads a scan; None for one that
        does not (a ``scan`` in the observation is then not read)."""
        if self.scan is None:
            return None
        if SCAN_INPUT not in observation:
            raise ValueError(f"this network reads a range scan of {self.scan.beams} beams: the observation has no "
                             f"{SCAN_INPUT!r}")
        return np.ascontiguousarray(observation[SCAN_INPUT], dtype=np.float32).reshape(-1, self.scan.beams)

    def predict(self, observation: Mapping[str, np.ndarray], state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        """SB3-style deterministic actions (B, 2), clipped to [-1, 1] (a single observation gives (2,))."""
        if not deterministic:
            raise ValueError("the exported policy acts deterministically; use samples() for MC-dropout")
        single = np.asarray(observation["robot"]).ndim == 1
        output = self.run(*self.trim(observation)[:3], scan=self.scan_of(observation))
        actions = np.clip(output.mean, -1.0, 1.0)
        return (actions[0] if single else actions), state

    def samples(self, observation: Mapping[str, np.ndarray], uniforms: Uniforms, k: int | None = None,
                p: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """K MC-dropout samples ``(h, mu, log_std)`` of shapes (K, B, H), (K, B, 2), (K, B, 2), as
        ``MCDropoutEstimator.samples``: the batch repeated K times sample-major, one graph call."""
        k = self.k if k is None else int(k)
        p = self.p_test if p is None else float(p)
        robot, humans, mask, any_human = self.trim(observation)
        scan = self.scan_of(observation)
        batch, steps = humans.shape[:2]
        repeat = (k,) + (1,) * (humans.ndim - 1)
        output = self.run(np.tile(robot, (k, 1)), np.tile(humans, repeat), np.tile(mask, (k, 1)),
                          self.keep_masks(k * batch, steps, any_human, uniforms, p),
                          scan=None if scan is None else np.tile(scan, (k, 1)))
        return (output.h.reshape(k, batch, -1), output.mean.reshape(k, batch, -1),
                output.log_std.reshape(k, batch, -1))

    def summarise(self, h: np.ndarray, mu: np.ndarray, log_std: np.ndarray) -> Uncertainty:
        """The uncertainty of K samples (K, B, ...): eqs. (5), (6) and (8) with the exported feature range."""
        mean, u_ep, u_al, feature_variance = summarise_samples(mu, log_std, h)
        return Uncertainty(mean, u_ep, u_al, apply_feature_map(feature_variance, *self.feature_map))

    def uncertainty(self, observation: Mapping[str, np.ndarray], uniforms: Uniforms) -> Uncertainty:
        """MC-dropout uncertainty of a batch, `MCDropoutEstimator`'s numbers for the same uniforms."""
        return self.summarise(*self.samples(observation, uniforms))

    def __repr__(self) -> str:
        scan = "" if self.scan is None else f", scan_beams={self.scan.beams}"
        return (f"ExportedPolicy({str(self.path)!r}, K={self.k}, p_test={self.p_test}, "
                f"max_humans={self.max_humans}{scan})")


class MCBatch:
    """The graph call of one observation repeated on ``deterministic_rows + k`` rows, with every buffer
    preallocated and bound to the onnxruntime session once (`SafeNavigator`'s per-decision call).

    :meth:`run` copies the observation (already trimmed to ``steps`` human rows; with its scan for a network that
    reads one) into all rows, draws the
    MC-dropout uniforms (ONE draw for all layers when the stream has a ``fill(out)`` method, as `DropoutStream`
    has, which must draw what the per-layer calls would; else one ``uniforms(layer, shape)`` call per layer, in
    forward order, with the shapes :meth:`ExportedPolicy.keep_masks` asks for), turns them into keep masks
    ``[u >= p] / (1 - p)`` in one compiled pass and runs the graph into the bound outputs ``h``, ``mean``,
    ``log_std`` (overwritten by the next call: copy what must outlive it).
    """

    def __init__(self, network: ExportedPolicy, k: int, steps: int, any_human: bool, deterministic_rows: int) -> None:
        self.network, self.k, self.steps, self.any_human = network, int(k), int(steps), bool(any_human)
        rows = deterministic_rows + self.k
        self.deterministic_rows = deterministic_rows
        self.robot = np.zeros((rows, 5), np.float32)
        self.humans = np.zeros((rows, steps, 7), np.float32)
        self.humans_mask = np.zeros((rows, steps), np.float32)
        self.scan = None if network.scan is None else np.zeros((rows, network.scan.beams), np.float32)
        # The keep masks: views of one flat buffer (so that one kernel call writes every layer's), each layer's
        # deterministic rows left at 1. The layers that draw (the LSTM-input layers only when a human is there,
        # as in torch) take their uniforms from consecutive pieces of one flat buffer, in forward order.
        shapes = [network._keep_shape(spec, rows, steps) for spec in network.dropout_inputs]
        sizes = [int(np.prod(shape)) for shape in shapes]
        starts = np.cumsum([0, *(-(-size // 16) * 16 for size in sizes)])  # regions on 16-float boundaries
        self.keep_buffer = np.ones(int(starts[-1]), np.float32)
        self.keep = [self.keep_buffer[start:start + size].reshape(shape)
                     for start, size, shape in zip(starts, sizes, shapes, strict=False)]  # starts: one more, the end
        drawn = [index for index, spec in enumerate(network.dropout_inputs) if any_human or not spec["per_human"]]
        mc_sizes = [sizes[index] // rows * self.k for index in drawn]
        self.uniform_buffer = np.zeros(sum(mc_sizes), np.float32)
        offsets = np.cumsum([0, *mc_sizes])
        self.layers: list[tuple[int, tuple[int, ...], np.ndarray]] = []
        for index, start, stop in zip(drawn, offsets[:-1], offsets[1:], strict=True):
            shape = network._keep_shape(network.dropout_inputs[index], self.k, steps)
            self.layers.append((index, shape, self.uniform_buffer[start:stop].reshape(shape)))
        self.segments = np.array([[start, starts[index] + sizes[index] - (stop - start), stop - start]
                                  for index, start, stop in zip(drawn, offsets[:-1], offsets[1:], strict=True)],
                                 dtype=np.int64).reshape(-1, 3)
        self.h = np.zeros((rows, network.hidden_size), np.float32)
        self.mean = np.zeros((rows, 2), np.float32)
        self.log_std = np.zeros((rows, 2), np.float32)
        outputs = {"h": self.h, "mean": self.mean, "log_std": self.log_std}
        self.binding = network.session.io_binding()
        self._values: list[Any] = []  # the OrtValues share the arrays' memory: keep them alive with the binding
        ranges = () if self.scan is None else (self.scan,)
        inputs = (self.robot, self.humans, self.humans_mask, *ranges, *self.keep)
        for name, array in zip(network.input_names, inputs, strict=True):
            value = onnxruntime.OrtValue.ortvalue_from_numpy(array)
            self._values.append(value)
            self.binding.bind_ortvalue_input(name, value)
        for name, array in outputs.items():  # only these: onnxruntime need not fetch the critic's value
            value = onnxruntime.OrtValue.ortvalue_from_numpy(array)
            self._values.append(value)
            self.binding.bind_ortvalue_output(name, value)

    def run(self, robot: np.ndarray, humans: np.ndarray, humans_mask: np.ndarray, uniforms: Uniforms,
            p: float, scan: np.ndarray | None = None) -> None:
        """One graph call: ``robot`` (1, 5), ``humans`` (1, steps, 7), ``humans_mask`` (1, steps) and, for a
        network that reads one, ``scan`` (1, beams) in every row."""
        self.robot[...] = robot
        self.humans[...] = humans
        self.humans_mask[...] = humans_mask
        if self.scan is not None:
            if scan is None:
                raise ValueError("this network reads a range scan: pass scan")
            self.scan[...] = scan
        self.draw_masks(uniforms, p)
        self.network.session.run_with_iobinding(self.binding)

    def draw_masks(self, uniforms: Uniforms, p: float) -> None:
        """Draw the MC rows' uniforms and write their keep masks into the bound ``keep`` inputs."""
        if not self.layers:
            return
        fill = getattr(uniforms, "fill", None)
        if fill is not None:
            fill(self.uniform_buffer)
        else:
            for index, shape, drawn in self.layers:
                drawn[...] = _uniforms_of(uniforms, index, shape)
        _keep_kernel(self.uniform_buffer, np.float32(p), np.float32(1.0 / (1.0 - p)), self.keep_buffer,
                     self.segments)
