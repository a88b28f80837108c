"""Stage 2: multiscale statistics and saliency of a block of pixels (``eq:4.s1``).

The matched filter along t, box filters at every scale ``k_q``, the pixel's background
level (``eq:background_2``), ``bhat`` (``eq:background_3``) and the saliency
``S = sum_l |sum_q lambda_q Box_q(Y (*) g) - bhat|``, in one fused numba kernel per
wavelength (:func:`~splidar.detection._fast.saliency_wavelength`). The same function
serves the data (stage 4, block by block) and the background-only cubes of the null
(stage 3), so that both see exactly the same filters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ._background import CLIP
from ._fast import saliency_wavelength
from ._filters import Correlator, fisher_sums
from ._threads import on_parts

__all__ = [
    "COHERENCE_VOXELS",
    "COHERENCE_Z",
    "STRIP_COLS",
    "SaliencyFilters",
    "Coherence",
    "RegionScales",
    "block_saliency",
    "coherent_scales",
    "region_scales",
    "saliency_filters",
]

#: Columns the saliency kernel filters together, each strip's rows in turn (the rows a
#: strip's boxes read stay in cache): CPU per voxel and wavelength on a 40 x 200 x 1500
#: block, 9.3-10.3 ns at full width, 6.9-7.4 ns at strips of 24-64. The result does not
#: depend on it (the column sums carry over from strip to strip).
STRIP_COLS = 32
#: Voxels (pixels x L x T) the spatial-coherence measurement (:func:`coherent_scales`)
#: reads at most: the whole image below it, else evenly spaced bands of rows.
COHERENCE_VOXELS = 3_000_000
#: A box is dropped from ``scales="auto"`` only where its signal-to-noise at the own
#: pixel's depth is below the own pixel's with this Poisson-style z (3 sigma, the
#: house's presence and split z): a scene that cannot show its incoherence keeps every
#: scale.
COHERENCE_Z = 3.0


@dataclass(frozen=True)
class SaliencyFilters:
    corr: Correlator
    scales: np.ndarray  # (Q,) ascending
    weights: np.ndarray  # (Q,)
    dev: np.ndarray  # (L, T) float32: bbar - mean_t bbar
    var_factor: np.ndarray  # (L,)
    workers: int
    gsq: np.ndarray = None  # (L,) sum of g^2
    fisher: np.ndarray = None  # (L, 3): sum g'^2, sum g g'^2, peak curvature (_fisher_sums)
    quantum: np.ndarray = None  # (L,) max g / K^2: one photon in a coarse voxel


def saliency_filters(
    corr: Correlator, scales: np.ndarray, weights: np.ndarray, dev: np.ndarray, irf: np.ndarray
) -> SaliencyFilters:
    """The filter set-up shared by every block: scales, weights, ``bbar`` and IRF sums."""
    K = int(scales.max())
    return SaliencyFilters(
        corr,
        scales,
        weights,
        dev,
        (irf**2).sum(axis=1) / K**2,
        workers=1,
        gsq=(irf**2).sum(axis=1),
        fisher=fisher_sums(irf),
        quantum=irf.max(axis=1) / K**2,
    )


def block_saliency(
    y, ctx: SaliencyFilters, spatial=None, keep=None, c=None, sal_out=None, work=None, box=None,
    cols=None, with_level=True,
):  # fmt: skip
    """Correlated cube, saliency and signed response of a block of pixels.

    Parameters
    ----------
    y : (r, c, L, T) counts
    spatial : (r, c, L) float32, optional
        Background level; estimated from the block's coarsest scale when None.

    keep : slice, optional
        Rows of the block to return the saliency of (the others are halo, used by the
        box filters only); default all.
    c : (r, c, L, T) float32, optional
        ``Y (*) g`` when already computed (halo rows carried over from the previous
        block); computed from ``y`` when None.
    sal_out : (r_keep, c, T) float32, optional
        Where to write the saliency (overwritten); a new array when None.
    box : (L, Qb, r_keep, c, T) float32, optional
        Receives the box means of every scale above 1 pixel (for surface extraction).
    cols : (slice, int, ndarray or None), optional
        ``(keep_cols, strip, carry)`` of :func:`~splidar.detection._fast.saliency_wavelength`
        (``carry`` (L, r_keep, Q, T) float64); the outputs then have the kept columns
        only. Default: every column, in strips of :data:`STRIP_COLS`.
    with_level : bool
        Return ``level``; False: None (not accumulated; ``sum_l bhat`` follows from
        ``spatial`` and ``ctx.dev``, as the threshold pass computes it).

    Returns
    -------
    c : (r, c, L, T) float32   correlated counts ``Y (*) g`` (all rows)
    sal : (r, c, T) float32    ``eq:4.s1``
    d : (r, c, T) float32      ``sum_l sum_q lambda_q Box_q(c) - bhat`` (signed)
    spatial : (r, c, L) float32
    level : (r, c, T) float32  ``sum_l bhat`` (None unless ``with_level``)
    """
    if c is None:
        c = ctx.corr(y, workers=ctx.workers)
    keep = slice(None) if keep is None else keep
    r_all, cc, L, T = c.shape
    r = len(range(*keep.indices(r_all)))
    keep_cols, strip, carry = (slice(None), STRIP_COLS, None) if cols is None else cols
    cc = len(range(*keep_cols.indices(cc)))
    # the first wavelength writes sal, d and level, the others add to them
    sal = np.empty((r, cc, T), np.float32) if sal_out is None else sal_out
    if work is None:
        d = np.empty((r, cc, T), np.float32)
        level = np.empty((r, cc, T), np.float32) if with_level else None
    else:  # reused buffers of a run of blocks (no fresh pages per block)
        d = work["d"].reshape(-1)[: r * cc * T].reshape(r, cc, T)
        level = np.empty((r, cc, T), np.float32) if with_level else None
    sp_out = np.empty((r, cc, L), np.float32) if spatial is None else spatial
    for l in range(L):
        # fused numba kernel (_fast.py): box filters of every scale, sum_q lambda_q Box_q,
        # robust level (eq:background_2), bhat (eq:background_3) and |.| (eq:4.s1)
        sp_l = saliency_wavelength(
            c[:, :, l, :],
            keep,
            ctx.scales,
            ctx.weights,
            ctx.dev[l],
            sal,
            d,
            level,
            spatial=None if spatial is None else np.ascontiguousarray(spatial[:, :, l]),
            var_factor=float(ctx.var_factor[l]),
            quantum=float(ctx.quantum[l]),
            clip=CLIP,
            n_threads=ctx.workers,
            box=None if box is None else box[l],
            overwrite=l == 0,
            keep_cols=keep_cols,
            strip=strip,
            carry=None if carry is None else carry[l],
        )
        if spatial is None:
            sp_out[:, :, l] = sp_l
    return c, sal, d, sp_out, level


@dataclass(frozen=True)
class Coherence:
    """The measured spatial coherence of the returns (:func:`coherent_scales`).

    Attributes
    ----------
    scales : ndarray (Q,) int
        The candidate box sizes (ascending).
    kept : ndarray (Q,) bool
        Which of them ``scales="auto"`` keeps.
    rho : ndarray (Q,) float
        ``rho_k``: the fraction of the own pixel's signal (matched-filter response above
        ``bhat``, noise-debiased energy) that the ring of the ``k x k`` box (the box
        without the own pixel) shares, depth by depth; 1 where neighbours share the
        depth, about 0 where their depths are independent (nan for k = 1 and when not
        measured).
    z : ndarray (Q,) float
        ``z`` of ``rho_k - 1 / (k + 1)`` (the box's break-even coherence).
    energy_z : float
        ``z`` of the own pixels' signal energy: below :data:`COHERENCE_Z` the scene shows
        no signal to measure and keeps every scale.
    pixels : int
        Pixels measured.
    """

    scales: np.ndarray
    kept: np.ndarray
    rho: np.ndarray
    z: np.ndarray
    energy_z: float
    pixels: int
    rows: np.ndarray = None  # (n,) int64: the measured pixels' rows
    cols: np.ndarray = None  # (n,) int64: and columns
    energy: np.ndarray = None  # (n,) float64: their terms of E
    shared: np.ndarray = None  # (Q, n) float64: their terms of A_k


def coherent_scales(counts, ctx: SaliencyFilters) -> Coherence:
    """Which of ``ctx.scales`` pool returns that share the own pixel's depth.

    The boxes of ``eq:4.s1`` average a pixel's matched-filter response ``c`` with its
    neighbours'; that adds signal only where the neighbours' returns lie at the own
    pixel's depth. With ``x = c - bhat`` (``eq:background_3``) and ``N_k`` the mean of
    ``x`` over the ``k x k`` box without the own pixel, the own pixels' signal energy is
    ``E = sum (x^2 - sum_j g_j^2 y)`` (the Poisson variance of ``c`` removed, ``y`` the
    counts) and the part the ring shares ``A_k = sum x N_k`` (noise of distinct pixels
    is independent: zero mean), summed over pixels, wavelengths and t; ``rho_k = A_k /
    E`` (``sum_j g_j^2`` holds inside the window; near its ends, where the filter reads
    mirrored samples twice, the exact weights: :func:`_variance_weights`). A box keeps
    ``m_k = (1 + (k^2 - 1) rho_k) / k^2`` of the own return at its depth with ``1 / k``
    of the own pixel's noise: it raises the signal-to-noise ratio at the own depth when
    ``k m_k >= 1``, i.e. ``rho_k >= 1 / (k + 1)``. A box whose ``rho_k`` is below that by
    more than :data:`COHERENCE_Z` standard errors (from the per-pixel terms) is dropped,
    and with it every larger box; none is when ``E`` itself is not that significant.
    Measured on the pixels at least ``max k // 2`` from the image border (no reflected
    self), in tiles
    (:data:`COHERENCE_VOXELS`); deterministic (no rng).

    Parameters
    ----------
    counts : array_like (rows, cols, L, T)
    ctx : SaliencyFilters
        The candidate scales and their filters (stage 2's set-up).

    Returns
    -------
    Coherence
    """
    scales = np.asarray(ctx.scales, np.int64)
    Q = scales.size
    R, C, L, T = counts.shape
    h = int(scales.max()) // 2
    nan = np.full(Q, np.nan)
    keep_all = Coherence(scales, np.ones(Q, bool), nan, nan.copy(), float("nan"), 0)
    if Q == 1 or R <= 2 * h or C <= 2 * h:
        return keep_all
    var_w = _variance_weights(ctx.corr, L, T)  # (L, T): Var(c) = sum_s var_w[s] lambda_s
    e_p, a_p, where = [], [], []
    for r0, r1, c0, c1 in _coherence_tiles(R, C, L * T, h):
        where.append(np.mgrid[r0:r1, c0:c1].reshape(2, -1))
        # the tile with a halo of h pixels: its boxes and levels exact inside
        y = np.asarray(counts[r0 - h : r1 + h, max(c0 - h, 0) : min(c1 + h, C)])
        j0 = c0 - max(c0 - h, 0)
        c, _, _, sp, _ = block_saliency(y, ctx, with_level=False)
        c -= np.maximum(sp[..., None] + ctx.dev[None, None], np.float32(0.0))  # x
        x = c[h : h + r1 - r0, j0 : j0 + c1 - c0]
        yin = y[h : h + r1 - r0, j0 : j0 + c1 - c0]
        var = np.einsum("ijlt,lt->ij", yin, var_w, dtype=np.float64)  # Poisson variance
        e_p.append((_dot(x, x) - var).ravel())
        ring = np.zeros((Q, x.shape[0] * x.shape[1]))
        table = _summed_area(c, ctx.workers)
        for q, k in enumerate(scales):
            if k > 1:  # the k x k sums about the tile's pixels, less the own pixel
                box = _box_sums(table, int(k) // 2, h, h + r1 - r0, j0, j0 + c1 - c0)
                box -= x
                ring[q] = _dot(x, box).ravel() / (k * k - 1)
        a_p.append(ring)
    e_p = np.concatenate(e_p)
    a_p = np.concatenate(a_p, axis=1)
    E = float(e_p.sum())
    ez = E / max(float(np.sqrt((e_p**2).sum())), 1e-300)
    rho, z = nan.copy(), nan.copy()
    kept = np.ones(Q, bool)
    if E > 0:
        rho[scales > 1] = a_p.sum(axis=1)[scales > 1] / E
    for q in np.flatnonzero(scales > 1):
        d = a_p[q] - e_p / (scales[q] + 1)
        z[q] = float(d.sum()) / max(float(np.sqrt((d**2).sum())), 1e-300)
        kept[q] = not (ez >= COHERENCE_Z and z[q] < -COHERENCE_Z)
    # nested: a box above a dropped one goes too. Its ring lies farther out; it passes
    # only by its lower break-even on a mixed scene's average, and a set with a gap
    # blurs more than it gains (3/4 of a scene incoherent: (1, 7, 11) lost F_true on
    # both parts and had 1.2-1.5x the false surfaces of (1, 3, 7, 11) in every cell;
    # benchmarks/README.md, "Spatially incoherent scenes")
    kept = np.logical_and.accumulate(kept)
    rc = np.concatenate(where, axis=1).astype(np.int64)
    return Coherence(scales, kept, rho, z, float(ez), int(e_p.size), rc[0], rc[1], e_p, a_p)


@dataclass(frozen=True)
class RegionScales:
    """The boxes each part of the image keeps (:func:`region_scales`).

    Attributes
    ----------
    scales : ndarray (Q,) int
        The candidate box sizes (ascending).
    n_kept : ndarray (rows, cols) int8
        Per pixel, how many of the candidate boxes (ascending, nested) it keeps: the
        pixel's set is ``scales[:n_kept]``.
    z : float
        The ``|z|`` a pixel's window needs to override the image's choice (nan: no
        measurement).
    window : int
        The windows' side (pixels).
    """

    scales: np.ndarray
    n_kept: np.ndarray
    z: float
    window: int

    @property
    def sets(self) -> tuple:
        """The distinct ``n_kept``, largest first."""
        return tuple(int(n) for n in np.unique(self.n_kept)[::-1])


def region_scales(coh: Coherence, shape: tuple) -> RegionScales:
    """Which boxes each pixel keeps: the image's choice (``coh.kept``) unless the
    measured pixels about it show otherwise.

    The measured pixels' terms of ``E`` and ``A_k`` (:func:`coherent_scales`) are summed
    over every window of ``w x w`` pixels that lies inside them, ``w`` the largest box
    (11: the footprint the boxes pool over; inside the smallest tile). Where a window's
    energy is significant, its own ``z`` of ``rho_k - 1 / (k + 1)`` beyond ``+-z_n``
    overrides the image's decision on box ``k`` for its centre: below, the box is
    dropped; above, it is kept. ``z_n = sqrt(COHERENCE_Z^2 + 2 ln n)`` for ``n`` windows
    (:data:`COHERENCE_Z` against the largest of ``n`` noise values, the rule of the split
    test; the windows overlap, so this is conservative): they do not override the
    image's choice on noise. Nested as there (a box above a dropped one goes too). A
    pixel that is no window's centre (near the image's border or a tile's edge) takes
    the decision of the nearest centre when its own window would hold measured pixels,
    else (outside the tiles of a large image) the image's choice. A window straddling
    a border between coherent and incoherent parts measures their mixture: the border
    of the choice moves by up to ``w / 2`` pixels.

    Parameters
    ----------
    coh : Coherence
        With its per-pixel terms.
    shape : (rows, cols)

    Returns
    -------
    RegionScales
    """
    from scipy.ndimage import distance_transform_edt

    R, C = int(shape[0]), int(shape[1])
    scales, base = coh.scales, int(coh.kept.sum())
    w = int(scales.max())
    out = np.full((R, C), base, np.int8)
    if coh.rows is None or coh.rows.size == 0:
        return RegionScales(scales, out, float("nan"), w)

    def window(v):
        m = np.zeros((R, C))
        m[coh.rows, coh.cols] = v
        return _window_sums(m, w // 2)

    e = coh.energy
    n_pix = window(np.ones(e.size))
    centre = n_pix >= w * w - 0.5  # the window lies inside the measured pixels
    if not centre.any():
        return RegionScales(scales, out, float("nan"), w)
    zn = float(np.sqrt(COHERENCE_Z**2 + 2 * np.log(centre.sum())))
    own = centre & (window(e) >= zn * _root(window(e * e)))
    kept = np.repeat(coh.kept[None, None], R, axis=0).repeat(C, axis=1)  # (R, C, Q)
    for q in np.flatnonzero(scales > 1):
        d = coh.shared[q] - e / (scales[q] + 1)
        zq = window(d) / np.maximum(_root(window(d * d)), 1e-300)
        kept[own & (zq < -zn), q] = False
        kept[own & (zq > zn), q] = True
    n = np.logical_and.accumulate(kept, axis=2).sum(axis=2).astype(np.int8)
    near = distance_transform_edt(~centre, return_distances=False, return_indices=True)
    reach = n_pix > 0  # the pixel's own window holds measured pixels
    out[reach] = n[near[0], near[1]][reach]
    return RegionScales(scales, out, zn, w)


def _root(v: np.ndarray) -> np.ndarray:
    """``sqrt(v)``, NaN where the summed-area table left ``v`` at or below 0 (a window
    of no spread: every comparison with it is then False, no evidence either way)."""
    return np.sqrt(np.where(v > 0, v, np.nan), where=v > 0, out=np.full(v.shape, np.nan))


def _window_sums(m: np.ndarray, r: int) -> np.ndarray:
    """Sums of ``m`` (rows, cols) over the ``(2 r + 1)^2`` window about each pixel, cut at
    the border (a summed-area table: float64 prefix sums down the rows, then along them,
    and each window's four corners combined as ``((t11 - t01) - t10) + t00``; one numba
    pass, no gathered copies of the table: :func:`_window_sums_kernel`)."""
    m = np.ascontiguousarray(m, dtype=np.float64)
    out = np.empty(m.shape, np.float64)
    _window_sums_kernel(m, int(r), out)
    return out


@njit(cache=True, nogil=True)
def _window_sums_kernel(m, r, out):  # pragma: no cover - numba
    """:func:`_window_sums` into ``out``: the table's cumulative sums in NumPy's order
    (``cumsum(axis=0)`` then ``cumsum(axis=1)``), so every value is the former
    NumPy expression's to the bit."""
    R, C = m.shape
    t = np.zeros((R + 1, C + 1))
    for j in range(C):  # down the rows (cumsum axis 0)
        acc = 0.0
        for i in range(R):
            acc += m[i, j]
            t[i + 1, j + 1] = acc
    for i in range(1, R + 1):  # then along each row (cumsum axis 1)
        acc = 0.0
        for j in range(1, C + 1):
            acc += t[i, j]
            t[i, j] = acc
    for i in range(R):
        i0, i1 = max(i - r, 0), min(i + r + 1, R)
        for j in range(C):
            j0, j1 = max(j - r, 0), min(j + r + 1, C)
            out[i, j] = ((t[i1, j1] - t[i0, j1]) - t[i1, j0]) + t[i0, j0]


def _coherence_tiles(R: int, C: int, per_pixel: int, h: int) -> list:
    """Tiles ``(r0, r1, c0, c1)`` of at most 32 x 32 pixels (fewer where one such tile and
    its halo would exceed :data:`COHERENCE_VOXELS`; 16 at least), at least ``h`` from the
    image border: all of them when they fit in :data:`COHERENCE_VOXELS` (with their
    halos), else an evenly spread lattice of as many as fit (the centre tile for one)."""
    side = int(np.clip(np.sqrt(COHERENCE_VOXELS / max(per_pixel, 1)) - 2 * h, 16, 32))
    rs = list(range(h, R - h, side))
    cs = list(range(h, C - h, side))
    grid = [(a, min(a + side, R - h), b, min(b + side, C - h)) for a in rs for b in cs]
    fit = max(1, int(COHERENCE_VOXELS // ((side + 2 * h) ** 2 * max(per_pixel, 1))))
    if fit >= len(grid):
        return grid
    # an m x m lattice of tiles, evenly spread over the image (its centre for one)
    m = int(np.floor(np.sqrt(fit)))
    ri = ((np.arange(min(m, len(rs))) + 0.5) * len(rs) / min(m, len(rs))).astype(np.int64)
    ci = ((np.arange(min(m, len(cs))) + 0.5) * len(cs) / min(m, len(cs))).astype(np.int64)
    return [grid[i * len(cs) + j] for i in dict.fromkeys(ri.tolist()) for j in ci.tolist()]


def _variance_weights(corr, L: int, T: int) -> np.ndarray:
    """``w[l, s] = sum_t (d c_t / d y_s)^2`` of the matched filter (mirrored edges):
    ``Var(c_t)`` summed over t is ``sum_s w[l, s] lambda_s`` for Poisson counts. Inside
    the window ``w = sum_j g_j^2``; within two IRF lengths of either end it is computed
    from unit impulses (a mirrored sample enters the response twice)."""
    irf = np.asarray(corr.irf, np.float64)
    w = np.repeat((irf**2).sum(axis=1)[:, None], T, axis=1)
    m = min(T, 2 * irf.shape[1])
    edge = np.unique(np.concatenate([np.arange(m), np.arange(T - m, T)]))
    imp = np.zeros((edge.size, 1, L, T), np.float32)
    imp[np.arange(edge.size), 0, :, edge] = 1.0
    resp = corr(imp).astype(np.float64)[:, 0]  # (n_edge, L, T)
    w[:, edge] = (resp**2).sum(axis=2).T
    return w


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sum_{l,t} a b`` per pixel (float64) of two (rows, cols, L, T) float32 arrays."""
    return np.einsum("ijlt,ijlt->ij", a, b, dtype=np.float64)


def _summed_area(x: np.ndarray, workers: int = 1) -> np.ndarray:
    """Summed-area table of ``x`` (rows, cols, L, T) over rows and columns, float64, with
    a leading row and column of zeros: ``(rows + 1, cols + 1, L, T)``.

    The running sums of ``np.cumsum`` over rows (float64), then over columns, each
    value's additions in the same order (bit for bit), in one numba pass over ``x``
    (:func:`_summed_area_kernel`), its ``L x T`` series split between ``workers``
    threads (each series is its own)."""
    R, C = x.shape[:2]
    out = np.zeros((R + 1, C + 1) + x.shape[2:], np.float64)
    if x.size == 0:
        return out
    xf = np.ascontiguousarray(x, np.float32).reshape(R, C, -1)
    of = out.reshape(R + 1, C + 1, -1)
    on_parts(lambda p0, p1: _summed_area_kernel(xf, of, p0, p1), xf.shape[2], workers)
    return out


@njit(cache=True, nogil=True)
def _summed_area_kernel(x, out, p0, p1):
    """``out[1:, 1:, p0:p1]``: ``cumsum(cumsum(x, axis=0, dtype=float64), axis=1)`` of
    ``x`` (R, C, P) float32, sequential sums as NumPy's (the first element taken as it
    is, then each added to the running sum)."""
    R, C, _ = x.shape
    col = np.empty((C, p1 - p0), np.float64)  # the running sums over rows
    for i in range(R):
        for j in range(C):
            if i == 0:
                for p in range(p0, p1):
                    col[j, p - p0] = np.float64(x[0, j, p])
            else:
                for p in range(p0, p1):
                    col[j, p - p0] += np.float64(x[i, j, p])
        for p in range(p0, p1):
            out[i + 1, 1, p] = col[0, p - p0]
        for j in range(1, C):
            for p in range(p0, p1):
                out[i + 1, j + 1, p] = out[i + 1, j, p] + col[j, p - p0]


def _box_sums(table: np.ndarray, r: int, i0: int, i1: int, j0: int, j1: int) -> np.ndarray:
    """``(2 r + 1)^2`` box sums about pixels ``[i0, i1) x [j0, j1)`` (their boxes inside
    the array) from its summed-area table, float32 (rows, cols, L, T)."""
    a = table[i0 + r + 1 : i1 + r + 1, j0 + r + 1 : j1 + r + 1]
    b = table[i0 - r : i1 - r, j0 + r + 1 : j1 + r + 1]
    c = table[i0 + r + 1 : i1 + r + 1, j0 - r : j1 - r]
    d = table[i0 - r : i1 - r, j0 - r : j1 - r]
    return (a - b - c + d).astype(np.float32)
