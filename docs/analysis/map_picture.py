"""The picture of the four map scenarios in docs/maps.md: the first frame of episode 0 of each (default config), as
`SceneRenderer` draws it, on axes in metres, with one legend.

    python docs/analysis/map_picture.py                     # writes docs/images/map_scenarios.png
    python docs/analysis/map_picture.py --out maps.png --seed 3
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

import socnav
from socnav.envs.env import scene_extent
from socnav.io import atomic_path
from socnav.viz.render import (
    HUMAN_COLOR,
    HUMAN_EDGE_COLOR,
    INATTENTIVE_COLOR,
    INATTENTIVE_EDGE_COLOR,
    ROBOT_COLOR,
    ROBOT_GOAL_COLOR,
    WALL_COLOR,
    SceneRenderer,
)

SCENARIOS = ("corridor", "doorway", "intersection", "room")
#: What each panel's title says about the walls (the defaults of the config's `layout` section; docs/maps.md).
WORDS = {
    "corridor": "corridor: two walls 3 m apart, 16 m long",
    "doorway": "doorway: two 8 m rooms, a 1.1 m door",
    "intersection": "intersection: two 3 m corridors crossing",
    "room": "room: cabinets in the corners and along the walls",
}
PIXELS = 560  # each scene's image, square


def scene_image(scenario: str, seed: int) -> tuple[np.ndarray, float, int]:
    """The first frame of episode `seed` of `scenario` (no annotations), its half side in metres, its humans."""
    env = socnav.make_env({"scenario": scenario})
    env.reset(seed=seed)
    config = env.unwrapped.config
    extent = scene_extent(config)
    renderer = SceneRenderer(width=PIXELS, height=PIXELS, extent=extent, dpi=100, clock=False)
    frame = env.unwrapped.scene_frame()
    image = renderer.render(frame)
    renderer.close()
    env.close()
    return image, extent, int(np.asarray(frame.active)[1:].sum())


def legend_handles() -> list[Line2D]:
    """What the scenes show, in the renderer's colours."""
    def disc(face: str | tuple[float, ...], edge: str, label: str) -> Line2D:
        return Line2D([], [], marker="o", linestyle="", markersize=11, markerfacecolor=face, markeredgecolor=edge,
                      label=label)

    return [
        disc(ROBOT_COLOR, "black", "robot (black line: heading)"),
        Line2D([], [], marker="*", linestyle="", markersize=14, markerfacecolor=ROBOT_GOAL_COLOR,
               markeredgecolor="#14524b", label="robot's goal"),
        disc(HUMAN_COLOR, HUMAN_EDGE_COLOR, "human who sees the robot"),
        disc(INATTENTIVE_COLOR, INATTENTIVE_EDGE_COLOR, "human who ignores the robot"),
        Line2D([], [], marker="o", linestyle="", markersize=15, markerfacecolor="none",
               markeredgecolor=HUMAN_COLOR, label="personal space (dashed ring)"),
        disc(to_rgba(HUMAN_COLOR, 0.35), HUMAN_EDGE_COLOR, "human behind a wall (faded: unseen)"),
        Line2D([], [], marker="x", linestyle="", markersize=8, color=HUMAN_COLOR, label="a human's goal"),
        Line2D([], [], color=WALL_COLOR, linewidth=5, label="wall, furniture"),
    ]


def map_picture(out: Path, seed: int = 0) -> Path:
    """Draw the four scenes (2 x 2) with their titles and one legend below; write `out` (PNG) atomically."""
    figure = Figure(figsize=(11.0, 12.4), dpi=100, facecolor="white")
    FigureCanvasAgg(figure)
    axes = figure.subplots(2, 2)
    for axis, scenario in zip(axes.flat, SCENARIOS, strict=True):
        image, extent, humans = scene_image(scenario, seed)
        axis.imshow(image, extent=(-extent, extent, -extent, extent), interpolation="antialiased")
        axis.set_title(f"{WORDS[scenario]}\n({humans} humans, episode {seed})", fontsize=12)
        axis.set_xlabel("x (m)", fontsize=10)
        axis.set_ylabel("y (m)", fontsize=10)
        axis.tick_params(labelsize=9)
    figure.legend(handles=legend_handles(), loc="lower center", ncol=4, fontsize=11, frameon=False,
                  handletextpad=0.4, columnspacing=1.6)
    figure.tight_layout(rect=(0.0, 0.07, 1.0, 1.0), h_pad=2.0)
    with atomic_path(out) as temporary:
        figure.savefig(temporary, format="png", dpi=100)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "images" /
                        "map_scenarios.png", help="the PNG to write (default: docs/images/map_scenarios.png)")
    parser.add_argument("--seed", type=int, default=0, help="the episode each scene starts (default 0)")
    args = parser.parse_args()
    print(map_picture(args.out, args.seed))


if __name__ == "__main__":
    main()
