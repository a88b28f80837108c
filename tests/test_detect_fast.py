"""The fused numba kernels of detection agree with the scipy/numpy reference."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from splidar import gaussian_irf
from splidar.detection._background import (
    CLIP,
    LOW_FRACTION,
    _low_median,
    robust_level,
    temporal_shape,
)
from splidar.detection._fast import (
    _median_near,
    _median_scratch,
    pixel_totals,
    poisson_background,
    saliency_wavelength,
    window_means,
)
from splidar.detection._filters import Correlator, box
from splidar.detection._null import _equal_count_groups


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


@pytest.mark.parametrize("scales", [(1, 3, 7, 11), (3, 5), (1, 9)])
def test_saliency_wavelength_box_output_matches_box_filters(scales):
    # the box means handed to surface extraction are scipy's uniform_filter (reflect)
    rng = np.random.default_rng(3)
    c = rng.gamma(0.5, 1.0, (14, 13, 150)).astype(np.float32)
    keep = slice(3, 12)
    scales = np.asarray(scales)
    big = scales[scales > 1]
    T = c.shape[-1]
    acc = [np.zeros((9, 13, T), np.float32) for _ in range(3)]
    out = np.full((big.size, 9, 13, T), np.nan, np.float32)
    saliency_wavelength(
        c, keep, scales, scales / scales.sum(), np.zeros(T, np.float32), *acc, box=out
    )
    for i, k in enumerate(big):
        # float32 sums of up to 121 values of order 1: a few 1e-7 relative
        np.testing.assert_allclose(out[i], box(c, int(k))[keep], rtol=0, atol=2e-5)
    with pytest.raises(ValueError, match="box"):
        saliency_wavelength(
            c, keep, scales, scales / scales.sum(), np.zeros(T, np.float32), *acc, box=out[:, :5]
        )


@pytest.mark.parametrize("rate", [0.005, 0.5, 3.9, 4.1, 30.0])
def test_poisson_background_counts_are_independent_poisson(rate):
    # arrivals walked for rates up to 4 per bin, direct draws above (a rate that
    # crosses 4 along t mixes both): per bin, the mean and the variance equal the rate,
    # P(0) = exp(-rate), and neighbouring bins are uncorrelated. 2,500 draws per bin,
    # 300 bins: every tolerance is 5 standard errors of the pooled statistic.
    sp = np.full((50, 50, 1), rate, np.float32)
    dev = (rate * np.linspace(-0.5, 0.5, 300)).astype(np.float32)[None]
    y = poisson_background(sp, dev, np.random.default_rng(7)).astype(np.float64)
    lam = (sp[0, 0, 0] + dev[0]).astype(np.float64)
    n = 2500
    z_mean = (y.mean(axis=(0, 1, 2)) - lam) / np.sqrt(lam / n)
    assert abs(z_mean.mean()) < 5 / np.sqrt(lam.size) and np.sqrt(np.mean(z_mean**2)) < 1.2
    # variance of a Poisson sample variance: (lam + 2 lam^2) / n, pooled over the bins
    v_ratio = (y.var(axis=(0, 1, 2)) / lam).mean()
    assert abs(v_ratio - 1) < 5 * np.sqrt(np.mean((1 / lam + 2) / n) / lam.size)
    p0 = (y == 0).mean(axis=(0, 1, 2))
    se0 = np.sqrt(np.mean(np.exp(-lam) * (1 - np.exp(-lam))) / (n * lam.size))
    assert abs(np.mean(p0 - np.exp(-lam))) < 5 * se0 + 1e-12
    r = y - lam
    corr = np.mean(r[..., :-1] * r[..., 1:]) / np.sqrt(np.mean(lam[:-1] * lam[1:]))
    assert abs(corr) < 5 / np.sqrt(n * (lam.size - 1))


@pytest.mark.parametrize("n, g", [(10, 3), (5, 1), (12345, 5), (200_000, 12)])
@pytest.mark.parametrize("ties", [False, True])
def test_equal_count_groups_match_stable_sort(n, g, ties):
    rng = np.random.default_rng(n)
    if ties:  # many equal values, some straddling group boundaries
        v = rng.integers(0, max(n // 3, 1) + 1, n).astype(np.float64)
    else:
        v = rng.random(n).astype(np.float32).astype(np.float64)
    want = np.array_split(np.argsort(v, kind="stable"), g)
    got = _equal_count_groups(v, g)
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(np.sort(a), np.sort(b))
    v = np.repeat(np.arange(5.0), 200)  # one value spans whole groups
    plain = np.array_split(np.argsort(v, kind="stable"), 7)
    for a, b in zip(_equal_count_groups(v, 7), plain, strict=True):
        np.testing.assert_array_equal(np.sort(a), np.sort(b))


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


@pytest.mark.parametrize("layout", ["view", "t_strided"])
def test_saliency_wavelength_any_layout_matches_reference(layout):
    # the kernel reads the block as a flat buffer: a view of one wavelength of a
    # (R, C, L, T) block (no copy), or a contiguous copy when t is not contiguous
    rng = np.random.default_rng(3)
    c4 = rng.gamma(0.5, 1.0, (14, 9, 3, 150)).astype(np.float32)
    c = c4[:, :, 1, :] if layout == "view" else np.asfortranarray(c4[:, :, 1, :])
    scales = np.array([1, 3, 7])
    w = scales / scales.sum()
    dev = (0.05 * rng.normal(size=150)).astype(np.float32)
    keep = slice(2, 12)
    ref = _reference(c, keep, scales, w, dev, 0.02, 0.003)
    acc = [np.zeros((10, 9, 150), np.float32) for _ in range(3)]
    sp = saliency_wavelength(c, keep, scales, w, dev, *acc, var_factor=0.02, quantum=0.003)
    # float32 rounding, as in test_saliency_wavelength_matches_reference
    np.testing.assert_allclose(sp, ref[0], rtol=0, atol=1e-5)
    for got, want in zip(acc, ref[1:], strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)


def _median_sample(n, ties):
    """n float32 normal samples; with ``ties``, few distinct values (sparse coarse counts)."""
    x = np.random.default_rng(n).normal(size=n).astype(np.float32)
    return np.round(x * 2).astype(np.float32) / 4 if ties else x


@pytest.mark.parametrize("n", [1, 2, 3, 10, 75, 76, 375])
@pytest.mark.parametrize("ties", [False, True])
def test_median_scratch_equals_numpy_median(n, ties):
    x = _median_sample(n, ties)
    want = np.median(x)
    got = _median_scratch(x.copy(), n)
    assert got == np.float64(want)  # the order statistic: exact


@pytest.mark.parametrize("n", [1, 2, 3, 10, 75, 76, 375])
@pytest.mark.parametrize("ties", [False, True])
def test_median_near_equals_median_scratch_whatever_the_hint(n, ties):
    # the band about the hint only speeds the selection up: the same value with a hint
    # on the median, beside it, far off (no band holds it), NaN, or a band of width 0
    x = _median_sample(n, ties)
    want = _median_scratch(x.copy(), n)
    for hint, width in [(want, 0.1), (want, 0.0), (want + 0.05, 0.1), (want - 0.3, 0.2),
                        (50.0, 1.0), (np.nan, 0.1), (want, np.inf)]:  # fmt: skip
        assert _median_near(x.copy(), n, hint, width) == want, (hint, width)


@pytest.mark.parametrize("dtype", [np.uint16, np.int64, np.float32])
def test_window_means_exact(dtype):
    rng = np.random.default_rng(4)
    y = rng.poisson(3.0, (5, 23, 2, 40)).astype(dtype)
    cols = np.array([0, 1, 7, 18])
    got = window_means(y, cols, 5)
    ref = np.stack([y[:, a : a + 5].astype(np.float64).mean(axis=(0, 1)) for a in cols])
    assert got.dtype == np.float32
    # integer sums are exact in float64: the float32 rounding of the exact mean
    np.testing.assert_array_equal(got, ref.astype(np.float32))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.uint32, np.float32])
def test_pixel_totals_equal_numpy_sums(dtype):
    rng = np.random.default_rng(3)
    hi = 200 if dtype == np.uint8 else 60_000
    y = rng.integers(0, hi, size=(7, 5, 3, 301)).astype(dtype)
    y[2, 3] = np.iinfo(dtype).max if dtype != np.float32 else 1e6  # large values exact
    ref = y.sum(axis=(2, 3), dtype=np.float64)
    out = pixel_totals(y)
    assert out.dtype == np.float64 and out.shape == (7, 5)
    assert np.array_equal(out, ref)
    # a strided view gives the same totals as its copy
    assert np.array_equal(pixel_totals(y[::2, 1:]), ref[::2, 1:])


@pytest.mark.parametrize("m", [1, 2, 37, 38, 300])
@pytest.mark.parametrize("ties", [False, True])
def test_low_median_equals_numpy_partition(m, ties):
    rng = np.random.default_rng(m)
    x = rng.gamma(2.0, 1.0, size=(301, 45)).astype(np.float32)
    if ties:  # few distinct values, as the window means of sparse counts
        x = (np.round(x * 2) / 7).astype(np.float32)
    x[3, 5] = np.nan  # a NaN column: NumPy's rule (NaNs sorted to the end)
    k1, k2 = (m - 1) // 2, m // 2
    part = np.partition(x, [k1, k2] if k2 > k1 else k1, axis=0)
    ref = (part[k1] + part[k2]) / np.float32(2)
    assert np.array_equal(_low_median(x, m), ref, equal_nan=True)
    assert np.array_equal(_low_median(x, m, slice(7, 40)), ref[7:40], equal_nan=True)
    # the definition: the median of the lowest m values of each column
    y = np.delete(x, 5, axis=1)
    low = np.sort(y, axis=0)[:m]
    assert np.array_equal(_low_median(y, m), np.median(low, axis=0).astype(np.float32))


def test_low_median_neighbouring_columns_hint_gives_the_same_statistics():
    # columns that drift slowly (the band about the previous column's statistic holds
    # them), with jumps (the band misses): the same values as a full selection
    rng = np.random.default_rng(11)
    n, P, m = 500, 300, 50
    level = np.cumsum(rng.normal(0, 0.01, P)) + 2.0
    level[100:] += 5.0  # a jump
    level[200:210] = 0.0  # a stretch of zeros (ties at 0)
    x = (level[None, :] + rng.gamma(2.0, 0.3, size=(n, P))).astype(np.float32)
    x[:, 200:210] = 0.0
    x[:, 150] = np.float32(1.5)  # one column of ties
    k1, k2 = (m - 1) // 2, m // 2
    part = np.partition(x, [k1, k2], axis=0)
    ref = (part[k1] + part[k2]) / np.float32(2)
    assert np.array_equal(_low_median(x, m), ref)


def test_window_means_rejects_windows_outside():
    with pytest.raises(ValueError, match="columns"):
        window_means(np.zeros((3, 10, 1, 4), np.uint16), np.array([0, 8]), 3)


def _temporal_reference(counts, corr, k, smooth, n_samples=2000):
    """temporal_shape without its debiasing, as first written (numpy row sums, cumsum,
    a partition to the lowest m then their median)."""
    R, C, L, T = counts.shape
    kr, kc = min(k, R), min(k, C)
    n_pos_r, n_pos_c = R - kr + 1, C - kc + 1
    step_r = kr if n_pos_r * n_pos_c > 4 * n_samples else 1
    row_starts = np.arange(0, n_pos_r, step_r)
    step_c = max(1, int(row_starts.size * n_pos_c // n_samples))
    col_starts = np.arange(0, n_pos_c, step_c)
    sampled = np.empty((row_starts.size, col_starts.size, L, T), np.float32)
    for i, a in enumerate(row_starts):
        rs = counts[a : a + kr].sum(axis=0, dtype=np.float32)
        cs = np.concatenate([np.zeros((1, L, T)), np.cumsum(rs, axis=0, dtype=np.float64)])
        sampled[i] = (cs[col_starts + kc] - cs[col_starts]) / (kr * kc)
    coarse = corr(sampled).reshape(-1, L, T)
    n = coarse.shape[0]
    m = max(1, int(np.ceil(LOW_FRACTION * n)))
    low = np.partition(coarse, m - 1, axis=0)[:m] if m < n else coarse
    prof = np.median(low, axis=0).astype(np.float64)
    if smooth > 1:
        prof = ndimage.median_filter(prof, size=(1, smooth), mode="nearest")
    return prof.astype(np.float32)


def test_temporal_shape_identical_to_reference():
    # window sums in numba and one selection for the low median are the same arithmetic
    # as the plain numpy form: the result must be bit-identical
    rng = np.random.default_rng(6)
    T = 90
    lam = np.full((40, 60, 2, T), 0.3) * np.linspace(1.5, 0.5, T)
    lam[10:30, 20:50, :, 40:45] += 2.0  # returns in part of the image
    counts = rng.poisson(lam).astype(np.uint16)
    irf = np.stack([gaussian_irf(3.0), gaussian_irf(4.0, length=13)])
    corr = Correlator(irf, T)
    got = temporal_shape(counts, corr, 7, smooth=9, refine=False)
    np.testing.assert_array_equal(got, _temporal_reference(counts, corr, 7, smooth=9))
    # the debiased shape: deterministic, and the same on threads (one wavelength each)
    ref = temporal_shape(counts, corr, 7, smooth=9)
    np.testing.assert_array_equal(temporal_shape(counts, corr, 7, smooth=9), ref)
    np.testing.assert_array_equal(temporal_shape(counts, corr, 7, smooth=9, workers=2), ref)


def _select_reference(row, col, mass, depth, keep, k_max):
    # the stable-lexsort selection that select_sorted replaces
    idx = np.flatnonzero(keep)
    order = np.lexsort((-mass[idx], col[idx], row[idx]))
    idx = idx[order]
    r, c = row[idx], col[idx]
    new = np.ones(idx.size, bool)
    new[1:] = (r[1:] != r[:-1]) | (c[1:] != c[:-1])
    rank = np.arange(idx.size) - np.flatnonzero(new)[np.cumsum(new) - 1]
    idx = idx[rank < k_max]
    idx = idx[np.lexsort((depth[idx], col[idx], row[idx]))]
    r, c = row[idx], col[idx]
    new = np.ones(idx.size, bool)
    new[1:] = (r[1:] != r[:-1]) | (c[1:] != c[:-1])
    slot = np.arange(idx.size) - np.flatnonzero(new)[np.cumsum(new) - 1]
    return idx, slot, rank


@pytest.mark.parametrize("k_max", [1, 2, 3])
def test_select_sorted_matches_lexsort_selection(k_max):
    from splidar.detection._6_select import _select
    from splidar.detection._table import _rank_in_pixel

    rng = np.random.default_rng(k_max)
    n = 5000
    pix = np.sort(rng.integers(0, 900, n))  # raster order, 0-12 candidates per pixel
    row, col = pix // 30, pix % 30
    mass = rng.integers(0, 4, n).astype(float)  # many ties
    depth = rng.integers(0, 6, n).astype(float)
    keep = rng.random(n) < 0.8
    surf = dict(row=row, col=col, saliency_mass=mass, depth_bin=depth)
    idx, slot = _select(surf, keep, k_max)
    ref_idx, ref_slot, _ = _select_reference(row, col, mass, depth, keep, k_max)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_array_equal(slot, ref_slot)
    # rank within the pixel: the stable lexsort's
    rank = _rank_in_pixel(row, col, mass, keep)
    k = np.flatnonzero(keep)
    order = np.lexsort((-mass[k], col[k], row[k]))
    r, c = row[k][order], col[k][order]
    new = np.ones(k.size, bool)
    new[1:] = (r[1:] != r[:-1]) | (c[1:] != c[:-1])
    want = np.full(n, -1)
    want[k[order]] = np.arange(k.size) - np.flatnonzero(new)[np.cumsum(new) - 1]
    np.testing.assert_array_equal(rank, want)
    # out of raster order (slope recovery appends): the lexsort path; without ties (they
    # are broken by position, which the permutation changes) the same choice
    surf = dict(row=row, col=col, saliency_mass=rng.random(n), depth_bin=rng.random(n))
    idx, slot = _select(surf, keep, k_max)
    perm = rng.permutation(n)
    idx_p, slot_p = _select({key: v[perm] for key, v in surf.items()}, keep[perm], k_max)
    np.testing.assert_array_equal(perm[idx_p], idx)
    np.testing.assert_array_equal(slot_p, slot)


def _correlate_reference(y, irf):
    """``C[t] = sum_j g[j] Y[t - p + j]`` in float64, Y mirrored (half-sample) at the
    window edges, one tap at a time."""
    y = np.asarray(y, np.float64)
    T = y.shape[-1]
    out = np.zeros(y.shape)
    for l, g in enumerate(irf):
        p = int(np.argmax(g))
        for j, gj in enumerate(g):
            idx = np.arange(T) - p + j
            idx = np.where(idx < 0, -idx - 1, idx)
            idx = np.where(idx >= T, 2 * T - 1 - idx, idx)
            out[..., l, :] += gj * y[..., l, idx]
    return out


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_correlator_direct_matches_reference_and_fft(dtype):
    # short IRFs (the direct sum) and a long one (the FFT): both the float64 reference
    # to float32 rounding of the sums; an asymmetric IRF with its peak near one end checks the
    # mirrored edges on both sides
    from splidar.detection._filters import DIRECT_MAX_TAPS

    rng = np.random.default_rng(3)
    T = 150
    tail = np.exp(-np.arange(9) / 2.0)
    irfs = [
        np.stack([gaussian_irf(2.0, length=13), gaussian_irf(3.0, length=13)]),
        np.stack([tail / tail.sum(), tail[::-1] / tail.sum()]),  # peak at either end
    ]
    y = rng.poisson(np.full((4, 5, 2, T), 2.0)).astype(dtype)
    for irf in irfs:
        c = Correlator(irf, T)
        assert c.direct and irf.shape[1] <= DIRECT_MAX_TAPS
        ref = _correlate_reference(y, irf)
        got = c(y)
        assert got.dtype == np.float32
        # float32 taps and sums of non-negative terms: each rounding (the tap, the
        # product, two in a group of four taps, one per group added to the accumulator,
        # at most 3 + 4 of them at 13 taps) is at most 2**-24 relative, so about 8 of
        # them: within 1e-6 of the float64 reference (2.3e-7 seen)
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-12)
        # threads over the rows: the same result; a given ``out`` is written
        out = np.empty(y.shape, np.float32)
        np.testing.assert_array_equal(c(y, workers=2, out=out), got)
        np.testing.assert_array_equal(out, got)
        # the FFT path (long IRFs) agrees to float32 rounding of the largest response
        c.direct = False
        np.testing.assert_allclose(c(y), ref, rtol=0, atol=2e-6 * np.abs(ref).max())


def _one_group_per_sweep(x, g, peak):
    """The former ``_correlate_direct_kernel`` in NumPy float32: a zeroed accumulator,
    one four-tap group ``(g0 a + g1 b) + (g2 c + g3 e)`` added per sweep, then the last
    ``n % 4`` taps one at a time; rows mirrored like scipy.ndimage ``mode="reflect"``."""
    M, L, T = x.shape
    n = g.shape[1]
    out = np.empty((M, L, T), np.float32)
    for l in range(L):
        idx = np.arange(T)[:, None] - peak[l] + np.arange(n)[None, :]
        m = np.mod(idx, 2 * T)
        idx = np.where(m >= T, 2 * T - 1 - m, m)
        xp = x[:, l, :].astype(np.float32)[:, idx]  # (M, T, n)
        acc = np.zeros((M, T), np.float32)
        j = 0
        while j + 4 <= n:
            q = [g[l, j + i] * xp[:, :, j + i] for i in range(4)]
            acc = acc + ((q[0] + q[1]) + (q[2] + q[3]))
            j += 4
        for i in range(j, n):
            acc = acc + g[l, i] * xp[:, :, i]
        out[:, l] = acc
    return out


@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_tap_sweeps_equal_one_group_per_sweep_bit_for_bit(dtype):
    # two groups per sweep and the remainder fused into the last group's sweep: the
    # same float32 additions in the same order per output bin as the former kernel, for
    # every IRF length 1..60 (odd and even, every remainder), peaks anywhere (mirrored
    # margins past either end, several reflections when T is shorter than the IRF)
    from splidar.detection._fast import _correlate_direct_kernel, _mirror_index, _tap_sweeps

    rng = np.random.default_rng(11)
    assert _mirror_index(2, 3, 4).tolist() == [1, 0, 2, 1, 0, 0]
    for n in range(1, 61):
        for T in (3, 17, 150):
            L = 2
            if dtype == np.uint16:
                x = rng.poisson(rng.choice([0.1, 4.0, 300.0]), (3, L, T)).astype(dtype)
            else:
                x = rng.standard_normal((3, L, T)) * 10.0 ** rng.uniform(-3, 3)
            g = rng.gamma(2.0, 1.0, (L, n))
            g = (g / g.sum(axis=1, keepdims=True)).astype(np.float32)
            g[0, rng.integers(n)] *= -1  # a negative tap: cancellations in the sums
            peak = rng.integers(0, n, L).astype(np.int64)
            out = np.full(x.shape, np.nan, np.float32)
            _correlate_direct_kernel(x, g, peak, int(peak.max()), out)
            ref = _one_group_per_sweep(x, g, peak)
            np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))
    # one row through the sweeps alone, the output written over stale values
    xp = rng.standard_normal(40).astype(np.float32)
    gl = rng.standard_normal(13).astype(np.float32)
    o = np.full(20, 7.0, np.float32)
    _tap_sweeps(o, xp, 3, gl, 13)
    ref = _one_group_per_sweep(xp[None, None, 3:], gl[None, :], np.array([0]))[0, 0, :20]
    np.testing.assert_array_equal(o.view(np.uint32), ref.view(np.uint32))


def test_correlator_long_irf_uses_fft():
    from splidar.detection._filters import DIRECT_MAX_TAPS

    g = gaussian_irf(15.0)
    assert g.size > DIRECT_MAX_TAPS
    c = Correlator(g[None, :], 200)
    assert not c.direct
    y = np.random.default_rng(0).poisson(1.0, size=(3, 1, 200)).astype(np.uint16)
    np.testing.assert_allclose(
        c(y), _correlate_reference(y, g[None, :]), rtol=0, atol=1e-5 * y.max()
    )


def _level_reference(sp, dev):
    """``sum_l max(sp_l + dev_l, 0)`` in float32, wavelengths in order: (r, C, T)."""
    lv = None
    for l in range(sp.shape[2]):
        bh = sp[:, :, l, None] + dev[l]
        bh = np.where(bh < 0, np.float32(0.0), bh).astype(np.float32)
        lv = bh if lv is None else (lv + bh).astype(np.float32)
    return lv


@pytest.mark.parametrize("G", [1, 2, 12])
def test_threshold_pass_equals_bisection(G):
    # the table interval found by counting the table points below a level gives the
    # same threshold as the bisection, also for levels on the table's points and beyond it
    from splidar.detection._kernels import _interp_table, threshold_pass

    rng = np.random.default_rng(4)
    r, C, T, L = 3, 5, 300, 2
    xs = np.sort(rng.uniform(0, 10, 12))
    ys = rng.uniform(1, 5, 12)
    if G < 12:
        xs, ys = xs[[3, 8][:G]], ys[:G]
    # levels sum_l max(sp + dev, 0): a slow drift over the whole table and beyond it
    dev = np.stack([np.linspace(-2, 10, T), rng.normal(0, 0.3, T)]).astype(np.float32)
    sp = rng.uniform(-1, 1.5, (r, C, L)).astype(np.float32)
    dev[:, 7] = 0.0
    sp[0, 0] = (np.float32(xs[G // 4]), 0.0)  # bin 7 of pixel (0, 0) on a table point
    level = _level_reference(sp, dev)
    assert level[0, 0, 7] == np.float32(xs[G // 4])
    assert level.min() < xs[0] and level.max() > xs[-1]
    sal = rng.uniform(0, 6, (r, C, T)).astype(np.float32)
    d = rng.normal(size=(r, C, T)).astype(np.float32)
    y = rng.poisson(1.0, (r + 2, C, L, T)).astype(np.uint16)
    thr = np.empty((r, C, T), np.float32)
    mask = np.empty((r, C, T), bool)
    cand, ev = np.empty_like(mask), np.empty((r, C, T), np.float32)
    n_ph, n_kept = threshold_pass(sal, d, sp, dev, xs, ys, y, 1, 0, thr, True, mask, cand, ev)
    ref = np.vectorize(lambda v: np.float32(_interp_table(np.float64(v), xs, ys)))(level)
    np.testing.assert_array_equal(thr, ref.astype(np.float32))
    np.testing.assert_array_equal(mask, sal > ref)
    np.testing.assert_array_equal(cand, (sal > ref) & (d > 0))
    np.testing.assert_array_equal(ev, np.maximum(sal / ref - np.float32(1), 0).astype(np.float32))
    assert n_ph == int(y[1:4].astype(np.int64).sum())
    assert n_kept == int((y[1:4].astype(np.int64) * mask[:, :, None, :]).sum())


def test_threshold_pass_table_points_between_float32_values():
    # the table interval is counted in float32 against each point rounded up to a
    # float32: a level equal to a float32 table point, or to the float32 just above or
    # below a point that no float32 represents, falls in the bisection's interval
    from splidar.detection._kernels import _interp_table, _table_ceil32, threshold_pass

    f = np.float32([0.5, 0.75, 1.0, 1.25, 1.5, 2.0])
    up = np.nextafter(f, np.float32(np.inf))
    xs = f.astype(np.float64)
    xs[[1, 3]] += 1e-12  # not float32: between f and the next float32 up
    xs[4] -= 1e-12  # just below a float32
    ys = np.array([1.0, 1.5, 1.2, 2.0, 2.5, 3.0])
    assert np.array_equal(_table_ceil32(xs), np.where(xs > f, up, f))
    levels = np.concatenate([f, up, np.nextafter(f, np.float32(-np.inf)), [0.1, 3.0]])
    T, L = levels.size, 1
    sp = np.zeros((1, 1, L), np.float32)
    dev = levels.astype(np.float32)[None, :]  # the level sum_l max(sp + dev, 0) = levels
    sal = np.full((1, 1, T), 2.0, np.float32)
    y = np.zeros((1, 1, L, T), np.uint16)
    thr, mask = np.empty((1, 1, T), np.float32), np.empty((1, 1, T), bool)
    cand, ev = np.empty_like(mask), np.empty((1, 1, T), np.float32)
    threshold_pass(sal, sal, sp, dev, xs, ys, y, 0, 0, thr, True, mask, cand, ev)
    ref = [np.float32(_interp_table(np.float64(np.float32(v)), xs, ys)) for v in levels]
    np.testing.assert_array_equal(thr[0, 0], np.array(ref, np.float32))


def test_threshold_pass_level_is_the_saliency_kernels_level():
    # the threshold pass recomputes sum_l bhat from the levels and dev: the same bits
    # as the saliency kernel's accumulated level (which the map pass no longer stores)
    from splidar.detection._kernels import threshold_pass

    rng = np.random.default_rng(8)
    R, C, T, L = 6, 9, 80, 3
    scales, weights = np.array([1, 3]), np.array([0.4, 0.6])
    dev = rng.normal(0, 0.5, (L, T)).astype(np.float32)
    acc = [np.zeros((R, C, T), np.float32) for _ in range(3)]
    acc_nolevel = [np.zeros((R, C, T), np.float32) for _ in range(2)]
    sp = np.empty((R, C, L), np.float32)
    for l in range(L):
        c = rng.gamma(2.0, 0.5, (R, C, T)).astype(np.float32)
        args = (c, slice(0, R), scales, weights, dev[l])
        sp[:, :, l] = saliency_wavelength(*args, *acc, var_factor=0.2, overwrite=l == 0)
        saliency_wavelength(*args, *acc_nolevel, None, var_factor=0.2, overwrite=l == 0)
    sal, d, level = acc
    np.testing.assert_array_equal(acc_nolevel[0], sal)
    np.testing.assert_array_equal(acc_nolevel[1], d)
    np.testing.assert_array_equal(_level_reference(sp, dev), level)
    from splidar.detection._kernels import _interp_table

    xs, ys = np.sort(rng.uniform(level.min(), level.max(), 7)), rng.uniform(1, 3, 7)
    y = np.zeros((R, C, L, T), np.uint16)
    thr, mask = np.empty((R, C, T), np.float32), np.empty((R, C, T), bool)
    cand, ev = np.empty_like(mask), np.empty((R, C, T), np.float32)
    threshold_pass(sal, d, sp, dev, xs, ys, y, 0, 0, thr, True, mask, cand, ev)
    ref = np.vectorize(lambda v: np.float32(_interp_table(np.float64(v), xs, ys)))(level)
    np.testing.assert_array_equal(thr, ref)
    np.testing.assert_array_equal(mask, sal > ref)


@pytest.mark.parametrize("stored_boxes", [True, False])
def test_extraction_order_does_not_change_detection(monkeypatch, stored_boxes):
    # candidates are extracted by depth band, then pixel (cache); in raster order every
    # output must be the same bit for bit, with the saliency pass's box means and with
    # the per-candidate box sums (large T: column sums cached per depth band and row)
    from splidar.detection import _4_map, detect
    from splidar.scenes import two_layer_scene

    if not stored_boxes:
        monkeypatch.setattr(_4_map, "_store_boxes", lambda *a: False)
    sim = two_layer_scene((24, 24), n_bins=120).simulate(ppp=10, sbr=1.0, rng=5)
    ref = detect(sim.cube, rng=0, n_jobs=1)
    monkeypatch.setattr(_4_map, "_ORDER_BAND", 1 << 40)
    other = detect(sim.cube, rng=0, n_jobs=1)
    assert len(ref.surfaces) > 300
    for name in ("depth_bin", "histograms", "evidence", "presence_llr", "signal"):
        np.testing.assert_array_equal(getattr(other.surfaces, name), getattr(ref.surfaces, name))


@pytest.mark.parametrize("strip", [1, 5, 16, 64])
def test_saliency_wavelength_column_blocks_and_strips_give_the_same_bits(strip):
    # float noise over 6 decades (what an FFT leaves): float64 running column sums are
    # then inexact, and only carrying them between blocks reproduces the full row's bits
    rng = np.random.default_rng(3)
    R, C, T = 9, 40, 70
    c = (rng.gamma(0.3, 1.0, (R, C, T)) * 10.0 ** rng.uniform(-6, 2, (R, C, T))).astype(np.float32)
    scales, w = np.array([1, 3, 7]), np.array([0.5, 0.3, 0.2])
    dev = np.zeros(T, np.float32)
    full = [np.empty((R, C, T), np.float32) for _ in range(3)]
    sp = saliency_wavelength(c, slice(0, R), scales, w, dev, *full, overwrite=True, strip=strip)
    got = [np.empty((R, C, T), np.float32) for _ in range(3)]
    sp2 = np.empty((R, C), np.float32)
    carry = np.empty((R, 3, T), np.float64)
    for a, b in ((0, 9), (9, 21), (21, 40)):  # blocks with a halo of h + 1 = 4 columns
        e0, e1 = max(0, a - 4), min(C, b + 4)
        acc = [np.empty((R, b - a, T), np.float32) for _ in range(3)]
        keep_cols = slice(a - e0, b - e0)
        sp2[:, a:b] = saliency_wavelength(
            c[:, e0:e1], slice(0, R), scales, w, dev, *acc, overwrite=True,
            keep_cols=keep_cols, strip=strip, carry=carry,
        )  # fmt: skip
        for g, x in zip(got, acc, strict=True):
            g[:, a:b] = x
    np.testing.assert_array_equal(sp2, sp)
    for g, f in zip(got, full, strict=True):
        np.testing.assert_array_equal(g, f)


def _box_sums_reference(c, scales, irow, jcol, e0, ce0, off, W, n_rows, n_cols):
    """Box sums about one pixel with NumPy: (Q, L, W) float64, scipy's reflect rule."""
    out = []
    for k in scales:
        h = int(k) // 2
        ri = np.array([_refl_np(irow + d, n_rows) for d in range(-h, h + 1)]) - e0
        cj = np.array([_refl_np(jcol + d, n_cols) for d in range(-h, h + 1)]) - ce0
        blk = c[np.ix_(ri, cj)][..., off : off + W].astype(np.float64)
        out.append(blk.sum(axis=(0, 1)))
    return np.stack(out)


