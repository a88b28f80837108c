"""The IRF's width against the data's own: the photon-pair (pair-lag) width and the
check of a supplied IRF.

Two consumers, neither above the other: :mod:`splidar.io` measures the data's pulse
width when no IRF is given (:func:`pair_lag_fwhm`, behind
:func:`splidar.io.estimate_irf_fwhm`) and checks a supplied IRF on :func:`splidar.io.load`
(:func:`check_irf_width`); ``detect`` checks a Cube built from arrays once
(:func:`check_cube_irf`). Both import this module, which imports neither (the detection
stage no longer reaches into the file-reading module).

The once-per-Cube memo (:func:`mark_checked`, :func:`check_cube_irf`) is kept here, keyed
by the Cube's ``id`` with a weak reference whose callback drops the entry when the Cube
is collected: the user's frozen Cube is not written to (no hidden attribute), not hashed
(a frozen dataclass hashes its fields: the count arrays) and not kept alive.
"""

from __future__ import annotations

import logging
import math
import weakref
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from ._validation import SplidarError, check_int
from .irf import irf_fwhm

if TYPE_CHECKING:  # annotations only
    from .cube import Cube

__all__ = [
    "TILT_CHECK",
    "TILT_LOAD",
    "TILT_RESCUE",
    "WIDTH_Z",
    "check_cube_irf",
    "check_irf_width",
    "is_checked",
    "mark_checked",
    "pair_lag_fwhm",
]

#: the logger of :mod:`splidar.io` (whose checks these were; as ``_irf_text``,
#: ``_photon_table``): a user's ``splidar.io`` logging settings keep covering them
log = logging.getLogger("splidar.io")

# --------------------------------------------------------------------------------------
# the photon-pair (pair-lag) width
# --------------------------------------------------------------------------------------
_PAIR_BUDGET = 50_000_000  # pairs of non-empty voxels per pass of the pair-lag width


