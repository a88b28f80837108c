"""Low-level readers shared by :mod:`splidar.io` and :mod:`splidar.library`: a file ->
``{name: array}``, with the checks that make untrusted files safe to open (sizes checked
before any allocation, nothing unpickled or executed).

This module imports nothing from the rest of splidar but the validators, so that
``library`` and ``io`` can both use it without an import cycle.
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ._memory import available_bytes, check_memory, format_bytes
from ._validation import SplidarError, describe

_CONTAINER_EXTS = (".npz", ".mat", ".h5", ".hdf5")


# --------------------------------------------------------------------------------------
# low-level readers: a file -> {name: array}
# --------------------------------------------------------------------------------------
def _check_path(path) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise SplidarError(f"`path` must be a file path; got {describe(path)}.")
    p = Path(path)
    if not p.exists():
        raise SplidarError(f"no such file: '{p}'. Check the path (relative to {Path.cwd()}).")
    return p


def _ext(p: Path) -> str:
    return p.suffix.lower()


def _is_hdf5(p: Path) -> bool:
    try:
        import h5py

        return bool(h5py.is_hdf5(p))
    except Exception:  # pragma: no cover - h5py is a dependency
        return False


def _h5_to_numpy(f, obj, matlab: bool):
    """Convert one HDF5 dataset to NumPy (MATLAB v7.3: reverse axes, resolve cells)."""
    import h5py

    data = obj[()]
    cls = obj.attrs.get("MATLAB_class", b"")
    cls = cls.decode() if isinstance(cls, bytes) else str(cls)
    if isinstance(data, np.ndarray) and data.dtype == h5py.ref_dtype:
        out = np.empty(data.shape, dtype=object)
        flat = out.reshape(-1)
        for i, ref in enumerate(data.reshape(-1)):
            flat[i] = _h5_to_numpy(f, f[ref], matlab)
        data = out
    if matlab:
        if obj.attrs.get("MATLAB_empty", 0):
            return np.zeros((0, 0))
        if isinstance(data, np.ndarray) and data.ndim >= 2:
            data = data.T  # h5py returns MATLAB arrays with their axes reversed
        if cls == "char" and isinstance(data, np.ndarray):
            return "".join(chr(c) for c in np.asarray(data).T.reshape(-1))
        if cls == "logical" and isinstance(data, np.ndarray):
            data = data.astype(bool)
    return data


#: attributes of HDF5 datasets and groups read as values (``"path/name"``): those that
#: describe a count array (splidar.io looks them up beside it)
_H5_ATTRS = frozenset(("irf", "bin_width_ps", "wavelengths_nm", "class_names", "metadata"))


def _read_hdf5(p: Path, matlab: bool) -> dict[str, Any]:
    import h5py

    kind = "a MATLAB v7.3 (HDF5) file" if matlab else "HDF5"
    out: dict[str, Any] = {}
    try:
        with h5py.File(p, "r") as f:
            _check_hdf5_sizes(f, p)

            attrs: dict[str, Any] = {}

            def visit(name, obj):
                if name.startswith("#"):  # #refs#
                    return
                if isinstance(obj, h5py.Dataset):
                    out[name] = _h5_to_numpy(f, obj, matlab)
                for k in _H5_ATTRS.intersection(obj.attrs.keys()):  # e.g. bin_width_ps
                    v = obj.attrs[k]
                    attrs[f"{name}/{k}"] = v.decode() if isinstance(v, bytes) else v

            f.visititems(visit)
            for k, v in attrs.items():  # a dataset of that name wins
                out.setdefault(k, v)
            for k, v in f.attrs.items():
                if k not in out and not k.startswith("MATLAB"):
                    out[k] = v.decode() if isinstance(v, bytes) else v
    except SplidarError:
        raise
    except Exception as exc:  # h5py raises OSError, KeyError, RuntimeError, ValueError
        raise SplidarError(
            f"cannot read '{p}' as {kind}: {_short(exc)}. The file is corrupt or truncated; "
            "write it again or copy it again."
        ) from None
    return out


# --------------------------------------------------------------------------------------
# untrusted files: sizes are checked before anything is allocated, nothing is unpickled
# --------------------------------------------------------------------------------------
_READ_CHUNK = 2**22  # bytes per read of a .npz member (whole-member reads were 4x slower)
#: Deflate (zip, MATLAB v5 compressed, HDF5 gzip) expands one byte to at most 1032.
_MAX_EXPANSION = 1032
_WAY_OUT_READ = (
    "convert the data to a chunked Zarr cube (splidar.io.save(cube, 'x.zarr')), "
    "crop it, or free memory"
)


def _short(exc: BaseException, n: int = 160) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if len(msg) <= n else msg[: n - 3] + "..."


def _claims_too_much(p: Path, what: str, nbytes: int, holds: int, note: str = "") -> None:
    if nbytes > holds:
        raise SplidarError(
            f"{what} in '{p.name}' claims {format_bytes(nbytes)} of data but the file can "
            f"hold at most {format_bytes(holds)}{note}: the file is corrupt or truncated."
        )


def _npy_header(fp, p: Path, name: str):
    """Read a ``.npy`` header: (shape, fortran_order, dtype); refuses object dtypes."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fp)
        reader = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = reader(fp)
    except Exception as exc:
        raise SplidarError(
            f"array '{name}' of '{p.name}' has no valid .npy header ({_short(exc)}): the file "
            "is corrupt or truncated."
        ) from None
    if dtype.hasobject:
        raise SplidarError(
            f"array '{name}' of '{p.name}' is an object (pickled) array; splidar never "
            "unpickles files (it could run code). Store numbers only: counts as an integer "
            "array, photon lists as `times` (n,), `pixel_index` (n,) and `shape` (rows, cols)."
        )
    return shape, fortran, dtype


