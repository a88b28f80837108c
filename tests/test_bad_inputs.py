"""The corpus of bad inputs: each refused in one clear line, with nothing written.

Every case crafts a bad file or option under a temporary folder and runs the command
line in-process (``splidar.cli.main``). It must exit non-zero, print exactly one
``splidar: error:`` line (at most two warning lines besides), no traceback, a message
matching the case's pattern, and leave the folder exactly as it was.

``python tests/test_bad_inputs.py`` prints the table of cases and their messages that
docs/reliability.md shows.
"""

from __future__ import annotations

import io
import os
import re
import struct
import sys
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from splidar.cli import main

ROWS, COLS, T = 4, 5, 32


def _counts(L: int | None = None, dtype=np.uint16) -> np.ndarray:
    rng = np.random.default_rng(0)
    shape = (ROWS, COLS, T) if L is None else (ROWS, COLS, L, T)
    c = rng.poisson(0.3, shape).astype(dtype)
    c[..., 10] += 5  # a surface at bin 10
    return c


IRF = np.array([0.1, 0.5, 1.0, 0.5, 0.1])


def _npz(d: Path, name: str = "cube.npz", **arrays) -> Path:
    p = d / name
    np.savez(p, **arrays)
    return p


def _cube_npz(d: Path, **extra) -> Path:
    return _npz(d, counts=_counts(), irf=IRF, **extra)


def _mat_cells(d: Path, cells, name: str = "lists.mat") -> Path:
    c = np.empty((ROWS, COLS), dtype=object)
    for i in range(ROWS):
        for j in range(COLS):
            c[i, j] = np.asarray(cells(i, j)).reshape(-1, 1)
    p = d / name
    scipy.io.savemat(p, {"Ts": c})
    return p


