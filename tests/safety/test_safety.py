"""Safety layer: the collision rule, windowing, the cautious controller, SafePolicy and threshold calibration."""

import itertools
import json
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st

from socnav.config import load_config
from socnav.controllers import OrcaController, StraightController
from socnav.envs.rollout import rollout_episodes
from socnav.safety import (
    THRESHOLD_PRESETS,
    CalibrationRun,
    CautiousController,
    FallbackCounter,
    SafePolicy,
    Thresholds,
    ThresholdsError,
    collect_records,
    collision_probability,
    held_fallback,
    load_thresholds,
    nearest_human,
    proxy_scores,
    save_thresholds,
    select_by_proxy,
    select_by_rollouts,
)
from socnav.sim.scenarios import InitialState
from socnav.sim.world import OUTCOME_COLLISION, OUTCOME_GOAL, CrowdWorld


class FakeEstimator:
    """Uncertainty-like output (duck typing): constant values, or the next of a sequence of per-step values."""

    def __init__(self, u_ep_heading=0.0, u_feat=0.0, sequence=None):
        self.u_ep_heading, self.u_feat, self.sequence, self.calls = u_ep_heading, u_feat, sequence, 0

    def __call__(self, obs):
        batch = obs["robot"].shape[0]
        if self.sequence is not None:
            ep, feat = (np.broadcast_to(np.asarray(v, float), (batch,)) for v in self.sequence[self.calls])
        else:
            ep, feat = np.full(batch, self.u_ep_heading), np.full(batch, self.u_feat)
        self.calls += 1
        u_ep = np.column_stack([np.zeros(batch), ep])  # index 0 speed, 1 heading
        return SimpleNamespace(mean_action=np.zeros((batch, 2)), u_ep=u_ep, u_al=np.zeros((batch, 2)), u_feat=feat)


ALWAYS = Thresholds.create(lambda_ep=0.0, lambda_feat=math.inf, lambda_prox=100.0, beta1=0.0)


# ----------------------------------------------------------------------------------------------- the rule

def test_truth_table_of_all_16_combinations():
    thresholds = Thresholds.create(lambda_ep=0.5, lambda_feat=0.5, lambda_prox=1.0, beta1=0.0)
    combos = np.array(list(itertools.product([False, True], repeat=4)))  # c_ep, c_feat, c_prox, c_ap
    u_ep = np.where(combos[:, 0], 0.6, 0.4)
    u_feat = np.where(combos[:, 1], 0.6, 0.4)
    gap = np.where(combos[:, 2], 0.5, 2.0)
    previous = np.where(combos[:, 3], gap + 0.1, gap - 0.1)
    p_col, conditions = collision_probability(u_ep, u_feat, gap, np.zeros(16), previous, thresholds,
                                              return_conditions=True)
    for name, column in zip(("c_ep", "c_feat", "c_prox", "c_ap"), combos.T, strict=True):
        np.testing.assert_array_equal(getattr(conditions, name), column)
    expected = (combos[:, 0] | combos[:, 1]) & combos[:, 2] & combos[:, 3]
    np.testing.assert_array_equal(p_col, expected)
    assert p_col.sum() == 3  # (1,0,1,1), (0,1,1,1), (1,1,1,1)
    np.testing.assert_array_equal(conditions.as_dict()["p_col"], expected)


def test_rule_edges_first_step_equal_gap_no_human_and_strictness():
    t = Thresholds.create(lambda_ep=0.5, lambda_feat=0.5, lambda_prox=1.0, beta1=0.5)
    # First step (previous gap NaN): c_ap is True; equal gaps count as approaching (d(t) <= d(t-1)).
    assert collision_probability(1.0, 0.0, 0.2, 0.0, np.nan, t)
    assert collision_probability(1.0, 0.0, 0.2, 0.0, 0.2, t)
    assert not collision_probability(1.0, 0.0, 0.2, 0.0, 0.1, t)  # moving away: risk averted
    # No human: never fires. Thresholds are strict (>, <).
    assert not collision_probability(1.0, 1.0, np.inf, 0.0, np.nan, t)
    assert not collision_probability(0.5, 0.5, 0.2, 0.0, np.nan, t)
    assert not collision_probability(1.0, 0.0, 1.0, 0.0, np.nan, t)
    # As printed: d + beta1 |dv|; a fast human makes c_prox harder to meet.
    assert collision_probability(1.0, 0.0, 0.5, 0.9, np.nan, t)
    assert not collision_probability(1.0, 0.0, 0.5, 1.1, np.nan, t)
    assert not collision_probability(1.0, 0.0, 0.5, -1.1, np.nan, t)  # |dv|


def test_closing_speed_variant_extrapolates_the_gap():
    t = Thresholds.create(lambda_ep=0.5, lambda_feat=0.5, lambda_prox=1.0, beta1=0.5, proximity="closing-speed")
    assert collision_probability(1.0, 0.0, 1.5, 2.0, np.nan, t)  # 1.5 - 0.5 * 2 = 0.5 < 1
    assert not collision_probability(1.0, 0.0, 0.9, -1.0, np.nan, t)  # receding: 0.9 + 0.5 = 1.4


