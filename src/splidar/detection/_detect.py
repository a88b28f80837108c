"""Multiscale saliency detection (Algorithm 1) and surface extraction."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from scipy import stats

from .._validation import (
    SplidarError,
    check_choice,
    check_int,
    check_positive,
    check_probability,
    describe,
)
from ..cube import Cube
from ._background import CLIP, temporal_shape
from ._fast import poisson_background, saliency_wavelength
from ._filters import Correlator
from ._kernels import (
    extract_surfaces,
    find_segments,
    rank_in_pixel_sorted,
    select_sorted,
    threshold_pass,
)
from ._null import fit_gamma_quantiles, threshold_table
from ._quality import (
    align_depths,
    reject_isolated,
    reject_spill_over,
    rescue_dark,
    restore_enclosed,
)
from ._result import Background, DataReduction, Detection, NullModel, Surfaces
from ._slopes import recover_slopes, support_sums
from ._threshold import ThresholdField

__all__ = ["detect"]

logger = logging.getLogger(__name__)

_NULL_METHODS = ("empirical", "gamma")
_PRESENCE = ("auto", "adaptive", "none", "pixel")


# ----------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------


def _check_scales(scales) -> np.ndarray:
    try:
        vals = list(scales)
    except TypeError:
        raise SplidarError(
            f"`scales` must be a sequence of positive odd integers (box sizes, e.g. (1, 3, 7, "
            f"11)); got {describe(scales)}."
        ) from None
    if not vals:
        raise SplidarError("`scales` is empty; give at least one box size, e.g. (1, 3, 7, 11).")
    out = []
    for k in vals:
        try:
            k = check_int(k, "scales")
        except SplidarError:
            raise SplidarError(
                f"`scales` must hold positive odd integers; got {describe(k)} in {vals!r}."
            ) from None
        if k < 1 or k % 2 == 0:
            raise SplidarError(
                f"`scales` must hold positive odd integers (a box has a centre pixel); got {k} "
                f"in {vals!r}. Use e.g. (1, 3, 7, 11)."
            )
        out.append(k)
    if len(set(out)) != len(out):
        raise SplidarError(f"`scales` must not repeat a box size; got {vals!r}.")
    return np.asarray(out, dtype=np.int64)


def _check_weights(weights, scales: np.ndarray) -> np.ndarray:
    q = scales.size
    if weights is None:
        # each scale contributes the same noise variance (lambda_q / k_q constant)
        return scales / scales.sum()
    try:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise SplidarError(
            f"`weights` must be {q} numbers summing to 1; got {describe(weights)}."
        ) from None
    if w.size != q:
        raise SplidarError(
            f"`weights` must have one value per scale ({q}); got {w.size} value(s). "
            "Pass weights=None for equal weights 1/Q."
        )
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise SplidarError(f"`weights` must be finite and non-negative; got {w.tolist()}.")
    if abs(w.sum() - 1.0) > 1e-6:
        raise SplidarError(
            f"`weights` must sum to 1 (lambda_q of eq:4.s1); they sum to {w.sum():.6g}. "
            "Divide them by their sum."
        )
    return w


# ----------------------------------------------------------------------------------------
# the block computation shared by the data and the simulated null
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Ctx:
    corr: Correlator
    scales: np.ndarray  # (Q,) ascending
    weights: np.ndarray  # (Q,)
    dev: np.ndarray  # (L, T) float32: bbar - mean_t bbar
    var_factor: np.ndarray  # (L,)
    workers: int
    gsq: np.ndarray = None  # (L,) sum of g^2
    fisher: np.ndarray = None  # (L, 3): sum g'^2, sum g g'^2, peak curvature (_fisher_sums)
    quantum: np.ndarray = None  # (L,) max g / K^2: one photon in a coarse voxel


def _core(y, ctx: _Ctx, spatial=None, keep=None, c=None, sal_out=None, work=None, box=None):
    """Correlated cube, saliency and signed response of a block of pixels.

    Parameters
    ----------
    y : (r, c, L, T) counts
    spatial : (r, c, L) float32, optional
        Background level; estimated from the block's coarsest scale when None.

    keep : slice, optional
        Rows of the block to return the saliency of (the others are halo, used by the
        box filters only); default all.
    c : (r, c, L, T) float32, optional
        ``Y (*) g`` when already computed (halo rows carried over from the previous
        block); computed from ``y`` when None.
    sal_out : (r_keep, c, T) float32, optional
        Where to write the saliency (overwritten); a new array when None.
    box : (L, Qb, r_keep, c, T) float32, optional
        Receives the box means of every scale above 1 pixel (for surface extraction).

    Returns
    -------
    c : (r, c, L, T) float32   correlated counts ``Y (*) g`` (all rows)
    sal : (r, c, T) float32    ``eq:4.s1``
    d : (r, c, T) float32      ``sum_l sum_q lambda_q Box_q(c) - bhat`` (signed)
    spatial : (r, c, L) float32
    level : (r, c, T) float32  ``sum_l bhat``
    """
    if c is None:
        c = ctx.corr(y, workers=ctx.workers)
    keep = slice(None) if keep is None else keep
    r_all, cc, L, T = c.shape
    r = len(range(*keep.indices(r_all)))
    # the first wavelength writes sal, d and level, the others add to them
    sal = np.empty((r, cc, T), np.float32) if sal_out is None else sal_out
    if work is None:
        d = np.empty((r, cc, T), np.float32)
        level = np.empty((r, cc, T), np.float32)
    else:  # reused buffers of a run of blocks (no fresh pages per block)
        d, level = work["d"][:r], work["level"][:r]
    sp_out = np.empty((r, cc, L), np.float32) if spatial is None else spatial
    for l in range(L):
        # fused numba kernel (_fast.py): box filters of every scale, sum_q lambda_q Box_q,
        # robust level (eq:background_2), bhat (eq:background_3) and |.| (eq:4.s1)
        sp_l = saliency_wavelength(
            c[:, :, l, :],
            keep,
            ctx.scales,
            ctx.weights,
            ctx.dev[l],
            sal,
            d,
            level,
            spatial=None if spatial is None else np.ascontiguousarray(spatial[:, :, l]),
            var_factor=float(ctx.var_factor[l]),
            quantum=float(ctx.quantum[l]),
            clip=CLIP,
            n_threads=ctx.workers,
            box=None if box is None else box[l],
            overwrite=l == 0,
        )
        if spatial is None:
            sp_out[:, :, l] = sp_l
    return c, sal, d, sp_out, level


class _FixedSeed:
    """Stands in for a Generator whose next ``integers`` draw was taken in advance."""

    def __init__(self, seed: int):
        self.seed = int(seed)

    def integers(self, *args, **kwargs) -> int:
        return self.seed


def _null_samples(counts, ctx: _Ctx, n_target: int, rng, *, patch: int = 32, max_patches=400):
    """Saliency of background-only cubes drawn from the estimated background.

    Random patches of the image: the background level is estimated from the data around
    each (exactly as in the main pass), a Poisson cube of ``bhat`` is drawn and its
    saliency computed with the same filters; the patch interior (at least ``h`` pixels
    from any cut) is kept. Returns null saliency, its level, and the data's saliency on
    the same patches (for the gamma fit).

    The patches and their seeds are drawn first, in order, from ``rng``; the patches are
    then computed on ``ctx.workers`` threads (one patch per thread), so the result does
    not depend on the number of threads.
    """
    R, C, L, T = counts.shape
    h = int(ctx.scales.max()) // 2
    pr, pc = min(R, patch), min(C, patch)
    plan = []
    n = 0
    while n < n_target and len(plan) < max_patches:
        # every pixel is equally likely to be in a patch (patches are clipped at the
        # image border): borders, where the reflected box filters have a larger
        # variance, are represented in proportion
        a0 = int(rng.integers(-(pr - 1), R)) if pr < R else 0
        b0 = int(rng.integers(-(pc - 1), C)) if pc < C else 0
        r0, r1 = max(0, a0), min(R, a0 + pr)
        c0, c1 = max(0, b0), min(C, b0 + pc)
        seed = int(rng.integers(2**62))  # as poisson_background draws it
        plan.append((r0, r1, c0, c1, seed))
        n += (r1 - r0) * (c1 - c0) * T

    def window(key):
        r0, r1, c0, c1 = key
        dr0, dr1 = max(0, r0 - 2 * h), min(R, r1 + 2 * h)
        dc0, dc1 = max(0, c0 - 2 * h), min(C, c1 + 2 * h)
        sr0, sr1 = max(0, r0 - h), min(R, r1 + h)
        sc0, sc1 = max(0, c0 - h), min(C, c1 + h)
        yw = np.asarray(counts[dr0:dr1, dc0:dc1])
        _, sal_w, _, sp_w, _ = _core(yw, wctx, keep=slice(sr0 - dr0, sr1 - dr0))
        sp = sp_w[:, sc0 - dc0 : sc1 - dc0].copy()
        real = sal_w[r0 - sr0 : r1 - sr0, c0 - dc0 : c1 - dc0].ravel().copy()
        return sp, real

    def simulate(item):
        r0, r1, c0, c1, seed = item
        sp, real = windows[(r0, r1, c0, c1)]
        # Poisson cube of bhat (eq:background_3), drawn in numba (seeded from rng)
        ysim = poisson_background(sp, ctx.dev, _FixedSeed(seed))
        _, sal, d, _, level = _core(ysim, wctx, spatial=sp)
        i0, j0 = r0 - max(0, r0 - h), c0 - max(0, c0 - h)
        sl = (slice(i0, i0 + r1 - r0), slice(j0, j0 + c1 - c0))
        return sal[sl].copy(), level[sl].copy(), d[sl].copy(), real

    keys = list(dict.fromkeys(p[:4] for p in plan))
    n_par = max(1, min(int(ctx.workers), len(plan)))
    # one patch per thread when there are several; threads inside a single patch
    wctx = dataclasses.replace(ctx, workers=1) if n_par > 1 else ctx
    if n_par > 1:
        with ThreadPoolExecutor(n_par) as ex:
            windows = dict(zip(keys, ex.map(window, keys), strict=True))
            res = list(ex.map(simulate, plan))
    else:
        windows = {k: window(k) for k in keys}
        res = [simulate(p) for p in plan]
    s_sim = [r[0] for r in res]
    lev = [r[1] for r in res]
    d_sim = [r[2] for r in res]
    return s_sim, lev, d_sim, np.concatenate([r[3] for r in res])


# ----------------------------------------------------------------------------------------
# surfaces
# ----------------------------------------------------------------------------------------


def _fisher_sums(irf: np.ndarray) -> np.ndarray:
    """Per wavelength, ``sum_t g'(t)^2`` and ``sum_t g(t) g'(t)^2`` of the normalised IRF.

    The Fisher information of a depth ``d`` from ``n`` signal photons over a background
    of ``b`` photons per bin is ``(n G1)^2 / (n G2 + b G1)`` (matched-filter peak,
    first order), with ``G1 = sum g'^2`` and ``G2 = sum g g'^2``. A third column holds
    the second difference of the matched-filter response at its peak per unit of the
    peak value, ``2 (A(0) - A(1)) / A(0)`` (``A``: the IRF's autocorrelation), against
    which a smeared response is measured: (L, 3).
    """
    g = np.asarray(irf, np.float64)
    dg = np.gradient(g, axis=1)
    a0 = (g * g).sum(axis=1)
    a1 = (g[:, 1:] * g[:, :-1]).sum(axis=1)
    return np.stack(
        [(dg**2).sum(axis=1), (g * dg**2).sum(axis=1), 2.0 * (a0 - a1) / np.maximum(a0, 1e-300)],
        axis=1,
    )


def _irf_halfwidth(irf: np.ndarray) -> int:
    """Half-width (bins) of the matched-filter response: autocorrelation >= 1e-3 of max."""
    w = 1
    for g in irf:
        ac = np.correlate(g, g, mode="full")
        keep = np.flatnonzero(ac >= 1e-3 * ac.max())
        centre = g.size - 1
        w = max(w, int(max(centre - keep[0], keep[-1] - centre)))
    return w


def _irf_fwhm(irf: np.ndarray) -> float:
    out = 1.0
    for g in irf:
        above = np.flatnonzero(g >= 0.5 * g.max())
        out = max(out, float(above[-1] - above[0] + 1))
    return out


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


def _extract(y, c_ext, box, e0, r0, rows, cols, start, stop, peak, mass, sp_blk, ctx, opts):
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
    if n_threads == 1:
        extract_surfaces(*args, 0, S, *outs)
    else:
        cuts = np.linspace(0, S, n_threads + 1).round().astype(np.int64)
        with ThreadPoolExecutor(n_threads) as ex:
            list(
                ex.map(
                    lambda ab: extract_surfaces(*args, int(ab[0]), int(ab[1]), *outs),
                    zip(cuts[:-1], cuts[1:], strict=True),
                )
            )
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


def _raster_ordered(row, col) -> bool:
    """Whether candidates come in raster order of ``(row, col)`` (as blocks emit them)."""
    if row.size < 2:
        return True
    dr = np.diff(row)
    return bool(np.all((dr > 0) | ((dr == 0) & (np.diff(col) >= 0))))


def _position_in_pixel(row, col) -> np.ndarray:
    """Position of each candidate among its pixel's, for candidates sorted by pixel."""
    new = np.ones(row.size, bool)
    new[1:] = (row[1:] != row[:-1]) | (col[1:] != col[:-1])
    return np.arange(row.size) - np.flatnonzero(new)[np.cumsum(new) - 1]


def _rank_in_pixel(row, col, score, keep):
    """Rank (0 = largest ``score``) of each kept candidate among its pixel's kept ones."""
    rank = np.full(row.size, -1, np.int64)
    if _raster_ordered(row, col):
        rank_in_pixel_sorted(
            np.ascontiguousarray(row, np.int64),
            np.ascontiguousarray(col, np.int64),
            np.ascontiguousarray(score, np.float64),
            np.ascontiguousarray(keep, np.bool_),
            rank,
        )
        return rank
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return rank
    idx = idx[np.lexsort((-score[idx], col[idx], row[idx]))]
    rank[idx] = _position_in_pixel(row[idx], col[idx])
    return rank


def _select(surf: dict, keep: np.ndarray, k_max: int):
    """Keep at most ``k_max`` candidates per pixel (largest saliency mass), depth order."""
    row, col = surf["row"], surf["col"]
    order = None
    if not _raster_ordered(row, col) and keep.any():
        # e.g. the slope recovery's surfaces appended at the end: one stable sort by
        # pixel (a pixel's candidates keep their order), then the linear kernel
        order = np.lexsort((col, row))
    if order is not None or _raster_ordered(row, col):
        n = row.size
        take = (lambda a: a[order]) if order is not None else (lambda a: a)
        idx, slot = np.empty(n, np.int64), np.empty(n, np.int64)
        m = select_sorted(
            np.ascontiguousarray(take(row), np.int64),
            np.ascontiguousarray(take(col), np.int64),
            np.ascontiguousarray(take(surf["saliency_mass"]), np.float64),
            np.ascontiguousarray(take(surf["depth_bin"]), np.float64),
            np.ascontiguousarray(take(keep), np.bool_),
            int(k_max),
            idx,
            slot,
        )
        return (order[idx[:m]] if order is not None else idx[:m]), slot[:m]
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return idx, np.zeros(0, np.int64)
    row, col = surf["row"], surf["col"]
    idx = idx[np.lexsort((-surf["saliency_mass"][idx], col[idx], row[idx]))]
    idx = idx[_position_in_pixel(row[idx], col[idx]) < k_max]
    idx = idx[np.lexsort((surf["depth_bin"][idx], col[idx], row[idx]))]
    return idx, _position_in_pixel(row[idx], col[idx])


def _evidence(sal, thr):
    """Excess of the saliency over the threshold, relative to it: ``max(S / thr - 1, 0)``."""
    thr = np.maximum(np.asarray(thr, np.float32), np.float32(1e-12))
    e = sal / thr
    e -= 1
    np.maximum(e, 0, out=e)
    return e


def _block(y, c_ext, e0, r0, r1, ctx: _Ctx, table, opts, out, work=None) -> _BlockOut:
    """Saliency, map and surfaces of image rows ``[r0, r1)``.

    ``y`` and ``c_ext`` hold the raw and correlated rows ``[e0, e0 + len(y))`` (the
    block with its halo); ``out`` the preallocated image-size outputs written here.
    """
    i0, i1 = r0 - e0, r1 - e0
    in_ram = isinstance(out["saliency"], np.ndarray)
    # in memory the block writes straight into the outputs; with a store it writes
    # into buffers copied to the (chunk-aligned) store at the end
    sal_out = out["saliency"][r0:r1] if in_ram else None
    L, T = ctx.dev.shape
    if opts["store_boxes"]:
        Qb = int((ctx.scales > 1).sum())
        n_box = L * Qb * (i1 - i0) * y.shape[1] * T
        box = np.empty(n_box, np.float32) if work is None else work["box"][:n_box]
        box = box.reshape(L, Qb, i1 - i0, y.shape[1], T)
    else:
        box = None
    _, sal, d, sp, level = _core(
        y, ctx, keep=slice(i0, i1), c=c_ext, sal_out=sal_out, work=work, box=box
    )
    xs, ys, store_thr = table
    r, C, T = sal.shape
    if work is None:
        cand = np.empty((r, C, T), bool)
        ev_vox = np.empty((r, C, T), np.float32)
    else:
        cand, ev_vox = work["cand"][:r], work["ev"][:r]
    # a per-voxel threshold is written out only to a store (in memory it is kept as
    # the background factors: ThresholdField)
    thr = np.empty((r, C, T) if store_thr else (1, 1, 1), np.float32)
    mask = out["mask"][r0:r1] if in_ram else np.empty((r, C, T), bool)
    # threshold, M, candidate voxels, evidence and photon counts in one pass
    n_ph, kept = threshold_pass(sal, d, level, xs, ys, y, i0, thr, store_thr, mask, cand, ev_vox)
    del level
    n_vox = int(np.count_nonzero(mask))
    if not in_ram:
        out["saliency"][r0:r1] = sal
        out["mask"][r0:r1] = mask
        if store_thr:
            out["threshold"][r0:r1] = thr
    out["spatial"][r0:r1] = sp
    # a surface is a positive excursion: voxels of M where the response is below the
    # background (|.| of eq:4.s1) are kept in M but start no candidate
    rows, cols, start, stop, peak, mass, ev = find_segments(
        cand, d, sal, ev_vox, opts["min_separation"], opts["split_ratio"]
    )
    del cand, ev_vox, d
    n_cand = int(rows.size)
    # candidates whose evidence does not beat the simulated null are dropped before
    # the (costly) extraction: the evidence does not depend on it
    pre = np.flatnonzero(ev > opts["evidence_threshold"])
    rows, cols, start, stop, peak, mass, ev = (
        a[pre] for a in (rows, cols, start, stop, peak, mass, ev)
    )
    surf, keep = _extract(y, c_ext, box, e0, r0, rows, cols, start, stop, peak, mass, sp, ctx, opts)
    del box
    surf["evidence"] = ev
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


def _run_rows(counts, a, b, ctx: _Ctx, table, opts, out, block_rows: int) -> list:
    """Blocks of ``block_rows`` rows over image rows ``[a, b)``, one after the other.

    The correlated halo rows shared by consecutive blocks are carried over, so every
    image row is matched-filtered once (plus ``2 h`` rows per call).
    """
    R = counts.shape[0]
    h = int(ctx.scales.max()) // 2
    res = []
    # one buffer per run: a block's correlated rows, the halo it shares with the next
    # block moved to the front afterwards (no concatenation, no per-block allocation)
    shape = tuple(counts.shape)
    buf = np.empty((min(block_rows + 2 * h, R),) + shape[1:], np.float32)
    nb = min(block_rows, R)
    work = dict(
        d=np.empty((nb, shape[1], shape[3]), np.float32),
        level=np.empty((nb, shape[1], shape[3]), np.float32),
        cand=np.empty((nb, shape[1], shape[3]), bool),
        ev=np.empty((nb, shape[1], shape[3]), np.float32),
    )
    if opts["store_boxes"]:
        # box means of the scales above 1 pixel (flat: reshaped per block)
        n_box = shape[2] * int((ctx.scales > 1).sum()) * nb * shape[1] * shape[3]
        work["box"] = np.empty(n_box, np.float32)
    have0, n_have = 0, 0  # buf[:n_have] holds correlated rows [have0, have0 + n_have)
    for r0 in range(a, b, block_rows):
        r1 = min(b, r0 + block_rows)
        e0, e1 = max(0, r0 - h), min(R, r1 + h)
        y = np.asarray(counts[e0:e1])
        n = e1 - e0
        if n_have and have0 == e0:
            k = min(n_have, n)
        else:
            k = 0
        if k < n:
            ctx.corr(y[k:], workers=ctx.workers, out=buf[k:n])
        c_ext = buf[:n]
        res.append(_block(y, c_ext, e0, r0, r1, ctx, table, opts, out, work))
        # rows [r1 - h, e1) are the next block's top halo
        have0 = max(e0, r1 - h)
        n_have = e1 - have0
        src = have0 - e0
        if n_have and src:
            buf[:n_have] = buf[src : src + n_have].copy() if src < n_have else buf[src:n]
        del c_ext, y
    return res


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
    out = {k: v[idx] for k, v in surf.items() if k != "histograms"}
    return _BlockOut(
        n_voxels=n_vox,
        n_photons_kept=kept,
        n_photons=n_ph,
        surf=out,
        n_candidates=n_cand,
        n_rejected=n_cand - int(keep.sum()),
        histograms=surf["histograms"],
        kept=idx,
    )


def _open_store(store, shape, block_rows: int, with_threshold: bool) -> dict:
    """Chunked Zarr arrays for saliency, mask (and threshold) in a new directory."""
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
    ch = (min(block_rows, R), C, T)
    out = dict(
        saliency=g.create_array("saliency", shape=shape, chunks=ch, dtype="float32"),
        mask=g.create_array("mask", shape=shape, chunks=ch, dtype="bool"),
        threshold=g.create_array("threshold", shape=shape, chunks=ch, dtype="float32")
        if with_threshold
        else None,
    )
    return out


# ----------------------------------------------------------------------------------------
# public
# ----------------------------------------------------------------------------------------


def detect(
    cube: Cube,
    *,
    scales=(1, 3, 7, 11),
    weights=None,
    pfa: float = 1e-3,
    max_surfaces: int = 2,
    surface_pfa: float = 0.01,
    null: str = "empirical",
    presence: str = "adaptive",
    presence_z: float = 3.0,
    presence_llr: float = 3.0,
    presence_secondary: float = 0.0,
    spill_llr: float | None = 0.0,
    isolated: bool = True,
    dark: bool = True,
    slopes: str | bool = "weak",
    min_separation: float | None = None,
    split_ratio: float = 0.5,
    refine: bool = True,
    block_rows: int | None = None,
    n_jobs: int | None = None,
    store=None,
    rng=0,
) -> Detection:
    """Multiscale saliency detection of surfaces in a photon-count cube (Algorithm 1).

    Steps: matched filter along t (``Y (*) g``, one FFT pass per wavelength), spatial
    box filters at every scale; background (``eq:background_1..3``) from the coarsest
    scale, kept factored; saliency ``S = sum_l |sum_q lambda_q Box_q(Y (*) g) - bhat|``
    (``eq:4.s1``); a threshold from a calibrated null; the binary map ``M``; per pixel,
    runs of ``M`` split between resolved peaks become candidate surfaces with their clean
    histograms at every scale (``eq:background_final``), a selected scale
    (``eq:scale_sel``) and a sub-bin depth.

    Parameters
    ----------
    cube : Cube
        Counts ``(rows, cols, L, T)`` with the IRF.
    scales : sequence of positive odd int
        Box sizes ``k_q`` (sorted ascending internally, with their weights).
    weights : array_like (Q,), optional
        ``lambda_q`` (non-negative, sum 1, in the order of ``scales``). Default
        ``lambda_q = k_q / sum k``: every scale then adds the same noise variance
        (``lambda_q^2 / k_q^2`` constant). Against the paper's ``1/Q`` on (1, 3, 7, 11),
        it raises the signal-to-noise ratio of extended surfaces 2.9-fold and lowers
        that of 1-pixel strands by 17 % (measured: F_true 0.30 -> 0.75 at PPP 1, SBR
        0.1). ``[0, 1, 0, 0]`` (the paper's real-data choice) discards the finest scale.
    pfa : float
        Probability of false alarm per voxel, in (0, 1).
    max_surfaces : int
        ``K_s``, the most surfaces kept per pixel (>= 1).
    surface_pfa : float
        Expected number of false surfaces per background-only pixel, in (0, 1). The
        voxel-level ``pfa`` lets about ``pfa x T`` noise voxels per pixel through the
        map; a candidate is kept only when its evidence (``sum max(S / threshold - 1,
        0)`` over its support) exceeds that of all but a fraction ``surface_pfa`` of the
        candidates found in the simulated null (per pixel).
    null : {"empirical", "gamma"}
        ``"empirical"`` (default): the threshold is the ``1 - pfa`` quantile of the
        saliency of background-only cubes drawn from the estimated background, as a
        function of the local background level (calibrated; varies with t and pixel
        when the background does). ``"gamma"``: the paper's gamma threshold with a
        robust (quantile-matched) fit, not calibrated.
    presence : {"auto", "adaptive", "none", "pixel"}
        Check that a candidate exists in its own pixel (coarse scales spread returns
        beside thin structures and across depth edges). ``"auto"`` (adaptive scale):
        keep a candidate when the local scale (the finest above 1 pixel, 3 x 3 by
        default) responds significantly at its depth (Poisson z >= ``presence_z``) and
        the pixel's own counts do not reject it (own-pixel log-likelihood ratio of a
        return of the local scale's intensity vs. background >= ``-presence_llr``);
        a pixel's further candidates (all but the one of largest evidence) need the
        own counts to favour them (log-ratio >= ``presence_secondary``).
        ``"adaptive"``: as ``"auto"``, but the z required is
        ``min(presence_z, z_pred - presence_z)``, where ``z_pred`` is the z a return of
        the selected scale's intensity would give at the local scale: a dim
        neighbourhood (a dark stripe), where even a true return cannot reach
        ``presence_z``, is not held to it, while a ghost beside a bright one falls far
        short of its prediction; further candidates need z >= ``presence_z`` too.
        The default: alone it raised F_true in nearly every cell of the benchmark grid
        (64 x 64, ``benchmarks/bench_detection.py``; single surface PPP 4, SBR 0.25:
        0.893 -> 0.918) but added 0.1-3.4 false surfaces per 100 true ones; the
        spill-over and isolated-candidate checks (``spill_llr``, ``isolated``) remove
        more than that (see ``spill_llr``).
        ``"pixel"``: own-pixel likelihood ratio >= 0 with the selected scale's
        intensity (strict; loses weak surfaces). ``"none"``: keep every candidate.
    presence_z : float
        Significance required of the local scale (``"auto"``, ``"adaptive"``).
    presence_llr : float
        How strongly (natural log of the likelihood ratio) the own pixel must speak
        against a return before it is rejected (``"auto"``).
    presence_secondary : float
        Log-likelihood ratio the own pixel must give a pixel's further candidates
        (``"auto"``, ``"adaptive"``). Measured on the net scene (PPP 10, SBR 1) with
        ``"auto"`` and no spill-over check: 0 -> F_true 0.955 with 0.107 false surfaces
        per true one; 0.6 -> 0.952 / 0.077; 1 -> 0.944 / 0.052. With the spill-over
        check most of those extras are caught by it and 0 is the default (64 x 64,
        seeds [0, 7], [1, 7], other options default: 1 -> 0.941 / 0.029, 0 -> 0.955 /
        0.037; single surface PPP 4, SBR 0.25: 1 -> 0.904 / 0.040, 0 -> 0.905 / 0.048).
    spill_llr : float or None
        Spill-over check (``"auto"``, ``"adaptive"``; ``None`` switches it off), run
        once on the candidates of the whole image (``_quality.py``). A candidate is the
        spread of a neighbour's return when a neighbour (8-connected) holds a candidate
        at the same depth (within the IRF's FWHM), no opposite pair of 4-neighbours
        (north/south, west/east) interpolates to its depth (the surface does not
        continue through the pixel: it lies beside a thin structure or across a depth
        edge), and its own counts give a log-likelihood ratio below ``spill_llr`` for a
        return as bright as that neighbour's own-pixel signal vs. background only
        (0: the counts favour "no return"). Repeated until nothing changes (a rejected
        candidate is no source any more, so the spread two or more pixels from its
        source is tested next). Measured (64 x 64, seeds [0, 7] and [1, 7], F_true /
        false surfaces per true one), net scene PPP 10, SBR 1: 0.955 / 0.107 without
        it, 0.955 / 0.037 with it (the old defaults "auto", ``presence_secondary=1``,
        no spill or isolated check: 0.943 / 0.057); single surface PPP 4, SBR 0.25:
        0.916 / 0.107 -> 0.905 / 0.048 (old: 0.887 / 0.078). At PPP 1 the own counts
        have little power: single surface SBR 10, 0.871 / 0.094 -> 0.843 / 0.032.
    isolated : bool
        (``"auto"``, ``"adaptive"``) A candidate that no neighbour (8-connected) shares
        at its depth (within the IRF's FWHM) gets no support from the spatial pooling:
        keep it only when its own counts n over its support (width w bins, background
        B) are significant by themselves at the surface level: ``1 - (1 - P(N >= n |
        B))^(T / w) <= surface_pfa`` (the chance that a background-only pixel shows such
        a count in any of its T / w windows). Measured (64 x 64, seeds [0, 7], [1, 7]):
        0.4-2.7 fewer false surfaces per 100 true ones for at most 0.1 % of true ones,
        except at PPP 1, SBR 10 (net scene F_true 0.687 -> 0.659, false 2.8 -> 1.9 per
        100: a single photon there is not significant on its own).
    dark : bool
        (``"auto"``, ``"adaptive"``) Dark-region pass (``_quality.rescue_dark``): a
        dim patch (low reflectivity) holds too few photons per pixel for the local
        presence test, and beside bright pixels at the same depth it looks like their
        spread, so its candidates are rejected. For each pixel left with no surface,
        its rejected candidate of largest evidence is pooled with the other such
        candidates, and the kept ones whose own counts are weak (z < ``presence_z``),
        within the largest box at the same depth (within the IRF's FWHM): it is
        restored when their own counts together are significant (Poisson, at
        ``surface_pfa``) and its own counts do not reject a return of the pool's mean
        intensity (log-ratio >= ``-presence_llr``). The spread of a neighbour puts no
        photons at its depth in the pixels it covers, so it stays rejected. Measured
        (64 x 64, 2 seeds, F_true / false surfaces per 100 true ones, off -> on): single
        surface PPP 4, SBR 0.25: 0.910 / 4.2 -> 0.923 / 4.6 (decaying background: 0.904
        / 6.3 -> 0.921 / 6.9); PPP 10, SBR 1: 0.974 / 1.2 -> 0.984 / 1.3; PPP 50, SBR 10:
        0.992 -> 0.994; net scene PPP 10, SBR 1: 0.958 / 2.7 -> 0.960 / 2.9. A pool needs
        at least 6 candidates (``_quality.MIN_POOL``): each candidate's depth sits on its
        own counts' peak, so a pool of one or two noise peaks would pass the test (pure
        background: 0.006-0.013 false surfaces per pixel without this rule, 0.003-0.008
        with it, as without the pass). Last (after the slope recovery), a pixel with
        room for a surface whose rejected candidate both opposite pairs of 4-neighbours
        enclose (kept surfaces whose mean depth is within the FWHM of it) and whose
        local scale is significant (z >= ``presence_z``) keeps it even with no own
        photons at its depth (a return of ``s`` photons leaves none with probability
        ``exp(-s)``); beside a kept surface of the pixel its own counts must favour it
        (log-ratio >= ``presence_secondary``, the rule for further surfaces: a one-pixel
        hole of a net is enclosed by the strands). ``_quality.restore_enclosed``. Full
        grid: see the changelog; the Art scene (PPP 1, 4, 10) F_true within 0.001.
    slopes : {"weak", "holes", "all"} or bool
        (``"auto"``, ``"adaptive"``) Recover surfaces on steep slopes that the square
        boxes miss (``_slopes.py``, issue #3): around each tested pixel, local planes
        are fitted (robustly) to the kept surfaces within the largest box; where a
        plane is steep (the coarsest box spreads a return over more than the IRF's
        FWHM) and encloses the pixel, the raw counts along the plane (sheared window)
        of the pixel and of its neighbours holding no surface near the plane are tested
        against the background (exact Poisson, corrected for the planes, boxes and depth
        shifts tried: ``surface_pfa`` per tested pixel), then the own counts must not
        reject the return (``presence_llr``); repeated so that the interiors of dim
        regions fill in. A recovered surface within 2 FWHM of a kept one of its pixel
        replaces it (the same return, its depth biased by the boxes) unless the own
        counts reject it against the kept one (log-likelihood ratio below the kept
        one's minus ``presence_llr``). A lazy cube is read by bands of rows where pixels
        are tested.

        - ``"weak"`` (default): the pixels left with no surface and those holding a
          surface their own counts do not confirm (own log-likelihood ratio below
          ``presence_llr``) are tested.
        - ``"holes"``: only the pixels left with no surface.
        - ``"all"`` (or ``True``): every pixel with room for a surface.
        - ``False``: no recovery.

        Measured (``benchmarks/bench_detection.py``, full grid, seed 0, every other
        pass at its default), F_true ``"holes"`` / ``"weak"`` / ``"all"``: single
        surface PPP 4, SBR 0.25: 0.963 / 0.972 / 0.973 (decaying background 0.965 /
        0.975 / 0.976); net scene PPP 10, SBR 1: 0.964 / 0.969 / 0.973 (decaying 0.942
        / 0.947 / 0.951); at least as good as the per-pixel detector on both figures in
        49 / 54 / 53 of 64 cells. ``"holes"`` -> ``"weak"``: F_true up in 49 cells and
        down in 2 (by at most 0.0007), false surfaces -18.5 per 100 true summed over the
        cells. Against no recovery (``False`` -> ``"holes"``, session 5): F_true up in 54
        of 64 cells and down in none; pure background unchanged. Cost of the pass on
        the Art-size cube (one thread): 0.015 s (``"holes"``), 0.07 s (``"weak"``, 9 %
        of its pixels tested), 1.4 s (``"all"``, the robust plane fits around every
        pixel); on ``n_jobs`` threads, results do not depend on them. On the
        200 x 200 x 4 x 1500 cube: 0.004 / 0.007 / 0.7 s.
    min_separation : float, optional
        Peaks closer than this (bins) are one surface. Default: the IRF's FWHM.
    split_ratio : float
        A run is split between two peaks when the response dips below this fraction of
        the smaller peak between them.
    refine : bool
        Adaptive depth by the intersection of confidence intervals (ICI) over the
        scales, rather than the depth of the selected scale (``eq:scale_sel``, which
        mixes neighbours' returns at depth edges and on slopes): each scale's peak gets
        a standard error from the Fisher information of its pooled signal photons over
        the pooled background (first-order matched-filter peak,
        ``(n G1)^2 / (n G2 + b G1)`` with ``G1 = sum g'^2``, ``G2 = sum g g'^2``),
        widened when the box smears the return (a response flatter than the IRF's
        autocorrelation: a slope or a crease under the box, its extra variance added as
        a bound on the bias); scales are taken finest first until one's interval
        (``+-2`` standard errors) misses the intersection of the finer ones, and the
        most precise depth among those before it is reported. A bright pixel at a depth
        edge keeps its own depth; a dim one on a smooth surface gets the pooled one.
        The own pixel takes part only when its peak is significant (z >= 3). Measured
        against the previous rule (the own pixel's depth whenever its z >= 3; 64 x 64, 10
        cells of ``benchmarks/bench_detection.py``, 2 seeds): the mean depth error fell by
        25-48 % in every cell (single surface PPP 4, SBR 0.25: 0.60 -> 0.34 bins; net
        scene PPP 10, SBR 1: 0.49 -> 0.29; PPP 50, SBR 10: 0.21 -> 0.15). ``scale_index``
        still reports ``eq:scale_sel``. Also: when a candidate's run is longer than the
        histogram window (a steep slope), the window is centred on the own pixel's
        matched-filter peak in the run if that peak is significant (z >= sqrt(9 + 2 ln
        run length), the max of that many background bins), not on the coarse peak,
        which drifts off the return beside brightness changes (single surface, PPP 50,
        SBR 10: F_true 0.980 -> 0.994). Last, on the selected surfaces, a depth that
        its 4-neighbours place elsewhere (each opposite pair holding the same return
        puts it more than the FWHM and at most 2 FWHM away, the pairs agreeing) moves to
        the own clean histogram's peak near their prediction when the own counts favour
        that peak over the current depth (``_quality.align_depths``: on a steep slope
        the 3 x 3 box has a lobe per row and a low-count peak can fall on a neighbour
        row's). Full grid (``benchmarks/bench_detection.py``, seed 0), without -> with:
        F_true up in 36 of 64 cells (by up to 0.028), down in 3 (by at most 0.005),
        false surfaces -2.2 to +1.0 per 100 true ones (summed over the cells -6.2);
        single surface PPP 4, SBR 0.25 decaying background 0.957 / 5.4 -> 0.960 / 4.4;
        the Art scene +0.0001 to +0.0002.
    block_rows : int, optional
        Rows per block (memory/time trade-off; results do not depend on it). Default:
        about 64 MB of work buffers per block, at least ``4 x max(k) // 2`` rows (halo
        rows are matched-filtered once per run of blocks, so small blocks cost little).
    n_jobs : int, optional
        Threads (default: CPU count, at most 4).
    store : str or path, optional
        A new directory in which ``saliency``, ``mask`` and a threshold varying per
        voxel are written as chunked Zarr arrays (chunks of ``block_rows`` rows) instead
        of being held in memory: for cubes whose ``(rows, cols, T)`` arrays do not fit
        in RAM (with a lazy, Zarr- or Dask-backed cube, the counts are read block by
        block too). The result then holds ``zarr`` arrays; results are identical.
        Needs the ``zarr`` package (``pip install splidar[dask]``).
    rng : None, int or Generator, default 0
        Seed of the Monte Carlo null (the background-only saliency simulated from the
        estimated background to calibrate the threshold) and of the slope recovery's
        robust plane fits. The default, a fixed seed, makes the same input give the
        same result; ``None`` draws fresh entropy (results then vary slightly between
        calls, within the null's Monte Carlo error).

    Returns
    -------
    Detection

    Raises
    ------
    SplidarError
        Not a Cube; scales not distinct positive odd integers; weights of the wrong
        length, negative or not summing to 1; pfa outside (0, 1); max_surfaces < 1;
        unknown null or presence method; an IRF longer than T; spill_llr not a finite
        number or None; isolated not a bool.

    Notes
    -----
    Departures from the paper, each measured (see the project's ALGORITHM-NOTES):

    * Background (``eq:background_1..3``) on the correlated scale, with the window
      mirrored at its edges (a flat level stays flat); the lowest-10 % median of the
      temporal shape is kept (robust to returns in up to 90 % of the pixels) but its
      low-quantile bias is simulated and removed; the spatial level is a clipped mean
      over t, not a median (unbiased at low counts).
    * The threshold is calibrated on background-only cubes drawn from the estimate
      (``null="empirical"``): the measured false-alarm rate on pure-background cubes
      stays within 2x of ``pfa`` from 0.02 to 2 photons per bin, uniform or decaying
      (``benchmarks/bench_null.py``), where the gamma tail misses by up to 100x.
    * Candidates are positive excursions only, ranked by ``evidence`` and kept when it
      beats the simulated null at ``surface_pfa`` per pixel; then the presence check.

    ``eq:depth_global`` and ``eq:depth_scale`` correlate the clean histograms with g; in
    the paper the clean histograms of ``eq:background_final`` already are ``Y (*) g``, so
    correlating again would double-filter (and bias depths for asymmetric IRFs). We take
    the argmax of the clean matched-filter response itself. Depth is then refined with
    a parabola through the peak of the selected scale's response.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar import Cube, gaussian_irf
    >>> from splidar.detection import detect
    >>> rng = np.random.default_rng(0)
    >>> g = gaussian_irf(3.0)
    >>> lam = np.full((24, 24, 1, 100), 0.05)
    >>> h = g.size // 2
    >>> for j in range(24):  # a plane tilted along the columns, depth 30 + j
    ...     lam[:, j, 0, 30 + j - h : 30 + j + h + 1] += 20 * g
    >>> det = detect(Cube(rng.poisson(lam), irf=g), rng=0)
    >>> err = det.points.depth_bin - (30 + det.points.col)
    >>> bool(np.mean(np.abs(err) < 1) > 0.95), bool(len(det.points) >= 24 * 24)
    (True, True)
    """
    t_start = time.perf_counter()
    timings = {}
    if not isinstance(cube, Cube):
        raise SplidarError(
            f"`cube` must be a splidar.Cube; got {describe(cube)}. Build one with "
            "splidar.Cube(counts, irf=...) or splidar.load(path)."
        )
    scales_in = _check_scales(scales)
    w_in = _check_weights(weights, scales_in)
    order = np.argsort(scales_in)
    scales_arr = scales_in[order]
    w = w_in[order]
    pfa = check_probability(pfa, "pfa")
    max_surfaces = check_int(max_surfaces, "max_surfaces", minimum=1)
    surface_pfa = check_probability(surface_pfa, "surface_pfa")
    null = check_choice(null, "null", _NULL_METHODS)
    presence = check_choice(presence, "presence", _PRESENCE)
    presence_z = float(presence_z)
    presence_llr = check_positive(presence_llr, "presence_llr", allow_zero=True)
    presence_secondary = float(presence_secondary)
    if not isinstance(isolated, (bool, np.bool_)):
        raise SplidarError(f"`isolated` must be True or False; got {describe(isolated)}.")
    if isinstance(slopes, (bool, np.bool_)):
        slopes = "all" if slopes else False
    elif slopes not in ("holes", "weak", "all"):
        raise SplidarError(
            f'`slopes` must be "holes", "weak", "all", True (= "all") or False; got '
            f"{describe(slopes)}. Use slopes=False to switch the slope recovery off."
        )
    if spill_llr is not None:
        spill_in = spill_llr
        try:
            spill_llr = float(spill_llr)
        except (TypeError, ValueError):
            spill_llr = float("nan")
        if not np.isfinite(spill_llr):
            raise SplidarError(
                "`spill_llr` must be a finite number (a natural-log likelihood ratio, e.g. "
                "0.0) or None to switch the spill-over check off; got "
                f"{describe(spill_in)}."
            )
    split_ratio = float(split_ratio)
    if not 0.0 < split_ratio < 1.0:
        raise SplidarError(f"`split_ratio` must lie in (0, 1); got {split_ratio!r}.")
    R, C, L, T = cube.shape
    irf = np.asarray(cube.irf, dtype=np.float64)
    if irf.shape[1] > T:
        raise SplidarError(
            f"the cube's IRF ({irf.shape[1]} samples) is longer than its T = {T} bins; crop it."
        )
    if min_separation is None:
        min_sep = int(np.ceil(_irf_fwhm(irf)))
    else:
        min_sep = int(np.ceil(check_positive(min_separation, "min_separation")))
    n_jobs = (
        min(os.cpu_count() or 1, 4) if n_jobs is None else check_int(n_jobs, "n_jobs", minimum=1)
    )
    rng = np.random.default_rng(rng)
    corr = Correlator(irf, T)
    K = int(scales_arr.max())

    # --- background temporal shape (eq:background_1) ---------------------------------
    t0 = time.perf_counter()
    wh = _irf_halfwidth(irf)
    temporal = temporal_shape(cube.counts, corr, K, smooth=4 * wh + 1, workers=n_jobs)
    dev = (temporal - temporal.mean(axis=-1, keepdims=True)).astype(np.float32)
    var_factor = (irf**2).sum(axis=1) / K**2
    ctx = _Ctx(
        corr,
        scales_arr,
        w,
        dev,
        var_factor,
        workers=1,
        gsq=(irf**2).sum(axis=1),
        fisher=_fisher_sums(irf),
        quantum=irf.max(axis=1) / K**2,
    )
    timings["background_temporal"] = time.perf_counter() - t0

    # --- null and threshold -----------------------------------------------------------
    t0 = time.perf_counter()
    n_target = int(np.clip(1000.0 / pfa, 5e5, 1e7))
    # the patches run one after the other: threads inside each (FFT and fused kernel)
    null_ctx = dataclasses.replace(ctx, workers=n_jobs)
    p_sim, p_lev, p_d, s_real = _null_samples(cube.counts, null_ctx, n_target, rng)
    s_sim = np.concatenate([a.ravel() for a in p_sim])
    lev_sim = np.concatenate([a.ravel() for a in p_lev])
    # the paper's gamma fit on the data (eq:gamma_distrib, robust fit), on a second
    # thread beside the empirical table when allowed (numpy's selections release the GIL)
    with ThreadPoolExecutor(1) if n_jobs > 1 else contextlib.nullcontext() as ex:
        fit = ex.submit(fit_gamma_quantiles, s_real) if ex is not None else None
        thr_emp_global = float(np.quantile(s_sim, 1.0 - pfa))
        xs, ys = threshold_table(s_sim, lev_sim, pfa)
        a_fit, sc_fit = fit.result() if fit is not None else fit_gamma_quantiles(s_real)
    thr_gamma = float(stats.gamma.isf(pfa, a_fit, scale=sc_fit))
    if null == "gamma":

        def thr_fn(level):
            return np.float32(thr_gamma)

        method = "gamma-quantile"
    elif xs.size == 1:
        thr_const = np.float32(ys[0])

        def thr_fn(level):
            return thr_const

        method = "empirical"
    else:
        xs32, ys32 = xs.astype(np.float64), ys.astype(np.float64)

        def thr_fn(level):
            return np.interp(level, xs32, ys32).astype(np.float32)

        method = "empirical-by-level"
    # surface-level calibration: evidence of the candidates found in the null patches
    ev_null = []
    for a, lv, dd in zip(p_sim, p_lev, p_d, strict=True):
        thr = thr_fn(lv)
        ev_null.append(
            find_segments((a > thr) & (dd > 0), dd, a, _evidence(a, thr), min_sep, split_ratio)[-1]
        )
    ev_null = np.sort(np.concatenate(ev_null))[::-1]
    n_null_px = sum(a.shape[0] * a.shape[1] for a in p_sim)
    n_allowed = int(np.floor(surface_pfa * n_null_px))
    ev_thr = float(ev_null[n_allowed]) if n_allowed < ev_null.size else 0.0
    del p_sim, p_lev, p_d
    null_model = NullModel(
        shape=float(a_fit),
        scale=float(sc_fit),
        method=method,
        pfa=pfa,
        calibration=(thr_emp_global / thr_gamma if thr_gamma > 0 else float("nan"))
        if null == "empirical"
        else 1.0,
        details=MappingProxyType(
            {
                "gamma_threshold": thr_gamma,
                "empirical_threshold": thr_emp_global,
                "table_levels": xs,
                "table_thresholds": ys,
                "n_null_voxels": int(s_sim.size),
                "gamma_rate_on_null": float(np.mean(s_sim > thr_gamma)),
                "surface_pfa": surface_pfa,
                "evidence_threshold": ev_thr,
                "null_candidates_per_pixel": ev_null.size / max(n_null_px, 1),
            }
        ),
    )
    timings["null"] = time.perf_counter() - t0

    # --- main pass over blocks of rows -------------------------------------------------
    t0 = time.perf_counter()
    h_max = K // 2
    width = min(2 * wh + 1, T)
    store_boxes = _store_boxes(scales_arr, width, T)
    if block_rows is None:
        # ~64 MB of work buffers per block (reused by the blocks of a run, so no fresh
        # pages); halo rows are correlated once per run, so small blocks cost little
        per_row = C * T * 4 * (L + 6 + (L * int((scales_arr > 1).sum()) if store_boxes else 0))
        block_rows = int(np.clip(64e6 // per_row, max(8, 4 * h_max), R))
    else:
        block_rows = check_int(block_rows, "block_rows", minimum=1)
    block_rows = min(block_rows, R)
    opts = dict(
        image_shape=(R, C),
        width=width,
        store_boxes=store_boxes,
        min_separation=min_sep,
        split_ratio=split_ratio,
        presence=presence,
        presence_llr=presence_llr,
        presence_z=presence_z,
        secondary_llr=presence_secondary,
        refine=refine,
        refine_z=3.0,
        keep_suspects=bool(dark) and presence in ("auto", "adaptive"),
        ici_gamma=2.0,
        evidence_threshold=ev_thr,
        max_surfaces=max_surfaces,
    )
    if null == "gamma":
        table = (np.zeros(1), np.array([float(np.float32(thr_gamma))]), False)
    else:
        # a threshold varying with the level is computed by the main pass and kept as
        # its factors (ThresholdField; written out only to a store), or reduced to its
        # variation with t alone if the background turns out spatially flat
        table = (
            np.asarray(xs, np.float64),
            np.asarray(ys, np.float64),
            xs.size > 1 and store is not None,
        )
    if store is None:
        out = dict(
            saliency=np.empty((R, C, T), np.float32),
            mask=np.empty((R, C, T), bool),
            spatial=np.empty((R, C, L), np.float32),
            threshold=None,
        )
    else:
        out = _open_store(store, (R, C, T), block_rows, table[2])
        out["spatial"] = np.empty((R, C, L), np.float32)
    # contiguous runs of rows, one per thread; blocks within a run share their halo
    n_run = max(1, min(n_jobs, R // (2 * h_max + 1)))
    cuts = np.linspace(0, R, n_run + 1).round().astype(int)
    if store is not None:
        # runs start on chunk boundaries: no two threads write one chunk
        cuts = np.unique(np.minimum(np.round(cuts / block_rows).astype(int) * block_rows, R))
        cuts[0], cuts[-1] = 0, R
    runs = [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]
    if len(runs) > 1:
        with ThreadPoolExecutor(len(runs)) as ex:
            outs = [
                o
                for res in ex.map(
                    lambda ab: _run_rows(
                        cube.counts, ab[0], ab[1], ctx, table, opts, out, block_rows
                    ),
                    runs,
                )
                for o in res
            ]
    else:
        # one run: threads inside each block instead
        bctx = dataclasses.replace(ctx, workers=n_jobs)
        outs = _run_rows(cube.counts, 0, R, bctx, table, opts, out, block_rows)
    saliency, mask, spatial = out["saliency"], out["mask"], out["spatial"]
    if table[0].size == 1:
        threshold = float(np.float32(table[1][0]))
    else:
        sp_sum = spatial.sum(axis=-1)
        if np.ptp(sp_sum) <= 1e-6 * max(float(sp_sum.max()), 1e-12):
            # spatially flat background: the threshold varies with t only
            lev_t = np.maximum(spatial[0, 0][:, None] + dev, 0).sum(axis=0)
            threshold = thr_fn(lev_t)[None, None, :]
        elif store is not None:
            threshold = out["threshold"]
        else:
            threshold = ThresholdField(spatial, dev, table[0], table[1])
    out.clear()
    timings["saliency_and_surfaces"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    keys = outs[0].surf.keys()
    surf = {k: np.concatenate([o.surf[k] for o in outs], axis=0) for k in keys}
    # where each candidate's histograms are: block and row in that block's array
    hist_block = np.concatenate([np.full(o.kept.size, b, np.int64) for b, o in enumerate(outs)])
    hist_row = np.concatenate([o.kept for o in outs])
    # global passes over the candidate table of the whole image (_quality.py: they need
    # the neighbours across block borders), then K_s per pixel
    if "presence_ok" in surf:
        keep = surf.pop("presence_ok").astype(bool)
    else:
        keep = np.ones(surf["row"].size, bool)
    n_spill = 0
    if presence in ("auto", "adaptive") and spill_llr is not None and keep.any():
        spill = reject_spill_over(
            {**surf, "image_shape": (R, C)},
            keep,
            irf=irf,
            peak=np.asarray(corr.peak),
            fwhm=_irf_fwhm(irf),
            llr_level=spill_llr,
            max_iter=max(R, C),
        )
        n_spill = int(spill.sum())
        keep &= ~spill
    n_isolated = 0
    if presence in ("auto", "adaptive") and isolated and keep.any():
        iso = reject_isolated(
            {**surf, "image_shape": (R, C)},
            keep,
            fwhm=_irf_fwhm(irf),
            pfa=surface_pfa,
            n_bins=T,
        )
        n_isolated = int(iso.sum())
        keep &= ~iso
    n_dark = 0
    if opts.get("keep_suspects") and keep.size:
        res = rescue_dark(
            {**surf, "image_shape": (R, C)},
            keep,
            irf=irf,
            peak=np.asarray(corr.peak),
            fwhm=_irf_fwhm(irf),
            half=int(scales_arr.max()) // 2,
            pfa=surface_pfa,
            llr_level=-presence_llr,
        )
        n_dark = int(res.sum())
        keep |= res
    del surf["own_counts"], surf["own_background"]
    # --- slope recovery (issue #3; _slopes.py): sheared pooled tests in the holes ----
    n_slopes = 0
    if slopes and presence in ("auto", "adaptive") and keep.any():
        t0 = time.perf_counter()
        rec = recover_slopes(
            cube.counts,
            {k: surf[k][keep] for k in ("row", "col", "depth_bin", "presence_llr")},
            spatial=spatial,
            dev=dev,
            irf=irf,
            scales=scales_arr,
            width=opts["width"],
            fwhm=_irf_fwhm(irf),
            surface_pfa=surface_pfa,
            presence_llr=presence_llr,
            max_surfaces=max_surfaces,
            qloc=_local_scale(scales_arr),
            pixels=slopes,
            seed=int(rng.integers(2**31)),
            n_jobs=n_jobs,
        )
        n_slopes = int(rec["row"].size)
        if n_slopes:
            rec["saliency_mass"], rec["evidence"] = support_sums(
                saliency, threshold, rec["row"], rec["col"], rec["start"], rec["stop"]
            )
            # a recovered surface replaces a kept one of its pixel within 2 FWHM of it
            # (the same return, its depth biased by the square boxes)
            keep[np.flatnonzero(keep)[rec["replaces"]]] = False
            for k in surf:
                surf[k] = np.concatenate([surf[k], rec[k].astype(surf[k].dtype)])
            keep = np.concatenate([keep, np.ones(n_slopes, bool)])
            # their histograms are the pass's own (block -1)
            hist_block = np.concatenate([hist_block, np.full(n_slopes, -1, np.int64)])
            hist_row = np.concatenate([hist_row, np.arange(n_slopes, dtype=np.int64)])
            rec_hist = rec["histograms"]
        timings["slopes"] = time.perf_counter() - t0
    # --- end of slope recovery ---------------------------------------------------------
    # an empty pixel that a surface encloses (both opposite pairs of 4-neighbours at its
    # depth) and whose local scale is significant keeps its candidate even with no own
    # photons there (_quality.restore_enclosed; after the slope recovery, which it would
    # otherwise deprive of the holes it grows from)
    if opts.get("keep_suspects") and keep.size and not keep.all():
        enc = restore_enclosed(
            {**surf, "image_shape": (R, C)},
            keep,
            fwhm=_irf_fwhm(irf),
            z_level=presence_z,
            max_kept=max_surfaces,
            llr_level=presence_secondary,
        )
        n_dark += int(enc.sum())
        keep |= enc
    idx, slot = _select(surf, keep, max_surfaces)
    surf = {k: v[idx] for k, v in surf.items()}
    surf["slot"] = slot
    # one gather of the selected surfaces' histograms from the blocks' arrays (and the
    # slope recovery's)
    hist = np.empty((idx.size,) + outs[0].histograms.shape[1:], np.float32)
    hb, hr = hist_block[idx], hist_row[idx]
    for b, o in enumerate(outs):
        sel = np.flatnonzero(hb == b)
        if sel.size:
            hist[sel] = o.histograms[hr[sel]]
    sel = np.flatnonzero(hb == -1)
    if sel.size:
        hist[sel] = rec_hist[hr[sel]]
    surf["histograms"] = hist
    del hist_block, hist_row
    n_aligned = 0
    if refine and presence in ("auto", "adaptive") and idx.size:
        # a depth that its 4-neighbours and its own counts place elsewhere (a box's
        # lobe of a neighbouring row on a steep slope) moves (_quality.align_depths)
        surf["depth_bin"], n_aligned = align_depths(
            surf["row"], surf["col"], surf["slot"], surf["depth_bin"], surf["offset"],
            hist[:, 0].sum(axis=1), image_shape=(R, C), n_slots=max_surfaces,
            fwhm=_irf_fwhm(irf),
        )  # fmt: skip
    for o in outs:
        o.histograms = None
    Q = scales_arr.size
    W = opts["width"]
    if surf["row"].size == 0:
        surf["histograms"] = np.zeros((0, Q, L, W), np.float32)
    surfaces = Surfaces(
        row=surf["row"].astype(np.int64),
        col=surf["col"].astype(np.int64),
        slot=surf["slot"].astype(np.int64),
        depth_bin=surf["depth_bin"].astype(np.float64),
        start=surf["start"].astype(np.int64),
        stop=surf["stop"].astype(np.int64),
        scale_index=surf["scale_index"].astype(np.int64),
        offset=surf["offset"].astype(np.int64),
        histograms=surf["histograms"],
        signal=surf["signal"].reshape(-1, Q, L),
        counts=surf["counts"].reshape(-1, L),
        background=surf["background"].reshape(-1, L),
        saliency_mass=surf["saliency_mass"].astype(np.float64),
        evidence=surf["evidence"].astype(np.float64),
        presence_llr=surf["presence_llr"].astype(np.float64),
        presence_z=surf["presence_z"].astype(np.float64),
        image_shape=(R, C),
        n_slots=max_surfaces,
    )
    timings["quality_and_selection"] = time.perf_counter() - t0
    n_ph = sum(o.n_photons for o in outs)
    n_kept = sum(o.n_photons_kept for o in outs)
    n_vox = sum(o.n_voxels for o in outs)
    reduction = DataReduction(
        voxel_fraction=n_vox / (R * C * T),
        photon_fraction=n_kept / n_ph if n_ph else 0.0,
        n_voxels=n_vox,
        n_photons=n_kept,
    )
    timings["total"] = time.perf_counter() - t_start
    options = MappingProxyType(
        dict(
            scales=tuple(int(k) for k in scales_arr),
            weights=tuple(float(x) for x in w),
            pfa=pfa,
            max_surfaces=max_surfaces,
            surface_pfa=surface_pfa,
            null=null,
            presence=presence,
            presence_z=presence_z,
            presence_llr=presence_llr,
            presence_secondary=presence_secondary,
            min_separation=min_sep,
            split_ratio=split_ratio,
            refine=refine,
            block_rows=block_rows,
            n_jobs=n_jobs,
            store=None if store is None else str(store),
            window=W,
            n_candidates=int(sum(o.n_candidates for o in outs)),
            n_rejected=int(sum(o.n_rejected for o in outs)) + n_spill + n_isolated,
            spill_llr=spill_llr,
            isolated=isolated,
            dark=dark,
            n_dark=n_dark,
            n_spill_over=n_spill,
            n_isolated=n_isolated,
            slopes=slopes,
            n_slopes=n_slopes,
            n_aligned=n_aligned,
        )
    )
    logger.info(
        "detect: %d surfaces in %d x %d px (%d candidates, %d rejected by evidence or presence); "
        "mask keeps "
        "%.3g%% of voxels and %.3g%% of photons; %.2f s",
        len(surfaces),
        R,
        C,
        options["n_candidates"],
        options["n_rejected"],
        100 * reduction.voxel_fraction,
        100 * reduction.photon_fraction,
        timings["total"],
    )
    return Detection(
        cube_shape=(R, C, L, T),
        irf=cube.irf,
        bin_width_ps=cube.bin_width_ps,
        wavelengths_nm=cube.wavelengths_nm,
        library=cube.library,
        scales=tuple(int(k) for k in scales_arr),
        weights=w,
        pfa=pfa,
        background=Background(spatial=spatial, temporal=temporal.astype(np.float32)),
        saliency=saliency,
        null=null_model,
        threshold=threshold,
        mask=mask,
        reduction=reduction,
        surfaces=surfaces,
        timings=MappingProxyType(timings),
        options=options,
    )
