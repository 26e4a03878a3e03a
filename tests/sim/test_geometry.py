"""Tests of the batched wall geometry (socnav.sim.geometry): hand-computed scenes, shapely as an independent oracle on
random walls, and hypothesis invariants (symmetry, monotonicity in the walls, Lipschitz distances)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import LineString, MultiLineString, Point

from socnav.sim.geometry import (
    distance_to_segments,
    line_of_sight,
    polygon_segments,
    range_scan,
    scan_angles,
    swept_distance_to_segments,
    swept_segment_hit,
)
from socnav.sim.maps import orient_rvo2

# A 4 x 4 m room (clockwise: free space inside) split at x = 2 by a wall with a door at 1.5 <= y <= 2.5.
ROOM = orient_rvo2(np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]]), solid=False)
LOWER_WALL = np.array([[2.0, 0.0], [2.0, 1.5]])
UPPER_WALL = np.array([[2.0, 2.5], [2.0, 4.0]])
ROOM_WITH_DOOR = [ROOM, LOWER_WALL, UPPER_WALL]


def _one_env(polygons):
    return polygon_segments([polygons])


# --------------------------------------------------------------------------------------------------------------------
# polygon_segments
# --------------------------------------------------------------------------------------------------------------------
def test_polygons_become_closed_edges_and_walls_one_segment_padded_per_env():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    seg_start, seg_end, n_segments = polygon_segments([[square, LOWER_WALL], [], [LOWER_WALL]])
    np.testing.assert_array_equal(n_segments, [5, 0, 1])
    assert seg_start.shape == seg_end.shape == (3, 5, 2)
    np.testing.assert_array_equal(seg_start[0, :4], square)
    np.testing.assert_array_equal(seg_end[0, :4], np.roll(square, -1, axis=0))  # the closing edge (0,1)->(0,0)
    np.testing.assert_array_equal(seg_start[0, 4], [2.0, 0.0])
    np.testing.assert_array_equal(seg_end[0, 4], [2.0, 1.5])
    np.testing.assert_array_equal(seg_start[2, 0], LOWER_WALL[0])
    with pytest.raises(ValueError, match="at least 2 vertices"):
        polygon_segments([[np.array([[0.0, 0.0]])]])


# --------------------------------------------------------------------------------------------------------------------
# Line of sight
# --------------------------------------------------------------------------------------------------------------------
def test_line_of_sight_through_a_door():
    positions = np.array([[[1.0, 2.0], [3.0, 2.0], [1.0, 1.0], [3.0, 1.0], [3.0, 3.0], [3.0, 2.0], [1.0, 3.0]]])
    active = np.array([[True, True, True, True, True, False, True]])
    visible = line_of_sight(positions, active, *_one_env(ROOM_WITH_DOOR))[0]
    assert visible[0, 1]  # straight through the door
    assert not visible[2, 3]  # through the lower wall
    assert visible[2, 4]  # (1,1) -> (3,3) crosses x = 2 at y = 2: in the door
    assert visible[2, 0] and visible[3, 4]  # same half of the room
    assert not visible[6, 4]  # through the upper wall
    assert visible[6, 3]  # (1,3) -> (3,1) crosses x = 2 at y = 2: in the door
    assert not visible[0, 5] and not visible[5, 5]  # agent 5 is inactive: sees nothing, not even itself
    np.testing.assert_array_equal(visible, visible.T)
    assert all(visible[i, i] == active[0, i] for i in range(7))


def test_grazing_a_wall_end_blocks_the_view():
    # (1, 1) -> (3, 2) crosses x = 2 at y = 1.5, exactly the lower wall's end: touching counts as blocked
    positions = np.array([[[1.0, 1.0], [3.0, 2.0], [1.0, 1.2], [3.0, 2.0]]])
    visible = line_of_sight(positions, np.ones((1, 4), dtype=bool), *_one_env(ROOM_WITH_DOOR))[0]
    assert not visible[0, 1]
    assert visible[2, 3]  # crosses at y = 1.6, inside the door


def test_a_line_through_two_corners_of_a_solid_square_is_blocked():
    square = orient_rvo2(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), solid=True)
    positions = np.array([[[-1.0, -1.0], [2.0, 2.0]]])
    assert not line_of_sight(positions, np.ones((1, 2), dtype=bool), *_one_env([square]))[0, 0, 1]


def _random_walls(rng: np.random.Generator, n_envs: int, max_walls: int = 8, side: float = 5.0):
    """Per environment 0..max_walls random wall segments in a side x side square (as two-vertex polygons)."""
    return [[rng.uniform(-side / 2, side / 2, (2, 2)) for _ in range(rng.integers(0, max_walls + 1))]
            for _ in range(n_envs)]


def _shapely_walls(polygons) -> MultiLineString:
    return MultiLineString([LineString(p) for p in polygons])


def test_line_of_sight_matches_shapely_on_random_walls():
    rng = np.random.default_rng(7)
    n_envs, n_agents = 40, 6
    walls = _random_walls(rng, n_envs)
    positions = rng.uniform(-2.5, 2.5, (n_envs, n_agents, 2))
    active = rng.random((n_envs, n_agents)) < 0.85
    visible = line_of_sight(positions, active, *polygon_segments(walls))
    blocked_pairs = 0
    for env in range(n_envs):
        shapely_walls = _shapely_walls(walls[env])
        for i in range(n_agents):
            for j in range(n_agents):
                if i == j or not (active[env, i] and active[env, j]):
                    expected = i == j and active[env, i]
                else:
                    expected = not LineString([positions[env, i], positions[env, j]]).intersects(shapely_walls)
                assert visible[env, i, j] == expected, (env, i, j)
                blocked_pairs += not expected
    assert blocked_pairs > 100  # the random scenes do block many views


# --------------------------------------------------------------------------------------------------------------------
# Range scan
# --------------------------------------------------------------------------------------------------------------------
def test_scan_angles_follow_laser_scan():
    assert scan_angles(4, 2.0 * math.pi) == (-math.pi, math.pi / 2)  # no beam repeats the first one at +pi
    assert scan_angles(3, math.pi) == (-math.pi / 2, math.pi / 2)  # first at -fov/2, last at +fov/2
    assert scan_angles(1, 1.0) == (0.0, 0.0)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="n_beams must be an integer >= 1"):
            scan_angles(bad, 1.0)
    for bad in (0.0, -1.0, 7.0):
        with pytest.raises(ValueError, match=r"fov must be in \(0, 2 pi\]"):
            scan_angles(3, bad)


@pytest.mark.parametrize("max_range", [0.0, -1.0, math.inf, math.nan])
def test_max_range_must_be_finite_and_positive(max_range):
    with pytest.raises(ValueError, match="max_range must be a finite number > 0"):
        range_scan(np.zeros((1, 2)), np.zeros(1), *polygon_segments([[]]), n_beams=4, max_range=max_range)


def test_beams_hit_a_wall_at_known_angles():
    wall = [np.array([[3.0, -10.0], [3.0, 10.0]])]  # x = 3
    # fov 120 degrees, 5 beams: -60, -30, 0, 30, 60 degrees; range 3 / cos(angle)
    ranges = range_scan(np.zeros((1, 2)), np.zeros(1), *_one_env(wall), n_beams=5, max_range=10.0,
                        fov=math.radians(120))
    np.testing.assert_allclose(ranges[0], [6.0, 2.0 * math.sqrt(3.0), 3.0, 2.0 * math.sqrt(3.0), 6.0], rtol=1e-12)
    ranges = range_scan(np.zeros((1, 2)), np.zeros(1), *_one_env(wall), n_beams=5, max_range=5.0,
                        fov=math.radians(120))
    np.testing.assert_allclose(ranges[0], [5.0, 2.0 * math.sqrt(3.0), 3.0, 2.0 * math.sqrt(3.0), 5.0], rtol=1e-12)


def test_a_full_turn_scan_in_the_room_with_a_door():
    # from (1, 1), 8 beams from -pi: left wall, corner (0,0), floor, the lower wall's foot (2,0), the lower wall,
    # through the door to the corner (4,4), ceiling, left wall at (0,2)
    ranges = range_scan(np.array([[1.0, 1.0]]), np.zeros(1), *_one_env(ROOM_WITH_DOOR), n_beams=8, max_range=10.0)
    r2 = math.sqrt(2.0)
    np.testing.assert_allclose(ranges[0], [1.0, r2, 1.0, r2, 1.0, 3.0 * r2, 3.0, r2], rtol=1e-12)
    # turning the robot by +90 degrees shifts the beams by two
    turned = range_scan(np.array([[1.0, 1.0]]), np.array([math.pi / 2]), *_one_env(ROOM_WITH_DOOR), n_beams=8,
                        max_range=10.0)
    np.testing.assert_allclose(turned[0], np.roll(ranges[0], -2), rtol=1e-12)


def test_humans_appear_in_the_scan_only_when_asked():
    no_walls = polygon_segments([[]])
    positions = np.array([[[2.0, 0.0], [-3.0, 0.0], [0.0, 2.0]]])
    radii = np.array([[0.5, 0.5, 0.5]])
    active = np.array([[True, True, False]])
    kwargs = dict(n_beams=4, max_range=8.0)  # beams at -pi, -pi/2, 0, pi/2
    np.testing.assert_array_equal(range_scan(np.zeros((1, 2)), np.zeros(1), *no_walls, **kwargs), [[8.0] * 4])
    ranges = range_scan(np.zeros((1, 2)), np.zeros(1), *no_walls, **kwargs, circles=(positions, radii, active))
    np.testing.assert_allclose(ranges, [[2.5, 8.0, 1.5, 8.0]])  # the inactive human at (0, 2) is not seen
    inside = range_scan(np.array([[2.2, 0.0]]), np.zeros(1), *no_walls, **kwargs, circles=(positions, radii, active))
    np.testing.assert_array_equal(inside, [[0.0] * 4])  # a beam starting inside a disc reads 0


def test_scan_matches_shapely_on_random_walls():
    rng = np.random.default_rng(11)
    n_envs, n_beams, max_range = 30, 16, 4.0
    walls = _random_walls(rng, n_envs)
    origins = rng.uniform(-2.5, 2.5, (n_envs, 2))
    headings = rng.uniform(-math.pi, math.pi, n_envs)
    fov = math.radians(270)
    ranges = range_scan(origins, headings, *polygon_segments(walls), n_beams=n_beams, max_range=max_range, fov=fov)
    angle_min, increment = scan_angles(n_beams, fov)
    hits = 0
    for env in range(n_envs):
        shapely_walls = _shapely_walls(walls[env])
        for beam in range(n_beams):
            angle = headings[env] + angle_min + beam * increment
            end = origins[env] + max_range * np.array([math.cos(angle), math.sin(angle)])
            crossing = LineString([origins[env], end]).intersection(shapely_walls)
            expected = max_range if crossing.is_empty else Point(origins[env]).distance(crossing)
            assert ranges[env, beam] == pytest.approx(expected, abs=1e-9), (env, beam)
            hits += not crossing.is_empty
    assert hits > 100


# --------------------------------------------------------------------------------------------------------------------
# Distances and sweeping
# --------------------------------------------------------------------------------------------------------------------
def test_distance_to_walls_in_the_room():
    points = np.array([[1.0, 1.0], [2.5, 2.0], [2.0, 2.0], [3.0, 0.5]])
    segments = polygon_segments([ROOM_WITH_DOOR] * 4 + [[]])
    distances = distance_to_segments(np.vstack([points, [[0.0, 0.0]]]), *segments)
    np.testing.assert_allclose(distances, [1.0, math.hypot(0.5, 0.5), 0.5, 0.5, np.inf])


def test_a_disc_sweeping_past_a_corner():
    square = orient_rvo2(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), solid=True)
    segments = polygon_segments([[square]] * 2)
    # along x + y = 2.5, from (2, 0.5) to (0.5, 2): both ends 1 m from the square, the corner (1, 1) at 0.5 / sqrt 2
    p0 = np.array([[2.0, 0.5]] * 2)
    p1 = np.array([[0.5, 2.0]] * 2)
    corner_distance = 0.5 / math.sqrt(2.0)
    np.testing.assert_allclose(swept_distance_to_segments(p0, p1, *segments), corner_distance, rtol=1e-12)
    np.testing.assert_allclose(distance_to_segments(p0, *segments), 1.0)
    np.testing.assert_allclose(distance_to_segments(p1, *segments), 1.0)
    np.testing.assert_array_equal(swept_segment_hit(p0, p1, np.array([0.35, 0.36]), *segments), [False, True])


def test_a_fast_disc_does_not_tunnel_through_a_thin_wall():
    segments = polygon_segments([[np.array([[0.0, -1.0], [0.0, 1.0]])]])
    p0, p1 = np.array([[-1.0, 0.0]]), np.array([[1.0, 0.0]])
    assert swept_segment_hit(p0, p1, np.array([0.1]), *segments)[0]
    assert swept_distance_to_segments(p0, p1, *segments)[0] == 0.0


def test_touching_a_wall_is_no_hit():
    segments = polygon_segments([[np.array([[0.0, 0.0], [4.0, 0.0]])]])
    p0, p1 = np.array([[1.0, 0.5]]), np.array([[3.0, 0.5]])
    assert not swept_segment_hit(p0, p1, np.array([0.5]), *segments)[0]
    assert swept_segment_hit(p0, p1, np.array([0.5000001]), *segments)[0]


def test_distances_match_shapely_on_random_walls():
    rng = np.random.default_rng(3)
    n_envs = 200
    walls = _random_walls(rng, n_envs)
    segments = polygon_segments(walls)
    p0 = rng.uniform(-3.0, 3.0, (n_envs, 2))
    p1 = p0 + rng.normal(0.0, 1.0, (n_envs, 2))
    point_distance = distance_to_segments(p0, *segments)
    swept = swept_distance_to_segments(p0, p1, *segments)
    for env in range(n_envs):
        if not walls[env]:
            assert point_distance[env] == swept[env] == np.inf
            continue
        shapely_walls = _shapely_walls(walls[env])
        assert point_distance[env] == pytest.approx(Point(p0[env]).distance(shapely_walls), abs=1e-12)
        assert swept[env] == pytest.approx(LineString([p0[env], p1[env]]).distance(shapely_walls), abs=1e-12)
    assert np.count_nonzero(swept == 0.0) > 10 and np.count_nonzero(swept > 0.0) > 10


# --------------------------------------------------------------------------------------------------------------------
# Invariants
# --------------------------------------------------------------------------------------------------------------------
coordinate = st.floats(-5.0, 5.0, allow_nan=False)
point = st.tuples(coordinate, coordinate)
wall = st.tuples(point, point).filter(lambda w: w[0] != w[1])
walls = st.lists(wall, min_size=1, max_size=6)


def _segments(wall_list):
    return polygon_segments([[np.array(w, dtype=float) for w in wall_list]])


@given(walls, st.lists(point, min_size=2, max_size=6), st.data())
def test_line_of_sight_is_symmetric_and_walls_only_hide(wall_list, agent_points, data):
    positions = np.array([agent_points], dtype=float)
    active = np.array([data.draw(st.lists(st.booleans(), min_size=len(agent_points), max_size=len(agent_points)))])
    seg_start, seg_end, n_segments = _segments(wall_list)
    visible = line_of_sight(positions, active, seg_start, seg_end, n_segments)[0]
    assert (visible == visible.T).all()
    assert (np.diag(visible) == active[0]).all()
    assert not visible[~active[0]].any()
    fewer = line_of_sight(positions, active, seg_start, seg_end, n_segments - 1)[0]  # the last wall removed
    assert (fewer | ~visible).all()  # removing a wall never hides anyone


@given(walls, point, st.floats(-math.pi, math.pi), st.integers(1, 12), st.floats(0.1, 2.0 * math.pi),
       st.lists(st.tuples(point, st.floats(0.1, 1.0)), max_size=3))
def test_scan_ranges_are_bounded_land_on_walls_and_grow_as_walls_go(wall_list, origin, heading, n_beams, fov, discs):
    seg_start, seg_end, n_segments = _segments(wall_list)
    origins, headings = np.array([origin], dtype=float), np.array([heading])
    max_range = 6.0
    ranges = range_scan(origins, headings, seg_start, seg_end, n_segments, n_beams, max_range, fov)[0]
    assert ((ranges >= 0.0) & (ranges <= max_range)).all()
    angle_min, increment = scan_angles(n_beams, fov)
    angles = heading + angle_min + increment * np.arange(n_beams)
    ends = origins + ranges[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    on_wall = distance_to_segments(ends, np.repeat(seg_start, n_beams, 0), np.repeat(seg_end, n_beams, 0),
                                   np.repeat(n_segments, n_beams))
    assert (on_wall[ranges < max_range] < 1e-9).all()  # a short beam ends on a wall
    fewer = range_scan(origins, headings, seg_start, seg_end, n_segments - 1, n_beams, max_range, fov)[0]
    assert (fewer >= ranges).all()  # removing a wall never shortens a beam
    if discs:
        circles = (np.array([[d[0] for d in discs]]), np.array([[d[1] for d in discs]]), np.ones((1, len(discs)), bool))
        with_discs = range_scan(origins, headings, seg_start, seg_end, n_segments, n_beams, max_range, fov,
                                circles=circles)[0]
        assert (with_discs <= ranges).all()


@given(walls, point, point, st.floats(0.0, 1.0))
def test_distances_are_lipschitz_and_the_sweep_bounds_the_ends(wall_list, p, q, radius):
    segments = _segments(wall_list)
    p0, p1 = np.array([p], dtype=float), np.array([q], dtype=float)
    d0, d1 = distance_to_segments(p0, *segments)[0], distance_to_segments(p1, *segments)[0]
    assert abs(d0 - d1) <= math.dist(p, q) + 1e-9
    swept = swept_distance_to_segments(p0, p1, *segments)[0]
    assert swept <= min(d0, d1) + 1e-12
    assert swept_distance_to_segments(p0, p0, *segments)[0] == pytest.approx(d0, abs=1e-12)
    assert swept_segment_hit(p0, p1, np.array([radius]), *segments)[0] == (swept < radius)
    # the path's own points are no closer to the walls than the swept distance
    for t in np.linspace(0.0, 1.0, 7):
        assert distance_to_segments(p0 + t * (p1 - p0), *segments)[0] >= swept - 1e-9


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_walls=st.integers(0, 12), n_agents=st.integers(1, 7))
def test_the_robot_row_of_sight_is_that_of_all_pairs(seed, n_walls, n_agents):
    from socnav.sim.geometry import robot_line_of_sight

    rng = np.random.default_rng(seed)
    positions = rng.uniform(-5.0, 5.0, (3, n_agents, 2))
    active = rng.random((3, n_agents)) < 0.8
    walls = [[rng.uniform(-5.0, 5.0, (2, 2)) for _ in range(n_walls)] for _ in range(3)]
    segments = polygon_segments(walls)
    everything = np.zeros(segments[0].shape[:2], dtype=bool)
    np.testing.assert_array_equal(robot_line_of_sight(positions, active, *segments, everything),
                                  line_of_sight(positions, active, *segments)[:, 0, :])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_beams=st.integers(1, 90), fov_deg=st.sampled_from([30.0, 180.0, 270.0, 360.0]),
       max_range=st.floats(0.5, 12.0))
def test_the_culled_scan_agrees_with_testing_every_beam_against_every_wall(seed, n_beams, fov_deg, max_range):
    from socnav.sim.geometry import ray_segment_distance, scan_angles

    rng = np.random.default_rng(seed)
    origins, headings = rng.uniform(-3.0, 3.0, (2, 2)), rng.uniform(-np.pi, np.pi, 2)
    walls = [[rng.uniform(-6.0, 6.0, (2, 2)) for _ in range(10)] for _ in range(2)]
    segments = polygon_segments(walls)
    fov = np.radians(fov_deg)
    ranges = range_scan(origins, headings, *segments, n_beams, max_range, fov)
    angle_min, increment = scan_angles(n_beams, fov)
    for env in range(2):
        for beam in range(n_beams):
            angle = headings[env] + angle_min + beam * increment
            expected = min([max_range] + [ray_segment_distance(origins[env, 0], origins[env, 1], np.cos(angle),
                                                               np.sin(angle), *wall[0], *wall[1])
                                          for wall in walls[env]])
            assert ranges[env, beam] == pytest.approx(expected, abs=1e-9)  # beam directions rotated, not re-sined


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_points_in_polygons_and_their_distances_agree_with_shapely(seed):
    from shapely.geometry import Polygon

    from socnav.sim.geometry import points_in_polygons, points_to_segments

    rng = np.random.default_rng(seed)
    polygons = []
    for _ in range(3):  # star-shaped (simple) polygons of 3-9 vertices
        n = int(rng.integers(3, 10))
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        radii = rng.uniform(0.5, 3.0, n)
        polygons.append(rng.uniform(-4, 4, 2) + np.stack([radii * np.cos(angles), radii * np.sin(angles)], 1))
    points = rng.uniform(-7, 7, (40, 2))
    offsets = np.cumsum([0] + [len(p) for p in polygons]).astype(np.int64)
    inside = points_in_polygons(points, np.concatenate(polygons), offsets)
    segments = polygon_segments([polygons])
    distance = points_to_segments(points, segments[0][0], segments[1][0], int(segments[2][0]))
    for k, point in enumerate(points):
        shapes = [Polygon(p) for p in polygons]
        assert min(shape.exterior.distance(Point(point)) for shape in shapes) == pytest.approx(distance[k], abs=1e-12)
        for p, shape in enumerate(shapes):
            if shape.exterior.distance(Point(point)) > 1e-9:
                assert inside[k, p] == shape.contains(Point(point))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_skipping_the_edges_facing_away_changes_no_range_from_free_space(seed):
    from socnav.sim.walls import Walls

    rng = np.random.default_rng(seed)
    boxes = []
    for _ in range(4):  # counter-clockwise (solid) boxes and one clockwise room around everything
        x, y, w, h = rng.uniform(-5, 4), rng.uniform(-5, 4), rng.uniform(0.3, 2), rng.uniform(0.3, 2)
        boxes.append(np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]]))
    room = np.array([[-8.0, -8.0], [-8.0, 8.0], [8.0, 8.0], [8.0, -8.0]])
    polygons = [*boxes, room, rng.uniform(-6, 6, (2, 2))]
    walls = Walls(polygons, 8)
    origins = rng.uniform(-7.5, 7.5, (8, 2))
    free = np.array([walls.misplaced(o[None], np.array([1e-6])) is None for o in origins])
    headings = rng.uniform(-np.pi, np.pi, 8)
    culled = range_scan(origins, headings, walls.seg_start, walls.seg_end, walls.n_segments, 45, 9.0,
                        one_sided=walls.one_sided)
    every = range_scan(origins, headings, walls.seg_start, walls.seg_end, walls.n_segments, 45, 9.0)
    np.testing.assert_array_equal(culled[free], every[free])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_skipping_the_edges_facing_away_changes_no_sight_line_from_free_space(seed):
    from socnav.sim.geometry import robot_line_of_sight
    from socnav.sim.walls import Walls

    rng = np.random.default_rng(seed)
    boxes = []
    for _ in range(4):
        x, y, w, h = rng.uniform(-5, 4), rng.uniform(-5, 4), rng.uniform(0.3, 2), rng.uniform(0.3, 2)
        boxes.append(np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]]))
    polygons = [*boxes, np.array([[-8.0, -8.0], [-8.0, 8.0], [8.0, 8.0], [8.0, -8.0]]), rng.uniform(-6, 6, (2, 2))]
    walls = Walls(polygons, 6)
    positions = rng.uniform(-7.5, 7.5, (6, 7, 2))
    active = np.ones((6, 7), dtype=bool)
    free = np.array([walls.misplaced(p[:1], np.array([1e-6])) is None for p in positions])
    every = np.zeros_like(walls.one_sided)
    culled = robot_line_of_sight(positions, active, walls.seg_start, walls.seg_end, walls.n_segments, walls.one_sided)
    full = robot_line_of_sight(positions, active, walls.seg_start, walls.seg_end, walls.n_segments, every)
    np.testing.assert_array_equal(culled[free], full[free])
