"""The exported navigator against the torch policy: deterministic actions, MC-dropout samples and uncertainties.
Both sides see the same observations of every scenario and, for MC-dropout, the same dropout uniforms."""

from __future__ import annotations

import json

import numpy as np
import pytest

from socnav.runtime import DropoutStream, ExportedPolicy, SafeNavigator
from socnav.safety import Thresholds

TOLERANCE = 1e-5
CHUNK = 128  # observations per MC call (K * CHUNK rows)


def _chunks(observations: dict[str, np.ndarray]):
    for start in range(0, len(observations["robot"]), CHUNK):
        yield {key: value[start:start + CHUNK] for key, value in observations.items()}


def test_observations_cover_every_case(observations):
    counts = observations["humans_mask"].sum(axis=1)
    assert len(counts) >= 1000
    assert {0, 1, 5, 10} <= set(counts.astype(int).tolist())


def test_deterministic_action_matches_torch(pretrained_policy, navigator_file, observations):
    network = ExportedPolicy.load(navigator_file)
    expected, _ = pretrained_policy.predict(observations, deterministic=True)
    actions, _ = network.predict(observations)
    assert actions.shape == expected.shape == (len(observations["robot"]), 2)
    np.testing.assert_allclose(actions, expected, rtol=0, atol=TOLERANCE)
    # One observation at a time (the robot's case: human rows trimmed to its own count) gives the same actions.
    for index in range(0, len(actions), 97):
        single = {key: value[index] for key, value in observations.items()}
        np.testing.assert_allclose(network.predict(single)[0], expected[index], rtol=0, atol=TOLERANCE)


def test_value_head_matches_torch(pretrained_policy, navigator_file, observations):
    import torch

    network = ExportedPolicy.load(navigator_file)
    batch = {key: value[:256] for key, value in observations.items()}
    with torch.no_grad():
        expected = pretrained_policy.predict_values(pretrained_policy.obs_to_tensor(batch)[0]).numpy()
    output = network.run(*network.trim(batch)[:3])
    np.testing.assert_allclose(output.value, expected, rtol=0, atol=TOLERANCE)


def test_mc_dropout_samples_and_uncertainty_match_torch(pretrained_policy, navigator_file, observations):
    from socnav.uncertainty import MCDropoutEstimator

    network = ExportedPolicy.load(navigator_file)
    torch_stream, onnx_stream = DropoutStream(11), DropoutStream(11)
    estimator = MCDropoutEstimator(pretrained_policy, k=20, uniforms=torch_stream)
    spreads = []
    for batch in _chunks(observations):
        expected = [t.detach().numpy() for t in estimator.samples(batch)]
        got = network.samples(batch, onnx_stream)
        for name, g, e in zip(("h", "mu", "log_std"), got, expected, strict=True):
            assert g.shape == e.shape, name
            np.testing.assert_allclose(g, e, rtol=0, atol=TOLERANCE, err_msg=name)
        expected_u, got_u = estimator(batch), network.uncertainty(batch, onnx_stream)
        for field in ("mean_action", "u_ep", "u_al", "u_feat"):
            np.testing.assert_allclose(getattr(got_u, field), getattr(expected_u, field), rtol=0, atol=TOLERANCE,
                                       err_msg=field)
        spreads.append(expected_u.u_ep.max(axis=1))
    # The masks really act: the samples disagree (u_ep > 0) wherever the policy sees anything at all.
    assert (np.concatenate(spreads) > 0).mean() > 0.99


def test_uniform_hook_feeds_the_masks(pretrained_policy, observations):
    """The torch estimator's `uniforms` hook is what sets its masks: same stream, same samples; other, different."""
    from socnav.uncertainty import MCDropoutEstimator

    batch = {key: value[:32] for key, value in observations.items()}
    first = MCDropoutEstimator(pretrained_policy, k=5, uniforms=DropoutStream(1)).samples(batch)[1].numpy()
    again = MCDropoutEstimator(pretrained_policy, k=5, uniforms=DropoutStream(1)).samples(batch)[1].numpy()
    other = MCDropoutEstimator(pretrained_policy, k=5, uniforms=DropoutStream(2)).samples(batch)[1].numpy()
    np.testing.assert_array_equal(first, again)
    assert np.abs(first - other).max() > 1e-3
    # p_test -> 0 keeps every unit: all samples equal the deterministic mean (an independent check of the masks).
    deterministic = pretrained_policy.action_stats(batch)[1].numpy()
    kept = MCDropoutEstimator(pretrained_policy, k=3, p_test=0.0, uniforms=DropoutStream(1)).samples(batch)[1]
    np.testing.assert_allclose(kept.numpy(), np.broadcast_to(deterministic, (3, *deterministic.shape)), atol=1e-6)


