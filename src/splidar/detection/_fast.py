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

Speed (issue 6): the block is read through a flat contiguous view with explicit
row/column strides, so every inner loop runs over contiguous 1-d slices and vectorises
(a strided 3-d view compiled to scalar code); the level's median is a branchless
quickselect on a scratch buffer and its clipped sums vectorise. Each change keeps the
arithmetic of every element, so the output is the same as before bit for bit (the
clipped float64 sums are reassociated, which moves them by float64 rounding only).
The kernel filters strips of columns, each strip's rows in turn (the input rows a
strip's boxes read stay in cache), and a block may hold part of the image's columns
with a halo (Dask tiles): the column pass's float64 running sums are carried from strip
to strip and from tile to tile, so every value is the one of a pass over the whole row.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

__all__ = [
    "correlate_direct",
    "low_median",
    "pixel_totals",
    "poisson_background",
    "poisson_scaled",
    "saliency_wavelength",
    "window_means",
]

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
def _select_inplace(a, n, k):
    """``k``-th smallest of ``a[:n]`` (quickselect, median-of-3 pivot); ``a`` is permuted.

    On return ``a[:k] <= a[k] <= a[k + 1 : n]``. The value is the order statistic, so
    it does not depend on the algorithm (same as :func:`numpy.median`'s selection).
    """
    lo = 0
    hi = n - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        # median of three as pivot, moved to a[hi]
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[mid] < a[hi]:
            a[mid], a[hi] = a[hi], a[mid]
        pivot = a[hi]
        # branchless Lomuto partition: a[lo:i] < pivot <= a[i:j] (no mispredictions)
        i = lo
        for j in range(lo, hi):
            v = a[j]
            a[j] = a[i]
            a[i] = v
            i += v < pivot
        a[i], a[hi] = a[hi], a[i]
        if i == k:
            break
        if i < k:
            lo = i + 1
        else:
            hi = i - 1
    return a[k]


@njit(cache=True, nogil=True)
def _median_scratch(a, n):
    """Median of ``a[:n]`` (float32), as ``np.median`` computes it in numba; ``a`` permuted."""
    half = n >> 1
    if n & 1:
        return np.float64(_select_inplace(a, n, half))
    lo = _select_inplace(a, n, half - 1)
    hi = a[half]
    for t in range(half + 1, n):
        if a[t] < hi:
            hi = a[t]
    return np.float64(lo + hi) / 2  # float32 sum, then halved in float64 (numba's median)


@njit(cache=True, nogil=True, fastmath={"reassoc", "nsz"})
def _clipped_sum(x, lo, hi):
    """Count and float64 sum of the ``x`` in ``[lo, hi]``.

    Reassociation (``fastmath``, this function only) lets the float64 sum vectorise
    instead of a chain of T dependent additions; it changes the sum only at float64
    rounding (about 1e-16 relative), far below the float32 level returned.
    """
    s = 0.0
    n = 0
    for t in range(x.size):
        v = x[t]
        inside = (v >= lo) & (v <= hi)
        s += np.float64(v) if inside else 0.0
        n += inside
    return n, s


@njit(cache=True, nogil=True)
def _median_near(a, n, hint, width):
    """:func:`_median_scratch` of ``a[:n]`` (the same value), faster when the median
    lies within ``hint +- width``; ``a`` is permuted.

    The values below, inside and above that band are counted (loops that vectorise);
    when the middle order statistics fall inside it, the band's values are moved to the
    front and the selection runs on them only (rank less the count below): the same
    order statistics. Otherwise (or with NaNs, or a NaN ``hint``) the whole selection.
    Neighbouring pixels' coarse series share most of their box, so the previous pixel's
    median is a close hint: on the bench cube's 375 samples per series, 1.1 -> 0.3 ns
    per bin of the series.
    """
    half = n >> 1
    k_lo = half if n & 1 else half - 1
    lo_b = np.float32(hint - width)
    hi_b = np.float32(hint + width)
    nb = 0
    nm = 0
    na = 0
    for t in range(n):
        v = a[t]
        nb += v < lo_b
        nm += (v >= lo_b) & (v <= hi_b)
        na += v > hi_b
    if nb + nm + na != n or nb > k_lo or half >= nb + nm:
        return _median_scratch(a, n)
    c = 0
    for t in range(n):  # the band's values to the front (c <= t: read before written)
        v = a[t]
        a[c] = v
        c += (v >= lo_b) & (v <= hi_b)
    if n & 1:
        return np.float64(_select_inplace(a, nm, half - nb))
    lo = _select_inplace(a, nm, k_lo - nb)
    hi = a[half - nb]
    for t in range(half - nb + 1, nm):
        if a[t] < hi:
            hi = a[t]
    return np.float64(lo + hi) / 2  # as _median_scratch


@njit(cache=True, nogil=True)
def _level_pixel(x, step, var_factor, quantum, clip, n_iter, scratch, hint):
    """Robust level of one pixel's detrended coarse series ``x`` (T,), as robust_level.

    ``eq:background_2`` (index n,l): start from the median of every ``step``-th bin,
    then ``n_iter`` clipped means within ``level +- clip`` Poisson sigmas (at least 3
    quanta). The mean over t is only needed when the median is 0 (sparse counts).
    ``hint``: a guess of the median (a neighbour's; NaN: none), for speed only
    (:func:`_median_near`). Returns the level and the median.
    """
    T = x.size
    ns = 0
    for t in range(0, T, step):
        scratch[ns] = x[t]
        ns += 1
    width = 0.1 * np.sqrt(max(hint, 0.0) * var_factor)  # a tenth of a sigma
    med = _median_near(scratch, ns, hint, width)
    level = max(med, 0.0)
    if level > 0:
        sig_base = level
    else:
        mean = 0.0
        for t in range(T):
            mean += x[t]
        sig_base = mean / T
    for it in range(n_iter):
        base = sig_base if it == 0 else level
        half = max(clip * np.sqrt(max(base, 1e-12) * var_factor), 3.0 * quantum)
        half32 = np.float32(half)
        lo = np.float32(level - half32)
        hi = np.float32(level + half32)
        n, s = _clipped_sum(x, lo, hi)
        if n > 0:
            level = s / n
        level = max(level, 0.0)
    return np.float32(level), med


