"""Compare two `socnav run` directories file by file, exactly: the check that a refactor changed no number.

    socnav run configs/experiments/table3.yaml --budget check --out runs/before   # on the old code
    socnav run configs/experiments/table3.yaml --budget check --out runs/after    # on the new code
    python docs/analysis/compare_runs.py runs/before runs/after                    # exit 1 if anything differs

Every result file of every unit is compared without tolerance: Parquet and CSV frames (wall-clock columns dropped),
JSON (wall-clock, host, version and output-hash keys dropped: the hashed files are compared themselves), threshold
YAML and report Markdown as text, trained models tensor by tensor. Run both on the same machine: training is
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


def compare_file(before: Path, after: Path) -> str | None:
    """None if the two files hold the same results, else what differs."""
    try:
        if before.suffix == ".parquet":
            pd.testing.assert_frame_equal(pd.read_parquet(before), pd.read_parquet(after), check_exact=True)
        elif before.suffix == ".csv":
            a, b = pd.read_csv(before), pd.read_csv(after)
            wall = [column for column in a.columns if column.startswith("wall")]
            pd.testing.assert_frame_equal(a.drop(columns=wall), b.drop(columns=wall), check_exact=True)
        elif before.suffix == ".json":
            assert _without_volatile(json.loads(before.read_text())) == _without_volatile(
                json.loads(after.read_text())), "JSON values differ"
        elif before.suffix == ".zip":
            a, b = _model_tensors(before), _model_tensors(after)
            assert a.keys() == b.keys() and all(a[k] == b[k] for k in a), "model tensors differ"
        else:
            assert before.read_text() == after.read_text(), "text differs"
    except AssertionError as error:
        return str(error)[:300]
    return None


def compare_runs(before: Path, after: Path) -> tuple[int, list[str]]:
    """(files compared, differences) over every result file of `before`."""
    compared, differences = 0, []
    for path in sorted(before.rglob("*")):
        relative = path.relative_to(before)
        if (not path.is_file() or path.name.startswith(".") or path.name in BOOKKEEPING_FILES
                or SKIPPED_DIRS & set(relative.parts)
                or path.suffix not in {".parquet", ".csv", ".json", ".zip", ".md", ".yaml"}):
            continue
        compared += 1
        if not (after / relative).exists():
            differences.append(f"{relative}: missing in {after}")
        elif (problem := compare_file(path, after / relative)) is not None:
            differences.append(f"{relative}: {problem}")
    return compared, differences


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__)
        return 2
    before, after = map(Path, argv)
    compared, differences = compare_runs(before, after)
    print(f"{before} vs {after}: {compared} files compared, {len(differences)} differ")
    for line in differences:
        print("  ", line)
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
