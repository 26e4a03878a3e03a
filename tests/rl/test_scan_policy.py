"""A policy that reads the range scan: its encoder (scaling, circular padding, dropout order), the scan-free network
without any scan module, training on a scan world, and saving / loading / checkpointing it in the safe format."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

import socnav
from socnav.envs.spaces import action_space, observation_space
from socnav.rl import make_model
from socnav.rl.extractor import HumanLSTMExtractor, ScanEncoder
from socnav.rl.persistence import load_checkpoint, load_policy, save_checkpoint, save_policy, verify_checkpoint
from socnav.rl.policy import ODVActorCriticPolicy
from socnav.rl.presets import policy_kwargs_for, resolve_config
from socnav.uncertainty import MCDropoutEstimator

CORRIDOR = {"scenario": "corridor", "n_humans": 3, "scan": {"beams": 36}}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,), "n_steps": 32, "batch_size": 32,
        "n_epochs": 1}


def _scan_config(beams: int = 36, max_range: float = 8.0, fov: float = 360.0):
    return socnav.load_config({"scan": {"beams": beams, "range": max_range, "fov": fov}}).scan


def _batch(space: spaces.Dict, rows: int = 6, seed: int = 0) -> dict[str, th.Tensor]:
    """Random observations of `space`: 0 .. 3 humans per row, ranges in [0, range]."""
    rng = np.random.default_rng(seed)
    humans = space["humans"].shape[0]
    counts = np.arange(rows) % 4
    observation = {
        "robot": rng.normal(size=(rows, 5)), "humans": rng.normal(size=(rows, humans, 7)),
        "humans_mask": (np.arange(humans)[None] < counts[:, None]).astype(float),
    }
    observation["humans"] *= observation["humans_mask"][..., None]
    if "pose" in space.spaces:
        observation["pose"] = rng.normal(size=(rows, 3))
    if "scan" in space.spaces:
        observation["scan"] = rng.uniform(0.0, float(space["scan"].high[0]), size=(rows, space["scan"].shape[0]))
    return {key: th.as_tensor(value, dtype=th.float32) for key, value in observation.items()}


def _trained_scan_model(config=CORRIDOR, seed: int = 3):
    model = make_model("odv-ppo-drop", socnav.make_vec_env(config, n_envs=2), seed=seed, overrides=TINY)
    model.learn(64)
    return model


# ------------------------------------------------------------------------------------------------ the extractor

def test_features_are_h_robot_then_scan_features_and_pose_is_not_read():
    space = observation_space(4, pose=True, scan=_scan_config())
    extractor = HumanLSTMExtractor(space, lstm_hidden_size=16).eval()
    batch = _batch(space)
    features, h = extractor.forward_with_h(batch)
    assert extractor.features_dim == 16 + 5 + 32 == features.shape[1]
    th.testing.assert_close(features[:, :16], h)
    th.testing.assert_close(features[:, 16:21], batch["robot"])
    th.testing.assert_close(features[:, 21:], extractor.scan_encoder(batch["scan"]))
    moved = dict(batch, pose=batch["pose"] + 100.0)  # anywhere else on the map: the same features
    th.testing.assert_close(extractor(moved), features, rtol=0, atol=0)
    closer = dict(batch, scan=batch["scan"] * 0.5)
    assert (extractor(closer)[:, 21:] - features[:, 21:]).abs().max() > 1e-3  # the scan is read


def test_ranges_are_read_relative_to_the_maximum_range():
    """Two encoders with the same weights, one for an 8 m scan and one for a 16 m scan, see the same scaled input."""
    short, long = ScanEncoder(36, 8.0, 360.0, 0.0), ScanEncoder(36, 16.0, 360.0, 0.0)
    long.load_state_dict(short.state_dict())
    ranges = th.rand(5, 36) * 8.0
    th.testing.assert_close(long(ranges * 2.0), short(ranges), rtol=0, atol=1e-6)
    th.testing.assert_close(short(th.full((1, 36), 8.0)), long(th.full((1, 36), 16.0)), rtol=0, atol=0)


def _convolutions(encoder: ScanEncoder, ranges: th.Tensor) -> th.Tensor:
    """The output (B, 16, N / 4) of the encoder's second convolution (after its ReLU)."""
    x = ranges / encoder.max_range
    for module in encoder.layers:
        if isinstance(module, th.nn.Flatten) and x.ndim == 3 and x.shape[1] == 16:
            return x
        x = module(x)
    raise AssertionError("no second convolution")


