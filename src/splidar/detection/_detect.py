"""``detect``: the driver that runs the detection stages in order (see the package doc)."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import os
import threading
import time
from pathlib import Path
from types import MappingProxyType

import numpy as np

from .._irf_width import check_cube_irf
from .._memory import check_detect_memory, give_back, hold_freed_memory
from .._validation import (
    SplidarError,
    check_choice,
    check_int,
    check_probability,
    describe,
)
from ..cube import Cube
from . import _4_map
from ._1_background import estimate_temporal_background
from ._2_saliency import _coherence_tiles, coherent_scales, region_scales, saliency_filters
from ._3_null import calibrate_null, tail_step
from ._4_map import (
    PRESENCE_LLR,
    PRESENCE_SECONDARY,
    PRESENCE_Z,
    REFINE,
    SPLIT_RATIO,
    SPLIT_REACH,
    SPLIT_TAIL_SLACK,
    SPLIT_Z,
    MapOptions,
    map_candidates,
)
from ._5_recentre import recentre_runs
from ._5a_spill_over import SPILL_LLR, remove_spill_over
from ._5b_isolated import remove_isolated
from ._5c_dark_regions import restore_dark_regions
from ._5d_slopes import SLOPE_PIXELS, recover_slope_surfaces
from ._5e_enclosed import restore_enclosed_holes
from ._5f_stray_clusters import remove_stray_clusters
from ._5g_unlayered import remove_unlayered_seconds
from ._6_select import select_surfaces
from ._7_depths import RULES, place_depths
from ._background import first_read
from ._filters import Correlator, irf_fwhm, irf_halfwidth
from ._hot_pixels import HOT_RATIO, hot_pixels
from ._regions import merge_by_region
from ._result import Background, Detection, StageRecord, StoredHistograms
from ._slopes import kept_counts
from ._table import remove_tree, skipped, store_histograms
from ._tiled import Gathered, first_pass, is_dask, map_candidates_tiled, tiled_window_means

__all__ = ["PASSES", "detect"]

logger = logging.getLogger(__name__)

_NULL_METHODS = ("empirical", "gamma")
#: The candidate box sizes of ``scales="auto"``, weighted ``k_q / sum k``.
AUTO_SCALES = (1, 3, 7, 11)
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


#: The clean-up passes :func:`detect` can run, in the order they run (``passes``).
PASSES = (
    "recentre", "spill_over", "isolated", "dark_regions", "slopes", "enclosed", "stray_clusters",
    "unlayered", "align_depths", "edge_bands",
)  # fmt: skip


def detect(
    cube: Cube,
    *,
    scales="auto",
    weights=None,
    pfa: float = 1e-3,
    surface_pfa: float = 0.01,
    max_surfaces: int = 2,
    null: str = "empirical",
    presence: str = "adaptive",
    passes=PASSES,
    block_rows: int | None = None,
    n_jobs: int | None = None,
    store=None,
    rng=0,
) -> Detection:
    """Multiscale saliency detection of surfaces in a photon-count cube (Algorithm 1).

    A driver over named stages (``docs/detection.md``): 1. the background's temporal
    shape (``eq:background_1``); 2. matched filter, box filters at every scale and
    saliency ``S = sum_l |sum_q lambda_q Box_q(Y (*) g) - bhat|`` (``eq:4.s1``); 3. a
    threshold from a calibrated null; 4. the binary map ``M`` and its candidates (runs
    of ``M`` split between resolved peaks, clean histograms at every scale,
    ``eq:background_final``, selected scale ``eq:scale_sel``, sub-bin depth), kept when
    their evidence beats the null's and their own pixel shows them; 5. clean-up passes;
    6. at most ``K_s`` surfaces per pixel; 7. depths placed (neighbours' planes, edge bands).

    Parameters
    ----------
    cube : Cube
        Counts ``(rows, cols, L, T)`` with the IRF (its width checked once: see Cube).
    scales : "auto" or sequence of positive odd int
        Spatial pooling: box sizes ``k_q`` (sorted ascending, with their weights).
        ``"auto"`` (default): ``(1, 3, 7, 11)`` less the boxes whose neighbours share the
        pixels' depths too little to raise the signal-to-noise ratio (measured on the
        data, ``_2_saliency.coherent_scales``), per 11 x 11 window where that differs
        significantly (``region_scales``; foliage beside buildings): one run per set,
        merged per pixel (``options["scale_regions"]``); all four with ``weights`` given.
    weights : array_like (Q,), optional
        Spatial pooling: ``lambda_q`` (non-negative, sum 1, in the order of ``scales``).
        Default ``k_q / sum k``: every scale adds the same noise variance (against the
        paper's ``1/Q``: F_true 0.30 -> 0.75 at PPP 1, SBR 0.1). ``[0, 1, 0, 0]`` (the
        paper's real-data choice) discards the finest scale.
    pfa : float
        Probability of false alarm per voxel of the map, in (0, 1).
    surface_pfa : float
        Expected false surfaces per background-only pixel, in (0, 1): a candidate is
        kept when its evidence (``sum max(S / threshold - 1, 0)`` over its support)
        beats all but this fraction of the null's candidates; also the level of the
        isolated, dark-region and slope tests (beside a surface, too: docs/detection.md).
    max_surfaces : int
        ``K_s``, the most surfaces kept per pixel (>= 1).
    null : {"empirical", "gamma"}
        ``"empirical"``: the ``1 - pfa`` quantile of the saliency of background-only
        cubes drawn from the estimated background, as a function of the local level
        (calibrated). ``"gamma"``: the paper's gamma threshold (robust fit, not
        calibrated).
    presence : {"adaptive", "auto", "pixel", "none"}
        Own-pixel test of the candidates (coarse boxes spread returns beside thin
        structures and across depth edges). ``"auto"``: the local scale responds at the
        depth (z >= ``PRESENCE_Z``) and the own counts do not reject the return
        (log-ratio >= ``-PRESENCE_LLR``); a pixel's further candidates need its counts
        to favour them. ``"adaptive"``: the z required drops where a dim neighbourhood
        could not reach it. ``"pixel"``: own log-ratio >= 0 (strict). ``"none"``: no
        test. The clean-up passes run with ``"auto"`` and ``"adaptive"`` only.
    passes : sequence of str
        The clean-up passes to run, any of :data:`PASSES` (``"recentre"`` ...
        ``"edge_bands"``, run in that order; default all; ``()``: none). What each does and
        its measured gain: ``docs/detection.md`` and ``benchmarks/bench_ablation.py``.
    block_rows : int, optional
        Rows per block (default: 64 MB of buffers, all threads' at most a quarter cube); a
        Dask cube's rows per tile (Dask task) (default: square tiles of that many pixels).
    n_jobs : int, optional
        Threads (default: CPU count, at most 4). A Dask cube's tiles run on the active
        Dask scheduler instead (threads, or a ``dask.distributed.Client`` when one is
        open: ``docs/distributed.md``); ``n_jobs`` then serves the null and the
        clean-up passes, which run in the calling process.
    store : str or path, optional
        A new directory for ``saliency`` and ``mask`` as chunked Zarr arrays (cubes whose
        ``(rows, cols, T)`` arrays do not fit in RAM; needs ``pip install splidar[dask]``);
        the threshold is kept as in memory (its factors, ``ThresholdField``).
        ``block_rows``, ``n_jobs`` and ``store`` never change the result.
    rng : None, int or Generator, default 0
        Seed of the Monte Carlo null and of the slope pass's robust plane fits: the same
        input gives the same result; ``None`` draws fresh entropy.

    Returns
    -------
    Detection
        With ``provenance``: what each stage added or removed.

    Raises
    ------
    SplidarError
        An option out of its range (the message names it), or an IRF longer than T.

    Notes
    -----
    The former options ``presence_z``, ``presence_llr``, ``presence_secondary``,
    ``spill_llr``, ``split_ratio``, ``min_separation``, ``refine``, ``isolated``, ``dark``
    and ``slopes`` are constants of the stages (reasons and measurements, and the
    departures from the paper: ``docs/detection.md``, ALGORITHM-NOTES) or ``passes``.

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
    t_start, timings = time.perf_counter(), {}
    o = _check_options(cube, scales, weights, pfa, surface_pfa, max_surfaces, null, presence)
    check_detect_memory(cube, store=store)  # refuse, with the way out, before allocating
    o.update(_check_resources(passes, block_rows, n_jobs, o["presence"]))
    cube, windows, t0, sub = _stuck_pixels_first(cube, o)
    irf, T, n_jobs, rng = o["irf"], cube.shape[3], o["n_jobs"], _generator(rng, o)
    corr = Correlator(irf, T)
    # a Dask cube: the passes over every voxel run as Dask tasks (detection/_tiled.py)
    tiled = o["tiled"] = is_dask(cube.counts)
    bg, filters = _stages_1_2(cube.counts, corr, irf, o, windows)  # 1, 2
    timings["background_temporal"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    nul = calibrate_null(  # 3 (sub: data_tail's sub-grid, read by a Zarr cube's first pass)
        cube.counts, filters, pfa=o["pfa"], surface_pfa=o["surface_pfa"], null=o["null"],
        min_separation=o["min_separation"], split=_split(), rng=rng, n_jobs=n_jobs, tail_sample=sub,
    )  # fmt: skip
    timings["null"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mp, held, n_map = _map_pass(cube, filters, nul, o, store, tiled)  # 4
    timings["saliency_and_surfaces"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hists, mp = [list(mp.histograms)], dataclasses.replace(mp, histograms=())  # stage 6 empties
    out = _stages_5_to_7(cube, o, mp, held, hists, bg, corr, rng, t0, store)  # 5, 6, 7
    done, surfaces, moves, t_sel, n_kept = out
    timings["quality_and_selection"] = time.perf_counter() - t0
    if any(p.name == "slopes" and p.ran for p in done):
        timings["slopes"] = next(p.seconds for p in done if p.name == "slopes")
    provenance = _provenance(mp, n_map, n_kept, done, len(surfaces), t_sel, moves, timings)
    timings["total"] = time.perf_counter() - t_start
    return _detection(cube, o, bg, nul, mp, surfaces, provenance, timings, store)


def _split() -> tuple:
    """The split rule's constants as stage 3's null runs it (``_4_map``; read at the
    call, so that a patched module constant takes effect)."""
    return (SPLIT_RATIO, SPLIT_Z, SPLIT_REACH, SPLIT_TAIL_SLACK, _4_map.SPLIT_POOL)


def _stages_5_to_7(cube, o, mp, held, hists: list, bg, corr, rng, t0: float, store):
    """The clean-up passes (5), the selection (6) and the depths placed (7): ``(done,
    surfaces, placed, t_sel, n_kept)``. A Zarr cube's counts are read from its chunks'
    nonzero entries meanwhile, each chunk decoded once (``_slopes.kept_counts``), ahead
    on ``n_jobs`` threads from the start (while the recentring runs).
    ``hists``: ``[list of the map's per-block histograms]``, which stage 6 empties block by
    block as it gathers the surfaces' rows (``select_surfaces(release=True)``).
    For a Dask cube the calling process reuses its freed memory meanwhile
    (:func:`~splidar._memory.hold_freed_memory`: the whole image's arrays, not pages
    faulted in afresh for each)."""
    held_memory = hold_freed_memory() if o["tiled"] else contextlib.nullcontext()
    with kept_counts(cube.counts, threads=o["n_jobs"]), held_memory:
        done = _clean_up(cube, o, mp, held, hists[0], bg, corr, rng)
        return done, *_select_and_align(cube, o, mp, hists, done, t0, store, bg)


def _stages_1_2(counts, corr, irf, o: dict, windows):
    """Stage 1 (the background's temporal shape) and stage 2's filters; with
    ``scales="auto"`` those of the boxes kept by the measured coherence
    (:func:`_coherent_scales`), stage 1 then run again with the coarsest kept box, as
    ``detect(scales=<kept>)`` runs it."""
    bg = estimate_temporal_background(
        counts, corr, irf, box=int(o["scales"].max()), n_jobs=o["n_jobs"], windows=windows,
    )  # fmt: skip
    filters = saliency_filters(corr, o["scales"], o["weights"], bg.dev, irf)
    if o["auto_scales"] and _coherent_scales(counts, filters, o):
        bg = estimate_temporal_background(
            counts, corr, irf, box=int(o["scales"].max()), n_jobs=o["n_jobs"], windows=windows,
        )  # fmt: skip
        filters = saliency_filters(corr, o["scales"], o["weights"], bg.dev, irf)
    return bg, filters


def _coherent_scales(counts, filters, o: dict) -> bool:
    """``scales="auto"``: keep the scales whose boxes pool returns sharing the own pixels'
    depths (:func:`coherent_scales`), region by region (:func:`region_scales`); ``o``'s
    scales and weights updated to the largest set a region keeps (the others, in
    ``o["scale_regions"]``, run after this one: :func:`_by_region`). True when a scale
    was dropped."""
    # on the detection's threads (the saliency kernel's rows, the tables' series: the
    # same values on any number); a Zarr cube's tiles as its first pass read them
    blocks = o.pop("coherence_blocks", None)
    src = Gathered(counts, blocks) if blocks else counts
    coh = coherent_scales(src, dataclasses.replace(filters, workers=o["n_jobs"]))
    reg = region_scales(coh, counts.shape[:2])
    # recorded in Detection.options: why the boxes were kept or dropped
    o["scale_coherence"] = tuple(None if np.isnan(r) else round(float(r), 4) for r in coh.rho)
    logger.info(
        "detect: spatial coherence rho %s of boxes %s (energy z %.1f, %d pixels): scales %s",
        np.round(coh.rho, 3).tolist(), coh.scales.tolist(), coh.energy_z, coh.pixels,
        coh.scales[coh.kept].tolist(),
    )  # fmt: skip
    if len(reg.sets) > 1:
        o["scale_regions"] = reg
        logger.info(
            "detect: parts of the image keep different boxes (windows of %d px, |z| >= "
            "%.2f): %s; one run per set, merged per pixel", reg.window, reg.z,
            ", ".join(f"{coh.scales[:n].tolist()} on {int((reg.n_kept == n).sum())} px"
                      for n in reg.sets),
        )  # fmt: skip
    n = reg.sets[0]
    if n == coh.scales.size:
        return False
    o["scales"] = coh.scales[:n]
    o["weights"] = o["scales"] / o["scales"].sum()
    return True


def _generator(rng, o: dict):
    """``np.random.default_rng(rng)``; ``rng`` kept in ``o`` for the further runs of
    ``scales="auto"`` by region (:func:`_by_region`)."""
    o["rng_in"] = rng
    return np.random.default_rng(rng)


def _by_region(det: Detection, o: dict, store) -> Detection:
    """``scales="auto"`` where regions keep different boxes (``o["scale_regions"]``):
    ``det`` ran with the largest set; :func:`detect` runs again with each smaller set
    (its own null and threshold; a store's run in a subdirectory, removed once merged),
    then every pixel takes its region's result (:func:`merge_by_region`)."""
    reg = o["scale_regions"]
    runs, subs = {reg.sets[0]: det}, []
    for n in reg.sets[1:]:
        sub = None if store is None else Path(os.fspath(store)) / f"scales_{n}"
        subs.append(sub)
        runs[n] = detect(
            o["cube_in"], scales=tuple(int(k) for k in reg.scales[:n]), pfa=o["pfa"],
            surface_pfa=o["surface_pfa"], max_surfaces=o["max_surfaces"], null=o["null"],
            presence=o["presence"], passes=o["passes"], block_rows=o["block_rows"],
            n_jobs=o["n_jobs"], store=sub, rng=o["rng_in"],
        )  # fmt: skip
    # which pixel took which set: scales[:n_kept]
    record = dict(z=round(reg.z, 4), window=reg.window, n_kept=reg.n_kept)
    out = merge_by_region(runs, reg.n_kept, o["cube_counts"], record)
    for sub in subs:
        if sub is not None:
            remove_tree(sub)
    return out


def _stuck_pixels_first(cube: Cube, o: dict):
    """The cube without its stuck pixels (:func:`_without_hot_pixels`), how stage 1
    reads its windows (None: in memory), when stage 1's timing starts, and the null's
    sub-grid of the counts (``_3_null.data_tail``'s ``sample``; None: read there). A Cube built
    from arrays has its IRF's width checked first (once per Cube, warns only:
    ``splidar._irf_width.check_cube_irf``).

    A Zarr cube on Dask: the stuck-pixel totals and stage 1's window sums come from one
    pass over its chunks (``_tiled.first_pass``, timed with stage 1), the windows used
    unless pixels were masked, and the null's sub-grid of the counts with them (its stuck
    pixels set to 0 as in the cube) and, with ``scales="auto"``, the counts of
    ``coherent_scales``' tiles (``o["coherence_blocks"]``, :func:`_coherence_blocks`;
    masked likewise); any other Dask cube is reduced to its totals, then read
    again for the windows (``_tiled.tiled_window_means``). An in-memory cube of integer
    counts: the totals and the windows from one read of its counts on ``n_jobs`` threads
    (``_background.first_read``, timed with stage 1; the same values)."""
    check_cube_irf(cube)  # a Cube built from arrays: its IRF's width (warns only, once)
    t0 = time.perf_counter()
    box = int(o["scales"].max())
    if is_dask(cube.counts):
        blocks = _coherence_blocks(cube.shape, box) if o["auto_scales"] else ()
        first = first_pass(cube.counts, box, tail_step(cube.shape), blocks)
    else:
        first = first_read(cube.counts, box, o["n_jobs"])
    tail, blocks = getattr(first, "sample", None), getattr(first, "blocks", None)
    cube = _without_hot_pixels(cube, o, None if first is None else first.totals, tail, blocks)
    if blocks:
        o["coherence_blocks"] = blocks
    if first is None:  # stage 1's time alone, as before (the check reads on its own)
        t0 = time.perf_counter()
    windows = tiled_window_means if is_dask(cube.counts) else None
    if first is not None and o["hot_pixels"] == 0:
        windows = first.windows
    return cube, windows, t0, tail


def _coherence_blocks(shape: tuple, box: int) -> list:
    """The blocks ``(r0, r1, c0, c1)`` of pixels whose counts
    :func:`~splidar.detection._2_saliency.coherent_scales` reads for the boxes up to
    ``box`` (its tiles with their halo of ``box // 2``; at most about
    ``COHERENCE_VOXELS`` voxels), for a Zarr cube's first pass to read with the rest."""
    R, C, L, T = (int(v) for v in shape)
    h = int(box) // 2
    if R <= 2 * h or C <= 2 * h:
        return []
    return [
        (r0 - h, r1 + h, max(c0 - h, 0), min(c1 + h, C))
        for r0, r1, c0, c1 in _coherence_tiles(R, C, L * T, h)
    ]


def _without_hot_pixels(cube: Cube, o: dict, totals=None, sample=None, blocks=None) -> Cube:
    """The cube with its stuck pixels' counts set to 0 (``_hot_pixels``); logged, and
    counted in ``o["hot_pixels"]``. A Dask cube is checked too (one reduction over its
    chunks on the active scheduler, or the ``totals`` of a Zarr cube's first pass) and
    masked lazily, so that it gives the in-memory result; ``sample``, the counts'
    sub-grid ``[::s, ::s]`` (``s = tail_step``), and ``blocks`` (``{(r0, r1, c0, c1):
    counts[r0:r1, c0:c1]}``) have them set to 0 in place too."""
    o["hot_pixels"] = 0
    hot = hot_pixels(cube.counts, totals=totals)
    n = int(hot.sum())
    if n == 0:
        return cube
    if sample is not None:
        s = tail_step(cube.shape)
        sample[hot[::s, ::s]] = 0
    for (r0, r1, c0, c1), block in (blocks or {}).items():
        block[hot[r0:r1, c0:c1]] = 0
    if is_dask(cube.counts):
        counts = cube.counts * (~hot)[:, :, None, None]  # lazy; the counts' dtype kept
    else:
        counts = np.array(cube.counts)
        counts[hot] = 0
    where = ", ".join(f"({r}, {c})" for r, c in np.argwhere(hot)[:5]) + (" ..." if n > 5 else "")
    logger.warning(
        "detect: %d stuck (hot) pixel(s) with a flat count level over %g times their "
        "neighbours' treated as dead (no counts): %s",
        n, HOT_RATIO, where,
    )  # fmt: skip
    o["hot_pixels"] = n
    return dataclasses.replace(cube, counts=counts)


def _check_options(cube, scales, weights, pfa, surface_pfa, max_surfaces, null, presence):
    """Validated, normalised statistical options of :func:`detect` (raises SplidarError)."""
    if not isinstance(cube, Cube):
        raise SplidarError(
            f"`cube` must be a splidar.Cube; got {describe(cube)}. Build one with "
            "splidar.Cube(counts, irf=...) or splidar.load(path)."
        )
    auto = isinstance(scales, str) and scales == "auto"
    scales_in = _check_scales(AUTO_SCALES if auto else scales)
    w_in = _check_weights(weights, scales_in)
    order = np.argsort(scales_in)
    o = dict(scales=scales_in[order], weights=w_in[order], auto_scales=auto and weights is None)
    o["cube_in"] = cube  # scales="auto" by region: the further sets' runs read it
    o["pfa"] = check_probability(pfa, "pfa")
    o["max_surfaces"] = check_int(max_surfaces, "max_surfaces", minimum=1)
    o["surface_pfa"] = check_probability(surface_pfa, "surface_pfa")
    o["null"] = check_choice(null, "null", _NULL_METHODS)
    o["presence"] = check_choice(presence, "presence", _PRESENCE)
    T = cube.shape[3]
    if T < 3:
        # the background's temporal shape and a return's peak need a bin on each side
        raise SplidarError(
            f"`cube` must hold at least 3 time bins to detect returns; got T = {T}. Check the "
            "time window, the bin width and which axis is time (load's time_axis=)."
        )
    irf = np.asarray(cube.irf, dtype=np.float64)
    if irf.shape[1] > T:
        raise SplidarError(
            f"the cube's IRF ({irf.shape[1]} samples) is longer than its T = {T} bins; crop it."
        )
    o["irf"], o["fwhm"] = irf, irf_fwhm(irf)
    # peaks closer than the IRF's FWHM are one surface (the former min_separation)
    o["min_separation"] = int(np.ceil(o["fwhm"]))
    return o


def _select_and_align(cube, o, mp, hists: list, done, t0: float, store, bg):
    """Stages 6 and 7: at most ``max_surfaces`` per pixel, then the depths placed (the
    depth alignment and the bands beside depth edges, :func:`place_depths`); with the
    selection's own seconds (since ``t0``, less the clean-up passes'). Returns
    ``(surfaces, placed, t_sel, n_kept)`` (``placed``: the :class:`DepthPlacement`, or
    None when stage 7 did not run).

    With a ``store``, the surfaces' histograms are written there part by part and stay
    there (:class:`StoredHistograms`); the candidates' ones the tiles wrote are removed
    (on a thread, while stage 7 runs; done when this returns).
    The last pass's table and the candidates' histograms (``hists``, emptied) are
    released before stage 7 (``done[-1]`` keeps its counts only); stage 7 writes
    its moved surfaces' histograms into the selection's array (no other use of it)."""
    out = None if store is None else functools.partial(_stored_histograms, store)
    surfaces = select_surfaces(
        done[-1].table, hists.pop(), max_surfaces=o["max_surfaces"],
        n_scales=o["scales"].size, n_wavelengths=cube.shape[2], width=mp.width,
        histograms_out=out, release=True, n_jobs=o["n_jobs"],
    )  # fmt: skip
    n_kept = int(done[-1].table.keep.sum())
    done[-1] = dataclasses.replace(done[-1], table=None)
    remover = None
    if store is not None:
        surfaces = dataclasses.replace(surfaces, histograms=StoredHistograms(surfaces.histograms))
        # removed on a thread while stage 7 runs (many files: it waits on the disk)
        remover = threading.Thread(
            target=_remove_logged, args=(Path(os.fspath(store)) / "candidate_histograms",),
            name="splidar-remove",
        )  # fmt: skip
        remover.start()
    t_sel, placed = time.perf_counter() - t0 - sum(p.seconds for p in done), None
    give_back()  # the table's pages and the map's histograms, released
    rules = tuple(r for r in RULES if r in o["passes"])
    try:
        if rules and o["checks"] and len(surfaces):
            background = Background(spatial=mp.spatial, temporal=bg.temporal.astype(np.float32))
            placed = place_depths(
                surfaces, counts=cube.counts, background=background, fwhm=o["fwhm"],
                irf=o["irf"], scales=o["scales"], saliency=mp.saliency,
                threshold=mp.threshold, rules=rules, n_jobs=o["n_jobs"], overwrite=True,
            )  # fmt: skip
            surfaces = placed.surfaces
    finally:
        if remover is not None:
            remover.join()
    o["depth_rounds"] = 0 if placed is None else placed.rounds
    return surfaces, placed, t_sel, n_kept


def _remove_logged(path) -> None:
    """:func:`remove_tree` on the remover thread: a failure (a file system refusing to
    delete) leaves scratch files behind but not a wrong result, so it is logged as a
    warning naming the folder, instead of a traceback printed by the thread's hook."""
    try:
        remove_tree(path)
    except OSError as err:
        logger.warning(
            "detect: could not remove the candidates' scratch histograms %s (%s): "
            "delete the folder by hand; the detection is complete",
            path,
            err,
        )


def _stored_histograms(store, shape):
    """A new Zarr array ``surface_histograms`` of ``shape`` in the detection's store,
    stored raw (stage 7 writes its moved surfaces' rows in the chunk files,
    :func:`~splidar.detection._table.write_rows`)."""
    import zarr

    g = zarr.open_group(os.fspath(store), mode="r+")
    return store_histograms(g, "surface_histograms", shape, compressed=False)


def _map_pass(cube, filters, nul, o, store, tiled: bool):
    """Stage 4, the one pass over every voxel: tile by tile on the active Dask scheduler
    for a Dask cube (``_tiled.py``), else in row blocks on ``n_jobs`` threads.

    Returns the map without its candidate table, the table (compacted) in a list, and
    the number of candidates the map kept: the table goes to the clean-up passes alone,
    which release each pass's input once it has run."""
    opts = _map_options(o, cube.shape[3])
    # a Dask cube's tiles' results are gathered, then joined into one table in the
    # calling process, which reuses the pages the joined parts free (hold_freed_memory:
    # the join 0.27 s against 1.3-1.5 s for 9.6 M candidates, "Lead, session 30")
    with hold_freed_memory() if tiled else contextlib.nullcontext():
        if tiled:
            mp = map_candidates_tiled(
                cube.counts, filters, nul, opts, block_rows=o["block_rows"], store=store,
                n_jobs=o["n_jobs"],
            )  # fmt: skip
        else:
            mp = map_candidates(
                cube.counts, filters, nul, opts, block_rows=o["block_rows"],
                n_jobs=o["n_jobs"], store=store,
            )  # fmt: skip
        held = [mp.candidates.compacted(cube.shape[3])]
    n_map = int(mp.candidates.keep.sum())
    mp = dataclasses.replace(mp, candidates=None)
    give_back()  # the blocks' pages (the threads' arenas) and the table before compaction
    return mp, held, n_map


def _check_resources(passes, block_rows, n_jobs, presence: str) -> dict:
    """Validated ``passes``, ``block_rows`` and ``n_jobs``."""
    if isinstance(passes, str):
        raise SplidarError(
            f"`passes` must be a sequence of pass names, e.g. ('spill_over', 'slopes'); got "
            f"the string {passes!r}: wrap it in a tuple, e.g. passes=({passes!r},)."
        )
    try:
        names = [str(p) for p in passes]
    except TypeError:
        raise SplidarError(
            f"`passes` must be a sequence of pass names from {PASSES}; got {describe(passes)}."
        ) from None
    bad = [p for p in names if p not in PASSES]
    if bad:
        raise SplidarError(
            f"`passes` holds unknown pass name(s) {bad}; choose from {PASSES} "
            "(passes=() runs none)."
        )
    o = dict(passes=tuple(p for p in PASSES if p in names))
    # the clean-up passes work on the presence test's statistics
    o["checks"] = presence in ("auto", "adaptive")
    # rejected candidates stay in the table for the passes that may restore them
    o["keep_suspects"] = o["checks"] and bool({"recentre", "dark_regions", "enclosed"} & set(names))
    o["n_jobs"] = (
        min(os.cpu_count() or 1, 4) if n_jobs is None else check_int(n_jobs, "n_jobs", minimum=1)
    )
    o["block_rows"] = None if block_rows is None else check_int(block_rows, "block_rows", minimum=1)
    return o


def _map_options(o: dict, T: int) -> MapOptions:
    return MapOptions(
        min_separation=o["min_separation"],
        split_ratio=SPLIT_RATIO,
        presence=o["presence"],
        presence_z=PRESENCE_Z,
        presence_llr=PRESENCE_LLR,
        secondary_llr=PRESENCE_SECONDARY,
        refine=REFINE,
        keep_suspects=o["keep_suspects"],
        max_surfaces=o["max_surfaces"],
        width=min(2 * irf_halfwidth(o["irf"]) + 1, T),
    )


def _clean_up(cube, o: dict, mp, held: list, hists: tuple, bg, corr, rng) -> list:
    """Stage 5: the clean-up passes over the candidate table ``held.pop()`` of the whole
    image (they need the neighbours across block borders), in order; a pass not in
    ``passes`` (or without the presence test) is recorded as not run. Only the last
    result keeps its table: a pass's input is released once it has run (the passes
    build new arrays), so the calling process holds one table and the pass's new one."""
    irf, fwhm, peak = o["irf"], o["fwhm"], np.asarray(corr.peak)
    on = set(o["passes"]) if o["checks"] else set()
    surface_pfa, T = o["surface_pfa"], cube.shape[3]
    table, done, tiled = held.pop(), [], bool(o.get("tiled"))

    def run(name, fn):
        if tiled and name in on:  # the pages the last pass (or the map's tiles) freed
            give_back()
        res = fn(table) if name in on else skipped(name, table)
        if done:
            done[-1] = dataclasses.replace(done[-1], table=None)
        done.append(res)
        return res.table

    half = int(o["scales"].max()) // 2
    table = run("recentre", lambda t: recentre_runs(
        t, irf=irf, peak=peak, fwhm=fwhm, pfa=surface_pfa, n_bins=T,
        llr_level=PRESENCE_LLR, secondary_llr=PRESENCE_SECONDARY,
        max_kept=o["max_surfaces"], histograms=hists, scales=o["scales"],
        n_jobs=o["n_jobs"]))  # fmt: skip
    table = run("spill_over", lambda t: remove_spill_over(
        t, irf=irf, peak=peak, fwhm=fwhm, llr_level=SPILL_LLR,
        vouch_level=-PRESENCE_LLR, counts=cube.counts, spatial=mp.spatial, dev=bg.dev,
        half=half, line_level=PRESENCE_LLR, n_jobs=o["n_jobs"]))  # fmt: skip
    table = run("isolated", lambda t: remove_isolated(t, fwhm=fwhm, pfa=surface_pfa, n_bins=T))
    table = run("dark_regions", lambda t: restore_dark_regions(
        t, irf=irf, peak=peak, fwhm=fwhm, half=half, pfa=surface_pfa,
        llr_level=-PRESENCE_LLR, agreed=True, max_kept=o["max_surfaces"],
        n_jobs=o["n_jobs"]))  # fmt: skip
    table = table.without("own_counts", "own_background", "line_support")
    done[-1] = dataclasses.replace(done[-1], table=table)  # the columns dropped: released
    give_back()
    table = run("slopes", lambda t: recover_slope_surfaces(
        t, cube.counts, saliency=mp.saliency, threshold=mp.threshold, spatial=mp.spatial,
        dev=bg.dev, irf=irf, scales=o["scales"], width=mp.width, fwhm=fwhm,
        surface_pfa=surface_pfa, presence_llr=PRESENCE_LLR, max_surfaces=o["max_surfaces"],
        rng=rng, n_jobs=o["n_jobs"]))  # fmt: skip
    table = run("enclosed", lambda t: restore_enclosed_holes(
        t, fwhm=fwhm, z_level=PRESENCE_Z, max_kept=o["max_surfaces"],
        llr_level=PRESENCE_SECONDARY))  # fmt: skip
    table = run("stray_clusters", lambda t: remove_stray_clusters(t, fwhm=fwhm, half=half))
    run("unlayered", lambda t: remove_unlayered_seconds(
        t, fwhm=fwhm, half=half, surface_pfa=surface_pfa, level=PRESENCE_LLR))  # fmt: skip
    return done


def _provenance(mp, n_map, n_kept, done, n_surfaces, t_sel, moves, timings) -> tuple:
    placed = moves  # stage 7: one record per rule family (RULES)
    ran = {} if placed is None else placed.moved
    secs = {} if placed is None else placed.seconds
    return (
        StageRecord(
            "map", True, n_map, mp.n_rejected,
            seconds=timings["saliency_and_surfaces"],
        ),
        *(StageRecord(p.name, p.ran, p.added, p.removed, p.moved, p.seconds) for p in done),
        StageRecord("select", True, 0, n_kept - n_surfaces, seconds=max(t_sel, 0.0)),
        *(StageRecord(r, r in ran, 0, 0, ran.get(r, 0), secs.get(r, 0.0)) for r in RULES),
    )  # fmt: skip


def _detection(cube, o, bg, nul, mp, surfaces, provenance, timings, store) -> Detection:
    R, C, L, T = cube.shape
    rec = {r.stage: r for r in provenance}
    passes = o["passes"]
    options = MappingProxyType(
        dict(
            scales=tuple(int(k) for k in o["scales"]),
            weights=tuple(float(x) for x in o["weights"]),
            pfa=o["pfa"],
            max_surfaces=o["max_surfaces"],
            surface_pfa=o["surface_pfa"],
            null=o["null"],
            presence=o["presence"],
            presence_z=PRESENCE_Z,
            presence_llr=PRESENCE_LLR,
            presence_secondary=PRESENCE_SECONDARY,
            min_separation=o["min_separation"],
            split_ratio=SPLIT_RATIO,
            split_z=SPLIT_Z,
            split_reach=SPLIT_REACH,
            split_tail_slack=SPLIT_TAIL_SLACK,
            split_coherent=_4_map.SPLIT_COHERENT,
            refine=REFINE,
            block_rows=mp.block_rows,
            n_jobs=o["n_jobs"],
            store=None if store is None else str(store),
            # a Dask cube: splidar.reconstruct runs on overlapping strips of rows as well
            dask=is_dask(cube.counts),
            window=mp.width,
            n_candidates=mp.n_candidates,
            n_rejected=mp.n_rejected + rec["spill_over"].removed + rec["isolated"].removed,
            spill_llr=SPILL_LLR if "spill_over" in passes else None,
            isolated="isolated" in passes,
            dark="dark_regions" in passes,
            n_dark=rec["dark_regions"].added + rec["enclosed"].added,
            n_spill_over=rec["spill_over"].removed,
            n_isolated=rec["isolated"].removed,
            slopes=SLOPE_PIXELS if "slopes" in passes else False,
            n_slopes=rec["slopes"].added,
            n_aligned=rec["align_depths"].moved,
            n_edge_bands=rec["edge_bands"].moved,
            depth_rounds=o.get("depth_rounds", 0),  # stage 7's rounds (_7_depths.ROUNDS)
            hot_pixels=o["hot_pixels"],
            passes=passes,
            # scales="auto": each candidate box's measured coherence rho (None for 1)
            scales_auto=o["auto_scales"],
            scale_coherence=o.get("scale_coherence"),
        )
    )
    red = mp.reduction
    logger.info(
        "detect: %d surfaces in %d x %d px (%d candidates, %d rejected by evidence or "
        "presence); mask keeps %.3g%% of voxels and %.3g%% of photons; %.2f s",
        len(surfaces), R, C, options["n_candidates"], options["n_rejected"],
        100 * red.voxel_fraction, 100 * red.photon_fraction, timings["total"],
    )  # fmt: skip
    det = Detection(
        cube_shape=(R, C, L, T),
        irf=cube.irf,
        bin_width_ps=cube.bin_width_ps,
        wavelengths_nm=cube.wavelengths_nm,
        library=cube.library,
        scales=tuple(int(k) for k in o["scales"]),
        weights=o["weights"],
        pfa=o["pfa"],
        background=Background(spatial=mp.spatial, temporal=bg.temporal.astype(np.float32)),
        saliency=mp.saliency,
        null=nul.model,
        threshold=mp.threshold,
        mask=mp.mask,
        reduction=red,
        surfaces=surfaces,
        timings=MappingProxyType(timings),
        options=options,
        provenance=provenance,
    )
    if o.get("scale_regions") is None:
        return det
    o["cube_counts"] = cube.counts
    return _by_region(det, o, store)
