"""Fixtures of the runtime tests: navigator files exported once per session, observations of every scenario, and a
simulated world's state as a robot's tracker gives it. Exports go through the CLI (`socnav export`) and the Python
API, so both paths are exercised."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from socnav.config import load_config
from socnav.controllers import OrcaController
from socnav.sim.scenarios import scenario_names
from socnav.sim.world import CrowdWorld

#: Humans per scenario in the collected observations: one, a crowd, the full observation, and a varying number.
SCENARIO_HUMANS = {"position_swap": 1, "circle_crossing": 5, "circle_interaction": 10, "random": (0, 10)}


@pytest.fixture(scope="session")
def pretrained_policy():
    import torch

    import socnav

    torch.set_num_threads(1)
    return socnav.load_policy("pretrained")


@pytest.fixture(scope="session")
def navigator_file(tmp_path_factory: pytest.TempPathFactory, pretrained_policy) -> Path:
    """The shipped policy exported with `socnav export` (paper MC-dropout thresholds, K = 20)."""
    from typer.testing import CliRunner

    from socnav.cli import app

    path = tmp_path_factory.mktemp("export") / "navigator.onnx"
    result = CliRunner().invoke(app, ["export", "pretrained", "--out", str(path), "--value"])
    assert result.exit_code == 0, result.output
    assert path.is_file()
    return path


@pytest.fixture(scope="session")
def observations() -> dict[str, np.ndarray]:
    """>= 1,000 observations from all four scenarios (ORCA-driven robot), plus rows with no human at all."""
    assert set(SCENARIO_HUMANS) <= set(scenario_names(self_contained=True))  # the paper's four (maps: elsewhere)
    batches = []
    for index, (scenario, humans) in enumerate(SCENARIO_HUMANS.items()):
        config = load_config({"scenario": scenario, "n_humans": humans})
        world = CrowdWorld(config, n_envs=16)
        for env in range(world.n_envs):
            world.seed(env, 1000 * index + env)
        world.reset()
        controller = OrcaController(config)
        for _ in range(17):
            obs = world.observe()
            batches.append(obs)
            result = world.step(controller.predict(obs)[0])
            world.reset(np.flatnonzero(result.terminated | result.truncated))
    merged = {key: np.concatenate([batch[key] for batch in batches]) for key in batches[0]}
    empty = {key: value[:8].copy() for key, value in merged.items()}
    empty["humans"][:] = 0.0
    empty["humans_mask"][:] = 0.0
    return {key: np.concatenate([merged[key], empty[key]]) for key in merged}


def _tracked_state(world, env: int = 0) -> tuple[dict, dict]:
    """The robot's state and the humans it sees in one environment of a simulated world (none behind a wall, as the
    world's occlusion has it), as a robot's tracker would give them to `SafeNavigator.act`."""
    visible = world.active[env].copy()
    if world.occlusion:
        visible &= world.walls.in_sight_of_robot(world.positions[env:env + 1], world.active[env:env + 1])[0]
    humans = np.flatnonzero(visible[1:]) + 1
    robot = {"position": world.positions[env, 0], "velocity": world.velocities[env, 0],
             "heading": world.heading[env], "goal": world.goals[env, 0], "v_pref": world.preferred_speeds[env, 0],
             "radius": world.radii[env, 0]}
    return robot, {"positions": world.positions[env, humans], "velocities": world.velocities[env, humans],
                   "radii": world.radii[env, humans]}


@pytest.fixture
def tracked_state():
    """`(robot, humans)` of one environment of a world: ``tracked_state(world, env=0)``."""
    return _tracked_state


def _navigator_steps(env, navigator, seeds, on_episode=None):
    """Drive `env` (a `SocialNavEnv` with a scan) with `navigator` from the world's state arrays, one episode per seed:
    yields ``(observation, robot, decision)`` at every step, the environment's observation beside the navigator's
    decision, then steps the environment with the decision's action. `on_episode()` runs at each episode's start."""
    for seed in seeds:
        observation, _ = env.reset(seed=seed)
        navigator.reset()
        if on_episode is not None:
            on_episode()
        done = False
        while not done:
            robot, humans = _tracked_state(env.world)
            decision = navigator.act(robot, humans, scan=observation["scan"])
            yield observation, robot, decision
            observation, _, terminated, truncated, _ = env.step(decision.action)
            done = terminated or truncated


@pytest.fixture
def navigator_steps():
    """``navigator_steps(env, navigator, seeds, on_episode=None)``: the steps of a navigator driving an environment."""
    return _navigator_steps
