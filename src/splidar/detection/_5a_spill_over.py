"""Stage 5a (clean-up): remove the spread of a neighbour's return (spill-over).

Coarse boxes spread a return into the pixels beside a thin structure or across a depth
edge. A candidate is such spread when a neighbour holds a candidate at its depth, no
opposite pair of 4-neighbours continues the surface through it, and its own counts
favour "no return" (:func:`~splidar.detection._quality.reject_spill_over`). A strip of
spread over the pixels' own surfaces does not continue itself: a pair whose members
are both such spread (further candidates whose counts reject their return below
``-PRESENCE_LLR``) encloses no further candidate. Then, given the raw counts, the spread
beside a thin structure that its own pixel cannot reject (a photon or two near the
depth) is decided on lines of pixels, pooled: the structure's line shows the return, the
candidate's parallel line and its line across reject it
(:func:`~splidar.detection._spill_lines.reject_spill_lines`).
"""

from __future__ import annotations

import time

import numpy as np

from ._quality import reject_spill_over
from ._spill_lines import reject_spill_lines
from ._table import CandidateTable, PassResult, skipped, with_keep

__all__ = ["SPILL_LLR", "remove_spill_over"]

#: A candidate beside a neighbour's return at its depth is that return's spread when its
#: own counts give a log-likelihood ratio below this for a return as bright as the
#: neighbour's (0: the counts favour "no return"). Measured, net scene PPP 10, SBR 1:
#: false surfaces per true one 0.107 -> 0.037 at equal F_true (docs/detection.md).
SPILL_LLR = 0.0


def remove_spill_over(
    table: CandidateTable,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    llr_level: float,
    vouch_level: float = -np.inf,
    counts=None,
    spatial: np.ndarray | None = None,
    dev: np.ndarray | None = None,
    half: int = 0,
    line_level: float = np.inf,
    n_jobs: int = 1,
) -> PassResult:
    """Reject the kept candidates that are a neighbour's spread; repeated to convergence.

    Parameters
    ----------
    table : CandidateTable
    irf : ndarray (L, n_irf), float64
    peak : ndarray (L,)
        The IRF's peak bin per wavelength.
    fwhm : float
        The IRF's FWHM (bins): "the same depth" is within it.
    llr_level : float
        Own-pixel log-likelihood ratio below which a candidate is spread (``spill_llr``).
    vouch_level : float
        Own-pixel log-likelihood ratio below which a neighbour that is a further
        candidate of its pixel does not enclose a further candidate (``detect`` passes
        ``-PRESENCE_LLR``; ``-inf``: the former test; see
        :func:`~splidar.detection._quality.reject_spill_over`).
    counts : array_like (R, C, L, T), optional
        Raw counts: with them (and ``spatial``, ``dev``), the line test of
        :func:`~splidar.detection._spill_lines.reject_spill_lines` runs on the candidates
        the per-pixel test keeps.
    spatial : ndarray (R, C, L), optional
        Background level ``b_{n,l}``.
    dev : ndarray (L, T), optional
        ``bbar_{l,t} - mean_t bbar_{l,t}``.
    half : int
        Half-length of the lines (``max k // 2``); 0 skips the line test.
    line_level : float
        Log-likelihood ratio at which a line shows or rejects a return (``detect``
        passes ``PRESENCE_LLR``).
    n_jobs : int
        Threads of the first pass of the per-pixel test and of the line test.

    Returns
    -------
    PassResult
        With the line test, its table has a ``line_support`` column (S,) bool: the
        kept candidates at the depth of a spread it rejected among that spread's 8
        neighbours (stage 5b counts them as shared).
    """
    if not table.keep.any():
        return skipped("spill_over", table)
    t0 = time.perf_counter()
    R, C = table.image_shape
    spill = reject_spill_over(
        table.view(),
        table.keep,
        irf=irf,
        peak=peak,
        fwhm=fwhm,
        llr_level=llr_level,
        vouch_level=vouch_level,
        max_iter=max(R, C),
        n_jobs=n_jobs,
    )
    keep = table.keep & ~spill
    if counts is not None and half > 0 and np.isfinite(line_level):
        lines = reject_spill_lines(
            table.view(),
            keep,
            counts,
            spatial=spatial,
            dev=dev,
            irf=irf,
            peak=peak,
            fwhm=fwhm,
            half=half,
            llr_level=line_level,
            n_jobs=n_jobs,
        )
        keep &= ~lines.rejected
        # the structures the spread came from keep that support (stage 5b)
        table = table.with_columns(line_support=lines.support)
    return with_keep("spill_over", table, keep, t0)
