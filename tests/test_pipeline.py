"""Tests of splidar.pipeline.process (detect, then reconstruct)."""

from __future__ import annotations

import numpy as np
import pytest

from splidar import Cube, SplidarError
from splidar.pipeline import process


@pytest.fixture(scope="module")
def sim():
    from splidar.scenes import multispectral_scene

    return multispectral_scene((24, 24), n_bins=160).simulate(ppp=10, sbr=1, rng=0)


def test_process_runs_both_stages_with_cube_library(sim):
    rec = process(sim.cube, rng=0)
    assert {"detect", "reconstruct", "process"} <= set(rec.timings)
    assert rec.timings["process"] >= rec.timings["detect"] + rec.timings["reconstruct"] - 1e-6
    # the library defaults to the cube's
    assert rec.library is not None
    np.testing.assert_array_equal(rec.library.signatures, sim.cube.library.signatures)
    assert rec.hyperparameters["classes"] == "library"
    from splidar.metrics import evaluate

    m = evaluate(rec.points, sim.truth, tau=2.0)
    # 576 true surfaces at 10 photons per pixel: most found and labelled (measured
    # F_true 0.98, label accuracy 0.98 on 48 x 48 versions of this scene)
    assert m.f_true > 0.9
    assert m.label_accuracy > 0.9


def test_process_splits_options(sim):
    rec = process(sim.cube, pfa=1e-4, max_surfaces=1, gamma=3.0, links="all", rng=0)
    assert rec.detection.pfa == pytest.approx(1e-4)
    assert rec.n_layers == 1
    assert rec.hyperparameters["gamma"] == 3.0
    assert rec.hyperparameters["links"] == "all"


def test_process_without_library_one_class(sim):
    cube = Cube(sim.cube.counts, irf=sim.cube.irf, bin_width_ps=sim.cube.bin_width_ps)
    rec = process(cube, rng=0)
    assert rec.library is None and rec.hyperparameters["classes"] == "one"
    assert np.all(rec.points.label == 0)


def test_process_unknown_option_lists_valid_ones(sim):
    with pytest.raises(SplidarError, match="unknown option") as exc:
        process(sim.cube, gama=4.0)
    msg = str(exc.value)
    assert "gama" in msg and "'gamma'" in msg and "'pfa'" in msg


def test_process_rejects_non_cube():
    with pytest.raises(SplidarError, match="Cube"):
        process(np.zeros((4, 4, 10)))
