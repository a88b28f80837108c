"""IRFs written as text by other groups' software: one column of samples, one column per
wavelength, or a time column beside the samples (``time_ps,counts`` with a header, or an
evenly spaced first column without one); and their resampling onto the cube's bins.

:func:`splidar.io.load_irf` reads text IRFs through :func:`read_irf_text`;
:func:`splidar.io.load` resamples an IRF file whose time column names its unit onto the
cube's bin width (:func:`irf_on_bins`).
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np

from ._photon_table import TIME_UNITS, _is_number, _role_and_unit
from ._validation import SplidarError

log = logging.getLogger("splidar.io")

#: picoseconds per unit of a time column's name
_PS = {"fs": 1e-3, "ps": 1.0, "ns": 1e3, "us": 1e6, "ms": 1e9, "s": 1e12}


def _header(p: Path, delim) -> list[str] | None:
    with open(p, encoding="utf-8", errors="replace") as fp:
        first = fp.readline().strip()
    parts = [x.strip().strip('"').strip("'") for x in first.split(delim)] if first else []
    if parts and not all(_is_number(x) for x in parts if x):
        return parts
    return None


def _time_column(a: np.ndarray, names: list[str] | None) -> tuple[int | None, str | None]:
    """Index of the time column of a 2-D text IRF (and its unit), or (None, None)."""
    if a.ndim != 2 or a.shape[1] < 2 or a.shape[0] < 3:
        return None, None
    if names is not None and len(names) == a.shape[1]:
        for i, n in enumerate(names):
            role, unit = _role_and_unit(n)
            if role == "time" or n.strip().lower() in ("bin", "bins", "sample", "index"):
                return i, unit
        return None, None
    step = np.diff(a[:, 0])  # no header: an evenly spaced first column is the time axis
    if step[0] > 0 and np.allclose(step, step[0], rtol=1e-3, atol=0):
        return 0, None
    return None, None


def read_irf_text(p: Path) -> tuple[np.ndarray, float | None, str | None]:
    """An IRF from a ``.csv`` / ``.txt`` file: (samples, time step, its unit).

    The samples are 1-D or ``(n, L)`` / ``(L, n)`` as written. A header row is
    skipped; a column whose header names a time (``time_ps``, ``t (ns)``, ``delay``,
    ``bin``: the names of photon tables' time columns) or, without a header, a first
    column evenly spaced and increasing is the time axis: dropped from the samples, its
    step returned with the unit its name carries (None when it names none).
    """
    ext = p.suffix.lower()
    delims = ("," if ext == ".csv" else None, None if ext == ".csv" else ",")
    last = None
    for delim in delims:
        names = _header(p, delim)
        try:
            a = np.loadtxt(p, delimiter=delim, ndmin=1, skiprows=1 if names else 0)
            break
        except ValueError as exc:
            last = exc
    else:
        raise SplidarError(
            f"cannot read the IRF '{p.name}' as numbers ({last}); write one sample per line, "
            "or columns of equal length with at most one header row (e.g. time_ps,counts)."
        ) from None
    col, unit = _time_column(a, names)
    if col is None:
        return a, None, None
    t = a[:, col]
    keep = [i for i in range(a.shape[1]) if i != col]
    values = a[:, keep[0]] if len(keep) == 1 else a[:, keep]
    step = float(np.median(np.diff(t)))
    name = names[col] if names else "the first column"
    log.info(
        "IRF '%s': '%s' read as its time axis (step %g%s), the samples from %s",
        p.name, name, step, f" {unit}" if unit else "",
        ", ".join(names[i] for i in keep) if names else f"column(s) {keep}",
    )  # fmt: skip
    return values, step, unit


def irf_on_bins(irf, bin_width_ps: float | None):
    """``irf`` (a path or anything else) and a note; a ``.csv``/``.txt`` path whose time
    column names its unit and whose step differs from ``bin_width_ps`` by more than
    0.1 % comes back as an array resampled onto the cube's bins (the IRF integrated over
    each bin: its cumulative sum interpolated at the bin edges; the peak sample centred
    in its bin, the end bins partial), with a note for ``metadata["irf_source"]``."""
    if not isinstance(irf, (str, os.PathLike)) or Path(irf).suffix.lower() not in (
        ".csv",
        ".txt",
    ):
        return irf, None
    p = Path(irf)
    if not p.is_file():
        return irf, None
    values, step, unit = read_irf_text(p)
    if step is None or unit is None or unit not in TIME_UNITS:
        if step is not None and unit is None and not math.isclose(step, 1.0):
            log.warning(
                "IRF '%s': its time column steps %g with no unit in its name: each sample "
                "is taken as one bin of the cube. Name the unit (e.g. time_ps) to have the "
                "IRF resampled to the cube's bin width.",
                p.name, step,
            )  # fmt: skip
        return irf, None
    step_ps = step * _PS[unit]
    if bin_width_ps is None:
        log.warning(
            "IRF '%s' is sampled every %g ps but the cube's bin width is unknown: each "
            "sample is taken as one bin. Give bin_width_ps= to resample it.",
            p.name, step_ps,
        )  # fmt: skip
        return irf, None
    if math.isclose(step_ps, float(bin_width_ps), rel_tol=1e-3):
        return irf, None
    a = np.asarray(values, dtype=np.float64)
    a = a[:, None] if a.ndim == 1 else a
    if a.shape[0] < a.shape[1]:
        a = a.T
    n = a.shape[0]
    out = resample_irf(a.T, step_ps, float(bin_width_ps))
    n_out = out.shape[1]
    log.warning(
        "IRF '%s' is sampled every %g ps, the cube's bins are %g ps: resampled to %d bins "
        "(%d samples before)",
        p.name, step_ps, bin_width_ps, n_out, n,
    )  # fmt: skip
    return out, f"file {p} (resampled from {step_ps:g} ps to {float(bin_width_ps):g} ps bins)"


def resample_irf(irf, step_ps: float, bin_width_ps: float) -> np.ndarray:
    """An IRF sampled every ``step_ps`` picoseconds, on bins of ``bin_width_ps``.

    Parameters
    ----------
    irf : ndarray, shape (L, n)
        One row per wavelength, ``n`` samples ``step_ps`` apart.
    step_ps, bin_width_ps : float
        The IRF's sample step and the cube's bin width, picoseconds (> 0).

    Returns
    -------
    ndarray, shape (L, m)
        The IRF integrated over each bin (its cumulative sum interpolated at the bin
        edges, ``m ~ n step_ps / bin_width_ps``); the bin edges placed so that the peak
        sample's centre (of the rows' sum) is a bin's centre: the depth reference (the
        IRF's maximum) stays where the pulse peaks; the end bins partial.
    """
    a = np.asarray(irf, dtype=np.float64).T  # (n, L)
    n = a.shape[0]
    ratio = float(bin_width_ps) / float(step_ps)  # samples per cube bin
    peak = int(np.argmax(a.sum(axis=1)))
    first = ((peak + 0.5) - ratio / 2) % ratio
    inner = first + ratio * np.arange(int(math.ceil((n - first) / ratio)))
    edges = np.unique(np.concatenate([[0.0], inner[(inner > 0) & (inner < n)], [float(n)]]))
    cum = np.vstack([np.zeros((1, a.shape[1])), np.cumsum(a, axis=0)])
    return np.diff(
        np.column_stack([np.interp(edges, np.arange(n + 1), cum[:, j]) for j in range(a.shape[1])]),
        axis=0,
    ).T
