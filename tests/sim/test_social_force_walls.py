"""Social force humans among walls against their oracle, PySocialForce 1.1.2's obstacle force (`ObstacleForce` on the
points its `EnvState` samples along line obstacles), and the invariant that humans walking at a wall stay on their side.

The walls reach the model as `Crowd.wall_segments` (`polygon_segments`); PySocialForce gets the same segments as its
(startx, endx, starty, endy) lines and each human's body radius as its agent_radius. One step from identical states
must agree to 1e-5 and 50-step trajectories to 1e-3 m (measured: both agree to ~1e-15).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_social_force import (  # tests/sim is on sys.path; psf, the oracle, is conftest.py's fixture
    DT,
    ONE_STEP_TOLERANCE,
    TRAJECTORY_TOLERANCE,
    batch,
    model,
    random_crowd,
)

from socnav.config import SocialForceConfig, load_config
from socnav.sim.geometry import polygon_segments
from socnav.sim.humans import Crowd

# ---------------------------------------------------------------------------------------------------- walls


def corridor(half_width: float = 1.5, length: float = 16.0) -> list[np.ndarray]:
    """Two parallel walls y = +-half_width from x = -length/2 to length/2 (two-vertex polygons: wall segments)."""
    return [np.array([[-length / 2, -half_width], [length / 2, -half_width]]),
            np.array([[length / 2, half_width], [-length / 2, half_width]])]


def box(centre=(0.0, 0.0), half_size: float = 0.8) -> list[np.ndarray]:
    """A solid square (counter-clockwise) inside a room (clockwise, enclosing free space)."""
    cx, cy = centre
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
    return [square * half_size + (cx, cy), square[::-1] * 6.0]


def random_walls(rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Wall segments through the crowd's square, 0.1-4 m long (1 to 40 sample points), some axis-aligned."""
    walls = []
    for k in range(count):
        start = rng.uniform(-3, 3, 2)
        angle = 0.0 if k % 5 == 0 else (math.pi / 2 if k % 5 == 1 else rng.uniform(-math.pi, math.pi))
        walls.append(np.stack([start, start + rng.uniform(0.1, 4.0) * np.array([math.cos(angle), math.sin(angle)])]))
    return walls


def outside_the_box(state, centre: np.ndarray, half_size: float) -> tuple:
    """The crowd with every human inside the square (or within 0.5 m of it) moved out to 0.5 m beyond its edge."""
    positions = state[0].copy()
    offsets = positions - centre
    reach = np.abs(offsets).max(axis=1)
    inside = reach < half_size + 0.5
    positions[inside] = centre + offsets[inside] / reach[inside, None] * (half_size + 0.5)
    return (positions, *state[1:])


def lines(polygons: list[np.ndarray]) -> list[tuple[float, float, float, float]]:
    """The polygons' edges as PySocialForce's line obstacles (startx, endx, starty, endy), in the same order."""
    seg_start, seg_end, n_segments = polygon_segments([polygons])
    count = n_segments[0]
    return [(a[0], b[0], a[1], b[1]) for a, b in zip(seg_start[0, :count], seg_end[0, :count], strict=True)]


def with_walls(crowd: Crowd, polygons_per_env: list[list[np.ndarray]], radii: np.ndarray | None = None) -> Crowd:
    """The crowd among these walls (one list of polygons per environment), with these body radii (E, N)."""
    return replace(crowd, radii=crowd.radii if radii is None else radii,
                   wall_segments=polygon_segments(polygons_per_env))


def oracle_simulator(psf, state, polygons, agent_radius: float, config_file: str | None = None):
    """PySocialForce's simulator on these agents and walls, stepping by DT with max speeds 1.3 v_pref."""
    positions, velocities, goals, v_pref = state
    sim = psf.Simulator(np.concatenate([positions, velocities, goals], axis=1).astype(float),
                        obstacles=lines(polygons) or None, config_file=config_file)
    sim.peds.step_width, sim.peds.agent_radius = DT, agent_radius
    sim.peds.initial_speeds = np.asarray(v_pref, dtype=float).copy()
    sim.peds.state = sim.peds.state  # recomputes max_speeds = max_speed_multiplier * initial_speeds
    return sim


def step(humans, crowd: Crowd, steps: int) -> None:
    """`steps` steps in place, as the world moves the humans: v from the model, p <- p + v dt."""
    for _ in range(steps):
        velocities = humans.velocities(crowd, crowd.active)
        crowd.positions[...] += velocities * DT
        crowd.velocities[...] = velocities


