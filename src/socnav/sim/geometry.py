"""Batched wall geometry for the world, compiled with numba: line of sight between agents, a LaserScan-like range
scan, and the distance from a point or a swept disc to the walls, over E environments at once.

Walls are line segments in padded arrays: `seg_start`, `seg_end` of shape (E, S, 2) and `n_segments` (E,), env e
using segments 0..n_segments[e]-1 (`polygon_segments` builds them from RVO2-ordered polygons, `socnav.sim.maps`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

__all__ = [
    "discs_clear",
    "distance_to_segments",
    "line_of_sight",
    "points_in_polygons",
    "points_to_segments",
    "polygon_segments",
    "range_scan",
    "ray_segment_distance",
    "robot_line_of_sight",
    "scan_angles",
    "swept_distance_to_segments",
    "swept_segment_hit",
]


def polygon_segments(polygons_per_env: Sequence[Sequence[np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge segments of each environment's polygons, padded to the most edges of any environment.

    A polygon of k >= 3 vertices gives its k edges, the closing edge (v[k-1], v[0]) included, whatever its
    orientation; a two-vertex polygon gives one segment. Returns (seg_start (E, S, 2), seg_end (E, S, 2),
    n_segments (E,) int64); padding is zero and never read.
    """
    edges_per_env = []
    for polygons in polygons_per_env:
        starts, ends = [], []
        for vertices in polygons:
            vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 2)
            if len(vertices) < 2:
                raise ValueError(f"a polygon needs at least 2 vertices, got {len(vertices)}")
            closed = len(vertices) >= 3
            starts.append(vertices if closed else vertices[:1])
            ends.append(np.roll(vertices, -1, axis=0) if closed else vertices[1:])
        edges_per_env.append((np.concatenate(starts) if starts else np.zeros((0, 2)),
                              np.concatenate(ends) if ends else np.zeros((0, 2))))
    n_segments = np.array([len(starts) for starts, _ in edges_per_env], dtype=np.int64)
    width = int(n_segments.max()) if len(n_segments) else 0
    seg_start = np.zeros((len(edges_per_env), width, 2))
    seg_end = np.zeros((len(edges_per_env), width, 2))
    for env, (env_starts, env_ends) in enumerate(edges_per_env):
        seg_start[env, : len(env_starts)] = env_starts
        seg_end[env, : len(env_ends)] = env_ends
    return seg_start, seg_end, n_segments


# --------------------------------------------------------------------------------------------------------------------
# Scalar primitives (scalars in, scalars out)
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _orientation(ax, ay, bx, by, cx, cy):
    """(b - a) x (c - a): > 0 when c lies left of the directed line a -> b, 0 when the three are collinear."""
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@numba.njit(cache=True)
def _within_box(ax, ay, bx, by, cx, cy):
    """For c collinear with a and b: whether c lies on the closed segment [a, b]."""
    return min(ax, bx) <= cx <= max(ax, bx) and min(ay, by) <= cy <= max(ay, by)


@numba.njit(cache=True)
def _segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
    """Whether the closed segments [a, b] and [c, d] share a point, touching included (orientation test, e.g. de Berg
    et al., Computational Geometry, ch. 2): each segment's ends lie on opposite sides of the other's line, or one end
    lies on the other segment."""
    d1 = _orientation(cx, cy, dx, dy, ax, ay)
    d2 = _orientation(cx, cy, dx, dy, bx, by)
    d3 = _orientation(ax, ay, bx, by, cx, cy)
    d4 = _orientation(ax, ay, bx, by, dx, dy)
    if ((d1 > 0.0 and d2 < 0.0) or (d1 < 0.0 and d2 > 0.0)) and ((d3 > 0.0 and d4 < 0.0) or (d3 < 0.0 and d4 > 0.0)):
        return True
    return ((d1 == 0.0 and _within_box(cx, cy, dx, dy, ax, ay))
            or (d2 == 0.0 and _within_box(cx, cy, dx, dy, bx, by))
            or (d3 == 0.0 and _within_box(ax, ay, bx, by, cx, cy))
            or (d4 == 0.0 and _within_box(ax, ay, bx, by, dx, dy)))


