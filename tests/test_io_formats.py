"""Files as a lab has them: other axis orders, bare Zarr arrays, bad counts, photon tables,
degenerate cubes (one pixel, too few bins).

Each file is written by the format's own library (NumPy, h5py, SciPy, zarr) and read
back through :func:`splidar.load` or ``splidar run``; a file splidar cannot read must
stop with one message naming the option that fixes it.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from splidar import SplidarError, load
from splidar.cli import main


@pytest.fixture(scope="module")
def counts():
    """A small (rows, cols, T) cube: one return per pixel over a weak background."""
    rng = np.random.default_rng(3)
    lam = np.full((9, 7, 40), 0.05)
    for r in range(9):
        for c in range(7):
            lam[r, c, 12 + r + c - 2 : 12 + r + c + 3] += [1, 3, 5, 3, 1]
    return rng.poisson(lam).astype(np.uint16)


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


# --------------------------------------------------------------------------------------
# axis order
# --------------------------------------------------------------------------------------
def test_load_time_axis_moves_time_last(counts, tmp_path):
    h5py = pytest.importorskip("h5py")
    p = tmp_path / "tfirst.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("counts", data=np.moveaxis(counts, -1, 0))  # (T, rows, cols)
    cube = load(p, time_axis=0, irf_fwhm=3)
    np.testing.assert_array_equal(cube.counts[:, :, 0, :], counts)


def test_load_time_first_shape_warns_and_time_axis_silences(counts, tmp_path, caplog):
    p = tmp_path / "tfirst.npy"
    np.save(p, np.moveaxis(counts, -1, 0))  # (40, 9, 7): time first
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        cube = load(p, irf_fwhm=3)
    assert cube.shape == (40, 9, 1, 7)  # the default reads time last, and says so
    assert any("time_axis=0" in m and "(40, 9, 7)" in m for m in _warnings(caplog))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(p, irf_fwhm=3, time_axis=-1)  # confirmed: no warning about the axes
    assert not [m for m in _warnings(caplog) if "time_axis" in m]


def test_load_time_last_shape_does_not_warn(counts, tmp_path, caplog):
    p = tmp_path / "c.npy"
    np.save(p, counts)
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(p, irf_fwhm=3)
    assert not _warnings(caplog)


def test_load_time_axis_out_of_range_names_the_shape(counts, tmp_path):
    p = tmp_path / "c.npy"
    np.save(p, counts)
    with pytest.raises(SplidarError, match=r"`time_axis`.*\(9, 7, 40\).*-3 to 2; got 3"):
        load(p, time_axis=3, irf_fwhm=3)


def test_main_run_time_axis_error_names_the_option(counts, tmp_path, capsys):
    p = tmp_path / "c.npy"
    np.save(p, counts)
    rc = main(["run", str(p), "--time-axis", "5", "--irf-fwhm", "3", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc != 0 and "--time-axis must be an axis" in err and "Traceback" not in err


# --------------------------------------------------------------------------------------
# bad counts: one message, before any IRF estimate
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (lambda c: np.where(c > 3, np.nan, c.astype(float)), "NaN"),
        (lambda c: c.astype(np.int64) - 1, "negative"),
        (lambda c: c * 0.5, "non-integer"),
    ],
)
def test_load_bad_counts_refused_before_irf_estimate(counts, tmp_path, caplog, bad, match):
    p = tmp_path / "bad.npz"
    np.savez(p, counts=bad(counts))
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        with pytest.raises(SplidarError, match=rf"'bad.npz': `counts` holds .*{match}"):
            load(p)
    assert not _warnings(caplog)  # no IRF estimated from data about to be refused


def test_load_integer_valued_float_counts_become_integers(counts, tmp_path):
    p = tmp_path / "f.npz"
    np.savez(p, counts=counts.astype(np.float64))
    cube = load(p, irf_fwhm=3)
    assert cube.counts.dtype.kind == "u"
    np.testing.assert_array_equal(cube.counts[:, :, 0, :], counts)


# --------------------------------------------------------------------------------------
# Zarr
# --------------------------------------------------------------------------------------
def test_load_zarr_bare_array_reads_counts(counts, tmp_path):
    zarr = pytest.importorskip("zarr")
    p = tmp_path / "bare.zarr"
    z = zarr.open_array(str(p), mode="w", shape=counts.shape, dtype=counts.dtype, chunks=(3, 7, 40))
    z[...] = counts
    cube = load(p, irf_fwhm=3)
    np.testing.assert_array_equal(np.asarray(cube.counts)[:, :, 0, :], counts)


def test_load_zarr_variable_selects_array(counts, tmp_path):
    zarr = pytest.importorskip("zarr")
    p = tmp_path / "g.zarr"
    g = zarr.open_group(str(p), mode="w")
    g.create_array("histograms", data=counts, chunks=(3, 7, 40))
    with pytest.raises(SplidarError, match=r"no `counts` array.*\['histograms'\].*variable="):
        load(p, irf_fwhm=3)
    cube = load(p, variable="histograms", irf_fwhm=3)
    np.testing.assert_array_equal(np.asarray(cube.counts)[:, :, 0, :], counts)


# --------------------------------------------------------------------------------------
# photon tables: one photon per line (CSV, .npz / HDF5 columns)
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def photons():
    """(row, col, time in ps, wavelength channel) of photons on a 5 x 4 image."""
    rng = np.random.default_rng(5)
    n = 400
    row, col = rng.integers(0, 5, n), rng.integers(0, 4, n)
    row[0], col[0] = 4, 3  # the image size comes from the largest indices
    t = rng.integers(1000, 3000, n)
    wl = rng.integers(0, 2, n)
    return row, col, t, wl


def test_load_photon_table_csv_with_unit_in_header(photons, tmp_path):
    row, col, t, _ = photons
    p = tmp_path / "photons.csv"
    lines = ["row,col,time_ps"] + [f"{r},{c},{x}" for r, c, x in zip(row, col, t, strict=True)]
    p.write_text("\n".join(lines) + "\n")
    cube = load(p, window=(1000, 3000), bin_width=100, irf_fwhm=2)
    assert cube.shape == (5, 4, 1, 20) and cube.bin_width_ps == 100.0  # ps from the header
    ref = np.zeros((5, 4, 20), int)
    np.add.at(ref, (row, col, (t - 1000) // 100), 1)
    np.testing.assert_array_equal(cube.counts[:, :, 0, :], ref)


def test_load_photon_table_wavelength_column_gives_wavelength_axis(photons, tmp_path):
    row, col, t, wl = photons
    p = tmp_path / "photons.npz"
    np.savez(p, x=col, y=row, t_ns=t / 1000.0, wavelength=np.where(wl == 0, 532.0, 1550.0))
    cube = load(p, window=(1.0, 3.0), bin_width=0.1, irf_fwhm=2)
    assert cube.shape == (5, 4, 2, 20) and cube.bin_width_ps == pytest.approx(100.0)
    np.testing.assert_array_equal(cube.wavelengths_nm, [532.0, 1550.0])
    ref = np.zeros((5, 4, 2, 20), int)
    np.add.at(ref, (row, col, wl, np.floor((t / 1000.0 - 1.0) / 0.1).astype(int)), 1)
    np.testing.assert_array_equal(cube.counts, ref)


def test_load_photon_table_hdf5_group(photons, tmp_path):
    h5py = pytest.importorskip("h5py")
    row, col, t, _ = photons
    p = tmp_path / "photons.h5"
    with h5py.File(p, "w") as f:
        g = f.create_group("scan/photons")
        g["row"], g["col"], g["timestamp"] = row, col, t
    cube = load(p, window=(1000, 3000), bin_width=100, irf_fwhm=2)
    assert cube.shape == (5, 4, 1, 20) and cube.bin_width_ps is None  # unit unknown: bins
    assert int(cube.counts.sum()) == t.size


def test_load_photon_table_without_header_names_the_form(tmp_path):
    p = tmp_path / "photons.csv"
    p.write_text("0,1,1200\n1,1,1300\n")
    with pytest.raises(SplidarError, match=r"no header row.*row,col,time_ps"):
        load(p)


def test_cli_names_quoted_value_becomes_option_and_value():
    from splidar.cli import _cli_names

    msg = "pass irf= or irf_fwhm= to override, irf='estimate' for a Gaussian, time_axis=-1 or 0"
    assert _cli_names(msg) == (
        "pass --irf or --irf-fwhm to override, --irf estimate for a Gaussian, --time-axis -1 or 0"
    )


# --------------------------------------------------------------------------------------
# degenerate but valid inputs through `splidar run`
# --------------------------------------------------------------------------------------
def test_main_run_single_pixel_writes_figures(counts, tmp_path):
    p = tmp_path / "small.npz"
    np.savez(p, counts=counts[:1, :1])  # contours and axis limits of one pixel
    out = tmp_path / "o"
    assert main(["run", str(p), "--irf-fwhm", "2", "--no-view", "--out", str(out), "-q"]) == 0
    assert (out / "figures" / "detection_slice.png").is_file()
    assert (out / "figures" / "point_cloud.png").is_file()


def test_main_run_too_few_bins_names_the_options(counts, tmp_path, capsys):
    p = tmp_path / "t2.npz"
    np.savez(p, counts=counts[:, :, 20:22])
    rc = main(["run", str(p), "--irf-fwhm", "2", "--out", str(tmp_path / "o"), "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and "T = 2 time bin(s)" in err and "--time-axis" in err


@pytest.mark.parametrize(
    ("bw", "hint"), [(0.016, "bin_width_ps=16 "), (16e6, "bin_width_ps=16000 ")]
)
def test_load_implausible_bin_width_warns_with_the_other_unit(counts, tmp_path, caplog, bw, hint):
    p = tmp_path / "c.npy"
    np.save(p, counts)
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        cube = load(p, irf_fwhm=3, bin_width_ps=bw)
    assert cube.bin_width_ps == bw  # used as given, with a warning
    assert any(hint in m for m in _warnings(caplog))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(p, irf_fwhm=3, bin_width_ps=16)
    assert not _warnings(caplog)


# --------------------------------------------------------------------------------------
# splidar info
# --------------------------------------------------------------------------------------
def test_main_info_lists_variables_and_reading(counts, tmp_path, capsys):
    h5py = pytest.importorskip("h5py")
    p = tmp_path / "scan.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("measurement/histograms", data=np.moveaxis(counts, -1, 0))
    args = ["info", str(p), "--variable", "measurement/histograms", "--time-axis", "0"]
    assert main([*args, "--irf-fwhm", "3", "--bin-width-ps", "16"]) == 0
    out = capsys.readouterr().out
    assert "measurement/histograms: (40, 9, 7) uint16" in out
    assert "read as: 9 x 7 pixels, 1 wavelength(s), 40 time bins" in out
    assert f"photons: {int(counts.sum())}" in out and "16 ps" in out
    assert not (tmp_path / "scan-splidar").exists()  # nothing written


def test_main_info_json_is_the_only_stdout(photons, tmp_path, capsys):
    import json

    row, col, t, _ = photons
    p = tmp_path / "photons.npz"
    np.savez(p, row=row, col=col, time_ps=t)
    assert main(["info", str(p), "--irf-fwhm", "2", "--bin-width", "100", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["shape"][:3] == [5, 4, 1] and s["bin_width_ps"] == 100.0
    assert s["variables"]["time_ps"] == "(400,) int64" and s["photons"] == t.size


def test_load_hdf5_group_irf_beside_the_counts_is_used(counts, tmp_path):
    h5py = pytest.importorskip("h5py")
    p = tmp_path / "nested.h5"
    irf = np.array([1.0, 3.0, 5.0, 3.0, 1.0])
    with h5py.File(p, "w") as f:
        f["scan/histograms"], f["scan/irf"], f["scan/bin_width_ps"] = counts, irf, 16.0
    cube = load(p, variable="scan/histograms")
    np.testing.assert_allclose(cube.irf[0], irf / irf.sum())  # the group's IRF, not estimated
    assert cube.bin_width_ps == 16.0 and "irf_source" in cube.metadata
    assert cube.metadata["irf_source"] == "file"


def test_main_info_bin_width_m_is_the_round_trip_time(counts, tmp_path, capsys):
    import json

    p = tmp_path / "c.npy"
    np.save(p, counts)
    assert main(["info", str(p), "--irf-fwhm", "3", "--bin-width-m", "0.0024", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["bin_width_ps"] == pytest.approx(16.011077, rel=1e-6)  # 2 x 2.4 mm / c


def test_load_photon_table_semicolons_read(tmp_path):
    p = tmp_path / "photons.csv"
    p.write_text("Row;Col;Time (ns)\n0;1;1.0\n1;0;1.5\n1;1;2.5\n")
    cube = load(p, window=(1.0, 3.0), bin_width=0.5, irf_fwhm=1)
    assert cube.shape == (2, 2, 1, 4) and cube.bin_width_ps == 500.0
    assert cube.counts[0, 1, 0, 0] == cube.counts[1, 0, 0, 1] == cube.counts[1, 1, 0, 3] == 1


def test_load_table_without_known_columns_names_the_table_form(tmp_path):
    p = tmp_path / "other.csv"
    p.write_text("a,b,c\n0,1,2\n")
    with pytest.raises(SplidarError, match=r"photon table: 1-D columns named row, col and time"):
        load(p)
