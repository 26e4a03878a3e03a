"""docs/configuration.md maps every CLI flag to its YAML field and Python name and lists every config field: a flag
or field added to the code without the doc fails here, and so does a doc not regenerated after a change."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "configuration.md"


def _generator():
    spec = importlib.util.spec_from_file_location("configuration_table", REPO / "docs" / "configuration_table.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("configuration_table", module)
    spec.loader.exec_module(module)
    return module


GENERATOR = _generator()


def _section(heading: str) -> str:
    """The doc's text from `heading` to the next heading of the same or a higher level."""
    text = DOC.read_text()
    start = text.index(heading)
    level = heading.split(" ")[0]
    following = re.search(rf"^#{{1,{len(level)}}} ", text[start + len(heading):], flags=re.MULTILINE)
    return text[start: start + len(heading) + following.start()] if following else text[start:]


def _first_column(section: str) -> set[str]:
    return set(re.findall(r"^\| `([^`]+)` \|", section, flags=re.MULTILINE))


@pytest.mark.parametrize("command", GENERATOR.COMMANDS)
def test_every_flag_of_the_documented_commands_is_in_its_table(command):
    documented = _first_column(_section(f"### `socnav {command}`"))
    params = GENERATOR.command_params(command)
    missing = [GENERATOR.flag_name(param) for param in params if GENERATOR.flag_name(param) not in documented]
    assert not missing, f"socnav {command}: {missing} missing from {DOC} (run docs/configuration_table.py)"
    unmapped = [param.name for param in params if (command, param.name) not in GENERATOR.FLAGS]
    assert not unmapped, f"socnav {command}: add {unmapped} to FLAGS in docs/configuration_table.py"


def _fields(model, prefix: str = "") -> list[str]:
    return [name for name, *_ in GENERATOR.model_rows(model, prefix)]


def test_every_config_field_is_in_the_doc():
    from socnav.config import EnvConfig
    from socnav.experiments.spec import Budget, Evaluation, Experiment, Grid, Safety, Study
    from socnav.rl.presets import AlgoConfig
    from socnav.safety.rule import Thresholds

    documented = set(re.findall(r"^\| `([^`]+)` \|", DOC.read_text(), flags=re.MULTILINE))
    expected = _fields(EnvConfig) + _fields(AlgoConfig) + _fields(Thresholds)
    expected += [name for name in Experiment.model_fields if name not in ("grid", "evaluation", "study", "safety",
                                                                           "budgets")]
    for block, model in (("grid", Grid), ("evaluation", Evaluation), ("study", Study), ("safety", Safety),
                         ("budgets.<name>", Budget)):
        expected += _fields(model, f"{block}.")
    missing = [name for name in expected if name not in documented]
    assert not missing, f"{missing} missing from {DOC} (run docs/configuration_table.py)"


def test_the_doc_is_what_the_generator_writes_now(capsys):
    GENERATOR.main()
    assert capsys.readouterr().out.rstrip() == DOC.read_text().rstrip(), (
        "docs/configuration.md is out of date: python docs/configuration_table.py > docs/configuration.md")


def test_readme_and_the_site_link_the_table():
    import yaml

    assert "(docs/configuration.md)" in (REPO / "README.md").read_text()  # a Markdown link to the page
    nav = yaml.safe_load((REPO / "mkdocs.yml").read_text())["nav"]
    assert {"Configuration": "configuration.md"} in nav
