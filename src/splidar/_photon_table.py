"""Photon tables: one photon per line, with its pixel's row and column, its arrival time
and optionally its wavelength (channel), as CSV files or as 1-D columns of ``.npz`` /
HDF5 / ``.mat`` files (the form TCSPC software and lab scripts export).

The columns are recognised by name (case-insensitive, the last part of an HDF5 path, a
unit suffix such as ``_ps`` or ``(ns)`` stripped and taken as the time unit); the mapping
is logged. :func:`splidar.io.load` bins them like photon lists.
"""

from __future__ import annotations

import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import SplidarError

log = logging.getLogger("splidar.io")

#: accepted column names (lower case, unit suffix removed) of each role
ROLES = {
    "row": ("row", "rows", "y", "iy", "line", "pixel_row"),
    "col": ("col", "cols", "column", "x", "ix", "pixel_col", "pixel_column"),
    "pixel": ("pixel", "pixels", "pixel_index", "pixel_id", "pixel_idx", "pix", "pixel_number"),
    "time": (
        "time", "times", "t", "timestamp", "timestamps", "arrival_time", "arrival_times",
        "arrival", "toa", "tof", "dtime", "delay", "macrotime", "microtime",
    ),
    "wavelength": (
        "wavelength", "wavelengths", "lambda", "wl", "channel", "band", "spectral_channel",
    ),
}  # fmt: skip
TIME_UNITS = ("fs", "ps", "ns", "us", "ms", "s")
#: names of single numbers giving the image size of a table with a flat pixel column
SIZE_NAMES = {
    "rows": ("n_rows", "nrows", "num_rows", "rows", "height", "ny", "n_y", "n_lines"),
    "cols": ("n_cols", "ncols", "num_cols", "cols", "width", "nx", "n_x", "n_columns"),
}
_UNIT_RE = re.compile(r"^(.*?)(?:[ _]*[\(\[]\s*([a-z]+)\s*[\)\]]|_([a-z]+))?$")
EXAMPLE = "row,col,time_ps[,wavelength]"


def _role_base(name: str) -> tuple[str, str | None]:
    """A column name's base (lower case, last path part) and its unit suffix, if any."""
    leaf = name.rsplit("/", 1)[-1].strip().lower()
    m = _UNIT_RE.match(leaf)
    base, unit = (m.group(1), m.group(2) or m.group(3)) if m else (leaf, None)
    if unit is not None and unit not in TIME_UNITS and unit != "nm":
        return leaf, None  # a name like "pixel_row": no unit suffix
    return base, unit


def _role_and_unit(name: str) -> tuple[str | None, str | None]:
    base, unit = _role_base(name)
    for role, names in ROLES.items():
        if base in names:
            return role, unit
    return None, None


@dataclass(frozen=True)
class PhotonTable:
    """The recognised columns of a photon table (names as in the file)."""

    columns: dict[str, str]  # role -> column name
    time_unit: str | None  # from the time column's name, if it carries one


def find_photon_table(d: dict[str, Any]) -> PhotonTable | None:
    """The row, column, time (and wavelength) columns of ``d``, or None when ``d`` is not
    a photon table (no 1-D numeric columns for all three of row, column and time)."""
    found: dict[str, list[tuple[str, str | None]]] = {}
    for k, v in d.items():
        if isinstance(v, np.ndarray) and v.ndim == 1 and v.dtype.kind in "uif":
            role, unit = _role_and_unit(k)
            if role is not None:
                found.setdefault(role, []).append((k, unit))
    if "time" not in found or not ({"row", "col"} <= found.keys() or "pixel" in found):
        return None
    if {"row", "col"} <= found.keys():
        found.pop("pixel", None)  # row and column given: a pixel column is a label
    else:
        found.pop("row", None)
        found.pop("col", None)
    for role, cands in found.items():
        if len(cands) > 1:
            names = ", ".join(f"'{k}'" for k, _ in cands)
            raise SplidarError(
                f"the photon table has several {role} columns ({names}); keep one (columns "
                f"are recognised by name, e.g. {EXAMPLE})."
            )
    cols = {role: cands[0][0] for role, cands in found.items()}
    n = {len(d[c]) for c in cols.values()}
    if len(n) != 1:
        sizes = ", ".join(f"'{c}' {len(d[c])}" for c in cols.values())
        raise SplidarError(f"the photon table's columns differ in length: {sizes}.")
    return PhotonTable(columns=cols, time_unit=found["time"][0][1])


def _indices(a: np.ndarray, name: str, what: str) -> np.ndarray:
    if a.size and (a.dtype.kind == "f" and not np.all(np.isfinite(a) & (a == np.round(a)))):
        raise SplidarError(f"column '{name}' ({what}) must hold whole numbers; got {a[:3]}...")
    a = a.astype(np.int64)
    if a.size and a.min() < 0:
        raise SplidarError(
            f"column '{name}' ({what}) must hold 0-based indices >= 0; its minimum is {a.min()}."
        )
    return a


