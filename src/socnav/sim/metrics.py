"""The navigation metrics the field reports (Francis et al. 2023, SocNavBench, SEAN 2.0, CrowdNav): one registry,
the per-step accumulators the batched world runs, each episode's values, and their aggregation over episodes.

Three levels, each defined once here:

* **per step** (`EpisodeMetrics`, a numba kernel over all environments, hooked into `socnav.sim.world.CrowdWorld`
  with ``CrowdWorld(config, n_envs, metrics=True)``): the robot's velocity, acceleration and jerk, its heading
  against the direction to its goal, the nearest human's gap, personal-space entries and who caused them, the time
  to collision with every human, stalls and progress towards the goal;
* **per episode** (`EpisodeMetrics.summary`, the record columns `METRIC_RECORD_COLUMNS`, added after the world's own
  `episode_summary` columns);
* **over episodes** (`METRICS`, the registry: name, unit, definition, direction, source; `summarize_episodes` and,
  per group of records, `summarize_groups`). A table column named like a record column is its mean over episodes;
  ``*_pct`` columns are shares of episodes in %; ``pv*`` columns are events per `PV_PER` episodes.

Adding a metric: a record column in `EpisodeMetrics.summary` (and, if it needs per-step state, a slot of
`_TOTALS` filled by `_accumulate`), and a `Metric` in `METRICS`. Everything that reports metrics (``socnav
evaluate``, the experiment reports, the safety studies, docs/metrics.md) reads this registry.

Distances to humans are *gaps*, body edge to body edge: ``|p_h - p_r| - r_r - r_h``, as the world's personal space
and its ``min_gap`` are measured. Personal-space entries are the world's intrusion events (the gap falls below the
human's personal-space radius, `socnav.sim.world._score`), split by who caused them.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numba
import numpy as np

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "ALL_METRICS",
    "DEFAULT_METRICS",
    "METRICS",
    "METRIC_RECORD_COLUMNS",
    "PV_PER",
    "EpisodeMetrics",
    "Metric",
    "episode_values",
    "metric_table_rows",
    "select_metrics",
    "summarize_episodes",
    "summarize_groups",
    "time_to_collision",
]

#: Proxemic zones (Hall 1966, as SEAN 2.0 and HuNav use them): a human's gap to the robot below each, in metres.
INTIMATE_ZONE, PERSONAL_ZONE, SOCIAL_ZONE = 0.45, 1.2, 3.6
#: A step is stalled when the robot moves slower than this (m/s): ten times slower than the slowest walker.
STALL_SPEED = 0.05
#: Failure to progress (SEAN 2.0's "stuck" window): no new PROGRESS_DISTANCE metres towards the goal for
#: PROGRESS_WINDOW seconds.
PROGRESS_DISTANCE, PROGRESS_WINDOW = 0.1, 5.0
#: Times to collision are capped at this horizon (s): beyond it there is no conflict at walking speed, and a finite
#: value keeps the mean over episodes finite (no collision course at all also reads as the horizon).
TTC_HORIZON = 10.0
#: Intrusion events are reported per this many episodes (the paper's PV: events per 200 episodes).
PV_PER = 200
#: Obstacle collisions: the world's per-environment ``wall_collision`` flag (set in the step the robot hits an
#: obstacle), or an episode outcome of this name, whichever the obstacle code uses.
OBSTACLE_COLLISION_OUTCOME = "collision_wall"

# ------------------------------------------------------------------------------------------------------------------
# Per step: what the world accumulates in every environment (one row of `EpisodeMetrics.totals` per environment)

_TOTALS = (
    "previous_x", "previous_y",  # the robot's position at the start of the step
    "previous_vx", "previous_vy",  # its velocity in the previous step (0 before the first: it starts at rest)
    "previous_ax", "previous_ay",  # its acceleration in the previous step (0 before the first)
    "speed_sum", "speed_max", "acceleration_sum", "acceleration_max", "jerk_sum", "jerk_max",
    "irregularity_sum",  # sum over steps of |heading - direction to the goal| (rad)
    "intimate_steps", "personal_steps", "social_steps",  # steps with the nearest gap inside each zone
    "intrusions_robot", "intrusions_human",  # personal-space entries caused by the robot / by the human
    "min_ttc",  # smallest time to collision so far (s), at most TTC_HORIZON
    "stalled_time",  # seconds of steps slower than STALL_SPEED
    "best_goal_distance", "last_progress_time", "failed_to_progress",  # failure to progress
)
(PREVIOUS_X, PREVIOUS_Y, PREVIOUS_VX, PREVIOUS_VY, PREVIOUS_AX, PREVIOUS_AY, SPEED_SUM, SPEED_MAX, ACCELERATION_SUM,
 ACCELERATION_MAX, JERK_SUM, JERK_MAX, IRREGULARITY_SUM, INTIMATE_STEPS, PERSONAL_STEPS, SOCIAL_STEPS,
 INTRUSIONS_ROBOT, INTRUSIONS_HUMAN, MIN_TTC, STALLED_TIME, BEST_GOAL_DISTANCE, LAST_PROGRESS_TIME,
 FAILED_TO_PROGRESS) = range(len(_TOTALS))


@numba.njit(cache=True)
def _begin(row, start_x, start_y, goal_x, goal_y):
    """A fresh episode's totals: the robot at rest at its start, nothing accumulated, no time to collision below the
    horizon, its best goal distance the initial one."""
    row[:] = 0.0
    row[PREVIOUS_X], row[PREVIOUS_Y] = start_x, start_y
    row[MIN_TTC] = TTC_HORIZON
    row[BEST_GOAL_DISTANCE] = math.hypot(goal_x - start_x, goal_y - start_y)


@numba.njit(cache=True)
def time_to_collision(rel_x, rel_y, rel_vx, rel_vy, combined_radius):
    """Time until two discs touch if both keep their velocity (Francis et al. 2023, "time to collision").

    With p the relative position, v the relative velocity and R the sum of the radii: the smallest t >= 0 with
    |p + v t| = R, i.e. t = (-b - sqrt(b^2 - 4ac)) / 2a for a = v.v, b = 2 p.v, c = p.p - R^2; 0 if the discs
    already overlap (c <= 0), inf if they never touch (moving apart, b >= 0, or missing, b^2 < 4ac).
    """
    c = rel_x * rel_x + rel_y * rel_y - combined_radius * combined_radius
    if c <= 0.0:
        return 0.0
    a = rel_vx * rel_vx + rel_vy * rel_vy
    b = 2.0 * (rel_x * rel_vx + rel_y * rel_vy)
    if a < 1e-12 or b >= 0.0:
        return np.inf
    discriminant = b * b - 4.0 * a * c
    if discriminant < 0.0:
        return np.inf
    return (-b - math.sqrt(discriminant)) / (2.0 * a)


@numba.njit(cache=True)
def _accumulate(totals, positions, velocities, radii, goals, personal_space, active, heading, time, steps, starts,
                was_intruded_before, time_step):
    """Add the step just taken to every environment's totals (the world after `_advance_and_score`, before its step
    counter advances: `steps` == 0 in an episode's first step, which starts its totals from `starts`).

    Robot motion, from its velocity v_t in the step (v_0 = 0, a_0 = 0: it starts at rest):
        a_t = (v_t - v_{t-1}) / dt,  j_t = (a_t - a_{t-1}) / dt   (vectors; |.| summed and maximised)
    Path irregularity (SocNavBench): the angle between the step's heading h = (cos theta_t, sin theta_t) and the
    straight line d = g - p_{t-1} to the goal from where the step starts, atan2(|h x d|, h . d) = |wrap(theta_t -
    atan2(d))|. Personal-space entries: a human whose gap falls below its personal-space radius this step and was
    outside before (`socnav.sim.world._score`'s intrusion events, from the same gap arithmetic) is robot-caused if
    the robot moves towards it, v_r . (p_h - p_r) > 0 (SEAN 2.0's fault rule), else human-caused. Failure to
    progress: the goal distance has not fallen PROGRESS_DISTANCE below its best for PROGRESS_WINDOW seconds.
    """
    n_envs, n_agents = active.shape
    for env in range(n_envs):
        row = totals[env]
        if steps[env] == 0:
            _begin(row, starts[env, 0], starts[env, 1], goals[env, 0, 0], goals[env, 0, 1])
        robot_x, robot_y = positions[env, 0, 0], positions[env, 0, 1]
        vx, vy = velocities[env, 0, 0], velocities[env, 0, 1]
        speed = math.sqrt(vx * vx + vy * vy)
        ax = (vx - row[PREVIOUS_VX]) / time_step
        ay = (vy - row[PREVIOUS_VY]) / time_step
        jx = (ax - row[PREVIOUS_AX]) / time_step
        jy = (ay - row[PREVIOUS_AY]) / time_step
        acceleration = math.sqrt(ax * ax + ay * ay)
        jerk = math.sqrt(jx * jx + jy * jy)
        row[SPEED_SUM] += speed
        row[SPEED_MAX] = max(row[SPEED_MAX], speed)
        row[ACCELERATION_SUM] += acceleration
        row[ACCELERATION_MAX] = max(row[ACCELERATION_MAX], acceleration)
        row[JERK_SUM] += jerk
        row[JERK_MAX] = max(row[JERK_MAX], jerk)

        to_goal_x = goals[env, 0, 0] - row[PREVIOUS_X]
        to_goal_y = goals[env, 0, 1] - row[PREVIOUS_Y]
        if to_goal_x * to_goal_x + to_goal_y * to_goal_y > 0.0:
            if speed > 0.0:  # the velocity is along the heading: no trigonometry
                hx, hy = vx, vy
            else:
                hx, hy = math.cos(heading[env]), math.sin(heading[env])
            row[IRREGULARITY_SUM] += math.atan2(abs(hx * to_goal_y - hy * to_goal_x), hx * to_goal_x + hy * to_goal_y)
        if speed < STALL_SPEED:
            row[STALLED_TIME] += time_step
        goal_distance = math.sqrt((goals[env, 0, 0] - robot_x) ** 2 + (goals[env, 0, 1] - robot_y) ** 2)
        if goal_distance < row[BEST_GOAL_DISTANCE] - PROGRESS_DISTANCE:
            row[BEST_GOAL_DISTANCE] = goal_distance
            row[LAST_PROGRESS_TIME] = time[env]
        elif time[env] - row[LAST_PROGRESS_TIME] >= PROGRESS_WINDOW:
            row[FAILED_TO_PROGRESS] = 1.0

        nearest_gap = np.inf
        for agent in range(1, n_agents):
            if not active[env, agent]:
                continue
            dx = positions[env, agent, 0] - robot_x
            dy = positions[env, agent, 1] - robot_y
            gap = math.sqrt(dx * dx + dy * dy) - radii[env, 0] - radii[env, agent]
            nearest_gap = min(nearest_gap, gap)
            if (personal_space[env, agent] > 0.0 and gap < personal_space[env, agent]
                    and not was_intruded_before[env, agent]):
                if speed > 0.0 and vx * dx + vy * dy > 0.0:
                    row[INTRUSIONS_ROBOT] += 1.0
                else:
                    row[INTRUSIONS_HUMAN] += 1.0
            ttc = time_to_collision(dx, dy, velocities[env, agent, 0] - vx, velocities[env, agent, 1] - vy,
                                    radii[env, 0] + radii[env, agent])
            row[MIN_TTC] = min(row[MIN_TTC], ttc)
        if nearest_gap < INTIMATE_ZONE:
            row[INTIMATE_STEPS] += 1.0
        if nearest_gap < PERSONAL_ZONE:
            row[PERSONAL_STEPS] += 1.0
        if nearest_gap < SOCIAL_ZONE:
            row[SOCIAL_STEPS] += 1.0

        row[PREVIOUS_X], row[PREVIOUS_Y] = robot_x, robot_y
        row[PREVIOUS_VX], row[PREVIOUS_VY] = vx, vy
        row[PREVIOUS_AX], row[PREVIOUS_AY] = ax, ay


class WorldState(Protocol):
    """What `EpisodeMetrics` reads of the batched world (`socnav.sim.world.CrowdWorld`'s arrays)."""

    positions: np.ndarray  # (E, N, 2), slot 0 the robot
    velocities: np.ndarray  # (E, N, 2)
    radii: np.ndarray  # (E, N)
    goals: np.ndarray  # (E, N, 2)
    personal_space: np.ndarray  # (E, N)
    active: np.ndarray  # (E, N) bool
    heading: np.ndarray  # (E,)
    time: np.ndarray  # (E,)
    steps: np.ndarray  # (E,) steps taken this episode
    starts: np.ndarray  # (E, 2) the robot's start
    path_length: np.ndarray  # (E,)
    min_gap: np.ndarray  # (E,)
    intrusion_steps: np.ndarray  # (E,)
    was_intruded: np.ndarray  # (E, N) bool
    wall_collision: np.ndarray  # (E,) bool: the robot hit an obstacle in the step just taken


class EpisodeMetrics:
    """Per-step accumulators of E environments: `before_step` and `after_step` around every world step (an episode's
    first step starts its totals), `summary` at the episode's end (before the environment is reset)."""

    def __init__(self, n_envs: int, n_slots: int, time_step: float):
        self.time_step = float(time_step)
        self.totals = np.zeros((n_envs, len(_TOTALS)))
        self.was_intruded_before = np.zeros((n_envs, n_slots), dtype=bool)

    def before_step(self, world: WorldState) -> None:
        """Keep which personal spaces the robot was in, to tell this step's new entries."""
        np.copyto(self.was_intruded_before, world.was_intruded)

    def after_step(self, world: WorldState) -> None:
        """Add the step the world just took (after its move and reward, before its step counter advances, humans
        enter or goals change); an episode's first step starts its totals."""
        _accumulate(self.totals, world.positions, world.velocities, world.radii, world.goals, world.personal_space,
                    world.active, world.heading, world.time, world.steps, world.starts, self.was_intruded_before,
                    self.time_step)

    def summary(self, world: WorldState, env: int, outcome: str) -> dict[str, float | bool | int]:
        """The episode's values (`METRIC_RECORD_COLUMNS`) in environment `env`, which ended with `outcome`
        ("goal", "collision", "timeout"; "running" mid-episode)."""
        steps = int(world.steps[env])
        start_x, start_y = world.starts[env].tolist()
        goal_x, goal_y = world.goals[env, 0].tolist()
        totals = self.totals[env]
        if steps == 0:  # no step yet: the totals are still those of the previous episode
            totals = np.empty_like(totals)
            _begin(totals, start_x, start_y, goal_x, goal_y)
        row = totals.tolist()  # Python floats: what follows is scalar arithmetic
        per_step = 1.0 / max(steps, 1)
        straight = math.hypot(goal_x - start_x, goal_y - start_y)
        path = float(world.path_length[env])
        success = outcome == "goal"
        wall = bool(world.wall_collision[env]) or outcome == OBSTACLE_COLLISION_OUTCOME
        return {
            "success": success,
            "collision_human": outcome == "collision" and not wall,
            "collision_obstacle": wall,
            "timeout": outcome == "timeout",
            "path_length_ratio": path / straight if success and straight > 0.0 else math.nan,
            "spl": straight / max(path, straight) if success and straight > 0.0 else 0.0,
            "personal_space_compliance": 100.0 * (1.0 - int(world.intrusion_steps[env]) * per_step),
            "intimate_zone_time": 100.0 * row[INTIMATE_STEPS] * per_step,
            "personal_zone_time": 100.0 * row[PERSONAL_STEPS] * per_step,
            "social_zone_time": 100.0 * row[SOCIAL_STEPS] * per_step,
            "intrusions_robot": int(row[INTRUSIONS_ROBOT]),
            "intrusions_human": int(row[INTRUSIONS_HUMAN]),
            "speed_mean": row[SPEED_SUM] * per_step,
            "speed_max": row[SPEED_MAX],
            "acceleration_mean": row[ACCELERATION_SUM] * per_step,
            "acceleration_max": row[ACCELERATION_MAX],
            "jerk_mean": row[JERK_SUM] * per_step,
            "jerk_max": row[JERK_MAX],
            "path_irregularity": row[IRREGULARITY_SUM] * per_step,
            "min_time_to_collision": row[MIN_TTC],
            "stalled_time": row[STALLED_TIME],
            "failure_to_progress": row[FAILED_TO_PROGRESS] > 0.0,
        }


#: The per-episode record columns `EpisodeMetrics.summary` adds, in order (after the world's own columns).
METRIC_RECORD_COLUMNS = (
    "success", "collision_human", "collision_obstacle", "timeout", "path_length_ratio", "spl",
    "personal_space_compliance", "intimate_zone_time", "personal_zone_time", "social_zone_time",
    "intrusions_robot", "intrusions_human", "speed_mean", "speed_max", "acceleration_mean", "acceleration_max",
    "jerk_mean", "jerk_max", "path_irregularity", "min_time_to_collision", "stalled_time", "failure_to_progress",
)

# ------------------------------------------------------------------------------------------------------------------
# Over episodes: the registry

#: How a metric reduces its per-episode values over episodes.
PERCENT, MEAN, STD, PER_EPISODES = "percent", "mean", "std", "per_episodes"

FRANCIS = "Francis et al. 2023/2025, Principles and Guidelines for Evaluating Social Robot Navigation Algorithms"
SOCNAVBENCH = "Biswas et al. 2022, SocNavBench"
SEAN = "Tsoi et al. 2022, SEAN 2.0"
CROWDNAV = "Chen et al. 2019, CrowdNav"
SPL_SOURCE = "Anderson et al. 2018, On Evaluation of Embodied Navigation Agents (SPL)"
OURS = "socnav (its reward's terms)"


@dataclass(frozen=True)
class Metric:
    """One reported metric: a table column aggregated over episodes from one per-episode record column.

    `kind`: PERCENT (100 x the share of episodes where the value is true), MEAN (mean over the episodes where it is
    defined: NaN values, e.g. time to goal of failed episodes, are left out), STD (population standard deviation),
    PER_EPISODES (the sum over episodes per `PV_PER` episodes). `equals`: the value is ``column == equals``.
    """

    name: str
    label: str
    unit: str
    definition: str
    higher_is_better: bool | None  # None: neither direction is better (e.g. speed, a spread)
    source: str
    column: str
    kind: str = MEAN
    equals: str | None = None
    default: bool = False  # one of today's `socnav evaluate` columns
    decimals: int = 2

    @property
    def direction(self) -> str:
        return {True: "higher", False: "lower", None: "–"}[self.higher_is_better]


METRICS: dict[str, Metric] = {m.name: m for m in [
    Metric("goal_pct", "Goal %", "%", "share of episodes ending with the robot's centre within goal_tolerance of "
           "its goal, before any collision and the time limit (success)", True, FRANCIS, "outcome", PERCENT,
           equals="goal", default=True, decimals=1),
    Metric("collision_pct", "Col. %", "%", "share of episodes whose outcome is 'collision': a collision with a "
           "human (obstacle collisions: collision_obstacle_pct)", False, FRANCIS, "outcome", PERCENT,
           equals="collision", default=True, decimals=1),
    Metric("timeout_pct", "TO %", "%", "share of episodes reaching the time limit (timeout_factor x straight-line "
           "time + timeout_margin)", False, FRANCIS, "outcome", PERCENT, equals="timeout", default=True,
           decimals=1),
    Metric("pv", f"PV/{PV_PER} ep.", f"events / {PV_PER} episodes", "PV, personal-space violations: intrusion events "
           "(the gap to a human falls below its personal-space radius after being above it) per 200 episodes", False,
           "Flögel, Gómez Villafañe et al. 2025 (PV, the replicated paper)", "intrusion_events", PER_EPISODES,
           default=True, decimals=0),
    Metric("return_mean", "Return", "", "mean episode return (undiscounted sum of the reward)", True, OURS,
           "return", default=True),
    Metric("return_std", "Return std", "", "population standard deviation of the episode return", None, OURS,
           "return", STD, default=True),
    Metric("time_to_goal_mean", "nav time (s)", "s", "episode duration of the episodes reaching the goal (time to "
           "goal, CrowdNav's navigation time)", False, FRANCIS, "time_to_goal", default=True, decimals=1),
    Metric("collision_human_pct", "Col. human %", "%", "share of episodes ending in a collision with a human (the "
           "swept robot-human gap falls below 0 during a step)", False, FRANCIS, "collision_human", PERCENT,
           decimals=1),
    Metric("collision_obstacle_pct", "Col. obstacle %", "%", "share of episodes ending in a collision with an "
           "obstacle (the world's wall_collision flag or outcome 'collision_wall'; 0 without obstacles)", False,
           FRANCIS, "collision_obstacle", PERCENT, decimals=1),
    Metric("path_length", "Path (m)", "m", "length of the robot's path (sum of speed x dt over the episode)", False,
           FRANCIS, "path_length"),
    Metric("path_length_ratio", "Path ratio", "", "path length / straight-line distance from start to goal, of the "
           "episodes reaching the goal (slightly below 1 for a straight drive: the episode ends goal_tolerance "
           "before the goal)", False, SOCNAVBENCH, "path_length_ratio", decimals=3),
    Metric("spl", "SPL", "", "success weighted by path length: S l / max(p, l), S = 1 at the goal else 0, l the "
           "straight-line start-goal distance (the shortest path without obstacles), p the path length", True,
           SPL_SOURCE, "spl", decimals=3),
    Metric("min_gap", "Min gap (m)", "m", "smallest gap (edge to edge) to any human during the episode, between "
           "steps included (swept)", True, FRANCIS, "min_gap"),
    Metric("personal_space_compliance", "PS compliance %", "%", "share of steps with every human's gap at or "
           "above its personal-space radius", True, FRANCIS, "personal_space_compliance", decimals=1),
    Metric("intimate_zone_time", "Intimate %", "%", f"share of steps with a human's gap below {INTIMATE_ZONE} m "
           "(intimate zone, Hall)", False, SEAN, "intimate_zone_time", decimals=1),
    Metric("personal_zone_time", "Personal %", "%", f"share of steps with a human's gap below {PERSONAL_ZONE} m "
           "(personal zone, Hall)", False, SEAN, "personal_zone_time", decimals=1),
    Metric("social_zone_time", "Social %", "%", f"share of steps with a human's gap below {SOCIAL_ZONE} m (social "
           "zone, Hall)", False, SEAN, "social_zone_time", decimals=1),
    Metric("pv_robot", f"PV robot/{PV_PER} ep.", f"events / {PV_PER} episodes", "intrusion events the robot "
           "caused (it moves towards the human: v_r . (p_h - p_r) > 0) per 200 episodes", False, SEAN,
           "intrusions_robot", PER_EPISODES, decimals=0),
    Metric("pv_human", f"PV human/{PV_PER} ep.", f"events / {PV_PER} episodes", "intrusion events the human caused "
           "(the robot stands still or moves away) per 200 episodes; pv_robot + pv_human = pv", False, SEAN,
           "intrusions_human", PER_EPISODES, decimals=0),
    Metric("speed_mean", "Speed (m/s)", "m/s", "the robot's mean speed over the episode's steps", None, FRANCIS,
           "speed_mean"),
    Metric("speed_max", "Max speed (m/s)", "m/s", "the robot's largest speed in the episode", None, FRANCIS,
           "speed_max"),
    Metric("acceleration_mean", "Accel. (m/s²)", "m/s²", "mean |a_t|, a_t = (v_t - v_{t-1}) / dt (velocity "
           "vectors, from rest: v_0 = 0)", False, FRANCIS, "acceleration_mean"),
    Metric("acceleration_max", "Max accel. (m/s²)", "m/s²", "largest |a_t| in the episode", False, FRANCIS,
           "acceleration_max"),
    Metric("jerk_mean", "Jerk (m/s³)", "m/s³", "mean |j_t|, j_t = (a_t - a_{t-1}) / dt (a_0 = 0)", False, FRANCIS,
           "jerk_mean", decimals=1),
    Metric("jerk_max", "Max jerk (m/s³)", "m/s³", "largest |j_t| in the episode", False, FRANCIS, "jerk_max",
           decimals=1),
    Metric("path_irregularity", "Path irreg. (rad)", "rad", "mean over steps of |heading - direction from the "
           "step's start to the goal|", False, SOCNAVBENCH, "path_irregularity", decimals=3),
    Metric("min_time_to_collision", "Min TTC (s)", "s", "smallest time to collision with any human if both kept "
           f"their velocity, over the steps (capped at {TTC_HORIZON:g} s)", True, FRANCIS,
           "min_time_to_collision"),
    Metric("stalled_time", "Stalled (s)", "s", f"time the robot moves slower than {STALL_SPEED} m/s", False, SEAN,
           "stalled_time"),
    Metric("failure_to_progress_pct", "No progress %", "%", f"share of episodes in which the robot gets no "
           f"{PROGRESS_DISTANCE} m closer to its goal than before for {PROGRESS_WINDOW:g} s", False, SEAN,
           "failure_to_progress", PERCENT, decimals=1),
    Metric("disturbance", "Disturbance", "", "sum over steps and humans within reward.social_radius of "
           "|v_i - v_i^0| / v_pref,i (v_i^0: the human's velocity were the robot absent; 0 when the reward's "
           "disturbance weight is 0)", False, OURS, "disturbance"),
]}

#: Today's columns of `socnav evaluate` and of `socnav.envs.rollout.summarize`, in their order.
DEFAULT_METRICS = tuple(name for name, metric in METRICS.items() if metric.default)
ALL_METRICS = tuple(METRICS)


def select_metrics(spec: str) -> list[str]:
    """Metric names from ``default``, ``all`` or a comma-separated list of names (ValueError naming the allowed
    names, and the closest one, for an unknown name)."""
    text = spec.strip()
    if text == "default":
        return list(DEFAULT_METRICS)
    if text == "all":
        return list(ALL_METRICS)
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise ValueError(f"no metric named in {spec!r}; allowed: default, all, or names from: {', '.join(METRICS)}")
    for name in names:
        if name not in METRICS:
            close = difflib.get_close_matches(name, list(METRICS), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(f"unknown metric {name!r}{hint}; allowed: default, all, or a comma-separated list of: "
                             f"{', '.join(METRICS)}")
    return list(dict.fromkeys(names))


def _values(records: pd.DataFrame, metric: Metric) -> pd.Series:
    """The metric's per-episode values (booleans for PERCENT metrics); all NaN without its record column."""
    import pandas as pd

    if metric.column not in records:
        return pd.Series(np.nan, index=records.index, dtype=float)
    column = records[metric.column]
    return column == metric.equals if metric.equals is not None else column


def summarize_episodes(records: pd.DataFrame, names: Sequence[str] = DEFAULT_METRICS,
                       pv_per: int = PV_PER) -> dict[str, float]:
    """The metrics `names` over all episodes of `records` (one row per episode), with ``episodes`` first.

    PERCENT: 100 x the share, ``100 * mean(indicator)``; MEAN: the mean of the defined values; STD: population
    std (ddof = 0); PER_EPISODES: ``sum * pv_per / n``.
    """
    n = len(records)
    summary: dict[str, float] = {"episodes": n}
    for name in names:
        metric = METRICS[name]
        values = _values(records, metric)
        if metric.kind == PERCENT:
            summary[name] = 100.0 * float(values.mean())
        elif metric.kind == STD:
            summary[name] = float(values.std(ddof=0))
        elif metric.kind == PER_EPISODES:
            summary[name] = float(values.sum()) * pv_per / n
        else:
            summary[name] = float(values.astype(float).mean())
    return summary


def summarize_groups(records: pd.DataFrame, by: Sequence[str], names: Sequence[str] = DEFAULT_METRICS,
                     pv_per: int = PV_PER) -> pd.DataFrame:
    """The metrics `names` per group of `records` (grouped by the columns `by`, in order of appearance): one row per
    group with the `by` columns, ``episodes`` and one column per metric; metrics whose record column `records`
    lacks are left out.

    The same reductions as `summarize_episodes`, with a group's PERCENT computed as the mean of per-episode
    percentages (``mean(100 * indicator)``, the arithmetic Table 1 has always used; it can differ from
    ``100 * mean(indicator)`` in the last bit).
    """
    by = list(by)
    present = [name for name in names if METRICS[name].column in records]
    columns: dict[str, Any] = {}
    spec: dict[str, tuple[str, str]] = {"episodes": ("_episodes", "size")}
    for name in present:
        metric = METRICS[name]
        values = _values(records, metric)
        source = f"_{name}"
        if metric.kind == PERCENT:
            columns[source] = values * 100.0
            spec[name] = (source, "mean")
        elif metric.kind == PER_EPISODES:
            columns[source] = values
            spec[name] = (source, "sum")
        else:
            columns[source] = values.astype(float)
            spec[name] = (source, "mean")
    frame = records[by].assign(_episodes=0, **columns)
    grouped = frame.groupby(by, sort=False)
    table = grouped.agg(**spec)
    for name in present:
        metric = METRICS[name]
        if metric.kind == PER_EPISODES:
            table[name] = table[name] * pv_per / table["episodes"]
        elif metric.kind == STD:
            table[name] = grouped[f"_{name}"].std(ddof=0)
    return table.reset_index()[[*by, "episodes", *present]]


def episode_values(records: pd.DataFrame, name: str, pv_per: int = PV_PER) -> np.ndarray:
    """The defined per-episode values of metric `name`, scaled so that their mean (their population std for a STD
    metric) is the metric: indicators x 100 for PERCENT, counts x `pv_per` for PER_EPISODES. For intervals by
    resampling episodes."""
    metric = METRICS[name]
    values = _values(records, metric).to_numpy(dtype=float)
    values = values[~np.isnan(values)]
    if metric.kind == PERCENT:
        return values * 100.0
    if metric.kind == PER_EPISODES:
        return values * pv_per
    return values


def metric_table_rows(summary: Mapping[str, float], names: Sequence[str]) -> list[tuple[str, str, str, str, str]]:
    """(name, label, value, unit, better) rows of `summary` for the metrics `names`, values at their decimals."""
    rows = []
    for name in names:
        metric = METRICS[name]
        value = summary.get(name, math.nan)
        text = "–" if value is None or math.isnan(value) else f"{value:.{metric.decimals}f}"
        rows.append((name, metric.label, text, metric.unit, metric.direction))
    return rows
