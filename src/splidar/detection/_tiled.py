"""Detection of a Dask-backed cube, tile by tile through ``dask.array``.

When ``cube.counts`` is a Dask array (a ``.zarr`` cube from :func:`splidar.load`, or
one the user builds), :func:`~splidar.detection.detect` hands the two passes that read
every voxel to Dask, which runs them on whatever scheduler is active: the threaded one
by default, a ``dask.distributed.Client`` when one is open (its workers read the
chunks and do the work; only small results travel back).

1. **Global statistics, one pass** (:func:`tiled_window_means`): the background's
   temporal shape (stage 1) is a statistic over a grid of ``K x K`` windows (``K`` the
   largest box); each task reads a band of rows and returns its window means, about
   2000 pixels' worth in all. The null model (stage 3) reads a bounded number of
   random patches (about ``1000 / pfa`` voxels, whatever the cube's size) through Dask
   and is simulated in the calling process, seeded as in memory. A cube read from Zarr
   as it is (``dask.array.from_zarr``) takes one pass for the stuck-pixel check's
   totals and stage 1's windows (:func:`first_pass`: each chunk decoded once, straight
   into the task's kept band buffer), which also gathers the null's sub-grid and
   ``coherent_scales``' tiles (:class:`Gathered`).
2. **Tiles** (:func:`map_candidates_tiled`): the map pass (stage 4) on tiles of rows x
   columns, each with a halo of ``h = max k // 2`` rows and ``h + 1`` columns on both
   sides (no padding at the image edge, which is handled as in memory, like
   ``map_overlap`` with ``boundary="none"``). A tile reads its counts with their halo
   straight from the cube's chunks (column pieces cut from each chunk, copied once into
   the worker thread's kept buffer: :func:`_tile_inputs`). By default the tiles
   are square, with as many pixels as the rows of whole image rows that fit (64 MB of
   work buffers, or :data:`TILE_SHARE` of a worker's memory): the halo is then a small
   share of a tile (a strip of 10 rows re-filtered 10 halo rows, 2x the work; a
   100 x 100 tile 1.2x). A tile returns its candidates (a few numbers per surface) and
   its pixels' saliency, mask and background level, or writes them to the Zarr
   ``store`` itself. On a ``dask.distributed`` cluster with a ``store``, a cube read
   from Zarr as it is runs one task per band of tiles instead (:func:`_map_band`): it
   reads the band's rows from the Zarr array and runs the tiles left to right, so Dask
   has no per-tile input, carry or result keys to schedule, move or spill.

The box filters' column sums are float64 running sums along each image row, whose
rounding depends on where a sum starts: a tile takes them, at the column before its
first, from the tile on its left (a small ``(L, rows, Q, T)`` array; the tiles of a
band of rows run left to right, the bands in parallel). The clean-up passes (stage 5)
then run on the gathered candidate table, as in memory: what they look at across
pixels is listed in ``docs/distributed.md``.

Every tile computes its pixels exactly as a block of the in-memory pass does, so the
Detection is the same, bit for bit, whatever the tiles, workers or scheduler.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
from pathlib import Path

import numpy as np

from .._arrays import deferred_chunk_writes, zarr_rows_into
from .._memory import keep_freed_memory
from ._2_saliency import SaliencyFilters
from ._3_null import NullCalibration
from ._4_map import (
    CandidateMap,
    MapOptions,
    _block,
    _open_store,
    assemble_map,
    map_plan,
    writer,
)
from ._fast import window_means

__all__ = [
    "FirstPass",
    "Gathered",
    "compute_each",
    "first_pass",
    "is_dask",
    "map_candidates_tiled",
    "release_work",
    "tile_bounds",
    "tile_bytes",
    "tiled_window_means",
    "worker_memory_limit",
]

logger = logging.getLogger(__name__)

#: Image rows read by one task of the global-statistics pass.
STATS_ROWS = 64

#: Share of a worker's memory limit that one tile may take (:func:`tile_bytes`). The
#: rest holds the worker process itself (about 300 MB with Python, NumPy, Dask and
#: numba's kernels loaded), its input chunks, and keeps it below Dask's pause (80 % of
#: the limit) and its nanny's restart (95 %).
TILE_SHARE = 0.4


def is_dask(a) -> bool:
    """True when ``a`` is a Dask array (without importing Dask when it is not loaded)."""
    return type(a).__module__.split(".")[0] == "dask" and hasattr(a, "dask")


def tile_bounds(n_rows: int, block_rows: int, halo: int) -> list[tuple[int, int]]:
    """Row ranges ``[r0, r1)`` of the tiles: ``block_rows`` each, the last one merged
    into the one before when shorter than the ``halo`` (a halo comes from one neighbour)."""
    cuts = list(range(0, n_rows, block_rows)) + [n_rows]
    if len(cuts) > 2 and cuts[-1] - cuts[-2] < halo:
        del cuts[-2]
    return list(zip(cuts[:-1], cuts[1:], strict=True))


def _window_band(rows, starts, kr: int, col_starts, kc: int) -> np.ndarray:
    rows = np.asarray(rows)
    out = np.empty((starts.size, col_starts.size) + rows.shape[2:], np.float32)
    for i, a in enumerate(starts):
        out[i] = window_means(rows[a : a + kr], col_starts, kc)
    return out


def tiled_window_means(counts, row_starts, kr: int, col_starts, kc: int) -> np.ndarray:
    """The sampled window means of stage 1, computed where the data are.

    One task per band of about :data:`STATS_ROWS` rows (its windows start in the band
    and may reach ``kr - 1`` rows past it); the tasks run on the active scheduler and
    return ``(n_windows_in_band, n_cols, L, T)`` float32 each. Same values as the loop of
    :func:`~splidar.detection._background.temporal_shape` (exact window sums).
    """
    import dask

    row_starts = np.asarray(row_starts, np.int64)
    if row_starts.size == 0:
        return np.empty((0, col_starts.size) + tuple(counts.shape[2:]), np.float32)
    band = np.asarray(row_starts // max(STATS_ROWS, kr))
    # only the columns the windows cover travel into a task: the band's rows are taken
    # from each chunk before they are joined (on a wide image the grid's windows cover a
    # small share of the columns; the in-memory loop reads only those too). The windows
    # are whole runs of ``kc`` columns, so each stays contiguous in the kept columns.
    cols = np.unique((np.asarray(col_starts, np.int64)[:, None] + np.arange(kc)).ravel())
    if cols.size < counts.shape[1]:
        col_starts = np.searchsorted(cols, col_starts)
    else:
        cols = slice(None)
    tasks = []
    # keys named for the dashboard: "splidar-window-means"
    name = "splidar-window-means-" + dask.base.tokenize(
        counts.name, row_starts, kr, col_starts, kc, cols
    )
    for i, b in enumerate(np.unique(band)):
        starts = row_starts[band == b]
        a0, a1 = int(starts[0]), int(starts[-1]) + kr
        tasks.append(
            dask.delayed(_window_band, pure=True)(
                counts[a0:a1, cols], starts - a0, kr, col_starts, kc, dask_key_name=(name, i)
            )
        )
    parts = dask.compute(*tasks)
    return np.concatenate(parts, axis=0)


def _first_band(
    z, a0: int, a1: int, groups: list, cols: np.ndarray, at, kc: int, step: int, blocks=()
):
    """Rows ``[a0, a1)`` of the Zarr array ``z`` read once: their pixel totals
    ``(a1 - a0, C)`` float64 (the stuck-pixel check's); per row group ``(w0, w1)`` of
    ``groups`` (the rows of one row of stage 1's windows that fall in the band), the
    counts summed over those rows and each window's ``kc`` columns (the columns ``cols``
    kept, a window's first at ``at``), ``(len(at), L, T)`` float64: integer sums, exact,
    so the windows' partial sums add up to the whole windows' sums whatever the bands;
    and the band's rows and columns of the sub-grid ``[::step, ::step]`` (the null's
    :func:`~splidar.detection._3_null.data_tail`; None for ``step`` 0); and the band's
    rows of each block ``(r0, r1, c0, c1)`` of ``blocks`` it holds some of (``[(i,
    rows)]``). Nothing returned refers to the thread's band buffer the rows are read
    into."""
    from ._fast import pixel_totals

    # into this thread's kept band buffer, one chunk of rows at a time (as the map pass
    # reads): no fresh pages faulted in per task
    y = _read_band(z, a0, a1, a1 - a0)
    totals = pixel_totals(y)
    # each window's kc columns are consecutive image columns: summed from the band's rows
    # as they lie (no copy of the kept columns, no fresh pages for it per row group)
    starts = np.asarray(cols)[np.asarray(at)]
    sums = []
    for w0, w1 in groups:
        part = np.empty((starts.size,) + y.shape[2:], np.float64)
        for i, c in enumerate(starts):
            y[w0 - a0 : w1 - a0, c : c + kc].sum(axis=(0, 1), dtype=np.float64, out=part[i])
        sums.append(part)
    sub = y[(-a0) % step :: step, ::step].copy() if step else None
    pieces = [
        (i, y[max(r0, a0) - a0 : min(r1, a1) - a0, c0:c1].copy())
        for i, (r0, r1, c0, c1) in enumerate(blocks)
        if max(r0, a0) < min(r1, a1)
    ]
    return totals, sums, sub, pieces


class FirstPass:
    """The stuck-pixel check's totals and stage 1's window sums of a Zarr-backed Dask
    cube, from one read of its chunks (:func:`first_pass`); :meth:`windows` serves the
    window means :func:`~splidar.detection._background.temporal_shape` asks for when the
    grid is the one computed here (else it reads them: :func:`tiled_window_means`)."""

    def __init__(self, totals, grid, means, sample=None, blocks=None):
        self.totals, self._grid, self._means = totals, grid, means
        self.sample = sample  # counts[::s, ::s] when asked (first_pass's step)
        # {(r0, r1, c0, c1): counts[r0:r1, c0:c1]} when asked (first_pass's blocks)
        self.blocks = blocks or {}

    def windows(self, counts, row_starts, kr, col_starts, kc) -> np.ndarray:
        kr0, kc0, rs0, cs0 = self._grid
        same = (kr, kc) == (kr0, kc0) and np.array_equal(row_starts, rs0)
        if same and np.array_equal(col_starts, cs0):
            return self._means
        return tiled_window_means(counts, row_starts, kr, col_starts, kc)


def first_pass(counts, box: int, step: int = 0, blocks=()) -> FirstPass | None:
    """One pass of Dask tasks over a Zarr-backed cube of integer counts
    (``dask.array.from_zarr``; None for any other cube): each task reads a band of
    whole stored chunks of rows from the Zarr array itself (each chunk decoded once)
    and returns its pixels' totals (:func:`~splidar.detection._hot_pixels.hot_pixels`),
    its rows' share of the sums of stage 1's windows (the grid of
    :func:`~splidar.detection._background.sample_grid` with ``k = box``, summed over
    each window's columns in the task) and, with ``step``, its rows of the sub-grid
    ``counts[::step, ::step]`` (``FirstPass.sample``, the null's
    :func:`~splidar.detection._3_null.data_tail`: the cube not read again for it), and
    its rows of each block ``(r0, r1, c0, c1)`` of ``blocks`` (``FirstPass.blocks``,
    ``{block: counts[r0:r1, c0:c1]}``: the tiles of
    :func:`~splidar.detection._2_saliency.coherent_scales`, served by
    :class:`Gathered`). The windows' means are then the float32 rounding of the exact
    sums over ``kr x kc`` pixels, as :func:`~splidar.detection._fast.window_means` gives
    them, bit for bit."""
    import dask

    from ._background import sample_grid

    z = _zarr_source(counts)
    if z is None or np.dtype(counts.dtype).kind not in "ui" or np.dtype(counts.dtype).itemsize > 4:
        return None
    R, C, L, T = counts.shape
    kr, kc, row_starts, col_starts = grid = sample_grid(counts.shape, box)
    cols = np.unique((col_starts[:, None] + np.arange(kc)).ravel())
    # each window: its kc columns among the kept ones (summed in the tasks)
    at = np.searchsorted(cols, col_starts)
    rows = int(z.chunks[0]) * max(1, round(STATS_ROWS / int(z.chunks[0])))
    src = dask.delayed(z, pure=True)
    blocks = tuple(tuple(int(v) for v in b) for b in blocks)
    name = "splidar-first-pass-" + dask.base.tokenize(counts.name, box, rows, step, blocks)
    tasks, parts = [], []
    for i, a0 in enumerate(range(0, R, rows)):
        a1 = min(R, a0 + rows)
        groups, which = [], []
        for w, r in enumerate(row_starts):
            w0, w1 = max(int(r), a0), min(int(r) + kr, a1)
            if w0 < w1:
                groups.append((w0, w1))
                which.append(w)
        tasks.append(
            dask.delayed(_first_band, pure=True)(
                src, a0, a1, groups, cols, at, kc, step, blocks, dask_key_name=(name, i)
            )
        )
        parts.append((a0, a1, which))
    totals = np.empty((R, C), np.float64)
    sums = np.zeros((row_starts.size, col_starts.size, L, T), np.float64)
    sub = np.empty((-(-R // step), -(-C // step), L, T), counts.dtype) if step else None
    got = [np.empty((r1 - r0, c1 - c0, L, T), counts.dtype) for r0, r1, c0, c1 in blocks]

    def take(i, result):
        a0, a1, which = parts[i]
        totals[a0:a1], band, part, pieces = result
        for w, s in zip(which, band, strict=True):
            sums[w] += s
        if step:
            first = -(-a0 // step)
            sub[first : first + part.shape[0]] = part
        for j, rows in pieces:
            start = max(blocks[j][0], a0) - blocks[j][0]
            got[j][start : start + rows.shape[0]] = rows

    compute_each(tasks, take)
    means = np.empty((row_starts.size, col_starts.size, L, T), np.float32)
    means[...] = sums / np.float64(kr * kc)
    return FirstPass(totals, grid, means, sub, dict(zip(blocks, got, strict=True)))


class Gathered:
    """A cube's counts (``shape``, ``dtype``, ``[rows, cols]``) that serves the blocks
    ``{(r0, r1, c0, c1): counts[r0:r1, c0:c1]}`` already read (:func:`first_pass`'s
    ``blocks``) when asked for exactly one of them, and reads any other selection from
    ``counts``."""

    def __init__(self, counts, blocks: dict):
        self.counts, self.blocks = counts, blocks
        self.shape, self.dtype, self.ndim = counts.shape, counts.dtype, counts.ndim

    def __getitem__(self, key):
        at = None
        if isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, slice) for k in key):
            if all(k.step in (None, 1) for k in key):
                at = (key[0].start, key[0].stop, key[1].start, key[1].stop)
        if at in self.blocks:
            return self.blocks[at]
        return self.counts[key]


def _client():
    """The active ``dask.distributed`` client, or None (threads, synchronous)."""
    import dask

    client = getattr(dask.base.get_scheduler(), "__self__", None)
    if type(client).__name__ != "Client" or not hasattr(client, "compute"):
        return None
    return client


def worker_memory_limit() -> int | None:
    """The smallest memory limit (bytes) of the active client's workers; None without a
    ``dask.distributed`` client or when no worker has a limit."""
    client = _client()
    if client is None:
        return None
    try:  # every worker (recent versions list 5 by default)
        info = client.scheduler_info(n_workers=-1)
    except TypeError:  # distributed before 2025: always every worker
        info = client.scheduler_info()
    workers = info.get("workers", {}).values()
    limits = [int(w.get("memory_limit") or 0) for w in workers]
    limits = [x for x in limits if x > 0]
    return min(limits) if limits else None


def tile_bytes(rows: int, shape, itemsize: int, halo: int, n_box: int) -> int:
    """Peak bytes of the buffers of one stage-4 tile of ``rows`` image rows.

    Per image row of the tile, ``C T`` float32 each: saliency, signed response,
    evidence, the copy a compressor makes on writing to a store and one spare (the
    level buffer the saliency kernel no longer keeps: a margin; the threshold is no
    longer held per voxel, even with a store), plus the
    bool candidates and mask, plus ``n_box`` box means per wavelength (the scales above
    1 pixel when they are kept for extraction); per row with its halo (``rows + 2 halo``),
    ``C L T`` of counts twice (the halo exchange's copy) and of float32 correlated counts.
    """
    _, C, L, T = shape
    own = C * T * (5 * 4 + 2) + C * L * T * 4 * n_box
    ext = C * L * T * (2 * itemsize + 4)
    return int(rows * own + (rows + 2 * halo) * ext)


def _rows_for(limit: int, shape, itemsize: int, halo: int, n_box: int, most: int) -> int:
    """The most rows (at most ``most``, at least the halo) whose tile fits
    :data:`TILE_SHARE` of a worker's ``limit``."""
    budget = TILE_SHARE * limit
    one = tile_bytes(1, shape, itemsize, halo, n_box) - tile_bytes(0, shape, itemsize, halo, n_box)
    rows = int((budget - tile_bytes(0, shape, itemsize, halo, n_box)) // one)
    if rows < max(halo, 1):
        logger.warning(
            "detect: a tile of %d rows (the halo) needs %.0f MB, more than %.0f %% of the "
            "workers' memory limit (%.0f MB): give the workers more memory (the rows of "
            "this cube are too wide for it)",
            max(halo, 1),
            tile_bytes(max(halo, 1), shape, itemsize, halo, n_box) / 1e6,
            100 * TILE_SHARE,
            limit / 1e6,
        )
    return max(min(rows, most), halo, 1)


#: Rows per chunk of a ``store`` written by square tiles (a divisor of their rows).
_CHUNK_ROWS = 16

#: Columns per tile (None: square tiles, see :func:`_tile_shape`); any width gives the
#: same Detection, bit for bit (the tests set it).
TILE_COLS = None

#: Work buffers of the tiles, per thread (a worker process runs tile after tile: the
#: pages are touched once, not once per tile); released when a map pass ends.
_WORK: dict = {}
_WORK_LOCK = threading.Lock()


def _work(own: int, ext: int, shape, n_box: int, thr: bool, dtype) -> tuple[dict, np.ndarray]:
    """This thread's ``(work, corr)`` flat buffers for tiles of up to ``own`` pixels and
    ``ext`` pixels with their halo (grown when a larger tile comes); ``thr``: with a
    per-voxel threshold buffer (written to a store); ``dtype``: the counts' (``work["y"]``
    receives the tile's counts with their halo)."""
    _, _, L, T = shape
    key = threading.get_ident()
    with _WORK_LOCK:
        have = _WORK.get(key)
    dtype = np.dtype(dtype)
    if have is not None and have[0] >= (own, ext) and have[1] == (L, T, n_box, thr, dtype):
        return have[2], have[3]
    work = dict(
        d=np.empty(own * T, np.float32),
        cand=np.empty(own * T, bool),
        ev=np.empty(own * T, np.float32),
        # the tile's outputs before they are written out (store or returned arrays)
        sal=np.empty(own * T, np.float32),
        mask=np.empty(own * T, bool),
        y=np.empty(ext * L * T, dtype),
    )
    if thr:
        work["thr"] = np.empty(own * T, np.float32)
    if n_box:
        work["box"] = np.empty(L * n_box * own * T, np.float32)
    corr = np.empty(ext * L * T, np.float32)
    with _WORK_LOCK:
        _WORK[key] = ((own, ext), (L, T, n_box, thr, dtype), work, corr)
    return work, corr


def release_work() -> None:
    """Free the tiles' work buffers of this process (every thread's)."""
    with _WORK_LOCK:
        _WORK.clear()


def compute_each(tasks: list, take) -> None:
    """Compute ``tasks`` on the active scheduler, calling ``take(i, result)`` for each.

    On a ``dask.distributed`` client the results are fetched as they complete and
    released at once, so no worker holds finished tiles until the last one is done; on
    the local schedulers, in one ``dask.compute``.
    """
    import dask

    client = _client()
    if client is None:
        for i, result in enumerate(dask.compute(*tasks)):
            take(i, result)
        return
    from distributed import as_completed

    futures = client.compute(tasks)
    index = {f.key: i for i, f in enumerate(futures)}
    del tasks
    for fut in as_completed(futures):
        take(index[fut.key], fut.result())
        fut.release()
    futures.clear()


class _Tile:
    """A tile's own array addressed by image pixels (``a[r0:r1, c0:c1] = x`` writes them)."""

    def __init__(self, array: np.ndarray, first_row: int, first_col: int):
        self.array, self.first = array, (first_row, first_col)

    def __setitem__(self, key: tuple, value) -> None:
        rows, cols = key
        r, c = self.first
        self.array[rows.start - r : rows.stop - r, cols.start - c : cols.stop - c] = value


def _assemble(pieces, places, out: np.ndarray) -> np.ndarray:
    """The tile's counts with their halo: each of the cube's chunks ``pieces[k]`` gives
    its part ``places[k] = (source slices, destination slices)`` to ``out``."""
    for piece, (src, dst) in zip(pieces, places, strict=True):
        out[dst] = np.asarray(piece)[src]
    return out


def _map_tile(y, tile, ctx, table, opts, store_path, most: tuple, carry, last: bool):
    """Stage 4 on image rows ``[r0, r1)`` and columns ``[c0, c1)``; ``y`` holds the
    pixels from ``(e0, ce0)`` (the tile with its halo), or is ``(shape, dtype, pieces,
    places)``: the cube's chunks that cover them (:func:`_assemble`, into this thread's
    kept buffer). ``tile = (e0, r0, r1, ce0, c0, c1)``.

    ``most`` = ``(own pixels, pixels with halo)`` of the largest tile: the size of this
    thread's reused work buffers. ``store_path``: the store's folder, or the store
    opened (:func:`_stores`, by a band task for its tiles); None: the own arrays are
    returned. ``carry``: the box filters' running column sums at
    column ``c0 - 1`` (from the tile to the left; None at the image's first column).
    Returns ``(result, own arrays, carry at column c1 - 1)`` (None when ``last``).
    """
    e0, r0, r1, ce0, c0, c1 = tile
    n_box = int((ctx.scales > 1).sum()) if opts["store_boxes"] else 0
    if isinstance(y, tuple):
        shape, dtype, pieces, places = y
        work, corr = _work(most[0], most[1], shape, n_box, bool(table[2]), dtype)
        y = work["y"][: int(np.prod(shape))].reshape(shape)
        y = _assemble(pieces, places, y)
        del pieces
    else:  # a view of the band's rows (:func:`_map_band`): copied into the kept buffer
        work, corr = _work(most[0], most[1], y.shape, n_box, bool(table[2]), y.dtype)
        y = _copy_into(work["y"], y)
    er, ec, L, T = y.shape
    c_ext = ctx.corr(y, workers=ctx.workers, out=corr[: y.size].reshape(y.shape))
    r, c = r1 - r0, c1 - c0
    own = dict(spatial=np.empty((r, c, L), np.float32))
    if store_path is None:
        own["saliency"] = np.empty((r, c, T), np.float32)
        own["mask"] = np.empty((r, c, T), bool)
        out = {k: _Tile(v, r0, c0) for k, v in own.items()}
        out["threshold"] = None
    else:
        stores = _stores(store_path)
        out = dict(
            saliency=stores["saliency"],
            mask=stores["mask"],
            threshold=None,
            spatial=_Tile(own["spatial"], r0, c0),
        )
        store_path = stores
    # the running sums are read and rewritten in place: a copy of the neighbour's
    shape = (L, r, ctx.scales.size, T)
    carry = np.empty(shape, np.float64) if carry is None else np.array(carry, np.float64)
    with deferred_chunk_writes(depth=1):  # (within a band task's block: that one)
        res = _block(y, c_ext, e0, r0, r1, ctx, table, opts, out, work, cols=(ce0, c0, c1, carry))
        if res.histograms is not None and res.kept.size < len(res.histograms):
            # only the histograms of the candidates in the table travel back (in memory
            # the block's whole array is kept and indexed by ``kept``: the same values)
            res.histograms = np.ascontiguousarray(res.histograms[res.kept])
            res.kept = np.arange(res.kept.size, dtype=res.kept.dtype)
        _compact_result(res, store_path, (r0, c0), opts["image_shape"], T)
    return res, own, None if last else carry


def _stores(store_path) -> dict:
    """The map pass's store at ``store_path`` opened for a tile's writes: its
    ``saliency`` and ``mask`` arrays (:func:`~splidar.detection._4_map.writer`) and the
    ``histograms`` group (``candidate_histograms``); ``store_path`` itself when it is
    such a dict already (a band task opens the store once for its tiles: each opening
    reads the group's and arrays' metadata through Zarr, 1.7 ms a tile)."""
    if isinstance(store_path, dict):
        return store_path
    import zarr

    g = zarr.open_group(str(store_path), mode="r+")
    return dict(
        saliency=writer(g["saliency"]),
        mask=writer(g["mask"]),
        histograms=_histograms_folder(store_path),
    )


def _histograms_folder(store_path) -> Path:
    """The folder of the tiles' candidate histograms in the store at ``store_path`` (or
    in the store :func:`_stores` opened)."""
    if isinstance(store_path, dict):
        return store_path["histograms"]
    return Path(os.fspath(store_path)) / "candidate_histograms"


def _copy_into(buf: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``y`` copied into the front of the flat kept buffer ``buf`` (same shape)."""
    out = buf[: y.size].reshape(y.shape)
    out[...] = y
    return out


def _read_band(z, e0: int, e1: int, most_rows: int) -> np.ndarray:
    """Rows ``[e0, e1)`` of the Zarr array ``z``, read into this thread's kept band
    buffer (for up to ``most_rows`` rows) one stored chunk of rows at a time: one chunk
    decoded at once, into pages touched once per worker thread, not per band."""
    row = tuple(int(v) for v in z.shape[1:])
    dtype = np.dtype(z.dtype)
    have = _kept_buffer("band", most_rows * int(np.prod(row)), dtype)
    y = have[: (e1 - e0) * int(np.prod(row))].reshape((e1 - e0,) + row)
    step = int(z.chunks[0])
    for a in range(e0 - e0 % step, e1, step):
        lo, hi = max(a, e0), min(a + step, e1)
        if hi - lo < step and a + step <= z.shape[0]:
            # part of a chunk (the band's ends): the whole chunk decoded into the thread's
            # kept chunk buffer, its rows copied (Zarr would decode it into a fresh
            # buffer each time: on a worker, Dask's malloc setting makes that new pages,
            # ~0.55 M page faults per pass over issue #16's cube; "Lead, session 28")
            whole = _kept_buffer("chunk", step * int(np.prod(row)), dtype)
            whole = zarr_rows_into(
                z, a, a + step, whole[: step * int(np.prod(row))].reshape((step,) + row)
            )
            y[lo - e0 : hi - e0] = whole[lo - a : hi - a]
        else:
            zarr_rows_into(z, lo, hi, y[lo - e0 : hi - e0])
    return y


def _kept_buffer(name: str, size: int, dtype) -> np.ndarray:
    """This thread's kept flat buffer ``name`` of at least ``size`` values of ``dtype``
    (reused band after band; dropped by :func:`release_work`)."""
    key = (name, threading.get_ident())
    with _WORK_LOCK:
        have = _WORK.get(key)
    if have is None or have.size < size or have.dtype != dtype:
        have = np.empty(size, dtype)
        with _WORK_LOCK:
            _WORK[key] = have
    return have


def _map_band(z, band: tuple, tiles: list, ctx, table, opts, store_path, most: tuple):
    """Stage 4 on a band of tiles, in one task: the band's rows with their halo
    ``band = (e0, e1, most rows)`` read from the Zarr array ``z`` (:func:`_read_band`),
    then its ``tiles`` (``(e0, r0, r1, ce0, ce1, c0, c1)`` each, left to right) run as
    :func:`_map_tile` runs them, the running column sums passed from tile to tile in
    this task (no carry or input keys). Returns ``[(result, own arrays)]`` per tile."""
    e0, e1, most_rows = band
    # on a Dask worker the tiles' temporaries (tens of MB each) reuse the pages the tile
    # before freed instead of new mappings, given back when the band ends
    # (:func:`~splidar._memory.keep_freed_memory`; "Lead, session 29" in
    # ``benchmarks/README.md``)
    with keep_freed_memory(any_size=True):
        return _map_band_tiles(z, band, tiles, ctx, table, opts, store_path, most)


def _map_band_tiles(z, band: tuple, tiles: list, ctx, table, opts, store_path, most: tuple):
    """:func:`_map_band`'s work."""
    e0, e1, most_rows = band
    y = _read_band(z, e0, e1, most_rows)
    # the store's arrays opened once for the band's tiles, not once per tile
    store_path = None if store_path is None else _stores(store_path)
    carry, done = None, []
    # the saliency's chunk files written by a writer thread while the next tiles compute
    # (the band returns once every file is in place); one tile's chunk in flight (a
    # tile's saliency is tens of MB, its write a few ms of the disk's)
    with deferred_chunk_writes(depth=1):
        for j, (t0, r0, r1, ce0, ce1, c0, c1) in enumerate(tiles):
            tile = (t0, r0, r1, ce0, c0, c1)
            last = j == len(tiles) - 1
            res, own, carry = _map_tile(
                y[:, ce0:ce1], tile, ctx, table, opts, store_path, most, carry, last
            )
            done.append((res, own))
    return done


def _carry(out):
    """A tile's running column sums, for the tile on its right."""
    return out[2]


def _result(out):
    """What the calling process fetches of a tile: its result and own arrays, without
    the running sums (which only the tile on its right needs, on a worker)."""
    return out[:2]


def _tile_shape(rows: int, shape, h: int, hc: int, given: bool) -> tuple[int, int]:
    """Tile ``(rows, cols)``: :data:`TILE_COLS` columns when set; whole rows when the
    caller ``given`` the rows per tile; otherwise square tiles of as many pixels as
    ``rows`` whole image rows (the same memory, a smaller halo)."""
    R, C = shape[:2]
    if TILE_COLS is not None:
        cols = TILE_COLS
    elif given:
        cols = C
    else:
        cols = int(np.sqrt(rows * C))
        rows = (rows * C) // max(min(cols, C), 1)
    return min(max(rows, h, 1), R), min(max(cols, hc, 1), C)


def _compact_result(res, store_path, origin: tuple, image_shape, n_bins: int) -> None:
    """What a tile sends back, made small for the calling process (which gathers every
    tile's): the candidates' integer columns in compact types (same values), and with a
    store, the histograms written there as one file (``candidate_histograms/<first
    row>_<first column>.raw``, from ``origin``: :class:`~splidar.detection._table.RawRows`,
    which the calling process reads at the selected surfaces' rows only) and replaced by
    its handle."""
    from ._table import RawRows, compact_columns

    res.surf = compact_columns(res.surf, image_shape, n_bins)
    if store_path is not None and res.histograms is not None:
        folder = _histograms_folder(store_path)  # (no Zarr metadata read for a path)
        # read once by the selection, then removed: raw bytes in one file per tile (no
        # Zarr array: a folder and two metadata files fewer to create per tile)
        res.histograms = RawRows.write(
            folder / f"{origin[0]}_{origin[1]}.raw", np.asarray(res.histograms, np.float32)
        )


def _parts(chunks, a: int, b: int) -> list[tuple[int, slice, slice]]:
    """The chunks of one axis that cover ``[a, b)``: ``(chunk index, slice in the chunk,
    slice in [a, b))`` each."""
    ends = np.cumsum(chunks)
    out = []
    for k, (c0, c1) in enumerate(zip(ends - np.asarray(chunks), ends, strict=True)):
        lo, hi = max(a, int(c0)), min(b, int(c1))
        if lo < hi:
            out.append((k, slice(lo - int(c0), hi - int(c0)), slice(lo - a, hi - a)))
    return out


def _piece(chunk, cols: slice) -> np.ndarray:
    """A copy of the columns ``cols`` of one of the cube's chunks (so that the chunk
    itself is released once every tile's columns are taken)."""
    return np.array(np.asarray(chunk)[:, cols], copy=True)


def _tile_inputs(counts, ext, ext_c):
    """``inputs(i, j)``: what the tile of row range ``ext[i]`` and column range
    ``ext_c[j]`` (with their halos) reads: ``(shape, dtype, pieces, places)`` for
    :func:`_assemble`. The pieces are Dask tasks ("splidar-map-input"): the columns of
    a column of tiles cut from each of the cube's chunks, shared by the tiles of
    consecutive bands of rows (the halo's rows)."""
    import dask

    blocks = counts.to_delayed()
    L, T = counts.shape[2:]
    whole = [_parts(counts.chunks[2], 0, L), _parts(counts.chunks[3], 0, T)]
    name = "splidar-map-input-" + dask.base.tokenize(counts.name, ext_c)
    made = {}

    def piece(k: tuple, j: int, sc: slice):
        key = (name, *k, j)
        if key not in made:
            made[key] = dask.delayed(_piece, pure=True)(blocks[k], sc, dask_key_name=key)
        return made[key]

    def inputs(i: int, j: int):
        (e0, e1), (f0, f1) = ext[i], ext_c[j]
        pieces, places = [], []
        for kr, sr, dr in _parts(counts.chunks[0], e0, e1):
            for kc, sc, dc in _parts(counts.chunks[1], f0, f1):
                for kl, sl, dl in whole[0]:
                    for kt, st, dt in whole[1]:
                        pieces.append(piece((kr, kc, kl, kt), j, sc))
                        places.append(((sr, slice(None), sl, st), (dr, dc, dl, dt)))
        return (e1 - e0, f1 - f0, L, T), counts.dtype, pieces, places

    return inputs


def map_candidates_tiled(
    counts,
    filters: SaliencyFilters,
    null: NullCalibration,
    options: MapOptions,
    *,
    block_rows: int | None,
    store=None,
    n_jobs: int = 1,
) -> CandidateMap:
    """Stage 4 (:func:`~splidar.detection._4_map.map_candidates`) on a Dask array.

    Parameters
    ----------
    counts : dask.array.Array (rows, cols, L, T)
        Any chunking: each tile reads the chunks that cover it with its halo.
    filters, null, options
        As for the in-memory pass.
    block_rows : int or None
        Rows per tile, of whole rows (None: square tiles of the pixels of the rows that
        make about 64 MB of work buffers, as in memory, and on a ``dask.distributed``
        cluster no more than fits :data:`TILE_SHARE` of the workers' memory limit,
        :func:`tile_bytes`); at least the halo ``max k // 2``.
    store : path, optional
        A new directory: the tiles write saliency, mask (and a per-voxel threshold)
        there as Zarr arrays, one chunk per tile; otherwise they come back to
        the calling process as NumPy arrays.
    n_jobs : int
        Threads of the calling process joining the tiles' candidate tables at the end.

    Returns
    -------
    CandidateMap
        Identical to the in-memory pass's (``block_rows`` is the tile height).
    """
    import dask

    R, C, L, T = counts.shape
    h = int(filters.scales.max()) // 2
    # columns: one more halo column, where the running column sums carried in from the
    # tile to the left start (h = 0: a single 1-pixel scale, no sums)
    hc = h + 1 if h else 0
    given = block_rows
    opts, block_rows = map_plan(filters, null, options, counts.shape, block_rows)
    n_box = int((filters.scales > 1).sum()) if opts["store_boxes"] else 0
    limit = worker_memory_limit() if given is None else None
    # on a cluster, with a store, a Zarr cube is read by one task per band of tiles
    # (:func:`_map_band`), which runs the band's tiles itself: no input, carry or
    # result keys per tile for Dask to schedule, move and spill
    zsrc = _zarr_source(counts) if store is not None and _client() is not None else None
    if limit is not None:
        item = np.dtype(counts.dtype).itemsize
        block_rows = _rows_for(limit, counts.shape, item, h, n_box, block_rows)
        if zsrc is not None:
            block_rows = _rows_with_band(limit, counts.shape, item, (h, hc), n_box, block_rows)
    block_rows, block_cols = _tile_shape(block_rows, counts.shape, h, hc, given is not None)
    # a tile of a multiple of 16 rows unless given
    if given is None and block_rows >= 2 * _CHUNK_ROWS:
        block_rows -= block_rows % _CHUNK_ROWS
    table = null.table(per_voxel=False)
    rows, cols = tile_bounds(R, block_rows, h), tile_bounds(C, block_cols, hc)
    ext = [(max(0, a - h), min(R, b + h)) for a, b in rows]
    ext_c = [(max(0, a - hc), min(C, b + hc)) for a, b in cols]
    most = (
        max(b - a for a, b in rows) * max(b - a for a, b in cols),
        max(b - a for a, b in ext) * max(b - a for a, b in ext_c),
    )
    if store is not None:
        # a store's saliency and mask in one chunk per tile (no two tasks write one
        # chunk): a file to create per tile, not one per 16 rows (the saliency is stored
        # raw, read at its voxels from the chunk files, never decoded whole by the
        # passes after the map; "Lead, session 30" in benchmarks/README.md)
        out = _open_store(store, (R, C, T), block_rows, block_cols=block_cols)
        store_path = str(store)
        import zarr

        # the tiles write their candidates' histograms here (_compact_result)
        zarr.open_group(store_path, mode="r+").create_group("candidate_histograms")
    else:
        out, store_path = None, None
    # the set-up every tile shares travels once (one key), not once per task
    ctx = dask.delayed(dataclasses.replace(filters, workers=1), pure=True)
    shared = dask.delayed((table, opts), pure=True)
    if zsrc is not None:
        tasks, where = _band_tasks(zsrc, counts.name, (rows, ext, cols, ext_c), ctx, shared,
                                   store_path, most)  # fmt: skip
        tiles = sum(len(w) for w in where)
    else:
        # each tile reads the cube's chunks that cover it with its halo and copies their
        # parts into its thread's kept buffer (no rechunked or overlapped copies between)
        inputs = _tile_inputs(counts, ext, ext_c)
        tasks, where = _tile_tasks(inputs, (rows, ext, cols, ext_c), ctx, shared, store_path,
                                   most, token_of=counts.name)  # fmt: skip
        tiles = len(tasks)
        where = [[w] for w in where]
    logger.info(
        "detect: map pass on %d tile(s) of %d x %d pixels (halo %d rows, %d columns) in %d "
        "task(s)", tiles, block_rows, block_cols, h, hc, len(tasks),
    )  # fmt: skip
    if out is None:
        out = dict(
            saliency=np.empty((R, C, T), np.float32),
            mask=np.empty((R, C, T), bool),
            threshold=None,
        )
    out["spatial"] = np.empty((R, C, L), np.float32)
    outs = [None] * len(tasks)

    def take(i, result):
        # a task's tiles (one, or a band's): (result, own arrays) each
        results = result if zsrc is not None else [result]
        for (_, own), (r0, r1, c0, c1) in zip(results, where[i], strict=True):
            for k, v in own.items():
                out[k][r0:r1, c0:c1] = v
        outs[i] = [res for res, _ in results]

    try:
        compute_each(tasks, take)
    finally:
        client = _client()
        if client is not None:
            client.run(release_work)
        release_work()
    outs = [res for band in outs for res in band]
    return assemble_map(outs, out, filters, null, store, counts.shape, block_rows, opts, n_jobs)


def _tile_tasks(inputs, grid, ctx, shared, store_path, most, *, token_of):
    """One Dask task per tile, with its running sums and its result as keys of their
    own: ``(tasks, where)`` (the tiles' ``(r0, r1, c0, c1)``)."""
    import dask

    rows, ext, cols, ext_c = grid
    # keys named for the dashboard: "splidar-map-tile" computes a tile,
    # "splidar-map-carry" passes its running sums to the tile on its right,
    # "splidar-map-result" is what the calling process fetches (not the sums)
    token = dask.base.tokenize(token_of, rows, cols, ctx.key, shared.key, store_path)
    name = "splidar-map-tile-" + token
    tasks, where = [], []
    for i, ((r0, r1), (e0, _)) in enumerate(zip(rows, ext, strict=True)):
        carry = None  # the tiles of a band of rows run left to right, passing the sums
        for j, ((c0, c1), (ce0, _)) in enumerate(zip(cols, ext_c, strict=True)):
            tile = (e0, r0, r1, ce0, c0, c1)
            done = dask.delayed(_map_tile, pure=True)(
                inputs(i, j), tile, ctx, shared[0], shared[1], store_path, most, carry,
                j == len(cols) - 1, dask_key_name=(name, i, j),
            )  # fmt: skip
            carry = dask.delayed(_carry, pure=True)(
                done, dask_key_name=("splidar-map-carry-" + token, i, j)
            )
            tasks.append(
                dask.delayed(_result, pure=True)(
                    done, dask_key_name=("splidar-map-result-" + token, i, j)
                )
            )
            where.append((r0, r1, c0, c1))
    return tasks, where


def _band_tasks(z, name, grid, ctx, shared, store_path, most):
    """One Dask task per band of tiles (:func:`_map_band`) reading the Zarr array ``z``
    itself: ``(tasks, where)``, ``where[i]`` the band's tiles' ``(r0, r1, c0, c1)``."""
    import dask

    rows, ext, cols, ext_c = grid
    most_rows = max(b - a for a, b in ext)
    src = dask.delayed(z, pure=True)
    token = dask.base.tokenize(name, rows, cols, ctx.key, shared.key, store_path)
    tasks, where = [], []
    for i, ((r0, r1), (e0, e1)) in enumerate(zip(rows, ext, strict=True)):
        tiles = [
            (e0, r0, r1, ce0, ce1, c0, c1) for (c0, c1), (ce0, ce1) in zip(cols, ext_c, strict=True)
        ]
        tasks.append(
            dask.delayed(_map_band, pure=True)(
                src,
                (e0, e1, most_rows),
                tiles,
                ctx,
                shared[0],
                shared[1],
                store_path,
                most,
                dask_key_name=("splidar-map-band-" + token, i),
            )  # fmt: skip
        )
        where.append([(r0, r1, c0, c1) for (c0, c1) in cols])
    return tasks, where


def _zarr_source(counts):
    """The Zarr array ``counts`` reads as it is (``dask.array.from_zarr``), else None."""
    from ._slopes import _zarr_of

    try:
        return _zarr_of(counts)
    except Exception:  # any other graph
        return None


def _rows_with_band(limit: int, shape, itemsize: int, halos: tuple, n_box: int, rows: int) -> int:
    """``rows`` (whole-row equivalents of a tile, from :func:`_rows_for`) lowered until
    a tile's buffers and its band's rows with their halo (:func:`_read_band`: whole
    image rows) fit :data:`TILE_SHARE` of a worker's ``limit`` together."""
    h, hc = halos
    _, C, L, T = shape
    while rows > max(h, 1):
        tr, _ = _tile_shape(rows, shape, h, hc, False)
        band = (tr + 2 * h) * C * L * T * itemsize
        if tile_bytes(rows, shape, itemsize, h, n_box) + band <= TILE_SHARE * limit:
            break
        rows -= 1
    return rows
