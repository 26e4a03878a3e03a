"""The safety layer's wall stop (`socnav.safety.wall_stop`): hand-computed steps against a wall, the world's own
wall collisions as the truth for random steps, and the layer that keeps a wall-blind policy off the walls."""

from __future__ import annotations

import math

import numpy as np
import pytest

import socnav
from socnav.envs.rollout import rollout_episodes
from socnav.envs.vec_env import SocialNavVecEnv
from socnav.safety import SafePolicy, Thresholds
from socnav.safety.wall_stop import WallStop
from socnav.sim.scenarios import get_scenario
from socnav.sim.walls import POSE_KEY, world_polygons

#: a rule that never fires: the layer is the policy, plus the wall stop
NEVER = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=0.0, beta1=0.0, conditions="proximity-only")
WALL = [np.array([[-10.0, 1.5], [10.0, 1.5]])]  # a wall segment along y = 1.5


def _facing_the_wall(y: float) -> dict[str, np.ndarray]:
    """A robot of radius 0.3 and v_pref 1 m/s at (0, y), heading straight at the wall (+y)."""
    return {"robot": np.array([[5.0, 0.0, 0.0, 1.0, 0.3]], dtype=np.float32),
            POSE_KEY: np.array([[0.0, y, math.pi / 2]], dtype=np.float32)}


@pytest.mark.parametrize(("action", "touches"), [
    ((1.0, 0.0), True),    # 0.25 m towards the wall: y 1.25, 0.25 m from it < radius 0.3
    ((0.0, 0.0), False),   # half speed: y 1.125, 0.375 m from it
    ((1.0, -1.0), True),   # turned 30 degrees away first: y 1.0 + 0.25 sin 60 = 1.2165, 0.283 m from it
    ((1.0, -3.0), True),   # a turn action beyond -1 is clipped to -1, as the simulator clips it: the same step
    ((0.2, -1.0), False),  # 0.6 m/s, 30 degrees away: y 1.0 + 0.15 sin 60 = 1.130, 0.370 m from it
])
def test_hand_computed_steps_towards_a_wall(action, touches):
    stop = WallStop(WALL, time_step=0.25, max_heading_change=math.pi / 6)
    assert bool(stop.touches(np.array([action]), _facing_the_wall(1.0))[0]) is touches


def test_stopping_keeps_the_turn_and_stands_still():
    stop = WallStop(WALL, time_step=0.25, max_heading_change=math.pi / 6)
    actions = np.array([[1.0, 0.5], [0.0, 0.5]], dtype=np.float32)
    observation = {key: np.repeat(value, 2, axis=0) for key, value in _facing_the_wall(1.0).items()}
    stopped = stop.apply(actions, observation)
    assert stopped.tolist() == [True, False]
    np.testing.assert_array_equal(actions, [[-1.0, 0.5], [0.0, 0.5]])
    assert not stop.touches(actions, observation).any()  # standing still, 0.5 m from the wall, touches nothing


def test_the_stop_predicts_the_worlds_wall_collisions():
    """Random actions in an empty corridor, driven towards the walls: a step ends against a wall exactly when the
    wall stop said it would (the world's own sweep is the truth)."""
    config = {"scenario": "corridor", "n_humans": 0, "layout": {"corridor_width": 1.2}}
    env = SocialNavVecEnv(config, n_envs=32)
    env.seed(3)
    world = env.config
    stop = WallStop(world_polygons(world, get_scenario(world.scenario)), world.time_step, world.max_heading_change)
    rng = np.random.default_rng(0)
    observation = env.reset()
    hits = 0
    for _ in range(60):
        actions = rng.uniform(-1.0, 1.0, size=(32, 2)).astype(np.float32)
        predicted = stop.touches(actions, observation)
        observation, _, _, infos = env.step(actions)
        hit = np.array([info.get("outcome") == "collision_wall" for info in infos])
        np.testing.assert_array_equal(predicted, hit)
        hits += int(hit.sum())
    assert hits > 10  # the check was exercised on many wall collisions


class IntoTheWall:
    """A wall-blind policy: turns towards the goal frame's +y (a corridor wall) and drives at full speed."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        heading = observation["robot"][:, 1]
        turn = np.clip(np.remainder(math.pi / 2 - heading + math.pi, 2 * math.pi) - math.pi, -0.5, 0.5) / 0.5
        return np.column_stack([np.ones_like(turn), turn]).astype(np.float32), state


def test_the_layer_keeps_a_wall_blind_policy_off_the_walls():
    """The same episodes: without the stop the policy ends most of them against a wall; with it, none."""
    config = socnav.load_config({"scenario": "corridor", "n_humans": 0})
    outcomes = {}
    for wall_stop in (False, True):
        layer = SafePolicy(IntoTheWall(), None, NEVER, config, wall_stop=wall_stop)
        records = rollout_episodes(layer, config, 16, seed=0, n_envs=16, progress=False)
        outcomes[wall_stop] = records["outcome"].value_counts().to_dict()
    assert outcomes[False].get("collision_wall", 0) >= 12
    assert outcomes[True].get("collision_wall", 0) == 0 and outcomes[True].get("timeout", 0) == 16
