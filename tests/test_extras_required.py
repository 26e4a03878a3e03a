"""`require` (tests/_extras.py): a missing test extra fails the test, naming what to install, unless allowed."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import tomllib
from _extras import ALLOW_MISSING, TEST_EXTRAS, require


def test_an_installed_module_is_returned():
    assert require("json") is json


@pytest.mark.parametrize("module", sorted(TEST_EXTRAS))
def test_a_missing_extra_fails_naming_its_package_and_the_install_command(monkeypatch, module):
    monkeypatch.delenv(ALLOW_MISSING, raising=False)
    monkeypatch.setitem(sys.modules, module, None)  # import -> ImportError, as if it were not installed
    with pytest.raises(pytest.fail.Exception) as failure:
        require(module)
    message = str(failure.value)
    assert f"{TEST_EXTRAS[module]} is not installed" in message
    assert 'pip install -e ".[test]"' in message and ALLOW_MISSING in message


@pytest.mark.parametrize("value", ["", "0", "yes"])
def test_only_the_value_1_allows_skipping(monkeypatch, value):
    monkeypatch.setenv(ALLOW_MISSING, value)
    monkeypatch.setitem(sys.modules, "pyrvo", None)
    with pytest.raises(pytest.fail.Exception):
        require("pyrvo")


def test_allowed_missing_extras_skip_instead(monkeypatch):
    monkeypatch.setenv(ALLOW_MISSING, "1")
    monkeypatch.setitem(sys.modules, "pyrvo", None)
    with pytest.raises(pytest.skip.Exception, match=r'pyrvo is not installed.*pip install -e "\.\[test\]"'):
        require("pyrvo")


def test_every_required_package_is_in_the_test_extra():
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    test_extra = pyproject["project"]["optional-dependencies"]["test"]
    names = {requirement.split(">")[0].split("=")[0].split("<")[0].strip() for requirement in test_extra}
    assert set(TEST_EXTRAS.values()) <= names


def test_no_test_skips_a_missing_extra_with_importorskip():
    tests = Path(__file__).parent
    offenders = [path.relative_to(tests) for path in tests.rglob("*.py")
                 if path.name != Path(__file__).name and "importorskip(" in path.read_text()]
    assert not offenders, f"use `from _extras import require` instead of pytest.importorskip in {offenders}"
