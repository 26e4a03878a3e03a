"""Scenarios: where the robot and the humans start and go, and their hidden social traits (the initial state
distribution T_0 of the paper's POMDP, Sec. III-A; the scenarios of its experimental setup, Sec. V-A).

Each scenario is a small registered object with `sample(rng, n_envs, config) -> InitialState`; add your own with
`register_scenario` (docs/world.md). The sampling steps every scenario shares are public here: `draw_humans_count`,
`fill_traits`, `far_enough` and `face_goal`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

MIN_START_SEPARATION = 1.0  # metres between any two starts (and any two goals) when a scenario samples them


@dataclass
class InitialState:
    """Initial world of `n_envs` episodes; agent slot 0 is the robot, slots 1.. humans (inactive slots padded).

    Arrays have shape (n_envs, n_slots[, 2]); `n_slots = 1 + the most humans the config allows`.
    """

    positions: np.ndarray
    goals: np.ndarray
    radii: np.ndarray
    preferred_speeds: np.ndarray
    personal_space_radii: np.ndarray  # 0 for the robot
    cooperation: np.ndarray  # share of avoidance each human takes w.r.t. the robot; 0 for the robot
    active: np.ndarray  # bool
    robot_heading: np.ndarray  # (n_envs,)
    #: per environment, the plan that scripted humans follow (`socnav.sim.humans.ScriptedHumans`; the replay
    #: scenario's `socnav.sim.humans.replay.ReplayStart`); None where the human model moves them from this state
    script: list[Any] | None = None

    @classmethod
    def empty(cls, n_envs: int, n_slots: int) -> InitialState:
        zeros = lambda *shape: np.zeros((n_envs, n_slots, *shape))  # noqa: E731
        return cls(
            positions=zeros(2),
            goals=zeros(2),
            radii=zeros(),
            preferred_speeds=zeros(),
            personal_space_radii=zeros(),
            cooperation=zeros(),
            active=np.zeros((n_envs, n_slots), dtype=bool),
            robot_heading=np.zeros(n_envs),
        )


class ScenarioSettings(Protocol):
    """The values of a world's config that scenarios read; `socnav.config.EnvConfig` provides them. sim/ sees these
    plain values and never imports the config layer (which imports sim/ for the scenario names)."""

    robot_radius: float
    human_radius: float
    preferred_speed: tuple[float, float]  # U[min, max] m/s, every agent
    personal_space: tuple[float, float]
    cooperation: tuple[float, float]
    circle_radius: float
    circle_jitter: float
    swap_jitter: float
    square_size: float
    perturbation: Any  # circle_interaction reads perturbation.human_speed_factor
    humans: Any  # replay reads humans.replay (files, robot_distance)
    time_step: float  # replay: its time windows and time grid
    timeout_factor: float
    timeout_margin: float
    layout: Any  # the map scenarios' geometry (corridor_width, corridor_length, door_width, room_size)

    def humans_range(self) -> tuple[int, int]: ...


class Scenario(Protocol):
    """What a scenario provides (read-only, so that frozen dataclasses qualify). `redraw_goals` is True when humans
    draw a new goal on arrival: the scenario then also provides `RoutedScenario.next_goal` or
    `GoalRedrawingScenario.goal_for`."""

    @property
    def name(self) -> str: ...

    @property
    def default_humans(self) -> int | tuple[int, int]: ...

    @property
    def redraw_goals(self) -> bool: ...

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState: ...


@runtime_checkable
class RoutedScenario(Protocol):
    """A scenario whose humans walk a route (the map scenarios): the next goal follows from the goal reached."""

    def next_goal(self, rng: np.random.Generator, config: ScenarioSettings, reached: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class GoalRedrawingScenario(Protocol):
    """A scenario whose humans draw a fresh goal on arrival, from where they stand (``random``)."""

    def goal_for(self, rng: np.random.Generator, config: ScenarioSettings, start: np.ndarray,
                 taken: list[np.ndarray] | None = None) -> np.ndarray: ...


@runtime_checkable
class FixedRouteScenario(Protocol):
    """A scenario whose robot starts and ends at points the config fixes (the circle scenarios' four diameters):
    the config check knows them before any episode (`socnav.config.EnvConfig`: reachable among the walls)."""

    def robot_routes(self, config: ScenarioSettings) -> list[tuple[np.ndarray, np.ndarray]]: ...


_REGISTRY: dict[str, Scenario] = {}


def register_scenario(scenario: Scenario) -> Scenario:
    """Register a scenario object under `scenario.name` (replacing one of the same name)."""
    _REGISTRY[scenario.name] = scenario
    return scenario


def get_scenario(name: str) -> Scenario:
    """The registered scenario `name` (KeyError listing the registered names)."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown scenario {name!r}; registered: {', '.join(scenario_names())}") from None


