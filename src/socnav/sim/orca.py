"""ORCA reciprocal collision avoidance: an exact float64 port of RVO2's agent-agent ORCA, compiled with numba.

One kernel call updates all agents of all envs; per pair (i, j) it adds a radius pad, an avoidance share and visibility.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "RVO_EPSILON",
    "default_social_arrays",
    "linear_program1",
    "linear_program2",
    "linear_program3",
    "nearest_neighbors",
    "orca_line",
    "orca_velocities",
    "orca_velocities_kernel",
]

# RVO2 treats two lines as parallel when |det(d_a, d_b)| <= RVO_EPSILON.
RVO_EPSILON = 1e-5


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
def linear_program3(points, directions, n_lines, begin_line, radius, rx, ry, proj_points, proj_directions):
    """RVO2 linearProgram3 (no obstacle lines): when the 2-D LP is infeasible, minimise the largest violation.

    Lines from `begin_line` on are handled one at a time: if line i is violated by more than the current worst
    distance, solve a 2-D LP in the space of lines 0..i-1 projected onto line i (the bisectors where violating them
    equals violating line i), optimising towards the inside of line i. Returns the new (x, y).
    """
    distance = 0.0
    for i in range(begin_line, n_lines):
        dix, diy = directions[i, 0], directions[i, 1]
        pix, piy = points[i, 0], points[i, 1]
        if _det(dix, diy, pix - rx, piy - ry) > distance:
            n_proj = 0
            for j in range(i):
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
# The batched kernel.
# --------------------------------------------------------------------------------------------------------------------
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
    """Write every agent's new ORCA velocity into `out` (E, N, 2); see `orca_velocities` for the arguments.

    Returns how many agents needed the 3-D fallback (linearProgram3) because their 2-D LP was infeasible.
    """
    n_envs, n_agents = positions.shape[0], positions.shape[1]
    # Scratch buffers, reused for every agent: at most N - 1 neighbours, hence at most N - 1 ORCA lines.
    capacity = max(0, min(max_neighbors, n_agents - 1))
    neighbor_index = np.empty(capacity, dtype=np.int64)
    neighbor_dist_sq = np.empty(capacity, dtype=np.float64)
    points = np.empty((capacity, 2), dtype=np.float64)
    directions = np.empty((capacity, 2), dtype=np.float64)
    proj_points = np.empty((capacity, 2), dtype=np.float64)
    proj_directions = np.empty((capacity, 2), dtype=np.float64)
    inv_time_horizon = 1.0 / time_horizon
    inv_time_step = 1.0 / time_step
    n_fallbacks = 0

    for e in range(n_envs):
        for i in range(n_agents):
            vix, viy = velocities[e, i, 0], velocities[e, i, 1]
            if not (active[e, i] and compute[e, i]):
                out[e, i, 0], out[e, i, 1] = vix, viy
                continue

            n_lines = nearest_neighbors(
                positions, active, sees, e, i, neighbor_dist, max_neighbors, neighbor_index, neighbor_dist_sq
            )

            # One ORCA half-plane per neighbour, nearest first (the LPs are order-sensitive when infeasible).
            for k in range(n_lines):
                j = neighbor_index[k]
                combined_radius = radii[e, i] + radii[e, j] + radius_pad[e, i, j]
                tie_sign = 1.0 if j < i else -1.0
                dx, dy, ux, uy = orca_line(
                    positions[e, j, 0] - positions[e, i, 0],
                    positions[e, j, 1] - positions[e, i, 1],
                    vix - velocities[e, j, 0],
                    viy - velocities[e, j, 1],
                    combined_radius,
                    inv_time_horizon,
                    inv_time_step,
                    tie_sign,
                )
                # Agent i takes `share` of the correction u (RVO2: 0.5, each agent does half).
                share = avoidance_share[e, i, j]
                points[k, 0], points[k, 1] = vix + share * ux, viy + share * uy
                directions[k, 0], directions[k, 1] = dx, dy

            # Closest velocity to the preferred one that satisfies every half-plane; if none does, the least bad one.
            max_speed = max_speeds[e, i]
            pref_x, pref_y = preferred_velocities[e, i, 0], preferred_velocities[e, i, 1]
            fail, vx, vy = linear_program2(points, directions, n_lines, max_speed, pref_x, pref_y, False)
            if fail < n_lines:
                vx, vy = linear_program3(
                    points, directions, n_lines, fail, max_speed, vx, vy, proj_points, proj_directions
                )
                n_fallbacks += 1

            # The LPs stay inside the speed disc by construction, but far-away projected lines (nearly anti-parallel
            # constraints in linearProgram3) can push the result out by rounding; project it back.
            speed_sq = vx * vx + vy * vy
            if speed_sq > max_speed * max_speed:
                scale = max_speed / np.sqrt(speed_sq)
                vx, vy = vx * scale, vy * scale
            out[e, i, 0], out[e, i, 1] = vx, vy
    return n_fallbacks


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
) -> np.ndarray:
    """New ORCA velocities of E environments of N agent slots each (RVO2 semantics, no obstacles).

    positions, velocities, preferred_velocities: (E, N, 2) float64; radii, max_speeds: (E, N) float64;
    active (slot holds a real agent), compute (compute a new velocity): (E, N) bool;
    radius_pad (extra radius i adds to j), avoidance_share (share of the avoidance i takes w.r.t. j; 0.5 = RVO2):
    (E, N, N) float64; sees (i considers j): (E, N, N) bool.
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

    out = np.empty(vectors, dtype=np.float64)
    orca_velocities_kernel(
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
        float(time_horizon),
        float(neighbor_dist),
        int(max_neighbors),
        float(time_step),
        out,
    )
    return out


def default_social_arrays(n_envs: int, n_agents: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairwise arrays that make `orca_velocities` plain RVO2.

    Returns (radius_pad zeros, avoidance_share 0.5, sees all True), each (n_envs, n_agents, n_agents).
    """
    shape = (n_envs, n_agents, n_agents)
    return np.zeros(shape), np.full(shape, 0.5), np.ones(shape, dtype=np.bool_)
