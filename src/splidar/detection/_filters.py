"""Linear filters of the detection stage: temporal matched filter and spatial box filters.

Both are linear and commute (ALGORITHM-NOTES): the cube is correlated with the IRF once
per wavelength, then box-filtered at every scale.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft
from scipy import ndimage

from ._fast import correlate_direct

__all__ = ["Correlator", "box", "fisher_sums", "irf_fwhm", "irf_halfwidth", "reflect_index"]

#: Bytes of padded float32 input per FFT call of :class:`Correlator` (a few MB: in cache).
_CHUNK_BYTES = 4 << 20
#: IRFs of at most this many samples are correlated by direct summation rather than by
#: FFT. Measured (CPU time, 12 M voxels, 4 wavelengths), direct / FFT: T = 1500: 0.25
#: at 13 samples, 0.36 at 25, 0.58 at 41, 0.90 at 65, 1.25 at 101; T = 164: 0.44, 0.70,
#: 0.87, 1.23, 1.51 (``_fast.correlate_direct``).
DIRECT_MAX_TAPS = 48


class Correlator:
    """Matched filter along t: ``C[t] = sum_j g[j] Y[t - p + j]`` (``p`` = IRF peak).

    A return whose peak lands on bin ``d`` (the depth reference) gives a response that
    peaks on ``d`` (the autocorrelation of ``g`` is symmetric about lag 0). Implemented
    by direct summation in float32 for IRFs of at most :data:`DIRECT_MAX_TAPS` samples
    (cheaper than an FFT there, within a float32 step of exact), else with a padded real
    FFT (no circular wrap; mirrored edges) and the IRF spectrum precomputed. The two
    agree to float32 rounding of the response (about 1e-7 of its largest value).

    Parameters
    ----------
    irf : ndarray (L, n_irf)
        Normalised IRF; the filter keeps its sum, so a flat background keeps its level.
    n_bins : int
        T.
    """

    def __init__(self, irf: np.ndarray, n_bins: int):
        irf = np.asarray(irf, dtype=np.float64)
        L, n = irf.shape
        peak = np.argmax(irf, axis=-1)
        self.n_bins = int(n_bins)
        # the mirrored margins, left (max peak) and right (n - 1 - min peak), must not
        # overlap in the padded window: with peaks that differ between wavelengths they
        # can need more than n samples together
        margins = int(peak.max()) + int(n - 1 - peak.min())
        self.n_fft = int(sfft.next_fast_len(self.n_bins + max(n, margins), real=True))
        kern = np.zeros((L, self.n_fft))
        for l in range(L):
            m = (peak[l] - np.arange(n)) % self.n_fft
            kern[l, m] = irf[l]
        self.spectrum = sfft.rfft(kern, axis=-1).astype(np.complex64)
        self.irf = irf
        self.peak = peak
        self.direct = n <= DIRECT_MAX_TAPS and n <= self.n_bins
        self.edge_mix = None
        self.edge_mix = self._edge_mix()

    def _edge_mix(self):
        """Per wavelength and edge bin, the weight ``lam_t`` of the mirrored response in
        ``lam_t C_t + (1 - lam_t) F`` (``F``: the mean of the ``m`` counts nearest the
        edge, ``m`` = the IRF's length) that gives a flat Poisson background's response
        the interior's variance ``sum_j g_j^2``.

        Mirroring reads some counts twice near an edge: bin 0 of a Gaussian IRF of FWHM
        3 bins has 1.86 times the interior's variance (1.25 at bin 1). Both the null's
        threshold (one function of the background level for every bin, stage 3) and
        stage 1's low-quantile shape (its bias model has the interior's variance) assume
        the interior's noise, so the edge bins passed 8-11 times ``pfa`` and stage 1's
        shape dipped there (``benchmarks/README.md``, "win36"). ``F`` keeps a flat
        level's mean and spreads the weight over more counts; ``lam_t`` solves
        ``var(lam C + (1 - lam) F) = sum g^2`` exactly (no constant). ``None`` when no
        bin needs it. Returns ``((bins, lam (L, bins)), ...)`` for the left and right edge.
        """
        irf = self.irf
        L, n = irf.shape
        T = self.n_bins
        m = min(n, T)
        if T < 2 * m:
            return None
        a = (irf**2).sum(axis=1)  # (L,)
        ks = np.arange(min(T, 2 * n + 1))
        imp = np.zeros((ks.size, L, T), np.float32)
        imp[np.arange(ks.size), :, ks] = 1.0
        w = np.asarray(self(imp), np.float64)  # w[k, l, t], mirror only (edge_mix None)
        out = []
        for side in (0, 1):
            bins = np.arange(min(n, T)) if side == 0 else np.arange(T - 1, max(T - 1 - n, -1), -1)
            # by symmetry of the mirror, the right edge's weights are the left's reversed
            # for the reversed IRF: compute them directly from impulses at the right end
            if side == 1:
                imp_r = imp[:, :, ::-1]
                w_s = np.asarray(self(np.ascontiguousarray(imp_r)), np.float64)
            else:
                w_s = w
            v = (w_s[:, :, bins] ** 2).sum(axis=0)  # (L, bins)
            c = w_s[:m][:, :, bins].sum(axis=0) / m  # cov(C_t, F) per unit
            f = 1.0 / m
            qa = v - 2.0 * c + f
            qb = 2.0 * c - 2.0 * f
            qc = f - a[:, None]
            disc = np.maximum(qb * qb - 4.0 * qa * qc, 0.0)
            lam = np.where(qa > 0, (-qb + np.sqrt(disc)) / (2.0 * np.where(qa > 0, qa, 1.0)), 1.0)
            lam = np.where(v > a[:, None] * (1.0 + 1e-5), np.clip(lam, 0.0, 1.0), 1.0)
            keep = np.flatnonzero((lam < 1.0).any(axis=0))
            out.append((bins[keep], lam[:, keep]))
        if all(b.size == 0 for b, _ in out):
            return None
        return tuple(out), m

    def _mix_edges(self, x, out) -> None:
        """``lam_t C_t + (1 - lam_t) F`` in the edge bins (:meth:`_edge_mix`)."""
        (left, right), m = self.edge_mix
        T = self.n_bins
        for (bins, lam), sl in ((left, slice(0, m)), (right, slice(T - m, T))):
            if bins.size == 0:
                continue
            f = np.asarray(x[..., sl], np.float32).mean(axis=-1, dtype=np.float64)  # (..., L)
            for i, t in enumerate(bins):
                lt = lam[:, i]
                out[..., t] = (lt * out[..., t] + (1.0 - lt) * f).astype(np.float32)

    def __call__(self, y: np.ndarray, *, workers: int = 1, out=None) -> np.ndarray:
        """Correlate ``y`` (..., L, T) with the IRF; returns float32 of the same shape.

        The window is extended by mirroring (half-sample symmetric, like
        :func:`scipy.ndimage` ``mode="reflect"``) rather than with zeros, so that a
        background keeps its level up to the window edges instead of dropping there.
        ``out`` (float32, the shape of ``y``) receives the result when given.
        """
        x = np.asarray(y)
        if out is None:
            out = np.empty(x.shape, np.float32)
        if self.direct:
            correlate_direct(x, self.irf, self.peak, out, n_threads=workers)
            if self.edge_mix is not None:
                self._mix_edges(x, out)
            return out
        if x.ndim < 2 or x.shape[0] <= 1:
            self._correlate(x, out, workers)
            if self.edge_mix is not None:
                self._mix_edges(x, out)
            return out
        # chunks of rows of a few MB: the FFT temporaries stay in cache and are reused by
        # the allocator instead of being faulted in afresh for every block (each 1-D
        # transform is computed the same way whatever the chunk: identical output)
        per_row = int(np.prod(x.shape[1:-1], dtype=np.int64)) * self.n_fft * 4
        step = max(1, int(_CHUNK_BYTES // max(per_row, 1)))
        for a in range(0, x.shape[0], step):
            self._correlate(x[a : a + step], out[a : a + step], workers)
        if self.edge_mix is not None:
            self._mix_edges(x, out)
        return out

    def _correlate(self, x, out, workers: int) -> None:
        T, N = self.n_bins, self.n_fft
        n = self.irf.shape[1]
        left = int(self.peak.max())
        right = int(n - 1 - self.peak.min())
        pad = np.zeros(x.shape[:-1] + (N,), np.float32)
        pad[..., :T] = x
        if right:
            r = min(right, T)
            pad[..., T : T + r] = x[..., T - 1 : T - 1 - r : -1] if r < T else x[..., ::-1]
        if left:
            m = min(left, T)
            pad[..., N - m :] = x[..., m - 1 :: -1] if m <= T else x[..., ::-1]
        f = sfft.rfft(pad, axis=-1, workers=workers, overwrite_x=True)
        del pad
        f *= self.spectrum
        res = sfft.irfft(f, n=N, axis=-1, workers=workers, overwrite_x=True)
        del f
        np.copyto(out, res[..., :T], casting="same_kind")


def box(x: np.ndarray, k: int) -> np.ndarray:
    """Spatial mean over ``k x k`` pixels of a ``(rows, cols, T)`` float32 array.

    ``mode="reflect"`` keeps a flat background's level at the image borders.
    """
    if k == 1:
        return x
    return ndimage.uniform_filter(x, size=(k, k, 1), mode="reflect", output=np.float32)


def reflect_index(i: np.ndarray, n: int) -> np.ndarray:
    """Indices mapped into ``[0, n)`` as :func:`scipy.ndimage` ``mode="reflect"`` does."""
    m = np.mod(i, 2 * n)
    return np.where(m >= n, 2 * n - 1 - m, m)


# IRF figures shared by the stages


def fisher_sums(irf: np.ndarray) -> np.ndarray:
    """Per wavelength, ``sum_t g'(t)^2`` and ``sum_t g(t) g'(t)^2`` of the normalised IRF.

    The Fisher information of a depth ``d`` from ``n`` signal photons over a background
    of ``b`` photons per bin is ``(n G1)^2 / (n G2 + b G1)`` (matched-filter peak,
    first order), with ``G1 = sum g'^2`` and ``G2 = sum g g'^2``. A third column holds
    the second difference of the matched-filter response at its peak per unit of the
    peak value, ``2 (A(0) - A(1)) / A(0)`` (``A``: the IRF's autocorrelation), against
    which a smeared response is measured: (L, 3).
    """
    g = np.asarray(irf, np.float64)
    dg = np.gradient(g, axis=1)
    a0 = (g * g).sum(axis=1)
    a1 = (g[:, 1:] * g[:, :-1]).sum(axis=1)
    return np.stack(
        [(dg**2).sum(axis=1), (g * dg**2).sum(axis=1), 2.0 * (a0 - a1) / np.maximum(a0, 1e-300)],
        axis=1,
    )


def irf_halfwidth(irf: np.ndarray) -> int:
    """Half-width (bins) of the matched-filter response: autocorrelation >= 1e-3 of max."""
    w = 1
    for g in irf:
        ac = np.correlate(g, g, mode="full")
        keep = np.flatnonzero(ac >= 1e-3 * ac.max())
        centre = g.size - 1
        w = max(w, int(max(centre - keep[0], keep[-1] - centre)))
    return w


def irf_fwhm(irf: np.ndarray) -> float:
    out = 1.0
    for g in irf:
        above = np.flatnonzero(g >= 0.5 * g.max())
        out = max(out, float(above[-1] - above[0] + 1))
    return out
