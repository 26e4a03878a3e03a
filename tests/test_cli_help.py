"""The `--help` of every command, word for word as recorded in tests/cli_help/help.json: moving the command line
between modules must not change what a user reads (regenerate the file only for a deliberate change of the help:
``SOCNAV_RECORD_CLI_HELP=1 python -m pytest tests/test_cli_help.py``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest
import typer.main
from typer.testing import CliRunner

from socnav.cli import app

RECORD = Path(__file__).resolve().parent / "cli_help" / "help.json"
WIDTH = {"COLUMNS": "100"}  # click wraps to the terminal: a fixed width makes the text the same everywhere


def command_paths(command: Any, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every command and group under `command` (typer's click command), as the words typed after `socnav`."""
    paths = [path]
    if hasattr(command, "commands"):  # a group (typer brings its own click: no isinstance on click.Group)
        for name, sub in command.commands.items():
            paths += command_paths(sub, (*path, name))
    return paths


def help_texts() -> dict[str, str]:
    runner = CliRunner()
    texts = {}
    for path in command_paths(typer.main.get_command(app)):
        result = runner.invoke(app, [*path, "--help"], env=WIDTH, prog_name="socnav")
        assert result.exit_code == 0, (path, result.output)
        texts[" ".join(("socnav", *path))] = result.output
    return texts


def test_every_command_prints_the_recorded_help():
    texts = help_texts()
    if os.environ.get("SOCNAV_RECORD_CLI_HELP"):
        RECORD.write_text(json.dumps(texts, indent=1, sort_keys=True) + "\n")
    recorded = json.loads(RECORD.read_text())
    assert sorted(texts) == sorted(recorded), "commands added or removed: record the help again"
    for command, text in recorded.items():
        assert texts[command] == text, command


@pytest.mark.parametrize("path", [("ros2",), ("evaluate",)])
def test_the_record_holds_groups_and_commands(path):
    recorded = json.loads(RECORD.read_text())
    assert "Usage: socnav " + " ".join(path) in recorded["socnav " + " ".join(path)]
