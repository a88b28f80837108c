"""Stage 6: the surfaces: at most ``K_s`` candidates per pixel, in depth order.

The kept candidates of largest saliency mass are selected per pixel (the ``K_s`` slots
of the paper's matrix C), their clean histograms gathered once from the blocks' arrays,
and the table becomes :class:`~splidar.detection.Surfaces`.
"""

from __future__ import annotations

import numpy as np

from .._arrays import _raw_chunks, zarr_take_rows
from .._memory import give_back
from ._kernels import select_sorted
from ._result import Surfaces
from ._table import CandidateTable, RawRows, _position_in_pixel, _raster_ordered
from ._threads import on_parts
from ._windows import SupportWindows

__all__ = ["select_surfaces"]

#: Surfaces whose histograms :func:`_gather` reads at a time (about 13 MB at Q = 4, L = 1,
#: W = 13): the calling process holds one such part when they go to a store. Fewer where
#: a part would exceed :data:`GATHER_BYTES` (a long IRF's wide window: W = 681 at the face
#: file's native bin made a part 0.7 GB).
GATHER_CHUNK = 2**16
#: Bytes of one part of :func:`_gather` (at most; at least one surface).
GATHER_BYTES = 2**26


def _select(surf: dict, keep: np.ndarray, k_max: int):
    """Keep at most ``k_max`` candidates per pixel (largest saliency mass), depth order."""
    row, col = surf["row"], surf["col"]
    order = None
    if not _raster_ordered(row, col) and keep.any():
        # e.g. the slope recovery's surfaces appended at the end: one stable sort by
        # pixel (a pixel's candidates keep their order), then the linear kernel
        order = np.lexsort((col, row))
    if order is not None or _raster_ordered(row, col):
        n = row.size
        take = (lambda a: a[order]) if order is not None else (lambda a: a)
        idx, slot = np.empty(n, np.int64), np.empty(n, np.int64)
        m = select_sorted(
            np.ascontiguousarray(take(row), np.int64),
            np.ascontiguousarray(take(col), np.int64),
            np.ascontiguousarray(take(surf["saliency_mass"]), np.float64),
            np.ascontiguousarray(take(surf["depth_bin"]), np.float64),
            np.ascontiguousarray(take(keep), np.bool_),
            int(k_max),
            idx,
            slot,
        )
        return (order[idx[:m]] if order is not None else idx[:m]), slot[:m]
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return idx, np.zeros(0, np.int64)
    row, col = surf["row"], surf["col"]
    idx = idx[np.lexsort((-surf["saliency_mass"][idx], col[idx], row[idx]))]
    idx = idx[_position_in_pixel(row[idx], col[idx]) < k_max]
    idx = idx[np.lexsort((surf["depth_bin"][idx], col[idx], row[idx]))]
    return idx, _position_in_pixel(row[idx], col[idx])


#: Rows of a stored array read one by one (:func:`_read_part`, a raw array's chunk
#: files at those rows) rather than as the slice from the first to the last, when the
#: slice is more than this many times longer.
ROWS_APART = 16

#: Threads that read the selected histograms from the blocks' Zarr arrays (in a store;
#: :func:`_gather`): each read waits on its files more than it computes.
GATHER_THREADS = 4


