"""Figures of detections and reconstructions (the only module that imports matplotlib).

Each ``plot_*`` function draws one picture on ``ax`` (or a new figure when ``ax`` is
None) and returns the axes, or, for multi-panel pictures, takes ``fig=`` and returns the
figure. :func:`save_figures` writes the set of PNGs that ``splidar run`` puts in
``figures/``.

Conventions: images are shown upright (row 0 at the top), depths in metres when the bin
width is known and in time bins otherwise, pixels without a surface in light grey, and
every colour scale has a labelled colour bar.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ._arrays import sample_rows, sum_over_rows
from ._validation import SplidarError, check_int
from .cube import SPEED_OF_LIGHT
from .points import PointSet

__all__ = [
    "plot_depth",
    "plot_detection_slice",
    "plot_intensity",
    "plot_labels",
    "plot_point_cloud",
    "plot_saliency_histogram",
    "save_figures",
]

logger = logging.getLogger(__name__)

_MISSING = "#d9d9d9"  # pixels with no surface
_UNKNOWN = (
    "#404040"  # surfaces no signature explains (label -1, splidar.reconstruction.flag_unknown)
)
_MAX_INTENSITY_PANELS = 6  # beyond this many wavelengths, show the total only


# ----------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------
def _plt():
    import matplotlib.pyplot as plt

    return plt


class _Maps:
    """Per-layer maps of a Reconstruction or PointSet, in display units."""

    def __init__(self, result, bin_width_ps: float | None = None):
        if isinstance(result, PointSet):
            m = result.maps()
            self.depth = m["depth_bin"]
            self.intensity = m.get("intensity")
            self.label = m.get("label")
            self.class_names = None
            self.points = result
            self.wavelengths_nm = None
            bw = bin_width_ps
            if bw is None and result.depth_m is not None and len(result):
                ok = result.depth_bin != 0
                if np.any(ok):
                    bw = float(
                        np.median(result.depth_m[ok] / result.depth_bin[ok])
                        / (1e-12 * SPEED_OF_LIGHT / 2)
                    )
        elif hasattr(result, "depth_map"):
            self.depth = np.asarray(result.depth_map, dtype=np.float64)
            self.intensity = np.asarray(result.intensity_map, dtype=np.float64)
            self.label = np.asarray(result.label_map)
            self.class_names = tuple(result.class_names)
            if getattr(result, "library", None) is None and len(self.class_names) == 1:
                self.class_names = ("one class (no spectral library)",)
            self.points = result.points
            det = getattr(result, "detection", None)
            self.wavelengths_nm = None if det is None else det.wavelengths_nm
            bw = bin_width_ps if bin_width_ps is not None else result.bin_width_ps
        else:
            raise SplidarError(
                f"expected a Reconstruction or a PointSet; got {type(result).__name__}."
            )
        self.bin_width_ps = bw
        self.scale = 1.0 if bw is None else bw * 1e-12 * SPEED_OF_LIGHT / 2.0
        self.unit = "time bins" if bw is None else "m"
        self.n_layers = int(self.depth.shape[2])

    def layer(self, layer: int) -> int:
        layer = check_int(layer, "layer", minimum=0)
        if layer >= self.n_layers:
            raise SplidarError(
                f"`layer` must be below the number of surface layers ({self.n_layers}); "
                f"got {layer}."
            )
        return layer

    def wavelength_name(self, l: int) -> str:
        if self.wavelengths_nm is not None:
            return f"{self.wavelengths_nm[l]:g} nm"
        return f"wavelength {l}"


def _layer_name(layer: int, n_layers: int) -> str:
    if n_layers == 1:
        return "surface"
    order = {0: "1st", 1: "2nd", 2: "3rd"}.get(layer, f"{layer + 1}th")
    near = " (nearest)" if layer == 0 else ""
    return f"{order} surface per pixel{near}"


def _cmap(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=_MISSING)


def _image(ax, img, *, cmap, vmin=None, vmax=None, label: str, title: str):
    plt = _plt()
    im = ax.imshow(
        np.ma.masked_invalid(img), cmap=_cmap(cmap), vmin=vmin, vmax=vmax, interpolation="nearest"
    )
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("column (pixel)")
    ax.set_ylabel("row (pixel)")
    cb = plt.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    cb.set_label(label)
    return im


def _robust_limits(values: np.ndarray, lo: float = 1.0, hi: float = 99.0):
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0.0, 1.0
    a, b = np.percentile(v, [lo, hi])
    if not b > a:
        a, b = float(v.min()), float(v.max())
        if not b > a:
            b = a + 1.0
    return float(a), float(b)


def _depth_limits(values: np.ndarray):
    """Depth colour limits: median +- 5 robust standard deviations (1.4826 MAD), within
    the 1st-99th percentiles. The percentiles alone span a nearby object and the wall
    behind it and flatten the object's relief into one colour."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0.0, 1.0
    p1, med, p99 = np.percentile(v, [1, 50, 99])
    sd = 1.4826 * float(np.median(np.abs(v - med)))
    lo, hi = max(p1, med - 5 * sd), min(p99, med + 5 * sd)
    if not hi > lo:
        return _robust_limits(values)
    return float(lo), float(hi)


