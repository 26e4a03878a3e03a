"""Tests of the numba ORCA kernel against RVO2 itself (pyrvo), hand-computed social variants, and invariants.

RVO2 computes in float32, so every input fed to both is float32-representable and velocities must agree within 1e-4 m/s.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from _extras import require
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from socnav.sim.orca import default_social_arrays, orca_velocities, orca_velocities_kernel

pyrvo = require("pyrvo")  # the RVO2 oracle (test extra): missing fails the module, never skips it

TOLERANCE = 1e-4  # m/s


# --------------------------------------------------------------------------------------------------------------------
# Helpers: random crowds, RVO2 oracle, our kernel on one environment.
# --------------------------------------------------------------------------------------------------------------------
def _f32(x) -> np.ndarray:
    """Round to float32 so RVO2 sees exactly the numbers we see."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def _random_crowd(rng: np.random.Generator, side: float) -> dict:
    """2-12 agents in a side x side square with random radii, speeds, velocities and preferred velocities."""
    n = int(rng.integers(2, 13))
    max_speeds = _f32(rng.uniform(0.5, 1.5, n))

    def random_vectors(max_norm):
        angle = rng.uniform(0.0, 2.0 * np.pi, n)
        norm = max_norm * rng.uniform(0.0, 1.0, n)
        return _f32(np.stack([np.cos(angle), np.sin(angle)], axis=1) * norm[:, None])

    return dict(
        positions=_f32(rng.uniform(-side / 2, side / 2, (n, 2))),
        velocities=random_vectors(max_speeds),
        radii=_f32(rng.uniform(0.15, 0.4, n)),
        preferred_velocities=random_vectors(1.5 * max_speeds),  # some beyond max speed: LP2's normalise branch
        max_speeds=max_speeds,
        time_horizon=float(rng.choice([0.5, 1.0, 2.0, 5.0])),
        neighbor_dist=float(rng.choice([1.0, 2.0, 5.0, 10.0])),
        max_neighbors=int(rng.integers(1, 11)),
        time_step=float(rng.choice([0.1, 0.25])),
    )


def _rvo2_step(crowd: dict) -> np.ndarray:
    """One RVO2 doStep from the crowd's state; returns the new velocities (doStep copies newVelocity into velocity)."""
    th, nd, mn = crowd["time_horizon"], crowd["neighbor_dist"], crowd["max_neighbors"]
    sim = pyrvo.RVOSimulator(crowd["time_step"], nd, mn, th, th, 0.3, 1.0)
    for k, position in enumerate(crowd["positions"]):
        sim.add_agent(
            tuple(position),
            nd,
            mn,
            th,
            th,  # time_horizon_obst: irrelevant without obstacles
            float(crowd["radii"][k]),
            float(crowd["max_speeds"][k]),
            tuple(crowd["velocities"][k]),
        )
        sim.set_agent_pref_velocity(k, tuple(crowd["preferred_velocities"][k]))
    sim.do_step()
    return np.array([[sim.get_agent_velocity(k).x, sim.get_agent_velocity(k).y] for k in range(len(crowd["radii"]))])


def _ours(crowd: dict, radius_pad=None, avoidance_share=None, sees=None, active=None, compute=None):
    """Our kernel on the crowd as a single environment; returns (new velocities (N, 2), #agents that ran LP3)."""
    n = len(crowd["radii"])
    default_pad, default_share, default_sees = default_social_arrays(1, n)
    ones = np.ones((1, n), dtype=bool)
    out = np.empty((1, n, 2))
    n_fallbacks = orca_velocities_kernel(
        crowd["positions"][None],
        crowd["velocities"][None],
        crowd["radii"][None],
        crowd["preferred_velocities"][None],
        crowd["max_speeds"][None],
        ones if active is None else active[None],
        ones if compute is None else compute[None],
        default_pad if radius_pad is None else radius_pad[None],
        default_share if avoidance_share is None else avoidance_share[None],
        default_sees if sees is None else sees[None],
        crowd["time_horizon"],
        crowd["neighbor_dist"],
        crowd["max_neighbors"],
        crowd["time_step"],
        out,
    )
    return out[0], n_fallbacks


def _rvo2_self_spread(crowd: dict, rng: np.random.Generator, repeats: int = 8) -> float:
    """How far RVO2 moves when its float inputs move by a few float32 ulps: its own float32 conditioning."""
    base = _rvo2_step(crowd)
    spread = 0.0
    for _ in range(repeats):
        nudged = dict(crowd)
        for key in ("positions", "velocities", "preferred_velocities"):
            ulps = rng.integers(-4, 5, crowd[key].shape)
            nudged[key] = _f32(crowd[key] * (1.0 + ulps * 2.0**-23))
        spread = max(spread, float(np.abs(_rvo2_step(nudged) - base).max()))
    return spread


