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