def corridor_walkers(rng: np.random.Generator, n: int):
    """n humans in the corridor, some walking +x and some -x, to the far end, many within 3 m of a wall."""
    direction = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    positions = np.stack([-direction * rng.uniform(3.0, 6.0, n), rng.uniform(-1.1, 1.1, n)], axis=1)
    goals = np.stack([direction * 7.5, rng.uniform(-1.0, 1.0, n)], axis=1)
    velocities = np.stack([direction, rng.uniform(-0.3, 0.3, n)], axis=1) * rng.uniform(0.3, 1.0, (n, 1))
    return positions, velocities, goals, rng.uniform(0.8, 1.4, n)


# ---------------------------------------------------------------------------------------------------- the oracle


def test_defaults_are_pysocialforces_published_ones(psf):
    obstacle_force = psf.utils.DefaultConfig().sub_config("obstacle_force")
    ours = SocialForceConfig()
    assert (ours.obstacle_force_factor, ours.obstacle_sigma, ours.obstacle_threshold) == (
        obstacle_force("factor"), obstacle_force("sigma"), obstacle_force("threshold"))
    # its simulator reads the resolution at the config's top level (default 10), where default.toml has none
    assert ours.obstacle_resolution == psf.Simulator(np.zeros((1, 6))).env.resolution == 10.0


def test_the_obstacle_parameters_stay_out_of_dumps_at_their_defaults():
    # dumps (model metadata, record-file names, unit hashes) of worlds without walls stay what they were
    config = load_config({"humans": {"model": "social_force", "social_force": {"obstacle_sigma": 0.3}}})
    dumped = config.humans.social_force.model_dump()
    assert not any(key.startswith("obstacle_") for key in SocialForceConfig().model_dump())
    assert dumped["obstacle_sigma"] == 0.3 and "obstacle_threshold" not in dumped
    assert SocialForceConfig(**dumped) == config.humans.social_force


def test_mismatched_wall_arrays_are_refused():
    crowd = batch([random_crowd(np.random.default_rng(0), 4, density=0.5)] * 2)
    seg_start, seg_end, n_segments = polygon_segments([corridor()] * 3)  # three environments' walls for two
    with pytest.raises(ValueError, match="wall_segments"):
        model().velocities(replace(crowd, wall_segments=(seg_start, seg_end, n_segments)), crowd.active)
    with pytest.raises(ValueError, match="wall_segments"):  # more segments counted than stored
        model().velocities(replace(crowd, wall_segments=(seg_start[:2], seg_end[:2], n_segments[:2] + 1)),
                           crowd.active)


def test_one_step_matches_pysocialforce_among_walls(psf):
    # A corridor, a box in a room and random segments, every one in one batched call (padded to the most segments).
    rng = np.random.default_rng(3)
    scenes = []
    for _ in range(2):
        scenes.append((corridor_walkers(rng, 7), corridor()))
        centre = rng.uniform(-1, 1, 2)
        scenes.append((outside_the_box(random_crowd(rng, 9, density=0.5), centre, 0.8), box(centre, 0.8)))
        scenes.append((random_crowd(rng, 12, density=0.8), random_walls(rng, int(rng.integers(1, 12)))))
    crowd = batch([state for state, _ in scenes])
    radii = rng.uniform(0.2, 0.4, len(scenes))
    crowd = with_walls(crowd, [polygons for _, polygons in scenes], np.repeat(radii[:, None], crowd.radii.shape[1], 1))
    ours = model().velocities(crowd, crowd.active)
    open_plane = model().velocities(batch([state for state, _ in scenes]), crowd.active)
    worst, walls_matter = 0.0, math.inf
    for env, (state, polygons) in enumerate(scenes):
        n = len(state[0])
        expected = oracle_simulator(psf, state, polygons, radii[env]).step(1).peds.vel()
        worst = max(worst, np.abs(ours[env, :n] - expected).max())
        walls_matter = min(walls_matter, np.abs(open_plane[env, :n] - expected).max())
    assert worst < ONE_STEP_TOLERANCE, worst
    assert walls_matter > 1e-2, "the walls must change every scene's step"