@numba.njit(cache=True)
def _point_segment_distance(px, py, ax, ay, bx, by):
    """Distance from p to the closed segment [a, b]: to the projection a + t (b - a), t = clip((p-a).(b-a)/|b-a|^2)."""
    ex, ey = bx - ax, by - ay
    length_squared = ex * ex + ey * ey
    t = 0.0
    if length_squared > 0.0:
        t = min(max(((px - ax) * ex + (py - ay) * ey) / length_squared, 0.0), 1.0)
    return math.hypot(px - (ax + t * ex), py - (ay + t * ey))


@numba.njit(cache=True)
def _segment_segment_distance(ax, ay, bx, by, cx, cy, dx, dy):
    """Distance between the closed segments [a, b] and [c, d]: 0 if they intersect, else the least of the four
    endpoint-to-segment distances (the closest pair of non-crossing segments includes an endpoint)."""
    if _segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
        return 0.0
    return min(
        min(_point_segment_distance(ax, ay, cx, cy, dx, dy), _point_segment_distance(bx, by, cx, cy, dx, dy)),
        min(_point_segment_distance(cx, cy, ax, ay, bx, by), _point_segment_distance(dx, dy, ax, ay, bx, by)),
    )


@numba.njit(cache=True)
def ray_segment_distance(ox, oy, ux, uy, ax, ay, bx, by):
    """Distance t >= 0 along the unit ray o + t u to the closed segment [a, b], or inf if the ray misses it.

    With e = b - a and w = a - o, o + t u = a + s e solves to t = (w x e) / (u x e), s = (w x u) / (u x e), a hit when
    t >= 0 and 0 <= s <= 1. A segment along the ray (u x e = 0, w x u = 0) is hit at its nearer end ahead of o
    (t = 0 when o lies on it).
    """
    ex, ey = bx - ax, by - ay
    wx, wy = ax - ox, ay - oy
    denominator = ux * ey - uy * ex
    if denominator == 0.0:
        if wx * uy - wy * ux != 0.0:
            return np.inf  # parallel, off the ray's line
        t_a = wx * ux + wy * uy
        t_b = (bx - ox) * ux + (by - oy) * uy
        if max(t_a, t_b) < 0.0:
            return np.inf  # behind the origin
        return max(min(t_a, t_b), 0.0)
    t = (wx * ey - wy * ex) / denominator
    s = (wx * uy - wy * ux) / denominator
    if t >= 0.0 and 0.0 <= s <= 1.0:
        return t
    return np.inf


@numba.njit(cache=True)
def _ray_circle_distance(ox, oy, ux, uy, cx, cy, radius):
    """Distance t >= 0 along the unit ray o + t u to the circle |x - c| = radius, 0 if o is inside it, inf on a miss:
    the smaller root of t^2 + 2 b t + k = 0, b = u.(o - c), k = |o - c|^2 - radius^2."""
    fx, fy = ox - cx, oy - cy
    k = fx * fx + fy * fy - radius * radius
    if k <= 0.0:
        return 0.0
    b = ux * fx + uy * fy
    discriminant = b * b - k
    if b >= 0.0 or discriminant < 0.0:
        return np.inf  # the circle lies behind the origin (k > 0 and b >= 0: both roots negative), or is missed
    return -b - math.sqrt(discriminant)


