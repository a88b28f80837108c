"""Stage 5f (clean-up): remove small stray clusters of a pixel's further surfaces.

A pixel that holds two kept candidates, one of them in a small cluster of same-depth
candidates (at most :data:`MAX_CLUSTER`, 8-connected, depths within :data:`GATE_FWHM`
FWHM of a neighbour's) that nothing else at that depth joins within
:data:`REACH_BOXES` x the largest box's half-width (15 pixels with the default scales),
keeps its other candidate only. A large cluster within the reach joins it; small
clusters within the reach of one another join only as a group of more than
:data:`MAX_CLUSTER` members (the fragments of a thin structure whose other pixels the
map missed): two or three stray clusters at one depth do not vouch for one another.
A true surface continues into its neighbours (a region, a line or the fragments of one
along a thin structure); the spatial pooling's false alarms behind a pixel's own surface
(the "background" and "window edge" kinds of issue #15's false surfaces) come in
clusters of 1-4 pixels at a depth no other surface nearby holds, which stage 5b (a
single pixel without a same-depth neighbour) does not see. A pixel's only candidate is
never removed, nor a neighbour's spread (a surface at its depth lies beside it).

Measured (``benchmarks/README.md``, "Issue #15 point 5, session 13"): single surface,
PPP 4, SBR 0.25, 96 x 80, seeds 0-2, false surfaces 147.7 -> 126.7 (uniform), 182.0 ->
160.0 (decaying; background kind 27.0 -> 13.3 and 31.0 -> 17.7, window edge 12.7 -> 5.3
and 20.0 -> 11.3) with F_true unchanged in every cube; the sheet and the net (a partly
transmissive layer) the same F_true in every cube, fewer false surfaces. The group rule
(session 16, depth23): 121.7 -> 118.3 / 153.0 -> 149.3 at the later main, background kind
13.7 -> 11.7 and 17.7 -> 15.0, window edge 5.3 -> 4.0 and 11.3 -> 10.3, F_true the same.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

from ._table import CandidateTable, PassResult, skipped, with_keep

__all__ = ["GATE_FWHM", "MAX_CLUSTER", "REACH_BOXES", "remove_stray_clusters"]

#: Candidates of neighbouring pixels whose depths differ by at most this many FWHM are
#: one cluster, and a candidate this close in depth within the reach joins it (9 bins at
#: FWHM 3). On the Art scene (PPP 4, SBR 1, curved surfaces) 1.5 FWHM with a reach of 10
#: pixels removed 22 true surfaces with 33 false ones, 3 FWHM with 15 pixels 1 with 19.
GATE_FWHM = 3.0
#: A cluster of at most this many candidates can be a stray one. Issue #15's cells
#: (seeds 0-2, gate 1.5 FWHM, reach 10): at most 2 -> 128.3 / 159.0 false surfaces
#: (uniform / decaying), 4 -> 119.3 / 148.0, 6 -> 115.7 / 144.3, the same F_true.
MAX_CLUSTER = 4
#: The reach searched for other candidates at the cluster's depth, in half-widths of the
#: largest box (15 pixels with the default 11 x 11): at 5 pixels the net under a
#: decaying background lost 2-11 strand surfaces per cube (fragments of a strand whose
#: neighbours the map missed), at 10 none; Art (above) wants 15.
REACH_BOXES = 3


@njit(cache=True, nogil=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True, nogil=True)
def _stray_kernel(row, col, depth, keep, R, C, gate, max_size, reach, out):
    """``out[i] = True`` for the kept candidates to remove (see the module)."""
    n = row.size
    head = np.full(R * C, -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    count = np.zeros(R * C, np.int64)
    for i in range(n - 1, -1, -1):
        if keep[i]:
            p = row[i] * C + col[i]
            nxt[i] = head[p]
            head[p] = i
            count[p] += 1
    parent = np.arange(n)
    dr4 = (0, 1, 1, 1)
    dc4 = (1, -1, 0, 1)
    for i in range(n):
        if not keep[i]:
            continue
        for m in range(4):
            r, c = row[i] + dr4[m], col[i] + dc4[m]
            if r < 0 or r >= R or c < 0 or c >= C:
                continue
            k = head[r * C + c]
            while k >= 0:
                if abs(depth[k] - depth[i]) <= gate:
                    a, b = _find(parent, i), _find(parent, k)
                    if a != b:
                        parent[a] = b
                k = nxt[k]
    root = np.empty(n, np.int64)
    size = np.zeros(n, np.int64)
    for i in range(n):
        if keep[i]:
            root[i] = _find(parent, i)
            size[root[i]] += 1
    _group_kernel(
        row, col, depth, keep, head, nxt, count, root, size, R, C, gate, max_size, reach, out
    )


@njit(cache=True, nogil=True)
def _group_kernel(
    row, col, depth, keep, head, nxt, count, root, size, R, C, gate, max_size, reach, out
):
    """Small clusters within the reach at one depth form a group; a group joins when one
    of its clusters has a large cluster within the reach, or its members number more
    than ``max_size``; ``out[i]`` for the crowded pixels' members of the other groups."""
    n = row.size
    parent = np.arange(n)
    big = np.zeros(n, np.bool_)
    for i in range(n):
        if not keep[i] or size[root[i]] > max_size or big[root[i]]:
            continue
        for r in range(max(row[i] - reach, 0), min(row[i] + reach + 1, R)):
            for c in range(max(col[i] - reach, 0), min(col[i] + reach + 1, C)):
                k = head[r * C + c]
                while k >= 0:
                    if root[k] != root[i] and abs(depth[k] - depth[i]) <= gate:
                        if size[root[k]] > max_size:
                            big[root[i]] = True
                        else:
                            a, b = _find(parent, root[i]), _find(parent, root[k])
                            if a != b:
                                parent[a] = b
                    k = nxt[k]
    total = np.zeros(n, np.int64)
    joined = np.zeros(n, np.bool_)
    for i in range(n):
        if keep[i] and root[i] == i and size[i] <= max_size:
            g = _find(parent, i)
            total[g] += size[i]
            joined[g] |= big[i]
    for i in range(n):
        if not keep[i] or count[row[i] * C + col[i]] < 2 or size[root[i]] > max_size:
            continue
        g = _find(parent, root[i])
        out[i] = not (joined[g] or total[g] > max_size)


