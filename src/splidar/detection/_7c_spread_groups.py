"""Stage 7c (clean-up, **off**: :data:`SPREAD_GROUPS`): a pixel's further surfaces tested
by group on their own counts.

Beside a depth edge the multiscale boxes pool a region's return into the pixels of its
neighbour, which keep their own surface and gain the neighbour's depth as a further one
(the "spread" kind of issue #15's false surfaces, the largest left at point 5's figures;
benchmarks/README.md "near27, session 19"). Their own raw counts hold no return at that
depth. One pixel's counts at 0.3-2 photons cannot show it (falsesurf3, false24), so the
surfaces of the pixels holding two or more (the *candidates*) are joined into groups,
8-connected with depths within :data:`GATE_FWHM` FWHM of each other, and each group's own
counts decide together: the joint log-likelihood ratio of a return at its members'
depths against each pixel's own background (stage 1, ``Background.at``), one intensity
``s`` shared by the group and profiled out,

    ``L_G = max_{s >= 0} sum_{p in G} [sum_t y_pt log(1 + s g_pt / b_pt) - s sum_t g_pt]``

(stage 7b's :func:`~splidar.detection._7b_edge_bands.profile_llr` summed over the group
before the maximum). A candidate is removed when ``L_G`` is below the prior log-odds
``log((1 - q) / q)``, ``q`` the fraction of the pixels holding a surface that hold two or
more on this detection (measured, as stage 7b's Potts weight), and only where

* another surface of its pixel passes (a pixel never loses every surface; a dim pixel
  whose own surface fails is left as it is), and
* the candidate's depth does not *continue* through its pixel: fewer than
  :data:`AXES` of the 4 axes through the pixel (left-right, up-down, the diagonals) hold
  a surface within the gate of its depth on both sides, within :data:`REACH` pixels. A
  neighbour's spread has its region on one side only; an object seen on both sides of a
  net's strand, or a layer's interior, was pooled rightly even where the own counts say
  nothing.

Why off (benchmarks/README.md, "spread28, session 20"; ``benchmarks/bench_spread_groups.py``
on the 24 cubes of ``bench_edge_bands.py``): issue #15's single-surface cells, seeds 0-2,
false surfaces 92.7 -> 65.0 (uniform) and 122.0 -> 84.7 (decaying) at F_true 0.9786 ->
0.9786 and 0.9803 -> 0.9802, but the sheet and the net lose true surfaces in every cell
(F_true -0.0002 to -0.0024 per cell: strand fragments and objects behind a layer whose
neighbours lost them at PPP 4, with own counts that say nothing): "nothing worse on any
benchmark" does not hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from ._7b_edge_bands import _windows, group_llr

__all__ = ["AXES", "GATE_FWHM", "REACH", "SPREAD_GROUPS", "SpreadGroups", "spread_groups"]

#: Off: measured, not adopted (see the module). ``detect`` does not run the stage.
SPREAD_GROUPS = False
#: Candidates of 8-neighbouring pixels whose depths differ by at most this many FWHM are
#: one group (stage 7b's region gate: 4.5 bins at FWHM 3).
GATE_FWHM = 1.5
#: A candidate is tested only when fewer than this many axes through its pixel continue
#: its depth on both sides. 2: a surface continuing along one axis only (a line beside a
#: depth edge, a layer's straight edge) is tested; 1 (with :data:`REACH` 2): only
#: surfaces continuing nowhere (single cells 92.7 -> 68.0 / 122.0 -> 95.0, the net's
#: and the sheet's losses smaller but not gone).
AXES = 2
#: Pixels along an axis searched for the depth on each side.
REACH = 1
_DIRS = (((0, 1), (0, -1)), ((1, 0), (-1, 0)), ((1, 1), (-1, -1)), ((1, -1), (-1, 1)))


@dataclass(frozen=True)
class SpreadGroups:
    """The surfaces to remove (indices, ascending), the level (nats), each candidate's
    index, group and its group's ``L_G`` (nats), and whether it was tested."""

    remove: np.ndarray
    level: float
    candidates: np.ndarray
    group: np.ndarray
    group_llr: np.ndarray
    tested: np.ndarray


def _slots(row, col, idx, shape) -> np.ndarray:
    """(R, C, K) int64: the indices ``idx`` of the surfaces in each pixel, -1 padded."""
    R, C = shape
    pix = row[idx] * C + col[idx]
    order = np.argsort(pix, kind="stable")
    p = pix[order]
    start = np.searchsorted(p, p, side="left")
    k = np.arange(p.size) - start
    out = np.full((R * C, max(int(k.max(initial=-1)) + 1, 1)), -1, np.int64)
    out[p, k] = idx[order]
    return out.reshape(R, C, -1)


