"""The navigator of a world with walls and a range scan: the exported network reads the scan as torch does, the file
carries the walls (format 3; wall-free files stay format 2), and `SafeNavigator` decides as the torch `SafePolicy`
step for step in a corridor, its fallback keeping off the walls of the file or of a map given at load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import socnav
from socnav.controllers import OrcaController
from socnav.export import ExportError, export_onnx
from socnav.rl import make_model
from socnav.runtime import DropoutStream, ExportedPolicy, InputError, NavigatorLoadError, SafeNavigator
from socnav.runtime.format import CHECKSUM_KEY, METADATA_KEY, seal
from socnav.safety import SafePolicy, Thresholds
from socnav.safety.cautious import CautiousController
from socnav.sim.observation import observe_robot
from socnav.sim.scenarios import get_scenario
from socnav.sim.walls import world_polygons
from socnav.sim.world import CrowdWorld

CORRIDOR = {"scenario": "corridor", "n_humans": 4, "scan": {"beams": 36}}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,)}
K, P_TEST = 6, 0.3
TOLERANCE = 1e-5
#: A rule that fires often (so the fallback path is compared too): any uncertainty, within about 2.5 m.
EAGER = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=2.5, beta1=0.5)
#: A rule that fires at the first step of an episode whenever a human is observed.
ALWAYS = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=1000.0, beta1=0.0,
                           conditions="proximity-only")


def _world_observations(config: dict, n_envs: int = 8, steps: int = 12) -> dict[str, np.ndarray]:
    """Observations of an ORCA-driven robot in `config`'s world (walls, occlusion and scan as the env gives them)."""
    world_config = socnav.load_config(config)
    world = CrowdWorld(world_config, n_envs=n_envs)
    for env in range(n_envs):
        world.seed(env, 500 + env)
    world.reset()
    controller = OrcaController(world_config)
    batches = []
    for _ in range(steps):
        observation = world.observe()
        batches.append(observation)
        result = world.step(controller.predict(observation)[0])
        world.reset(np.flatnonzero(result.terminated | result.truncated))
    return {key: np.concatenate([batch[key] for batch in batches]) for key in batches[0]}


@pytest.fixture(scope="module")
def scan_policy():
    """An untrained odv-ppo-drop policy of the corridor with a 36-beam scan, its feature range taken from the
    corridor's observations (so that u_feat is computed, as for a trained policy)."""
    torch.set_num_threads(1)
    model = make_model("odv-ppo-drop", socnav.make_vec_env(CORRIDOR, n_envs=1), seed=3, overrides=TINY)
    policy = model.policy
    policy.features_extractor.update_feature_range(policy.action_stats(_world_observations(CORRIDOR))[0])
    return policy


