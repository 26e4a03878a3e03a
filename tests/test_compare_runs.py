"""docs/analysis/compare_runs.py: the before/after check of a refactor finds a changed number, and with
--allow-added-columns tolerates a new column (only) when the shared ones are identical; a file naming its own run
directory compares equal to the same file of the other run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd

SCRIPT = Path(__file__).resolve().parents[1] / "docs" / "analysis" / "compare_runs.py"
spec = importlib.util.spec_from_file_location("compare_runs", SCRIPT)
compare_runs = importlib.util.module_from_spec(spec)
spec.loader.exec_module(compare_runs)


def write(root: Path, frame: pd.DataFrame) -> Path:
    (root / "unit").mkdir(parents=True)
    frame.to_parquet(root / "unit" / "episodes.parquet")
    frame.to_csv(root / "unit" / "eval.csv", index=False)
    return root


def test_identical_runs_pass_and_a_changed_value_fails(tmp_path):
    frame = pd.DataFrame({"outcome": ["goal", "collision"], "return": [1.5, -4.0]})
    before = write(tmp_path / "before", frame)
    assert compare_runs.main([str(before), str(write(tmp_path / "same", frame))]) == 0
    changed = frame.assign(**{"return": [1.5, -4.0000001]})
    assert compare_runs.main([str(before), str(write(tmp_path / "changed", changed))]) == 1


def test_added_columns_pass_only_when_allowed_and_the_shared_ones_are_identical(tmp_path):
    frame = pd.DataFrame({"outcome": ["goal", "collision"], "return": [1.5, -4.0]})
    before = write(tmp_path / "before", frame)
    added = write(tmp_path / "added", frame.assign(spl=[0.9, 0.0]))
    assert compare_runs.main([str(before), str(added)]) == 1
    assert compare_runs.main([str(before), str(added), "--allow-added-columns"]) == 0
    both = write(tmp_path / "both", frame.assign(spl=[0.9, 0.0], **{"return": [1.0, -4.0]}))
    assert compare_runs.main([str(before), str(both), "--allow-added-columns"]) == 1


def test_a_file_naming_its_own_run_directory_is_the_same_in_both_runs(tmp_path):
    def layers(root: Path, model: Path) -> Path:
        (root / "unit").mkdir(parents=True)
        (root / "unit" / "layers.yaml").write_text(f"risk:\n  model: {model}\n  threshold: 0.25\n")
        return root

    before = layers(tmp_path / "before", tmp_path / "before" / "unit" / "risk-model.npz")
    after = layers(tmp_path / "after", tmp_path / "after" / "unit" / "risk-model.npz")
    assert compare_runs.main([str(before), str(after)]) == 0
    elsewhere = layers(tmp_path / "elsewhere", tmp_path / "before" / "unit" / "risk-model.npz")  # not its own
    assert compare_runs.main([str(before), str(elsewhere)]) == 1