def _read_npz(p: Path) -> dict[str, Any]:
    """Read every array of a ``.npz`` without pickle, checking each header's claim first."""
    import zipfile
    import zlib

    out: dict[str, Any] = {}
    try:
        with zipfile.ZipFile(p) as zf:
            infos = [i for i in zf.infolist() if i.filename.endswith(".npy")]
            plan = []
            for info in infos:
                name = info.filename[:-4]
                with zf.open(info) as fp:
                    shape, fortran, dtype = _npy_header(fp, p, name)
                    header = fp.tell()
                nbytes = math.prod(shape) * dtype.itemsize
                _claims_too_much(p, f"array '{name}' {shape}", nbytes, info.file_size - header)
                if info.compress_type != zipfile.ZIP_STORED:
                    _claims_too_much(
                        p,
                        f"array '{name}' {shape}",
                        nbytes,
                        info.compress_size * _MAX_EXPANSION,
                        " once decompressed",
                    )
                plan.append((info, name, shape, fortran, dtype, nbytes))
            check_memory(sum(x[-1] for x in plan), f"reading '{p.name}'", _WAY_OUT_READ)
            for info, name, shape, fortran, dtype, nbytes in plan:
                with zf.open(info) as fp:
                    _npy_header(fp, p, name)
                    a = np.empty(shape[::-1] if fortran else shape, dtype=dtype)
                    view = memoryview(a.reshape(-1).view(np.uint8)) if nbytes else b""
                    got = 0
                    while got < nbytes:
                        k = fp.readinto(view[got : got + _READ_CHUNK])
                        if not k:
                            break
                        got += k
                    if got < nbytes:
                        raise SplidarError(
                            f"array '{name}' of '{p.name}' is truncated ({got} of {nbytes} "
                            "bytes): the file is corrupt or was not completely written."
                        )
                out[name] = a.T if fortran else a
    except SplidarError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error) as exc:
        raise SplidarError(
            f"cannot read '{p}' as .npz ({_short(exc)}): the file is corrupt, truncated or "
            "not a NumPy .npz; write it again with numpy.savez or splidar.io.save."
        ) from None
    if not out:
        raise SplidarError(f"'{p}' is a zip file but holds no NumPy arrays (.npy members).")
    return out


#: bytes per element of MATLAB classes (as listed by scipy.io.whosmat)
_MAT_ITEMSIZE = {
    "double": 8, "single": 4, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
    "int32": 4, "uint32": 4, "int64": 8, "uint64": 8, "logical": 1, "char": 2,
}  # fmt: skip


