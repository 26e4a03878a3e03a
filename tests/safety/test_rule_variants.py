"""The rule's ablations (``Thresholds.conditions``): proximity-only and uncertainty-only next to eq. (10), in the rule,
SafePolicy, the rollout counter and the calibration (each searching only the parameters it reads)."""

import itertools
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from test_safety import FakeEstimator, typed_records  # a sibling module: pytest puts tests/safety on sys.path

from socnav.config import load_config
from socnav.controllers import StraightController
from socnav.envs.rollout import rollout_episodes
from socnav.safety import (
    FallbackCounter,
    SafePolicy,
    Thresholds,
    ThresholdsError,
    calibrate_budgets,
    calibrate_thresholds,
    collision_probability,
    load_thresholds,
    proxy_scores,
    save_thresholds,
    select_by_proxy,
)
from socnav.safety.calibration import NEUTRAL_VALUES, eager_neighbours

BASE = {"lambda_ep": 0.5, "lambda_feat": 0.5, "lambda_prox": 1.0, "beta1": 0.0}


def _staged(conditions: str):
    """Every combination of (uncertain, close, approaching), staged through the rule's inputs."""
    combos = np.array(list(itertools.product([False, True], repeat=3)))  # c_ep (the uncertainty), c_prox, c_ap
    u_ep = np.where(combos[:, 0], 0.6, 0.4)
    gap = np.where(combos[:, 1], 0.5, 2.0)
    previous = np.where(combos[:, 2], gap + 0.1, gap - 0.1)
    thresholds = Thresholds.create(BASE, conditions=conditions)
    p_col, found = collision_probability(u_ep, np.zeros(8), gap, np.zeros(8), previous, thresholds,
                                         return_conditions=True)
    return combos, p_col, found


@pytest.mark.parametrize("conditions,fires", [
    # (uncertain, close, approaching) -> fires, by hand from the three formulas
    ("paper", {(True, True, True)}),
    ("proximity-only", {(False, True, True), (True, True, True)}),
    ("uncertainty-only", {(True, False, True), (True, True, True)}),
])
def test_each_rule_variant_fires_exactly_where_its_conditions_hold(conditions, fires):
    combos, p_col, found = _staged(conditions)
    for combo, fired in zip(map(tuple, combos.tolist()), p_col, strict=True):
        assert bool(fired) == (combo in fires), (conditions, combo)
    # the individual conditions are evaluated whichever the rule combines
    np.testing.assert_array_equal(found.c_prox, combos[:, 1])
    np.testing.assert_array_equal(found.c_ap, combos[:, 2])
    assert found.conditions == conditions


def test_vetoed_marks_the_hand_overs_the_uncertainty_condition_holds_back():
    combos, _, found = _staged("paper")
    vetoed = {tuple(c) for c, v in zip(combos.tolist(), found.vetoed, strict=True) if v}
    assert vetoed == {(False, True, True)}  # close and approaching, but certain: eq. (10) keeps the policy
    for conditions in ("proximity-only", "uncertainty-only"):  # nothing to veto: no combination of both
        assert not _staged(conditions)[2].vetoed.any()


def test_no_human_uncertainty_only_rule_reads_c_ap_as_documented():
    t = Thresholds.create(BASE, conditions="uncertainty-only")
    # nobody observed: no previous gap, so c_ap holds and the uncertainty alone decides
    assert collision_probability(0.6, 0.0, np.inf, 0.0, np.nan, t)
    assert not collision_probability(0.4, 0.0, np.inf, 0.0, np.nan, t)
    assert not collision_probability(0.6, 0.0, np.inf, 0.0, np.nan, Thresholds.create(BASE, conditions="paper"))


