"""Triggers: hand-computed scores, the registry's errors, spec files, the layer's decisions with a trigger, the
conformal bound's update, the risk model's training, file round trip and refusals, and the threshold proposals."""

from __future__ import annotations

import math
import re

import numpy as np
import pandas as pd
import pytest

from socnav.safety import SafePolicy, Thresholds
from socnav.safety.calibration.trigger_search import collision_labels, threshold_candidates
from socnav.safety.conformal import ConformalShieldTrigger
from socnav.safety.risk_model import (
    GEOMETRY_FEATURES,
    RiskModelTrigger,
    load_risk_model,
    risk_scores,
    save_risk_model,
    train_risk_model,
)
from socnav.safety.rule import nearest_human
from socnav.safety.safe_policy import BRAKE_ACTION
from socnav.safety.triggers import (
    TRIGGERS,
    ScoreTrigger,
    TriggerError,
    TriggerInputs,
    TriggerSpec,
    intended_relative_motion,
    load_safety,
    make_trigger,
    predicted_clearance,
    register_trigger,
    save_trigger_spec,
    time_to_contact,
    trigger_names,
)


def observation(humans: list[tuple[float, float, float, float]], heading: float = 0.0, speed: float = 0.0,
                v_pref: float = 1.0, combined: float = 0.5, max_humans: int = 3) -> dict[str, np.ndarray]:
    """A batch of one observation: humans as (rel x, rel y, rel vx, rel vy), nearest LAST as the env orders them."""
    rows = np.zeros((1, max_humans, 7), dtype=np.float32)
    mask = np.zeros((1, max_humans), dtype=np.float32)
    ordered = sorted(humans, key=lambda h: -math.hypot(h[0], h[1]))
    for index, (x, y, vx, vy) in enumerate(ordered):
        rows[0, index] = (x, y, vx, vy, combined / 2, combined, math.hypot(x, y) - combined)
        mask[0, index] = 1.0
    robot = np.array([[5.0, heading, speed, v_pref, combined / 2]], dtype=np.float32)
    return {"robot": robot, "humans": rows, "humans_mask": mask}


def inputs_for(obs: dict[str, np.ndarray], action: tuple[float, float] = (-1.0, 0.0),
               previous_gap: float = math.nan) -> TriggerInputs:
    zeros = np.zeros(1)
    uncertainty = {key: zeros for key in ("u_ep_speed", "u_ep_heading", "u_al_speed", "u_al_heading", "u_feat")}
    return TriggerInputs(observation=obs, actions=np.array([action], dtype=np.float32), uncertainty=uncertainty,
                         nearest=nearest_human(obs), previous_gap=np.array([previous_gap]), time_step=0.25,
                         max_heading_change=math.pi / 6)


# ------------------------------------------------------------------------------------------- geometry by hand