def _refl_np(i, n):
    m = i % (2 * n)
    return 2 * n - 1 - m if m >= n else m


def _box_sums_call(c, scales, irow, jcol, e0, ce0, off, W, n_rows, n_cols, cache=None):
    """``_box_sums`` with a cold cache, or ``cache = (colbuf, valid, state, hint)``."""
    from splidar.detection._kernels import _box_sums

    Q, L = scales.size, c.shape[2]
    colbuf, valid, state, hint = cache or (
        np.empty((Q, c.shape[1], L, W)),
        np.zeros((c.shape[1], 3), np.int64),
        np.array([0, -1, 0]),
        off,
    )
    acc = np.empty((Q, L, W))
    rr = np.empty(int(scales[-1]) // 2 * 2 + 1, np.int64)
    _box_sums(
        acc, colbuf, valid, state, rr, c, scales, irow, jcol, e0, ce0, hint, off, n_rows, n_cols
    )
    return acc


@pytest.mark.parametrize("scales", [(1, 3, 7, 11), (3, 5), (1,)])
def test_box_sums_match_numpy_boxes_at_edges_and_inside(scales):
    # integer-valued float32: every float64 sum is exact, so any order gives the same bits
    rng = np.random.default_rng(11)
    scales = np.array(scales, np.int64)
    n_rows, n_cols, L, T = 14, 12, 2, 40
    c = rng.poisson(3.0, (n_rows, n_cols, L, T)).astype(np.float32)
    W = 9
    for irow, jcol, off in [(0, 0, 0), (13, 11, 31), (6, 5, 12), (2, 10, 3), (12, 1, 20)]:
        got = _box_sums_call(c, scales, irow, jcol, 0, 0, off, W, n_rows, n_cols)
        ref = _box_sums_reference(c, scales, irow, jcol, 0, 0, off, W, n_rows, n_cols)
        np.testing.assert_array_equal(got, ref)
    # a block holding image rows [3, 14) and columns [2, 12): indices shift, sums do not
    got = _box_sums_call(c[3:, 2:], scales, 8, 7, 3, 2, 10, W, n_rows, n_cols)
    np.testing.assert_array_equal(got, _box_sums_reference(c, scales, 8, 7, 0, 0, 10, W, 14, 12))


def test_reflect_fast_path_is_the_reflect_rule():
    from splidar.detection._fast import _refl
    from splidar.detection._kernels import _reflect

    for n in (1, 2, 5, 13):
        for i in range(-3 * n - 2, 3 * n + 2):
            assert _reflect(i, n) == _refl(i, n) == _refl_np(i, n)


def test_box_sums_cached_column_sums_give_the_same_bits():
    # float noise over 6 decades: float64 sums are inexact, so the same bits from a warm
    # cache (shifted windows, neighbouring pixels of one row) as from a cold one show that
    # each column sum is computed in one fixed order; the values are NumPy's to rounding
    rng = np.random.default_rng(5)
    scales = np.array([1, 3, 7, 11], np.int64)
    n_rows, n_cols, L, T, W, n_span = 16, 30, 3, 64, 13, 29
    c = rng.random((n_rows, n_cols, L, T)) * 10.0 ** rng.uniform(-6, 0, (n_rows, n_cols, L, T))
    c = c.astype(np.float32)
    Q = scales.size
    colbuf = np.empty((Q, n_cols, L, n_span))
    valid = np.zeros((n_cols, 3), np.int64)
    state = np.array([0, -1, 0])
    # windows inside a cached interval, overlapping it on either side, touching it, apart
    # from it (the interval restarts), leaving the span (the cache restarts)
    cases = [(4, 20), (5, 24), (9, 36), (6, 22), (29, 30), (0, 27), (3, 50), (2, 21),
             (4, 8), (5, 5), (6, 18), (7, 4), (8, 6), (6, 20), (7, 3)]  # fmt: skip
    for jcol, off in cases:
        warm = _box_sums_call(c, scales, 7, jcol, 0, 0, off, W, n_rows, n_cols,
                              cache=(colbuf, valid, state, 20))  # fmt: skip
        cold = _box_sums_call(c, scales, 7, jcol, 0, 0, off, W, n_rows, n_cols)
        np.testing.assert_array_equal(warm, cold)
        ref = _box_sums_reference(c, scales, 7, jcol, 0, 0, off, W, n_rows, n_cols)
        np.testing.assert_allclose(warm, ref, rtol=1e-12, atol=0)


@pytest.mark.parametrize("scales", [(1, 3, 7, 11), (3, 5), (1,), (5, 7, 15), (1, 9)])
def test_row_pass_equals_one_row_pair_at_a_time(scales):
    # float noise over 6 decades (inexact float32 sums): two row pairs per pass and the
    # copy of the scale below fused give the bits of adding one pair after the other
    from splidar.detection._fast import _refl, _row_pass

    rng = np.random.default_rng(25)
    scales = np.array(scales, np.int64)
    R, C, T = 9, 6, 40
    c = rng.random((R, C, T)) * 10.0 ** rng.uniform(-6, 0, (R, C, T))
    cf = c.astype(np.float32).reshape(-1)
    sr, sc = C * T, T
    Q, tn, t0, ja, jb = scales.size, 24, 10, 1, 5
    for i in (0, 2, 4, 8):  # rows reflected at both image edges
        V = np.full((Q, C, 32), np.nan, np.float32)
        _row_pass(cf, 0, R, sr, sc, i, ja, jb, t0, tn, scales, V)
        for q in range(Q):
            for j in range(ja, jb):
                v = cf[i * sr + j * sc + t0 : i * sr + j * sc + t0 + tn].copy()
                for d in range(1, int(scales[q]) // 2 + 1):
                    a = _refl(i - d, R) * sr + j * sc + t0
                    b = _refl(i + d, R) * sr + j * sc + t0
                    v = v + (cf[a : a + tn] + cf[b : b + tn])
                np.testing.assert_array_equal(V[q, j, :tn].view(np.uint32), v.view(np.uint32))
        assert np.isnan(V[:, [0, 5]]).all() and np.isnan(V[:, :, tn:]).all()


def test_fill_columns_equals_centre_out_float64_sums_in_order():
    # float noise over 6 decades (inexact float64 sums): the register-kept running sum
    # gives, at every scale, the bits of the centre row plus rows -d, +d added one at a
    # time in that order (the order the cached boxes of extract_surfaces rely on)
    from splidar.detection._kernels import _fill_columns

    rng = np.random.default_rng(37)
    n_rows, n_cols, L, T, span = 13, 4, 3, 50, 21
    c = rng.random((n_rows, n_cols, L, T)) * 10.0 ** rng.uniform(-6, 0, (n_rows, n_cols, L, T))
    c = c.astype(np.float32)
    for scales in ([1, 3, 7, 11], [3, 5], [1], [5, 7]):
        scales = np.array(scales, np.int64)
        Q, hmax = scales.size, int(scales[-1]) // 2
        rr = np.array([6] + [6 + s * d for d in range(1, hmax + 1) for s in (-1, 1)], np.int64)
        colbuf = np.full((Q, n_cols, L, span), np.nan)
        a, b, ts = 17, 35, 15
        _fill_columns(colbuf, c, scales, rr, 2, a, b, ts)
        for q in range(Q):
            for l in range(L):
                for t in range(a, b):
                    v = float(c[rr[0], 2, l, t])
                    for d in range(1, int(scales[q]) // 2 + 1):
                        v = v + float(c[rr[2 * d - 1], 2, l, t])
                        v = v + float(c[rr[2 * d], 2, l, t])
                    assert colbuf[q, 2, l, t - ts] == v
        # nothing written outside [a, b) of column 2
        assert np.isnan(colbuf[:, 2, :, : a - ts]).all()
        assert np.isnan(colbuf[:, 2, :, b - ts :]).all()
        assert np.isnan(colbuf[:, [0, 1, 3]]).all()


def _segments_reference(mask, d, s, e, min_sep, rho):
    """find_segments without the fine split, in plain Python (runs of the mask, peaks of
    ``d`` strongest first, cuts at the first minimum between kept peaks, sums in order)."""
    out = []
    R, C, T = mask.shape
    for i in range(R):
        for j in range(C):
            m = np.r_[False, mask[i, j], False]
            starts = np.flatnonzero(m[1:] & ~m[:-1])
            stops = np.flatnonzero(~m[1:] & m[:-1])
            dd = [float(v) for v in d[i, j]]
            for a, b in zip(starts, stops, strict=True):
                cand = [
                    t
                    for t in range(a, b)
                    if dd[t] >= (dd[t - 1] if t > a else -np.inf)
                    and dd[t] > (dd[t + 1] if t < b - 1 else -np.inf)
                ]
                if not cand:
                    cand = [a + int(np.argmax(dd[a:b]))]
                acc = []
                for p in sorted(cand, key=lambda t: -dd[t]):
                    ok = all(
                        abs(p - q) >= min_sep
                        and min(dd[min(p, q) : max(p, q) + 1]) <= rho * min(dd[p], dd[q])
                        for q in acc
                    )
                    if ok:
                        acc.append(p)
                peaks = sorted(acc)
                lo = a
                for k, pk in enumerate(peaks):
                    if k < len(peaks) - 1:
                        seg = dd[pk : peaks[k + 1] + 1]
                        hi = max(pk + int(np.argmin(seg)), lo + 1)
                    else:
                        hi = b
                    mass = 0.0
                    ev = 0.0
                    for t in range(lo, hi):
                        mass += float(s[i, j, t])
                        ev += float(e[i, j, t])
                    out.append((i, j, lo, hi, pk, mass, ev))
                    lo = hi
    return out


def _random_segment_block(seed, R=3, C=5, T=160):
    rng = np.random.default_rng(seed)
    # smooth bumps of several widths: runs with one peak, several peaks, flat tops
    d = rng.normal(0.0, 0.05, (R, C, T))
    tt = np.arange(T)
    for _ in range(R * C * 4):
        i, j = rng.integers(R), rng.integers(C)
        d[i, j] += rng.uniform(0.3, 2.0) * np.exp(
            -0.5 * ((tt - rng.uniform(0, T)) / rng.uniform(1.0, 8.0)) ** 2
        )
    d = d.astype(np.float32)
    d[0, 0, 40:48] = 1.0  # a flat run
    mask = np.ascontiguousarray(d > 0.15)
    mask[0, 1] = True  # one run over the whole series
    s = rng.uniform(0, 1, (R, C, T)).astype(np.float32)
    e = rng.uniform(0, 1, (R, C, T)).astype(np.float32)
    return mask, d, s, e


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_find_segments_equals_python_reference_on_random_blocks(seed):
    # the run walk over each pixel's row and the one-peak path give every segment as
    # the plain definition does (bit for bit)
    from splidar.detection._kernels import find_segments

    mask, d, s, e = _random_segment_block(seed)
    no4 = np.empty((0, 0, 0, 0), np.float32)
    no3 = np.empty((0, 0, 0), np.float32)
    fine = (no4, no4.astype(np.uint16), 0, 0, no3, np.empty((0, 0), np.float32), no3, no3, no3)
    split = (0.0, np.zeros((2, 1)), 1.0, np.zeros((1, 2), np.int64), 0, False)
    got = find_segments(mask, d, s, e, 3, 0.5, fine, split)
    ref = _segments_reference(mask, d, s, e, 3, 0.5)
    assert len(ref) > 3 * mask.shape[0] * mask.shape[1]  # several runs and splits per pixel
    assert [tuple(a[k] for a in got[:7]) for k in range(got[0].size)] == ref
    assert not got[7].any()


@pytest.mark.parametrize("seed", [0, 1])
def test_find_segments_fine_split_from_counts_equals_precomputed_response(seed):
    # the map pass's way (the fine response read from the correlated counts, n and mu
    # only at the response's local maxima) gives the segments of the null's way (every
    # voxel's f, n and mu precomputed by fine_response): bit for bit, splits included
    from splidar.detection._3_null import split_rule
    from splidar.detection._kernels import find_segments, fine_response

    rng = np.random.default_rng(seed)
    R, C, L, T = 3, 6, 2, 150
    g = gaussian_irf(3.0).reshape(1, -1).repeat(L, 0)
    lam = np.full((R, C, L, T), 0.05)
    tt = np.arange(T)
    for _ in range(R * C * 3):
        i, j = rng.integers(R), rng.integers(C)
        prof = np.exp(-0.5 * ((tt - rng.uniform(10, T - 10)) / 1.3) ** 2)
        lam[i, j] += rng.uniform(3, 20) * prof / prof.sum()
    y = rng.poisson(lam).astype(np.uint16)
    c = Correlator(g, T)(y, workers=1)
    sp = np.full((R, C, L), 0.05, np.float32)
    dev = rng.normal(0, 0.005, (L, T)).astype(np.float32)
    # a broad d over the returns: the coarse scales merge them, the fine split cuts
    d = np.stack([np.convolve(v, np.ones(9) / 9, "same") for v in c.sum(2).reshape(-1, T)])
    d = (d.reshape(R, C, T) - 0.1).astype(np.float32)
    mask = np.ascontiguousarray(d > 0.05)
    s = rng.uniform(0, 1, (R, C, T)).astype(np.float32)
    rule = split_rule(g, 2.0)
    no = np.empty((0, 0, 0), np.float32)
    from_c = find_segments(mask, d, s, s, 3, 0.5, (c, y, 0, 0, sp, dev, no, no, no), rule)
    pre = tuple(np.empty((R, C, T), np.float32) for _ in range(3))
    fine_response(c, y, sp, dev, rule[3], *pre)
    empty = (np.empty((0,) * 4, np.float32), np.empty((0,) * 4, np.uint16), 0, 0, no)
    no_dev = np.empty((0, 0), np.float32)
    from_f = find_segments(mask, d, s, s, 3, 0.5, (*empty, no_dev, *pre), rule)
    assert from_c[7].sum() >= 3  # the fine split cut some segments
    for a, b in zip(from_c, from_f, strict=True):
        np.testing.assert_array_equal(a, b)
