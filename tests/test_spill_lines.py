"""Stage 5a's line test (``_spill_lines``) on its own: spread beside a thin structure."""

import numpy as np
import pytest

from splidar import gaussian_irf
from splidar.detection._5a_spill_over import remove_spill_over
from splidar.detection._5b_isolated import remove_isolated
from splidar.detection._spill_lines import reject_spill_lines
from splidar.metrics import PointSet, match_points
from splidar.scenes import two_layer_scene

T, W, B = 80, 13, 0.08  # bins, window, background photons per bin
G = np.asarray(gaussian_irf(3.0), np.float64)[None]  # FWHM 3 bins
PEAK = np.array([int(G[0].argmax())])
NEAR, FAR = 20.0, 60.0  # the structure's depth, the pixels' own surface behind


def _counts(rng, rows, near):
    """Counts (rows, cols, 1, T): every pixel shows a bright surface at FAR (8 photons);
    ``near`` (cols,) the photons of a return at NEAR per column (0: none)."""
    C = len(near)
    t = np.arange(T)
    g = lambda d: np.interp(t - d + PEAK[0], np.arange(G.shape[1]), G[0], left=0, right=0)  # noqa: E731
    lam = B + 8.0 * g(FAR)[None, None] + np.asarray(near)[None, :, None] * g(NEAR)[None, None]
    return rng.poisson(np.broadcast_to(lam, (rows, C, T)))[:, :, None, :]


def _table(y, cands):
    """The candidate table of ``cands`` [(row, col, depth)] over the counts ``y``."""
    R, C = y.shape[:2]
    row = np.array([c[0] for c in cands])
    col = np.array([c[1] for c in cands])
    d = np.array([c[2] for c in cands], float)
    off = np.round(d).astype(int) - W // 2
    own = np.stack([y[r, c, :, o : o + W] for r, c, o in zip(row, col, off, strict=True)])
    return dict(
        row=row, col=col, depth_bin=d, offset=off, own_counts=own.astype(np.int32),
        own_background=np.full(own.shape, B, np.float32), image_shape=(R, C),
    )  # fmt: skip


def _run(y, surf, **kw):
    R, C = y.shape[:2]
    args = dict(spatial=np.full((R, C, 1), B, np.float32), dev=np.zeros((1, T)), irf=G,
                peak=PEAK, fwhm=3.0, half=5, llr_level=3.0)  # fmt: skip
    args.update(kw)
    return reject_spill_lines(surf, np.ones(len(surf["row"]), bool), y, **args)


def _strand(rng, rows=40, strand=1.6, beside=0.0):
    """A vertical strand (column 2) of ``strand`` photons, ``beside`` photons at its
    depth in column 3; candidates at the strand's depth in columns 2 and 3, and every
    pixel's own surface behind."""
    y = _counts(rng, rows, [0.0, 0.0, strand, beside, 0.0, 0.0])
    cands = [(r, c, FAR) for r in range(rows) for c in range(6)]
    cands += [(r, c, NEAR) for r in range(rows) for c in (2, 3)]
    return y, _table(y, cands)


def test_reject_spill_lines_removes_a_strands_spread_and_keeps_the_strand():
    # 1.6 photons per strand pixel (the net at PPP 4): per pixel, 62 % of the spread and
    # 21 % of the strand have an own log-ratio below 0 (benchmarks/README.md). A line of
    # 11 strand pixels sums about +11 nats (sd about 7): it shows the return (>= 3) in
    # about 85 % of the rows, and the empty column's line (about -17) always rejects it
    rng = np.random.default_rng(0)
    y, surf = _strand(rng)
    res = _run(y, surf)
    near = surf["depth_bin"] == NEAR
    spread, strand = near & (surf["col"] == 3), near & (surf["col"] == 2)
    assert res.rejected[spread].mean() > 0.75
    assert not res.rejected[strand].any() and not res.rejected[~near].any()
    # the strand's candidates beside a rejected spread keep the pooled support
    assert res.support[strand].mean() > 0.9 and not res.support[res.rejected].any()


