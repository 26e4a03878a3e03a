"""Static obstacles for the ORCA kernel: RVO2's processed obstacle vertices and obstacle k-d tree as flat arrays, one
map (`ObstacleMap`) or one per environment, padded (`ObstacleBatch`), and RVO2's visibility query on them.

Follows RVO2 2.0.3 (the library pyrvo wraps): `RVOSimulator::addObstacle` links each polygon's vertices into a ring
(vertex k is the start of the edge k -> next[k]; counter-clockwise polygons are solid, a two-vertex polygon is a wall
blocking both sides), `KdTree::buildObstacleTree` (`processObstacles`) builds a binary space partition of the edges,
SPLITTING every edge that straddles a partition line (the new vertex is convex), and `KdTree::queryVisibilityRecursive`
answers line-of-sight queries. The tree is kept (not replaced by a brute-force scan) because its traversal order
decides the order of equidistant obstacle neighbours -- the two edges meeting at the corner nearest an agent tie
exactly -- on which RVO2's "already covered" test and linearProgram3 depend; it also prunes visibility queries
differently from a scan in corner cases. The ORCA kernel's own obstacle code (neighbours, half-planes) is in
`socnav.sim.orca`, in the kernel's file so that numba's cache of the kernel stays in step with it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np

from socnav.sim.maps import MAX_TOTAL_VERTICES, MapError

__all__ = [
    "MAX_TOTAL_VERTICES",
    "RVO_EPSILON",
    "ObstacleBatch",
    "ObstacleMap",
    "process_obstacles",
    "query_visibility",
]

# RVO2's RVO_EPSILON: two lines are parallel when |det(d_a, d_b)| <= RVO_EPSILON; an edge end within it of a partition
# line counts as on the line; an obstacle half-plane is "already covered" up to it. `socnav.sim.orca` imports it (numba
# freezes it into that file's cached kernels: it is RVO2's constant, never to be edited).
RVO_EPSILON = 1e-5


# --------------------------------------------------------------------------------------------------------------------
# Small vector helpers (scalars in, scalars out).
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _left_of(ax, ay, bx, by, cx, cy):
    """RVO2 leftOf(a, b, c) = det(a - c, b - a): > 0 when c lies to the left of the directed line a -> b."""
    return (ax - cx) * (by - ay) - (ay - cy) * (bx - ax)


@numba.njit(cache=True)
def _pair_less(a_first, a_second, b_first, b_second):
    """Lexicographic (a_first, a_second) < (b_first, b_second), as std::pair's operator<."""
    return a_first < b_first or (a_first == b_first and a_second < b_second)


# --------------------------------------------------------------------------------------------------------------------
# Processing (RVOSimulator::addObstacle + KdTree::buildObstacleTree), once per map.
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _grown_float2(array, capacity):
    grown = np.empty((capacity, 2), dtype=np.float64)
    grown[: array.shape[0]] = array
    return grown


@numba.njit(cache=True)
def _grown_int(array, capacity):
    grown = np.full(capacity, -1, dtype=np.int64)
    grown[: array.shape[0]] = array
    return grown


@numba.njit(cache=True)
def _grown_bool(array, capacity):
    grown = np.zeros(capacity, dtype=np.bool_)
    grown[: array.shape[0]] = array
    return grown


@numba.njit(cache=True)
def _sides_of_edge(point, i1, i2, j1, j2):
    """leftOf(i1, i2, .) of edge j1 -> j2's two ends: where the edge lies with respect to the line i1 -> i2."""
    j1_left = _left_of(point[i1, 0], point[i1, 1], point[i2, 0], point[i2, 1], point[j1, 0], point[j1, 1])
    j2_left = _left_of(point[i1, 0], point[i1, 1], point[i2, 0], point[i2, 1], point[j2, 0], point[j2, 1])
    return j1_left, j2_left


