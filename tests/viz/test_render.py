"""Behavioural tests of socnav.viz: pixels land where the geometry says, files are written safely.
Pixel positions are computed by hand from extent / width, independently of matplotlib transforms."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from _extras import require
from matplotlib.colors import to_rgb

from socnav.viz import HumanViewer, SceneFrame, SceneRenderer, save_animation
from socnav.viz import animation as anim
from socnav.viz.render import HUMAN_COLOR, ROBOT_COLOR

W = H = 480
EXTENT = 8.5


def to_pixel(x: float, y: float, width: int = W, extent: float = EXTENT) -> tuple[int, int]:
    """(row, col) of scene point (x, y) for a square image without side panel."""
    scale = width / (2 * extent)
    return int((extent - y) * scale), int((x + extent) * scale)


def color_fraction(img: np.ndarray, rc: tuple[int, int], color: str, half: int = 3, tol: int = 12) -> float:
    """Fraction of pixels in a (2*half+1)^2 window around rc whose colour is within tol of `color`."""
    r, c = rc
    window = img[r - half : r + half + 1, c - half : c + half + 1].astype(int)
    target = np.round(np.array(to_rgb(color)) * 255).astype(int)
    return float((np.abs(window - target).max(axis=-1) <= tol).mean())


def make_frame(robot_xy=(0.0, 0.0), n_humans: int = 3, **kw) -> SceneFrame:
    """Robot at robot_xy heading +y, humans on a ring of radius 5 m."""
    ang = np.linspace(0, 2 * np.pi, n_humans, endpoint=False)
    humans = 5.0 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    pos = np.vstack([robot_xy, humans])
    n = len(pos)
    defaults = {
        "positions": pos,
        "velocities": np.zeros((n, 2)),
        "radii": np.full(n, 0.3),
        "goals": np.vstack([[6.0, 6.0], -humans]),
        "personal_space_radii": np.r_[0.0, np.full(n - 1, 0.5)],
        "active": np.ones(n, dtype=bool),
        "robot_heading": np.pi / 2,
    }
    return SceneFrame(**{**defaults, **kw})


@pytest.fixture(scope="module")
def renderer():
    r = SceneRenderer(width=W, height=H, extent=EXTENT)
    yield r
    r.close()


def test_shape_dtype_constant(renderer):
    frames = [
        renderer.render(make_frame((0.0, 0.0))),
        renderer.render(make_frame((2.0, 1.0), n_humans=7, time=3.5, caption="step 14")),
        renderer.render(make_frame((-1.0, 0.0), trails=np.random.default_rng(0).normal(size=(10, 4, 2)))),
    ]
    for img in frames:
        assert img.shape == (H, W, 3) and img.dtype == np.uint8
    assert not np.array_equal(frames[0], frames[1])
    assert SceneRenderer(width=320, height=240).render(make_frame()).shape == (240, 320, 3)


def test_robot_drawn_at_projected_position_and_moves(renderer):
    a, b = (0.0, 0.0), (3.0, -2.0)
    img_a = renderer.render(make_frame(a))
    img_b = renderer.render(make_frame(b))
    assert to_pixel(*b) == (296, 324)  # hand computation: 480 / 17 px per metre
    assert color_fraction(img_a, to_pixel(*a), ROBOT_COLOR) > 0.5
    assert color_fraction(img_b, to_pixel(*b), ROBOT_COLOR) > 0.5
    assert color_fraction(img_b, to_pixel(*a), ROBOT_COLOR) == 0.0
    assert color_fraction(img_a, to_pixel(*b), ROBOT_COLOR) == 0.0


def test_humans_drawn_and_inactive_slots_hidden(renderer):
    frame = make_frame(n_humans=4, trails=np.zeros((5, 5, 2)) + np.linspace(0, 1, 5)[:, None, None])
    human_px = to_pixel(*frame.positions[1])
    img_all = renderer.render(frame)
    assert color_fraction(img_all, human_px, HUMAN_COLOR) > 0.5

    frame.active = np.array([True, False, True, True, True])
    img_inactive = renderer.render(frame)
    assert color_fraction(img_inactive, human_px, HUMAN_COLOR) == 0.0
    # Identical to a scene where that slot does not exist at all (no disc, ring, goal, trail).
    keep = [0, 2, 3, 4]
    without = make_frame(
        positions=frame.positions[keep], velocities=frame.velocities[keep], radii=frame.radii[keep],
        goals=frame.goals[keep], personal_space_radii=frame.personal_space_radii[keep],
        active=np.ones(4, dtype=bool), trails=frame.trails[:, keep],
    )  # fmt: skip
    np.testing.assert_array_equal(img_inactive, renderer.render(without))


def test_robot_color_override(renderer):
    override = "#00c800"
    img = renderer.render(make_frame((1.0, 1.0), robot_color=override))
    assert color_fraction(img, to_pixel(1.0, 1.0), override) > 0.5
    assert color_fraction(img, to_pixel(1.0, 1.0), ROBOT_COLOR) == 0.0


def test_side_panel_keeps_shape_and_shows_bars(renderer):
    plain = renderer.render(make_frame())
    low = renderer.render(make_frame(side_panel={"epistemic": 0.0, "aleatoric": 0.2}))
    high = renderer.render(make_frame(side_panel={"epistemic": 1.0, "aleatoric": 0.2}))
    more = renderer.render(make_frame(side_panel={"a": 0.1, "b": 0.5, "c": 0.9}))
    assert plain.shape == low.shape == high.shape == more.shape == (H, W, 3)
    panel_cols = slice(int(0.72 * W), W)
    assert not np.array_equal(low[:, panel_cols], high[:, panel_cols])  # bar length follows the value
    # Scene squeezed into the left 70 %: 17 m over 0.7 * 480 px, centred vertically.
    scene_w = 0.7 * W
    assert color_fraction(low, (H // 2, int(scene_w / 2)), ROBOT_COLOR) > 0.5
    # Back to no panel: the full-width layout is restored exactly.
    np.testing.assert_array_equal(renderer.render(make_frame()), plain)


def _distinct_frames(n: int, size: int = 64) -> list[np.ndarray]:
    return [np.full((size, size, 3), 40 * (i + 1), dtype=np.uint8) for i in range(n)]


def test_gif_round_trip_and_no_temp_files(tmp_path):
    path = save_animation(_distinct_frames(3), tmp_path / "sub" / "episode.gif", fps=5)
    assert path == tmp_path / "sub" / "episode.gif"
    frames = iio.imread(path, index=None)
    assert frames.shape == (3, 64, 64, 3)
    assert [p.name for p in path.parent.iterdir()] == ["episode.gif"]


def test_rendered_frames_to_gif(tmp_path, renderer):
    frames = [renderer.render(make_frame((x, 0.0), time=x)) for x in (0.0, 1.0, 2.0)]
    read = iio.imread(save_animation(frames, tmp_path / "scene.gif"), index=None)
    assert read.shape == (3, H, W, 3)


def test_interrupted_write_leaves_old_file_and_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "out.gif"
    path.write_bytes(b"previous")

    def broken_writer(tmp: Path, frames, fps):
        tmp.write_bytes(b"half a gif")
        raise KeyboardInterrupt

    monkeypatch.setattr(anim, "_write_gif", broken_writer)
    with pytest.raises(KeyboardInterrupt):
        save_animation(_distinct_frames(2), path)
    assert path.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["out.gif"]


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match=r"\.gif.*\.mp4"):
        save_animation(_distinct_frames(2), tmp_path / "out.avi")
    with pytest.raises(ValueError, match="at least one frame"):
        save_animation([], tmp_path / "out.gif")
    with pytest.raises(ValueError, match="same shape"):
        save_animation([np.zeros((8, 8, 3), np.uint8), np.zeros((9, 8, 3), np.uint8)], tmp_path / "out.gif")
    assert list(tmp_path.iterdir()) == []


def test_mp4_without_ffmpeg_says_what_to_install(tmp_path, monkeypatch):
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(anim.importlib.util, "find_spec",
                        lambda name, *a: None if name == "imageio_ffmpeg" else real_find_spec(name, *a))
    with pytest.raises(ImportError, match=r"\[video\]"):
        save_animation(_distinct_frames(2), tmp_path / "out.mp4")


def test_mp4_round_trip(tmp_path):
    imageio_ffmpeg = require("imageio_ffmpeg")
    path = save_animation(_distinct_frames(4, size=48), tmp_path / "out.mp4", fps=4)
    n_frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(path))
    assert n_frames == 4 and seconds == pytest.approx(1.0)
    assert [p.name for p in tmp_path.iterdir()] == ["out.mp4"]


def test_human_viewer_shows_each_frame_pixel_for_pixel_headless(monkeypatch):
    import matplotlib
    import matplotlib.pyplot as plt

    monkeypatch.setitem(matplotlib.rcParams, "backend", "Agg")  # never open a window in tests
    # Distinct pixels everywhere (not flat colours), so a shifted, scaled or stale picture would show.
    frames = [np.random.default_rng(seed).integers(0, 256, (48, 64, 3), dtype=np.uint8) for seed in range(2)]
    viewer = HumanViewer(title="socnav test viewer")
    windows = []
    for frame in frames:
        viewer.show(frame)
        assert plt.get_figlabels().count("socnav test viewer") == 1
        figure = plt.figure("socnav test viewer")  # the viewer's window, looked up by its title
        figure.canvas.draw()
        shown = np.asarray(figure.canvas.buffer_rgba())[..., :3]
        np.testing.assert_array_equal(shown, frame)  # the whole window is the frame, at its own size
        windows.append(figure.number)
    assert windows[0] == windows[1], "later frames update the same window"
    viewer.close()
    assert not plt.fignum_exists(windows[0]) and "socnav test viewer" not in plt.get_figlabels()
    viewer.close()  # idempotent
    viewer.show(frames[0])  # a closed viewer opens a new window on the next frame
    assert "socnav test viewer" in plt.get_figlabels()
    viewer.close()
    assert "socnav test viewer" not in plt.get_figlabels()


def test_the_planned_path_and_its_subgoal_are_drawn(renderer):
    """A route (dashed line) and a subgoal (diamond) in the route colour where the geometry puts them, nothing of
    them without."""
    from socnav.viz.render import ROUTE_COLOR

    route = np.array([[-6.0, -6.0], [-6.0, 6.0], [-2.0, 6.0]])
    subgoal = np.array([-6.0, -3.0])
    plain = renderer.render(make_frame())
    drawn = renderer.render(make_frame(route=route, subgoal=subgoal))
    assert color_fraction(drawn, to_pixel(*subgoal), ROUTE_COLOR, half=1) > 0.5
    assert color_fraction(drawn, to_pixel(-4.0, 6.0), ROUTE_COLOR, half=4) > 0.0  # on the last leg
    assert color_fraction(plain, to_pixel(*subgoal), ROUTE_COLOR, half=4) == 0.0
    assert color_fraction(drawn, to_pixel(2.0, -6.0), ROUTE_COLOR, half=4) == 0.0  # not where the path is not


def test_a_map_scene_shows_the_robots_planned_path():
    """`scene_frame` of a doorway: the robot's shortest path from where it is to its goal, through the door, and
    the subgoal `lookahead` metres along it; none in the open plane."""
    import socnav

    env = socnav.make_env({"scenario": "doorway", "n_humans": 0})
    env.reset(seed=3)
    world = env.unwrapped.world
    frame = env.unwrapped.scene_frame()
    start, goal = world.positions[0, 0], world.goals[0, 0]
    np.testing.assert_allclose(frame.route[0], start)
    np.testing.assert_allclose(frame.route[-1], goal)
    assert np.sign(start[0]) != np.sign(goal[0])  # rooms either side of the wall at x = 0 ...
    crossings = [a[1] + (b[1] - a[1]) * (0.0 - a[0]) / (b[0] - a[0])
                 for a, b in zip(frame.route[:-1], frame.route[1:], strict=True) if a[0] * b[0] < 0.0]
    assert len(crossings) == 1 and abs(crossings[0]) < 0.55  # ... crossed once, through the door (|y| < 0.55)
    along = np.linalg.norm(frame.subgoal - start)
    assert 0.0 < along <= 1.0 + 1e-9  # planner.lookahead: 1 m along the path, never farther as the crow flies
    open_plane = socnav.make_env({"scenario": "circle_crossing"})
    open_plane.reset(seed=0)
    assert open_plane.unwrapped.scene_frame().route is None
