"""Stage 7 (clean-up): move depths that the 4-neighbours' plane places elsewhere.

On a steep slope the 3 x 3 box has a lobe per row and a low-count peak can fall on a
neighbour row's: where the opposite pairs of 4-neighbours place a depth more than half
the FWHM away, the 3 x 3 box is sheared along their plane and the depth moves to that
pool's peak near their prediction, unless the own counts favour the current depth
by more than their noise (:func:`~splidar.detection._quality.align_depths`). Then a
surface far (more than 2 FWHM) from what its neighbours offer moves there when the own
counts favour it against a prior (:func:`move_far_depths`). Adds or removes no surface.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from ._4_map import _local_scale
from ._kernels import _llr_one, _select_scale
from ._quality import _shifted_irf, align_depths
from ._result import STAGES, StoredHistograms, Surfaces
from ._slopes import _row_bands, _zarr_of, pixels_of, support_sums, surface_fields
from ._table import write_rows
from ._threads import on_parts
from ._tiled import is_dask

__all__ = ["DepthAlignment", "align_surface_depths", "move_far_depths"]

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


@dataclass(frozen=True)
class DepthAlignment:
    """The surfaces with aligned depths, how many moved and the time it took."""

    surfaces: Surfaces
    n_moved: int
    seconds: float


def align_surface_depths(
    surfaces: Surfaces,
    *,
    fwhm: float,
    irf: np.ndarray,
    counts=None,
    background=None,
    scales=None,
    saliency=None,
    threshold=None,
    n_jobs: int = 1,
    overwrite: bool = False,
) -> DepthAlignment:
    """Align the depths of ``surfaces`` with their 4-neighbours' plane (see the module).

    Parameters
    ----------
    surfaces : Surfaces
    fwhm : float
        The IRF's FWHM (bins).
    irf : ndarray (L, n_irf)
        The normalised IRF: the background's noise on the clean histograms (the matched
        filter's response) is ``b sum_t g(t)^2`` per bin.
    counts : array_like (rows, cols, L, T), optional
        The cube's raw counts; with ``background`` (:class:`Background`), the far depths
        are re-decided too (:func:`move_far_depths`, when ``FAR_DEPTHS``) and every
        moved surface's fields follow its depth (:func:`_moved_fields`).
    background : Background, optional
    scales : ndarray (Q,) int, optional
        The box sizes of the clean histograms (``Detection.scales``): a moved surface's
        histograms are recomputed at its new depth with them. Required with ``counts``.
    saliency, threshold : optional
        ``Detection.saliency`` and ``.threshold``: the ``saliency_mass`` and ``evidence``
        of a surface whose support moved are summed over the new support.
    n_jobs : int
        Threads for the moved surfaces' fields (:func:`_window_fields`); the result does
        not depend on it.
    overwrite : bool
        Write the moved surfaces' histograms into ``surfaces.histograms`` itself (the
        input's array changes) instead of a copy of the ``(S, Q, L, W)`` array: for a
        caller that holds no other use of it (``detect``; the same result).

    Returns
    -------
    DepthAlignment
        ``surfaces.moved_by`` holds ``"align_depths"``'s index in ``STAGES`` for the
        surfaces it moved.
    """
    t0 = time.perf_counter()
    s = surfaces
    g2 = np.sum(np.atleast_2d(np.asarray(irf, np.float64)) ** 2, axis=-1)  # (L,)
    width = np.maximum(s.stop - s.start, 1).astype(np.float64)
    b = np.asarray(s.background, np.float64) / width[:, None]  # per bin, (S, L)
    noise = np.sqrt(2.0 * np.maximum(b, 0.0) @ g2)
    depth, _ = align_depths(
        s.row, s.col, s.slot, s.depth_bin, s.offset, s.histograms[:, 0].sum(axis=1),
        image_shape=s.image_shape, n_slots=s.n_slots, fwhm=fwhm, noise=noise, z_own=OWN_Z,
    )  # fmt: skip
    out = replace(s, depth_bin=np.asarray(depth).astype(np.float64))
    far = np.zeros(0, np.int64)
    if FAR_DEPTHS and counts is not None and background is not None and scales is not None:
        out, far = _far_moves(out, counts, background, fwhm=fwhm, irf=irf)
        out, refit = _moved_fields(
            out, s.depth_bin, far, counts, background, scales, irf, n_jobs=n_jobs,
            overwrite=overwrite,
        )  # fmt: skip
        out = _support_fields(out, refit, saliency, threshold)
    moved = np.flatnonzero(out.depth_bin != np.asarray(s.depth_bin, np.float64))
    code = np.full(len(out), -1, np.int8) if out.moved_by is None else np.array(out.moved_by)
    code[moved] = STAGES.index("align_depths")
    out = replace(out, moved_by=code)
    return DepthAlignment(out, int(moved.size), time.perf_counter() - t0)


def _moved_fields(
    s: Surfaces, old, far, counts, background, scales, irf, *, n_jobs=1, overwrite=False
) -> tuple:
    """Every field of the surfaces stage 7 moved at their new depths (``old``: the
    depths before it; ``far``: those :func:`_far_moves` moved, whose supports and own
    counts followed already). A depth the sheared pool moved inside its support keeps
    its window and support; only the presence statistics follow it. One it moved out
    of its support is treated as a far move: its support (shifted with the depth, cut
    to the new window), own counts and window follow it. Returns the surfaces and the
    indices of those whose support moved (``far`` and the latter: their
    ``saliency_mass`` and ``evidence`` are recomputed by :func:`_support_fields`)."""
    d = np.asarray(s.depth_bin, np.float64)
    sheared = np.setdiff1d(np.flatnonzero(d != np.asarray(old, np.float64)), far)
    out_of = sheared[(d[sheared] < s.start[sheared]) | (d[sheared] >= s.stop[sheared])]
    if out_of.size:
        start, stop = np.array(s.start), np.array(s.stop)
        own_counts = np.array(s.counts, np.float64)
        own_bg = np.array(s.background, np.float64)
        ys = _pixels(counts, s.row[out_of], s.col[out_of]).astype(np.float64)
        bs = np.maximum(background.at(s.row[out_of], s.col[out_of]).astype(np.float64), 1e-6)
        W, T = int(s.histograms.shape[-1]), int(np.shape(counts)[-1])
        for m, i in enumerate(out_of):
            _follow(start, stop, own_counts, own_bg, i, old[i], d[i], ys[m], bs[m], W, T)
        s = replace(s, start=start, stop=stop, counts=own_counts, background=own_bg)
    refit = np.union1d(far, out_of)
    idx = np.union1d(refit, sheared)
    if not idx.size:
        return s, refit
    refit_m = np.isin(idx, refit)
    out = _window_fields(
        s, idx, refit_m, counts, background, scales, irf, n_jobs=n_jobs, overwrite=overwrite
    )
    return out, refit


#: One-sided alternatives extrapolate a neighbour's surface over two pixels along one of
#: the four directions; the two pixels must hold the same return within this many FWHM
#: (the slope the extrapolation trusts: 4.5 bins per pixel at FWHM 3 bins).
EXTRAPOLATE_FWHM = 1.5


@njit(cache=True, nogil=True)
def _far_kernel(row, col, slot, depth, R, C, K, fwhm, alt, src, isolated):
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
    D = np.full((R + 4, C + 4, K), np.nan)
    index = np.full((R + 4, C + 4, K), -1, np.int64)
    for i in range(row.size):
        D[row[i] + 2, col[i] + 2, slot[i]] = depth[i]
        index[row[i] + 2, col[i] + 2, slot[i]] = i
    far = 2.0 * fwhm
    for i in range(row.size):
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


def _pixels(counts, rows, cols) -> np.ndarray:
    """The raw counts of a few pixels, ``(n, L, T)``: read at once from a Dask array.

    A Dask array that only reads a Zarr array (``splidar.load`` of a Zarr cube) is read
    by this process from the Zarr array itself, a chunk of rows at a time (each chunk
    holding a pixel decoded once, as Dask's ``vindex`` does), not through the active
    scheduler: on a cluster the workers' reads were serialised and sent over.
    """
    if is_dask(counts):
        kept = pixels_of(counts, rows, cols)  # kept sparse during the detection
        if kept is not None:
            return kept
        z = _zarr_of(counts)
        if z is not None:
            try:
                return _pixels_by_chunk(z, counts.chunks[0], rows, cols)
            except OSError:  # a path the workers see and this process does not
                pass
        return np.asarray(counts.vindex[rows, cols].compute())
    if isinstance(counts, np.ndarray):
        return counts[rows, cols]
    return np.stack([np.asarray(counts[r, c]) for r, c in zip(rows, cols, strict=True)])


def _pixels_by_chunk(z, row_chunks, rows, cols) -> np.ndarray:
    """Pixels ``(rows, cols)`` of the Zarr array ``z``, read a chunk of rows at a time."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    edges = np.cumsum((0,) + tuple(int(n) for n in row_chunks))
    band = np.searchsorted(edges, rows, side="right") - 1
    out = np.empty((rows.size,) + tuple(z.shape[2:]), z.dtype)
    for b in np.unique(band):
        sel = np.flatnonzero(band == b)
        y = np.asarray(z[int(edges[b]) : int(edges[b + 1])])
        out[sel] = y[rows[sel] - edges[b], cols[sel]]
    return out


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
    out, moved = _far_moves(surfaces, counts, background, fwhm=fwhm, irf=irf)
    if moved.size == 0:
        return surfaces, 0
    ones = np.ones(moved.size, bool)
    out = _window_fields(out, moved, ones, counts, background, scales, irf, n_jobs=n_jobs)
    return _support_fields(out, moved, saliency, threshold), int(moved.size)


def _far_moves(surfaces: Surfaces, counts, background, *, fwhm: float, irf) -> tuple:
    """The far-depth rule of :func:`move_far_depths`: the surfaces with the moved ones'
    ``depth_bin``, ``start``, ``stop``, ``counts`` and ``background`` changed (the other
    fields not yet), and the moved surfaces' indices."""
    s = surfaces
    R, C = s.image_shape
    S = len(s)
    alt = np.empty((S, 4))
    src = np.full((S, 4, 4), -1, np.int64)
    isolated = np.zeros(S, np.bool_)
    _far_kernel(
        s.row, s.col, s.slot, np.asarray(s.depth_bin, np.float64), int(R), int(C),
        int(s.n_slots), float(fwhm), alt, src, isolated,
    )  # fmt: skip
    cand = np.flatnonzero(~np.all(np.isnan(alt), axis=1))
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
    for j in np.flatnonzero(np.isin(pix, pix[cand])):
        others.setdefault(int(pix[j]), []).append(int(j))
    ys = _pixels(counts, rows, cols)  # (n, L, T), the candidates' pixels only
    bs = np.maximum(background.at(rows, cols).astype(np.float64), 1e-6)
    for m, i in enumerate(cand):
        y, b = ys[m : m + 1].astype(np.float64), bs[m : m + 1]
        best, to = np.inf, np.nan
        for u in np.flatnonzero(~np.isnan(alt[i])):
            j = src[i, u][src[i, u] >= 0]
            sp = np.maximum(photons[j].mean(axis=0), 1e-9)[None, :, None]  # (1, L, 1)
            g = _shifted_irf(irf, peak, np.array([depth[i], alt[i, u]]), T)  # (2, L, T)
            ll = (y * np.log1p(sp * g / b)).sum(axis=(1, 2)) - (sp * g).sum(axis=(1, 2))
            v = ll[0] - ll[1]
            if not isolated[i]:
                # more than one background photon at the alternative's peak would give
                tb = min(max(int(np.rint(alt[i, u])), 0), T - 1)
                v += np.log1p(np.max(sp[0, :, 0] * irf.max(axis=1) / b[0, :, tb]))
            if v < best:
                best, to = v, alt[i, u]
        if best >= (plane_prior if isolated[i] else 0.0) or not 0.0 <= to <= T - 1:
            continue
        same = others.get(int(pix[i]), ())  # keep the slots' depth order
        if any((s.slot[j] < s.slot[i]) == (depth[j] >= to) for j in same if j != i):
            continue
        _follow(start, stop, own_counts, own_bg, i, depth[i], to, y[0], b[0], W, T)
        depth[i] = to
        moved.append(int(i))
    if not moved:
        return s, np.zeros(0, np.int64)
    out = replace(
        s, depth_bin=depth, start=start, stop=stop, counts=own_counts, background=own_bg,
    )  # fmt: skip
    return out, np.array(moved, np.int64)


def _follow(start, stop, own_counts, own_bg, i, old, to, y, b, W, T) -> None:
    """The support of surface ``i`` moved from depth ``old`` to ``to``, in place: shifted
    with the depth and cut to the new window (the extraction's rule,
    ``extract_surfaces``: the window about the integer depth), its raw counts and
    background (``y``, ``b``: the pixel's (L, T)) summed over it (``reconstruct`` takes
    the IRF's fraction over the support)."""
    shift = int(np.rint(to - old))
    off = min(max(int(np.rint(to)) - W // 2, 0), max(T - W, 0))
    start[i] = max(start[i] + shift, 0, off)
    stop[i] = max(min(stop[i] + shift, T, off + W), start[i])
    own_counts[i] = y[:, start[i] : stop[i]].sum(axis=-1)
    own_bg[i] = b[:, start[i] : stop[i]].sum(axis=-1)


def _window_fields(
    s: Surfaces,
    idx,
    refit,
    counts,
    background,
    scales,
    irf,
    *,
    n_jobs: int = 1,
    overwrite: bool = False,
) -> Surfaces:
    """``offset``, clean ``histograms``, ``signal``, ``scale_index``, ``presence_llr``
    and ``presence_z`` of surfaces ``idx`` recomputed at their depths over their
    supports, as extraction computes them; where ``refit`` (``idx.size``, bool) is
    False, the surface keeps its window (``offset``, histograms, ``signal``,
    ``scale_index``: its depth moved inside its support) and only the presence
    statistics, which depend on the depth, are recomputed.

    The histograms are :func:`~splidar.detection._slopes.surface_fields`' (the slopes
    pass's extraction from the raw counts: ``max(Box_q(Y (*) g) - bhat, 0)`` of every
    scale over the window of ``W`` bins about the integer depth, ``eq:background_final``)
    set to zero outside the support as in ``extract_surfaces``; ``signal`` their sums
    over time; ``scale_index`` the selected scale (``_select_scale``, ``eq:scale_sel``);
    ``presence_llr`` the own counts' log-likelihood ratio with the local scale's signal
    (``_llr_one``, as ``extract_surfaces``) over the surface's window; ``presence_z``
    the local scale's z at the depth (``surface_fields``, as ``_local_z``). The raw
    counts are read a band of rows at a time from a lazy cube (``_row_bands``); each
    band's surfaces are split over ``n_jobs`` threads (``surface_fields`` releases the
    GIL; every surface's fields are computed alone, so the split changes no value).
    With ``overwrite``, an in-memory ``s.histograms`` gets the new rows in place (no
    copy of the whole array; :func:`align_surface_depths`)."""
    scales = np.asarray(scales, np.int64)
    refit = np.asarray(refit, bool)
    irf = np.ascontiguousarray(np.atleast_2d(np.asarray(irf, np.float64)))
    L, T = background.temporal.shape
    Q, W = scales.size, int(s.histograms.shape[-1])
    tm = background.temporal
    dev = (tm - tm.mean(axis=-1, keepdims=True)).astype(np.float32)  # as stage 1
    sp = np.ascontiguousarray(background.spatial, np.float32)
    peak = irf.argmax(axis=1).astype(np.int64)
    gsq = (irf**2).sum(axis=1)
    qloc = _local_scale(scales)
    n = idx.size
    o = dict(
        offset=np.empty(n, np.int64), histograms=np.empty((n, Q, L, W), np.float32),
        signal=np.empty((n, Q, L)), counts=np.empty((n, L)), background=np.empty((n, L)),
        presence_llr=np.empty(n), presence_z=np.empty(n),
    )  # fmt: skip
    raw = np.zeros((n, L, W))
    rows, cols = s.row[idx], s.col[idx]
    depth = np.asarray(s.depth_bin, np.float64)[idx]
    # the window the presence test reads: the new one, or the surface's own (kept)
    win = np.asarray(s.offset, np.int64)[idx].copy()
    s_pool = np.zeros((n, L))
    for sel, y, y0 in _row_bands(counts, rows, int(scales[-1]) // 2):

        def fields(a, b, sel=sel, y=y, y0=y0):
            ss = sel[a:b]
            part = {k: v[ss] for k, v in o.items()}
            surface_fields(
                y, int(y0), sp, dev, rows[ss], cols[ss], depth[ss], s_pool[ss], scales, irf,
                peak, gsq, W, int(qloc), *part.values(),
            )  # fmt: skip
            for k, v in part.items():
                o[k][ss] = v

        on_parts(fields, sel.size, n_jobs if sel.size >= 64 else 1)
        for m in sel:
            if refit[m]:
                win[m] = o["offset"][m]
            raw[m] = y[rows[m] - y0, cols[m], :, win[m] : win[m] + W]
    hist = o["histograms"]
    qbar = np.array(s.scale_index)
    signal = np.array(s.signal, np.float64)
    tot, d_q = np.empty(W, np.float32), np.empty(Q, np.int64)
    for m, i in enumerate(idx):
        inside = (win[m] + np.arange(W) >= s.start[i]) & (win[m] + np.arange(W) < s.stop[i])
        raw[m][:, ~inside] = 0.0
        if refit[m]:
            hist[m][..., ~inside] = 0.0  # zero outside the support (eq:background_final)
            # the selected scale (eq:scale_sel) on the clean responses summed over L
            qbar[i] = _select_scale(hist[m].sum(axis=1, dtype=np.float32), tot, d_q)
            signal[i] = hist[m].sum(axis=-1, dtype=np.float64)
        bh = np.maximum(sp[rows[m], cols[m]][:, None] + dev[:, win[m] : win[m] + W], 0)
        o["presence_llr"][m] = _llr_one(
            raw[m], bh.astype(np.float32), inside, depth[m] - win[m],
            np.ascontiguousarray(signal[i, qloc], np.float64), irf, peak.astype(np.float64),
            L, W,
        )  # fmt: skip
    new = idx[refit]
    offset = np.array(s.offset)
    offset[new] = o["offset"][refit]
    if not new.size:
        histograms = s.histograms
    elif isinstance(s.histograms, StoredHistograms):  # the detection's own store
        write_rows(s.histograms.array, idx[refit], hist[refit])  # a chunk written once
        histograms = s.histograms
    elif overwrite and isinstance(s.histograms, np.ndarray) and s.histograms.flags.writeable:
        histograms = s.histograms  # the caller's own array (no copy of every surface's)
        histograms[new] = hist[refit]
    else:
        histograms = np.array(s.histograms)
        histograms[new] = hist[refit]
    llr = z = None
    if s.presence_llr is not None:
        llr = np.array(s.presence_llr, np.float64)
        llr[idx] = o["presence_llr"]
    if s.presence_z is not None:  # the local scale's z at the depth (as _local_z)
        z = np.array(s.presence_z, np.float64)
        z[idx] = o["presence_z"]
    return replace(
        s, offset=offset, histograms=histograms, signal=signal, scale_index=qbar,
        presence_llr=llr, presence_z=z,
    )  # fmt: skip


def _support_fields(s: Surfaces, idx, saliency, threshold) -> Surfaces:
    """``saliency_mass`` and ``evidence`` of surfaces ``idx`` summed over their supports
    (:func:`~splidar.detection._slopes.support_sums`, as the slope pass computes its
    surfaces': the map's run at a depth a surface moved to may not exist); unchanged
    without ``saliency``."""
    if saliency is None or threshold is None or not np.size(idx):
        return s
    mass, ev = support_sums(saliency, threshold, s.row[idx], s.col[idx], s.start[idx], s.stop[idx])
    new_mass = np.array(s.saliency_mass, np.float64)
    new_mass[idx] = mass
    new_ev = None
    if s.evidence is not None:
        new_ev = np.array(s.evidence, np.float64)
        new_ev[idx] = ev
    return replace(s, saliency_mass=new_mass, evidence=new_ev)
