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
* the range scan is a sensor_msgs/LaserScan in the robot's frame, the scanner taken at the robot's centre facing its
  heading (no tf): `scan_to_ranges` turns it into the beams a policy was trained with (REP 117's readings kept);
* the map is a nav_msgs/OccupancyGrid in the map frame: `grid_to_walls` turns its cells that are not known to be free
  into wall polygons (`socnav.sim.maps.occupancy_to_polygons`, as socnav's map_server loader does), `walls_to_grid`
  rasterises walls into one; the robot's map pose is a geometry_msgs/PoseWithCovarianceStamped (AMCL's
  ``amcl_pose``) and a route a nav_msgs/Path, both in the map frame;
* the command is a geometry_msgs/Twist in the robot's frame: ``linear.x = v`` and ``angular.z = dtheta / dt``,
  where ``dtheta`` is the policy's heading change over one control step of ``dt`` seconds (the simulator's unicycle
  turns by ``dtheta`` and then drives ``v dt`` along its new heading: `socnav.sim.world._integrate`).
"""

from __future__ import annotations

import math
from array import array as ctype_array
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, PoseStamped, PoseWithCovarianceStamped, Quaternion, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.msg import Path as PathMessage
from sensor_msgs.msg import LaserScan, PointCloud2, PointField
from shapely.geometry import Polygon

from socnav.sim.geometry import scan_angles
from socnav.sim.maps import MAX_GRID_CELLS, MapError, is_counter_clockwise, occupancy_to_polygons, validate_polygons

__all__ = [
    "HUMAN_FIELDS", "MAX_PATH_POSES", "MAX_SCAN_READINGS", "MAX_TRACKED_HUMANS", "SCAN_ANGLE_TOLERANCE",
    "MessageError", "RobotOdometry", "TrackedHumans", "cloud_to_humans", "command_to_twist", "goal_to_position",
    "grid_to_walls", "humans_to_cloud", "ns_to_stamp", "odometry_to_robot", "path_to_waypoints", "point_stamped",
    "pose_to_map_pose", "position_to_goal", "quaternion_from_yaw", "ranges_to_scan", "robot_to_odometry",
    "scan_to_ranges", "stamp_to_ns", "trained_scan_angles", "twist_to_command", "walls_to_grid",
    "yaw_from_quaternion",
]

#: The humans cloud's fields: position, velocity over the ground (odometry frame), body radius (optional).
HUMAN_FIELDS = ("x", "y", "vx", "vy", "radius")
#: More points than this in one humans cloud are refused (a tracker's crowd is tens; the policy reads the closest).
MAX_TRACKED_HUMANS = 10_000
#: How far the orientation quaternion's norm may be from 1 (drivers normalise theirs; a zero quaternion is unset).
QUATERNION_NORM_TOLERANCE = 1e-2
#: More readings than this in one LaserScan are refused (a 2-D lidar gives a few thousand per turn).
MAX_SCAN_READINGS = 100_000
#: Radians: a LaserScan whose first and last beams lie this close to the trained layout's is passed through as it is.
#: (A float32 angle is within 1e-6 rad of its float64 value; a driver half a beam off is resampled.)
SCAN_ANGLE_TOLERANCE = 1e-4
#: More poses than this in one nav_msgs/Path are refused (nav2's planner: a pose every 5 cm, 2,000 per 100 m).
MAX_PATH_POSES = 100_000
#: Occupancy values of an OccupancyGrid cell (nav_msgs): known occupied, and what `walls_to_grid` writes for free.
OCCUPIED, FREE = 100, 0
#: Fraction of a trained beam's sector two sectors must share to count as overlapping: a driver's float32 angles
#: that put a reading's sector a hair into the next beam's do not add that reading to it.
_SECTOR_OVERLAP = 1e-3
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


# --------------------------------------------------------------------------------------------------------------------
# Range scan
# --------------------------------------------------------------------------------------------------------------------
def trained_scan_angles(beams: int, fov_degrees: float) -> tuple[float, float]:
    """``(angle_min, angle_increment)`` in radians of the scan a policy was trained with (an env config's ``scan``):
    the simulator's layout (`socnav.sim.geometry.scan_angles`): from -fov/2 counter-clockwise; with a 360 degree
    field of view the increment is 2 pi / beams, otherwise fov / (beams - 1) (the last beam at +fov/2)."""
    fov = 2.0 * math.pi if fov_degrees >= 360.0 else math.radians(fov_degrees)
    return scan_angles(beams, fov)


def scan_to_ranges(message: LaserScan, frame: str, beams: int, fov_degrees: float) -> np.ndarray:
    """The ``beams`` ranges (float64, metres; +inf and -inf kept) a policy trained with a scan of ``beams`` beams over
    ``fov_degrees`` reads (`trained_scan_angles`), from a LaserScan in ``frame`` (the robot's: the scanner is taken
    at the robot's centre, facing its heading; socnav looks up no tf).

    Each reading is first read as REP 117 and the message's own definition say (``angle_max`` is not read: reading
    ``i`` is at ``angle_min + i angle_increment``):

    * +inf: no return within the sensor's reach; kept (the navigator reads it as its trained range);
    * -inf: an object too close to measure; kept (the navigator reads it as 0 m);
    * a finite value above ``range_max``: beyond the sensor's reach, i.e. no return: +inf;
    * NaN, and a finite value below ``range_min``: an invalid reading (REP 117's erroneous measurement; the message
      says to discard out-of-range values, and older drivers write 0 for "nothing measured"): no information.

    If the message has the trained layout (``beams`` readings, ``angle_min`` and the last beam's angle within
    :data:`SCAN_ANGLE_TOLERANCE` of the trained ones) the readings are the ranges. Otherwise they are resampled,
    conservatively: trained beam ``b`` owns the angles within half a trained increment of it (its sector; with one
    beam and a field of view under 360 degrees, the whole field), each reading the angles within half the message's
    increment of it, and the beam takes the MINIMUM of the valid readings whose sectors overlap its own (so a
    narrow obstacle seen by one reading is not lost between two trained beams). A trained sector that no reading
    overlaps (a sensor with a narrower field of view) reads +inf: no return.

    :raises MessageError: another frame; no reading or more than :data:`MAX_SCAN_READINGS`; a non-finite angle,
        increment or range limit, ``range_min < 0`` or ``range_max <= range_min``; a zero increment with several
        readings, or readings spanning more than two turns; a trained beam whose readings are all invalid (the robot
        stops rather than take unseen space for free).
    """
    _check_frame("scan", "header.frame_id", message.header.frame_id, frame)
    _finite("scan", angle_min=message.angle_min, angle_increment=message.angle_increment,
            range_min=message.range_min, range_max=message.range_max)
    count = len(message.ranges)
    if not 1 <= count <= MAX_SCAN_READINGS:
        raise MessageError(f"scan has {count} ranges; allowed: 1 to {MAX_SCAN_READINGS}")
    if not 0.0 <= message.range_min < message.range_max:
        raise MessageError(f"scan range limits must satisfy 0 <= range_min < range_max, got range_min "
                           f"{message.range_min:g}, range_max {message.range_max:g}")
    if message.angle_increment == 0.0 and count > 1:
        raise MessageError(f"scan.angle_increment is 0 for {count} ranges; allowed: a non-zero increment")
    if abs(message.angle_increment) * count > 4.0 * math.pi:
        raise MessageError(f"scan spans {abs(message.angle_increment) * count:.3f} rad ({count} ranges x "
                           f"angle_increment {message.angle_increment:g}); allowed: at most two turns (4 pi)")
    readings = _rep117_readings(np.asarray(message.ranges, dtype=np.float64), message.range_min, message.range_max)
    angle_min, increment = trained_scan_angles(beams, fov_degrees)
    if _same_layout(message, count, beams, angle_min, increment):
        ranges, invalid = readings, np.isnan(readings)
    else:
        full_turn = fov_degrees >= 360.0
        if beams == 1 and not full_turn:  # one beam along the heading: its sector is the whole field of view
            angle_min, increment = 0.0, math.radians(fov_degrees)
        ranges, invalid = _sector_minimum(readings, message.angle_min, message.angle_increment, beams, angle_min,
                                          increment, full_turn)
    if invalid.any():
        raise MessageError(f"scan: trained beams {np.flatnonzero(invalid)[:10].tolist()} have only invalid readings "
                           f"(NaN, or finite below range_min {message.range_min:g} m); the robot stops rather than "
                           "take unseen space for free space")
    return ranges


def _rep117_readings(values: np.ndarray, range_min: float, range_max: float) -> np.ndarray:
    """The readings as `scan_to_ranges` describes: +inf / -inf kept, finite above ``range_max`` to +inf, finite
    below ``range_min`` and NaN to NaN (invalid)."""
    readings = values.copy()
    finite = np.isfinite(values)
    readings[finite & (values > range_max)] = math.inf
    readings[finite & (values < range_min)] = math.nan
    return readings


def _same_layout(message: LaserScan, count: int, beams: int, angle_min: float, increment: float) -> bool:
    """Whether the message's beams are the trained ones: as many, the first and the last within
    :data:`SCAN_ANGLE_TOLERANCE` (a turn apart counts as the same angle)."""
    if count != beams or abs(math.remainder(message.angle_min - angle_min, 2.0 * math.pi)) > SCAN_ANGLE_TOLERANCE:
        return False
    return beams == 1 or abs(message.angle_increment - increment) * (beams - 1) <= SCAN_ANGLE_TOLERANCE


def _sector_minimum(readings: np.ndarray, first_angle: float, step: float, beams: int, angle_min: float,
                    increment: float, full_turn: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per trained beam: the minimum of the valid readings whose sectors overlap its sector (+inf where none
    overlaps), and whether the readings that overlap it are all invalid. Angles are counted in trained beams:
    beam ``b`` owns ``[b - 1/2, b + 1/2]``, reading ``i`` ``[u_i - w, u_i + w]`` with ``w`` half the message's
    increment (each angle taken about the heading, in [-pi, pi)); on a full turn beam indices wrap around."""
    count = len(readings)
    angles = first_angle + step * np.arange(count)
    relative = np.remainder(angles + math.pi, 2.0 * math.pi) - math.pi  # about the heading, in [-pi, pi)
    u = (relative - angle_min) / increment
    half = abs(step) / (2.0 * increment)
    shrink = min(_SECTOR_OVERLAP, half / 2.0)  # a ray (no width) keeps its point
    low = np.floor(u - half + shrink + 0.5).astype(np.int64)
    high = np.floor(u + half - shrink + 0.5).astype(np.int64)
    spans = high - low + 1
    if full_turn:
        spans = np.minimum(spans, beams)
    reading = np.repeat(np.arange(count), spans)
    beam = np.repeat(low, spans) + (np.arange(spans.sum()) - np.repeat(np.cumsum(spans) - spans, spans))
    if full_turn:
        beam %= beams
    else:  # angles outside the trained field of view belong to no beam
        inside = (beam >= 0) & (beam < beams)
        reading, beam = reading[inside], beam[inside]
    values = readings[reading]
    valid = ~np.isnan(values)
    ranges = np.full(beams, math.inf)
    np.minimum.at(ranges, beam[valid], values[valid])
    seen = np.bincount(beam, minlength=beams) > 0
    invalid = seen & (np.bincount(beam[valid], minlength=beams) == 0)
    return ranges, invalid


def ranges_to_scan(ranges: np.ndarray, stamp_ns: int, frame: str, fov_degrees: float, max_range: float,
                   scan_time: float = 0.0) -> LaserScan:
    """A LaserScan of a simulated scan (`socnav.sim.walls.Walls.scan`): ``ranges`` in the trained layout
    (`trained_scan_angles`), ``range_min`` 0, ``range_max`` the scan's range (a beam that hits nothing reads it)."""
    angle_min, increment = trained_scan_angles(len(ranges), fov_degrees)
    message = LaserScan()
    message.header.stamp = ns_to_stamp(stamp_ns)
    message.header.frame_id = frame
    message.angle_min, message.angle_increment = float(angle_min), float(increment)
    message.angle_max = float(angle_min + increment * (len(ranges) - 1))
    message.scan_time = float(scan_time)
    message.range_min, message.range_max = 0.0, float(max_range)
    message.ranges = np.asarray(ranges, dtype=np.float32)
    return message


# --------------------------------------------------------------------------------------------------------------------
# Map, map pose and route
# --------------------------------------------------------------------------------------------------------------------
def grid_to_walls(message: OccupancyGrid, frame: str, free_thresh: float = 0.25) -> list[np.ndarray]:
    """The walls of an occupancy grid in ``frame``: polygons (map frame, RVO2's convention, validated as
    `socnav.sim.maps.validate_polygons` does) covering every cell that is not known to be free.

    A cell is free when its occupancy value ``v`` (0 to 100; -1 unknown) satisfies ``0 <= v < 100 free_thresh``, as
    map_server's ``free_thresh`` reads an image; unknown cells, occupied ones and values outside [-1, 100] are walls,
    so the robot keeps to space known to be free (socnav's own map_server loader, `socnav.sim.maps.load_map`, does
    the same). Row 0 of ``data`` is the row at ``info.origin`` (the grid's lower edge); the origin's yaw rotates the
    grid about it. The area outside the grid is free. `socnav.sim.maps.occupancy_to_polygons` turns the cells into
    polygons.

    :raises MessageError: another frame, a resolution that is not a finite number > 0, a data length other than
        width x height, more than `socnav.sim.maps.MAX_GRID_CELLS` cells, a non-finite origin or an origin
        orientation that is not a unit quaternion, or walls over socnav's map bounds (too detailed a grid).
    """
    _check_frame("map", "header.frame_id", message.header.frame_id, frame)
    info = message.info
    _finite("map", **{"info.resolution": info.resolution, "info.origin.position.x": info.origin.position.x,
                      "info.origin.position.y": info.origin.position.y})
    if info.resolution <= 0.0:
        raise MessageError(f"map.info.resolution must be > 0 (metres per cell), got {info.resolution:g}")
    cells = info.width * info.height
    if cells > MAX_GRID_CELLS:
        raise MessageError(f"map has {info.width} x {info.height} cells; at most {MAX_GRID_CELLS} are accepted (crop "
                           "it or use a coarser resolution)")
    if len(message.data) != cells:
        raise MessageError(f"map.data has {len(message.data)} cells; info.width {info.width} x info.height "
                           f"{info.height} = {cells}")
    yaw = yaw_from_quaternion(info.origin.orientation, "map.info.origin.orientation")
    values = np.asarray(message.data, dtype=np.int16).reshape(info.height, info.width)
    blocked = ~((values >= 0) & (values < 100.0 * free_thresh))
    try:
        # occupancy_to_polygons reads an image, row 0 at the top: the grid's last row
        polygons = occupancy_to_polygons(blocked[::-1], info.resolution,
                                         (info.origin.position.x, info.origin.position.y), yaw)
        return validate_polygons(polygons, name="map: the polygons of the grid")
    except MapError as exc:
        raise MessageError(f"map: {exc}") from None


def walls_to_grid(polygons: Sequence[np.ndarray], resolution: float, stamp_ns: int, frame: str,
                  padding: float = 1.0) -> OccupancyGrid:
    """An occupancy grid of walls (polygons in RVO2's convention, as `socnav.sim.walls.world_polygons` gives them)
    over their bounding box grown by ``padding`` metres, ``resolution`` metres per cell, origin at its lower-left
    corner (no rotation). A cell is occupied (100) when its centre lies in solid space -- the smallest closed
    polygon containing it is counter-clockwise, or, in none, some clockwise polygon (a boundary agents stay inside)
    lies in no other -- or when a polygon's edge passes through it (sampled every quarter cell, so that two-vertex
    walls and thin obstacles are drawn); every other cell is free (0).

    :raises ValueError: no polygon, a resolution that is not a finite number > 0, or a grid of more than
        `socnav.sim.maps.MAX_GRID_CELLS` cells.
    """
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"resolution must be a finite number > 0 (metres per cell), got {resolution!r}")
    if not polygons:
        raise ValueError("no walls to rasterise")
    points = np.concatenate([np.asarray(vertices, dtype=np.float64) for vertices in polygons])
    origin = np.floor((points.min(axis=0) - padding) / resolution) * resolution
    width, height = (int(n) for n in np.ceil((points.max(axis=0) + padding - origin) / resolution))
    if width * height > MAX_GRID_CELLS:
        raise ValueError(f"the walls need a grid of {width} x {height} cells at {resolution:g} m per cell, more than "
                         f"{MAX_GRID_CELLS}; use a coarser resolution")
    occupied = _solid_cells(polygons, origin, resolution, width, height) | \
        _edge_cells(polygons, origin, resolution, width, height)
    message = OccupancyGrid()
    message.header.stamp = ns_to_stamp(stamp_ns)
    message.header.frame_id = frame
    message.info.map_load_time = message.header.stamp
    message.info.resolution = float(resolution)
    message.info.width, message.info.height = width, height
    message.info.origin.position.x, message.info.origin.position.y = float(origin[0]), float(origin[1])
    message.info.origin.orientation.w = 1.0
    data = ctype_array("b")
    data.frombytes(np.where(occupied, OCCUPIED, FREE).astype(np.int8).tobytes())  # row 0 at the origin, as required
    message.data = data
    return message


