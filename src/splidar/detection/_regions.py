"""``scales="auto"`` region by region: one detection per set of boxes, merged per pixel.

Where the regions of an image keep different boxes (:func:`~._2_saliency.region_scales`:
foliage beside buildings), :func:`~splidar.detect` runs once with every set a region
keeps, each with its own null and threshold (``_3_null``: the null is calibrated for one
set of filters), and every pixel takes the result of its region's set:
:func:`merge_by_region`. The sets are nested (``scales[:n]``), so a surface of a smaller
set keeps its ``scale_index`` in the full set's ``scales``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from types import MappingProxyType

import numpy as np

from ._result import Background, DataReduction, Detection, StoredHistograms, Surfaces
from ._threshold import ThresholdField

__all__ = ["RegionThreshold", "merge_by_region"]


class RegionThreshold(ThresholdField):
    """Read-only ``(rows, cols, T)`` float32 threshold of a detection merged by region:
    each pixel's from the detection of its region's set of boxes (each set has its own
    null). Reads as :class:`ThresholdField` does (indexing, ``np.asarray``, ``pixels``).

    Parameters
    ----------
    parts : sequence
        The thresholds of the detections (float, ndarray broadcastable to (rows, cols,
        T), or ThresholdField).
    label : ndarray (rows, cols) int
        Which part each pixel reads (an index into ``parts``).
    n_bins : int
        T.
    """

    def __init__(self, parts, label, n_bins: int):
        self._parts = tuple(parts)
        self._label = np.asarray(label, np.int64)
        self.shape = self._label.shape + (int(n_bins),)
        self.dtype = np.dtype(np.float32)
        self.ndim = 3

    def _part_rows(self, p, r0: int, r1: int) -> np.ndarray:
        if isinstance(p, ThresholdField) or (np.ndim(p) == 3 and np.shape(p)[0] == self.shape[0]):
            return np.asarray(p[r0:r1], np.float32)
        return np.broadcast_to(np.asarray(p, np.float32), self.shape)[r0:r1]

    def _rows(self, r0: int, r1: int) -> np.ndarray:
        r1 = max(r1, r0)
        out = np.empty((r1 - r0,) + self.shape[1:], np.float32)
        lab = self._label[r0:r1]
        for i, p in enumerate(self._parts):
            m = lab == i
            if m.any():
                out[m] = self._part_rows(p, r0, r1)[m]
        return out

    def pixels(self, rows, cols) -> np.ndarray:
        rows = np.asarray(rows, np.int64)
        cols = np.asarray(cols, np.int64)
        out = np.empty((rows.size, self.shape[2]), np.float32)
        lab = self._label[rows, cols]
        for i, p in enumerate(self._parts):
            m = lab == i
            if not m.any():
                continue
            if isinstance(p, ThresholdField):
                out[m] = p.pixels(rows[m], cols[m])
            else:
                full = np.broadcast_to(np.asarray(p, np.float32), self.shape)
                out[m] = full[rows[m], cols[m]]
        return out

    def __repr__(self) -> str:
        return f"RegionThreshold(shape={self.shape}, parts={len(self._parts)})"


def merge_by_region(runs: dict, n_kept: np.ndarray, counts, record: dict) -> Detection:
    """One detection from the detections ``runs`` (``{n: Detection}``, run with the
    boxes ``scales[:n]``; the largest ``n`` first): every pixel takes the result of
    ``runs[n_kept[pixel]]``.

    Merged per pixel: the surfaces (their histograms and signals padded with zeros at
    the boxes their set lacks; written to the store when they were stored), the
    saliency, the mask and the background level (``Background.spatial``; in place, in
    the full set's arrays or store), the threshold (:class:`RegionThreshold`) and the
    data reduction (recounted over the merged mask). The full set's: ``scales``,
    ``weights``, the background's temporal shape, the null model and the provenance
    (whole-image counts of that run; each run's in ``options["scale_regions"]``).
    Timings are summed over the runs.

    Parameters
    ----------
    runs : dict of int -> Detection
    n_kept : ndarray (rows, cols) int
        The pixel's set (``RegionScales.n_kept``).
    counts : array_like (rows, cols, L, T)
        The counts the detections read (stuck pixels zeroed), for the photons in the mask.
    record : dict
        What ``options["scale_regions"]`` tells besides the runs' figures.

    Returns
    -------
    Detection
    """
    sets = sorted(runs, reverse=True)
    top = runs[sets[0]]
    label = np.searchsorted(-np.asarray(sets), -np.asarray(n_kept, np.int64))  # index in sets
    dets = [runs[n] for n in sets]
    R, C, L, T = top.cube_shape
    saliency = _merge_pixels([d.saliency for d in dets], label)
    mask = _merge_pixels([d.mask for d in dets], label)
    spatial = _merge_pixels([d.background.spatial for d in dets], label)
    surfaces = _merge_surfaces([d.surfaces for d in dets], label, len(top.scales), top)
    timings = {}
    for d in dets:
        for k, v in d.timings.items():
            timings[k] = timings.get(k, 0.0) + float(v)
    n_vox, kept, total = _mask_photons(mask, counts)
    reduction = DataReduction(
        voxel_fraction=n_vox / (R * C * T),
        photon_fraction=kept / total if total else 0.0,
        n_voxels=n_vox,
        n_photons=kept,
    )
    pixels = np.bincount(label.ravel(), minlength=len(sets))
    rec = dict(record)
    rec.update(
        scales=tuple(tuple(int(k) for k in d.scales) for d in dets),
        pixels=tuple(int(p) for p in pixels),
        provenance=tuple(
            tuple((r.stage, r.added, r.removed, r.moved) for r in d.provenance) for d in dets
        ),
    )
    options = dict(top.options)
    options["scale_regions"] = MappingProxyType(rec)
    return dataclasses.replace(
        top,
        background=Background(spatial=spatial, temporal=top.background.temporal),
        saliency=saliency,
        threshold=RegionThreshold([d.threshold for d in dets], label, T),
        mask=mask,
        reduction=reduction,
        surfaces=surfaces,
        timings=MappingProxyType(timings),
        options=MappingProxyType(options),
    )


def _merge_pixels(arrays: list, label: np.ndarray):
    """``arrays[0]`` with each pixel ``label == i`` replaced by ``arrays[i]``'s, in place
    (a NumPy array, or a Zarr array written row block by row block)."""
    dst = arrays[0]
    if isinstance(dst, np.ndarray):
        for i, a in enumerate(arrays[1:], 1):
            m = label == i
            dst[m] = np.asarray(a)[m] if isinstance(a, np.ndarray) else _rows(a, m)
        return dst
    step = int(dst.chunks[0])
    for r0 in range(0, dst.shape[0], step):
        lab = label[r0 : r0 + step]
        if not (lab > 0).any():
            continue
        blk = np.asarray(dst[r0 : r0 + step])
        for i, a in enumerate(arrays[1:], 1):
            m = lab == i
            if m.any():
                blk[m] = np.asarray(a[r0 : r0 + step])[m]
        dst[r0 : r0 + step] = blk
    return dst


def _rows(a, m: np.ndarray) -> np.ndarray:
    """``a[m]`` of a row-indexable array, read in the rows that hold ``m``."""
    rows = np.flatnonzero(m.any(axis=1))
    return np.asarray(a[rows[0] : rows[-1] + 1])[m[rows[0] : rows[-1] + 1]]


def _merge_surfaces(parts: list, label: np.ndarray, Q: int, top: Detection) -> Surfaces:
    """The surfaces of every part at the pixels of its label, in raster and slot order;
    ``histograms`` (S, Q, L, W) and ``signal`` (S, Q, L) padded with zeros at the boxes a
    part's (nested) set lacks."""
    take = [np.flatnonzero(label[s.row, s.col] == i) for i, s in enumerate(parts)]
    src = np.concatenate([np.full(t.size, i) for i, t in enumerate(take)]).astype(np.int64)
    idx = np.concatenate(take).astype(np.int64)
    row = np.concatenate([s.row[t] for s, t in zip(parts, take, strict=True)])
    col = np.concatenate([s.col[t] for s, t in zip(parts, take, strict=True)])
    slot = np.concatenate([s.slot[t] for s, t in zip(parts, take, strict=True)])
    order = np.lexsort((slot, col, row))
    src, idx = src[order], idx[order]
    out = {}
    for f in dataclasses.fields(Surfaces):
        vals = [getattr(s, f.name) for s in parts]
        if f.name in ("image_shape", "n_slots") or vals[0] is None or f.name == "histograms":
            continue
        pieces = [_pad(np.asarray(v)[t], Q) if f.name == "signal" else np.asarray(v)[t]
                  for v, t in zip(vals, take, strict=True)]  # fmt: skip
        out[f.name] = np.concatenate(pieces)[order]
    out["histograms"] = _merge_histograms([s.histograms for s in parts], src, idx, Q)
    return Surfaces(**out, image_shape=parts[0].image_shape, n_slots=parts[0].n_slots)


def _pad(a: np.ndarray, Q: int) -> np.ndarray:
    """``a`` (S, q, ...) with zeros appended on axis 1 up to ``Q``."""
    if a.shape[1] == Q:
        return a
    out = np.zeros((a.shape[0], Q) + a.shape[2:], a.dtype)
    out[:, : a.shape[1]] = a
    return out


def _merge_histograms(hists: list, src: np.ndarray, idx: np.ndarray, Q: int):
    """Row ``j`` = ``hists[src[j]][idx[j]]`` padded to ``Q`` boxes; in memory, or a new
    Zarr array that replaces the full set's ``surface_histograms`` in its store."""
    first = hists[0]
    shape = (src.size, Q) + tuple(first.shape[2:])
    if not isinstance(first, StoredHistograms):
        out = np.zeros(shape, np.float32)
        for i, h in enumerate(hists):
            m = src == i
            out[m, : h.shape[1]] = np.asarray(h)[idx[m]]
        return out
    import zarr

    from ._table import HIST_CHUNK, remove_tree, store_histograms

    path = Path(os.fspath(first.array.store.root)) / first.array.path
    group = zarr.open_group(str(path.parent), mode="r+")
    z = store_histograms(group, "merged_histograms", shape, compressed=False)  # as detect's
    for j0 in range(0, src.size, HIST_CHUNK):
        s, ix = src[j0 : j0 + HIST_CHUNK], idx[j0 : j0 + HIST_CHUNK]
        blk = np.zeros((s.size,) + shape[1:], np.float32)
        for i, h in enumerate(hists):
            m = s == i
            if m.any():
                blk[m, : h.shape[1]] = h[ix[m]]
        z[j0 : j0 + s.size] = blk
    remove_tree(path)
    os.rename(path.parent / "merged_histograms", path)
    return StoredHistograms(zarr.open_array(str(path), mode="r"))


def _mask_photons(mask, counts) -> tuple:
    """Voxels set in ``mask`` (rows, cols, T), the photons (all L) in them and all the
    photons of ``counts`` (rows, cols, L, T), read a block of rows at a time."""
    R = int(counts.shape[0])
    per_row = int(np.prod(counts.shape[1:], dtype=np.int64)) or 1
    step = max(1, (1 << 24) // per_row)
    n_vox = kept = total = 0
    for r0 in range(0, R, step):
        y = np.asarray(counts[r0 : r0 + step]).sum(axis=2, dtype=np.int64)  # (r, C, T)
        m = np.asarray(mask[r0 : r0 + step], bool)
        n_vox += int(m.sum())
        kept += int(y[m].sum())
        total += int(y.sum())
    return n_vox, kept, total
