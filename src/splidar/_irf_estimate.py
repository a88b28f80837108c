"""Non-parametric IRF shape from the data (private core of :func:`splidar.io.estimate_irf`).

Bright pixels are aligned at their own return (the peak of their correlation with a
template), their background is subtracted, and the aligned histograms are pooled per
wavelength; the pooled curve is cut where it reaches the noise floor or rises again.
Then (:func:`soft_align`) expectation-maximisation over each pixel's return position
removes the hard alignment's jitter from the shape, so its peak (the depth reference)
does not slide into a slowly decaying tail.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit
from scipy.optimize import curve_fit
from scipy.stats import chi2, norm, poisson

from ._validation import SplidarError
from .irf import gaussian_irf

log = logging.getLogger(__name__)

#: voxels per processing chunk (float32 work arrays of a few tens of MB)
_CHUNK_VOXELS = 1 << 22
#: most soft-alignment (EM) iterations, and the change (L1, per wavelength) that stops them
_EM_MAX_ITER = 20
_EM_TOL = 5e-3
#: centre weight of the smoothing kernel [1, w, 1] / (w + 2) applied after each M-step
_EM_SMOOTH = 2.0
#: photon-shift pairs per EM step at most (cost bound): beyond it every k-th bright pixel
_EM_PAIRS = 1 << 22
#: fine samples per bin of the soft alignment's shifts and shape
_EM_UP = 1
_EM_PASSES = 1


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


def _photons(a: np.ndarray):
    """The non-empty voxels of ``a`` (P, L, T): (pixel, wavelength, bin, count), ordered
    by pixel, wavelength and bin, and the offset of each pixel's first one (P + 1,)."""
    n_pix, n_l, n_bins = a.shape
    rowi, t = np.nonzero(a.reshape(n_pix * n_l, n_bins))
    c = a.reshape(n_pix * n_l, n_bins)[rowi, t].astype(np.float64)
    pix, l = np.divmod(rowi, n_l)
    ptr = np.concatenate([[0], np.cumsum(np.bincount(pix, minlength=n_pix))])
    return pix, l, t.astype(np.int64), c, ptr


#: relative difference below which two correlation scores are a tie (exact ties are
#: common with a few integer counts and a symmetric template)
_TIE = 1e-9


def _photons_sparse(uniq: np.ndarray, cnt: np.ndarray, shape):
    """:func:`_photons` of a one-wavelength cube of ``shape`` from its sorted non-empty
    flat voxel indices ``uniq`` and their counts."""
    n_pix, _, n_bins = shape
    pix, t = np.divmod(np.asarray(uniq, dtype=np.int64), n_bins)
    ptr = np.concatenate([[0], np.cumsum(np.bincount(pix, minlength=n_pix))])
    return pix, np.zeros(pix.size, np.int64), t, np.asarray(cnt, np.float64), ptr


@njit(cache=True)
def _peaks(ptr, t, c, kp, n_bins, reach):  # pragma: no cover - numba
    """Per pixel: the peak ``p`` of its photons' correlation with ``kp`` (centred:
    ``score[s] = sum c kp[t - s + h]``); per photon: the peak of the
    pixel's other photons (its own kernel removed) within ``reach`` bins of ``p``
    (leave-one-out). Ties (scores within ``_TIE``): the first one for even pixels
    (photons), the last for odd ones, so neither side is favoured (the FFT of earlier
    releases broke them by its rounding)."""
    n_pix = ptr.size - 1
    n_k = kp.size
    h = n_k // 2
    score = np.zeros(n_bins)
    p = np.zeros(n_pix, np.int64)
    loo = np.zeros(t.size, np.int64)
    for i in range(n_pix):
        a, b = ptr[i], ptr[i + 1]
        if a == b:
            continue
        lo, hi = n_bins, -1
        for u in range(a, b):
            for j in range(n_k):
                s = t[u] - j + h
                if 0 <= s < n_bins:
                    score[s] += c[u] * kp[j]
                    lo = min(lo, s)
                    hi = max(hi, s)
        best = 0
        if lo <= hi:
            first, last = lo, lo
            for s in range(lo + 1, hi + 1):
                if score[s] > score[first] * (1.0 + _TIE):
                    first, last = s, s
                elif score[s] >= score[first] * (1.0 - _TIE):
                    last = s
            best = first if i % 2 == 0 else last
            if score[best] <= 0.0:
                best = 0
        p[i] = best
        for u in range(a, b):
            bv = 0.0
            first, last = -1, -1
            for d in range(-reach, reach + 1):
                s = best + d
                if s < 0 or s >= n_bins:
                    continue
                j = t[u] - s + h
                own = kp[j] if 0 <= j < n_k else 0.0
                v = score[s] - own
                if first < 0 or v > bv + _TIE * abs(bv):
                    bv = v
                    first, last = s, s
                elif v >= bv - _TIE * abs(bv):
                    last = s
            loo[u] = first if u % 2 == 0 else last
        for s in range(max(lo, 0), min(hi, n_bins - 1) + 1):
            score[s] = 0.0
    return p, loo


