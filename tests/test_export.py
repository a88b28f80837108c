"""Tests of splidar.export: CSV, binary PLY (read back with plyfile), npz and summary."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from plyfile import PlyData

from splidar import PointSet, SpectralLibrary, SplidarError
from splidar.cube import SPEED_OF_LIGHT
from splidar.detection._result import Background, DataReduction, Detection, NullModel, Surfaces
from splidar.export import point_colors, write_csv, write_npz, write_ply, write_summary
from splidar.reconstruction._result import ConvergenceHistory, Reconstruction


def make_reconstruction(
    rows=12, cols=10, L=3, T=80, K=2, seed=0, bin_width_ps=250.0, with_detection=True
):
    """A small, self-consistent fake Reconstruction (and Detection) following the contracts.

    Two layers: a tilted plane at bin ~20 over the whole image (class "wall", layer 0) and
    a square at bin ~50 (class "box", layer 1) in the central block only.
    """
    rng = np.random.default_rng(seed)
    rr, cc = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    front_d = 20.0 + 0.3 * cc + rng.normal(0, 0.2, rr.size)
    centre = (np.abs(rr - rows / 2) < rows / 4) & (np.abs(cc - cols / 2) < cols / 4)
    row = np.r_[rr, rr[centre]]
    col = np.r_[cc, cc[centre]]
    depth = np.r_[front_d, 50.0 + rng.normal(0, 0.2, centre.sum())]
    layer = np.r_[np.zeros(rr.size, int), np.ones(centre.sum(), int)]
    label = np.r_[np.zeros(rr.size, int), np.ones(centre.sum(), int)]
    sig = np.array([[3.0, 1.0, 0.5], [0.5, 1.0, 3.0]])[:, :L]
    inten = sig[label] * rng.gamma(20, 1 / 20, (row.size, 1))
    n = row.size
    bw_m = None if bin_width_ps is None else bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2
    pts = PointSet(
        row=row,
        col=col,
        depth_bin=depth,
        image_shape=(rows, cols),
        intensity=inten,
        label=label,
        depth_m=None if bw_m is None else depth * bw_m,
        intensity_std=0.1 * inten,
        label_confidence=np.full(n, 0.9),
        layer=layer,
    )
    maps = pts.maps(n_layers=K)
    lib = SpectralLibrary(sig, class_names=["wall", "box"])
    det = None
    if with_detection:
        sal = rng.gamma(2.0, 0.5, (rows, cols, T)).astype(np.float32)
        mask = np.zeros((rows, cols, T), bool)
        mask[row, col, np.round(depth).astype(int)] = True
        sal[mask] += 20
        irf = np.zeros((L, 9))
        irf[:, 3:6] = [0.25, 0.5, 0.25]
        surf = Surfaces(
            row=row,
            col=col,
            slot=layer,
            depth_bin=depth,
            start=np.round(depth).astype(int) - 1,
            stop=np.round(depth).astype(int) + 2,
            scale_index=np.zeros(n, int),
            offset=np.round(depth).astype(int) - 1,
            histograms=np.zeros((n, 1, L, 3), np.float32),
            signal=inten[:, None, :],
            counts=inten,
            background=np.zeros((n, L)),
            saliency_mass=np.ones(n),
            image_shape=(rows, cols),
            n_slots=K,
        )
        det = Detection(
            cube_shape=(rows, cols, L, T),
            irf=irf,
            bin_width_ps=bin_width_ps,
            wavelengths_nm=np.array([500.0, 550.0, 600.0])[:L],
            library=lib,
            scales=(1, 3),
            weights=np.array([0.5, 0.5]),
            pfa=1e-3,
            background=Background(
                spatial=np.full((rows, cols, L), 0.1, np.float32),
                temporal=np.full((L, T), 0.1, np.float32),
            ),
            saliency=sal,
            null=NullModel(shape=2.0, scale=0.5, method="quantile", pfa=1e-3),
            threshold=np.float64(6.0),
            mask=mask,
            reduction=DataReduction(
                voxel_fraction=float(mask.mean()),
                photon_fraction=0.5,
                n_voxels=int(mask.sum()),
                n_photons=100,
            ),
            surfaces=surf,
            timings={"saliency": 0.01},
            options={"max_surfaces": K},
        )
    return Reconstruction(
        points=pts,
        depth_map=maps["depth_bin"],
        intensity_map=maps["intensity"],
        label_map=maps["label"],
        library=lib,
        history=ConvergenceHistory(
            objective=np.zeros(3),
            change=np.array([0.1, 1e-4]),
            n_iter=2,
            converged=True,
            reason="tol",
        ),
        hyperparameters={"gamma": 4.0, "rho": 1.0},
        timings={"coordinate_descent": 0.02},
        detection=det,
    )


@pytest.fixture
def rec():
    return make_reconstruction()


def test_write_csv_header_and_values(rec, tmp_path):
    f = write_csv(rec, tmp_path / "points.csv")
    with open(f, newline="") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    L = rec.points.n_wavelengths
    assert header[: 4 + L] == ["row", "col", "depth_bin", "label"] + [
        f"intensity_{i}" for i in range(L)
    ]
    assert header[4 + L :] == (
        ["depth_m"] + [f"intensity_std_{i}" for i in range(L)] + ["label_confidence", "layer"]
    )
    data = np.array(rows[1:], dtype=float)
    p = rec.points
    assert data.shape == (len(p), len(header))
    np.testing.assert_array_equal(data[:, 0], p.row)
    np.testing.assert_array_equal(data[:, 3], p.label)
    # 7 significant digits: relative error below 1e-6
    np.testing.assert_allclose(data[:, 2], p.depth_bin, rtol=1e-6)
    np.testing.assert_allclose(data[:, 4 : 4 + L], p.intensity, rtol=1e-6)


def test_write_csv_minimal_points_label_zero(tmp_path):
    p = PointSet(row=[0, 1], col=[1, 0], depth_bin=[3.5, 4.0], image_shape=(2, 2))
    text = write_csv(p, tmp_path / "p.csv").read_text().splitlines()
    assert text == ["row,col,depth_bin,label", "0,1,3.5,0", "1,0,4,0"]


def test_write_csv_empty_has_header(tmp_path):
    p = PointSet(row=[], col=[], depth_bin=[], image_shape=(2, 2), intensity=np.zeros((0, 2)))
    text = write_csv(p, tmp_path / "p.csv").read_text()
    assert text == "row,col,depth_bin,label,intensity_0,intensity_1\n"


def test_write_ply_reads_back_with_plyfile(rec, tmp_path):
    f = write_ply(rec, tmp_path / "points.ply")
    assert f.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    ply = PlyData.read(str(f))
    v = ply["vertex"].data
    p = rec.points
    rows = p.image_shape[0]
    assert v.size == len(p)
    names = v.dtype.names
    assert names[:3] == ("x", "y", "z")
    assert {"red", "green", "blue", "label", "intensity_0", "intensity_2"} <= set(names)
    np.testing.assert_array_equal(v["x"], p.col)
    np.testing.assert_array_equal(v["y"], rows - 1 - p.row)
    # float32 storage: relative error below 1e-6
    np.testing.assert_allclose(v["z"], -p.depth_m, rtol=1e-6)
    np.testing.assert_allclose(v["depth"], p.depth_m, rtol=1e-6)
    np.testing.assert_allclose(v["intensity_1"], p.intensity[:, 1], rtol=1e-6)
    np.testing.assert_array_equal(v["label"], p.label)
    assert v["red"].dtype == np.uint8


def test_write_ply_depth_in_bins_without_bin_width(tmp_path):
    p = PointSet(row=[0, 2], col=[1, 0], depth_bin=[3.5, 4.0], image_shape=(3, 2))
    v = PlyData.read(str(write_ply(p, tmp_path / "p.ply")))["vertex"].data
    np.testing.assert_allclose(v["z"], [-3.5, -4.0])
    np.testing.assert_array_equal(v["y"], [2, 0])
    np.testing.assert_array_equal(v["label"], [0, 0])
    # bin width given: metres
    v = PlyData.read(str(write_ply(p, tmp_path / "m.ply", bin_width_ps=1000, pixel_size=0.01)))
    d = v["vertex"].data
    np.testing.assert_allclose(d["depth"], np.array([3.5, 4.0]) * 1e-9 * SPEED_OF_LIGHT / 2, 1e-6)
    np.testing.assert_allclose(d["x"], [0.01, 0.0], rtol=1e-6)


def test_write_ply_rejects_bad_input(tmp_path):
    with pytest.raises(SplidarError, match="PointSet"):
        write_ply(np.zeros(3), tmp_path / "p.ply")
    p = PointSet(row=[0], col=[0], depth_bin=[1.0], image_shape=(1, 1))
    with pytest.raises(SplidarError, match="bin_width_ps"):
        write_ply(p, tmp_path / "p.ply", bin_width_ps=-1)


def test_point_colors_rgb_channels_order():
    p = PointSet(
        row=[0, 0, 0],
        col=[0, 1, 2],
        depth_bin=[1.0, 1.0, 1.0],
        image_shape=(1, 3),
        intensity=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]],
    )
    c = point_colors(p, percentile=100)
    # last wavelength -> red, middle -> green, first -> blue
    np.testing.assert_array_equal(c, [[0, 0, 255], [0, 255, 0], [255, 0, 0]])


def test_write_npz_roundtrip(rec, tmp_path):
    f = write_npz(rec, tmp_path / "result.npz")
    with np.load(f) as z:
        np.testing.assert_array_equal(z["depth_map"], rec.depth_map)
        np.testing.assert_array_equal(z["label_map"], rec.label_map)
        np.testing.assert_array_equal(z["detection_mask"], rec.detection.mask)
        assert list(z["class_names"]) == ["wall", "box"]
        pts = PointSet.from_dict({k[7:]: z[k] for k in z.files if k.startswith("points_")})
        assert float(z["null_shape"]) == 2.0
        assert z["depth_map_m"].shape == rec.depth_map.shape
    np.testing.assert_array_equal(pts.depth_bin, rec.points.depth_bin)
    np.testing.assert_array_equal(pts.intensity, rec.points.intensity)


def test_write_npz_rejects_pointset(tmp_path):
    p = PointSet(row=[0], col=[0], depth_bin=[1.0], image_shape=(1, 1))
    with pytest.raises(SplidarError, match="Reconstruction"):
        write_npz(p, tmp_path / "r.npz")


def test_write_summary_contents(rec, tmp_path):
    f = write_summary(rec, tmp_path / "summary.json", extra={"input": "x.npz"})
    s = json.loads(f.read_text())
    n_front = rec.image_shape[0] * rec.image_shape[1]
    assert s["counts"]["points"] == len(rec.points)
    assert s["counts"]["points_per_layer"] == {"0": n_front, "1": len(rec.points) - n_front}
    assert s["counts"]["points_per_class"]["box"] == len(rec.points) - n_front
    assert s["parameters"]["detection"]["scales"] == [1, 3]
    assert s["parameters"]["reconstruction"]["gamma"] == 4.0
    assert s["data_reduction"]["n_voxels"] == int(rec.detection.mask.sum())
    assert s["versions"]["splidar"]
    assert s["input"] == "x.npz"
    assert s["convergence"]["converged"] is True
