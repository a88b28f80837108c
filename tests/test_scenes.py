"""Tests of splidar.scenes: synthetic ground truths and the Middlebury Art scene."""

from __future__ import annotations

import numpy as np
import pytest

from splidar import SplidarError
from splidar.irf import irf_fwhm
from splidar.scenes import (
    Scene,
    art_scene,
    multispectral_scene,
    single_surface_scene,
    two_layer_scene,
)
from splidar.simulation import Simulation


def _inside_window(scene: Scene) -> None:
    """Every return's whole IRF support fits in the window."""
    left = max(m.support[0] for m in scene.irf)
    right = max(m.support[1] for m in scene.irf)
    d = scene.truth.depth_bin
    assert d.min() >= left and d.max() <= scene.n_bins - 1 - right


def test_single_surface_scene_geometry():
    s = single_surface_scene((32, 40), n_bins=150)
    assert s.shape == (32, 40) and s.n_bins == 150 and s.n_wavelengths == 1
    assert np.all(s.surfaces_per_pixel() == 1)
    _inside_window(s)
    depth = s.truth.maps()["depth_bin"][..., 0]
    inten = s.truth.maps()["intensity"][..., 0, 0]
    # fractional depths (slopes), steps (jumps of many bins between neighbours)
    assert np.mean(depth != np.round(depth)) > 0.5
    assert np.abs(np.diff(depth, axis=1)).max() > 20
    # dark patches: some pixels 10x darker than the median
    assert inten.min() < 0.15 * np.median(inten)
    assert inten.mean() == pytest.approx(10.0)
    assert s.library is None and np.all(s.truth.label == 0)


def test_single_surface_scene_simulates_at_requested_ppp_sbr():
    s = single_surface_scene((16, 16), n_bins=100, irf=("exp_tail", 2.0, 2.0), n_wavelengths=2)
    sim = s.simulate(ppp=12, sbr=0.5, background="decaying", rng=0)
    assert isinstance(sim, Simulation)
    assert sim.cube.shape == (16, 16, 2, 100)
    assert (sim.ppp, sim.sbr) == (pytest.approx(12), pytest.approx(0.5))
    np.testing.assert_array_equal(sim.cube.irf, s.irf_array)
    again = s.simulate(ppp=12, sbr=0.5, background="decaying", rng=0)
    np.testing.assert_array_equal(sim.cube.counts, again.cube.counts)


def test_two_layer_scene_net_in_front():
    s = two_layer_scene((40, 40), n_bins=200)
    n = s.surfaces_per_pixel()
    assert set(np.unique(n).tolist()) == {1, 2}
    assert 0.2 <= (n == 2).mean() <= 0.4  # strands cover 20-40 % of pixels
    maps = s.truth.maps()
    d = maps["depth_bin"]
    two = n == 2
    gap = d[two, 1] - d[two, 0]
    width = max(irf_fwhm(m.sample()) for m in s.irf)
    assert gap.min() >= 4 * width
    # the net is thin: no 2x2 block of strand pixels except at crossings
    assert np.all(np.isnan(d[~two, 1]))
    # the net is partly transmissive: the object behind gets the rest of the light
    inten = maps["intensity"][..., 0]
    assert np.all(inten[two, 0] > 0) and np.all(inten[two, 1] > 0)
    _inside_window(s)


def test_two_layer_scene_spacing_sets_coverage():
    s = two_layer_scene((40, 40), n_bins=200, net_spacing=4)
    assert (s.surfaces_per_pixel() == 2).mean() == pytest.approx(1 - (3 / 4) ** 2, abs=0.03)


def test_multispectral_scene_labels_follow_library():
    s = multispectral_scene((30, 30), n_bins=160, n_materials=4)
    lib = s.library
    assert lib.n_classes == 4 and lib.n_wavelengths == 4 == s.n_wavelengths
    assert s.wavelengths_nm.shape == (4,)
    assert sorted(set(s.truth.label.tolist())) == [0, 1, 2, 3]
    # intensity = shading x signature: normalised spectra equal the library rows
    spec = s.truth.intensity / s.truth.intensity.sum(axis=1, keepdims=True)
    sig = lib.signatures / lib.signatures.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(spec, sig[s.truth.label], rtol=1e-12)
    # signatures are distinct: smallest angle between spectra > 10 degrees
    u = lib.signatures / np.linalg.norm(lib.signatures, axis=1, keepdims=True)
    cos = u @ u.T
    assert np.max(cos[~np.eye(4, dtype=bool)]) < np.cos(np.deg2rad(10))
    # shading varies
    h = s.truth.intensity.sum(axis=1) / lib.signatures.sum(axis=1)[s.truth.label]
    assert h.max() / h.min() > 2


def test_multispectral_scene_two_layers_materials_differ():
    s = multispectral_scene((30, 30), n_bins=200, two_layers=True)
    maps = s.truth.maps()
    lab = maps["label"]
    two = s.surfaces_per_pixel() == 2
    assert two.any()
    assert np.all(lab[two, 0] != lab[two, 1])
    spec = s.truth.intensity / s.truth.intensity.sum(axis=1, keepdims=True)
    sig = s.library.signatures / s.library.signatures.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(spec, sig[s.truth.label], rtol=1e-12)
    sim = s.simulate(ppp=5, sbr=1, rng=0)
    assert sim.cube.library is s.library
    assert sim.cube.shape == (30, 30, 4, 200)


@pytest.mark.parametrize(
    ("builder", "kwargs", "match"),
    [
        (single_surface_scene, {"shape": (4, 4)}, "shape"),
        (single_surface_scene, {"n_bins": 20, "irf": ("gaussian", 6.0)}, "too short"),
        (two_layer_scene, {"n_bins": 30}, "too short"),
        (two_layer_scene, {"net_transmission": 1.0}, "net_transmission"),
        (two_layer_scene, {"net_spacing": 1}, "net_spacing"),
        (multispectral_scene, {"n_materials": 7}, "n_materials"),
        (multispectral_scene, {"photons": -1.0}, "photons"),
    ],
)
def test_scene_bad_inputs_raise(builder, kwargs, match):
    with pytest.raises(SplidarError, match=match):
        builder(**kwargs)


def test_art_scene_missing_files_raise(tmp_path):
    with pytest.raises(SplidarError, match="view1.png"):
        art_scene(tmp_path)


@pytest.mark.realdata
def test_art_scene_paper_geometry(shared_data):
    s = art_scene(shared_data / "middlebury-art")
    assert s.shape == (185, 232)
    assert s.n_bins == 164
    assert np.all(s.surfaces_per_pixel() == 2)
    assert s.n_wavelengths == 3 and s.library is not None
    _inside_window(s)
    d = s.truth.maps()["depth_bin"]
    assert np.all(d[..., 1] > d[..., 0])  # the second copy is behind the first
    # the two copies do not overlap in depth
    assert d[..., 1].min() > d[..., 0].max()
    assert s.truth.label.max() < s.library.n_classes
    grey = art_scene(shared_data / "middlebury-art", color=False)
    assert grey.n_wavelengths == 1 and grey.library is None
    sim = s.simulate(ppp=4, sbr=1, rng=0)
    assert sim.cube.shape == (185, 232, 3, 164)
    assert sim.ppp == pytest.approx(4)
