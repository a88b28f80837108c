"""Slope-aware recovery of missed surfaces (issue #3).

The saliency of :func:`splidar.detection.detect` pools photons over *square* boxes
(``eq:4.s1``). On a steep slope a ``k x k`` box spreads a return over about
``(k // 2) (|b| + |c|)`` bins either side of its depth (``b``, ``c``: the depth gradient
in bins per row and per column), far more than the IRF's width: at low photon counts
the pixels of a dim region on a slope then get no candidate at all.

This pass runs once after the main pass and the quality passes (``_quality.py``), on the
kept candidates of the whole image. For each pixel:

1. **Local planes.** The kept surfaces in the ``(2 r + 1)^2`` window around the pixel
   (``r`` = the largest box's half-width) are fitted by planes ``depth = a + b dr + c dc``
   (``dr``, ``dc``: offsets from the pixel), robustly: random triples (a fixed generator
   seeded per pixel, so the result does not depend on the order of work), the plane with
   most surfaces within the IRF's FWHM (its *inliers*), refined by least squares on its
   inliers; then the next plane on the surfaces left (sequential RANSAC; at most
   ``max_surfaces`` planes). A plane needs at least ``2 x 3`` inliers.
2. **Which planes are tested at the pixel.** A plane is tested when it is *steep* (its
   coarsest box spreads a return over at least the FWHM, ``(k_max // 2) (|b| + |c|) >=
   FWHM``: square boxes already work on gentler ones), *encloses* the pixel (in each of
   8 directions an inlier lies beyond it, or the image ends: a plane is not
   extrapolated past its patch's edge, where the pooled neighbours of the patch would
   make ghosts), no surface of the
   pixel lies on it (within the FWHM: the pixel is a hole of that plane) and the pixel
   has room: fewer than ``max_surfaces`` kept surfaces, or one within 2 FWHM of the
   plane (the same return at a depth biased by the square boxes; it is replaced).
3. **Sheared pooled test.** For each tested plane, each box size ``k`` of ``scales``
   above 1 and each shift ``delta`` in ``[-FWHM, FWHM]`` bins: the raw counts ``n`` of
   the ``k x k`` box around the pixel over the IRF's half-maximum window around the
   plane's depth at each pixel, ``plane(m) + delta``, against the expected background
   ``B`` there (``bhat`` of ``eq:background_3``, from the factored estimate). Neighbours
   holding a surface within the test's reach of the plane (shift range + counting window
   + the matched filter's half-width) are left out: their own returns would make ghosts.
   Exact Poisson tail ``p = P(N >= n | B)``; the smallest ``p`` of a pixel is corrected
   for the number of tests (planes x boxes x shifts, Bonferroni) and the plane is
   accepted when that is at most ``surface_pfa`` (false surfaces per tested pixel).
4. **Own-pixel check.** As for the main pass (``presence_llr``): the pixel's own counts
   must not reject a return of the pooled per-pixel intensity, log-likelihood ratio
   ``>= -presence_llr``.
5. **Region growing.** Accepted surfaces take part in the next round (they supply planes
   and leave the pools); only pixels whose window gained a surface are tested again;
   ``n_iter`` rounds at most.
6. **Replacements.** A recovered surface within 2 FWHM of a kept one of its pixel
   replaces it (the same return, its depth biased by the square boxes) unless the own
   counts reject it against the kept one: own log-likelihood ratio below the kept
   surface's minus ``presence_llr``.

Which pixels are tested
-----------------------
``pixels="all"`` (``detect(slopes="all")``) tests every pixel. The robust plane fits
around every pixel are most of its cost, and most pixels need none:

* ``"holes"``: only the pixels with no kept surface, in every round;
* ``"weak"`` (``detect``'s default): those, and the pixels holding a surface that their
  own counts do not confirm: own log-likelihood ratio (``presence_llr`` of the main
  pass) below ``presence_llr``, the level at which they would reject it. A depth the
  square boxes biased onto a neighbouring row's lobe is such a surface (its own photons
  lie elsewhere); a surface the own counts confirm is not replaced by the sheared test
  in practice, and second surfaces beside it are the main pass's job.

Measured (``benchmarks/bench_detection.py``, full grid, seed 0): ``"holes"`` ->
``"weak"``: F_true up in 49 of 64 cells, down in 2 (by at most 0.0007), false surfaces
-18.5 per 100 true summed over the cells; single surface PPP 4, SBR 0.25: 0.963 -> 0.972
(decaying background 0.965 -> 0.975), ``"all"`` 0.973 / 0.976. The weak pixels are
35-49 % of the filled pixels on that scene and hold 94-100 % of what ``"all"`` recovers
in filled pixels; on the Art scene (two copies, every pixel has two surfaces) they are
9 % of the pixels, so the pass costs 0.07 s there (one thread) against 0.015 s
(``"holes"``) and 1.3 s (``"all"``).

Every :class:`~splidar.detection.Surfaces` field of a recovered surface is computed from
the raw counts: the clean histograms of every scale are ``max(Box_q(Y (*) g) - bhat, 0)``
over the window (square boxes, as in the main pass, the matched filter computed
directly), the support is the whole window, ``depth_bin`` is the plane's depth plus the
best shift (sub-bin: the plane is continuous), ``scale_index`` is the index of the box
``k`` of the accepted test, ``presence_llr`` / ``presence_z`` as in the main pass (own
counts with the pooled intensity; local scale's z).
"""

from __future__ import annotations

import contextlib
import logging
import threading

import numpy as np
from numba import njit
from scipy import stats

from .._arrays import zarr_rows_into, zarr_voxels
from ._fast import _refl as _reflect
from ._kernels import _llr_one

__all__ = ["recover_slopes"]

logger = logging.getLogger(__name__)

#: fewest inliers of a local plane (twice the three points that define one)
MIN_INLIERS = 6
#: random triples tried per plane
N_TRIALS = 64
#: the 8 directions of the enclosure test
_DIR_R = np.array([-1, 1, 0, 0, -1, -1, 1, 1], np.float64)
_DIR_C = np.array([0, 0, -1, 1, -1, 1, -1, 1], np.float64)


@njit(cache=True, nogil=True)
def _draw(state, n):
    """Next state of a 64-bit linear congruential generator and an index in ``[0, n)``."""
    state = state * 6364136223846793005 + 1442695040888963407  # wraps modulo 2^64
    return state, ((state >> 33) & 0x7FFFFFFF) % n


@njit(cache=True, nogil=True, inline="always")
def _det3(a00, a01, a02, a10, a11, a12, a20, a21, a22):
    """Determinant of a 3 x 3 matrix given row by row."""
    return (
        a00 * (a11 * a22 - a12 * a21)
        - a01 * (a10 * a22 - a12 * a20)
        + a02 * (a10 * a21 - a11 * a20)
    )


@njit(cache=True, nogil=True)
def _solve3_into(A, v, out):
    """Solve the 3 x 3 system ``A x = v`` into ``out`` by Cramer's rule; False if singular."""
    det = _det3(A[0, 0], A[0, 1], A[0, 2], A[1, 0], A[1, 1], A[1, 2], A[2, 0], A[2, 1], A[2, 2])
    if abs(det) < 1e-9:
        return False
    out[0] = _det3(v[0], A[0, 1], A[0, 2], v[1], A[1, 1], A[1, 2], v[2], A[2, 1], A[2, 2]) / det
    out[1] = _det3(A[0, 0], v[0], A[0, 2], A[1, 0], v[1], A[1, 2], A[2, 0], v[2], A[2, 2]) / det
    out[2] = _det3(A[0, 0], A[0, 1], v[0], A[1, 0], A[1, 1], v[1], A[2, 0], A[2, 1], v[2]) / det
    return True


@njit(cache=True, nogil=True, inline="always")
def _triple_plane(pr, pc, pd, i0, i1, i2):  # pragma: no cover - numba
    """``(ok, a, b, c)``: the plane through the points ``i0, i1, i2`` (offsets ``pr``,
    ``pc``, depth ``pd``) by Cramer's rule, from scalars: :func:`_solve3_into`'s
    determinants term by term (the same values), ``ok`` False where it is singular."""
    r0, r1, r2, c0, c1, c2 = pr[i0], pr[i1], pr[i2], pc[i0], pc[i1], pc[i2]
    d0, d1, d2 = pd[i0], pd[i1], pd[i2]
    det = _det3(1.0, r0, c0, 1.0, r1, c1, 1.0, r2, c2)
    if abs(det) < 1e-9:
        return False, 0.0, 0.0, 0.0
    a = _det3(d0, r0, c0, d1, r1, c1, d2, r2, c2) / det
    b = _det3(1.0, d0, c0, 1.0, d1, c1, 1.0, d2, c2) / det
    return True, a, b, _det3(1.0, r0, d0, 1.0, r1, d1, 1.0, r2, d2) / det


