"""Stage 7 (clean-up): move depths that the 4-neighbours and own counts place elsewhere.

On a steep slope the 3 x 3 box has a lobe per row and a low-count peak can fall on a
neighbour row's: a depth that both opposite pairs of 4-neighbours place 1-2 FWHM away
moves to the own clean histogram's peak near their prediction when the own counts favour
it (:func:`~splidar.detection._quality.align_depths`). Adds or removes no surface.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ._quality import align_depths
from ._result import Surfaces

__all__ = ["DepthAlignment", "align_surface_depths"]


@dataclass(frozen=True)
class DepthAlignment:
    """The surfaces with aligned depths, how many moved and the time it took."""

    surfaces: Surfaces
    n_moved: int
    seconds: float


def align_surface_depths(surfaces: Surfaces, *, fwhm: float) -> DepthAlignment:
    """Align the depths of ``surfaces`` with their 4-neighbours' (see the module)."""
    t0 = time.perf_counter()
    s = surfaces
    depth, n_moved = align_depths(
        s.row, s.col, s.slot, s.depth_bin, s.offset, s.histograms[:, 0].sum(axis=1),
        image_shape=s.image_shape, n_slots=s.n_slots, fwhm=fwhm,
    )  # fmt: skip
    out = replace(s, depth_bin=np.asarray(depth).astype(np.float64))
    return DepthAlignment(out, int(n_moved), time.perf_counter() - t0)
