"""Tests of splidar.plotting on small fake results that follow the contracts."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402
from test_export import make_reconstruction  # noqa: E402

from splidar import PointSet, SplidarError  # noqa: E402
from splidar.plotting import (  # noqa: E402
    plot_depth,
    plot_detection_slice,
    plot_intensity,
    plot_labels,
    plot_point_cloud,
    plot_saliency_histogram,
    save_figures,
)


@pytest.fixture
def rec():
    return make_reconstruction(rows=20, cols=24, T=80)


@pytest.fixture(autouse=True)
def _close():
    yield
    plt.close("all")


def test_plot_depth_units_and_missing_pixels(rec):
    ax = plot_depth(rec, layer=1)
    im = ax.images[0]
    assert "2nd surface" in ax.get_title()
    cbar_label = im.colorbar.ax.get_ylabel()
    assert cbar_label == "depth (m)"
    # layer 1 exists only in the central block: the rest is masked (drawn grey)
    data = im.get_array()
    assert np.ma.count_masked(data) == np.isnan(rec.depth_map[:, :, 1]).sum() > 0
    d = rec.depth_map[:, :, 1]
    # 250 ps bins: depth_m = bins x 250e-12 s x c / 2
    np.testing.assert_allclose(data.compressed(), d[~np.isnan(d)] * 250e-12 * 299_792_458.0 / 2)


def test_plot_depth_bins_without_bin_width():
    r = make_reconstruction(bin_width_ps=None, with_detection=False)
    ax = plot_depth(r)
    assert ax.images[0].colorbar.ax.get_ylabel() == "depth (time bins)"


def test_plot_depth_pointset_and_bad_layer(rec):
    ax = plot_depth(rec.points)
    assert ax.images
    with pytest.raises(SplidarError, match="layer"):
        plot_depth(rec, layer=2)
    with pytest.raises(SplidarError, match="Reconstruction or a PointSet"):
        plot_depth(np.zeros((3, 3)))


def test_plot_intensity_wavelength_and_total(rec):
    ax = plot_intensity(rec, layer=0, wavelength=2)
    assert "600 nm" in ax.get_title()
    img = ax.images[0].get_array()
    np.testing.assert_allclose(img.filled(np.nan), rec.intensity_map[:, :, 0, 2])
    ax = plot_intensity(rec, layer=0)
    assert "total" in ax.get_title()
    with pytest.raises(SplidarError, match="wavelength"):
        plot_intensity(rec, wavelength=3)


def test_plot_labels_legend_has_class_names(rec):
    ax = plot_labels(rec, layer=1)
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    # layer 1 holds only "box"; "wall" is listed as absent, and empty pixels explained
    assert texts == ["wall (absent)", "box", "no surface"]


def test_plot_labels_colour_from_class_name():
    p = PointSet(row=[0, 0], col=[0, 1], depth_bin=[1.0, 2.0], image_shape=(1, 2), label=[0, 1])
    ax = plot_labels(p, class_names=["green foliage", "red paint"])
    handles = ax.get_legend().legend_handles
    assert matplotlib.colors.to_hex(handles[0].get_facecolor()) == "#2ca02c"
    assert matplotlib.colors.to_hex(handles[1].get_facecolor()) == "#d62728"


def test_plot_labels_unknown_material_apart_from_no_surface():
    # label -1 where a surface exists is "unknown material"; a pixel with no point stays
    # "no surface": the two get different colours and legend entries
    p = PointSet(row=[0, 0], col=[0, 1], depth_bin=[1.0, 2.0], image_shape=(1, 3), label=[0, -1])
    ax = plot_labels(p, class_names=["wall"])
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts == ["wall", "unknown material", "no surface"]
    img = ax.get_images()[0]
    rgba = img.to_rgba(img.get_array())
    assert not np.allclose(rgba[0, 1], rgba[0, 2])  # unknown drawn apart from empty
    assert not np.allclose(rgba[0, 0], rgba[0, 1])


def test_plot_point_cloud_subsamples_and_orients(rec):
    ax = plot_point_cloud(rec, max_points=50, rng=0)
    assert ax.name == "3d"
    n_drawn = sum(c.get_offsets().shape[0] for c in ax.collections)
    assert n_drawn == 50
    assert "50 shown" in ax.get_title()
    zlo, zhi = ax.get_zlim()
    assert zlo > zhi  # row 0 at the top
    assert ax.get_ylabel() == "depth (m)"
    with pytest.raises(SplidarError, match="color_by"):
        plot_point_cloud(rec, color_by="nope")


def test_plot_saliency_histogram_null_and_threshold(rec):
    ax = plot_saliency_histogram(rec)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("gamma null" in t for t in labels)
    assert any("threshold 6" in t for t in labels)
    assert ax.get_yscale() == "log"
    # the dashed threshold line sits at the detection threshold
    vlines = [ln for ln in ax.lines if ln.get_linestyle() == "--"]
    assert vlines and vlines[0].get_xdata()[0] == pytest.approx(6.0)


def test_plot_saliency_histogram_all_zero_saliency():
    # a detection whose saliency is 0 everywhere (no photon above the background level)
    # drew NaN axis limits in the zoom inset and raised inside matplotlib
    from splidar.reconstruction import synthetic_detection

    det, _ = synthetic_detection(shape=(6, 6), rng=0)
    assert not np.asarray(det.saliency).any()
    ax = plot_saliency_histogram(det)
    assert not ax.child_axes  # no zoom on a degenerate histogram
    assert all(np.isfinite(ax.get_ylim()))


def test_plot_saliency_histogram_needs_detection():
    r = make_reconstruction(with_detection=False)
    with pytest.raises(SplidarError, match="Detection"):
        plot_saliency_histogram(r)


def test_plot_detection_slice_with_and_without_data(rec):
    fig = plot_detection_slice(rec, t=20, row=5)
    a1, a2 = fig.axes[:2]
    assert "saliency" in a1.images[0].colorbar.ax.get_ylabel()
    rng = np.random.default_rng(0)
    counts = rng.poisson(0.2, rec.detection.cube_shape).astype(np.uint16)
    fig = plot_detection_slice(rec.detection, counts, t=20, row=5, half_window=1)
    a1 = fig.axes[0]
    np.testing.assert_allclose(a1.images[0].get_array(), counts[:, :, :, 19:22].sum(axis=(2, 3)))
    assert "photon counts" in a1.images[0].colorbar.ax.get_ylabel()
    with pytest.raises(SplidarError, match="shape"):
        plot_detection_slice(rec, counts[:, :, :, :10])
    with pytest.raises(SplidarError, match="`t`"):
        plot_detection_slice(rec, t=10_000)


def test_save_figures_writes_pngs(rec, tmp_path):
    paths = save_figures(rec, tmp_path / "figs")
    assert set(paths) == {
        "depth",
        "intensity",
        "labels",
        "label_confidence",
        "point_cloud",
        "saliency_histogram",
        "detection_slice",
    }
    for p in paths.values():
        with Image.open(p) as im:
            a = np.asarray(im.convert("L"))
        assert a.shape[0] > 200 and a.shape[1] > 200
        assert a.std() > 10  # not a blank picture


def test_save_figures_without_detection(tmp_path):
    r = make_reconstruction(with_detection=False, L=1)
    paths = save_figures(r, tmp_path)
    assert set(paths) == {"depth", "intensity", "labels", "label_confidence", "point_cloud"}