def _new_ax(ax, **kw):
    if ax is not None:
        return ax
    fig, ax = _plt().subplots(figsize=kw.pop("figsize", (5.5, 4.5)), **kw)
    return ax


# ----------------------------------------------------------------------------------------
# maps
# ----------------------------------------------------------------------------------------
def plot_depth(
    result,
    *,
    layer: int = 0,
    ax=None,
    vmin: float | None = None,
    vmax: float | None = None,
    bin_width_ps: float | None = None,
):
    """Depth map of one surface layer.

    Parameters
    ----------
    result : Reconstruction or PointSet
    layer : int, default 0
        Surface slot within the pixel (0 = nearest detected surface of each pixel).
    ax : matplotlib Axes, optional
        Where to draw; a new figure when None.
    vmin, vmax : float, optional
        Colour limits in the displayed unit (default: the median +- 5 robust standard
        deviations of the layer's depths, within their 1st and 99th percentiles, so that
        an object's relief shows in front of a distant wall).
    bin_width_ps : float, optional
        Overrides the result's bin width (depths in metres when known, else bins).

    Returns
    -------
    matplotlib Axes

    Raises
    ------
    SplidarError
        ``layer`` out of range or ``result`` of the wrong type.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> ax = plot_depth(rec, layer=0)
    >>> ax.get_title() != ''
    True
    """
    m = _Maps(result, bin_width_ps)
    k = m.layer(layer)
    img = m.depth[:, :, k] * m.scale
    lo, hi = _depth_limits(img)
    ax = _new_ax(ax)
    _image(
        ax,
        img,
        cmap="viridis_r",
        vmin=lo if vmin is None else vmin,
        vmax=hi if vmax is None else vmax,
        label=f"depth ({m.unit})",
        title=f"Depth, {_layer_name(k, m.n_layers)}",
    )
    return ax


def plot_intensity(
    result,
    *,
    layer: int = 0,
    wavelength: int | None = None,
    ax=None,
    vmax: float | None = None,
):
    """Intensity map of one surface layer (one wavelength, or the sum over wavelengths).

    Parameters
    ----------
    result : Reconstruction or PointSet
    layer : int, default 0
        Surface slot within the pixel (0 = nearest).
    wavelength : int, optional
        Index of the wavelength; None shows the total over all wavelengths.
    ax : matplotlib Axes, optional
    vmax : float, optional
        Upper colour limit in photons (default: 99th percentile).

    Returns
    -------
    matplotlib Axes

    Raises
    ------
    SplidarError
        No intensity in ``result``, ``layer`` or ``wavelength`` out of range.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> ax = plot_intensity(rec, layer=0, wavelength=2)
    """
    m = _Maps(result)
    k = m.layer(layer)
    if m.intensity is None:
        raise SplidarError("these points carry no intensity to plot.")
    L = m.intensity.shape[3]
    if wavelength is None:
        img = m.intensity[:, :, k, :].sum(axis=-1)
        what = "total over wavelengths" if L > 1 else ""
    else:
        wavelength = check_int(wavelength, "wavelength", minimum=0)
        if wavelength >= L:
            raise SplidarError(f"`wavelength` must be below L = {L}; got {wavelength}.")
        img = m.intensity[:, :, k, wavelength]
        what = m.wavelength_name(wavelength)
    _, hi = _robust_limits(img, 0, 99)
    ax = _new_ax(ax)
    title = f"Intensity, {_layer_name(k, m.n_layers)}"
    if what:
        title += f"\n{what}"
    _image(
        ax,
        img,
        cmap="magma",
        vmin=0,
        vmax=hi if vmax is None else vmax,
        label="signal photons",
        title=title,
    )
    return ax


