"""Walls and humans hidden behind them in rendered frames (pixel checks at hand-computed positions)."""

from __future__ import annotations

import numpy as np

from socnav.viz.render import SceneFrame, SceneRenderer


def pixel(image: np.ndarray, x: float, y: float, extent: float) -> np.ndarray:
    height, width = image.shape[:2]
    return image[int((extent - y) / (2 * extent) * height), int((x + extent) / (2 * extent) * width)].astype(int)


def test_walls_are_drawn_and_hidden_humans_are_faded():
    extent = 5.0
    frame = SceneFrame(
        positions=np.array([[0.0, -4.0], [-2.0, -1.0], [2.0, -1.0]]), velocities=np.zeros((3, 2)),
        radii=np.full(3, 0.4), goals=np.array([[0.0, 4.0], [-2.0, -1.0], [2.0, -1.0]]),
        personal_space_radii=np.zeros(3), active=np.ones(3, dtype=bool), robot_heading=np.pi / 2,
        walls=[np.array([[-4.0, 2.0], [4.0, 2.0]]), np.array([[3.0, 3.0], [4.5, 3.0], [4.5, 4.5], [3.0, 4.5]])],
        hidden=np.array([False, True, False]),
    )
    image = SceneRenderer(width=400, height=400, extent=extent).render(frame)
    wall = np.array([0x4A, 0x4A, 0x4A])
    assert np.abs(pixel(image, 0.0, 2.0, extent) - wall).max() <= 20  # the wall segment
    assert np.abs(pixel(image, 3.75, 3.75, extent) - wall).max() <= 20  # inside the solid block
    assert np.abs(pixel(image, 0.0, 1.0, extent) - wall).max() > 100  # free space below the wall
    hidden, seen = pixel(image, -2.0, -1.0, extent), pixel(image, 2.0, -1.0, extent)
    assert hidden.sum() > seen.sum() + 150  # the hidden human is drawn faded (lighter)
    open_plane = SceneRenderer(width=400, height=400, extent=extent).render(
        SceneFrame(**{**frame.__dict__, "walls": None, "hidden": None}))
    assert np.abs(pixel(open_plane, 0.0, 2.0, extent) - wall).max() > 100  # no walls, none drawn