def pair_lag_fwhm(
    pix,
    b,
    w,
    n_bins: int,
    max_lag: int | None,
    bounds=None,
    budget: int | None = None,
    var_scale: float = 1.0,
    tilt: bool | None = None,
) -> float:
    """:func:`estimate_irf_fwhm` on sparse voxels (pixel, bin, count).

    The voxels of one pixel may repeat a bin (one per wavelength): pairs across them
    are lag-0 pairs too. Above ``_PAIR_BUDGET`` pairs, every k-th pixel is used
    (deterministic; the peak and the floor scale alike; ``budget`` lowers that bound,
    the width check's; ``var_scale`` multiplies the lags' variance the bracket reads).
    ``bounds``: a list given gets
    the FWHMs of the half-maximum crossing's ``WIDTH_Z``-sigma bracket (lower, upper;
    :func:`_half_max_bounds`). ``tilt``: remove the signal-background pairs' tilt
    (:func:`_cross_tilt`; the width check's; None: ``TILT_LOAD``, off).
    """
    tilt = TILT_LOAD[0] if tilt is None else tilt
    budget = _PAIR_BUDGET if budget is None else budget
    stride = 2 * n_bins + 1
    key = np.asarray(pix, dtype=np.int64) * stride + np.asarray(b, dtype=np.int64)
    order = np.argsort(key, kind="stable")
    key = key[order]
    w = np.asarray(w, dtype=np.float64)[order]
    top = max(n_bins // 2, 2)
    lag = min(32 if max_lag is None else check_int(max_lag, "max_lag", minimum=2), top)
    searched = False
    while True:
        # partners j > i with key_j - key_i <= lag share the pixel (pixel stride 2T + 1)
        cnt = _partners(key, lag)
        total = int(cnt.sum())
        if total > budget:
            k = math.ceil(total / budget)
            keep = (key // stride) % k == 0
            log.info(
                "IRF width: %s voxel pairs at lags <= %d; using every %d-th pixel",
                f"{total:,}",
                lag,
                k,
            )
            if keep.all():  # one pixel holds them all: no subset to take (terminates)
                budget = total
                continue
            key, w = key[keep], w[keep]
            continue
        h = _pair_histogram(key, w, cnt, lag)
        # two-sided autocorrelation: ordered pairs, so lag 0 counts each pair twice;
        # pairs inside one voxel, plus those across voxels sharing a bin (wavelengths)
        h[0] = float(np.sum(w * (w - 1))) + 2 * h[0]
        # a flat background gives pairs in proportion to the T - k bin pairs at lag k:
        # undo that triangle so the floor is flat
        tri = n_bins / (n_bins - np.arange(lag + 1))
        h *= tri
        # Poisson variance of each lag's pair count, times the triangle factor; lag 0
        # counts every pair twice (ordered)
        var = np.maximum(h, 1.0) * tri * var_scale
        var[0] *= 2.0
        # ... but a return's pairs with its own pixel's background are flat in k: the
        # triangle tilts them up towards the floor's lags (heavy background, short T)
        if tilt:
            h -= _cross_tilt(h, n_bins)
        # 5 sd as always; 7 once a window without a peak was passed (more tests made)
        k_half = _half_max_lag(h, 7.0 if searched else 5.0)
        if k_half is not None and bounds is not None:
            bounds[:] = _half_max_bounds(h, var, k_half)
        if k_half is None:  # no peak at one-lag resolution: pool lags (a broad pulse)
            k_half = _pooled_half_max_lag(h, var, bounds)
            if k_half is None:
                if max_lag is not None or lag >= top:
                    raise SplidarError(
                        "no IRF peak stands out of the background in the photon-pair time "
                        "differences (too little signal per pixel); pass irf= (array or "
                        "file) or irf_fwhm= (Gaussian FWHM in bins)."
                    )
                log.info("IRF width: no pair peak at lags <= %d; widening the window", lag)
                searched = True
                lag = min(lag * 2, top)
                continue
        if max_lag is not None or k_half < lag / 4 or lag >= top:
            break
        lag = min(lag * 2, top)
    # FWHM of the autocorrelation = 2 k_half = sqrt(2) x FWHM of a Gaussian IRF
    if bounds is not None:
        bounds[:] = [max(2.0 * x / math.sqrt(2.0), 0.5) for x in bounds]
    return max(2.0 * k_half / math.sqrt(2.0), 0.5)


#: sigmas of the half-maximum crossing's bracket (the width's uncertainty, irf24)
WIDTH_Z = 3.0


#: the signal-background pairs' tilt is removed where its fitted size stands this many
#: standard errors above 0 (the significance the IRF estimate uses elsewhere; rob30)
_TILT_Z = 3.0
#: the tilt's removal in ``load``'s width and ``estimate_irf_fwhm`` (False: measured,
#: not adopted: it mends the width at heavy background but moves load's IRF on tailed
#: pulses at PPP 1-4, SBR 0.2, where a narrower IRF scores better; benchmarks/README.md
#: rob30, ``bench_pair_tilt.py``). The width check removes it (``_data_pair_width``).
TILT_LOAD = [False]
#: the same in the width check (benchmarks: [False] restores the width check before rob30)
TILT_CHECK = [True]
#: load's width retried with the removal where it found no return (``_pooled_fwhm_or_
#: untilted``; benchmarks: [False] restores load before rob30)
TILT_RESCUE = [True]


def _cross_tilt(h: np.ndarray, n_bins: int) -> np.ndarray | float:
    """The tilt the triangle correction gives the pairs of returns with their own
    pixel's background, per lag of the triangle-corrected pair histogram ``h``; 0 where
    it does not stand ``_TILT_Z`` standard errors above 0.

    A pixel of ``S`` signal photons over ``b`` background photons a bin holds ``2 S b``
    such pairs at every lag shorter than its return's distance to the record's ends (a
    background photon after the return, one before), not ``(T - k)``-proportional as the
    background's own pairs: times ``T / (T - k)`` they become ``2 S b (1 + u)``, ``u =
    k / (T - k)``, which raises the floor read at the outer lags above the level under
    the peak and moves the half-maximum in (a 3-bin pulse at SBR 0.01, 50 counts a bin,
    T 200, read 1.4-1.7 bins; benchmarks/README.md rob30). Its size ``C = sum 2 S b``
    is the slope in ``u`` of a least-squares line through the outer half of the lags
    (the peak's own tail there only lowers it: its standard error from the residuals),
    and ``C u`` is removed. A per-pixel ``S b`` from the counts was measured and
    dropped: at SBR 0.01 ``S`` is 1 % of a pixel's photons, and a 1 % bias of ``b``
    doubles it."""
    lag = h.size - 1
    if lag < 8:
        return 0.0
    k = np.arange(lag // 2, lag + 1)
    u = k / (n_bins - k)
    x = u - u.mean()
    sxx = float(np.sum(x * x))
    if sxx <= 0:
        return 0.0
    c = float(np.sum(x * (h[k] - h[k].mean()))) / sxx
    resid = h[k] - h[k].mean() - c * x
    se = math.sqrt(float(np.sum(resid * resid)) / (k.size - 2) / sxx)
    if c <= _TILT_Z * se:
        return 0.0
    j = np.arange(lag + 1)
    return c * j / (n_bins - j)


def _half_max_bounds(h: np.ndarray, var: np.ndarray, k_half: float) -> tuple[float, float]:
    """The ``WIDTH_Z``-sigma bracket (lags) of the half-maximum crossing ``k_half`` of
    ``h`` (floor as in :func:`_half_max_lag`; ``var``: each lag's variance): the last
    lag before it that stands significantly above half the peak (0 when none), and the
    first one after it significantly below (the window's end when none); the half
    level's own noise (the peak's and the floor's) is counted."""
    lag = h.size - 1
    floor, n_f = _pair_floor(h)
    half = (float(h[0]) - floor) / 2
    # the half level's variance: a quarter of the peak's (lag 0 and the floor's median)
    v_half = (var[0] + (math.pi / 2) * float(np.mean(var[lag - n_f + 1 :])) / n_f) / 4
    s = np.sqrt(var + v_half)
    s[0] = math.sqrt(var[0]) / 2  # lag 0 against half itself: h0 - half = peak / 2
    e = h - floor
    lags = np.arange(h.size)
    above = np.flatnonzero((e > half + WIDTH_Z * s) & (lags < k_half))
    below = np.flatnonzero((e < half - WIDTH_Z * s) & (lags > k_half))
    return (
        float(above[-1]) if above.size else 0.0,
        float(below[0]) if below.size else float(lag),
    )


def _pair_floor(h: np.ndarray) -> tuple[float, int]:
    """The pair-lag histogram's floor (the median of its last quarter of lags, the
    uncorrelated pairs' level) and the number of lags it reads."""
    n_f = max((h.size - 1) // 4, 1)
    return float(np.median(h[h.size - n_f :])), n_f


def _half_max_lag(h: np.ndarray, z: float = 5.0) -> float | None:
    """Half-maximum lag of the pair peak above the floor; None when no peak stands out
    (``z`` floor standard deviations)."""
    lag = h.size - 1
    if h.sum() < 20:
        raise SplidarError(
            f"only {int(h.sum())} photon pairs within a pixel: too few to estimate the IRF; "
            "pass irf= (array or file) or irf_fwhm= (Gaussian FWHM in bins)."
        )
    floor, _ = _pair_floor(h)
    peak = float(h[0]) - floor
    if peak <= z * math.sqrt(max(floor, 1.0)):
        return None
    above = h - floor - peak / 2
    below = np.flatnonzero(above <= 0)
    if below.size == 0:
        return float(lag)
    k = int(below[0])
    # linear interpolation between lag k-1 (above half) and k (at or below)
    return (k - 1) + above[k - 1] / (above[k - 1] - above[k])


def _pooled_half_max_lag(h: np.ndarray, var=None, bounds=None) -> float | None:
    """:func:`_half_max_lag` on sums of ``r`` adjacent lags (r = 3, 5, 9, ...).

    A broad or tailed pulse spreads its pair excess over many lags, each within the
    floor's noise; summed over ``r`` lags it stands ``sqrt(r)`` times higher. The
    autocorrelation is even, so the sums are centred on lags ``0, r, 2r, ...``. The
    peak must stand 7 standard deviations out (5 on single lags): the triangle
    correction (up to x2 at lag T / 2) inflates the floor's variance, and several ``r``
    and windows are tried.
    """
    lag = h.size - 1
    cs = np.concatenate([[0.0], np.cumsum(np.concatenate([h[:0:-1], h]))])  # lags -lag..lag
    v = np.ones_like(h) if var is None else var
    cv = np.concatenate([[0.0], np.cumsum(np.concatenate([v[:0:-1], v]))])
    r = 3
    while lag // r >= 8:
        half = (r - 1) // 2
        m = (lag - half) // r  # coarse bins whose lags all lie within the window
        centre = lag + r * np.arange(m + 1)
        c = cs[centre + half + 1] - cs[centre - half]
        k = _half_max_lag(c, 7.0)
        if k is not None:
            log.info("IRF width: pair peak measured on sums of %d lags", r)
            if bounds is not None:
                cvar = cv[centre + half + 1] - cv[centre - half]
                # the centre sum holds lags -half..half: each +-j pair is one value
                cvar[0] = v[0] + 4.0 * float(np.sum(v[1 : half + 1]))
                bounds[:] = [x * r for x in _half_max_bounds(c, cvar, k)]
            return k * r
        r = 2 * r - 1
    return None


# --------------------------------------------------------------------------------------
# a supplied IRF's width against the data's own (irfw29)
# --------------------------------------------------------------------------------------
#: factor by which a supplied IRF's photon-pair width may differ from the data's before
#: ``load`` warns. With the true IRF the ratio (IRF / data, where the check decides) lies
#: within 0.71-1.35 over 156 cubes of Gaussian 1-10, exp-tail 3/6 and 2/25 and the
#: measured pulse at PPP 1-50, SBR 0.2-1, and 0.74-1.62 on bench_robustness's sensors
#: (benchmarks/README.md, irfw29; irf24 found 0.63-1.49 for load's pooled estimate): 2
#: leaves a margin above that spread; an IRF recorded at another bin width is off by the
#: ratio of the steps (2, 2.5, 4, 8, 10, ...).
_IRF_WIDTH_FACTOR = 2.0
#: voxels the width check reads at most: evenly spaced whole rows of pixels (a few
#: rows of a large cube; the pair-lag width is a per-pixel statistic)
_CHECK_VOXELS = 1 << 24


@njit(cache=True, nogil=True)
def _partners(key, lag):  # pragma: no cover - numba
    """Per voxel ``i`` of the sorted ``key``, how many ``j > i`` have ``key_j - key_i <=
    lag``: ``searchsorted(key, key + lag, side="right") - i - 1``, by one merge."""
    n = key.size
    cnt = np.empty(n, np.int64)
    hi = 0
    for i in range(n):
        lim = key[i] + lag
        if hi < i + 1:
            hi = i + 1
        while hi < n and key[hi] <= lim:
            hi += 1
        cnt[i] = hi - i - 1
    return cnt


@njit(cache=True, nogil=True)
def _pair_histogram(key, w, cnt, lag):  # pragma: no cover - numba
    """``h[d] = sum w_i w_j`` over the pairs ``j > i`` of :func:`_partners` at ``key_j -
    key_i = d``, float64: ``np.bincount`` of the pairs listed ``i`` by ``i``, ``j`` by
    ``j``, the same additions in the same order (the same values) without the pair
    arrays."""
    h = np.zeros(lag + 1, np.float64)
    for i in range(key.size):
        wi = w[i]
        for j in range(i + 1, i + 1 + cnt[i]):
            h[key[j] - key[i]] += wi * w[j]
    return h


@njit(cache=True, nogil=True)
def _nonzero_rows(y, rows, pix, b, w):  # pragma: no cover - numba
    """The nonzero voxels of the rows ``rows`` of ``y`` (R, C, L, T): pixel (among the
    rows' pixels), bin and count, pixel by pixel, bin by bin, wavelength by wavelength
    (the order of a stable sort by pixel and bin); ``pix``, ``b``, ``w`` hold one spare
    entry (written branch-free)."""
    _, C, L, T = y.shape
    k = 0
    for ri in range(rows.size):
        r = rows[ri]
        for c in range(C):
            p = ri * C + c
            for t in range(T):
                for l in range(L):
                    v = y[r, c, l, t]
                    pix[k] = p
                    b[k] = t
                    w[k] = v
                    k += v != 0


@njit(cache=True, nogil=True)
def _count_nonzero_rows(y, rows):  # pragma: no cover - numba
    _, C, L, T = y.shape
    n = 0
    for ri in range(rows.size):
        src = y[rows[ri]]
        for c in range(C):
            for l in range(L):
                for t in range(T):
                    n += src[c, l, t] != 0
    return n


def _sampled_voxels(counts, rows: np.ndarray) -> tuple | None:
    """``(pix, b, w)``: the nonzero voxels of the rows ``rows`` of an in-memory cube of
    integer counts (rows, cols, L, T) (pixel index among the rows' pixels, bin, count),
    read in place (no copy of the rows) by two numba passes (count, fill), in the order
    of ``pair_lag_fwhm``'s stable sort by pixel and bin: the arrays of ``np.nonzero`` of
    ``counts[rows].reshape(-1, T)`` in another order, the integer totals per pixel and
    the sorted pairs the same. None for other arrays."""
    y = np.asarray(counts) if isinstance(counts, np.ndarray) else counts  # memory maps too
    ok = isinstance(y, np.ndarray) and y.ndim == 4 and y.flags.c_contiguous
    if not ok or y.dtype.kind not in "ui":
        return None
    rows = np.ascontiguousarray(rows, np.int64)
    n = int(_count_nonzero_rows(y, rows))
    pix, b, w = np.empty(n + 1, np.int64), np.empty(n + 1, np.int64), np.empty(n + 1, y.dtype)
    _nonzero_rows(y, rows, pix, b, w)
    return pix[:n], b[:n], w[:n]


#: the width check decides only where the data's width is known to better than the
#: factor it tests: its 3-sigma bracket's half-length below this fraction of the width
#: (the bracket within 0.5-1.5 x the width; irf24's "determined" is 1, which let an
#: exp tail 2/25 at PPP 4 SBR 0.2 read 9.5 bins in [1.4, 19.8] for a 28-bin pulse)
_CHECK_PRECISION = 0.5
#: voxel pairs the width check's pair-lag histogram counts at most per lag window
#: (every k-th pixel above it, as estimate_irf_fwhm's 50M; about 0.1 s)
_CHECK_PAIRS = 2_000_000
#: pixels holding more than this many times the median pixel's photons are left out of
#: the width check's pairs (stuck pixels; the pairs of a pixel grow as its count squared)
_HOT = 10.0


def _irf_pair_width(irf) -> float | None:
    """The photon-pair width (FWHM, bins) of an IRF ``(L, n)`` itself: the statistic of
    :func:`estimate_irf_fwhm` on the noise-free autocorrelation of the rows' sum (each
    row normalised to its sum), its own floor flattened and removed as there (median of
    the outer quarter of a lag window grown from 32 until the half-maximum lies below a
    quarter of it). For a Gaussian this is its FWHM; for any other shape it is the width
    the data's estimate measures for that pulse, so the two compare without the shape's
    own bias (a tailed pulse's pair width is not its FWHM). None for an IRF of no mass."""
    from scipy.signal import fftconvolve

    a = np.asarray(irf, dtype=np.float64)
    a = a.reshape(-1, a.shape[-1])
    s = a.sum(axis=1)
    if not np.any(s > 0):
        return None
    a = a[s > 0] / s[s > 0, None]
    peaks = np.argmax(a, axis=1)  # each row's depth reference is its peak: aligned there
    g = np.zeros(a.shape[1] + int(peaks.max() - peaks.min()))
    for row, p in zip(a, peaks, strict=True):
        g[peaks.max() - p : peaks.max() - p + row.size] += row
    n = g.size
    if n < 3:
        return 0.5
    h = fftconvolve(g, g[::-1])[n - 1 :] * (n / (n - np.arange(n)))  # lags 0..n-1
    top = max(n // 2, 2)
    lag = min(32, top)
    while True:
        hh = h[: lag + 1]
        floor, _ = _pair_floor(hh)
        if floor >= hh[0]:  # an IRF filling its window: no baseline of its own to remove
            floor = 0.0
        peak = float(hh[0]) - floor
        if peak <= 0:
            return None
        above = hh - floor - peak / 2
        below = np.flatnonzero(above <= 0)
        if below.size:
            k = int(below[0])
            k_half = (k - 1) + above[k - 1] / (above[k - 1] - above[k])
        else:
            k_half = float(lag)
        if k_half < lag / 4 or lag >= top:
            return max(2.0 * k_half / math.sqrt(2.0), 0.5)
        lag = min(2 * lag, top)


def _sample_rows(n_rows: int, per_row: int) -> np.ndarray:
    """Evenly spaced rows holding at most ``_CHECK_VOXELS`` voxels (at least one)."""
    m = min(n_rows, max(_CHECK_VOXELS // max(per_row, 1), 1))
    return np.unique(np.linspace(0, n_rows - 1, m).round().astype(np.int64))


def _data_pair_width(counts, n_bins: int, sparse=None):
    """The data's photon-pair width on single pixels of a bounded sample (evenly spaced
    rows, ``_CHECK_VOXELS`` voxels at most; photon lists the same rows): (FWHM, its
    ``WIDTH_Z``-sigma bracket, pixels read), or None where it is not determined (no
    pair peak, or a bracket's half-length over ``_CHECK_PRECISION`` of the width: weak
    data). Never raises on valid data."""
    n_rows, n_cols = int(counts.shape[0]), int(counts.shape[1])
    n_l = int(counts.shape[2]) if counts.ndim == 4 else 1
    if n_bins < 8:  # no lag window with an outer quarter to read the floor from
        return None
    rows = _sample_rows(n_rows, n_cols * n_l * n_bins)
    if sparse is not None:
        uniq, w = sparse
        pix = (np.asarray(uniq) // n_bins) // n_l
        keep = np.isin(pix // n_cols, rows)
        pix, b, w = pix[keep], np.asarray(uniq)[keep] % n_bins, np.asarray(w)[keep]
    else:
        if hasattr(counts, "compute") and not isinstance(counts, np.ndarray):
            mid = (n_rows - rows.size) // 2  # lazy data: one band of rows (few chunks)
            sub = np.asarray(counts[mid : mid + rows.size].compute())
        else:
            sub = None
        got = _sampled_voxels(counts, rows) if sub is None else None
        if got is not None:  # an in-memory cube: read in place, the same arrays
            pix, b, w = got
        else:
            sub = np.asarray(counts[rows] if rows.size < n_rows else counts) if sub is None else sub
            flat = sub.reshape(-1, n_bins)
            rowi, b = np.nonzero(flat)
            w = flat[rowi, b]
            pix = rowi // n_l
    # hot (stuck) pixels: counts in every bin, pairs growing as their square, would
    # swamp the others' peak with their floor's noise; a pixel's width does not depend
    # on its brightness, so those above _HOT x the median pixel are left out
    tot = np.bincount(pix, weights=w)
    hot = tot > _HOT * np.median(tot[tot > 0]) if np.any(tot > 0) else tot > 0
    if np.any(hot):
        keep = ~hot[pix]
        pix, b, w = pix[keep], b[keep], w[keep]
    # a pair count a b of Poisson voxels (means m, n) has variance m n (1 + m + n), not
    # its mean m n: the Poisson variance of the pair histogram holds where a voxel
    # holds well under a photon; with more (heavy background) the bracket is widened
    # by 1 + 2 x the pair-weighted photons per voxel (50 a bin gave a 1.5-bin "width"
    # for a 3-bin pulse with a bracket 10 x too narrow)
    tot = np.bincount(pix, weights=w)
    per_voxel = float(np.sum(tot**3) / max(np.sum(tot**2), 1.0)) / n_bins
    bounds: list = []
    try:
        fwhm = pair_lag_fwhm(
            pix, b, w, n_bins, None, bounds, budget=_CHECK_PAIRS,
            var_scale=1.0 + 2.0 * per_voxel, tilt=TILT_CHECK[0],
        )  # fmt: skip
    except SplidarError:
        return None
    if not bounds or (bounds[1] - bounds[0]) / 2 > _CHECK_PRECISION * fwhm:
        return None
    return fwhm, (float(bounds[0]), float(bounds[1])), rows.size * n_cols


def check_irf_width(
    irf_a, src: str, counts, n_bins: int, bin_width_ps, sparse=None, fix: str = "load"
):
    """Warn (once, from :func:`load`, or from ``detect`` for a Cube built from arrays:
    :func:`check_cube_irf`) when a supplied IRF's width and the data's own pulse width
    (:func:`estimate_irf_fwhm`'s photon-pair statistic on both, single pixels of a
    bounded sample) differ by more than ``_IRF_WIDTH_FACTOR`` and the IRF's lies outside
    the data's ``WIDTH_Z``-sigma bracket: the usual cause is an IRF recorded at another
    bin width than the cube's, read one sample per bin. Nothing is changed (the fix,
    named by ``fix``: ``"load"``'s ``irf_bin_width_ps=``, ``"cube"``'s
    :func:`splidar.irf.resample_irf`); undetermined widths (weak data) skip the check
    (INFO). Returns the ratio (IRF / data) or None when not determined."""
    mine = _irf_pair_width(irf_a)
    got = _data_pair_width(counts, n_bins, sparse) if mine is not None else None
    if got is None:
        log.info("IRF width check: the data's pulse width is not determined; not checked")
        return None
    w, (lo, hi), n_pix = got
    ratio = mine / w
    log.info(
        "IRF width check: the IRF's photon-pair width %.2f bins, the data's %.2f (%.2f-%.2f "
        "at %g sigma, %d pixels): ratio %.2f",
        mine, w, lo, hi, WIDTH_Z, n_pix, ratio,
    )  # fmt: skip
    if max(ratio, 1 / ratio) <= _IRF_WIDTH_FACTOR or lo <= mine <= hi:
        return ratio
    try:
        fw = f"FWHM {float(np.max(irf_fwhm(irf_a))):.2f} bins, "
    except SplidarError:
        fw = ""
    if src.startswith("gaussian"):
        cause = "irf_fwhm= is the FWHM in bins of the cube, not in picoseconds"
    elif fix == "cube":
        cause = _cube_cause(ratio, w, lo, hi, mine, bin_width_ps)
    elif bin_width_ps:
        step, s_lo, s_hi = (bin_width_ps * x / mine for x in (w, lo, hi))
        cause = (
            f"an IRF recorded at another bin width is read one sample per bin: if it was "
            f"sampled every {step:.3g} ps ({s_lo:.3g}-{s_hi:.3g} ps would match; the cube's "
            f"bins are {bin_width_ps:g} ps), pass irf_bin_width_ps={step:.3g} (its sample "
            "step) to resample it"
        )
    else:
        cause = (
            f"an IRF recorded at another bin width is read one sample per bin (it would "
            f"match sampled {ratio:.3g} times {'finer' if ratio > 1 else 'coarser'} than "
            "the cube's bins): pass bin_width_ps= and irf_bin_width_ps= (its sample step) "
            "to resample it"
        )
    log.warning(
        "the IRF (%s) is %.1f times %s than the pulse in the data: %sa photon-pair width "
        "of %.2f bins against %.2f bins from the data's photon-pair time differences "
        "(%.2f-%.2f at %g sigma). Likely cause: %s; or %s to take the pulse from the "
        "data. The IRF is used as given.",
        src, max(ratio, 1 / ratio), "wider" if ratio > 1 else "narrower", fw, mine, w,
        lo, hi, WIDTH_Z, cause,
        "estimate it (splidar.io.estimate_irf(counts))" if fix == "cube"
        else "pass irf='estimate-shape'",
    )  # fmt: skip
    return ratio


def _cube_cause(ratio: float, w: float, lo: float, hi: float, mine: float, bin_width_ps):
    """The likely cause and its fix for a Cube built from arrays (no ``load`` option to
    name): resample the IRF onto the bins with :func:`splidar.irf.resample_irf`."""
    if bin_width_ps:
        step, s_lo, s_hi = (bin_width_ps * x / mine for x in (w, lo, hi))
        return (
            f"an IRF recorded at another bin width is read one sample per bin by Cube: if "
            f"it was sampled every {step:.3g} ps ({s_lo:.3g}-{s_hi:.3g} ps would match; "
            f"the cube's bins are {bin_width_ps:g} ps), build the Cube with "
            f"irf=splidar.irf.resample_irf(irf, {step:.3g}, {bin_width_ps:g}) (its sample "
            "step, the bin width)"
        )
    return (
        f"an IRF recorded at another bin width is read one sample per bin by Cube (it "
        f"would match sampled {ratio:.3g} times {'finer' if ratio > 1 else 'coarser'} "
        "than the cube's bins): build the Cube with irf=splidar.irf.resample_irf(irf, "
        "step_ps, bin_width_ps) (its sample step, the bin width)"
    )


#: the Cubes whose IRF width needs no check (``load`` checked it, or it was estimated
#: from the data or saved with them) or was checked: ``id(cube)`` -> a weak reference to
#: it, whose callback drops the entry when the Cube is collected. Not an attribute of the
#: Cube (it is the user's frozen object), not keyed by the Cube itself (a frozen
#: dataclass hashes its fields, the count arrays); ``dataclasses.replace`` gives a new
#: Cube, checked anew.
_CHECKED: dict[int, weakref.ref] = {}


def _drop(key: int):
    """The weak reference's callback: forget ``key`` when its Cube is collected (only
    the entry of that reference: a later Cube may reuse the id)."""

    def drop(ref: weakref.ref) -> None:
        if _CHECKED.get(key) is ref:
            del _CHECKED[key]

    return drop


def is_checked(cube) -> bool:
    """Whether ``cube`` (this object, not an equal one) is in the memo."""
    ref = _CHECKED.get(id(cube))
    return ref is not None and ref() is cube


def mark_checked(cube):
    """``cube``, remembered as having had its IRF's width checked (``load`` did, or it
    was estimated from the data or saved with it): ``detect`` does not check it again.
    The Cube itself is not changed; an object that takes no weak reference is not
    remembered (checked each time)."""
    if not is_checked(cube):
        key = id(cube)
        try:
            _CHECKED[key] = weakref.ref(cube, _drop(key))
        except TypeError:
            pass
    return cube


def check_cube_irf(cube: Cube) -> float | None:
    """:func:`check_irf_width` for ``detect``: a Cube built from arrays
    (``Cube(counts, irf=...)``, the path simulation groups take) is checked once, the
    first time it is detected on (a Cube from :func:`load` was checked there). Warns
    only; never raises on valid data; the result of ``detect`` does not depend on it.
    Returns the ratio (IRF / data) or None (not determined, or checked before)."""
    if is_checked(cube):
        return None
    mark_checked(cube)
    try:
        return check_irf_width(
            cube.irf, "the Cube's IRF", cube.counts, cube.n_bins, cube.bin_width_ps,
            fix="cube",
        )  # fmt: skip
    except (SplidarError, ValueError, MemoryError) as exc:  # a check, never an obstacle
        log.info("IRF width check: not checked (%s)", exc)
        return None
