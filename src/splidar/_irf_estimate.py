"""Non-parametric IRF shape from the data (private core of :func:`splidar.io.estimate_irf`).

Bright pixels are aligned at their own return (the peak of their correlation with a
template), their background is subtracted, and the aligned histograms are pooled per
wavelength; the pooled curve is cut where it reaches the noise floor or rises again.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import fftconvolve
from scipy.stats import norm, poisson

from ._validation import SplidarError
from .irf import gaussian_irf

#: voxels per processing chunk (float32 work arrays of a few tens of MB)
_CHUNK_VOXELS = 1 << 22


def _centred(kernel: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Pad ``kernel`` with zeros so its peak is the centre sample; also the signal window
    (first, last sample at >= 5 % of the peak) relative to the peak."""
    m = int(np.argmax(kernel))
    n = kernel.size
    h = max(m, n - 1 - m)
    kp = np.zeros(2 * h + 1)
    kp[h - m : h - m + n] = kernel
    big = np.flatnonzero(kernel >= 0.05 * kernel[m])
    return kp, int(big[0]) - m, int(big[-1]) - m


def _pool(a: np.ndarray, kernel: np.ndarray, k_left: int, k_right: int, z: float):
    """Align bright pixels of ``a`` (P, L, T) at the peak of their correlation with
    ``kernel`` and pool their background-subtracted histograms over lags
    ``-k_left..k_right``. Returns (sum (L, K), variance (L, K), pixels per lag (K,),
    number of pixels used)."""
    n_pix, n_l, n_bins = a.shape
    kp, s_lo, s_hi = _centred(np.asarray(kernel, np.float64))
    width = s_hi - s_lo + 1
    # a pixel is bright when its peak window beats the background at the p-value of a
    # one-sided z-sigma Gaussian, Bonferroni-corrected for the T / width windows searched
    alpha = norm.sf(z) / max(n_bins / width, 1.0)
    n_lag = k_left + k_right + 1
    lags = np.arange(-k_left, k_right + 1)
    tot = np.zeros((n_l, n_lag))
    var = np.zeros((n_l, n_lag))
    cover = np.zeros(n_lag)
    n_used = 0
    step = max(1, _CHUNK_VOXELS // (n_l * n_bins))
    for s in range(0, n_pix, step):
        y = np.asarray(a[s : s + step], dtype=np.float32)
        ys = y.sum(axis=1)
        # correlation with the template (FFT: a long-tailed template on thousands of bins)
        score = fftconvolve(ys, kp[::-1][None, :].astype(np.float32), mode="same", axes=-1)
        p = np.argmax(score, axis=-1)
        cs = np.concatenate([np.zeros(y.shape[:2] + (1,), np.float64), np.cumsum(y, -1)], -1)
        lo = np.clip(p - k_left, 0, n_bins - 1)
        hi = np.clip(p + k_right, 0, n_bins - 1)
        r = np.arange(y.shape[0])
        inside = cs[r, :, hi + 1] - cs[r, :, lo]  # (Pc, L)
        n_out = n_bins - (hi - lo + 1)
        # background per bin from the bins away from the return; (outside + 1) / bins
        # outside is never zero, so a pixel of a few photons in a dark scene is not
        # taken for significant on its photon count alone
        b_up = (cs[:, :, -1] - inside + 1.0) / np.maximum(n_out, 1)[:, None]
        b = np.where(n_out[:, None] > 0, (cs[:, :, -1] - inside) / np.maximum(n_out, 1)[:, None], 0)
        w_lo = np.clip(p + s_lo, 0, n_bins - 1)
        w_hi = np.clip(p + s_hi, 0, n_bins - 1)
        n_sig = (cs[r, :, w_hi + 1] - cs[r, :, w_lo]).sum(axis=1)
        mu = (w_hi - w_lo + 1) * b_up.sum(axis=1)
        keep = poisson.sf(n_sig - 1, mu) < alpha
        if not keep.any():
            continue
        y, p, b, score = y[keep], p[keep], b[keep], score[keep]
        idx = p[:, None] + lags[None, :]  # (Pk, K)
        valid = (idx >= 0) & (idx < n_bins)
        tot -= (b[:, :, None] * valid[:, None, :]).sum(axis=0)
        cover += valid.sum(axis=0)
        n_used += int(keep.sum())
        i, l, t = np.nonzero(y)
        c = y[i, l, t]
        lag = t - _loo_peak(score, p, kp, i, t, width)
        ok = (lag >= -k_left) & (lag <= k_right)
        flat = l[ok] * n_lag + lag[ok] + k_left
        h = np.bincount(flat, weights=c[ok], minlength=n_l * n_lag).reshape(n_l, n_lag)
        tot += h
        var += h
    return tot, var, cover, n_used


def _loo_peak(score, p, kp, i, t, reach: int) -> np.ndarray:
    """Return of pixel ``i`` without one photon of bin ``t`` (leave-one-out), searched
    within ``reach`` bins of its full-data peak ``p[i]``: a photon never aligns its own
    pixel, so the pooled shape has no spike at the peak."""
    h = kp.size // 2
    d = np.arange(-reach, reach + 1)
    out = np.empty(i.size, np.int64)
    step = max(1, (1 << 21) // d.size)
    n_bins = score.shape[1]
    for s in range(0, i.size, step):
        ii, tt = i[s : s + step], t[s : s + step]
        cand = p[ii, None] + d[None, :]
        inb = (cand >= 0) & (cand < n_bins)
        cc = np.clip(cand, 0, n_bins - 1)
        j = tt[:, None] - cc + h
        own = np.where((j >= 0) & (j < kp.size), kp[np.clip(j, 0, kp.size - 1)], 0.0)
        sc = np.where(inb, score[ii[:, None], cc] - own, -np.inf)
        out[s : s + step] = cc[np.arange(ii.size), np.argmax(sc, axis=1)]
    return out


def _support(r: np.ndarray, sig: np.ndarray, z: float, m: int) -> tuple[int, int]:
    """First and last lag index kept: walking out of the peak, stop before the curve
    reaches ``z`` noise sigmas, or, once below half the peak, at its lowest point
    before a rise of more than ``z`` sigmas (a second surface). Both tests read the
    curve averaged over ``m`` bins (odd), whose noise is ``sqrt(m)`` times lower."""
    box = np.ones(m) / m
    rs = np.convolve(r, box, mode="same")
    ss = np.sqrt(np.convolve(sig**2, box / m, mode="same"))
    pk = int(np.argmax(r))
    half = r[pk] / 2.0
    ends = []
    for direction in (-1, 1):
        j, jmin, end = pk, pk, None
        while 0 <= j + direction < r.size:
            j += direction
            if rs[j] <= z * ss[j]:
                end = j - direction
                break
            if rs[j] < rs[jmin]:
                jmin = j
            elif rs[jmin] < half and rs[j] - rs[jmin] > z * math.hypot(ss[j], ss[jmin]):
                end = jmin
                break
        ends.append(j if end is None else end)
    return ends[0], ends[1]


def pooled_shape(
    a: np.ndarray, fwhm: float, k_left: int, k_right: int, z: float, min_pixels: int
) -> tuple[np.ndarray, int]:
    """IRF ``(L, n)`` pooled from ``a`` (P, L, T): two alignment passes (a Gaussian of
    ``fwhm``, then the first pass's shape), cut to its support, unit sum per row.
    Returns the IRF and the number of pixels pooled."""
    kernel = gaussian_irf(fwhm)
    m = 2 * int(fwhm // 4) + 1  # about half the FWHM, odd
    for _ in range(2):
        tot, var, cover, n_used = _pool(a, kernel, k_left, k_right, z)
        if n_used < min_pixels:
            raise SplidarError(
                f"only {n_used} pixel(s) with a return significant at {z:g} sigma (need "
                f"min_pixels={min_pixels}): too little signal to estimate the IRF shape; pass "
                "irf= (array or file), irf_fwhm=, or lower `significance` / `min_pixels`."
            )
        n = np.maximum(cover, 1.0)
        r = tot / n
        sig = np.sqrt(np.maximum(var, 1.0)) / n
        rows = []
        for l in range(r.shape[0]):
            lo, hi = _support(r[l], sig[l], z, m)
            rows.append(np.clip(r[l, lo : hi + 1], 0.0, None))
        pooled = r.sum(axis=0)
        lo, hi = _support(pooled, np.sqrt((sig**2).sum(axis=0)), z, m)
        kernel = np.clip(pooled[lo : hi + 1], 0.0, None)
    width = max(row.size for row in rows)
    out = np.zeros((len(rows), width))
    for l, row in enumerate(rows):
        if row.sum() <= 0:
            raise SplidarError(
                f"wavelength {l} has no return above the background: its IRF shape cannot "
                "be estimated; pass irf= (array or file) or irf_fwhm=."
            )
        out[l, : row.size] = row / row.sum()
    return out, n_used
