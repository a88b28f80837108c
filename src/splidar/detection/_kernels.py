"""Numba kernels of the surface extraction (runs of the binary map, multiscale gathers)."""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from ._fast import _refl  # one reflect rule for every kernel

__all__ = [
    "ORDER_BAND",
    "extract_surfaces",
    "find_segments",
    "rank_in_pixel_sorted",
    "select_sorted",
    "threshold_pass",
]


@njit(cache=True, nogil=True, inline="always")
def _reflect(i, n):
    """:func:`~splidar.detection._fast._refl` (``mode="reflect"``), without its integer
    divisions for an index already inside ``[0, n)`` (almost every one)."""
    if i >= 0 and i < n:
        return i
    return _refl(i, n)


@intrinsic
def _prefetch(typingctx, arr, idx):
    """Hint the CPU to fetch the cache line of ``arr[idx]`` (1-d array) for reading
    (``llvm.prefetch``: no effect on any value, no fault on any address)."""
    if not isinstance(arr, types.Array) or arr.ndim != 1 or not isinstance(idx, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(
            context, builder, aryty, ary, [args[1]], wraparound=False, boundscheck=False
        )
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        # read, high temporal locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


@njit(cache=True, nogil=True)
def _prefetch_next(c, y, rows, cols, peak_bin, order, ii, i_end, scales, r0, e0, ce0, W, T,
                   n_rows_img, n_cols_img):  # fmt: skip
    """Prefetch what candidate ``order[ii]`` reads from ``c`` and ``y`` that its
    predecessor ``order[ii - 1]`` did not (the columns entering its boxes): the first
    and last bin of its window (at the peak; a long run's window may move) in each.
    Speed only: the box sums wait on memory, the lines scattered over the block."""
    if ii >= i_end:
        return
    s = order[ii]
    irow = rows[s] + r0
    jcol = cols[s]
    off = min(max(peak_bin[s] - W // 2, 0), max(T - W, 0))
    last = min(off + W, T) - 1
    hmax = scales[scales.size - 1] // 2
    L = c.shape[2]
    j_first = jcol - hmax
    if ii > 0:
        p = order[ii - 1]
        if rows[p] == rows[s] and peak_bin[p] // ORDER_BAND == peak_bin[s] // ORDER_BAND:
            j_first = max(j_first, cols[p] + hmax + 1)
    for dj in range(j_first - jcol, hmax + 1):
        cj = _reflect(jcol + dj, n_cols_img) - ce0
        for di in range(-hmax, hmax + 1):
            ri = _reflect(irow + di, n_rows_img) - e0
            for l in range(L):
                cr = c[ri, cj, l]
                _prefetch(cr, off)
                _prefetch(cr, last)
    yr = irow - e0
    for l in range(L):
        v = y[yr, jcol - ce0, l]
        _prefetch(v, off)
        _prefetch(v, last)


@njit(cache=True, nogil=True)
def _segments_of_run(d, s, e, a, b, min_sep, rho, seg_start, seg_stop, seg_peak, seg_mass, seg_ev,
                     cand, vals, acc):  # fmt: skip
    """Split the run ``[a, b)`` at deep minima between separated peaks of ``d``.

    Returns the number of segments written into the ``seg_*`` scratch arrays. ``cand``,
    ``vals`` (float64) and ``acc``: scratch of at least ``b - a`` values (no allocation
    per run: most runs are short and have one peak).
    """
    nc = 0
    for t in range(a, b):
        left = d[t - 1] if t > a else -np.inf
        right = d[t + 1] if t < b - 1 else -np.inf
        if d[t] >= left and d[t] > right:
            cand[nc] = t
            nc += 1
    if nc == 0:
        # flat run: take its first maximum
        best = a
        for t in range(a, b):
            if d[t] > d[best]:
                best = t
        cand[0] = best
        nc = 1
    if nc == 1:
        # one peak: the whole run (what the general path below gives for one peak)
        m = 0.0
        ev = 0.0
        for t in range(a, b):
            m += s[t]
            ev += e[t]
        seg_ev[0] = ev
        seg_start[0] = a
        seg_stop[0] = b
        seg_peak[0] = cand[0]
        seg_mass[0] = m
        return 1
    for i in range(nc):
        vals[i] = -d[cand[i]]
    order = np.argsort(vals[:nc])
    na = 0
    for oi in range(nc):
        p = cand[order[oi]]
        ok = True
        for j in range(na):
            q = acc[j]
            if abs(p - q) < min_sep:
                ok = False
                break
            lo = min(p, q)
            hi = max(p, q)
            dip = d[lo]
            for t in range(lo, hi + 1):
                if d[t] < dip:
                    dip = d[t]
            if dip > rho * min(d[p], d[q]):
                ok = False
                break
        if ok:
            acc[na] = p
            na += 1
    peaks = np.sort(acc[:na])
    start = a
    for i in range(na):
        if i < na - 1:
            lo = peaks[i]
            hi = peaks[i + 1]
            cut = lo
            for t in range(lo, hi + 1):
                if d[t] < d[cut]:
                    cut = t
            stop = cut
            if stop <= start:
                stop = start + 1
        else:
            stop = b
        m = 0.0
        ev = 0.0
        for t in range(start, stop):
            m += s[t]
            ev += e[t]
        seg_ev[i] = ev
        seg_start[i] = start
        seg_stop[i] = stop
        seg_peak[i] = peaks[i]
        seg_mass[i] = m
        start = stop
    return na


@njit(cache=True, nogil=True, inline="always")
def _fine_at(c, y, sp, dev, win, t):
    """The own pixel's fine response at bin ``t``: ``(f, n, mu_b)``.

    ``f = sum_l c_l(t) - bhat_l(t)``: the matched-filter response minus background
    (``c`` (L, T) the pixel's correlated counts ``Y (*) g``, ``g`` summing to 1); ``n``:
    the pixel's photons ``y`` (L, T) in the window of a return peaking at ``t`` (bins
    ``t + win[l, 0]`` to ``t + win[l, 1]``: where the IRF is above half its peak);
    ``mu_b``: the background ``bhat`` expects there.
    """
    n, mu = _fine_counts(y, sp, dev, win, t)
    return _fine_f(c, sp, dev, t), n, mu


@njit(cache=True, nogil=True, inline="always")
def _fine_f(c, sp, dev, t):
    """``f`` of :func:`_fine_at` alone."""
    f = 0.0
    for l in range(c.shape[0]):
        b = sp[l] + dev[l, t]
        if b < 0:
            b = np.float32(0.0)
        f += np.float64(c[l, t]) - np.float64(b)
    return f


@njit(cache=True, nogil=True, inline="always")
def _fine_counts(y, sp, dev, win, t):
    """``(n, mu_b)`` of :func:`_fine_at` alone."""
    L, T = y.shape
    n = 0.0
    mu = 0.0
    for l in range(L):
        for u in range(max(t + win[l, 0], 0), min(t + win[l, 1] + 1, T)):
            n += np.float64(y[l, u])
            bu = sp[l] + dev[l, u]
            if bu > 0:
                mu += np.float64(bu)
    return n, mu


@njit(cache=True, nogil=True)
def fine_response(c, y, sp, dev, win, f, n, mu):
    """:func:`_fine_at` of every voxel: ``f``, ``n``, ``mu`` (r, C, T) float32 written.

    ``c`` (r, C, L, T) correlated counts, ``y`` (r, C, L, T) counts, ``sp`` (r, C, L)
    background level, ``dev`` (L, T), ``win`` (L, 2) the half-peak window's offsets.
    """
    R, C, L, T = c.shape
    for i in range(R):
        for j in range(C):
            for t in range(T):
                a, b, m = _fine_at(c[i, j], y[i, j], sp[i, j], dev, win, t)
                f[i, j, t] = np.float32(a)
                n[i, j, t] = np.float32(b)
                mu[i, j, t] = np.float32(m)


@njit(cache=True, nogil=True, inline="always")
def _poisson_z(n, mu):
    """Signed root of the Poisson deviance of ``n`` counts against mean ``mu``: about
    the normal z of the upper tail ``P(X >= n)``, also for a few counts."""
    mu = max(mu, 1e-12)
    if n <= mu:
        return -1.0
    dev = 2.0 * (n * np.log(n / mu) - (n - mu))
    return np.sqrt(max(dev, 0.0))


@njit(cache=True, nogil=True)
def _pooled_counts(pool, p, q, tail, gmin, min_sep):
    """The 3 x 3 neighbours' photons at ``q``'s place relative to their own return near
    ``p`` (:func:`_fine_split`'s pooled test): ``(n, spill, m)``.

    Each of the ``m`` neighbours inside the array takes its own return as the maximum
    of its fine response within ``min_sep // 2`` bins of ``p`` (at ``p'``); ``n`` sums
    its photons in the half-peak window at ``q + p' - p`` (a surface beside a tilted
    one keeps its distance), ``spill`` what that return brings there (``tail`` of its
    response / ``gmin``, as the own pixel's). The background is the own pixel's (its
    neighbours' are not all in the block: the same values for any block layout).
    """
    fine, from_c, i, j, win, _ = pool
    c, y, row0, col0, sp, dev, f_in, n_in, mu_in = fine
    if from_c:
        R, C, T = c.shape[0], c.shape[1], c.shape[3]
        ci, cj = row0 + i, col0 + j
    else:
        R, C, T = f_in.shape
        ci, cj = i, j
    side = 0 if q > p else 1
    k = abs(q - p)
    h = max(min_sep // 2, 1)
    n = 0.0
    spill = 0.0
    m = 0
    for a in range(ci - 1, ci + 2):
        for b in range(cj - 1, cj + 2):
            if (a == ci and b == cj) or a < 0 or b < 0 or a >= R or b >= C:
                continue
            best = -np.inf
            pb = p
            for t in range(max(p - h, 0), min(p + h + 1, T)):
                if from_c:
                    v = np.float64(np.float32(_fine_f(c[a, b], sp[i, j], dev, t)))
                else:
                    v = np.float64(f_in[a, b, t])
                if v > best:
                    best = v
                    pb = t
            qq = q + pb - p
            if qq < 0 or qq >= T:
                continue
            if from_c:
                n += np.float64(np.float32(_fine_counts(y[a, b], sp[i, j], dev, win, qq)[0]))
            else:
                n += np.float64(n_in[a, b, qq])
            if k < tail.shape[1]:
                spill += tail[side, k] * max(best, 0.0) / gmin
            m += 1
    return n, spill, m


@njit(cache=True, nogil=True)
def _fine_split(fr, nr, mr, st, en, min_sep, z, tail, gmin, reach, peaks, cuts, cand, vals, acc,
                pool):  # fmt: skip
    """Peaks of the own pixel's fine response ``fr`` in the segment ``[st, en)`` that
    are separate returns.

    Interior local maxima of ``fr``, strongest first, are accepted when at least
    ``min_sep`` bins from every accepted (stronger) peak ``p`` and when the pixel's
    photons in the half-peak window at ``q``, ``nr[q]``, exceed what the background
    (``mr[q]``) and the return at ``p`` bring there by ``sqrt(z^2 + 2 ln n)``
    (:func:`_poisson_z`; ``n`` the segment's bins, the places a second return was
    looked for: ``z`` against the largest of ``n`` background values): the
    return at ``p`` holds ``fr[p] / gmin`` photons (``gmin``: the smallest ``sum g^2``),
    a fraction ``tail[0, k]`` of them in the window ``k = q - p`` bins behind it, ``tail[1, k]``
    in the window ``k = p - q`` bins in front (its rise, not its tail). Writes the
    accepted peaks in increasing order into ``peaks`` and the cuts (the response's
    minimum between two consecutive peaks) into ``cuts``; returns their number (1: not
    split). ``nr`` and ``mr`` are read only at the interior local maxima of ``fr``.
    ``cand``, ``vals`` (float64) and ``acc``: scratch of at least ``en - st`` values.

    ``pool``: ``(fine, from_c, i, j, win, on)`` (:func:`find_segments`: the pixel ``(i,
    j)``; ``on`` false: no pooled test). A peak ``q`` in front of ``p`` that the own
    photons show by at least ``z`` (at one place: the pooled test found it) but not by
    ``sqrt(z^2 + 2 ln n)`` is accepted when the 3 x 3 neighbourhood's photons at the
    same place relative to each pixel's own return near ``p`` (:func:`_pooled_counts`)
    with the own ones beat their background and those returns' rise by ``sqrt(z^2 + 2
    ln n)``, and ``p``'s own photons ``nr[p]`` beat their background and what ``q``'s
    return brings behind it (``tail[0]``, ``fr[q] / gmin`` photons) by ``z`` (a split
    leaves two returns: else ``p`` is ``q``'s tail, a real return split off before a
    noise bump in its tail). Behind ``p`` never: a real or SPAD return's tail lies there,
    and the neighbours' tails heavier than the pooled one would add up. A weak return
    2-3 FWHM before a bright tailed one shows 4-5 photons a pixel, z 3.5-3.9 against
    4.1-4.3 needed (a net before a wall, benchmarks/README.md "gap31, session 23"; the
    tail check "gap31b, session 23").
    """
    n = en - st
    if n < 3 or z <= 0:
        return 1
    nc = 0
    for t in range(st + 1, en - 1):
        if fr[t] >= fr[t - 1] and fr[t] > fr[t + 1]:
            cand[nc] = t
            nc += 1
    if nc < 2:
        return 1
    for i in range(nc):
        vals[i] = -fr[cand[i]]
    order = np.argsort(vals[:nc])
    # the largest of the segment's bins: z against the max of that many tested places
    # (as _window_centre)
    z_need = np.sqrt(z * z + 2.0 * np.log(n))
    na = 0
    for oi in range(nc):
        q = cand[order[oi]]
        ok = True
        if reach > 0 and na > 0:
            # a second return only where the coarse scales merge it with a stronger
            # one: within ``reach`` of an accepted peak
            near = False
            for j in range(na):
                if abs(acc[j] - q) <= reach:
                    near = True
            ok = near
        for j in range(na if ok else 0):
            p = acc[j]
            k = abs(p - q)
            if k < min_sep:
                ok = False
                break
            side = 0 if q > p else 1  # q behind p: p's tail; in front: its rise
            spill = tail[side, k] * max(fr[p], 0.0) / gmin if k < tail.shape[1] else 0.0
            zq = _poisson_z(nr[q], mr[q] + spill)
            if zq >= z_need:
                continue
            # pooled: in front of p only (a real or SPAD return's tail lies behind it:
            # behind, the neighbours' tails heavier than the pooled one would add up)
            if not pool[5] or side == 0 or zq < z:
                ok = False
                break
            nn, ss, m = _pooled_counts(pool, p, q, tail, gmin, min_sep)
            if _poisson_z(nr[q] + nn, mr[q] * (1 + m) + spill + ss) < z_need:
                ok = False
                break
            # both parts returns of their own: p's photons beat what q's return brings
            # behind it (its tail) by z at p's one place, else p is q's tail
            back = tail[0, k] * max(fr[q], 0.0) / gmin if k < tail.shape[1] else 0.0
            if _poisson_z(nr[p], mr[p] + back) < z:
                ok = False
                break
        if ok:
            acc[na] = q
            na += 1
    if na < 2:
        return 1
    pk = np.sort(acc[:na])
    for i in range(na):
        peaks[i] = pk[i]
    for i in range(na - 1):
        m = pk[i]
        for t in range(pk[i], pk[i + 1] + 1):
            if fr[t] < fr[m]:
                m = t
        cuts[i] = m
    return na


@njit(cache=True, nogil=True, inline="always")
def _own_part(fr, peaks, nf, win):
    """Which of the ``nf`` parts of a split segment is its own (the rest are returns
    the split added, :func:`find_segments`): the one with the strongest fine response
    ``fr`` at its peak among those whose half-peak window (``win`` (L, 2), widest over
    the wavelengths) lies inside the window, else the strongest. A return peaking at
    or past the window's end shows only its rise there; on strength alone that part
    took the segment from the return before it (a net before a wall at the window's
    end, benchmarks/README.md "gap30, session 22")."""
    T = fr.size
    lo, hi = win[:, 0].min(), win[:, 1].max()
    w0 = -1
    for w in range(nf):
        if peaks[w] + hi < T and peaks[w] + lo >= 0:
            if w0 < 0 or fr[peaks[w]] > fr[peaks[w0]]:
                w0 = w
    if w0 >= 0:
        return w0
    w0 = 0
    for w in range(1, nf):
        if fr[peaks[w]] > fr[peaks[w0]]:
            w0 = w
    return w0


@njit(cache=True, nogil=True)
def _segment_sums(s, e, a, b):
    m = 0.0
    ev = 0.0
    for t in range(a, b):
        m += s[t]
        ev += e[t]
    return m, ev


@njit(cache=True, nogil=True)
def _fine_of_run(c, y, sp, dev, win, a, b, fr, nr, mr):
    """:func:`_fine_at` of the pixel's run ``[a, b)`` into ``fr``, ``nr``, ``mr`` (T,),
    rounded to float32 as the null's stored values (the same tests): ``f`` at every bin,
    ``n`` and ``mu`` only where :func:`_fine_split` reads them, the interior local maxima
    of ``fr`` (a segment's are its run's)."""
    for u in range(a, b):
        fr[u] = np.float32(_fine_f(c, sp, dev, u))
    for u in range(a + 1, b - 1):
        if fr[u] >= fr[u - 1] and fr[u] > fr[u + 1]:
            n, mu = _fine_counts(y, sp, dev, win, u)
            nr[u] = np.float32(n)
            mr[u] = np.float32(mu)


@njit(cache=True, nogil=True, inline="always")
def _next_run(m, t):
    """The first ``u >= t`` with ``m[u]`` (``m.size`` if none): the start of the next run
    of a pixel's mask ``m`` (T,) bool (a tight loop over one pixel's row: the skip over
    the clear bins was about half of :func:`find_segments`' time indexed ``mask[i, j, t]``)."""
    T = m.size
    while t < T and not m[t]:
        t += 1
    return t


@njit(cache=True, nogil=True)
def find_segments(mask, d, s, e, min_sep, rho, fine, split):
    """Candidate surfaces: runs of ``mask`` along t, split between resolved peaks.

    Parameters
    ----------
    mask : (r, c, T) bool
    d : (r, c, T) float32
        Signed multiscale matched-filter response minus background (summed over L).
    s : (r, c, T) float32
        Saliency (``eq:4.s1``), summed over each segment (``mass``).
    e : (r, c, T) float32
        Evidence per voxel (excess of the saliency over the threshold), summed over
        each segment (``evidence``).
    min_sep : int
        Peaks closer than this (bins) are one surface.
    rho : float
        Two peaks are two surfaces if ``d`` dips below ``rho`` times the smaller peak
        between them.
    fine : tuple
        ``(c, y, row0, col0, sp, dev, f, n, mu)``: the own pixel's fine response, read
        by :func:`_fine_at` from the correlated counts ``c`` and counts ``y`` (pixel
        ``(i, j)`` at ``[row0 + i, col0 + j]``, background ``sp[i, j]``, ``dev``), or
        taken from ``f``, ``n`` and ``mu`` (r, c, T) float32 when ``c`` is empty (the
        null's patches; the values read from ``c`` are rounded to float32 alike).
    split : tuple
        ``(z, tail, gmin, win)`` (:func:`~splidar.detection._3_null.split_rule`): a
        segment of ``d`` is split further where the own pixel's photons show a second
        return of ``z`` beside the first (:func:`_fine_split`); ``z = 0``: never.

    Returns
    -------
    row, col, start, stop, peak : int64 arrays; mass, evidence : float64 arrays;
    added : bool array
        ``added``: a part the fine split cut off a stronger return's segment.
    """
    c, y, row0, col0, sp, dev, f_in, n_in, mu_in = fine
    split_z, tail, gmin, win, reach, pool = split
    from_c = c.shape[0] > 0
    R, C, T = mask.shape
    nmax = 0  # runs of the mask along t
    total = 0  # voxels of the mask
    for i in range(R):
        for j in range(C):
            for t in range(T):
                if mask[i, j, t]:
                    total += 1
                    if t == 0 or not mask[i, j, t - 1]:
                        nmax += 1
    # segments: min_sep apart in d, again within d's segments (bound generously)
    cap = min(total, nmax * 2 * (T // max(min_sep, 1) + 1)) + 1
    o_row = np.empty(cap, np.int64)
    o_col = np.empty(cap, np.int64)
    o_start = np.empty(cap, np.int64)
    o_add = np.zeros(cap, np.bool_)
    o_stop = np.empty(cap, np.int64)
    o_peak = np.empty(cap, np.int64)
    o_mass = np.empty(cap, np.float64)
    o_ev = np.empty(cap, np.float64)
    seg_start = np.empty(T, np.int64)
    seg_stop = np.empty(T, np.int64)
    seg_peak = np.empty(T, np.int64)
    seg_mass = np.empty(T, np.float64)
    seg_ev = np.empty(T, np.float64)
    fr = np.zeros(T)
    nr = np.zeros(T)
    mr = np.zeros(T)
    f_peaks = np.empty(T, np.int64)
    f_cuts = np.empty(T, np.int64)
    sc_cand = np.empty(T, np.int64)  # scratch of the per-run and per-segment kernels
    sc_vals = np.empty(T)
    sc_acc = np.empty(T, np.int64)
    k = 0
    for i in range(R):
        for j in range(C):
            mij = mask[i, j]
            t = _next_run(mij, 0)
            while t < T:
                a = t
                while t < T and mij[t]:
                    t += 1
                b = t
                ns = _segments_of_run(
                    d[i, j],
                    s[i, j],
                    e[i, j],
                    a,
                    b,
                    min_sep,
                    rho,
                    seg_start,
                    seg_stop,
                    seg_peak,
                    seg_mass,
                    seg_ev,
                    sc_cand,
                    sc_vals,
                    sc_acc,
                )
                if split_z > 0 and b - a >= 3:
                    if from_c:
                        ii, jj = row0 + i, col0 + j
                        _fine_of_run(c[ii, jj], y[ii, jj], sp[i, j], dev, win, a, b, fr, nr, mr)
                    else:
                        fr[a:b] = f_in[i, j, a:b]
                        nr[a:b] = n_in[i, j, a:b]
                        mr[a:b] = mu_in[i, j, a:b]
                for u in range(ns):
                    nf = 1
                    if split_z > 0:
                        nf = _fine_split(
                            fr, nr, mr, seg_start[u], seg_stop[u], min_sep, split_z, tail, gmin,
                            reach, f_peaks, f_cuts, sc_cand, sc_vals, sc_acc,
                            (fine, from_c, i, j, win, pool),
                        )  # fmt: skip
                    if nf == 1:
                        o_row[k] = i
                        o_col[k] = j
                        o_start[k] = seg_start[u]
                        o_stop[k] = seg_stop[u]
                        o_peak[k] = seg_peak[u]
                        o_mass[k] = seg_mass[u]
                        o_ev[k] = seg_ev[u]
                        k += 1
                        continue
                    # d's segment split at the fine response's dips, each part about
                    # the fine response's peak (d's, the coarse blend of both, lies
                    # between them)
                    lo = seg_start[u]
                    w0 = _own_part(fr, f_peaks, nf, win)  # the rest: parts the split added
                    for w in range(nf):
                        hi = f_cuts[w] if w < nf - 1 else seg_stop[u]
                        pk = f_peaks[w]
                        m, ev = _segment_sums(s[i, j], e[i, j], lo, hi)
                        o_row[k] = i
                        o_col[k] = j
                        o_start[k] = lo
                        o_stop[k] = hi
                        o_peak[k] = pk
                        o_mass[k] = m
                        o_ev[k] = ev
                        o_add[k] = w != w0
                        k += 1
                        lo = hi
                t = _next_run(mij, t)
    return (
        o_row[:k], o_col[:k], o_start[:k], o_stop[:k], o_peak[:k], o_mass[:k], o_ev[:k],
        o_add[:k],
    )  # fmt: skip


@njit(cache=True, nogil=True)
def _interp_irf(g, x):
    """``np.interp(x, arange(n), g, left=0, right=0)`` for one sample."""
    n = g.size
    if x < 0.0 or x > n - 1:
        return 0.0
    i = int(np.floor(x))
    if i >= n - 1:
        return g[n - 1]
    return g[i] + (x - i) * (g[i + 1] - g[i])


@njit(cache=True, nogil=True)
def _parabola(u, w0, W):
    """Sub-bin offset of the vertex of the parabola through ``u[w0-1:w0+2]``.

    Kept only for a concave peak away from the window edges, clipped to half a bin.
    """
    if w0 <= 0 or w0 >= W - 1:
        return 0.0
    um = np.float64(u[w0 - 1])
    uc = np.float64(u[w0])
    up = np.float64(u[w0 + 1])
    den = um - 2.0 * uc + up
    if den < 0.0:
        delta = 0.5 * (um - up) / den
        return min(max(delta, -0.5), 0.5)
    return 0.0


@njit(cache=True, nogil=True)
def _llr_one(raw, bh, inside, dw, s, irf, peak, L, W):
    """Own-pixel Poisson log-likelihood ratio of a return of ``s`` (L,) photons at depth
    ``dw`` (window coordinates) against background ``bh`` (L, W) over the support."""
    out = 0.0
    for l in range(L):
        sl = max(s[l], 1e-9)
        gsum = 0.0
        for w in range(W):
            if not inside[w]:
                continue
            gv = _interp_irf(irf[l], w - dw + peak[l])
            gsum += gv
            if raw[l, w] != 0.0:  # 0 * log1p(x >= 0) adds +0.0: skipped, same bits
                b = max(np.float64(bh[l, w]), 1e-9)
                out += raw[l, w] * np.log1p(sl * gv / b)
        out -= sl * gsum
    return out


@njit(cache=True, nogil=True)
def _window_centre(c, sp, dev, gsq, row_blk, irow, jc, jo, e0, start, stop, centre, refine_z, wh):
    """A run longer than the window (a steep slope smears the coarse scales): the own
    pixel's matched-filter peak in the run when it is significant against the max of
    that many background bins, else ``centre``. ``jc`` and ``jo``: the pixel's column in
    ``c`` and in ``sp``."""
    L = c.shape[2]
    n_run = stop - start
    z_need = np.sqrt(refine_z * refine_z + 2.0 * np.log(n_run))
    yr0 = irow - e0
    best_z = -np.inf
    best_t = centre
    for t in range(start, stop):
        num = 0.0
        var = 0.0
        for l in range(L):
            b = sp[row_blk, jo, l] + dev[l, t]
            if b < 0:
                b = np.float32(0.0)
            num += c[yr0, jc, l, t] - b
            var += max(b, np.float32(1e-6)) * gsq[l]
        z = num / np.sqrt(var)
        if z > best_z:
            best_z = z
            best_t = t
    if best_z >= z_need and abs(best_t - centre) >= wh:
        return best_t
    return centre


#: Bins per depth band of the order in which candidates are extracted: consecutive
#: candidates of a band and an image row share the column sums of :func:`_box_sums`
#: (speed only; every sum is the same whatever the order).
ORDER_BAND = 16


@njit(cache=True, nogil=True)
def _fill_columns(colbuf, c, scales, rr, cj, a, b, ts):
    """``colbuf[q, cj, l, t - ts]`` for ``t`` in ``[a, b)``: the sum of block rows
    ``rr[0], rr[1], rr[2], ...`` of column ``cj`` (the centre row, then rows ``-d`` and
    ``+d`` for ``d = 1, 2, ...``) up to ``h_q = scales[q] // 2`` in float64, in that
    order; scale ``q`` continues the sum of ``q - 1``.

    One running sum per bin, kept in a register and stored once per scale (not a pass
    over ``colbuf`` per row pair and a copy per scale): the same additions in the same
    order, so the same values; 12-20 % less CPU in :func:`extract_surfaces` on the
    200 x 200 x 4 x 1500 bench cube (``benchmarks/README.md``, "map37, session 25").
    """
    Q = scales.size
    L = c.shape[2]
    for l in range(L):
        for t in range(a, b):
            v = np.float64(c[rr[0], cj, l, t])
            d = 1
            for q in range(Q):
                h = scales[q] // 2
                while d <= h:
                    v = v + c[rr[2 * d - 1], cj, l, t]
                    v = v + c[rr[2 * d], cj, l, t]
                    d += 1
                colbuf[q, cj, l, t - ts] = v


@njit(cache=True, nogil=True)
def _column_sums(colbuf, valid, gen, c, scales, rr, cj, t0, t1, ts):
    """Column sums of block column ``cj`` about one image row for ``t`` in ``[t0, t1)``
    (:func:`_fill_columns`, rows ``rr`` reflected at the image's edges). ``valid[cj] =
    (gen, lo, hi)``: ``colbuf`` holds them for ``[lo, hi)`` of the current image row
    and span; only what the window adds to that interval is computed (all of it when
    the two neither overlap nor touch). Every value is the same whenever it is
    computed."""
    if valid[cj, 0] == gen:
        lo = valid[cj, 1]
        hi = valid[cj, 2]
        if t0 >= lo and t1 <= hi:
            return
        if t1 >= lo and t0 <= hi:
            if t0 < lo:
                _fill_columns(colbuf, c, scales, rr, cj, t0, lo, ts)
                valid[cj, 1] = t0
            if t1 > hi:
                _fill_columns(colbuf, c, scales, rr, cj, hi, t1, ts)
                valid[cj, 2] = t1
            return
    _fill_columns(colbuf, c, scales, rr, cj, t0, t1, ts)
    valid[cj, 0] = gen
    valid[cj, 1] = t0
    valid[cj, 2] = t1


@njit(cache=True, nogil=True)
def _window_background(bh, sp, dev, row_blk, jo, off):
    """``bhat`` (``eq:background_3``, clipped at 0) of one pixel over the window:
    ``bh`` (L, W) float32."""
    L, W = bh.shape
    for l in range(L):
        spl = sp[row_blk, jo, l]
        for w in range(W):
            b = spl + dev[l, off + w]
            if b < 0:
                b = np.float32(0.0)
            bh[l, w] = b


@njit(cache=True, nogil=True)
def _box_sums(acc, colbuf, valid, state, rr, c, scales, irow, jcol, e0, ce0, hint, off,
              n_rows_img, n_cols_img):  # fmt: skip
    """Box sums of every scale about image pixel ``(irow, jcol)`` over the window ``[off,
    off + W)``: ``acc[q, l, w]`` (Q, L, W) float64, the column sums of
    :func:`_column_sums` added left to right, columns ``jcol - h_q .. jcol + h_q``
    reflected at the image's edges. Image pixel ``(i, j)`` is ``c[i - e0, j - ce0]``.
    The column sums of one image row over a span of ``n_span`` bins from ``ts`` are
    cached in ``colbuf`` (Q, ec, L, n_span), column ``cj`` over ``[lo, hi)`` where
    ``valid[cj] = (gen, lo, hi)``; ``state = [gen, row, ts]``. Another row, or a window
    outside the span, starts the cache afresh from bin ``hint`` (clipped; ``off`` when
    the window is not inside). ``rr`` (2 h_max + 1,) int64 is scratch (the block rows
    of the boxes). Each sum is the same whatever was cached.
    """
    T = c.shape[3]
    n_span = colbuf.shape[3]
    Q, L, W = acc.shape
    if irow != state[1] or off < state[2] or off + W > state[2] + n_span:
        state[0] += 1
        state[1] = irow
        state[2] = min(max(hint, 0), T - n_span)
        if off < state[2] or off + W > state[2] + n_span:
            state[2] = min(off, T - n_span)
    gen = state[0]
    ts = state[2]
    hmax = scales[Q - 1] // 2
    rr[0] = irow - e0  # block rows: centre, then -d, +d
    for d in range(1, hmax + 1):
        rr[2 * d - 1] = _reflect(irow - d, n_rows_img) - e0
        rr[2 * d] = _reflect(irow + d, n_rows_img) - e0
    for dj in range(-hmax, hmax + 1):
        cj = _reflect(jcol + dj, n_cols_img) - ce0
        _column_sums(colbuf, valid, gen, c, scales, rr, cj, off, off + W, ts)
    for q in range(Q):
        h = scales[q] // 2
        for l in range(L):
            for w in range(W):
                acc[q, l, w] = 0.0
        for dj in range(-h, h + 1):
            cj = _reflect(jcol + dj, n_cols_img) - ce0
            for l in range(L):
                cb = colbuf[q, cj, l]
                for w in range(W):
                    acc[q, l, w] += cb[off - ts + w]


@njit(cache=True, nogil=True)
def _clean_responses(
    s, c, box, bidx, scales, acc, use_box, irow, row_blk, jc, jo, e0, off, inside, bh,
    resp, hv_buf, per_scale, o_hist, o_signal,
):  # fmt: skip
    """Per scale: the response minus ``bhat`` (``resp``), the clean histogram
    (``eq:background_final``) and its sum, and the clean response summed over L. ``jc``
    and ``jo``: the pixel's column in ``c`` and in ``box``."""
    Q, L, W = resp.shape
    for q in range(Q):
        bq = bidx[q]
        inv = 1.0 / (scales[q] * scales[q])
        for w in range(W):
            per_scale[q, w] = 0.0
        for l in range(L):
            if not use_box:
                for w in range(W):
                    hv_buf[w] = np.float32(acc[q, l, w] * inv)
            elif bq < 0:  # scale 1: the correlated block itself
                cr = c[irow - e0, jc, l]
                for w in range(W):
                    hv_buf[w] = cr[off + w]
            else:  # box means computed once per voxel by the saliency pass
                cr = box[l, bq, row_blk, jo]
                for w in range(W):
                    hv_buf[w] = cr[off + w]
            ssum = 0.0
            for w in range(W):
                hv = hv_buf[w]
                r = hv - bh[l, w]
                resp[q, l, w] = r
                cv = r if (r > 0 and inside[w]) else np.float32(0.0)  # eq:background_final
                o_hist[s, q, l, w] = cv
                ssum += cv
                per_scale[q, w] += cv
            o_signal[s, q, l] = ssum


@njit(cache=True, nogil=True)
def _select_scale(per_scale, tot, d_q):
    """``eq:depth_global`` / ``eq:depth_scale`` on the clean matched-filter response
    (per-scale peaks into ``d_q``) and the selected scale ``eq:scale_sel``."""
    Q, W = per_scale.shape
    for w in range(W):
        tot[w] = 0.0
    for q in range(Q):
        best = 0
        for w in range(W):
            tot[w] += per_scale[q, w]
            if per_scale[q, w] > per_scale[q, best]:
                best = w
        d_q[q] = best
    d_glob = 0
    for w in range(W):
        if tot[w] > tot[d_glob]:
            d_glob = w
    qbar = 0
    if Q > 1:
        qbar = 1
        for q in range(2, Q):
            if abs(d_q[q] - d_glob) < abs(d_q[qbar] - d_glob):
                qbar = q  # eq:scale_sel
    return qbar


@njit(cache=True, nogil=True)
def _scale_variance(uq, resp, fisher, q, wq, info):
    """Variance of scale ``q``'s peak: ``1 / info``, widened when the response is wider
    than the IRF's (a slope smeared by the box): scaled by the squared curvature deficit
    plus the spread of depths within the box as a bound on the bias of its peak."""
    L, W = resp.shape[1], resp.shape[2]
    var_q = 1.0 / info
    if q > 0 and 0 < wq < W - 1:
        den = np.float64(uq[wq - 1]) - 2.0 * np.float64(uq[wq]) + np.float64(uq[wq + 1])
        model = 0.0
        for l in range(L):
            model += max(np.float64(resp[q, l, wq]), 0.0) * fisher[l, 2]
        if den >= 0:
            var_q = np.inf
        elif model > 0 and -den < model:
            rho = -den / model
            var_q /= rho * rho
            c0 = 0.0
            for l in range(L):
                c0 += fisher[l, 2] / L
            var_q += (1.0 / rho - 1.0) / max(c0, 1e-12)
    return var_q


@njit(cache=True, nogil=True)
def _ici_depth(resp, bh, per_scale, d_q, uq, scales, gsq, fisher, refine_z, ici_gamma):
    """Depth by the intersection of confidence intervals (ICI) over the scales, finest
    first: each scale's peak with its standard error (Fisher information of n signal
    photons over b background photons per bin, widened when the box smears the return);
    stop at the first scale whose interval misses the intersection of the finer ones and
    take the most precise depth among the scales before it. Returns (found, depth in the
    window)."""
    Q, L, W = resp.shape
    lo_i = -np.inf
    hi_i = np.inf
    d_star = 0.0
    sd_star = np.inf
    q_star = -1
    for q in range(Q):
        wq = d_q[q]
        if per_scale[q, wq] <= 0:
            continue
        k2 = np.float64(scales[q] * scales[q])
        if q == 0:
            # the own pixel takes part only when its peak is significant (z >= refine_z):
            # a peak of a few background photons claims a precision it does not have
            zn = 0.0
            zv = 0.0
            for l in range(L):
                zn += np.float64(resp[0, l, wq])
                zv += max(np.float64(bh[l, wq]), 1e-6) * gsq[l]
            if zn < refine_z * np.sqrt(zv / k2):
                continue
        info = 0.0
        # the response summed over L at the peak and its two neighbours
        wa = max(wq - 1, 0)
        wb = min(wq + 1, W - 1)
        for w in range(wa, wb + 1):
            uq[w] = 0.0
        for l in range(L):
            for w in range(wa, wb + 1):
                uq[w] += resp[q, l, w]
            n_sig = k2 * max(np.float64(resp[q, l, wq]), 0.0) / gsq[l]
            b_pool = k2 * max(np.float64(bh[l, wq]), 1e-6)
            if n_sig > 0:
                info += (n_sig * fisher[l, 0]) ** 2 / (n_sig * fisher[l, 1] + b_pool * fisher[l, 0])
        if info <= 0:
            continue
        dq = wq + _parabola(uq, wq, W)
        var_q = _scale_variance(uq, resp, fisher, q, wq, info)
        if not np.isfinite(var_q):
            continue
        sd = np.sqrt(var_q + 1.0 / 12.0)
        a = max(lo_i, dq - ici_gamma * sd)
        b = min(hi_i, dq + ici_gamma * sd)
        if a > b:
            break
        lo_i = a
        hi_i = b
        if q_star < 0 or sd <= sd_star:
            q_star = q
            d_star = dq
            sd_star = sd
    return q_star >= 0, d_star


@njit(cache=True, nogil=True)
def _own_pixel(
    s, y, yr, jcol, off, inside, bh, raw, o_own_counts, o_own_background, o_counts, o_background
):
    """Own-pixel raw counts and background over the support (zero outside)."""
    L, W = raw.shape
    for l in range(L):
        cnt = 0.0
        bsum = 0.0
        for w in range(W):
            if inside[w]:
                v = y[yr, jcol, l, off + w]
                raw[l, w] = np.float64(v)
                bsum += bh[l, w]
                o_own_counts[s, l, w] = v
                o_own_background[s, l, w] = bh[l, w]
            else:
                raw[l, w] = 0.0
                o_own_counts[s, l, w] = 0
                o_own_background[s, l, w] = 0.0
            cnt += raw[l, w]
        o_counts[s, l] = cnt
        o_background[s, l] = bsum


@njit(cache=True, nogil=True)
def _local_z(resp, bh, gsq, signal_sel, scale, dw):
    """z of the local scale's response at the depth and the z a return of the selected
    scale's intensity would give there."""
    L, W = bh.shape
    wd = int(np.rint(dw))
    wd = min(max(wd, 0), W - 1)
    r_loc = np.float32(0.0)
    var = 0.0
    zp = 0.0
    for l in range(L):
        r_loc += resp[l, wd]
        var += bh[l, wd] * gsq[l]
        zp += signal_sel[l] * gsq[l]
    var /= scale * scale
    sd = np.sqrt(max(var, 1e-12))
    return r_loc / sd, zp / sd


@njit(cache=True, nogil=True)
def extract_surfaces(
    y,
    c,
    box,
    bidx,
    e0,
    r0,
    ce0,
    c0,
    rows,
    cols,
    start,
    stop,
    peak_bin,
    sp,
    dev,
    scales,
    gsq,
    irf,
    irf_peak,
    width,
    n_rows_img,
    n_cols_img,
    refine,
    refine_z,
    fisher,
    ici_gamma,
    qloc,
    want_llr_sel,
    order,
    i_begin,
    i_end,
    o_depth,
    o_lo,
    o_hi,
    o_qbar,
    o_offset,
    o_hist,
    o_signal,
    o_counts,
    o_background,
    o_llr,
    o_zloc,
    o_zpred,
    o_llr_sel,
    o_own_counts,
    o_own_background,
):
    """Clean histograms, scale selection, depth and presence statistics of candidates.

    One candidate at a time (``order[i_begin:i_end]``: indices into the candidate
    arrays, in the order they are computed; no output depends on it), each output
    written at the candidate's position ``ii`` in ``order`` (one after the other, not
    scattered: 5 % faster); see :func:`splidar.detection._4_map._extract` for each. ``rows``: block
    rows (image ``r0 + rows``); ``cols``: image columns. Box means (``mode="reflect"``
    at the image's edges) come from the correlated block ``c`` (``(er, ec, L, T)``
    from image pixel ``(e0, ce0)``), ``bhat`` (``eq:background_3``) from ``sp`` (from
    ``(r0, c0)``) and ``dev``, raw counts from ``y`` (as ``c``); ``o_own_counts`` and
    ``o_own_background`` (S, L, W) get the pixel's counts and ``bhat`` over the window
    (zero outside the support). ``box`` (L, Qb, r, c, T), when ``Qb > 0``: box means of
    the scales with ``bidx[q] >= 0`` from ``(r0, c0)`` (saliency pass; scale 1 is
    ``c``); otherwise (``Qb = 0``) the boxes are summed here, about each candidate.
    """
    Q = scales.size
    L = c.shape[2]
    T = c.shape[3]
    W = width
    wh = W // 2
    resp = np.empty((Q, L, W), np.float32)
    bh = np.empty((L, W), np.float32)
    inside = np.empty(W, np.bool_)
    per_scale = np.empty((Q, W), np.float32)
    tot = np.empty(W, np.float32)
    u = np.empty(W, np.float32)
    uq = np.empty(W, np.float32)
    raw = np.empty((L, W), np.float64)
    d_q = np.empty(Q, np.int64)
    s_tmp = np.empty(L, np.float64)
    use_box = box.shape[1] > 0
    acc = np.zeros((Q, L, W), np.float64)
    hv_buf = np.empty(W, np.float32)
    # column sums of one image row over a depth band, shared by consecutive candidates
    n_cb = c.shape[1] if not use_box else 0
    colbuf = np.empty((Q, n_cb, L, min(T, W + ORDER_BAND)), np.float64)
    valid = np.zeros((n_cb, 3), np.int64)
    state = np.array([0, -1, 0], np.int64)
    rr = np.empty(scales[Q - 1] // 2 * 2 + 1, np.int64)
    for ii in range(i_begin, i_end):
        _prefetch_next(c, y, rows, cols, peak_bin, order, ii + 1, i_end, scales, r0, e0, ce0, W,
                       T, n_rows_img, n_cols_img)  # fmt: skip
        s, so = order[ii], ii  # inputs at s, outputs at so
        irow = rows[s] + r0
        jcol = cols[s]
        jc = jcol - ce0  # column in c and y
        jo = jcol - c0  # column in sp and box
        centre = peak_bin[s]
        if refine and stop[s] - start[s] > W:
            centre = _window_centre(
                c, sp, dev, gsq, rows[s], irow, jc, jo, e0, start[s], stop[s], centre, refine_z, wh
            )
        off = min(max(centre - wh, 0), max(T - W, 0))
        lo = max(start[s], off)
        hi = min(stop[s], off + W)
        for w in range(W):
            inside[w] = (off + w >= lo) and (off + w < hi)
        _window_background(bh, sp, dev, rows[s], jo, off)
        if not use_box:
            band0 = (peak_bin[s] // ORDER_BAND) * ORDER_BAND - wh
            _box_sums(acc, colbuf, valid, state, rr, c, scales, irow, jcol, e0, ce0, band0, off,
                      n_rows_img, n_cols_img)  # fmt: skip
        _clean_responses(
            so, c, box, bidx, scales, acc, use_box, irow, rows[s], jc, jo, e0, off, inside, bh,
            resp, hv_buf, per_scale, o_hist, o_signal,
        )  # fmt: skip
        qbar = _select_scale(per_scale, tot, d_q)
        for w in range(W):
            u[w] = 0.0
            for l in range(L):
                u[w] += resp[qbar, l, w]
        w0 = d_q[qbar]
        ici_done = False
        if refine:
            ici_done, d_star = _ici_depth(
                resp, bh, per_scale, d_q, uq, scales, gsq, fisher, refine_z, ici_gamma
            )
        if ici_done:
            depth = off + d_star
        else:
            depth = off + w0 + _parabola(u, w0, W)
        o_depth[so] = depth
        o_lo[so] = lo
        o_hi[so] = hi
        o_qbar[so] = qbar
        o_offset[so] = off
        _own_pixel(
            so, y, irow - e0, jc, off, inside, bh, raw, o_own_counts, o_own_background,
            o_counts, o_background,
        )  # fmt: skip
        dw = depth - off
        for l in range(L):
            s_tmp[l] = o_signal[so, qloc, l]
        o_llr[so] = _llr_one(raw, bh, inside, dw, s_tmp, irf, irf_peak, L, W)
        if want_llr_sel:
            for l in range(L):
                s_tmp[l] = o_signal[so, qbar, l]
            o_llr_sel[so] = _llr_one(raw, bh, inside, dw, s_tmp, irf, irf_peak, L, W)
        o_zloc[so], o_zpred[so] = _local_z(
            resp[qloc], bh, gsq, o_signal[so, qbar], scales[qloc], dw
        )


@njit(cache=True, nogil=True)
def _interp_table(x, xs, ys):
    """``np.interp(x, xs, ys)`` (constant beyond the ends) for one sample."""
    n = xs.size
    if n == 1 or x <= xs[0]:
        return ys[0]
    if x >= xs[n - 1]:
        return ys[n - 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= x:
            lo = mid
        else:
            hi = mid
    slope = (ys[lo + 1] - ys[lo]) / (xs[lo + 1] - xs[lo])
    return slope * (x - xs[lo]) + ys[lo]


@njit(cache=True, nogil=True)
def _table_slopes(xs, ys):
    """Slope of each interval of the threshold table, as :func:`_interp_table` computes
    it (the same float64 value, computed once instead of once per voxel)."""
    G = xs.size
    slope = np.zeros(max(G - 1, 1), np.float64)
    for k in range(G - 1):
        slope[k] = (ys[k + 1] - ys[k]) / (xs[k + 1] - xs[k])
    return slope


@njit(cache=True, nogil=True)
def _table_ceil32(xs):
    """The smallest float32 at or above each table point: for a float32 level ``v``,
    ``xs[k] <= float64(v)`` exactly when ``ceil32[k] <= v``, so the table interval of a
    level is counted in float32 (8 lanes, not 4) with the same result."""
    out = np.empty(xs.size, np.float32)
    for k in range(xs.size):
        f = np.float32(xs[k])
        if np.float64(f) < xs[k]:
            f = np.nextafter(f, np.float32(np.inf))
        out[k] = f
    return out


@njit(cache=True, nogil=True, inline="always")
def _thresholds(lv, xs, ys, slope, xc, idx, th):
    """``th[t] = float32(interp(lv[t], xs, ys))`` for one pixel (T,), as
    :func:`_interp_table` gives it bit for bit, in loops over t that vectorise.

    The interval of ``x`` strictly inside the table is the number of inner table
    points ``xs[1:G-1]`` at or below it (the ``lo`` with ``xs[lo] <= x < xs[lo + 1]``
    of the bisection, ``xs`` ascending), counted in float32 against ``xc =
    _table_ceil32(xs)`` into ``idx`` (T,) int32 (the same count, twice the lanes of
    float64 and int64: the threshold pass 17 % faster); the value is the bisection's
    formula on it, and the ends are the table's end values.
    """
    T = lv.size
    G = xs.size
    y0 = ys[0]
    if G == 1:
        for t in range(T):
            th[t] = np.float32(y0)
        return
    x0 = xs[0]
    xe = xs[G - 1]
    ye = ys[G - 1]
    for t in range(T):
        idx[t] = 0
    for k in range(1, G - 1):
        xk = xc[k]
        for t in range(T):
            idx[t] += xk <= lv[t]
    for t in range(T):
        x = np.float64(lv[t])
        lo = idx[t]
        v = slope[lo] * (x - xs[lo]) + ys[lo]
        v = y0 if x <= x0 else v
        v = ye if x >= xe else v
        th[t] = np.float32(v)


@njit(cache=True, nogil=True)
def _pixel_level(spx, dev, lv):
    """``sum_l bhat`` (``eq:background_3``) of one pixel into ``lv`` (T,) float32,
    wavelengths in order, each ``bhat`` clipped at 0: the saliency kernel's
    accumulation, bit for bit."""
    T = lv.size
    for l in range(spx.size):
        s = spx[l]
        dl = dev[l]
        if l == 0:
            for t in range(T):
                bh = s + dl[t]
                lv[t] = bh if not bh < 0 else np.float32(0.0)
        else:
            for t in range(T):
                bh = s + dl[t]
                lv[t] += bh if not bh < 0 else np.float32(0.0)


@njit(cache=True, nogil=True)
def threshold_pass(sal, d, sp, dev, xs, ys, y, y_row0, y_col0, thr_out, store_thr, mask, cand, ev):
    """Threshold, binary map, candidate voxels and evidence of a block, in one pass.

    Parameters
    ----------
    sal, d : (r, C, T) float32
        Saliency (``eq:4.s1``) and signed response of the block.
    sp : (r, C, L) float32
        Background level ``b_{n,l}`` of its pixels (``eq:background_2``).
    dev : (L, T) float32
        ``bbar_t - mean_t bbar``: the background level ``sum_l bhat`` of a voxel is
        :func:`_pixel_level` (the saliency kernel's sum, in the same order: same bits).
    xs, ys : (G,) float64
        Threshold table: ``threshold = interp(level, xs, ys)`` (``G = 1``: constant).
    y : (er, ec, L, T) integer
        Raw counts of the block with its halo; output pixel ``(i, j)`` is
        ``y[y_row0 + i, y_col0 + j]``.
    thr_out : (r, C, T) float32
        Threshold per voxel, written when ``store_thr``.
    mask, cand : (r, C, T) bool
        Written: ``M = S > threshold``; ``M & (d > 0)`` (a surface is a positive
        excursion of the response).
    ev : (r, C, T) float32
        Written: evidence ``max(S / threshold - 1, 0)``.

    Returns
    -------
    n_photons, n_photons_kept : int
        Photons of the block and photons in voxels of ``M`` (summed over wavelengths).
    """
    r, C, T = sal.shape
    L = y.shape[2]
    n_ph = 0
    n_kept = 0
    lv = np.empty(T, np.float32)
    th = np.empty(T, np.float32)
    idx = np.empty(T, np.int32)
    slope = _table_slopes(xs, ys)
    xc = _table_ceil32(xs)
    for i in range(r):
        for j in range(C):
            _pixel_level(sp[i, j], dev, lv)
            # the pixel's thresholds first, then the voxels in loops that vectorise
            # (a table walk per voxel inside the loop kept it scalar: 36 % slower)
            _thresholds(lv, xs, ys, slope, xc, idx, th)
            if store_thr:
                thr_out[i, j] = th
            sr = sal[i, j]
            dr = d[i, j]
            mr = mask[i, j]
            cr = cand[i, j]
            er = ev[i, j]
            for t in range(T):
                s = sr[t]
                h = th[t]
                m = s > h
                mr[t] = m
                cr[t] = m and dr[t] > 0
                e = s / max(h, np.float32(1e-12)) - np.float32(1.0)
                er[t] = e if e > 0 else np.float32(0.0)
            for l in range(L):
                yr = y[y_row0 + i, y_col0 + j, l]
                for t in range(T):  # integer sums, branch-free (vectorised)
                    v = np.int64(yr[t])
                    n_ph += v
                    n_kept += v * np.int64(mr[t])
    return n_ph, n_kept


@njit(cache=True, nogil=True)
def _before(score, a, b):
    """Candidate ``b`` ranks before ``a``: larger score, ties in index order."""
    return score[b] > score[a] or (score[b] == score[a] and b < a)


@njit(cache=True, nogil=True)
def rank_in_pixel_sorted(row, col, score, keep, rank):
    """Rank (0 = largest ``score``, ties in index order) of each kept candidate among its
    pixel's kept ones; -1 for the others.

    The candidates must come in raster order of ``(row, col)`` (as the blocks emit
    them): a pixel's candidates are then consecutive and ranked in one pass (the same
    ranks as a stable ``lexsort((-score, col, row))``).
    """
    n = row.size
    i = 0
    while i < n:
        j = i + 1
        while j < n and row[j] == row[i] and col[j] == col[i]:
            j += 1
        for a in range(i, j):
            if not keep[a]:
                rank[a] = -1
                continue
            r = 0
            for b in range(i, j):
                if b != a and keep[b] and _before(score, a, b):
                    r += 1
            rank[a] = r
        i = j


@njit(cache=True, nogil=True)
def select_sorted(row, col, mass, depth, keep, k_max, out_idx, out_slot):
    """At most ``k_max`` kept candidates per pixel (largest ``mass``), in depth order.

    Candidates in raster order of ``(row, col)``. Writes the chosen indices, by pixel
    and then increasing depth (equal depths in the mass order), to ``out_idx`` and
    their rank in depth to ``out_slot``; returns how many. The same choice and order as
    the stable lexsorts of :func:`splidar.detection._6_select._select`.
    """
    n = row.size
    m = 0
    i = 0
    buf = np.empty(64, np.int64)
    mrank = np.empty(64, np.int64)
    while i < n:
        j = i + 1
        while j < n and row[j] == row[i] and col[j] == col[i]:
            j += 1
        if j - i > buf.size:
            buf = np.empty(2 * (j - i), np.int64)
            mrank = np.empty(2 * (j - i), np.int64)
        # the kept ones with a mass rank below k_max
        nb = 0
        for a in range(i, j):
            if not keep[a]:
                continue
            r = 0
            for b in range(i, j):
                if b != a and keep[b] and _before(mass, a, b):
                    r += 1
            if r < k_max:
                buf[nb] = a
                mrank[nb] = r
                nb += 1
        # insertion sort by (depth, mass rank)
        for u in range(1, nb):
            a = buf[u]
            ra = mrank[u]
            v = u - 1
            while v >= 0 and (
                depth[buf[v]] > depth[a] or (depth[buf[v]] == depth[a] and mrank[v] > ra)
            ):
                buf[v + 1] = buf[v]
                mrank[v + 1] = mrank[v]
                v -= 1
            buf[v + 1] = a
            mrank[v + 1] = ra
        for u in range(nb):
            out_idx[m] = buf[u]
            out_slot[m] = u
            m += 1
        i = j
    return m
