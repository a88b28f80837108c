"""Low-level file readers shared by :mod:`splidar.io` and :mod:`splidar.library`.

A ``.npz`` / ``.mat`` / ``.h5`` file becomes ``{name: NumPy value}``. This module imports
no other splidar module but ``_validation``, so that ``library`` (which reads library
files) and ``io`` (which reads cubes holding libraries) both use it without an import cycle.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import SplidarError, describe

_CONTAINER_EXTS = (".npz", ".mat", ".h5", ".hdf5")


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


def _read_hdf5(p: Path, matlab: bool) -> dict[str, Any]:
    import h5py

    out: dict[str, Any] = {}
    with h5py.File(p, "r") as f:

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and not name.startswith("#"):  # #refs#, #subsystem#
                out[name] = _h5_to_numpy(f, obj, matlab)

        f.visititems(visit)
        for k, v in f.attrs.items():
            if k not in out and not k.startswith("MATLAB"):
                out[k] = v.decode() if isinstance(v, bytes) else v
    return out


def _read_container(p: Path) -> dict[str, Any]:
    """Every variable of a .npz / .mat / .h5 file as NumPy values (cells -> object arrays)."""
    ext = _ext(p)
    if ext == ".npz":
        try:
            with np.load(p, allow_pickle=True) as z:
                return {k: z[k] for k in z.files}
        except Exception as exc:
            raise SplidarError(f"cannot read '{p}' as .npz: {exc}") from None
    if ext == ".mat":
        if _is_hdf5(p):
            return _read_hdf5(p, matlab=True)
        import scipy.io

        try:
            d = scipy.io.loadmat(p, squeeze_me=False, mat_dtype=False)
        except Exception as exc:
            raise SplidarError(f"cannot read '{p}' as a MATLAB file: {exc}") from None
        return {k: v for k, v in d.items() if not k.startswith("__")}
    if ext in (".h5", ".hdf5"):
        if not _is_hdf5(p):
            raise SplidarError(f"'{p}' is not an HDF5 file.")
        return _read_hdf5(p, matlab=False)
    raise SplidarError(
        f"unknown file extension '{p.suffix}' for '{p}'; splidar reads "
        f"{', '.join(_CONTAINER_EXTS)} and .zarr directories."
    )


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
