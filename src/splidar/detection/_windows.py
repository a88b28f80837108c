"""Candidates' windows stored over their supports only (not a stage: a container).

The map pass (stage 4) computes each candidate's clean histograms ``(Q, L, W)`` over a
window of ``W`` bins about its peak, zero outside the candidate's support ``[start,
stop)`` (``eq:background_final``; ``_kernels._clean_responses``). With a long IRF the
window is wide (``W = 681`` bins at the face file's native bin) and so are the supports,
but a candidate's support is a part of its window only (median 245 of 681 bins there):
the dense ``(S, Q, L, W)`` arrays of every candidate were the largest arrays of a
detection after the saliency (``benchmarks/README.md``, "mem31, session 23").
:class:`SupportWindows` keeps each row's bins inside its support, one after the other in
one flat array, and gives the dense rows back where they are indexed (zero outside the
support, the same values bit for bit).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["OwnBackground", "SupportWindows"]


@njit(cache=True, nogil=True)
def _pack(dense, rows, first, length, pos, out):
    """``out[pos[i]:pos[i + 1]]`` = ``dense[rows[i], :, first[i]:first[i] + length[i]]``
    (``dense`` (S, M, W)), row ``i``'s M parts one after the other."""
    M = dense.shape[1]
    for i in range(rows.size):
        r, a, m, p = rows[i], first[i], length[i], pos[i]
        for k in range(M):
            for w in range(m):
                out[p + k * m + w] = dense[r, k, a + w]


@njit(cache=True, nogil=True)
def _unpack(data, idx, first, length, pos, out):
    """``out[i]`` (M, W) = row ``idx[i]``: its stored bins, zero elsewhere."""
    M, W = out.shape[1], out.shape[2]
    zero = out.dtype.type(0)
    for i in range(idx.size):
        j = idx[i]
        a, m, p = first[j], length[j], pos[j]
        for k in range(M):
            for w in range(a):
                out[i, k, w] = zero
            for w in range(m):
                out[i, k, a + w] = data[p + k * m + w]
            for w in range(a + m, W):
                out[i, k, w] = zero


class _RowIndexing:
    """NumPy-style indexing of the first axis over a ``rows(idx)`` method: an int, a
    slice, an integer or boolean array, a tuple whose first entry is one of those (the
    rest index the rows' other axes); ``np.asarray`` gives every row."""

    __slots__ = ()

    def __getitem__(self, key) -> np.ndarray:
        if isinstance(key, tuple):
            head, rest = key[0], key[1:]
            return self[head][(slice(None), *rest)] if np.ndim(head) else self[head][rest]
        if isinstance(key, (int, np.integer)):
            return self.rows(np.array([key]))[0]
        if isinstance(key, slice):
            return self.rows(np.arange(len(self))[key])
        key = np.asarray(key)
        if key.dtype == bool:
            key = np.flatnonzero(key)
        return self.rows(key)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self.rows(np.arange(len(self)))
        return a if dtype is None else a.astype(dtype, copy=False)


