"""Files written with other groups' conventions (benchmarks/bench_foreign_cubes.py): axis
orders, attributes, flat pixel indices, IRFs as text with a header and a time column."""

from __future__ import annotations

import json
import logging

import h5py
import numpy as np
import pytest
import scipy.io

from splidar import SplidarError, load
from splidar.cli import main
from splidar.io import load_irf


def _cube(rows=5, cols=6, L=3, T=40, seed=0):
    """Counts (rows, cols, L, T) whose every voxel is distinct (so axis mix-ups show)."""
    rng = np.random.default_rng(seed)
    return rng.permutation(rows * cols * L * T).reshape(rows, cols, L, T).astype(np.uint16)


def _pulse(n=20, peak=8, width=2.0):
    return np.exp(-0.5 * ((np.arange(n) - peak) / width) ** 2)


def test_load_wavelength_axis_reads_wavelength_first_hdf5(tmp_path):
    y = _cube()
    p = tmp_path / "multi.h5"
    with h5py.File(p, "w") as f:
        f["data/counts"] = np.moveaxis(y, 2, 0)  # (L, rows, cols, T)
    cube = load(p, variable="data/counts", wavelength_axis=0, irf_fwhm=2)
    np.testing.assert_array_equal(cube.counts, y)
    # time first and wavelength last: (T, rows, cols, L)
    q = tmp_path / "tl.npy"
    np.save(q, np.transpose(y, (3, 0, 1, 2)))
    cube = load(q, time_axis=0, wavelength_axis=3, irf_fwhm=2)
    np.testing.assert_array_equal(cube.counts, y)


def test_load_wavelength_axis_errors_name_the_option(tmp_path):
    p = tmp_path / "c.npy"
    np.save(p, _cube()[:, :, 0, :])
    with pytest.raises(SplidarError, match="`wavelength_axis` applies to a 4-D"):
        load(p, wavelength_axis=0, irf_fwhm=2)
    np.save(p, _cube())
    with pytest.raises(SplidarError, match="name the same axis"):
        load(p, wavelength_axis=3, irf_fwhm=2)
    with pytest.raises(SplidarError, match="`wavelength_axis` must be an axis"):
        load(p, wavelength_axis=4, irf_fwhm=2)


def test_load_warns_when_first_axis_looks_like_wavelengths(tmp_path, caplog):
    p = tmp_path / "lrct.npy"
    np.save(p, np.zeros((3, 20, 24, 30), np.uint16))
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(p, irf_fwhm=2)
    assert "pass wavelength_axis=0" in caplog.text
    caplog.clear()
    np.save(p, np.zeros((20, 24, 3, 30), np.uint16))  # (rows, cols, L, T): no warning
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(p, irf_fwhm=2)
    assert "wavelength_axis" not in caplog.text


def test_load_uses_hdf5_attributes_of_the_counts_and_their_group(tmp_path):
    y = _cube(L=1)[:, :, 0, :]
    p = tmp_path / "scan.h5"
    with h5py.File(p, "w") as f:
        ds = f.create_dataset("counts", data=y)
        ds.attrs["bin_width_ps"] = 16.0
        g = f.create_group("scan")
        g["histograms"] = np.moveaxis(y, -1, 0)
        g["irf"] = _pulse()
        g.attrs["bin_width_ps"] = 4.0
    assert load(p, irf_fwhm=2).bin_width_ps == 16.0
    cube = load(p, variable="scan/histograms", time_axis=0)
    assert cube.bin_width_ps == 4.0
    np.testing.assert_array_equal(cube.counts[:, :, 0], y)
    assert cube.metadata["irf_source"] == "file"
    assert int(np.argmax(cube.irf[0])) == 8