def scenario_names(self_contained: bool = False) -> list[str]:
    """The registered scenario names, sorted; `self_contained`: only those that run without data of their own (all
    but ``replay``, which needs recorded trajectory files), e.g. to try every scenario in its default world."""
    return sorted(name for name, scenario in _REGISTRY.items()
                  if not (self_contained and getattr(scenario, "replays_humans", False)))


def n_slots(config: ScenarioSettings) -> int:
    """Agent slots of the simulation: the robot plus the most humans an episode of this config can have."""
    return 1 + config.humans_range()[1]


# --------------------------------------------------------------------------------------------------------------
# Shared sampling steps


def draw_humans_count(rng: np.random.Generator, config: ScenarioSettings) -> int:
    """The number of humans of one episode, uniform over the config's inclusive range (one draw of `rng`)."""
    low, high = config.humans_range()
    return int(rng.integers(low, high + 1))


def fill_traits(state: InitialState, env: int, n_humans: int, rng: np.random.Generator,
                config: ScenarioSettings) -> None:
    """Mark environment `env`'s robot and `n_humans` humans active and draw their traits from `rng`, in this order:
    every agent's preferred speed v_pref ~ U[preferred_speed], each human's personal space r_prox ~ U[personal_space]
    and cooperation ~ U[cooperation]; radii are the config's (the hidden state of the paper's Sec. III-A)."""
    agents = 1 + n_humans
    state.active[env, :agents] = True
    state.radii[env, 0] = config.robot_radius
    state.radii[env, 1:agents] = config.human_radius
    state.preferred_speeds[env, :agents] = rng.uniform(*config.preferred_speed, size=agents)
    state.personal_space_radii[env, 1:agents] = rng.uniform(*config.personal_space, size=n_humans)
    state.cooperation[env, 1:agents] = rng.uniform(*config.cooperation, size=n_humans)


def _unit(angle: float) -> np.ndarray:
    # math on Python floats: resets run once per episode per env, and numpy's per-call overhead dominated them.
    return np.array((math.cos(angle), math.sin(angle)))


def far_enough(point: np.ndarray, others: list[np.ndarray], separation: float) -> bool:
    """Whether `point` lies at least `separation` metres from every point of `others` (True when there are none)."""
    x, y = float(point[0]), float(point[1])
    return all(math.hypot(x - float(other[0]), y - float(other[1])) >= separation for other in others)


def face_goal(state: InitialState, env: int) -> None:
    """Turn environment `env`'s robot towards its goal (its heading before `initial_heading` applies)."""
    offset = state.goals[env, 0] - state.positions[env, 0]
    state.robot_heading[env] = np.arctan2(offset[1], offset[0])


ROBOT_CROSSING_ANGLES = np.deg2rad([0.0, 90.0, 180.0, 270.0])
MAX_TRIES = 200


def crossing_routes(config: ScenarioSettings) -> list[tuple[np.ndarray, np.ndarray]]:
    """The robot's four fixed (start, goal) pairs of the circle scenarios: the diameters at
    `ROBOT_CROSSING_ANGLES`, from ``circle_radius`` to its antipode."""
    return [(config.circle_radius * _unit(angle), -config.circle_radius * _unit(angle))
            for angle in ROBOT_CROSSING_ANGLES]


