"""`require(module)`: import a package of the `test` extra, or FAIL the test (never skip it silently).

`pytest.importorskip` turned a CI machine without, say, pyrvo into a green run that never compared ORCA with RVO2.
`require` fails instead, naming the package and the command that installs it; set ``SOCNAV_ALLOW_MISSING_EXTRAS=1``
to skip those tests on a partial local setup. Test modules import it with ``from _extras import require``
(`tests/conftest.py` puts this directory on ``sys.path``).
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType

import pytest

#: The environment variable that turns a missing test extra from a failure into a skip.
ALLOW_MISSING = "SOCNAV_ALLOW_MISSING_EXTRAS"
#: Import name -> pip name of the optional packages the tests need; all of them are in pyproject's `test` extra.
TEST_EXTRAS = {
    "pyrvo": "pyrvo",
    "imageio_ffmpeg": "imageio-ffmpeg",
    "ray": "ray",
    "optuna": "optuna",
    "onnx": "onnx",
    "onnxruntime": "onnxruntime",
}
INSTALL = 'pip install -e ".[test]"'


def require(module: str) -> ModuleType:
    """The imported `module`; if it cannot be imported, fail the calling test (or module, at import time) with a
    message naming its package and the `test` extra, or skip it when ``SOCNAV_ALLOW_MISSING_EXTRAS=1``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        error = exc  # reported below, outside the handler: one clear message rather than a chained traceback
    message = f"{TEST_EXTRAS.get(module, module)} is not installed ({error}); it is part of the test extra: {INSTALL}"
    if os.environ.get(ALLOW_MISSING) == "1":
        pytest.skip(f"{message} (skipped: {ALLOW_MISSING}=1)", allow_module_level=True)
    pytest.fail(f"{message}, or set {ALLOW_MISSING}=1 to skip the tests that need it", pytrace=False)
