"""Tests of splidar.irf: sampled IRFs, continuous IRF models and FWHM measurement."""

from __future__ import annotations

import numpy as np
import pytest

from splidar import SplidarError
from splidar.irf import (
    FWHM_TO_SIGMA,
    ExpTailIRF,
    GaussianIRF,
    SampledIRF,
    as_irf_models,
    exp_tail_irf,
    gaussian_irf,
    irf_fwhm,
    irf_peak,
    normalise_irf,
    sample_irf_models,
    shifted_irf,
)


def test_gaussian_irf_peak_central_and_normalised():
    g = gaussian_irf(3.0)
    assert g.size % 2 == 1
    assert int(g.argmax()) == g.size // 2
    assert g.sum() == pytest.approx(1.0, abs=1e-12)
    # symmetric point samples of exp(-t^2 / 2 sigma^2)
    np.testing.assert_allclose(g, g[::-1], atol=1e-15)
    sigma = 3.0 * FWHM_TO_SIGMA
    assert g[g.size // 2 + 1] / g[g.size // 2] == pytest.approx(np.exp(-0.5 / sigma**2))


def test_gaussian_irf_model_matches_function():
    np.testing.assert_allclose(GaussianIRF(3.0).sample(), gaussian_irf(3.0), rtol=1e-12)
    np.testing.assert_allclose(GaussianIRF(2.5).sample(9), gaussian_irf(2.5, length=9), rtol=1e-12)


@pytest.mark.parametrize(("fwhm", "tail"), [(3.0, 4.0), (1.0, 0.5), (2.0, 20.0), (5.0, 0.05)])
def test_exp_tail_irf_mode_on_integer_sample(fwhm, tail):
    m = ExpTailIRF(fwhm, tail)
    g = exp_tail_irf(fwhm, tail)
    assert g.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(g >= 0)
    assert int(g.argmax()) == m.support[0]
    # the continuous mode is at t = 0: values just beside it are lower
    eps = 1e-4
    v = m.evaluate([-eps, 0.0, eps])
    assert v[1] > v[0] and v[1] > v[2]


def test_exp_tail_irf_is_gaussian_convolved_with_exponential():
    # independent reference: scipy's exponentially modified normal (K = tail / sigma)
    from scipy.stats import exponnorm

    fwhm, tail = 2.0, 3.0
    m = ExpTailIRF(fwhm, tail)
    sigma = fwhm * FWHM_TO_SIGMA
    u = np.arange(-5, 20, 0.25)  # times from the Gaussian centre
    want = exponnorm.pdf(u, tail / sigma, loc=0.0, scale=sigma)
    got = m.evaluate(u - m.mode_offset)  # the model puts its mode at 0
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)
    # numerically stable far in the tail, where erfc underflows and exp overflows
    far = m.evaluate(np.array([200.0, 2000.0]))
    assert np.all(np.isfinite(far)) and far[0] > far[1] >= 0
    dx = 0.01
    # the density integrates to 1 (trapezoid on a 0.01 grid, tails beyond truncated)
    t = np.arange(-20, 80, dx)
    assert np.trapezoid(m.evaluate(t), t) == pytest.approx(1.0, abs=1e-4)


def test_exp_tail_irf_length_keeps_mode_on_sample():
    g = exp_tail_irf(3.0, 4.0, length=31)
    assert g.shape == (31,)
    assert g.sum() == pytest.approx(1.0)
    m = ExpTailIRF(3.0, 4.0)
    left, right = m.support
    assert int(g.argmax()) == round(30 * left / (left + right))


def test_exp_tail_irf_bad_inputs_raise():
    with pytest.raises(SplidarError, match="tail"):
        exp_tail_irf(3.0, 0.0)
    with pytest.raises(SplidarError, match="fwhm"):
        exp_tail_irf(-1.0, 2.0)
    with pytest.raises(SplidarError, match="length"):
        exp_tail_irf(3.0, 2.0, length=0)


@pytest.mark.parametrize("fwhm", [2.0, 3.0, 6.5])
def test_irf_fwhm_of_gaussian_matches_parameter(fwhm):
    # linear interpolation between point samples overestimates by up to ~2 % (worst when
    # the half-maximum falls midway between samples, e.g. FWHM 3); allow 3 %
    assert irf_fwhm(gaussian_irf(fwhm)) == pytest.approx(fwhm, rel=0.03)


def test_irf_fwhm_per_wavelength_and_exact_triangle():
    out = irf_fwhm([[0, 1, 2, 1, 0], [0, 0, 1, 0, 0]])
    assert isinstance(out, np.ndarray)
    np.testing.assert_allclose(out, [2.0, 1.0])
    assert isinstance(irf_fwhm([0, 1, 2, 1, 0]), float)


def test_irf_fwhm_exp_tail_grows_with_tail():
    widths = [irf_fwhm(exp_tail_irf(3.0, t)) for t in (0.1, 1.0, 3.0, 10.0)]
    assert widths[0] == pytest.approx(3.0, abs=0.1)
    assert np.all(np.diff(widths) > 0)


