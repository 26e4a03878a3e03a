"""Off-screen rendering of one social-navigation scene into an RGB array.
One matplotlib figure (Agg canvas, no pyplot) is built once; per frame only the moving artists are redrawn.

With ``SceneRenderer(annotate=True)`` a frame explains itself: a title, a legend (robot, attentive and
inattentive humans, personal space, goal, trail), a metre scale, the outcome in large type, and uncertainty bars
with tick values and the threshold marked. Every annotation lies outside the scene (bands above and below it, the
side column), so none covers a wall, a piece of furniture or an agent.

When a frame's humans are not all ORCA humans (``SceneFrame.models``: social force, replayed or mixed crowds), each
human carries its model's colour and mark (`MODEL_STYLES`), listed in a legend (the side legend, or one in the
scene's lower right corner)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.artist import Artist
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection, LineCollection, PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Rectangle
from matplotlib.text import Text
from matplotlib.transforms import ScaledTranslation, Transform, blended_transform_factory

# Palette. The robot colour is used by no other artist except the robot's own trail.
ROBOT_COLOR = "#e4572e"
HUMAN_COLOR = "#3a6ea5"
HUMAN_EDGE_COLOR = "#1d3a57"
INATTENTIVE_COLOR = "#b0b0b0"  # humans that ignore the robot: grey fill, dashed outline
INATTENTIVE_EDGE_COLOR = "#555555"
THRESHOLD_COLOR = "#d62828"
ROBOT_GOAL_COLOR = "#2a9d8f"
PANEL_BAR_COLOR = "#6c5b7b"
ROUTE_COLOR = "#7b3294"  # the robot's planned path and its subgoal
WALL_COLOR = "#4a4a4a"  # walls: solid polygons filled, wall segments as thick lines
HIDDEN_VEIL = (1.0, 1.0, 1.0, 0.65)  # a human the robot cannot see (behind a wall): drawn faded, dotted outline

TRAIL_ALPHA_RANGE = (0.08, 0.6)  # oldest -> newest trail chunk
TRAIL_BANDS = 6  # number of alpha steps along a trail
HEADING_LENGTH = 1.4  # heading line length, in robot radii
PANEL_FRACTION = 0.3  # share of the image width given to the side panel when present
PANEL_MIN_ROWS = 8  # bars keep the same height for up to this many keys
#: How each human model is drawn when a scene holds other than ORCA humans: the colour of the mark at the human's
#: centre and of its disc's outline, the mark, the legend's words. Other registered models take
#: `EXTRA_MODEL_STYLES` in turn (by name, so a model keeps its style from frame to frame).
MODEL_STYLES = {
    "orca": ("#1d3a57", "o", "ORCA"),
    "social_force": ("#8e3fb0", "^", "social force"),
    "replay": ("#2d7a46", "s", "replayed (recorded)"),
}
EXTRA_MODEL_STYLES = (("#b5651d", "D"), ("#c9184a", "v"), ("#00838f", "P"), ("#6d6875", "X"))
MODEL_MARK_SIZE = 8.0  # points


def model_style(name: str) -> tuple[str, str, str]:
    """(colour, marker, legend words) of human model `name`."""
    if name in MODEL_STYLES:
        return MODEL_STYLES[name]
    colour, marker = EXTRA_MODEL_STYLES[sum(name.encode()) % len(EXTRA_MODEL_STYLES)]
    return colour, marker, name.replace("_", " ")


#: Without annotations, where the outcome banner goes (axes fraction): under the two-line title, or over the
#: one-line caption, whichever band is farther from the robot, so that the end of the episode stays visible.
OUTCOME_TOP, OUTCOME_BOTTOM = 0.89, 0.07
#: Annotated frames: the bands (points) kept free above the scene (the two-line title, the outcome) and below it
#: (the metre scale, then the caption), and the annotations' font sizes (points).
TOP_BAND_PT, BOTTOM_BAND_PT = 30.0, 34.0
TEXT_PT, OUTCOME_PT, SCALE_PT = 9.0, 17.0, 8.0
#: Plain frames: the clock sits in the scene's top-left corner, `CLOCK_INSET_PT` in from both edges; its box (text
#: and padding) and half a wall line lie in the band `CLOCK_BAND_PT` high at the top of the scene, so a scene whose
#: walls stay below that band (`clock_clear_extent`) has no wall under the clock.
CLOCK_INSET_PT, CLOCK_BAND_PT = 4.0, 20.0


def clock_clear_extent(top: float, size: int = 480, dpi: int = 80) -> float:
    """The smallest extent of a plain frame whose scene, drawn `size` pixels high at `dpi`, shows everything up to
    the height `top` (metres) below the clock's band (`CLOCK_BAND_PT`): with ``extent >= clock_clear_extent(top)``,
    ``(extent - top) / (2 * extent)`` of the scene's height lies above `top`, at least the band."""
    band = CLOCK_BAND_PT / (size / dpi * 72.0)  # the band as a fraction of the scene's height
    return float(top) / (1.0 - 2.0 * band)