def _has_overlap(crowd: dict) -> bool:
    delta = crowd["positions"][:, None, :] - crowd["positions"][None, :, :]
    dist = np.sqrt((delta**2).sum(-1))
    reach = crowd["radii"][:, None] + crowd["radii"][None, :]
    np.fill_diagonal(dist, np.inf)
    return bool((dist < reach).any())


# --------------------------------------------------------------------------------------------------------------------
# Agreement with RVO2.
# --------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "side, n_crowds, min_fallback_crowds, min_overlap_crowds",
    [
        (8.0, 400, 40, 60),  # sparse: mostly free motion, some interactions
        (3.0, 400, 150, 200),  # dense: many neighbours, infeasible 2-D LPs
        (1.5, 400, 200, 250),  # packed: overlapping agents (collision case, 1 / time_step)
    ],
)
def test_matches_rvo2_on_random_crowds(side, n_crowds, min_fallback_crowds, min_overlap_crowds):
    rng = np.random.default_rng(int(side * 1000))
    nudge_rng = np.random.default_rng(7)
    agreed_fallback = agreed_overlap = ill_conditioned = 0
    for _ in range(n_crowds):
        crowd = _random_crowd(rng, side)
        ours, n_fallbacks = _ours(crowd)
        expected = _rvo2_step(crowd)
        error = float(np.abs(ours - expected).max())
        if error <= TOLERANCE:
            agreed_fallback += n_fallbacks > 0
            agreed_overlap += _has_overlap(crowd)
            continue
        # Disagreement is only allowed where RVO2's float32 answer is itself unstable: linearProgram3 intersects
        # nearly anti-parallel lines far away and loses most digits. Then RVO2 moves by a comparable amount when its
        # inputs move by a few ulps; our float64 answer must lie within that noise.
        spread = _rvo2_self_spread(crowd, nudge_rng)
        assert error <= TOLERANCE + 4.0 * spread, (error, spread, crowd)
        ill_conditioned += 1

    # The interesting branches were exercised, and matched RVO2 to 1e-4 (not merely within its noise).
    assert agreed_fallback >= min_fallback_crowds
    assert agreed_overlap >= min_overlap_crowds
    assert ill_conditioned <= 0.1 * n_crowds


def test_matches_rvo2_when_neighbour_list_is_truncated():
    """max_neighbors < #agents in range: RVO2 keeps the nearest ones (k-d tree with > 10 agents splits)."""
    rng = np.random.default_rng(3)
    for _ in range(100):
        crowd = _random_crowd(rng, 4.0)
        crowd["max_neighbors"] = int(rng.integers(1, 4))
        crowd["neighbor_dist"] = 10.0
        ours, _ = _ours(crowd)
        np.testing.assert_allclose(ours, _rvo2_step(crowd), atol=TOLERANCE, rtol=0)


def test_collision_case_by_hand():
    """Two overlapping discs at rest: each takes half of the push that separates them within one time step."""
    crowd = dict(
        positions=np.array([[0.0, 0.0], [0.5, 0.0]]),
        velocities=np.zeros((2, 2)),
        radii=np.array([0.5, 0.5]),
        preferred_velocities=np.zeros((2, 2)),
        max_speeds=np.array([2.0, 2.0]),
        time_horizon=2.0,
        neighbor_dist=10.0,
        max_neighbors=10,
        time_step=0.25,
    )
    # w = -(0.5, 0) / 0.25 = (-2, 0); u = (R / dt - |w|) w / |w| = (4 - 2) (-1, 0); each agent takes u / 2.
    ours, n_fallbacks = _ours(crowd)
    np.testing.assert_allclose(ours, [[-1.0, 0.0], [1.0, 0.0]], atol=1e-12)
    assert n_fallbacks == 0
    np.testing.assert_allclose(ours, _rvo2_step(crowd), atol=TOLERANCE)

    # Too slow to get out: the half-plane misses the speed disc, linearProgram3 goes as far out as possible.
    crowd["max_speeds"] = np.array([0.5, 0.5])
    ours, n_fallbacks = _ours(crowd)
    np.testing.assert_allclose(ours, [[-0.5, 0.0], [0.5, 0.0]], atol=1e-12)
    assert n_fallbacks == 2
    np.testing.assert_allclose(ours, _rvo2_step(crowd), atol=TOLERANCE)


