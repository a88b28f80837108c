"""Reading and writing photon data: histogram cubes, photon time lists, IRFs and libraries.

File kinds read by :func:`load`:

* **Histogram cubes** in ``.npz``, ``.mat`` (MATLAB v5 via :func:`scipy.io.loadmat`, or
  v7.3 = HDF5 via :mod:`h5py`, whose axes come out reversed and are put back in MATLAB
  order), ``.h5``/``.hdf5`` (axes as stored): a ``counts`` array ``(rows, cols, T)`` or
  ``(rows, cols, L, T)`` and optionally ``irf``, ``bin_width_ps``, ``wavelengths_nm``,
  ``library`` ``(K, L)``, ``class_names`` and ``metadata`` (a JSON string).
* **Photon time lists**: a ``rows x cols`` cell array (MATLAB cell / NumPy object array)
  holding the arrival times of each pixel's photons, binned by :func:`bin_photons`.
* **Zarr** directories (``.zarr``) for data larger than RAM: ``counts`` is opened as a
  Dask array and the :class:`~splidar.cube.Cube` stays lazy.

:func:`save` writes ``.npz`` (read back exactly by :func:`load`) or chunked ``.zarr``.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._bin_hints import grouping_hint, memory_hint
from ._containers import (
    _CONTAINER_EXTS,
    _check_channels_apply,
    _check_path,
    _ext,
    _read_any,
    _read_container,
    _read_npy,
    _str_list,
    _summary,
)
from ._files import savez
from ._irf_text import irf_on_bins, read_irf_text, resample_irf
from ._irf_width import (
    TILT_LOAD,
    TILT_RESCUE,
    WIDTH_Z,
    check_irf_width,
    mark_checked,
    pair_lag_fwhm,
)
from ._memory import available_bytes, check_memory
from ._photon_table import find_photon_table, table_as_flat
from ._validation import SplidarError, check_choice, check_int, check_positive, describe
from .cube import Cube, as_counts
from .irf import gaussian_irf
from .library import SpectralLibrary, load_library

__all__ = [
    "PhotonLists",
    "bin_photons",
    "estimate_irf",
    "estimate_irf_fwhm",
    "load",
    "load_irf",
    "load_library",
    "photon_lists_from_cells",
    "read_photon_lists",
    "save",
]

log = logging.getLogger(__name__)

#: Factors from supported time units to picoseconds (``"bin"``: unknown physical unit).
TIME_UNITS_PS = {"bin": None, "fs": 1e-3, "ps": 1.0, "ns": 1e3, "us": 1e6, "ms": 1e9, "s": 1e12}

_MAX_CUBE_BYTES = 8 * 2**30  # refuse to allocate a dense binned cube larger than 8 GiB


# --------------------------------------------------------------------------------------
# low-level readers: a file -> {name: array} (in _containers.py, shared with library.py)
# --------------------------------------------------------------------------------------
def _scalar(v, name: str) -> float:
    a = np.asarray(v)
    if a.size != 1:
        raise SplidarError(f"`{name}` in the file must be a single number; got shape {a.shape}.")
    return float(a.reshape(-1)[0])


def _is_cell_of_numbers(v) -> bool:
    if not (isinstance(v, np.ndarray) and v.dtype == object and v.ndim == 2 and v.size):
        return False
    for x in v.flat[: min(v.size, 50)]:
        a = np.asarray(x)
        if a.dtype == object or (a.size and a.dtype.kind not in "uif"):
            return False
    return True


# --------------------------------------------------------------------------------------
# photon lists
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PhotonLists:
    """Photon arrival times of every pixel, flattened (the raw form of TCSPC data).

    Attributes
    ----------
    times : ndarray, shape (n,)
        Arrival times in the file's own unit (bin indices or picoseconds), in pixel
        order (row-major over ``shape``), dtype as stored.
    pixel_index : ndarray of int64, shape (n,)
        Flat pixel index ``row * cols + col`` of each photon.
    shape : tuple (rows, cols)
        Image size.
    source : str
        Where the lists came from (file and variable), for metadata.
    """

    times: np.ndarray
    pixel_index: np.ndarray
    shape: tuple[int, int]
    source: str = ""

    @property
    def n_photons(self) -> int:
        return int(self.times.size)

    def photons_per_pixel(self) -> float:
        """Mean number of photons per pixel (all times, before any window)."""
        return self.n_photons / (self.shape[0] * self.shape[1])


def photon_lists_from_cells(cells, *, source: str = "") -> PhotonLists:
    """Flatten a ``rows x cols`` cell array of per-pixel arrival times.

    Parameters
    ----------
    cells : ndarray of object, shape (rows, cols), or nested lists
        Each element an array (any shape, flattened) of arrival times; empty allowed.
    source : str
        Recorded in :attr:`PhotonLists.source`.

    Returns
    -------
    PhotonLists

    Raises
    ------
    SplidarError
        Not 2-D, or an element that is not numeric.

    Examples
    --------
    >>> import numpy as np
    >>> c = np.empty((1, 2), dtype=object)
    >>> c[0, 0], c[0, 1] = np.array([3, 5]), np.array([], dtype=int)
    >>> pl = photon_lists_from_cells(c)
    >>> pl.times.tolist(), pl.pixel_index.tolist(), pl.shape
    ([3, 5], [0, 0], (1, 2))
    """
    if isinstance(cells, np.ndarray) and cells.dtype == object:
        arr = cells
    else:
        arr = np.empty((len(cells), len(cells[0]) if len(cells) else 0), dtype=object)
        for i, row in enumerate(cells):
            for j, x in enumerate(row):
                arr[i, j] = x
    if arr.ndim != 2:
        raise SplidarError(
            f"photon lists must be a 2-D (rows, cols) cell array; got shape {arr.shape}."
        )
    parts = [np.asarray(x).reshape(-1) for x in arr.flat]
    sizes = np.fromiter((p.size for p in parts), dtype=np.int64, count=len(parts))
    nonempty = [p for p in parts if p.size]
    for p in nonempty[:1] + nonempty[-1:]:
        if p.dtype.kind not in "uif":
            raise SplidarError(
                f"photon lists must hold numbers (arrival times); found dtype {p.dtype}."
            )
    times = np.concatenate(nonempty) if nonempty else np.zeros(0)
    if times.dtype.kind not in "uif":
        raise SplidarError(f"photon lists must hold numbers; got dtype {times.dtype}.")
    pix = np.repeat(np.arange(arr.size, dtype=np.int64), sizes)
    return PhotonLists(
        times=times, pixel_index=pix, shape=(int(arr.shape[0]), int(arr.shape[1])), source=source
    )


def _pick_variable(d: dict[str, Any], p: Path, variable: str | None, want: str) -> str:
    """Choose the data variable of a container (``want``: 'data' or 'photons')."""
    if variable is not None:
        if variable not in d:
            raise SplidarError(
                f"variable '{variable}' is not in '{p.name}'; it holds: {_summary(d)}. "
                "Pass one of these as variable=."
            )
        return variable
    if want == "data" and "counts" in d:
        return "counts"
    cells = [k for k, v in d.items() if _is_cell_of_numbers(v)]
    cubes = []
    if want == "data":
        cubes = [
            k
            for k, v in d.items()
            if isinstance(v, np.ndarray)
            and v.dtype.kind in "uifb"
            and v.ndim in (3, 4)
            and min(v.shape) > 0
        ]
    cands = cells + cubes
    if len(cands) == 1 and cells:
        log.info("reading variable '%s' of '%s'", cands[0], p.name)
        return cands[0]
    if len(cands) == 1:  # a numeric array not named `counts`: never guess silently
        raise SplidarError(
            f"'{p.name}' has no `counts` array; it holds: {_summary(d)}. If '{cands[0]}' holds "
            f"the photon counts, select it with `variable` set to '{cands[0]}'."
        )
    what = "photon-list (cell) or count-cube" if want == "data" else "photon-list (cell)"
    if not cands:
        raise SplidarError(
            f"'{p.name}' holds no {what} variable; it holds: {_summary(d)}. A histogram file "
            "needs `counts` (rows, cols[, L], T); a photon-list file a rows x cols cell array "
            "or a photon table: 1-D columns named row, col and time (e.g. row,col,time_ps)."
        )
    raise SplidarError(
        f"'{p.name}' holds several {what} variables ({', '.join(cands)}); it holds: "
        f"{_summary(d)}. Choose one with variable=."
    )


def read_photon_lists(path: str | os.PathLike, variable: str | None = None) -> PhotonLists:
    """Read a rows x cols cell array of photon arrival times from a file.

    Parameters
    ----------
    path : str or path-like
        ``.mat`` (v5 or v7.3) or ``.h5``. (``.npz`` files are never unpickled, so
        they cannot hold cell arrays: :func:`load` reads their photon lists stored
        flat as ``times``, ``pixel_index`` and ``shape``.)
    variable : str, optional
        Name of the cell array; needed only when the file holds several.

    Returns
    -------
    PhotonLists
        Times in the file's unit, with the flat pixel index of each photon.

    Raises
    ------
    SplidarError
        Missing file, unknown extension, variable not found or ambiguous (the message
        lists what the file holds), or a variable that is not a cell array of numbers.

    Examples
    --------
    >>> pl = read_photon_lists("data_face.mat")  # doctest: +SKIP
    >>> pl.shape, round(pl.photons_per_pixel(), 2)  # doctest: +SKIP
    ((340, 340), 8.27)
    """
    p = _check_path(path)
    d = _read_container(p)
    if variable is None and _FLAT_LIST_KEYS <= d.keys():
        return _flat_photon_lists(d, p)
    name = _pick_variable(d, p, variable, "photons")
    v = d[name]
    if not _is_cell_of_numbers(v):
        raise SplidarError(
            f"variable '{name}' of '{p.name}' is not a rows x cols cell array of arrival times "
            f"(got {describe(v)}); the file holds: {_summary(d)}."
        )
    return photon_lists_from_cells(v, source=f"{p.name}:{name}")


def _default_window(times: np.ndarray, bin_width: float) -> tuple[float, float]:
    lo, hi = float(times.min()), float(times.max())
    n = math.floor((hi - lo) / bin_width) + 1  # include the latest photon
    return lo, lo + n * bin_width


def _check_window(window, bin_width) -> tuple[float, float, float]:
    bw = check_positive(bin_width, "bin_width")
    try:
        start, stop = (float(w) for w in window)
    except (TypeError, ValueError):
        raise SplidarError(
            f"`window` must be (start, stop) in the data's time unit; got {describe(window)}."
        ) from None
    if not (np.isfinite(start) and np.isfinite(stop)):
        raise SplidarError(f"`window` must be finite; got {window!r}.")
    if stop <= start:
        raise SplidarError(
            f"`window` must have stop > start; got ({start:g}, {stop:g}). It is the time "
            "range to histogram, in the data's own unit."
        )
    return start, stop, bw


def bin_photons(
    times,
    pixel_index,
    *,
    shape: tuple[int, int],
    window: tuple[float, float],
    bin_width: float = 1.0,
) -> np.ndarray:
    """Histogram photon arrival times into a ``(rows, cols, 1, T)`` count cube.

    Bin ``k`` covers ``[start + k w, start + (k+1) w)``, ``T = ceil((stop - start) / w)``;
    photons outside ``[start, stop)`` (or outside the last bin) are dropped. One
    vectorised pass (``np.unique`` of the flat voxel index), no loop over pixels.

    Parameters
    ----------
    times : array_like, shape (n,)
        Arrival times (any unit; integers are binned with exact integer arithmetic when
        ``start`` and ``bin_width`` are whole numbers).
    pixel_index : array_like of int, shape (n,)
        Flat pixel index ``row * cols + col`` of each photon.
    shape : tuple (rows, cols)
        Image size.
    window : tuple (start, stop)
        Time range to histogram, same unit as ``times``; ``stop > start``.
    bin_width : float
        Width of one bin in the same unit (> 0).

    Returns
    -------
    counts : ndarray, shape (rows, cols, 1, T), uint16 (uint32 if a bin exceeds 65535)

    Raises
    ------
    SplidarError
        Mismatched lengths, pixel indices outside the image, bad window or bin width,
        or a cube that would exceed 8 GiB (choose a wider bin or narrower window).

    Examples
    --------
    >>> c = bin_photons([0, 1, 1, 5], [0, 0, 1, 1], shape=(1, 2), window=(0, 6), bin_width=2)
    >>> c.shape, c[0, 0, 0].tolist(), c[0, 1, 0].tolist()
    ((1, 2, 1, 3), [2, 0, 0], [1, 0, 1])
    """
    return _dense(*_bin_sparse(times, pixel_index, shape, window, bin_width))


def _bin_sparse(times, pixel_index, shape, window, bin_width, irf_fwhm=None):
    """Non-empty voxels of the binned cube: (flat index, count, rows, cols, T). Refused
    above 8 GiB, naming a bin width that fits and suits the pulse (``irf_fwhm``: ``load``'s,
    in bins of ``bin_width``; else measured on the photons: :func:`_bin_hints.memory_hint`)."""
    start, stop, bw = _check_window(window, bin_width)
    try:
        rows, cols = (check_int(s, "shape", minimum=1) for s in shape)
    except (TypeError, ValueError):
        raise SplidarError(f"`shape` must be (rows, cols); got {describe(shape)}.") from None
    t = np.asarray(times).reshape(-1)
    pix = np.asarray(pixel_index).reshape(-1)
    if t.size != pix.size:
        raise SplidarError(
            f"`times` and `pixel_index` must have the same length; got {t.size} and {pix.size}."
        )
    if t.size and t.dtype.kind not in "uif":
        raise SplidarError(f"`times` must be numeric; got dtype {t.dtype}.")
    if pix.size and pix.dtype.kind not in "ui":
        raise SplidarError(f"`pixel_index` must be integers; got dtype {pix.dtype}.")
    n_pix = rows * cols
    if pix.size and (pix.min() < 0 or pix.max() >= n_pix):
        raise SplidarError(
            f"`pixel_index` must lie in [0, {n_pix}) for shape {(rows, cols)}; got range "
            f"[{pix.min()}, {pix.max()}]."
        )
    n_bins = math.ceil((stop - start) / bw - 1e-12)
    n_bins = max(n_bins, 1)
    nbytes = n_pix * n_bins * 2
    if nbytes > _MAX_CUBE_BYTES:
        hint = memory_hint(t, pix, (start, stop), bw, nbytes, irf_fwhm)
        raise SplidarError(
            f"binning into T = {n_bins} bins of width {bw:g} over {(rows, cols)} pixels would "
            f"allocate {nbytes / 2**30:.1f} GiB; pass a larger `bin_width` or a narrower "
            f"`window` (both in the data's time unit){hint}."
        )
    if t.dtype.kind in "ui" and float(start).is_integer() and float(bw).is_integer():
        b = (t.astype(np.int64) - int(start)) // int(bw)
    else:
        b = np.floor((t.astype(np.float64) - start) / bw).astype(np.int64)
    keep = (b >= 0) & (b < n_bins)
    if not np.isinf(stop):
        keep &= t < stop
    flat = pix[keep].astype(np.int64) * n_bins + b[keep]
    uniq, cnt = np.unique(flat, return_counts=True)
    return uniq, cnt, rows, cols, n_bins


def _dense(uniq, cnt, rows, cols, n_bins):
    n_pix = rows * cols
    dtype = np.uint16 if (cnt.size == 0 or cnt.max() <= np.iinfo(np.uint16).max) else np.uint32
    out = np.empty(n_pix * n_bins, dtype=dtype)
    out.fill(0)  # explicit fill: first-touch page faults of np.zeros were 2x slower here
    out[uniq] = cnt
    return out.reshape(rows, cols, 1, n_bins)


# --------------------------------------------------------------------------------------
# IRFs
# --------------------------------------------------------------------------------------
def _trim_zeros(irf: np.ndarray) -> np.ndarray:
    """Drop all-zero samples at both ends (lossless: depth is referenced to the peak)."""
    nz = np.flatnonzero(np.any(irf > 0, axis=0))
    if nz.size == 0:
        return irf
    return irf[:, nz[0] : nz[-1] + 1]


def _crop_irf(irf: np.ndarray, n_bins: int) -> np.ndarray:
    """Crop an ``(L, n)`` IRF to at most ``n_bins - 1`` samples around its peak."""
    n = irf.shape[1]
    limit = max(n_bins - 1, 1)
    if n <= limit:
        return irf
    peak = int(np.argmax(irf.sum(axis=0)))
    lo = min(max(peak - limit // 2, 0), n - limit)
    kept = irf[:, lo : lo + limit].sum() / irf.sum()
    log.warning(
        "IRF (%d samples) is longer than the histograms allow (T = %d); cropped to %d samples "
        "around its peak, keeping %.1f%% of its mass",
        n,
        n_bins,
        limit,
        100 * kept,
    )
    return irf[:, lo : lo + limit]


def _irf_from_container(d: dict[str, Any], p: Path, variable: str | None) -> np.ndarray:
    if variable is not None:
        if variable not in d:
            raise SplidarError(
                f"IRF variable '{variable}' is not in '{p.name}'; it holds: {_summary(d)}."
            )
        name = variable
    elif "irf" in d:
        name = "irf"
    else:
        cands = []
        for k, v in d.items():
            if isinstance(v, np.ndarray) and v.dtype.kind in "uif" and v.size > 1:
                s = [n for n in v.shape if n > 1]
                if len(s) == 1 or (len(s) == 2 and min(s) <= 16):
                    cands.append(k)
        if len(cands) != 1:
            raise SplidarError(
                f"cannot tell which variable of '{p.name}' is the IRF "
                f"({'none looks like one' if not cands else 'candidates: ' + ', '.join(cands)}); "
                f"it holds: {_summary(d)}. Name it with irf_variable= "
                "(variable= when calling load_irf)."
            )
        name = cands[0]
    return np.asarray(d[name])


def _orient_irf(a, source: str, n_wavelengths: int | None = None) -> np.ndarray:
    """Return an IRF as ``(L, n)``; a 2-D array is transposed when it reads as ``(n, L)``.

    With ``n_wavelengths`` known, the axis of that length (or of length 1) is L;
    otherwise a column vector or a taller-than-wide array is read as ``(n, L)``.
    """
    try:
        a = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise SplidarError(f"the IRF in {source} must be numeric; got {describe(a)}.") from None
    if a.ndim == 0:
        a = a.reshape(1, 1)
    if a.ndim > 2:
        a = np.squeeze(a)
    if a.ndim == 1:
        return a[None, :]
    if a.ndim != 2:
        raise SplidarError(f"the IRF in {source} must be 1-D or (L, n); got shape {a.shape}.")
    rows_are_l = a.shape[0] == 1 or (n_wavelengths is not None and a.shape[0] == n_wavelengths)
    cols_are_l = a.shape[1] == 1 or (n_wavelengths is not None and a.shape[1] == n_wavelengths)
    if rows_are_l:
        return a
    if cols_are_l or (n_wavelengths is None and a.shape[0] > a.shape[1]):
        log.info("IRF from %s has shape %s: read as (n, L) and transposed", source, a.shape)
        return a.T
    return a


def load_irf(path: str | os.PathLike, *, variable: str | None = None) -> np.ndarray:
    """Read an IRF ``(L, n)`` from an array, text or vendor file (.npy, .npz, .csv, .ptu, ...).

    The variable ``irf`` is used when present, otherwise the only 1-D (or thin
    ``(L, n)`` with L <= 16) numeric array, otherwise ``variable=`` is required. A 2-D
    array taller than wide is read as ``(n, L)`` columns. All-zero samples at both
    ends are trimmed (lossless: depths are referenced to the IRF peak). Values are
    returned as stored (not normalised; :class:`~splidar.cube.Cube` normalises).
    A ``.npy`` file is one array (read with ``allow_pickle=False``); a vendor file
    (``.ptu``, ``.sdt``) gives its histograms summed over all pixels, one row per
    channel, a PicoQuant ``.phu`` its curves (:func:`splidar.vendor.read_vendor_irf`).

    Parameters
    ----------
    path : str or path-like
    variable : str, optional
        Variable holding the IRF in a container file.

    Returns
    -------
    irf : ndarray, shape (L, n), float64

    Raises
    ------
    SplidarError
        Missing file, unknown extension, ambiguous or missing variable, bad shape.

    Examples
    --------
    >>> irf = load_irf("irf-sample/data_supp.mat")  # doctest: +SKIP
    >>> irf.shape  # doctest: +SKIP
    (1, 31)
    """
    p = _check_path(path)
    ext = _ext(p)
    if ext in (".csv", ".txt"):  # a header row and a time column are skipped
        a = read_irf_text(p)[0]
    elif ext in _CONTAINER_EXTS:
        a = _irf_from_container(_read_container(p), p, variable)
    elif ext == ".npy":
        a = _read_npy(p)
    elif ext in (".ptu", ".sdt", ".phu"):
        from .vendor import read_vendor_irf

        a = read_vendor_irf(p)
    else:
        raise SplidarError(
            f"unknown IRF file extension '{p.suffix}'; use .npy, .npz, .mat, .h5, .csv, .txt, "
            ".ptu, .sdt or .phu."
        )
    out = _trim_zeros(_orient_irf(a, f"'{p.name}'"))
    if not np.all(np.isfinite(out)) or np.any(out < 0) or out.sum() <= 0:
        raise SplidarError(f"the IRF in '{p.name}' must be finite, non-negative and not all zero.")
    return out


def estimate_irf(
    counts,
    *,
    fwhm: float | None = None,
    max_length: int | None = None,
    significance: float = 3.0,
    min_pixels: int = 20,
    fallback: bool = True,
    refine: bool = True,
) -> np.ndarray:
    """Estimate the IRF **shape** from the data, without a model (non-parametric).

    The pulse of a real detector is rarely Gaussian (a SPAD response has a long
    exponential tail); this pools the returns of the bright pixels:

    1. **Bright pixels.** Each pixel (wavelengths summed) is correlated with a template
       (first a Gaussian of ``fwhm``) and its return is the correlation's peak. Its
       background rate ``b`` is the mean count per bin away from the return (outside
       ``[peak - max_length / 4, peak + max_length]``), taken as ``(photons + 1) / bins``
       for the test, so never zero. A pixel is used when the photons in the template's
       window (samples >= 5 % of its peak) would occur under Poisson(``width * b``) with
       a probability below that of a one-sided ``significance``-sigma Gaussian,
       Bonferroni-corrected for the ``T / width`` windows searched: a rule from the
       Poisson noise of each pixel, not a scene constant.
    2. **Align and pool.** Each photon of a used pixel is placed at its lag from the
       return the pixel's *other* photons give (leave-one-out, searched within the
       template's width of the peak; aligning a photon with itself would pile the
       peak bin up); the pixels' histograms so aligned, minus their background, are
       averaged per lag and per wavelength. Whole bins: the estimate is the IRF
       convolved with the alignment's jitter (+-0.5 bin at least).
    3. **Cut.** Walking out of the peak, the curve stops before it reaches
       ``significance`` times its Poisson standard error (the noise floor) or, once
       below half the peak, at its lowest point before a rise of more than
       ``significance`` standard errors (a second surface behind the first); both
       tests read the curve averaged over about half a FWHM.
    4. The pooled shape becomes the template of a second pass (a matched filter: the
       return's reference is then the IRF's own peak).
    5. **Soft alignment** (``refine=True``). Hard alignment is self-consistent with a
       shape blurred by its own jitter (a 3-bin rise becomes about 6 and the peak moves
       into a slowly decaying tail). Expectation-maximisation over each bright pixel's
       unknown return position (within a FWHM of its hard alignment; Poisson model
       ``a h(t - s) + b`` with the pixel's background ``b``) weights every candidate
       shift by its posterior instead of taking one, and re-estimates the shape and the
       pixels' amplitudes; each step is smoothed by ``[1, 2, 1] / 4`` (unsmoothed, the
       steps amplify the noise of the top). At most 20 steps (stopped when the shape
       changes by less than 0.005 in L1); a scene with more than about 4 million
       photon-shift pairs uses every k-th bright pixel. Each row is then normalised to
       unit sum.
    6. **Fall-back.** The best Gaussian (amplitude, centre, width; weighted least
       squares) is fitted to the hard-aligned pooled curve (all wavelengths) on its
       support; when
       its chi-square (``samples - 3`` degrees of freedom, the Poisson standard errors)
       does not reject it at the ``significance``-sigma p-value, the pooled photons
       cannot support a shape better than a Gaussian and the Gaussian of ``fwhm`` is
       returned instead (logged; ``load`` records it in ``metadata["irf_source"]``).
    7. **Reference** (the soft-aligned shape of step 5; a hard-aligned one, whose local
       maxima are Poisson wiggles, keeps its argmax). The depth reference is the
       shape's maximum. Each sample's chance of being the true maximum is computed from
       the pooled curve's Poisson standard errors (independent Gaussian errors) and
       credited to the local maximum (peak) it climbs to; the sample at the expected
       position of the peak so weighted is raised to just above the maximum (a change
       within its noise). A shape with one peak, or whose photons determine its peak,
       keeps its argmax; on a top that is flat within the noise with two bumps the
       reference lies between them, in proportion to their chances, instead of jumping
       to one end.

    Parameters
    ----------
    counts : ndarray, shape (rows, cols, L, T) or (rows, cols, T)
        Photon counts (non-negative).
    fwhm : float, optional
        Width (bins) of the first pass's Gaussian template. Default:
        :func:`estimate_irf_fwhm` of ``counts``.
    max_length : int, optional
        Longest tail searched after the peak, bins (the leading edge: a quarter of it).
        Default ``min(T // 3, max(32, 20 * fwhm))``.
    significance : float, default 3.0
        Sigmas of the Poisson tests (bright pixels, noise floor, second-surface rise).
    min_pixels : int, default 20
        Fewest bright pixels accepted.
    fallback : bool, default True
        Return the Gaussian of ``fwhm`` when the pooled curve does not reject a
        Gaussian (step 6); ``False``: always the pooled shape.
    refine : bool, default True
        The soft alignment (step 5); ``False``: the hard-aligned pooled shape (the
        estimate of earlier releases, whose peak may sit 1-6 bins into a
        slowly decaying tail).

    Returns
    -------
    irf : ndarray, shape (L, n), float64
        Non-negative, unit sum per wavelength, cut to its support (rows of different
        lengths padded with zeros at the end). The depth reference is each row's
        ``argmax`` (:func:`splidar.irf.irf_peak`). Units: time bins of ``counts``.

    Raises
    ------
    SplidarError
        ``counts`` not of the forms above, negative or not finite; a bad option
        (named); fewer than ``min_pixels`` bright pixels, or a wavelength without a
        return: give the IRF (``irf=``) or a Gaussian width (``irf_fwhm=``).

    Notes
    -----
    The depth reference is the estimate's argmax (step 7). On the simulated pulses of
    ``benchmarks/bench_irf_estimate.py`` the soft alignment brings the depth bias of
    ``process`` with the estimate within 0.2 bin of the true IRF's on exp tail 3/6 and
    the measured pulse, and within about 1 bin of it on the slowly decaying exp tail
    2/25 (the hard alignment: +1 and +5); whole-bin alignment of sub-bin depths still
    flattens the top by about half a bin, so on a pulse whose next sample is within
    10 % of its peak the argmax may sit on either. A second
    surface at a fixed distance behind the first is cut away; second surfaces at
    depths that vary from pixel to pixel within ``max_length`` average into a pedestal
    that the cut may keep as tail. Needs the counts in memory (not lazy data).
    It works on the non-empty voxels (compiled loops): about 2-3 s CPU on a 340 x 340 x
    1750 cube of 8 photons per pixel. Equal correlation scores (frequent with a few
    integer counts and a symmetric template) go to the earlier bin for even pixels
    (photons), the later for odd ones, so neither side is favoured.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.ndimage import convolve1d
    >>> from splidar.irf import exp_tail_irf
    >>> rng = np.random.default_rng(0)
    >>> h = exp_tail_irf(2.0, 6.0)
    >>> lam = np.zeros((40, 40, 160))
    >>> lam[np.arange(40)[:, None], np.arange(40), rng.integers(40, 100, (40, 40))] = 30.0
    >>> y = rng.poisson(convolve1d(lam, h, axis=-1) + 0.02)
    >>> est = estimate_irf(y)
    >>> est.shape[0], round(float(est.sum()), 6)
    (1, 1.0)
    """
    irf, _ = _estimate_irf(
        counts,
        fwhm=fwhm,
        max_length=max_length,
        significance=significance,
        min_pixels=min_pixels,
        fallback=fallback,
        refine=refine,
    )
    return irf


def _estimate_irf(
    counts,
    *,
    fwhm,
    max_length,
    significance,
    min_pixels,
    fallback,
    refine=True,
    voxels=None,
    stats=None,
    reference=True,
):
    """:func:`estimate_irf`; also its source for ``metadata["irf_source"]``. ``voxels``:
    photon lists' sorted non-empty (flat voxel index, count) of one-wavelength ``counts``.
    ``stats``: a dict given gets ``"n_used"``, the number of bright pixels pooled."""
    from scipy.stats import norm

    from ._irf_estimate import pooled_shape

    a = np.asarray(counts)
    if a.ndim == 3:
        a = a[:, :, None, :]
    if a.ndim != 4 or a.shape[-1] < 8 or a.size == 0:
        raise SplidarError(
            f"`counts` must be (rows, cols[, L], T) with T >= 8 bins; got {describe(counts)}."
        )
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise SplidarError(f"`counts` must hold photon counts; got {describe(counts)}.")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        raise SplidarError("`counts` holds NaN or inf; photon counts must be finite.")
    if a.min() < 0:
        raise SplidarError("`counts` holds negative values; photon counts must be >= 0.")
    z = check_positive(significance, "significance")
    min_pixels = check_int(min_pixels, "min_pixels", minimum=1)
    n_bins = a.shape[-1]
    fwhm = estimate_irf_fwhm(a) if fwhm is None else check_positive(fwhm, "fwhm")
    if max_length is None:
        k_right = int(min(n_bins // 3, max(32, math.ceil(20 * fwhm))))
    else:
        k_right = check_int(max_length, "max_length", minimum=2)
        if k_right > n_bins - 2:
            raise SplidarError(
                f"`max_length` must be below T - 1 = {n_bins - 1} bins; got {k_right}."
            )
    k_left = max(2, k_right // 4)
    out, n_used, (c2, dof, p) = pooled_shape(
        a.reshape(-1, *a.shape[2:]),
        fwhm,
        k_left,
        k_right,
        z,
        min_pixels,
        refine=bool(refine),
        gaussian_p=norm.sf(z) if fallback else 2.0,
        voxels=voxels if a.shape[2] == 1 else None,
        reference=bool(reference),
    )
    if stats is not None:
        stats["n_used"] = n_used
    if fallback and p >= norm.sf(z):
        log.warning(
            "IRF shape: the pooled curve of %d bright pixels does not reject a Gaussian "
            "(chi2 %.1f on %d dof, p %.2g >= %.2g): using the Gaussian of FWHM %.2f bins",
            n_used,
            c2,
            dof,
            p,
            norm.sf(z),
            fwhm,
        )
        g = np.repeat(gaussian_irf(fwhm)[None, :], out.shape[0], axis=0)
        return g, (
            f"estimated gaussian fwhm={fwhm:.3f} bins (shape not supported by the pooled "
            f"photons: chi2 {c2:.1f} on {dof} dof, p {p:.2g})"
        )
    log.info("IRF shape estimated from %d bright pixels: %d samples", n_used, out.shape[1])
    return out, f"estimated shape from the data ({out.shape[1]} samples)"


def estimate_irf_fwhm(counts, *, max_lag: int | None = None) -> float:
    """Estimate the IRF width (FWHM, bins) from the photons themselves.

    Uses the time differences of photon pairs **within the same pixel**: two signal
    photons from one surface differ by the IRF's autocorrelation whatever the pixel's
    depth, so no per-pixel peak alignment (and none of its self-alignment bias at a
    few photons per pixel) is needed. Background pairs add a floor, made flat by
    dividing lag ``k`` by the ``T - k`` bin pairs it spans. The pairs of a return with
    its own pixel's background are flat in ``k`` already, and that division tilts them
    up: under heavy background and on short records the width reads too narrow (a 3-bin
    pulse at SBR 0.01, T 200: 1.5 bins; ``load``'s IRF check removes the tilt,
    ``_irf_width._cross_tilt``). The floor is the median of the outer quarter of the lag window, and
    the FWHM of the autocorrelation peak above it is read at the half-maximum
    crossing (linear interpolation); for a Gaussian IRF this is ``sqrt(2)`` times the
    IRF's FWHM, which is what is returned. For a skewed or heavy-tailed pulse it is
    a Gaussian-equivalent width: give a measured IRF when you have one.

    Parameters
    ----------
    counts : ndarray, shape (rows, cols, L, T) or (rows, cols, T)
        Photon counts (all wavelengths pooled).
    max_lag : int, optional
        Largest lag used, bins. Default: grown from 32 (x2, at most T / 2) until the
        half-maximum crossing lies below a quarter of it, so the floor is measured well
        outside the peak.

    Returns
    -------
    fwhm : float
        Estimated FWHM in bins (at least 0.5: a pulse narrower than a bin is not
        resolved).

    Notes
    -----
    The wavelengths of a pixel are pooled (pairs across them count, lag 0 included).
    Dense cubes (more than 50 million pairs of non-empty voxels within the lag window)
    use every k-th pixel, a deterministic subset: the cost stays bounded. When no lag
    stands 5 standard deviations above the floor (a broad or long-tailed pulse spreads
    its excess over many lags), sums of 3, 5, 9, ... adjacent lags are tested (7 sd),
    then wider lag windows; only when none shows a peak does it raise. The route taken
    is logged (INFO).

    Raises
    ------
    SplidarError
        Too few photon pairs or no peak standing out of the background floor: give
        the IRF explicitly (``irf=`` or ``irf_fwhm=``).

    Examples
    --------
    >>> import numpy as np
    >>> from splidar.irf import gaussian_irf
    >>> rng = np.random.default_rng(0)
    >>> d = rng.integers(20, 80, (40, 40))
    >>> lam = np.zeros((40, 40, 120))
    >>> lam[np.arange(40)[:, None], np.arange(40), d] = 20.0
    >>> from scipy.ndimage import convolve1d
    >>> y = rng.poisson(convolve1d(lam, gaussian_irf(6.0), axis=-1) + 0.01)
    >>> bool(5.0 < estimate_irf_fwhm(y) < 7.0)
    True
    """
    a = np.asarray(counts)
    if a.ndim == 3:
        a = a[:, :, None, :]
    if a.ndim != 4:
        raise SplidarError(f"`counts` must be (rows, cols[, L], T); got shape {a.shape}.")
    n_l, n_bins = a.shape[2], a.shape[3]
    flat = a.reshape(-1, n_bins)
    rowi, b = np.nonzero(flat)
    w = flat[rowi, b]
    return pair_lag_fwhm(rowi // n_l, b, w, n_bins, max_lag)


def _resolve_irf(irf, irf_fwhm, irf_variable, file_irf, counts, n_bins: int, sparse=None):
    """Return (irf array (L, n), source description)."""
    n_l = int(counts.shape[2]) if counts.ndim == 4 else 1
    if irf is not None and irf_fwhm is not None:
        raise SplidarError("give either `irf` or `irf_fwhm`, not both.")
    if irf_fwhm is not None:
        fwhm = check_positive(irf_fwhm, "irf_fwhm")
        g = gaussian_irf(fwhm)
        return g[None, :], f"gaussian fwhm={fwhm:g} bins"
    if isinstance(irf, (int, float, np.number)) and not isinstance(irf, bool):
        raise SplidarError(
            f"`irf` got the number {irf!r}; for a Gaussian IRF pass irf_fwhm={irf!r} (FWHM in "
            "bins); `irf` takes an array, a file path, 'estimate' or 'estimate-shape'."
        )
    if isinstance(irf, str) and irf == "estimate-shape":
        if hasattr(counts, "compute") and not isinstance(counts, np.ndarray):
            raise SplidarError(
                "irf='estimate-shape' needs the counts in memory, not lazy (Dask/zarr) data; "
                "pass irf= (array or file) or irf_fwhm=."
            )
        return _estimate_irf(
            counts, fwhm=None, max_length=None, significance=3.0, min_pixels=20, fallback=True
        )
    gaussian_only = isinstance(irf, str) and irf == "estimate"
    if gaussian_only:
        file_irf = None
        irf = None
    elif isinstance(irf, (str, os.PathLike)):
        a = load_irf(irf, variable=irf_variable)
        return _orient_irf(a, f"'{irf}'", n_l), f"file {irf}"
    if irf is not None:
        return _orient_irf(irf, "`irf`", n_l), "given array"
    if file_irf is not None:
        return _orient_irf(file_irf, "the file", n_l), "file"
    if hasattr(counts, "compute") and not isinstance(counts, np.ndarray):
        raise SplidarError(
            "the data hold no IRF and it is not estimated from lazy (Dask/zarr) data; pass "
            "irf= (array or file) or irf_fwhm= (Gaussian FWHM in bins)."
        )
    if sparse is None and not np.any(counts):
        raise SplidarError(
            "the counts hold no photon (every voxel is 0): there is no IRF to estimate and "
            "nothing to detect. Check the file, its variable and the time window."
        )
    seen: list = []
    fwhm, k = _pooled_fwhm_or_untilted(counts, n_bins, sparse, seen)
    if not gaussian_only:  # the shape (irf20's proposal); its Gaussian fall-back inside
        # its blocks start where a pair peak was first seen (the width's level may be
        # coarser: where the width is determined, irf24)
        shaped = _pooled_shape(counts, fwhm, seen[0], sparse)
        if shaped is not None:
            arr, src = shaped
            log.warning(
                "no IRF given and none in the file: %s (pass irf= or irf_fwhm= to override, "
                "irf='estimate' for a Gaussian of the estimated width)",
                src,
            )
            return arr, src
    g = gaussian_irf(fwhm)
    how = "photon-pair time differences" + _blocks_text(k)
    log.warning(
        "no IRF given and none in the file: estimated a Gaussian IRF of FWHM %.2f bins from "
        "%s (pass irf= or irf_fwhm= to override)",
        fwhm,
        how,
    )
    return g[None, :], f"estimated gaussian fwhm={fwhm:.3f} bins" + _blocks_text(k)


#: fewest pixel blocks the weak-signal pooling keeps (the shape needs 20 bright ones)
_MIN_BLOCKS = 16
#: bright pixels (or blocks) per sample of the estimated shape from which the shape is
#: taken without measuring its split-half spread against the next coarser pixel blocks
#: (a cost bound, not the choice: the spread there is a few hundredths; every real file
#: of benchmarks/real_data.py holds 31-750 per sample; irf23)
_SPLIT_ABOVE = 16
#: fewest bright blocks per sample of the shape that a block level's shape is taken from
#: without trying coarser blocks (irf22b; the blocks' own rule, the split-half spread
#: decides between single pixels and blocks)
_PIXELS_PER_SAMPLE = 2


def _blocks_text(k: int) -> str:
    return "" if k == 1 else f" (pooled over {k} x {k} pixel blocks: weak signal)"


def _block_index(pix: np.ndarray, n_cols: int, k: int) -> np.ndarray:
    """Flat index of the ``k x k`` block of each flat pixel index (row-major)."""
    r, c = np.divmod(np.asarray(pix, dtype=np.int64), n_cols)
    return (r // k) * (-(-n_cols // k)) + c // k


def _pooled_fwhm_or_untilted(counts, n_bins: int, sparse, seen: list) -> tuple[float, int]:
    """:func:`_pooled_fwhm`; where it finds no return, once more with the pairs of the
    returns with their pixels' background untilted
    (:func:`splidar._irf_width._cross_tilt`): under heavy background the triangle
    correction's tilt can hide the peak (PPP 100 at SBR 0.01: Gaussian FWHM 10, exp
    tail 3/6 and the measured pulse raised on 14 of 54 cubes, all load with it;
    benchmarks/README.md rob30). A file that loaded keeps its width: elsewhere the
    removal moved tailed pulses' IRFs at PPP 1-2 for the worse
    (``TILT_LOAD``)."""
    try:
        return _pooled_fwhm(counts, n_bins, sparse, seen)
    except SplidarError as exc:
        if TILT_LOAD[0] or not TILT_RESCUE[0]:
            raise
        first = exc
    seen.clear()
    try:
        out = _pooled_fwhm(counts, n_bins, sparse, seen, tilt=True)
    except SplidarError:
        raise first from None  # the message of the width as it was
    log.warning(
        "IRF width: the photon-pair peak shows only with the pairs of the returns with "
        "their pixels' background untilted (heavy background): FWHM %.2f bins",
        out[0],
    )
    return out


def _pooled_fwhm(counts, n_bins: int, sparse, seen=None, tilt=None) -> tuple[float, int]:
    """The pair-lag width (:func:`estimate_irf_fwhm`) of ``counts``; when single pixels
    show no pair peak (weak signal: a few tenths of a signal photon per pixel), on
    ``k x k`` pixel blocks, ``k = 2, 4, 8, ...`` while at least ``_MIN_BLOCKS`` blocks
    remain: neighbouring pixels of a real scene share their depth, so a block's
    photons hold ``k^2`` times the signal pairs (the depth differences within a block
    widen the width). A level's width is taken only where it is determined (irf24): the
    ``WIDTH_Z``-sigma bracket of its half-maximum crossing
    (:func:`splidar._irf_width._half_max_bounds`) has a half-length below the width
    (the width differs from 0 at that significance; a lone noisy lag 0 gave 1-bin
    widths for a 16-bin pulse), and overlaps the brackets of the finer levels (blocks
    of pixels at unrelated depths measure the depth spread, not the pulse). When no
    level determines it, the finest level's width (the one taken before irf24), with a
    warning. Returns (FWHM, k); raises naming ``irf=`` when no level shows a return.
    ``seen``: a list given gets the first level whose pairs show a peak (determined or
    not). ``tilt``: :func:`splidar._irf_width.pair_lag_fwhm`'s."""
    n_rows, n_cols = int(counts.shape[0]), int(counts.shape[1])
    n_l = int(counts.shape[2]) if counts.ndim == 4 else 1
    if sparse is not None:  # photon lists: (flat voxel index, count) already at hand
        uniq, w = sparse
        pix, b = uniq // n_bins, uniq % n_bins
    else:
        flat = np.asarray(counts).reshape(-1, n_bins)
        rowi, b = np.nonzero(flat)
        w = flat[rowi, b]
        pix = rowi // n_l
    k, vague, finer = 1, [], []
    while True:
        if k == 1:
            key_p, key_b, key_w = pix, b, w
        else:  # one voxel per (block, bin): the pair count stays within blocks x T x lag
            key = _block_index(pix, n_cols, k) * n_bins + np.asarray(b, dtype=np.int64)
            u, inv = np.unique(key, return_inverse=True)
            key_w = np.bincount(inv.ravel(), weights=np.asarray(w, np.float64))
            key_p, key_b = u // n_bins, u % n_bins
        bounds: list = []
        try:
            fwhm = pair_lag_fwhm(key_p, key_b, key_w, n_bins, None, bounds, tilt=tilt)
            if seen is not None and not seen:
                seen.append(k)
            # the width is taken where it differs from 0 at WIDTH_Z sigma: its bracket's
            # half-length (the half-maximum crossing's noise) below the width (irf24)
            clash = [f for f in finer if bounds[1] < f[0] or bounds[0] > f[1]]
            if (bounds[1] - bounds[0]) / 2 > fwhm:
                if not clash:
                    vague.append((k, fwhm, bounds))
                    finer.append(bounds)
                raise SplidarError(
                    f"the photon-pair width is not determined ({fwhm:.2f} bins, between "
                    f"{bounds[0]:.2f} and {bounds[1]:.2f} at {WIDTH_Z:g} sigma)"
                )
            if clash:
                raise SplidarError(
                    f"the photon-pair width on {k} x {k} pixel blocks ({fwhm:.2f} bins, between "
                    f"{bounds[0]:.2f} and {bounds[1]:.2f}) is outside the finer level's "
                    f"({clash[0][0]:.2f} to {clash[0][1]:.2f}): the blocks' depth spread"
                )
        except SplidarError as exc:
            nxt = 2 * k
            if -(-n_rows // nxt) * -(-n_cols // nxt) < _MIN_BLOCKS and vague:
                # no level determines it: the finest level's width (as before irf24), warned
                k, fwhm, bounds = vague[0]
                log.warning(
                    "IRF width not determined by the photon-pair time differences at any "
                    "level of pixel pooling: %.2f bins (between %.2f and %.2f at %g sigma, "
                    "%s); pass irf= or irf_fwhm= if you know it",
                    fwhm,
                    bounds[0],
                    bounds[1],
                    WIDTH_Z,
                    "single pixels" if k == 1 else f"{k} x {k} pixel blocks",
                )
                return fwhm, k
            if -(-n_rows // nxt) * -(-n_cols // nxt) < _MIN_BLOCKS:
                n_ph = float(np.sum(w))
                where = (
                    f"on single pixels and pooled over pixel blocks up to {k} x {k}"
                    if k > 1
                    else "on single pixels (too few pixels to pool blocks)"
                )
                raise SplidarError(
                    f"no return found to estimate the IRF from: {exc.args[0].split(';')[0]}, "
                    f"{where} ({n_ph:,.0f} photons, "
                    f"{n_ph / max(n_rows * n_cols, 1):.2g} per pixel). "
                    "If the data do hold a return, pass irf= (array or file) or irf_fwhm= "
                    "(Gaussian FWHM in bins)."
                ) from None
            log.info("IRF width: %s; pooling %d x %d pixel blocks", exc.args[0][:90], nxt, nxt)
            k = nxt
            continue
        if k > 1:
            log.warning(
                "IRF width: no determined photon-pair peak within single pixels (weak signal); "
                "measured on %d x %d pixel blocks: FWHM %.2f bins (the depth differences "
                "within a block may widen it)",
                k,
                k,
                fwhm,
            )
        return fwhm, k


def _block_sum(counts, k: int) -> np.ndarray:
    """``counts`` (R, C[, L], T) summed over ``k x k`` pixel blocks (edges padded)."""
    a = np.asarray(counts)
    if a.ndim == 3:
        a = a[:, :, None, :]
    r, c = a.shape[:2]
    rp, cp = -(-r // k) * k, -(-c // k) * k
    dt = np.float64 if np.issubdtype(a.dtype, np.floating) else np.int64
    pad = np.zeros((rp, cp) + a.shape[2:], dtype=dt)
    pad[:r, :c] = a
    return pad.reshape(rp // k, k, cp // k, k, *a.shape[2:]).sum(axis=(1, 3))


def _split_spread(cube, fwhm: float) -> float:
    """The estimate's own spread on ``cube`` (R, C[, L], T): the shape (no Gaussian
    fall-back) of each half of its pixels, the halves' L1 distance (at their best
    correlation, the largest over wavelengths) averaged over two partitions
    (:func:`splidar._irf_estimate.split_halves`); ``inf`` where a half has fewer than
    10 bright pixels (half the 20 the shape needs)."""
    from ._irf_estimate import shape_distance, split_halves

    a = np.asarray(cube)
    if a.ndim == 3:
        a = a[:, :, None, :]
    flat = a.reshape(-1, 1, *a.shape[2:])
    out = []
    for first in split_halves(a.shape[0], a.shape[1]):
        halves = []
        for m in (first, ~first):
            try:
                h, _ = _estimate_irf(
                    flat[m],
                    fwhm=fwhm,
                    max_length=None,
                    significance=3.0,
                    min_pixels=10,
                    fallback=False,
                    reference=False,
                )
            except SplidarError:
                return math.inf
            halves.append(h)
        out.append(max(shape_distance(x, y) for x, y in zip(*halves, strict=True)))
    return float(np.mean(out))


def _pooled_shape(counts, fwhm: float, k: int, sparse=None):
    """The shape (:func:`_estimate_irf`) on single pixels; where they are too few bright
    ones, or their pooled photons do not reject a Gaussian (the Gaussian fall-back), on
    ``k x k`` pixel blocks (``k`` doubling from 2, or from the width's level, while at
    least ``_MIN_BLOCKS`` blocks remain): a block holds ``k^2`` times a pixel's signal
    (its depth spread widens the shape a little).

    Single pixels' shape against blocks (irf23): below ``_SPLIT_ABOVE`` bright pixels
    per sample, the next level's shape is estimated too and the one of the lower
    split-half spread (:func:`_split_spread`, the estimate's own noise) is taken.
    Block levels (single pixels without a shape): the first one that gives a shape from
    at least ``_PIXELS_PER_SAMPLE`` bright blocks per sample wins, else the level of the
    most bright blocks (the finer on ties) (irf22b); else the single pixels' Gaussian
    fall-back, or None (the caller keeps the Gaussian of the width). Returns (irf,
    source) or None."""
    n_rows, n_cols = int(counts.shape[0]), int(counts.shape[1])
    level, gaussian, best, first = 1, None, None, None
    while True:
        cube = counts if level == 1 else _block_sum(counts, level)
        stats: dict = {}
        try:
            arr, src = _estimate_irf(
                cube,
                fwhm=fwhm,
                max_length=None,
                significance=3.0,
                min_pixels=20,
                fallback=True,
                voxels=sparse if level == 1 else None,
                stats=stats,
            )
        except SplidarError as exc:
            if first is not None:  # the blocks have too few bright ones: the pixels' shape
                return first[1]
            if "pixel(s) with a return" not in str(exc):
                log.warning("IRF shape not estimated (%s); using the Gaussian", exc)
                return best[1] if best is not None else gaussian
            why = "too few bright pixels"
        else:
            if src.startswith("estimated shape"):
                if level == 1 and k > 1:
                    src += f" (its width pooled over {k} x {k} pixel blocks: weak signal)"
                shaped = (arr, src + _blocks_text(level))
                per = stats["n_used"] / arr.shape[1]
                if first is not None:  # blocks against the single pixels' shape
                    spread = _split_spread(cube, fwhm)
                    # neither spread measurable (halves of too few bright pixels): the
                    # level of the more bright pixels (blocks), as irf22b
                    blocks = spread < first[0] or (
                        math.isinf(spread) and math.isinf(first[0]) and stats["n_used"] > first[2]
                    )
                    log.info(
                        "IRF shape: split-half spread %.3f on %d x %d pixel blocks, %.3f on "
                        "single pixels: the %s taken",
                        spread,
                        level,
                        level,
                        first[0],
                        "blocks" if blocks else "single pixels",
                    )
                    return shaped if blocks else first[1]
                if level == 1:
                    if per >= _SPLIT_ABOVE:
                        return shaped
                    first = (_split_spread(cube, fwhm), shaped, stats["n_used"])
                    why = (
                        f"{stats['n_used']} bright pixels for a shape of {arr.shape[1]} "
                        f"samples, split-half spread {first[0]:.3f}; comparing pixel blocks"
                    )
                else:
                    if per >= _PIXELS_PER_SAMPLE:
                        return shaped
                    if best is None or stats["n_used"] > best[0]:
                        best = (stats["n_used"], shaped)
                    why = (
                        f"{stats['n_used']} bright blocks for a shape of {arr.shape[1]} "
                        f"samples (fewer than {_PIXELS_PER_SAMPLE} per sample)"
                    )
            else:
                if first is not None:  # the blocks fall back to a Gaussian: the pixels' shape
                    return first[1]
                if gaussian is None:
                    gaussian = (arr, src + _blocks_text(k))
                why = "the pooled photons do not reject a Gaussian"
        nxt = max(2 * level, k)
        if -(-n_rows // nxt) * -(-n_cols // nxt) < _MIN_BLOCKS:
            if first is not None:
                return first[1]
            return best[1] if best is not None else gaussian
        log.info("IRF shape: %s; pooling %d x %d pixel blocks", why, nxt, nxt)
        level = nxt


# --------------------------------------------------------------------------------------
# load / save
# --------------------------------------------------------------------------------------
def _metadata_from(v) -> dict:
    if v is None:
        return {}
    s = v.item() if isinstance(v, np.ndarray) and v.size == 1 else v
    if isinstance(s, bytes):
        s = s.decode()
    if not isinstance(s, str):
        return {}
    try:
        out = json.loads(s)
    except json.JSONDecodeError:
        return {"metadata": s}
    return out if isinstance(out, dict) else {"metadata": out}


def _library_from(d: dict[str, Any]):
    if "library" not in d:
        return None
    names = _str_list(d.get("class_names"))
    return SpectralLibrary(np.asarray(d["library"], dtype=np.float64), class_names=names)


def load(
    path: str | os.PathLike,
    *,
    variable: str | None = None,
    window: tuple[float, float] | None = None,
    bin_width: float | None = None,
    time_unit: str = "bin",
    irf=None,
    irf_fwhm: float | None = None,
    irf_variable: str | None = None,
    irf_bin_width_ps: float | None = None,
    bin_width_ps: float | None = None,
    wavelengths_nm=None,
    library=None,
    channels=None,
    time_axis: int | None = None,
    wavelength_axis: int | None = None,
) -> Cube:
    """Read a histogram cube or photon time lists from a file into a :class:`Cube`.

    Parameters
    ----------
    path : str or path-like
        ``.npz``, ``.npy``, ``.mat`` (v5 or v7.3), ``.h5``/``.hdf5``, a ``.zarr``
        directory or vendor files (``.ptu``, ``.sdt``: :mod:`splidar.vendor`).
        Nothing is unpickled; sizes are checked before allocating (docs/reliability.md).
        A ``.npz`` holds photon lists flat: ``times`` (n,), ``pixel_index`` (n,) = ``row *
        cols + col`` and ``shape`` (rows, cols).
    variable : str, optional
        Which variable holds the data when the file holds several. Default: ``counts``
        if present, else the only cell array of arrival times or numeric 3-D/4-D array;
        otherwise an error lists what the file holds.
    window : (start, stop), optional
        Photon lists: the time range to histogram, in the data's unit (``time_unit``).
        Default: from the earliest to the latest photon (logged). Histogram files: an
        integer bin range ``[start, stop)`` to crop along T.
    bin_width : float, optional
        Photon lists only: bin width in the data's unit (default 1: one unit per bin).
        ``T = ceil((stop - start) / bin_width)``.
    time_unit : {"bin", "fs", "ps", "ns", "us", "ms", "s"}
        Photon lists only: unit of the arrival times. With a physical unit, the cube's
        ``bin_width_ps`` is ``bin_width`` converted to picoseconds. ``"bin"`` (default)
        means time-bin indices of unknown duration.
    irf : array_like (L, n) or (n,), path, "estimate" or "estimate-shape", optional
        Instrument response. Default: the file's ``irf``; if it has none and the counts
        are in memory, the non-parametric shape pooled from the bright pixels
        (:func:`estimate_irf`, seeded by :func:`estimate_irf_fwhm`; logged as a
        warning), or a Gaussian of the estimated width where the pooled photons do not
        reject a Gaussian or the shape cannot be estimated (too few bright pixels).
        Weak signal (a few tenths of a signal photon per pixel): where single pixels
        give no width or no shape, both are measured on 2 x 2, 4 x 4, ... pixel blocks
        (at least 16 blocks; neighbouring pixels share their depth), logged and
        recorded in ``metadata["irf_source"]``; when no level shows a return, load
        raises, naming ``irf=`` / ``irf_fwhm=``.
        ``"estimate"``: always that Gaussian (the opt-out). ``"estimate-shape"``: the
        shape, whatever IRF the file holds. A path is read by :func:`load_irf`. An
        IRF longer than T - 1 samples is cropped around its peak (logged).
    irf_fwhm : float, optional
        Use a Gaussian IRF of this FWHM in bins instead (data without a measured IRF).
    irf_variable : str, optional
        Variable of the IRF file to read (see :func:`load_irf`).
    irf_bin_width_ps : float, optional
        The supplied IRF's sample step in picoseconds (``irf=`` or the file's own), when
        it was recorded at another bin width than the cube's: resampled onto the cube's
        bins (needs the cube's bin width; overrides a text IRF's time column). A
        supplied IRF (or ``irf_fwhm``) whose width differs from the data's own pulse
        width by more than a factor 2 is warned about, naming this option; nothing is
        rescaled without it (docs/usage.md).
    bin_width_ps : float, optional
        Overrides the bin width in picoseconds (e.g. known for bin-index data).
    wavelengths_nm : array_like (L,), optional
        Overrides the file's wavelengths.
    library : SpectralLibrary, array (K, L) or path, optional
        Overrides the file's spectral library.
    channels : {"wavelengths", "detectors"}, int or sequence of int, optional
        Vendor files: channels as wavelengths (default), summed, or a subset (see vendor).
    time_axis : int, optional
        Histogram files: the stored array's time axis (``0`` for ``(T, rows, cols)``),
        moved last. Default: the last, with a warning when the shape suggests time first
        (first axis over twice the others, last the shortest); ``-1`` silences it.
    wavelength_axis : int, optional
        Histogram files: the stored 4-D array's wavelength axis (``0`` for ``(L, rows,
        cols, T)``), moved before time; rows and cols keep their order. Default: the
        axis before time, with a warning when the first axis is short (<= 16) and that
        one longer than 16.

    Returns
    -------
    Cube
        Photon lists become ``(rows, cols, 1, T)`` uint16 counts; ``metadata`` records the
        source, variable, window, bin width, time unit and IRF source.

    Raises
    ------
    SplidarError
        Missing file, unknown extension, variable missing or ambiguous (lists the
        contents), wrong shape, ``window`` with stop <= start, ``bin_width`` <= 0,
        unknown ``time_unit``, options that do not apply, IRF problems.

    Examples
    --------
    >>> cube = load("face/data_face.mat", irf_fwhm=20)  # doctest: +SKIP
    >>> cube.shape  # doctest: +SKIP
    (340, 340, 1, 7001)
    >>> tower = load("tower/tower.mat", variable="data_processed", time_unit="ps",
    ...              window=(5_180_000, 5_380_000), bin_width=100)  # doctest: +SKIP
    """
    check_choice(time_unit, "time_unit", tuple(TIME_UNITS_PS))
    p = _check_channels_apply(_check_path(path), channels)
    if _ext(p) == ".zarr":
        cube = _load_zarr(
            p, irf_opts=(irf, irf_fwhm, irf_variable, irf_bin_width_ps),
            bin_width_ps=bin_width_ps, variable=variable,
            time_axis=time_axis if wavelength_axis is None else (time_axis, wavelength_axis),
        )  # fmt: skip
        return mark_checked(_override(cube, bin_width_ps, wavelengths_nm, library))
    d = _read_any(p, channels)
    flat = variable is None and "counts" not in d and _FLAT_LIST_KEYS <= d.keys()
    d, time_unit, n_wl, flat = _photon_table(d, p, time_unit, flat, variable)
    name = "times" if flat else _pick_variable(d, p, variable, "data")
    d = _group_siblings(d, p, name)
    v = d[name]
    meta: dict[str, Any] = {"source": str(p), "variable": name}
    sparse = None
    from_save = False
    if flat or _is_cell_of_numbers(v):
        src = f"{p.name}:{name}"
        pl = _flat_photon_lists(d, p) if flat else photon_lists_from_cells(v, source=src)
        counts, md, sparse = _bin_lists(pl, window, bin_width, time_unit, n_wl, irf_fwhm)
        meta.update(md)
        bw_ps = md.get("bin_width_ps")
    else:
        _check_cube_options(bin_width, time_unit)
        axes = (time_axis, wavelength_axis)
        counts, meta, from_save = _binned_cube(d, p, name, window, meta, axes)
        bw_ps = _scalar(d["bin_width_ps"], "bin_width_ps") if "bin_width_ps" in d else None
    file_irf, wl, lib = d.get("irf"), d.get("wavelengths_nm"), _library_from(d)
    irf_opts = (irf, irf_fwhm, irf_variable, irf_bin_width_ps)
    bw = bw_ps if bin_width_ps is None else bin_width_ps
    irf_a = _cube_irf(irf_opts, file_irf, counts, bw, sparse, from_save, meta)
    cube = Cube(
        counts,
        irf=irf_a,
        bin_width_ps=bw_ps,
        wavelengths_nm=None if wl is None else np.asarray(wl, dtype=np.float64).reshape(-1),
        library=lib,
        metadata=meta,
    )
    return mark_checked(_override(cube, bin_width_ps, wavelengths_nm, library))


def _cube_irf(irf_opts, file_irf, counts, bw_ps, sparse, from_save: bool, meta: dict):
    """The cube's IRF ``(L, n)`` for :func:`load` (``meta["irf_source"]`` set): the text
    IRF's time column or ``irf_bin_width_ps`` resampled onto the bins of ``bw_ps``
    picoseconds, cropped to T - 1 samples, its width checked against the data's
    (:func:`check_irf_width`; not for a saved Cube's own IRF nor an estimated one)."""
    irf, irf_fwhm, irf_variable, irf_bin_width_ps = irf_opts
    n_bins = counts.shape[-1]
    if irf_bin_width_ps is None:
        irf, resampled = irf_on_bins(irf, bw_ps)
    else:
        step = _check_irf_step(irf_bin_width_ps, irf, irf_fwhm, file_irf, bw_ps)
    irf_a, irf_src = _resolve_irf(
        irf, irf_fwhm, irf_variable, file_irf, counts, n_bins, sparse=sparse
    )
    if irf_bin_width_ps is not None:
        irf_a, resampled = _irf_step_on_bins(irf_a, irf_src, step, float(bw_ps))
    irf_src = resampled or irf_src
    if not (from_save and irf_src == "file"):  # a saved Cube's IRF fits already: exact
        irf_a = _crop_irf(irf_a, n_bins)
        if not irf_src.startswith("estimated"):
            check_irf_width(irf_a, irf_src, counts, n_bins, bw_ps, sparse)
    if irf_src != "file":
        meta["irf_source"] = irf_src
    elif not from_save:
        meta.setdefault("irf_source", "file")
    grouping_hint(irf_a, n_bins, meta)  # a wide IRF in bins: a coarser binning (warns only)
    return irf_a


def _check_irf_step(irf_bin_width_ps, irf, irf_fwhm, file_irf, bw_ps) -> float:
    """``irf_bin_width_ps`` checked: positive, a supplied IRF to apply to, a known bin
    width of the cube."""
    step = check_positive(irf_bin_width_ps, "irf_bin_width_ps")
    if (
        irf_fwhm is not None
        or (isinstance(irf, str) and irf in ("estimate", "estimate-shape"))
        or (irf is None and file_irf is None)
    ):
        raise SplidarError(
            "`irf_bin_width_ps` is the sample step of a supplied IRF (irf= array or file, "
            "or the file's own); it does not apply to irf_fwhm= or an estimated IRF."
        )
    if bw_ps is None:
        raise SplidarError(
            "`irf_bin_width_ps` needs the cube's bin width to resample the IRF onto, and "
            "the file does not give it: pass bin_width_ps= too."
        )
    return step


def _irf_step_on_bins(irf_a, src: str, step_ps: float, bw_ps: float):
    """``irf_a`` (L, n) sampled every ``step_ps`` on bins of ``bw_ps`` ps, and a note for
    ``metadata["irf_source"]`` (None when the steps agree within 0.1 %)."""
    if math.isclose(step_ps, bw_ps, rel_tol=1e-3):
        return irf_a, None
    out = resample_irf(irf_a, step_ps, bw_ps)
    log.info(
        "IRF (%s) resampled from %g ps samples to the cube's %g ps bins: %d -> %d samples",
        src, step_ps, bw_ps, irf_a.shape[1], out.shape[1],
    )  # fmt: skip
    return out, f"{src} (resampled from {step_ps:g} ps to {bw_ps:g} ps bins, irf_bin_width_ps)"


def _check_cube_options(bin_width, time_unit) -> None:
    if bin_width is not None or time_unit != "bin":
        raise SplidarError(
            "`bin_width` and `time_unit` apply to photon-list files; this file holds an "
            "already binned cube (use bin_width_ps= to set its bin width)."
        )


def _axis(ax, what: str, v, name: str, p: Path) -> int:
    a = check_int(ax, what, minimum=-v.ndim)
    if a >= v.ndim:
        raise SplidarError(
            f"`{what}` must be an axis of variable '{name}' of '{p.name}', shape {v.shape}: "
            f"-{v.ndim} to {v.ndim - 1}; got {ax}."
        )
    return a % v.ndim


def _time_last(v, name: str, p: Path, time_axis: int | None, wavelength_axis=None):
    """Move the time axis of a stored count array last (``time_axis``) and, for a 4-D
    array, its wavelength axis before it (``wavelength_axis``); by default keep the
    order, warning when the shape suggests ``(T, rows, cols)`` or ``(L, rows, cols, T)``
    (a first axis of at most 16 and more than 16 "wavelengths")."""
    s = v.shape
    if time_axis is None:
        if v.ndim == 3 and s[0] > 2 * max(s[1], s[2]) and s[2] <= s[1]:
            log.warning(
                "variable '%s' of '%s' has shape %s, read as (rows, cols, T) = %d x %d pixels "
                "of %d bins. If its first axis holds the time bins, pass time_axis=0; "
                "time_axis=-1 confirms the time axis is last.",
                name, p.name, s, *s,
            )  # fmt: skip
        t = v.ndim - 1
    else:
        t = _axis(time_axis, "time_axis", v, name, p)
    if wavelength_axis is not None and v.ndim != 4:
        raise SplidarError(
            f"`wavelength_axis` applies to a 4-D count array; variable '{name}' of '{p.name}' "
            f"has shape {s} (one wavelength: leave it out)."
        )
    if v.ndim == 4 and wavelength_axis is None:
        rest = [a for a in range(4) if a != t]
        if s[rest[0]] <= 16 < s[rest[2]]:  # more than 16 wavelengths: rarely so
            log.warning(
                "variable '%s' of '%s' has shape %s, read as %d x %d pixels of %d "
                "wavelengths. If axis %d holds the wavelengths, pass wavelength_axis=%d; "
                "wavelength_axis=%d confirms the order.",
                name, p.name, s, s[rest[0]], s[rest[1]], s[rest[2]], rest[0], rest[0],
                rest[2],
            )  # fmt: skip
    if v.ndim == 4 and wavelength_axis is not None:
        w = _axis(wavelength_axis, "wavelength_axis", v, name, p)
        if w == t:
            raise SplidarError(
                f"`wavelength_axis` and `time_axis` name the same axis ({w}) of variable "
                f"'{name}' of '{p.name}', shape {s}."
            )
        order = [a for a in range(4) if a not in (w, t)] + [w, t]
        if order != [0, 1, 2, 3]:
            log.info("variable '%s' of '%s': axes %s read as (rows, cols, L, T)", name,
                     p.name, tuple(order))  # fmt: skip
        return np.transpose(v, order)
    if t != v.ndim - 1:
        log.info("variable '%s' of '%s': time axis %d moved last", name, p.name, t)
    return np.moveaxis(v, t, -1)


#: variables that describe the counts; in an HDF5 file, looked up beside them in their group
_SIBLINGS = ("irf", "bin_width_ps", "wavelengths_nm", "library", "class_names", "metadata")


def _group_siblings(d: dict[str, Any], p: Path, name: str) -> dict[str, Any]:
    """``d`` with the ``irf``, ``bin_width_ps``, ... of the counts' own HDF5 group (e.g.
    ``scan/irf`` beside ``scan/histograms``, or an attribute of that group) or attributes
    of the counts' dataset (``scan/histograms/bin_width_ps``, read by ``_read_hdf5``) as
    top-level names, where those are absent; the dataset's own attributes first."""
    group = name.rpartition("/")[0]
    found, where = {}, {}
    for k in _SIBLINGS:
        for key, place in ((f"{name}/{k}", f"attribute of '{name}'"), (f"{group}/{k}", group)):
            if k not in d and k not in found and key in d:
                found[k], where[k] = d[key], place
    if not found:
        return d
    log.info("'%s': using %s", p.name, ", ".join(f"{k} ({where[k]})" for k in found))
    return {**d, **found}


def _photon_table(d: dict[str, Any], p: Path, time_unit: str, flat: bool, variable):
    """A photon table (one photon per line: row, col, time[, wavelength] columns) as flat
    photon lists: (d, time unit, wavelengths folded into the columns, flat)."""
    table = None if flat or variable is not None or "counts" in d else find_photon_table(d)
    if table is None:
        return d, time_unit, 1, flat
    d, time_unit, n_wl = table_as_flat(d, p, table, time_unit)
    return d, time_unit, n_wl, True


def _binned_cube(d: dict[str, Any], p: Path, name: str, window, meta: dict, axes=(None, None)):
    """The count cube ``(rows, cols, L, T)`` of variable ``name`` (``axes``: its time
    and wavelength axes, see :func:`_time_last`), cropped to ``window`` (a bin range),
    with its metadata; ``from_save`` when :func:`save` wrote the file."""
    v = d[name]
    if not (isinstance(v, np.ndarray) and v.dtype.kind in "uifb"):
        raise SplidarError(
            f"variable '{name}' of '{p.name}' is neither a count cube nor a cell array of "
            f"photon times (got {describe(v)}); the file holds: {_summary(d)}."
        )
    if v.ndim not in (3, 4):
        raise SplidarError(
            f"variable '{name}' of '{p.name}' must be a count cube (rows, cols, T) or "
            f"(rows, cols, L, T); got shape {v.shape}."
        )
    v = _time_last(v, name, p, *axes)
    counts = v if v.ndim == 4 else v[:, :, None, :]
    md0 = _metadata_from(d.get("metadata"))
    from_save = str(np.asarray(d.get("__kind__", ""))) == "Cube"
    # written by `save`: restore its metadata exactly
    meta = md0 if from_save else {**md0, **meta}
    if window is not None:
        start, stop, _ = _check_window(window, 1)
        if not (float(start).is_integer() and float(stop).is_integer()):
            raise SplidarError(f"`window` on a histogram file is a bin range; got {window}.")
        counts = counts[..., int(start) : int(stop)]
        meta["window"] = [int(start), int(stop)]
        if counts.shape[-1] == 0:
            raise SplidarError(f"`window` {window} selects no bins of T = {v.shape[-1]}.")
    try:  # before any IRF work: a bad cube gets its one message, not IRF warnings first
        counts = as_counts(counts, name)
    except SplidarError as exc:
        raise SplidarError(f"'{p.name}': {exc}") from None
    return counts, meta, from_save


def _check_bin_width_unit(bin_width_ps) -> None:
    """Warn about a bin width no TCSPC system has: most likely given in another unit."""
    if bin_width_ps is None or not np.isfinite(bw := float(bin_width_ps)) or bw <= 0:
        return
    if bw < 0.5:
        log.warning(
            "bin width %g ps is below any TCSPC resolution (1 ps and up): if it is in "
            "nanoseconds, pass bin_width_ps=%g (picoseconds)",
            bw, bw * 1e3,
        )  # fmt: skip
    elif bw > 1e6:
        log.warning(
            "bin width %g ps is %g us (%.0f m of range per bin): if it is in femtoseconds, "
            "pass bin_width_ps=%g (picoseconds)",
            bw, bw * 1e-6, bw * 1e-12 * 299_792_458.0 / 2, bw * 1e-3,
        )  # fmt: skip


def _override(cube: Cube, bin_width_ps, wavelengths_nm, library) -> Cube:
    _check_bin_width_unit(cube.bin_width_ps if bin_width_ps is None else bin_width_ps)
    if bin_width_ps is None and wavelengths_nm is None and library is None:
        return cube
    return Cube(
        cube.counts,
        irf=cube.irf,
        bin_width_ps=cube.bin_width_ps if bin_width_ps is None else bin_width_ps,
        wavelengths_nm=cube.wavelengths_nm if wavelengths_nm is None else wavelengths_nm,
        library=cube.library if library is None else library,
        metadata=cube.metadata,
    )


#: a photon-list file without pickle: flat arrival times, their flat pixel index, image size
_FLAT_LIST_KEYS = frozenset(("times", "pixel_index", "shape"))


def _flat_photon_lists(d: dict[str, Any], p: Path) -> PhotonLists:
    """Photon lists stored flat (``times``, ``pixel_index``, ``shape``): no object arrays."""
    t, pix, shape = (np.asarray(d[k]) for k in ("times", "pixel_index", "shape"))
    if shape.shape != (2,) or shape.dtype.kind not in "ui" or np.any(shape < 1):
        raise SplidarError(
            f"`shape` in '{p.name}' must be two positive integers (rows, cols); got "
            f"{describe(shape)}."
        )
    if t.ndim != 1 or pix.ndim != 1 or t.size != pix.size:
        raise SplidarError(
            f"`times` and `pixel_index` in '{p.name}' must be 1-D of the same length; got "
            f"shapes {t.shape} and {pix.shape}."
        )
    rows, cols = (int(x) for x in shape)
    if pix.size and (pix.dtype.kind not in "ui" or pix.min() < 0 or pix.max() >= rows * cols):
        raise SplidarError(
            f"`pixel_index` in '{p.name}' must be integers in [0, {rows * cols}) for shape "
            f"({rows}, {cols}); got {describe(pix)}."
        )
    return PhotonLists(times=t, pixel_index=pix.astype(np.int64), shape=(rows, cols),
                       source=f"{p.name}:times")  # fmt: skip


def _check_times(pl: PhotonLists) -> None:
    t = pl.times
    if t.size and t.dtype.kind not in "uif":
        raise SplidarError(f"photon arrival times must be numbers; got dtype {t.dtype}.")
    if t.dtype.kind == "f" and not np.all(np.isfinite(t)):
        n = int(np.count_nonzero(~np.isfinite(t)))
        raise SplidarError(
            f"the photon lists ({pl.source}) hold {n} NaN or infinite arrival time(s); remove "
            "them (a photon without a time cannot be binned)."
        )


def _bin_lists(pl: PhotonLists, window, bin_width, time_unit, n_wl: int = 1, irf_fwhm=None):
    """Bin photon lists: (counts, metadata, sparse voxels). ``n_wl`` > 1: a photon table's
    wavelengths folded into the columns (``cols x n_wl``), unfolded here. A cube that
    does not fit is refused naming a bin width that does and suits the pulse
    (:func:`_bin_hints.memory_hint`; ``irf_fwhm``: ``load``'s, bins)."""
    bw = 1.0 if bin_width is None else check_positive(bin_width, "bin_width")
    _check_times(pl)
    if pl.n_photons == 0 and window is None:
        raise SplidarError(
            f"the photon lists ({pl.source}) hold no photon: every cell is empty. Check the "
            "file and variable (pass window= to build an empty cube on purpose)."
        )
    if window is None:
        window = _default_window(pl.times, bw)
        log.info(
            "no window given: binning %s from the earliest to the latest photon, [%g, %g) in "
            "%s units",
            pl.source,
            window[0],
            window[1],
            time_unit,
        )
    start, stop, bw = _check_window(window, bw)
    uniq, cnt, rows, cols, n_bins = _bin_sparse(
        pl.times, pl.pixel_index, pl.shape, (start, stop), bw, irf_fwhm
    )
    if pl.n_photons and not cnt.size:
        raise SplidarError(
            f"none of the {pl.n_photons} photons falls in the window [{start:g}, {stop:g}) "
            f"{time_unit}; their arrival times range from {pl.times.min():g} to "
            f"{pl.times.max():g}. Pass a window (and time unit) that covers them."
        )
    nbytes = rows * cols * n_bins * 2
    try:
        check_memory(
            nbytes,
            f"binning {pl.source} into {rows} x {cols} x {n_bins} bins",
            "pass a larger bin width, a narrower window or crop the photon lists",
        )
    except SplidarError as exc:
        hint = memory_hint(
            pl.times, pl.pixel_index, (start, stop), bw, nbytes, irf_fwhm, available_bytes()
        )
        raise SplidarError(f"{exc.args[0].rstrip('.')}{hint}.") from None
    counts = _dense(uniq, cnt, rows, cols, n_bins)
    factor = TIME_UNITS_PS[time_unit]
    md = {
        "photon_lists": pl.source,
        "window": [start, stop],
        "bin_width": bw,
        "time_unit": time_unit,
        "n_photons_total": pl.n_photons,
        "n_photons_in_window": int(cnt.sum(dtype=np.int64)),
    }
    if factor is not None:
        md["bin_width_ps"] = bw * factor
    if n_wl > 1:  # the voxels' flat index is of the folded layout: no sparse form
        return counts.reshape(rows, -1, n_wl, n_bins), md, None
    return counts, md, (uniq, cnt)


def save(cube: Cube, path: str | os.PathLike, *, chunks: tuple[int, int] | None = None) -> None:
    """Write a cube to ``.npz`` (exact round trip with :func:`load`) or ``.zarr``.

    ``.npz`` stores ``counts`` (dtype kept), ``irf``, ``bin_width_ps``,
    ``wavelengths_nm``, ``library`` + ``class_names`` and ``metadata`` as a JSON string
    (values JSON cannot hold are written with ``str``). ``.zarr`` writes a directory
    with ``counts`` chunked over pixels (all of L and T in each chunk) and the rest as
    small arrays and attributes; a lazy (Dask) cube is written chunk by chunk.

    Parameters
    ----------
    cube : Cube
    path : str or path-like
        Ends in ``.npz`` or ``.zarr``.
    chunks : (rows, cols), optional
        Zarr only: pixel block per chunk (default 64 x 64).

    Raises
    ------
    SplidarError
        Not a Cube, unknown extension, or zarr not installed.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar import Cube
    >>> c = Cube(np.ones((2, 2, 8), np.uint16), irf=[1.0, 2.0, 1.0], bin_width_ps=4.0)
    >>> save(c, "cube.npz")  # doctest: +SKIP
    >>> load("cube.npz").bin_width_ps  # doctest: +SKIP
    4.0
    """
    if not isinstance(cube, Cube):
        raise SplidarError(f"`cube` must be a splidar.Cube; got {describe(cube)}.")
    if not isinstance(path, (str, os.PathLike)):
        raise SplidarError(f"`path` must be a file path; got {describe(path)}.")
    p = Path(path)
    ext = _ext(p)
    meta = json.dumps(dict(cube.metadata), default=str)
    if ext == ".zarr":
        _save_zarr(cube, p, chunks, meta)
        return
    if ext != ".npz":
        raise SplidarError(f"`save` writes .npz or .zarr; got '{p.suffix}' in '{p}'.")
    counts = cube.counts
    if cube.is_lazy:
        counts = counts.compute()
    arrays: dict[str, Any] = {
        "counts": counts,
        "irf": cube.irf,
        "metadata": np.array(meta),
        "__kind__": np.array("Cube"),
    }
    if cube.bin_width_ps is not None:
        arrays["bin_width_ps"] = np.array(cube.bin_width_ps)
    if cube.wavelengths_nm is not None:
        arrays["wavelengths_nm"] = cube.wavelengths_nm
    if cube.library is not None:
        arrays["library"] = cube.library.signatures
        arrays["class_names"] = np.array(cube.library.class_names, dtype=str)
    savez(p, arrays)  # atomic, and the same cube gives the same bytes


# --------------------------------------------------------------------------------------
# zarr
# --------------------------------------------------------------------------------------
def _zarr():
    try:
        import zarr
    except ImportError:  # pragma: no cover - depends on the environment
        raise SplidarError(
            "reading or writing .zarr needs the optional packages zarr and dask: "
            "pip install 'splidar[dask]'."
        ) from None
    return zarr


def _save_zarr(cube: Cube, p: Path, chunks, meta: str) -> None:
    zarr = _zarr()
    r, c = (64, 64) if chunks is None else (check_int(x, "chunks", minimum=1) for x in chunks)
    rows, cols, n_l, n_bins = cube.shape
    ch = (min(r, rows), min(c, cols), n_l, n_bins)
    g = zarr.open_group(str(p), mode="w")
    dtype = np.dtype(cube.counts.dtype)
    arr = g.create_array("counts", shape=cube.shape, chunks=ch, dtype=dtype)
    if cube.is_lazy:
        import dask.array as da

        da.store(cube.counts.rechunk(ch), arr, lock=False)
    else:
        arr[...] = cube.counts
    g.create_array("irf", data=cube.irf)
    if cube.wavelengths_nm is not None:
        g.create_array("wavelengths_nm", data=cube.wavelengths_nm)
    if cube.library is not None:
        g.create_array("library", data=cube.library.signatures)
        g.attrs["class_names"] = list(cube.library.class_names)
    if cube.bin_width_ps is not None:
        g.attrs["bin_width_ps"] = float(cube.bin_width_ps)
    g.attrs["metadata"] = meta
    g.attrs["kind"] = "Cube"


def _open_zarr(p: Path, zarr):
    """A zarr group, or a bare zarr array as a group-like ``{"counts": array}``."""
    try:
        return zarr.open_group(str(p), mode="r")
    except Exception as exc:
        try:
            arr = zarr.open_array(str(p), mode="r")
        except Exception:
            raise SplidarError(f"cannot open '{p}' as a zarr group: {exc}") from None
    log.info("'%s' is a single zarr array: read as the counts", p.name)
    return _BareZarr(arr)


class _BareZarr(dict):
    """A bare zarr array seen as a group holding only ``counts``, without attributes."""

    def __init__(self, arr):
        super().__init__(counts=arr)
        self.attrs: dict = {}

    def array_keys(self):
        return self.keys()


def _load_zarr(p: Path, *, irf_opts, bin_width_ps, variable=None, time_axis=None) -> Cube:
    zarr = _zarr()
    import dask.array as da

    g = _open_zarr(p, zarr)
    names = sorted(g.array_keys())
    name = "counts" if variable is None or isinstance(g, _BareZarr) else variable
    if name not in names:
        hint = "; pass the one holding the counts as variable=" if names else ""
        raise SplidarError(
            f"the zarr group '{p}' has no `{name}` array; it holds arrays {names}{hint}."
        )
    counts = da.from_zarr(g[name])
    if isinstance(time_axis, tuple):
        raise SplidarError(
            f"`wavelength_axis` is not supported for Zarr input ('{p.name}'): rewrite the "
            "array as (rows, cols, L, T) (splidar.save(cube, 'x.zarr'))."
        )
    if time_axis is not None and int(time_axis) % max(counts.ndim, 1) != counts.ndim - 1:
        raise SplidarError(
            f"`time_axis` {time_axis} is not supported for Zarr input ('{p.name}', shape "
            f"{counts.shape}): the time axis must be last, each chunk holding whole "
            "histograms. Rewrite the array time-last (splidar.save(cube, 'x.zarr'))."
        )
    if counts.ndim == 3:
        counts = counts[:, :, None, :]
    if counts.ndim != 4:
        raise SplidarError(
            f"`counts` in '{p}' must be (rows, cols[, L], T); got shape {counts.shape}."
        )
    file_irf = np.asarray(g["irf"][...]) if "irf" in names else g.attrs.get("irf")
    bw = g.attrs.get("bin_width_ps") if bin_width_ps is None else bin_width_ps
    meta = _metadata_from(g.attrs.get("metadata"))
    if g.attrs.get("kind") != "Cube":  # not written by `save`: record where it came from
        meta.setdefault("source", str(p))
    from_save = g.attrs.get("kind") == "Cube"
    irf_a = _cube_irf(irf_opts, file_irf, counts, bw, None, from_save, meta)
    lib = None
    if "library" in names:
        lib = SpectralLibrary(
            np.asarray(g["library"][...]), class_names=tuple(g.attrs.get("class_names", ()))
        )
    return Cube(
        counts,
        irf=irf_a,
        bin_width_ps=g.attrs.get("bin_width_ps"),
        wavelengths_nm=np.asarray(g["wavelengths_nm"][...]) if "wavelengths_nm" in names else None,
        library=lib,
        metadata=meta,
    )


# --------------------------------------------------------------------------------------
# libraries
# --------------------------------------------------------------------------------------
