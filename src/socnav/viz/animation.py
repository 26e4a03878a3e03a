"""Turning rendered frames into files (GIF / MP4, written atomically) or an on-screen window.
`save_animation` for recordings, `HumanViewer` for Gymnasium's render_mode="human"."""

from __future__ import annotations

import importlib.util
import os
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from socnav.extras import install_hint

ALLOWED_EXTENSIONS = (".gif", ".mp4")


def _check_frames(frames: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Return the frames as uint8 (H, W, 3|4) arrays of one shape, or raise ValueError."""
    if len(frames) == 0:
        raise ValueError("save_animation needs at least one frame, got an empty sequence")
    arrays = [np.asarray(f) for f in frames]
    shape = arrays[0].shape
    if len(shape) != 3 or shape[2] not in (3, 4):
        raise ValueError(f"frames must be (height, width, 3|4) images, got shape {shape}")
    for i, a in enumerate(arrays):
        if a.shape != shape:
            raise ValueError(f"all frames must have the same shape: frame 0 is {shape}, frame {i} is {a.shape}")
        if a.dtype != np.uint8:
            raise ValueError(f"frames must be uint8, frame {i} is {a.dtype}")
    return arrays


#: Frames sampled (evenly over the animation) to build the GIF's one shared 256-colour palette.
PALETTE_SAMPLES = 8


def _write_gif(tmp: Path, frames: list[np.ndarray], fps: float) -> None:
    """One palette for the whole GIF, built from a few frames, then every frame mapped onto it without dithering:
    ten times faster than Pillow's per-frame median-cut quantisation (which dominated writing an animation), and
    a scene's colours do not flicker from frame to frame."""
    from PIL import Image

    images = [Image.fromarray(np.ascontiguousarray(frame[..., :3])) for frame in frames]
    picks = np.unique(np.linspace(0, len(images) - 1, min(PALETTE_SAMPLES, len(images))).round().astype(int))
    mosaic = Image.fromarray(np.concatenate([np.asarray(images[i]) for i in picks], axis=0))
    palette = mosaic.quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    indexed = [image.quantize(palette=palette, dither=Image.Dither.NONE) for image in images]
    indexed[0].save(tmp, format="GIF", save_all=True, append_images=indexed[1:], duration=1000.0 / fps, loop=0)


def _write_mp4(tmp: Path, frames: list[np.ndarray], fps: float) -> None:
    import imageio.v2 as iio2

    with iio2.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                         pixelformat="yuv420p", macro_block_size=1) as writer:
        for frame in frames:
            frame = frame[..., :3]
            pad_h, pad_w = frame.shape[0] % 2, frame.shape[1] % 2  # yuv420p needs even sizes
            if pad_h or pad_w:
                frame = np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
            # imageio types get_writer's result as its plugin base class; the FFMPEG (legacy) writer appends frames
            writer.append_data(frame)  # type: ignore[attr-defined]


def check_animation_path(path: str | Path) -> Path:
    """`path` as a Path if `save_animation` can write it: a .gif, or a .mp4 with imageio-ffmpeg installed. Call it
    before simulating an episode, so a missing package is reported before the work, not after.

    :raises ValueError: another extension. :raises ImportError: .mp4 without imageio-ffmpeg (with the install hint).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in ALLOWED_EXTENSIONS:
        raise ValueError(f"unsupported animation extension {path.suffix!r} for {path}; use one of {ALLOWED_EXTENSIONS}")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ImportError(
            f"writing .mp4 needs the optional package imageio-ffmpeg: {install_hint('video')} "
            "(or pip install imageio-ffmpeg), or save a .gif instead"
        )
    return path


def save_animation(frames: Sequence[np.ndarray], path: str | Path, fps: float = 8) -> Path:
    """Write `frames` (uint8 RGB arrays of one shape) to a `.gif` or `.mp4` file and return its path.

    The file is written to a temporary sibling (same extension, so the writer picks the right
    format) and moved into place with `os.replace`: an interrupted write never leaves a partial
    file at `path`. Parent directories are created. MP4 needs the optional `imageio-ffmpeg`
    package (`pip install socnav[video]`).
    """
    path = check_animation_path(path)
    suffix = path.suffix.lower()
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    arrays = _check_frames(frames)

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.tmp{suffix}")
    try:
        (_write_gif if suffix == ".gif" else _write_mp4)(tmp, arrays, float(fps))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # only left over when writing failed
    return path


class HumanViewer:
    """Show frames in a matplotlib window (for render_mode="human").

    pyplot is imported lazily, on the first `show`, so importing this module is safe on
    headless machines; there, matplotlib falls back to a non-interactive backend and `show`
    just updates an invisible figure.
    """

    def __init__(self, title: str = "socnav") -> None:
        self.title = title
        self._plt: Any = None
        self._fig: Any = None
        self._image: Any = None

    def show(self, frame: np.ndarray) -> None:
        """Display `frame` (H, W, 3 uint8), creating the window on first use or after it was closed."""
        if self._plt is None:
            import matplotlib.pyplot as plt

            self._plt = plt
        plt = self._plt
        if self._fig is None or not plt.fignum_exists(self._fig.number):
            plt.ion()
            height, width = frame.shape[:2]
            self._fig = plt.figure(self.title, figsize=(width / 100, height / 100), dpi=100)
            ax = self._fig.add_axes((0.0, 0.0, 1.0, 1.0))
            ax.set_axis_off()
            self._image = ax.imshow(frame)
        else:
            self._image.set_data(frame)
        self._fig.canvas.draw_idle()
        self._fig.canvas.flush_events()
        plt.pause(0.001)

    def close(self) -> None:
        """Close the window (no-op if it was never opened)."""
        if self._fig is not None:
            self._plt.close(self._fig)
            self._fig = self._image = None
