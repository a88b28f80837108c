"""Fused numba kernels of the detection's main pass (issue 6: speed).

One kernel per wavelength replaces, for a block of correlated counts, the per-scale
:func:`scipy.ndimage.uniform_filter` calls, the weighted multiscale sum, the robust
background level (:func:`~splidar.detection._background.robust_level`), ``bhat``
(``eq:background_3``) and the saliency accumulation (``eq:4.s1``): the correlated
block is read about once per output row from cache, and no ``(rows, cols, T)``
temporary is allocated per scale or step.

The box filters reproduce :func:`~splidar.detection._filters.box` (``mode="reflect"``,
separable: a float32 pass along rows, then one along columns with float64 running
sums), so the results agree with the scipy reference up to float32 rounding
(``tests/test_detect_fast.py``).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

__all__ = ["poisson_background", "poisson_scaled", "saliency_wavelength"]

#: Time bins per tile of the column pass (keeps the per-scale row sums in cache).
_T_TILE = 256


@njit(cache=True, nogil=True, inline="always")
def _refl(i, n):
    """Index ``i`` mapped into ``[0, n)`` like scipy.ndimage ``mode="reflect"``."""
    m = i % (2 * n)
    if m < 0:
        m += 2 * n
    if m >= n:
        m = 2 * n - 1 - m
    return m


@njit(cache=True, nogil=True)
def _level_pixel(x, step, var_factor, quantum, clip, n_iter, scratch):
    """Robust level of one pixel's detrended coarse series ``x`` (T,), as robust_level."""
    T = x.size
    ns = 0
    for t in range(0, T, step):
        scratch[ns] = x[t]
        ns += 1
    med = np.float64(np.median(scratch[:ns]))
    mean = 0.0
    for t in range(T):
        mean += x[t]
    mean /= T
    level = max(med, 0.0)
    sig_base = level if level > 0 else mean
    for it in range(n_iter):
        base = sig_base if it == 0 else level
        half = max(clip * np.sqrt(max(base, 1e-12) * var_factor), 3.0 * quantum)
        half32 = np.float32(half)
        lo = np.float32(level - half32)
        hi = np.float32(level + half32)
        n = 0
        s = 0.0
        for t in range(T):
            v = x[t]
            if v >= lo and v <= hi:
                n += 1
                s += v
        if n > 0:
            level = s / n
        level = max(level, 0.0)
    return np.float32(level)