# --------------------------------------------------------------------------------------------------------------------
# Batched kernels
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def line_of_sight(positions, active, seg_start, seg_end, n_segments):
    """(E, N, N) bool: whether agents i and j of each environment see each other.

    Both must be active, and the closed segment between their centres must share no point with any wall segment:
    a sight line that only touches a wall (grazes a corner or an end) counts as blocked, the conservative choice,
    which also makes a line through two opposite corners of a solid polygon blocked. Symmetric; an active agent
    sees itself. positions (E, N, 2), active (E, N) bool.
    """
    n_envs, n_agents = active.shape
    visible = np.zeros((n_envs, n_agents, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        for i in range(n_agents):
            if not active[env, i]:
                continue
            visible[env, i, i] = True
            ax, ay = positions[env, i, 0], positions[env, i, 1]
            for j in range(i + 1, n_agents):
                if not active[env, j]:
                    continue
                bx, by = positions[env, j, 0], positions[env, j, 1]
                clear = True
                for s in range(n_segments[env]):
                    if _segments_intersect(ax, ay, bx, by, seg_start[env, s, 0], seg_start[env, s, 1],
                                           seg_end[env, s, 0], seg_end[env, s, 1]):
                        clear = False
                        break
                visible[env, i, j] = clear
                visible[env, j, i] = clear
    return visible


@numba.njit(cache=True)
def robot_line_of_sight(positions, active, seg_start, seg_end, n_segments, one_sided):
    """(E, N) bool: `line_of_sight(...)[:, 0, :]`, the row of the robot (slot 0) alone: which agents it sees.

    The per-step form: N - 1 sight lines per environment instead of N (N - 1) / 2, and a wall whose bounding box
    misses the sight line's is skipped before the exact test (the same answer, `tests/sim/test_geometry.py`).
    `one_sided` (E, S) bool marks the edges of closed polygons (solid on their left, as `range_scan` reads it): from
    a robot in free space a sight line into a polygon crosses an edge facing the robot first, so the edges with the
    robot on their solid side are skipped (all False: every edge is tested).
    """
    n_envs, n_agents = active.shape
    visible = np.zeros((n_envs, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        if not active[env, 0]:
            continue
        visible[env, 0] = True
        ax, ay = positions[env, 0, 0], positions[env, 0, 1]
        for j in range(1, n_agents):
            if not active[env, j]:
                continue
            bx, by = positions[env, j, 0], positions[env, j, 1]
            low_x, high_x, low_y, high_y = min(ax, bx), max(ax, bx), min(ay, by), max(ay, by)
            clear = True
            for s in range(n_segments[env]):
                cx, cy, dx, dy = seg_start[env, s, 0], seg_start[env, s, 1], seg_end[env, s, 0], seg_end[env, s, 1]
                if max(cx, dx) < low_x or min(cx, dx) > high_x or max(cy, dy) < low_y or min(cy, dy) > high_y:
                    continue
                if one_sided[env, s] and _orientation(cx, cy, dx, dy, ax, ay) > 0.0:
                    continue
                if _segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
                    clear = False
                    break
            visible[env, j] = clear
    return visible


@numba.njit(cache=True)
def points_to_segments(points, seg_start, seg_end, n_segments):
    """(K,) least distance from each point (K, 2) to the first `n_segments` segments (S, 2) of ONE map; inf if none."""
    distance = np.full(points.shape[0], np.inf)
    for k in range(points.shape[0]):
        for s in range(n_segments):
            distance[k] = min(distance[k], _point_segment_distance(points[k, 0], points[k, 1], seg_start[s, 0],
                                                                   seg_start[s, 1], seg_end[s, 0], seg_end[s, 1]))
    return distance


@numba.njit(cache=True)
def points_in_polygons(points, vertices, offsets):
    """(K, P) bool: whether point k lies inside polygon p (crossing number; a point on the boundary may fall either
    way). Polygon p's vertices are vertices[offsets[p]:offsets[p + 1]] (closed implicitly)."""
    n_polygons = offsets.shape[0] - 1
    inside = np.zeros((points.shape[0], n_polygons), dtype=np.bool_)
    for k in range(points.shape[0]):
        px, py = points[k, 0], points[k, 1]
        for p in range(n_polygons):
            first, last = offsets[p], offsets[p + 1]
            crossing = False
            j = last - 1
            for i in range(first, last):
                xi, yi, xj, yj = vertices[i, 0], vertices[i, 1], vertices[j, 0], vertices[j, 1]
                if (yi > py) != (yj > py) and px < (xj - xi) * (py - yi) / (yj - yi) + xi:
                    crossing = not crossing
                j = i
            inside[k, p] = crossing
    return inside


@numba.njit(cache=True)
def discs_clear(points, radii, seg_start, seg_end, n_segments, vertices, offsets, area_sizes, solid_inside,
                solid_outside):
    """Whether every disc (points (K, 2), radii (K,)) lies in free space at least its radius from every wall of ONE
    map: `points_to_segments` >= radius, and free by the nesting rule of `socnav.sim.maps.clearance_violation` (the
    smallest closed polygon containing the point is clockwise; in none: no top-level clockwise polygon,
    `solid_outside` False). Closed polygons as in `points_in_polygons`, with their areas and orientations."""
    inside = points_in_polygons(points, vertices, offsets)
    distance = points_to_segments(points, seg_start, seg_end, n_segments)
    for k in range(points.shape[0]):
        if distance[k] < radii[k]:
            return False
        innermost, smallest = -1, np.inf
        for p in range(area_sizes.shape[0]):
            if inside[k, p] and area_sizes[p] < smallest:
                innermost, smallest = p, area_sizes[p]
        solid = solid_outside if innermost < 0 else solid_inside[innermost]
        if solid:
            return False
    return True


def scan_angles(n_beams: int, fov: float) -> tuple[float, float]:
    """(angle_min, angle_increment) of a scan, relative to the heading, as in sensor_msgs/LaserScan.

    Beams run counter-clockwise from -fov/2; with fov < 2 pi the last beam is at +fov/2 (increment fov / (n - 1);
    a single beam points along the heading), with fov = 2 pi the increment is 2 pi / n so that no beam repeats
    the first one.
    """
    if isinstance(n_beams, bool) or int(n_beams) != n_beams or n_beams < 1:
        raise ValueError(f"n_beams must be an integer >= 1, got {n_beams!r}")
    if not 0.0 < fov <= 2.0 * math.pi:
        raise ValueError(f"fov must be in (0, 2 pi] radians, got {fov!r}")
    if fov == 2.0 * math.pi:
        return -math.pi, 2.0 * math.pi / n_beams
    if n_beams == 1:
        return 0.0, 0.0
    return -fov / 2.0, fov / (n_beams - 1)


@numba.njit(cache=True)
def _scan_segment(ranges, env, low, high, ox, oy, cos_h, sin_h, relative_x, relative_y, n_beams, wraps, ax, ay, bx,
                  by):
    """Shorten beams low..high (indices wrapped in a 360-degree scan, else clipped) to the wall [a, b] they hit;
    a beam's direction is its direction relative to the heading (relative_x, relative_y) turned by the heading."""
    for k in range(low, high + 1):
        beam = k % n_beams if wraps else k
        if beam < 0 or beam >= n_beams:
            continue
        ux = cos_h * relative_x[beam] - sin_h * relative_y[beam]
        uy = sin_h * relative_x[beam] + cos_h * relative_y[beam]
        t = ray_segment_distance(ox, oy, ux, uy, ax, ay, bx, by)
        if t < ranges[env, beam]:
            ranges[env, beam] = t


@numba.njit(cache=True, inline="always")
def _beyond_range(ox, oy, ax, ay, bx, by, max_range):
    """Whether the wall [a, b] lies beyond `max_range` from o along an axis, so beyond it (a hit there would read
    max_range anyway)."""
    return (min(ax, bx) - ox >= max_range or ox - max(ax, bx) >= max_range or min(ay, by) - oy >= max_range
            or oy - max(ay, by) >= max_range)


@numba.njit(cache=True, inline="always")
def _on_wall(ox, oy, ax, ay, bx, by):
    """Whether the origin o lies on the wall [a, b] (then every beam reads 0)."""
    return (min(ax, bx) <= ox <= max(ax, bx) and min(ay, by) <= oy <= max(ay, by)
            and _point_segment_distance(ox, oy, ax, ay, bx, by) < 1e-9)


@numba.njit(cache=True, inline="always")
def _angular_extent(ox, oy, ax, ay, bx, by, first):
    """The directions the wall [a, b] covers seen from o, relative to beam 0's direction `first`: (start, width),
    start in [-pi, pi), the extent [start, start + width] (a segment subtends at most pi)."""
    full_turn = 2.0 * math.pi
    angle_a = math.atan2(ay - oy, ax - ox)
    span = math.atan2(by - oy, bx - ox) - angle_a
    if span > math.pi:
        span -= full_turn
    elif span < -math.pi:
        span += full_turn
    start = (angle_a if span >= 0.0 else angle_a + span) - first
    while start >= math.pi:
        start -= full_turn
    while start < -math.pi:
        start += full_turn
    return start, abs(span)


@numba.njit(cache=True, inline="always")
def _scan_circles(ranges, env, ox, oy, cos_h, sin_h, relative_x, relative_y, circle_positions, circle_radii,
                  circle_active):
    """Shorten environment `env`'s beams to the first active circle each one hits (`_ray_circle_distance`)."""
    for beam in range(ranges.shape[1]):
        ux = cos_h * relative_x[beam] - sin_h * relative_y[beam]
        uy = sin_h * relative_x[beam] + cos_h * relative_y[beam]
        nearest = ranges[env, beam]
        for c in range(circle_radii.shape[1]):
            if circle_active[env, c]:
                nearest = min(nearest, _ray_circle_distance(ox, oy, ux, uy, circle_positions[env, c, 0],
                                                            circle_positions[env, c, 1], circle_radii[env, c]))
        ranges[env, beam] = nearest


@numba.njit(cache=True)
def _range_scan_kernel(origins, headings, seg_start, seg_end, n_segments, n_beams, angle_min, angle_increment,
                       max_range, circle_positions, circle_radii, circle_active, one_sided):
    # Each wall is tested only against the beams within its angular extent seen from the origin (one beam of margin
    # each side), and not at all when it lies beyond max_range: the exact ray test decides every remaining pair, so
    # the ranges are those of testing every beam against every wall.
    n_envs = origins.shape[0]
    ranges = np.full((n_envs, n_beams), max_range)
    full_turn = 2.0 * math.pi
    wraps = abs(n_beams * angle_increment - full_turn) < 1e-12  # a 360-degree scan: beam indices wrap around
    # The beams' directions relative to the heading, once; each environment rotates them by its heading (a rotation
    # instead of a cosine and a sine per beam: equal to them within a few ulps).
    relative_x, relative_y = np.empty(n_beams), np.empty(n_beams)
    for beam in range(n_beams):
        relative_x[beam] = math.cos(angle_min + beam * angle_increment)
        relative_y[beam] = math.sin(angle_min + beam * angle_increment)
    n_circles = circle_radii.shape[1]
    for env in range(n_envs):
        ox, oy = origins[env, 0], origins[env, 1]
        first = headings[env] + angle_min
        cos_h, sin_h = math.cos(headings[env]), math.sin(headings[env])
        for s in range(n_segments[env]):
            ax, ay, bx, by = seg_start[env, s, 0], seg_start[env, s, 1], seg_end[env, s, 0], seg_end[env, s, 1]
            if one_sided[env, s] and _orientation(ax, ay, bx, by, ox, oy) > 0.0:
                continue  # the origin on the solid side of a polygon's edge: a beam leaves solid there, never first
            if _beyond_range(ox, oy, ax, ay, bx, by, max_range):
                continue
            if angle_increment == 0.0 or _on_wall(ox, oy, ax, ay, bx, by):
                _scan_segment(ranges, env, 0, n_beams - 1, ox, oy, cos_h, sin_h, relative_x, relative_y, n_beams, wraps,
                              ax, ay, bx, by)  # one beam, or the origin on the wall: every beam
                continue
            start, width = _angular_extent(ox, oy, ax, ay, bx, by, first)
            for offset in (0.0, full_turn):  # beams run over [0, fov]: the extent, or its copy one turn on
                if wraps and offset > 0.0:
                    break
                low = math.floor((start + offset) / angle_increment) - 1
                high = math.ceil((start + offset + width) / angle_increment) + 1
                _scan_segment(ranges, env, low, high, ox, oy, cos_h, sin_h, relative_x, relative_y, n_beams, wraps,
                              ax, ay, bx, by)
        if n_circles > 0:
            _scan_circles(ranges, env, ox, oy, cos_h, sin_h, relative_x, relative_y, circle_positions, circle_radii,
                          circle_active)
    return ranges


def range_scan(
    origins: np.ndarray,
    headings: np.ndarray,
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    n_segments: np.ndarray,
    n_beams: int,
    max_range: float,
    fov: float = 2.0 * math.pi,
    circles: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    one_sided: np.ndarray | None = None,
) -> np.ndarray:
    """(E, n_beams) float64 ranges of a planar laser scan from each environment's `origins[e]` (E, 2), like a
    sensor_msgs/LaserScan: beam b points at headings[e] + angle_min + b angle_increment (`scan_angles`), and reads
    the distance to the first wall it hits, `max_range` if none is hit within it (hits beyond are cut to it).

    Walls only by default. `circles` = (positions (E, M, 2), radii (E, M), active (E, M)) adds discs the beams stop
    at, e.g. the humans: ``(positions[:, 1:], radii[:, 1:], active[:, 1:])`` -- leave the robot's own slot out, as a
    beam starting inside a disc reads 0 (as does one starting on a wall).

    `one_sided` (E, S) bool, optional: the segments that are edges of closed polygons (RVO2 orientation: solid on
    their left); a beam from free space first enters solid through an edge whose left side faces away from the
    origin, so the others are skipped -- the same ranges from any origin in free space, in about half the time.
    """
    if not (math.isfinite(max_range) and max_range > 0.0):
        raise ValueError(f"max_range must be a finite number > 0 (metres), got {max_range!r}")
    angle_min, angle_increment = scan_angles(n_beams, fov)
    origins = np.asarray(origins, dtype=np.float64)
    n_envs = origins.shape[0]
    if circles is None:
        circles = (np.zeros((n_envs, 0, 2)), np.zeros((n_envs, 0)), np.zeros((n_envs, 0), dtype=np.bool_))
    circle_positions, circle_radii, circle_active = circles
    if one_sided is None:
        one_sided = np.zeros(seg_start.shape[:2], dtype=np.bool_)
    return _range_scan_kernel(
        origins, np.asarray(headings, dtype=np.float64), seg_start, seg_end, n_segments, int(n_beams), angle_min,
        angle_increment, float(max_range), np.asarray(circle_positions, dtype=np.float64),
        np.asarray(circle_radii, dtype=np.float64), np.asarray(circle_active, dtype=np.bool_), one_sided,
    )


@numba.njit(cache=True)
def distance_to_segments(points, seg_start, seg_end, n_segments):
    """(E,) least distance from each environment's point (E, 2) to its wall segments; inf where it has none."""
    n_envs = points.shape[0]
    distance = np.full(n_envs, np.inf)
    for env in range(n_envs):
        for s in range(n_segments[env]):
            distance[env] = min(distance[env], _point_segment_distance(
                points[env, 0], points[env, 1], seg_start[env, s, 0], seg_start[env, s, 1], seg_end[env, s, 0],
                seg_end[env, s, 1]))
    return distance


@numba.njit(cache=True)
def swept_distance_to_segments(p0, p1, seg_start, seg_end, n_segments):
    """(E,) least distance from the path segment [p0[e], p1[e]] (E, 2 each) to the walls; inf where there are none.
    A disc of radius r moving along the path comes closest to the walls at this distance, so its swept gap is this
    minus r."""
    n_envs = p0.shape[0]
    distance = np.full(n_envs, np.inf)
    for env in range(n_envs):
        for s in range(n_segments[env]):
            distance[env] = min(distance[env], _segment_segment_distance(
                p0[env, 0], p0[env, 1], p1[env, 0], p1[env, 1], seg_start[env, s, 0], seg_start[env, s, 1],
                seg_end[env, s, 0], seg_end[env, s, 1]))
    return distance


def swept_segment_hit(
    p0: np.ndarray, p1: np.ndarray, radius: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray,
    n_segments: np.ndarray,
) -> np.ndarray:
    """(E,) bool: whether a disc of `radius` (E,) moving straight from p0 to p1 (E, 2) overlaps a wall on the way:
    swept distance < radius. Touching (distance == radius) is no hit, as in the world, where only a negative gap is a
    collision."""
    return _swept_hit_kernel(np.ascontiguousarray(p0, dtype=np.float64), np.ascontiguousarray(p1, dtype=np.float64),
                             np.asarray(radius, dtype=np.float64), seg_start, seg_end, n_segments)


@numba.njit(cache=True)
def _swept_hit_kernel(p0, p1, radius, seg_start, seg_end, n_segments):
    """`swept_distance_to_segments(...) < radius`, skipping the walls farther from p0 than radius + |p1 - p0| (the
    path cannot come closer to them than that)."""
    n_envs = p0.shape[0]
    hit = np.zeros(n_envs, dtype=np.bool_)
    for env in range(n_envs):
        step = math.hypot(p1[env, 0] - p0[env, 0], p1[env, 1] - p0[env, 1])
        reach = radius[env]  # the path's bounding box grown by the radius: walls outside it cannot be touched
        low_x, high_x = min(p0[env, 0], p1[env, 0]) - reach, max(p0[env, 0], p1[env, 0]) + reach
        low_y, high_y = min(p0[env, 1], p1[env, 1]) - reach, max(p0[env, 1], p1[env, 1]) + reach
        for s in range(n_segments[env]):
            ax, ay, bx, by = seg_start[env, s, 0], seg_start[env, s, 1], seg_end[env, s, 0], seg_end[env, s, 1]
            if max(ax, bx) < low_x or min(ax, bx) > high_x or max(ay, by) < low_y or min(ay, by) > high_y:
                continue
            if _point_segment_distance(p0[env, 0], p0[env, 1], ax, ay, bx, by) - step >= radius[env]:
                continue
            if _segment_segment_distance(p0[env, 0], p0[env, 1], p1[env, 0], p1[env, 1], ax, ay, bx, by) < radius[env]:
                hit[env] = True
                break
    return hit