@pytest.mark.parametrize(
    "positions, velocities",
    [
        ([[0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]]),  # coincident and at rest
        ([[0.0, 0.0], [0.5, 0.0]], [[1.0, 0.0], [-1.0, 0.0]]),  # would coincide exactly after one step
    ],
)
def test_degenerate_collision_pushes_agents_apart(positions, velocities):
    """w = 0 in the collision case: RVO2 divides 0 by 0, its NaN line then fails every comparison and the neighbour
    is silently ignored (both keep their preferred velocity 0). We separate the agents instead."""
    crowd = dict(
        positions=np.array(positions),
        velocities=np.array(velocities),
        radii=np.array([0.5, 0.5]),
        preferred_velocities=np.zeros((2, 2)),
        max_speeds=np.array([1.0, 1.0]),
        time_horizon=2.0,
        neighbor_dist=10.0,
        max_neighbors=10,
        time_step=0.25,
    )
    np.testing.assert_array_equal(_rvo2_step(crowd), np.zeros((2, 2)))
    ours, _ = _ours(crowd)
    np.testing.assert_allclose(ours, [[-1.0, 0.0], [1.0, 0.0]], atol=1e-12)


# --------------------------------------------------------------------------------------------------------------------
# Batching and masks.
# --------------------------------------------------------------------------------------------------------------------
def test_batch_with_masks_is_bit_identical_to_each_env_alone():
    rng = np.random.default_rng(11)
    n_envs, n_slots = 6, 9
    crowds = [_random_crowd(rng, 2.5) for _ in range(n_envs)]
    for crowd in crowds:  # the batch shares these scalars
        crowd.update(time_horizon=2.0, neighbor_dist=5.0, max_neighbors=6, time_step=0.25)

    # Scatter each env's agents into random slots; the other slots hold junk (overlapping the real agents).
    active = np.zeros((n_envs, n_slots), dtype=bool)
    batch = {
        "positions": rng.uniform(-1, 1, (n_envs, n_slots, 2)),
        "velocities": rng.uniform(-1, 1, (n_envs, n_slots, 2)),
        "radii": rng.uniform(0.2, 0.5, (n_envs, n_slots)),
        "preferred_velocities": rng.uniform(-1, 1, (n_envs, n_slots, 2)),
        "max_speeds": rng.uniform(0.5, 1.5, (n_envs, n_slots)),
    }
    slots = []
    for e, crowd in enumerate(crowds):
        n = min(len(crowd["radii"]), n_slots) if e != 2 else 1  # env 2 has a single agent
        for key in batch:
            crowd[key] = crowd[key][:n]
        chosen = np.sort(rng.choice(n_slots, n, replace=False))
        slots.append(chosen)
        active[e, chosen] = True
        for key in batch:
            batch[key][e, chosen] = crowd[key]
    compute = active | (rng.uniform(size=active.shape) < 0.5)  # compute on inactive slots must be ignored
    pad, share, sees = default_social_arrays(n_envs, n_slots)

    out = orca_velocities(
        batch["positions"],
        batch["velocities"],
        batch["radii"],
        batch["preferred_velocities"],
        batch["max_speeds"],
        active,
        compute,
        pad,
        share,
        sees,
        2.0,
        5.0,
        6,
        0.25,
    )

    for e, crowd in enumerate(crowds):
        # Inactive slots keep their velocity.
        np.testing.assert_array_equal(out[e, ~active[e]], batch["velocities"][e, ~active[e]])
        # The env alone, in the same slots, gives the same bits.
        alone = orca_velocities(
            *(batch[key][e : e + 1] for key in batch),
            active[e : e + 1],
            compute[e : e + 1],
            pad[:1],
            share[:1],
            sees[:1],
            2.0,
            5.0,
            6,
            0.25,
        )
        np.testing.assert_array_equal(out[e], alone[0])
        # Compacted to its real agents (same relative order), it gives the same bits too...
        compact, _ = _ours(crowd)
        np.testing.assert_array_equal(out[e, slots[e]], compact)
        # ...and agrees with RVO2 (a lone agent just takes its preferred velocity, clipped to max speed).
        np.testing.assert_allclose(compact, _rvo2_step(crowd), atol=TOLERANCE, rtol=0)


