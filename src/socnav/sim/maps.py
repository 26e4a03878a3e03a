"""Static maps: obstacle polygons validated and oriented in RVO2's convention, loaded from a polygon YAML or from a
ROS map_server occupancy grid (YAML + PGM/PNG image), and the clearance check of a start or goal against them.

Orientation (RVO2, `RVO::RVOSimulator::addObstacle`): the vertices of a solid obstacle run counter-clockwise, so its
inside lies to the left of every edge; a clockwise polygon is solid *outside*, i.e. it encloses free space (the walls
of a room agents stay inside); a two-vertex polygon is a single wall segment, blocking from both sides. Every polygon
this module returns is a float64 (k, 2) array of distinct consecutive vertices, without the closing repeat.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import shapely
import yaml
from PIL import Image, UnidentifiedImageError
from shapely.geometry import LinearRing, LineString, Point, Polygon
from shapely.geometry.polygon import orient
from shapely.validation import explain_validity

__all__ = [
    "MAX_COORDINATE",
    "MAX_GRID_CELLS",
    "MAX_GRID_CORNERS",
    "MAX_IMAGE_BYTES",
    "MAX_MAP_BYTES",
    "MAX_POLYGON_VERTICES",
    "MAX_TOTAL_VERTICES",
    "MapError",
    "clearance_violation",
    "is_counter_clockwise",
    "load_map",
    "occupancy_to_polygons",
    "orient_rvo2",
    "validate_polygons",
]

#: Bounds on a map's size: every obstacle edge is checked by the ORCA kernel, the line-of-sight and scan kernels of
#: every agent and beam at every step, so a map is kept to a few thousand edges.
MAX_POLYGON_VERTICES = 512
MAX_TOTAL_VERTICES = 4096
#: An occupancy grid larger than this (2048 x 2048 cells) is refused before it is read into polygons.
MAX_GRID_CELLS = 2048 * 2048
#: A grid whose occupied cells have more boundary corners than this is refused before the (slow) cell union: the
#: half-cell simplification removes the corners of shallow staircases, but not 16 times the vertex bound.
MAX_GRID_CORNERS = 16 * MAX_TOTAL_VERTICES
#: The largest map YAML read (refused from its size, before reading): a polygon map at `MAX_TOTAL_VERTICES` is
#: ~200 KB. Its YAML is also bounded in nesting and values (`socnav.io.safe_load_yaml`).
MAX_MAP_BYTES = 1 << 20
#: The largest occupancy-grid image file read (refused from its size, before PIL opens it): a 2048 x 2048 RGBA
#: image is 16 MB uncompressed. Its pixel count (`MAX_GRID_CELLS`) is read from the header before decoding.
MAX_IMAGE_BYTES = 64 << 20
#: Every wall vertex lies within this many metres of the map frame's origin in x and y (1000 km: a crowd scene is
#: tens of metres, a UTM-referenced building map would be re-centred first). Beyond it a coordinate is a mistake
#: or an attack, and its squares overflow the float32 kernels.
MAX_COORDINATE = 1e6

_GRID_KEYS = {"image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
_GRID_MODES = ("trinary", "scale")  # "raw" (pixel values are occupancy values) is refused
_POLYGON_KEYS = {"obstacles", "boundaries"}


class MapError(ValueError):
    """A map file or polygon list that cannot be used; the message names the file or polygon and the rule broken."""


# --------------------------------------------------------------------------------------------------------------------
# Polygon lists: validation and orientation
# --------------------------------------------------------------------------------------------------------------------
def validate_polygons(polygons: Sequence[Any], name: str = "obstacles") -> list[np.ndarray]:
    """Check a list of polygons and return them as float64 (k, 2) arrays (orientation kept: it carries meaning).

    Rules, each failure a `MapError` (a ValueError) naming ``{name}[i]`` and the rule: a polygon is a list of
    [x, y] vertices with finite coordinates within `MAX_COORDINATE` metres (in x and y); a closing vertex equal to
    the first is dropped; at least 2 vertices remain; no two consecutive vertices coincide (RVO2 divides by every
    edge's length); a polygon of 3 or more vertices is simple (shapely `LinearRing.is_simple`: no edge crosses or
    touches another) with non-zero area; at most `MAX_POLYGON_VERTICES` vertices per polygon and
    `MAX_TOTAL_VERTICES` in all. Polygons may overlap each other.
    The counts are checked first, from the lists' lengths, before any array is built.
    """
    if isinstance(polygons, (str, bytes)) or not isinstance(polygons, (Sequence, np.ndarray)):
        raise MapError(f"{name}: expected a list of polygons, got {type(polygons).__name__}")
    # Each polygon loses at most its closing repeat: more than this many written vertices is over the bound anyway.
    written = sum(len(polygon) for polygon in polygons if isinstance(polygon, (Sequence, np.ndarray))
                  and not isinstance(polygon, (str, bytes)))
    if written - len(polygons) > MAX_TOTAL_VERTICES:
        raise MapError(f"{name}: at least {written - len(polygons)} vertices in all, more than the bound of "
                       f"{MAX_TOTAL_VERTICES}")
    checked = []
    total = 0
    for index, polygon in enumerate(polygons):
        vertices = _polygon_vertices(polygon, f"{name}[{index}]")
        total += len(vertices)
        checked.append(vertices)
    if total > MAX_TOTAL_VERTICES:
        raise MapError(f"{name}: {total} vertices in all, more than the bound of {MAX_TOTAL_VERTICES}")
    return checked


def _polygon_vertices(polygon: Any, label: str) -> np.ndarray:
    """One polygon of `validate_polygons` as a float64 (k, 2) array, its closing repeat dropped, or a `MapError`
    naming `label` and the first rule it breaks (in the order the rules are listed there)."""
    try:
        vertices = np.array(polygon)
    except (TypeError, ValueError):  # ragged
        vertices = np.array(None)
    if vertices.dtype.kind not in "iuf" or vertices.ndim == 0:  # strings, None, booleans, ragged lists
        raise MapError(f"{label}: expected a list of [x, y] vertices of numbers, got {polygon!r}")
    vertices = vertices.astype(np.float64)
    if vertices.size == 0:
        vertices = vertices.reshape(0, 2)
    if vertices.ndim != 2 or vertices.shape[1] != 2:
        raise MapError(f"{label}: expected a list of [x, y] vertices, got an array of shape {vertices.shape}")
    if len(vertices) > MAX_POLYGON_VERTICES + 1:  # before any geometry (a closing repeat may still be dropped)
        raise MapError(
            f"{label}: {len(vertices)} vertices, more than the bound of {MAX_POLYGON_VERTICES} per polygon")
    if not np.isfinite(vertices).all():
        raise MapError(f"{label}: non-finite coordinate (every x and y must be a finite number)")
    far = np.abs(vertices) > MAX_COORDINATE
    if far.any():
        index, axis = (int(i) for i in np.argwhere(far)[0])
        raise MapError(f"{label}: vertex {index} has {'xy'[axis]} = {vertices[index, axis]:g} m, beyond the bound of "
                       f"{MAX_COORDINATE:g} m from the origin")
    if len(vertices) >= 3 and np.array_equal(vertices[0], vertices[-1]):
        vertices = vertices[:-1]  # a closed ring written with its first vertex repeated
    if len(vertices) < 2:
        raise MapError(f"{label}: a polygon needs at least 2 vertices (2 make a wall segment), got {len(vertices)}")
    if len(vertices) > MAX_POLYGON_VERTICES:
        raise MapError(
            f"{label}: {len(vertices)} vertices, more than the bound of {MAX_POLYGON_VERTICES} per polygon")
    following = np.roll(vertices, -1, axis=0) if len(vertices) > 2 else vertices[1:]
    edges = vertices[: len(following)]
    repeated = np.flatnonzero((edges == following).all(axis=1))
    if repeated.size:
        raise MapError(f"{label}: zero-length edge at vertex {int(repeated[0])} (consecutive vertices coincide)")
    if len(vertices) >= 3:
        offsets = vertices[1:] - vertices[0]
        if np.all(offsets[0, 0] * offsets[:, 1] - offsets[0, 1] * offsets[:, 0] == 0.0):
            raise MapError(f"{label}: zero-area polygon (all vertices on one line; use 2 vertices for a wall)")
        if not LinearRing(vertices).is_simple:
            reason = explain_validity(Polygon(vertices))
            raise MapError(f"{label}: self-intersecting polygon ({reason})")
    return vertices


def is_counter_clockwise(vertices: np.ndarray) -> bool:
    """True when the closed polygon through `vertices` (3 or more) runs counter-clockwise, i.e. is solid in RVO2."""
    return bool(LinearRing(vertices).is_ccw)


def orient_rvo2(vertices: np.ndarray, solid: bool) -> np.ndarray:
    """The polygon with its vertices ordered for RVO2: counter-clockwise when `solid` (agents stay outside),
    clockwise when it encloses free space (agents stay inside). A two-vertex wall is returned unchanged."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if len(vertices) < 3:
        return vertices.copy()
    oriented = orient(Polygon(vertices), sign=1.0 if solid else -1.0)  # sign 1: exterior counter-clockwise
    return np.asarray(oriented.exterior.coords, dtype=np.float64)[:-1]


