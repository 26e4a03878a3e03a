"""Atomic file writing: results, records and checkpoints never exist half-written.

Write to a temporary file in the destination's directory, flush it to disk, then `os.replace` it into place.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pandas as pd


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