@pytest.fixture(scope="module")
def scan_file(scan_policy, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scan") / "corridor.onnx"
    return export_onnx(scan_policy, path, k=K, p_test=P_TEST, env_config=CORRIDOR, with_value=True)


@pytest.fixture(scope="module")
def observations() -> dict[str, np.ndarray]:
    return _world_observations(CORRIDOR, steps=20)


def _metadata(path: Path) -> dict:
    model = onnx.load(str(path))
    return json.loads({entry.key: entry.value for entry in model.metadata_props}[METADATA_KEY])


def _resealed(source: Path, target: Path, edit) -> Path:
    """`source` with its metadata edited by `edit(dict)` and sealed again (a file as `socnav export` could write)."""
    model = onnx.load(str(source))
    metadata = _metadata(source)
    edit(metadata)
    for entry in model.metadata_props:
        entry.value = json.dumps(metadata) if entry.key == METADATA_KEY else entry.value
        if entry.key == CHECKSUM_KEY:
            entry.value = "0" * 64
    target.write_bytes(seal(model.SerializeToString()))
    return target


# ------------------------------------------------------------------------------------------------ the file

def test_the_file_carries_the_scan_input_and_the_walls(scan_file):
    network = ExportedPolicy.load(scan_file)
    metadata = network.metadata
    assert metadata["version"] == 3
    assert network.input_names[:4] == ["robot", "humans", "humans_mask", "scan"]
    names = [spec["name"] for spec in metadata["dropout_inputs"]]
    assert names == ["keep_lstm_input_0", "keep_lstm_input_1", "keep_h", "keep_scan_0", "keep_scan_1",
                     "keep_scan_2", "keep_scan_3", "keep_actor_0"]
    assert [spec["width"] for spec in metadata["dropout_inputs"]][3:7] == [36, 8 * 18, 16 * 9, 32]
    config = socnav.load_config(CORRIDOR)
    expected = world_polygons(config, get_scenario("corridor"))
    assert len(network.walls) == len(expected) > 0
    for got, polygon in zip(network.walls, expected, strict=True):
        np.testing.assert_array_equal(got, polygon)
    assert network.scan == config.scan


def test_a_wall_free_navigator_stays_a_version_2_file(tmp_path):
    config = {"scenario": "circle_crossing", "n_humans": 2}
    model = make_model("ppo-drop", socnav.make_vec_env(config, n_envs=1), seed=1, overrides=TINY)
    path = export_onnx(model.policy, tmp_path / "open.onnx", k=2, env_config=config)
    metadata = _metadata(path)
    assert metadata["version"] == 2 and "walls" not in metadata
    assert ExportedPolicy.load(path).input_names[:4] == ["robot", "humans", "humans_mask", "keep_lstm_input_0"]
    observation = observe_robot(np.zeros(2), np.zeros(2), 0.0, np.ones(2), 1.0, 0.3, np.zeros((0, 2)),
                                np.zeros((0, 2)), np.zeros(0), 10)
    assert set(observation) == {"robot", "humans", "humans_mask"}


def test_a_map_file_travels_as_polygons(tmp_path):
    """A world whose walls come from a map file: the file stores the polygons and no path, and the navigator loads
    where the map file does not exist (on the robot)."""
    map_file = tmp_path / "map.yaml"
    map_file.write_text("obstacles:\n  - [[2, -1], [3, -1], [3, 1], [2, 1]]\n"
                        "boundaries:\n  - [[-8, -8], [8, -8], [8, 8], [-8, 8]]\n")
    config = {"scenario": "circle_crossing", "n_humans": 2, "circle_radius": 5.0, "map": str(map_file)}
    model = make_model("ppo-drop", socnav.make_vec_env(config, n_envs=1), seed=1, overrides=TINY)
    path = export_onnx(model.policy, tmp_path / "mapped.onnx", k=2, env_config=config)
    expected = world_polygons(socnav.load_config(config), get_scenario("circle_crossing"))
    map_file.unlink()
    metadata = _metadata(path)
    assert metadata["version"] == 3 and "map" not in metadata["env_config"]
    navigator = SafeNavigator.load(path, seed=0)
    assert len(navigator.walls) == 2
    for got, polygon in zip(navigator.walls, expected, strict=True):
        np.testing.assert_array_equal(got, polygon)


@pytest.mark.parametrize("case,edit,match", [
    ("crossed walls", lambda m: m.update(walls=[[[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]]]),
     r"walls\[0\]: self-intersecting"),
    ("no walls in a corridor", lambda m: m.pop("walls"), "holds no walls"),
    ("walls in version 2", lambda m: m.update(version=2), "version 2 has neither a scan nor walls"),
    ("no scan masks", lambda m: m.update(dropout_inputs=[s for s in m["dropout_inputs"]
                                                          if not s["name"].startswith("keep_scan")]),
     "scan masks"),
])
def test_inconsistent_wall_and_scan_records_are_refused(scan_file, tmp_path, case, edit, match):
    with pytest.raises(NavigatorLoadError, match=match):
        ExportedPolicy.load(_resealed(scan_file, tmp_path / "edited.onnx", edit))


def test_export_refuses_an_env_config_without_the_policys_scan(scan_policy, tmp_path):
    with pytest.raises(ExportError, match="reads a range scan but the env config has none"):
        export_onnx(scan_policy, tmp_path / "x.onnx", k=2, env_config={**CORRIDOR, "scan": None})
    with pytest.raises(ExportError, match=r"\(beams, range, fov\) = \(36, 8.0, 360.0\) but the env config's scan "
                                          r"is \(24, 8.0, 360.0\)"):
        export_onnx(scan_policy, tmp_path / "x.onnx", k=2, env_config={**CORRIDOR, "scan": {"beams": 24}})
    assert not (tmp_path / "x.onnx").exists()


# ------------------------------------------------------------------------------------------------ the network

def test_actions_values_and_mc_samples_match_torch(scan_policy, scan_file, observations):
    from socnav.uncertainty import MCDropoutEstimator

    network = ExportedPolicy.load(scan_file)
    assert len(observations["robot"]) >= 150
    expected, _ = scan_policy.predict(observations, deterministic=True)
    np.testing.assert_allclose(network.predict(observations)[0], expected, rtol=0, atol=TOLERANCE)
    with torch.no_grad():
        values = scan_policy.predict_values(scan_policy.obs_to_tensor(observations)[0]).numpy()
    output = network.run(*network.trim(observations)[:3], scan=network.scan_of(observations))
    np.testing.assert_allclose(output.value, values, rtol=0, atol=TOLERANCE)
    estimator = MCDropoutEstimator(scan_policy, k=K, p_test=P_TEST, uniforms=DropoutStream(4))
    stream = DropoutStream(4)
    for start in range(0, len(observations["robot"]), 64):
        batch = {key: value[start:start + 64] for key, value in observations.items()}
        for name, got, want in zip(("h", "mu", "log_std"), network.samples(batch, stream), estimator.samples(batch),
                                   strict=True):
            np.testing.assert_allclose(got, want.numpy(), rtol=0, atol=TOLERANCE, err_msg=name)
    # the scan is read: walls elsewhere, another action
    farther = dict(observations, scan=np.full_like(observations["scan"], 8.0))
    assert np.abs(network.predict(farther)[0] - network.predict(observations)[0]).max() > 1e-4


# ------------------------------------------------------------------------------------------------ the navigator

@pytest.mark.parametrize("seed,hold", [(1, 0), (2, 2)])
def test_navigator_reproduces_safe_policy_in_a_corridor_with_scan(scan_policy, scan_file, seed, hold,
                                                                 navigator_steps):
    """The navigator drives the corridor from the world's state arrays, the scan and the pose; at every step it
    builds the environment's observation, and the torch SafePolicy (its fallback planning around the config's
    walls), fed that observation and the same mask stream, decides the same."""
    from socnav.envs.env import SocialNavEnv
    from socnav.uncertainty import MCDropoutEstimator

    config = socnav.load_config(CORRIDOR)
    thresholds = EAGER.model_copy(update={"hold_steps": hold})
    estimator = MCDropoutEstimator(scan_policy, k=K, p_test=P_TEST, uniforms=DropoutStream(seed))
    reference = SafePolicy(scan_policy, estimator, thresholds, config, n_envs=1)
    navigator = SafeNavigator.load(scan_file, thresholds=thresholds, seed=seed)
    env = SocialNavEnv(config)
    steps = fallbacks = 0
    for observation, _, decision in navigator_steps(env, navigator, [100 * seed, 100 * seed + 1], reference.reset):
        for key, value in observation.items():
            np.testing.assert_array_equal(decision.observation[key][0], value, err_msg=key)
        expected, _ = reference.predict(observation)
        assert decision.fallback == bool(reference.last_fallback[0])
        np.testing.assert_allclose(decision.action, expected, rtol=0, atol=TOLERANCE)
        for name, value in reference.last_uncertainty.items():
            assert decision.windowed[name] == pytest.approx(float(value[0]), abs=TOLERANCE), name
        steps += 1
        fallbacks += decision.fallback
    assert 0 < fallbacks < steps  # both the fallback and the policy were compared


def test_the_fallback_keeps_off_the_walls_given_at_load(scan_file):
    """Walls given at load replace the file's: the fallback is the cautious controller of a world whose only walls
    are those (an env config's `obstacles`), planned from the pose; without walls it would act otherwise."""
    walls = [np.array([[-0.5, 0.6], [0.5, 0.6]]), np.array([[1.0, -1.0], [2.0, -1.0], [2.0, 1.0], [1.0, 1.0]])]
    navigator = SafeNavigator.load(scan_file, thresholds=ALWAYS, seed=0, walls=walls)
    assert len(navigator.walls) == 2
    config = socnav.load_config({"scenario": "circle_crossing", "obstacles": [w.tolist() for w in walls]})
    reference, open_plane = CautiousController(config), CautiousController(socnav.load_config({}))
    scan = np.full(36, 8.0)
    differs = 0
    rng = np.random.default_rng(5)
    for _ in range(12):
        heading = rng.uniform(-np.pi, np.pi)
        robot = {"position": [rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.2)], "velocity": [0.0, 0.0],
                 "heading": heading, "goal": [0.0, 4.0], "v_pref": 1.0, "radius": 0.3}
        humans = {"positions": [[-2.0, -2.0]], "velocities": [[0.0, 0.0]], "radii": [0.3]}
        navigator.reset()
        decision = navigator.act(robot, humans, scan=scan)
        assert decision.fallback
        np.testing.assert_array_equal(decision.observation["pose"][0],
                                      np.float32([*robot["position"], heading]))
        np.testing.assert_allclose(decision.action, reference.predict(decision.observation)[0][0], atol=1e-6)
        differs += np.abs(decision.action - open_plane.predict(decision.observation)[0][0]).max() > 1e-3
    assert differs > 0
    # The pose may be given in the map frame apart from the robot's own (odometry) frame.
    navigator.reset()
    moved = navigator.act({**robot, "position": [50.0, 50.0], "goal": [50.0, 54.0]}, None, scan=scan,
                          pose=[0.0, 0.0, heading])
    np.testing.assert_array_equal(moved.observation["pose"][0], np.float32([0.0, 0.0, heading]))