def test_load_photon_table_with_flat_pixel_column_and_size_numbers(tmp_path):
    rows, cols = 3, 4
    pix = np.array([0, 5, 5, 11, 7], np.int32)
    t = np.array([1000, 1016, 1020, 1100, 1190], np.int64)
    p = tmp_path / "photons.npz"
    np.savez(p, pixel=pix, t_ps=t, n_rows=np.int32(rows), n_cols=np.int32(cols))
    cube = load(p, window=(1000, 1200), bin_width=16, irf_fwhm=1)
    assert cube.shape == (rows, cols, 1, 13)
    assert cube.bin_width_ps == 16.0
    want = np.zeros((rows, cols, 13), np.int64)
    for i, ti in zip(pix, t, strict=True):
        want[i // cols, i % cols, (ti - 1000) // 16] += 1
    np.testing.assert_array_equal(cube.counts[:, :, 0], want)
    # the size as `shape`, height / width names
    np.savez(p, pixel_index=pix, time_ps=t, shape=np.array([rows, cols]))
    assert load(p, window=(1000, 1200), bin_width=16, irf_fwhm=1).shape == (3, 4, 1, 13)
    np.savez(p, pix=pix, toa_ps=t, height=rows, width=cols)
    assert load(p, window=(1000, 1200), bin_width=16, irf_fwhm=1).shape == (3, 4, 1, 13)


def test_load_photon_table_flat_pixel_errors_say_what_to_add(tmp_path):
    p = tmp_path / "photons.npz"
    np.savez(p, pixel=np.array([1, 2]), t_ps=np.array([5, 6]))
    with pytest.raises(SplidarError, match="no image size: add a `shape` array"):
        load(p, irf_fwhm=1)
    np.savez(p, pixel=np.array([1, 12]), t_ps=np.array([5, 6]), n_rows=3, n_cols=4)
    with pytest.raises(SplidarError, match="1-based .MATLAB. indices"):
        load(p, irf_fwhm=1)


def test_load_irf_text_with_header_and_time_column(tmp_path):
    g = _pulse()
    p = tmp_path / "irf.csv"
    lines = ["time_ps,counts"] + [f"{4 * k},{v:.8g}" for k, v in enumerate(g)]
    p.write_text("\n".join(lines) + "\n")
    np.testing.assert_allclose(load_irf(p)[0], g / 1.0, rtol=1e-6)  # the time column dropped
    q = tmp_path / "irf.txt"  # no header: an evenly spaced first column is the time axis
    np.savetxt(q, np.c_[0.5 + 0.004 * np.arange(g.size), g])
    np.testing.assert_allclose(load_irf(q)[0], g, rtol=1e-6)
    r = tmp_path / "irf2.csv"  # two wavelengths, no time column: kept as (L, n)
    np.savetxt(r, np.c_[g, g[::-1]], delimiter=",")
    assert load_irf(r).shape == (2, g.size)
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,x\n")
    with pytest.raises(SplidarError, match="cannot read the IRF 'bad.csv' as numbers"):
        load_irf(bad)


def test_load_resamples_an_irf_text_file_to_the_cube_bin_width(tmp_path):
    fine = _pulse(n=160, peak=64, width=16.0)  # 2 ps samples: FWHM 75 ps
    p = tmp_path / "irf.csv"
    p.write_text("time_ps,counts\n" + "".join(f"{2 * k},{v}\n" for k, v in enumerate(fine)))
    c = tmp_path / "scan.npy"
    np.save(c, np.ones((4, 4, 100), np.uint16))
    cube = load(c, irf=str(p), bin_width_ps=16.0)
    g = cube.irf[0]
    # 160 samples of 2 ps in bins of 16 ps, the peak sample (64) centred in its bin:
    # [60.5, 68.5) samples; partial end bins [0, 4.5) and [156.5, 160)
    assert g.size == 21 and int(np.argmax(g)) == 8
    np.testing.assert_allclose(g.sum(), 1.0, rtol=1e-12)
    np.testing.assert_allclose(g[1:8], g[9:16][::-1], rtol=1e-6)  # symmetric stays so (full bins)
    assert "resampled from 2 ps to 16 ps" in cube.metadata["irf_source"]
    same = load(c, irf=str(p), bin_width_ps=2.0)  # same grid: as written (cropped to T)
    assert same.irf.shape[1] == 99 and "resampled" not in same.metadata["irf_source"]


def test_cli_irf_variable_and_wavelength_axis(tmp_path, capsys):
    y = _cube(rows=6, cols=7, L=2, T=48)
    p = tmp_path / "lego.mat"
    irf = np.stack([_pulse(), _pulse(width=3.0)], axis=1)  # (n, L) MATLAB columns
    scipy.io.savemat(p, {"Y": np.moveaxis(y, 2, 0), "IRF": irf, "lambda_nm": [500.0, 600.0]})
    args = ["info", str(p), "--variable", "Y", "--irf", str(p), "--json"]
    assert main(args + ["--irf-variable", "IRF", "--wavelength-axis", "0"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["shape"] == [6, 7, 2, 48] and info["irf_samples"] == 20
    # without --irf-variable the IRF is ambiguous (IRF, lambda_nm): the message names it
    assert main(args) == 1
    err = capsys.readouterr().err
    # the CLI names its own option and not the Python function's keyword
    assert "--irf-variable" in err and "load_irf" not in err and "--variable" not in err
    with pytest.raises(SplidarError, match=r"irf_variable=.*variable= when calling load_irf"):
        load(p, variable="Y", irf=p, wavelength_axis=0)