def _v73(d: Path, arrays: dict, name: str = "v73.mat") -> Path:
    """A MATLAB -v7.3 file: HDF5 with a 512-byte user block and reversed axes."""
    p = d / name
    with h5py.File(p, "w", userblock_size=512) as f:
        for k, v in arrays.items():
            ds = f.create_dataset(k, data=np.asarray(v).T)
            ds.attrs["MATLAB_class"] = np.bytes_("double" if v.dtype.kind == "f" else "uint16")
    with open(p, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .")
    return p


def _truncate(p: Path, keep: float = 0.5) -> Path:
    data = p.read_bytes()
    p.write_bytes(data[: int(len(data) * keep)])
    return p


def _text(d: Path, name: str, text: str) -> Path:
    p = d / name
    p.write_text(text)
    return p


def _garbage(d: Path, name: str) -> Path:
    p = d / name
    p.write_bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    return p


def _npz_claiming(d: Path, shape=(10**7, 10**6)) -> Path:
    """A .npz whose `counts` header claims 10^13 uint16 values but holds 64 bytes."""
    p = d / "claims.npz"
    header = {"descr": "<u2", "fortran_order": False, "shape": shape}
    bio = io.BytesIO()
    np.lib.format.write_array_header_1_0(bio, header)
    with zipfile.ZipFile(p, "w") as zf:
        zf.writestr("counts.npy", bio.getvalue() + bytes(64))
    return p


def _mat_claiming(d: Path) -> Path:
    """A .mat v5 whose `counts` dimensions are patched to claim 10^13 values."""
    p = d / "claims.mat"
    scipy.io.savemat(p, {"counts": np.ones((2, 2, 4))}, do_compression=False)
    b = bytearray(p.read_bytes())
    # header 128 + matrix tag 8 + array flags 16 + dims tag 8: the int32 dims at 160
    assert struct.unpack_from("<3i", b, 160) == (2, 2, 4)
    struct.pack_into("<3i", b, 160, 100_000, 100_000, 1000)
    p.write_bytes(bytes(b))
    return p


def _mat_cell_damaged(d: Path) -> Path:
    """A compressed cell array whose second cell's data tag claims a wrong size.

    scipy.io.loadmat 1.17 can crash (segfault) on such damage; splidar's own walk of
    the element sizes refuses the file first.
    """
    import zlib

    c = np.empty((2, 2), dtype=object)
    for i, j in np.ndindex(2, 2):
        c[i, j] = np.array([[3 + i + j]], dtype=np.uint16)
    p = d / "cd.mat"
    scipy.io.savemat(p, {"Ts": c}, do_compression=True)
    b = p.read_bytes()
    tag, n = struct.unpack_from("<II", b, 128)
    assert tag == 15  # miCOMPRESSED
    inner = bytearray(zlib.decompress(b[136 : 136 + n]))
    k = inner.index(struct.pack("<HH", 4, 2))  # the first small uint16 data tag (2 bytes)
    k = inner.index(struct.pack("<HH", 4, 2), k + 8)  # the second cell's
    struct.pack_into("<HH", inner, k, 4, 4)  # now claims 4 bytes for 1 value
    z = zlib.compress(bytes(inner))
    p.write_bytes(b[:128] + struct.pack("<II", 15, len(z)) + z)
    return p


def _mat_name_damaged(d: Path) -> Path:
    """A .mat v5 whose name element claims 64 characters (it reads into the data)."""
    p = d / "nd.mat"
    scipy.io.savemat(p, {"counts": np.ones((2, 2, 4))}, do_compression=False)
    b = bytearray(p.read_bytes())
    # header 128, matrix tag 8, flags 16, dims 8 + 16: the name tag at 176 (miINT8, 6)
    assert struct.unpack_from("<II", b, 176) == (1, 6)
    struct.pack_into("<II", b, 176, 1, 64)
    p.write_bytes(bytes(b))
    return p


def _h5_claiming(d: Path) -> Path:
    """An .h5 whose chunked `counts` declares 10^12 values and stores none."""
    p = d / "claims.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("counts", shape=(10**4, 10**4, 10**4), dtype=np.uint16, chunks=True)
        f["irf"] = IRF
    return p


def _zarr(d: Path, counts=None, name: str = "cube.zarr", **extra) -> Path:
    import zarr

    p = d / name
    g = zarr.open_group(str(p), mode="w")
    if counts is not None:
        g.create_array("counts", data=counts)
    g.create_array("irf", data=IRF)
    for k, v in extra.items():
        g.create_array(k, data=v)
    return p


def _zarr_corrupt(d: Path) -> Path:
    p = _zarr(d, _counts())
    for meta in list(p.rglob("zarr.json")) + list(p.rglob(".zgroup")):
        meta.write_text("{ not json")
    return p


def _zarr_bad_chunk(d: Path) -> Path:
    from splidar import Cube
    from splidar.io import save

    p = d / "chunk.zarr"
    save(Cube(_counts(), irf=IRF), p, chunks=(2, 2))
    chunk = sorted(f for f in (p / "counts").rglob("*") if f.is_file() and "zarr" not in f.name)
    chunk[0].write_bytes(b"garbage")
    return p


def _ro_dir() -> str:
    return "/proc/splidar-cannot-write-here/out"


@dataclass(frozen=True)
class Case:
    id: str
    what: str  # the bad input, for the docs table
    make: Callable[[Path], list[str]]  # -> argv (the output folder is appended for `run`)
    expect: str  # regular expression the error line must match
    run: bool = True  # a `splidar run` case (gets --out and -q --no-figures)


C = Case
CASES = [
    # ---- files that cannot be read --------------------------------------------------
    C("missing", "input file does not exist", lambda d: [str(d / "nope.npz")], r"does not exist"),
    C(
        "dir-not-zarr",
        "input is a folder, not a .zarr",
        lambda d: [str(d)],
        r"unknown file ext|folder",
    ),
    C(
        "unknown-ext",
        "input with an unknown extension (.txt)",
        lambda d: [str(_garbage(d, "scan.txt"))],
        r"unknown file extension '\.txt'.*reads",
    ),
    C(
        "npz-garbage",
        ".npz of random bytes",
        lambda d: [str(_garbage(d, "g.npz"))],
        r"cannot read .* as \.npz .*corrupt",
    ),
    C(
        "npz-truncated",
        ".npz cut in half",
        lambda d: [str(_truncate(_cube_npz(d)))],
        r"cannot read .* as \.npz .*corrupt|truncated",
    ),
    C(
        "npz-header-claims",
        ".npz whose header claims 10^13 values (64 bytes stored)",
        lambda d: [str(_npz_claiming(d))],
        r"claims 18\.\d TiB .* at most .*corrupt or truncated",
    ),
    C(
        "npz-object",
        ".npz holding an object (pickled) array",
        lambda d: [str(_npz(d, counts=np.array([[1, 2], [3]], dtype=object), irf=IRF))],
        r"object \(pickled\) array; splidar never unpickles",
    ),
    C(
        "npz-no-counts",
        ".npz without `counts` (a 3-D array named `data`)",
        lambda d: [str(_npz(d, data=_counts(), irf=IRF))],
        r"has no `counts` array.*select it with --variable set to .data.",
    ),
    C(
        "npz-nothing",
        ".npz holding no cube at all",
        lambda d: [str(_npz(d, a=np.ones(3)))],
        r"holds no photon-list \(cell\) or count-cube variable",
    ),
    C(
        "npz-2d-counts",
        "`counts` with 2 dimensions",
        lambda d: [str(_npz(d, counts=np.ones((4, 4), np.uint16), irf=IRF))],
        r"must be a count cube \(rows, cols, T\)",
    ),
    C(
        "npz-empty-axis",
        "`counts` with an empty axis (0 rows)",
        lambda d: [str(_npz(d, counts=np.zeros((0, 5, 32), np.uint16), irf=IRF))],
        r"empty axis|no photon-list",
    ),
    C(
        "npz-text-counts",
        "`counts` of strings",
        lambda d: [str(_npz(d, counts=np.array([[["a"]]])))],
        r"neither a count cube",
    ),
    C(
        "mat-garbage",
        ".mat of random bytes",
        lambda d: [str(_garbage(d, "g.mat"))],
        r"cannot read .* as a MATLAB .*corrupt",
    ),
    C(
        "mat-truncated",
        ".mat v5 cut in half",
        lambda d: [str(_truncate(_mat_cells(d, lambda i, j: [3, 4, 9], "t.mat")))],
        r"cannot read .* MATLAB .*(corrupt|truncated)",
    ),
    C(
        "mat-cell-damaged",
        ".mat v5 with a damaged cell inside a compressed variable",
        lambda d: [str(_mat_cell_damaged(d))],
        r"cannot read .* MATLAB .*damaged or truncated \(.*data bytes for",
    ),
    C(
        "mat-name-damaged",
        ".mat v5 whose variable name length is damaged",
        lambda d: [str(_mat_name_damaged(d))],
        r"damaged or truncated \(a variable name is not valid",
    ),
    C(
        "mat-header-claims",
        ".mat v5 whose dimensions claim 10^13 values",
        lambda d: [str(_mat_claiming(d))],
        r"claims 72\.\d TiB .*corrupt or truncated",
    ),
    C(
        "mat73-truncated",
        ".mat v7.3 (HDF5) cut in half",
        lambda d: [str(_truncate(_v73(d, {"counts": _counts(), "irf": IRF})))],
        r"cannot read .* MATLAB v7\.3 .*corrupt or truncated",
    ),
    C(
        "h5-garbage",
        ".h5 of random bytes",
        lambda d: [str(_garbage(d, "g.h5"))],
        r"not an HDF5 file",
    ),
    C(
        "h5-truncated",
        ".h5 cut in half",
        lambda d: [str(_truncate(_h5(d)))],
        r"cannot read .* as HDF5.*corrupt or truncated",
    ),
    C(
        "h5-claims",
        ".h5 dataset declaring 10^12 values, storing none",
        lambda d: [str(_h5_claiming(d))],
        r"claims 1\.\d TiB .*stores 0 bytes.*corrupt",
    ),
    C(
        "zarr-no-counts",
        ".zarr without `counts`",
        lambda d: [str(_zarr(d))],
        r"has no `counts` array",
    ),
    C(
        "zarr-corrupt",
        ".zarr with corrupt metadata",
        lambda d: [str(_zarr_corrupt(d))],
        r"cannot open .* as a zarr group",
    ),
    C(
        "zarr-float",
        ".zarr `counts` of floats",
        lambda d: [str(_zarr(d, _counts().astype(np.float32))), "--store", str(d / "st.zarr")],
        r"integer dtype",
    ),
    C(
        "zarr-2d",
        ".zarr `counts` with 2 dimensions",
        lambda d: [str(_zarr(d, np.ones((4, 4), np.uint16)))],
        r"must be \(rows, cols\[, L\], T\)",
    ),
    C(
        "zarr-damaged-chunk",
        ".zarr with a damaged chunk",
        lambda d: [str(_zarr_bad_chunk(d))],
        r"cannot read the counts of .*a chunk is damaged or missing",
    ),
    # ---- photon tables and axes (ux22) -----------------------------------------------
    C(
        "table-no-header",
        "photon table (.csv) without a header row",
        lambda d: [str(_text(d, "photons.csv", "0,1,1200\n1,1,1300\n"))],
        r"no header row naming its columns.*row,col,time_ps",
    ),
    C(
        "table-fractional-row",
        "photon table with a fractional pixel row",
        lambda d: [str(_text(d, "photons.csv", "row,col,time_ps\n0.5,1,1200\n1,1,1300\n"))],
        r"column 'row' \(pixel row\) must hold whole numbers",
    ),
    C(
        "time-axis-out-of-range",
        "--time-axis beyond the array's axes",
        lambda d: [str(_npz(d, counts=_counts(), irf=IRF)), "--time-axis", "3"],
        r"--time-axis must be an axis of variable 'counts'.*-3 to 2; got 3",
    ),
    C(
        "too-few-bins",
        "a cube of 2 time bins",
        lambda d: [str(_npz(d, counts=_counts()[..., 9:11], irf=IRF))],
        r"T = 2 time bin\(s\); detection needs at least 3",
    ),
    # ---- counts --------------------------------------------------------------------
    C(
        "counts-nan",
        "NaN counts",
        lambda d: [str(_npz(d, counts=_nan_counts(), irf=IRF))],
        r"NaN or infinite .*finite whole numbers",
    ),
    C(
        "counts-inf",
        "infinite counts",
        lambda d: [str(_npz(d, counts=_nan_counts(np.inf), irf=IRF))],
        r"NaN or infinite",
    ),
    C(
        "counts-negative",
        "negative counts",
        lambda d: [str(_npz(d, counts=_counts(dtype=np.int32) - 3, irf=IRF))],
        r"negative value.*non-negative",
    ),
    C(
        "counts-fraction",
        "fractional counts",
        lambda d: [str(_npz(d, counts=_counts(dtype=np.float64) + 0.5, irf=IRF))],
        r"non-integer values.*raw counts",
    ),
    C(
        "counts-huge",
        "float counts beyond 2^32 photons in a bin",
        lambda d: [str(_npz(d, counts=_counts(dtype=np.float64) * 1e12, irf=IRF))],
        r"more photons than a bin can count",
    ),
    C(
        "counts-zero",
        "a cube without a single photon",
        lambda d: [str(_npz(d, counts=np.zeros((4, 5, 32), np.uint16), irf=IRF))],
        r"hold no photon: nothing to detect",
    ),
    # ---- photon lists ----------------------------------------------------------------
    C(
        "lists-empty",
        "photon lists whose cells are all empty",
        lambda d: [str(_mat_cells(d, lambda i, j: np.zeros(0, np.uint16))), "--irf-fwhm", "2"],
        r"hold no photon: every cell is empty",
    ),
    C(
        "lists-out-of-window",
        "photon times all outside --window",
        lambda d: [
            str(_mat_cells(d, lambda i, j: [1000 + i, 1020])),
            "--window",
            "0",
            "100",
            "--irf-fwhm",
            "2",
        ],
        r"none of the \d+ photons falls in the window \[0, 100\).*range from 1000",
    ),
    C(
        "lists-nan-times",
        "photon times holding NaN",
        lambda d: [
            str(_mat_cells(d, lambda i, j: [3.0, np.nan] if i else [4.0])),
            "--irf-fwhm",
            "2",
        ],
        r"NaN or infinite arrival time",
    ),
    C(
        "lists-text",
        "photon-list cells of text",
        lambda d: [str(_mat_cells(d, lambda i, j: np.array(["ab"])))],
        r"holds no photon-list \(cell\) or count-cube|must hold numbers",
    ),
    C(
        "lists-flat-pixel",
        "flat .npz photon lists with a pixel index outside the image",
        lambda d: [
            str(_npz(d, times=[1, 2], pixel_index=[0, 99], shape=[2, 2])),
            "--irf-fwhm",
            "2",
        ],
        r"`pixel_index` .* must be integers in \[0, 4\)",
    ),
    C(
        "lists-flat-length",
        "flat .npz photon lists of different lengths",
        lambda d: [str(_npz(d, times=[1, 2, 3], pixel_index=[0, 1], shape=[2, 2]))],
        r"same length; got shapes \(3,\) and \(2,\)",
    ),
    C(
        "lists-window-reversed",
        "--window with stop <= start",
        lambda d: [
            str(_mat_cells(d, lambda i, j: [3, 4])),
            "--window",
            "10",
            "5",
            "--irf-fwhm",
            "2",
        ],
        r"--window must have stop > start",
    ),
    C(
        "lists-huge-binning",
        "binning into more bins than memory holds",
        lambda d: [
            str(_mat_cells(d, lambda i, j: [3, 4])),
            "--window",
            "0",
            "1e12",
            "--irf-fwhm",
            "2",
        ],
        r"would allocate .* GiB.*larger --bin-width",
    ),
    # ---- IRFs --------------------------------------------------------------------------
    C(
        "irf-zero",
        "IRF all zero",
        lambda d: [str(_cube_npz_irf(d, np.zeros(5)))],
        r"IRF|irf.*(no positive|zero)",
    ),
    C(
        "irf-negative",
        "IRF with negative values",
        lambda d: [str(_cube_npz_irf(d, IRF - 0.3))],
        r"negative",
    ),
    C(
        "irf-nan",
        "IRF holding NaN",
        lambda d: [str(_cube_npz_irf(d, np.r_[IRF, np.nan]))],
        r"NaN or infinite",
    ),
    C(
        "irf-wavelengths",
        "IRF with 3 rows for 2 wavelengths",
        lambda d: [str(_npz(d, counts=_counts(L=2), irf=np.tile(IRF, (3, 1))))],
        r"wavelength",
    ),
    C(
        "irf-file-nan",
        "--irf file holding NaN",
        lambda d: [str(_cube_npz(d)), "--irf", str(_text(d, "irf.csv", "0,1,nan,1"))],
        r"must be finite, non-negative and not all zero",
    ),
    C(
        "irf-file-missing",
        "--irf file that does not exist",
        lambda d: [str(_cube_npz(d)), "--irf", str(d / "nope.csv")],
        r"no such file",
    ),
    C(
        "irf-fwhm-inf",
        "--irf-fwhm inf",
        lambda d: [str(_cube_npz(d)), "--irf-fwhm", "inf"],
        r"--irf-fwhm: must be a finite number > 0",
    ),
    # ---- libraries ----------------------------------------------------------------------
    C(
        "library-shape",
        "library over 3 wavelengths for a 1-wavelength cube",
        lambda d: [str(_cube_npz(d)), "--library", str(_text(d, "lib.csv", "a,1,2,3\nb,3,2,1"))],
        r"3 wavelength\(s\) but the data has 1.*\(K, 1\)",
    ),
    C(
        "library-negative",
        "library with a negative signature",
        lambda d: [str(_cube_npz(d)), "--library", str(_text(d, "lib.csv", "a,-1\nb,2"))],
        r"non-negative",
    ),
    C(
        "library-garbage",
        "library file of text",
        lambda d: [str(_cube_npz(d)), "--library", str(_text(d, "lib.csv", "hello\nworld,x"))],
        r"not a signature|no signature rows",
    ),
    # ---- options --------------------------------------------------------------------------
    C(
        "opt-pfa",
        "--pfa 2",
        lambda d: [str(_cube_npz(d)), "--pfa", "2"],
        r"--pfa: must lie in \(0, 1\)",
    ),
    C(
        "opt-max-surfaces",
        "--max-surfaces 0",
        lambda d: [str(_cube_npz(d)), "--max-surfaces", "0"],
        r"--max-surfaces: must be > 0",
    ),
    C(
        "opt-scales-even",
        "--scales 2,4 (even box sizes)",
        lambda d: [str(_cube_npz(d)), "--scales", "2,4"],
        r"--scales.*odd",
    ),
    C(
        "opt-weights",
        "--weights that do not match --scales",
        lambda d: [str(_cube_npz(d)), "--scales", "1,3", "--weights", "1,2,3"],
        r"--weights",
    ),
    C(
        "opt-gamma",
        "--gamma -1",
        lambda d: [str(_cube_npz(d)), "--gamma", "-1"],
        r"--gamma: must be >= 0",
    ),
    C(
        "opt-tol",
        "--tol nan",
        lambda d: [str(_cube_npz(d)), "--tol", "nan"],
        r"--tol: must be > 0",
    ),
    C("opt-jobs", "--jobs 0", lambda d: [str(_cube_npz(d)), "--jobs", "0"], r"--jobs: must be > 0"),
    C(
        "opt-window-empty",
        "--window selecting no bin of a cube",
        lambda d: [str(_cube_npz(d)), "--window", "40", "50"],
        r"selects no bins",
    ),
    C(
        "opt-bin-width-cube",
        "--bin-width on a histogram file",
        lambda d: [str(_cube_npz(d)), "--bin-width", "2"],
        r"apply to photon-list files",
    ),
    C(
        "opt-variable",
        "--variable naming no variable",
        lambda d: [str(_cube_npz(d)), "--variable", "nope"],
        r"variable 'nope' is not in .*it holds",
    ),
    C(
        "opt-unknown",
        "an unknown option",
        lambda d: [str(_cube_npz(d)), "--speed", "11"],
        r"unrecognized arguments: --speed",
    ),
    # ---- outputs ------------------------------------------------------------------------
    C(
        "out-exists",
        "output folder exists, no --force",
        lambda d: [str(_cube_npz(d)), "--out", str(_mkdir(d / "o"))],
        r"exists; pass --force",
        run=True,
    ),
    C(
        "out-not-splidar",
        "--force on a folder splidar did not write",
        lambda d: [str(_cube_npz(d)), "--force", "--out", str(_mkdir(d / "o", "notes.txt"))],
        r"refusing to replace .* no summary\.json",
    ),
    C(
        "out-under-file",
        "output folder under a regular file",
        lambda d: [str(_cube_npz(d)), "--out", str(_text(d, "f.txt", "x") / "sub" / "out")],
        r"lies under .*f\.txt', which is a file",
    ),
    C(
        "out-unwritable",
        "output folder in a place that cannot be written",
        lambda d: [str(_cube_npz(d)), "--out", _ro_dir()],
        r"cannot write into the folder",
    ),
    C(
        "out-is-input",
        "output folder containing the input",
        lambda d: [str(_cube_npz(d)), "--out", str(d)],
        r"would contain or replace the input",
    ),
    C(
        "out-is-file",
        "output path is an existing file",
        lambda d: [str(_cube_npz(d)), "--out", str(_text(d, "o.txt", "x"))],
        r"exists and is not a folder",
    ),
    # ---- other commands -------------------------------------------------------------------
    C(
        "simulate-ext",
        "simulate --out without .npz/.zarr",
        lambda d: ["simulate", "single", "--out", str(d / "x.txt")],
        r"must end in \.npz or \.zarr",
        run=False,
    ),
    C(
        "evaluate-garbage",
        "evaluate on a file that holds no points",
        lambda d: ["evaluate", str(_garbage(d, "p.npz")), str(_garbage(d, "q.npz"))],
        r"cannot read '.*p\.npz' as \.npz .*corrupt",
        run=False,
    ),
]


def _h5(d: Path) -> Path:
    p = d / "c.h5"
    with h5py.File(p, "w") as f:
        f["counts"] = _counts()
        f["irf"] = IRF
    return p


def _nan_counts(value=np.nan) -> np.ndarray:
    c = _counts(dtype=np.float32)
    c[1, 2, 3] = value
    return c


def _cube_npz_irf(d: Path, irf) -> Path:
    return _npz(d, counts=_counts(), irf=np.asarray(irf))


def _text(d: Path, name: str, text: str) -> Path:
    p = d / name
    p.write_text(text)
    return p


def _mkdir(p: Path, *files: str) -> Path:
    p.mkdir()
    for f in files:
        (p / f).write_text("keep me")
    return p


def _listing(d: Path) -> dict[str, int]:
    return {str(f.relative_to(d)): f.stat().st_size for f in d.rglob("*") if f.is_file()} | {
        str(f.relative_to(d)) + "/": 0 for f in d.rglob("*") if f.is_dir()
    }


def run_case(case: Case, d: Path) -> tuple[int, str, str, list[str]]:
    """Run one case in folder ``d``; return (exit code, stdout, stderr, argv)."""
    argv = case.make(d)
    if case.run:
        if "--out" not in argv:
            argv += ["--out", str(d / "result")]
        argv = ["run", *argv, "-q", "--no-figures"]
    return (*_capture(argv), argv)


def _capture(argv) -> tuple[int, str, str]:
    import contextlib

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_cli_bad_input_refused_in_one_line(case, tmp_path):
    argv = case.make(tmp_path)
    before = _listing(tmp_path)
    if case.run:
        if "--out" not in argv:
            argv += ["--out", str(tmp_path / "result")]
        argv = ["run", *argv, "-q", "--no-figures"]
    code, out, err = _capture(argv)
    assert code != 0, (argv, out, err)
    assert "Traceback" not in err
    lines = [x for x in err.splitlines() if x.strip()]
    errors = [x for x in lines if x.startswith("splidar: error: ")]
    assert len(errors) == 1 and len(lines) <= 3, err
    assert re.search(case.expect, errors[0]), errors[0]
    assert len(errors[0]) < 400, errors[0]
    assert _listing(tmp_path) == before, "nothing may be written"


def test_corpus_has_at_least_40_cases():
    assert len({c.id for c in CASES}) == len(CASES) >= 40


def test_load_unsorted_photon_times_same_cube(tmp_path):
    """Unsorted arrival times are not an error: binning does not depend on their order."""
    from splidar.io import load

    a = load(_mat_cells(tmp_path, lambda i, j: [3, 9, 4, 9], "a.mat"), irf_fwhm=2)
    b = load(_mat_cells(tmp_path, lambda i, j: [9, 4, 9, 3], "b.mat"), irf_fwhm=2)
    np.testing.assert_array_equal(a.counts, b.counts)
    assert int(a.counts.sum()) == 4 * ROWS * COLS


def test_load_npz_never_unpickles(tmp_path):
    """An object array whose unpickling would run code is refused before unpickling."""
    from splidar import SplidarError
    from splidar.io import load

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.mkdir, (str(marker),))

    arr = np.empty(1, dtype=object)
    arr[0] = Evil()
    np.savez(tmp_path / "evil.npz", counts=arr)
    with pytest.raises(SplidarError, match="never unpickles"):
        load(tmp_path / "evil.npz")
    assert not marker.exists()


