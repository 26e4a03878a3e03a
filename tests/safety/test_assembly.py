"""`socnav.safety.assembly`: the safety layer assembled from a policy, an estimator and thresholds decides exactly as
the layer built by hand from the same parts (`SafePolicy` over a seeded `MCDropoutEstimator`, or over the ensemble),
and `socnav evaluate --safety` plays that layer; parts that cannot make a layer are refused by name."""

from __future__ import annotations

import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

import socnav
from socnav.cli import app
from socnav.config import load_config
from socnav.envs.rollout import EPISODE_COLUMNS, rollout_episodes
from socnav.rl import make_model
from socnav.rl.persistence import load_policy, training_world
from socnav.safety import FallbackCounter, SafePolicy, Thresholds
from socnav.safety.assembly import (
    SafetyAssemblyError,
    assemble_safe_policy,
    default_estimator_kind,
    has_mc_dropout,
    make_safety_estimator,
)
from socnav.uncertainty import MC_SEED, EnsembleEstimator, MCDropoutEstimator

WORLD = {"scenario": "position_swap", "n_humans": 2, "perturbation": {"heading_noise": 0.8}}
#: A rule that fires often (any uncertainty, a human within 2.5 m), so the fallback's decisions are compared too.
EAGER = Thresholds.create(lambda_ep=0.0, lambda_feat=0.0, lambda_prox=2.5, beta1=0.5)
EPISODES = 4


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    torch.set_num_threads(1)  # as the command line runs: the same float reductions in every rollout compared


@pytest.fixture(scope="module")
def pretrained():
    return load_policy("pretrained")


def _play(safe: SafePolicy, config) -> tuple[pd.DataFrame, list[int]]:
    """Records of EPISODES episodes of `safe` and its fallback steps per episode."""
    counter = FallbackCounter(safe)
    records = rollout_episodes(safe, config, EPISODES, seed=11, n_envs=EPISODES, observer=counter)
    return records, counter.per_episode(records["episode"])


def _untrained(seed: int):
    env = socnav.make_vec_env(WORLD, n_envs=1)
    return make_model("odv-ppo-drop", env, seed=seed).policy


def test_mc_layer_decides_as_the_one_built_by_hand(pretrained):
    config = load_config(WORLD)
    assembled = assemble_safe_policy(pretrained, EAGER, config, estimator="mc", k=4)
    assert isinstance(assembled.estimator, MCDropoutEstimator) and assembled.estimator.k == 4
    # the parts as `socnav evaluate --safety mc` put them together: a private mask stream seeded with MC_SEED
    by_hand = SafePolicy(pretrained, MCDropoutEstimator(pretrained, k=4, seed=MC_SEED), EAGER, config)
    records, fallbacks = _play(assembled, config)
    expected, expected_fallbacks = _play(by_hand, config)
    pd.testing.assert_frame_equal(records, expected)
    assert fallbacks == expected_fallbacks
    assert 0 < sum(fallbacks) < records["length"].sum(), "the fallback never or always drove: nothing compared"


def test_ensemble_layer_decides_as_the_one_built_by_hand():
    config = load_config(WORLD)
    members = [_untrained(seed) for seed in (1, 2, 3)]
    assembled = assemble_safe_policy(members[0], EAGER, config, estimator="ensemble", members=members)
    assert isinstance(assembled.estimator, EnsembleEstimator) and assembled.policy is members[0]
    by_hand = SafePolicy(members[0], EnsembleEstimator(members), EAGER, config)
    records, fallbacks = _play(assembled, config)
    expected, expected_fallbacks = _play(by_hand, config)
    pd.testing.assert_frame_equal(records, expected)
    assert fallbacks == expected_fallbacks and sum(fallbacks) > 0


def test_evaluate_safety_plays_the_assembled_layer(tmp_path, pretrained):
    out = tmp_path / "records.parquet"
    result = CliRunner().invoke(app, ["evaluate", "--model", "pretrained", "--safety", "mc", "--k", "4", "--perturb",
                                      "heading_noise=0.8", "--episodes", str(EPISODES), "--seed", "5",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    world = load_config(training_world(pretrained)[0])
    config = load_config(world, perturbation={**world.perturbation.model_dump(), "heading_noise": 0.8})
    safe = assemble_safe_policy(pretrained, "mc", config, estimator=default_estimator_kind("mc"), k=4)
    counter = FallbackCounter(safe)
    expected = rollout_episodes(safe, config, EPISODES, seed=5, n_envs=32, observer=counter)
    expected = expected[list(EPISODE_COLUMNS)].assign(fallback_steps=counter.per_episode(expected["episode"]))
    pd.testing.assert_frame_equal(pd.read_parquet(out), expected)


def test_default_estimator_follows_the_thresholds_preset():
    assert default_estimator_kind("ensemble") == "ensemble"
    assert default_estimator_kind("mc") == "mc"
    assert default_estimator_kind("runs/calibration/thresholds.yaml") == "mc"


def test_mc_dropout_is_read_from_the_policy_file_else_the_network(pretrained):
    assert has_mc_dropout(pretrained)  # odv-ppo-drop, p_train 0.1 in its file
    untrained = _untrained(0)
    assert has_mc_dropout(untrained)  # no file: its dropout_p, 0.1
    untrained.socnav_metadata = {"algo_config": {"p_train": 0.0}}  # a file saying it was trained without
    assert not has_mc_dropout(untrained)
    assert not has_mc_dropout(make_model("ppo", socnav.make_vec_env(WORLD, n_envs=1), seed=0).policy)


def test_parts_that_make_no_layer_are_refused(pretrained):
    ppo = make_model("ppo", socnav.make_vec_env(WORLD, n_envs=1), seed=0).policy
    with pytest.raises(SafetyAssemblyError, match="'mc' needs a policy trained with dropout"):
        assemble_safe_policy(ppo, "mc", WORLD)
    with pytest.raises(SafetyAssemblyError, match="'bootstrap' is not known; allowed: mc, ensemble"):
        make_safety_estimator("bootstrap", pretrained)
    with pytest.raises(SafetyAssemblyError, match="at least 2 members, got 1"):
        assemble_safe_policy(pretrained, "ensemble", WORLD, estimator="ensemble", members=[pretrained])
    assert issubclass(SafetyAssemblyError, ValueError)
