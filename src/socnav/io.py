"""Atomic file writing (results, records and checkpoints never exist half-written), the directory lock, run
directories that never follow a symbolic link, and bounded reading of untrusted files (JSON above all).

Write to a temporary file in the destination's directory, flush it to disk, then `os.replace` it into place. A
process killed in between leaves its temporary file (``.<name>.<8 random characters>.tmp<suffix>``) behind;
`remove_stale_temporaries`, called by the next run holding the directory's lock, deletes them. `os.replace` replaces
a symbolic link at the destination itself (never writes through it); the directories above it are the caller's to
check (`real_directory`, `refuse_links`).
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:  # pandas loads with the first table written or read: `import socnav.io` stays light
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
    import pandas as pd

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
    """An exclusive flock on `path` (released when the holder dies); yields False if not blocking and busy.

    :raises UnsafePathError: `path` is a symbolic link (never opened through: a lock file planted as a link to a
        file elsewhere would be created or locked there).
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: no locking
        yield True
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        descriptor = os.open(path, flags, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UnsafePathError(f"{path} is a symbolic link; {_LINK_ADVICE}") from None
        raise
    with os.fdopen(descriptor, "a+") as handle:
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


# --------------------------------------------------------------------------------------------------------------
# Run directories never follow a symbolic link
# --------------------------------------------------------------------------------------------------------------

_LINK_ADVICE = "socnav never follows a link inside a run directory (remove it)"


class UnsafePathError(OSError):
    """A symbolic link (or a file) where a run directory keeps its own files or directories: socnav refuses it or
    replaces it, and never reads, writes or deletes through it."""


def _components(root: Path, path: Path) -> list[Path]:
    """The paths from the first component below `root` down to `path` itself (`path` must lie inside `root`)."""
    current, components = root, []
    for part in path.relative_to(root).parts:
        current = current / part
        components.append(current)
    return components


def first_link(root: str | Path, path: str | Path) -> Path | None:
    """The first symbolic link among the components of `path` below `root` (`path` included), None if there is none
    (the walk stops at the first component that does not exist). `root` itself may be a link: it is the user's."""
    for component in _components(Path(root), Path(path)):
        if component.is_symlink():
            return component
        if not component.exists():
            return None
    return None


def refuse_links(root: str | Path, path: str | Path) -> None:
    """:raises UnsafePathError: a component of `path` below `root` (`path` included) is a symbolic link."""
    link = first_link(root, path)
    if link is not None:
        raise UnsafePathError(f"{link} is a symbolic link; {_LINK_ADVICE}")


def remove_links(root: str | Path, path: str | Path) -> list[Path]:
    """Remove every symbolic link among the components of `path` below `root` (`path` included); returns them.
    A link is removed, never followed: its target is left untouched. What lay below a removed link is gone from the
    run directory (the caller redoes it).

    Safe against a concurrent caller: `os.unlink` never removes a real directory, so a link another process already
    replaced by a directory stays replaced.
    """
    removed = []
    for component in _components(Path(root), Path(path)):
        if component.is_symlink():
            with suppress(FileNotFoundError):
                component.unlink()
            removed.append(component)
        elif not component.exists():
            break
    return removed


def real_directory(root: str | Path, path: str | Path) -> Path:
    """Create `path` below `root` like ``mkdir -p``, each component a real directory: a symbolic link on the way is
    removed (`remove_links`) and replaced by a new, empty directory. `root` itself is the caller's (created if
    missing, and may be a link).

    :raises UnsafePathError: a component is a file (or another non-directory).
    """
    path = Path(path)
    Path(root).mkdir(parents=True, exist_ok=True)
    remove_links(root, path)
    for component in _components(Path(root), path):
        with suppress(FileExistsError):
            component.mkdir()
        if component.is_symlink() or not component.is_dir():
            raise UnsafePathError(f"{component} is not a directory; socnav keeps its own directory there "
                                  "(move the file away)")
    return path


def find_links(directory: str | Path) -> list[Path]:
    """Every symbolic link inside `directory`, which is walked without following any (a linked directory is listed,
    never entered); empty when `directory` does not exist."""
    links: list[Path] = []
    for parent, directories, files in os.walk(directory):  # followlinks=False
        links.extend(Path(parent) / name for name in (*directories, *files)
                     if os.path.islink(os.path.join(parent, name)))
    return sorted(links)


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


# --------------------------------------------------------------------------------------------------------------
# Bounded reading of untrusted files
# --------------------------------------------------------------------------------------------------------------

#: What a JSON file socnav reads may hold. socnav writes a few KB (a unit's marker, a run's state) up to ~0.5 MB (the
#: plan of the paper's Table 1, 900 units) with nesting 5 deep; a crafted file can be far larger or deeper.
JSON_MAX_BYTES = 16 << 20
JSON_MAX_DEPTH = 64

# A JSON string: quotes around anything but quotes and backslashes, or escapes. An unterminated string runs to
# the end (and a lone trailing backslash ends it), so the search never retries from inside one: linear time.
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*(?:"|\\?\Z)', re.DOTALL)
_NOT_BRACKETS = bytes(code for code in range(256) if code not in b"[]{}")


class UntrustedInputError(ValueError):
    """An input file socnav refuses to parse: too large, nested too deeply, not a regular file or not UTF-8 text, or
    not valid JSON; the message is one line naming the file and why."""


def read_bounded(path: str | Path, max_bytes: int, follow_links: bool = True) -> bytes:
    """The bytes of the regular file `path`, at most `max_bytes` of them: a file whose size is larger is refused
    before anything is read, and the limit is enforced while reading too, so a file whose size the filesystem does
    not report (``/proc``, a file still growing) cannot make us read more.

    :param follow_links: False refuses a symbolic link at `path` (a run directory's own files).
    :raises UntrustedInputError: larger than `max_bytes`, a directory, a device, a pipe or a link not followed.
    :raises OSError: missing or unreadable.
    """
    path = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NONBLOCK", 0)  # a FIFO must not block
    if not follow_links:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    try:
        descriptor = os.open(path, flags)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UntrustedInputError(f"{path} is a symbolic link; {_LINK_ADVICE}") from None
        raise
    status = os.fstat(descriptor)
    mode = status.st_mode
    if not stat.S_ISREG(mode):
        os.close(descriptor)
        if stat.S_ISDIR(mode):
            raise UntrustedInputError(f"{path} is a directory, not a file")
        raise UntrustedInputError(f"{path} is not a regular file (a device, pipe or socket)")
    if status.st_size > max_bytes:  # from its size, before reading: a 2 GB file costs nothing to refuse
        os.close(descriptor)
        raise UntrustedInputError(f"{path} is larger than {max_bytes:,} bytes, the most socnav reads from such a file "
                                  f"(it has {status.st_size:,})")
    with os.fdopen(descriptor, "rb") as stream:
        data = stream.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise UntrustedInputError(f"{path} is larger than {max_bytes:,} bytes, the most socnav reads from such a file")
    return data


def json_depth(data: bytes) -> int:
    """How deeply the arrays and objects of the JSON text `data` nest (brackets inside strings do not count);
    linear in its length, recursion-free: it runs before the (recursive) parser sees the text."""
    brackets = _JSON_STRING.sub(b"", data).translate(None, _NOT_BRACKETS)
    depth = deepest = 0
    for code in brackets:
        depth += 1 if code in b"[{" else -1
        deepest = max(deepest, depth)
    return deepest


def parse_json(data: bytes | str, what: str, max_depth: int = JSON_MAX_DEPTH) -> Any:
    """`json.loads` of untrusted text: at most `max_depth` levels of nesting (checked before parsing), valid UTF-8,
    numbers within Python's limits (an integer of thousands of digits is refused, not converted).

    :param what: how the message names the input, e.g. the file's path.
    :raises UntrustedInputError: one line naming `what` and the problem.
    """
    raw = data.encode() if isinstance(data, str) else data
    depth = json_depth(raw)
    if depth > max_depth:
        raise UntrustedInputError(f"{what} is nested too deeply ({depth} levels; socnav reads JSON nested at most "
                                  f"{max_depth} deep)")
    try:
        text = raw.decode("utf-8")  # JSON is UTF-8 (RFC 8259); json.loads would guess UTF-16/32 from the bytes
    except UnicodeDecodeError:
        raise UntrustedInputError(f"{what} is not UTF-8 text") from None
    try:
        return json.loads(text)
    except RecursionError:  # cannot happen within the depth bound; kept so the contract holds regardless
        raise UntrustedInputError(f"{what} is nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, or an integer over sys.get_int_max_str_digits()
        raise UntrustedInputError(f"{what} is not valid JSON ({' '.join(str(exc).split())[:200]})") from None


def read_json(path: str | Path, max_bytes: int = JSON_MAX_BYTES, max_depth: int = JSON_MAX_DEPTH,
              follow_links: bool = True) -> Any:
    """The JSON value of the file `path`, read within `max_bytes` and `max_depth` (`read_bounded`, `parse_json`).

    :raises UntrustedInputError: too large, too deep, not a regular file, not UTF-8, not JSON (one line).
    :raises OSError: missing or unreadable.
    """
    return parse_json(read_bounded(path, max_bytes, follow_links), str(path), max_depth)


class OutputPathError(ValueError):
    """An output path socnav refuses before any work starts; the message is one line naming the path and why."""


_SPECIAL_ROOTS = (Path("/proc"), Path("/sys"), Path("/dev"))


def check_output_file(path: str | Path, what: str = "output", force: bool = False,
                      create_parent: bool = False) -> Path:
    """Refuse, before any work, an output path that is not a new or regular file in a writable directory.

    Refused: an existing path that is not a regular file (a directory, FIFO, device or socket), a path that resolves
    into ``/proc``, ``/sys`` or ``/dev``, an existing regular file unless `force`, a parent directory that does not
    exist (unless `create_parent`: then its first existing ancestor must be a writable directory) or is not
    writable. A symbolic link at `path` is checked by what it points to (atomic writes replace the link itself).

    :param what: the option or output the message names (e.g. ``--out``).
    :returns: `path` as a Path.
    :raises OutputPathError: one line naming `what`, the path and the reason.
    """
    path = Path(path)
    resolved = path.resolve()
    if any(resolved == root or root in resolved.parents for root in _SPECIAL_ROOTS):
        raise OutputPathError(f"{what} {path} resolves to {resolved}, a system path (/proc, /sys, /dev); "
                              f"give a regular file")
    if path.exists() or path.is_symlink():
        try:
            mode = path.stat().st_mode
        except OSError as exc:
            raise OutputPathError(f"{what} {path} cannot be checked: {exc.strerror or exc}") from None
        if stat.S_ISDIR(mode):
            raise OutputPathError(f"{what} {path} is a directory; give a file name")
        if not stat.S_ISREG(mode):
            raise OutputPathError(f"{what} {path} is not a regular file (a FIFO, device or socket); give a new file")
        if not force:
            raise OutputPathError(f"{what} {path} exists; pass --force to replace it, or choose another name")
    parent = resolved.parent
    if not parent.exists():
        if not create_parent:
            raise OutputPathError(f"{what} {path}: directory {path.parent} does not exist (a typo? create it first)")
        parent = next(ancestor for ancestor in parent.parents if ancestor.exists())
    if not parent.is_dir():
        raise OutputPathError(f"{what} {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"{what} {path}: directory {parent} is not writable")
    return path


# ---------------------------------------------------------------------------------------------------- YAML input

#: socnav's config, experiment, preset, threshold and map files are a few KB (a polygon map at its vertex bound
#: ~200 KB): these limits leave ample room while bounding what a crafted file can make the reader build (a 409-byte
#: "billion laughs" alias bomb expands to ~10^9 values, whose repr in an error message alone took ~1 GB). The values
#: are counted as the document is composed, before any Python object is built (docs/limits.md).
YAML_MAX_BYTES = 1 << 20
YAML_MAX_NODES = 100_000
#: Nesting of sequences and mappings (socnav's own files nest 5 deep): checked before the composer recurses, so a
#: document nested thousands of levels deep is one line, never a RecursionError.
YAML_MAX_DEPTH = 64


class YAMLTooLargeError(yaml.YAMLError):
    """A YAML input is too large (bytes, or values once its aliases are expanded), recursive or too deeply nested.

    A `yaml.YAMLError`, so every reader's existing YAML error handling reports it.
    """


def _expanded_size(root: yaml.Node) -> int:
    """Number of nodes of the document with every alias expanded (a DAG walk, memoised: linear in its size)."""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, finished = stack.pop()
        key = id(node)
        if isinstance(node, yaml.MappingNode):
            children = [item for pair in node.value for item in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        else:
            children = []
        if finished:
            on_path.discard(key)
            sizes[key] = 1 + sum(sizes[id(child)] for child in children)
            if sizes[key] > YAML_MAX_NODES:
                raise YAMLTooLargeError(f"its aliases (*name) expand to more than {YAML_MAX_NODES:,} values "
                                        "(an alias bomb?)")
            continue
        if key in sizes:
            continue
        if key in on_path:
            raise YAMLTooLargeError("an alias (*name) refers to a node that contains it (recursive anchors)")
        on_path.add(key)
        stack.append((node, True))
        stack.extend((child, False) for child in children if id(child) not in sizes)
    return sizes[id(root)]


class _BoundedLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that bounds a document while composing it -- nesting depth (`YAML_MAX_DEPTH`, before
    recursing) and values written (`YAML_MAX_NODES`, as they are composed) -- and checks its size with aliases
    expanded before constructing any Python object."""

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._depth = 0
        self._composed = 0

    def compose_document(self) -> yaml.Node | None:
        self._depth = self._composed = 0
        node = super().compose_document()
        if node is not None:
            _expanded_size(node)
        return node

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if not self.check_event(yaml.AliasEvent):  # an alias adds no node (its expansion is checked at the end)
            self._composed += 1
            if self._composed > YAML_MAX_NODES:
                raise YAMLTooLargeError(f"it holds more than {YAML_MAX_NODES:,} values")
        if self.check_event(yaml.SequenceStartEvent, yaml.MappingStartEvent):
            self._depth += 1
            if self._depth > YAML_MAX_DEPTH:
                raise YAMLTooLargeError(f"it is nested too deeply: more than {YAML_MAX_DEPTH} levels of lists or "
                                        "mappings inside each other")
            try:
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1
        return super().compose_node(parent, index)


def safe_load_yaml(text: str) -> Any:
    """`yaml.safe_load` for untrusted input: at most `YAML_MAX_BYTES` characters, at most `YAML_MAX_NODES` values
    (counted as written while composing, then with aliases expanded), no recursive anchors, nesting at most
    `YAML_MAX_DEPTH` deep; every bound is checked before a Python object is built.

    :raises YAMLTooLargeError: (a `yaml.YAMLError`) when a bound is exceeded; other `yaml.YAMLError` for bad YAML.
    """
    if len(text) > YAML_MAX_BYTES:
        raise YAMLTooLargeError(f"{len(text):,} characters; socnav reads YAML of at most {YAML_MAX_BYTES:,}")
    try:
        return yaml.load(text, Loader=_BoundedLoader)
    except RecursionError:
        raise YAMLTooLargeError("nested too deeply") from None


def _read_bounded_text(path: Path) -> str:
    """The text of a file, refusing files over `YAML_MAX_BYTES` before reading them (OSError as usual)."""
    size = path.stat().st_size
    if size > YAML_MAX_BYTES:
        raise YAMLTooLargeError(f"{size:,} bytes; socnav reads files of at most {YAML_MAX_BYTES:,}")
    try:  # within the bound whatever the size reported (a file still growing, /proc)
        return read_bounded(path, YAML_MAX_BYTES).decode()
    except UntrustedInputError as exc:
        raise YAMLTooLargeError(str(exc)) from None


def file_size_problem(path: str | Path, limit: int) -> str | None:
    """'is N bytes, more than the M bytes socnav reads from such a file' when the regular file `path` is larger than
    `limit` (from its size, before anything is read), else None (missing or not regular files are the reader's)."""
    import os
    import stat

    try:
        status = os.stat(path)
    except OSError:
        return None
    if stat.S_ISREG(status.st_mode) and status.st_size > limit:
        return f"is {status.st_size:,} bytes, more than the {limit:,} bytes socnav reads from such a file"
    return None


def read_yaml_file(path: Path) -> Any:
    """`safe_load_yaml` of a file, refusing files over `YAML_MAX_BYTES` before reading them (OSError as usual)."""
    return safe_load_yaml(_read_bounded_text(Path(path)))


def yaml_problem(error: yaml.YAMLError) -> str:
    """The end of an error message about a YAML input: 'is refused: ...' or 'is not valid YAML: ...'."""
    kind = "is refused" if isinstance(error, YAMLTooLargeError) else "is not valid YAML"
    return f"{kind}: {error}"
