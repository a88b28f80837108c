"""``detect``: the driver that runs the detection stages in order (see the package doc)."""

from __future__ import annotations

import logging
import os
import time
from types import MappingProxyType

import numpy as np

from .._validation import (
    SplidarError,
    check_choice,
    check_int,
    check_positive,
    check_probability,
    describe,
)
from ..cube import Cube
from ._1_background import estimate_temporal_background
from ._2_saliency import saliency_filters
from ._3_null import calibrate_null
from ._4_map import MapOptions, map_candidates
from ._5a_spill_over import remove_spill_over
from ._5b_isolated import remove_isolated
from ._5c_dark_regions import restore_dark_regions
from ._5d_slopes import recover_slope_surfaces
from ._5e_enclosed import restore_enclosed_holes
from ._6_select import select_surfaces
from ._7_align_depths import align_surface_depths
from ._filters import Correlator, irf_fwhm, irf_halfwidth
from ._result import Background, Detection, StageRecord
from ._table import skipped

__all__ = ["detect"]

logger = logging.getLogger(__name__)

_NULL_METHODS = ("empirical", "gamma")
_PRESENCE = ("auto", "adaptive", "none", "pixel")


def _check_scales(scales) -> np.ndarray:
    try:
        vals = list(scales)
    except TypeError:
        raise SplidarError(
            f"`scales` must be a sequence of positive odd integers (box sizes, e.g. (1, 3, 7, "
            f"11)); got {describe(scales)}."
        ) from None
    if not vals:
        raise SplidarError("`scales` is empty; give at least one box size, e.g. (1, 3, 7, 11).")
    out = []
    for k in vals:
        try:
            k = check_int(k, "scales")
        except SplidarError:
            raise SplidarError(
                f"`scales` must hold positive odd integers; got {describe(k)} in {vals!r}."
            ) from None
        if k < 1 or k % 2 == 0:
            raise SplidarError(
                f"`scales` must hold positive odd integers (a box has a centre pixel); got {k} "
                f"in {vals!r}. Use e.g. (1, 3, 7, 11)."
            )
        out.append(k)
    if len(set(out)) != len(out):
        raise SplidarError(f"`scales` must not repeat a box size; got {vals!r}.")
    return np.asarray(out, dtype=np.int64)


def _check_weights(weights, scales: np.ndarray) -> np.ndarray:
    q = scales.size
    if weights is None:
        # each scale contributes the same noise variance (lambda_q / k_q constant)
        return scales / scales.sum()
    try:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise SplidarError(
            f"`weights` must be {q} numbers summing to 1; got {describe(weights)}."
        ) from None
    if w.size != q:
        raise SplidarError(
            f"`weights` must have one value per scale ({q}); got {w.size} value(s). "
            "Pass weights=None for equal weights 1/Q."
        )
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise SplidarError(f"`weights` must be finite and non-negative; got {w.tolist()}.")
    if abs(w.sum() - 1.0) > 1e-6:
        raise SplidarError(
            f"`weights` must sum to 1 (lambda_q of eq:4.s1); they sum to {w.sum():.6g}. "
            "Divide them by their sum."
        )
    return w


