"""Instrument response functions (IRFs): construction and conventions.

Conventions (see ALGORITHM-NOTES): an IRF is an array ``(L, n_irf)`` (or ``(n_irf,)``
for one wavelength), non-negative, normalised to sum 1 per wavelength. The *depth
reference* of a return is the bin where the IRF **peak** lands: for an IRF array, its
peak index is ``argmax`` along the last axis (:func:`irf_peak`). Padding an IRF with
zeros therefore never moves a depth.

Continuous models (:class:`GaussianIRF`, :class:`ExpTailIRF` for an asymmetric SPAD
response, :class:`SampledIRF` for a measured one) put their mode at ``t = 0``;
``model.sample()`` gives the array form (argmax = mode) and :func:`shifted_irf` renders
returns at fractional depths with true sub-bin shifts (used by :mod:`splidar.simulation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validation import SplidarError, check_int, check_ndim, check_positive, describe

__all__ = [
    "FWHM_TO_SIGMA",
    "ExpTailIRF",
    "GaussianIRF",
    "SampledIRF",
    "as_irf_models",
    "exp_tail_irf",
    "gaussian_irf",
    "irf_fwhm",
    "irf_peak",
    "normalise_irf",
    "resample_irf",
    "sample_irf_models",
    "shifted_irf",
    "shifted_irf_window",
]

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
    ((13,), 6, 1.0)
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

    Examples
    --------
    >>> g = normalise_irf([1.0, 2.0, 1.0], n_wavelengths=2)
    >>> g.shape, g[0].tolist()
    ((2, 3), [0.25, 0.5, 0.25])
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
    # idempotent: a row already summing to 1 (to rounding) is kept bit for bit, so that
    # Cube(counts, irf=cube.irf) holds exactly cube's IRF and gives exactly its results
    s = sums[:, None]
    return np.where(np.abs(s - 1.0) <= 1e-12, a, a / s)


def irf_peak(irf: np.ndarray) -> np.ndarray:
    """Index of each wavelength's IRF peak (the depth reference), shape ``(L,)`` int.

    Examples
    --------
    >>> irf_peak(np.array([[0.1, 0.6, 0.3], [0.2, 0.3, 0.5]])).tolist()
    [1, 2]
    """
    a = np.asarray(irf)
    if a.ndim == 1:
        a = a[None, :]
    return np.argmax(a, axis=-1).astype(np.intp)


# --------------------------------------------------------------------------------------
# Parametric and sampled IRF models (continuous, mode at t = 0) used by the simulator
# --------------------------------------------------------------------------------------


def _exgauss_pdf(u: np.ndarray, sigma: float, tau: float) -> np.ndarray:
    """Density of a N(0, sigma^2) convolved with a one-sided exponential of mean ``tau``.

    ``f(u) = (1/2tau) exp(sigma^2/2tau^2 - u/tau) erfc((sigma^2/tau - u)/(sqrt2 sigma))``,
    evaluated without overflow: for ``z >= 0`` with the scaled ``erfcx`` (which turns
    the product into ``exp(-u^2/2sigma^2) erfcx(z)``), for ``z < 0`` directly.
    """
    from scipy.special import erfc, erfcx

    u = np.asarray(u, dtype=np.float64)
    lam = 1.0 / tau
    z = (lam * sigma**2 - u) / (np.sqrt(2.0) * sigma)
    out = np.empty_like(z)
    pos = z >= 0
    out[pos] = 0.5 * lam * np.exp(-0.5 * (u[pos] / sigma) ** 2) * erfcx(z[pos])
    neg = ~pos
    out[neg] = 0.5 * lam * np.exp(0.5 * (lam * sigma) ** 2 - lam * u[neg]) * erfc(z[neg])
    return out


def _exgauss_mode(sigma: float, tau: float) -> float:
    """Position of the maximum of :func:`_exgauss_pdf` (it lies in ``[0, tau]``)."""
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(
        lambda x: -float(_exgauss_pdf(np.array([x]), sigma, tau)[0]),
        bounds=(-1e-9, tau + 1e-9),
        method="bounded",
        options={"xatol": 1e-12 * max(1.0, tau)},
    )
    return float(res.x)


def _sample_model(model, length: int | None) -> np.ndarray:
    """Point samples of ``model.evaluate`` on integers with the mode on sample ``index``."""
    left, right = model.support
    if length is None:
        index, length = left, left + right + 1
    else:
        length = check_int(length, "length", minimum=1)
        index = int(round((length - 1) * left / (left + right))) if left + right else 0
    t = np.arange(length, dtype=np.float64) - index
    g = model.evaluate(t)
    return g / g.sum()


@dataclass(frozen=True)
class GaussianIRF:
    """Gaussian IRF model, mode (= mean) at ``t = 0``.

    Parameters
    ----------
    fwhm : float
        Full width at half maximum, in time bins (> 0).

    Examples
    --------
    >>> m = GaussianIRF(3.0)
    >>> int(m.sample().argmax()) == m.support[0]
    True
    """

    fwhm: float

    def __post_init__(self):
        object.__setattr__(self, "fwhm", check_positive(self.fwhm, "fwhm"))

    @property
    def sigma(self) -> float:
        """Standard deviation in bins."""
        return self.fwhm * FWHM_TO_SIGMA

    @property
    def support(self) -> tuple[int, int]:
        """Bins ``(left, right)`` of the mode that hold all but ~1e-4 of the mass (+-4 sigma)."""
        half = max(1, int(np.ceil(4.0 * self.sigma)))
        return half, half

    def evaluate(self, t) -> np.ndarray:
        """Continuous density (integral 1) at times ``t`` (bins, mode at 0)."""
        t = np.asarray(t, dtype=np.float64)
        s = self.sigma
        return np.exp(-0.5 * (t / s) ** 2) / (s * np.sqrt(2.0 * np.pi))

    def sample(self, length: int | None = None) -> np.ndarray:
        """Sampled IRF ``(length,)`` summing to 1 with the mode on an integer sample.

        Same as :func:`gaussian_irf` for the default and for odd lengths.
        """
        return _sample_model(self, length)


@dataclass(frozen=True)
class ExpTailIRF:
    """Gaussian convolved with a one-sided exponential tail (ex-Gaussian), mode at ``t = 0``.

    A common model of a SPAD timing response: a fast Gaussian jitter followed by a slow
    diffusion tail. The model is shifted so that its **mode** (the depth reference of
    ALGORITHM-NOTES) sits at ``t = 0``; the mean lies ``tail - mode`` bins later.

    Parameters
    ----------
    fwhm : float
        FWHM of the Gaussian component, in bins (> 0). The FWHM of the whole IRF is
        larger; measure it with :func:`irf_fwhm`.
    tail : float
        Decay constant (mean) of the exponential tail, in bins (> 0).

    Examples
    --------
    >>> m = ExpTailIRF(3.0, 4.0)
    >>> g = m.sample()
    >>> int(g.argmax()) == m.support[0], bool(irf_fwhm(g) > 3.0)
    (True, True)
    """

    fwhm: float
    tail: float

    def __post_init__(self):
        object.__setattr__(self, "fwhm", check_positive(self.fwhm, "fwhm"))
        object.__setattr__(self, "tail", check_positive(self.tail, "tail"))
        object.__setattr__(self, "_mode", _exgauss_mode(self.sigma, self.tail))

    @property
    def sigma(self) -> float:
        """Standard deviation of the Gaussian component, bins."""
        return self.fwhm * FWHM_TO_SIGMA

    @property
    def mode_offset(self) -> float:
        """Distance from the Gaussian centre to the mode, bins (in ``[0, tail]``)."""
        return self._mode  # type: ignore[attr-defined]

    @property
    def support(self) -> tuple[int, int]:
        """Bins ``(left, right)`` of the mode holding all but ~1e-4 of the mass.

        Left: 4 sigma before the Gaussian centre; right: 4 sigma plus 10 tails after it.
        """
        m = self.mode_offset
        left = max(1, int(np.ceil(4.0 * self.sigma + m)))
        right = max(1, int(np.ceil(4.0 * self.sigma + 10.0 * self.tail - m)))
        return left, right

    def evaluate(self, t) -> np.ndarray:
        """Continuous density (integral 1) at times ``t`` (bins, mode at 0)."""
        return _exgauss_pdf(
            np.asarray(t, dtype=np.float64) + self.mode_offset, self.sigma, self.tail
        )

    def sample(self, length: int | None = None) -> np.ndarray:
        """Sampled IRF ``(length,)`` summing to 1, mode on an integer sample (its argmax)."""
        return _sample_model(self, length)


@dataclass(frozen=True, eq=False)
class SampledIRF:
    """A measured (sampled) IRF used as a continuous model by linear interpolation.

    The reference (``t = 0``) is the sample's argmax. Shifting by a fraction of a bin
    and re-sampling on integers keeps the sum exactly (linear interpolation of a
    zero-padded sequence), and an integer shift reproduces the samples exactly.

    Parameters
    ----------
    values : array_like, shape (n,)
        Non-negative samples with at least one positive value; normalised to sum 1.

    Examples
    --------
    >>> m = SampledIRF([0.0, 1.0, 3.0, 2.0, 1.0, 0.5])
    >>> m.support, round(float(m.evaluate([0.5])[0]), 6)
    ((2, 3), 0.333333)
    """

    values: np.ndarray

    def __post_init__(self):
        v = normalise_irf(self.values, name="irf")
        if v.shape[0] != 1:
            raise SplidarError(
                f"`SampledIRF` takes one wavelength, shape (n,); got shape {np.shape(self.values)}."
            )
        v = v[0]
        v.flags.writeable = False
        object.__setattr__(self, "values", v)

    @property
    def peak(self) -> int:
        """Index of the maximum sample (the depth reference)."""
        return int(np.argmax(self.values))

    @property
    def support(self) -> tuple[int, int]:
        """``(left, right)``: samples before and after the peak."""
        return self.peak, self.values.size - 1 - self.peak

    def evaluate(self, t) -> np.ndarray:
        """Linearly interpolated samples at times ``t`` (bins, peak at 0), 0 outside."""
        x = np.arange(self.values.size, dtype=np.float64) - self.peak
        return np.interp(np.asarray(t, dtype=np.float64), x, self.values, left=0.0, right=0.0)

    def sample(self, length: int | None = None) -> np.ndarray:
        """The samples (optionally cropped/padded to ``length`` around the peak)."""
        if length is None:
            return self.values.copy()
        return _sample_model(self, length)


IRFModel = GaussianIRF | ExpTailIRF | SampledIRF


def exp_tail_irf(fwhm: float, tail: float, *, length: int | None = None) -> np.ndarray:
    """Sampled asymmetric SPAD-like IRF: a Gaussian convolved with an exponential tail.

    Point samples of :class:`ExpTailIRF` on integer times, placed so that the **mode**
    of the continuous model falls exactly on a sample; that sample is the argmax, i.e.
    the depth reference (ALGORITHM-NOTES).

    Parameters
    ----------
    fwhm : float
        FWHM of the Gaussian component, bins (> 0).
    tail : float
        Decay constant of the exponential tail, bins (> 0).
    length : int, optional
        Number of samples. Default: 4 sigma before the Gaussian centre to 4 sigma + 10
        tails after it (:attr:`ExpTailIRF.support`). A given length keeps the same
        left/right proportion around the mode.

    Returns
    -------
    irf : ndarray, shape (length,), float64
        Non-negative, sums to 1.

    Raises
    ------
    SplidarError
        ``fwhm`` or ``tail`` not a finite positive number, ``length`` < 1.

    Examples
    --------
    >>> g = exp_tail_irf(3.0, 4.0)
    >>> round(float(g.sum()), 12), int(g.argmax()) == ExpTailIRF(3.0, 4.0).support[0]
    (1.0, True)
    """
    return ExpTailIRF(fwhm, tail).sample(length)


def irf_fwhm(irf) -> float | np.ndarray:
    """Full width at half maximum of a sampled IRF, in bins, per wavelength.

    The half-maximum crossings on each side of the peak (argmax) are located by linear
    interpolation between samples.

    Parameters
    ----------
    irf : array_like, shape (n,) or (L, n)
        Non-negative IRF (need not be normalised).

    Returns
    -------
    fwhm : float (1-D input) or ndarray (L,) (2-D input)

    Raises
    ------
    SplidarError
        Invalid IRF, or one that does not fall below half its maximum on both sides
        (pad it with zeros or take a longer window).

    Examples
    --------
    >>> round(float(irf_fwhm(gaussian_irf(4.0))), 2)
    4.0
    >>> irf_fwhm([[0, 1, 2, 1, 0], [0, 0, 1, 0, 0]]).tolist()
    [2.0, 1.0]
    """
    one = np.ndim(irf) == 1
    a = normalise_irf(irf)
    out = np.empty(a.shape[0])
    for k, g in enumerate(a):
        p = int(np.argmax(g))
        half = 0.5 * g[p]
        below_l = np.flatnonzero(g[:p] < half)
        below_r = np.flatnonzero(g[p + 1 :] < half)
        if below_l.size == 0 or below_r.size == 0:
            side = "left" if below_l.size == 0 else "right"
            raise SplidarError(
                f"`irf` row {k} does not fall below half its maximum on the {side} of its "
                "peak, so its FWHM cannot be measured; pad it with zeros or use a longer window."
            )
        i = int(below_l[-1])  # g[i] < half <= g[i + 1]
        xl = i + (half - g[i]) / (g[i + 1] - g[i])
        j = p + 1 + int(below_r[0])  # g[j - 1] >= half > g[j]
        xr = j - 1 + (g[j - 1] - half) / (g[j - 1] - g[j])
        out[k] = xr - xl
    return float(out[0]) if one else out


def resample_irf(irf, step_ps: float, bin_width_ps: float) -> np.ndarray:
    """An IRF recorded every ``step_ps`` picoseconds, on the cube's bins of ``bin_width_ps``.

    For an IRF array recorded at another step than the cube's bins (a 2 ps IRF for a
    cube of 16 ps bins): :class:`~splidar.Cube` reads an IRF one sample per bin. The
    same integration ``splidar.load(..., irf_bin_width_ps=)`` applies.

    Parameters
    ----------
    irf : array_like, shape (n,) or (L, n)
        Non-negative IRF, ``n`` samples ``step_ps`` apart (need not be normalised).
    step_ps, bin_width_ps : float
        The IRF's sample step and the cube's bin width, picoseconds (> 0).

    Returns
    -------
    ndarray, shape (m,) or (L, m)
        The IRF integrated over each bin (its cumulative sum interpolated at the bin
        edges, ``m ~ n step_ps / bin_width_ps``), normalised to sum 1 per row; the peak
        sample's centre is a bin's centre, so the depth reference (the maximum) stays
        where the pulse peaks.

    Raises
    ------
    SplidarError
        ``step_ps`` or ``bin_width_ps`` not a finite number > 0, or ``irf`` not a
        non-negative numeric array of one or two dimensions with a positive sum
        (:func:`normalise_irf`'s checks).

    Examples
    --------
    >>> g2 = gaussian_irf(24.0)  # a 3-bin pulse recorded 8 x finer
    >>> g = resample_irf(g2, 2.0, 16.0)
    >>> round(float(irf_fwhm(g)), 1), round(float(g.sum()), 12)
    (3.1, 1.0)
    """
    from ._irf_text import resample_irf as _resample

    step = check_positive(step_ps, "step_ps")
    bw = check_positive(bin_width_ps, "bin_width_ps")
    a = normalise_irf(irf)
    out = _resample(a, step, bw)
    out = out / out.sum(axis=1, keepdims=True)
    return out[0] if np.ndim(irf) == 1 else out


def as_irf_models(irf, *, n_wavelengths: int | None = None) -> tuple:
    """Turn an IRF specification into one continuous model per wavelength.

    Parameters
    ----------
    irf : model, tuple, number, array_like or sequence of these
        - a :class:`GaussianIRF`, :class:`ExpTailIRF` or :class:`SampledIRF`;
        - ``("gaussian", fwhm)`` or ``("exp_tail", fwhm, tail)``;
        - a number: a Gaussian of that FWHM (bins);
        - an array ``(n,)`` (every wavelength) or ``(L, n)``: sampled IRFs, peak = argmax;
        - a list with one of the above per wavelength (shapes may differ).

        A flat list of numbers is one sampled IRF, not one FWHM per wavelength: write
        ``[("gaussian", 2.0), ("gaussian", 3.0)]`` for that.
    n_wavelengths : int, optional
        L. A single specification is repeated L times.

    Returns
    -------
    models : tuple of length L (or of the given length when ``n_wavelengths`` is None)

    Raises
    ------
    SplidarError
        Unknown model name, wrong parameters, or a count of specifications that differs
        from ``n_wavelengths``.

    Examples
    --------
    >>> as_irf_models(("exp_tail", 3.0, 2.0), n_wavelengths=2)[1].tail
    2.0
    """

    def one(spec):
        if isinstance(spec, (GaussianIRF, ExpTailIRF, SampledIRF)):
            return spec
        if isinstance(spec, tuple) and spec and isinstance(spec[0], str):
            name, *par = spec
            if name == "gaussian" and len(par) == 1:
                return GaussianIRF(par[0])
            if name == "exp_tail" and len(par) == 2:
                return ExpTailIRF(par[0], par[1])
            raise SplidarError(
                f"`irf` specification {spec!r} is not understood; use ('gaussian', fwhm) or "
                "('exp_tail', fwhm, tail), with widths in bins."
            )
        if isinstance(spec, (int, float, np.integer, np.floating)) and not isinstance(spec, bool):
            return GaussianIRF(spec)
        return None

    m = one(irf)
    if m is not None:
        models: tuple = (m,)
    elif isinstance(irf, np.ndarray) or (
        isinstance(irf, (list, tuple)) and irf and all(np.isscalar(x) for x in irf)
    ):
        a = np.asarray(irf)
        if a.ndim == 2:
            models = tuple(SampledIRF(row) for row in a)
        else:
            models = (SampledIRF(a),)
    elif isinstance(irf, (list, tuple)) and irf:
        out = []
        for k, s in enumerate(irf):
            m = one(s)
            if m is None:
                try:
                    m = SampledIRF(s)
                except SplidarError as exc:
                    raise SplidarError(f"`irf[{k}]`: {exc}") from None
            out.append(m)
        models = tuple(out)
    else:
        raise SplidarError(
            f"`irf` must be an IRF model, ('gaussian', fwhm), ('exp_tail', fwhm, tail), a "
            f"FWHM number, an array (n,) or (L, n), or a list of these; got {describe(irf)}."
        )
    if n_wavelengths is not None:
        if len(models) == 1:
            models = models * n_wavelengths
        elif len(models) != n_wavelengths:
            raise SplidarError(
                f"`irf` gives {len(models)} IRFs but there are {n_wavelengths} wavelengths; "
                "pass one per wavelength or a single one for all."
            )
    return models


def sample_irf_models(models) -> np.ndarray:
    """Sample models into one ``(L, n)`` array (rows right-padded with zeros).

    Each row's argmax is its model's mode (the depth reference).

    Examples
    --------
    >>> g = sample_irf_models([GaussianIRF(2.0), GaussianIRF(4.0)])
    >>> g.shape[0], bool(g[0, g[0].argmax() + 1 :].sum() < g[1, g[1].argmax() + 1 :].sum())
    (2, True)
    """
    rows = [m.sample() for m in models]
    n = max(r.size for r in rows)
    out = np.zeros((len(rows), n))
    for k, r in enumerate(rows):
        out[k, : r.size] = r
    return out


def shifted_irf_window(model, depth) -> tuple[np.ndarray, np.ndarray]:
    """A return of IRF ``model`` whose peak lands at fractional bin ``depth``, on its support.

    The continuous model is evaluated at ``t - depth`` for the integer bins ``t`` with
    ``-left <= t - depth <= right`` (``model.support``) and normalised to sum 1 over
    them: a true sub-bin shift (no rounding), and at an integer depth exactly the
    sampled IRF (``model.sample()``) moved so its argmax lands on ``depth``.

    Parameters
    ----------
    model : GaussianIRF, ExpTailIRF or SampledIRF
    depth : array_like, shape (n,)
        Fractional bins of the return peaks.

    Returns
    -------
    t : ndarray, shape (n, W), int64
        Bins of each row (may fall outside any time window; ``W = left + right + 2``).
    values : ndarray, shape (n, W), float64
        Non-negative, each row sums to 1 (the sample that falls outside the support of
        the row is 0).

    Examples
    --------
    >>> t, v = shifted_irf_window(GaussianIRF(2.0), [10.0, 10.5])
    >>> int(t[0, v[0].argmax()]), v.sum(axis=1).round(12).tolist()
    (10, [1.0, 1.0])
    """
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    left, right = model.support
    W = left + right + 2
    base = np.floor(depth).astype(np.int64) - left
    t = base[:, None] + np.arange(W)
    u = t - depth[:, None]
    # exactly left + right + 1 samples with offsets in [-left, right]
    vals = np.where((u >= -left) & (u <= right), model.evaluate(u), 0.0)
    vals /= vals.sum(axis=1, keepdims=True)
    return t, vals


def shifted_irf(irf, depth, *, n_bins: int) -> np.ndarray:
    """Dense returns ``(n, L, n_bins)`` of unit intensity peaking at fractional ``depth``.

    Parameters
    ----------
    irf : IRF specification
        See :func:`as_irf_models`.
    depth : array_like, shape (n,)
        Fractional bins of the return peaks.
    n_bins : int
        T; the parts of a return outside ``[0, T)`` are cut (rows then sum to < 1).

    Returns
    -------
    returns : ndarray, shape (n, L, n_bins), float64

    Examples
    --------
    >>> g = shifted_irf(("exp_tail", 3.0, 2.0), [20.3], n_bins=60)
    >>> g.shape, int(g[0, 0].argmax()), round(float(g.sum()), 9)
    ((1, 1, 60), 20, 1.0)
    """
    T = check_int(n_bins, "n_bins", minimum=1)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    models = as_irf_models(irf)
    out = np.zeros((depth.size, len(models), T))
    for l, m in enumerate(models):
        t, v = shifted_irf_window(m, depth)
        ok = (t >= 0) & (t < T)
        rows = np.broadcast_to(np.arange(depth.size)[:, None], t.shape)
        np.add.at(out[:, l], (rows[ok], t[ok]), v[ok])
    return out
