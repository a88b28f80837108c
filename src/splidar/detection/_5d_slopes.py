"""Stage 5d (clean-up): recover surfaces on steep slopes that the square boxes miss.

Local planes are fitted (robustly) to the kept surfaces around the tested pixels; where
a plane is steep and encloses a pixel, the raw counts along the plane (a sheared window)
are tested against the background; a recovered surface within 2 FWHM of a kept one of
its pixel replaces it (:func:`~splidar.detection._slopes.recover_slopes`, issue #3).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ._4_map import _local_scale
from ._slopes import recover_slopes, support_sums
from ._table import CandidateTable, PassResult, skipped, stage_code

__all__ = ["SLOPE_PIXELS", "recover_slope_surfaces"]

#: Pixels the slope pass tests: "weak" (those left with no surface and those holding one
#: their own counts do not confirm), "holes" (only the empty ones) or "all". "weak"
#: against "holes": F_true up in 49 of 64 cells of the benchmark grid, down in 2 (by at
#: most 0.0007), for 0.07 s on the Art-size cube ("all": 1.4 s for +0.001). Read at call
#: time (tests and studies may set it). docs/detection.md.
SLOPE_PIXELS = "weak"


def recover_slope_surfaces(
    table: CandidateTable,
    counts,
    *,
    saliency,
    threshold,
    spatial: np.ndarray,
    dev: np.ndarray,
    irf: np.ndarray,
    scales: np.ndarray,
    width: int,
    fwhm: float,
    surface_pfa: float,
    presence_llr: float,
    max_surfaces: int,
    pixels: str | None = None,
    rng: np.random.Generator,
    n_jobs: int,
) -> PassResult:
    """Append the surfaces recovered on slopes; drop the kept ones they replace.

    Parameters
    ----------
    table : CandidateTable
        Without the ``own_counts`` / ``own_background`` columns.
    counts : array_like (rows, cols, L, T)
        Raw counts (a lazy cube is read by bands of rows where pixels are tested).
    saliency, threshold
        The map pass's, for the recovered surfaces' evidence and saliency mass.
    spatial, dev : ndarray
        Background level and temporal deviation (stage 4 and stage 1).
    irf, scales, width, fwhm
        IRF, box sizes, histogram window (bins) and the IRF's FWHM.
    surface_pfa, presence_llr, max_surfaces
        As in :func:`splidar.detect`.
    pixels : {"weak", "holes", "all"}, optional
        Which pixels are tested; default :data:`SLOPE_PIXELS`.
    rng : Generator
        One draw seeds the robust plane fits (only when the pass runs).
    n_jobs : int
        Threads (results do not depend on them).
    """
    if not table.keep.any():
        return skipped("slopes", table)
    t0 = time.perf_counter()
    keep, surf = table.keep, table.columns
    rec = recover_slopes(
        counts,
        {k: surf[k][keep] for k in ("row", "col", "depth_bin", "presence_llr")},
        spatial=spatial,
        dev=dev,
        irf=irf,
        scales=scales,
        width=width,
        fwhm=fwhm,
        surface_pfa=surface_pfa,
        presence_llr=presence_llr,
        max_surfaces=max_surfaces,
        qloc=_local_scale(scales),
        pixels=SLOPE_PIXELS if pixels is None else pixels,
        seed=int(rng.integers(2**31)),
        n_jobs=n_jobs,
    )
    n = int(rec["row"].size)
    if not n:
        return PassResult("slopes", table, 0, 0, time.perf_counter() - t0)
    rec["saliency_mass"], rec["evidence"] = support_sums(
        saliency, threshold, rec["row"], rec["col"], rec["start"], rec["stop"]
    )
    # a recovered surface replaces a kept one of its pixel within 2 FWHM of it
    # (the same return, its depth biased by the square boxes)
    keep = keep.copy()
    replaced = np.flatnonzero(keep)[rec["replaces"]]
    keep[replaced] = False
    columns = {k: np.concatenate([v, rec[k].astype(v.dtype)]) for k, v in surf.items()}
    new = replace(
        table,
        columns=columns,
        keep=np.concatenate([keep, np.ones(n, bool)]),
        origin=np.concatenate([table.origin, np.full(n, stage_code("slopes"), np.int8)]),
        # their histograms are the pass's own (block -1)
        hist_block=np.concatenate([table.hist_block, np.full(n, -1, np.int64)]),
        hist_row=np.concatenate([table.hist_row, np.arange(n, dtype=np.int64)]),
        extra_histograms=rec["histograms"],
    )
    n_replaced = int(table.keep.sum()) - int(keep.sum())
    return PassResult("slopes", new, n, n_replaced, time.perf_counter() - t0)