@njit(cache=True, nogil=True)
def _rows_kernel(
    c,
    i_start,
    i_stop,
    keep0,
    scales,
    weights,
    sp,
    estimate,
    dev,
    var_factor,
    quantum,
    clip,
    n_iter,
    step,
    sal,
    d,
    level,
):
    """Output rows ``[i_start, i_stop)`` (block coordinates) of one wavelength."""
    R, C, T = c.shape
    Q = scales.size
    tile = min(_T_TILE, T)
    V = np.empty((Q, C, tile), np.float32)  # row-pass sums of each scale (/k)
    acc = np.empty(tile, np.float64)
    m = np.empty((C, T), np.float32)
    coarse = np.empty((C, T), np.float32)
    xs = np.empty(T, np.float32)
    scratch = np.empty(T, np.float32)
    for i in range(i_start, i_stop):
        o = i - keep0
        for t0 in range(0, T, tile):
            tn = min(tile, T - t0)
            # pass along rows (axis 0): nested, scale q reuses scale q-1's rows
            for q in range(Q):
                h = scales[q] // 2
                if q == 0:
                    for j in range(C):
                        vr = V[0, j]
                        cr = c[i, j]
                        for t in range(tn):
                            vr[t] = cr[t0 + t]
                    hp = 0
                else:
                    for j in range(C):
                        vr = V[q, j]
                        vp = V[q - 1, j]
                        for t in range(tn):
                            vr[t] = vp[t]
                    hp = scales[q - 1] // 2
                for di in range(hp + 1, h + 1):
                    ia = _refl(i - di, R)
                    ib = _refl(i + di, R)
                    for j in range(C):
                        vr = V[q, j]
                        ca = c[ia, j]
                        cb = c[ib, j]
                        for t in range(tn):
                            vr[t] += ca[t0 + t] + cb[t0 + t]
            # float32 row-pass result divided by k, as uniform_filter1d stores it
            for q in range(Q):
                k = scales[q]
                if k == 1:
                    continue
                inv = np.float32(1.0 / k)
                for j in range(C):
                    vr = V[q, j]
                    for t in range(tn):
                        vr[t] = vr[t] * inv
            for j in range(C):
                mr = m[j]
                for t in range(tn):
                    mr[t0 + t] = 0.0
            # pass along columns (axis 1): running float64 sums, reflected borders
            for q in range(Q):
                k = scales[q]
                h = k // 2
                w = np.float32(weights[q])
                last = q == Q - 1
                if k == 1:
                    for j in range(C):
                        vr = V[q, j]
                        mr = m[j]
                        if w != 0:
                            for t in range(tn):
                                mr[t0 + t] += w * vr[t]
                        if last:
                            cr = coarse[j]
                            for t in range(tn):
                                cr[t0 + t] = vr[t]
                    continue
                for t in range(tn):
                    acc[t] = 0.0
                for u in range(-h, h + 1):
                    vr = V[q, _refl(u, C)]
                    for t in range(tn):
                        acc[t] += vr[t]
                inv = 1.0 / k
                for j in range(C):
                    if j > 0:
                        va = V[q, _refl(j + h, C)]
                        vb = V[q, _refl(j - h - 1, C)]
                        for t in range(tn):
                            acc[t] += np.float64(va[t]) - np.float64(vb[t])
                    mr = m[j]
                    if w != 0:
                        for t in range(tn):
                            mr[t0 + t] += w * np.float32(acc[t] * inv)
                    if last:
                        cr = coarse[j]
                        for t in range(tn):
                            cr[t0 + t] = np.float32(acc[t] * inv)
        # background level, bhat and saliency of each pixel of the row
        for j in range(C):
            if estimate:
                for t in range(T):
                    xs[t] = coarse[j, t] - dev[t]
                sp[o, j] = _level_pixel(xs, step, var_factor, quantum, clip, n_iter, scratch)
            s0 = sp[o, j]
            for t in range(T):
                bh = s0 + dev[t]
                if bh < 0:
                    bh = np.float32(0.0)  # eq:background_3
                level[o, j, t] += bh
                x = m[j, t] - bh
                d[o, j, t] += x
                sal[o, j, t] += abs(x)  # eq:4.s1


