"""Fabricated detections with known truth, for tests and benchmarks of the reconstruction.

They let the reconstruction be checked independently of detection quality: every true
surface is "detected" at its true depth (plus optional jitter), and the own-pixel counts
over its support are drawn from exactly the Poisson model of the observation
(``eq:4.1`` summed over the support).
"""

from __future__ import annotations

import numpy as np

from .._validation import check_int, check_positive
from ..detection._result import Background, DataReduction, Detection, NullModel, Surfaces
from ..irf import gaussian_irf
from ..library import SpectralLibrary
from ..points import PointSet
from ._core import irf_fraction

__all__ = ["synthetic_detection"]


def _patches(shape, n_classes, size, rng):
    """Class map of Voronoi patches about ``size`` pixels across."""
    rows, cols = shape
    n_seeds = max(n_classes, int(rows * cols / size**2))
    pts = rng.uniform([0, 0], [rows, cols], size=(n_seeds, 2))
    lab = np.arange(n_seeds) % n_classes
    rng.shuffle(lab)
    rr, cc = np.mgrid[0:rows, 0:cols]
    grid = np.stack([rr.ravel(), cc.ravel()], 1).astype(np.float64)
    # nearest seed, in blocks to bound memory
    near = np.empty(grid.shape[0], np.int64)
    for i in range(0, grid.shape[0], 65536):
        d = ((grid[i : i + 65536, None, :] - pts[None]) ** 2).sum(-1)
        near[i : i + 65536] = d.argmin(1)
    return lab[near].reshape(shape)


def _shading(shape, rng):
    """Smooth shading in about [0.4, 1.6], mean about 1."""
    rows, cols = shape
    rr, cc = np.mgrid[0:rows, 0:cols] / max(rows, cols)
    ph = rng.uniform(0, 2 * np.pi, 2)
    f = rng.uniform(1.0, 2.5, 2)
    return (
        1.0
        + 0.3 * np.sin(2 * np.pi * f[0] * rr + ph[0])
        + 0.3 * np.cos(2 * np.pi * f[1] * cc + ph[1])
    )


def synthetic_detection(
    *,
    shape: tuple[int, int] = (32, 32),
    n_wavelengths: int = 4,
    n_classes: int = 3,
    layers: int = 1,
    ppp: float = 10.0,
    sbr: float = 1.0,
    n_bins: int = 200,
    fwhm: float = 3.0,
    patch_size: float = 8.0,
    depth_jitter: float = 0.0,
    variability: float = 0.0,
    layer_scale=None,
    signatures: np.ndarray | None = None,
    rng=None,
) -> tuple[Detection, PointSet]:
    """A :class:`Detection` whose surfaces are the true ones, and the truth.

    Each layer is a plane (foreground near bin ``0.3 T``, background near ``0.7 T``, with
    a slight tilt) of Voronoi material patches; intensity ``I = shading x m_k`` with a
    smooth shading per layer. Signal photons per pixel (all wavelengths and layers)
    average ``ppp``; the background is uniform in time with ``sbr`` = total signal /
    total background over the ``n_bins`` window. The support of a surface is
    ``depth +- 2 FWHM``; its counts are ``Poisson(eta I + b)`` summed over it.

    Parameters
    ----------
    shape : (rows, cols)
    n_wavelengths, n_classes, layers : int
    ppp, sbr : float
    n_bins : int
    fwhm : float
        Gaussian IRF width (bins).
    patch_size : float
        Typical material patch size (pixels).
    depth_jitter : float
        Standard deviation (bins) of the error added to the detected depth.
    variability : float
        Coefficient of variation of the reflectivity about its class signature: each
        surface and wavelength is multiplied by an independent gamma factor of mean 1
        (0: every surface of a class has exactly the signature's shape).
    layer_scale : sequence of float, optional
        Brightness factor of each layer (applied after the PPP normalisation).
    signatures : array (K, L), optional
        Library; default random well-separated shapes of mean 1 per class.
    rng : None, int or Generator

    Returns
    -------
    detection : Detection
        With ``library`` set to the true signatures.
    truth : PointSet
        True surfaces (same order as ``detection.surfaces``): depth, intensity, label, layer.

    Examples
    --------
    >>> det, truth = synthetic_detection(shape=(4, 5), layers=2, rng=1)
    >>> len(det.surfaces), len(truth)
    (40, 40)
    """
    rng = np.random.default_rng(rng)
    rows, cols = (int(shape[0]), int(shape[1]))
    L = check_int(n_wavelengths, "n_wavelengths", minimum=1)
    K = check_int(n_classes, "n_classes", minimum=1)
    layers = check_int(layers, "layers", minimum=1)
    ppp = check_positive(ppp, "ppp")
    sbr = check_positive(sbr, "sbr")
    if signatures is None:
        m = rng.uniform(0.05, 1.0, size=(K, L))
        # make the shapes distinct: each class peaks at its own wavelength
        for k in range(K):
            m[k, k % L] += 1.0
        m = m / m.mean(axis=1, keepdims=True)
    else:
        m = np.asarray(signatures, dtype=np.float64)
        K, L = m.shape
    g = gaussian_irf(fwhm)
    irf = np.repeat(g[None], L, axis=0)
    half = int(np.ceil(2 * fwhm))

    rr, cc = np.mgrid[0:rows, 0:cols]
    recs = []
    for layer in range(layers):
        lab = _patches((rows, cols), K, patch_size, rng)
        shade = _shading((rows, cols), rng)
        base = n_bins * (0.3 + 0.4 * layer / max(layers - 1, 1)) if layers > 1 else 0.4 * n_bins
        tilt = rng.uniform(-0.05, 0.05, 2)
        depth = base + tilt[0] * (rr - rows / 2) + tilt[1] * (cc - cols / 2)
        depth = depth + rng.uniform(-0.5, 0.5, size=(rows, cols))
        recs.append((lab, shade, depth, layer))
    row = np.tile(rr.ravel(), layers)
    col = np.tile(cc.ravel(), layers)
    label = np.concatenate([r_[0].ravel() for r_ in recs])
    shading = np.concatenate([r_[1].ravel() for r_ in recs])
    depth = np.concatenate([r_[2].ravel() for r_ in recs])
    slot = np.concatenate([np.full(rows * cols, r_[3]) for r_ in recs])
    inten = shading[:, None] * m[label]
    if variability > 0:
        k_shape = 1.0 / variability**2
        inten = inten * rng.gamma(k_shape, 1.0 / k_shape, size=inten.shape)
    inten *= ppp * rows * cols / inten.sum()
    if layer_scale is not None:
        inten = inten * np.asarray(layer_scale, dtype=np.float64)[slot][:, None]
    S = row.size
    det_depth = depth + depth_jitter * rng.standard_normal(S)
    start = np.floor(det_depth).astype(np.int64) - half
    stop = np.floor(det_depth).astype(np.int64) + half + 1
    start = np.clip(start, 0, n_bins)
    stop = np.clip(stop, 0, n_bins)
    # expected signal in the support is computed at the true depth
    eta = irf_fraction(irf, depth, start, stop)
    b_bin = ppp / (sbr * n_bins * L)  # per bin and wavelength
    b = np.full((S, L), b_bin) * (stop - start)[:, None]
    counts = rng.poisson(eta * inten + b).astype(np.float64)
    return _assemble(
        row, col, slot, depth, det_depth, start, stop, counts, b, b_bin, inten, label, irf, m,
        (rows, cols, L, int(n_bins)), layers,
    )  # fmt: skip


