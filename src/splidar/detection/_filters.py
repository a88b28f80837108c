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
            return correlate_direct(x, self.irf, self.peak, out, n_threads=workers)
        if x.ndim < 2 or x.shape[0] <= 1:
            self._correlate(x, out, workers)
            return out
        # chunks of rows of a few MB: the FFT temporaries stay in cache and are reused by
        # the allocator instead of being faulted in afresh for every block (each 1-D
        # transform is computed the same way whatever the chunk: identical output)
        per_row = int(np.prod(x.shape[1:-1], dtype=np.int64)) * self.n_fft * 4
        step = max(1, int(_CHUNK_BYTES // max(per_row, 1)))
        for a in range(0, x.shape[0], step):
            self._correlate(x[a : a + step], out[a : a + step], workers)
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
