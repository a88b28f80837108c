"""Tests of splidar.io: every file kind round-trips, real photon-list files load, errors."""

from __future__ import annotations

import json
import re
import time

import h5py
import numpy as np
import pytest
import scipy.io
from scipy.ndimage import convolve1d

from splidar import Cube, SpectralLibrary, SplidarError
from splidar.io import (
    bin_photons,
    estimate_irf_fwhm,
    load,
    load_irf,
    load_library,
    photon_lists_from_cells,
    read_photon_lists,
    save,
)
from splidar.irf import gaussian_irf


@pytest.fixture
def cube():
    rng = np.random.default_rng(0)
    counts = rng.poisson(0.3, size=(5, 4, 2, 30)).astype(np.uint16)
    lib = SpectralLibrary([[1.0, 0.5], [0.2, 1.0]], class_names=["red", "blue"])
    return Cube(
        counts,
        irf=np.array([[0.0, 1.0, 3.0, 1.0], [1.0, 2.0, 1.0, 0.5]]),
        bin_width_ps=16.0,
        wavelengths_nm=[532.0, 633.0],
        library=lib,
        metadata={"scene": "test", "n": 3, "nested": {"a": [1, 2]}},
    )


def _assert_same(a: Cube, b: Cube, *, meta=True):
    counts_b = b.counts.compute() if b.is_lazy else b.counts
    assert counts_b.dtype == a.counts.dtype
    np.testing.assert_array_equal(counts_b, a.counts)
    np.testing.assert_array_equal(b.irf, a.irf)
    assert b.bin_width_ps == a.bin_width_ps
    np.testing.assert_array_equal(b.wavelengths_nm, a.wavelengths_nm)
    np.testing.assert_array_equal(b.library.signatures, a.library.signatures)
    assert b.library.class_names == a.library.class_names
    if meta:
        assert dict(b.metadata) == json.loads(json.dumps(dict(a.metadata)))


def _cells(lists, shape):
    c = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        c[idx] = np.asarray(lists.get(idx, []), dtype=np.uint16).reshape(-1, 1)
    return c


# --------------------------------------------------------------------------------------
# histogram files
# --------------------------------------------------------------------------------------
def test_save_load_npz_round_trip_exact(cube, tmp_path):
    p = tmp_path / "c.npz"
    save(cube, p)
    back = load(p)
    _assert_same(cube, back)
    assert dict(back.metadata)["nested"] == {"a": [1, 2]}


def test_save_load_npz_uint32_counts(tmp_path):
    c = Cube(np.full((2, 2, 5), 70_000, np.uint32), irf=[1.0])
    save(c, tmp_path / "c.npz")
    back = load(tmp_path / "c.npz")
    assert back.counts.dtype == np.uint32 and int(back.counts.max()) == 70_000


def test_load_mat_v5_histogram(cube, tmp_path):
    p = tmp_path / "c.mat"
    scipy.io.savemat(
        p,
        {
            "counts": cube.counts,
            "irf": cube.irf,
            "bin_width_ps": 16.0,
            "wavelengths_nm": cube.wavelengths_nm,
            "library": cube.library.signatures,
            "class_names": np.array(["red", "blue"], dtype=object),
        },
    )
    back = load(p)
    _assert_same(cube, back, meta=False)


