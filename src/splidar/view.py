"""An interactive 3D view of a point cloud as one self-contained HTML file.

:func:`write_view` writes ``view.html``: the points of a reconstruction (or of a
``result.npz`` / output folder of ``splidar run``) drawn by a small WebGL renderer
in plain JavaScript, with every byte it needs inside the file: no network request,
no external script, so it opens offline (air-gapped labs) in any current browser.
Rotate, zoom and pan with the mouse or touch; colour by depth, class label,
intensity, spectral colour, uncertainty or label confidence; show one surface layer
or all; a legend names the classes.

The points travel as base64 typed arrays (gzip-compressed, decoded by the browser's
own ``DecompressionStream``) and are drawn in one ``gl.drawArrays`` call, sorted by
layer so that each layer is one contiguous range. ``window.splidarView`` exposes the
viewer's state (``ready``, ``nPoints``, ``drawn``, ``drawCalls``, ``setColor``,
``setLayer``, ``litPixels``) for tests and scripting.
"""

from __future__ import annotations

import base64
import gzip
import html
import json
import logging
import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import SplidarError, check_positive
from ._version import __version__
from .points import PointSet

__all__ = ["ViewInput", "is_view_file", "load_view_input", "view_html", "write_view"]

log = logging.getLogger(__name__)

_BACKGROUND = (22, 24, 29)  # the page's background, #16181d
_LUT_SIZE = 256
_MAX_PIXELS = 65535  # rows and cols travel as uint16
_Q = 65535.0  # continuous attributes are quantised to uint16 (display only)
_TEMPLATE = "_view_template.html"


@dataclass(frozen=True)
class ViewInput:
    """What the viewer shows: points, class names and the depth unit.

    Attributes
    ----------
    points : PointSet
        The points (any number of layers and wavelengths).
    class_names : tuple of str
        Name of each label (``class k`` when unknown).
    bin_width_ps : float or None
        Bin width, for depths in metres when the points carry no ``depth_m``.
    title : str
        Page title (e.g. the output folder's name).
    """

    points: PointSet
    class_names: tuple[str, ...]
    bin_width_ps: float | None
    title: str


def load_view_input(result: Any, *, title: str | None = None) -> ViewInput:
    """Gather the points, class names and bin width of a result.

    Parameters
    ----------
    result : Reconstruction, PointSet, ViewInput, str or path-like
        A reconstruction, a point set, or a path to a ``result.npz``, an output folder of
        ``splidar run``/``demo`` (its ``result.npz``) or a point-set ``.npz``.
    title : str, optional
        Page title; default the folder's or file's name, else ``"splidar points"``.

    Returns
    -------
    ViewInput

    Raises
    ------
    SplidarError
        A missing file, or one that holds no points.

    Examples
    --------
    >>> import splidar
    >>> p = splidar.PointSet(row=[0, 1], col=[0, 1], depth_bin=[10.0, 12.0], image_shape=(2, 2))
    >>> v = load_view_input(p)
    >>> len(v.points), v.title
    (2, 'splidar points')
    """
    if isinstance(result, ViewInput):
        return result if title is None else ViewInput(**{**result.__dict__, "title": title})
    if isinstance(result, PointSet):
        k = int(result.label.max()) + 1 if result.label is not None and len(result) else 1
        names = tuple(f"class {i}" for i in range(k))
        return ViewInput(result, names, None, title or "splidar points")
    if isinstance(result, str | os.PathLike):
        return _load_path(Path(result), title)
    points = getattr(result, "points", None)
    if not isinstance(points, PointSet):
        raise SplidarError(
            "`result` must be a Reconstruction, a PointSet or the path of a result.npz or "
            f"output folder; got {type(result).__name__}."
        )
    names = tuple(str(c) for c in (getattr(result, "class_names", None) or ()))
    bw = getattr(result, "bin_width_ps", None)
    return ViewInput(points, names, bw, title or "splidar points")


