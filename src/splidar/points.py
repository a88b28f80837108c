"""Point sets: the common currency of truth, detections and reconstructions.

A :class:`PointSet` is a list of surfaces: one point per (pixel, surface), with its
fractional depth in time bins and, when known, its intensity per wavelength, class
label and uncertainties. The simulator's ground truth, ``Detection.points``,
``Reconstruction.points`` and the metrics all use this one form.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields

import numpy as np

from ._validation import SplidarError, as_float_array

__all__ = ["PointSet"]

_OPTIONAL = ("intensity", "label", "depth_m", "intensity_std", "label_confidence", "layer")


@dataclass(frozen=True)
class PointSet:
    """Surfaces as points: ``row``, ``col``, ``depth_bin`` and optional attributes.

    Parameters
    ----------
    row, col : array_like of int, shape (n,)
        Pixel of each point (0-based).
    depth_bin : array_like of float, shape (n,)
        Fractional time bin where the peak of the return lands (the depth reference of
        ALGORITHM-NOTES).
    image_shape : tuple (rows, cols)
        Size of the image the points live in.
    intensity : array_like, shape (n, L), optional
        Expected signal photons per wavelength (``I = h r``).
    label : array_like of int, shape (n,), optional
        0-based row of the spectral library (0 when there is no library).
    depth_m : array_like, shape (n,), optional
        Depth in metres (when the bin width is known).
    intensity_std : array_like, shape (n, L), optional
        Posterior standard deviation of ``intensity``.
    label_confidence : array_like, shape (n,), optional
        Posterior probability of ``label`` given the neighbours, in [0, 1].
    layer : array_like of int, shape (n,), optional
        Surface slot within the pixel (0 = nearest detected surface).

    Examples
    --------
    >>> p = PointSet(row=[0, 0], col=[1, 1], depth_bin=[10.0, 42.5], image_shape=(2, 3))
    >>> len(p), p.n_wavelengths
    (2, 0)
    """

    row: np.ndarray
    col: np.ndarray
    depth_bin: np.ndarray
    image_shape: tuple[int, int]
    intensity: np.ndarray | None = None
    label: np.ndarray | None = None
    depth_m: np.ndarray | None = None
    intensity_std: np.ndarray | None = None
    label_confidence: np.ndarray | None = None
    layer: np.ndarray | None = None

    def __post_init__(self):
        row = np.asarray(self.row).reshape(-1)
        col = np.asarray(self.col).reshape(-1)
        n = row.size
        if not (np.issubdtype(row.dtype, np.integer) or row.size == 0):
            raise SplidarError(f"`row` must be integers; got dtype {row.dtype}.")
        if not (np.issubdtype(col.dtype, np.integer) or col.size == 0):
            raise SplidarError(f"`col` must be integers; got dtype {col.dtype}.")
        row = row.astype(np.int64)
        col = col.astype(np.int64)
        depth = as_float_array(self.depth_bin, "depth_bin").reshape(-1)
        try:
            shape = tuple(int(s) for s in self.image_shape)
        except TypeError:
            raise SplidarError(
                f"`image_shape` must be (rows, cols); got {self.image_shape!r}."
            ) from None
        if len(shape) != 2:
            raise SplidarError(f"`image_shape` must be (rows, cols); got {self.image_shape!r}.")
        if col.size != n or depth.size != n:
            raise SplidarError(
                f"`row`, `col` and `depth_bin` must have the same length; got {n}, {col.size}, "
                f"{depth.size}."
            )
        if n and (row.min() < 0 or col.min() < 0 or row.max() >= shape[0] or col.max() >= shape[1]):
            raise SplidarError(f"points lie outside `image_shape` {shape}.")
        vals = {"row": row, "col": col, "depth_bin": depth, "image_shape": shape}
        for name in _OPTIONAL:
            v = getattr(self, name)
            if v is None:
                vals[name] = None
                continue
            if name in ("label", "layer"):
                a = np.asarray(v).reshape(-1).astype(np.int64)
            else:
                a = as_float_array(v, name, finite=name not in ("depth_m",))
            if name in ("intensity", "intensity_std"):
                if a.ndim == 1:
                    a = a[:, None]
                if a.ndim != 2 or a.shape[0] != n:
                    raise SplidarError(
                        f"`{name}` must have shape (n, L) with n = {n}; got {a.shape}."
                    )
            else:
                a = a.reshape(-1)
                if a.size != n:
                    raise SplidarError(f"`{name}` must have length n = {n}; got {a.size}.")
            vals[name] = a
        for k, v in vals.items():
            if isinstance(v, np.ndarray):
                v.flags.writeable = False
            object.__setattr__(self, k, v)

    def __len__(self) -> int:
        return int(self.row.size)

    def __repr__(self) -> str:
        have = [k for k in _OPTIONAL if getattr(self, k) is not None]
        return f"PointSet(n={len(self)}, image_shape={self.image_shape}, fields={have})"

    @property
    def n_wavelengths(self) -> int:
        """L of ``intensity`` (0 when there is no intensity)."""
        return 0 if self.intensity is None else int(self.intensity.shape[1])

    def subset(self, index) -> PointSet:
        """Points selected by a boolean mask or integer index array."""
        kw = {"image_shape": self.image_shape}
        for f in fields(self):
            if f.name == "image_shape":
                continue
            v = getattr(self, f.name)
            kw[f.name] = None if v is None else v[index]
        return PointSet(**kw)

    def to_dict(self) -> dict[str, np.ndarray]:
        """Arrays by name (absent fields left out), ``image_shape`` as an int array."""
        out = {"image_shape": np.asarray(self.image_shape, dtype=np.int64)}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name != "image_shape" and v is not None:
                out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, d) -> PointSet:
        """Inverse of :meth:`to_dict` (also reads an opened ``.npz``)."""
        keys = set(d.keys()) if hasattr(d, "keys") else set(d)
        missing = {"row", "col", "depth_bin", "image_shape"} - keys
        if missing:
            raise SplidarError(
                f"a point set needs arrays {sorted(missing)}; the input holds {sorted(keys)}."
            )
        kw = {k: np.asarray(d[k]) for k in ("row", "col", "depth_bin")}
        kw["image_shape"] = tuple(int(s) for s in np.asarray(d["image_shape"]))
        for k in _OPTIONAL:
            if k in keys:
                kw[k] = np.asarray(d[k])
        return cls(**kw)

    def save(self, path: str | os.PathLike) -> None:
        """Write to ``.npz``; :meth:`load` reads it back exactly."""
        np.savez_compressed(path, **self.to_dict(), __kind__=np.array("PointSet"))

    @classmethod
    def load(cls, path: str | os.PathLike) -> PointSet:
        """Read a point set written by :meth:`save`."""
        with np.load(path, allow_pickle=False) as z:
            return cls.from_dict(z)

    def maps(self, n_layers: int | None = None) -> dict[str, np.ndarray]:
        """Per-layer maps ``(rows, cols, K_s)``: depth (NaN where absent), label (-1), intensity.

        Points are placed by ``layer`` when present, otherwise by depth order in the pixel.
        """
        rows, cols = self.image_shape
        if self.layer is not None:
            layer = self.layer
        else:
            order = np.lexsort((self.depth_bin, self.col, self.row))
            pix = self.row[order] * cols + self.col[order]
            first = np.r_[True, pix[1:] != pix[:-1]]
            start = np.maximum.accumulate(np.where(first, np.arange(pix.size), 0))
            layer = np.empty(pix.size, np.int64)
            layer[order] = np.arange(pix.size) - start
        k = int(layer.max()) + 1 if layer.size else 1
        k = max(k, n_layers or 0)
        depth = np.full((rows, cols, k), np.nan)
        depth[self.row, self.col, layer] = self.depth_bin
        out = {"depth_bin": depth}
        if self.label is not None:
            lab = np.full((rows, cols, k), -1, np.int64)
            lab[self.row, self.col, layer] = self.label
            out["label"] = lab
        if self.intensity is not None:
            inten = np.full((rows, cols, k, self.n_wavelengths), np.nan)
            inten[self.row, self.col, layer] = self.intensity
            out["intensity"] = inten
        return out
