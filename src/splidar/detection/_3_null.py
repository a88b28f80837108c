"""Stage 3: the null model and the thresholds (voxel and surface level).

Background-only cubes are drawn from the estimated background on random patches of the
image and their saliency computed with the data's filters (stage 2): the voxel threshold
is the ``1 - pfa`` quantile of that null saliency as a function of the local background
level (``null="empirical"``), or the paper's gamma fit (``eq:gamma_distrib``,
``null="gamma"``). The candidates found in the null patches then set the surface-level
threshold on the evidence (``surface_pfa`` false surfaces per background-only pixel).
"""

from __future__ import annotations

import contextlib
import dataclasses
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from numba import njit
from scipy import stats

from ._2_saliency import SaliencyFilters, block_saliency
from ._fast import poisson_background
from ._kernels import find_segments, fine_response
from ._null import fit_gamma_quantiles, threshold_table
from ._result import NullModel
from ._threads import on_parts

__all__ = [
    "NullCalibration",
    "TAIL_VOXELS",
    "calibrate_null",
    "data_tail",
    "evidence",
    "split_rule",
    "tail_step",
]

#: Voxels :func:`data_tail` reads at most (a regular sub-grid of the pixels).
TAIL_VOXELS = 8_000_000


def tail_step(shape, max_voxels: int = TAIL_VOXELS) -> int:
    """The step ``s`` of :func:`data_tail`'s sub-grid ``counts[::s, ::s]`` for a cube of
    ``shape`` ``(rows, cols, L, T)``: the smallest with at most about ``max_voxels``."""
    R, C, L, T = shape
    return max(1, int(np.ceil(np.sqrt(R * C * L * T / max_voxels))))


# the fine response of the null's patches comes precomputed (find_segments's ``fine``)
_NO_C = np.empty((0, 0, 0, 0), np.float32)
_NO_SP = np.empty((0, 0, 0), np.float32)
_NO_DEV = np.empty((0, 0), np.float32)
_NO_Y = np.empty((0, 0, 0, 0), np.uint16)


@dataclass(frozen=True)
class NullCalibration:
    """The fitted null and the thresholds drawn from it.

    Attributes
    ----------
    model : NullModel
        What :class:`~splidar.detection.Detection` reports.
    levels, thresholds : ndarray
        The empirical threshold table: threshold as a function of the summed
        background level ``sum_l bhat``.
    gamma_threshold : float
        The paper's gamma threshold at ``pfa``.
    evidence_threshold : float
        A candidate is kept when its evidence exceeds this (``surface_pfa``).
    split : tuple, optional
        The fine split's rule the null's candidates were split with
        (:func:`split_rule`, its tail taken from the data by :func:`data_tail`); the
        map pass splits with the same. ``None``: the rule of the IRF alone.
    """

    model: NullModel
    levels: np.ndarray
    thresholds: np.ndarray
    gamma_threshold: float
    evidence_threshold: float
    split: tuple | None = None

    def threshold_at(self, level):
        """The voxel threshold (float32) at a summed background level."""
        if self.model.method == "gamma-quantile":
            return np.float32(self.gamma_threshold)
        if self.levels.size == 1:
            return np.float32(self.thresholds[0])
        xs, ys = self.levels.astype(np.float64), self.thresholds.astype(np.float64)
        return np.interp(level, xs, ys).astype(np.float32)

    def table(self, per_voxel: bool) -> tuple:
        """``(levels, thresholds, write per-voxel threshold)`` for the map pass."""
        if self.model.method == "gamma-quantile":
            return (np.zeros(1), np.array([float(np.float32(self.gamma_threshold))]), False)
        # a threshold varying with the level is computed by the main pass and kept as
        # its factors (ThresholdField; written out only to a store), or reduced to its
        # variation with t alone if the background turns out spatially flat
        return (
            np.asarray(self.levels, np.float64),
            np.asarray(self.thresholds, np.float64),
            self.levels.size > 1 and per_voxel,
        )


class _FixedSeed:
    """Stands in for a Generator whose next ``integers`` draw was taken in advance."""

    def __init__(self, seed: int):
        self.seed = int(seed)

    def integers(self, *args, **kwargs) -> int:
        return self.seed


