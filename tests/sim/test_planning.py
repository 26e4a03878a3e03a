"""The global planner (`socnav.sim.planning`): shortest paths checked against hand-computed ones, the clearance of
every path segment (a hypothesis invariant), the agents that follow it (the ORCA robot, the cautious fallback, ORCA
and social force humans) on maps where heading straight at the goal fails, unreachable goals, the config switch,
and the open plane left unchanged bit for bit.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import shapely
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from socnav.config import ConfigError, load_config
from socnav.controllers import make_controller
from socnav.envs.rollout import rollout_episodes
from socnav.safety.cautious import CautiousController
from socnav.sim import planning
from socnav.sim.maps import orient_rvo2
from socnav.sim.planning import GlobalPlanner, PathFollower, planner_for
from socnav.sim.scenarios import InitialState
from socnav.sim.world import OUTCOME_GOAL, OUTCOME_RUNNING, CrowdWorld


def square(cx: float, cy: float, half: float) -> np.ndarray:
    """A solid square pillar (counter-clockwise)."""
    return np.array([[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]])


#: an L-shaped corridor 2 m wide: up the left arm x in [0, 2], along the bottom arm y in [0, 2] (a boundary agents
#: stay inside, clockwise); its inner corner (2, 2) is the one convex corner of the walls
L_CORRIDOR = [orient_rvo2(np.array([[0, 0], [10, 0], [10, 2], [2, 2], [2, 10], [0, 10]], dtype=float), solid=False)]
#: a U-turn: up the left arm, across the top, down the right arm (2 m wide); the goal lies straight across the wall
U_CORRIDOR = [orient_rvo2(np.array([[0, 0], [2, 0], [2, 8], [8, 8], [8, 0], [10, 0], [10, 10], [0, 10]], dtype=float),
                          solid=False)]
#: two 6 x 6 m rooms side by side, the wall between them at x = 0 with a 1.1 m door near the top (y in [1.5, 2.6])
TWO_ROOMS = [orient_rvo2(np.array([[-6, -3], [6, -3], [6, 3], [-6, 3]], dtype=float), solid=False),
             np.array([[0.0, -3.0], [0.0, 1.5]]), np.array([[0.0, 2.6], [0.0, 3.0]])]


def path_length(path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


def wall_distance(polygons, path: np.ndarray) -> float:
    """The least distance from the polygonal path to every wall edge (shapely, independent of the planner)."""
    edges = []
    for vertices in polygons:
        closed = len(vertices) >= 3
        edges.append(shapely.LineString(np.concatenate([vertices, vertices[:1]]) if closed else vertices))
    return float(shapely.MultiLineString([edge.coords for edge in edges]).distance(shapely.LineString(path)))


def staged(config: dict, robot: tuple, goal: tuple, humans: list[tuple[tuple, tuple]] = ()) -> CrowdWorld:
    """A one-environment world with the robot at `robot` facing its goal and humans (start, goal) walking at 1 m/s."""
    world = CrowdWorld(load_config({"scenario": "position_swap", "n_humans": len(humans), **config}), 1)
    state = InitialState.empty(1, world.n_slots)
    state.active[0, : 1 + len(humans)] = True
    state.positions[0, 0], state.goals[0, 0] = robot, goal
    state.robot_heading[0] = math.atan2(goal[1] - robot[1], goal[0] - robot[0])
    state.radii[0, : 1 + len(humans)] = 0.3
    state.preferred_speeds[0, : 1 + len(humans)] = 1.0
    for k, (start, human_goal) in enumerate(humans, start=1):
        state.positions[0, k], state.goals[0, k] = start, human_goal
    world.load(0, state)
    return world


def drive(world: CrowdWorld, controller, max_steps: int = 400) -> int:
    """Run the staged episode with `controller` to its end; its outcome (running if `max_steps` ran out)."""
    for _ in range(max_steps):
        actions, _ = controller.predict(world.observe())
        outcome = int(world.step(actions).outcome[0])
        if outcome != OUTCOME_RUNNING:
            return outcome
    return OUTCOME_RUNNING


# ---------------------------------------------------------------------------------------------------- shortest paths


def test_around_a_square_pillar_the_path_is_the_hand_computed_one():
    # pillar [-1, 1]^2 inflated by 0.5: the square [-1.5, 1.5]^2; from (-5, 0) to (5, 0) over two of its corners
    planner = GlobalPlanner([square(0, 0, 1.0)], clearance=0.5)
    path = planner.shortest_path((-5.0, 0.0), (5.0, 0.0))
    assert path is not None and len(path) == 4
    assert path_length(path) == pytest.approx(2 * math.hypot(3.5, 1.5) + 3.0, abs=1e-5)
    assert np.abs(path[1:3]) == pytest.approx(np.full((2, 2), 1.5), abs=1e-5)
    # a goal in plain view: the straight line
    assert planner.shortest_path((-5.0, 3.0), (5.0, 3.0)) == pytest.approx(np.array([[-5.0, 3.0], [5.0, 3.0]]))


def test_in_an_l_corridor_the_path_turns_at_the_inner_corner():
    planner = GlobalPlanner(L_CORRIDOR, clearance=0.4)
    path = planner.shortest_path((1.0, 9.0), (9.0, 1.0))
    assert path is not None and len(path) == 3
    assert path[1] == pytest.approx([1.6, 1.6], abs=1e-5)  # the inner corner (2, 2) inflated by 0.4
    assert path_length(path) == pytest.approx(2 * math.hypot(0.6, 7.4), abs=1e-5)


def test_into_the_other_room_the_path_goes_through_the_door():
    planner = GlobalPlanner(TWO_ROOMS, clearance=0.4)
    path = planner.shortest_path((-4.0, -2.0), (4.0, -2.0))
    assert path is not None
    # over the lower door post (its end (0, 1.5) inflated, square-capped: corners (-+0.4, 1.9))
    assert path[1:-1] == pytest.approx(np.array([[-0.4, 1.9], [0.4, 1.9]]), abs=1e-5)
    assert path_length(path) == pytest.approx(2 * math.hypot(3.6, 3.9) + 0.8, abs=1e-5)
    # a clearance wider than the door closes it
    assert GlobalPlanner(TWO_ROOMS, clearance=0.6).shortest_path((-4.0, -2.0), (4.0, -2.0)) is None


def test_unreachable_goals_have_no_path():
    ring = [np.array([[-1.5, -1.5], [1.5, -1.5]]), np.array([[1.5, -1.5], [1.5, 1.5]]),
            np.array([[1.5, 1.5], [-1.5, 1.5]]), np.array([[-1.5, 1.5], [-1.5, -1.5]])]  # four walls, closed
    planner = GlobalPlanner([*ring, square(6.0, 0.0, 1.0)], clearance=0.4)
    assert planner.shortest_path((-5.0, 0.0), (0.0, 0.0)) is None  # enclosed
    assert planner.shortest_path((-5.0, 0.0), (6.0, 0.0)) is None  # inside a solid pillar
    assert planner.shortest_path((0.5, 0.0), (-0.5, 0.5)) is not None  # both inside the ring


def test_maps_too_large_for_the_table_search_their_graph_per_query(monkeypatch):
    # the same paths from Dijkstra per query (scipy) as from the table of shortest paths between nodes
    rng = np.random.default_rng(0)
    pillars = [square(x, y, 0.5) for x, y in rng.uniform(-5, 5, (8, 2))]
    tabled = GlobalPlanner(pillars, 0.4)
    monkeypatch.setattr(planning, "_TABLE_NODES", 0)
    searched = GlobalPlanner(pillars, 0.4)
    assert tabled._table is not None and searched._table is None
    starts, goals = rng.uniform(-7, 7, (40, 2)), rng.uniform(-7, 7, (40, 2))
    for a, b in zip(tabled.shortest_paths(starts, goals), searched.shortest_paths(starts, goals), strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert path_length(a) == pytest.approx(path_length(b), abs=1e-9)


def test_planners_are_built_once_per_map_and_clearance():
    pillar = [square(0, 0, 0.5)]
    assert planner_for(pillar, 0.4) is planner_for([vertices.copy() for vertices in pillar], 0.4)
    assert planner_for(pillar, 0.4) is not planner_for(pillar, 0.5)


def _boxes(draw) -> list[np.ndarray]:
    polygons = []
    for _ in range(draw(st.integers(1, 5))):
        x, y = draw(st.floats(-4, 4)), draw(st.floats(-4, 4))
        half = draw(st.floats(0.2, 1.2))
        polygons.append(square(x, y, half))
    for _ in range(draw(st.integers(0, 3))):
        x, y = draw(st.floats(-4, 4)), draw(st.floats(-4, 4))
        angle, length = draw(st.floats(0, math.pi)), draw(st.floats(0.5, 4))
        polygons.append(np.array([[x, y], [x + length * math.cos(angle), y + length * math.sin(angle)]]))
    return polygons


@st.composite
def maps_and_queries(draw):
    polygons = _boxes(draw)
    points = [(draw(st.floats(-6, 6)), draw(st.floats(-6, 6))) for _ in range(2)]
    return polygons, points, draw(st.floats(0.1, 0.6))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(maps_and_queries())
def test_every_path_segment_keeps_the_clearance_from_every_wall(case):
    polygons, (start, goal), clearance = case
    planner = GlobalPlanner(polygons, clearance)
    ends = np.array([start, goal])
    if not planner.is_free(ends).all() or (planner.wall_distance(ends) < clearance).any():
        return  # a start or goal among the inflated walls keeps only its own distance (another test)
    path = planner.shortest_path(start, goal)
    if path is None:
        return
    assert path[0] == pytest.approx(start) and path[-1] == pytest.approx(goal)
    for a, b in itertools.pairwise(path):
        assert wall_distance(polygons, np.stack([a, b])) >= clearance - 1e-6
    assert planner.clear(path[:-1], path[1:]).all()  # the per-step rule agrees with shapely's
    assert path_length(path) >= math.dist(start, goal) - 1e-9
    assert planner.is_free(path).all()


def test_a_start_near_a_wall_leaves_it_keeping_its_own_distance():
    planner = GlobalPlanner([square(0, 0, 1.0)], clearance=0.5)
    start = (-1.2, 0.0)  # 0.2 m from the pillar: inside the inflated one
    path = planner.shortest_path(start, (5.0, 0.0))
    assert path is not None
    assert wall_distance([square(0, 0, 1.0)], path) >= 0.2 - 1e-6
    assert wall_distance([square(0, 0, 1.0)], path[1:]) >= 0.5 - 1e-6


# ---------------------------------------------------------------------------------------------------- followers


def test_the_follower_heads_for_a_visible_goal_and_for_the_carrot_otherwise():
    planner = GlobalPlanner([square(0, 0, 1.0)], clearance=0.5)
    follower = PathFollower(planner, 2, lookahead=1.0, replan_distance=0.5)
    positions = np.array([[-5.0, 0.0], [-5.0, 3.0]])
    goals = np.array([[5.0, 0.0], [5.0, 3.0]])
    subgoals, direct = follower.update(positions, goals, np.ones(2, dtype=bool))
    assert direct.tolist() == [False, True]
    assert subgoals[1].tolist() == [5.0, 3.0]  # the goal itself, bit for bit
    corner = follower.paths[0, 1]  # over the top or the bottom of the pillar: the two are equally short
    assert np.abs(corner) == pytest.approx([1.5, 1.5], abs=1e-5)
    carrot = positions[0] + (corner - positions[0]) / np.linalg.norm(corner - positions[0])
    assert subgoals[0] == pytest.approx(carrot, abs=1e-5)
    assert follower.queries == 1
    for _ in range(5):  # walking along the path: no new query
        positions[0] += 0.2 * (corner - positions[0]) / np.linalg.norm(corner - positions[0])
        follower.update(positions, goals, np.ones(2, dtype=bool))
    assert follower.queries == 1
    positions[0] = (-5.0, -1.0)  # pushed off the path: planned again
    follower.update(positions, goals, np.ones(2, dtype=bool))
    assert follower.queries == 2


def test_an_unreachable_goal_leaves_the_follower_heading_straight_at_it():
    ring = [np.array([[-1.5, -1.5], [1.5, -1.5]]), np.array([[1.5, -1.5], [1.5, 1.5]]),
            np.array([[1.5, 1.5], [-1.5, 1.5]]), np.array([[-1.5, 1.5], [-1.5, -1.5]])]
    follower = PathFollower(GlobalPlanner(ring, 0.4), 1, lookahead=1.0, replan_distance=0.5)
    positions, goals = np.array([[-5.0, 0.0]]), np.array([[0.0, 0.0]])
    for _ in range(3):
        subgoals, direct = follower.update(positions, goals, np.ones(1, dtype=bool))
        assert direct[0] and subgoals[0].tolist() == [0.0, 0.0]
    assert follower.queries == 1  # not asked again while the robot stays where the query failed


# ---------------------------------------------------------------------------------------------------- the ORCA robot


def test_the_orca_robot_goes_around_a_pillar_on_its_straight_line_with_the_planner_only():
    pillar = square(0, 0, 0.5).tolist()  # centred on all four of circle crossing's diameters
    outcomes = {}
    for enabled in (True, False):
        config = load_config({"scenario": "circle_crossing", "n_humans": 0, "obstacles": [pillar],
                              "planner": {"enabled": enabled}})
        records = rollout_episodes(make_controller("orca", config), config, 8, seed=0, n_envs=8, progress=False,
                                   metrics=False)
        outcomes[enabled] = records["outcome"].value_counts().to_dict()
    assert outcomes[True] == {"goal": 8}
    assert outcomes[False] == {"timeout": 8}  # ORCA's local minimum: it stops in front of the pillar


def episode_steps(walls, robot: tuple, goal: tuple, enabled: bool, controller: str = "orca") -> tuple[int, int]:
    """(outcome, steps) of the ORCA robot (or the cautious fallback) driving from `robot` to `goal` among `walls`."""
    config = {"obstacles": [vertices.tolist() for vertices in walls], "planner": {"enabled": enabled},
              "timeout_margin": 100.0}
    world = staged(config, robot, goal)
    policy = make_controller("orca", world.config) if controller == "orca" else CautiousController(world.config)
    return drive(world, policy, max_steps=300), int(world.steps[0])


@pytest.mark.parametrize(("walls", "robot", "goal"), [(U_CORRIDOR, (1.0, 1.0), (9.0, 1.0)),
                                                      (TWO_ROOMS, (-4.0, -2.0), (4.0, -2.0))],
                         ids=["u_corridor", "other_room"])
def test_the_orca_robot_reaches_a_goal_behind_a_wall_with_the_planner_only(walls, robot, goal):
    assert episode_steps(walls, robot, goal, enabled=True)[0] == OUTCOME_GOAL
    # without it the robot heads at the wall between it and its goal and stops there (ORCA's local minimum)
    assert episode_steps(walls, robot, goal, enabled=False)[0] == OUTCOME_RUNNING
    # the cautious fallback of the safety layer follows the same path
    assert episode_steps(walls, robot, goal, enabled=True, controller="cautious")[0] == OUTCOME_GOAL


def test_in_an_l_corridor_the_orca_robot_takes_the_short_way_round_the_corner():
    # Without the planner ORCA slides along the inner wall and gets there too (an L is no local minimum), but late.
    with_planner = episode_steps(L_CORRIDOR, (1.0, 9.0), (9.0, 1.0), enabled=True)
    without = episode_steps(L_CORRIDOR, (1.0, 9.0), (9.0, 1.0), enabled=False)
    assert with_planner[0] == without[0] == OUTCOME_GOAL
    assert with_planner[1] < 0.75 * without[1]  # measured: 62 steps against 102


def test_the_cautious_controller_plans_around_the_walls_it_is_given():
    config = load_config({"scenario": "position_swap", "n_humans": 0})
    assert CautiousController(config).planner is None  # the open plane
    given = CautiousController(config, walls=TWO_ROOMS)
    assert given.planner is not None and given.planner is planner_for(TWO_ROOMS, 0.3 + 0.1)
    assert CautiousController(load_config({"obstacles": [v.tolist() for v in TWO_ROOMS]}), walls=[]).planner is None


# ---------------------------------------------------------------------------------------------------- the humans


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_humans_walk_around_a_pillar_to_their_goal(model):
    # the robot stands far off, unseen; a human walks from one side of a pillar on its straight line to the other
    pillar = square(0, 0, 0.6).tolist()
    config = {"obstacles": [pillar], "robot_visible": False, "humans": {"model": model}}
    world = staged(config, robot=(0.0, -8.0), goal=(0.0, -8.0), humans=[((-4.0, 0.0), (4.0, 0.0))])
    stop = np.array([[0.0, -1.0]], dtype=np.float32)  # speed 0, no turn
    for _ in range(80):
        world.step(stop)
    assert np.linalg.norm(world.positions[0, 1] - (4.0, 0.0)) < 0.6
    assert world.human_paths is not None and world.human_paths.queries >= 1
    if model == "orca":  # without the planner an ORCA human stops in front of the pillar
        world = staged({**config, "planner": {"enabled": False}}, robot=(0.0, -8.0), goal=(0.0, -8.0),
                       humans=[((-4.0, 0.0), (4.0, 0.0))])
        for _ in range(80):
            world.step(stop)
        assert world.positions[0, 1, 0] < -0.5


# ---------------------------------------------------------------------------------------------------- the config


def test_an_unreachable_fixed_goal_is_refused_when_the_config_is_read():
    # four walls closed around circle crossing's goal (-7, 0) of the start (7, 0)
    ring = [[[-8.5, -1.5], [-5.5, -1.5]], [[-5.5, -1.5], [-5.5, 1.5]], [[-5.5, 1.5], [-8.5, 1.5]],
            [[-8.5, 1.5], [-8.5, -1.5]]]
    with pytest.raises(ConfigError, match=r"planner: the robot's goal \(-7, 0\) cannot be reached from its start "
                                          r"\(7, 0\).*planner.margin"):
        load_config({"scenario": "circle_crossing", "obstacles": ring})
    load_config({"scenario": "circle_crossing", "obstacles": ring, "planner": {"enabled": False}})  # today's world


def test_bad_planner_settings_are_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"planner.margin: Input should be greater than or equal to 0"):
        load_config({"planner": {"margin": -0.1}})
    with pytest.raises(ConfigError, match=r"planner.lookahed: unknown field.*did you mean lookahead"):
        load_config({"planner": {"lookahed": 1.0}})
    with pytest.raises(ConfigError, match=r"planner.enabled: Input should be a valid boolean"):
        load_config({"planner": {"enabled": "sometimes"}})


def test_the_planner_stays_out_of_dumps_at_its_defaults():
    assert "planner" not in load_config({}).model_dump()
    assert load_config({"planner": {"margin": 0.2}}).model_dump()["planner"]["margin"] == 0.2


# ---------------------------------------------------------------------------------------------------- unchanged


def test_the_open_plane_is_unchanged_bit_for_bit():
    records = {}
    for enabled in (True, False):
        config = load_config({"scenario": "circle_crossing", "planner": {"enabled": enabled}})
        world = CrowdWorld(config, 2)
        assert world.human_paths is None and make_controller("orca", config).planner is None
        records[enabled] = rollout_episodes(make_controller("orca", config), config, 6, seed=0, n_envs=3,
                                            progress=False)
    assert records[True].equals(records[False])


def test_a_world_with_the_planner_plays_the_same_episodes_whatever_the_batch():
    config = load_config({"scenario": "doorway"})
    one = rollout_episodes(make_controller("orca", config), config, 4, seed=3, n_envs=1, progress=False)
    four = rollout_episodes(make_controller("orca", config), config, 4, seed=3, n_envs=4, progress=False)
    assert one.equals(four)


def test_the_observed_goal_follows_the_route_with_planner_observe():
    """With ``planner.observe`` the robot observes its goal in the direction of its path's subgoal, at the goal's
    distance: behind a pillar the goal is seen off to the side the path takes; with the line clear, and without the
    option, the observation is the one of the open plane."""
    pillar = square(0.0, 0.0, 0.5).tolist()
    plain = staged({"obstacles": [pillar]}, robot=(-4.0, 0.0), goal=(4.0, 0.0)).observe()
    routed_world = staged({"obstacles": [pillar], "planner": {"observe": True}}, robot=(-4.0, 0.0), goal=(4.0, 0.0))
    routed = routed_world.observe()
    distance, heading = 0, 1  # socnav.envs.spaces.ROBOT_FEATURE_NAMES
    assert plain["robot"][0, heading] == pytest.approx(0.0, abs=1e-6)  # facing the goal
    assert routed["robot"][0, distance] == pytest.approx(plain["robot"][0, distance], rel=1e-6)
    subgoal = routed_world.robot_path.update(routed_world.positions[:, 0], routed_world.goals[:, 0])[0][0]
    bearing = math.atan2(subgoal[1], subgoal[0] + 4.0)  # of the subgoal from the robot
    assert abs(bearing) > 0.05  # the path leaves the straight line round the pillar
    # docs/world.md: the robot's heading (0, along +x) relative to the observed goal's direction
    assert routed["robot"][0, heading] == pytest.approx(0.0 - bearing, abs=1e-4)
    clear = staged({"obstacles": [square(0.0, 3.0, 0.5).tolist()], "planner": {"observe": True}},
                   robot=(-4.0, 0.0), goal=(4.0, 0.0)).observe()
    np.testing.assert_array_equal(clear["robot"], plain["robot"])


def test_the_orca_robot_plays_the_same_episodes_whatever_the_batch():
    """The robot's path is forgotten when its row starts a new episode (`OrcaController.on_episode_start`): an
    episode does not inherit the path of the episode that ran before it in its row."""
    config = load_config({"scenario": "doorway"})
    played = [rollout_episodes(make_controller("orca", config), config, 60, seed=0, n_envs=n, progress=False,
                               metrics=False).sort_values("seed").reset_index(drop=True) for n in (20, 7)]
    assert played[0][["seed", "outcome", "length"]].equals(played[1][["seed", "outcome", "length"]])
