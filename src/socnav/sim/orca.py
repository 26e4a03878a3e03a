"""ORCA reciprocal collision avoidance: an exact float64 port of RVO2's ORCA (agents and static obstacles), in numba.

One kernel call updates all agents of all envs; per pair (i, j) it adds a radius pad, an avoidance share and visibility.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from socnav.sim.obstacles import RVO_EPSILON, ObstacleBatch

__all__ = [
    "RVO_EPSILON",
    "TOUCH_MARGIN",
    "default_social_arrays",
    "linear_program1",
    "linear_program2",
    "linear_program3",
    "nearest_neighbors",
    "obstacle_neighbors",
    "obstacle_orca_lines",
    "orca_line",
    "orca_velocities",
    "orca_velocities_kernel",
    "orca_velocities_obstacles_kernel",
]


# --------------------------------------------------------------------------------------------------------------------
# Small vector helpers (scalars in, scalars out: numba keeps them in registers).
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _det(ax, ay, bx, by):
    """2-D cross product a x b; > 0 when b points to the left of a."""
    return ax * by - ay * bx


# --------------------------------------------------------------------------------------------------------------------
# The linear programs. Lines are stored as two (K, 2) arrays: `points[k]` lies on line k and `directions[k]` is its unit
# direction; the admissible half-plane is to the LEFT of the direction, so a velocity v violates line k when
# det(directions[k], points[k] - v) > 0.
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def linear_program1(points, directions, line_no, radius, opt_x, opt_y, direction_opt):
    """RVO2 linearProgram1: best point on line `line_no` inside the disc |v| <= radius and left of lines 0..line_no-1.

    Returns (feasible, x, y); with direction_opt the optimum is the extreme point along (opt_x, opt_y), otherwise the
    point closest to (opt_x, opt_y).
    """
    px, py = points[line_no, 0], points[line_no, 1]
    dx, dy = directions[line_no, 0], directions[line_no, 1]

    # Intersect the line p + t d with the speed circle: t = -p.d -+ sqrt((p.d)^2 + r^2 - |p|^2).
    dot = px * dx + py * dy
    discriminant = dot * dot + radius * radius - (px * px + py * py)
    if discriminant < 0.0:
        return False, 0.0, 0.0  # the speed circle lies entirely outside this line's half-plane
    sqrt_discriminant = np.sqrt(discriminant)
    t_left = -dot - sqrt_discriminant
    t_right = -dot + sqrt_discriminant

    # Every earlier line clips the admissible interval [t_left, t_right] of this one.
    for k in range(line_no):
        denominator = _det(dx, dy, directions[k, 0], directions[k, 1])
        numerator = _det(directions[k, 0], directions[k, 1], px - points[k, 0], py - points[k, 1])
        if abs(denominator) <= RVO_EPSILON:
            # (Almost) parallel lines: either line k excludes this whole line, or it does not constrain it.
            if numerator < 0.0:
                return False, 0.0, 0.0
            continue
        t = numerator / denominator
        if denominator >= 0.0:
            t_right = min(t_right, t)  # line k bounds this line on the right
        else:
            t_left = max(t_left, t)  # line k bounds this line on the left
        if t_left > t_right:
            return False, 0.0, 0.0

    if direction_opt:
        t = t_right if opt_x * dx + opt_y * dy > 0.0 else t_left
    else:
        # Project the optimisation velocity on the line and clamp to the admissible interval.
        t = dx * (opt_x - px) + dy * (opt_y - py)
        if t < t_left:
            t = t_left
        elif t > t_right:
            t = t_right
    return True, px + t * dx, py + t * dy


@numba.njit(cache=True)
def linear_program2(points, directions, n_lines, radius, opt_x, opt_y, direction_opt):
    """RVO2 linearProgram2: incremental 2-D LP over lines 0..n_lines-1 inside the disc |v| <= radius.

    Returns (fail_line, x, y): fail_line == n_lines on success; otherwise the first line that made the problem
    infeasible, with (x, y) the optimum of the lines before it (where linearProgram3 starts).
    """
    if direction_opt:
        # (opt_x, opt_y) is a unit direction: start at the extreme point of the disc along it.
        rx, ry = opt_x * radius, opt_y * radius
    elif opt_x * opt_x + opt_y * opt_y > radius * radius:
        # Closest point of the disc to an optimisation velocity outside it.
        norm = np.sqrt(opt_x * opt_x + opt_y * opt_y)
        rx, ry = opt_x / norm * radius, opt_y / norm * radius
    else:
        rx, ry = opt_x, opt_y

    for k in range(n_lines):
        if _det(directions[k, 0], directions[k, 1], points[k, 0] - rx, points[k, 1] - ry) > 0.0:
            # The current optimum violates line k: the new optimum lies on line k.
            feasible, nx, ny = linear_program1(points, directions, k, radius, opt_x, opt_y, direction_opt)
            if not feasible:
                return k, rx, ry
            rx, ry = nx, ny
    return n_lines, rx, ry


@numba.njit(cache=True)
def linear_program3(
    points, directions, n_lines, n_obstacle_lines, begin_line, radius, rx, ry, proj_points, proj_directions
):
    """RVO2 linearProgram3: when the 2-D LP is infeasible, minimise the largest violation of the agent lines while
    keeping the first `n_obstacle_lines` lines (the obstacles') hard.

    Lines from `begin_line` on are handled one at a time: if line i is violated by more than the current worst
    distance, solve a 2-D LP over the obstacle lines and the agent lines before i projected onto line i (the
    bisectors where violating them equals violating line i), optimising towards the inside of line i. Returns the new
    (x, y).
    """
    distance = 0.0
    for i in range(begin_line, n_lines):
        dix, diy = directions[i, 0], directions[i, 1]
        pix, piy = points[i, 0], points[i, 1]
        if _det(dix, diy, pix - rx, piy - ry) > distance:
            # The obstacle lines are copied as they are: never relaxed.
            for j in range(n_obstacle_lines):
                proj_points[j, 0], proj_points[j, 1] = points[j, 0], points[j, 1]
                proj_directions[j, 0], proj_directions[j, 1] = directions[j, 0], directions[j, 1]
            n_proj = n_obstacle_lines
            for j in range(n_obstacle_lines, i):
                djx, djy = directions[j, 0], directions[j, 1]
                pjx, pjy = points[j, 0], points[j, 1]
                determinant = _det(dix, diy, djx, djy)
                if abs(determinant) <= RVO_EPSILON:
                    if dix * djx + diy * djy > 0.0:
                        continue  # same direction: line j never binds harder than line i
                    # Opposite directions: the bisector runs midway between them.
                    qx, qy = 0.5 * (pix + pjx), 0.5 * (piy + pjy)
                else:
                    # The bisector passes through the intersection of lines i and j.
                    s = _det(djx, djy, pix - pjx, piy - pjy) / determinant
                    qx, qy = pix + s * dix, piy + s * diy
                ex, ey = djx - dix, djy - diy
                norm = np.sqrt(ex * ex + ey * ey)
                proj_points[n_proj, 0], proj_points[n_proj, 1] = qx, qy
                proj_directions[n_proj, 0], proj_directions[n_proj, 1] = ex / norm, ey / norm
                n_proj += 1

            # Optimise along the inward normal of line i. The current result is feasible by construction, so a
            # failure can only be floating-point noise: then RVO2 keeps the current result.
            fail, nx, ny = linear_program2(proj_points, proj_directions, n_proj, radius, -diy, dix, True)
            if fail >= n_proj:
                rx, ry = nx, ny
            distance = _det(dix, diy, pix - rx, piy - ry)
    return rx, ry


# --------------------------------------------------------------------------------------------------------------------
# Neighbours and ORCA half-planes.
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True)
def nearest_neighbors(positions, active, sees, e, i, neighbor_dist, max_neighbors, neighbor_index, neighbor_dist_sq):
    """RVO2 computeNeighbors for agent i of env e: the up-to-max_neighbors nearest visible active agents.

    Fills neighbor_index / neighbor_dist_sq in ascending squared distance and returns their count. Mirrors
    insertAgentNeighbor: strict '<' comparisons (ties keep the earlier agent first), and once the list is full the
    search range shrinks to the farthest kept neighbour.
    """
    if max_neighbors <= 0:
        return 0
    range_sq = neighbor_dist * neighbor_dist
    count = 0
    xi, yi = positions[e, i, 0], positions[e, i, 1]
    for j in range(positions.shape[1]):
        if j == i or not active[e, j] or not sees[e, i, j]:
            continue  # an unseen agent does not take a neighbour slot
        dx, dy = xi - positions[e, j, 0], yi - positions[e, j, 1]
        dist_sq = dx * dx + dy * dy
        if dist_sq < range_sq:
            if count < max_neighbors:
                count += 1
            # Insertion sort; when full, the farthest neighbour falls off the end.
            k = count - 1
            while k > 0 and dist_sq < neighbor_dist_sq[k - 1]:
                neighbor_dist_sq[k] = neighbor_dist_sq[k - 1]
                neighbor_index[k] = neighbor_index[k - 1]
                k -= 1
            neighbor_dist_sq[k] = dist_sq
            neighbor_index[k] = j
            if count == max_neighbors:
                range_sq = neighbor_dist_sq[count - 1]
    return count


@numba.njit(cache=True)
def orca_line(rel_px, rel_py, rel_vx, rel_vy, combined_radius, inv_time_horizon, inv_time_step, tie_sign):
    """RVO2's agent-agent ORCA geometry: the line direction d and the smallest change u of the relative velocity that
    leaves the velocity obstacle (truncated at the time horizon).

    rel_p = p_j - p_i, rel_v = v_i - v_j. Returns (d_x, d_y, u_x, u_y); the caller places the line at v_i + share * u.
    tie_sign (+1 or -1, opposite for i and j) only breaks the 0/0 of RVO2 when w = 0 in the collision case.
    """
    dist_sq = rel_px * rel_px + rel_py * rel_py
    combined_radius_sq = combined_radius * combined_radius

    if dist_sq > combined_radius_sq:
        # No collision. w: from the cut-off circle's centre (rel_p / tau) to the relative velocity.
        wx, wy = rel_vx - inv_time_horizon * rel_px, rel_vy - inv_time_horizon * rel_py
        w_length_sq = wx * wx + wy * wy
        dot = wx * rel_px + wy * rel_py

        if dot < 0.0 and dot * dot > combined_radius_sq * w_length_sq:
            # The relative velocity is closest to the cut-off circle (radius R / tau): push it out radially.
            w_length = np.sqrt(w_length_sq)
            unit_wx, unit_wy = wx / w_length, wy / w_length
            dx, dy = unit_wy, -unit_wx
            scale = combined_radius * inv_time_horizon - w_length
            return dx, dy, scale * unit_wx, scale * unit_wy

        # Otherwise it is closest to one of the cone's legs (tangents from the origin to the disc of radius R).
        leg = np.sqrt(dist_sq - combined_radius_sq)
        if _det(rel_px, rel_py, wx, wy) > 0.0:
            # Left leg: rel_p rotated by +asin(R / |rel_p|).
            dx = (rel_px * leg - rel_py * combined_radius) / dist_sq
            dy = (rel_px * combined_radius + rel_py * leg) / dist_sq
        else:
            # Right leg: rel_p rotated by -asin(R / |rel_p|), reversed so the admissible side stays on the left.
            dx = -(rel_px * leg + rel_py * combined_radius) / dist_sq
            dy = -(-rel_px * combined_radius + rel_py * leg) / dist_sq
        # u: from the relative velocity to its projection on the leg.
        along = rel_vx * dx + rel_vy * dy
        return dx, dy, along * dx - rel_vx, along * dy - rel_vy

    # Collision: the agents already overlap, so resolve it within one time step (cut-off circle at rel_p / dt).
    wx, wy = rel_vx - inv_time_step * rel_px, rel_vy - inv_time_step * rel_py
    w_length = np.sqrt(wx * wx + wy * wy)
    if w_length > 0.0:
        unit_wx, unit_wy = wx / w_length, wy / w_length
    elif dist_sq > 0.0:
        # RVO2 divides 0 by 0 here (NaN); move straight away from the neighbour instead.
        dist = np.sqrt(dist_sq)
        unit_wx, unit_wy = -rel_px / dist, -rel_py / dist
    else:
        # Coincident agents with equal velocities: separate them along x, in opposite directions.
        unit_wx, unit_wy = tie_sign, 0.0
    dx, dy = unit_wy, -unit_wx
    scale = combined_radius * inv_time_step - w_length
    return dx, dy, scale * unit_wx, scale * unit_wy


# --------------------------------------------------------------------------------------------------------------------
# Static obstacles (RVO2 Agent::computeNeighbors / insertObstacleNeighbor / computeNewVelocity, obstacle part), on one
# env's `ObstacleBatch` rows. They live here, next to the kernel that runs them, not in `socnav.sim.obstacles`: numba
# keys a cached kernel on its own file's content only, so a kernel calling njit code of another file keeps running
# the old code after that file changes.
# --------------------------------------------------------------------------------------------------------------------
# An agent whose squared distance to an edge or vertex is within this relative margin of r^2 counts as touching it
# (RVO2 tests `distSq <= radiusSq` exactly). At the exact touch RVO2's non-collision half-planes degenerate: seen from
# distance r, a wall segment's two legs turn "foreign" (parallel to the wall) and tie with its cut-off line, rounding
# can pick a foreign leg, and then no half-plane is added at all -- pyrvo itself lets an agent that converged onto a
# wall walk through it that way. The collision half-plane (v . n <= 0) is the limit of the cut-off one
# (v . n <= (d - r) / tau) as d -> r, so the margin changes velocities by at most ~1e-9 r / tau elsewhere.
TOUCH_MARGIN = 1e-9


@numba.njit(cache=True)
def obstacle_neighbors(
    px, py, range_sq, point, next_vertex, tree_vertex, tree_left, tree_right, n_vertices, stack, neighbor_vertex,
    neighbor_dist_sq,
):  # fmt: skip
    """RVO2 computeObstacleNeighbors for an agent at p: the edges it faces within sqrt(range_sq), nearest first.

    queryObstacleTreeRecursive, in its order: descend to the agent's side of each node's line first; then, if the
    line is within range, offer the node's edge (only when the agent is strictly on its right, i.e. outside a solid
    polygon's edge) and visit the other side. insertObstacleNeighbor keeps the edges whose closest point is within
    range, insertion-sorted by squared distance with strict '<' (ties keep the earlier edge first).
    `stack`: int64 scratch of n_vertices + 1 entries (entry 2 node + phase); fills neighbor_vertex / neighbor_dist_sq
    (n_vertices entries each) and returns the neighbour count.
    """
    count = 0
    if n_vertices == 0:
        return 0
    stack[0] = 0  # root, phase 0 (not yet descended)
    depth = 1
    while depth > 0:
        depth -= 1
        node, phase = stack[depth] >> 1, stack[depth] & 1
        a = tree_vertex[node]
        b = next_vertex[a]
        ax, ay, bx, by = point[a, 0], point[a, 1], point[b, 0], point[b, 1]
        agent_left = _det(ax - px, ay - py, bx - ax, by - ay)  # RVO2 leftOf(a, b, p)
        near, far = (tree_left[node], tree_right[node]) if agent_left >= 0.0 else (tree_right[node], tree_left[node])
        if phase == 0:
            stack[depth] = 2 * node + 1
            depth += 1
            if near >= 0:
                stack[depth] = 2 * near
                depth += 1
            continue
        edge_x, edge_y = bx - ax, by - ay
        edge_length_sq = edge_x * edge_x + edge_y * edge_y
        if agent_left * agent_left / edge_length_sq < range_sq:
            if agent_left < 0.0:
                # Distance to the edge: to its closest point a + r (b - a), r clamped to [0, 1].
                r = ((px - ax) * edge_x + (py - ay) * edge_y) / edge_length_sq
                if r < 0.0:
                    dx, dy = px - ax, py - ay
                elif r > 1.0:
                    dx, dy = px - bx, py - by
                else:
                    dx, dy = px - (ax + r * edge_x), py - (ay + r * edge_y)
                dist_sq = dx * dx + dy * dy
                if dist_sq < range_sq:
                    k = count
                    count += 1
                    while k > 0 and dist_sq < neighbor_dist_sq[k - 1]:
                        neighbor_dist_sq[k] = neighbor_dist_sq[k - 1]
                        neighbor_vertex[k] = neighbor_vertex[k - 1]
                        k -= 1
                    neighbor_dist_sq[k] = dist_sq
                    neighbor_vertex[k] = a
            if far >= 0:
                stack[depth] = 2 * far
                depth += 1
    return count


@numba.njit(cache=True)
def _any_edge_within(px, py, range_sq, point, next_vertex, n_vertices):
    """Whether some edge (vertex a to next_vertex[a]) may have its closest point to p within sqrt(range_sq)."""
    reach = math.sqrt(range_sq) * (1.0 + 1e-9) + 1e-9
    for a in range(n_vertices):
        b = next_vertex[a]
        ax, ay, bx, by = point[a, 0], point[a, 1], point[b, 0], point[b, 1]
        if px < min(ax, bx) - reach or px > max(ax, bx) + reach or py < min(ay, by) - reach or py > max(ay, by) + reach:
            continue  # the edge's bounding box, grown by the range, misses p: so does the edge
        edge_x, edge_y = bx - ax, by - ay
        r = ((px - ax) * edge_x + (py - ay) * edge_y) / (edge_x * edge_x + edge_y * edge_y)
        r = min(max(r, 0.0), 1.0)
        dx, dy = px - (ax + r * edge_x), py - (ay + r * edge_y)
        if dx * dx + dy * dy < range_sq * (1.0 + 1e-9) + 1e-12:  # a margin: the query itself decides at the edge
            return True
    return False


@numba.njit(cache=True)
def _push_line(line_points, line_directions, n_lines, point_x, point_y, direction_x, direction_y):
    line_points[n_lines, 0], line_points[n_lines, 1] = point_x, point_y
    line_directions[n_lines, 0], line_directions[n_lines, 1] = direction_x, direction_y
    return n_lines + 1


@numba.njit(cache=True, inline="always")
def _covered_by_earlier_lines(line_points, line_directions, n_lines, r1x, r1y, r2x, r2y, radius,
                              inv_time_horizon_obst):
    """Whether both cut-off discs of an edge (end vertices at r1, r2 relative to the agent) already lie beyond one
    of the half-planes found so far (up to RVO_EPSILON): RVO2 then adds no line for that edge."""
    for j in range(n_lines):
        ljx, ljy = line_points[j, 0], line_points[j, 1]
        djx, djy = line_directions[j, 0], line_directions[j, 1]
        c1x, c1y = inv_time_horizon_obst * r1x - ljx, inv_time_horizon_obst * r1y - ljy
        c2x, c2y = inv_time_horizon_obst * r2x - ljx, inv_time_horizon_obst * r2y - ljy
        if (
            c1x * djy - c1y * djx - inv_time_horizon_obst * radius >= -RVO_EPSILON
            and c2x * djy - c2y * djx - inv_time_horizon_obst * radius >= -RVO_EPSILON
        ):
            return True
    return False


@numba.njit(cache=True, inline="always")
def _overlap_line(r1x, r1y, r2x, r2y, s, dist_sq1, dist_sq2, dist_sq_line, touch_sq, obstacle1, obstacle2,
                  is_convex, unit_dir):
    """An agent already overlapping (or touching, `TOUCH_MARGIN`) the edge or one of its vertices: the half-plane
    through v = 0 that forbids moving further in. Returns (overlapping, has_line, direction_x, direction_y).

    Only a convex vertex gets a line (a concave vertex's edges cover it); the right vertex is the next edge's left
    vertex, so it is left to that edge unless the agent is behind it; an agent centred exactly on a vertex has no
    direction (RVO2: a NaN line), so no line.
    """
    if s < 0.0 and dist_sq1 <= touch_sq:
        if is_convex[obstacle1] and dist_sq1 > 0.0:
            norm = np.sqrt(dist_sq1)
            return True, True, -r1y / norm, r1x / norm
        return True, False, 0.0, 0.0
    if s > 1.0 and dist_sq2 <= touch_sq:
        behind = r2x * unit_dir[obstacle2, 1] - r2y * unit_dir[obstacle2, 0] >= 0.0
        if is_convex[obstacle2] and behind and dist_sq2 > 0.0:
            norm = np.sqrt(dist_sq2)
            return True, True, -r2y / norm, r2x / norm
        return True, False, 0.0, 0.0
    if s >= 0.0 and s <= 1.0 and dist_sq_line <= touch_sq:
        return True, True, -unit_dir[obstacle1, 0], -unit_dir[obstacle1, 1]
    return False, False, 0.0, 0.0


@numba.njit(cache=True, inline="always")
def _obstacle_legs(r1x, r1y, r2x, r2y, s, dist_sq1, dist_sq2, dist_sq_line, radius, radius_sq, obstacle1,
                   obstacle2, is_convex, unit_dir, prev_vertex):
    """The legs of the edge's velocity obstacle for an agent that does not overlap it.

    Leg directions are the tangents from p to the disc of radius r around a vertex at relative position q: q rotated
    by +-asin(r / |q|), scaled to unit length: (q_x l -+ q_y r, +-q_x r + q_y l) / |q|^2 with l = sqrt(|q|^2 - r^2).
    Seen obliquely, one (convex) vertex alone shapes the velocity obstacle (then obstacle1 == obstacle2); a concave
    end vertex continues the cut-off line. A leg at a convex vertex must not point into the neighbouring edge: then
    that edge's direction replaces it ("foreign" leg). Returns (skip, obstacle1, obstacle2, left_x, left_y, right_x,
    right_y, left_foreign, right_foreign); skip: the edge adds no line (seen obliquely at a concave vertex).
    """
    if s < 0.0 and dist_sq_line <= radius_sq:
        if not is_convex[obstacle1]:
            return True, obstacle1, obstacle2, 0.0, 0.0, 0.0, 0.0, False, False
        obstacle2 = obstacle1
        leg1 = np.sqrt(dist_sq1 - radius_sq)
        left_x = (r1x * leg1 - r1y * radius) / dist_sq1
        left_y = (r1x * radius + r1y * leg1) / dist_sq1
        right_x = (r1x * leg1 + r1y * radius) / dist_sq1
        right_y = (-r1x * radius + r1y * leg1) / dist_sq1
    elif s > 1.0 and dist_sq_line <= radius_sq:
        if not is_convex[obstacle2]:
            return True, obstacle1, obstacle2, 0.0, 0.0, 0.0, 0.0, False, False
        obstacle1 = obstacle2
        leg2 = np.sqrt(dist_sq2 - radius_sq)
        left_x = (r2x * leg2 - r2y * radius) / dist_sq2
        left_y = (r2x * radius + r2y * leg2) / dist_sq2
        right_x = (r2x * leg2 + r2y * radius) / dist_sq2
        right_y = (-r2x * radius + r2y * leg2) / dist_sq2
    else:
        if is_convex[obstacle1]:
            leg1 = np.sqrt(dist_sq1 - radius_sq)
            left_x = (r1x * leg1 - r1y * radius) / dist_sq1
            left_y = (r1x * radius + r1y * leg1) / dist_sq1
        else:
            left_x, left_y = -unit_dir[obstacle1, 0], -unit_dir[obstacle1, 1]
        if is_convex[obstacle2]:
            leg2 = np.sqrt(dist_sq2 - radius_sq)
            right_x = (r2x * leg2 + r2y * radius) / dist_sq2
            right_y = (-r2x * radius + r2y * leg2) / dist_sq2
        else:
            right_x, right_y = unit_dir[obstacle1, 0], unit_dir[obstacle1, 1]

    left_neighbor = prev_vertex[obstacle1]
    left_foreign = False
    right_foreign = False
    if is_convex[obstacle1] and (
        left_x * -unit_dir[left_neighbor, 1] - left_y * -unit_dir[left_neighbor, 0] >= 0.0
    ):
        left_x, left_y = -unit_dir[left_neighbor, 0], -unit_dir[left_neighbor, 1]
        left_foreign = True
    if is_convex[obstacle2] and right_x * unit_dir[obstacle2, 1] - right_y * unit_dir[obstacle2, 0] <= 0.0:
        right_x, right_y = unit_dir[obstacle2, 0], unit_dir[obstacle2, 1]
        right_foreign = True
    return False, obstacle1, obstacle2, left_x, left_y, right_x, right_y, left_foreign, right_foreign


@numba.njit(cache=True, inline="always")
def _cutoff_circle_line(vx, vy, centre_x, centre_y, radius, inv_time_horizon_obst):
    """v nearest to a cut-off circle: its tangent at v's projection. Returns (has_line, point_x, point_y,
    direction_x, direction_y); v on the centre has no direction, so no line."""
    wx, wy = vx - centre_x, vy - centre_y
    w_length = np.sqrt(wx * wx + wy * wy)
    if w_length > 0.0:
        ux, uy = wx / w_length, wy / w_length
        return (True, centre_x + radius * inv_time_horizon_obst * ux, centre_y + radius * inv_time_horizon_obst * uy,
                uy, -ux)
    return False, 0.0, 0.0, 0.0, 0.0


@numba.njit(cache=True, inline="always")
def _projection_line(px, py, vx, vy, radius, inv_time_horizon_obst, point, unit_dir, obstacle1, obstacle2, left_x,
                     left_y, right_x, right_y, left_foreign, right_foreign):
    """Project v on the nearest boundary piece of the truncated velocity obstacle (a cut-off circle, the cut-off
    line, the left or the right leg) and return that piece's tangent as (has_line, point_x, point_y, direction_x,
    direction_y); a velocity projecting on a foreign leg adds no line (the neighbouring edge handles it)."""
    # Cut-off centres and where v projects: on the cut-off segment (t), on the left leg (t_left), right (t_right).
    left_cx, left_cy = inv_time_horizon_obst * (point[obstacle1, 0] - px), inv_time_horizon_obst * (
        point[obstacle1, 1] - py
    )
    right_cx, right_cy = inv_time_horizon_obst * (point[obstacle2, 0] - px), inv_time_horizon_obst * (
        point[obstacle2, 1] - py
    )
    cut_x, cut_y = right_cx - left_cx, right_cy - left_cy
    same_vertex = obstacle1 == obstacle2
    t = 0.5 if same_vertex else ((vx - left_cx) * cut_x + (vy - left_cy) * cut_y) / (cut_x * cut_x + cut_y * cut_y)
    t_left = (vx - left_cx) * left_x + (vy - left_cy) * left_y
    t_right = (vx - right_cx) * right_x + (vy - right_cy) * right_y

    if (t < 0.0 and t_left < 0.0) or (same_vertex and t_left < 0.0 and t_right < 0.0):
        return _cutoff_circle_line(vx, vy, left_cx, left_cy, radius, inv_time_horizon_obst)
    if t > 1.0 and t_right < 0.0:
        return _cutoff_circle_line(vx, vy, right_cx, right_cy, radius, inv_time_horizon_obst)

    # Otherwise the nearest of the cut-off line, the left leg and the right leg (those v projects onto).
    if t < 0.0 or t > 1.0 or same_vertex:
        dist_sq_cutoff = np.inf
    else:
        dx, dy = vx - (left_cx + t * cut_x), vy - (left_cy + t * cut_y)
        dist_sq_cutoff = dx * dx + dy * dy
    if t_left < 0.0:
        dist_sq_left = np.inf
    else:
        dx, dy = vx - (left_cx + t_left * left_x), vy - (left_cy + t_left * left_y)
        dist_sq_left = dx * dx + dy * dy
    if t_right < 0.0:
        dist_sq_right = np.inf
    else:
        dx, dy = vx - (right_cx + t_right * right_x), vy - (right_cy + t_right * right_y)
        dist_sq_right = dx * dx + dy * dy

    # Each line passes r / tau outside its boundary piece, on the normal (-d_y, d_x).
    offset = radius * inv_time_horizon_obst
    if dist_sq_cutoff <= dist_sq_left and dist_sq_cutoff <= dist_sq_right:
        dx, dy = -unit_dir[obstacle1, 0], -unit_dir[obstacle1, 1]
        return True, left_cx - offset * dy, left_cy + offset * dx, dx, dy
    if dist_sq_left <= dist_sq_right:
        if left_foreign:
            return False, 0.0, 0.0, 0.0, 0.0
        return True, left_cx - offset * left_y, left_cy + offset * left_x, left_x, left_y
    if right_foreign:
        return False, 0.0, 0.0, 0.0, 0.0
    dx, dy = -right_x, -right_y
    return True, right_cx - offset * dy, right_cy + offset * dx, dx, dy


@numba.njit(cache=True)
def obstacle_orca_lines(
    px, py, vx, vy, radius, inv_time_horizon_obst, point, unit_dir, is_convex, next_vertex, prev_vertex,
    neighbor_vertex, n_neighbors, line_points, line_directions,
):  # fmt: skip
    """RVO2 Agent::computeNewVelocity, obstacle part: one ORCA half-plane per obstacle neighbour (nearest first) that
    is not already implied by the earlier ones, for an agent at p with velocity v and `radius`.

    Velocity obstacle of an edge a -> b over the horizon tau = 1 / inv_time_horizon_obst: the edge seen from p and
    truncated at (a - p) / tau, (b - p) / tau (cut-off centres, radius r / tau), bounded by legs tangent to the discs
    of radius r around the (convex) end vertices. The velocity v is projected on its nearest boundary piece (cut-off
    circle, cut-off line, left or right leg) and the half-plane is that piece's tangent line; obstacles are static, so
    the agent takes the whole correction. Already overlapping (or touching, `TOUCH_MARGIN`) an edge or vertex: the
    half-plane through v = 0 that forbids moving further in. Lines are appended to line_points / line_directions
    (admissible side on the left of the direction); returns their count.
    """
    radius_sq = radius * radius
    touch_sq = radius_sq * (1.0 + TOUCH_MARGIN)
    n_lines = 0
    for k in range(n_neighbors):
        obstacle1 = neighbor_vertex[k]
        obstacle2 = next_vertex[obstacle1]
        r1x, r1y = point[obstacle1, 0] - px, point[obstacle1, 1] - py
        r2x, r2y = point[obstacle2, 0] - px, point[obstacle2, 1] - py
        if _covered_by_earlier_lines(line_points, line_directions, n_lines, r1x, r1y, r2x, r2y, radius,
                                     inv_time_horizon_obst):
            continue

        dist_sq1 = r1x * r1x + r1y * r1y
        dist_sq2 = r2x * r2x + r2y * r2y
        ox, oy = point[obstacle2, 0] - point[obstacle1, 0], point[obstacle2, 1] - point[obstacle1, 1]
        # s: where p projects on the edge's line, a + s (b - a).
        s = (-r1x * ox - r1y * oy) / (ox * ox + oy * oy)
        lx, ly = -r1x - s * ox, -r1y - s * oy
        dist_sq_line = lx * lx + ly * ly

        overlapping, has_line, dx, dy = _overlap_line(r1x, r1y, r2x, r2y, s, dist_sq1, dist_sq2, dist_sq_line,
                                                      touch_sq, obstacle1, obstacle2, is_convex, unit_dir)
        if overlapping:
            if has_line:
                n_lines = _push_line(line_points, line_directions, n_lines, 0.0, 0.0, dx, dy)
            continue

        skip, obstacle1, obstacle2, left_x, left_y, right_x, right_y, left_foreign, right_foreign = _obstacle_legs(
            r1x, r1y, r2x, r2y, s, dist_sq1, dist_sq2, dist_sq_line, radius, radius_sq, obstacle1, obstacle2,
            is_convex, unit_dir, prev_vertex,
        )  # fmt: skip
        if skip:
            continue
        has_line, line_x, line_y, dx, dy = _projection_line(
            px, py, vx, vy, radius, inv_time_horizon_obst, point, unit_dir, obstacle1, obstacle2, left_x, left_y,
            right_x, right_y, left_foreign, right_foreign,
        )  # fmt: skip
        if has_line:
            n_lines = _push_line(line_points, line_directions, n_lines, line_x, line_y, dx, dy)
    return n_lines


# --------------------------------------------------------------------------------------------------------------------
# The batched kernels.
# --------------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def _line_buffers(max_vertices, capacity):
    """Scratch rows for one agent's half-planes and linearProgram3's projected ones: at most one line per obstacle
    edge and per other agent."""
    rows = max_vertices + capacity
    return (np.empty((rows, 2), dtype=np.float64), np.empty((rows, 2), dtype=np.float64),
            np.empty((rows, 2), dtype=np.float64), np.empty((rows, 2), dtype=np.float64))


@numba.njit(cache=True, inline="always")
def _within_speed(vx, vy, max_speed):
    """(vx, vy) projected back into the speed disc: the LPs stay inside it by construction, but far-away projected
    lines (nearly anti-parallel constraints in linearProgram3) can push the result out by rounding."""
    speed_sq = vx * vx + vy * vy
    if speed_sq > max_speed * max_speed:
        scale = max_speed / np.sqrt(speed_sq)
        vx, vy = vx * scale, vy * scale
    return vx, vy


@numba.njit(cache=True, inline="always")
def _orca_kernel(positions, velocities, radii, preferred_velocities, max_speeds, active, compute, radius_pad,
                 avoidance_share, sees, time_horizon, neighbor_dist, max_neighbors, time_step, obstacles,
                 time_horizon_obst, out):
    """The two kernels' common body. `obstacles` is None or the tuple `ObstacleBatch.kernel_arrays()`; numba prunes
    the `obstacles is None` branches at compile time, so the obstacle-free kernel carries no obstacle code at all.
    Per agent, as RVO2's computeNewVelocity: obstacle half-planes, agent half-planes, linearProgram2 and, when it is
    infeasible, linearProgram3."""
    n_envs, n_agents = positions.shape[0], positions.shape[1]
    max_vertices = 0
    if obstacles is not None:  # the obstacle query's scratch
        max_vertices = obstacles[0].shape[1]
        obstacle_vertex = np.empty(max_vertices, dtype=np.int64)
        obstacle_dist_sq = np.empty(max_vertices, dtype=np.float64)
        tree_stack = np.empty(max_vertices + 1, dtype=np.int64)
    capacity = max(0, min(max_neighbors, n_agents - 1))
    neighbor_index = np.empty(capacity, dtype=np.int64)
    neighbor_dist_sq = np.empty(capacity, dtype=np.float64)
    points, directions, proj_points, proj_directions = _line_buffers(max_vertices, capacity)
    inv_time_horizon, inv_time_step = 1.0 / time_horizon, 1.0 / time_step
    inv_time_horizon_obst = 1.0 / time_horizon_obst
    n_fallbacks = 0
    for e in range(n_envs):
        if obstacles is not None:
            # The env's map, as views taken once per env (a view per agent cost as much as the rest of its query).
            point, unit_dir, is_convex, next_vertex, prev_vertex, tree_vertex, tree_left, tree_right, count = (
                obstacles
            )
            n_vertices = count[e]
            env_point, env_unit_dir, env_is_convex = point[e], unit_dir[e], is_convex[e]
            env_next, env_prev = next_vertex[e], prev_vertex[e]
            env_tree_vertex, env_tree_left, env_tree_right = tree_vertex[e], tree_left[e], tree_right[e]
        for i in range(n_agents):
            vix, viy = velocities[e, i, 0], velocities[e, i, 1]
            if not (active[e, i] and compute[e, i]):
                out[e, i, 0], out[e, i, 1] = vix, viy
                continue
            n_obstacle_lines = 0
            if obstacles is not None and n_vertices > 0:
                # RVO2 computeNeighbors: the edges within the distance the agent covers in time_horizon_obst. The
                # tree query returns only edges closer than that: when a plain scan of the edges finds none (most
                # agents, most steps), it would return nothing, so it is skipped.
                px, py = positions[e, i, 0], positions[e, i, 1]
                obstacle_range = time_horizon_obst * max_speeds[e, i] + radii[e, i]
                range_sq = obstacle_range * obstacle_range
                n_obstacles = 0
                if _any_edge_within(px, py, range_sq, env_point, env_next, n_vertices):
                    n_obstacles = obstacle_neighbors(
                        px, py, range_sq, env_point, env_next, env_tree_vertex, env_tree_left, env_tree_right,
                        n_vertices, tree_stack, obstacle_vertex, obstacle_dist_sq,
                    )  # fmt: skip
                if n_obstacles > 0:
                    n_obstacle_lines = obstacle_orca_lines(
                        px, py, vix, viy, radii[e, i], inv_time_horizon_obst, env_point, env_unit_dir,
                        env_is_convex, env_next, env_prev, obstacle_vertex, n_obstacles, points, directions,
                    )  # fmt: skip
            n_agent_lines = nearest_neighbors(
                positions, active, sees, e, i, neighbor_dist, max_neighbors, neighbor_index, neighbor_dist_sq
            )
            # One ORCA half-plane per neighbour, nearest first (the LPs are order-sensitive when infeasible).
            for k in range(n_agent_lines):
                j = neighbor_index[k]
                dx, dy, ux, uy = orca_line(
                    positions[e, j, 0] - positions[e, i, 0], positions[e, j, 1] - positions[e, i, 1],
                    vix - velocities[e, j, 0], viy - velocities[e, j, 1],
                    radii[e, i] + radii[e, j] + radius_pad[e, i, j], inv_time_horizon, inv_time_step,
                    1.0 if j < i else -1.0,
                )  # fmt: skip
                share = avoidance_share[e, i, j]  # agent i takes `share` of the correction u (RVO2: 0.5)
                line = n_obstacle_lines + k
                points[line, 0], points[line, 1] = vix + share * ux, viy + share * uy
                directions[line, 0], directions[line, 1] = dx, dy
            n_lines = n_obstacle_lines + n_agent_lines
            # Closest velocity to the preferred one that satisfies every half-plane; if none does, the least bad one
            # for the agent lines (linearProgram3 keeps the obstacle lines hard).
            max_speed = max_speeds[e, i]
            fail, vx, vy = linear_program2(points, directions, n_lines, max_speed, preferred_velocities[e, i, 0],
                                           preferred_velocities[e, i, 1], False)
            if fail < n_lines:
                vx, vy = linear_program3(points, directions, n_lines, n_obstacle_lines, fail, max_speed, vx, vy,
                                         proj_points, proj_directions)
                n_fallbacks += 1
            out[e, i, 0], out[e, i, 1] = _within_speed(vx, vy, max_speed)
    return n_fallbacks


@numba.njit(cache=True)
def orca_velocities_kernel(
    positions,
    velocities,
    radii,
    preferred_velocities,
    max_speeds,
    active,
    compute,
    radius_pad,
    avoidance_share,
    sees,
    time_horizon,
    neighbor_dist,
    max_neighbors,
    time_step,
    out,
):
    """Write every agent's new ORCA velocity into `out` (E, N, 2), without obstacles; see `orca_velocities` for the
    arguments. Returns how many agents needed the 3-D fallback (linearProgram3) because their 2-D LP was infeasible.
    """
    return _orca_kernel(
        positions, velocities, radii, preferred_velocities, max_speeds, active, compute, radius_pad, avoidance_share,
        sees, time_horizon, neighbor_dist, max_neighbors, time_step, None, 1.0, out,
    )  # fmt: skip


@numba.njit(cache=True)
def orca_velocities_obstacles_kernel(
    positions,
    velocities,
    radii,
    preferred_velocities,
    max_speeds,
    active,
    compute,
    radius_pad,
    avoidance_share,
    sees,
    time_horizon,
    neighbor_dist,
    max_neighbors,
    time_step,
    obstacle_point,
    obstacle_unit_dir,
    obstacle_is_convex,
    obstacle_next,
    obstacle_prev,
    obstacle_tree_vertex,
    obstacle_tree_left,
    obstacle_tree_right,
    obstacle_count,
    time_horizon_obst,
    out,
):
    """`orca_velocities_kernel` with static obstacles: the obstacle arrays are `ObstacleBatch.kernel_arrays()`, in
    order; returns the fallback count.

    As RVO2's computeNewVelocity: the obstacle half-planes first (agent i's obstacle neighbours within
    time_horizon_obst * max_speed + radius), then the agent ones; linearProgram3 never relaxes the obstacle lines.
    An env without obstacles (count 0) gives bit for bit what `orca_velocities_kernel` gives.
    """
    obstacles = (
        obstacle_point, obstacle_unit_dir, obstacle_is_convex, obstacle_next, obstacle_prev, obstacle_tree_vertex,
        obstacle_tree_left, obstacle_tree_right, obstacle_count,
    )  # fmt: skip
    return _orca_kernel(
        positions, velocities, radii, preferred_velocities, max_speeds, active, compute, radius_pad, avoidance_share,
        sees, time_horizon, neighbor_dist, max_neighbors, time_step, obstacles, time_horizon_obst, out,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------------------------------
# Python API.
# --------------------------------------------------------------------------------------------------------------------
def _check_array(name: str, array: np.ndarray, shape: tuple[int, ...], dtype: type) -> None:
    if not isinstance(array, np.ndarray):
        raise TypeError(f"{name} must be a numpy array, got {type(array).__name__}")
    if array.dtype != dtype:
        raise TypeError(f"{name} must have dtype {np.dtype(dtype)}, got {array.dtype}")
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")


def orca_velocities(
    positions: np.ndarray,
    velocities: np.ndarray,
    radii: np.ndarray,
    preferred_velocities: np.ndarray,
    max_speeds: np.ndarray,
    active: np.ndarray,
    compute: np.ndarray,
    radius_pad: np.ndarray,
    avoidance_share: np.ndarray,
    sees: np.ndarray,
    time_horizon: float,
    neighbor_dist: float,
    max_neighbors: int,
    time_step: float,
    *,
    obstacles: ObstacleBatch | None = None,
    time_horizon_obst: float | None = None,
) -> np.ndarray:
    """New ORCA velocities of E environments of N agent slots each (RVO2 semantics).

    positions, velocities, preferred_velocities: (E, N, 2) float64; radii, max_speeds: (E, N) float64;
    active (slot holds a real agent), compute (compute a new velocity): (E, N) bool;
    radius_pad (extra radius i adds to j), avoidance_share (share of the avoidance i takes w.r.t. j; 0.5 = RVO2):
    (E, N, N) float64; sees (i considers j): (E, N, N) bool.
    obstacles: static obstacles of each env (`ObstacleBatch.from_maps`, E maps), avoided as RVO2 does with the agent's
    own radius (no pad), hard constraints; time_horizon_obst (> 0, required with obstacles, unused without):
    RVO2's timeHorizonObst. Without obstacles the result is bit-identical to the obstacle-free kernel.
    Returns (E, N, 2) float64; agents that are inactive or not computed keep their current velocity.
    """
    if not isinstance(positions, np.ndarray) or positions.ndim != 3:
        raise ValueError("positions must be an (E, N, 2) array")
    n_envs, n_agents = positions.shape[0], positions.shape[1]
    vectors, per_agent, per_pair = (n_envs, n_agents, 2), (n_envs, n_agents), (n_envs, n_agents, n_agents)
    _check_array("positions", positions, vectors, np.float64)
    _check_array("velocities", velocities, vectors, np.float64)
    _check_array("radii", radii, per_agent, np.float64)
    _check_array("preferred_velocities", preferred_velocities, vectors, np.float64)
    _check_array("max_speeds", max_speeds, per_agent, np.float64)
    _check_array("active", active, per_agent, np.bool_)
    _check_array("compute", compute, per_agent, np.bool_)
    _check_array("radius_pad", radius_pad, per_pair, np.float64)
    _check_array("avoidance_share", avoidance_share, per_pair, np.float64)
    _check_array("sees", sees, per_pair, np.bool_)
    if not time_horizon > 0.0:
        raise ValueError(f"time_horizon must be > 0, got {time_horizon}")
    if not time_step > 0.0:
        raise ValueError(f"time_step must be > 0, got {time_step}")
    if not neighbor_dist >= 0.0:
        raise ValueError(f"neighbor_dist must be >= 0, got {neighbor_dist}")
    if int(max_neighbors) != max_neighbors or max_neighbors < 0:
        raise ValueError(f"max_neighbors must be an integer >= 0, got {max_neighbors}")

    if time_horizon_obst is not None and not time_horizon_obst > 0.0:
        raise ValueError(f"time_horizon_obst must be > 0, got {time_horizon_obst}")

    out = np.empty(vectors, dtype=np.float64)
    if obstacles is None:
        orca_velocities_kernel(
            positions, velocities, radii, preferred_velocities, max_speeds, active, compute, radius_pad,
            avoidance_share, sees, float(time_horizon), float(neighbor_dist), int(max_neighbors), float(time_step), out,
        )  # fmt: skip
        return out
    if not isinstance(obstacles, ObstacleBatch):
        raise TypeError(f"obstacles must be an ObstacleBatch (ObstacleBatch.from_maps), got {type(obstacles).__name__}")
    if obstacles.n_envs != n_envs:
        raise ValueError(f"obstacles must hold one map per env: {n_envs} envs, got {obstacles.n_envs} maps")
    if time_horizon_obst is None:
        raise ValueError("time_horizon_obst must be given (> 0) with obstacles")
    orca_velocities_obstacles_kernel(
        positions, velocities, radii, preferred_velocities, max_speeds, active, compute, radius_pad, avoidance_share,
        sees, float(time_horizon), float(neighbor_dist), int(max_neighbors), float(time_step),
        *obstacles.kernel_arrays(), float(time_horizon_obst), out,
    )  # fmt: skip
    return out


def default_social_arrays(n_envs: int, n_agents: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairwise arrays that make `orca_velocities` plain RVO2.

    Returns (radius_pad zeros, avoidance_share 0.5, sees all True), each (n_envs, n_agents, n_agents).
    """
    shape = (n_envs, n_agents, n_agents)
    return np.zeros(shape), np.full(shape, 0.5), np.ones(shape, dtype=np.bool_)
