"""Stuck (hot) pixels: a flat count level far above every neighbour's, set aside.

A SPAD pixel stuck at a high dark-count rate, or saturated by stray light, records a
level that is flat in time and orders of magnitude above its neighbours'. Pooled by
the coarse boxes into its neighbours' background (``eq:background_2``) it would reach
every pixel within a box, and through the null's simulated patches the threshold of
the whole image (one such pixel, 10^4 times the background, took F_true from 0.98 to
0.20 at PPP 2; ``benchmarks/bench_robustness.py``). A lidar researcher masks such
pixels; :func:`hot_pixels` finds them so that :func:`splidar.detect` treats them as dead
(no counts): the clean-up passes may then restore their surface from the neighbours,
as for any pixel without photons.

A pixel is hot when, summed over wavelengths, the **median** over t of its counts (a
flat level: a return, however bright, covers far fewer than half the bins) is at least
:data:`HOT_RATIO` times the mean counts per bin of its third brightest 8-neighbour
(signal included; a bright patch's corner has at least three bright neighbours, a
lone pixel none), at least :data:`HOT_MIN_LEVEL` counts per bin, and flat (its lower
quartile over t at least half its median: a return wider than half the window is not). Realistic hot
pixels (20-100 times the dark level) stay: they do not hurt the detection.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ._fast import pixel_totals

__all__ = ["HOT_MIN_LEVEL", "HOT_RATIO", "hot_pixels"]

#: A hot pixel's flat level over its third brightest neighbour's mean counts per bin.
HOT_RATIO = 1000.0
#: ... and at least this many counts per bin (its median over t, summed over L).
HOT_MIN_LEVEL = 5.0


def hot_pixels(counts: np.ndarray, *, totals: np.ndarray | None = None) -> np.ndarray:
    """Mask ``(rows, cols)`` of the stuck pixels of a cube ``(rows, cols, L, T)``.

    Reads the counts once (their totals per pixel; for a Dask array, one reduction on
    the active scheduler), or takes ``totals`` ``(rows, cols)`` float64, the counts
    summed over wavelengths and bins, when a pass that read them gave them (a Zarr
    cube's first pass: ``_tiled.first_pass``); the median over t is taken only on the
    few pixels whose total passes the ratio test.
    """
    R, C, L, T = counts.shape
    hot = np.zeros((R, C), bool)
    if R * C < 2:
        return hot
    if totals is not None:
        total = np.asarray(totals, np.float64)
    elif isinstance(counts, np.ndarray):  # one numba pass, the same values (_fast)
        total = pixel_totals(counts)
    else:
        total = counts.sum(axis=(2, 3), dtype=np.float64)
    if hasattr(total, "compute"):  # a Dask cube: one pass over its chunks
        total = total.compute()
    foot = np.ones((3, 3), bool)
    foot[1, 1] = False
    # third largest of the 8 neighbours (reflected at the image border)
    ref = ndimage.rank_filter(total, rank=-3, footprint=foot, mode="reflect")
    cand = np.flatnonzero((total >= 0.5 * HOT_RATIO * ref) & (total >= 0.5 * HOT_MIN_LEVEL * T))
    for i in cand:
        r, c = divmod(int(i), C)
        q1, level = np.percentile(np.asarray(counts[r, c], np.float64).sum(axis=0), [25, 50])
        flat = q1 >= 0.5 * level  # a wide, bright return over half the window is not
        if flat and level >= HOT_MIN_LEVEL and level >= HOT_RATIO * ref[r, c] / T:
            hot[r, c] = True
    return hot
