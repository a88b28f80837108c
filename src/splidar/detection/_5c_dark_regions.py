"""Stage 5c (clean-up): restore the candidates of dim patches, pooled.

A dim patch holds too few photons per pixel for the presence test and, beside bright
pixels at the same depth, looks like their spread. The rejected candidates of pixels
left empty are pooled with the weak kept ones at the same depth; a candidate is restored
when the pool's own counts together are significant
(:func:`~splidar.detection._quality.rescue_dark`). Then a rejected candidate at the
depth 3 of its 4-neighbours agree on inside its run (each holding that surface alone), in
a pixel with no surface, whose own counts do not reject the return there, is restored:
the neighbours pool for it what the local scale could not show; repeated while it
restores any
(:func:`~splidar.detection._5_recentre.restore_agreed`; issue #15's cells,
benchmarks/README.md "depth22, session 15").
"""

from __future__ import annotations

import time

import numpy as np

from ._5_recentre import agreed_items, restore_agreed
from ._quality import rescue_dark
from ._table import CandidateTable, PassResult, skipped, with_keep

__all__ = ["restore_dark_regions"]


def restore_dark_regions(
    table: CandidateTable,
    *,
    irf: np.ndarray,
    peak: np.ndarray,
    fwhm: float,
    half: int,
    pfa: float,
    llr_level: float,
    agreed: bool = False,
    max_kept: int = 2,
    n_jobs: int = 1,
) -> PassResult:
    """Restore rejected candidates of pixels with no surface whose pool is significant.

    Parameters
    ----------
    table : CandidateTable
    irf, peak, fwhm
        The IRF, its peak bins and FWHM.
    half : int
        Half-size of the pooling box (``max k // 2``).
    pfa : float
        ``surface_pfa``.
    llr_level : float
        The own counts must not reject the pool's return beyond this (``-presence_llr``).
    agreed : bool
        Restore too the candidates of empty pixels that 3 of their 4-neighbours agree on
        (:func:`~splidar.detection._5_recentre.restore_agreed`), repeated while it
        restores any.
    max_kept : int
        ``K_s``: those are restored in pixels with room only.
    n_jobs : int
        Threads of the pools' sums and the neighbours' agreed depths (the result does
        not depend on it).
    """
    if not table.keep.size:
        return skipped("dark_regions", table)
    t0 = time.perf_counter()
    res = rescue_dark(
        table.view(),
        table.keep,
        irf=irf,
        peak=peak,
        fwhm=fwhm,
        half=half,
        pfa=pfa,
        llr_level=llr_level,
        n_jobs=n_jobs,
    )
    keep, items = table.keep | res, None
    while agreed:  # repeated while it restores (a restored pixel is a neighbour too)
        more = restore_agreed(
            table, keep, irf=irf, peak=peak, fwhm=fwhm, llr_level=-llr_level,
            max_kept=max_kept, items=items, n_jobs=n_jobs,
        )  # fmt: skip
        if not more.any():
            break
        keep = keep | more
        items = agreed_items(table, more)  # only those pixels' outcomes can change
    return with_keep("dark_regions", table, keep, t0)
