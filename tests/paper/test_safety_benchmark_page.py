"""docs/analysis/safety_benchmark_shipped.py's ``--keep-seeds``: the page's section across training seeds (which does
not depend on the shipped policy) is kept whole while the shipped policy's table is regenerated."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "docs" / "analysis" / "safety_benchmark_shipped.py"
PAGE = SCRIPT.parents[1] / "safety-benchmark.md"


def test_the_section_across_training_seeds_is_kept_to_the_end_of_the_page():
    script = runpy.run_path(str(SCRIPT))
    page = PAGE.read_text()
    kept = script["kept_seeds_section"](page)
    assert kept.startswith(script["SEEDS_HEADING"] + "\n") and page.endswith(kept)
    assert "The shipped policy acting" not in kept and "training seeds' acting policies" in kept
    fresh = "# Safety-layer benchmark (the shipped policy)\n\n## The table\n\n| a |\n"
    assert (fresh + "\n" + kept).count(script["SEEDS_HEADING"]) == 1
    with pytest.raises(SystemExit, match="has no '## Across training seeds' section to keep"):
        script["kept_seeds_section"](fresh)