def stray_clusters(row, col, depth, keep, *, image_shape, fwhm: float, half: int) -> np.ndarray:
    """The kept candidates that are stray clusters' members in a crowded pixel: (n,) bool.

    Parameters
    ----------
    row, col : ndarray (n,), int
        Pixel of each candidate.
    depth : ndarray (n,), float
        Depth (bins).
    keep : ndarray (n,), bool
        The kept candidates (the others are ignored).
    image_shape : (rows, cols)
    fwhm : float
        The IRF's FWHM (bins): the depth gate is :data:`GATE_FWHM` x ``fwhm``.
    half : int
        The largest box's half-width (pixels): the reach is :data:`REACH_BOXES` x ``half``.
    """
    R, C = image_shape
    out = np.zeros(np.size(row), np.bool_)
    if out.size:
        _stray_kernel(
            np.ascontiguousarray(row, np.int64), np.ascontiguousarray(col, np.int64),
            np.ascontiguousarray(depth, np.float64), np.ascontiguousarray(keep, np.bool_),
            int(R), int(C), float(GATE_FWHM * fwhm), int(MAX_CLUSTER),
            int(max(REACH_BOXES * half, 1)), out,
        )  # fmt: skip
    return out


def remove_stray_clusters(table: CandidateTable, *, fwhm: float, half: int) -> PassResult:
    """Remove kept candidates of crowded pixels that form small stray clusters.

    Parameters
    ----------
    table : CandidateTable
    fwhm : float
        The IRF's FWHM (bins).
    half : int
        The largest box's half-width (pixels).
    """
    if not table.keep.any():
        return skipped("stray_clusters", table)
    t0 = time.perf_counter()
    c = table.columns
    stray = stray_clusters(
        c["row"], c["col"], c["depth_bin"], table.keep, image_shape=table.image_shape,
        fwhm=fwhm, half=half,
    )  # fmt: skip
    return with_keep("stray_clusters", table, table.keep & ~stray, t0)
