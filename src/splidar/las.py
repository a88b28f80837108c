"""LAS / LAZ point clouds (ASPRS LAS 1.4) for CloudCompare, PDAL, QGIS and other GIS tools.

Written with `laspy <https://pypi.org/project/laspy/>`_; LAZ (compressed) through its
``lazrs`` backend. Both come with ``pip install 'splidar[las]'``.

``splidar run`` and ``splidar demo`` write ``points.las`` beside ``points.csv`` and
``points.ply`` when laspy is installed (without it they log a one-line note and go on).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import SplidarError, check_positive
from .points import PointSet

__all__ = ["las_available", "write_las"]

log = logging.getLogger(__name__)

#: LAS ``user_id`` of the VLR holding splidar's units, scales and class names (JSON).
VLR_USER_ID = "splidar"


def las_available() -> bool:
    """True when laspy (the ``splidar[las]`` extra) is installed.

    Examples
    --------
    >>> las_available() in (True, False)
    True
    """
    try:
        import laspy  # noqa: F401
    except ImportError:
        return False
    return True


def _laspy():
    try:
        import laspy
    except ImportError:
        raise SplidarError(
            "writing LAS/LAZ needs the optional package laspy: pip install 'splidar[las]'."
        ) from None
    return laspy


def _points_of(result) -> tuple[PointSet, Any]:
    if isinstance(result, PointSet):
        return result, None
    pts = getattr(result, "points", None)
    if isinstance(pts, PointSet):
        return pts, result
    raise SplidarError(
        f"`points` must be a PointSet, Reconstruction or Detection; got {type(result).__name__}."
    )


def _decade(step: float) -> float:
    """``step`` rounded down to a power of ten (LAS scales read best as 0.001, 1e-5...)."""
    return float(10.0 ** np.floor(np.log10(step)))


def _depth(p: PointSet, bin_width_ps: float | None) -> tuple[np.ndarray, str, float]:
    """z = -depth (float64), its unit ("m" or "bin") and its LAS scale.

    The scale is a thousandth of a bin rounded down to a power of ten (int32 coordinates
    then span 2e6 bins); 10 um when only ``depth_m`` is known.
    """
    from .cube import SPEED_OF_LIGHT

    bin_m = None if bin_width_ps is None else bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0
    if p.depth_m is not None and np.all(np.isfinite(p.depth_m)):
        return -p.depth_m, "m", 1e-5 if bin_m is None else _decade(bin_m * 1e-3)
    if bin_m is not None:
        return -p.depth_bin * bin_m, "m", _decade(bin_m * 1e-3)
    return -p.depth_bin, "bin", 1e-3


def _extra_dims(p: PointSet) -> list[tuple[str, np.ndarray]]:
    """The LAS extra dimensions: name and values (their dtype is the stored type)."""
    n = len(p)
    out = [
        ("row", p.row.astype(np.uint32)),
        ("col", p.col.astype(np.uint32)),
        ("depth_bin", p.depth_bin.astype(np.float64)),
    ]
    if p.depth_m is not None:
        out.append(("depth_m", p.depth_m.astype(np.float64)))
    out.append(("layer", (p.layer if p.layer is not None else np.full(n, -1)).astype(np.int16)))
    for i in range(p.n_wavelengths):
        out.append((f"intensity_{i}", p.intensity[:, i].astype(np.float32)))
    if p.intensity_std is not None:
        for i in range(p.intensity_std.shape[1]):
            out.append((f"intensity_std_{i}", p.intensity_std[:, i].astype(np.float32)))
    if p.label_confidence is not None:
        out.append(("label_confidence", p.label_confidence.astype(np.float32)))
    return out


def _returns(p: PointSet) -> tuple[np.ndarray, np.ndarray]:
    """Return number (1 = nearest surface of the pixel) and surfaces in the pixel, 1..15."""
    n = len(p)
    cols = p.image_shape[1]
    pix = p.row * cols + p.col
    order = np.lexsort((p.depth_bin, pix))
    first = np.r_[True, pix[order][1:] != pix[order][:-1]] if n else np.zeros(0, bool)
    start = np.maximum.accumulate(np.where(first, np.arange(n), 0)) if n else first
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n) - start
    per_pixel = np.bincount(pix, minlength=1)[pix] if n else np.zeros(0, np.int64)
    return np.minimum(rank + 1, 15), np.minimum(per_pixel, 15)


def write_las(
    points,
    path: str | os.PathLike,
    *,
    bin_width_ps: float | None = None,
    pixel_size: float | None = None,
    class_names=None,
) -> Path:
    """Write points as a LAS 1.4 (or, for a ``.laz`` path, LAZ) point cloud.

    Parameters
    ----------
    points : PointSet, Reconstruction or Detection
        n points with L intensities.
    path : str or path-like
        Destination ending in ``.las`` or ``.laz`` (overwritten).
    bin_width_ps : float, optional
        Bin width in picoseconds for depths in metres when the points carry no
        ``depth_m`` (a Reconstruction passes its own).
    pixel_size : float, optional
        Pixel footprint at the target, metres. Default: x and y in pixel units.
    class_names : sequence of str, optional
        Names of the labels (default: a Reconstruction's ``class_names``).

    Returns
    -------
    pathlib.Path
        ``path``.

    Notes
    -----
    Coordinates (as in ``points.ply``): ``x = col * pixel_size``,
    ``y = (rows - 1 - row) * pixel_size`` (the image upright), ``z = -depth`` (the
    sensor looks down -z; the nearest surface is highest). Depth is in metres when the
    bin width is known (``depth_m``, or ``depth_bin`` times ``c * bin_width / 2``),
    else in time bins; x and y are in metres only when ``pixel_size`` is given, else
    in pixels. The file holds no coordinate reference system; the units are recorded
    in a VLR (``user_id`` "splidar", record 1, JSON: ``xy_unit``, ``z_unit``,
    ``pixel_size``, ``bin_width_ps``, ``intensity_scale``, ``class_names``). Scales
    (coordinate steps): a thousandth of a pixel in x, y and of a time bin in z, each
    rounded down to a power of ten (10 um in z when only ``depth_m`` is known).

    Point format 7 (LAS 1.4) with, per point:

    * ``classification`` = ``label`` (0-based row of the spectral library; splidar's
      classes, not ASPRS codes: the names are in the VLR);
    * ``intensity`` = total intensity ``sum_l I_l`` scaled so that the largest is
      65535 (the factor is ``intensity_scale`` in the VLR);
    * ``return_number`` = rank of the surface in its pixel by depth (1 = nearest),
      ``number_of_returns`` = surfaces in the pixel (both at most 15);
    * ``red green blue`` = the colours of :func:`splidar.export.point_colors` (x 257);
    * extra dimensions: ``row``, ``col`` (uint32), ``depth_bin`` (float64),
      ``depth_m`` (float64, when known), ``layer`` (int16, -1 when unknown),
      ``intensity_0..intensity_{L-1}`` and ``intensity_std_0..`` (float32, expected
      photons and their posterior standard deviation), ``label_confidence``
      (float32), each present when the points carry it.

    Raises
    ------
    SplidarError
        laspy missing (names ``splidar[las]``), a ``.laz`` path with no LAZ backend
        installed, a suffix other than ``.las``/``.laz``, a label outside 0..255, or
        ``bin_width_ps``/``pixel_size`` not > 0.

    Examples
    --------
    >>> p = PointSet(row=[0, 1], col=[1, 1], depth_bin=[12.5, 20.0], image_shape=(2, 2),
    ...              intensity=[[3.0], [1.5]], label=[0, 1])
    >>> f = write_las(p, "points.las", bin_width_ps=250.0)  # doctest: +SKIP
    >>> import laspy; las = laspy.read(f)  # doctest: +SKIP
    >>> las.classification.tolist(), las.depth_bin.tolist()  # doctest: +SKIP
    ([0, 1], [12.5, 20.0])
    """
    laspy = _laspy()
    p, result = _points_of(points)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".las", ".laz"):
        raise SplidarError(f"`path` must end in .las or .laz; got '{path.name}'.")
    if suffix == ".laz" and not laspy.LazBackend.detect_available():
        raise SplidarError(
            "writing .laz needs a LAZ backend for laspy: pip install 'splidar[las]' (lazrs); "
            "or write .las."
        )
    if bin_width_ps is None and result is not None:
        bin_width_ps = getattr(result, "bin_width_ps", None)
    if bin_width_ps is not None:
        bin_width_ps = check_positive(bin_width_ps, "bin_width_ps")
    if pixel_size is not None:
        pixel_size = check_positive(pixel_size, "pixel_size")
    if class_names is None and result is not None:
        class_names = getattr(result, "class_names", None)
    n = len(p)
    label = p.label if p.label is not None else np.zeros(n, np.int64)
    if n and (label.min() < 0 or label.max() > 255):
        raise SplidarError(
            f"LAS classification holds 0..255; the labels range over [{label.min()}, "
            f"{label.max()}]."
        )
    z, z_unit, z_scale = _depth(p, bin_width_ps)
    xy = 1.0 if pixel_size is None else pixel_size
    x = p.col * xy
    y = (p.image_shape[0] - 1 - p.row) * xy
    extra = _extra_dims(p)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = [_decade(xy * 1e-3)] * 2 + [z_scale]
    header.offsets = [float(np.floor(v.min())) if n else 0.0 for v in (x, y, z)]
    header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=v.dtype) for k, v in extra])
    total = p.intensity.sum(axis=1) if p.intensity is not None else np.zeros(n)
    top = float(total.max()) if n else 0.0
    scale = 65535.0 / top if top > 0 else 0.0
    info = {
        "xy_unit": "m" if pixel_size else "pixel",
        "z_unit": z_unit,
        "pixel_size": pixel_size,
        "bin_width_ps": bin_width_ps,
        "intensity_scale": scale,
        "image_shape": list(p.image_shape),
        "class_names": None if class_names is None else [str(c) for c in class_names],
        "coordinates": "x = col * pixel_size, y = (rows - 1 - row) * pixel_size, z = -depth",
    }
    record = json.dumps(info).encode()
    header.vlrs.append(laspy.VLR(VLR_USER_ID, 1, "units and class names", record))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z
    las.classification = label.astype(np.uint8)
    las.intensity = np.round(total * scale).astype(np.uint16)
    ret, nret = _returns(p)
    las.return_number = ret.astype(np.uint8)
    las.number_of_returns = nret.astype(np.uint8)
    from .export import point_colors

    rgb = point_colors(p).astype(np.uint16) * 257
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    for name, values in extra:
        las[name] = values
    las.write(str(path))
    log.info("wrote %d points to %s (xy in %s, z in %s)", n, path, info["xy_unit"], z_unit)
    return path