@njit(cache=True, nogil=True)
def _row_pass(cf, base, R, sr, sc, i, ja, jb, t0, tn, scales, V):
    """The pass along rows (axis 0) of :func:`_filter_row`: ``V[q, j, :tn]`` = the sum of
    block rows ``i - h_q .. i + h_q`` of column ``j`` (reflected), bins ``[t0, t0 + tn)``,
    for ``j`` in ``[ja, jb)``; nested, scale ``q`` continues scale ``q - 1``'s sums with
    the row pairs ``i -+ d`` for ``d = h_{q-1} + 1 .. h_q``, one pair after the other
    (``v + (c[i - d] + c[i + d])``, float32).

    Up to two row pairs are added per pass over ``V`` (the first pass of a scale also
    copies the scale below): the same additions in the same order as one pass per
    pair, so the same bits, with fewer loads and stores of ``V`` (the saliency kernel
    7 % less CPU on the 200 x 200 x 4 x 1500 bench cube; ``benchmarks/README.md``,
    "map37, session 25").
    """
    Q = scales.size
    for q in range(Q):
        h = scales[q] // 2
        if q == 0:
            for j in range(ja, jb):
                vr = V[0, j, :tn]
                off = base + i * sr + j * sc + t0
                cr = cf[off : off + tn]
                for t in range(tn):
                    vr[t] = cr[t]
            hp = 0
        else:
            hp = scales[q - 1] // 2
            if hp + 2 <= h:  # the copy of scale q - 1 and two row pairs in one pass
                ia = _refl(i - hp - 1, R)
                ib = _refl(i + hp + 1, R)
                ia2 = _refl(i - hp - 2, R)
                ib2 = _refl(i + hp + 2, R)
                for j in range(ja, jb):
                    vr = V[q, j, :tn]
                    vp = V[q - 1, j, :tn]
                    oa = base + ia * sr + j * sc + t0
                    ob = base + ib * sr + j * sc + t0
                    oa2 = base + ia2 * sr + j * sc + t0
                    ob2 = base + ib2 * sr + j * sc + t0
                    ca = cf[oa : oa + tn]
                    cb = cf[ob : ob + tn]
                    ca2 = cf[oa2 : oa2 + tn]
                    cb2 = cf[ob2 : ob2 + tn]
                    for t in range(tn):
                        vr[t] = (vp[t] + (ca[t] + cb[t])) + (ca2[t] + cb2[t])
                hp += 2
            elif hp < h:  # the copy of scale q - 1 and its first row pair in one pass
                ia = _refl(i - hp - 1, R)
                ib = _refl(i + hp + 1, R)
                for j in range(ja, jb):
                    vr = V[q, j, :tn]
                    vp = V[q - 1, j, :tn]
                    oa = base + ia * sr + j * sc + t0
                    ob = base + ib * sr + j * sc + t0
                    ca = cf[oa : oa + tn]
                    cb = cf[ob : ob + tn]
                    for t in range(tn):
                        vr[t] = vp[t] + (ca[t] + cb[t])
                hp += 1
            else:
                for j in range(ja, jb):
                    vr = V[q, j, :tn]
                    vp = V[q - 1, j, :tn]
                    for t in range(tn):
                        vr[t] = vp[t]
        di = hp + 1
        while di + 1 <= h:  # two row pairs per pass
            ia = _refl(i - di, R)
            ib = _refl(i + di, R)
            ia2 = _refl(i - di - 1, R)
            ib2 = _refl(i + di + 1, R)
            for j in range(ja, jb):
                vr = V[q, j, :tn]
                oa = base + ia * sr + j * sc + t0
                ob = base + ib * sr + j * sc + t0
                oa2 = base + ia2 * sr + j * sc + t0
                ob2 = base + ib2 * sr + j * sc + t0
                ca = cf[oa : oa + tn]
                cb = cf[ob : ob + tn]
                ca2 = cf[oa2 : oa2 + tn]
                cb2 = cf[ob2 : ob2 + tn]
                for t in range(tn):
                    vr[t] = (vr[t] + (ca[t] + cb[t])) + (ca2[t] + cb2[t])
            di += 2
        if di <= h:
            ia = _refl(i - di, R)
            ib = _refl(i + di, R)
            for j in range(ja, jb):
                vr = V[q, j, :tn]
                oa = base + ia * sr + j * sc + t0
                ob = base + ib * sr + j * sc + t0
                ca = cf[oa : oa + tn]
                cb = cf[ob : ob + tn]
                for t in range(tn):
                    vr[t] += ca[t] + cb[t]


