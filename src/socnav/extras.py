"""Install hints for socnav's optional extras (`tune`, `ray`, `video`, ...), worded for how socnav was installed."""

from __future__ import annotations

from pathlib import Path

__all__ = ["install_hint"]


def _checkout_root() -> Path | None:
    """The source checkout socnav runs from (an editable install: src/socnav/ below a pyproject.toml), if any."""
    root = Path(__file__).resolve().parent.parent.parent
    pyproject = root / "pyproject.toml"
    if pyproject.is_file() and 'name = "socnav"' in pyproject.read_text(errors="replace"):
        return root
    return None


def install_hint(extra: str) -> str:
    """The pip command that installs the optional `extra`: `pip install -e ".[tune]"` from a checkout (run in its
    root), `pip install "socnav[tune]"` otherwise. Print it with markup escaped (Rich reads `[tune]` as a tag)."""
    root = _checkout_root()
    if root is not None:
        return f'pip install -e ".[{extra}]" (in {root})'
    return f'pip install "socnav[{extra}]"'
