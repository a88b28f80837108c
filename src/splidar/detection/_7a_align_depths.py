"""Stage 7's first rules (``"align_depths"``): depths the 4-neighbours' plane places elsewhere.

On a steep slope the 3 x 3 box has a lobe per row and a low-count peak can fall on a
neighbour row's: where the opposite pairs of 4-neighbours place a depth more than half
the FWHM away, the 3 x 3 box is sheared along their plane and the depth moves to that
pool's peak near their prediction, unless the own counts favour the current depth
by more than their noise (:func:`~splidar.detection._quality.align_depths`). Then a
surface far (more than 2 FWHM) from what its neighbours offer moves there when the own
counts favour it against a prior (:func:`move_far_depths`). Adds or removes no surface.
These rules decide depths (:func:`aligned_depths`); stage 7 (``_7_depths.place_depths``)
runs them before stage 7b's rules and the moved surfaces' fields follow once, after
both (``_depth_fields``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit

from ._6_select import _stored_rows
from ._depth_fields import (
    _follow,
    _pixels,
    _support_fields,
    _window_fields,
    follow_supports,
    part_size,
)
from ._quality import _shifted_irf, align_depths
from ._result import StoredHistograms, Surfaces
from ._threads import on_parts

__all__ = ["aligned_depths", "move_far_depths"]

#: A pixel whose own counts favour its current depth over the sheared pool's peak by
#: more than this many standard deviations of the background noise keeps it: the pool
#: re-decides only depths the own counts cannot tell from the plane's (on the Art scene
#: at PPP 16 the own pixel's depth beats a 3 x 3 plane through a curved surface).
#: Measured on the same cubes (single surface 96 x 80, PPP 4, SBR 0.25, seeds 0-2,
#: false surfaces uniform / decaying; Art, seed 0, PPP 16 uniform / decaying, tau 4 mm;
#: before this pass's sheared pool: 151.0 / 192.7; 1,240 / 1,023): 0 -> 142.7 / 180.7;
#: 1,230 / 1,011; 1 -> 135.3 / 172.7; 1,219 / 1,006; 2 -> 131.7 / 168.0; 1,267 / 1,026;
#: 3 -> 126.7 / 164.7; 1,338 / 1,104 (F_true at Art PPP 16 below its former figure).
OWN_Z = 1.0

#: Re-decide the far depths after the sheared pool (:func:`move_far_depths`). Measured
#: (benchmarks/README.md, "depth21, session 14"): single surface PPP 4, SBR 0.25, seeds
#: 0-2, F_true / false 0.9674 / 126.7 -> 0.9682 / 120.7 (uniform), 0.9715 / 160.0 ->
#: 0.9719 / 157.0 (decaying); every layer cell equal or better. A moved surface's
#: support, raw counts and background follow it (without, ``reconstruct``'s IRF fraction
#: over the old support was about 0: ``tests/test_paper.py``, net PPP 4 decaying, IAE 2.9
#: -> 257); so do its window (``offset``), clean histograms, ``signal``, selected scale
#: and presence statistics (:func:`_window_fields`).
FAR_DEPTHS = True


#: Bytes of float32 histograms :func:`_finest_sums` reads at a time.
FINEST_PART_BYTES = 2**24


def _finest_sums(histograms, n_jobs: int = 1) -> np.ndarray:
    """``histograms[:, 0].sum(axis=1)`` (the finest scale summed over wavelengths, (S, W))
    as float64, a part of the surfaces at a time: the same values (each row's sum is its
    own) without the float32 array beside the float64 one (0.1 float32 cubes on the face
    file at its native bin). Stored histograms (:class:`StoredHistograms`) are read by
    rows (:func:`~splidar.detection._6_select._stored_rows`: a raw array's chunk files
    read directly), every scale of a part at a time. The parts in ``n_jobs`` contiguous
    runs on as many threads (NumPy's sums and the file reads release the GIL; each part
    fills its own rows: the same values on any number)."""
    S, W = int(histograms.shape[0]), int(histograms.shape[-1])
    out = np.empty((S, W), np.float64)
    stored = isinstance(histograms, StoredHistograms)
    row = histograms.shape[1 if stored else 2 :]
    step = max(1, FINEST_PART_BYTES // (4 * int(np.prod(row, dtype=np.int64))))
    firsts = list(range(0, S, step))

    def parts(k0: int, k1: int) -> None:
        for a in firsts[k0:k1]:
            if stored:  # the finest scale as Zarr's ``[a:b, 0]`` gives it (C order)
                b = min(S, a + step)
                part = np.ascontiguousarray(_stored_rows(histograms.array, a, b)[:, 0])
            else:
                part = np.asarray(histograms[a : a + step, 0])
            out[a : a + step] = part.sum(axis=1)

    on_parts(parts, len(firsts), n_jobs)
    return out


def aligned_depths(
    surfaces: Surfaces,
    *,
    fwhm: float,
    irf,
    counts=None,
    background=None,
    shear: bool = True,
    memo: dict | None = None,
    n_jobs: int = 1,
) -> tuple:
    """The depths of ``surfaces`` after the sheared pool (when ``shear``) and, with
    ``counts`` and ``background`` (when :data:`FAR_DEPTHS`), the far-depth rule (see the
    module).

    Parameters
    ----------
    surfaces : Surfaces
    fwhm : float
        The IRF's FWHM (bins).
    irf : ndarray (L, n_irf)
        The normalised IRF: the background's noise on the clean histograms (the matched
        filter's response) is ``b sum_t g(t)^2`` per bin.
    counts : array_like (rows, cols, L, T), optional
        The cube's raw counts.
    background : Background, optional
    shear : bool
        Run the sheared pool (stage 7 runs it in its first round only:
        ``_7_depths.ROUNDS``).
    memo : dict, optional
        The far rule's scores met before on this cube (:func:`_far_moves`; stage 7's
        rounds share one): never changes the result.
    n_jobs : int
        Threads of the sheared pool, its histograms' sums and the far rule's
        alternatives (never changes the result).

    Returns
    -------
    surfaces : Surfaces
        ``depth_bin`` moved; the supports (``start``, ``stop``) and own ``counts`` /
        ``background`` of the surfaces whose depth left its support followed
        (``_depth_fields.follow_supports``); the window fields not yet.
    refit : ndarray (m,) int64
        The surfaces whose support moved (their window fields to be recomputed).
    moved : ndarray (n,) int64
        Every surface whose depth changed (``refit`` among them; the others moved inside
        their support: only their presence statistics follow).
    """
    s = surfaces
    g2 = np.sum(np.atleast_2d(np.asarray(irf, np.float64)) ** 2, axis=-1)  # (L,)
    width = np.maximum(s.stop - s.start, 1).astype(np.float64)
    b = np.asarray(s.background, np.float64) / width[:, None]  # per bin, (S, L)
    noise = np.sqrt(2.0 * np.maximum(b, 0.0) @ g2)
    depth = s.depth_bin
    if shear:
        depth, _ = align_depths(
            s.row, s.col, s.slot, s.depth_bin, s.offset, _finest_sums(s.histograms, n_jobs),
            image_shape=s.image_shape, n_slots=s.n_slots, fwhm=fwhm, noise=noise, z_own=OWN_Z,
            n_jobs=n_jobs,
        )  # fmt: skip
    old = np.asarray(s.depth_bin, np.float64)
    out = replace(s, depth_bin=np.asarray(depth).astype(np.float64))
    far = np.zeros(0, np.int64)
    if FAR_DEPTHS and counts is not None and background is not None:
        out, far = _far_moves(out, counts, background, fwhm=fwhm, irf=irf, memo=memo, n_jobs=n_jobs)
    d = np.asarray(out.depth_bin, np.float64)
    moved = np.flatnonzero(d != old)
    # a depth the sheared pool moved out of its support: treated as a far move
    sheared = np.setdiff1d(moved, far)
    out_of = sheared[(d[sheared] < out.start[sheared]) | (d[sheared] >= out.stop[sheared])]
    if out_of.size and counts is not None and background is not None:
        out = follow_supports(out, out_of, old, counts, background)
    else:
        out_of = np.zeros(0, np.int64)
    return out, np.union1d(far, out_of), moved


#: One-sided alternatives extrapolate a neighbour's surface over two pixels along one of
#: the four directions; the two pixels must hold the same return within this many FWHM
#: (the slope the extrapolation trusts: 4.5 bins per pixel at FWHM 3 bins).
EXTRAPOLATE_FWHM = 1.5


@njit(cache=True, nogil=True)
def _far_kernel(row, col, slot, depth, fwhm, alt, src, isolated, index):
    """Depths the neighbours offer a surface that lies far (more than 2 FWHM) from them.

    ``isolated[i]``: no 8-neighbour holds a surface within 2 FWHM of surface ``i``'s
    depth; then ``alt[i, 0]`` is the plane both opposite pairs of 4-neighbours agree on
    (pair means within the FWHM; the slots nearest the depth), ``src[i, 0]`` its four
    surfaces. Otherwise, when no opposite pair of 8-neighbours holds the depth (it does
    not continue through the pixel: the depth of one side only), ``alt[i, u]`` is the
    extrapolation ``2 D1 - D2`` of the two pixels along direction ``u`` (north, south,
    west, east) that hold one return (within ``EXTRAPOLATE_FWHM`` FWHM), ``src[i, u]``
    those two. Alternatives within 2 FWHM of the depth or of another of the pixel's
    surfaces are dropped (NaN).
    """
    D = _far_maps(row, col, slot, depth, index)
    _far_items(row, col, depth, fwhm, alt, src, isolated, index, D, 0, row.size)


@njit(cache=True, nogil=True)
def _far_maps(row, col, slot, depth, index):
    """The padded depth map ``D`` (R + 4, C + 4, K) of the surfaces (NaN: none) of
    :func:`_far_kernel`, their indices written to ``index`` (same shape, -1: none)."""
    R, C, K = index.shape[0] - 4, index.shape[1] - 4, index.shape[2]
    D = np.full((R + 4, C + 4, K), np.nan)
    for i in range(row.size):
        D[row[i] + 2, col[i] + 2, slot[i]] = depth[i]
        index[row[i] + 2, col[i] + 2, slot[i]] = i
    return D


@njit(cache=True, nogil=True)
def _far_items(row, col, depth, fwhm, alt, src, isolated, index, D, i0, i1):
    """:func:`_far_kernel`'s ``alt``, ``src`` (-1 first: no source) and ``isolated`` of
    surfaces ``i0..i1-1`` (``D`` and ``index`` from :func:`_far_maps`: each surface's
    entries its own)."""
    K = index.shape[2]
    far = 2.0 * fwhm
    for i in range(i0, i1):
        src[i] = -1
        r, c, d = row[i] + 2, col[i] + 2, depth[i]
        for u in range(4):
            alt[i, u] = np.nan
        n8 = 0
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                if dr != 0 or dc != 0:
                    for k in range(K):
                        if abs(D[r + dr, c + dc, k] - d) <= far:
                            n8 += 1
                            break
        isolated[i] = n8 == 0
        if isolated[i]:
            best = np.inf
            for a in range(K):
                for b in range(K):
                    m1 = 0.5 * (D[r - 1, c, a] + D[r + 1, c, b])
                    if np.isnan(m1):
                        continue
                    for e in range(K):
                        for f in range(K):
                            m2 = 0.5 * (D[r, c - 1, e] + D[r, c + 1, f])
                            if np.isnan(m2) or abs(m1 - m2) > fwhm:
                                continue
                            p = 0.5 * (m1 + m2)
                            if abs(p - d) < best:
                                best = abs(p - d)
                                alt[i, 0] = p
                                src[i, 0, 0] = index[r - 1, c, a]
                                src[i, 0, 1] = index[r + 1, c, b]
                                src[i, 0, 2] = index[r, c - 1, e]
                                src[i, 0, 3] = index[r, c + 1, f]
        else:
            through = False
            for dr, dc in ((1, 0), (0, 1), (1, 1), (1, -1)):
                h1 = False
                h2 = False
                for k in range(K):
                    h1 = h1 or abs(D[r - dr, c - dc, k] - d) <= far
                    h2 = h2 or abs(D[r + dr, c + dc, k] - d) <= far
                through = through or (h1 and h2)
            if through:
                continue
            for u in range(4):
                dr = (-1, 1, 0, 0)[u]
                dc = (0, 0, -1, 1)[u]
                best = np.inf
                held = False
                for k in range(K):  # that side holds the depth too: no side to take
                    held = held or abs(D[r + dr, c + dc, k] - d) <= far
                if held:
                    continue
                for a in range(K):
                    x = D[r + dr, c + dc, a]
                    if np.isnan(x) or abs(x - d) <= far:
                        continue
                    for b in range(K):
                        y = D[r + 2 * dr, c + 2 * dc, b]
                        if abs(x - y) <= EXTRAPOLATE_FWHM * fwhm and abs(x - y) < best:
                            best = abs(x - y)
                            alt[i, u] = 2.0 * x - y
                            src[i, u, 0] = index[r + dr, c + dc, a]
                            src[i, u, 1] = index[r + 2 * dr, c + 2 * dc, b]
        for u in range(4):
            if abs(alt[i, u] - d) <= far:
                alt[i, u] = np.nan
            for k in range(K):
                if abs(D[r, c, k] - alt[i, u]) <= far:
                    alt[i, u] = np.nan  # the pixel holds that return already


def move_far_depths(
    surfaces: Surfaces,
    counts,
    background,
    *,
    fwhm: float,
    irf: np.ndarray,
    scales,
    saliency=None,
    threshold=None,
    n_jobs: int = 1,
) -> tuple[Surfaces, int]:
    """Move surfaces far from what their neighbours hold where the own counts favour it.

    Two configurations (:func:`_far_kernel`). A surface no 8-neighbour continues, in a
    pixel whose opposite pairs of 4-neighbours agree on a plane, is either an off-plane
    return of this pixel alone or a background cluster that beat a missed return on the
    plane; a surface whose depth only the neighbours on one side hold (it does not
    continue through the pixel) is either that side's return or a neighbour's spread
    over a missed return of the other side, which two pixels extrapolate. Each
    hypothesis is a return of the neighbours' intensity ``s`` (their mean selected-scale
    signal, per wavelength) at one depth; the own raw counts' Poisson log-likelihoods
    ``L(x) = sum_t y_t log(1 + s g(t - x) / b_t) - s sum_t g(t - x)`` at the surface's
    depth ``d`` and at the alternative ``a`` decide, against a prior: the plane predicts
    one depth where an off-plane return could lie at any of ``T / FWHM`` resolvable
    depths (``log(T / FWHM)``, an Occam factor); the two sides of an edge are equally
    likely, but ``a`` must win by more than one background photon at its peak would
    give (``log(1 + s g_max / b_a)``: a chance photon near the other side's depth does
    not move a pixel whose own return is dim). The surface moves to ``a`` (the
    best-supported alternative) when ``L(d) - L(a) <`` the prior. A bright off-plane
    pixel (own photons many times the background at its depth) keeps its depth; so does
    a depth that continues through the pixel (a line: a thin structure, a real layer's
    edge).

    Returns the surfaces and the number moved. A moved surface's fields follow it as
    extraction computes them for a candidate at that depth (:func:`_window_fields`):
    the window ``offset`` about the new depth, the support ``start`` / ``stop`` shifted
    with it (cut to the window), the raw ``counts`` / ``background`` summed over it, the
    clean ``histograms`` of every scale (``scales``) there, zero outside the support,
    ``signal`` their sums, the selected ``scale_index``, ``presence_llr`` and
    ``presence_z``; with ``saliency`` and ``threshold`` (``Detection.saliency`` and
    ``.threshold``) their ``saliency_mass`` and ``evidence`` too, summed over the new
    support (:func:`~splidar.detection._slopes.support_sums`; without, the old depth's).
    """
    out, moved = _far_moves(surfaces, counts, background, fwhm=fwhm, irf=irf, n_jobs=n_jobs)
    if moved.size == 0:
        return surfaces, 0
    ones = np.ones(moved.size, bool)
    out = _window_fields(out, moved, ones, counts, background, scales, irf, n_jobs=n_jobs)
    return _support_fields(out, moved, saliency, threshold), int(moved.size)


#: Fewest surfaces per thread of :func:`_far_items`.
_FAR_PART = 4096


def _far_moves(
    surfaces: Surfaces, counts, background, *, fwhm: float, irf, memo=None, n_jobs: int = 1
) -> tuple:
    """The far-depth rule of :func:`move_far_depths`: the surfaces with the moved ones'
    ``depth_bin``, ``start``, ``stop``, ``counts`` and ``background`` changed (the other
    fields not yet), and the moved surfaces' indices. ``memo``: a dict kept by the
    caller over calls on the same cube, background and IRF (stage 7's rounds): a
    candidate whose inputs to its score (pixel, depth, alternatives, isolation and the
    sources' ``photons``) all equal one met before takes that score
    (:func:`_memo_far_scores`; the same to the bit). ``n_jobs``: threads of
    :func:`_far_items` (each surface's alternatives its own: the same on any number)."""
    s = surfaces
    R, C = s.image_shape
    S = len(s)
    alt = np.empty((S, 4))
    # the sources' indices in 4 bytes when they fit (the same values): the (S, 4, 4)
    # array is the rule's largest (436 MB at 3.4 M surfaces, new pages at each round)
    kind = np.int32 if S < 2**31 else np.int64
    src = np.empty((S, 4, 4), kind)  # -1 written by _far_items, on its threads
    isolated = np.zeros(S, np.bool_)
    index = np.full((int(R) + 4, int(C) + 4, int(s.n_slots)), -1, kind)  # surface per slot
    depth = np.asarray(s.depth_bin, np.float64)
    D = _far_maps(s.row, s.col, s.slot, depth, index)  # then the surfaces on threads
    args = (s.row, s.col, depth, float(fwhm), alt, src, isolated, index, D)
    on_parts(lambda i0, i1: _far_items(*args, i0, i1), S, min(int(n_jobs), S // _FAR_PART))
    del index, D, args
    none = np.isnan(alt[:, 0])  # no alternative: column by column (np.all's axis-1
    for k in range(1, alt.shape[1]):  # reduction over 4 values took 3x as long)
        none &= np.isnan(alt[:, k])
    cand = np.flatnonzero(~none)
    if cand.size == 0:
        return s, np.zeros(0, np.int64)
    irf = np.atleast_2d(np.asarray(irf, np.float64))
    peak = np.argmax(irf, axis=1)
    T = int(np.shape(counts)[-1])
    plane_prior = np.log(T / max(float(fwhm), 1.0))
    photons = s.photons  # (S, L)
    depth = np.array(s.depth_bin, np.float64)
    W = int(s.histograms.shape[-1])
    moved: list = []
    start, stop = np.array(s.start), np.array(s.stop)
    own_counts = np.array(s.counts, np.float64)
    own_bg = np.array(s.background, np.float64)
    rows, cols = s.row[cand], s.col[cand]
    pix = s.row * C + s.col
    others: dict = {}  # the candidates' pixels' surfaces
    at = np.zeros(int(R) * int(C), bool)  # the candidates' pixels (np.isin's set, unsorted)
    at[pix[cand]] = True
    for j in np.flatnonzero(at[pix]):
        others.setdefault(int(pix[j]), []).append(int(j))
    del at
    args = (alt, src, isolated, photons, depth, irf, peak, counts, background, rows, cols)
    best, to = _memo_far_scores(cand, *args, {} if memo is None else memo)
    prior = np.where(isolated[cand], plane_prior, 0.0)
    go = np.flatnonzero((best < prior) & (to >= 0.0) & (to <= T - 1))
    step = part_size(counts)  # the moving candidates' pixels (n, L, T), a part at a time
    for a in range(0, go.size, step):
        part = go[a : a + step]
        ys = _pixels(counts, rows[part], cols[part])
        bs = np.maximum(background.at(rows[part], cols[part]).astype(np.float64), 1e-6)
        for k, m in enumerate(part):  # in the candidates' order, as in one part
            i = cand[m]
            same = others.get(int(pix[i]), ())  # keep the slots' depth order
            if any((s.slot[j] < s.slot[i]) == (depth[j] >= to[m]) for j in same if j != i):
                continue
            y = ys[k].astype(np.float64)
            _follow(start, stop, own_counts, own_bg, i, depth[i], to[m], y, bs[k], W, T)
            depth[i] = to[m]
            moved.append(int(i))
        del ys, bs
    if not moved:
        return s, np.zeros(0, np.int64)
    out = replace(
        s, depth_bin=depth, start=start, stop=stop, counts=own_counts, background=own_bg,
    )  # fmt: skip
    return out, np.array(moved, np.int64)


def _memo_far_scores(
    cand, alt, src, isolated, photons, depth, irf, peak, counts, background, rows, cols, memo
) -> tuple:
    """:func:`_far_scores` of the candidates ``cand`` (pixels ``rows``, ``cols``), those
    whose inputs equal a key of ``memo`` read from it, the others computed (their
    pixels' counts and background read) and added. A candidate's score is a function of
    its pixel's counts and background, its depth, its alternatives and their sources'
    ``photons`` and its isolation alone (each candidate's pairs are its own; the blocks
    never change a value), so the result is the same to the bit."""
    keys = _far_keys(cand, alt, src, isolated, photons, depth, rows, cols)
    new = np.array([m for m, key in enumerate(keys) if key not in memo], np.int64)
    step = part_size(counts)  # the new candidates' pixels (n, L, T), a part at a time
    for a in range(0, new.size, step):
        part = new[a : a + step]
        ys = _pixels(counts, rows[part], cols[part])
        bs = np.maximum(background.at(rows[part], cols[part]).astype(np.float64), 1e-6)
        got = _far_scores(cand[part], alt, src, isolated, photons, depth, irf, peak, ys, bs)
        memo.update(zip([keys[m] for m in part], zip(*got, strict=True), strict=True))
        del ys, bs
    best, to = np.array([memo[key] for key in keys], np.float64).reshape(-1, 2).T
    return best.copy(), to.copy()


def _far_keys(cand, alt, src, isolated, photons, depth, rows, cols) -> list:
    """The memo's key of each candidate ``cand[m]``: the bytes of its pixel, its depth
    (``+ 0.0``: -0.0 and 0.0 one key, as for float keys), its alternatives, their
    sources' indices, the sources' ``photons`` (zero where a source is -1: the indices
    tell those apart) and its isolation, side by side: equal keys are equal inputs to
    its score. Made for all the candidates at once (no Python loop per candidate)."""
    n = cand.size
    if n == 0:
        return []
    sc = src[cand]  # (n, 4, 4)
    ph = np.asarray(photons, np.float64)[np.maximum(sc, 0)]  # (n, 4, 4, L)
    ph[sc < 0] = 0.0
    parts = (
        np.stack([np.asarray(rows, np.int64), np.asarray(cols, np.int64)], axis=1),
        np.asarray(depth, np.float64)[cand] + 0.0,
        np.asarray(alt, np.float64)[cand],
        sc.astype(np.int64),
        ph,
        np.asarray(isolated[cand], np.int64),
    )
    raw = np.concatenate([np.ascontiguousarray(a).view(np.uint8).reshape(n, -1) for a in parts], 1)
    return raw.view(np.dtype((np.void, raw.shape[1]))).ravel().tolist()


#: Elements of the (pairs, 2, L, T) float64 arrays of :func:`_far_scores`, per block.
_FAR_BLOCK = 1 << 20


def _far_scores(cand, alt, src, isolated, photons, depth, irf, peak, ys, bs) -> tuple:
    """Per candidate ``cand[m]`` of :func:`_far_moves`, the best alternative's score
    ``best[m] = L(d) - L(a)`` (plus, beside an edge, the one-photon term; ``inf`` when it
    has none) and its depth ``to[m]`` (the first of the lowest scores in the order of
    the directions, as one loop over them finds it).

    Every (candidate, alternative) pair at once, in blocks of pairs: each pair's values
    are computed as the former loop computed them one at a time (the neighbours' mean
    intensity summed row by row in their order, the IRF shifted by ``_shifted_irf``, the
    log-likelihoods summed over (L, T) of each depth), so the scores are the same to
    the bit (``tests/test_far_depths.py``). ``ys`` (n, L, T) the candidates' raw counts,
    ``bs`` (n, L, T) their background (float64, >= 1e-6)."""
    n, L, T = ys.shape
    best, to = np.full(n, np.inf), np.full(n, np.nan)
    pm, pu = np.nonzero(~np.isnan(alt[cand]))  # pairs, candidate-major, directions rising
    g_max = irf.max(axis=1)
    step = max(_FAR_BLOCK // max(2 * L * T, 1), 1)
    for a in range(0, pm.size, step):
        m, u = pm[a : a + step], pu[a : a + step]
        i = cand[m]
        j = src[i, u]  # (P, 4); -1: none (2 sources beside an edge, 4 on a plane)
        has = j >= 0
        acc = photons[j[:, 0]].copy()
        for k in range(1, 4):  # as photons[j].mean(axis=0): row by row, then / count
            add = has[:, k]
            acc[add] = acc[add] + photons[j[add, k]]
        sp = np.maximum(acc / has.sum(axis=1)[:, None].astype(acc.dtype), 1e-9)  # (P, L)
        d = np.stack([depth[i], alt[i, u]], axis=1).ravel()
        g = _shifted_irf(irf, peak, d, T).reshape(m.size, 2, L, T)
        y, b, spg = ys[m][:, None].astype(np.float64), bs[m][:, None], sp[:, None, :, None] * g
        ll = (y * np.log1p(spg / b)).sum(axis=(2, 3)) - spg.sum(axis=(2, 3))
        v = ll[:, 0] - ll[:, 1]
        edge = ~isolated[i]
        if edge.any():  # more than one background photon at the alternative's peak
            tb = np.clip(np.rint(alt[i[edge], u[edge]]).astype(np.int64), 0, T - 1)
            bt = bs[m[edge], :, tb]  # (E, L)
            v[edge] += np.log1p(np.max(sp[edge] * g_max / bt, axis=1))
        v = np.where(np.isnan(v), np.inf, v)
        for k in range(m.size):  # the first lowest per candidate, pairs in their order
            if v[k] < best[m[k]]:
                best[m[k]], to[m[k]] = v[k], alt[i[k], u[k]]
    return best, to
