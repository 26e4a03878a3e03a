"""The nodes with a map, a range scan and a route: a navigator exported from a (tiny, untrained) policy of the doorway
with a scan and ``planner.observe`` decides on a LaserScan, takes its walls from an OccupancyGrid (a late joiner
still gets map_server's latched map), a map file or its own file, places the robot on the map from a pose, follows a
nav_msgs/Path it is given and publishes its subgoal; a missing, stale or refused scan, map or pose stops the robot and
says why; the simulator publishes the scan, the map and the humans its robot sees, and drives that navigator in
lock-step."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.ros2

DOORWAY = {"scenario": "doorway", "n_humans": 3, "scan": {"beams": 36}, "planner": {"observe": True}}
TINY = {"lstm_hidden_size": 16, "net_arch_pi": (32,), "net_arch_vf": (32,)}
#: The simulator's episodes end (time-out) after about 10 steps: a few decisions, not a crossing.
SHORT = {"timeout_factor": 0.01, "timeout_margin": 2.0}
#: 4 rows x 6 columns at 0.5 m from (1, 2): one occupied 2 x 2 block, x in [3, 4], y in [2, 3].
BLOCK = [[0, 0, 0, 0, 100, 100], [0, 0, 0, 0, 100, 100], [0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]]


@pytest.fixture(scope="module")
def route_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A navigator of the doorway with a 36-beam scan whose policy observes its route (untrained: its commands are
    whatever they are, the plumbing is what is tested)."""
    import torch

    import socnav
    from socnav.export import export_onnx
    from socnav.rl import make_model

    torch.set_num_threads(1)
    policy = make_model("odv-ppo-drop", socnav.make_vec_env(DOORWAY, n_envs=1), seed=2, overrides=TINY).policy
    return export_onnx(policy, tmp_path_factory.mktemp("route") / "doorway.onnx", k=4, env_config=DOORWAY)


class Capture:
    """Stands in for a publisher: keeps what is published."""

    def __init__(self) -> None:
        self.messages: list = []

    def publish(self, message) -> None:
        self.messages.append(message)


def _navigator(context, model: Path, **parameters):
    """A navigator node whose outputs are captured (``node.cmd_vel.messages``, ...)."""
    from rclpy.parameter import Parameter

    from socnav.ros2.navigator import NavigatorNode

    settings = {"model": str(model), "seed": 0, **parameters}
    node = NavigatorNode(parameter_overrides=[Parameter(name, value=value) for name, value in settings.items()],
                         context=context)
    for name in ("cmd_vel", "diagnostics", "markers", "subgoal_topic"):
        setattr(node, name, Capture())
    return node


def _feed(node, stamp_ns: int, position=(-3.0, 3.0), heading=0.0, goal=(4.0, 3.0), scan: bool = True) -> None:
    """Odometry, one human, the goal and (``scan``) an empty-room scan, all stamped ``stamp_ns``, through the node's
    callbacks."""
    from socnav.ros2 import messages

    node._on_odometry(messages.robot_to_odometry(np.array(position, dtype=float), np.zeros(2), heading, 0.0,
                                                 stamp_ns, "odom", "base_link"))
    node._on_humans(messages.humans_to_cloud(np.array([[-1.5, 2.0]]), np.zeros((1, 2)), np.array([0.3]), stamp_ns,
                                             "odom"))
    node._on_goal(messages.position_to_goal(np.array(goal, dtype=float), stamp_ns, "odom"))
    if scan:
        node._on_scan(messages.ranges_to_scan(np.full(36, 8.0), stamp_ns, "base_link", 360.0, 8.0))


def _decide(node):
    """One decision now: its Twist and diagnostic status."""
    node._decide(time.perf_counter())
    return node.cmd_vel.messages[-1], node.diagnostics.messages[-1].status[0]


def _is_stop(twist) -> bool:
    return (twist.linear.x, twist.angular.z) == (0.0, 0.0)


def _grid(values, frame="map"):
    from nav_msgs.msg import OccupancyGrid

    values = np.asarray(values, dtype=np.int8)
    message = OccupancyGrid()
    message.header.frame_id = frame
    message.info.resolution = 0.5
    message.info.height, message.info.width = values.shape
    message.info.origin.position.x, message.info.origin.position.y = 1.0, 2.0
    message.info.origin.orientation.w = 1.0
    message.data = values.ravel().tolist()
    return message


