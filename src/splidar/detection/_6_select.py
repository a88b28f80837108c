"""Stage 6: the surfaces: at most ``K_s`` candidates per pixel, in depth order.

The kept candidates of largest saliency mass are selected per pixel (the ``K_s`` slots
of the paper's matrix C), their clean histograms gathered once from the blocks' arrays,
and the table becomes :class:`~splidar.detection.Surfaces`.
"""

from __future__ import annotations

import numpy as np

from ._kernels import select_sorted
from ._result import Surfaces
from ._table import CandidateTable, _position_in_pixel, _raster_ordered

__all__ = ["select_surfaces"]


def _select(surf: dict, keep: np.ndarray, k_max: int):
    """Keep at most ``k_max`` candidates per pixel (largest saliency mass), depth order."""
    row, col = surf["row"], surf["col"]
    order = None
    if not _raster_ordered(row, col) and keep.any():
        # e.g. the slope recovery's surfaces appended at the end: one stable sort by
        # pixel (a pixel's candidates keep their order), then the linear kernel
        order = np.lexsort((col, row))
    if order is not None or _raster_ordered(row, col):
        n = row.size
        take = (lambda a: a[order]) if order is not None else (lambda a: a)
        idx, slot = np.empty(n, np.int64), np.empty(n, np.int64)
        m = select_sorted(
            np.ascontiguousarray(take(row), np.int64),
            np.ascontiguousarray(take(col), np.int64),
            np.ascontiguousarray(take(surf["saliency_mass"]), np.float64),
            np.ascontiguousarray(take(surf["depth_bin"]), np.float64),
            np.ascontiguousarray(take(keep), np.bool_),
            int(k_max),
            idx,
            slot,
        )
        return (order[idx[:m]] if order is not None else idx[:m]), slot[:m]
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return idx, np.zeros(0, np.int64)
    row, col = surf["row"], surf["col"]
    idx = idx[np.lexsort((-surf["saliency_mass"][idx], col[idx], row[idx]))]
    idx = idx[_position_in_pixel(row[idx], col[idx]) < k_max]
    idx = idx[np.lexsort((surf["depth_bin"][idx], col[idx], row[idx]))]
    return idx, _position_in_pixel(row[idx], col[idx])


def _gather(table: CandidateTable, idx: np.ndarray, histograms: tuple) -> np.ndarray:
    """The selected candidates' histograms from the blocks' (and passes') arrays."""
    hist = np.empty((idx.size,) + histograms[0].shape[1:], np.float32)
    hb, hr = table.hist_block[idx], table.hist_row[idx]
    for b, h in enumerate(histograms):
        sel = np.flatnonzero(hb == b)
        if sel.size:
            hist[sel] = h[hr[sel]]
    sel = np.flatnonzero(hb == -1)
    if sel.size:
        hist[sel] = table.extra_histograms[hr[sel]]
    return hist


def select_surfaces(
    table: CandidateTable,
    histograms: tuple,
    *,
    max_surfaces: int,
    n_scales: int,
    n_wavelengths: int,
    width: int,
) -> Surfaces:
    """Keep at most ``max_surfaces`` kept candidates per pixel as :class:`Surfaces`.

    Parameters
    ----------
    table : CandidateTable
    histograms : tuple of ndarray
        The map pass's per-block histogram arrays (``CandidateMap.histograms``).
    max_surfaces : int
        ``K_s``.
    n_scales, n_wavelengths, width : int
        Q, L and W (the shape of an empty histogram array).
    """
    idx, slot = _select(table.columns, table.keep, max_surfaces)
    surf = {k: v[idx] for k, v in table.columns.items()}
    Q, L = n_scales, n_wavelengths
    if idx.size == 0:
        hist = np.zeros((0, Q, L, width), np.float32)
    else:
        hist = _gather(table, idx, histograms)
    R, C = table.image_shape
    return Surfaces(
        row=surf["row"].astype(np.int64),
        col=surf["col"].astype(np.int64),
        slot=slot.astype(np.int64),
        depth_bin=surf["depth_bin"].astype(np.float64),
        start=surf["start"].astype(np.int64),
        stop=surf["stop"].astype(np.int64),
        scale_index=surf["scale_index"].astype(np.int64),
        offset=surf["offset"].astype(np.int64),
        histograms=hist,
        signal=surf["signal"].reshape(-1, Q, L),
        counts=surf["counts"].reshape(-1, L),
        background=surf["background"].reshape(-1, L),
        saliency_mass=surf["saliency_mass"].astype(np.float64),
        evidence=surf["evidence"].astype(np.float64),
        presence_llr=surf["presence_llr"].astype(np.float64),
        presence_z=surf["presence_z"].astype(np.float64),
        image_shape=(R, C),
        n_slots=max_surfaces,
        stage=table.origin[idx].astype(np.int8),
    )