def staged_world(kind, n_envs=1, **config):
    """Robot (-4, 0) -> (4, 0) facing its goal; one human that ignores the robot, head-on or crossing."""
    cfg = load_config({"scenario": "circle_crossing", "n_humans": 1, "robot_visible": False, **config})
    world = CrowdWorld(cfg, n_envs)
    state = InitialState.empty(1, world.n_slots)
    state.positions[0, 0], state.goals[0, 0] = (-4.0, 0.0), (4.0, 0.0)
    state.radii[0, :2], state.preferred_speeds[0, :2], state.active[0, :2] = 0.3, 1.0, True
    if kind == "head_on":
        state.positions[0, 1], state.goals[0, 1] = (4.0, 0.05), (-4.0, 0.05)
    else:
        state.positions[0, 1], state.goals[0, 1] = (0.0, -4.0), (0.0, 4.0)
    state.personal_space_radii[0, 1], state.cooperation[0, 1] = 0.5, 0.5
    for env in range(n_envs):
        world.load(env, state)
    return cfg, world


def play(world, policy, max_steps=120, on_step=None):
    for _ in range(max_steps):
        actions, _ = policy.predict(world.observe())
        if on_step is not None:
            on_step()
        result = world.step(actions)
        if result.terminated[0] or result.truncated[0]:
            return int(result.outcome[0])
    return -1


def test_nearest_human_is_the_last_real_row_and_closing_speed_matches_the_gap_rate():
    cfg, world = staged_world("crossing", n_humans=3)
    state = InitialState.empty(1, world.n_slots)
    state.positions[0, :4] = [(-4, 0), (3, 3), (0, -3), (5, -5)]
    state.goals[0, :4] = [(4, 0), (3, -3), (0, 3), (-5, 5)]
    state.radii[0, :4], state.preferred_speeds[0, :4], state.active[0, :4] = 0.3, 1.0, True
    world.load(0, state)
    for _ in range(3):
        world.step(np.array([[1.0, 0.0]]))
    obs = world.observe()
    nearest = nearest_human(obs)
    true_gap = np.min(np.linalg.norm(world.positions[0, 1:4] - world.positions[0, 0], axis=1)) - 0.6
    assert nearest.gap[0] == pytest.approx(true_gap, abs=1e-5)
    assert nearest.gap[0] == pytest.approx(obs["humans"][0, 2, 6])
    assert nearest.relative_speed[0] == pytest.approx(np.linalg.norm(obs["humans"][0, 2, 2:4]), abs=1e-6)
    world.step(np.array([[1.0, 0.0]]))  # the velocities just observed carry the next step exactly
    rate = (nearest_human(world.observe()).gap[0] - nearest.gap[0]) / cfg.time_step
    assert -rate == pytest.approx(nearest.closing_speed[0], abs=0.05)

    empty = {"robot": np.zeros((2, 5)), "humans": np.zeros((2, 4, 7)), "humans_mask": np.zeros((2, 4))}
    alone = nearest_human(empty)
    assert np.isinf(alone.gap).all() and not alone.present.any()
    assert not collision_probability(1.0, 1.0, alone.gap, alone.relative_speed, np.nan, ALWAYS).any()


# ----------------------------------------------------------------------------------------------- windowing

def test_uncertainty_is_windowed_per_env_and_reset_at_episode_boundaries():
    values = [(1.0, 10.0), (2.0, 20.0), (3.0, 30.0), (4.0, 40.0), (5.0, 50.0), (6.0, 60.0)]
    estimator = FakeEstimator(sequence=[([v[0], 10 * v[0]], [v[1], 0.0]) for v in values])
    safe = SafePolicy(StraightController(load_config()), estimator, Thresholds.never(), window=4)
    obs = {"robot": np.tile([5.0, 0.0, 0.0, 1.0, 0.3], (2, 1)).astype(np.float32),
           "humans": np.zeros((2, 3, 7), np.float32), "humans_mask": np.zeros((2, 3), np.float32)}
    seen = []
    for step in range(6):
        safe.predict(obs, episode_start=np.array([False, step == 4]))
        seen.append((safe.last_uncertainty["u_ep_heading"].copy(), safe.last_uncertainty["u_feat"].copy()))
        assert not safe.last_fallback.any()
    ep = [s[0] for s in seen]
    assert [e[0] for e in ep] == pytest.approx([1.0, 1.5, 2.0, 2.5, 3.5, 4.5])  # mean of min(4, t) steps
    assert [e[1] for e in ep] == pytest.approx([10.0, 15.0, 20.0, 25.0, 50.0, 55.0])  # env 1 restarted at step 4
    assert seen[3][1][0] == pytest.approx(25.0)
    safe.reset([0])
    safe.estimator = FakeEstimator(7.0, 0.0)
    safe.predict(obs)
    assert safe.last_uncertainty["u_ep_heading"] == pytest.approx([7.0, (50 + 60 + 7) / 3])
    with pytest.raises(ValueError, match="batch"):
        safe.predict({key: value[:1] for key, value in obs.items()})


# ----------------------------------------------------------------------------------------------- cautious

@st.composite
def observations(draw):
    batch, max_humans = draw(st.integers(1, 4)), draw(st.integers(1, 5))
    seed = draw(st.integers(0, 2**31))
    rng = np.random.default_rng(seed)
    robot = np.column_stack([rng.uniform(0, 15, batch), rng.uniform(-np.pi, np.pi, batch), rng.uniform(0, 1.2, batch),
                             rng.uniform(0.3, 1.5, batch), rng.uniform(0.2, 0.4, batch)])
    humans = np.zeros((batch, max_humans, 7))
    mask = np.zeros((batch, max_humans))
    for env in range(batch):
        count = rng.integers(0, max_humans + 1)
        humans[env, :count, 0:2] = rng.uniform(-4, 4, (count, 2))  # overlapping humans included
        humans[env, :count, 2:4] = rng.uniform(-3, 3, (count, 2))
        humans[env, :count, 4] = rng.uniform(0.1, 0.5, count)
        humans[env, :count, 5] = humans[env, :count, 4] + robot[env, 4]
        humans[env, :count, 6] = np.linalg.norm(humans[env, :count, 0:2], axis=1) - humans[env, :count, 5]
        mask[env, :count] = 1.0
    if draw(st.booleans()):  # observation noise: noisy robot fields and radii too
        robot += rng.normal(0, 1.0, robot.shape)
        humans[mask > 0] += rng.normal(0, 1.0, humans[mask > 0].shape)
    return {"robot": robot.astype(np.float32), "humans": humans.astype(np.float32),
            "humans_mask": mask.astype(np.float32)}