def saliency_wavelength(
    c,
    keep: slice,
    scales: np.ndarray,
    weights: np.ndarray,
    dev: np.ndarray,
    sal: np.ndarray,
    d: np.ndarray,
    level: np.ndarray,
    *,
    spatial: np.ndarray | None = None,
    var_factor: float = 1.0,
    quantum: float = 0.0,
    clip: float = 2.5,
    n_iter: int = 2,
    n_threads: int = 1,
) -> np.ndarray:
    """Add one wavelength's saliency, signed response and ``bhat`` to the accumulators.

    Parameters
    ----------
    c : ndarray (R, C, T) float32
        Correlated counts ``Y_l (*) g_l`` of a block (halo rows included); any strides
        with ``T`` contiguous is fastest.
    keep : slice
        Block rows to output (step 1); the others only feed the box filters.
    scales, weights : ndarray (Q,)
        Box sizes (odd, ascending) and ``lambda_q``.
    dev : ndarray (T,) float32
        ``bbar_t - mean_t bbar``.
    sal, d, level : ndarray (r, C, T) float32
        Accumulators (``r`` = rows of ``keep``), updated in place: ``|x|``, ``x`` and
        ``bhat`` with ``x = sum_q lambda_q Box_q(c) - bhat``.
    spatial : ndarray (r, C) float32, optional
        Background level; estimated (robust clipped mean over t of the coarsest scale,
        as :func:`~splidar.detection._background.robust_level`) when None.
    var_factor, quantum, clip, n_iter
        As :func:`~splidar.detection._background.robust_level`.
    n_threads : int
        Threads over output rows (the kernel releases the GIL); results do not depend
        on it (every output row is computed the same way).

    Returns
    -------
    spatial : ndarray (r, C) float32

    Example
    -------
    >>> import numpy as np
    >>> c = np.ones((5, 6, 40), np.float32)
    >>> acc = [np.zeros((5, 6, 40), np.float32) for _ in range(3)]
    >>> sp = saliency_wavelength(c, slice(0, 5), np.array([1, 3]), np.array([0.5, 0.5]),
    ...                          np.zeros(40, np.float32), *acc, var_factor=0.1)
    >>> bool(np.allclose(sp, 1.0)), bool(np.allclose(acc[0], 0.0, atol=1e-6))
    (True, True)
    """
    R, C, T = c.shape
    i0, i1, st = keep.indices(R)
    if st != 1:
        raise ValueError("keep must be a contiguous slice")
    estimate = spatial is None
    sp = np.empty((i1 - i0, C), np.float32) if estimate else spatial
    step = max(1, min(4, T // 64))
    args = (
        np.ascontiguousarray(scales, dtype=np.int64),
        np.ascontiguousarray(weights, dtype=np.float64),
        sp,
        estimate,
        np.ascontiguousarray(dev, dtype=np.float32),
        float(var_factor),
        float(quantum),
        float(clip),
        int(n_iter),
        step,
        sal,
        d,
        level,
    )
    n = i1 - i0
    n_threads = max(1, min(int(n_threads), n))
    if n_threads == 1:
        _rows_kernel(c, i0, i1, i0, *args)
    else:
        cuts = np.linspace(i0, i1, n_threads + 1).round().astype(int)
        with ThreadPoolExecutor(n_threads) as ex:
            list(
                ex.map(
                    lambda ab: _rows_kernel(c, ab[0], ab[1], i0, *args),
                    zip(cuts[:-1], cuts[1:], strict=True),
                )
            )
    return sp


@njit(cache=True, nogil=True)
def _poisson_background_kernel(sp, dev, seed, out):
    # numba's own per-thread generator, seeded from the caller's Generator
    np.random.seed(seed)  # noqa: NPY002
    R, C, L = sp.shape
    T = dev.shape[1]
    for i in range(R):
        for j in range(C):
            for l in range(L):
                s0 = sp[i, j, l]
                for t in range(T):
                    lam = s0 + dev[l, t]
                    out[i, j, l, t] = np.random.poisson(lam) if lam > 0 else 0  # noqa: NPY002


def poisson_background(spatial: np.ndarray, dev: np.ndarray, rng) -> np.ndarray:
    """Poisson draw of ``bhat = max(b_{n,l} + dev_{l,t}, 0)`` (``eq:background_3``).

    ``bhat`` is never materialised. numba's own generator is seeded from ``rng`` (one
    integer), so the draw is reproducible given ``rng`` and independent of threads.

    Parameters
    ----------
    spatial : ndarray (r, c, L) float32
    dev : ndarray (L, T) float32
    rng : numpy Generator

    Returns
    -------
    counts : ndarray (r, c, L, T) uint16 (uint32 when a mean reaches 1000)

    Example
    -------
    >>> import numpy as np
    >>> y = poisson_background(np.full((4, 4, 1), 2.0, np.float32),
    ...                        np.zeros((1, 50), np.float32), np.random.default_rng(0))
    >>> y.shape, bool(abs(y.mean() - 2.0) < 0.3)
    ((4, 4, 1, 50), True)
    """
    sp = np.ascontiguousarray(spatial, dtype=np.float32)
    dv = np.ascontiguousarray(dev, dtype=np.float32)
    top = float(sp.max(initial=0.0)) + float(dv.max(initial=0.0))
    out = np.empty(sp.shape + (dv.shape[1],), np.uint16 if top < 1000 else np.uint32)
    _poisson_background_kernel(sp, dv, int(rng.integers(2**62)), out)
    return out


@njit(cache=True, nogil=True)
def _poisson_scaled_kernel(lam, scale, seed, out):
    # numba's own per-thread generator, seeded from the caller's Generator
    np.random.seed(seed)  # noqa: NPY002
    for i in range(lam.size):
        v = lam.flat[i]
        out.flat[i] = scale * np.random.poisson(v) if v > 0 else 0.0  # noqa: NPY002


def poisson_scaled(lam: np.ndarray, scale: float, rng) -> np.ndarray:
    """``scale * Poisson(lam)`` as float64 (numba's generator seeded from ``rng``).

    Example
    -------
    >>> import numpy as np
    >>> x = poisson_scaled(np.full(1000, 4.0), 0.5, np.random.default_rng(0))
    >>> bool(abs(x.mean() - 2.0) < 0.2)
    True
    """
    lam = np.ascontiguousarray(lam, dtype=np.float64)
    out = np.empty(lam.shape, np.float64)
    _poisson_scaled_kernel(lam, float(scale), int(rng.integers(2**62)), out)
    return out
