"""What the safety layer senses (paper IV-C; `socnav.safety.rule`, ``Thresholds.sensing``): with ``sensing: true``
the proximity terms and the cautious controller read the simulator's noise-free state while the policy and the
estimator see the noisy observation; with ``perceived`` (the default, the paper's formulation) everything reads
the observation."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from socnav.config import load_config
from socnav.controllers import StraightController
from socnav.envs.rollout import rollout_episodes
from socnav.safety import (
    CautiousController,
    SafePolicy,
    Thresholds,
    ThresholdsError,
    collect_records,
    load_thresholds,
    nearest_human,
    save_thresholds,
)
from socnav.sim.world import CrowdWorld

NOISY = {"scenario": "position_swap", "n_humans": 1, "perturbation": {"observation_noise": 0.8}}
FIRING = {"lambda_ep": 0.0, "lambda_feat": math.inf, "lambda_prox": 100.0, "beta1": 0.5}  # fires near anyone


class Recorder:
    """A policy or estimator stub that keeps every observation it is given."""

    def __init__(self) -> None:
        self.seen: list[dict[str, np.ndarray]] = []

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        self.seen.append({key: np.array(value) for key, value in observation.items()})
        return np.zeros((*np.asarray(observation["robot"]).shape[:-1], 2), np.float32), state

    def __call__(self, obs):
        self.seen.append({key: np.array(value) for key, value in obs.items()})
        batch = obs["robot"].shape[0]
        return SimpleNamespace(u_ep=np.ones((batch, 2)), u_al=np.zeros((batch, 2)), u_feat=np.zeros(batch))


def _scene() -> CrowdWorld:
    """Two environments with one human each, placed by hand: env 0 at 1.5 m ahead and 0.4 m to the left of the
    robot (which faces its goal along +x), env 1 at 3 m, with known velocities."""
    world = CrowdWorld(load_config(NOISY), 2)
    for env in range(2):
        world.seed(env, 10 + env)
    world.reset()
    world.positions[:, 0] = [0.0, 0.0]
    world.goals[:, 0] = [5.0, 0.0]
    world.heading[:] = 0.0
    world.velocities[:, 0] = [[0.5, 0.0], [0.3, 0.0]]
    world.positions[:, 1] = [[1.5, 0.4], [3.0, 0.0]]
    world.velocities[:, 1] = [[-0.4, 0.1], [-0.6, 0.0]]
    return world


def _true_gap_and_speed(world: CrowdWorld) -> tuple[np.ndarray, np.ndarray]:
    """The nearest (only) human's gap and relative speed from the simulator's state, by hand."""
    offset = world.positions[:, 1] - world.positions[:, 0]
    gap = np.linalg.norm(offset, axis=1) - world.radii[:, 0] - world.radii[:, 1]
    speed = np.linalg.norm(world.velocities[:, 1] - world.velocities[:, 0], axis=1)
    return gap, speed


def test_true_sensing_reads_the_state_while_policy_and_estimator_see_the_noise():
    world = _scene()
    noisy, truth = world.observe(), world.observe(noisy=False)
    assert not np.allclose(noisy["humans"], truth["humans"])  # the noise is there
    gap, speed = _true_gap_and_speed(world)

    policy, estimator = Recorder(), Recorder()
    safe = SafePolicy(policy, estimator, Thresholds.create(FIRING, sensing="true"), world.config)
    actions, _ = safe.predict(noisy, true_observation=truth)
    np.testing.assert_allclose(safe.last_nearest.gap, gap, atol=1e-9)
    np.testing.assert_allclose(safe.last_nearest.relative_speed, speed, atol=1e-9)
    for seen in (policy.seen[0], estimator.seen[0]):
        np.testing.assert_array_equal(seen["humans"], noisy["humans"])
        np.testing.assert_array_equal(seen["robot"], noisy["robot"])
    # the rule fired everywhere: the actions are the cautious controller's on the true state
    assert safe.last_fallback.all()
    expected, _ = CautiousController(world.config).predict(truth)
    np.testing.assert_allclose(actions, expected, atol=1e-6)

    # perceived (the default): the proximity terms and the fallback read the noisy observation;
    # a true observation handed in is ignored
    perceived = SafePolicy(Recorder(), Recorder(), Thresholds.create(FIRING), world.config)
    actions, _ = perceived.predict(noisy, true_observation=truth)
    np.testing.assert_allclose(perceived.last_nearest.gap, nearest_human(noisy).gap)
    assert not np.allclose(perceived.last_nearest.gap, gap)
    np.testing.assert_allclose(actions, CautiousController(world.config).predict(noisy)[0], atol=1e-6)


def test_true_sensing_needs_the_true_observation_and_uses_it_once():
    world = _scene()
    safe = SafePolicy(Recorder(), Recorder(), Thresholds.create(FIRING, sensing="true"), world.config)
    assert safe.needs_true_observation
    with pytest.raises(ValueError, match=r"sensing='true'.*noise-free"):
        safe.predict(world.observe())
    safe.sense(world.observe(noisy=False))
    safe.predict(world.observe())
    with pytest.raises(ValueError, match="sensing='true'"):  # a sensed state is not reused on the next step
        safe.predict(world.observe())
    single = {key: value[0] for key, value in world.observe().items()}
    safe = SafePolicy(Recorder(), Recorder(), Thresholds.create(FIRING, sensing="true"), world.config)
    action, _ = safe.predict(single, true_observation={k: v[0] for k, v in world.observe(noisy=False).items()})
    assert np.asarray(action).shape == (2,)
    np.testing.assert_allclose(safe.last_nearest.gap, _true_gap_and_speed(world)[0][:1], atol=1e-9)


class SensedGaps(SafePolicy):
    """Keeps the rule's sensed nearest gap and the action of every step of environment 0."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True, true_observation=None):
        actions, state = super().predict(observation, state, episode_start, deterministic, true_observation)
        self.trace.append((float(self.last_nearest.gap[0]), np.array(actions[0])))
        return actions, state