@given(obs=observations())
def test_cautious_actions_stay_within_the_limits(obs):
    controller = CautiousController(load_config())
    actions, state = controller.predict(obs)
    assert state is None and actions.shape == (obs["robot"].shape[0], 2)
    assert np.isfinite(actions).all() and (np.abs(actions) <= 1.0).all()
    single, _ = controller.predict({key: value[0] for key, value in obs.items()})
    np.testing.assert_allclose(single, actions[0], atol=1e-6)


@pytest.mark.parametrize("kind", ["head_on", "crossing"])
def test_cautious_controller_avoids_the_staged_collision_of_straight(kind):
    cfg, world = staged_world(kind)
    assert play(world, StraightController(cfg)) == OUTCOME_COLLISION
    cfg, world = staged_world(kind)
    assert play(world, CautiousController(cfg)) == OUTCOME_GOAL
    # the inflated radius (x1.5 of the observed 0.3 m, plus the 0.1 m margin) keeps the robot farther away
    assert world.min_gap[0] > 0.2
    cfg, world = staged_world(kind)
    assert play(world, OrcaController(cfg)) == OUTCOME_GOAL
    assert world.min_gap[0] < 0.15


def test_cautious_scales_the_observed_human_radius():
    cfg = load_config()
    obs = {"robot": np.array([[5.0, 0.0, 0.0, 1.0, 0.3]], np.float32),
           "humans": np.array([[[1.2, 0.0, 0.0, 0.0, 0.3, 0.6, 0.6]]], np.float32),
           "humans_mask": np.ones((1, 1), np.float32)}
    inflated = CautiousController(cfg, safety_margin=0.0).desired_velocity(obs)
    big = {**obs, "humans": obs["humans"].copy()}
    big["humans"][0, 0, 4] = 0.45
    np.testing.assert_allclose(OrcaController(cfg, safety_margin=0.0).desired_velocity(big), inflated)


# ----------------------------------------------------------------------------------------------- SafePolicy

@pytest.mark.parametrize("kind", ["head_on", "crossing"])
def test_safe_policy_with_a_firing_rule_avoids_the_staged_collision(kind):
    cfg, world = staged_world(kind)
    safe = SafePolicy(StraightController(cfg), FakeEstimator(u_ep_heading=1.0), ALWAYS, cfg)
    fallbacks = []
    outcome = play(world, safe, on_step=lambda: fallbacks.append(bool(safe.last_fallback[0])))
    assert outcome == OUTCOME_GOAL
    assert any(fallbacks) and not all(fallbacks)  # the policy acts again once the robot moves away
    assert safe.episode_fallbacks[0] == sum(fallbacks)
    assert safe.last_conditions is not None


def test_held_fallback_by_hand():
    fires = np.array([1, 0, 0, 0, 1, 0, 0, 1, 0], dtype=bool)
    for hold, expected in ((0, fires), (2, [1, 1, 1, 0, 1, 1, 1, 1, 1]), (3, [1, 1, 1, 1, 1, 1, 1, 1, 1])):
        steps_left, drove = np.zeros(1, dtype=np.int64), []
        for fire in fires:
            fallback, steps_left = held_fallback(np.array([fire]), steps_left, hold)
            drove.append(bool(fallback[0]))
        assert drove == list(np.asarray(expected, dtype=bool)), hold


@pytest.mark.parametrize("bad", [-1, 1001, 2.5, True, "2"])
def test_hold_steps_is_a_whole_number_of_steps(bad):
    with pytest.raises(ThresholdsError, match="hold_steps"):
        Thresholds.create(Thresholds.preset("mc").model_dump(), hold_steps=bad)
    assert Thresholds.preset("mc").hold_steps == 0  # the paper's per-step rule by default


@pytest.mark.parametrize("hold", [1, 3])
def test_safe_policy_holds_the_fallback_for_hold_steps_after_the_rule_last_fired(hold):
    cfg, world = staged_world("head_on")
    thresholds = ALWAYS.model_copy(update={"hold_steps": hold})
    safe = SafePolicy(StraightController(cfg), FakeEstimator(u_ep_heading=1.0), thresholds, cfg)
    fired, drove = [], []
    play(world, safe, on_step=lambda: (fired.append(bool(safe.last_conditions.p_col[0])),
                                       drove.append(bool(safe.last_fallback[0]))))
    # the fallback drives at step t iff the rule fired at one of the steps t - hold ... t
    expected = [any(fired[max(0, t - hold): t + 1]) for t in range(len(fired))]
    assert drove == expected
    assert any(d and not f for d, f in zip(drove, fired, strict=True))  # some steps were held, not fired
    assert safe.episode_fallbacks[0] == sum(drove)
    # a new episode ends the hold: the rule cannot fire without a human (gap inf), so nothing drives
    safe.reset()
    empty = {"robot": np.array([[4.0, 0.0, 0.0, 1.0, 0.3]], np.float32),
             "humans": np.zeros((1, 1, 7), np.float32), "humans_mask": np.zeros((1, 1), np.float32)}
    safe.predict(empty)
    assert not safe.last_fallback[0]


