"""Tests of stage 7b (``detection/_7b_edge_bands.py``): the bands beside depth edges."""

from __future__ import annotations

import itertools
from dataclasses import fields, replace

import numpy as np
import pytest
from numba import njit

from splidar import gaussian_irf
from splidar.detection import STAGES
from splidar.detection._7_depths import place_depths
from splidar.detection._7b_edge_bands import (
    _windows,
    band_depths,
    far_inside_depths,
    min_cut_labels,
    near_depths,
    profile_llr,
)
from splidar.detection._result import Background, Surfaces

IRF = gaussian_irf(3.0)[None, :]  # (1, 13), FWHM 3 bins
T = 100
SHAPE = (20, 24)
D_BRIGHT, D_DIM = 30.0, 62.0
BG = 0.02  # background counts per bin


def _lam(dim_photons: float, edge: int = 12) -> np.ndarray:
    """A bright region (columns < ``edge``, depth 30, 12 photons) beside a dim one
    (depth 62, ``dim_photons``), the Poisson mean (rows, cols, 1, T)."""
    lam = np.full(SHAPE + (1, T), BG)
    t = np.arange(T)
    g = np.exp(-0.5 * ((t - 0.0) / (3.0 / 2.3548)) ** 2)
    for c in range(SHAPE[1]):
        d, ph = (D_BRIGHT, 12.0) if c < edge else (D_DIM, dim_photons)
        g = np.exp(-0.5 * ((t - d) / (3.0 / 2.3548)) ** 2)
        lam[:, c, 0] += ph * g / g.sum()
    return lam


