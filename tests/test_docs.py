"""The documentation cannot fall behind the code: every public name is in the API
reference, every example has the title the gallery needs, and CI builds the pages.

The build itself (``sphinx-build -W``: warnings are errors, examples executed) runs in
``.ci/run`` after the tests, with the ``docs`` extra installed; these checks need no Sphinx.
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import splidar

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
EXAMPLES = ROOT / "examples"


def _api_sections() -> dict[str, set[str]]:
    """Module -> names listed in its autosummary block of docs/api.rst."""
    text = (DOCS / "api.rst").read_text()
    sections: dict[str, set[str]] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"\.\. currentmodule:: (\S+)", line)
        if m:
            current = m.group(1)
            sections[current] = set()
        elif current and re.match(r"   [A-Za-z_]\w*$", line):
            sections[current].add(line.strip())
    return sections


def _public_modules() -> list[str]:
    """splidar's public submodules and subpackages (no leading underscore)."""
    return sorted(
        f"splidar.{m.name}"
        for m in pkgutil.iter_modules(splidar.__path__)
        if not m.name.startswith("_")
    )


def test_api_reference_lists_every_public_module():
    sections = _api_sections()
    missing = [m for m in _public_modules() if m not in sections]
    assert not missing, f"add a section for {missing} to docs/api.rst"


@pytest.mark.parametrize("module", _public_modules())
def test_api_reference_lists_every_public_name(module):
    mod = importlib.import_module(module)
    public = set(getattr(mod, "__all__", ()))
    listed = _api_sections().get(module, set())
    assert public <= listed, f"docs/api.rst misses {sorted(public - listed)} of {module}"
    assert listed <= public, f"docs/api.rst lists {sorted(listed - public)} not in {module}"


def test_api_reference_top_level_names_point_to_their_modules():
    text = (DOCS / "api.rst").read_text()
    for name in splidar.__all__:
        assert f"``splidar.{name}``" in text, f"splidar.{name} missing from the top-level table"


@pytest.mark.parametrize("script", sorted(EXAMPLES.glob("[0-9][0-9]_*.py")), ids=lambda p: p.name)
def test_example_docstring_starts_with_a_gallery_title(script):
    doc = ast.get_docstring(ast.parse(script.read_text()), clean=True)
    assert doc, f"{script.name} has no module docstring"
    lines = doc.splitlines()
    # sphinx-gallery takes the page title from a reST title: a line underlined with '='
    assert len(lines) >= 3 and lines[1] == "=" * len(lines[0]), (
        f"{script.name}: the docstring must start with a title underlined by "
        f"{len(lines[0])} '=' (got {lines[:2]})"
    )
    assert lines[2] == "", f"{script.name}: a blank line must follow the title"


def test_gallery_header_is_found_before_the_markdown_readme():
    # sphinx-gallery looks for GALLERY_HEADER.txt first, then README.md (which is for
    # GitHub and not valid reST); a GALLERY_HEADER.rst would lose to README.md
    assert (EXAMPLES / "GALLERY_HEADER.txt").is_file()


def test_docs_extra_and_ci_build_with_warnings_as_errors():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    names = {re.split(r"[<>=\[ ]", req, maxsplit=1)[0] for req in extras["docs"]}
    assert {"sphinx", "sphinx-gallery", "numpydoc", "myst-parser"} <= names
    ci = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"sphinx-build -W .*-b html docs ", ci), "CI must build the docs with -W"
    assert "python -m pytest -q -n 2" in ci  # the README's test command stays in CI