def test_full_circle_padding_wraps_around():
    """With a 360-degree scan, turning the robot by 4 beams (two stride-2 convolutions) turns the convolution
    outputs by exactly one position: the padding wraps around. A narrower field of view pads with zeros, which
    breaks that equivariance at the ends."""
    ranges = th.rand(3, 36) * 8.0
    turned = th.roll(ranges, 4, dims=1)
    circular = ScanEncoder(36, 8.0, 360.0, 0.0)
    th.testing.assert_close(_convolutions(circular, turned), th.roll(_convolutions(circular, ranges), 1, dims=2),
                            rtol=0, atol=1e-6)
    flat = ScanEncoder(36, 8.0, 270.0, 0.0)
    flat.load_state_dict(circular.state_dict())
    gap = (_convolutions(flat, turned) - th.roll(_convolutions(flat, ranges), 1, dims=2)).abs().amax(dim=(0, 1))
    # Output j of the second convolution reads beams 4j - 6 .. 4j + 6 (kernel 5, stride 2, twice): for j = 3 .. 7
    # neither side reads padding or the 4 beams the turn wrapped around; the others do.
    assert gap[3:8].max() < 1e-6
    assert gap[[0, 1, 2, 8]].min() > 1e-4


@pytest.mark.parametrize("beams", [1, 2, 3, 7])
def test_a_scan_of_few_beams_encodes(beams):
    for fov in (360.0, 90.0):
        encoder = ScanEncoder(beams, 8.0, fov, 0.1)
        assert encoder(th.rand(4, beams)).shape == (4, 32)


def test_without_scan_a_pose_key_changes_nothing_in_the_network():
    """The pose key (a world with walls, no scan) changes nothing: same parameters, drawn the same from a seed."""
    plain = observation_space(4)
    with_pose = observation_space(4, pose=True)
    built = []
    for space in (plain, with_pose):
        th.manual_seed(11)
        built.append(ODVActorCriticPolicy(space, action_space(), lambda _: 3e-4, dropout_p=0.1))
    first, second = (policy.state_dict() for policy in built)
    assert list(first) == list(second)
    assert not any("scan" in name for name in first)
    for name in first:
        assert th.equal(first[name], second[name]), name
    assert built[0].features_extractor.scan_encoder is None
    assert len(built[0].dropout_layers()) == 2 + 1 + 2  # two LSTM inputs, h, two actor layers: no scan layers


def test_mc_dropout_draws_the_scan_masks_after_h_in_forward_order():
    """The runtime draws the masks in `dropout_layers()` order: torch's forward pass must draw them in that order,
    with (rows, width) shapes: LSTM inputs, h, the scan encoder's four, then the actor's."""
    space = observation_space(4, scan=_scan_config(beams=36))
    policy = ODVActorCriticPolicy(space, action_space(), lambda _: 3e-4, dropout_p=0.1, lstm_hidden_size=16,
                                  net_arch=dict(pi=[32], vf=[32]))
    shapes = []

    def record(layer: int, shape: tuple[int, ...]) -> np.ndarray:
        shapes.append((layer, shape))
        return np.full(shape, 0.99, np.float32)

    batch = {key: value.numpy() for key, value in _batch(space, rows=3).items()}
    MCDropoutEstimator(policy, k=2, uniforms=record).samples(batch)
    rows, steps = 6, 2  # K * B rows; the longest human sequence of the batch (0, 1, 2 humans)
    assert shapes == [(0, (rows, steps, 7)), (1, (rows, steps, 16)), (2, (rows, 16)),
                      (3, (rows, 36)), (4, (rows, 8 * 18)), (5, (rows, 16 * 9)), (6, (rows, 32)),
                      (7, (rows, 32))]
    scan_layers = policy.features_extractor.scan_encoder.dropout_layers()
    assert policy.dropout_layers()[3:7] == scan_layers