def test_walls_can_be_taken_away_and_are_validated(scan_file):
    assert SafeNavigator.load(scan_file, seed=0, walls=[]).walls is None
    with pytest.raises(ValueError, match=r"walls\[0\]: a polygon needs at least 2 vertices"):
        SafeNavigator.load(scan_file, seed=0, walls=[[[0.0, 0.0]]])


ROBOT = {"position": [0.0, -2.0], "velocity": [0.0, 0.0], "heading": 1.5, "goal": [0.0, 4.0], "v_pref": 1.0,
         "radius": 0.3}


@pytest.mark.parametrize("scan,match", [
    (None, r"scan: this navigator's policy reads a range scan of 36 beams"),
    (np.full(35, 4.0), r"scan must have shape \(36,\)"),
    (np.r_[np.nan, np.full(35, 4.0)], r"scan is NaN at beams \[0\]"),
    (np.r_[np.full(35, 4.0), -0.5], r"scan ranges must be >= 0 \(metres\), got -0.5 at beams \[35\]"),
    (["4.0"] * 36, "must be numeric"),
])
def test_a_bad_scan_is_a_clear_error(scan_file, scan, match):
    navigator = SafeNavigator.load(scan_file, seed=0)
    with pytest.raises(InputError, match=match):
        navigator.act(ROBOT, None, scan=scan)


def test_out_of_range_readings_read_as_the_simulator_reads_them(scan_file):
    """REP 117: +inf (no return) and readings beyond the range are the range, -inf (too close) is 0."""
    navigator = SafeNavigator.load(scan_file, seed=0)
    ranges = np.full(36, 3.0)
    ranges[:3] = [np.inf, 12.0, -np.inf]
    decision = navigator.act(ROBOT, None, scan=ranges)
    np.testing.assert_array_equal(decision.observation["scan"][0, :4], np.float32([8.0, 8.0, 0.0, 3.0]))
    assert decision.fault is None
    with pytest.raises(InputError, match="lacks"):
        navigator.act_observation({key: value for key, value in decision.observation.items() if key != "scan"})
