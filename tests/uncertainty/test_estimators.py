"""Tests of socnav.uncertainty: the estimators against direct NumPy computations of the paper's equations.
Tiny seeded networks (LSTM 4, actor/critic 8x8) keep every test fast; dropout masks are fixed by seeding or patching.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import torch as th
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import socnav
from socnav.rl import make_model
from socnav.uncertainty import (
    EnsembleEstimator,
    MCDropoutEstimator,
    Uncertainty,
    WindowedUncertainty,
    feature_uncertainty,
    make_estimator,
)

TINY = {"lstm_hidden_size": 4, "net_arch_pi": (8, 8), "net_arch_vf": (8, 8)}
MAX_HUMANS = 10
K = 6


# ----------------------------------------------------------------------------------------------------------
# Fixtures and independent reference computations
# ----------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def vec_env() -> Iterator[Any]:
    env = socnav.make_vec_env({"scenario": "position_swap", "n_humans": 1}, n_envs=2)
    yield env
    env.close()


def tiny_policy(vec_env: Any, seed: int) -> Any:
    """A tiny odv-ppo-drop policy with seeded (hence known) weights and a tracked feature range."""
    policy = make_model("odv-ppo-drop", vec_env, seed=seed, overrides=TINY).policy
    with th.no_grad():  # a feature range around the eval-mode features of varied observations
        h, _, _ = policy.action_stats(random_obs(64, seed=100 + seed))
        policy.features_extractor.update_feature_range(h - 0.5)
        policy.features_extractor.update_feature_range(h + 0.5)
    return policy


@pytest.fixture(scope="module")
def policy(vec_env: Any) -> Any:
    return tiny_policy(vec_env, seed=0)


@pytest.fixture(scope="module")
def members(vec_env: Any) -> list[Any]:
    return [tiny_policy(vec_env, seed=s) for s in (1, 2, 3)]


def random_obs(batch: int, seed: int = 0, n: list[int] | None = None) -> dict[str, np.ndarray]:
    """Observations with n_b real humans (a prefix of the rows) each; default n_b ~ U{0..MAX_HUMANS}."""
    rng = np.random.default_rng(seed)
    counts = np.asarray(n if n is not None else rng.integers(0, MAX_HUMANS + 1, size=batch))
    humans = np.zeros((batch, MAX_HUMANS, 7), np.float32)
    mask = np.zeros((batch, MAX_HUMANS), np.float32)
    for b, count in enumerate(counts):
        humans[b, :count] = rng.normal(size=(count, 7))
        mask[b, :count] = 1.0
    robot = rng.normal(size=(batch, 5)).astype(np.float32)
    return {"robot": robot, "humans": humans, "humans_mask": mask}


def reference(
    h: np.ndarray, mu: np.ndarray, log_std: np.ndarray, h_min: np.ndarray | None, h_max: np.ndarray | None
) -> dict[str, np.ndarray]:
    """The paper's equations, written out with explicit loops, from samples (K, B, .) in float64."""
    h, mu, log_std = (np.asarray(a, np.float64) for a in (h, mu, log_std))
    n_samples, batch, dims = h.shape
    mean = mu.sum(axis=0) / n_samples
    u_ep = sum((mu[k] - mean) ** 2 for k in range(n_samples)) / n_samples
    u_al = sum(np.exp(log_std[k]) ** 2 for k in range(n_samples)) / n_samples
    h_bar = h.sum(axis=0) / n_samples
    var = sum((h[k] - h_bar) ** 2 for k in range(n_samples)) / n_samples  # (B, D)
    u_feat = np.zeros(batch)
    for b in range(batch):
        if h_min is None:  # ensemble, eq. (9)
            u_feat[b] = var[b].sum() / dims
            continue
        used = [d for d in range(dims) if np.isfinite(h_max[d] - h_min[d]) and h_max[d] > h_min[d]]
        total = sum(var[b, d] for d in used)
        if total > 0:
            u_feat[b] = sum(var[b, d] / total * var[b, d] / ((h_max[d] - h_min[d]) ** 2 / 12) for d in used)
    return {"mean_action": mean, "u_ep": u_ep, "u_al": u_al, "u_feat": u_feat}


def assert_matches(u: Uncertainty, ref: dict[str, np.ndarray], rtol: float = 1e-9, atol: float = 1e-12) -> None:
    for name, expected in ref.items():
        np.testing.assert_allclose(getattr(u, name), expected, rtol=rtol, atol=atol, err_msg=name)


