"""Social force humans: the extended social force model (Helbing & Molnár 1995; Moussaïd et al. 2009) as PySocialForce
1.1.2 implements it, walls included, groups left out, one numba kernel over every human of every environment.

Walls push as PySocialForce's `ObstacleForce` pushes: from points sampled along each wall segment exactly as its
`EnvState` samples its line obstacles (int(length x resolution) points, `np.linspace` from end to end), not from the
closest point of each segment. The force is a sum over those points, so its size grows with the resolution and a
closest-point force would differ from PySocialForce's by far more than the point spacing; sampling the same points
keeps the oracle agreement exact. Segments are the walls' polygon edges, unsplit (`Crowd.wall_segments`), each
sampled on its own as PySocialForce samples each line (a corner is sampled once per edge that meets there).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from socnav.sim.humans.base import Crowd, HumanSettings

#: The parameters of `SocialForceHumans`, in the kernel's order; `socnav.config.SocialForceConfig` validates them
#: and holds their defaults, PySocialForce's published ones (its default.toml and `PedState.step`).
PARAMETERS = (
    "relaxation_time", "goal_threshold", "desired_force_factor", "social_force_factor", "lambda_importance",
    "gamma", "n", "n_prime", "wrap_theta", "max_speed_multiplier", "stop_distance", "field_of_view", "fov_phi",
    "fov_factor", "obstacle_force_factor", "obstacle_sigma", "obstacle_threshold", "obstacle_resolution",
)

# Wall points are skipped unevaluated only when this much beyond the cut-off (a whole segment by its closest point,
# the rest of a segment by where the cut-off circle crosses it): rounding (~1e-15 m) can then never skip a point
# that PySocialForce counts.
_SKIP_MARGIN = 1e-9


@numba.njit(cache=True)
def _sign(x):
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@numba.njit(cache=True)
def _segment_distance(px, py, ax, ay, bx, by):
    """Distance from p to the closest point of the segment [a, b] (a point when a = b)."""
    dx, dy = bx - ax, by - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else min(1.0, max(0.0, ((px - ax) * dx + (py - ay) * dy) / length2))
    cx, cy = px - (ax + t * dx), py - (ay + t * dy)
    return math.sqrt(cx * cx + cy * cy)


@numba.njit(cache=True)
def _wall_push(px, py, radius, seg_start, seg_end, n_segments, env, sigma, cutoff, resolution):
    """PySocialForce's ObstacleForce on an agent at p of radius r, before its factor: (fx, fy, any point in range).

    Each segment [a, b] is sampled as PySocialForce's EnvState samples a line: m = int(|a - b| resolution) points
    q_k = k (b - a) / (m - 1) + a (numpy's linspace: q_{m-1} = b exactly; m = 1: a alone; m = 0: none). Every point
    with d_k = |p - q_k| - r < cutoff = threshold + r pushes along u_k = (p - q_k) / |p - q_k| (0 when p = q_k):
        F = sum_k exp(-d_k / sigma) u_k.
    """
    fx, fy, near = 0.0, 0.0, False
    reach = cutoff + radius + _SKIP_MARGIN  # |p - q| below which a point may count
    for s in range(n_segments[env]):
        ax, ay = seg_start[env, s, 0], seg_start[env, s, 1]
        bx, by = seg_end[env, s, 0], seg_end[env, s, 1]
        if _segment_distance(px, py, ax, ay, bx, by) >= reach:
            continue
        lx, ly = ax - bx, ay - by
        samples = int(math.sqrt(lx * lx + ly * ly) * resolution)
        step_x = (bx - ax) / (samples - 1) if samples > 1 else 0.0
        step_y = (by - ay) / (samples - 1) if samples > 1 else 0.0
        first, last = 0, samples - 1
        if samples > 2:
            # Only points at t = k / (m - 1) inside the circle |p - q(t)| < reach, q(t) = a + t (b - a), can count:
            # t in tc -+ h, tc the foot of p, h the half chord; one point more each side covers any rounding.
            dx, dy = bx - ax, by - ay
            length2 = dx * dx + dy * dy
            foot = ((px - ax) * dx + (py - ay) * dy) / length2
            off_x, off_y = px - (ax + foot * dx), py - (ay + foot * dy)
            half_chord = math.sqrt(max(0.0, reach * reach - off_x * off_x - off_y * off_y) / length2)
            first = max(0, math.floor((foot - half_chord) * (samples - 1)) - 1)
            last = min(samples - 1, math.ceil((foot + half_chord) * (samples - 1)) + 1)
        for k in range(first, last + 1):
            if k == samples - 1 and samples > 1:
                qx, qy = bx, by
            else:
                qx, qy = k * step_x + ax, k * step_y + ay
            dx, dy = px - qx, py - qy
            distance = math.sqrt(dx * dx + dy * dy)
            clearance = distance - radius
            if not clearance < cutoff:
                continue
            near = True
            if distance == 0.0:
                continue  # PySocialForce's normalize: a zero vector stays zero
            weight = math.exp(-clearance / sigma)
            fx += dx / distance * weight
            fy += dy / distance * weight
    return fx, fy, near


@numba.njit(cache=True, inline="always")
def _pair_force(dx, dy, relative_vx, relative_vy, pad, lambda_importance, gamma, n, n_prime, wrap_theta):
    """The social force of agent j on agent i (Moussaïd et al. 2009) from d = p_i - p_j and v_j - v_i, written
    with u = d / |d|:

        D = lambda (v_j - v_i) + u,   t = D / |D|,   B = gamma |D|,   theta = angle(t) - angle(u),
        f_ij = exp(-d/B - (n' B theta)^2) t - sign(theta) exp(-d/B - (n B theta)^2) normal_left(t).

    (The paper's D_ij = lambda (v_i - v_j) + e_ij is -D here, and f_ij = -exp(-d/B) [...] there.) Personal space:
    j seems nearer by i's `pad` (0 between humans), never nearer than touching. Returns (exerted, f_x, f_y); B = 0
    exerts none (exp(-d / 0) = 0; PySocialForce: 0, or NaN for coincident agents).
    """
    distance = math.sqrt(dx * dx + dy * dy)
    ux, uy = (dx / distance, dy / distance) if distance > 0.0 else (0.0, 0.0)
    distance = max(distance - pad, 0.0)

    Dx = lambda_importance * relative_vx + ux
    Dy = lambda_importance * relative_vy + uy
    D_length = math.sqrt(Dx * Dx + Dy * Dy)
    B = gamma * D_length
    if B == 0.0:
        return False, 0.0, 0.0
    tx, ty = Dx / D_length, Dy / D_length
    theta = math.atan2(ty, tx) - math.atan2(uy, ux)  # in (-2 pi, 2 pi): PySocialForce does not wrap
    if wrap_theta:
        # Moussaïd et al.'s angle between t and u, in [-pi, pi): without it a pair whose t and u straddle the -x
        # direction gets |theta| near 2 pi, and its force all but vanishes.
        theta = (theta + math.pi) % (2.0 * math.pi) - math.pi

    along = math.exp(-distance / B - (n_prime * B * theta) ** 2)  # velocity term, along t
    across = -_sign(theta) * math.exp(-distance / B - (n * B * theta) ** 2)  # angle term, along normal
    return True, along * tx - across * ty, along * ty + across * tx  # normal_left(t) = (-t_y, t_x)


@numba.njit(cache=True)
def social_force_velocities_kernel(
    positions, velocities, goals, radii, max_speeds, active, compute, radius_pad, sees,  # the `Crowd`
    seg_start, seg_end, n_segments,  # its walls (`Crowd.wall_segments`; no segments without walls)
    time_step, relaxation_time, goal_threshold, desired_force_factor, social_force_factor, lambda_importance,
    gamma, n, n_prime, wrap_theta, max_speed_multiplier, stop_distance, field_of_view, cos_fov_phi, fov_factor,
    obstacle_force_factor, obstacle_sigma, obstacle_threshold, obstacle_resolution,
    out,
):
    """Write every computed agent's new velocity into `out` (E, N, 2); the others keep their current velocity.

    Per agent i: the desired force, the social force of every agent j it sees and the walls' force, then
    PySocialForce's velocity step. PySocialForce's sign convention is kept (vectors point from j to i) so that its
    unwrapped angle difference theta, and with it every force, comes out the same (`wrap_theta` wraps it to
    [-pi, pi) instead).
    """
    n_envs, n_agents = active.shape
    for env in range(n_envs):
        for i in range(n_agents):
            vx, vy = velocities[env, i, 0], velocities[env, i, 1]
            if not (active[env, i] and compute[env, i]):
                out[env, i, 0], out[env, i, 1] = vx, vy
                continue
            # PySocialForce: max speed = max_speed_multiplier * initial speed; v_pref plays the initial speed.
            max_speed = max_speed_multiplier * max_speeds[env, i]

            # Desired direction e_i = (g_i - p_i) / |g_i - p_i| (zero on the goal).
            gx = goals[env, i, 0] - positions[env, i, 0]
            gy = goals[env, i, 1] - positions[env, i, 1]
            goal_distance = math.sqrt(gx * gx + gy * gy)
            ex, ey = (gx / goal_distance, gy / goal_distance) if goal_distance > 0.0 else (0.0, 0.0)

            # Desired force, relaxation to the desired velocity within tau (PySocialForce walks at its max speed):
            #   F0_i = (v_max e_i - v_i) / tau,   or F0_i = -v_i / tau (brake) within goal_threshold of the goal.
            if goal_distance > goal_threshold:
                fx, fy = (max_speed * ex - vx) / relaxation_time, (max_speed * ey - vy) / relaxation_time
            else:
                fx, fy = -vx / relaxation_time, -vy / relaxation_time
            fx, fy = desired_force_factor * fx, desired_force_factor * fy

            # Social force of every seen agent j (`_pair_force`), weighted by i's field of view.
            sx, sy = 0.0, 0.0
            for j in range(n_agents):
                if j == i or not active[env, j] or not sees[env, i, j]:
                    continue  # an unseen agent (e.g. the robot of an inattentive human) exerts no force
                exerted, pair_x, pair_y = _pair_force(
                    positions[env, i, 0] - positions[env, j, 0], positions[env, i, 1] - positions[env, j, 1],
                    velocities[env, j, 0] - vx, velocities[env, j, 1] - vy, radius_pad[env, i, j], lambda_importance,
                    gamma, n, n_prime, wrap_theta,
                )  # fmt: skip
                if not exerted:
                    continue
                # Field of view (PySocialForce's FieldOfView, Helbing & Molnár's w): full weight if the force comes
                # from inside the cone of half-angle phi around e_i, e_i . (-f) > |f| cos(phi), else the factor C.
                weight = 1.0
                if field_of_view and not (-(ex * pair_x + ey * pair_y)
                                          > math.sqrt(pair_x * pair_x + pair_y * pair_y) * cos_fov_phi):
                    weight = fov_factor
                sx += weight * pair_x
                sy += weight * pair_y
            fx += social_force_factor * sx
            fy += social_force_factor * sy

            # Walls (PySocialForce's ObstacleForce, `_wall_push`), the human's body radius as its agent_radius.
            radius = radii[env, i]
            push_x, push_y, near_wall = _wall_push(
                positions[env, i, 0], positions[env, i, 1], radius, seg_start, seg_end, n_segments, env,
                obstacle_sigma, obstacle_threshold + radius, obstacle_resolution,
            )
            if near_wall:
                fx += obstacle_force_factor * push_x
                fy += obstacle_force_factor * push_y

            # Velocity step (PySocialForce's PedState.step): v <- v + dt F, capped at the max speed,
            #   v <- v min(1, v_max / |v|)  (0 if |v| = 0),  and v <- 0 within stop_distance of the goal.
            # The world then moves the human by p <- p + v dt (semi-implicit Euler, as PySocialForce).
            wx, wy = vx + time_step * fx, vy + time_step * fy
            speed = math.sqrt(wx * wx + wy * wy)
            scale = min(1.0, max_speed / speed) if speed > 0.0 else 0.0
            if goal_distance < stop_distance:
                scale = 0.0
            out[env, i, 0], out[env, i, 1] = wx * scale, wy * scale


class SocialForceHumans:
    """`HumanModel` "social_force": the `Crowd`'s inputs as the social force can use them.

    Attention: an agent a human does not see (``sees``; the robot while the human is inattentive or has not
    noticed it) exerts no force on it. Personal space: ``radius_pad`` shortens the distance d in the robot's force
    (never below 0), so a human with a larger personal space is pushed harder and from farther away. The social
    force acts between centres, so body radii play no part in it (as in PySocialForce), and it has no reciprocal
    avoidance to share: ``avoidance_share`` (cooperation) is unused. The robot is one more agent, moved by the
    policy, not by this model. With ``field_of_view``, forces from outside the human's view cone are weighted by
    ``fov_factor`` (PySocialForce applies this weighting to its older pedestrian repulsion only, which its simulator
    leaves out; off by default, as there). The interaction angle theta is left unwrapped, as PySocialForce leaves
    it, unless ``wrap_theta``. Walls (``wall_segments``) push with PySocialForce's obstacle force, each human's body
    radius playing its ``agent_radius``.
    """

    name = "social_force"
    #: The force fades as exp(-d / B) and has no cut-off: a noticed robot is reacted to at any distance.
    interaction_range = math.inf

    def __init__(self, time_step: float, *, relaxation_time: float, goal_threshold: float,
                 desired_force_factor: float, social_force_factor: float, lambda_importance: float, gamma: float,
                 n: float, n_prime: float, wrap_theta: bool, max_speed_multiplier: float, stop_distance: float,
                 field_of_view: bool, fov_phi: float, fov_factor: float, obstacle_force_factor: float,
                 obstacle_sigma: float, obstacle_threshold: float, obstacle_resolution: float):
        self.time_step = float(time_step)
        self.parameters = {
            "relaxation_time": float(relaxation_time), "goal_threshold": float(goal_threshold),
            "desired_force_factor": float(desired_force_factor), "social_force_factor": float(social_force_factor),
            "lambda_importance": float(lambda_importance), "gamma": float(gamma), "n": float(n),
            "n_prime": float(n_prime), "wrap_theta": bool(wrap_theta),
            "max_speed_multiplier": float(max_speed_multiplier), "stop_distance": float(stop_distance),
            "field_of_view": bool(field_of_view), "fov_phi": float(fov_phi), "fov_factor": float(fov_factor),
            "obstacle_force_factor": float(obstacle_force_factor), "obstacle_sigma": float(obstacle_sigma),
            "obstacle_threshold": float(obstacle_threshold), "obstacle_resolution": float(obstacle_resolution),
        }
        self.arrival_distance = self.parameters["stop_distance"]
        # The kernel's scalar arguments in `PARAMETERS` order, the view cone's half-angle as its cosine.
        self._arguments = tuple(math.cos(math.radians(self.parameters[name])) if name == "fov_phi"
                                else self.parameters[name] for name in PARAMETERS)

    @classmethod
    def from_config(cls, config: HumanSettings) -> SocialForceHumans:
        section = config.humans.social_force
        return cls(config.time_step, **{name: getattr(section, name) for name in PARAMETERS})

    def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
        out = np.empty_like(crowd.velocities)
        if crowd.wall_segments is None:
            n_envs = len(crowd.positions)
            walls = (np.zeros((n_envs, 0, 2)), np.zeros((n_envs, 0, 2)), np.zeros(n_envs, dtype=np.int64))
        else:
            walls = crowd.wall_segments
            seg_start, seg_end, n_segments = walls
            # numba does not check bounds: a mismatch would read past the arrays
            if (seg_start.shape != seg_end.shape or seg_start.shape[0] != len(crowd.positions)
                    or n_segments.shape != (len(crowd.positions),) or np.any(n_segments > seg_start.shape[1])):
                raise ValueError(f"Crowd.wall_segments: expected (seg_start (E, S, 2), seg_end (E, S, 2), "
                                 f"n_segments (E,) <= S) for E = {len(crowd.positions)}, got shapes "
                                 f"{seg_start.shape}, {seg_end.shape}, {n_segments.shape}")
        social_force_velocities_kernel(
            crowd.positions, crowd.velocities, crowd.goals, crowd.radii, crowd.max_speeds, crowd.active, compute,
            crowd.radius_pad, crowd.sees, *walls, self.time_step, *self._arguments, out,
        )
        return out