def test_each_human_is_pushed_as_a_body_of_its_own_radius(psf):
    # PySocialForce has one agent_radius: each human i must move as in PySocialForce with agent_radius = r_i.
    rng = np.random.default_rng(4)
    state = corridor_walkers(rng, 8)
    n = len(state[0])
    radii = np.zeros((1, n + 1))
    radii[0, :n] = rng.uniform(0.15, 0.5, n)
    crowd = with_walls(batch([state]), [corridor()], radii)
    ours = model().velocities(crowd, crowd.active)[0]
    for i in range(n):
        expected = oracle_simulator(psf, state, corridor(), radii[0, i]).step(1).peds.vel()[i]
        assert np.abs(ours[i] - expected).max() < ONE_STEP_TOLERANCE, i
    uniform = model().velocities(with_walls(batch([state]), [corridor()], np.full((1, n + 1), 0.3)), crowd.active)
    assert np.abs(uniform[0, :n] - ours[:n]).max() > 1e-3, "the radii must matter in this scene"


@pytest.mark.parametrize("seed", range(3))
def test_fifty_step_corridor_walks_match_pysocialforce(psf, seed):
    rng = np.random.default_rng(200 + seed)
    state = corridor_walkers(rng, int(rng.integers(3, 9)))
    n = len(state[0])
    crowd = with_walls(batch([state]), [corridor()], np.full((1, n + 1), 0.3))
    step(model(), crowd, steps=50)
    expected = oracle_simulator(psf, state, corridor(), 0.3).step(50).peds.pos()
    assert np.abs(crowd.positions[0, :n] - expected).max() < TRAJECTORY_TOLERANCE
    open_plane = batch([state])
    step(model(), open_plane, steps=50)
    assert np.abs(open_plane.positions[0, :n] - expected).max() > 0.1, "the walls must shape the walk"
    assert np.abs(crowd.positions[0, :n] - state[0]).max() > 5.0, "the crowd must actually walk"


def test_parameters_reach_the_model(psf, tmp_path):
    # The obstacle parameters changed at once, PySocialForce given the same through its config file (it reads the
    # resolution at the file's top level).
    parameters = {"obstacle_force_factor": 6.0, "obstacle_sigma": 0.35, "obstacle_threshold": 1.5,
                  "obstacle_resolution": 7.0}
    toml = tmp_path / "config.toml"
    toml.write_text(f"resolution = {parameters['obstacle_resolution']}\n[obstacle_force]\n"
                    f"factor = {parameters['obstacle_force_factor']}\nsigma = {parameters['obstacle_sigma']}\n"
                    f"threshold = {parameters['obstacle_threshold']}\n")
    rng = np.random.default_rng(5)
    state, polygons = random_crowd(rng, 10, density=0.5), random_walls(rng, 8)
    crowd = with_walls(batch([state]), [polygons])
    ours = model(**parameters).velocities(crowd, crowd.active)[0, :10]
    expected = oracle_simulator(psf, state, polygons, 0.3, config_file=str(toml)).step(1).peds.vel()
    assert np.abs(ours - expected).max() < ONE_STEP_TOLERANCE
    assert np.abs(model().velocities(crowd, crowd.active)[0, :10] - expected).max() > 1e-2, "and they matter"


def test_long_walls_at_other_thresholds_and_resolutions_match_pysocialforce(psf, tmp_path):
    # Walls up to 20 m long reach past the cut-off circle, where the model skips points unevaluated; fractional
    # resolutions truncate int(length x resolution). PySocialForce's config file replaces a whole section, so the
    # file repeats the factor.
    rng = np.random.default_rng(8)
    worst = 0.0
    for scene in range(30):
        state = random_crowd(rng, 8, density=rng.uniform(0.1, 1.0))
        walls = []
        for _ in range(int(rng.integers(1, 8))):
            start, angle = rng.uniform(-8, 8, 2), rng.uniform(-math.pi, math.pi)
            walls.append(np.stack([start, start + rng.uniform(0.1, 20.0) * np.array([math.cos(angle),
                                                                                     math.sin(angle)])]))
        threshold, resolution = float(rng.uniform(0.2, 4.0)), float(rng.uniform(2.0, 30.0))
        toml = tmp_path / f"config{scene}.toml"
        toml.write_text(f"resolution = {resolution!r}\n[obstacle_force]\nfactor = 10.0\nthreshold = {threshold!r}\n")
        crowd = with_walls(batch([state]), [walls])
        ours = model(obstacle_threshold=threshold, obstacle_resolution=resolution).velocities(crowd, crowd.active)
        expected = oracle_simulator(psf, state, walls, 0.3, config_file=str(toml)).step(1).peds.vel()
        worst = max(worst, np.abs(ours[0, :8] - expected).max())
    assert worst < ONE_STEP_TOLERANCE, worst


