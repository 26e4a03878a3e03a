"""Fixtures of the simulator tests: `psf`, the social force oracle (PySocialForce 1.1.2), for test_social_force.py
and test_social_force_walls.py."""

from __future__ import annotations

import logging
import os

import pytest
from _extras import require


@pytest.fixture(scope="module")
def psf(tmp_path_factory):
    """The pysocialforce package, imported without its side effects: on import it opens ``file.log`` in the
    working directory and sets the root logger to DEBUG with a console handler."""
    root = logging.getLogger()
    level, handlers, cwd = root.level, list(root.handlers), os.getcwd()
    os.chdir(tmp_path_factory.mktemp("pysocialforce"))
    try:
        module = require("pysocialforce")
    finally:
        os.chdir(cwd)
        for handler in [h for h in root.handlers if h not in handlers]:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(level)
    assert module.__version__ == "1.1.2", "the oracle is PySocialForce 1.1.2"
    return module
