"""The compiled kernels of one step of `socnav.sim.world.CrowdWorld`, each looping over every environment: the
robot's unicycle command and motion, the episode's outcome, the socially integrated reward (docs/world.md), the
observation (and its noise) and the humans' attention. The kernels that call one another are in this one file: numba
invalidates a cached kernel only when its own file changes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from socnav.sim.config import RewardConfig
from socnav.sim.noise import (
    ATTENTION_STREAM,
    HEADING_STREAM,
    OBSERVATION_STREAM,
    SPEED_STREAM,
    standard_normal,
    uniform01,
)

ROBOT_FEATURES = 5  # distance to goal, heading relative to goal direction, speed, v_pref, radius


HUMAN_FEATURES = 7  # rel. position (2), rel. velocity (2), radius, combined radius, gap


OUTCOME_RUNNING, OUTCOME_GOAL, OUTCOME_COLLISION, OUTCOME_TIMEOUT, OUTCOME_COLLISION_WALL = 0, 1, 2, 3, 4


OUTCOME_NAMES = {OUTCOME_GOAL: "goal", OUTCOME_COLLISION: "collision", OUTCOME_TIMEOUT: "timeout",
                 OUTCOME_COLLISION_WALL: "collision_wall"}


@numba.njit(cache=True)
def _wrap_angle(angle):
    """Wrap to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@numba.njit(cache=True)
def robot_command_batch(actions, preferred_speed, max_heading_change, keys, steps, heading_noise, speed_noise):
    """Map [-1, 1]^2 actions to the robot's (v, dtheta) (paper Sec. III-A), then apply action noise (Sec. V-A).

    v = v_pref (a0 + 1) / 2, dtheta = dtheta_max a1 (clipped); heading noise dtheta + N(0, s^2); speed v U(1 - s, 1).
    """
    n_envs = actions.shape[0]
    speed = np.empty(n_envs)
    turn = np.empty(n_envs)
    for env in range(n_envs):
        a_speed = min(max(actions[env, 0], -1.0), 1.0)
        a_turn = min(max(actions[env, 1], -1.0), 1.0)
        speed[env] = preferred_speed[env] * (a_speed + 1.0) / 2.0
        turn[env] = max_heading_change * a_turn
        if heading_noise > 0.0:
            turn[env] += heading_noise * standard_normal(keys[env], HEADING_STREAM, steps[env], 0)
        if speed_noise > 0.0:
            speed[env] *= 1.0 - speed_noise * uniform01(keys[env], SPEED_STREAM, steps[env], 0)
    return speed, turn


@numba.njit(cache=True)
def _closest_approach(rel_x, rel_y, rel_vx, rel_vy, time_step):
    """Smallest centre distance while two agents move linearly over one step (catches pass-throughs at high speed)."""
    speed_sq = rel_vx * rel_vx + rel_vy * rel_vy
    s = 0.0
    if speed_sq > 1e-12:
        s = min(max(-(rel_x * rel_vx + rel_y * rel_vy) / (speed_sq * time_step), 0.0), 1.0)
    x = rel_x + s * rel_vx * time_step
    y = rel_y + s * rel_vy * time_step
    return math.sqrt(x * x + y * y)


@numba.njit(cache=True)
def _integrate(positions, velocities, radii, goals, active, heading, speed, turn, human_velocities, path_length, time,
               time_step):
    """Move every agent one step and sweep the robot's path against every human's (docs/world.md, "Observation and
    action").

    Robot (unicycle): theta <- wrap(theta + dtheta), p <- p + v [cos theta, sin theta] dt; humans (holonomic) take
    the human model's velocity, p <- p + v dt. Updates positions, velocities, heading, path length and time in place.
    Returns per environment the smallest robot-human gap at any moment of the step (the swept closest approach, so a
    human that passes through the robot between two steps still collides) and the progress d_goal(t-1) - d_goal(t).
    """
    n_envs, n_agents = active.shape
    closest_gap = np.full(n_envs, np.inf)
    progress = np.empty(n_envs)
    for env in range(n_envs):
        old_x, old_y = positions[env, 0, 0], positions[env, 0, 1]
        old_goal_distance = math.hypot(goals[env, 0, 0] - old_x, goals[env, 0, 1] - old_y)

        heading[env] = _wrap_angle(heading[env] + turn[env])
        robot_vx = speed[env] * math.cos(heading[env])
        robot_vy = speed[env] * math.sin(heading[env])
        for agent in range(1, n_agents):
            if not active[env, agent]:
                continue
            hvx, hvy = human_velocities[env, agent, 0], human_velocities[env, agent, 1]
            approach = _closest_approach(
                positions[env, agent, 0] - old_x, positions[env, agent, 1] - old_y,
                hvx - robot_vx, hvy - robot_vy, time_step,
            )
            closest_gap[env] = min(closest_gap[env], approach - radii[env, 0] - radii[env, agent])
            velocities[env, agent, 0] = hvx
            velocities[env, agent, 1] = hvy
            positions[env, agent, 0] += hvx * time_step
            positions[env, agent, 1] += hvy * time_step
        velocities[env, 0, 0] = robot_vx
        velocities[env, 0, 1] = robot_vy
        positions[env, 0, 0] += robot_vx * time_step
        positions[env, 0, 1] += robot_vy * time_step
        path_length[env] += speed[env] * time_step
        time[env] += time_step
        goal_distance = math.hypot(goals[env, 0, 0] - positions[env, 0, 0], goals[env, 0, 1] - positions[env, 0, 1])
        progress[env] = old_goal_distance - goal_distance
    return closest_gap, progress


