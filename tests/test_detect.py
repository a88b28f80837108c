"""Tests of splidar.detect (Algorithm 1 and surface extraction).

Small cubes with fixed seeds; statistical tolerances are justified where they appear.
"""

from __future__ import annotations

import numpy as np
import pytest

from splidar import Cube, SplidarError, gaussian_irf
from splidar.detection import PASSES, Detection, detect
from splidar.detection._filters import Correlator

IRF = gaussian_irf(3.0)  # FWHM 3 bins, 13 samples, peak on the centre


def _without(*names) -> tuple:
    """detect's clean-up passes without the named ones (the ablation of a pass)."""
    return tuple(p for p in PASSES if p not in names)


# the former dark=False: the dark-region and enclosed-hole passes both off
NO_DARK = _without("dark_regions", "enclosed")


def _cube(lam, rng=0) -> Cube:
    return Cube(np.random.default_rng(rng).poisson(lam).astype(np.uint16), irf=IRF)


def _returns(shape, T, depths, photons, bg):
    """Poisson mean (rows, cols, 1, T) with returns at fractional ``depths`` (per pixel)."""
    lam = np.full(shape + (1, T), float(bg))
    t = np.arange(T)
    sig = 3.0 / 2.3548
    for d, ph in zip(depths, photons, strict=True):
        d = np.broadcast_to(d, shape)[..., None]
        g = np.exp(-0.5 * ((t - d) / sig) ** 2)
        lam[:, :, 0, :] += ph * g / g.sum(axis=-1, keepdims=True)
    return lam


def _tilted(shape=(32, 32), T=120, photons=20.0, bg=0.05):
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]]
    depth = 30.0 + 1.3 * c + 0.4 * r  # fractional depths spanning ~60 bins
    return _returns(shape, T, [depth], [photons], bg), depth


# ----------------------------------------------------------------------------------------
# filters and background
# ----------------------------------------------------------------------------------------


def test_correlator_peak_lands_on_depth():
    corr = Correlator(IRF[None, :], 60)
    x = np.zeros((1, 60), np.float32)
    x[0, 30 - 6 : 30 + 7] = IRF  # a return whose peak lands on bin 30
    out = corr(x)
    assert out.argmax() == 30
    # normalised g keeps a flat level everywhere, window edges included (mirrored)
    np.testing.assert_allclose(corr(np.ones((1, 60), np.float32)), 1.0, atol=1e-5)


@pytest.mark.parametrize("shape", ["uniform", "decaying"])
def test_detect_background_close_to_truth(shape):
    from splidar.simulation import background_shape

    lam_t, _ = _tilted(T=160, bg=0.0)
    b_t = 0.3 * background_shape(shape, 160)
    det = detect(_cube(lam_t + b_t, rng=1), rng=0)
    bh = det.background.dense()[:, :, 0, :].mean(axis=(0, 1))
    err = (bh - b_t) / b_t.mean()
    # 32 x 32 pixels x 160 bins at 0.3 photons/bin: the pixel mean has a relative sd of
    # ~0.2 % per bin; returns in ~70 % of the coarse windows at some bins (the tilt
    # spread by the 11 x 11 box) leave a bias: measured <= 2 % on average and <= 13 %
    # of the mean level at worst
    assert abs(err.mean()) < 0.04
    assert np.abs(err).max() < 0.16
    assert det.background.spatial.shape == (32, 32, 1)
    assert det.background.temporal.shape == (1, 160)


def test_detect_saliency_peaks_at_true_depth():
    lam, depth = _tilted()
    det = detect(_cube(lam), rng=0)
    peak = det.saliency.argmax(axis=-1)
    # 20 photons per pixel: the saliency peak sits within 1 bin of the true depth away
    # from the image border (there the reflected coarse boxes of a tilted plane are
    # asymmetric and shift the coarse response by up to 2 bins)
    inner = (slice(5, -5), slice(5, -5))
    assert np.mean(np.abs(peak - depth)[inner] <= 1.0) > 0.97
    assert np.mean(np.abs(peak - depth) <= 2.0) > 0.97


# ----------------------------------------------------------------------------------------
# false-alarm calibration
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("level", "shape"), [(0.02, "uniform"), (2.0, "decaying")])
def test_detect_false_alarm_rate_matches_pfa(level, shape):
    from splidar.simulation import background_shape

    T = 200
    lam = np.broadcast_to(level * background_shape(shape, T), (48, 48, 1, T))
    det = detect(_cube(lam, rng=3), pfa=1e-3, rng=0)
    rate = det.mask.mean()
    # 460,800 voxels: ~460 expected false alarms (sampling sd ~5 %); the requirement is
    # a factor 2 (the plain gamma fit misses by 7-126x, ALGORITHM-NOTES)
    assert 0.5e-3 <= rate <= 2e-3
    assert det.null.method.startswith("empirical")
    assert det.null.pfa == 1e-3


def test_detect_threshold_varies_with_t_for_decaying_background():
    from splidar.simulation import background_shape

    lam = np.broadcast_to(1.0 * background_shape("decaying", 200), (32, 32, 1, 200))
    det = detect(_cube(lam, rng=4), rng=0)
    thr = np.broadcast_to(det.threshold, det.saliency.shape)
    # background falls 20-fold along t: its noise, hence the threshold, falls too
    assert thr[0, 0, 10] > 1.5 * thr[0, 0, -10]


# ----------------------------------------------------------------------------------------
# surfaces
# ----------------------------------------------------------------------------------------


def test_detect_resolves_two_surfaces_a_few_irf_widths_apart():
    shape = (24, 24)
    d1 = 50.3 + np.zeros(shape)
    d2 = d1 + 10.4  # 3.5 FWHM apart
    lam = _returns(shape, 140, [d1, d2], [15.0, 15.0], 0.02)
    det = detect(_cube(lam, rng=5), rng=0)
    s = det.surfaces
    n_per_px = np.bincount(s.row * shape[1] + s.col, minlength=shape[0] * shape[1])
    assert np.mean(n_per_px == 2) > 0.95
    two = n_per_px[s.row * shape[1] + s.col] == 2
    near = s.depth_bin[two & (s.slot == 0)]
    far = s.depth_bin[two & (s.slot == 1)]
    # 15 photons per return: the sub-bin depth has an sd of ~0.35 bin; the mean over
    # ~550 pixels must sit within 0.15 bin of the truth (integer depths would be 0.3-0.4 off)
    assert abs(near.mean() - 50.3) < 0.15
    assert abs(far.mean() - 60.7) < 0.15
    assert np.median(np.abs(near - 50.3)) < 0.5


def test_detect_respects_max_surfaces_and_slot_order():
    shape = (16, 16)
    lam = _returns(shape, 160, [40.0, 70.0, 100.0], [15.0, 15.0, 15.0], 0.02)
    det = detect(_cube(lam, rng=6), max_surfaces=2, rng=0)
    s = det.surfaces
    key = s.row * shape[1] + s.col
    assert np.bincount(key).max() <= 2
    assert s.n_slots == 2
    # slots in depth order within each pixel
    for k in np.unique(key)[:50]:
        sel = key == k
        order = np.argsort(s.slot[sel])
        assert np.all(np.diff(s.depth_bin[sel][order]) > 0)
    det1 = detect(_cube(lam, rng=6), max_surfaces=1, rng=0)
    assert np.bincount(det1.surfaces.row * shape[1] + det1.surfaces.col).max() == 1


def test_detect_scale_selection_and_histograms():
    lam, depth = _tilted()
    det = detect(_cube(lam), rng=0)
    s = det.surfaces
    Q = len(det.scales)
    assert s.scale_index.min() >= 1 and s.scale_index.max() <= Q - 1  # eq:scale_sel, q in 2..Q
    assert s.histograms.shape[:3] == (len(s), Q, 1)
    assert np.all(s.histograms >= 0)
    # zero outside the support
    W = s.histograms.shape[-1]
    tt = s.offset[:, None] + np.arange(W)
    outside = (tt < s.start[:, None]) | (tt >= s.stop[:, None])
    assert np.all(s.histograms[:, :, 0, :][np.broadcast_to(outside[:, None], (len(s), Q, W))] == 0)
    np.testing.assert_allclose(s.signal, s.histograms.sum(axis=-1), rtol=1e-4, atol=1e-4)
    # own-pixel counts minus background ~ 20 photons per surface on average
    assert 15 < s.net_counts[:, 0].mean() < 25
    p = det.points
    err = p.depth_bin - depth[p.row, p.col]
    assert np.mean(np.abs(err) < 1.0) > 0.95
    assert np.all(p.layer == s.slot)


