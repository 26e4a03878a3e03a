"""`SimulatorNode`: socnav's crowd world as a ROS 2 node (``socnav ros2 sim``), standing in for a robot and its
tracker: it publishes what they would, steps the world with ``cmd_vel``, and writes each episode's record.

Each step of ``dt`` (the env config's ``time_step``), stamped with the simulated time it starts at:

* ``/clock`` (rosgraph_msgs/Clock: the simulated time, for nodes with ``use_sim_time``), the goal
  (geometry_msgs/PoseStamped), the robot's odometry (nav_msgs/Odometry, twist in ``base_link``), in a world with a
  range scan the scan (sensor_msgs/LaserScan in ``base_link``: the world's own, the layout the policy trained with),
  the humans (sensor_msgs/PointCloud2, FLOAT64 fields x, y, vx, vy, radius: the world's exact state; in a world with
  occlusion, those the robot sees, as the policy's observation has them) and ``~/markers``;
* then the world steps with the latest command: ``v = linear.x``, ``dtheta = angular.z dt`` turned into the
  environment's action ``a = (2 v / v_pref - 1, dtheta / max_heading_change)`` (clipped to [-1, 1] by the world).

Real time (default): one step every ``dt / real_time_factor`` s of wall time, with the last command received (a stop
once it is older than ``command_timeout`` s of simulated time, as a robot base's watchdog does). Lock-step
(``lockstep``): after publishing a step, the node waits for the navigator's command for it (the navigator runs with
``lockstep:=true`` and answers each set of inputs exactly once), so the episode is the one an in-process evaluation
plays, whatever the machine's load.

A world with walls publishes them once, at start, as a nav_msgs/OccupancyGrid on ``map`` (transient local, as
map_server does; frame ``map_frame``, ``map_resolution`` m per cell: `socnav.ros2.messages.walls_to_grid`), and waits
(at most ``wait_timeout``) for the navigator to have it before the first step. Its odometry frame is the map frame:
a navigator leaves its ``pose_topic`` empty.

Episode ``k`` is seeded ``seed + k`` (as `socnav.envs.rollout.rollout_episodes` seeds it); its record
(`EPISODE_COLUMNS`, as ``socnav evaluate`` writes them) is appended to ``out`` when it ends. Before each episode
the node sets the navigator's ``preferred_speed`` and ``robot_radius`` parameters (the episode's robot: its
preferred speed is drawn per episode), unless ``navigator_node`` is empty. Observation noise (a perturbation) is not
applied: the humans are published as the world has them. ``record`` writes every published and received message to
an MCAP file (`McapRecorder`).
"""

from __future__ import annotations

import importlib
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from geometry_msgs.msg import Point, PoseStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import Parameter as ParameterMessage
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.client import Client
from rclpy.duration import Duration
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import LaserScan, PointCloud2
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from socnav.config import EnvConfig
from socnav.envs.rollout import EPISODE_COLUMNS
from socnav.io import write_table_atomic
from socnav.ros2.messages import (
    MessageError,
    humans_to_cloud,
    ns_to_stamp,
    position_to_goal,
    ranges_to_scan,
    robot_to_odometry,
    twist_to_command,
    walls_to_grid,
)
from socnav.ros2.recording import McapRecorder
from socnav.sim.world import CrowdWorld

__all__ = ["DEFAULT_NODE_NAME", "SimulatorError", "SimulatorNode"]

DEFAULT_NODE_NAME = "socnav_sim"
_NS = 1_000_000_000
#: seconds a lock-step simulator waits for a command before it sends the step's messages again (same stamp)
RESEND_PERIOD = 1.0
#: wall seconds between two "still waiting" lines while the simulator waits for the navigator or its command
WAIT_REPORT_PERIOD = 10.0
#: Navigator topics recorded besides the simulator's own (relative to the navigator node's name).
_NAVIGATOR_TOPICS = (("fallback", "std_msgs/msg/Bool"), ("uncertainty", "std_msgs/msg/Float64MultiArray"),
                     ("latency", "std_msgs/msg/Float64"), ("markers", "visualization_msgs/msg/MarkerArray"),
                     ("subgoal", "geometry_msgs/msg/PointStamped"))