class SupportWindows(_RowIndexing):
    """A read-only stand-in for an ``(n, *inner, W)`` array of windows that are zero
    outside one run of bins per row (a candidate's support in its window).

    ``w[key]`` gives the selected rows as a dense NumPy array (integers, slices, integer
    or boolean arrays on the first axis); ``np.asarray(w)`` gives them all. Memory:
    ``sum_i prod(inner) x length_i`` values and 16 bytes per row, against
    ``n x prod(inner) x W`` values dense.

    Parameters
    ----------
    data : ndarray (sum_i prod(inner) * length_i,)
        Row ``i``'s bins ``[first_i, first_i + length_i)`` of every inner index (C order),
        from ``pos[i]``.
    first, length : ndarray (n,), int
        First window bin and number of bins kept per row.
    pos : ndarray (n + 1,), int64
        Where each row starts in ``data``.
    inner : tuple of int
        The shape between the row and the window axes (``(Q, L)`` for histograms).
    width : int
        W, the window's bins.

    Examples
    --------
    >>> import numpy as np
    >>> dense = np.zeros((3, 2, 6), np.float32)
    >>> dense[0, :, 1:3] = 1.0
    >>> dense[2, :, 4:] = 2.0
    >>> w = SupportWindows.pack(dense, np.arange(3), first=[1, 0, 4], length=[2, 0, 2])
    >>> w.shape, w.data.size, bool(np.array_equal(np.asarray(w), dense))
    ((3, 2, 6), 8, True)
    >>> w[np.array([2])][0, 1].tolist()
    [0.0, 0.0, 0.0, 0.0, 2.0, 2.0]
    """

    __slots__ = ("data", "first", "length", "pos", "inner", "width", "__weakref__")

    def __init__(self, data, first, length, pos, inner: tuple, width: int):
        self.data = data
        self.first = first
        self.length = length
        self.pos = pos
        self.inner = tuple(int(k) for k in inner)
        self.width = int(width)

    @classmethod
    def pack(cls, dense: np.ndarray, rows, *, first, length) -> SupportWindows:
        """Rows ``rows`` of ``dense`` (S, *inner, W), each kept over ``[first, first +
        length)`` (its values elsewhere must be zero: they are not stored)."""
        dense = np.asarray(dense)
        inner, W = dense.shape[1:-1], dense.shape[-1]
        M = int(np.prod(inner, dtype=np.int64))
        rows = np.ascontiguousarray(rows, np.int64)
        first = np.ascontiguousarray(first, np.int64)
        length = np.ascontiguousarray(length, np.int64)
        first = np.where(length > 0, first, 0)  # an empty support: nothing stored
        if rows.size and (first.min() < 0 or length.min() < 0 or int((first + length).max()) > W):
            raise ValueError("a support lies outside its window")
        pos = np.zeros(rows.size + 1, np.int64)
        np.cumsum(length * M, out=pos[1:])
        data = np.empty(int(pos[-1]), dense.dtype)
        if rows.size:
            _pack(np.ascontiguousarray(dense).reshape(-1, M, W), rows, first, length, pos, data)
        small = np.int32 if W < 2**31 else np.int64
        return cls(data, first.astype(small), length.astype(small), pos, inner, W)

    @property
    def shape(self) -> tuple:
        return (int(self.first.size), *self.inner, self.width)

    @property
    def dtype(self) -> np.dtype:
        return self.data.dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        """Bytes held (data and the per-row positions)."""
        return int(self.data.nbytes + self.first.nbytes + self.length.nbytes + self.pos.nbytes)

    def __len__(self) -> int:
        return int(self.first.size)

    def rows(self, idx, out: np.ndarray | None = None) -> np.ndarray:
        """Rows ``idx`` (integer array) dense, into ``out`` (``(idx.size, *inner, W)``)
        or a new array."""
        idx = np.ascontiguousarray(idx, np.int64).reshape(-1)
        n = len(self)
        if idx.size and (idx.min() < -n or idx.max() >= n):
            raise IndexError(f"row index out of range for {n} rows")
        idx = np.where(idx < 0, idx + n, idx)
        shape = (idx.size, *self.inner, self.width)
        if out is None:
            out = np.empty(shape, self.data.dtype)
        elif out.shape != shape or not out.flags.c_contiguous:
            raise ValueError(f"`out` must be a C-contiguous array of shape {shape}")
        M = int(np.prod(self.inner, dtype=np.int64))
        flat = out.reshape(idx.size, M, self.width)
        if idx.size:
            _unpack(self.data, idx, self.first, self.length, self.pos, flat)
        return out


#: Bytes of float32 rows :meth:`OwnBackground.rows` computes at a time (its int64 bins
#: and float temporaries are a few times that).
PART_BYTES = 2**25