def _spin_until(executor, done, what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        executor.spin_once(timeout_sec=0.01)


# ------------------------------------------------------------------------------------------------- setup


def test_a_path_topic_for_a_policy_that_observes_no_route_is_refused(ros_context, navigator_file):
    from socnav.ros2.navigator import NavigatorSetupError

    with pytest.raises(NavigatorSetupError, match=re.escape(
            "parameter path_topic is 'plan', but this navigator's policy does not observe a route (its env config's "
            "planner.observe is false): leave path_topic empty")):
        _navigator(ros_context, navigator_file, path_topic="plan")


@pytest.mark.parametrize("parameters,match", [
    ({"map_file": "missing.yaml"}, "parameter map_file: map file not found: missing.yaml"),
    ({"map_free_thresh": 0.0}, r"parameter map_free_thresh must be > 0 and <= 1, got 0\.0"),
])
def test_a_bad_map_parameter_is_refused(ros_context, navigator_file, parameters, match):
    from socnav.ros2.navigator import NavigatorSetupError

    with pytest.raises(NavigatorSetupError, match=match):
        _navigator(ros_context, navigator_file, **parameters)


def test_a_map_file_gives_the_walls_at_start(ros_context, route_file, tmp_path):
    map_file = tmp_path / "table.yaml"
    map_file.write_text("obstacles:\n  - [[1, 1], [2, 1], [2, 2], [1, 2]]\n")
    node = _navigator(ros_context, route_file, map_file=str(map_file))
    try:
        assert len(node.navigator.walls) == 1
        np.testing.assert_array_equal(node.navigator.walls[0], [[1, 1], [2, 1], [2, 2], [1, 2]])
        assert node.walls_source == f"map_file {map_file}"
    finally:
        node.destroy_node()
    node = _navigator(ros_context, route_file)  # no map given: the navigator file's (the doorway's 6 walls)
    try:
        assert len(node.navigator.walls) == 6 and node.walls_source == "the navigator file"
    finally:
        node.destroy_node()


def test_a_step_onto_a_wall_of_the_map_stands_still_and_says_so(ros_context, route_file, tmp_path):
    """The wall stop (socnav.safety.wall_stop) in the node: a robot 2 cm from a wall of its map_file, facing it,
    does not drive on whatever the policy says: zero speed, a WARN that names the wall stop, ``wall_stop`` True;
    the same robot 2 m from the wall drives."""
    map_file = tmp_path / "wall.yaml"
    map_file.write_text("obstacles:\n  - [[0.32, -2], [1, -2], [1, 2], [0.32, 2]]\n")
    node = _navigator(ros_context, route_file, map_file=str(map_file))
    try:
        for position, stopped in (((0.0, 0.0), True), ((-2.0, 0.0), False)):
            _feed(node, node.get_clock().now().nanoseconds, position=position, goal=(-6.0, 0.0))
            twist, status = _decide(node)
            values = {value.key: value.value for value in status.values}
            assert values["wall_stop"] == str(stopped), status.message
            assert ("wall stop: the step would meet a wall, standing still" in status.message) is stopped
            if stopped:
                assert twist.linear.x == 0.0 and status.level == status.WARN
            else:
                assert twist.linear.x > 0.0
    finally:
        node.destroy_node()


# ------------------------------------------------------------------------------------------------- map


def test_a_latched_map_replaces_the_walls_and_a_map_in_another_frame_stops_the_robot(ros_context, route_file):
    """The map is published (transient local, as map_server does) before the navigator starts: it still gets it,
    and its walls become the navigator's. Then a map in the odometry frame: refused, the walls kept, the robot
    stopped with the reason until a good map comes."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from shapely.geometry import Polygon, box

    from socnav.ros2.navigator import LATCHED_QOS

    driver = Node("map_server", context=ros_context)
    publisher = driver.create_publisher(OccupancyGrid, "map", LATCHED_QOS)
    publisher.publish(_grid(BLOCK))
    node = _navigator(ros_context, route_file)
    executor = SingleThreadedExecutor(context=ros_context)
    for each in (driver, node):
        executor.add_node(each)
    try:
        _spin_until(executor, lambda: node.map.received == 1, "the latched map")
        assert len(node.navigator.walls) == 1 and Polygon(node.navigator.walls[0]).equals(box(3.0, 2.0, 4.0, 3.0))
        assert node.walls_source == "map topic (1 polygons)"
        stamp = node.get_clock().now().nanoseconds
        _feed(node, stamp)
        twist, status = _decide(node)
        assert not _is_stop(twist) and status.level != status.ERROR, status.message
        values = {value.key: value.value for value in status.values}
        assert values["walls"] == "1" and values["walls_from"] == "map topic (1 polygons)"
        publisher.publish(_grid(BLOCK, frame="odom"))
        _spin_until(executor, lambda: node.map.received == 2, "the second map")
        twist, status = _decide(node)
        assert _is_stop(twist) and status.level == status.ERROR
        assert status.message == ("stopped: map.header.frame_id is 'odom', expected 'map' (set the node's frame "
                                  "parameters to your robot's frames; socnav does not look up tf)")
        assert len(node.navigator.walls) == 1  # the refused map changed nothing
        publisher.publish(_grid(np.zeros((4, 6))))  # an empty map: no walls at all
        _spin_until(executor, lambda: node.map.received == 3, "the third map")
        assert node.navigator.walls is None and not _is_stop(_decide(node)[0])
    finally:
        executor.shutdown()
        node.destroy_node()
        driver.destroy_node()


# ------------------------------------------------------------------------------------------------- scan


def test_a_scan_navigator_stops_without_a_fresh_scan_in_its_frame(ros_context, route_file):
    from socnav.ros2 import messages

    node = _navigator(ros_context, route_file)
    try:
        now = node.get_clock().now().nanoseconds
        _feed(node, now, scan=False)
        twist, status = _decide(node)
        assert _is_stop(twist) and status.message == "stopped: no scan received yet"
        node._on_scan(messages.ranges_to_scan(np.full(36, 8.0), now - 2 * 10**9, "base_link", 360.0, 8.0))
        twist, status = _decide(node)
        assert _is_stop(twist) and status.message.startswith("stopped: scan is stale: 2.")
        node._on_scan(messages.ranges_to_scan(np.full(36, 8.0), now, "laser", 360.0, 8.0))
        twist, status = _decide(node)
        assert _is_stop(twist) and "scan.header.frame_id is 'laser', expected 'base_link'" in status.message
        _feed(node, node.get_clock().now().nanoseconds)
        twist, status = _decide(node)
        assert not _is_stop(twist) and status.level != status.ERROR, status.message
    finally:
        node.destroy_node()


def test_lockstep_waits_for_a_scan_with_the_inputs_stamp(ros_context, route_file):
    from geometry_msgs.msg import Twist
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from socnav.ros2 import messages

    node = _navigator(ros_context, route_file, lockstep=True)
    node.cmd_vel = node.create_publisher(Twist, "cmd_vel", 10)  # a real one: lock-step waits for its subscriber
    driver = Node("robot", context=ros_context)
    driver.create_subscription(Twist, "cmd_vel", lambda _message: None, 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(driver)
    try:
        _spin_until(executor, lambda: node.cmd_vel.get_subscription_count() == 1, "the cmd_vel subscriber")
        stamp = node.get_clock().now().nanoseconds
        _feed(node, stamp, scan=False)
        node._on_scan(messages.ranges_to_scan(np.full(36, 8.0), stamp - 1, "base_link", 360.0, 8.0))
        assert node.decisions == 0
        node._on_scan(messages.ranges_to_scan(np.full(36, 8.0), stamp, "base_link", 360.0, 8.0))
        assert node.decisions == 1
    finally:
        executor.shutdown()
        node.destroy_node()
        driver.destroy_node()


# ------------------------------------------------------------------------------------------------- pose and path


def test_the_pose_places_the_odometry_on_the_map_and_the_path_sets_the_subgoal(ros_context, route_file):
    """Odometry (1, 2) heading 0 and a map pose (11, 2) heading 90 degrees at the same stamp: the odometry frame is
    turned by 90 degrees and shifted by (13, 1) from the map. Later odometry (2, 2) is the map pose (11, 3), heading
    90 degrees; on the path x = 11 the subgoal is 1 m (the lookahead) beyond (11, 3): (11, 4), published in the map
    frame and drawn at (3, 2) in the odometry frame (1 m ahead of the robot)."""
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from nav_msgs.msg import Path as PathMessage

    from socnav.ros2.messages import ns_to_stamp, quaternion_from_yaw

    node = _navigator(ros_context, route_file, pose_topic="amcl_pose", path_topic="plan")
    try:
        assert node.navigator.config.planner.lookahead == 1.0
        first = node.get_clock().now().nanoseconds
        _feed(node, first, position=(1.0, 2.0), goal=(8.0, 2.0))
        twist, status = _decide(node)
        assert _is_stop(twist) and status.message == "stopped: no pose received yet"
        pose = PoseWithCovarianceStamped()
        pose.header.frame_id, pose.header.stamp = "map", ns_to_stamp(first)
        pose.pose.pose.position.x, pose.pose.pose.position.y = 11.0, 2.0
        pose.pose.pose.orientation = quaternion_from_yaw(math.pi / 2)
        node._on_pose(pose)
        path = PathMessage()
        path.header.frame_id = "map"
        for y in (0.0, 10.0):
            waypoint = PoseStamped()
            waypoint.pose.position.x, waypoint.pose.position.y = 11.0, y
            path.poses.append(waypoint)
        node._on_path(path)
        _feed(node, node.get_clock().now().nanoseconds, position=(2.0, 2.0), goal=(8.0, 2.0))
        twist, status = _decide(node)
        assert not _is_stop(twist), status.message
        robot = node.odometry.value
        np.testing.assert_allclose(node._map_pose(robot), [11.0, 3.0, math.pi / 2], atol=1e-12)
        subgoal = node.subgoal_topic.messages[-1]
        assert subgoal.header.frame_id == "map"
        assert (subgoal.point.x, subgoal.point.y) == pytest.approx((11.0, 4.0), abs=1e-9)
        marker = next(item for item in node.markers.messages[-1].markers if item.ns == "subgoal")
        assert (marker.pose.position.x, marker.pose.position.y) == pytest.approx((3.0, 2.0), abs=1e-9)
        node._on_path(PathMessage(header=path.header))  # an empty path: the navigator plans its own again
        assert node._given_path() is None
        pose.header.frame_id = "odom"
        node._on_pose(pose)
        twist, status = _decide(node)
        assert _is_stop(twist) and "pose.header.frame_id is 'odom', expected 'map'" in status.message
    finally:
        node.destroy_node()


# ------------------------------------------------------------------------------------------------- simulator


def test_the_simulator_publishes_the_scan_the_map_and_only_the_humans_its_robot_sees(ros_context):
    """The doorway with 6 humans, at the start of the first seed where a wall hides one of them from the robot:
    the scan is the world's observation's, the humans cloud holds the humans in sight, the map is the walls'."""
    from rclpy.parameter import Parameter

    import socnav
    from socnav.ros2.messages import cloud_to_humans, grid_to_walls, scan_to_ranges
    from socnav.ros2.simulator import SimulatorNode

    config = socnav.load_config({**DOORWAY, "n_humans": 6})
    for seed in range(50):
        node = SimulatorNode(config, seed=seed, context=ros_context,
                             parameter_overrides=[Parameter("navigator_node", value="")])
        world = node.world
        for name in ("clock", "goal", "odometry", "scan", "humans", "markers"):
            setattr(node, name, Capture())
        node._begin_episode(executor=None)
        hidden = world.active[0, 1:] & ~world.in_sight[0, 1:]
        if hidden.any():
            break
        node.destroy_node()
    else:
        pytest.fail("no seed of 50 hides a human behind a wall at the start")
    try:
        observation = world.observe()
        scan = node.scan.messages[-1]
        assert scan.header.frame_id == "base_link" and scan.range_max == pytest.approx(8.0)
        np.testing.assert_array_equal(scan_to_ranges(scan, "base_link", 36, 360.0), observation["scan"][0])
        humans = cloud_to_humans(node.humans.messages[-1], "odom", 0.3)
        seen = np.flatnonzero(world.active[0, 1:] & world.in_sight[0, 1:]) + 1
        np.testing.assert_array_equal(humans.positions, world.positions[0, seen])
        assert len(humans.radii) == int(world.active[0, 1:].sum() - hidden.sum())
        assert node.grid.header.frame_id == "map" and len(grid_to_walls(node.grid, "map")) == 2
    finally:
        node.destroy_node()


def _lockstep(context, route_file: Path, seed: int, path_waypoints=None):
    """The doorway (short episodes) played by the simulator node against the route navigator in lock-step, in one
    executor; the navigator, and the odometry and subgoals it sent by stamp. ``path_waypoints``: a nav_msgs/Path
    published on ``plan`` first (and the navigator told to follow it)."""
    from geometry_msgs.msg import PointStamped, PoseStamped, Twist
    from nav_msgs.msg import Odometry
    from nav_msgs.msg import Path as PathMessage
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    import socnav
    from socnav.ros2.messages import stamp_to_ns
    from socnav.ros2.navigator import NavigatorNode
    from socnav.ros2.simulator import SimulatorNode

    parameters = {"model": str(route_file), "lockstep": True, "use_sim_time": True, "seed": 0}
    if path_waypoints is not None:
        parameters["path_topic"] = "plan"
    navigator = NavigatorNode(parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()],
                              context=context)
    simulator = SimulatorNode(socnav.load_config({**DOORWAY, **SHORT}), seed=seed, lockstep=True, context=context)
    driver = Node("observer", context=context)
    odometry, subgoals, twists = {}, {}, []
    driver.create_subscription(Odometry, "odom", lambda m: odometry.__setitem__(stamp_to_ns(m.header.stamp), m), 10)
    driver.create_subscription(PointStamped, "/socnav_navigator/subgoal",
                               lambda m: subgoals.__setitem__(stamp_to_ns(m.header.stamp), m), 10)
    driver.create_subscription(Twist, "cmd_vel", twists.append, 10)
    executor = SingleThreadedExecutor(context=context)
    for node in (navigator, simulator, driver):
        executor.add_node(node)
    try:
        if path_waypoints is not None:
            plan = driver.create_publisher(PathMessage, "plan", 10)
            message = PathMessage()
            message.header.frame_id = "map"
            for x, y in path_waypoints:
                waypoint = PoseStamped()
                waypoint.pose.position.x, waypoint.pose.position.y = float(x), float(y)
                message.poses.append(waypoint)
            _spin_until(executor, lambda: plan.get_subscription_count() == 1, "the path's subscriber")
            plan.publish(message)
            _spin_until(executor, lambda: navigator.path.received == 1, "the path")
        records = simulator.run(executor)
        _spin_until(executor, lambda: len(subgoals) == len(twists) == navigator.decisions,
                    "the last command and subgoal", timeout=5.0)
    finally:
        executor.shutdown()
        for node in (navigator, simulator, driver):
            node.destroy_node()
    return navigator, records, odometry, subgoals, twists


