"""`NavigatorNode`: the torch-free `SafeNavigator` as a ROS 2 node (``socnav ros2 navigator``).
Odometry, goal and tracked humans in (and, as the navigator needs them, a range scan, a map, the robot's map pose and
a path); geometry_msgs/Twist on ``cmd_vel`` out, with diagnostics, state and markers.

Each decision (every ``1 / rate`` s of the node's clock — simulated time with ``use_sim_time`` — or, with
``lockstep``, once per set of odometry, humans, goal and, for a policy that reads one, scan carrying one stamp, as a
lock-step simulator sends them):

1. the inputs are checked: present, not older than ``max_input_age`` (nor stamped that far in the future: another
   clock), in the configured frames, finite (`socnav.ros2.messages`); the goal not yet reached (``goal_tolerance``);
2. `SafeNavigator.act` decides (policy, MC-dropout uncertainty, collision-probability rule, cautious fallback), with
   the scan (sensor_msgs/LaserScan on ``scan_topic``, turned into the policy's beams), the robot's map pose and the
   path (nav_msgs/Path on ``path_topic``) where they are configured;
3. the command goes out on ``cmd_vel``; the decision's state on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray),
   ``~/fallback`` (std_msgs/Bool), ``~/uncertainty`` (std_msgs/Float64MultiArray: :data:`UNCERTAINTY_NAMES`),
   ``~/latency`` (std_msgs/Float64: seconds from the triggering callback to the command's publication) and
   ``~/markers`` (visualization_msgs/MarkerArray: the ``marker_humans`` humans nearest the robot, not the whole
   crowd, so that the cost of the markers is bounded whatever the size of an accepted cloud: 10,000 humans' markers
   took 2 s a decision).

The command goes out first; the state after it, bounded in size (a fixed number of values and markers), so that no
input the node accepts slows its decisions. A stamp farther from the node's clock than :data:`CLOCK_MISMATCH_S` is
reported as a clock mismatch naming ``use_sim_time``, not as stale input. A stop's cause is logged once when it
starts, and again at most every :data:`REPEAT_LOG_S` s while it lasts (the diagnostics carry every decision's).
After the context is shut down (Ctrl-C, SIGTERM) the node publishes nothing more.

Whenever step 1 fails, or `act` refuses its input, the node publishes a zero Twist (the robot stops) and says why on
``/diagnostics`` (level ERROR for a missing, stale or invalid input; OK for "no goal yet" and "goal reached"). No
message makes a callback raise: a message is parsed once, when it arrives, and a bad one is kept as its error, so the
next decision stops the robot until a good one replaces it. A goal at a new position starts a new navigation task
(`SafeNavigator.reset`: empty uncertainty window, no held fallback).

The map: the navigator file's walls, or the map_server YAML ``map_file`` (loaded at start), replaced by every
nav_msgs/OccupancyGrid that arrives on ``map_topic`` (the latest map received wins; `SafeNavigator.set_walls`). The
robot's map pose: without ``pose_topic`` the odometry frame is the map frame; with it, each pose
(geometry_msgs/PoseWithCovarianceStamped, e.g. AMCL's ``amcl_pose``) gives the map-from-odometry correction at its
stamp (paired with the odometry nearest that stamp), which places every later odometry on the map until the next
pose, as tf's map -> odom -> base_link chain does: AMCL publishes a pose only when it updates (after the robot moved),
so a pose's age is not held against it. With a route-observing policy, the decision's subgoal goes out on
``~/subgoal``.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PointStamped, PoseStamped, PoseWithCovarianceStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.msg import Path as PathMessage
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import LaserScan, PointCloud2
from std_msgs.msg import Bool, ColorRGBA, Float64, Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from socnav.ros2.messages import (
    MessageError,
    RobotOdometry,
    TrackedHumans,
    cloud_to_humans,
    command_to_twist,
    goal_to_position,
    grid_to_walls,
    odometry_to_robot,
    path_to_waypoints,
    point_stamped,
    pose_to_map_pose,
    scan_to_ranges,
    stamp_to_ns,
)
from socnav.runtime import InputError, SafeNavigator
from socnav.sim.maps import MapError, load_map

__all__ = ["DEFAULT_NODE_NAME", "UNCERTAINTY_NAMES", "NavigatorNode", "NavigatorSetupError", "Outcome"]

DEFAULT_NODE_NAME = "socnav_navigator"
#: The order of ``~/uncertainty``'s values: the windowed uncertainties the collision rule read (NaN when none).
UNCERTAINTY_NAMES = ("u_ep_speed", "u_ep_heading", "u_al_speed", "u_al_heading", "u_feat")
#: Lock-step: how often (wall clock) a decision waiting for ``cmd_vel``'s first subscriber is retried.
_PENDING_RETRY_S = 0.01
#: Seconds between an input's stamp and the node's clock beyond which no latency explains it: two clocks (wall time
#: and a simulator's /clock, two machines' clocks) -- reported as a clock mismatch naming ``use_sim_time``.
CLOCK_MISMATCH_S = 3600.0
#: Wall seconds between two log lines of one ongoing stop's cause (the first is logged at once).
REPEAT_LOG_S = 60.0
#: Default of parameter ``marker_humans``: how many of the nearest humans get a marker.
MARKER_HUMANS = 50
#: Odometry messages kept (with ``pose_topic``) to pair a pose with the odometry nearest its stamp: 5 s at 50 Hz.
ODOMETRY_HISTORY = 256
#: What a map and a pose are received with: reliable and transient local, as map_server and AMCL publish them (a late
#: subscriber still gets the last one; a volatile publisher does not match it).
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
_NS = 1_000_000_000


class NavigatorSetupError(ValueError):
    """A parameter of the node that it cannot start with (the text names it and the allowed values)."""


@dataclass
class _Latest:
    """The last message of one input: its parsed value, or why it could not be used; its header stamp either way."""

    value: Any = None
    error: str | None = None
    stamp_ns: int | None = None
    received: int = 0


@dataclass(frozen=True)
class Outcome:
    """What one decision published: the command, whether the robot was stopped and why, the decision's state."""

    speed: float
    turn: float
    stopped: bool
    level: int  # diagnostic_msgs/DiagnosticStatus level
    message: str
    fallback: bool = False
    windowed: dict[str, float] = field(default_factory=lambda: dict.fromkeys(UNCERTAINTY_NAMES, math.nan))
    fault: str | None = None
    humans: int = 0
    goal_distance: float = math.nan
    #: What the stop's log line is keyed on: the cause without its changing numbers (None: the message itself).
    cause: str | None = None
    #: A route-observing policy's subgoal (map frame, (2,)), None otherwise.
    subgoal: np.ndarray | None = None
    #: The command's step would have met a wall of the map: the robot stands still (`Decision.wall_stop`).
    wall_stop: bool = False


