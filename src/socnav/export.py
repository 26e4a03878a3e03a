"""Export a trained socnav policy to ONNX for the torch-free runtime (`socnav.runtime`, `socnav export`).
The dropout keep-masks are graph inputs, so K MC-dropout samples (and the deterministic pass) run as one call.

The graph (:class:`NavigatorGraph`) is the policy's forward pass written with explicit masks: the LSTM layers over
the human rows, the final hidden state read at the last real row (the LSTM is causal, so rows after it — padding —
never change it; no packing needed), the range-scan encoder of a policy that reads one, the actor MLP with its
dropout layers replaced by ``x * keep``, the mean and the ODV log-sigma heads (clamped), and optionally the critic.
See `socnav.runtime.format` for the file layout; a world with walls also stores them (the cautious fallback's map).
In the file, the LSTM layers are ONNX ``LSTM`` nodes fed each row's number of humans as ``sequence_lens`` (their
``Y_h`` is that last-real-row state), and LSTM outputs nothing reads are dropped: a small graph, since onnxruntime
pays a per-node cost on every call of the deployed navigator (see :func:`_encoder`).
Export uses torch's TorchScript-based ``torch.onnx.export(..., dynamo=False)``: in torch 2.13 the dynamo exporter
turns the LSTM's sequence length into a constant on every export after the first in a process, which would break
the dynamic number of humans. The file is sealed with its sha256 checksum, loaded back as the runtime loads it
(checksum, metadata schema, graph) and checked against the torch policy (finite outputs, within
:data:`EXPORT_TOLERANCE`) before it replaces ``out``.
"""

from __future__ import annotations

import io
import json
import logging
import numbers
import operator
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from pydantic import ValidationError
from torch import nn

from socnav.rl.extractor import to_heading_frame
from socnav.runtime.format import (
    CHECKSUM_KEY,
    FORMAT_NAME,
    FORMAT_VERSION,
    MAX_K,
    MAX_WINDOW,
    METADATA_KEY,
    OBSERVATION_INPUTS,
    OUTPUTS,
    ROUTE_VERSION,
    SCAN_INPUT,
    SCAN_KEEP_PREFIX,
    TRIGGER_VERSION,
    VALUE_OUTPUT,
    WALL_FREE_VERSION,
    NavigatorMetadata,
    metadata_message,
    seal,
)

__all__ = ["ExportError", "NavigatorGraph", "check_settings", "export_onnx"]

#: ONNX opset of the written graph (LSTM, Clip, ...: every op it uses exists since opset 14).
OPSET = 17
#: Largest |ONNX - torch| accepted by the check after export (float32 arithmetic in a different order).
EXPORT_TOLERANCE = 1e-4


class ExportError(ValueError):
    """The policy cannot be exported (unsupported network, missing metadata) or the export does not match it."""


#: What p_test = 0 would do, said wherever it is refused.
_P_TEST_ZERO = "0 keeps every unit: the K samples would be identical and the uncertainty estimate disabled"


def check_settings(k: Any, p_test: Any, window: Any,
                   names: Mapping[str, str] | None = None) -> tuple[int, float | None, int]:
    """``(k, p_test, window)`` checked against the bounds of the navigator format (those the runtime enforces at
    load: `socnav.runtime.format.NavigatorMetadata`), text converted as the command line gives it. ``p_test`` None
    stays None (the policy's own, checked once the policy is loaded).

    :param names: how the messages name the arguments (``socnav export``: ``--k``, ``--p-test``, ``--window``).
    :raises ExportError: one line naming the argument, the allowed range and the value given.
    """
    names = {"k": "k", "p_test": "p_test", "window": "window", **(names or {})}
    k = _integer(k, names["k"], 2, MAX_K)
    window = _integer(window, names["window"], 1, MAX_WINDOW)
    if p_test is not None:
        p_test = _probability(p_test, names["p_test"])
    return k, p_test, window