def test_conditions_field_is_validated_and_the_default_is_left_out_of_dumps(tmp_path):
    with pytest.raises(ThresholdsError, match="conditions: Input should be 'paper', 'proximity-only' or "
                                              "'uncertainty-only'"):
        Thresholds.create(BASE, conditions="proximity")
    paper = Thresholds.create(BASE)
    assert paper.conditions == "paper" and "conditions" not in paper.model_dump()
    # a file written with the paper's rule has no `conditions` line
    path = save_thresholds(paper, tmp_path / "paper.yaml")
    assert path.read_text() == ("lambda_ep: 0.5\nlambda_feat: 0.5\nlambda_prox: 1.0\nbeta1: 0.0\n"
                                "proximity: abs-relative-speed\nsensing: perceived\nhold_steps: 0\n")
    for conditions in ("proximity-only", "uncertainty-only"):
        variant = Thresholds.create(BASE, conditions=conditions)
        for suffix in (".yaml", ".json"):
            assert load_thresholds(save_thresholds(variant, tmp_path / f"v{suffix}")) == variant
    assert Thresholds.create(BASE, conditions="proximity-only").uses_uncertainty is False
    assert Thresholds.create(BASE, conditions="uncertainty-only").uses_proximity is False


# ----------------------------------------------------------------------------------------------- SafePolicy

RISKY = {"scenario": "circle_crossing", "n_humans": 3, "robot_visible": False}


def test_proximity_only_hands_over_however_certain_the_policy_is():
    cfg = load_config(RISKY)
    policy = StraightController(cfg)
    thresholds = dict(lambda_ep=0.5, lambda_feat=0.5, lambda_prox=1.5, beta1=0.0)
    certain = FakeEstimator(0.0, 0.0)  # the uncertainty condition never holds
    paper = SafePolicy(policy, certain, Thresholds.create(thresholds), cfg)
    proximity = SafePolicy(policy, None, Thresholds.create(thresholds, conditions="proximity-only"), cfg)
    counters = [FallbackCounter(paper), FallbackCounter(proximity)]
    for safe, counter in zip((paper, proximity), counters, strict=True):
        rollout_episodes(safe, cfg, 4, seed=5, n_envs=2, observer=counter)
    paper_cols, proximity_cols = (c.columns(range(4)) for c in counters)
    assert sum(paper_cols["fallback_steps"]) == 0  # certain: eq. (10) never hands over ...
    # ... and every step its proximity terms fired was vetoed by the uncertainty condition
    assert paper_cols["vetoed_steps"] == paper_cols["proximity_steps"] and sum(paper_cols["proximity_steps"]) > 0
    assert sum(proximity_cols["fallback_steps"]) > 0 and sum(proximity_cols["vetoed_steps"]) == 0
    # other hand-over decisions show as other digests of the same episodes
    assert any(a != b for a, b in zip(paper_cols["fallback_digest"], proximity_cols["fallback_digest"],
                                      strict=True))


def test_safe_policy_without_estimator_only_for_a_rule_that_reads_no_uncertainty():
    cfg = load_config(RISKY)
    with pytest.raises(ValueError, match=r"only a trigger that reads no uncertainty .* conditions='paper'"):
        SafePolicy(StraightController(cfg), None, Thresholds.create(BASE), cfg)
    with pytest.raises(ValueError, match="conditions='uncertainty-only'"):
        SafePolicy(StraightController(cfg), None, Thresholds.create(BASE, conditions="uncertainty-only"), cfg)


def test_fallback_counter_digest_identifies_the_fallback_steps():
    safe = SimpleNamespace(last_fallback=np.array([True, False]), last_conditions=None)
    counter, other = FallbackCounter(safe), FallbackCounter(safe)
    for c in (counter, other):
        c.on_episode_start(np.arange(2))
    counter.on_step(None, None, None, np.array([0, 1]))  # episode 0: fallback at step 0
    other.on_step(None, None, None, np.array([0, 1]))
    safe.last_fallback = np.array([False, False])
    counter.on_step(None, None, None, np.array([0, 1]))
    safe.last_fallback = np.array([True, False])
    other.on_step(None, None, None, np.array([0, 1]))  # episode 0 of `other`: steps 0 and 1
    a, b = counter.columns([0, 1]), other.columns([0, 1])
    assert a["fallback_steps"] == [1, 0] and b["fallback_steps"] == [2, 0]
    assert a["fallback_digest"][0] != b["fallback_digest"][0]
    assert a["fallback_digest"][1] == b["fallback_digest"][1]  # neither handed over in episode 1


# ----------------------------------------------------------------------------------------------- calibration

