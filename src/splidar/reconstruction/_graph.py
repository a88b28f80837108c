"""The surface graph of the gamma-MRF and Potts priors (``fig:HMB`` (b)), as CSR arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._kernels import bridge_csr, graph_csr, pixel_ranks

__all__ = ["SurfaceGraph", "build_graph", "irf_fwhm", "surface_keys"]


@dataclass(frozen=True)
class SurfaceGraph:
    """Symmetric links between surfaces of 4-neighbour pixels, without self links.

    Attributes
    ----------
    indptr : ndarray (S + 1,), int64
    indices : ndarray (E,), int64
        Neighbours of surface s are ``indices[indptr[s]:indptr[s + 1]]``.
    parity : ndarray (S,), int64
        Colour of the surface's pixel, such that linked surfaces differ in colour:
        ``(row + col) % 2`` (red-black), or ``(row + col) % 4`` for a graph with links
        across one pixel (``build_graph(bridge=True)``).
    links : str
        ``"depth"`` or ``"all"``.
    gate : float
        Depth gate in bins (``inf`` for ``"all"``).
    key : ndarray (S,), uint64
        What each surface is, independent of its place in the arrays
        (``surface_keys``): the label sampler keys its random numbers by it.
        ``None`` (a graph built by hand): the surfaces' indices.
    """

    indptr: np.ndarray
    indices: np.ndarray
    parity: np.ndarray
    links: str
    gate: float
    key: np.ndarray | None = None

    @property
    def n_edges(self) -> int:
        """Number of undirected links."""
        return int(self.indices.size // 2)

    @property
    def degree(self) -> np.ndarray:
        return np.diff(self.indptr)


_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser, elementwise on uint64 (wraps modulo 2**64)."""
    x = x + _GOLD
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


def surface_keys(row: np.ndarray, col: np.ndarray, depth: np.ndarray, slot=None) -> np.ndarray:
    """A 64-bit key of what each surface is: its pixel and its rank by depth there.

    ``key = mix(mix(mix(row) ^ col) ^ rank)`` (splitmix64's finaliser ``mix``), ``rank``
    = 0 for the nearest surface of the pixel, 1 for the next... (ties by ``slot``, then
    by index). It does not depend on where the surface sits in the arrays, on the other
    pixels' surfaces or on the image's size: adding or removing a surface changes the
    keys of the deeper surfaces of its own pixel only. The label sampler draws every
    random number from such keys (:func:`splidar.reconstruction.potts_marginals`), so a
    change of the detection at one place changes the random numbers there only.

    Parameters
    ----------
    row, col : ndarray (S,), int
        Pixel of each surface (the image's rows, not a strip's).
    depth : ndarray (S,)
        Depth, any unit (only its order within a pixel is used).
    slot : ndarray (S,), optional
        Tie-break between surfaces of one pixel at the same depth.

    Returns
    -------
    ndarray (S,), uint64

    Examples
    --------
    >>> k = surface_keys(np.array([0, 0, 3]), np.array([1, 1, 2]), np.array([9.0, 4.0, 5.0]))
    >>> k2 = surface_keys(np.array([0, 3]), np.array([1, 2]), np.array([4.0, 5.0]))
    >>> bool(k[1] == k2[0] and k[2] == k2[1] and k[0] != k[1])
    True
    """
    row = np.asarray(row, np.int64)
    col = np.asarray(col, np.int64)
    S = row.size
    if S == 0:
        return np.zeros(0, np.uint64)
    tie = np.zeros(S, np.int64) if slot is None else np.asarray(slot, np.int64)
    depth = np.asarray(depth, np.float64)
    # surfaces listed pixel by pixel (a detection's order): ranks in one pass, else a sort
    rank, grouped = pixel_ranks(
        np.ascontiguousarray(row), np.ascontiguousarray(col), np.ascontiguousarray(depth),
        np.ascontiguousarray(tie),
    )  # fmt: skip
    if not grouped:
        order = np.lexsort((tie, depth, col, row))
        r, c = row[order], col[order]
        first = np.ones(S, bool)
        first[1:] = (r[1:] != r[:-1]) | (c[1:] != c[:-1])
        start = np.maximum.accumulate(np.where(first, np.arange(S), 0))
        rank = np.empty(S, np.int64)
        rank[order] = np.arange(S) - start
    x = _mix64(row.astype(np.uint64))
    x = _mix64(x ^ col.astype(np.uint64))
    return _mix64(x ^ rank.astype(np.uint64))