# --------------------------------------------------------------------------------------------------------------
# The four scenarios of the paper


@dataclass(frozen=True)
class PositionSwap:
    """Robot and humans start on a circle at independent random angles and swap to their antipodes."""

    name: str = "position_swap"
    default_humans: int | tuple[int, int] = 1
    redraw_goals: bool = False

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            starts: list[np.ndarray] = []
            for agent in range(1 + n_humans):
                for _ in range(MAX_TRIES):
                    angle = rng.uniform(0.0, 2 * np.pi)
                    start = config.circle_radius * _unit(angle) + rng.normal(0.0, config.swap_jitter, 2)
                    goal = -config.circle_radius * _unit(angle) + rng.normal(0.0, config.swap_jitter, 2)
                    if far_enough(start, starts, MIN_START_SEPARATION):
                        break
                starts.append(start)
                state.positions[env, agent] = start
                state.goals[env, agent] = goal
            face_goal(state, env)
        return state


@dataclass(frozen=True)
class CircleCrossing:
    """Humans on a circle (random angles, jittered) cross to their antipodes; the robot takes one of four fixed
    diameters."""

    name: str = "circle_crossing"
    default_humans: int | tuple[int, int] = 5
    redraw_goals: bool = False

    def robot_routes(self, config: ScenarioSettings) -> list[tuple[np.ndarray, np.ndarray]]:
        """The robot's start and goal of every episode: one of the four `crossing_routes`."""
        return crossing_routes(config)

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        radius, jitter = config.circle_radius, config.circle_jitter
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            robot_angle = rng.choice(ROBOT_CROSSING_ANGLES)
            state.positions[env, 0] = radius * _unit(robot_angle)
            state.goals[env, 0] = -radius * _unit(robot_angle)
            starts, goals = [state.positions[env, 0]], [state.goals[env, 0]]
            for human in range(1, 1 + n_humans):
                for _ in range(MAX_TRIES):
                    angle = rng.uniform(0.0, 2 * np.pi)
                    start = radius * _unit(angle) + rng.uniform(-jitter, jitter, 2)
                    goal = -radius * _unit(angle) + rng.uniform(-jitter, jitter, 2)
                    if (far_enough(start, starts, MIN_START_SEPARATION)
                            and far_enough(goal, goals, MIN_START_SEPARATION)):
                        break
                starts.append(start)
                goals.append(goal)
                state.positions[env, human] = start
                state.goals[env, human] = goal
            face_goal(state, env)
        return state


@dataclass(frozen=True)
class CircleInteraction:
    """Staged interaction: each human is placed to reach the circle's centre when the robot does, from a random
    direction."""

    name: str = "circle_interaction"
    default_humans: int | tuple[int, int] = (1, 3)
    redraw_goals: bool = False
    arrival_spread: float = 0.15  # relative spread of the humans' arrival times, so they do not all meet at once

    def robot_routes(self, config: ScenarioSettings) -> list[tuple[np.ndarray, np.ndarray]]:
        """The robot's start and goal of every episode: one of the four `crossing_routes`."""
        return crossing_routes(config)

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        radius = config.circle_radius
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            robot_angle = rng.choice(ROBOT_CROSSING_ANGLES)
            state.positions[env, 0] = radius * _unit(robot_angle)
            state.goals[env, 0] = -radius * _unit(robot_angle)
            robot_time_to_centre = radius / state.preferred_speeds[env, 0]
            starts = [state.positions[env, 0]]
            for human in range(1, 1 + n_humans):
                speed = state.preferred_speeds[env, human] * config.perturbation.human_speed_factor
                for _ in range(MAX_TRIES):
                    angle = rng.uniform(0.0, 2 * np.pi)
                    arrival = robot_time_to_centre * (1.0 + rng.uniform(-self.arrival_spread, self.arrival_spread))
                    start = speed * arrival * _unit(angle)
                    if far_enough(start, starts, MIN_START_SEPARATION):
                        break
                starts.append(start)
                state.positions[env, human] = start
                state.goals[env, human] = -start  # through the centre, as far beyond it as it started
            face_goal(state, env)
        return state


