"""Stage 1: the background's temporal shape ``bbar_{l,t}`` (``eq:background_1``).

The per-pixel level ``b_{n,l}`` (``eq:background_2``) needs the coarsest box of every
pixel; it is computed by the saliency kernel during the map pass (stage 4), block by
block, so that no dense background cube is ever formed. Stage 1 only fixes the shape in
time that every pixel shares (robust to returns in up to 90 % of the pixels, see
:func:`~splidar.detection._background.temporal_shape`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._background import temporal_shape
from ._filters import Correlator, irf_halfwidth

__all__ = ["TemporalBackground", "estimate_temporal_background"]


@dataclass(frozen=True)
class TemporalBackground:
    """The background's shape in time.

    Attributes
    ----------
    temporal : ndarray (L, T)
        ``bbar_{l,t}``, counts per bin on the matched-filtered scale.
    dev : ndarray (L, T), float32
        ``bbar_{l,t} - mean_t bbar_{l,t}``: what ``eq:background_3`` adds to a pixel's level.
    """

    temporal: np.ndarray
    dev: np.ndarray


def estimate_temporal_background(
    counts, corr: Correlator, irf: np.ndarray, *, box: int, n_jobs: int, windows=None
) -> TemporalBackground:
    """``bbar`` from the coarsest box (size ``box``) of the matched-filtered counts.

    Parameters
    ----------
    counts : array_like (rows, cols, L, T)
    corr : Correlator
        The matched filter ``Y (*) g``.
    irf : ndarray (L, n_irf), float64
        Normalised IRF (its matched-filter half-width sets the smoothing, ``4 w + 1`` bins).
    box : int
        The largest box size ``max k_q``.
    n_jobs : int
        Threads.
    windows : callable, optional
        Reads the sampled window means (a Dask cube: on its workers); see
        :func:`~splidar.detection._background.temporal_shape`.
    """
    wh = irf_halfwidth(irf)
    temporal = temporal_shape(counts, corr, box, smooth=4 * wh + 1, workers=n_jobs, windows=windows)
    dev = (temporal - temporal.mean(axis=-1, keepdims=True)).astype(np.float32)
    return TemporalBackground(temporal=temporal, dev=dev)