@dataclass
class SceneFrame:
    """Everything needed to draw one instant of the scene (agent 0 is the robot)."""

    positions: np.ndarray  # (N, 2) metres
    velocities: np.ndarray  # (N, 2) m/s
    radii: np.ndarray  # (N,) body radii, metres
    goals: np.ndarray  # (N, 2)
    personal_space_radii: np.ndarray  # (N,) measured from the body boundary; 0 for the robot
    active: np.ndarray  # (N,) bool: which slots are real agents (only these are drawn)
    robot_heading: float  # radians
    time: float = 0.0  # seconds, shown as text
    trails: np.ndarray | None = None  # (T, N, 2) past positions, oldest first; NaN breaks a line
    robot_color: str | None = None  # override, e.g. to highlight a safety fallback
    caption: str = ""  # extra text (outcome, step, ...)
    side_panel: dict[str, float] | None = None  # label -> value in [0, 1], drawn as bars
    attentive: np.ndarray | None = None  # (N,) bool: False = the human ignores the robot (None: all attentive)
    title: str = ""  # what is shown (scenario, policy, seed, ...), on top of the scene (replaces the time)
    outcome: str = ""  # drawn in large type across the scene (e.g. at the last frame)
    #: per bar label: ((position in [0, 1], tick label), ...) drawn under the bar -- the bar's scale in words
    panel_ticks: dict[str, tuple[tuple[float, str], ...]] | None = None
    panel_marks: dict[str, float] | None = None  # per bar label: threshold position in [0, 1], a red line
    panel_title: str = ""  # heading of the bars
    #: (N,) the name of the model moving each agent (slot 0, the robot, is ignored); None: not shown. Drawn (mark,
    #: outline colour, legend) when the active humans are not all ORCA humans.
    models: Sequence[str] | None = None
    #: the world's walls: polygons (K, 2) in metres (K = 2: a wall segment); None or empty: the open plane
    walls: Sequence[np.ndarray] | None = None
    #: (N,) bool: the humans the robot cannot see (behind a wall, ``occlusion``), drawn faded; None: all seen
    hidden: np.ndarray | None = None
    #: the robot's planned path from where it is to its goal, (M, 2) vertices (a dashed line); None: not shown
    route: np.ndarray | None = None
    #: the subgoal on that path the robot heads for, (2,) (a diamond); None: not shown
    subgoal: np.ndarray | None = None