def test_wrapper_rejects_bad_inputs():
    n_envs, n = 2, 3
    pad, share, sees = default_social_arrays(n_envs, n)
    args = [
        np.zeros((n_envs, n, 2)),
        np.zeros((n_envs, n, 2)),
        np.full((n_envs, n), 0.3),
        np.zeros((n_envs, n, 2)),
        np.ones((n_envs, n)),
        np.ones((n_envs, n), dtype=bool),
        np.ones((n_envs, n), dtype=bool),
        pad,
        share,
        sees,
    ]
    scalars = (2.0, 5.0, 4, 0.25)
    assert orca_velocities(*args, *scalars).shape == (n_envs, n, 2)
    with pytest.raises(TypeError, match="active"):
        orca_velocities(*args[:5], np.ones((n_envs, n)), *args[6:], *scalars)
    with pytest.raises(ValueError, match="radius_pad"):
        orca_velocities(*args[:7], np.zeros((n_envs, n, n + 1)), *args[8:], *scalars)
    with pytest.raises(ValueError, match="time_step"):
        orca_velocities(*args, 2.0, 5.0, 4, 0.0)


# --------------------------------------------------------------------------------------------------------------------
# Social generalisations, against hand-computed geometry.
# --------------------------------------------------------------------------------------------------------------------
def _head_on() -> dict:
    """Two r=0.5 agents 4 m apart closing at 1.8 m/s with tau = 2: the relative velocity sits just inside the cut-off
    disc (centre (2, 0), radius R / tau = 0.5), so ORCA pushes it straight back along x.

    w = (1.8, 0) - (4, 0) / 2 = (-0.2, 0): u = (R / tau - |w|) (-1, 0); agent i's constraint is v_x <= 0.9 + share u_x.
    """
    return dict(
        positions=np.array([[0.0, 0.0], [4.0, 0.0]]),
        velocities=np.array([[0.9, 0.0], [-0.9, 0.0]]),
        radii=np.array([0.5, 0.5]),
        preferred_velocities=np.array([[0.9, 0.0], [-0.9, 0.0]]),
        max_speeds=np.array([1.0, 1.0]),
        time_horizon=2.0,
        neighbor_dist=10.0,
        max_neighbors=10,
        time_step=0.25,
    )


@pytest.mark.parametrize("share", [0.0, 0.25, 0.5, 1.0])
def test_avoidance_share_scales_the_correction(share):
    crowd = _head_on()
    shares = np.full((2, 2), 0.5)
    shares[0, 1] = share  # agent 0's share w.r.t. agent 1; agent 1 stays reciprocal
    ours, _ = _ours(crowd, avoidance_share=shares)
    u = 0.5 - 0.2  # R / tau - |w|
    np.testing.assert_allclose(ours[0], [0.9 - share * u, 0.0], atol=1e-12)
    np.testing.assert_allclose(ours[1], [-(0.9 - 0.5 * u), 0.0], atol=1e-12)
    if share == 0.5:
        np.testing.assert_allclose(ours, _rvo2_step(crowd), atol=TOLERANCE)


def test_radius_pad_enlarges_the_avoided_disc_for_that_agent_only():
    crowd = _head_on()
    pad = np.zeros((2, 2))
    pad[0, 1] = 0.4  # agent 0 keeps 0.4 m more from agent 1
    ours, _ = _ours(crowd, radius_pad=pad)
    # Agent 0: R = 1.4, cut-off radius 0.7, u = 0.7 - 0.2; agent 1 still sees R = 1.
    np.testing.assert_allclose(ours[0], [0.9 - 0.5 * (0.7 - 0.2), 0.0], atol=1e-12)
    np.testing.assert_allclose(ours[1], [-(0.9 - 0.5 * (0.5 - 0.2)), 0.0], atol=1e-12)


@pytest.mark.parametrize("pad", [0.0, 0.6])
def test_full_share_passes_a_static_neighbour_on_the_tangent(pad):
    """Share 1 against a standing agent: the new velocity is the preferred one projected on the cone's left leg, the
    tangent from the origin to the disc of radius r_i + r_j + pad around the neighbour."""
    preferred = np.array([1.0, 0.2])
    crowd = dict(
        positions=np.array([[0.0, 0.0], [4.0, 0.0]]),
        velocities=np.array([preferred, [0.0, 0.0]]),
        radii=np.array([0.5, 0.5]),
        preferred_velocities=np.array([preferred, [0.0, 0.0]]),
        max_speeds=np.array([2.0, 2.0]),
        time_horizon=100.0,  # cut-off circle far smaller than the legs' reach: the legs bind
        neighbor_dist=10.0,
        max_neighbors=10,
        time_step=0.25,
    )
    pads = np.zeros((2, 2))
    pads[0, 1] = pad
    shares = np.full((2, 2), 1.0)
    compute = np.array([True, False])
    ours, _ = _ours(crowd, radius_pad=pads, avoidance_share=shares, compute=compute)

    half_angle = math.asin((1.0 + pad) / 4.0)
    tangent = np.array([math.cos(half_angle), math.sin(half_angle)])
    np.testing.assert_allclose(ours[0], (preferred @ tangent) * tangent, atol=1e-12)
    np.testing.assert_array_equal(ours[1], [0.0, 0.0])  # not computed: keeps its velocity


