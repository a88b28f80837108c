"""Tests of stage 7c (``detection/_7c_spread_groups.py``, off in ``detect``): a pixel's
further surfaces tested by group on their own counts."""

from __future__ import annotations

import numpy as np

from splidar import gaussian_irf
from splidar.detection._7b_edge_bands import profile_llr
from splidar.detection._7c_spread_groups import (
    SPREAD_GROUPS,
    _windows,
    continued_axes,
    group_llr,
    spread_groups,
)
from splidar.detection._result import Background

IRF = gaussian_irf(3.0)[None, :]  # (1, 13), FWHM 3 bins
T = 100
SHAPE = (20, 24)
D_BRIGHT, D_DIM = 30.0, 62.0
BG = 0.02  # background counts per bin
EDGE = 12  # the bright region's columns: < EDGE


def _pulse(d: float, photons: float) -> np.ndarray:
    t = np.arange(T)
    g = np.exp(-0.5 * ((t - d) / (3.0 / 2.3548)) ** 2)
    return photons * g / g.sum()


def _cube(extra=(), dim_photons: float = 3.0, seed: int = 0) -> np.ndarray:
    """A bright region (columns < EDGE, depth 30, 12 photons) beside a dim one (depth
    62), raw counts (rows, cols, 1, T); ``extra``: (column, depth, photons) added to a
    whole column."""
    lam = np.full(SHAPE + (1, T), BG)
    for c in range(SHAPE[1]):
        lam[:, c, 0] += _pulse(D_BRIGHT, 12.0) if c < EDGE else _pulse(D_DIM, dim_photons)
    for c, d, ph in extra:
        lam[:, c, 0] += _pulse(d, ph)
    return np.random.default_rng(seed).poisson(lam).astype(np.uint16)


def _background() -> Background:
    return Background(
        spatial=np.full(SHAPE + (1,), BG, np.float32), temporal=np.full((1, T), BG, np.float32)
    )


def _surfaces(further_cols=()):
    """Each pixel its region's depth; the columns ``further_cols`` also hold the bright
    region's depth as a further surface (the boxes' spread). Returns row, col, depth."""
    R, C = SHAPE
    row, col = (a.ravel() for a in np.mgrid[0:R, 0:C])
    depth = np.where(col < EDGE, D_BRIGHT, D_DIM)
    fr = np.repeat(np.arange(R), len(further_cols))
    fc = np.tile(np.asarray(further_cols, np.int64), R)
    return (
        np.concatenate([row, fr]),
        np.concatenate([col, fc]),
        np.concatenate([depth, np.full(fr.size, D_BRIGHT)]),
    )


def _run(counts, surfaces, **kw):
    row, col, depth = surfaces
    return spread_groups(row, col, depth, SHAPE, counts, _background(), fwhm=3.0, irf=IRF, **kw)


def test_spread_groups_is_off_in_detect():
    assert SPREAD_GROUPS is False


def test_spread_groups_removes_a_neighbours_spread_beside_a_depth_edge():
    # the dim region's first column holds the bright region's depth as well, with no
    # return there in its own counts: a line of spread beside the depth edge
    row, col, depth = _surfaces(further_cols=[EDGE])
    out = _run(_cube(), (row, col, depth))
    spread = np.arange(SHAPE[0] * SHAPE[1], row.size)  # the further surfaces
    np.testing.assert_array_equal(out.remove, spread)
    assert out.level == np.log((1 - 1 / 24) / (1 / 24))


def test_spread_groups_keeps_a_further_surface_its_own_counts_show():
    # the same line, but the pixels hold a return at that depth (a real second layer)
    counts = _cube(extra=[(EDGE, D_BRIGHT, 3.0)])
    out = _run(counts, _surfaces(further_cols=[EDGE]))
    assert out.remove.size == 0


def test_spread_groups_keeps_a_surface_that_continues_through_its_pixel():
    # three columns inside the dim region hold a further surface with no return: the
    # outer two stop there (one axis continues), the middle one continues on all four
    row, col, depth = _surfaces(further_cols=[17, 18, 19])
    further = np.arange(row.size) >= SHAPE[0] * SHAPE[1]
    out = _run(_cube(), (row, col, depth))
    removed = np.zeros(row.size, bool)
    removed[out.remove] = True
    assert removed[further & ((col == 17) | (col == 19))].all()
    inner = (row > 0) & (row < SHAPE[0] - 1)  # at the image's border it continues on one
    assert not removed[further & (col == 18) & inner].any()
    assert removed[further & (col == 18) & ~inner].all()
    assert not removed[~further].any()
    # testing every candidate (no axis condition) removes the middle one too
    every = _run(_cube(), (row, col, depth), axes=5)
    np.testing.assert_array_equal(every.remove, np.flatnonzero(further))


def test_spread_groups_never_empties_a_pixel():
    # one pixel with two surfaces and no return at either: both tested (no axis
    # condition) and both fail, neither goes
    row, col, depth = _surfaces()
    row, col, depth = np.append(row, 10), np.append(col, 18), np.append(depth, D_BRIGHT)
    counts = _cube()
    counts[10, 18] = 0
    out = _run(counts, (row, col, depth), axes=5)
    assert out.candidates.size == 2
    assert out.tested.all() and (out.group_llr < out.level).all()
    assert out.remove.size == 0


def test_continued_axes_counts_the_axes_holding_the_depth_on_both_sides():
    row, col, depth = _surfaces(further_cols=[17, 18, 19])
    cand = np.arange(SHAPE[0] * SHAPE[1], row.size)  # the further surfaces, row by row
    ax = continued_axes(row, col, depth, cand, SHAPE, 4.5, 1).reshape(SHAPE[0], 3)
    # inner rows: columns 17 and 19 continue up-down only, column 18 on all four axes
    np.testing.assert_array_equal(ax[1:-1], np.tile([1, 4, 1], (SHAPE[0] - 2, 1)))
    np.testing.assert_array_equal(ax[0], [0, 1, 0])  # the first row: no neighbour above


def test_group_llr_matches_profile_llr_alone_and_a_grid_in_groups():
    counts = _cube(dim_photons=1.0, seed=4)
    row, col, depth = _surfaces(further_cols=[EDGE])
    y, g, b = _windows(counts, _background(), row, col, depth, IRF)
    n = row.size
    np.testing.assert_allclose(group_llr(y, g, b, np.arange(n)), profile_llr(y, g, b), atol=1e-9)
    grp = np.arange(n) // 7
    s = np.concatenate([[0.0], np.geomspace(1e-3, 100.0, 4001)])
    G = g.sum(axis=(1, 2))
    f = np.stack([(y * np.log1p(x * g / b)).sum(axis=(1, 2)) - x * G for x in s], 1)
    fg = np.zeros((grp.max() + 1, s.size))
    np.add.at(fg, grp, f)
    got = group_llr(y, g, b, grp)
    assert (got >= fg.max(axis=1) - 1e-9).all()
    np.testing.assert_allclose(got, fg.max(axis=1), atol=1e-3)
