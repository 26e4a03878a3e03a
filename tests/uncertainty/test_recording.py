"""Per-step uncertainty records of rollouts: one row per step, windows within episodes, critical steps."""

import numpy as np
import pandas as pd

import socnav
from socnav.controllers import StraightController
from socnav.rl import make_model
from socnav.uncertainty import MCDropoutEstimator
from socnav.uncertainty.recording import UNCERTAINTY_COLUMNS, critical_steps, record_uncertainty

CONFIG = {"scenario": "circle_crossing", "n_humans": 5, "robot_visible": False}


def test_records_every_step_with_windows_restarting_each_episode():
    policy = make_model("odv-ppo-drop", socnav.make_vec_env(CONFIG, n_envs=2), seed=0,
                        overrides={"lstm_hidden_size": 8, "net_arch_pi": (16,), "net_arch_vf": (16,)}).policy
    config = socnav.load_config(CONFIG)
    steps, episodes = record_uncertainty(StraightController(config), MCDropoutEstimator(policy, k=4, seed=1), config,
                                         n_episodes=6, seed=3, n_envs=4)
    assert len(steps) == episodes["length"].sum()
    lengths = steps.groupby("episode")["step"].agg(["min", "max", "count"])
    assert (lengths["min"] == 0).all() and (lengths["max"] + 1 == lengths["count"]).all()
    for name in UNCERTAINTY_COLUMNS:
        expected = steps.groupby("episode")[name].transform(lambda s: s.rolling(4, min_periods=1).mean())
        np.testing.assert_allclose(steps[f"w_{name}"], expected, rtol=1e-9, atol=1e-12)
    finals = steps.groupby("episode").tail(1).set_index("episode")["outcome"]
    assert (finals.sort_index().to_numpy() == episodes.set_index("episode")["outcome"].sort_index().to_numpy()).all()
    assert (steps.groupby("episode")["outcome"].apply(lambda s: (s != "").sum()) == 1).all()


def test_critical_steps_pick_last_step_of_collisions_and_closest_approach_otherwise():
    steps = pd.DataFrame({
        "episode": [0, 0, 0, 1, 1, 1],
        "nearest_gap": [2.0, 0.5, -0.1, 3.0, 0.4, 1.0],
        "w_u_feat": [0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
        "outcome": ["", "", "collision", "", "", "goal"],
    })
    critical = critical_steps(steps)
    assert critical.to_dict("records") == [
        {"episode": 0, "collided": True, "value": 0.3},
        {"episode": 1, "collided": False, "value": 0.5},
    ]
