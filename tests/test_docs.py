"""The README and the documentation site say what the project does: the README's install and test commands are the
ones CI runs, its links and its Python example point at files and names that exist, every guide page is in the
site's navigation, every API page documents a package of src/, and no docstring holds what the strict site build
(`mkdocs build --strict`, docstrings rendered as Markdown) refuses."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
import unicodedata
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
DOCS = REPO / "docs"
API_PACKAGES = ("sim", "envs", "rl", "uncertainty", "safety", "experiments", "runtime", "export", "ros2")


def code_blocks(markdown: str, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", markdown, flags=re.MULTILINE | re.DOTALL)


def slug(heading: str) -> str:
    """The anchor Python-Markdown's toc extension (and so mkdocs) gives a heading."""
    text = unicodedata.normalize("NFKD", heading).encode("ascii", "ignore").decode()
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def anchors(markdown: str) -> set[str]:
    markdown = re.sub(r"^```.*?^```", "", markdown, flags=re.MULTILINE | re.DOTALL)  # comments in code are no headings
    return {slug(heading) for heading in re.findall(r"^#+ (.+)$", markdown, flags=re.MULTILINE)}


def nav_files(entries: list) -> list[str]:
    files: list[str] = []
    for entry in entries:
        values = entry.values() if isinstance(entry, dict) else [entry]
        for value in values:
            files += nav_files(value) if isinstance(value, list) else [value]
    return files


def test_readme_install_and_test_commands_are_the_ones_ci_runs():
    ci = (REPO / ".ci" / "run").read_text()
    commands = [line.split("#")[0].strip() for line in ci.splitlines()
                if line.startswith(("pip install", "python -m pytest"))]
    assert any(c.startswith("pip install torch") for c in commands) and "python -m pytest -n 2 -q" in commands
    readme_lines = {line.strip() for block in code_blocks(README, "bash") for line in block.splitlines()}
    missing = [command for command in commands if command not in readme_lines]
    assert not missing, f"README does not show what .ci/run runs: {missing}"


def test_readme_links_point_at_files_and_headings_that_exist():
    links = re.findall(r"\]\(([^)\s]+)\)", README)
    assert links
    for link in links:
        if link.startswith(("http://", "https://")):
            continue
        path, _, anchor = link.partition("#")
        target = REPO / path
        assert target.exists(), f"README links {link}: no such file"
        if anchor:
            assert anchor in anchors(target.read_text()), f"README links {link}: no such heading in {path}"


def test_readme_example_imports_names_that_exist():
    (example,) = code_blocks(README, "python")
    tree = ast.parse(example)
    imported = [(node.module, alias.name) for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                for alias in node.names]
    assert imported
    for module, name in imported:
        assert hasattr(importlib.import_module(module), name), f"README example: {module} has no {name}"
    import socnav

    calls = {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)
             and isinstance(node.value, ast.Name) and node.value.id == "socnav"}
    assert calls and all(hasattr(socnav, name) for name in calls), calls


def test_every_guide_page_is_in_the_site_navigation_and_every_entry_exists():
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text())
    listed = nav_files(config["nav"])
    assert len(listed) == len(set(listed)), "a page is listed twice"
    pages = {str(path.relative_to(DOCS)) for path in DOCS.rglob("*.md")}
    assert not set(listed) - pages, f"nav entries without a page: {set(listed) - pages}"
    assert not pages - set(listed), f"pages missing from the nav in mkdocs.yml: {pages - set(listed)}"
    assert "configuration.md" in listed and "metrics.md" in listed


def test_api_pages_document_every_package_and_only_what_exists():
    documented = {}
    for page in sorted((DOCS / "api").glob("*.md")):
        for target in re.findall(r"^::: (\S+)$", page.read_text(), flags=re.MULTILINE):
            documented[target] = page.name
    assert {f"socnav.{package}" for package in API_PACKAGES} <= set(documented), documented
    for target in documented:
        path = REPO / "src" / Path(*target.split("."))
        assert (path / "__init__.py").is_file() or path.with_suffix(".py").is_file(), f"{target}: not in src/"


def string_statements(source: str) -> list[tuple[int, str]]:
    """Docstrings of modules, classes and functions, and of attributes: every statement that is a string."""
    return [(node.lineno, node.value.value) for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)]


def test_docstrings_hold_no_markdown_reference_links():
    # The API pages render docstrings as Markdown; there `a[i][j]` or `[x][y]` outside backticks is a reference link,
    # and mkdocs-autorefs fails the strict build on a target it cannot find. Code goes in backticks.
    reference = re.compile(r"\[[^\]\n]*\]\s?\[[^\]\n]*\]")
    found = []
    for path in sorted((REPO / "src" / "socnav").rglob("*.py")):
        for lineno, docstring in string_statements(path.read_text()):
            prose = [line for line in inspect.cleandoc(docstring).splitlines()
                     if not line.startswith("    ")]  # indented lines: Markdown code blocks
            text = re.sub(r"``.*?``|`[^`]*`", "", "\n".join(prose), flags=re.DOTALL)
            found += [f"{path.relative_to(REPO)}:{lineno}: {m}" for m in reference.findall(text)]
    assert not found, "put these in backticks:\n" + "\n".join(found)
