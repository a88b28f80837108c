"""Tests of splidar.vendor (PicoQuant .ptu via ptufile, Becker & Hickl .sdt via sdtfile) and
of .npy files wherever an array file is read.

Every file is written by the test itself: PTU files by the vendor library's own writer
(``ptufile.imwrite``). sdtfile cannot write, so the SDT files are assembled by
``_write_sdt`` below from sdtfile's own record definitions (FILE_HEADER, MEASURE_INFO,
BLOCK_HEADER); they are test fixtures in the documented B&H layout, not output of
B&H software.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

import splidar
from splidar import SplidarError
from splidar.io import load_irf, load_library

# --------------------------------------------------------------------------------------
# PicoQuant PTU
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_cube():
    from splidar.scenes import multispectral_scene

    sim = multispectral_scene((20, 20), n_bins=96).simulate(ppp=8, sbr=1, rng=3)
    return sim.cube


def _write_ptu(path, counts, bin_width_ps, **kw):
    ptufile = pytest.importorskip("ptufile")
    n_bins = counts.shape[-1]
    tcspc = bin_width_ps * 1e-12
    # one laser period = the histogram's T bins, so the file's histogram has T bins
    ptufile.imwrite(path, counts, n_bins * tcspc, tcspc, **kw)
    return path


def test_load_ptu_same_points_as_npz(scene_cube, tmp_path):
    cube = scene_cube
    counts = np.ascontiguousarray(cube.counts.astype(np.uint16))
    # (rows, cols, L, T) is ptufile's 'YXCH': the L wavelengths are its 4 channels
    ptu = _write_ptu(tmp_path / "scene.ptu", counts, cube.bin_width_ps)
    npz = tmp_path / "scene.npz"
    splidar.save(cube, npz)

    from_ptu = splidar.load(ptu, irf=cube.irf, wavelengths_nm=cube.wavelengths_nm)
    from_npz = splidar.load(npz)
    assert from_ptu.shape == from_npz.shape == cube.shape
    np.testing.assert_array_equal(from_ptu.counts, from_npz.counts)
    assert from_ptu.bin_width_ps == from_npz.bin_width_ps == cube.bin_width_ps
    assert from_ptu.metadata["reader"].startswith("ptufile")
    assert from_ptu.metadata["channel_ids"] == [0, 1, 2, 3]

    lib = cube.library
    a = splidar.process(from_ptu, library=lib).points
    b = splidar.process(from_npz, library=lib).points
    assert len(a) == len(b) > 0.5 * cube.n_rows * cube.n_cols
    for name in ("row", "col", "depth_bin", "depth_m", "label", "intensity", "layer"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_read_ptu_channels_detectors_sum_or_select(tmp_path):
    from splidar.vendor import read_ptu

    rng = np.random.default_rng(0)
    counts = rng.poisson(0.4, (5, 6, 2, 64)).astype(np.uint16)
    ptu = _write_ptu(tmp_path / "two.ptu", counts, 16.0)
    h = read_ptu(ptu)
    np.testing.assert_array_equal(h.counts, counts)
    assert h.channels == (0, 1) and h.bin_width_ps == 16.0
    det = read_ptu(ptu, channels="detectors")
    assert det.channels == ()
    np.testing.assert_array_equal(det.counts, counts.sum(axis=2, keepdims=True))
    one = splidar.load(ptu, channels=1, irf_fwhm=2)
    np.testing.assert_array_equal(one.counts, counts[:, :, 1:2])
    with pytest.raises(SplidarError, match=r"channel\(s\) \[5\].*holds channels \[0, 1\]"):
        read_ptu(ptu, channels=[0, 5])
    with pytest.raises(SplidarError, match="`channels` must be"):
        read_ptu(ptu, channels="spectra")


def test_read_ptu_frames_summed_or_one(tmp_path):
    from splidar.vendor import read_ptu

    rng = np.random.default_rng(1)
    frames = rng.poisson(0.3, (3, 4, 5, 32)).astype(np.uint16)  # 'TYXH': 3 frames
    ptu = _write_ptu(tmp_path / "frames.ptu", frames, 50.0, has_frames=True)
    h = read_ptu(ptu)
    assert h.metadata["frames_in_file"] == 3
    np.testing.assert_array_equal(h.counts[:, :, 0], frames.sum(axis=0))
    np.testing.assert_array_equal(read_ptu(ptu, frame=2).counts[:, :, 0], frames[2])
    with pytest.raises(SplidarError, match="`frame` 3 is out of range"):
        read_ptu(ptu, frame=3)


def test_load_irf_ptu_sums_pixels(tmp_path):
    rng = np.random.default_rng(2)
    counts = np.zeros((3, 3, 1, 40), np.uint16)
    counts[..., 10:15] = rng.poisson([5, 40, 90, 35, 6], (3, 3, 1, 5))
    ptu = _write_ptu(tmp_path / "irf.ptu", counts, 8.0)
    irf = load_irf(ptu)
    # all-zero ends trimmed (lossless: depths are referenced to the peak)
    np.testing.assert_array_equal(irf, counts.sum(axis=(0, 1))[:, 10:15])


def _write_phu(path, curves, resolution_s=8e-12):
    """Assemble a PicoQuant histogram-mode .phu file with ptufile's own tag encoder.

    ptufile writes no .phu files; this fixture follows the PicoQuant unified tag layout
    (magic, version, tags, Header_End, then each curve as uint32 at its
    HistResDscr_DataOffset). Not output of PicoQuant software.
    """
    pytest.importorskip("ptufile")
    from ptufile.ptufile import encode_tag

    n = len(curves)

    def header(offsets):
        tags = [
            encode_tag("Measurement_Mode", 0),
            encode_tag("Measurement_SubMode", 0),
            encode_tag("MeasDesc_Resolution", float(resolution_s)),
            encode_tag("HistoResult_NumberOfCurves", n),
        ]
        for i, (c, off) in enumerate(zip(curves, offsets, strict=True)):
            tags.append(encode_tag("HistResDscr_DataOffset", int(off), i))
            tags.append(encode_tag("HistResDscr_HistogramBins", len(c), i))
        return b"PQHISTO\0" + b"1.0.00\0\0" + b"".join(tags) + encode_tag("Header_End", None)

    size = len(header([0] * n))  # integer tags have a fixed size
    offsets = np.cumsum([size] + [4 * len(c) for c in curves[:-1]])
    data = b"".join(np.asarray(c, "<u4").tobytes() for c in curves)
    path.write_bytes(header(offsets) + data)
    return path


def test_load_irf_phu_curves(tmp_path):
    curves = [[0, 0, 5, 60, 20, 2, 0, 0], [0, 1, 9, 70, 10, 0, 0, 0]]
    phu = _write_phu(tmp_path / "irf.phu", curves)
    # all-zero ends trimmed over both curves
    np.testing.assert_array_equal(load_irf(phu), np.asarray(curves, float)[:, 1:6])
    with pytest.raises(SplidarError, match="hold no image.*can serve as the IRF"):
        splidar.load(phu, irf_fwhm=2)


def test_load_vendor_missing_extra_names_it(tmp_path, monkeypatch):
    f = tmp_path / "x.ptu"
    f.write_bytes(b"")
    monkeypatch.setitem(sys.modules, "ptufile", None)  # as if not installed
    with pytest.raises(SplidarError, match=r"pip install 'splidar\[ptu\]'"):
        splidar.load(f)
    g = tmp_path / "x.sdt"
    g.write_bytes(b"")
    monkeypatch.setitem(sys.modules, "sdtfile", None)
    with pytest.raises(SplidarError, match=r"pip install 'splidar\[sdt\]'"):
        splidar.load(g)


def test_load_spc_and_channels_refused(tmp_path):
    spc = tmp_path / "scan.spc"
    spc.write_bytes(b"\0" * 16)
    with pytest.raises(SplidarError, match=r"\.spc FIFO .* sdtfile reads \.sdt only"):
        splidar.load(spc)
    npy = tmp_path / "c.npy"
    np.save(npy, np.ones((2, 2, 8), np.uint16))
    with pytest.raises(SplidarError, match="`channels` applies to vendor files"):
        splidar.load(npy, channels="detectors", irf_fwhm=2)


# --------------------------------------------------------------------------------------
# Becker & Hickl SDT
# --------------------------------------------------------------------------------------


def _write_sdt(path, blocks, *, tac_r=50e-9, tac_g=1):
    """Assemble an SDT "Setup & Data" file from sdtfile's record definitions.

    Layout (B&H SPC_data_file_structure.h as sdtfile reads it): FILE_HEADER, the
    info text, one MEASURE_INFO, then per data block a BLOCK_HEADER followed by its
    uint16 counts. ``blocks``: arrays (scan_y, scan_x, adc_re) or (1, adc_re).
    """
    pytest.importorskip("sdtfile")
    import sdtfile.sdtfile as mod  # the record definitions live in the inner module

    fh_t = np.dtype(mod.FILE_HEADER)
    mi_t = np.dtype(mod.MEASURE_INFO)
    bh_t = np.dtype(mod.BLOCK_HEADER)
    info = b"*IDENTIFICATION\r\n  ID        : SPC Setup & Data File\r\n*END\r\n\r\n"
    adc_re = blocks[0].shape[-1]
    image = [b for b in blocks if b.ndim == 3]
    mi = np.zeros(1, mi_t)
    mi["tac_r"], mi["tac_g"], mi["adc_re"] = tac_r, tac_g, adc_re
    if image:
        mi["scan_y"], mi["scan_x"] = image[0].shape[:2]
    mi_offs = fh_t.itemsize + len(info)
    data_offs = mi_offs + mi_t.itemsize
    hdr = np.zeros(1, fh_t)
    hdr["revision"] = 0x28F  # SPC-150, file revision 15 (BLOCK_HEADER layout)
    hdr["info_offs"], hdr["info_length"] = fh_t.itemsize, len(info)
    hdr["data_block_offs"], hdr["no_of_data_blocks"] = data_offs, len(blocks)
    hdr["meas_desc_block_offs"], hdr["no_of_meas_desc_blocks"] = mi_offs, 1
    hdr["meas_desc_block_length"] = mi_t.itemsize
    hdr["header_valid"], hdr["chksum"] = 0x5555, 0x55AA
    parts = [hdr.tobytes(), info, mi.tobytes()]
    offs = data_offs
    for i, b in enumerate(blocks):
        raw = np.ascontiguousarray(b, "<u2").tobytes()
        bh = np.zeros(1, bh_t)
        bh["data_offs"] = offs + bh_t.itemsize
        bh["next_block_offs"] = offs + bh_t.itemsize + len(raw)
        bh["block_type"] = 0x0061 if b.ndim == 3 else 0x0001  # IMG / DECAY, measured, uint16
        bh["lblock_no"], bh["block_length"] = i + 1, len(raw)
        parts += [bh.tobytes(), raw]
        offs += bh_t.itemsize + len(raw)
    path.write_bytes(b"".join(parts))
    return path


def test_load_sdt_image_blocks_as_channels(tmp_path):
    rng = np.random.default_rng(4)
    a = rng.poisson(0.5, (6, 7, 64)).astype(np.uint16)
    b = rng.poisson(0.2, (6, 7, 64)).astype(np.uint16)
    sdt = _write_sdt(tmp_path / "two.sdt", [a, b])
    cube = splidar.load(sdt, irf_fwhm=2)
    assert cube.shape == (6, 7, 2, 64)
    np.testing.assert_array_equal(cube.counts, np.stack([a, b], axis=2))
    assert cube.bin_width_ps == 781.25  # tac_r / (tac_g adc_re) = 50 ns / 64
    assert cube.metadata["reader"].startswith("sdtfile")
    det = splidar.load(sdt, channels="detectors", irf_fwhm=2)
    np.testing.assert_array_equal(det.counts[:, :, 0], a + b)


def test_load_irf_sdt_decay_curve(tmp_path):
    curve = np.zeros((1, 32), np.uint16)
    curve[0, 5:9] = [10, 80, 40, 5]
    sdt = _write_sdt(tmp_path / "irf.sdt", [curve])
    np.testing.assert_array_equal(load_irf(sdt), [[10.0, 80.0, 40.0, 5.0]])
    with pytest.raises(SplidarError, match="no image data block"):
        splidar.load(sdt, irf_fwhm=2)


# --------------------------------------------------------------------------------------
# .npy
# --------------------------------------------------------------------------------------


def test_load_npy_counts_irf_library(tmp_path):
    rng = np.random.default_rng(5)
    counts = rng.poisson(1.0, (4, 5, 2, 30)).astype(np.uint16)
    np.save(tmp_path / "counts.npy", counts)
    np.save(tmp_path / "irf.npy", np.array([0.0, 1.0, 4.0, 1.0, 0.0]))
    np.save(tmp_path / "lib.npy", np.array([[1.0, 2.0], [3.0, 1.0]]))
    cube = splidar.load(
        tmp_path / "counts.npy", irf=tmp_path / "irf.npy", library=tmp_path / "lib.npy"
    )
    np.testing.assert_array_equal(cube.counts, counts)
    np.testing.assert_allclose(cube.irf, [[1 / 6, 4 / 6, 1 / 6]] * 2)
    np.testing.assert_array_equal(cube.library.signatures, [[1.0, 2.0], [3.0, 1.0]])
    assert load_library(tmp_path / "lib.npy").n_classes == 2


def test_load_npy_refuses_pickles(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([np.arange(3), None], dtype=object))
    for reader in (splidar.load, load_irf, load_library):
        with pytest.raises(SplidarError, match="allow_pickle=False"):
            reader(tmp_path / "obj.npy")


def test_main_run_ptu_with_npy_irf_and_library(scene_cube, tmp_path):
    from splidar.cli import main

    cube = scene_cube
    ptu = _write_ptu(tmp_path / "scene.ptu", cube.counts.astype(np.uint16), cube.bin_width_ps)
    np.save(tmp_path / "irf.npy", cube.irf)
    np.save(tmp_path / "lib.npy", cube.library.signatures)
    out = tmp_path / "out"
    args = ["run", str(ptu), "--irf", str(tmp_path / "irf.npy"), "--library"]
    args += [str(tmp_path / "lib.npy"), "--channels", "wavelengths", "--no-figures", "-q"]
    assert main([*args, "-o", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cube_shape"] == list(cube.shape)
    expected = splidar.process(cube, library=cube.library.signatures, rng=0).points
    with np.load(out / "result.npz") as z:
        np.testing.assert_array_equal(z["points_depth_bin"], expected.depth_bin)
        np.testing.assert_array_equal(z["points_label"], expected.label)
    # --channels detectors: one wavelength, the channels' sum
    out2 = tmp_path / "out2"
    args2 = ["run", str(ptu), "--irf-fwhm", "3", "--channels", "detectors", "--no-figures"]
    assert main([*args2, "-q", "-o", str(out2)]) == 0
    assert json.loads((out2 / "summary.json").read_text())["cube_shape"][2] == 1