def feature_range(policy: Any) -> tuple[np.ndarray, np.ndarray]:
    return tuple(t.detach().numpy().astype(np.float64) for t in policy.feature_range)  # type: ignore[return-value]


def tile(obs: dict[str, np.ndarray], k: int) -> dict[str, th.Tensor]:
    """K copies of the batch, sample-major (row k * B + b = observation b), written independently of repeat_obs."""
    return {key: th.as_tensor(np.concatenate([value] * k, axis=0)) for key, value in obs.items()}


def mode_snapshot(policy: Any) -> tuple[list[tuple[str, bool]], list[float]]:
    return [(name, m.training) for name, m in policy.named_modules()], [d.p for d in policy.dropout_layers()]


# ----------------------------------------------------------------------------------------------------------
# feature_uncertainty (paper eq. (8)) as a pure function
# ----------------------------------------------------------------------------------------------------------
def test_feature_uncertainty_hand_example() -> None:
    # V = (1, 3), ranges 6 and 12 -> V_max = (3, 12); weights (1/4, 3/4), ratios (1/3, 1/4): 1/12 + 3/16 = 13/48.
    assert feature_uncertainty([1.0, 3.0], [0.0, -2.0], [6.0, 10.0]) == pytest.approx(13 / 48)
    # Batched, and elements with untracked (inf) or zero-width ranges are excluded from both sums.
    got = feature_uncertainty(
        [[1.0, 3.0, 5.0, 7.0], [0.0, 0.0, 2.0, 2.0]],
        [0.0, -2.0, np.inf, 1.0],
        [6.0, 10.0, -np.inf, 1.0],
    )
    np.testing.assert_allclose(got, [13 / 48, 0.0])
    assert feature_uncertainty(np.zeros((3, 2)), [0.0, 0.0], [1.0, 1.0]).tolist() == [0.0, 0.0, 0.0]  # all V = 0
    assert feature_uncertainty([1.0, 2.0], [np.inf, np.inf], [-np.inf, -np.inf]) == 0.0  # nothing tracked
    # V equal to V_max everywhere -> exactly 1.
    assert feature_uncertainty([3.0, 12.0], [0.0, 0.0], [6.0, 12.0]) == pytest.approx(1.0)


@settings(max_examples=60, deadline=None)
@given(
    width=st.lists(st.floats(1e-3, 1e3), min_size=1, max_size=8),
    data=st.data(),
)
def test_feature_uncertainty_in_unit_interval_within_bound(width: list[float], data: st.DataObject) -> None:
    width_a = np.asarray(width)
    frac = np.asarray(data.draw(st.lists(st.floats(0.0, 1.0), min_size=len(width), max_size=len(width))))
    v_max = width_a**2 / 12
    variances = frac * v_max
    u = float(feature_uncertainty(variances, np.zeros_like(width_a), width_a))
    assert 0.0 <= u <= 1.0 + 1e-12
    if variances.sum() > 0:  # a weighted average of the ratios V_d / V_max,d
        assert frac[variances > 0].min() - 1e-12 <= u <= frac.max() + 1e-12


# ----------------------------------------------------------------------------------------------------------
# MC-dropout
# ----------------------------------------------------------------------------------------------------------
def test_mc_dropout_equals_numpy_formulas(policy: Any) -> None:
    obs = random_obs(3, seed=1, n=[2, 0, 6])  # 6 > 4 humans: the fused-LSTM path too
    estimator = MCDropoutEstimator(policy, k=K)
    u = estimator(obs, seed=7)
    # Independent samples: the same seed, the repeated batch, one pass under mc_dropout.
    with th.random.fork_rng(devices=[]):
        th.manual_seed(7)
        with policy.mc_dropout(0.5):
            h, mu, log_std = (t.numpy().reshape(K, 3, -1) for t in policy.action_stats(tile(obs, K)))
    assert_matches(u, reference(h, mu, log_std, *feature_range(policy)))
    assert (u.u_ep[[0, 2]] > 0).all() and (u.u_feat[[0, 2]] > 0).all()  # non-trivial samples
    assert u.u_feat[1] == 0.0  # no humans: h = 0 in every sample


