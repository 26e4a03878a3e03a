"""Frames a person understands without the source: inattentive humans marked, a legend, a metre scale, a title,
the outcome in large type, uncertainty bars with tick values and the threshold marked.
Pixel positions are computed by hand from extent / width, as in test_render.py."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.colors import to_rgb

from socnav.viz import SceneFrame, SceneRenderer
from socnav.viz.render import HUMAN_COLOR, INATTENTIVE_COLOR, THRESHOLD_COLOR

W = H = 480
EXTENT = 8.5


def to_pixel(x: float, y: float, left: float = 0, size: float = H, extent: float = EXTENT,
             top: float = 0) -> tuple[int, int]:
    """(row, col) of scene point (x, y) in a square scene of `size` px starting `left` px from the image's left
    edge and `top` px from its top."""
    scale = size / (2 * extent)
    return int(top + (extent - y) * scale), int(left + (x + extent) * scale)


def annotated_pixel(renderer: SceneRenderer, x: float, y: float) -> tuple[int, int]:
    """(row, col) of scene point (x, y) in an annotated frame: the scene is the square between the bands above and
    below it, centred in the left 70 % of the image (`SceneRenderer.scene_box`)."""
    left, top, size, _ = renderer.scene_box()
    return to_pixel(x, y, left=left, size=size, top=top)


def fraction(img: np.ndarray, rc: tuple[int, int], color: str, half: int = 3, tol: int = 12) -> float:
    r, c = rc
    window = img[r - half: r + half + 1, c - half: c + half + 1].astype(int)
    target = np.round(np.array(to_rgb(color)) * 255).astype(int)
    return float((np.abs(window - target).max(axis=-1) <= tol).mean())


def frame(**kw) -> SceneFrame:
    """Robot at the origin, humans at (5, 0), (0, 5), (-5, 0)."""
    pos = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [-5.0, 0.0]])
    defaults = {"positions": pos, "velocities": np.zeros((4, 2)), "radii": np.full(4, 0.3),
                "goals": np.vstack([[6.0, 6.0], -pos[1:]]), "personal_space_radii": np.r_[0.0, 0.5, 0.5, 0.5],
                "active": np.ones(4, dtype=bool), "robot_heading": 0.0}
    return SceneFrame(**{**defaults, **kw})


def test_inattentive_humans_are_drawn_differently():
    image = SceneRenderer(width=W, height=H, extent=EXTENT).render(frame(attentive=np.array([True, True, False, True])))
    assert fraction(image, to_pixel(5.0, 0.0), HUMAN_COLOR) > 0.5
    assert fraction(image, to_pixel(-5.0, 0.0), HUMAN_COLOR) > 0.5
    assert fraction(image, to_pixel(0.0, 5.0), INATTENTIVE_COLOR) > 0.5
    assert fraction(image, to_pixel(0.0, 5.0), HUMAN_COLOR) == 0.0


@pytest.fixture(scope="module")
def annotated():
    renderer = SceneRenderer(width=720, height=480, extent=EXTENT, annotate=True, fallback_color="#f4a261")
    yield renderer
    renderer.close()


def test_annotated_frames_carry_a_legend_and_a_metre_scale(annotated):
    annotated.render(frame())
    labels = [text.get_text() for text in annotated.legend_ax.get_legend().get_texts()]
    for words in ("robot", "safety fallback", "sees the robot", "ignores the robot", "personal space", "goal",
                  "trail"):
        assert any(words in label for label in labels), (words, labels)
    assert any(text.get_text().startswith("2 m") for text in annotated.ax.texts)
    # The scene is a square between the bands, centred in the left 70 %; a human is where the hand computation
    # puts it.
    image = annotated.render(frame())
    assert image.shape == (480, 720, 3)
    left, top, width, height = annotated.scene_box()
    assert width == pytest.approx(height) and 380 < height < 480 and top > 20 and top + height < 460
    assert left + width / 2 == pytest.approx(0.7 * 720 / 2, abs=1)
    assert fraction(image, annotated_pixel(annotated, 5.0, 0.0), HUMAN_COLOR) > 0.5


def test_title_and_outcome_are_drawn(annotated):
    plain = annotated.render(frame())
    titled = annotated.render(frame(title="position_swap | pretrained | seed 3"))
    top = slice(0, 25), slice(100, 380)
    assert (np.abs(titled[top].astype(int) - plain[top].astype(int)).max(axis=-1) > 60).sum() > 50
    ended = annotated.render(frame(outcome="COLLISION"))
    dark = lambda img: (img.max(axis=-1) < 60).sum()  # noqa: E731 - black text pixels
    assert dark(ended) > dark(plain) + 300  # large type
    outcome = annotated.outcome_text.get_window_extent(annotated.canvas.get_renderer())
    title = annotated.title_text.get_window_extent(annotated.canvas.get_renderer())
    assert outcome.height > 1.5 * title.height / 2  # taller than a line of the (two-line) title


@pytest.mark.parametrize("robot_y", [0.0, 3.0, 6.5, -3.0, -6.5])
def test_outcome_banner_leaves_the_robot_visible(annotated, robot_y):
    # Where an episode ends -- a collision above all -- must stay visible under the banner saying how it ended.
    positions = np.array([[0.0, robot_y], [0.6, robot_y], [5.0, 0.0], [-5.0, 0.0]])
    plain = annotated.render(frame(positions=positions))
    ended = annotated.render(frame(positions=positions, outcome="COLLISION"))
    changed = np.abs(ended.astype(int) - plain.astype(int)).max(axis=-1) > 30
    assert changed.sum() > 500  # the banner is there
    for x in (0.0, 0.6):  # the robot and the human it touches
        row, col = annotated_pixel(annotated, x, robot_y)
        assert not changed[row - 12: row + 13, col - 12: col + 13].any(), (x, robot_y)


def test_uncertainty_bars_show_ticks_and_threshold(annotated):
    image = annotated.render(frame(side_panel={"epistemic heading": 0.2}, panel_marks={"epistemic heading": 0.5},
                                   panel_ticks={"epistemic heading": ((0.25, "0.01"), (0.5, "0.03"))},
                                   panel_title="uncertainty"))
    texts = [text.get_text() for text in annotated.panel_ax.texts]
    assert {"0.01", "0.03", "uncertainty"} <= set(texts)
    target = np.round(np.array(to_rgb(THRESHOLD_COLOR)) * 255).astype(int)
    red = np.abs(image.astype(int) - target).max(axis=-1) <= 20
    columns = np.flatnonzero(red[:, 500:].sum(axis=0) >= 20) + 500  # a vertical line, not the red caption text
    # The mark sits halfway along the bar: the panel axes span [0.72, 0.97] of the width.
    assert len(columns) and abs(np.median(columns) - (0.72 + 0.25 * 0.5) * 720) < 8


def test_episode_title_names_everything_shown():
    from socnav import load_config
    from socnav.cli.workflows.animation import episode_title

    config = load_config({"scenario": "position_swap", "n_humans": 1, "perturbation": {"heading_noise": 0.8}})
    title = episode_title(config, "pretrained", 7, "mc")
    for words in ("position_swap", "1 human", "pretrained", "seed 7", "heading_noise=0.8", "safety layer: mc"):
        assert words in title
    assert "no safety layer" in episode_title(config, "pretrained", 7)