# --------------------------------------------------------------------------------------------------------------------
# Clearance of a start or goal
# --------------------------------------------------------------------------------------------------------------------
def clearance_violation(
    polygons: Sequence[np.ndarray], point: Sequence[float], radius: float, name: str = "obstacles"
) -> str | None:
    """Why a disc of `radius` centred at `point` does not fit among `polygons` (RVO2 orientation), or None if it fits.

    It does not fit when its centre is in solid space or closer than `radius` to any edge; touching (distance ==
    radius) fits, as in the world, where only a negative gap is a collision. Solid space, read from the orientation
    as nested rings: a point belongs to the smallest polygon of 3 or more vertices containing it, solid if that one
    is counter-clockwise (an obstacle, or the outline of a wall block), free if clockwise (a room, possibly inside
    walls, as `occupancy_to_polygons` makes them). A point in no polygon is free, unless a clockwise polygon lies in
    no other polygon (outer walls drawn on their own, the ``boundaries`` of a polygon map): outside those is solid.
    """
    centre = Point(float(point[0]), float(point[1]))
    areas = {index: Polygon(vertices) for index, vertices in enumerate(polygons) if len(vertices) >= 3}
    containing = [index for index, area in areas.items() if area.contains(centre)]
    where = f"({centre.x:g}, {centre.y:g})"
    if containing:
        innermost = min(containing, key=lambda index: areas[index].area)
        if is_counter_clockwise(polygons[innermost]):
            return f"{where} is inside the obstacle {name}[{innermost}]"
    else:
        for index, area in areas.items():
            top_level = not any(other.contains(area) for key, other in areas.items() if key != index)
            if not is_counter_clockwise(polygons[index]) and top_level:
                return f"{where} is outside the free space enclosed by {name}[{index}]"
    for index, vertices in enumerate(polygons):
        outline = areas[index].exterior if index in areas else LineString(vertices)
        distance = outline.distance(centre)
        if distance < radius:
            return f"{where} is {distance:.3g} m from {name}[{index}], closer than the radius {radius:g} m"
    return None


