"""Shared test settings: a small, deterministic hypothesis profile so the suite stays fast in CI, and `require`
(`tests/_extras.py`), which fails a test whose optional package is missing instead of skipping it."""

import sys
from pathlib import Path

from hypothesis import HealthCheck, settings

# Test modules import helpers of this directory (`from _extras import require`) whatever pytest's import mode.
if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))

settings.register_profile(
    "socnav", max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("socnav")