def _integer(value: Any, name: str, low: int, high: int) -> int:
    """An integer in [low, high] from an int or its text (no float: 1e9 or 2.5 are refused, not truncated)."""
    allowed = f"{name} must be an integer in [{low}, {high}]"
    try:
        if isinstance(value, bool):
            raise TypeError
        number = int(value.strip()) if isinstance(value, str) else operator.index(value)
    except (TypeError, ValueError):
        raise ExportError(f"{allowed}, got {value!r:.60}") from None
    if not low <= number <= high:
        raise ExportError(f"{allowed}, got {number:.3g}" if abs(number) > 10**6 else f"{allowed}, got {number}")
    return number


def _probability(value: Any, name: str) -> float:
    """A number in (0, 1) from a real number or its text."""
    try:
        if isinstance(value, bool) or not isinstance(value, (str, numbers.Real)):
            raise TypeError
        number = float(value.strip()) if isinstance(value, str) else float(value)
    except (TypeError, ValueError):
        raise ExportError(f"{name} must be a number in (0, 1), got {value!r:.60}") from None
    if not 0.0 < number < 1.0:  # NaN fails too
        hint = f" ({_P_TEST_ZERO})" if number == 0.0 else ""
        raise ExportError(f"{name} must be a number in (0, 1), got {number:g}{hint}")
    return number


class NavigatorGraph(nn.Module):
    """The policy network of an ``ODVActorCriticPolicy`` with its dropout layers driven by keep-mask inputs.

    ``forward(robot, humans, humans_mask[, scan], *keep) -> (h, mean, log_std[, value])``; ``scan`` (N, beams) only
    for a policy with a scan encoder; ``keep`` holds one mask per entry of ``policy.dropout_layers()`` (LSTM
    inputs (N, L, width), then ``h``, the scan encoder's and the actor layers' (N, width)).
    With all-ones masks it is the deterministic policy; with ``[u >= p] / (1 - p)`` masks it is the policy in
    ``mc_dropout(p)`` mode with those uniforms. The weights are the policy's own modules (shared, not copied).
    """

    def __init__(self, policy: Any, with_value: bool = False) -> None:
        super().__init__()
        extractor = policy.features_extractor
        self.lstm_layers = extractor.lstm_layers
        self.scan_encoder = getattr(extractor, "scan_encoder", None)
        self.heading_frame = getattr(extractor, "frame", "goal") == "heading"
        self.actor = policy.mlp_extractor.policy_net
        self.action_net = policy.action_net
        self.odv = bool(policy.odv)
        if self.odv:
            self.log_std_net = policy.log_std_net
            self.log_std_bounds = (float(policy.log_std_min), float(policy.log_std_max))
        else:
            self.log_std_parameter = policy.log_std  # not `log_std`: that name is the output
        self.with_value = with_value
        if with_value:
            self.critic = policy.mlp_extractor.value_net
            self.value_net = policy.value_net
        self.dropout_inputs = _dropout_inputs(policy)
        self.encoder = _encoder(list(self.lstm_layers))

    def forward(self, robot: th.Tensor, humans: th.Tensor, humans_mask: th.Tensor,
                *rest: th.Tensor) -> tuple[th.Tensor, ...]:
        scan, keep = (rest[0], rest[1:]) if self.scan_encoder is not None else (None, rest)
        n_lstm = len(self.lstm_layers)
        if self.heading_frame:
            robot, humans = to_heading_frame(robot, humans)
        h = self.encoder.apply(humans, humans_mask, *keep[:n_lstm])
        parts = [h * keep[n_lstm], robot]
        masks = iter(keep[n_lstm + 1:])  # the scan encoder's (if any), then the actor's
        if self.scan_encoder is not None:
            parts.append(_masked(self.scan_encoder.layers, self.scan_encoder.normalise(scan), masks))
        features = th.cat(parts, dim=1)
        latent = _masked(self.actor, features, masks)
        mean = self.action_net(latent)
        if self.odv:
            log_std = th.clamp(self.log_std_net(latent), *self.log_std_bounds)
        else:
            log_std = self.log_std_parameter.expand_as(mean)
        if not self.with_value:
            return h, mean, log_std
        return h, mean, log_std, self.value_net(self.critic(features))