def _load_path(p: Path, title: str | None) -> ViewInput:
    folder_title = p.name
    if p.is_dir():
        if not (p / "result.npz").is_file():
            raise SplidarError(
                f"folder '{p}' holds no result.npz; pass an output folder of 'splidar run' or "
                "its result.npz"
            )
        p = p / "result.npz"
    elif p.name == "result.npz":
        folder_title = p.resolve().parent.name
    if not p.is_file():
        raise SplidarError(f"file '{p}' does not exist; pass a result.npz or an output folder")
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SplidarError(f"cannot read '{p}' as a .npz of points ({exc})") from None
    with z:
        files = set(getattr(z, "files", ()))
        if "points_row" in files:
            points = PointSet.from_dict({k[7:]: z[k] for k in files if k.startswith("points_")})
        elif "row" in files:
            points = PointSet.from_dict(z)
        else:
            raise SplidarError(
                f"'{p}' holds no points (arrays: {', '.join(sorted(files)[:8]) or 'none'}); "
                "pass a result.npz of 'splidar run' or a point-set .npz"
            )
        names = tuple(str(c) for c in z["class_names"]) if "class_names" in files else ()
        bw = float(z["bin_width_ps"]) if "bin_width_ps" in files else float("nan")
    k = int(points.label.max()) + 1 if points.label is not None and len(points) else 1
    if len(names) < k:
        names = names + tuple(f"class {i}" for i in range(len(names), k))
    return ViewInput(points, names, bw if np.isfinite(bw) else None, title or folder_title)


# --------------------------------------------------------------------------------------
# colours
# --------------------------------------------------------------------------------------
def _lut(name: str) -> list[int]:
    import matplotlib

    cmap = matplotlib.colormaps[name].resampled(_LUT_SIZE)
    rgb = np.round(cmap(np.linspace(0, 1, _LUT_SIZE))[:, :3] * 255).astype(int)
    return rgb.reshape(-1).tolist()


def _class_lut(k: int) -> list[int]:
    import matplotlib

    if k <= 10:
        cols = matplotlib.colormaps["tab10"].colors[:k]
    elif k <= 20:
        cols = matplotlib.colormaps["tab20"].colors[:k]
    else:  # evenly spread hues, alternating lightness
        import colorsys

        cols = [
            colorsys.hls_to_rgb((i * 0.618034) % 1.0, 0.45 + 0.15 * (i % 2), 0.75) for i in range(k)
        ]
    return np.round(np.asarray(cols, dtype=float) * 255).astype(int).reshape(-1).tolist()


def _quantise(v: np.ndarray) -> tuple[np.ndarray, float, float]:
    """uint16 codes q with ``v ~ scale * q + offset`` over the finite range of v (NaN -> 0)."""
    v = np.asarray(v, dtype=np.float64)
    fin = np.isfinite(v)
    lo = float(v[fin].min()) if fin.any() else 0.0
    hi = float(v[fin].max()) if fin.any() else 1.0
    scale = (hi - lo) / _Q if hi > lo else 1.0
    q = np.zeros(v.shape, np.uint16)
    q[fin] = np.round((v[fin] - lo) / scale).clip(0, _Q).astype(np.uint16)
    return q, scale, lo


def _robust_range(v: np.ndarray, *, lo_pct: float = 0.0, hi_pct: float = 99.0):
    fin = np.asarray(v, dtype=np.float64)
    fin = fin[np.isfinite(fin)]
    if fin.size == 0:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(fin, [lo_pct, hi_pct]))
    if not hi > lo:
        lo, hi = float(fin.min()), float(fin.max())
    if not hi > lo:
        hi = lo + 1.0
    return lo, hi


def _continuous(
    arrays: dict, name: str, values: np.ndarray, title: str, cmap: str, **range_kw
) -> dict[str, Any]:
    if name in arrays:  # drawn from an array already sent (the depth)
        scale, offset = 1.0, 0.0
    else:
        arrays[name], scale, offset = _quantise(values)
    lo, hi = _robust_range(values, **range_kw)
    spec: dict[str, Any] = {"kind": "continuous", "array": name, "scale": scale}
    spec.update(offset=offset, lo=lo, hi=hi, lut=_lut(cmap), title=title)
    fin = values[np.isfinite(values)]
    if fin.size and hi < fin.max():
        spec["hi_note"] = "\u2265 "
    if fin.size and lo > fin.min():
        spec["lo_note"] = "\u2264 "
    return spec


