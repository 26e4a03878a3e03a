"""Atomic file writing (results, records and checkpoints never exist half-written) and the directory lock.

Write to a temporary file in the destination's directory, flush it to disk, then `os.replace` it into place. A
process killed in between leaves its temporary file (``.<name>.<8 random characters>.tmp<suffix>``) behind;
`remove_stale_temporaries`, called by the next run holding the directory's lock, deletes them.
"""

from __future__ import annotations

import math

import os
import re
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import pandas as pd

# The names `atomic_path` gives its temporary files: mkstemp's 8 random characters between prefix and suffix.
_TEMPORARY_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\.[^.]*)?$")


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path (same directory and suffix) that replaces `path` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(handle)
    temporary_path = Path(temporary)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temporary_path, 0o666 & ~umask)  # mkstemp creates 0600; give the file normal permissions
    try:
        yield temporary_path
        with open(temporary_path, "rb+") as stream:
            os.fsync(stream.fileno())
        os.replace(temporary_path, path)
    finally:
        temporary_path.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> Path:
    with atomic_path(path) as temporary:
        temporary.write_text(text)
    return Path(path)


TABLE_FORMATS = (".csv", ".parquet")


def write_table_atomic(frame: pd.DataFrame, path: str | Path) -> Path:
    """Write a DataFrame as CSV or Parquet (by the file's suffix) atomically."""
    path = Path(path)
    if path.suffix not in TABLE_FORMATS:
        raise ValueError(f"unsupported table format {path.suffix!r} for {path}; allowed: {', '.join(TABLE_FORMATS)}")
    with atomic_path(path) as temporary:
        if path.suffix == ".csv":
            frame.to_csv(temporary, index=False)
        else:
            frame.to_parquet(temporary, index=False)
    return path


def read_table(path: str | Path) -> pd.DataFrame:
    path = Path(path)
    if path.suffix not in TABLE_FORMATS:
        raise ValueError(f"unsupported table format {path.suffix!r} for {path}; allowed: {', '.join(TABLE_FORMATS)}")
    return pd.read_csv(path) if path.suffix == ".csv" else pd.read_parquet(path)


def remove_stale_temporaries(directory: str | Path, recursive: bool = True) -> list[Path]:
    """Delete the temporary files `atomic_path` left in `directory` when its writer was killed; returns them.

    Call it only while holding the directory's `file_lock`: a live writer's temporary file looks the same.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    candidates = directory.rglob(".*") if recursive else directory.glob(".*")
    removed = [path for path in candidates if _TEMPORARY_NAME.match(path.name) and path.is_file()]
    for path in removed:
        path.unlink(missing_ok=True)
    return removed


@contextmanager
def file_lock(path: str | Path, blocking: bool = True) -> Iterator[bool]:
    """An exclusive flock on `path` (released when the holder dies); yields False if not blocking and busy."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no locking
        yield True
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        except OSError:  # a filesystem without flock (some network mounts): go on unlocked
            yield True
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def save_figure(figure, out_base: Path) -> list[Path]:
    """Write a matplotlib figure as `out_base`.png (150 dpi) and .svg, each atomically, then close it."""
    import matplotlib.pyplot as plt

    paths = []
    for suffix in (".png", ".svg"):
        path = Path(out_base).with_suffix(suffix)
        with atomic_path(path) as temporary:
            figure.savefig(temporary, format=suffix[1:], dpi=150)
        paths.append(path)
    plt.close(figure)
    return paths


def json_safe(value: Any) -> Any:
    """Strict JSON: NaN / infinities become null, numpy scalars plain numbers."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