# --------------------------------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------------------------------
def load_map(path: str | Path) -> list[np.ndarray]:
    """Load a map's obstacle polygons, in metres, oriented for RVO2 (see the module docstring), validated.

    Two YAML formats, told apart by their keys (any other key is an error):

    * Polygons::

          obstacles:            # solid obstacles, each a list of [x, y] vertices (any orientation; returned
            - [[0, 0], [1, 0], [1, 1], [0, 1]]      #   counter-clockwise); 2 vertices make a wall segment
            - [[3, -1], [3, 2]]
          boundaries:           # optional: polygons enclosing free space, agents stay inside (returned clockwise)
            - [[-5, -5], [5, -5], [5, 5], [-5, 5]]

      A polygon may be closed by repeating its first vertex; the repeat is dropped. The returned list holds the
      obstacles, then the boundaries, in file order.

    * A ROS map_server occupancy grid: keys ``image`` (path of a PGM/PNG, relative to the YAML's folder),
      ``resolution`` (m/cell), ``origin`` ([x, y, yaw]: pose of the lower-left pixel), ``negate`` (0/1),
      ``occupied_thresh``, ``free_thresh`` and optional ``mode`` (``trinary``, the default, or ``scale``). As in
      map_server, a pixel's occupancy is p = (255 - v) / 255 (v / 255 with negate), v the mean of its colour channels
      (an alpha channel is ignored); it is free when p < free_thresh. Every other cell -- occupied (p >
      occupied_thresh) or unknown, and in ``scale`` mode partly occupied -- is an obstacle, so agents keep to cells
      known to be free. ``raw`` mode is refused. See `occupancy_to_polygons` for the conversion; the area outside the
      image is free.

    The map YAML is bounded before it is parsed (`MAX_MAP_BYTES` from the file's size, then nesting and values as
    `socnav.io.safe_load_yaml` bounds them), the image before it is decoded (`MAX_IMAGE_BYTES` from the file's
    size, `MAX_GRID_CELLS` from its header); see docs/limits.md.
    """
    from socnav.io import UntrustedInputError, file_size_problem, read_bounded, safe_load_yaml, yaml_problem

    path = Path(path)
    if not path.is_file():
        raise MapError(f"map file not found: {path}")
    too_large = file_size_problem(path, MAX_MAP_BYTES)
    if too_large:
        raise MapError(f"{path}: the map YAML {too_large}")
    try:
        document = safe_load_yaml(read_bounded(path, MAX_MAP_BYTES).decode())
    except UntrustedInputError as error:
        raise MapError(f"{path}: cannot read the map YAML ({error})") from None
    except (OSError, UnicodeDecodeError) as error:
        raise MapError(f"{path}: cannot read the map YAML ({' '.join(str(error).split())})") from None
    except yaml.YAMLError as error:
        raise MapError(f"{path}: cannot read the map YAML: it {' '.join(yaml_problem(error).split())}") from None
    except ValueError as error:  # a value YAML parses but Python will not build (an integer of 5,000 digits)
        raise MapError(f"{path}: cannot read the map YAML ({' '.join(str(error).split())[:200]})") from None
    if not isinstance(document, dict):
        raise MapError(f"{path}: expected a mapping with 'obstacles' or map_server keys ('image', ...)")
    if "image" in document:
        return _load_occupancy_grid(path, document)
    if "obstacles" in document:
        return _load_polygon_map(path, document)
    raise MapError(
        f"{path}: neither a polygon map (key 'obstacles') nor a map_server map (keys {', '.join(sorted(_GRID_KEYS))})"
    )


