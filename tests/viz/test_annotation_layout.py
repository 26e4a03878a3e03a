"""Annotated frames of the map scenarios (what `socnav animate` draws): the title, the time, the caption, the metre
scale and the outcome lie outside the scene -- none of their boxes overlaps a wall's box, the scene, or another
annotation -- and all of them lie inside the image. Boxes are matplotlib's own (`get_window_extent` with the
renderer's canvas), in pixels."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.transforms import Bbox

import socnav
from socnav.cli.workflows.animation import BARS, episode_title
from socnav.envs.env import scene_extent
from socnav.sim.map_scenarios import Corridor, Doorway, Intersection, Room
from socnav.viz.render import SceneRenderer

MAP_SCENARIOS = [Corridor().name, Doorway().name, Intersection().name, Room().name]
#: the longest caption `animate` writes (a safety layer, the fallback driving)
CAPTION = "step 120 (30.00 s); nearest human 12.3 m away; SAFETY FALLBACK DRIVES (uncertain and close)"


def wall_boxes(renderer: SceneRenderer, walls: list[np.ndarray]) -> list[Bbox]:
    """Each wall's box in pixels: its polygon's vertices through the scene's transform, widened by the drawn line's
    half width (3 pt)."""
    half = 1.5 * renderer.dpi / 72
    boxes = []
    for polygon in walls:
        points = renderer.ax.transData.transform(np.asarray(polygon, dtype=float))
        boxes.append(Bbox([points.min(axis=0) - half, points.max(axis=0) + half]))
    return boxes


def render_map_frame(scenario: str, **frame: object) -> tuple[SceneRenderer, list[np.ndarray]]:
    """An annotated frame of `scenario`'s first episode, as `animate_episode` renders it (720 x 480, the scenario's
    extent), with the longest title and caption, the uncertainty bars and the outcome."""
    env = socnav.make_env({"scenario": scenario})
    env.reset(seed=0)
    config = env.unwrapped.config
    renderer = SceneRenderer(width=720, height=480, extent=scene_extent(config), annotate=True,
                             fallback_color="#f4a261")
    scene = env.unwrapped.scene_frame(title=episode_title(config, "pretrained", 12, "calibrated"), caption=CAPTION,
                                      side_panel=dict.fromkeys(BARS, 0.5), panel_title="uncertainty", **frame)
    renderer.render(scene)
    env.close()
    assert scene.walls, f"{scenario} has walls"
    return renderer, [np.asarray(wall) for wall in scene.walls]


@pytest.mark.parametrize("scenario", MAP_SCENARIOS)
@pytest.mark.parametrize("outcome", ["", "GOAL REACHED"])
def test_annotations_lie_outside_the_walls_and_the_scene(scenario, outcome):
    renderer, walls = render_map_frame(scenario, outcome=outcome)
    canvas = renderer.canvas.get_renderer()
    texts = renderer.annotation_texts()
    names = {id(text): repr(text.get_text()[:30]) for text in texts}
    expected = 4 if outcome else 3  # title, caption, metre scale (+ outcome)
    assert len(texts) == expected, [names[id(text)] for text in texts]
    boxes = {id(text): text.get_window_extent(canvas) for text in texts}
    boxes[id(renderer.scale_bar)] = renderer.scale_bar.get_window_extent(canvas)
    names[id(renderer.scale_bar)] = "the metre scale's bar"
    image = Bbox([[0, 0], [renderer.width, renderer.height]])
    scene = renderer.ax.get_window_extent(canvas)
    for key, box in boxes.items():
        for index, wall in enumerate(wall_boxes(renderer, walls)):
            assert not box.overlaps(wall), f"{scenario}: {names[key]} {box} overlaps wall {index} {wall}"
        assert not box.overlaps(scene), f"{scenario}: {names[key]} {box} lies on the scene {scene}"
        assert image.containsx(box.x0) and image.containsx(box.x1), f"{names[key]} leaves the image: {box}"
        assert image.containsy(box.y0) and image.containsy(box.y1), f"{names[key]} leaves the image: {box}"
        for other, other_box in boxes.items():
            assert key == other or not box.overlaps(other_box), f"{names[key]} overlaps {names[other]}"
    # nor does the side column (legend, bars) cover the scene
    for axes in (renderer.legend_ax, renderer.panel_ax):
        assert not axes.get_tightbbox(canvas).overlaps(scene)
    renderer.close()


@pytest.mark.parametrize("scenario", MAP_SCENARIOS)
def test_the_walls_lie_inside_the_scene(scenario):
    # the check above means something only if the scene holds the map: every wall is drawn inside it
    renderer, walls = render_map_frame(scenario)
    scene = renderer.ax.get_window_extent(renderer.canvas.get_renderer())
    for wall in wall_boxes(renderer, walls):
        assert scene.x0 - 2 <= wall.x0 and wall.x1 <= scene.x1 + 2 and scene.y0 - 2 <= wall.y0
        assert wall.y1 <= scene.y1 + 2
    renderer.close()


@pytest.mark.parametrize("scenario", MAP_SCENARIOS)
def test_the_clock_of_a_plain_frame_lies_off_the_walls(scenario):
    """`env.render` (and so Gymnasium's RecordVideo) draws the clock in the scene's top-left corner; the scenario's
    extent leaves a band above the walls for it (`clock_clear_extent`), so its box -- text and padding -- overlaps
    no wall's box, at any time of the episode, and the frame keeps the documented pixel mapping (the scene fills
    the image) with every wall inside it."""
    import dataclasses

    env = socnav.make_env({"scenario": scenario}, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.action_space.sample())
    image = env.render()
    renderer = env.unwrapped._renderer
    assert image.shape == (renderer.height, renderer.width, 3)
    assert renderer.scene_box() == (0.0, 0.0, renderer.width, renderer.height)
    assert renderer.extent == scene_extent(env.unwrapped.config)
    frame = env.unwrapped.scene_frame()
    walls = [np.asarray(wall) for wall in frame.walls]
    canvas = renderer.canvas.get_renderer()
    pixels = Bbox([[0, 0], [renderer.width, renderer.height]])
    for time in (frame.time, 999.9):  # the widest clock an episode shows
        renderer.render(dataclasses.replace(frame, time=time))
        clock = renderer.time_text
        assert clock.get_visible() and clock.get_text().startswith("t = ")
        box = Bbox.union([clock.get_window_extent(canvas), clock.get_bbox_patch().get_window_extent(canvas)])
        assert pixels.containsx(box.x0) and pixels.containsx(box.x1), box
        assert pixels.containsy(box.y0) and pixels.containsy(box.y1), box
        for index, wall in enumerate(wall_boxes(renderer, walls)):
            assert not box.overlaps(wall), f"{scenario}: the clock {box} overlaps wall {index} {wall}"
    for wall in wall_boxes(renderer, walls):  # the map is still shown whole
        assert wall.x0 >= -2 and wall.x1 <= renderer.width + 2 and wall.y0 >= -2 and wall.y1 <= renderer.height + 2
    env.close()
