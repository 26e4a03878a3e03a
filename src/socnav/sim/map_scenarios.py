"""Scenarios with walls: a corridor, a doorway between two rooms, a crossing of two corridors and a furnished room.

Each builds its walls from the config's ``layout`` section (`static_map`, polygons in RVO2's convention) and places
starts and goals in free space so that every straight path an agent is sent along stays clear of the walls, as
RVO2's own examples do without a roadmap: with the global planner off (``planner.enabled: false``) the humans and the
ORCA robot steer locally along these straight legs; with it on (the default) they head straight wherever the leg is
clear, and follow a planned path (`socnav.sim.planning`) where it is not.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from socnav.sim.scenarios import (
    MAX_TRIES,
    MIN_START_SEPARATION,
    InitialState,
    ScenarioSettings,
    crossing_routes,
    draw_humans_count,
    face_goal,
    far_enough,
    fill_traits,
    n_slots,
    register_scenario,
)

#: metres between a wall and a start or goal (a body radius and a margin)
WALL_CLEARANCE = 0.6


def segment(a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    """A wall segment: RVO2's two-vertex obstacle."""
    return np.array([a, b], dtype=np.float64)


def box(x_min: float, y_min: float, x_max: float, y_max: float) -> np.ndarray:
    """A solid rectangle, vertices counter-clockwise (RVO2's convention for a solid obstacle)."""
    return np.array([(x_min, y_min), (x_max, y_min), (x_max, y_max), (x_min, y_max)], dtype=np.float64)


def _lateral(rng: np.random.Generator, half_width: float) -> float:
    """A lateral offset that keeps a body clear of both walls of a lane of half-width `half_width`."""
    room = max(0.0, half_width - WALL_CLEARANCE)
    return float(rng.uniform(-room, room))


def _place_humans(state: InitialState, env: int, n_humans: int, rng: np.random.Generator,
                  draw: Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]) -> None:
    """Start and goal of each human from `draw(rng) -> (start, goal)`, starts and goals >= 1 m from the others'."""
    starts, goals = [state.positions[env, 0]], [state.goals[env, 0]]
    for human in range(1, 1 + n_humans):
        for _ in range(MAX_TRIES):
            start, goal = draw(rng)
            if far_enough(start, starts, MIN_START_SEPARATION) and far_enough(goal, goals, MIN_START_SEPARATION):
                break
        starts.append(start)
        goals.append(goal)
        state.positions[env, human] = start
        state.goals[env, human] = goal


