import numpy as np
import pytest

from splidar import Cube, PointSet, SpectralLibrary, SplidarError
from splidar.irf import gaussian_irf, irf_peak, normalise_irf


def test_cube_accepts_3d_counts_as_single_wavelength():
    c = Cube(np.ones((3, 4, 50), np.uint16), irf=gaussian_irf(2.0))
    assert c.shape == (3, 4, 1, 50)
    assert c.counts.dtype == np.uint16


def test_cube_normalises_irf_without_touching_input():
    irf = np.array([1.0, 2.0, 1.0])
    c = Cube(np.zeros((2, 2, 2, 10), np.uint8), irf=irf)
    np.testing.assert_array_equal(irf, [1.0, 2.0, 1.0])
    assert c.irf.shape == (2, 3)
    np.testing.assert_allclose(c.irf.sum(axis=1), 1.0)
    assert c.irf_peak.tolist() == [1, 1]


def test_cube_converts_whole_float_counts_to_unsigned():
    c = Cube(np.full((2, 2, 10), 3.0), irf=[1.0])
    assert c.counts.dtype == np.uint16


@pytest.mark.parametrize(
    "counts, irf, match",
    [
        (np.zeros((2, 10)), [1.0], "dimension"),
        (np.full((2, 2, 10), -1), [1.0], "negative"),
        (np.full((2, 2, 10), np.nan), [1.0], "NaN"),
        (np.full((2, 2, 10), 0.5), [1.0], "non-integer"),
        (np.zeros((2, 2, 5), np.uint8), np.ones(6), "longer"),
        (np.zeros((2, 2, 5), np.uint8), np.zeros(3), "no positive"),
        (np.zeros((2, 2, 3, 5), np.uint8), np.ones((2, 3)), "L differs"),
        (np.zeros((2, 2, 5), np.uint8), [1.0, -0.1], "negative"),
    ],
)
def test_cube_rejects_bad_input_with_clear_error(counts, irf, match):
    with pytest.raises(SplidarError, match=match):
        Cube(counts, irf=irf)


def test_cube_depth_to_m_needs_bin_width():
    c = Cube(np.zeros((1, 1, 8), np.uint8), irf=[1.0])
    with pytest.raises(SplidarError, match="bin_width_ps"):
        c.depth_to_m(1.0)
    c = Cube(np.zeros((1, 1, 8), np.uint8), irf=[1.0], bin_width_ps=100.0)
    # 100 ps round trip = 1.49896229 cm
    assert c.depth_to_m(1.0) == pytest.approx(0.0149896229)


def test_gaussian_irf_peak_is_central_and_fwhm_is_right():
    g = gaussian_irf(6.0, length=101)
    assert g.argmax() == 50
    half = g.max() / 2
    above = np.flatnonzero(g >= half)
    # sampled FWHM within one bin of the request
    assert abs((above[-1] - above[0] + 1) - 6.0) <= 1.0


def test_normalise_irf_broadcasts_single_row():
    a = normalise_irf([0.0, 1.0, 3.0], n_wavelengths=3)
    assert a.shape == (3, 3)
    assert irf_peak(a).tolist() == [2, 2, 2]


def test_spectral_library_validates_names():
    with pytest.raises(SplidarError, match="class_names"):
        SpectralLibrary([[1.0, 2.0]], class_names=["a", "b"])


def test_pointset_maps_orders_layers_by_depth():
    p = PointSet(row=[0, 0, 1], col=[0, 0, 1], depth_bin=[30.0, 10.0, 5.0], image_shape=(2, 2))
    d = p.maps()["depth_bin"]
    assert d.shape == (2, 2, 2)
    assert d[0, 0].tolist() == [10.0, 30.0]
    assert np.isnan(d[1, 0]).all()


def test_pointset_save_load_roundtrip(tmp_path):
    p = PointSet(
        row=[0, 1],
        col=[1, 0],
        depth_bin=[1.5, 2.25],
        image_shape=(2, 2),
        intensity=[[1.0, 2.0], [3.0, 4.0]],
        label=[0, 1],
    )
    p.save(tmp_path / "p.npz")
    q = PointSet.load(tmp_path / "p.npz")
    for k, v in p.to_dict().items():
        np.testing.assert_array_equal(v, q.to_dict()[k])


def test_pointset_rejects_points_outside_image():
    with pytest.raises(SplidarError, match="outside"):
        PointSet(row=[5], col=[0], depth_bin=[1.0], image_shape=(2, 2))
