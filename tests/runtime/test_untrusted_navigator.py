"""No NaN ever reaches a command, and a navigator file is validated like every other input.

- the file carries a sha256 checksum: a corrupted byte anywhere is a `NavigatorLoadError` at load (format 2; a
  version-1 file, which has none, is refused with a request to re-export it);
- its metadata is a strict, bounded schema, consistent with the graph: every violation is a `NavigatorLoadError`
  at load, never an error at the first `act` and never a silently disabled safety layer;
- `act` refuses text, bools, complex numbers, non-finite values and a v_pref above the env config's; when the
  network's output is not finite the command is the cautious controller's, or a stop, and the decision says so;
- `socnav export` refuses out-of-range settings in one line, a policy with NaN weights and non-finite outputs;
- `load_policy` checks complex weights for NaN too.

Tampered files are re-sealed (`seal`) where the test is about what lies behind the checksum.
"""

from __future__ import annotations

import copy
import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from socnav.runtime import (
    NON_FINITE_OBSERVATION,
    NON_FINITE_OUTPUT,
    STOPPED,
    ExportedPolicy,
    InputError,
    NavigatorLoadError,
    SafeNavigator,
)
from socnav.runtime.format import CHECKSUM_KEY, METADATA_KEY, metadata_entries, seal
from socnav.runtime.network import MCBatch
from socnav.sim.observation import robot_command

ROBOT = {"position": [0.0, -4.0], "velocity": [0.0, 0.5], "heading": 1.5, "goal": [0.0, 4.0], "v_pref": 1.0,
         "radius": 0.3}
HUMANS = {"positions": [[0.2, -2.5], [1.0, 0.0]], "velocities": [[0.0, -1.0], [-0.5, 0.0]], "radii": [0.3, 0.3]}


# ------------------------------------------------------------------------------------------------- file helpers

def _entry(key: str, value: bytes) -> bytes:
    """One ``metadata_props`` field (ModelProto field 14) written by hand: any bytes, valid UTF-8 or not."""
    def varint(number: int) -> bytes:
        out = bytearray()
        while True:
            out.append((number & 0x7F) | (0x80 if number > 0x7F else 0))
            number >>= 7
            if not number:
                return bytes(out)

    def string(field: int, data: bytes) -> bytes:
        return bytes([field << 3 | 2]) + varint(len(data)) + data

    body = string(1, key.encode()) + string(2, value)
    return bytes([14 << 3 | 2]) + varint(len(body)) + body


def _rewrite(source: Path, target: Path, metadata_text: bytes | None = None, edit_graph=None,
             checksum: bytes | None = b"0" * 64, sealed: bool = True) -> Path:
    """``source`` with its metadata text replaced (None: kept), its graph edited, and its checksum entry (None:
    left out) re-sealed; the entries are written by hand, so any bytes can be planted."""
    model = onnx.load(str(source))
    text = {entry.key: entry.value for entry in model.metadata_props}[METADATA_KEY].encode()
    del model.metadata_props[:]
    if edit_graph is not None:
        edit_graph(model.graph)
    data = model.SerializeToString() + _entry(METADATA_KEY, text if metadata_text is None else metadata_text)
    if checksum is not None:
        data += _entry(CHECKSUM_KEY, checksum)
    target.write_bytes(seal(data) if sealed and checksum is not None else data)
    return target


def _metadata(path: Path) -> dict:
    model = onnx.load(str(path))
    return json.loads({entry.key: entry.value for entry in model.metadata_props}[METADATA_KEY])


def _with_metadata(source: Path, target: Path, edit) -> Path:
    """``source`` with ``edit(metadata)`` applied to its metadata dict, re-sealed."""
    metadata = _metadata(source)
    edit(metadata)
    return _rewrite(source, target, json.dumps(metadata).encode())


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def edit(metadata):
        node = metadata
        for key in keys[:-1]:
            node = node[key]
        node[keys[-1]] = value
    return edit


def _drop(*keys):
    def edit(metadata):
        node = metadata
        for key in keys[:-1]:
            node = node[key]
        del node[keys[-1]]
    return edit


