"""Stage 7d (model): where the scene shows a second layer. Stage 5g
(:mod:`~splidar.detection._5g_unlayered`) uses its whole-image decision; the line rule
it gates here (:func:`spread_lines`) stays **off** (:data:`LAYER_GATE`).

Issue #15's "spread" false surfaces (a neighbour's depth pooled into the pixels beside a
depth edge by the multiscale boxes) and the dim second layers of partly transmissive
scenes (the object behind a sheet at the sheet's edge row, the object behind a net's
strands) look alike in every pixel's own counts and in every line of pixels through
them (benchmarks/README.md, "spread28, session 20" and "spr36, session 24"). What
separates them is whether the scene *has* layers there. This module measures that from
the detection's geometry alone:

* **Layer evidence** (per pixel). A pixel holding two or more surfaces shows a second
  layer when one of its depths ``x`` is held, among the pixels within the largest box's
  half-width ``h`` (the reach of a spread: the boxes pool nothing from farther), by
  more pixels that hold two or more surfaces than by pixels that hold ``x`` alone:
  ``n_2(x) > n_1(x)``. A spread strip's further depth is its source region's, held
  alone by the region's pixels within the reach (a strip of width ``w`` beside a
  region: ``n_2 ~ w (2h + 1)`` against ``n_1 ~ (h + 1 - w)(2h + 1)``), and its own
  depth is its own region's; a second layer's depths continue as pairs (the sheet's
  pixels hold sheet and object, the net's strands strand and object).
  A background alarm behind a pixel's own surface is evidence too (no pixel holds its
  depth alone): the null's false alarms, counted next.
* **Layered regions.** The evidence pixels counted in a window of radius ``radius``
  pixels (None: the whole image) are tested against what the null explains: a pixel
  shows a background alarm at the rate ``surface_pfa`` (stage 3 calibrates the
  threshold on the evidence to that many false surfaces per background-only pixel),
  so the count is Poisson with mean ``surface_pfa x pixels`` under "no layer". The
  window is *layered* when ``P(N >= n) < surface_pfa``: the level comes from the null,
  not from a tuned constant.

**The rule it gates** (:func:`spread_lines`, spr36's ``line_open``): outside the layered
windows, a candidate (a surface of a pixel holding two or more) that stage 7c would test
(its depth continues on fewer than 2 of the 4 axes through its pixel) is removed when no
line of ``2 h + 1`` pixels through it along the 4 axes holds its depth in the own counts:
each pixel of a line at the surface nearest the line's running course within the gate
(its own, else its 8-neighbours'), the pixels holding one surface only at the course left
out (a spread's source region), one intensity shared by the line and profiled out
(stage 7b's ``group_llr``), against 7c's prior level ``log((1 - q) / q)``; a pixel never
loses every surface.

Why off (benchmarks/README.md, "lay38, session 26"; ``benchmarks/bench_spread_sources.py
--layer``): gating spr36's line rules (``line_open``, ``line_all``) by the layered
regions keeps every true surface of the sheet and net families (0 of 18 cubes lose one,
whole-image window) and takes issue #15's single-surface cells from 90.3 / 116.7 false
surfaces to about 48.0 / 62.7 (1 true surface lost in 6 cubes), but on
``bench_detection.py``'s 64 cells the single-surface scene itself loses 47 true surfaces
in 11 cells, 10 of them at PPP 1-4 (no layer to gate on: the line test, not the gate),
and the two-layer scene at PPP 1 15 in 2 cells (too few second surfaces detected to show
the layer): "nothing worse on any benchmark" does not hold. Kept with its tests so that a
rule for a pixel's further surfaces can consult it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage, stats

from ._7b_edge_bands import _windows, group_llr
from ._7c_spread_groups import AXES, GATE_FWHM, REACH, continued_axes

__all__ = [
    "LAYER_GATE",
    "LayerEvidence",
    "SpreadLines",
    "layer_evidence",
    "spread_lines",
    "window_counts",
]

#: Off: measured, not adopted (see the module). ``detect`` does not run the stage.
LAYER_GATE = False


@dataclass(frozen=True)
class LayerEvidence:
    """Where the detection shows a second layer.

    Attributes
    ----------
    evidence : ndarray (rows, cols) bool
        Pixels whose depths continue as pairs (see the module).
    count : ndarray (rows, cols) int64
        Evidence pixels in each pixel's window.
    expected : ndarray (rows, cols) float64
        What the null explains there: ``surface_pfa`` x the window's pixels.
    layered : ndarray (rows, cols) bool
        ``P(Poisson(expected) >= count) < surface_pfa``.
    """

    evidence: np.ndarray
    count: np.ndarray
    expected: np.ndarray
    layered: np.ndarray


@njit(cache=True, nogil=True)
def _fill_slots(pix, depth, out):
    """``out[p, k]``: the depth of pixel ``p``'s ``k``-th surface in input order; returns
    the number each pixel holds (one pass, no sort)."""
    n = np.zeros(out.shape[0], np.int64)
    for i in range(pix.size):
        p = pix[i]
        out[p, n[p]] = depth[i]
        n[p] += 1
    return n


def depth_slots(row, col, depth, image_shape) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols, K) float64 depths of each pixel's surfaces (NaN padded; a pixel's in
    their input order) and (rows, cols) int64 the number each pixel holds."""
    R, C = image_shape
    pix = np.asarray(row, np.int64) * C + np.asarray(col, np.int64)
    k = int(np.bincount(pix, minlength=R * C).max(initial=0))
    out = np.full((R * C, max(k, 1)), np.nan)
    n = _fill_slots(pix, np.asarray(depth, np.float64), out)
    return out.reshape(R, C, -1), n.reshape(R, C)