def _surfaces(depth: np.ndarray) -> Surfaces:
    """One surface per pixel at ``depth`` (rows, cols), the other fields placeholders
    of the right shapes (window 13 bins about the depth)."""
    R, C = depth.shape
    row, col = (a.ravel() for a in np.mgrid[0:R, 0:C])
    n, W = row.size, 13
    d = depth.ravel().astype(np.float64)
    off = np.clip(np.rint(d).astype(np.int64) - W // 2, 0, T - W)
    return Surfaces(
        row=row, col=col, slot=np.zeros(n, np.int64), depth_bin=d, start=off, stop=off + W,
        scale_index=np.zeros(n, np.int64), offset=off,
        histograms=np.zeros((n, 4, 1, W), np.float32), signal=np.ones((n, 4, 1)),
        counts=np.zeros((n, 1)), background=np.zeros((n, 1)), saliency_mass=np.ones(n),
        image_shape=(R, C), n_slots=2, presence_llr=np.zeros(n), presence_z=np.zeros(n),
        stage=np.zeros(n, np.int8),
    )  # fmt: skip


def _background() -> Background:
    return Background(
        spatial=np.full(SHAPE + (1,), BG, np.float32), temporal=np.full((1, T), BG, np.float32)
    )


def _band(width: int) -> np.ndarray:
    """The detection's depths: the dim region's first ``width`` columns took the
    bright region's depth (the boxes pooled its returns into them)."""
    depth = np.where(np.arange(SHAPE[1]) < 12 + width, D_BRIGHT, D_DIM)
    return np.broadcast_to(depth, SHAPE).copy()


def test_band_depths_moves_a_dim_band_beside_a_bright_region_to_its_own_depth():
    counts = np.random.default_rng(3).poisson(_lam(dim_photons=1.5)).astype(np.uint16)
    wrong = _band(3)
    depth, moved, beta = band_depths(
        _surfaces(wrong), counts, _background(), fwhm=3.0, irf=IRF, half=5
    )
    depth = depth.reshape(SHAPE)
    band = np.zeros(SHAPE, bool)
    band[:, 12:15] = True
    # the band's pixels (one or two photons each) move to their region's depth together
    assert np.mean(np.abs(depth[band] - D_DIM) < 1.0) > 0.9
    # nothing else moves, and the prior comes from the depth field (beta > 0)
    assert np.array_equal(depth[~band], wrong[~band])
    assert moved.size == np.sum(np.abs(depth - wrong) > 0) and beta > 0


def test_band_depths_keeps_a_band_its_counts_place_on_the_bright_side():
    # the bright region really reaches column 14: its pixels show it, none moves
    counts = np.random.default_rng(3).poisson(_lam(dim_photons=1.5, edge=15)).astype(np.uint16)
    wrong = _band(3)
    depth, moved, _ = band_depths(
        _surfaces(wrong), counts, _background(), fwhm=3.0, irf=IRF, half=5
    )
    assert moved.size == 0 and np.array_equal(depth, wrong.ravel())


def test_band_depths_leaves_multi_surface_pixels_alone():
    counts = np.random.default_rng(3).poisson(_lam(dim_photons=1.5)).astype(np.uint16)
    s = _surfaces(_band(3))
    # every band pixel also holds a second surface: a layer, not an occlusion
    extra = np.flatnonzero((s.col >= 12) & (s.col < 15))
    two = Surfaces(
        **{
            k: (
                np.concatenate([v, v[extra]])
                if isinstance(v, np.ndarray) and v.shape[:1] == (len(s),)
                else v
            )
            for k, v in vars(s).items()
        }
    )
    depth, moved, _ = band_depths(two, counts, _background(), fwhm=3.0, irf=IRF, half=5)
    assert moved.size == 0


def test_min_cut_labels_is_the_exact_minimum():
    rng = np.random.default_rng(0)
    node = np.full((3, 4), -1, np.int64)
    node[:, 1:3] = np.arange(6).reshape(3, 2)
    fixed_a = np.zeros((3, 4), bool)
    fixed_a[:, 0] = True
    fixed_b = np.zeros((3, 4), bool)
    fixed_b[:, 3] = True
    pairs = [(node[r, c], node[r2, c2]) for r, c in np.argwhere(node >= 0)
             for r2, c2 in ((r + 1, c), (r, c + 1)) if r2 < 3 and node[r2, c2] >= 0]  # fmt: skip
    for _ in range(20):
        ll = rng.normal(0, 2, (6, 2))
        beta = float(rng.uniform(0, 3))

        def energy(lab, ll=ll, beta=beta):
            e = -ll[np.arange(6), lab].sum() + beta * sum(lab[a] != lab[b] for a, b in pairs)
            # pairs with the fixed columns: column 0 holds label 0, column 3 label 1
            return e + beta * (np.sum(lab[[0, 2, 4]] == 1) + np.sum(lab[[1, 3, 5]] == 0))

        best = min(energy(np.array(x)) for x in itertools.product((0, 1), repeat=6))
        lab = min_cut_labels(node, ll, beta, fixed_a, fixed_b)
        assert energy(lab) <= best + 1e-2


def test_profile_llr_is_the_maximum_over_the_intensity():
    rng = np.random.default_rng(1)
    g = np.zeros((5, 1, 40))
    g[:, 0, 14:27] = IRF[0]
    b = np.full((5, 1, 40), 0.05)
    y = rng.poisson(b + 2.0 * g).astype(np.float64)
    got = profile_llr(y, g, b)
    s = np.linspace(0, 30, 30001)[:, None, None, None]
    grid = (y * np.log1p(s * g / b)).sum(axis=(2, 3)) - s[..., 0, 0] * g.sum(axis=(1, 2))
    assert np.allclose(got, np.maximum(grid.max(axis=0), 0.0), atol=1e-3)


def test_place_depths_edge_bands_records_its_moves():
    counts = np.random.default_rng(3).poisson(_lam(dim_photons=1.5)).astype(np.uint16)
    res = place_depths(
        _surfaces(_band(3)), counts=counts, background=_background(), fwhm=3.0, irf=IRF,
        scales=np.array([1, 3, 7, 11]), rules=("edge_bands",),
    )  # fmt: skip
    moved = np.flatnonzero(res.surfaces.moved_by == STAGES.index("edge_bands"))
    assert res.moved["edge_bands"] == moved.size > 0
    s = res.surfaces
    # a moved surface's support and window follow its depth
    assert np.all((s.start[moved] <= s.depth_bin[moved]) & (s.depth_bin[moved] < s.stop[moved]))


def test_detect_runs_edge_bands_after_align_depths_unless_skipped():
    from splidar import Cube
    from splidar.detection import PASSES, detect

    counts = np.random.default_rng(0).poisson(_lam(dim_photons=1.5)).astype(np.uint16)
    cube = Cube(counts, irf=gaussian_irf(3.0))
    on = detect(cube, rng=0)
    off = detect(cube, rng=0, passes=tuple(p for p in PASSES if p != "edge_bands"))
    rec_on = {r.stage: r for r in on.provenance}
    rec_off = {r.stage: r for r in off.provenance}
    assert [r.stage for r in on.provenance][-2:] == ["align_depths", "edge_bands"]
    assert rec_on["edge_bands"].ran and not rec_off["edge_bands"].ran
    assert on.options["n_edge_bands"] == rec_on["edge_bands"].moved
    if rec_on["edge_bands"].moved == 0:
        assert np.array_equal(on.points.depth_bin, off.points.depth_bin)


def _ramp_lam(photons: float, bright_at=None) -> tuple:
    """One region, a ramp ``depth = 40 + 0.5 col`` (bins) of ``photons`` per pixel; with
    ``bright_at`` (row, col, depth) that pixel's return is 30 photons at that depth.
    Returns the Poisson mean (rows, cols, 1, T) and the ramp's depths (rows, cols)."""
    depth = np.broadcast_to(40.0 + 0.5 * np.arange(SHAPE[1]), SHAPE).copy()
    t = np.arange(T)
    lam = np.full(SHAPE + (1, T), BG)
    for (r, c), d in np.ndenumerate(depth):
        ph = photons
        if bright_at is not None and (r, c) == bright_at[:2]:
            d, ph = bright_at[2], 30.0
        g = np.exp(-0.5 * ((t - d) / (3.0 / 2.3548)) ** 2)
        lam[r, c, 0] += ph * g / g.sum()
    return lam, depth


@pytest.mark.parametrize("offset", [5.0, 50.0], ids=["near", "far"])
def test_band_depths_moves_a_wrong_depth_inside_its_region_onto_the_plane(offset):
    # a pixel inside a ramp whose counts are the ramp's 3.4 photons moves back onto the
    # plane. near: its depth 5 bins off the ramp (inside the 4.5-bin gate of a
    # neighbour's; the near depths, on since near27). far: detected 50 bins behind it (a
    # background cluster beat its dim return), no neighbour holds that depth
    # (FAR_INSIDE; the near rule never offers it: it is not a member of the region)
    lam, ramp = _ramp_lam(3.4)
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    wrong = ramp.copy()
    wrong[10, 12] += offset
    depth, moved, _ = band_depths(
        _surfaces(wrong), counts, _background(), fwhm=3.0, irf=IRF, half=5
    )
    i = 10 * SHAPE[1] + 12
    assert moved.tolist() == [i]
    assert abs(depth[i] - ramp[10, 12]) < 0.5


def test_near_depths_keeps_a_pixel_its_counts_place_off_the_plane():
    # the same pixel's counts show a bright return where it was detected: it stays
    lam, ramp = _ramp_lam(3.4, bright_at=(10, 12, 51.0))
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    wrong = ramp.copy()
    wrong[10, 12] = 51.0
    s = _surfaces(wrong)
    moved, to = near_depths(
        s, np.asarray(s.depth_bin), np.arange(len(s)), counts, _background(),
        fwhm=3.0, irf=IRF, half=5,
    )  # fmt: skip
    assert moved.size == 0 and to.size == 0


def test_near_depths_keeps_a_step_its_pixels_share():
    # a 3 x 3 patch 5 bins behind the ramp (a step inside the 4.5-bin gate), dim: its
    # pixels share their offset from the plane, so it is a surface, not a fluctuation
    lam, ramp = _ramp_lam(0.0)
    depth = ramp.copy()
    depth[8:11, 10:13] += 5.0
    t = np.arange(T)
    for (r, c), d in np.ndenumerate(depth):
        g = np.exp(-0.5 * ((t - d) / (3.0 / 2.3548)) ** 2)
        lam[r, c, 0] += (0.3 if 8 <= r < 11 and 10 <= c < 13 else 3.4) * g / g.sum()
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    s = _surfaces(depth)
    moved, _ = near_depths(
        s, np.asarray(s.depth_bin), np.arange(len(s)), counts, _background(),
        fwhm=3.0, irf=IRF, half=5,
    )  # fmt: skip
    assert moved.size == 0


def test_near_depths_keeps_a_pixel_at_its_region_border(monkeypatch):
    import splidar.detection._7b_edge_bands as stage

    # the pixel the ramp test moves (5 bins off the ramp, the ramp's counts; joined to
    # its region by its right neighbour, 4.5 bins away), but its region ends at its row
    # (border: 3 of its 8-neighbours outside) or at its row and column (corner: 5
    # outside): the plane there extrapolates across the border, so it is not offered
    # (NEAR_INSIDE); offered (NEAR_INSIDE = 0), it moves
    lam, ramp = _ramp_lam(3.4)
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    wrong = ramp.copy()
    wrong[10, 12] += 5.0
    s = _surfaces(wrong)
    i, default = 10 * SHAPE[1] + 12, stage.NEAR_INSIDE
    for members in (s.row <= 10, (s.row <= 10) & (s.col >= 12)):
        solo = np.flatnonzero(members)
        for inside, want in ((default, []), (0, [i])):
            monkeypatch.setattr(stage, "NEAR_INSIDE", inside)  # read at call time
            moved, _ = near_depths(
                s, np.asarray(s.depth_bin), solo, counts, _background(),
                fwhm=3.0, irf=IRF, half=5,
            )  # fmt: skip
            assert moved.tolist() == want


def _other_brute(lab: np.ndarray, half: int) -> np.ndarray:
    """The other region with most members within ``half`` of each labelled pixel, ties
    to the lower label (-1 if none): the definition, pixel by pixel."""
    R, C = lab.shape
    out = np.full((R, C), -1, np.int64)
    for r, c in itertools.product(range(R), range(C)):
        if lab[r, c] < 0:
            continue
        w = lab[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1]
        w = w[(w >= 0) & (w != lab[r, c])]
        if w.size:
            vals, n = np.unique(w, return_counts=True)
            out[r, c] = vals[np.argmax(n)]  # the first maximum: the lowest label
    return out


def test_band_planes_other_region_is_the_most_frequent_with_ties_to_the_lower_label():
    from splidar.detection._7b_edge_bands import _band_planes

    rng = np.random.default_rng(3)
    lab = rng.integers(-1, 6, size=(23, 19))  # many ties in 3 x 3 windows
    depth = rng.uniform(10, 40, size=lab.shape)
    other, dep = _band_planes(lab, depth, 1, 4.5)
    np.testing.assert_array_equal(other, _other_brute(lab, 1))
    # a plane wherever there is another region, NaN elsewhere
    assert np.array_equal(np.isfinite(dep[..., 0]), other >= 0)


def test_band_planes_same_on_any_number_of_threads():
    from splidar.detection._7b_edge_bands import _band_planes

    rng = np.random.default_rng(4)
    lab = np.repeat(np.repeat(rng.integers(-1, 8, size=(12, 10)), 6, axis=0), 5, axis=1)
    depth = 20.0 + 0.3 * np.arange(lab.shape[0])[:, None] + rng.normal(0, 0.5, lab.shape)
    one = _band_planes(lab, depth, 3, 4.5, n_jobs=1)
    for n_jobs in (2, 3):
        other, dep = _band_planes(lab, depth, 3, 4.5, n_jobs=n_jobs)
        np.testing.assert_array_equal(other, one[0])
        np.testing.assert_array_equal(dep, one[1])


class _Lazy:
    """Counts read pixel by pixel (neither NumPy nor Dask): ``_pixels``'s generic path."""

    def __init__(self, a):
        self.a, self.shape = a, a.shape

    def __getitem__(self, key):
        return self.a[key]


def _every_pixel_two_depths(rng):
    """Counts of the dim-layer scene and every pixel with its two depths, each moved by
    up to 3 bins (``rng``'s draws in the order the tests made them)."""
    counts = rng.poisson(_lam(2.0)).astype(np.uint16)
    rows, cols = (a.ravel() for a in np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]])
    dep = np.stack([np.full(rows.size, D_BRIGHT), np.full(rows.size, D_DIM)], axis=1)
    dep += rng.uniform(-3, 3, dep.shape)
    return counts, rows, cols, dep


