"""Tests of splidar.simulate: the observation model eq:4.1, PPP/SBR scaling, backgrounds."""

from __future__ import annotations

import numpy as np
import pytest

from splidar import Cube, PointSet, SplidarError
from splidar.irf import ExpTailIRF, GaussianIRF, as_irf_models
from splidar.simulation import (
    BACKGROUND_SHAPES,
    Simulation,
    background_shape,
    expected_counts,
    simulate,
)


def _same_surfaces(shape=(40, 40), depths=(12.3, 31.8), intensity=((3.0, 1.0), (2.0, 4.0))):
    """Every pixel holds the same surfaces: pixels are i.i.d. draws of one histogram."""
    r, c = shape
    rr, cc = np.mgrid[:r, :c]
    n = r * c
    k = len(depths)
    return PointSet(
        row=np.tile(rr.ravel(), k),
        col=np.tile(cc.ravel(), k),
        depth_bin=np.repeat(depths, n),
        image_shape=shape,
        intensity=np.repeat(np.asarray(intensity, float), n, axis=0),
        layer=np.repeat(np.arange(k), n),
    )


def _one(depth, intensity=100.0, n_bins=80):
    return PointSet(
        row=[0], col=[0], depth_bin=[depth], image_shape=(1, 1), intensity=[[intensity]]
    )


def _peak_parabola(h):
    k = int(np.argmax(h))
    a, b, c = h[k - 1 : k + 2]
    return k, k + 0.5 * (a - c) / (a - 2 * b + c)


# ---------------------------------------------------------------- statistics of draws


@pytest.mark.parametrize(
    "bg_kwargs",
    [
        {"background": "decaying", "background_per_bin": 0.05},  # sparse path: photon placement
        {"background": "pileup", "background_per_bin": 2.0},  # dense path: a draw per voxel
        {"background": np.linspace(0.1, 1.0, 50)},  # user array, absolute
    ],
)
def test_simulate_mean_and_variance_match_expected_counts(bg_kwargs):
    truth = _same_surfaces()
    kw = dict(n_bins=50, irf=[("gaussian", 2.0), ("exp_tail", 2.0, 3.0)], **bg_kwargs)
    lam = expected_counts(truth, **kw)[0, 0]  # (L, T), identical in every pixel
    sim = simulate(truth, rng=1, **kw)
    y = sim.cube.counts.reshape(-1, 2, 50).astype(np.float64)
    n = y.shape[0]
    z = (y.mean(axis=0) - lam) / np.sqrt(lam / n)
    # 100 per-bin z-scores of 1600 i.i.d. pixels: P(max |z| > 4.5) ~ 100 x 7e-6 < 1e-3
    assert np.abs(z).max() < 4.5
    # Poisson: variance = mean. Pooled over bins the ratio's standard error is < 1 %
    ratio = y.var(axis=0, ddof=1).sum() / lam.sum()
    assert ratio == pytest.approx(1.0, abs=0.05)


def test_simulate_user_dense_background_mean():
    truth = _same_surfaces((30, 30))
    rng = np.random.default_rng(5)
    bg = rng.uniform(0.0, 0.4, size=(30, 30, 2, 40))
    sim = simulate(truth, n_bins=40, irf=("gaussian", 2.0), background=bg, rng=2)
    np.testing.assert_allclose(sim.background(), bg)
    lam = expected_counts(truth, n_bins=40, irf=("gaussian", 2.0), background=bg)
    total = sim.cube.counts.sum(dtype=np.float64)
    # the cube total is Poisson(lam.sum()): 4.5 standard deviations
    assert abs(total - lam.sum()) < 4.5 * np.sqrt(lam.sum())


def test_simulate_is_reproducible_with_seed():
    truth = _same_surfaces((8, 8))
    kw = dict(n_bins=50, irf=2.0, ppp=20, sbr=0.5, background="decaying")
    a = simulate(truth, rng=7, **kw).cube.counts
    b = simulate(truth, rng=np.random.default_rng(7), **kw).cube.counts
    c = simulate(truth, rng=8, **kw).cube.counts
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


# ---------------------------------------------------------------- PPP and SBR


