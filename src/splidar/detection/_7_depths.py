"""Stage 7 (clean-up): depths moved onto a neighbouring surface's or region's plane.

One stage, two families of rules that do one job: a surface whose depth its neighbours
place elsewhere moves there where its own counts favour it. Session 22's ablation
(benchmarks/README.md, "abl30, session 22") found them overlapping: without both, F_true
falls 2.2 times the sum of each left out alone (-0.0065 against -0.0029). They run in
this order, each on the depths the previous left:

1. ``"align_depths"`` (:func:`~splidar.detection._7a_align_depths.aligned_depths`): the
   sheared 3 x 3 pool of the 4-neighbours' plane, then the far depths that the
   4-neighbours' plane or one side's extrapolation place elsewhere;
2. ``"edge_bands"`` (:func:`~splidar.detection._7b_edge_bands.band_depths`): the bands
   beside depth edges labelled jointly between two regions (a Potts field solved by a
   minimum cut), then a region's members off its plane (near depths) and lone far depths
   inside a region.

The rules decide depths only (and move the supports of the depths that left them); the
moved surfaces' window, histograms, signal, selected scale, presence statistics,
``saliency_mass`` and ``evidence`` follow once, after the last rule
(``_depth_fields``): the same fields as following them after each family
(``tests/test_depths.py``), one read of the moved pixels fewer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np

from ._7a_align_depths import aligned_depths
from ._7b_edge_bands import band_depths
from ._depth_fields import _support_fields, _window_fields, follow_supports
from ._result import STAGES, Surfaces

__all__ = ["RULES", "DepthPlacement", "place_depths"]

#: The rule families of stage 7, in the order they run (``passes`` entries and
#: ``STAGES`` names: ``Detection.provenance`` and ``Surfaces.moved_by`` say which moved a
#: surface).
RULES = ("align_depths", "edge_bands")


@dataclass(frozen=True)
class DepthPlacement:
    """Stage 7's result.

    Attributes
    ----------
    surfaces : Surfaces
        The surfaces with their depths placed and the moved ones' fields following;
        ``moved_by`` holds the index in ``STAGES`` of the last rule family that moved a
        surface.
    moved : Mapping[str, int]
        Per rule family that ran (:data:`RULES`), the surfaces whose depth it changed.
    beta : float
        The Potts weight of the bands' labelling (nats; NaN when ``"edge_bands"`` did not
        run).
    seconds : Mapping[str, float]
        Per rule family that ran, its seconds; the fields' following counted with the
        last family that ran.
    """

    surfaces: Surfaces
    moved: MappingProxyType
    beta: float
    seconds: MappingProxyType


def place_depths(
    surfaces: Surfaces,
    *,
    counts,
    background,
    fwhm: float,
    irf,
    scales,
    saliency=None,
    threshold=None,
    rules=RULES,
    n_jobs: int = 1,
) -> DepthPlacement:
    """Stage 7: the depths of ``surfaces`` re-decided by the rule families ``rules`` (see
    the module).

    Parameters
    ----------
    surfaces : Surfaces
        After stage 6 (at most ``K_s`` per pixel, in depth order).
    counts : array_like (rows, cols, L, T)
        The cube's raw counts (NumPy, Dask or Zarr-backed Dask).
    background : Background
        The detection's background (``Background.at``).
    fwhm : float
        The IRF's FWHM (bins).
    irf : ndarray (L, n_irf)
        The normalised IRF.
    scales : ndarray (Q,) int
        ``Detection.scales``: the bands' reach is the largest box's half-width, and a
        moved surface's clean histograms are recomputed with them.
    saliency, threshold : optional
        ``Detection.saliency`` and ``.threshold``: a surface whose support moved has its
        ``saliency_mass`` and ``evidence`` summed over the new support.
    rules : sequence of str
        Which of :data:`RULES` run (in :data:`RULES`' order whatever this order).
    n_jobs : int
        Threads for the planes, likelihoods and fields (never changes the result).

    Returns
    -------
    DepthPlacement
    """
    unknown = set(rules) - set(RULES)
    if unknown:
        raise ValueError(f"unknown rules {sorted(unknown)}; known: {RULES}")
    s = surfaces
    code = np.full(len(s), -1, np.int8) if s.moved_by is None else np.array(s.moved_by)
    refit, moved_any = np.zeros(0, np.int64), np.zeros(0, np.int64)
    n_moved, seconds, beta = {}, {}, float("nan")
    for rule in (r for r in RULES if r in rules):
        t0 = time.perf_counter()
        before = np.asarray(s.depth_bin, np.float64)
        if rule == "align_depths":
            s, support, moved = aligned_depths(
                s, fwhm=fwhm, irf=irf, counts=counts, background=background
            )
        else:
            depth, moved, beta = band_depths(
                s, counts, background, fwhm=fwhm, irf=irf, half=int(np.max(scales)) // 2,
                n_jobs=n_jobs,
            )  # fmt: skip
            s = follow_supports(replace(s, depth_bin=depth), moved, before, counts, background)
            support = moved
        code[moved] = STAGES.index(rule)
        refit = np.union1d(refit, support)
        moved_any = np.union1d(moved_any, moved)
        n_moved[rule] = int(moved.size)
        seconds[rule] = time.perf_counter() - t0
        last = rule
    if n_moved:
        t0 = time.perf_counter()
        s = _fields(
            s, moved_any, refit, counts, background, scales, irf, saliency, threshold, n_jobs
        )
        seconds[last] += time.perf_counter() - t0
    s = replace(s, moved_by=code)
    return DepthPlacement(s, MappingProxyType(n_moved), beta, MappingProxyType(seconds))


def _fields(s, moved, refit, counts, background, scales, irf, saliency, threshold, n_jobs):
    """The window fields of the surfaces ``moved`` at their depths (a new window for those
    in ``refit``, whose support moved; the presence statistics alone for the others) and
    the ``saliency_mass`` and ``evidence`` of ``refit`` over their supports."""
    idx = np.union1d(moved, refit)
    if not idx.size:
        return s
    s = _window_fields(s, idx, np.isin(idx, refit), counts, background, scales, irf, n_jobs=n_jobs)
    return _support_fields(s, refit, saliency, threshold)
