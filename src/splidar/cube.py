"""The :class:`Cube`: photon-count histograms with their instrument response."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from ._validation import SplidarError, check_ndim, check_positive, describe
from .irf import irf_peak, normalise_irf
from .library import SpectralLibrary, as_library

__all__ = ["Cube", "SPEED_OF_LIGHT", "as_counts"]

log = logging.getLogger(__name__)

#: Speed of light in vacuum, metres per second.
SPEED_OF_LIGHT = 299_792_458.0


def _is_lazy(a) -> bool:
    """True for a Dask array (larger-than-RAM data): validated by shape and dtype only."""
    return hasattr(a, "chunks") and hasattr(a, "compute") and not isinstance(a, np.ndarray)


def as_counts(counts, name: str = "counts"):
    """Validate photon counts and return them as a ``(rows, cols, L, T)`` integer array.

    A ``(rows, cols, T)`` input is returned as a ``(rows, cols, 1, T)`` view. Integer
    input is kept as it is (no copy). Float input is accepted only when every value is
    a non-negative whole number, and is converted to the smallest unsigned type
    (uint16 or uint32) that holds it. A masked array's masked voxels (dead pixels)
    count 0 photons.

    Raises
    ------
    SplidarError
        Wrong number of dimensions, NaN/inf, negative or non-integer values.

    Examples
    --------
    >>> import numpy as np
    >>> c = as_counts(np.array([[[0.0, 2.0, 1.0]]]))
    >>> c.shape, c.dtype.name
    ((1, 1, 1, 3), 'uint16')
    """
    lazy = _is_lazy(counts)
    if np.ma.isMaskedArray(counts):
        # masked voxels (dead pixels, gated-off bins) recorded no photons: 0, never the
        # values the mask hides
        n_masked = int(np.count_nonzero(np.ma.getmaskarray(counts)))
        counts = np.ma.filled(counts, 0)
        if n_masked:
            log.info("`%s`: %d masked voxel(s) taken as 0 counts", name, n_masked)
    a = counts if lazy else np.asarray(counts)
    check_ndim(a, name, (3, 4), "(rows, cols, T) or (rows, cols, L, T)")
    if a.ndim == 3:
        a = a[:, :, None, :]
    if min(a.shape) == 0:
        raise SplidarError(f"`{name}` must not have an empty axis; got shape {a.shape}.")
    kind = np.dtype(a.dtype).kind
    if kind not in "uifb":
        raise SplidarError(
            f"`{name}` must hold numbers (photon counts); got {describe(np.asarray(a[:0]))}."
        )
    if lazy:
        if kind not in "ui":
            raise SplidarError(
                f"`{name}` is a lazy (Dask) array of dtype {a.dtype}; photon counts must be an "
                "integer dtype. Cast it with `.astype(np.uint16)` (after checking it holds "
                "whole numbers)."
            )
        return a
    if kind == "b":
        return a.astype(np.uint8)
    if kind == "i":
        mn = a.min()
        if mn < 0:
            raise SplidarError(
                f"`{name}` holds {int(np.count_nonzero(a < 0))} negative value(s) (min {mn}); "
                "photon counts are non-negative."
            )
        return a
    if kind == "u":
        return a
    # floating point
    if not np.all(np.isfinite(a)):
        raise SplidarError(
            f"`{name}` holds {int(np.count_nonzero(~np.isfinite(a)))} NaN or infinite value(s); "
            "photon counts must be finite whole numbers. If NaN marks dead pixels, pass "
            "np.nan_to_num(counts) (no photons) or a numpy masked array."
        )
    mn = a.min()
    if mn < 0:
        raise SplidarError(
            f"`{name}` holds {int(np.count_nonzero(a < 0))} negative value(s) (min {mn:g}); "
            "photon counts are non-negative."
        )
    if not np.all(a == np.round(a)):
        raise SplidarError(
            f"`{name}` holds non-integer values (e.g. {a[a != np.round(a)].flat[0]:g}); photon "
            "counts are whole numbers. If these are background-subtracted or averaged "
            "histograms, pass the raw counts instead."
        )
    mx = a.max()
    if mx > np.iinfo(np.uint32).max:
        raise SplidarError(
            f"`{name}` holds a value of {mx:.3g}, more photons than a bin can count "
            f"(at most {np.iinfo(np.uint32).max}); these are not raw photon counts."
        )
    dtype = np.uint16 if mx <= np.iinfo(np.uint16).max else np.uint32
    return a.astype(dtype)


#: IRF samples at most this fraction of their wavelength's peak are negligible: an IRF
#: longer than the window loses them from its ends (a measured pulse is often stored
#: in a long record of zeros).
IRF_NEGLIGIBLE = 1e-9


def _trim_irf(irf: np.ndarray, T: int) -> np.ndarray:
    """``irf`` (L, n) without its negligible ends (renormalised), if that fits in T bins."""
    big = np.any(irf > IRF_NEGLIGIBLE * irf.max(axis=1, keepdims=True), axis=0)
    lo, hi = int(np.argmax(big)), int(big.size - np.argmax(big[::-1]))
    if hi - lo > T:
        raise SplidarError(
            f"`irf` is longer ({irf.shape[1]} samples; {hi - lo} above {IRF_NEGLIGIBLE:g} of "
            f"the peak) than the histograms (T = {T} bins); crop the IRF around its peak or "
            "use a longer time window (the IRF must fit inside it)."
        )
    log.info(
        "irf: %d samples kept of %d (the rest below %g of the peak) to fit T = %d bins",
        hi - lo, irf.shape[1], IRF_NEGLIGIBLE, T,
    )  # fmt: skip
    out = irf[:, lo:hi]
    return out / out.sum(axis=1, keepdims=True)


@dataclass(frozen=True)
class Cube:
    """Histograms of photon arrival times, ``(rows, cols, L, T)``, with their IRF.

    The input every splidar stage starts from. Validated on construction.

    Parameters
    ----------
    counts : array_like of int, shape (rows, cols, L, T) or (rows, cols, T)
        Photon counts per pixel, wavelength and time bin (time last). A 3-D array means
        L = 1. Integer dtypes are kept without a copy (uint16/uint32 recommended); float
        input must hold whole numbers; a masked array's masked voxels (dead pixels)
        count 0. A Dask array is accepted for data larger than RAM
        (checked by shape and dtype only).
    irf : array_like, shape (L, n_irf) or (n_irf,)
        Instrument response per wavelength; normalised to sum 1 per wavelength into a
        new array (the caller's is not modified). A 1-D IRF serves every wavelength.
        An IRF longer than T loses its negligible ends (a measured pulse in a long
        record of zeros fits a shorter window).
        Its peak (argmax) is the depth reference. Sampled on the cube's bins: an IRF
        recorded at another step must be resampled (:func:`splidar.irf.resample_irf`);
        ``detect`` compares its photon-pair width with the data's the first time it
        runs on this Cube and warns (``splidar.io`` logger) beyond a factor 2, naming
        the step that would match; nothing is changed.
    bin_width_ps : float, optional
        Width of one time bin in picoseconds; enables depths in metres.
    wavelengths_nm : array_like, shape (L,), optional
        Wavelength of each channel in nanometres.
    library : SpectralLibrary or array_like (K, L), optional
        Spectral library that came with the data (e.g. read from the same file).
    metadata : mapping, optional
        Free-form information (source file, acquisition settings); stored read-only.

    Raises
    ------
    SplidarError
        Wrong number of dimensions, NaN, negative or non-integer counts, an IRF longer
        than T (after dropping its negligible ends: samples at most ``1e-9`` of the
        peak), an IRF with no positive value, or L differing between counts and IRF.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar import Cube
    >>> cube = Cube(np.zeros((4, 5, 100), np.uint16), irf=[0.25, 0.5, 0.25], bin_width_ps=250)
    >>> cube.shape, cube.irf.shape, cube.irf_peak.tolist()
    ((4, 5, 1, 100), (1, 3), [1])
    >>> round(float(cube.depth_to_m(10.0)), 6)  # 10 bins x 250 ps x c / 2
    0.374741
    """

    counts: Any
    irf: np.ndarray
    bin_width_ps: float | None = None
    wavelengths_nm: np.ndarray | None = None
    library: SpectralLibrary | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        counts = as_counts(self.counts)
        L, T = counts.shape[2], counts.shape[3]
        try:
            irf = normalise_irf(self.irf, n_wavelengths=L)
        except SplidarError as exc:
            if "wavelength(s) but the counts" in str(exc):
                raise SplidarError(
                    f"L differs between `counts` ({L} wavelength(s), shape {counts.shape}) and "
                    f"`irf` (shape {np.shape(self.irf)}); pass one IRF row per wavelength."
                ) from None
            raise
        if irf.shape[1] > T:
            irf = _trim_irf(irf, T)
        irf.flags.writeable = False
        bw = self.bin_width_ps
        if bw is not None:
            bw = check_positive(bw, "bin_width_ps")
        wl = self.wavelengths_nm
        if wl is not None:
            wl = np.asarray(wl, dtype=np.float64).reshape(-1)
            if wl.shape != (L,):
                raise SplidarError(
                    f"`wavelengths_nm` must have one value per wavelength ({L}); got shape "
                    f"{wl.shape}."
                )
            wl.flags.writeable = False
        lib = as_library(self.library, n_wavelengths=L)
        md = MappingProxyType(dict(self.metadata or {}))
        object.__setattr__(self, "counts", counts)
        object.__setattr__(self, "irf", irf)
        object.__setattr__(self, "bin_width_ps", bw)
        object.__setattr__(self, "wavelengths_nm", wl)
        object.__setattr__(self, "library", lib)
        object.__setattr__(self, "metadata", md)

    def __repr__(self) -> str:
        bw = f"{self.bin_width_ps:g} ps" if self.bin_width_ps else "unknown"
        return (
            f"Cube(shape={self.shape}, dtype={np.dtype(self.counts.dtype)}, "
            f"irf={self.irf.shape}, bin_width={bw})"
        )

    # --- shape -------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(rows, cols, L, T)``."""
        return tuple(int(s) for s in self.counts.shape)  # type: ignore[return-value]

    @property
    def n_rows(self) -> int:
        return self.shape[0]

    @property
    def n_cols(self) -> int:
        return self.shape[1]

    @property
    def n_wavelengths(self) -> int:
        """L."""
        return self.shape[2]

    @property
    def n_bins(self) -> int:
        """T."""
        return self.shape[3]

    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def irf_peak(self) -> np.ndarray:
        """Peak index of each wavelength's IRF, shape ``(L,)``: the depth reference."""
        return irf_peak(self.irf)

    @property
    def is_lazy(self) -> bool:
        """True when ``counts`` is a Dask array (data larger than RAM)."""
        return _is_lazy(self.counts)

    # --- units -------------------------------------------------------------------
    @property
    def bin_width_m(self) -> float | None:
        """Depth spanned by one time bin, metres (round trip): ``bin_width x c / 2``."""
        if self.bin_width_ps is None:
            return None
        return self.bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0

    def depth_to_m(self, depth_bin):
        """Convert a (fractional) depth in bins to metres; raises if the bin width is unknown."""
        if self.bin_width_ps is None:
            raise SplidarError(
                "This cube has no `bin_width_ps`, so depths cannot be given in metres; "
                "pass bin_width_ps= when building or loading it."
            )
        return np.asarray(depth_bin, dtype=np.float64) * self.bin_width_m

    def photons_per_pixel(self) -> float:
        """Mean total photons per pixel (signal plus background), summed over L and T."""
        total = self.counts.sum(dtype=np.float64)
        if self.is_lazy:
            total = total.compute()
        return float(total) / self.n_pixels