class FixedMasks:
    """Replaces every dropout layer's forward by ``x * m / (1 - p)`` with masks from a fixed bank.

    ``m`` for rows ``offset .. offset + N`` of layer ``i`` is ``U[i][rows] >= p`` with ``U`` drawn once per layer and
    input shape: a batched pass over K * B rows (offset 0) and K sequential passes over B rows (offset k * B) use the
    very same masks for sample k of observation b, whatever order the RNG would have drawn them in.
    """

    def __init__(self, policy: Any, rows: int, monkeypatch: pytest.MonkeyPatch) -> None:
        self.rows, self.offset, self.calls = rows, 0, 0
        self.bank: dict[tuple[int, tuple[int, ...]], th.Tensor] = {}
        self.rng = np.random.default_rng(123)
        for index, layer in enumerate(policy.dropout_layers()):
            monkeypatch.setattr(layer, "forward", self._forward(index, layer))

    def _forward(self, index: int, layer: th.nn.Dropout) -> Callable[[th.Tensor], th.Tensor]:
        def forward(x: th.Tensor) -> th.Tensor:
            if not layer.training or layer.p == 0:
                return x
            self.calls += 1
            key = (index, tuple(x.shape[1:]))
            if key not in self.bank:
                self.bank[key] = th.as_tensor(self.rng.random((self.rows, *x.shape[1:])), dtype=x.dtype)
            keep = (self.bank[key][self.offset : self.offset + x.shape[0]] >= layer.p).to(x.dtype)
            return x * keep / (1 - layer.p)

        return forward