def _null_samples(
    counts, ctx: SaliencyFilters, n_target: int, rng, *, patch: int = 32, max_patches=400,
    fine: bool = False,
):  # fmt: skip
    """Saliency of background-only cubes drawn from the estimated background.

    Random patches of the image: the background level is estimated from the data around
    each (exactly as in the main pass), a Poisson cube of ``bhat`` is drawn and its
    saliency computed with the same filters; the patch interior (at least ``h`` pixels
    from any cut) is kept. Returns null saliency, its level, its signed response, the
    data's saliency on the same patches (for the gamma fit), and with ``fine`` each
    patch's own-pixel fine response, photons and background
    (:func:`~splidar.detection._kernels.fine_response`; empty arrays without).

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
        # the data's saliency and levels only: no sum_l bhat (the same values)
        _, sal_w, _, sp_w, _ = block_saliency(
            yw, wctx, keep=slice(sr0 - dr0, sr1 - dr0), with_level=False
        )
        sp = sp_w[:, sc0 - dc0 : sc1 - dc0].copy()
        real = sal_w[r0 - sr0 : r1 - sr0, c0 - dc0 : c1 - dc0].ravel().copy()
        return sp, real

    def simulate(item):
        r0, r1, c0, c1, seed = item
        sp, real = windows[(r0, r1, c0, c1)]
        # Poisson cube of bhat (eq:background_3), drawn in numba (seeded from rng)
        ysim = poisson_background(sp, ctx.dev, _FixedSeed(seed))
        c, sal, d, _, level = block_saliency(ysim, wctx, spatial=sp)
        i0, j0 = r0 - max(0, r0 - h), c0 - max(0, c0 - h)
        sl = (slice(i0, i0 + r1 - r0), slice(j0, j0 + c1 - c0))
        # the own pixel's fine response, photons and background (the map pass's second
        # split), when it splits
        shp = (r1 - r0, c1 - c0, T) if fine else (0, 0, 0)
        f_n_mu = tuple(np.empty(shp, np.float32) for _ in range(3))
        if fine:
            _fine_on_threads(c[sl], ysim[sl], sp[sl], dev, win, f_n_mu, wctx.workers)
        return sal[sl].copy(), level[sl].copy(), d[sl].copy(), real, f_n_mu

    dev = np.ascontiguousarray(ctx.dev, np.float32)
    win = split_rule(ctx.corr.irf, 0.0)[3] if fine else None
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
    f_n_mu = [r[4] for r in res]
    return s_sim, lev, d_sim, np.concatenate([r[3] for r in res]), f_n_mu


def _fine_on_threads(c, y, sp, dev, win, out: tuple, workers: int) -> None:
    """:func:`~splidar.detection._kernels.fine_response` of a patch into ``out`` (f, n,
    mu), its rows split between ``workers`` threads (every voxel's values are its own,
    so the split never changes them; the kernel releases the GIL)."""

    def part(i0, i1):
        rows = slice(i0, i1)
        fine_response(c[rows], y[rows], sp[rows], dev, win, *(a[rows] for a in out))

    on_parts(part, c.shape[0], workers)


def split_rule(
    irf: np.ndarray, z: float, data: np.ndarray | None = None, reach: float = 0.0,
    slack: float = 0.0, pool: bool = False,
) -> tuple:  # fmt: skip
    """The fine split's settings for :func:`~splidar.detection._kernels.find_segments`.

    Parameters
    ----------
    irf : ndarray (L, n_irf)
        Normalised IRF.
    z : float
        The Poisson z a second return's photons need beside the first (0: no split).
    data : ndarray (2, m) or (m,), optional
        The same fraction measured on the data's own returns (:func:`data_tail`), after
        / before the peak (one row: both sides): ``tail`` is the larger of the IRF's
        and this at each offset and side (and as long as the longer), so a real
        return's tail heavier than the IRF's is not taken for a second return, and
        nothing changes where the IRF is right.

    reach : float
        A second return is looked for only within ``reach`` FWHMs (the half-peak
        window's width) of a stronger accepted one (0: anywhere in the segment).

    Returns
    -------
    (z, tail, gmin, win, reach, pool) : tuple
        (float, ndarray (2, n_irf), float, ndarray (L, 2), int, bool).
        ``win[l]``: offsets from a response's bin to the first and last bin where the
        IRF of a return peaking there is above half its peak (the half-peak window);
        ``tail[0, k]`` / ``tail[1, k]``: the fraction of one return's photons in the
        half-peak window of a bin ``k`` bins after / before its peak (the largest over
        the wavelengths). Each side its own: a tailed return (a SPAD's, a real one)
        puts its tail behind its peak, so a weaker return in front of it (a net before
        a wall) is not judged against the tail behind it;
        ``gmin``: the smallest ``sum g^2`` (one photon's matched-filter response);
        ``reach``: in bins (0: anywhere).
    slack : float
        The first return's tail may be ``1 + slack`` times the one measured (pixels'
        tails vary about the pooled one): ``tail`` scaled so. Matters only beside
        bright returns; a weak return's tail is a fraction of a photon either way.
    pool : bool
        A second return in front of a stronger one that the own photons show by ``z``
        but not by ``sqrt(z^2 + 2 ln n)`` is accepted when its 3 x 3 neighbourhood's
        photons at the same place relative to their own first return show it
        (:func:`~splidar.detection._kernels._fine_split`): the last entry.
    """
    g = np.asarray(irf, np.float64)
    L, n = g.shape
    win = np.zeros((L, 2), np.int64)
    tail = np.zeros((2, n))
    for l in range(L):
        p = int(np.argmax(g[l]))
        above = np.flatnonzero(g[l] >= 0.5 * g[l, p])
        lo, hi = int(above[0]) - p, int(above[-1]) - p
        win[l] = lo, hi
        # a return peaking at 0: its photon at bin u has probability g[p + u]; side 0
        # the window k bins after its peak, side 1 k bins before
        for k in range(n):
            for side, sgn in enumerate((1, -1)):
                idx = p + sgn * k + np.arange(lo, hi + 1)
                ok = (idx >= 0) & (idx < n)
                tail[side, k] = max(tail[side, k], float(g[l, idx[ok]].sum()))
    if data is not None and data.size:
        data = np.atleast_2d(np.asarray(data, np.float64))
        data = np.broadcast_to(data, (2, data.shape[-1]))
        m = max(n, data.shape[1])
        both = np.zeros((2, 2, m))
        both[0, :, :n], both[1, :, : data.shape[1]] = tail, data
        tail = both.max(axis=0)
    fw = int((win[:, 1] - win[:, 0]).max()) + 1
    reach_bins = int(np.ceil(reach * fw)) if reach > 0 else 0
    tail = tail * (1.0 + slack)
    return float(z), tail, float((g * g).sum(axis=1).min()), win, reach_bins, bool(pool)


def data_tail(
    counts, irf: np.ndarray, dev: np.ndarray, *, max_voxels: int = TAIL_VOXELS, sample=None
):
    """The fraction of one real return's photons in the half-peak window ``k`` bins
    from its peak, measured on the data (the fine split's ``tail``, :func:`split_rule`).

    The pixels of a regular sub-grid (at most ``max_voxels`` voxels read) are aligned at
    their own matched-filter peak; those whose peak is a bright return (the photons of
    its half-peak window above the background by a Poisson z of ``sqrt(25 + 2 ln T)``)
    are pooled: their background-subtracted photons in the half-peak window ``k`` bins
    before and after the peak, over their summed matched-filter peak response divided
    by ``sum g^2`` (the photons :func:`~splidar.detection._kernels._fine_split` gives a
    return), each side its own. Made non-increasing in ``k`` (a running minimum), so that
    second returns at a common distance (a scene of close pairs) do not raise it past
    the dip before them. Background: each pixel's median matched-filtered level plus
    the temporal shape ``dev``.

    Parameters
    ----------
    counts : array_like (rows, cols, L, T)
    irf : ndarray (L, n_irf)
        Normalised IRF.
    dev : ndarray (L, T)
        The background's temporal shape (stage 1).
    max_voxels : int
        Voxels read at most.
    sample : ndarray (rows', cols', L, T), optional
        ``counts[::s, ::s]`` with ``s = tail_step(counts.shape, max_voxels)``, already
        read (a Zarr cube's first pass gathers it: ``_tiled.first_pass``); ``counts``
        is then not read (it may be None). The same result.

    Returns
    -------
    ndarray (2, m) float64
        After / before the peak; ``m = n_irf + 4 x`` the half-peak width; empty (size 0)
        when fewer than 20 pixels qualify.
    """
    from scipy.ndimage import correlate1d

    g = np.asarray(irf, np.float64)
    if sample is None:
        s = tail_step(counts.shape, max_voxels)
        sample = counts[::s, ::s]
    L, T = sample.shape[2:]
    n = g.shape[1]
    gmin, win = split_rule(g, 0.0)[2:4]
    fw = int((win[:, 1] - win[:, 0]).max()) + 1
    m = n + 4 * fw
    lo_u, hi_u = -m + int(win[:, 0].min()), m + int(win[:, 1].max())
    y = np.asarray(sample, np.float32).reshape(-1, L, T)
    if y.shape[0] < 20:
        return np.zeros(0)
    c = np.empty_like(y)
    pk = np.argmax(g, axis=1)
    for l in range(L):
        # c[t] = sum_u y[t + u - pk] g[u]: a return peaking at t
        c[:, l] = correlate1d(y[:, l], g[l].astype(np.float32), axis=-1, mode="constant",
                              origin=int(pk[l]) - n // 2)  # fmt: skip
    dv = np.asarray(dev, np.float32)
    # each pixel's peak: argmax over t of sum_l (c - max(median_t c - median_t dv + dv, 0))
    t0 = np.empty(c.shape[0], np.int64)
    _peak_bins(c, dv, np.median(dv, axis=-1).astype(np.float32), t0)
    ok = (t0 + lo_u >= 0) & (t0 + hi_u < T)
    idx = np.flatnonzero(ok)
    u = np.arange(lo_u, hi_u + 1)
    if idx.size < 20 or T - u.size < 16:
        return np.zeros(0)
    y, c, t0 = y[idx], c[idx], t0[idx]
    tt = np.broadcast_to((t0[:, None] + u[None])[:, None, :], (idx.size, L, u.size))
    ya = np.take_along_axis(y, tt, axis=-1)  # (P, L, U): aligned at the peak
    # each pixel's background level: its mean outside the aligned bins (the median of
    # a few counts a bin falls below their mean)
    dva = dv[:, u[None, :] + t0[:, None]].transpose(1, 0, 2)
    lvl = ((y - dv[None]).sum(axis=-1, dtype=np.float64) - (ya - dva).sum(axis=-1)) / (T - u.size)
    b = np.maximum(lvl[:, :, None] + dva, 0.0)
    i0 = -lo_u
    cb = np.maximum(lvl + dv[:, t0].T, 0.0)  # (P, L) background at the peak
    f = (c[np.arange(t0.size), :, t0] - cb).sum(axis=1)
    # the half-peak window at the peak: a bright return (z against the T places)
    nw = np.zeros(t0.size)
    mw = np.zeros(t0.size)
    for l in range(L):
        sl = slice(int(win[l, 0]) + i0, int(win[l, 1]) + i0 + 1)
        nw += ya[:, l, sl].sum(axis=-1)
        mw += b[:, l, sl].sum(axis=-1)
    mw = np.maximum(mw, 1e-12)
    dvs = 2.0 * (nw * np.log(np.maximum(nw, 1e-300) / mw) - (nw - mw))
    bright = (nw > mw) & (np.sqrt(np.maximum(dvs, 0.0)) >= np.sqrt(25.0 + 2.0 * np.log(T)))
    if bright.sum() < 20:
        return np.zeros(0)
    return _pooled_tail(ya[bright], b[bright], f[bright].sum(dtype=np.float64) / gmin, win, i0, m)


@njit(cache=True, nogil=True)
def _median_ties(a, n):  # pragma: no cover - numba
    """``np.median`` of ``a[:n]`` (float32, no NaN): the middle order statistic, or the
    float32 mean of the two middle ones; ``a`` permuted. Hoare's selection (the scans
    stop at values equal to the pivot), linear on the many ties of sparse counts."""
    half = n >> 1
    k = half if n & 1 else half - 1
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = a[(lo + hi) >> 1]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    if n & 1:
        return a[k]
    nxt = a[k + 1]  # the next order statistic: the smallest above position k
    for t in range(k + 2, n):
        if a[t] < nxt:
            nxt = a[t]
    return (a[k] + nxt) / np.float32(2)


@njit(cache=True, nogil=True)
def _peak_bins(c, dv, dv_med, t0):  # pragma: no cover - numba
    """``t0[p] = argmax_t f[p, t]``, ``f = (c - max(lvl[:, :, None] + dv, 0)).sum(axis=1)``
    with ``lvl = median_t c - dv_med`` (float32, NumPy's median: the mean of the two
    middle order statistics), the float32 operations of NumPy's expression in its order
    (the wavelengths added one after the other), in one pass per pixel without the
    ``(P, L, T)`` temporaries: the same bins."""
    P, L, T = c.shape
    scratch = np.empty(T, np.float32)
    f = np.empty(T, np.float32)
    for p in range(P):
        for l in range(L):
            for t in range(T):
                scratch[t] = c[p, l, t]
            lvl = _median_ties(scratch, T) - dv_med[l]
            row, d = c[p, l], dv[l]
            zero = np.float32(0.0)
            if l == 0:  # np.maximum(bh, 0.0): bh unless below 0 (NaN, -0.0 kept)
                for t in range(T):
                    bh = lvl + d[t]
                    f[t] = row[t] - (zero if bh < zero else bh)
            else:
                for t in range(T):
                    bh = lvl + d[t]
                    f[t] += row[t] - (zero if bh < zero else bh)
        best = 0  # np.argmax: the first of the largest, the first NaN if any
        if f[0] == f[0]:
            for t in range(1, T):
                v = f[t]
                if v != v:
                    best = t
                    break
                if v > f[best]:
                    best = t
        t0[p] = best


def _windows(a, win, i0, m):
    """(P, m, 2): ``a`` (P, L, U) summed over L and the half-peak window ``k`` bins
    after / before the bin ``i0``, ``k < m``."""
    P, L, _ = a.shape
    cs = np.concatenate([np.zeros((P, L, 1)), np.cumsum(a, axis=-1, dtype=np.float64)], axis=-1)
    out = np.zeros((P, m, 2))
    k = np.arange(m)
    for l in range(L):
        for side, sgn in enumerate((1, -1)):
            lo = i0 + sgn * k + int(win[l, 0])
            hi = i0 + sgn * k + int(win[l, 1]) + 1
            out[:, :, side] += cs[:, l, hi] - cs[:, l, lo]
    return out


def _pooled_tail(ya, b, photons, win, i0, m):
    """The pooled tail fraction (:func:`data_tail`) of aligned counts ``ya`` (P, L, U)
    over the background ``b``, ``photons`` the pixels' summed return photons."""
    if ya.shape[0] < 20 or photons <= 0:
        return np.zeros(0)
    var = ya.sum(axis=0, dtype=np.float64)  # (L, U) Poisson variance of the pooled counts
    res = var - b.sum(axis=0, dtype=np.float64)
    z_rise = np.sqrt(9.0 + 2.0 * np.log(res.shape[1]))
    for l in range(res.shape[0]):
        for sl in (slice(i0, None), slice(i0, None, -1)):
            # non-increasing away from the peak, bin by bin; where the pool rises again
            # significantly (a second return at a common distance, not a tail) the
            # tail ends at the dip before it
            v, w = res[l, sl], var[l, sl]
            out = np.maximum(v, 0.0)
            jmin = 0
            for j in range(1, v.size):
                if out[j] <= out[jmin]:
                    jmin = j
                elif v[j] - v[jmin] > z_rise * np.sqrt(w[j] + w[jmin]):
                    out[jmin:] = 0.0
                    break
                out[j] = out[jmin]
            res[l, sl] = out
    out = _windows(res[None], win, i0, m)[0].T  # (2, m): after / before the peak
    return np.minimum.accumulate(np.maximum(out / photons, 0.0), axis=1)


def evidence(sal, thr):
    """Excess of the saliency over the threshold, relative to it: ``max(S / thr - 1, 0)``."""
    thr = np.maximum(np.asarray(thr, np.float32), np.float32(1e-12))
    e = sal / thr
    e -= 1
    np.maximum(e, 0, out=e)
    return e


def calibrate_null(
    counts,
    filters: SaliencyFilters,
    *,
    pfa: float,
    surface_pfa: float,
    null: str,
    min_separation: int,
    split: tuple,
    rng: np.random.Generator,
    n_jobs: int,
    tail_sample=None,
) -> NullCalibration:
    """Simulate the background-only saliency and fit the voxel and surface thresholds.

    Parameters
    ----------
    counts : array_like (rows, cols, L, T)
    filters : SaliencyFilters
        Stage 2's set-up (its ``dev`` is stage 1's temporal shape).
    pfa, surface_pfa : float
        False alarms per voxel; false surfaces per background-only pixel.
    null : {"empirical", "gamma"}
    min_separation : int
    split : (float, float, float, float[, float])
        ``(split_ratio, split_z, split_reach, split_slack[, split_pool])``: how runs of
        the map split into candidates (as in the map pass: ``SPLIT_RATIO``, ``SPLIT_Z``,
        ``SPLIT_REACH``, ``SPLIT_TAIL_SLACK``, ``SPLIT_POOL``; :func:`split_rule`;
        without the fifth, no pooled test).
    rng : Generator
        Draws the patches and their Poisson cubes (the first draws of ``detect``'s rng).
    n_jobs : int
        Threads.
    tail_sample : ndarray, optional
        :func:`data_tail`'s sub-grid of ``counts``, already read (``sample``).
    """
    n_target = int(np.clip(1000.0 / pfa, 5e5, 1e7))
    # the patches run one after the other: threads inside each (FFT and fused kernel)
    null_ctx = dataclasses.replace(filters, workers=n_jobs)
    split_ratio, split_z, split_reach, split_slack = split[:4]
    split_pool = bool(split[4]) if len(split) > 4 else False
    # the first return's tail as the data's returns carry it (not only the IRF's): from
    # the data alone, so an in-memory cube's is measured on a thread of its own beside
    # the null's patches (a Dask cube's reads go to its scheduler, one after the other)
    beside = n_jobs > 1 and split_z > 0 and isinstance(counts, np.ndarray)
    with ThreadPoolExecutor(1) if beside else contextlib.nullcontext() as ex:
        job = ex.submit(data_tail, counts, filters.corr.irf, filters.dev) if beside else None
        p_sim, p_lev, p_d, s_real, p_fine = _null_samples(
            counts, null_ctx, n_target, rng, fine=split_z > 0
        )
    if job is not None:
        tail = job.result()
    else:
        args = (counts, filters.corr.irf, filters.dev)
        tail = data_tail(*args, sample=tail_sample) if split_z > 0 else None
    s_sim = np.concatenate([a.ravel() for a in p_sim])
    lev_sim = np.concatenate([a.ravel() for a in p_lev])
    # the paper's gamma fit on the data (eq:gamma_distrib, robust fit), on a second
    # thread beside the empirical table when allowed (numpy's selections release the GIL)
    with ThreadPoolExecutor(1) if n_jobs > 1 else contextlib.nullcontext() as ex:
        fit = ex.submit(fit_gamma_quantiles, s_real) if ex is not None else None
        thr_emp_global = float(np.quantile(s_sim, 1.0 - pfa))
        xs, ys = threshold_table(s_sim, lev_sim, pfa, workers=n_jobs)
        a_fit, sc_fit = fit.result() if fit is not None else fit_gamma_quantiles(s_real)
    thr_gamma = float(stats.gamma.isf(pfa, a_fit, scale=sc_fit))
    if null == "gamma":
        method = "gamma-quantile"
    elif xs.size == 1:
        method = "empirical"
    else:
        method = "empirical-by-level"
    provisional = NullCalibration(
        NullModel(shape=0.0, scale=0.0, method=method, pfa=pfa), xs, ys, thr_gamma, 0.0
    )
    # surface-level calibration: evidence of the candidates found in the null patches
    ev_null = []
    rule = split_rule(filters.corr.irf, split_z, tail, split_reach, split_slack, split_pool)
    # (split as the map pass splits: at d's deep dips, then at the own pixel's)
    for a, lv, dd, (f, n, mu) in zip(p_sim, p_lev, p_d, p_fine, strict=True):
        thr = provisional.threshold_at(lv)
        fine = (_NO_C, _NO_Y, 0, 0, _NO_SP, _NO_DEV, f, n, mu)
        ev_null.append(
            find_segments(
                (a > thr) & (dd > 0), dd, a, evidence(a, thr), min_separation, split_ratio,
                fine, rule,
            )[6]
        )  # fmt: skip
    ev_null = np.sort(np.concatenate(ev_null))[::-1]
    n_null_px = sum(a.shape[0] * a.shape[1] for a in p_sim)
    n_allowed = int(np.floor(surface_pfa * n_null_px))
    ev_thr = float(ev_null[n_allowed]) if n_allowed < ev_null.size else 0.0
    del p_sim, p_lev, p_d, p_fine
    model = NullModel(
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
    return NullCalibration(model, xs, ys, thr_gamma, ev_thr, rule)
