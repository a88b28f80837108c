"""Spectral libraries: the K known material signatures used for classification."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ._validation import SplidarError, as_float_array, check_ndim, describe

__all__ = ["SpectralLibrary", "as_library"]


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
    file that :func:`splidar.io.load_library` reads. Checks L against ``n_wavelengths``.
    """
    if library is None:
        return None
    if isinstance(library, SpectralLibrary):
        lib = library
    elif isinstance(library, (str, os.PathLike)):
        from .io import load_library

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