def test_safe_policy_with_paper_thresholds_and_low_uncertainty_is_the_plain_policy_here():
    cfg, world = staged_world("head_on")
    safe = SafePolicy(StraightController(cfg), FakeEstimator(0.0, 0.0), "mc", cfg)
    assert play(world, safe) == OUTCOME_COLLISION


def test_never_firing_safe_policy_gives_the_plain_policys_episodes():
    cfg = load_config({"scenario": "circle_crossing", "n_humans": 3, "robot_visible": False})
    plain = rollout_episodes(StraightController(cfg), cfg, n_episodes=6, seed=11, n_envs=3)
    safe = SafePolicy(StraightController(cfg), FakeEstimator(10.0, 10.0), Thresholds.never(), cfg)
    wrapped = rollout_episodes(safe, cfg, n_episodes=6, seed=11, n_envs=3)
    pd.testing.assert_frame_equal(plain, wrapped)
    assert (plain["outcome"] == "collision").any()
    assert safe.episode_fallbacks.sum() == 0


# ----------------------------------------------------------------------------------------------- calibration

def synthetic_records(spoilers=0):
    """Known optimum: collisions flagged by u_ep in (0.05, 0.1] or u_feat in (0.2, 0.3] near the human; the
    unperturbed steps have u_ep <= 0.02 and u_feat <= 0.1. `spoilers` unperturbed close approaching steps have
    u_ep = 0.2 (so flagging the u_ep collisions costs false activations)."""
    rng = np.random.default_rng(0)
    rows = []

    def episode(eid, perturbed, n, collided, ep_hi=None, feat_hi=None, spoil=0):
        gap = np.linspace(5.0, 0.1, n)
        ep, feat = rng.uniform(0, 0.02, n), rng.uniform(0, 0.1, n)
        if ep_hi is not None:
            ep[-4:] = rng.uniform(*ep_hi, 4)
        if feat_hi is not None:
            feat[-4:] = rng.uniform(*feat_hi, 4)
        if spoil:
            ep[-spoil:] = 0.2
        for step in range(n):
            rows.append({"episode": eid, "step": step, "perturbed": perturbed, "u_ep_heading": ep[step],
                         "u_feat": feat[step], "gap": gap[step], "relative_speed": 0.5,
                         "previous_gap": gap[step - 1] if step else np.nan, "collided": collided,
                         "collision_step": n - 1 if collided else np.nan})

    for k in range(20):
        episode(k, False, 40, False, spoil=spoilers if k == 0 else 0)
    for k in range(5):
        episode(100 + k, True, 30, True, ep_hi=(0.05, 0.1))
        episode(200 + k, True, 30, True, feat_hi=(0.2, 0.3))
        episode(300 + k, True, 30, False)
    return pd.DataFrame(rows)


def test_calibration_finds_the_known_optimum():
    records = synthetic_records()
    result = select_by_proxy(records, false_activation_budget=0.05)
    t = result.thresholds
    assert result.prevented_fraction == 1.0 and result.n_collisions == 10
    assert result.false_activation_rate <= 0.05
    # Known optimum under the documented tie-break (no false activation, then the least eager rule): each
    # threshold just below the smallest per-episode window maximum of the collisions it must flag.
    last4 = records[records["collided"] & (records["step"] >= records["collision_step"] - 3)]
    ep_upper = last4[last4["episode"] < 200].groupby("episode")["u_ep_heading"].max().min()
    feat_upper = last4[last4["episode"] >= 200].groupby("episode")["u_feat"].max().min()
    assert result.false_activation_rate == 0.0
    assert ep_upper - 0.01 < t.lambda_ep < ep_upper and feat_upper - 0.02 < t.lambda_feat < feat_upper
    assert ep_upper > 0.05 and feat_upper > 0.2
    score = proxy_scores(records, t)  # the vectorised search agrees with the rule itself
    assert score["prevented_fraction"] == result.prevented_fraction
    assert score["false_activation_rate"] == pytest.approx(result.false_activation_rate)
    assert select_by_proxy(records).thresholds == t  # deterministic
    assert not result.frontier.empty


def test_calibration_respects_the_false_activation_budget():
    records = synthetic_records(spoilers=4)  # 4 of 800 unperturbed steps
    tight = select_by_proxy(records, false_activation_budget=0.0)
    assert tight.false_activation_rate == 0.0 and tight.prevented_fraction == 0.5
    assert proxy_scores(records, tight.thresholds)["false_activation_rate"] == 0.0
    loose = select_by_proxy(records, false_activation_budget=0.01)
    assert loose.prevented_fraction == 1.0 and 0 < loose.false_activation_rate <= 0.01
    explicit = select_by_proxy(records, grid={"lambda_ep": [0.03, math.inf], "lambda_feat": [0.15],
                                              "lambda_prox": [3.0], "beta1": [0.5]}, false_activation_budget=0.01)
    assert explicit.thresholds.lambda_ep == 0.03 and explicit.thresholds.lambda_prox == 3.0
    with pytest.raises(ValueError, match="unknown grid keys"):
        select_by_proxy(records, grid={"lambda": [1.0]})
    with pytest.raises(ValueError, match="no collisions"):
        select_by_proxy(records[~records["collided"]])


