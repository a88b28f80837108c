"""Hints on the bin width from the pulse's width: a hint, never a change.

Detection's time and memory grow with the number of bins T (the multiscale statistics,
the matched filter, the candidates' windows, which span the IRF's support). An IRF whose
FWHM spans many bins buys no better depths (a return's depth is read to a fraction of
a bin from the samples around its peak) and costs in proportion: the face file at its
native bins (FWHM 15 bins, T = 7,001) took 96 s and 10.7 GB, grouped by 4 (FWHM 3.75
bins) a tenth of the time with the same surfaces within 2 % (benchmarks/README.md,
"Lead, session 22"). Two places say so:

* :func:`grouping_hint`: ``load``, once the IRF is known (supplied or estimated), warns
  when its FWHM spans more than ``HINT_ABOVE`` bins and names the grouping that keeps
  at least ``FWHM_BINS`` bins per FWHM (photon lists: ``bin_width=``).
* :func:`memory_hint`: the binning of photon lists that the memory guard refuses names a
  bin width that fits and, where the pulse's width is known (``irf_fwhm`` given) or
  measured on the photons themselves (their pair time differences, binned sparsely at
  the width memory allows: no dense cube), one that also keeps the FWHM at about
  ``FWHM_BINS`` bins or more.

Nothing here changes a result: the messages name options the user may pass.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ._irf_width import pair_lag_fwhm
from ._validation import SplidarError
from .irf import irf_fwhm

__all__ = ["FWHM_BINS", "HINT_ABOVE", "grouping_hint", "memory_hint"]

#: the logger of :mod:`splidar.io`, whose ``load`` gives these hints
log = logging.getLogger("splidar.io")

#: bins per FWHM a suggested bin width keeps at least: the face file grouped to 3.75
#: bins per FWHM gave the surfaces of 15 within 2 %, and the simulated benchmarks run at
#: Gaussian FWHMs of 2-4 bins (benchmarks/README.md, "Lead, session 22")
FWHM_BINS = 4.0
#: ``load`` hints at grouping when the IRF's FWHM spans more bins than this: grouping by
#: ``k = floor(FWHM / FWHM_BINS) >= 2`` then leaves at least 5 bins per FWHM. The 21 km
#: file at real_data.py's 128 ps (its estimated FWHM under 10 bins) is quiet; the tower at
#: 64 ps (10.5 bins) is told 128 ps (its 100 ps: surfaces within 0.2 %, detection 1.4x
#: faster; benchmarks/README.md, "lay31, session 23")
HINT_ABOVE = 10.0
#: bytes the memory guard's suggested bin width keeps the binned cube under
_TARGET_BYTES = 2**30
#: voxel pairs the photons' pulse width reads at most (as the IRF width check's)
_PAIRS = 2_000_000
#: bins per FWHM from which the photons' pulse width is taken at a trial bin width
#: (below it, coarser trials: the width may be a quantisation comb, :func:`_pulse_width`)
_RESOLVED = 2.0
#: relative difference within which two trial widths' readings of the pulse agree
_AGREE = 0.15
#: fewest bins a trial binning keeps (the pair-lag width reads lags up to T / 2)
_MIN_BINS = 64


def _round_125(x: float, up: bool) -> float:
    """The 1, 2 or 5 x 10^k at or above (``up``) / at or below ``x`` (> 0)."""
    e = math.floor(math.log10(x))
    steps = [m * 10.0**k for k in (e - 1, e, e + 1) for m in (1, 2, 5)]
    if up:
        return next(s for s in steps if s >= x * (1 - 1e-12))
    return [s for s in steps if s <= x * (1 + 1e-12)][-1]


def _fwhm_bins(irf) -> float | None:
    """The IRF's FWHM in bins (the widest wavelength), None where it cannot be read."""
    try:
        return float(np.max(irf_fwhm(np.atleast_2d(np.asarray(irf, dtype=np.float64)))))
    except (SplidarError, ValueError):
        return None


