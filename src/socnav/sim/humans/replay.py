"""Replayed humans (``humans.model: replay`` with ``scenario: replay``): pedestrians follow recorded trajectories and
do not react to anyone, the robot included (as in SocNavBench).

The recordings are the pedestrian-trajectory text files of ETH/UCY as TrajNet and Social-GAN distribute them: one
observation per line, ``frame_id ped_id x y`` separated by whitespace (tabs or spaces), positions in metres,
samples at 2.5 Hz (frame ids step by 10 in those files; the step is inferred per file). `read_trajectories`
reads one file with errors naming the file and the line; `interpolate_tracks` puts every pedestrian on the env's time
grid (linear, and a pedestrian exists only between its first and last frame); `load_replay` builds the flat arrays
the world's kernels read, once per process and set of files (`ReplayScenes`).

A replayed episode (`ReplayScenes.plan`, drawn by the ``replay`` scenario from the episode's generator) picks a file,
a start step within it and the robot's path: a straight line through the centre of the file's bounding box (the
world's origin: every file is centred on it) at ``humans.replay.robot_distance``, in a direction drawn per
episode. `ReplayHumans` then moves each slot's pedestrian from recorded position to recorded position; pedestrians
that enter the scene take a free slot, those that leave free theirs (the slot becomes inactive padding).
"""

from __future__ import annotations

import bisect
import functools
import io
import math
import re
import warnings
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numba
import numpy as np

from socnav.sim.humans.base import Crowd

#: Files larger than this are refused from their size, before they are read (the ETH/UCY files are below 1 MB). A
#: file is parsed in blocks of ~1 MB: reading one costs about its size plus its rows (32 bytes each), docs/limits.md.
MAX_FILE_BYTES = 64 << 20
#: All the trajectory files of a config together, from their sizes, before any is read.
MAX_TOTAL_BYTES = 256 << 20
#: The longest line (a row is ~25 bytes; a file of one huge line -- NUL bytes, say -- is no trajectory file).
MAX_LINE_BYTES = 1 << 16
#: Lines of one file (a data row is ~20-30 bytes: a full-size file holds 2-3 million), counted before parsing.
MAX_LINES = 4_000_000
#: Pedestrians in one file (ETH/UCY: at most a few hundred); each costs two small arrays.
MAX_PEDESTRIANS = 100_000
#: Interpolated positions of all the files of a config together (16 bytes each): beyond this, a longer time step
#: or fewer files. Counted from each pedestrian's first and last frame before anything is interpolated.
MAX_SAMPLES = 50_000_000
#: The env steps of a recording: a step index beyond this cannot be an exact integer in float64.
MAX_STEP = 2**53
#: Frame ids must be exact integers in float64.
MAX_FRAME_ID = 2**53
COLUMNS = ("frame_id", "ped_id", "x", "y")
#: Attempts at drawing an episode whose robot start is clear of the pedestrians present then.
MAX_TRIES = 200
#: Metres between the robot's start and any pedestrian present at the episode's first step.
START_CLEARANCE = 1.0
_EPS = 1e-9
#: The blocks a file is parsed in (cut at a line's end): numpy's parser per block, the line-by-line scan only for a
#: block it does not read (which names the bad line), so that neither costs more than a block beyond the rows.
_BLOCK_BYTES = 1 << 20
_LONG_LINE = re.compile(rb"[^\n]{%d}" % (MAX_LINE_BYTES + 1))


class TrajectoryFileError(ValueError):
    """A trajectory file cannot be used; the message names the file and, for its content, the line."""


# ---------------------------------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Recording:
    """One trajectory file as read: each pedestrian's track, pedestrians in the order they first appear.

    A track's samples are the recording's sample indices ``(frame_id - first_frame) / frame_step`` (increasing);
    its time in seconds is ``sample / sample_rate``.
    """

    path: str
    frame_step: int
    first_frame: int
    ids: np.ndarray  # (P,) pedestrian ids as written in the file
    samples: tuple[np.ndarray, ...]  # per pedestrian (m,) float64
    positions: tuple[np.ndarray, ...]  # per pedestrian (m, 2) metres

    @property
    def n_rows(self) -> int:
        return sum(len(samples) for samples in self.samples)


def _fail(path: Path, line: int, message: str) -> NoReturn:
    raise TrajectoryFileError(f"trajectory file {path} line {line}: {message}")


def _data_rows(text: str, first_line: int = 1):
    """(line number, content) of every line holding data: '#' starts a comment, blank lines are skipped."""
    for number, line in enumerate(text.split("\n"), first_line):
        content = line.split("#", 1)[0].strip()
        if content:
            yield number, content