def test_rollouts_hand_the_true_state_to_the_safety_layer_only():
    config = load_config(NOISY)
    policy = Recorder()
    safe = SensedGaps(policy, Recorder(), Thresholds.create(FIRING, lambda_prox=0.6, sensing="true"), config)
    safe.trace = []
    rollout_episodes(safe, config, n_episodes=1, seed=3, n_envs=1)
    # replay the episode's actions in a fresh world: the sensed gaps are the noise-free ones, step by step, and
    # the policy saw the noisy observations
    world = CrowdWorld(config, 1)
    world.seed(0, 3)
    world.reset()
    for step, (sensed_gap, action) in enumerate(safe.trace):
        assert sensed_gap == pytest.approx(float(nearest_human(world.observe(noisy=False)).gap[0]), abs=1e-9)
        np.testing.assert_array_equal(policy.seen[step]["humans"], world.observe()["humans"])
        world.step(action[None])
    assert len(safe.trace) > 5


def test_without_observation_noise_both_sensings_play_the_same_episodes():
    config = load_config({"scenario": "position_swap", "n_humans": 1, "perturbation": {"heading_noise": 0.5}})
    results = []
    for sensing in ("perceived", "true"):
        thresholds = Thresholds.create(FIRING, lambda_prox=0.8, sensing=sensing)
        safe = SafePolicy(StraightController(config), Recorder(), thresholds, config)
        results.append(rollout_episodes(safe, config, n_episodes=6, seed=0, n_envs=3))
    assert results[0].equals(results[1])


def test_calibration_records_read_the_sensed_gap():
    config = load_config(NOISY)
    for sensing, noisy in (("true", False), ("perceived", True)):
        records = collect_records(StraightController(config), Recorder(), config, n_episodes=3, seed=5, n_envs=2,
                                  sensing=sensing)
        first = records[records["step"] == 0].sort_values("episode")["gap"].to_numpy()
        # step 0 of episode k is seed 5 + k's start, whatever the actions: observe it directly
        expected = []
        for k in range(3):
            world = CrowdWorld(config, 1)
            world.seed(0, 5 + k)
            world.reset()
            expected.append(float(nearest_human(world.observe(noisy=noisy)).gap[0]))
        np.testing.assert_allclose(first, expected, atol=1e-6)


def test_sensing_is_a_validated_threshold_field_that_files_keep(tmp_path):
    assert Thresholds.preset("mc").sensing == "perceived"
    assert Thresholds.preset("mc", sensing="true").sensing == "true"
    with pytest.raises(ThresholdsError, match=r"sensing.*'perceived' or 'true'"):
        Thresholds.create(FIRING, sensing="lidar")
    path = save_thresholds(Thresholds.create(FIRING, sensing="true"), tmp_path / "t.yaml")
    assert load_thresholds(path).sensing == "true"


def test_calibrated_thresholds_carry_the_sensing_they_were_calibrated_with():
    from socnav.safety import calibrate_thresholds

    env = {"scenario": "circle_crossing", "n_humans": 3, "robot_visible": False}
    config = load_config(env)
    thresholds, report = calibrate_thresholds(StraightController(config), Recorder(), env, episodes=1,
                                              proximity="abs-relative-speed", sensing="true")
    assert thresholds.sensing == "true" and report["sensing"] == "true"
    assert report["n_collisions"] > 0  # the straight robot collides: there was something to calibrate on


def test_command_line_sensing_option(tmp_path):
    from typer.testing import CliRunner

    from socnav.cli import app

    runner = CliRunner()
    common = ["evaluate", "--model", "pretrained", "--scenario", "position_swap", "--n-humans", "1", "--episodes",
              "2", "--k", "4", "--perturb", "observation_noise=0.5", "--safety", "mc"]
    result = runner.invoke(app, [*common, "--sensing", "true", "--out", str(tmp_path / "r.csv")])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, [*common, "--sensing", "lidar"])
    assert result.exit_code == 2 and "allowed: perceived, true" in " ".join(result.output.split())
    result = runner.invoke(app, ["calibrate", "--model", "pretrained", "--sensing", "lidar"])
    assert result.exit_code == 2 and "allowed: perceived, true" in " ".join(result.output.split())


def test_animation_hands_the_true_state_to_the_safety_layer(tmp_path):
    from socnav.cli.workflows.animation import animate_episode

    config = load_config(NOISY)
    thresholds = Thresholds.create(FIRING, sensing="true")
    path, summary = animate_episode(StraightController(config), Recorder(), config, tmp_path / "a.gif",
                                    thresholds=thresholds, max_steps=4)
    assert path.is_file() and summary["fallback_steps"] == 4  # the rule fired on every step, with the true state