def test_lead_demands_that_the_rule_fire_before_the_last_steps():
    records = synthetic_records()
    # u_ep flags collisions 100..104 only through their last 4 steps; move the spike to the collision step alone.
    last = records["collided"] & (records["step"] == records["collision_step"])
    early = records["collided"] & (records["step"] < records["collision_step"])
    records.loc[early & (records["episode"] < 200), "u_ep_heading"] = 0.0
    records.loc[last & (records["episode"] < 200), "u_ep_heading"] = 0.09
    rule = Thresholds.create(lambda_ep=0.05, lambda_feat=math.inf, lambda_prox=100.0, beta1=0.0)
    assert proxy_scores(records, rule, lead=0)["prevented_fraction"] == 0.5   # 5 of 10 at the contact step
    assert proxy_scores(records, rule, lead=1)["prevented_fraction"] == 0.0   # too late with a lead of 1
    # with no false activation allowed, only the u_feat collisions (flagged earlier) can be caught
    assert select_by_proxy(records, false_activation_budget=0.0, lead=1).prevented_fraction == 0.5
    assert select_by_proxy(records, false_activation_budget=0.0, lead=0).prevented_fraction == 1.0
    with pytest.raises(ValueError, match=r"lead must be in \[0, lookback - 1\] = \[0, 3\]"):
        select_by_proxy(records, lead=4)


def typed_records():
    """Two perturbation types and a budget that affords one uncertainty condition: u_ep flags all 8 collisions of
    type a and none of type b; u_feat flags 4 of type a and both of type b (hand-built, so the optimum is known).
    Unperturbed episodes 0 and 1 end with 4 steps of high u_ep and of high u_feat, approaching like the
    collisions: each condition costs at least 1 of 800 steps (the last, if c_prox is tightened to it)."""
    rng = np.random.default_rng(1)
    rows = []

    def episode(eid, perturbed, collided, group, ep_high=False, feat_high=False):
        n = 40
        gap = np.linspace(5.0, 0.1, n)
        ep, feat = rng.uniform(0, 0.02, n), rng.uniform(0, 0.1, n)
        if ep_high:
            ep[-4:] = 0.3
        if feat_high:
            feat[-4:] = 0.6
        for step in range(n):
            rows.append({"episode": eid, "step": step, "perturbed": perturbed, "u_ep_heading": ep[step],
                         "u_feat": feat[step], "gap": gap[step], "relative_speed": 0.5,
                         "previous_gap": gap[step - 1] if step else np.nan, "collided": collided,
                         "collision_step": n - 1 if collided else np.nan, "group": group})

    for k in range(20):
        episode(k, False, False, "", ep_high=k == 0, feat_high=k == 1)
    for k in range(8):
        episode(100 + k, True, True, "a", ep_high=True, feat_high=k < 4)
    for k in range(2):
        episode(200 + k, True, True, "b", feat_high=True)
    return pd.DataFrame(rows)


def test_calibration_maximises_the_worst_perturbation_type():
    records = typed_records()
    budget = 1 / 800
    result = select_by_proxy(records, false_activation_budget=budget)
    # u_feat: type a 4/8, type b 2/2 (worst 0.5, mean 0.75); u_ep: 8/8 and 0/2 (worst 0) -- u_feat wins
    assert math.isinf(result.thresholds.lambda_ep) and result.thresholds.lambda_feat < 0.6
    assert result.worst_type_fraction == 0.5 and result.prevented_fraction == 0.75
    score = proxy_scores(records, result.thresholds)
    assert score["worst_type_fraction"] == 0.5 and score["prevented_fraction"] == 0.75
    assert score["false_activation_rate"] <= budget
    # the same records without types: pooled counts prefer u_ep (8 of 10 collisions against 6 of 10)
    pooled = select_by_proxy(records.drop(columns="group"), false_activation_budget=budget)
    assert math.isinf(pooled.thresholds.lambda_feat) and pooled.thresholds.lambda_ep < 0.3
    assert pooled.prevented_fraction == 0.8 and pooled.worst_type_fraction == 0.8


def test_select_by_rollouts_ranks_the_worst_type_first(monkeypatch):
    from socnav.safety.calibration import rollout_selection

    # measured collisions per candidate (None = the plain policy): candidate 0 has the higher mean, 1 the
    # higher worst type, 2 the same worst type as 1 with a lower mean
    measured = {None: {"a": 10, "b": 4}, 0: {"a": 0, "b": 4}, 1: {"a": 6, "b": 2}, 2: {"a": 8, "b": 2}}
    candidates = [Thresholds.create(lambda_ep=x, lambda_feat=math.inf, lambda_prox=1.0, beta1=0.0)
                  for x in (0.1, 0.2, 0.3)]

    def fake_scores(thresholds, *args, **kwargs):
        key = None if thresholds is None else candidates.index(thresholds)
        return {"collisions": measured[key], "false_activation_rate": 0.01, "false_activation_se": 0.0,
                "false_activation_steps": 10, "unperturbed_steps": 100_000}

    monkeypatch.setattr(rollout_selection, "rollout_scores", fake_scores)
    runs = [CalibrationRun(None, True, 1, 0, "a"), CalibrationRun(None, True, 1, 1, "b"),
            CalibrationRun(None, False, 1, 2)]
    chosen, table = select_by_rollouts(candidates, None, None, runs, false_activation_budget=0.05)
    assert table["prevented_worst"].tolist() == pytest.approx([0.0, 0.4, 0.2])
    assert table["prevented_fraction"].tolist() == pytest.approx([0.5, 0.45, 0.35])
    assert chosen == candidates[1] and table["chosen"].tolist() == [False, True, False]