def _write_v73(path, arrays):
    """Write like MATLAB -v7.3: HDF5 with a 512-byte user block and reversed axes."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for k, v in arrays.items():
            ds = f.create_dataset(k, data=np.asarray(v).T)
            ds.attrs["MATLAB_class"] = np.bytes_("double" if v.dtype.kind == "f" else "uint16")
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .")


def test_load_mat_v73_reversed_axes(cube, tmp_path):
    p = tmp_path / "c73.mat"
    _write_v73(p, {"counts": cube.counts, "irf": cube.irf, "bin_width_ps": np.array([[16.0]])})
    back = load(p)
    np.testing.assert_array_equal(back.counts, cube.counts)
    np.testing.assert_array_equal(back.irf, cube.irf)
    assert back.bin_width_ps == 16.0


def test_load_mat_v73_cell_photon_lists(tmp_path):
    p = tmp_path / "ts73.mat"
    lists = {(0, 0): [3, 4, 4], (1, 2): [0, 9]}
    with h5py.File(p, "w", userblock_size=512) as f:
        refs_grp = f.create_group("#refs#")
        refs = np.empty((3, 2), dtype=h5py.ref_dtype)  # MATLAB 2 x 3 cell, reversed
        for r in range(2):
            for c in range(3):
                v = np.asarray(lists.get((r, c), []), dtype=np.uint16)
                ds = refs_grp.create_dataset(f"r{r}c{c}", data=v.reshape(1, -1))
                refs[c, r] = ds.ref
        ts = f.create_dataset("Ts", data=refs)
        ts.attrs["MATLAB_class"] = np.bytes_("cell")
    c = load(p, irf_fwhm=1.0)
    assert c.shape == (2, 3, 1, 10)
    assert c.counts[0, 0, 0].tolist() == [0, 0, 0, 1, 2, 0, 0, 0, 0, 0]
    assert c.counts[1, 2, 0, 0] == 1 and c.counts[1, 2, 0, 9] == 1
    assert int(c.counts.sum()) == 5


def test_load_h5_histogram(cube, tmp_path):
    p = tmp_path / "c.h5"
    with h5py.File(p, "w") as f:
        f["counts"] = cube.counts
        f["irf"] = cube.irf
        f["bin_width_ps"] = 16.0
    back = load(p)
    np.testing.assert_array_equal(back.counts, cube.counts)
    assert back.bin_width_ps == 16.0


def test_load_histogram_window_crops_bins(cube, tmp_path):
    save(cube, tmp_path / "c.npz")
    back = load(tmp_path / "c.npz", window=(5, 20))
    np.testing.assert_array_equal(back.counts, cube.counts[..., 5:20])


def test_load_overrides(cube, tmp_path):
    save(cube, tmp_path / "c.npz")
    back = load(tmp_path / "c.npz", bin_width_ps=8.0, wavelengths_nm=[1.0, 2.0])
    assert back.bin_width_ps == 8.0 and back.wavelengths_nm.tolist() == [1.0, 2.0]


# --------------------------------------------------------------------------------------
# zarr
# --------------------------------------------------------------------------------------
def test_save_load_zarr_lazy_round_trip(cube, tmp_path):
    pytest.importorskip("zarr")
    p = tmp_path / "c.zarr"
    save(cube, p, chunks=(2, 3))
    back = load(p)
    assert back.is_lazy
    assert back.counts.chunks[0][0] == 2 and back.counts.chunks[1][0] == 3
    _assert_same(cube, back)
    # a lazy cube saves again (chunk by chunk) and to .npz
    save(back, tmp_path / "d.zarr")
    _assert_same(cube, load(tmp_path / "d.zarr"))
    save(back, tmp_path / "d.npz")
    _assert_same(cube, load(tmp_path / "d.npz"))


def test_load_zarr_without_irf_needs_one(tmp_path):
    zarr = pytest.importorskip("zarr")
    g = zarr.open_group(str(tmp_path / "x.zarr"), mode="w")
    g.create_array("counts", data=np.ones((2, 2, 10), np.uint16))
    with pytest.raises(SplidarError, match="irf_fwhm"):
        load(tmp_path / "x.zarr")
    c = load(tmp_path / "x.zarr", irf_fwhm=2.0)
    assert c.shape == (2, 2, 1, 10) and c.is_lazy
    h = zarr.open_group(str(tmp_path / "y.zarr"), mode="w")
    h.create_array("other", data=np.ones(3))
    with pytest.raises(SplidarError, match="no `counts`"):
        load(tmp_path / "y.zarr")


# --------------------------------------------------------------------------------------
# photon lists
# --------------------------------------------------------------------------------------
def test_bin_photons_by_hand():
    # bins of width 2 over [0, 6): [0,2) [2,4) [4,6); t = 6 is outside, t = -1 too
    c = bin_photons(
        [0, 1, 1, 5, 6, -1, 3.999],
        [0, 0, 1, 1, 1, 0, 0],
        shape=(1, 2),
        window=(0, 6),
        bin_width=2,
    )
    assert c.shape == (1, 2, 1, 3) and c.dtype == np.uint16
    assert c[0, 0, 0].tolist() == [2, 1, 0]
    assert c[0, 1, 0].tolist() == [1, 0, 1]


def test_bin_photons_integer_times_exact_and_ragged_window():
    t = np.array([1000, 1003, 1004, 1007, 1008], dtype=np.int32)
    c = bin_photons(t, np.zeros(5, np.int64), shape=(1, 1), window=(1000, 1009), bin_width=4)
    # T = ceil(9 / 4) = 3 bins: [1000,1004) [1004,1008) [1008,1012) cut at stop 1009
    assert c[0, 0, 0].tolist() == [2, 2, 1]


def test_bin_photons_matches_per_pixel_histogram():
    rng = np.random.default_rng(4)
    n, shape = 20_000, (30, 20)
    t = rng.uniform(0, 1000, n)
    pix = rng.integers(0, 600, n)
    c = bin_photons(t, pix, shape=shape, window=(100, 900), bin_width=7.5)
    for p in (0, 17, 599):
        h, _ = np.histogram(t[pix == p], bins=100 + 7.5 * np.arange(c.shape[-1] + 1))
        h[-1] -= np.count_nonzero((t[pix == p] >= 900) & (t[pix == p] <= 100 + 7.5 * 107))
        np.testing.assert_array_equal(c.reshape(600, -1)[p], h)


def test_bin_photons_errors():
    with pytest.raises(SplidarError, match="stop > start"):
        bin_photons([1], [0], shape=(1, 1), window=(5, 5), bin_width=1)
    with pytest.raises(SplidarError, match="bin_width"):
        bin_photons([1], [0], shape=(1, 1), window=(0, 5), bin_width=0)
    with pytest.raises(SplidarError, match="same length"):
        bin_photons([1, 2], [0], shape=(1, 1), window=(0, 5))
    with pytest.raises(SplidarError, match="pixel_index"):
        bin_photons([1], [4], shape=(1, 2), window=(0, 5))
    with pytest.raises(SplidarError, match="GiB"):
        bin_photons([1], [0], shape=(1000, 1000), window=(0, 1e7), bin_width=1)


def test_bin_photons_too_large_suggests_a_bin_width_that_fits():
    # 1000 x 1000 pixels x 1e7 bins of 2 bytes: the suggestion must be a round width
    # whose cube fits under 1 GiB (and the next round width down must not)
    with pytest.raises(SplidarError, match="GiB") as err:
        bin_photons([1], [0], shape=(1000, 1000), window=(0, 1e7), bin_width=1)
    m = re.search(r"`bin_width` (\S+) gives T = (\d+) bins \((\d+) MiB\)", str(err.value))
    assert m is not None, str(err.value)
    width, n_bins, mib = float(m[1]), int(m[2]), int(m[3])
    assert width == 20000.0 and n_bins == 500
    assert mib == round(1000 * 1000 * n_bins * 2 / 2**20) and mib <= 1024
    assert 1000 * 1000 * (1e7 / 10000) * 2 > 2**30  # 10000 would not fit


def test_photon_lists_from_cells_and_read(tmp_path):
    lists = {(0, 0): [5, 7], (2, 1): [1]}
    cells = _cells(lists, (3, 2))
    pl = photon_lists_from_cells(cells)
    assert pl.shape == (3, 2) and pl.times.tolist() == [5, 7, 1]
    assert pl.pixel_index.tolist() == [0, 0, 5] and pl.times.dtype == np.uint16
    scipy.io.savemat(tmp_path / "ts.mat", {"Ts": cells, "gate": 3.0})
    pl2 = read_photon_lists(tmp_path / "ts.mat")
    assert pl2.times.tolist() == [5, 7, 1] and pl2.shape == (3, 2)
    assert photon_lists_from_cells([[[1, 2], []], [[3], [4]]]).pixel_index.tolist() == [0, 0, 2, 3]


def test_load_photon_list_mat_default_window_and_units(tmp_path):
    lists = {(0, 0): [10, 12, 12], (1, 1): [19]}
    scipy.io.savemat(tmp_path / "ts.mat", {"Ts": _cells(lists, (2, 2))})
    c = load(tmp_path / "ts.mat", irf_fwhm=2.0)
    # default window: earliest (10) to latest (19) photon inclusive -> T = 10, unit bins
    assert c.shape == (2, 2, 1, 10) and c.bin_width_ps is None
    assert c.counts[0, 0, 0, 0] == 1 and c.counts[0, 0, 0, 2] == 2 and c.counts[1, 1, 0, 9] == 1
    assert c.metadata["window"] == [10.0, 20.0] and c.metadata["irf_source"].startswith("gauss")
    c = load(tmp_path / "ts.mat", irf_fwhm=2.0, time_unit="ns", window=(8, 24), bin_width=4)
    assert c.shape[-1] == 4 and c.bin_width_ps == 4000.0
    assert c.counts[0, 0, 0].tolist() == [1, 2, 0, 0]


def test_load_photon_lists_variable_choice(tmp_path):
    cells = _cells({(0, 0): [1, 2]}, (2, 2))
    scipy.io.savemat(tmp_path / "two.mat", {"A": cells, "B": cells, "x": 1.0})
    with pytest.raises(SplidarError, match="variable=") as ei:
        load(tmp_path / "two.mat")
    assert "'A'" in str(ei.value) and "'B'" in str(ei.value) and "(2, 2)" in str(ei.value)
    c = load(tmp_path / "two.mat", variable="B", irf_fwhm=1.0)
    assert int(c.counts.sum()) == 2
    with pytest.raises(SplidarError, match="'nope' is not in") as ei:
        load(tmp_path / "two.mat", variable="nope")
    assert "'x'" in str(ei.value)
    with pytest.raises(SplidarError, match="count cube"):
        load(tmp_path / "two.mat", variable="x")


def test_load_photon_list_npz_flat(tmp_path):
    np.savez(tmp_path / "ts.npz", times=[4, 6, 4], pixel_index=[1, 1, 1], shape=[1, 2])
    c = load(tmp_path / "ts.npz", irf_fwhm=1.0, window=(0, 8))
    assert c.counts[0, 1, 0].tolist() == [0, 0, 0, 0, 2, 0, 1, 0]
    assert c.counts[0, 0, 0].sum() == 0
    assert read_photon_lists(tmp_path / "ts.npz").times.tolist() == [4, 6, 4]


def test_load_npz_object_array_refused_without_unpickling(tmp_path):
    cells = _cells({(0, 1): [4, 4, 6]}, (1, 2))
    np.savez(tmp_path / "ts.npz", times=cells)
    with pytest.raises(SplidarError, match="never unpickles"):
        load(tmp_path / "ts.npz", irf_fwhm=1.0, window=(0, 8))


# --------------------------------------------------------------------------------------
# IRFs
# --------------------------------------------------------------------------------------
def test_load_irf_files(tmp_path):
    g = np.array([0.0, 0.0, 1.0, 4.0, 2.0, 0.0])
    np.savetxt(tmp_path / "irf.csv", g[None, :], delimiter=",")
    np.testing.assert_array_equal(load_irf(tmp_path / "irf.csv"), [[1.0, 4.0, 2.0]])
    np.savetxt(tmp_path / "irf.txt", g)
    np.testing.assert_array_equal(load_irf(tmp_path / "irf.txt"), [[1.0, 4.0, 2.0]])
    np.savez(tmp_path / "irf.npz", pulse=np.stack([g, g[::-1]]))
    # only the zero samples shared by both rows are trimmed
    assert load_irf(tmp_path / "irf.npz").shape == (2, 4)
    scipy.io.savemat(tmp_path / "m.mat", {"big": np.ones((30, 30)), "w": g[None, :]})
    np.testing.assert_array_equal(load_irf(tmp_path / "m.mat"), [[1.0, 4.0, 2.0]])
    scipy.io.savemat(tmp_path / "amb.mat", {"a": g, "b": g})
    with pytest.raises(SplidarError, match="irf_variable"):
        load_irf(tmp_path / "amb.mat")
    assert load_irf(tmp_path / "amb.mat", variable="b").shape == (1, 3)
    (tmp_path / "irf.json").write_text("[1, 2]")
    with pytest.raises(SplidarError, match="extension"):
        load_irf(tmp_path / "irf.json")


def test_load_irf_options(cube, tmp_path):
    save(cube, tmp_path / "c.npz")
    np.savetxt(tmp_path / "irf.csv", [1.0, 3.0, 1.0])
    c = load(tmp_path / "c.npz", irf=tmp_path / "irf.csv")
    np.testing.assert_allclose(c.irf, [[0.2, 0.6, 0.2]] * 2)
    c = load(tmp_path / "c.npz", irf_fwhm=3.0)
    np.testing.assert_allclose(c.irf[0], gaussian_irf(3.0))
    # an IRF longer than T is cropped around its peak
    long = gaussian_irf(4.0, length=101)
    c = load(tmp_path / "c.npz", irf=long)
    assert c.irf.shape == (2, 29) and c.irf_peak.tolist() == [14, 14]
    with pytest.raises(SplidarError, match="irf_fwhm=4.0"):
        load(tmp_path / "c.npz", irf=4.0)
    with pytest.raises(SplidarError, match="not both"):
        load(tmp_path / "c.npz", irf=[1.0], irf_fwhm=2.0)


def _simulated(fwhm, signal, bg, seed=0, shape=(50, 50), n_bins=200):
    rng = np.random.default_rng(seed)
    d = rng.integers(30, n_bins - 30, shape)
    lam = np.zeros((*shape, n_bins))
    lam[np.arange(shape[0])[:, None], np.arange(shape[1]), d] = signal
    return rng.poisson(convolve1d(lam, gaussian_irf(fwhm, length=61), axis=-1) + bg)


@pytest.mark.parametrize("fwhm", [2.0, 5.0, 10.0])
def test_estimate_irf_fwhm_recovers_gaussian_width(fwhm):
    # 2 signal photons/pixel and SBR ~ 1: measured errors were under 10 % at 2-10 bins
    # (seeds 0-3); 20 % tolerance covers seed-to-seed spread.
    y = _simulated(fwhm, 2.0, 0.01)
    assert abs(estimate_irf_fwhm(y) - fwhm) < 0.2 * fwhm


def test_estimate_irf_fwhm_no_signal_raises():
    y = np.random.default_rng(1).poisson(0.05, (40, 40, 200))
    with pytest.raises(SplidarError, match="irf_fwhm"):
        estimate_irf_fwhm(y)


def test_estimate_irf_fwhm_dense_cube_uses_a_pixel_subset(monkeypatch, caplog):
    # regression: above the pair budget it raised "too many photon pairs" (Art at PPP 64:
    # 53M pairs); now every k-th pixel is used. The budget is lowered to keep the test
    # small (the budget counts pairs of non-empty voxels: ~60 per pixel here).
    from splidar import _irf_width

    y = _simulated(4.0, 40.0, 0.01, shape=(40, 40))
    full = estimate_irf_fwhm(y)
    monkeypatch.setattr(_irf_width, "_PAIR_BUDGET", 20_000)
    with caplog.at_level("INFO", logger="splidar.io"):
        sub = estimate_irf_fwhm(y)
    assert "every" in caplog.text
    assert abs(sub - 4.0) < 0.15 * 4.0 and abs(full - 4.0) < 0.15 * 4.0
    assert sub == estimate_irf_fwhm(y)  # deterministic


def test_estimate_irf_fwhm_pools_wavelengths_at_lag_zero():
    # regression: pairs across wavelengths in one bin were dropped from lag 0, which
    # widened the width (Gaussian Art: 5.4 for 3.06) or hid the peak (exp-tail Art)
    rng = np.random.default_rng(2)
    d = rng.integers(30, 170, (40, 40))
    lam = np.zeros((40, 40, 3, 200))
    lam[np.arange(40)[:, None], np.arange(40), :, d] = 1.0
    y = rng.poisson(convolve1d(lam, gaussian_irf(3.0, length=31), axis=-1) + 0.003)
    assert abs(estimate_irf_fwhm(y) - 3.0) < 0.15 * 3.0


def test_estimate_irf_fwhm_tailed_pulse_gives_a_width_where_no_single_lag_peak(caplog):
    # regression: a long-tailed pulse (exp tail 2/25, FWHM 19.6 bins) at 2 photons per
    # pixel and SBR 1 spreads its pair excess over many lags, none 5 sd above the floor:
    # it raised "no IRF peak stands out". Now lags are pooled (and the window widened).
    # Seeds 0-5 gave 12-27 bins: a Gaussian-equivalent width, noisy at this signal.
    from splidar.irf import exp_tail_irf

    irf = exp_tail_irf(2.0, 25.0)
    rng = np.random.default_rng(0)
    d = rng.integers(60, 200, (32, 32))
    lam = np.zeros((32, 32, 300))
    lam[np.arange(32)[:, None], np.arange(32), d] = 1.0
    origin = -(irf.size // 2) + int(np.argmax(irf))
    lam = convolve1d(lam, irf / irf.sum(), axis=-1, origin=origin) + 1.0 / 300
    with caplog.at_level("INFO", logger="splidar.io"):
        w = estimate_irf_fwhm(rng.poisson(lam))
    assert "sums of" in caplog.text or "widening" in caplog.text
    assert 0.5 * 19.64 < w < 2.0 * 19.64


def test_estimate_irf_fwhm_dense_background_raises():
    # 100 background photons per pixel and no return: pooled lags find no peak either
    y = np.random.default_rng(3).poisson(0.5, (30, 30, 200))
    with pytest.raises(SplidarError, match="irf= .*irf_fwhm="):
        estimate_irf_fwhm(y)


def test_load_estimates_irf_when_missing(tmp_path):
    y = _simulated(6.0, 3.0, 0.01).astype(np.uint16)
    np.savez(tmp_path / "noirf.npz", counts=y)
    c = load(tmp_path / "noirf.npz", irf="estimate")  # the Gaussian (opt-out of the shape)
    assert c.metadata["irf_source"].startswith("estimated gaussian")
    fwhm = float(c.metadata["irf_source"].split("=")[1].split()[0])
    assert abs(fwhm - 6.0) < 1.2


# --------------------------------------------------------------------------------------
# libraries
# --------------------------------------------------------------------------------------
def test_load_library_formats(tmp_path):
    sig = np.array([[1.0, 0.5, 0.1], [0.2, 1.0, 0.3]])
    np.savez(tmp_path / "lib.npz", library=sig, class_names=np.array(["a", "b"]))
    lib = load_library(tmp_path / "lib.npz")
    np.testing.assert_array_equal(lib.signatures, sig)
    assert lib.class_names == ("a", "b")
    scipy.io.savemat(tmp_path / "lib.mat", {"signatures": sig})
    assert load_library(tmp_path / "lib.mat").n_classes == 2
    (tmp_path / "lib.csv").write_text("class,532,633,780\na,1,0.5,0.1\nb,0.2,1,0.3\n")
    lib = load_library(tmp_path / "lib.csv")
    np.testing.assert_array_equal(lib.signatures, sig)
    assert lib.class_names == ("a", "b")
    (tmp_path / "plain.csv").write_text("1,0.5,0.1\n0.2,1,0.3\n")
    assert load_library(tmp_path / "plain.csv").class_names == ("class 0", "class 1")
    (tmp_path / "lib.json").write_text(json.dumps({"a": [1, 0.5, 0.1], "b": [0.2, 1, 0.3]}))
    assert load_library(tmp_path / "lib.json").class_names == ("a", "b")
    (tmp_path / "lib2.json").write_text(json.dumps({"signatures": sig.tolist()}))
    np.testing.assert_array_equal(load_library(tmp_path / "lib2.json").signatures, sig)
    # a Cube accepts the path directly
    c = Cube(np.zeros((1, 1, 3, 5), np.uint16), irf=[1.0], library=tmp_path / "lib.csv")
    assert c.library.class_names == ("a", "b")


def test_load_library_errors(tmp_path):
    np.savez(tmp_path / "x.npz", other=np.ones(3))
    with pytest.raises(SplidarError, match="'other'"):
        load_library(tmp_path / "x.npz")
    (tmp_path / "x.yaml").write_text("a: 1")
    with pytest.raises(SplidarError, match="extension"):
        load_library(tmp_path / "x.yaml")
    (tmp_path / "bad.csv").write_text("a,1,2\nb,1\n")
    with pytest.raises(SplidarError, match="different lengths"):
        load_library(tmp_path / "bad.csv")


# --------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------
def test_load_errors(cube, tmp_path):
    with pytest.raises(SplidarError, match="no such file"):
        load(tmp_path / "missing.npz")
    (tmp_path / "x.tiff").write_bytes(b"\0")
    with pytest.raises(SplidarError, match="unknown file extension"):
        load(tmp_path / "x.tiff")
    np.savez(tmp_path / "bad.npz", counts=np.ones((4, 4)))
    with pytest.raises(SplidarError, match="shape"):
        load(tmp_path / "bad.npz", irf_fwhm=1.0)
    np.savez(tmp_path / "none.npz", a=np.ones(3), b=np.ones((2, 2)))
    with pytest.raises(SplidarError, match="holds no") as ei:
        load(tmp_path / "none.npz")
    assert "'a' (3,)" in str(ei.value)
    save(cube, tmp_path / "c.npz")
    with pytest.raises(SplidarError, match="photon-list"):
        load(tmp_path / "c.npz", bin_width=2)
    with pytest.raises(SplidarError, match="time_unit"):
        load(tmp_path / "c.npz", time_unit="hours")
    scipy.io.savemat(tmp_path / "ts.mat", {"Ts": _cells({(0, 0): [1, 2]}, (2, 2))})
    with pytest.raises(SplidarError, match="stop > start"):
        load(tmp_path / "ts.mat", window=(10, 2), irf_fwhm=1.0)
    with pytest.raises(SplidarError, match="bin_width"):
        load(tmp_path / "ts.mat", bin_width=-1, irf_fwhm=1.0)
    with pytest.raises(SplidarError, match="save"):
        save(cube, tmp_path / "c.mat")
    with pytest.raises(SplidarError, match="Cube"):
        save(np.zeros(3), tmp_path / "c.npz")
    (tmp_path / "junk.mat").write_bytes(b"not a mat file at all")
    with pytest.raises(SplidarError, match="MATLAB"):
        load(tmp_path / "junk.mat")


# --------------------------------------------------------------------------------------
# real data (skipped when ../shared/data is absent)
# --------------------------------------------------------------------------------------
@pytest.mark.realdata
def test_load_real_face(shared_data):
    # CPU time, not wall: the guard is against a slow reader, not against a loaded machine
    # (wall time reached 15 s for about 2 s of CPU with six agents on two cores)
    t0 = time.process_time()
    # bin_width=4 keeps the cube at 0.4 GB (T = 1751); the default 1-bin cube is 1.6 GB
    c = load(shared_data / "face" / "data_face.mat", bin_width=4, irf="estimate")
    elapsed = time.process_time() - t0
    assert c.shape == (340, 340, 1, 1751)
    assert c.photons_per_pixel() == pytest.approx(8.267, abs=0.01)  # all photons kept
    # photon-pair estimate: ~8 bins of 4 (about 31 raw bins, measured also at bin_width=1)
    fwhm = float(c.metadata["irf_source"].split("=")[1].split()[0])
    assert 4 < fwhm < 16
    assert elapsed < 10


@pytest.mark.realdata
def test_load_real_tower(shared_data):
    c = load(
        shared_data / "tower" / "tower.mat",
        time_unit="ps",
        window=(5_180_000, 5_380_000),
        bin_width=100,
        irf_fwhm=4.0,
    )
    assert c.shape == (160, 160, 1, 2000) and c.bin_width_ps == 100.0
    # the gate [mm, MM) holds all but the few photons stamped exactly at MM
    assert c.metadata["n_photons_total"] == 94534
    assert c.metadata["n_photons_in_window"] == int(c.counts.sum())
    assert 94534 - 10 <= int(c.counts.sum()) < 94534


@pytest.mark.realdata
def test_load_real_21km(shared_data):
    c = load(
        shared_data / "longrange-21km" / "21km_K11_night.mat",
        time_unit="ps",
        bin_width=100,
        irf="estimate",
    )
    assert c.shape[:3] == (256, 256, 1) and c.bin_width_ps == 100.0
    assert c.photons_per_pixel() == pytest.approx(640952 / 65536)
    # estimated IRF: ~10 bins of 100 ps (1.04 ns, the same at 20 ps bins)
    fwhm = float(c.metadata["irf_source"].split("=")[1].split()[0])
    assert 5 < fwhm < 20


@pytest.mark.realdata
def test_load_real_irf_sample(shared_data):
    irf = load_irf(shared_data / "irf-sample" / "data_supp.mat")
    assert irf.shape[0] == 1 and 15 < irf.shape[1] < 60
    assert irf[0, 0] > 0 and irf[0, -1] > 0


def test_estimate_irf_fwhm_too_few_pairs_raises_clear_error():
    # regression: with no photon pair inside any pixel, bincount returned int64 and the
    # triangle correction crashed with a casting error instead of saying what is wrong
    from splidar._irf_width import pair_lag_fwhm

    with pytest.raises(SplidarError, match="too few to estimate the IRF"):
        pair_lag_fwhm(np.array([0, 1]), np.array([3, 50]), np.array([1, 1]), 100, None)


def test_load_npz_fortran_order_and_big_endian_read_exactly(tmp_path):
    """The pickle-free .npz reader keeps memory order and byte order of every member."""
    counts = np.asfortranarray(np.arange(2 * 3 * 8, dtype=">u2").reshape(2, 3, 8))
    np.savez(tmp_path / "f.npz", counts=counts, irf=np.array([0.5, 1.0]))
    c = load(tmp_path / "f.npz")
    np.testing.assert_array_equal(c.counts[:, :, 0, :], counts)


def _weak_plane(seed, n=32, n_bins=300, signal=0.17, bg=0.83):
    """A tilted plane (depths 80-120 bins), exp tail 3/6 (FWHM 7.09), 0.17 signal and 0.83
    background photons per pixel: PPP 1 at SBR 0.2."""
    from splidar.irf import exp_tail_irf

    rng = np.random.default_rng(seed)
    irf = exp_tail_irf(3.0, 6.0)
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    lam = np.zeros((n, n, n_bins))
    lam[r, c, (80 + 40 * (r + c) / (2 * n - 2)).astype(int)] = signal
    origin = -(irf.size // 2) + int(np.argmax(irf))
    lam = convolve1d(lam, irf / irf.sum(), axis=-1, origin=origin) + bg / n_bins
    return rng.poisson(lam).astype(np.uint16)


def test_load_weak_signal_pools_pixel_blocks_for_the_irf(tmp_path, caplog):
    # regression: at 0.17 signal photons per pixel no single pixel's photon pairs show
    # the IRF (estimate_irf_fwhm raises) and load raised with it; the pair-lag width is
    # now measured on 2 x 2, 4 x 4, ... pixel blocks (a plane's neighbours share their
    # depth), logged and recorded. Seeds 1-4 gave 6.3-15.5 bins for 7.09 (the depth
    # spread within a block and the few pairs): the range below is 0.5-2.5 times it.
    from splidar.irf import irf_fwhm

    y = _weak_plane(1)
    with pytest.raises(SplidarError, match="no IRF peak"):
        estimate_irf_fwhm(y)
    np.savez(tmp_path / "weak.npz", counts=y)
    with caplog.at_level("WARNING", logger="splidar.io"):
        c = load(tmp_path / "weak.npz")
    assert "pixel blocks" in c.metadata["irf_source"]
    assert "pixel blocks" in caplog.text and "weak signal" in caplog.text
    assert 0.5 * 7.09 < float(irf_fwhm(c.irf[0])) < 2.5 * 7.09
    g = load(tmp_path / "weak.npz", irf="estimate")  # the Gaussian opt-out pools too
    assert g.metadata["irf_source"].startswith("estimated gaussian fwhm=")
    assert "pixel blocks" in g.metadata["irf_source"]


def test_pooled_fwhm_undetermined_at_every_level_warns_and_keeps_a_width(caplog):
    # irf24: 0.17 signal photons per pixel (seed 3): no level's pair-lag width differs
    # from 0 at 3 sigma (4 x 4 blocks, the first level with a pair peak: 6.3 bins,
    # bracket 0.5-14.1); the finest level's width is kept (the file still loads, as
    # before) and the warning says so
    from splidar.io import _pooled_fwhm

    with caplog.at_level("WARNING", logger="splidar.io"):
        fw, k = _pooled_fwhm(_weak_plane(3), 300, None)
    assert k == 4 and 0.5 * 7.09 < fw < 2.5 * 7.09
    assert "not determined" in caplog.text and "irf=" in caplog.text


def test_load_without_return_raises_naming_irf(tmp_path):
    # background only (0.83 photons per pixel, the weak plane's): no level of pooling
    # shows a pair peak; the error says so and names the options that fix it
    y = np.random.default_rng(1).poisson(0.83 / 300, (32, 32, 300)).astype(np.uint16)
    np.savez(tmp_path / "bg.npz", counts=y)
    with pytest.raises(SplidarError, match=r"no return found.*8 x 8.*irf= .*irf_fwhm="):
        load(tmp_path / "bg.npz")


def test_block_sum_adds_edge_blocks():
    from splidar.io import _block_index, _block_sum

    y = np.arange(5 * 3 * 4).reshape(5, 3, 4)
    s = _block_sum(y, 2)
    assert s.shape == (3, 2, 1, 4) and s.sum() == y.sum()
    np.testing.assert_array_equal(s[2, 1, 0], y[4, 2])
    np.testing.assert_array_equal(_block_index(np.array([0, 2, 4, 14]), 3, 2), [0, 1, 0, 5])


def test_load_weak_signal_rgb_float_counts_pool_blocks():
    # the pooling keeps float counts (no truncation) and pools the wavelengths of a
    # pixel (RGB): the weak plane's photons split over three wavelengths
    from splidar.io import _block_sum, _resolve_irf

    y = _weak_plane(1).astype(np.float64)
    rgb = np.zeros(y.shape[:2] + (3, y.shape[-1]))
    for i in range(3):
        rgb[:, :, i] = np.where(np.arange(y.shape[-1]) % 3 == i, y, 0.0)
    assert _block_sum(rgb * 0.5, 2).sum() == pytest.approx(0.5 * y.sum())
    irf, src = _resolve_irf(None, None, None, None, rgb, y.shape[-1])
    assert "pixel blocks" in src and irf.shape[0] in (1, 3)


def test_load_tiny_background_cube_raises_naming_irf():
    from splidar.io import _resolve_irf

    y = np.random.default_rng(0).poisson(0.01, (3, 3, 100))
    with pytest.raises(SplidarError, match=r"single pixels \(too few pixels.*irf="):
        _resolve_irf(None, None, None, None, y, 100)


def test_load_all_zero_counts_raises_no_photon(tmp_path):
    # an empty cube used to be reported as "only 0 photon pairs": say what is wrong instead
    p = tmp_path / "zero.npy"
    np.save(p, np.zeros((6, 6, 50), np.uint16))
    with pytest.raises(SplidarError, match="hold no photon.*time window"):
        load(p)
