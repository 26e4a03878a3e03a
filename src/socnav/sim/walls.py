"""The static walls of a world: the scenario's map, the config's `obstacles` and its `map` file, held once as RVO2
obstacles (for ORCA) and as segments (for sight lines, the range scan and the robot's wall collisions).

Every environment of a world shares one map, as a robot shares the map of the building it localises in.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from shapely.geometry import Polygon

from socnav.sim.geometry import (
    discs_clear,
    points_in_polygons,
    points_to_segments,
    polygon_segments,
    range_scan,
    robot_line_of_sight,
    swept_segment_hit,
)
from socnav.sim.maps import clearance_violation, load_map, validate_polygons
from socnav.sim.obstacles import ObstacleBatch, ObstacleMap

#: observation key of the robot's pose in the map frame (x, y, yaw), present when the world has walls
POSE_KEY = "pose"
#: observation key of the range scan, present with a `scan` setting
SCAN_KEY = "scan"


def world_polygons(config: Any, scenario: Any) -> list[np.ndarray]:
    """The polygons of a world: its scenario's map (map scenarios), then ``obstacles``, then the ``map`` file's."""
    polygons = list(scenario.static_map(config)) if hasattr(scenario, "static_map") else []
    polygons += validate_polygons(config.obstacles, name="obstacles") if config.obstacles else []
    if config.map is not None:
        polygons += load_map(config.map)
    return polygons


def has_walls(config: Any) -> bool:
    """Whether a world of this config has walls (a map scenario, ``obstacles`` or ``map``)."""
    from socnav.sim.scenarios import get_scenario

    return bool(getattr(get_scenario(config.scenario), "has_map", False) or config.obstacles or config.map)


class Walls:
    """The walls of E environments (one map shared by all), in the forms the world's kernels read."""

    def __init__(self, polygons: list[np.ndarray], n_envs: int):
        self.polygons = polygons
        self.obstacles = ObstacleBatch.from_maps([ObstacleMap.from_polygons(polygons)] * n_envs)
        self.seg_start, self.seg_end, self.n_segments = polygon_segments([polygons] * n_envs)
        # the edges of closed polygons (solid on their left, RVO2's orientation), in polygon_segments' order
        edge_sides = [np.full(len(vertices), len(vertices) >= 3) if len(vertices) >= 3 else np.zeros(1, dtype=bool)
                      for vertices in polygons]
        sides = np.concatenate(edge_sides) if edge_sides else np.zeros(0, dtype=bool)
        self.one_sided = np.zeros(self.seg_start.shape[:2], dtype=bool)
        self.one_sided[:, : len(sides)] = sides
        # The placement check's solid space (`maps.clearance_violation`'s rule, vectorised): a point belongs to the
        # smallest closed polygon containing it, solid if that one is counter-clockwise; a point in none is solid
        # when some clockwise polygon (a boundary agents stay inside) lies in no other polygon.
        closed = [np.asarray(vertices, dtype=np.float64) for vertices in polygons if len(vertices) >= 3]
        self._areas = [Polygon(vertices) for vertices in closed]
        self._area_sizes = np.array([area.area for area in self._areas], dtype=np.float64)
        self._closed_vertices = np.concatenate(closed) if closed else np.zeros((0, 2))
        self._closed_offsets = np.cumsum([0] + [len(vertices) for vertices in closed]).astype(np.int64)
        self._solid_inside = np.array([_counter_clockwise(vertices) for vertices in closed], dtype=bool)
        self._solid_outside = any(
            not solid and not any(other.contains(area) for other in self._areas if other is not area)
            for area, solid in zip(self._areas, self._solid_inside, strict=True))

    def _segments(self, n_envs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # the map is the same in every environment: the first n rows serve any n environments
        return self.seg_start[:n_envs], self.seg_end[:n_envs], self.n_segments[:n_envs]

    def in_sight_of_robot(self, positions: np.ndarray, active: np.ndarray) -> np.ndarray:
        """(E, N) bool: no wall crosses the line between the robot's centre (slot 0) and agent j's."""
        return robot_line_of_sight(positions, active, *self._segments(len(positions)), self.one_sided[: len(positions)])

    def robot_hit(self, before: np.ndarray, after: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """(E,) bool: the robot's disc, moving straight from `before` to `after` (E, 2), touched a wall."""
        return swept_segment_hit(before, after, radius, *self._segments(len(before)))

    def scan(self, origins: np.ndarray, headings: np.ndarray, beams: int, max_range: float,
             fov_deg: float, circles: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(E, beams) float32 ranges to the walls (and to the discs `circles`, `geometry.range_scan`'s), as a
        sensor_msgs/LaserScan from -fov/2 counter-clockwise."""
        fov = 2.0 * math.pi if fov_deg >= 360.0 else math.radians(fov_deg)
        ranges = range_scan(np.ascontiguousarray(origins), headings, *self._segments(len(origins)), beams, max_range,
                            fov, circles=circles, one_sided=self.one_sided[: len(origins)])
        return ranges.astype(np.float32)

    def misplaced(self, points: np.ndarray, radii: np.ndarray) -> str | None:
        """Why some disc (point (K, 2), radius (K,)) does not fit among the walls (inside an obstacle, outside an
        enclosing boundary, or closer than its radius), or None if every one fits (`maps.clearance_violation`'s
        rule; this vectorised pre-check calls it only for the discs that may not fit, to name the reason)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        if discs_clear(points, np.asarray(radii, dtype=np.float64), self.seg_start[0], self.seg_end[0],
                       int(self.n_segments[0]), self._closed_vertices, self._closed_offsets, self._area_sizes,
                       self._solid_inside, self._solid_outside):
            return None  # the common case, in one compiled call; otherwise find which disc and why
        distance = points_to_segments(points, self.seg_start[0], self.seg_end[0], int(self.n_segments[0]))
        suspect = distance < np.asarray(radii)
        solid = np.full(len(points), self._solid_outside)
        if self._areas:
            contains = points_in_polygons(points, self._closed_vertices, self._closed_offsets)
            innermost = np.argmin(np.where(contains, self._area_sizes, np.inf), axis=1)
            solid = np.where(contains.any(axis=1), self._solid_inside[innermost], solid)
        suspect |= solid
        for index in np.flatnonzero(suspect):
            reason = clearance_violation(self.polygons, points[index], float(radii[index]), name="walls")
            if reason is not None:
                return reason
        return None


def _counter_clockwise(vertices: np.ndarray) -> bool:
    x, y = vertices[:, 0], vertices[:, 1]
    return float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)) > 0.0