@dataclass(frozen=True)
class RandomSquare:
    """Starts and goals uniform in a square, >= 1 m apart, goals >= 4 m from starts; humans redraw goals on arrival."""

    name: str = "random"
    default_humans: int | tuple[int, int] = 5
    redraw_goals: bool = True
    min_goal_distance: float = 4.0

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            starts: list[np.ndarray] = []
            goals: list[np.ndarray] = []
            for agent in range(1 + n_humans):
                start = self._point(rng, config, starts)
                goal = self.goal_for(rng, config, start, goals)
                starts.append(start)
                goals.append(goal)
                state.positions[env, agent] = start
                state.goals[env, agent] = goal
            face_goal(state, env)
        return state

    def _point(self, rng: np.random.Generator, config: ScenarioSettings, taken: list[np.ndarray]) -> np.ndarray:
        half = config.square_size / 2
        for _ in range(MAX_TRIES):
            point = rng.uniform(-half, half, 2)
            if far_enough(point, taken, MIN_START_SEPARATION):
                return point
        return point

    def goal_for(
        self, rng: np.random.Generator, config: ScenarioSettings, start: np.ndarray,
        taken: list[np.ndarray] | None = None,
    ) -> np.ndarray:
        """A goal at least `min_goal_distance` from `start` (and 1 m from goals in `taken`)."""
        half = config.square_size / 2
        for _ in range(MAX_TRIES):
            goal = rng.uniform(-half, half, 2)
            if (np.linalg.norm(goal - start) >= self.min_goal_distance
                    and far_enough(goal, taken or [], MIN_START_SEPARATION)):
                return goal
        return goal


# --------------------------------------------------------------------------------------------------------------
# Recorded pedestrians


@dataclass(frozen=True)
class Replay:
    """Recorded pedestrians (``humans.model: replay``, files in ``humans.replay.files``) walk their recorded tracks;
    the robot crosses the scene through its centre.

    Per episode, from the episode's generator: the agents' traits, a file (weighted by its length), a time window
    (its start drawn so that the episode's time limit fits in the recording where the file is long enough) and the
    robot's direction; start and goal lie ``humans.replay.robot_distance`` apart on a line through the centre of the
    file's bounding box (the world's origin), redrawn until the start is clear of the pedestrians present then.
    There are ``n_humans`` (default 10; the upper bound of a range) slots for humans: the pedestrians present at the
    start closest to the robot's path take them, later ones take the slots left free in the order they appear
    (`socnav.sim.humans.replay`). `scenes`, `plan` and the slots' kernels are in that module.
    """

    name: str = "replay"
    default_humans: int | tuple[int, int] = 10
    redraw_goals: bool = False
    replays_humans: bool = True  # needs a `ScriptedHumans` model (humans.model: replay)

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        from socnav.sim.humans.replay import load_replay

        settings = config.humans.replay
        scenes = load_replay(settings, config.time_step)
        slots = n_slots(config)
        state = InitialState.empty(n_envs, slots)
        state.script = []
        for env in range(n_envs):
            fill_traits(state, env, slots - 1, rng, config)
            time_limit = (config.timeout_factor * settings.robot_distance / state.preferred_speeds[env, 0]
                          + config.timeout_margin)
            plan = scenes.plan(rng, slots - 1, settings.robot_distance, math.ceil(time_limit / config.time_step))
            state.positions[env, 0], state.goals[env, 0] = plan.start, plan.goal
            state.active[env, 1:] = plan.pedestrians[1:] >= 0
            state.positions[env, 1:], state.goals[env, 1:] = plan.positions[1:], plan.goals[1:]
            face_goal(state, env)
            state.script.append(plan)
        return state


for _scenario in (PositionSwap(), CircleCrossing(), CircleInteraction(), RandomSquare(), Replay()):
    register_scenario(_scenario)

