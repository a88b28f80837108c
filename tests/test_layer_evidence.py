"""Tests of stage 7d (``detection/_7d_layer_evidence.py``, off in ``detect``): where the
detection shows a second layer, tested against the null's false-alarm rate."""

from __future__ import annotations

import numpy as np
from scipy import stats

from splidar import gaussian_irf
from splidar.detection._7d_layer_evidence import (
    LAYER_GATE,
    depth_slots,
    layer_evidence,
    line_llr,
    spread_lines,
)
from splidar.detection._result import Background

SHAPE = (40, 48)
D_NEAR, D_FAR, D_SHEET = 30.0, 62.0, 12.0
EDGE = 24  # the near region's columns: < EDGE
GATE, HALF, PFA = 4.5, 5, 0.01


def _scene(extra=()):
    """Each pixel its region's depth (near left of EDGE, far right of it); ``extra``:
    (row, col, depth) further surfaces. Returns row, col, depth."""
    R, C = SHAPE
    row, col = (a.ravel() for a in np.mgrid[0:R, 0:C])
    depth = np.where(col < EDGE, D_NEAR, D_FAR)
    if len(extra):
        er, ec, ed = (np.asarray(x) for x in zip(*extra, strict=True))
        row, col = np.concatenate([row, er]), np.concatenate([col, ec])
        depth = np.concatenate([depth, ed])
    return row, col, depth.astype(np.float64)


def _run(extra=(), radius=None):
    row, col, depth = _scene(extra)
    return layer_evidence(
        row, col, depth, SHAPE, gate=GATE, half=HALF, surface_pfa=PFA, radius=radius
    )


def _strip(cols, depth):
    return [(r, c, depth) for r in range(SHAPE[0]) for c in cols]


def test_layer_evidence_spread_strip_shows_no_layer():
    # the near region's depth spread 1-2 px into the far region (a strip along the edge)
    le = _run(_strip((EDGE, EDGE + 1), D_NEAR))
    assert not le.evidence.any()
    assert not le.layered.any()


def test_layer_evidence_two_layer_region_is_layered():
    # a sheet in front of both regions over rows 10-29, columns 8-39: its pixels hold two
    sheet = [(r, c, D_SHEET) for r in range(10, 30) for c in range(8, 40)]
    le = _run(sheet)
    inside = np.zeros(SHAPE, bool)
    inside[10:30, 8:40] = True
    assert le.evidence[inside].mean() > 0.9
    assert not le.evidence[~inside].any()
    assert le.layered.all()


def test_layer_evidence_sheet_edge_row_shows_the_layer():
    # a sheet in front of the far region only (rows 10-29, columns EDGE-39): the object
    # it hides is held alone above and below it, within the boxes' reach of its edge
    # rows (where a spread would come from), yet its pairs outnumber those pixels
    sheet = [(r, c, D_SHEET) for r in range(10, 30) for c in range(EDGE, 40)]
    le = _run(sheet)
    assert le.evidence[10:30, EDGE + HALF + 1 : 40 - HALF].all()
    assert le.layered.all()