@dataclass(frozen=True)
class Corridor:
    """Two-way flow in a straight corridor along x (``layout.corridor_width`` x ``layout.corridor_length``).

    The robot walks from one end to the other; each human walks towards one end (either, drawn per human) and turns
    back on arrival, so the flow keeps coming both ways. The ends are open: every goal lies inside the corridor.
    """

    name: str = "corridor"
    default_humans: int | tuple[int, int] = 6
    redraw_goals: bool = True
    has_map: bool = True

    def static_map(self, config: ScenarioSettings) -> list[np.ndarray]:
        half_length, half_width = config.layout.corridor_length / 2, config.layout.corridor_width / 2
        return [segment((-half_length, -half_width), (half_length, -half_width)),
                segment((half_length, half_width), (-half_length, half_width))]

    def _end(self, config: ScenarioSettings) -> float:
        return config.layout.corridor_length / 2 - 1.0

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        end, half_width = self._end(config), config.layout.corridor_width / 2
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            side = float(rng.choice((-1.0, 1.0)))
            state.positions[env, 0] = (side * end, _lateral(rng, half_width))
            state.goals[env, 0] = (-side * end, _lateral(rng, half_width))

            def draw(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
                heading = float(rng.choice((-1.0, 1.0)))
                start = np.array((rng.uniform(-end, end), _lateral(rng, half_width)))
                return start, np.array((heading * end, _lateral(rng, half_width)))

            _place_humans(state, env, n_humans, rng, draw)
            face_goal(state, env)
        return state

    def next_goal(self, rng: np.random.Generator, config: ScenarioSettings, reached: np.ndarray) -> np.ndarray:
        """The other end of the corridor from the goal just reached."""
        side = -1.0 if reached[0] > 0 else 1.0
        return np.array((side * self._end(config), _lateral(rng, config.layout.corridor_width / 2)))


@dataclass(frozen=True)
class Doorway:
    """Two square rooms (``layout.room_size``) side by side, joined by a door (``layout.door_width``) in the wall
    between them at x = 0. People cross both ways through a route of three legs: to a point in front of the door,
    through it to a point behind it, then to a random point of the other room; the robot starts and ends on the
    door's axis, so its straight path goes through the door."""

    name: str = "doorway"
    default_humans: int | tuple[int, int] = 6
    redraw_goals: bool = True
    has_map: bool = True
    #: metres from the door plane: a route's point in front of the door (approach) and behind it (exit)
    approach: float = 0.8
    exit: float = 1.4

    def static_map(self, config: ScenarioSettings) -> list[np.ndarray]:
        size, half_door = config.layout.room_size, config.layout.door_width / 2
        half = size / 2
        return [segment((-size, -half), (size, -half)), segment((size, -half), (size, half)),
                segment((size, half), (-size, half)), segment((-size, half), (-size, -half)),
                segment((0.0, -half), (0.0, -half_door)), segment((0.0, half_door), (0.0, half))]

    def _room_point(self, rng: np.random.Generator, config: ScenarioSettings, side: float) -> np.ndarray:
        """A random point of the room on `side` (-1 left, +1 right), clear of the walls and of the door's route."""
        size, inner = config.layout.room_size, config.layout.room_size / 2 - WALL_CLEARANCE
        return np.array((side * rng.uniform(self.exit + 0.6, size - WALL_CLEARANCE), rng.uniform(-inner, inner)))

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        size = config.layout.room_size
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            side = float(rng.choice((-1.0, 1.0)))
            jitter = 0.1 * config.layout.door_width
            state.positions[env, 0] = (side * (size - 1.0), rng.uniform(-jitter, jitter))
            state.goals[env, 0] = (-side * (size - 1.0), rng.uniform(-jitter, jitter))

            def draw(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
                room = float(rng.choice((-1.0, 1.0)))
                return self._room_point(rng, config, room), np.array((room * self.approach, 0.0))

            _place_humans(state, env, n_humans, rng, draw)
            face_goal(state, env)
        return state

    def next_goal(self, rng: np.random.Generator, config: ScenarioSettings, reached: np.ndarray) -> np.ndarray:
        """The route's next point after the goal just reached: in front of the door -> behind it -> a point of that
        room -> in front of the door again (from that side)."""
        x, y = float(reached[0]), float(reached[1])
        side = 1.0 if x > 0 else -1.0
        if y == 0.0 and abs(x) == self.approach:
            return np.array((-side * self.exit, 0.0))  # in front of the door: go through it
        if y == 0.0 and abs(x) == self.exit:
            return self._room_point(rng, config, side)  # behind the door: into the room
        return np.array((side * self.approach, 0.0))  # in a room: back to the door


@dataclass(frozen=True)
class Intersection:
    """Two corridors (``layout.corridor_width`` wide, arms ``layout.corridor_length / 2`` long) crossing at the
    origin; the four corners are solid blocks that hide the people of one arm from those of the next. The robot and
    each human walk from one arm straight across to the opposite arm (humans turn back on arrival)."""

    name: str = "intersection"
    default_humans: int | tuple[int, int] = 6
    redraw_goals: bool = True
    has_map: bool = True

    def static_map(self, config: ScenarioSettings) -> list[np.ndarray]:
        arm, half_width = config.layout.corridor_length / 2, config.layout.corridor_width / 2
        return [box(half_width, half_width, arm, arm), box(-arm, half_width, -half_width, arm),
                box(-arm, -arm, -half_width, -half_width), box(half_width, -arm, arm, -half_width)]

    def _arm_point(self, rng: np.random.Generator, config: ScenarioSettings, direction: int,
                   along: float) -> np.ndarray:
        """A point `along` metres out on arm `direction` (0 east, 1 north, 2 west, 3 south), jittered sideways."""
        angle = direction * math.pi / 2
        lateral = _lateral(rng, config.layout.corridor_width / 2)
        return np.array((along * math.cos(angle) - lateral * math.sin(angle),
                         along * math.sin(angle) + lateral * math.cos(angle)))

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        state = InitialState.empty(n_envs, n_slots(config))
        end = config.layout.corridor_length / 2 - 1.0
        for env in range(n_envs):
            n_humans = draw_humans_count(rng, config)
            fill_traits(state, env, n_humans, rng, config)
            direction = int(rng.integers(4))
            state.positions[env, 0] = self._arm_point(rng, config, direction, end)
            state.goals[env, 0] = self._arm_point(rng, config, (direction + 2) % 4, end)

            def draw(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
                arm = int(rng.integers(4))
                start = self._arm_point(rng, config, arm, rng.uniform(config.layout.corridor_width / 2 + 1.0, end))
                return start, self._arm_point(rng, config, (arm + 2) % 4, end)

            _place_humans(state, env, n_humans, rng, draw)
            face_goal(state, env)
        return state

    def next_goal(self, rng: np.random.Generator, config: ScenarioSettings, reached: np.ndarray) -> np.ndarray:
        """The end of the arm opposite the goal just reached."""
        arm = round(math.atan2(reached[1], reached[0]) / (math.pi / 2)) % 4
        return self._arm_point(rng, config, (arm + 2) % 4, config.layout.corridor_length / 2 - 1.0)


@dataclass(frozen=True)
class Room:
    """Circle crossing (as ``circle_crossing``, ``circle_radius``) inside a closed square room with furniture: a
    cabinet in each corner and against the middle of each wall, all outside the circle the crossings span."""

    name: str = "room"
    default_humans: int | tuple[int, int] = 5
    redraw_goals: bool = False
    has_map: bool = True

    def static_map(self, config: ScenarioSettings) -> list[np.ndarray]:
        reach = config.circle_radius + config.circle_jitter + WALL_CLEARANCE  # the crossings' disc, and a margin
        half = reach + 1.5
        corner = reach / math.sqrt(2.0)
        inner = half - 0.3
        walls = [segment((-half, -half), (half, -half)), segment((half, -half), (half, half)),
                 segment((half, half), (-half, half)), segment((-half, half), (-half, -half))]
        corners = [box(corner, corner, inner, inner), box(-inner, corner, -corner, inner),
                   box(-inner, -inner, -corner, -corner), box(corner, -inner, inner, -corner)]
        cabinets = [box(-1.0, reach, 1.0, inner), box(-1.0, -inner, 1.0, -reach),
                    box(reach, -1.0, inner, 1.0), box(-inner, -1.0, -reach, 1.0)]
        return walls + corners + cabinets

    def sample(self, rng: np.random.Generator, n_envs: int, config: ScenarioSettings) -> InitialState:
        from socnav.sim.scenarios import get_scenario

        return get_scenario("circle_crossing").sample(rng, n_envs, config)

    def robot_routes(self, config: ScenarioSettings) -> list[tuple[np.ndarray, np.ndarray]]:
        """The robot's start and goal of every episode: circle crossing's four diameters."""
        return crossing_routes(config)


for _scenario in (Corridor(), Doorway(), Intersection(), Room()):
    register_scenario(_scenario)
