"""socnav.ros2.messages against hand-computed values: frames, quaternions, clouds of any layout, commands.
A cloud is also built byte by byte with NumPy (another writer than ours), and random bytes never escape as anything
but a `MessageError`."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

pytestmark = pytest.mark.ros2


@pytest.fixture(scope="module")
def messages():
    from socnav.ros2 import messages

    return messages


def _odometry(x=1.0, y=2.0, yaw=math.pi / 2, vx=1.0, vy=0.0, frame="odom", child="base_link"):
    from nav_msgs.msg import Odometry

    message = Odometry()
    message.header.frame_id, message.child_frame_id = frame, child
    message.header.stamp.sec, message.header.stamp.nanosec = 3, 250_000_000
    message.pose.pose.position.x, message.pose.pose.position.y = x, y
    message.pose.pose.orientation.z, message.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    message.twist.twist.linear.x, message.twist.twist.linear.y = vx, vy
    return message


def test_odometry_twist_is_rotated_from_base_link_into_odom(messages):
    # facing +y (yaw 90 deg), 1 m/s forward and 0.5 m/s to the left: over the ground that is (-0.5, 1.0)
    robot = messages.odometry_to_robot(_odometry(vx=1.0, vy=0.5), "odom", "base_link")
    np.testing.assert_allclose(robot.velocity, [-0.5, 1.0], atol=1e-12)
    np.testing.assert_array_equal(robot.position, [1.0, 2.0])
    assert robot.heading == pytest.approx(math.pi / 2, abs=1e-12)
    assert robot.stamp_ns == 3_250_000_000


@pytest.mark.parametrize("frame,child,field", [("map", "base_link", "header.frame_id"),
                                               ("odom", "base_footprint", "child_frame_id"), ("", "base_link", "")])
def test_odometry_in_other_frames_is_refused(messages, frame, child, field):
    with pytest.raises(messages.MessageError, match=f"odometry.{field}"):
        messages.odometry_to_robot(_odometry(frame=frame, child=child), "odom", "base_link")


@pytest.mark.parametrize("field,value", [("x", math.nan), ("vx", math.inf), ("vy", -math.inf)])
def test_odometry_nan_is_refused(messages, field, value):
    with pytest.raises(messages.MessageError, match="not finite"):
        messages.odometry_to_robot(_odometry(**{field: value}), "odom", "base_link")


def test_an_unset_orientation_is_refused(messages):
    message = _odometry()
    message.pose.pose.orientation.w = message.pose.pose.orientation.z = 0.0
    with pytest.raises(messages.MessageError, match="not a unit quaternion: norm 0"):
        messages.odometry_to_robot(message, "odom", "base_link")


@given(st.floats(-math.pi, math.pi), st.floats(-3, 3), st.floats(-3, 3))
def test_odometry_round_trip(yaw, vx, vy):
    from socnav.ros2 import messages

    message = messages.robot_to_odometry(np.array([0.5, -1.0]), np.array([vx, vy]), yaw, 0.1, 7, "odom", "base_link")
    robot = messages.odometry_to_robot(message, "odom", "base_link")
    np.testing.assert_allclose(robot.velocity, [vx, vy], atol=1e-12)
    assert math.remainder(robot.heading - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    # the twist is the velocity in the robot's axes: forward speed = v . (cos yaw, sin yaw)
    assert message.twist.twist.linear.x == pytest.approx(vx * math.cos(yaw) + vy * math.sin(yaw), abs=1e-12)


def test_yaw_of_a_tilted_quaternion_is_its_rotation_about_z(messages):
    from geometry_msgs.msg import Quaternion

    # roll 180 deg about x then yaw 90 deg about z: q = q_z(90) * q_x(180) = (c, s, 0, 0) with c = s = sqrt(1/2)
    half = math.sqrt(0.5)
    q = Quaternion(x=half, y=half, z=0.0, w=0.0)
    assert messages.yaw_from_quaternion(q) == pytest.approx(math.pi / 2, abs=1e-12)


def _numpy_cloud(points: dict[str, np.ndarray], dtype: np.dtype, frame="odom", row_padding=0, height=1):
    """A PointCloud2 written with NumPy's structured arrays (not by socnav): any field order, types, padding."""
    from sensor_msgs.msg import PointCloud2, PointField

    count = len(next(iter(points.values())))
    array = np.zeros(count, dtype=dtype)
    for name, values in points.items():
        array[name] = values
    width = count // height
    rows = array.tobytes()
    row_step = width * dtype.itemsize + row_padding
    data = b"".join(rows[r * width * dtype.itemsize:(r + 1) * width * dtype.itemsize] + b"\xff" * row_padding
                    for r in range(height))
    kinds = {np.dtype(order + kind): datatype for order in "<>"
             for kind, datatype in (("f4", PointField.FLOAT32), ("f8", PointField.FLOAT64), ("i4", PointField.INT32))}
    cloud = PointCloud2(height=height, width=width, point_step=dtype.itemsize, row_step=row_step,
                        is_bigendian=dtype.fields[dtype.names[0]][0].byteorder == ">", is_dense=True, data=data)
    cloud.header.frame_id = frame
    cloud.fields = [PointField(name=name, offset=offset, datatype=kinds[field_dtype], count=1)
                    for name, (field_dtype, offset) in dtype.fields.items()]
    return cloud