def _masked(layers: nn.Sequential, x: th.Tensor, masks: Iterator[th.Tensor]) -> th.Tensor:
    """``layers`` applied to ``x`` with each dropout module replaced by ``x * keep``, the masks taken in order."""
    for module in layers:
        x = x * next(masks) if isinstance(module, nn.Dropout) else module(x)
    return x


def _encode(layers: list[nn.LSTM], humans: th.Tensor, humans_mask: th.Tensor,
            keep: tuple[th.Tensor, ...]) -> th.Tensor:
    """``h`` (N, H): the top LSTM layer's output at each row's last real human row (0 for a row without humans),
    each layer's input multiplied by its keep mask. The LSTM is causal, so padding rows after the last real one
    never change it."""
    x = humans
    for lstm, mask in zip(layers, keep, strict=True):
        x = lstm(x * mask)[0]  # (N, L, H)
    # h = x[b, n_b - 1]: a one-hot selection (exact: the other rows are multiplied by 0), zero where n_b = 0.
    count = th.round(humans_mask.sum(dim=1))
    steps = th.arange(x.shape[1], dtype=x.dtype, device=x.device)
    select = (steps[None, :] == th.clamp(count - 1.0, min=0.0)[:, None]).to(x.dtype)
    return (x * select[:, :, None]).sum(dim=1) * (count > 0.0).to(x.dtype)[:, None]


def _onnx_gates(weight: th.Tensor) -> th.Tensor:
    """torch's LSTM gate blocks (input, forget, cell, output) in ONNX's order (input, output, forget, cell)."""
    input_gate, forget_gate, cell_gate, output_gate = weight.detach().chunk(4, dim=0)
    return th.cat([input_gate, output_gate, forget_gate, cell_gate]).clone()


def _encoder(layers: list[nn.LSTM]) -> type[th.autograd.Function]:
    """The human encoder of the graph as an autograd Function: :func:`_encode` in torch, and in the ONNX graph
    one ``LSTM`` node per layer fed ``sequence_lens`` = each row's number of humans, whose ``Y_h`` output IS
    that state (an ONNX LSTM stops at the sequence length; length 0 leaves the zero initial state). onnxruntime
    then runs far fewer nodes per call than for the generic export of :func:`_encode` (no initial-state
    ``Shape`` / ``ConstantOfShape`` nodes, no one-hot selection); `export_onnx` checks the file against
    :func:`_encode` on rows with 0 .. L humans."""
    for lstm in layers:
        if lstm.num_layers != 1 or lstm.bidirectional or not lstm.batch_first or lstm.proj_size:
            raise ExportError("unsupported network: the LSTM layers must be single-layer, unidirectional, "
                              "batch-first and without projection")

    def weights(lstm: nn.LSTM) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        def gates(name: str) -> th.Tensor:
            return _onnx_gates(lstm.get_parameter(name))

        w, r = gates("weight_ih_l0")[None], gates("weight_hh_l0")[None]
        if lstm.bias:  # ONNX's B: [input biases | recurrence biases]
            b = th.cat([gates("bias_ih_l0"), gates("bias_hh_l0")])[None]
        else:
            b = th.zeros(1, 8 * lstm.hidden_size, dtype=w.dtype)
        return w, r, b

    class Encoder(th.autograd.Function):
        @staticmethod
        def forward(ctx: Any, humans: th.Tensor, humans_mask: th.Tensor, *keep: th.Tensor) -> th.Tensor:
            if th.jit.is_tracing():  # exporting: `symbolic` writes the graph, and tracing through the LSTM
                # modules' parameters in here fails; only the output's shape and type matter
                return humans.new_zeros((humans.shape[0], layers[-1].hidden_size))
            return _encode(layers, humans, humans_mask, keep)

        @staticmethod
        def symbolic(g: Any, humans: Any, humans_mask: Any, *keep: Any) -> Any:
            def constant(value: th.Tensor) -> Any:
                return g.op("Constant", value_t=value)

            axis_0, axis_1 = constant(th.tensor([0])), constant(th.tensor([1]))
            count = g.op("Round", g.op("ReduceSum", humans_mask, axis_1, keepdims_i=0))
            lengths = g.op("Cast", count, to_i=6)  # INT32, as sequence_lens requires
            x = g.op("Transpose", g.op("Mul", humans, keep[0]), perm_i=[1, 0, 2])  # time-major (L, N, F)
            y = state = None
            for index, lstm in enumerate(layers):
                if index:  # Y (L, 1, N, H) of the layer below, times this layer's (time-major) keep mask
                    x = g.op("Mul", g.op("Squeeze", y, axis_1), g.op("Transpose", keep[index], perm_i=[1, 0, 2]))
                y, state, _ = g.op("LSTM", x, *(constant(w) for w in weights(lstm)), lengths,
                                   hidden_size_i=lstm.hidden_size, outputs=3)
            return g.op("Squeeze", state, axis_0)  # Y_h (1, N, H) -> (N, H)

    return Encoder


