"""The candidate table the clean-up passes work on, and what each pass did to it.

Not a stage: the data structure between stage 4 (the map pass, which fills the table)
and stage 6 (selection into :class:`~splidar.detection.Surfaces`). Every clean-up pass
(stage 5a-5e) is a pure function ``(CandidateTable, ...) -> PassResult``: it returns a
new table (its ``keep`` flags changed, or rows appended) and the counts of what it
added and removed; ``origin`` records, per candidate, the stage whose decision keeps it.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from .._arrays import (
    FLAT_CHUNK_KEYS,
    _mapped_values,
    _raw_chunks,
    write_raw_chunk,
    write_whole_file,
    zarr_write_rows,
)
from ._kernels import rank_in_pixel_sorted
from ._result import STAGES
from ._windows import _RowIndexing

__all__ = [
    "STAGES",
    "CandidateTable",
    "PassResult",
    "RawRows",
    "compact_columns",
    "remove_tree",
    "stage_code",
    "store_histograms",
]

#: Candidates per chunk of the histogram arrays written to a store
#: (:func:`store_histograms`): about 3 MB at Q = 4, L = 1, W = 13.
HIST_CHUNK = 2**12


def stage_code(name: str) -> int:
    """Index of a stage in :data:`STAGES`."""
    return STAGES.index(name)


@dataclass(frozen=True)
class CandidateTable:
    """Candidate surfaces of the whole image (one row each) and which are kept.

    Attributes
    ----------
    columns : mapping of str to ndarray (n, ...)
        The per-candidate fields (``row``, ``col``, ``depth_bin``, ``start``, ...).
        Treated as read-only: passes build new arrays.
    keep : ndarray (n,), bool
        Whether each candidate is currently kept.
    origin : ndarray (n,), int8
        Index into :data:`STAGES` of the stage that created or restored the candidate.
    hist_block, hist_row : ndarray (n,), int64
        Where each candidate's histograms are: the map pass's block (``-1``: the slope
        pass's ``extra_histograms``) and the row in that block's array.
    image_shape : (rows, cols)
    extra_histograms : ndarray (m, Q, L, W), float32, optional
        Histograms of the candidates a pass appended (``hist_block == -1``).
    moved_by : ndarray (n,), int8, optional
        Index into :data:`STAGES` of the last pass that moved the candidate's depth,
        ``-1`` for none (``None``: no pass moved any; :meth:`moved_codes`).
    """

    columns: Mapping[str, np.ndarray]
    keep: np.ndarray
    origin: np.ndarray
    hist_block: np.ndarray
    hist_row: np.ndarray
    image_shape: tuple[int, int]
    extra_histograms: np.ndarray | None = None
    moved_by: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.keep.size)

    def view(self) -> dict:
        """The columns with ``image_shape``, as the ``_quality`` passes take them."""
        return {**self.columns, "image_shape": self.image_shape}

    def compacted(self, n_bins: int) -> CandidateTable:
        """The table with ``hist_block`` and ``hist_row`` as int32 (the same values: a
        block holds fewer than 2**31 candidates) and the integer columns as
        :func:`compact_columns` makes them."""
        small = {}
        for k in ("hist_block", "hist_row"):
            v = getattr(self, k)
            if v.dtype.itemsize > 4 and (v.size == 0 or int(np.abs(v).max()) < 2**31):
                small[k] = v.astype(np.int32)
        cols = compact_columns(self.columns, self.image_shape, n_bins)
        return replace(self, columns=cols, **small)

    def moved_codes(self) -> np.ndarray:
        """``moved_by`` for every candidate, (n,) int8 (``-1``: not moved; rows a pass
        appended after the table's ``moved_by`` was made were not moved)."""
        out = np.full(len(self), -1, np.int8)
        if self.moved_by is not None:
            out[: self.moved_by.size] = self.moved_by
        return out

    def with_moved(self, idx: np.ndarray, name: str) -> CandidateTable:
        """The table with candidates ``idx`` recorded as moved by the pass ``name``."""
        if not np.size(idx):
            return self
        code = self.moved_codes()
        code[np.asarray(idx, np.int64)] = stage_code(name)
        return replace(self, moved_by=code)

    def with_columns(self, **new: np.ndarray) -> CandidateTable:
        """The table with the named (n, ...) columns added or replaced."""
        return replace(self, columns={**self.columns, **new})

    def without(self, *names: str) -> CandidateTable:
        """The table without the named columns."""
        return replace(self, columns={k: v for k, v in self.columns.items() if k not in names})


@dataclass(frozen=True)
class PassResult:
    """What one clean-up pass did.

    Attributes
    ----------
    name : str
        The stage (an entry of :data:`STAGES`).
    table : CandidateTable
        The table after the pass.
    added, removed : int
        Candidates the pass added or restored, and kept ones it removed.
    seconds : float
        Time spent in the pass.
    ran : bool
        False when the pass was switched off or had nothing to do.
    moved : int
        Candidates whose depth the pass changed (``"recentre"``).
    """

    name: str
    table: CandidateTable
    added: int
    removed: int
    seconds: float
    ran: bool = True
    moved: int = 0


def skipped(name: str, table: CandidateTable) -> PassResult:
    """A pass that did not run."""
    return PassResult(name, table, 0, 0, 0.0, ran=False)


def with_keep(name: str, table: CandidateTable, keep: np.ndarray, t0: float) -> PassResult:
    """The result of a pass that changed only the ``keep`` flags (timed from ``t0``)."""
    added = keep & ~table.keep
    removed = table.keep & ~keep
    origin = table.origin
    if added.any():
        origin = origin.copy()
        origin[added] = stage_code(name)
    new = replace(table, keep=keep, origin=origin)
    return PassResult(name, new, int(added.sum()), int(removed.sum()), time.perf_counter() - t0)


def _raster_ordered(row, col) -> bool:
    """Whether candidates come in raster order of ``(row, col)`` (as blocks emit them)."""
    if row.size < 2:
        return True
    dr = np.diff(row)
    return bool(np.all((dr > 0) | ((dr == 0) & (np.diff(col) >= 0))))


def _position_in_pixel(row, col) -> np.ndarray:
    """Position of each candidate among its pixel's, for candidates sorted by pixel."""
    new = np.ones(row.size, bool)
    new[1:] = (row[1:] != row[:-1]) | (col[1:] != col[:-1])
    return np.arange(row.size) - np.flatnonzero(new)[np.cumsum(new) - 1]


def _rank_in_pixel(row, col, score, keep):
    """Rank (0 = largest ``score``) of each kept candidate among its pixel's kept ones."""
    rank = np.full(row.size, -1, np.int64)
    if _raster_ordered(row, col):
        rank_in_pixel_sorted(
            np.ascontiguousarray(row, np.int64),
            np.ascontiguousarray(col, np.int64),
            np.ascontiguousarray(score, np.float64),
            np.ascontiguousarray(keep, np.bool_),
            rank,
        )
        return rank
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return rank
    idx = idx[np.lexsort((-score[idx], col[idx], row[idx]))]
    rank[idx] = _position_in_pixel(row[idx], col[idx])
    return rank


def compact_columns(columns: dict, image_shape: tuple[int, int], n_bins: int) -> dict:
    """The candidates' integer columns in the smallest integer type that holds every
    value they can take (the values unchanged): ``row``, ``col`` int32 (when ``rows x
    cols`` fits int32, so ``row * cols + col`` does too), ``start``, ``stop``, ``offset``
    int32 (bins, ``T`` < 2**30), ``scale_index`` int16, ``own_counts`` int16 when its
    counts fit. The clean-up passes compute on them as before (NumPy widens them
    wherever they meet int64 or float64 values); the selection gives
    :class:`~splidar.detection.Surfaces` its int64 fields back. Saves 52 of the about
    250 bytes a gathered candidate takes in the calling process."""
    R, C = (int(v) for v in image_shape)
    want = {}
    if R * C < 2**31:
        want.update(row=np.int32, col=np.int32)
    if n_bins < 2**30:
        want.update(start=np.int32, stop=np.int32, offset=np.int32)
    want["scale_index"] = np.int16
    own = columns.get("own_counts")
    if own is not None and (own.size == 0 or (own.min() >= -(2**15) and own.max() < 2**15)):
        # photon counts per bin: NumPy sums them as int64 and the numba kernels compute
        # on them as int64 (intp) whatever their type
        want["own_counts"] = np.int16
    out = dict(columns)
    for k, dt in want.items():
        if k in out and np.asarray(out[k]).dtype.itemsize > np.dtype(dt).itemsize:
            out[k] = np.asarray(out[k]).astype(dt)
    return out


def store_histograms(group, name: str, shape: tuple, *, data=None, compressed: bool = True):
    """A float32 Zarr array ``name`` of ``shape`` ``(n, Q, L, W)`` in the Zarr group
    ``group`` (replaced if it exists), chunked by :data:`HIST_CHUNK` candidates,
    compressed with lz4 (histograms are zero outside their supports) unless
    ``compressed=False``; ``data``, when given, written to it.

    The surfaces' histograms (``detect(store=...)``) are written uncompressed: on the
    ``--large`` benchmark scene lz4 stored histograms in 82 % of their bytes (27 % of
    the values are 0), for 1.5-2x the CPU of a plain write and 2-4x that of a plain
    read (``benchmarks/README.md``, "Branch dist24"; the tiles' candidate histograms are
    raw files, :class:`RawRows`), and stage 7 rewrites its moved surfaces' rows in
    place in the raw chunk files (:func:`write_rows`) instead of decoding and encoding
    every chunk they fall in ("call39" in ``benchmarks/README.md``).

    Every chunk is written, even one of zeros (Zarr's ``write_empty_chunks``): Zarr would
    otherwise compare each chunk with the fill value before writing it, bit pattern by
    bit pattern (0.8 ms per MB, a pass over every histogram written; "dist27" in
    ``benchmarks/README.md``). The values read back are the same. Data in one chunk of
    an uncompressed array is written as its chunk file
    (:func:`~splidar._arrays.write_raw_chunk`: the same bytes)."""
    from zarr.codecs import BloscCodec

    fast = [BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")] if compressed else None
    chunks = (max(1, min(int(shape[0]), HIST_CHUNK)),) + tuple(int(v) for v in shape[1:])
    z = group.create_array(
        name, shape=tuple(int(v) for v in shape), chunks=chunks, dtype="float32",
        compressors=fast, overwrite=True, config={"write_empty_chunks": True},
        chunk_key_encoding=FLAT_CHUNK_KEYS,
    )  # fmt: skip
    if data is not None and len(data):
        raw = None if chunks[0] < len(data) else _raw_chunks(z)
        if raw is None:
            z[...] = data
        else:  # one raw chunk: its file (past the page cache when large enough)
            write_raw_chunk(raw, (0,) * len(shape), np.asarray(data, np.float32))
    return z


class RawRows(_RowIndexing):
    """A read-only array of rows kept in one file of its C-order bytes: a tile's
    candidate histograms ``(n, Q, L, W)`` float32 on a Dask cube with a store, written
    by the worker that computed them and read once, at the selected rows, by the calling
    process (stage 6; then removed with the ``candidate_histograms`` folder).

    ``r[key]`` gives the selected rows as a NumPy array (integers, slices, integer or
    boolean arrays on the first axis, as :class:`~splidar.detection._windows.SupportWindows`);
    picklable (the path, shape and dtype only). A Zarr array of one raw chunk held the
    same bytes in a chunk file, but also made a folder and its ``zarr.json`` and
    rewrote the parent group's ``zarr.json`` for each tile, through Zarr's event loop:
    7 % of a map tile's time on issue #16's cluster run ("Lead, session 31" in
    ``benchmarks/README.md``).

    Parameters
    ----------
    path : pathlib.Path
    shape : tuple of int
    dtype : numpy dtype
    """

    #: Rows read by mapping the file at those rows only (random access) rather than as
    #: the range from the first to the last, when the range is more than this many times
    #: longer (as the selection's reads of Zarr arrays, ``_6_select.ROWS_APART``).
    APART = 16

    def __init__(self, path, shape: tuple, dtype):
        self.path = path
        self.shape = tuple(int(v) for v in shape)
        self.dtype = np.dtype(dtype)

    @classmethod
    def write(cls, path, data: np.ndarray) -> RawRows:
        """``data`` written as the new file ``path`` (whole: a temporary file renamed;
        inside ``deferred_chunk_writes`` by the writer thread)."""
        data = np.ascontiguousarray(data)
        write_whole_file(path, data)
        return cls(path, data.shape, data.dtype)

    def __len__(self) -> int:
        return self.shape[0]

    def rows(self, idx) -> np.ndarray:
        """Rows ``idx`` (non-negative, in bounds, any order, repeats allowed)."""
        idx = np.asarray(idx, np.int64).reshape(-1)
        if idx.size == 0:
            return np.empty((0,) + self.shape[1:], self.dtype)
        lo, hi = int(idx.min()), int(idx.max()) + 1
        if idx.size * self.APART < hi - lo:  # few rows far apart: those rows' pages
            return _mapped_values(self.path, self.dtype, self.shape, (idx,))
        per_row = int(np.prod(self.shape[1:], dtype=np.int64))
        got = np.fromfile(
            self.path, self.dtype, count=(hi - lo) * per_row,
            offset=lo * per_row * self.dtype.itemsize,
        )  # fmt: skip
        if got.size != (hi - lo) * per_row:
            raise OSError(f"{self.path}: {got.size} values, {(hi - lo) * per_row} expected")
        return got.reshape((hi - lo,) + self.shape[1:])[idx - lo]


def write_rows(z, idx, values) -> None:
    """``z[idx[i]] = values[i]`` for a Zarr array ``z`` (e.g. a detection's stored
    histograms, :func:`store_histograms`), as one orthogonal selection: each chunk
    holding some of the rows is read, changed and written once, not once per row
    (a row's write decodes and encodes its whole chunk: 4,096 histograms). Where an
    index repeats, its last value is written, as in a loop of single writes. An array
    stored raw in a local folder (the surfaces' histograms, :func:`store_histograms`
    with ``compressed=False``) gets the rows' bytes written in its chunk files
    (:func:`splidar._arrays.zarr_write_rows`; the same values)."""
    idx = np.asarray(idx, np.int64).reshape(-1)
    if idx.size == 0:
        return
    values = np.asarray(values)
    # the last occurrence of each index, in ascending order
    _, first_rev = np.unique(idx[::-1], return_index=True)
    last = idx.size - 1 - first_rev
    if not zarr_write_rows(z, idx[last], values[last]):
        z.set_orthogonal_selection((idx[last],), values[last])


#: Threads that remove a directory's entries (:func:`remove_tree`).
REMOVE_THREADS = 8


def remove_tree(path) -> None:
    """Remove the directory ``path`` and everything in it (nothing if it does not exist).

    Its top-level entries are removed on :data:`REMOVE_THREADS` threads: a Zarr store's
    arrays are many small files and nested chunk folders, and a file system that trims
    freed blocks at once (ext4 mounted with ``discard``) spends milliseconds on each
    removal, waiting, not computing. The candidates' histograms of a 512 x 1024 slab
    (66 arrays, 968 entries): 2.2-2.5 s one by one, 0.10-0.16 s on 8 threads.
    """
    import os
    import shutil
    from concurrent.futures import ThreadPoolExecutor

    path = os.fspath(path)
    try:
        entries = [e.path for e in os.scandir(path)]
    except (FileNotFoundError, NotADirectoryError):
        return

    def remove(p):
        if os.path.isdir(p) and not os.path.islink(p):
            shutil.rmtree(p, ignore_errors=True)
        else:
            try:
                os.remove(p)
            except FileNotFoundError:
                pass

    with ThreadPoolExecutor(max(1, min(REMOVE_THREADS, len(entries)))) as ex:
        list(ex.map(remove, entries))
    shutil.rmtree(path, ignore_errors=True)
