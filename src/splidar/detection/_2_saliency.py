"""Stage 2: multiscale statistics and saliency of a block of pixels (``eq:4.s1``).

The matched filter along t, box filters at every scale ``k_q``, the pixel's background
level (``eq:background_2``), ``bhat`` (``eq:background_3``) and the saliency
``S = sum_l |sum_q lambda_q Box_q(Y (*) g) - bhat|``, in one fused numba kernel per
wavelength (:func:`~splidar.detection._fast.saliency_wavelength`). The same function
serves the data (stage 4, block by block) and the background-only cubes of the null
(stage 3), so that both see exactly the same filters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._background import CLIP
from ._fast import saliency_wavelength
from ._filters import Correlator, fisher_sums

__all__ = ["STRIP_COLS", "SaliencyFilters", "block_saliency", "saliency_filters"]

#: Columns the saliency kernel filters together, each strip's rows in turn (the rows a
#: strip's boxes read stay in cache): CPU per voxel and wavelength on a 40 x 200 x 1500
#: block, 9.3-10.3 ns at full width, 6.9-7.4 ns at strips of 24-64. The result does not
#: depend on it (the column sums carry over from strip to strip).
STRIP_COLS = 32


@dataclass(frozen=True)
class SaliencyFilters:
    corr: Correlator
    scales: np.ndarray  # (Q,) ascending
    weights: np.ndarray  # (Q,)
    dev: np.ndarray  # (L, T) float32: bbar - mean_t bbar
    var_factor: np.ndarray  # (L,)
    workers: int
    gsq: np.ndarray = None  # (L,) sum of g^2
    fisher: np.ndarray = None  # (L, 3): sum g'^2, sum g g'^2, peak curvature (_fisher_sums)
    quantum: np.ndarray = None  # (L,) max g / K^2: one photon in a coarse voxel


def saliency_filters(
    corr: Correlator, scales: np.ndarray, weights: np.ndarray, dev: np.ndarray, irf: np.ndarray
) -> SaliencyFilters:
    """The filter set-up shared by every block: scales, weights, ``bbar`` and IRF sums."""
    K = int(scales.max())
    return SaliencyFilters(
        corr,
        scales,
        weights,
        dev,
        (irf**2).sum(axis=1) / K**2,
        workers=1,
        gsq=(irf**2).sum(axis=1),
        fisher=fisher_sums(irf),
        quantum=irf.max(axis=1) / K**2,
    )


def block_saliency(
    y, ctx: SaliencyFilters, spatial=None, keep=None, c=None, sal_out=None, work=None, box=None,
    cols=None, with_level=True,
):  # fmt: skip
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
    cols : (slice, int, ndarray or None), optional
        ``(keep_cols, strip, carry)`` of :func:`~splidar.detection._fast.saliency_wavelength`
        (``carry`` (L, r_keep, Q, T) float64); the outputs then have the kept columns
        only. Default: every column, in strips of :data:`STRIP_COLS`.
    with_level : bool
        Return ``level``; False: None (not accumulated; ``sum_l bhat`` follows from
        ``spatial`` and ``ctx.dev``, as the threshold pass computes it).

    Returns
    -------
    c : (r, c, L, T) float32   correlated counts ``Y (*) g`` (all rows)
    sal : (r, c, T) float32    ``eq:4.s1``
    d : (r, c, T) float32      ``sum_l sum_q lambda_q Box_q(c) - bhat`` (signed)
    spatial : (r, c, L) float32
    level : (r, c, T) float32  ``sum_l bhat`` (None unless ``with_level``)
    """
    if c is None:
        c = ctx.corr(y, workers=ctx.workers)
    keep = slice(None) if keep is None else keep
    r_all, cc, L, T = c.shape
    r = len(range(*keep.indices(r_all)))
    keep_cols, strip, carry = (slice(None), STRIP_COLS, None) if cols is None else cols
    cc = len(range(*keep_cols.indices(cc)))
    # the first wavelength writes sal, d and level, the others add to them
    sal = np.empty((r, cc, T), np.float32) if sal_out is None else sal_out
    if work is None:
        d = np.empty((r, cc, T), np.float32)
        level = np.empty((r, cc, T), np.float32) if with_level else None
    else:  # reused buffers of a run of blocks (no fresh pages per block)
        d = work["d"].reshape(-1)[: r * cc * T].reshape(r, cc, T)
        level = np.empty((r, cc, T), np.float32) if with_level else None
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
            keep_cols=keep_cols,
            strip=strip,
            carry=None if carry is None else carry[l],
        )
        if spatial is None:
            sp_out[:, :, l] = sp_l
    return c, sal, d, sp_out, level
