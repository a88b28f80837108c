"""Stage 5e (clean-up): restore the candidates of holes that a surface encloses.

An empty pixel whose both opposite pairs of 4-neighbours hold the surface at a
candidate's depth, and whose local scale is significant, keeps that candidate even with
no own photons there (:func:`~splidar.detection._quality.restore_enclosed`). Runs after
the slope recovery (5d), which grows from such holes.
"""

from __future__ import annotations

import time

from ._quality import restore_enclosed
from ._table import CandidateTable, PassResult, skipped, with_keep

__all__ = ["restore_enclosed_holes"]


def restore_enclosed_holes(
    table: CandidateTable, *, fwhm: float, z_level: float, max_kept: int, llr_level: float
) -> PassResult:
    """Restore enclosed candidates (``presence_z``; ``presence_secondary`` beside a kept one).

    Parameters
    ----------
    table : CandidateTable
    fwhm : float
        The IRF's FWHM (bins).
    z_level : float
        Significance the local scale needs (``presence_z``).
    max_kept : int
        ``K_s``: a pixel already full gets nothing.
    llr_level : float
        Log-likelihood ratio the own counts must give a pixel's further surface.
    """
    if not table.keep.size or table.keep.all():
        return skipped("enclosed", table)
    t0 = time.perf_counter()
    enc = restore_enclosed(
        table.view(),
        table.keep,
        fwhm=fwhm,
        z_level=z_level,
        max_kept=max_kept,
        llr_level=llr_level,
    )
    return with_keep("enclosed", table, table.keep | enc, t0)
