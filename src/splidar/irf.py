"""Instrument response functions (IRFs): construction and conventions.

Conventions (see ALGORITHM-NOTES): an IRF is an array ``(L, n_irf)`` (or ``(n_irf,)``
for one wavelength), non-negative, normalised to sum 1 per wavelength. The *depth
reference* of a return is the bin where the IRF **peak** lands: for an IRF array, its
peak index is ``argmax`` along the last axis (:func:`irf_peak`). Padding an IRF with
zeros therefore never moves a depth.
"""

from __future__ import annotations

import numpy as np

from ._validation import SplidarError, check_int, check_ndim, check_positive, describe

__all__ = ["FWHM_TO_SIGMA", "gaussian_irf", "irf_peak", "normalise_irf"]

#: Factor from full width at half maximum to the standard deviation of a Gaussian.
FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def gaussian_irf(fwhm: float, *, length: int | None = None) -> np.ndarray:
    """Sampled Gaussian IRF with its peak on the centre sample.

    Parameters
    ----------
    fwhm : float
        Full width at half maximum, in time bins (> 0).
    length : int, optional
        Number of samples (odd lengths keep the peak exactly central). Default:
        the smallest odd length covering +-4 standard deviations, at least 3.

    Returns
    -------
    irf : ndarray, shape (length,), float64
        Non-negative, sums to 1, ``argmax == length // 2``.

    Examples
    --------
    >>> g = gaussian_irf(3.0)
    >>> g.shape, int(g.argmax()), round(float(g.sum()), 12)
    ((11,), 5, 1.0)
    """
    fwhm = check_positive(fwhm, "fwhm")
    sigma = fwhm * FWHM_TO_SIGMA
    if length is None:
        half = max(1, int(np.ceil(4.0 * sigma)))
        length = 2 * half + 1
    length = check_int(length, "length", minimum=1)
    centre = length // 2
    t = np.arange(length, dtype=np.float64) - centre
    g = np.exp(-0.5 * (t / sigma) ** 2)
    return g / g.sum()


def normalise_irf(irf, *, n_wavelengths: int | None = None, name: str = "irf") -> np.ndarray:
    """Validate an IRF and return a new ``(L, n_irf)`` float64 array summing to 1 per row.

    The caller's array is never modified.

    Parameters
    ----------
    irf : array_like, shape (n_irf,) or (L, n_irf)
        Non-negative, finite, with at least one positive value per wavelength.
    n_wavelengths : int, optional
        Expected L. A 1-D IRF is repeated for every wavelength.
    name : str
        Parameter name used in error messages.

    Raises
    ------
    SplidarError
        Wrong number of dimensions, NaN/inf, negative values, an all-zero row, or L
        different from ``n_wavelengths``.
    """
    try:
        a = np.array(irf, dtype=np.float64, copy=True)
    except (TypeError, ValueError):
        raise SplidarError(f"`{name}` must be a numeric array; got {describe(irf)}.") from None
    check_ndim(a, name, (1, 2), "(n_irf,) or (L, n_irf)")
    if a.ndim == 1:
        a = a[None, :]
    if a.shape[-1] == 0:
        raise SplidarError(f"`{name}` is empty; it needs at least one sample per wavelength.")
    if not np.all(np.isfinite(a)):
        raise SplidarError(f"`{name}` holds NaN or infinite values; an IRF must be finite.")
    if np.any(a < 0):
        raise SplidarError(
            f"`{name}` has {int(np.count_nonzero(a < 0))} negative value(s) (min {a.min():.3g}); "
            "an IRF must be non-negative. Subtract the baseline and clip it yourself if intended."
        )
    sums = a.sum(axis=-1)
    if np.any(sums <= 0):
        bad = np.flatnonzero(sums <= 0).tolist()
        raise SplidarError(
            f"`{name}` has no positive value for wavelength(s) {bad}; each IRF row needs a pulse."
        )
    if n_wavelengths is not None:
        if a.shape[0] == 1 and n_wavelengths > 1:
            a = np.repeat(a, n_wavelengths, axis=0)
        elif a.shape[0] != n_wavelengths:
            raise SplidarError(
                f"`{name}` has {a.shape[0]} wavelength(s) but the counts have {n_wavelengths}; "
                f"pass an IRF of shape ({n_wavelengths}, n_irf) or a single (n_irf,) IRF."
            )
    return a / sums[:, None]


def irf_peak(irf: np.ndarray) -> np.ndarray:
    """Index of each wavelength's IRF peak (the depth reference), shape ``(L,)`` int."""
    a = np.asarray(irf)
    if a.ndim == 1:
        a = a[None, :]
    return np.argmax(a, axis=-1).astype(np.intp)
