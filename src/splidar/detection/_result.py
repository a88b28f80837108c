"""Result dataclasses of the detection stage (Algorithm 1 and surface extraction).

These are the contract between :func:`splidar.detect` and everything downstream
(:func:`splidar.reconstruct`, metrics, plots, exports). Fields may be added; the
ones documented here keep their names, shapes and meaning.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..library import SpectralLibrary
from ..points import PointSet

__all__ = [
    "STAGES",
    "Background",
    "DataReduction",
    "Detection",
    "NullModel",
    "PixelStory",
    "StageRecord",
    "StoredHistograms",
    "SurfaceStory",
    "Surfaces",
]

#: Stages that can create (keep) a surface or remove a candidate, in the order they run;
#: ``origin`` / ``Surfaces.stage`` hold indices into this tuple.
STAGES = (
    "map",  # 4: a candidate of the 3D map that passed the evidence and presence tests
    "recentre",  # 5: moves a candidate to its 4-neighbours' depth inside its own run
    "spill_over",  # 5a: removes the spread of a neighbour's return
    "isolated",  # 5b: removes candidates that no neighbour shares and own counts do not show
    "dark_regions",  # 5c: restores candidates of dim patches, pooled
    "slopes",  # 5d: adds surfaces on steep slopes (sheared pooled tests)
    "enclosed",  # 5e: restores candidates of holes that a surface encloses
    "stray_clusters",  # 5f: removes a crowded pixel's small stray same-depth clusters
    "unlayered",  # 5g: an image with no second layer: further candidates need the presence level
    "select",  # 6: keeps at most K_s candidates per pixel
    "align_depths",  # 7: moves depths (counts surfaces moved, adds or removes none)
    "edge_bands",  # 7b: moves the bands beside depth edges to the side their counts favour
)

#: What a stage's code in ``Surfaces.stage`` (added) or ``Surfaces.moved_by`` (moved)
#: says about a surface (:meth:`Detection.explain`).
STAGE_REASONS = {
    "map": "a candidate of the 3D map whose evidence beat the null and whose own pixel "
    "shows it (presence test)",
    "recentre": "its 4-neighbours agree on a depth inside its own run of the map",
    "dark_regions": "restored: the pooled counts of a dim patch, or its 4-neighbours' "
    "agreed depth, show it",
    "slopes": "added on a steep slope by the sheared pooled test",
    "enclosed": "restored in a hole that the surface encloses on both axes",
    "align_depths": "its 4-neighbours' plane (or the depth they offer a far surface) "
    "places it there",
    "edge_bands": "a band beside a depth edge, decided together (Potts prior, own counts): "
    "the neighbouring region's plane",
}


@dataclass(frozen=True)
class SurfaceStory:
    """Why one surface exists and where its depth comes from (:meth:`Detection.explain`).

    Attributes
    ----------
    index : int
        Row of the surface in ``Detection.surfaces``.
    slot : int
    depth_bin : float
    added_by : str
        The stage whose decision keeps it (``Surfaces.stage``; ``"map"`` when unknown).
    moved_by : str or None
        The last stage that moved its depth (``Surfaces.moved_by``), None if none did.
    evidence, presence_llr, presence_z : float or None
        Its statistics (at its current depth).
    """

    index: int
    slot: int
    depth_bin: float
    added_by: str
    moved_by: str | None
    evidence: float | None
    presence_llr: float | None
    presence_z: float | None

    def __str__(self) -> str:
        stats = ", ".join(
            f"{k} {v:.3g}"
            for k, v in (
                ("evidence", self.evidence),
                ("presence_llr", self.presence_llr),
                ("presence_z", self.presence_z),
            )
            if v is not None
        )
        text = (
            f"slot {self.slot}, depth {self.depth_bin:.2f} bins: added by {self.added_by!r} "
            f"({STAGE_REASONS.get(self.added_by, self.added_by)})"
        )
        if self.moved_by is not None:
            text += f"; depth moved by {self.moved_by!r} ({STAGE_REASONS[self.moved_by]})"
        return text + (f"; {stats}" if stats else "")


@dataclass(frozen=True)
class PixelStory:
    """The surfaces of one pixel and why each exists (:meth:`Detection.explain`);
    ``str()`` gives it as text."""

    row: int
    col: int
    surfaces: tuple[SurfaceStory, ...]

    def __str__(self) -> str:
        n = len(self.surfaces)
        head = f"pixel ({self.row}, {self.col}): {n} surface{'' if n == 1 else 's'}"
        if n == 0:
            head += " (no candidate kept by the map or restored by a clean-up pass)"
        return "\n".join([head] + [f"  {s}" for s in self.surfaces])


@dataclass(frozen=True)
class Background:
    """Background estimate kept as its spatial and temporal factors (``eq:background_3``).

    ``bhat[n, l, t] = max(spatial[n, l] + temporal[l, t] - temporal[l].mean(), 0)``.
    Kept factored so that a real-size cube never needs a dense background cube.

    Attributes
    ----------
    spatial : ndarray, shape (rows, cols, L), float32
        ``b_{n,l}``: per-pixel level, counts per bin (``eq:background_2``), on the
        temporally filtered (IRF-correlated) scale of the saliency.
    temporal : ndarray, shape (L, T), float32
        ``bbar_{l,t}``: temporal shape, counts per bin (``eq:background_1``).
    """

    spatial: np.ndarray
    temporal: np.ndarray

    def dense(self, rows=slice(None), cols=slice(None)) -> np.ndarray:
        """The background ``bhat`` over a block of pixels, shape ``(r, c, L, T)`` float32."""
        sp = self.spatial[rows, cols]
        tm = self.temporal
        out = sp[..., None] + (tm - tm.mean(axis=-1, keepdims=True))
        return np.maximum(out, 0, out=out).astype(np.float32, copy=False)

    def at(self, row, col) -> np.ndarray:
        """The background at given pixels, shape ``(n, L, T)`` float32."""
        sp = self.spatial[np.asarray(row), np.asarray(col)]
        tm = self.temporal
        out = sp[..., None] + (tm - tm.mean(axis=-1, keepdims=True))
        return np.maximum(out, 0, out=out).astype(np.float32, copy=False)

    @property
    def per_bin(self) -> np.ndarray:
        """Mean background counts per bin and pixel, per wavelength, shape ``(L,)``."""
        return self.spatial.reshape(-1, self.spatial.shape[-1]).mean(axis=0, dtype=np.float64)


@dataclass(frozen=True)
class NullModel:
    """The fitted distribution of background saliency and how the threshold came from it.

    Attributes
    ----------
    shape, scale : float
        Gamma parameters ``(alpha_b, beta_b)`` of ``eq:gamma_distrib`` (scale, not rate).
    method : str
        How they were fitted (e.g. ``"quantile"``, ``"trimmed-mle"``).
    pfa : float
        Requested probability of false alarm per voxel.
    calibration : float
        Factor applied to the gamma threshold so that the empirical false-alarm rate of
        a simulated background-only null matches ``pfa`` (1.0 when not calibrated).
    details : mapping
        Anything else worth reporting (fit quantiles, iterations, empirical rates).
    """

    shape: float
    scale: float
    method: str
    pfa: float
    calibration: float = 1.0
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DataReduction:
    """How much of the cube the binary map keeps."""

    voxel_fraction: float  #: fraction of (pixel, time) voxels set in ``mask``
    photon_fraction: float  #: fraction of all photons (all L) that fall in ``mask``
    n_voxels: int  #: voxels kept
    n_photons: int  #: photons kept


class StoredHistograms:
    """The surfaces' clean histograms kept in a Zarr array on disk (``detect(store=...)``),
    read where they are indexed: a read-only stand-in for the ``(S, Q, L, W)`` float32
    array, so a large detection does not hold them in memory.

    ``h[key]`` reads the selection (integers, slices, integer arrays on the first axis)
    as a NumPy array; ``np.asarray(h)`` reads them all.

    Parameters
    ----------
    array : zarr.Array
        ``(S, Q, L, W)`` float32 array of the clean histograms: S surfaces, Q scales, L
        wavelengths, W bins of the surface's window (photon counts, background removed).

    Examples
    --------
    >>> import numpy as np, zarr
    >>> z = zarr.zeros((3, 1, 2, 5), dtype="f4")
    >>> z[1] = 1.0
    >>> h = StoredHistograms(z)
    >>> h.shape, float(h[1].sum()), str(np.asarray(h).dtype)
    ((3, 1, 2, 5), 10.0, 'float32')
    """

    __slots__ = ("array",)

    def __init__(self, array):
        #: the Zarr array (``surface_histograms`` in the detection's store)
        self.array = array

    @property
    def shape(self) -> tuple:
        return tuple(self.array.shape)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.array.dtype)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return int(self.shape[0])

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.array[key])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = np.asarray(self.array[...])
        return a if dtype is None else a.astype(dtype, copy=False)

    def __getstate__(self):
        return self.array

    def __setstate__(self, array) -> None:
        self.array = array

    def __repr__(self) -> str:
        return f"StoredHistograms(shape={self.shape}, dtype=float32, store={self.array.store})"


@dataclass(frozen=True)
class Surfaces:
    """Candidate surfaces extracted from the binary map, at most ``n_slots`` per pixel.

    S surfaces, Q scales, L wavelengths, W samples of histogram window.

    Attributes
    ----------
    row, col : ndarray (S,), int64
        Pixel of each surface.
    slot : ndarray (S,), int64
        Index of the surface within its pixel, in depth order (0 = nearest): the
        ``K_s`` slot of the paper's matrix C.
    depth_bin : ndarray (S,), float64
        Sub-bin depth from the selected scale (the depth reference of ALGORITHM-NOTES).
    start, stop : ndarray (S,), int64
        Support in time: the run of ``mask`` ``[start, stop)``.
    scale_index : ndarray (S,), int64
        Selected scale (``eq:scale_sel``), an index into ``Detection.scales``.
    offset : ndarray (S,), int64
        Time bin of ``histograms[..., 0]``.
    histograms : ndarray (S, Q, L, W), float32, or StoredHistograms
        Clean (background-free) histograms ``max(Y^q * g - bhat, 0)`` of every scale
        (``eq:background_final``), zero outside the support. With ``detect(store=...)``
        they stay in the store (:class:`StoredHistograms`: indexing reads them,
        ``np.asarray`` reads them all).
    signal : ndarray (S, Q, L), float64
        ``ybar`` of every scale: the clean histograms summed over time.
    counts : ndarray (S, L), float64
        Raw photon counts of the surface's own pixel (finest scale, no filtering) summed
        over the support, background included.
    background : ndarray (S, L), float64
        Expected background counts of the surface's own pixel summed over the support.
    saliency_mass : ndarray (S,), float64
        Sum of the saliency over the support (used to rank candidates).
    image_shape : (rows, cols)
    n_slots : int
        ``K_s``, the maximum number of surfaces per pixel.
    evidence : ndarray (S,), float64, optional
        Sum over the support of ``max(saliency / threshold - 1, 0)``: the statistic
        calibrated against the simulated null (``surface_pfa``). Added field.
    presence_llr : ndarray (S,), float64, optional
        Own-pixel Poisson log-likelihood ratio, surface (with the local scale's signal)
        vs. background only, over the support. Added field.
    presence_z : ndarray (S,), float64, optional
        Significance (Poisson z) of the local scale's (finest above 1 px) response at
        the depth. Added field.
    stage : ndarray (S,), int8, optional
        Why the surface exists: the index into :data:`splidar.detection.STAGES` of the
        stage whose decision keeps it (``"map"``: a candidate of the 3D map that passed
        the evidence and presence tests; ``"dark_regions"``, ``"slopes"``,
        ``"enclosed"``: restored or added by that clean-up pass). Added field.
    moved_by : ndarray (S,), int8, optional
        The index into :data:`splidar.detection.STAGES` of the last stage that moved the
        surface's depth (``"recentre"``: to the depth its 4-neighbours agree on inside
        its own run; ``"align_depths"``: onto its neighbours' plane or off a far depth;
        ``"edge_bands"``: a band beside a depth edge onto the neighbouring region's
        plane), ``-1`` when no stage moved it. Every other field describes the depth it holds
        now. With ``stage``, what :meth:`Detection.explain` tells. Added field.
    """

    row: np.ndarray
    col: np.ndarray
    slot: np.ndarray
    depth_bin: np.ndarray
    start: np.ndarray
    stop: np.ndarray
    scale_index: np.ndarray
    offset: np.ndarray
    histograms: np.ndarray
    signal: np.ndarray
    counts: np.ndarray
    background: np.ndarray
    saliency_mass: np.ndarray
    image_shape: tuple[int, int]
    n_slots: int
    evidence: np.ndarray | None = None
    presence_llr: np.ndarray | None = None
    presence_z: np.ndarray | None = None
    stage: np.ndarray | None = None
    moved_by: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.row.size)

    @property
    def n_surfaces(self) -> int:
        return len(self)

    @property
    def photons(self) -> np.ndarray:
        """``ybar_{s,l}``: clean signal at each surface's selected scale, shape (S, L)."""
        s = np.arange(len(self))
        return self.signal[s, self.scale_index]

    @property
    def net_counts(self) -> np.ndarray:
        """Own-pixel signal estimate ``counts - background``, shape (S, L) (may be < 0)."""
        return self.counts - self.background