def test_detect_with_one_scale_uses_it():
    lam, _ = _tilted()
    det = detect(_cube(lam), scales=(3,), rng=0)
    assert det.scales == (3,)
    assert np.all(det.surfaces.scale_index == 0)
    assert len(det.surfaces) > 0.9 * 32 * 32


def test_detect_thin_net_few_false_surfaces():
    from splidar.scenes import two_layer_scene

    scene = two_layer_scene((40, 40), n_bins=160)
    sim = scene.simulate(ppp=10, sbr=1, background="uniform", rng=0)
    from splidar.metrics import evaluate

    auto = evaluate(detect(sim.cube, rng=0).points, sim.truth, tau=3)
    none = evaluate(detect(sim.cube, presence="none", rng=0).points, sim.truth, tau=3)
    # the presence check removes most of what coarse scales plant beside the strands
    # while keeping the true surfaces (measured on 64 x 64, two seeds: F_true 0.944 and
    # 0.052 false surfaces per true one with the check, 0.899 and 0.566 without)
    assert auto.f_false_rate < 0.3 * none.f_false_rate
    assert auto.f_true > 0.9


def test_detect_adaptive_presence_keeps_dim_extended_surface():
    # a flat plane of 0.5 signal photons per pixel: its 3 x 3 response cannot reach
    # presence_z = 3 (predicted z ~ 2), so the fixed z test ("auto") drops about half of it
    # (measured: 53 % kept, seeds 0 and 1); the adaptive test only asks a local response
    # presence_z below the neighbourhood's prediction and keeps it (measured 86 % and
    # 96 %, with 12 and 19 wrong-depth points of 1024)
    lam = _returns((32, 32), 120, [60.0], [0.5], 0.04)
    cube = _cube(lam, rng=0)
    det = detect(cube, presence="adaptive", rng=0)
    ok = np.abs(det.points.depth_bin - 60.0) <= 3
    assert ok.sum() > 0.75 * 32 * 32
    assert (~ok).sum() < 0.03 * 32 * 32
    fixed = np.abs(detect(cube, presence="auto", rng=0).points.depth_bin - 60.0) <= 3
    assert fixed.sum() < ok.sum()


def test_detect_result_fields_and_reduction():
    lam, _ = _tilted()
    cube = _cube(lam)
    det = detect(cube, rng=0)
    assert isinstance(det, Detection)
    assert det.saliency.shape == (32, 32, 120) and det.saliency.dtype == np.float32
    assert det.mask.shape == (32, 32, 120) and det.mask.dtype == bool
    r = det.reduction
    assert r.n_voxels == int(det.mask.sum())
    assert 0 < r.voxel_fraction < 0.2
    # the mask keeps far more photons than voxels (signal is concentrated)
    assert r.photon_fraction > 3 * r.voxel_fraction
    assert set(det.timings) >= {"null", "total"}
    assert det.options["pfa"] == 1e-3
    np.testing.assert_allclose(det.weights.sum(), 1.0)


def test_detect_is_reproducible_with_rng():
    lam, _ = _tilted(shape=(16, 16))
    cube = _cube(lam)
    a, b = detect(cube, rng=1), detect(cube, rng=1)
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_array_equal(a.surfaces.depth_bin, b.surfaces.depth_bin)


def test_detect_steep_slope_keeps_own_pixel_depth():
    # the single-surface scene's ramp (4.9 bins per row) with a dark disc on it: beside
    # the disc the boxes weigh the bright rows more and their peak drifts 10-15 bins off
    # the own return; bright pixels must keep their own depth (PPP 50, SBR 10)
    from splidar.metrics import evaluate
    from splidar.scenes import single_surface_scene

    sim = single_surface_scene((64, 64)).simulate(ppp=50, sbr=10, rng=0)
    m = evaluate(detect(sim.cube, rng=0).points, sim.truth, tau=3)
    assert m.f_true >= 0.99  # 0.981 when windows stayed on the coarse peak


def test_detect_dark_restores_dim_stripe_beside_bright_rows():
    # 8 rows at 0.4 signal photons per pixel across a plane of 6: the local presence
    # test and the spill-over check take the stripe for the bright rows' spread and drop
    # a third of it (measured, seeds 0-2: 198-232 of 320 found); pooled, the stripe's own
    # counts are significant and the dark-region pass restores it (308-316 of 320) with
    # no more wrong-depth points (2-26 with and without)
    shape = (40, 40)
    ph = np.full(shape, 6.0)
    ph[15:23] = 0.4
    cube = _cube(_returns(shape, 120, [60.0], [ph[..., None]], 0.04), rng=0)
    res = {}
    for dark in (False, True):
        det = detect(cube, rng=0, passes=PASSES if dark else NO_DARK)
        p = det.points
        ok = np.abs(p.depth_bin - 60.0) <= 3
        hit = np.zeros(shape, bool)
        hit[p.row[ok], p.col[ok]] = True
        res[dark] = (int(hit[15:23].sum()), int((~ok).sum()), det)
    assert res[False][0] < 0.8 * 320
    assert res[True][0] >= 0.93 * 320
    assert res[True][1] <= res[False][1] + 3
    assert res[True][2].options["n_dark"] > 0 and res[False][2].options["n_dark"] == 0


def test_detect_dark_restores_enclosed_pixels_with_no_own_photons():
    # a flat surface of 8 photons per pixel; 12 scattered pixels lose every photon (a
    # return of 8 x 0.76 photons in the half-maximum window leaves none with probability
    # 0.2 %, so the own-pixel check rejects them): their neighbours enclose them and the
    # enclosed-pixel restore keeps them; without the dark passes they stay missed
    shape = (32, 32)
    ph = np.full(shape, 8.0)
    lam = _returns(shape, 120, [60.0], [ph[..., None]], 0.02)
    y = np.random.default_rng(4).poisson(lam)
    holes = [(r, c) for r in (6, 12, 18, 24) for c in (7, 15, 23)]
    for r, c in holes:
        y[r, c] = 0
    cube = Cube(y, irf=IRF[None], bin_width_ps=100.0)
    hits, wrong = {}, {}
    for dark in (False, True):
        p = detect(cube, rng=0, passes=PASSES if dark else NO_DARK).points
        ok = np.abs(p.depth_bin - 60.0) <= 3
        found = set(zip(p.row[ok].tolist(), p.col[ok].tolist(), strict=True))
        hits[dark] = sum((r, c) in found for r, c in holes)
        wrong[dark] = int((~ok).sum())
    # measured, seeds 4-6: 0 of 12 without, 12 of 12 with; wrong-depth points (2-22 by
    # seed, noise peaks elsewhere) the same with and without
    assert hits[False] <= 4, hits
    assert hits[True] == len(holes)
    assert wrong[True] <= wrong[False]


def test_detect_dark_leaves_net_spread_rejected():
    # beside the net's strands the spread has no photons of its own at the net's depth:
    # pooling it does not restore it (64 x 64, 2 seeds: false surfaces 2.6 % of true with
    # and without the pass)
    from splidar.metrics import evaluate
    from splidar.scenes import two_layer_scene

    sim = two_layer_scene((40, 40), n_bins=160).simulate(ppp=10, sbr=1, rng=0)
    on = evaluate(detect(sim.cube, rng=0).points, sim.truth, tau=3)
    off = evaluate(detect(sim.cube, rng=0, passes=NO_DARK).points, sim.truth, tau=3)
    assert on.f_false <= off.f_false + 0.005 * on.n_true
    assert on.f_true >= off.f_true


def test_detect_refine_pools_depth_on_dim_plane_keeps_own_at_edge():
    # a tilted plane at 2 photons per pixel: the own pixel's peak is too noisy for tau =
    # 3 bins, the pooled scales are not (the intersection of confidence intervals takes
    # them: 978-999 of 1024 within 3 bins over seeds 0-2, 969-986 with the previous
    # own-pixel-when-z >= 3 rule)
    lam, depth = _tilted(photons=2.0, bg=0.05)
    p = detect(_cube(lam, rng=0), rng=0).points
    err = np.abs(p.depth_bin - depth[p.row, p.col])
    assert (err <= 3).sum() >= 0.94 * 1024
    assert err[err <= 3].mean() < 0.8
    # a 6-bin step at 40 photons per pixel: the boxes across the edge mix both depths;
    # bright pixels beside it keep their own (measured: mean error 0.10 bins)
    shape = (32, 32)
    step = np.where(np.arange(32)[None, :] < 16, 50.0, 56.0) + np.zeros(shape)
    p = detect(_cube(_returns(shape, 120, [step], [40.0], 0.02), rng=0), rng=0).points
    err = np.abs(p.depth_bin - step[p.row, p.col])
    edge = (p.col >= 13) & (p.col <= 18) & (err < 3)
    assert edge.sum() >= 0.95 * 6 * 32
    assert err[edge].mean() < 0.3


