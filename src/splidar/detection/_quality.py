"""Global quality passes over the candidate surfaces of :func:`splidar.detection.detect`.

These passes run once on the table of candidates of the whole image, after every block
of rows has been processed (they need the neighbours across block borders) and before
the ``K_s`` per pixel are selected. They only read the candidate table (the ``surf``
dict of ``_detect._extract``), so they do not depend on how the candidates were found.

Spill-over rejection (issue #3)
-------------------------------
The coarse scales of ``eq:4.s1`` spread a return into the neighbouring pixels: beside a
thin foreground (a net) and across depth edges they plant candidates at a neighbour's
depth where the pixel itself holds nothing. Such a candidate

1. has a *source*: a candidate in one of its 8 neighbours at the same depth (within the
   IRF's FWHM);
2. is not *enclosed* by that surface: no pair of opposite 4-neighbours (north/south or
   west/east) holds candidates whose mean depth is within the FWHM of its depth. A
   continuous surface (flat or sloped) passes through a pixel it surrounds, so a pixel
   inside a surface keeps the benefit of the spatial pooling; a pixel beside a strand or
   on the far side of a depth edge has same-depth neighbours on one side only. The
   spread beside an edge forms a strip over the pixels' own surfaces, and each member
   of the strip is enclosed along it by the others: a *further* candidate (its pixel
   holds another that the own counts support) is enclosed only by a pair with a member
   that is not itself a further candidate whose counts reject its return;
3. is not supported by its own counts: the own-pixel Poisson log-likelihood ratio of a
   return as bright as the source (its own-pixel signal) against background only,
   ``sum_t y_t log(1 + s g(t - d) / b_t) - s sum_t g(t - d)`` (the test of ``_own_llr``
   with the source's intensity), is below ``llr_level``.

Only candidates meeting all three are rejected; the test is repeated until nothing
changes (a rejected candidate is no longer a source nor part of an enclosing pair, so the
spread two or more pixels away from the source is tested next). The intensity of the
source rather than the local box average is what a real surface continuing into the
pixel would bring: a pixel with no photons at that depth then gives a log-ratio of about
``-s``, far below zero, while the box average (diluted by the pixel's empty neighbours)
cannot reject it. At very low counts (about 1 photon per pixel) the test has little
power either way: it then trades some true surfaces at edges for more false ones.

Isolated candidates
-------------------
A candidate no neighbour shares at its depth has no support from the pooling and must be
significant on its own counts (:func:`reject_isolated`).

Dark regions
------------
A dim patch beside bright pixels at the same depth fails the presence test and looks like
their spread. After the two passes above, the rejected candidates of pixels left empty are
pooled with the dim candidates around them at the same depth; a pool whose own counts
together show a return restores them (:func:`rescue_dark`).

Enclosed pixels
---------------
A pixel inside a bright surface whose own counts hold no photon at its depth (a return
of ``s`` photons leaves none with probability ``exp(-s)``) fails the own-pixel check.
When both opposite pairs of its 4-neighbours hold kept surfaces through its depth and
its local scale is significant, its candidate is restored (:func:`restore_enclosed`):
the spread beside a thin structure or across a depth edge has same-depth neighbours on
one side only. In a pixel that already holds a surface the own counts must favour the
candidate too (a one-pixel hole of a net is enclosed by the strands).

Depth alignment
---------------
On a steep slope a low-count peak of the 3 x 3 box can fall on a neighbouring row's
return; :func:`align_depths` re-decides a depth that the 4-neighbours place more than
half the FWHM away with the 3 x 3 box sheared along their plane (each neighbour's clean
histogram shifted by the plane's depth difference before pooling), unless the own
counts favour the current depth by more than their noise.
"""

from __future__ import annotations

import logging

import numpy as np
from numba import njit

from ._kernels import _interp_irf
from ._threads import on_parts

__all__ = [
    "reject_isolated",
    "reject_spill_over",
    "rescue_dark",
    "restore_enclosed",
    "spill_over_features",
]

logger = logging.getLogger(__name__)