def _pool(shape, ph, kernel: np.ndarray, k_left: int, k_right: int, z: float):
    """Align bright pixels of the cube ``shape`` (P, L, T) whose photons are ``ph``
    (:func:`_photons`) at the peak of their correlation with ``kernel`` and pool their
    background-subtracted histograms over lags ``-k_left..k_right``. Returns (sum (L, K),
    variance (L, K), pixels per lag (K,), number of pixels used, (indices, peaks,
    backgrounds (Pk, L)) of the pixels used)."""
    n_pix, n_l, n_bins = shape
    pix, l, t, c, ptr = ph
    kp, s_lo, s_hi = _centred(np.asarray(kernel, np.float64))
    width = s_hi - s_lo + 1
    # a pixel is bright when its peak window beats the background at the p-value of a
    # one-sided z-sigma Gaussian, Bonferroni-corrected for the T / width windows searched
    alpha = norm.sf(z) / max(n_bins / width, 1.0)
    n_lag = k_left + k_right + 1
    p, loo = _peaks(ptr, t, c, kp, n_bins, width)
    lo = np.clip(p - k_left, 0, n_bins - 1)
    hi = np.clip(p + k_right, 0, n_bins - 1)
    key = pix * n_l + l
    total = np.bincount(key, c, n_pix * n_l).reshape(n_pix, n_l)
    inn = (t >= lo[pix]) & (t <= hi[pix])
    inside = np.bincount(key[inn], c[inn], n_pix * n_l).reshape(n_pix, n_l)
    n_out = n_bins - (hi - lo + 1)
    # background per bin from the bins away from the return; (outside + 1) / bins
    # outside is never zero, so a pixel of a few photons in a dark scene is not
    # taken for significant on its photon count alone
    b_up = (total - inside + 1.0) / np.maximum(n_out, 1)[:, None]
    b = np.where(n_out[:, None] > 0, (total - inside) / np.maximum(n_out, 1)[:, None], 0)
    w_lo = np.clip(p + s_lo, 0, n_bins - 1)
    w_hi = np.clip(p + s_hi, 0, n_bins - 1)
    inw = (t >= w_lo[pix]) & (t <= w_hi[pix])
    n_sig = np.bincount(pix[inw], c[inw], n_pix)
    mu = (w_hi - w_lo + 1) * b_up.sum(axis=1)
    keep = poisson.sf(n_sig - 1, mu) < alpha
    kept_i = np.flatnonzero(keep)
    # each kept pixel covers the lags whose bin p + lag is inside the cube: a run
    first = np.maximum(-k_left, -p[kept_i]) + k_left
    last = np.minimum(k_right, n_bins - 1 - p[kept_i]) + k_left
    run = np.zeros((n_l + 1, n_lag + 1))
    np.add.at(run, (slice(None), first), np.vstack([b[kept_i].T, np.ones(kept_i.size)]))
    np.add.at(run, (slice(None), last + 1), -np.vstack([b[kept_i].T, np.ones(kept_i.size)]))
    run = np.cumsum(run, axis=1)[:, :n_lag]
    cover = run[n_l]
    sel = keep[pix]
    lag = t[sel] - loo[sel]
    ok = (lag >= -k_left) & (lag <= k_right)
    flat = l[sel][ok] * n_lag + lag[ok] + k_left
    hist = np.bincount(flat, weights=c[sel][ok], minlength=n_l * n_lag).reshape(n_l, n_lag)
    return hist - run[:n_l], hist.copy(), cover, int(kept_i.size), (kept_i, p[kept_i], b_up[kept_i])


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


