"""The navigator node in a ROS 2 graph (one process, simulated time): its command is `SafeNavigator.act`'s, and on
every bad input — stale odometry or humans, a NaN in any message, no goal, a goal reached, another frame — it
publishes a zero Twist, says why on /diagnostics, and drives again once good messages come back."""

from __future__ import annotations

import math
import re
import time

import numpy as np
import pytest

from socnav.runtime import SafeNavigator

pytestmark = pytest.mark.ros2

STEP_NS = 250_000_000
START_NS = 10_000_000_000
ROBOT = {"position": [0.0, -4.0], "velocity": [0.3, 0.4], "heading": 1.2, "goal": [0.0, 4.0], "radius": 0.3}
HUMANS = {"positions": [[0.5, -2.0], [-1.5, 0.0], [2.0, 1.0]], "velocities": [[0.0, -0.8], [0.7, 0.0], [-0.5, -0.5]],
          "radii": [0.3, 0.35, 0.25]}


class Graph:
    """A navigator node (timer mode, simulated time) and a driver node that plays the robot, tracker and clock."""

    def __init__(self, context, navigator_file, **parameters) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, Twist
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import PointCloud2

        from socnav.ros2.navigator import NavigatorNode

        settings = {"model": str(navigator_file), "seed": 3, "use_sim_time": True, "preferred_speed": 0.9,
                    **parameters}
        self.navigator = NavigatorNode(parameter_overrides=[Parameter(k, value=v) for k, v in settings.items()],
                                       context=context)
        self.driver = Node("driver", context=context)
        self.clock = self.driver.create_publisher(Clock, "/clock", 10)
        self.odometry = self.driver.create_publisher(Odometry, "odom", 10)
        self.humans = self.driver.create_publisher(PointCloud2, "humans", 10)
        self.goal = self.driver.create_publisher(PoseStamped, "goal_pose", 10)
        self.twists, self.diagnostics = [], []
        self.driver.create_subscription(Twist, "cmd_vel", self.twists.append, 10)
        self.driver.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.navigator)
        self.executor.add_node(self.driver)
        self.now_ns = START_NS
        self._publish_clock()

    def _publish_clock(self) -> None:
        from rosgraph_msgs.msg import Clock

        from socnav.ros2.messages import ns_to_stamp

        self.clock.publish(Clock(clock=ns_to_stamp(self.now_ns)))
        self.spin_until(lambda: self.navigator.get_clock().now().nanoseconds == self.now_ns, "the clock")

    def spin_until(self, done, what: str, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            self.executor.spin_once(timeout_sec=0.01)

    def send(self, publisher, latest, message) -> None:
        """Publish one input and wait until the navigator has it."""
        received = latest.received
        publisher.publish(message)
        self.spin_until(lambda: latest.received > received, publisher.topic_name)

    def send_state(self, robot=ROBOT, humans=HUMANS, goal=True, stamp_ns=None, **changes):
        from socnav.ros2 import messages

        stamp = self.now_ns if stamp_ns is None else stamp_ns
        odometry = messages.robot_to_odometry(np.array(robot["position"]), np.array(robot["velocity"]),
                                              robot["heading"], 0.0, stamp, "odom", "base_link")
        cloud = messages.humans_to_cloud(np.array(humans["positions"]), np.array(humans["velocities"]),
                                         np.array(humans["radii"]), stamp, "odom")
        for change in changes.values():
            change(odometry, cloud)
        self.send(self.odometry, self.navigator.odometry, odometry)
        self.send(self.humans, self.navigator.humans, cloud)
        if goal:
            self.send(self.goal, self.navigator.goal, messages.position_to_goal(np.array(robot["goal"]), stamp, "odom"))

    def tick(self):
        """Advance the clock by one control period: one decision; its Twist and diagnostic status. The decision is
        the one whose diagnostics carry the new time; every decision publishes one Twist, then one status, so the
        k-th Twist is the k-th status's (an earlier decision's messages may still be on their way)."""
        from socnav.ros2.messages import stamp_to_ns

        self.now_ns += STEP_NS
        self._publish_clock()
        stamps = lambda: [stamp_to_ns(report.header.stamp) for report in self.diagnostics]  # noqa: E731
        self.spin_until(lambda: self.now_ns in stamps(), "a decision")
        index = stamps().index(self.now_ns)
        self.spin_until(lambda: len(self.twists) > index, "its Twist")
        status = self.diagnostics[index].status[0]
        return self.twists[index], status, {value.key: value.value for value in status.values}

    def close(self) -> None:
        self.executor.shutdown()
        self.navigator.destroy_node()
        self.driver.destroy_node()


@pytest.fixture
def graph(ros_context, navigator_file):
    graph = Graph(ros_context, navigator_file)
    yield graph
    graph.close()


def _is_stop(twist) -> bool:
    return (twist.linear.x, twist.linear.y, twist.angular.z) == (0.0, 0.0, 0.0)


def test_the_command_is_the_navigators(graph, navigator_file):
    """Three decisions on one state: the Twist carries SafeNavigator.act's (v, dtheta / dt) decision for decision
    (same seed, so the same MC-dropout masks), the state topics its fallback and uncertainty."""
    reference = SafeNavigator.load(navigator_file, seed=3)
    for _ in range(3):
        graph.send_state()
        twist, status, values = graph.tick()
        decision = reference.act({**ROBOT, "v_pref": 0.9}, HUMANS)
        assert twist.linear.x == pytest.approx(decision.speed, abs=1e-9)
        assert twist.angular.z == pytest.approx(decision.turn / 0.25, abs=1e-9)
        assert values["fallback"] == str(decision.fallback)
        assert float(values["u_feat"]) == pytest.approx(decision.windowed["u_feat"], rel=1e-9)
        assert status.level in (status.OK, status.WARN) and values["stopped"] == "False"
        assert not _is_stop(twist)


def _nan_position(odometry, cloud):
    odometry.pose.pose.position.x = math.nan


def _nan_human(odometry, cloud):
    data = bytearray(cloud.data)
    data[8 * 5 + 16: 8 * 5 + 24] = np.array([math.nan]).tobytes()  # the second human's vx
    cloud.data = bytes(data)


def _other_frame(odometry, cloud):
    cloud.header.frame_id = "map"


def _zero_quaternion(odometry, cloud):
    odometry.pose.pose.orientation.z = odometry.pose.pose.orientation.w = 0.0


def _no_rows(odometry, cloud):
    cloud.height = 0  # 0 points, but 120 bytes of data: a malformed cloud, not "no humans"


BAD_INPUTS = {
    "stale odometry and humans": (dict(stamp_ns=START_NS), "odometry is stale: 0.750 s old"),
    "odometry from the future": (dict(stamp_ns=START_NS + 10**10), "odometry is stamped"),
    "NaN odometry": (dict(change=_nan_position), "odometry is not finite"),
    "NaN human": (dict(change=_nan_human), r"humans cloud: vx, vy not finite \(NaN or inf\) at points \[1\]"),
    "humans in another frame": (dict(change=_other_frame), "humans cloud.header.frame_id is 'map'"),
    "unset orientation": (dict(change=_zero_quaternion), "not a unit quaternion"),
    "a cloud of height 0 with data": (dict(change=_no_rows), r"humans cloud data has 120 bytes; row_step 120 x "
                                                             r"height 0 = 0"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_a_bad_input_stops_the_robot_and_says_why(graph, case):
    settings, reason = BAD_INPUTS[case]
    graph.send_state()
    assert not _is_stop(graph.tick()[0])
    graph.now_ns += STEP_NS  # stale inputs: 0.75 s old at the next tick
    graph.send_state(**settings)
    twist, status, values = graph.tick()
    assert _is_stop(twist)
    assert status.level == status.ERROR and values["stopped"] == "True"
    assert re.search(reason, status.message), status.message
    graph.send_state()  # good messages again: the node kept running and drives
    twist, status, _ = graph.tick()
    assert not _is_stop(twist) and status.level != status.ERROR


def test_wall_clock_stamps_on_a_simulated_clock_are_a_clock_mismatch(graph, monkeypatch):
    """The node on /clock (10 s), the inputs stamped with the wall clock: the diagnostic names the clock mismatch
    and use_sim_time at every decision; the log says it once, not once per decision."""
    import types

    warnings: list[str] = []
    logger = types.SimpleNamespace(warning=warnings.append, error=warnings.append, info=lambda *_: None)
    monkeypatch.setattr(graph.navigator, "get_logger", lambda: logger)
    for _ in range(6):
        graph.send_state(stamp_ns=time.time_ns())
        twist, status, _ = graph.tick()
        assert _is_stop(twist) and status.level == status.ERROR
        expected = (r"stopped: odometry stamp is \d+ s ahead of the node clock: a clock mismatch; the node uses "
                    r"simulated time \(use_sim_time\) but the publisher does not: start the navigator without "
                    r"--use-sim-time, or stamp the messages with /clock")
        assert re.fullmatch(expected, status.message), status.message
    assert [line for line in warnings if "clock mismatch" in line] == [graph.diagnostics[-6].status[0].message]


def test_stale_humans_alone_stop_the_robot(graph):
    from socnav.ros2 import messages

    graph.send_state()
    graph.tick()
    for _ in range(2):  # odometry keeps coming, the tracker went silent
        odometry = messages.robot_to_odometry(np.array(ROBOT["position"]), np.zeros(2), 1.2, 0.0,
                                              graph.now_ns + STEP_NS, "odom", "base_link")
        graph.send(graph.odometry, graph.navigator.odometry, odometry)
        twist, status, _ = graph.tick()
    assert _is_stop(twist) and status.message.startswith("stopped: humans is stale: 0.750 s old")


def test_no_goal_then_a_nan_goal_then_a_reached_goal(graph):
    from socnav.ros2 import messages

    graph.send_state(goal=False)
    twist, status, _ = graph.tick()
    assert _is_stop(twist) and status.level == status.OK and status.message == "stopped: no goal yet"
    goal = messages.position_to_goal(np.array([0.0, 4.0]), graph.now_ns, "odom")
    goal.pose.position.x = math.nan
    graph.send(graph.goal, graph.navigator.goal, goal)
    graph.send_state(goal=False)
    twist, status, _ = graph.tick()
    assert _is_stop(twist) and status.level == status.ERROR and "goal is not finite" in status.message
    # the robot 0.2 m from its goal, inside the default tolerance (the navigator's env config: 0.3 m)
    graph.send_state(robot={**ROBOT, "goal": [0.0, -3.8]})
    twist, status, values = graph.tick()
    assert _is_stop(twist) and status.level == status.OK
    assert status.message == "stopped: goal reached (0.200 m from it)"
    assert float(values["goal_distance"]) == pytest.approx(0.2)


def test_a_new_goal_starts_a_new_task(graph):
    """The uncertainty window is reset by a goal at a new position, not by the same goal sent again."""
    graph.send_state()
    first = graph.tick()[2]
    graph.send_state()
    second = graph.tick()[2]
    assert float(second["u_feat"]) != float(first["u_feat"])  # a window of two decisions
    graph.send_state(robot={**ROBOT, "goal": [1.0, 4.0]})
    third = graph.tick()[2]
    navigator = SafeNavigator.load(graph.navigator.navigator.network.path, seed=3)
    decisions = [navigator.act({**ROBOT, "v_pref": 0.9, "goal": goal}, HUMANS) for goal in ([0, 4], [0, 4])]
    navigator.reset()
    decisions.append(navigator.act({**ROBOT, "v_pref": 0.9, "goal": [1.0, 4.0]}, HUMANS))
    for values, decision in zip((first, second, third), decisions, strict=True):
        assert float(values["u_feat"]) == pytest.approx(decision.windowed["u_feat"], rel=1e-9)


def test_parameters_are_checked(graph, ros_context):
    from rclpy.parameter import Parameter

    from socnav.ros2.navigator import NavigatorSetupError

    results = graph.navigator.set_parameters([Parameter("preferred_speed", value=5.0)])
    assert not results[0].successful and "preferred_speed must be > 0 and <= 1.0" in results[0].reason
    assert graph.navigator.set_parameters([Parameter("preferred_speed", value=0.6)])[0].successful
    assert graph.navigator.settings["preferred_speed"] == 0.6
    assert not graph.navigator.set_parameters([Parameter("odom_frame", value="map")])[0].successful  # read-only
    with pytest.raises(NavigatorSetupError, match=r"parameter max_input_age must be > 0, got -1\.0"):
        Graph(ros_context, graph.navigator.navigator.network.path, max_input_age=-1.0)


def test_no_message_crashes_the_node_and_every_command_is_safe(ros_context, navigator_file):
    """300 decisions on random messages — NaN, inf, huge and tiny numbers, wrong frames, unset quaternions, random
    cloud bytes — fed to the node's callbacks: none raises; each command is finite and within the robot's limits,
    and a zero Twist whenever an input held a non-finite number or another frame."""
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2, PointField

    from socnav.ros2 import messages
    from socnav.ros2.navigator import NavigatorNode

    node = NavigatorNode(parameter_overrides=[Parameter("model", value=str(navigator_file)),
                                              Parameter("seed", value=0)], context=ros_context)
    twists = []

    class Capture:
        def publish(self, twist):
            twists.append(twist)

    node.cmd_vel = Capture()
    rng = np.random.default_rng(0)
    nasty = [math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, 0.0]
    stops = 0
    for _ in range(300):
        values = {name: float(rng.normal(scale=3.0)) for name in ("x", "y", "vx", "vy", "heading", "gx", "gy")}
        for name in values:
            if rng.random() < 0.05:
                values[name] = nasty[rng.integers(len(nasty))]
        invalid = not all(math.isfinite(value) for value in values.values())
        stamp = node.get_clock().now().nanoseconds
        heading = values["heading"] if math.isfinite(values["heading"]) else 0.0
        odometry = messages.robot_to_odometry(np.array([values["x"], values["y"]]),
                                              np.array([values["vx"], values["vy"]]), heading, 0.0, stamp, "odom",
                                              "base_link")
        if not math.isfinite(values["heading"]):  # a driver's broken orientation
            odometry.pose.pose.orientation.z = values["heading"]
        if rng.random() < 0.05:
            odometry.child_frame_id, invalid = "base_footprint", True
        if rng.random() < 0.05:
            odometry.pose.pose.orientation.w = odometry.pose.pose.orientation.z = 0.0
            invalid = True
        count = int(rng.integers(0, 12))
        positions, velocities = rng.normal(scale=3.0, size=(2, count, 2))
        if count and rng.random() < 0.1:
            positions[rng.integers(count), rng.integers(2)] = nasty[rng.integers(3)]  # NaN or inf
            invalid = True
        cloud = messages.humans_to_cloud(positions, velocities, np.abs(rng.normal(0.3, 0.1, count)), stamp, "odom")
        if count and rng.random() < 0.1:  # random bytes: refused, or read as whatever numbers they hold
            cloud = PointCloud2(height=1, width=count, point_step=int(rng.integers(0, 48)),
                                row_step=int(rng.integers(0, 400)), data=rng.bytes(int(rng.integers(0, 400))),
                                fields=[PointField(name=name, offset=int(rng.integers(0, 40)),
                                                   datatype=int(rng.integers(1, 9)), count=1)
                                        for name in ("x", "y", "vx", "vy")])
            cloud.header.frame_id = "odom"
        goal = messages.position_to_goal(np.array([values["gx"], values["gy"]]), stamp, "odom")
        for callback, message in ((node._on_odometry, odometry), (node._on_humans, cloud), (node._on_goal, goal)):
            callback(message)
        node._decide(time.perf_counter())
        twist = twists[-1]
        assert math.isfinite(twist.linear.x) and math.isfinite(twist.angular.z)
        assert 0.0 <= twist.linear.x <= node.settings["preferred_speed"] + 1e-9
        assert abs(twist.angular.z) * node.time_step <= node.navigator.config.max_heading_change + 1e-9
        if invalid:
            assert (twist.linear.x, twist.angular.z) == (0.0, 0.0)
        stops += (twist.linear.x, twist.angular.z) == (0.0, 0.0)
    assert node.decisions == 300 and 30 < stops < 270  # both kinds of decisions were exercised
    node.destroy_node()


class _FakeRclpy:
    """rclpy's init / ok / shutdown / try_shutdown, as `socnav.cli.ros2._spin` uses them, on a flag."""

    def __init__(self) -> None:
        self.alive = False

    def init(self, args: list[str]) -> None:
        self.alive = True

    def ok(self) -> bool:
        return self.alive

    def shutdown(self) -> None:
        self.alive = False

    def try_shutdown(self) -> None:
        self.alive = False


class _Node:
    destroyed = False

    def destroy_node(self) -> None:
        self.destroyed = True


def test_a_context_shut_down_by_ctrl_c_while_spinning_is_a_clean_interruption(capsys):
    """rclpy's SIGINT handler shuts the context down; an executor building its wait set just then raises RCLError
    ("the given context is not valid"): the node exits as for any Ctrl-C. The same error while ROS 2 is still up
    is a real failure and propagates."""
    from socnav.cli.ros2 import _spin

    rclpy = _FakeRclpy()
    node = _Node()

    def interrupted(_node: _Node) -> None:
        rclpy.alive = False  # what rclpy's signal handler does
        raise RuntimeError("failed to initialize wait set: the given context is not valid")

    _spin(rclpy, [], lambda: node, interrupted)
    assert node.destroyed and "interrupted" in capsys.readouterr().out

    def broken(_node: _Node) -> None:
        raise RuntimeError("something else")

    with pytest.raises(RuntimeError, match="something else"):
        _spin(_FakeRclpy(), [], _Node, broken)


def test_the_node_decides_with_a_trigger_file(ros_context, navigator_file, tmp_path):
    """`thresholds` may name a trigger file (socnav.safety.triggers): the node's navigator decides with it."""
    from rclpy.parameter import Parameter

    from socnav.ros2.navigator import NavigatorNode
    from socnav.safety.triggers import TriggerSpec, save_trigger_spec

    spec = TriggerSpec.create(trigger="time-to-collision", threshold=-2.0)
    path = save_trigger_spec(spec, tmp_path / "ttc.yaml")
    node = NavigatorNode(parameter_overrides=[Parameter("model", value=str(navigator_file)),
                                              Parameter("thresholds", value=str(path)),
                                              Parameter("seed", value=0)], context=ros_context)
    try:
        assert node.navigator.thresholds == spec
        assert type(node.navigator.trigger).__name__ == "TimeToCollisionTrigger"
    finally:
        node.destroy_node()