def _assert_refused(path: Path, *words: str) -> str:
    for load in (ExportedPolicy.load, SafeNavigator.load):
        with pytest.raises(NavigatorLoadError) as error:
            load(path)
        message = str(error.value)
        assert "\n" not in message, message
        for word in words:
            assert word in message, message
    return message


# ------------------------------------------------------------------------------------------------- the checksum

def test_every_single_byte_corruption_is_refused_at_load(navigator_file, tmp_path):
    """200 seeded single-byte corruptions, over the whole file and concentrated on its metadata and checksum: each
    is a NavigatorLoadError at load (the checksum covers every byte). Were one to load, it would still have to
    give finite commands; none does."""
    data = Path(navigator_file).read_bytes()
    entries = metadata_entries(data)
    rng = np.random.default_rng(2024)
    positions = [*rng.integers(0, len(data), 150), *rng.integers(*entries[METADATA_KEY], 30),
                 *rng.integers(*entries[CHECKSUM_KEY], 20)]
    loaded = []
    corrupted = tmp_path / "corrupted.onnx"
    for position in positions:
        damaged = bytearray(data)
        damaged[position] ^= int(rng.integers(1, 256))  # a different byte, never the same
        corrupted.write_bytes(bytes(damaged))
        try:
            navigator = SafeNavigator.load(corrupted, seed=0)
        except NavigatorLoadError as error:
            assert "\n" not in str(error)
            continue
        loaded.append(int(position))
        for _ in range(3):
            assert all(math.isfinite(value) for value in navigator.act(ROBOT, HUMANS).command)
    assert not loaded, f"corruptions at bytes {loaded} loaded"


def test_a_flipped_weight_bit_is_refused_naming_the_checksum(navigator_file, tmp_path):
    data = bytearray(Path(navigator_file).read_bytes())
    weights = onnx.load_from_string(bytes(data)).graph.initializer[0].raw_data
    data[bytes(data).index(weights) + 5] ^= 0x40  # one bit of a weight, far from the metadata
    (tmp_path / "flipped.onnx").write_bytes(bytes(data))
    _assert_refused(tmp_path / "flipped.onnx", "flipped.onnx", "corrupted", "checksum does not match")


def test_metadata_edited_without_resealing_is_refused(navigator_file, tmp_path):
    """The checksum covers the metadata: raising K (or anything else) by hand makes the file corrupted."""
    data = Path(navigator_file).read_bytes()
    old_checksum = data[slice(*metadata_entries(data)[CHECKSUM_KEY])]
    metadata = _metadata(navigator_file)
    metadata["mc_dropout"]["k"] = 50
    path = _rewrite(navigator_file, tmp_path / "edited.onnx", json.dumps(metadata).encode(), checksum=old_checksum,
                    sealed=False)
    _assert_refused(path, "checksum does not match")


def test_a_file_without_checksum_is_refused_with_re_export(navigator_file, tmp_path):
    _assert_refused(_rewrite(navigator_file, tmp_path / "bare.onnx", checksum=None), CHECKSUM_KEY, "re-export")
    _assert_refused(_rewrite(navigator_file, tmp_path / "short.onnx", checksum=b"abc", sealed=False), "malformed")
    _assert_refused(_rewrite(navigator_file, tmp_path / "upper.onnx", checksum=b"A" * 64, sealed=False), "malformed")


def test_a_version_1_file_is_refused_with_re_export(navigator_file, tmp_path):
    """Version 1 had no checksum: such a file is refused, saying why and what to do."""
    metadata = _metadata(navigator_file)
    metadata["version"] = 1
    path = _rewrite(navigator_file, tmp_path / "v1.onnx", json.dumps(metadata).encode(), checksum=None)
    message = _assert_refused(path, "version 1 is not supported", "allowed: 2", "checksum", "re-export")
    assert "socnav export" in message


def test_duplicated_metadata_entries_are_refused(navigator_file, tmp_path):
    data = Path(navigator_file).read_bytes() + _entry(METADATA_KEY, b"{}")
    (tmp_path / "twice.onnx").write_bytes(data)
    _assert_refused(tmp_path / "twice.onnx", "occurs twice")


