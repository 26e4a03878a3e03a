"""Tests of socnav.sim.maps: polygon validation and RVO2 orientation, the clearance check, and both map formats
(polygon YAML; ROS map_server YAML + PGM/PNG written here with Pillow), every loader error path included."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image
from shapely import union_all
from shapely.geometry import LinearRing, Polygon, box

from socnav.sim import maps
from socnav.sim.maps import (
    MAX_POLYGON_VERTICES,
    MAX_TOTAL_VERTICES,
    MapError,
    clearance_violation,
    is_counter_clockwise,
    load_map,
    orient_rvo2,
    validate_polygons,
)

SQUARE_CCW = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]


def _regular_polygon(n: int, radius: float = 1.0, centre=(0.0, 0.0)) -> list[list[float]]:
    angles = 2.0 * np.pi * np.arange(n) / n
    return (np.stack([np.cos(angles), np.sin(angles)], axis=1) * radius + centre).tolist()


# --------------------------------------------------------------------------------------------------------------------
# validate_polygons
# --------------------------------------------------------------------------------------------------------------------
def test_valid_polygons_come_back_as_float_arrays_with_their_orientation():
    wall = [[0, 0], [2, 1]]
    clockwise = SQUARE_CCW[::-1]
    checked = validate_polygons([SQUARE_CCW, wall, clockwise])
    assert [p.dtype for p in checked] == [np.float64] * 3
    np.testing.assert_array_equal(checked[1], [[0.0, 0.0], [2.0, 1.0]])
    np.testing.assert_array_equal(checked[2], clockwise)  # orientation carries meaning: never changed here


def test_a_closing_repeat_of_the_first_vertex_is_dropped():
    (checked,) = validate_polygons([[*SQUARE_CCW, SQUARE_CCW[0]]])
    np.testing.assert_array_equal(checked, SQUARE_CCW)


@pytest.mark.parametrize(
    "polygon, rule",
    [
        ([[0, 0], [1, 1], [1, 0], [0, 1]], "self-intersecting polygon"),  # a bow tie
        ([[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]], "self-intersecting polygon"),  # a vertex touching an edge
        ([[0, 0], [1, 0], [2, 0]], "zero-area polygon"),
        ([[0, 0], [1, 0], [1, 0], [1, 1]], "zero-length edge at vertex 1"),
        ([[3, 3], [3, 3]], "zero-length edge at vertex 0"),
        ([[0, 0]], "at least 2 vertices"),
        ([], "at least 2 vertices"),
        ([[0, 0], [1, float("nan")], [1, 1]], "non-finite coordinate"),
        ([[0, 0], [float("inf"), 0]], "non-finite coordinate"),
        ([0, 1, 2], "list of [x, y] vertices"),
        ([[0, 0, 0], [1, 1, 1]], "list of [x, y] vertices"),
        ([["a", 0], [1, 1]], "vertices of numbers"),
    ],
)
def test_each_rule_is_named_with_the_polygon_index(polygon, rule):
    with pytest.raises(MapError) as error:
        validate_polygons([SQUARE_CCW, polygon], name="obstacles")
    assert str(error.value).startswith("obstacles[1]: ")
    assert rule in str(error.value)
    assert isinstance(error.value, ValueError)  # pydantic validators turn ValueError into a field error


def test_the_vertex_bounds():
    validate_polygons([_regular_polygon(MAX_POLYGON_VERTICES)])
    with pytest.raises(MapError, match=rf"obstacles\[0\]: {MAX_POLYGON_VERTICES + 1} vertices, more than the bound"):
        validate_polygons([_regular_polygon(MAX_POLYGON_VERTICES + 1)])
    many = [_regular_polygon(MAX_POLYGON_VERTICES, centre=(3.0 * k, 0.0)) for k in range(MAX_TOTAL_VERTICES // 512)]
    validate_polygons(many)
    with pytest.raises(MapError, match=rf"obstacles: {MAX_TOTAL_VERTICES + 2} vertices in all"):
        validate_polygons([*many, [[0, 5], [1, 5]]])


def test_a_string_is_not_a_polygon_list():
    with pytest.raises(MapError, match="obstacles: expected a list of polygons, got str"):
        validate_polygons("[[0, 0], [1, 1]]")


# --------------------------------------------------------------------------------------------------------------------
# Orientation
# --------------------------------------------------------------------------------------------------------------------
def test_orient_rvo2_gives_counter_clockwise_solids_and_clockwise_free_space():
    clockwise = np.array(SQUARE_CCW[::-1])
    assert is_counter_clockwise(np.array(SQUARE_CCW)) and not is_counter_clockwise(clockwise)
    solid = orient_rvo2(clockwise, solid=True)
    enclosing = orient_rvo2(np.array(SQUARE_CCW), solid=False)
    assert is_counter_clockwise(solid) and not is_counter_clockwise(enclosing)
    # same vertex set, cyclically reordered
    assert LinearRing(solid).equals(LinearRing(clockwise)) and LinearRing(enclosing).equals(LinearRing(SQUARE_CCW))
    assert len(solid) == 4 and len(enclosing) == 4
    wall = np.array([[2.0, 0.0], [0.0, 0.0]])
    np.testing.assert_array_equal(orient_rvo2(wall, solid=True), wall)


# --------------------------------------------------------------------------------------------------------------------
# clearance_violation
# --------------------------------------------------------------------------------------------------------------------
def _room_with_pillar():
    """Walls 1 m thick around a 10 x 10 m room, as the grid loader makes them: outer outline counter-clockwise, the
    room (the hole) clockwise, and a 1 x 1 m pillar at [4, 5] x [4, 5] counter-clockwise."""
    outer = orient_rvo2(np.array([[-1, -1], [11, -1], [11, 11], [-1, 11]], float), solid=True)
    room = orient_rvo2(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float), solid=False)
    pillar = orient_rvo2(np.array([[4, 4], [5, 4], [5, 5], [4, 5]], float), solid=True)
    return [outer, room, pillar]


@pytest.mark.parametrize(
    "point, radius, expected",
    [
        ((2.0, 2.0), 0.3, None),  # in the room, clear of everything
        ((4.5, 4.5), 0.3, "inside the obstacle obstacles[2]"),  # in the pillar
        ((10.5, 5.0), 0.3, "inside the obstacle obstacles[0]"),  # in the wall
        ((20.0, 5.0), 0.3, None),  # outside the walls: free space (in RVO2 too)
        ((3.8, 4.5), 0.3, "0.2 m from obstacles[2], closer than the radius 0.3 m"),
        ((3.5, 4.5), 0.5, None),  # touching the pillar: fits (gap 0 is no collision)
        ((0.25, 5.0), 0.3, "0.25 m from obstacles[1]"),  # the room's edge is the hole's ring
    ],
)
def test_clearance_in_a_walled_room(point, radius, expected):
    message = clearance_violation(_room_with_pillar(), point, radius)
    if expected is None:
        assert message is None
    else:
        assert expected in message


def test_clearance_with_a_standalone_boundary_and_a_wall_segment():
    boundary = orient_rvo2(np.array([[0, 0], [6, 0], [6, 4], [0, 4]], float), solid=False)
    wall = np.array([[3.0, 0.0], [3.0, 2.0]])
    polygons = [wall, boundary]
    assert clearance_violation(polygons, (1.0, 1.0), 0.5) is None
    assert "outside the free space enclosed by obstacles[1]" in clearance_violation(polygons, (7.0, 1.0), 0.5)
    assert "0.4 m from obstacles[0]" in clearance_violation(polygons, (3.4, 1.0), 0.5)
    assert "0.5 m from obstacles[0]" in clearance_violation(polygons, (3.0, 2.5), 0.6)  # past the wall's end
    # the same square as a solid obstacle: its inside is blocked, its outside free
    solid = orient_rvo2(boundary, solid=True)
    assert "inside the obstacle obstacles[0]" in clearance_violation([solid], (1.0, 1.0), 0.1)
    assert clearance_violation([solid], (7.0, 1.0), 0.5) is None


# --------------------------------------------------------------------------------------------------------------------
# Polygon YAML
# --------------------------------------------------------------------------------------------------------------------
def _write_yaml(path: Path, document) -> Path:
    path.write_text(yaml.safe_dump(document))
    return path


def test_polygon_map_is_oriented_for_rvo2(tmp_path):
    path = _write_yaml(tmp_path / "map.yaml", {
        "obstacles": [[*SQUARE_CCW[::-1], SQUARE_CCW[-1]], [[3, -1], [3, 2]]],  # clockwise, written closed
        "boundaries": [[[-5, -5], [5, -5], [5, 5], [-5, 5]]],  # counter-clockwise as written
    })
    square, wall, boundary = load_map(path)
    assert len(square) == 4 and is_counter_clockwise(square) and LinearRing(square).equals(LinearRing(SQUARE_CCW))
    np.testing.assert_array_equal(wall, [[3.0, -1.0], [3.0, 2.0]])
    assert not is_counter_clockwise(boundary) and Polygon(boundary).area == 100.0


def test_a_polygon_map_may_have_no_obstacles(tmp_path):
    assert load_map(_write_yaml(tmp_path / "map.yaml", {"obstacles": []})) == []


@pytest.mark.parametrize(
    "document, message",
    [
        ([1, 2], "expected a mapping with 'obstacles'"),
        ({"walls": []}, "neither a polygon map (key 'obstacles') nor a map_server map"),
        ({"obstacles": [], "boundary": []}, "unknown key 'boundary'; a polygon map allows boundaries, obstacles"),
        ({"obstacles": [SQUARE_CCW, [[0, 0], [1, 1], [1, 0], [0, 1]]]}, "obstacles[1]: self-intersecting polygon"),
        ({"obstacles": [], "boundaries": [[[0, 0], [1, 0]], [[0, 0]]]}, "boundaries[1]: a polygon needs at least 2"),
        ({"obstacles": {"a": 1}}, "obstacles: expected a list of polygons, got dict"),
        ({"obstacles": [[[0, 0], [1, ".nan"]]]}, "obstacles[0]: expected a list of [x, y] vertices of numbers"),
    ],
)
def test_polygon_map_errors_name_the_file_and_the_rule(tmp_path, document, message):
    path = _write_yaml(tmp_path / "map.yaml", document)
    with pytest.raises(MapError) as error:
        load_map(path)
    assert str(path) in str(error.value) and message in str(error.value)


def test_non_finite_yaml_coordinates_are_refused(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("obstacles:\n  - [[0, 0], [1, .inf]]\n")
    with pytest.raises(MapError, match=r"obstacles\[0\]: non-finite coordinate"):
        load_map(path)


def test_the_total_bound_counts_obstacles_and_boundaries(tmp_path):
    half = [_regular_polygon(512, 1.0, (3.0 * k, 0.0)) for k in range(MAX_TOTAL_VERTICES // 1024)]
    path = _write_yaml(tmp_path / "map.yaml", {"obstacles": half, "boundaries": [*half, [[0, 9], [1, 9]]]})
    with pytest.raises(MapError, match=rf"{MAX_TOTAL_VERTICES + 2} vertices in obstacles and boundaries"):
        load_map(path)


def test_missing_and_unparsable_map_files(tmp_path):
    with pytest.raises(MapError, match=r"map file not found: .*nowhere.yaml"):
        load_map(tmp_path / "nowhere.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("obstacles: [[[0, 0], [1, 1]]\n")
    with pytest.raises(MapError, match=re.escape("broken.yaml: cannot read the map YAML")):
        load_map(broken)


# --------------------------------------------------------------------------------------------------------------------
# map_server occupancy grids
# --------------------------------------------------------------------------------------------------------------------
FREE, OCCUPIED, UNKNOWN = 254, 0, 205  # the values map_saver writes (trinary)
RESOLUTION = 0.1
ORIGIN = [-1.0, -2.0, 0.0]


def _room_image() -> np.ndarray:
    """A 30 x 40 (rows x columns) image: free, with a walled room -- walls 2 cells thick around columns 5..34, rows
    5..24 -- and a 3 x 4 pillar at rows 8..10, columns 10..13 (near the top of the image)."""
    image = np.full((30, 40), FREE, dtype=np.uint8)
    image[5:25, 5:35] = OCCUPIED
    image[7:23, 7:33] = FREE
    image[8:11, 10:14] = OCCUPIED
    return image


def _cells_to_map(row0, row1, col0, col1, height=30, resolution=RESOLUTION, origin=ORIGIN):
    """The box, in metres in the map frame, of image rows row0..row1-1 and columns col0..col1-1 (y flipped)."""
    x0, x1 = origin[0] + col0 * resolution, origin[0] + col1 * resolution
    y0, y1 = origin[1] + (height - row1) * resolution, origin[1] + (height - row0) * resolution
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def _write_grid(tmp_path: Path, pixels: np.ndarray, name: str = "map.pgm", **overrides) -> Path:
    Image.fromarray(pixels).save(tmp_path / name)
    document = {"image": name, "resolution": RESOLUTION, "origin": ORIGIN, "negate": 0,
                "occupied_thresh": 0.65, "free_thresh": 0.196}
    document.update(overrides)
    return _write_yaml(tmp_path / "map.yaml", {k: v for k, v in document.items() if v is not None})


def _match(polygons, box) -> np.ndarray:
    """The polygon whose outline lies within half a cell of `box` (Hausdorff distance), which must be unique."""
    found = [p for p in polygons if LinearRing(p).hausdorff_distance(LinearRing(box)) <= RESOLUTION / 2 + 1e-9]
    assert len(found) == 1, f"{len(found)} polygons match {box.tolist()} in {[p.tolist() for p in polygons]}"
    return found[0]


def test_walled_room_with_a_pillar_gives_the_outline_the_room_and_the_pillar(tmp_path):
    polygons = load_map(_write_grid(tmp_path, _room_image()))
    assert len(polygons) == 3
    outline = _match(polygons, _cells_to_map(5, 25, 5, 35))
    room = _match(polygons, _cells_to_map(7, 23, 7, 33))
    pillar = _match(polygons, _cells_to_map(8, 11, 10, 14))
    assert is_counter_clockwise(outline) and is_counter_clockwise(pillar)  # solid
    assert not is_counter_clockwise(room)  # free space agents stay inside (RVO2: clockwise)
    # by hand: the pillar's cells are x in [-1 + 1.0, -1 + 1.4], y in [-2 + (30 - 11) 0.1, -2 + (30 - 8) 0.1]
    np.testing.assert_allclose(pillar.min(axis=0), [0.0, -0.1], atol=RESOLUTION / 2)
    np.testing.assert_allclose(pillar.max(axis=0), [0.4, 0.2], atol=RESOLUTION / 2)
    inside_room = (0.0, 0.0 + 0.8)
    assert clearance_violation(polygons, inside_room, 0.2) is None
    assert "inside the obstacle" in clearance_violation(polygons, (0.2, 0.05), 0.1)


def test_negate_unknown_cells_scale_mode_and_colour_images(tmp_path):
    image = _room_image()
    reference = load_map(_write_grid(tmp_path, image))
    # negate: white is occupied
    negated = load_map(_write_grid(tmp_path, 255 - image, negate=1))
    assert [p.tolist() for p in negated] == [p.tolist() for p in reference]
    # unknown (grey) cells are obstacles, like occupied ones; in scale mode too
    grey = np.where(image == OCCUPIED, UNKNOWN, image).astype(np.uint8)
    for mode in (None, "trinary", "scale"):
        assert [p.tolist() for p in load_map(_write_grid(tmp_path, grey, mode=mode))] == \
            [p.tolist() for p in reference]


def test_colour_channels_are_averaged_and_alpha_ignored(tmp_path):
    """(255, 255, 60) averages to 190: p = 65/255 = 0.255, not free. Pillow's luma (233) or an average with the
    alpha (206) would read it free (p < 0.196)."""
    rgba = np.full((6, 6, 4), 255, dtype=np.uint8)
    rgba[2:4, 1:3, :3] = [255, 255, 60]
    (cell,) = load_map(_write_grid(tmp_path, rgba, name="map.png"))
    assert LinearRing(cell).hausdorff_distance(LinearRing(_cells_to_map(2, 4, 1, 3, height=6))) < 1e-12


def test_free_threshold_is_strict_as_in_map_server(tmp_path):
    image = np.full((4, 4), FREE, dtype=np.uint8)
    image[1, 1] = 204  # p = 51 / 255 = 0.2 exactly
    assert load_map(_write_grid(tmp_path, image, free_thresh=0.2)) != []  # p < free_thresh is false: not free
    assert load_map(_write_grid(tmp_path, image, free_thresh=0.21)) == []


def test_yaw_rotates_the_map_about_its_origin(tmp_path):
    image = np.full((10, 10), FREE, dtype=np.uint8)
    image[9, 2] = OCCUPIED  # bottom row: cell x in [2, 3] cells, y in [0, 1] cells
    (cell,) = load_map(_write_grid(tmp_path, image, origin=[1.0, 1.0, math.pi / 2]))
    # rotated by +90 degrees about (1, 1): x' = 1 - y, y' = 1 + x (in metres)
    expected = np.array([[1.0 - 0.1, 1.2], [1.0, 1.2], [1.0, 1.3], [1.0 - 0.1, 1.3]])
    assert LinearRing(cell).hausdorff_distance(LinearRing(expected)) < 1e-12
    assert is_counter_clockwise(cell)


def test_an_empty_grid_has_no_obstacles(tmp_path):
    assert load_map(_write_grid(tmp_path, np.full((5, 7), FREE, dtype=np.uint8))) == []


@pytest.mark.parametrize("key", ["image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"])
def test_each_missing_key_is_named(tmp_path, key):
    path = _write_grid(tmp_path, _room_image(), **{key: None})
    if key == "image":  # without 'image' the file is no map_server map at all
        with pytest.raises(MapError, match="neither a polygon map"):
            load_map(path)
        return
    with pytest.raises(MapError, match=f"missing map_server key\\(s\\) {key}"):
        load_map(path)


@pytest.mark.parametrize(
    "override, message",
    [
        ({"mode": "raw"}, "mode must be one of trinary, scale ('raw' is not supported), got 'raw'"),
        ({"mode": "binary"}, "mode must be one of trinary, scale"),
        ({"resolution": 0}, "resolution must be > 0"),
        ({"resolution": "fine"}, "resolution must be a finite number, got 'fine'"),
        ({"resolution": True}, "resolution must be a finite number"),
        ({"origin": [0.0, 0.0]}, "origin must be [x, y, yaw]"),
        ({"origin": [0.0, "a", 0.0]}, "origin must be three finite numbers"),
        ({"negate": 2}, "negate must be 0 or 1, got 2"),
        ({"free_thresh": 0.7}, "0 <= free_thresh < occupied_thresh <= 1, got free_thresh 0.7, occupied_thresh 0.65"),
        ({"occupied_thresh": 1.5}, "0 <= free_thresh < occupied_thresh <= 1"),
        ({"free_thresh": -0.1}, "0 <= free_thresh < occupied_thresh <= 1"),
        ({"image": ""}, "image must be the path of a PGM/PNG file"),
        ({"image": "elsewhere.pgm"}, "image not found: "),
        ({"cost": 3}, "unknown key 'cost'; a map_server map allows free_thresh, image, mode, negate"),
    ],
)
def test_grid_errors_name_the_field(tmp_path, override, message):
    path = _write_grid(tmp_path, _room_image(), **override)
    with pytest.raises(MapError) as error:
        load_map(path)
    assert str(path) in str(error.value) and message in str(error.value)
    if "not found" in message:
        assert str(tmp_path / "elsewhere.pgm") in str(error.value)


def test_an_unreadable_image_is_named(tmp_path):
    path = _write_grid(tmp_path, _room_image())
    (tmp_path / "map.pgm").write_bytes(b"not an image at all")
    with pytest.raises(MapError, match=f"cannot read image {tmp_path / 'map.pgm'}"):
        load_map(path)


def test_grid_bounds(tmp_path, monkeypatch):
    # isolated occupied cells on a lattice: 35 x 35 squares of 4 vertices each, past the vertex bound
    lattice = np.full((70, 70), FREE, dtype=np.uint8)
    lattice[::2, ::2] = OCCUPIED
    with pytest.raises(MapError, match=f"the polygons of map.pgm: 4900 vertices in all, more than the bound of "
                                       f"{MAX_TOTAL_VERTICES}"):
        load_map(_write_grid(tmp_path, lattice))
    monkeypatch.setattr(maps, "MAX_GRID_CORNERS", 4899)
    with pytest.raises(MapError, match="too detailed: its obstacles have 4900 cell corners, more than 4899"):
        load_map(_write_grid(tmp_path, lattice))
    monkeypatch.setattr(maps, "MAX_GRID_CELLS", 70 * 70 - 1)
    with pytest.raises(MapError, match="is 70 x 70 cells, more than the bound of 4899 cells"):
        load_map(_write_grid(tmp_path, lattice))


def test_diagonal_and_staircase_outlines_stay_within_half_a_cell(tmp_path):
    """A filled triangle below a shallow diagonal: the simplified outline lies within half a cell of the cells'
    outline and is much shorter than it."""
    blocked = np.zeros((40, 40), dtype=bool)
    rows, columns = np.indices(blocked.shape)
    blocked[rows > 10 + columns // 4] = True
    (polygon,) = maps.occupancy_to_polygons(blocked, 1.0)
    cells = union_all([box(c, 39 - r, c + 1, 40 - r) for r, c in zip(*np.nonzero(blocked), strict=True)])
    assert Polygon(polygon).hausdorff_distance(cells) <= 0.5 + 1e-9
    assert len(polygon) < len(cells.exterior.coords) // 4