def test_proximity_only_calibration_searches_only_the_proximity_gate():
    records = typed_records()
    budget = 1 / 800
    result = select_by_proxy(records, false_activation_budget=budget, conditions="proximity-only")
    t = result.thresholds
    assert t.conditions == "proximity-only"
    assert (t.lambda_ep, t.lambda_feat) == (NEUTRAL_VALUES["lambda_ep"], NEUTRAL_VALUES["lambda_feat"])
    # by hand: every episode approaches linearly from 5 m to 0.1 m in 40 steps and all end alike, so no gate
    # separates collisions from the 20 unperturbed episodes: within 1 of 800 unperturbed steps, the gate may open
    # on none of their rows, and nothing is flagged -- the best is the gate that (almost) never opens
    assert result.false_activation_rate <= budget and result.prevented_fraction == 0.0
    assert proxy_scores(records, t)["false_activation_rate"] <= budget
    # with a budget for the last step of every episode, the gate at the contact flags every collision
    loose = select_by_proxy(records, false_activation_budget=20 / 800, conditions="proximity-only")
    assert loose.prevented_fraction == 1.0 and loose.false_activation_rate == pytest.approx(20 / 800)
    with pytest.raises(ValueError, match=r"grid keys \['lambda_ep'\] are not searched for "
                                         r"conditions='proximity-only'.*allowed: lambda_prox, beta1"):
        select_by_proxy(records, grid={"lambda_ep": [0.1]}, conditions="proximity-only")


def test_uncertainty_only_calibration_searches_only_the_uncertainty_thresholds():
    records = typed_records()
    budget = 1 / 800
    result = select_by_proxy(records, false_activation_budget=budget, conditions="uncertainty-only")
    t = result.thresholds
    assert t.conditions == "uncertainty-only"
    assert (t.lambda_prox, t.beta1) == (NEUTRAL_VALUES["lambda_prox"], NEUTRAL_VALUES["beta1"])
    # as for the paper's rule on these records (test_calibration_maximises_the_worst_perturbation_type), u_feat
    # flags 4 of 8 collisions of type a and both of type b; without c_prox each high-u_feat step of the unperturbed
    # episode 1 costs, so a budget of 1 / 800 affords none of them and the rule must not fire there
    assert result.prevented_fraction == 0.0 and result.false_activation_rate == 0.0
    wide = select_by_proxy(records, false_activation_budget=4 / 800, conditions="uncertainty-only")
    assert math.isinf(wide.thresholds.lambda_ep) and wide.thresholds.lambda_feat < 0.6
    assert wide.worst_type_fraction == 0.5 and wide.prevented_fraction == 0.75
    with pytest.raises(ValueError, match="not searched for conditions='uncertainty-only'"):
        select_by_proxy(records, grid={"beta1": [0.5]}, conditions="uncertainty-only")
    with pytest.raises(ValueError, match="unknown rule conditions 'both'; allowed: paper, proximity-only"):
        select_by_proxy(records, conditions="both")


def test_eager_neighbours_move_only_what_the_rule_reads():
    base = Thresholds.create(lambda_ep=0.2, lambda_feat=0.4, lambda_prox=1.0, beta1=0.5, proximity="closing-speed")
    moved = {}
    for variant in ("paper", "proximity-only", "uncertainty-only"):
        rule = base.model_copy(update={"conditions": variant})
        moved[variant] = [{k for k in Thresholds.model_fields if getattr(n, k) != getattr(rule, k)}
                          for n in eager_neighbours(rule)]
    assert moved["paper"] == [{"lambda_prox"}, {"beta1"}, {"lambda_ep"}, {"lambda_feat"}, {"hold_steps"}]
    assert moved["proximity-only"] == [{"lambda_prox"}, {"beta1"}, {"hold_steps"}]
    assert moved["uncertainty-only"] == [{"lambda_ep"}, {"lambda_feat"}, {"hold_steps"}]


