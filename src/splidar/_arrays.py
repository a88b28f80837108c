"""Reading image-size ``(rows, cols, T)`` arrays that may live on disk (Zarr, Dask).

``Detection.saliency``, ``mask`` and ``threshold`` are NumPy arrays, or chunked Zarr
arrays when :func:`splidar.detect` was given ``store=``. Exports and figures read them
through these helpers, a block of rows at a time, so that a detection larger than RAM
can still be summarised and drawn.
"""

from __future__ import annotations

from collections.abc import Iterator

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

    ``out`` has shape ``(hi - lo,) + z.shape[1:]`` and ``z``'s dtype. Zarr 3 takes an
    ``NDBuffer`` over ``out``; zarr 2 takes the NumPy array itself.
    """
    try:
        from zarr.core.buffer import default_buffer_prototype
    except ImportError:  # zarr 2
        z.get_basic_selection((slice(lo, hi),), out=out)
        return out
    nd = default_buffer_prototype().nd_buffer
    z.get_basic_selection((slice(lo, hi),), out=nd.from_numpy_array(out))
    return out