# ------------------------------------------------------------------------------------------------- the metadata

BAD_METADATA = {
    "p_test 0 (no uncertainty)": (_set("mc_dropout", "p_test", 0.0), "mc_dropout.p_test"),
    "p_test 1": (_set("mc_dropout", "p_test", 1.0), "mc_dropout.p_test"),
    "p_test as text": (_set("mc_dropout", "p_test", "0.5"), "mc_dropout.p_test"),
    "k 1e9": (_set("mc_dropout", "k", 10**9), "mc_dropout.k"),
    "k 1": (_set("mc_dropout", "k", 1), "mc_dropout.k"),
    "k a float": (_set("mc_dropout", "k", 20.5), "mc_dropout.k"),
    "k a bool": (_set("mc_dropout", "k", True), "mc_dropout.k"),
    "window 1e12": (_set("safety", "window", 10**12), "safety.window"),
    "window 0": (_set("safety", "window", 0), "safety.window"),
    "max_humans 1e6": (_set("observation", "max_humans", 10**6), "observation.max_humans"),
    "max_humans not the env config's": (_set("observation", "max_humans", 12), "max_humans"),
    "huge lstm": (_set("policy", "lstm_hidden_size", 10**9), "policy.lstm_hidden_size"),
    "lstm size not the graph's": (_set("policy", "lstm_hidden_size", 32), "lstm_hidden_size=32"),
    "huge dropout width": (_set("dropout_inputs", 3, "width", 10**9), "dropout_inputs.3.width"),
    "dropout width not the graph's": (_set("dropout_inputs", 3, "width", 64), "keep_actor_0"),
    "dropout input renamed": (_set("dropout_inputs", 4, "name", "keep_other"), "do not match its metadata"),
    "no safety section": (_drop("safety"), "safety"),
    "no thresholds": (_drop("safety", "thresholds"), "safety.thresholds"),
    "thresholds a preset name": (_set("safety", "thresholds", "mc"), "safety.thresholds"),
    "thresholds a file path": (_set("safety", "thresholds", "/etc/passwd"), "safety.thresholds"),
    "NaN threshold": (_set("safety", "thresholds", "lambda_ep", float("nan")), "lambda_ep"),
    "unknown threshold": (_set("safety", "thresholds", "lambda_typo", 1.0), "lambda_typo"),
    "radius scale 0": (_set("safety", "radius_scale", 0.0), "safety.radius_scale"),
    "unknown top-level field": (_set("loader", "os.system"), "loader"),
    "unknown mc_dropout field": (_set("mc_dropout", "seed", 3), "mc_dropout.seed"),
    "NaN feature range": (_set("feature_range", "h_min", 0, float("nan")), "feature_range"),
    "short feature range": (_set("feature_range", "h_min", [0.0]), "feature_range"),
    "invalid env config": (_set("env_config", "time_step", -1.0), "env_config.time_step"),
    "env config a path": (_set("env_config", "/etc/passwd"), "env_config"),
    "value output dropped": (_set("outputs", ["h", "mean", "log_std"]), "do not match its metadata"),
    "outputs reordered": (_set("outputs", ["mean", "h", "log_std", "value"]), "outputs"),
    "other observation layout": (_set("observation", "robot", ["a", "b", "c", "d", "e"]), "observation"),
    "action box": (_set("action", "high", 2.0), "action"),
    "format": (_set("format", "other"), "format"),
    "not an object": (lambda metadata: metadata.clear(), "format"),
}


@pytest.mark.parametrize("case", list(BAD_METADATA))
def test_invalid_metadata_is_refused_at_load(navigator_file, tmp_path, case):
    edit, words = BAD_METADATA[case]
    _assert_refused(_with_metadata(navigator_file, tmp_path / "crafted.onnx", edit), words)