@njit(cache=True, nogil=True)
def _filter_row(
    cf, base, R, C, T, sr, sc, i, s0, s1, scales, weights, dev, estimate, V, acc, m, coarse,
    box, bidx, o, oc, carry, have_carry,
):  # fmt: skip
    """``m = sum_q lambda_q Box_q(c)`` and the coarsest scale (minus ``dev`` when
    ``estimate``) of block row ``i``, block columns ``[s0, s1)``; element ``(i, j, t)``
    of ``c`` is ``cf[base + i * sr + j * sc + t]``. ``V`` (Q, C, tile) and ``acc``
    (tile,) are work buffers; ``m`` and ``coarse`` (C, T) are written at columns
    ``[s0, s1)``. When ``bidx[q] >= 0`` the box mean of scale ``q`` is also written to
    ``box[bidx[q], o, j - oc]`` (T,).

    The column pass keeps running float64 sums along the image row: ``carry`` (Q, T)
    holds them at column ``s0 - 1`` on entry when ``have_carry`` (a strip or tile to
    the left computed them; columns from ``s0 - h - 1`` must be in the block) and at
    column ``s1 - 1`` on return. Without a carry ``s0`` is the image's first column. So
    every value is the one a pass over the whole row gives, bit for bit, whatever the
    strips or tiles.
    """
    Q = scales.size
    tile = V.shape[2]
    hmax = scales[Q - 1] // 2
    # columns the row pass fills: the strip and the halo its running sums read
    # (reflected indices stay inside: a block edge that is not the image's has a halo)
    ja = max(0, s0 - hmax - 1)
    jb = min(C, s1 + hmax)
    for t0 in range(0, T, tile):
        tn = min(tile, T - t0)
        dv = dev[t0 : t0 + tn]
        # pass along rows (axis 0): nested, scale q reuses scale q-1's rows
        _row_pass(cf, base, R, sr, sc, i, ja, jb, t0, tn, scales, V)
        # pass along columns (axis 1): running float64 sums of the row-pass results
        # divided by k in float32 (as uniform_filter1d stores them), reflected borders
        for q in range(Q):
            k = scales[q]
            h = k // 2
            w = np.float32(weights[q])
            first = q == 0
            last = q == Q - 1
            if k == 1:
                for j in range(s0, s1):
                    vr = V[q, j, :tn]
                    mr = m[j, t0 : t0 + tn]
                    if first:
                        for t in range(tn):
                            mr[t] = w * vr[t]
                    elif w != 0:
                        for t in range(tn):
                            mr[t] += w * vr[t]
                    if last:
                        cr = coarse[j, t0 : t0 + tn]
                        if estimate:
                            for t in range(tn):
                                cr[t] = vr[t] - dv[t]
                        else:
                            for t in range(tn):
                                cr[t] = vr[t]
                continue
            inv32 = np.float32(1.0 / k)
            ac = acc[:tn]
            inv = 1.0 / k
            bq = bidx[q]
            cq = carry[q, t0 : t0 + tn]
            for j in range(s0, s1):
                if j == s0:
                    if have_carry:
                        for t in range(tn):
                            ac[t] = cq[t]
                    else:
                        for t in range(tn):
                            ac[t] = 0.0
                        for u in range(-h, h + 1):
                            vr = V[q, _refl(u, C), :tn]
                            for t in range(tn):
                                ac[t] += np.float32(vr[t] * inv32)
                if j > s0 or have_carry:
                    va = V[q, _refl(j + h, C), :tn]
                    vb = V[q, _refl(j - h - 1, C), :tn]
                    for t in range(tn):
                        ac[t] += np.float64(np.float32(va[t] * inv32)) - np.float64(
                            np.float32(vb[t] * inv32)
                        )
                if bq >= 0:
                    br = box[bq, o, j - oc, t0 : t0 + tn]
                    for t in range(tn):
                        br[t] = np.float32(ac[t] * inv)
                mr = m[j, t0 : t0 + tn]
                if first:
                    for t in range(tn):
                        mr[t] = w * np.float32(ac[t] * inv)
                elif w != 0:
                    for t in range(tn):
                        mr[t] += w * np.float32(ac[t] * inv)
                if last:
                    cr = coarse[j, t0 : t0 + tn]
                    if estimate:
                        for t in range(tn):
                            cr[t] = np.float32(ac[t] * inv) - dv[t]
                    else:
                        for t in range(tn):
                            cr[t] = np.float32(ac[t] * inv)
            for t in range(tn):
                cq[t] = ac[t]


@njit(cache=True, nogil=True)
def _bhat_saliency(s0_, dev, mr, sr_, dr, level, o, jo, overwrite):
    """One pixel's ``bhat`` (``eq:background_3``), signed response and saliency
    (``eq:4.s1``) from its level ``s0_`` and filtered series ``mr`` (T,): written
    (``overwrite``, the first wavelength) or added to ``sr_`` and ``dr`` (T,), and to
    ``level[o, jo]`` unless ``level`` is empty (then the caller recomputes ``sum_l
    bhat`` where it needs it, from the levels and ``dev``)."""
    T = mr.size
    with_level = level.shape[0] > 0
    if overwrite:  # the first wavelength: no zeroing pass before
        for t in range(T):
            bh = s0_ + dev[t]
            if bh < 0:
                bh = np.float32(0.0)  # eq:background_3
            x = mr[t] - bh
            dr[t] = x
            sr_[t] = abs(x)  # eq:4.s1
        if with_level:
            lr = level[o, jo]
            for t in range(T):
                bh = s0_ + dev[t]
                lr[t] = bh if not bh < 0 else np.float32(0.0)
    else:
        for t in range(T):
            bh = s0_ + dev[t]
            if bh < 0:
                bh = np.float32(0.0)  # eq:background_3
            x = mr[t] - bh
            dr[t] += x
            sr_[t] += abs(x)  # eq:4.s1
        if with_level:
            lr = level[o, jo]
            for t in range(T):
                bh = s0_ + dev[t]
                lr[t] += bh if not bh < 0 else np.float32(0.0)


