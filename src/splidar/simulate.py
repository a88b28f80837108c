"""Simulate single-photon lidar cubes from ground-truth surfaces (the observation model).

Implements ``eq:4.1`` of the paper::

    y[n, l, t] ~ Poisson( sum_c I[n, c, l] g_l(t - d[n, c]) + b[n, l, t] )

where each surface ``c`` of pixel ``n`` has a fractional depth ``d`` (the bin where the
*peak* of its return lands, ALGORITHM-NOTES) and an intensity ``I`` per wavelength
(expected signal photons, ``I = h r``), ``g_l`` is the IRF of wavelength ``l`` shifted
by the **true** sub-bin amount (no rounding), and ``b`` is the background.

Definitions used throughout (they are also what :class:`Simulation` reports):

- **PPP** = expected signal photons per pixel, summed over all wavelengths and bins,
  averaged over *all* pixels (pixels with no surface count as zero).
- **SBR** = total expected signal photons / total expected background photons in the
  cube (all pixels, wavelengths and bins).
- Only photons that land inside the time window ``[0, n_bins)`` count: a return cut by
  the window edge contributes the part inside.

Rendering cost grows with the number of surfaces times the IRF support, not with T,
and the Poisson draws run in blocks of rows; background photons are placed one by one
(their count per pixel is Poisson, their bins follow the temporal shape) when the
background is sparse, which is exact and much faster than one draw per voxel.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from ._validation import SplidarError, as_float_array, check_choice, check_int, check_positive
from .cube import SPEED_OF_LIGHT, Cube
from .irf import as_irf_models, sample_irf_models, shifted_irf_window
from .library import as_library
from .points import PointSet

__all__ = ["BACKGROUND_SHAPES", "Simulation", "background_shape", "expected_counts", "simulate"]

logger = logging.getLogger(__name__)

#: Names of the built-in temporal background shapes.
BACKGROUND_SHAPES = ("uniform", "decaying", "pileup")

# Voxel budget of one block of rows (int64 bincount buffer of 8 bytes per voxel).
_BLOCK_VOXELS = 4_000_000
# Below this many background photons per voxel, place photons instead of drawing per voxel.
_SPARSE_BACKGROUND = 0.5


def background_shape(name: str, n_bins: int) -> np.ndarray:
    """A built-in temporal background shape ``(n_bins,)`` with mean exactly 1.

    Parameters
    ----------
    name : {"uniform", "decaying", "pileup"}
        - ``"uniform"``: constant (ambient light, dark counts).
        - ``"decaying"``: ``exp(-3 t / T)``, a 20-fold decay across the window, like the
          backscatter of an obscurant (fog, smoke, foliage) that falls with range.
        - ``"pileup"``: ``0.05 + exp(-t / (T / 30))``, high in the first bins and decaying
          quickly to a low floor, like the early-photon bias of pile-up or a gate opening.
    n_bins : int
        T.

    Returns
    -------
    shape : ndarray, shape (n_bins,), float64, mean 1

    Raises
    ------
    SplidarError
        Unknown name or ``n_bins`` < 1.

    Examples
    --------
    >>> s = background_shape("decaying", 100)
    >>> round(float(s.mean()), 12), bool(s[0] > s[-1])
    (1.0, True)
    """
    check_choice(name, "background", BACKGROUND_SHAPES)
    T = check_int(n_bins, "n_bins", minimum=1)
    t = np.arange(T, dtype=np.float64)
    if name == "uniform":
        s = np.ones(T)
    elif name == "decaying":
        s = np.exp(-3.0 * t / T)
    else:
        s = 0.05 + np.exp(-t / max(1.0, T / 30.0))
    return s / s.mean()


@dataclass(frozen=True)
class Simulation:
    """A simulated cube with its ground truth and the Poisson mean that produced it.

    Attributes
    ----------
    cube : Cube
        The simulated counts ``(rows, cols, L, T)`` (uint16, or uint32 when a count
        exceeds 65535) with the sampled IRF (argmax = mode = depth reference).
    truth : PointSet
        The surfaces, with ``intensity`` (n, L) **after** scaling to the requested PPP
        (expected signal photons, including any part cut by the window edge), labels
        and layers as given, and ``depth_m`` when the bin width is known.
    background_spatial : ndarray, shape (rows, cols, L), float64
        Spatial factor of the background mean.
    background_temporal : ndarray, shape (L, T), float64, or None
        Temporal factor: the background mean is
        ``background_spatial[..., None] * background_temporal`` (counts per bin).
        ``None`` when a full ``(rows, cols, L, T)`` background was given; then it is in
        ``background_dense``.
    background_dense : ndarray, shape (rows, cols, L, T), float64, or None
        The background mean when it does not factor.
    ppp : float
        Expected signal photons per pixel (all wavelengths), as realised in the window.
    sbr : float
        Expected signal / background photons over the cube (``inf`` with no background).
    metadata : mapping
        How the cube was made (background name, requested ppp/sbr, scale factors).
    """

    cube: Cube
    truth: PointSet
    background_spatial: np.ndarray
    background_temporal: np.ndarray | None
    background_dense: np.ndarray | None
    ppp: float
    sbr: float
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        return (
            f"Simulation(cube={self.cube!r}, truth={self.truth!r}, ppp={self.ppp:.4g}, "
            f"sbr={self.sbr:.4g}, background={self.metadata.get('background')!r})"
        )

    def background(self, rows=slice(None), cols=slice(None)) -> np.ndarray:
        """Background mean over a block of pixels, shape ``(r, c, L, T)`` float64."""
        if self.background_dense is not None:
            return self.background_dense[rows, cols]
        return self.background_spatial[rows, cols][..., None] * self.background_temporal

    @property
    def background_per_bin(self) -> np.ndarray:
        """Mean background counts per bin and pixel, per wavelength, shape ``(L,)``."""
        if self.background_dense is not None:
            return self.background_dense.mean(axis=(0, 1, 3))
        sp = self.background_spatial.reshape(-1, self.background_spatial.shape[-1]).mean(axis=0)
        return sp * self.background_temporal.mean(axis=-1)

    @property
    def signal_photons(self) -> float:
        """Total expected signal photons in the cube (``ppp x`` pixels)."""
        return self.ppp * self.cube.n_pixels


# ----------------------------------------------------------------------------------------
# planning: validate inputs, scale intensities and background
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Plan:
    rows: int
    cols: int
    L: int
    T: int
    models: tuple
    truth: PointSet  # as given, intensities scaled
    order: np.ndarray  # point indices sorted by row
    spatial: np.ndarray  # (rows, cols, L)
    temporal: np.ndarray | None  # (L, T)
    dense: np.ndarray | None  # (rows, cols, L, T)
    ppp: float
    sbr: float
    metadata: dict


def _kernels(models, depth: np.ndarray, l: int, T: int):
    """Sum-normalised returns ``(t, vals)`` of wavelength ``l`` (:func:`shifted_irf_window`)."""
    return shifted_irf_window(models[l], depth)


def _window_mass(models, depth: np.ndarray, L: int, T: int) -> np.ndarray:
    """Fraction ``(n, L)`` of each normalised return inside ``[0, T)``."""
    mass = np.ones((depth.size, L))
    for l in range(L):
        left, right = models[l].support
        near = (np.floor(depth) - left < 0) | (np.floor(depth) - left + left + right + 2 > T)
        idx = np.flatnonzero(near)
        for k in range(0, idx.size, 20_000):  # bounded memory for long IRF tails
            sel = idx[k : k + 20_000]
            t, v = _kernels(models, depth[sel], l, T)
            mass[sel, l] = np.where((t >= 0) & (t < T), v, 0.0).sum(axis=1)
    return mass


def _as_background(background, background_map, rows, cols, L, T):
    """Unscaled background as factors ``(spatial, temporal)`` or ``dense``, plus a name."""
    if background is None or isinstance(background, str):
        name = "uniform" if background is None else background
        check_choice(name, "background", BACKGROUND_SHAPES)
        temporal = np.repeat(background_shape(name, T)[None], L, axis=0)
        dense = None
    else:
        name = "array"
        a = as_float_array(background, "background")
        if np.any(a < 0):
            raise SplidarError(
                f"`background` has {int(np.count_nonzero(a < 0))} negative value(s); a "
                "background is a mean count per bin (>= 0)."
            )
        if a.shape == (T,):
            temporal, dense = np.repeat(a[None], L, axis=0), None
        elif a.shape == (L, T):
            temporal, dense = a.copy(), None
        elif a.shape == (rows, cols, L, T):
            temporal, dense = None, a.copy()
        else:
            raise SplidarError(
                f"`background` array must have shape (T,) = ({T},), (L, T) = ({L}, {T}) or "
                f"(rows, cols, L, T) = ({rows}, {cols}, {L}, {T}); got {a.shape}. Or pass one "
                f"of {', '.join(map(repr, BACKGROUND_SHAPES))}."
            )
    if background_map is None:
        spatial = np.ones((rows, cols, L))
    else:
        mp = as_float_array(background_map, "background_map")
        if mp.shape == (rows, cols):
            mp = np.repeat(mp[..., None], L, axis=-1)
        if mp.shape != (rows, cols, L):
            raise SplidarError(
                f"`background_map` must have shape (rows, cols) = ({rows}, {cols}) or "
                f"(rows, cols, L) = ({rows}, {cols}, {L}); got {mp.shape}."
            )
        if np.any(mp < 0):
            raise SplidarError("`background_map` must be non-negative (a relative level).")
        spatial = mp.copy()
    if dense is not None:
        dense = dense * spatial[..., None]
        spatial = np.ones((rows, cols, L))
    return spatial, temporal, dense, name


def _bg_mean_per_l(spatial, temporal, dense) -> np.ndarray:
    if dense is not None:
        return dense.mean(axis=(0, 1, 3))
    return spatial.mean(axis=(0, 1)) * temporal.mean(axis=-1)


def _infer_L(truth, irf, wavelengths_nm, library) -> int:
    if truth.intensity is not None:
        return truth.n_wavelengths
    if wavelengths_nm is not None:
        return int(np.size(wavelengths_nm))
    if library is not None:
        return as_library(library).n_wavelengths
    return len(as_irf_models(irf))


def _plan(
    truth, n_bins, irf, ppp, sbr, background, background_map, background_per_bin,
    wavelengths_nm, library,
) -> _Plan:  # fmt: skip
    if not isinstance(truth, PointSet):
        raise SplidarError(
            f"`truth` must be a splidar.PointSet; got {type(truth).__name__}. Build one with "
            "PointSet(row=, col=, depth_bin=, image_shape=, intensity=)."
        )
    T = check_int(n_bins, "n_bins", minimum=1)
    rows, cols = truth.image_shape
    L = _infer_L(truth, irf, wavelengths_nm, library)
    models = as_irf_models(irf, n_wavelengths=L)
    if ppp is not None:
        ppp = check_positive(ppp, "ppp")
    if sbr is not None:
        sbr = check_positive(sbr, "sbr")
    depth = truth.depth_bin
    if depth.size and (depth.min() < 0 or depth.max() > T - 1):
        bad = int(np.count_nonzero((depth < 0) | (depth > T - 1)))
        raise SplidarError(
            f"{bad} truth point(s) have depth_bin outside the time window [0, {T - 1}] "
            f"(range {depth.min():.3g}..{depth.max():.3g}); increase n_bins or move the surfaces."
        )
    if truth.intensity is None:
        if ppp is None:
            raise SplidarError(
                "`truth` has no intensity; give it intensities (n, L) (expected signal photons) "
                "or pass ppp= to give every surface the same brightness."
            )
        intensity = np.ones((len(truth), L))
    else:
        intensity = np.array(truth.intensity, dtype=np.float64)
        if np.any(intensity < 0):
            raise SplidarError("`truth.intensity` must be non-negative (expected photon counts).")

    # signal photons inside the window, before scaling
    mass = _window_mass(models, depth, L, T)
    signal = float((intensity * mass).sum())
    scale = 1.0
    if ppp is not None:
        if signal <= 0:
            raise SplidarError(
                "cannot scale to `ppp`: the truth has no signal inside the window (all "
                "intensities zero or no points)."
            )
        scale = ppp * rows * cols / signal
        intensity = intensity * scale
        signal = ppp * rows * cols

    # background
    spatial, temporal, dense, bg_name = _as_background(background, background_map, rows, cols, L, T)
    explicit_name = isinstance(background, str)
    if background_per_bin is not None:
        lv = as_float_array(background_per_bin, "background_per_bin").reshape(-1)
        if lv.size == 1:
            lv = np.repeat(lv, L)
        if lv.size != L or np.any(lv < 0):
            raise SplidarError(
                f"`background_per_bin` must be a number >= 0 or {L} numbers >= 0 (one per "
                f"wavelength); got {np.asarray(background_per_bin)!r}."
            )
        cur = _bg_mean_per_l(spatial, temporal, dense)
        if np.any((cur <= 0) & (lv > 0)):
            raise SplidarError(
                "`background_per_bin` asks for background where the given background shape "
                "or `background_map` is zero everywhere; pass a non-zero shape."
            )
        f = np.where(cur > 0, lv / np.where(cur > 0, cur, 1.0), 0.0)
        if dense is not None:
            dense = dense * f[None, None, :, None]
        else:
            spatial = spatial * f
    elif sbr is None and bg_name != "array":
        if explicit_name or background_map is not None:
            what = f"`background={background!r}`" if explicit_name else "`background_map`"
            raise SplidarError(
                f"{what} gives only a shape; also pass sbr= or background_per_bin= to set "
                "the background level (or leave both out for no background)."
            )
        spatial = np.zeros((rows, cols, L))
    bg_total = float(_bg_mean_per_l(spatial, temporal, dense).sum()) * rows * cols * T
    bg_scale = 1.0
    if sbr is not None:
        if signal <= 0:
            raise SplidarError("cannot set `sbr`: the truth has no signal inside the window.")
        if bg_total <= 0:
            raise SplidarError(
                "cannot set `sbr`: the background shape is zero everywhere; pass a non-zero "
                "background (and background_per_bin > 0 if given)."
            )
        bg_scale = signal / sbr / bg_total
        if dense is not None:
            dense = dense * bg_scale
        else:
            spatial = spatial * bg_scale
        bg_total = signal / sbr

    kw = truth.to_dict()
    kw.pop("image_shape")
    kw["intensity"] = intensity
    new_truth = PointSet(image_shape=(rows, cols), **kw)
    order = np.argsort(truth.row, kind="stable")  # rendering walks blocks of rows
    real_ppp = signal / (rows * cols)
    real_sbr = signal / bg_total if bg_total > 0 else float("inf")
    md = {
        "simulated": True,
        "background": bg_name,
        "requested_ppp": ppp,
        "requested_sbr": sbr,
        "intensity_scale": scale,
        "background_scale": bg_scale,
    }
    return _Plan(
        rows, cols, L, T, models, new_truth, order, spatial, temporal, dense, real_ppp, real_sbr, md
    )


# ----------------------------------------------------------------------------------------
# rendering
# ----------------------------------------------------------------------------------------


def _signal_block(plan: _Plan, lo: int, hi: int, r0: int):
    """Flat voxel indices and expected values of the signal of points ``lo:hi`` (rows from r0)."""
    tr = plan.truth
    L, T, cols = plan.L, plan.T, plan.cols
    sel = plan.order[lo:hi]
    depth = tr.depth_bin[sel]
    pix = (tr.row[sel] - r0) * cols + tr.col[sel]
    idx, val = [], []
    for l in range(L):
        t, v = _kernels(plan.models, depth, l, T)
        v *= tr.intensity[sel, l][:, None]
        ok = (t >= 0) & (t < T) & (v > 0)
        flat = (pix[:, None] * L + l) * T + t
        idx.append(flat[ok])
        val.append(v[ok])
    return np.concatenate(idx), np.concatenate(val)


def _blocks(plan: _Plan):
    per_row = plan.cols * plan.L * plan.T
    step = max(1, _BLOCK_VOXELS // per_row)
    rows_sorted = plan.truth.row[plan.order]
    for r0 in range(0, plan.rows, step):
        r1 = min(plan.rows, r0 + step)
        lo, hi = np.searchsorted(rows_sorted, [r0, r1])
        yield r0, r1, int(lo), int(hi)


def expected_counts(
    truth: PointSet,
    *,
    n_bins: int,
    irf,
    ppp: float | None = None,
    sbr: float | None = None,
    background=None,
    background_map=None,
    background_per_bin=None,
) -> np.ndarray:
    """The Poisson mean of ``eq:4.1`` as a dense ``(rows, cols, L, T)`` float64 array.

    Same parameters and scaling rules as :func:`simulate` (which draws from this mean).
    Dense: mind memory on large cubes (8 bytes per voxel).

    Examples
    --------
    >>> from splidar import PointSet
    >>> truth = PointSet(row=[0], col=[0], depth_bin=[20.3], image_shape=(1, 2), intensity=[[5.0]])
    >>> lam = expected_counts(truth, n_bins=50, irf=("gaussian", 3.0), background_per_bin=0.1)
    >>> lam.shape, int(lam[0, 0, 0].argmax()), round(float(lam.sum()), 6)
    ((1, 2, 1, 50), 20, 15.0)
    """
    plan = _plan(
        truth, n_bins, irf, ppp, sbr, background, background_map, background_per_bin, None, None
    )
    return _expected(plan)


def _expected(plan: _Plan) -> np.ndarray:
    rows, cols, L, T = plan.rows, plan.cols, plan.L, plan.T
    out = np.empty((rows, cols, L, T))
    for r0, r1, lo, hi in _blocks(plan):
        if plan.dense is not None:
            blk = plan.dense[r0:r1].copy()
        else:
            blk = plan.spatial[r0:r1][..., None] * plan.temporal
        if hi > lo:
            idx, val = _signal_block(plan, lo, hi, r0)
            blk += np.bincount(idx, weights=val, minlength=blk.size).reshape(blk.shape)
        out[r0:r1] = blk
    return out


def _draw_counts(plan: _Plan, rng: np.random.Generator) -> np.ndarray:
    """The Poisson counts of ``plan`` (``eq:4.1``), block by block of rows: uint16 (uint32
    when a count exceeds it), shape ``(rows, cols, L, T)``."""
    rows, cols, L, T = plan.rows, plan.cols, plan.L, plan.T
    counts = np.empty((rows, cols, L, T), np.uint16)
    cdf = None
    if plan.temporal is not None:
        tsum = plan.temporal.sum(axis=-1)  # (L,)
        cdf = np.cumsum(plan.temporal, axis=-1)
        cdf /= np.where(cdf[:, -1:] > 0, cdf[:, -1:], 1.0)
    for r0, r1, lo, hi in _blocks(plan):
        nb = (r1 - r0) * cols
        size = nb * L * T
        parts = []
        # background
        if plan.dense is not None:
            bg = rng.poisson(plan.dense[r0:r1]).reshape(-1)
        else:
            sp = plan.spatial[r0:r1].reshape(nb, L)
            lam_tot = sp * tsum  # (nb, L) expected background photons per pixel
            if lam_tot.sum() <= _SPARSE_BACKGROUND * size:
                bg = None
                n_ph = rng.poisson(lam_tot)
                for l in range(L):
                    m = int(n_ph[:, l].sum())
                    if m == 0:
                        continue
                    pix = np.repeat(np.arange(nb), n_ph[:, l])
                    t = np.searchsorted(cdf[l], rng.random(m), side="right")
                    np.minimum(t, T - 1, out=t)
                    parts.append((pix * L + l) * T + t)
            else:
                bg = rng.poisson(sp[..., None] * plan.temporal).reshape(-1)
        # signal: independent Poisson per voxel of each return (sums of Poissons are Poisson)
        if hi > lo:
            idx, val = _signal_block(plan, lo, hi, r0)
            k = rng.poisson(val)
            parts.append(np.repeat(idx, k))
        if parts:
            blk = np.bincount(np.concatenate(parts), minlength=size)
            if bg is not None:
                blk += bg
        else:
            blk = bg if bg is not None else np.zeros(size, np.int64)
        mx = int(blk.max()) if blk.size else 0
        if mx > np.iinfo(counts.dtype).max:
            logger.info("a count of %d exceeds uint16; storing counts as uint32", mx)
            counts = counts.astype(np.uint32)
        counts[r0:r1] = blk.reshape(r1 - r0, cols, L, T)
    return counts


def simulate(
    truth: PointSet,
    *,
    n_bins: int,
    irf,
    ppp: float | None = None,
    sbr: float | None = None,
    background=None,
    background_map=None,
    background_per_bin=None,
    bin_width_ps: float | None = None,
    wavelengths_nm=None,
    library=None,
    rng=None,
) -> Simulation:
    """Draw a photon-count cube from ground-truth surfaces (``eq:4.1``).

    Parameters
    ----------
    truth : PointSet
        Surfaces: ``row``, ``col``, fractional ``depth_bin`` (bin of the return's peak,
        inside ``[0, n_bins - 1]``), ``intensity`` (n, L) = expected signal photons per
        wavelength, optional ``label``/``layer`` (kept). Any number of surfaces per pixel.
        Without intensity, ``ppp`` is required and every surface gets the same brightness.
    n_bins : int
        T, the number of time bins.
    irf : IRF model, ("gaussian", fwhm), ("exp_tail", fwhm, tail), number, array or list
        Per-wavelength IRF (see :func:`splidar.irf.as_irf_models`; widths in bins).
        Parametric models are evaluated exactly at the sub-bin shift; sampled arrays are
        shifted by linear interpolation (which keeps their sum). Each return is
        normalised so that its photons over the IRF support equal the intensity.
    ppp : float, optional
        Rescale all intensities by one factor so that the expected signal photons per
        pixel (over all pixels and wavelengths, inside the window) equal ``ppp``.
    sbr : float, optional
        Rescale the background by one factor so that total expected signal / total
        expected background = ``sbr``. ``background_per_bin`` then sets only the relative
        levels between wavelengths.
    background : None, {"uniform", "decaying", "pileup"} or ndarray
        Temporal shape of the background (see :func:`background_shape`), or an array
        ``(T,)``, ``(L, T)`` or ``(rows, cols, L, T)`` of mean counts per bin. ``None``:
        uniform, and no background at all unless ``sbr`` or ``background_per_bin`` is
        given. A named shape requires one of them; an array without them is used as
        the absolute background mean.
    background_map : array_like (rows, cols) or (rows, cols, L), optional
        Relative spatial level of the background (e.g. brighter where the sun hits).
    background_per_bin : float or array_like (L,), optional
        Mean background counts per bin and pixel, per wavelength (averaged over pixels
        and bins): the background (shape times map) is scaled to it per wavelength.
    bin_width_ps : float, optional
        Bin width, stored in the cube (and used for ``truth.depth_m``).
    wavelengths_nm : array_like (L,), optional
    library : SpectralLibrary or array_like (K, L), optional
        Stored in the cube (the simulator does not use it).
    rng : None, int or numpy Generator
        Source of randomness (``np.random.default_rng(rng)``).

    Returns
    -------
    Simulation
        Cube, scaled truth, the background mean used, realised PPP and SBR.

    Raises
    ------
    SplidarError
        Non-positive ``ppp``/``sbr``, unknown background name, wrong background or map
        shape, negative values, a truth depth outside the window, no signal to scale,
        a named background with no level, an IRF longer than ``n_bins``.

    Notes
    -----
    Expected counts never get clipped or rescaled beyond the documented ``ppp``/``sbr``
    factors. Counts are uint16, or uint32 if any count exceeds 65535.

    Examples
    --------
    >>> import numpy as np
    >>> from splidar import PointSet
    >>> truth = PointSet(row=[0, 0, 1], col=[0, 0, 1], depth_bin=[10.2, 30.7, 22.5],
    ...                  image_shape=(2, 2), intensity=np.ones((3, 1)))
    >>> sim = simulate(truth, n_bins=64, irf=("exp_tail", 2.0, 1.5), ppp=50, sbr=2, rng=0)
    >>> sim.cube.shape, round(sim.ppp, 6), round(sim.sbr, 6)
    ((2, 2, 1, 64), 50.0, 2.0)
    """
    plan = _plan(
        truth,
        n_bins,
        irf,
        ppp,
        sbr,
        background,
        background_map,
        background_per_bin,
        wavelengths_nm,
        library,
    )
    rng = np.random.default_rng(rng)
    L, T = plan.L, plan.T
    irf_arr = sample_irf_models(plan.models)
    if irf_arr.shape[1] > T:
        raise SplidarError(
            f"the sampled IRF ({irf_arr.shape[1]} samples) is longer than n_bins = {T}; use a "
            "longer window or a narrower IRF (shorter tail)."
        )
    counts = _draw_counts(plan, rng)

    lib = as_library(library, n_wavelengths=L)
    tr = plan.truth
    if bin_width_ps is not None:
        bw = check_positive(bin_width_ps, "bin_width_ps")
        kw = tr.to_dict()
        kw.pop("image_shape")
        kw["depth_m"] = tr.depth_bin * bw * 1e-12 * SPEED_OF_LIGHT / 2.0
        tr = PointSet(image_shape=tr.image_shape, **kw)
    md = dict(plan.metadata, ppp=plan.ppp, sbr=plan.sbr)
    cube = Cube(
        counts,
        irf=irf_arr,
        bin_width_ps=bin_width_ps,
        wavelengths_nm=wavelengths_nm,
        library=lib,
        metadata=md,
    )
    return Simulation(
        cube=cube,
        truth=tr,
        background_spatial=plan.spatial,
        background_temporal=plan.temporal,
        background_dense=plan.dense,
        ppp=plan.ppp,
        sbr=plan.sbr,
        metadata=MappingProxyType(md),
    )
