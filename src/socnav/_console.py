"""The output of the `socnav` command line: one console every command prints to, and `fail`, its one way to reject bad
input (a red one-line error, exit code 2), shared by every `socnav.cli` module.
"""

from __future__ import annotations

from typing import NoReturn

import typer
from rich.console import Console
from rich.markup import escape

__all__ = ["console", "fail"]

# Tables keep their words whole when the output is piped (Rich falls back to 80 columns without a terminal).
console = Console(width=None if Console().is_terminal else 160)


def fail(message: str, code: int = 2) -> NoReturn:
    """Print ``error: <message>`` and exit with `code` (2: bad input)."""
    # Escaped: messages hold brackets (`pip install -e ".[video]"`, `[min, max]`) that Rich would take for markup.
    console.print(f"[bold red]error:[/] {escape(message)}", highlight=False)
    raise typer.Exit(code=code)