def test_select_by_rollouts_maximises_measured_prevention_within_the_budget():
    risky = load_config({"scenario": "circle_crossing", "n_humans": 3, "robot_visible": False})
    runs = [CalibrationRun(risky, True, 6, 11), CalibrationRun(risky, False, 4, 40)]
    policy, estimator = StraightController(risky), FakeEstimator(1.0, 0.0)
    candidates = [Thresholds.never(), ALWAYS]
    chosen, table = select_by_rollouts(candidates, policy, estimator, runs, false_activation_budget=1.0, n_envs=3)
    # independent truth: the same episodes played directly, plain and with the firing rule
    plain = rollout_episodes(policy, risky, 6, seed=11, n_envs=3)
    safe = SafePolicy(policy, estimator, ALWAYS, risky)
    guarded = rollout_episodes(safe, risky, 6, seed=11, n_envs=3)
    n_plain, n_safe = (plain["outcome"] == "collision").sum(), (guarded["outcome"] == "collision").sum()
    assert n_plain > n_safe
    assert chosen == ALWAYS and table["chosen"].tolist() == [False, True]
    assert table.loc[1, "prevented_fraction"] == pytest.approx((n_plain - n_safe) / n_plain)
    assert table.loc[0, "prevented_fraction"] == 0.0 and table.loc[0, "false_activation_rate"] == 0.0
    assert table.loc[1, "false_activation_rate"] > 0.0
    # two perturbation types: the score is the mean of the per-type fractions, not the pooled fraction
    typed = [CalibrationRun(risky, True, 6, 11, "a"), CalibrationRun(risky, True, 3, 70, "b"), runs[1]]
    _, table = select_by_rollouts(candidates, policy, estimator, typed, false_activation_budget=1.0, n_envs=3)
    plain_b = rollout_episodes(policy, risky, 3, seed=70, n_envs=3)
    guarded_b = rollout_episodes(SafePolicy(policy, estimator, ALWAYS, risky), risky, 3, seed=70, n_envs=3)
    nb_plain, nb_safe = (plain_b["outcome"] == "collision").sum(), (guarded_b["outcome"] == "collision").sum()
    assert nb_plain > 0
    expected = ((n_plain - n_safe) / n_plain + (nb_plain - nb_safe) / nb_plain) / 2
    assert table.loc[1, "prevented_fraction"] == pytest.approx(expected)
    assert table.loc[1, "prevented_b"] == pytest.approx((nb_plain - nb_safe) / nb_plain)
    # a budget the firing rule exceeds in the unperturbed run: the never-firing candidate is all that is left
    chosen, table = select_by_rollouts(candidates, policy, estimator, runs, false_activation_budget=0.0, n_envs=3)
    assert chosen == Thresholds.never() and table["chosen"].tolist() == [True, False]
    with pytest.raises(ValueError, match="both perturbed"):
        select_by_rollouts(candidates, policy, estimator, runs[:1])


def test_false_activation_standard_error_is_the_ratio_estimators():
    from socnav.safety.calibration import ratio_and_standard_error

    counts, lengths = np.array([2.0, 0.0, 5.0, 1.0]), np.array([20.0, 10.0, 30.0, 20.0])
    rate, se = ratio_and_standard_error(counts, lengths)
    assert rate == pytest.approx(8 / 80)
    # hand: residuals c - 0.1 n = 0, -1, 2, -1; sum of squares 6; SE = sqrt(6 / (4 * 3)) / 20
    assert se == pytest.approx(math.sqrt(6 / 12) / 20)
    assert ratio_and_standard_error(np.array([3.0]), np.array([10.0])) == (0.3, math.inf)
    # the bound matters: a rate just under the budget, but uncertain, is not accepted at 95 %
    risky = load_config({"scenario": "circle_crossing", "n_humans": 3, "robot_visible": False})
    runs = [CalibrationRun(risky, True, 3, 11), CalibrationRun(risky, False, 4, 40)]
    policy, estimator = StraightController(risky), FakeEstimator(1.0, 0.0)
    _, table = select_by_rollouts([ALWAYS], policy, estimator, runs, false_activation_budget=1.0, n_envs=3)
    rate, upper = table.loc[0, "false_activation_rate"], table.loc[0, "false_activation_upper"]
    assert 0 < rate < upper
    chosen, _ = select_by_rollouts([ALWAYS], policy, estimator, runs, false_activation_budget=(rate + upper) / 2,
                                   n_envs=3)
    assert chosen == Thresholds.never()
    chosen, _ = select_by_rollouts([ALWAYS], policy, estimator, runs, false_activation_budget=(rate + upper) / 2,
                                   n_envs=3, confidence=0.5)
    assert chosen == ALWAYS


def test_fallback_counter_counts_the_fallback_steps_of_each_episode():
    cfg = load_config({"scenario": "circle_crossing", "n_humans": 3, "robot_visible": False})
    safe = SafePolicy(StraightController(cfg), FakeEstimator(1.0, 0.0), ALWAYS, cfg)
    counter = FallbackCounter(safe)
    records = rollout_episodes(safe, cfg, 4, seed=3, n_envs=2, observer=counter)
    counts = counter.per_episode(records["episode"])
    assert all(0 < c <= n for c, n in zip(counts, records["length"], strict=True))
    assert counter.per_episode([99]) == [0]


