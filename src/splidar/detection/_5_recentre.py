"""Stage 5, first clean-up: move a candidate to the depth its 4-neighbours agree on
inside its own run of the map.

A run of the map ``M`` spans several bins (the coarse boxes widen it); the candidate's
depth is the refined peak of its own response (the own pixel's when significant), which
a few photons can put at the run's edge, a FWHM or more from where the neighbours' runs
peak. At that depth the candidate then fails the presence test (the local scale does
not respond there), or no neighbour shares it and the isolated test (5b) removes it, or
it stays as a wrong depth: the pixel loses its surface although its own run holds the
neighbours' depth. Measured on issue #15's cells (single surface, PPP 4, SBR 0.25,
seeds 0-2): 62 (uniform) and 53 (decaying) of the 240 / 215 missed true surfaces per
cube were such runs (benchmarks/README.md, "depth22, session 15").

The rule (:func:`recentre_runs`), on the map's table before any other pass: at least
:data:`MIN_AGREE` of the 4-neighbours hold a kept candidate inside the candidate's
support ``[start, stop)``, within the FWHM of one another; their mean depth ``a`` lies
more than the FWHM from the candidate's depth ``d``; the pixel holds no other kept
candidate near ``a``. The own raw counts' Poisson log-likelihood of a return as bright
as those neighbours' (``L(x)``, the spill-over pass's statistic) decides:

* a kept candidate moves to ``a`` when its own counts do not favour ``d``
  (``L(d) <= L(a)``: two depths of one run are equally likely a priori), or when ``d``
  would be lost anyway (no 8-neighbour shares it and its own counts are not significant
  alone: the isolated test of 5b);
* a candidate the presence test rejected is moved and restored (a pixel with room only).

Either way the own counts must not reject the return at ``a`` (``L(a) >= -PRESENCE_LLR``,
the presence test's own-count veto). The candidate keeps its support, window, clean
histograms, signal, saliency mass and evidence (sums over the support: ``a`` lies
inside the support, so inside the window); its ``depth_bin`` changes and its presence
statistics (``presence_llr``, ``presence_z``) are recomputed there
(:func:`moved_presence`). No threshold is fitted to a scene: the FWHM, the
support of the map's run and the presence test's constants decide.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from numba import njit

from ._4_map import _local_scale
from ._6_select import _gather
from ._kernels import _llr_one, _local_z
from ._quality import _by_pixel, _own_llr, reject_isolated
from ._table import CandidateTable, PassResult, skipped, with_keep
from ._threads import on_parts

__all__ = ["MIN_AGREE", "moved_presence", "recentre_runs"]

#: 4-neighbours that must hold the agreed depth inside the candidate's run: 3 of 4 (a
#: plane on at least three sides; 2 would follow a line, a strand or an edge's spread).
MIN_AGREE = 3


@njit(cache=True, nogil=True, inline="always")
def _small_median(vals, srt, n):
    """``np.median(vals[:n])`` (finite values, ``n >= 1``) by insertion sort into ``srt``:
    no allocation per candidate (``np.median`` copies and partitions; 2-3x the
    kernel's time). The same value: the middle one, or ``(a + b) / 2`` of the middle
    two, as numba's ``np.median``."""
    for m in range(n):
        v = vals[m]
        k = m
        while k > 0 and srt[k - 1] > v:
            srt[k] = srt[k - 1]
            k -= 1
        srt[k] = v
    h = n >> 1
    if n & 1 == 0:
        return (srt[h - 1] + srt[h]) / 2
    return srt[h]


@njit(cache=True, nogil=True)
def _agree_kernel(
    row,
    col,
    depth,
    start,
    stop,
    keep,
    solo,
    sig,
    order,
    starts,
    R,
    C,
    fwhm,
    min_agree,
    near,
    alt,
    s_alt,
    items,
):
    """For each candidate ``items[t]`` (the others' entries left as they are): the mean
    depth ``alt`` of the 4-neighbours' kept candidates inside its support that agree
    (within ``fwhm`` of their median, one per neighbour) and their mean signal ``s_alt``
    (L,). NaN when fewer than ``min_agree`` agree, when
    ``alt`` lies within ``fwhm`` of another kept candidate of the pixel, and by ``near``:
    0, when it lies within ``fwhm`` of the own depth (the far moves); 2, when it does not,
    or the candidate is kept (the rejected candidates already at the agreed depth)."""
    L = sig.shape[1]
    vals = np.empty(16, np.float64)
    who = np.empty(16, np.int64)
    srt = np.empty(16, np.float64)
    best = np.empty(4, np.int64)
    for t in range(items.size):
        i = items[t]
        alt[i] = np.nan
        r = row[i]
        c = col[i]
        n = 0
        for dd in range(4):
            rr = r + (-1, 1, 0, 0)[dd]
            cc = c + (0, 0, -1, 1)[dd]
            if rr < 0 or rr >= R or cc < 0 or cc >= C:
                continue
            q = rr * C + cc
            for k in range(starts[q], starts[q + 1]):
                j = order[k]
                if keep[j] and solo[j] and start[i] <= depth[j] < stop[i] and n < 16:
                    vals[n] = depth[j]
                    who[n] = j
                    n += 1
        if n < min_agree:
            continue
        med = _small_median(vals, srt, n)
        # one value per neighbour: the one nearest the median
        best[:] = -1
        for m in range(n):
            j = who[m]
            if abs(vals[m] - med) > fwhm:
                continue
            dd = 0 if row[j] < r else (1 if row[j] > r else (2 if col[j] < c else 3))
            if best[dd] < 0 or abs(vals[m] - med) < abs(depth[best[dd]] - med):
                best[dd] = j
        cnt = 0
        a = 0.0
        for dd in range(4):
            if best[dd] >= 0:
                cnt += 1
                a += depth[best[dd]]
        if cnt < min_agree:
            continue
        a /= cnt
        close = abs(a - depth[i]) <= fwhm
        if close and (keep[i] or near == 0):
            continue
        if not close and near == 2:
            continue
        p = r * C + c
        taken = False
        for k in range(starts[p], starts[p + 1]):
            j = order[k]
            if j != i and keep[j] and abs(depth[j] - a) <= fwhm:
                taken = True
        if taken:
            continue
        alt[i] = a
        for l in range(L):
            s = 0.0
            for dd in range(4):
                if best[dd] >= 0:
                    s += sig[best[dd], l]
            s_alt[i, l] = s / cnt


#: Fewest candidates per thread of :func:`_agree_kernel`.
_AGREE_PART = 4096


def _agreed(
    table: CandidateTable, keep: np.ndarray, fwhm: float, near: int, items=None, n_jobs: int = 1
):
    """The neighbours' agreed depth and signal of each candidate (:func:`_agree_kernel`),
    or of the candidates ``items`` (sorted indices) only (the others' ``alt``: NaN).
    ``items`` in ``n_jobs`` contiguous parts on as many threads (each candidate's values
    are its own: the same on any number)."""
    cols = table.columns
    R, C = table.image_shape
    row = np.asarray(cols["row"], np.int64)
    col = np.asarray(cols["col"], np.int64)
    d = np.asarray(cols["depth_bin"], np.float64)
    sel = np.asarray(cols["signal"])[np.arange(d.size), np.asarray(cols["scale_index"], np.int64)]
    order, starts = _by_pixel(row, col, (R, C))
    alt = np.full(d.size, np.nan)
    s_alt = np.zeros((d.size, sel.shape[1]), np.float64)
    items = np.arange(d.size) if items is None else np.asarray(items, np.int64)
    if near == 2:  # the restoration: neighbours holding that surface alone
        pix = row * C + col
        n_kept = np.bincount(pix[keep], minlength=R * C)
        solo = keep & (n_kept[pix] == 1)
    else:
        solo = keep
    args = (
        row, col, d, np.asarray(cols["start"], np.int64), np.asarray(cols["stop"], np.int64),
        keep, solo, np.ascontiguousarray(sel, np.float64), order, starts, int(R), int(C),
        float(fwhm), int(MIN_AGREE), int(near), alt, s_alt,
    )  # fmt: skip
    work = min(int(n_jobs), items.size // _AGREE_PART)
    on_parts(lambda i0, i1: _agree_kernel(*args, items[i0:i1]), items.size, work)
    return alt, s_alt


def _own_llrs(table: CandidateTable, ii, depths, s, irf, peak) -> np.ndarray:
    """The own counts' log-likelihood ratio of a return ``s`` at each of ``depths``."""
    cols = table.columns
    off = np.asarray(cols["offset"], np.float64)[ii]
    cnt = np.asarray(cols["own_counts"])[ii]
    bkg = np.asarray(cols["own_background"][ii])  # those rows only (OwnBackground)
    return _own_llr(cnt, bkg, irf, peak, depths - off, s)


def _restore(table, keep, ii, l_a, llr_level, secondary_llr, max_kept, restore) -> np.ndarray:
    """Which of the candidates ``ii`` (``restore``: rejected ones to restore, if they
    pass) are kept: a pixel with room, the own counts not rejecting the return at the
    agreed depth (``l_a >= -llr_level``; ``>= secondary_llr`` beside a kept candidate,
    the presence test's rule for a pixel's further candidates)."""
    R, C = table.image_shape
    pix = np.asarray(table.columns["row"], np.int64) * C + np.asarray(table.columns["col"])
    room = np.bincount(pix[keep], minlength=R * C)
    ok = np.zeros(ii.size, bool)
    for k in np.flatnonzero(restore):
        p = pix[ii[k]]
        need = -llr_level if room[p] == 0 else secondary_llr
        if room[p] < max_kept and l_a[k] >= need:
            room[p] += 1
            ok[k] = True
    return ok


def recentre_runs(
    table: CandidateTable,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    pfa: float,
    n_bins: int,
    llr_level: float,
    secondary_llr: float,
    max_kept: int,
    histograms=None,
    scales=None,
    n_jobs: int = 1,
) -> PassResult:
    """Move candidates to the depth their 4-neighbours agree on inside their run (module).

    Parameters
    ----------
    table : CandidateTable
        The map's table (with the presence-rejected candidates of pixels with room and
        the ``own_counts`` / ``own_background`` windows).
    irf : ndarray (L, n_irf), float64
    peak : ndarray (L,)
        The IRF's peak bin per wavelength.
    fwhm : float
        The IRF's FWHM (bins).
    pfa : float
        ``surface_pfa``: the isolated test's level (a depth lost anyway).
    n_bins : int
        T.
    llr_level : float
        The own counts must not reject the return at the new depth beyond this
        (``PRESENCE_LLR``).
    secondary_llr : float
        A rejected candidate of a pixel holding a kept one is restored only when its own
        counts give at least this (``PRESENCE_SECONDARY``).
    max_kept : int
        ``K_s``: a rejected candidate is restored only in a pixel with room.
    histograms : tuple of ndarray, optional
        The map's per-block histogram arrays (``CandidateMap.histograms``); with
        ``scales`` (the box sizes), a moved candidate's ``presence_llr`` and
        ``presence_z`` are recomputed at its new depth (:func:`moved_presence`).
    scales : ndarray (Q,) int, optional
    n_jobs : int
        Threads of the neighbours' agreed depths (:func:`_agreed`; the result does not
        depend on it).

    Returns
    -------
    PassResult
        ``added``: rejected candidates restored at the new depth; ``moved``: candidates
        whose depth changed (restored ones included; the table's ``moved_by`` names
        this pass for them).
    """
    if not table.keep.size or "own_counts" not in table.columns:
        return skipped("recentre", table)
    t0 = time.perf_counter()
    keep = np.asarray(table.keep, bool)
    d = np.asarray(table.columns["depth_bin"], np.float64)
    alt, s_alt = _agreed(table, keep, fwhm, near=0, n_jobs=n_jobs)
    ii = np.flatnonzero(np.isfinite(alt))
    if ii.size == 0:
        return with_keep("recentre", table, keep, t0)
    l_d = _own_llrs(table, ii, d[ii], s_alt[ii], irf, peak)
    l_a = _own_llrs(table, ii, alt[ii], s_alt[ii], irf, peak)
    lost = reject_isolated(table.view(), keep, fwhm=fwhm, pfa=pfa, n_bins=n_bins)[ii]
    move = keep[ii] & ((l_d <= l_a) | lost) & (l_a >= -llr_level)
    move |= _restore(table, keep, ii, l_a, llr_level, secondary_llr, max_kept, ~keep[ii])
    moved = ii[move]
    new_keep = keep.copy()
    new_keep[moved] = True
    new_d = d.copy()
    new_d[moved] = alt[moved]
    depth = np.asarray(table.columns["depth_bin"])
    new = {"depth_bin": new_d.astype(depth.dtype)}
    if histograms is not None and scales is not None and moved.size:
        new.update(moved_presence(table, moved, new_d[moved], histograms, scales, irf, peak))
    res = with_keep("recentre", table.with_columns(**new), new_keep, t0)
    return replace(res, table=res.table.with_moved(moved, "recentre"), moved=int(moved.size))


def moved_presence(table, ii, depths, histograms, scales, irf, peak) -> dict:
    """The ``presence_llr`` and ``presence_z`` columns with candidates ``ii`` moved to
    ``depths`` inside their supports (their windows, supports, histograms and signal
    unchanged), as the map computes them (``extract_surfaces``): the own counts'
    log-likelihood ratio of a return with the local scale's signal over the support
    (``_llr_one``) and the local scale's z at the depth (``_local_z``). The local
    scale's response is read from the candidate's clean histogram (``histograms``: the
    map's per-block arrays): it equals the map's where positive; a response that is
    not positive there gives ``z = 0`` (the clean histogram keeps positive parts)."""
    cols = table.columns
    scales = np.asarray(scales, np.int64)
    q = _local_scale(scales)
    irf = np.ascontiguousarray(np.atleast_2d(np.asarray(irf, np.float64)))
    pk = np.asarray(peak, np.float64)
    gsq = (irf**2).sum(axis=1)
    L = irf.shape[0]
    hist = _gather(table, np.asarray(ii, np.int64), histograms)  # (n, Q, L, W)
    W = hist.shape[-1]
    llr = np.array(cols["presence_llr"], np.float64)
    z = np.array(cols["presence_z"], np.float64)
    off = np.asarray(cols["offset"], np.int64)[ii]
    lo = np.asarray(cols["start"], np.int64)[ii]
    hi = np.asarray(cols["stop"], np.int64)[ii]
    qbar = np.asarray(cols["scale_index"], np.int64)[ii]
    sig = np.asarray(cols["signal"], np.float64)[ii]
    cnt = np.asarray(cols["own_counts"])[ii]
    bkg = np.asarray(cols["own_background"][ii], np.float32)
    for m, i in enumerate(ii):
        w = off[m] + np.arange(W)
        inside = (w >= lo[m]) & (w < hi[m])
        dw = float(depths[m]) - off[m]
        raw = cnt[m].astype(np.float64)
        llr[i] = _llr_one(raw, bkg[m], inside, dw, np.ascontiguousarray(sig[m, q]), irf, pk, L, W)
        z[i] = _local_z(
            np.ascontiguousarray(hist[m, q]), bkg[m], gsq, np.ascontiguousarray(sig[m, qbar[m]]),
            int(scales[q]), dw,
        )[0]  # fmt: skip
    return {"presence_llr": llr, "presence_z": z}


def restore_agreed(
    table: CandidateTable,
    keep: np.ndarray,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    llr_level: float,
    max_kept: int,
    items=None,
    n_jobs: int = 1,
) -> np.ndarray:
    """Rejected candidates of pixels with no kept surface, at the depth :data:`MIN_AGREE`
    of their 4-neighbours agree on (within the FWHM, inside the candidate's run; each
    neighbour holding that surface alone), whose own counts do not reject the return
    there (log-ratio >= ``-llr_level``, the presence test's veto): (n,) bool, True for
    those to restore (stage 5c, after the pooled dark-region test; ``keep`` the
    candidates kept so far). The pooled neighbours stand for the local scale's response
    the presence test asked for. The candidate keeps its own depth.

    Not beside a kept surface, and not from neighbours holding two: on the net (strands
    in front of an object) the strands' spread into the open pixels agrees with itself
    (``benchmarks/README.md``, "depth22, session 15").

    ``items`` (sorted candidate indices, whole pixels): only those are tested (the others
    False); a candidate's outcome depends on ``keep`` in its pixel and its 4-neighbours
    only, so a repeat after a round need only test those pixels' candidates
    (:func:`agreed_items`). ``n_jobs``: threads of :func:`_agreed` (the same result on
    any number).
    """
    out = np.zeros(keep.size, bool)
    if not keep.size or "own_counts" not in table.columns:
        return out
    d = np.asarray(table.columns["depth_bin"], np.float64)
    alt, s_alt = _agreed(table, np.asarray(keep, bool), fwhm, near=2, items=items, n_jobs=n_jobs)
    ii = np.flatnonzero(np.isfinite(alt))
    if ii.size:
        l_a = _own_llrs(table, ii, d[ii], s_alt[ii], irf, peak)
        # a pixel with no kept surface only (a further surface's level: infinite)
        ok = _restore(table, keep, ii, l_a, llr_level, np.inf, max_kept, ~keep[ii])
        out[ii[ok]] = True
    return out


def agreed_items(table: CandidateTable, changed: np.ndarray) -> np.ndarray:
    """The candidates (sorted indices) in the pixels of the candidates ``changed`` (n,)
    bool and in those pixels' 4-neighbours: the ones whose :func:`restore_agreed`
    outcome a change of ``keep`` at ``changed`` can alter (its ``items`` for the next
    round)."""
    R, C = table.image_shape
    row = np.asarray(table.columns["row"], np.int64)
    col = np.asarray(table.columns["col"], np.int64)
    near = np.zeros((R + 2, C + 2), bool)
    r, c = row[changed] + 1, col[changed] + 1
    for dr, dc in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
        near[r + dr, c + dc] = True
    return np.flatnonzero(near[row + 1, col + 1])