@numba.njit(cache=True)
def _optimal_split(point, next_vertex, pool, start, size):
    """The edge of pool[start:start + size] whose line best balances the others between its two sides: minimise
    (larger side, smaller side), an edge crossing the line counting on both (ties: the first such edge). Returns
    (left count, right count, index of the edge in the list)."""
    min_left, min_right, optimal = size, size, 0
    best_larger, best_smaller = size, size
    for i in range(size):
        i1 = pool[start + i]
        i2 = next_vertex[i1]
        left_size, right_size = 0, 0
        for j in range(size):
            if i == j:
                continue
            j1 = pool[start + j]
            j1_left, j2_left = _sides_of_edge(point, i1, i2, j1, next_vertex[j1])
            if j1_left >= -RVO_EPSILON and j2_left >= -RVO_EPSILON:
                left_size += 1
            elif j1_left <= RVO_EPSILON and j2_left <= RVO_EPSILON:
                right_size += 1
            else:
                left_size += 1
                right_size += 1
            # Counts only grow, so this candidate can no longer beat the best one.
            if not _pair_less(max(left_size, right_size), min(left_size, right_size), best_larger, best_smaller):
                break
        if _pair_less(max(left_size, right_size), min(left_size, right_size), best_larger, best_smaller):
            min_left, min_right, optimal = left_size, right_size, i
            best_larger, best_smaller = max(min_left, min_right), min(min_left, min_right)
    return min_left, min_right, optimal


@numba.njit(cache=True)
def _split_edge(point, unit_dir, is_convex, next_vertex, prev_vertex, i1, i2, j1, j2, split):
    """Split edge j1 -> j2 where it crosses the line i1 -> i2, at j1 + t (j2 - j1) with
    t = det(i2 - i1, j1 - i1) / det(i2 - i1, j1 - j2); the new vertex `split` continues the edge (RVO2)."""
    ex, ey = point[i2, 0] - point[i1, 0], point[i2, 1] - point[i1, 1]
    t = (ex * (point[j1, 1] - point[i1, 1]) - ey * (point[j1, 0] - point[i1, 0])) / (
        ex * (point[j1, 1] - point[j2, 1]) - ey * (point[j1, 0] - point[j2, 0])
    )
    point[split, 0] = point[j1, 0] + t * (point[j2, 0] - point[j1, 0])
    point[split, 1] = point[j1, 1] + t * (point[j2, 1] - point[j1, 1])
    unit_dir[split, 0], unit_dir[split, 1] = unit_dir[j1, 0], unit_dir[j1, 1]
    is_convex[split] = True
    next_vertex[split], prev_vertex[split] = j2, j1
    next_vertex[j1], prev_vertex[j2] = split, split


@numba.njit(cache=True)
def _partition(point, unit_dir, is_convex, next_vertex, prev_vertex, pool, start, size, optimal, left_start,
               right_start, n_vertices):
    """Write the edges of pool[start:start + size] other than the partition edge `optimal` into the left list
    (from left_start) and the right list (from right_start), in their order, splitting those that cross its line;
    the arrays must have room for `size` more vertices. Returns the vertex count after the splits."""
    left_count, right_count = 0, 0
    i1 = pool[start + optimal]
    i2 = next_vertex[i1]
    for j in range(size):
        if j == optimal:
            continue
        j1 = pool[start + j]
        j2 = next_vertex[j1]
        j1_left, j2_left = _sides_of_edge(point, i1, i2, j1, j2)
        if j1_left >= -RVO_EPSILON and j2_left >= -RVO_EPSILON:
            pool[left_start + left_count] = j1
            left_count += 1
        elif j1_left <= RVO_EPSILON and j2_left <= RVO_EPSILON:
            pool[right_start + right_count] = j1
            right_count += 1
        else:
            split = n_vertices
            n_vertices += 1
            _split_edge(point, unit_dir, is_convex, next_vertex, prev_vertex, i1, i2, j1, j2, split)
            if j1_left > 0.0:
                pool[left_start + left_count], pool[right_start + right_count] = j1, split
            else:
                pool[right_start + right_count], pool[left_start + left_count] = j1, split
            left_count += 1
            right_count += 1
    return n_vertices


