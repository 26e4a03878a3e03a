"""Conversions between ROS 2 standard messages and the navigator's plain arrays (odom frame, metres, seconds).
Every reader checks its message (frame, shape, finite numbers) and raises `MessageError` naming what is wrong.

Conventions (REP 103 / REP 105; nav_msgs/Odometry's own comments):

* the robot's pose is in the odometry frame (``header.frame_id``, e.g. ``odom``); its twist is in the robot's frame
  (``child_frame_id``, e.g. ``base_link``: x forward, y left), so the velocity over the ground in the odometry
  frame is ``R(yaw) [v_x, v_y]``, ``yaw`` the heading read from the orientation quaternion
  ``yaw = atan2(2 (w z + x y), 1 - 2 (y^2 + z^2))``;
* the tracked humans are a sensor_msgs/PointCloud2 in the odometry frame, one point per human, with FLOAT32 or
  FLOAT64 fields ``x``, ``y`` (position), ``vx``, ``vy`` (velocity over the ground) and optionally ``radius`` (m);
* the goal is a geometry_msgs/PoseStamped in the odometry frame (its orientation is not used);
* the command is a geometry_msgs/Twist in the robot's frame: ``linear.x = v`` and ``angular.z = dtheta / dt``,
  where ``dtheta`` is the policy's heading change over one control step of ``dt`` seconds (the simulator's unicycle
  turns by ``dtheta`` and then drives ``v dt`` along its new heading: `socnav.sim.world._integrate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Quaternion, Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField

__all__ = [
    "HUMAN_FIELDS", "MAX_TRACKED_HUMANS", "MessageError", "RobotOdometry", "TrackedHumans", "cloud_to_humans",
    "command_to_twist", "goal_to_position", "humans_to_cloud", "ns_to_stamp", "odometry_to_robot",
    "position_to_goal", "quaternion_from_yaw", "robot_to_odometry", "stamp_to_ns", "twist_to_command",
    "yaw_from_quaternion",
]

#: The humans cloud's fields: position, velocity over the ground (odometry frame), body radius (optional).
HUMAN_FIELDS = ("x", "y", "vx", "vy", "radius")
#: More points than this in one humans cloud are refused (a tracker's crowd is tens; the policy reads the closest).
MAX_TRACKED_HUMANS = 10_000
#: How far the orientation quaternion's norm may be from 1 (drivers normalise theirs; a zero quaternion is unset).
QUATERNION_NORM_TOLERANCE = 1e-2
_FLOAT_TYPES = {PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}
_NS = 1_000_000_000


class MessageError(ValueError):
    """A message the navigator or the simulator cannot use: the text names the message, the field and the reason."""


def stamp_to_ns(stamp: Time) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def ns_to_stamp(nanoseconds: int) -> Time:
    """Integer nanoseconds (>= 0) as a builtin_interfaces/Time."""
    seconds, nanosec = divmod(int(nanoseconds), _NS)
    return Time(sec=seconds, nanosec=nanosec)


def quaternion_from_yaw(yaw: float) -> Quaternion:
    """The rotation by ``yaw`` about z: ``(0, 0, sin(yaw / 2), cos(yaw / 2))``."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def yaw_from_quaternion(q: Quaternion, owner: str = "orientation") -> float:
    """The heading (rotation about z, in [-pi, pi]) of a unit quaternion: ``atan2(2 (w z + x y), 1 - 2 (y^2 + z^2))``.

    :raises MessageError: a component that is not finite, or a norm farther than 1e-2 from 1 (e.g. the all-zero
        quaternion of a pose that was never set).
    """
    components = (q.x, q.y, q.z, q.w)
    if not all(math.isfinite(value) for value in components):
        raise MessageError(f"{owner} is not finite: (x, y, z, w) = {components}")
    norm = math.sqrt(sum(value * value for value in components))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise MessageError(f"{owner} is not a unit quaternion: norm {norm:.6g} (x, y, z, w) = {components}")
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _check_frame(owner: str, field: str, actual: str, expected: str) -> None:
    if actual != expected:
        raise MessageError(f"{owner}.{field} is {actual!r}, expected {expected!r} (set the node's frame parameters to "
                           "your robot's frames; socnav does not look up tf)")


def _finite(owner: str, **values: float) -> None:
    bad = {name: value for name, value in values.items() if not math.isfinite(value)}
    if bad:
        raise MessageError(f"{owner} is not finite: {bad}")


@dataclass(frozen=True)
class RobotOdometry:
    """The robot's state from one odometry message, odometry frame: ``position`` (2,), ``velocity`` (2,) over the
    ground, ``heading`` (rad), ``stamp_ns``."""

    position: np.ndarray
    velocity: np.ndarray
    heading: float
    stamp_ns: int