def test_metadata_carries_what_the_runtime_needs(pretrained_policy, navigator_file):
    from socnav import __version__

    network = ExportedPolicy.load(navigator_file)
    meta = network.metadata
    assert meta["socnav_version"] == __version__
    assert meta["mc_dropout"] == {"k": 20, "p_test": pretrained_policy.p_test}
    assert meta["observation"]["max_humans"] == pretrained_policy.observation_space["humans"].shape[0]
    assert Thresholds.create(meta["safety"]["thresholds"]) == Thresholds.preset("mc")
    h_min, h_max = (t.numpy() for t in pretrained_policy.feature_range)
    np.testing.assert_array_equal(np.asarray(meta["feature_range"]["h_min"], np.float32), h_min)
    np.testing.assert_array_equal(np.asarray(meta["feature_range"]["h_max"], np.float32), h_max)
    assert json.loads(json.dumps(meta)) == meta  # plain JSON


def test_non_odv_policy_exports_with_calibrated_thresholds(tmp_path, observations):
    """Another architecture (state-independent log sigma, other sizes) and thresholds from a file."""
    import torch

    import socnav
    from socnav.rl import make_model
    from socnav.safety import save_thresholds
    from socnav.uncertainty import MCDropoutEstimator

    config = {"scenario": "circle_crossing"}
    model = make_model("ppo-drop", socnav.make_vec_env(config, n_envs=1), seed=3,
                       overrides={"lstm_hidden_size": 16, "net_arch_pi": (32,)})
    torch.set_num_threads(1)
    policy = model.policy
    thresholds = Thresholds.create(lambda_ep=0.1, lambda_feat=float("inf"), lambda_prox=1.2, beta1=0.0, hold_steps=2,
                                   conditions="uncertainty-only")
    save_thresholds(thresholds, tmp_path / "calibrated.yaml")
    path = socnav.export_onnx(policy, tmp_path / "ppo.onnx", thresholds=tmp_path / "calibrated.yaml", k=4,
                              p_test=0.3, env_config=config)
    network = ExportedPolicy.load(path)
    assert Thresholds.create(network.metadata["safety"]["thresholds"]) == thresholds
    navigator = SafeNavigator(network)
    assert navigator.thresholds.hold_steps == 2  # the navigator holds as calibrated ...
    assert navigator.thresholds.conditions == "uncertainty-only"  # ... with the rule variant of the file
    assert network.metadata["safety"]["thresholds"]["conditions"] == "uncertainty-only"
    batch = {key: value[::7] for key, value in observations.items()}
    np.testing.assert_allclose(network.predict(batch)[0], policy.predict(batch, deterministic=True)[0], atol=TOLERANCE)
    expected = MCDropoutEstimator(policy, k=4, p_test=0.3, uniforms=DropoutStream(5)).samples(batch)
    got = network.samples(batch, DropoutStream(5))
    for g, e in zip(got, expected, strict=True):
        np.testing.assert_allclose(g, e.detach().numpy(), rtol=0, atol=TOLERANCE)


@pytest.mark.parametrize("k", [1, 0])
def test_export_rejects_bad_arguments(pretrained_policy, tmp_path, k):
    from socnav.export import ExportError, export_onnx

    with pytest.raises(ExportError, match=r"k must be an integer in \[2, 1000\]"):
        export_onnx(pretrained_policy, tmp_path / "x.onnx", k=k)
    assert not (tmp_path / "x.onnx").exists()


def test_export_rejects_a_mismatched_env_config(pretrained_policy, tmp_path):
    from socnav.export import ExportError, export_onnx

    with pytest.raises(ExportError, match="max_humans=10 but the env config has max_humans=12"):
        export_onnx(pretrained_policy, tmp_path / "x.onnx", env_config={"scenario": "random", "max_humans": 12})
