"""Stage 4: the 3D map and its candidate surfaces, in one pass over blocks of rows.

For each block of image rows (with a halo of ``max k // 2`` rows): the saliency (stage
2), the threshold from the null (stage 3), the binary map ``M``, runs of ``M`` split
between resolved peaks into candidates; a candidate whose evidence beats the null's is
extracted (clean histograms at every scale, ``eq:background_final``; selected scale,
``eq:scale_sel``; sub-bin depth) and tested for presence in its own pixel. Saliency, map
and candidates are computed together so that the cube is read and matched-filtered once
and no ``(rows, cols, L, T)`` float array is ever held whole.
"""

from __future__ import annotations

import dataclasses
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numba import njit

from .._arrays import FLAT_CHUNK_KEYS, _raw_chunks, write_raw_chunk
from .._validation import SplidarError, describe
from ._2_saliency import STRIP_COLS, SaliencyFilters, block_saliency
from ._3_null import NullCalibration, split_rule
from ._kernels import ORDER_BAND, extract_surfaces, find_segments, threshold_pass
from ._result import DataReduction
from ._table import CandidateTable, _rank_in_pixel, stage_code
from ._threshold import ThresholdField
from ._windows import OwnBackground, SupportWindows

__all__ = ["CandidateMap", "MapOptions", "assemble_map", "map_candidates", "map_plan"]

#: Presence test (``presence="auto"/"adaptive"``): the local scale (finest above 1
#: pixel) must respond at a candidate's depth with this Poisson z: 3 sigma, about one
#: false pass per 700 tested depths of pure background. Measured: docs/detection.md.
PRESENCE_Z = 3.0
#: Presence test: the own pixel's counts reject a candidate when they favour "no return"
#: by more than this natural-log likelihood ratio (3 nats, odds of 20:1): weak own
#: counts never reject a surface the pooled scales show. Measured: docs/detection.md.
PRESENCE_LLR = 3.0
#: Presence test: a pixel's further candidates need own counts favouring them (log-ratio
#: >= 0): 0 rather than 1 since the spill-over pass catches the extras (net scene PPP 10,
#: SBR 1: F_true 0.941 -> 0.955, false 0.029 -> 0.037 per true one). docs/detection.md.
PRESENCE_SECONDARY = 0.0
#: A run of the map is split between two peaks when the response dips below this
#: fraction of the smaller peak between them (half: two resolved returns).
SPLIT_RATIO = 0.5
#: A segment of that response can be split again where the own pixel's matched-filter
#: response (the finest scale, whose dip the coarse boxes do not fill) has a second peak
#: at least ``min_separation`` from a stronger one and the pixel's photons in its
#: half-peak window exceed what the background and the stronger return's tail bring
#: there by a Poisson z of ``sqrt(SPLIT_Z^2 + 2 ln n)`` (``n`` bins searched); the
#: null's candidates are then split the same way (``_kernels._fine_split``). The tail:
#: the larger of the IRF's and the data's own returns' (``_3_null.data_tail``). On
#: (3) with the three rules below: two returns 2.5 FWHM apart (PPP 10, SBR 1) go from
#: F_true 0.684 to 0.855; the face, tower and 21 km data keep their counts (+0.05 % at
#: most, default IRF or ``irf="estimate-shape"``). 0: off (session 13's segments, bit
#: for bit). Measured: benchmarks/README.md (branches close19, close19b, close19c,
#: close20).
SPLIT_Z = 3.0
#: The fine split looks for a second return only within this many FWHMs of a stronger
#: one (0: anywhere in the segment): where the coarse scales merge two returns (3 FWHM
#: apart they split them already); beyond, its finds on the tower were bumps inside
#: long segments (tower +1.7 -> +0.7 % with the shape IRF, close pairs kept).
SPLIT_REACH = 3.0
#: The fine split takes the first return's tail as up to ``1 + SPLIT_TAIL_SLACK`` times
#: the measured one (``split_rule(slack=)``): the pooled tail is an average and real
#: pixels' tails vary about it (the tower's), which matters beside bright returns
#: only (a weak return's tail is a fraction of a photon either way). 3: tower +1.1 ->
#: +0.03 % with the default IRF, close pairs 0.856 -> 0.855; 1: +0.31 %, 2: +0.27 %.
SPLIT_TAIL_SLACK = 3.0
#: A return the fine split added is kept only where a 4-neighbour pixel has a kept
#: candidate within one FWHM of its depth (1), and that neighbour shows a pair too (2);
#: 0: always. The map pass only (``_4_map._table``, whole image): the null counts
#: every split part, so its false-alarm rate stays an upper bound.
SPLIT_COHERENT = 1
#: The fine split's test pooled over the 3 x 3 neighbourhood (1) for a weaker return in
#: front of a stronger one that the own pixel's photons show by ``SPLIT_Z`` at its one
#: place but not by the look-elsewhere bound (``split_rule(pool=)``,
#: ``_kernels._fine_split``); 0: off. Behind a return never (its tail lies there), and
#: the stronger part must beat the front return's tail by ``SPLIT_Z`` (else it is that
#: tail: a single surface with a 25-bin exponential tail 76 -> 87 false surfaces
#: without this, 76 with). A net 2-3 FWHM before a wall, tailed IRFs: net F_true
#: T4096 0.63 -> 0.75, L4 0.77 -> 0.83; two surfaces 2 / 2.5 FWHM apart 0.743 ->
#: 0.758 / 0.855 -> 0.889; bench_detection false 5,509 -> 5,515; tower +0.48 %
#: (benchmarks/README.md, gap31 and gap31b).
SPLIT_POOL = 1
#: Depth by the intersection of confidence intervals over the scales (ICI) rather than
#: the selected scale's (``eq:scale_sel``): mean depth error -25 to -48 % in every cell
#: measured (single surface PPP 4, SBR 0.25: 0.60 -> 0.34 bins). docs/detection.md.
REFINE = True
#: z the own pixel's matched-filter peak needs to take part in the depth refinement
#: (ICI) and to centre a long run's window: a 3-sigma peak, rarely noise in one window.
REFINE_Z = 3.0
#: Bins per depth band of the order in which candidates are extracted (speed only; the
#: extraction kernel caches column sums per band and row).
_ORDER_BAND = ORDER_BAND
#: Per-candidate arrays of windows the extraction kernel leaves in the order it computed
#: the candidates (row ``i``: candidate ``order[i]``; see :func:`_extract`): written one
#: after the other instead of scattered (5 % of the kernel), and gathered only for the
#: candidates kept, by their slot.
_BY_SLOT = ("histograms", "signal", "own_counts", "own_background")
#: Half-width, in standard errors, of the ICI depth intervals (``refine``): 2 keeps a
#: true depth inside its interval 95 % of the time.
ICI_GAMMA = 2.0
#: Placeholder for the fine response's precomputed arrays (read from ``c_ext`` here).
_NO_FINE = np.empty((0, 0, 0), np.float32)