def test_batched_pass_equals_sequential_passes_with_same_masks(
    policy: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    batch = 3
    obs = random_obs(batch, seed=2, n=[3, 1, 2])
    masks = FixedMasks(policy, K * batch, monkeypatch)
    u = MCDropoutEstimator(policy, k=K)(obs)
    assert masks.calls == len(policy.dropout_layers())  # one batched pass, every dropout layer active once
    samples = []
    with policy.mc_dropout(0.5):
        for k in range(K):
            masks.offset = k * batch
            samples.append([t.numpy() for t in policy.action_stats(tile(obs, 1))])
    h, mu, log_std = (np.stack(s) for s in zip(*samples, strict=True))
    assert masks.calls == (K + 1) * len(policy.dropout_layers())
    assert_matches(u, reference(h, mu, log_std, *feature_range(policy)), rtol=1e-5, atol=1e-9)
    assert (u.u_ep > 0).all()  # the K masks really differ


def test_p_test_zero_gives_zero_epistemic_and_feature_uncertainty(policy: Any) -> None:
    obs = random_obs(4, seed=3)
    u = MCDropoutEstimator(policy, k=K, p_test=0.0)(obs)
    assert (u.u_ep == 0).all() and (u.u_feat == 0).all()
    assert (u.u_al > 0).all()
    policy.set_training_mode(False)
    _, mu, log_std = policy.action_stats(obs)
    np.testing.assert_allclose(u.mean_action, mu.numpy(), rtol=1e-6)
    np.testing.assert_allclose(u.u_al, np.exp(2 * log_std.numpy().astype(np.float64)), rtol=1e-6)


def test_seeded_estimator_is_reproducible_and_leaves_global_rng_alone(policy: Any) -> None:
    obs = random_obs(2, seed=4, n=[3, 5])
    state = th.random.get_rng_state()
    first = [MCDropoutEstimator(policy, k=K, seed=11)(obs) for _ in range(2)]
    estimator = MCDropoutEstimator(policy, k=K, seed=11)
    a, b = estimator(obs), estimator(obs)
    assert th.equal(state, th.random.get_rng_state())
    np.testing.assert_array_equal(first[0].u_ep, first[1].u_ep)
    np.testing.assert_array_equal(a.u_ep, first[0].u_ep)
    assert not np.array_equal(a.u_ep, b.u_ep)  # a stream, not the same masks every call
    np.testing.assert_array_equal(estimator(obs, seed=5).u_feat, estimator(obs, seed=5).u_feat)
    estimator.restart()  # back to the start of the stream
    np.testing.assert_array_equal(estimator(obs).u_ep, a.u_ep)
    np.testing.assert_array_equal(estimator(obs).u_ep, b.u_ep)


def test_feature_range_change_is_picked_up(vec_env: Any) -> None:
    policy = tiny_policy(vec_env, seed=4)
    estimator = MCDropoutEstimator(policy, k=K)
    obs = random_obs(2, seed=10, n=[3, 2])
    before = estimator(obs, seed=1).u_feat
    h, _, _ = estimator.samples(obs, seed=1)
    variances = h.double().var(dim=0, unbiased=False).numpy()
    policy.features_extractor.update_feature_range(th.full((4,), 50.0))  # widen the range in place
    after = estimator(obs, seed=1).u_feat
    np.testing.assert_allclose(after, feature_uncertainty(variances, *feature_range(policy)), rtol=1e-9)
    assert (after < before).all()


def test_single_observation_and_tensor_input(policy: Any) -> None:
    obs = random_obs(1, seed=5, n=[2])
    single = {key: value[0] for key, value in obs.items()}
    u1 = MCDropoutEstimator(policy, k=K)(single, seed=1)
    u2 = MCDropoutEstimator(policy, k=K)({k: th.as_tensor(v) for k, v in obs.items()}, seed=1)
    assert u1.batch_size == 1 and u1.mean_action.shape == (1, 2) and u1.mean_action.dtype == np.float64
    np.testing.assert_array_equal(u1.u_ep, u2.u_ep)


# ----------------------------------------------------------------------------------------------------------
# Modes are restored; during estimation only the dropout layers are active
# ----------------------------------------------------------------------------------------------------------
def _record_modes(policy: Any) -> tuple[list[Any], dict[str, set[bool]]]:
    seen: dict[str, set[bool]] = {}
    handles = [
        m.register_forward_pre_hook(lambda mod, _, name=name: seen.setdefault(name, set()).add(mod.training))
        for name, m in policy.named_modules()
        if name
    ]
    return handles, seen


@pytest.mark.parametrize("training", [False, True])
def test_modes_and_dropout_p_restored(policy: Any, members: list[Any], training: bool) -> None:
    policies = [policy, *members]
    for p in policies:
        p.set_training_mode(training)
    policy.dropout_layers()[1].p = 0.3  # an unusual p must survive too
    before = [mode_snapshot(p) for p in policies]
    obs = random_obs(3, seed=6)
    handles, seen = _record_modes(policy)
    try:
        MCDropoutEstimator(policy, k=K)(obs)
    finally:
        for handle in handles:
            handle.remove()
    dropout_names = {n for n, m in policy.named_modules() if isinstance(m, th.nn.Dropout)}
    assert seen and all(modes == ({True} if n in dropout_names else {False}) for n, modes in seen.items())
    EnsembleEstimator(members)(obs)
    EnsembleEstimator(members, stacked=False)(obs)
    assert [mode_snapshot(p) for p in policies] == before
    policy.dropout_layers()[1].p = policy.dropout_p
    for p in policies:
        p.set_training_mode(False)


# ----------------------------------------------------------------------------------------------------------
# Deep ensemble
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("stacked", [True, False])
def test_ensemble_equals_numpy_formulas(members: list[Any], stacked: bool) -> None:
    obs = random_obs(4, seed=7, n=[0, 2, 7, 4])  # 7 > 4 humans: the stacked path's written-out LSTM
    estimator = EnsembleEstimator(members, stacked=stacked)
    assert estimator.stacked is stacked
    u = estimator(obs)
    samples = []
    for member in members:
        member.set_training_mode(False)
        samples.append([t.numpy() for t in member.action_stats(obs)])
    h, mu, log_std = (np.stack(s) for s in zip(*samples, strict=True))
    assert_matches(u, reference(h, mu, log_std, None, None), rtol=1e-4, atol=1e-9)
    assert (u.u_ep > 0).all()


@pytest.mark.parametrize("stacked", [True, False])
def test_ensemble_of_identical_copies_has_zero_epistemic(policy: Any, stacked: bool) -> None:
    copies = [policy, copy.deepcopy(policy), copy.deepcopy(policy)]
    u = EnsembleEstimator(copies, stacked=stacked)(random_obs(5, seed=8))
    np.testing.assert_allclose(u.u_ep, 0.0, atol=1e-15)
    np.testing.assert_allclose(u.u_feat, 0.0, atol=1e-15)
    assert (u.u_al > 0).all()


def test_ensemble_refresh_picks_up_new_weights(members: list[Any]) -> None:
    clones = [copy.deepcopy(m) for m in members]
    estimator = EnsembleEstimator(clones)
    obs = random_obs(2, seed=9, n=[1, 3])
    before = estimator(obs)
    with th.no_grad():
        clones[0].action_net.bias.add_(1.0)
    assert np.array_equal(estimator(obs).mean_action, before.mean_action)  # a snapshot ...
    estimator.refresh()
    np.testing.assert_allclose(estimator(obs).mean_action, before.mean_action + 1 / 3, rtol=1e-5)  # ... refreshed


# ----------------------------------------------------------------------------------------------------------
# Windowing
# ----------------------------------------------------------------------------------------------------------
def _u(values: list[float]) -> Uncertainty:
    v = np.asarray(values, np.float64)
    return Uncertainty(np.c_[v, -v], np.c_[v, 2 * v], np.c_[3 * v, v], 10 * v)


def test_window_hand_checked() -> None:
    window = WindowedUncertainty(n_envs=2, window=4)
    env0 = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    expected0 = [1.0, 1.5, 2.0, 2.5, 3.5, 4.5]  # mean of the last <= 4 values
    for t, (value, want) in enumerate(zip(env0, expected0, strict=True)):
        out = window.update(_u([value, 100.0 + t]))
        assert out.u_ep[0].tolist() == [want, 2 * want]
        assert out.u_al[0].tolist() == [3 * want, want]
        assert out.u_feat[0] == pytest.approx(10 * want)
        assert out.mean_action[0].tolist() == [value, -value]  # not windowed: the current step's
    assert window.counts.tolist() == [4, 4]
    window.reset([0])  # env 0 starts a new episode
    out = window.update(_u([20.0, 106.0]))
    assert out.u_ep[0, 0] == 20.0 and window.counts.tolist() == [1, 4]
    assert out.u_ep[1, 0] == pytest.approx(np.mean([103.0, 104.0, 105.0, 106.0]))
    out = window.update(_u([30.0, 107.0]))
    assert out.u_ep[0, 0] == 25.0
    window.reset(np.array([False, True]))
    assert window.update(_u([0.0, 1.0])).u_feat[1] == 10.0
    window.reset()
    assert window.counts.tolist() == [0, 0]
    with pytest.raises(ValueError):
        window.update(_u([1.0]))


# ----------------------------------------------------------------------------------------------------------
# Invariants, API
# ----------------------------------------------------------------------------------------------------------
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(batch=st.integers(1, 5), k=st.integers(2, 8), seed=st.integers(0, 2**16), p=st.floats(0.0, 0.9))
def test_mc_invariants(policy: Any, batch: int, k: int, seed: int, p: float) -> None:
    u = MCDropoutEstimator(policy, k=k, p_test=p)(random_obs(batch, seed=seed), seed=seed)
    assert u.mean_action.shape == u.u_ep.shape == u.u_al.shape == (batch, 2) and u.u_feat.shape == (batch,)
    for name in ("mean_action", "u_ep", "u_al", "u_feat"):
        assert getattr(u, name).dtype == np.float64 and np.isfinite(getattr(u, name)).all()
    assert (u.u_ep >= 0).all() and (u.u_al > 0).all() and (u.u_feat >= 0).all()
    assert set(u.as_dict()) == {
        "mean_action_speed", "mean_action_heading", "u_ep_speed", "u_ep_heading", "u_al_speed", "u_al_heading",
        "u_feat",
    }


def test_uncertainty_properties_follow_the_action_order() -> None:
    u = Uncertainty([[0.1, 0.2]], [[1.0, 2.0]], [[3.0, 4.0]], [5.0])  # index 0 = speed, 1 = heading change
    assert (u.u_ep_speed[0], u.u_ep_heading[0], u.u_al_speed[0], u.u_al_heading[0]) == (1.0, 2.0, 3.0, 4.0)
    assert u.as_dict()["mean_action_heading"][0] == 0.2
    with pytest.raises(ValueError):
        Uncertainty(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)), np.zeros(3))


def test_make_estimator(policy: Any, members: list[Any]) -> None:
    mc = make_estimator("mc", policy, k=4)
    assert isinstance(mc, MCDropoutEstimator) and mc.k == 4 and mc.p_test == 0.5
    assert make_estimator("mc", [policy], p_test=0.2).p_test == 0.2
    ens = make_estimator("ensemble", members)
    assert isinstance(ens, EnsembleEstimator) and ens.k == 3
    with pytest.raises(ValueError, match="'mc', 'ensemble'"):
        make_estimator("bootstrap", policy)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        make_estimator("ensemble", members, p_test=0.5)
    with pytest.raises(ValueError):
        MCDropoutEstimator(policy, k=1)
