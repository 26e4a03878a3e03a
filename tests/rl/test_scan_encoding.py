"""The scan encoder's input option (`AlgoConfig.scan_encoding`): each beam as range / max range (the default) or as
nearness exp(-range / 1 m); values by hand, the option's validation, and the option carried through saving,
loading and the exported navigator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch as th
from pydantic import ValidationError

import socnav
from socnav.export import export_onnx
from socnav.rl import make_model
from socnav.rl.extractor import HumanLSTMExtractor, ScanEncoder
from socnav.rl.persistence import load_policy, save_policy
from socnav.rl.presets import resolve_config
from socnav.runtime import ExportedPolicy

DOORWAY = {"scenario": "doorway", "n_humans": 3, "scan": {"beams": 36}, "planner": {"observe": True}}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,), "n_steps": 32, "batch_size": 32,
        "n_epochs": 1, "scan_encoding": "nearness"}


def test_each_encoding_reads_the_beams_as_computed_by_hand():
    ranges = th.tensor([[0.0, 0.3, 0.5, 1.0, 8.0]])
    by_range = ScanEncoder(5, 8.0, 360.0, 0.0, encoding="range").normalise(ranges)
    np.testing.assert_allclose(by_range.numpy(), [[0.0, 0.0375, 0.0625, 0.125, 1.0]], rtol=1e-6)
    nearness = ScanEncoder(5, 8.0, 360.0, 0.0, encoding="nearness").normalise(ranges)
    np.testing.assert_allclose(nearness.numpy(), [[1.0, math.exp(-0.3), math.exp(-0.5), math.exp(-1.0),
                                                   math.exp(-8.0)]], rtol=1e-6)


def test_the_default_is_the_range_so_saved_policies_read_as_before():
    assert resolve_config("odv-ppo-drop", {}).scan_encoding == "range"
    space = socnav.make_vec_env(DOORWAY, n_envs=1).observation_space
    assert HumanLSTMExtractor(space).scan_encoder.encoding == "range"


def test_an_unknown_encoding_is_a_clear_error():
    with pytest.raises(ValidationError, match="scan_encoding"):
        resolve_config("odv-ppo-drop", {"scan_encoding": "log"})
    space = socnav.make_vec_env(DOORWAY, n_envs=1).observation_space
    with pytest.raises(ValueError, match=r"scan_encoding must be one of \['range', 'nearness'\], got 'log'"):
        HumanLSTMExtractor(space, scan_encoding="log")


def test_a_nearness_policy_trains_saves_loads_and_exports(tmp_path):
    """The option travels with the policy's config: the loaded policy and the exported navigator (the encoding is in
    the graph) act as the trained one; the same weights reading ranges give other scan features."""
    th.set_num_threads(1)
    env = socnav.make_vec_env(DOORWAY, n_envs=2)
    env.seed(0)
    model = make_model("odv-ppo-drop", env, seed=0, overrides=TINY)
    model.learn(64)
    assert model.policy.features_extractor.scan_encoder.encoding == "nearness"
    observations = env.reset()
    for _ in range(5):
        observations = env.step(model.predict(observations, deterministic=True)[0])[0]
    expected, _ = model.policy.predict(observations, deterministic=True)
    metadata = {"algo": "odv-ppo-drop", "algo_config": model.algo_config,
                "env_config": socnav.load_config(DOORWAY).model_dump(mode="json")}
    loaded = load_policy(save_policy(model.policy, tmp_path / "nearness.zip", metadata))
    np.testing.assert_allclose(loaded.predict(observations, deterministic=True)[0], expected, atol=1e-6)
    network = ExportedPolicy.load(export_onnx(loaded, tmp_path / "nearness.onnx", k=2, env_config=DOORWAY))
    np.testing.assert_allclose(network.predict(observations)[0], expected, atol=1e-4)
    encoder = loaded.features_extractor.scan_encoder.eval()
    scan = th.as_tensor(observations["scan"])
    with th.no_grad():
        features = encoder(scan)
        encoder.encoding = "range"  # the same weights reading the other input: other features
        assert (encoder(scan) - features).abs().max() > 1e-2