def _shift(a: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """``out[r, c] = a[r + dr, c + dc]`` (-1 outside the image), over the first two axes."""
    R, C = a.shape[:2]
    out = np.full_like(a, -1)
    out[max(-dr, 0) : R - max(dr, 0), max(-dc, 0) : C - max(dc, 0)] = a[
        max(dr, 0) : R - max(-dr, 0), max(dc, 0) : C - max(-dc, 0)
    ]
    return out


def candidate_groups(row, col, depth, cand, shape, gate: float) -> np.ndarray:
    """(n,) int64 labels of the candidates ``cand``: 8-connected components, depths of
    neighbours within ``gate`` bins joined."""
    slots = _slots(row, col, cand, shape)
    pos = np.full(row.size, -1, np.int64)
    pos[cand] = np.arange(cand.size)
    a, b = [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        other = _shift(slots, dr, dc)
        for k1 in range(slots.shape[2]):
            for k2 in range(slots.shape[2]):
                i, j = slots[..., k1], other[..., k2]
                ok = (i >= 0) & (j >= 0)
                i, j = i[ok], j[ok]
                near = np.abs(depth[i] - depth[j]) <= gate
                a.append(pos[i[near]])
                b.append(pos[j[near]])
    a, b = np.concatenate(a), np.concatenate(b)
    g = sparse.coo_matrix((np.ones(a.size), (a, b)), shape=(cand.size, cand.size))
    return csgraph.connected_components(g.tocsr(), directed=False)[1].astype(np.int64)


def continued_axes(row, col, depth, cand, shape, gate: float, reach: int) -> np.ndarray:
    """(n,) int64: per candidate, how many of the 4 axes through its pixel hold a surface
    (any of the pixel's neighbours' surfaces) within ``gate`` bins of its depth on both
    sides, within ``reach`` pixels along the axis."""
    slots = _slots(row, col, np.arange(row.size), shape)
    r, c, d = row[cand], col[cand], depth[cand]
    out = np.zeros(cand.size, np.int64)
    for ends in _DIRS:
        both = np.ones(cand.size, bool)
        for dr, dc in ends:
            side = np.zeros(cand.size, bool)
            for k in range(1, int(reach) + 1):
                nb = _shift(slots, k * dr, k * dc)[r, c]  # (n, K)
                dn = np.where(nb >= 0, depth[np.maximum(nb, 0)], np.inf)
                side |= (np.abs(dn - d[:, None]) <= gate).any(axis=1)
            both &= side
        out += both
    return out


def spread_groups(
    row, col, depth, image_shape, counts, background, *, fwhm: float, irf, axes=AXES, reach=REACH
) -> SpreadGroups:
    """Stage 7c's decision on the surfaces at ``(row, col, depth)`` (see the module).

    Parameters
    ----------
    row, col : ndarray (S,) int
    depth : ndarray (S,) float
        Bins (after stage 7b).
    image_shape : (int, int)
    counts : ndarray (rows, cols, L, T)
        The cube's raw counts.
    background : Background
    fwhm : float
        The IRF's FWHM (bins).
    irf : ndarray (L, n_irf)
    axes, reach : int
        :data:`AXES`, :data:`REACH`.

    Returns
    -------
    SpreadGroups
    """
    row, col = np.asarray(row, np.int64), np.asarray(col, np.int64)
    depth = np.asarray(depth, np.float64)
    R, C = image_shape
    pix = row * C + col
    n_at = np.bincount(pix, minlength=R * C)
    cand = np.flatnonzero(n_at[pix] >= 2)
    q = float((n_at >= 2).sum()) / max(int((n_at >= 1).sum()), 1)
    level = float(np.log((1.0 - q) / q)) if 0.0 < q < 1.0 else 0.0
    none = np.zeros(0, np.int64)
    if cand.size == 0:
        return SpreadGroups(none, level, cand, none, np.zeros(0), np.zeros(0, bool))
    gate = GATE_FWHM * float(fwhm)
    group = candidate_groups(row, col, depth, cand, image_shape, gate)
    y, g, b = _windows(counts, background, row[cand], col[cand], depth[cand], irf)
    llr = group_llr(y, g, b, group)[group]
    tested = continued_axes(row, col, depth, cand, image_shape, gate, reach) < int(axes)
    fail = tested & (llr < level)
    passes = np.bincount(pix[cand], weights=~fail, minlength=R * C)
    remove = cand[fail & (passes[pix[cand]] >= 1)]
    return SpreadGroups(np.sort(remove), level, cand, group, llr, tested)