def test_metadata_json_is_bounded_and_utf8(navigator_file, tmp_path):
    _assert_refused(_rewrite(navigator_file, tmp_path / "deep.onnx", b"[" * 5000 + b"]" * 5000),
                    "nested too deeply")
    _assert_refused(_rewrite(navigator_file, tmp_path / "large.onnx", b'{"x": "' + b"a" * (2 << 20) + b'"}'),
                    "larger than")
    text = json.dumps(_metadata(navigator_file)).encode().replace(b'"mc"', b'"m\xff"')
    _assert_refused(_rewrite(navigator_file, tmp_path / "latin.onnx", text), "not UTF-8")
    _assert_refused(_rewrite(navigator_file, tmp_path / "not_json.onnx", b"{k: 20"), "not valid JSON")
    _assert_refused(_rewrite(navigator_file, tmp_path / "list.onnx", b"[1, 2]"), "format")


def test_graph_with_nan_weights_is_refused_at_load(navigator_file, tmp_path):
    """Checksummed but built with a NaN weight: the test call at load finds the non-finite output."""
    def poison(graph):
        for index, tensor in enumerate(graph.initializer):
            if tensor.name == "action_net.bias":
                values = numpy_helper.to_array(tensor).copy()
                values[0] = np.nan
                graph.initializer[index].CopyFrom(numpy_helper.from_array(values, tensor.name))
    _assert_refused(_rewrite(navigator_file, tmp_path / "nan.onnx", edit_graph=poison), "'mean' is not finite")


def test_untouched_file_still_loads_and_is_validated(navigator_file):
    network = ExportedPolicy.load(navigator_file)
    assert network.record.mc_dropout.k == 20 and network.record.safety.window == 4
    assert network.record.env_config.max_humans == network.max_humans


# ------------------------------------------------------------------------------------------------- act's inputs

@pytest.mark.parametrize("robot,humans,match", [
    ({**ROBOT, "v_pref": 5.0}, None, r"robot.v_pref must be > 0.0 and <= 1.0, got 5.0"),
    ({**ROBOT, "v_pref": 1.0000001}, None, r"robot.v_pref must be > 0.0 and <= 1.0"),
    ({**ROBOT, "heading": "1.5"}, None, r"robot.heading must be a finite number \(a real int or float\), got str"),
    ({**ROBOT, "heading": True}, None, r"robot.heading must be a finite number .* got bool"),
    ({**ROBOT, "heading": np.bool_(True)}, None, r"robot.heading must be a finite number"),
    ({**ROBOT, "heading": 1.5 + 0j}, None, r"robot.heading must be a finite number .* got complex"),
    ({**ROBOT, "radius": b"0.3"}, None, r"robot.radius must be a finite number"),
    ({**ROBOT, "v_pref": np.array([1.0])}, None, r"robot.v_pref must be a finite number"),
    ({**ROBOT, "heading": math.inf}, None, r"robot.heading must be a finite number"),
    ({**ROBOT, "position": [1 + 1j, 0.0]}, None, r"robot.position must be numeric .* complex numbers"),
    ({**ROBOT, "position": np.array([1.0, 2.0], dtype=np.complex64)}, None, r"robot.position .* complex"),
    ({**ROBOT, "goal": ["0", "4"]}, None, r"robot.goal must be numeric .* text"),
    ({**ROBOT, "velocity": [True, False]}, None, r"robot.velocity must be numeric .* booleans"),
    ({**ROBOT, "velocity": [0.0, -math.inf]}, None, r"robot.velocity must be finite"),
    ({**ROBOT, "position": [1e300, 0.0]}, None, r"non-finite observation"),
    (ROBOT, {**HUMANS, "positions": np.array([[0.2, -2.5], [1.0, 0.0]]) + 1j}, r"humans.positions .* complex"),
    (ROBOT, {**HUMANS, "velocities": [[0.0, math.nan], [0.0, 0.0]]}, r"humans.velocities is not finite in rows \[0\]"),
    (ROBOT, {**HUMANS, "radii": ["0.3", "0.3"]}, r"humans.radii must be numeric .* text"),
    (ROBOT, {**HUMANS, "positions": [[0.0, 1.0], [2.0]]}, r"humans.positions must be numeric"),
    ("robot", None, r"robot must be a RobotState or a mapping"),
    (ROBOT, [[0.0, 1.0]], r"humans must be a HumansState"),
])
def test_act_refuses_bad_input_naming_the_argument(navigator_file, robot, humans, match):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    with pytest.raises(InputError, match=match) as error:
        navigator.act(robot, humans)
    assert isinstance(error.value, ValueError) and "\n" not in str(error.value)