def gaussian_test(r: np.ndarray, sig: np.ndarray) -> tuple[float, int, float]:
    """Chi-square of the best Gaussian (amplitude, centre, width: weighted least squares)
    against the pooled curve ``r`` of standard errors ``sig`` (its support). Returns
    (chi-square, degrees of freedom, p-value): a large p-value means the pooled photons
    cannot tell the curve from a Gaussian."""
    x = np.arange(r.size, dtype=np.float64)
    k = r.size - 3
    if k < 1:
        return 0.0, max(k, 0), 1.0
    pk = int(np.argmax(r))
    w0 = max(0.5, float(np.sum(r > r[pk] / 2.0)) / 2.3548)

    def model(x, a, c, s):
        return a * np.exp(-0.5 * ((x - c) / s) ** 2)

    try:
        popt, _ = curve_fit(model, x, r, p0=(r[pk], pk, w0), sigma=sig, maxfev=2000)
    except (RuntimeError, ValueError):  # no convergence: the curve is far from a Gaussian
        return math.inf, k, 0.0
    c2 = float(np.sum(((r - model(x, *popt)) / sig) ** 2))
    return c2, k, float(chi2.sf(c2, k))


#: how the depth reference (argmax) of an estimated shape is placed (:func:`_reference`):
#: "peaks" (the local maxima's positions weighted by their chance of being the
#: maximum), "pmax" (every sample's position so weighted) or "argmax" (the estimate's
#: own maximum, releases before irf25); the last two for benchmarks
_REFERENCE = "peaks"


def max_probability(u: np.ndarray, s: np.ndarray, n_grid: int = 801) -> np.ndarray:
    """Probability that each sample of a noisy curve is its true maximum.

    Parameters
    ----------
    u : ndarray, shape (K,)
        The estimated curve.
    s : ndarray, shape (K,)
        Standard error of each sample (same units as ``u``), > 0.

    Returns
    -------
    p : ndarray, shape (K,)
        ``P(x_j = max_k x_k)`` for independent ``x_k ~ N(u_k, s_k^2)``: ``int phi_j(x)
        prod_{k != j} Phi_k(x) dx`` on a grid of ``n_grid`` points; sums to 1."""
    u = np.asarray(u, np.float64)
    s = np.maximum(np.asarray(s, np.float64), 1e-300)
    m = int(np.argmax(u))
    lo = float(np.max(u - 8.0 * s))  # the maximum is above every sample's -8 sigma
    hi = float(np.max(u + 8.0 * s))
    x = np.linspace(lo, hi, n_grid)
    zz = (x[None, :] - u[:, None]) / s[:, None]
    logcdf = norm.logcdf(zz)
    dens = norm.pdf(zz) / s[:, None] * np.exp(logcdf.sum(axis=0)[None, :] - logcdf)
    p = np.trapezoid(dens, x, axis=1)
    tot = float(p.sum())
    if not tot > 0:
        p = np.zeros(u.size)
        p[m] = 1.0
        return p
    return p / tot


def _hill_tops(u: np.ndarray) -> np.ndarray:
    """For each sample of ``u`` (K,), the local maximum that steepest ascent (to the
    higher neighbour) reaches from it (K,) int."""
    n = u.size
    left = np.r_[-np.inf, u[:-1]]
    right = np.r_[u[1:], -np.inf]
    step = np.where((left > u) & (left >= right), -1, np.where(right > u, 1, 0))
    top = np.arange(n)
    for _ in range(n):  # follow the steps until every sample sits on a top
        nxt = top + step[top]
        if np.array_equal(nxt, top):
            break
        top = nxt
    return top


