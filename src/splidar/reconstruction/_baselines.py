"""Classification baselines for the benchmarks (issue 14): per-pixel, then a majority filter.

* :func:`per_pixel_classify`: each detected surface classified alone, as in per-pixel
  multispectral classification (MSTD-like: the spectrum of the surface's own counts,
  background subtracted, against each signature's shape; no spatial prior, no class
  proportions): the label maximising ``sum_l x_l log(m_{k,l} / sum_l m_{k,l})`` with
  ``x = max((y - b) / eta, 0)`` (:func:`splidar.reconstruction.nearest_signature`).
* :func:`majority_filter_labels`: those labels smoothed by a majority vote over each
  surface and its depth-gated 4-neighbours (the surface graph of
  :func:`splidar.reconstruction.build_graph`), repeated ``n_iter`` times; a tie keeps
  the surface's own label. The spatial filter the paper compares against.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._validation import SplidarError, check_int
from ..detection._result import Detection
from ..library import as_library
from ._core import irf_fraction, nearest_signature
from ._graph import build_graph, irf_fwhm

__all__ = ["majority_filter_labels", "per_pixel_classify"]


def _check_detection(detection) -> Detection:
    if not isinstance(detection, Detection):
        raise SplidarError(
            f"`detection` must be a splidar Detection (the output of splidar.detect); got "
            f"{type(detection).__name__}."
        )
    return detection


def per_pixel_classify(detection: Detection, library) -> np.ndarray:
    """Per-surface nearest-signature labels of a detection (no spatial prior).

    Parameters
    ----------
    detection : Detection
    library : SpectralLibrary, array (K, L) or path

    Returns
    -------
    label : ndarray (S,), int64, one per ``detection.surfaces`` entry.

    Examples
    --------
    >>> from splidar.reconstruction import synthetic_detection
    >>> det, truth = synthetic_detection(shape=(8, 8), ppp=200, rng=0)
    >>> lab = per_pixel_classify(det, det.library)
    >>> bool(np.mean(lab == truth.label) > 0.9)
    True
    """
    det = _check_detection(detection)
    s = det.surfaces
    L = det.n_wavelengths
    lib = as_library(library, n_wavelengths=L)
    S = len(s)
    if S == 0:
        return np.zeros(0, np.int64)
    y = np.asarray(s.counts, np.float64).reshape(S, L)
    b = np.asarray(s.background, np.float64).reshape(S, L)
    irf = np.atleast_2d(np.asarray(det.irf, np.float64))
    eta = np.maximum(irf_fraction(irf, s.depth_bin, s.start, s.stop), 1e-6)
    return nearest_signature((y - b) / eta, lib.signatures)


@njit(cache=True)
def _majority(indptr, indices, u, K, out):
    votes = np.zeros(K, np.int64)
    for s in range(u.size):
        votes[:] = 0
        votes[u[s]] += 1
        for e in range(indptr[s], indptr[s + 1]):
            votes[u[indices[e]]] += 1
        best = u[s]
        for k in range(K):
            if votes[k] > votes[best]:
                best = k
        out[s] = best


def majority_filter_labels(
    detection: Detection, label: np.ndarray, *, n_iter: int = 1, depth_gate: float | None = None
) -> np.ndarray:
    """Majority vote of each surface's label with its depth-gated 4-neighbours.

    Parameters
    ----------
    detection : Detection
        Gives the surfaces' pixels, layers and depths.
    label : ndarray (S,), int
    n_iter : int
        Passes of the filter (>= 1).
    depth_gate : float, optional
        Depth gate in bins (default 3 x the widest IRF FWHM, as ``reconstruct``).

    Returns
    -------
    label : ndarray (S,), int64

    Examples
    --------
    >>> from splidar.reconstruction import synthetic_detection
    >>> det, truth = synthetic_detection(shape=(8, 8), ppp=200, rng=0)
    >>> noisy = truth.label.copy(); noisy[10] = (noisy[10] + 1) % 3
    >>> int(majority_filter_labels(det, noisy)[10] == truth.label[10])
    1
    """
    det = _check_detection(detection)
    s = det.surfaces
    u = np.array(label, dtype=np.int64)  # a copy: the passes below write into it
    if u.shape != (len(s),):
        raise SplidarError(
            f"`label` must be ({len(s)},), one per detected surface; got shape {u.shape}."
        )
    n_iter = check_int(n_iter, "n_iter", minimum=1)
    if u.size == 0:
        return u.copy()
    if np.min(u) < 0:
        raise SplidarError(f"`label` must be >= 0; got min {int(np.min(u))}.")
    gate = 3.0 * float(irf_fwhm(det.irf).max()) if depth_gate is None else float(depth_gate)
    g = build_graph(
        s.row, s.col, s.slot, s.depth_bin, s.image_shape, int(s.n_slots), links="depth", gate=gate
    )
    K = int(u.max()) + 1
    out = np.empty_like(u)
    for _ in range(n_iter):
        _majority(g.indptr, g.indices, u, K, out)
        u, out = out, u
    return u
