"""Compare two `socnav run` directories file by file, exactly: the check that a refactor changed no number.

    socnav run configs/experiments/table3.yaml --budget check --out runs/before   # on the old code
    socnav run configs/experiments/table3.yaml --budget check --out runs/after    # on the new code
    python docs/analysis/compare_runs.py runs/before runs/after                    # exit 1 if anything differs
    python docs/analysis/compare_runs.py runs/before runs/after --allow-added-columns

With ``--allow-added-columns``, a table of `after` may hold columns `before` lacks (a new metric recorded beside the
old ones): its shared columns must still be identical, and the added columns are listed, not counted as a
difference.

Every result file of every unit is compared without tolerance: Parquet and CSV frames (wall-clock columns dropped),
JSON (wall-clock, host, version and output-hash keys dropped: the hashed files are compared themselves), threshold
YAML and report Markdown as text (each run's own directory, which a file may name, read as the same), trained models
tensor by tensor. Run both on the same machine: training is
reproducible there, not across CPUs.
"""

from __future__ import annotations

import json
import sys
import zipfile
from pathlib import Path
from typing import Any

import pandas as pd

#: JSON keys that record when, where or how fast something ran, not what it computed.
VOLATILE_KEYS = {"seconds", "elapsed", "started", "finished", "timestamp", "duration_s", "host", "hostname", "pid",
                 "socnav_version", "python", "torch", "created", "path", "root", "out_dir", "fps",
                 "steps_per_second", "written", "sha256", "size", "outputs"}
#: Files describing the run's bookkeeping (plans, markers of the spec), not its results.
BOOKKEEPING_FILES = {"unit.json", "run.json", "resolved.json", "experiment.yaml", "units.json", "report.md"}
SKIPPED_DIRS = {"tb", "checkpoints", ".locks"}


def _without_volatile(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _without_volatile(item) for key, item in value.items()
                if key not in VOLATILE_KEYS and "wall" not in key}
    if isinstance(value, list):
        return [_without_volatile(item) for item in value]
    return value


def _model_tensors(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as archive:
        return {name: archive.read(name) for name in archive.namelist() if not name.endswith(("json", "txt"))}


def _shared(a: pd.DataFrame, b: pd.DataFrame, added: list[str] | None) -> pd.DataFrame:
    """`b` restricted to `a`'s columns when added columns are allowed (their names appended to `added`)."""
    extra = [column for column in b.columns if column not in a.columns]
    if added is None or not extra or [c for c in b.columns if c in a.columns] != list(a.columns):
        return b
    added.extend(extra)
    return b[list(a.columns)]


def _text(path: Path, run_root: Path | None) -> str:
    """The file's text with its run directory's path (a safety layer's file names its risk model by it) replaced."""
    text = path.read_text()
    return text if run_root is None else text.replace(str(run_root), "<run directory>")


def compare_file(before: Path, after: Path, added: list[str] | None = None,
                 roots: tuple[Path, Path] | None = None) -> str | None:
    """None if the two files hold the same results, else what differs. `added`: a list to collect the columns
    `after`'s tables add (then they are allowed), or None (then they are a difference); `roots`: the two run
    directories, whose paths inside text files are read as the same."""
    try:
        if before.suffix == ".parquet":
            a, b = pd.read_parquet(before), pd.read_parquet(after)
            pd.testing.assert_frame_equal(a, _shared(a, b, added), check_exact=True)
        elif before.suffix == ".csv":
            a, b = pd.read_csv(before), pd.read_csv(after)
            b = _shared(a, b, added)
            wall = [column for column in a.columns if column.startswith("wall")]
            pd.testing.assert_frame_equal(a.drop(columns=wall), b.drop(columns=wall), check_exact=True)
        elif before.suffix == ".json":
            assert _without_volatile(json.loads(before.read_text())) == _without_volatile(
                json.loads(after.read_text())), "JSON values differ"
        elif before.suffix == ".zip":
            a, b = _model_tensors(before), _model_tensors(after)
            assert a.keys() == b.keys() and all(a[k] == b[k] for k in a), "model tensors differ"
        else:
            root_before, root_after = roots if roots is not None else (None, None)
            assert _text(before, root_before) == _text(after, root_after), "text differs"
    except AssertionError as error:
        return str(error)[:300]
    return None


def compare_runs(before: Path, after: Path, added: dict[str, list[str]] | None = None) -> tuple[int, list[str]]:
    """(files compared, differences) over every result file of `before`; `added`: a dict to collect, per file, the
    columns its table gains in `after` (allowed), or None (a difference)."""
    compared, differences = 0, []
    roots = (before.resolve(), after.resolve())
    for path in sorted(before.rglob("*")):
        relative = path.relative_to(before)
        if (not path.is_file() or path.name.startswith(".") or path.name in BOOKKEEPING_FILES
                or SKIPPED_DIRS & set(relative.parts)
                or path.suffix not in {".parquet", ".csv", ".json", ".zip", ".md", ".yaml"}):
            continue
        compared += 1
        if not (after / relative).exists():
            differences.append(f"{relative}: missing in {after}")
        else:
            columns: list[str] | None = None if added is None else []
            if (problem := compare_file(path, after / relative, columns, roots)) is not None:
                differences.append(f"{relative}: {problem}")
            elif columns:
                added[str(relative)] = columns
    return compared, differences


def main(argv: list[str]) -> int:
    allow_added = "--allow-added-columns" in argv
    paths = [argument for argument in argv if argument != "--allow-added-columns"]
    if len(paths) != 2:
        print(__doc__)
        return 2
    before, after = map(Path, paths)
    added: dict[str, list[str]] | None = {} if allow_added else None
    compared, differences = compare_runs(before, after, added)
    print(f"{before} vs {after}: {compared} files compared, {len(differences)} differ")
    for line in differences:
        print("  ", line)
    if added:
        columns = sorted({column for names in added.values() for column in names})
        print(f"   {len(added)} tables gained columns (shared columns identical): {', '.join(columns)}")
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