def test_likelihoods_window_read_equals_whole_series_on_any_threads(monkeypatch):
    from splidar.detection import _7b_edge_bands as eb

    rng = np.random.default_rng(5)
    counts, rows, cols, dep = _every_pixel_two_depths(rng)
    dep[:3] = [[-5.0, T + 5.0]] * 3  # clipped at the window's ends
    ref = eb._likelihoods(_Lazy(counts), _background(), rows, cols, dep, IRF)
    monkeypatch.setattr(eb, "_BLOCK", 37)  # several blocks
    for n_jobs in (1, 2):
        got = eb._likelihoods(counts, _background(), rows, cols, dep, IRF, n_jobs)
        np.testing.assert_array_equal(got, ref)
    assert (ref > 0).any()


def test_profile_llr_gathered_bins_give_the_dense_sums():
    rng = np.random.default_rng(6)
    n, L, W = 50, 2, 15
    y = rng.poisson(0.4, size=(n, L, W)).astype(np.float64)
    y[:, :, 5:9] += rng.poisson(2.0, size=(n, L, 4))
    g = np.broadcast_to(np.exp(-0.5 * ((np.arange(W) - 7) / 1.3) ** 2), (n, L, W))
    g = g / g.sum(axis=-1, keepdims=True)
    b = rng.uniform(0.05, 0.5, size=(n, L, W))
    got = profile_llr(y, g, b)
    # the dense Newton steps over every bin (bins without counts add 0 * ... = 0)
    G = g.sum(axis=(1, 2))
    s = np.maximum((y * g).sum(axis=(1, 2)) / G, 1e-3)
    for _ in range(30):
        q = y * g / (b + s[:, None, None] * g)
        d1 = -G + q.sum(axis=(1, 2))
        d2 = -(q * g / (b + s[:, None, None] * g)).sum(axis=(1, 2))
        s = np.where(d2 < 0, np.maximum(s - d1 / np.where(d2 < 0, d2, -1), 0.0), s)
    llr = (y * np.log1p(s[:, None, None] * g / b)).sum(axis=(1, 2)) - s * G
    ref = np.where((y * g / b).sum(axis=(1, 2)) > G, np.maximum(llr, 0.0), 0.0)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)


