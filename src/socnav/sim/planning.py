"""The global planner of worlds with walls: the shortest collision-free path of a disc among a map's walls, and the
subgoal along it that an agent steers towards instead of its goal (pure pursuit), re-planned only when needed.

`GlobalPlanner` holds one map's visibility graph for one clearance (an agent's radius plus a margin): its nodes are
the convex corners of the walls inflated by that clearance (shapely buffers, mitred), its edges the pairs of nodes
tangent to the walls at both ends that see each other keeping the clearance from every wall (a shapely `STRtree`
query), and the shortest paths between every two nodes (`scipy.sparse.csgraph` Dijkstra), built once per map and
clearance and shared (`planner_for`). A query connects its start and goal to the nodes they see and reads the path
off that table; a batch of queries is answered in one compiled call (maps too large for the table run Dijkstra per
query).

`PathFollower` keeps one path per agent and gives each step's subgoal for a batch of agents in one compiled call:
the goal itself whenever the straight line to it keeps the agent's own radius from every wall (so an agent with a
clear view of its goal moves exactly as it would without a planner), else the point `lookahead` metres along its
path. It re-plans when an agent's goal changes, when the agent strays more than `replan_distance` from its path,
or when it loses sight of the path's next vertex. A goal no path reaches (enclosed, or behind a gap narrower than
the clearance allows) leaves the agent heading straight at it, as without a planner: never an exception mid-episode.

"Keeps a clearance" is one rule everywhere (`segments_clear`): no wall is within the clearance of the segment, or
within the smaller distance one of its ends already has (an agent pushed close to a wall may still leave it). The
graph is built with shapely; the checks made every step for every agent and those connecting a query to the graph
apply the same rule in compiled loops over the wall edges (`socnav.sim.geometry`'s distances), at a few tens of
nanoseconds a wall, where a shapely call costs microseconds before it starts.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from shapely import STRtree
from shapely.geometry import MultiLineString, Polygon
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

from socnav.sim.geometry import (
    points_to_segments,
    polygon_segments,
)
from socnav.sim.planning_kernels import (
    CLEARANCE_SLACK,
    NO_PLAN,
    links_kernel,
    nearest_wall_points,
    plan_kernel,
    redirect_to_subgoals,
    segments_clear,
    solid_points,
    steer,
    store_plans,
)

__all__ = [
    "CLEARANCE_SLACK",
    "GlobalPlanner",
    "Nesting",
    "PathFollower",
    "planner_for",
    "redirect_to_subgoals",
    "segments_clear",
    "unreachable_route",
]


#: metres: nodes are the corners of the walls inflated by the clearance plus this, so that every node, and every
#: edge along an inflated wall, keeps the clearance despite rounding
_NODE_OFFSET = 1e-6


#: mitred corners sharper than this ratio of mitre length to clearance are clipped (at that distance: still at least
#: the clearance from the wall, unlike a bevel)
_MITRE_LIMIT = 2.0


#: maps of at most this many nodes keep a table of the shortest paths between every two (8 N^2 + 4 N^2 bytes: 27 MB
#: at 1,500); larger ones search their graph per query
_TABLE_NODES = 1500


#: planners kept by `planner_for` (one per map and clearance; a world has at most two: the robot's and the humans')
_CACHE_SIZE = 16


#: a point in the plane: (x, y)
Point = Sequence[float] | np.ndarray


@dataclass(frozen=True)
class Nesting:
    """The closed polygons of a map as the nesting rule of solid space reads them
    (`socnav.sim.maps.clearance_violation`; `socnav.sim.walls.Walls.misplaced` vectorises it the same way): a point
    belongs to the smallest closed polygon containing it, solid if that one is counter-clockwise; in none, solid
    when some clockwise polygon (a boundary agents stay inside) lies in no other polygon."""

    vertices: np.ndarray  # (V, 2): every closed polygon's vertices, one after the other
    offsets: np.ndarray  # (P + 1,) int64: polygon p is vertices[offsets[p]:offsets[p + 1]]
    area_sizes: np.ndarray  # (P,)
    solid_inside: np.ndarray  # (P,) bool: counter-clockwise
    solid_outside: bool

    @classmethod
    def of(cls, polygons: Sequence[np.ndarray]) -> Nesting:
        """The nesting of RVO2-ordered `polygons` (two-vertex walls have no inside and are left out)."""
        closed = [np.asarray(vertices, dtype=np.float64) for vertices in polygons if len(vertices) >= 3]
        areas = [Polygon(vertices) for vertices in closed]
        solid_inside = np.array([_signed_area(vertices) > 0.0 for vertices in closed], dtype=bool)
        solid_outside = any(not solid and not any(other.contains(area) for other in areas if other is not area)
                            for area, solid in zip(areas, solid_inside, strict=True))
        return cls(vertices=np.concatenate(closed) if closed else np.zeros((0, 2)),
                   offsets=np.cumsum([0] + [len(vertices) for vertices in closed]).astype(np.int64),
                   area_sizes=np.array([area.area for area in areas], dtype=np.float64),
                   solid_inside=solid_inside, solid_outside=bool(solid_outside))


def _signed_area(vertices: np.ndarray) -> float:
    x, y = vertices[:, 0], vertices[:, 1]
    return float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _wall_lines(polygons: Sequence[np.ndarray]) -> list[shapely.LineString]:
    """Every edge of the polygons as a line (a closed polygon's closing edge included; a two-vertex wall itself)."""
    seg_start, seg_end, n_segments = polygon_segments([polygons])
    count = int(n_segments[0])
    return list(shapely.linestrings(np.stack([seg_start[0, :count], seg_end[0, :count]], axis=1)))


def _convex_corners(inflated: BaseGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The convex corners of an obstacle geometry's outline, with the ring vertices before and after each:
    (corners (N, 2), previous (N, 2), following (N, 2)). Rings are oriented with the obstacle on their left (shapely
    `orient`: exteriors counter-clockwise, holes clockwise), so a convex corner is a strict left turn; only those can
    lie on a shortest path."""
    corners, previous, following = [], [], []
    pieces = getattr(inflated, "geoms", [inflated])
    for piece in pieces:
        if piece.is_empty or not isinstance(piece, Polygon):
            continue
        piece = orient(piece, sign=1.0)
        for ring in (piece.exterior, *piece.interiors):
            points = np.asarray(ring.coords, dtype=np.float64)[:-1]
            before, after = np.roll(points, 1, axis=0), np.roll(points, -1, axis=0)
            incoming, outgoing = points - before, after - points
            turn = incoming[:, 0] * outgoing[:, 1] - incoming[:, 1] * outgoing[:, 0]
            scale = np.linalg.norm(incoming, axis=1) * np.linalg.norm(outgoing, axis=1)
            left = turn > 1e-9 * scale  # collinear vertices (buffer leaves some) are no corners
            corners.append(points[left])
            previous.append(before[left])
            following.append(after[left])
    if not corners:
        empty = np.zeros((0, 2))
        return empty, empty, empty
    return np.concatenate(corners), np.concatenate(previous), np.concatenate(following)


def _tangent_at(corners: np.ndarray, previous: np.ndarray, following: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(N, K) bool: whether the line from corner n to point k leaves the corner's two ring neighbours on one side
    (is tangent to the obstacle there): a shortest path only turns at a corner along tangent lines."""
    direction = others[None, :, :] - corners[:, None, :]
    to_previous = (previous - corners)[:, None, :]
    to_following = (following - corners)[:, None, :]
    side_previous = direction[..., 0] * to_previous[..., 1] - direction[..., 1] * to_previous[..., 0]
    side_following = direction[..., 0] * to_following[..., 1] - direction[..., 1] * to_following[..., 0]
    return side_previous * side_following >= 0.0


class GlobalPlanner:
    """Shortest paths among one map's walls for a disc whose centre keeps `clearance` metres from every wall (an
    agent's radius plus a margin): a visibility graph over the walls inflated by `clearance`, built once here.

    `shortest_path(start, goal)` connects the two points to the graph and returns the path's vertices, or None when
    the goal cannot be reached (start or goal in a solid obstacle, or enclosed: no way wide enough leads there).
    A start or goal nearer a wall than `clearance` is connected by segments keeping its own distance (the rule of
    `segments_clear`); every other segment of a path keeps `clearance`.
    """

    def __init__(self, polygons: Sequence[np.ndarray], clearance: float):
        if not clearance > 0.0 or not math.isfinite(clearance):
            raise ValueError(f"clearance must be a finite number of metres > 0, got {clearance!r}")
        self.polygons = [np.asarray(vertices, dtype=np.float64) for vertices in polygons]
        self.clearance = float(clearance)
        seg_start, seg_end, n_segments = polygon_segments([self.polygons])
        count = int(n_segments[0])
        #: the walls' edges (S, 2) each, as the compiled clearance rule reads them
        self.seg_start = np.ascontiguousarray(seg_start[0, :count])
        self.seg_end = np.ascontiguousarray(seg_end[0, :count])
        lines = _wall_lines(self.polygons)
        self._lines = STRtree(lines)
        self.nesting = Nesting.of(self.polygons)
        # Every edge inflated (a solid obstacle's inside is bounded by its edges, so the edges are enough); mitred
        # and square-capped, the inflated walls contain the round ones, so their corners keep the clearance.
        inflated = shapely.buffer(MultiLineString([line.coords for line in lines]), self.clearance + _NODE_OFFSET,
                                  cap_style="square", join_style="mitre", mitre_limit=_MITRE_LIMIT) if lines else None
        corners, previous, following = (_convex_corners(inflated) if inflated is not None
                                        else (np.zeros((0, 2)),) * 3)
        keep = self.is_free(corners)  # corners inside a solid obstacle (holes of its inflated edges) are no nodes
        #: the graph's nodes (N, 2), with their ring neighbours (for the tangent test)
        self.nodes, self._previous, self._following = corners[keep], previous[keep], following[keep]
        #: the point of the walls nearest each node: the corner its path turns round
        self.anchors = nearest_wall_points(self.nodes, self.seg_start, self.seg_end)
        self._rows, self._cols, self._lengths = self._edges()
        self._table = self._shortest_between_nodes()

    def _shortest_between_nodes(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Dijkstra from every node (`scipy.sparse.csgraph`): the (N, N) distances and predecessors every query
        reads, or None for a map of more than `_TABLE_NODES` nodes (its queries then search the graph one by one)."""
        from scipy.sparse import coo_matrix  # scipy only where there are walls to plan around
        from scipy.sparse.csgraph import dijkstra

        n = self.n_nodes
        if n == 0 or n > _TABLE_NODES:
            return None
        graph = coo_matrix((np.maximum(self._lengths, 1e-12), (self._rows, self._cols)), shape=(n, n)).tocsr()
        distance, predecessors = dijkstra(graph, directed=False, return_predecessors=True)
        return distance, predecessors

    # ------------------------------------------------------------------------------------------------ the graph
    @property
    def n_nodes(self) -> int:
        """The graph's nodes: the convex corners of the inflated walls in free space."""
        return len(self.nodes)

    @property
    def n_edges(self) -> int:
        """The graph's edges (each pair of nodes once)."""
        return len(self._rows)

    def _blocked(self, starts: np.ndarray, ends: np.ndarray, keep: float) -> np.ndarray:
        """(K,) bool: whether some wall lies within `keep` of each segment (shapely `STRtree` queries: those that
        cross a wall first, the cheaper test that settles most long segments, then the distance of the others)."""
        if len(starts) == 0:
            return np.zeros(0, dtype=bool)
        segments = shapely.linestrings(np.stack([starts, ends], axis=1))
        blocked = np.zeros(len(starts), dtype=bool)
        blocked[self._lines.query(segments, predicate="intersects")[0]] = True
        rest = np.flatnonzero(~blocked)
        blocked[rest[self._lines.query(segments[rest], predicate="dwithin", distance=keep)[0]]] = True
        return blocked

    def _edges(self, block: int = 512) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The graph's edges (rows, cols, lengths), i < j: node pairs tangent at both ends that see each other
        keeping the clearance. Built in blocks of rows, so that a map of thousands of corners stays in memory."""
        n = self.n_nodes
        rows, cols = [], []
        keep = max(self.clearance - CLEARANCE_SLACK, 0.0)
        for first in range(0, n, block):
            last = min(n, first + block)
            tangent = _tangent_at(self.nodes[first:last], self._previous[first:last], self._following[first:last],
                                  self.nodes)
            tangent &= _tangent_at(self.nodes, self._previous, self._following, self.nodes[first:last]).T
            tangent &= np.arange(n)[None, :] > np.arange(first, last)[:, None]  # each pair once
            i, j = np.nonzero(tangent)
            i += first
            visible = ~self._blocked(self.nodes[i], self.nodes[j], keep)
            rows.append(i[visible])
            cols.append(j[visible])
        row = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
        col = np.concatenate(cols) if cols else np.zeros(0, dtype=np.int64)
        return row, col, np.linalg.norm(self.nodes[row] - self.nodes[col], axis=1)

    # ------------------------------------------------------------------------------------------------ queries
    def is_free(self, points: np.ndarray) -> np.ndarray:
        """(K,) bool: whether each point (K, 2) lies outside solid space (`Nesting`), compiled."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        nesting = self.nesting
        return ~solid_points(points, nesting.vertices, nesting.offsets, nesting.area_sizes, nesting.solid_inside,
                              nesting.solid_outside)

    def wall_distance(self, points: np.ndarray) -> np.ndarray:
        """(K,) distance from each point (K, 2) to the nearest wall edge (inf without walls), compiled."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        return points_to_segments(points, self.seg_start, self.seg_end, len(self.seg_start))

    def clear(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """(K,) bool: whether each segment keeps this planner's clearance (`segments_clear`), compiled."""
        return segments_clear(starts, ends, self.clearance, self.seg_start, self.seg_end)

    def _links(self, points: np.ndarray) -> np.ndarray:
        """(K, N): the length of the segment from each point (K, 2) to each node it connects to, inf where it does
        not (`links_kernel`)."""
        return links_kernel(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2), self.nodes,
                             self._previous, self._following, self.clearance, self.seg_start, self.seg_end)

    def shortest_path(self, start: Point, goal: Point) -> np.ndarray | None:
        """The shortest path from `start` to `goal` (vertices (P, 2), P >= 2, from start to goal), or None when no
        path reaches the goal: start or goal inside a solid obstacle, or no way there wide enough."""
        return self.shortest_paths(np.asarray(start, dtype=np.float64).reshape(1, 2),
                                   np.asarray(goal, dtype=np.float64).reshape(1, 2))[0]

    def shortest_paths(self, starts: np.ndarray, goals: np.ndarray) -> list[np.ndarray | None]:
        """`shortest_path` of each (starts[q], goals[q]) (Q, 2 each), answered together (`plan`)."""
        paths, counts, _ = self.plan(starts, goals)
        return [paths[q, :count] if count else None for q, count in enumerate(counts.tolist())]

    def plan(self, starts: np.ndarray, goals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The shortest paths of a batch of queries (starts, goals: (Q, 2) each) as padded arrays: vertices
        (Q, P, 2), counts (Q,), 0 where no path reaches the goal, and the node each vertex is (Q, P), -1 for the
        start and goal. The connections of all of them are found in one compiled call and the paths read off the
        graph's table of shortest paths between nodes, in the same call."""
        starts = np.ascontiguousarray(starts, dtype=np.float64).reshape(-1, 2)
        goals = np.ascontiguousarray(goals, dtype=np.float64).reshape(-1, 2)
        nesting = self.nesting
        if self._table is not None:
            distance, predecessors = self._table
            return plan_kernel(starts, goals, self.nodes, self._previous, self._following, distance, predecessors,
                                self.clearance, self.seg_start, self.seg_end, nesting.vertices, nesting.offsets,
                                nesting.area_sizes, nesting.solid_inside, nesting.solid_outside)
        free = self.is_free(np.concatenate([starts, goals])).reshape(2, -1).all(axis=0)
        straight = free & self.clear(starts, goals)  # a straight line is the shortest of all
        around = np.flatnonzero(free & ~straight) if self.n_nodes else np.zeros(0, dtype=np.int64)
        start_links, goal_links = self._links(starts[around]), self._links(goals[around])
        found: dict[int, list[int]] = {}
        for row, query in enumerate(around.tolist()):
            order = self._search(start_links[row], goal_links[row])
            if order is not None:
                found[query] = order
        counts = np.where(straight, 2, 0)
        for query, order in found.items():
            counts[query] = len(order) + 2
        width = max(2, int(counts.max(initial=0)))
        paths, node_of = np.zeros((len(starts), width, 2)), np.full((len(starts), width), -1)
        for query in np.flatnonzero(counts).tolist():
            order = found.get(query, [])
            paths[query, 0], paths[query, len(order) + 1] = starts[query], goals[query]
            paths[query, 1: len(order) + 1] = self.nodes[order]
            node_of[query, 1: len(order) + 1] = order
        return paths, counts, node_of

    def _search(self, start_links: np.ndarray, goal_links: np.ndarray) -> list[int] | None:
        """One query by Dijkstra on the graph with the start and goal connected (maps too large for the table):
        the nodes of the shortest path, in order, or None."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        n = self.n_nodes
        source, target = n, n + 1
        start_nodes, goal_nodes = np.flatnonzero(np.isfinite(start_links)), np.flatnonzero(np.isfinite(goal_links))
        rows = np.concatenate([self._rows, np.full(len(start_nodes), source), goal_nodes])
        cols = np.concatenate([self._cols, start_nodes, np.full(len(goal_nodes), target)])
        # csgraph reads an explicit zero as no edge: a start or goal on a node is kept a hair apart
        lengths = np.maximum(np.concatenate([self._lengths, start_links[start_nodes], goal_links[goal_nodes]]), 1e-12)
        graph = coo_matrix((lengths, (rows, cols)), shape=(n + 2, n + 2)).tocsr()
        distance, predecessors = dijkstra(graph, directed=False, indices=source, return_predecessors=True)
        if not np.isfinite(distance[target]):
            return None
        order = [int(predecessors[target])]
        while order[-1] != source:
            order.append(int(predecessors[order[-1]]))
        return order[-2::-1]


_PLANNERS: OrderedDict[tuple[str, float], GlobalPlanner] = OrderedDict()


def _map_key(polygons: Sequence[np.ndarray]) -> str:
    digest = hashlib.sha256()
    for vertices in polygons:
        array = np.ascontiguousarray(vertices, dtype=np.float64)
        digest.update(np.int64(len(array)).tobytes())
        digest.update(array.tobytes())
    return digest.hexdigest()


def planner_for(polygons: Sequence[np.ndarray], clearance: float) -> GlobalPlanner:
    """The `GlobalPlanner` of these walls and clearance, built on first use and kept (the last 16): the config's
    check, the world's humans and the robot's controller share one graph per map."""
    key = (_map_key(polygons), float(clearance))
    planner = _PLANNERS.get(key)
    if planner is None:
        planner = GlobalPlanner(polygons, clearance)
        _PLANNERS[key] = planner
        while len(_PLANNERS) > _CACHE_SIZE:
            _PLANNERS.popitem(last=False)
    else:
        _PLANNERS.move_to_end(key)
    return planner


def unreachable_route(planner: GlobalPlanner, routes: Sequence[tuple[np.ndarray, np.ndarray]],
                      radius: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The first route (start, goal) whose goal `planner` cannot reach from its start, or None. Routes whose start
    or goal does not fit among the walls (inside an obstacle, or nearer a wall than `radius`) are left out: the
    world redraws those episodes (`socnav.sim.world.MAX_PLACEMENT_DRAWS`)."""
    for start, goal in routes:
        ends = np.stack([np.asarray(start, dtype=np.float64), np.asarray(goal, dtype=np.float64)])
        if not planner.is_free(ends).all() or (planner.wall_distance(ends) < radius).any():
            continue
        if planner.shortest_path(ends[0], ends[1]) is None:
            return ends[0], ends[1]
    return None


class PathFollower:
    """The paths of K agents (e.g. the E x N slots of a world, or E robots) on one planner's map, and each step's
    subgoal of those asked for (`update`). Whatever the order or subset of agents a caller passes, a subgoal is
    always valid for the agent's current position and goal: a stored path is reused only while the agent is near it,
    sees its next vertex and keeps its goal; otherwise it is planned again.

    :param planner: the map and clearance.
    :param n_agents: K.
    :param lookahead: metres along the path from the agent's nearest point to its subgoal.
    :param replan_distance: metres from its path beyond which an agent's path is planned again.
    :param goal_tolerance: metres a goal may move (an estimated goal, e.g. from a noisy observation) before the path
        is planned again; 0: any change.
    :param reach: intermediate subgoals nearer than this are pushed out along their direction (0: never).
    :param direct_clearance: an agent heads straight at its goal while the straight line keeps this from every wall
        (its radius: it fits; None: the planner's clearance), and follows its path only where it does not.
    """

    def __init__(self, planner: GlobalPlanner, n_agents: int, lookahead: float, replan_distance: float,
                 goal_tolerance: float = 0.0, reach: float = 0.0, direct_clearance: float | None = None):
        self.planner = planner
        self.direct_clearance = planner.clearance if direct_clearance is None else float(direct_clearance)
        self.n_agents = int(n_agents)
        self.lookahead = float(lookahead)
        self.replan_distance = float(replan_distance)
        self.goal_tolerance = float(goal_tolerance)
        self.reach = float(reach)
        k = self.n_agents
        self.mode = np.zeros(k, dtype=np.int8)
        # the last straight line to the goal found clear: from, to, and its room to spare
        self.view_at, self.view_goal, self.view_spare = np.zeros((k, 2)), np.zeros((k, 2)), np.zeros(k)
        # the stored path: vertices, count, current segment, the goal it leads to
        self.paths = np.zeros((k, 2, 2))
        self.path_nodes = np.full((k, 2), -1)  # the graph node each path vertex is (-1: the start, the goal)
        self.counts = np.zeros(k, dtype=np.int64)
        self.segments = np.zeros(k, dtype=np.int64)
        self.path_goal = np.full((k, 2), np.nan)
        self.fallback_at = np.zeros((k, 2))  # where a plan failed
        self.queries = 0  # shortest-path queries made (re-plans), for benchmarks and tests
        self._subgoals = np.zeros((k, 2))
        self._direct = np.ones(k, dtype=bool)
        self._replan = np.zeros(k, dtype=bool)
        self._everyone: np.ndarray | None = None

    def forget(self, agents: np.ndarray | slice) -> None:
        """Drop the paths of `agents` (e.g. at a new episode): their next `update` plans afresh."""
        self.mode[agents] = NO_PLAN
        self.counts[agents] = 0
        self.path_goal[agents] = np.nan

    def update(self, positions: np.ndarray, goals: np.ndarray, asked: np.ndarray | None = None,
               out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """This step's subgoals of the agents `asked` ((K,) bool; None: all) at `positions` heading for `goals`
        (K, 2 each): returns (subgoals (K, 2), direct (K,) bool), where direct means the subgoal is the goal itself
        (every agent not asked gets its goal). The subgoals are written into `out` (K, 2) when given, else into an
        internal buffer; both returned arrays are valid until the next call."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        goals = np.ascontiguousarray(goals, dtype=np.float64)
        if asked is None:
            if self._everyone is None:
                self._everyone = np.ones(self.n_agents, dtype=bool)
            asked = self._everyone
        subgoals = self._subgoals if out is None else out
        if self._steer(np.ascontiguousarray(asked, dtype=bool), True, positions, goals, subgoals):
            pending = self._replan.copy()
            agents = np.flatnonzero(pending)
            self._plan(agents, positions[agents], goals[agents])
            self._steer(pending, False, positions, goals, subgoals)
            self._replan[:] = False  # a path just planned is followed even if its next vertex just went out of sight
        return subgoals, self._direct

    def _steer(self, asked: np.ndarray, fill: bool, positions: np.ndarray, goals: np.ndarray,
               subgoals: np.ndarray) -> int:
        """`steer` of the agents `asked`; returns how many it marked for a re-plan."""
        planner = self.planner
        return steer(asked, fill, positions, goals, self.mode, self.view_at, self.view_goal, self.view_spare,
                     self.paths, self.path_nodes, self.counts, self.segments, self.path_goal, self.fallback_at,
                     planner.anchors, planner.seg_start, planner.seg_end, planner.clearance, self.direct_clearance,
                     self.lookahead, self.replan_distance, self.goal_tolerance, self.reach, subgoals, self._direct,
                     self._replan)

    def _plan(self, agents: np.ndarray, positions: np.ndarray, goals: np.ndarray) -> None:
        """Plan the paths of `agents` in one batch; a goal no path reaches leaves its agent heading straight at it
        (`FALLBACK`) until it has moved `replan_distance` or its goal changes."""
        self.queries += len(agents)
        paths, counts, nodes = self.planner.plan(positions, goals)
        if paths.shape[1] > self.paths.shape[1]:
            width = self.paths.shape[1]
            grown = np.zeros((self.n_agents, paths.shape[1], 2))
            grown_nodes = np.full((self.n_agents, paths.shape[1]), -1)
            grown[:, :width], grown_nodes[:, :width] = self.paths, self.path_nodes
            self.paths, self.path_nodes = grown, grown_nodes
        store_plans(agents, positions, goals, paths, counts, nodes, self.paths, self.path_nodes, self.counts,
                     self.segments, self.path_goal, self.fallback_at, self.mode)