class OwnBackground(_RowIndexing):
    """The candidates' own background over their windows, ``(n, L, W)`` float32,
    computed where it is indexed: ``bhat`` (``eq:background_3``, clipped at 0) of the
    candidate's pixel over the window ``[offset, offset + W)``, zero outside the support
    ``[start, stop)``, as the map pass's kernel wrote it (``_kernels._window_background``
    and ``_own_pixel``: the same float32 sums, bit for bit). Stands in for the dense
    ``own_background`` column of the candidate table (the map pass's maximum on the face
    file at its native bin 1.83 -> 1.72 float32 cubes without it, ``benchmarks/README.md``,
    "own36, session 24"): 48 bytes a candidate.

    Parameters
    ----------
    spatial : ndarray (R, C, L), float32
        The background's spatial level ``b_{n,l}`` (``CandidateMap.spatial``).
    dev : ndarray (L, T)
        Its temporal deviation ``dev_l(t)`` (``Background.dev``).
    row, col, offset, start, stop : ndarray (n,), int
        The candidates' pixels, first window bin and support (bins).
    width : int
        W, the window's bins.

    Examples
    --------
    >>> import numpy as np
    >>> sp = np.full((1, 1, 1), 0.5, np.float32)
    >>> dev = np.array([[0.0, -1.0, 0.25, 0.0, 0.0]], np.float32)
    >>> ob = OwnBackground(sp, dev, [0], [0], [0], [1], [3], width=4)
    >>> ob[0].tolist()
    [[0.0, 0.0, 0.75, 0.0]]
    """

    __slots__ = ("spatial", "dev", "row", "col", "offset", "start", "stop", "width")

    def __init__(self, spatial, dev, row, col, offset, start, stop, *, width: int):
        self.spatial, self.dev = np.asarray(spatial), np.asarray(dev)
        self.row, self.col = np.array(row, np.int64), np.array(col, np.int64)
        self.offset = np.array(offset, np.int64)
        self.start, self.stop = np.array(start, np.int64), np.array(stop, np.int64)
        self.width = int(width)

    @property
    def shape(self) -> tuple:
        return (int(self.row.size), int(self.dev.shape[0]), self.width)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.float32)

    @property
    def ndim(self) -> int:
        return 3

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.row.size)

    def rows(self, idx) -> np.ndarray:
        """Rows ``idx`` (integer array) dense, ``(idx.size, L, W)`` float32 (computed
        :data:`PART_BYTES` of them at a time)."""
        idx = np.arange(len(self))[np.ascontiguousarray(idx, np.int64).reshape(-1)]
        L, W = self.shape[1:]
        out = np.empty((idx.size, L, W), np.float32)
        step = max(1, PART_BYTES // (4 * max(L, 1) * max(W, 1)))
        for a in range(0, idx.size, step):
            out[a : a + step] = self._part(idx[a : a + step])
        return out

    def _part(self, idx) -> np.ndarray:
        out = np.empty((idx.size, self.dev.shape[0], self.width), np.float32)
        _own_rows(self.spatial, self.dev, self.row, self.col, self.offset, self.start,
                  self.stop, np.ascontiguousarray(idx, np.int64), out)  # fmt: skip
        return out


@njit(cache=True, nogil=True)
def _own_rows(spatial, dev, row, col, offset, start, stop, idx, out):
    """``out[i]`` (L, W) = :class:`OwnBackground`'s row ``idx[i]``: ``max(spatial[r, c, l]
    + dev[l, min(t, T - 1)], 0)`` in the operands' common type, then float32, at the
    window's bins ``t = offset + w`` inside ``[max(start, offset), stop)``, 0 elsewhere
    (the former NumPy expression's values, element by element)."""
    L, W, T = out.shape[1], out.shape[2], dev.shape[1]
    for i in range(idx.size):
        j = idx[i]
        r, c, off = row[j], col[j], offset[j]
        lo, hi = max(start[j], off), stop[j]
        for l in range(L):
            s = spatial[r, c, l]
            for w in range(W):
                t = off + w
                if t >= lo and t < hi:
                    b = s + dev[l, min(t, T - 1)]
                    if b < 0:
                        out[i, l, w] = 0
                    else:
                        out[i, l, w] = b
                else:
                    out[i, l, w] = 0
