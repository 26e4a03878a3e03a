"""The scan encoder's input option (`AlgoConfig.scan_encoding`): each beam as range / max range (the default) or as
nearness exp(-range / 1 m); values by hand, the option's validation, and that it reaches the features (its
round trip through saving, loading and export is in test_heading_frame.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch as th
from pydantic import ValidationError

import socnav
from socnav.rl.extractor import HumanLSTMExtractor, ScanEncoder
from socnav.rl.presets import resolve_config

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


def test_the_same_weights_reading_the_other_encoding_give_other_features():
    """The encoding reaches the features (its round trip through save, load and export: test_heading_frame.py)."""
    th.manual_seed(0)
    encoder = ScanEncoder(36, 8.0, 360.0, 0.0, encoding="nearness").eval()
    scan = th.rand(4, 36) * 8.0
    with th.no_grad():
        features = encoder(scan)
        encoder.encoding = "range"
        assert (encoder(scan) - features).abs().max() > 1e-2
