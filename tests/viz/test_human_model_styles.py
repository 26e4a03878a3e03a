"""Each human is drawn with its model: in scenes with other than ORCA humans (social force, replayed, mixed
crowds) a mark in the model's colour sits at each human's centre and the legend lists the models; scenes of ORCA
humans alone are drawn without model marks. Pixel positions are computed by hand from extent / width, as in
test_render.py."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.colors import to_rgb

import socnav
from socnav.viz import SceneFrame, SceneRenderer
from socnav.viz.render import HUMAN_COLOR, MODEL_STYLES, model_style

W = H = 480
EXTENT = 8.5


def to_pixel(x: float, y: float) -> tuple[int, int]:
    scale = W / (2 * EXTENT)
    return int((EXTENT - y) * scale), int((x + EXTENT) * scale)


def fraction(img: np.ndarray, rc: tuple[int, int], color: str, half: int = 1, tol: int = 16) -> float:
    r, c = rc
    window = img[r - half: r + half + 1, c - half: c + half + 1].astype(int)
    target = np.round(np.array(to_rgb(color)) * 255).astype(int)
    return float((np.abs(window - target).max(axis=-1) <= tol).mean())


HUMANS = [(5.0, 0.0), (0.0, 5.0), (-5.0, 0.0), (0.0, -5.0)]


def frame(models=None, **kw) -> SceneFrame:
    pos = np.array([(0.0, 0.0), *HUMANS])
    defaults = {"positions": pos, "velocities": np.zeros((5, 2)), "radii": np.full(5, 0.4),
                "goals": np.vstack([[6.0, 6.0], -pos[1:]]), "personal_space_radii": np.r_[0.0, np.full(4, 0.5)],
                "active": np.ones(5, dtype=bool), "robot_heading": 0.0, "models": models}
    return SceneFrame(**{**defaults, **kw})


def legend_labels(legend) -> list[str]:
    return [] if legend is None else [text.get_text() for text in legend.get_texts()]


@pytest.fixture()
def renderer():
    r = SceneRenderer(width=W, height=H, extent=EXTENT)
    yield r
    r.close()


def test_each_model_has_its_own_colour_and_mark():
    styles = [model_style(name) for name in ("orca", "social_force", "replay", "someone_elses")]
    assert len({colour for colour, _, _ in styles}) == 4 and len({marker for _, marker, _ in styles}) == 4
    assert model_style("someone_elses") == model_style("someone_elses"), "a registered model keeps its style"


def test_a_mixed_crowd_is_drawn_model_by_model_with_a_legend(renderer):
    models = ["orca", "orca", "social_force", "orca", "social_force"]
    image = renderer.render(frame(models))
    orca, social_force = MODEL_STYLES["orca"][0], MODEL_STYLES["social_force"][0]
    for (x, y), model in zip(HUMANS, models[1:], strict=True):
        colour, other = (social_force, orca) if model == "social_force" else (orca, social_force)
        assert fraction(image, to_pixel(x, y), colour) >= 0.4, (x, y, model)  # the 3 x 3 px around the centre
        assert fraction(image, to_pixel(x, y), other) == 0.0, (x, y, model)
    assert legend_labels(renderer.ax.get_legend()) == ["human: ORCA", "human: social force"]
    # the same scene of ORCA humans alone: no marks, no legend, the plain human colour at the centres
    plain = renderer.render(frame(["orca"] * 5))
    assert renderer.ax.get_legend() is None
    for x, y in HUMANS:
        assert fraction(plain, to_pixel(x, y), HUMAN_COLOR) == 1.0
        assert fraction(plain, to_pixel(x, y), orca) == 0.0
    assert np.array_equal(plain, renderer.render(frame(None))), "ORCA humans alone: the image of a frame without models"


def test_one_model_other_than_orca_is_named_too(renderer):
    image = renderer.render(frame(["replay"] * 5))
    assert legend_labels(renderer.ax.get_legend()) == ["human: replayed (recorded)"]
    assert fraction(image, to_pixel(*HUMANS[0]), MODEL_STYLES["replay"][0]) >= 0.5
    # an inactive human's model is not listed
    renderer.render(frame(["", "replay", "replay", "replay", "social_force"],
                          active=np.array([True, True, True, True, False])))
    assert legend_labels(renderer.ax.get_legend()) == ["human: replayed (recorded)"]


def test_the_annotated_legend_lists_the_models():
    renderer = SceneRenderer(width=720, height=480, extent=EXTENT, annotate=True)
    renderer.render(frame(["orca", "social_force", "orca", "orca", "orca"]))
    labels = legend_labels(renderer.legend_ax.get_legend())
    assert "human: ORCA" in labels and "human: social force" in labels and "trail (recent path)" in labels
    assert renderer.ax.get_legend() is None, "one legend: the side one"
    renderer.render(frame(["orca"] * 5))
    assert not any(label.startswith("human: ") for label in legend_labels(renderer.legend_ax.get_legend()))
    renderer.close()


def test_env_frames_carry_each_humans_model():
    env = socnav.make_env({"scenario": "circle_crossing", "n_humans": 6, "max_humans": 6,
                           "humans": {"mix": {"orca": 0.5, "social_force": 0.5}}}, render_mode="rgb_array")
    env.reset(seed=1)
    scene = env.unwrapped.scene_frame()
    index = env.unwrapped.world.model_index[0]
    assert list(scene.models[1:]) == [["orca", "social_force"][k] for k in index[1:]]
    assert {"orca", "social_force"} <= set(scene.models[1:]), "seed 1 draws both models"
    env.render()
    assert legend_labels(env.unwrapped._renderer.ax.get_legend()) == [
        f"human: {model_style(name)[2]}" for name in dict.fromkeys(scene.models[1:])]
    default = socnav.make_env({"scenario": "circle_crossing"})
    default.reset(seed=1)
    assert set(default.unwrapped.scene_frame().models) == {"orca"}
