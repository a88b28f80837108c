"""Stage 7b's rules (``"edge_bands"``): the bands beside depth edges decided together.

These rules decide depths (:func:`band_depths`); stage 7 (``_7_depths.place_depths``) runs
them after stage 7's own (``_7a_align_depths``) and the moved surfaces' fields follow
once, after both (``_depth_fields``).

Beside a depth edge the multiscale boxes pool a bright region B's returns into the dim
pixels of its neighbour A: a band of A's pixels takes B's depth. Per pixel the own
counts (0.3-2 photons) cannot tell A from B (benchmarks/README.md, "false24, session
17": with oracle proposals 33-42 % of such pixels would move right, with the
4-neighbours' about 2 per cube); summed over the band they can. So the single-surface
pixels are grouped into regions (8-connected, depths within :data:`GATE_FWHM` FWHM of
a neighbour's, at least :data:`MIN_REGION` members), and the pixels of two adjacent
regions A and B within the largest box's half-width of the other region (the reach of
the pooling) are labelled A or B jointly by a Potts Markov random field. Its data
terms are the own raw counts' Poisson log-likelihood ratio of a return at each
region's local depth plane (a robust least-squares plane over the region's members
within twice that reach, extrapolated to the pixel: slopes and ramps exist, a median
would not follow them) against background alone, the return's intensity ``s`` profiled
out (:func:`profile_llr`),

    ``L_X(p) = max_s sum_t y_t log(1 + s g(t - d_X(p)) / b_t) - s sum_t g(t - d_X(p))``

(the statistic of stages 5 and 7, ``b`` stage 1's background): only where the return
lies is compared, since a region's intensity misleads in a dark stripe that shares its
depth. The pairwise cost ``beta`` is paid per pair of 4-neighbours with different
labels: ``beta = log((1 - p) / p)`` with ``p`` the fraction of 4-neighbour pairs of
single-surface pixels that lie in different regions on this detection (the prior odds
that two neighbours belong to one region: measured, not tuned). The labelling is solved
exactly by a minimum s-t cut (Greig, Porteous and Seheult 1989;
``scipy.sparse.csgraph.maximum_flow``) with the pixels outside the band fixed at their
regions. The prior shapes a band but never moves one: a pair's relabelling is kept
only when the own counts of the pixels it moves favour the move in sum (without, the
prior erased the object's cells between a net's strands). A pixel whose label changes
moves to the other region's plane; its fields follow the depth as in stage 7's far
rule. Multi-surface pixels (layers, nets) and small clusters are left alone and offer
no depth.

Then (:data:`NEAR_DEPTHS`) a region's member more than :data:`NEAR_FWHM` FWHM off its
own region's local plane (the plane through the other members), inside its region (at
least :data:`NEAR_INSIDE` of its 8-neighbours members) and not sharing that offset with
two of its 8-neighbours, is offered the plane's depth, with the same profile likelihood
and a prior measured on the detection (:func:`near_depths`): the "near" wrong depths,
a pixel's own peak moved a few bins by a Poisson fluctuation, which the labelling of
two regions never sees. Last (:data:`FAR_INSIDE`), a lone single-surface pixel inside a
region but not a member of it (its depth far off the region's plane and shared by no
8-neighbour) is offered the plane the same way (:func:`far_inside_depths`). (A fourth
rule, stage 5c's restorations beside another region decided by band on their summed own
counts, ``dark_bands``, was removed in session 22: benchmarks/README.md, "abl30, session
22", its effect inside run-to-run noise and nil on the measured files.)

A straight band shifted by a row costs no more boundary than before, so the prior does
not pull edges; it keeps a lone pixel (4 ``beta``) or a ragged boundary from moving on
a fraction of a nat, and the data of the whole band decides where the edge lies.
Measured (``benchmarks/bench_edge_bands.py``, benchmarks/README.md "edge25, session
18"): single surface PPP 4, SBR 0.25, seeds 0-2 per cube, false surfaces 118.0 ->
113.3 (uniform), 149.0 -> 141.7 (decaying), F_true 0.9753 -> 0.9759, 0.9767 -> 0.9777;
every sheet and net cell better or equal; with ``beta = 0`` (every pixel alone) 146-159
true surfaces moved off per cube. With the near depths (``NEAR_DEPTHS``; "near26,
session 18", and its inside condition, "near27, session 19"): see :data:`NEAR_INSIDE`.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit
from scipy import sparse
from scipy.sparse import csgraph

from ._depth_fields import _pixels
from ._quality import _shifted_irf
from ._result import Surfaces
from ._slopes import sparse_of
from ._threads import on_parts

__all__ = [
    "FAR_INSIDE",
    "GATE_FWHM",
    "MIN_REGION",
    "NEAR_FWHM",
    "NEAR_INSIDE",
    "band_depths",
]

#: Neighbouring single-surface pixels whose depths differ by at most this many FWHM are
#: one region (4.5 bins at FWHM 3: the benchmark's ramp of 3.2 bins per row stays one
#: region; the wrong depths' clusters, false24 (6), were counted at this gate).
GATE_FWHM = 1.5
#: A region of fewer pixels offers no depth and is not relabelled (stage 5f's stray
#: clusters hold at most 4).
MIN_REGION = 5
#: A region's member more than this many FWHM off its region's local plane (the plane
#: through the other members) is offered the plane's depth (:func:`near_depths`): the
#: "near" wrong depths, a pixel's own peak moved 3-8 bins by a Poisson fluctuation at a
#: few photons. Measured (benchmarks/README.md, "near26, session 18"): on issue #15's
#: single-surface cells the plane lies within 3 bins of the truth for every such wrong
#: depth, and 95 % of the pixels so far off (86-100 % per cube) are wrong depths.
#: Single surface PPP 4, SBR 0.25, seeds 0-2: false surfaces 113.3 -> 89.3 (uniform),
#: 141.7 -> 118.0 (decaying) without :data:`NEAR_INSIDE` (Art at PPP 4 worse).
NEAR_FWHM = 1.0
#: Move the near wrong depths (:func:`near_depths`) in :func:`band_depths`. On since
#: near27 (session 19), with :data:`NEAR_INSIDE`; without it, the paper's Art scene at
#: PPP 4 lost more true surfaces than it fixed (benchmarks/README.md, "near26, session
#: 18").
NEAR_DEPTHS = True
#: A pixel is offered its plane only when at least this many of its 8-neighbours are
#: members of its own region: it lies inside the region, at most one neighbour outside
#: (a lone wrong neighbour or a missed pixel). A pixel on a straight or diagonal border
#: of its region has 3 neighbours outside, at a convex corner 5: there the plane through
#: the other members is an extrapolation across the border, and on curved, finely
#: structured surfaces (the paper's Art, whose single-surface pixels are where one of two
#: surfaces was missed) it is not the pixel's surface. Measured (benchmarks/README.md,
#: "near27, session 19"): Art PPP 4 moves (fixed / true moved off at 1.67 bins) 39 (11 /
#: 20) -> 1 (0 / 0) uniform, 36 (6 / 18) -> 0 decaying; the single-surface cells keep
#: 120 of 143 fixes (3 seeds, both backgrounds), none moved off.
NEAR_INSIDE = 7
#: Move the far depths inside a region (:func:`far_inside_depths`) in
#: :func:`band_depths`: a single-surface pixel that is not a member of the region
#: holding at least :data:`NEAR_INSIDE` of its 8-neighbours, its depth more than the
#: region's gate off that region's plane and shared by none of its 8-neighbours' surfaces
#: (any slot), offered the plane with a prior measured on the detection. Measured
#: (benchmarks/README.md, "far28, session 20").
FAR_INSIDE = True
#: Max-flow capacities are integers: nats times this.
_SCALE = 1000.0
#: Pixels per block of the likelihoods ((block, L, T) float64 arrays).
_BLOCK = 4096


def region_labels(depth: np.ndarray, gate: float) -> np.ndarray:
    """8-connected components of the finite entries of ``depth`` (R, C) whose neighbours'
    depths differ by at most ``gate`` bins: (R, C) int64 labels, -1 where NaN.

    The labels are those of ``scipy.sparse.csgraph.connected_components`` over every
    pixel of the image (a NaN pixel its own component): numbered in the order of each
    component's first pixel (row-major), NaN pixels' numbers skipped
    (:func:`_region_kernel`, a union-find; ``tests/test_edge_bands.py``)."""
    depth = np.ascontiguousarray(depth, np.float64)
    out = np.empty(depth.shape, np.int64)
    _region_kernel(depth, float(gate), out)
    return out


@njit(cache=True, nogil=True)
def _region_kernel(depth, gate, out):  # pragma: no cover - numba
    """:func:`region_labels` into ``out``: each pixel joined to its right, lower-left,
    lower and lower-right neighbours within ``gate`` (both finite), every component's
    root its first pixel (the smaller root wins a union), then the roots numbered in
    row-major order with every NaN pixel taking a number of its own."""
    R, C = depth.shape
    root = np.arange(R * C)
    for r in range(R):
        for c in range(C):
            z = depth[r, c]
            if not np.isfinite(z):
                continue
            for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
                rr, cc = r + dr, c + dc
                if rr >= R or cc < 0 or cc >= C:
                    continue
                y = depth[rr, cc]
                if np.isfinite(y) and abs(z - y) <= gate:
                    a, b = _find(root, r * C + c), _find(root, rr * C + cc)
                    if a < b:
                        root[b] = a
                    elif b < a:
                        root[a] = b
    num = np.empty(R * C, np.int64)
    n = 0
    for i in range(R * C):
        a = _find(root, i)
        if a == i:
            num[i] = n
            n += 1
        else:
            num[i] = num[a]  # the root comes first: numbered already
    for r in range(R):
        for c in range(C):
            out[r, c] = num[r * C + c] if np.isfinite(depth[r, c]) else -1


@njit(cache=True, nogil=True, inline="always")
def _find(root, i):  # pragma: no cover - numba
    """The root of ``i`` in the union-find ``root``, the path halved on the way."""
    while root[i] != i:
        root[i] = root[root[i]]
        i = root[i]
    return i


def potts_weight(labels: np.ndarray) -> float:
    """``log((1 - p) / p)``, ``p`` the fraction of 4-neighbour pairs of labelled pixels
    (``labels >= 0``) with different labels (at least one such pair counted), at most
    1/2: labels that change across most pairs carry no evidence of smoothness, and a
    negative weight would reward label changes (negative capacities in the cut; ``p = 1``
    gave ``-inf`` and a divide-by-zero warning on a 3 x 3 image of three regions), so the
    weight is then 0 (no prior: each band by its own counts)."""
    pairs = diff = 0
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1], labels[1:])):
        both = (a >= 0) & (b >= 0)
        pairs += int(both.sum())
        diff += int((both & (a != b)).sum())
    p = min(max(diff, 1) / max(pairs, 2), 0.5)
    return float(np.log((1.0 - p) / p))


@njit(cache=True, nogil=True)
def _band_kernel(lab, depth, half, gate, other, dep, r0, r1):  # pragma: no cover - numba
    """For each pixel of a region in rows ``r0:r1``, ``other[r, c]``: the other region
    with most members within ``half`` (Chebyshev; ties to the lower label), -1 if none;
    then for such pixels the local plane of its own (``dep[..., 0]``) and of the other
    region (``dep[..., 1]``) at the pixel (:func:`_window_plane` over the members within
    ``2 half``). Rows outside ``r0:r1`` are neither read from ``other``/``dep`` nor
    written, so disjoint row ranges run on threads side by side."""
    R, C = lab.shape
    reach = 2 * half
    buf = np.empty((3, (2 * reach + 1) ** 2))
    seen = np.empty((2, (2 * half + 1) ** 2), np.int64)
    for r in range(r0, r1):
        for c in range(C):
            other[r, c] = -1
            own = lab[r, c]
            if own < 0:
                continue
            best = _most_members(lab, r, c, half, own, seen)
            other[r, c] = best
            if best < 0:
                continue
            for j in range(2):
                x = own if j == 0 else best
                dep[r, c, j] = _window_plane(lab, depth, r, c, reach, x, False, gate, 0, buf)


@njit(cache=True, nogil=True)
def _own_plane_kernel(lab, depth, reach, gate, out, r0, r1):  # pragma: no cover - numba
    """For each pixel of a region in rows ``r0:r1``, ``out[r, c]``: its region's local
    plane at the pixel (:func:`_window_plane`) over the other members within ``reach``
    (Chebyshev; the pixel itself left out); NaN elsewhere and with fewer than 3 other
    members. Only rows ``r0:r1`` of ``out`` are written, so disjoint row ranges run on
    threads side by side (the result does not depend on the split)."""
    R, C = lab.shape
    buf = np.empty((3, (2 * reach + 1) ** 2))
    for r in range(r0, r1):
        for c in range(C):
            out[r, c] = np.nan
            x = lab[r, c]
            if x >= 0:
                out[r, c] = _window_plane(lab, depth, r, c, reach, x, True, gate, 3, buf)


@njit(cache=True, nogil=True)
def _most_members(lab, r, c, half, own, seen):  # pragma: no cover - numba
    """The label other than ``own`` (and >= 0) with most pixels within ``half`` of
    ``(r, c)`` (Chebyshev), ties to the lower label; -1 if none. One pass over the
    window counts each label met in ``seen`` (2, at least the window's size: the labels
    in the order met, their counts), looked up from the last label met, then the
    labels seen are compared (the same answer as sorting them)."""
    R, C = lab.shape
    nd = 0
    last, at = -1, -1
    for rr in range(max(r - half, 0), min(r + half + 1, R)):
        for cc in range(max(c - half, 0), min(c + half + 1, C)):
            x = lab[rr, cc]
            if x < 0 or x == own:
                continue
            if x != last:  # a run of another label: find its entry (or add one)
                at = -1
                for j in range(nd):
                    if seen[0, j] == x:
                        at = j
                        break
                if at < 0:
                    at = nd
                    seen[0, nd], seen[1, nd] = x, 0
                    nd += 1
                last = x
            seen[1, at] += 1
    best, n_best = -1, 0
    for j in range(nd):
        x, n = seen[0, j], seen[1, j]
        if n > n_best or (n == n_best and x < best):
            best, n_best = x, n
    return best


def _band_planes(lab, depth, half: int, gate: float, n_jobs: int = 1):
    """``other`` (R, C) int64 and ``dep`` (R, C, 2) of :func:`_band_kernel`, its rows
    split between ``n_jobs`` threads (the kernel releases the GIL; each row's result
    depends on the inputs alone, so the split never changes it)."""
    R, C = lab.shape
    other = np.empty((R, C), np.int64)
    dep = np.full((R, C, 2), np.nan)
    on_parts(
        lambda i0, i1: _band_kernel(lab, depth, int(half), float(gate), other, dep, i0, i1),
        R,
        min(int(n_jobs), R // 16),  # rows of at least 16 per thread
    )
    return other, dep


@njit(cache=True, nogil=True)
def _window_plane(lab, depth, r, c, reach, x, skip_self, gate, min_m, buf):  # pragma: no cover
    """A robust plane through the depths of the pixels labelled ``x`` within ``reach``
    of ``(r, c)`` (Chebyshev; the pixel itself left out when ``skip_self``), evaluated
    at ``(r, c)``: least squares, the members off it by more than ``gate`` dropped,
    least squares again; the median of the members with fewer than 3 non-collinear
    ones (taken only then: a plane's value does not need it); NaN with fewer than
    ``min_m`` members.

    Each fit solves the 3 x 3 normal equations from sums (no design matrix): the
    offsets' sums are integers, exact in float64. The first fit's one scan of the
    window keeps its members' depths and offsets in ``buf`` (3, at least the window's
    size), in the scan's order; the second fit sums those within ``gate`` of the first
    plane in that order (the terms a second scan would add, in its order), and when
    the gate drops none its sums are the first's, so its plane is the first one. The
    members off the first plane are counted without a branch (vectorised: 0.31 -> 0.27
    s of :func:`_own_plane_kernel` on the large cube's 256 rows, bd38)."""
    R, C = lab.shape
    r_lo, r_hi = max(r - reach, 0), min(r + reach + 1, R)
    c_lo, c_hi = max(c - reach, 0), min(c + reach + 1, C)
    m = 0
    s = _NO_MOMENTS
    for rr in range(r_lo, r_hi):
        for cc in range(c_lo, c_hi):
            if lab[rr, cc] != x or (skip_self and rr == r and cc == c):
                continue
            u, v, z = float(rr - r), float(cc - c), depth[rr, cc]
            buf[0, m], buf[1, m], buf[2, m] = z, u, v
            m += 1
            s = _add_moments(s, u, v, z)
    if s[0] < min_m:
        return np.nan
    if _degenerate(s):
        return np.median(buf[0, :m])
    c0, c1, c2 = _solve_sym3(*s)
    n_off = 0
    for i in range(m):  # branch-free, so it vectorises (the same test per member)
        n_off += abs(c0 + c1 * buf[1, i] + c2 * buf[2, i] - buf[0, i]) > gate
    if n_off == 0:
        return c0
    s = _NO_MOMENTS
    for i in range(m):
        z, u, v = buf[0, i], buf[1, i], buf[2, i]
        if abs(c0 + c1 * u + c2 * v - z) > gate:
            continue
        s = _add_moments(s, u, v, z)
    if _degenerate(s):
        return c0
    return _solve_sym3(*s)[0]


# the plane fit's sums (n, sr, sc, srr, src, scc, sd, srd, scd) before any member
_NO_MOMENTS = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@njit(cache=True, nogil=True, inline="always")
def _add_moments(s, u, v, z):  # pragma: no cover - numba
    """The plane fit's 9 sums ``s`` = ``(n, sr, sc, srr, src, scc, sd, srd, scd)``
    with the member at offsets ``(u, v)`` and depth ``z`` added (each sum's terms in
    the members' order, as :func:`_window_plane`'s scans add them)."""
    return (
        s[0] + 1.0, s[1] + u, s[2] + v, s[3] + u * u, s[4] + u * v, s[5] + v * v,
        s[6] + z, s[7] + u * z, s[8] + v * z,
    )  # fmt: skip


@njit(cache=True, nogil=True, inline="always")
def _degenerate(s) -> bool:  # pragma: no cover - numba
    """Fewer than 3 members, or members on one line: no plane through the sums ``s``."""
    return (
        s[0] < 3.0
        or abs(_det_sym3(s[0], s[1], s[2], s[3], s[4], s[5])) < 1e-9 * max(s[0], 1.0) ** 3
    )


@njit(cache=True, nogil=True)
def _solve_sym3(n, sr, sc, srr, src, scc, sd, srd, scd):  # pragma: no cover - numba
    """The plane ``(c0, c1, c2)`` of the normal equations ``[[n, sr, sc], [sr, srr, src],
    [sc, src, scc]] c = [sd, srd, scd]`` by cofactors (the matrix is symmetric)."""
    k00, k01, k02 = srr * scc - src * src, sc * src - sr * scc, sr * src - srr * sc
    k11, k12, k22 = n * scc - sc * sc, sr * sc - n * src, n * srr - sr * sr
    det = n * k00 + sr * k01 + sc * k02
    c0 = (k00 * sd + k01 * srd + k02 * scd) / det
    c1 = (k01 * sd + k11 * srd + k12 * scd) / det
    c2 = (k02 * sd + k12 * srd + k22 * scd) / det
    return c0, c1, c2


@njit(cache=True, nogil=True)
def _det_sym3(n, sr, sc, srr, src, scc):  # pragma: no cover - numba
    """The determinant of the symmetric ``[[n, sr, sc], [sr, srr, src], [sc, src, scc]]``."""
    return n * (srr * scc - src * src) + sr * (sc * src - sr * scc) + sc * (sr * src - srr * sc)


def profile_llr(y, g, b, n_iter: int = 30) -> np.ndarray:
    """``max_{s >= 0} sum_t y_t log(1 + s g_t / b_t) - s sum_t g_t`` per pixel: the
    own counts' log-likelihood ratio of a return at the depth against background
    alone, the return's intensity ``s`` profiled out (one ``s`` over the wavelengths).

    Concave in ``s``: 0 (``s = 0``) when its slope at 0, ``sum_t y_t g_t / b_t - sum_t
    g_t``, is not positive; else Newton steps from the counts' IRF-weighted sum.

    Parameters
    ----------
    y : ndarray (n, L, T)
        Raw counts.
    g : ndarray (n, L, T)
        The IRF with its peak on the depth (sums to 1 per wavelength inside the window).
    b : ndarray (n, L, T)
        Background counts per bin (> 0).
    n_iter : int
        Newton steps.

    Returns
    -------
    ndarray (n,)
        Nats, >= 0.
    """
    y, g, b = (np.ascontiguousarray(a, np.float64) for a in (y, g, b))
    out = np.empty(y.shape[0])
    _profile_llr_kernel(y, g, b, int(n_iter), out)
    return out


@njit(cache=True, nogil=True)
def _profile_llr_kernel(y, g, b, n_iter, out):  # pragma: no cover - numba
    """:func:`profile_llr`, one pixel at a time. The bins without counts add nothing to
    the sums over ``y``: each pixel's bins with counts are gathered first (in the same
    order) and the Newton steps run over them alone, the same sums term by term. A step
    is a function of ``s`` alone, so once one leaves ``s`` as it was (a nonzero fixed
    point, or no step taken) every later one would too: the steps stop there, with the
    same ``s`` to the bit as all ``n_iter`` of them."""
    n, L, W = y.shape
    ya = np.empty(L * W)
    ga = np.empty(L * W)
    ba = np.empty(L * W)
    for i in range(n):
        G = 0.0
        slope = 0.0
        yg = 0.0
        m = 0
        for l in range(L):
            for t in range(W):
                G += g[i, l, t]
                if y[i, l, t] > 0:
                    slope += y[i, l, t] * g[i, l, t] / b[i, l, t]
                    yg += y[i, l, t] * g[i, l, t]
                    ya[m], ga[m], ba[m] = y[i, l, t], g[i, l, t], b[i, l, t]
                    m += 1
        if not slope > G:
            out[i] = 0.0
            continue
        s = max(yg / max(G, 1e-12), 1e-3)
        for _ in range(n_iter):
            d1 = -G
            d2 = 0.0
            for k in range(m):
                q = ya[k] * ga[k] / (ba[k] + s * ga[k])
                d1 += q
                d2 -= q * ga[k] / (ba[k] + s * ga[k])
            if not d2 < 0:
                break  # s stays: every later step the same
            step = max(s - d1 / d2, 0.0)
            if step == s and s != 0.0:
                break  # a fixed point (the same bits): every later step the same
            s = step
        llr = -s * G
        for k in range(m):
            llr += ya[k] * np.log1p(s * ga[k] / ba[k])
        out[i] = max(llr, 0.0)


@njit(cache=True, nogil=True)
def _window_counts(counts, rows, cols, lo, out):  # pragma: no cover - numba
    """``out[i, l, :] = counts[rows[i], cols[i], l, lo[i] : lo[i] + W]`` as float64."""
    W = out.shape[2]
    for i in range(rows.size):
        for l in range(out.shape[1]):
            for k in range(W):
                out[i, l, k] = counts[rows[i], cols[i], l, lo[i] + k]


def _likelihoods(
    counts, background, rows, cols, dep, irf, n_jobs: int = 1, memo: LikelihoodMemo | None = None
) -> np.ndarray:
    """:func:`profile_llr` of the pixels ``(rows, cols)`` at their depths ``dep`` (n, k):
    (n, k), in blocks of pixels on ``n_jobs`` threads (each block's result is its own,
    so the threads never change it). An in-memory cube is read over each depth's window
    alone, and so is a Zarr cube whose nonzero counts detect keeps
    (``_slopes.sparse_of``); others (Dask) a pixel's whole series at once.

    ``memo``: a :class:`LikelihoodMemo` kept by the caller over calls on the
    same cube, background and IRF (stage 7's rounds): a (pixel, depth) met before is
    read from it, the others computed and added. Each value is a function of its pixel
    and depth alone, so the result is the same to the bit
    (``tests/test_depths.py``)."""
    if memo is not None:
        return _memo_likelihoods(counts, background, rows, cols, dep, irf, n_jobs, memo)
    irf = np.atleast_2d(np.asarray(irf, np.float64))
    peak = np.argmax(irf, axis=1)
    T = int(np.shape(counts)[-1])
    # the IRF's support about a depth (+1 bin for the sub-bin shift): all that counts
    W = min(irf.shape[1] + 2, T)
    out = np.empty((rows.size, dep.shape[1]))
    tm = background.temporal
    tm = tm - tm.mean(axis=-1, keepdims=True)  # as Background.at: (L, T)

    # a Zarr cube kept sparse (stages 5-7 of detect): read over the windows too
    kept = None if isinstance(counts, np.ndarray) else sparse_of(counts)

    def block(a):
        sl = slice(a, a + _BLOCK)
        r, c = rows[sl], cols[sl]
        whole = not isinstance(counts, np.ndarray) and kept is None
        y = _pixels(counts, r, c) if whole else None  # (n, L, T)
        sp = background.spatial[r, c]  # (n, L)
        for j in range(dep.shape[1]):
            d = np.clip(dep[sl, j], 0.0, T - 1.0)
            lo = np.clip(np.floor(d).astype(np.int64) - int(peak.max()) - 1, 0, T - W)
            t = lo[:, None] + np.arange(W)  # (n, W)
            g = _shifted_irf(irf, peak, d - lo, W)  # (n, L, W)
            if isinstance(counts, np.ndarray):  # the window alone
                yw = np.empty((r.size, counts.shape[2], W))
                _window_counts(counts, r, c, lo, yw)
            elif y is None:
                yw = kept.windows(r, c, lo, W).astype(np.float64)  # (n, L, W)
            else:
                yw = y[np.arange(y.shape[0])[:, None], :, t]
                yw = np.moveaxis(yw, -1, 1).astype(np.float64)  # (n, L, W)
            # Background.at over the window only, the same float32 arithmetic
            bw = sp[:, :, None] + np.moveaxis(tm[:, t], 0, 1)
            bw = np.maximum(bw, 0, out=bw).astype(np.float32, copy=False)
            bw = np.maximum(bw.astype(np.float64), 1e-6)
            out[sl, j] = profile_llr(yw, g, bw)

    starts = range(0, rows.size, _BLOCK)
    if n_jobs > 1 and len(starts) > 1:
        with ThreadPoolExecutor(min(int(n_jobs), len(starts))) as ex:
            list(ex.map(block, starts))
    else:
        for a in starts:
            block(a)
    return out


class LikelihoodMemo:
    """:func:`_likelihoods`' values kept over calls (stage 7's rounds), per (pixel,
    depth): sorted keys ``row * 2**31 + col + 1j * depth`` (complex128: NumPy orders
    them by pixel, then depth, and ``==`` compares both as the former dict's float keys
    did: 0.0 and -0.0 the same key, a NaN depth never found) beside their values.
    Looked up and extended by arrays (no Python loop per key)."""

    __slots__ = ("keys", "values")

    def __init__(self):
        self.keys = np.empty(0, np.complex128)
        self.values = np.empty(0, np.float64)

    def __len__(self) -> int:
        return int(self.keys.size)

    @staticmethod
    def key(rows, cols, depth) -> np.ndarray:
        """The keys (n,) complex128 of pixels ``(rows, cols)`` at ``depth`` (n,)."""
        pix = np.asarray(rows, np.int64) * 2**31 + np.asarray(cols, np.int64)
        return pix.astype(np.float64) + 1j * np.asarray(depth, np.float64)

    def find(self, q) -> tuple:
        """``(hit, pos)`` (n,): whether key ``q[i]`` is kept, and where."""
        pos = np.searchsorted(self.keys, q)
        pos = np.minimum(pos, max(self.keys.size - 1, 0))
        hit = self.keys[pos] == q if self.keys.size else np.zeros(q.size, bool)
        return hit, pos

    def add(self, q, v) -> None:
        """Keep the values ``v`` of the new keys ``q`` (a key met twice: its first; a
        NaN depth's key is not kept: it would never be found)."""
        ok = ~np.isnan(q)
        keys = np.concatenate([self.keys, q[ok]])
        values = np.concatenate([self.values, np.asarray(v, np.float64)[ok]])
        order = np.argsort(keys, kind="stable")
        keys, values = keys[order], values[order]
        first = np.ones(keys.size, bool)
        first[1:] = keys[1:] != keys[:-1]
        self.keys, self.values = keys[first], values[first]


def _memo_likelihoods(counts, background, rows, cols, dep, irf, n_jobs, memo) -> np.ndarray:
    """:func:`_likelihoods` with its ``memo`` (:class:`LikelihoodMemo`): the (pixel,
    depth) pairs not in it computed (one depth per row) and added, then every value
    read from it (a NaN depth: computed, as it is never found)."""
    dep = np.asarray(dep, np.float64)
    k = dep.shape[1]
    q = LikelihoodMemo.key(np.repeat(rows, k), np.repeat(cols, k), dep.ravel())
    hit, _ = memo.find(q)
    new = np.flatnonzero(~hit)
    got = np.empty(0)
    if new.size:
        p, d = new // k, dep.ravel()[new, None]
        got = _likelihoods(counts, background, rows[p], cols[p], d, irf, n_jobs)[:, 0]
        memo.add(q[new], got)
    hit, pos = memo.find(q)
    out = np.where(hit, memo.values[pos], np.nan)
    out[new] = got  # NaN keys are never found: their values as computed
    return out.reshape(dep.shape)


def group_llr(y, g, b, group, n_iter: int = 30) -> np.ndarray:
    """``max_{s >= 0} sum_{p in G} sum_t [y_pt log(1 + s g_pt / b_pt) - s g_pt]`` per
    group ``G``: the joint own-count log-likelihood ratio of one shared intensity.

    Parameters
    ----------
    y, g, b : ndarray (n, L, W)
        Raw counts, the IRF about each member's depth, the background (> 0).
    group : ndarray (n,) int
        Each member's group, ``0..m-1``.
    n_iter : int
        Newton steps (the function is concave in ``s``).

    Returns
    -------
    ndarray (m,)
        Nats, >= 0; a one-member group gives ``profile_llr`` of its member.
    """
    m = int(group.max(initial=-1)) + 1
    G = np.bincount(group, weights=g.sum(axis=(1, 2)), minlength=m)
    nz = y > 0
    ge = np.broadcast_to(group[:, None, None], y.shape)[nz]
    ye, gv, bv = y[nz].astype(np.float64), g[nz], b[nz]
    slope = np.bincount(ge, weights=ye * gv / bv, minlength=m) - G
    yg = np.bincount(ge, weights=ye * gv, minlength=m)
    s = np.where(slope > 0, np.maximum(yg / np.maximum(G, 1e-12), 1e-3), 0.0)
    for _ in range(n_iter):
        den = bv + s[ge] * gv
        q = ye * gv / den
        d1 = np.bincount(ge, weights=q, minlength=m) - G
        d2 = -np.bincount(ge, weights=q * gv / den, minlength=m)
        step = np.where(d2 < 0, d1 / np.where(d2 < 0, d2, -1.0), 0.0)
        s = np.where(slope > 0, np.maximum(s - step, 0.0), 0.0)
    llr = np.bincount(ge, weights=ye * np.log1p(s[ge] * gv / bv), minlength=m) - s * G
    return np.maximum(llr, 0.0)


def _windows(counts, background, rows, cols, depth, irf):
    """The own counts ``y``, the IRF ``g`` and the background ``b`` (n, L, W) over the
    IRF's window about each depth (the window and arithmetic of :func:`_likelihoods`);
    ``counts`` NumPy (each window read alone) or Dask / Zarr (each pixel's series)."""
    irf = np.atleast_2d(np.asarray(irf, np.float64))
    peak = np.argmax(irf, axis=1)
    T = int(np.shape(counts)[-1])
    W = min(irf.shape[1] + 2, T)
    tm = background.temporal
    tm = tm - tm.mean(axis=-1, keepdims=True)
    d = np.clip(depth, 0.0, T - 1.0)
    lo = np.clip(np.floor(d).astype(np.int64) - int(peak.max()) - 1, 0, T - W)
    t = lo[:, None] + np.arange(W)
    g = _shifted_irf(irf, peak, d - lo, W)
    y = np.empty((rows.size, int(np.shape(counts)[2]), W))
    if isinstance(counts, np.ndarray):
        _window_counts(counts, rows, cols, lo, y)
    else:  # Dask, Zarr: the pixels' whole series, then their windows
        n = np.arange(rows.size)
        _window_counts(_pixels(counts, rows, cols)[:, None], n, np.zeros_like(n), lo, y)
    bw = background.spatial[rows, cols][:, :, None] + np.moveaxis(tm[:, t], 0, 1)
    bw = np.maximum(bw, 0).astype(np.float32, copy=False)
    return y, g, np.maximum(bw.astype(np.float64), 1e-6)


def min_cut_labels(node, ll, beta, fixed_a, fixed_b) -> np.ndarray:
    """The labels (0 or 1) of the band's pixels minimising ``-sum_p ll[p, label_p] +
    beta * #(4-neighbour pairs with different labels)``, exactly (a minimum s-t cut).

    Parameters
    ----------
    node : ndarray (R, C) int64
        The band's pixels numbered ``0..n-1``, -1 elsewhere.
    ll : ndarray (n, 2)
        Log-likelihoods (nats) of labels 0 and 1.
    beta : float
        Potts weight (nats per differing pair).
    fixed_a, fixed_b : ndarray (R, C) bool
        Pixels outside the band held at label 0 / 1 (their pairs with the band count).
    """
    R, C = node.shape
    cap_s, cap_t = _unary(ll)
    src, dst = [], []
    for p, q in (
        ((slice(None), slice(0, C - 1)), (slice(None), slice(1, C))),
        ((slice(0, R - 1), slice(None)), (slice(1, R), slice(None))),
    ):
        for u, v in ((p, q), (q, p)):
            a, b = node[u], node[v]
            both = (a >= 0) & (b >= 0)
            src.append(a[both])
            dst.append(b[both])
            np.add.at(cap_s, a[(a >= 0) & fixed_a[v]], beta)
            np.add.at(cap_t, a[(a >= 0) & fixed_b[v]], beta)
    return _cut(np.concatenate(src), np.concatenate(dst), cap_s, cap_t, beta)


def _unary(ll: np.ndarray):
    """The terminal capacities ``(cut when label 1, cut when label 0)`` of log-likelihoods
    ``ll`` (n, 2), shifted to be non-negative."""
    cost = -ll - (-ll).min(axis=1, keepdims=True)
    return cost[:, 1].copy(), cost[:, 0].copy()


def _cut(src, dst, cap_s, cap_t, beta: float) -> np.ndarray:
    """Labels (0: source side) of the minimum s-t cut of ``n = cap_s.size`` nodes with
    terminal capacities ``cap_s`` / ``cap_t`` and ``beta`` on each directed edge
    ``src -> dst``: the source side is the set the source reaches in the residual graph
    of a maximum flow (the smallest minimum cut, the same for every maximum flow)."""
    n = cap_s.size
    i = np.concatenate([src, np.full(n, n), np.arange(n)])
    j = np.concatenate([dst, np.arange(n), np.full(n, n + 1)])
    w = np.concatenate([np.full(src.size, beta), cap_s, cap_t])
    w = np.rint(w * _SCALE).astype(np.int64)
    g = sparse.csr_matrix((w[w > 0], (i[w > 0], j[w > 0])), shape=(n + 2, n + 2))
    g.sum_duplicates()
    res = (g - csgraph.maximum_flow(g, n, n + 1).flow).tocsr()
    res.data[res.data < 0] = 0
    res.eliminate_zeros()
    reach = csgraph.breadth_first_order(res, n, directed=True, return_predecessors=False)
    label = np.ones(n, np.int64)
    label[reach[reach < n]] = 0
    return label


def _all_bands(big, zr, zc, pair_a, pair_b, ll_ab, beta) -> np.ndarray:
    """:func:`min_cut_labels` of every pair of regions' band at once: the bands' pixels
    are disjoint (each has one other region) and a Potts edge joins two pixels of one
    band only, so the graph is the bands' graphs side by side, sharing the source and
    the sink, and its minimum cut is theirs. A neighbour outside the pixel's band is
    held at its region (A: label 0, B: label 1) as in :func:`min_cut_labels`."""
    R, C = big.shape
    node = np.full((R, C), -1, np.int64)
    node[zr, zc] = np.arange(zr.size)
    cap_s, cap_t = _unary(ll_ab)
    src, dst = [], []
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        r, c = zr + dr, zc + dc
        ok = (r >= 0) & (r < R) & (c >= 0) & (c < C)
        u, r, c = np.flatnonzero(ok), r[ok], c[ok]
        v = node[r, c]
        same = v >= 0
        same[same] = (pair_a[v[same]] == pair_a[u[same]]) & (pair_b[v[same]] == pair_b[u[same]])
        src.append(u[same])
        dst.append(v[same])
        held = big[r, c]
        np.add.at(cap_s, u[~same & (held == pair_a[u])], beta)
        np.add.at(cap_t, u[~same & (held == pair_b[u])], beta)
    return _cut(np.concatenate(src), np.concatenate(dst), cap_s, cap_t, beta)


def band_depths(
    surfaces: Surfaces,
    counts,
    background,
    *,
    fwhm: float,
    irf,
    half: int,
    n_jobs: int = 1,
    memo: LikelihoodMemo | None = None,
):
    """The depths of ``surfaces`` after the bands' labelling (see the module), the
    indices of the surfaces moved and the Potts weight ``beta``.

    Parameters
    ----------
    surfaces : Surfaces
    counts : array_like (rows, cols, L, T)
        The cube's raw counts (NumPy or Dask).
    background : Background
        The detection's background (``Background.at``).
    fwhm : float
        The IRF's FWHM (bins).
    irf : ndarray (L, n_irf)
    half : int
        The largest box's half-width (pixels): the band's reach.
    n_jobs : int
        Threads for the planes and the likelihoods (never changes the result).
    memo : LikelihoodMemo, optional
        The own counts' likelihoods met before on this cube (:func:`_likelihoods`; stage
        7's rounds share one): never changes the result.

    Returns
    -------
    depth : ndarray (S,) float64
    moved : ndarray (m,) int64
    beta : float
    """
    s = surfaces
    R, C = s.image_shape
    pix = s.row * C + s.col
    solo = np.flatnonzero(np.bincount(pix, minlength=R * C)[pix] == 1)
    D = np.full((R, C), np.nan)
    D[s.row[solo], s.col[solo]] = s.depth_bin[solo]
    at = np.full((R, C), -1, np.int64)
    at[s.row[solo], s.col[solo]] = solo
    gate = GATE_FWHM * float(fwhm)
    lab = region_labels(D, gate)
    beta = potts_weight(lab)
    size = np.bincount(lab[lab >= 0], minlength=1)
    big = np.where((lab >= 0) & (size[np.maximum(lab, 0)] >= MIN_REGION), lab, -1)
    other, dep = _band_planes(big, D, int(half), gate, n_jobs)
    depth = np.array(s.depth_bin, np.float64)
    zr, zc = np.nonzero(other >= 0)
    ll = (
        np.zeros((0, 2))
        if zr.size == 0
        else _likelihoods(counts, background, zr, zc, dep[zr, zc], irf, n_jobs, memo)
    )  # own, other
    T = int(np.shape(counts)[-1])
    pair_a = np.minimum(big[zr, zc], other[zr, zc])
    pair_b = np.maximum(big[zr, zc], other[zr, zc])
    own_b = big[zr, zc] == pair_b
    ll_ab = np.where(own_b[:, None], ll[:, ::-1], ll)  # column 0: A, 1: B
    change = _all_bands(big, zr, zc, pair_a, pair_b, ll_ab, beta) != own_b
    # the prior shapes a band; it never moves one the own counts do not favour
    pair = _pair_index(pair_a, pair_b)
    gain = np.bincount(pair, weights=np.where(change, ll[:, 1] - ll[:, 0], 0.0))
    go = change & (gain[pair] > 0.0)
    i, d_new = at[zr[go], zc[go]], dep[zr[go], zc[go], 1]  # the other region's plane
    ok = (np.abs(d_new - depth[i]) > fwhm) & (d_new >= 0.0) & (d_new <= T - 1)
    depth[i[ok]] = d_new[ok]
    moved = i[ok]
    near, to = np.zeros(0, np.int64), np.zeros(0)
    if NEAR_DEPTHS:
        near, to = near_depths(
            s, depth, solo, counts, background, fwhm=fwhm, irf=irf, half=half, n_jobs=n_jobs,
            memo=memo,
        )  # fmt: skip
    depth[near] = to
    moved = np.union1d(np.asarray(moved, np.int64), near)
    if FAR_INSIDE:
        far, to = far_inside_depths(
            s, depth, solo, counts, background, fwhm=fwhm, irf=irf, half=half, memo=memo,
            n_jobs=n_jobs,
        )  # fmt: skip
        depth[far] = to
        moved = np.union1d(moved, far)
    return depth, moved, beta


def _pair_index(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) int64: the rank of each pair ``(a, b)`` (integer labels) among the distinct
    pairs in lexicographic order, as ``np.unique(np.stack([a, b]), axis=1,
    return_inverse=True)[1]`` gives it: one integer key per pair (``a`` major), sorted
    once."""
    if a.size == 0:
        return np.zeros(0, np.int64)
    a = np.asarray(a, np.int64)
    b = np.asarray(b, np.int64)
    a0, b0 = int(a.min()), int(b.min())
    key = (a - a0) * (int(b.max()) - b0 + 1) + (b - b0)
    return np.unique(key, return_inverse=True)[1].ravel().astype(np.int64, copy=False)


def _shared_at(depth: np.ndarray, tol: float, zr: np.ndarray, zc: np.ndarray) -> np.ndarray:
    """(n,) int: at the pixels ``(zr, zc)`` of ``depth`` (R, C), how many 8-neighbours'
    finite values lie within ``tol`` of the pixel's (neighbours outside the image count
    as not): the same comparisons as over the whole image, at those pixels only."""
    pad = np.pad(depth, 1, constant_values=np.nan)
    own = depth[zr, zc]
    out = np.zeros(zr.size, np.int64)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                with np.errstate(invalid="ignore"):
                    out += np.abs(pad[zr + 1 + dr, zc + 1 + dc] - own) <= tol
    return out


def _inside_at(lab: np.ndarray, zr: np.ndarray, zc: np.ndarray) -> np.ndarray:
    """(n,) int: at the pixels ``(zr, zc)`` of ``lab`` (R, C), how many 8-neighbours
    carry the pixel's label (0 where ``lab < 0``; neighbours outside the image count as
    not)."""
    pad = np.pad(lab, 1, constant_values=-1)
    own = lab[zr, zc]
    out = np.zeros(zr.size, np.int64)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                out += pad[zr + 1 + dr, zc + 1 + dc] == own
    return np.where(own >= 0, out, 0)


def near_depths(
    surfaces, depth, solo, counts, background, *, fwhm: float, irf, half: int, n_jobs: int = 1,
    memo: LikelihoodMemo | None = None,
):  # fmt: skip
    """The "near" wrong depths: single-surface pixels more than :data:`NEAR_FWHM` FWHM
    off their own region's local plane, moved onto it where the own counts with the
    measured prior favour it (see :data:`NEAR_FWHM`).

    The regions are re-formed on ``depth`` (after the bands' labelling); each member's
    plane is :func:`_window_plane` over the other members within ``2 half`` (the pixel left
    out). A pixel is offered its plane when it lies more than ``NEAR_FWHM`` FWHM off it,
    at least :data:`NEAR_INSIDE` of its 8-neighbours are members of its region (not at
    its border, where the plane extrapolates), and fewer than 2 of its 8-neighbours lie
    off their own planes by the same amount (within half the FWHM): a lone fluctuation
    or a pair, not a step of a surface inside the region's gate (with a wide IRF, FWHM 7
    bins, a region spans steps of up to 10 bins; without this guard the step's side
    moved onto the plane). With ``q`` the
    fraction of the members (with a plane) off it by more than ``NEAR_FWHM`` FWHM,
    measured on this detection, the prior log-odds that a pixel lies on its region's
    plane is ``log((1 - q) / q)``; a pixel moves when ``L(plane) - L(own) + log((1 - q)
    / q) > 0`` (``L``: :func:`profile_llr` of its raw counts).

    Parameters
    ----------
    surfaces : Surfaces
    depth : ndarray (S,) float64
        The surfaces' depths (bins) after the bands' labelling.
    solo : ndarray (n,) int64
        The surfaces alone in their pixels.
    counts, background, fwhm, irf, half, n_jobs, memo
        As :func:`band_depths`.

    Returns
    -------
    moved : ndarray (m,) int64
        Indices of the surfaces moved.
    to : ndarray (m,) float64
        Their new depths (bins).
    """
    s = surfaces
    R, C = s.image_shape
    none = np.zeros(0, np.int64), np.zeros(0)
    D, gate, big = _solo_regions(s, depth, solo, fwhm)
    plane = np.full((R, C), np.nan)
    reach = 2 * int(half)
    on_parts(
        lambda i0, i1: _own_plane_kernel(big, D, reach, float(gate), plane, i0, i1),
        R,
        min(int(n_jobs), R // 16),  # rows of at least 16 per thread
    )
    has = np.isfinite(plane)
    off = has & (np.abs(D - plane) > NEAR_FWHM * float(fwhm))
    zr, zc = np.nonzero(off)  # those of them few 8-neighbours share and inside a region
    ok = (_shared_at(D - plane, 0.5 * float(fwhm), zr, zc) < 2) & (
        _inside_at(big, zr, zc) >= NEAR_INSIDE
    )
    zr, zc = zr[ok], zc[ok]
    T = int(np.shape(counts)[-1])
    keep = (plane[zr, zc] >= 0.0) & (plane[zr, zc] <= T - 1)
    zr, zc = zr[keep], zc[keep]
    if zr.size == 0:
        return none
    q = max(int(off.sum()), 1) / max(int(has.sum()), 2)
    return _plane_moves(s, solo, counts, background, zr, zc, D, plane, q, irf, memo)


@njit(cache=True, nogil=True)
def _inside_plane_kernel(big, depth, reach, gate, need, region, plane, r0, r1):  # pragma: no cover
    """Per pixel of rows ``r0:r1``, ``region[r, c]``: the region holding at least ``need``
    of its 8-neighbours (-1 if none); for a pixel with a depth that is not a member of
    that region, ``plane[r, c]``: the region's local plane at the pixel
    (:func:`_window_plane` over its members within ``reach``, Chebyshev); NaN elsewhere.
    Only rows ``r0:r1`` are written: disjoint row ranges run on threads side by side."""
    R, C = big.shape
    buf = np.empty((3, (2 * reach + 1) ** 2))
    for r in range(r0, r1):
        for c in range(C):
            region[r, c] = -1
            plane[r, c] = np.nan
            best = -1
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    rr, cc = r + dr, c + dc
                    if (dr == 0 and dc == 0) or not (0 <= rr < R and 0 <= cc < C):
                        continue
                    x = big[rr, cc]
                    if x < 0 or best >= 0:
                        continue
                    k = 0
                    for er in range(-1, 2):
                        for ec in range(-1, 2):
                            ar, ac = r + er, c + ec
                            if (er or ec) and 0 <= ar < R and 0 <= ac < C and big[ar, ac] == x:
                                k += 1
                    if k >= need:
                        best = x
            region[r, c] = best
            if best < 0 or big[r, c] == best or np.isnan(depth[r, c]):
                continue
            plane[r, c] = _window_plane(big, depth, r, c, reach, best, False, gate, 3, buf)


def _shared_any(surfaces, depth, D, tol: float, where: np.ndarray) -> np.ndarray:
    """(R, C) bool: the pixels of ``where`` (R, C) bool one of whose 8-neighbours holds a
    surface (any slot) within ``tol`` of the pixel's depth ``D`` (NaN: none); False
    elsewhere. Only the surfaces of the pixels beside ``where`` are read (each offers
    ``|depth - D| <= tol`` to its 8-neighbours of ``where``: the same comparison, bit
    for bit, as the neighbours' depth maps of every slot)."""
    s = surfaces
    R, C = s.image_shape
    out = np.zeros((R, C), bool)
    near = np.zeros((R + 2, C + 2), bool)  # ``where`` dilated by the 8-neighbourhood
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            near[dr : dr + R, dc : dc + C] |= where
    pick = np.flatnonzero(near[s.row + 1, s.col + 1])
    row, col, dep = s.row[pick], s.col[pick], np.asarray(depth, np.float64)[pick]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                r, c = row + dr, col + dc
                ok = np.flatnonzero((r >= 0) & (r < R) & (c >= 0) & (c < C))
                r, c = r[ok], c[ok]
                on = where[r, c]
                r, c, d = r[on], c[on], dep[ok][on]
                with np.errstate(invalid="ignore"):
                    hit = np.abs(d - D[r, c]) <= tol
                out[r[hit], c[hit]] = True
    return out


def far_inside_depths(
    surfaces, depth, solo, counts, background, *, fwhm: float, irf, half: int, memo=None,
    n_jobs: int = 1,
):  # fmt: skip
    """The far wrong depths inside a region: a single-surface pixel that is not a member
    of the region holding at least :data:`NEAR_INSIDE` of its 8-neighbours (its depth
    more than the gate, :data:`GATE_FWHM` FWHM, off every neighbour's), moved onto that
    region's local plane where the own counts with a measured prior favour it.

    On issue #15's single-surface cells these are a dim pixel's missed return replaced
    by a background cluster or a far neighbour's pooled return (benchmarks/README.md,
    "far28, session 20"). A pixel is offered the plane (:func:`_window_plane` over the region's
    members within ``2 half``) when its depth lies more than the gate off it and none of
    its 8-neighbours holds a surface (any slot) within the gate of its depth: a lone
    depth, not a strand or an edge that continues through the pixel (without this
    guard the net's strand pixels whose object return was missed moved onto the
    object's plane). With ``q`` the fraction of the pixels inside a region (``>=
    NEAR_INSIDE`` of their 8-neighbours members) so offered, measured on this
    detection, a pixel moves when ``L(plane) - L(own) + log((1 - q) / q) > 0`` (``L``:
    :func:`profile_llr` of its raw counts), as :func:`near_depths`.

    Parameters
    ----------
    surfaces, depth, solo, counts, background, fwhm, irf, half, memo, n_jobs
        As :func:`near_depths` (``depth`` after the near depths; ``n_jobs``: threads of
        the planes, rows of at least 16 each).

    Returns
    -------
    moved : ndarray (m,) int64
        Indices of the surfaces moved.
    to : ndarray (m,) float64
        Their new depths (bins).
    """
    s = surfaces
    R, C = s.image_shape
    none = np.zeros(0, np.int64), np.zeros(0)
    D, gate, big = _solo_regions(s, depth, solo, fwhm)
    region = np.empty((R, C), np.int64)
    plane = np.empty((R, C))
    on_parts(
        lambda i0, i1: _inside_plane_kernel(
            big, D, 2 * int(half), gate, NEAR_INSIDE, region, plane, i0, i1
        ),
        R,
        min(int(n_jobs), R // 16),  # rows of at least 16 per thread
    )
    T = int(np.shape(counts)[-1])
    with np.errstate(invalid="ignore"):
        cand = np.isfinite(plane) & (np.abs(D - plane) > gate) & (plane >= 0.0)
        cand &= plane <= T - 1
    cand &= ~_shared_any(s, depth, D, gate, cand)
    zr, zc = np.nonzero(cand)
    if zr.size == 0:
        return none
    q = zr.size / max(int((region >= 0).sum()), 2)
    return _plane_moves(s, solo, counts, background, zr, zc, D, plane, q, irf, memo)


def _solo_regions(s: Surfaces, depth: np.ndarray, solo: np.ndarray, fwhm: float) -> tuple:
    """``(D, gate, big)``: the depth image of the pixels' lone surfaces (NaN elsewhere),
    the region gate (``GATE_FWHM`` FWHM, bins) and the region labels of the regions of at
    least ``MIN_REGION`` pixels (-1 elsewhere), as :func:`near_depths` and
    :func:`far_inside_depths` use them."""
    D = np.full(s.image_shape, np.nan)
    D[s.row[solo], s.col[solo]] = depth[solo]
    gate = GATE_FWHM * float(fwhm)
    lab = region_labels(D, gate)
    size = np.bincount(lab[lab >= 0], minlength=1)
    big = np.where((lab >= 0) & (size[np.maximum(lab, 0)] >= MIN_REGION), lab, -1)
    return D, gate, big


def _plane_moves(
    s: Surfaces, solo, counts, background, zr, zc, D, plane, q: float, irf, memo=None
) -> tuple:
    """``(moved, to)``: the lone surfaces at pixels ``(zr, zc)`` whose own counts, with the
    prior log-odds ``log((1 - q) / q)`` of lying on the plane, favour ``plane`` over their
    depth ``D`` (``L(plane) - L(own) + prior > 0``), and their new depths (bins)."""
    none = np.zeros(0, np.int64), np.zeros(0)
    prior = np.log((1.0 - q) / q)
    dep = np.stack([D[zr, zc], plane[zr, zc]], 1)
    ll = _likelihoods(counts, background, zr, zc, dep, irf, memo=memo)
    go = ll[:, 1] - ll[:, 0] + prior > 0.0
    if not go.any():
        return none
    at = np.full(s.image_shape, -1, np.int64)
    at[s.row[solo], s.col[solo]] = solo
    return at[zr[go], zc[go]], plane[zr[go], zc[go]]