@dataclass(frozen=True)
class MapOptions:
    """How the map pass splits, extracts and tests candidates (see :func:`splidar.detect`)."""

    min_separation: int
    split_ratio: float
    presence: str
    presence_z: float
    presence_llr: float
    secondary_llr: float
    refine: bool
    keep_suspects: bool
    max_surfaces: int
    width: int


@dataclass(frozen=True)
class CandidateMap:
    """Result of the map pass.

    Attributes
    ----------
    saliency : ndarray or zarr array (rows, cols, T), float32
    mask : ndarray or zarr array (rows, cols, T), bool
    spatial : ndarray (rows, cols, L), float32
        The background level ``b_{n,l}`` (``eq:background_2``).
    threshold : float, ndarray, ThresholdField or zarr array
    candidates : CandidateTable
        Every candidate that passed the evidence test, ``keep`` set by the presence
        test (rejected ones stay in the table while their pixel has room, for the
        restoring passes).
    histograms : tuple of ndarray
        Per block, the clean histograms of its candidates (gathered once, for the
        selected surfaces).
    reduction : DataReduction
    n_candidates, n_rejected : int
        Runs of the map found, and those dropped by the evidence or presence tests.
    block_rows, width : int
        Rows per block; histogram window W (bins).
    """

    saliency: object
    mask: object
    spatial: np.ndarray
    threshold: object
    candidates: CandidateTable
    histograms: tuple
    reduction: DataReduction
    n_candidates: int
    n_rejected: int
    block_rows: int
    width: int


def _store_boxes(scales: np.ndarray, width: int, n_bins: int) -> bool:
    """Whether the saliency pass should keep its box means for surface extraction.

    Keeping them costs ``Qb`` float32 writes per voxel (``Qb`` scales above 1 pixel);
    summing the boxes about each candidate costs ``sum_q k_q^2`` additions per window
    bin, for a few (about 3) candidates per pixel, each ``width`` bins long. A write
    to memory costs about 5 additions (measured on the 200 x 200 x 4 x 1500 and
    Art-size cubes: keeping them is 1.3x slower on the first, 2.5x faster on the
    second), hence the rule. It depends on the sizes only, never on the data or the
    blocks, so every block takes the same path (the two differ by float32 rounding).
    """
    qb = int((scales > 1).sum())
    if qb == 0:
        return False
    return 3 * width * float((scales.astype(np.float64) ** 2).sum()) >= 5 * n_bins * qb


def _local_scale(scales: np.ndarray) -> int:
    """Index of the local scale of the presence check: the finest one above 1 pixel."""
    above = np.flatnonzero(scales > 1)
    return int(above[0]) if above.size else 0