@numba.njit(cache=True)
def _outcome(positions, goals, closest_gap, time, time_limit, goal_tolerance):
    """How each episode stands after the move (docs/world.md, "Reward and episode end"), the first that applies:
    collision (swept gap < 0), goal (robot centre within `goal_tolerance` of its goal), time-out (t > time limit),
    else still running."""
    n_envs = closest_gap.shape[0]
    outcome = np.full(n_envs, OUTCOME_RUNNING, dtype=np.int64)
    for env in range(n_envs):
        goal_distance = math.hypot(goals[env, 0, 0] - positions[env, 0, 0], goals[env, 0, 1] - positions[env, 0, 1])
        if closest_gap[env] < 0.0:
            outcome[env] = OUTCOME_COLLISION
        elif goal_distance < goal_tolerance:
            outcome[env] = OUTCOME_GOAL
        elif time[env] > time_limit[env]:
            outcome[env] = OUTCOME_TIMEOUT
    return outcome


def reward_weights(reward: RewardConfig) -> tuple[float, float, float, float, float, float]:
    """The weights `_score` reads, in its order: (goal, collision, time, progress, personal_space, disturbance)."""
    return (reward.goal, reward.collision, reward.time, reward.progress, reward.personal_space, reward.disturbance)


@numba.njit(cache=True)
def _score(
    positions, velocities, radii, max_speeds, personal_space, active,  # the world after the move
    progress, closest_gap, outcome, near_robot, unhindered_velocities,  # what the step did (`_integrate`, `_outcome`)
    weights, time_step,  # `reward_weights(config.reward)`, dt
    was_intruded, episode_return, min_gap, intrusion_steps, intrusion_events, disturbance_total,  # episode, in place
):
    """The socially integrated reward of the step just taken (Flögel et al., IROS 2024, which the paper trains with,
    Sec. III-A; docs/world.md): its one definition.

        r = -w_time dt + w_prog (d_goal(t-1) - d_goal(t))
            - sum_{i: gap_i < r_prox,i} w_prox (1 - gap_i / r_prox,i)            personal space, per intruded human
            - sum_{i near the robot} w_dist |v_i - v_i^0| / v_pref,i             disturbance, v_i^0 robot-free
            + w_goal [goal] - w_col [collision]

    `near_robot`: the humans within `reward.social_radius` at the start of the step, whose robot-free velocity v_i^0
    (`unhindered_velocities`) was computed. Also returns the nearest human's gap and relative speed and the number of
    intruded personal spaces, and updates the episode accumulators in place (`disturbance_total`: the unweighted sum
    of |v_i - v_i^0| / v_pref,i; `min_gap` includes the swept `closest_gap`).
    """
    w_goal, w_collision, w_time, w_progress, w_personal_space, w_disturbance = weights
    n_envs, n_agents = active.shape
    reward = np.zeros(n_envs)
    nearest_gap = np.full(n_envs, np.inf)
    nearest_speed = np.zeros(n_envs)
    intrusions = np.zeros(n_envs, dtype=np.int64)
    for env in range(n_envs):
        robot_vx, robot_vy = velocities[env, 0, 0], velocities[env, 0, 1]
        r = -w_time * time_step + w_progress * progress[env]
        for agent in range(1, n_agents):
            if not active[env, agent]:
                continue
            dx = positions[env, agent, 0] - positions[env, 0, 0]
            dy = positions[env, agent, 1] - positions[env, 0, 1]
            gap = math.sqrt(dx * dx + dy * dy) - radii[env, 0] - radii[env, agent]
            if gap < nearest_gap[env]:
                nearest_gap[env] = gap
                nearest_speed[env] = math.hypot(
                    velocities[env, agent, 0] - robot_vx, velocities[env, agent, 1] - robot_vy
                )
            intruded = gap < personal_space[env, agent]
            if intruded and personal_space[env, agent] > 0.0:
                intrusions[env] += 1
                r -= w_personal_space * (1.0 - max(gap, 0.0) / personal_space[env, agent])
                if not was_intruded[env, agent]:
                    intrusion_events[env] += 1
            was_intruded[env, agent] = intruded
            if near_robot[env, agent] and w_disturbance > 0.0:
                push = math.hypot(
                    velocities[env, agent, 0] - unhindered_velocities[env, agent, 0],
                    velocities[env, agent, 1] - unhindered_velocities[env, agent, 1],
                )
                disturbance_total[env] += push / max_speeds[env, agent]
                r -= w_disturbance * push / max_speeds[env, agent]
        if intrusions[env] > 0:
            intrusion_steps[env] += 1
        min_gap[env] = min(min_gap[env], nearest_gap[env], closest_gap[env])

        if outcome[env] == OUTCOME_COLLISION:
            r -= w_collision
        elif outcome[env] == OUTCOME_GOAL:
            r += w_goal
        reward[env] = r
        episode_return[env] += r
    return reward, nearest_gap, nearest_speed, intrusions