def test_irf_fwhm_truncated_irf_raises():
    with pytest.raises(SplidarError, match="half its maximum"):
        irf_fwhm([1.0, 0.8, 0.2, 0.0])


def test_sampled_irf_integer_shift_exact_and_fraction_keeps_sum():
    vals = np.array([0.0, 1.0, 3.0, 2.0, 1.0, 0.5, 0.0])
    m = SampledIRF(vals)
    assert m.peak == 2
    t = np.arange(-4, 8)
    np.testing.assert_allclose(m.evaluate(t)[2:9], vals / vals.sum(), atol=1e-15)
    for f in (0.1, 0.5, 0.83):
        assert m.evaluate(t - f).sum() == pytest.approx(1.0, abs=1e-12)


def test_sampled_irf_two_dimensional_raises():
    with pytest.raises(SplidarError, match="one wavelength"):
        SampledIRF(np.ones((2, 5)))


def test_as_irf_models_accepts_all_forms():
    assert as_irf_models(("gaussian", 2.0))[0] == GaussianIRF(2.0)
    assert as_irf_models(2.0, n_wavelengths=3) == (GaussianIRF(2.0),) * 3
    ms = as_irf_models([("gaussian", 2.0), ("exp_tail", 2.0, 1.0), [0.0, 1.0, 0.5]])
    assert isinstance(ms[1], ExpTailIRF) and isinstance(ms[2], SampledIRF)
    arr = as_irf_models(np.array([[0.0, 1.0, 0.5], [0.5, 1.0, 0.0]]))
    assert len(arr) == 2 and arr[1].peak == 1
    assert len(as_irf_models(gaussian_irf(3.0), n_wavelengths=4)) == 4


def test_as_irf_models_bad_inputs_raise():
    with pytest.raises(SplidarError, match="not understood"):
        as_irf_models(("lorentz", 2.0))
    with pytest.raises(SplidarError, match="wavelengths"):
        as_irf_models([("gaussian", 2.0), ("gaussian", 3.0)], n_wavelengths=3)
    with pytest.raises(SplidarError, match="must be an IRF model"):
        as_irf_models({"fwhm": 2})
    with pytest.raises(SplidarError, match="negative"):
        as_irf_models([0.0, -1.0, 2.0])


def test_sample_irf_models_pads_and_keeps_modes():
    ms = as_irf_models([("gaussian", 2.0), ("exp_tail", 3.0, 5.0)])
    a = sample_irf_models(ms)
    assert a.shape[0] == 2
    np.testing.assert_allclose(a.sum(axis=1), 1.0)
    assert irf_peak(a).tolist() == [ms[0].support[0], ms[1].support[0]]
    np.testing.assert_allclose(normalise_irf(a), a)


@pytest.mark.parametrize("spec", [("gaussian", 2.5), ("exp_tail", 2.0, 3.0), [0.1, 1.0, 0.6, 0.2]])
def test_shifted_irf_integer_depth_is_sampled_irf(spec):
    m = as_irf_models(spec)[0]
    g = m.sample()
    p = int(g.argmax())
    out = shifted_irf(spec, [25.0], n_bins=80)[0, 0]
    np.testing.assert_allclose(out[25 - p : 25 - p + g.size], g, rtol=1e-12, atol=1e-15)
    assert out.sum() == pytest.approx(1.0, abs=1e-12)


def test_shifted_irf_fractional_depth_moves_peak_and_keeps_sum():
    d = np.array([30.0, 30.25, 30.75, 31.0])
    out = shifted_irf(("exp_tail", 3.0, 2.0), d, n_bins=80)[:, 0]
    np.testing.assert_allclose(out.sum(axis=1), 1.0, atol=1e-12)
    assert out.argmax(axis=1).tolist() == [30, 30, 31, 31]
    # the mean arrival time moves with the depth, by exactly the shift (support far inside)
    t = np.arange(80)
    mean = out @ t
    np.testing.assert_allclose(np.diff(mean), np.diff(d), atol=2e-3)


def test_shifted_irf_window_edge_cut():
    out = shifted_irf(("gaussian", 3.0), [0.0, 79.0], n_bins=80)[:, 0]
    half = gaussian_irf(3.0)[6:].sum()
    np.testing.assert_allclose(out.sum(axis=1), [half, half], rtol=1e-12)


def test_normalise_irf_is_idempotent_bit_for_bit():
    # an IRF that already sums to 1 (to rounding) is kept exactly: rebuilding a Cube
    # from another cube's IRF must not move its last bits (and so the results)
    rng = np.random.default_rng(5)
    raw = rng.gamma(2.0, 1.0, size=(3, 37))
    once = normalise_irf(raw)
    assert np.array_equal(normalise_irf(once), once)
    np.testing.assert_allclose(once.sum(axis=1), 1.0, rtol=0, atol=1e-12)


def test_cube_rebuilt_from_its_irf_is_identical():
    from splidar import Cube

    rng = np.random.default_rng(6)
    c = Cube(rng.poisson(1.0, size=(4, 5, 3, 40)), irf=rng.gamma(2.0, 1.0, size=(3, 9)))
    assert np.array_equal(Cube(c.counts, irf=c.irf).irf, c.irf)