@pytest.mark.parametrize("background", [None, "uniform", "decaying", "pileup"])
def test_simulate_ppp_and_sbr_exact_on_expected_counts(background):
    rng = np.random.default_rng(0)
    r, c, T = 20, 24, 90
    n = 300
    truth = PointSet(
        row=rng.integers(0, r, n),
        col=rng.integers(0, c, n),
        depth_bin=rng.uniform(0, T - 1, n),  # some returns cut by the window edges
        image_shape=(r, c),
        intensity=rng.uniform(0, 5, (n, 3)),
    )
    bmap = rng.uniform(0.5, 2.0, (r, c))
    kw = dict(n_bins=T, irf=("exp_tail", 2.0, 2.0), ppp=7.5, sbr=0.3, background=background,
              background_map=bmap, background_per_bin=[1.0, 2.0, 0.5])  # fmt: skip
    sim = simulate(truth, rng=3, **kw)
    lam = expected_counts(truth, **kw)
    bg = sim.background()
    signal = lam - bg
    assert signal.min() >= -1e-12
    assert signal.sum() / (r * c) == pytest.approx(7.5, rel=1e-10)
    assert signal.sum() / bg.sum() == pytest.approx(0.3, rel=1e-10)
    assert (sim.ppp, sim.sbr) == (pytest.approx(7.5), pytest.approx(0.3))
    # relative per-wavelength levels of background_per_bin are kept under sbr
    per_l = bg.mean(axis=(0, 1, 3))
    np.testing.assert_allclose(per_l / per_l[0], [1.0, 2.0, 0.5], rtol=1e-10)
    np.testing.assert_allclose(sim.background_per_bin, per_l, rtol=1e-10)
    # the draws: total is Poisson(lam.sum()); 4.5 standard deviations
    total = sim.cube.counts.sum(dtype=np.float64)
    assert abs(total - lam.sum()) < 4.5 * np.sqrt(lam.sum())


def test_simulate_ppp_rescales_truth_intensity():
    truth = _same_surfaces((10, 10))
    sim = simulate(truth, n_bins=50, irf=2.0, ppp=2.0)
    # both surfaces are far from the edges: truth photons per pixel = ppp exactly
    per_pixel = sim.truth.intensity.sum() / 100
    assert per_pixel == pytest.approx(2.0, rel=1e-12)
    ratio = sim.truth.intensity / truth.intensity
    np.testing.assert_allclose(ratio, ratio.flat[0])  # one common factor
    np.testing.assert_array_equal(sim.truth.layer, truth.layer)
    assert sim.sbr == np.inf and sim.background_per_bin.max() == 0


def test_simulate_without_ppp_uses_truth_and_background_per_bin():
    truth = _same_surfaces((6, 6))
    sim = simulate(truth, n_bins=50, irf=2.0, background_per_bin=0.2)
    np.testing.assert_allclose(sim.truth.intensity, truth.intensity)
    assert sim.ppp == pytest.approx(10.0)  # (3 + 1) + (2 + 4)
    np.testing.assert_allclose(sim.background_per_bin, [0.2, 0.2])
    assert sim.sbr == pytest.approx(10.0 / (0.2 * 2 * 50))


def test_simulate_returns_cube_with_metadata():
    truth = _same_surfaces((5, 5))
    sim = simulate(truth, n_bins=50, irf=("exp_tail", 2.0, 3.0), ppp=5, bin_width_ps=250,
                   wavelengths_nm=[532, 1064], library=[[1.0, 0.5], [0.2, 1.0]], rng=0)  # fmt: skip
    assert isinstance(sim, Simulation) and isinstance(sim.cube, Cube)
    assert sim.cube.counts.dtype == np.uint16
    assert sim.cube.shape == (5, 5, 2, 50)
    assert sim.cube.bin_width_ps == 250 and sim.cube.library.n_classes == 2
    assert sim.cube.irf_peak.tolist() == [ExpTailIRF(2.0, 3.0).support[0]] * 2
    np.testing.assert_allclose(sim.truth.depth_m, sim.truth.depth_bin * sim.cube.bin_width_m)
    assert sim.cube.metadata["simulated"] is True


def test_simulate_large_counts_become_uint32():
    truth = _one(20.0, intensity=3e5, n_bins=40)
    sim = simulate(truth, n_bins=40, irf=1.0, rng=0)
    assert sim.cube.counts.dtype == np.uint32
    assert sim.cube.counts.max() > 65535