def grouping_hint(irf, n_bins: int, meta: dict) -> str | None:
    """The warning ``load`` gives when the IRF's FWHM spans more than ``HINT_ABOVE`` bins
    (None otherwise): the grouping ``k = floor(FWHM / FWHM_BINS)`` that keeps at least
    ``FWHM_BINS`` bins per FWHM, how to ask for it (photon lists: ``bin_width=``; a
    histogram file: summing ``k`` adjacent bins and resampling the IRF), the T it gives
    and the expected gain (detection's memory and time grow with T: about ``k`` times
    less). Logged here as a warning; returns the message.

    Parameters
    ----------
    irf : ndarray, shape (L, n)
        The cube's IRF on its bins.
    n_bins : int
        T, the cube's bins.
    meta : dict
        The cube's metadata as ``load`` built it (``photon_lists``, ``bin_width``,
        ``time_unit``, ``irf_source``).
    """
    fw = _fwhm_bins(irf)
    if fw is None or fw <= HINT_ABOVE:
        return None
    k = int(fw // FWHM_BINS)
    src = meta.get("irf_source", "file")
    if "photon_lists" in meta:
        bw, unit = float(meta.get("bin_width", 1.0)), meta.get("time_unit", "bin")
        unit = "" if unit == "bin" else f"{unit}, "
        how = f"pass bin_width={k * bw:g} ({unit}{k} of the current bins)"
    else:
        how = (
            f"sum every {k} adjacent bins (counts[..., :T // {k} * {k}].reshape(..., -1, "
            f"{k}).sum(-1), the IRF by splidar.irf.resample_irf(irf, 1, {k}))"
        )
    msg = (
        f"the IRF's FWHM spans {fw:.1f} bins (IRF: {src}): detection needs about "
        f"{FWHM_BINS:g} bins per FWHM and its memory and time grow with the bins; {how} "
        f"for T = {math.ceil(n_bins / k)} instead of {n_bins} bins (FWHM {fw / k:.1f} bins), "
        f"about {k}x less memory and time. A hint only: nothing is changed"
    )
    log.warning(msg)
    return msg


def _photon_fwhm(t, pix, start: float, stop: float, width: float) -> float | None:
    """The pulse's FWHM in the data's time unit from the photons' pair time differences
    within a pixel (:func:`splidar._irf_width.pair_lag_fwhm`), on bins of ``width``
    built sparsely (no dense cube); None where no pulse stands out or its width is not
    determined (the half-maximum bracket's half-length above the width)."""
    n = max(math.ceil((stop - start) / width - 1e-12), 1)
    b = np.floor((np.asarray(t, dtype=np.float64) - start) / width).astype(np.int64)
    keep = (b >= 0) & (b < n)
    key = np.asarray(pix, dtype=np.int64)[keep] * n + b[keep]
    uniq, cnt = np.unique(key, return_counts=True)
    bounds: list = []
    try:
        fw = pair_lag_fwhm(uniq // n, uniq % n, cnt, n, None, bounds, budget=_PAIRS)
    except SplidarError:
        return None
    if not bounds or (bounds[1] - bounds[0]) / 2 > fw:
        return None
    return fw * width


def _pulse_width(t, pix, start: float, stop: float, width: float):
    """(FWHM in the data's unit, the width it was read at) or None: read at ``width``,
    2, 5, 10, ... x (while ``_MIN_BINS`` bins remain) until two resolved readings (at
    least ``_RESOLVED`` bins per FWHM) in a row agree within ``_AGREE``; the coarser is
    taken. Time tags quantised near or above the trial width (the tower file's 24.4 ps
    steps) leave bins empty: at 10 ps lag 0 alone stood above half the peak (a "5 ps"
    pulse), at 20 ps it read 506, at 50 and 100 ps 628 and 636. Where no two agree, the
    coarsest resolved reading; where none is resolved, the first."""
    prev = first = None
    for m in (1, 2, 5, 10, 20, 50, 100):
        w = width * m
        if (stop - start) / w < _MIN_BINS:
            break
        fw = _photon_fwhm(t, pix, start, stop, w)
        if fw is None:
            continue
        if fw / w < _RESOLVED:  # coarser trials resolve it less
            if prev is not None:
                break
            first = first or (fw, w)
            continue
        if prev is not None and abs(fw / prev[0] - 1.0) <= _AGREE:
            return fw, w
        prev = (fw, w)
    return prev or first


def memory_hint(
    t, pix, window, bin_width: float, nbytes: int, irf_fwhm_bins=None, available=None
) -> str:
    """The memory guard's suggested ``bin_width`` for photon lists (appended to its
    message): the round width (1, 2 or 5 x 10^k) that brings the binned cube under
    1 GiB (or the ``available`` bytes, when fewer); where the pulse's FWHM is known
    (``irf_fwhm_bins`` x ``bin_width``) or measured on the photons
    (:func:`_pulse_width`), the coarser of that and the round width at most FWHM /
    ``FWHM_BINS`` (at least ``FWHM_BINS`` bins per FWHM: finer bins cost memory and
    time without better depths), and why.

    Parameters
    ----------
    t, pix : ndarray, shape (n,)
        Arrival times (data's unit) and flat pixel indices of the photons.
    window : (start, stop)
        The time range binned, data's unit.
    bin_width : float
        The width asked for, data's unit.
    nbytes : int
        The dense cube's size at that width, bytes.
    irf_fwhm_bins : float, optional
        ``load``'s ``irf_fwhm`` (bins of ``bin_width``), when given.
    available : int, optional
        The memory available, bytes (the memory guard's refusal).
    """
    start, stop = (float(w) for w in window)
    span = stop - start
    if not (np.isfinite(span) and span > 0):
        return ""
    target = _TARGET_BYTES if available is None else min(_TARGET_BYTES, max(available, 1))
    fit = _round_125(max(bin_width * nbytes / target, 1e-300), up=True)
    fw, how = None, ""
    if irf_fwhm_bins is not None:
        try:
            fw, how = float(irf_fwhm_bins) * bin_width, "`irf_fwhm`"
        except (TypeError, ValueError):
            fw = None
        if fw is not None and not (np.isfinite(fw) and fw > 0):
            fw = None
    if fw is None and np.size(t):
        got = _pulse_width(t, pix, start, stop, fit)
        if got is not None:
            fw, at = got
            how = f"from the photons' pair time differences binned at {at:g}"
    width = fit
    if fw is not None:
        width = max(fit, _round_125(fw / FWHM_BINS, up=False))
    n_bins = max(math.ceil(span / width - 1e-12), 1)
    mib = nbytes / max(math.ceil(span / bin_width - 1e-12), 1) * n_bins / 2**20
    text = f"; e.g. `bin_width` {width:g} gives T = {n_bins} bins ({mib:.0f} MiB)"
    if fw is None:
        return text + " (the pulse's width is not known: a width that fits in memory)"
    per = fw / width
    size = f"{fw:.0f}" if fw >= 10 else f"{fw:.3g}"
    text += f": the pulse's FWHM, about {size} ({how}), then spans {per:.2g} bins"
    if per < FWHM_BINS:
        return text + "; a narrower `window` allows finer bins"
    note = f" (irf_fwhm={per:.3g} in those bins)" if how == "`irf_fwhm`" else ""
    return (
        f"{text}{note}; detection needs about {FWHM_BINS:g}, finer bins cost memory and "
        "time, not depth accuracy"
    )