@njit(cache=True, nogil=True)
def _rows_kernel(
    cf, R, C, T, sr, sc, i_start, i_stop, keep0, jk0, jk1, strip, carry_in, carry_out, scales,
    weights, sp, estimate, dev, var_factor, quantum, clip, n_iter, step, sal, d, level, box,
    bidx, overwrite,
):  # fmt: skip
    """Output rows ``[i_start, i_stop)`` and columns ``[jk0, jk1)`` (block coordinates)
    of one wavelength, in strips of ``strip`` columns (each strip's rows one after the
    other, so the input rows its boxes read stay in cache); outputs are indexed from
    row ``keep0`` and column ``jk0``.

    ``carry_in`` (r, Q, T) float64 holds the column pass's running sums at column
    ``jk0 - 1`` of each output row when ``jk0 > 0`` (a tile to the left computed them);
    ``carry_out`` (same shape, or empty) receives them at column ``jk1 - 1``.

    ``cf`` is the correlated block as a flat contiguous float32 buffer: element
    ``(i, j, t)`` at ``i * sr + j * sc + t``. Contiguous 1-d slices of it (rather than
    a strided 3-d view) let the row pass vectorise.
    """
    Q = scales.size
    tile = min(_T_TILE, T)
    V = np.empty((Q, C, tile), np.float32)  # row-pass sums of each scale (not yet / k)
    acc = np.empty(tile, np.float64)
    m = np.empty((C, T), np.float32)
    coarse = np.empty((C, T), np.float32)  # coarsest scale minus dev (when estimating)
    scratch = np.empty(T, np.float32)
    # running column sums of each output row between strips
    carry = np.empty((i_stop - i_start, Q, T), np.float64)
    if jk0 > 0:
        for i in range(i_start, i_stop):
            carry[i - i_start] = carry_in[i - keep0]
    hint = np.nan  # the previous pixel's median (speed only)
    for s0 in range(jk0, jk1, strip):
        s1 = min(jk1, s0 + strip)
        for i in range(i_start, i_stop):
            o = i - keep0
            _filter_row(
                cf, 0, R, C, T, sr, sc, i, s0, s1, scales, weights, dev, estimate, V, acc, m,
                coarse, box, bidx, o, jk0, carry[i - i_start], s0 > 0,
            )  # fmt: skip
            # background level, bhat and saliency of each pixel of the strip's row
            for j in range(s0, s1):
                jo = j - jk0
                if estimate:
                    sp[o, jo], hint = _level_pixel(
                        coarse[j], step, var_factor, quantum, clip, n_iter, scratch, hint
                    )
                _bhat_saliency(sp[o, jo], dev, m[j], sal[o, jo], d[o, jo], level, o, jo, overwrite)
    if carry_out.shape[0] > 0:
        for i in range(i_start, i_stop):
            carry_out[i - keep0] = carry[i - i_start]


def _kept_span(shape, keep: slice, keep_cols, Q: int, carry) -> tuple:
    """``(i0, i1, j0, j1)``: the kept rows and columns of a block of ``shape`` (R, C, T);
    raises ValueError on a strided slice or a ``carry`` of the wrong form."""
    R, C, T = shape
    i0, i1, st = keep.indices(R)
    if st != 1:
        raise ValueError("keep must be a contiguous slice")
    j0, j1, st = (slice(None) if keep_cols is None else keep_cols).indices(C)
    if st != 1:
        raise ValueError("keep_cols must be a contiguous slice")
    if carry is not None and (carry.shape != (i1 - i0, Q, T) or carry.dtype != np.float64):
        raise ValueError("carry must be float64 (kept rows, scales, T)")
    if j0 > 0 and carry is None:
        raise ValueError("keep_cols starting past column 0 needs the carry of the columns before")
    return i0, i1, j0, j1


def _flat_rows(c: np.ndarray):
    """``c`` (R, C, T) float32 as a flat contiguous buffer and its row/column strides.

    A view of the same memory when ``t`` is contiguous (the usual ``c[:, :, l, :]`` of a
    C-ordered block), a contiguous copy otherwise.
    """
    it = c.itemsize
    R, C, T = c.shape
    st = c.strides
    if c.dtype != np.float32 or st[2] != it or st[0] < 0 or st[1] < 0 or st[0] % it or st[1] % it:
        c = np.ascontiguousarray(c, dtype=np.float32)
        st = c.strides
    sr, sc = st[0] // it, st[1] // it
    span = (R - 1) * sr + (C - 1) * sc + T
    flat = np.lib.stride_tricks.as_strided(c, shape=(span,), strides=(it,), writeable=False)
    return flat, sr, sc