# --------------------------------------------------------------------------------------
# MATLAB v5 structure check: scipy.io.loadmat can crash (segfault) on damaged files
# --------------------------------------------------------------------------------------
_MI_ITEMSIZE = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 9: 8, 12: 8, 13: 8}  # miINT8..
_MX_NUMERIC = frozenset(range(4, 16)) - {5}  # char, double..uint64 (5 = sparse)


class _Mat5Damaged(Exception):
    pass


def _mat5_tag(buf, pos: int, end: int, e: str) -> tuple[int, int, int, int]:
    """(mdtype, nbytes, data start, next element) of the element at ``pos``."""
    if end - pos < 8:
        raise _Mat5Damaged(f"element tag cut at byte {pos}")
    w0, w1 = struct.unpack_from(e + "II", buf, pos)
    if w0 >> 16:  # small data element: 2-byte size, 2-byte type, 4 bytes of data
        n, mdt = w0 >> 16, w0 & 0xFFFF
        if n > 4:
            raise _Mat5Damaged(f"small element of {n} bytes at byte {pos}")
        return mdt, n, pos + 4, pos + 8
    start = pos + 8
    if w1 > end - start:
        raise _Mat5Damaged(f"element at byte {pos} claims {w1} bytes, {end - start} remain")
    pad = 0 if w0 == 15 else -w1 % 8  # compressed elements are not padded
    return w0, w1, start, min(start + w1 + pad, end)


def _mat5_matrix(buf, pos: int, end: int, e: str, depth: int) -> None:
    """Check one miMATRIX payload ``buf[pos:end]`` and, recursively, its cells and fields."""
    if depth > 32:
        raise _Mat5Damaged("cells or structs nested more than 32 deep")
    if pos == end:
        return  # an empty matrix
    mdt, n, s, pos = _mat5_tag(buf, pos, end, e)
    if mdt != 6 or n != 8:
        raise _Mat5Damaged("array flags missing")
    cls = struct.unpack_from(e + "I", buf, s)[0] & 0xFF
    mdt, n, s, pos = _mat5_tag(buf, pos, end, e)
    if mdt != 5 or n < 8 or n % 4:
        raise _Mat5Damaged("array dimensions missing")
    dims = struct.unpack_from(f"{e}{n // 4}i", buf, s)
    if min(dims) < 0:
        raise _Mat5Damaged(f"negative dimension {dims}")
    count = math.prod(dims)
    _, _, _, pos = _mat5_tag(buf, pos, end, e)  # name
    if cls in (2, 3):  # struct, object
        if cls == 3:
            _, _, _, pos = _mat5_tag(buf, pos, end, e)  # class name
        mdt, n, s, pos = _mat5_tag(buf, pos, end, e)
        flen = struct.unpack_from(e + "i", buf, s)[0] if n == 4 else 0
        mdt, n, s, pos = _mat5_tag(buf, pos, end, e)
        count *= n // flen if flen > 0 else 0
    if cls in (1, 2, 3):  # cell, struct, object: `count` matrices follow
        for _ in range(count):
            mdt, n, s, pos = _mat5_tag(buf, pos, end, e)
            if mdt != 14:
                raise _Mat5Damaged(f"cell or field element of type {mdt}, not a matrix")
            _mat5_matrix(buf, s, s + n, e, depth + 1)
    elif cls in _MX_NUMERIC:
        mdt, n, s, pos = _mat5_tag(buf, pos, end, e)
        size = _MI_ITEMSIZE.get(mdt)
        if size is not None and n != count * size:
            raise _Mat5Damaged(f"{n} data bytes for {count} values of {size} bytes")


def _check_mat5(p: Path, size_limit: int) -> None:
    """Walk a MATLAB v5 file's elements, checking every size against its container.

    scipy.io.loadmat (1.17) trusts these sizes and can crash the interpreter
    (segfault) on a damaged file; this walk refuses such files first.
    """
    import zlib

    buf = p.read_bytes()
    if len(buf) < 128:
        raise _Mat5Damaged("shorter than the 128-byte header")
    e = "<" if buf[126:128] == b"IM" else ">"
    pos = 128
    while pos < len(buf):
        mdt, n, s, pos = _mat5_tag(buf, pos, len(buf), e)
        if mdt == 15:  # miCOMPRESSED: one element, zlib-compressed
            d = zlib.decompressobj()
            try:
                inner = d.decompress(buf[s : s + n], size_limit)
            except zlib.error as exc:
                raise _Mat5Damaged(f"compressed variable: {exc}") from None
            if d.unconsumed_tail:
                raise _Mat5Damaged("a compressed variable expands beyond the size limit")
            imdt, inn, ins, _ = _mat5_tag(inner, 0, len(inner), e)
            if imdt == 14:
                _mat5_matrix(inner, ins, ins + inn, e, 0)
        elif mdt == 14:
            _mat5_matrix(buf, s, s + n, e, 0)