@pytest.mark.parametrize("store_boxes", [True, False])
def test_detect_histograms_match_box_filter_reference(store_boxes, monkeypatch):
    # independent reference: scipy's uniform_filter of the correlated cube minus bhat,
    # whether the box means come from the saliency pass or are summed per candidate
    from scipy import ndimage

    import splidar.detection._4_map as map_stage

    monkeypatch.setattr(map_stage, "_store_boxes", lambda *a: store_boxes)
    lam, _ = _tilted(shape=(20, 24), T=100)
    lam[::3, ::2, 0, 70] += 4.0  # a second, sparse return in some pixels
    cube = _cube(lam, rng=3)
    det = detect(cube, rng=0, presence="none")
    s = det.surfaces
    c = Correlator(cube.irf, cube.n_bins)(cube.counts)[:, :, 0, :]  # (R, C, T)
    bh = det.background.dense()[:, :, 0, :]  # eq:background_3 (clipped at 0)
    W = s.histograms.shape[-1]
    tt = s.offset[:, None] + np.arange(W)
    inside = (tt >= s.start[:, None]) & (tt < s.stop[:, None])
    for q, k in enumerate(det.scales):
        box = ndimage.uniform_filter(c.astype(np.float64), size=(k, k, 1), mode="reflect")
        resp = box[s.row[:, None], s.col[:, None], tt] - bh[s.row[:, None], s.col[:, None], tt]
        ref = np.where(inside, np.maximum(resp, 0), 0)  # eq:background_final
        # float32 box sums vs float64 reference: 1e-5 relative to the response scale
        np.testing.assert_allclose(s.histograms[:, q, 0], ref, rtol=1e-4, atol=1e-5)
    raw = cube.counts[s.row[:, None], s.col[:, None], 0, tt]
    np.testing.assert_array_equal(s.counts[:, 0], np.where(inside, raw, 0).sum(axis=1))


def test_store_boxes_depends_on_sizes_only():
    from splidar.detection._4_map import _store_boxes

    sc = np.array([1, 3, 7, 11])
    assert _store_boxes(sc, 13, 164)  # Art-size: few bins, keep the box means
    assert not _store_boxes(sc, 13, 1500)  # long histograms: sum about candidates
    assert not _store_boxes(np.array([1]), 13, 10)  # no box above 1 pixel


def test_threshold_field_indexes_like_the_array_it_stands_for():
    from splidar.detection._threshold import ThresholdField

    rng = np.random.default_rng(4)
    sp = rng.random((7, 5, 2)).astype(np.float32)
    dev = (rng.random((2, 9)) - 0.5).astype(np.float32)
    f = ThresholdField(sp, dev, np.array([0.2, 0.8, 1.5]), np.array([1.0, 2.0, 2.5]))
    full = np.asarray(f)
    assert f.shape == full.shape == (7, 5, 9) and np.ndim(f) == 3 and full.dtype == np.float32
    # the level is sum_l max(b + dev, 0) and the table is interpolated (clamped at the ends)
    level = np.maximum(sp[..., None] + dev[None, None], 0).sum(axis=2)
    want = np.interp(level, [0.2, 0.8, 1.5], [1.0, 2.0, 2.5]).astype(np.float32)
    np.testing.assert_allclose(full, want, rtol=1e-6)
    keys = [np.s_[2:5], np.s_[::2], np.s_[::-1], np.s_[5:1:-2], np.s_[3], np.s_[-1, 2],
            np.s_[1:3, 2:4, ::3], np.s_[...], np.s_[[1, 3]], np.s_[0:0]]  # fmt: skip
    for key in keys:
        np.testing.assert_array_equal(f[key], full[key])
    assert (full + 0.1 > f).all()  # comparisons go through np.asarray
    # single pixels, computed alone: the same values as the whole field
    r, c = np.array([0, 6, 3, 3]), np.array([4, 0, 2, 2])
    np.testing.assert_array_equal(f.pixels(r, c), full[r, c])
    assert f.pixels([], []).shape == (0, 9)


@pytest.mark.parametrize(
    ("spatial", "dev", "xs", "ys", "match"),
    [
        (np.ones((3, 4)), np.zeros((1, 5)), [0.0, 1.0], [1.0, 2.0], "spatial"),
        (np.ones((3, 4, 2)), np.zeros((1, 5)), [0.0, 1.0], [1.0, 2.0], "dev"),
        (np.ones((3, 4, 1)), np.zeros((1, 5)), [0.0, 1.0], [1.0], "levels"),
    ],
)
def test_threshold_field_rejects_bad_inputs(spatial, dev, xs, ys, match):
    from splidar.detection import ThresholdField

    with pytest.raises(SplidarError, match=match):
        ThresholdField(spatial, dev, np.asarray(xs), np.asarray(ys))


def test_detect_same_result_whatever_blocks_and_threads():
    lam, _ = _tilted(shape=(40, 20), T=90)
    lam[..., :] += np.linspace(0.0, 0.2, 40)[:, None, None, None]  # spatially varying bg
    cube = _cube(lam, rng=4)
    ref = detect(cube, rng=2, n_jobs=1, block_rows=40)
    # a spatially varying level: the threshold is per voxel, kept as its factors
    assert np.ndim(ref.threshold) == 3 and ref.threshold.shape == (40, 20, 90)
    assert type(ref.threshold).__name__ == "ThresholdField"
    np.testing.assert_array_equal(ref.mask, ref.saliency > ref.threshold)
    for kw in (dict(n_jobs=1, block_rows=6), dict(n_jobs=3, block_rows=7), dict(n_jobs=2)):
        other = detect(cube, rng=2, **kw)
        np.testing.assert_array_equal(other.saliency, ref.saliency)
        np.testing.assert_array_equal(other.mask, ref.mask)
        np.testing.assert_array_equal(other.threshold, ref.threshold)
        np.testing.assert_array_equal(other.surfaces.depth_bin, ref.surfaces.depth_bin)
        np.testing.assert_array_equal(other.surfaces.histograms, ref.surfaces.histograms)
        assert other.reduction == ref.reduction


@pytest.mark.parametrize("strip", [1, 3, 7])
def test_detect_same_result_whatever_column_strips(monkeypatch, strip):
    # the saliency kernel filters strips of columns (each strip's rows in turn); the box
    # filters' running column sums carry over between strips: the same bits as one pass
    from splidar.detection import _2_saliency

    lam, _ = _tilted(shape=(16, 20), T=90)
    cube = _cube(lam, rng=4)
    ref = detect(cube, rng=2, n_jobs=1)
    monkeypatch.setattr(_2_saliency, "STRIP_COLS", strip)
    other = detect(cube, rng=2, n_jobs=2, block_rows=5)
    np.testing.assert_array_equal(other.saliency, ref.saliency)
    np.testing.assert_array_equal(other.mask, ref.mask)
    np.testing.assert_array_equal(other.background.spatial, ref.background.spatial)
    for k, v in vars(ref.surfaces).items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(getattr(other.surfaces, k), v, err_msg=k)


# ----------------------------------------------------------------------------------------
# bad inputs
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_cube():
    return _cube(np.full((8, 8, 1, 40), 0.1))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(scales=(1, 2, 7)), "odd"),
        (dict(scales=(0, 3)), "odd"),
        (dict(scales=(1.5, 3)), "scales"),
        (dict(scales=()), "empty"),
        (dict(scales=(3, 3)), "repeat"),
        (dict(weights=[0.5, 0.5]), "one value per scale"),
        (dict(weights=[0.5, 0.5, 0.5, 0.5]), "sum to 1"),
        (dict(weights=[1.5, -0.5, 0, 0]), "non-negative"),
        (dict(pfa=0.0), "pfa"),
        (dict(pfa=1.0), "pfa"),
        (dict(max_surfaces=0), "max_surfaces"),
        (dict(surface_pfa=2.0), "surface_pfa"),
        (dict(null="normal"), "null"),
        (dict(presence="maybe"), "presence"),
        (dict(passes="slopes"), "wrap it in a tuple"),
        (dict(passes=("slopes", "dark")), "unknown pass"),
        (dict(passes=3), "sequence of pass names"),
        (dict(block_rows=0), "block_rows"),
    ],
)
def test_detect_bad_options_raise(small_cube, kwargs, match):
    with pytest.raises(SplidarError, match=match):
        detect(small_cube, **kwargs)


