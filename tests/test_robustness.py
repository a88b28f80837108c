"""Robustness of the defaults to sensors and defects other groups' data have.

The cases of ``benchmarks/bench_robustness.py`` that failed before their fix: an IRF
given in a record longer than the window, and a stuck (hot) pixel.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from splidar import Cube, PointSet, SplidarError, gaussian_irf
from splidar.detection import detect
from splidar.detection._hot_pixels import hot_pixels
from splidar.metrics import evaluate
from splidar.simulation import simulate


def _plane_cube(shape=(24, 24), n_bins=120, ppp=2.0, sbr=1.0, seed=0):
    r, c = shape
    rr, cc = np.meshgrid(np.arange(r), np.arange(c), indexing="ij")
    truth = PointSet(
        row=rr.ravel(), col=cc.ravel(), depth_bin=50.0 + 0.3 * (rr + cc).ravel(),
        image_shape=shape, intensity=np.ones((r * c, 1)),
    )  # fmt: skip
    sim = simulate(truth, n_bins=n_bins, irf=gaussian_irf(3.0), ppp=ppp, sbr=sbr, rng=seed)
    return sim.cube, sim.truth


def test_cube_irf_longer_than_t_loses_its_zero_ends():
    g = gaussian_irf(3.0)
    padded = np.zeros(625)
    padded[300 : 300 + g.size] = g  # a measured pulse in a long record of zeros
    counts = np.zeros((2, 3, 200), np.uint16)
    cube = Cube(counts, irf=padded)
    assert cube.irf.shape == (1, g.size)
    np.testing.assert_allclose(cube.irf[0], g, rtol=1e-12, atol=0)
    assert cube.irf_peak.tolist() == [g.size // 2]


def test_cube_irf_longer_than_t_refused_when_not_negligible():
    flat_tail = np.r_[gaussian_irf(3.0), np.full(300, 1e-4)]
    with pytest.raises(SplidarError, match=r"`irf` is longer .*T = 200 bins"):
        Cube(np.zeros((2, 3, 200), np.uint16), irf=flat_tail)


def test_detect_hot_pixel_set_aside_keeps_the_image(caplog):
    cube, truth = _plane_cube()
    rng = np.random.default_rng(1)
    counts = np.array(cube.counts, np.uint32)
    counts[12, 12, 0] += rng.poisson(100.0, cube.n_bins).astype(np.uint32)  # 10^4 x bg
    with caplog.at_level(logging.WARNING, logger="splidar.detection"):
        det = detect(Cube(counts, irf=cube.irf))
    assert det.options["hot_pixels"] == 1
    assert "(12, 12)" in caplog.text
    ref = detect(cube)
    # before the fix: F_true 0.10 against 0.98 (the threshold of every pixel raised)
    f_hot = evaluate(det.points, truth, tau=2).f_true
    assert f_hot >= evaluate(ref.points, truth, tau=2).f_true - 0.02
    assert ref.options["hot_pixels"] == 0


def test_hot_pixels_leaves_returns_and_bright_patches():
    rng = np.random.default_rng(2)
    T = 64
    counts = rng.poisson(0.05, (12, 12, 1, T)).astype(np.uint32)
    g = gaussian_irf(3.0)
    counts[2, 2, 0, 20 : 20 + g.size] += (1e6 * g).astype(np.uint32)  # a glint: peaked
    counts[6:9, 6:9, 0] += rng.poisson(200.0, (3, 3, T)).astype(np.uint32)  # sunlit patch
    wide = np.exp(-0.5 * ((np.arange(T) - 32) / 12.7) ** 2)  # FWHM 30 bins
    counts[10, 2, 0] += (1e4 * wide).astype(np.uint32)  # a return over half of T
    counts[2, 9, 0] += rng.poisson(200.0, T).astype(np.uint32)  # a stuck pixel
    hot = hot_pixels(counts)
    assert np.argwhere(hot).tolist() == [[2, 9]]
    assert not hot_pixels(counts[:1, :1]).any()  # one pixel: nothing to compare with


def test_cube_masked_array_dead_pixels_count_zero():
    counts = np.ones((3, 4, 1, 16), np.uint16)
    dead = np.zeros(counts.shape, bool)
    dead[1, 2] = True
    cube = Cube(np.ma.masked_array(counts * 9, mask=dead), irf=[0.25, 0.5, 0.25])
    assert cube.counts.dtype == np.uint16
    assert cube.counts[1, 2].sum() == 0  # not the 9s the mask hides
    assert cube.counts.sum() == 9 * 16 * 11


def test_cube_nan_counts_refused_suggesting_dead_pixel_forms():
    counts = np.ones((2, 2, 8))
    counts[0, 1] = np.nan
    with pytest.raises(SplidarError, match=r"`counts` holds 8 NaN .*nan_to_num.*masked array"):
        Cube(counts, irf=[1.0])


def test_fit_planes_draws_depend_on_the_hole_not_on_the_others():
    # a change elsewhere in the image adds or removes holes; each hole's random triples
    # must stay as they were (before: seeded by the hole's index in the list, so one
    # pixel zeroed in the face data moved 2,558 surfaces all over the image)
    from splidar.detection._slopes import fit_planes

    rng = np.random.default_rng(3)
    D = np.full((20, 20, 2), np.nan)
    D[..., 0] = 40 + 0.8 * np.arange(20)[:, None] + rng.normal(0, 1.5, (20, 20))
    D[..., 1] = np.where(rng.random((20, 20)) < 0.5, rng.uniform(20, 80, (20, 20)), np.nan)
    hr = np.array([3, 9, 10, 15, 16], np.int64)
    hc = np.array([4, 9, 12, 3, 15], np.int64)
    full = np.zeros((hr.size, 2, 5))
    fit_planes(D, hr, hc, 5, 3.0, 2, 6, 8, 11, full)
    part = np.zeros((hr.size - 1, 2, 5))
    fit_planes(D, hr[1:], hc[1:], 5, 3.0, 2, 6, 8, 11, part)
    np.testing.assert_array_equal(full[1:], part)


def test_triple_plane_equals_the_former_matrix_solve_bit_for_bit():
    # the trials' plane through three points from scalars: _solve3_into's values to
    # the bit (and singular where it is: repeated or collinear points)
    from splidar.detection._slopes import _solve3_into, _triple_plane

    rng = np.random.default_rng(31)
    pr = rng.integers(-5, 6, 400).astype(float)
    pc = rng.integers(-5, 6, 400).astype(float)
    pd = rng.normal(50, 10, 400)
    A, v, x = np.empty((3, 3)), np.empty(3), np.empty(3)
    n_singular = 0
    for _ in range(3000):
        i = rng.integers(0, 400, 3)
        if rng.random() < 0.1:
            pr[i[2]], pc[i[2]] = 2 * pr[i[1]] - pr[i[0]], 2 * pc[i[1]] - pc[i[0]]  # a line
        A[:, 0], A[:, 1], A[:, 2], v[:] = 1.0, pr[i], pc[i], pd[i]
        ok = _solve3_into(A, v, x)
        got = _triple_plane(pr, pc, pd, *i)
        assert got[0] == ok
        n_singular += not ok
        if ok:
            assert np.array_equal(np.array(got[1:]).view(np.uint64), x.view(np.uint64))
    assert n_singular > 50


def test_fit_planes_enclosed_as_the_inliers_directions_say():
    # a plane's ``enclosed``: in each of 8 directions an inlier lies beyond the hole
    # (or the image ends), recomputed here from the planes written
    from splidar.detection._slopes import _DIR_C, _DIR_R, fit_planes

    rng = np.random.default_rng(32)
    R = C = 24
    D = np.full((R, C, 2), np.nan)
    rows = np.arange(R)[:, None]
    D[..., 0] = 40 + 0.8 * rows + rng.normal(0, 1.0, (R, C))
    D[rng.random((R, C)) < 0.4, 0] = np.nan  # ragged patches
    D[8:17, 11:, 0] = np.nan  # holes beside a patch's edge: not enclosed
    D[..., 1] = np.where(rng.random((R, C)) < 0.4, 60 - 0.5 * rows + 0 * D[..., 0], np.nan)
    hr, hc = (a.astype(np.int64).ravel() for a in np.mgrid[0:R:3, 0:C:3])
    out = np.zeros((hr.size, 2, 5))
    fit_planes(D, hr, hc, 5, 3.0, 2, 6, 64, 7, out)
    n_open = n_closed = 0
    for h in range(hr.size):
        r0, c0 = max(hr[h] - 5, 0), max(hc[h] - 5, 0)
        dr, dc, k = np.nonzero(np.isfinite(D[r0 : hr[h] + 6, c0 : hc[h] + 6]))
        pr, pc = (dr + r0 - hr[h]).astype(float), (dc + c0 - hc[h]).astype(float)
        pd = D[dr + r0, dc + c0, k]
        used = np.zeros(pd.size, bool)
        for p in range(2):
            a, b, c, n_in, enclosed = out[h, p]
            if n_in == 0:
                break
            inl = ~used & (np.abs(a + b * pr + c * pc - pd) <= 3.0)
            assert inl.sum() == n_in
            used |= inl
            want = all(
                (_DIR_R[u] * pr[inl] + _DIR_C[u] * pc[inl] > 0).any()
                or not (0 <= hr[h] + _DIR_R[u] < R and 0 <= hc[h] + _DIR_C[u] < C)
                for u in range(8)
            )
            assert enclosed == float(want)
            n_open += not want
            n_closed += want
    assert n_open > 5 and n_closed > 5