HUMANS = {"x": np.array([1.0, -2.5, 3.25, 0.0]), "y": np.array([0.5, 4.0, -1.0, 2.0]),
          "vx": np.array([0.0, 1.0, -0.5, 0.25]), "vy": np.array([1.0, 0.0, 0.5, -0.25]),
          "radius": np.array([0.3, 0.25, 0.4, 0.35])}


@pytest.mark.parametrize("order,kind", [(">", "f4"), ("<", "f4"), ("<", "f8")])
def test_clouds_of_other_layouts_are_read(messages, order, kind):
    # fields in another order, with an unused intensity field and padding between points and after each row
    dtype = np.dtype({"names": ["radius", "intensity", "vy", "vx", "y", "x"],
                      "formats": [order + kind, "<i4", order + kind, order + kind, order + kind, order + kind],
                      "offsets": [0, 8, 16, 24, 32, 40], "itemsize": 56})
    cloud = _numpy_cloud({**HUMANS, "intensity": np.arange(4)}, dtype, row_padding=6, height=2)
    humans = messages.cloud_to_humans(cloud, "odom", default_radius=9.0)
    stored = {name: values.astype(order + kind).astype(np.float64) for name, values in HUMANS.items()}
    np.testing.assert_array_equal(humans.positions, np.column_stack([stored["x"], stored["y"]]))
    np.testing.assert_array_equal(humans.velocities, np.column_stack([stored["vx"], stored["vy"]]))
    np.testing.assert_array_equal(humans.radii, stored["radius"])


def test_a_cloud_without_radius_uses_the_default(messages):
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("vx", "<f4"), ("vy", "<f4")])
    cloud = _numpy_cloud({name: HUMANS[name] for name in ("x", "y", "vx", "vy")}, dtype)
    np.testing.assert_array_equal(messages.cloud_to_humans(cloud, "odom", default_radius=0.3).radii, [0.3] * 4)
    np.testing.assert_array_equal(messages.cloud_to_humans(cloud, "odom", default_radius=0.3).positions[:, 0],
                                  HUMANS["x"].astype(np.float32))


def test_humans_round_trip_exactly(messages):
    positions, velocities = np.random.default_rng(0).normal(size=(2, 5, 2))
    radii = np.full(5, 0.3)
    cloud = messages.humans_to_cloud(positions, velocities, radii, 12, "odom")
    humans = messages.cloud_to_humans(cloud, "odom", 0.0)
    np.testing.assert_array_equal(humans.positions, positions)  # FLOAT64: the simulator's state, bit for bit
    np.testing.assert_array_equal(humans.velocities, velocities)
    assert humans.stamp_ns == 12


@pytest.mark.parametrize("change,match", [
    (lambda c: setattr(c.header, "frame_id", "base_link"), "header.frame_id is 'base_link'"),
    (lambda c: setattr(c, "fields", c.fields[1:]), r"lacks fields \['x'\]"),
    (lambda c: setattr(c.fields[2], "datatype", 5), "datatype 5; allowed: FLOAT32"),
    (lambda c: setattr(c.fields[1], "offset", 36), "does not fit in point_step"),
    (lambda c: setattr(c, "data", c.data[:-1]), "data has 159 bytes"),
    (lambda c: setattr(c, "width", 5), "layout is inconsistent"),
    (lambda c: setattr(c, "fields", [*c.fields, c.fields[0]]), "declares field 'x' twice"),
])
def test_bad_clouds_are_refused(messages, change, match):
    cloud = messages.humans_to_cloud(np.zeros((4, 2)), np.zeros((4, 2)), np.full(4, 0.3), 0, "odom")
    change(cloud)
    with pytest.raises(messages.MessageError, match=match):
        messages.cloud_to_humans(cloud, "odom", 0.3)