_MATLAB_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}")


def _read_mat5(p: Path) -> dict[str, Any]:
    """Read a MATLAB v4/v5 file, checking the sizes its headers declare first."""
    import scipy.io

    kind = "a MATLAB (.mat v5) file"
    try:
        listing = scipy.io.whosmat(p)
    except Exception as exc:
        raise SplidarError(
            f"cannot read '{p}' as {kind} ({_short(exc)}): the file is corrupt, truncated "
            "or not a MATLAB file; save it again from MATLAB (save -v7 or -v7.3)."
        ) from None
    size = p.stat().st_size
    total = 0
    for name, shape, cls in listing:
        if not _MATLAB_NAME.fullmatch(name):
            # a damaged name length; scipy.io.loadmat can crash (segfault) reading on
            raise SplidarError(
                f"cannot read '{p}' as {kind}: it is damaged or truncated (a variable name "
                f"is not valid: {name[:20]!r}...); save it again from MATLAB."
            )
        nbytes = math.prod(shape) * _MAT_ITEMSIZE.get(cls, 8)
        _claims_too_much(
            p, f"variable '{name}' {tuple(shape)}", nbytes, size * _MAX_EXPANSION,
            " once decompressed",
        )  # fmt: skip
        total += nbytes
    check_memory(total, f"reading '{p.name}'", _WAY_OUT_READ)
    if listing and scipy.io.matlab.matfile_version(p)[0] == 1:  # v5 (v4 has no tags)
        try:
            _check_mat5(p, min(size * _MAX_EXPANSION, available_bytes() or 2**62))
        except (_Mat5Damaged, struct.error) as exc:
            raise SplidarError(
                f"cannot read '{p}' as {kind}: it is damaged or truncated ({exc}); save it "
                "again from MATLAB."
            ) from None
    try:
        d = scipy.io.loadmat(p, squeeze_me=False, mat_dtype=False)
    except Exception as exc:
        raise SplidarError(
            f"cannot read '{p}' as {kind} ({_short(exc)}): the file is corrupt or truncated; "
            "save it again from MATLAB."
        ) from None
    return {k: v for k, v in d.items() if not k.startswith("__")}


def _check_hdf5_sizes(f, p: Path) -> None:
    """Refuse datasets declaring more data than stored (beyond compression) or than fits."""
    import h5py

    total = 0

    def visit(name, obj):
        nonlocal total
        if not isinstance(obj, h5py.Dataset) or obj.shape is None:
            return
        nbytes = math.prod(obj.shape) * obj.dtype.itemsize
        total += nbytes
        if nbytes > 2**20:
            stored = obj.id.get_storage_size()
            _claims_too_much(
                p, f"dataset '{name}' {obj.shape}", nbytes, stored * _MAX_EXPANSION,
                " (it stores " + format_bytes(stored) + ")",
            )  # fmt: skip

    f.visititems(visit)
    check_memory(total, f"reading '{p.name}'", _WAY_OUT_READ)


def _read_container(p: Path) -> dict[str, Any]:
    """Every variable of a .npz / .mat / .h5 file as NumPy values (cells -> object arrays).

    Nothing is unpickled or executed: ``.npz`` members are read with their ``.npy``
    header checked first (:func:`_read_npz`), and every declared size is checked
    against the file's size and the free memory before anything is allocated.
    """
    ext = _ext(p)
    if ext == ".npz":
        return _read_npz(p)
    if ext == ".mat":
        if _is_hdf5(p):
            return _read_hdf5(p, matlab=True)
        return _read_mat5(p)
    if ext in (".h5", ".hdf5"):
        if not _is_hdf5(p):
            raise SplidarError(
                f"'{p}' is not an HDF5 file (no HDF5 signature): corrupt, truncated or of "
                "another format."
            )
        return _read_hdf5(p, matlab=False)
    if p.is_dir():
        raise SplidarError(
            f"'{p}' is a folder, not a file; splidar reads {', '.join(_CONTAINER_EXTS)} files "
            "and .zarr folders (a folder's name must end in .zarr)."
        )
    raise SplidarError(
        f"unknown file extension '{p.suffix}' for '{p}'; splidar reads "
        f"{', '.join(_CONTAINER_EXTS)}, .npy, .ptu, .sdt, .zarr directories and photon "
        "tables (.csv: row,col,time_ps[,wavelength])."
    )