def test_the_simulator_drives_a_map_and_scan_navigator_in_lockstep(ros_context, route_file):
    """The navigator takes the simulator's map (its walls replace the file's), decides on every step's scan (its
    stamp matches the step's), drives (not zero stops), and publishes a subgoal in the map frame each decision."""
    navigator, records, _, subgoals, twists = _lockstep(ros_context, route_file, seed=3)
    steps = int(records["length"].sum())
    assert 5 <= steps <= 20 and navigator.decisions == steps == len(twists)
    assert navigator.map.received == 1 and navigator.walls_source.startswith("map topic")
    assert navigator.scan.received >= steps and navigator.scan.error is None
    assert all(not _is_stop(twist) for twist in twists)
    assert len(subgoals) == steps and {message.header.frame_id for message in subgoals.values()} == {"map"}


def test_a_path_on_path_topic_becomes_the_subgoal(ros_context, route_file):
    """A straight path along y = -3: at every decision the subgoal is the point 1 m (the lookahead) along it from
    the robot's nearest point, (x + 1, -3) for the robot at x, not the navigator's own (which heads for the goal
    at y ~ 0 through the door)."""
    navigator, records, odometry, subgoals, twists = _lockstep(ros_context, route_file, seed=3,
                                                               path_waypoints=[(-7.9, -3.0), (7.9, -3.0)])
    assert len(subgoals) == navigator.decisions == int(records["length"].sum()) >= 5
    for stamp, subgoal in subgoals.items():
        x = odometry[stamp].pose.pose.position.x
        assert (subgoal.point.x, subgoal.point.y) == pytest.approx((x + 1.0, -3.0), abs=1e-9)
    assert all(not _is_stop(twist) for twist in twists)
