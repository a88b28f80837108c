"""Stage 7d (model, **off**: :data:`LAYER_GATE`): where the scene shows a second layer.

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

Why off (benchmarks/README.md, "lay38, session 26"; ``benchmarks/bench_spread_sources.py
--layer``): gating spr36's line rules (``line_open``, ``line_all``) by the layered
regions keeps every true surface of the sheet and net families (0 of 18 cubes lose one,
whole-image window) and takes issue #15's single-surface cells from 90.3 / 116.7 false
surfaces to about 48.0 / 62.7 (1 true surface lost in 6 cubes), but on
``bench_detection.py``'s 64 cells the single-surface scene itself loses 47 true surfaces
in 11 cells at PPP 1-4 (no layer to gate on: the line test, not the gate) and the
two-layer scene at PPP 1 15 in 2 cells (too few second surfaces detected to show the
layer): "nothing worse on any benchmark" does not hold. Kept with its tests so that a
rule for a pixel's further surfaces can consult it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage, stats

__all__ = ["LAYER_GATE", "LayerEvidence", "layer_evidence"]

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


def depth_slots(row, col, depth, image_shape) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols, K) float64 depths of each pixel's surfaces (NaN padded) and
    (rows, cols) int64 the number each pixel holds."""
    R, C = image_shape
    pix = np.asarray(row, np.int64) * C + np.asarray(col, np.int64)
    n = np.bincount(pix, minlength=R * C)
    out = np.full((R * C, max(int(n.max(initial=0)), 1)), np.nan)
    order = np.argsort(pix, kind="stable")
    p = pix[order]
    out[p, np.arange(p.size) - np.searchsorted(p, p)] = np.asarray(depth, np.float64)[order]
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
def _evidence(D, n, gate, h):
    R, C, K = D.shape
    ev = np.zeros((R, C), np.bool_)
    for r in range(R):
        for c in range(C):
            for k in range(min(n[r, c], K) if n[r, c] >= 2 else 0):
                n1, n2 = _held(D, n, r, c, D[r, c, k], gate, h)
                if n2 > n1:
                    ev[r, c] = True
                    break
    return ev


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
    ev = _evidence(D, n, float(gate), int(half))
    if radius is None:
        count = np.full(ev.shape, int(ev.sum()), np.int64)
        area = np.full(ev.shape, float(ev.size))
    else:
        k = 2 * int(radius) + 1
        box = ndimage.uniform_filter
        count = np.rint(box(ev.astype(np.float64), k, mode="constant") * k * k).astype(np.int64)
        area = np.rint(box(np.ones(ev.shape), k, mode="constant") * k * k)
    expected = float(surface_pfa) * area
    layered = stats.poisson.sf(count - 1, expected) < float(surface_pfa)
    return LayerEvidence(ev, count, expected, layered)