def test_layer_evidence_background_alarms_explained_by_null():
    # scattered background alarms behind the pixels' own surfaces, fewer than the null's
    # rate explains (surface_pfa x 1,920 pixels = 19.2): evidence, but no layer
    rng = np.random.default_rng(0)
    pix = rng.choice(SHAPE[0] * SHAPE[1], 12, replace=False)
    alarms = [(p // SHAPE[1], p % SHAPE[1], float(d)) for p, d in
              zip(pix, rng.uniform(80, 190, pix.size), strict=True)]  # fmt: skip
    le = _run(alarms)
    assert le.evidence.sum() == 12
    assert le.count[0, 0] == 12
    np.testing.assert_allclose(le.expected, PFA * SHAPE[0] * SHAPE[1])
    assert not le.layered.any()


def test_layer_evidence_level_is_the_null_poisson_tail():
    # n evidence pixels in the whole image: layered iff P(Poisson(pfa x pixels) >= n) < pfa
    lam = PFA * SHAPE[0] * SHAPE[1]
    n_min = int(stats.poisson.isf(PFA, lam)) + 1  # the smallest n with sf(n - 1) < pfa
    assert stats.poisson.sf(n_min - 1, lam) < PFA <= stats.poisson.sf(n_min - 2, lam)
    for n, want in ((n_min - 1, False), (n_min, True)):
        alarms = [(2 * (i // 20), 2 * (i % 20), 150.0 + 7 * (i % 3)) for i in range(n)]
        le = _run(alarms)
        assert le.evidence.sum() == n
        assert le.layered.all() == want and le.layered.any() == want


def test_layer_evidence_window_keeps_the_layer_local():
    # a layered patch in the top-left corner: with a 10-pixel window the far corner
    # shows no layer; the whole image (radius None) is layered
    patch = [(r, c, D_SHEET) for r in range(0, 12) for c in range(0, 12)]
    local = _run(patch, radius=10)
    assert local.layered[0, 0] and not local.layered[-1, -1]
    assert _run(patch).layered.all()


def test_depth_slots_pads_and_counts():
    D, n = depth_slots(np.array([0, 1, 0]), np.array([1, 0, 1]), np.array([5.0, 6.0, 7.0]),
                       (2, 2))  # fmt: skip
    assert n.tolist() == [[0, 2], [1, 0]]
    np.testing.assert_array_equal(D[0, 1], [5.0, 7.0])
    assert np.isnan(D[1, 0, 1]) and np.isnan(D[0, 0]).all()


def test_layer_gate_is_off():
    # measured, not adopted (benchmarks/README.md, "lay38, session 26")
    assert LAYER_GATE is False


# --- the rule it gates: spread_lines (spr36's line_open outside the layered windows) ---

IRF = gaussian_irf(3.0)[None, :]  # (1, 13), FWHM 3 bins
T = 100
SMALL = (20, 24)
BG = 0.02  # background counts per bin
SPREAD_COL = 12  # the first column of the dim region, holding the bright depth too


def _pulse(d: float, photons: float) -> np.ndarray:
    t = np.arange(T)
    g = np.exp(-0.5 * ((t - d) / (3.0 / 2.3548)) ** 2)
    return photons * g / g.sum()


def _counts(sheet_cols=(), seed: int = 0) -> np.ndarray:
    """Bright region (columns < SPREAD_COL, depth 30, 12 photons) beside a dim one
    (depth 62, 3 photons); ``sheet_cols``: a sheet at depth 12 (6 photons) in front,
    hiding the dim object entirely (no return of it in their counts)."""
    lam = np.full(SMALL + (1, T), BG)
    for c in range(SMALL[1]):
        if c in sheet_cols:
            lam[:, c, 0] += _pulse(D_SHEET, 6.0)
        else:
            lam[:, c, 0] += _pulse(D_NEAR, 12.0) if c < SPREAD_COL else _pulse(D_FAR, 3.0)
    return np.random.default_rng(seed).poisson(lam).astype(np.uint16)


def _small_surfaces(further):
    """Each pixel its region's depth; ``further``: (column, depth) held by every row."""
    R, C = SMALL
    row, col = (a.ravel() for a in np.mgrid[0:R, 0:C])
    depth = np.where(col < SPREAD_COL, D_NEAR, D_FAR).astype(np.float64)
    for c, d in further:
        row = np.concatenate([row, np.arange(R)])
        col = np.concatenate([col, np.full(R, c)])
        depth = np.concatenate([depth, np.full(R, d)])
    return row, col, depth


def _spread_lines(further, counts):
    row, col, depth = _small_surfaces(further)
    bg = Background(
        spatial=np.full(SMALL + (1,), BG, np.float32), temporal=np.full((1, T), BG, np.float32)
    )
    out = spread_lines(
        row, col, depth, SMALL, counts, bg, fwhm=3.0, irf=IRF, half=HALF, surface_pfa=PFA
    )
    return out, (row, col, depth), bg


def test_spread_lines_removes_a_spread_strip_in_a_single_surface_scene():
    out, (row, col, depth), _ = _spread_lines([(SPREAD_COL, D_NEAR)], _counts())
    assert not out.layers.layered.any()
    strip = np.flatnonzero((col == SPREAD_COL) & (depth == D_NEAR))
    np.testing.assert_array_equal(out.remove, np.sort(strip))
    # the strip pixels' own (dim) surfaces stay: their line holds the return
    assert out.level > 0


def test_spread_lines_keeps_a_hidden_layer():
    # a sheet over columns 12-17 hides the dim object (no return of it in the counts):
    # the object's surfaces there fail every line, but the scene shows a second layer
    sheet = range(SPREAD_COL, SPREAD_COL + 6)
    further = [(c, D_SHEET) for c in sheet]
    out, (row, col, depth), bg = _spread_lines(further, _counts(sheet_cols=sheet))
    assert out.layers.layered.all()
    assert out.remove.size == 0 and not out.tested.any()
    hidden = np.flatnonzero(np.isin(col, list(sheet)) & (depth == D_FAR))
    D, n = depth_slots(row, col, depth, SMALL)
    lines = line_llr(D, n, row[hidden], col[hidden], depth[hidden], _counts(sheet_cols=sheet),
                     bg, IRF, gate=4.5, half=HALF)  # fmt: skip
    assert (lines.max(axis=1) < out.level).mean() > 0.5


def test_line_llr_open_pool_leaves_out_the_source_region():
    # a spread strip's line across the edge: open, the bright region's single-surface
    # pixels are left out and only the strip's own (empty) counts remain; pooled over
    # every pixel the line reaches the bright return
    row, col, depth = _small_surfaces([(SPREAD_COL, D_NEAR)])
    bg = Background(
        spatial=np.full(SMALL + (1,), BG, np.float32), temporal=np.full((1, T), BG, np.float32)
    )
    D, n = depth_slots(row, col, depth, SMALL)
    i = np.flatnonzero((row == 10) & (col == SPREAD_COL) & (depth == D_NEAR))
    args = (D, n, row[i], col[i], depth[i], _counts(), bg, IRF)
    closed = line_llr(*args, gate=4.5, half=HALF, open_pool=False)[0]
    opened = line_llr(*args, gate=4.5, half=HALF)[0]
    assert closed[0] > 20.0  # left-right: the bright region
    assert opened[0] < 3.0 and opened[1] < 3.0  # the strip alone
