"""socnav.ros2.messages' scan, map, pose and path conversions against hand-computed values: a LaserScan in the trained
layout passes through, any other is resampled by the minimum over each trained beam's sector, REP 117's readings keep
their meaning; an OccupancyGrid's blocked cells become wall polygons where they lie (rows from the origin up, the
origin's yaw applied), and the simulator's walls survive the trip through a grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import unary_union

pytestmark = pytest.mark.ros2


@pytest.fixture(scope="module")
def messages():
    from socnav.ros2 import messages

    return messages


def _scan(ranges, angle_min=-math.pi, increment=None, frame="base_link", range_min=0.0, range_max=30.0):
    """A LaserScan of ``ranges`` from ``angle_min`` (default: a full turn, ``2 pi / len(ranges)`` apart)."""
    from sensor_msgs.msg import LaserScan

    message = LaserScan()
    message.header.frame_id = frame
    message.angle_min = angle_min
    message.angle_increment = 2.0 * math.pi / len(ranges) if increment is None else increment
    message.angle_max = message.angle_min + message.angle_increment * (len(ranges) - 1)
    message.range_min, message.range_max = range_min, range_max
    message.ranges = [float(value) for value in ranges]
    return message


# ------------------------------------------------------------------------------------------------- scan: layouts


def test_the_trained_layout_passes_through(messages):
    ranges = np.linspace(0.5, 7.5, 36)
    np.testing.assert_array_equal(messages.scan_to_ranges(_scan(ranges), "base_link", 36, 360.0),
                                  ranges.astype(np.float32))


def test_a_narrower_trained_field_of_view_passes_through(messages):
    """5 beams over 180 degrees: -90, -45, 0, 45, 90 degrees (the simulator's layout: the last beam at +fov/2)."""
    assert messages.trained_scan_angles(5, 180.0) == pytest.approx((-math.pi / 2, math.pi / 4))
    ranges = [1.0, 2.0, 3.0, 4.0, 5.0]
    scan = _scan(ranges, angle_min=-math.pi / 2, increment=math.pi / 4)
    np.testing.assert_array_equal(messages.scan_to_ranges(scan, "base_link", 5, 180.0), ranges)


def test_the_simulators_scan_message_is_the_trained_layout(messages):
    ranges = np.linspace(1.0, 8.0, 36)
    scan = messages.ranges_to_scan(ranges, 7, "base_link", 360.0, 8.0)
    assert (scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max) == pytest.approx(
        (-math.pi, math.pi / 18, 0.0, 8.0))
    np.testing.assert_allclose(messages.scan_to_ranges(scan, "base_link", 36, 360.0), ranges, rtol=1e-7)


def test_a_finer_scan_takes_the_minimum_over_each_trained_sector(messages):
    """72 readings (5 degrees apart, each owning +-2.5 degrees) for 36 trained beams (10 degrees apart, each owning
    +-5 degrees): beam b overlaps readings 2b - 1 (its last half), 2b and 2b + 1 (its first half), wrapping around.
    Readings 100 - j: beam 0 = min(r71, r0, r1) = 29; beam b = r(2b + 1) = 99 - 2b for b < 35; beam 35 = min(r69,
    r70, r71) = 29."""
    ranges = 100.0 - np.arange(72)
    got = messages.scan_to_ranges(_scan(ranges, range_max=200.0), "base_link", 36, 360.0)
    expected = [29.0] + [99.0 - 2 * b for b in range(1, 35)] + [29.0]
    np.testing.assert_array_equal(got, expected)


def test_a_coarser_scan_covers_every_trained_beam_its_readings_overlap(messages):
    """18 readings (20 degrees apart, each owning +-10 degrees) for 36 trained beams: beam 2k sees reading k alone,
    beam 2k + 1 readings k and k + 1; beam 35 readings 17 and 0."""
    ranges = np.arange(1.0, 19.0)
    got = messages.scan_to_ranges(_scan(ranges), "base_link", 36, 360.0)
    expected = [min(ranges[b // 2], ranges[(b // 2 + b % 2) % 18]) for b in range(36)]
    np.testing.assert_array_equal(got, expected)
    assert got[:6].tolist() == [1.0, 1.0, 2.0, 2.0, 3.0, 3.0] and got[35] == 1.0


def test_a_scan_a_quarter_beam_off_takes_the_two_readings_each_beam_overlaps(messages):
    """36 readings shifted by a quarter of a beam (2.5 degrees): reading j owns [j - 1/4, j + 3/4] beams, so beam b
    overlaps readings b - 1 and b."""
    ranges = np.array([5.0, 1.0, 7.0, 3.0] * 9)
    got = messages.scan_to_ranges(_scan(ranges, angle_min=-math.pi + math.pi / 72), "base_link", 36, 360.0)
    np.testing.assert_array_equal(got, np.minimum(ranges, np.roll(ranges, 1)))


def test_a_narrower_sensor_leaves_the_unseen_sectors_at_no_return(messages):
    """A 3-reading sensor over -45, 0, 45 degrees for 8 trained beams over a full turn (-180, -135, ..., 135): its
    readings are beams 3, 4, 5; the others read +inf."""
    got = messages.scan_to_ranges(_scan([2.0, 3.0, 4.0], angle_min=-math.pi / 4, increment=math.pi / 4), "base_link",
                                  8, 360.0)
    assert got.tolist() == [math.inf] * 3 + [2.0, 3.0, 4.0] + [math.inf] * 2


def test_a_scan_in_another_frame_is_refused(messages):
    with pytest.raises(messages.MessageError, match=r"scan\.header\.frame_id is 'laser', expected 'base_link'"):
        messages.scan_to_ranges(_scan(np.ones(36), frame="laser"), "base_link", 36, 360.0)


# ------------------------------------------------------------------------------------------------- scan: REP 117


def test_rep_117_readings_keep_their_meaning(messages):
    """+inf (no return) and -inf (too close) stay; a finite reading beyond range_max is no return (+inf)
    (`SafeNavigator.act` then reads them as its trained range, 0 and its trained range)."""
    ranges = np.full(36, 2.0)
    ranges[:3] = [math.inf, -math.inf, 50.0]
    got = messages.scan_to_ranges(_scan(ranges, range_min=0.1, range_max=30.0), "base_link", 36, 360.0)
    assert got[:4].tolist() == [math.inf, -math.inf, math.inf, 2.0]


@pytest.mark.parametrize("value", [math.nan, 0.0, 0.05])
def test_a_beam_with_only_invalid_readings_stops_the_robot(messages, value):
    """NaN (erroneous) and a finite value below range_min (discarded, as the message says) tell nothing: a trained
    beam with nothing else is refused, not taken for free space."""
    ranges = np.full(36, 2.0)
    ranges[4] = value
    with pytest.raises(messages.MessageError, match=r"scan: trained beams \[4\] have only invalid readings"):
        messages.scan_to_ranges(_scan(ranges, range_min=0.1), "base_link", 36, 360.0)


def test_an_invalid_reading_among_valid_ones_is_left_out_of_the_minimum(messages):
    ranges = np.full(72, 3.0)
    ranges[8], ranges[9] = math.nan, 0.0  # both in beam 4's sector (readings 7, 8, 9), with reading 7 valid
    ranges[7] = 2.5
    got = messages.scan_to_ranges(_scan(ranges, range_min=0.1), "base_link", 36, 360.0)
    assert got[4] == 2.5 and got[3] == 2.5 and got[5] == 3.0  # reading 7 is also in beam 3's sector


def _no_ranges(scan) -> None:
    scan.ranges = []


@pytest.mark.parametrize("change,match", [
    (_no_ranges, "scan has 0 ranges; allowed: 1 to 100000"),
    (lambda scan: setattr(scan, "range_min", 40.0), "0 <= range_min < range_max"),
    (lambda scan: setattr(scan, "angle_increment", 0.0), "scan.angle_increment is 0 for 36 ranges"),
    (lambda scan: setattr(scan, "angle_min", math.nan), r"scan is not finite: \{'angle_min': nan\}"),
    (lambda scan: setattr(scan, "angle_increment", 1.0), "at most two turns"),
])
def test_a_malformed_scan_is_refused(messages, change, match):
    scan = _scan(np.ones(36))
    change(scan)
    with pytest.raises(messages.MessageError, match=match):
        messages.scan_to_ranges(scan, "base_link", 36, 360.0)


# ------------------------------------------------------------------------------------------------- map


def _grid(values, resolution=0.5, origin=(1.0, 2.0), yaw=0.0, frame="map"):
    """An OccupancyGrid of ``values`` given row by row from the origin's row (row 0: the lowest y)."""
    from nav_msgs.msg import OccupancyGrid

    values = np.asarray(values, dtype=np.int8)
    message = OccupancyGrid()
    message.header.frame_id = frame
    message.info.resolution = resolution
    message.info.height, message.info.width = values.shape
    message.info.origin.position.x, message.info.origin.position.y = origin
    message.info.origin.orientation.z, message.info.origin.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    message.data = values.ravel().tolist()
    return message


#: 4 rows x 6 columns, rows from the origin up: a 2 x 2 block of occupied cells in columns 4-5 of rows 0-1.
BLOCK = [[0, 0, 0, 0, 100, 100],
         [0, 0, 0, 0, 100, 100],
         [0, 0, 0, 0, 0, 0],
         [0, 0, 0, 0, 0, 0]]


def _only_polygon(walls) -> Polygon:
    assert len(walls) == 1, walls
    return Polygon(walls[0])


def test_one_occupied_block_becomes_one_solid_polygon_where_it_lies(messages):
    """Columns 4-5 are x in [1 + 4 * 0.5, 1 + 6 * 0.5] = [3, 4]; rows 0-1 (the lowest) are y in [2, 3]."""
    from socnav.sim.maps import is_counter_clockwise

    walls = messages.grid_to_walls(_grid(BLOCK), "map")
    assert _only_polygon(walls).equals(box(3.0, 2.0, 4.0, 3.0))
    assert is_counter_clockwise(walls[0])  # solid (RVO2)


def test_the_origins_yaw_turns_the_grid_about_the_origin(messages):
    """Yaw 90 degrees: the grid's (x, y) = ([2, 3], [0, 1]) m from the origin lands at origin + (-y, x): x in
    [1 - 1, 1 - 0] = [0, 1], y in [2 + 2, 2 + 3] = [4, 5]."""
    walls = messages.grid_to_walls(_grid(BLOCK, yaw=math.pi / 2), "map")
    assert _only_polygon(walls).symmetric_difference(box(0.0, 4.0, 1.0, 5.0)).area < 1e-12  # (rotation: rounding)


@pytest.mark.parametrize("value,is_wall", [(-1, True), (10, False), (24, False), (25, True), (100, True)])
def test_a_cell_is_a_wall_unless_known_to_be_free(messages, value, is_wall):
    """free_thresh 0.25: occupancy below 25 is free; unknown (-1) and anything else is a wall."""
    values = np.zeros((3, 3), dtype=np.int8)
    values[1, 1] = value
    walls = messages.grid_to_walls(_grid(values, resolution=1.0, origin=(0.0, 0.0)), "map", free_thresh=0.25)
    assert (walls != []) == is_wall
    if is_wall:
        assert _only_polygon(walls).equals(box(1.0, 1.0, 2.0, 2.0))


@pytest.mark.parametrize("change,match", [
    (lambda grid: setattr(grid.header, "frame_id", "odom"), "map.header.frame_id is 'odom', expected 'map'"),
    (lambda grid: setattr(grid, "data", [0] * 5), r"map.data has 5 cells; info.width 6 x info.height 4 = 24"),
    (lambda grid: setattr(grid.info, "resolution", 0.0), "map.info.resolution must be > 0"),
    (lambda grid: setattr(grid.info.origin.orientation, "w", 0.0), "not a unit quaternion"),
])
def test_a_malformed_map_is_refused(messages, change, match):
    grid = _grid(BLOCK)
    change(grid)
    with pytest.raises(messages.MessageError, match=match):
        messages.grid_to_walls(grid, "map")


def test_the_doorways_walls_survive_a_grid(messages):
    """The simulator's doorway (two 8 x 8 m rooms, a 1.1 m door at x = 0) rasterised at 5 cm and read back: walls
    where the world has them, at most a cell (and half a cell of simplification) thicker; the door still open."""
    import socnav
    from socnav.sim.world import CrowdWorld

    world = CrowdWorld(socnav.load_config({"scenario": "doorway", "n_humans": 0}), 1)
    grid = messages.walls_to_grid(world.walls.polygons, 0.05, 5, "map")
    assert grid.header.frame_id == "map" and grid.info.resolution == pytest.approx(0.05)
    walls = [Polygon(vertices) for vertices in messages.grid_to_walls(grid, "map")]
    solid = unary_union([polygon for polygon in walls if polygon.exterior.is_ccw]).difference(
        unary_union([polygon for polygon in walls if not polygon.exterior.is_ccw]))
    for wall in world.walls.polygons:
        assert solid.buffer(1e-9).contains(LineString(wall)), wall
    assert solid.buffer(-0.1).is_empty  # no thicker than two cells anywhere
    assert not solid.contains(Point(0.0, 0.0)) and not solid.intersects(LineString([(0.0, -0.45), (0.0, 0.45)]))
    assert not solid.contains(Point(-4.0, 0.0)) and not solid.contains(Point(4.0, 2.0))  # the rooms are free


def test_a_boundary_encloses_free_space_in_the_grid(messages):
    """A clockwise polygon (a room agents stay inside) with a solid box in it: outside the room and inside the box
    are occupied, the room around the box free."""
    room = np.array([[0.0, 0.0], [0.0, 4.0], [4.0, 4.0], [4.0, 0.0]])  # clockwise
    table = np.array([[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]])  # counter-clockwise
    grid = messages.walls_to_grid([room, table], 0.25, 5, "map", padding=1.0)
    cells = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    origin = np.array([grid.info.origin.position.x, grid.info.origin.position.y])

    def at(x, y):
        column, row = np.floor((np.array([x, y]) - origin) / 0.25).astype(int)
        return cells[row, column]

    assert (at(-0.6, 2.0), at(1.5, 1.5), at(3.0, 3.0), at(0.6, 3.4)) == (100, 100, 0, 0)


# ------------------------------------------------------------------------------------------------- pose and path


def test_a_pose_is_read_in_the_map_frame(messages):
    from geometry_msgs.msg import PoseWithCovarianceStamped

    pose = PoseWithCovarianceStamped()
    pose.header.frame_id = "map"
    pose.pose.pose.position.x, pose.pose.pose.position.y = 3.0, -1.0
    pose.pose.pose.orientation.z, pose.pose.pose.orientation.w = math.sin(0.3), math.cos(0.3)
    np.testing.assert_allclose(messages.pose_to_map_pose(pose, "map"), [3.0, -1.0, 0.6])
    pose.header.frame_id = "odom"
    with pytest.raises(messages.MessageError, match=r"pose\.header\.frame_id is 'odom', expected 'map'"):
        messages.pose_to_map_pose(pose, "map")


def test_a_path_is_read_as_waypoints(messages):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path

    path = Path()
    path.header.frame_id = "map"
    assert messages.path_to_waypoints(path, "map").shape == (0, 2)  # empty: the navigator plans its own
    for x, y in ((0.0, 1.0), (2.0, 3.0)):
        pose = PoseStamped()
        pose.pose.position.x, pose.pose.position.y = x, y
        path.poses.append(pose)
    np.testing.assert_array_equal(messages.path_to_waypoints(path, "map"), [[0.0, 1.0], [2.0, 3.0]])
    path.poses[1].pose.position.y = math.inf
    with pytest.raises(messages.MessageError, match=r"path: poses \[1\] are not finite"):
        messages.path_to_waypoints(path, "map")
    path.poses[1].pose.position.y, path.poses[1].header.frame_id = 3.0, "odom"
    with pytest.raises(messages.MessageError, match=r"path.poses\[\].header.frame_id holds \['odom'\]"):
        messages.path_to_waypoints(path, "map")