def test_collect_records_from_rollouts():
    cfg = load_config({"scenario": "position_swap", "robot_visible": False})
    records = collect_records(StraightController(cfg), FakeEstimator(0.01, 0.2), cfg, n_episodes=3, n_envs=2)
    assert set(records["episode"]) == {0, 1, 2} and not records["perturbed"].any()
    for _, episode in records.groupby("episode"):
        assert list(episode["step"]) == list(range(len(episode)))
        assert np.isnan(episode["previous_gap"].iloc[0])
        np.testing.assert_allclose(episode["previous_gap"].iloc[1:], episode["gap"].iloc[:-1])
        if episode["collided"].iloc[0]:
            assert episode["collision_step"].iloc[0] == episode["step"].max()
    assert records["collided"].any()
    np.testing.assert_allclose(records["u_feat"], 0.2)


# ----------------------------------------------------------------------------------------------- threshold files

@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_threshold_file_round_trip(tmp_path, suffix):
    for thresholds in (Thresholds.preset("ensemble"), Thresholds.never(),
                       Thresholds.create(lambda_ep=0.1, lambda_feat=0.2, lambda_prox=1.0, beta1=0.3,
                                         proximity="closing-speed")):
        path = save_thresholds(thresholds, tmp_path / f"t{suffix}")
        assert load_thresholds(path) == thresholds
        assert load_thresholds(str(path)) == thresholds
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write leaves no temporary behind


def test_presets_and_nested_files(tmp_path):
    for name, (ep, feat, prox, beta) in THRESHOLD_PRESETS.items():
        t = load_thresholds(name)
        assert (t.lambda_ep, t.lambda_feat, t.lambda_prox, t.beta1) == (ep, feat, prox, beta)
        assert t.proximity == "abs-relative-speed"
    assert load_thresholds("mc").lambda_feat == 0.3 and load_thresholds("ensemble").lambda_feat == 0.0033
    path = tmp_path / "nested.json"
    path.write_text(json.dumps({"thresholds": {"lambda_ep": 1, "lambda_feat": 2, "lambda_prox": 3, "beta1": 4}}))
    assert load_thresholds(path).beta1 == 4.0


def test_bad_thresholds_are_rejected_with_a_clear_message(tmp_path):
    good = {"lambda_ep": 0.1, "lambda_feat": 0.1, "lambda_prox": 1.0, "beta1": 0.5}
    with pytest.raises(ThresholdsError, match=r"lambda_fet: unknown field; allowed fields: lambda_ep, lambda_feat"):
        Thresholds.create({**good, "lambda_fet": 0.3})
    with pytest.raises(ThresholdsError, match="beta1"):
        Thresholds.create({**good, "beta1": -1})
    with pytest.raises(ThresholdsError, match="lambda_ep"):
        Thresholds.create({**good, "lambda_ep": float("nan")})
    with pytest.raises(ThresholdsError, match=r"proximity.*abs-relative-speed"):
        Thresholds.create({**good, "proximity": "speed"})
    with pytest.raises(ThresholdsError, match="missing"):
        Thresholds.create({"lambda_ep": 0.1})
    with pytest.raises(ThresholdsError, match=r"preset.*mc, ensemble"):
        load_thresholds("mcdropout")
    bad = tmp_path / "bad.yaml"
    bad.write_text("lambda_ep: 0.1\nlambda_feat: 0.1\nlambda_prox: 1.0\nbeta: 0.5\n")
    with pytest.raises(ThresholdsError, match=r"beta: unknown field.*bad\.yaml"):
        load_thresholds(bad)
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ThresholdsError, match="mapping"):
        load_thresholds(bad)
    with pytest.raises(ValueError, match="extra"):  # the plain constructor validates too (pydantic error)
        Thresholds(**good, extra=1)


@pytest.mark.parametrize("field", ["lambda_prox", "beta1"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, 1e300])
def test_threshold_distances_and_times_must_be_finite_and_physical(field, bad):
    good = {"lambda_ep": 0.1, "lambda_feat": 0.1, "lambda_prox": 1.0, "beta1": 0.5}
    with pytest.raises(ThresholdsError, match=rf"{field}: Input should be (a finite number|less than or equal)"):
        Thresholds.create({**good, field: bad})
    # inf stays meaningful for the uncertainty thresholds: that condition is off (Thresholds.never)
    assert Thresholds.create({**good, "lambda_ep": math.inf}).lambda_ep == math.inf


def test_threshold_yaml_files_with_non_finite_values_are_refused(tmp_path):
    path = tmp_path / "t.yaml"
    path.write_text("lambda_ep: 0.1\nlambda_feat: 0.1\nlambda_prox: .inf\nbeta1: .nan\n")
    with pytest.raises(ThresholdsError) as error:
        load_thresholds(path)
    assert "lambda_prox" in str(error.value) and "beta1" in str(error.value)


