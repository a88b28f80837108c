"""Hints on the bin width from the pulse's width (``splidar._bin_hints``): ``load``'s
warning when the IRF's FWHM spans many bins, and the memory guard's suggested bin width
for photon lists that knows the pulse. Hints only: nothing is changed."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from splidar import SplidarError, load
from splidar.cli import main
from splidar.irf import gaussian_irf

HINT = "detection needs about 4 bins per FWHM"


def _photons(path, *, fwhm, span, shape=(32, 32), signal=20, background=20, step=None, seed=0):
    """Flat photon lists (``times``, ``pixel_index``, ``shape``) of one return a pixel:
    Gaussian pulses of ``fwhm`` (time units) at random depths in ``[0, span)``, plus
    uniform background; times rounded to multiples of ``step`` (a TDC's quantum)."""
    rng = np.random.default_rng(seed)
    n_pix = shape[0] * shape[1]
    depth = rng.uniform(0.1 * span, 0.9 * span, n_pix)
    pix_s = np.repeat(np.arange(n_pix), signal)
    t_s = depth[pix_s] + rng.normal(0.0, fwhm / 2.3548, pix_s.size)
    pix_b = rng.integers(0, n_pix, n_pix * background)
    t_b = rng.uniform(0.0, span, pix_b.size)
    t = np.concatenate([t_s, t_b])
    t = np.round(t / step) * step if step else np.round(t)
    t = np.clip(t, 0, span - 1).astype(np.int64)
    pix = np.concatenate([pix_s, pix_b])
    np.savez(path, times=t, pixel_index=pix, shape=np.array(shape))
    return path


def _hints(caplog):
    return [r for r in caplog.records if HINT in r.getMessage()]


def test_grouping_hint_photon_lists_names_the_bin_width(tmp_path, caplog):
    # an IRF of FWHM 24 bins: grouping by 6 keeps 4 bins per FWHM and T / 6
    f = _photons(tmp_path / "p.npz", fwhm=24.0, span=1200)
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        cube = load(f, irf_fwhm=24.0)
    (rec,) = _hints(caplog)
    msg = rec.getMessage()
    assert "bin_width=6 (6 of the current bins)" in msg
    assert f"T = {-(-cube.n_bins // 6)} instead of {cube.n_bins} bins" in msg
    assert "about 6x less memory and time" in msg and "nothing is changed" in msg
    assert cube.n_bins == 1200 and cube.metadata["bin_width"] == 1.0  # a hint only


def test_grouping_hint_narrow_irf_is_quiet(tmp_path, caplog):
    # FWHM 8 bins (under HINT_ABOVE): no hint
    f = _photons(tmp_path / "p.npz", fwhm=8.0, span=600)
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(f, irf_fwhm=8.0)
    assert not _hints(caplog)


def test_grouping_hint_histogram_file_names_the_grouping(tmp_path, caplog):
    # a binned cube has no bin_width option: the hint says how to group k bins
    rng = np.random.default_rng(1)
    y = rng.poisson(0.05, (16, 16, 400)).astype(np.uint16)
    y[..., 200] += 5
    np.save(tmp_path / "c.npy", y)
    np.save(tmp_path / "irf.npy", gaussian_irf(20.0))
    with caplog.at_level(logging.WARNING, logger="splidar.io"):
        load(tmp_path / "c.npy", irf=str(tmp_path / "irf.npy"))
    (rec,) = _hints(caplog)
    assert "sum every 5 adjacent bins" in rec.getMessage()
    assert "resample_irf(irf, 1, 5)" in rec.getMessage()


def _suggested(err) -> tuple[float, int]:
    m = re.search(r"`bin_width` (\S+) gives T = (\d+) bins", str(err.value))
    assert m is not None, str(err.value)
    return float(m[1]), int(m[2])


def test_memory_hint_measures_the_pulse_on_the_photons(tmp_path):
    # 32 x 32 pixels x 5e6 bins of 1 ps: 9.5 GiB, refused. Memory alone asks for 10 ps;
    # the pulse (FWHM 500 ps), measured on the photons' pairs, asks for 100 ps (5 bins
    # per FWHM: at least 4), and the message says why
    f = _photons(tmp_path / "p.npz", fwhm=500.0, span=5_000_000)
    with pytest.raises(SplidarError, match="GiB") as err:
        load(f, time_unit="ps", window=(0, 5_000_000))
    assert _suggested(err) == (100.0, 50_000)
    m = re.search(r"the pulse's FWHM, about (\d+) \(from the photons'", str(err.value))
    assert m is not None and 400 < int(m[1]) < 600, str(err.value)
    assert "detection needs about 4, finer bins cost memory and time" in str(err.value)


def test_memory_hint_quantised_time_tags_read_at_a_coarser_width(tmp_path):
    # time tags in steps of 25 ps read at the 10 ps memory allows: every other bin is
    # empty and lag 0 alone stood above half the peak (the tower file: "5 ps" for about
    # 600); coarser trial widths read the pulse
    f = _photons(tmp_path / "p.npz", fwhm=500.0, span=5_000_000, step=25)
    with pytest.raises(SplidarError, match="GiB") as err:
        load(f, time_unit="ps", window=(0, 5_000_000))
    assert _suggested(err)[0] == 100.0, str(err.value)
    m = re.search(r"the pulse's FWHM, about (\d+) \(from the photons'", str(err.value))
    assert m is not None and 400 < int(m[1]) < 600, str(err.value)
    assert "binned at 10)" not in str(err.value)  # not at the 10 ps memory allows


def test_memory_hint_uses_irf_fwhm(tmp_path):
    # irf_fwhm (bins of the width asked for) gives the pulse: 300 x 1 ps -> 50 ps bins
    # (6 per FWHM), and the irf_fwhm to pass in those bins
    f = _photons(tmp_path / "p.npz", fwhm=300.0, span=5_000_000, signal=2, background=1)
    with pytest.raises(SplidarError, match="GiB") as err:
        load(f, time_unit="ps", window=(0, 5_000_000), irf_fwhm=300.0)
    assert _suggested(err)[0] == 50.0
    assert "about 300 (`irf_fwhm`), then spans 6 bins (irf_fwhm=6 in those bins)" in str(err.value)


def test_memory_hint_pulse_finer_than_memory_allows_names_the_window(tmp_path):
    # a 3 ps pulse over 5 us at 1 ps: the 10 ps that fit leave it under a bin
    f = _photons(tmp_path / "p.npz", fwhm=500.0, span=5_000_000, signal=2, background=1)
    with pytest.raises(SplidarError, match="GiB") as err:
        load(f, time_unit="ps", window=(0, 5_000_000), irf_fwhm=3.0)
    assert _suggested(err)[0] == 10.0
    assert "then spans 0.3 bins; a narrower `window` allows finer bins" in str(err.value)


def test_memory_hint_unknown_pulse_keeps_the_memory_width(tmp_path):
    # no pulse in the photons (background only): the width that fits, said so
    f = _photons(tmp_path / "p.npz", fwhm=500.0, span=5_000_000, signal=0)
    with pytest.raises(SplidarError, match="GiB") as err:
        load(f, time_unit="ps", window=(0, 5_000_000))
    assert _suggested(err)[0] == 10.0
    assert "the pulse's width is not known" in str(err.value)


def test_bin_lists_available_memory_names_a_pulse_bin_width(tmp_path, monkeypatch):
    # under the 8 GiB cap but over the memory available (SPLIDAR_MEMORY_LIMIT): the
    # available-memory message also names a bin width that suits the pulse
    f = _photons(tmp_path / "p.npz", fwhm=500.0, span=100_000, shape=(32, 32))
    monkeypatch.setenv("SPLIDAR_MEMORY_LIMIT", "50M")  # the cube: 1024 x 1e5 x 2 = 195 MiB
    with pytest.raises(SplidarError, match="is available") as err:
        load(f, time_unit="ps", window=(0, 100_000))
    width, _ = _suggested(err)
    assert width == 100.0 and "detection needs about 4" in str(err.value)


def test_main_info_memory_guard_prints_one_line_with_the_pulse_width(tmp_path, capsys):
    f = _photons(tmp_path / "p.npz", fwhm=500.0, span=5_000_000)
    assert main(["info", str(f), "--time-unit", "ps", "--window", "0", "5000000"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("splidar: error: binning into")
    assert "--bin-width 100 gives T = 50000 bins" in err and "Traceback" not in err


def test_main_info_grouping_hint_names_the_option(tmp_path, capsys):
    f = _photons(tmp_path / "p.npz", fwhm=24.0, span=1200)
    assert main(["info", str(f), "--irf-fwhm", "24"]) == 0
    err = capsys.readouterr().err
    (line,) = [x for x in err.splitlines() if HINT in x]
    assert line.startswith("splidar: ") and "--bin-width 6 (6 of the current bins)" in line