def test_detect_rejects_non_cube():
    with pytest.raises(SplidarError, match="Cube"):
        detect(np.zeros((4, 4, 10)))


def test_detect_rejects_irf_longer_than_t():
    # Cube itself refuses such an IRF; detect re-checks cubes built around validation
    with pytest.raises(SplidarError, match="longer"):
        Cube(np.zeros((4, 4, 5), np.uint16), irf=IRF)


def test_detect_rejects_fewer_than_three_bins():
    # T = 2 used to fail inside NumPy's gradient; the message names the fix instead
    cube = Cube(np.ones((3, 3, 2), np.uint16), irf=np.array([1.0]))
    with pytest.raises(SplidarError, match="at least 3 time bins.*T = 2"):
        detect(cube)


# ----------------------------------------------------------------------------------------
# spill-over check (_quality.py)
# ----------------------------------------------------------------------------------------


def _table(depth, counts, bg=0.05, W=15):
    """Candidate table of one candidate per pixel of a (R, C) image: ``depth`` (R, C)
    (NaN: none) and each pixel's own photons ``counts`` (R, C) at its depth."""
    from splidar.irf import gaussian_irf as girf

    g = np.asarray(girf(3.0), float)
    rr, cc = np.nonzero(np.isfinite(depth))
    S = rr.size
    own = np.zeros((S, 1, W), np.int32)
    centre = W // 2
    for i, n in enumerate(counts[rr, cc]):
        # the photons spread like the IRF around the window's centre (integer counts)
        own[i, 0, centre - 1 : centre + 2] = np.round(n * np.array([0.25, 0.5, 0.25]))
    surf = dict(
        row=rr,
        col=cc,
        depth_bin=depth[rr, cc].astype(float),
        offset=np.round(depth[rr, cc]).astype(np.int64) - centre,
        own_counts=own,
        own_background=np.full((S, 1, W), bg, np.float32),
        image_shape=depth.shape,
    )
    return surf, g[None], np.array([g.argmax()])


def test_reject_spill_over_rejects_spread_beside_strand():
    from splidar.detection._quality import reject_spill_over

    # a bright strand (row 2, 8 photons) at depth 40; rows 1 and 3 hold empty candidates
    # at the strand's depth (the coarse scales' spread): a pixel with no photons where a
    # return of 8 would bring ~8 has log-ratio ~ -8 < 0; the strand pixels are enclosed
    # along the strand (west/east pair at their depth) and kept
    depth = np.full((5, 6), np.nan)
    depth[1:4] = 40.0
    counts = np.zeros((5, 6))
    counts[2] = 8
    surf, g, pk = _table(depth, counts)
    rej = reject_spill_over(
        surf, np.ones(surf["row"].size, bool), irf=g, peak=pk, fwhm=3.0, llr_level=0.0, max_iter=3
    )
    on_strand = surf["row"] == 2
    assert not rej[on_strand].any()
    assert rej[~on_strand].all()


def test_reject_spill_over_keeps_enclosed_and_supported_candidates():
    from splidar.detection._quality import reject_spill_over

    # a plane at depth 40 over the whole 5 x 5 image with 8 photons per pixel except an
    # empty pixel inside it (enclosed: its neighbours interpolate to its depth, so the
    # pooled evidence decides, not its own counts) and a corner pixel (not enclosed: no
    # opposite pair inside the image) with 4 photons (half the source: the log-ratio of
    # a return of 8 is about 4 log(1 + 8 g / b) - 8 >> 0)
    depth = np.full((5, 5), 40.0)
    counts = np.full((5, 5), 8.0)
    counts[2, 2] = 0
    counts[4, 4] = 4
    surf, g, pk = _table(depth, counts)
    keep = np.ones(surf["row"].size, bool)
    rej = reject_spill_over(surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0)
    assert not rej.any()
    # an empty corner pixel is rejected (log-ratio about -8)
    counts[0, 0] = 0
    surf, g, pk = _table(depth, counts)
    rej = reject_spill_over(surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0)
    assert rej.sum() == 1 and (surf["row"][rej], surf["col"][rej]) == (0, 0)
    # a candidate not in keep is neither tested nor a source
    keep[(surf["row"] == 0) & (surf["col"] == 0)] = False
    rej = reject_spill_over(surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0)
    assert not rej.any()


def test_reject_spill_over_same_on_any_number_of_threads(monkeypatch):
    from splidar.detection import _quality
    from splidar.detection._quality import reject_spill_over

    # strands and spread of random brightness at a few depths: several passes, and the
    # first pass's log-ratios split between threads (parts of 40 candidates)
    rng = np.random.default_rng(7)
    depth = rng.choice([30.0, 31.0, 60.0], size=(16, 18))
    depth[rng.random(depth.shape) < 0.1] = np.nan
    counts = rng.choice([0.0, 1.0, 4.0, 8.0], size=depth.shape)
    surf, g, pk = _table(depth, counts)
    keep = np.ones(surf["row"].size, bool)
    one = reject_spill_over(surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, max_iter=18)
    monkeypatch.setattr(_quality, "_SPILL_PART", 40)
    for n_jobs in (2, 3):
        rej = reject_spill_over(
            surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, max_iter=18, n_jobs=n_jobs
        )
        np.testing.assert_array_equal(rej, one)
    assert 0 < one.sum() < one.size


def test_reject_spill_over_strip_of_spread_does_not_enclose_itself():
    from splidar.detection._quality import reject_spill_over

    # a bright block (columns 0-2, 8 photons) at depth 40 beside a depth edge; column 3
    # holds its own surface at depth 80 (8 photons) and the coarse boxes' spread at 40
    # (no photons) except two pixels with 4 photons (own counts that favour the return:
    # not suspects). Between them the spread is enclosed along the column by its own
    # members: kept by the former test (any pair encloses), rejected when beside the
    # pixel's own surface a pair needs a member whose counts do not reject the return
    # (log-ratio >= -3; an empty pixel gives about -8)
    depth = np.full((12, 6), np.nan)
    depth[:, :4] = 40.0
    counts = np.zeros((12, 6))
    counts[:, :3] = 8
    counts[[3, 8], 3] = 4
    near, g, pk = _table(depth, counts)
    back = np.full((12, 6), np.nan)
    back[:, 3] = 80.0
    far, _, _ = _table(back, np.full((12, 6), 8.0))
    surf = {k: near[k] if k == "image_shape" else np.concatenate([near[k], far[k]]) for k in near}
    n_near = near["row"].size
    keep = np.ones(surf["row"].size, bool)
    ghost = np.zeros(surf["row"].size, bool)
    ghost[:n_near] = (near["col"] == 3) & (counts[near["row"], near["col"]] == 0)
    old = reject_spill_over(surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, max_iter=12)
    new = reject_spill_over(
        surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, vouch_level=-3.0, max_iter=12
    )
    between = ghost & (surf["row"] > 3) & (surf["row"] < 8)
    assert not old[between].any() and old[ghost & ~between].all()
    assert new.tolist() == ghost.tolist()
    # a pixel's only candidate vouches for its neighbours (a dim surface behind a
    # strand): without the surface at 80 in rows 5 and 7, their spread encloses row 6's
    drop = np.zeros(surf["row"].size, bool)
    drop[n_near:] = np.isin(far["row"], [5, 7])
    some = reject_spill_over(
        surf, keep & ~drop, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, vouch_level=-3.0,
        max_iter=12,
    )  # fmt: skip
    assert some.tolist() == old.tolist()
    # without the surface at 80 the spread is the pixels' only candidate: the former
    # rule (a dim surface's pixels enclose one another)
    keep[n_near:] = False
    alone = reject_spill_over(
        surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, vouch_level=-3.0, max_iter=12
    )
    assert alone.tolist() == old.tolist()


def test_detect_spill_over_removes_net_spread():
    from splidar.metrics import evaluate
    from splidar.scenes import two_layer_scene

    scene = two_layer_scene((40, 40), n_bins=160)
    sim = scene.simulate(ppp=10, sbr=1, background="uniform", rng=1)
    on = detect(sim.cube, rng=0)
    off = detect(sim.cube, passes=_without("spill_over"), rng=0)
    m_on = evaluate(on.points, sim.truth, tau=3)
    m_off = evaluate(off.points, sim.truth, tau=3)
    # measured here: F_true 0.943 -> 0.938, false surfaces 342 -> 97 (321 rejected as
    # spill-over); on 64 x 64 (seeds [0, 7], [1, 7]) 0.955 / 0.107 -> 0.955 / 0.037 per
    # true one. Asserted: at least half of the false surfaces go, < 1 % of true ones
    assert on.options["n_spill_over"] > 0
    assert m_on.f_false < 0.5 * m_off.f_false
    assert m_on.f_true > m_off.f_true - 0.01