def _dropout_inputs(policy: Any) -> list[dict[str, Any]]:
    """Name, shape kind and width of each keep-mask input, in the order of ``policy.dropout_layers()``."""
    extractor = policy.features_extractor
    encoder = getattr(extractor, "scan_encoder", None)
    scan_layers = [] if encoder is None else encoder.dropout_layers()
    layers = policy.dropout_layers()
    expected = [*extractor.input_dropouts, extractor.h_dropout, *scan_layers, *policy.mlp_extractor.dropout_layers()]
    if [id(layer) for layer in layers] != [id(layer) for layer in expected]:
        raise ExportError("unsupported network: dropout layers other than the LSTM inputs, h, the scan encoder's "
                          "and the actor's")
    inputs = []
    for index, lstm in enumerate(extractor.lstm_layers):
        inputs.append({"name": f"keep_lstm_input_{index}", "per_human": True, "width": int(lstm.input_size)})
    inputs.append({"name": "keep_h", "per_human": False, "width": int(extractor.lstm_hidden_size)})
    if encoder is not None:
        for index, width in enumerate(_scan_dropout_widths(encoder)):
            inputs.append({"name": f"{SCAN_KEEP_PREFIX}{index}", "per_human": False, "width": width})
    linear_widths = [m.out_features for m in policy.mlp_extractor.policy_net if isinstance(m, nn.Linear)]
    for index, width in enumerate(linear_widths):
        inputs.append({"name": f"keep_actor_{index}", "per_human": False, "width": int(width)})
    if len(inputs) != len(layers):
        raise ExportError("unsupported network: the actor must have one dropout layer per hidden layer")
    return inputs


def _scan_dropout_widths(encoder: Any) -> list[int]:
    """The input width of each dropout module of a `ScanEncoder`, found by walking its layers on one row of ranges
    (the dropout modules themselves are skipped: no random draw)."""
    widths = []
    with th.no_grad():
        x = th.zeros(1, encoder.beams, device=next(encoder.parameters()).device)
        for module in encoder.layers:
            if isinstance(module, nn.Dropout):
                widths.append(int(x.shape[1]))
            else:
                x = module(x)
    return widths


def _example_inputs(graph: NavigatorGraph, rows: int, steps: int, seed: int = 0) -> tuple[th.Tensor, ...]:
    """Random observation-shaped inputs (some rows with fewer or no humans, ranges in [0, max range]) and random
    keep masks."""
    generator = th.Generator().manual_seed(seed)
    robot = th.randn(rows, 5, generator=generator)
    humans = th.randn(rows, steps, 7, generator=generator)
    counts = th.arange(rows) % (steps + 1)
    mask = (th.arange(steps)[None, :] < counts[:, None]).float()
    humans = humans * mask[:, :, None]
    scan = []
    if graph.scan_encoder is not None:
        scan.append(th.rand(rows, graph.scan_encoder.beams, generator=generator) * graph.scan_encoder.max_range)
    keep = []
    for spec in graph.dropout_inputs:
        shape = (rows, steps, spec["width"]) if spec["per_human"] else (rows, spec["width"])
        keep.append((th.rand(shape, generator=generator) >= 0.5).float() * 2.0)
    return (robot, humans, mask, *scan, *keep)