@njit(cache=True, nogil=True)
def fit_planes(D, hr, hc, radius, tol, max_planes, min_inliers, n_trials, seed, out):
    """Local planes of the kept surfaces around each hole (sequential RANSAC + LSQ).

    Parameters
    ----------
    D : (R, C, K) float64
        Depths (bins) of the kept surfaces per pixel, nan where none.
    hr, hc : (H,) int64
        The holes.
    radius : int
        Half-width of the window.
    tol : float
        Inlier tolerance (bins).
    max_planes, min_inliers, n_trials, seed : int
        Each hole draws from ``seed * 1000003 + row * C + col``: a split over threads
        gives the same planes, and a change elsewhere in the image does not move a
        hole's.
    out : (H, max_planes, 5) float64
        Written: ``a, b, c, n_inliers, enclosed`` of each plane (``n_inliers = 0``:
        none; ``enclosed`` 1.0 when, in each of 8 directions, an inlier lies beyond the
        hole or the image ends: the hole is inside the plane's patch, not beyond its
        edge).
    """
    R, C, K = D.shape
    nmax = (2 * radius + 1) * (2 * radius + 1) * K
    pr = np.empty(nmax)
    pc = np.empty(nmax)
    pd = np.empty(nmax)
    used = np.empty(nmax, np.bool_)
    pdu = np.empty(nmax)
    A = np.empty((3, 3))
    v = np.empty(3)
    x = np.empty(3)
    best = np.zeros(3)
    dirs = np.zeros(8, np.bool_)
    ext = np.empty(8)
    for h in range(hr.size):
        for p in range(max_planes):
            out[h, p, :] = 0.0
        n = 0
        for dr in range(-radius, radius + 1):
            i = hr[h] + dr
            if i < 0 or i >= R:
                continue
            for dc in range(-radius, radius + 1):
                j = hc[h] + dc
                if j < 0 or j >= C:
                    continue
                for k in range(K):
                    if not np.isnan(D[i, j, k]):
                        pr[n] = dr
                        pc[n] = dc
                        pd[n] = D[i, j, k]
                        pdu[n] = D[i, j, k]
                        used[n] = False
                        n += 1
        # per hole, from its pixel: reproducible, order-free, and local (another pixel's
        # change, which adds or removes holes, leaves this hole's draws as they were)
        st = np.int64(seed) * 1000003 + np.int64(hr[h]) * C + hc[h]
        avail = n  # points not on a plane yet
        for p in range(max_planes):
            if avail < min_inliers:
                break
            best_n = 0
            best[:] = 0.0
            for _ in range(n_trials):
                st, i0 = _draw(st, n)
                st, i1 = _draw(st, n)
                st, i2 = _draw(st, n)
                if used[i0] or used[i1] or used[i2] or i0 == i1 or i1 == i2 or i0 == i2:
                    continue
                ok, x0, x1, x2 = _triple_plane(pr, pc, pd, i0, i1, i2)
                if not ok:
                    continue
                cnt = 0
                # branch-free, so it vectorises (used points hold nan in pdu: never
                # inliers): 2.8x faster than testing ``used`` (identical counts)
                for s in range(n):
                    cnt += abs(x0 + x1 * pr[s] + x2 * pc[s] - pdu[s]) <= tol
                if cnt > best_n:
                    best_n = cnt
                    best[0] = x0
                    best[1] = x1
                    best[2] = x2
                    if 5 * cnt >= 4 * avail:
                        break
            if best_n < min_inliers:
                break
            for _ in range(2):
                A[:, :] = 0.0
                v[:] = 0.0
                cnt = 0
                for s in range(n):
                    if used[s] or abs(best[0] + best[1] * pr[s] + best[2] * pc[s] - pd[s]) > tol:
                        continue
                    cnt += 1
                    f0, f1, f2 = 1.0, pr[s], pc[s]
                    A[0, 0] += f0 * f0
                    A[0, 1] += f0 * f1
                    A[0, 2] += f0 * f2
                    A[1, 1] += f1 * f1
                    A[1, 2] += f1 * f2
                    A[2, 2] += f2 * f2
                    v[0] += f0 * pd[s]
                    v[1] += f1 * pd[s]
                    v[2] += f2 * pd[s]
                A[1, 0] = A[0, 1]
                A[2, 0] = A[0, 2]
                A[2, 1] = A[1, 2]
                if cnt < min_inliers or not _solve3_into(A, v, x):
                    break
                best[:] = x
            cnt = 0
            ext[:] = -np.inf
            for s in range(n):
                if not used[s] and abs(best[0] + best[1] * pr[s] + best[2] * pc[s] - pd[s]) <= tol:
                    used[s] = True
                    pdu[s] = np.nan
                    cnt += 1
                    for u in range(8):  # the largest step along each direction (exact)
                        ext[u] = max(ext[u], _DIR_R[u] * pr[s] + _DIR_C[u] * pc[s])
            for u in range(8):
                dirs[u] = ext[u] > 0
            avail -= cnt
            if cnt < min_inliers:
                break
            for u in range(8):
                iu = hr[h] + int(_DIR_R[u])
                ju = hc[h] + int(_DIR_C[u])
                if iu < 0 or iu >= R or ju < 0 or ju >= C:
                    dirs[u] = True
            out[h, p, 4] = 1.0 if dirs.all() else 0.0
            out[h, p, 0] = best[0]
            out[h, p, 1] = best[1]
            out[h, p, 2] = best[2]
            out[h, p, 3] = cnt


@njit(cache=True, nogil=True)
def pooled_counts(y, y0, D, tol, sp, dev, hr, hc, planes, pool_k, deltas, lo, hi, n_out, b_out):
    """Sheared pooled counts and background of each (hole, plane, box, shift).

    ``y`` holds image rows ``[y0, y0 + len(y))``; ``D`` (R, C, K) the kept depths (nan:
    none): a neighbour holding a surface within ``tol`` of the plane is not pooled (its
    own return, or its tail, would make ghosts; the tested pixel is always pooled);
    ``planes`` (H, P, 5); bins ``round(plane(m) + delta) + [lo, hi]``. ``n_out``,
    ``b_out`` (H, P, nk, nd, L) float64 are written.
    """
    R, C = D.shape[0], D.shape[1]
    K = D.shape[2]
    L = y.shape[2]
    T = y.shape[3]
    H, P = planes.shape[0], planes.shape[1]
    n_out[...] = 0.0
    b_out[...] = 0.0
    for h in range(H):
        for p in range(P):
            if planes[h, p, 3] <= 0:
                continue
            a, b, c = planes[h, p, 0], planes[h, p, 1], planes[h, p, 2]
            for ik in range(pool_k.size):
                hk = pool_k[ik] // 2
                for dr in range(-hk, hk + 1):
                    i = hr[h] + dr
                    if i < 0 or i >= R:
                        continue
                    for dc in range(-hk, hk + 1):
                        j = hc[h] + dc
                        if j < 0 or j >= C:
                            continue
                        dm = a + b * dr + c * dc
                        covered = False
                        if dr != 0 or dc != 0:  # the tested pixel itself is always pooled
                            for k in range(K):
                                if abs(D[i, j, k] - dm) <= tol:  # False for nan
                                    covered = True
                        if covered:
                            continue
                        for idl in range(deltas.size):
                            t0 = int(np.rint(dm + deltas[idl]))
                            for t in range(max(t0 + lo, 0), min(t0 + hi + 1, T)):
                                for l in range(L):
                                    n_out[h, p, ik, idl, l] += y[i - y0, j, l, t]
                                    bb = sp[i, j, l] + dev[l, t]
                                    if bb > 0:  # eq:background_3
                                        b_out[h, p, ik, idl, l] += bb


@njit(cache=True, nogil=True)
def _n_pooled(D, r, c, hk, a, b, cc, tol):
    """Pixels of the ``(2 hk + 1)^2`` box around ``(r, c)`` that :func:`pooled_counts`
    pools for the plane ``a + b dr + cc dc``: the pixel itself and the neighbours with no
    surface within ``tol`` of the plane."""
    R, C, K = D.shape
    n = 0
    for i in range(max(r - hk, 0), min(r + hk + 1, R)):
        for j in range(max(c - hk, 0), min(c + hk + 1, C)):
            if i == r and j == c:
                n += 1
                continue
            dm = a + b * (i - r) + cc * (j - c)
            covered = False
            for k in range(K):
                if abs(D[i, j, k] - dm) <= tol:  # False for nan
                    covered = True
            if not covered:
                n += 1
    return n