def table_as_flat(d: dict[str, Any], p: Path, table: PhotonTable, time_unit: str):
    """``d`` as flat photon lists (``times``, ``pixel_index``, ``shape``; the wavelengths
    folded into the columns: ``cols x L``), the time unit to use and L."""
    c = table.columns
    if "pixel" in c:
        row, col, rows, cols = _flat_pixels(d, p, c["pixel"])
    else:
        row = _indices(np.asarray(d[c["row"]]), c["row"], "pixel row")
        col = _indices(np.asarray(d[c["col"]]), c["col"], "pixel column")
    if "pixel" in c:
        pass  # the size is given
    elif "shape" in d:
        rows, cols = (int(s) for s in np.asarray(d["shape"]).reshape(-1)[:2])
    else:
        rows = int(row.max()) + 1 if row.size else 1
        cols = int(col.max()) + 1 if col.size else 1
    if row.size and (row.max() >= rows or col.max() >= cols):
        raise SplidarError(f"`shape` ({rows}, {cols}) in '{p.name}' is smaller than the indices.")
    unit = time_unit
    if table.time_unit is not None and time_unit == "bin":
        unit = table.time_unit
    elif table.time_unit is not None and time_unit != table.time_unit:
        log.warning(
            "column '%s' names the unit %s but time_unit=%s was given: times read in %s",
            c["time"], table.time_unit, time_unit, time_unit,
        )  # fmt: skip
    n_wl, wl_nm, l_idx = 1, None, None
    if "wavelength" in c:
        values, l_idx = np.unique(np.asarray(d[c["wavelength"]]), return_inverse=True)
        n_wl = len(values)
        is_channel = _role_base(c["wavelength"])[0] in ("channel", "band", "spectral_channel")
        if not is_channel and values.size and values.min() > 100:  # nm, not channel numbers
            wl_nm = values.astype(np.float64)
    log.info(
        "'%s' read as a photon table: %s, time '%s' (%s)%s; %d x %d pixels (%s)",
        p.name,
        f"pixel '{c['pixel']}' (row * cols + col)" if "pixel" in c
        else f"row '{c['row']}', column '{c['col']}'",
        c["time"], unit,
        f", wavelength '{c['wavelength']}' ({n_wl} values)" if "wavelength" in c else "",
        rows, cols,
        "from `shape`" if "shape" in d else "given" if "pixel" in c else "from the largest indices",
    )  # fmt: skip
    pix = row * cols + col
    if l_idx is not None:
        pix = pix * n_wl + l_idx.astype(np.int64).reshape(-1)
    out = {k: v for k, v in d.items() if k not in c.values()}
    out.update(times=np.asarray(d[c["time"]]), pixel_index=pix, shape=np.array([rows, cols * n_wl]))
    if wl_nm is not None:
        out["wavelengths_nm"] = wl_nm
    return out, unit, n_wl


def _image_size(d: dict[str, Any], p: Path, pixel: str) -> tuple[int, int]:
    """(rows, cols) of a table with a flat pixel column: a ``shape`` array, or two single
    numbers named as in :data:`SIZE_NAMES` (``n_rows`` / ``n_cols``, ``height`` /
    ``width``, ...)."""
    if "shape" in d:
        a = np.asarray(d["shape"]).reshape(-1)
        if a.size == 2 and a.dtype.kind in "uif" and np.all(a >= 1) and np.all(a == np.round(a)):
            return int(a[0]), int(a[1])
        raise SplidarError(
            f"`shape` in '{p.name}' must be two positive integers (rows, cols); got {a[:4]}."
        )
    size = []
    for names in SIZE_NAMES.values():
        hit = [k for k in d if k.rsplit("/", 1)[-1].lower() in names and np.size(d[k]) == 1]
        if len(hit) != 1:
            break
        v = float(np.asarray(d[hit[0]]).reshape(-1)[0])
        if not (v >= 1 and v == round(v)):
            break
        size.append(int(v))
    if len(size) == 2:
        return size[0], size[1]
    raise SplidarError(
        f"'{p.name}' is a photon table with a flat pixel column '{pixel}' (row * cols + col) "
        "but no image size: add a `shape` array (rows, cols), or two numbers named n_rows "
        "and n_cols (or height and width)."
    )


def _flat_pixels(d: dict[str, Any], p: Path, pixel: str):
    """Row and column of each photon of a flat pixel column, and the image size."""
    rows, cols = _image_size(d, p, pixel)
    pix = _indices(np.asarray(d[pixel]), pixel, "flat pixel index")
    n = rows * cols
    if pix.size and pix.max() >= n:
        hint = (
            " The largest index equals rows x cols: 1-based (MATLAB) indices? Subtract 1."
            if pix.max() == n and pix.min() >= 1
            else ""
        )
        raise SplidarError(
            f"column '{pixel}' of '{p.name}' holds pixel indices up to {pix.max()}, beyond the "
            f"{rows} x {cols} image (0-based row * cols + col, below {n}).{hint}"
        )
    row, col = np.divmod(pix, cols)
    return row, col, rows, cols


def read_table(p: Path) -> dict[str, np.ndarray]:
    """The columns of a delimited text file with a header row (``,``, tab, ``;`` or
    spaces)."""
    with open(p, encoding="utf-8", errors="replace") as fp:
        header = fp.readline().strip()
    delim = next((c for c in (",", "\t", ";") if c in header), None)  # else whitespace
    names = [h.strip().strip('"').strip("'") for h in header.split(delim)]
    if not names or all(_is_number(h) for h in names):
        raise SplidarError(
            f"'{p.name}' has no header row naming its columns; splidar reads photon tables "
            f"with one, e.g. `{EXAMPLE}` (one photon per line)."
        )
    try:
        with warnings.catch_warnings():  # "input contained no data": an empty table is fine
            warnings.simplefilter("ignore", UserWarning)
            a = np.loadtxt(p, delimiter=delim, skiprows=1, ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise SplidarError(f"cannot read '{p.name}' as a numeric table: {exc}") from None
    if a.size and a.shape[1] != len(names):
        raise SplidarError(
            f"'{p.name}': the header names {len(names)} columns ({', '.join(names)}) but the "
            f"lines hold {a.shape[1]} values."
        )
    if a.size == 0:
        a = np.zeros((0, len(names)))
    return {n: a[:, i] for i, n in enumerate(names)}


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