def _scan(text: str, path: Path, first_line: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The (rows, 4) values and the line number of each row, line by line: raises on the first bad line."""
    rows, lines = [], []
    for number, content in _data_rows(text, first_line):
        tokens = content.split()
        if len(tokens) != len(COLUMNS):
            shown = content if len(content) <= 80 else content[:77] + "..."
            _fail(path, number, f"expected {len(COLUMNS)} columns (frame_id ped_id x y), found {len(tokens)}: "
                                f"{shown!r}")
        values = []
        for column, token in zip(COLUMNS, tokens, strict=True):
            shown = token if len(token) <= 40 else token[:37] + "..."
            try:
                value = float(token)
            except ValueError:
                _fail(path, number, f"{column} is not a number: {shown!r}")
            if not math.isfinite(value):
                _fail(path, number, f"{column} is not a finite number: {shown!r}")
            values.append(value)
        rows.append(values)
        lines.append(number)
    return np.asarray(rows, dtype=np.float64).reshape(-1, len(COLUMNS)), np.asarray(lines, dtype=np.int64)


def _file_size(path: Path, limit: int = 0) -> int:
    """The size of the trajectory file `path` (0 when it cannot be stat'ed: the reader reports that), refused over
    `limit` (default `MAX_FILE_BYTES`) before anything is read."""
    limit = limit or MAX_FILE_BYTES
    try:
        size = path.stat().st_size
    except OSError:
        return 0
    if size > limit and path.is_file():
        raise TrajectoryFileError(f"trajectory file {path} is larger than {limit:,} bytes, the most socnav reads "
                                  f"from such a file (it has {size:,})")
    return size


def check_total_size(paths: list[str] | list[Path] | tuple[str, ...]) -> None:
    """Raise `TrajectoryFileError` when the files together are larger than `MAX_TOTAL_BYTES` (from their sizes)."""
    sizes = {}
    for name in paths:
        path = Path(name)
        with_size = _file_size(path)
        sizes[str(path.resolve()) if with_size else str(path)] = with_size  # a file listed twice is read once
    total = sum(sizes.values())
    if total > MAX_TOTAL_BYTES:
        raise TrajectoryFileError(f"trajectory files {short_list(list(sizes))} hold {total:,} bytes together, more "
                                  f"than the {MAX_TOTAL_BYTES:,} socnav reads for one config")


def short_list(names: list[str], most: int = 3) -> str:
    """'a, b, c and 7 more'."""
    shown = ", ".join(names[:most])
    return shown if len(names) <= most else f"{shown} and {len(names) - most} more"


def _check_text(raw: bytes, path: Path) -> None:
    """Refuse bytes that are not UTF-8 text (naming the line), of more than `MAX_LINES` lines, or holding a line over
    `MAX_LINE_BYTES`."""
    decoder_start = 0
    while decoder_start < len(raw):  # block by block: no second copy of the whole file
        end = raw.find(b"\n", decoder_start + _BLOCK_BYTES)
        end = len(raw) if end < 0 else end + 1
        try:
            str(raw[decoder_start:end], "utf-8")
        except UnicodeDecodeError as exc:
            line = raw[: decoder_start + exc.start].count(b"\n") + 1
            _fail(path, line, "not UTF-8 text (a binary file?)")
        decoder_start = end
    lines = raw.count(b"\n") + (0 if raw.endswith(b"\n") else 1)
    if lines > MAX_LINES:
        raise TrajectoryFileError(f"trajectory file {path} has {lines:,} lines, more than the {MAX_LINES:,} socnav "
                                  "reads from one file (split it)")
    long = _LONG_LINE.search(raw)
    if long is not None:
        end = raw.find(b"\n", long.start())
        length = (len(raw) if end < 0 else end) - long.start()
        _fail(path, raw[: long.start()].count(b"\n") + 1, f"{length:,} bytes long, longer than the {MAX_LINE_BYTES:,} "
                                                          "a line of a trajectory file may be (not a trajectory file?)")


@dataclass(frozen=True)
class _Block:
    """Where a block of the file lies (bytes, first line) and its first data row."""

    start: int
    end: int
    first_line: int
    first_row: int


def _parse_block(chunk: bytes, path: Path, first_line: int) -> np.ndarray:
    """The (rows, 4) values of one block. Fast path: numpy's C parser; any doubt (a parse error, a non-finite
    value, another number of columns) falls back to the line-by-line scan of the block, which finds and names the
    bad line (or reads what numpy does not, e.g. ``1_000``)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            parsed = np.loadtxt(io.BytesIO(chunk), dtype=np.float64, comments="#", ndmin=2, encoding="utf-8")
        if parsed.size == 0:  # blank lines and comments only (as the scan would find)
            return np.zeros((0, len(COLUMNS)))
        if parsed.shape[1] == len(COLUMNS) and np.isfinite(parsed).all():
            return parsed
    except ValueError:
        pass
    return _scan(chunk.decode("utf-8"), path, first_line)[0]


def _parse(raw: bytes, path: Path) -> tuple[np.ndarray, list[_Block]]:
    """The (rows, 4) values of the file, parsed block by block, and where each block lies (for `_line_of`)."""
    blocks, values = [], []
    start, line, rows = 0, 1, 0
    while start < len(raw):
        end = raw.find(b"\n", start + _BLOCK_BYTES)
        end = len(raw) if end < 0 else end + 1
        chunk = raw[start:end]
        parsed = _parse_block(chunk, path, line)
        blocks.append(_Block(start, end, line, rows))
        if len(parsed):
            values.append(parsed)
        rows += len(parsed)
        line += chunk.count(b"\n")
        start = end
    data = values[0] if len(values) == 1 else np.concatenate(values) if values else np.zeros((0, len(COLUMNS)))
    return data, blocks


def _line_of(raw: bytes, blocks: list[_Block], row: int) -> int:
    """The line number of data row `row` (its block's lines only are walked)."""
    block = blocks[bisect.bisect_right([b.first_row for b in blocks], row) - 1]
    text = raw[block.start:block.end].decode("utf-8")
    for index, (number, _) in enumerate(_data_rows(text, block.first_line)):
        if index == row - block.first_row:
            return number
    raise AssertionError(f"row {row} not found")  # cannot happen: the block's rows are its data lines


def read_trajectories(path: str | Path, frame_step: int | None = None) -> Recording:
    """Read one ``frame_id ped_id x y`` file (ETH/UCY as TrajNet / Social-GAN distribute them).

    Whitespace-separated (tabs or spaces), one observation per line; blank lines and ``#`` comments are skipped.
    Frame ids must be whole numbers; `frame_step` (frame ids between two samples) defaults to the greatest common
    divisor of the steps between the file's distinct frame ids (10 in ETH/UCY). Each pedestrian's frames must
    increase down the file.

    Bounded before the expensive steps: the file's size (`MAX_FILE_BYTES`, from the filesystem, before reading),
    its lines (`MAX_LINES`, `MAX_LINE_BYTES`) before parsing, its pedestrians (`MAX_PEDESTRIANS`) before their
    tracks are built.

    :raises TrajectoryFileError: naming the file, and the line for a bad line: a wrong number of columns, a value
        that is not a number or not finite, a fractional frame id, a pedestrian whose frames do not increase, a
        line too long; or an empty, unreadable, non-text or too large file, or one of too many pedestrians.
    """
    from socnav.io import UntrustedInputError, read_bounded

    path = Path(path)
    _file_size(path)
    try:
        raw = read_bounded(path, MAX_FILE_BYTES)
    except UntrustedInputError as exc:
        raise TrajectoryFileError(f"trajectory file {exc}") from None
    except OSError as exc:
        raise TrajectoryFileError(f"trajectory file {path} cannot be read: {exc.strerror or exc}") from None
    _check_text(raw, path)
    data, blocks = _parse(raw, path)
    if len(data) == 0:
        raise TrajectoryFileError(f"trajectory file {path} holds no trajectories (no line of frame_id ped_id x y)")

    def line_of(row: int) -> int:
        return _line_of(raw, blocks, row)

    frames, ids, positions = data[:, 0], data[:, 1], data[:, 2:4]
    bad = np.flatnonzero((frames != np.round(frames)) | (np.abs(frames) > MAX_FRAME_ID))
    if bad.size:
        row = int(bad[0])
        _fail(path, line_of(row), f"frame_id {float(frames[row])!r} is not a whole number (of at most 2^53)")

    # Each pedestrian's frames must increase down the file: sort by pedestrian, keeping the file's order within one.
    order = np.lexsort((np.arange(len(ids)), ids))
    same = ids[order[1:]] == ids[order[:-1]]
    backwards = same & (frames[order[1:]] <= frames[order[:-1]])
    if backwards.any():
        rows, previous = order[1:][backwards], order[:-1][backwards]
        k = int(np.argmin(rows))
        row, before = int(rows[k]), int(previous[k])
        _fail(path, line_of(row), f"frame {frames[row]:g} of pedestrian {ids[row]:g} does not come after its frame "
                                  f"{frames[before]:g} on line {line_of(before)} (each pedestrian's frames must "
                                  "increase down the file)")

    pedestrians = 1 + int(np.count_nonzero(~same))
    if pedestrians > MAX_PEDESTRIANS:
        raise TrajectoryFileError(f"trajectory file {path} holds {pedestrians:,} pedestrians, more than the "
                                  f"{MAX_PEDESTRIANS:,} socnav reads from one file (split it)")
    integer_frames = frames.astype(np.int64)
    first_frame = int(integer_frames.min())
    if frame_step is None:
        distinct = np.unique(integer_frames)
        frame_step = int(np.gcd.reduce(np.diff(distinct))) if len(distinct) > 1 else 1
    starts = np.flatnonzero(np.r_[True, ~same])  # first sorted row of each pedestrian
    ends = np.r_[starts[1:], len(order)]
    first_rows = order[starts]  # each pedestrian's first line
    by_appearance = np.argsort(first_rows, kind="stable")
    samples, tracks = [], []
    for pedestrian in by_appearance:
        rows = order[starts[pedestrian]:ends[pedestrian]]
        samples.append((integer_frames[rows] - first_frame) / frame_step)
        tracks.append(positions[rows].copy())
    return Recording(path=str(path), frame_step=int(frame_step), first_frame=first_frame,
                     ids=ids[first_rows[by_appearance]].copy(), samples=tuple(samples), positions=tuple(tracks))


def check_trajectory_file(path: str | Path) -> None:
    """Raise `TrajectoryFileError` if `read_trajectories` would refuse `path`; a file that passed is not read again
    while its size and modification time stay the same (the config is validated often, the file read once)."""
    stat = Path(path).stat()
    _checked(str(path), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=256)
def _checked(path: str, size: int, mtime_ns: int) -> None:
    read_trajectories(path)


def _track_steps(recording: Recording, ratio: float) -> list[tuple[int, int]]:
    """Each pedestrian's first step and number of steps on the grid of `ratio` recorded samples per step, from its
    first and last sample only (nothing allocated per step).

    :raises TrajectoryFileError: a step beyond `MAX_STEP` (a tiny time step or sample rate, or frame ids far apart).
    """
    spans = []
    for samples in recording.samples:
        with np.errstate(over="ignore"):  # an overflow is refused below
            low, high = samples[0] / ratio - _EPS, samples[-1] / ratio + _EPS
        if not high <= MAX_STEP:  # also inf and NaN
            raise TrajectoryFileError(
                f"trajectory file {recording.path}: a pedestrian's last frame lies {float(samples[-1]):g} samples "
                f"after the first frame, step {float(high):g} at {ratio:g} samples per step; socnav counts at most "
                f"{MAX_STEP:,} steps (a longer time_step, or the file's sample_rate / frame_step?)")
        first, last = math.ceil(low), math.floor(high)
        spans.append((first, max(last - first + 1, 0)))
    return spans


def count_positions(recordings: list[Recording], time_step: float, sample_rate: float) -> int:
    """How many positions `interpolate_tracks` gives the recordings at `time_step`, without interpolating."""
    ratio = time_step * sample_rate
    return sum(count for recording in recordings for _, count in _track_steps(recording, ratio))


def _check_positions(recordings: list[Recording], time_step: float, sample_rate: float) -> None:
    total = count_positions(recordings, time_step, sample_rate)
    if total > MAX_SAMPLES:
        raise TrajectoryFileError(
            f"trajectory files {short_list([r.path for r in recordings])} give {total:,} positions at time_step "
            f"{time_step:g} s; socnav keeps at most {MAX_SAMPLES:,} (fewer or shorter files, or a longer time_step)")


def interpolate_tracks(recording: Recording, time_step: float, sample_rate: float
                       ) -> list[tuple[int, np.ndarray]]:
    """Every pedestrian of `recording` on the time grid t = k `time_step` (t = 0 at the file's first frame): its
    first step k0 and its positions (n, 2) at steps k0 .. k0 + n - 1, linear between recorded samples.

    A pedestrian exists from its first to its last frame only: the steps whose time lies in that interval (none for
    a pedestrian seen between two steps, which then gets an empty track). A gap in its frames is bridged linearly.

    :raises TrajectoryFileError: more than `MAX_SAMPLES` positions (counted before any is computed).
    """
    _check_positions([recording], time_step, sample_rate)
    ratio = time_step * sample_rate  # recorded samples per env step
    return [(first, _interpolate(samples, positions, first, count, ratio))
            for (first, count), samples, positions in zip(_track_steps(recording, ratio), recording.samples,
                                                          recording.positions, strict=True)]


def _interpolate(samples: np.ndarray, positions: np.ndarray, first: int, count: int, ratio: float) -> np.ndarray:
    """One track's (count, 2) positions at steps first .. first + count - 1."""
    steps = np.arange(first, first + count)
    at = np.clip(steps * ratio, samples[0], samples[-1])
    xy = np.stack([np.interp(at, samples, positions[:, 0]), np.interp(at, samples, positions[:, 1])], axis=1)
    return xy.reshape(-1, 2)


def check_positions(settings: Any, time_step: float) -> None:
    """Raise `TrajectoryFileError` if the files of ``settings`` (a `socnav.config.ReplayConfig`) would give more than
    `MAX_SAMPLES` positions at `time_step`, or steps beyond `MAX_STEP` -- what `load_replay` refuses -- without
    interpolating anything (for the config's validation; cached while the files stay the same)."""
    files = []
    for name in settings.files:
        status = Path(name).stat()
        files.append((str(name), status.st_size, status.st_mtime_ns))
    _positions(tuple(files), float(settings.sample_rate),
               None if settings.frame_step is None else int(settings.frame_step), float(time_step))


@functools.lru_cache(maxsize=64)
def _positions(files: tuple[tuple[str, int, int], ...], sample_rate: float, frame_step: int | None,
               time_step: float) -> int:
    check_total_size([name for name, _, _ in files])
    total, counted = 0, []
    for name, _, _ in files:  # one recording at a time: only the counts are kept
        recording = read_trajectories(name, frame_step)
        total += count_positions([recording], time_step, sample_rate)
        counted.append(name)
        if total > MAX_SAMPLES:
            break
    if total > MAX_SAMPLES:
        raise TrajectoryFileError(
            f"trajectory files {short_list(counted)} give {total:,} positions at time_step {time_step:g} s; socnav "
            f"keeps at most {MAX_SAMPLES:,} (fewer or shorter files, or a longer time_step)")
    return total


# ---------------------------------------------------------------------------------------------------- the scenes


@numba.njit(cache=True)
def _segment_distance(px, py, ax, ay, bx, by):
    """Distance from point p to the segment a-b."""
    dx, dy = bx - ax, by - ay
    length_sq = dx * dx + dy * dy
    s = 0.0
    if length_sq > 0.0:
        s = min(max(((px - ax) * dx + (py - ay) * dy) / length_sq, 0.0), 1.0)
    return math.hypot(px - ax - s * dx, py - ay - s * dy)


@dataclass(frozen=True)
class ReplayStart:
    """The scenario's plan of one replayed episode: where it starts in which file, the robot's path and the
    pedestrian in each agent slot at the start (-1: none; slot 0 is the robot)."""

    scenes: ReplayScenes
    scene: int
    step: int  # the scene's step at the episode's start
    start: np.ndarray  # (2,) robot start
    goal: np.ndarray  # (2,) robot goal
    pedestrians: np.ndarray  # (n_slots,) int64 global pedestrian index per slot
    positions: np.ndarray  # (n_slots, 2)
    goals: np.ndarray  # (n_slots, 2): each pedestrian's last recorded position


@dataclass(frozen=True)
class ReplayScenes:
    """The recorded pedestrians of one or more files on the env's time grid, as flat arrays for the kernels.

    Scene s (file s) holds pedestrians ``scene_lo[s] .. scene_hi[s] - 1``, sorted by first step (then by first
    appearance in the file); pedestrian p exists at scene steps ``first[p] .. first[p] + count[p] - 1`` at
    positions ``samples[offset[p] + k - first[p]]``. Positions are centred: each file's bounding-box centre
    (`centres`) is subtracted, so the world's origin is the centre of every scene.
    """

    files: tuple[str, ...]
    time_step: float
    centres: np.ndarray  # (S, 2) metres, in the file's coordinates
    half_sizes: np.ndarray  # (S, 2) half the bounding box
    scene_steps: np.ndarray  # (S,) steps from the file's first frame to its last, + 1
    scene_lo: np.ndarray  # (S,)
    scene_hi: np.ndarray  # (S,)
    ids: np.ndarray  # (P,) pedestrian ids as in the files
    first: np.ndarray  # (P,) int64
    count: np.ndarray  # (P,) int64
    offset: np.ndarray  # (P,) int64
    samples: np.ndarray  # (M, 2)

    @property
    def n_pedestrians(self) -> int:
        return len(self.first)

    def track(self, scene: int, pedestrian_id: float) -> tuple[int, np.ndarray]:
        """(first step, centred positions (n, 2)) of the pedestrian `pedestrian_id` of file `scene`."""
        lo, hi = int(self.scene_lo[scene]), int(self.scene_hi[scene])
        matches = np.flatnonzero(self.ids[lo:hi] == pedestrian_id)
        if matches.size == 0:
            raise KeyError(f"no pedestrian {pedestrian_id:g} in {self.files[scene]} (or it never meets a time step)")
        p = lo + int(matches[0])
        return int(self.first[p]), self.samples[self.offset[p]:self.offset[p] + self.count[p]]

    def present(self, scene: int, step: int) -> np.ndarray:
        """Global indices of the pedestrians of `scene` that exist at `step`, in the scene's order."""
        lo, hi = int(self.scene_lo[scene]), int(self.scene_hi[scene])
        first, count = self.first[lo:hi], self.count[lo:hi]
        return lo + np.flatnonzero((first <= step) & (step < first + count))

    def position(self, pedestrian: int, step: int) -> np.ndarray:
        return self.samples[self.offset[pedestrian] + step - self.first[pedestrian]]

    def last_position(self, pedestrian: int) -> np.ndarray:
        return self.samples[self.offset[pedestrian] + self.count[pedestrian] - 1]

    def plan(self, rng: np.random.Generator, n_humans: int, distance: float, horizon: int) -> ReplayStart:
        """Draw one episode from `rng`: a file (weighted by its length, so every recorded moment is equally likely),
        a start step leaving `horizon` steps of recording where the file is long enough, and the robot's direction
        through the scene's centre (start and goal `distance` apart), redrawn (at most `MAX_TRIES` times) until no
        pedestrian present at the start step is within `START_CLEARANCE` of the robot's start.

        With more than `n_humans` pedestrians present at the start, those closest to the robot's path (the segment
        from start to goal) take the slots.
        """
        weights = self.scene_steps / self.scene_steps.sum()
        for _ in range(MAX_TRIES):
            scene = int(rng.choice(len(weights), p=weights)) if len(weights) > 1 else 0
            latest = max(int(self.scene_steps[scene]) - 1 - horizon, 0)
            step = int(rng.integers(0, latest + 1))
            angle = rng.uniform(0.0, 2.0 * math.pi)
            direction = np.array((math.cos(angle), math.sin(angle)))
            start, goal = -0.5 * distance * direction, 0.5 * distance * direction
            present = self.present(scene, step)
            where = np.array([self.position(p, step) for p in present]).reshape(-1, 2)
            if not len(present) or np.hypot(*(where - start).T).min() >= START_CLEARANCE:
                break
        path_distance = np.array([_segment_distance(x, y, start[0], start[1], goal[0], goal[1]) for x, y in where])
        chosen = np.argsort(path_distance, kind="stable")[:n_humans]
        pedestrians = np.full(1 + n_humans, -1, dtype=np.int64)
        positions, goals = np.zeros((1 + n_humans, 2)), np.zeros((1 + n_humans, 2))
        for slot, k in enumerate(np.sort(chosen), start=1):  # slots in the scene's order
            pedestrians[slot] = present[k]
            positions[slot] = where[k]
            goals[slot] = self.last_position(present[k])
        return ReplayStart(scenes=self, scene=scene, step=step, start=start, goal=goal, pedestrians=pedestrians,
                           positions=positions, goals=goals)


def build_scenes(recordings: list[Recording], time_step: float, sample_rate: float) -> ReplayScenes:
    """`ReplayScenes` of `recordings` (one scene each) on the grid of `time_step` (`interpolate_tracks`).

    The positions are counted first (`MAX_SAMPLES`, from each pedestrian's first and last frame), then written
    straight into the one array the kernels read: the peak is that array (16 bytes a position) plus one track.
    """
    if not recordings:
        raise TrajectoryFileError("no trajectory files: set humans.replay.files")
    ratio = time_step * sample_rate  # recorded samples per env step
    per_scene = [_track_steps(recording, ratio) for recording in recordings]
    total = sum(count for spans in per_scene for _, count in spans)
    if total > MAX_SAMPLES:
        raise TrajectoryFileError(
            f"trajectory files {short_list([r.path for r in recordings])} give {total:,} positions at time_step "
            f"{time_step:g} s; socnav keeps at most {MAX_SAMPLES:,} (fewer or shorter files, or a longer time_step)")
    centres: list[np.ndarray] = []
    half_sizes: list[np.ndarray] = []
    scene_steps: list[int] = []
    scene_lo: list[int] = []
    scene_hi: list[int] = []
    ids: list[float] = []
    first: list[int] = []
    count: list[int] = []
    samples = np.empty((total, 2))
    filled = 0
    for recording, spans in zip(recordings, per_scene, strict=True):
        everything = np.concatenate(recording.positions)
        low, high = everything.min(axis=0), everything.max(axis=0)
        del everything
        centre = (low + high) / 2.0
        centres.append(centre)
        half_sizes.append((high - low) / 2.0)
        kept = [(k0, n, index) for index, (k0, n) in enumerate(spans) if n]
        kept.sort(key=lambda item: item[0])  # stable: ties keep the order of first appearance
        scene_lo.append(len(first))
        for k0, n, index in kept:
            ids.append(recording.ids[index])
            first.append(k0)
            count.append(n)
            xy = _interpolate(recording.samples[index], recording.positions[index], k0, n, ratio)
            np.subtract(xy, centre, out=samples[filled:filled + n])
            filled += n
        scene_hi.append(len(first))
        scene_steps.append(max((k0 + n for k0, n, _ in kept), default=1))
    count_array = np.asarray(count, dtype=np.int64)
    return ReplayScenes(
        files=tuple(r.path for r in recordings), time_step=float(time_step),
        centres=np.asarray(centres), half_sizes=np.asarray(half_sizes),
        scene_steps=np.asarray(scene_steps, dtype=np.int64), scene_lo=np.asarray(scene_lo, dtype=np.int64),
        scene_hi=np.asarray(scene_hi, dtype=np.int64), ids=np.asarray(ids, dtype=np.float64),
        first=np.asarray(first, dtype=np.int64), count=count_array,
        offset=np.r_[0, np.cumsum(count_array)[:-1]].astype(np.int64) if len(count) else np.zeros(0, np.int64),
        samples=samples,
    )


@functools.lru_cache(maxsize=8)
def read_scenes(files: tuple[str, ...], sample_rate: float, frame_step: int | None, time_step: float) -> ReplayScenes:
    """The `ReplayScenes` of trajectory files (`read_trajectories`, `build_scenes`), cached for the last 8 sets of
    arguments; `load_replay`, which keeps the scenes some world still uses, is the entry point.

    The files' sizes together are checked first (`MAX_TOTAL_BYTES`), then each file as it is read.
    """
    check_total_size(files)
    return build_scenes([read_trajectories(path, frame_step) for path in files], time_step, sample_rate)


#: The scenes some model still uses, by key: `load_replay` hands out the same object while one does, whatever
#: `read_scenes`'s cache has dropped meanwhile (the model's arrays and the scenario's plans must index the same scenes).
_LIVE: weakref.WeakValueDictionary[tuple, ReplayScenes] = weakref.WeakValueDictionary()


def load_replay(settings: Any, time_step: float) -> ReplayScenes:
    """The scenes of ``settings`` (a `socnav.config.ReplayConfig`: files, sample_rate, frame_step) at `time_step`,
    read once per process: the scenario and the model of every world of this config share one `ReplayScenes`."""
    if not settings.files:
        raise TrajectoryFileError("replayed humans need trajectory files: set humans.replay.files")
    key = (tuple(str(path) for path in settings.files), float(settings.sample_rate),
           None if settings.frame_step is None else int(settings.frame_step), float(time_step))
    scenes = _LIVE.get(key)
    if scenes is None:
        scenes = _LIVE[key] = read_scenes(*key)
    return scenes


# ---------------------------------------------------------------------------------------------------- the model


@numba.njit(cache=True)
def _replay_velocities(positions, velocities, compute, slot_pedestrian, step, first, count, offset, samples,
                       time_step):
    """Each computed slot's velocity to its pedestrian's next recorded position (0 if it has none)."""
    out = velocities.copy()
    n_envs, n_agents = compute.shape
    for env in range(n_envs):
        k = step[env] + 1
        for agent in range(1, n_agents):
            p = slot_pedestrian[env, agent]
            if not compute[env, agent] or p < 0:
                continue
            i = k - first[p]
            if 0 <= i < count[p]:
                out[env, agent, 0] = (samples[offset[p] + i, 0] - positions[env, agent, 0]) / time_step
                out[env, agent, 1] = (samples[offset[p] + i, 1] - positions[env, agent, 1]) / time_step
            else:
                out[env, agent, 0] = 0.0
                out[env, agent, 1] = 0.0
    return out


@numba.njit(cache=True)
def _leave(active, velocities, slot_pedestrian, step, first, count):
    """Free the slots whose pedestrian has no recorded position at the next step; returns the freed slots."""
    n_envs, n_agents = active.shape
    left = np.zeros((n_envs, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        k = step[env] + 1
        for agent in range(1, n_agents):
            p = slot_pedestrian[env, agent]
            if p >= 0 and not (first[p] <= k < first[p] + count[p]):
                slot_pedestrian[env, agent] = -1
                active[env, agent] = False
                velocities[env, agent, 0] = 0.0
                velocities[env, agent, 1] = 0.0
                left[env, agent] = True
    return left


@numba.njit(cache=True)
def _arrive(positions, velocities, goals, active, slot_pedestrian, step, next_arrival, scene, path,
            scene_hi, first, count, offset, samples, time_step):
    """After the move: advance every env's scene step, put its pedestrians exactly on their recorded positions, and
    give the pedestrians that appear at this step a free slot, closest to the robot's path first (those that find
    none are left out). Returns the slots that got a new pedestrian."""
    n_envs, n_agents = active.shape
    arrived = np.zeros((n_envs, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        k = step[env] + 1
        step[env] = k
        for agent in range(1, n_agents):
            p = slot_pedestrian[env, agent]
            if p >= 0:
                j = offset[p] + k - first[p]
                positions[env, agent, 0] = samples[j, 0]
                positions[env, agent, 1] = samples[j, 1]
        lo = next_arrival[env]
        hi = lo
        end = scene_hi[scene[env]]
        while hi < end and first[hi] <= k:
            hi += 1
        next_arrival[env] = hi
        n_new = hi - lo
        if n_new == 0:
            continue
        distance = np.empty(n_new)
        for c in range(n_new):
            p = lo + c
            j = offset[p] + k - first[p]
            if k - first[p] >= count[p]:
                distance[c] = np.inf  # gone already (cannot happen for a pointer kept up to date)
            else:
                distance[c] = _segment_distance(samples[j, 0], samples[j, 1], path[env, 0], path[env, 1],
                                                path[env, 2], path[env, 3])
        order = np.argsort(distance, kind="mergesort")
        agent = 1
        for c in order:
            if not distance[c] < np.inf:
                break
            while agent < n_agents and slot_pedestrian[env, agent] >= 0:
                agent += 1
            if agent == n_agents:
                break  # every slot is taken: this pedestrian (and the farther ones) stay out of the episode
            p = lo + c
            j = offset[p] + k - first[p]
            slot_pedestrian[env, agent] = p
            active[env, agent] = True
            positions[env, agent, 0] = samples[j, 0]
            positions[env, agent, 1] = samples[j, 1]
            if k + 1 - first[p] < count[p]:  # its velocity over the coming step
                velocities[env, agent, 0] = (samples[j + 1, 0] - samples[j, 0]) / time_step
                velocities[env, agent, 1] = (samples[j + 1, 1] - samples[j, 1]) / time_step
            else:
                velocities[env, agent, 0] = 0.0
                velocities[env, agent, 1] = 0.0
            last = offset[p] + count[p] - 1
            goals[env, agent, 0] = samples[last, 0]
            goals[env, agent, 1] = samples[last, 1]
            arrived[env, agent] = True
    return arrived


class ReplayHumans:
    """`HumanModel` "replay": every human follows its recorded track, whatever the robot or the others do.

    None of the `Crowd`'s social inputs (attention, personal space, cooperation) changes a replayed human's path;
    personal space still scores the robot's intrusions in the reward, and the disturbance term is zero (a replayed
    human walks the same with and without the robot). Besides `velocities` (the velocity to the next recorded
    position), the world calls the `socnav.sim.humans.base.ScriptedHumans` hooks: `start_episode` at every reset,
    `before_move` (pedestrians whose track ends leave: their slot becomes inactive) and `after_move` (positions set
    exactly to the recorded ones, pedestrians whose track starts enter a free slot).
    """

    name = "replay"
    interaction_range = 0.0  # a replayed human never notices the robot
    arrival_distance = 0.0

    def __init__(self, scenes: ReplayScenes, time_step: float):
        self.scenes = scenes
        self.time_step = float(time_step)
        self.attach(0, 1)

    @classmethod
    def from_config(cls, config: Any) -> ReplayHumans:
        return cls(load_replay(config.humans.replay, config.time_step), config.time_step)

    def attach(self, n_envs: int, n_slots: int) -> None:
        """Allocate the per-environment state of a world of `n_envs` environments with `n_slots` agent slots."""
        self.scene = np.zeros(n_envs, dtype=np.int64)
        self.step = np.zeros(n_envs, dtype=np.int64)  # the scene's step now
        self.next_arrival = np.zeros(n_envs, dtype=np.int64)  # first pedestrian (global index) yet to appear
        self.path = np.zeros((n_envs, 4))  # the robot's start and goal
        self.slot_pedestrian = np.full((n_envs, n_slots), -1, dtype=np.int64)

    def start_episode(self, env: int, plan: ReplayStart, positions: np.ndarray, velocities: np.ndarray,
                      goals: np.ndarray, active: np.ndarray) -> None:
        """Begin environment `env`'s episode as `plan` says; writes its humans' state into the world's arrays."""
        scenes = self.scenes
        if not isinstance(plan, ReplayStart) or plan.scenes is not scenes:
            raise ValueError("replayed humans start from the replay scenario's plan of the same trajectory files")
        k = plan.step
        self.scene[env], self.step[env] = plan.scene, k
        self.path[env] = (*plan.start, *plan.goal)
        lo, hi = int(scenes.scene_lo[plan.scene]), int(scenes.scene_hi[plan.scene])
        self.next_arrival[env] = lo + int(np.searchsorted(scenes.first[lo:hi], k, side="right"))
        self.slot_pedestrian[env] = plan.pedestrians
        for slot, p in enumerate(plan.pedestrians):
            if p < 0:
                continue
            active[env, slot] = True
            positions[env, slot] = plan.positions[slot]
            goals[env, slot] = plan.goals[slot]
            # "the velocity of the last step": backwards where the track goes back that far, else forwards
            i = k - scenes.first[p]
            if i > 0:
                velocities[env, slot] = (scenes.position(p, k) - scenes.position(p, k - 1)) / self.time_step
            elif i + 1 < scenes.count[p]:
                velocities[env, slot] = (scenes.position(p, k + 1) - scenes.position(p, k)) / self.time_step
            else:
                velocities[env, slot] = 0.0

    def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
        s = self.scenes
        return _replay_velocities(crowd.positions, crowd.velocities, compute, self.slot_pedestrian, self.step,
                                  s.first, s.count, s.offset, s.samples, self.time_step)

    def before_move(self, active: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Pedestrians whose track ends before the next step leave now; returns the (E, N) slots they freed."""
        return _leave(active, velocities, self.slot_pedestrian, self.step, self.scenes.first, self.scenes.count)

    def after_move(self, positions: np.ndarray, velocities: np.ndarray, goals: np.ndarray,
                   active: np.ndarray) -> np.ndarray:
        """Advance to the next step: recorded positions, arrivals; returns the (E, N) slots that got a pedestrian."""
        s = self.scenes
        return _arrive(positions, velocities, goals, active, self.slot_pedestrian, self.step, self.next_arrival,
                       self.scene, self.path, s.scene_hi, s.first, s.count, s.offset, s.samples, self.time_step)