def test_check_memory_refuses_with_figure_and_way_out(tmp_path, monkeypatch):
    """The memory guard names the need, what is free and the way out (SPLIDAR_MEMORY_LIMIT)."""
    monkeypatch.setenv("SPLIDAR_MEMORY_LIMIT", "1K")
    p = _cube_npz(tmp_path)
    code, _, err = _capture(["run", str(p), "--out", str(tmp_path / "o"), "-q"])
    assert code == 1
    assert re.search(r"reading 'cube\.npz' needs about .* but 1\.0 KiB is available; .*Zarr", err)
    monkeypatch.setenv("SPLIDAR_MEMORY_LIMIT", "4K")  # reading fits, detection does not
    code, _, err = _capture(["run", str(p), "--out", str(tmp_path / "o"), "-q"])
    assert code == 1 and "detection on 4 x 5 pixels x 32 bins needs about" in err
    assert not (tmp_path / "o").exists()


def _table() -> str:
    rows = ["| input | `splidar run` says |", "|---|---|"]
    for case in CASES:
        with tempfile.TemporaryDirectory() as t:
            code, _, err, _ = run_case(case, Path(t))
        line = next((x for x in err.splitlines() if x.startswith("splidar: error:")), err)
        line = line.replace(t, "DIR").replace("|", "\\|")
        msg = line[len("splidar: error: ") :]
        rows.append(f"| {case.what} | `` {msg} `` (exit {code}) |")
    return "\n".join(rows)


if __name__ == "__main__":
    sys.exit(print(_table()))


def test_load_npy_header_claiming_more_than_the_file_is_refused_before_allocating(tmp_path):
    # 72.8 TiB claimed, 64 bytes stored: refused from the header, not by a failed allocation
    from splidar import SplidarError
    from splidar.io import load, load_irf

    p = tmp_path / "claims.npy"
    with open(p, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (10**7, 10**6)}
        )
        f.write(b"\0" * 64)
    for reader in (load, load_irf):
        with pytest.raises(SplidarError, match=r"claims 72\.8 TiB .* at most 64 bytes"):
            reader(p)