def _solid_cells(polygons: Sequence[np.ndarray], origin: np.ndarray, resolution: float, width: int,
                 height: int) -> np.ndarray:
    """(height, width) bool: the cells whose centre lies in solid space (`walls_to_grid`'s rule); row 0 at the
    origin."""
    x = origin[0] + (np.arange(width) + 0.5) * resolution
    y = origin[1] + (np.arange(height) + 0.5) * resolution
    grid_x, grid_y = np.meshgrid(x, y)
    closed = [(Polygon(vertices), is_counter_clockwise(vertices)) for vertices in polygons if len(vertices) >= 3]
    outside_solid = any(not solid and not any(other.contains(area) for other, _ in closed if other is not area)
                        for area, solid in closed)
    occupied = np.full((height, width), outside_solid)
    for area, solid in sorted(closed, key=lambda item: -item[0].area):  # the smallest containing polygon decides
        occupied[shapely.contains_xy(area, grid_x, grid_y)] = solid
    return occupied


def _edge_cells(polygons: Sequence[np.ndarray], origin: np.ndarray, resolution: float, width: int,
                height: int) -> np.ndarray:
    """(height, width) bool: the cells a polygon's edge passes through, sampled every quarter cell along it."""
    occupied = np.zeros((height, width), dtype=bool)
    for vertices in polygons:
        vertices = np.asarray(vertices, dtype=np.float64)
        ends = np.roll(vertices, -1, axis=0) if len(vertices) >= 3 else vertices[1:]
        for start, end in zip(vertices[: len(ends)], ends, strict=True):
            samples = math.ceil(4.0 * float(np.hypot(*(end - start))) / resolution) + 1
            points = start + np.linspace(0.0, 1.0, samples)[:, None] * (end - start)
            cells = np.floor((points - origin) / resolution).astype(np.int64)
            inside = (cells[:, 0] >= 0) & (cells[:, 0] < width) & (cells[:, 1] >= 0) & (cells[:, 1] < height)
            occupied[cells[inside, 1], cells[inside, 0]] = True
    return occupied


