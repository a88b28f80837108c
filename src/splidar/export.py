"""Writing results to files other tools read: CSV, binary PLY, ``.npz`` and a JSON summary.

Every writer takes the result first and the destination path second, writes one file and
returns its path. They are what ``splidar run`` and ``splidar demo`` write into their
output folder; they are equally usable from Python.

File formats
------------
``points.csv``
    One line per point. The first columns are exactly
    ``row,col,depth_bin,label,intensity_0,...,intensity_{L-1}``; further columns follow
    when known: ``depth_m``, ``intensity_std_0..``, ``label_confidence``, ``layer``.
``points.ply``
    Binary little-endian PLY with one ``vertex`` element: ``x y z`` (float32), ``depth``
    (float32), ``intensity_0..`` (float32), ``label`` (int32), ``layer`` (int32) and
    ``red green blue`` (uchar) for viewers (CloudCompare, MeshLab).
``result.npz``
    Maps, points and the 3D detection map (see :func:`write_npz`).
``summary.json``
    Parameters, versions, timings, counts and data reduction (see :func:`write_summary`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._arrays import sample_rows
from ._files import atomic_path, savez
from ._validation import SplidarError, check_positive
from .points import PointSet

__all__ = ["point_colors", "write_csv", "write_npz", "write_ply", "write_summary"]

logger = logging.getLogger(__name__)

#: A threshold array larger than this is summarised (median) in result.npz, not stored.
_MAX_THRESHOLD_VALUES = 65_536


def _as_points(result) -> PointSet:
    """A :class:`PointSet` from a PointSet, a Reconstruction or a Detection."""
    if isinstance(result, PointSet):
        return result
    pts = getattr(result, "points", None)
    if isinstance(pts, PointSet):
        return pts
    raise SplidarError(
        f"expected a PointSet, Reconstruction or Detection; got {type(result).__name__}."
    )


def _labels(points: PointSet) -> np.ndarray:
    # without a library every point is class 0 (ALGORITHM-NOTES conventions)
    return points.label if points.label is not None else np.zeros(len(points), np.int64)


def _intensity(points: PointSet) -> np.ndarray:
    if points.intensity is None:
        return np.zeros((len(points), 0))
    return points.intensity


def write_csv(points: PointSet | Any, path: str | os.PathLike) -> Path:
    """Write points as CSV, one line per point.

    Parameters
    ----------
    points : PointSet, Reconstruction or Detection
        n points with L intensities (``L = 0`` when there is no intensity).
    path : str or path-like
        Destination file (overwritten).

    Returns
    -------
    pathlib.Path
        ``path``.

    Notes
    -----
    The header is exactly ``row,col,depth_bin,label,intensity_0,...,intensity_{L-1}``,
    then, when present, ``depth_m``, ``intensity_std_0..intensity_std_{L-1}``,
    ``label_confidence`` and ``layer``. ``label`` is 0 for every point when the points
    carry no labels (one class). Floats are written with 7 significant digits
    (float32 precision), integers as integers.

    Raises
    ------
    SplidarError
        ``points`` is not a point set or a result holding one.
    OSError
        The file cannot be written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = PointSet(row=[0], col=[1], depth_bin=[12.5], image_shape=(2, 2), intensity=[[3.0, 4.0]])
    >>> f = write_csv(p, pathlib.Path(tempfile.mkdtemp()) / "points.csv")
    >>> f.read_text().splitlines()[0]
    'row,col,depth_bin,label,intensity_0,intensity_1'
    """
    p = _as_points(points)
    n = len(p)
    inten = _intensity(p)
    L = inten.shape[1]
    names = ["row", "col", "depth_bin", "label"] + [f"intensity_{i}" for i in range(L)]
    cols: list[np.ndarray] = [p.row, p.col, p.depth_bin, _labels(p)] + [
        inten[:, i] for i in range(L)
    ]
    fmts = ["%d", "%d", "%.7g", "%d"] + ["%.7g"] * L
    if p.depth_m is not None:
        names.append("depth_m")
        cols.append(p.depth_m)
        fmts.append("%.7g")
    if p.intensity_std is not None:
        names += [f"intensity_std_{i}" for i in range(p.intensity_std.shape[1])]
        cols += [p.intensity_std[:, i] for i in range(p.intensity_std.shape[1])]
        fmts += ["%.7g"] * p.intensity_std.shape[1]
    if p.label_confidence is not None:
        names.append("label_confidence")
        cols.append(p.label_confidence)
        fmts.append("%.7g")
    if p.layer is not None:
        names.append("layer")
        cols.append(p.layer)
        fmts.append("%d")
    path = Path(path)
    table = np.empty((n, len(cols)), dtype=object)
    for j, c in enumerate(cols):
        table[:, j] = np.asarray(c)
    with atomic_path(path) as tmp, open(tmp, "w", newline="\n", encoding="ascii") as fh:
        fh.write(",".join(names) + "\n")
        if n:
            np.savetxt(fh, table, fmt=fmts, delimiter=",")
    return path


def point_colors(points: PointSet | Any, *, percentile: float = 99.0) -> np.ndarray:
    """Display colours of points from their intensity, ``(n, 3)`` uint8.

    With L >= 3 wavelengths the last, middle and first channels become red, green and
    blue (wavelengths are assumed in increasing order, as in the cube); with fewer the
    colour is grey from the total intensity. Values are scaled so that the given
    percentile of all channels maps to 255 (a display choice only; the intensities
    written beside the colours are untouched). Points without intensity are mid grey.

    Examples
    --------
    >>> p = PointSet(row=[0, 1], col=[0, 0], depth_bin=[1.0, 2.0], image_shape=(2, 1),
    ...              intensity=[[0.0], [10.0]])
    >>> point_colors(p, percentile=100).tolist()
    [[0, 0, 0], [255, 255, 255]]
    """
    p = _as_points(points)
    n = len(p)
    if p.intensity is None or n == 0:
        return np.full((n, 3), 128, np.uint8)
    inten = p.intensity
    L = inten.shape[1]
    if L >= 3:
        rgb = inten[:, [L - 1, L // 2, 0]].astype(np.float64)
    else:
        rgb = np.repeat(inten.sum(axis=1, dtype=np.float64)[:, None], 3, axis=1)
    rgb = np.clip(rgb, 0, None)
    top = float(np.percentile(rgb, percentile))
    if not top > 0:
        top = float(rgb.max()) or 1.0
    return np.round(np.clip(rgb / top, 0, 1) * 255).astype(np.uint8)


def write_ply(
    points: PointSet | Any,
    path: str | os.PathLike,
    *,
    bin_width_ps: float | None = None,
    pixel_size: float = 1.0,
) -> Path:
    """Write points as a binary little-endian PLY point cloud.

    Parameters
    ----------
    points : PointSet, Reconstruction or Detection
        n points with L intensities.
    path : str or path-like
        Destination file (overwritten).
    bin_width_ps : float, optional
        Bin width in picoseconds, used for depths in metres when the points carry no
        ``depth_m`` (a Reconstruction passes its own).
    pixel_size : float, default 1.0
        Length of one pixel in the units of x and y. The default keeps x and y in pixels;
        pass the pixel footprint at the target in metres to get a metric cloud.

    Returns
    -------
    pathlib.Path
        ``path``.

    Notes
    -----
    Coordinates: ``x = col * pixel_size``, ``y = (rows - 1 - row) * pixel_size`` (the
    image upright) and ``z = -depth``, with depth in metres when known, else in time
    bins. The minus sign makes the frame right-handed with the sensor looking down -z,
    which is the default view of CloudCompare and MeshLab: the nearest surface faces the
    viewer. The positive depth is also stored as the ``depth`` property. Per-vertex
    properties: ``x y z depth`` (float32), ``intensity_0..intensity_{L-1}`` (float32),
    ``label`` and ``layer`` (int32, ``layer`` = -1 when unknown), and ``red green blue``
    (uchar, see :func:`point_colors`).

    Raises
    ------
    SplidarError
        ``points`` is not a point set, or ``bin_width_ps``/``pixel_size`` is not > 0.
    OSError
        The file cannot be written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = PointSet(row=[0], col=[1], depth_bin=[12.5], image_shape=(2, 2), intensity=[[3.0]])
    >>> f = write_ply(p, pathlib.Path(tempfile.mkdtemp()) / "points.ply")
    >>> f.read_bytes().startswith(b"ply\\nformat binary_little_endian 1.0\\n")
    True
    """
    p = _as_points(points)
    if bin_width_ps is None and not isinstance(points, PointSet):
        bin_width_ps = getattr(points, "bin_width_ps", None)
    if bin_width_ps is not None:
        bin_width_ps = check_positive(bin_width_ps, "bin_width_ps")
    pixel_size = check_positive(pixel_size, "pixel_size")
    n = len(p)
    rows = p.image_shape[0]
    if p.depth_m is not None and np.all(np.isfinite(p.depth_m)):
        depth, unit = p.depth_m, "metres"
    elif bin_width_ps is not None:
        from .cube import SPEED_OF_LIGHT

        depth, unit = p.depth_bin * (bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0), "metres"
    else:
        depth, unit = p.depth_bin, "time bins"
    inten = _intensity(p)
    L = inten.shape[1]
    dtype = (
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("depth", "<f4")]
        + [(f"intensity_{i}", "<f4") for i in range(L)]
        + [("label", "<i4"), ("layer", "<i4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )
    v = np.empty(n, dtype=dtype)
    v["x"] = p.col * pixel_size
    v["y"] = (rows - 1 - p.row) * pixel_size
    v["z"] = -depth
    v["depth"] = depth
    for i in range(L):
        v[f"intensity_{i}"] = inten[:, i]
    v["label"] = _labels(p)
    v["layer"] = p.layer if p.layer is not None else -1
    rgb = point_colors(p)
    v["red"], v["green"], v["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    ply_type = {"<f4": "float", "<i4": "int", "u1": "uchar"}
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by splidar",
        f"comment x = col * {pixel_size:g}, y = (rows - 1 - row) * {pixel_size:g}, "
        f"z = -depth, depth in {unit}",
        f"element vertex {n}",
    ]
    header += [f"property {ply_type[t]} {name}" for name, t in dtype]
    header.append("end_header")
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(v.tobytes())
    return path


def _maps_m(rec, depth_map: np.ndarray) -> np.ndarray | None:
    bw = getattr(rec, "bin_width_ps", None)
    if bw is None:
        return None
    from .cube import SPEED_OF_LIGHT

    return depth_map * (bw * 1e-12 * SPEED_OF_LIGHT / 2.0)


def write_npz(reconstruction, path: str | os.PathLike) -> Path:
    """Write a reconstruction's maps, points and 3D detection map to a compressed ``.npz``.

    Parameters
    ----------
    reconstruction : Reconstruction
        The result of :func:`splidar.reconstruct` or :func:`splidar.process`.
    path : str or path-like
        Destination ``.npz`` (overwritten).

    Returns
    -------
    pathlib.Path
        ``path``.

    Notes
    -----
    Arrays stored (K_s layers, L wavelengths, T bins):

    - ``depth_map`` (rows, cols, K_s) bins, NaN where no surface; ``depth_map_m`` in
      metres when the bin width is known; ``intensity_map`` (rows, cols, K_s, L);
      ``label_map`` (rows, cols, K_s), -1 where no surface;
    - ``points_<field>`` for every field of the PointSet (``points_row``, ...,
      ``points_image_shape``): ``PointSet.from_dict`` of these with the prefix removed
      rebuilds the points, and ``splidar evaluate`` reads this file directly;
    - ``class_names``, ``bin_width_ps`` (NaN when unknown), ``wavelengths_nm`` (when known);
    - from the detection, when attached: ``detection_mask`` (rows, cols, T) bool, the 3D
      binary map M; ``detection_threshold`` (or ``detection_threshold_median`` when the
      threshold varies over more than 65,536 voxels); ``null_shape``, ``null_scale`` (the gamma
      null of ``eq:gamma_distrib``); ``background_spatial`` (rows, cols, L) and
      ``background_temporal`` (L, T).

    Raises
    ------
    SplidarError
        ``reconstruction`` lacks the maps of a Reconstruction.
    OSError
        The file cannot be written.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> f = write_npz(rec, "result.npz")
    >>> import numpy as np
    >>> with np.load(f) as z:
    ...     depth = z["depth_map"][..., 0]     # nearest surface, bins
    >>> depth.shape
    (16, 16)
    """
    for name in ("points", "depth_map", "intensity_map", "label_map"):
        if not hasattr(reconstruction, name):
            raise SplidarError(
                f"write_npz needs a Reconstruction; got {type(reconstruction).__name__} "
                f"without `{name}`."
            )
    rec = reconstruction
    arrays: dict[str, Any] = {
        "depth_map": np.asarray(rec.depth_map),
        "intensity_map": np.asarray(rec.intensity_map),
        "label_map": np.asarray(rec.label_map),
    }
    dm = _maps_m(rec, arrays["depth_map"])
    if dm is not None:
        arrays["depth_map_m"] = dm
    for k, v in rec.points.to_dict().items():
        arrays[f"points_{k}"] = v
    names = getattr(rec, "class_names", None) or ()
    arrays["class_names"] = np.asarray([str(c) for c in names], dtype=str)
    bw = getattr(rec, "bin_width_ps", None)
    arrays["bin_width_ps"] = np.float64(np.nan if bw is None else bw)
    det = getattr(rec, "detection", None)
    if det is not None:
        if getattr(det, "wavelengths_nm", None) is not None:
            arrays["wavelengths_nm"] = np.asarray(det.wavelengths_nm)
        if isinstance(det.mask, np.ndarray):
            arrays["detection_mask"] = np.asarray(det.mask, dtype=bool)
        else:  # written by detect(store=...): it stays there
            arrays["detection_store"] = np.asarray(str(det.options.get("store", "")))
        thr = sample_rows(det.threshold).astype(np.float64)
        if isinstance(det.threshold, np.ndarray | float) and thr.size <= _MAX_THRESHOLD_VALUES:
            arrays["detection_threshold"] = thr
        else:  # a per-voxel threshold would dwarf the rest of the file
            arrays["detection_threshold_median"] = np.float64(np.median(thr))
        arrays["null_shape"] = np.float64(det.null.shape)
        arrays["null_scale"] = np.float64(det.null.scale)
        arrays["background_spatial"] = np.asarray(det.background.spatial)
        arrays["background_temporal"] = np.asarray(det.background.temporal)
    path = Path(path)
    savez(path, arrays)  # fixed timestamps: the same result gives the same bytes
    return path


def _jsonable(x: Any) -> Any:
    """Convert numpy scalars/arrays, paths, tuples and dataclasses to JSON types."""
    from dataclasses import asdict, is_dataclass

    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if is_dataclass(x) and not isinstance(x, type):
        return _jsonable(asdict(x))
    if isinstance(x, (list, tuple, set)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        if x.size > 64:
            return f"<array shape={list(x.shape)} dtype={x.dtype}>"
        return _jsonable(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        f = float(x)
        return f if math.isfinite(f) else None
    if isinstance(x, (str, int)) or x is None:
        return x
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    return repr(x)


def _versions() -> dict[str, str]:
    from . import __version__

    out = {"splidar": __version__, "python": platform.python_version()}
    for mod in ("numpy", "scipy", "numba", "matplotlib"):
        m = sys.modules.get(mod)
        if m is None:
            try:
                m = __import__(mod)
            except ImportError:  # pragma: no cover - optional
                continue
        out[mod] = getattr(m, "__version__", "?")
    return out


def summarize(reconstruction, *, metrics: Any = None, extra: Mapping[str, Any] | None = None):
    """The content of ``summary.json`` as a JSON-ready dict (see :func:`write_summary`)."""
    rec = reconstruction
    p = rec.points
    det = getattr(rec, "detection", None)
    counts: dict[str, Any] = {"points": len(p)}
    if p.layer is not None:
        layers, n = np.unique(p.layer, return_counts=True)
        counts["points_per_layer"] = {int(k): int(c) for k, c in zip(layers, n, strict=True)}
    names = tuple(getattr(rec, "class_names", ()) or ())
    labels = _labels(p)
    if labels.size:
        lab, n = np.unique(labels, return_counts=True)
        counts["points_per_class"] = {
            (names[k] if 0 <= k < len(names) else str(k)): int(c)
            for k, c in zip(lab, n, strict=True)
        }
    rows, cols = p.image_shape
    counts["pixels"] = int(rows * cols)
    counts["pixels_with_surface"] = int(np.unique(p.row * cols + p.col).size) if len(p) else 0
    out: dict[str, Any] = {
        "splidar_summary": 1,
        "versions": _versions(),
        "image_shape": [int(rows), int(cols)],
        "n_wavelengths": int(getattr(rec, "n_wavelengths", p.n_wavelengths)),
        "n_layers": int(getattr(rec, "n_layers", 0)),
        "bin_width_ps": getattr(rec, "bin_width_ps", None),
        "class_names": list(names),
        "counts": counts,
        "parameters": {"reconstruction": getattr(rec, "hyperparameters", {})},
        "timings_s": {"reconstruction": dict(getattr(rec, "timings", {}) or {})},
    }
    hist = getattr(rec, "history", None)
    if hist is not None:
        out["convergence"] = {
            "n_iter": getattr(hist, "n_iter", None),
            "converged": getattr(hist, "converged", None),
            "reason": getattr(hist, "reason", None),
        }
    if det is not None:
        out["cube_shape"] = list(det.cube_shape)
        out["parameters"]["detection"] = {
            "scales": det.scales,
            "weights": det.weights,
            "pfa": det.pfa,
            **dict(det.options or {}),
        }
        out["timings_s"]["detection"] = dict(det.timings or {})
        out["data_reduction"] = det.reduction
        out["null_model"] = {
            "shape": det.null.shape,
            "scale": det.null.scale,
            "method": det.null.method,
            "pfa": det.null.pfa,
            "calibration": det.null.calibration,
        }
        thr = sample_rows(det.threshold).astype(np.float64)
        out["threshold"] = (
            float(thr)
            if thr.ndim == 0
            else {
                "min": float(thr.min()),
                "median": float(np.median(thr)),
                "max": float(thr.max()),
            }
        )
        out["counts"]["detected_surfaces"] = len(det.surfaces)
    if metrics is not None:
        out["metrics"] = metrics
    if extra:
        out.update(extra)
    return _jsonable(out)


def write_summary(
    reconstruction,
    path: str | os.PathLike,
    *,
    metrics: Any = None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``summary.json``: parameters, versions, timings, counts and data reduction.

    Parameters
    ----------
    reconstruction : Reconstruction
        The result to summarise (its ``detection`` adds detection parameters, timings,
        the null model and the data reduction).
    path : str or path-like
        Destination JSON file (overwritten).
    metrics : Metrics or mapping, optional
        Metrics against a ground truth, stored under ``"metrics"``.
    extra : mapping, optional
        Further top-level entries (e.g. ``{"input": ..., "command": ...}``).

    Returns
    -------
    pathlib.Path
        ``path``.

    Notes
    -----
    Numpy values become JSON numbers, non-finite floats ``null``, dataclasses objects and
    arrays larger than 64 values a short description. Keys: ``versions``,
    ``image_shape``, ``n_wavelengths``, ``n_layers``, ``bin_width_ps``, ``class_names``,
    ``counts``, ``parameters``, ``timings_s``, ``convergence`` and, with a detection,
    ``cube_shape``, ``data_reduction``, ``null_model``, ``threshold``.

    Raises
    ------
    OSError
        The file cannot be written.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> f = write_summary(rec, "summary.json", extra={"input": "scan.mat"})
    >>> import json
    >>> json.loads(f.read_text())["input"]
    'scan.mat'
    """
    data = summarize(reconstruction, metrics=metrics, extra=extra)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path