def test_unseen_neighbour_is_ignored_and_takes_no_neighbour_slot():
    crowd = _head_on()
    sees = np.ones((2, 2), dtype=bool)
    sees[0, 1] = False
    ours, _ = _ours(crowd, sees=sees)
    np.testing.assert_array_equal(ours[0], [0.9, 0.0])  # agent 0 keeps its preferred velocity
    np.testing.assert_allclose(ours[1], [-0.75, 0.0], atol=1e-12)  # agent 1 still avoids

    # A near unseen agent does not use up max_neighbors = 1: the farther, seen one is still avoided.
    three = _head_on()
    three.update(
        positions=np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 1.5]]),
        velocities=np.array([[0.9, 0.0], [-0.9, 0.0], [0.0, 0.3]]),
        radii=np.array([0.5, 0.5, 0.5]),
        preferred_velocities=np.array([[0.9, 0.0], [-0.9, 0.0], [0.0, 0.3]]),
        max_speeds=np.ones(3),
        max_neighbors=1,
    )
    sees = np.ones((3, 3), dtype=bool)
    sees[0, 2] = False
    ours, _ = _ours(three, sees=sees)
    np.testing.assert_allclose(ours[0], [0.75, 0.0], atol=1e-12)

    # Same for an inactive slot: as if it were not there at all.
    active = np.array([True, True, False])
    ours, _ = _ours(three, active=active)
    alone, _ = _ours(_head_on())
    np.testing.assert_array_equal(ours[:2], alone)
    np.testing.assert_array_equal(ours[2], three["velocities"][2])


# --------------------------------------------------------------------------------------------------------------------
# Invariants on arbitrary inputs.
# --------------------------------------------------------------------------------------------------------------------
@st.composite
def _batches(draw):
    n_envs = draw(st.integers(1, 3))
    n = draw(st.integers(1, 7))

    def floats(shape, low, high):
        return draw(hnp.arrays(np.float64, shape, elements=st.floats(low, high, allow_nan=False, width=32)))

    def bools(shape):
        return draw(hnp.arrays(np.bool_, shape))

    return dict(
        positions=floats((n_envs, n, 2), -2.0, 2.0),  # dense and often coincident: the collision case and LP3
        velocities=floats((n_envs, n, 2), -2.0, 2.0),
        radii=floats((n_envs, n), 0.0, 0.5),
        preferred_velocities=floats((n_envs, n, 2), -3.0, 3.0),
        max_speeds=floats((n_envs, n), 0.0, 2.0),
        active=bools((n_envs, n)),
        compute=bools((n_envs, n)),
        radius_pad=floats((n_envs, n, n), 0.0, 0.5),
        avoidance_share=floats((n_envs, n, n), 0.0, 1.0),
        sees=bools((n_envs, n, n)),
        time_horizon=draw(st.sampled_from([0.25, 1.0, 5.0])),
        neighbor_dist=draw(st.sampled_from([0.5, 3.0, 10.0])),
        max_neighbors=draw(st.integers(0, 8)),
        time_step=draw(st.sampled_from([0.05, 0.25])),
    )


@settings(max_examples=300, deadline=None)
@given(_batches())
def test_invariants(batch):
    out = orca_velocities(**batch)
    assert out.shape == batch["velocities"].shape
    assert np.isfinite(out).all()
    speed = np.sqrt((out**2).sum(-1))
    computed = batch["active"] & batch["compute"]
    assert (speed[computed] <= batch["max_speeds"][computed] + 1e-9).all()
    np.testing.assert_array_equal(out[~computed], batch["velocities"][~computed])
    # Each env depends on its own inputs only.
    for e in range(out.shape[0]):
        alone = orca_velocities(
            **{key: value[e : e + 1] if isinstance(value, np.ndarray) else value for key, value in batch.items()}
        )
        np.testing.assert_array_equal(out[e], alone[0])