def test_act_accepts_numpy_scalars_and_ints(navigator_file):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    robot = {**ROBOT, "heading": np.float32(1.5), "v_pref": np.array(1.0), "radius": np.int64(0), "position": [0, -4]}
    decision = navigator.act(robot, {**HUMANS, "radii": np.array([0.3, 0.3], dtype=np.float32)})
    assert all(math.isfinite(value) for value in decision.command) and decision.fault is None


@pytest.mark.parametrize("k", [10**9, 1, 2.5, True])
def test_navigator_k_is_bounded(navigator_file, k):
    with pytest.raises(ValueError, match=r"k \(MC-dropout samples per decision\) must be an integer in \[2, 1000\]"):
        SafeNavigator.load(navigator_file, k=k)


# ------------------------------------------------------------------------------------------------- act's outputs

def _poison_outputs(monkeypatch, where: str) -> None:
    """Every graph call of the navigator writes NaN into one of its outputs (row 0's action, or an MC row's h)."""
    run = MCBatch.run

    def poisoned(self, *args, **kwargs):
        run(self, *args, **kwargs)
        if where == "action":
            self.mean[0, 1] = np.nan
        else:
            self.h[3, 5] = np.inf
    monkeypatch.setattr(MCBatch, "run", poisoned)


@pytest.mark.parametrize("where", ["action", "uncertainty samples"])
def test_non_finite_network_output_gives_the_cautious_command(navigator_file, monkeypatch, where):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    _poison_outputs(monkeypatch, where)
    decision = navigator.act(ROBOT, HUMANS)
    assert decision.fault == NON_FINITE_OUTPUT and decision.fallback
    action = navigator.cautious.predict(decision.observation)[0][0]
    expected = robot_command(action, ROBOT["v_pref"], navigator.config.max_heading_change)
    assert decision.command == pytest.approx(expected)
    assert all(math.isfinite(value) for value in decision.command)
    assert all(math.isnan(value) for value in decision.windowed.values())  # the window was not fed


def test_without_a_finite_fallback_the_robot_stops(navigator_file, monkeypatch):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    _poison_outputs(monkeypatch, "action")
    monkeypatch.setattr(navigator.cautious, "predict", lambda observation: (np.full((1, 2), np.nan), None))
    decision = navigator.act(ROBOT, HUMANS)
    assert decision.command == (0.0, 0.0) and not decision.fallback
    assert decision.fault == f"{NON_FINITE_OUTPUT}; {STOPPED}"
    np.testing.assert_array_equal(decision.action, [-1.0, 0.0])


def test_a_non_finite_step_does_not_poison_the_window(navigator_file, monkeypatch):
    """After a NaN step the next decisions are the policy's again, with finite windowed uncertainties (a NaN kept
    in the window would make every uncertainty condition False: the rule blind for `window` steps)."""
    navigator = SafeNavigator.load(navigator_file, seed=0, thresholds={"lambda_ep": 0.0, "lambda_feat": 0.0,
                                                                       "lambda_prox": 0.0, "beta1": 0.0})
    with monkeypatch.context() as patch:
        _poison_outputs(patch, "action")
        assert navigator.act(ROBOT, HUMANS).fault == NON_FINITE_OUTPUT
    decision = navigator.act(ROBOT, HUMANS)
    assert decision.fault is None and not decision.fallback
    assert all(math.isfinite(value) for value in decision.windowed.values())


def test_a_non_finite_observation_stops_the_robot(navigator_file):
    """`act_observation` does not check its input, and onnxruntime's LSTM can turn a NaN input into finite outputs:
    a non-finite observation must still never drive the robot (nor reach its command)."""
    navigator = SafeNavigator.load(navigator_file, seed=0)
    observation = navigator.act(ROBOT, HUMANS).observation
    for key, index in (("robot", (0, 0)), ("robot", (0, 3)), ("humans", (0, 0, 2)), ("humans_mask", (0, 0))):
        for value in (np.inf, np.nan):
            bad = {name: array.copy() for name, array in observation.items()}
            bad[key][index] = value
            decision = navigator.act_observation(bad)
            assert decision.command == (0.0, 0.0), (key, value, decision.command)
            assert decision.fault == f"{NON_FINITE_OBSERVATION}; {STOPPED}" and not decision.fallback