@njit(cache=True, nogil=True)
def _held(D, n, r, c, x, gate, h):
    """Pixels within ``h`` of ``(r, c)`` holding a depth within ``gate`` of ``x``:
    (alone, as one of two or more)."""
    R, C, K = D.shape
    n1 = n2 = 0
    for rr in range(max(r - h, 0), min(r + h + 1, R)):
        for cc in range(max(c - h, 0), min(c + h + 1, C)):
            m = n[rr, cc]
            for k in range(min(m, K)):
                if abs(D[rr, cc, k] - x) <= gate:
                    if m == 1:
                        n1 += 1
                    else:
                        n2 += 1
                    break
    return n1, n2


@njit(cache=True, nogil=True)
def _evidence(D, n, gate, h, ev, stop):
    """Mark in ``ev`` (rows, cols) the pixels that show a second layer, in raster order,
    stopping once ``stop`` are marked; returns how many are."""
    R, C, K = D.shape
    count = 0
    for r in range(R):
        for c in range(C):
            for k in range(min(n[r, c], K) if n[r, c] >= 2 else 0):
                n1, n2 = _held(D, n, r, c, D[r, c, k], gate, h)
                if n2 > n1:
                    ev[r, c] = True
                    count += 1
                    break
            if count >= stop:
                return count
    return count


def layer_evidence(
    row, col, depth, image_shape, *, gate: float, half: int, surface_pfa: float, radius=None
) -> LayerEvidence:
    """Stage 7d's model of where a second layer exists (see the module).

    Parameters
    ----------
    row, col : ndarray (S,) int
    depth : ndarray (S,) float
        The surfaces' depths (bins).
    image_shape : (int, int)
    gate : float
        Depths within this many bins are one (stage 7b's region gate: 1.5 FWHM).
    half : int
        The largest box's half-width (pixels): a spread's reach.
    surface_pfa : float
        The null's false surfaces per background-only pixel (``detect``'s option), the
        rate under "no layer" and the test's level.
    radius : int, optional
        The window's radius (pixels); None: the whole image (measured best: the module).

    Returns
    -------
    LayerEvidence
    """
    D, n = depth_slots(row, col, depth, image_shape)
    ev = np.zeros(n.shape, np.bool_)
    _evidence(D, n, float(gate), int(half), ev, ev.size + 1)
    if radius is None:
        count = np.full(ev.shape, int(ev.sum()), np.int64)
        area = np.full(ev.shape, float(ev.size))
    else:
        count, area = window_counts(ev, int(radius))
    expected = float(surface_pfa) * area
    layered = stats.poisson.sf(count - 1, expected) < float(surface_pfa)
    return LayerEvidence(ev, count, expected, layered)


def window_counts(ev, radius: int, at=None) -> tuple[np.ndarray, np.ndarray]:
    """Evidence pixels and pixels inside the image in the ``(2 radius + 1)^2`` window
    about each pixel (int64, float64; ``at``: ``(rows, cols)`` to return them there only)."""
    k = 2 * int(radius) + 1
    box = ndimage.uniform_filter
    count = box(ev.astype(np.float64), k, mode="constant")
    area = box(np.ones(ev.shape), k, mode="constant")
    if at is not None:
        count, area = count[at], area[at]
    return np.rint(count * k * k).astype(np.int64), np.rint(area * k * k)


@dataclass(frozen=True)
class SpreadLines:
    """Stage 7d's decision: the surfaces to remove (indices, ascending), 7c's prior level
    (nats), the candidates (indices), whether each was tested (7c's axes, outside the
    layered windows), each one's best line log-ratio (nats; NaN where not tested) and
    the layer model."""

    remove: np.ndarray
    level: float
    candidates: np.ndarray
    tested: np.ndarray
    line_llr: np.ndarray
    layers: LayerEvidence


_AXES4 = np.array([[0, 1], [1, 0], [1, 1], [1, -1]], np.int64)


@njit(cache=True, nogil=True)
def _nearest(D, n, r, c, course, gate):
    """The depth of pixel ``(r, c)`` nearest ``course`` within ``gate`` (NaN: none)."""
    best, out = gate, np.nan
    for k in range(min(n[r, c], D.shape[2])):
        e = abs(D[r, c, k] - course)
        if e <= best and (np.isnan(out) or e < abs(out - course)):
            best, out = e, D[r, c, k]
    return out