def _reference(row: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``row`` (K,) with its argmax (the depth reference) moved to the expected position
    of its maximum among its peaks: each sample's chance ``P_j`` of being the maximum
    (:func:`max_probability`, standard errors ``s``: the pooled curve's Poisson errors
    relative to its sum) goes to the local maximum that steepest ascent reaches from it
    (:func:`_hill_tops`); the reference is ``sum_j P_j top_j``, rounded.

    A curve with one peak keeps its argmax (the convention): every sample climbs to it,
    however flat its top or slow its tail (exp tail 2/25: the reference moved into the
    tail on 9 of 24 seeds when every sample counted as its own candidate, "pmax"). On
    a top that is flat within the noise with two bumps (a measured pulse's plateau,
    within 10-20 % of its peak over 12 bins) the estimate's argmax jumps from one end to
    the other between data sets (depth bias 0 or -6 bins); the reference then lies
    between the bumps in proportion to their chances, a stable point. Where the photons
    determine the peak, ``P`` sits on the argmax and nothing changes (the real files of
    benchmarks/real_data.py). The chosen sample is raised to just above the maximum, a
    change within its noise (the row is then returned scaled to unit sum). Measured in
    benchmarks/README.md, irf25."""
    if _REFERENCE == "argmax" or row.size < 2:
        return row
    u = np.asarray(row, np.float64) / max(float(np.sum(row)), 1e-300)
    p = max_probability(u, s)
    pos = _hill_tops(u) if _REFERENCE == "peaks" else np.arange(u.size)
    ref = int(np.rint(np.sum(p * pos)))
    m = int(np.argmax(u))
    if ref == m:
        return row
    out = u.copy()
    out[ref] = u[m] * (1.0 + 1e-6)
    return out / out.sum()


def _peak_move(h: np.ndarray, h0: np.ndarray) -> int:
    """Distance (samples) between the peaks of ``h`` and ``h0`` once ``h`` is placed where
    it best correlates with ``h0``."""
    lag = int(np.argmax(np.correlate(h, h0, mode="full"))) - (h0.size - 1)
    return abs(int(np.argmax(h)) - lag - int(np.argmax(h0)))


def pooled_shape(
    a: np.ndarray,
    fwhm: float,
    k_left: int,
    k_right: int,
    z: float,
    min_pixels: int,
    *,
    refine: bool = True,
    gaussian_p: float = 2.0,
    voxels=None,
    reference: bool = True,
) -> tuple[np.ndarray, int, tuple[float, int, float]]:
    """IRF ``(L, n)`` pooled from ``a`` (P, L, T): two alignment passes (a Gaussian of
    ``fwhm``, then the first pass's shape), cut to its support, then (``refine``) the
    soft alignment (:func:`soft_align`) unless the Gaussian test's p-value is at least
    ``gaussian_p`` (the caller falls back to a Gaussian); unit sum per row. Returns the
    IRF, the number of pixels pooled and :func:`gaussian_test` of the hard-aligned
    pooled curve (all wavelengths) on its support. ``voxels``: the non-empty voxels of
    a one-wavelength ``a`` as (sorted flat index ``pixel * T + bin``, count), when at
    hand (photon lists), to skip the scan of the dense cube."""
    kernel = gaussian_irf(fwhm)
    m = 2 * int(fwhm // 4) + 1  # about half the FWHM, odd
    ph = _photons(a) if voxels is None else _photons_sparse(*voxels, a.shape)
    for _ in range(2):
        tot, var, cover, n_used, kept = _pool(a.shape, ph, kernel, k_left, k_right, z)
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
        spans = []
        for l in range(r.shape[0]):
            lo, hi = _support(r[l], sig[l], z, m)
            spans.append((lo, hi))
            rows.append(np.clip(r[l, lo : hi + 1], 0.0, None))
        pooled = r.sum(axis=0)
        sig_p = np.sqrt((sig**2).sum(axis=0))
        lo, hi = _support(pooled, sig_p, z, m)
        kernel = np.clip(pooled[lo : hi + 1], 0.0, None)
    test = gaussian_test(pooled[lo : hi + 1], sig_p[lo : hi + 1])
    soft = False
    if refine and test[2] < gaussian_p:
        support = np.zeros(r.shape, bool)
        h0 = np.zeros(r.shape)
        for l, (a_, b_) in enumerate(spans):
            support[l, a_ : b_ + 1] = True
            h0[l, a_ : b_ + 1] = rows[l]
        # the jitter of the hard alignment is within about a FWHM of the template
        reach = max(2, int(np.count_nonzero(kernel > kernel.max() / 2.0)))
        h, _ = soft_align(ph, kept, h0, support, k_left, reach)
        # the soft peak corrects the jitter's shift of the hard one (measured: at most a
        # quarter of the FWHM); a move beyond half the FWHM, the two shapes placed where
        # they best correlate (the EM may shift the whole shape: its shifts absorb it),
        # is a flat top's other end (a measured pulse whose plateau is within a few %
        # of its peak), which the photons do not tell apart: the hard shape is kept
        move = np.array([_peak_move(h[l], h0[l]) for l in range(h.shape[0])])
        if np.all(move <= reach / 2.0):
            rows = [h[l, a_ : b_ + 1] for l, (a_, b_) in enumerate(spans)]
            soft = True
        else:
            log.info(
                "IRF shape: the soft alignment moves the peak by %d bins (more than half the "
                "FWHM, %d bins): the hard-aligned shape is kept",
                int(move.max()),
                reach,
            )
    # the peak where the photons place it (:func:`_reference`), on the soft shape (smoothed
    # each step: its local maxima are features; the hard-aligned curve's are Poisson
    # wiggles, which moved exp tail 2/25's reference 3 bins into the tail on 2 seeds of 3)
    if reference and soft:
        for l, (a_, b_) in enumerate(spans):  # errors relative to the pooled curve's sum
            tot = max(float(np.clip(r[l, a_ : b_ + 1], 0.0, None).sum()), 1e-300)
            rows[l] = _reference(rows[l], sig[l, a_ : b_ + 1] / tot)
    width = max(row.size for row in rows)
    out = np.zeros((len(rows), width))
    for l, row in enumerate(rows):
        if row.sum() <= 0:
            raise SplidarError(
                f"wavelength {l} has no return above the background: its IRF shape cannot "
                "be estimated; pass irf= (array or file) or irf_fwhm=."
            )
        out[l, : row.size] = row / row.sum()
    return out, n_used, test


def _photons_near(ph, kept, k_left: int, n_lag: int, reach: int):
    """Photons (``ph``, :func:`_photons`) of the bright pixels within ``reach`` bins of
    their lag window: (pixel (index into ``kept``), wavelength, lag index
    ``t - p + k_left``, count)."""
    idx, p, _ = kept
    pix, l, t, c, _ = ph
    pos = np.clip(np.searchsorted(idx, pix), 0, max(idx.size - 1, 0))
    sel = idx[pos] == pix if idx.size else np.zeros(pix.size, bool)
    i = pos[sel]
    u = t[sel] - p[i] + k_left
    ok = (u >= -reach) & (u < n_lag + reach)
    return i[ok], l[sel][ok], u[ok], c[sel][ok]


def _pairs(hf, ratio, pi, pl, pu, e, up: int, s, step):
    """Photons ``s : s + step`` against every candidate shift ``e`` (fine samples): the
    first fine sample under each pair's bin (clipped), the fine masses of its ``up``
    samples (0 off the grid) and ``ratio`` times their sum (the bin's rate over ``b``)."""
    n_f = hf.shape[1]
    i, l = pi[s : s + step], pl[s : s + step]
    j0 = up * pu[s : s + step, None] - e[None, :]
    parts = []
    for q in range(up):
        j = j0 + q
        parts.append(np.where((j >= 0) & (j < n_f), hf[l[:, None], np.clip(j, 0, n_f - 1)], 0.0))
    return j0, parts, ratio[i, l][:, None] * sum(parts)


def _em_step_fine(hf, ratio, pi, pl, pu, pc, e, up: int, n_pix: int):
    """One E- and M-step of :func:`soft_align` on a grid of ``1 / up`` bin (NumPy): the
    unsmoothed expected signal photons per fine sample (L, n_f) and per pixel (P, L)."""
    n_l, n_f = hf.shape
    n_d = e.size
    step = max(1, (1 << 21) // n_d)
    cols = np.arange(n_d)
    ll = np.zeros(n_pix * n_d)
    for s in range(0, pi.size, step):
        _, _, sh = _pairs(hf, ratio, pi, pl, pu, e, up, s, step)
        key = (pi[s : s + step, None] * n_d + cols).ravel()
        ll += np.bincount(key, (pc[s : s + step, None] * np.log1p(sh)).ravel(), n_pix * n_d)
    ll = ll.reshape(n_pix, n_d)
    post = np.exp(ll - ll.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)
    num = np.zeros(n_l * n_f)
    amp_new = np.zeros(n_pix * n_l)
    for s in range(0, pi.size, step):
        j0, parts, sh = _pairs(hf, ratio, pi, pl, pu, e, up, s, step)
        i, l = pi[s : s + step], pl[s : s + step]
        w = pc[s : s + step, None] * post[i] * (ratio[i, l][:, None] / (1.0 + sh))
        for q in range(up):  # each fine sample its share h_f / sum of the bin
            key = (l[:, None] * n_f + np.clip(j0 + q, 0, n_f - 1)).ravel()
            num += np.bincount(key, (w * parts[q]).ravel(), n_l * n_f)
        amp_new += np.bincount(i * n_l + l, (w * (sh / ratio[i, l][:, None])).sum(1), n_pix * n_l)
    return num.reshape(n_l, n_f), amp_new.reshape(n_pix, n_l)


@njit(cache=True)
def _em_step(hf, ratio, pi, pl, pu, pc, reach):  # pragma: no cover - numba
    """:func:`_em_step_fine` on whole bins (``up = 1``), compiled: no photon x shift
    work arrays. Shift ``e = k - reach``; the photon at lag ``pu`` reads ``hf[pu - e]``
    (0 off the support's grid)."""
    n_l, n_f = hf.shape
    n_pix = ratio.shape[0]
    n_d = 2 * reach + 1
    ll = np.zeros((n_pix, n_d))
    for u in range(pi.size):
        i, l, q, c = pi[u], pl[u], pu[u], pc[u]
        r = ratio[i, l]
        for k in range(n_d):
            j = q - k + reach
            if 0 <= j < n_f:
                ll[i, k] += c * math.log1p(r * hf[l, j])
    for i in range(n_pix):
        m = ll[i].max()
        tot = 0.0
        for k in range(n_d):
            ll[i, k] = math.exp(ll[i, k] - m)
            tot += ll[i, k]
        for k in range(n_d):
            ll[i, k] /= tot
    num = np.zeros((n_l, n_f))
    amp = np.zeros((n_pix, n_l))
    for u in range(pi.size):
        i, l, q, c = pi[u], pl[u], pu[u], pc[u]
        r = ratio[i, l]
        for k in range(n_d):
            j = q - k + reach
            if 0 <= j < n_f:
                hv = hf[l, j]
                w = c * ll[i, k] * r / (1.0 + r * hv)
                num[l, j] += w * hv
                amp[i, l] += w * hv
    return num, amp


def soft_align(ph, kept, h0, support, k_left: int, reach: int) -> tuple[np.ndarray, int]:
    """Refine the hard-aligned IRF ``h0`` (L, K) by expectation-maximisation over each
    bright pixel's unknown return position (soft alignment), smoothed each step.

    Model per used pixel ``n`` and wavelength ``l``: ``y(t) ~ Poisson(a_nl h_l(t - s_n)
    + b_nl)``, the shift ``s_n`` uniform over ``p_n - reach .. p_n + reach`` (``p_n``: its
    hard alignment), ``b_nl`` its background per bin (``kept``). E-step: each pixel's
    posterior over the shifts (log-likelihood ``sum_t y log(1 + a h(t - s) / b)``, the
    ``- a`` term being the same for every shift). M-step: ``h`` is the expected signal
    photons per lag, ``a`` the expected signal photons per pixel. Hard alignment is
    self-consistent with a shape blurred by its own jitter (a slow rise, the peak moved
    into the tail); the soft one is not, and sharpens the rise back. Unregularised, the
    steps amplify the noise (a spiky top: the reference then jumps on a flat-topped
    pulse; 2-fold cross-validation stops them after 1-5 steps, before the rise is
    back), so each M-step is smoothed by ``[1, 2, 1] / 4`` inside ``support`` (EMS: a
    fixed point, adding 0.7 bin of Gaussian spread). Stops when the shape changes by
    less than ``_EM_TOL`` (L1) or after ``_EM_MAX_ITER`` steps. Beyond ``_EM_PAIRS``
    photon-shift pairs per step every k-th pixel is used. ``_EM_UP`` > 1 runs it on a
    grid of ``1 / _EM_UP`` bin (measured with 2: sharper on fast pulses, but the peak of
    a flat-topped one jumps; benchmarks/README.md, irf20). Returns the shape (L, K) and
    the steps taken."""
    n_l, n_lag = h0.shape
    up = _EM_UP
    n_f = up * n_lag
    b = np.maximum(kept[2], 1e-12)
    pi, pl, pu, pc = _photons_near(ph, kept, k_left, n_lag, reach)
    e = np.arange(-up * reach, up * reach + 1)
    n_d = e.size
    stride = max(1, math.ceil(pi.size * n_d / _EM_PAIRS))
    if stride > 1:  # a large scene: every stride-th bright pixel (deterministic)
        sel = pi % stride == 0
        pi, pl, pu, pc = pi[sel] // stride, pl[sel], pu[sel], pc[sel]
        b = b[::stride]
    n_pix = b.shape[0]
    fsup = np.repeat(support, up, axis=1)
    hf = np.repeat(np.where(support, np.clip(h0, 0.0, None), 0.0), up, axis=1)
    hf /= np.maximum(hf.sum(axis=1, keepdims=True), 1e-300)
    inside = (pu >= 0) & (pu < n_lag)
    amp = np.bincount(pi[inside] * n_l + pl[inside], pc[inside], n_pix * n_l).reshape(n_pix, n_l)
    amp = np.maximum(amp - b * support.sum(axis=1), 1.0)
    it = 0
    while it < _EM_MAX_ITER:
        it += 1
        ratio = amp / b
        if up == 1:
            num, amp_new = _em_step(hf, ratio, pi, pl, pu, pc, reach)
        else:
            num, amp_new = _em_step_fine(hf, ratio, pi, pl, pu, pc, e, up, n_pix)
        num = num.reshape(n_l, n_f)
        for _ in range(_EM_PASSES):
            pad = np.pad(num, ((0, 0), (1, 1)))
            num = np.where(fsup, pad[:, :-2] + _EM_SMOOTH * num + pad[:, 2:], 0.0)
        new = num / np.maximum(num.sum(axis=1, keepdims=True), 1e-300)
        amp = np.maximum(amp_new, 1e-3)
        change = float(np.abs(new - hf).sum(axis=1).max())
        hf = new
        if change < _EM_TOL:
            break
    log.info(
        "IRF shape: %d soft-alignment (EM) steps on %d bright pixels, shifts +-%d bins",
        it,
        n_pix,
        reach,
    )
    # back to whole bins: the fine samples of the phase of the fine peak (point samples
    # at whole-bin distances from the mode)
    h = np.zeros((n_l, n_lag))
    for l in range(n_l):
        ph = int(np.argmax(hf[l])) % up
        g = hf[l, ph::up][:n_lag]
        h[l, : g.size] = g
    h = np.where(support, h, 0.0)
    return h, it


def shape_distance(a: np.ndarray, b: np.ndarray) -> float:
    """L1 distance between two non-negative shapes (1-D, any lengths), each scaled to unit
    sum, placed where they best correlate (the smallest L1 over the relative shifts)."""
    a = np.asarray(a, np.float64) / max(float(np.sum(a)), 1e-300)
    b = np.asarray(b, np.float64) / max(float(np.sum(b)), 1e-300)
    n = a.size + 2 * b.size
    x = np.zeros(n)
    x[b.size : b.size + a.size] = a
    best = math.inf
    for s in range(a.size + b.size - 1):  # b's first sample at x[s + 1]
        y = np.zeros(n)
        y[s + 1 : s + 1 + b.size] = b
        best = min(best, float(np.abs(x - y).sum()))
    return best


def split_halves(n_rows: int, n_cols: int) -> list[np.ndarray]:
    """Two partitions of the ``n_rows x n_cols`` image into halves, as boolean masks of
    the first half (flat, row-major): the checkerboard and alternate rows (or columns
    for a single row). Each half samples the whole image (neighbours in the other)."""
    rr, cc = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    second = rr % 2 == 0 if n_rows > 1 else cc % 2 == 0
    return [((rr + cc) % 2 == 0).ravel(), second.ravel()]
