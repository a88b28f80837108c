"""The fused numba kernels of detection agree with the scipy/numpy reference."""

from __future__ import annotations

import numpy as np
import pytest

from splidar.detection._background import CLIP, robust_level
from splidar.detection._fast import poisson_background, saliency_wavelength
from splidar.detection._filters import box


def _reference(c, keep, scales, weights, dev, var_factor, quantum, spatial=None):
    m = np.zeros_like(c[keep])
    coarse = None
    for q, k in enumerate(scales):
        a = box(c, int(k))[keep]
        if weights[q] != 0:
            m += np.float32(weights[q]) * a
        coarse = a
    if spatial is None:
        spatial = robust_level(coarse, dev, var_factor, quantum=quantum)
    bh = np.maximum(spatial[..., None] + dev, 0)
    x = m - bh
    return spatial, np.abs(x), x, bh


@pytest.mark.parametrize(
    "shape, scales, weights, keep",
    [
        ((20, 17, 130), (1, 3, 7, 11), None, slice(5, 15)),
        ((9, 8, 300), (3, 5), (0.0, 1.0), slice(0, 9)),
        ((4, 30, 70), (1, 3, 7, 11), (0, 1, 0, 0), slice(0, 4)),  # rows < box: reflections
        ((12, 3, 257), (1, 9), None, slice(2, 11)),  # T beyond one tile
    ],
)
@pytest.mark.parametrize("given_spatial", [False, True])
def test_saliency_wavelength_matches_reference(shape, scales, weights, keep, given_spatial):
    rng = np.random.default_rng(0)
    c = rng.gamma(0.5, 1.0, shape).astype(np.float32)
    scales = np.asarray(scales)
    w = scales / scales.sum() if weights is None else np.asarray(weights, float)
    T = shape[-1]
    dev = (0.1 * rng.normal(size=T)).astype(np.float32)
    r = len(range(*keep.indices(shape[0])))
    sp_in = rng.uniform(0.2, 1.0, (r, shape[1])).astype(np.float32) if given_spatial else None
    ref = _reference(c, keep, scales, w, dev, 0.01, 0.002, sp_in)
    acc = [np.zeros((r, shape[1], T), np.float32) for _ in range(3)]
    sp = saliency_wavelength(
        c, keep, scales, w, dev, *acc, spatial=sp_in, var_factor=0.01, quantum=0.002, clip=CLIP
    )
    # float32 rounding of sums of up to 121 values of order 1: a few 1e-7 relative; a
    # clipping decision at the window edge could move the level by ~1/T, never seen here
    np.testing.assert_allclose(sp, ref[0], rtol=0, atol=1e-5)
    for got, want in zip(acc, ref[1:], strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)


def test_saliency_wavelength_threads_do_not_change_result():
    rng = np.random.default_rng(1)
    c = rng.gamma(0.5, 1.0, (23, 11, 90)).astype(np.float32)
    scales = np.array([1, 3, 7])
    dev = np.zeros(90, np.float32)
    out = []
    for n in (1, 3):
        acc = [np.zeros((17, 11, 90), np.float32) for _ in range(3)]
        sp = saliency_wavelength(
            c, slice(3, 20), scales, scales / 11, dev, *acc, var_factor=0.02, n_threads=n
        )
        out.append((sp, *acc))
    for a, b in zip(*out, strict=True):
        np.testing.assert_array_equal(a, b)


def test_saliency_wavelength_accumulates_over_calls():
    c = np.ones((5, 6, 40), np.float32)
    acc = [np.full((5, 6, 40), 2.0, np.float32) for _ in range(3)]
    sp = saliency_wavelength(
        c,
        slice(0, 5),
        np.array([1, 3]),
        np.array([0.5, 0.5]),
        np.zeros(40, np.float32),
        *acc,
        spatial=np.full((5, 6), 0.25, np.float32),
    )
    np.testing.assert_allclose(sp, 0.25)
    np.testing.assert_allclose(acc[1], 2.75, rtol=1e-6)  # 2 + (1 - 0.25)
    np.testing.assert_allclose(acc[2], 2.25, rtol=1e-6)


def test_poisson_background_mean_variance_and_reproducible():
    sp = np.full((20, 20, 2), 0.5, np.float32)
    dev = np.zeros((2, 500), np.float32)
    dev[1] = np.linspace(-0.6, 0.5, 500)  # bhat clipped at 0 where sp + dev < 0
    y = poisson_background(sp, dev, np.random.default_rng(5))
    y2 = poisson_background(sp, dev, np.random.default_rng(5))
    np.testing.assert_array_equal(y, y2)
    lam = np.maximum(sp[..., None] + dev, 0)
    # 200,000 draws at mean 0.5: the mean's standard error is 0.0016; 5 sigma
    assert abs(y[:, :, 0].mean() - 0.5) < 0.008
    assert abs(y[:, :, 0].var() - 0.5) < 0.02
    assert np.all(y[lam == 0] == 0)
    # mean follows the varying rate along t
    np.testing.assert_allclose(
        y[:, :, 1].mean(axis=(0, 1)).reshape(10, 50).mean(1),
        lam[0, 0, 1].reshape(10, 50).mean(1),
        atol=0.03,
    )