def _load(model: Any) -> Any:
    """The policy of ``model``: a path / ``"pretrained"`` (loaded with `load_policy`), a policy or an SB3 model."""
    if isinstance(model, (str, Path)):
        from socnav.rl.persistence import load_policy

        return load_policy(model)
    policy = getattr(model, "policy", model)
    if not hasattr(policy, "features_extractor") or not hasattr(policy, "dropout_layers"):
        raise ExportError(f"expected a socnav policy file or an ODVActorCriticPolicy, got {type(model).__name__}")
    return policy


def _metadata(policy: Any, graph: NavigatorGraph, env_config: Any, thresholds: Any, thresholds_source: str,
              k: int, p_test: float, window: int) -> dict[str, Any]:
    from socnav import __version__
    from socnav.envs.spaces import ACTION_NAMES, HUMAN_FEATURE_NAMES, ROBOT_FEATURE_NAMES
    from socnav.safety.cautious import CAUTIOUS_RADIUS_SCALE

    h_min, h_max = (t.detach().cpu().double().numpy().tolist() for t in policy.feature_range)
    header = getattr(policy, "socnav_metadata", {})
    walls = _world_walls(env_config)
    # A world with walls or a scan needs format 3; any other navigator stays a version-2 file, byte for byte.
    version = WALL_FREE_VERSION if walls is None and env_config.scan is None else FORMAT_VERSION
    # The walls travel as polygons: a map file's path (env_config.map) would not exist on the robot.
    stored_config = env_config.model_copy(update={"map": None}) if env_config.map is not None else env_config
    return {
        "format": FORMAT_NAME,
        "version": version,
        "socnav_version": __version__,
        "observation": {
            "robot": list(ROBOT_FEATURE_NAMES),
            "human": list(HUMAN_FEATURE_NAMES),
            "max_humans": int(env_config.max_humans),
            "layout": "robot-centric, x-axis towards the goal; real human rows first, sorted farthest to closest "
                      "(the closest is the last real row); zero padding; humans_mask 1 on real rows",
        },
        "action": {
            "names": list(ACTION_NAMES),
            "low": -1.0,
            "high": 1.0,
            "command": "v = v_pref (a0 + 1) / 2, dtheta = max_heading_change * a1",
            "max_heading_change": float(env_config.max_heading_change),
            "time_step": float(env_config.time_step),
        },
        "env_config": stored_config.model_dump(mode="json"),
        "policy": {
            "algo": header.get("algo"),
            "timesteps": header.get("timesteps"),
            "seed": header.get("seed"),
            "odv": bool(policy.odv),
            "dropout_p": float(policy.dropout_p),
            "lstm_hidden_size": int(policy.features_extractor.lstm_hidden_size),
        },
        "mc_dropout": {"k": int(k), "p_test": float(p_test)},
        "dropout_inputs": graph.dropout_inputs,
        "outputs": [*OUTPUTS, *([VALUE_OUTPUT] if graph.with_value else [])],
        "feature_range": {"h_min": h_min, "h_max": h_max},
        "safety": {
            "thresholds": thresholds.model_dump(),
            "source": thresholds_source,
            "window": int(window),
            "radius_scale": CAUTIOUS_RADIUS_SCALE,
        },
        **({} if walls is None else {"walls": walls}),
    }


def _world_walls(env_config: Any) -> list[list[list[float]]] | None:
    """The polygons of the world's walls (its scenario's map, ``obstacles``, the ``map`` file's) as JSON lists, in
    the map frame and RVO2's orientation (`socnav.sim.walls.world_polygons`); None in a world without walls."""
    from socnav.sim.scenarios import get_scenario
    from socnav.sim.walls import world_polygons

    polygons = world_polygons(env_config, get_scenario(env_config.scenario))
    return [polygon.tolist() for polygon in polygons] if polygons else None


