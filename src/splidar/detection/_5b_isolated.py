"""Stage 5b (clean-up): remove isolated candidates that their own counts do not show.

A candidate that no neighbour shares at its depth got no support from the spatial
pooling; it is kept only when its own counts are significant by themselves at the
surface level (:func:`~splidar.detection._quality.reject_isolated`). A candidate beside a
spread that stage 5a's line test rejected at its depth (column ``line_support``) had
that support from the pooling all the same: it is not tested.
"""

from __future__ import annotations

import time

import numpy as np

from ._quality import reject_isolated
from ._table import CandidateTable, PassResult, skipped, with_keep

__all__ = ["remove_isolated"]


def remove_isolated(table: CandidateTable, *, fwhm: float, pfa: float, n_bins: int) -> PassResult:
    """Reject kept candidates with no neighbour at their depth and weak own counts.

    Parameters
    ----------
    table : CandidateTable
    fwhm : float
        The IRF's FWHM (bins).
    pfa : float
        ``surface_pfa``: the chance a background-only pixel shows such a count.
    n_bins : int
        T.
    """
    if not table.keep.any():
        return skipped("isolated", table)
    t0 = time.perf_counter()
    iso = reject_isolated(table.view(), table.keep, fwhm=fwhm, pfa=pfa, n_bins=n_bins)
    if "line_support" in table.columns:
        iso &= ~np.asarray(table.columns["line_support"], bool)
    return with_keep("isolated", table, table.keep & ~iso, t0)