def _fake_calibration(monkeypatch, records):
    """calibrate_thresholds' rollouts replaced: records from `records`, replays that count what they play."""
    from socnav.safety.calibration import rollout_selection, workflow

    replayed: list = []

    def fake_collect(policy, estimator, config, n, seed=0, perturbed=None, episode_offset=0, progress=None, **kw):
        part = records[records["perturbed"] == bool(perturbed)].drop(columns="group").assign(closing_speed=0.5)
        part["episode"] += episode_offset * 1000
        progress(n)
        return part

    def fake_scores(thresholds, policy, estimator, runs, window=4, n_envs=40, progress=None):
        replayed.append(thresholds)
        progress(sum(run.n_episodes for run in runs))
        groups = {run.group for run in runs if run.perturbed}
        # a rule's measured score: more eager (larger lambda_prox, longer hold) prevents more and costs more
        eager = 0 if thresholds is None else min(3, int(thresholds.lambda_prox > 1) + thresholds.hold_steps)
        return {"collisions": {g: 5 - eager for g in groups}, "false_activation_rate": 0.01 * eager,
                "false_activation_se": 0.0, "false_activation_steps": 10 * eager, "unperturbed_steps": 10 ** 5}

    monkeypatch.setattr(workflow, "collect_records", fake_collect)
    for module in (workflow, rollout_selection):  # the plain replay, the candidates' replays
        monkeypatch.setattr(module, "rollout_scores", fake_scores)
    return replayed


def test_calibrate_budgets_replays_each_rule_once_and_matches_single_budget_calibrations(monkeypatch):
    records = typed_records()
    replayed = _fake_calibration(monkeypatch, records)
    env = {"scenario": "position_swap"}
    several = calibrate_budgets(None, None, env, 2, [0.05, 0.02, 0.1])
    rules = [t for t in replayed if t is not None]
    assert replayed.count(None) == 1 and len(rules) == len(set(rules))  # one plain pass; no rule replayed twice
    for budget, (thresholds, report) in several.items():
        alone = calibrate_thresholds(None, None, env, 2, budget)
        assert alone[0] == thresholds and alone[1]["prevented_worst"] == report["prevented_worst"]
        assert report["false_activation_budget"] == budget and "conditions" not in report


def test_a_light_budget_proposes_at_the_budget_alone_and_is_not_refined(monkeypatch):
    records = typed_records()
    replayed = _fake_calibration(monkeypatch, records)
    env = {"scenario": "position_swap"}
    results = calibrate_budgets(None, None, env, 2, [0.05, 0.1], light=[0.1])
    light = results[0.1][1]
    assert light["search"] == "light" and light["proxy_budgets"] == [0.1]
    assert set(pd.DataFrame(light["candidates"])["stage"]) == {"proxy"}  # no refinement stage
    full = results[0.05][1]
    assert "search" not in full and full["proxy_budgets"] == [0.05, 0.025]
    # the light budget keeps the c_prox reading the full budget chose; the full one searched both
    assert {row["proximity"] for row in full["candidates"]} == {"abs-relative-speed", "closing-speed"}
    assert {row["proximity"] for row in light["candidates"]} == {results[0.05][0].proximity}
    assert calibrate_thresholds(None, None, env, 2, 0.05)[0] == results[0.05][0]  # the full budget as alone
    with pytest.raises(ValueError, match=r"light must name budgets of \[0.05\]; got \[0.2\]"):
        calibrate_budgets(None, None, env, 2, [0.05], light=[0.2])
    assert replayed  # the fakes did the replays


def test_calibrate_thresholds_per_variant_proposes_only_that_variant(monkeypatch):
    records = typed_records()
    replayed = _fake_calibration(monkeypatch, records)
    for conditions in ("proximity-only", "uncertainty-only"):
        replayed.clear()
        thresholds, report = calibrate_thresholds(None, None, {"scenario": "position_swap"}, 2, 0.05,
                                                  conditions=conditions, sensing="true")
        assert report["conditions"] == conditions and report["sensing"] == "true"
        assert {t.conditions for t in replayed if t is not None} == {conditions}
        assert thresholds.conditions == conditions and thresholds.sensing == "true"
        frame = pd.DataFrame(report["candidates"])
        ignored = [k for k in ("lambda_ep", "lambda_feat", "lambda_prox", "beta1")
                   if k not in {"proximity-only": ("lambda_prox", "beta1"),
                                "uncertainty-only": ("lambda_ep", "lambda_feat")}[conditions]]
        for key in ignored:  # every candidate keeps the neutral value of what the variant ignores
            assert set(frame[key]) == {NEUTRAL_VALUES[key]}
    # uncertainty-only has no c_prox: one proximity reading is searched
    assert report["proximity_searched"] == ["abs-relative-speed"]