def pose_to_map_pose(message: PoseWithCovarianceStamped, frame: str) -> np.ndarray:
    """The robot's pose ``(x, y, yaw)`` (3,) in ``frame`` (the map frame) of a PoseWithCovarianceStamped (AMCL's
    ``amcl_pose``; the covariance is not used).

    :raises MessageError: another frame, a non-finite position, or an orientation that is not a unit quaternion."""
    _check_frame("pose", "header.frame_id", message.header.frame_id, frame)
    position = message.pose.pose.position
    _finite("pose", **{"pose.pose.position.x": position.x, "pose.pose.position.y": position.y})
    yaw = yaw_from_quaternion(message.pose.pose.orientation, "pose.pose.pose.orientation")
    return np.array([position.x, position.y, yaw])


def path_to_waypoints(message: PathMessage, frame: str) -> np.ndarray:
    """The (x, y) waypoints (M, 2) of a nav_msgs/Path in ``frame`` (the map frame); M = 0 for an empty path. A pose
    may leave its own ``header.frame_id`` empty; otherwise it must be ``frame`` too.

    :raises MessageError: another frame, more than :data:`MAX_PATH_POSES` poses, or a non-finite position."""
    _check_frame("path", "header.frame_id", message.header.frame_id, frame)
    if len(message.poses) > MAX_PATH_POSES:
        raise MessageError(f"path has {len(message.poses)} poses; at most {MAX_PATH_POSES} are accepted")
    frames = {pose.header.frame_id for pose in message.poses} - {"", frame}
    if frames:
        raise MessageError(f"path.poses[].header.frame_id holds {sorted(frames)}, expected {frame!r} or '' (socnav "
                           "does not look up tf)")
    waypoints = np.array([(pose.pose.position.x, pose.pose.position.y) for pose in message.poses],
                         dtype=np.float64).reshape(-1, 2)
    bad = np.flatnonzero(~np.isfinite(waypoints).all(axis=1))
    if bad.size:
        raise MessageError(f"path: poses {bad[:10].tolist()} are not finite")
    return waypoints


def point_stamped(point: np.ndarray, stamp: Time, frame: str) -> PointStamped:
    """A PointStamped at ``point`` (x, y; z = 0) in ``frame``."""
    message = PointStamped()
    message.header.stamp = stamp
    message.header.frame_id = frame
    message.point.x, message.point.y = float(point[0]), float(point[1])
    return message