@numba.njit(cache=True)
def _build_obstacle_tree(point, unit_dir, is_convex, next_vertex, prev_vertex):
    """RVO2 KdTree::buildObstacleTreeRecursive, iteratively, on the addObstacle rings of `n` vertices.

    Each node's partition line is the edge that best balances the others between its two sides (ties: the first
    such edge); edges crossing it are split. Returns the vertex arrays grown by the split vertices (ids in RVO2's
    creation order), and the tree: tree_vertex[node] (the edge's start vertex), tree_left / tree_right[node] (child
    node or -1), nodes numbered in creation (pre-)order, node 0 the root, one node per vertex.
    """
    n_vertices = point.shape[0]
    capacity = max(16, 2 * n_vertices)
    point, unit_dir = _grown_float2(point, capacity), _grown_float2(unit_dir, capacity)
    is_convex = _grown_bool(is_convex, capacity)
    next_vertex, prev_vertex = _grown_int(next_vertex, capacity), _grown_int(prev_vertex, capacity)
    tree_vertex = np.full(capacity, -1, dtype=np.int64)
    tree_left = np.full(capacity, -1, dtype=np.int64)
    tree_right = np.full(capacity, -1, dtype=np.int64)
    n_nodes = 0

    # The recursion's edge lists live in `pool`; a pending call is (start, size, parent node, side: 0 left, 1 right).
    pool = np.empty(max(16, 4 * n_vertices), dtype=np.int64)
    pool[:n_vertices] = np.arange(n_vertices)
    pool_top = n_vertices
    tasks = np.empty((max(16, n_vertices + 1), 4), dtype=np.int64)
    tasks[0, 0], tasks[0, 1], tasks[0, 2], tasks[0, 3] = 0, n_vertices, -1, 0
    n_tasks = 1

    while n_tasks > 0:
        n_tasks -= 1
        start, size, parent, side = tasks[n_tasks, 0], tasks[n_tasks, 1], tasks[n_tasks, 2], tasks[n_tasks, 3]
        if size == 0:
            continue
        node = n_nodes
        n_nodes += 1
        if parent >= 0:
            if side == 0:
                tree_left[parent] = node
            else:
                tree_right[parent] = node

        min_left, min_right, optimal = _optimal_split(point, next_vertex, pool, start, size)
        # Partition the other edges into [left list | right list] on top of the pool; room for every split first.
        while pool_top + min_left + min_right > pool.shape[0]:
            pool = _grown_int(pool, 2 * pool.shape[0])
        while n_vertices + size > point.shape[0]:
            capacity = 2 * point.shape[0]
            point, unit_dir = _grown_float2(point, capacity), _grown_float2(unit_dir, capacity)
            is_convex = _grown_bool(is_convex, capacity)
            next_vertex, prev_vertex = _grown_int(next_vertex, capacity), _grown_int(prev_vertex, capacity)
            tree_vertex, tree_left = _grown_int(tree_vertex, capacity), _grown_int(tree_left, capacity)
            tree_right = _grown_int(tree_right, capacity)
        left_start, right_start = pool_top, pool_top + min_left
        n_vertices = _partition(point, unit_dir, is_convex, next_vertex, prev_vertex, pool, start, size, optimal,
                                left_start, right_start, n_vertices)
        pool_top += min_left + min_right
        tree_vertex[node] = pool[start + optimal]

        # Recurse: left subtree first (popped first), then right, as RVO2 does.
        if n_tasks + 2 > tasks.shape[0]:
            grown_tasks = np.empty((2 * tasks.shape[0], 4), dtype=np.int64)
            grown_tasks[:n_tasks] = tasks[:n_tasks]
            tasks = grown_tasks
        tasks[n_tasks, 0], tasks[n_tasks, 1], tasks[n_tasks, 2], tasks[n_tasks, 3] = right_start, min_right, node, 1
        tasks[n_tasks + 1, 0], tasks[n_tasks + 1, 1] = left_start, min_left
        tasks[n_tasks + 1, 2], tasks[n_tasks + 1, 3] = node, 0
        n_tasks += 2

    return (
        point[:n_vertices].copy(), unit_dir[:n_vertices].copy(), is_convex[:n_vertices].copy(),
        next_vertex[:n_vertices].copy(), prev_vertex[:n_vertices].copy(), tree_vertex[:n_vertices].copy(),
        tree_left[:n_vertices].copy(), tree_right[:n_vertices].copy(),
    )