_NAMED_COLORS = {
    "red": "#d62728",
    "green": "#2ca02c",
    "blue": "#1f77b4",
    "grey": "#7f7f7f",
    "gray": "#7f7f7f",
    "orange": "#ff7f0e",
    "purple": "#9467bd",
    "brown": "#8c564b",
    "pink": "#e377c2",
    "yellow": "#bcbd22",
    "cyan": "#17becf",
    "black": "#000000",
    "white": "#f0f0f0",
}


def _class_colors(n: int, names=()) -> list:
    """One colour per class; a colour word in a class name ("red paint") gives that colour."""
    import matplotlib
    from matplotlib.colors import to_rgba

    base = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    chosen: list = [None] * n
    for i, name in enumerate(list(names)[:n]):
        for word in str(name).lower().replace("-", " ").split():
            c = _NAMED_COLORS.get(word)
            if c is not None and to_rgba(c) not in chosen:
                chosen[i] = to_rgba(c)
                break
    pool = [base(j % base.N) for j in range(base.N)]
    for i in range(n):
        if chosen[i] is None:
            free = [c for c in pool if c not in chosen] or pool
            chosen[i] = free[0]
    return chosen


def plot_labels(result, *, layer: int = 0, ax=None, class_names=None):
    """Class map of one surface layer, with a legend of class names.

    Parameters
    ----------
    result : Reconstruction or PointSet
    layer : int, default 0
    ax : matplotlib Axes, optional
    class_names : sequence of str, optional
        Overrides the result's class names.

    Returns
    -------
    matplotlib Axes

    Raises
    ------
    SplidarError
        No labels in ``result`` or ``layer`` out of range.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> ax = plot_labels(rec)
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    m = _Maps(result)
    k = m.layer(layer)
    if m.label is None:
        raise SplidarError("these points carry no class labels to plot.")
    lab = m.label[:, :, k]
    n = max(int(m.label.max()) + 1, 1)
    names = list(class_names or m.class_names or ())
    names += [f"class {i}" for i in range(len(names), n)]
    n = max(n, len(names))
    colors = _class_colors(n, names)
    ax = _new_ax(ax)
    # label -1 at a pixel holding a surface: "unknown material" (flag_unknown), drawn as
    # its own colour after the n classes; no surface stays masked
    unknown = (lab < 0) & np.isfinite(m.depth[:, :, k])
    cmap = ListedColormap([*colors, _UNKNOWN]).with_extremes(bad=_MISSING)
    img = np.ma.masked_array(np.where(unknown, n, lab), mask=(lab < 0) & ~unknown)
    ax.imshow(img, cmap=cmap, vmin=-0.5, vmax=n + 0.5, interpolation="nearest")
    ax.set_title(f"Class, {_layer_name(k, m.n_layers)}", fontsize=10)
    ax.set_xlabel("column (pixel)")
    ax.set_ylabel("row (pixel)")
    present = set(np.unique(lab[lab >= 0]).tolist())
    handles = [
        Patch(color=colors[i], label=f"{names[i]}" + ("" if i in present else " (absent)"))
        for i in range(n)
    ]
    if np.any(unknown):
        handles.append(Patch(color=_UNKNOWN, label="unknown material"))
    if np.any((lab < 0) & ~unknown):
        handles.append(Patch(color=_MISSING, label="no surface"))
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False
    )
    return ax


# ----------------------------------------------------------------------------------------
# point cloud
# ----------------------------------------------------------------------------------------
def plot_point_cloud(
    result,
    *,
    ax=None,
    color_by: str = "label",
    max_points: int = 20_000,
    rng=None,
    marker_size: float = 1.5,
):
    """3D scatter of the points: column, depth and row (image upright, depth into the page).

    Parameters
    ----------
    result : Reconstruction or PointSet
    ax : matplotlib 3D Axes, optional
        Created with ``projection="3d"`` when None.
    color_by : {"label", "depth", "intensity"}, default "label"
        Point colour: class (legend with class names), depth or total intensity.
        ``"label"`` falls back to ``"depth"`` when there are fewer than two classes.
    max_points : int, default 20000
        Points drawn at most; larger sets are subsampled uniformly at random. Points
        outside the 0.5-99.5 % depth range (stray detections) are left out of the view.
    rng : None, int or numpy Generator
        For the subsampling (``np.random.default_rng(rng)``).
    marker_size : float, default 1.5

    Returns
    -------
    matplotlib 3D Axes

    Raises
    ------
    SplidarError
        Unknown ``color_by`` or ``max_points < 1``.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> ax = plot_point_cloud(rec, color_by="depth")
    >>> ax.name
    '3d'
    """
    from ._validation import check_choice

    check_choice(color_by, "color_by", ("label", "depth", "intensity"))
    max_points = check_int(max_points, "max_points", minimum=1)
    m = _Maps(result)
    p = m.points
    n = len(p)
    depth_all = p.depth_bin * m.scale
    # depth axis from the 0.5-99.5 % range: a few stray detections must not flatten the view
    if n:
        d_lo, d_hi = np.percentile(depth_all, [0.5, 99.5])
        pad = 0.05 * (d_hi - d_lo) if d_hi > d_lo else 1.0
        d_lo, d_hi = d_lo - pad, d_hi + pad
        inside = np.flatnonzero((depth_all >= d_lo) & (depth_all <= d_hi))
    else:
        d_lo, d_hi, inside = 0.0, 1.0, np.arange(0)
    idx = inside
    if idx.size > max_points:
        idx = np.sort(np.random.default_rng(rng).choice(idx, max_points, replace=False))
    plt = _plt()
    if ax is None:
        fig = plt.figure(figsize=(6.5, 5.5))
        ax = fig.add_subplot(projection="3d")
    x = p.col[idx]
    z = p.row[idx]
    y = depth_all[idx]
    n_classes = max(int(p.label.max()) + 1, 1) if (p.label is not None and n) else 1
    if color_by == "label" and (p.label is None or n_classes < 2):
        color_by = "depth"  # one class: colour carries depth instead
    title = f"Point cloud ({n} points"
    title += f", {idx.size} shown)" if idx.size < n else ")"
    if color_by == "label":
        lab = p.label[idx]
        k = max(int(p.label.max()) + 1, 1) if n else 1
        names = list(m.class_names or ())
        names += [f"class {i}" for i in range(len(names), k)]
        colors = _class_colors(max(k, len(names)), names)
        for c in np.unique(lab):
            s = lab == c
            ax.scatter(x[s], y[s], z[s], s=marker_size, color=colors[c], label=names[c])
        if n:
            ax.legend(loc="upper left", fontsize=8, markerscale=4, frameon=False)
    else:
        if color_by == "depth":
            c, cl, cmap = y, f"depth ({m.unit})", "viridis_r"
        else:
            if p.intensity is None:
                raise SplidarError("these points carry no intensity to colour by.")
            c, cl, cmap = p.intensity[idx].sum(axis=1), "signal photons", "magma"
        sc = ax.scatter(x, y, z, s=marker_size, c=c, cmap=cmap)
        cb = plt.colorbar(sc, ax=ax, shrink=0.6, pad=0.1)
        cb.set_label(cl)
    rows, cols = p.image_shape
    ax.set_xlim(0, max(cols - 1, 1))  # a single column or row: a range of one pixel
    ax.set_ylim(d_lo, d_hi)
    ax.set_zlim(max(rows - 1, 1), 0)  # row 0 at the top: the image upright
    ax.set_xlabel("column (pixel)")
    ax.set_ylabel(f"depth ({m.unit})")
    ax.set_zlabel("row (pixel)")
    ax.view_init(elev=20, azim=-70)
    ax.set_title(title, fontsize=10)
    return ax


# ----------------------------------------------------------------------------------------
# detection
# ----------------------------------------------------------------------------------------
def _detection(result):
    det = getattr(result, "detection", None) if hasattr(result, "depth_map") else result
    if det is None or not hasattr(det, "saliency"):
        what = " without a detection" if hasattr(result, "depth_map") else ""
        raise SplidarError(
            f"expected a Detection or a Reconstruction that carries one; got "
            f"{type(result).__name__}{what}."
        )
    return det


def plot_saliency_histogram(
    detection, *, ax=None, bins: int = 200, max_samples: int = 2_000_000, rng=None
):
    """Histogram of the saliency with the fitted gamma null and the detection threshold.

    Parameters
    ----------
    detection : Detection or Reconstruction
        Uses ``saliency``, ``null`` (gamma shape and scale, ``eq:gamma_distrib``) and
        ``threshold``.
    ax : matplotlib Axes, optional
    bins : int, default 200
    max_samples : int, default 2,000,000
        Voxels used for the histogram at most (drawn uniformly at random, with
        replacement, beyond).
    rng : None, int or numpy Generator
        For the subsampling.

    Returns
    -------
    matplotlib Axes
        The main axes; an inset zooms on the background part around the threshold.

    Notes
    -----
    The y axis is logarithmic so that the tail, where signal voxels separate from the
    background, is visible. The null density is drawn scaled by the fraction of voxels
    at or below the threshold, the part of the histogram it models. A threshold that
    varies over voxels (a calibrated, background-dependent null) is drawn at its median
    with its range shaded.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> ax = plot_saliency_histogram(rec.detection)
    """
    from scipy import stats

    det = _detection(detection)
    bins = check_int(bins, "bins", minimum=2)
    max_samples = check_int(max_samples, "max_samples", minimum=1)
    s = sample_rows(det.saliency, max_values=max(max_samples, 1 << 22)).reshape(-1)
    if s.size > max_samples:
        s = s[np.random.default_rng(rng).integers(0, s.size, max_samples)]
    s = s[np.isfinite(s)].astype(np.float64)
    thr = sample_rows(det.threshold).astype(np.float64)
    t_med = float(np.median(thr))
    t_lo, t_hi = float(thr.min()), float(thr.max())
    null = det.null
    frac_bg = float(np.mean(s <= t_med)) if s.size else 1.0

    def draw(a, hi, n_bins, legend):
        edges = np.linspace(0.0, hi, n_bins + 1)
        dens, _, _ = a.hist(
            s, bins=edges, density=True, color="#9ecae1", edgecolor="none", label="all voxels"
        )
        x = np.linspace(hi / (20 * n_bins), hi, 400)
        pdf = stats.gamma.pdf(x, a=null.shape, scale=null.scale) * frac_bg
        a.plot(
            x,
            pdf,
            color="#d62728",
            lw=1.5,
            label=f"fitted gamma null (shape {null.shape:.3g}, scale {null.scale:.3g})",
        )
        a.axvline(
            t_med, color="k", ls="--", lw=1.2, label=f"threshold {t_med:.3g} (pfa {det.pfa:g})"
        )
        if t_hi > t_lo:
            a.axvspan(t_lo, t_hi, color="k", alpha=0.12, label="threshold range over voxels")
        pos = dens[dens > 0]
        a.set_yscale("log")
        if pos.size and np.isfinite(dens).all():
            a.set_ylim(float(pos.min()) / 3, float(dens.max()) * 3)
        a.set_xlim(0, hi)
        return dens

    ax = _new_ax(ax, figsize=(7, 4.8))
    hi = max(float(s.max()) if s.size else 1.0, t_hi * 1.1, 1e-12)
    draw(ax, hi, bins, True)
    ax.set_xlabel("saliency S (eq. 4.s1, filtered photon counts)")
    ax.set_ylabel("probability density")
    kept = float(det.reduction.voxel_fraction) * 100
    ax.set_title(
        f"Saliency of all voxels ({det.null.method} null); {kept:.3g} % of voxels detected",
        fontsize=10,
    )
    ax.legend(fontsize=8, loc="upper right")
    zoom = min(max(4.0 * t_hi, 3.0 * t_med), hi)
    if 0 < zoom < 0.5 * hi:  # no zoom on a degenerate (all-zero) saliency
        ins = ax.inset_axes([0.42, 0.22, 0.36, 0.36])
        draw(ins, zoom, 60, False)
        ins.set_title("zoom on the background part", fontsize=8)
        ins.tick_params(labelsize=7)
    return ax


def _slices(cube, det, lo: int, hi: int, row: int):
    """(time slice summed over [lo, hi) and L, (cols, T) slice at ``row``) without big copies."""
    R, C, T = det.mask.shape
    if cube is None:
        sal = det.saliency
        return (
            np.asarray(sal[:, :, lo:hi], dtype=np.float32).sum(axis=-1),
            np.asarray(sal[row], dtype=np.float32),
            "saliency S",
        )
    counts = getattr(cube, "counts", cube)
    shape = tuple(counts.shape)
    if len(shape) == 3:
        shape = (shape[0], shape[1], 1, shape[2])
    if (shape[0], shape[1], shape[3]) != (R, C, T):
        raise SplidarError(
            f"`cube` has shape {shape} but the detection map has {(R, C, T)} (rows, cols, T); "
            "pass the cube the detection was computed from."
        )
    c = counts if len(counts.shape) == 4 else counts[:, :, None, :]
    ts = np.asarray(c[:, :, :, lo:hi]).sum(axis=(2, 3), dtype=np.float32)
    xt = np.asarray(c[row]).sum(axis=1, dtype=np.float32)  # (cols, T)
    what = "photon counts" + (" (sum over wavelengths)" if shape[2] > 1 else "")
    return ts, xt, what


def plot_detection_slice(
    detection,
    cube=None,
    *,
    t: int | None = None,
    row: int | None = None,
    fig=None,
    half_window: int | None = None,
):
    """A time slice and a column-time slice of the data with the 3D detection map over it.

    Parameters
    ----------
    detection : Detection or Reconstruction
        Uses ``mask`` (rows, cols, T); ``saliency`` when there is no ``cube``.
    cube : Cube or array (rows, cols, L, T), optional
        The data; without it the saliency is shown instead of photon counts.
    t : int, optional
        Time bin of the time slice (default: the bin with most detected voxels).
    row : int, optional
        Image row of the column-time slice (default: the row with most detected voxels).
    fig : matplotlib Figure, optional
        Figure to draw on (two panels); a new one when None.
    half_window : int, optional
        The time slice sums the data over ``t +- half_window`` bins so that sparse photons
        show (default: half the IRF's full width at half maximum, at least 1 bin). The
        detected region drawn is the union over the same bins.

    Returns
    -------
    matplotlib Figure

    Raises
    ------
    SplidarError
        ``t`` or ``row`` out of range, or data of another shape than the detection.

    Notes
    -----
    Detected voxels are outlined in red over the grey-scale data so that the photons
    inside them stay visible. Only the two slices are read from the cube (no copy of it).

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> fig = plot_detection_slice(rec.detection, sim.cube)
    >>> len(fig.axes) >= 2
    True
    """
    det = _detection(detection)
    mask = det.mask
    R, C, T = mask.shape
    if t is None:
        per_t = sum_over_rows(mask, 2)
        t = int(np.argmax(per_t)) if per_t.any() else T // 2
    t = check_int(t, "t", minimum=0)
    if t >= T:
        raise SplidarError(f"`t` must be below T = {T}; got {t}.")
    if row is None:
        per_r = sum_over_rows(mask, 0)
        row = int(np.argmax(per_r)) if per_r.any() else R // 2
    row = check_int(row, "row", minimum=0)
    if row >= R:
        raise SplidarError(f"`row` must be below the number of rows ({R}); got {row}.")
    if half_window is None:
        irf = np.asarray(det.irf)
        width = np.count_nonzero(irf >= irf.max(axis=-1, keepdims=True) / 2, axis=-1).max()
        half_window = max(int(width) // 2, 1)
    half_window = check_int(half_window, "half_window", minimum=0)
    lo, hi = max(t - half_window, 0), min(t + half_window + 1, T)
    ts, xt, what = _slices(cube, det, lo, hi, row)

    plt = _plt()
    if fig is None:
        fig = plt.figure(figsize=(12, 4.8))
    ax1, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.5]})
    red = "#ff2a2a"

    _, vmax = _robust_limits(ts, 0, 99.5)
    im = ax1.imshow(ts, cmap="gray", vmin=0, vmax=vmax, interpolation="nearest")
    m1 = np.asarray(mask[:, :, lo:hi]).any(axis=-1)
    if m1.any() and not m1.all() and min(m1.shape) >= 2:  # contour needs 2 x 2 at least
        ax1.contour(m1.astype(np.float32), levels=[0.5], colors=red, linewidths=0.9)
    ax1.axhline(row, color="#4da6ff", lw=0.9, ls="--")
    span = f"bins {lo}-{hi - 1}" if hi - lo > 1 else f"bin {lo}"
    full = " (all detected)" if m1.all() else ""
    ax1.set_title(
        f"Time slice, {span}\nred outline: detected region{full}; blue: row {row}", fontsize=10
    )
    ax1.set_xlabel("column (pixel)")
    ax1.set_ylabel("row (pixel)")
    cb = fig.colorbar(im, ax=ax1, fraction=0.046, pad=0.04)
    cb.set_label(what)

    bw = det.bin_width_ps
    tt = np.arange(T, dtype=np.float64)
    ylabel = "time bin"
    if bw is not None:
        tt = tt * bw * 1e-3
        ylabel = "time (ns)"
    dt = tt[1] - tt[0] if T > 1 else 1.0
    extent = (-0.5, C - 0.5, tt[-1] + dt / 2, tt[0] - dt / 2)
    _, vmax = _robust_limits(xt, 0, 99.5)
    im2 = ax2.imshow(
        xt.T, cmap="gray", aspect="auto", interpolation="nearest", vmin=0, vmax=vmax, extent=extent
    )
    m2 = np.asarray(mask[row]).T  # (T, cols)
    if m2.any() and min(m2.shape) >= 2:
        ax2.contour(
            np.arange(C), tt, m2.astype(np.float32), levels=[0.5], colors=red, linewidths=0.9
        )
    ax2.axhline(tt[t], color="#4da6ff", lw=0.9, ls="--")
    ax2.set_title(
        f"Column-time slice at row {row}\nred outline: detected voxels; blue: time slice",
        fontsize=10,
    )
    ax2.set_xlabel("column (pixel)")
    ax2.set_ylabel(ylabel)
    cb2 = fig.colorbar(im2, ax=ax2, fraction=0.046, pad=0.04)
    cb2.set_label(what)
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------------------
# the set of figures of a run
# ----------------------------------------------------------------------------------------
def _grid(n_rows: int, n_cols: int, w: float = 4.2, h: float = 3.6):
    plt = _plt()
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(w * n_cols, h * n_rows), squeeze=False)
    return fig, axes


def save_figures(
    reconstruction,
    folder: str | os.PathLike,
    *,
    cube=None,
    dpi: int = 110,
    rng=0,
) -> dict[str, Path]:
    """Write the standard figures of a reconstruction as PNGs into ``folder``.

    Parameters
    ----------
    reconstruction : Reconstruction
    folder : str or path-like
        Created if needed; existing files of the same names are overwritten.
    cube : Cube, optional
        The data, for the detection slice (the saliency is shown without it).
    dpi : int, default 110
    rng : None, int or numpy Generator, default 0
        For subsampling large point clouds and saliency arrays (fixed by default so that
        figures are reproducible).

    Returns
    -------
    dict of str to pathlib.Path
        ``depth``, ``intensity``, ``labels``, ``point_cloud``; ``label_confidence`` when
        the points carry a label confidence; and, when the reconstruction carries its
        detection, ``saliency_histogram`` and ``detection_slice``.

    Notes
    -----
    ``depth.png`` has one panel per surface layer sharing one colour scale;
    ``intensity.png`` one row per layer and one column per wavelength (the total only
    when L > 6); ``labels.png`` and ``label_confidence.png`` one panel per layer (an
    unknown material, label -1 from :func:`splidar.reconstruction.flag_unknown`, has its
    own colour in ``labels.png``).

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> paths = save_figures(rec, "figures", cube=sim.cube)
    >>> sorted(paths)[:3]
    ['depth', 'detection_slice', 'intensity']
    """
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "ps", "cairo"):
        # figures go to files only; never open windows
        _plt().switch_backend("Agg")
    plt = _plt()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    m = _Maps(reconstruction)
    K = m.n_layers
    out: dict[str, Path] = {}

    def save(fig, name):
        path = folder / f"{name}.png"
        fig.savefig(path, dpi=dpi, bbox_inches="tight")
        plt.close(fig)
        out[name] = path

    # depth: one shared colour scale across layers so that layers compare (robust: the
    # relief of a near object shows in front of a far wall)
    fig, axes = _grid(1, K)
    lo, hi = _depth_limits(m.depth * m.scale)
    for k in range(K):
        plot_depth(reconstruction, layer=k, ax=axes[0, k], vmin=lo, vmax=hi)
    fig.tight_layout()
    save(fig, "depth")

    if m.intensity is not None:
        L = m.intensity.shape[3]
        wl = list(range(L)) if 1 < L <= _MAX_INTENSITY_PANELS else [None]
        fig, axes = _grid(K, len(wl), w=3.8, h=3.4)
        for k in range(K):
            for j, w in enumerate(wl):
                img = m.intensity[..., w] if w is not None else m.intensity.sum(axis=-1)
                _, vmax = _robust_limits(img, 0, 99)
                plot_intensity(reconstruction, layer=k, wavelength=w, ax=axes[k, j], vmax=vmax)
        fig.tight_layout()
        save(fig, "intensity")

    if m.label is not None:
        fig, axes = _grid(1, K, w=5.2)
        for k in range(K):
            plot_labels(reconstruction, layer=k, ax=axes[0, k])
        fig.tight_layout()
        save(fig, "labels")

    if getattr(m.points, "label_confidence", None) is not None and len(m.points):
        fig, axes = _grid(1, K)
        for k in range(K):
            plot_label_confidence(reconstruction, layer=k, ax=axes[0, k])
        fig.tight_layout()
        save(fig, "label_confidence")

    ax = plot_point_cloud(reconstruction, rng=rng)
    save(ax.figure, "point_cloud")

    det = getattr(reconstruction, "detection", None)
    if det is not None:
        ax = plot_saliency_histogram(det, rng=rng)
        ax.figure.tight_layout()
        save(ax.figure, "saliency_histogram")
        save(plot_detection_slice(det, cube), "detection_slice")
    return out


# ----------------------------------------------------------------------------------------
# label confidence (issue 14)
# ----------------------------------------------------------------------------------------
def _calibration_bins(confidence, correct, n_bins: int):
    conf = np.asarray(confidence, dtype=np.float64).ravel()
    ok = np.asarray(correct, dtype=np.float64).ravel()
    if conf.shape != ok.shape or conf.size == 0:
        raise SplidarError(
            f"`confidence` and `correct` must be non-empty and of one length; got "
            f"{conf.size} and {ok.size}."
        )
    n_bins = check_int(n_bins, "n_bins", minimum=1)
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    idx = np.clip(np.digitize(conf, edges) - 1, 0, n_bins - 1)
    n = np.bincount(idx, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        acc = np.bincount(idx, ok, minlength=n_bins) / n
        mean_conf = np.bincount(idx, conf, minlength=n_bins) / n
    ece = float(np.nansum(n / conf.size * np.abs(acc - mean_conf)))
    return edges, n, acc, mean_conf, ece


def reliability_diagram(confidence, correct, *, n_bins: int = 10, ax=None, title=None):
    """Reliability diagram of label confidences: accuracy against confidence, per bin.

    A calibrated confidence lies on the diagonal: among points given confidence p, a
    fraction p is right. The expected calibration error (ECE, the share-weighted mean
    of ``|accuracy - mean confidence|`` over ``n_bins`` equal-width bins) is in the
    title; a histogram of the confidences is drawn beneath the curve.

    Parameters
    ----------
    confidence : array (n,)
        Per-point confidence in [0, 1] (``points.label_confidence``).
    correct : array (n,) of bool
        Whether each point's label is right (e.g. over matched points).
    n_bins : int
    ax : matplotlib Axes, optional
    title : str, optional

    Returns
    -------
    matplotlib Figure

    Raises
    ------
    SplidarError
        Empty or unequal inputs, ``n_bins`` < 1.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> from splidar.metrics import match_points
    >>> m = match_points(rec.points, sim.truth, tau=2.0)
    >>> ok = rec.points.label[m.est_index] == sim.truth.label[m.true_index]
    >>> fig = reliability_diagram(rec.points.label_confidence[m.est_index], ok)
    """
    edges, n, acc, mean_conf, ece = _calibration_bins(confidence, correct, n_bins)
    ax = _new_ax(ax, figsize=(4.8, 4.4))
    centres = 0.5 * (edges[1:] + edges[:-1])
    width = edges[1] - edges[0]
    share = n / max(n.sum(), 1)
    ax.bar(centres, share, width=0.9 * width, color="#c6dbef", label="share of points")
    ax.plot([0, 1], [0, 1], color="0.5", lw=1, ls="--", label="calibrated")
    ok = n > 0
    ax.plot(mean_conf[ok], acc[ok], "o-", color="#08519c", label="accuracy")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("label confidence")
    ax.set_ylabel("fraction right / share of points")
    ax.set_title(title or f"Reliability (ECE {ece:.3f}, {int(n.sum())} points)", fontsize=10)
    ax.legend(loc="upper left", fontsize=8, frameon=False)
    return ax.figure


def plot_label_confidence(result, *, layer: int = 0, ax=None):
    """Map of the label confidence (marginal probability of the label) of one layer.

    Parameters
    ----------
    result : Reconstruction
    layer : int, default 0
    ax : matplotlib Axes, optional

    Returns
    -------
    matplotlib Axes

    Raises
    ------
    SplidarError
        No label confidence in ``result`` or ``layer`` out of range.

    Examples
    --------
    >>> import splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)
    >>> ax = plot_label_confidence(rec)
    """
    p = getattr(result, "points", result)
    if getattr(p, "label_confidence", None) is None:
        raise SplidarError("these points carry no label confidence to plot.")
    m = _Maps(result)
    k = m.layer(layer)
    rows, cols = p.image_shape
    img = np.full((rows, cols), np.nan)
    layer_of = p.layer if p.layer is not None else np.zeros(len(p), np.int64)
    sel = layer_of == k
    img[p.row[sel], p.col[sel]] = p.label_confidence[sel]
    ax = _new_ax(ax)
    _image(
        ax, img, cmap="viridis", vmin=0.0, vmax=1.0, label="label confidence",
        title=f"Label confidence, {_layer_name(k, m.n_layers)}",
    )  # fmt: skip
    return ax


__all__ += ["plot_label_confidence", "reliability_diagram"]