@numba.njit(cache=True)
def advance_and_score(
    positions, velocities, radii, goals, max_speeds, personal_space, active, heading, time, time_limit,  # world
    speed, turn, human_velocities, unhindered_velocities, near_robot,  # this step's robot command, human velocities
    time_step, goal_tolerance, weights,  # dt, goal radius, `reward_weights(config.reward)`
    was_intruded, episode_return, path_length, min_gap, intrusion_steps, intrusion_events, disturbance_total,  # episode
):
    """One step of every environment: `_integrate` (move, sweep), `_outcome` (episode end), `_score` (reward).

    One compiled entry point rather than three calls from Python: each call from Python costs about a microsecond of
    argument checking, which at one environment is several per cent of a step. Returns reward, outcome, nearest
    gap, nearest relative speed and intrusions per environment; the world and the episode totals change in place.
    """
    closest_gap, progress = _integrate(positions, velocities, radii, goals, active, heading, speed, turn,
                                       human_velocities, path_length, time, time_step)
    outcome = _outcome(positions, goals, closest_gap, time, time_limit, goal_tolerance)
    reward, nearest_gap, nearest_speed, intrusions = _score(
        positions, velocities, radii, max_speeds, personal_space, active,
        progress, closest_gap, outcome, near_robot, unhindered_velocities,
        weights, time_step,
        was_intruded, episode_return, min_gap, intrusion_steps, intrusion_events, disturbance_total,
    )
    return reward, outcome, nearest_gap, nearest_speed, intrusions


@numba.njit(cache=True)
def observe_batch(positions, velocities, radii, goals, preferred_speed, active, heading, max_humans):
    """Robot-centric, goal-aligned observation; humans sorted by gap with the closest LAST, zero padding after them.

    robot: [distance to goal, heading relative to the goal direction, speed, v_pref, radius];
    human row: [relative position (2), relative velocity (2), radius, combined radius, gap], in the goal frame.
    """
    n_envs, n_agents = active.shape
    robot = np.zeros((n_envs, ROBOT_FEATURES), dtype=np.float32)
    humans = np.zeros((n_envs, max_humans, HUMAN_FEATURES), dtype=np.float32)
    mask = np.zeros((n_envs, max_humans), dtype=np.float32)
    gaps = np.empty(n_agents)
    rows = np.empty((n_agents, HUMAN_FEATURES))
    for env in range(n_envs):
        px, py = positions[env, 0, 0], positions[env, 0, 1]
        gx, gy = goals[env, 0, 0] - px, goals[env, 0, 1] - py
        goal_angle = math.atan2(gy, gx)
        cos_a, sin_a = math.cos(goal_angle), math.sin(goal_angle)
        rvx, rvy = velocities[env, 0, 0], velocities[env, 0, 1]
        robot_values = (
            math.hypot(gx, gy),
            _wrap_angle(heading[env] - goal_angle),
            math.hypot(rvx, rvy),
            preferred_speed[env],
            radii[env, 0],
        )
        for k in range(ROBOT_FEATURES):
            robot[env, k] = robot_values[k]
        count = 0
        for agent in range(1, n_agents):
            if not active[env, agent]:
                continue
            dx, dy = positions[env, agent, 0] - px, positions[env, agent, 1] - py
            dvx, dvy = velocities[env, agent, 0] - rvx, velocities[env, agent, 1] - rvy
            combined = radii[env, agent] + radii[env, 0]
            rows[count, 0] = cos_a * dx + sin_a * dy
            rows[count, 1] = -sin_a * dx + cos_a * dy
            rows[count, 2] = cos_a * dvx + sin_a * dvy
            rows[count, 3] = -sin_a * dvx + cos_a * dvy
            rows[count, 4] = radii[env, agent]
            rows[count, 5] = combined
            rows[count, 6] = math.sqrt(dx * dx + dy * dy) - combined
            gaps[count] = rows[count, 6]
            count += 1
        order = np.argsort(-gaps[:count], kind="mergesort")  # farthest first: the closest is read last
        for slot in range(min(count, max_humans)):
            source = order[slot + max(count - max_humans, 0)]  # keep the closest rows if there are too many
            for k in range(HUMAN_FEATURES):
                humans[env, slot, k] = rows[source, k]
            mask[env, slot] = 1.0
    return robot, humans, mask


