"""Stage 7 (clean-up): depths moved onto a neighbouring surface's or region's plane.

One stage, two families of rules that do one job: a surface whose depth its neighbours
place elsewhere moves there where its own counts favour it. Session 22's ablation
(benchmarks/README.md, "abl30, session 22") found them overlapping: without both, F_true
falls 2.2 times the sum of each left out alone (-0.0065 against -0.0029). They run in
this order, each on the depths the previous left:

1. ``"align_depths"`` (:func:`~splidar.detection._7a_align_depths.aligned_depths`): the
   sheared 3 x 3 pool of the 4-neighbours' plane (first round only), then the far
   depths that the 4-neighbours' plane or one side's extrapolation place elsewhere;
2. ``"edge_bands"`` (:func:`~splidar.detection._7b_edge_bands.band_depths`): the bands
   beside depth edges labelled jointly between two regions (a Potts field solved by a
   minimum cut), then a region's members off its plane (near depths) and lone far depths
   inside a region.

The rules decide depths only (and move the supports of the depths that left them); the
moved surfaces' window, histograms, signal, selected scale, presence statistics,
``saliency_mass`` and ``evidence`` follow once per round, after the last family
(``_depth_fields``): the same fields as following them after each family
(``tests/test_depths.py``). The families run in rounds (:data:`ROUNDS`), each on the
depths and fields the previous round left, until a round moves no depth: what one family
moves gives the other new neighbours, which one pass of each in turn never saw.

A later round recomputes only what the previous round's moves changed, with the same
result to the bit: the bands' own-count likelihoods (per pixel and depth,
``_7b_edge_bands._likelihoods``) and the far rule's scores (per candidate, keyed by
every input of its score, ``_7a_align_depths._memo_far_scores``) are kept over the rounds
and read back where their inputs are equal. The rules' global parts are recomputed in
every round: the bands' Potts weight and the near and far-inside priors are fractions
over the whole image, and the regions' planes (reach twice the largest box's
half-width) are within reach of a first-round move at 99 % of the face file's pixels
(benchmarks/README.md, "rnd36, session 24").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np

from ._7a_align_depths import aligned_depths
from ._7b_edge_bands import LikelihoodMemo, band_depths
from ._depth_fields import _support_fields, _window_fields, follow_supports
from ._result import STAGES, Surfaces

__all__ = ["ROUNDS", "RULES", "DepthPlacement", "place_depths"]

#: The rule families of stage 7, in the order they run (``passes`` entries and
#: ``STAGES`` names: ``Detection.provenance`` and ``Surfaces.moved_by`` say which moved a
#: surface).
RULES = ("align_depths", "edge_bands")
#: Rounds of the families at most: a round runs every family and follows the moved
#: surfaces' fields; the next round starts from its depths, until a round moves no
#: depth. One family's moves give the other new neighbours and planes (a band moved
#: onto its region's plane leaves a lone far depth beside it with 4-neighbours that
#: agree; a far depth moved joins a region). The sheared pool runs in the first round
#: only: run again on a wide IRF (the measured irf-sample pulse, FWHM about 15 bins) it
#: cost true surfaces (F_true lower on 17 of 36 such cubes, higher on 10), where the far
#: rules and the bands alone in the later rounds raise it on 16 and lower it on 4 (the
#: pool re-run only beside the previous round's moves: 13 higher, 14 lower). Two rounds:
#: issue #15's single-surface cells (seeds 0-2) 92.3 / 119.7 false surfaces with one,
#: 90.3 / 116.7 with two, 90.3 / 116.3 with three; on the measured files the rounds do
#: not settle (5 rounds on the face, tower and Art, each moving a few surfaces more) and
#: stage 7 took 3.5 times one round's time with 5 (face 3.0 -> 10.5 s). Measured
#: (benchmarks/README.md, "mrg31, session 23").
ROUNDS = 2


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
        Per rule family that ran, its seconds (all rounds); the fields' following
        counted with the last family that ran.
    rounds : int
        The rounds run (:data:`ROUNDS` at most; 0 when no family ran).
    """

    surfaces: Surfaces
    moved: MappingProxyType
    beta: float
    seconds: MappingProxyType
    rounds: int


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
    overwrite: bool = False,
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
        Which of :data:`RULES` run (in :data:`RULES`' order whatever this order), in
        rounds (:data:`ROUNDS`) until a round moves no depth.
    n_jobs : int
        Threads for the planes, likelihoods and fields (never changes the result).
    overwrite : bool
        Write the moved surfaces' histograms into ``surfaces.histograms`` itself (the
        input's array changes) instead of a copy of the ``(S, Q, L, W)`` array: for a
        caller that holds no other use of it (``detect``; the same result).

    Returns
    -------
    DepthPlacement
    """
    unknown = set(rules) - set(RULES)
    if unknown:
        raise ValueError(f"unknown rules {sorted(unknown)}; known: {RULES}")
    s = surfaces
    code = np.full(len(s), -1, np.int8) if s.moved_by is None else np.array(s.moved_by)
    moved: dict = {}
    seconds: dict = {}
    beta, rounds = float("nan"), 0
    half = int(np.max(scales)) // 2
    # what the rules computed in earlier rounds, read back where the inputs are the same
    ll_memo = LikelihoodMemo()  # the bands' own-count likelihoods, per (pixel, depth)
    far_memo: dict = {}  # the far rule's scores, per candidate's inputs
    while rounds < ROUNDS:
        rounds += 1
        before = np.array(s.depth_bin, np.float64)
        refit, moved_any = np.zeros(0, np.int64), np.zeros(0, np.int64)
        for rule in (r for r in RULES if r in rules):
            t0 = time.perf_counter()
            at = np.asarray(s.depth_bin, np.float64)
            if rule == "align_depths":
                s, support, now = aligned_depths(
                    s, fwhm=fwhm, irf=irf, counts=counts, background=background,
                    shear=rounds == 1, memo=far_memo, n_jobs=n_jobs,
                )  # fmt: skip
            else:
                depth, now, beta = band_depths(
                    s, counts, background, fwhm=fwhm, irf=irf, half=half, n_jobs=n_jobs,
                    memo=ll_memo,
                )  # fmt: skip
                s = follow_supports(replace(s, depth_bin=depth), now, at, counts, background)
                support = now
            code[now] = STAGES.index(rule)
            refit, moved_any = np.union1d(refit, support), np.union1d(moved_any, now)
            moved[rule] = np.union1d(moved.get(rule, np.zeros(0, np.int64)), now)
            seconds[rule] = seconds.get(rule, 0.0) + time.perf_counter() - t0
            last = rule
        if not moved:
            break
        t0 = time.perf_counter()
        s = _fields(
            s, moved_any, refit, counts, background, scales, irf, saliency, threshold, n_jobs,
            overwrite,
        )  # fmt: skip
        seconds[last] += time.perf_counter() - t0
        if np.array_equal(np.asarray(s.depth_bin, np.float64), before):
            break
    s = replace(s, moved_by=code)
    n_moved = MappingProxyType({r: int(m.size) for r, m in moved.items()})
    return DepthPlacement(s, n_moved, beta, MappingProxyType(seconds), rounds if moved else 0)


def _fields(
    s, moved, refit, counts, background, scales, irf, saliency, threshold, n_jobs, overwrite
):
    """The window fields of the surfaces ``moved`` at their depths (a new window for those
    in ``refit``, whose support moved; the presence statistics alone for the others) and
    the ``saliency_mass`` and ``evidence`` of ``refit`` over their supports."""
    idx = np.union1d(moved, refit)
    if not idx.size:
        return s
    s = _window_fields(
        s, idx, np.isin(idx, refit), counts, background, scales, irf, n_jobs=n_jobs,
        overwrite=overwrite,
    )  # fmt: skip
    return _support_fields(s, refit, saliency, threshold)