def _color_modes(v: ViewInput, order: np.ndarray, depth: np.ndarray, unit: str):
    """Colour modes (legend specs) and the attribute arrays they read, in draw order."""
    p = v.points
    arrays: dict[str, np.ndarray] = {}
    modes: dict[str, dict[str, Any]] = {}
    arrays["depth"] = depth.astype(np.float32)
    modes["depth"] = _continuous(
        arrays, "depth", depth, f"depth ({unit})", "viridis", lo_pct=0.5, hi_pct=99.5
    )
    modes["depth"]["label"] = "depth"
    k = max(len(v.class_names), 1)
    if p.label is not None and len(p):
        label = np.clip(p.label[order], 0, k - 1)
        counts = np.bincount(label, minlength=k).tolist()
        arrays["label"] = label.astype(np.uint8 if k <= 256 else np.uint16)
        modes["label"] = {
            "kind": "categorical",
            "array": "label",
            "label": "class label",
            "title": "class (points)",
            "names": list(v.class_names) or ["class 0"],
            "counts": counts,
            "lut": _class_lut(k),
        }
    if p.intensity is not None:
        total = p.intensity[order].sum(axis=1, dtype=np.float64)
        modes["intensity"] = _continuous(
            arrays, "q_intensity", total, "intensity (signal photons, all wavelengths)", "magma"
        )
        modes["intensity"]["label"] = "intensity"
        if p.intensity.shape[1] >= 3:
            from .export import point_colors

            arrays["spectral"] = point_colors(p)[order].reshape(-1)
            L = p.intensity.shape[1]
            modes["spectral"] = {
                "kind": "rgb",
                "label": "spectral colour",
                "title": "spectral colour",
                "note": f"red, green, blue = wavelengths {L}, {L // 2 + 1} and 1 of {L}",
            }
    if p.intensity_std is not None:
        std = np.sqrt((p.intensity_std[order].astype(np.float64) ** 2).sum(axis=1))
        modes["uncertainty"] = _continuous(
            arrays, "q_uncertainty", std, "intensity std (photons, posterior)", "inferno"
        )
        modes["uncertainty"]["label"] = "uncertainty"
    if p.label_confidence is not None:
        conf = p.label_confidence[order].astype(np.float64)
        modes["confidence"] = _continuous(
            arrays, "q_confidence", conf, "label confidence (posterior)", "cividis", hi_pct=100
        )
        modes["confidence"].update(label="label confidence", lo=0.0, hi=1.0)
        modes["confidence"].pop("lo_note", None)
        modes["confidence"].pop("hi_note", None)
    return modes, arrays


# --------------------------------------------------------------------------------------
# the page
# --------------------------------------------------------------------------------------
def _depths(v: ViewInput) -> tuple[np.ndarray, str, bool]:
    p = v.points
    if p.depth_m is not None and np.all(np.isfinite(p.depth_m)):
        return np.asarray(p.depth_m, np.float64), "m", True
    if v.bin_width_ps is not None:
        from .cube import SPEED_OF_LIGHT

        return p.depth_bin * (v.bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0), "m", True
    return np.asarray(p.depth_bin, np.float64), "bins", False


def _pack(arrays: dict[str, np.ndarray], delta: dict[str, int]) -> tuple[bytes, list]:
    """One buffer of all arrays, coded for gzip; rows (name, kind, offset, length, delta).

    An array named in ``delta`` is stored as differences of elements ``delta[name]``
    apart (uint16, wrapping), which turns the sorted pixel indices into runs of small
    numbers; every array of multi-byte items is stored byte plane by byte plane (all
    first bytes, then all second bytes, ...), which groups the slowly varying high bytes.
    The page undoes both.
    """
    kinds = {np.dtype(np.uint8): "u8", np.dtype(np.uint16): "u16", np.dtype(np.float32): "f32"}
    parts, table, offset = [], [], 0
    for name, a in arrays.items():
        a = np.ascontiguousarray(a).astype(np.dtype(a.dtype).newbyteorder("<"), copy=False)
        kind = kinds[a.dtype.newbyteorder("=")]
        step = delta.get(name, 0)
        if step:
            a = a.copy()
            a[step:] = a[step:] - a[:-step]  # uint16 arithmetic wraps, as in the page
        planes = a.view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()
        table.append([name, kind, offset, int(a.size), step])
        pad = (-len(planes)) % 4
        parts += [planes, b"\0" * pad]
        offset += len(planes) + pad
    return b"".join(parts), table


