"""Every ``Examples`` section in splidar's docstrings runs and prints what it shows.

The examples are the first code a newcomer copies; a wrong one is a bug. Each module's
docstrings are collected with :mod:`doctest` (the standard library's finder, not pytest's
``--doctest-modules``, so the README's test command runs them unchanged) and run in a
fresh temporary directory, so an example may write its files under relative paths.
Lines marked ``# doctest: +SKIP`` need a user's file and are only shown.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import matplotlib
import pytest

import splidar

FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _modules() -> list[str]:
    names = ["splidar"]
    for info in pkgutil.walk_packages(splidar.__path__, prefix="splidar."):
        if info.name.endswith("__main__"):
            continue
        names.append(info.name)
    return sorted(names)


def _examples() -> list:
    found = []
    finder = doctest.DocTestFinder(exclude_empty=True)
    for name in _modules():
        try:
            module = importlib.import_module(name)
        except ImportError:  # an optional extra that is not installed
            continue
        for test in finder.find(module, name):
            if test.examples and test.name.startswith(name):
                found.append(pytest.param(test, id=test.name))
    return found


EXAMPLES = _examples()


def test_docstring_examples_found():
    # The public stages and the loader carry examples; an empty collection would mean
    # the finder silently found nothing and every test below passed vacuously.
    names = {p.id for p in EXAMPLES}
    for expected in ("splidar.detection._detect.detect", "splidar.cube.Cube"):
        assert expected in names
    assert len(EXAMPLES) > 50


@pytest.mark.parametrize("test", EXAMPLES)
def test_docstring_example_runs(test, tmp_path, monkeypatch):
    matplotlib.use("Agg")  # plotting examples draw off screen
    monkeypatch.chdir(tmp_path)
    test.globs = dict(test.globs)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    out: list[str] = []
    result = runner.run(test, out=out.append, clear_globs=True)
    assert result.failed == 0, "".join(out)