def export_onnx(
    model: Any,
    out: str | Path,
    thresholds: Any = "mc",
    k: int = 20,
    p_test: float | None = None,
    window: int = 4,
    with_value: bool = False,
    env_config: Any = None,
) -> Path:
    """Write ``model``'s policy network and everything the runtime needs as one ONNX file (atomically).

    :param model: a policy file (``socnav train``'s ``model.zip``), ``"pretrained"``, an ``ODVActorCriticPolicy``
        or an SB3 model holding one.
    :param out: the ``.onnx`` file to write.
    :param thresholds: safety thresholds: a preset name (``mc``, ``ensemble``), a ``socnav calibrate`` file, a
        mapping or a :class:`~socnav.safety.Thresholds`.
    :param k: MC-dropout samples K the runtime draws per decision (2 ... :data:`~socnav.runtime.format.MAX_K`).
    :param p_test: MC-dropout probability in (0, 1) (None: the policy's stored ``p_test``); 0 is refused: it
        would disable the uncertainty estimate.
    :param window: uncertainty window in steps (paper: 4; 1 ... :data:`~socnav.runtime.format.MAX_WINDOW`).
    :param with_value: also export the critic (output ``value``).
    :param env_config: the env config the policy acts in (None: the one stored in the policy file).
    :raises ExportError: an unsupported network, non-finite weights, a missing env config, bad arguments, metadata
        the runtime would refuse, a written file that does not load, or an exported graph whose outputs are not
        finite or differ from the torch policy's by more than :data:`EXPORT_TOLERANCE`.
    :raises socnav.rl.persistence.PolicyLoadError: an unreadable policy file.
    :raises socnav.safety.ThresholdsError: invalid thresholds.
    """
    from socnav.safety.triggers import TriggerSpec, load_safety

    k, p_test, window = check_settings(k, p_test, window)  # before the policy loads: cheap checks first
    policy = _load(model)
    if p_test is None:
        p_test = _stored_p_test(policy)
    env_config = _policy_env_config(policy, env_config)
    source = str(thresholds) if isinstance(thresholds, (str, Path)) else "given"
    decision = load_safety(thresholds)
    trigger = _trigger_record(decision) if isinstance(decision, TriggerSpec) else None
    thresholds = decision if trigger is None else _rule_beside(decision)

    graph = NavigatorGraph(policy, with_value=with_value)
    for name, parameter in graph.named_parameters():  # a NaN weight would give NaN commands on the robot
        if not bool(th.isfinite(parameter).all()):
            raise ExportError(f"the policy's weights hold NaN or inf values (in {name}): it cannot be exported")
    metadata = _metadata(policy, graph, env_config, thresholds, source, k, p_test, window)
    if trigger is not None:  # version 4: older socnav versions refuse it instead of deciding with the rule
        metadata["safety"]["trigger"] = trigger
        metadata["version"] = TRIGGER_VERSION
    if env_config.planner.observe and "walls" in metadata:  # version 5: older ones would not plan its route
        metadata["version"] = ROUTE_VERSION
    try:  # the runtime's schema: what it would refuse at load is refused here, before anything is written
        NavigatorMetadata.model_validate(metadata)
    except ValidationError as exc:
        raise ExportError(f"the navigator metadata would be invalid: {metadata_message(exc)}") from None
    return _write_navigator(graph, metadata, Path(out), env_config.max_humans)


def _trigger_record(spec: Any) -> dict[str, Any]:
    """The metadata record of a score trigger (`socnav.runtime.format.TriggerRecord`): its spec without the file path,
    a risk model's ``.npz`` embedded as base64 (checked as it is read)."""
    import base64

    from socnav.safety.risk_model import read_risk_model_bytes, risk_model_from_bytes

    if spec.threshold == float("inf"):
        raise ExportError(f"trigger {spec.trigger!r} has threshold inf: it never fires; calibrate it first")
    record = {"trigger": spec.trigger, "params": dict(spec.params), "threshold": float(spec.threshold),
              "sensing": spec.sensing, "hold_steps": int(spec.hold_steps)}
    if spec.model is not None:
        raw = read_risk_model_bytes(spec.model)
        risk_model_from_bytes(raw, f"risk-model file {spec.model}")
        record["risk_model"] = base64.b64encode(raw).decode("ascii")
    return record