def saliency_wavelength(
    c,
    keep: slice,
    scales: np.ndarray,
    weights: np.ndarray,
    dev: np.ndarray,
    sal: np.ndarray,
    d: np.ndarray,
    level: np.ndarray | None,
    *,
    spatial: np.ndarray | None = None,
    var_factor: float = 1.0,
    quantum: float = 0.0,
    clip: float = 2.5,
    n_iter: int = 2,
    n_threads: int = 1,
    box: np.ndarray | None = None,
    overwrite: bool = False,
    keep_cols: slice | None = None,
    strip: int | None = None,
    carry: np.ndarray | None = None,
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
        ``bhat`` with ``x = sum_q lambda_q Box_q(c) - bhat``. ``level=None``: ``bhat``
        is not accumulated (a caller that needs ``sum_l bhat`` recomputes it from the
        levels and ``dev``, in the same order, as the threshold pass does).
    spatial : ndarray (r, C) float32, optional
        Background level; estimated (robust clipped mean over t of the coarsest scale,
        as :func:`~splidar.detection._background.robust_level`) when None.
    var_factor, quantum, clip, n_iter
        As :func:`~splidar.detection._background.robust_level`.
    n_threads : int
        Threads over output rows (the kernel releases the GIL); results do not depend
        on it (every output row is computed the same way).
    box : ndarray (Qb, r, C, T) float32, optional
        When given, receives the box means ``Box_q(c)`` of the kept rows for every scale
        ``k_q > 1`` (in increasing order; scale 1 is ``c`` itself): surface extraction
        reads them instead of summing the boxes again.
    overwrite : bool
        Write ``sal``, ``d`` and ``level`` instead of adding to them (the first
        wavelength; saves zeroing them first).
    keep_cols : slice, optional
        Block columns to output (step 1; default all): the others are halo. ``C`` of
        the outputs above is then the number of kept columns. A block edge that is not
        the image's needs a halo of ``max(scales) // 2`` rows and that plus one columns
        (the box filters reflect at the block's edges).
    strip : int, optional
        Columns filtered together (default all): each strip's rows in turn, so that
        the input rows its boxes read stay in cache. The result does not depend on it.
    carry : ndarray (r, Q, T) float64, optional
        The column pass's running sums (one per output row, scale and bin) along the
        image row: read at the column before the first kept one when that is not block
        column 0 (a block to the left wrote them; required then), overwritten with
        those at the last kept column. Passing them on makes every value the one a pass
        over the whole row gives, bit for bit.

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
    Q = np.size(scales)
    i0, i1, j0, j1 = _kept_span(c.shape, keep, keep_cols, Q, carry)
    strip = max(j1 - j0, 1) if strip is None else max(int(strip), 1)
    nc = j1 - j0
    estimate = spatial is None
    sp = np.empty((i1 - i0, nc), np.float32) if estimate else spatial
    sc_arr = np.ascontiguousarray(scales, dtype=np.int64)
    bidx = np.full(sc_arr.size, -1, np.int64)
    if box is None:
        box = np.empty((1, 1, 1, 1), np.float32)
    else:
        bidx[sc_arr > 1] = np.arange(int((sc_arr > 1).sum()))
        if box.shape != (int((sc_arr > 1).sum()), i1 - i0, nc, T) or box.dtype != np.float32:
            raise ValueError("box must be float32 (scales > 1, kept rows, C, T)")
    step = max(1, min(4, T // 64))
    if level is None:
        level = np.empty((0, 0, 0), np.float32)
    args = (
        sc_arr,
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
        box,
        bidx,
        bool(overwrite),
    )
    n = i1 - i0
    if n <= 0 or nc <= 0 or T == 0:
        return sp
    n_threads = max(1, min(int(n_threads), n))
    cf, sr, sc = _flat_rows(c)
    head = (cf, R, C, T, sr, sc)
    none = np.empty((0, Q, T), np.float64)
    cols = (j0, j1, strip, none if carry is None else carry, none if carry is None else carry)
    if n_threads == 1:
        _rows_kernel(*head, i0, i1, i0, *cols, *args)
    else:
        cuts = np.linspace(i0, i1, n_threads + 1).round().astype(int)
        with ThreadPoolExecutor(n_threads) as ex:
            list(
                ex.map(
                    lambda ab: _rows_kernel(*head, ab[0], ab[1], i0, *cols, *args),
                    zip(cuts[:-1], cuts[1:], strict=True),
                )
            )
    return sp


#: Above this mean per bin, _poisson_background_kernel draws a bin's count directly;
#: below, it walks the photon arrivals (one exponential draw per photon, none per bin).
_ARRIVALS_MAX_RATE = 4.0


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
                # photon arrivals of a Poisson process in rescaled time (the cumulative
                # mean): the counts of the bins, each the arrivals within its share of
                # the cumulative mean, are independent Poisson of their means. The
                # residual to the next arrival is exponential whatever came before, so
                # a bin drawn directly (a high mean) is stepped over with it.
                acc = 0.0
                nxt = np.random.exponential()  # noqa: NPY002
                for t in range(T):
                    lam = np.float64(s0 + dev[l, t])
                    if lam <= 0:
                        out[i, j, l, t] = 0
                    elif lam > _ARRIVALS_MAX_RATE:
                        out[i, j, l, t] = np.random.poisson(lam)  # noqa: NPY002
                        nxt += lam
                        acc += lam
                    else:
                        acc += lam
                        c = 0
                        while nxt < acc:
                            c += 1
                            nxt += np.random.exponential()  # noqa: NPY002
                        out[i, j, l, t] = c


def poisson_background(spatial: np.ndarray, dev: np.ndarray, rng) -> np.ndarray:
    """Poisson draw of ``bhat = max(b_{n,l} + dev_{l,t}, 0)`` (``eq:background_3``).

    ``bhat`` is never materialised. numba's own generator is seeded from ``rng`` (one
    integer), so the draw is reproducible given ``rng`` and independent of threads.
    Low means (the usual background, well below a photon per bin) are drawn as the
    arrivals of a Poisson process, one exponential draw per photon rather than one
    Poisson draw per bin (about 6 x faster at 0.005 photons per bin); bins above
    :data:`_ARRIVALS_MAX_RATE` photons get a direct Poisson draw.

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


#: Columns gathered together by :func:`_low_median_kernel` (a row of the block is one
#: 64-byte cache line of float32).
_LOW_COLS = 16


@njit(cache=True, nogil=True)
def _low_pair(a, n, k1, k2):
    """Order statistics ``k1`` and ``k2`` (``k1`` or ``k1 + 1``) of ``a[:n]``; ``a``
    permuted."""
    lo = _select_inplace(a, n, k1)
    hi = lo
    if k2 > k1:  # the next order statistic: the smallest above a[k1]
        hi = a[k1 + 1]
        for i in range(k1 + 2, n):
            if a[i] < hi:
                hi = a[i]
    return lo, hi


@njit(cache=True, nogil=True)
def _low_median_kernel(x, k1, k2, p0, p1, out, bad):
    """``out[p] = (a[k1] + a[k2]) / 2`` with ``a`` the order statistics of ``x[:, p]``,
    for the columns ``[p0, p1)``; a column holding a NaN is flagged in ``bad`` (the
    caller takes NumPy's selection for it).

    Neighbouring columns (bins ``t`` and ``t + 1``) have close order statistics: the
    values within ``hint +- width`` of the previous column's ``a[k1]`` are counted and,
    when both order statistics lie among them, selected from those only (the rank less
    the count below): the same values (as :func:`_median_near`). ``width`` adapts
    (shrunk after a hit, widened after a miss), for speed only.
    """
    n = x.shape[0]
    blk = np.empty((n, _LOW_COLS), np.float32)
    a = np.empty(n, np.float32)
    hint = np.nan
    width = 0.0
    for q0 in range(p0, p1, _LOW_COLS):
        nq = min(_LOW_COLS, p1 - q0)
        for i in range(n):  # the block's rows: whole cache lines
            for u in range(nq):
                blk[i, u] = x[i, q0 + u]
        for u in range(nq):
            nan = False
            for i in range(n):
                v = blk[i, u]
                a[i] = v
                nan |= v != v
            if nan:
                bad[q0 + u] = True
                continue
            done = False
            if hint == hint and width > 0:
                lo_b = np.float32(hint - width)
                hi_b = np.float32(hint + width)
                nb = 0
                nm = 0
                for i in range(n):
                    v = a[i]
                    nb += v < lo_b
                    nm += (v >= lo_b) & (v <= hi_b)
                if nb <= k1 and k2 < nb + nm:
                    c = 0
                    for i in range(n):  # the band's values to the front
                        v = a[i]
                        a[c] = v
                        c += (v >= lo_b) & (v <= hi_b)
                    lo, hi = _low_pair(a, nm, k1 - nb, k2 - nb)
                    done = True
                    width *= 0.75
                else:
                    width *= 4.0
            if not done:
                lo, hi = _low_pair(a, n, k1, k2)
                if not width > 0:
                    width = max(abs(np.float64(lo)), 1e-6) * 0.02
            hint = np.float64(lo)
            out[q0 + u] = (lo + hi) / np.float32(2)


def low_median(x: np.ndarray, k1: int, k2: int, cols: slice, out: np.ndarray) -> None:
    """``out[cols] = (part[k1] + part[k2]) / 2`` (float32) with ``part`` the order
    statistics of each column of ``x`` (n, P) float32 (``k2`` is ``k1`` or ``k1 + 1``):
    the value of ``np.partition(x[:, cols], [k1, k2], axis=0)``, bit for bit (order
    statistics do not depend on the selection), without its copy of the columns.

    Example
    -------
    >>> import numpy as np
    >>> x = np.random.default_rng(0).random((101, 5)).astype(np.float32)
    >>> out = np.empty(5, np.float32)
    >>> low_median(x, 9, 10, slice(0, 5), out)
    >>> p = np.partition(x, [9, 10], axis=0)
    >>> bool(np.array_equal(out, (p[9] + p[10]) / np.float32(2)))
    True
    """
    p0, p1, _ = cols.indices(x.shape[1])
    bad = np.zeros(x.shape[1], np.bool_)
    _low_median_kernel(x, int(k1), int(k2), p0, p1, out, bad)
    for p in np.flatnonzero(bad):  # NaNs: NumPy's rule (sorted to the end)
        part = np.partition(x[:, p], [k1, k2] if k2 > k1 else k1)
        out[p] = (part[k1] + part[k2]) / x.dtype.type(2)


@njit(cache=True, nogil=True)
def _pixel_totals_kernel(y, out):
    R, C, L, T = y.shape
    for i in range(R):
        for j in range(C):
            s = 0
            for l in range(L):
                row = y[i, j, l]
                for t in range(T):  # integer sums, vectorised
                    s += np.int64(row[t])
            out[i, j] = np.float64(s)


def pixel_totals(counts: np.ndarray) -> np.ndarray:
    """Counts of every pixel summed over wavelengths and bins, ``(rows, cols)`` float64.

    ``counts.sum(axis=(2, 3), dtype=np.float64)``, bit for bit: integer counts (of at
    most 32 bits) are summed exactly in int64 here and converted once (exact below
    2**53, as NumPy's float64 sums of integers are), in one pass that vectorises (about
    7 x faster than NumPy's reduction over two axes of a uint16 cube). Other dtypes,
    and views that are not C-contiguous (no copy of the cube), take NumPy's reduction.

    Example
    -------
    >>> import numpy as np
    >>> y = np.arange(2 * 3 * 2 * 4, dtype=np.uint16).reshape(2, 3, 2, 4)
    >>> bool(np.array_equal(pixel_totals(y), y.sum(axis=(2, 3), dtype=np.float64)))
    True
    """
    y = np.asarray(counts)
    if y.ndim != 4 or y.dtype.kind not in "ui" or y.dtype.itemsize > 4 or not y.flags.c_contiguous:
        return y.sum(axis=(2, 3), dtype=np.float64)
    out = np.empty(y.shape[:2], np.float64)
    _pixel_totals_kernel(y, out)
    return out


@njit(cache=True, nogil=True)
def _window_means_kernel(rows, col_starts, kc, out):
    kr, C, L, T = rows.shape
    norm = np.float64(kr * kc)
    rs = np.empty(T, np.float64)
    cs = np.empty((C + 1, T), np.float64)
    for l in range(L):
        for t in range(T):
            cs[0, t] = 0.0
        for j in range(C):
            for t in range(T):
                rs[t] = 0.0
            for a in range(kr):
                src = rows[a, j, l]
                for t in range(T):
                    rs[t] += src[t]
            for t in range(T):
                cs[j + 1, t] = cs[j, t] + rs[t]
        for u in range(col_starts.size):
            b0 = col_starts[u]
            for t in range(T):
                out[u, l, t] = (cs[b0 + kc, t] - cs[b0, t]) / norm


def window_means(rows: np.ndarray, col_starts: np.ndarray, kc: int) -> np.ndarray:
    """Means of the counts over ``kr x kc`` pixel windows (all ``kr`` rows of ``rows``).

    Integer counts are summed exactly in float64 (up to 2**53), so the result is the
    float32 rounding of the exact window mean, whatever the order of the sums.

    Parameters
    ----------
    rows : ndarray (kr, C, L, T)
        Counts of ``kr`` consecutive image rows (any numeric dtype).
    col_starts : ndarray (n,) int
        First column of each window; ``col_starts + kc <= C``.
    kc : int
        Window width (columns).

    Returns
    -------
    means : ndarray (n, L, T) float32

    Example
    -------
    >>> import numpy as np
    >>> y = np.arange(2 * 5 * 1 * 3).reshape(2, 5, 1, 3)
    >>> m = window_means(y, np.array([0, 2]), 3)
    >>> bool(np.allclose(m[1, 0], y[:, 2:5, 0].mean(axis=(0, 1))))
    True
    """
    rows = np.ascontiguousarray(rows)
    kr, C, L, T = rows.shape
    cols = np.ascontiguousarray(col_starts, dtype=np.int64)
    kc = int(kc)
    if cols.size and (cols.min() < 0 or cols.max() + kc > C):
        raise ValueError(
            f"windows of {kc} columns starting at {cols.min()}..{cols.max()} leave C = {C}"
        )
    out = np.empty((cols.size, L, T), np.float32)
    _window_means_kernel(rows, cols, kc, out)
    return out


@njit(cache=True, nogil=True)
def _mirror_index(left, T, right):
    """Sources in ``[0, T)`` of the ``left`` mirrored samples before a row and the
    ``right`` ones after it (scipy.ndimage ``mode="reflect"``), once per call."""
    idx = np.empty(left + right, np.int64)
    for u in range(left):
        idx[u] = _refl(u - left, T)
    for u in range(right):
        idx[left + u] = _refl(T + u, T)
    return idx


@njit(cache=True, nogil=True, inline="always")
def _tap_sweeps(o, xp, base, gl, n):
    """``o[t] = sum_j gl[j] xp[base + t + j]`` in float32, summed as
    ``((0 + G_0) + G_1) + ... + r_0 + r_1 ...`` with ``G_k`` the four-tap group
    ``(g0 a + g1 b) + (g2 c + g3 e)`` and ``r_i`` the last ``n % 4`` taps one at a time
    (the order of the former one-group-per-sweep kernel: the same bits). Two groups
    per sweep over ``o``, the remainder fused into the last group's sweep; every loop
    runs over ``t`` with the taps in registers (vectorised)."""
    T = o.shape[0]
    z = np.float32(0.0)
    if n < 8:
        for t in range(T):
            o[t] = z
    j = 0
    while n - j >= 8:
        a = xp[base + j :]
        g0, g1, g2, g3 = gl[j], gl[j + 1], gl[j + 2], gl[j + 3]
        h0, h1, h2, h3 = gl[j + 4], gl[j + 5], gl[j + 6], gl[j + 7]
        if j == 0:
            for t in range(T):
                s = z + ((g0 * a[t] + g1 * a[t + 1]) + (g2 * a[t + 2] + g3 * a[t + 3]))
                o[t] = s + ((h0 * a[t + 4] + h1 * a[t + 5]) + (h2 * a[t + 6] + h3 * a[t + 7]))
        else:
            for t in range(T):
                s = o[t] + ((g0 * a[t] + g1 * a[t + 1]) + (g2 * a[t + 2] + g3 * a[t + 3]))
                o[t] = s + ((h0 * a[t + 4] + h1 * a[t + 5]) + (h2 * a[t + 6] + h3 * a[t + 7]))
        j += 8
    a = xp[base + j :]
    r = n - j
    if r >= 4:
        g0, g1, g2, g3 = gl[j], gl[j + 1], gl[j + 2], gl[j + 3]
        if r == 4:
            for t in range(T):
                o[t] = o[t] + ((g0 * a[t] + g1 * a[t + 1]) + (g2 * a[t + 2] + g3 * a[t + 3]))
        elif r == 5:
            h0 = gl[j + 4]
            for t in range(T):
                s = o[t] + ((g0 * a[t] + g1 * a[t + 1]) + (g2 * a[t + 2] + g3 * a[t + 3]))
                o[t] = s + h0 * a[t + 4]
        elif r == 6:
            h0, h1 = gl[j + 4], gl[j + 5]
            for t in range(T):
                s = o[t] + ((g0 * a[t] + g1 * a[t + 1]) + (g2 * a[t + 2] + g3 * a[t + 3]))
                o[t] = (s + h0 * a[t + 4]) + h1 * a[t + 5]
        else:
            h0, h1, h2 = gl[j + 4], gl[j + 5], gl[j + 6]
            for t in range(T):
                s = o[t] + ((g0 * a[t] + g1 * a[t + 1]) + (g2 * a[t + 2] + g3 * a[t + 3]))
                o[t] = ((s + h0 * a[t + 4]) + h1 * a[t + 5]) + h2 * a[t + 6]
    elif r >= 1:
        g0 = gl[j]
        if r == 1:
            for t in range(T):
                o[t] = o[t] + g0 * a[t]
        elif r == 2:
            g1 = gl[j + 1]
            for t in range(T):
                o[t] = (o[t] + g0 * a[t]) + g1 * a[t + 1]
        else:
            g1, g2 = gl[j + 1], gl[j + 2]
            for t in range(T):
                o[t] = ((o[t] + g0 * a[t]) + g1 * a[t + 1]) + g2 * a[t + 2]


@njit(cache=True, nogil=True)
def _correlate_direct_kernel(x, g, peak, left, out):
    """``out[m, l, t] = sum_j g[l, j] x[m, l, t - peak[l] + j]``, mirrored edges.

    ``x`` (M, L, T) of any numeric dtype, ``out`` (M, L, T) float32; each row is
    converted into one float32 buffer reused across rows and extended by ``left``
    samples on the left (and what the IRF needs on the right) by half-sample symmetric
    reflection (scipy.ndimage ``mode="reflect"``, the sources precomputed), then the
    float32 taps ``g`` are summed in float32 by :func:`_tap_sweeps` (twice the vector
    lanes of float64: -28 % on this pass; the values move by at most one float32 step
    against float64 sums, benchmarks/README.md "branch speed23"). The row is written
    through a view indexed from 0 (the former ``xp[left + u]`` and the sweeps through an
    accumulator: 1.6 -> 0.95 ns a sample, benchmarks/README.md "cor37"). Each pixel's
    series is filtered on its own, so the result does not depend on blocks, threads or
    tiles.
    """
    M, L, T = x.shape
    n = g.shape[1]
    right = n  # at most n - 1 - min(peak) samples are read past the end
    xp = np.empty(left + T + right, np.float32)
    idx = _mirror_index(left, T, right)
    mid = xp[left : left + T]
    for m in range(M):
        for l in range(L):
            row = x[m, l]
            for u in range(T):
                mid[u] = np.float32(row[u])
            for u in range(left):
                xp[u] = mid[idx[u]]
            for u in range(right):
                xp[left + T + u] = mid[idx[left + u]]
            _tap_sweeps(out[m, l], xp, left - peak[l], g[l], n)


def correlate_direct(
    x: np.ndarray, irf: np.ndarray, peak: np.ndarray, out: np.ndarray, *, n_threads: int = 1
) -> np.ndarray:
    """Matched filter along t by direct summation (short IRFs): see
    :class:`~splidar.detection._filters.Correlator`, which chooses it.

    Parameters
    ----------
    x : ndarray (..., L, T)
        Counts (any numeric dtype) or float32 values.
    irf : ndarray (L, n)
        Taps (rounded to float32: the sums run in float32).
    peak : ndarray (L,) int
        Sample of each IRF's peak (the response of a return peaks on its depth bin).
    out : ndarray (..., L, T) float32
        Written.
    n_threads : int
        Threads over the leading rows (the kernel releases the GIL); the result does
        not depend on them.

    Example
    -------
    >>> import numpy as np
    >>> y = np.zeros((1, 1, 20)); y[0, 0, 10] = 1.0
    >>> g = np.array([[0.25, 0.5, 0.25]])
    >>> out = np.empty((1, 1, 20), np.float32)
    >>> r = correlate_direct(y, g, np.array([1]), out)
    >>> [float(v) for v in r[0, 0, 9:12]]
    [0.25, 0.5, 0.25]
    """
    L, T = x.shape[-2:]
    xs = x.reshape((-1, L, T))
    if not xs.flags.c_contiguous:
        xs = np.ascontiguousarray(xs)
    if not (out.flags.c_contiguous and out.dtype == np.float32):
        tmp = correlate_direct(x, irf, peak, np.empty(x.shape, np.float32), n_threads=n_threads)
        out[...] = tmp
        return out
    os_ = out.reshape((-1, L, T))
    g = np.ascontiguousarray(irf, dtype=np.float32)
    pk = np.ascontiguousarray(peak, dtype=np.int64)
    left = int(pk.max()) if pk.size else 0
    M = xs.shape[0]
    n_threads = max(1, min(int(n_threads), M))
    if n_threads == 1 or M < 2:
        _correlate_direct_kernel(xs, g, pk, left, os_)
    else:
        cuts = np.linspace(0, M, n_threads + 1).round().astype(int)
        with ThreadPoolExecutor(n_threads) as ex:
            list(
                ex.map(
                    lambda ab: _correlate_direct_kernel(
                        xs[ab[0] : ab[1]], g, pk, left, os_[ab[0] : ab[1]]
                    ),
                    zip(cuts[:-1], cuts[1:], strict=True),
                )
            )
    return out
