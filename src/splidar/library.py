"""Spectral libraries: the K known material signatures used for classification."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from ._containers import (
    _CONTAINER_EXTS,
    _check_path,
    _ext,
    _read_container,
    _read_npy,
    _str_list,
    _summary,
)
from ._validation import SplidarError, as_float_array, check_ndim, describe

__all__ = ["SpectralLibrary", "as_library", "load_library"]

_CSV_HEADER_WORDS = ("", "class", "classes", "name", "names", "class_name", "label", "material")


@dataclass(frozen=True)
class SpectralLibrary:
    """K spectral signatures over L wavelengths, with optional class names.

    Parameters
    ----------
    signatures : array_like, shape (K, L)
        ``m_{k,l}``: the expected signal photons of class k at wavelength l for a
        surface of unit shading (the paper's spectral signatures). Non-negative,
        finite, at least one positive value per class. Stored as float64.
    class_names : sequence of str, optional
        K names; default ``("class 0", ..., "class K-1")``.

    Notes
    -----
    A label is the 0-based row of ``signatures``. Only the *shape* of a signature
    matters for classification; its scale sets the prior mean of the reflectivity
    ``r`` (see :func:`splidar.reconstruct`).

    Examples
    --------
    >>> lib = SpectralLibrary([[1.0, 0.2, 0.1], [0.1, 1.0, 0.3]], class_names=["red", "green"])
    >>> lib.n_classes, lib.n_wavelengths
    (2, 3)
    """

    signatures: np.ndarray
    class_names: tuple[str, ...] = field(default=())

    def __post_init__(self):
        sig = as_float_array(self.signatures, "signatures")
        if sig.ndim == 1:
            sig = sig[None, :]
        check_ndim(sig, "signatures", (2,), "(K, L)")
        if sig.shape[0] == 0 or sig.shape[1] == 0:
            raise SplidarError(f"`signatures` must have K >= 1 and L >= 1; got shape {sig.shape}.")
        if np.any(sig < 0):
            raise SplidarError("`signatures` must be non-negative; a signature is a mean count.")
        if np.any(sig.sum(axis=1) <= 0):
            bad = np.flatnonzero(sig.sum(axis=1) <= 0).tolist()
            raise SplidarError(f"`signatures` rows {bad} are all zero; each class needs a signal.")
        sig = sig.copy()
        sig.flags.writeable = False
        names = tuple(str(n) for n in self.class_names) or tuple(
            f"class {k}" for k in range(sig.shape[0])
        )
        if len(names) != sig.shape[0]:
            raise SplidarError(
                f"`class_names` must have one name per signature ({sig.shape[0]}); "
                f"got {len(names)}."
            )
        object.__setattr__(self, "signatures", sig)
        object.__setattr__(self, "class_names", names)

    @property
    def n_classes(self) -> int:
        """K, the number of classes."""
        return int(self.signatures.shape[0])

    @property
    def n_wavelengths(self) -> int:
        """L, the number of wavelengths."""
        return int(self.signatures.shape[1])


def as_library(library, *, n_wavelengths: int | None = None, name: str = "library"):
    """Coerce ``library`` to a :class:`SpectralLibrary` (or ``None``).

    Accepts ``None``, a :class:`SpectralLibrary`, an array ``(K, L)``, or a path to a
    file that :func:`load_library` reads (also :func:`splidar.io.load_library`). Checks L
    against ``n_wavelengths``.

    Examples
    --------
    >>> lib = as_library([[1.0, 0.2], [0.3, 1.0]], n_wavelengths=2)
    >>> lib.n_wavelengths, as_library(None) is None
    (2, True)
    """
    if library is None:
        return None
    if isinstance(library, SpectralLibrary):
        lib = library
    elif isinstance(library, (str, os.PathLike)):
        lib = load_library(library)
    else:
        try:
            lib = SpectralLibrary(library)
        except SplidarError as exc:
            raise SplidarError(f"`{name}`: {exc} (received {describe(library)})") from None
    if n_wavelengths is not None and lib.n_wavelengths != n_wavelengths:
        raise SplidarError(
            f"`{name}` has signatures over {lib.n_wavelengths} wavelength(s) but the data has "
            f"{n_wavelengths}; pass a library of shape (K, {n_wavelengths})."
        )
    return lib


def load_library(path: str | os.PathLike) -> SpectralLibrary:
    """Read a spectral library ``(K, L)`` with optional class names.

    Formats:

    * ``.npz`` / ``.mat`` / ``.h5``: ``library`` (or ``signatures``) ``(K, L)`` and
      optional ``class_names``.
    * ``.npy``: the signatures ``(K, L)`` alone (read with ``allow_pickle=False``;
      classes are unnamed).
    * ``.csv``: one class per row, an optional leading name column, an optional header
      row (ignored) recognised by a non-numeric value after its first field or by a
      first field that is empty or one of "class", "name", "label", "material".
    * ``.json``: ``{"signatures": [[...], ...], "class_names": [...]}`` or
      ``{"name": [values], ...}``.

    Returns
    -------
    SpectralLibrary

    Raises
    ------
    SplidarError
        Missing file, unknown extension, no library in the file, bad values.

    Examples
    --------
    >>> lib = load_library("lego_library.csv")  # doctest: +SKIP
    """
    p = _check_path(path)
    ext = _ext(p)
    if ext in _CONTAINER_EXTS:
        d = _read_container(p)
        key = "library" if "library" in d else "signatures" if "signatures" in d else None
        if key is None:
            raise SplidarError(
                f"'{p.name}' has no `library` or `signatures` array; it holds: {_summary(d)}."
            )
        names = _str_list(d.get("class_names"))
        return SpectralLibrary(np.asarray(d[key], dtype=np.float64), class_names=names)
    if ext == ".npy":
        return SpectralLibrary(np.asarray(_read_npy(p), dtype=np.float64))
    if ext == ".json":
        try:
            obj = json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise SplidarError(f"'{p.name}' is not valid JSON: {exc}") from None
        if isinstance(obj, dict) and "signatures" in obj:
            return SpectralLibrary(obj["signatures"], class_names=obj.get("class_names", ()))
        if isinstance(obj, dict) and obj:
            return SpectralLibrary(list(obj.values()), class_names=list(obj.keys()))
        raise SplidarError(
            f"'{p.name}' must hold {{'signatures': [[...]], 'class_names': [...]}} or "
            "{name: [values], ...}."
        )
    if ext == ".csv":
        names, rows = [], []
        for i, line in enumerate(p.read_text().splitlines()):
            fields = [f.strip() for f in line.split(",")]
            if not line.strip():
                continue
            if not rows and not names and fields[0].lower() in _CSV_HEADER_WORDS:
                continue  # header, e.g. "class,532,633,780"
            try:
                rows.append([float(f) for f in fields])
                continue
            except ValueError:
                pass
            try:
                vals = [float(f) for f in fields[1:]]
            except ValueError:
                if rows or names:
                    raise SplidarError(
                        f"line {i + 1} of '{p.name}' is not a signature: {line!r}."
                    ) from None
                continue  # header
            names.append(fields[0])
            rows.append(vals)
        if not rows:
            raise SplidarError(f"'{p.name}' holds no signature rows.")
        if names and len(names) != len(rows):
            raise SplidarError(f"'{p.name}': name every row or none.")
        try:
            sig = np.array(rows, dtype=np.float64)
        except ValueError:
            raise SplidarError(f"'{p.name}': rows have different lengths.") from None
        return SpectralLibrary(sig, class_names=names)
    raise SplidarError(
        f"unknown library file extension '{p.suffix}'; use .npy, .npz, .mat, .h5, .csv or .json."
    )