def _load_polygon_map(path: Path, document: dict) -> list[np.ndarray]:
    unknown = sorted(set(document) - _POLYGON_KEYS, key=str)
    if unknown:
        raise MapError(f"{path}: unknown key {unknown[0]!r}; a polygon map allows {', '.join(sorted(_POLYGON_KEYS))}")
    obstacles = validate_polygons(document["obstacles"] or [], name=f"{path}: obstacles")
    boundaries = validate_polygons(document.get("boundaries") or [], name=f"{path}: boundaries")
    polygons = [orient_rvo2(vertices, solid=True) for vertices in obstacles]
    polygons += [orient_rvo2(vertices, solid=False) for vertices in boundaries]
    total = sum(len(vertices) for vertices in polygons)
    if total > MAX_TOTAL_VERTICES:
        raise MapError(f"{path}: {total} vertices in obstacles and boundaries, more than the bound of "
                       f"{MAX_TOTAL_VERTICES}")
    return polygons


def _number(path: Path, document: dict, key: str) -> float:
    value = document[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MapError(f"{path}: {key} must be a finite number, got {value!r}")
    return float(value)


def _load_occupancy_grid(path: Path, document: dict) -> list[np.ndarray]:
    missing = sorted(_GRID_KEYS - set(document))
    if missing:
        raise MapError(f"{path}: missing map_server key(s) {', '.join(missing)}")
    unknown = sorted(set(document) - _GRID_KEYS - {"mode"}, key=str)
    if unknown:
        raise MapError(f"{path}: unknown key {unknown[0]!r}; a map_server map allows "
                       f"{', '.join(sorted(_GRID_KEYS | {'mode'}))}")
    mode = document.get("mode", "trinary")
    if mode not in _GRID_MODES:
        raise MapError(f"{path}: mode must be one of {', '.join(_GRID_MODES)} ('raw' is not supported), got {mode!r}")
    resolution = _number(path, document, "resolution")
    if resolution <= 0.0:
        raise MapError(f"{path}: resolution must be > 0 (metres per cell), got {resolution:g}")
    origin = document["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise MapError(f"{path}: origin must be [x, y, yaw], got {origin!r}")
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in origin):
        raise MapError(f"{path}: origin must be three finite numbers [x, y, yaw], got {origin!r}")
    negate = document["negate"]
    if negate not in (0, 1):  # also True/False
        raise MapError(f"{path}: negate must be 0 or 1, got {negate!r}")
    occupied_thresh = _number(path, document, "occupied_thresh")
    free_thresh = _number(path, document, "free_thresh")
    if not 0.0 <= free_thresh < occupied_thresh <= 1.0:
        raise MapError(f"{path}: thresholds must satisfy 0 <= free_thresh < occupied_thresh <= 1, got free_thresh "
                       f"{free_thresh:g}, occupied_thresh {occupied_thresh:g}")
    image = document["image"]
    if not isinstance(image, str) or not image:
        raise MapError(f"{path}: image must be the path of a PGM/PNG file, got {image!r}")
    image_path = (path.parent / image).resolve()
    pixels = _read_image(path, image_path)
    occupancy = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
    blocked = ~(occupancy < free_thresh)  # occupied, unknown, or (scale mode) partly occupied
    polygons = occupancy_to_polygons(blocked, resolution, (float(origin[0]), float(origin[1])), float(origin[2]))
    return validate_polygons(polygons, name=f"{path}: the polygons of {image}")


def _read_image(path: Path, image_path: Path) -> np.ndarray:
    """The image's pixel values as float64 (rows top to bottom), colour channels averaged as map_server does.

    Bounded before decoding: the file's size (`MAX_IMAGE_BYTES`), then its width x height from the header
    (`MAX_GRID_CELLS`); PIL's own decompression-bomb check (far above ours) is reported the same way.
    """
    from socnav.io import file_size_problem

    if not image_path.is_file():
        raise MapError(f"{path}: image not found: {image_path}")
    too_large = file_size_problem(image_path, MAX_IMAGE_BYTES)
    if too_large:
        raise MapError(f"{path}: image {image_path} {too_large}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our bound is far lower, checked below
            opened = Image.open(image_path)
    except Image.DecompressionBombError as error:  # declared over 2 x PIL's MAX_IMAGE_PIXELS
        declared = re.search(r"\((\d+) pixels\)", str(error))
        cells = f"{int(declared.group(1)):,} cells" if declared else "too many cells"
        raise MapError(f"{path}: image {image_path} is {cells}, more than the bound of {MAX_GRID_CELLS} cells; crop "
                       "it or use a coarser resolution") from None
    except (OSError, UnidentifiedImageError, ValueError) as error:
        raise MapError(f"{path}: cannot read image {image_path} ({error})") from None
    try:
        with opened:
            width, height = opened.size
            if width * height <= MAX_GRID_CELLS:
                image: Image.Image = opened
                if image.mode not in ("L", "LA", "RGB", "RGBA"):
                    image = image.convert("RGBA" if "A" in image.getbands() else "RGB")
                pixels = np.asarray(image, dtype=np.float64)
    except (OSError, UnidentifiedImageError, ValueError) as error:
        raise MapError(f"{path}: cannot read image {image_path} ({error})") from None
    if width * height > MAX_GRID_CELLS:
        raise MapError(f"{path}: image {image_path} is {width} x {height} cells, more than the bound of "
                       f"{MAX_GRID_CELLS} cells; crop it or use a coarser resolution")
    if pixels.ndim == 3:
        channels = pixels.shape[2] - 1 if pixels.shape[2] in (2, 4) else pixels.shape[2]  # without alpha
        pixels = pixels[:, :, :channels].mean(axis=2)
    return pixels


def occupancy_to_polygons(
    blocked: np.ndarray, resolution: float, origin: tuple[float, float] = (0.0, 0.0), yaw: float = 0.0
) -> list[np.ndarray]:
    """Polygons, in metres in the map frame, covering the blocked cells of an image-ordered grid (row 0 at the top).

    Cell (row r, column c) of an H-row image covers [c, c+1] x [H-1-r, H-r] in cells (map_server flips the image's y
    axis: row H-1 is the bottom), scaled by `resolution`, rotated by `yaw` about the origin and shifted by `origin`.
    The blocked cells are merged with shapely (`union_all` of one box per run of blocked cells), each piece simplified
    with `simplify(resolution / 2, preserve_topology=True)`, so every vertex lies within half a cell of the cells'
    outline. A piece's outline becomes a counter-clockwise (solid) polygon, each of its holes -- free space enclosed
    by blocked cells, such as a walled room -- a clockwise one agents stay inside of (RVO2). Raises `MapError` when
    the grid is too detailed (`MAX_GRID_CORNERS`); the caller checks the vertex bounds.
    """
    blocked = np.asarray(blocked, dtype=bool)
    height = blocked.shape[0]
    corners = _count_corners(blocked)
    if corners > MAX_GRID_CORNERS:
        raise MapError(f"the occupancy grid is too detailed: its obstacles have {corners} cell corners, more than "
                       f"{MAX_GRID_CORNERS}; use a coarser resolution or a cleaner map")
    x0, y0, x1, y1 = _cell_rectangles(blocked)
    if len(x0) == 0:
        return []
    rectangles = shapely.box(x0, height - y1, x1, height - y0)  # y from the bottom row up
    merged = shapely.union_all(rectangles).simplify(0.5, preserve_topology=True)  # in cells: half a cell
    pieces = list(merged.geoms) if hasattr(merged, "geoms") else [merged]
    cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[cos_yaw, -sin_yaw], [sin_yaw, cos_yaw]]) * resolution

    def to_map(ring) -> np.ndarray:
        return np.asarray(ring.coords, dtype=np.float64)[:-1] @ rotation.T + np.asarray(origin, dtype=np.float64)

    polygons = []
    for piece in pieces:
        piece = orient(piece, sign=1.0)  # exterior counter-clockwise, holes clockwise: RVO2's convention
        polygons.append(to_map(piece.exterior))
        polygons.extend(to_map(hole) for hole in piece.interiors)
    return polygons