def test_an_empty_cloud_is_no_humans(messages):
    cloud = messages.humans_to_cloud(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 7, "odom")
    humans = messages.cloud_to_humans(cloud, "odom", 0.3)
    assert humans.positions.shape == (0, 2) and humans.radii.shape == (0,) and humans.stamp_ns == 7


def _empty(height: int, width: int, data: bytes, fields: bool = True, point_step: int = 40):
    """A cloud of ``height * width`` = 0 points as a broken tracker (or an attacker) might send it."""
    from sensor_msgs.msg import PointCloud2

    from socnav.ros2 import messages

    cloud = messages.humans_to_cloud(np.zeros((1, 2)), np.zeros((1, 2)), np.full(1, 0.3), 0, "odom")
    cloud.height, cloud.width, cloud.data, cloud.point_step = height, width, data, point_step
    cloud.row_step = width * point_step
    if not fields:
        cloud = PointCloud2(height=height, width=width, data=data)
        cloud.header.frame_id = "odom"
    return cloud


@pytest.mark.parametrize("cloud,match", [
    (lambda: _empty(0, 1, b"\0" * 40), "data has 40 bytes; row_step 40 x height 0 = 0"),
    (lambda: _empty(1, 0, b"\0" * 40), "data has 40 bytes; row_step 0 x height 1 = 0"),
    (lambda: _empty(0, 0, b"", fields=False), r"lacks fields \['x', 'y', 'vx', 'vy'\]"),
    (lambda: _empty(0, 1, b"", point_step=0), "does not fit in point_step 0"),
])
def test_a_malformed_cloud_of_no_points_is_refused_too(messages, cloud, match):
    """Zero points is no excuse: the layout is checked at any point count (height 0 and 40 data bytes is not "no
    humans", it is a broken message)."""
    with pytest.raises(messages.MessageError, match=match):
        messages.cloud_to_humans(cloud(), "odom", 0.3)


@pytest.mark.parametrize("field,row", [("x", 2), ("vy", 0), ("radius", 3)])
def test_a_nan_human_is_refused_naming_its_point(messages, field, row):
    values = {name: array.copy() for name, array in HUMANS.items()}
    values[field][row] = math.nan
    cloud = messages.humans_to_cloud(np.column_stack([values["x"], values["y"]]),
                                     np.column_stack([values["vx"], values["vy"]]), values["radius"], 0, "odom")
    with pytest.raises(messages.MessageError, match=rf"not finite \(NaN or inf\) at points \[{row}\]"):
        messages.cloud_to_humans(cloud, "odom", 0.3)


@given(st.integers(0, 4), st.integers(0, 6), st.integers(0, 64), st.integers(0, 80), st.binary(max_size=300),
       st.lists(st.tuples(st.sampled_from(["x", "y", "vx", "vy", "radius", "z"]), st.integers(-4, 70),
                          st.integers(0, 9), st.integers(0, 3)), max_size=7), st.booleans())
def test_any_cloud_is_read_or_refused_with_a_message_error(height, width, point_step, row_step, data, fields,
                                                            bigendian):
    from sensor_msgs.msg import PointCloud2, PointField

    from socnav.ros2.messages import MessageError, cloud_to_humans

    cloud = PointCloud2(height=height, width=width, point_step=point_step, row_step=row_step, data=data,
                        is_bigendian=bigendian)
    cloud.header.frame_id = "odom"
    cloud.fields = [PointField(name=name, offset=max(offset, 0), datatype=kind, count=count)
                    for name, offset, kind, count in fields]
    try:
        humans = cloud_to_humans(cloud, "odom", 0.3)
    except MessageError:
        return
    assert len(humans.radii) == height * width
    assert np.isfinite(humans.positions).all() and (humans.radii >= 0).all()


def test_goal_and_command(messages):
    goal = messages.position_to_goal(np.array([3.0, -4.0]), 5, "odom")
    np.testing.assert_array_equal(messages.goal_to_position(goal, "odom"), [3.0, -4.0])
    goal.pose.position.y = math.nan
    with pytest.raises(messages.MessageError, match="goal is not finite"):
        messages.goal_to_position(goal, "odom")
    # 0.8 m/s and a 0.1 rad turn per 0.25 s step: a yaw rate of 0.4 rad/s
    twist = messages.command_to_twist(0.8, 0.1, 0.25)
    assert (twist.linear.x, twist.angular.z) == (0.8, pytest.approx(0.4))
    assert messages.twist_to_command(twist, 0.25) == (0.8, pytest.approx(0.1))
    twist.angular.z = math.inf
    with pytest.raises(messages.MessageError, match="cmd_vel is not finite"):
        messages.twist_to_command(twist, 0.25)