# ------------------------------------------------------------------------------------------------ training

def test_scan_environment_passes_the_env_checkers():
    from gymnasium.utils.env_checker import check_env as gym_check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = socnav.make_env(CORRIDOR)
    assert set(env.observation_space.spaces) == {"robot", "humans", "humans_mask", "pose", "scan"}
    gym_check_env(env, skip_render_check=True)
    sb3_check_env(socnav.make_env(CORRIDOR), warn=True)


def test_a_scan_policy_trains_and_its_scan_encoder_learns():
    model = make_model("odv-ppo-drop", socnav.make_vec_env(CORRIDOR, n_envs=2), seed=5, overrides=TINY)
    encoder = model.policy.features_extractor.scan_encoder
    before = {name: value.clone() for name, value in encoder.state_dict().items()}
    model.learn(64)
    changed = [name for name, value in encoder.state_dict().items() if not th.equal(value, before[name])]
    assert len(changed) == len(before)  # every convolution and the linear layer took gradient steps
    h_min, h_max = model.policy.feature_range
    assert bool((h_min <= h_max).all())  # the feature range was tracked on the rollouts


# ------------------------------------------------------------------------------------------------ saving

def _metadata(model, config=CORRIDOR) -> dict:
    return {"algo": "odv-ppo-drop", "algo_config": model.algo_config,
            "env_config": socnav.load_config(config).model_dump(mode="json")}


def test_a_scan_policy_saves_loads_and_predicts_the_same(tmp_path):
    model = _trained_scan_model()
    loaded = load_policy(save_policy(model.policy, tmp_path / "scan.zip", _metadata(model)))
    assert loaded.observation_space == model.observation_space
    for name, value in model.policy.state_dict().items():
        assert th.equal(loaded.state_dict()[name], value), name
    env = socnav.make_vec_env(CORRIDOR, n_envs=4)
    env.seed(9)
    observation = env.reset()
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0],
                                  model.policy.predict(observation, deterministic=True)[0])


def test_a_narrow_scan_policy_is_rebuilt_with_its_field_of_view(tmp_path):
    config = {**CORRIDOR, "scan": {"beams": 24, "fov": 240.0}}
    env = socnav.make_vec_env(config, n_envs=1)
    algo_config = resolve_config("odv-ppo-drop", TINY)
    metadata = {"algo": "odv-ppo-drop", "algo_config": algo_config.model_dump(mode="json"),
                "env_config": socnav.load_config(config).model_dump(mode="json")}

    def build(**extractor: float) -> ODVActorCriticPolicy:
        return ODVActorCriticPolicy(env.observation_space, action_space(), lambda _: 3e-4,
                                    **{**policy_kwargs_for(algo_config), "features_extractor_kwargs": extractor})

    with pytest.raises(ValueError, match=r"built for a 360-degree scan but its env config has scan.fov=240"):
        save_policy(build(), tmp_path / "wrong.zip", metadata)  # loaded, it would pad differently
    policy = build(scan_fov=240.0)
    loaded = load_policy(save_policy(policy, tmp_path / "narrow.zip", metadata))
    assert loaded.features_extractor.scan_encoder.fov == 240.0
    observation = env.reset()
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0],
                                  policy.predict(observation, deterministic=True)[0])


def test_a_scan_checkpoint_round_trips(tmp_path):
    model = _trained_scan_model(seed=4)
    env_config = socnav.load_config(CORRIDOR).model_dump(mode="json")
    path = save_checkpoint(model, tmp_path / "checkpoint.zip", env_config, seed=4)
    assert verify_checkpoint(path).env_config == env_config
    resumed, _ = load_checkpoint(path, socnav.make_vec_env(CORRIDOR, n_envs=2))
    for name, value in model.policy.state_dict().items():
        assert th.equal(resumed.policy.state_dict()[name], value), name
    again = save_checkpoint(resumed, tmp_path / "again.zip", env_config, seed=4)
    assert again.read_bytes() == path.read_bytes()