#: opposite 4-neighbour pairs of the enclosure test (north/south, west/east)
_PAIRS = (((-1, 0), (1, 0)), ((0, -1), (0, 1)))
#: the 8 neighbours searched for a source
_NEIGHBOURS = tuple((dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc)


def _by_pixel(row, col, image_shape):
    """Candidates grouped by pixel: ``order`` sorts them by pixel (stable: a pixel's
    candidates keep their table order), ``starts`` (R * C + 1) delimits each pixel's run.

    A counting sort (:func:`_pixel_order`): the same arrays as ``np.argsort(pix,
    kind="stable")`` and ``np.searchsorted(pix[order], np.arange(R * C + 1))`` in one
    pass over the candidates and one over the pixels (5-10x faster on 290k candidates;
    the clean-up passes group the table this way eight times)."""
    R, C = image_shape
    pix = np.asarray(row, np.int64) * C + np.asarray(col, np.int64)
    starts = np.zeros(R * C + 1, np.int64)
    np.cumsum(np.bincount(pix, minlength=R * C), out=starts[1:])
    return _pixel_order(pix, starts), starts


@njit(cache=True, nogil=True)
def _pixel_order(pix, starts):
    """Candidate indices sorted by pixel ``pix``, stable (a counting sort; ``starts``: the
    cumulative counts per pixel, ``R * C + 1``)."""
    fill = starts[:-1].copy()
    order = np.empty(pix.size, np.int64)
    for i in range(pix.size):
        p = pix[i]
        order[fill[p]] = i
        fill[p] += 1
    return order


def _dense(row, col, image_shape, values, fill):
    """Candidates per pixel as a dense (R + 2, C + 2, K, ...) array with a 1-pixel pad.

    Returns the array and each candidate's slot ``k``.
    """
    R, C = image_shape
    pix = row * C + col
    order = np.argsort(pix, kind="stable")
    ps = pix[order]
    first = np.searchsorted(ps, ps, side="left")
    slot = np.empty(row.size, np.int64)
    slot[order] = np.arange(row.size) - first
    K = int(slot.max()) + 1 if row.size else 1
    out = np.full((R + 2, C + 2, K) + values.shape[1:], fill, dtype=values.dtype)
    out[row + 1, col + 1, slot] = values
    return out, slot


def _shifted_irf(irf, peak, depth_w, W):
    """``g_l(t - d)`` on the window ``t = 0..W-1`` with the peak on ``d``: (S, L, W)."""
    L, n = irf.shape
    t = np.arange(W, dtype=np.float64)
    out = np.empty((depth_w.size, L, W), np.float64)
    for l in range(L):
        x = t[None, :] - depth_w[:, None] + peak[l]
        out[:, l] = np.interp(x, np.arange(n), irf[l], left=0.0, right=0.0)
    return out


def _own_llr(counts, bkg, irf, peak, depth_w, s) -> np.ndarray:
    """Own-pixel Poisson log-likelihood ratio of returns against background only: (n,).

    ``sum_t y_t log(1 + s g(t - d) / b_t) - s sum_t g(t - d)`` summed over L, over each
    candidate's support (``bkg > 0``): ``counts`` (n, L, W) raw counts, ``bkg`` (n, L, W)
    float background, ``depth_w`` (n,) depths in window coordinates, ``s`` (n, L)
    signal photons.
    """
    W = counts.shape[-1]
    g = _shifted_irf(irf, peak, depth_w, W) * (bkg > 0)
    s = np.maximum(s, 1e-9)
    y = counts.astype(np.float64)
    llr = (y * np.log1p(s[:, :, None] * g / np.maximum(bkg, 1e-9))).sum(axis=(1, 2))
    return llr - (s * g.sum(axis=-1)).sum(axis=1)


def spill_over_features(
    surf: dict,
    keep: np.ndarray,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    llr_level: float = 0.0,
    vouch_level: float = -np.inf,
) -> dict:
    """Source, enclosure and source-intensity log-likelihood ratio of each candidate.

    Parameters
    ----------
    surf : dict
        Candidate table: ``row``, ``col`` (S,) int, ``depth_bin`` (S,) float (bins),
        ``offset`` (S,) int (first bin of the window), ``own_counts`` (S, L, W) int
        (the pixel's raw counts over the window, zero outside the support) and
        ``own_background`` (S, L, W) float (the background ``bhat`` there, zero outside
        the support), and ``image_shape`` (R, C).
    keep : (S,) bool
        Candidates that take part (sources and tested ones).
    irf : (L, n) float
        Normalised IRF.
    peak : (L,) int
        Sample of each IRF's peak (the depth reference).
    fwhm : float
        Depth tolerance (bins): the IRF's full width at half maximum.
    llr_level : float
        Own log-likelihood ratio at which a candidate is supported by its counts.
    vouch_level : float
        Own log-likelihood ratio (for its own source's return, ``+inf`` without a
        source) below which a further candidate does not enclose a further candidate
        of a neighbour (see :func:`reject_spill_over`; ``-inf``: any pair encloses).

    Returns
    -------
    dict
        ``has_source`` (S,) bool, ``enclosed`` (S,) bool, ``source_signal`` (S, L) float
        (the source's own-pixel signal, photons), ``llr_source`` (S,) float (``+inf``
        without a source) and ``own_signal`` (S, L) float.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar.irf import gaussian_irf
    >>> g = np.asarray(gaussian_irf(3.0), float)[None]
    >>> W = 9
    >>> cnt = np.zeros((2, 1, W), np.int32)
    >>> cnt[0, 0, 3:6] = [3, 6, 3]  # a bright pixel, an empty neighbour
    >>> surf = dict(row=np.array([0, 0]), col=np.array([0, 1]), depth_bin=np.array([4.0, 4.0]),
    ...             offset=np.array([0, 0]), own_counts=cnt,
    ...             own_background=np.full((2, 1, W), 0.05, np.float32), image_shape=(1, 2))
    >>> f = spill_over_features(surf, np.ones(2, bool), irf=g, peak=np.array([g.argmax()]),
    ...                         fwhm=3.0)
    >>> f["has_source"].tolist(), f["enclosed"].tolist(), bool(f["llr_source"][1] < -5)
    ([True, True], [False, False], True)
    """
    R, C = surf["image_shape"]
    idx = np.flatnonzero(keep)
    S = surf["row"].size
    L = irf.shape[0]
    has_source = np.zeros(S, bool)
    enclosed = np.zeros(S, bool)
    src_sig = np.zeros((S, L))
    llr = np.full(S, np.inf)
    counts = np.asarray(surf["own_counts"])
    bkg = np.asarray(surf["own_background"], np.float64)
    own = np.maximum(counts.sum(axis=-1, dtype=np.float64) - bkg.sum(axis=-1), 0.0)  # (S, L)
    out = dict(
        has_source=has_source,
        enclosed=enclosed,
        source_signal=src_sig,
        llr_source=llr,
        own_signal=own,
    )
    if idx.size == 0:
        return out
    row = np.asarray(surf["row"])[idx]
    col = np.asarray(surf["col"])[idx]
    d = np.asarray(surf["depth_bin"], np.float64)[idx]
    D, _ = _dense(row, col, (R, C), d, np.nan)  # (R+2, C+2, K)
    SIG, _ = _dense(row, col, (R, C), own[idx], 0.0)  # (R+2, C+2, K, L)
    r1, c1 = row + 1, col + 1
    # 1. source: the same-depth neighbour of largest own-pixel signal (summed over L)
    best = np.full(idx.size, -np.inf)
    sig = np.zeros((idx.size, L))
    for dr, dc in _NEIGHBOURS:
        dn = D[r1 + dr, c1 + dc]  # (n, K)
        sn = SIG[r1 + dr, c1 + dc]  # (n, K, L)
        tot = np.where(np.abs(dn - d[:, None]) <= fwhm, sn.sum(axis=-1), -np.inf)
        k = tot.argmax(axis=1)
        tk = tot[np.arange(idx.size), k]
        better = tk > best
        best = np.where(better, tk, best)
        sig[better] = sn[np.arange(idx.size), k][better]
    has = np.isfinite(best)
    # 3. own-pixel log-likelihood ratio of a return as bright as the source
    sub = idx[has]
    llr_s = _own_llr(
        counts[sub], bkg[sub], irf, peak, d[has] - np.asarray(surf["offset"])[sub], sig[has]
    )
    # 2. enclosure: an opposite pair of 4-neighbours interpolates to the candidate's
    # depth; a further candidate (beside another of its pixel that the own counts
    # support, log-ratio >= llr_level) needs one of the two to be no further candidate
    # or to reach vouch_level
    own_llr = np.full(idx.size, np.inf)
    own_llr[has] = llr_s
    sup = own_llr >= llr_level
    n_sup = np.zeros(R * C, np.int64)
    np.add.at(n_sup, row * C + col, sup)
    further = (n_sup[row * C + col] - sup) > 0
    V, _ = _dense(row, col, (R, C), ~further | (own_llr >= vouch_level), False)
    enc = np.zeros(idx.size, bool)
    for (ar, ac), (br, bc) in _PAIRS:
        a = D[r1 + ar, c1 + ac]  # (n, K)
        b = D[r1 + br, c1 + bc]
        mid = 0.5 * (a[:, :, None] + b[:, None, :])
        ok = V[r1 + ar, c1 + ac][:, :, None] | V[r1 + br, c1 + bc][:, None, :]
        ok |= ~further[:, None, None]
        enc |= np.any((np.abs(mid - d[:, None, None]) <= fwhm) & ok, axis=(1, 2))
    has_source[idx] = has
    enclosed[idx] = enc
    src_sig[idx] = sig
    llr[sub] = llr_s
    return out


def reject_spill_over(
    surf: dict,
    keep: np.ndarray,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    llr_level: float,
    vouch_level: float = -np.inf,
    max_iter: int = 10,
    n_jobs: int = 1,
) -> np.ndarray:
    """Candidates that are a neighbour's return spread by the coarse scales.

    A kept candidate is rejected when it has a same-depth source among its 8
    neighbours, is not enclosed by that surface (no opposite 4-neighbour pair
    interpolating to its depth) and its own counts give a log-likelihood ratio below
    ``llr_level`` for a return as bright as the source (see the module docstring).
    A *further* candidate (its pixel holds another that the own counts support:
    log-ratio ``>= llr_level``) is enclosed only by a pair of which at least one
    candidate is no further candidate with an own log-likelihood ratio (for its own
    source's return; ``+inf`` without a source) below ``vouch_level``: a strip of
    spread along a depth edge or beside a strand lies over the pixels' own surfaces and
    encloses itself along the strip with such members only (a pixel with no photon at
    the depth gives about ``-s``). A pixel's only candidate keeps the former rule (a
    dim surface's pixels, whose counts speak weakly either way, enclose one another),
    and it vouches for its neighbours (a dim surface behind a strand).

    Parameters
    ----------
    surf : dict
        Candidate table (see :func:`spill_over_features`); ``image_shape`` (R, C).
    keep : (S,) bool
        Candidates kept so far; the others are neither sources nor tested.
    irf : (L, n) float
        Normalised IRF.
    peak : (L,) int
        Sample of each IRF's peak.
    fwhm : float
        Same-depth tolerance (bins).
    llr_level : float
        Natural log of the likelihood ratio below which the own counts reject a return
        of the source's intensity (0: the counts favour "no return").
    vouch_level : float
        Own log-likelihood ratio below which a further candidate does not enclose a
        further candidate of a neighbour (``-inf``: every pair encloses, the former
        test; ``detect`` passes ``-presence_llr``: counts that reject a return as
        strongly as the presence test requires do not vouch for a neighbour).
    max_iter : int
        Most passes; each one removes the spread one pixel further from the sources.
    n_jobs : int
        Threads of the first pass's log-ratios (every candidate's own: the result does
        not depend on it).

    Returns
    -------
    (S,) bool
        True for the candidates to reject (always False where ``keep`` is False).

    Examples
    --------
    >>> import numpy as np
    >>> from splidar.irf import gaussian_irf
    >>> g = np.asarray(gaussian_irf(3.0), float)[None]
    >>> cnt = np.zeros((2, 1, 9), np.int32)
    >>> cnt[0, 0, 3:6] = [3, 6, 3]
    >>> surf = dict(row=np.array([0, 0]), col=np.array([0, 1]), depth_bin=np.array([4.0, 4.0]),
    ...             offset=np.array([0, 0]), own_counts=cnt,
    ...             own_background=np.full((2, 1, 9), 0.05, np.float32), image_shape=(1, 2))
    >>> reject_spill_over(surf, np.ones(2, bool), irf=g, peak=np.array([g.argmax()]),
    ...                   fwhm=3.0, llr_level=0.0).tolist()
    [False, True]
    """
    R, C = surf["image_shape"]
    idx = np.flatnonzero(keep)
    rej = np.zeros(keep.size, bool)
    if idx.size == 0:
        return rej
    counts = np.asarray(surf["own_counts"])[idx]
    bkg = np.asarray(surf["own_background"][idx], np.float32)  # those rows only
    own = np.maximum(
        counts.sum(axis=-1, dtype=np.float64) - bkg.sum(axis=-1, dtype=np.float64), 0.0
    )
    row = np.asarray(surf["row"], np.int64)[idx]
    col = np.asarray(surf["col"], np.int64)[idx]
    order, starts = _by_pixel(row, col, (R, C))
    out = np.zeros(idx.size, bool)
    args = (
        row, col, np.asarray(surf["depth_bin"], np.float64)[idx],
        np.asarray(surf["offset"], np.int64)[idx], np.ascontiguousarray(counts),
        np.ascontiguousarray(bkg), own, order, starts, int(R), int(C),
        np.ascontiguousarray(irf, np.float64), np.ascontiguousarray(peak, np.float64),
        float(fwhm),
    )  # fmt: skip
    llr = _first_llrs(args, n_jobs)
    n_pass = _spill_kernel(*args, float(llr_level), float(vouch_level), int(max_iter), llr, out)
    rej[idx] = out
    logger.debug(
        "spill-over: %d of %d kept candidates rejected in %d passes",
        int(rej.sum()),
        int(keep.sum()),
        n_pass,
    )
    return rej


@njit(cache=True, nogil=True)
def _pair_encloses(r, c, pair, depth_i, d, mask, mute, strict, order, starts, R, C, fwhm):
    """Whether the opposite 4-neighbours of pixel ``(r, c)`` (``pair`` 0: north/south,
    1: west/east) hold candidates of ``mask`` whose mean depth is within ``fwhm`` of
    ``depth_i`` (False at the image border). When ``strict``, a pair whose two
    candidates are both ``mute`` does not enclose (a strip of spread over the pixels'
    own surfaces encloses itself along the strip, with such members only)."""
    ra, ca, rb, cb = (r - 1, c, r + 1, c) if pair == 0 else (r, c - 1, r, c + 1)
    if ra < 0 or ca < 0 or rb >= R or cb >= C:
        return False
    pa = ra * C + ca
    pb = rb * C + cb
    for ka in range(starts[pa], starts[pa + 1]):
        ja = order[ka]
        if not mask[ja]:
            continue
        for kb in range(starts[pb], starts[pb + 1]):
            jb = order[kb]
            if not mask[jb] or (strict and mute[ja] and mute[jb]):
                continue
            if abs(0.5 * (d[ja] + d[jb]) - depth_i) <= fwhm:
                return True
    return False


@njit(cache=True, nogil=True)
def _spill_suspect(
    i,
    row,
    col,
    d,
    offset,
    counts,
    bkg,
    own,
    active,
    order,
    starts,
    R,
    C,
    irf,
    peak,
    fwhm,
    sig,
):
    """Conditions 1 and 3 of the spill-over test for candidate ``i``: the own-pixel
    log-likelihood ratio of a return as bright as its source (the same-depth candidate
    of largest own signal among the active 8 neighbours); ``+inf`` without a source."""
    L = counts.shape[1]
    r = row[i]
    c = col[i]
    best = -np.inf
    src = -1
    for dr in range(-1, 2):
        for dc in range(-1, 2):
            if dr == 0 and dc == 0:
                continue
            rr = r + dr
            cc = c + dc
            if rr < 0 or rr >= R or cc < 0 or cc >= C:
                continue
            p = rr * C + cc
            for kk in range(starts[p], starts[p + 1]):
                j = order[kk]
                if not active[j] or abs(d[j] - d[i]) > fwhm:
                    continue
                tot = 0.0
                for l in range(L):
                    tot += own[j, l]
                if tot > best:
                    best = tot
                    src = j
    if src < 0:
        return np.inf
    for l in range(L):
        sig[l] = max(own[src, l], 1e-9)
    return _llr_at(i, sig, d, offset, counts, bkg, irf, peak)


@njit(cache=True, nogil=True)
def _llr_at(i, sig, d, offset, counts, bkg, irf, peak):
    """Own-pixel log-likelihood ratio of candidate ``i`` for a return of ``sig`` (L,)
    photons against background only (``_own_llr`` for one candidate). The logarithm is
    taken at the bins holding photons only (most bins are empty at low flux; an empty
    bin's term ``0 * log1p(.)`` adds exactly 0, so the sum is the same bit for bit)."""
    L = counts.shape[1]
    W = counts.shape[2]
    dw = d[i] - offset[i]
    llr = 0.0
    for l in range(L):
        for w in range(W):
            b = bkg[i, l, w]
            if not b > 0:
                continue  # outside the support
            g = _interp_irf(irf[l], w - dw + peak[l])
            n = counts[i, l, w]
            if n != 0:
                llr += n * np.log1p(sig[l] * g / max(np.float64(b), 1e-9))
            llr -= sig[l] * g
    return llr


#: Fewest candidates per thread of the spill-over test's first pass.
_SPILL_PART = 4096


def _first_llrs(args: tuple, n_jobs: int) -> np.ndarray:
    """The first pass's log-ratios of :func:`_spill_kernel` (every candidate active), in
    ``n_jobs`` contiguous parts on as many threads (each candidate's value is its own)."""
    n = args[0].size
    llr = np.empty(n)
    work = min(int(n_jobs), n // _SPILL_PART)
    on_parts(lambda i0, i1: _first_llrs_kernel(*args, i0, i1, llr), n, work)
    return llr


@njit(cache=True, nogil=True)
def _first_llrs_kernel(
    row, col, d, offset, counts, bkg, own, order, starts, R, C, irf, peak, fwhm, i0, i1, llr
):  # pragma: no cover - numba
    """``llr[i0:i1]``: :func:`_spill_suspect` of candidates ``i0..i1-1`` with every
    candidate active (the first pass of :func:`_spill_kernel`)."""
    active = np.ones(row.size, np.bool_)
    sig = np.empty(counts.shape[1], np.float64)
    for i in range(i0, i1):
        llr[i] = _spill_suspect(
            i, row, col, d, offset, counts, bkg, own, active, order, starts, R, C, irf, peak,
            fwhm, sig,
        )  # fmt: skip


@njit(cache=True, nogil=True)
def _spill_kernel(
    row,
    col,
    d,
    offset,
    counts,
    bkg,
    own,
    order,
    starts,
    R,
    C,
    irf,
    peak,
    fwhm,
    level,
    vouch,
    max_iter,
    llr,
    rej,
):
    """Iterated spill-over test of :func:`reject_spill_over` on ``n`` candidates.

    ``order`` sorts the candidates by pixel, ``starts`` (R * C + 1) delimits each
    pixel's run in it. Each pass computes the own log-ratio of every active candidate
    that has a source (``+inf`` without one), then rejects those below ``level`` that
    no opposite pair of 4-neighbours encloses; a further candidate (beside another of
    its pixel at or above ``level``) needs a pair of which one is no further candidate
    below ``vouch`` (all at once, as :func:`spill_over_features`). ``llr`` (n,) holds
    the first pass's log-ratios (:func:`_first_llrs_kernel`) and is updated in place.
    Returns the number of passes.

    After the first pass, only what a pass's rejections can change is computed again:
    a log-ratio, the further and mute flags where the 3 x 3 neighbourhood lost a
    candidate (the *dirty* pixels: its source may have gone, its pixel's other
    candidates changed), the test of the dirty pixels' candidates and of their
    4-neighbours' (an enclosing pair's member may have gone or turned mute). Every other
    candidate's inputs are those of the last pass, where it was not rejected: it is not
    rejected again (the same passes as testing every candidate each time).
    """
    n = row.size
    active = np.ones(n, np.bool_)
    further = np.zeros(n, np.bool_)
    mute = np.zeros(n, np.bool_)
    new = np.empty(n, np.int64)
    mark = np.zeros(R * C, np.int32)  # the pass that listed a pixel (dirty; tested: -pass)
    sig = np.empty(counts.shape[1], np.float64)
    dirty = np.empty(0, np.int64)  # no log-ratio recomputed in the first pass
    touched = np.arange(R * C)  # the first pass: every pixel's flags and tests
    tested = touched
    passes = 0
    for _ in range(max_iter):
        passes += 1
        for p in dirty:
            for kk in range(starts[p], starts[p + 1]):
                i = order[kk]
                if active[i]:
                    llr[i] = _spill_suspect(
                        i, row, col, d, offset, counts, bkg, own, active, order, starts,
                        R, C, irf, peak, fwhm, sig,
                    )  # fmt: skip
        _spill_flags(touched, order, starts, active, llr, level, vouch, further, mute)
        n_new = _spill_unenclosed(
            tested, row, col, d, order, starts, R, C, fwhm, level, active, llr, further,
            mute, new,
        )  # fmt: skip
        if n_new == 0:
            break
        for i in new[:n_new]:
            rej[i] = True
            active[i] = False
        dirty = _spill_dirty(new[:n_new], row, col, R, C, mark, passes)
        touched, tested = dirty, _spill_cross(dirty, R, C, mark, passes)
    return passes


@njit(cache=True, nogil=True)
def _spill_flags(pixels, order, starts, active, llr, level, vouch, further, mute):
    """``further`` and ``mute`` of :func:`_spill_kernel` for the candidates of
    ``pixels``: beside another active candidate of the pixel that its own counts
    support (``llr >= level``); mute: further and its own ``llr < vouch``."""
    for p in pixels:
        for k in range(starts[p], starts[p + 1]):
            i = order[k]
            further[i] = False
            if active[i]:
                for kk in range(starts[p], starts[p + 1]):
                    j = order[kk]
                    if j != i and active[j] and llr[j] >= level:
                        further[i] = True
                        break
            mute[i] = further[i] and llr[i] < vouch


@njit(cache=True, nogil=True)
def _spill_unenclosed(
    pixels, row, col, d, order, starts, R, C, fwhm, level, active, llr, further, mute, new
):
    """The active candidates of ``pixels`` below ``level`` that no opposite pair of
    4-neighbours encloses (:func:`_pair_encloses`), written to ``new``; their number."""
    n_new = 0
    for p in pixels:
        for k in range(starts[p], starts[p + 1]):
            i = order[k]
            if not active[i] or not llr[i] < level:
                continue
            f = further[i]
            if not (
                _pair_encloses(
                    row[i], col[i], 0, d[i], d, active, mute, f, order, starts, R, C, fwhm
                )
                or _pair_encloses(
                    row[i], col[i], 1, d[i], d, active, mute, f, order, starts, R, C, fwhm
                )
            ):
                new[n_new] = i
                n_new += 1
    return n_new


@njit(cache=True, nogil=True)
def _spill_dirty(gone, row, col, R, C, mark, stamp):
    """The pixels (each once) of the 3 x 3 neighbourhoods of the candidates ``gone``;
    ``mark`` set to ``stamp`` there."""
    out = np.empty(9 * gone.size, np.int64)
    m = 0
    for i in gone:
        for rr in range(max(row[i] - 1, 0), min(row[i] + 2, R)):
            for cc in range(max(col[i] - 1, 0), min(col[i] + 2, C)):
                q = rr * C + cc
                if mark[q] != stamp:
                    mark[q] = stamp
                    out[m] = q
                    m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def _spill_cross(dirty, R, C, mark, stamp):
    """``dirty`` (marked ``stamp`` in ``mark``) and their 4-neighbours, each once (the
    latter marked ``-stamp``)."""
    out = np.empty(5 * dirty.size, np.int64)
    out[: dirty.size] = dirty
    m = dirty.size
    for p in dirty:
        r = p // C
        c = p - r * C
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            rr = r + dr
            cc = c + dc
            if rr < 0 or rr >= R or cc < 0 or cc >= C:
                continue
            q = rr * C + cc
            if mark[q] != stamp and mark[q] != -stamp:
                mark[q] = -stamp
                out[m] = q
                m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def _shared_kernel(row, col, depth, order, starts, R, C, fwhm, shared, n_own):
    """For each candidate: a candidate at the same depth (within ``fwhm``) among its 8
    neighbours (``shared``), and the number of candidates in its pixel (``n_own``).
    Candidates of pixel ``p`` are ``order[starts[p]:starts[p + 1]]``."""
    for i in range(row.size):
        r = row[i]
        c = col[i]
        p = r * C + c
        n_own[i] = starts[p + 1] - starts[p]
        found = False
        for dr in range(-1, 2):
            rr = r + dr
            if rr < 0 or rr >= R:
                continue
            for dc in range(-1, 2):
                cc = c + dc
                if (dr == 0 and dc == 0) or cc < 0 or cc >= C:
                    continue
                q = rr * C + cc
                for k in range(starts[q], starts[q + 1]):
                    if abs(depth[order[k]] - depth[i]) <= fwhm:
                        found = True
                        break
                if found:
                    break
            if found:
                break
        shared[i] = found


def reject_isolated(
    surf: dict,
    keep: np.ndarray,
    *,
    fwhm: float,
    pfa: float,
    only_extra: bool = False,
    n_bins: int | None = None,
) -> np.ndarray:
    """Candidates no neighbour shares whose own counts are not significant on their own.

    The spatial pooling of the coarse scales is evidence for a surface that extends
    over several pixels. A candidate with no kept candidate at the same depth (within
    ``fwhm``) among its 8 neighbours gets no such support: it is kept only when its own
    pixel is significant by itself, i.e. the Poisson probability of at least the
    observed counts n over its support under the background alone, ``p = P(N >= n |
    B)``, is at most ``pfa``; with ``n_bins`` given, ``p`` is first corrected for the
    free depth (look-elsewhere): ``1 - (1 - p)^(n_bins / w)`` for a support of ``w``
    bins, the chance that a background-only pixel shows such a count in any of its
    windows, so that ``pfa`` is a per-pixel rate (``detect`` passes ``surface_pfa``).

    Parameters
    ----------
    surf : dict
        Candidate table (see :func:`spill_over_features`).
    keep : (S,) bool
        Candidates kept so far (only they count as neighbours and are tested).
    fwhm : float
        Same-depth tolerance (bins).
    pfa : float
        Significance required of an isolated candidate's own counts.
    only_extra : bool
        Test only isolated candidates in pixels holding another kept candidate.
    n_bins : int, optional
        T, the pixel's number of time bins (look-elsewhere correction); None: none.

    Returns
    -------
    (S,) bool
        True for the candidates to reject.

    Examples
    --------
    >>> import numpy as np
    >>> cnt = np.zeros((2, 1, 9), np.int32)
    >>> cnt[0, 0, 4] = 1  # one photon over a background of 0.45: not significant
    >>> cnt[1, 0, 3:6] = [2, 4, 2]
    >>> surf = dict(row=np.array([0, 4]), col=np.array([0, 4]), depth_bin=np.array([4.0, 4.0]),
    ...             own_counts=cnt, own_background=np.full((2, 1, 9), 0.05, np.float32),
    ...             image_shape=(5, 5))
    >>> reject_isolated(surf, np.ones(2, bool), fwhm=3.0, pfa=1e-3).tolist()
    [True, False]
    """
    from scipy import stats

    R, C = surf["image_shape"]
    S = surf["row"].size
    rej = np.zeros(S, bool)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return rej
    row = np.asarray(surf["row"], np.int64)[idx]
    col = np.asarray(surf["col"], np.int64)[idx]
    d = np.asarray(surf["depth_bin"], np.float64)[idx]
    # a neighbour at the same depth (within fwhm) shares
    order, starts = _by_pixel(row, col, (R, C))
    shared = np.zeros(idx.size, bool)
    n_own = np.zeros(idx.size, np.int64)  # candidates in the pixel (itself included)
    _shared_kernel(row, col, d, order, starts, int(R), int(C), float(fwhm), shared, n_own)
    test = ~shared & ((n_own > 1) if only_extra else True)
    sub = idx[test]
    n = np.asarray(surf["own_counts"])[sub].sum(axis=(1, 2))
    own_bg = np.asarray(surf["own_background"][sub])  # the tested rows only
    B = own_bg.astype(np.float64).sum(axis=(1, 2))
    p = stats.poisson.sf(n - 1, np.maximum(B, 1e-12))  # P(N >= n | B)
    if n_bins is not None:
        # the candidate's depth was free: any of the T / width windows of the pixel
        # could have held such a count (look-elsewhere), so the chance that a
        # background-only pixel shows one somewhere is 1 - (1 - p)^(T / width)
        support = own_bg > 0  # (m, L, W)
        width = np.maximum(support.any(axis=1).sum(axis=1), 1)
        p = -np.expm1(np.log1p(-np.minimum(p, 1 - 1e-12)) * (n_bins / width))
    rej[sub] = p > pfa
    logger.debug("isolated: %d tested, %d rejected", int(test.sum()), int(rej.sum()))
    return rej


#: fewest candidates in a dark-region pool (a patch, not a noise peak or two: each
#: candidate's depth sits on its own counts' peak, so a small pool's counts are biased up)
MIN_POOL = 6


#: Fewest candidates (suspects) per thread of :func:`_dark_sums`
#: (:func:`_dark_pool_sums`).
_DARK_PART = 4096
_DARK_POOL_PART = 256


def _dark_pools(
    row, col, d, offset, counts, bkg, keep, ev, order, starts, R, C, irf, peak, hw, fwhm,
    half, weak_z, n_jobs=1,
):  # fmt: skip
    """Suspects of :func:`rescue_dark` and the sums of their pools.

    Returns the suspects' indices (m,), the pooled counts, background and IRF fraction
    in the half-maximum windows about the suspect's depth, per wavelength ((m, L)
    each), the pools' sizes, and the pooled counts and background about each member's
    own depth ((m,) each). The candidates' own sums (:func:`_dark_sums`) and the
    suspects' pools (:func:`_dark_pool_sums`) in ``n_jobs`` contiguous parts on as many
    threads: each candidate's and each pool's sums are its own, added in the same order
    (the same values on any number).
    """
    S, L = row.size, counts.shape[1]
    n_l = np.zeros((S, L))
    b_l = np.zeros((S, L))
    member = np.zeros(S, np.bool_)
    own = (d, offset, counts, bkg, keep, hw, weak_z, n_l, b_l, member)
    on_parts(lambda i0, i1: _dark_sums(*own, i0, i1), S, min(int(n_jobs), S // _DARK_PART))
    idx = _dark_suspects(keep, ev, order, starts, R, C, member)
    m = idx.size
    pn, pb, pf = np.zeros((m, L)), np.zeros((m, L)), np.zeros((m, L))
    size = np.zeros(m, np.int64)
    n0, b0 = np.zeros(m), np.zeros(m)  # the same pool counted about each member's own depth
    args = (
        idx, row, col, d, offset, counts, bkg, member, n_l, b_l, order, starts, R, C, irf,
        peak, hw, fwhm, half, pn, pb, pf, size, n0, b0,
    )  # fmt: skip
    on_parts(
        lambda k0, k1: _dark_pool_sums(*args, k0, k1), m, min(int(n_jobs), m // _DARK_POOL_PART)
    )
    return idx, pn, pb, pf, size, n0, b0


@njit(cache=True, nogil=True)
def _dark_sums(d, offset, counts, bkg, keep, hw, weak_z, n_l, b_l, member, i0, i1):
    """Candidates ``i0..i1-1``' own counts ``n_l`` and background ``b_l`` (S, L) in the
    half-maximum window about their depths; ``member``: kept ones whose own z is below
    ``weak_z``."""
    L = counts.shape[1]
    W = counts.shape[2]
    for i in range(i0, i1):
        nt = 0.0
        bt = 0.0
        for l in range(L):
            for w in range(W):
                b = np.float64(bkg[i, l, w])
                if b <= 0.0:
                    continue
                x = offset[i] + w - d[i]
                if abs(x) <= hw:
                    n_l[i, l] += counts[i, l, w]
                    b_l[i, l] += b
            nt += n_l[i, l]
            bt += b_l[i, l]
        if keep[i]:
            member[i] = (nt - bt) < weak_z * np.sqrt(max(bt, 1e-9))


@njit(cache=True, nogil=True)
def _dark_suspects(keep, ev, order, starts, R, C, member):
    """One suspect per pixel with no kept candidate: its rejected candidate of largest
    evidence, in pixel order (m,); ``member`` set for them."""
    sus = np.full(R * C, -1, np.int64)
    for p in range(R * C):
        best = -1
        for j in range(starts[p], starts[p + 1]):
            i = order[j]
            if keep[i]:
                best = -1
                break
            if best < 0 or ev[i] > ev[best]:
                best = i
        sus[p] = best
    m = 0
    for p in range(R * C):
        if sus[p] >= 0:
            member[sus[p]] = True
            m += 1
    idx = np.empty(m, np.int64)
    k = 0
    for p in range(R * C):
        if sus[p] >= 0:
            idx[k] = sus[p]
            k += 1
    return idx


@njit(cache=True, nogil=True)
def _dark_pool_sums(
    idx, row, col, d, offset, counts, bkg, member, n_l, b_l, order, starts, R, C, irf, peak,
    hw, fwhm, half, pn, pb, pf, size, n0, b0, k0, k1,
):  # fmt: skip
    """The pools of suspects ``idx[k0:k1]``: members within ``half`` pixels at the
    suspect's depth (within ``fwhm``); their counts, background and IRF fraction about
    the suspect's depth (``pn``, ``pb``, ``pf``), their number and their own sums
    (``n0``, ``b0``)."""
    L = counts.shape[1]
    W = counts.shape[2]
    for k in range(k0, k1):
        i = idx[k]
        r0 = row[i]
        c0 = col[i]
        for rr in range(max(r0 - half, 0), min(r0 + half + 1, R)):
            for cc in range(max(c0 - half, 0), min(c0 + half + 1, C)):
                q = rr * C + cc
                for j in range(starts[q], starts[q + 1]):
                    a = order[j]
                    if member[a] and abs(d[a] - d[i]) <= fwhm:
                        size[k] += 1
                        for l in range(L):
                            n0[k] += n_l[a, l]
                            b0[k] += b_l[a, l]
                        # counted about the pool's depth d[i], not the member's own: a
                        # member's depth sits on its own counts' peak, and summed over
                        # the pool that bias alone passes the test (the halo of empty
                        # pixels around a bright object)
                        for l in range(L):
                            for w in range(W):
                                b = np.float64(bkg[a, l, w])
                                x = offset[a] + w - d[i]
                                if b > 0.0 and abs(x) <= hw:
                                    pn[k, l] += counts[a, l, w]
                                    pb[k, l] += b
                                    pf[k, l] += _interp_irf(irf[l], x + peak[l])


def rescue_dark(
    surf: dict,
    keep: np.ndarray,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    half: int,
    pfa: float,
    llr_level: float,
    weak_z: float = 3.0,
    min_pool: int = MIN_POOL,
    n_jobs: int = 1,
) -> np.ndarray:
    """Rejected candidates of empty pixels that a dim surface around them explains.

    A dark patch (low reflectivity) holds too few photons per pixel for the local
    presence test, and beside bright pixels at the same depth it looks like their
    spread. What tells the two apart is the pixels' own counts taken together: a dim
    surface puts photons at its depth in every pixel of the patch, the spread of a
    neighbour puts none. For each pixel with no kept candidate, its rejected candidate
    of largest evidence (a *suspect*) is pooled with the other suspects and the kept
    candidates whose own counts are weak (z < ``weak_z`` in the half-maximum window),
    within ``half`` pixels and at the same depth (within ``fwhm``): their own counts
    ``n`` and background ``B`` in the half-maximum window about the suspect's depth (the
    pool's). It is restored when ``P(N >= n | B) <= pfa``, also with each member's
    counts taken about its own depth (the former test), and its own counts do not
    reject a return of the pool's mean intensity (own log-likelihood ratio
    ``>= llr_level``). Each member's depth sits on its own counts' peak: summed about
    those depths, a pool of background-only pixels (the halo of empty pixels beside a
    bright object, whose coarse boxes planted the candidates) passed the test on that
    bias alone.

    Parameters
    ----------
    surf : dict
        Candidate table (see :func:`spill_over_features`), with ``evidence`` (S,).
    keep : (S,) bool
        Candidates kept so far.
    irf : (L, n) float
        Normalised IRF.
    peak : (L,) int
        Sample of each IRF's peak.
    fwhm : float
        Same-depth tolerance (bins); the window is ``+-max(1, fwhm / 2)`` bins.
    half : int
        Half-size of the pool's square (pixels): ``detect`` passes the largest box's.
    pfa : float
        Significance required of the pool (``detect`` passes ``surface_pfa``).
    llr_level : float
        Lowest own log-likelihood ratio (``detect`` passes ``-presence_llr``).
    weak_z : float
        Kept candidates below this own z join the pools (``presence_z``).
    min_pool : int
        Fewest members of a pool.
    n_jobs : int
        Threads of the candidates' sums and the pools' (:func:`_dark_pools`; the result
        does not depend on it).

    Returns
    -------
    (S,) bool
        True for the candidates to restore.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar.irf import gaussian_irf
    >>> g = np.asarray(gaussian_irf(2.0), float)[None]
    >>> n, W = 25, 13  # a 5 x 5 dim patch: one photon per pixel at bin 6
    >>> cnt = np.zeros((n, 1, W), np.int32)
    >>> cnt[:, 0, 6] = 1
    >>> r, c = np.divmod(np.arange(n), 5)
    >>> surf = dict(row=r, col=c, depth_bin=np.full(n, 6.0), offset=np.zeros(n, int),
    ...             own_counts=cnt, own_background=np.full((n, 1, W), 0.02, np.float32),
    ...             evidence=np.ones(n), image_shape=(5, 5))
    >>> res = rescue_dark(surf, np.zeros(n, bool), irf=g, peak=np.array([g.argmax()]),
    ...                   fwhm=4.7, half=2, pfa=0.01, llr_level=-3.0)
    >>> int(res.sum())
    25
    >>> surf["own_counts"] = np.zeros_like(cnt)  # the spread of a neighbour: no photons
    >>> int(rescue_dark(surf, np.zeros(n, bool), irf=g, peak=np.array([g.argmax()]),
    ...                 fwhm=4.7, half=2, pfa=0.01, llr_level=-3.0).sum())
    0
    """
    from scipy import stats

    R, C = surf["image_shape"]
    S = keep.size
    out = np.zeros(S, bool)
    if S == 0 or keep.all():
        return out
    row = np.asarray(surf["row"], np.int64)
    col = np.asarray(surf["col"], np.int64)
    order, starts = _by_pixel(row, col, (R, C))
    d = np.asarray(surf["depth_bin"], np.float64)
    off = np.asarray(surf["offset"], np.int64)
    counts = np.ascontiguousarray(surf["own_counts"])
    bkg = np.ascontiguousarray(surf["own_background"], np.float32)
    hw = max(1.0, 0.5 * float(fwhm))
    sus, pn, pb, pf, size, n0, b0 = _dark_pools(
        row, col, d, off, counts, bkg, np.ascontiguousarray(keep),
        np.asarray(surf["evidence"], np.float64), order, starts, int(R), int(C),
        np.ascontiguousarray(irf, np.float64), np.asarray(peak, np.float64), hw,
        float(fwhm), int(half), float(weak_z), n_jobs,
    )  # fmt: skip
    if sus.size == 0:
        return out
    p = stats.poisson.sf(pn.sum(axis=1) - 1, np.maximum(pb.sum(axis=1), 1e-12))
    # the same pool counted about each member's own depth: the former test, kept as a
    # second condition (alone, the pool's depth let suspects of wrong depth through on
    # a true surface beside them: single surface PPP 1, SBR 1, false restored 4 -> 35)
    p = np.maximum(p, stats.poisson.sf(n0 - 1, np.maximum(b0, 1e-12)))
    sig = np.flatnonzero((p <= pfa) & (size >= min_pool))
    if sig.size == 0:
        return out
    # own counts must not reject a return of the pool's mean intensity
    i = sus[sig]
    s_hat = np.maximum(pn[sig] - pb[sig], 0.0) / np.maximum(pf[sig], 1e-9)  # (k, L)
    llr = _own_llr(counts[i], bkg[i].astype(np.float64), irf, peak, d[i] - off[i], s_hat)
    out[i[llr >= llr_level]] = True
    logger.debug("dark-region pass: %d of %d suspects restored", int(out.sum()), sus.size)
    return out


@njit(cache=True, nogil=True)
def _align_pairs(D, r, c, d, K, fwhm, kb, grad, has):
    """The opposite pairs of 4-neighbours (north/south, west/east) that hold the return
    of a surface at depth ``d`` of padded pixel ``(r, c)``: per pair, the slots ``kb``
    of its two surfaces whose mean is nearest ``d`` (kept when within 2 FWHM), the half
    difference of their depths ``grad`` (the plane's slope along the pair) and ``has``.
    Returns the pairs' mean prediction, or NaN when none holds it or two disagree by
    more than the FWHM."""
    n_pred = 0
    psum = 0.0
    p_first = 0.0
    for u in range(2):
        dr = 1 if u == 0 else 0
        dc = 1 - dr
        best = np.inf
        pb = 0.0
        has[u] = False
        for k1 in range(K):
            x = D[r - dr, c - dc, k1]
            if np.isnan(x):
                continue
            for k2 in range(K):
                y = D[r + dr, c + dc, k2]
                if np.isnan(y):
                    continue
                if abs(0.5 * (x + y) - d) < best:
                    best = abs(0.5 * (x + y) - d)
                    pb = 0.5 * (x + y)
                    grad[u] = 0.5 * (y - x)
                    kb[u, 0] = k1
                    kb[u, 1] = k2
        if best <= 2.0 * fwhm:  # the same return, at most 2 FWHM off
            if n_pred and abs(pb - p_first) > fwhm:
                return np.nan
            if n_pred == 0:
                p_first = pb
            has[u] = True
            n_pred += 1
            psum += pb
    return psum / n_pred if n_pred else np.nan


@njit(cache=True, nogil=True)
def _sheared_pool(i, r, c, own, offset, index, kb, grad, has, pool):
    """``pool``: the own clean histogram of surface ``i`` plus its pairs' members', each
    shifted along the plane (by its pair's slope, linear interpolation) so that a return
    on the plane lands on the same bin for all (the 3 x 3 box sheared by the slope)."""
    W = own.shape[1]
    for t in range(W):
        pool[t] = own[i, t]
    for u in range(2):
        if not has[u]:
            continue
        dr = 1 if u == 0 else 0
        dc = 1 - dr
        for side in range(2):
            sgn = 2 * side - 1
            j = index[r + sgn * dr, c + sgn * dc, kb[u, side]]
            x0 = offset[i] + sgn * grad[u] - offset[j]
            for t in range(W):
                pool[t] += _interp_irf(own[j], x0 + t)


@njit(cache=True, nogil=True)
def _align_maps(row, col, slot, depth, R, C, K):
    """The padded depth map ``D`` (R + 2, C + 2, K) of the surfaces (NaN: none) and
    their indices ``index`` (-1: none) for :func:`_align_kernel`."""
    D = np.full((R + 2, C + 2, K), np.nan)
    index = np.full((R + 2, C + 2, K), -1, np.int64)
    for i in range(row.size):
        D[row[i] + 1, col[i] + 1, slot[i]] = depth[i]
        index[row[i] + 1, col[i] + 1, slot[i]] = i
    return D, index


@njit(cache=True, nogil=True)
def _align_kernel(row, col, depth, offset, own, noise, D, index, K, fwhm, z_own, out, i0, i1):
    """``out[i0:i1]``: the depths of surfaces ``i0..i1-1``, moved where their neighbours'
    plane and the sheared pool agree on another (see :func:`align_depths`; ``D`` and
    ``index`` from :func:`_align_maps`: the depths before any move, so each surface's
    result is its own). Returns the number moved."""
    W = own.shape[1]
    kb = np.zeros((2, 2), np.int64)
    grad = np.zeros(2)
    has = np.zeros(2, np.bool_)
    pool = np.zeros(W)
    moved = 0
    for i in range(i0, i1):
        out[i] = depth[i]
        d = depth[i]
        p = _align_pairs(D, row[i] + 1, col[i] + 1, d, K, fwhm, kb, grad, has)
        if np.isnan(p) or abs(p - d) <= 0.5 * fwhm:
            continue
        _sheared_pool(i, row[i] + 1, col[i] + 1, own, offset, index, kb, grad, has, pool)
        # the pool's peak within half the FWHM of the prediction, if the pool favours it
        # over the current depth and the own counts do not (significantly) reject it
        lo = max(int(np.floor(p - 0.5 * fwhm - offset[i])), 0)
        hi = min(int(np.ceil(p + 0.5 * fwhm - offset[i])), W - 1)
        if hi < lo:
            continue
        w = lo
        for t in range(lo + 1, hi + 1):
            if pool[t] > pool[w]:
                w = t
        wo = min(max(int(np.rint(d - offset[i])), 0), W - 1)
        if pool[w] <= 0.0 or pool[w] <= pool[wo]:
            continue
        if own[i, wo] - own[i, w] > z_own * noise[i]:
            continue
        dw = 0.0
        if 0 < w < W - 1 and pool[w] >= pool[w - 1] and pool[w] >= pool[w + 1]:
            # sub-bin: the vertex of the parabola through a local maximum (within
            # half a bin of it)
            den = pool[w - 1] - 2.0 * pool[w] + pool[w + 1]
            if den < 0.0:
                dw = min(max(0.5 * (pool[w - 1] - pool[w + 1]) / den, -0.5), 0.5)
        out[i] = offset[i] + w + dw
        moved += 1
    return moved


#: Fewest surfaces per thread of :func:`_align_kernel`.
_ALIGN_PART = 4096


def align_depths(
    row, col, slot, depth, offset, own_hist, *, image_shape, n_slots: int, fwhm: float,
    noise=None, z_own: float = 1.0, n_jobs: int = 1,
) -> tuple[np.ndarray, int]:  # fmt: skip
    """Depths that the 4-neighbours' plane and the sheared 3 x 3 pool place elsewhere, moved.

    On a steep slope the square boxes pool returns several bins apart (a slope of 5 bins
    per row puts the rows above and below 5 bins either side): the pooled response has a
    lobe per row, and at low counts its peak can fall on a neighbour's lobe, one row's
    slope off the pixel's return. The opposite pairs of 4-neighbours that hold the same
    return (their mean within 2 FWHM of the depth; one pair suffices, two must agree
    within the FWHM) predict the depth (their mean) and the local plane's slope (half
    their difference). When the prediction is more than half the FWHM away, the 3 x 3
    box is sheared along that plane: the own clean histogram (the finest scale of
    ``eq:background_final``) and the pairs' members', each shifted by the plane's depth
    difference, are summed (a return on the plane lands on one bin in every pixel, as a
    flat surface does in the square box). The surface moves to that pool's peak within
    half the FWHM of the prediction (sub-bin, parabola) when the pool is higher there
    than at the current depth, unless the own counts favour the current depth by more
    than ``z_own`` standard deviations of the background's noise (the own pixel's depth
    wins where its counts can tell it from the plane's: a bright pixel off the plane, a
    curved surface at high counts; as in the scale selection's intersection of
    confidence intervals). Predictions use the depths before any move (the result does not depend
    on the order).

    Parameters
    ----------
    row, col, slot : (S,) int
        Pixel and ``K_s`` slot of each surface (at most one per slot).
    depth : (S,) float
        Depths (bins).
    offset : (S,) int
        First bin of each surface's histogram window.
    own_hist : (S, W) float
        The own pixel's clean histogram (summed over wavelengths).
    image_shape : (int, int)
    n_slots : int
    fwhm : float
        IRF's full width at half maximum (bins).
    noise : (S,) float, optional
        Standard deviation of the difference of two bins of ``own_hist`` under the
        background alone (``sqrt(2 sum_l b_l sum_t g_l(t)^2)``, ``b_l`` the background
        per bin). Default: infinite (the own counts never veto a move).
    z_own : float
        How many of ``noise`` the own counts must favour the current depth by to keep it.
    n_jobs : int
        Threads (the surfaces in contiguous parts; each surface's depth is its own: the
        same result on any number).

    Returns
    -------
    depth : (S,) float
        The depths, moved where the rule applies.
    n_moved : int

    Examples
    --------
    >>> import numpy as np
    >>> r, c = np.divmod(np.arange(9), 3)  # a ramp of 5 bins per row, the centre 5 off
    >>> d = 10.0 + 5 * r
    >>> d[4] = 20.0
    >>> own = np.zeros((9, 13))
    >>> own[4, 6 - 5] = 1.0  # its one photon sits at bin 15 (window from bin 14)
    >>> new, n = align_depths(r, c, np.zeros(9, int), d, np.full(9, 14), own,
    ...                       image_shape=(3, 3), n_slots=1, fwhm=3.0)
    >>> float(new[4]), n
    (15.0, 1)
    """
    depth = np.asarray(depth, np.float64)
    out = np.empty_like(depth)
    if depth.size == 0:
        return out, 0
    noise = np.full(depth.size, np.inf) if noise is None else np.asarray(noise, np.float64)
    R, C = image_shape
    row, col = np.asarray(row, np.int64), np.asarray(col, np.int64)
    D, index = _align_maps(
        row, col, np.asarray(slot, np.int64), depth, int(R), int(C), int(n_slots)
    )
    args = (
        row, col, depth, np.asarray(offset, np.int64), np.ascontiguousarray(own_hist, np.float64),
        np.ascontiguousarray(noise, np.float64), D, index, int(n_slots), float(fwhm),
        float(z_own), out,
    )  # fmt: skip
    counts: list = []  # the parts' numbers moved
    work = min(int(n_jobs), depth.size // _ALIGN_PART)
    on_parts(lambda i0, i1: counts.append(_align_kernel(*args, i0, i1)), depth.size, work)
    n = sum(counts)
    logger.debug("depth alignment: %d surfaces moved", n)
    return out, int(n)


@njit(cache=True, nogil=True)
def _enclosed_kernel(
    row, col, depth, ev, z, llr, keep, order, starts, R, C, fwhm, z_level, max_kept, llr_level, out
):
    """For each pixel with fewer than ``max_kept`` kept candidates: its rejected
    candidate of largest evidence among those with ``z >= z_level`` (and, beside a kept
    one, ``llr >= llr_level``), none kept within ``fwhm`` of it, that both opposite
    pairs of 4-neighbours enclose (kept candidates whose mean depth is within ``fwhm``
    of its depth)."""
    for p in range(R * C):
        a, b = starts[p], starts[p + 1]
        if a == b:
            continue
        n_kept = 0
        for k in range(a, b):
            if keep[order[k]]:
                n_kept += 1
        if n_kept >= max_kept:
            continue
        r = p // C
        c = p % C
        best = -1
        for k in range(a, b):
            i = order[k]
            if keep[i] or z[i] < z_level or (best >= 0 and ev[i] <= ev[best]):
                continue
            if n_kept > 0 and llr[i] < llr_level:
                continue
            dup = False
            for k in range(a, b):  # a kept surface of the pixel at this depth already
                j = order[k]
                if keep[j] and abs(depth[j] - depth[i]) <= fwhm:
                    dup = True
            if dup:
                continue
            if _pair_encloses(
                r, c, 0, depth[i], depth, keep, keep, False, order, starts, R, C, fwhm
            ) and (
                _pair_encloses(
                    r, c, 1, depth[i], depth, keep, keep, False, order, starts, R, C, fwhm
                )
            ):
                best = i
        if best >= 0:
            out[best] = True


def restore_enclosed(
    surf: dict,
    keep: np.ndarray,
    *,
    fwhm: float,
    z_level: float,
    max_kept: int = 1,
    llr_level: float = -np.inf,
) -> np.ndarray:
    """Rejected candidates of pixels inside a surface that encloses them.

    A pixel inside a continuous surface (flat or sloped) whose own counts hold no photon
    at its depth fails the own-pixel check (a return of ``s`` photons leaves none with
    probability ``exp(-s)``: 5 % at 3 photons). Its neighbours tell it apart from the
    spread of a thin structure or of a depth edge: both opposite pairs of 4-neighbours
    (north/south and west/east) hold kept candidates whose mean depth is within ``fwhm``
    of its depth. Such a candidate, when its local scale is significant
    (``presence_z >= z_level``), is restored (one per pixel: the largest evidence) in a
    pixel with fewer than ``max_kept`` kept candidates, none within ``fwhm`` of it. In a
    pixel that holds a kept candidate already, its own counts must favour it as well
    (``presence_llr >= llr_level``): a one-pixel hole of a net is enclosed by the
    strands, and its own photons come from the surface seen through it.

    Parameters
    ----------
    surf : dict
        Candidate table with ``row``, ``col``, ``depth_bin``, ``evidence``,
        ``presence_z``, ``presence_llr`` (S,) and ``image_shape``.
    keep : (S,) bool
        Candidates kept so far.
    fwhm : float
        Same-depth tolerance (bins).
    z_level : float
        Lowest local-scale z (``detect`` passes ``presence_z``).
    max_kept : int
        Pixels with this many kept candidates are full (``detect`` passes
        ``max_surfaces``).
    llr_level : float
        Lowest own log-likelihood ratio in a pixel holding a kept candidate (``detect``
        passes ``presence_secondary``, the rule for a pixel's further surfaces).

    Returns
    -------
    (S,) bool
        True for the candidates to restore.

    Examples
    --------
    >>> import numpy as np
    >>> r, c = np.divmod(np.arange(9), 3)  # a 3 x 3 patch at 5 + row bins, centre rejected
    >>> surf = dict(row=r, col=c, depth_bin=5.0 + r, evidence=np.ones(9),
    ...             presence_z=np.full(9, 5.0), presence_llr=np.full(9, -2.0),
    ...             image_shape=(3, 3))
    >>> keep = np.arange(9) != 4
    >>> np.flatnonzero(restore_enclosed(surf, keep, fwhm=3.0, z_level=3.0)).tolist()
    [4]
    >>> keep[1] = False  # the north neighbour missing: not enclosed
    >>> restore_enclosed(surf, keep, fwhm=3.0, z_level=3.0).any()
    np.False_
    """
    R, C = surf["image_shape"]
    S = keep.size
    out = np.zeros(S, bool)
    if S == 0 or keep.all():
        return out
    row = np.asarray(surf["row"], np.int64)
    col = np.asarray(surf["col"], np.int64)
    order, starts = _by_pixel(row, col, (R, C))
    _enclosed_kernel(
        row, col, np.asarray(surf["depth_bin"], np.float64),
        np.asarray(surf["evidence"], np.float64), np.asarray(surf["presence_z"], np.float64),
        np.asarray(surf["presence_llr"], np.float64),
        np.ascontiguousarray(keep), order, starts, int(R), int(C), float(fwhm),
        float(z_level), int(max_kept), float(llr_level), out,
    )  # fmt: skip
    logger.debug("enclosed pass: %d candidates restored", int(out.sum()))
    return out