def _descriptor(description: str, read_only: bool = True) -> ParameterDescriptor:
    return ParameterDescriptor(description=description, read_only=read_only)


def _map_correction(map_pose: np.ndarray, odometry: RobotOdometry) -> np.ndarray:
    """The rigid motion ``(x, y, angle)`` that takes odometry-frame coordinates to the map frame, from the robot's
    map pose and its odometry at the same time: ``p_map = R(angle) p_odom + (x, y)``, ``yaw = heading + angle``."""
    angle = float(map_pose[2]) - odometry.heading
    rotated = _rotate(odometry.position, angle)
    return np.array([map_pose[0] - rotated[0], map_pose[1] - rotated[1], angle])


def _rotate(point: np.ndarray, angle: float) -> np.ndarray:
    cos_a, sin_a = math.cos(angle), math.sin(angle)
    return np.array([cos_a * point[0] - sin_a * point[1], sin_a * point[0] + cos_a * point[1]])


class NavigatorNode(Node):
    """The safe navigator as a ROS 2 node; see the module's docstring and docs/ros2.md for topics and parameters.

    :param model: the navigator file (``socnav export``); the ``model`` parameter overrides it.
    :param node_name: the node's name. :param parameter_overrides: parameters (e.g. from a test) that take
        precedence over ``--ros-args -p``. :param context: the rclpy context (None: the default one).
    :raises NavigatorSetupError: an invalid parameter value.
    :raises socnav.runtime.NavigatorLoadError: the navigator file cannot be used.
    """

    def __init__(self, model: str | Path | None = None, node_name: str = DEFAULT_NODE_NAME,
                 parameter_overrides: list[Parameter] | None = None, context: Any = None) -> None:
        super().__init__(node_name, parameter_overrides=parameter_overrides, context=context)
        declare = self.declare_parameter
        path = declare("model", "" if model is None else str(model),
                       _descriptor("navigator file written by `socnav export`")).value
        if not path:
            raise NavigatorSetupError("parameter model is empty: name the navigator file (socnav export's output)")
        thresholds = declare("thresholds", "", _descriptor("safety thresholds: '' (the file's), mc, ensemble or a "
                                                           "`socnav calibrate` file")).value
        k = declare("k", 0, _descriptor("MC-dropout samples per decision (0: the file's)")).value
        seed = declare("seed", -1, _descriptor("seed of the MC-dropout masks (-1: fresh entropy)")).value
        self.map_file = declare("map_file", "", _descriptor(
            "map_server YAML (or socnav polygon map) loaded at start as the walls ('': the navigator file's)")).value
        self.navigator = SafeNavigator.load(path, thresholds=thresholds or None, k=k or None,
                                            seed=None if seed < 0 else seed, walls=self._file_walls())
        config = self.navigator.config
        self.time_step = float(config.time_step)
        self.rate = float(declare("rate", 1.0 / self.time_step,
                                  _descriptor("decisions (cmd_vel messages) per second of the node's clock")).value)
        self.lockstep = bool(declare("lockstep", False, _descriptor(
            "decide once per set of odometry, humans and goal with one stamp (lock-step simulators), not on a "
            "timer")).value)
        topics = {name: declare(f"{name}_topic", default, _descriptor(f"topic of the {what}")).value
                  for name, default, what in (
                      ("odom", "odom", "robot's odometry (nav_msgs/Odometry)"),
                      ("humans", "humans", "tracked humans (sensor_msgs/PointCloud2: x, y, vx, vy[, radius])"),
                      ("goal", "goal_pose", "goal (geometry_msgs/PoseStamped)"),
                      ("cmd_vel", "cmd_vel", "command (geometry_msgs/Twist)"),
                      ("diagnostics", "/diagnostics", "diagnostics (diagnostic_msgs/DiagnosticArray)"),
                      ("scan", "scan", "range scan (sensor_msgs/LaserScan), read when the policy reads one"),
                      ("map", "map", "map (nav_msgs/OccupancyGrid, transient local; '': none)"),
                      ("pose", "", "robot's map pose (geometry_msgs/PoseWithCovarianceStamped, e.g. amcl_pose; '': "
                                   "the odometry frame is the map frame)"),
                      ("path", "", "path to follow (nav_msgs/Path) for a route-observing policy ('': it plans "
                                   "its own)"))}
        self.odom_frame = declare("odom_frame", "odom", _descriptor("the odometry frame: odometry, humans and goal "
                                                                    "are in it")).value
        self.base_frame = declare("base_frame", "base_link", _descriptor("the robot's frame (odometry's "
                                                                         "child_frame_id)")).value
        self.scan_frame = declare("scan_frame", "", _descriptor(
            "the scan's frame ('': base_frame); the scanner is taken at the robot's centre, facing its "
            "heading")).value or self.base_frame
        self.map_frame = declare("map_frame", "map", _descriptor("the map frame: map, pose, path and subgoal are in "
                                                                 "it")).value
        self.map_free_thresh = declare("map_free_thresh", 0.25, _descriptor(
            "a map cell is free when its occupancy (0-100) is below 100 x this; others (and unknown) are walls")).value
        self.reads_scan = self.navigator.scan_beams is not None
        self.pose_topic, self.path_topic = topics["pose"], topics["path"]
        if self.path_topic and not self.navigator.observes_route:
            raise NavigatorSetupError(
                f"parameter path_topic is {self.path_topic!r}, but this navigator's policy does not observe a route "
                "(its env config's planner.observe is false): leave path_topic empty")
        dynamic = {
            "max_input_age": (0.5, "seconds: older odometry, humans or scan (by header stamp) stop the robot"),
            "preferred_speed": (float(config.preferred_speed[1]), "the robot's preferred speed v_pref (m/s), at "
                                                                   "most the navigator's largest"),
            "robot_radius": (float(config.robot_radius), "the robot's radius (m)"),
            "human_radius": (float(config.human_radius), "radius (m) of humans in a cloud without a radius field"),
            "goal_tolerance": (float(config.goal_tolerance), "metres: closer to the goal, the robot stops"),
        }
        for name, (default, description) in dynamic.items():
            declare(name, default, _descriptor(description, read_only=False))
        self.settings = {name: float(self.get_parameter(name).value) for name in dynamic}
        self.publish_markers = bool(declare("markers", True, _descriptor("publish ~/markers for RViz")).value)
        self.marker_humans = declare("marker_humans", MARKER_HUMANS, _descriptor(
            "markers are drawn for this many humans, the nearest to the robot (bounds the markers' cost)")).value
        if isinstance(self.marker_humans, bool) or not isinstance(self.marker_humans, int) or self.marker_humans < 0:
            raise NavigatorSetupError(f"parameter marker_humans must be an integer >= 0, got {self.marker_humans!r}")
        for name, value in [("rate", self.rate), *self.settings.items(), ("map_free_thresh", self.map_free_thresh)]:
            problem = self._problem(name, value)
            if problem:
                raise NavigatorSetupError(problem)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.odometry, self.humans, self.goal = _Latest(), _Latest(), _Latest()
        self.scan, self.map, self.pose, self.path = _Latest(), _Latest(), _Latest(), _Latest()
        #: where the navigator's walls come from, for the diagnostics
        self.walls_source = f"map_file {self.map_file}" if self.map_file else "the navigator file"
        # with pose_topic: recent odometry (to pair a pose with) and the correction of the latest pose, with its
        # stamp and whether odometry at or after that stamp was there (no nearer odometry can then come)
        self._odometry_history: deque[RobotOdometry] = deque(maxlen=ODOMETRY_HISTORY)
        self._correction: tuple[int, np.ndarray, bool] | None = None
        self._last_decided_stamp: int | None = None
        self._pending_trigger: float | None = None  # lock-step: a decision waiting for cmd_vel's first subscriber
        self._logged_cause: str | None = None  # the stop cause last logged, and when (time.monotonic)
        self._logged_at = -math.inf
        self.decisions = 0
        # Lock-step loses no message (the simulator waits for each command); on a robot, best effort also accepts
        # sensor drivers' best-effort publishers.
        sensor_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE) if self.lockstep \
            else qos_profile_sensor_data
        # The map first: an executor takes a node's ready subscriptions in creation order, so a map that is waiting
        # is in use before the inputs that arrived with it are decided on.
        if topics["map"]:
            self.create_subscription(OccupancyGrid, topics["map"], self._on_map, LATCHED_QOS)
        if self.pose_topic:
            self.create_subscription(PoseWithCovarianceStamped, self.pose_topic, self._on_pose, LATCHED_QOS)
        if self.path_topic:
            self.create_subscription(PathMessage, self.path_topic, self._on_path, 10)
        self.create_subscription(Odometry, topics["odom"], self._on_odometry, sensor_qos)
        self.create_subscription(PointCloud2, topics["humans"], self._on_humans, sensor_qos)
        self.create_subscription(PoseStamped, topics["goal"], self._on_goal, 10)
        if self.reads_scan:
            self.create_subscription(LaserScan, topics["scan"], self._on_scan, sensor_qos)
        self.cmd_vel = self.create_publisher(Twist, topics["cmd_vel"], 10)
        self.diagnostics = self.create_publisher(DiagnosticArray, topics["diagnostics"], 10)
        self.fallback_topic = self.create_publisher(Bool, "~/fallback", 10)
        self.uncertainty_topic = self.create_publisher(Float64MultiArray, "~/uncertainty", 10)
        self.latency_topic = self.create_publisher(Float64, "~/latency", 10)
        self.markers = self.create_publisher(MarkerArray, "~/markers", 10) if self.publish_markers else None
        self.subgoal_topic = self.create_publisher(PointStamped, "~/subgoal", 10) \
            if self.navigator.observes_route else None
        if self.lockstep:
            self.create_timer(_PENDING_RETRY_S, self._retry_pending, clock=Clock(clock_type=ClockType.STEADY_TIME))
        else:
            self.create_timer(1.0 / self.rate, self._on_timer)
        used = {name: topic for name, topic in topics.items() if topic and (name != "scan" or self.reads_scan)}
        self.get_logger().info(f"{self.navigator!r}; {'lock-step' if self.lockstep else f'{self.rate:g} Hz'}, "
                               f"topics {used}, frames odom {self.odom_frame!r}, base {self.base_frame!r}, map "
                               f"{self.map_frame!r}" + (f", scan {self.scan_frame!r}" if self.reads_scan else "")
                               + f"; walls from {self.walls_source}")

    def _file_walls(self) -> list[np.ndarray] | None:
        """The walls of parameter ``map_file`` (None: none named, the navigator file's walls stay)."""
        if not self.map_file:
            return None
        try:
            return load_map(self.map_file)
        except MapError as exc:
            raise NavigatorSetupError(f"parameter map_file: {exc}") from None

    # ------------------------------------------------------------------------------------------------- parameters

    def _problem(self, name: str, value: Any) -> str | None:
        """Why ``value`` is not allowed for parameter ``name`` (None: it is)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return f"parameter {name} must be a finite number, got {value!r}"
        if name == "preferred_speed" and not 0.0 < value <= self.navigator.max_speed:
            return (f"parameter preferred_speed must be > 0 and <= {self.navigator.max_speed} (the navigator's "
                    f"largest trained preferred speed), got {value}")
        if name in ("robot_radius", "human_radius") and value < 0.0:
            return f"parameter {name} must be >= 0, got {value}"
        if name in ("rate", "max_input_age", "goal_tolerance") and value <= 0.0:
            return f"parameter {name} must be > 0, got {value}"
        if name == "map_free_thresh" and not 0.0 < value <= 1.0:
            return f"parameter map_free_thresh must be > 0 and <= 1, got {value}"
        return None

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        updates = {}
        for parameter in parameters:
            if parameter.name in self.settings:
                problem = self._problem(parameter.name, parameter.value)
                if problem:
                    return SetParametersResult(successful=False, reason=problem)
                updates[parameter.name] = float(parameter.value)
        self.settings.update(updates)
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------------------------------------- inputs

    def _on_odometry(self, message: Odometry) -> None:
        self._store(self.odometry, message, "odometry",
                    lambda: odometry_to_robot(message, self.odom_frame, self.base_frame))
        if self.pose_topic and self.odometry.value is not None:
            self._odometry_history.append(self.odometry.value)

    def _on_humans(self, message: PointCloud2) -> None:
        self._store(self.humans, message, "humans",
                    lambda: cloud_to_humans(message, self.odom_frame, self.settings["human_radius"]))

    def _on_goal(self, message: PoseStamped) -> None:
        previous = self.goal.value
        self._store(self.goal, message, "goal", lambda: goal_to_position(message, self.odom_frame))
        if self.goal.value is not None and (previous is None or not np.array_equal(previous, self.goal.value)):
            self.navigator.reset()  # a new navigation task

    def _on_scan(self, message: LaserScan) -> None:
        scan = self.navigator.network.scan
        assert scan is not None  # subscribed only for a policy that reads a scan
        self._store(self.scan, message, "scan", lambda: scan_to_ranges(message, self.scan_frame, scan.beams, scan.fov))

    def _on_map(self, message: OccupancyGrid) -> None:
        self._keep(self.map, message, "map", lambda: self._use_map(message))

    def _use_map(self, message: OccupancyGrid) -> int:
        """Make the map's walls the navigator's; their number of polygons."""
        walls = grid_to_walls(message, self.map_frame, self.map_free_thresh)
        try:
            self.navigator.set_walls(walls)
        except ValueError as exc:
            raise MessageError(f"map: {exc}") from None
        self.walls_source = f"map topic ({len(walls)} polygons)"
        return len(walls)

    def _on_pose(self, message: PoseWithCovarianceStamped) -> None:
        self._keep(self.pose, message, "pose", lambda: pose_to_map_pose(message, self.map_frame))

    def _on_path(self, message: PathMessage) -> None:
        self._keep(self.path, message, "path", lambda: path_to_waypoints(message, self.map_frame))

    def _store(self, latest: _Latest, message: Any, what: str, parse: Callable[[], Any]) -> None:
        """Keep ``message`` parsed, or its problem; then, in lock-step, decide if the inputs now share a stamp."""
        started = time.perf_counter()
        self._keep(latest, message, what, parse)
        if self.lockstep:
            self._pending_trigger = started
            self._decide_if_complete()

    def _keep(self, latest: _Latest, message: Any, what: str, parse: Callable[[], Any]) -> None:
        """Keep ``message`` parsed, or its problem (never raises)."""
        latest.received += 1
        try:
            latest.stamp_ns = stamp_to_ns(message.header.stamp)
            latest.value, latest.error = parse(), None
        except MessageError as exc:
            latest.value, latest.error = None, str(exc)
        except Exception as exc:
            latest.value, latest.error = None, f"{what} message could not be read ({type(exc).__name__}: {exc})"

    def _decide_if_complete(self) -> None:
        if not self.context.ok():  # shut down (signal): the graph queries below would raise
            return
        stamps = {self.odometry.stamp_ns, self.humans.stamp_ns, self.goal.stamp_ns}
        if self.reads_scan:
            stamps.add(self.scan.stamp_ns)
        if len(stamps) != 1 or self._pending_trigger is None:
            return
        stamp = stamps.pop()
        if stamp is None:  # an input not received yet (or without a readable stamp)
            return
        if self._last_decided_stamp is not None and stamp <= self._last_decided_stamp:
            self._pending_trigger = None  # a repeated stamp: decided already
            return
        if self.cmd_vel.get_subscription_count() == 0:
            return  # nobody would receive it: `_retry_pending` decides once the simulator's subscription matched
        started, self._pending_trigger = self._pending_trigger, None
        self._last_decided_stamp = stamp
        self._decide(started)

    def _retry_pending(self) -> None:
        if self._pending_trigger is not None:
            self._decide_if_complete()

    def _on_timer(self) -> None:
        self._decide(time.perf_counter())

    # ------------------------------------------------------------------------------------------------- decision

    def _input_problem(self, latest: _Latest, what: str, now_ns: int) -> tuple[str, str] | None:
        """Why ``latest`` cannot be used now, and that reason's cause without numbers (for the log); None: it can."""
        if latest.error is not None:
            return latest.error, latest.error
        if latest.value is None or latest.stamp_ns is None:  # a parsed value always has its stamp
            return f"no {what} received yet", f"no {what}"
        age = (now_ns - latest.stamp_ns) / _NS
        limit = self.settings["max_input_age"]
        if abs(age) > CLOCK_MISMATCH_S:
            return self._clock_mismatch(what, age, now_ns), f"{what}: clock mismatch"
        if age > limit:
            return f"{what} is stale: {age:.3f} s old (max_input_age {limit:g} s)", f"{what}: stale"
        if -age > limit:
            return (f"{what} is stamped {-age:.3f} s in the future (max_input_age {limit:g} s): does it use the node's "
                    "clock (use_sim_time)?", f"{what}: in the future")
        return None

    def _clock_mismatch(self, what: str, age: float, now_ns: int) -> str:
        """The diagnostic of a stamp ``age`` s (more than :data:`CLOCK_MISMATCH_S`) from the node's clock: the
        likely cause, for the clock the node is on."""
        sim_time = bool(self.get_parameter("use_sim_time").value)
        where = f"{abs(age):.0f} s {'behind' if age > 0 else 'ahead of'} the node clock"
        if sim_time and now_ns == 0:
            hint = "the node uses simulated time (use_sim_time) and no /clock came yet: is the simulator publishing it?"
        elif sim_time:
            hint = ("the node uses simulated time (use_sim_time) but the publisher does not: start the navigator "
                    "without --use-sim-time, or stamp the messages with /clock")
        elif age > 0:
            hint = ("is the publisher on simulated time (e.g. socnav ros2 sim, publishing /clock)? start the navigator "
                    "with --use-sim-time (use_sim_time:=true)")
        else:
            hint = "the publisher's clock is far ahead of this machine's: do both use the same clock (use_sim_time)?"
        return f"{what} stamp is {where}: a clock mismatch; {hint}"

    def _decide(self, started: float) -> None:
        """One decision from the latest inputs; publishes the command and the decision's state. Raises only if the
        command cannot be published while ROS 2 is up; publishes nothing once the context is shut down."""
        if not self.context.ok():  # Ctrl-C / SIGTERM: rclpy shut the context down; a publish would raise RCLError
            return
        try:
            outcome = self._outcome(self.get_clock().now().nanoseconds)
        except Exception as exc:
            outcome = Outcome(0.0, 0.0, True, DiagnosticStatus.ERROR,
                              f"stopped: internal error ({type(exc).__name__}: {exc})")
        try:
            self.cmd_vel.publish(command_to_twist(outcome.speed, outcome.turn, self.time_step))
        except RuntimeError:  # RCLError: the context was shut down (signal) since the check above
            if self.context.ok():
                raise
            return
        latency = time.perf_counter() - started
        self.decisions += 1
        try:
            self._publish_state(outcome, latency)
        except Exception as exc:
            if self.context.ok():  # otherwise: shut down meanwhile, nothing to say
                self.get_logger().error(f"could not publish the decision's state: {type(exc).__name__}: {exc}")

    def _outcome(self, now_ns: int) -> Outcome:
        stop = DiagnosticStatus.ERROR
        problem = self._inputs_problem(now_ns)
        if problem:
            return Outcome(0.0, 0.0, True, stop, f"stopped: {problem[0]}", cause=problem[1])
        if self.goal.error is not None:
            return Outcome(0.0, 0.0, True, stop, f"stopped: {self.goal.error}")
        if self.goal.value is None:
            return Outcome(0.0, 0.0, True, DiagnosticStatus.OK, "stopped: no goal yet")
        robot: RobotOdometry = self.odometry.value
        humans: TrackedHumans = self.humans.value
        goal_distance = float(np.hypot(*(self.goal.value - robot.position)))
        if goal_distance < self.settings["goal_tolerance"]:
            return Outcome(0.0, 0.0, True, DiagnosticStatus.OK,
                           f"stopped: goal reached ({goal_distance:.3f} m from it)", humans=len(humans.radii),
                           goal_distance=goal_distance)
        state = {"position": robot.position, "velocity": robot.velocity, "heading": robot.heading,
                 "goal": self.goal.value, "v_pref": self.settings["preferred_speed"],
                 "radius": self.settings["robot_radius"]}
        try:
            decision = self.navigator.act(state, humans.as_mapping(), scan=self.scan.value if self.reads_scan else None,
                                          pose=self._map_pose(robot), path=self._given_path())
        except InputError as exc:
            return Outcome(0.0, 0.0, True, stop, f"stopped: {exc}", humans=len(humans.radii),
                           goal_distance=goal_distance)
        stopped = decision.fault is not None and not decision.fallback
        level = stop if stopped else DiagnosticStatus.WARN if (decision.fallback or decision.fault
                                                               or decision.wall_stop) else DiagnosticStatus.OK
        message = (f"stopped: {decision.fault}" if stopped else
                   "fallback: the cautious controller drives" if decision.fallback else "policy drives")
        if decision.wall_stop and not stopped:
            message += "; wall stop: the step would meet a wall, standing still"
        return Outcome(decision.speed, decision.turn, stopped, level, message, decision.fallback,
                       dict(decision.windowed), decision.fault, len(humans.radii), goal_distance,
                       subgoal=decision.subgoal, wall_stop=decision.wall_stop)

    def _inputs_problem(self, now_ns: int) -> tuple[str, str] | None:
        """Why the inputs cannot be decided on now (the first problem, and its cause without numbers for the log);
        None: they can. Odometry, humans and a scan must be fresh; a map or a path that was refused stops the robot
        until a good one arrives; with ``pose_topic``, the robot's map pose must be known."""
        stamped = [(self.odometry, "odometry"), (self.humans, "humans")]
        if self.reads_scan:
            stamped.append((self.scan, "scan"))
        for latest, what in stamped:
            problem = self._input_problem(latest, what, now_ns)
            if problem:
                return problem
        for latest in (self.map, self.path):
            if latest.error is not None:
                return latest.error, latest.error
        return self._pose_problem() if self.pose_topic else None

    def _pose_problem(self) -> tuple[str, str] | None:
        """Why the robot's map pose is not known (None: ``_correction`` holds the latest pose's map-from-odometry
        correction). A pose is paired with the odometry nearest its stamp, within ``max_input_age``; the pairing is
        kept once odometry at or after that stamp was there (none nearer can come), until the next pose."""
        pose = self.pose
        if pose.error is not None:
            return pose.error, pose.error
        if pose.value is None or pose.stamp_ns is None:
            return "no pose received yet", "no pose"
        stamp = pose.stamp_ns
        if self._correction is not None and self._correction[0] == stamp and self._correction[2]:
            return None
        limit = self.settings["max_input_age"]
        nearest = min(self._odometry_history, key=lambda odometry: abs(odometry.stamp_ns - stamp), default=None)
        if nearest is None or abs(nearest.stamp_ns - stamp) > limit * _NS:
            return (f"no odometry within max_input_age ({limit:g} s) of the pose's stamp to place the robot on the map",
                    "pose: no odometry at its stamp")
        self._correction = (stamp, _map_correction(pose.value, nearest), self._odometry_history[-1].stamp_ns >= stamp)
        return None

    def _map_pose(self, robot: RobotOdometry) -> np.ndarray | None:
        """The robot's map pose (x, y, yaw): its odometry moved by the latest pose's correction; None without
        ``pose_topic`` (the odometry frame is the map frame)."""
        if not self.pose_topic or self._correction is None:
            return None
        correction = self._correction[1]
        position = _rotate(robot.position, float(correction[2])) + correction[:2]
        return np.array([position[0], position[1], robot.heading + correction[2]])

    def _given_path(self) -> np.ndarray | None:
        """The waypoints of the latest path on ``path_topic``; None without one, or for an empty path (the
        navigator then plans its own)."""
        waypoints = self.path.value if self.path_topic else None
        return waypoints if waypoints is not None and len(waypoints) else None

    def _in_odometry_frame(self, point: np.ndarray) -> np.ndarray:
        """A map-frame point in the odometry frame (the inverse of the latest pose's correction; the same point
        without ``pose_topic``)."""
        if not self.pose_topic or self._correction is None:
            return point
        correction = self._correction[1]
        return _rotate(point - correction[:2], -float(correction[2]))

    # ------------------------------------------------------------------------------------------------- reports

    def _log_stop(self, outcome: Outcome) -> None:
        """Log a stop's message when its cause starts, then at most every REPEAT_LOG_S s while it lasts: a cause
        whose numbers change every decision (an age, a distance) is still one cause, not one line per decision."""
        cause = (outcome.cause or outcome.message) if outcome.stopped else None
        now = time.monotonic()
        if cause is not None and (cause != self._logged_cause or now - self._logged_at >= REPEAT_LOG_S):
            self.get_logger().warning(outcome.message)
            self._logged_at = now
        self._logged_cause = cause

    def _publish_state(self, outcome: Outcome, latency: float) -> None:
        stamp = self.get_clock().now().to_msg()
        self._log_stop(outcome)
        subgoal = "" if outcome.subgoal is None else f"{outcome.subgoal[0]:.3f}, {outcome.subgoal[1]:.3f}"
        values = {"stopped": outcome.stopped, "fallback": outcome.fallback, "wall_stop": outcome.wall_stop,
                  "speed": outcome.speed,
                  "turn_rate": outcome.turn / self.time_step, "latency_s": latency, "humans": outcome.humans,
                  "goal_distance": outcome.goal_distance, "fault": outcome.fault or "", **outcome.windowed,
                  "walls": len(self.navigator.walls or ()), "walls_from": self.walls_source, "subgoal": subgoal}
        status = DiagnosticStatus(level=outcome.level, name=f"{self.get_name()}: safe navigator",
                                  message=outcome.message, hardware_id=self.get_fully_qualified_name(),
                                  values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = stamp
        self.diagnostics.publish(array)
        self.fallback_topic.publish(Bool(data=outcome.fallback))
        uncertainty = Float64MultiArray(data=[float(outcome.windowed[name]) for name in UNCERTAINTY_NAMES])
        uncertainty.layout.dim = [MultiArrayDimension(label=",".join(UNCERTAINTY_NAMES), size=len(UNCERTAINTY_NAMES),
                                                      stride=len(UNCERTAINTY_NAMES))]
        self.uncertainty_topic.publish(uncertainty)
        self.latency_topic.publish(Float64(data=latency))
        if self.subgoal_topic is not None and outcome.subgoal is not None:
            self.subgoal_topic.publish(point_stamped(outcome.subgoal, stamp, self.map_frame))
        if self.markers is not None:
            self.markers.publish(self._marker_array(outcome, stamp))

    def _marker_array(self, outcome: Outcome, stamp: Any) -> MarkerArray:
        """The ``marker_humans`` humans nearest the robot (grey cylinders), goal (green disc), subgoal (purple
        sphere, a route-observing policy's), robot (blue: policy, orange: fallback, red: stopped) and a text with the
        windowed uncertainties (and the number of wall polygons), in the odometry frame; a DELETEALL first drops
        humans no longer seen."""
        markers = [Marker(action=Marker.DELETEALL)]

        def marker(namespace: str, ident: int, kind: int, x: float, y: float, diameter: float, height: float,
                   color: tuple[float, float, float, float]) -> Marker:
            item = Marker(ns=namespace, id=ident, type=kind, action=Marker.ADD)
            item.header.frame_id, item.header.stamp = self.odom_frame, stamp
            item.pose.position = Point(x=float(x), y=float(y), z=height / 2.0)
            item.pose.orientation.w = 1.0
            item.scale.x = item.scale.y = float(diameter)
            item.scale.z = float(height)
            item.color = ColorRGBA(r=color[0], g=color[1], b=color[2], a=color[3])
            return item

        humans: TrackedHumans | None = self.humans.value
        robot: RobotOdometry | None = self.odometry.value
        drawn = np.zeros(0, dtype=int)
        if humans is not None:
            drawn = self._drawn_humans(humans, robot)
            for index, slot in enumerate(drawn):
                position, radius = humans.positions[slot], humans.radii[slot]
                markers.append(marker("humans", index, Marker.CYLINDER, position[0], position[1], 2 * radius, 1.7,
                                      (0.6, 0.6, 0.6, 0.8)))
        goal = self.goal.value
        if goal is not None:
            markers.append(marker("goal", 0, Marker.CYLINDER, goal[0], goal[1], 2 * self.settings["goal_tolerance"],
                                  0.02, (0.1, 0.8, 0.2, 0.8)))
        if outcome.subgoal is not None:
            subgoal = self._in_odometry_frame(outcome.subgoal)
            markers.append(marker("subgoal", 0, Marker.SPHERE, subgoal[0], subgoal[1], 0.2, 0.2, (0.6, 0.2, 0.9, 0.9)))
        if robot is not None:
            color = (0.9, 0.1, 0.1, 0.9) if outcome.stopped else (1.0, 0.55, 0.0, 0.9) if outcome.fallback \
                else (0.2, 0.4, 1.0, 0.9)
            markers.append(marker("robot", 0, Marker.CYLINDER, robot.position[0], robot.position[1],
                                  2 * self.settings["robot_radius"], 0.3, color))
            text = marker("uncertainty", 0, Marker.TEXT_VIEW_FACING, robot.position[0], robot.position[1], 0.0, 0.25,
                          (1.0, 1.0, 1.0, 1.0))
            text.pose.position.z = 1.0
            text.text = (outcome.message if outcome.stopped else
                         f"{'FALLBACK' if outcome.fallback else 'policy'}  u_ep {outcome.windowed['u_ep_heading']:.3f}"
                         f"  u_feat {outcome.windowed['u_feat']:.3f}")
            if humans is not None and len(drawn) < len(humans.radii):
                text.text += f"  ({len(drawn)} nearest of {len(humans.radii)} humans drawn)"
            if self.navigator.walls:
                text.text += f"  walls: {len(self.navigator.walls)} polygons"
            markers.append(text)
        return MarkerArray(markers=markers)

    def _drawn_humans(self, humans: TrackedHumans, robot: RobotOdometry | None) -> np.ndarray:
        """The indices of the humans that get a marker: the ``marker_humans`` nearest the robot (the first ones
        while its position is unknown), nearest first."""
        count, limit = len(humans.radii), self.marker_humans
        if count <= limit or robot is None:
            return np.arange(min(count, limit))
        distance = np.hypot(*(humans.positions - robot.position).T)
        nearest = np.argpartition(distance, limit - 1)[:limit] if limit else np.zeros(0, dtype=int)
        return nearest[np.argsort(distance[nearest], kind="stable")]
