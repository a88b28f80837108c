"""Ready-made test scenes: ground-truth surfaces to simulate cubes from.

Each builder returns a frozen :class:`Scene` (truth :class:`~splidar.PointSet`, time
window, IRF, optional spectral library) whose :meth:`Scene.simulate` draws a cube with
:func:`splidar.simulation.simulate`. Synthetic scenes need no files and are deterministic
(no randomness in the truth); :func:`art_scene` reads the Middlebury "Art" files the
user points to (the paper's simulated scene).

Intensities in a scene's truth are expected signal photons per wavelength at the
scene's nominal brightness; :meth:`Scene.simulate` with ``ppp=`` rescales them.

Examples
--------
>>> from splidar.scenes import single_surface_scene
>>> scene = single_surface_scene((16, 16), n_bins=100)
>>> sim = scene.simulate(ppp=10, sbr=1, rng=0)
>>> sim.cube.shape, round(sim.ppp, 6)
((16, 16, 1, 100), 10.0)
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._validation import SplidarError, check_in_range, check_int, check_positive
from .irf import as_irf_models, sample_irf_models
from .library import SpectralLibrary
from .points import PointSet

__all__ = [
    "Scene",
    "art_scene",
    "multispectral_scene",
    "single_surface_scene",
    "two_layer_scene",
]

logger = logging.getLogger(__name__)

_DEFAULT_BIN_PS = 16.0  # bin width of the paper's 325 m head data; an assumption elsewhere


@dataclass(frozen=True)
class Scene:
    """A ground-truth scene ready to be simulated.

    Attributes
    ----------
    truth : PointSet
        Surfaces with ``depth_bin`` (fractional bins), ``intensity`` (n, L) (expected
        signal photons at nominal brightness), ``label`` (library row, 0 without a
        library) and ``layer`` (0 = nearest surface of the pixel).
    n_bins : int
        T, the time window length.
    irf : tuple of IRF models, length L
        See :mod:`splidar.irf` (``GaussianIRF``, ``ExpTailIRF``, ``SampledIRF``).
    library : SpectralLibrary or None
        The materials behind ``label``.
    wavelengths_nm : ndarray (L,) or None
    bin_width_ps : float or None
    name, description : str
    """

    truth: PointSet
    n_bins: int
    irf: tuple
    library: SpectralLibrary | None
    wavelengths_nm: np.ndarray | None
    bin_width_ps: float | None
    name: str
    description: str

    def __repr__(self) -> str:
        lib = "none" if self.library is None else f"{self.library.n_classes} classes"
        return (
            f"Scene({self.name!r}, shape={self.shape}, n_bins={self.n_bins}, "
            f"L={self.n_wavelengths}, surfaces={len(self.truth)}, library={lib})"
        )

    @property
    def shape(self) -> tuple[int, int]:
        """Image size ``(rows, cols)``."""
        return self.truth.image_shape

    @property
    def n_wavelengths(self) -> int:
        """L."""
        return self.truth.n_wavelengths

    @property
    def irf_array(self) -> np.ndarray:
        """The sampled IRF ``(L, n)`` that simulated cubes carry (argmax = depth reference)."""
        return sample_irf_models(self.irf)

    def surfaces_per_pixel(self) -> np.ndarray:
        """Number of surfaces in each pixel, ``(rows, cols)`` int."""
        out = np.zeros(self.shape, np.int64)
        np.add.at(out, (self.truth.row, self.truth.col), 1)
        return out

    def simulate(
        self,
        *,
        ppp: float | None = None,
        sbr: float | None = None,
        background=None,
        background_map=None,
        background_per_bin=None,
        rng=None,
    ):
        """Draw a cube of this scene; see :func:`splidar.simulation.simulate`.

        Returns
        -------
        Simulation
        """
        from .simulation import simulate

        return simulate(
            self.truth,
            n_bins=self.n_bins,
            irf=self.irf,
            ppp=ppp,
            sbr=sbr,
            background=background,
            background_map=background_map,
            background_per_bin=background_per_bin,
            bin_width_ps=self.bin_width_ps,
            wavelengths_nm=self.wavelengths_nm,
            library=self.library,
            rng=rng,
        )


# ----------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------


def _check_shape(shape, minimum: int = 8) -> tuple[int, int]:
    try:
        r, c = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise SplidarError(f"`shape` must be (rows, cols); got {shape!r}.") from None
    if r < minimum or c < minimum:
        raise SplidarError(f"`shape` must be at least ({minimum}, {minimum}); got {(r, c)}.")
    return r, c


def _margins(models) -> tuple[int, int]:
    """Bins to keep free before/after a depth so every return fits in the window."""
    left = max(m.support[0] for m in models)
    right = max(m.support[1] for m in models)
    return left + 1, right + 1


def _usable(models, n_bins: int, need: float) -> tuple[float, float]:
    """Depth interval ``[lo, hi]`` inside which returns fit; raise if shorter than ``need``."""
    ml, mr = _margins(models)
    lo, hi = float(ml), float(n_bins - 1 - mr)
    if hi - lo < need:
        raise SplidarError(
            f"`n_bins` = {n_bins} is too short for this scene with this IRF (support "
            f"{ml - 1} + {mr - 1} bins): it needs about {int(np.ceil(need + ml + mr + 1))} bins. "
            "Increase n_bins or use a narrower IRF."
        )
    return lo, hi


def _irf_width(models) -> float:
    """A width scale of the IRFs, bins: the largest sampled FWHM."""
    from .irf import irf_fwhm

    return max(float(irf_fwhm(m.sample())) for m in models)


def _single_geometry(r: int, c: int):
    """Unit depth map in [0, 1] (0 = near) and reflectivity in (0, 1] for one surface.

    A tilted back wall, two boxes (steps), a ramp (slope along rows), dark patches.
    """
    y, x = np.mgrid[0:r, 0:c].astype(np.float64)
    yn, xn = y / (r - 1), x / (c - 1)
    depth = 0.85 - 0.15 * xn  # tilted wall (fractional depths everywhere)
    box1 = (yn > 0.15) & (yn < 0.45) & (xn > 0.1) & (xn < 0.4)
    depth[box1] = 0.25
    box2 = (yn > 0.2) & (yn < 0.5) & (xn > 0.6) & (xn < 0.9)
    depth[box2] = 0.45
    ramp = (yn > 0.6) & (yn < 0.9) & (xn > 0.15) & (xn < 0.85)
    depth[ramp] = 0.1 + 0.5 * (yn[ramp] - 0.6) / 0.3
    refl = 0.6 + 0.4 * np.cos(2 * np.pi * (xn + 0.5 * yn)) ** 2  # smooth shading
    dark1 = (yn > 0.25) & (yn < 0.35) & (xn > 0.05) & (xn < 0.95)
    refl[dark1] *= 0.1  # a dark stripe across both boxes and the wall
    disc = (yn - 0.75) ** 2 + (xn - 0.7) ** 2 < 0.1**2
    refl[disc] *= 0.2  # a dark disc on the ramp
    return depth, refl


def _grid_points(depth_maps, intensity_maps, labels, layers, mask_maps, shape):
    rows, cols = [], []
    dd, ii, ll, yy = [], [], [], []
    for d, inten, lab, lay, m in zip(
        depth_maps, intensity_maps, labels, layers, mask_maps, strict=True
    ):
        rr, cc = np.nonzero(m)
        rows.append(rr)
        cols.append(cc)
        dd.append(d[rr, cc])
        ii.append(inten[rr, cc])
        ll.append(lab[rr, cc])
        yy.append(np.full(rr.size, lay))
    return PointSet(
        row=np.concatenate(rows),
        col=np.concatenate(cols),
        depth_bin=np.concatenate(dd),
        image_shape=shape,
        intensity=np.concatenate(ii),
        label=np.concatenate(ll),
        layer=np.concatenate(yy),
    )


def _net_mask(r: int, c: int, spacing: int) -> np.ndarray:
    """Strands 1 px wide every ``spacing`` rows and columns (covers 1 - (1-1/s)^2)."""
    y, x = np.mgrid[0:r, 0:c]
    off = spacing // 2
    return ((y - off) % spacing == 0) | ((x - off) % spacing == 0)


# ----------------------------------------------------------------------------------------
# scenes
# ----------------------------------------------------------------------------------------


def single_surface_scene(
    shape: tuple[int, int] = (48, 48),
    *,
    n_bins: int = 200,
    irf=("gaussian", 3.0),
    n_wavelengths: int = 1,
    photons: float = 10.0,
    bin_width_ps: float | None = _DEFAULT_BIN_PS,
) -> Scene:
    """One surface per pixel: a tilted wall, two boxes (steps), a ramp, dark patches.

    Depths are fractional everywhere (tilt and ramp) and use most of the window; the
    reflectivity has smooth shading, a dark stripe (x0.1) and a dark disc (x0.2).

    Parameters
    ----------
    shape : (rows, cols)
        Image size (>= 8 x 8).
    n_bins : int
        T. Depths span the window minus the IRF support at each end.
    irf : IRF specification
        See :func:`splidar.irf.as_irf_models` (one per wavelength or one for all).
    n_wavelengths : int
        L; the surface is grey (same intensity at every wavelength).
    photons : float
        Mean expected signal photons per pixel and wavelength at nominal brightness.
    bin_width_ps : float or None
        Bin width stored with the scene (default 16 ps, an assumption).

    Returns
    -------
    Scene
        ``label`` 0 everywhere, no library, ``layer`` 0.

    Raises
    ------
    SplidarError
        Too small a shape, too short a window for the IRF, bad numbers.

    Examples
    --------
    >>> s = single_surface_scene((20, 24), n_bins=120)
    >>> len(s.truth), int(s.surfaces_per_pixel().max())
    (480, 1)
    """
    r, c = _check_shape(shape)
    T = check_int(n_bins, "n_bins", minimum=8)
    L = check_int(n_wavelengths, "n_wavelengths", minimum=1)
    photons = check_positive(photons, "photons")
    models = as_irf_models(irf, n_wavelengths=L)
    lo, hi = _usable(models, T, need=10.0)
    unit, refl = _single_geometry(r, c)
    depth = lo + unit * (hi - lo)
    inten = np.repeat((refl * photons / refl.mean())[..., None], L, axis=-1)
    truth = _grid_points(
        [depth], [inten], [np.zeros((r, c), np.int64)], [0], [np.ones((r, c), bool)], (r, c)
    )
    return Scene(
        truth=truth,
        n_bins=T,
        irf=models,
        library=None,
        wavelengths_nm=None,
        bin_width_ps=bin_width_ps,
        name="single_surface",
        description="one surface per pixel: tilted wall, two boxes, a ramp, dark patches",
    )


def two_layer_scene(
    shape: tuple[int, int] = (48, 48),
    *,
    n_bins: int = 200,
    irf=("gaussian", 3.0),
    n_wavelengths: int = 1,
    net_spacing: int = 5,
    net_transmission: float = 0.6,
    photons: float = 10.0,
    bin_width_ps: float | None = _DEFAULT_BIN_PS,
) -> Scene:
    """A thin, partly transmissive net in front of objects and a back wall.

    Strands 1 pixel wide run every ``net_spacing`` rows and columns (covering
    ``1 - (1 - 1/net_spacing)^2`` of the pixels: 36 % for 5, 44 % for 4). Pixels on a
    strand have two surfaces: the net (layer 0, a fraction ``1 - net_transmission`` of
    the pixel's light) and the object behind (layer 1, the rest); other pixels have
    one. The net sags gently (fractional depths); behind it are a tilted wall, a box
    and a ramp. Net and objects are at least 4 IRF widths (largest FWHM) apart.

    Parameters
    ----------
    shape : (rows, cols)
    n_bins : int
        T.
    irf : IRF specification
    n_wavelengths : int
        L (grey surfaces).
    net_spacing : int
        Period of the strands, pixels (>= 2).
    net_transmission : float
        Fraction of a strand pixel's light that reaches the object behind, in (0, 1).
    photons : float
        Mean expected signal photons per pixel and wavelength of the *back* scene.
    bin_width_ps : float or None

    Returns
    -------
    Scene
        ``label`` 0, no library, ``layer`` 0 (nearest) / 1.

    Raises
    ------
    SplidarError
        Window too short to keep 4 IRF widths between the layers, bad parameters.

    Examples
    --------
    >>> s = two_layer_scene((20, 20), n_bins=150)
    >>> n = s.surfaces_per_pixel()
    >>> int(n.max()), round(float((n == 2).mean()), 2)
    (2, 0.36)
    """
    r, c = _check_shape(shape)
    T = check_int(n_bins, "n_bins", minimum=8)
    L = check_int(n_wavelengths, "n_wavelengths", minimum=1)
    s = check_int(net_spacing, "net_spacing", minimum=2)
    tr = check_in_range(net_transmission, "net_transmission", 0.0, 1.0, lo_open=True, hi_open=True)
    photons = check_positive(photons, "photons")
    models = as_irf_models(irf, n_wavelengths=L)
    w = _irf_width(models)
    gap = 4.0 * w
    lo, hi = _usable(models, T, need=gap + 12.0)
    y, x = np.mgrid[0:r, 0:c].astype(np.float64)
    yn, xn = y / (r - 1), x / (c - 1)
    # net occupies [lo, lo + net_span]; objects start gap after it
    net_span = 0.1 * (hi - lo - gap)
    net_depth = lo + net_span * (0.5 + 0.5 * np.sin(np.pi * xn) * np.sin(np.pi * yn))
    back_lo = lo + net_span + gap
    unit, refl = _single_geometry(r, c)
    # keep the back scene's own layout, squeezed into [back_lo, hi]
    back_depth = back_lo + (unit - unit.min()) / (unit.max() - unit.min()) * (hi - back_lo)
    net = _net_mask(r, c, s)
    back_int = refl * photons / refl.mean()
    back_int = np.where(net, tr * back_int, back_int)
    net_int = np.full((r, c), (1.0 - tr) * photons)
    zeros = np.zeros((r, c), np.int64)
    truth = _grid_points(
        [net_depth, back_depth],
        [np.repeat(net_int[..., None], L, -1), np.repeat(back_int[..., None], L, -1)],
        [zeros, zeros],
        [0, 1],
        [net, np.ones((r, c), bool)],
        (r, c),
    )
    # single-surface pixels hold their only surface in layer 0
    layer = np.where(net[truth.row, truth.col], truth.layer, 0)
    truth = PointSet(
        row=truth.row,
        col=truth.col,
        depth_bin=truth.depth_bin,
        image_shape=(r, c),
        intensity=truth.intensity,
        label=truth.label,
        layer=layer,
    )
    return Scene(
        truth=truth,
        n_bins=T,
        irf=models,
        library=None,
        wavelengths_nm=None,
        bin_width_ps=bin_width_ps,
        name="two_layer",
        description=(
            f"net of 1-px strands every {s} px ({100 * net.mean():.0f}% of pixels, "
            f"transmission {tr:g}) in front of a wall, boxes and a ramp"
        ),
    )


#: Default materials of :func:`multispectral_scene`: relative reflectance at 4 wavelengths.
_MATERIALS = {
    "red paint": [0.25, 0.3, 1.0, 0.9],
    "green foliage": [0.3, 1.0, 0.35, 0.8],
    "blue plastic": [1.0, 0.55, 0.2, 0.15],
    "grey concrete": [0.6, 0.6, 0.6, 0.6],
}
_MATERIAL_WAVELENGTHS = (470.0, 550.0, 640.0, 780.0)


def multispectral_scene(
    shape: tuple[int, int] = (48, 48),
    *,
    n_bins: int = 200,
    irf=("gaussian", 3.0),
    n_materials: int = 3,
    two_layers: bool = False,
    net_spacing: int = 5,
    net_transmission: float = 0.6,
    photons: float = 10.0,
    bin_width_ps: float | None = _DEFAULT_BIN_PS,
) -> Scene:
    """Materials with distinct spectra at L = 4 wavelengths, with a spectral library.

    The image is split into vertical bands of ``n_materials`` materials (plus a block of
    a different material in each band); intensity = smooth shading ``h`` (0.4..1) times
    the material's signature ``m_k`` (the library row), so ``label`` = library row. The
    library signatures are scaled so that a surface of unit shading gives ``photons``
    expected photons per wavelength on average (``I = h m_k``).

    With ``two_layers=True`` a net (as in :func:`two_layer_scene`) is added in front;
    each strand pixel's net material differs from the material behind it
    (``(k_back + 1) mod K``).

    Parameters
    ----------
    shape : (rows, cols)
    n_bins : int
    irf : IRF specification (one for all 4 wavelengths or a list of 4)
    n_materials : int
        K, 3 or 4 (red paint, green foliage, blue plastic, grey concrete).
    two_layers : bool
    net_spacing, net_transmission : see :func:`two_layer_scene`
    photons : float
    bin_width_ps : float or None

    Returns
    -------
    Scene
        With ``library`` (K, 4) and ``wavelengths_nm`` (470, 550, 640, 780).

    Raises
    ------
    SplidarError
        ``n_materials`` outside 3..4, window too short, bad parameters.

    Examples
    --------
    >>> s = multispectral_scene((24, 24), n_bins=160)
    >>> s.library.n_classes, s.n_wavelengths, sorted(set(s.truth.label.tolist()))
    (3, 4, [0, 1, 2])
    """
    r, c = _check_shape(shape)
    T = check_int(n_bins, "n_bins", minimum=8)
    K = check_int(n_materials, "n_materials", minimum=3)
    if K > len(_MATERIALS):
        raise SplidarError(f"`n_materials` must be 3 or 4; got {K}.")
    photons = check_positive(photons, "photons")
    L = len(_MATERIAL_WAVELENGTHS)
    names = list(_MATERIALS)[:K]
    sig = np.array([_MATERIALS[n] for n in names], dtype=np.float64)
    sig *= photons / sig.mean()
    library = SpectralLibrary(sig, class_names=names)
    models = as_irf_models(irf, n_wavelengths=L)

    y, x = np.mgrid[0:r, 0:c].astype(np.float64)
    yn, xn = y / (r - 1), x / (c - 1)
    band = np.minimum((xn * K).astype(np.int64), K - 1)
    label = band.copy()
    block = (yn > 0.55) & (yn < 0.85) & (((xn * K) % 1.0) > 0.25) & (((xn * K) % 1.0) < 0.75)
    label[block] = (band[block] + 1) % K  # a patch of the next material inside each band
    shading = 0.4 + 0.6 * (0.5 + 0.5 * np.cos(2 * np.pi * (0.7 * xn + 0.4 * yn)))

    if not two_layers:
        lo, hi = _usable(models, T, need=10.0)
        unit, _ = _single_geometry(r, c)
        depth = lo + unit * (hi - lo)
        inten = shading[..., None] * sig[label]
        truth = _grid_points([depth], [inten], [label], [0], [np.ones((r, c), bool)], (r, c))
        desc = f"{K} materials in bands with patches, 4 wavelengths, one surface per pixel"
    else:
        back = two_layer_scene(
            (r, c),
            n_bins=T,
            irf=models,
            n_wavelengths=L,
            net_spacing=net_spacing,
            net_transmission=net_transmission,
            photons=1.0,
            bin_width_ps=bin_width_ps,
        ).truth
        # material per point: back surfaces keep the pixel's material, the net the next one
        cnt = np.zeros((r, c), np.int64)
        np.add.at(cnt, (back.row, back.col), 1)
        on_net = cnt[back.row, back.col] == 2
        net_pt = on_net & (back.layer == 0)
        lab = label[back.row, back.col]
        lab = np.where(net_pt, (lab + 1) % K, lab)
        tr = float(net_transmission)
        share = np.where(net_pt, 1.0 - tr, np.where(on_net, tr, 1.0))  # light per surface
        inten = (share * shading[back.row, back.col])[:, None] * sig[lab]
        truth = PointSet(
            row=back.row,
            col=back.col,
            depth_bin=back.depth_bin,
            image_shape=(r, c),
            intensity=inten,
            label=lab,
            layer=back.layer,
        )
        desc = f"{K} materials, 4 wavelengths, a net of a different material in front"
    return Scene(
        truth=truth,
        n_bins=T,
        irf=models,
        library=library,
        wavelengths_nm=np.array(_MATERIAL_WAVELENGTHS),
        bin_width_ps=bin_width_ps,
        name="multispectral" + ("_two_layers" if two_layers else ""),
        description=desc,
    )


# ----------------------------------------------------------------------------------------
# Middlebury Art
# ----------------------------------------------------------------------------------------


def _read_png(path: Path) -> np.ndarray:
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - depends on the environment
        raise SplidarError(
            "art_scene needs Pillow to read PNG files; install it with `pip install pillow`."
        ) from None
    with Image.open(path) as im:
        return np.asarray(im)


def _halve(a: np.ndarray) -> np.ndarray:
    """2 x 2 block mean, repeating the last row/column when a size is odd."""
    if a.shape[0] % 2:
        a = np.concatenate([a, a[-1:]], axis=0)
    if a.shape[1] % 2:
        a = np.concatenate([a, a[:, -1:]], axis=1)
    r, c = a.shape[0] // 2, a.shape[1] // 2
    return a.reshape(r, 2, c, 2, *a.shape[2:]).mean(axis=(1, 3))


def art_scene(
    folder: str | os.PathLike,
    *,
    color: bool = True,
    n_bins: int = 164,
    irf=("gaussian", 3.0),
    n_classes: int = 4,
    photons: float = 10.0,
    bin_width_ps: float | None = _DEFAULT_BIN_PS,
) -> Scene:
    """The paper's simulated scene: Middlebury 2005 "Art", two copies one behind the other.

    Reads ``view1.png`` (RGB), ``disp1.png`` (disparity, 0 = unknown) and ``dmin.txt``
    (disparity offset) from ``folder`` (third-size files, 463 x 370). Unknown disparities
    are filled from the nearest known pixel, then image and disparity are halved by 2 x 2
    block means (odd sizes repeat the last row/column) to 185 x 232 pixels.

    Depth is proportional to ``1 / (disp + dmin)``; it is mapped linearly into the
    window so that the front copy spans ``[lo, lo + D]`` and the back copy is the same
    scene ``D + gap`` bins later (``gap`` = 2 IRF widths), with ``lo`` and the end
    margin set by the IRF support. Every pixel thus has two surfaces (layer 0 / 1).

    Intensity: ``photons x (0.05 + 0.95 v / 255)`` for each RGB channel ``v``
    (``color=True``, L = 3, wavelengths 640/550/460 nm for R/G/B) or of the luminance
    ``0.299 R + 0.587 G + 0.114 B`` (``color=False``, L = 1); the 0.05 floor keeps black
    pixels detectable. Both copies share the image.

    Labels: with ``color``, the RGB intensities are clustered by k-means
    (``scipy.cluster.vq.kmeans2``, fixed seed, ``n_classes`` clusters) on colours
    normalised to unit sum (hue, not brightness); the library holds the cluster mean
    intensities (K, 3) and ``label`` is the cluster. Grey: label 0, no library.

    Parameters
    ----------
    folder : path
        Folder with ``view1.png``, ``disp1.png``, ``dmin.txt``.
    color : bool
    n_bins : int
        T (the paper: 164).
    irf : IRF specification
    n_classes : int
        Number of colour classes (``color=True`` only).
    photons : float
        Mean expected signal photons per surface and wavelength at nominal brightness.
    bin_width_ps : float or None
        Stored bin width (16 ps by default: an assumption, the paper does not say).

    Returns
    -------
    Scene

    Raises
    ------
    SplidarError
        Missing files, unreadable content, a window too short for the IRF.

    Examples
    --------
    >>> s = art_scene("/work/shared/data/middlebury-art")  # doctest: +SKIP
    >>> s.shape, s.n_bins, int(s.surfaces_per_pixel().min())  # doctest: +SKIP
    ((185, 232), 164, 2)
    """
    from scipy import ndimage

    folder = Path(folder)
    files = {n: folder / n for n in ("view1.png", "disp1.png", "dmin.txt")}
    missing = [n for n, p in files.items() if not p.is_file()]
    if missing:
        raise SplidarError(
            f"art_scene: {folder} lacks {missing}; point `folder` at the Middlebury 2005 Art "
            "third-size files (view1.png, disp1.png, dmin.txt)."
        )
    T = check_int(n_bins, "n_bins", minimum=8)
    photons = check_positive(photons, "photons")
    try:
        dmin = float(files["dmin.txt"].read_text().split()[0])
    except (ValueError, IndexError):
        raise SplidarError(f"art_scene: {files['dmin.txt']} must hold a number.") from None
    rgb = _read_png(files["view1.png"]).astype(np.float64)
    disp = _read_png(files["disp1.png"]).astype(np.float64)
    if rgb.ndim != 3 or rgb.shape[2] < 3 or disp.ndim != 2 or disp.shape != rgb.shape[:2]:
        raise SplidarError(
            f"art_scene: expected an RGB view1.png and a grey disp1.png of the same size; got "
            f"{rgb.shape} and {disp.shape}."
        )
    rgb = rgb[..., :3]
    unknown = disp == 0
    if unknown.all():
        raise SplidarError("art_scene: disp1.png holds no known disparity (all zero).")
    if unknown.any():
        idx = ndimage.distance_transform_edt(unknown, return_distances=False, return_indices=True)
        disp = disp[tuple(idx)]
    disp = _halve(disp)
    rgb = _halve(rgb)
    r, c = disp.shape

    if color:
        L = 3
        inten = photons * (0.05 + 0.95 * rgb / 255.0)
        wl = np.array([640.0, 550.0, 460.0])
    else:
        L = 1
        grey = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
        inten = photons * (0.05 + 0.95 * grey / 255.0)[..., None]
        wl = None
    models = as_irf_models(irf, n_wavelengths=L)
    w = _irf_width(models)
    gap = 2.0 * w
    lo, hi = _usable(models, T, need=gap + 10.0)
    span = (hi - lo - gap) / 2.0
    z = 1.0 / (disp + dmin)
    unit = (z - z.min()) / (z.max() - z.min()) if z.max() > z.min() else np.zeros_like(z)
    front = lo + unit * span
    back = front + span + gap

    if color:
        from scipy.cluster.vq import kmeans2

        K = check_int(n_classes, "n_classes", minimum=1)
        feats = inten.reshape(-1, 3)
        hue = feats / feats.sum(axis=1, keepdims=True)
        _, lab = kmeans2(hue, K, seed=0, minit="++")
        present = np.unique(lab)
        remap = np.full(K, -1)
        remap[present] = np.arange(present.size)
        lab = remap[lab]
        sig = np.stack([feats[lab == k].mean(axis=0) for k in range(present.size)])
        library = SpectralLibrary(sig, class_names=[f"colour {k}" for k in range(present.size)])
        label = lab.reshape(r, c)
    else:
        library = None
        label = np.zeros((r, c), np.int64)
    ones = np.ones((r, c), bool)
    truth = _grid_points(
        [front, back], [inten, inten], [label, label], [0, 1], [ones, ones], (r, c)
    )
    return Scene(
        truth=truth,
        n_bins=T,
        irf=models,
        library=library,
        wavelengths_nm=wl,
        bin_width_ps=bin_width_ps,
        name="art" + ("_color" if color else "_grey"),
        description=(
            "Middlebury 2005 Art (Scharstein & Pal, CVPR 2007), halved to "
            f"{r}x{c}, two copies {span + gap:.1f} bins apart"
        ),
    )