def _rule_beside(spec: Any) -> Any:
    """The rule's thresholds a trigger navigator carries for the conditions it reports (the paper's MC-dropout
    preset, read as the trigger senses)."""
    from socnav.safety.rule import Thresholds

    return Thresholds.preset("mc", sensing=spec.sensing)


def _stored_p_test(policy: Any) -> float:
    """The MC-dropout p the policy file stores, refused outside (0, 1)."""
    p_test = float(policy.p_test)
    if not 0.0 < p_test < 1.0:
        hint = f": {_P_TEST_ZERO}" if p_test == 0.0 else ""
        raise ExportError(f"the policy's stored p_test is {p_test:g}, outside (0, 1){hint}; pass p_test "
                          "(socnav export --p-test) in (0, 1)")
    return p_test


def _policy_env_config(policy: Any, env_config: Any) -> Any:
    """`env_config` (None: the one stored in the policy file) as an `EnvConfig`, checked against what the policy
    observes: its max_humans and its range scan."""
    from socnav.config import load_config

    if env_config is None:
        stored = getattr(policy, "socnav_metadata", {}).get("env_config")
        if stored is None:
            raise ExportError("the policy carries no env config (not loaded from a policy file): pass env_config")
        env_config = stored
    env_config = load_config(env_config)
    observed = int(policy.observation_space["humans"].shape[0])
    if observed != env_config.max_humans:
        raise ExportError(f"the policy observes max_humans={observed} but the env config has "
                          f"max_humans={env_config.max_humans}")
    _check_scan(policy, env_config)
    return env_config


def _write_navigator(graph: NavigatorGraph, metadata: dict[str, Any], path: Path, max_humans: int) -> Path:
    """Trace `graph` (in eval mode, restored after) to ONNX with dynamic rows and human rows, attach `metadata`,
    seal the file with its checksum and write it to `path` atomically once `_check` accepts it."""
    import onnx

    from socnav.io import atomic_path

    output_names = [*OUTPUTS, *([VALUE_OUTPUT] if graph.with_value else [])]
    scan_input = [] if graph.scan_encoder is None else [SCAN_INPUT]
    input_names = [*OBSERVATION_INPUTS, *scan_input, *(spec["name"] for spec in graph.dropout_inputs)]
    # Rows and human rows are dynamic: K samples run as one call and the runtime trims the padding rows.
    dynamic = {name: {0: "rows"} for name in input_names + output_names}
    for name in ("humans", "humans_mask", *(spec["name"] for spec in graph.dropout_inputs if spec["per_human"])):
        dynamic[name] = {0: "rows", 1: "human_rows"}
    modes = [(module, module.training) for module in graph.modules()]
    graph.train(False)
    try:
        with th.no_grad(), _quiet_exporter():
            buffer = io.BytesIO()
            # torch annotates `f` as a path, but its TorchScript exporter (dynamo=False) writes file objects too
            th.onnx.export(graph, _example_inputs(graph, 3, 2), buffer,  # type: ignore[arg-type]
                           input_names=input_names, output_names=output_names, dynamic_axes=dynamic,
                           opset_version=OPSET, dynamo=False)
            proto = onnx.load_from_string(buffer.getvalue())
            _drop_unused_outputs(proto)
            proto.metadata_props.add(key=METADATA_KEY, value=json.dumps(metadata))
            proto.metadata_props.add(key=CHECKSUM_KEY, value="0" * 64)  # filled in by `seal`
            data = seal(proto.SerializeToString())
            with atomic_path(path) as temporary:
                temporary.write_bytes(data)
                _check(graph, temporary, input_names, output_names, max_humans)
    finally:
        for module, mode in modes:
            module.training = mode
    return path


