"""The compiled kernels of the global planner and the path follower (`socnav.sim.planning`): the clearance rule
(`segments_clear`), a batch of queries through the visibility graph, each step's subgoal of a batch of agents, and
the redirection of preferred velocities to the subgoals. They call one another, so they are in one file: numba
invalidates a cached kernel only when its own file changes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from socnav.sim.geometry import (
    _point_segment_distance,
    _segment_segment_distance,
    points_in_polygons,
)

#: metres: a segment keeps a clearance c when no wall is within c minus this (floating-point slack, so that a path
#: along an inflated wall's edge, exactly c away, counts as clear)
CLEARANCE_SLACK = 1e-7


#: metres: an agent checked to see its goal with this much room to spare beyond its clearance (at most) sees it still
#: until it has strayed that far from the line it was checked on, so it skips the next checks
_SPARE_HORIZON = 1.0


# Follower modes of an agent
NO_PLAN, DIRECT, ON_PATH, FALLBACK = 0, 1, 2, 3


@numba.njit(cache=True)
def _wall_distance_within(px, py, reach, seg_start, seg_end):
    """The distance from p to the nearest wall segment, or `reach` if none is nearer (walls whose bounding box lies
    farther than `reach` are skipped without computing their distance)."""
    best = reach
    for s in range(seg_start.shape[0]):
        ax, ay, bx, by = seg_start[s, 0], seg_start[s, 1], seg_end[s, 0], seg_end[s, 1]
        if min(ax, bx) - px > best or px - max(ax, bx) > best or min(ay, by) - py > best or py - max(ay, by) > best:
            continue
        best = min(best, _point_segment_distance(px, py, ax, ay, bx, by))
    return best


@numba.njit(cache=True)
def _segment_spare(ax, ay, bx, by, clearance, horizon, seg_start, seg_end):
    """Whether the segment [a, b] keeps min(clearance, its ends' own distances to the walls) from every wall (minus
    `CLEARANCE_SLACK`; a segment that touches a wall never does), and its room to spare: how far another segment
    may lie from this one (each of its points that close to a point of this one) and surely keep `clearance` --
    this segment's distance to the walls less the clearance, at most `horizon`; 0 when it keeps only its ends'
    smaller distance. Returns (clear, spare).

    One pass over the walls (those farther than clearance + horizon are skipped by their bounding box); the ends'
    own distances are computed only for a segment nearer a wall than the clearance."""
    full = clearance - CLEARANCE_SLACK
    reach = clearance + horizon
    low_x, high_x = min(ax, bx) - reach, max(ax, bx) + reach
    low_y, high_y = min(ay, by) - reach, max(ay, by) + reach
    nearest = reach
    for s in range(seg_start.shape[0]):
        cx, cy, dx, dy = seg_start[s, 0], seg_start[s, 1], seg_end[s, 0], seg_end[s, 1]
        if max(cx, dx) < low_x or min(cx, dx) > high_x or max(cy, dy) < low_y or min(cy, dy) > high_y:
            continue
        distance = _segment_segment_distance(ax, ay, bx, by, cx, cy, dx, dy)
        if distance <= 0.0:
            return False, 0.0  # it crosses or touches a wall
        nearest = min(nearest, distance)
    if nearest > full:
        return True, min(nearest - full, horizon)
    keep = min(clearance, _wall_distance_within(ax, ay, clearance, seg_start, seg_end),
               _wall_distance_within(bx, by, clearance, seg_start, seg_end))
    return nearest > max(keep - CLEARANCE_SLACK, 0.0), 0.0


@numba.njit(cache=True)
def _segment_clear(ax, ay, bx, by, clearance, seg_start, seg_end):
    """Whether the segment [a, b] keeps min(clearance, its ends' own distances to the walls) from every wall
    (`_segment_spare` without the room to spare)."""
    return _segment_spare(ax, ay, bx, by, clearance, 0.0, seg_start, seg_end)[0]


@numba.njit(cache=True)
def _segments_clear_kernel(starts, ends, clearance, seg_start, seg_end):
    clear = np.empty(starts.shape[0], dtype=np.bool_)
    for k in range(starts.shape[0]):
        clear[k] = _segment_clear(starts[k, 0], starts[k, 1], ends[k, 0], ends[k, 1], clearance, seg_start, seg_end)
    return clear


def segments_clear(starts: np.ndarray, ends: np.ndarray, clearance: float, seg_start: np.ndarray,
                   seg_end: np.ndarray) -> np.ndarray:
    """(K,) bool: whether each segment [starts[k], ends[k]] (K, 2) keeps `clearance` from every wall segment
    [seg_start[s], seg_end[s]] (S, 2) -- or, where one of its ends is already nearer a wall, that end's distance."""
    return _segments_clear_kernel(np.ascontiguousarray(starts, dtype=np.float64).reshape(-1, 2),
                                  np.ascontiguousarray(ends, dtype=np.float64).reshape(-1, 2), float(clearance),
                                  seg_start, seg_end)


@numba.njit(cache=True)
def links_kernel(points, nodes, previous, following, clearance, seg_start, seg_end):
    """(K, N): the length of the segment from each point (K, 2) to each node (N, 2) it connects to, inf where it
    does not: the segment keeps the clearance (`_segment_clear`: a point among the inflated walls keeps its own
    distance) and, from a point that keeps the full clearance, is tangent at the node (its ring neighbours
    `previous`, `following` on one side: `_tangent_at`); a point among the inflated walls may leave them past any
    node."""
    links = np.full((points.shape[0], nodes.shape[0]), np.inf)
    full = clearance - 2.0 * CLEARANCE_SLACK
    for q in range(points.shape[0]):
        px, py = points[q, 0], points[q, 1]
        inside = _wall_distance_within(px, py, clearance, seg_start, seg_end) < full
        for n in range(nodes.shape[0]):
            nx, ny = nodes[n, 0], nodes[n, 1]
            if not inside:
                dx, dy = px - nx, py - ny
                side_previous = dx * (previous[n, 1] - ny) - dy * (previous[n, 0] - nx)
                side_following = dx * (following[n, 1] - ny) - dy * (following[n, 0] - nx)
                if side_previous * side_following < 0.0:
                    continue
            if _segment_clear(px, py, nx, ny, clearance, seg_start, seg_end):
                links[q, n] = math.hypot(nx - px, ny - py)
    return links


@numba.njit(cache=True)
def _through_table(start_links, goal_links, distance):
    """For each query q: the nodes (entry, leave) minimising start_links[q, entry] + distance[entry, leave] +
    goal_links[q, leave] (the first in row order on a tie), -1 where no sum is finite."""
    n_queries, n_nodes = start_links.shape
    entries = np.full(n_queries, -1, dtype=np.int64)
    leaves = np.full(n_queries, -1, dtype=np.int64)
    for q in range(n_queries):
        seen_by_goal = np.nonzero(goal_links[q] < np.inf)[0]
        best = np.inf
        for i in range(n_nodes):
            if start_links[q, i] == np.inf:
                continue
            for j in seen_by_goal:
                total = start_links[q, i] + distance[i, j] + goal_links[q, j]
                if total < best:
                    best, entries[q], leaves[q] = total, i, j
    return entries, leaves


@numba.njit(cache=True)
def _table_paths(starts, goals, straight, around, start_links, goal_links, distance, predecessors, nodes):
    """The paths of a batch of queries as `GlobalPlanner.plan` returns them: (start, goal) where `straight`; for the
    queries `around` (rows of the links), start, the nodes from the best entry to the best leave node
    (`_through_table`, walked back through the `predecessors` of the table's Dijkstra), goal."""
    n_queries = starts.shape[0]
    entries, leaves = _through_table(start_links, goal_links, distance)
    counts = np.zeros(n_queries, dtype=np.int64)
    for q in range(n_queries):
        if straight[q]:
            counts[q] = 2
    for row in range(around.shape[0]):
        if entries[row] < 0:
            continue
        node, count = leaves[row], 3
        while node != entries[row]:
            node = predecessors[entries[row], node]
            count += 1
        counts[around[row]] = count
    width = 2
    for q in range(n_queries):
        width = max(width, counts[q])
    paths = np.zeros((n_queries, width, 2))
    node_of = np.full((n_queries, width), -1, dtype=np.int64)
    for q in range(n_queries):
        if counts[q] > 0:
            paths[q, 0, 0], paths[q, 0, 1] = starts[q, 0], starts[q, 1]
            paths[q, counts[q] - 1, 0], paths[q, counts[q] - 1, 1] = goals[q, 0], goals[q, 1]
    for row in range(around.shape[0]):
        q = around[row]
        if counts[q] == 0:
            continue
        node, index = leaves[row], counts[q] - 2
        while True:
            paths[q, index, 0], paths[q, index, 1] = nodes[node, 0], nodes[node, 1]
            node_of[q, index] = node
            if node == entries[row]:
                break
            node = predecessors[entries[row], node]
            index -= 1
    return paths, counts, node_of


@numba.njit(cache=True)
def nearest_wall_points(points, seg_start, seg_end):
    """(K, 2): the point of the walls nearest each point (K, 2)."""
    nearest = np.zeros_like(points)
    for k in range(points.shape[0]):
        px, py, best = points[k, 0], points[k, 1], np.inf
        for s in range(seg_start.shape[0]):
            ax, ay, bx, by = seg_start[s, 0], seg_start[s, 1], seg_end[s, 0], seg_end[s, 1]
            ex, ey = bx - ax, by - ay
            length_squared = ex * ex + ey * ey
            t = 0.0
            if length_squared > 0.0:
                t = min(max(((px - ax) * ex + (py - ay) * ey) / length_squared, 0.0), 1.0)
            cx, cy = ax + t * ex, ay + t * ey
            distance = (px - cx) * (px - cx) + (py - cy) * (py - cy)
            if distance < best:
                best = distance
                nearest[k, 0], nearest[k, 1] = cx, cy
    return nearest


@numba.njit(cache=True)
def plan_kernel(starts, goals, nodes, previous, following, distance, predecessors, clearance, seg_start, seg_end,
                 vertices, offsets, area_sizes, solid_inside, solid_outside):
    """`GlobalPlanner.plan` with the table, in one compiled call: starts and goals in free space (`solid_points`),
    the straight line where it keeps the clearance, else the connections (`links_kernel`) and the table
    (`_table_paths`)."""
    free = ~(solid_points(starts, vertices, offsets, area_sizes, solid_inside, solid_outside)
             | solid_points(goals, vertices, offsets, area_sizes, solid_inside, solid_outside))
    straight = np.zeros(starts.shape[0], dtype=np.bool_)
    for q in range(starts.shape[0]):
        straight[q] = free[q] and _segment_clear(starts[q, 0], starts[q, 1], goals[q, 0], goals[q, 1], clearance,
                                                 seg_start, seg_end)
    around = np.nonzero(free & ~straight)[0]
    start_links = links_kernel(starts[around], nodes, previous, following, clearance, seg_start, seg_end)
    goal_links = links_kernel(goals[around], nodes, previous, following, clearance, seg_start, seg_end)
    return _table_paths(starts, goals, straight, around, start_links, goal_links, distance, predecessors, nodes)


@numba.njit(cache=True)
def solid_points(points, vertices, offsets, area_sizes, solid_inside, solid_outside):
    """(K,) bool: whether each point lies in solid space (`Nesting`'s rule)."""
    inside = points_in_polygons(points, vertices, offsets)
    solid = np.full(points.shape[0], solid_outside)
    for k in range(points.shape[0]):
        innermost, smallest = -1, np.inf
        for p in range(area_sizes.shape[0]):
            if inside[k, p] and area_sizes[p] < smallest:
                innermost, smallest = p, area_sizes[p]
        if innermost >= 0:
            solid[k] = solid_inside[innermost]
    return solid


@numba.njit(cache=True, inline="always")
def _nearest_on_segment(px, py, ax, ay, bx, by):
    """(t, distance): p's nearest point on the segment [a, b] is a + t (b - a) (sqrt rather than hypot: this runs for
    every agent at every step)."""
    ex, ey = bx - ax, by - ay
    length_squared = ex * ex + ey * ey
    t = 0.0
    if length_squared > 0.0:
        t = min(max(((px - ax) * ex + (py - ay) * ey) / length_squared, 0.0), 1.0)
    dx, dy = px - (ax + t * ex), py - (ay + t * ey)
    return t, math.sqrt(dx * dx + dy * dy)


@numba.njit(cache=True, inline="always")
def _distance_to_segment(px, py, ax, ay, bx, by):
    """Distance from p to the segment [a, b]."""
    return _nearest_on_segment(px, py, ax, ay, bx, by)[1]


@numba.njit(cache=True)
def _follow(k, px, py, paths, counts, segments, lookahead):
    """Agent k on its path: the nearest point of the path from its current segment on (the segment index advances
    to it; at a vertex, the segment leaving it), and the point `lookahead` metres further along the path (its last
    vertex at most). Returns (distance to the path, carrot x, carrot y, the carrot's segment)."""
    best, best_distance, best_t = segments[k], np.inf, 0.0
    for s in range(segments[k], counts[k] - 1):
        t, distance = _nearest_on_segment(px, py, paths[k, s, 0], paths[k, s, 1], paths[k, s + 1, 0],
                                          paths[k, s + 1, 1])
        if distance <= best_distance:
            best, best_distance, best_t = s, distance, t
    segments[k] = best
    remaining, s, t = lookahead, best, best_t
    last = counts[k] - 1
    carrot_x, carrot_y = paths[k, last, 0], paths[k, last, 1]
    while s < last:
        ax, ay, bx, by = paths[k, s, 0], paths[k, s, 1], paths[k, s + 1, 0], paths[k, s + 1, 1]
        length = math.sqrt((bx - ax) * (bx - ax) + (by - ay) * (by - ay))
        ahead = (1.0 - t) * length
        if remaining <= ahead and length > 0.0:
            u = t + remaining / length
            carrot_x, carrot_y = ax + u * (bx - ax), ay + u * (by - ay)
            break
        remaining -= ahead
        s += 1
        t = 0.0
    return best_distance, carrot_x, carrot_y, min(s, last - 1)


def follow_path(path: np.ndarray, position: np.ndarray, lookahead: float) -> np.ndarray:
    """The pure-pursuit subgoal on one path ((M, 2), M >= 2): `lookahead` metres along it beyond its point nearest to
    `position`, searched over the whole path (`_follow`, as for a stored path; its last vertex at most)."""
    paths = np.ascontiguousarray(path, dtype=np.float64)[None]
    counts, segments = np.array([len(path)], dtype=np.int64), np.zeros(1, dtype=np.int64)
    _, x, y, _ = _follow(0, float(position[0]), float(position[1]), paths, counts, segments, float(lookahead))
    return np.array([x, y])


@numba.njit(cache=True)
def steer(asked, fill, positions, goals, mode, view_at, view_goal, view_spare, paths, path_nodes, counts, segments,
           path_goal, fallback_at, anchors, seg_start, seg_end, clearance, direct_clearance, lookahead,
           replan_distance, goal_tolerance, reach, subgoals, direct, replan):
    """Each step's subgoal of every agent `asked` ((K,) bool; positions, goals (K, 2) of all K agents), in place
    (with `fill`, every other agent gets its goal):

    * the goal (`direct`), when the straight line to it keeps `direct_clearance`. A line found so with room to
      spare (`view_spare`, `_segment_spare`) is not checked again while the agent lies that close to the line
      checked (from `view_at` to `view_goal`) and its goal that close to the goal checked: the line from the agent
      to its goal is then that close to the one checked. An agent following its path checks its goal only on the
      path's last leg (so that it does not flip between its goal and its path at every push of the crowd).
    * else, along its stored path when the path leads to this goal (`path_goal`, within `goal_tolerance`; the
      path's last vertex follows a goal that moved less), the agent is within `replan_distance` of it and sees its
      next vertex (no wall crosses the line to it; certain, and not checked, for an agent nearer its path than the
      clearance the path keeps): the carrot `lookahead` metres ahead along the path. A carrot past a vertex is
      used where the line to it keeps the clearance from the wall corner each vertex passed turns round (its node's
      `anchors`), else the next vertex (the agent rounds the corner rather than cutting across it); a carrot before
      it lies between the agent's nearest path point and the next vertex, within the triangle of the agent, that
      point and the vertex. A carrot nearer than `reach` is pushed out along
      its direction (models that slow down near their goal must not slow down for a subgoal).
    * else, after a failed plan for this goal: the goal, until the agent is `replan_distance` from where the plan
      failed (`fallback_at`).
    * else: `replan`, the goal meanwhile.

    Returns how many agents it marked for `replan`.
    """
    inside_tube = clearance - CLEARANCE_SLACK
    pending = 0
    for k in range(asked.shape[0]):
        if not asked[k] and not fill:
            continue
        px, py = positions[k, 0], positions[k, 1]
        gx, gy = goals[k, 0], goals[k, 1]
        subgoals[k, 0], subgoals[k, 1] = gx, gy
        direct[k] = True
        replan[k] = False
        if not asked[k]:
            continue
        if mode[k] == DIRECT:
            dx, dy = gx - view_goal[k, 0], gy - view_goal[k, 1]
            shift = max(_distance_to_segment(px, py, view_at[k, 0], view_at[k, 1], view_goal[k, 0], view_goal[k, 1]),
                        math.sqrt(dx * dx + dy * dy))
            if shift < view_spare[k]:
                continue
        dx, dy = gx - path_goal[k, 0], gy - path_goal[k, 1]
        same_goal = math.sqrt(dx * dx + dy * dy) <= goal_tolerance
        # An agent on its path keeps to it up to the path's last leg (no check of its goal before)
        before_last_leg = mode[k] == ON_PATH and same_goal and segments[k] < counts[k] - 2
        if not before_last_leg:
            clear, room = _segment_spare(px, py, gx, gy, direct_clearance, _SPARE_HORIZON, seg_start, seg_end)
            if clear:
                mode[k] = DIRECT
                view_at[k, 0], view_at[k, 1] = px, py
                view_goal[k, 0], view_goal[k, 1] = gx, gy
                view_spare[k] = room
                continue
        if same_goal and counts[k] >= 2:
            last = counts[k] - 1
            paths[k, last, 0], paths[k, last, 1] = gx, gy
            distance, carrot_x, carrot_y, carrot_segment = _follow(k, px, py, paths, counts, segments, lookahead)
            segment = segments[k]
            next_x, next_y = paths[k, segment + 1, 0], paths[k, segment + 1, 1]
            if distance <= replan_distance and (
                    distance < inside_tube or _segment_clear(px, py, next_x, next_y, 0.0, seg_start, seg_end)):
                for vertex in range(segment + 1, carrot_segment + 1):  # the corners the carrot lies past
                    node = path_nodes[k, vertex]
                    if node >= 0 and _distance_to_segment(anchors[node, 0], anchors[node, 1], px, py, carrot_x,
                                                          carrot_y) < inside_tube:
                        carrot_x, carrot_y = next_x, next_y  # round the corner, not across it
                        break
                offset_x, offset_y = carrot_x - px, carrot_y - py
                length = math.sqrt(offset_x * offset_x + offset_y * offset_y)
                if 0.0 < length < reach:
                    carrot_x, carrot_y = px + offset_x * reach / length, py + offset_y * reach / length
                mode[k] = ON_PATH
                subgoals[k, 0], subgoals[k, 1] = carrot_x, carrot_y
                direct[k] = False
                continue
        elif mode[k] == FALLBACK and same_goal:
            dx, dy = px - fallback_at[k, 0], py - fallback_at[k, 1]
            if math.sqrt(dx * dx + dy * dy) <= replan_distance:
                continue  # heading straight at a goal no path reaches
        replan[k] = True
        pending += 1
    return pending


@numba.njit(cache=True)
def store_plans(agents, positions, goals, new_paths, new_counts, new_nodes, paths, path_nodes, counts, segments,
                 path_goal, fallback_at, mode):
    """Store the paths just planned for `agents` (`GlobalPlanner.plan`'s arrays); a failed plan (count 0) is a
    `FALLBACK` at the agent's position."""
    for a in range(agents.shape[0]):
        k = agents[a]
        counts[k] = new_counts[a]
        for v in range(new_counts[a]):
            paths[k, v, 0], paths[k, v, 1] = new_paths[a, v, 0], new_paths[a, v, 1]
            path_nodes[k, v] = new_nodes[a, v]
        segments[k] = 0
        path_goal[k, 0], path_goal[k, 1] = goals[a, 0], goals[a, 1]
        if new_counts[a] == 0:
            mode[k] = FALLBACK
            fallback_at[k, 0], fallback_at[k, 1] = positions[a, 0], positions[a, 1]
        else:
            mode[k] = ON_PATH


@numba.njit(cache=True)
def _redirect(velocities, positions, subgoals, direct):
    for k in range(velocities.shape[0]):
        if direct[k]:
            continue
        offset_x, offset_y = subgoals[k, 0] - positions[k, 0], subgoals[k, 1] - positions[k, 1]
        length = max(math.hypot(offset_x, offset_y), 1e-12)
        speed = math.hypot(velocities[k, 0], velocities[k, 1])
        velocities[k, 0], velocities[k, 1] = speed * offset_x / length, speed * offset_y / length


def redirect_to_subgoals(velocities: np.ndarray, positions: np.ndarray, subgoals: np.ndarray,
                         direct: np.ndarray) -> None:
    """Turn each velocity (K, 2; a view is written in place) whose agent is not `direct` towards its subgoal at the
    same speed; the others keep theirs exactly (`PathFollower.update`'s subgoals and direct flags)."""
    _redirect(velocities, positions, subgoals, direct)