@numba.njit(cache=True)
def draw_attention(key, n_slots, inattentive_share):
    """Per-episode attentiveness of every slot: a human is inattentive with probability `inattentive_share`.

    Counter-based (episode key, ATTENTION_STREAM, step 0, slot): the same episode gets the same humans whatever the
    batch, and no draw of the episode generator is consumed.
    """
    attentive = np.ones(n_slots, dtype=np.bool_)
    for agent in range(1, n_slots):
        attentive[agent] = uniform01(key, ATTENTION_STREAM, 0, agent) >= inattentive_share
    return attentive


@numba.njit(cache=True)
def notice_robot(positions, velocities, goals, active, facing, noticed, cos_half_fov, interaction_range, in_sight):
    """Field of view: update each human's facing direction and whether it has noticed the robot.

    A human faces where it walks (towards its goal while standing still, its last facing once at the goal). It
    notices the robot when the robot's centre is within its interaction range (`interaction_range` (E, N): that of
    the model moving it) and inside the cone of half-angle fov/2 around its facing; once noticed, it keeps reacting
    while the robot stays within the interaction range. A human never notices a robot it has no line of sight to
    (`in_sight` (E, N), a wall in between).
    """
    n_envs, n_agents = active.shape
    for env in range(n_envs):
        for agent in range(1, n_agents):
            if not active[env, agent]:
                continue
            vx, vy = velocities[env, agent, 0], velocities[env, agent, 1]
            if vx * vx + vy * vy > 1e-12:
                facing[env, agent] = math.atan2(vy, vx)
            else:
                gx = goals[env, agent, 0] - positions[env, agent, 0]
                gy = goals[env, agent, 1] - positions[env, agent, 1]
                if gx * gx + gy * gy > 1e-18:
                    facing[env, agent] = math.atan2(gy, gx)
            dx = positions[env, 0, 0] - positions[env, agent, 0]
            dy = positions[env, 0, 1] - positions[env, agent, 1]
            distance = math.sqrt(dx * dx + dy * dy)
            in_range = distance < interaction_range[env, agent]
            in_view = False
            if in_range and in_sight[env, agent]:
                if distance < 1e-12:
                    in_view = True
                else:
                    cos_angle = (dx * math.cos(facing[env, agent]) + dy * math.sin(facing[env, agent])) / distance
                    in_view = cos_angle >= cos_half_fov
            noticed[env, agent] = (noticed[env, agent] and in_range) or in_view


@numba.njit(cache=True)
def humans_within(positions, radii, active, social_radius):
    """Mask of the active humans whose gap to the robot is below `social_radius` (whose disturbance is scored)."""
    n_envs, n_agents = active.shape
    near = np.zeros((n_envs, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        for agent in range(1, n_agents):
            if active[env, agent]:
                dx = positions[env, agent, 0] - positions[env, 0, 0]
                dy = positions[env, agent, 1] - positions[env, 0, 1]
                near[env, agent] = math.sqrt(dx * dx + dy * dy) - radii[env, agent] - radii[env, 0] < social_radius
    return near


@numba.njit(cache=True)
def add_observation_noise(robot, humans, mask, keys, steps, observation_noise):
    """Add N(0, s^2) to every real observation element (sigma_obs, paper Sec. V-A); padding and the mask stay
    exact."""
    n_envs, max_humans, n_features = humans.shape
    for env in range(n_envs):
        element = 0
        for k in range(robot.shape[1]):
            robot[env, k] += observation_noise * standard_normal(keys[env], OBSERVATION_STREAM, steps[env], element)
            element += 1
        for slot in range(max_humans):
            if mask[env, slot] == 0.0:
                break
            for k in range(n_features):
                humans[env, slot, k] += observation_noise * standard_normal(
                    keys[env], OBSERVATION_STREAM, steps[env], element
                )
                element += 1