def _count_corners(blocked: np.ndarray) -> int:
    """Corners of the blocked cells' outline: 2 x 2 windows holding 1 or 3 blocked cells, or 2 diagonal ones (2
    corners)."""
    padded = np.pad(blocked, 1).astype(np.int8)
    a, b, c, d = padded[:-1, :-1], padded[:-1, 1:], padded[1:, :-1], padded[1:, 1:]
    count = a + b + c + d
    diagonal = (count == 2) & (a == d)
    return int(np.count_nonzero((count == 1) | (count == 3)) + 2 * np.count_nonzero(diagonal))


def _cell_rectangles(blocked: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rectangles (x0, row0, x1, row1), in cells with rows downwards, covering the blocked cells: each row's runs of
    blocked cells, a run extended downwards while the next row has the same run (fewer boxes for the union)."""
    rectangles = []
    open_runs: dict[tuple[int, int], int] = {}  # (first column, end column) -> first row
    for row in range(blocked.shape[0] + 1):
        runs = set()
        if row < blocked.shape[0]:
            edges = np.diff(np.concatenate(([0], blocked[row].astype(np.int8), [0])))
            runs = set(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))
        for run in [run for run in open_runs if run not in runs]:
            rectangles.append((run[0], open_runs.pop(run), run[1], row))
        for run in runs:
            open_runs.setdefault(run, row)
    columns = np.asarray(rectangles, dtype=np.float64).reshape(-1, 4).T
    return columns[0], columns[1], columns[2], columns[3]
