"""The single social-navigation environment with the Gymnasium API (observation, action and reward: docs/world.md).

`SocialNavEnv` is one `CrowdWorld` environment; `make_env` builds it from a config object, a partial dict or a YAML
path.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from socnav.config import ConfigError, ConfigLike, EnvConfig, load_config
from socnav.envs.spaces import ACTION_NAMES, action_space, world_observation_space
from socnav.sim.world import OUTCOME_GOAL, OUTCOME_NAMES, CrowdWorld, StepResult

if TYPE_CHECKING:
    from socnav.viz import HumanViewer
    from socnav.viz.render import SceneFrame, SceneRenderer


class ActionError(ValueError):
    """An action cannot be applied (NaN, wrong shape); the message names the environment."""


def check_actions(actions: Any, n_envs: int, label: str = "environment") -> np.ndarray:
    """`actions` as a float64 (n_envs, 2) array, or `ActionError` naming the first environment whose action is NaN.

    A NaN action would make the robot's position and reward NaN for the rest of the episode (no end, no error),
    so it is refused. +-inf is accepted: like every out-of-range action it is clipped to the action bounds [-1, 1]
    (SB3 clips a Box policy's actions the same way before they reach the environment).
    """
    array = np.asarray(actions, dtype=np.float64)
    n_values = len(ACTION_NAMES)  # speed, heading change
    if array.size != n_values * n_envs:
        raise ActionError(f"expected {n_envs} action(s) of {n_values} values (speed, heading change), got shape "
                          f"{array.shape}")
    array = array.reshape(n_envs, n_values)
    bad = np.flatnonzero(np.isnan(array).any(axis=1))
    if bad.size:
        env = int(bad[0])
        others = f" (and {bad.size - 1} other(s))" if bad.size > 1 else ""
        raise ActionError(f"the action of {label} {env}{others} is NaN: {array[env].tolist()}; actions must be "
                          "numbers in [-1, 1] (larger values and +-inf are clipped)")
    return array


#: Memory of one environment in bytes ~ a + b * slots + c * slots**2 + d * max_humans (slots = 1 + most humans):
#: the world's per-agent and per-pair arrays, the observation and the per-step info dict, fitted (and rounded up
#: by ~25 %) to tracemalloc peaks of 1,500-environment VecEnvs over reset + 3 steps with 1 to 64 humans.
_ENV_BYTES = (2048, 128, 24, 128)


def env_memory_estimate(config: EnvConfig, n_envs: int) -> int:
    """Estimated bytes that `n_envs` batched environments of `config` take while stepping."""
    from socnav.sim.scenarios import n_slots

    a, b, c, d = _ENV_BYTES
    slots = n_slots(config)
    return n_envs * (a + b * slots + c * slots * slots + d * config.max_humans)


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX: no bound known
        return None


def check_env_count(n_envs: Any, config: EnvConfig, what: str = "n_envs") -> int:
    """`n_envs` if it is a positive integer whose environments fit in this machine's memory, else `ConfigError`
    naming `what`, the estimate and the most environments that fit (see `env_memory_estimate`)."""
    if isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or n_envs < 1:
        raise ConfigError(f"{what} must be a positive integer, got {n_envs!r}")
    need, total = env_memory_estimate(config, int(n_envs)), _physical_memory()
    if total is not None and need > total:
        most = total // env_memory_estimate(config, 1)
        raise ConfigError(
            f"{what}={int(n_envs):,} environments need about {need / 2**30:,.1f} GiB (~{need // n_envs:,} bytes each "
            f"with at most {config.humans_range()[1]} human(s)), more than this machine's {total / 2**30:,.1f} GiB of "
            f"memory; use at most {most:,}"
        )
    return int(n_envs)


def step_infos(world: CrowdWorld, result: StepResult) -> list[dict[str, Any]]:
    """Per-step `info` of every environment; at the end of an episode it carries the `episode` summary."""
    # .tolist() converts whole columns at once: building these dicts element by element cost more than the physics.
    columns = zip(world.time.tolist(), result.nearest_gap.tolist(), result.nearest_relative_speed.tolist(),
                  result.intrusions.tolist(), strict=True)
    infos = [
        {"time": time, "nearest_gap": gap, "nearest_relative_speed": speed, "intrusions": intrusions}
        for time, gap, speed, intrusions in columns
    ]
    for env in np.flatnonzero(result.outcome).tolist():
        outcome = int(result.outcome[env])
        summary = world.episode_summary(env, outcome)
        info = infos[env]
        info["outcome"] = OUTCOME_NAMES[outcome]
        info["is_success"] = outcome == OUTCOME_GOAL
        # "r" and "l" make SB3 log rollout/ep_rew_mean and ep_len_mean as with its Monitor wrapper.
        info["episode"] = {"r": summary["return"], "l": summary["length"], "t": summary["duration"], **summary}
    return infos


def scene_frame(world: CrowdWorld, env: int, trail: list[np.ndarray] | None = None, caption: str = "",
                **extra: Any) -> SceneFrame:
    """Environment `env` of `world` as a `socnav.viz.SceneFrame`, with the robot's recent `trail` of positions."""
    from socnav.viz.render import SceneFrame

    walls = world.walls
    route, subgoal = robot_route(world, env) or (None, None)
    return SceneFrame(
        positions=world.positions[env].copy(),
        velocities=world.velocities[env].copy(),
        radii=world.radii[env].copy(),
        goals=world.goals[env].copy(),
        personal_space_radii=world.personal_space[env].copy(),
        active=world.active[env].copy(),
        robot_heading=float(world.heading[env]),
        time=float(world.time[env]),
        trails=np.stack(trail) if trail else None,
        caption=caption,
        attentive=world.attentive[env].copy(),
        models=world.human_model_names(env),
        walls=None if walls is None else walls.polygons,
        hidden=~walls.in_sight_of_robot(world.positions[env:env + 1], world.active[env:env + 1])[0]
        if world.occlusion and walls is not None else None,
        route=route,
        subgoal=subgoal,
        **extra,
    )


def robot_route(world: CrowdWorld, env: int) -> tuple[np.ndarray, np.ndarray] | None:
    """What the global planner shows for the robot of environment `env`: its shortest path from where it is to its
    goal (`socnav.sim.planning`, at the robot's clearance) and the subgoal ``planner.lookahead`` metres along it;
    None in the open plane, with the planner off, or where no path reaches the goal."""
    from socnav.sim.planning import planner_for
    from socnav.sim.route import subgoal_on_path

    planner = world.config.planner
    if world.walls is None or not planner.enabled:
        return None
    graph = planner_for(world.walls.polygons, world.config.robot_radius + planner.margin)
    position = world.positions[env, 0]
    path = graph.shortest_path(position, world.goals[env, 0])
    if path is None:
        return None
    return path, subgoal_on_path(path, position, planner.lookahead)


def scene_extent(config: EnvConfig) -> float:
    """Half the side of the square a rendered scene shows (metres around the origin): the circle scenarios'
    circle, the random scenario's square, the replayed robot's path, plus a margin; a map scenario's walls, with
    a band above them for the clock of a plain frame (`socnav.viz.render.clock_clear_extent`, at `env.render`'s
    480 pixels), so that the clock is never drawn over a wall."""
    if config.scenario == "random":
        return config.square_size / 2 + 1.5
    if config.scenario == "replay":
        return config.humans.replay.robot_distance / 2 + 1.5
    if config.scenario in ("corridor", "intersection"):
        extent = config.layout.corridor_length / 2 + 0.5
    elif config.scenario == "doorway":
        extent = config.layout.room_size + 0.5
    elif config.scenario == "room":
        extent = config.circle_radius + config.circle_jitter + 2.6
    else:
        return config.circle_radius + 1.5
    from socnav.sim.scenarios import get_scenario
    from socnav.viz.render import clock_clear_extent

    static_map = getattr(get_scenario(config.scenario), "static_map", None)  # a map scenario's walls
    walls = static_map(config) if static_map is not None else []
    top = max((float(np.max(np.asarray(polygon)[:, 1])) for polygon in walls), default=0.0)
    return max(extent, clock_clear_extent(top))


class SocialNavEnv(gym.Env):
    """A unicycle robot crossing a crowd of reactive, socially individual humans (docs/world.md).

    ## Description

    The robot (agent 0) drives to its goal on a 2-D open plane among humans who walk to their own goals with ORCA
    (exact RVO2 semantics, van den Berg et al. 2011; or social force, ``humans.model``, docs/humans.md; the
    behaviour-shift perturbation ``perturbation.human_model`` swaps the model) and react to the robot as
    individuals: each keeps its personal
    space `r_prox` free of the robot, takes its own share of the avoidance (cooperation), and may be inattentive to
    the robot or notice it only inside its view cone. None of this is observable, so the task is the POMDP of paper
    eq. (1); the reward is the socially integrated reward of Flögel et al. (IROS 2024) that the paper trains
    with. One `SocialNavEnv` is one environment of a `socnav.sim.world.CrowdWorld`; `socnav.make_vec_env` steps
    many of them in one batched call with identical episodes.

    ## Action Space

    `Box(-1, 1, (2,), float32)`; out-of-range values (+-inf included) are clipped to [-1, 1], NaN is refused:

    | Num | Action    | Maps to                                                       |
    |-----|-----------|---------------------------------------------------------------|
    | 0   | `speed`   | `v = v_pref (a0 + 1) / 2` m/s, in `[0, v_pref]`               |
    | 1   | `heading` | heading change `dtheta = max_heading_change * a1` (pi/6 rad)  |

    The robot then moves as a unicycle: `theta <- wrap(theta + dtheta)`, `p <- p + v [cos theta, sin theta] dt`.
    Action noise (`perturbation.heading_noise`, `perturbation.speed_noise`) perturbs `v` and `dtheta` before the move.

    ## Observation Space

    A `Dict` of float32 arrays in the robot-centric, goal-aligned frame (x-axis from the robot to its goal):

    `robot`, `Box(-inf, inf, (5,))`:

    | Num | Feature           | Meaning                                                      | Unit |
    |-----|-------------------|--------------------------------------------------------------|------|
    | 0   | `goal_distance`   | distance from the robot's centre to its goal                 | m    |
    | 1   | `goal_heading`    | robot heading relative to the goal direction, in [-pi, pi)   | rad  |
    | 2   | `speed`           | current speed                                                | m/s  |
    | 3   | `preferred_speed` | the robot's preferred (maximum) speed `v_pref`               | m/s  |
    | 4   | `radius`          | the robot's radius                                           | m    |

    `humans`, `Box(-inf, inf, (max_humans, 7))`: one row per human, rows sorted by gap with the closest LAST (an
    LSTM reads it last), zero padding after the real rows; with more than `max_humans` humans the closest are kept:

    | Num | Feature           | Meaning                                                      | Unit |
    |-----|-------------------|--------------------------------------------------------------|------|
    | 0   | `rel_x`           | human minus robot position, along the goal direction         | m    |
    | 1   | `rel_y`           | human minus robot position, across the goal direction        | m    |
    | 2   | `rel_vx`          | human minus robot velocity, along the goal direction         | m/s  |
    | 3   | `rel_vy`          | human minus robot velocity, across the goal direction        | m/s  |
    | 4   | `radius`          | the human's radius                                           | m    |
    | 5   | `combined_radius` | human radius + robot radius                                  | m    |
    | 6   | `gap`             | centre distance - combined radius (negative: bodies overlap) | m    |

    `humans_mask`, `Box(0, 1, (max_humans,))`: 1 for the rows that are real humans, 0 for padding.

    No hidden state of the humans (goal, `v_pref`, `r_prox`, cooperation, attention) appears in the observation.
    `perturbation.observation_noise` adds N(0, s^2) to every real element (neither padding nor the mask).

    In a world with walls (a map scenario, `obstacles` or `map`), `pose`, `Box(-inf, inf, (3,))`: the robot's x, y
    (m) and yaw (rad) in the map frame, as a localised robot knows them (the ORCA robot plans around the walls from
    it). With `occlusion` (on in the map scenarios), a human behind a wall is absent from `humans`, exactly as if out
    of range. With `scan: {beams, range, fov}`, `scan`, `Box(0, range, (beams,))`: the distance to the first wall
    along each beam, from -fov/2 counter-clockwise about the heading (a `sensor_msgs/LaserScan`), `range` where
    none is hit (humans do not appear in it).

    ## Rewards

    The socially integrated reward (Flögel et al., IROS 2024; paper Sec. III-A), every step; it is defined in one place,
    `socnav.sim.world._score`, with the weights of `config.reward` (`socnav.config.RewardConfig`):

        r_t = - w_time dt + w_prog (d_goal(t-1) - d_goal(t))
              - sum over humans i with gap_i < r_prox,i        of w_prox (1 - gap_i / r_prox,i)
              - sum over humans i within social_radius         of w_dist |v_i - v_i^0| / v_pref,i
              + w_goal [goal reached] - w_col [collision]

    `gap_i` is the distance between the bodies; `v_i^0` is the velocity ORCA would have given human i this step had
    the robot not been there (how far the robot pushed that person off their way); the disturbance counts the
    humans within `social_radius` at the start of the step. Every weight can be switched off with 0:

    | Symbol    | Config field                   | Default | Term                                           |
    |-----------|--------------------------------|---------|------------------------------------------------|
    | `w_goal`  | `reward.goal`                  | 5.0     | reaching the goal                              |
    | `w_col`   | `reward.collision`             | 5.0     | a collision                                    |
    | `w_time`  | `reward.time`                  | 0.5     | per second of episode                          |
    | `w_prog`  | `reward.progress`              | 1.0     | per metre of progress (potential-based)        |
    | `w_prox`  | `reward.personal_space`        | 0.5     | per intruded personal space                    |
    | `w_dist`  | `reward.disturbance`           | 0.25    | per unit of relative disturbance               |
    |           | `reward.social_radius`         | 3.0     | metres (gap) within which humans score         |

    ## Starting State

    Each reset draws an episode from the scenario (`config.scenario`) with the environment's own generator:

    - `position_swap`: the robot and one human on a circle of radius `circle_radius` (7 m) at independent uniform
      angles, each heading to its own antipode;
    - `circle_crossing`: `n_humans` (5) humans at uniform angles on the circle (+- `circle_jitter`), goals at their
      antipodes; the robot on one of four fixed diameters;
    - `circle_interaction`: the robot crosses the circle and each of 1-3 humans is placed to reach the centre when
      the robot does;
    - `random`: starts and goals uniform in a `square_size` (14 m) square; humans draw a new goal on arrival.

    Every agent's `v_pref ~ U[preferred_speed]` (0.5-1.0 m/s); every human's `r_prox ~ U[personal_space]`
    (0.3-0.7 m) and cooperation `~ U[cooperation]` (0.25-0.5), and it is inattentive with probability
    `inattentive_share`. All velocities start at zero; the robot's heading is uniform (`initial_heading="random"`)
    or points at its goal (`"goal"`).

    ## Episode End

    Checked after every step, the first that applies (`info["outcome"]`; codes `socnav.sim.world.OUTCOME_*`):

    1. Termination, `"collision"` (`OUTCOME_COLLISION`): the robot's body overlaps a human's at any moment of the
       step (the swept gap is negative).
    2. Termination, `"collision_wall"` (`OUTCOME_COLLISION_WALL`): in a world with walls, the robot's body touches
       a wall at any moment of the step (its disc swept along the step's straight move); the collision penalty.
    3. Termination, `"goal"` (`OUTCOME_GOAL`): the robot's centre is within `goal_tolerance` (0.3 m) of its goal;
       `info["is_success"]` is True.
    4. Truncation, `"timeout"` (`OUTCOME_TIMEOUT`): `t > timeout_factor |start - goal| / v_pref + timeout_margin`
       (2 |start - goal| / v_pref + 10 s).

    Every step's `info` holds `time`, `nearest_gap`, `nearest_relative_speed` and `intrusions`; the last step's also
    `outcome`, `is_success` and `episode` (return `r`, length `l`, time `t`, path length, minimum gap, intrusion
    steps and events, disturbance).

    ## Arguments

    ```python
    import gymnasium as gym
    import socnav

    env = gym.make("socnav/CircleCrossing-v0", n_humans=3, render_mode="rgb_array")
    env = socnav.make_env({"scenario": "random", "perturbation": {"heading_noise": 0.4}})
    ```

    | Parameter     | Type                                 | Default | Description                                     |
    |---------------|--------------------------------------|---------|-------------------------------------------------|
    | `config`      | `EnvConfig`, dict, YAML path or None | `None`  | the world; missing fields take their defaults   |
    | `render_mode` | `"rgb_array"`, `"human"` or None     | `None`  | frames: agents, goals, personal spaces, trails  |
    | `**overrides` | config fields                        |         | e.g. `n_humans=3` (`gymnasium.make`'s kwargs)   |

    `reset(seed=s)` makes the episode a function of `s` alone: environment i of a VecEnv seeded with `s` plays the
    episodes of this environment seeded with `s + i`.

    ## Version History

    * v0: initial release (`socnav/PositionSwap-v0`, `socnav/CircleCrossing-v0`, `socnav/CircleInteraction-v0`,
      `socnav/Random-v0`); the map scenarios (`socnav/Corridor-v0`, `socnav/Doorway-v0`, `socnav/Intersection-v0`,
      `socnav/Room-v0`) with walls, the `collision_wall` outcome and the `pose` and `scan` observation keys.
    """

    # Gymnasium's API declares `metadata` a class attribute (gym.Env's own is a dict); `__init__` replaces it per
    # instance, nothing mutates it in place.
    metadata: dict[str, Any] = {"render_modes": ["rgb_array", "human"], "render_fps": 4}  # noqa: RUF012

    def __init__(self, config: ConfigLike = None, render_mode: str | None = None, **overrides: Any):
        self.config: EnvConfig = load_config(config, **overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} is not supported; allowed: rgb_array, human, None")
        self.render_mode = render_mode
        self.world = CrowdWorld(self.config, n_envs=1)
        self.observation_space = world_observation_space(self.world)
        self.action_space = action_space()
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.config.time_step)}
        self._trail: list[np.ndarray] = []
        self._renderer: SceneRenderer | None = None
        self._viewer: HumanViewer | None = None
        self._started = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None or not self._started:
            # The world owns the randomness so that env i of a VecEnv seeded with s equals this env seeded with s+i.
            self.world.seed(0, seed if seed is not None else int(self.np_random.integers(2**63)))
        self._started = True
        self.world.reset([0])
        self._trail = [self._trail_point()]
        info = {"time": 0.0}
        if self.render_mode == "human":
            self.render()
        return self._observation(), info

    def step(self, action: np.ndarray):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        result = self.world.step(check_actions(action, 1))
        if self.world.entered[0].any():  # a new (replayed) human in a slot: its trail starts here
            self._trail[-1] = np.where(self.world.entered[0][:, None], np.nan, self._trail[-1])
        self._trail.append(self._trail_point())
        info = step_infos(self.world, result)[0]
        if self.render_mode == "human":
            self.render()
        return (
            self._observation(),
            float(result.reward[0]),
            bool(result.terminated[0]),
            bool(result.truncated[0]),
            info,
        )

    def _trail_point(self) -> np.ndarray:
        """Every agent's position now, NaN for the inactive slots (a break in their trail)."""
        return np.where(self.world.active[0][:, None], self.world.positions[0], np.nan)

    def _observation(self) -> dict[str, np.ndarray]:
        return {key: value[0] for key, value in self.world.observe().items()}

    # ------------------------------------------------------------------------------------------------ rendering

    def scene_frame(self, caption: str = "", **extra: Any) -> SceneFrame:
        """The current scene as a `socnav.viz.SceneFrame` (positions, goals, personal spaces, trail)."""
        return scene_frame(self.world, 0, self._trail[-40:], caption=caption, **extra)

    def render_frame(self, caption: str = "") -> np.ndarray:
        """The current scene as an rgb array with `caption` written on it, whatever the `render_mode`."""
        from socnav.viz.render import SceneRenderer

        if self._renderer is None:
            self._renderer = SceneRenderer(extent=scene_extent(self.config))
        return self._renderer.render(self.scene_frame(caption=caption))

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'.")
            return None
        image = self.render_frame()
        if self.render_mode == "rgb_array":
            return image
        from socnav.viz import HumanViewer

        if self._viewer is None:
            self._viewer = HumanViewer()
        self._viewer.show(image)
        return None

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


def make_env(config: ConfigLike = None, render_mode: str | None = None, **overrides: Any) -> SocialNavEnv:
    """Build one environment; `config` may be an `EnvConfig`, a partial dict, a YAML path or None."""
    return SocialNavEnv(config, render_mode=render_mode, **overrides)