# ------------------------------------------------------------------------------------------------- export

def test_equivalence_check_treats_nan_as_failure():
    """`max` drops a NaN difference (``nan > x`` is False): the check must fail on it, in any output, either side."""
    from socnav.export import ExportError, largest_difference

    good = [np.zeros((2, 4), np.float32), np.zeros((2, 2), np.float32)]
    assert largest_difference(good, [a + 1e-7 for a in good], ["h", "mean"], "x") == pytest.approx(1e-7)
    for side in (0, 1):
        for value in (np.nan, np.inf):
            bad = [good[0], good[1].copy()]
            bad[1][1, 0] = value
            got, expected = (bad, good) if side == 0 else (good, bad)
            with pytest.raises(ExportError, match=r"'mean' output is not finite"):
                largest_difference(got, expected, ["h", "mean"], "rows=1")
    with pytest.raises(ExportError, match="shape"):
        largest_difference([good[0], good[1][:1]], good, ["h", "mean"], "rows=1")


def test_export_refuses_a_policy_with_nan_weights(pretrained_policy, tmp_path):
    from socnav.export import ExportError, export_onnx

    policy = copy.deepcopy(pretrained_policy)
    with __import__("torch").no_grad():
        policy.value_net.bias[0] = float("nan")  # only the critic's output is not finite: still refused
    with pytest.raises(ExportError, match=r"NaN or inf values \(in value_net.bias\)"):
        export_onnx(policy, tmp_path / "nan.onnx", with_value=True)
    assert not (tmp_path / "nan.onnx").exists()


@pytest.mark.parametrize("settings,match", [
    ({"k": 10**9}, r"k must be an integer in \[2, 1000\], got 1e\+09"),
    ({"k": 2.5}, r"k must be an integer in \[2, 1000\], got 2.5"),
    ({"k": True}, r"k must be an integer"),
    ({"window": 10**12}, r"window must be an integer in \[1, 10000\]"),
    ({"window": 0}, r"window must be an integer in \[1, 10000\], got 0"),
    ({"p_test": 0.0}, r"p_test must be a number in \(0, 1\), got 0 \(0 keeps every unit: .* estimate disabled"),
    ({"p_test": 1.0}, r"p_test must be a number in \(0, 1\), got 1"),
    ({"p_test": float("nan")}, r"p_test must be a number in \(0, 1\), got nan"),
    ({"p_test": "0.5"}, None),  # text is read as the command line gives it
])
def test_export_settings_are_bounded(pretrained_policy, tmp_path, monkeypatch, settings, match):
    import socnav.export as export

    if match is None:
        assert export.check_settings(**{"k": 20, "p_test": None, "window": 4, **settings}) == (20, 0.5, 4)
        return
    monkeypatch.setattr(export, "_load", lambda model: pytest.fail("the policy was loaded before the check"))
    with pytest.raises(export.ExportError, match=match):
        export.export_onnx(pretrained_policy, tmp_path / "x.onnx", **settings)
    assert not (tmp_path / "x.onnx").exists()


def test_export_refuses_a_stored_p_test_of_zero(pretrained_policy, tmp_path):
    from socnav.export import ExportError, export_onnx

    policy = copy.deepcopy(pretrained_policy)
    policy.p_test = 0.0
    with pytest.raises(ExportError, match=r"stored p_test is 0, outside \(0, 1\): 0 keeps every unit: .* disabled"):
        export_onnx(policy, tmp_path / "x.onnx")


class WorkStarted(Exception):
    """The command went on to load the policy: it should have refused its options first."""