def test_reject_isolated_shared_neighbours_match_dense_reference():
    # the numba neighbour search against the dense-array form it replaced
    from splidar.detection import _quality

    rng = np.random.default_rng(11)
    R, C, n = 17, 13, 600
    row, col = rng.integers(0, R, n), rng.integers(0, C, n)
    d = rng.integers(20, 60, n).astype(float) + rng.random(n)
    keep = rng.random(n) < 0.7
    idx = np.flatnonzero(keep)
    D, _ = _quality._dense(row[idx], col[idx], (R, C), d[idx], np.nan)
    r1, c1 = row[idx] + 1, col[idx] + 1
    want = np.zeros(idx.size, bool)
    for dr, dc in _quality._NEIGHBOURS:
        want |= np.any(np.abs(D[r1 + dr, c1 + dc] - d[idx][:, None]) <= 3.0, axis=1)
    want_own = np.isfinite(D[r1, c1]).sum(axis=1)
    pix = row[idx] * C + col[idx]
    order = np.argsort(pix, kind="stable")
    starts = np.searchsorted(pix[order], np.arange(R * C + 1))
    got = np.zeros(idx.size, bool)
    own = np.zeros(idx.size, np.int64)
    _quality._shared_kernel(
        row[idx].astype(np.int64), col[idx].astype(np.int64), d[idx], order, starts, R, C,
        3.0, got, own,
    )  # fmt: skip
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(own, want_own)
    assert 0 < got.sum() < got.size


def test_reject_isolated_needs_significant_own_counts():
    from splidar.detection._quality import reject_isolated

    # three candidates at depth 40 in a 5 x 5 image: two neighbours (each shares the
    # other's depth: never tested) and one alone at (4, 4)
    depth = np.full((5, 5), np.nan)
    depth[0, 0] = depth[0, 1] = depth[4, 4] = 40.0
    counts = np.zeros((5, 5))
    surf, _, _ = _table(depth, counts, bg=0.05)  # no photons anywhere
    keep = np.ones(3, bool)
    alone = (surf["row"] == 4) & (surf["col"] == 4)
    rej = reject_isolated(surf, keep, fwhm=3.0, pfa=0.01)
    assert rej.tolist() == alone.tolist()
    # 4 photons (_table rounds 0.25 / 0.5 / 0.25 of them) over a background of
    # B = 15 x 0.05 = 0.75: P(N >= 4) = 0.0073 <= 0.01, kept; with the look-elsewhere
    # correction over T = 200 bins (200 / 15 windows) it is 0.093 > 0.01, rejected
    counts[4, 4] = 4
    surf, _, _ = _table(depth, counts, bg=0.05)
    assert not reject_isolated(surf, keep, fwhm=3.0, pfa=0.01).any()
    rej = reject_isolated(surf, keep, fwhm=3.0, pfa=0.01, n_bins=200)
    assert rej.tolist() == alone.tolist()
    # 8 photons: P(N >= 8 | 0.75) = 1.3e-6, significant even after the correction
    counts[4, 4] = 8
    surf, _, _ = _table(depth, counts, bg=0.05)
    assert not reject_isolated(surf, keep, fwhm=3.0, pfa=0.01, n_bins=200).any()