def view_html(
    result: Any,
    *,
    pixel_size: float | None = None,
    title: str | None = None,
    color: str = "depth",
    compress: bool = True,
) -> str:
    """The HTML text of the interactive 3D view (see :func:`write_view`).

    Examples
    --------
    >>> import splidar
    >>> p = splidar.PointSet(row=[0, 1], col=[0, 1], depth_bin=[10.0, 12.0], image_shape=(2, 2))
    >>> html = view_html(p, title="two points")
    >>> html.startswith("<!DOCTYPE html>"), "two points" in html
    (True, True)
    """
    v = load_view_input(result, title=title)
    p = v.points
    n = len(p)
    rows, cols = p.image_shape
    if max(rows, cols) > _MAX_PIXELS:
        raise SplidarError(
            f"the viewer handles images up to {_MAX_PIXELS} pixels a side; got {rows} x {cols}"
        )
    if pixel_size is not None:
        pixel_size = check_positive(pixel_size, "pixel_size")
    layer = p.layer if p.layer is not None else np.zeros(n, np.int64)
    order = np.argsort(layer, kind="stable")  # each layer one contiguous range
    depth, unit, metric = _depths(v)
    depth = depth[order]
    fin = np.isfinite(depth)
    if not fin.all():
        log.warning("view: %d points without a finite depth are drawn at depth 0", (~fin).sum())
        depth = np.where(fin, depth, 0.0)
    modes, attr = _color_modes(v, order, depth, unit)
    if color not in modes:
        raise SplidarError(
            f"`color` must be one of {', '.join(modes)} for these points; got {color!r}"
        )
    rowcol = np.empty((n, 2), np.uint16)
    rowcol[:, 0], rowcol[:, 1] = p.row[order], p.col[order]
    arrays = {"rowcol": rowcol.reshape(-1), **attr}
    payload, table = _pack(arrays, {"rowcol": 2})
    raw_bytes = len(payload)
    if compress:
        payload = gzip.compress(payload, compresslevel=6, mtime=0)
    log.debug(
        "view: %d points, %d colour modes, %d bytes of arrays (%d after coding)",
        n,
        len(modes),
        raw_bytes,
        len(payload),
    )
    # scene units: pixels (or pixel_size) across; depth stretched to the same unit when both
    # are metric, else to half the image width so that the relief is visible
    px = pixel_size or 1.0
    d_lo, d_hi = (float(depth.min()), float(depth.max())) if n else (0.0, 1.0)
    d_span = max(d_hi - d_lo, 1e-12)
    if metric and pixel_size is not None:
        zscale, note = 1.0, "x, y, depth in metres"
    else:
        zscale = 0.5 * max(rows, cols) * px / d_span
        note = f"depth ({unit}) stretched to half the image width"
    lay_ids, lay_counts = np.unique(layer, return_counts=True)
    starts = np.cumsum(lay_counts) - lay_counts
    layers = [
        {
            "name": "nearest layer" if k == 0 else f"layer {k + 1}",
            "range": [int(s), int(c)],
        }
        for k, s, c in zip(lay_ids.tolist(), starts.tolist(), lay_counts.tolist(), strict=True)
    ]
    info = (
        f"{n:,} points, {rows} x {cols} pixels, {len(layers)} layer(s), "
        f"{p.n_wavelengths} wavelength(s); {note}"
    )
    meta = {
        "n": n,
        "title": v.title,
        "info": info,
        "arrays": table,
        "compression": "gzip" if compress else None,
        "colors": modes,
        "default_color": color,
        "layers": layers,
        "pixel": px,
        "zscale": zscale,
        "center": [(cols - 1) / 2.0, (rows - 1) / 2.0, (d_lo + d_hi) / 2.0],
        "extent": [cols * px / 2.0, rows * px / 2.0, d_span * zscale / 2.0],
        "point_size": 1.5 if n > 300_000 else 2.5 if n > 30_000 else 4.0,
        "background": list(_BACKGROUND),
    }
    # JSON inside <script>: no "<" so that no "</script>" can end it early
    meta_text = json.dumps(meta, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    template = resources.files("splidar").joinpath(_TEMPLATE).read_text(encoding="utf-8")
    fill = {
        "VERSION": __version__,
        "TITLE": html.escape(v.title),
        "META": meta_text,
        "DATA": base64.b64encode(payload).decode("ascii"),
    }
    # one pass, so that a placeholder inside a title or class name stays text
    return re.sub(r"__SPLIDAR_([A-Z]+)__", lambda m: fill[m.group(1)], template)


def write_view(
    result: Any,
    path: str | os.PathLike,
    *,
    pixel_size: float | None = None,
    title: str | None = None,
    color: str = "depth",
    compress: bool = True,
) -> Path:
    """Write an interactive 3D view of the points as one self-contained HTML file.

    Parameters
    ----------
    result : Reconstruction, PointSet, str or path-like
        The points: a reconstruction, a point set, or the path of a ``result.npz`` or an
        output folder of ``splidar run``/``demo``.
    path : str or path-like
        Destination ``.html`` (overwritten).
    pixel_size : float, optional
        Pixel footprint in metres. With it and a known bin width the view is metric
        (x, y and depth in metres, not stretched); otherwise x and y are in pixels and
        the depth is stretched to half the image width (a slider changes the stretch).
    title : str, optional
        Page title; default the folder's name.
    color : {'depth', 'label', 'intensity', 'spectral', 'uncertainty', 'confidence'}
        Initial colouring (the page switches between those the points support).
    compress : bool, default True
        gzip the embedded arrays (decoded by the browser's ``DecompressionStream``:
        Chrome/Edge 80+, Firefox 113+, Safari 16.4+). ``False`` writes a larger file that
        also opens in older browsers.

    Returns
    -------
    pathlib.Path
        ``path``.

    Notes
    -----
    Coordinates as in :func:`splidar.export.write_ply`: ``x = col``, ``y = -row`` (image
    upright), ``z = -depth`` (the sensor looks down -z; "Sensor view" puts the camera
    there). Per point the file holds rows and columns (uint16), the depth (float32) and
    the colouring attributes (uint8 labels, uint16 quantised intensity, uncertainty and
    confidence, uint8 spectral RGB): about 15 bytes a point before compression; the
    legend's ranges are exact. Colour ranges of intensity and uncertainty end at the
    99th percentile, of depth span the 0.5-99.5th percentiles.

    The page makes no network request (a Content-Security-Policy forbids them) and
    draws every point of the shown layers in one ``gl.drawArrays`` call.

    Raises
    ------
    SplidarError
        ``result`` holds no points, ``color`` is not available for them, or the image is
        wider than 65,535 pixels.
    OSError
        The file cannot be written.

    Examples
    --------
    >>> import splidar, tempfile, pathlib
    >>> from splidar.view import write_view
    >>> p = splidar.PointSet(row=[0, 1], col=[0, 1], depth_bin=[10.0, 12.0],
    ...                      image_shape=(2, 2))
    >>> f = write_view(p, pathlib.Path(tempfile.mkdtemp()) / "view.html")
    >>> f.read_text().startswith("<!DOCTYPE html>")
    True
    """
    text = view_html(result, pixel_size=pixel_size, title=title, color=color, compress=compress)
    path = Path(path)
    path.write_text(text, encoding="utf-8")
    return path


def is_view_file(path: str | os.PathLike) -> bool:
    """True when ``path`` is an HTML view written by splidar (safe to replace).

    Examples
    --------
    >>> import splidar
    >>> p = splidar.PointSet(row=[0, 1], col=[0, 1], depth_bin=[10.0, 12.0], image_shape=(2, 2))
    >>> f = write_view(p, "view.html")
    >>> is_view_file(f), is_view_file("no-such-file.html")
    (True, False)
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError:
        return False
    return b'<meta name="generator" content="splidar ' in head