@pytest.mark.parametrize("option,value,words", [
    ("--k", "1e9", "error: --k must be an integer in [2, 1000], got '1e9'"),
    ("--k", "1000000000", "error: --k must be an integer in [2, 1000], got 1e+09"),
    ("--k", "1", "error: --k must be an integer in [2, 1000], got 1"),
    ("--window", "1e12", "error: --window must be an integer in [1, 10000], got '1e12'"),
    ("--window", "-3", "error: --window must be an integer in [1, 10000], got -3"),
    ("--p-test", "0", "error: --p-test must be a number in (0, 1), got 0 (0 keeps every unit: the K samples would be "
                      "identical and the uncertainty estimate disabled)"),
    ("--p-test", "1.5", "error: --p-test must be a number in (0, 1), got 1.5"),
    ("--p-test", "nan", "error: --p-test must be a number in (0, 1), got nan"),
    ("--p-test", "half", "error: --p-test must be a number in (0, 1), got 'half'"),
])
def test_export_command_refuses_out_of_range_settings_in_one_line(monkeypatch, tmp_path, option, value, words):
    from typer.testing import CliRunner

    import socnav.cli.deploy
    from socnav.cli import app

    monkeypatch.setattr(socnav.cli.deploy, "load_learned_policy", lambda model: (_ for _ in ()).throw(WorkStarted()))
    result = CliRunner().invoke(app, ["export", "pretrained", "--out", str(tmp_path / "n.onnx"), option, value])
    assert result.exit_code == 2, (result.output, result.exception)
    assert result.output.strip().count("\n") == 0, result.output  # one line (these messages fit in 160 columns)
    assert words in result.output, result.output


def test_export_command_documents_the_format_bounds():
    """The ranges `socnav export --help` and docs/configuration.md show are the ones enforced."""
    import typer.main

    from socnav.cli import app
    from socnav.runtime.format import MAX_K, MAX_WINDOW

    params = {param.name: param for param in typer.main.get_command(app).commands["export"].params}
    assert (params["k"].min, params["k"].max) == (2, MAX_K)
    assert (params["window"].min, params["window"].max) == (1, MAX_WINDOW)


def test_export_command_passes_the_settings_on(monkeypatch, tmp_path):
    from typer.testing import CliRunner

    import socnav.cli.deploy
    import socnav.export
    from socnav.cli import app

    calls = []
    monkeypatch.setattr(socnav.cli.deploy, "load_learned_policy", lambda model: "policy")
    monkeypatch.setattr(socnav.export, "export_onnx", lambda *args, **kwargs: calls.append((args, kwargs)) or
                        tmp_path / "n.onnx")
    result = CliRunner().invoke(app, ["export", "pretrained", "--out", str(tmp_path / "n.onnx"), "--k", "7",
                                      "--p-test", "0.25", "--window", "3"])
    assert result.exit_code == 0, result.output
    (_, kwargs), = calls
    assert (kwargs["k"], kwargs["p_test"], kwargs["window"]) == (7, 0.25, 3)


# ------------------------------------------------------------------------------------------------- load_policy

def test_load_policy_checks_complex_weights_for_nan(tmp_path):
    """A complex tensor is checked for finiteness too (torch.isfinite of both parts), not skipped as 'not
    floating'; in a policy file it is refused (a PolicyLoadError, never loaded)."""
    import torch

    from socnav.rl.persistence import PolicyLoadError, entry_is_finite, load_policy, pretrained_path

    assert not entry_is_finite("w", torch.tensor([1 + 1j, complex(0.0, math.nan)]), {})
    assert not entry_is_finite("w", torch.tensor([complex(math.inf, 0.0)]), {})
    assert entry_is_finite("w", torch.tensor([1 + 1j]), {}) and entry_is_finite("n", torch.tensor([3, 4]), {})
    with zipfile.ZipFile(pretrained_path()) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    state = torch.load(io.BytesIO(members["policy.pt"]), weights_only=True)
    state["action_net.bias"] = torch.tensor([complex(math.nan, 0.0), 0j])
    buffer = io.BytesIO()
    torch.save(state, buffer)
    members["policy.pt"] = buffer.getvalue()
    crafted = tmp_path / "complex.zip"
    with zipfile.ZipFile(crafted, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    with pytest.raises(PolicyLoadError, match=r"action_net\.bias") as error:
        load_policy(crafted)
    assert "\n" not in str(error.value)