# ---------------------------------------------------------------- sub-bin depth


@pytest.mark.parametrize(
    ("irf", "tol"),
    [
        (("gaussian", 3.0), 0.04),  # parabola bias through samples of a Gaussian: < 0.03 bin
        (("exp_tail", 3.0, 4.0), 0.12),  # asymmetric: parabola bias measured <= 0.10 bin
        (("exp_tail", 2.0, 1.0), 0.12),
    ],
)
def test_expected_counts_peak_at_fractional_depth(irf, tol):
    for d in (40.0, 40.2, 40.37, 40.63, 40.9, 41.0):
        lam = expected_counts(_one(d), n_bins=80, irf=irf)[0, 0, 0]
        k, sub = _peak_parabola(lam)
        assert k == round(d)
        assert sub == pytest.approx(d, abs=tol)
        # exact: the return is the continuous IRF evaluated at t - d (mode at d) on the
        # model's support around d, normalised to the intensity
        m = as_irf_models(irf)[0]
        left, right = m.support
        t = np.arange(-100, 200)  # beyond the window: the tail past T is cut, not renormalised
        inside = (t - d >= -left) & (t - d <= right)
        want = np.where(inside, m.evaluate(t - d), 0.0)
        want *= 100.0 / want.sum()
        np.testing.assert_allclose(lam, want[100:180], rtol=1e-9, atol=1e-12)


def test_expected_counts_integer_depth_reproduces_cube_irf():
    irf = ("exp_tail", 2.5, 3.0)
    sim = simulate(_one(30.0), n_bins=80, irf=irf)
    g = sim.cube.irf[0]
    p = int(sim.cube.irf_peak[0])
    lam = expected_counts(_one(30.0), n_bins=80, irf=irf)[0, 0, 0]
    np.testing.assert_allclose(lam[30 - p : 30 - p + g.size], 100.0 * g, rtol=1e-12)


def test_expected_counts_sampled_irf_fractional_shift():
    g = np.array([0.0, 0.2, 1.0, 0.7, 0.4, 0.2, 0.1, 0.0])
    for d in (20.0, 20.3, 20.5, 20.8):
        lam = expected_counts(_one(d), n_bins=50, irf=g)[0, 0, 0]
        assert lam.sum() == pytest.approx(100.0, rel=1e-12)  # shift keeps the photons
        # linear interpolation: the return's value at t is g at t - d
        assert lam[20] == pytest.approx(100 * np.interp(-(d - 20), np.arange(8) - 2, g / g.sum()))


def test_expected_counts_multiple_surfaces_add():
    truth = PointSet(row=[0, 0, 0], col=[0, 0, 0], depth_bin=[10.0, 25.5, 60.2],
                     image_shape=(1, 1), intensity=[[5.0], [3.0], [8.0]])  # fmt: skip
    lam = expected_counts(truth, n_bins=80, irf=("gaussian", 2.0))[0, 0, 0]
    parts = [
        expected_counts(truth.subset([i]), n_bins=80, irf=("gaussian", 2.0))[0, 0, 0]
        for i in range(3)
    ]
    np.testing.assert_allclose(lam, sum(parts), rtol=1e-12)
    np.testing.assert_allclose([p.sum() for p in parts], [5.0, 3.0, 8.0])
    assert lam.sum() == pytest.approx(16.0)


def test_expected_counts_edge_return_is_cut():
    lam = expected_counts(_one(0.0), n_bins=40, irf=("gaussian", 3.0))[0, 0, 0]
    assert lam.sum() == pytest.approx(100.0 * GaussianIRF(3.0).sample()[6:].sum(), rel=1e-9)


# ---------------------------------------------------------------- backgrounds