@njit(cache=True, nogil=True)
def _line_pools(D, n, rows, cols, depth, gate, h, open_pool):
    """Rows, columns, depths and line (``4 * candidate + axis``) of the pixels pooled on
    the 4 axes through each candidate (see the module; ``open_pool``: the pixels holding
    one surface only at the course left out)."""
    R, C, _ = D.shape
    m = rows.size * 4 * (2 * h + 1)
    orow, ocol = np.empty(m, np.int64), np.empty(m, np.int64)
    odep, ogrp = np.empty(m, np.float64), np.empty(m, np.int64)
    j = 0
    for i in range(rows.size):
        for a in range(4):
            dr, dc = _AXES4[a, 0], _AXES4[a, 1]
            orow[j], ocol[j], odep[j], ogrp[j] = rows[i], cols[i], depth[i], 4 * i + a
            j += 1
            for sgn in (1, -1):
                course = depth[i]
                for k in range(1, h + 1):
                    r, c = rows[i] + sgn * k * dr, cols[i] + sgn * k * dc
                    if r < 0 or r >= R or c < 0 or c >= C:
                        break
                    own = _nearest(D, n, r, c, course, gate)
                    if not np.isnan(own):
                        course = own
                        if open_pool and n[r, c] == 1:
                            continue
                    else:
                        best = np.nan
                        for rr in range(max(r - 1, 0), min(r + 2, R)):
                            for cc in range(max(c - 1, 0), min(c + 2, C)):
                                x = _nearest(D, n, rr, cc, course, gate)
                                if not np.isnan(x) and (
                                    np.isnan(best) or abs(x - course) < abs(best - course)
                                ):
                                    best = x
                        if not np.isnan(best):
                            course = best
                    orow[j], ocol[j], odep[j], ogrp[j] = r, c, course, 4 * i + a
                    j += 1
    return orow[:j], ocol[:j], odep[:j], ogrp[:j]


def line_llr(D, n, rows, cols, depth, counts, background, irf, *, gate, half, open_pool=True):
    """(m, 4) the profiled log-ratios (nats) of the 4 lines through each of ``m``
    surfaces at ``(rows, cols, depth)`` (see the module); ``D, n``: :func:`depth_slots`."""
    if rows.size == 0:
        return np.zeros((0, 4))
    r, c, d, g = _line_pools(D, n, np.asarray(rows, np.int64), np.asarray(cols, np.int64),
                             np.asarray(depth, np.float64), float(gate), int(half),
                             bool(open_pool))  # fmt: skip
    y, gg, b = _windows(counts, background, r, c, d, irf)
    return group_llr(y, gg, b, g).reshape(rows.size, 4)


def spread_lines(
    row, col, depth, image_shape, counts, background, *, fwhm: float, irf, half: int,
    surface_pfa: float,
) -> SpreadLines:  # fmt: skip
    """Stage 7d's decision on the surfaces at ``(row, col, depth)`` (see the module).

    Parameters
    ----------
    row, col : ndarray (S,) int
    depth : ndarray (S,) float
        Bins (after stage 7).
    image_shape : (int, int)
    counts : ndarray (rows, cols, L, T)
        The cube's raw counts.
    background : Background
    fwhm : float
        The IRF's FWHM (bins).
    irf : ndarray (L, n_irf)
    half : int
        The largest box's half-width (pixels).
    surface_pfa : float
        The null's false surfaces per background-only pixel (:func:`layer_evidence`).

    Returns
    -------
    SpreadLines
    """
    row, col = np.asarray(row, np.int64), np.asarray(col, np.int64)
    depth = np.asarray(depth, np.float64)
    R, C = image_shape
    gate = GATE_FWHM * float(fwhm)
    pix = row * C + col
    n_at = np.bincount(pix, minlength=R * C)
    cand = np.flatnonzero(n_at[pix] >= 2)
    q = float((n_at >= 2).sum()) / max(int((n_at >= 1).sum()), 1)
    level = float(np.log((1.0 - q) / q)) if 0.0 < q < 1.0 else 0.0
    layers = layer_evidence(row, col, depth, image_shape, gate=gate, half=half,
                            surface_pfa=surface_pfa)  # fmt: skip
    tested = ~layers.layered[row[cand], col[cand]]
    if tested.any():
        tested &= continued_axes(row, col, depth, cand, image_shape, gate, REACH) < AXES
    llr = np.full(cand.size, np.nan)
    t = cand[tested]
    D, n = depth_slots(row, col, depth, image_shape)
    irf = np.atleast_2d(np.asarray(irf, np.float64))
    lines = line_llr(D, n, row[t], col[t], depth[t], counts, background, irf, gate=gate,
                     half=half)  # fmt: skip
    if t.size:
        llr[tested] = lines.max(axis=1)
    fail = tested & (np.nan_to_num(llr, nan=np.inf) < level)
    passes = np.bincount(pix[cand], weights=~fail, minlength=R * C)
    remove = cand[fail & (passes[pix[cand]] >= 1)]
    return SpreadLines(np.sort(remove), level, cand, tested, llr, layers)