def _check_options(
    cube, scales, weights, pfa, max_surfaces, surface_pfa, null, presence, presence_z,
    presence_llr, presence_secondary, spill_llr, isolated, slopes, split_ratio,
    min_separation, block_rows, n_jobs,
) -> dict:  # fmt: skip
    """Validated, normalised options of :func:`detect` (raises SplidarError)."""
    if not isinstance(cube, Cube):
        raise SplidarError(
            f"`cube` must be a splidar.Cube; got {describe(cube)}. Build one with "
            "splidar.Cube(counts, irf=...) or splidar.load(path)."
        )
    scales_in = _check_scales(scales)
    w_in = _check_weights(weights, scales_in)
    order = np.argsort(scales_in)
    o = dict(scales=scales_in[order], weights=w_in[order])
    o["pfa"] = check_probability(pfa, "pfa")
    o["max_surfaces"] = check_int(max_surfaces, "max_surfaces", minimum=1)
    o["surface_pfa"] = check_probability(surface_pfa, "surface_pfa")
    o["null"] = check_choice(null, "null", _NULL_METHODS)
    o["presence"] = check_choice(presence, "presence", _PRESENCE)
    o["presence_z"] = float(presence_z)
    o["presence_llr"] = check_positive(presence_llr, "presence_llr", allow_zero=True)
    o["presence_secondary"] = float(presence_secondary)
    if not isinstance(isolated, (bool, np.bool_)):
        raise SplidarError(f"`isolated` must be True or False; got {describe(isolated)}.")
    if isinstance(slopes, (bool, np.bool_)):
        slopes = "all" if slopes else False
    elif slopes not in ("holes", "weak", "all"):
        raise SplidarError(
            f'`slopes` must be "holes", "weak", "all", True (= "all") or False; got '
            f"{describe(slopes)}. Use slopes=False to switch the slope recovery off."
        )
    o["slopes"] = slopes
    if spill_llr is not None:
        spill_in = spill_llr
        try:
            spill_llr = float(spill_llr)
        except (TypeError, ValueError):
            spill_llr = float("nan")
        if not np.isfinite(spill_llr):
            raise SplidarError(
                "`spill_llr` must be a finite number (a natural-log likelihood ratio, e.g. "
                "0.0) or None to switch the spill-over check off; got "
                f"{describe(spill_in)}."
            )
    o["spill_llr"] = spill_llr
    split_ratio = float(split_ratio)
    if not 0.0 < split_ratio < 1.0:
        raise SplidarError(f"`split_ratio` must lie in (0, 1); got {split_ratio!r}.")
    o["split_ratio"] = split_ratio
    T = cube.shape[3]
    irf = np.asarray(cube.irf, dtype=np.float64)
    if irf.shape[1] > T:
        raise SplidarError(
            f"the cube's IRF ({irf.shape[1]} samples) is longer than its T = {T} bins; crop it."
        )
    o["irf"] = irf
    if min_separation is None:
        o["min_separation"] = int(np.ceil(irf_fwhm(irf)))
    else:
        o["min_separation"] = int(np.ceil(check_positive(min_separation, "min_separation")))
    o["n_jobs"] = (
        min(os.cpu_count() or 1, 4) if n_jobs is None else check_int(n_jobs, "n_jobs", minimum=1)
    )
    o["block_rows"] = None if block_rows is None else check_int(block_rows, "block_rows", minimum=1)
    return o


