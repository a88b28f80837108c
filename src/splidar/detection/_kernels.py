"""Numba kernels of the surface extraction (runs of the binary map, multiscale gathers)."""

from __future__ import annotations

import numpy as np
from numba import njit

from ._fast import _refl as _reflect  # one reflect rule for every kernel

__all__ = ["find_segments", "gather_scales"]


@njit(cache=True, nogil=True)
def _segments_of_run(d, s, e, a, b, min_sep, rho, seg_start, seg_stop, seg_peak, seg_mass, seg_ev):
    """Split the run ``[a, b)`` at deep minima between separated peaks of ``d``.

    Returns the number of segments written into the ``seg_*`` scratch arrays.
    """
    n = b - a
    cand = np.empty(n, np.int64)
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
    vals = np.empty(nc)
    for i in range(nc):
        vals[i] = -d[cand[i]]
    order = np.argsort(vals)
    acc = np.empty(nc, np.int64)
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


@njit(cache=True, nogil=True)
def find_segments(mask, d, s, e, min_sep, rho):
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
        Two peaks are two surfaces only if ``d`` dips below ``rho`` times the smaller
        peak between them.

    Returns
    -------
    row, col, start, stop, peak : int64 arrays; mass, evidence : float64 arrays
    """
    R, C, T = mask.shape
    nmax = 0
    for i in range(R):
        for j in range(C):
            for t in range(T):
                if mask[i, j, t] and (t == 0 or not mask[i, j, t - 1]):
                    nmax += 1
    # each run gives at most ceil(len / min_sep) + 1 segments; bound generously
    total = 0
    for i in range(R):
        for j in range(C):
            for t in range(T):
                if mask[i, j, t]:
                    total += 1
    cap = min(total, nmax * (T // max(min_sep, 1) + 1)) + 1
    o_row = np.empty(cap, np.int64)
    o_col = np.empty(cap, np.int64)
    o_start = np.empty(cap, np.int64)
    o_stop = np.empty(cap, np.int64)
    o_peak = np.empty(cap, np.int64)
    o_mass = np.empty(cap, np.float64)
    o_ev = np.empty(cap, np.float64)
    seg_start = np.empty(T, np.int64)
    seg_stop = np.empty(T, np.int64)
    seg_peak = np.empty(T, np.int64)
    seg_mass = np.empty(T, np.float64)
    seg_ev = np.empty(T, np.float64)
    k = 0
    for i in range(R):
        for j in range(C):
            t = 0
            while t < T:
                if not mask[i, j, t]:
                    t += 1
                    continue
                a = t
                while t < T and mask[i, j, t]:
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
                )
                for u in range(ns):
                    o_row[k] = i
                    o_col[k] = j
                    o_start[k] = seg_start[u]
                    o_stop[k] = seg_stop[u]
                    o_peak[k] = seg_peak[u]
                    o_mass[k] = seg_mass[u]
                    o_ev[k] = seg_ev[u]
                    k += 1
    return o_row[:k], o_col[:k], o_start[:k], o_stop[:k], o_peak[:k], o_mass[:k], o_ev[:k]


@njit(cache=True, nogil=True)
def gather_scales(c, row, col, offset, width, scales, n_rows_img, row0, n_cols_img):
    """Box means of ``c`` at every scale over each surface's time window.

    Parameters
    ----------
    c : (er, C, L, T) float32
        Correlated counts of a block of rows starting at image row ``row0`` (with a
        halo of ``max(scales) // 2`` rows wherever the image continues).
    row, col : (S,) int64
        Image pixel of each surface.
    offset : (S,) int64
        First bin of each window; the window is ``[offset, offset + width)``.
    scales : (Q,) int64
        Box sizes.

    Returns
    -------
    out : (S, Q, L, width) float32
        ``mean_{k x k}(c)`` with ``mode="reflect"`` borders, as the full-image filter.
    """
    S = row.size
    Q = scales.size
    L = c.shape[2]
    out = np.zeros((S, Q, L, width), np.float32)
    acc = np.zeros((L, width), np.float64)
    for s in range(S):
        for q in range(Q):
            k = scales[q]
            h = k // 2
            acc[:] = 0.0
            for di in range(-h, h + 1):
                ri = _reflect(row[s] + di, n_rows_img) - row0
                for dj in range(-h, h + 1):
                    cj = _reflect(col[s] + dj, n_cols_img)
                    for l in range(L):
                        for w in range(width):
                            acc[l, w] += c[ri, cj, l, offset[s] + w]
            inv = 1.0 / (k * k)
            for l in range(L):
                for w in range(width):
                    out[s, q, l, w] = acc[l, w] * inv
    return out