@njit(cache=True, nogil=True)
def _filtered_window(yt, g, base, cvw, nz_t, nz_v):
    """The matched filter ``C[t] = sum_j g[j] Y[t - p + j]`` (``Correlator``) of one
    pixel's series ``yt`` (T,) at the window's bins: ``cvw[w] = sum_j g[j] yt[base + w +
    j]`` (indices reflected at the series' ends), ``base = offset - peak``.

    Away from the ends, the sum runs over the bins holding photons only (gathered once,
    ``nz_t`` / ``nz_v``, in time order): the same terms in the same order less the empty
    bins' ``0 * g[j]``, which add exactly 0 (the same value bit for bit). At low flux
    almost every bin is empty: the full sum cost ``W x n_irf`` per pixel, 27 of 31 s of
    the clean-up passes on the face scan (``_window_fields``)."""
    T = yt.size
    n = g.size
    W = cvw.size
    if base < 0 or base + W + n - 1 > T:  # a reflected index: the full sum
        for w in range(W):
            cv = 0.0
            for jj in range(n):
                cv += g[jj] * yt[_reflect(base + w + jj, T)]
            cvw[w] = cv
        return
    m = 0
    for t in range(base, base + W + n - 1):
        if yt[t] != 0:
            nz_t[m] = t
            nz_v[m] = yt[t]
            m += 1
    k0 = 0  # the first photon bin at or after the sample's first bin
    for w in range(W):
        while k0 < m and nz_t[k0] < base + w:
            k0 += 1
        cv = 0.0
        for k in range(k0, m):
            jj = nz_t[k] - base - w
            if jj >= n:
                break
            cv += g[jj] * nz_v[k]
        cvw[w] = cv


