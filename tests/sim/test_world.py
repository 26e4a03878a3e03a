"""World invariants (hypothesis), scenario sampling rules and batch-size independence of whole episodes."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from socnav.config import load_config
from socnav.controllers import OrcaController
from socnav.envs.rollout import rollout_episodes
from socnav.sim.scenarios import get_scenario, scenario_names
from socnav.sim.world import CrowdWorld

scenarios = st.sampled_from(scenario_names(self_contained=True))  # replay: test_replay_and_mix.py


@given(scenario=scenarios, seed=st.integers(0, 2**31), n_humans=st.integers(0, 6), n_envs=st.integers(1, 4),
       noise=st.floats(0.0, 1.0))
def test_observation_invariants(scenario, seed, n_humans, n_envs, noise):
    """No NaN; the mask is a prefix of exactly the real humans; padding rows are exactly zero even with noise."""
    config = load_config({"scenario": scenario, "n_humans": n_humans, "max_humans": 8,
                          "perturbation": {"observation_noise": noise}})
    world = CrowdWorld(config, n_envs)
    for env in range(n_envs):
        world.seed(env, seed + env)
    world.reset()
    rng = np.random.default_rng(seed)
    for _ in range(15):
        obs = world.observe()
        for key, value in obs.items():
            assert np.isfinite(value).all(), key
        mask = obs["humans_mask"]
        observable = world.active.copy()
        if world.occlusion:  # map scenarios: the humans behind walls are not observed
            observable &= world.walls.in_sight_of_robot(world.positions, world.active)
        real = observable[:, 1:].sum(axis=1)
        np.testing.assert_array_equal(mask.sum(axis=1), real)
        for env in range(n_envs):
            assert np.all(mask[env, : int(real[env])] == 1.0)
            assert np.all(obs["humans"][env, int(real[env]):] == 0.0), "humans observed beyond the padding"
        result = world.step(rng.uniform(-1, 1, (n_envs, 2)))
        assert np.isfinite(result.reward).all()
        done = np.flatnonzero(result.terminated | result.truncated)
        if len(done):
            world.reset(done)


@given(seed=st.integers(0, 2**31))
def test_closest_human_is_read_last(seed):
    config = load_config({"scenario": "circle_crossing", "n_humans": 6})
    world = CrowdWorld(config, 1)
    world.seed(0, seed)
    world.reset()
    for _ in range(10):
        world.step(np.zeros((1, 2)))
    humans = world.observe()["humans"][0, :6]
    gaps = humans[:, 6]
    assert np.all(np.diff(gaps) <= 1e-6), "rows must go from the farthest to the closest human"
    distance = np.linalg.norm(world.positions[0, 1:7] - world.positions[0, 0], axis=1) - 0.6
    assert gaps[-1] == pytest.approx(distance.min(), abs=1e-5)


@given(seed=st.integers(0, 2**31), scenario=scenarios)
def test_noise_off_means_no_change(seed, scenario):
    """Zero-strength perturbations give exactly the unperturbed world."""
    plain = load_config({"scenario": scenario})
    zero = load_config({"scenario": scenario, "perturbation": {"observation_noise": 0.0, "heading_noise": 0.0,
                                                                 "speed_noise": 0.0, "human_speed_factor": 1.0}})
    worlds = [CrowdWorld(plain, 1), CrowdWorld(zero, 1)]
    for world in worlds:
        world.seed(0, seed)
        world.reset()
    actions = np.random.default_rng(seed).uniform(-1, 1, (20, 1, 2))
    for action in actions:
        a, b = (world.observe() for world in worlds)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
        for world in worlds:
            world.step(action)


def test_noise_on_changes_only_real_elements():
    config = load_config({"scenario": "position_swap", "perturbation": {"observation_noise": 0.5}})
    clean = load_config({"scenario": "position_swap"})
    noisy_world, clean_world = CrowdWorld(config, 1), CrowdWorld(clean, 1)
    for world in (noisy_world, clean_world):
        world.seed(0, 3)
        world.reset()
    noisy, exact = noisy_world.observe(), clean_world.observe()
    assert not np.allclose(noisy["robot"], exact["robot"])
    assert not np.allclose(noisy["humans"][0, 0], exact["humans"][0, 0])
    np.testing.assert_array_equal(noisy["humans"][0, 1:], 0.0)
    np.testing.assert_array_equal(noisy["humans_mask"], exact["humans_mask"])
    residual = np.concatenate([(noisy["robot"] - exact["robot"]).ravel(), (noisy["humans"] - exact["humans"])[0, 0]])
    assert 0.2 < residual.std() < 1.0


def test_faster_humans_and_more_humans():
    config = load_config({"scenario": "position_swap", "perturbation": {"human_speed_factor": 3.0, "total_agents": 5}})
    world = CrowdWorld(config, 1)
    world.seed(0, 0)
    world.reset()
    assert world.active[0].sum() == 5
    np.testing.assert_allclose(world.max_speeds[0, 1:5], 3.0 * world.preferred_speeds[0, 1:5])
    assert world.max_speeds[0, 0] == world.preferred_speeds[0, 0]


def test_action_noise_perturbs_motion():
    def final_position(perturbation):
        world = CrowdWorld(load_config({"scenario": "position_swap", "perturbation": perturbation}), 1)
        world.seed(0, 1)
        world.reset()
        for _ in range(10):
            world.step(np.array([[1.0, 0.0]]))
        return world.positions[0, 0].copy(), world.path_length[0]

    plain, plain_path = final_position({})
    turned, _ = final_position({"heading_noise": 0.5})
    _, slowed_path = final_position({"speed_noise": 0.8})
    assert not np.allclose(plain, turned)
    assert slowed_path < plain_path


@pytest.mark.parametrize("scenario", [name for name in scenario_names(self_contained=True)
                                      if not getattr(get_scenario(name), "has_map", False)])
def test_scenario_sampling_rules(scenario):
    """The paper's scenarios (the map scenarios' placements: test_walls_world.py)."""
    config = load_config({"scenario": scenario})
    state = get_scenario(scenario).sample(np.random.default_rng(0), 50, config)
    low, high = config.humans_range()
    counts = state.active[:, 1:].sum(axis=1)
    assert counts.min() >= low and counts.max() <= high
    speeds = state.preferred_speeds[state.active]
    assert speeds.min() >= 0.5 and speeds.max() <= 1.0
    humans = state.active.copy()
    humans[:, 0] = False
    assert state.personal_space_radii[humans].min() >= 0.3 and state.personal_space_radii[humans].max() <= 0.7
    assert state.cooperation[humans].min() >= 0.25 and state.cooperation[humans].max() <= 0.5
    robot_distance = np.linalg.norm(state.goals[:, 0] - state.positions[:, 0], axis=1)
    if scenario == "random":
        assert robot_distance.min() >= 4.0
        assert np.abs(state.positions[state.active]).max() <= 7.0
    else:
        assert robot_distance == pytest.approx(np.full(50, 14.0))  # robot crosses the 7 m circle
    if scenario == "circle_crossing":
        angles = np.degrees(np.arctan2(state.positions[:, 0, 1], state.positions[:, 0, 0])) % 360
        assert set(np.round(angles).astype(int)) <= {0, 90, 180, 270}
    if scenario == "circle_interaction":
        # each human reaches the centre within 15 % of the robot's arrival time
        robot_time = 7.0 / state.preferred_speeds[:, 0]
        for env in range(50):
            for k in np.flatnonzero(state.active[env, 1:]) + 1:
                human_time = np.linalg.norm(state.positions[env, k]) / state.preferred_speeds[env, k]
                assert abs(human_time / robot_time[env] - 1) <= 0.15 + 1e-9


def test_rollout_records_do_not_depend_on_batch_size():
    config = load_config({"scenario": "circle_crossing", "perturbation": {"heading_noise": 0.3}})
    policy = OrcaController(config)
    one = rollout_episodes(policy, config, 6, seed=40, n_envs=1)
    many = rollout_episodes(policy, config, 6, seed=40, n_envs=4)
    np.testing.assert_array_equal(one.drop(columns=["outcome"]).to_numpy(dtype=float),
                                  many.drop(columns=["outcome"]).to_numpy(dtype=float))
    assert list(one["outcome"]) == list(many["outcome"])


def test_random_scenario_humans_redraw_goals():
    config = load_config({"scenario": "random", "n_humans": 3, "time_step": 0.5})
    world = CrowdWorld(config, 1)
    world.seed(0, 2)
    world.reset()
    first_goals = world.goals[0, 1:4].copy()
    for _ in range(60):
        world.step(np.array([[-1.0, 0.0]]))
    assert not np.allclose(first_goals, world.goals[0, 1:4]), "humans should have drawn new goals"


@pytest.mark.parametrize("humans", [{"model": "orca"}, {"model": "social_force"},
                                    {"mix": {"orca": 0.5, "social_force": 0.5}}])
@pytest.mark.parametrize("scenario", ["circle_crossing", "doorway"])
def test_disturbance_skips_only_humans_blind_to_the_robot(humans, scenario):
    """The disturbance term's robot-free velocities: recomputing only the near humans who see the robot gives, bit
    for bit, what recomputing every near human gives (a human blind to the robot moves the same without it)."""
    config = load_config({"scenario": scenario, "humans": humans, "inattentive_share": 0.5})
    world = CrowdWorld(config, 16)
    for env in range(16):
        world.seed(env, 100 + env)
    world.reset()
    rng = np.random.default_rng(0)
    checked_blind = checked_seeing = 0
    for _ in range(40):
        humans_now = world.human_velocities()
        near = world.humans_near_robot(config.reward.social_radius)
        every_near = world.human_velocities(without_robot=True, only=near)
        skipped = world.unhindered_velocities(humans_now, near)
        np.testing.assert_array_equal(skipped[near], every_near[near])
        checked_blind += int((near & ~world.sees[:, :, 0]).sum())
        checked_seeing += int((near & world.sees[:, :, 0]).sum())
        world.step(rng.uniform(-1.0, 1.0, (16, 2)))
    assert checked_blind > 0 and checked_seeing > 0  # both kinds of human were compared