def _read_npy(p: Path) -> np.ndarray:
    """One array from a ``.npy`` file (never unpickled: object arrays are refused; the
    header's size is checked against the file's before anything is allocated)."""
    try:
        fmt = np.lib.format
        with open(p, "rb") as fp:
            try:
                v = fmt.read_magic(fp)
                read = fmt.read_array_header_1_0 if v == (1, 0) else fmt.read_array_header_2_0
                shape, _, dtype = read(fp)
            except Exception:  # a broken header: np.load below names the problem
                shape, dtype = None, None
            holds = os.fstat(fp.fileno()).st_size - fp.tell()
        if shape is not None and not dtype.hasobject:  # object arrays: np.load refuses them
            nbytes = math.prod(shape) * dtype.itemsize
            _claims_too_much(p, f"array {tuple(shape)}", nbytes, holds)
        return np.load(p, allow_pickle=False)
    except SplidarError:
        raise
    except ValueError as exc:
        raise SplidarError(
            f"cannot read '{p}' as a numeric .npy array ({exc}); splidar opens .npy files "
            "with allow_pickle=False: save a numeric array (np.save(path, array))."
        ) from None
    except OSError as exc:
        raise SplidarError(f"cannot read '{p}' as .npy: {exc}") from None


def _check_channels_apply(p: Path, channels) -> Path:
    from .vendor import VENDOR_SUFFIXES

    if channels is not None and _ext(p) not in VENDOR_SUFFIXES:
        raise SplidarError(
            f"`channels` applies to vendor files ({', '.join(VENDOR_SUFFIXES)}); '{p.name}' is "
            "not one."
        )
    return p


def _read_any(p: Path, channels) -> dict[str, Any]:
    """The variables of a data file: containers, ``.npy`` (``counts``) or vendor files."""
    from .vendor import VENDOR_SUFFIXES

    ext = _ext(p)
    if ext == ".npy":
        return {"counts": _read_npy(p)}
    if ext in (".csv", ".tsv"):
        from ._photon_table import read_table

        return read_table(p)
    if ext in VENDOR_SUFFIXES:
        from .vendor import read_vendor

        h = read_vendor(p, channels="wavelengths" if channels is None else channels)
        meta = {**h.metadata, "source": str(p)}
        return {"counts": h.counts, "bin_width_ps": h.bin_width_ps, "metadata": json.dumps(meta)}
    return _read_container(p)


def _summary(d: dict[str, Any]) -> str:
    parts = []
    for k, v in d.items():
        if isinstance(v, np.ndarray):
            kind = "cell/object array" if v.dtype == object else str(v.dtype)
            parts.append(f"'{k}' {v.shape} {kind}")
        else:
            parts.append(f"'{k}' {type(v).__name__}")
    return "; ".join(parts) or "(nothing)"


def _str_list(v) -> tuple[str, ...]:
    """Names from a string array, a MATLAB cell of strings or a char matrix."""
    if v is None:
        return ()
    if isinstance(v, str):
        return (v,)
    a = np.asarray(v)
    if (
        a.dtype.kind in "US"
        and a.ndim == 2
        and a.dtype.itemsize == np.dtype(a.dtype.kind + "1").itemsize
    ):
        return tuple("".join(r).strip() for r in a.astype(str))  # char matrix
    out = []
    for x in a.reshape(-1):
        if isinstance(x, np.ndarray):
            x = "".join(str(c) for c in x.reshape(-1))
        elif isinstance(x, bytes):
            x = x.decode()
        out.append(str(x).strip())
    return tuple(out)