def irf_fwhm(irf: np.ndarray) -> np.ndarray:
    """Full width at half maximum of each IRF row, in bins (linear interpolation), shape (L,).

    Examples
    --------
    >>> from splidar.irf import gaussian_irf
    >>> round(float(irf_fwhm(gaussian_irf(4.0))[0]), 1)
    4.0
    """
    g = np.atleast_2d(np.asarray(irf, dtype=np.float64))
    out = np.empty(g.shape[0])
    for i, row in enumerate(g):
        p = int(np.argmax(row))
        half = row[p] / 2.0
        # walk left and right to the half-maximum crossings
        left = p
        while left > 0 and row[left - 1] > half:
            left -= 1
        right = p
        while right < row.size - 1 and row[right + 1] > half:
            right += 1
        if left > 0:
            a, c = row[left - 1], row[left]
            xl = left - 1 + (half - a) / (c - a) if c != a else left - 0.5
        else:
            xl = -0.5
        if right < row.size - 1:
            a, c = row[right], row[right + 1]
            xr = right + (a - half) / (a - c) if c != a else right + 0.5
        else:
            xr = row.size - 0.5
        out[i] = max(xr - xl, 1.0)
    return out


def build_graph(
    row: np.ndarray,
    col: np.ndarray,
    slot: np.ndarray,
    depth: np.ndarray,
    image_shape: tuple[int, int],
    n_slots: int,
    *,
    links: str = "depth",
    gate: float = np.inf,
    bridge: bool = False,
    key: np.ndarray | None = None,
) -> SurfaceGraph:
    """Link every surface to the surfaces of its 4 neighbour pixels (numba, one pass).

    ``links="all"`` keeps every pair (the paper's 4 K_s neighbours); ``links="depth"``
    keeps a pair only when ``|d_s - d_s'| <= gate`` bins.

    ``bridge=True`` (the label field's graph, issue 14) also links two surfaces two pixels
    apart along a row or a column, within the gate, when each has at most one link and no
    surface of the pixel between them is linked to both: the two ends of a strand whose
    detection is missed in one pixel, which then stays one chain instead of two pieces,
    each pooled on its own. Inside a region (surfaces of 2-4 links, a hole is walked
    round) and where the middle pixel holds a surface at their depth nothing is added
    (bridging every gap measured -0.004 at PPP 1: docs/classification.md). The colours
    (``parity``) are then ``(row + col) % 4``, so that no two linked surfaces share one.

    ``key``: the surfaces' keys when already computed (``surface_keys`` of these
    surfaces, or of the image's rows for a strip's), else computed here.
    """
    S = int(row.size)
    rows, cols = image_shape
    parity = ((row + col) % 2).astype(np.int64)
    key = surface_keys(row, col, depth, slot) if key is None else key
    if S == 0:
        graph = SurfaceGraph(np.zeros(1, np.int64), np.zeros(0, np.int64), parity, links, gate, key)
        return with_bridges(graph, row, col, slot, depth, image_shape, n_slots) if bridge else graph
    n_slots = max(int(n_slots), int(slot.max()) + 1)
    g = np.inf if links == "all" else float(gate)
    indptr, indices = graph_csr(
        np.ascontiguousarray(row, np.int64), np.ascontiguousarray(col, np.int64),
        np.ascontiguousarray(slot, np.int64), np.ascontiguousarray(depth, np.float64),
        int(rows), int(cols), n_slots, g,
    )  # fmt: skip
    graph = SurfaceGraph(indptr, indices, parity, links, float(gate), key)
    return with_bridges(graph, row, col, slot, depth, image_shape, n_slots) if bridge else graph


def with_bridges(graph, row, col, slot, depth, image_shape, n_slots) -> SurfaceGraph:
    """``graph`` (:func:`build_graph` of these surfaces, without bridges) with the links
    of ``build_graph(bridge=True)`` added and its colours ``(row + col) % 4``: the label
    field's graph from the sweeps' one, without building the links or the keys again."""
    parity = ((row + col) % 4).astype(np.int64)
    S = int(row.size)
    if S == 0:
        return SurfaceGraph(graph.indptr, graph.indices, parity, graph.links, graph.gate, graph.key)
    n_slots = max(int(n_slots), int(slot.max()) + 1)
    g = np.inf if graph.links == "all" else float(graph.gate)
    indptr, indices = bridge_csr(
        np.ascontiguousarray(row, np.int64), np.ascontiguousarray(col, np.int64),
        np.ascontiguousarray(slot, np.int64), np.ascontiguousarray(depth, np.float64),
        int(image_shape[0]), int(image_shape[1]), n_slots, g, graph.indptr, graph.indices,
    )  # fmt: skip
    return SurfaceGraph(indptr, indices, parity, graph.links, graph.gate, graph.key)
