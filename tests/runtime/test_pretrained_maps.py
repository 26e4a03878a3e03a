"""The shipped map policy (``pretrained-maps``, socnav/data/README.md): it loads by name with the observation it was
trained with (route, scan) and a tracked feature range, and its exported navigator with the safety layer shipped
beside it decides in the doorway as the torch safety layer does, step for step."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import socnav
from socnav.cli import app
from socnav.cli.workflows.demo import MAP_POLICY, MAP_POLICY_LAYER, comparison_file
from socnav.rl.persistence import PolicyLoadError, pretrained_path
from socnav.runtime import SafeNavigator
from socnav.safety import SafePolicy

TOLERANCE = 1e-5


@pytest.fixture(scope="module")
def map_policy():
    torch.set_num_threads(1)
    return socnav.load_policy(MAP_POLICY)


def test_the_map_policy_loads_by_name_and_observes_its_route_and_the_scan(map_policy):
    world = map_policy.socnav_metadata["env_config"]
    assert world["planner"]["observe"] is True and world["scan"]["beams"] == 72 and world["scenario"] == "doorway"
    assert map_policy.features_extractor.scan_encoder.encoding == "nearness"
    h_min, h_max = (bound.numpy() for bound in map_policy.feature_range)
    assert np.isfinite(h_min).all() and np.isfinite(h_max).all()  # feature uncertainty is computed
    assert pretrained_path(MAP_POLICY) != pretrained_path()


def test_an_unknown_shipped_name_is_a_clear_error():
    with pytest.raises(PolicyLoadError, match="no shipped policy named 'pretrained-map'; the shipped ones are "
                                              "pretrained, pretrained-maps"):
        pretrained_path("pretrained-map")
    with pytest.raises(PolicyLoadError, match="no policy file at pretrained-mapz; did you mean the shipped policy "
                                              "'pretrained-maps'"):
        socnav.load_policy("pretrained-mapz")


def test_the_exported_map_navigator_decides_as_its_safety_layer(map_policy, tmp_path, navigator_steps):
    """`socnav export pretrained-maps --thresholds <its layer>`: driving the doorway from the world's state arrays
    and the scan, the navigator's every decision (the fallback's hand-over, the wall stop, the action) is the torch
    `SafePolicy`'s with the same trigger file."""
    from socnav.envs.env import SocialNavEnv

    layer = comparison_file(MAP_POLICY_LAYER)
    out = tmp_path / "maps.onnx"
    result = CliRunner().invoke(app, ["export", MAP_POLICY, "--thresholds", str(layer), "--out", str(out)])
    assert result.exit_code == 0, result.output
    config = socnav.load_config(map_policy.socnav_metadata["env_config"])
    reference = SafePolicy(map_policy, None, str(layer), config, n_envs=1)
    navigator = SafeNavigator.load(out, seed=0)
    steps = fallbacks = 0
    for observation, _, decision in navigator_steps(SocialNavEnv(config), navigator, [0, 1, 2], reference.reset):
        expected, _ = reference.predict(observation)
        assert decision.fallback == bool(reference.last_fallback[0])
        np.testing.assert_allclose(decision.action, expected, rtol=0, atol=TOLERANCE)
        steps += 1
        fallbacks += decision.fallback
    assert 0 < fallbacks < steps  # both the policy and the fallback were compared