def test_far_inside_depths_keeps_a_far_pixel_its_counts_place_off_the_plane():
    # the same pixel with a bright return (30 photons) where it was detected: it stays
    lam, ramp = _ramp_lam(3.4, bright_at=(10, 12, 90.0))
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    wrong = ramp.copy()
    wrong[10, 12] = 90.0
    s = _surfaces(wrong)
    moved, _ = far_inside_depths(
        s, np.asarray(s.depth_bin), np.arange(len(s)), counts, _background(),
        fwhm=3.0, irf=IRF, half=5,
    )  # fmt: skip
    assert moved.size == 0


def test_far_inside_depths_keeps_a_depth_a_neighbour_shares():
    # a strand through the pixel: its neighbour above holds the same far depth as a
    # second surface (a two-surface pixel), so the depth continues and is not offered
    lam, ramp = _ramp_lam(3.4)
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    wrong = ramp.copy()
    wrong[10, 12] += 50.0
    s = _surfaces(wrong)
    extra = _surfaces(np.full((1, 1), wrong[10, 12]))
    R, C = SHAPE
    n = len(s)
    both = replace(s, **{
        f.name: np.concatenate([getattr(s, f.name), getattr(extra, f.name)])
        for f in fields(s)
        if isinstance(getattr(s, f.name), np.ndarray) and getattr(s, f.name).shape[:1] == (n,)
    })  # fmt: skip
    both = replace(both, row=np.r_[s.row, 9], col=np.r_[s.col, 12], slot=np.r_[s.slot, 1])
    pix = both.row * C + both.col
    solo = np.flatnonzero(np.bincount(pix, minlength=R * C)[pix] == 1)
    moved, _ = far_inside_depths(
        both, np.asarray(both.depth_bin), solo, counts, _background(),
        fwhm=3.0, irf=IRF, half=5,
    )  # fmt: skip
    assert moved.size == 0
    # without the neighbour's surface it moves
    moved, _ = far_inside_depths(
        s, np.asarray(s.depth_bin), np.arange(len(s)), counts, _background(),
        fwhm=3.0, irf=IRF, half=5,
    )  # fmt: skip
    assert moved.tolist() == [10 * C + 12]


def _plane_reference(lab, depth, r, c, reach, x, skip_self, gate):
    """The robust plane of :func:`_window_plane` with NumPy's least squares."""
    rr, cc = np.nonzero(lab == x)
    near = (np.abs(rr - r) <= reach) & (np.abs(cc - c) <= reach)
    if skip_self:
        near &= (rr != r) | (cc != c)
    dr, dc = (rr[near] - r).astype(float), (cc[near] - c).astype(float)
    d = depth[rr[near], cc[near]]
    keep, value = np.ones(d.size, bool), np.nan
    for it in range(2):
        A = np.stack([np.ones(keep.sum()), dr[keep], dc[keep]], axis=1)
        if keep.sum() < 3 or abs(np.linalg.det(A.T @ A)) < 1e-9 * max(keep.sum(), 1) ** 3:
            return np.median(d) if it == 0 else value
        coef = np.linalg.lstsq(A, d[keep], rcond=None)[0]
        value = coef[0]
        keep = np.abs(coef[0] + coef[1] * dr + coef[2] * dc - d) <= gate
    return value


def test_window_plane_equals_two_step_least_squares():
    from splidar.detection._7b_edge_bands import _window_plane

    rng = np.random.default_rng(11)
    lab = rng.integers(-1, 3, size=(30, 30))
    rows, cols = np.mgrid[0:30, 0:30]
    depth = 40.0 + 0.4 * rows - 0.7 * cols + rng.normal(0, 0.5, lab.shape)
    depth[rng.random(lab.shape) < 0.15] += 12.0  # outliers the gate drops
    buf = np.empty((3, 21 * 21))
    for r, c in [(0, 0), (5, 17), (15, 15), (29, 3), (12, 29)]:
        for x, skip in [(0, True), (1, False), (2, True)]:
            got = _window_plane(lab, depth, r, c, 10, x, skip, 4.5, 0, buf)
            want = _plane_reference(lab, depth, r, c, 10, x, skip, 4.5)
            # tolerance: the normal equations against an orthogonal solver, well
            # conditioned windows of up to 441 points -> agreement to ~1e-12 bins
            assert got == pytest.approx(want, abs=1e-9)