def _extract(
    y, c_ext, box, e0, r0, ce0, c0, rows, cols, start, stop, peak, mass, sp_blk, ctx, opts
):
    """Per-candidate clean histograms at every scale, scale selection, depth, presence.

    Runs the numba kernel :func:`~splidar.detection._kernels.extract_surfaces` over the
    candidates (split over ``ctx.workers`` threads; each candidate is computed the same
    way whatever the split). For each candidate: box means of the correlated block at
    every scale (``box``, written by the saliency pass) over a window of ``width`` bins
    about its peak, minus ``bhat``
    (``eq:background_3``), kept positive inside the support (``eq:background_final``);
    the global and per-scale depths (argmax of the clean matched-filter response,
    ``eq:depth_global`` / ``eq:depth_scale``) and the selected scale (``eq:scale_sel``);
    a sub-bin depth (parabola through the selected scale's response, or the finest
    scale's when significant and ``refine``); own-pixel counts, background and the
    presence statistics (own-pixel log-likelihood ratio, local-scale z, predicted z).
    ``rows`` and ``cols`` are block rows and image columns; ``y`` and ``c_ext`` start at
    image row ``e0`` and column ``ce0``, ``sp_blk`` and ``box`` at ``r0`` and ``c0``.
    """
    R, C = opts["image_shape"]
    L, T = ctx.dev.shape
    Q = ctx.scales.size
    W = opts["width"]
    S = rows.size
    qloc = _local_scale(ctx.scales)
    want_sel = opts["presence"] == "pixel"
    o = dict(
        depth_bin=np.empty(S, np.float64),
        start=np.empty(S, np.int64),
        stop=np.empty(S, np.int64),
        scale_index=np.empty(S, np.int64),
        offset=np.empty(S, np.int64),
        histograms=np.empty((S, Q, L, W), np.float32),
        signal=np.empty((S, Q, L), np.float64),
        counts=np.empty((S, L), np.float64),
        background=np.empty((S, L), np.float64),
        presence_llr=np.empty(S, np.float64),
        presence_z=np.empty(S, np.float64),
    )
    zpred = np.empty(S, np.float64)
    llr_sel = np.empty(S if want_sel else 0, np.float64)
    # own-pixel counts and background over the window, for the global spill-over and
    # isolated-candidate passes (_quality.py); not part of Surfaces
    o["own_counts"] = np.empty((S, L, W), np.int32)
    o["own_background"] = np.empty((S, L, W), np.float32)
    bidx = np.full(ctx.scales.size, -1, np.int64)
    if box is None:  # boxes summed about each candidate by the kernel
        box = np.empty((L, 0, 1, 1, 1), np.float32)
    else:
        bidx[ctx.scales > 1] = np.arange(int((ctx.scales > 1).sum()))
    args = (
        y,
        c_ext,
        box,
        bidx,
        int(e0),
        int(r0),
        int(ce0),
        int(c0),
        np.ascontiguousarray(rows, np.int64),
        np.ascontiguousarray(cols, np.int64),
        np.ascontiguousarray(start, np.int64),
        np.ascontiguousarray(stop, np.int64),
        np.ascontiguousarray(peak, np.int64),
        sp_blk,
        ctx.dev,
        ctx.scales,
        np.ascontiguousarray(ctx.gsq, np.float64),
        np.ascontiguousarray(ctx.corr.irf, np.float64),
        np.ascontiguousarray(ctx.corr.peak, np.float64),
        int(W),
        int(R),
        int(C),
        bool(opts["refine"]),
        float(opts["refine_z"]),
        np.ascontiguousarray(ctx.fisher, np.float64),
        float(opts["ici_gamma"]),
        int(qloc),
        want_sel,
    )
    outs = (
        o["depth_bin"],
        o["start"],
        o["stop"],
        o["scale_index"],
        o["offset"],
        o["histograms"],
        o["signal"],
        o["counts"],
        o["background"],
        o["presence_llr"],
        o["presence_z"],
        zpred,
        llr_sel,
        o["own_counts"],
        o["own_background"],
    )
    n_threads = max(1, min(int(ctx.workers), S // 2000))
    # candidates taken by depth band, then raster order: consecutive ones read the same
    # stretch of t from neighbouring pixels (in cache; 23 % faster on the 200 x 200 x 4
    # x 1500 cube). Each candidate is computed the same way in any order.
    order = np.lexsort((cols, rows, np.asarray(peak) // _ORDER_BAND)).astype(np.int64)
    if n_threads == 1:
        extract_surfaces(*args, order, 0, S, *outs)
    else:
        cuts = np.linspace(0, S, n_threads + 1).round().astype(np.int64)
        with ThreadPoolExecutor(n_threads) as ex:
            list(
                ex.map(
                    lambda ab: extract_surfaces(*args, order, int(ab[0]), int(ab[1]), *outs),
                    zip(cuts[:-1], cuts[1:], strict=True),
                )
            )
    # the kernel wrote candidate order[i] at row i: the per-candidate values back to the
    # candidates' order, the arrays of windows (_BY_SLOT) left where they are (their
    # kept rows are gathered once, by slot, in _finish_block)
    slot = np.empty(S, np.int64)
    slot[order] = np.arange(S, dtype=np.int64)
    for k in o:
        if k not in _BY_SLOT:
            o[k] = o[k][slot]
    zpred = zpred[slot]
    llr_sel = llr_sel[slot] if want_sel else llr_sel
    o["_slot"] = slot
    keep = np.ones(S, bool)
    zloc, llr = o["presence_z"], o["presence_llr"]
    if opts["presence"] == "pixel" and S:
        keep = llr_sel >= 0.0
    elif opts["presence"] in ("auto", "adaptive") and S:
        zreq = opts["presence_z"]
        if opts["presence"] == "adaptive":
            # presence_z, or presence_z below the predicted z when the neighbourhood
            # is too dim for a true return to reach presence_z
            zreq = np.minimum(zreq, zpred - opts["presence_z"])
        keep = (zloc >= zreq) & (llr >= -opts["presence_llr"])
    o["row"] = rows + r0
    o["col"] = cols
    o["saliency_mass"] = mass
    return o, keep


@dataclass
class _BlockOut:
    n_voxels: int
    n_photons_kept: int
    n_photons: int
    surf: dict
    n_candidates: int
    n_rejected: int
    # the block's histograms of every extracted candidate (not subset: the large array
    # is gathered once, for the selected surfaces) and the rows of the kept ones
    histograms: np.ndarray = None
    kept: np.ndarray = None


def _buffer(work, key: str, shape, dtype) -> np.ndarray:
    """A ``shape`` view of the reused work buffer ``work[key]`` (a new array without)."""
    if work is None or key not in work:
        return np.empty(shape, dtype)
    return work[key].reshape(-1)[: int(np.prod(shape))].reshape(shape)


def _put(dst, r0: int, c0: int, value: np.ndarray) -> None:
    """``dst[r0:, c0:] = value`` (``value`` an ``(r, c, ...)`` array); a Zarr array is
    written one chunk at a time.

    Zarr (3.x) takes a write that covers exactly one chunk as it is; a write over several
    chunks makes each one a new fill-value array and copies its part in (two passes over
    the memory more than the write itself: on the tiles of a stored map pass, about a
    sixth of a worker's time). The pieces are whole chunks wherever ``value`` covers
    them (rows and columns cut at the chunk grid), so the stored values are the same.
    A whole chunk of an array stored raw in a local folder (the saliency) is written as
    its chunk file (:func:`~splidar._arrays.write_raw_chunk`: the same bytes, without
    Zarr's per-chunk pipeline); any other piece through Zarr.
    """
    r1, c1 = r0 + value.shape[0], c0 + value.shape[1]
    chunks = getattr(dst, "chunks", None) if type(dst).__module__.startswith("zarr") else None
    if chunks is None:
        dst[r0:r1, c0:c1] = value
        return
    raw = _raw_chunks(dst)
    cr, cc = int(chunks[0]), int(chunks[1])
    for a in range(r0, r1, cr) if r0 % cr == 0 else [r0, *range(r0 - r0 % cr + cr, r1, cr)]:
        a1 = min(r1, a - a % cr + cr)
        for b in range(c0, c1, cc) if c0 % cc == 0 else [c0, *range(c0 - c0 % cc + cc, c1, cc)]:
            b1 = min(c1, b - b % cc + cc)
            piece = value[a - r0 : a1 - r0, b - c0 : b1 - c0]
            if raw is not None and piece.shape == raw[1] and a % cr == 0 and b % cc == 0:
                write_raw_chunk(raw, (a // cr, b // cc) + (0,) * (piece.ndim - 2), piece)
            else:
                dst[a:a1, b:b1] = piece


def _block(
    y, c_ext, e0, r0, r1, ctx: SaliencyFilters, table, opts, out, work=None, cols=None
) -> _BlockOut:
    """Saliency, map and surfaces of image rows ``[r0, r1)`` (and columns ``[c0, c1)``).

    ``y`` and ``c_ext`` hold the raw and correlated rows ``[e0, e0 + len(y))`` (the
    block with its halo); ``out`` the preallocated image-size outputs written here
    (``out[k][r0:r1, c0:c1] = x``). ``cols = (ce0, c0, c1, carry)``: the block holds
    image columns ``[ce0, ce0 + y.shape[1])`` and its own are ``[c0, c1)``; ``carry``
    (L, r1 - r0, Q, T) float64, the box filters' running column sums (read at column
    ``c0 - 1`` when ``c0 > 0``, written at ``c1 - 1``). Default: every column.
    """
    i0, i1 = r0 - e0, r1 - e0
    ce0, c0, c1, carry = (0, 0, y.shape[1], None) if cols is None else cols
    j0, j1 = c0 - ce0, c1 - ce0
    in_ram = isinstance(out["saliency"], np.ndarray) and cols is None
    # in memory the block writes straight into the outputs; with a store it writes
    # into buffers copied to the (chunk-aligned) store at the end
    L, T = ctx.dev.shape
    r, C = i1 - i0, j1 - j0
    # else the tiles' own buffers (``work["sal"]``, ``"thr"``, ``"mask"``, kept from
    # tile to tile by the worker thread: no fresh pages per tile), copied out by ``_put``
    sal_out = out["saliency"][r0:r1] if in_ram else _buffer(work, "sal", (r, C, T), np.float32)
    if opts["store_boxes"]:
        Qb = int((ctx.scales > 1).sum())
        box = _buffer(work, "box", (L, Qb, r, C, T), np.float32)
    else:
        box = None
    k_cols = None if cols is None else (slice(j0, j1), STRIP_COLS, carry)
    # sum_l bhat is recomputed by the threshold pass from sp and dev (not stored)
    _, sal, d, sp, _ = block_saliency(
        y, ctx, keep=slice(i0, i1), c=c_ext, sal_out=sal_out, work=work, box=box, cols=k_cols,
        with_level=False,
    )  # fmt: skip
    xs, ys, store_thr = table
    cand = _buffer(work, "cand", (r, C, T), bool)
    ev_vox = _buffer(work, "ev", (r, C, T), np.float32)
    # a per-voxel threshold is written out only to a store (in memory it is kept as
    # the background factors: ThresholdField)
    thr = (
        _buffer(work, "thr", (r, C, T), np.float32)
        if store_thr
        else np.empty((1, 1, 1), np.float32)
    )
    mask = out["mask"][r0:r1] if in_ram else _buffer(work, "mask", (r, C, T), bool)
    # threshold, M, candidate voxels, evidence and photon counts in one pass
    n_ph, kept = threshold_pass(
        sal,
        d,
        sp,
        np.ascontiguousarray(ctx.dev, np.float32),
        xs,
        ys,
        y,
        i0,
        j0,
        thr,
        store_thr,
        mask,
        cand,
        ev_vox,
    )
    n_vox = int(np.count_nonzero(mask))
    if not in_ram:
        _put(out["saliency"], r0, c0, sal)
        _put(out["mask"], r0, c0, mask)
        if store_thr:
            _put(out["threshold"], r0, c0, thr)
    out["spatial"][r0:r1, c0:c1] = sp
    # a surface is a positive excursion: voxels of M where the response is below the
    # background (|.| of eq:4.s1) are kept in M but start no candidate
    # block rows and own columns (from r0, c0)
    # the own pixel's fine response is read from the correlated rows (block row i at
    # c_ext row i0 + i, own column j at j0 + j)
    dev = np.ascontiguousarray(ctx.dev, np.float32)
    fine = (c_ext, y, i0, j0, sp, dev, _NO_FINE, _NO_FINE, _NO_FINE)
    rows, cols, start, stop, peak, mass, ev, added = find_segments(
        cand, d, sal, ev_vox, opts["min_separation"], opts["split_ratio"], fine, opts["split"]
    )
    del cand, ev_vox, d
    n_cand = int(rows.size)
    # candidates whose evidence does not beat the simulated null are dropped before
    # the (costly) extraction: the evidence does not depend on it
    pre = np.flatnonzero(ev > opts["evidence_threshold"])
    rows, cols, start, stop, peak, mass, ev, added = (
        a[pre] for a in (rows, cols, start, stop, peak, mass, ev, added)
    )
    surf, keep = _extract(
        y, c_ext, box, e0, r0, ce0, c0, rows, cols + c0, start, stop, peak, mass, sp, ctx, opts
    )
    del box
    surf["evidence"] = ev
    if opts["split_coherent"][1]:
        surf["_fine_added"] = added
    if opts["presence"] in ("auto", "adaptive") and keep.any():
        # a pixel's strongest candidate is supported by the scene's continuity; any
        # further one is an extra claim on the pixel and needs its own counts to favour
        # it (log-likelihood ratio >= presence_secondary): coarse scales plant such
        # extras beside thin structures and across depth edges
        rank = _rank_in_pixel(surf["row"], surf["col"], ev, keep)
        extra_ok = surf["presence_llr"] >= opts["secondary_llr"]
        if opts["presence"] == "adaptive":
            extra_ok &= surf["presence_z"] >= opts["presence_z"]
        keep &= (rank == 0) | extra_ok
    return _finish_block(n_vox, kept, n_ph, surf, keep, opts, n_cand)


def _move_rows(buf: np.ndarray, dst: int, src: int, n: int) -> None:
    """``buf[dst : dst + n] = buf[src : src + n]`` (rows of the first axis, in place).

    Where the two ranges overlap (the halo of ``2 h`` rows is longer than the step
    ``|dst - src|`` between blocks: 10 rows against 5 on the face file at its native
    bin), NumPy copies through a temporary of all ``n`` rows: a fresh array each block
    (95 MB on the face) and twice the bytes copied (70 against 20 ms a block there,
    ``benchmarks/README.md``, "halo36, session 24"). Here the
    rows go in pieces of ``|dst - src|`` rows, each apart from its source, in the order
    that reads every source row before it is overwritten: the same values, no temporary.
    """
    step = dst - src
    if step == 0 or n <= 0:
        return
    k = abs(step)
    # towards the front: from the first piece on; towards the back: from the last one
    starts = range(0, n, k) if step < 0 else range((n - 1) // k * k, -1, -k)
    for i in starts:
        j = min(n, i + k)
        buf[dst + i : dst + j] = buf[src + i : src + j]


def _run_rows(counts, blocks, ctx: SaliencyFilters, table, opts, out, block_rows: int) -> list:
    """The blocks ``(r0, r1)`` that ``blocks`` yields, one after the other; returns
    ``[(r0, result), ...]``.

    The correlated halo rows shared by consecutive blocks (downwards or upwards) are
    carried over, so every image row is matched-filtered once (plus ``2 h`` rows where
    the sequence jumps).
    """
    R = counts.shape[0]
    h = int(ctx.scales.max()) // 2
    res = []
    # one buffer per run: a block's correlated rows; the halo it shares with the next
    # block is moved to where that block needs it (no concatenation, no per-block
    # allocation: _move_rows)
    shape = tuple(counts.shape)
    buf = np.empty((min(block_rows + 2 * h, R),) + shape[1:], np.float32)
    nb = min(block_rows, R)
    work = dict(
        d=np.empty((nb, shape[1], shape[3]), np.float32),
        cand=np.empty((nb, shape[1], shape[3]), bool),
        ev=np.empty((nb, shape[1], shape[3]), np.float32),
    )
    if opts["store_boxes"]:
        # box means of the scales above 1 pixel (flat: reshaped per block)
        n_box = shape[2] * int((ctx.scales > 1).sum()) * nb * shape[1] * shape[3]
        work["box"] = np.empty(n_box, np.float32)
    have0, have1 = 0, 0  # buf[have0 - e0 : have1 - e0] holds correlated rows [have0, have1)
    e0 = 0
    for r0, r1 in blocks:
        e0_new, e1 = max(0, r0 - h), min(R, r1 + h)
        a, b = max(e0_new, have0), min(e1, have1)  # rows already correlated
        if a < b:
            _move_rows(buf, a - e0_new, a - e0, b - a)
        else:
            a = b = e0_new
        e0 = e0_new
        y = np.asarray(counts[e0:e1])
        if e0 < a:
            ctx.corr(y[: a - e0], workers=ctx.workers, out=buf[: a - e0])
        if b < e1:
            ctx.corr(y[b - e0 :], workers=ctx.workers, out=buf[b - e0 : e1 - e0])
        c_ext = buf[: e1 - e0]
        res.append((r0, _block(y, c_ext, e0, r0, r1, ctx, table, opts, out, work)))
        have0, have1 = e0, e1
        del c_ext, y
    return res


class _Schedule:
    """Blocks of rows handed to threads: each thread takes the blocks of its own run from
    the top; a thread whose run is done takes blocks from the bottom of the run with the
    most left (upwards, one such helper per run), so that no thread waits while others
    work (runs differ in cost with their number of candidates: 2.1 and 2.9 s of CPU on
    the two halves of the 200 x 200 x 4 x 1500 bench cube). The blocks are those of the
    runs whoever computes them, and every block's result is the same whichever thread
    computes it.
    """

    def __init__(self, runs: list, block_rows: int):
        self.blocks = [_blocks(a, b, block_rows) for a, b in runs]
        self.lo = [0] * len(runs)
        self.hi = [len(x) for x in self.blocks]
        self.helped = [False] * len(runs)
        self.lock = threading.Lock()

    def blocks_for(self, k: int):
        """The blocks thread ``k`` computes: its run's, then helping others."""
        yield from self._own(k)
        while True:
            k_help = self._pick()
            if k_help < 0:
                return
            yield from self._from_bottom(k_help)

    def _own(self, k: int):
        """Run ``k``'s blocks from the top, while it has some left."""
        while True:
            with self.lock:
                if self.lo[k] >= self.hi[k]:
                    return
                i = self.lo[k]
                self.lo[k] += 1
            yield self.blocks[k][i]

    def _pick(self) -> int:
        """The run with the most blocks left and no helper yet (-1: none with two)."""
        with self.lock:
            left = [
                (self.hi[k] - self.lo[k], k) for k in range(len(self.blocks)) if not self.helped[k]
            ]
            n, k = max(left, default=(0, -1))
            if n < 2:  # the owner is busy with its last block
                return -1
            self.helped[k] = True
            return k

    def _from_bottom(self, k: int):
        """Run ``k``'s remaining blocks from the bottom, while it has some left."""
        while True:
            with self.lock:
                if self.lo[k] >= self.hi[k]:
                    return
                self.hi[k] -= 1
                i = self.hi[k]
            yield self.blocks[k][i]


def _finish_block(n_vox, kept, n_ph, surf, keep, opts, n_cand) -> _BlockOut:
    # the candidates that passed the block's rules, unselected: detect() runs the global
    # passes of _quality.py on them (they need neighbours across block borders), then
    # _select (K_s per pixel)
    if opts.get("keep_suspects"):
        # the rejected candidates of pixels left with room for a surface stay in the
        # table (the dark-region passes may restore them); ``presence_ok`` tells them
        # apart
        C = opts["image_shape"][1]
        pix = surf["row"] * C + surf["col"]
        u, cnt = np.unique(pix[keep], return_counts=True)
        room = ~np.isin(pix, u[cnt >= opts["max_surfaces"]])
        idx = np.flatnonzero(keep | room)
        surf["presence_ok"] = keep.copy()
    else:
        idx = np.flatnonzero(keep)
    slot = surf.pop("_slot")  # rows of the _BY_SLOT arrays (see _extract)
    # the own background is not kept: the table's OwnBackground computes it from the
    # background where it is read (assemble_map), the block's dense array released
    surf.pop("own_background", None)
    rows = slot[idx]
    out = {k: v[rows] if k in _BY_SLOT else v[idx] for k, v in surf.items() if k != "histograms"}
    own = out.get("own_counts")
    if own is not None and (own.size == 0 or (own.min() >= -(2**15) and own.max() < 2**15)):
        # compact_columns' type for it, from the block on (the table takes int16 where
        # every block's fit, as compacting the whole column gives; the same values)
        out["own_counts"] = own.astype(np.int16)
    # the table's candidates' histograms over their supports only (zero elsewhere in
    # the window: _kernels._clean_responses), the block's dense array released
    hist = SupportWindows.pack(
        surf.pop("histograms"), rows, first=out["start"] - out["offset"],
        length=np.maximum(out["stop"] - out["start"], 0),
    )  # fmt: skip
    return _BlockOut(
        n_voxels=n_vox,
        n_photons_kept=kept,
        n_photons=n_ph,
        surf=out,
        n_candidates=n_cand,
        n_rejected=n_cand - int(keep.sum()),
        histograms=hist,
        kept=np.arange(rows.size, dtype=np.int64),
    )


def _open_store(store, shape, block_rows: int, block_cols=None) -> dict:
    """Chunked Zarr arrays for saliency and mask in a new directory, in chunks of
    ``block_rows`` rows and ``block_cols`` columns (default all). The threshold is not
    stored: as in memory, it is kept as its factors (:class:`ThresholdField`)."""
    import os as _os
    from pathlib import Path

    try:
        import zarr
    except ImportError:
        raise SplidarError(
            "`store` needs the zarr package; install it with `pip install splidar[dask]` "
            "or pass store=None to keep the arrays in memory."
        ) from None
    try:
        path = Path(_os.fspath(store))
    except TypeError:
        raise SplidarError(
            f"`store` must be a directory path (str or os.PathLike); got {describe(store)}."
        ) from None
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise SplidarError(
            f"`store` '{path}' exists and is not an empty directory; name a new directory "
            "(detect does not overwrite files)."
        )
    g = zarr.open_group(str(path), mode="w")
    R, C, T = shape
    ch = (min(block_rows, R), C if block_cols is None else min(block_cols, C), T)
    # the saliency's float noise does not compress (zstd: 1.1 x, at a fifth of the disk's
    # write speed); the sparse mask ~150 x with Zarr's default zstd
    out = dict(
        saliency=g.create_array(
            "saliency", shape=shape, chunks=ch, dtype="float32", compressors=None,
            chunk_key_encoding=FLAT_CHUNK_KEYS,
        ),
        mask=g.create_array(
            "mask", shape=shape, chunks=ch, dtype="bool", chunk_key_encoding=FLAT_CHUNK_KEYS
        ),
    )  # fmt: skip
    out = {k: writer(v) for k, v in out.items()}
    out["threshold"] = None
    return out


def writer(z):
    """The Zarr array ``z`` as the map pass writes it: every chunk stored, even one equal
    to the fill value (Zarr otherwise compares each chunk with it before writing, a
    third pass over the memory written: the values read back are the same)."""
    return z.with_config({"write_empty_chunks": True})


def _block_rows(block_rows, scales, width, store_boxes, shape) -> int:
    R, C, L, T = shape
    h_max = int(scales.max()) // 2
    if block_rows is None:
        # ~64 MB of work buffers per block (reused by the blocks of a run, so no fresh
        # pages); halo rows are correlated once per run, so small blocks cost little
        per_row = C * T * 4 * (L + 6 + (L * int((scales > 1).sum()) if store_boxes else 0))
        block_rows = int(np.clip(64e6 // per_row, max(8, 4 * h_max), R))
    return min(block_rows, R)


#: The in-memory map pass's work buffers (all threads' together, :func:`_run_bytes`) are
#: kept to at most this fraction of the float32 cube (or ``n_runs x 64 MB`` when that is
#: more) by taking fewer rows per block: issue #15's peak of at most 2 float32 cubes above
#: the input holds the map's outputs (saliency and mask, ``1.25 / L`` cubes) and the
#: candidates besides. The former floor of ``4 h_max`` rows per block made the buffers
#: 0.8 cubes on the face file at its native bin (95 MB per row of 7,001 bins, 2 threads;
#: ``benchmarks/README.md``, "mem36, session 24"). A block's rows never change a result.
WORK_FRACTION = 0.25
#: Bytes of work buffers per thread the cap never goes below (the default rule asks for
#: about 64 MB per block): small cubes keep their rows.
WORK_FLOOR = 64e6


def _run_bytes(rows: int, shape, h: int, n_box: int) -> int:
    """Bytes of one run's work buffers (:func:`_run_rows`) at ``rows`` rows per block: the
    correlated rows with their halo (``rows + 2 h``, ``C L T`` float32), the signed
    response and evidence (float32), the candidate voxels (bool) and ``n_box`` box means
    per wavelength (``C T`` float32 each, when kept for extraction)."""
    R, C, L, T = shape
    rows_h = min(rows + 2 * h, R)
    return int(rows_h * C * L * T * 4 + rows * C * T * (4 + 4 + 1 + 4 * L * n_box))


def _capped_rows(block_rows: int, shape, h: int, n_box: int, n_runs: int) -> int:
    """``block_rows`` (the default rule's), or fewer, so that ``n_runs`` runs' buffers
    stay within :data:`WORK_FRACTION` of the float32 cube (at least 1 row; never fewer
    rows than ``n_runs x WORK_FLOOR`` bytes of buffers allow)."""
    R, C, L, T = shape
    budget = max(WORK_FRACTION * R * C * L * T * 4, n_runs * WORK_FLOOR)
    rows = int(block_rows)
    while rows > 1 and n_runs * _run_bytes(rows, shape, h, n_box) > budget:
        rows -= 1
    return rows


def _blocks(a: int, b: int, block_rows: int) -> list:
    """Blocks ``(r0, r1)`` of ``block_rows`` rows over ``[a, b)``, from the top."""
    return [(r0, min(b, r0 + block_rows)) for r0 in range(a, b, block_rows)]


def _n_runs(R: int, h_max: int, n_jobs: int) -> int:
    """Runs of blocks (threads) of the in-memory map pass."""
    return max(1, min(n_jobs, R // (2 * h_max + 1)))


def _runs(R: int, h_max: int, n_jobs: int, block_rows: int, store) -> list:
    """Contiguous runs of rows, one per thread; blocks within a run share their halo."""
    n_run = _n_runs(R, h_max, n_jobs)
    cuts = np.linspace(0, R, n_run + 1).round().astype(int)
    if store is not None:
        # runs start on chunk boundaries: no two threads write one chunk
        cuts = np.unique(np.minimum(np.round(cuts / block_rows).astype(int) * block_rows, R))
        cuts[0], cuts[-1] = 0, R
    return [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]


def _threshold(spatial, dev, table, null: NullCalibration):
    if table[0].size == 1:
        return float(np.float32(table[1][0]))
    sp_sum = spatial.sum(axis=-1)
    if np.ptp(sp_sum) <= 1e-6 * max(float(sp_sum.max()), 1e-12):
        # spatially flat background: the threshold varies with t only
        lev_t = np.maximum(spatial[0, 0][:, None] + dev, 0).sum(axis=0)
        return null.threshold_at(lev_t)[None, None, :]
    # with a store too: the factors are in memory (``spatial``, ``dev``) and any rows
    # are computed on access, as the map pass computed them (no per-voxel array)
    return ThresholdField(spatial, dev, table[0], table[1])


def _table(outs, image_shape, coherent=(0.0, 0), threads: int = 1) -> CandidateTable:
    keys = list(outs[0].surf.keys())
    # column by column, each block's part released once copied in (the calling process
    # holds ``threads`` columns and a block's part of each, not the whole table); the
    # columns on ``threads`` threads (NumPy's copies release the GIL: on a cluster this
    # runs after the last tile, the workers idle; 1.8 s of 2.6 s of the calling
    # process's serial end of issue #16's map pass was these copies)
    parts = [o.surf for o in outs]
    if threads > 1 and len(keys) > 1:
        with ThreadPoolExecutor(min(threads, len(keys))) as ex:
            surf = dict(zip(keys, ex.map(lambda k: _join(parts, k), keys), strict=True))
    else:
        surf = {k: _join(parts, k) for k in keys}
    # where each candidate's histograms are: block and row in that block's array
    hist_block = np.concatenate([np.full(o.kept.size, b, np.int64) for b, o in enumerate(outs)])
    hist_row = np.concatenate([o.kept for o in outs])
    if "presence_ok" in surf:
        keep = surf.pop("presence_ok").astype(bool)
    else:
        keep = np.ones(surf["row"].size, bool)
    if "_fine_added" in surf:
        # a return the fine split added stays only beside a 4-neighbour's kept
        # candidate within ``coherent_within`` bins of its depth (whole-image, so
        # the same whatever the blocks)
        added = surf.pop("_fine_added").astype(bool)
        lone = added & ~_coherent(surf, keep, image_shape, added, *coherent)
        if lone.any():
            ok = ~lone
            surf = {k: v[ok] for k, v in surf.items()}
            keep, hist_block, hist_row = keep[ok], hist_block[ok], hist_row[ok]
    # raster order (row, column, then depth), whatever the blocks or tiles: blocks of
    # whole rows give it as they are; 2D tiles of a band need their candidates merged
    if not _raster_sorted(surf["row"], surf["col"], surf["start"]):
        order = np.lexsort((surf["start"], surf["col"], surf["row"]))
        surf = {k: v[order] for k, v in surf.items()}
        keep, hist_block, hist_row = keep[order], hist_block[order], hist_row[order]
    origin = np.full(keep.size, stage_code("map"), np.int8)
    return CandidateTable(surf, keep, origin, hist_block, hist_row, image_shape)


def _join(parts: list, key: str) -> np.ndarray:
    """``np.concatenate`` of the parts' ``key`` arrays (popped from the dicts ``parts``,
    each released once copied): the same values and type."""
    first = [p[key] for p in parts]
    shape = (sum(int(a.shape[0]) for a in first), *first[0].shape[1:])
    out = np.empty(shape, np.result_type(*first))
    del first
    a = 0
    for p in parts:
        v = p.pop(key)
        out[a : a + v.shape[0]] = v
        a += v.shape[0]
        del v
    return out


def _raster_sorted(row, col, start) -> bool:
    """Whether the candidates are in raster order already (row, column, then start, each
    non-decreasing in turn): then the stable ``np.lexsort`` would leave them as they are,
    and one comparison of neighbours replaces the sort (30-60 ms per 256 rows)."""
    if len(row) < 2:
        return True
    dr, dc, ds = (np.diff(np.asarray(v, np.int64)) for v in (row, col, start))
    return bool(np.all((dr > 0) | ((dr == 0) & ((dc > 0) | ((dc == 0) & (ds >= 0))))))


def _fwhm_bins(irf) -> float:
    """The IRF's FWHM in bins (its widest half-peak window over the wavelengths)."""
    g = np.asarray(irf, np.float64)
    return float(max(np.count_nonzero(r >= 0.5 * r.max()) for r in g))


def _coherent(surf, keep, image_shape, query, tol, mode=1) -> np.ndarray:
    """Whether each candidate flagged in ``query`` has a kept candidate within ``tol``
    bins of its depth in a 4-neighbour pixel (bool, length of the table; False
    elsewhere)."""
    R, C = image_shape
    row = np.asarray(surf["row"], np.int64)
    col = np.asarray(surf["col"], np.int64)
    dep = np.asarray(surf["depth_bin"], np.float64)
    pix = row * C + col
    q = np.flatnonzero(query)
    # the kept candidates of the queries' 4-neighbours only (a few of the table: sorting
    # all of them took 20-50 ms per 256 rows for a handful of queries)
    near = np.zeros(R * C, bool)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        rr, cc = row[q] + dr, col[q] + dc
        inside = (rr >= 0) & (rr < R) & (cc >= 0) & (cc < C)
        near[rr[inside] * C + cc[inside]] = True
    sel = keep & near[pix]
    k = pix[sel]
    dk = dep[sel]
    order = np.lexsort((dk, k))
    out = np.zeros(row.size, bool)
    _coherent_kernel(row, col, dep, q, k[order], dk[order], R, C, float(tol), int(mode), out)
    return out


@njit(cache=True, nogil=True)
def _coherent_kernel(row, col, dep, q, k, dk, R, C, tol, mode, out):
    """:func:`_coherent` for the candidates ``q``: ``k``, ``dk`` the kept candidates'
    pixels and depths sorted by pixel, then depth. One loop over the queries (it was a
    Python loop over them, ~4 us each, per direction)."""
    for i in q:
        for dd in range(4):
            rr = row[i] + (1, -1, 0, 0)[dd]
            cc = col[i] + (0, 0, 1, -1)[dd]
            if rr < 0 or rr >= R or cc < 0 or cc >= C:
                continue
            kn = rr * C + cc
            a = np.searchsorted(k, kn, side="left")
            b = np.searchsorted(k, kn, side="right")
            hit = False
            for m in range(a, b):
                if abs(dk[m] - dep[i]) <= tol:
                    hit = True
            # mode 2: the neighbour shows a pair too (another candidate a FWHM or more
            # from the matching one; its depths are sorted: the spread is last - first)
            if hit and (mode < 2 or (b - a >= 2 and dk[b - 1] - dk[a] >= tol)):
                out[i] = True


def map_plan(
    filters: SaliencyFilters, null: NullCalibration, options: MapOptions, shape, block_rows
):
    """The map pass's settings for every block, and the rows per block.

    Returns ``(opts, block_rows)``; ``opts`` is what :func:`_block` reads (the same for
    every block, so blocks or tiles of any size give the same candidates).
    """
    R, C, L, T = shape
    scales = filters.scales
    width = options.width
    store_boxes = _store_boxes(scales, width, T)
    block_rows = _block_rows(block_rows, scales, width, store_boxes, (R, C, L, T))
    # the null's rule (its tail from the data), else the IRF's
    split = null.split
    if split is None:
        split = split_rule(
            filters.corr.irf, SPLIT_Z, None, SPLIT_REACH, SPLIT_TAIL_SLACK, bool(SPLIT_POOL)
        )
    opts = dict(
        image_shape=(R, C),
        width=width,
        store_boxes=store_boxes,
        min_separation=options.min_separation,
        split_ratio=options.split_ratio,
        split=split,
        # a return the fine split added needs a 4-neighbour's candidate within a FWHM
        split_coherent=(_fwhm_bins(filters.corr.irf), int(SPLIT_COHERENT))
        if SPLIT_COHERENT and split[0] > 0
        else (0.0, 0),
        presence=options.presence,
        presence_llr=options.presence_llr,
        presence_z=options.presence_z,
        secondary_llr=options.secondary_llr,
        refine=options.refine,
        refine_z=REFINE_Z,
        keep_suspects=options.keep_suspects,
        ici_gamma=ICI_GAMMA,
        evidence_threshold=null.evidence_threshold,
        max_surfaces=options.max_surfaces,
    )
    return opts, block_rows


def assemble_map(
    outs, out, filters, null, store, shape, block_rows, opts, threads: int = 1
) -> CandidateMap:
    """The :class:`CandidateMap` of the blocks' results ``outs`` (in row order) and the
    image-size arrays ``out`` they wrote (``saliency``, ``mask``, ``spatial``, and
    ``threshold`` in a store); the candidate table's columns joined on ``threads``
    threads."""
    R, C, L, T = shape
    width = opts["width"]
    table = null.table(per_voxel=False)
    saliency, mask, spatial = out["saliency"], out["mask"], out["spatial"]
    threshold = _threshold(spatial, filters.dev, table, null)
    out.clear()
    n_ph = sum(o.n_photons for o in outs)
    n_kept = sum(o.n_photons_kept for o in outs)
    n_vox = sum(o.n_voxels for o in outs)
    reduction = DataReduction(
        voxel_fraction=n_vox / (R * C * T),
        photon_fraction=n_kept / n_ph if n_ph else 0.0,
        n_voxels=n_vox,
        n_photons=n_kept,
    )
    cands = _table(outs, (R, C), opts["split_coherent"], threads)
    if "own_counts" in cands.columns:
        c = cands.columns
        own_bg = OwnBackground(
            spatial, filters.dev, c["row"], c["col"], c["offset"], c["start"], c["stop"],
            width=width,
        )  # fmt: skip
        cands = cands.with_columns(own_background=own_bg)
    hists = tuple(o.histograms for o in outs)
    for o in outs:
        o.histograms = None
    return CandidateMap(
        saliency=saliency,
        mask=mask,
        spatial=spatial,
        threshold=threshold,
        candidates=cands,
        histograms=hists,
        reduction=reduction,
        n_candidates=int(sum(o.n_candidates for o in outs)),
        n_rejected=int(sum(o.n_rejected for o in outs)),
        block_rows=block_rows,
        width=width,
    )


def map_candidates(
    counts,
    filters: SaliencyFilters,
    null: NullCalibration,
    options: MapOptions,
    *,
    block_rows: int | None,
    n_jobs: int,
    store=None,
) -> CandidateMap:
    """Saliency, map ``M`` and candidate surfaces of the whole image, block by block.

    Parameters
    ----------
    counts : array_like (rows, cols, L, T)
        In memory, or lazy (read block by block).
    filters : SaliencyFilters
        Stage 2's set-up.
    null : NullCalibration
        Stage 3's thresholds.
    options : MapOptions
    block_rows : int or None
        Rows per block (None: about 64 MB of work buffers, at least ``4 h_max`` rows,
        all threads' buffers within :data:`WORK_FRACTION` of the float32 cube).
    n_jobs : int
        Threads: runs of blocks in parallel, or threads inside the blocks of one run.
    store : path, optional
        A new directory for Zarr arrays of saliency, mask (and a per-voxel threshold).
    """
    R, C, L, T = counts.shape
    h_max = int(filters.scales.max()) // 2
    given = block_rows
    opts, block_rows = map_plan(filters, null, options, counts.shape, block_rows)
    if given is None:  # the default rows, within WORK_FRACTION of the cube
        n_box = int((filters.scales > 1).sum()) if opts["store_boxes"] else 0
        n_run = _n_runs(R, h_max, n_jobs)
        block_rows = _capped_rows(block_rows, counts.shape, h_max, n_box, n_run)
    table = null.table(per_voxel=False)
    if store is None:
        out = dict(
            saliency=np.empty((R, C, T), np.float32),
            mask=np.empty((R, C, T), bool),
            spatial=np.empty((R, C, L), np.float32),
            threshold=None,
        )
    else:
        out = _open_store(store, (R, C, T), block_rows)
        out["spatial"] = np.empty((R, C, L), np.float32)
    runs = _runs(R, h_max, n_jobs, block_rows, store)
    if len(runs) > 1:
        plan = _Schedule(runs, block_rows)

        def work(k: int) -> list:
            # one sequence of blocks per thread: its run's, then others' (one buffer)
            return _run_rows(counts, plan.blocks_for(k), filters, table, opts, out, block_rows)

        with ThreadPoolExecutor(len(runs)) as ex:
            done = [o for res in ex.map(work, range(len(runs))) for o in res]
    else:
        # one run: threads inside each block instead
        bctx = dataclasses.replace(filters, workers=n_jobs)
        done = _run_rows(counts, _blocks(0, R, block_rows), bctx, table, opts, out, block_rows)
    outs = [o for _, o in sorted(done, key=lambda x: x[0])]
    return assemble_map(outs, out, filters, null, store, counts.shape, block_rows, opts, n_jobs)
