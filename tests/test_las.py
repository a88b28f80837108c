"""Tests of splidar.las: LAS/LAZ written with laspy and read back with laspy."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from splidar import PointSet, SplidarError
from splidar.cube import SPEED_OF_LIGHT

laspy = pytest.importorskip("laspy")

from splidar.las import write_las  # noqa: E402


def _points(n_rows=6, n_cols=5, L=3, seed=0, depth_m=True):
    rng = np.random.default_rng(seed)
    rr, cc = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    row = np.r_[rr.ravel(), rr.ravel()[:7]]
    col = np.r_[cc.ravel(), cc.ravel()[:7]]
    n = row.size
    depth = np.r_[rng.uniform(10, 20, n - 7), rng.uniform(40, 60, 7)]
    inten = rng.gamma(3.0, 1.0, (n, L))
    bw_m = 250e-12 * SPEED_OF_LIGHT / 2
    return PointSet(
        row=row,
        col=col,
        depth_bin=depth,
        image_shape=(n_rows, n_cols),
        intensity=inten,
        label=rng.integers(0, 3, n),
        depth_m=depth * bw_m if depth_m else None,
        intensity_std=0.1 * inten,
        label_confidence=rng.uniform(0.3, 1.0, n),
        layer=np.r_[np.zeros(n - 7, int), np.ones(7, int)],
    )


def _splidar_vlr(las) -> dict:
    return json.loads(next(v for v in las.header.vlrs if v.user_id == "splidar").record_data)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_write_las_holds_every_point_and_field(tmp_path, suffix):
    p = _points()
    f = write_las(p, tmp_path / f"points{suffix}", pixel_size=0.02, class_names=["a", "b", "c"])
    las = laspy.read(f)
    with laspy.open(f) as fh:
        assert fh.header.are_points_compressed == (suffix == ".laz")
    n = len(p)
    assert las.header.point_count == n
    np.testing.assert_array_equal(las.classification, p.label)
    np.testing.assert_array_equal(las.row, p.row)
    np.testing.assert_array_equal(las.col, p.col)
    np.testing.assert_array_equal(las.depth_bin, p.depth_bin)
    np.testing.assert_array_equal(las.depth_m, p.depth_m)
    np.testing.assert_array_equal(las.layer, p.layer)
    for i in range(3):
        np.testing.assert_array_equal(las[f"intensity_{i}"], p.intensity[:, i].astype(np.float32))
        np.testing.assert_array_equal(
            las[f"intensity_std_{i}"], p.intensity_std[:, i].astype(np.float32)
        )
    np.testing.assert_array_equal(las.label_confidence, p.label_confidence.astype(np.float32))
    # metres: x, y from the pixel footprint, z = -depth, within half a coordinate step
    sx, sy, sz = las.header.scales
    np.testing.assert_allclose(las.x, p.col * 0.02, atol=sx / 2 + 1e-12)
    np.testing.assert_allclose(las.y, (5 - p.row) * 0.02, atol=sy / 2 + 1e-12)
    np.testing.assert_allclose(las.z, -p.depth_m, atol=sz / 2 + 1e-12)
    assert sz == 1e-5  # depth_m without a bin width: 10 um steps
    total = p.intensity.sum(axis=1)
    assert las.intensity.max() == 65535
    np.testing.assert_allclose(las.intensity, total * 65535 / total.max(), atol=0.5)
    # the 7 pixels with two surfaces: the far one is the 2nd of 2 returns
    assert np.asarray(las.return_number).tolist() == [1] * (n - 7) + [2] * 7
    assert np.asarray(las.number_of_returns)[:7].tolist() == [2] * 7
    assert np.asarray(las.number_of_returns)[7 : n - 7].tolist() == [1] * (n - 14)
    info = _splidar_vlr(las)
    assert info["xy_unit"] == "m" and info["z_unit"] == "m"
    assert info["class_names"] == ["a", "b", "c"]


def test_write_las_without_footprint_or_bin_width_uses_pixels_and_bins(tmp_path):
    p = _points(depth_m=False)
    las = laspy.read(write_las(p, tmp_path / "points.las"))
    np.testing.assert_allclose(las.x, p.col, atol=5e-4)
    np.testing.assert_allclose(las.z, -p.depth_bin, atol=5e-4)
    assert "depth_m" not in set(las.point_format.extra_dimension_names)
    info = _splidar_vlr(las)
    assert (info["xy_unit"], info["z_unit"]) == ("pixel", "bin")
    # a bin width alone gives z in metres, x and y still in pixels
    las = laspy.read(write_las(p, tmp_path / "m.las", bin_width_ps=250.0))
    bin_m = 250e-12 * SPEED_OF_LIGHT / 2
    assert las.header.scales[2] <= bin_m * 1e-3  # finer than a thousandth of a bin
    np.testing.assert_allclose(las.z, -p.depth_bin * bin_m, atol=las.header.scales[2] / 2)
    np.testing.assert_allclose(las.x, p.col, atol=5e-4)


def test_write_las_refuses_bad_input(tmp_path, monkeypatch):
    p = _points()
    with pytest.raises(SplidarError, match="must end in .las or .laz"):
        write_las(p, tmp_path / "points.txt")
    big = PointSet(row=[0], col=[0], depth_bin=[3.0], image_shape=(1, 1), label=[300])
    with pytest.raises(SplidarError, match="0..255"):
        write_las(big, tmp_path / "big.las")
    monkeypatch.setitem(sys.modules, "laspy", None)  # as if not installed
    with pytest.raises(SplidarError, match=r"pip install 'splidar\[las\]'"):
        write_las(p, tmp_path / "points.las")


@pytest.fixture(scope="module")
def small_cube(tmp_path_factory):
    from splidar import save
    from splidar.scenes import multispectral_scene

    sim = multispectral_scene((16, 16), n_bins=80).simulate(ppp=10, sbr=2, rng=0)
    path = tmp_path_factory.mktemp("las") / "scene.npz"
    save(sim.cube, path)
    return path


def test_main_run_writes_las_beside_csv_and_ply(small_cube, tmp_path):
    from splidar.cli import main

    out = tmp_path / "out"
    args = ["run", str(small_cube), "-q", "--no-figures", "--pixel-size", "0.01", "-o", str(out)]
    assert main(args) == 0
    assert "points.las" in json.loads((out / "summary.json").read_text())["files"]
    with np.load(out / "result.npz") as z:
        p = PointSet.from_dict({k[7:]: z[k] for k in z.files if k.startswith("points_")})
    las = laspy.read(out / "points.las")
    assert las.header.point_count == len(p) > 16 * 16 // 2
    np.testing.assert_array_equal(las.row, p.row)
    np.testing.assert_array_equal(las.col, p.col)
    np.testing.assert_array_equal(las.classification, p.label)
    np.testing.assert_array_equal(las.depth_bin, p.depth_bin)
    np.testing.assert_array_equal(las.depth_m, p.depth_m)
    np.testing.assert_array_equal(las.intensity_3, p.intensity[:, 3].astype(np.float32))
    np.testing.assert_array_equal(las.intensity_std_0, p.intensity_std[:, 0].astype(np.float32))
    np.testing.assert_array_equal(las.label_confidence, p.label_confidence.astype(np.float32))
    np.testing.assert_allclose(las.x, p.col * 0.01, atol=las.header.scales[0] / 2)
    np.testing.assert_allclose(las.z, -p.depth_m, atol=las.header.scales[2] / 2)
    assert (_splidar_vlr(las)["xy_unit"], _splidar_vlr(las)["z_unit"]) == ("m", "m")


def test_main_run_without_laspy_notes_and_goes_on(small_cube, tmp_path, monkeypatch, capsys):
    from splidar.cli import main

    monkeypatch.setitem(sys.modules, "laspy", None)  # as if not installed
    out = tmp_path / "out"
    assert main(["run", str(small_cube), "--no-figures", "-o", str(out)]) == 0
    assert (out / "points.ply").is_file() and not (out / "points.las").exists()
    err = [x for x in capsys.readouterr().err.splitlines() if "points.las" in x]
    assert err == [
        "splidar: points.las not written: laspy is not installed (pip install 'splidar[las]')"
    ]
