"""The batched crowd world: a unicycle robot among humans with personal space, cooperation and attention (the
POMDP of the paper's Sec. III-A; its scenarios, reward and episode ends on docs/world.md).

`CrowdWorld` holds the state of E environments as arrays and advances all of them in one call; every environment's
episode depends only on its own seed, so results are bit-identical whatever the batch size. How the humans walk is
a plug-in `socnav.sim.humans.HumanModel` (``humans.model``: ORCA by default, or the social force model); the world
gives it its arrays (`CrowdWorld.crowd`) and moves every human by the velocity it returns. A mixed crowd
(``humans.mix``) draws each human's model per episode from the episode's noise key (`CrowdWorld.model_index`);
replayed humans (``replay``) follow recorded tracks, entering and leaving slots mid-episode through the
`socnav.sim.humans.ScriptedHumans` hooks.

Attention (docs/attention.md): each human is, per episode, attentive to the robot or not (probability
`inattentive_share` of not); an inattentive human plans as if the robot were absent (RVO2 `collabCoeff = 0`), and
with `human_fov_deg < 360` an attentive human reacts only once the robot has entered its view cone, and keeps
reacting while the robot stays within the model's interaction range (ORCA: `orca.neighbor_dist`). Attentiveness is
drawn from the episode's counter-based noise key, not from the episode generator, so switching it on or off leaves
starts, goals and every other draw of an episode unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from socnav.sim.config import EnvConfig
from socnav.sim.geometry import range_scan
from socnav.sim.humans import Crowd, MixedHumans, ScriptedHumans, make_human_model
from socnav.sim.metrics import EpisodeMetrics
from socnav.sim.orca import default_social_arrays
from socnav.sim.planning import PathFollower, planner_for
from socnav.sim.route import observed_goals
from socnav.sim.scenarios import GoalRedrawingScenario, InitialState, RoutedScenario, get_scenario, n_slots
from socnav.sim.walls import POSE_KEY, SCAN_KEY, Walls, world_polygons
from socnav.sim.world_kernels import (
    HUMAN_FEATURES,
    OUTCOME_COLLISION,
    OUTCOME_COLLISION_WALL,
    OUTCOME_GOAL,
    OUTCOME_NAMES,
    OUTCOME_RUNNING,
    OUTCOME_TIMEOUT,
    ROBOT_FEATURES,
    add_observation_noise,
    advance_and_score,
    draw_attention,
    humans_within,
    notice_robot,
    observe_batch,
    reward_weights,
    robot_command_batch,
)
from socnav.validation import ConfigError

#: what `socnav.sim.world` has always exported, the kernels' constants included
__all__ = ["HUMAN_FEATURES", "MAX_PLACEMENT_DRAWS", "OUTCOME_COLLISION", "OUTCOME_COLLISION_WALL", "OUTCOME_GOAL",
           "OUTCOME_NAMES", "OUTCOME_RUNNING", "OUTCOME_TIMEOUT", "ROBOT_FEATURES", "CrowdWorld", "StepResult",
           "observe_batch", "robot_command_batch"]


#: how many times a reset redraws an episode whose starts or goals do not fit among the walls before it gives up
MAX_PLACEMENT_DRAWS = 100


@dataclass
class StepResult:
    """What one batched step produced, per environment."""

    reward: np.ndarray  # (E,)
    terminated: np.ndarray  # (E,) bool: goal or collision
    truncated: np.ndarray  # (E,) bool: time-out
    outcome: np.ndarray  # (E,) int: OUTCOME_*
    nearest_gap: np.ndarray  # (E,) gap to the nearest human after the step (inf without humans)
    nearest_relative_speed: np.ndarray  # (E,) |v_human - v_robot| of that human
    intrusions: np.ndarray  # (E,) number of personal spaces the robot is in


class CrowdWorld:
    """E independent social-navigation worlds advanced together.

    Agent slot 0 is the robot; slots 1.. are humans (inactive slots are padding). Each environment owns a
    `numpy.random.Generator` used only at its resets (and goal redraws), and a counter-based noise key per episode.
    """

    def __init__(self, config: EnvConfig, n_envs: int, metrics: bool = False):
        self.config = config
        self.n_envs = n_envs
        self.n_slots = n_slots(config)
        self.scenario = get_scenario(config.scenario)
        self.rngs = [np.random.default_rng() for _ in range(n_envs)]
        shape = (n_envs, self.n_slots)
        self.positions = np.zeros((*shape, 2))
        self.velocities = np.zeros((*shape, 2))
        self.goals = np.zeros((*shape, 2))
        self.radii = np.zeros(shape)
        self.preferred_speeds = np.zeros(shape)  # robot and humans, unperturbed
        self.max_speeds = np.zeros(shape)  # after the faster-humans perturbation
        self.personal_space = np.zeros(shape)
        self.cooperation = np.zeros(shape)
        self.active = np.zeros(shape, dtype=bool)
        self.heading = np.zeros(n_envs)
        self.time = np.zeros(n_envs)
        self.steps = np.zeros(n_envs, dtype=np.int64)
        self.time_limit = np.zeros(n_envs)
        self.starts = np.zeros((n_envs, 2))
        self.noise_keys = np.zeros(n_envs, dtype=np.uint64)
        # per-pair social arrays every human model reads (`Crowd`); constant within an episode but for `sees`
        # (neutral between humans, as in RVO2: no pad, even shares, everyone seen)
        self.radius_pad, self.avoidance_share, self.sees = default_social_arrays(n_envs, self.n_slots)
        self.sees_without_robot = np.ones_like(self.sees)
        self.sees_without_robot[:, :, 0] = False
        # episode accumulators
        self.was_intruded = np.zeros(shape, dtype=bool)
        self.episode_return = np.zeros(n_envs)
        self.path_length = np.zeros(n_envs)
        self.min_gap = np.full(n_envs, np.inf)
        self.intrusion_steps = np.zeros(n_envs, dtype=np.int64)
        self.intrusion_events = np.zeros(n_envs, dtype=np.int64)
        self.disturbance = np.zeros(n_envs)
        # Obstacle hook: True when the robot hit an obstacle in the step just taken (set by obstacle code; cleared
        # at every episode start); the metric collision_obstacle reads it at the episode's end.
        self.wall_collision = np.zeros(n_envs, dtype=bool)
        # The field's navigation metrics (socnav.sim.metrics), accumulated every step when asked for.
        self.metrics = EpisodeMetrics(n_envs, self.n_slots, config.time_step) if metrics else None
        self.humans_slots = np.zeros(shape, dtype=bool)
        self.humans_slots[:, 1:] = True
        # attention (docs/attention.md): per episode; `noticed` and `facing` change every step with a field of view
        self.attentive = np.ones(shape, dtype=bool)
        self.noticed = np.ones(shape, dtype=bool)
        self.facing = np.zeros(shape)
        self.has_field_of_view = config.human_fov_deg < 360.0
        self.cos_half_fov = math.cos(math.radians(config.human_fov_deg) / 2.0)
        self.human_model = make_human_model(config)
        # a human within this of its goal has arrived: scenarios with `redraw_goals` give it a new one
        self.arrival_distance = max(config.goal_tolerance, self.human_model.arrival_distance)
        # per human, as the model moving it has them (a mixed crowd: per episode, `set_models`)
        self.arrival_distances = np.full(shape, self.arrival_distance)
        self.interaction_ranges = np.full(shape, float(self.human_model.interaction_range))
        # mixed crowds (humans.mix): which model moves each human, drawn per episode from its noise key
        self.mix = self.human_model if isinstance(self.human_model, MixedHumans) else None
        self.model_index = np.zeros(shape, dtype=np.int64)
        # scripted humans (replay): they enter and leave, the model keeps their script per environment
        self.script = self.human_model if isinstance(self.human_model, ScriptedHumans) else None
        if bool(getattr(self.scenario, "replays_humans", False)) != (self.script is not None):
            raise ConfigError(
                f"scenario {config.scenario!r} with {self.human_model.name} humans: recorded trajectories are "
                "replayed with scenario: replay and humans.model: replay together (humans.replay.files), never one "
                "without the other")
        if self.script is not None:
            self.script.attach(n_envs, self.n_slots)
        self.entered = np.zeros(shape, dtype=bool)  # slots a human entered in the last step (scripted humans)
        # walls (map scenarios, `obstacles`, `map`): one map for every environment; None in the open plane
        polygons = world_polygons(config, self.scenario)
        self.walls = Walls(polygons, n_envs) if polygons else None
        self.occlusion = self.walls is not None and (
            config.occlusion if config.occlusion is not None else bool(getattr(self.scenario, "has_map", False)))
        self.in_sight = np.ones(shape, dtype=bool)  # (E, N): no wall between the robot and each agent
        # the global planner (walls, ``planner.enabled``): humans head for their path's subgoal (`subgoals`) rather
        # than their goal; None in the open plane, with the planner off, and for scripted humans (they walk a script)
        self.human_paths: PathFollower | None = None
        planner = config.planner
        if self.walls is not None and planner.enabled and self.script is None:
            # An intermediate subgoal nearer than a model's arrival distance would stop its human: pushed out.
            reach = max(planner.lookahead, 1.0 + float(self.arrival_distances.max()))
            self.human_paths = PathFollower(planner_for(polygons, config.human_radius + planner.margin),
                                            n_envs * self.n_slots, planner.lookahead, planner.replan_distance,
                                            reach=reach, direct_clearance=config.human_radius)
        self.subgoals = self.goals.copy()  # (E, N, 2): where each human heads this step (its goal without planner)
        # ``planner.observe``: the robot's own path, whose subgoal turns the goal the policy observes (`observe`)
        self.robot_path: PathFollower | None = None
        if self.walls is not None and planner.enabled and planner.observe:
            self.robot_path = PathFollower(planner_for(polygons, config.robot_radius + planner.margin), n_envs,
                                           planner.lookahead, planner.replan_distance,
                                           direct_clearance=config.robot_radius)

    # ---------------------------------------------------------------------------------------------------- seeding

    def seed(self, env: int, seed: int | None) -> None:
        """Give environment `env` a fresh generator (None: OS entropy)."""
        self.rngs[env] = np.random.default_rng(seed)

    # ---------------------------------------------------------------------------------------------------- reset

    def reset(self, envs: np.ndarray | list[int] | None = None) -> None:
        """Start a new episode in each of `envs` (default all), drawn from that environment's own generator."""
        for env in range(self.n_envs) if envs is None else envs:
            rng = self.rngs[env]
            initial = self._placed_episode(rng)
            self.load(env, initial)
            self.noise_keys[env] = np.uint64(rng.integers(0, 2**63))
            self.set_attention(env, draw_attention(self.noise_keys[env], self.n_slots, self.config.inattentive_share))
            if self.mix is not None:
                self.set_models(env, self.mix.draw(self.noise_keys[env], self.n_slots))
            if self.config.initial_heading == "random":
                # Drawn last, so starts, goals and noise are the same episode for either setting.
                self.heading[env] = rng.uniform(-math.pi, math.pi)

    def _placed_episode(self, rng: np.random.Generator) -> InitialState:
        """The scenario's next episode; with walls, redrawn until every start and goal fits among them."""
        initial = self.scenario.sample(rng, 1, self.config)
        if self.walls is None:
            return initial
        for _ in range(MAX_PLACEMENT_DRAWS):
            active = initial.active[0]
            points = np.concatenate([initial.positions[0, active], initial.goals[0, active]])
            radii = np.concatenate([initial.radii[0, active]] * 2)
            reason = self.walls.misplaced(points, radii)
            if reason is None:
                return initial
            initial = self.scenario.sample(rng, 1, self.config)
        raise ConfigError(f"scenario {self.config.scenario!r}: no episode in {MAX_PLACEMENT_DRAWS} draws has every "
                          f"start and goal clear of the walls (last: {reason}); move the obstacles or the map")

    def load(self, env: int, initial: InitialState) -> None:
        """Start environment `env` from a given initial state (its first env), e.g. a staged encounter."""
        cfg = self.config
        self.positions[env] = initial.positions[0]
        self.goals[env] = initial.goals[0]
        self.radii[env] = initial.radii[0]
        self.preferred_speeds[env] = initial.preferred_speeds[0]
        self.max_speeds[env] = initial.preferred_speeds[0]
        self.max_speeds[env, 1:] *= cfg.perturbation.human_speed_factor
        self.personal_space[env] = initial.personal_space_radii[0]
        self.cooperation[env] = initial.cooperation[0]
        self.active[env] = initial.active[0]
        self.heading[env] = initial.robot_heading[0]
        self.velocities[env] = 0.0
        self.time[env] = 0.0
        self.steps[env] = 0
        self.starts[env] = initial.positions[0, 0]
        distance = np.linalg.norm(initial.goals[0, 0] - initial.positions[0, 0])
        self.time_limit[env] = cfg.timeout_factor * distance / initial.preferred_speeds[0, 0] + cfg.timeout_margin
        # How each human sees the robot: bigger by its personal space, its own share of avoidance, or not at all.
        self.radius_pad[env] = 0.0
        self.radius_pad[env, :, 0] = self.personal_space[env]
        self.avoidance_share[env] = 0.5
        self.avoidance_share[env, :, 0] = self.cooperation[env]
        self.sees[env] = True
        if self.walls is not None:
            self.in_sight[env] = self.walls.in_sight_of_robot(self.positions[env:env + 1], self.active[env:env + 1])[0]
        self.set_attention(env, np.ones(self.n_slots, dtype=bool))
        self.was_intruded[env] = False
        self.episode_return[env] = 0.0
        self.path_length[env] = 0.0
        self.min_gap[env] = np.inf
        self.intrusion_steps[env] = 0
        self.intrusion_events[env] = 0
        self.disturbance[env] = 0.0
        self.wall_collision[env] = False
        if self.mix is not None:
            self.set_models(env, np.zeros(self.n_slots, dtype=np.int64))
        self.entered[env] = False
        self.subgoals[env] = self.goals[env]
        if self.human_paths is not None:  # a new episode: no path of the last one is reused
            self.human_paths.forget(slice(env * self.n_slots, (env + 1) * self.n_slots))
        if self.robot_path is not None:
            self.robot_path.forget(slice(env, env + 1))
        if self.script is not None:
            if not initial.script:
                raise ValueError(f"{self.human_model.name} humans start from their scenario's script: load an "
                                 f"initial state of scenario {self.config.scenario!r}")
            self.script.start_episode(env, initial.script[0], self.positions, self.velocities, self.goals,
                                      self.active)

    def set_models(self, env: int, index: np.ndarray) -> None:
        """Which model of the mix moves each human of environment `env` (indices into ``human_model.models``).

        `reset` draws this (after `load`); call it after `load` to stage a mixed scene.
        """
        mix = self.mix
        if mix is None:
            raise ValueError(f"set_models stages a mixed crowd; these humans are {self.human_model.name!r}, not a "
                             "mix (humans.mix)")
        self.model_index[env] = index
        self.interaction_ranges[env] = mix.ranges[self.model_index[env]]
        arrival = mix.arrival_distances[self.model_index[env]]
        self.arrival_distances[env] = np.maximum(self.config.goal_tolerance, arrival)

    def human_model_names(self, env: int) -> list[str]:
        """The name of the model moving each slot of environment `env` (slot 0, the robot, included)."""
        if self.mix is not None:
            return [self.mix.names[k] for k in self.model_index[env]]
        return [self.human_model.name] * self.n_slots

    def set_attention(self, env: int, attentive: np.ndarray) -> None:
        """Make the humans of environment `env` attentive (True) or not (False) to the robot for this episode.

        `reset` draws this; call it after `load` to stage a scene. With a field of view, no human has noticed the
        robot yet: the first step's view check decides.
        """
        self.attentive[env] = attentive
        self.attentive[env, 0] = True
        self.noticed[env] = not self.has_field_of_view
        self._update_robot_visibility(env)

    def _update_robot_visibility(self, env: int | slice = slice(None)) -> None:
        """Which humans plan around the robot: visible robot, attentive human, robot noticed (field of view)."""
        self.sees[env, :, 0] = (self.config.robot_visible & self.attentive[env] & self.noticed[env]
                                & self.in_sight[env])

    # ---------------------------------------------------------------------------------------------------- step

    def crowd(self, without_robot: bool = False) -> Crowd:
        """The world's arrays as the human model reads them (views); `without_robot`: no human sees the robot. With
        the global planner, a human's goal is this step's subgoal on its path (`steer_humans`)."""
        return Crowd(
            positions=self.positions, velocities=self.velocities,
            goals=self.goals if self.human_paths is None else self.subgoals, radii=self.radii,
            max_speeds=self.max_speeds, active=self.active, radius_pad=self.radius_pad,
            avoidance_share=self.avoidance_share, sees=self.sees_without_robot if without_robot else self.sees,
            model_index=self.model_index, obstacles=None if self.walls is None else self.walls.obstacles,
            wall_segments=None if self.walls is None else (self.walls.seg_start, self.walls.seg_end,
                                                           self.walls.n_segments),
        )

    def human_velocities(self, without_robot: bool = False, only: np.ndarray | None = None) -> np.ndarray:
        """The human model's velocities of all humans this step (optionally as if the robot were absent, for `only`
        some); the others keep their current velocity."""
        compute = self.active & self.humans_slots if only is None else only
        return self.human_model.velocities(self.crowd(without_robot), compute)

    def unhindered_velocities(self, humans: np.ndarray, near: np.ndarray) -> np.ndarray:
        """The velocities the `near` humans would take this step had the robot not been there (`v_i^0` of the
        disturbance term); `humans` are this step's velocities with the robot.

        Every human model gives a human who does not see the robot (``sees[e, i, 0]`` False) the same velocity with
        or without it, bit for bit (the robot adds no neighbour, line or force), so only those who see it are
        computed again."""
        seeing = near & self.sees[:, :, 0]
        if not seeing.any():
            return humans
        return np.where(seeing[:, :, None], self.human_velocities(without_robot=True, only=seeing), humans)

    def step(self, actions: np.ndarray) -> StepResult:
        """Advance every environment by one step with the robot actions `actions` in [-1, 1]^2, shape (E, 2)."""
        cfg, pert, rew = self.config, self.config.perturbation, self.config.reward
        actions = np.asarray(actions, dtype=np.float64).reshape(self.n_envs, 2)
        if self.script is not None:  # humans whose script ends leave before the move (their slots turn inactive)
            self.was_intruded[self.script.before_move(self.active, self.velocities)] = False
        speed, turn = robot_command_batch(
            actions, self.preferred_speeds[:, 0], cfg.max_heading_change, self.noise_keys, self.steps,
            pert.heading_noise, pert.speed_noise,
        )
        if self.has_field_of_view:
            notice_robot(self.positions, self.velocities, self.goals, self.active, self.facing, self.noticed,
                          self.cos_half_fov, self.interaction_ranges, self.in_sight)
            self._update_robot_visibility()
        elif self.walls is not None:
            self._update_robot_visibility()
        if self.human_paths is not None:
            self.steer_humans()
        humans = self.human_velocities()
        near = self.humans_near_robot(rew.social_radius)
        unhindered = self.unhindered_velocities(humans, near) if rew.disturbance > 0.0 and near.any() else humans
        if self.metrics is not None:
            self.metrics.before_step(self)
        robot_before = self.positions[:, 0].copy() if self.walls is not None else None
        reward, outcome, nearest_gap, nearest_speed, intrusions = advance_and_score(
            self.positions, self.velocities, self.radii, self.goals, self.max_speeds, self.personal_space,
            self.active, self.heading, self.time, self.time_limit,
            speed, turn, humans, unhindered, near,
            cfg.time_step, cfg.goal_tolerance, reward_weights(rew),
            self.was_intruded, self.episode_return, self.path_length, self.min_gap, self.intrusion_steps,
            self.intrusion_events, self.disturbance,
        )
        if self.walls is not None and robot_before is not None:
            self._end_at_walls(self.walls, robot_before, outcome, reward)
        if self.metrics is not None:
            self.metrics.after_step(self)
        self.steps += 1
        if self.script is not None:  # on the script's positions; humans whose script starts enter
            self.entered = self.script.after_move(self.positions, self.velocities, self.goals, self.active)
            self.was_intruded[self.entered] = False
        if self.scenario.redraw_goals:
            self._redraw_reached_goals()
        if self.walls is not None:  # who the robot sees now: its observation, and the humans' next step
            self.in_sight = self.walls.in_sight_of_robot(self.positions, self.active)
        return StepResult(
            reward=reward,
            terminated=(outcome == OUTCOME_GOAL) | (outcome == OUTCOME_COLLISION) | (outcome == OUTCOME_COLLISION_WALL),
            truncated=outcome == OUTCOME_TIMEOUT,
            outcome=outcome,
            nearest_gap=nearest_gap,
            nearest_relative_speed=nearest_speed,
            intrusions=intrusions,
        )

    def steer_humans(self) -> None:
        """This step's subgoal of every active human (`subgoals`), from the global planner (`human_paths`): the goal
        itself where the straight line to it keeps the human's radius from every wall, else a point along its path
        around the walls (re-planned only when the human strayed from its path, lost sight of it, or got a new
        goal)."""
        paths = self.human_paths
        if paths is None:
            return
        asked = (self.active & self.humans_slots).ravel()
        paths.update(self.positions.reshape(-1, 2), self.goals.reshape(-1, 2), asked, out=self.subgoals.reshape(-1, 2))

    def _end_at_walls(self, walls: Walls, robot_before: np.ndarray, outcome: np.ndarray, reward: np.ndarray) -> None:
        """A robot whose disc touched a wall during the step (swept, like a collision with a human) ends its episode
        with `OUTCOME_COLLISION_WALL` and the collision penalty instead of the step's goal bonus; a collision with a
        human in the same step is counted as that. Updates `outcome`, `reward` and the episode return in place."""
        hit = walls.robot_hit(robot_before, self.positions[:, 0], self.radii[:, 0])
        hit &= outcome != OUTCOME_COLLISION
        if not hit.any():
            return
        rew = self.config.reward
        correction = -rew.collision - np.where(outcome == OUTCOME_GOAL, rew.goal, 0.0)
        reward[hit] += correction[hit]
        self.episode_return[hit] += correction[hit]
        outcome[hit] = OUTCOME_COLLISION_WALL
        self.wall_collision[hit] = True

    def humans_near_robot(self, radius: float) -> np.ndarray:
        """(E, N) bool: the active humans whose gap to the robot is below `radius` (those the disturbance term
        scores, with ``reward.social_radius``)."""
        return humans_within(self.positions, self.radii, self.active, radius)

    def _redraw_reached_goals(self) -> None:
        reached = self.active & self.humans_slots
        reached &= np.linalg.norm(self.goals - self.positions, axis=-1) < self.arrival_distances
        scenario = self.scenario
        for env, agent in zip(*np.nonzero(reached), strict=True):
            if isinstance(scenario, RoutedScenario):  # map scenarios: the next leg of a route after the goal reached
                self.goals[env, agent] = scenario.next_goal(self.rngs[env], self.config, self.goals[env, agent])
            elif isinstance(scenario, GoalRedrawingScenario):
                self.goals[env, agent] = scenario.goal_for(self.rngs[env], self.config, self.positions[env, agent])
            else:
                raise TypeError(f"scenario {scenario.name!r} redraws goals (redraw_goals) but has neither next_goal "
                                "nor goal_for")

    # ---------------------------------------------------------------------------------------------------- observe

    def observe(self, envs: np.ndarray | None = None, noisy: bool = True) -> dict[str, np.ndarray]:
        """The policy's observation of every environment (or of `envs` only, in that order; docs/world.md),
        perturbed by observation noise if set; `noisy=False`: the same observation without the noise (the true
        state, as a separate safety sensor reads it; same row order, since rows are sorted before the noise)."""
        if envs is None:
            positions, velocities, radii, goals = self.positions, self.velocities, self.radii, self.goals
            speeds, active, heading, keys, steps = (self.preferred_speeds[:, 0], self.active, self.heading,
                                                    self.noise_keys, self.steps)
        else:
            envs = np.asarray(envs, dtype=np.int64)
            positions, velocities, radii, goals = (self.positions[envs], self.velocities[envs], self.radii[envs],
                                                   self.goals[envs])
            speeds, active, heading, keys, steps = (self.preferred_speeds[envs, 0], self.active[envs],
                                                    self.heading[envs], self.noise_keys[envs], self.steps[envs])
        if self.occlusion:  # a human behind a wall is absent, exactly as one out of range
            active = active & (self.in_sight if envs is None else self.in_sight[envs])
        if self.robot_path is not None:
            goals = goals.copy()
            goals[:, 0] = self.route_goals(envs)
        robot, humans, mask = observe_batch(positions, velocities, radii, goals, speeds, active, heading,
                                            self.config.max_humans)
        if noisy and self.config.perturbation.observation_noise > 0.0:
            add_observation_noise(robot, humans, mask, keys, steps, self.config.perturbation.observation_noise)
        observation = {"robot": robot, "humans": humans, "humans_mask": mask}
        if self.walls is not None:  # where the robot is on the map (a localised robot: x, y, yaw in the map frame)
            observation[POSE_KEY] = np.concatenate([positions[:, 0], heading[:, None]], axis=1).astype(np.float32)
        if self.config.scan is not None:
            observation[SCAN_KEY] = self.range_scan(envs)
        return observation

    def range_scan(self, envs: np.ndarray | None = None) -> np.ndarray:
        """The robot's range scan ((E, beams) float32, or of `envs`): the walls' ranges (the full range in the open
        plane) and, with ``scan.people``, the humans' bodies in its line of sight, whatever the occlusion of the
        humans' observation (a lidar sees whom it sees)."""
        scan = self.config.scan
        assert scan is not None
        rows = slice(None) if envs is None else np.asarray(envs, dtype=np.int64)
        origins, heading = self.positions[rows, 0], self.heading[rows]
        circles = None
        if scan.people:
            circles = (self.positions[rows, 1:], self.radii[rows, 1:], self.active[rows, 1:])
        if self.walls is not None:
            return self.walls.scan(origins, heading, scan.beams, scan.range, scan.fov, circles=circles)
        if circles is None:
            return np.full((len(origins), scan.beams), scan.range, dtype=np.float32)
        fov = 2.0 * math.pi if scan.fov >= 360.0 else math.radians(scan.fov)
        no_walls = np.zeros((len(origins), 0, 2))
        return range_scan(origins, heading, no_walls, no_walls, np.zeros(len(origins), dtype=np.int64), scan.beams,
                          scan.range, fov, circles=circles).astype(np.float32)

    def route_goals(self, envs: np.ndarray | None = None) -> np.ndarray:
        """The goal the robot observes with ``planner.observe`` ((E, 2), or of `envs`): at the distance of its goal,
        in the direction of its path's subgoal (DRL-VO's sub-goal from the global planner; the goal itself where the
        straight line to it is clear), so the observation's layout and the goal's distance stay those of the open
        plane."""
        assert self.robot_path is not None
        asked = np.ones(self.n_envs, dtype=bool)
        if envs is not None:
            asked[:] = False
            asked[envs] = True
        positions, goals = self.positions[:, 0], self.goals[:, 0]
        subgoals, _ = self.robot_path.update(positions, goals, asked)
        rows = slice(None) if envs is None else envs
        return observed_goals(positions[rows], subgoals[rows], goals[rows])

    def episode_summary(self, env: int, outcome: int) -> dict[str, float | int | str]:
        """End-of-episode metrics of environment `env` (call before it is reset); with ``metrics=True`` followed by
        the columns `socnav.sim.metrics.METRIC_RECORD_COLUMNS`."""
        time = float(self.time[env])
        name = OUTCOME_NAMES.get(int(outcome), "running")
        extended = {} if self.metrics is None else self.metrics.summary(self, env, name)
        return {
            "outcome": name,
            "return": float(self.episode_return[env]),
            "length": int(self.steps[env]),
            "duration": time,
            "path_length": float(self.path_length[env]),
            "time_to_goal": time if outcome == OUTCOME_GOAL else float("nan"),
            "min_gap": float(self.min_gap[env]),
            "intrusion_steps": int(self.intrusion_steps[env]),
            "intrusion_events": int(self.intrusion_events[env]),
            "disturbance": float(self.disturbance[env]),
            **extended,
        }