def test_reject_spill_lines_keeps_a_two_pixel_wide_structure():
    # the same return in both columns: column 3's parallel line shows it
    rng = np.random.default_rng(1)
    y, surf = _strand(rng, beside=1.6)
    res = _run(y, surf)
    assert res.rejected.sum() <= 1  # a line of 11 pixels at 1.6 photons: rarely below -3


def test_reject_spill_lines_keeps_a_dim_surface_enclosed_by_a_bright_one():
    # a surface seen through a strand (column 2 at 0.6 of its neighbours' light) between
    # two bright columns: its parallel line at the neighbours' brightness may reject it,
    # but the far side's line shows the same return (condition 4)
    rng = np.random.default_rng(2)
    rows = 40
    y = _counts(rng, rows, [0.4, 4.0, 2.4, 4.0, 4.0, 0.4])
    cands = [(r, c, FAR) for r in range(rows) for c in (2,)]
    cands += [(r, c, NEAR) for r in range(rows) for c in range(1, 5)]
    surf = _table(y, cands)
    res = _run(y, surf)
    assert not res.rejected.any()


def test_reject_spill_lines_keeps_a_dim_edge_column_beside_a_wide_bright_surface():
    # column 2 at a quarter of its bright neighbours' light, nothing beyond it (a depth
    # edge): its parallel line rejects the bright return and the far side shows none,
    # but the line across it shows the surface it belongs to (condition 3)
    rng = np.random.default_rng(4)
    rows = 40
    y = _counts(rng, rows, [0.0, 0.0, 2.0, 8.0, 8.0, 8.0, 8.0])
    cands = [(r, 2, FAR) for r in range(rows)]
    cands += [(r, c, NEAR) for r in range(rows) for c in range(2, 7)]
    res = _run(y, _table(y, cands))
    assert not res.rejected.any()
    # the same column with nothing at that depth is the bright surface's spread
    y = _counts(rng, rows, [0.0, 0.0, 0.0, 8.0, 0.0, 0.0, 0.0])
    cands = [(r, 2, FAR) for r in range(rows)] + [(r, c, NEAR) for r in range(rows) for c in (2, 3)]
    surf = _table(y, cands)
    res = _run(y, surf)
    assert res.rejected[(surf["col"] == 2) & (surf["depth_bin"] == NEAR)].mean() > 0.9


def test_reject_spill_lines_tests_only_pixels_with_another_candidate():
    # the same spread without the pixels' own surfaces: each is its pixel's only
    # candidate, which keeps the per-pixel rule
    rng = np.random.default_rng(0)
    y, surf = _strand(rng)
    near = surf["depth_bin"] == NEAR
    sub = {k: (v[near] if isinstance(v, np.ndarray) else v) for k, v in surf.items()}
    res = _run(y, sub)
    assert not res.rejected.any() and not res.support.any()


def test_reject_spill_lines_reads_a_lazy_cube_by_bands_with_the_same_result():
    da = pytest.importorskip("dask.array")
    rng = np.random.default_rng(3)
    y, surf = _strand(rng, rows=70)
    a = _run(y, surf)
    assert a.rejected.sum() > 50  # something to compare
    b = _run(da.from_array(y, chunks=(16, -1, -1, -1)), surf)
    assert np.array_equal(a.rejected, b.rejected) and np.array_equal(a.support, b.support)


def test_reject_spill_lines_gives_the_same_result_on_threads():
    rng = np.random.default_rng(5)
    y, surf = _strand(rng, rows=600)  # 600 candidates tested: 2 parts of >= 256
    a = _run(y, surf)
    b = _run(y, surf, n_jobs=2)
    assert np.array_equal(a.rejected, b.rejected) and np.array_equal(a.support, b.support)


