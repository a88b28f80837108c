"""Background estimation (``eq:background_1..3``), kept factored.

Both factors live on the IRF-correlated scale of the saliency: the matched filter has
unit sum, so a smooth background keeps its level, and the saliency subtracts the
estimate from the correlated cube.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage, signal

from ._fast import window_means
from ._filters import Correlator

__all__ = ["robust_level", "sample_grid", "temporal_shape"]

#: Fraction of pixels whose median gives the temporal shape (``eq:background_1``).
LOW_FRACTION = 0.10
#: Half-width of the symmetric clipping window, in Poisson sigmas of the coarse cube.
#: Symmetric, so the clipped mean of background-only values is unbiased; returns
#: leaking in from neighbours (weak, positive) are cut beyond it.
CLIP = 2.5
#: Seed of the (fixed) simulation that measures the low-quantile bias (_debias_profile).
_DEBIAS_SEED = 12345
#: Pixels simulated per wavelength in _debias_profile (a subsample when more are sampled).
_DEBIAS_PIXELS = 600
#: Simulated draws per pixel and bin in _debias_profile.
_DEBIAS_SIMS = 4


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
    (:func:`_refine_profile`).

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
        sampled = np.empty((row_starts.size, col_starts.size, L, T), np.float32)
        for i, a in enumerate(row_starts):
            # exact window sums in one numba pass over the rows (_fast.window_means)
            sampled[i] = window_means(np.asarray(counts[a : a + kr]), col_starts, kc)
    else:
        sampled = windows(counts, row_starts, kr, col_starts, kc)
    coarse = corr(sampled, workers=workers).reshape(-1, L, T)
    n = coarse.shape[0]
    m = max(1, int(np.ceil(LOW_FRACTION * n)))
    low = np.partition(coarse, m - 1, axis=0)[:m] if m < n else coarse
    prof = np.median(low, axis=0).astype(np.float64)  # eq:background_1
    if smooth > 1:
        prof = ndimage.median_filter(prof, size=(1, smooth), mode="nearest")
    if refine:
        var_factor = (corr.irf**2).sum(axis=1) / (kr * kc)
        # one independent stream per wavelength (spawned from a fixed seed), so the
        # wavelengths run on threads (numpy's Poisson draws release the GIL) and the
        # result does not depend on the number of threads
        rngs = np.random.default_rng(_DEBIAS_SEED).spawn(L)

        def one(l):
            quantum = float(corr.irf[l].max()) / (kr * kc)
            return _debias_profile(
                coarse[:, l], prof[l], float(var_factor[l]), m, smooth, rngs[l], quantum=quantum
            )

        n_thr = max(1, min(int(workers), L))
        if n_thr > 1:
            with ThreadPoolExecutor(n_thr) as ex:
                prof = np.stack(list(ex.map(one, range(L))))
        else:
            prof = np.stack([one(l) for l in range(L)])
    return prof.astype(np.float32)


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


def _debias_profile(x, prof, var_factor, m, smooth, rng, n_iter=1, n_sim=None, quantum=0.0):
    """Remove the low-quantile bias of ``eq:background_1`` (robust to signal).

    The median of the lowest 10 % sits below the background mean by an amount that
    grows with the level and with the skew of low counts, which distorts a decaying
    shape and then mis-calibrates the threshold along t. The bias is measured by
    applying the same estimator to simulated background-only coarse values (a scaled
    Poisson ``v Pois(b / v)`` with the coarse cube's mean ``b`` and variance ``b v``,
    per sampled pixel and bin) and subtracted. The estimator itself keeps the paper's
    robustness to returns in up to 90 % of the pixels.
    """
    n, T = x.shape
    n_sim = _DEBIAS_SIMS if n_sim is None else n_sim
    if n > _DEBIAS_PIXELS:
        # the bias is a property of the estimator at this sample size: simulate it on a
        # subsample of the pixels with the same 10 % fraction (cost)
        x = x[rng.choice(n, _DEBIAS_PIXELS, replace=False)]
        n = _DEBIAS_PIXELS
        m = max(1, int(np.ceil(LOW_FRACTION * n)))
    est = prof.copy()
    for _ in range(n_iter):
        dev = (est - est.mean()).astype(np.float32)
        lvl = robust_level(x, dev, var_factor, quantum=quantum).astype(np.float64)  # (n,)
        mu = np.maximum(lvl[:, None] + dev[None, :], 0.0)  # (n, T)
        bias = np.zeros(T)
        mu_mean = mu.mean(axis=0)
        # all draws in one call (the same stream as n_sim successive (n, T) draws); each
        # is transposed so that the selection and the median run along contiguous memory
        draws = rng.poisson(mu / var_factor, size=(n_sim, n, T))
        for i in range(n_sim):
            sim = var_factor * np.ascontiguousarray(draws[i].T)  # (T, n)
            low = np.partition(sim, m - 1, axis=-1)[:, :m] if m < n else sim
            bias += np.median(low, axis=-1) - mu_mean
        bias /= n_sim
        if smooth > 1:
            bias = ndimage.median_filter(bias, size=smooth, mode="nearest")
        est = prof - bias
    win = min(max(5, smooth | 1), T if T % 2 else T - 1)
    if win >= 5:
        # a local quadratic fit (Savitzky-Golay, polynomial at the window edges) takes
        # the sampling noise of the low quantile off the shape; bumps are gone already
        est = signal.savgol_filter(est, win, 2, mode="interp")
    return est


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
