"""Reading image-size ``(rows, cols, T)`` arrays that may live on disk (Zarr, Dask).

``Detection.saliency``, ``mask`` and ``threshold`` are NumPy arrays, or chunked Zarr
arrays when :func:`splidar.detect` was given ``store=``. Exports and figures read them
through these helpers, a block of rows at a time, so that a detection larger than RAM
can still be summarised and drawn.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

__all__ = ["row_blocks", "sample_rows", "sum_over_rows"]

#: Values read at once by :func:`row_blocks` (about 64 MB of float32).
_BLOCK_VALUES = 1 << 24


def row_blocks(a, *, max_values: int = _BLOCK_VALUES) -> Iterator[np.ndarray]:
    """Consecutive blocks of rows of ``a`` (any array with ``shape`` and slicing), as NumPy."""
    n = int(a.shape[0])
    per_row = int(np.prod(a.shape[1:], dtype=np.int64)) or 1
    step = max(1, max_values // per_row)
    for r0 in range(0, n, step):
        yield np.asarray(a[r0 : r0 + step])


def sample_rows(a, *, max_values: int = _BLOCK_VALUES) -> np.ndarray:
    """``a`` as NumPy, or evenly spaced rows of it when it holds more than ``max_values``."""
    if isinstance(a, np.ndarray) or np.ndim(a) == 0:
        return np.asarray(a)
    n = int(a.shape[0])
    per_row = int(np.prod(a.shape[1:], dtype=np.int64)) or 1
    if n * per_row <= max_values:
        return np.asarray(a[:])
    rows = np.unique(np.linspace(0, n - 1, max(1, max_values // per_row)).round().astype(int))
    return np.concatenate([np.asarray(a[r : r + 1]) for r in rows], axis=0)


def sum_over_rows(a, axis_keep: int) -> np.ndarray:
    """Sum of ``a`` (rows, cols, T) over all axes but ``axis_keep`` (0, 1 or 2), by blocks."""
    if isinstance(a, np.ndarray):
        axes = tuple(i for i in range(a.ndim) if i != axis_keep)
        return a.sum(axis=axes, dtype=np.int64)
    if axis_keep == 0:
        return np.concatenate([b.sum(axis=(1, 2), dtype=np.int64) for b in row_blocks(a)], axis=0)
    axes = tuple(i for i in range(a.ndim) if i != axis_keep)
    total = None
    for b in row_blocks(a):
        s = b.sum(axis=axes, dtype=np.int64)
        total = s if total is None else total + s
    return total


def zarr_rows_into(z, lo: int, hi: int, out: np.ndarray) -> np.ndarray:
    """Rows ``[lo, hi)`` of the Zarr array ``z`` decoded straight into ``out`` (no copy).

    ``out`` has shape ``(hi - lo,) + z.shape[1:]`` and ``z``'s dtype. One whole chunk of
    whole rows of a Zarr 3 array stored with zstd in a local folder
    (:func:`_zstd_chunks`) is decoded from its chunk file into ``out`` itself
    (:func:`_zstd_chunk_into`); any other read is Zarr's: Zarr 3 takes an ``NDBuffer``
    over ``out``, zarr 2 the NumPy array itself.
    """
    if _zstd_chunk_into(z, lo, hi, out):
        return out
    try:
        from zarr.core.buffer import default_buffer_prototype
    except ImportError:  # zarr 2
        z.get_basic_selection((slice(lo, hi),), out=out)
        return out
    nd = default_buffer_prototype().nd_buffer
    z.get_basic_selection((slice(lo, hi),), out=nd.from_numpy_array(out))
    return out


def _zstd_chunk_into(z, lo: int, hi: int, out: np.ndarray) -> bool:
    """Rows ``[lo, hi)`` of ``z`` decoded from their chunk file straight into ``out`` when
    they are one whole chunk of whole rows of an array stored with zstd in a local
    folder (:func:`_zstd_chunks`); False (nothing read) otherwise, for Zarr to read.

    Zarr decodes a chunk into a fresh buffer of the chunk's size and then copies it into
    ``out``: on a ``dask.distributed`` worker (glibc's ``MALLOC_TRIM_THRESHOLD_`` set by
    the nanny, so every such buffer is a new mapping) each 32 MB chunk of the ``--large``
    cube faults 8,000 fresh pages in, 2.2-2.4 against 0.55 s of CPU for the cube's 96
    chunks (``benchmarks/README.md``, "st141, session 28"). Here the chunk file's zstd
    frame (Zarr's ``zstd`` codec is numcodecs' ``Zstd``) is decoded by numcodecs into
    ``out``; a frame that does not declare exactly one chunk's bytes, or that numcodecs
    refuses, is left to Zarr. A chunk never written is the fill value. Same bytes as
    Zarr's read."""
    if hi - lo < 1 or out.dtype != np.dtype(z.dtype) or not out.flags.c_contiguous:
        return False
    local = _zstd_chunks(z)
    if local is None:
        return False
    folder, chunk, md = local
    if lo % chunk[0] or hi - lo != chunk[0] or tuple(chunk[1:]) != tuple(z.shape[1:]):
        return False
    path = folder / md.encode_chunk_key((lo // chunk[0],) + (0,) * (len(chunk) - 1))
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        out[...] = md.fill_value
        return True
    if _zstd_frame_size(data) != out.nbytes:
        return False
    from numcodecs import Zstd

    try:
        Zstd().decode(data, out=out.reshape(-1).view(np.uint8))
    except (ValueError, RuntimeError):  # numcodecs' refusals: Zarr reads it (or says why)
        return False
    return True


def _zstd_frame_size(data: bytes) -> int | None:
    """The content size a zstd frame's header declares (RFC 8878, section 3.1.1.1: the
    frame header descriptor, then the window descriptor unless single-segment, the
    dictionary id and the frame content size field), or None (no zstd frame, or no
    size declared)."""
    if len(data) < 6 or data[:4] != b"\x28\xb5\x2f\xfd":
        return None
    desc = data[4]
    single = (desc >> 5) & 1
    n = (single, 2, 4, 8)[desc >> 6]  # the size field's bytes
    at = 5 + (1 - single) + (0, 1, 2, 4)[desc & 3]
    if n == 0 or len(data) < at + n:
        return None
    size = int.from_bytes(data[at : at + n], "little")
    return size + 256 if n == 2 else size


def _zstd_chunks(z):
    """``(folder, chunk shape, metadata)`` of a Zarr 3 array whose chunks are stored with
    the ``bytes`` codec (one-byte values, or in native order) then ``zstd`` alone, without
    storage transformer, on a regular grid, in a local folder (a chunk file is then one
    zstd frame of the chunk's C-order bytes); else None."""
    local = _local_chunks(z)
    if local is None:
        return None
    folder, chunk, dtype, md = local
    from zarr.codecs import ZstdCodec

    codecs = tuple(md.codecs)
    if len(codecs) != 2 or not isinstance(codecs[1], ZstdCodec) or dtype != np.dtype(z.dtype):
        return None
    return folder, chunk, md


def _raw_chunks(z):
    """``(folder, chunk shape, dtype, metadata)`` of a Zarr 3 array whose chunks are
    stored raw (the ``bytes`` codec alone, no storage transformer, a regular grid) in a
    local folder, whose chunk files are then the chunks' C-order bytes; else None."""
    local = _local_chunks(z)
    if local is None or len(local[3].codecs) != 1:
        return None
    return local


def _local_chunks(z):
    """``(folder, chunk shape, dtype, metadata)`` of a Zarr 3 array in a local folder
    (``LocalStore``) on a regular grid, without storage transformer, whose first codec
    is ``bytes`` (``dtype``: the stored values' byte order); else None."""
    try:
        from zarr.codecs import BytesCodec
        from zarr.core.chunk_grids import RegularChunkGrid
        from zarr.storage import LocalStore
    except ImportError:  # zarr 2
        return None
    md = getattr(z, "metadata", None)
    if getattr(md, "zarr_format", None) != 3 or not isinstance(z.store, LocalStore):
        return None
    codecs = tuple(md.codecs)
    if not codecs or not isinstance(codecs[0], BytesCodec) or md.storage_transformers:
        return None
    if not isinstance(md.chunk_grid, RegularChunkGrid):
        return None
    dtype = np.dtype(z.dtype)
    if dtype.itemsize > 1:
        if codecs[0].endian is None:
            return None
        dtype = dtype.newbyteorder("<" if codecs[0].endian.value == "little" else ">")
    folder = Path(os.fspath(z.store.root)) / z.store_path.path
    return folder, tuple(int(k) for k in md.chunk_grid.chunk_shape), dtype, md


def zarr_voxels(z, index: tuple) -> np.ndarray | None:
    """``z[index[0][i], index[1][i], ...]`` (a coordinate selection) of a Zarr array whose
    chunks are stored raw in a local folder (:func:`_raw_chunks`), read from the chunk
    files at those voxels only; None for any other array (read it with Zarr).

    Zarr reads a whole chunk for any voxel of it (5.8 MB for a saliency chunk of
    16 x 90 x 1000 float32): a support of a few bins read this way costs a chunk's read.
    A raw chunk file is the chunk's bytes in C order, so each chunk that holds some of
    the voxels is mapped (``mmap``, random access) and only the pages of its voxels are read. A
    chunk never written is the fill value. Same values as Zarr's selection; None (Zarr's
    read) when a chunk file is not one whole chunk's bytes.

    Parameters
    ----------
    z : zarr.Array
    index : tuple of int arrays (n,)
        One integer array per axis, in bounds (non-negative).

    Returns
    -------
    ndarray (n,) of ``z``'s dtype, or None
    """
    raw = _raw_chunks(z)
    if raw is None:
        return None
    folder, chunk, dtype, md = raw
    index = tuple(np.asarray(i, np.int64) for i in index)
    n = index[0].size
    out = np.empty(n, np.dtype(z.dtype))
    if n == 0:
        return out
    grid = tuple(-(-int(s) // c) for s, c in zip(z.shape, chunk, strict=True))
    key = np.ravel_multi_index(tuple(i // c for i, c in zip(index, chunk, strict=True)), grid)
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    size = int(np.prod(chunk)) * dtype.itemsize
    fill = np.asarray(md.fill_value, np.dtype(z.dtype))
    parts = []
    for sel in np.split(order, cuts):
        where = np.unravel_index(int(key[sel[0]]), grid)
        path = folder / md.encode_chunk_key(tuple(int(w) for w in where))
        if not path.exists():
            out[sel] = fill
            continue
        if path.stat().st_size != size:
            return None
        within = tuple(i[sel] % c for i, c in zip(index, chunk, strict=True))
        _prefetch(path, np.ravel_multi_index(within, chunk) * dtype.itemsize)
        parts.append((sel, path, within))
    for sel, path, within in parts:
        out[sel] = _mapped_values(path, dtype, chunk, within)
    return out


def _whole_row_chunks(z) -> tuple:
    """``(raw, shape)``: :func:`_raw_chunks` of ``z`` when its chunks are whole rows (every
    axis but the first whole), else ``(None, shape)``."""
    raw = _raw_chunks(z)
    shape = tuple(int(v) for v in z.shape)
    if raw is None or tuple(raw[1][1:]) != shape[1:]:
        return None, shape
    return raw, shape


def _by_chunk(rows: np.ndarray, step: int) -> tuple:
    """``(key, order, cuts)``: each row's chunk ``key`` (``rows // step``), the rows'
    stable ``order`` by it, and where a new chunk starts in that order (``cuts``, for
    ``np.split(order, cuts)``)."""
    key = rows // step
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    return key, order, cuts


def zarr_take_rows(z, rows: np.ndarray) -> np.ndarray | None:
    """``z[rows]`` (rows of the first axis) of a Zarr array stored raw in a local folder
    (:func:`_raw_chunks`) in chunks of whole rows, read from the chunk files at those
    rows only (each chunk holding some of them mapped, :func:`_mapped_values`); None for
    any other array, or when a chunk file is not one whole chunk's bytes (read them
    with Zarr). A chunk never written is the fill value. Same values as Zarr's read.

    Zarr reads a whole chunk (4,096 histograms) for any row of it: a few rows of each
    of many chunks (the candidates the recentring moved) cost every chunk's read.

    Parameters
    ----------
    z : zarr.Array
    rows : int array (n,)
        Rows in bounds (non-negative), in any order, repeats allowed.

    Returns
    -------
    ndarray (n,) + z.shape[1:] of ``z``'s dtype, or None
    """
    raw, shape = _whole_row_chunks(z)
    if raw is None:
        return None
    folder, chunk, dtype, md = raw
    rows = np.asarray(rows, np.int64).reshape(-1)
    out = np.empty((rows.size,) + shape[1:], np.dtype(z.dtype))
    key, order, cuts = _by_chunk(rows, chunk[0])
    tail = (0,) * (len(shape) - 1)
    size = int(np.prod(chunk)) * dtype.itemsize
    for sel in np.split(order, cuts) if rows.size else []:
        path = folder / md.encode_chunk_key((int(key[sel[0]]),) + tail)
        if not path.exists():
            out[sel] = np.asarray(md.fill_value, out.dtype)
            continue
        if path.stat().st_size != size:
            return None
        out[sel] = _mapped_values(path, dtype, chunk, (rows[sel] % chunk[0],))
    return out


def zarr_write_rows(z, idx: np.ndarray, values: np.ndarray) -> bool:
    """``z[idx[i]] = values[i]`` written straight into the chunk files of a Zarr array
    stored raw in a local folder (:func:`_raw_chunks`) in chunks of whole rows (a
    detection's stored histograms, ``store_histograms(compressed=False)``); False, and
    nothing written, for any other array or when a chunk file the rows fall in is
    missing or not one whole chunk's bytes (write them with Zarr).

    Zarr writes a row by reading, changing and writing its whole chunk (4,096
    histograms); a raw chunk file is the chunk's bytes in C order, so each chunk holding
    some of the rows is mapped and only the rows' bytes change. The values read back are
    Zarr's write's (the same cast to ``z``'s dtype).

    Parameters
    ----------
    z : zarr.Array
    idx : int array (n,)
        Distinct rows (first axis), in bounds.
    values : array (n,) + z.shape[1:]

    Returns
    -------
    bool
        Whether the rows were written (False also when a file cannot be mapped for
        writing: then some rows may be written already, and Zarr's write of all of
        them gives the same array).
    """
    raw, shape = _whole_row_chunks(z)
    if raw is None:
        return False
    folder, chunk, dtype, md = raw
    idx = np.asarray(idx, np.int64).reshape(-1)
    key, order, cuts = _by_chunk(idx, chunk[0])
    groups = np.split(order, cuts) if idx.size else []
    tail = (0,) * (len(shape) - 1)
    paths = [folder / md.encode_chunk_key((int(key[g[0]]),) + tail) for g in groups]
    size = int(np.prod(chunk)) * dtype.itemsize
    if not all(p.is_file() and p.stat().st_size == size for p in paths):
        return False  # checked before any write: all rows through Zarr
    values = np.asarray(values)
    try:
        for g, path in zip(groups, paths, strict=True):
            m = np.memmap(path, dtype=dtype, mode="r+", shape=chunk)
            m[idx[g] % chunk[0]] = values[g]  # (no msync: the page cache is the file's)
            del m
    except OSError:  # a file system that cannot map for writing: Zarr writes every row
        return False
    return True


def write_raw_chunk(raw: tuple, where: tuple, value: np.ndarray) -> None:
    """One whole chunk of a Zarr 3 array whose chunks are stored raw in a local folder
    (``raw`` from :func:`_raw_chunks`), written as its chunk file: ``value`` (the chunk's
    shape) at chunk grid position ``where``, its C-order bytes in the array's byte order.

    The file Zarr writes for it (``bytes`` codec alone: the same bytes at the same key,
    ``metadata.encode_chunk_key``), written as Zarr's local store writes one (a temporary
    file in the chunk's folder, then renamed over the key: never half a chunk), without
    Zarr's per-chunk pipeline around it: 0.27-0.33 against 0.37-0.58 s of CPU for a
    256-row slab's saliency in 16 x 90-pixel chunks (``benchmarks/README.md``, "halo39,
    session 27"). Zarr reads the values back unchanged (every chunk written, as with
    ``write_empty_chunks``). A chunk file of at least :data:`DIRECT_MIN_BYTES` is written
    past the page cache (:func:`_write_direct`); inside :func:`deferred_chunk_writes` it
    is copied and written by a writer thread, in place when the block ends.
    """
    folder, chunk, dtype, md = raw
    if tuple(value.shape) != tuple(chunk):
        raise ValueError(f"a chunk of shape {tuple(chunk)} expected, got {tuple(value.shape)}")
    path = folder / md.encode_chunk_key(tuple(int(w) for w in where))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_whole_file(path, np.ascontiguousarray(value, dtype=dtype))


def write_whole_file(path: Path, value: np.ndarray) -> None:
    """``value``'s C-order bytes as the file ``path``, written as Zarr's local store
    writes a chunk (a temporary file beside it, then renamed over ``path``: never half a
    file), past the page cache when large enough (:func:`_write_direct`), and inside
    :func:`deferred_chunk_writes` by the writer thread (``value`` copied first)."""
    import uuid

    data = memoryview(np.ascontiguousarray(value)).cast("B")
    tmp = path.with_suffix(f".{uuid.uuid4().hex}.partial")
    queue = getattr(_DEFERRED, "queue", None)
    if queue is not None and _direct_possible(tmp, data.nbytes):
        queue.put(tmp, path, data)
        return
    _write_file(tmp, path, data)


def _write_file(tmp: Path, path: Path, data: memoryview) -> None:
    """``data`` written as ``tmp`` (past the page cache where possible), then renamed
    over ``path``; ``tmp`` removed on any error."""
    try:
        if not _write_direct(tmp, data):
            with open(tmp, "wb") as f:
                f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


_DEFERRED = threading.local()
_WRITER: list = []  # the process's one chunk-writer thread pool, made when first needed
_WRITER_LOCK = threading.Lock()
if hasattr(os, "register_at_fork"):  # a forked child has no writer thread: it makes its own
    os.register_at_fork(after_in_child=_WRITER.clear)


class _WriteQueue:
    """The direct chunk writes of one thread's :func:`deferred_chunk_writes` block: each
    chunk copied into one of ``depth`` page-aligned buffers (kept by the thread) and
    written by the process's writer thread while the caller goes on."""

    def __init__(self, depth: int):
        self.depth, self.pending = depth, []
        self.buffers = getattr(_DEFERRED, "buffers", None) or []
        _DEFERRED.buffers = self.buffers

    def put(self, tmp: Path, path: Path, data: memoryview) -> None:
        if len(self.pending) >= self.depth:  # every buffer in flight: the oldest done
            self.pending.pop(0)[1].result()
        busy = {id(b) for b, _ in self.pending}
        free = [b for b in self.buffers if id(b) not in busy]
        n = data.nbytes
        buf = next((b for b in free if b.size >= n), None)
        if buf is None:
            if free:  # a free buffer too small for this chunk: replaced
                self.buffers.remove(free[0])
            buf = _new_aligned(n)
            self.buffers.append(buf)
        buf[:n] = np.frombuffer(data, np.uint8)
        fut = _writer().submit(_write_file, tmp, path, memoryview(buf[:n]))
        self.pending.append((buf, fut))

    def wait(self) -> None:
        """Every write done; the first error raised (after all have ended)."""
        error = None
        for _, fut in self.pending:
            try:
                fut.result()
            except BaseException as e:  # noqa: BLE001 (re-raised below)
                error = error or e
        self.pending.clear()
        if error is not None:
            raise error


def _writer():
    with _WRITER_LOCK:
        if not _WRITER:
            from concurrent.futures import ThreadPoolExecutor

            _WRITER.append(ThreadPoolExecutor(1, thread_name_prefix="splidar-chunk-writer"))
        return _WRITER[0]


@contextlib.contextmanager
def deferred_chunk_writes(depth: int = 2):
    """Within the block, this thread's :func:`write_raw_chunk` calls that go past the
    page cache (:func:`_write_direct`) return once the chunk is copied into one of
    ``depth`` page-aligned buffers: a writer thread writes the files while the caller
    computes the next chunks (the disk's time overlapped, not waited for: on issue #16's
    cube the workers otherwise sat 8 % of the map pass in I/O wait; "Lead, session 28"
    in ``benchmarks/README.md``). The block's end waits for every write and raises the
    first error; a file is only ever renamed into place whole. Nested blocks are one."""
    if getattr(_DEFERRED, "queue", None) is not None:
        yield
        return
    queue = _DEFERRED.queue = _WriteQueue(depth)
    try:
        yield
    except BaseException:
        _DEFERRED.queue = None
        try:
            queue.wait()
        except BaseException:  # noqa: BLE001 (the block's own error goes first)
            pass
        raise
    _DEFERRED.queue = None
    queue.wait()


#: The chunk key encoding of the arrays a detection writes in its store (the saliency, the
#: map, the histograms): Zarr 3's default keys with ``.`` between the grid indices
#: (``c.12.3.0``), every chunk file in the array's folder. With ``/`` (Zarr's default)
#: each chunk makes folders too (``c/12/3/0``): new inodes besides the chunk file's
#: (issue #16's cluster run: 11,986 folders for 7,098 files), and on this project's VMs
#: (ext4 without a journal, where each new inode skips every inode deleted in the last
#: 3000 s, one buffer lookup each) creating them was 8 % of all CPU during the map pass
#: ("Lead, session 30" in ``benchmarks/README.md``). A Zarr reader follows the keys the
#: array's metadata names: nothing else changes.
FLAT_CHUNK_KEYS = {"name": "default", "separator": "."}

#: Chunk files at least this large are written past the page cache (:func:`_write_direct`).
DIRECT_MIN_BYTES = 1 << 20
#: The alignment ``O_DIRECT`` asks of the buffer, the file offset and the length: a page
#: (every logical block size of Linux's block devices divides it).
_ALIGN = 4096
#: Devices (``st_dev``) whose file system refused ``O_DIRECT`` (e.g. tmpfs): not retried.
_NO_DIRECT: set = set()
_DIRECT_BUFFERS = threading.local()


def _direct_possible(tmp: Path, n: int) -> bool:
    """Whether a file of ``n`` bytes at ``tmp`` is written past the page cache
    (:func:`_write_direct`: Linux, at least :data:`DIRECT_MIN_BYTES` of whole pages, not
    turned off, a file system not known to refuse it)."""
    if not getattr(os, "O_DIRECT", 0) or n - n % _ALIGN < DIRECT_MIN_BYTES:
        return False
    if os.environ.get("SPLIDAR_DIRECT_IO") == "0":
        return False
    try:
        return os.stat(tmp.parent).st_dev not in _NO_DIRECT
    except OSError:
        return False


def _aligned_buffer(n: int) -> np.ndarray:
    """This thread's kept ``n``-byte buffer, its address a multiple of :data:`_ALIGN`
    (reused chunk after chunk: its pages are touched once per thread, not per chunk)."""
    have = getattr(_DIRECT_BUFFERS, "buf", None)
    if have is None or have.size < n:
        have = _DIRECT_BUFFERS.buf = _new_aligned(n)
    return have[:n]


def _new_aligned(n: int) -> np.ndarray:
    """A new ``n``-byte uint8 array whose address is a multiple of :data:`_ALIGN`."""
    raw = np.empty(n + _ALIGN, np.uint8)
    off = (-raw.ctypes.data) % _ALIGN
    return raw[off : off + n]


def _write_direct(tmp: Path, data: memoryview) -> bool:
    """Write ``data`` as the new file ``tmp`` past the page cache; False (nothing left
    behind) where that is not possible, for the caller to write it the usual way.

    A chunk file written once and read back sparsely (the map pass's saliency: 4 bytes
    per voxel, 12.6 GB on issue #16's 3-G-voxel cube) gains nothing from the page cache,
    and filling it costs the kernel a copy into freshly allocated pages: on the virtual
    machines measured this was a third of a cluster's map pass (0.4-1.2 GB/s of system
    CPU, against 2.1-2.4 GB/s and almost no CPU for ``O_DIRECT``; ``benchmarks/README.md``,
    "Lead, session 28"). The bytes up to the last whole :data:`_ALIGN` go through
    ``O_DIRECT`` from an aligned copy (:func:`_aligned_buffer`), the tail through a
    plain write; the file holds the same bytes either way. Used on Linux for files of at
    least :data:`DIRECT_MIN_BYTES`; a file system that refuses ``O_DIRECT`` (``EINVAL``
    on opening, e.g. tmpfs) is remembered and written the usual way, and the environment
    variable ``SPLIDAR_DIRECT_IO=0`` turns it off (e.g. a network file system where a
    synchronous write costs more than the page cache's copy).
    """
    n = data.nbytes
    head = n - n % _ALIGN
    if not _direct_possible(tmp, n):
        return False
    dev = os.stat(tmp.parent).st_dev
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_DIRECT, 0o666)
    except OSError as e:
        if e.errno != errno.EINVAL:
            raise
        _NO_DIRECT.add(dev)
        return False
    try:
        src = np.frombuffer(data, np.uint8, count=head)
        if src.ctypes.data % _ALIGN == 0:  # already aligned (a deferred write's buffer)
            buf = src
        else:
            buf = _aligned_buffer(head)
            buf[:] = src
        view = memoryview(buf)
        done = 0
        while done < head:
            done += os.write(fd, view[done:head])
    except OSError as e:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        if e.errno != errno.EINVAL:
            raise
        _NO_DIRECT.add(dev)
        return False
    os.close(fd)
    if head < n:
        with open(tmp, "ab") as f:
            f.write(data[head:])
    return True


def _prefetch(path, offsets: np.ndarray) -> None:
    """Ask the kernel to read the pages holding the byte ``offsets`` of the file
    ``path`` now (``POSIX_FADV_WILLNEED``, runs of consecutive pages together), without
    waiting: called for every chunk file of a read before any is touched, so that a
    store not in the page cache (written past it, :func:`_write_direct`) is read with
    many requests in flight instead of one page fault at a time. Advice only: the bytes
    read are the same, and a file system that ignores it is read as before."""
    if not hasattr(os, "posix_fadvise") or offsets.size == 0:
        return
    page = 4096
    pages = np.unique(offsets // page)
    starts = np.flatnonzero(np.diff(pages, prepend=pages[0] - 2) != 1)
    ends = np.append(starts[1:], pages.size)
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        for a, b in zip(pages[starts].tolist(), (pages[ends - 1] + 1).tolist(), strict=True):
            os.posix_fadvise(fd, a * page, (b - a) * page, os.POSIX_FADV_WILLNEED)
    except OSError:
        pass
    finally:
        os.close(fd)


def _mapped_values(path, dtype, chunk: tuple, within: tuple) -> np.ndarray:
    """The values at ``within`` (index arrays into the chunk) of a raw chunk file, mapped
    for random access: no read-ahead around each page touched (on a chunk not in the
    page cache the kernel's default read-ahead reads about 32 pages per voxel; 1.5 s
    against 0.13 s of wall for dist30's 900 supports, ``benchmarks/README.md``)."""
    import mmap

    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        if hasattr(mm, "madvise") and hasattr(mmap, "MADV_RANDOM"):
            mm.madvise(mmap.MADV_RANDOM)
        a = np.frombuffer(mm, dtype).reshape(chunk)
        values = a[within]  # a copy (fancy indexing): the mapping can close
        del a
    return values