def test_one_wall_point_pushes_as_computed_by_hand():
    # A 0.15 m segment holds int(0.15 x 10) = 1 point, its start q. A human standing (v = 0) 0.5 m from q, away from
    # its goal beyond the stop distance, feels F = F_desired + 10 exp(-(0.5 - r) / 0.2) u, u the unit vector q -> p;
    # a segment under 0.1 m long holds no point and no push (PySocialForce cannot sample it: it raises).
    q = np.array([1.0, 2.0])
    u = np.array([0.6, 0.8])
    positions = np.array([q + 0.5 * u])
    goal = positions[0] + np.array([0.0, -3.0])
    state = (positions, np.zeros((1, 2)), goal[None], np.array([1.0]))
    radius = 0.3
    for length, points in ((0.15, 1), (0.09, 0)):
        crowd = with_walls(batch([state]), [[np.stack([q, q + length * np.array([0.0, 1.0])])]],
                           np.full((1, 2), radius))
        velocity = model().velocities(crowd, crowd.active)[0, 0]
        desired = 1.3 * np.array([0.0, -1.0]) / 0.5
        push = points * 10.0 * math.exp(-(0.5 - radius) / 0.2) * u
        expected = DT * (desired + push)
        expected *= min(1.0, 1.3 / np.linalg.norm(expected))
        assert np.abs(velocity - expected).max() < 1e-12, length


def test_walls_out_of_reach_leave_the_step_bit_identical():
    # PySocialForce skips a human whose every wall point is beyond the threshold: no force at all, not +0.
    rng = np.random.default_rng(6)
    state = random_crowd(rng, 15, density=0.5)  # within +-3 m of the origin
    far = [np.array([[-50.0, 40.0], [50.0, 40.0]]), np.array([[30.0, -30.0], [30.0, 30.0], [35.0, 0.0]])]
    crowd = with_walls(batch([state]), [far])
    assert np.array_equal(model().velocities(crowd, crowd.active), model().velocities(batch([state]),
                                                                                      crowd.active))


# ---------------------------------------------------------------------------------------------------- invariant


def crosses(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Whether each move a -> b (K, 2) meets the wall c -> d (2,), touching included."""
    def side(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
    return ((side(a, b, c) * side(a, b, d) <= 0) & (side(c, d, a) * side(c, d, b) <= 0))


def distance_to_wall(points: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    t = np.clip(((points - c) @ (d - c)) / ((d - c) @ (d - c)), 0.0, 1.0)
    return np.linalg.norm(points - (c + t[..., None] * (d - c)), axis=-1)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 8), angle=st.floats(-math.pi, math.pi), seed=st.integers(0, 2**32 - 1))
def test_humans_walking_at_a_wall_do_not_pass_through_it(n, angle, seed):
    # n humans 0.1-3 m in front of an 8 m wall, headed for goals behind it at up to 1.3 x 1.5 m/s, pushing each
    # other: none crosses the wall in 30 s, and no body overlaps it (they may walk round its ends).
    rng = np.random.default_rng(seed)
    radii = rng.uniform(0.2, 0.4, n)
    local_positions = np.stack([rng.uniform(-2.0, 2.0, n), radii + rng.uniform(0.1, 3.0, n)], axis=1)
    local_goals = np.stack([rng.uniform(-3.0, 3.0, n), rng.uniform(-4.0, -0.5, n)], axis=1)
    v_pref = rng.uniform(0.5, 1.5, n)
    towards = local_goals - local_positions
    local_velocities = towards / np.linalg.norm(towards, axis=1, keepdims=True) * (1.3 * v_pref)[:, None]
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    offset = rng.uniform(-5.0, 5.0, 2)
    c, d = rotation @ np.array([-4.0, 0.0]) + offset, rotation @ np.array([4.0, 0.0]) + offset
    state = (local_positions @ rotation.T + offset, local_velocities @ rotation.T, local_goals @ rotation.T + offset,
             v_pref)
    crowd = batch([state])
    crowd.radii[0, :n] = radii
    crowd = with_walls(crowd, [[np.stack([c, d])]])
    humans = model()
    for _ in range(120):
        before = crowd.positions[0, :n].copy()
        step(humans, crowd, steps=1)
        after = crowd.positions[0, :n]
        assert not crosses(before, after, c, d).any(), "a human passed through the wall"
        assert (distance_to_wall(after, c, d) >= radii).all(), "a body overlaps the wall"
    assert np.abs(crowd.positions[0, :n] - state[0]).max() > 0.5, "the humans must actually walk"
