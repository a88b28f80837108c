"""splidar.io.estimate_irf: the non-parametric IRF shape from the data."""

from __future__ import annotations

import numpy as np
import pytest

import splidar
from splidar import PointSet, SplidarError
from splidar.io import estimate_irf
from splidar.irf import exp_tail_irf, irf_fwhm
from splidar.simulation import simulate


def _cube(irf, *, n=32, T=200, ppp=20.0, sbr=2.0, second=None, seed=0):
    """A tilted plane (depths 40..100 bins) on n x n pixels; ``second``: a surface that
    many bins behind it in every pixel."""
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    depth = (40.0 + 60.0 * (rr + cc) / (2 * n - 2)).ravel()
    row, col, dep = rr.ravel(), cc.ravel(), depth
    if second is not None:
        row, col, dep = np.r_[row, row], np.r_[col, col], np.r_[dep, dep + second]
    truth = PointSet(row=row, col=col, depth_bin=dep, image_shape=(n, n))
    sim = simulate(truth, n_bins=T, irf=irf, ppp=ppp, sbr=sbr, rng=seed)
    return sim.cube


def _on_common_grid(a, b):
    """Both IRFs (1-D) on one grid with their peaks on the same sample."""
    pa, pb = int(np.argmax(a)), int(np.argmax(b))
    o = max(pa, pb)
    n = o + max(a.size - pa, b.size - pb)
    x, y = np.zeros(n), np.zeros(n)
    x[o - pa : o - pa + a.size] = a
    y[o - pb : o - pb + b.size] = b
    return x, y, o


def test_estimate_irf_recovers_exp_tail_shape():
    true = exp_tail_irf(2.0, 6.0)
    cube = _cube(true)
    est = estimate_irf(cube.counts)
    assert est.shape[0] == 1 and np.isclose(est.sum(), 1.0) and np.all(est >= 0)
    t, e, o = _on_common_grid(true / true.sum(), est[0])
    # measured on this seed: L1 0.10, FWHM 7.5 vs 6.2 bins (whole-bin alignment of
    # sub-bin depths and the alignment's own jitter widen it), tail mass beyond +5 bins
    # 0.37 vs 0.38; a Gaussian of the true FWHM is at L1 0.72 and tail mass 0.04
    assert np.abs(t - e).sum() < 0.2
    assert abs(irf_fwhm(e) / irf_fwhm(t) - 1.0) < 0.3
    assert abs(e[o + 5 :].sum() - t[o + 5 :].sum()) < 0.08


def test_estimate_irf_does_not_take_a_second_surface_for_tail():
    true = exp_tail_irf(2.0, 4.0)
    cube = _cube(true, second=40.0, T=240)
    est = estimate_irf(cube.counts)[0]
    p = int(np.argmax(est))
    # the exp tail has < 0.3 % of its mass beyond 25 bins; the second surface (as bright
    # as the first) at +40 bins would put about half of the photons there
    assert est.size - p < 40
    assert est[p + 25 :].sum() < 0.02


def test_estimate_irf_per_wavelength_rows():
    true = exp_tail_irf(2.0, 5.0)
    cube = _cube(true)
    two = np.concatenate([cube.counts, cube.counts], axis=2)
    est = estimate_irf(two)
    assert est.shape[0] == 2
    np.testing.assert_allclose(est[0], est[1])


def test_load_estimate_shape_records_irf_source(tmp_path):
    cube = _cube(exp_tail_irf(2.0, 6.0))
    f = tmp_path / "c.npz"
    np.savez(f, counts=cube.counts)
    c = splidar.load(f, irf="estimate-shape")
    assert "estimated shape" in c.metadata["irf_source"]
    np.testing.assert_allclose(c.irf, estimate_irf(cube.counts))


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(counts=np.ones((4, 50))), "counts"),
        (dict(counts=-np.ones((4, 4, 50))), "counts"),
        (dict(counts=np.full((4, 4, 50), np.nan)), "counts"),
        (dict(counts=np.ones((4, 4, 50)), significance=0.0), "significance"),
        (dict(counts=np.ones((4, 4, 50)), fwhm=-1.0), "fwhm"),
        (dict(counts=np.ones((4, 4, 50)), fwhm=3.0, min_pixels=0), "min_pixels"),
        (dict(counts=np.ones((4, 4, 50)), fwhm=3.0, max_length=60), "max_length"),
        (dict(counts=np.ones((4, 4, 50), np.uint8), fwhm=3.0), "min_pixels"),
    ],
)
def test_estimate_irf_bad_input_names_parameter(kwargs, name):
    counts = kwargs.pop("counts")
    with pytest.raises(SplidarError, match=name):
        estimate_irf(counts, **kwargs)