def test_window_plane_median_when_collinear_and_nan_below_min_members():
    from splidar.detection._7b_edge_bands import _window_plane

    lab = -np.ones((9, 9), np.int64)
    depth = np.zeros((9, 9))
    for i, d in zip(range(1, 8), (3.0, 9.0, 4.0, 8.0, 5.0, 7.0, 6.0), strict=True):
        lab[i, i], depth[i, i] = 0, d  # members on the diagonal: no plane
    buf = np.empty((3, 81))
    assert _window_plane(lab, depth, 4, 4, 4, 0, False, 4.5, 0, buf) == 6.0
    assert np.isnan(_window_plane(lab, depth, 4, 4, 4, 0, False, 4.5, 8, buf))
    assert np.isnan(_window_plane(lab, depth, 4, 4, 4, 1, False, 4.5, 0, buf))  # none


def test_near_depths_same_on_any_number_of_threads():
    lam, ramp = _ramp_lam(3.4)
    counts = np.random.default_rng(5).poisson(lam).astype(np.uint16)
    wrong = ramp.copy()
    wrong[10, 12] += 5.0  # the near move of the parametrized test above, twice
    wrong[4, 5] += 5.0
    s = _surfaces(wrong)
    args = (s, np.asarray(s.depth_bin), np.arange(len(s)), counts, _background())
    one = near_depths(*args, fwhm=3.0, irf=IRF, half=5, n_jobs=1)
    assert one[0].size == 2
    for n_jobs in (2, 3):
        got = near_depths(*args, fwhm=3.0, irf=IRF, half=5, n_jobs=n_jobs)
        np.testing.assert_array_equal(got[0], one[0])
        np.testing.assert_array_equal(got[1], one[1])


def test_own_plane_kernel_same_on_any_split_of_rows():
    from splidar.detection._7b_edge_bands import _own_plane_kernel

    rng = np.random.default_rng(4)
    lab = np.repeat(np.repeat(rng.integers(-1, 8, size=(12, 10)), 6, axis=0), 5, axis=1)
    depth = 20.0 + 0.3 * np.arange(lab.shape[0])[:, None] + rng.normal(0, 0.5, lab.shape)
    R = lab.shape[0]
    whole = np.full(lab.shape, -1.0)
    _own_plane_kernel(lab, depth, 6, 4.5, whole, 0, R)
    assert np.isfinite(whole).sum() > 0.5 * (lab >= 0).sum()
    for cuts in ([0, 17, R], [0, 1, 30, 31, R]):
        parts = np.full(lab.shape, -1.0)
        for a, b in itertools.pairwise(cuts):
            _own_plane_kernel(lab, depth, 6, 4.5, parts, a, b)
        np.testing.assert_array_equal(parts, whole)


def test_band_depths_has_no_dark_band_rule():
    # dark_bands (dark29) removed in session 22: inside run-to-run noise on issue #15's
    # cells and Art, no move on the measured files (benchmarks/README.md, "abl30")
    from splidar.detection import _7b_edge_bands as eb

    assert not hasattr(eb, "DARK_BANDS") and not hasattr(eb, "dark_bands")


def test_windows_reads_lazy_counts_as_numpy():
    # counts neither NumPy nor Dask (a Zarr-like reader): each pixel's series is read
    counts = np.random.default_rng(5).poisson(_lam(2.0)).astype(np.uint16)
    rows, cols = np.array([0, 3, 7, 19]), np.array([2, 12, 23, 0])
    depth = np.array([30.0, 61.5, 2.0, 97.0])
    ref = _windows(counts, _background(), rows, cols, depth, IRF)
    got = _windows(_Lazy(counts), _background(), rows, cols, depth, IRF)
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a, b)
    assert ref[0].sum() > 0


def test_potts_weight_is_never_negative_when_labels_change_across_most_pairs():
    """Labels differing across every 4-neighbour pair (a 3 x 3 image of three regions,
    the steep 3 x 3 case) give weight 0, not -inf with a divide-by-zero warning."""
    import warnings

    from splidar.detection._7b_edge_bands import potts_weight

    stripes = np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert potts_weight(stripes) == 0.0
    smooth = np.zeros((6, 6), np.int64)
    smooth[:, 3:] = 1  # 6 of 60 pairs differ: log(0.9 / 0.1)
    assert potts_weight(smooth) == pytest.approx(np.log(9.0))


def test_likelihoods_memo_gives_the_values_computed_anew(monkeypatch):
    # a memo filled by one call, then read by another whose pixels partly repeat at the
    # same depths, partly at new depths (a memo keyed by the pixel alone would return
    # the old depth's value there)
    from splidar.detection import _7b_edge_bands as eb

    rng = np.random.default_rng(8)
    counts, rows, cols, dep = _every_pixel_two_depths(rng)
    memo = eb.LikelihoodMemo()
    first = eb._likelihoods(counts, _background(), rows, cols, dep, IRF, memo=memo)
    want = eb._likelihoods(counts, _background(), rows, cols, dep, IRF)
    np.testing.assert_array_equal(first, want)
    dep2 = dep.copy()
    dep2[::3, 1] += rng.uniform(0.5, 4, dep2[::3].shape[0])
    n = len(memo)
    got = eb._likelihoods(counts, _background(), rows, cols, dep2, IRF, memo=memo)
    want = eb._likelihoods(counts, _background(), rows, cols, dep2, IRF)
    np.testing.assert_array_equal(got, want)
    assert len(memo) == n + dep2[::3].shape[0] and (got[::3, 1] != first[::3, 1]).any()