def _check_scan(policy: Any, env_config: Any) -> None:
    """The policy reads a scan exactly when the env config has one, of the same beams, range and field of view."""
    encoder = getattr(policy.features_extractor, "scan_encoder", None)
    scan = env_config.scan
    if encoder is None or scan is None:
        if encoder is not None:
            raise ExportError("the policy reads a range scan but the env config has none (scan: null): export it "
                              "with the env config it was trained in")
        if scan is not None:
            raise ExportError(f"the policy reads no range scan but the env config has one (scan: "
                              f"{scan.model_dump()}): export it with the env config it was trained in")
        return
    trained = (encoder.beams, encoder.max_range, encoder.fov)
    if trained != (scan.beams, scan.range, scan.fov):
        raise ExportError(f"the policy reads a scan of (beams, range, fov) = {trained} but the env config's scan is "
                          f"{(scan.beams, scan.range, scan.fov)}")


def _drop_unused_outputs(proto: Any) -> None:
    """Blank the optional LSTM outputs that nothing reads (the top layer's sequence ``Y``, every ``Y_c``), so
    that onnxruntime does not write them on every call."""
    graph = proto.graph
    read = {name for node in graph.node for name in node.input} | {output.name for output in graph.output}
    for node in graph.node:
        if node.op_type == "LSTM":
            for index, name in enumerate(node.output):
                if name and name not in read:
                    node.output[index] = ""


@contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the exporter's warnings and log lines: torch internals (deprecations, axis renaming, optional
    torchvision ops), nothing a user can act on."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.setLevel(level)


def _check(graph: NavigatorGraph, path: Path, input_names: list[str], output_names: list[str],
           max_humans: int) -> None:
    """Load the written file as the runtime will (checksum, metadata, graph) and run it on random inputs; raise
    :class:`ExportError` unless it loads and matches the torch graph."""
    from socnav.runtime.network import ExportedPolicy, NavigatorLoadError

    try:
        session = ExportedPolicy.load(path).session
    except NavigatorLoadError as exc:
        raise ExportError(f"the written navigator does not load: {exc}") from None
    for rows, steps in ((1, 1), (7, max_humans)):
        inputs = _example_inputs(graph, rows, steps, seed=rows)
        expected = [tensor.numpy() for tensor in graph(*inputs)]
        got = session.run(None, {name: value.numpy() for name, value in zip(input_names, inputs, strict=True)})
        error = largest_difference(got, expected, output_names, f"rows={rows}, human rows={steps}")
        if error > EXPORT_TOLERANCE:
            raise ExportError(f"the exported graph differs from the torch policy by {error:.2e} "
                              f"(rows={rows}, human rows={steps}); tolerance {EXPORT_TOLERANCE:g}")


def largest_difference(got: Sequence[np.ndarray], expected: Sequence[np.ndarray], names: Sequence[str],
                        where: str) -> float:
    """The largest |ONNX - torch| over all outputs. A NaN / inf output (either side) or a missing or misshapen one
    is an :class:`ExportError`, never a number: ``max`` would silently drop a NaN difference (``nan > x`` is
    False), so the outputs are checked for finiteness before any difference is taken."""
    if not len(got) == len(expected) == len(names):
        raise ExportError(f"the exported graph gives {len(got)} outputs, the torch policy {len(expected)} "
                          f"({where})")
    largest = 0.0
    for name, onnx_value, torch_value in zip(names, got, expected, strict=True):
        onnx_value, torch_value = np.asarray(onnx_value), np.asarray(torch_value)
        if onnx_value.shape != torch_value.shape:
            raise ExportError(f"the exported graph's {name!r} has shape {onnx_value.shape}, the torch policy's "
                              f"{torch_value.shape} ({where})")
        for side, value in (("exported graph", onnx_value), ("torch policy", torch_value)):
            if not np.isfinite(value).all():
                raise ExportError(f"the {side}'s {name!r} output is not finite (NaN or inf) on the check inputs "
                                  f"({where}): the export does not give usable commands")
        if onnx_value.size:
            difference = float(np.abs(onnx_value.astype(np.float64) - torch_value.astype(np.float64)).max())
            largest = max(largest, difference)  # both finite (float64: no overflow), so no NaN can be dropped
    return largest
