"""Off-screen rendering of one social-navigation scene into an RGB array.
One matplotlib figure (Agg canvas, no pyplot) is built once; per frame only the moving artists are redrawn."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib.artist import Artist
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection, LineCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

# Palette. The robot colour is used by no other artist except the robot's own trail.
ROBOT_COLOR = "#e4572e"
HUMAN_COLOR = "#3a6ea5"
HUMAN_EDGE_COLOR = "#1d3a57"
ROBOT_GOAL_COLOR = "#2a9d8f"
PANEL_BAR_COLOR = "#6c5b7b"

TRAIL_ALPHA_RANGE = (0.08, 0.6)  # oldest -> newest trail chunk
TRAIL_BANDS = 6  # number of alpha steps along a trail
HEADING_LENGTH = 1.4  # heading line length, in robot radii
PANEL_FRACTION = 0.3  # share of the image width given to the side panel when present
PANEL_MIN_ROWS = 8  # bars keep the same height for up to this many keys


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


class SceneRenderer:
    """Render `SceneFrame`s to uint8 RGB arrays of a fixed shape `(height, width, 3)`.

    - Axis limits are fixed to `[-extent, extent]` with equal aspect, so frames are comparable;
      scene point (x, y) lands at pixel column `(x + extent) / (2 * extent) * width` and row
      `(extent - y) / (2 * extent) * height` (square image, no side panel).
    - The image size never changes: when a frame has a `side_panel`, the scene is drawn in the
      left `1 - PANEL_FRACTION` of the image and the bars fill the right part. Frames with and
      without a panel can therefore be mixed in one animation.
    - Speed: the static layer (grid, border, panel tracks and labels) is rasterised once per
      layout and restored from a pixel cache; only the moving artists are drawn per frame.
    """

    def __init__(self, width: int = 480, height: int = 480, extent: float = 8.5, dpi: int = 80):
        if min(width, height, extent, dpi) <= 0:
            raise ValueError("width, height, extent and dpi must be positive")
        self.width, self.height, self.extent, self.dpi = int(width), int(height), float(extent), int(dpi)

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

        self._add_static_scene()
        self._add_dynamic_scene()
        self._panel_bars: list[Rectangle] = []
        self._layout: tuple[str, ...] | None = None  # side-panel keys of the cached background
        self._background = None  # pixel cache of the static layer

    # ------------------------------------------------------------------ setup
    def _add_static_scene(self) -> None:
        """Light 1 m grid, axes through the origin and the arena border."""
        e = self.extent
        ticks = np.arange(np.ceil(-e), np.floor(e) + 1)
        grid = [[(t, -e), (t, e)] for t in ticks] + [[(-e, t), (e, t)] for t in ticks]
        self.ax.add_collection(LineCollection(grid, colors="#eeeeee", linewidths=0.6, zorder=0))
        origin = [[(0, -e), (0, e)], [(-e, 0), (e, 0)]]
        self.ax.add_collection(LineCollection(origin, colors="#d8d8d8", linewidths=0.8, zorder=0))
        self.ax.add_patch(Rectangle((-e, -e), 2 * e, 2 * e, fill=False, edgecolor="#999999", linewidth=1.0))

    def _add_dynamic_scene(self) -> None:
        """Create every moving artist once (animated, so it is left out of the static layer)."""
        ax = self.ax

        def discs(**kw) -> EllipseCollection:
            empty = np.zeros((0, 2))
            return ax.add_collection(
                EllipseCollection([], [], [], units="xy", offsets=empty, offset_transform=ax.transData, **kw)
            )

        self.trail_lines = ax.add_collection(LineCollection([], linewidths=1.5, joinstyle="round"))
        self.personal_space = discs(facecolors="none", edgecolors=to_rgba(HUMAN_COLOR, 0.45),
                                    linestyles="--", linewidths=0.9)
        (self.human_goals,) = ax.plot([], [], "x", color=HUMAN_COLOR, alpha=0.35, markersize=4)
        self.humans = discs(facecolors=HUMAN_COLOR, edgecolors=HUMAN_EDGE_COLOR, linewidths=0.8)
        self.human_vel = ax.add_collection(LineCollection([], colors=to_rgba(HUMAN_EDGE_COLOR, 0.5), linewidths=1.0))
        (self.robot_goal,) = ax.plot([], [], "*", color=ROBOT_GOAL_COLOR, markeredgecolor="#14524b", markersize=15)
        self.robot = ax.add_patch(Circle((0.0, 0.0), 0.3, facecolor=ROBOT_COLOR, edgecolor="black", linewidth=1.0))
        (self.heading_line,) = ax.plot([], [], color="black", linewidth=2.0, solid_capstyle="round")
        box = {"boxstyle": "round,pad=0.2", "facecolor": "white", "alpha": 0.7, "edgecolor": "none"}
        self.time_text = ax.text(0.02, 0.98, "", transform=ax.transAxes, ha="left", va="top", fontsize=9, bbox=box)
        self.caption_text = ax.text(0.02, 0.02, "", transform=ax.transAxes, ha="left", va="bottom", fontsize=9,
                                    bbox=box)
        # Drawn in this order (back to front).
        self._dynamic: list[Artist] = [
            self.trail_lines, self.personal_space, self.human_goals, self.humans, self.human_vel,
            self.robot_goal, self.robot, self.heading_line, self.time_text, self.caption_text,
        ]  # fmt: skip
        for artist in self._dynamic:
            artist.set_animated(True)

    def _set_layout(self, panel_keys: tuple[str, ...] | None) -> None:
        """Place the axes for this side-panel layout and rasterise the static layer."""
        self.ax.set_position((0.0, 0.0, 1.0 - PANEL_FRACTION, 1.0) if panel_keys else (0.0, 0.0, 1.0, 1.0))
        self.panel_ax.set_visible(bool(panel_keys))
        for artist in [*self.panel_ax.patches, *self.panel_ax.texts]:
            artist.remove()
        self._panel_bars = []
        keys = panel_keys or ()
        self.panel_ax.set_ylim(max(len(keys), PANEL_MIN_ROWS), 0.0)  # row i spans [i, i+1], first key on top
        for i, key in enumerate(keys):  # grey track + label are static, the coloured bar moves
            y = i + 0.45
            self.panel_ax.add_patch(Rectangle((0.0, y), 1.0, 0.4, facecolor="#eeeeee", edgecolor="#bbbbbb",
                                              linewidth=0.5))
            self.panel_ax.text(0.0, y - 0.05, key, fontsize=8, ha="left", va="bottom")
            bar = self.panel_ax.add_patch(Rectangle((0.0, y), 0.0, 0.4, facecolor=PANEL_BAR_COLOR, animated=True))
            self._panel_bars.append(bar)
        self.canvas.draw()  # animated artists are skipped
        self._background = self.canvas.copy_from_bbox(self.fig.bbox)
        self._layout = panel_keys

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

        # Humans: body discs, personal-space rings (radius r + r_prox), velocity ticks (1 s ahead), goals.
        zeros = np.zeros(len(humans))
        for discs, diameters in ((self.humans, 2 * radii[humans]),
                                 (self.personal_space, 2 * (radii[humans] + ps_radii[humans]))):
            discs.set_offsets(pos[humans])
            discs.set_widths(diameters)
            discs.set_heights(diameters)
            discs.set_angles(zeros)
        self.human_vel.set_segments(np.stack([pos[humans], pos[humans] + vel[humans]], axis=1))
        self.human_goals.set_data(goals[humans, 0], goals[humans, 1])

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
        for start, stop, alpha in zip(edges[:-1], edges[1:], np.linspace(*TRAIL_ALPHA_RANGE, len(edges) - 1)):
            for a in agents:
                lines.append(trails[start : stop + 1, a])  # chunks share their end point: no gaps
                colors.append(to_rgba(robot_color if a == 0 else HUMAN_COLOR, alpha))
        self.trail_lines.set_segments(lines)
        self.trail_lines.set_color(colors)

    def _update_panel(self, panel: dict[str, float]) -> None:
        for bar, value in zip(self._panel_bars, panel.values()):
            value = float(value)
            bar.set_width(float(np.clip(value, 0.0, 1.0)) if np.isfinite(value) else 0.0)

    # ------------------------------------------------------------------ public API
    def render(self, frame: SceneFrame) -> np.ndarray:
        """Draw `frame` and return a new uint8 array of shape `(height, width, 3)`."""
        panel_keys = tuple(frame.side_panel) if frame.side_panel else None
        if self._background is None or panel_keys != self._layout:
            self._set_layout(panel_keys)
        self._update_scene(frame)
        if panel_keys:
            self._update_panel(frame.side_panel)

        self.canvas.restore_region(self._background)
        for artist in [*self._dynamic, *self._panel_bars]:
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