def test_reject_spill_over_matches_numpy_reference_on_random_tables():
    # the numba kernel against the vectorised definition (spill_over_features), iterated
    from splidar.detection._quality import reject_spill_over, spill_over_features

    g = np.asarray(IRF, float)[None]
    pk = np.array([int(g.argmax())])
    rng = np.random.default_rng(11)
    for _ in range(5):
        R, C, W = 12, 12, 11
        row = np.repeat(np.arange(R * C) // C, 2)
        col = np.repeat(np.arange(R * C) % C, 2)
        present = rng.random(row.size) < 0.7
        row, col = row[present], col[present]
        depth = rng.choice([20.0, 21.5, 40.0], row.size) + rng.normal(0, 0.7, row.size)
        cnt = rng.poisson(rng.choice([0.05, 0.6], (row.size, 1, 1)), (row.size, 1, W))
        cnt = cnt.astype(np.int32)
        bkg = np.full((row.size, 1, W), 0.05, np.float32)
        bkg[:, :, :2] = 0.0  # outside the support
        surf = dict(
            row=row,
            col=col,
            depth_bin=depth,
            offset=np.round(depth).astype(int) - W // 2,
            own_counts=cnt,
            own_background=bkg,
            image_shape=(R, C),
        )
        keep = rng.random(row.size) < 0.9
        for vouch in (-np.inf, -3.0, 0.0):  # the former test, detect's level, strict
            ref = np.zeros(row.size, bool)
            for _ in range(24):
                f = spill_over_features(
                    surf, keep & ~ref, irf=g, peak=pk, fwhm=3.0, llr_level=0.0,
                    vouch_level=vouch,
                )  # fmt: skip
                new = keep & ~ref & f["has_source"] & ~f["enclosed"] & (f["llr_source"] < 0.0)
                if not new.any():
                    break
                ref |= new
            got = reject_spill_over(
                surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, vouch_level=vouch,
                max_iter=24,
            )  # fmt: skip
            assert ref.any()
            np.testing.assert_array_equal(got, ref)


def test_reject_spill_over_matches_numpy_reference_pass_by_pass():
    # after the first pass the kernel tests again only the candidates near the last
    # pass's rejections (a 4-neighbour's pair member may have turned mute: seed 14 with
    # vouch_level 1 catches a kernel that forgets those): after every number of
    # passes, the full test's result
    from splidar.detection._quality import reject_spill_over, spill_over_features

    g = np.asarray(IRF, float)[None]
    pk = np.array([int(g.argmax())])
    rng = np.random.default_rng(14)
    R, C, W = 16, 16, 11
    row = np.repeat(np.arange(R * C) // C, 3)
    col = np.repeat(np.arange(R * C) % C, 3)
    present = rng.random(row.size) < 0.8
    row, col = row[present], col[present]
    depth = rng.choice([20.0, 21.0, 22.0, 40.0], row.size) + rng.normal(0, 0.5, row.size)
    cnt = rng.poisson(rng.choice([0.05, 0.8], (row.size, 1, 1)), (row.size, 1, W))
    surf = dict(
        row=row, col=col, depth_bin=depth, offset=np.round(depth).astype(int) - W // 2,
        own_counts=cnt.astype(np.int32), own_background=np.full((row.size, 1, W), 0.05, np.float32),
        image_shape=(R, C),
    )  # fmt: skip
    keep = np.ones(row.size, bool)
    for vouch in (-3.0, 1.0):
        ref, sums = np.zeros(row.size, bool), []
        for n_pass in range(1, 12):
            f = spill_over_features(
                surf, keep & ~ref, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, vouch_level=vouch
            )
            ref |= keep & ~ref & f["has_source"] & ~f["enclosed"] & (f["llr_source"] < 0.0)
            got = reject_spill_over(
                surf, keep, irf=g, peak=pk, fwhm=3.0, llr_level=0.0, vouch_level=vouch,
                max_iter=n_pass,
            )  # fmt: skip
            np.testing.assert_array_equal(got, ref)
            sums.append(int(got.sum()))
        assert sums[2] > sums[1] > sums[0] > 0  # later passes rejected more


def test_by_pixel_equals_the_stable_argsort_and_its_run_starts():
    # the counting sort gives np.argsort(kind="stable") and the runs' searchsorted starts
    from splidar.detection._quality import _by_pixel

    rng = np.random.default_rng(9)
    R, C = 7, 13
    for n in (0, 1, 50, 600):
        row = rng.integers(0, R, n).astype(np.int32)
        col = rng.integers(0, C, n).astype(np.int32)
        order, starts = _by_pixel(row, col, (R, C))
        pix = row.astype(np.int64) * C + col
        ref = np.argsort(pix, kind="stable")
        np.testing.assert_array_equal(order, ref)
        np.testing.assert_array_equal(starts, np.searchsorted(pix[ref], np.arange(R * C + 1)))


def test_llr_at_equals_the_sum_over_every_bin():
    # the spill-over test's own log-likelihood ratio takes the logarithm at the bins
    # holding photons only: the same value as the sum over every bin of the support
    from splidar.detection._kernels import _interp_irf
    from splidar.detection._quality import _llr_at

    g = np.asarray(IRF, float)[None]
    pk = np.array([float(g.argmax())])
    rng = np.random.default_rng(5)
    n, W = 40, 13
    counts = rng.poisson(rng.choice([0.05, 0.8], (n, 1, 1)), (n, 1, W)).astype(np.int32)
    bkg = rng.uniform(0.02, 0.3, (n, 1, W)).astype(np.float32)
    bkg[:, :, :2] = 0.0  # outside the support
    d = rng.uniform(20.0, 40.0, n)
    offset = np.round(d).astype(np.int64) - W // 2
    for i in range(n):
        sig = rng.uniform(0.5, 6.0, 1)
        ref = 0.0
        for w in range(W):
            b = bkg[i, 0, w]
            if b > 0:
                gv = _interp_irf(g[0], w - (d[i] - offset[i]) + pk[0])
                ref += counts[i, 0, w] * np.log1p(sig[0] * gv / max(np.float64(b), 1e-9))
                ref -= sig[0] * gv
        got = _llr_at.py_func(i, sig, d, offset, counts, bkg, g, pk)
        assert got == ref
        np.testing.assert_allclose(_llr_at(i, sig, d, offset, counts, bkg, g, pk), ref, rtol=1e-13)


# ----------------------------------------------------------------------------------------
# slope recovery (_slopes.py, issue #3)
# ----------------------------------------------------------------------------------------


def _ramp_with_disc(shape=(32, 32), T=200, bright=4.0, dim=0.8, bg=0.08):
    """A ramp of 5 bins per row (0.3 per column) with a dim disc of radius 5 on it."""
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]]
    depth = 20.0 + 5.0 * r + 0.3 * c
    disc = (r - shape[0] // 2) ** 2 + (c - shape[1] // 2) ** 2 <= 25
    ph = np.where(disc, dim, bright)[..., None]
    lam = np.full(shape + (1, T), float(bg))
    t = np.arange(T)
    g = np.exp(-0.5 * ((t - depth[..., None]) / (3.0 / 2.3548)) ** 2)
    lam[:, :, 0, :] += ph * g / g.sum(axis=-1, keepdims=True)
    return lam, depth, disc


def _slope_args(shape, T, bg):
    return dict(
        spatial=np.full(shape + (1,), bg, np.float32),
        dev=np.zeros((1, T), np.float32),
        irf=np.asarray(IRF, np.float64)[None],
        scales=np.array([1, 3, 7, 11]),
        width=13,
        fwhm=3.0,
        surface_pfa=0.01,
        presence_llr=3.0,
        max_surfaces=2,
        qloc=1,
    )


def test_detect_slopes_recovers_dim_disc_on_steep_ramp(monkeypatch):
    import splidar.detection._5d_slopes as slopes_stage

    # 0.8 signal photons per pixel on a ramp of 5 bins per row: the square boxes smear
    # the return over ~25 bins and the main pass finds 2-6 of the 81 disc pixels (seeds
    # 0-2); the sheared pooled test finds 78-81 when it tests every pixel and 69-73 when
    # it tests the empty ones only (a disc pixel holding a wrong-depth surface is not
    # tested); the default also tests the pixels whose surface their own counts do not
    # confirm, which the wrong-depth ones are
    lam, depth, disc = _ramp_with_disc()
    cube = _cube(lam, rng=0)
    res = {}
    for slopes in (False, "holes", "weak", "all"):
        # the pixels the pass tests are a constant of its stage (read at call time)
        monkeypatch.setattr(slopes_stage, "SLOPE_PIXELS", slopes or "weak")
        det = detect(cube, rng=0, passes=PASSES if slopes else _without("slopes"))
        p = det.points
        ok = np.abs(p.depth_bin - depth[p.row, p.col]) <= 3
        hit = np.zeros(disc.shape, bool)
        hit[p.row[ok], p.col[ok]] = True
        res[slopes] = ((hit & disc).sum(), (~ok).sum(), det)
    assert res[False][0] <= 20
    assert res["holes"][0] >= 60 and res["all"][0] >= 72
    assert res["weak"][0] >= max(res["holes"][0], 70)
    # recovered surfaces replace biased ones: no more wrong-depth surfaces than before
    assert res["all"][1] <= res[False][1]
    assert res["holes"][1] <= res[False][1]
    assert res["weak"][1] <= res["holes"][1]
    monkeypatch.undo()
    assert detect(cube, rng=0).options["slopes"] == "weak"  # the default
    det = res["all"][2]
    assert det.options["n_slopes"] > 0 and "slopes" in det.timings
    s = det.surfaces
    assert np.all(np.isfinite(s.presence_llr)) and np.all(np.isfinite(s.evidence))


def test_recover_slopes_no_surfaces_in_background_only_holes():
    # the plane is known all around the hole but the hole holds background only: each
    # tested pixel may pass at rate <= surface_pfa (0.01, Bonferroni: conservative), so
    # over the ~81 pixels tested about 0.8 at most; 2 allows for the region growing
    from splidar.detection._slopes import recover_slopes

    lam, depth, disc = _ramp_with_disc(dim=0.0)
    y = np.random.default_rng(5).poisson(lam)
    rr, cc = np.nonzero(~disc)
    surf = dict(row=rr, col=cc, depth_bin=depth[rr, cc])
    new = recover_slopes(y, surf, **_slope_args(disc.shape, 200, 0.08))
    assert new["n_tested"] >= disc.sum()
    assert len(new["row"]) <= 2


def test_recover_slopes_skips_gentle_slopes_and_surface_edges():
    from splidar.detection._slopes import recover_slopes

    lam, depth, disc = _ramp_with_disc(dim=4.0)
    y = np.random.default_rng(6).poisson(lam)
    args = _slope_args(disc.shape, 200, 0.08)
    # a flat surface: square boxes work there, nothing is tested
    rr, cc = np.nonzero(~disc)
    flat = recover_slopes(y, dict(row=rr, col=cc, depth_bin=np.full(rr.size, 50.0)), **args)
    assert flat["n_tested"] == 0 and len(flat["row"]) == 0
    # only the left half detected: the pixels beyond its edge are not enclosed by the
    # plane, so it is not extrapolated into them (their returns are real here)
    rr, cc = np.nonzero(np.ones(disc.shape, bool))
    left = cc < 12
    edge = recover_slopes(
        y, dict(row=rr[left], col=cc[left], depth_bin=depth[rr[left], cc[left]]), **args
    )
    assert edge["n_tested"] == 0 and len(edge["row"]) == 0


def test_recover_slopes_fields_match_box_filter_reference():
    # recovered surfaces carry every Surfaces field; histograms as in the main pass
    from scipy import ndimage

    from splidar.detection._slopes import recover_slopes

    lam, depth, disc = _ramp_with_disc(shape=(24, 24))
    y = np.random.default_rng(7).poisson(lam)
    rr, cc = np.nonzero(~disc)
    args = _slope_args(disc.shape, 200, 0.08)
    new = recover_slopes(y, dict(row=rr, col=cc, depth_bin=depth[rr, cc]), **args)
    S = len(new["row"])
    assert S >= 0.8 * disc.sum()  # 0.8 photons per pixel pooled over the disc
    assert np.all(disc[new["row"], new["col"]])
    assert np.all(np.abs(new["depth_bin"] - depth[new["row"], new["col"]]) <= 3)
    W = 13
    assert new["histograms"].shape == (S, 4, 1, W)
    np.testing.assert_array_equal(new["start"], new["offset"])
    np.testing.assert_array_equal(new["stop"], new["offset"] + W)
    c = Correlator(IRF[None], 200)(y)[:, :, 0, :].astype(np.float64)
    tt = new["offset"][:, None] + np.arange(W)
    for q, k in enumerate((1, 3, 7, 11)):
        box = ndimage.uniform_filter(c, size=(k, k, 1), mode="reflect")
        ref = np.maximum(box[new["row"][:, None], new["col"][:, None], tt] - 0.08, 0)
        # float32 FFT correlation vs direct sums: 1e-4 relative
        np.testing.assert_allclose(new["histograms"][:, q, 0], ref, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(new["signal"][:, q, 0], ref.sum(axis=1), rtol=1e-4, atol=1e-4)
    raw = y[new["row"][:, None], new["col"][:, None], 0, tt]
    np.testing.assert_array_equal(new["counts"][:, 0], raw.sum(axis=1))
    np.testing.assert_allclose(new["background"][:, 0], 0.08 * W, rtol=1e-5)
    assert np.all(new["presence_llr"] >= -3.0) and np.all(np.isfinite(new["presence_z"]))


@pytest.mark.parametrize("rate", [0.02, 0.5, 5.0])
def test_filtered_window_equals_the_full_reflected_sum(rate):
    # the window's matched filter from the bins holding photons only gives the full
    # sum over the IRF (indices reflected at the series' ends) bit for bit
    from splidar.detection._fast import _refl
    from splidar.detection._slopes import _filtered_window

    rng = np.random.default_rng(2)
    T, W = 120, 13
    g = np.asarray(gaussian_irf(2.5), np.float64)
    n = g.size
    cvw, nz_t, nz_v = np.empty(W), np.empty(W + n, np.int64), np.empty(W + n)
    for base in (-n, -3, 0, 40, T - W - n + 1, T - W - n + 2, T - W):
        yt = rng.poisson(rate, T).astype(np.uint16)
        _filtered_window(yt, g, base, cvw, nz_t, nz_v)
        ref = np.empty(W)
        for w in range(W):
            cv = 0.0
            for j in range(n):
                cv += g[j] * yt[_refl(base + w + j, T)]
            ref[w] = cv
        np.testing.assert_array_equal(cvw, ref)


def test_recover_slopes_replacement_needs_own_counts_not_to_reject_it():
    # the disc's centre holds a kept surface 4.5 bins off the ramp (within 2 FWHM of the
    # plane: a box-biased depth). The sheared test finds the ramp's depth there; it
    # replaces the kept surface only when the pixel's own counts do not favour the kept
    # one by more than presence_llr (3 nats)
    from splidar.detection._slopes import recover_slopes

    lam, depth, disc = _ramp_with_disc(dim=1.5)
    y = np.random.default_rng(3).poisson(lam)
    rr, cc = np.nonzero(~disc)
    rows = np.r_[rr, 16]
    cols = np.r_[cc, 16]
    dep = np.r_[depth[rr, cc], depth[16, 16] + 4.5]
    args = _slope_args(disc.shape, 200, 0.08)
    out = {}
    for old_llr in (-50.0, 50.0):
        llr = np.r_[np.zeros(rr.size), old_llr]
        surf = dict(row=rows, col=cols, depth_bin=dep, presence_llr=llr)
        new = recover_slopes(y, surf, **args)
        at = (new["row"] == 16) & (new["col"] == 16)
        out[old_llr] = (at.sum(), rows.size - 1 in new["replaces"], new)
    n_at, replaced, new = out[-50.0]
    assert n_at == 1 and replaced
    assert abs(new["depth_bin"][(new["row"] == 16) & (new["col"] == 16)][0] - depth[16, 16]) <= 3
    assert out[50.0][0] == 0 and not out[50.0][1]
    # the other disc pixels are recovered either way, and by the holes-only pass too
    holes = recover_slopes(y, surf, pixels="holes", **args)
    assert not np.any((holes["row"] == 16) & (holes["col"] == 16))
    assert holes["row"].size >= 70 and holes["replaces"].size == 0


def test_recover_slopes_weak_tests_pixels_their_own_counts_do_not_confirm():
    # as above, the disc's centre holds a box-biased surface. pixels="weak" tests it, and
    # replaces it, when its own log-likelihood ratio is below presence_llr (3 nats: the
    # own counts do not confirm it); above, the pixel is not tested at all
    from splidar.detection._slopes import recover_slopes

    lam, depth, disc = _ramp_with_disc(dim=1.5)
    y = np.random.default_rng(3).poisson(lam)
    rr, cc = np.nonzero(~disc)
    rows, cols = np.r_[rr, 16], np.r_[cc, 16]
    dep = np.r_[depth[rr, cc], depth[16, 16] + 4.5]
    args = _slope_args(disc.shape, 200, 0.08)
    res = {}
    for own in (2.9, 3.1):
        llr = np.r_[np.full(rr.size, 10.0), own]  # the ramp's surfaces are confirmed
        surf = dict(row=rows, col=cols, depth_bin=dep, presence_llr=llr)
        res[own] = recover_slopes(y, surf, pixels="weak", **args)
    weak, strong = res[2.9], res[3.1]
    assert rows.size - 1 in weak["replaces"] and weak["replaces"].size == 1
    at = (weak["row"] == 16) & (weak["col"] == 16)
    assert at.sum() == 1 and abs(weak["depth_bin"][at][0] - depth[16, 16]) <= 3
    assert strong["replaces"].size == 0
    assert not np.any((strong["row"] == 16) & (strong["col"] == 16))
    # the empty disc pixels are tested either way; the confirmed ramp pixels never
    for new in (weak, strong):
        assert new["row"].size >= 70 and np.all(disc[new["row"], new["col"]])
    # the weak pixel is one more tested pixel than the holes
    holes = recover_slopes(y, surf, pixels="holes", **args)
    assert weak["n_tested"] > holes["n_tested"] == strong["n_tested"]


def test_align_depths_moves_only_where_neighbours_and_own_counts_agree():
    from splidar.detection._quality import align_depths

    r, c = np.divmod(np.arange(9), 3)  # a ramp of 5 bins per row; the centre 5 bins off
    d = 10.0 + 5 * r
    d[4] = 20.0
    own = np.zeros((9, 13))
    own[4, 1] = 2.0  # its own photons at bin 15 (window from bin 14): moved there
    kw = dict(image_shape=(3, 3), n_slots=1, fwhm=3.0)
    new, n = align_depths(r, c, np.zeros(9, int), d, np.full(9, 14), own, **kw)
    assert n == 1 and new[4] == pytest.approx(15.0) and np.all(new[:4] == d[:4])
    own[4, 6] = 3.0  # the own counts favour the current depth (nothing else pooled): kept
    new, n = align_depths(r, c, np.zeros(9, int), d, np.full(9, 14), own, **kw)
    assert n == 0 and new[4] == 20.0
    own[4, 6] = 0.0
    d2 = d.copy()
    d2[3] = 30.0  # the west/east pair now places it at 25: the pairs disagree, kept
    new, n = align_depths(r, c, np.zeros(9, int), d2, np.full(9, 14), own, **kw)
    assert new[4] == 20.0


def _ramp_3x3(centre_photons: float):
    """A 3 x 3 ramp of 5 bins per row (and 1 per column): depths, windows and clean
    histograms with a return of 2 (centre: ``centre_photons``) at each pixel's true
    depth (IRF-shaped, FWHM 3); the centre's depth put 5 bins off, on the next row's."""
    from splidar.irf import gaussian_irf

    r, c = np.divmod(np.arange(9), 3)
    true = 40.0 + 5 * r + c
    g = np.asarray(gaussian_irf(3.0), np.float64).ravel()
    g /= g.sum()
    off = (np.rint(true) - 6).astype(np.int64)
    off[4] = 40  # the centre's window is centred on its wrong depth, 46
    own = np.zeros((9, 13))
    t = np.arange(13)
    for i in range(9):
        amp = centre_photons if i == 4 else 2.0
        own[i] = amp * np.interp(off[i] + t - true[i] + g.size // 2, np.arange(g.size), g, 0, 0)
    d = true.copy()
    d[4] = true[4] + 5.0
    return r, c, d, off, own, true, g


def test_align_depths_shears_the_pool_along_the_neighbours_plane():
    # a dim centre (no photon of its own, as in the dark stripe) whose depth fell on the
    # next row's lobe: its own counts cannot move it; the 4-neighbours' histograms,
    # shifted along their plane, pool at its true depth and do
    from splidar.detection._quality import align_depths

    r, c, d, off, own, true, _ = _ramp_3x3(centre_photons=0.0)
    kw = dict(image_shape=(3, 3), n_slots=1, fwhm=3.0)
    new, n = align_depths(r, c, np.zeros(9, int), d, off, own, **kw)
    assert n == 1 and abs(new[4] - true[4]) <= 0.5  # within half a bin of the plane
    assert np.all(new[np.arange(9) != 4] == d[np.arange(9) != 4])  # the rest in place
    # a depth the plane places within half the FWHM stays
    d2 = d.copy()
    d2[4] = true[4] + 1.4
    new, n = align_depths(r, c, np.zeros(9, int), d2, off, own, **kw)
    assert n == 0 and new[4] == d2[4]


def test_align_depths_keeps_a_bright_pixel_off_the_plane():
    # the centre is its own bright return 5 bins off its neighbours' plane (a bump): the
    # sheared pool of 5 pixels favours the plane, but the own counts favour the current
    # depth by far more than the background's noise: kept. Without the noise (no veto)
    # the pool would move it.
    from splidar.detection._quality import align_depths

    r, c, d, off, own, true, g = _ramp_3x3(centre_photons=0.0)
    t = np.arange(13)
    own[4] = 6.0 * np.interp(off[4] + t - d[4] + g.size // 2, np.arange(g.size), g, 0, 0)
    kw = dict(image_shape=(3, 3), n_slots=1, fwhm=3.0)
    noise = np.full(9, np.sqrt(2 * 0.05 * np.sum(g**2)))  # 0.05 background per bin
    new, n = align_depths(r, c, np.zeros(9, int), d, off, own, noise=noise, **kw)
    assert n == 0 and new[4] == d[4]
    new, n = align_depths(r, c, np.zeros(9, int), d, off, own, **kw)
    assert n == 1 and abs(new[4] - true[4]) <= 0.5


def test_detect_refine_aligns_box_biased_depths_on_steep_ramp():
    # 4 photons per pixel on a ramp of 5 bins per row (without the slope recovery): the
    # 3 x 3 box has a lobe per row and some peaks fall on a neighbour row's lobe, 5 bins
    # off; the alignment with the 4-neighbours' plane moves them back (measured, cube
    # seeds 0-2, points more than 3 bins off: 111 / 78 / 83 without it; 95 / 70 / 63
    # when the own counts alone had to favour the plane; 59 / 40 / 38 with the 3 x 3 box
    # sheared along the plane). Stage 7b is left out on both sides: its near depths
    # (a pixel off its region's plane) fix the ramp's wrong depths themselves when stage
    # 7 does not run, which would hide what stage 7 does
    lam, depth, _ = _ramp_with_disc(bright=4.0, dim=4.0)
    cube = _cube(lam, rng=0)
    on = detect(cube, rng=0, passes=_without("slopes", "edge_bands"))
    off = detect(cube, rng=0, passes=_without("slopes", "align_depths", "edge_bands"))
    rec = {r.stage: r for r in off.provenance}
    assert off.options["n_aligned"] == 0 and not rec["align_depths"].ran
    err = {}
    for name, det in (("on", on), ("off", off)):
        p = det.points
        err[name] = int((np.abs(p.depth_bin - depth[p.row, p.col]) > 3).sum())
    assert on.options["n_aligned"] >= 10
    assert err["on"] <= 0.7 * err["off"]


def test_detect_align_depths_keeps_a_bright_one_pixel_bump(monkeypatch):
    import splidar.detection._7a_align_depths as align_stage

    # a flat wall with one pixel 5 bins in front of it, every pixel 40 photons: the
    # bump's 4-neighbours place it on the wall (within 2 FWHM) and their sheared pool
    # favours the wall's depth, but its own counts show its return far above the
    # background's noise, so it keeps its depth; without that veto it moves onto the wall
    T, shape = 120, (12, 12)
    depth = np.full(shape, 60.0)
    depth[6, 6] = 55.0
    lam = np.full(shape + (1, T), 0.05)
    t = np.arange(T)
    g = np.exp(-0.5 * ((t - depth[..., None]) / (3.0 / 2.3548)) ** 2)
    lam[:, :, 0, :] += 40.0 * g / g.sum(axis=-1, keepdims=True)
    cube = _cube(lam, rng=1)

    def bump_depths():
        p = detect(cube, rng=0).points
        return p.depth_bin[(p.row == 6) & (p.col == 6)]

    assert np.any(np.abs(bump_depths() - 55.0) <= 1.0)
    monkeypatch.setattr(align_stage, "OWN_Z", np.inf)  # read at call time
    assert not np.any(np.abs(bump_depths() - 55.0) <= 1.0)


def test_restore_enclosed_needs_own_counts_beside_a_kept_surface():
    from splidar.detection._quality import restore_enclosed

    # a 3 x 3 net: strands at depth 20 around a one-pixel hole that sees a wall at 80;
    # the hole's rejected candidate at the net's depth is enclosed by the strands
    r = np.r_[np.divmod(np.arange(9), 3)[0], 1]
    c = np.r_[np.divmod(np.arange(9), 3)[1], 1]
    d = np.r_[np.full(9, 20.0), 80.0]
    keep = np.ones(10, bool)
    keep[4] = False  # the hole's net-depth candidate
    surf = dict(row=r, col=c, depth_bin=d, evidence=np.ones(10), presence_z=np.full(10, 5.0),
                presence_llr=np.full(10, -2.0), image_shape=(3, 3))  # fmt: skip
    kw = dict(fwhm=3.0, z_level=3.0, max_kept=2)
    # its own counts do not favour it (log-ratio -2 < 0): it stays rejected
    assert not restore_enclosed(surf, keep, llr_level=0.0, **kw).any()
    surf["presence_llr"][4] = 0.5  # they do: restored as the pixel's second surface
    assert np.flatnonzero(restore_enclosed(surf, keep, llr_level=0.0, **kw)).tolist() == [4]
    # a full pixel takes nothing; an empty one needs no own-count support
    assert not restore_enclosed(surf, keep, llr_level=0.0, fwhm=3.0, z_level=3.0, max_kept=1).any()
    keep[9] = False
    surf["presence_llr"][4] = -2.0
    assert restore_enclosed(surf, keep, llr_level=0.0, **kw)[4]


def test_align_depths_stays_within_half_a_bin_of_the_chosen_bin():
    # the sub-bin step is a parabola's vertex: at the edge of the search range (not a
    # local maximum) or on a nearly flat top it once jumped 13 bins out of the window
    from splidar.detection._quality import align_depths

    r, c = np.divmod(np.arange(9), 3)
    d = 10.0 + 5 * r
    d[4] = 20.0
    rng = np.random.default_rng(0)
    for _ in range(200):
        own = rng.random((9, 13)) * (rng.random((9, 13)) < 0.5)
        own[4, 6] = 0.0  # the current depth unsupported
        new, n = align_depths(r, c, np.zeros(9, int), d, np.full(9, 14), own,
                              image_shape=(3, 3), n_slots=1, fwhm=3.0)  # fmt: skip
        if n:
            # the prediction is 15: the bins searched are 13.5..16.5 (14..17)
            assert 13.5 <= new[4] <= 17.5


def test_align_depths_same_on_any_number_of_threads(monkeypatch):
    # the surfaces in parts on threads: each one's depth is its own (the moves read the
    # depths before any move), the number moved their sum
    from splidar.detection import _quality
    from splidar.detection._quality import align_depths

    monkeypatch.setattr(_quality, "_ALIGN_PART", 5)
    rng = np.random.default_rng(4)
    R, C, W = 12, 10, 13
    r, c = (a.ravel() for a in np.mgrid[0:R, 0:C])
    d = 10.0 + 5.0 * r + rng.normal(0, 0.3, r.size)  # a steep ramp
    bad = rng.random(r.size) < 0.3
    d[bad] += rng.choice([-5.0, 5.0], int(bad.sum()))  # a neighbour row's lobe
    off = np.rint(d).astype(np.int64) - W // 2
    own = rng.random((r.size, W)) * (rng.random((r.size, W)) < 0.5)
    kw = dict(image_shape=(R, C), n_slots=1, fwhm=3.0)
    one, n1 = align_depths(r, c, np.zeros(r.size, int), d, off, own, **kw)
    assert n1 > 5
    for n_jobs in (2, 3, 7):
        got, n = align_depths(r, c, np.zeros(r.size, int), d, off, own, n_jobs=n_jobs, **kw)
        assert n == n1 and got.tobytes() == one.tobytes()


def test_pooled_same_on_any_number_of_threads():
    # the sheared pools of 900 holes, one thread or three: each hole's sums are its own
    from splidar.detection._slopes import _pooled

    rng = np.random.default_rng(11)
    R, C, L, T, K = 40, 36, 2, 120, 2
    y = rng.poisson(0.3, (R, C, L, T)).astype(np.uint16)
    D = rng.uniform(10, 110, (R, C, K + 1))
    D[rng.random(D.shape) < 0.4] = np.nan
    sp = rng.uniform(0.0, 0.2, (R, C, L)).astype(np.float32)
    dev = rng.normal(0.0, 0.05, (L, T)).astype(np.float32)
    H = 900
    hr, hc = rng.integers(0, R, H), rng.integers(0, C, H)
    planes = np.zeros((H, K, 5))
    planes[..., 0] = rng.uniform(5, 115, (H, K))
    planes[..., 1:3] = rng.normal(0, 3, (H, K, 2))
    planes[..., 3] = rng.random((H, K)) < 0.8
    args = (y, D, 4.5, sp, dev, hr, hc, planes, np.array([3, 7, 11]), np.arange(-3.0, 4.0), -2, 3)
    n1, b1 = _pooled(*args, n_jobs=1)
    n3, b3 = _pooled(*args, n_jobs=3)
    assert n1.any() and b1.any()
    np.testing.assert_array_equal(n1, n3)
    np.testing.assert_array_equal(b1.view(np.int64), b3.view(np.int64))