def detect(
    cube: Cube,
    *,
    scales=(1, 3, 7, 11),
    weights=None,
    pfa: float = 1e-3,
    max_surfaces: int = 2,
    surface_pfa: float = 0.01,
    null: str = "empirical",
    presence: str = "adaptive",
    presence_z: float = 3.0,
    presence_llr: float = 3.0,
    presence_secondary: float = 0.0,
    spill_llr: float | None = 0.0,
    isolated: bool = True,
    dark: bool = True,
    slopes: str | bool = "weak",
    min_separation: float | None = None,
    split_ratio: float = 0.5,
    refine: bool = True,
    block_rows: int | None = None,
    n_jobs: int | None = None,
    store=None,
    rng=0,
) -> Detection:
    """Multiscale saliency detection of surfaces in a photon-count cube (Algorithm 1).

    Steps: matched filter along t (``Y (*) g``, one FFT pass per wavelength), spatial
    box filters at every scale; background (``eq:background_1..3``) from the coarsest
    scale, kept factored; saliency ``S = sum_l |sum_q lambda_q Box_q(Y (*) g) - bhat|``
    (``eq:4.s1``); a threshold from a calibrated null; the binary map ``M``; per pixel,
    runs of ``M`` split between resolved peaks become candidate surfaces with their clean
    histograms at every scale (``eq:background_final``), a selected scale
    (``eq:scale_sel``) and a sub-bin depth.

    Parameters
    ----------
    cube : Cube
        Counts ``(rows, cols, L, T)`` with the IRF.
    scales : sequence of positive odd int
        Box sizes ``k_q`` (sorted ascending internally, with their weights).
    weights : array_like (Q,), optional
        ``lambda_q`` (non-negative, sum 1, in the order of ``scales``). Default
        ``lambda_q = k_q / sum k``: every scale then adds the same noise variance
        (``lambda_q^2 / k_q^2`` constant). Against the paper's ``1/Q`` on (1, 3, 7, 11),
        it raises the signal-to-noise ratio of extended surfaces 2.9-fold and lowers
        that of 1-pixel strands by 17 % (measured: F_true 0.30 -> 0.75 at PPP 1, SBR
        0.1). ``[0, 1, 0, 0]`` (the paper's real-data choice) discards the finest scale.
    pfa : float
        Probability of false alarm per voxel, in (0, 1).
    max_surfaces : int
        ``K_s``, the most surfaces kept per pixel (>= 1).
    surface_pfa : float
        Expected number of false surfaces per background-only pixel, in (0, 1). The
        voxel-level ``pfa`` lets about ``pfa x T`` noise voxels per pixel through the
        map; a candidate is kept only when its evidence (``sum max(S / threshold - 1,
        0)`` over its support) exceeds that of all but a fraction ``surface_pfa`` of the
        candidates found in the simulated null (per pixel).
    null : {"empirical", "gamma"}
        ``"empirical"`` (default): the threshold is the ``1 - pfa`` quantile of the
        saliency of background-only cubes drawn from the estimated background, as a
        function of the local background level (calibrated; varies with t and pixel
        when the background does). ``"gamma"``: the paper's gamma threshold with a
        robust (quantile-matched) fit, not calibrated.
    presence : {"auto", "adaptive", "none", "pixel"}
        Check that a candidate exists in its own pixel (coarse scales spread returns
        beside thin structures and across depth edges). ``"auto"`` (adaptive scale):
        keep a candidate when the local scale (the finest above 1 pixel, 3 x 3 by
        default) responds significantly at its depth (Poisson z >= ``presence_z``) and
        the pixel's own counts do not reject it (own-pixel log-likelihood ratio of a
        return of the local scale's intensity vs. background >= ``-presence_llr``);
        a pixel's further candidates (all but the one of largest evidence) need the
        own counts to favour them (log-ratio >= ``presence_secondary``).
        ``"adaptive"``: as ``"auto"``, but the z required is
        ``min(presence_z, z_pred - presence_z)``, where ``z_pred`` is the z a return of
        the selected scale's intensity would give at the local scale: a dim
        neighbourhood (a dark stripe), where even a true return cannot reach
        ``presence_z``, is not held to it, while a ghost beside a bright one falls far
        short of its prediction; further candidates need z >= ``presence_z`` too.
        The default: alone it raised F_true in nearly every cell of the benchmark grid
        (64 x 64, ``benchmarks/bench_detection.py``; single surface PPP 4, SBR 0.25:
        0.893 -> 0.918) but added 0.1-3.4 false surfaces per 100 true ones; the
        spill-over and isolated-candidate checks (``spill_llr``, ``isolated``) remove
        more than that (see ``spill_llr``).
        ``"pixel"``: own-pixel likelihood ratio >= 0 with the selected scale's
        intensity (strict; loses weak surfaces). ``"none"``: keep every candidate.
    presence_z : float
        Significance required of the local scale (``"auto"``, ``"adaptive"``).
    presence_llr : float
        How strongly (natural log of the likelihood ratio) the own pixel must speak
        against a return before it is rejected (``"auto"``).
    presence_secondary : float
        Log-likelihood ratio the own pixel must give a pixel's further candidates
        (``"auto"``, ``"adaptive"``). Measured on the net scene (PPP 10, SBR 1) with
        ``"auto"`` and no spill-over check: 0 -> F_true 0.955 with 0.107 false surfaces
        per true one; 0.6 -> 0.952 / 0.077; 1 -> 0.944 / 0.052. With the spill-over
        check most of those extras are caught by it and 0 is the default (64 x 64,
        seeds [0, 7], [1, 7], other options default: 1 -> 0.941 / 0.029, 0 -> 0.955 /
        0.037; single surface PPP 4, SBR 0.25: 1 -> 0.904 / 0.040, 0 -> 0.905 / 0.048).
    spill_llr : float or None
        Spill-over check (``"auto"``, ``"adaptive"``; ``None`` switches it off), run
        once on the candidates of the whole image (``_quality.py``). A candidate is the
        spread of a neighbour's return when a neighbour (8-connected) holds a candidate
        at the same depth (within the IRF's FWHM), no opposite pair of 4-neighbours
        (north/south, west/east) interpolates to its depth (the surface does not
        continue through the pixel: it lies beside a thin structure or across a depth
        edge), and its own counts give a log-likelihood ratio below ``spill_llr`` for a
        return as bright as that neighbour's own-pixel signal vs. background only
        (0: the counts favour "no return"). Repeated until nothing changes (a rejected
        candidate is no source any more, so the spread two or more pixels from its
        source is tested next). Measured (64 x 64, seeds [0, 7] and [1, 7], F_true /
        false surfaces per true one), net scene PPP 10, SBR 1: 0.955 / 0.107 without
        it, 0.955 / 0.037 with it (the old defaults "auto", ``presence_secondary=1``,
        no spill or isolated check: 0.943 / 0.057); single surface PPP 4, SBR 0.25:
        0.916 / 0.107 -> 0.905 / 0.048 (old: 0.887 / 0.078). At PPP 1 the own counts
        have little power: single surface SBR 10, 0.871 / 0.094 -> 0.843 / 0.032.
    isolated : bool
        (``"auto"``, ``"adaptive"``) A candidate that no neighbour (8-connected) shares
        at its depth (within the IRF's FWHM) gets no support from the spatial pooling:
        keep it only when its own counts n over its support (width w bins, background
        B) are significant by themselves at the surface level: ``1 - (1 - P(N >= n |
        B))^(T / w) <= surface_pfa`` (the chance that a background-only pixel shows such
        a count in any of its T / w windows). Measured (64 x 64, seeds [0, 7], [1, 7]):
        0.4-2.7 fewer false surfaces per 100 true ones for at most 0.1 % of true ones,
        except at PPP 1, SBR 10 (net scene F_true 0.687 -> 0.659, false 2.8 -> 1.9 per
        100: a single photon there is not significant on its own).
    dark : bool
        (``"auto"``, ``"adaptive"``) Dark-region pass (``_quality.rescue_dark``): a
        dim patch (low reflectivity) holds too few photons per pixel for the local
        presence test, and beside bright pixels at the same depth it looks like their
        spread, so its candidates are rejected. For each pixel left with no surface,
        its rejected candidate of largest evidence is pooled with the other such
        candidates, and the kept ones whose own counts are weak (z < ``presence_z``),
        within the largest box at the same depth (within the IRF's FWHM): it is
        restored when their own counts together are significant (Poisson, at
        ``surface_pfa``) and its own counts do not reject a return of the pool's mean
        intensity (log-ratio >= ``-presence_llr``). The spread of a neighbour puts no
        photons at its depth in the pixels it covers, so it stays rejected. Measured
        (64 x 64, 2 seeds, F_true / false surfaces per 100 true ones, off -> on): single
        surface PPP 4, SBR 0.25: 0.910 / 4.2 -> 0.923 / 4.6 (decaying background: 0.904
        / 6.3 -> 0.921 / 6.9); PPP 10, SBR 1: 0.974 / 1.2 -> 0.984 / 1.3; PPP 50, SBR 10:
        0.992 -> 0.994; net scene PPP 10, SBR 1: 0.958 / 2.7 -> 0.960 / 2.9. A pool needs
        at least 6 candidates (``_quality.MIN_POOL``): each candidate's depth sits on its
        own counts' peak, so a pool of one or two noise peaks would pass the test (pure
        background: 0.006-0.013 false surfaces per pixel without this rule, 0.003-0.008
        with it, as without the pass). Last (after the slope recovery), a pixel with
        room for a surface whose rejected candidate both opposite pairs of 4-neighbours
        enclose (kept surfaces whose mean depth is within the FWHM of it) and whose
        local scale is significant (z >= ``presence_z``) keeps it even with no own
        photons at its depth (a return of ``s`` photons leaves none with probability
        ``exp(-s)``); beside a kept surface of the pixel its own counts must favour it
        (log-ratio >= ``presence_secondary``, the rule for further surfaces: a one-pixel
        hole of a net is enclosed by the strands). ``_quality.restore_enclosed``. Full
        grid: see the changelog; the Art scene (PPP 1, 4, 10) F_true within 0.001.
    slopes : {"weak", "holes", "all"} or bool
        (``"auto"``, ``"adaptive"``) Recover surfaces on steep slopes that the square
        boxes miss (``_slopes.py``, issue #3): around each tested pixel, local planes
        are fitted (robustly) to the kept surfaces within the largest box; where a
        plane is steep (the coarsest box spreads a return over more than the IRF's
        FWHM) and encloses the pixel, the raw counts along the plane (sheared window)
        of the pixel and of its neighbours holding no surface near the plane are tested
        against the background (exact Poisson, corrected for the planes, boxes and depth
        shifts tried: ``surface_pfa`` per tested pixel), then the own counts must not
        reject the return (``presence_llr``); repeated so that the interiors of dim
        regions fill in. A recovered surface within 2 FWHM of a kept one of its pixel
        replaces it (the same return, its depth biased by the boxes) unless the own
        counts reject it against the kept one (log-likelihood ratio below the kept
        one's minus ``presence_llr``). A lazy cube is read by bands of rows where pixels
        are tested.

        - ``"weak"`` (default): the pixels left with no surface and those holding a
          surface their own counts do not confirm (own log-likelihood ratio below
          ``presence_llr``) are tested.
        - ``"holes"``: only the pixels left with no surface.
        - ``"all"`` (or ``True``): every pixel with room for a surface.
        - ``False``: no recovery.

        Measured (``benchmarks/bench_detection.py``, full grid, seed 0, every other
        pass at its default), F_true ``"holes"`` / ``"weak"`` / ``"all"``: single
        surface PPP 4, SBR 0.25: 0.963 / 0.972 / 0.973 (decaying background 0.965 /
        0.975 / 0.976); net scene PPP 10, SBR 1: 0.964 / 0.969 / 0.973 (decaying 0.942
        / 0.947 / 0.951); at least as good as the per-pixel detector on both figures in
        49 / 54 / 53 of 64 cells. ``"holes"`` -> ``"weak"``: F_true up in 49 cells and
        down in 2 (by at most 0.0007), false surfaces -18.5 per 100 true summed over the
        cells. Against no recovery (``False`` -> ``"holes"``, session 5): F_true up in 54
        of 64 cells and down in none; pure background unchanged. Cost of the pass on
        the Art-size cube (one thread): 0.015 s (``"holes"``), 0.07 s (``"weak"``, 9 %
        of its pixels tested), 1.4 s (``"all"``, the robust plane fits around every
        pixel); on ``n_jobs`` threads, results do not depend on them. On the
        200 x 200 x 4 x 1500 cube: 0.004 / 0.007 / 0.7 s.
    min_separation : float, optional
        Peaks closer than this (bins) are one surface. Default: the IRF's FWHM.
    split_ratio : float
        A run is split between two peaks when the response dips below this fraction of
        the smaller peak between them.
    refine : bool
        Adaptive depth by the intersection of confidence intervals (ICI) over the
        scales, rather than the depth of the selected scale (``eq:scale_sel``, which
        mixes neighbours' returns at depth edges and on slopes): each scale's peak gets
        a standard error from the Fisher information of its pooled signal photons over
        the pooled background (first-order matched-filter peak,
        ``(n G1)^2 / (n G2 + b G1)`` with ``G1 = sum g'^2``, ``G2 = sum g g'^2``),
        widened when the box smears the return (a response flatter than the IRF's
        autocorrelation: a slope or a crease under the box, its extra variance added as
        a bound on the bias); scales are taken finest first until one's interval
        (``+-2`` standard errors) misses the intersection of the finer ones, and the
        most precise depth among those before it is reported. A bright pixel at a depth
        edge keeps its own depth; a dim one on a smooth surface gets the pooled one.
        The own pixel takes part only when its peak is significant (z >= 3). Measured
        against the previous rule (the own pixel's depth whenever its z >= 3; 64 x 64, 10
        cells of ``benchmarks/bench_detection.py``, 2 seeds): the mean depth error fell by
        25-48 % in every cell (single surface PPP 4, SBR 0.25: 0.60 -> 0.34 bins; net
        scene PPP 10, SBR 1: 0.49 -> 0.29; PPP 50, SBR 10: 0.21 -> 0.15). ``scale_index``
        still reports ``eq:scale_sel``. Also: when a candidate's run is longer than the
        histogram window (a steep slope), the window is centred on the own pixel's
        matched-filter peak in the run if that peak is significant (z >= sqrt(9 + 2 ln
        run length), the max of that many background bins), not on the coarse peak,
        which drifts off the return beside brightness changes (single surface, PPP 50,
        SBR 10: F_true 0.980 -> 0.994). Last, on the selected surfaces, a depth that
        its 4-neighbours place elsewhere (each opposite pair holding the same return
        puts it more than the FWHM and at most 2 FWHM away, the pairs agreeing) moves to
        the own clean histogram's peak near their prediction when the own counts favour
        that peak over the current depth (``_quality.align_depths``: on a steep slope
        the 3 x 3 box has a lobe per row and a low-count peak can fall on a neighbour
        row's). Full grid (``benchmarks/bench_detection.py``, seed 0), without -> with:
        F_true up in 36 of 64 cells (by up to 0.028), down in 3 (by at most 0.005),
        false surfaces -2.2 to +1.0 per 100 true ones (summed over the cells -6.2);
        single surface PPP 4, SBR 0.25 decaying background 0.957 / 5.4 -> 0.960 / 4.4;
        the Art scene +0.0001 to +0.0002.
    block_rows : int, optional
        Rows per block (memory/time trade-off; results do not depend on it). Default:
        about 64 MB of work buffers per block, at least ``4 x max(k) // 2`` rows (halo
        rows are matched-filtered once per run of blocks, so small blocks cost little).
    n_jobs : int, optional
        Threads (default: CPU count, at most 4).
    store : str or path, optional
        A new directory in which ``saliency``, ``mask`` and a threshold varying per
        voxel are written as chunked Zarr arrays (chunks of ``block_rows`` rows) instead
        of being held in memory: for cubes whose ``(rows, cols, T)`` arrays do not fit
        in RAM (with a lazy, Zarr- or Dask-backed cube, the counts are read block by
        block too). The result then holds ``zarr`` arrays; results are identical.
        Needs the ``zarr`` package (``pip install splidar[dask]``).
    rng : None, int or Generator, default 0
        Seed of the Monte Carlo null (the background-only saliency simulated from the
        estimated background to calibrate the threshold) and of the slope recovery's
        robust plane fits. The default, a fixed seed, makes the same input give the
        same result; ``None`` draws fresh entropy (results then vary slightly between
        calls, within the null's Monte Carlo error).

    Returns
    -------
    Detection

    Raises
    ------
    SplidarError
        Not a Cube; scales not distinct positive odd integers; weights of the wrong
        length, negative or not summing to 1; pfa outside (0, 1); max_surfaces < 1;
        unknown null or presence method; an IRF longer than T; spill_llr not a finite
        number or None; isolated not a bool.

    Notes
    -----
    Departures from the paper, each measured (see the project's ALGORITHM-NOTES):

    * Background (``eq:background_1..3``) on the correlated scale, with the window
      mirrored at its edges (a flat level stays flat); the lowest-10 % median of the
      temporal shape is kept (robust to returns in up to 90 % of the pixels) but its
      low-quantile bias is simulated and removed; the spatial level is a clipped mean
      over t, not a median (unbiased at low counts).
    * The threshold is calibrated on background-only cubes drawn from the estimate
      (``null="empirical"``): the measured false-alarm rate on pure-background cubes
      stays within 2x of ``pfa`` from 0.02 to 2 photons per bin, uniform or decaying
      (``benchmarks/bench_null.py``), where the gamma tail misses by up to 100x.
    * Candidates are positive excursions only, ranked by ``evidence`` and kept when it
      beats the simulated null at ``surface_pfa`` per pixel; then the presence check.
    ``eq:depth_global`` and ``eq:depth_scale`` correlate the clean histograms with g; in
    the paper the clean histograms of ``eq:background_final`` already are ``Y (*) g``, so
    correlating again would double-filter (and bias depths for asymmetric IRFs). We take
    the argmax of the clean matched-filter response itself. Depth is then refined with
    a parabola through the peak of the selected scale's response.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar import Cube, gaussian_irf
    >>> from splidar.detection import detect
    >>> rng = np.random.default_rng(0)
    >>> g = gaussian_irf(3.0)
    >>> lam = np.full((24, 24, 1, 100), 0.05)
    >>> h = g.size // 2
    >>> for j in range(24):  # a plane tilted along the columns, depth 30 + j
    ...     lam[:, j, 0, 30 + j - h : 30 + j + h + 1] += 20 * g
    >>> det = detect(Cube(rng.poisson(lam), irf=g), rng=0)
    >>> err = det.points.depth_bin - (30 + det.points.col)
    >>> bool(np.mean(np.abs(err) < 1) > 0.95), bool(len(det.points) >= 24 * 24)
    (True, True)
    """
    t_start = time.perf_counter()
    timings = {}
    o = _check_options(
        cube, scales, weights, pfa, max_surfaces, surface_pfa, null, presence, presence_z,
        presence_llr, presence_secondary, spill_llr, isolated, slopes, split_ratio,
        min_separation, block_rows, n_jobs,
    )  # fmt: skip
    scales_arr, w, n_jobs = o["scales"], o["weights"], o["n_jobs"]
    presence, max_surfaces, surface_pfa = o["presence"], o["max_surfaces"], o["surface_pfa"]
    R, C, L, T = cube.shape
    irf, min_sep, fwhm = o["irf"], o["min_separation"], irf_fwhm(o["irf"])
    rng = np.random.default_rng(rng)
    corr = Correlator(irf, T)
    checks = presence in ("auto", "adaptive")  # the clean-up passes need the presence test

    # 1. background temporal shape (eq:background_1)
    t0 = time.perf_counter()
    bg = estimate_temporal_background(
        cube.counts, corr, irf, box=int(scales_arr.max()), n_jobs=n_jobs
    )
    # 2. multiscale statistics and saliency: the filters every block shares (eq:4.s1)
    filters = saliency_filters(corr, scales_arr, w, bg.dev, irf)
    timings["background_temporal"] = time.perf_counter() - t0

    # 3. null model and thresholds (voxel: pfa; surface: surface_pfa)
    t0 = time.perf_counter()
    nul = calibrate_null(
        cube.counts, filters, pfa=o["pfa"], surface_pfa=surface_pfa, null=o["null"],
        min_separation=min_sep, split_ratio=o["split_ratio"], rng=rng, n_jobs=n_jobs,
    )  # fmt: skip
    timings["null"] = time.perf_counter() - t0

    # 4. the 3D map and its candidate surfaces (one pass over blocks of rows)
    t0 = time.perf_counter()
    keep_suspects = bool(dark) and checks
    mp = map_candidates(
        cube.counts,
        filters,
        nul,
        MapOptions(
            min_separation=min_sep,
            split_ratio=o["split_ratio"],
            presence=presence,
            presence_z=o["presence_z"],
            presence_llr=o["presence_llr"],
            secondary_llr=o["presence_secondary"],
            refine=bool(refine),
            keep_suspects=keep_suspects,
            max_surfaces=max_surfaces,
            width=min(2 * irf_halfwidth(irf) + 1, T),
        ),
        block_rows=o["block_rows"],
        n_jobs=n_jobs,
        store=store,
    )
    timings["saliency_and_surfaces"] = time.perf_counter() - t0

    # 5. clean-up passes over the candidate table of the whole image (they need the
    # neighbours across block borders), each named for what it does
    t0 = time.perf_counter()
    table, peak = mp.candidates, np.asarray(corr.peak)
    passes = []
    if checks and o["spill_llr"] is not None:
        passes.append(
            remove_spill_over(table, irf=irf, peak=peak, fwhm=fwhm, llr_level=o["spill_llr"])
        )
    else:
        passes.append(skipped("spill_over", table))
    table = passes[-1].table
    if checks and isolated:
        passes.append(remove_isolated(table, fwhm=fwhm, pfa=surface_pfa, n_bins=T))
    else:
        passes.append(skipped("isolated", table))
    table = passes[-1].table
    if keep_suspects:
        passes.append(
            restore_dark_regions(
                table,
                irf=irf,
                peak=peak,
                fwhm=fwhm,
                half=int(scales_arr.max()) // 2,
                pfa=surface_pfa,
                llr_level=-o["presence_llr"],
            )  # fmt: skip
        )
    else:
        passes.append(skipped("dark_regions", table))
    table = passes[-1].table.without("own_counts", "own_background")
    if o["slopes"] and checks:
        passes.append(
            recover_slope_surfaces(
                table,
                cube.counts,
                saliency=mp.saliency,
                threshold=mp.threshold,
                spatial=mp.spatial,
                dev=bg.dev,
                irf=irf,
                scales=scales_arr,
                width=mp.width,
                fwhm=fwhm,
                surface_pfa=surface_pfa,
                presence_llr=o["presence_llr"],
                max_surfaces=max_surfaces,
                pixels=o["slopes"],
                rng=rng,
                n_jobs=n_jobs,
            )  # fmt: skip
        )
        timings["slopes"] = passes[-1].seconds
    else:
        passes.append(skipped("slopes", table))
    table = passes[-1].table
    if keep_suspects:
        passes.append(
            restore_enclosed_holes(
                table,
                fwhm=fwhm,
                z_level=o["presence_z"],
                max_kept=max_surfaces,
                llr_level=o["presence_secondary"],
            )  # fmt: skip
        )
    else:
        passes.append(skipped("enclosed", table))
    table = passes[-1].table

    # 6. the surfaces: K_s per pixel
    t_sel = time.perf_counter()
    surfaces = select_surfaces(
        table, mp.histograms, max_surfaces=max_surfaces, n_scales=scales_arr.size,
        n_wavelengths=L, width=mp.width,
    )  # fmt: skip
    n_kept = int(table.keep.sum())
    t_sel = time.perf_counter() - t_sel
    # 7. depths that the 4-neighbours and the own counts place elsewhere move
    n_aligned, t_align, ran_align = 0, 0.0, False
    if refine and checks and len(surfaces):
        aligned = align_surface_depths(surfaces, fwhm=fwhm)
        surfaces, n_aligned = aligned.surfaces, aligned.n_moved
        t_align, ran_align = aligned.seconds, True
    provenance = (
        StageRecord(
            "map", True, int(mp.candidates.keep.sum()), mp.n_rejected,
            seconds=timings["saliency_and_surfaces"],
        ),
        *(StageRecord(p.name, p.ran, p.added, p.removed, seconds=p.seconds) for p in passes),
        StageRecord("select", True, 0, n_kept - len(surfaces), seconds=t_sel),
        StageRecord("align_depths", ran_align, 0, 0, n_aligned, t_align),
    )  # fmt: skip
    timings["quality_and_selection"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    by_name = {p.name: p for p in passes}
    n_spill, n_isolated = by_name["spill_over"].removed, by_name["isolated"].removed
    n_dark = by_name["dark_regions"].added + by_name["enclosed"].added
    options = MappingProxyType(
        dict(
            scales=tuple(int(k) for k in scales_arr),
            weights=tuple(float(x) for x in w),
            pfa=o["pfa"],
            max_surfaces=max_surfaces,
            surface_pfa=surface_pfa,
            null=o["null"],
            presence=presence,
            presence_z=o["presence_z"],
            presence_llr=o["presence_llr"],
            presence_secondary=o["presence_secondary"],
            min_separation=min_sep,
            split_ratio=o["split_ratio"],
            refine=refine,
            block_rows=mp.block_rows,
            n_jobs=n_jobs,
            store=None if store is None else str(store),
            window=mp.width,
            n_candidates=mp.n_candidates,
            n_rejected=mp.n_rejected + n_spill + n_isolated,
            spill_llr=o["spill_llr"],
            isolated=isolated,
            dark=dark,
            n_dark=n_dark,
            n_spill_over=n_spill,
            n_isolated=n_isolated,
            slopes=o["slopes"],
            n_slopes=by_name["slopes"].added,
            n_aligned=n_aligned,
        )
    )
    reduction = mp.reduction
    logger.info(
        "detect: %d surfaces in %d x %d px (%d candidates, %d rejected by evidence or presence); "
        "mask keeps "
        "%.3g%% of voxels and %.3g%% of photons; %.2f s",
        len(surfaces),
        R,
        C,
        options["n_candidates"],
        options["n_rejected"],
        100 * reduction.voxel_fraction,
        100 * reduction.photon_fraction,
        timings["total"],
    )
    return Detection(
        cube_shape=(R, C, L, T),
        irf=cube.irf,
        bin_width_ps=cube.bin_width_ps,
        wavelengths_nm=cube.wavelengths_nm,
        library=cube.library,
        scales=tuple(int(k) for k in scales_arr),
        weights=w,
        pfa=o["pfa"],
        background=Background(spatial=mp.spatial, temporal=bg.temporal.astype(np.float32)),
        saliency=mp.saliency,
        null=nul.model,
        threshold=mp.threshold,
        mask=mp.mask,
        reduction=reduction,
        surfaces=surfaces,
        timings=MappingProxyType(timings),
        options=options,
        provenance=provenance,
    )
