"""The recorded pedestrian trajectories replayed humans follow (`socnav.sim.humans.replay`): the text files of
ETH/UCY as TrajNet and Social-GAN distribute them, one observation per line, ``frame_id ped_id x y`` separated by
whitespace (tabs or spaces), positions in metres, samples at 2.5 Hz (frame ids step by 10 in those files; the step
is inferred per file). `read_trajectories` reads one file within bounds (of size, lines, pedestrians and samples,
docs/limits.md) with errors naming the file and the line; `interpolate_tracks` puts every pedestrian on the env's
time grid (linear, and a pedestrian exists only between its first and last frame).
"""

from __future__ import annotations

import bisect
import functools
import io
import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

#: Files larger than this are refused from their size, before they are read (the ETH/UCY files are below 1 MB). A
#: file is parsed in blocks of ~1 MB: reading one costs about its size plus its rows (32 bytes each), docs/limits.md.


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


_EPS = 1e-9


#: The blocks a file is parsed in (cut at a line's end): numpy's parser per block, the line-by-line scan only for a
#: block it does not read (which names the bad line), so that neither costs more than a block beyond the rows.
_BLOCK_BYTES = 1 << 20


_LONG_LINE = re.compile(rb"[^\n]{%d}" % (MAX_LINE_BYTES + 1))


class TrajectoryFileError(ValueError):
    """A trajectory file cannot be used; the message names the file and, for its content, the line."""


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


def track_steps(recording: Recording, ratio: float) -> list[tuple[int, int]]:
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
    return sum(count for recording in recordings for _, count in track_steps(recording, ratio))


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
    return [(first, interpolate_track(samples, positions, first, count, ratio))
            for (first, count), samples, positions in zip(track_steps(recording, ratio), recording.samples,
                                                          recording.positions, strict=True)]


def interpolate_track(samples: np.ndarray, positions: np.ndarray, first: int, count: int, ratio: float) -> np.ndarray:
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