@dataclass(frozen=True)
class StageRecord:
    """What one stage of :func:`splidar.detect` did to the surfaces.

    Attributes
    ----------
    stage : str
        An entry of :data:`splidar.detection.STAGES`.
    ran : bool
        False when the stage was switched off (``passes``) or had nothing to work on.
    added : int
        Surfaces (candidates) it created, added or restored.
    removed : int
        Kept candidates it rejected (``"map"``: the runs of the map dropped by the
        evidence or presence tests; ``"select"``: those beyond ``K_s`` per pixel).
    moved : int
        Surfaces (candidates) whose depth it changed (``"recentre"``, ``"align_depths"``,
        ``"edge_bands"``).
    seconds : float
    """

    stage: str
    ran: bool
    added: int
    removed: int
    moved: int = 0
    seconds: float = 0.0


@dataclass(frozen=True)
class Detection:
    """Result of :func:`splidar.detect`.

    Attributes
    ----------
    cube_shape : (rows, cols, L, T)
    irf : ndarray (L, n_irf)
        The cube's normalised IRF (carried for downstream stages).
    bin_width_ps : float or None
    wavelengths_nm : ndarray (L,) or None
    library : SpectralLibrary or None
        The library that came with the cube, if any.
    scales : tuple of int
        Spatial box sizes ``k_q`` of the multiscale cubes.
    weights : ndarray (Q,)
        ``lambda_q``, summing to 1.
    pfa : float
        Requested probability of false alarm per voxel.
    background : Background
    saliency : ndarray (rows, cols, T), float32
        ``S`` of ``eq:4.s1``.
    null : NullModel
    threshold : float, ndarray broadcastable to (rows, cols, T), or ThresholdField
        Voxels with ``saliency > threshold`` form ``mask`` (before surface checks). A
        threshold that varies with the pixel is a read-only ``ThresholdField`` (rows
        computed from the background factors on access; ``np.asarray`` gives the
        (rows, cols, T) float32 cube), with or without ``store=``.
    mask : ndarray (rows, cols, T), bool
        The 3D binary map M.
    reduction : DataReduction
    surfaces : Surfaces
    timings : mapping
        Seconds spent in each step.
    options : mapping
        The options the detection ran with (for reports and reproducibility).
    provenance : tuple of StageRecord
        Per stage, in the order they ran, the candidates it added, removed and moved;
        with ``surfaces.stage`` and ``surfaces.moved_by`` it tells why each surface
        exists and where its depth comes from (see :meth:`provenance_table`, and
        :meth:`explain` for one pixel).
    """

    cube_shape: tuple[int, int, int, int]
    irf: np.ndarray
    bin_width_ps: float | None
    wavelengths_nm: np.ndarray | None
    library: SpectralLibrary | None
    scales: tuple[int, ...]
    weights: np.ndarray
    pfa: float
    background: Background
    saliency: np.ndarray
    null: NullModel
    threshold: Any
    mask: np.ndarray
    reduction: DataReduction
    surfaces: Surfaces
    timings: Mapping[str, float] = field(default_factory=dict)
    options: Mapping[str, Any] = field(default_factory=dict)
    provenance: tuple[StageRecord, ...] = ()

    def provenance_table(self) -> str:
        """The provenance as a text table: stage, ran, added, removed, moved, surfaces
        kept, surfaces whose depth it placed.

        ``kept`` counts the final surfaces that each stage's decision keeps
        (``surfaces.stage``); ``placed`` those whose depth it moved last
        (``surfaces.moved_by``: a candidate ``recentre`` moved may be removed later, or
        moved again by ``align_depths``).
        """
        kept = np.zeros(len(STAGES), np.int64)
        placed = np.zeros(len(STAGES), np.int64)
        s = self.surfaces
        if s.stage is not None:
            kept = np.bincount(s.stage, minlength=len(STAGES))
        if s.moved_by is not None:
            m = np.asarray(s.moved_by, np.int64)
            placed = np.bincount(m[m >= 0], minlength=len(STAGES))
        head = (
            f"{'stage':14s} {'ran':>4s} {'added':>7s} {'removed':>8s} {'moved':>6s} "
            f"{'kept':>6s} {'placed':>7s}"
        )
        rows = [head]
        for r in self.provenance:
            j = STAGES.index(r.stage) if r.stage in STAGES else None
            k, p = (0, 0) if j is None else (int(kept[j]), int(placed[j]))
            rows.append(
                f"{r.stage:14s} {'yes' if r.ran else 'no':>4s} {r.added:7d} {r.removed:8d} "
                f"{r.moved:6d} {k:6d} {p:7d}"
            )
        return "\n".join(rows)

    def explain(self, row: int, col: int) -> PixelStory:
        """Why each surface of pixel ``(row, col)`` exists: the stage that added (or
        restored) it, the last stage that moved its depth and its statistics.

        Examples
        --------
        >>> story = det.explain(12, 30)  # doctest: +SKIP
        >>> print(story)  # doctest: +SKIP
        pixel (12, 30): 1 surface
          slot 0, depth 57.31 bins: added by 'map' (...); depth moved by 'align_depths' ...
        """
        from .._validation import SplidarError, check_int

        R, C = self.image_shape
        r, c = check_int(row, "row"), check_int(col, "col")
        if not (0 <= r < R and 0 <= c < C):
            raise SplidarError(
                f"pixel (row, col) must lie in the image of {R} x {C} pixels; got ({r}, {c})."
            )
        s = self.surfaces
        out = []
        for i in np.flatnonzero((s.row == r) & (s.col == c)):
            moved = -1 if s.moved_by is None else int(s.moved_by[i])

            def stat(a, i=i):
                return None if a is None else float(a[i])

            out.append(
                SurfaceStory(
                    index=int(i),
                    slot=int(s.slot[i]),
                    depth_bin=float(s.depth_bin[i]),
                    added_by=STAGES[int(s.stage[i])] if s.stage is not None else "map",
                    moved_by=STAGES[moved] if moved >= 0 else None,
                    evidence=stat(s.evidence),
                    presence_llr=stat(s.presence_llr),
                    presence_z=stat(s.presence_z),
                )
            )
        out.sort(key=lambda t: t.slot)
        return PixelStory(r, c, tuple(out))

    def __repr__(self) -> str:
        return (
            f"Detection(cube_shape={tuple(self.cube_shape)}, surfaces={len(self.surfaces)}, "
            f"scales={tuple(self.scales)}, pfa={self.pfa:g}, "
            f"voxels_kept={self.reduction.voxel_fraction:.4g}, "
            f"photons_kept={self.reduction.photon_fraction:.4g})"
        )

    @property
    def image_shape(self) -> tuple[int, int]:
        return (int(self.cube_shape[0]), int(self.cube_shape[1]))

    @property
    def n_wavelengths(self) -> int:
        return int(self.cube_shape[2])

    @property
    def n_bins(self) -> int:
        return int(self.cube_shape[3])

    @property
    def points(self) -> PointSet:
        """The detected surfaces as a :class:`~splidar.PointSet` (row, col, depth_bin, layer).

        ``intensity`` is the clean signal at the selected scale (``Surfaces.photons``).
        """
        s = self.surfaces
        depth_m = None
        if self.bin_width_ps is not None:
            from ..cube import SPEED_OF_LIGHT

            depth_m = s.depth_bin * self.bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0
        return PointSet(
            row=s.row,
            col=s.col,
            depth_bin=s.depth_bin,
            image_shape=self.image_shape,
            intensity=s.photons,
            depth_m=depth_m,
            layer=s.slot,
        )