#: The map's publisher: reliable and transient local, as map_server's (a navigator that starts later still gets it).
MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class SimulatorError(RuntimeError):
    """The simulation cannot go on: no navigator showed up, or in lock-step none answered in time."""


def _descriptor(description: str) -> ParameterDescriptor:
    return ParameterDescriptor(description=description, read_only=True)


class SimulatorNode(Node):
    """The crowd world as a ROS 2 node; see the module's docstring and docs/ros2.md.

    :param config: the world. :param episodes: episodes to play (>= 1). :param seed: episode ``k`` uses ``seed + k``.
    :param out: the per-episode records (.csv or .parquet; None: not written). :param record: an ``.mcap`` file to
        record to (None: none). :param lockstep: wait for the navigator's command at every step.
    :param real_time_factor: simulated seconds per wall second (real-time mode).
    """

    def __init__(self, config: EnvConfig, episodes: int = 1, seed: int = 0, out: str | Path | None = None,
                 record: str | Path | None = None, lockstep: bool = False, real_time_factor: float = 1.0,
                 node_name: str = DEFAULT_NODE_NAME, parameter_overrides: list[Parameter] | None = None,
                 context: Any = None) -> None:
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        if not (math.isfinite(real_time_factor) and real_time_factor > 0.0):
            raise ValueError(f"real_time_factor must be > 0, got {real_time_factor}")
        super().__init__(node_name, parameter_overrides=parameter_overrides, context=context)
        declare = self.declare_parameter
        topics = {name: declare(f"{name}_topic", default, _descriptor(f"topic of the {name}")).value
                  for name, default in (("odom", "odom"), ("humans", "humans"), ("goal", "goal_pose"),
                                        ("cmd_vel", "cmd_vel"), ("scan", "scan"), ("map", "map"))}
        self.odom_frame = declare("odom_frame", "odom", _descriptor("the world's frame")).value
        self.base_frame = declare("base_frame", "base_link", _descriptor("the robot's frame (and the scan's)")).value
        self.map_frame = declare("map_frame", "map", _descriptor(
            "the map's frame (the world's frame under another name: the odometry frame is the map frame)")).value
        map_resolution = declare("map_resolution", 0.05, _descriptor("metres per cell of the published map")).value
        self.navigator_node = declare("navigator_node", "socnav_navigator", _descriptor(
            "node whose preferred_speed and robot_radius are set before each episode ('': none)")).value
        self.command_timeout = float(declare("command_timeout", 0.5, _descriptor(
            "real time: a command older than this (simulated s) is replaced by a stop")).value)
        self.wait_timeout = float(declare("wait_timeout", 60.0, _descriptor(
            "wall seconds to wait for the navigator at start, and in lock-step for each command")).value)
        self.config, self.episodes, self.seed, self.lockstep = config, int(episodes), int(seed), bool(lockstep)
        self.out = None if out is None else Path(out)
        self.real_time_factor = float(real_time_factor)
        self.world = CrowdWorld(config, 1)
        self.time_step = float(config.time_step)
        self._step_ns = round(self.time_step * _NS)
        self.now_ns = self._step_ns  # simulated time of the current step (never 0: ROS reads 0 as "no time yet")
        self.grid = None if self.world.walls is None else self._grid(map_resolution)
        self.records: list[dict[str, Any]] = []
        self.episode = -1
        self._command: tuple[float, float] | None = None
        self._command_ns = 0
        self.commands_received = 0
        self._turn_rate = 0.0
        self.recorder = None if record is None else McapRecorder(record)
        self.clock = self.create_publisher(Clock, "/clock", 10)
        self.goal = self.create_publisher(PoseStamped, topics["goal"], 10)
        self.odometry = self.create_publisher(Odometry, topics["odom"], 10)
        self.humans = self.create_publisher(PointCloud2, topics["humans"], 10)
        self.scan = None if config.scan is None else self.create_publisher(LaserScan, topics["scan"], 10)
        self.map = None if self.grid is None else self.create_publisher(OccupancyGrid, topics["map"], MAP_QOS)
        self.markers = self.create_publisher(MarkerArray, "~/markers", 10)
        self.create_subscription(Twist, topics["cmd_vel"], self._on_cmd_vel, 10)
        self.cmd_vel_topic = self.resolve_topic_name(topics["cmd_vel"])
        # (not `_parameters`: rclpy's Node keeps its own parameters under that name)
        self._navigator_parameters: Client | None = None
        if self.navigator_node:
            name = self.navigator_node if self.navigator_node.startswith("/") else f"/{self.navigator_node}"
            self._navigator_parameters = self.create_client(SetParameters, f"{name}/set_parameters")
            if self.recorder is not None:
                for topic, type_name in (*((f"{name}/{topic}", kind) for topic, kind in _NAVIGATOR_TOPICS),
                                         ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")):
                    self._record_topic(self.recorder, topic, type_name)

    def _grid(self, resolution: Any) -> OccupancyGrid:
        """The world's walls as the occupancy grid the node publishes on ``map``.

        :raises ValueError: naming parameter ``map_resolution``: not a number > 0, or too fine for the walls."""
        assert self.world.walls is not None
        if isinstance(resolution, bool) or not isinstance(resolution, (int, float)):
            raise ValueError(f"parameter map_resolution must be a number of metres per cell > 0, got {resolution!r}")
        try:
            return walls_to_grid(self.world.walls.polygons, float(resolution), self.now_ns, self.map_frame)
        except ValueError as exc:
            raise ValueError(f"parameter map_resolution: {exc}") from None

    # ------------------------------------------------------------------------------------------------- inputs

    def _record_topic(self, recorder: McapRecorder, topic: str, type_name: str) -> None:
        """Record another node's topic as it arrives (serialized, not decoded), at the current simulated time."""
        package, _, name = type_name.split("/")
        message_type = getattr(importlib.import_module(f"{package}.msg"), name)
        self.create_subscription(message_type, topic, lambda data: recorder.write(topic, data, self.now_ns, type_name),
                                 10, raw=True)

    def _on_cmd_vel(self, message: Twist) -> None:
        try:
            self._command = twist_to_command(message, self.time_step)
        except MessageError as exc:
            self.get_logger().warning(f"{exc}: the robot stops")
            self._command = (0.0, 0.0)
        self._command_ns = self.now_ns
        self.commands_received += 1
        if self.recorder is not None:
            self.recorder.write(self.cmd_vel_topic, message, self.now_ns)

    # ------------------------------------------------------------------------------------------------- running

    def run(self, executor: Executor | None = None) -> pd.DataFrame:
        """Play every episode and return their records (one row each, `EPISODE_COLUMNS`).

        :param executor: spins this node (and any other node the caller added to it); None: one of its own.
        :raises SimulatorError: no navigator in ``wait_timeout`` s, or (lock-step) no command in time.
        """
        if executor is None:
            executor = SingleThreadedExecutor(context=self.context)
            executor.add_node(self)
        try:
            if self.map is not None:
                self._publish(self.map, self.grid)
            self._wait_for_navigator(executor)
            self._wait_for_map_delivery(executor)
            self._begin_episode(executor)
            (self._run_lockstep if self.lockstep else self._run_real_time)(executor)
        finally:
            if self.recorder is not None:
                self.recorder.close()
        return self.frame()

    def frame(self) -> pd.DataFrame:
        """The records of the episodes played so far: episode, seed, then the world's episode summary."""
        if not self.records:
            return pd.DataFrame(columns=list(EPISODE_COLUMNS))
        return pd.DataFrame.from_records(self.records)

    def _spin_until(self, executor: Executor, done: Any, timeout: float, what: str, resend: Any = None,
                    waiting: Any = None) -> None:
        """Spin until `done()`; `resend()`, if given, every RESEND_PERIOD s while waiting; `waiting(seconds)`, if
        given, returns a line logged every WAIT_REPORT_PERIOD s while waiting (so a wait is never silent)."""
        started = time.monotonic()
        deadline = started + timeout
        next_resend = started + RESEND_PERIOD
        next_report = started + WAIT_REPORT_PERIOD
        while not done():
            now = time.monotonic()
            if now > deadline:
                raise SimulatorError(f"{what} within {timeout:g} s (parameter wait_timeout)")
            if resend is not None and now >= next_resend:
                resend()
                next_resend = now + RESEND_PERIOD
            if waiting is not None and now >= next_report:
                self.get_logger().warning(waiting(now - started))
                next_report = now + WAIT_REPORT_PERIOD
            executor.spin_once(timeout_sec=0.01)

    def _navigator_missing(self) -> list[str]:
        """What the graph still lacks of a navigator: a subscriber on odometry, humans, goal, a publisher on
        cmd_vel, the navigator node's parameter service (empty: it is there)."""
        missing = [f"a subscriber on {publisher.topic_name}" for publisher in (self.odometry, self.humans, self.goal)
                   if publisher.get_subscription_count() == 0]
        if self.count_publishers(self.cmd_vel_topic) == 0:
            missing.append(f"a publisher on {self.cmd_vel_topic}")
        if self._navigator_parameters is not None and not self._navigator_parameters.service_is_ready():
            missing.append(f"the parameter service of node {self.navigator_node}")
        return missing

    def _wait_for_navigator(self, executor: Executor) -> None:
        """Until the navigator subscribes to odometry, humans and goal and publishes on cmd_vel (and its
        parameter service is up): nothing published before that would reach it. Says so at once, and every
        WAIT_REPORT_PERIOD s, naming what is missing."""
        if self._navigator_missing():
            self.get_logger().info(
                f"waiting for a navigator (up to {self.wait_timeout:g} s, parameter wait_timeout): one that subscribes "
                f"to {self.odometry.topic_name}, {self.humans.topic_name} and {self.goal.topic_name} and publishes "
                f"{self.cmd_vel_topic}"
                + (f", node {self.navigator_node}" if self._navigator_parameters else "")
                + f", e.g. socnav ros2 navigator --model FILE --use-sim-time{' --lockstep' if self.lockstep else ''}")
        self._spin_until(executor, lambda: not self._navigator_missing(), self.wait_timeout,
                         f"no navigator subscribed to {self.odometry.topic_name}, {self.humans.topic_name} and "
                         f"{self.goal.topic_name} and published on {self.cmd_vel_topic}"
                         + (f" (with node {self.navigator_node})" if self._navigator_parameters else ""),
                         waiting=lambda seconds: f"still waiting for a navigator after {seconds:.0f} s; missing: "
                                                 f"{', '.join(self._navigator_missing())}")
        self.get_logger().info("navigator found: starting")

    def _wait_for_map_delivery(self, executor: Executor) -> None:
        """Until every subscriber of the map acknowledged it (spinning meanwhile, for a navigator in this process),
        so that the first step is decided on the map: at most ``wait_timeout`` s, then a warning and on."""
        if self.map is None or self.map.get_subscription_count() == 0:
            return
        try:
            self._spin_until(executor, lambda: self.map.wait_for_all_acked(Duration(seconds=0)), self.wait_timeout,
                             f"the map on {self.map.topic_name} was not acknowledged by its subscribers")
        except SimulatorError as exc:
            self.get_logger().warning(f"{exc}: starting all the same")

    def _begin_episode(self, executor: Executor) -> None:
        """Start the next episode (seed ``seed + k``), tell the navigator its robot, publish its first state."""
        self.episode += 1
        self.world.seed(0, self.seed + self.episode)
        self.world.reset([0])
        self._turn_rate, self._command = 0.0, None
        if self._navigator_parameters is not None:
            self._configure_navigator(executor, self._navigator_parameters)
        self._publish_state()

    def _configure_navigator(self, executor: Executor, client: Client) -> None:
        """Set the navigator's preferred_speed and robot_radius to this episode's robot (its SetParameters
        `client`), waiting for the answer."""
        values = {"preferred_speed": float(self.world.preferred_speeds[0, 0]),
                  "robot_radius": float(self.world.radii[0, 0])}
        request = SetParameters.Request(parameters=[
            ParameterMessage(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value))
            for name, value in values.items()])
        future = client.call_async(request)
        # Waited for, so that the episode's first decision already knows its robot (a few ms, between episodes)
        self._spin_until(executor, future.done, self.wait_timeout,
                         f"node {self.navigator_node} did not answer set_parameters")
        refused = [result.reason for result in future.result().results if not result.successful]
        if refused:
            message = f"node {self.navigator_node} refused {values}: {'; '.join(refused)}"
            if self.lockstep:  # the episode would not be the one asked for
                raise SimulatorError(message)
            self.get_logger().error(message)

    def _run_lockstep(self, executor: Executor) -> None:
        while len(self.records) < self.episodes:
            self._advance(executor, self._next_command(executor))

    def _next_command(self, executor: Executor) -> tuple[float, float]:
        """Lock-step: wait for the navigator's command for the step just published, sending the step again every
        RESEND_PERIOD s meanwhile."""
        answered = self.commands_received
        self._spin_until(executor, lambda: self.commands_received > answered, self.wait_timeout,
                         f"no command on {self.cmd_vel_topic} for step {self.world.steps[0]} of episode "
                         f"{self.episode} (is the navigator running with lockstep:=true?)",
                         resend=self._resend_state,
                         waiting=lambda seconds: f"still waiting for the command of step {self.world.steps[0]} of "
                                                 f"episode {self.episode} on {self.cmd_vel_topic} after "
                                                 f"{seconds:.0f} s (is the navigator running with lockstep:=true?)")
        command = self._command
        assert command is not None  # `_on_cmd_vel` set it: it counted the command just received
        return command

    def _resend_state(self) -> None:
        """The step's messages again, same stamp, not recorded: one lost before a subscriber was matched (a relay
        node starting, a graph still discovering) would otherwise stall the lock-step for good; a navigator decides
        once per stamp, so a repeat changes nothing else."""
        self._publish_state(record=False)

    def _run_real_time(self, executor: Executor) -> None:
        period = self.time_step / self.real_time_factor
        next_step = time.monotonic() + period
        while len(self.records) < self.episodes:
            executor.spin_once(timeout_sec=max(0.0, next_step - time.monotonic()))
            if time.monotonic() < next_step:
                continue
            next_step += period
            self._advance(executor, self._fresh_command())

    def _fresh_command(self) -> tuple[float, float]:
        """Real time: the last command received, or a stop once it is older than ``command_timeout`` s of simulated
        time (a robot base's watchdog)."""
        command = self._command
        if command is not None and self.now_ns - self._command_ns <= self.command_timeout * _NS:
            return command
        return (0.0, 0.0)

    def _advance(self, executor: Executor, command: tuple[float, float]) -> None:
        """Step the world with ``(v, dtheta)``; record an ended episode and begin the next (or stop)."""
        world = self.world
        speed, turn = command
        v_pref, heading = world.preferred_speeds[0, 0], world.heading[0]
        action = np.array([[2.0 * speed / v_pref - 1.0, turn / self.config.max_heading_change]])
        result = world.step(action)
        self._turn_rate = math.remainder(world.heading[0] - heading, 2.0 * math.pi) / self.time_step
        self.now_ns += self._step_ns
        if not (result.terminated[0] or result.truncated[0]):
            self._publish_state()
            return
        summary = world.episode_summary(0, int(result.outcome[0]))
        self.records.append({"episode": self.episode, "seed": self.seed + self.episode, **summary})
        self.get_logger().info(f"episode {self.episode} (seed {self.seed + self.episode}): {summary['outcome']} "
                               f"after {summary['length']} steps")
        if self.out is not None:
            write_table_atomic(self.frame(), self.out)
        if len(self.records) < self.episodes:
            self._begin_episode(executor)

    # ------------------------------------------------------------------------------------------------- output

    def _publish(self, publisher: Any, message: Any, record: bool = True) -> None:
        """Publish (and record) one message; once a signal shut the context down, end the run instead (a publish
        would raise RCLError "publisher's context is invalid")."""
        if not self.context.ok():
            raise ExternalShutdownException()
        publisher.publish(message)
        if self.recorder is not None and record:
            self.recorder.write(publisher.topic_name, message, self.now_ns)

    def _publish_state(self, record: bool = True) -> None:
        """This step's clock, goal, odometry, scan, humans and markers, all stamped with the simulated time; the
        humans last, so that a navigator deciding on them has the rest."""
        world, stamp = self.world, self.now_ns
        humans = np.flatnonzero(world.active[0, 1:]) + 1
        seen = humans[world.in_sight[0, humans]] if world.occlusion else humans  # a tracker sees no one behind walls
        self._publish(self.clock, Clock(clock=ns_to_stamp(stamp)), record)
        self._publish(self.goal, position_to_goal(world.goals[0, 0], stamp, self.odom_frame), record)
        self._publish(self.odometry, robot_to_odometry(world.positions[0, 0], world.velocities[0, 0],
                                                       float(world.heading[0]), self._turn_rate, stamp,
                                                       self.odom_frame, self.base_frame), record)
        if self.scan is not None:
            self._publish(self.scan, self._scan_message(), record)
        self._publish(self.humans, humans_to_cloud(world.positions[0, seen], world.velocities[0, seen],
                                                   world.radii[0, seen], stamp, self.odom_frame), record)
        self._publish(self.markers, self._marker_array(humans), record)

    def _scan_message(self) -> LaserScan:
        """The robot's range scan now, as the world's observation has it (`CrowdWorld.observe`'s ``scan``: the walls'
        ranges, the full range in the open plane), computed without observing (which would move the robot's path)."""
        scan = self.config.scan
        assert scan is not None
        ranges = self.world.range_scan(np.zeros(1, dtype=np.int64))[0]
        return ranges_to_scan(ranges, self.now_ns, self.base_frame, scan.fov, scan.range, self.time_step)

    def _marker_array(self, humans: np.ndarray) -> MarkerArray:
        """The world as the simulator has it: humans and their personal spaces, the robot and its heading, the
        goal; a DELETEALL first drops humans that left."""
        world, stamp = self.world, ns_to_stamp(self.now_ns)
        markers = [Marker(action=Marker.DELETEALL)]

        def marker(namespace: str, ident: int, kind: int, x: float, y: float, size: tuple[float, float, float],
                   color: tuple[float, float, float, float]) -> Marker:
            item = Marker(ns=namespace, id=ident, type=kind, action=Marker.ADD)
            item.header.frame_id, item.header.stamp = self.odom_frame, stamp
            item.pose.position = Point(x=float(x), y=float(y), z=size[2] / 2.0)
            item.pose.orientation.w = 1.0
            item.scale.x, item.scale.y, item.scale.z = (float(value) for value in size)
            item.color = ColorRGBA(r=color[0], g=color[1], b=color[2], a=color[3])
            return item

        for index, slot in enumerate(humans):
            x, y = world.positions[0, slot]
            body, space = 2 * world.radii[0, slot], 2 * (world.radii[0, slot] + world.personal_space[0, slot])
            markers.append(marker("sim_humans", index, Marker.CYLINDER, x, y, (body, body, 1.7), (0.8, 0.5, 0.3, 0.9)))
            markers.append(marker("sim_personal_space", index, Marker.CYLINDER, x, y, (space, space, 0.01),
                                  (0.8, 0.5, 0.3, 0.25)))
        x, y = world.positions[0, 0]
        diameter = 2 * world.radii[0, 0]
        markers.append(marker("sim_robot", 0, Marker.CYLINDER, x, y, (diameter, diameter, 0.3), (0.2, 0.4, 1.0, 0.9)))
        heading = marker("sim_robot_heading", 0, Marker.ARROW, x, y, (0.6, 0.08, 0.08), (0.2, 0.4, 1.0, 1.0))
        heading.pose.orientation.z, heading.pose.orientation.w = (math.sin(world.heading[0] / 2),
                                                                  math.cos(world.heading[0] / 2))
        markers.append(heading)
        goal_size = 2 * self.config.goal_tolerance
        goal_x, goal_y = world.goals[0, 0]
        markers.append(marker("sim_goal", 0, Marker.CYLINDER, goal_x, goal_y, (goal_size, goal_size, 0.02),
                              (0.1, 0.8, 0.2, 0.8)))
        return MarkerArray(markers=markers)