def test_likelihood_memo_finds_what_the_former_dict_found():
    # keys met before (0.0 and -0.0 one key, as for the dict's floats), new ones, repeats
    # within one call, NaN depths (never found), pixels whose index alone would collide
    from splidar.detection._7b_edge_bands import LikelihoodMemo

    rng = np.random.default_rng(2)
    memo, ref = LikelihoodMemo(), {}
    for _ in range(4):
        n = 300
        r, c = rng.integers(0, 5, n), rng.integers(0, 2**20, n)
        d = rng.choice([0.0, -0.0, 1.5, 2.25, np.nan, 7.0], n)
        q = LikelihoodMemo.key(r, c, d)
        hit, pos = memo.find(q)
        keys = list(zip(r.tolist(), c.tolist(), d.tolist(), strict=True))
        np.testing.assert_array_equal(hit, [k in ref for k in keys])
        np.testing.assert_array_equal(memo.values[pos[hit]], [ref[k] for k in keys if k in ref])
        new = np.flatnonzero(~hit)
        v = rng.normal(size=new.size)
        v_of = {}  # one value per key (the values are functions of their key)
        for i, m in enumerate(new):
            v[i] = v_of.setdefault(keys[m], v[i])
        memo.add(q[new], v)
        ref.update((keys[m], v[i]) for i, m in enumerate(new))
        assert len(memo) == sum(1 for k in ref if not np.isnan(k[2]))


def _two_scans_plane(lab, depth, r, c, reach, x, skip_self, gate, min_m):
    """The former :func:`_window_plane` (two scans of the window), in Python: the
    reference, term by term."""
    R, C = lab.shape
    value, c0, c1, c2 = np.nan, 0.0, 0.0, 0.0
    r_lo, r_hi = max(r - reach, 0), min(r + reach + 1, R)
    c_lo, c_hi = max(c - reach, 0), min(c + reach + 1, C)
    for it in range(2):
        n = sr = sc = srr = src = scc = sd = srd = scd = 0.0
        for rr in range(r_lo, r_hi):
            for cc in range(c_lo, c_hi):
                if lab[rr, cc] != x or (skip_self and rr == r and cc == c):
                    continue
                u, v, z = float(rr - r), float(cc - c), float(depth[rr, cc])
                if it == 1 and abs(c0 + c1 * u + c2 * v - z) > gate:
                    continue
                n += 1.0
                sr += u
                sc += v
                srr += u * u
                src += u * v
                scc += v * v
                sd += z
                srd += u * z
                scd += v * z
        if it == 0 and n < min_m:
            return np.nan
        det3 = n * (srr * scc - src * src) + sr * (sc * src - sr * scc) + sc * (sr * src - srr * sc)
        if n < 3.0 or abs(det3) < 1e-9 * max(n, 1.0) ** 3:
            if it == 1:
                return value
            near = lab[r_lo:r_hi, c_lo:c_hi] == x
            if skip_self:
                near[r - r_lo, c - c_lo] = False
            return float(np.median(depth[r_lo:r_hi, c_lo:c_hi][near])) if near.any() else np.nan
        k00, k01, k02 = srr * scc - src * src, sc * src - sr * scc, sr * src - srr * sc
        k11, k12, k22 = n * scc - sc * sc, sr * sc - n * src, n * srr - sr * sr
        det = n * k00 + sr * k01 + sc * k02
        c0 = (k00 * sd + k01 * srd + k02 * scd) / det
        c1 = (k01 * sd + k11 * srd + k12 * scd) / det
        c2 = (k02 * sd + k12 * srd + k22 * scd) / det
        value = c0
    return value


def test_window_plane_one_scan_equals_the_two_scans_bit_for_bit():
    # the members kept from the first scan give the second fit's sums in the same order
    # (or, with none dropped, the first plane): the former kernel's values to the bit
    from splidar.detection._7b_edge_bands import _window_plane

    rng = np.random.default_rng(12)
    n_drop = n_same = 0
    for trial in range(6):
        lab = rng.integers(-1, 3, size=(25, 25))
        if trial % 2:
            lab[:] = 0  # whole windows of one region
        rows, cols = np.mgrid[0:25, 0:25]
        depth = 40.0 + 0.4 * rows - 0.7 * cols + rng.normal(0, 0.5, lab.shape)
        depth[rng.random(lab.shape) < (0.1 if trial < 4 else 0.0)] += 12.0
        buf = np.empty((3, 21 * 21))
        for r, c in rng.integers(0, 25, (25, 2)):
            for x, skip, min_m in [(0, True, 3), (1, False, 0), (2, True, 0)]:
                got = _window_plane(lab, depth, r, c, 10, x, skip, 4.5, min_m, buf)
                want = _two_scans_plane(lab, depth, r, c, 10, x, skip, 4.5, min_m)
                assert (np.isnan(got) and np.isnan(want)) or got == want
                near = (lab == x) & (np.abs(rows - r) <= 10) & (np.abs(cols - c) <= 10)
                near[r, c] &= not skip
                if near.sum() >= max(min_m, 3):  # the first plane's residuals
                    A = np.stack([np.ones(near.sum()), rows[near] - r, cols[near] - c], 1)
                    coef = np.linalg.lstsq(A, depth[near], rcond=None)[0]
                    off = np.abs(A @ coef - depth[near]) > 4.5
                    n_drop += bool(off.any())
                    n_same += not off.any()
    assert n_drop > 20 and n_same > 20


