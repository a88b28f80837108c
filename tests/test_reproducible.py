"""Same input, same result: by default, across runs, thread counts and worker counts.

The randomness of detection and reconstruction comes only from their ``rng`` argument,
which defaults to the fixed seed 0 (``splidar run --seed``, default 0). Threads never
change a result: detection splits work into fixed patches and candidates computed
the same way on any thread, and the reconstruction's parallel loops update
independent surfaces. Output files carry no timestamp (``result.npz`` members have a
fixed zip date), so the same result gives the same bytes.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import splidar
from splidar.cli import main
from splidar.io import load, save
from splidar.scenes import multispectral_scene

FILES = ("result.npz", "points.csv", "points.ply")


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("repro")
    p = d / "scene.npz"
    args = ["--size", "24", "24", "--bins", "100", "--ppp", "10", "--sbr", "1", "--seed", "5"]
    assert main(["simulate", "multispectral-two-layer", *args, "--out", str(p), "-q"]) == 0
    return p


def _digest(folder: Path) -> dict[str, str]:
    return {f: hashlib.sha256((folder / f).read_bytes()).hexdigest() for f in FILES}


def test_run_byte_identical_across_runs_threads_and_workers(scene_file, tmp_path):
    """`splidar run` on one input: identical bytes with 1 or 2 threads and workers.

    Two programs with 1 and 2 threads (numba, OpenMP, BLAS) and workers (``--jobs``),
    and one run inside this process (threads as configured here, default workers).
    """
    runs = []
    for threads in (1, 2):
        env = dict(os.environ)
        for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[var] = str(threads)
        out = tmp_path / f"out{threads}"
        cmd = [sys.executable, "-m", "splidar", "run", str(scene_file), "--out", str(out)]
        cmd += ["--jobs", str(threads), "--no-figures", "-q"]
        runs.append((out, subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)))
    here = tmp_path / "here"
    assert main(["run", str(scene_file), "--out", str(here), "--no-figures", "-q"]) == 0
    digests = [_digest(here)]
    for out, proc in runs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
        digests.append(_digest(out))
    assert all(d == digests[0] for d in digests[1:]), digests


def test_process_default_same_result_each_call():
    """`process` with default options three times on one cube: identical points."""
    sim = multispectral_scene((16, 16), n_bins=60).simulate(ppp=5, sbr=0.5, rng=2)
    recs = [splidar.process(sim.cube, max_iter=20) for _ in range(3)]
    for rec in recs[1:]:
        for name, value in recs[0].points.to_dict().items():
            np.testing.assert_array_equal(rec.points.to_dict()[name], value, err_msg=name)


def test_detect_same_surfaces_with_one_or_two_jobs():
    sim = multispectral_scene((20, 20), n_bins=80).simulate(ppp=5, sbr=0.5, rng=4)
    a = splidar.detect(sim.cube, n_jobs=1)
    b = splidar.detect(sim.cube, n_jobs=2)
    np.testing.assert_array_equal(a.mask, b.mask)
    for name in ("row", "col", "depth_bin", "histograms"):
        np.testing.assert_array_equal(getattr(a.surfaces, name), getattr(b.surfaces, name))


def test_save_same_cube_same_bytes(tmp_path):
    """A cube saved twice (seconds apart or not) gives the same bytes; load reads it back."""
    sim = multispectral_scene((8, 8), n_bins=40).simulate(ppp=5, sbr=1, rng=0)
    save(sim.cube, tmp_path / "a.npz")
    save(sim.cube, tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    np.testing.assert_array_equal(load(tmp_path / "a.npz").counts, sim.cube.counts)
