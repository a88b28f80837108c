"""The per-voxel detection threshold, computed from the factored background on access.

Where the background level varies with the pixel, the calibrated threshold does too:
``threshold(r, c, t) = interp(level(r, c, t), levels, thresholds)`` with ``level = sum_l
max(b_{r,c,l} + dev_{l,t}, 0)`` (``eq:background_3`` summed over wavelengths) and the
empirical null's table. Storing it as a dense (rows, cols, T) float32 cube cost a quarter
of the input's float32 size and, on the 200 x 200 x 4 x 1500 cube, about 0.6 s of CPU
just writing it; :class:`ThresholdField` keeps the factors and computes any rows asked
for, with the same arithmetic as the detection pass (identical values).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._validation import SplidarError
from ._kernels import _interp_table

__all__ = ["ThresholdField"]


@njit(cache=True, nogil=True)
def _threshold_rows(sp, dev, xs, ys, out):
    """``out[i, j, t]``: the threshold of rows ``sp`` (r, C, L), as the detection pass."""
    r, C, L = sp.shape
    T = dev.shape[1]
    lev = np.empty(T, np.float32)
    for i in range(r):
        for j in range(C):
            for l in range(L):  # the same float32 accumulation order as the saliency pass
                s0 = sp[i, j, l]
                for t in range(T):
                    bh = s0 + dev[l, t]
                    if bh < 0:
                        bh = np.float32(0.0)
                    if l == 0:
                        lev[t] = bh
                    else:
                        lev[t] += bh
            for t in range(T):
                out[i, j, t] = np.float32(_interp_table(np.float64(lev[t]), xs, ys))


class ThresholdField:
    """Read-only ``(rows, cols, T)`` float32 threshold, computed row by row on access.

    Behaves as an array for reading: ``shape``, ``ndim``, ``dtype``, ``size``,
    ``len()``, indexing (any NumPy index; rows are computed, then indexed) and
    ``np.asarray`` (the whole cube). Comparisons such as ``saliency > threshold`` work
    through ``np.asarray``.

    Parameters
    ----------
    spatial : ndarray (rows, cols, L) float32
        Background level per pixel and wavelength (``Background.spatial``).
    dev : ndarray (L, T) float32
        ``bbar_{l,t} - mean_t bbar_{l,t}`` of the temporal shape.
    levels, thresholds : ndarray (G,)
        The threshold table (increasing levels).

    Raises
    ------
    SplidarError
        ``spatial`` not (rows, cols, L), ``dev`` not (L, T), or a table of unequal or
        empty arrays.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar.detection import ThresholdField
    >>> f = ThresholdField(np.full((2, 3, 1), 1.0, np.float32), np.zeros((1, 4), np.float32),
    ...                    np.array([0.0, 2.0]), np.array([1.0, 3.0]))
    >>> f.shape, float(f[1, 2, 3]), np.asarray(f).mean().item()
    ((2, 3, 4), 2.0, 2.0)
    """

    def __init__(self, spatial, dev, levels, thresholds):
        self._sp = np.ascontiguousarray(spatial, np.float32)
        self._dev = np.ascontiguousarray(dev, np.float32)
        self._xs = np.ascontiguousarray(levels, np.float64)
        self._ys = np.ascontiguousarray(thresholds, np.float64)
        if self._sp.ndim != 3:
            raise SplidarError(
                f"`spatial` must be (rows, cols, L), the background level per pixel and "
                f"wavelength; got shape {self._sp.shape}."
            )
        R, C, L = self._sp.shape
        if self._dev.ndim != 2 or self._dev.shape[0] != L:
            raise SplidarError(
                f"`dev` must be (L, T) with the L = {L} wavelengths of `spatial` (rows, cols, L);"
                f" got shape {self._dev.shape}."
            )
        if self._xs.ndim != 1 or self._xs.shape != self._ys.shape or self._xs.size == 0:
            raise SplidarError(
                "`levels` and `thresholds` must be 1-d arrays of one length >= 1 (the table); "
                f"got shapes {self._xs.shape} and {self._ys.shape}."
            )
        self.shape = (R, C, self._dev.shape[1])
        self.dtype = np.dtype(np.float32)
        self.ndim = 3

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        return self.size * 4

    def __len__(self) -> int:
        return self.shape[0]

    def _rows(self, r0: int, r1: int) -> np.ndarray:
        out = np.empty((max(r1 - r0, 0),) + self.shape[1:], np.float32)
        if out.size:
            _threshold_rows(self._sp[r0:r1], self._dev, self._xs, self._ys, out)
        return out

    def pixels(self, rows, cols) -> np.ndarray:
        """The thresholds of single pixels, computed for those pixels only.

        Parameters
        ----------
        rows, cols : array_like (S,) int
            Pixel coordinates.

        Returns
        -------
        ndarray (S, T) float32
            ``field[rows[i], cols[i], :]`` for each i (the same values).

        Examples
        --------
        >>> import numpy as np
        >>> from splidar.detection import ThresholdField
        >>> f = ThresholdField(np.full((2, 3, 1), 1.0, np.float32), np.zeros((1, 4), np.float32),
        ...                    np.array([0.0, 2.0]), np.array([1.0, 3.0]))
        >>> f.pixels([1, 0], [2, 0]).shape
        (2, 4)
        """
        rows = np.asarray(rows, np.int64)
        cols = np.asarray(cols, np.int64)
        out = np.empty((rows.size, 1, self.shape[2]), np.float32)
        if rows.size:
            sp = np.ascontiguousarray(self._sp[rows, cols][:, None, :])
            _threshold_rows(sp, self._dev, self._xs, self._ys, out)
        return out[:, 0]

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        first = key[0] if key else slice(None)
        R = self.shape[0]
        if isinstance(first, slice):
            idx = range(*first.indices(R))
            if len(idx) == 0:
                return self._rows(0, 0)[(slice(None),) + key[1:]]
            lo, hi = min(idx[0], idx[-1]), max(idx[0], idx[-1]) + 1
            block = self._rows(lo, hi)
            if idx.step == 1:
                local = slice(None)
            else:
                local = np.arange(idx.start, idx.stop, idx.step) - lo
            return block[(local,) + key[1:]]
        if isinstance(first, int | np.integer):
            i = int(first) + (R if first < 0 else 0)
            if not 0 <= i < R:
                raise IndexError(f"row {first} is out of range for {R} rows")
            return self._rows(i, i + 1)[(0,) + key[1:]]
        return np.asarray(self)[key]

    def __array__(self, dtype=None, copy=None):
        full = self._rows(0, self.shape[0])
        return full if dtype is None else full.astype(dtype)

    def __repr__(self) -> str:
        return f"ThresholdField(shape={self.shape}, levels={self._xs.size})"