class SceneRenderer:
    """Render `SceneFrame`s to uint8 RGB arrays of a fixed shape `(height, width, 3)`.

    - Axis limits are fixed to `[-extent, extent]` with equal aspect, so frames are comparable;
      scene point (x, y) lands at pixel column `(x + extent) / (2 * extent) * width` and row
      `(extent - y) / (2 * extent) * height` (square image, no side panel, no annotations).
    - With `annotate`, bands above (`TOP_BAND_PT`: title or time, outcome) and below (`BOTTOM_BAND_PT`: metre
      scale, caption) the scene hold the annotations, so none covers the scene; the scene is the square left
      between them (`scene_box`).
    - The image size never changes: when a frame has a `side_panel`, the scene is drawn in the
      left `1 - PANEL_FRACTION` of the image and the bars fill the right part. Frames with and
      without a panel can therefore be mixed in one animation.
    - Speed: the static layer (grid, border, panel tracks and labels) is rasterised once per
      layout and restored from a pixel cache; only the moving artists are drawn per frame.
    """

    def __init__(self, width: int = 480, height: int = 480, extent: float = 8.5, dpi: int = 80,
                 annotate: bool = False, fallback_color: str | None = None, clock: bool = True):
        """`annotate`: draw a legend (beside the scene, in the side-panel column, which is then always there) and a
        metre scale; `fallback_color`: the robot's colour while a safety fallback drives, listed in the legend;
        `clock`: draw the time (``t = 1.5 s``) when a frame has no title (False: the scene alone, e.g. for a figure
        that says what it shows around it)."""
        if min(width, height, extent, dpi) <= 0:
            raise ValueError("width, height, extent and dpi must be positive")
        self.width, self.height, self.extent, self.dpi = int(width), int(height), float(extent), int(dpi)
        self.annotate, self.fallback_color, self.clock = bool(annotate), fallback_color, bool(clock)

        self.fig = Figure(figsize=(self.width / self.dpi, self.height / self.dpi), dpi=self.dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = self.fig.add_axes((0.0, 0.0, 1.0, 1.0))
        self.ax.set_xlim(-self.extent, self.extent)
        self.ax.set_ylim(-self.extent, self.extent)
        self.ax.set_aspect("equal", adjustable="box")
        self.ax.set_axis_off()
        self.panel_ax = self.fig.add_axes((1.0 - PANEL_FRACTION + 0.02, 0.05, PANEL_FRACTION - 0.05, 0.9))
        self.panel_ax.set_xlim(0.0, 1.0)
        self.panel_ax.set_axis_off()
        self.legend_ax = self.fig.add_axes((1.0 - PANEL_FRACTION + 0.01, 0.01, PANEL_FRACTION - 0.02, 0.36))
        self.legend_ax.set_axis_off()
        self.legend_ax.set_visible(False)

        self._add_static_scene()
        self._add_dynamic_scene()
        self._panel_bars: list[Rectangle] = []
        self._panel_marks: list[Line2D] = []
        self._layout: tuple | None = None  # side-panel layout of the cached background
        self._background = None  # pixel cache of the static layer

    # ------------------------------------------------------------------ setup
    def _add_static_scene(self) -> None:
        """Light 1 m grid, axes through the origin and the arena border."""
        e = self.extent
        ticks = np.arange(np.ceil(-e), np.floor(e) + 1)
        grid: list[list[tuple[float, float]]] = [[(t, -e), (t, e)] for t in ticks] + [[(-e, t), (e, t)] for t in ticks]
        self.ax.add_collection(LineCollection(grid, colors="#eeeeee", linewidths=0.6, zorder=0))
        origin: list[list[tuple[float, float]]] = [[(0, -e), (0, e)], [(-e, 0), (e, 0)]]
        self.ax.add_collection(LineCollection(origin, colors="#d8d8d8", linewidths=0.8, zorder=0))
        self.ax.add_patch(Rectangle((-e, -e), 2 * e, 2 * e, fill=False, edgecolor="#999999", linewidth=1.0,
                                    clip_on=False))  # (clipped, the axes' edge would cut half of each side)
        if self.annotate:
            self._add_scale_bar()
            self._add_legend()

    def _band(self, points: float) -> Transform:
        """x in scene metres, y in the scene axes' fraction, shifted by `points` (negative: below the scene)."""
        return blended_transform_factory(self.ax.transData, self.ax.transAxes) + ScaledTranslation(
            0.0, points / 72.0, self.fig.dpi_scale_trans)

    def _add_scale_bar(self) -> None:
        """A metre scale under the scene's right edge, outside the scene (the grid lines are 1 m apart)."""
        e = self.extent
        length = 2.0 if e >= 4 else 1.0
        band = self._band(-9.0)
        self.scale_bar = self.ax.plot([e - length, e], [0.0, 0.0], color="black", linewidth=2.5, marker="|",
                                      markersize=8, markeredgewidth=1.5, solid_capstyle="butt", transform=band,
                                      clip_on=False)[0]
        self.scale_text = self.ax.text(e - length - 0.25, 0.0, f"{length:g} m (grid 1 m)", ha="right",
                                       va="center", fontsize=SCALE_PT, transform=band)

    def annotation_texts(self) -> list[Text]:
        """The texts drawn on or around the scene (title or time, caption, outcome, metre scale) that the last frame
        shows: what must not cover the scene's walls (checked in tests/viz/test_annotation_layout.py)."""
        texts = [self.time_text, self.title_text, self.caption_text, self.outcome_text]
        if self.annotate:
            texts.append(self.scale_text)
        return [text for text in texts if text.get_visible() and text.get_text()]

    def _add_legend(self, models: Sequence[str] = (), walls: bool = False) -> None:
        """Proxy artists for every kind of thing in the scene, in the side column (and each human model shown)."""
        handles = [
            Line2D([], [], marker="o", linestyle="", markersize=10, markerfacecolor=ROBOT_COLOR,
                   markeredgecolor="black", label="robot (line: heading)"),
        ]
        if self.fallback_color is not None:
            handles.append(Line2D([], [], marker="o", linestyle="", markersize=10, markerfacecolor=self.fallback_color,
                                  markeredgecolor="black", label="robot, safety fallback driving"))
        handles += [
            Line2D([], [], marker="o", linestyle="", markersize=10, markerfacecolor=HUMAN_COLOR,
                   markeredgecolor=HUMAN_EDGE_COLOR, label="human, sees the robot"),
            Line2D([], [], marker="o", linestyle="", markersize=10, markerfacecolor=INATTENTIVE_COLOR,
                   markeredgecolor=INATTENTIVE_EDGE_COLOR, label="human, ignores the robot (dashed)"),
            Line2D([], [], marker="o", linestyle="", markersize=13, markerfacecolor="none",
                   markeredgecolor=to_rgba(HUMAN_COLOR, 0.6), label="personal space (dashed ring)"),
            Line2D([], [], marker="*", linestyle="", markersize=12, markerfacecolor=ROBOT_GOAL_COLOR,
                   markeredgecolor="#14524b", label="robot's goal (x: humans' goals)"),
            Line2D([], [], color=ROBOT_COLOR, linewidth=1.5, label="trail (recent path)"),
        ]
        if walls:
            handles += [
                Line2D([], [], color=WALL_COLOR, linewidth=4.0, label="wall"),
                Line2D([], [], color=ROUTE_COLOR, linewidth=1.2, linestyle="--", marker="D", markersize=5,
                       label="planned path, subgoal"),
                Line2D([], [], marker="o", linestyle="", markersize=10, markerfacecolor=to_rgba(HUMAN_COLOR, 0.35),
                       markeredgecolor=HUMAN_EDGE_COLOR, label="human behind a wall (faded: unseen)"),
            ]
        handles += self._model_handles(models)
        self.legend_ax.legend(handles=handles, loc="lower left", fontsize=7, frameon=False, borderaxespad=0.0,
                              handletextpad=0.4, labelspacing=0.5)

    @staticmethod
    def _model_handles(models: Sequence[str]) -> list[Line2D]:
        """A legend entry per human model shown: its mark, in its colour."""
        handles = []
        for name in models:
            colour, marker, words = model_style(name)
            handles.append(Line2D([], [], marker=marker, linestyle="", markersize=MODEL_MARK_SIZE + 1,
                                  markerfacecolor=colour, markeredgecolor="white", label=f"human: {words}"))
        return handles

    def _add_model_legend(self, models: Sequence[str]) -> None:
        """Without the side legend: the human models shown, in the scene's lower right corner (static layer)."""
        legend = self.ax.get_legend()
        if legend is not None:
            legend.remove()
        if models and not self.annotate:
            self.ax.legend(handles=self._model_handles(models), loc="lower right", fontsize=7, title="human model",
                           title_fontsize=7, framealpha=0.8, handletextpad=0.3, borderaxespad=0.3)

    def _add_dynamic_scene(self) -> None:
        """Create every moving artist once (animated, so it is left out of the static layer)."""
        ax = self.ax

        def discs(**kw: Any) -> EllipseCollection:
            empty = np.zeros((0, 2))
            collection = EllipseCollection([], [], [], units="xy", offsets=empty, offset_transform=ax.transData, **kw)
            ax.add_collection(collection)
            return collection

        # Each artist is created, then added (the add_* methods are typed to return the base class).
        self.wall_blocks = PolyCollection([], facecolors=WALL_COLOR, edgecolors=WALL_COLOR, linewidths=1.0)
        ax.add_collection(self.wall_blocks)
        self.wall_lines = LineCollection([], colors=WALL_COLOR, linewidths=3.0, capstyle="round")
        ax.add_collection(self.wall_lines)
        self.trail_lines = LineCollection([], linewidths=1.5, joinstyle="round")
        ax.add_collection(self.trail_lines)
        (self.route_line,) = ax.plot([], [], "--", color=ROUTE_COLOR, linewidth=1.2)
        (self.subgoal_mark,) = ax.plot([], [], "D", color=ROUTE_COLOR, markersize=5)
        self.personal_space = discs(facecolors="none", edgecolors=to_rgba(HUMAN_COLOR, 0.45),
                                    linestyles="--", linewidths=0.9)
        (self.human_goals,) = ax.plot([], [], "x", color=HUMAN_COLOR, alpha=0.35, markersize=4)
        self.humans = discs(facecolors=HUMAN_COLOR, edgecolors=HUMAN_EDGE_COLOR, linewidths=0.8)
        self.inattentive = discs(facecolors=INATTENTIVE_COLOR, edgecolors=INATTENTIVE_EDGE_COLOR, linewidths=1.2,
                                 linestyles="--")
        self.human_vel = LineCollection([], colors=to_rgba(HUMAN_EDGE_COLOR, 0.5), linewidths=1.0)
        ax.add_collection(self.human_vel)
        self.hidden_humans = discs(facecolors=HIDDEN_VEIL, edgecolors=HUMAN_EDGE_COLOR, linewidths=1.0,
                                   linestyles=":")
        (self.robot_goal,) = ax.plot([], [], "*", color=ROBOT_GOAL_COLOR, markeredgecolor="#14524b", markersize=15)
        self.robot = Circle((0.0, 0.0), 0.3, facecolor=ROBOT_COLOR, edgecolor="black", linewidth=1.0)
        ax.add_patch(self.robot)
        (self.heading_line,) = ax.plot([], [], color="black", linewidth=2.0, solid_capstyle="round")
        box = {"boxstyle": "round,pad=0.2", "facecolor": "white", "alpha": 0.7, "edgecolor": "none"}
        if self.annotate:  # in the bands above and below the scene: nothing covers it
            above, below = self._shifted(3.0), self._shifted(-19.0)  # below: under the metre scale
            self.time_text = ax.text(0.0, 1.0, "", transform=above, ha="left", va="bottom", fontsize=TEXT_PT)
            self.caption_text = ax.text(0.0, 0.0, "", transform=below, ha="left", va="top", fontsize=TEXT_PT)
            self.title_text = ax.text(0.0, 1.0, "", transform=above, ha="left", va="bottom", fontsize=TEXT_PT,
                                      fontweight="bold", linespacing=1.15)
            right = blended_transform_factory(self.fig.transFigure, ax.transAxes) + ScaledTranslation(
                0.0, 3.0 / 72.0, self.fig.dpi_scale_trans)
            self.outcome_text = ax.text(0.99, 1.0, "", transform=right, ha="right", va="bottom", fontsize=OUTCOME_PT,
                                        fontweight="bold")
        else:
            inset = ax.transAxes + ScaledTranslation(CLOCK_INSET_PT / 72.0, -CLOCK_INSET_PT / 72.0,
                                                     self.fig.dpi_scale_trans)  # in the band of CLOCK_BAND_PT
            self.time_text = ax.text(0.0, 1.0, "", transform=inset, ha="left", va="top", fontsize=TEXT_PT, bbox=box)
            self.caption_text = ax.text(0.02, 0.02, "", transform=ax.transAxes, ha="left", va="bottom",
                                        fontsize=TEXT_PT, bbox=box)
            self.title_text = ax.text(0.5, 0.98, "", transform=ax.transAxes, ha="center", va="top", fontsize=TEXT_PT,
                                      fontweight="bold", bbox=box)
            self.outcome_text = ax.text(0.5, OUTCOME_BOTTOM, "", transform=ax.transAxes, ha="center", va="bottom",
                                        fontsize=30, fontweight="bold", bbox={**box, "alpha": 0.85, "pad": 0.4})
        self._model_marks: dict[str, Line2D] = {}  # per human model, its marks (made when first shown)
        # Drawn in this order (back to front).
        self._dynamic: list[Artist] = [
            self.wall_blocks, self.wall_lines,
            self.trail_lines, self.route_line, self.subgoal_mark,
            self.personal_space, self.human_goals, self.humans, self.inattentive, self.human_vel,
            self.hidden_humans,
            self.robot_goal, self.robot, self.heading_line, self.time_text, self.caption_text, self.title_text,
            self.outcome_text,
        ]  # fmt: skip
        for artist in self._dynamic:
            artist.set_animated(True)

    def _shifted(self, points: float) -> Transform:
        """The scene axes' fraction, shifted `points` up (negative: down): for the bands around the scene."""
        return self.ax.transAxes + ScaledTranslation(0.0, points / 72.0, self.fig.dpi_scale_trans)

    def _set_layout(self, layout: tuple) -> None:
        """Place the axes for this side-panel layout and rasterise the static layer.

        `layout` = (bar labels or None, ticks, threshold marks, panel title, human models shown, walls shown), all
        hashable."""
        panel_keys, ticks, marks, panel_title, models, walls = layout
        if self.annotate:
            self._add_legend(models, walls)
        self._add_model_legend(models)
        ticks, marks = dict(ticks or ()), dict(marks or ())
        side = bool(panel_keys) or self.annotate
        below, above = self._bands()
        self.ax.set_position((0.0, below, 1.0 - PANEL_FRACTION if side else 1.0, 1.0 - below - above))
        self.panel_ax.set_visible(bool(panel_keys))
        self.legend_ax.set_visible(self.annotate)
        # With a legend below them, the bars take the upper part of the column (under the top band).
        bottom, top = (below + 0.39, 1.0 - above - 0.01) if self.annotate else (0.05, 0.95)
        self.panel_ax.set_position((1.0 - PANEL_FRACTION + 0.02, bottom, PANEL_FRACTION - 0.05, top - bottom))
        self.legend_ax.set_position((1.0 - PANEL_FRACTION + 0.01, below, PANEL_FRACTION - 0.02, 0.36))
        for artist in [*self.panel_ax.patches, *self.panel_ax.texts, *self.panel_ax.lines]:
            artist.remove()
        self._panel_bars, self._panel_marks = [], []
        keys = panel_keys or ()
        rows = max(len(keys), PANEL_MIN_ROWS if not self.annotate else 1)
        self.panel_ax.set_ylim(rows + (0.6 if panel_title else 0.0), -0.6 if panel_title else 0.0)
        if panel_title:
            self.panel_ax.text(0.0, -0.1, panel_title, fontsize=8, fontweight="bold", ha="left", va="bottom")
        for i, key in enumerate(keys):  # grey track + label are static, the coloured bar moves
            y = i + 0.45
            self.panel_ax.add_patch(Rectangle((0.0, y), 1.0, 0.3, facecolor="#eeeeee", edgecolor="#bbbbbb",
                                              linewidth=0.5))
            self.panel_ax.text(0.0, y - 0.05, key, fontsize=8, ha="left", va="bottom")
            for position, label in ticks.get(key, ()):
                self.panel_ax.plot([position, position], [y + 0.3, y + 0.38], color="#777777", linewidth=0.6)
                self.panel_ax.text(position, y + 0.38, label, fontsize=6, ha="center", va="top", color="#555555")
            bar = Rectangle((0.0, y), 0.0, 0.3, facecolor=PANEL_BAR_COLOR, animated=True)
            self.panel_ax.add_patch(bar)
            self._panel_bars.append(bar)
            if key in marks:  # animated too: drawn over the moving bar
                (mark,) = self.panel_ax.plot([marks[key]] * 2, [y - 0.08, y + 0.38], color=THRESHOLD_COLOR,
                                             linewidth=2.0, animated=True)
                self._panel_marks.append(mark)
        if marks:
            self.panel_ax.text(0.0, len(keys) + 0.1, "red line: safety threshold", fontsize=7,
                               color=THRESHOLD_COLOR, ha="left", va="top")
        self.canvas.draw()  # animated artists are skipped
        self._background = self.canvas.copy_from_bbox(self.fig.bbox)
        self._layout = layout

    def _bands(self) -> tuple[float, float]:
        """The figure fractions kept free below and above the scene: the annotated bands (none without
        annotations, where the scene fills the image)."""
        if not self.annotate:
            return 0.0, 0.0
        height_pt = self.height / self.dpi * 72.0
        return BOTTOM_BAND_PT / height_pt, TOP_BAND_PT / height_pt

    # ------------------------------------------------------------------ per-frame updates
    def _update_scene(self, f: SceneFrame) -> None:
        pos = np.asarray(f.positions, dtype=float).reshape(-1, 2)
        n = len(pos)
        vel = np.asarray(f.velocities, dtype=float).reshape(n, 2)
        radii = np.broadcast_to(np.asarray(f.radii, dtype=float), (n,))
        goals = np.asarray(f.goals, dtype=float).reshape(n, 2)
        ps_radii = np.broadcast_to(np.asarray(f.personal_space_radii, dtype=float), (n,))
        active = np.broadcast_to(np.asarray(f.active, dtype=bool), (n,))
        humans = np.flatnonzero(active[1:]) + 1
        attentive = (np.ones(n, dtype=bool) if f.attentive is None
                     else np.broadcast_to(np.asarray(f.attentive, dtype=bool), (n,)))
        seeing, ignoring = humans[attentive[humans]], humans[~attentive[humans]]
        models = self._models_shown(f)

        # Humans: body discs (grey, dashed: ignores the robot), personal-space rings (radius r + r_prox), velocity
        # ticks (1 s ahead), goals.
        for discs, agents, diameters in ((self.humans, seeing, 2 * radii[seeing]),
                                         (self.inattentive, ignoring, 2 * radii[ignoring]),
                                         (self.personal_space, humans, 2 * (radii[humans] + ps_radii[humans]))):
            discs.set_offsets(pos[agents].reshape(-1, 2))
            discs.set_widths(diameters)
            discs.set_heights(diameters)
            discs.set_angles(np.zeros(len(agents)))
        # matplotlib's stubs want a sequence of segments; set_segments iterates an (N, 2, 2) array the same way
        self.human_vel.set_segments(np.stack([pos[humans], pos[humans] + vel[humans]], axis=1))  # type: ignore[arg-type]
        hidden = humans if f.hidden is None else humans[np.asarray(f.hidden, dtype=bool)[humans]]
        hidden = hidden if f.hidden is not None else humans[:0]
        self.hidden_humans.set_offsets(pos[hidden].reshape(-1, 2))
        self.hidden_humans.set_widths(2 * radii[hidden])
        self.hidden_humans.set_heights(2 * radii[hidden])
        self.hidden_humans.set_angles(np.zeros(len(hidden)))
        walls = [np.asarray(polygon, dtype=float) for polygon in (f.walls or ())]
        self.wall_blocks.set_verts([polygon for polygon in walls if len(polygon) >= 3])
        self.wall_lines.set_segments([polygon for polygon in walls if len(polygon) == 2])
        self.human_goals.set_data(goals[humans, 0], goals[humans, 1])
        self._update_models(f, models, pos, seeing, ignoring)
        route = np.zeros((0, 2)) if f.route is None else np.asarray(f.route, dtype=float).reshape(-1, 2)
        self.route_line.set_data(route[:, 0], route[:, 1])
        subgoal = np.zeros((0, 2)) if f.subgoal is None else np.asarray(f.subgoal, dtype=float).reshape(-1, 2)
        self.subgoal_mark.set_data(subgoal[:, 0], subgoal[:, 1])

        # Robot: disc, heading line, goal star.
        robot_on = n > 0 and bool(active[0])
        robot_color = f.robot_color or ROBOT_COLOR
        for artist in (self.robot, self.heading_line, self.robot_goal):
            artist.set_visible(robot_on)
        if robot_on:
            (x, y), r = pos[0], radii[0]
            self.robot.set_center((x, y))
            self.robot.set_radius(r)
            self.robot.set_facecolor(robot_color)
            tip_x = x + HEADING_LENGTH * r * np.cos(f.robot_heading)
            tip_y = y + HEADING_LENGTH * r * np.sin(f.robot_heading)
            self.heading_line.set_data([x, tip_x], [y, tip_y])
            self.robot_goal.set_data([goals[0, 0]], [goals[0, 1]])

        self._update_trails(f.trails, active, robot_color)
        self.time_text.set_text(f"t = {f.time:5.1f} s")
        self.caption_text.set_text(f.caption)
        self.caption_text.set_visible(bool(f.caption))
        self.title_text.set_text(f.title)
        self.title_text.set_visible(bool(f.title))
        self.time_text.set_visible(self.clock and not f.title)  # the title takes the top; a caption can carry the time
        self.outcome_text.set_text(f.outcome)
        self.outcome_text.set_visible(bool(f.outcome))
        if f.outcome and not self.annotate:  # annotated: in the band above the scene, never over it
            self._place_outcome(pos[0] if robot_on else None)

    @staticmethod
    def _models_shown(f: SceneFrame) -> tuple[str, ...]:
        """The models of the frame's active humans, in order of first slot, if any is not ORCA; else ()."""
        if f.models is None:
            return ()
        active = np.broadcast_to(np.asarray(f.active, dtype=bool), (len(f.models),))
        names = tuple(dict.fromkeys(str(f.models[i]) for i in range(1, len(f.models)) if active[i]))
        return names if any(name != "orca" for name in names) else ()

    def _update_models(self, f: SceneFrame, models: tuple[str, ...], pos: np.ndarray, seeing: np.ndarray,
                       ignoring: np.ndarray) -> None:
        """Each human's model: a mark at its centre and its disc's outline in the model's colour (none shown: the
        plain outlines)."""
        for name in models:
            if name not in self._model_marks:
                colour, marker, _ = model_style(name)
                (mark,) = self.ax.plot([], [], marker=marker, linestyle="", markersize=MODEL_MARK_SIZE,
                                       markerfacecolor=colour, markeredgecolor="white", markeredgewidth=0.8,
                                       animated=True)
                self._model_marks[name] = mark
                self._dynamic.insert(self._dynamic.index(self.human_vel), mark)  # over the discs
        names = np.asarray(f.models, dtype=object) if models else None  # (models: the frame has f.models)
        for name, mark in self._model_marks.items():
            if names is None:
                agents = np.zeros(0, dtype=int)
            else:
                agents = np.concatenate([seeing, ignoring])
                agents = agents[names[agents] == name]
            mark.set_data(pos[agents, 0], pos[agents, 1])
            mark.set_visible(len(agents) > 0)
        for discs, agents, plain in ((self.humans, seeing, HUMAN_EDGE_COLOR),
                                     (self.inattentive, ignoring, INATTENTIVE_EDGE_COLOR)):
            if names is not None:
                discs.set_edgecolor([model_style(str(names[a]))[0] for a in agents] or plain)
                discs.set_linewidth(1.6)
            else:
                discs.set_edgecolor(plain)
                discs.set_linewidth(0.8 if discs is self.humans else 1.2)

    def _place_outcome(self, robot: np.ndarray | None) -> None:
        """Put the outcome banner in the band of the scene farther from the robot (below the title, or above the
        caption): where an episode ends -- a collision above all -- stays visible under it."""
        if robot is None:
            robot_height = 0.5
        else:
            _, robot_height = self.ax.transAxes.inverted().transform(self.ax.transData.transform(robot))
        if robot_height < 0.5:
            self.outcome_text.set_position((0.5, OUTCOME_TOP))
            self.outcome_text.set_verticalalignment("top")
        else:
            self.outcome_text.set_position((0.5, OUTCOME_BOTTOM))
            self.outcome_text.set_verticalalignment("bottom")

    def _update_trails(self, trails: np.ndarray | None, active: np.ndarray, robot_color: str) -> None:
        """Trails as polylines fading from oldest to newest.

        The history is cut into at most `TRAIL_BANDS` chunks of constant alpha (one polyline per
        agent and chunk), far cheaper than one segment per time step.
        """
        if trails is None or len(trails) < 2:
            self.trail_lines.set_segments([])
            return
        trails = np.asarray(trails, dtype=float)
        agents = np.flatnonzero(active[: trails.shape[1]])
        edges = np.unique(np.linspace(0, len(trails) - 1, TRAIL_BANDS + 1).round().astype(int))
        lines, colors = [], []
        alphas = np.linspace(*TRAIL_ALPHA_RANGE, len(edges) - 1)
        for start, stop, alpha in zip(edges[:-1], edges[1:], alphas, strict=True):
            for a in agents:
                lines.append(trails[start : stop + 1, a])  # chunks share their end point: no gaps
                colors.append(to_rgba(robot_color if a == 0 else HUMAN_COLOR, alpha))
        self.trail_lines.set_segments(lines)
        self.trail_lines.set_color(colors)

    def _update_panel(self, panel: dict[str, float]) -> None:
        for bar, value in zip(self._panel_bars, panel.values(), strict=True):  # the layout's bars: one per key
            value = float(value)
            bar.set_width(float(np.clip(value, 0.0, 1.0)) if np.isfinite(value) else 0.0)

    # ------------------------------------------------------------------ public API
    def scene_box(self) -> tuple[float, float, float, float]:
        """(left, top, width, height) in pixels of the image of the square `[-extent, extent]^2` the scene is drawn
        in, as of the last rendered frame (rows count from the top)."""
        if self._background is None:
            self.canvas.draw()
        box = self.ax.get_window_extent(self.canvas.get_renderer())
        return box.x0, self.height - box.y1, box.width, box.height

    def render(self, frame: SceneFrame) -> np.ndarray:
        """Draw `frame` and return a new uint8 array of shape `(height, width, 3)`."""
        panel_keys = tuple(frame.side_panel) if frame.side_panel else None
        layout = (panel_keys, tuple((frame.panel_ticks or {}).items()), tuple((frame.panel_marks or {}).items()),
                  frame.panel_title, self._models_shown(frame), bool(frame.walls))
        if self._background is None or layout != self._layout:
            self._set_layout(layout)
        self._update_scene(frame)
        if frame.side_panel:  # (panel_keys)
            self._update_panel(frame.side_panel)

        self.canvas.restore_region(self._background)
        for artist in [*self._dynamic, *self._panel_bars, *self._panel_marks]:
            if artist.get_visible():
                self.fig.draw_artist(artist)
        image = np.asarray(self.canvas.buffer_rgba())[..., :3]
        if image.shape[:2] != (self.height, self.width):  # guard against dpi rounding: pad/crop
            out = np.full((self.height, self.width, 3), 255, dtype=np.uint8)
            h, w = min(self.height, image.shape[0]), min(self.width, image.shape[1])
            out[:h, :w] = image[:h, :w]
            return out
        return image.copy()

    def close(self) -> None:
        """Release the figure; the renderer must not be used afterwards."""
        self._background = None
        self.fig.clear()