def odometry_to_robot(message: Odometry, odom_frame: str, base_frame: str) -> RobotOdometry:
    """The robot's position, heading and ground velocity in ``odom_frame``: ``v = R(yaw) [twist.linear.x,
    twist.linear.y]`` (the twist is in ``child_frame_id``).

    :raises MessageError: other frames, a non-finite number, or an orientation that is not a unit quaternion.
    """
    _check_frame("odometry", "header.frame_id", message.header.frame_id, odom_frame)
    _check_frame("odometry", "child_frame_id", message.child_frame_id, base_frame)
    position, linear = message.pose.pose.position, message.twist.twist.linear
    _finite("odometry", **{"pose.position.x": position.x, "pose.position.y": position.y,
                           "twist.linear.x": linear.x, "twist.linear.y": linear.y})
    heading = yaw_from_quaternion(message.pose.pose.orientation, "odometry.pose.orientation")
    cos_h, sin_h = math.cos(heading), math.sin(heading)
    velocity = np.array([cos_h * linear.x - sin_h * linear.y, sin_h * linear.x + cos_h * linear.y])
    return RobotOdometry(np.array([position.x, position.y]), velocity, heading, stamp_to_ns(message.header.stamp))


def robot_to_odometry(position: np.ndarray, velocity: np.ndarray, heading: float, turn_rate: float, stamp_ns: int,
                      odom_frame: str, base_frame: str) -> Odometry:
    """An Odometry message of a planar robot: pose in ``odom_frame``, twist in ``base_frame``
    (``[v_x, v_y] = R(-yaw) velocity``, ``angular.z = turn_rate``)."""
    message = Odometry()
    message.header.stamp = ns_to_stamp(stamp_ns)
    message.header.frame_id = odom_frame
    message.child_frame_id = base_frame
    message.pose.pose.position.x, message.pose.pose.position.y = float(position[0]), float(position[1])
    message.pose.pose.orientation = quaternion_from_yaw(float(heading))
    cos_h, sin_h = math.cos(heading), math.sin(heading)
    message.twist.twist.linear.x = float(cos_h * velocity[0] + sin_h * velocity[1])
    message.twist.twist.linear.y = float(-sin_h * velocity[0] + cos_h * velocity[1])
    message.twist.twist.angular.z = float(turn_rate)
    return message


@dataclass(frozen=True)
class TrackedHumans:
    """The tracked humans of one cloud, odometry frame: ``positions`` (n, 2), ``velocities`` (n, 2), ``radii`` (n,)."""

    positions: np.ndarray
    velocities: np.ndarray
    radii: np.ndarray
    stamp_ns: int

    def as_mapping(self) -> dict[str, np.ndarray]:
        """The mapping `socnav.runtime.SafeNavigator.act` takes."""
        return {"positions": self.positions, "velocities": self.velocities, "radii": self.radii}


def _field_dtype(cloud: PointCloud2, field: Any) -> np.dtype:
    """The NumPy dtype of one scalar field (FLOAT32 or FLOAT64, the cloud's byte order), checked to fit in a point.

    :raises MessageError: another datatype, a count other than 1, or an offset outside ``point_step``."""
    name = field.name
    if field.datatype not in _FLOAT_TYPES:
        raise MessageError(f"humans cloud field {name!r} has datatype {field.datatype}; allowed: FLOAT32 (7), "
                           "FLOAT64 (8)")
    if field.count not in (0, 1):
        raise MessageError(f"humans cloud field {name!r} has count {field.count}; allowed: 1")
    dtype = np.dtype(_FLOAT_TYPES[field.datatype]).newbyteorder(">" if cloud.is_bigendian else "<")
    if field.offset < 0 or field.offset + dtype.itemsize > cloud.point_step:
        raise MessageError(f"humans cloud field {name!r} (offset {field.offset}, {dtype.itemsize} bytes) does not fit "
                           f"in point_step {cloud.point_step}")
    return dtype


def _cloud_field(cloud: PointCloud2, field: Any, dtype: np.dtype, data: bytes) -> np.ndarray:
    """One scalar field of every point, as float64 (n,), read in place with the cloud's strides."""
    values = np.ndarray((cloud.height, cloud.width), dtype=dtype, buffer=data, offset=field.offset,
                        strides=(cloud.row_step, cloud.point_step))
    return values.astype(np.float64).reshape(-1)