def _scipy_region_labels(depth, gate):
    """The former :func:`region_labels`: scipy's connected components over every pixel."""
    from scipy import sparse
    from scipy.sparse import csgraph

    R, C = depth.shape
    idx = np.arange(R * C).reshape(R, C)
    ok = np.isfinite(depth)
    a, b = [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        c0, c1 = max(0, -dc), C - max(0, dc)
        p = (slice(0, R - dr), slice(c0, c1))
        q = (slice(dr, R), slice(c0 + dc, c1 + dc))
        with np.errstate(invalid="ignore"):
            e = ok[p] & ok[q] & (np.abs(depth[p] - depth[q]) <= gate)
        a.append(idx[p][e])
        b.append(idx[q][e])
    a, b = np.concatenate(a), np.concatenate(b)
    g = sparse.coo_matrix((np.ones(a.size), (a, b)), shape=(R * C, R * C))
    _, lab = csgraph.connected_components(g.tocsr(), directed=False)
    return np.where(ok, lab.reshape(R, C), -1).astype(np.int64)


def test_region_kernel_numbers_the_components_as_scipy_did():
    # the union-find's labels equal scipy's connected components' to the number: the
    # order of each component's first pixel, NaN and inf pixels' numbers skipped
    from splidar.detection._7b_edge_bands import _region_kernel, region_labels

    rng = np.random.default_rng(21)
    for trial in range(200):
        R, C = (int(v) for v in rng.integers(1, 30, 2))
        depth = rng.normal(0, 3, (R, C)).cumsum(axis=trial % 2)
        depth[rng.random((R, C)) < rng.random() * 0.6] = np.nan
        if trial % 9 == 0:
            depth[rng.random((R, C)) < 0.3] = np.inf
        if trial % 13 == 0:
            depth[:] = np.nan
        gate = float(rng.choice([0.0, 1.0, 4.5, 100.0]))
        got = np.empty((R, C), np.int64)
        _region_kernel(depth, gate, got)
        assert np.array_equal(got, _scipy_region_labels(depth, gate))
        assert np.array_equal(region_labels(depth, gate), got)


@njit
def _every_step_kernel(y, g, b, n_iter, out):
    """The former ``_profile_llr_kernel``: all ``n_iter`` Newton steps (compiled by numba
    as the library's, so its arithmetic is the same)."""
    n, L, W = y.shape
    ya, ga, ba = np.empty(L * W), np.empty(L * W), np.empty(L * W)
    for i in range(n):
        G = slope = yg = 0.0
        m = 0
        for l in range(L):
            for t in range(W):
                G += g[i, l, t]
                if y[i, l, t] > 0:
                    slope += y[i, l, t] * g[i, l, t] / b[i, l, t]
                    yg += y[i, l, t] * g[i, l, t]
                    ya[m], ga[m], ba[m] = y[i, l, t], g[i, l, t], b[i, l, t]
                    m += 1
        if not slope > G:
            out[i] = 0.0
            continue
        s = max(yg / max(G, 1e-12), 1e-3)
        for _ in range(n_iter):
            d1, d2 = -G, 0.0
            for k in range(m):
                q = ya[k] * ga[k] / (ba[k] + s * ga[k])
                d1 += q
                d2 -= q * ga[k] / (ba[k] + s * ga[k])
            if d2 < 0:
                s = max(s - d1 / d2, 0.0)
        llr = -s * G
        for k in range(m):
            llr += ya[k] * np.log1p(s * ga[k] / ba[k])
        out[i] = max(llr, 0.0)


def test_profile_llr_stops_at_the_fixed_point_with_every_steps_value():
    # the Newton steps stop once one leaves s as it was: the values of all 30 steps to
    # the bit (strong, weak and absent returns, zero background, counts in one bin)
    rng = np.random.default_rng(22)
    n, L, W = 300, 2, 15
    g = np.abs(rng.normal(0, 1, (n, L, W))) * (rng.random((n, L, W)) < 0.7)
    g /= np.maximum(g.sum(axis=2, keepdims=True), 1e-12)
    b = rng.choice([1e-6, 0.01, 0.3, 2.0], (n, 1, 1)) * rng.uniform(0.5, 1.5, (n, L, W))
    y = rng.poisson(rng.choice([0.0, 0.05, 0.5, 5.0, 50.0], (n, 1, 1)) * g + b).astype(float)
    y[::7] = 0.0
    y[3::11, :, 1:] = 0.0
    for n_iter in (0, 1, 3, 30):
        got = profile_llr(y, g, b, n_iter=n_iter)
        want = np.empty(n)
        _every_step_kernel(y, g, b, n_iter, want)
        assert np.array_equal(got.view(np.uint64), want.view(np.uint64))
    assert (got > 0).sum() > 100


def test_most_members_counts_in_one_pass_as_sorting_did():
    # the label other than the own with most pixels in the window, ties to the lower
    # label: the same answer as counting the sorted labels (many labels, ties, none)
    from splidar.detection._7b_edge_bands import _most_members

    rng = np.random.default_rng(23)
    n_tie = n_none = 0
    for trial in range(60):
        lab = rng.integers(-1, int(rng.integers(1, 9)), size=(17, 19))
        if trial % 5 == 0:
            lab[:] = 0
        half = int(rng.integers(1, 6))
        seen = np.empty((2, (2 * half + 1) ** 2), np.int64)
        for r, c in rng.integers(0, 17, (12, 2)):
            own = int(lab[r, c])
            w = lab[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1]
            x, n = np.unique(w[(w >= 0) & (w != own)], return_counts=True)
            want = int(x[np.argmax(n)]) if x.size else -1  # argmax: the first (lowest)
            n_tie += int(x.size > 0 and (n == n.max()).sum() > 1)
            n_none += int(x.size == 0)
            assert _most_members(lab, r, c, half, own, seen) == want
    assert n_tie > 10 and n_none > 10


def test_pair_index_equals_unique_of_stacked_pairs():
    # one integer key per pair gives np.unique(axis=1)'s inverse (lexicographic ranks)
    from splidar.detection._7b_edge_bands import _pair_index

    rng = np.random.default_rng(29)
    for n, hi in ((0, 3), (1, 3), (50, 4), (400, 40), (300, 2_000_000)):
        a = rng.integers(-1, hi, n)
        b = np.maximum(a, rng.integers(-1, hi, n))
        want = np.unique(np.stack([a, b]), axis=1, return_inverse=True)[1].ravel()
        got = _pair_index(a, b)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, want)