@njit(cache=True, nogil=True)
def surface_fields(
    y,
    y0,
    sp,
    dev,
    rows,
    cols,
    depth,
    s_pool,
    scales,
    irf,
    irf_peak,
    gsq,
    W,
    qloc,
    o_offset,
    o_hist,
    o_signal,
    o_counts,
    o_background,
    o_llr,
    o_z,
):
    """Surfaces fields of recovered surfaces from the raw counts (see module docstring).

    ``s_pool`` (S, L): pooled per-pixel intensity (photons) for the own-pixel check.
    """
    R, C = sp.shape[0], sp.shape[1]
    L = y.shape[2]
    T = y.shape[3]
    Q = scales.size
    n_irf = irf.shape[1]
    hmax = scales[Q - 1] // 2
    acc = np.zeros((Q, L, W))
    bh = np.empty((L, W), np.float32)
    raw = np.empty((L, W))
    inside = np.ones(W, np.bool_)
    resp = np.empty((Q, L, W))
    cvw = np.empty(W)
    nz_t = np.empty(W + n_irf, np.int64)
    nz_v = np.empty(W + n_irf)
    for s in range(rows.size):
        off = min(max(int(np.rint(depth[s])) - W // 2, 0), max(T - W, 0))
        o_offset[s] = off
        acc[:] = 0.0
        for di in range(-hmax, hmax + 1):
            ri = _reflect(rows[s] + di, R)
            for dj in range(-hmax, hmax + 1):
                cj = _reflect(cols[s] + dj, C)
                for l in range(L):
                    _filtered_window(y[ri - y0, cj, l], irf[l], off - irf_peak[l], cvw, nz_t, nz_v)
                    for q in range(Q):  # the boxes holding the pixel, in the pixels' order
                        hq = scales[q] // 2
                        if abs(di) <= hq and abs(dj) <= hq:
                            for w in range(W):
                                acc[q, l, w] += cvw[w]
        for l in range(L):
            cnt = 0.0
            bsum = 0.0
            for w in range(W):
                b = sp[rows[s], cols[s], l] + dev[l, off + w]
                bh[l, w] = b if b > 0 else np.float32(0.0)  # eq:background_3
                raw[l, w] = y[rows[s] - y0, cols[s], l, off + w]
                cnt += raw[l, w]
                bsum += bh[l, w]
            o_counts[s, l] = cnt
            o_background[s, l] = bsum
        for q in range(Q):
            inv = 1.0 / (scales[q] * scales[q])
            for l in range(L):
                ssum = 0.0
                for w in range(W):
                    r = acc[q, l, w] * inv - bh[l, w]
                    resp[q, l, w] = r
                    cv = r if r > 0 else 0.0  # eq:background_final
                    o_hist[s, q, l, w] = cv
                    ssum += cv
                o_signal[s, q, l] = ssum
        dw = depth[s] - off
        pk = irf_peak.astype(np.float64)
        o_llr[s] = _llr_one(raw, bh, inside, dw, s_pool[s], irf, pk, L, W)
        wd = min(max(int(np.rint(dw)), 0), W - 1)
        num = 0.0
        var = 0.0
        for l in range(L):
            num += resp[qloc, l, wd]
            var += bh[l, wd] * gsq[l]
        var /= scales[qloc] * scales[qloc]
        o_z[s] = num / np.sqrt(max(var, 1e-12))


def _half_max_window(irf: np.ndarray) -> tuple[int, int, np.ndarray]:
    """Bins ``[lo, hi]`` about the depth where some IRF is >= half its max; mass inside."""
    peak = irf.argmax(axis=1)
    lo, hi = 0, 0
    for g, p in zip(irf, peak, strict=True):
        above = np.flatnonzero(g >= 0.5 * g.max())
        lo, hi = min(lo, int(above[0] - p)), max(hi, int(above[-1] - p))
    idx = peak[:, None] + np.arange(lo, hi + 1)[None, :]
    ok = (idx >= 0) & (idx < irf.shape[1])
    mass = np.where(ok, np.take_along_axis(irf, np.clip(idx, 0, irf.shape[1] - 1), 1), 0).sum(1)
    return lo, hi, mass


def recover_slopes(
    counts,
    surf: dict,
    *,
    spatial: np.ndarray,
    dev: np.ndarray,
    irf: np.ndarray,
    scales: np.ndarray,
    width: int,
    fwhm: float,
    surface_pfa: float,
    presence_llr: float,
    max_surfaces: int,
    qloc: int,
    n_iter: int = 4,
    pixels: str = "all",
    seed: int = 0,
    n_jobs: int = 1,
) -> dict:
    """Surfaces missed on steep slopes, found by sheared pooled tests (module docstring).

    Parameters
    ----------
    counts : array_like (R, C, L, T) int
        Raw counts (read by rows; a lazy array is read once over the rows needed).
    surf : dict
        Kept candidate surfaces: ``row``, ``col`` (S,) int, ``depth_bin`` (S,) float;
        optionally ``presence_llr`` (S,) float (own-pixel log-likelihood ratio), which
        a replacement must not fall short of by more than ``presence_llr``.
    spatial, dev : (R, C, L) and (L, T) float32
        Background level ``b_{n,l}`` and temporal shape minus its mean
        (``bhat = max(spatial + dev, 0)``, ``eq:background_2``, ``eq:background_3``).
    irf, scales, width
        Normalised IRF (L, n); box sizes, ascending (the pooling boxes are those above
        1); W, the histogram window (bins).
    fwhm : float
        IRF's full width at half maximum (bins): inlier tolerance, shift range.
    surface_pfa : float
        False surfaces per tested pixel (after the correction for the number of tests).
    presence_llr : float
        Own-pixel check (log-likelihood ratio ``>= -presence_llr``).
    max_surfaces, qloc, n_iter : int
        Most planes tried per hole; index of the local scale; rounds of region growing.
    pixels : {"all", "weak", "holes"}
        The pixels tested: all of them; those with no kept surface or with a *weak*
        one (own log-likelihood ratio below ``presence_llr``); or only those with no
        kept surface (no replacements). See the module docstring.
    seed, n_jobs : int
        Seed of the random triples; threads (results do not depend on them).

    Returns
    -------
    dict
        The new surfaces: ``row``, ``col``, ``depth_bin``, ``start``, ``stop``,
        ``scale_index``, ``offset``, ``histograms`` (S, Q, L, W), ``signal`` (S, Q, L),
        ``counts``, ``background`` (S, L), ``presence_llr``, ``presence_z`` (S,);
        ``replaces`` (int array): indices into ``surf`` of the kept surfaces replaced
        (within 2 FWHM of a recovered one in its pixel); ``n_tested`` (int): pixels
        tested over all rounds.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar.irf import gaussian_irf
    >>> g = np.asarray(gaussian_irf(3.0), float)[None]
    >>> rng = np.random.default_rng(0)
    >>> lam = np.full((21, 21, 1, 200), 0.05)
    >>> for i in range(21):  # a ramp of 5 bins per row
    ...     lam[i, :, 0, 40 + 5 * i - 6 : 40 + 5 * i + 7] += 1.0 * g[0]
    >>> y = rng.poisson(lam)
    >>> rr, cc = np.meshgrid(np.arange(21), np.arange(21), indexing="ij")
    >>> miss = (rr - 10) ** 2 + (cc - 10) ** 2 <= 9  # a hole of 29 pixels
    >>> surf = dict(row=rr[~miss], col=cc[~miss], depth_bin=40.0 + 5 * rr[~miss])
    >>> dev = np.zeros((1, 200), np.float32)
    >>> new = recover_slopes(y, surf, spatial=np.full((21, 21, 1), 0.05, np.float32),
    ...                      dev=dev, irf=g, scales=np.array([1, 3, 7, 11]), width=13,
    ...                      fwhm=3.0, surface_pfa=0.01, presence_llr=3.0, max_surfaces=2,
    ...                      qloc=1)
    >>> err = new["depth_bin"] - (40 + 5 * new["row"])
    >>> bool(len(new["row"]) >= 20), bool(np.all(np.abs(err) <= 3))
    (True, True)
    """
    (R, C), L, Q = spatial.shape[:2], dev.shape[0], scales.size
    irf = np.asarray(irf, np.float64)
    h_max = int(scales.max()) // 2
    pool_idx = np.flatnonzero(scales > 1)
    empty = _empty(Q, L, width)
    if pool_idx.size == 0 or h_max == 0:
        return empty
    pool_k = scales[pool_idx].astype(np.int64)
    lo, hi, mass = _half_max_window(irf)
    nd = int(np.ceil(fwhm))
    deltas = np.arange(-nd, nd + 1, dtype=np.float64)
    # a neighbour is left out of the pools when one of its surfaces lies within the
    # test's reach of the plane: shift range + counting window + the matched filter's
    # half-width (beyond it a return leaves no counts in the window)
    excl = float(nd + max(-lo, hi) + width // 2)
    sp = np.ascontiguousarray(spatial, np.float32)
    dev = np.ascontiguousarray(dev, np.float32)
    K = max(int(max_surfaces), 1)
    D, Di, n_in = _dense_surfaces(surf, R, C, K)
    weak = _weak_pixels(surf, R, C, presence_llr) if pixels == "weak" else np.zeros((R, C), bool)
    tried = np.zeros((R, C), bool)  # pixels given a surface here (not tested again)
    grown = np.zeros((R, C), bool)  # pixels given a surface in the last round
    new = {k: [] for k in ("row", "col", "depth_bin", "k", "s_pool", "replaces")}
    n_tested = 0
    for it in range(n_iter):
        hr, hc = _round_pixels(n_in, tried, grown, weak, h_max, pixels, it)
        if hr.size == 0:
            break
        planes = np.zeros((hr.size, K, 5))
        _split(
            hr.size,
            n_jobs,
            lambda a, b, it=it, hr=hr, hc=hc, planes=planes: fit_planes(
                D, hr[a:b], hc[a:b], h_max, float(fwhm), K, MIN_INLIERS, N_TRIALS,
                seed + 7919 * it, planes[a:b],
            ),
        )  # fmt: skip
        hr, hc, planes, valid, repl = _testable(D, Di, n_in, hr, hc, planes, h_max, fwhm, excl)
        if hr.size == 0:
            break
        planes[..., 3] *= valid
        n_tested += hr.size
        pools = (counts, D, excl, sp, dev, hr, hc, planes, pool_k, deltas, lo, hi)
        n_arr, b_arr = _pooled(*pools, n_jobs)
        added = _accept(
            n_arr, b_arr, valid, repl, planes, hr, hc, D, tried, new, pool_k, pool_idx,
            deltas, excl, mass, surface_pfa,
        )  # fmt: skip
        logger.debug("slopes round %d: %d pixels tested, %d accepted", it, hr.size, len(added))
        if not added:
            break
        # region growing: the recovered surfaces take part in the next round (they
        # supply planes and leave the pools)
        grown = np.zeros((R, C), bool)
        for r, c, d in added:
            D[r, c, n_in[r, c]] = d
            n_in[r, c] += 1
            grown[r, c] = True
    if not new["row"]:
        out = dict(empty)
        out["n_tested"] = n_tested
        return out
    out = _recovered(
        counts, surf, new, sp, dev, irf, scales, width, qloc, presence_llr, h_max, n_jobs
    )
    out["n_tested"] = n_tested
    return out


def _empty(Q: int, L: int, width: int) -> dict:
    """What :func:`recover_slopes` returns when it recovers nothing."""
    return dict(
        row=np.zeros(0, np.int64),
        col=np.zeros(0, np.int64),
        depth_bin=np.zeros(0),
        start=np.zeros(0, np.int64),
        stop=np.zeros(0, np.int64),
        scale_index=np.zeros(0, np.int64),
        offset=np.zeros(0, np.int64),
        histograms=np.zeros((0, Q, L, width), np.float32),
        signal=np.zeros((0, Q, L)),
        counts=np.zeros((0, L)),
        background=np.zeros((0, L)),
        presence_llr=np.zeros(0),
        presence_z=np.zeros(0),
        replaces=np.zeros(0, np.int64),
        n_tested=0,
    )


def _weak_pixels(surf: dict, R: int, C: int, presence_llr: float) -> np.ndarray:
    """Pixels holding a kept surface that their own counts do not confirm: own
    log-likelihood ratio below presence_llr (the level at which they would reject it)."""
    weak = np.zeros((R, C), bool)
    if len(surf["row"]):
        row, col = np.asarray(surf["row"], np.int64), np.asarray(surf["col"], np.int64)
        llr = np.asarray(surf.get("presence_llr", np.full(row.size, -np.inf)), np.float64)
        lw = llr < presence_llr
        weak[row[lw], col[lw]] = True
    return weak


def _pooled(counts, D, excl, sp, dev, hr, hc, planes, pool_k, deltas, lo, hi, n_jobs=1):
    """Pooled counts and background along every plane, box and shift (read by bands of
    rows): two arrays ``(H, K, n_boxes, n_shifts, L)``. The holes of a band are split
    between ``n_jobs`` threads (each hole's sums are its own: the same values)."""
    h_max = int(pool_k.max()) // 2
    shape = (hr.size, planes.shape[1], pool_k.size, deltas.size, dev.shape[0])
    n_arr, b_arr = np.zeros(shape), np.zeros(shape)
    for sel, y, y0 in _row_bands(counts, hr, h_max, cols=hc):
        n_b, b_b = np.zeros((sel.size,) + shape[1:]), np.zeros((sel.size,) + shape[1:])
        r_s, c_s, pl_s = hr[sel], hc[sel], planes[sel]

        def part(a, b, y=y, y0=y0, r_s=r_s, c_s=c_s, pl_s=pl_s, n_b=n_b, b_b=b_b):
            pooled_counts(
                y, y0, D, excl, sp, dev, r_s[a:b], c_s[a:b], pl_s[a:b], pool_k, deltas, lo,
                hi, n_b[a:b], b_b[a:b],
            )  # fmt: skip

        _split(sel.size, n_jobs, part)
        n_arr[sel], b_arr[sel] = n_b, b_b
    return n_arr, b_arr


def _dense_surfaces(surf: dict, R: int, C: int, K: int):
    """The kept surfaces per pixel, dense (R, C, K + 1): nan where none; ``Di``: their
    index in ``surf`` (-1: recovered here); ``n_in``: how many per pixel."""
    row = np.asarray(surf["row"], np.int64)
    col = np.asarray(surf["col"], np.int64)
    dep = np.asarray(surf["depth_bin"], np.float64)
    D = np.full((R, C, K + 1), np.nan)
    Di = np.full((R, C, K + 1), -1, np.int64)
    n_in = np.zeros((R, C), np.int64)
    if row.size:
        # slot of each surface among its pixel's (in table order); the first K are kept
        lin = row * C + col
        order = np.argsort(lin, kind="stable")
        ls = lin[order]
        first = np.r_[True, ls[1:] != ls[:-1]]
        start = np.maximum.accumulate(np.where(first, np.arange(ls.size), 0))
        slot = np.empty(ls.size, np.int64)
        slot[order] = np.arange(ls.size) - start
        ok = slot < K
        D[row[ok], col[ok], slot[ok]] = dep[ok]
        Di[row[ok], col[ok], slot[ok]] = np.flatnonzero(ok)
        np.add.at(n_in, (row[ok], col[ok]), 1)
    return D, Di, n_in


def _box_count(mask: np.ndarray, h: int) -> np.ndarray:
    """Number of true pixels of ``mask`` in the ``(2 h + 1)^2`` box about each pixel."""
    kk = 2 * h + 1
    cs = np.pad(np.pad(mask, h).astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    return cs[kk:, kk:] - cs[:-kk, kk:] - cs[kk:, :-kk] + cs[:-kk, :-kk]


def _round_pixels(n_in, tried, grown, weak, h_max: int, pixels: str, it: int):
    """The pixels a round tests: enough surfaces around them to fit a plane, of the kind
    ``pixels`` asks for, and (after the first round) a surface gained in their window."""
    cand = ~tried & (_box_count(n_in > 0, h_max) >= MIN_INLIERS)
    if pixels == "holes":
        # only the pixels with no kept surface (module docstring, "Holes only")
        cand &= n_in == 0
    elif pixels == "weak":
        # and those with a surface their own counts do not confirm (module
        # docstring, "Weak pixels")
        cand &= (n_in == 0) | weak
    if it > 0:
        # only the pixels whose window gained a surface can have a new plane
        cand &= _box_count(grown, h_max) > 0
    return np.nonzero(cand)


def _testable(D, Di, n_in, hr, hc, planes, h_max: int, fwhm: float, excl: float):
    """The planes worth testing at each pixel, and the surface each would replace.

    A plane is tested at a pixel when it is steep (the coarsest square box spreads a
    return over more than the FWHM: square boxes already work on gentler ones), no
    surface of the pixel lies on it (within the FWHM: a hole of that plane), and the
    pixel has room for a surface: fewer than max_surfaces, or one within 2 FWHM of the
    plane (the same return at a depth biased by the square boxes, which the recovered
    surface replaces). Returns the pixels with at least one such plane: ``hr, hc,
    planes, valid (H, K), repl (H, K)``.
    """
    K = planes.shape[1]
    steep = h_max * (np.abs(planes[..., 1]) + np.abs(planes[..., 2])) >= fwhm
    dist = np.abs(D[hr, hc][:, None, :] - planes[..., :1])  # (H, K, K + 1)
    dist = np.where(np.isnan(dist), np.inf, dist)
    dmin = dist.min(axis=2)
    repl = np.take_along_axis(Di[hr, hc][:, None, :].repeat(K, 1), dist.argmin(2)[..., None], 2)[
        ..., 0
    ]
    repl = np.where((dmin > fwhm) & (dmin <= 2 * fwhm), repl, -1)
    # a new surface needs its pixel's other surfaces beyond the test's reach (else
    # their own returns, pooled with the pixel, would make it: measured on the face
    # data set, 1.4 k second surfaces in pixels of one surface)
    room = ((n_in[hr, hc] < K)[:, None] & (dmin > excl)) | (repl >= 0)
    valid = (planes[..., 3] > 0) & (planes[..., 4] > 0) & steep & (dmin > fwhm) & room
    has = valid.any(axis=1)
    return hr[has], hc[has], planes[has], valid[has], repl[has]


def _accept(
    n_arr, b_arr, valid, repl, planes, hr, hc, D, tried, new, pool_k, pool_idx, deltas,
    excl, mass, surface_pfa,
) -> list:  # fmt: skip
    """The exact Poisson test of the pooled counts (Bonferroni over the planes, boxes
    and shifts tried at a pixel); at most one recovered surface per pixel, its most
    significant plane. Appends to ``new``, marks ``tried``; returns ``(r, c, depth)``."""
    H, K = valid.shape
    nk = pool_k.size
    n_tot = n_arr.sum(-1)
    b_tot = b_arr.sum(-1)
    p = stats.poisson.sf(n_tot - 1, np.maximum(b_tot, 1e-12))  # P(N >= n | B)
    p = np.where(valid[:, :, None, None], p, 1.0)
    n_tests = valid.sum(axis=1) * nk * deltas.size  # (H,)
    flat = p.reshape(H, K, -1)
    best = flat.argmin(axis=2)  # (H, K)
    pmin = np.take_along_axis(flat, best[..., None], 2)[..., 0]
    ok = (pmin * n_tests[:, None] <= surface_pfa) & valid
    added = []
    oh, op = np.nonzero(ok)
    for i in np.argsort(pmin[oh, op], kind="stable"):
        h, pi = oh[i], op[i]
        r, c = int(hr[h]), int(hc[h])
        if tried[r, c]:
            continue
        ik, idl = np.unravel_index(best[h, pi], (nk, deltas.size))
        k = int(pool_k[ik])
        # pooled per-pixel intensity: the excess over the pixels pooled
        npix = _n_pooled(
            D, r, c, k // 2, planes[h, pi, 0], planes[h, pi, 1], planes[h, pi, 2], excl
        )
        s_pool = np.maximum(n_arr[h, pi, ik, idl] - b_arr[h, pi, ik, idl], 0)
        s_pool = s_pool / max(npix, 1) / mass
        d_new = planes[h, pi, 0] + deltas[idl]
        new["row"].append(r)
        new["col"].append(c)
        new["depth_bin"].append(d_new)
        new["k"].append(pool_idx[ik])
        new["s_pool"].append(s_pool)
        new["replaces"].append(int(repl[h, pi]))
        added.append((r, c, d_new))
        tried[r, c] = True
    return added


def _recovered(counts, surf, new, sp, dev, irf, scales, width, qloc, presence_llr, h_max, n_jobs):
    """The recovered surfaces' fields (histograms, signal, counts, presence statistics)
    and the own-pixel checks; the table :func:`recover_slopes` returns."""
    L, T = dev.shape
    Q = scales.size
    irf_peak = irf.argmax(axis=1).astype(np.int64)
    gsq = (irf**2).sum(axis=1)
    S = len(new["row"])
    rows = np.asarray(new["row"], np.int64)
    cols = np.asarray(new["col"], np.int64)
    depth = np.clip(np.asarray(new["depth_bin"], np.float64), 0, T - 1)
    s_pool = np.asarray(new["s_pool"], np.float64).reshape(S, L)
    o = dict(
        offset=np.empty(S, np.int64),
        histograms=np.empty((S, Q, L, width), np.float32),
        signal=np.empty((S, Q, L)),
        counts=np.empty((S, L)),
        background=np.empty((S, L)),
        presence_llr=np.empty(S),
        presence_z=np.empty(S),
    )
    keys = ("offset", "histograms", "signal", "counts", "background", "presence_llr")
    keys = keys + ("presence_z",)
    for sel, y, y0 in _row_bands(counts, rows, h_max, cols=cols):
        part = {k: np.empty((sel.size,) + v.shape[1:], v.dtype) for k, v in o.items()}
        r_s, c_s, d_s = rows[sel], cols[sel], depth[sel]
        sp_s = np.ascontiguousarray(s_pool[sel])

        def fields(a, b, y=y, y0=y0, part=part, r_s=r_s, c_s=c_s, d_s=d_s, sp_s=sp_s):
            surface_fields(
                y, y0, sp, dev, r_s[a:b], c_s[a:b], d_s[a:b], sp_s[a:b],
                scales.astype(np.int64), irf, irf_peak, gsq, int(width), int(qloc),
                *(part[k][a:b] for k in keys),
            )  # fmt: skip

        _split(sel.size, n_jobs, fields)
        for k in o:
            o[k][sel] = part[k]
    # own-pixel check (presence_llr). Requiring a replacement to fit the own counts at
    # least as well as the surface it replaces was measured worse
    # (single surface PPP 4, SBR 0.25: F_true 0.943 -> 0.940, false 3.9 -> 4.3 %): at
    # low counts the own pixel cannot tell two depths 3-6 bins apart
    keep = o["presence_llr"] >= -presence_llr
    # a replacement must not be rejected by the pixel's own counts against the surface
    # it replaces: own log-likelihood ratio at least the replaced one's minus
    # presence_llr. On the Art scene (PPP 10, SBR 1) replacements otherwise moved
    # 1.4 k surfaces that were within tau off their depth (F_true 0.904 -> 0.899); with
    # it, 0.905; on the single-surface ramp, where the own counts are few, it keeps the
    # replacements (F_true 0.969 either way)
    rp_all = np.asarray(new["replaces"], np.int64)
    if "presence_llr" in surf and np.any(rp_all >= 0):
        llr_old = np.asarray(surf["presence_llr"], np.float64)[np.maximum(rp_all, 0)]
        keep &= (rp_all < 0) | (o["presence_llr"] >= llr_old - presence_llr)
    out = {k: v[keep] for k, v in o.items()}
    out["row"] = rows[keep]
    out["col"] = cols[keep]
    out["depth_bin"] = depth[keep]
    out["start"] = out["offset"].copy()
    out["stop"] = out["offset"] + width
    out["scale_index"] = np.asarray(new["k"], np.int64)[keep]
    rp = np.asarray(new["replaces"], np.int64)[keep]
    out["replaces"] = np.unique(rp[rp >= 0])
    logger.debug(
        "slopes: %d surfaces recovered (%d failed the own-pixel check)",
        int(keep.sum()),
        int((~keep).sum()),
    )
    return out


def _split(n: int, n_jobs: int, fn) -> None:
    """Call ``fn(a, b)`` over ``[0, n)`` in ``n_jobs`` contiguous parts on threads."""
    n_jobs = max(1, min(int(n_jobs), n // 256 or 1))
    if n_jobs == 1:
        fn(0, n)
        return
    from concurrent.futures import ThreadPoolExecutor

    cuts = np.linspace(0, n, n_jobs + 1).round().astype(int)
    with ThreadPoolExecutor(n_jobs) as ex:
        list(ex.map(lambda ab: fn(int(ab[0]), int(ab[1])), zip(cuts[:-1], cuts[1:], strict=True)))


#: Bytes of one band of rows read from a lazy (Dask / Zarr) array by :func:`_row_bands`.
#: The calling process holds about twice that per array read (Zarr's and Dask's chunk
#: buffers beside the band), and the saliency and threshold together: 128 MB bands took
#: it 545 MB above the rest (a 128 x 1024 x 1000 slab on one worker), 32 MB ones ~140 MB.
BAND_BYTES = 32_000_000


def _row_bands(counts, rows: np.ndarray, halo: int, band: int = 64, cols=None):
    """``(selection, y, y0)`` for the items at image ``rows``: the raw counts of the rows
    they need (``y`` holds image rows from ``y0``, ``halo`` rows beyond the items').

    An in-memory cube is used whole, without a copy; a lazy (Dask / Zarr) one is read a
    band of ``band`` rows at a time (fewer when they would hold over :data:`BAND_BYTES`),
    only where there are items, the next band on a thread while the caller works on
    this one (the calling process holds two bands). The Zarr array of a cube from
    :func:`splidar.load` is read by whole stored chunks, each decoded once per call
    (:class:`_ChunkRows`), into kept buffers: a band ``y`` is valid in the caller's loop
    body only (the callers use it there and keep nothing of it).

    ``cols`` (the items' columns, optional): the caller reads only the pixels within
    ``halo`` of an item (Chebyshev distance, rows and columns). A cube kept sparse
    (:func:`kept_counts`) then writes only those pixels' counts into the band; the
    others read 0 (in memory, and unkept lazy cubes, every pixel holds its counts).
    The slope pass's later rounds and the depth alignment test a few hundred items per
    band: scattering the whole band was most of their reads' cost.
    """
    R = counts.shape[0]
    rows = np.asarray(rows, np.int64)
    if isinstance(counts, np.ndarray):
        yield np.arange(rows.size), counts, 0
        return
    row_bytes = np.dtype(counts.dtype).itemsize * int(np.prod(counts.shape[1:]))
    band = int(max(1, min(band, BAND_BYTES // max(row_bytes, 1))))
    todo = []
    for a in range(0, R, band):
        sel = np.flatnonzero((rows >= a) & (rows < a + band))
        if sel.size:
            todo.append((sel, max(0, a - halo), min(R, a + band + halo)))
    if not todo:
        return
    from concurrent.futures import ThreadPoolExecutor

    chunked = _ChunkRows.of(counts)
    masked = cols is not None and chunked is not None and chunked.sparse is not None
    cols = None if cols is None else np.asarray(cols, np.int64)

    def read(i):
        if chunked is not None:
            sel, y0, y1 = todo[i]
            need = None
            if masked:  # the pixels the items read
                need = _near_items(rows[sel] - y0, cols[sel], (y1 - y0, counts.shape[1]), halo)
            try:
                return chunked(y0, y1, need)
            except OSError as exc:  # a path the workers see and this process does not
                logger.debug("rows read through the scheduler: %s", exc)
        return np.ascontiguousarray(_read_rows(counts, todo[i][1], todo[i][2]))

    with ThreadPoolExecutor(1) as ex:
        ahead = ex.submit(read, 0)
        for i, (sel, y0, _) in enumerate(todo):
            y = ahead.result()
            ahead = ex.submit(read, i + 1) if i + 1 < len(todo) else None
            yield sel, y, y0
            del y


def _near_items(r: np.ndarray, c: np.ndarray, shape: tuple, halo: int) -> np.ndarray:
    """``(shape)`` bool: the pixels within ``halo`` (Chebyshev) of the items ``(r, c)``."""
    from scipy.ndimage import maximum_filter

    m = np.zeros(shape, np.uint8)
    m[r, c] = 1
    if halo > 0:
        m = maximum_filter(m, size=2 * int(halo) + 1, mode="constant")
    return m.astype(bool)


#: Bytes of a Zarr cube's counts the calling process may keep, sparse, while the
#: clean-up passes and the depth alignment read it (:func:`kept_counts`): the flat
#: indices and values of the nonzero counts of every chunk of rows read, up to this
#: size (5 bytes per nonzero uint8 count; the ``--large`` scene of
#: ``bench_distributed.py``, PPP about 8 in 1000 bins, needs about 130 MB for its
#: 3.1 G voxels). Chunks past it are decoded again at each read.
SPARSE_BYTES = 256 * 2**20

#: Bytes of the decoded chunks the threads of :meth:`_Sparse.start` hold at once (one
#: each): the ``--large`` cube's chunks of 32 rows (33 MB) get two threads; a cube in
#: chunks of over this size is decoded at its first read instead.
AHEAD_BYTES = 128 * 2**20

#: Sparse counts of the Zarr cubes whose clean-up runs (:func:`kept_counts`), by the
#: Dask array's name.
_KEPT: dict = {}
_KEPT_LOCK = threading.Lock()


@contextlib.contextmanager
def kept_counts(counts, threads: int = 0):
    """While the context runs, the Zarr array a Dask cube reads as it is (``splidar.load``
    of a Zarr cube) is read by :func:`_row_bands` and :func:`pixels_of` from the
    nonzero counts of its chunks of rows, each chunk decoded once (:class:`_Sparse`),
    instead of decoding the chunks again at every pass (the slope pass reads the
    cube up to five times, the spill-over lines and the alignment once each). Any
    other array: nothing changes. The values read are the same.

    ``threads`` (> 0): the chunks are decoded ahead, in row order, on that many threads
    from the context's start (:meth:`_Sparse.start`), while the passes before the first
    read (the recentring) run; the first reader (the spill-over lines) then finds them
    decoded instead of decoding them one after the other on its one read-ahead thread.
    """
    z = None
    if not isinstance(counts, np.ndarray) and hasattr(counts, "dask"):
        try:
            z = _zarr_of(counts)
        except Exception:  # any other graph
            z = None
    name = getattr(counts, "name", None)
    with _KEPT_LOCK:
        mine = z is not None and name not in _KEPT
        if mine:
            _KEPT[name] = _Sparse(z)
            if threads > 0:
                _KEPT[name].start(int(threads))
    try:
        yield
    finally:
        if mine:
            with _KEPT_LOCK:
                sp = _KEPT.pop(name, None)
            if sp is not None:
                sp.stop()


class _Sparse:
    """A Zarr array's chunks of rows, each decoded once and kept as the flat indices
    (in the chunk) and values of its nonzero entries, with where each pixel's entries
    start (``ptr``), within :data:`SPARSE_BYTES`."""

    def __init__(self, z):
        self.z, self.step = z, int(z.chunks[0])
        self.row = tuple(int(v) for v in z.shape[1:])
        self.per = int(np.prod(self.row))  # entries per image row
        self.pix = int(np.prod(self.row[1:]))  # entries per pixel
        self.dtype = np.dtype(z.dtype)
        self.chunks: dict = {}  # chunk index -> (indices, values, ptr), or None: decode
        self.bytes = 0
        self.lock = threading.Lock()
        self.buf = None  # one decoded chunk
        self.ahead: dict = {}  # chunk index -> Future of its entries (:meth:`start`)
        self.pool = None
        self.ahead_bytes = 0  # bytes the threads decoded ahead (approximately)
        self.bufs: dict = {}  # a decoding thread's chunk buffer, by thread

    def _decode(self, k: int, buf=None) -> np.ndarray:
        lo, hi = k * self.step, min((k + 1) * self.step, self.z.shape[0])
        if buf is None:
            if self.buf is None:
                self.buf = np.empty((self.step,) + self.row, self.dtype)
            buf = self.buf
        return zarr_rows_into(self.z, lo, hi, buf[: hi - lo])

    def _entries(self, a: np.ndarray) -> tuple:
        """``(indices, values, ptr)`` of the decoded chunk ``a``."""
        idx, val = _nonzero(a.reshape(-1))
        n_pix = a.shape[0] * self.row[0]
        ptr = np.searchsorted(idx, np.arange(n_pix + 1, dtype=np.int64) * self.pix)
        return idx, val, ptr.astype(idx.dtype)

    def start(self, threads: int) -> None:
        """Decode every chunk ahead, in row order, on ``threads`` threads (each into
        its own buffer; no more threads than decoded chunks fit :data:`AHEAD_BYTES`,
        none when one does not), until :data:`SPARSE_BYTES` would be passed;
        :meth:`_chunk` takes a chunk's entries from there (waiting for it when under
        way)."""
        from concurrent.futures import ThreadPoolExecutor

        chunk = self.step * int(np.prod(self.row)) * self.dtype.itemsize
        threads = min(int(threads), AHEAD_BYTES // max(chunk, 1))
        if threads < 1:  # chunks too large to hold one more per thread: read as before
            return
        n = -(-int(self.z.shape[0]) // self.step)
        self.pool = ThreadPoolExecutor(threads, thread_name_prefix="splidar-sparse")
        self.ahead = {k: self.pool.submit(self._ahead, k) for k in range(n)}

    def _ahead(self, k: int):
        """Chunk ``k``'s entries, decoded on a thread of :meth:`start` (None past the
        budget, or once stopped)."""
        if self.pool is None or self.ahead_bytes > SPARSE_BYTES:
            return None
        key = threading.get_ident()
        buf = self.bufs.get(key)
        if buf is None:
            buf = self.bufs[key] = np.empty((self.step,) + self.row, self.dtype)
        got = self._entries(self._decode(k, buf))
        self.ahead_bytes += sum(v.nbytes for v in got)
        return got

    def stop(self) -> None:
        """End the decoding ahead (chunks not started are dropped) and its buffers."""
        pool, self.pool = self.pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        self.ahead, self.bufs = {}, {}

    def _chunk(self, k: int):
        """``(indices, values, ptr)`` of chunk ``k`` (pixel ``p``'s entries are
        ``ptr[p]:ptr[p + 1]``), or the decoded chunk (over budget)."""
        if k in self.chunks and self.chunks[k] is not None:
            return self.chunks[k]
        fut = self.ahead.pop(k, None)
        got = None
        if fut is not None and not fut.cancelled():
            try:
                got = fut.result()
            except Exception:  # read it here (the error, if any, raised from there)
                got = None
        if got is not None and k not in self.chunks and self.bytes <= SPARSE_BYTES:
            self.bytes += sum(v.nbytes for v in got)
            self.chunks[k] = got
            return got
        a = self._decode(k)
        if k in self.chunks or self.bytes > SPARSE_BYTES:
            self.chunks[k] = None
            return a
        got = self._entries(a)
        self.bytes += sum(v.nbytes for v in got)
        self.chunks[k] = got
        return got

    def rows_into(self, out: np.ndarray, y0: int, y1: int, zero: bool, need=None):
        """Rows ``[y0, y1)`` written into ``out`` (shape ``(y1 - y0,) + row``; ``zero``:
        it holds zeros already); ``need`` (``(y1 - y0, cols)`` bool, optional): only
        these pixels' entries are written (the others left as they are, zero with
        ``zero``). Returns what :meth:`clear` needs to zero the entries written, or
        None when a chunk was copied whole (over the budget)."""
        parts, flat = [], out.reshape(-1)
        C = self.row[0]
        with self.lock:
            for k in range(y0 // self.step, (y1 - 1) // self.step + 1):
                lo = k * self.step
                a, b = max(y0, lo), min(y1, lo + self.step)
                got = self._chunk(k)
                if isinstance(got, np.ndarray):
                    out[a - y0 : b - y0] = got[a - lo : b - lo]
                    parts = None
                    continue
                if not zero:
                    out[a - y0 : b - y0] = 0
                if need is None:
                    cps = np.arange((a - lo) * C, (b - lo) * C, dtype=np.int64)
                else:  # the needed pixels, numbered in the chunk
                    cps = np.flatnonzero(need[a - y0 : b - y0]) + (a - lo) * C
                shift = (lo - y0) * self.per  # a chunk entry's position in ``out``
                idx, val, ptr = got
                _scatter_pixels(idx, val, ptr, cps, shift, flat, False)
                if parts is not None:
                    parts.append((k, cps, shift))
        return parts

    def clear(self, out: np.ndarray, parts) -> None:
        """Zero the entries :meth:`rows_into` wrote into ``out`` (its ``parts``)."""
        flat = out.reshape(-1)
        for k, cps, shift in parts:
            idx, val, ptr = self.chunks[k]
            _scatter_pixels(idx, val, ptr, cps, shift, flat, True)

    def pixels(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The entries ``[rows[i], cols[i]]``, ``(n,) + row[1:]``."""
        return self.windows(rows, cols, np.zeros(np.size(rows), np.int64), self.row[-1])

    def windows(self, rows: np.ndarray, cols: np.ndarray, lo: np.ndarray, width: int):
        """The entries ``[rows[i], cols[i], ..., lo[i] : lo[i] + width]`` (the last axis
        cut to ``width`` entries from ``lo[i]``, ``0 <= lo[i] <= row[-1] - width``; the
        array has at least 3 axes, a cube's counts 4), ``(n,) + row[1:-1] + (width,)``:
        only the nonzero entries inside the windows are written (:func:`_gather`)."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        lo, width = np.asarray(lo, np.int64), int(width)
        mid, n_t = self.row[1:-1], self.row[-1]  # the axes after the columns
        n_mid = int(np.prod(mid))
        out = np.zeros((rows.size * n_mid, width), self.dtype)
        # each window's first entry in its pixel, for every middle index (n, n_mid)
        heads = (np.arange(n_mid, dtype=np.int64) * n_t)[None, :] + lo[:, None]
        chunk = rows // self.step
        for k in np.unique(chunk):
            sel = np.flatnonzero(chunk == k)
            dst = (sel[:, None] * n_mid + np.arange(n_mid)).reshape(-1)
            with self.lock:
                got = self._chunk(int(k))
                if isinstance(got, np.ndarray):  # decoded (over the budget): a buffer
                    y = got[rows[sel] - k * self.step, cols[sel]].reshape(sel.size * n_mid, n_t)
                    t = np.repeat(lo[sel], n_mid)[:, None] + np.arange(width)
                    out[dst] = np.take_along_axis(y, t, axis=1)
                    continue
            idx, val = got[0], got[1]  # kept as they are once made: read without the lock
            first = ((rows[sel] - k * self.step) * self.row[0] + cols[sel]) * (n_mid * n_t)
            _gather(idx, val, (first[:, None] + heads[sel]).reshape(-1), width, dst, out)
        return out.reshape((rows.size,) + mid + (width,))


@njit(cache=True, nogil=True)
def _scatter_pixels(idx, val, ptr, cps, shift, out, clear):  # pragma: no cover - numba
    """``out[idx[e] + shift] = val[e]`` (0 with ``clear``) for the entries ``e`` of the
    pixels ``cps`` (``ptr[p]:ptr[p + 1]``)."""
    for p in cps:
        for e in range(ptr[p], ptr[p + 1]):
            out[idx[e] + shift] = 0 if clear else val[e]


@njit(cache=True, nogil=True)
def _gather(idx, val, starts, width, dst, out):  # pragma: no cover - numba
    """``out[dst[i], j - starts[i]] = val[p]`` for every entry ``p`` of the sparse
    ``(idx, val)`` (``idx`` ascending) with ``starts[i] <= j = idx[p] < starts[i] +
    width``: each window found by bisection, its entries copied."""
    for i in range(starts.size):
        s0 = starts[i]
        p = np.searchsorted(idx, s0)
        while p < idx.size and idx[p] < s0 + width:
            out[dst[i], idx[p] - s0] = val[p]
            p += 1


def _nonzero(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (ascending; int32 when they fit) and values of the nonzero entries
    of a 1-D array: the 8-byte words holding one are found first (most are zero)."""
    kind = np.int32 if flat.size < 2**31 else np.int64
    n = int(np.count_nonzero(flat))
    idx, val = np.empty(n, kind), np.empty(n, flat.dtype)
    per = 8 // flat.itemsize if 8 % flat.itemsize == 0 else 0
    if n == 0:
        return idx, val
    try:
        if per == 0 or flat.size % per:
            raise ValueError
        words = flat.view(np.uint64)
    except ValueError:  # not a whole number of aligned 8-byte words
        idx[:] = np.flatnonzero(flat)
        val[:] = flat[idx]
        return idx, val
    _nonzero_words(words, flat, per, idx, val)
    return idx, val


@njit(cache=True, nogil=True)
def _nonzero_words(words, flat, per, idx, val):
    n = 0
    for w in range(words.size):
        if words[w] != 0:
            base = w * per
            for j in range(base, base + per):
                if flat[j] != 0:
                    idx[n] = j
                    val[n] = flat[j]
                    n += 1
    return n


def pixels_of(counts, rows, cols):
    """The counts of pixels ``(rows, cols)`` from the sparse chunks of a cube in a
    :func:`kept_counts` context, or None (not kept)."""
    sp = _KEPT.get(getattr(counts, "name", None))
    return None if sp is None else sp.pixels(rows, cols)


def sparse_of(counts):
    """The sparse chunks (:class:`_Sparse`: ``.pixels``, ``.windows``) of a cube in a
    :func:`kept_counts` context, or None (not kept)."""
    return _KEPT.get(getattr(counts, "name", None))


class _ChunkRows:
    """Rows ``[y0, y1)`` of a Zarr array, for :func:`_row_bands`: from its sparse chunks
    in a :func:`kept_counts` context, else by whole stored chunks of rows, each
    decoded once while the bands (which go down the image and overlap by their halos)
    need it. Reading a band of 32 rows with a halo of 5 as one slice decoded the three
    chunks of 32 rows it touches (a chunk decoded up to three times per pass). The
    values are the same; only the decoding is saved. Bands are returned in three
    buffers used in turn: one the caller works on, one read ahead, a spare."""

    def __init__(self, z, sparse=None):
        self.z, self.step, self.sparse = z, int(z.chunks[0]), sparse
        self.row = tuple(int(v) for v in z.shape[1:])
        self.dtype = np.dtype(z.dtype)
        self.kept: dict = {}  # chunk index -> its rows (a view of a kept buffer)
        self.free: list = []  # buffers of chunks no later band needs
        self.bands: list = [np.empty(0, self.dtype) for _ in range(3)]
        # sparse: each band buffer's nonzero positions (zeroed before its next band;
        # None: zero it whole)
        self.dirty: list = [None] * 3
        self.turn = 0

    @classmethod
    def of(cls, counts):
        """A reader of the Zarr array a Dask array reads as it is (``splidar.load`` of
        a Zarr cube), else None."""
        if isinstance(counts, np.ndarray) or not hasattr(counts, "dask"):
            return None
        sparse = _KEPT.get(getattr(counts, "name", None))
        if sparse is not None:
            return cls(sparse.z, sparse)
        try:
            z = _zarr_of(counts)
        except Exception:  # any other graph
            return None
        return None if z is None else cls(z)

    def _chunk(self, k: int) -> np.ndarray:
        a = self.kept.get(k)
        if a is None:
            lo, hi = k * self.step, min((k + 1) * self.step, self.z.shape[0])
            buf = self.free.pop() if self.free else np.empty((self.step,) + self.row, self.dtype)
            a = zarr_rows_into(self.z, lo, hi, buf[: hi - lo])
            self.kept[k] = a
        return a

    def __call__(self, y0: int, y1: int, need=None) -> np.ndarray:
        """The rows ``[y0, y1)`` (valid until the third call after this one); ``need``
        (sparse only, see :meth:`_Sparse.rows_into`): the pixels whose counts are
        written, the others 0."""
        n, t = (y1 - y0) * int(np.prod(self.row)), self.turn
        self.turn = (t + 1) % len(self.bands)
        if self.sparse is not None:  # buffers of zeros, where only the nonzeros move
            if self.bands[t].size < n:
                self.bands[t], self.dirty[t] = np.zeros(n, self.dtype), []
            buf, zero = self.bands[t], self.dirty[t] is not None
            if zero:
                self.sparse.clear(buf, self.dirty[t])
            out = buf[:n].reshape((y1 - y0,) + self.row)
            self.dirty[t] = None  # until written
            self.dirty[t] = self.sparse.rows_into(out, y0, y1, zero, need)
            return out
        if self.bands[t].size < n:
            self.bands[t] = np.empty(n, self.dtype)
        out = self.bands[t][:n].reshape((y1 - y0,) + self.row)
        for k in range(y0 // self.step, (y1 - 1) // self.step + 1):
            c, lo = self._chunk(k), k * self.step
            a, b = max(y0, lo), min(y1, lo + c.shape[0])
            out[a - y0 : b - y0] = c[a - lo : b - lo]
        # the bands go down the image: no later band starts above y0
        for k in [k for k in self.kept if k < y0 // self.step]:
            self.free.append(self.kept.pop(k).base)
        return out


#: Name prefixes of the Dask graph layers that only read stored chunks and slice them
#: (``dask.array.from_zarr`` / ``from_array`` and indexing).
_READ_LAYERS = ("original-", "from-zarr-", "array-", "getitem-")


def _read_rows(counts, y0: int, y1: int) -> np.ndarray:
    """Rows ``[y0, y1)`` of an array in memory in the calling process.

    A Dask array whose graph only reads stored chunks (``splidar.load`` of a Zarr cube)
    is read by this process directly, not through the cluster: a worker's read,
    serialised and sent over, took 5 x longer (0.11 s against 0.02 s for 32 rows of
    1024 x 1000 uint8 counts; the slopes pass reads the cube up to five times). The
    Zarr array of a ``dask.array.from_zarr`` graph is sliced itself (:func:`_zarr_of`:
    a third of the CPU time of Dask's synchronous scheduler, which copies the chunks
    into the band once more); another reading graph runs on that scheduler. Any other
    graph is computed by the active scheduler, and so is a stored one whose files this
    process cannot open (a cluster's workers may see a path the calling process does
    not).
    """
    part = counts[y0:y1]
    layers = getattr(getattr(part, "dask", None), "layers", None)
    if layers is not None and all(str(k).startswith(_READ_LAYERS) for k in layers):
        try:
            z = _zarr_of(counts)
            if z is not None:
                return np.asarray(z[y0:y1])
            return np.asarray(part.compute(scheduler="sync"))
        except OSError as exc:
            logger.debug("rows %d-%d read through the scheduler: %s", y0, y1, exc)
    return np.asarray(part)


def _zarr_of(counts):
    """The Zarr array a Dask array reads as it is (``dask.array.from_zarr``: one layer
    holding the array, one reading its chunks; same shape and dtype), else None."""
    layers = counts.dask.layers
    if len(layers) != 2 or not str(counts.name).startswith("from-zarr-"):
        return None
    orig = [v for k, v in layers.items() if str(k).startswith("original-")]
    if len(orig) != 1 or len(orig[0]) != 1:
        return None
    z = next(iter(orig[0].values()))
    z = getattr(z, "value", z)  # a DataNode of Dask's task spec
    ok = hasattr(z, "get_orthogonal_selection") and tuple(z.shape) == tuple(counts.shape)
    return z if ok and np.dtype(z.dtype) == counts.dtype else None


def support_sums(saliency, threshold, rows, cols, start, stop) -> tuple[np.ndarray, np.ndarray]:
    """Saliency mass and evidence of surfaces over their supports ``[start, stop)``.

    ``saliency`` (R, C, T) (array or Zarr); ``threshold`` a float, (1, 1, T) or
    (R, C, T). Evidence as in the main pass: ``sum max(S / threshold - 1, 0)``. Arrays
    in memory and Zarr arrays are read at the supports' voxels only (a Zarr array
    decodes the chunks that hold them, once each); any other array a band of rows at a
    time (not once per surface).
    """
    rows = np.asarray(rows, np.int64)
    cols = np.asarray(cols, np.int64)
    S = rows.size
    lo = np.asarray(start, np.int64)
    n = np.asarray(stop, np.int64) - lo
    cut = np.concatenate([[0], np.cumsum(n)])
    item = np.repeat(np.arange(S), n)  # the supports' voxels, surface by surface
    t = lo[item] + np.arange(item.size) - cut[item]
    sal = _voxels(saliency, rows[item], cols[item], t)
    if sal is None:
        return _support_sums_bands(saliency, threshold, rows, cols, start, stop)
    if np.isscalar(threshold):
        thr = np.full(item.size, float(threshold))
    elif threshold.shape[0] == 1:
        thr = np.asarray(threshold[0, 0], np.float64)[t]
    elif hasattr(threshold, "pixels"):
        # a threshold computed on access (ThresholdField), at these pixels only
        thr = threshold.pixels(rows, cols)[item, t]
    else:
        thr = _voxels(threshold, rows[item], cols[item], t)
        if thr is None:
            return _support_sums_bands(saliency, threshold, rows, cols, start, stop)
    mass, ev = np.zeros(S), np.zeros(S)
    for s in range(S):  # each sum over its support alone, as the band loop does
        v = np.asarray(sal[cut[s] : cut[s + 1]], np.float64)
        w = np.asarray(thr[cut[s] : cut[s + 1]], np.float64)
        mass[s] = v.sum()
        ev[s] = np.maximum(v / np.maximum(w, 1e-12) - 1.0, 0.0).sum()
    return mass, ev


#: Voxels read from a Zarr array by one coordinate selection in :func:`_voxels`.
_VOXELS_PER_READ = 1 << 20


def _voxels(a, rows, cols, t) -> np.ndarray | None:
    """``a[rows[i], cols[i], t[i]]`` of an ndarray or a Zarr array; None for any other
    kind of array. A Zarr array stored raw in a folder (the map pass's saliency) is read
    at the voxels' pages of its chunk files (:func:`~splidar._arrays.zarr_voxels`), any
    other by Zarr's coordinate selection (the chunks holding the voxels read whole)."""
    if isinstance(a, np.ndarray):
        return a[rows, cols, t]
    if not hasattr(a, "get_coordinate_selection"):
        return None
    out = zarr_voxels(a, (rows, cols, t))
    if out is not None:
        return out
    out = np.empty(rows.size, a.dtype)
    for i in range(0, rows.size, _VOXELS_PER_READ):
        j = slice(i, i + _VOXELS_PER_READ)
        out[j] = a.get_coordinate_selection((rows[j], cols[j], t[j]))
    return out


def _support_sums_bands(saliency, threshold, rows, cols, start, stop):
    """:func:`support_sums` for an array read a band of rows at a time (e.g. Dask)."""
    S = rows.size
    mass = np.zeros(S)
    ev = np.zeros(S)
    thr_arr = None if np.isscalar(threshold) else threshold
    per_voxel = thr_arr is not None and thr_arr.shape[0] != 1
    thr_t = None
    if thr_arr is not None and not per_voxel:
        thr_t = np.asarray(thr_arr[0, 0], np.float64)
    # a threshold computed on access (ThresholdField) is computed at these pixels only
    thr_px = thr_arr.pixels(rows, cols) if per_voxel and hasattr(thr_arr, "pixels") else None
    for sel, sal_b, r0 in _row_bands(saliency, rows, 0):
        thr_b = None
        if per_voxel and thr_px is None:
            thr_b = np.asarray(thr_arr[r0 : r0 + sal_b.shape[0]])
        for s in sel:
            a, b = int(start[s]), int(stop[s])
            i, j = rows[s] - r0, cols[s]
            sal = np.asarray(sal_b[i, j, a:b], np.float64)
            if thr_arr is None:
                thr = float(threshold)
            elif thr_px is not None:
                thr = np.asarray(thr_px[s, a:b], np.float64)
            elif per_voxel:
                thr = np.asarray(thr_b[i, j, a:b], np.float64)
            else:
                thr = thr_t[a:b]
            mass[s] = sal.sum()
            ev[s] = np.maximum(sal / np.maximum(thr, 1e-12) - 1.0, 0.0).sum()
    return mass, ev