@dataclass(frozen=True, eq=False)
class ObstacleMap:
    """One map's obstacles as RVO2 holds them after addObstacle (each polygon) and processObstacles.

    V vertices, V >= the input count (processObstacles adds the split vertices, ids after the input ones):
    point (V, 2) float64: the vertex; edge k runs from point[k] to point[next_vertex[k]].
    unit_dir (V, 2) float64: unit direction of edge k (a split vertex inherits its edge's).
    is_convex (V,) bool: RVO2's isConvex_, leftOf(previous, vertex, next) >= 0; wall ends and split vertices are convex.
    next_vertex, prev_vertex (V,) int64: the ring links.
    tree_vertex, tree_left, tree_right (V,) int64: the obstacle k-d tree, one node per edge (tree_vertex[node] is its
    start vertex), child nodes or -1, node 0 the root.
    """

    point: np.ndarray
    unit_dir: np.ndarray
    is_convex: np.ndarray
    next_vertex: np.ndarray
    prev_vertex: np.ndarray
    tree_vertex: np.ndarray
    tree_left: np.ndarray
    tree_right: np.ndarray

    @classmethod
    def from_polygons(cls, polygons: Sequence[np.ndarray]) -> ObstacleMap:
        """`process_obstacles(polygons)`."""
        return process_obstacles(polygons)

    @classmethod
    def empty(cls) -> ObstacleMap:
        """The map without obstacles."""
        return process_obstacles([])

    @property
    def n_vertices(self) -> int:
        return int(self.point.shape[0])

    def visible(self, q1: Sequence[float], q2: Sequence[float], radius: float = 0.0) -> bool:
        """RVO2 queryVisibility: whether a disc of `radius` sweeps from q1 to q2 without an edge blocking it."""
        stack = np.empty(max(1, self.n_vertices), dtype=np.int64)
        return bool(
            query_visibility(
                float(q1[0]), float(q1[1]), float(q2[0]), float(q2[1]), float(radius),
                self.point, self.next_vertex, self.tree_vertex, self.tree_left, self.tree_right, self.n_vertices, stack,
            )
        )  # fmt: skip