def test_time_to_contact_by_hand():
    positions = np.array([[3.0, 0.0], [0.3, 0.0], [3.0, 0.0], [0.0, 3.0]])
    velocities = np.array([[-1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    radii = np.full(4, 1.0)
    # head-on from 3 m at 1 m/s with 1 m of radii: 2 s; overlapping: 0; receding: never; passing 3 m aside: never
    np.testing.assert_allclose(time_to_contact(positions, velocities, radii), [2.0, 0.0, np.inf, np.inf])


def test_predicted_clearance_by_hand():
    obs = observation([(2.0, 1.0, -1.0, 0.0)], combined=0.5)
    # a robot at rest (action speed -1 -> v = 0): closest approach at t = 2 s, 1 m away -> 0.5 m of clearance
    assert predicted_clearance(inputs_for(obs), horizon=5.0)[0] == pytest.approx(0.5)
    # within 1 s the human reaches (1, 1) only
    assert predicted_clearance(inputs_for(obs), horizon=1.0)[0] == pytest.approx(math.sqrt(2) - 0.5)
    # no human: infinite clearance
    assert predicted_clearance(inputs_for(observation([])), horizon=1.0)[0] == np.inf


def test_intended_motion_uses_the_action():
    obs = observation([(3.0, 0.0, 0.0, 0.0)], heading=0.0, speed=0.0, v_pref=1.0)
    # full speed ahead (a0 = 1 -> v = v_pref), no turn: the (still) human closes at 1 m/s
    _, velocities, _, _ = intended_relative_motion(inputs_for(obs, action=(1.0, 0.0)))
    np.testing.assert_allclose(velocities[0, 0], [-1.0, 0.0], atol=1e-12)
    # full turn left: the heading changes by pi / 6
    _, velocities, _, _ = intended_relative_motion(inputs_for(obs, action=(1.0, 1.0)))
    np.testing.assert_allclose(velocities[0, 0], [-math.cos(math.pi / 6), -math.sin(math.pi / 6)], atol=1e-7)


def test_analytic_scores_by_hand():
    obs = observation([(3.0, 0.0, -1.0, 0.0)], combined=1.0)
    inputs = inputs_for(obs)  # robot at rest, human 3 m ahead closing at 1 m/s, radii 1 m: contact in 2 s
    ttc = make_trigger(TriggerSpec.create(trigger="time-to-collision", threshold=-2.5))
    assert isinstance(ttc, ScoreTrigger)
    assert ttc.score(inputs)[0] == pytest.approx(-2.0)
    assert ttc.fires(inputs)[0]  # contact sooner than 2.5 s
    assert not make_trigger(TriggerSpec.create(trigger="time-to-collision", threshold=-1.5)).fires(inputs)[0]
    closing = make_trigger(TriggerSpec.create(trigger="closing-gap", threshold=0.0, params={"beta": 0.5}))
    assert isinstance(closing, ScoreTrigger)
    assert closing.score(inputs)[0] == pytest.approx(-(2.0 - 0.5 * 1.0))


# ------------------------------------------------------------------------------------------- registry and specs

def test_unknown_trigger_names_the_closest_and_the_list():
    with pytest.raises(TriggerError, match=r"unknown trigger 'time-to-colision'; did you mean 'time-to-collision'"):
        TriggerSpec.create(trigger="time-to-colision", threshold=0.0)
    with pytest.raises(TriggerError, match="allowed: paper, proximity-only, uncertainty-only, time-to-collision"):
        TriggerSpec.create(trigger="zzz", threshold=0.0)


def test_bad_parameters_and_threshold_name_the_field():
    with pytest.raises(TriggerError, match="horizon"):
        TriggerSpec.create(trigger="time-to-collision", threshold=0.0, params={"horizon": -1})
    with pytest.raises(TriggerError, match=r"unknown_field|extra"):
        TriggerSpec.create(trigger="closing-gap", threshold=0.0, params={"unknown_field": 1})
    with pytest.raises(TriggerError, match="NaN"):
        TriggerSpec.create(trigger="closing-gap", threshold=math.nan)
    with pytest.raises(TriggerError, match="model file"):
        TriggerSpec.create(trigger="risk-model", threshold=0.5).uses_uncertainty  # noqa: B018


def test_spec_file_round_trip_and_rule_files(tmp_path):
    spec = TriggerSpec.create(trigger="conformal", threshold=-0.25, params={"alpha": 0.2}, hold_steps=2)
    path = save_trigger_spec(spec, tmp_path / "conformal.yaml", extra={"budget": 0.05})
    assert load_safety(path) == spec
    assert load_safety(save_trigger_spec(spec, tmp_path / "c.json")) == spec
    # a file without `trigger` (or naming the rule) is the rule's thresholds
    (tmp_path / "rule.yaml").write_text("lambda_ep: 0.1\nlambda_feat: 0.2\nlambda_prox: 0.9\nbeta1: 0.5\n")
    assert load_safety(tmp_path / "rule.yaml") == Thresholds.create(lambda_ep=0.1, lambda_feat=0.2, lambda_prox=0.9,
                                                                    beta1=0.5)
    (tmp_path / "prox.yaml").write_text("trigger: proximity-only\nlambda_ep: 0.1\nlambda_feat: 0.2\n"
                                        "lambda_prox: 0.9\nbeta1: 0.5\n")
    assert load_safety(tmp_path / "prox.yaml").conditions == "proximity-only"
    (tmp_path / "bad.yaml").write_text("trigger: closing-gap\nthreshold: 0\nparams: {beta: -3}\n")
    with pytest.raises(TriggerError, match=r"beta.*bad\.yaml"):
        load_safety(tmp_path / "bad.yaml")


def test_a_new_trigger_is_a_class_and_a_registry_entry():
    from socnav.config import StrictModel

    class _NoParams(StrictModel):
        pass

    class AlwaysRisky(ScoreTrigger):
        name = "test-always"
        Params = _NoParams

        def score(self, inputs: TriggerInputs) -> np.ndarray:
            return np.ones(len(inputs.previous_gap))

    register_trigger(AlwaysRisky)
    try:
        assert "test-always" in trigger_names()
        with pytest.raises(ValueError, match="registered already"):
            register_trigger(AlwaysRisky)
        obs = observation([(3.0, 0.0, -1.0, 0.0)])
        safe = SafePolicy(_FullSpeed(), None, TriggerSpec.create(trigger="test-always", threshold=0.5),
                          fallback="brake")
        actions, _ = safe.predict(obs)
        np.testing.assert_array_equal(actions, BRAKE_ACTION[None])  # it fired: the brake drove
        safe = SafePolicy(_FullSpeed(), None, TriggerSpec.create(trigger="test-always", threshold=1.0))
        actions, _ = safe.predict(obs)
        np.testing.assert_array_equal(actions, [[1.0, 0.0]])  # score 1 is not above 1: the policy drove
    finally:
        del TRIGGERS["test-always"]


class _FullSpeed:
    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return np.tile(np.array([1.0, 0.0], dtype=np.float32), (np.asarray(observation["robot"]).shape[0], 1)), None


def test_safe_policy_fires_where_the_score_exceeds_the_threshold():
    spec = TriggerSpec.create(trigger="time-to-collision", threshold=-1.5)
    safe = SafePolicy(_FullSpeed(), None, spec, n_envs=1)
    # human 3 m ahead at rest (relative velocity -1 m/s), robot driving at 1 m/s towards it and going on, radii
    # 0.5: contact in 2.5 s -> no hand-over
    safe.predict(observation([(3.0, 0.0, -1.0, 0.0)], speed=1.0))
    assert not safe.last_fallback[0]
    assert safe.trigger.last_scores[0] == pytest.approx(-2.5)  # type: ignore[attr-defined]
    # 1.5 m ahead: contact in 1 s -> the cautious controller drives
    safe.predict(observation([(1.5, 0.0, -1.0, 0.0)], speed=1.0))
    assert safe.last_fallback[0]
    assert safe.last_conditions is None  # only the rule has conditions


def test_estimator_required_only_for_uncertainty():
    with pytest.raises(ValueError, match="read it"):
        SafePolicy(_FullSpeed(), None, Thresholds.preset("mc"))
    with pytest.raises(ValueError, match="fallback 'stop'; allowed: cautious, brake"):
        SafePolicy(_FullSpeed(), None, TriggerSpec.create(trigger="closing-gap", threshold=0.0), fallback="stop")


# ------------------------------------------------------------------------------------------- conformal bound

def test_conformal_bound_tracks_the_forecast_error():
    params = {"horizon_steps": 1, "alpha": 0.25, "learning_rate": 0.1, "initial_quantile": 0.0}
    shield = ConformalShieldTrigger(TriggerSpec.create(trigger="conformal", threshold=0.0, params=params))
    shield.allocate(1)
    shield.reset(np.array([0]))
    # step 0: human 3 m ahead, still, robot at rest: forecast of the gap 0.25 s ahead = 3 - 0.5 = 2.5
    shield.score(inputs_for(observation([(3.0, 0.0, 0.0, 0.0)])))
    assert math.isnan(shield.last_errors[0]) and shield.last_quantile[0] == 0.0
    # step 1: the human jumped to 2 m: error = 2.5 - 1.5 = 1 > q = 0 -> a miss: q = 0 + 0.1 (1 - 0.25)
    shield.score(inputs_for(observation([(2.0, 0.0, 0.0, 0.0)])))
    assert shield.last_errors[0] == pytest.approx(1.0)
    assert shield.last_quantile[0] == pytest.approx(0.075)
    # step 2: it stayed: error 0 <= q -> a hit: q = 0.075 - 0.1 * 0.25
    score = shield.score(inputs_for(observation([(2.0, 0.0, 0.0, 0.0)])))
    assert shield.last_quantile[0] == pytest.approx(0.05)
    # the score is the bound minus the clearance over the horizon (0.25 s: still 1.5 m)
    assert score[0] == pytest.approx(0.05 - 1.5)
    shield.reset(np.array([0]))
    assert shield.score(inputs_for(observation([(2.0, 0.0, 0.0, 0.0)])))[0] == pytest.approx(-1.5)


# ------------------------------------------------------------------------------------------- risk model

def _synthetic(n: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    features = rng.normal(size=(n, len(GEOMETRY_FEATURES)))
    labels = (features[:, 0] < -0.8).astype(np.float64)  # "close": the first feature (the gap) is small
    return features, labels, np.arange(n) // 10


def test_risk_model_learns_and_round_trips(tmp_path):
    features, labels, episodes = _synthetic()
    model = train_risk_model(features, labels, episodes, uncertainty=False, horizon_steps=4, members=3, epochs=40)
    scores = risk_scores(model, features, kappa=1.0)
    from scipy.stats import mannwhitneyu

    positive, negative = scores[labels == 1], scores[labels == 0]
    auroc = mannwhitneyu(positive, negative).statistic / (len(positive) * len(negative))
    assert auroc > 0.95  # the rule behind the labels is one threshold on one feature
    loaded = load_risk_model(save_risk_model(model, tmp_path / "risk.npz"))
    np.testing.assert_array_equal(risk_scores(loaded, features, 1.0), scores)
    spec = TriggerSpec.create(trigger="risk-model", threshold=0.5, model=str(tmp_path / "risk.npz"))
    assert isinstance(make_trigger(spec), RiskModelTrigger) and not spec.uses_uncertainty


def test_risk_model_files_are_checked(tmp_path):
    features, labels, episodes = _synthetic(100)
    model = train_risk_model(features, labels, episodes, uncertainty=False, horizon_steps=4, members=2, epochs=2)
    good = save_risk_model(model, tmp_path / "good.npz")
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, meta=np.array([{"a": 1}], dtype=object))
    with pytest.raises(TriggerError, match=re.escape("pickled.npz")):
        load_risk_model(pickled)
    with np.load(good) as data:
        arrays = {key: data[key] for key in data.files}
    for name, change in [("nan", {"w0_0": arrays["w0_0"] * np.nan}), ("shape", {"w1_1": arrays["w1_1"][:3]}),
                         ("missing", {"mean": None})]:
        broken = {key: value for key, value in {**arrays, **change}.items() if value is not None}
        path = tmp_path / f"{name}.npz"
        np.savez(path, **broken)
        with pytest.raises(TriggerError, match=f"{name}.npz"):
            load_risk_model(path)
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(TriggerError, match=re.escape("text.npz")):
        load_risk_model(tmp_path / "text.npz")


# ------------------------------------------------------------------------------------------- calibration helpers

def test_threshold_candidates_are_order_statistics():
    scores = np.arange(100, dtype=np.float64)  # 0 ... 99
    # 5 % of 100 steps above the threshold: the 95th smallest (94) is the largest that leaves 5 above it
    assert threshold_candidates(scores, 0.05, shares=(1.0,)) == [94.0]
    assert threshold_candidates(scores, 0.1, shares=(0.5, 1.0)) == [94.0, 89.0]
    assert threshold_candidates(np.zeros(0), 0.05) == [math.inf]
    assert (scores > 94.0).mean() == 0.05


def test_collision_labels_mark_the_last_steps_of_collisions():
    records = pd.DataFrame({"step": [0, 1, 2, 3, 0, 1], "length": [4, 4, 4, 4, 2, 2],
                            "collided": [True] * 4 + [False] * 2})
    np.testing.assert_array_equal(collision_labels(records, 2), [0, 0, 1, 1, 0, 0])


def test_the_map_policys_trigger_file_loads_and_fires_when_it_says():
    """socnav/data/pretrained-maps_time-to-collision.yaml (the layer shipped with the map policy, docs/maps.md): a
    time-to-collision trigger that fires where contact
    is less than 2 s away. A robot standing still, a human walking at it at 1 m/s, 0.5 m of radii: from 3 m contact
    is 2.5 s away (no), from 2 m 1.5 s (yes)."""
    from socnav.cli.workflows.demo import MAP_POLICY_LAYER, comparison_file

    spec = load_safety(comparison_file(MAP_POLICY_LAYER))
    assert isinstance(spec, TriggerSpec) and spec.trigger == "time-to-collision" and spec.threshold == -2.0
    trigger = make_trigger(spec)
    trigger.allocate(1)
    for distance, seconds, fires in ((3.0, 2.5, False), (2.0, 1.5, True)):
        inputs = inputs_for(observation([(distance, 0.0, -1.0, 0.0)]))
        np.testing.assert_allclose(trigger.score(inputs), [-seconds], atol=1e-5)
        assert bool(trigger.fires(inputs)[0]) is fires


def test_a_shipped_layer_loads_by_its_name_and_an_unknown_name_lists_them():
    """``--safety pretrained-maps_time-to-collision``: a layer shipped beside a pretrained policy is found by its
    file's stem (an installed package's socnav/data is nowhere a user would look); an unknown name is a clear error
    that lists the presets and the shipped layers."""
    from socnav.safety import ThresholdsError, shipped_layers

    names = shipped_layers()
    shipped = {"pretrained_proximity-only", "pretrained_time-to-collision", "pretrained-maps_time-to-collision"}
    assert shipped <= set(names)
    for name, path in names.items():
        assert load_safety(name) == load_safety(path)
    assert load_safety("pretrained-maps_time-to-collision").threshold == -2.0
    with pytest.raises(ThresholdsError, match=r"thresholds file not found: pretrained-map .*mc, ensemble.*"
                                              r"pretrained-maps_time-to-collision"):
        load_safety("pretrained-map")
