"""Background estimation (``eq:background_1..3``), kept factored.

Both factors live on the IRF-correlated scale of the saliency: the matched filter has
unit sum, so a smooth background keeps its level, and the saliency subtracts the
estimate from the correlated cube.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage, signal, special

from ._fast import low_median as _low_median_kernel
from ._fast import pixel_totals, window_means
from ._filters import Correlator
from ._threads import on_parts

logger = logging.getLogger(__name__)

__all__ = [
    "FirstRead",
    "first_read",
    "grid_window_means",
    "low_quantile_bias",
    "robust_level",
    "sample_grid",
    "temporal_shape",
]

#: Fraction of pixels whose median gives the temporal shape (``eq:background_1``).
LOW_FRACTION = 0.10
#: Half-width of the symmetric clipping window, in Poisson sigmas of the coarse cube.
#: Symmetric, so the clipped mean of background-only values is unbiased; returns
#: leaking in from neighbours (weak, positive) are cut beyond it.
CLIP = 2.5
#: Values of ``dev`` at which :func:`low_quantile_bias` is computed (then interpolated):
#: the bias is a smooth function of ``dev`` on the scale of the coarse values' spread.
_BIAS_GRID = 33


def temporal_shape(
    counts,
    corr: Correlator,
    k: int,
    *,
    smooth: int = 1,
    refine: bool = True,
    n_samples: int = 2000,
    workers: int = 1,
    windows=None,
) -> np.ndarray:
    """``bbar_{l,t}`` (``eq:background_1``): median of the lowest 10 % of the coarsest cube.

    The coarsest cube ``Box_k(Y) (*) g`` is evaluated on a grid of pixels only (about
    ``n_samples`` of them, whole ``k x k`` windows inside the image): the shape is a
    statistic over pixels, and the coarse cube is smooth at the scale of ``k``, so a
    grid loses nothing while reading the counts about once.

    The paper notes the estimate fails when more than 90 % of the pixels have a return
    in the same bin (a wall facing the sensor). Returns are narrow and backgrounds are
    smooth, so the profile then gets a running median over ``smooth`` bins (a window
    at least twice as wide as a return): it removes bumps narrower than half the window
    and keeps monotone shapes (a decay, pile-up) unchanged. With ``refine`` (default)
    the shape is then re-estimated without the low-quantile bias
    (:func:`_debias_profile`).

    ``windows``, when given, reads the grid's window means instead of the loop here:
    ``windows(counts, row_starts, kr, col_starts, kc)`` returns the float32 array
    ``(row_starts.size, col_starts.size, L, T)`` of
    :func:`~splidar.detection._fast.window_means` (a Dask cube computes them tile by
    tile where its data are: :func:`splidar.detection._tiled.tiled_window_means`).

    Returns
    -------
    temporal : ndarray (L, T), float32
    """
    R, C, L, T = counts.shape
    kr, kc, row_starts, col_starts = sample_grid(counts.shape, k, n_samples)
    if windows is None:
        sampled = grid_window_means(counts, row_starts, kr, col_starts, kc, workers)
    else:
        sampled = windows(counts, row_starts, kr, col_starts, kc)
    coarse = corr(sampled, workers=workers).reshape(-1, L, T)
    n = coarse.shape[0]
    m = max(1, int(np.ceil(LOW_FRACTION * n)))
    prof = np.empty(L * T, np.float32)

    def select_part(i0, i1):  # eq:background_1, one selection per (l, t): any split
        cols = slice(i0, i1)  # contiguous parts: no copy
        prof[cols] = _low_median(coarse.reshape(n, L * T), m, cols)

    on_parts(select_part, L * T, workers)
    prof = prof.reshape(L, T).astype(np.float64)
    var_factor = (corr.irf**2).sum(axis=1) / (kr * kc)
    if smooth > 1:
        med = ndimage.median_filter(prof, size=(1, smooth), mode="nearest")
        noise = _end_noise(coarse, row_starts.size, col_starts.size, smooth // 2)
        prof = _end_of_window(prof, med, smooth, var_factor, noise)
    if refine:
        skew_factor = (corr.irf**3).sum(axis=1) / (kr * kc) ** 2

        def one(l):
            quantum = float(corr.irf[l].max()) / (kr * kc)
            return _debias_profile(
                coarse[:, l], prof[l], float(var_factor[l]), float(skew_factor[l]), m, smooth,
                quantum=quantum,
            )  # fmt: skip

        n_thr = max(1, min(int(workers), L))
        if n_thr > 1:
            with ThreadPoolExecutor(n_thr) as ex:
                prof = np.stack(list(ex.map(one, range(L))))
        else:
            prof = np.stack([one(l) for l in range(L)])
    return prof.astype(np.float32)


def grid_window_means(counts, row_starts, kr: int, col_starts, kc: int, workers: int = 1):
    """The grid's window means ``(row_starts.size, col_starts.size, L, T)`` float32 of an
    in-memory cube: exact window sums in one numba pass over each window's rows
    (:func:`~splidar.detection._fast.window_means`), the rows of windows on ``workers``
    threads."""
    R, C, L, T = counts.shape
    sampled = np.empty((row_starts.size, col_starts.size, L, T), np.float32)

    def rows(i0, i1):
        for i in range(i0, i1):
            a = row_starts[i]
            sampled[i] = window_means(np.asarray(counts[a : a + kr]), col_starts, kc)

    on_parts(rows, row_starts.size, workers)
    return sampled


@dataclass(frozen=True)
class FirstRead:
    """The stuck-pixel check's totals and stage 1's window means of an in-memory cube,
    from one read of its counts (:func:`first_read`).

    Attributes
    ----------
    totals : ndarray (rows, cols) float64
        Counts summed over wavelengths and bins (``pixel_totals``, the same values).
    grid : tuple
        ``(kr, kc, row_starts, col_starts)`` of :func:`sample_grid`.
    means : ndarray (row_starts.size, col_starts.size, L, T) float32
        The windows' means (``window_means``, the same values).
    workers : int
        Threads for a grid other than ``grid`` (:meth:`windows` then reads the counts).
    """

    totals: np.ndarray
    grid: tuple
    means: np.ndarray
    workers: int = 1

    def windows(self, counts, row_starts, kr, col_starts, kc) -> np.ndarray:
        """The window means :func:`temporal_shape` asks for: :attr:`means` on this grid,
        else read from ``counts`` (:func:`grid_window_means`)."""
        kr0, kc0, rs0, cs0 = self.grid
        same = (kr, kc) == (kr0, kc0) and np.array_equal(row_starts, rs0)
        if same and np.array_equal(col_starts, cs0):
            return self.means
        return grid_window_means(counts, row_starts, kr, col_starts, kc, self.workers)


@njit(cache=True, nogil=True)
def _band_sums(rows, col_starts, kc, out, totals):
    """Window means of ``kr`` rows ``rows`` (kr, C, L, T) integer counts into ``out``
    (n, L, T) float32, and the rows' pixel totals into ``totals`` (kr, C) float64: exact
    integer sums (int64), so each mean is the float32 rounding of the float64 quotient of
    the exact sum, as :func:`~splidar.detection._fast.window_means` gives it, and each
    total the float64 of the exact sum, as ``pixel_totals``."""
    kr, C, L, T = rows.shape
    norm = np.float64(kr * kc)
    rs = np.empty(T, np.int64)
    cs = np.empty((C + 1, T), np.int64)
    tot = np.zeros((kr, C), np.int64)
    for l in range(L):
        for t in range(T):
            cs[0, t] = 0
        for j in range(C):
            for t in range(T):
                rs[t] = 0
            for a in range(kr):
                src = rows[a, j, l]
                s = np.int64(0)
                for t in range(T):
                    v = np.int64(src[t])
                    rs[t] += v
                    s += v
                tot[a, j] += s
            for t in range(T):
                cs[j + 1, t] = cs[j, t] + rs[t]
        for u in range(col_starts.size):
            b0 = col_starts[u]
            for t in range(T):
                out[u, l, t] = np.float64(cs[b0 + kc, t] - cs[b0, t]) / norm
    for a in range(kr):
        for j in range(C):
            totals[a, j] = np.float64(tot[a, j])


def first_read(counts, k: int, workers: int = 1, n_samples: int = 2000) -> FirstRead | None:
    """The pixel totals of the stuck-pixel check and stage 1's window means (the grid of
    :func:`sample_grid` with box ``k``) from one read of an in-memory cube, its bands of
    rows on ``workers`` threads: each count is read once where the two reads read it
    twice (``pixel_totals``, then :func:`grid_window_means`). The same values, bit for
    bit (exact integer sums). None (read as before) unless ``counts`` is a C-contiguous
    NumPy array of integers of at most 32 bits and the grid's bands of rows do not
    overlap (large images: ``sample_grid`` steps its rows by ``kr``)."""
    if not isinstance(counts, np.ndarray) or counts.ndim != 4 or not counts.flags.c_contiguous:
        return None
    counts = np.asarray(counts)  # a memory map's array (numba takes plain arrays)
    if counts.dtype.kind not in "ui" or counts.dtype.itemsize > 4:
        return None
    R, C, L, T = counts.shape
    kr, kc, row_starts, col_starts = grid = sample_grid(counts.shape, k, n_samples)
    if row_starts.size > 1 and np.diff(row_starts).min() < kr:
        return None
    totals = np.empty((R, C), np.float64)
    means = np.empty((row_starts.size, col_starts.size, L, T), np.float32)
    cols = np.ascontiguousarray(col_starts, np.int64)

    def bands(i0, i1):
        for i in range(i0, i1):
            a = int(row_starts[i])
            _band_sums(counts[a : a + kr], cols, int(kc), means[i], totals[a : a + kr])

    on_parts(bands, row_starts.size, workers)
    covered = np.zeros(R, bool)
    for a in row_starts:
        covered[a : a + kr] = True
    for r in np.flatnonzero(~covered):  # rows outside every band: their totals alone
        totals[r] = pixel_totals(counts[r : r + 1])[0]
    return FirstRead(totals, grid, means, int(workers))


def sample_grid(shape, k: int, n_samples: int = 2000) -> tuple:
    """The grid of ``kr x kc`` windows :func:`temporal_shape` averages.

    Returns ``(kr, kc, row_starts, col_starts)``: window size (``k`` clipped to the
    image) and the first row and column of the windows (about ``n_samples`` of them).
    """
    R, C = shape[:2]
    kr = min(k, R)
    kc = min(k, C)
    n_pos_r = R - kr + 1
    n_pos_c = C - kc + 1
    step_r = kr if n_pos_r * n_pos_c > 4 * n_samples else 1
    row_starts = np.arange(0, n_pos_r, step_r)
    step_c = max(1, int(row_starts.size * n_pos_c // n_samples))
    col_starts = np.arange(0, n_pos_c, step_c)
    return kr, kc, row_starts, col_starts


def _low_median(x: np.ndarray, m: int, cols: slice | None = None) -> np.ndarray:
    """Median over axis 0 of the ``m`` lowest values of ``x`` (float32), of the columns
    ``cols`` (default all) of a 2-d ``x``.

    The same as ``np.median(np.partition(x, m - 1, axis=0)[:m], axis=0)``, bit for bit:
    the middle of the lowest ``m`` are the order statistics ``(m - 1) // 2`` and
    ``m // 2`` of all, found by one selection (a numba kernel for 2-d float32 ``x``,
    :func:`~splidar.detection._fast.low_median`: no copy of the columns, 2 x faster
    than ``np.partition`` over axis 0); their float32 mean as ``np.median`` takes it.
    """
    x = x if cols is None else x[:, cols]
    n = x.shape[0]
    if m >= n:
        return np.median(x, axis=0)
    k1, k2 = (m - 1) // 2, m // 2
    if x.ndim == 2 and x.dtype == np.float32 and x.strides[1] == x.itemsize:
        out = np.empty(x.shape[1], np.float32)
        _low_median_kernel(x, k1, k2, slice(None), out)
        return out
    part = np.partition(x, [k1, k2] if k2 > k1 else k1, axis=0)
    return (part[k1] + part[k2]) / x.dtype.type(2)


def _end_noise(coarse: np.ndarray, n_rows: int, n_cols: int, h: int) -> np.ndarray:
    """Sampling standard deviation of the ``eq:background_1`` profile before the last bins.

    The sampled windows are split into two halves of the grid (top and bottom rows, or
    left and right columns), each gives its own profile (the median of its lowest 10 %)
    over the bins ``[T - 1 - 3h, T - 1 - h]``, and the spread of their difference about
    its median is twice the full profile's (``var(p1 - p2) = 2 var(p_half) = 4
    var(p)``). A measured, not a modelled, noise: it holds for overlapping windows, any
    level and any count statistics. Returns ``(L,)``; ``inf`` when the grid cannot be
    split or the window is too short.
    """
    n, L, T = coarse.shape
    if T < 4 * h + 1 or h < 1 or max(n_rows, n_cols) < 2:
        return np.full(L, np.inf)
    grid = coarse.reshape(n_rows, n_cols, L, T)
    if n_rows >= 2:
        halves = (grid[: n_rows // 2], grid[n_rows // 2 :])
    else:
        halves = (grid[:, : n_cols // 2], grid[:, n_cols // 2 :])
    cols = np.arange(T - 1 - 3 * h, T - h)
    prof = []
    for half in halves:
        x = np.ascontiguousarray(half[..., cols].reshape(-1, L * cols.size))
        m = max(1, int(np.ceil(LOW_FRACTION * x.shape[0])))
        prof.append(_low_median(x, m).reshape(L, cols.size).astype(np.float64))
    d = prof[0] - prof[1]
    dev = d - np.median(d, axis=-1, keepdims=True)
    return 0.5 * np.sqrt(np.mean(dev**2, axis=-1))


def _end_of_window(
    raw: np.ndarray, med: np.ndarray, smooth: int, var_factor: np.ndarray, noise
) -> np.ndarray:
    """The running median's last ``h = smooth // 2`` bins, where a rise is a return cut by
    the window's end rather than a background rising to it.

    With ``mode="nearest"`` the last bins' windows hold copies of bin ``T - 1``: when the
    returns of most pixels lie within about a FWHM of the window's end (more than the
    90 % ``eq:background_1`` tolerates) they stay in the profile, and ``detect`` found 7
    % of them (``benchmarks/bench_foreign_cubes.py --window-end 296 299 --pulse 3 0``). A
    background rising to the end gives the same last bins; what tells them apart is what
    comes before: the matched filter's response to a return spans ``wh`` bins either
    side of it (``irf_halfwidth``, ``smooth = 4 wh + 1``), so a return within ``wh`` of
    the end adds nothing before bin ``T - 1 - h`` (``h = 2 wh``), and a rising background
    rises there too. Counting bins back from the end, with ``A`` and ``B`` the medians of
    the raw profile over ``[h, 2h]`` and ``[2h, 3h]`` (about its values at ``1.5 h`` and
    ``2.5 h``), the end's excess ``E = med_{T-1} - A`` and the rise before it ``F = A -
    B`` of ``c + a exp(-t / s)`` (any floor ``c``) have the ratio ``E / F = (1 -
    e^{-1.5 h / s}) / (e^{-1.5 h / s} - e^{-2.5 h / s})``, which grows as ``s`` shrinks,
    without bound for a return. The end is taken for returns when ``E`` exceeds that
    ratio at ``s = wh`` (about 22) times an upper bound of ``F`` (the measured rise plus
    3 standard deviations of ``A - B``, from the profile's sampling noise ``noise``,
    :func:`_end_noise`), and when ``E`` is more than 3 standard deviations of one
    coarsest-box value at the end's level (``sqrt(med_{T-1} var_factor)``). The last
    ``h`` bins then keep the lower of the running median and the background's linear
    trend from ``A`` and ``B``; otherwise (a rise, noise) the ``nearest`` values stay.

    The window's start is not treated so, although the same test finds its returns
    (``benchmarks/README.md``, "start24"): a background that falls from bin 0 faster than
    over ``wh`` bins (pile-up or a gate's opening over about a FWHM) cannot be told from
    returns there, and the test would take it for one return in every pixel. The start
    keeps ``nearest``: such backgrounds are common at the start of gated sensors' windows.
    """
    T = raw.shape[-1]
    h = smooth // 2
    if h < 2 or T < 4 * h + 1:
        return med
    rev_raw, rev_med = raw[:, ::-1], med[:, ::-1]
    a = np.median(rev_raw[:, h : 2 * h + 1], axis=-1)
    b = np.median(rev_raw[:, 2 * h : 3 * h + 1], axis=-1)
    excess, rise = rev_med[:, 0] - a, a - b
    # E / F of c + a exp(-t / s) at s = wh = h / 2 (about 22): 1.5 h / s = 3, 2.5 h / s = 5
    ratio = -np.expm1(-3.0) / (np.exp(-3.0) - np.exp(-5.0))
    sigma = np.sqrt(np.maximum(rev_med[:, 0], 0.0) * np.asarray(var_factor, np.float64))
    # the rise's upper bound: 3 standard deviations of A - B above the measured rise
    # (A and B each taken as noisy as one bin of the profile: sqrt(2) noise)
    upper = np.maximum(rise, 0.0) + 3.0 * np.sqrt(2.0) * np.asarray(noise, np.float64)
    cut = (a > 0) & (excess > ratio * upper) & (excess > 3.0 * sigma)
    if not cut.any():
        return med
    logger.info(
        "background: the last %d bins' excess (%.3g x the level before them) taken for "
        "returns cut by the window's end, wavelengths %s",
        h, float(np.max(excess[cut] / a[cut])), np.flatnonzero(cut).tolist(),
    )  # fmt: skip
    out = med.copy()
    t = np.arange(h, dtype=np.float64)[::-1]  # bins T - h .. T - 1, counted from the end
    trend = np.maximum(a[:, None] + rise[:, None] * (1.5 * h - t[None, :]) / h, 0.0)
    out[cut, T - h :] = np.minimum(med[cut, T - h :], trend[cut])
    return out


def _debias_profile(x, prof, var_factor, skew_factor, m, smooth, quantum=0.0):
    """Remove the low-quantile bias of ``eq:background_1`` (robust to signal).

    The median of the lowest 10 % sits below the background mean by an amount that
    grows with the level and with the skew of low counts, which distorts a decaying
    shape and then mis-calibrates the threshold along t. The bias of that estimator on
    background-only coarse values, with each sampled pixel at its own level
    (:func:`robust_level`, detrended by the biased shape), is computed by
    :func:`low_quantile_bias` and subtracted. The estimator itself keeps the paper's
    robustness to returns in up to 90 % of the pixels.
    """
    T = x.shape[1]
    dev = (prof - prof.mean()).astype(np.float32)
    # the levels from every s-th bin: the coarse series is smooth over the IRF's width,
    # so this keeps nearly all its information at a quarter of the cost (T >= 1024)
    s = max(1, min(4, T // 256))
    lvl = robust_level(x[:, ::s], dev[::s], var_factor, quantum=quantum).astype(np.float64)
    bias = low_quantile_bias(lvl, dev.astype(np.float64), var_factor, skew_factor, m)
    if smooth > 1:
        bias = ndimage.median_filter(bias, size=smooth, mode="nearest")
    est = prof - bias
    win = min(max(5, smooth | 1), T if T % 2 else T - 1)
    if win >= 5:
        # a local quadratic fit (Savitzky-Golay, polynomial at the window edges) takes
        # the sampling noise of the low quantile off the shape; bumps are gone already
        est = signal.savgol_filter(est, win, 2, mode="interp")
    return est


def low_quantile_bias(
    levels: np.ndarray,
    dev: np.ndarray,
    var_factor: float,
    skew_factor: float,
    m: int,
    *,
    n_grid: int = _BIAS_GRID,
) -> np.ndarray:
    """Expected error of the median of the lowest ``m`` of ``n`` background coarse values.

    A coarse value of pixel ``i`` at bin ``t`` is a weighted sum of Poisson counts
    (``Box_k(Y) (*) g``) with mean ``mu_{i,t} = max(levels_i + dev_t, 0)``, variance
    ``mu var_factor`` and third cumulant ``mu skew_factor``. It is modelled by the
    gamma distribution with those three cumulants (Pearson type III: shifted,
    ``theta = skew_factor / (2 var_factor)``, shape ``mu var_factor / theta^2``), a
    continuous law like the coarse values themselves. The median of the lowest ``m``
    is the order statistic of rank ``r = (m + 1) / 2`` (the mean of two ranks for even
    ``m``); its expectation is the mixture's quantile at Blom's position
    ``(r - 0.375) / (n + 0.25)`` (the order statistic's spread is ``O(n^-1/2)`` and its
    skew ``O(1/n)``: n is in the thousands here), clipped at 0 like the data.

    The bias depends on t only through ``dev_t``: it is computed on ``n_grid`` values
    of ``dev`` and interpolated. The pixels enter as level groups (equal counts, finer
    in the lowest quarter of the levels where the low quantile sits). Checked against
    large simulations of the coarse cube (``tests/test_detection_stages.py``): the rms
    error is 0.5, 5, 1.4 and 0.4 % of the coarse values' standard deviation at 1.5, 3,
    7 and 74 photons' worth of variance per value (``mu / var_factor``), where the
    simulation of 600 pixels x 4 draws it replaces (a scaled Poisson, on a lattice the
    coarse values do not have) erred by 1.4, 9, 8 and 11 %. It costs no random draws.

    Parameters
    ----------
    levels : ndarray (n,)
        Level of each sampled pixel (``b_{n,l}`` on the coarse scale).
    dev : ndarray (T,)
        ``bbar_t - mean_t bbar``.
    var_factor, skew_factor : float
        Variance and third cumulant of one coarse value per unit mean:
        ``sum g^2 / k^2`` and ``sum g^3 / k^4``.
    m : int
        How many of the lowest values the median is taken over.

    Returns
    -------
    bias : ndarray (T,) float64
        Expected estimate less the mean of ``mu_{., t}`` over the pixels.
    """
    n, T = levels.size, dev.size
    srt = np.sort(np.asarray(levels, np.float64))
    r = 0.5 * (min(m, n) + 1)
    p = (r - 0.375) / (n + 0.25)
    theta = max(float(skew_factor), 1e-300) / (2.0 * max(float(var_factor), 1e-300))
    w, rep = _level_groups(srt)
    c_min, c_max = float(dev.min()), float(dev.max())
    cs = np.linspace(c_min, c_max, n_grid) if c_max > c_min else np.array([c_min])
    mu = np.maximum(rep[:, None] + cs[None, :], 0.0)  # (groups, grid)
    shape = np.maximum(mu * var_factor / theta**2, 1e-300)
    shift = mu - shape * theta
    lo = np.minimum(shift.min(axis=0), 0.0)
    hi = (mu + 20.0 * np.sqrt(mu * var_factor) + 20.0 * theta).max(axis=0)
    q = _mixture_quantile(w, shape, shift, theta, p, lo, hi)
    mean_mu = np.maximum(srt[:, None] + cs[None, :], 0.0).mean(axis=0)
    bias = np.maximum(q, 0.0) - mean_mu
    return np.interp(dev, cs, bias) if cs.size > 1 else np.full(T, bias[0])


def _level_groups(srt: np.ndarray) -> tuple:
    """Weights and mean levels of groups of the sorted levels ``srt``.

    Equal counts, at most 96 groups in the lowest quarter (where the low quantile of
    the mixture sits) and 32 above, where a pixel's law only shifts the mixture's
    weight below the quantile.
    """
    n = srt.size
    n_low = int(np.ceil(0.25 * n))
    b_low = np.linspace(0, n_low, min(n_low, 96) + 1)
    b_high = np.linspace(n_low, n, max(min(n - n_low, 32), 1) + 1)[1:]
    bounds = np.unique(np.concatenate([b_low, b_high]).round().astype(np.int64))
    sizes = np.diff(bounds)
    return sizes / n, np.add.reduceat(srt, bounds[:-1]) / sizes


def _mixture_quantile(w, shape, shift, theta, p, lo, hi, *, n_iter: int = 100):
    """Per column, ``x`` with ``sum_b w_b P(shift_b + theta Gamma(shape_b) <= x) = p``.

    Regula falsi with the Illinois step inside the bracket ``[lo, hi]``; stops when the
    mixture's CDF is within 1e-8 of ``p`` or the bracket within 1e-9 of its width.
    """

    def excess(x):
        z = np.maximum(x[None, :] - shift, 0.0) / theta
        return (w[:, None] * special.gammainc(shape, z)).sum(axis=0) - p

    f_lo, f_hi = excess(lo), excess(hi)
    width = np.maximum(hi - lo, 1e-300)
    last = np.zeros(lo.shape, np.int8)
    x = 0.5 * (lo + hi)
    for _ in range(n_iter):
        x = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        x = np.where(np.isfinite(x) & (x > lo) & (x < hi), x, 0.5 * (lo + hi))
        fx = excess(x)
        up = fx > 0
        hi, lo = np.where(up, x, hi), np.where(up, lo, x)
        # Illinois: the end that stays twice in a row has its value halved
        f_lo = np.where(up, np.where(last == 1, 0.5 * f_lo, f_lo), fx)
        f_hi = np.where(up, fx, np.where(last == -1, 0.5 * f_hi, f_hi))
        last = np.where(up, 1, -1).astype(np.int8)
        if np.all((np.abs(fx) <= 1e-8) | (hi - lo <= 1e-9 * width)):
            break
    return x


def robust_level(
    coarse: np.ndarray,
    dev: np.ndarray,
    var_factor: float,
    *,
    quantum: float = 0.0,
    n_iter: int = 2,
) -> np.ndarray:
    """Per-pixel level ``b_{n,l}`` of the coarsest cube (``eq:background_2``, index n,l).

    The paper takes the median over t. On low counts the coarse values are skewed
    (the median of a Poisson sum sits below its mean, and is 0 for a fine scale at
    0.02 photons per bin), which biases the background and then the false-alarm
    rate. We take instead a trimmed mean over t of the coarse values detrended by the
    temporal shape, excluding signal: start from the median, keep values within
    ``level +- 2.5 sigma`` with the Poisson sigma of the filtered cube
    (``var = level * var_factor``), and iterate.

    Parameters
    ----------
    coarse : ndarray (..., T) float32
        Coarsest correlated cube of one wavelength.
    dev : ndarray (T,)
        ``bbar_t - mean_t bbar`` of this wavelength.
    var_factor : float
        Variance of one coarse voxel per unit background mean: ``sum g^2 / k^2``.
    quantum : float
        What one photon adds to a coarse voxel at most (``max g / k^2``). The clipping
        window is at least 3 quanta wide: at a small fraction of a photon per coarse
        window the distribution is a spike at 0 plus single photons, and a window in
        sigmas would clip every photon away (a zero background, a zero threshold).

    Returns
    -------
    level : ndarray (...,) float32
    """
    x = coarse - dev.astype(np.float32)
    T = x.shape[-1]
    # the median only centres the first clipping window: every 4th bin is enough
    med = np.median(x[..., :: max(1, min(4, T // 64))], axis=-1)
    mean = x.mean(axis=-1, dtype=np.float64)
    level = np.maximum(med, 0.0)
    # the median is 0 on sparse fine scales: take the Poisson sigma from the mean then
    sig_base = np.where(level > 0, level, mean)
    for it in range(n_iter):
        base = sig_base if it == 0 else level
        half = np.maximum(CLIP * np.sqrt(np.maximum(base, 1e-12) * var_factor), 3.0 * quantum)
        half = half.astype(np.float32)
        lo = (level - half).astype(np.float32)[..., None]
        hi = (level + half).astype(np.float32)[..., None]
        keep = (x >= lo) & (x <= hi)
        n = np.count_nonzero(keep, axis=-1)
        s = np.einsum("...t,...t->...", x, keep.astype(np.float32), dtype=np.float64)
        level = np.where(n > 0, s / np.maximum(n, 1), level)
        level = np.maximum(level, 0.0)
    return level.astype(np.float32)