def test_background_shape_forms():
    T = 200
    uni = background_shape("uniform", T)
    dec = background_shape("decaying", T)
    pil = background_shape("pileup", T)
    for s in (uni, dec, pil):
        assert s.mean() == pytest.approx(1.0)
    np.testing.assert_allclose(uni, 1.0)
    assert np.all(np.diff(dec) < 0) and dec[0] / dec[-1] == pytest.approx(np.exp(3), rel=0.02)
    assert np.all(np.diff(pil) < 0)
    assert pil[0] > 10 * pil[-1]  # high early bins
    assert pil[: T // 10].sum() > 0.35 * pil.sum()  # decays quickly: > 3.5x its uniform share


@pytest.mark.parametrize("name", BACKGROUND_SHAPES)
def test_simulate_background_draws_have_shape(name):
    empty = PointSet(row=[], col=[], depth_bin=[], image_shape=(40, 40), intensity=np.zeros((0, 1)))
    sim = simulate(empty, n_bins=60, irf=2.0, background=name, background_per_bin=0.3, rng=4)
    y = sim.cube.counts.sum(axis=(0, 1, 2), dtype=np.float64)
    want = 0.3 * 1600 * background_shape(name, 60)
    # per-bin totals are Poisson: 4.5 sigma over 60 bins
    assert np.all(np.abs(y - want) < 4.5 * np.sqrt(want) + 1)
    first, last = y[:15].sum(), y[-15:].sum()
    if name == "uniform":
        assert first == pytest.approx(last, rel=0.1)
    else:
        assert first > 2 * last


def test_simulate_background_map_and_levels_per_wavelength():
    empty = PointSet(row=[], col=[], depth_bin=[], image_shape=(4, 5), intensity=np.zeros((0, 2)))
    bmap = np.arange(20, dtype=float).reshape(4, 5) + 1
    sim = simulate(empty, n_bins=30, irf=2.0, background_map=bmap, background_per_bin=[0.1, 0.4])
    bg = sim.background()
    np.testing.assert_allclose(bg.mean(axis=(0, 1, 3)), [0.1, 0.4])
    np.testing.assert_allclose(bg[..., 0, 0] / bg[0, 0, 0, 0], bmap / bmap[0, 0])


# ---------------------------------------------------------------- bad inputs


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"ppp": -1.0}, "ppp"),
        ({"ppp": 0.0}, "ppp"),
        ({"sbr": 0.0}, "sbr"),
        ({"background": "fog", "background_per_bin": 1.0}, "background"),
        ({"background": np.ones(7)}, r"\(T,\)"),
        ({"background": -np.ones(50)}, "negative"),
        ({"background": "decaying"}, "only a shape"),
        ({"background_map": np.ones((4, 4))}, "only a shape"),
        ({"background_map": np.ones((3, 3)), "background_per_bin": 1.0}, "background_map"),
        ({"background_per_bin": [1.0, 2.0, 3.0]}, "background_per_bin"),
        ({"irf": ("lorentz", 2.0)}, "not understood"),
        ({"irf": [("gaussian", 2.0)] * 3}, "wavelengths"),
        ({"irf": ("exp_tail", 2.0, 30.0)}, "longer than n_bins"),
        ({"n_bins": 0}, "n_bins"),
    ],
)
def test_simulate_bad_inputs_raise(kwargs, match):
    kw = {"n_bins": 50, "irf": 2.0, **kwargs}
    with pytest.raises(SplidarError, match=match):
        simulate(_same_surfaces((4, 4)), **kw)


def test_simulate_truth_outside_window_raises():
    with pytest.raises(SplidarError, match="outside the time window"):
        simulate(_one(80.5), n_bins=80, irf=2.0)
    with pytest.raises(SplidarError, match="outside the time window"):
        simulate(_one(-0.1), n_bins=80, irf=2.0)


def test_simulate_bad_truth_raises():
    with pytest.raises(SplidarError, match="PointSet"):
        simulate({"row": [0]}, n_bins=10, irf=2.0)
    no_int = PointSet(row=[0], col=[0], depth_bin=[5.0], image_shape=(1, 1))
    with pytest.raises(SplidarError, match="no intensity"):
        simulate(no_int, n_bins=20, irf=2.0)
    # ...but with ppp every surface gets the same brightness
    assert simulate(no_int, n_bins=20, irf=2.0, ppp=3.0).truth.intensity.tolist() == [[3.0]]
    dark = PointSet(row=[0], col=[0], depth_bin=[5.0], image_shape=(1, 1), intensity=[[0.0]])
    with pytest.raises(SplidarError, match="no signal"):
        simulate(dark, n_bins=20, irf=2.0, ppp=3.0)
    with pytest.raises(SplidarError, match="no signal"):
        simulate(dark, n_bins=20, irf=2.0, sbr=3.0)