@pytest.fixture(scope="module")
def net_cube():
    """A detection's candidate table before stage 5a, on the project's net (PPP 4, SBR
    0.25): the map pass of ``detect`` with the inputs stage 5a gets."""
    import splidar.detection._detect as D
    from splidar.detection import detect

    sim = two_layer_scene((40, 40), n_bins=120).simulate(
        ppp=4, sbr=0.25, background="uniform", rng=0
    )
    seen = {}

    def spy(table, **kw):  # records the real inputs, runs the real pass
        seen.update(table=table, **kw)
        return real(table, **kw)

    real = D.remove_spill_over
    D.remove_spill_over = spy
    try:
        detect(sim.cube, passes=("spill_over",))
    finally:
        D.remove_spill_over = real
    return sim, seen


def test_remove_spill_over_line_test_removes_mostly_false_candidates(net_cube):
    sim, seen = net_cube
    table = seen.pop("table")
    kw = {k: v for k, v in seen.items() if k not in ("counts", "spatial", "dev")}
    without = remove_spill_over(table, **{**kw, "half": 0})
    with_lines = remove_spill_over(
        table, **kw, counts=seen["counts"], spatial=seen["spatial"], dev=seen["dev"]
    )
    assert "line_support" in with_lines.table.columns
    assert not np.any(with_lines.table.keep & ~without.table.keep)  # it only removes
    gone = np.flatnonzero(without.table.keep & ~with_lines.table.keep)
    assert gone.size > 20
    c = table.columns
    est = PointSet(row=c["row"][gone], col=c["col"][gone], depth_bin=c["depth_bin"][gone],
                   image_shape=table.image_shape)  # fmt: skip
    m = match_points(est, sim.truth, tau=3.0)
    # the removed ones are mostly spread, not true surfaces (measured: 32 of 37; of the
    # candidates the per-pixel test keeps, 194 of 1,694 are false: removing at random
    # would give about 1 in 9)
    assert len(m.unmatched_est) >= 0.75 * gone.size
    # the isolated test counts the support as shared: what it rejects on top is no more
    iso_with = remove_isolated(with_lines.table, fwhm=kw["fwhm"], pfa=0.01, n_bins=120)
    sup = np.asarray(with_lines.table.columns["line_support"])
    assert not np.any(sup & with_lines.table.keep & ~iso_with.table.keep)


def test_line_any_decides_as_the_largest_fraction_does():
    # _line_any stops at the first fraction whose line reaches the level and takes the
    # caller's whole sum as fraction 1: the decision of max over every fraction >= level
    from splidar.detection import _spill_lines as sl
    from splidar.detection._quality import _by_pixel

    rng = np.random.default_rng(4)
    R, C, h = 9, 11, 3
    near = rng.choice([0.0, 0.5, 1.5, 4.0], C)
    y = _counts(rng, R, near)
    row, col = (a.ravel() for a in np.mgrid[0:R, 0:C])
    keep = rng.random(row.size) < 0.6
    row, col = row[keep], col[keep]
    depth = NEAR + rng.normal(0.0, 1.0, row.size)
    order, starts = _by_pixel(row, col, (R, C))
    sp = np.full((R, C, 1), B, np.float32)
    dev = np.zeros((1, T))
    a = (depth, order, starts, R, C, y, 0, sp, dev, G, PEAK.astype(float), 3.0, h)
    n_true = 0
    for r, c, ur, uc in zip(rng.integers(0, R, 60), rng.integers(0, C, 60),
                            *rng.choice([[0, 1], [1, 0]], 60).T, strict=True):  # fmt: skip
        s = np.array([rng.choice([0.3, 1.0, 3.0])])
        lines = [sl._line(r, c, ur, uc, 1, NEAR, s * 0.5**k, a) for k in range(sl._N_FRACTIONS)]
        for level in (-3.0, 0.0, 3.0):
            want = max(lines) >= level
            assert sl._line_any(r, c, ur, uc, 1, NEAR, s, a, level) == want
            first = sl._line(r, c, ur, uc, 1, NEAR, s, a, -level)
            if first < -level:  # the whole sum: the kernel passes it on
                assert first == lines[0]
                assert sl._line_any(r, c, ur, uc, 1, NEAR, s, a, level, first) == want
            n_true += want
    assert 0 < n_true < 180