def process_obstacles(polygons: Sequence[np.ndarray]) -> ObstacleMap:
    """RVO2's addObstacle for each polygon in order, then processObstacles: the `ObstacleMap` of `polygons`.

    Each polygon is a (K, 2) array-like of finite vertices, K >= 2, without a closing repeat, no two consecutive
    vertices equal (RVO2 divides by every edge's length); counter-clockwise is solid (RVO2), clockwise encloses free
    space, K == 2 is a wall segment blocking both sides. At most `MAX_TOTAL_VERTICES` input vertices in all (RVO2's
    tree build is quadratic per level). Bad input raises `MapError` (a ValueError) naming ``polygons[i]``.
    """
    if isinstance(polygons, (str, bytes)) or not isinstance(polygons, Sequence):
        raise MapError(f"polygons: expected a list of (K, 2) vertex arrays, got {type(polygons).__name__}")
    points: list[np.ndarray] = []
    directions: list[np.ndarray] = []
    convex: list[np.ndarray] = []
    next_links: list[np.ndarray] = []
    prev_links: list[np.ndarray] = []
    total = 0
    for index, polygon in enumerate(polygons):
        label = f"polygons[{index}]"
        try:
            vertices = np.array(polygon, dtype=np.float64)
        except (TypeError, ValueError):
            raise MapError(f"{label}: expected a (K, 2) array of numbers, got {polygon!r}") from None
        if vertices.ndim != 2 or vertices.shape[1] != 2:
            raise MapError(f"{label}: expected shape (K, 2), got {vertices.shape}")
        if not np.isfinite(vertices).all():
            raise MapError(f"{label}: non-finite coordinate (every x and y must be a finite number)")
        k = len(vertices)
        if k < 2:
            raise MapError(f"{label}: a polygon needs K >= 2 vertices (2 make a wall segment), got {k}")
        total += k
        if total > MAX_TOTAL_VERTICES:
            raise MapError(f"{label}: more than MAX_TOTAL_VERTICES = {MAX_TOTAL_VERTICES} vertices in all")
        following = np.roll(vertices, -1, axis=0)
        edges = following - vertices
        length = np.sqrt((edges**2).sum(axis=1))
        zero = np.flatnonzero(length == 0.0)
        if zero.size:
            raise MapError(
                f"{label}: zero-length edge from vertex {int(zero[0])} (consecutive vertices, or the last and the "
                "first, coincide; do not repeat the first vertex to close a polygon)"
            )
        preceding = np.roll(vertices, 1, axis=0)
        if k == 2:
            is_convex = np.ones(2, dtype=np.bool_)  # a wall's two ends are convex from both sides
        else:
            # leftOf(previous, vertex, next) >= 0: the ring turns left (or runs straight) at the vertex.
            is_convex = (preceding[:, 0] - following[:, 0]) * (vertices[:, 1] - preceding[:, 1]) - (
                preceding[:, 1] - following[:, 1]
            ) * (vertices[:, 0] - preceding[:, 0]) >= 0.0
        first = sum(len(p) for p in points)
        points.append(vertices)
        directions.append(edges / length[:, None])
        convex.append(is_convex)
        next_links.append(first + (np.arange(k) + 1) % k)
        prev_links.append(first + (np.arange(k) - 1) % k)

    def stacked(parts, shape, dtype):
        return np.concatenate(parts).astype(dtype) if parts else np.empty(shape, dtype=dtype)

    built = _build_obstacle_tree(
        stacked(points, (0, 2), np.float64),
        stacked(directions, (0, 2), np.float64),
        stacked(convex, (0,), np.bool_),
        stacked(next_links, (0,), np.int64),
        stacked(prev_links, (0,), np.int64),
    )
    return ObstacleMap(*built)


@dataclass(frozen=True, eq=False)
class ObstacleBatch:
    """The obstacle maps of E environments, padded to the largest vertex count Vmax, as the ORCA kernel reads them.

    point, unit_dir (E, Vmax, 2) float64; is_convex (E, Vmax) bool; next_vertex, prev_vertex, tree_vertex, tree_left,
    tree_right (E, Vmax) int64: env e's `ObstacleMap` arrays in [e, :count[e]] (padding: 0 / False / -1, never read);
    count (E,) int64. An env with count 0 costs the kernel one comparison per agent.
    """

    point: np.ndarray
    unit_dir: np.ndarray
    is_convex: np.ndarray
    next_vertex: np.ndarray
    prev_vertex: np.ndarray
    tree_vertex: np.ndarray
    tree_left: np.ndarray
    tree_right: np.ndarray
    count: np.ndarray

    @classmethod
    def from_maps(cls, maps: Sequence[ObstacleMap]) -> ObstacleBatch:
        """One env per map, in order (the same `ObstacleMap` may appear many times)."""
        if isinstance(maps, ObstacleMap) or not isinstance(maps, Sequence):
            raise TypeError(f"maps: expected a sequence of ObstacleMap, one per env, got {type(maps).__name__}")
        for e, obstacle_map in enumerate(maps):
            if not isinstance(obstacle_map, ObstacleMap):
                raise TypeError(f"maps[{e}]: expected an ObstacleMap, got {type(obstacle_map).__name__}")
        n_envs = len(maps)
        count = np.array([m.n_vertices for m in maps], dtype=np.int64)
        max_vertices = int(count.max()) if n_envs else 0
        batch = cls(
            point=np.zeros((n_envs, max_vertices, 2)),
            unit_dir=np.zeros((n_envs, max_vertices, 2)),
            is_convex=np.zeros((n_envs, max_vertices), dtype=np.bool_),
            next_vertex=np.full((n_envs, max_vertices), -1, dtype=np.int64),
            prev_vertex=np.full((n_envs, max_vertices), -1, dtype=np.int64),
            tree_vertex=np.full((n_envs, max_vertices), -1, dtype=np.int64),
            tree_left=np.full((n_envs, max_vertices), -1, dtype=np.int64),
            tree_right=np.full((n_envs, max_vertices), -1, dtype=np.int64),
            count=count,
        )
        for e, obstacle_map in enumerate(maps):
            v = obstacle_map.n_vertices
            for field in _MAP_FIELDS:
                getattr(batch, field)[e, :v] = getattr(obstacle_map, field)
        return batch

    @classmethod
    def empty(cls, n_envs: int) -> ObstacleBatch:
        """E envs without obstacles (Vmax = 0)."""
        return cls.from_maps([ObstacleMap.empty()] * n_envs)

    @property
    def n_envs(self) -> int:
        return int(self.count.shape[0])

    def kernel_arrays(self) -> tuple[np.ndarray, ...]:
        """The arrays in the order `orca_velocities_obstacles_kernel` takes them."""
        return (self.point, self.unit_dir, self.is_convex, self.next_vertex, self.prev_vertex, self.tree_vertex,
                self.tree_left, self.tree_right, self.count)  # fmt: skip