def _shared_any_dense(s: Surfaces, depth, D, tol) -> np.ndarray:
    # the former rule: every slot's depth map, 8 shifted comparisons
    R, C = s.image_shape
    maps = np.full((int(s.slot.max()) + 1, R + 2, C + 2), np.nan)
    maps[s.slot, s.row + 1, s.col + 1] = depth
    out = np.zeros((R, C), np.int64)
    for dr, dc in itertools.product((-1, 0, 1), repeat=2):
        if dr or dc:
            nb = maps[:, 1 + dr : 1 + dr + R, 1 + dc : 1 + dc + C]
            with np.errstate(invalid="ignore"):
                out += np.any(np.abs(nb - D) <= tol, axis=0)
    return out


def test_shared_any_equals_the_dense_slot_maps_where_asked():
    from splidar.detection._7b_edge_bands import _shared_any

    rng = np.random.default_rng(31)
    R, C = SHAPE
    n_hit = 0
    for trial in range(8):
        one = _surfaces(rng.choice([20.0, 22.5, 40.0], SHAPE) + rng.normal(0, 1.0, SHAPE))
        two = rng.random(SHAPE) < 0.3  # a second slot in some pixels
        r2, c2 = np.nonzero(two)
        s = replace(
            one, row=np.r_[one.row, r2], col=np.r_[one.col, c2],
            slot=np.r_[one.slot, np.ones(r2.size, np.int64)],
        )  # fmt: skip
        depth = np.r_[one.depth_bin, rng.uniform(10.0, 50.0, r2.size)]
        D = np.where(rng.random(SHAPE) < 0.2, np.nan, rng.uniform(15.0, 45.0, SHAPE))
        where = rng.random(SHAPE) < (0.05 if trial % 2 else 0.6)
        where[0, :] |= trial == 3  # the border's pixels
        want = where & (_shared_any_dense(s, depth, D, 2.0) > 0)
        got = _shared_any(s, depth, D, 2.0, where)
        np.testing.assert_array_equal(got, want)
        n_hit += int(want.sum())
    assert n_hit > 50


def test_shared_at_and_inside_at_equal_the_whole_images_counts():
    # near_depths' guards at its offered pixels only: the whole image's counts there
    from splidar.detection._7b_edge_bands import _inside_at, _shared_at

    rng = np.random.default_rng(37)
    R, C = 17, 13
    for trial in range(6):
        depth = np.where(rng.random((R, C)) < 0.25, np.nan, rng.choice([0.0, 0.4, 3.0], (R, C)))
        lab = rng.integers(-1, 3, (R, C))
        zr, zc = np.nonzero(rng.random((R, C)) < (1.0 if trial == 0 else 0.3))
        pad, padl = np.pad(depth, 1, constant_values=np.nan), np.pad(lab, 1, constant_values=-1)
        shared, inside = np.zeros((R, C), np.int64), np.zeros((R, C), np.int64)
        for dr, dc in itertools.product((-1, 0, 1), repeat=2):
            if dr or dc:
                with np.errstate(invalid="ignore"):
                    shared += np.abs(pad[1 + dr : 1 + dr + R, 1 + dc : 1 + dc + C] - depth) <= 0.5
                inside += padl[1 + dr : 1 + dr + R, 1 + dc : 1 + dc + C] == lab
        inside = np.where(lab >= 0, inside, 0)
        np.testing.assert_array_equal(_shared_at(depth, 0.5, zr, zc), shared[zr, zc])
        np.testing.assert_array_equal(_inside_at(lab, zr, zc), inside[zr, zc])
        assert len(set(shared[zr, zc])) > 3 and len(set(inside[zr, zc])) > 3


def test_inside_plane_kernel_same_on_any_split_of_rows():
    # far_inside_depths' planes on threads: rows r0:r1 each, the whole image's values
    from splidar.detection._7b_edge_bands import _inside_plane_kernel, _solo_regions
    from splidar.detection._threads import on_parts

    rng = np.random.default_rng(41)
    depth = (
        np.where(np.arange(SHAPE[1]) < 12, 30.0, 62.0)[None, :] + 0.3 * np.arange(SHAPE[0])[:, None]
    )
    far = rng.random(SHAPE) < 0.08
    depth = np.where(far, rng.uniform(0.0, 99.0, SHAPE), depth)
    s = _surfaces(depth)
    D, gate, big = _solo_regions(s, s.depth_bin, np.arange(len(s)), 3.0)
    want = np.empty(SHAPE, np.int64), np.empty(SHAPE)
    _inside_plane_kernel(big, D, 4, gate, 5, *want, 0, SHAPE[0])
    assert np.isfinite(want[1]).sum() > 5
    for workers in (2, 3, 20):
        got = np.empty(SHAPE, np.int64), np.empty(SHAPE)
        on_parts(lambda i0, i1, got=got: _inside_plane_kernel(big, D, 4, gate, 5, *got, i0, i1),
                 SHAPE[0], workers)  # fmt: skip
        np.testing.assert_array_equal(got[0], want[0])
        assert got[1].tobytes() == want[1].tobytes()