def _assemble(
    row, col, slot, depth, det_depth, start, stop, counts, b, b_bin, inten, label, irf, m,
    cube_shape, layers,
) -> tuple[Detection, PointSet]:  # fmt: skip
    """The Detection of the true surfaces and the truth, from the simulated arrays."""
    rows, cols, L, T = cube_shape
    S = row.size
    signal = np.maximum(counts - b, 0.0)
    surfaces = Surfaces(
        row=row.astype(np.int64),
        col=col.astype(np.int64),
        slot=slot.astype(np.int64),
        depth_bin=det_depth,
        start=start,
        stop=stop,
        scale_index=np.zeros(S, np.int64),
        offset=start.copy(),
        histograms=np.zeros((S, 1, L, 1), np.float32),
        signal=signal[:, None, :],
        counts=counts,
        background=b,
        saliency_mass=signal.sum(1),
        image_shape=(rows, cols),
        n_slots=layers,
    )
    det = Detection(
        cube_shape=(rows, cols, L, T),
        irf=irf,
        bin_width_ps=250.0,
        wavelengths_nm=None,
        library=SpectralLibrary(m),
        scales=(1,),
        weights=np.ones(1),
        pfa=1e-3,
        background=Background(
            spatial=np.full((rows, cols, L), b_bin, np.float32),
            temporal=np.zeros((L, T), np.float32),
        ),
        saliency=np.broadcast_to(np.zeros((1, 1, 1), np.float32), (rows, cols, T)),
        null=NullModel(shape=1.0, scale=1.0, method="synthetic", pfa=1e-3),
        threshold=0.0,
        mask=np.broadcast_to(np.zeros((1, 1, 1), bool), (rows, cols, T)),
        reduction=DataReduction(0.0, 0.0, 0, 0),
        surfaces=surfaces,
        options={"synthetic": True},
    )
    truth = PointSet(
        row=row.astype(np.int64),
        col=col.astype(np.int64),
        depth_bin=depth,
        image_shape=(rows, cols),
        intensity=inten,
        label=label.astype(np.int64),
        layer=slot.astype(np.int64),
    )
    return det, truth