_MAP_FIELDS = ("point", "unit_dir", "is_convex", "next_vertex", "prev_vertex", "tree_vertex", "tree_left", "tree_right")


# --------------------------------------------------------------------------------------------------------------------
# Visibility on one map (an `ObstacleMap`'s arrays, or one env's rows of an `ObstacleBatch` and its count).
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def query_visibility(
    q1x, q1y, q2x, q2y, radius, point, next_vertex, tree_vertex, tree_left, tree_right, n_vertices, stack
):
    """RVO2 KdTree::queryVisibility: True when no edge blocks a disc of `radius` moving from q1 to q2.

    RVO2's rule per tree node (edge a -> b): with both q on one side, the edge does not block, and the subtree on the
    other side is skipped when both q are at least `radius` from the edge's line; q1 left and q2 right ("seen through
    from behind") does not block; otherwise it blocks unless a and b lie strictly on one side of the line q1 q2, both
    more than `radius` from it. RVO2's recursion is the AND of that rule over the nodes it reaches, so a depth-first
    scan of the same nodes gives its value. `stack`: int64 scratch of at least n_vertices entries.
    """
    if n_vertices == 0:
        return True
    radius_sq = radius * radius
    stack[0] = 0
    depth = 1
    while depth > 0:
        depth -= 1
        node = stack[depth]
        a = tree_vertex[node]
        b = next_vertex[a]
        ax, ay, bx, by = point[a, 0], point[a, 1], point[b, 0], point[b, 1]
        q1_left = _left_of(ax, ay, bx, by, q1x, q1y)
        q2_left = _left_of(ax, ay, bx, by, q2x, q2y)
        inv_length_sq = 1.0 / ((bx - ax) * (bx - ax) + (by - ay) * (by - ay))
        both_far = q1_left * q1_left * inv_length_sq >= radius_sq and q2_left * q2_left * inv_length_sq >= radius_sq
        left, right = tree_left[node], tree_right[node]
        if q1_left >= 0.0 and q2_left >= 0.0:
            if both_far:
                right = -1
        elif q1_left <= 0.0 and q2_left <= 0.0:
            if both_far:
                left = -1
        elif not (q1_left >= 0.0 and q2_left <= 0.0):
            a_left = _left_of(q1x, q1y, q2x, q2y, ax, ay)
            b_left = _left_of(q1x, q1y, q2x, q2y, bx, by)
            inv_q_sq = 1.0 / ((q2x - q1x) * (q2x - q1x) + (q2y - q1y) * (q2y - q1y))
            if not (
                a_left * b_left >= 0.0
                and a_left * a_left * inv_q_sq > radius_sq
                and b_left * b_left * inv_q_sq > radius_sq
            ):
                return False
        if left >= 0:
            stack[depth] = left
            depth += 1
        if right >= 0:
            stack[depth] = right
            depth += 1
    return True