def test_eager_neighbours_fire_in_more_situations_one_parameter_at_a_time():
    from socnav.safety.calibration import eager_neighbours

    closing = Thresholds.create(lambda_ep=0.25, lambda_feat=math.inf, lambda_prox=0.5, beta1=1.0,
                                proximity="closing-speed", sensing="true")
    moves = {tuple(sorted((k, v) for k, v in n.model_dump().items() if v != closing.model_dump()[k]))
             for n in eager_neighbours(closing)}
    # lambda_prox x1.5, beta1 + 0.5 s, lambda_ep x0.75, a hold one step longer; lambda_feat is off (inf), stays off
    assert moves == {(("lambda_prox", 0.75),), (("beta1", 1.5),), (("lambda_ep", 0.1875),),
                     (("hold_steps", 1),)}  # exact in binary
    assert all(n.sensing == "true" and n.proximity == "closing-speed" for n in eager_neighbours(closing))
    # with |dv| added to the gap a larger beta1 fires less: not a neighbour; lambda_prox 0 grows by 0.1 m
    printed = Thresholds.create(lambda_ep=math.inf, lambda_feat=0.3, lambda_prox=0.0, beta1=0.5)
    assert sorted(n.model_dump()["lambda_prox"] for n in eager_neighbours(printed)) == [0.0, 0.0,
                                                                                         pytest.approx(0.1)]
    assert all(n.beta1 == 0.5 for n in eager_neighbours(printed))


def test_refinement_climbs_while_measured_rollouts_improve(monkeypatch):
    from socnav.safety.calibration import refine_by_rollouts, rollout_selection

    start = Thresholds.create(lambda_ep=math.inf, lambda_feat=0.4, lambda_prox=0.5, beta1=0.0)
    wider = start.model_copy(update={"lambda_prox": 0.75})
    widest = start.model_copy(update={"lambda_prox": 1.125})
    # measured collisions of type b (plain: 10): the wider rules prevent more, until the widest exceeds the budget
    collisions = {start: 5, wider: 3, widest: 1}
    rates = {widest: 0.2}

    def fake_scores(thresholds, *args, **kwargs):
        return {"collisions": {"b": collisions.get(thresholds, 6)},
                "false_activation_rate": rates.get(thresholds, 0.01), "false_activation_se": 0.0,
                "false_activation_steps": 10, "unperturbed_steps": 100_000}

    monkeypatch.setattr(rollout_selection, "rollout_scores", fake_scores)
    runs = [CalibrationRun(None, True, 1, 0, "b"), CalibrationRun(None, False, 1, 1)]
    table = pd.DataFrame([{**start.model_dump(), "chosen": True, "candidate": 0}]).assign(stage="proxy")
    chosen, refined = refine_by_rollouts(start, table, {"b": 10}, None, None, runs, 0.05, 4, 4, 0.95,
                                         lambda n: None)
    assert chosen == wider                                        # 70 % prevented; the widest is over budget
    assert refined["chosen"].sum() == 1 and refined.loc[refined["chosen"], "lambda_prox"].item() == 0.75
    assert set(refined["stage"]) == {"proxy", "refine-1", "refine-2"}
    assert refined["candidate"].is_unique
    assert refine_by_rollouts(Thresholds.never(), table, {"b": 10}, None, None, runs, 0.05, 4, 4, 0.95,
                              lambda n: None)[0] == Thresholds.never()
    # a neighbour that only ties (same prevention, lower false activation) does not replace the current rule
    collisions.update({wider: 5})
    rates.update({wider: 0.001})
    chosen, refined = refine_by_rollouts(start, table, {"b": 10}, None, None, runs, 0.05, 4, 4, 0.95,
                                         lambda n: None)
    assert chosen == start and refined.loc[refined["chosen"], "stage"].tolist() == ["proxy"]


def test_calibrate_thresholds_replays_the_plain_policy_once_and_fills_the_bar(monkeypatch):
    from socnav.safety.calibration import calibrate_thresholds, rollout_selection, workflow

    records = typed_records()
    plain_passes = []

    def fake_collect(policy, estimator, config, n, seed=0, perturbed=None, episode_offset=0, progress=None, **kw):
        part = records[records["perturbed"] == bool(perturbed)].drop(columns="group").assign(closing_speed=0.5)
        part["episode"] += episode_offset * 1000
        progress(n)
        return part

    def fake_scores(thresholds, policy, estimator, runs, window=4, n_envs=40, progress=None):
        plain_passes.append(thresholds is None)
        progress(sum(run.n_episodes for run in runs))
        groups = {run.group for run in runs if run.perturbed}
        return {"collisions": {g: 5 if thresholds is None else 2 for g in groups}, "false_activation_rate": 0.0,
                "false_activation_se": 0.0, "false_activation_steps": 0, "unperturbed_steps": 10 ** 6}

    monkeypatch.setattr(workflow, "collect_records", fake_collect)
    for module in (workflow, rollout_selection):  # the plain replay, the candidates' replays
        monkeypatch.setattr(module, "rollout_scores", fake_scores)
    seen = []
    _, report = calibrate_thresholds(None, None, {"scenario": "position_swap"}, 2,
                                     progress=lambda done, total: seen.append((done, total)))
    assert sum(plain_passes) == 1 and len(plain_passes) > 1      # stages 2 and 3 share one plain replay
    assert all(done <= total for done, total in seen) and seen[-1][0] == seen[-1][1]
    frame = pd.DataFrame(report["candidates"])
    assert frame["candidate"].is_unique and frame["chosen"].sum() == 1
    # stage 2 replays every proposed rule with and without a hold; a tie goes to the per-step rule
    proposed = frame[frame["stage"] == "proxy"]
    rules = proposed.drop(columns=["hold_steps", "candidate", "chosen"]).astype(str).apply(tuple, axis=1)
    assert sorted(proposed["hold_steps"]) == sorted([0, 1] * (len(proposed) // 2))
    assert set(rules[proposed["hold_steps"] == 0]) == set(rules[proposed["hold_steps"] == 1])
    assert proposed.loc[proposed["chosen"], "hold_steps"].tolist() in ([0], [])
