"""Tests of the package entry point (splidar/__init__.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def _omp_policy(env_value):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_value is not None:
        env["OMP_WAIT_POLICY"] = env_value
    code = "import os, splidar; print(os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    return out.stdout.strip()


@pytest.mark.parametrize(("given", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_import_sets_passive_openmp_wait_unless_user_set(given, expected):
    # spinning OpenMP threads stall the parallel reconstruction on a busy machine
    assert _omp_policy(given) == expected


def test_import_is_lazy_about_heavy_modules():
    code = (
        "import sys, splidar; "
        "print(sorted(m for m in ('numba', 'scipy', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("first", ["splidar.scenes", "splidar.simulation", "splidar.pipeline"])
def test_top_level_functions_survive_submodule_imports(first):
    # a submodule named like a top-level function (the former splidar/simulate.py) is set
    # on the package by the import system and hides the function: splidar.simulate became
    # a module once splidar.scenes had been imported
    code = (
        f"import importlib, splidar; importlib.import_module({first!r}); "
        "print(all(callable(getattr(splidar, n)) for n in "
        "('simulate', 'detect', 'reconstruct', 'process', 'load', 'save', 'evaluate')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"