def cloud_to_humans(cloud: PointCloud2, frame: str, default_radius: float) -> TrackedHumans:
    """The humans of a PointCloud2 (fields :data:`HUMAN_FIELDS`; without ``radius``, every human has
    ``default_radius``), in ``frame``.

    :raises MessageError: another frame, a missing or non-float field, a layout that does not match the data (at
        any point count, 0 included), more than :data:`MAX_TRACKED_HUMANS` points, a NaN / inf, or a negative
        radius.
    """
    _check_frame("humans cloud", "header.frame_id", cloud.header.frame_id, frame)
    count = cloud.height * cloud.width
    stamp = stamp_to_ns(cloud.header.stamp)
    if count > MAX_TRACKED_HUMANS:
        raise MessageError(f"humans cloud has {count} points; at most {MAX_TRACKED_HUMANS} are accepted")
    # Every check below holds for an empty cloud too: "no humans" is a well-formed cloud of 0 points (what
    # `humans_to_cloud` writes), not whatever arrives with height or width 0 -- a malformed one stops the robot.
    fields: dict[str, Any] = {}
    for field in cloud.fields:
        if field.name in fields:
            raise MessageError(f"humans cloud declares field {field.name!r} twice")
        fields[field.name] = field
    missing = [name for name in HUMAN_FIELDS[:4] if name not in fields]
    if missing:
        raise MessageError(f"humans cloud lacks fields {missing}; it needs x, y, vx, vy (and optionally radius), got "
                           f"{sorted(fields)}")
    dtypes = {name: _field_dtype(cloud, fields[name]) for name in HUMAN_FIELDS if name in fields}
    data = bytes(cloud.data)
    if cloud.point_step <= 0 or cloud.row_step < cloud.width * cloud.point_step:
        raise MessageError(f"humans cloud layout is inconsistent: point_step {cloud.point_step}, row_step "
                           f"{cloud.row_step} for width {cloud.width}")
    if len(data) != cloud.row_step * cloud.height:
        raise MessageError(f"humans cloud data has {len(data)} bytes; row_step {cloud.row_step} x height "
                           f"{cloud.height} = {cloud.row_step * cloud.height}")
    if count == 0:
        empty = np.zeros((0, 2))
        return TrackedHumans(empty, empty.copy(), np.zeros(0), stamp)
    values = {name: _cloud_field(cloud, fields[name], dtype, data) for name, dtype in dtypes.items()}
    radii = values.get("radius", np.full(count, float(default_radius)))
    positions = np.column_stack([values["x"], values["y"]])
    velocities = np.column_stack([values["vx"], values["vy"]])
    for name, array in (("x, y", positions), ("vx, vy", velocities), ("radius", radii)):
        if not np.isfinite(array).all():
            rows = np.flatnonzero(~np.isfinite(array.reshape(count, -1)).all(axis=1))
            raise MessageError(f"humans cloud: {name} not finite (NaN or inf) at points {rows[:10].tolist()}")
    if (radii < 0.0).any():
        raise MessageError(f"humans cloud: negative radius at points {np.flatnonzero(radii < 0.0)[:10].tolist()}")
    return TrackedHumans(positions, velocities, radii, stamp)


def humans_to_cloud(positions: np.ndarray, velocities: np.ndarray, radii: np.ndarray, stamp_ns: int,
                    frame: str) -> PointCloud2:
    """A PointCloud2 of humans: one point per human, FLOAT64 fields :data:`HUMAN_FIELDS` (little-endian, dense),
    so the navigator reads the simulator's float64 state exactly."""
    count = len(radii)
    points = np.empty((count, len(HUMAN_FIELDS)), dtype="<f8")
    points[:, 0:2], points[:, 2:4], points[:, 4] = positions, velocities, radii
    cloud = PointCloud2()
    cloud.header.stamp = ns_to_stamp(stamp_ns)
    cloud.header.frame_id = frame
    cloud.height, cloud.width = 1, count
    cloud.fields = [PointField(name=name, offset=8 * index, datatype=PointField.FLOAT64, count=1)
                    for index, name in enumerate(HUMAN_FIELDS)]
    cloud.is_bigendian = False
    cloud.point_step = 8 * len(HUMAN_FIELDS)
    cloud.row_step = cloud.point_step * count
    cloud.is_dense = True
    cloud.data = points.tobytes()
    return cloud


def goal_to_position(message: PoseStamped, frame: str) -> np.ndarray:
    """The goal's position (2,) in ``frame``.

    :raises MessageError: another frame or a non-finite position."""
    _check_frame("goal", "header.frame_id", message.header.frame_id, frame)
    position = message.pose.position
    _finite("goal", **{"pose.position.x": position.x, "pose.position.y": position.y})
    return np.array([position.x, position.y])


def position_to_goal(goal: np.ndarray, stamp_ns: int, frame: str) -> PoseStamped:
    """A PoseStamped at ``goal`` (identity orientation)."""
    message = PoseStamped()
    message.header.stamp = ns_to_stamp(stamp_ns)
    message.header.frame_id = frame
    message.pose.position.x, message.pose.position.y = float(goal[0]), float(goal[1])
    message.pose.orientation.w = 1.0
    return message


def command_to_twist(speed: float, turn: float, time_step: float) -> Twist:
    """The command ``(v, dtheta)`` of one control step of ``time_step`` s: ``linear.x = v``, ``angular.z =
    dtheta / time_step``."""
    twist = Twist()
    twist.linear.x = float(speed)
    twist.angular.z = float(turn) / time_step
    return twist


def twist_to_command(twist: Twist, time_step: float) -> tuple[float, float]:
    """``(v, dtheta)`` of a unicycle's Twist over one step of ``time_step`` s: ``v = linear.x``, ``dtheta =
    angular.z * time_step`` (the other components are not used).

    :raises MessageError: ``linear.x`` or ``angular.z`` is not finite."""
    _finite("cmd_vel", **{"linear.x": twist.linear.x, "angular.z": twist.angular.z})
    return float(twist.linear.x), float(twist.angular.z) * time_step