def _gather(
    table: CandidateTable, idx: np.ndarray, histograms, out=None, release: bool = False
) -> np.ndarray:
    """The selected candidates' histograms from the blocks' (and passes') arrays (NumPy
    or Zarr), into ``out`` (an array-like of shape ``(idx.size, Q, L, W)``, e.g. a Zarr
    array: filled :data:`GATHER_CHUNK` surfaces at a time) or a new array. Zarr arrays
    are read on :data:`GATHER_THREADS` threads, a block's array each (the same values).
    An ``out`` not in memory is written part by part on one of these threads while the
    next part is read (a store's compressed writes took about half of the selection's
    time on a Zarr cube; ``benchmarks/README.md``, "dist38").

    ``release`` (``histograms`` a list): each block's entry is set to None once the
    part holding its last selected row is gathered, so that the blocks' arrays are
    released while the gathered one fills (``idx`` in raster order meets the blocks of
    rows one after the other)."""
    shape = (idx.size,) + tuple(histograms[0].shape[1:])
    last = _last_part(table.hist_block[idx], len(histograms)) if release else None
    if out is None:
        out = np.empty(shape, np.float32)
    # in memory each part is written where it goes (no copy of it)
    direct = isinstance(out, np.ndarray) and out.flags.c_contiguous
    stored = any(not isinstance(h, (np.ndarray, SupportWindows)) for h in histograms)
    pool = None
    if (stored or not direct) and idx.size:
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(GATHER_THREADS)
    row_bytes = 4 * max(int(np.prod(shape[1:], dtype=np.int64)), 1)
    chunk = int(min(GATHER_CHUNK, max(1, GATHER_BYTES // row_bytes)))
    # ``out`` not in memory (a store's array): part k is written on the pool while part
    # k + 1 is read, the parts' buffers used in turn (a buffer is refilled once its
    # write is done)
    spare, writing = [], None
    try:
        for a in range(0, idx.size, chunk):
            part = idx[a : a + chunk]
            if direct:
                hist = out[a : a + part.size]
            else:
                hist = spare.pop() if spare else np.empty((chunk,) + shape[1:], "f4")
                hist = hist[: part.size]
            _read_part(table, histograms, hist, part, pool)
            if not direct:
                if writing is not None:
                    spare.append(writing.result())
                writing = pool.submit(_write_part, out, a, hist)
            del hist
            if last is not None:
                done_ = np.flatnonzero(last < a + part.size)
                gone = [b for b in done_ if histograms[b] is not None]
                # the pages go back only when a block held its histograms in memory: a
                # stored block (a Zarr array, a detection on a cluster) frees next to
                # nothing, and trimming the heap there made the parts' next buffers new
                # pages again at each block (system CPU on a VM charging first touches)
                held = any(isinstance(histograms[b], (np.ndarray, SupportWindows)) for b in gone)
                for b in gone:
                    histograms[b] = None  # no later part reads it
                if held:
                    give_back()
        if writing is not None:
            writing.result()
    finally:
        if pool is not None:  # (an error: the write under way ends first)
            pool.shutdown()
    return out


def _write_part(out, a: int, hist: np.ndarray) -> np.ndarray:
    """``out[a : a + len(hist)] = hist``; returns ``hist``'s buffer for the next part."""
    out[a : a + hist.shape[0]] = hist
    return hist.base if hist.base is not None else hist


def _read_part(table: CandidateTable, histograms, hist: np.ndarray, part: np.ndarray, pool):
    """The candidates ``part``'s histograms into ``hist``, each block's rows read on
    ``pool`` (when given) into their own rows of ``hist``."""
    hb, hr = table.hist_block[part], table.hist_row[part]

    def read(b):
        sel = np.flatnonzero(hb == b)
        src = table.extra_histograms if b == -1 else histograms[b]
        rows = hr[sel]
        if isinstance(src, SupportWindows) and rows.size:
            if sel.size == hist.shape[0]:  # the whole part from one block
                src.rows(rows, hist)
            else:
                hist[sel] = src.rows(rows)
            return
        if isinstance(src, (np.ndarray, RawRows)) or rows.size == 0:
            hist[sel] = src[rows]  # a RawRows: read at those rows from its file
            return
        # a stored array: the rows' range read as one slice (most of a block's
        # candidates are selected: Zarr's integer indexing took 2.5x the CPU); rows
        # far apart (the recentring's moved candidates) from a raw array's chunk files
        # at those rows only
        lo, hi = int(rows.min()), int(rows.max()) + 1
        got = zarr_take_rows(src, rows) if rows.size * ROWS_APART < hi - lo else None
        hist[sel] = _stored_rows(src, lo, hi)[rows - lo] if got is None else got

    blocks = np.unique(hb)
    if pool is None:
        for b in blocks:
            read(b)
    else:  # every block's rows land in their own rows of ``hist``
        list(pool.map(read, blocks))


def _stored_rows(z, lo: int, hi: int) -> np.ndarray:
    """Rows ``[lo, hi)`` of the stored array ``z``; a Zarr array stored raw in a local
    folder in chunks of whole rows (the tiles' candidate histograms,
    ``store_histograms(compressed=False)``) is read from its chunk files directly: its
    reads then do not wait on Zarr's one event loop, where the surfaces' compressed
    writes run (:func:`_gather` overlaps the two). The same values as ``z[lo:hi]``."""
    raw = _raw_chunks(z) if hi > lo else None
    shape = tuple(int(v) for v in z.shape)
    if raw is None or tuple(raw[1][1:]) != shape[1:]:
        return np.asarray(z[lo:hi])
    folder, chunk, dtype, md = raw
    step, tail = chunk[0], (0,) * (len(shape) - 1)
    out = np.empty((hi - lo,) + shape[1:], np.dtype(z.dtype))
    for k in range(lo // step, (hi - 1) // step + 1):
        a, b = max(lo, k * step), min(hi, (k + 1) * step)
        path = folder / md.encode_chunk_key((k,) + tail)
        try:
            got = np.fromfile(path, dtype)
        except FileNotFoundError:  # never written: the fill value
            out[a - lo : b - lo] = np.asarray(md.fill_value, out.dtype)
            continue
        if got.size != int(np.prod(chunk)):  # not one whole chunk's bytes: Zarr reads it
            return np.asarray(z[lo:hi])
        out[a - lo : b - lo] = got.reshape(chunk)[a - k * step : b - k * step]
    return out


def _last_part(hb: np.ndarray, n_blocks: int) -> np.ndarray:
    """Per block, the position after which ``hb`` (the selected rows' blocks, -1 the
    passes' own array) never names it again (-1: never named)."""
    last = np.full(n_blocks, -1, np.int64)
    own = hb >= 0
    np.maximum.at(last, hb[own].astype(np.int64), np.flatnonzero(own))
    return last


#: Fewest rows per thread of :func:`_take_rows`.
TAKE_PART = 2**16


def _take_rows(a, idx: np.ndarray, dtype, n_jobs: int) -> np.ndarray:
    """``a[idx].astype(dtype, copy=False)`` for an array ``a`` (n, ...) and row
    positions ``idx`` (m,) in ``[0, n)``: ``idx`` in ``n_jobs`` contiguous parts on as
    many threads, each writing its rows of one new array (NumPy's ``take`` and casts
    release the GIL; the same values, cast as ``astype`` casts). Anything but a NumPy
    array is indexed as before, on this thread."""
    work = min(int(n_jobs), idx.size // TAKE_PART)
    if not isinstance(a, np.ndarray) or work <= 1:
        return a[idx].astype(dtype, copy=False)
    out = np.empty((idx.size, *a.shape[1:]), dtype)

    def part(i0: int, i1: int) -> None:
        if a.dtype == out.dtype:
            np.take(a, idx[i0:i1], axis=0, out=out[i0:i1], mode="clip")  # unbuffered
        else:
            out[i0:i1] = a[idx[i0:i1]].astype(dtype)

    on_parts(part, idx.size, work)
    return out


def select_surfaces(
    table: CandidateTable,
    histograms: tuple,
    *,
    max_surfaces: int,
    n_scales: int,
    n_wavelengths: int,
    width: int,
    histograms_out=None,
    release: bool = False,
    n_jobs: int = 1,
) -> Surfaces:
    """Keep at most ``max_surfaces`` kept candidates per pixel as :class:`Surfaces`.

    Parameters
    ----------
    table : CandidateTable
    histograms : tuple of ndarray
        The map pass's per-block histogram arrays (``CandidateMap.histograms``).
    max_surfaces : int
        ``K_s``.
    n_scales, n_wavelengths, width : int
        Q, L and W (the shape of an empty histogram array).
    histograms_out : callable, optional
        ``histograms_out(shape)`` gives an array-like the selected histograms are written
        to part by part (e.g. a Zarr array in the detection's store) and that becomes
        ``Surfaces.histograms``; default a NumPy array.
    release : bool
        ``histograms`` is a list this call may empty: each block's array is dropped (its
        entry set to None) once its selected rows are gathered (``detect``, which holds
        the map's arrays in that list alone: they are released while the surfaces'
        array fills instead of after it).
    n_jobs : int
        Threads of the columns' selected rows (:func:`_take_rows`; the same values).
    """
    idx, slot = _select(table.columns, table.keep, max_surfaces)
    cols = table.columns

    def take(name, dtype, shape=None):
        # one column at a time: the selected rows in the Surfaces' type
        v = _take_rows(cols[name], idx, dtype, n_jobs)
        return v if shape is None else v.reshape(shape)

    Q, L = n_scales, n_wavelengths
    if histograms_out is not None:
        hist = histograms_out((idx.size, Q, L, width))
        if idx.size:
            _gather(table, idx, histograms, hist, release)
    elif idx.size == 0:
        hist = np.zeros((0, Q, L, width), np.float32)
    else:
        hist = _gather(table, idx, histograms, release=release)
    R, C = table.image_shape
    i8, f8 = np.int64, np.float64
    return Surfaces(
        row=take("row", i8),
        col=take("col", i8),
        slot=slot.astype(i8, copy=False),
        depth_bin=take("depth_bin", f8),
        start=take("start", i8),
        stop=take("stop", i8),
        scale_index=take("scale_index", i8),
        offset=take("offset", i8),
        histograms=hist,
        signal=take("signal", cols["signal"].dtype, (-1, Q, L)),
        counts=take("counts", cols["counts"].dtype, (-1, L)),
        background=take("background", cols["background"].dtype, (-1, L)),
        saliency_mass=take("saliency_mass", f8),
        evidence=take("evidence", f8),
        presence_llr=take("presence_llr", f8),
        presence_z=take("presence_z", f8),
        image_shape=(R, C),
        n_slots=max_surfaces,
        stage=table.origin[idx].astype(np.int8, copy=False),
        moved_by=table.moved_codes()[idx],
    )
