"""The runtime's per-decision fast path (docs/benchmarks.md) against its generic, unbuffered counterpart:
one uniform draw for all layers, the compiled keep-mask kernel, the preallocated IO-bound buffers and the
simplified exported graph must all give exactly what the per-layer, allocate-per-call path gives."""

from __future__ import annotations

import numpy as np
import onnx
import pytest

from socnav.runtime import DropoutStream, ExportedPolicy, SafeNavigator
from socnav.runtime.network import keep_from_uniforms
from socnav.safety import Thresholds

EAGER = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=2.5, beta1=0.5)
ROBOT = {"position": [0.0, -4.0], "velocity": [0.1, 0.4], "heading": 1.5, "goal": [0.0, 4.0], "v_pref": 1.0,
         "radius": 0.3}


def _crowd(rng: np.random.Generator, count: int) -> dict[str, np.ndarray]:
    return {"positions": rng.uniform(-3, 3, size=(count, 2)) + np.array([0.0, -3.0]),
            "velocities": rng.normal(size=(count, 2)), "radii": rng.uniform(0.2, 0.4, size=count)}


@pytest.mark.parametrize("shapes", [[(20, 3, 7), (20, 3, 64), (20, 64), (20, 128)], [(3, 1, 7), (5,), (1, 3)]])
def test_one_fill_is_the_per_layer_calls(shapes):
    """`DropoutStream.fill` of the concatenation draws what consecutive per-layer calls draw (odd sizes too)."""
    per_layer = DropoutStream(7)
    expected = np.concatenate([per_layer(index, shape).ravel() for index, shape in enumerate(shapes)])
    buffer = np.empty(expected.size, np.float32)
    one = DropoutStream(7)
    one.fill(buffer)
    np.testing.assert_array_equal(buffer, expected)
    # ... and both streams continue identically
    np.testing.assert_array_equal(one(0, (9,)), per_layer(0, (9,)))


def test_keep_from_uniforms():
    u = np.array([[0.0, 0.3, 0.29999998], [0.5, 0.99, 0.3000001]], np.float32)
    out = np.empty_like(u)
    keep_from_uniforms(u, 0.3, out)
    scale = np.float32(1 / 0.7)
    np.testing.assert_array_equal(out, np.where(u >= np.float32(0.3), scale, np.float32(0.0)))
    with pytest.raises(ValueError, match="C-contiguous"):
        keep_from_uniforms(u, 0.3, np.empty((3, 2), np.float64))
    with pytest.raises(ValueError, match="C-contiguous"):
        keep_from_uniforms(u[:, :2], 0.3, np.empty((4, 2), np.float32)[::2])


class _PerLayer:
    """A uniforms hook without `fill`: the navigator must draw layer by layer (the generic path)."""

    def __init__(self, seed: int) -> None:
        self.stream = DropoutStream(seed)

    def __call__(self, layer: int, shape: tuple[int, ...]) -> np.ndarray:
        return self.stream(layer, shape)


def test_batched_decisions_equal_the_generic_path(navigator_file):
    """Over crowds of 0 .. more-than-observed humans, the buffered fast path (one draw, IO binding) decides
    exactly as the per-layer hook path, and both equal the unbuffered `ExportedPolicy` calls."""
    fast = SafeNavigator.load(navigator_file, thresholds=EAGER, seed=4)
    slow = SafeNavigator.load(navigator_file, thresholds=EAGER, uniforms=_PerLayer(4))
    network = ExportedPolicy.load(navigator_file)
    reference_stream = DropoutStream(4)
    rng = np.random.default_rng(0)
    for count in (0, 1, 5, 3, 5, fast.max_humans + 4, 0, 2):
        crowd = _crowd(rng, count)
        a, b = fast.act(ROBOT, crowd), slow.act(ROBOT, crowd)
        np.testing.assert_array_equal(a.action, b.action)
        for field in ("mean_action", "u_ep", "u_al", "u_feat"):
            np.testing.assert_array_equal(getattr(a.uncertainty, field), getattr(b.uncertainty, field))
        assert a.windowed == b.windowed and a.fallback == b.fallback
        # the unbuffered path: deterministic action, and MC samples from the same stream
        expected_action, _ = network.predict(a.observation)
        if not a.fallback:
            np.testing.assert_allclose(a.action, expected_action[0], rtol=0, atol=1e-6)
        robot, humans, mask, any_human = network.trim(a.observation)
        keep = network.keep_masks(fast.k, humans.shape[1], any_human, reference_stream, network.p_test,
                                  deterministic_rows=1)
        rows = 1 + fast.k
        output = network.run(np.repeat(robot, rows, 0), np.repeat(humans, rows, 0), np.repeat(mask, rows, 0), keep)
        expected = network.summarise(output.h[1:, None], output.mean[1:, None], output.log_std[1:, None])
        for field in ("mean_action", "u_ep", "u_al", "u_feat"):
            np.testing.assert_allclose(getattr(a.uncertainty, field), getattr(expected, field), rtol=0, atol=1e-6)


def test_decisions_do_not_alias_the_buffers(navigator_file):
    """A Decision keeps its values after later decisions reuse the navigator's preallocated buffers."""
    navigator = SafeNavigator.load(navigator_file, seed=1)
    rng = np.random.default_rng(1)
    crowd = _crowd(rng, 4)
    first = navigator.act(ROBOT, crowd)
    saved = (first.action.copy(), first.uncertainty.mean_action.copy(), first.uncertainty.u_ep.copy(),
             {k: v.copy() for k, v in first.observation.items()})
    for _ in range(3):
        navigator.act(ROBOT, _crowd(rng, 4))
    np.testing.assert_array_equal(first.action, saved[0])
    np.testing.assert_array_equal(first.uncertainty.mean_action, saved[1])
    np.testing.assert_array_equal(first.uncertainty.u_ep, saved[2])
    for key, value in saved[3].items():
        np.testing.assert_array_equal(first.observation[key], value)


def test_a_bad_uniforms_hook_is_a_clear_error(navigator_file):
    navigator = SafeNavigator.load(navigator_file, uniforms=lambda layer, shape: np.zeros((1,), np.float32))
    with pytest.raises(ValueError, match="expected shape"):
        navigator.act(ROBOT, _crowd(np.random.default_rng(2), 2))


def test_exported_graph_is_lean(navigator_file):
    """The human encoder is exported as LSTM nodes fed the sequence lengths (their Y_h is h): no initial-state
    or one-hot selection subgraph, and no LSTM output computed for nothing."""
    graph = onnx.load(str(navigator_file)).graph
    lstms = [node for node in graph.node if node.op_type == "LSTM"]
    assert len(lstms) == 2
    for node in lstms:
        assert len(node.input) == 5 and node.input[4]  # X, W, R, B, sequence_lens; no initial_h / initial_c
    assert not lstms[-1].output[0]  # the top layer's Y sequence is not written
    assert all(not node.output[2] for node in lstms)  # nor any Y_c
    kinds = {node.op_type for node in graph.node}
    assert not kinds & {"ConstantOfShape", "Range", "Equal", "Shape"}
