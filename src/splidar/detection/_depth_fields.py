"""The fields of a surface whose depth a stage-7 rule moved, following its depth.

A moved surface's support, raw counts and background follow it (:func:`follow_supports`),
then its window, clean histograms, ``signal``, selected scale and presence statistics
(:func:`_window_fields`) and its ``saliency_mass`` and ``evidence``
(:func:`_support_fields`), computed as extraction computes them for a candidate at that
depth. Shared by the rules of stage 7 (``_7_depths.place_depths``): each rule decides
depths (and moves supports); the window fields follow once, after the last rule. Also
the raw counts of a few pixels (:func:`_pixels`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ._4_map import _local_scale
from ._kernels import _llr_one, _select_scale
from ._result import StoredHistograms, Surfaces
from ._slopes import _row_bands, _zarr_of, pixels_of, support_sums, surface_fields
from ._table import write_rows
from ._threads import on_parts
from ._tiled import is_dask

__all__ = ["follow_supports"]

#: Bytes of the moved pixels' float64 counts and background :func:`follow_supports`
#: holds at a time (all of them at once were 0.3 float32 cubes on the face file at its
#: native bin: 7,001 bins per pixel, about 15,000 surfaces moved).
FOLLOW_BYTES = 2**27


def part_size(counts) -> int:
    """Pixels per part so that their float64 counts and background, ``(n, L, T)`` each,
    hold about :data:`FOLLOW_BYTES` (at least one pixel)."""
    per_pixel = 16 * int(np.prod(np.shape(counts)[2:], dtype=np.int64))
    return max(1, FOLLOW_BYTES // max(per_pixel, 1))


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


def follow_supports(s: Surfaces, idx, old, counts, background) -> Surfaces:
    """The supports (``start``, ``stop``) and own raw ``counts`` / ``background`` of
    surfaces ``idx`` moved from depths ``old`` (S,) to ``s.depth_bin``, each by
    :func:`_follow` (the pixels' raw counts read once, :func:`_pixels`); the other fields
    unchanged. ``idx`` (m,) int: the surfaces moved."""
    idx = np.asarray(idx, np.int64)
    if not idx.size:
        return s
    start, stop = np.array(s.start), np.array(s.stop)
    own_counts = np.array(s.counts, np.float64)
    own_bg = np.array(s.background, np.float64)
    W, T = int(s.histograms.shape[-1]), int(np.shape(counts)[-1])
    old, new = np.asarray(old, np.float64), np.asarray(s.depth_bin, np.float64)
    # the pixels' (L, T) counts and background as float64, a part of them at a time
    # (each surface follows from its own pixel's: the same values in any parts)
    step = part_size(counts)
    for a in range(0, idx.size, step):
        part = idx[a : a + step]
        ys = _pixels(counts, s.row[part], s.col[part]).astype(np.float64)
        bs = np.maximum(background.at(s.row[part], s.col[part]).astype(np.float64), 1e-6)
        for m, i in enumerate(part):
            _follow(start, stop, own_counts, own_bg, i, old[i], new[i], ys[m], bs[m], W, T)
        del ys, bs
    return replace(s, start=start, stop=stop, counts=own_counts, background=own_bg)


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
    copy of the whole array; :func:`~splidar.detection._7_depths.place_depths`)."""
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
    for sel, y, y0 in _row_bands(counts, rows, int(scales[-1]) // 2, cols=cols):

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
