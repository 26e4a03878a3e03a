"""SafeNavigator: torch-free imports, the environment's observation, SafePolicy's episodes, clear input errors.
The episode test drives one environment with the navigator and another with the torch SafePolicy, same seeds."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import socnav
from socnav.runtime import DropoutStream, HumansState, InputError, NavigatorLoadError, RobotState, SafeNavigator
from socnav.safety import Thresholds

#: A rule that fires often (so the fallback path is compared too): any uncertainty, within about 2.5 m.
EAGER = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=2.5, beta1=0.5)
ROBOT = {"position": [0.0, -4.0], "velocity": [0.0, 0.0], "heading": 1.5, "goal": [0.0, 4.0], "v_pref": 1.0,
         "radius": 0.3}


def test_runtime_imports_no_torch():
    code = ("import sys, socnav.runtime, socnav.sim.observation; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'stable_baselines3')); "
            "print(bad); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


def test_import_socnav_imports_no_torch():
    code = "import sys, socnav; sys.exit(1 if {'torch', 'stable_baselines3'} & set(sys.modules) else 0)"
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_observation_is_the_environments(navigator_file, tracked_state):
    """Built from plain state arrays, the navigator's observation is bit-identical to the environment's."""
    from socnav.sim import world as world_module
    from socnav.sim.observation import observe_batch
    from socnav.sim.world import CrowdWorld

    assert observe_batch is world_module.observe_batch  # one function, shared
    navigator = SafeNavigator.load(navigator_file, seed=0)
    for scenario, humans in (("circle_crossing", 5), ("random", (0, 10)), ("position_swap", 1)):
        world = CrowdWorld(socnav.load_config({"scenario": scenario, "n_humans": humans}), n_envs=4)
        for env in range(4):
            world.seed(env, env)
        world.reset()
        world.velocities[:] = np.random.default_rng(0).normal(size=world.velocities.shape)  # not all at rest
        expected = world.observe()
        for env in range(4):
            decision = navigator.act(*tracked_state(world, env))
            for key, value in expected.items():
                np.testing.assert_array_equal(decision.observation[key][0], value[env], err_msg=key)


def test_more_humans_than_rows_keeps_the_closest(navigator_file):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    rng = np.random.default_rng(3)
    count = navigator.max_humans + 6
    positions = rng.uniform(-5, 5, size=(count, 2))
    radii = rng.uniform(0.2, 0.4, size=count)
    decision = navigator.act(ROBOT, {"positions": positions, "velocities": np.zeros((count, 2)), "radii": radii})
    gaps = np.linalg.norm(positions - np.array(ROBOT["position"]), axis=1) - radii - ROBOT["radius"]
    closest = np.sort(gaps)[: navigator.max_humans]
    observed = decision.observation["humans"][0, :, 6]
    assert decision.observation["humans_mask"][0].sum() == navigator.max_humans
    np.testing.assert_allclose(np.sort(observed), closest, atol=1e-5)
    assert observed[-1] == pytest.approx(closest[0], abs=1e-5)  # the closest is the last row


@pytest.mark.parametrize("scenario,humans,seed,hold,conditions", [
    ("position_swap", 1, 0, 0, "paper"), ("circle_crossing", 5, 1, 0, "paper"), ("random", (0, 10), 2, 0, "paper"),
    ("circle_crossing", 5, 3, 2, "paper"), ("circle_crossing", 5, 4, 0, "proximity-only"),
    ("random", (0, 10), 5, 1, "uncertainty-only")])
def test_navigator_reproduces_safe_policy_episodes(pretrained_policy, navigator_file, scenario, humans, seed, hold,
                                                   conditions, tracked_state):
    """The navigator drives the environment from the world's state arrays; at every step the torch SafePolicy,
    fed the environment's observation and the same mask stream, decides the same: fallback, action, uncertainty;
    with a hold of the fallback too (held steps: the fallback drives while the rule does not fire), and with each
    ablation of the rule (``Thresholds.conditions``).

    (Two environments stepped independently by the two drift apart from float32 rounding (~1e-7), which the
    shipped policy's saturated turns can amplify; so both decide on the one trajectory.)
    """
    from socnav.envs.env import SocialNavEnv
    from socnav.safety import SafePolicy
    from socnav.uncertainty import MCDropoutEstimator

    config = socnav.load_config({"scenario": scenario, "n_humans": humans})
    estimator = MCDropoutEstimator(pretrained_policy, k=20, uniforms=DropoutStream(seed))
    thresholds = EAGER.model_copy(update={"hold_steps": hold, "conditions": conditions})
    reference = SafePolicy(pretrained_policy, estimator, thresholds, config, n_envs=1)
    navigator = SafeNavigator.load(navigator_file, thresholds=thresholds, seed=seed)
    env = SocialNavEnv(config)
    fallbacks = steps = held = 0
    for episode in range(2):
        obs, _ = env.reset(seed=100 * seed + episode)
        reference.reset()
        navigator.reset()
        done = False
        while not done:
            decision = navigator.act(*tracked_state(env.world))
            expected, _ = reference.predict(obs)
            assert decision.fallback == bool(reference.last_fallback[0])
            np.testing.assert_allclose(decision.action, expected, rtol=0, atol=1e-5)
            for name, value in reference.last_uncertainty.items():
                assert decision.windowed[name] == pytest.approx(float(value[0]), abs=1e-5), name
            fallbacks += decision.fallback
            held += decision.fallback and not decision.conditions.p_col[0]
            steps += 1
            obs, _, terminated, truncated, _ = env.step(decision.action)
            done = terminated or truncated
    assert fallbacks > 0 and steps > fallbacks  # both the fallback and the policy were compared
    assert (held > 0) == (hold > 0)
    assert navigator.thresholds.conditions == conditions


def test_command_and_window(navigator_file):
    navigator = SafeNavigator.load(navigator_file, thresholds=Thresholds.never(), seed=0)
    first = navigator.act(ROBOT)
    # A window of one step: the windowed values are this step's estimate.
    assert first.windowed["u_feat"] == pytest.approx(float(first.uncertainty.u_feat[0]))
    assert first.windowed["u_ep_heading"] == pytest.approx(float(first.uncertainty.u_ep_heading[0]))
    second = navigator.act(ROBOT)
    mean_of_two = (first.uncertainty.u_ep_heading[0] + second.uncertainty.u_ep_heading[0]) / 2
    assert second.windowed["u_ep_heading"] == pytest.approx(float(mean_of_two))
    navigator.reset()
    third = navigator.act(ROBOT)
    assert third.windowed["u_ep_heading"] == pytest.approx(float(third.uncertainty.u_ep_heading[0]))
    # The command is the environment's mapping of the action.
    speed, turn = third.command
    assert speed == pytest.approx(ROBOT["v_pref"] * (float(third.action[0]) + 1) / 2)
    assert turn == pytest.approx(navigator.config.max_heading_change * float(third.action[1]))
    assert not third.fallback


@pytest.mark.parametrize("robot,humans,match", [
    ({**ROBOT, "position": [0.0, 1.0, 2.0]}, None, r"robot.position must have shape \(2,\)"),
    ({**ROBOT, "heading": float("nan")}, None, "robot.heading must be a finite number"),
    ({**ROBOT, "v_pref": [1.0, 2.0]}, None, "robot.v_pref must be a finite number"),
    ({**ROBOT, "v_pref": 1.5}, None, r"robot.v_pref must be > 0.0 and <= 1.0"),  # the env config's fastest
    ({**ROBOT, "v_pref": 0.0}, None, "robot.v_pref must be > 0"),
    ({**ROBOT, "radius": -0.1}, None, "robot.radius must be >= 0"),
    ({key: value for key, value in ROBOT.items() if key != "goal"}, None, "lacks"),
    (ROBOT, {"positions": [[0.0, 1.0], [np.nan, 2.0]], "velocities": [[0, 0], [0, 0]], "radii": [0.3, 0.3]},
     r"humans.positions is not finite in rows \[1\]"),
    (ROBOT, {"positions": [[0.0, 1.0, 0.0]], "velocities": [[0, 0]], "radii": [0.3]},
     r"humans.positions must have shape \(n, 2\)"),
    (ROBOT, {"positions": [[0.0, 1.0]], "velocities": [[0, 0], [1, 1]], "radii": [0.3]}, "one row per human"),
    (ROBOT, {"positions": [[0.0, 1.0]], "velocities": [[0, 0]], "radii": [-0.3]}, "radii must be >= 0"),
    (ROBOT, {"positions": [[0.0, 1.0]], "velocities": [[0, 0]], "radius": [0.3]}, "unknown human fields"),
    (ROBOT, {"positions": "here", "velocities": [[0, 0]], "radii": [0.3]}, "must be numeric"),
])
def test_bad_input_is_a_clear_error(navigator_file, robot, humans, match):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    with pytest.raises(InputError, match=match) as error:
        navigator.act(robot, humans)
    assert isinstance(error.value, ValueError)


def test_no_humans_and_dataclass_input(navigator_file):
    navigator = SafeNavigator.load(navigator_file, seed=0)
    decision = navigator.act(RobotState(**ROBOT), HumansState())
    assert decision.observation["humans_mask"].sum() == 0
    assert np.isfinite(decision.action).all() and not decision.fallback


def test_bad_files_are_clear_errors(navigator_file, tmp_path):
    import onnx
    from onnx import TensorProto, helper

    with pytest.raises(NavigatorLoadError, match="no navigator file"):
        SafeNavigator.load(tmp_path / "missing.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not an onnx model at all" * 10)
    with pytest.raises(NavigatorLoadError, match="not a readable ONNX model"):
        SafeNavigator.load(garbage)
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(Path(navigator_file).read_bytes()[:5000])
    with pytest.raises(NavigatorLoadError):
        SafeNavigator.load(truncated)
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])
    foreign = tmp_path / "foreign.onnx"
    onnx.save(helper.make_model(helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [x],
                                                  [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])),
              str(foreign))
    with pytest.raises(NavigatorLoadError, match="not a socnav navigator"):
        SafeNavigator.load(foreign)
    future = onnx.load(str(navigator_file))
    future.metadata_props[0].value = future.metadata_props[0].value.replace('"version": 2', '"version": 99')
    onnx.save(future, str(tmp_path / "future.onnx"))
    with pytest.raises(NavigatorLoadError, match="version 99 is not supported"):
        SafeNavigator.load(tmp_path / "future.onnx")


def test_example_control_loop_runs_without_torch(navigator_file):
    example = Path(__file__).parents[2] / "examples" / "control_loop.py"
    code = (f"import runpy, sys; sys.argv = ['control_loop.py', {str(navigator_file)!r}, '--fast', '--steps', '40']; "
            f"runpy.run_path({str(example)!r}, run_name='__main__'); "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "step" in result.stdout


def test_the_command_uses_the_full_precision_preferred_speed(navigator_file):
    # 0.7123456789 has no exact float32: the speed must come from the float64 v_pref, as the simulator computes it
    from socnav.sim.observation import robot_command

    navigator = SafeNavigator.load(navigator_file, thresholds=Thresholds.never(), seed=0)
    v_pref = 0.7123456789
    decision = navigator.act({**ROBOT, "v_pref": v_pref})
    expected = robot_command(decision.action, v_pref, navigator.config.max_heading_change)
    assert (decision.speed, decision.turn) == expected
    assert decision.speed != robot_command(decision.action, float(np.float32(v_pref)),
                                           navigator.config.max_heading_change)[0] or decision.speed == 0.0
