"""Each stage of ``splidar.detect`` on its own, and the provenance that ties them together."""

import functools

import numpy as np
import pytest

from splidar import Cube, gaussian_irf
from splidar.detection import STAGES, _4_map, detect
from splidar.detection._1_background import estimate_temporal_background
from splidar.detection._2_saliency import block_saliency, saliency_filters
from splidar.detection._3_null import calibrate_null, split_rule
from splidar.detection._4_map import MapOptions, map_candidates
from splidar.detection._5a_spill_over import remove_spill_over
from splidar.detection._5b_isolated import remove_isolated
from splidar.detection._5c_dark_regions import restore_dark_regions
from splidar.detection._5e_enclosed import restore_enclosed_holes
from splidar.detection._6_select import select_surfaces
from splidar.detection._detect import PASSES
from splidar.detection._filters import Correlator, irf_fwhm, irf_halfwidth
from splidar.detection._kernels import find_segments, fine_response
from splidar.irf import exp_tail_irf
from splidar.scenes import two_layer_scene

SCALES = np.array([1, 3, 7, 11])
WEIGHTS = SCALES / SCALES.sum()


def _setup(counts, irf):
    irf = np.asarray(irf, np.float64).reshape(1, -1) if np.ndim(irf) == 1 else irf
    corr = Correlator(irf, counts.shape[-1])
    bg = estimate_temporal_background(counts, corr, irf, box=11, n_jobs=1)
    return irf, bg, saliency_filters(corr, SCALES, WEIGHTS, bg.dev, irf)


def _map(counts, irf, *, pfa=1e-3, rng=0, block_rows=None, n_jobs=1):
    irf, bg, filters = _setup(counts, irf)
    fw = irf_fwhm(irf)
    nul = calibrate_null(
        counts, filters, pfa=pfa, surface_pfa=0.01, null="empirical",
        min_separation=int(np.ceil(fw)), split=(0.5, _4_map.SPLIT_Z, 3.0, 0.0),
        rng=np.random.default_rng(rng), n_jobs=1,
    )  # fmt: skip
    opts = MapOptions(
        min_separation=int(np.ceil(fw)), split_ratio=0.5, presence="adaptive", presence_z=3.0,
        presence_llr=3.0, secondary_llr=0.0, refine=True, keep_suspects=True, max_surfaces=2,
        width=min(2 * irf_halfwidth(irf) + 1, counts.shape[-1]),
    )  # fmt: skip
    mp = map_candidates(counts, filters, nul, opts, block_rows=block_rows, n_jobs=n_jobs)
    return irf, bg, nul, mp


@pytest.fixture(scope="module")
def net_map():
    """The map pass on a net in front of objects (PPP 4, SBR 0.25, decaying background)."""
    sim = two_layer_scene((24, 24), n_bins=120).simulate(
        ppp=4, sbr=0.25, background="decaying", rng=0
    )
    counts = np.asarray(sim.cube.counts)
    irf, bg, nul, mp = _map(counts, sim.cube.irf)
    return sim, irf, mp


def test_estimate_temporal_background_recovers_a_decaying_shape():
    # pure background whose rate decays linearly from 0.4 to 0.1 photons per bin: the
    # shape (up to the estimator's clipped level) follows it; dev has zero mean in t
    T = 120
    rate = np.linspace(0.4, 0.1, T)
    counts = np.random.default_rng(1).poisson(np.broadcast_to(rate, (32, 32, 1, T)))
    _, bg, _ = _setup(counts, gaussian_irf(3.0))
    t = bg.temporal[0]
    assert np.corrcoef(t[10:-10], rate[10:-10])[0, 1] > 0.95
    np.testing.assert_allclose(bg.dev.mean(axis=-1), 0.0, atol=1e-5)  # float32 sum of T values
    # the level of the shape: within 10 % of the true mean rate (Poisson noise of 1024 px)
    assert abs(t.mean() - rate.mean()) < 0.1 * rate.mean()


def test_estimate_temporal_background_returns_at_the_window_end_are_not_background():
    # every pixel's return within 3 bins of the window's end (more pixels than the 90 %
    # eq:background_1 tolerates): the running median's repeated edge values kept the
    # returns in the profile and detect found 7 % of them (bench_foreign_cubes.py
    # --window-end 296 299 --pulse 3 0). The end's full-window median removes them.
    rng = np.random.default_rng(0)
    n, T = 24, 200
    irf = gaussian_irf(3.0)
    d = 196 + 3 * rng.random((n, n))
    t = np.arange(T)
    pulse = np.exp(-0.5 * ((t - d[..., None]) / (3.0 / 2.3548)) ** 2)
    lam = 12 * pulse / pulse.sum(axis=-1, keepdims=True) + 12 / T  # SBR about 1
    counts = rng.poisson(lam).astype(np.uint16)[:, :, None, :]
    _, bg, _ = _setup(counts, irf)
    # the profile at the end stays at the background's level (12 / T per bin), not the
    # returns' (about 3.5 photons per pixel in the last bins)
    assert bg.temporal[0, -3:].max() < 3 * 12 / T
    det = detect(Cube(counts, irf=irf), rng=0)
    found = np.zeros((n, n), bool)
    found[det.surfaces.row, det.surfaces.col] = (
        np.abs(det.surfaces.depth_bin - d[det.surfaces.row, det.surfaces.col]) <= 2
    )
    assert found.mean() > 0.9  # 0.07 with the edge values repeated


@pytest.mark.parametrize("shape", ["pileup", "decaying"])
def test_estimate_temporal_background_a_decay_from_the_window_start_is_background(shape):
    # background alone, falling from bin 0: pile-up (0.05 + exp(-t / 6.7 bins), an
    # e-folding scale just above the matched filter's half-width of 6 bins) and the
    # 20-fold decay. The start must keep them: the first 3 bins within 15 % of the matched
    # filter of the true mean (-5 % and -3 %; the end's rule applied at the start, with
    # the lower of the running median and the first full window's median, puts the
    # pile-up's first bins 8 x too low).
    from splidar.simulation import background_shape

    T = 200
    mean = 0.08 * background_shape(shape, T)
    counts = np.random.default_rng(2).poisson(np.broadcast_to(mean, (96, 80, 1, T)))
    irf, bg, _ = _setup(counts, gaussian_irf(3.0))
    target = Correlator(irf, T)(mean[None, None].astype(np.float32))[0, 0]
    np.testing.assert_allclose(bg.temporal[0, :3], target[:3], rtol=0.15)


def test_estimate_temporal_background_a_rise_to_the_window_end_is_background():
    # background alone rising 20-fold to the end (exp(3 t / T), 0.5 photons a bin on
    # average): it goes on rising before the last bins, a return cut by the end does
    # not, so the end's rule keeps it. Session 16's rule (the lower of the running
    # median and the last full window's median) put the last 3 bins 15 % low.
    T = 200
    mean = np.exp(3.0 * np.arange(T) / T)
    mean *= 0.5 / mean.mean()
    counts = np.random.default_rng(4).poisson(np.broadcast_to(mean, (96, 80, 1, T)))
    irf, bg, _ = _setup(counts, gaussian_irf(3.0))
    target = Correlator(irf, T)(mean[None, None].astype(np.float32))[0, 0]
    np.testing.assert_allclose(bg.temporal[0, -3:], target[-3:], rtol=0.06)


def _low_median_truth(levels, rate, irf, k, reps, rng):
    """Mean over ``reps`` simulated coarse cubes of stage 1's estimator (the median of the
    lowest 10 %), less the mean rate: the exact window sums of Poisson counts (a sum of
    k^2 Poisson counts is Poisson) correlated with the IRF, as temporal_shape forms them."""
    from splidar.detection._background import LOW_FRACTION, _low_median

    n, T = levels.size, rate.size
    mu = np.maximum(levels[:, None] + rate[None, :], 0.0)
    corr = Correlator(irf, T)
    m = int(np.ceil(LOW_FRACTION * n))
    est = np.empty((reps, T))
    for i in range(reps):
        sums = rng.poisson(mu * k * k).astype(np.float32) / (k * k)
        est[i] = _low_median(corr(sums[:, None, :])[:, 0], m)
    return est.mean(axis=0) - mu.mean(axis=0), est.std(axis=0) / np.sqrt(reps), m


@pytest.mark.parametrize("rate", [0.05, 0.5, 3.0])
def test_low_quantile_bias_matches_a_large_simulation(rate):
    # levels spread over a factor 3 across the pixels, a decaying shape in t, 7 to 440
    # photons' worth of variance per coarse value: the computed bias equals the simulated
    # one within 3 Monte-Carlo standard errors plus 4 % of the coarse values' standard
    # deviation per bin, 1 % on average (the model's error, three cumulants and Blom's
    # position, measured with 100 draws: at most 3.2 % and 0.6 % at rate 0.05, 1.2 % and
    # 0.02 % at 0.5). The simulation of 600 pixels x 4 draws it replaces erred by 6-11 %
    # rms here, 2-25 x more.
    from splidar.detection._background import low_quantile_bias

    rng = np.random.default_rng(3)
    g = gaussian_irf(2.0).reshape(1, -1)
    k, T, n = 7, 80, 2000
    levels = rate * rng.uniform(0.5, 1.5, n)
    shape_t = rate * (0.6 * np.exp(-np.arange(T) / 30.0) - 0.2)
    truth, se, m = _low_median_truth(levels, shape_t, g, k, 30, rng)
    vf = float((g**2).sum()) / k**2
    sf = float((g**3).sum()) / k**4
    got = low_quantile_bias(levels + shape_t.mean(), shape_t - shape_t.mean(), vf, sf, m)
    sd = np.sqrt(rate * vf)
    inner = slice(5, T - 5)  # the mirrored edges of the matched filter
    err = np.abs(got - truth)[inner]
    assert np.all(err <= 3 * se[inner] + 0.04 * sd)
    assert abs(np.mean((got - truth)[inner])) <= 0.01 * sd + np.mean(se[inner])


def test_low_quantile_bias_sparse_counts_take_the_whole_mean():
    # most coarse values are 0 at 1e-4 photons per bin: the low median is 0, so its bias
    # is minus the mean level, exactly
    from splidar.detection._background import low_quantile_bias

    g = gaussian_irf(2.0)
    levels = np.full(500, 1e-4)
    dev = np.linspace(-5e-5, 5e-5, 40)
    got = low_quantile_bias(levels, dev, (g**2).sum() / 49, (g**3).sum() / 49**2, 50)
    np.testing.assert_allclose(got, -(levels[0] + dev), rtol=1e-9)


def test_block_saliency_peaks_at_a_planted_return():
    # one bright return at bin 50 in every pixel over a flat background: the saliency of
    # every pixel peaks within one bin of it
    g = gaussian_irf(3.0)
    lam = np.full((16, 16, 1, 100), 0.05)
    h = g.size // 2
    lam[:, :, 0, 50 - h : 50 + h + 1] += 10 * g
    counts = np.random.default_rng(2).poisson(lam)
    _, _, filters = _setup(counts, g)
    _, sal, d, sp, level = block_saliency(counts, filters)
    assert sal.shape == (16, 16, 100) and sp.shape == (16, 16, 1)
    assert np.all(np.abs(sal.argmax(axis=-1) - 50) <= 1)
    assert np.all(sal >= 0) and np.all(level >= 0)


def test_calibrate_null_holds_the_false_alarm_rate_on_fresh_background():
    # the threshold from one background-only cube, applied to the saliency of another:
    # the voxel false-alarm rate stays within 2x of pfa (the documented calibration)
    T, pfa = 100, 1e-2
    rng = np.random.default_rng(3)
    lam = np.full((48, 48, 1, T), 0.2)
    counts = rng.poisson(lam)
    g = gaussian_irf(3.0)
    _, _, filters = _setup(counts, g)
    nul = calibrate_null(
        counts, filters, pfa=pfa, surface_pfa=0.01, null="empirical", min_separation=3,
        split=(0.5, _4_map.SPLIT_Z, 3.0, 0.0), rng=np.random.default_rng(0), n_jobs=1,
    )  # fmt: skip
    _, sal, _, _, level = block_saliency(rng.poisson(lam), filters)
    rate = float(np.mean(sal > nul.threshold_at(level)))
    assert pfa / 2 < rate < 2 * pfa
    assert nul.evidence_threshold >= 0 and nul.model.pfa == pfa


def test_map_candidates_keeps_a_bright_plane_in_every_pixel():
    g = gaussian_irf(3.0)
    lam = np.full((20, 20, 1, 100), 0.05)
    h = g.size // 2
    for j in range(20):  # a plane tilted along the columns, depth 30 + j
        lam[:, j, 0, 30 + j - h : 30 + j + h + 1] += 20 * g
    counts = np.random.default_rng(4).poisson(lam)
    _, _, _, mp = _map(counts, g)
    t = mp.candidates
    c = t.columns
    kept = t.keep
    good = kept & (np.abs(c["depth_bin"] - (30 + c["col"])) < 1.5)
    pix = np.unique(c["row"][good] * 20 + c["col"][good])
    assert pix.size == 400  # every pixel holds its return
    assert np.all(t.origin == STAGES.index("map"))
    assert mp.mask.shape == (20, 20, 100) and 0 < mp.reduction.voxel_fraction < 0.2


def test_schedule_hands_out_every_block_once():
    # a thread done with its run helps the run with the most blocks left, from its bottom
    plan = _4_map._Schedule([(0, 30), (30, 50)], 7)
    first = list(plan.blocks_for(0))
    assert first == [(0, 7), (7, 14), (14, 21), (21, 28), (28, 30), (44, 50), (37, 44), (30, 37)]
    assert list(plan.blocks_for(1)) == []
    plan = _4_map._Schedule([(0, 30), (30, 50)], 7)
    own1, own0 = plan.blocks_for(1), plan.blocks_for(0)
    got = [next(own1), next(own1), *own0, *own1]
    assert sorted(got) == _4_map._blocks(0, 30, 7) + _4_map._blocks(30, 50, 7)


def test_map_candidates_same_map_whatever_order_of_blocks(monkeypatch, net_map):
    # one thread computes every block bottom-up (the halo rows move the other way, and
    # jump from one run to the next): the same map and candidates as one run downwards
    sim, _, ref = net_map

    def upwards(self, k):
        yield from [b for run in self.blocks for b in run][::-1] if k == 1 else []

    monkeypatch.setattr(_4_map._Schedule, "blocks_for", upwards)
    *_, mp = _map(np.asarray(sim.cube.counts), sim.cube.irf, block_rows=5, n_jobs=2)
    np.testing.assert_array_equal(mp.saliency, ref.saliency)
    np.testing.assert_array_equal(mp.mask, ref.mask)
    np.testing.assert_array_equal(mp.spatial, ref.spatial)
    np.testing.assert_array_equal(mp.candidates.keep, ref.candidates.keep)
    for k, v in ref.candidates.columns.items():
        np.testing.assert_array_equal(mp.candidates.columns[k], v, err_msg=k)


def _check_pass(res, before, keep0, *, removes: bool):
    new = res.table
    np.testing.assert_array_equal(before.keep, keep0)  # the input table is not modified
    assert res.ran
    assert res.removed == int((before.keep & ~new.keep[: len(before)]).sum())
    assert res.added == int((~before.keep & new.keep[: len(before)]).sum())
    if removes:
        assert res.added == 0
    else:
        assert res.removed == 0
        restored = np.flatnonzero(~before.keep & new.keep)
        assert np.all(new.origin[restored] == STAGES.index(res.name))


def test_remove_spill_over_only_removes_candidates_beside_kept_ones(net_map):
    sim, irf, mp = net_map
    t = mp.candidates
    keep0 = t.keep.copy()
    res = remove_spill_over(t, irf=irf, peak=irf.argmax(axis=1), fwhm=3.0, llr_level=0.0)
    _check_pass(res, t, keep0, removes=True)
    assert res.removed > 0
    # a removed candidate is the spread of a neighbour's return: some 8-neighbour kept a
    # candidate within the FWHM of its depth
    c, k = t.columns, res.table.keep
    gone = np.flatnonzero(t.keep & ~k)
    for i in gone[:50]:
        near = (np.abs(c["row"] - c["row"][i]) <= 1) & (np.abs(c["col"] - c["col"][i]) <= 1)
        near &= (np.arange(len(t)) != i) & t.keep
        assert np.any(np.abs(c["depth_bin"][near] - c["depth_bin"][i]) <= 3.0)


def test_remove_isolated_and_restoring_passes_change_only_their_direction(net_map):
    sim, irf, mp = net_map
    t = mp.candidates
    keep0 = t.keep.copy()
    iso = remove_isolated(t, fwhm=3.0, pfa=0.01, n_bins=120)
    _check_pass(iso, t, keep0, removes=True)
    keep1 = iso.table.keep.copy()
    dark = restore_dark_regions(
        iso.table, irf=irf, peak=irf.argmax(axis=1), fwhm=3.0, half=5, pfa=0.01, llr_level=-3.0
    )
    _check_pass(dark, iso.table, keep1, removes=False)
    keep2 = dark.table.keep.copy()
    enc = restore_enclosed_holes(
        dark.table.without("own_counts", "own_background"), fwhm=3.0, z_level=3.0,
        max_kept=2, llr_level=0.0,
    )  # fmt: skip
    _check_pass(enc, dark.table, keep2, removes=False)


def test_select_surfaces_keeps_at_most_k_per_pixel_in_depth_order(net_map):
    _, _, mp = net_map
    for k in (1, 2):
        s = select_surfaces(
            mp.candidates, mp.histograms, max_surfaces=k, n_scales=4, n_wavelengths=1,
            width=mp.width,
        )  # fmt: skip
        pix = s.row * 24 + s.col
        assert np.bincount(pix).max() <= k and np.all(s.slot < k)
        two = np.flatnonzero(s.slot == 1)
        assert np.all(s.depth_bin[two] > s.depth_bin[two - 1])
        assert s.histograms.shape == (len(s), 4, 1, mp.width)


def test_select_surfaces_from_a_compacted_table_in_parts_is_the_same(net_map, monkeypatch):
    """The compact integer types hold every value, and the surfaces selected from the
    compacted table, their histograms gathered a few at a time into a given array, are
    the ones of the table as the map pass gave it."""
    from splidar.detection import _6_select
    from splidar.detection._table import compact_columns

    _, _, mp = net_map
    table = mp.candidates
    small = table.compacted(120)
    for k, v in table.columns.items():
        np.testing.assert_array_equal(small.columns[k], v, err_msg=k)
    assert small.columns["row"].dtype == np.int32 and small.columns["offset"].dtype == np.int32
    assert small.columns["scale_index"].dtype == np.int16 and small.hist_row.dtype == np.int32
    assert small.columns["own_counts"].dtype == np.int16
    # an image of more than 2**31 pixels keeps int64 rows and columns (row * C + col)
    big = compact_columns(table.columns, (50_000, 50_000), 120)
    assert big["row"].dtype == np.int64 and big["start"].dtype == np.int32
    opts = dict(max_surfaces=2, n_scales=4, n_wavelengths=1, width=mp.width)
    a = select_surfaces(table, mp.histograms, **opts)
    monkeypatch.setattr(_6_select, "GATHER_CHUNK", 7)
    out = functools.partial(np.zeros, dtype=np.float32)
    b = select_surfaces(small, mp.histograms, histograms_out=out, **opts)
    for name, x in vars(a).items():
        if isinstance(x, np.ndarray):
            y = getattr(b, name)
            assert y.dtype == x.dtype, name
            np.testing.assert_array_equal(y, x, err_msg=name)


def test_detect_provenance_accounts_for_every_surface(net_map):
    sim, _, _ = net_map
    det = detect(sim.cube)
    rec = {r.stage: r for r in det.provenance}
    assert [r.stage for r in det.provenance] == list(STAGES)
    total = rec["map"].added + sum(r.added - r.removed for r in det.provenance[1:])
    assert total == len(det.surfaces)
    kept = np.bincount(det.surfaces.stage, minlength=len(STAGES))
    for name in ("dark_regions", "slopes", "enclosed"):
        assert kept[STAGES.index(name)] <= rec[name].added
    assert kept.sum() == len(det.surfaces) and rec["slopes"].added > 0
    assert "spill_over" in det.provenance_table()


def test_detect_passes_selects_the_clean_up_passes(net_map):
    # passes=() runs no clean-up pass: every kept candidate of the map (at most K_s per
    # pixel) is a surface; leaving one pass out changes only that pass's record
    sim, _, _ = net_map
    none = detect(sim.cube, passes=())
    assert not any(r.ran for r in none.provenance if r.stage not in ("map", "select"))
    assert np.all(none.surfaces.stage == STAGES.index("map"))
    rec = {r.stage: r for r in none.provenance}
    assert len(none.surfaces) == rec["map"].added - rec["select"].removed
    no_spill = detect(sim.cube, passes=("isolated", "dark_regions", "slopes"))
    assert [r.stage for r in no_spill.provenance if r.ran] == [
        "map", "isolated", "dark_regions", "slopes", "select",
    ]  # fmt: skip
    assert no_spill.options["n_spill_over"] == 0 and no_spill.options["spill_llr"] is None


def test_detect_refuses_a_cube_larger_than_free_memory(monkeypatch):
    # the memory guard runs at detect's entry for Python callers too: refused with the
    # figure and the way out, before anything large is allocated
    from splidar import Cube, SplidarError, gaussian_irf
    from splidar.detection import detect

    cube = Cube(np.zeros((32, 32, 1, 400), np.uint16), irf=gaussian_irf(3.0))
    monkeypatch.setenv("SPLIDAR_MEMORY_LIMIT", "1M")
    with pytest.raises(SplidarError, match=r"(?s)detection on 32 x 32 pixels.*store="):
        detect(cube)


def test_rescue_dark_ignores_pools_whose_members_peak_at_their_own_depths():
    # the halo of empty pixels around a bright object: each rejected candidate's depth
    # sits on one background photon of its own, at one of three depths 3.5 bins apart
    # (within the FWHM of each other, outside each other's half-maximum window). Counted
    # about their own depths the pool holds 25 photons for a background of 12.5:
    # "significant"; about the pool's depth only a third of them: background.
    from splidar.detection._quality import rescue_dark

    g = np.asarray(gaussian_irf(2.0), float)[None]
    n, W = 25, 13
    r, c = np.divmod(np.arange(n), 5)
    depth = np.array([2.5, 6.0, 9.5])[(r + c) % 3]
    cnt = np.zeros((n, 1, W), np.int32)
    cnt[np.arange(n), 0, np.round(depth).astype(int)] = 1
    surf = dict(
        row=r, col=c, depth_bin=depth, offset=np.zeros(n, int), own_counts=cnt,
        own_background=np.full((n, 1, W), 0.1, np.float32), evidence=np.ones(n),
        image_shape=(5, 5),
    )  # fmt: skip
    kw = dict(irf=g, peak=np.array([g.argmax()]), fwhm=4.7, half=4, pfa=0.01, llr_level=-3.0)
    assert rescue_dark(surf, np.zeros(n, bool), **kw).sum() == 0
    # the same pixels with their photon at one common depth: a dim patch, restored
    cnt[:] = 0
    cnt[:, 0, 6] = 1
    surf.update(own_counts=cnt, depth_bin=np.full(n, 6.0))
    assert rescue_dark(surf, np.zeros(n, bool), **kw).sum() == n


def _close_pair_segments(
    second: bool, z: float, n_pix: int = 300, seed: int = 5, sep: float = 7.5, reach=0.0
):
    """find_segments on pixels whose multiscale response ``d`` is one broad bump (the
    coarse scales fill the dip) over own counts with one return of 16 photons at bin
    30, or two of 8 photons each 2.5 FWHM (7.5 bins) apart; background 0.025 a bin (as
    in the close-pair cases of bench_robustness). Returns the segments from the
    correlated counts (the map pass's way) and from fine_response (the null's way)."""
    T, fwhm = 80, 3.0
    g = gaussian_irf(fwhm).reshape(1, -1)
    lam = np.full((1, n_pix, 1, T), 0.025)
    for centre, n in [(30.0, 8.0), (30.0 + sep, 8.0)] if second else [(30.0, 16.0)]:
        x = np.arange(T) - centre
        prof = np.exp(-0.5 * (x / (fwhm / 2.3548)) ** 2)
        lam[..., :] += n * prof / prof.sum()
    y = np.random.default_rng(seed).poisson(lam).astype(np.uint16)
    c = Correlator(g, T)(y, workers=1)
    sp = np.full((1, n_pix, 1), 0.025, np.float32)
    dev = np.zeros((1, T), np.float32)
    tt = np.arange(T)
    d = np.broadcast_to(np.exp(-0.5 * ((tt - 33.0) / 6.0) ** 2), (1, n_pix, T))
    d = np.ascontiguousarray(d, np.float32)
    mask = np.ascontiguousarray(d > 0.05)
    ones = np.ones_like(d)
    rule = split_rule(g, z, reach=reach)
    no = np.empty((0, 0, 0), np.float32)
    from_c = find_segments(mask, d, ones, ones, 3, 0.5, (c, y, 0, 0, sp, dev, no, no, no), rule)
    pre = tuple(np.empty((1, n_pix, T), np.float32) for _ in range(3))
    fine_response(c, y, sp, dev, rule[3], *pre)
    no_c = np.empty((0, 0, 0, 0), np.float32)
    no_y = np.empty((0, 0, 0, 0), np.uint16)
    no_sp = np.empty((0, 0, 0), np.float32)
    no_dev = np.empty((0, 0), np.float32)
    from_f = find_segments(
        mask, d, ones, ones, 3, 0.5, (no_c, no_y, 0, 0, no_sp, no_dev, *pre), rule
    )
    return from_c, from_f, n_pix


@pytest.mark.parametrize("second", [True, False])
def test_find_segments_splits_two_returns_25_fwhm_apart_not_one(second):
    # the broad d alone never splits; the own pixel's photons split two returns 2.5 FWHM
    # apart in most pixels (8 photons each on average, about 6 in the half-peak window:
    # a Poisson z of 6 against the background's 0.1 there, above the sqrt(9 + 2 ln 29)
    # = 4.0 needed in a segment of 29 bins) and one return of the same 16 photons
    # never (its photons beyond min_sep are its own tail)
    from_c, from_f, n_pix = _close_pair_segments(second, 3.0)  # SPLIT_Z measured
    for a, b in zip(from_c, from_f, strict=True):
        np.testing.assert_array_equal(a, b)  # the null's way gives the map pass's segments
    col, stop, peak = from_c[1], from_c[3], from_c[4]
    n_seg = np.bincount(col, minlength=n_pix)
    assert np.all(n_seg >= 1)
    if second:
        assert np.mean(n_seg == 2) > 0.85  # 0.92: the rest short of photons (Poisson)
        two = np.flatnonzero(n_seg == 2)
        first = np.searchsorted(col, two)
        cut = stop[first]
        assert np.mean((cut > 30) & (cut < 38)) > 0.95  # cut between the returns
        assert np.median(np.abs(peak[first] - 30)) <= 1
        assert np.median(np.abs(peak[first + 1] - 37.5)) <= 1
    else:
        assert np.mean(n_seg > 1) < 0.02
    # without the fine split (z = 0): one segment per pixel, as d alone has
    off = _close_pair_segments(second, 0.0)[0]
    assert np.array_equal(off[1], np.arange(n_pix))


def test_find_segments_split_reach_keeps_close_pairs_not_far_bumps():
    # SPLIT_REACH 3 (FWHMs): a second return 2.5 FWHM behind the first is still split
    # off (measured 92 % of the pixels); one 4 FWHM behind (inside the same broad
    # segment of d) is split off without the reach (92 %) and nearly never with it (1 %:
    # the noisy peaks of the own response come within 3 FWHM)
    col = _close_pair_segments(True, 3.0, reach=3.0)[0][1]
    assert np.mean(np.bincount(col, minlength=300) == 2) > 0.85
    far = _close_pair_segments(True, 3.0, sep=12.0)[0][1]
    assert np.mean(np.bincount(far, minlength=300) == 2) > 0.85
    far = _close_pair_segments(True, 3.0, sep=12.0, reach=3.0)[0][1]
    assert np.mean(np.bincount(far, minlength=300) == 2) < 0.03


def test_coherent_keeps_an_added_return_beside_a_neighbours_candidate():
    # SPLIT_COHERENT: a return the fine split added (depth 58 behind a plane at 50) is
    # coherent when a 4-neighbour has a kept candidate within the tolerance (3 bins);
    # mode 2 also asks that neighbour to show a pair
    from splidar.detection._4_map import _coherent

    def table(extra):
        r, c = np.mgrid[0:5, 0:5]
        row = np.r_[r.ravel(), [e[0] for e in extra]]
        col = np.r_[c.ravel(), [e[1] for e in extra]]
        dep = np.r_[np.full(25, 50.0), [e[2] for e in extra]]
        return dict(row=row, col=col, depth_bin=dep), np.ones(row.size, bool)

    surf, keep = table([(2, 2, 58.0), (2, 3, 59.5), (0, 0, 58.0)])
    q = np.zeros(keep.size, bool)
    q[25:] = True
    # (2, 2) beside (2, 3)'s pair; (2, 3) beside (2, 2); (0, 0) alone at 58
    assert _coherent(surf, keep, (5, 5), q, 3.0).tolist()[25:] == [True, True, False]
    assert _coherent(surf, keep, (5, 5), q, 3.0, 2).tolist()[25:] == [True, True, False]
    # a neighbour's single return at that depth (a depth edge): coherent in mode 1 only
    surf, keep = table([(2, 2, 58.0)])
    surf["depth_bin"][2 * 5 + 3] = 57.0
    q = np.zeros(keep.size, bool)
    q[25] = True
    assert _coherent(surf, keep, (5, 5), q, 3.0)[25]
    assert not _coherent(surf, keep, (5, 5), q, 3.0, 2)[25]
    # a candidate that is not kept does not count
    keep[2 * 5 + 3] = False
    assert not _coherent(surf, keep, (5, 5), q, 3.0)[25]


def test_detect_fine_split_resolves_returns_the_coarse_scales_merge(monkeypatch):
    # end to end (map pass and the null's candidates split alike): a second surface 2.5
    # FWHM behind a gently tilted plane in every other column (the close-pair case of
    # bench_robustness, PPP 10, SBR 1): the coarse boxes halve it and fill the dip, so
    # with SPLIT_Z = 0 (off) most of those pixels keep one merged surface; at 3 (the
    # default) five times as many get both
    from splidar import PointSet
    from splidar.detection import _detect
    from splidar.simulation import simulate

    n, T = 24, 120
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    dep = 50.0 + 0.35 * (rr + cc).ravel()
    even = (cc % 2 == 0).ravel()
    truth = PointSet(
        row=np.concatenate([rr.ravel(), rr.ravel()[even]]),
        col=np.concatenate([cc.ravel(), cc.ravel()[even]]),
        depth_bin=np.concatenate([dep, dep[even] + 7.5]), image_shape=(n, n),
    )  # fmt: skip
    cube = simulate(truth, n_bins=T, irf=gaussian_irf(3.0), ppp=10.0, sbr=1.0, rng=0).cube
    both = {}
    # (SPLIT_Z, SPLIT_REACH, SPLIT_COHERENT, SPLIT_TAIL_SLACK): with the reach, the
    # coherence and the slack rules the pairs (within 3 FWHM, a neighbour showing them
    # too, weak returns' tails a fraction of a photon) stay
    runs = ((0.0, 0.0, 0, 0.0), (3.0, 0.0, 0, 0.0), (3.0, 3.0, 1, 3.0), (3.0, 3.0, 2, 0.0))
    for z, reach, coh, slack in runs:
        for mod in (_4_map, _detect):
            monkeypatch.setattr(mod, "SPLIT_Z", z)
            monkeypatch.setattr(mod, "SPLIT_REACH", reach)
            monkeypatch.setattr(mod, "SPLIT_TAIL_SLACK", slack)
        monkeypatch.setattr(_4_map, "SPLIT_COHERENT", coh)
        p = detect(cube, rng=0).points
        k = p.row * n + p.col
        front = np.bincount(k[np.abs(p.depth_bin - dep[k]) <= 2], minlength=n * n)
        back = np.bincount(k[np.abs(p.depth_bin - dep[k] - 7.5) <= 2], minlength=n * n)
        both[z, reach, coh, slack] = np.mean(((front > 0) & (back > 0))[even])
    # measured 0.10 / 0.53 / 0.51 (the defaults) / 0.40 of those pixels (the rest: the
    # second return's few photons; mode 2 also needs a neighbour's pair, only half of
    # them have both)
    off, split, near, pair = both.values()
    assert off < 0.2 and split > 0.4 and near > 0.4 and pair > 0.3, both


def _tailed_pair_segments(
    front, back, sep, T, back_at, n_pix=300, seed=5, rows=1, pool=0.0, irf=None, span=None
):
    """find_segments (defaults: z 3, reach 3, slack 3) on pixels whose IRF carries an
    exponential tail (Gaussian FWHM 3 convolved with exp(-t / 2): FWHM 5, a SPAD's
    shape) and whose broad multiscale response merges a weaker return of ``front``
    photons ``sep`` bins in front of one of ``back`` photons at ``back_at`` (a net
    before a wall); background 0.025 a bin; ``rows`` x ``n_pix`` pixels, the split's
    pooled test ``pool`` (``split_rule(pool=)``); ``irf``: another IRF; ``span``: the
    segments' mask width (default ``sep``). Returns (fraction of pixels whose
    front return is a segment of its own, whether the null's way gives the same
    segments, fraction whose front segment is not flagged ``added``)."""
    if irf is None:
        irf = np.convolve(gaussian_irf(3.0, length=61), np.exp(-np.arange(61) / 2.0))[:61]
    g = (irf / irf.sum()).reshape(1, -1)
    n_irf = g.shape[1]
    p0 = int(np.argmax(g[0]))
    x = np.arange(T)
    lam = np.full((rows, n_pix, 1, T), 0.025)
    for centre, n in [(back_at - sep, front), (back_at, back)]:
        lam[..., :] += n * np.interp(x - centre + p0, np.arange(n_irf), g[0], left=0, right=0)
    y = np.random.default_rng(seed).poisson(lam).astype(np.uint16)
    c = Correlator(g, T)(y, workers=1)
    sp = np.full((rows, n_pix, 1), 0.025, np.float32)
    dev = np.zeros((1, T), np.float32)
    d = np.exp(-0.5 * ((x - back_at + sep / 2) / (span or sep)) ** 2)
    d = np.ascontiguousarray(np.broadcast_to(d, (rows, n_pix, T)), np.float32)
    mask = np.ascontiguousarray(d > 0.05)
    ones = np.ones_like(d)
    rule = split_rule(g, 3.0, None, 3.0, 3.0, pool)
    no = np.empty((0, 0, 0), np.float32)
    out = find_segments(mask, d, ones, ones, 3, 0.5, (c, y, 0, 0, sp, dev, no, no, no), rule)
    pre = tuple(np.empty((rows, n_pix, T), np.float32) for _ in range(3))
    fine_response(c, y, sp, dev, rule[3], *pre)
    empty = (np.empty((0,) * 4, np.float32), np.empty((0,) * 4, np.uint16), 0, 0)
    nulls = (np.empty((0, 0, 0), np.float32), np.empty((0, 0), np.float32))
    out_f = find_segments(mask, d, ones, ones, 3, 0.5, (*empty, *nulls, *pre), rule)
    same = all(np.array_equal(a, b) for a, b in zip(out, out_f, strict=True))
    px, peak = out[0] * n_pix + out[1], out[4]
    n_all = rows * n_pix
    two = np.bincount(px, minlength=n_all) >= 2
    hit = np.zeros(n_all, bool)
    near = np.abs(peak - (back_at - sep)) <= 2
    hit[px[near]] = True
    own = np.zeros(n_all, bool)  # the front part is the segment's own, not an added one
    own[px[near & ~out[7]]] = True
    return float(np.mean(hit & two)), same, float(np.mean(own & two))


def test_find_segments_pools_the_neighbourhood_for_a_weaker_return_in_front():
    # 4 photons 2.1 FWHM in front of 30 with a tailed IRF in every pixel of 12 x 25: the
    # own pixel's photons often miss the look-elsewhere bound sqrt(9 + 2 ln n), the 3 x 3
    # neighbourhood's at the same place relative to their own return (with the own
    # pixel's z >= 3 there) beat it (measured split in 0.55 of the pixels pooled, 0.38
    # without); one tailed return of 40 is still never split, and the null's way
    # (stored fine responses) gives the map's segments
    args = (10.5, 100, 60.0, 25)
    pooled, same, _ = _tailed_pair_segments(4.0, 30.0, *args, rows=12, pool=True)
    alone, _, _ = _tailed_pair_segments(4.0, 30.0, *args, rows=12, pool=False)
    assert pooled > 0.47 and alone < 0.45 and same, (pooled, alone)
    one, same, _ = _tailed_pair_segments(0.0, 40.0, *args, rows=12, pool=True)
    assert one < 0.02 and same, one


def test_find_segments_never_pools_behind_a_stronger_return():
    # a weaker return behind a tailed one lies in its tail: the pooled test is not
    # applied there (the neighbours' tails heavier than the pooled one would add up)
    args = (5.0, 30.0, -10.5, 100, 45.0, 25)
    on = _tailed_pair_segments(*args, rows=12, pool=True)
    off = _tailed_pair_segments(*args, rows=12, pool=False)
    assert on == off, (on, off)


def test_find_segments_never_pools_a_return_off_its_own_tail():
    # one return of 6 or 10 photons whose IRF has a 25-bin exponential tail (FWHM 19.6):
    # a noise bump in its tail can be the segment's strongest peak, the real return then
    # "in front" of it; the pooled test may show that one, but the bump's photons do not
    # beat the real return's tail, so no split (measured without that check: 0.25 and
    # 0.75 % of 1,200 pixels split, the bump a false surface; bench_robustness "exp
    # tail 2/25" 76 -> 87 false surfaces)
    g = exp_tail_irf(2.0, 25.0)
    for back, seed in ((6.0, 5), (10.0, 5), (10.0, 6)):
        args = (0.0, back, 0.0, 400, 150.0, 100)
        split, same, _ = _tailed_pair_segments(
            *args, seed=seed, rows=12, pool=True, irf=g, span=60.0
        )
        assert split == 0.0 and same, (back, seed, split)


def test_find_segments_finds_a_weaker_return_in_front_of_a_tailed_one():
    # 6 photons 2.1 FWHM in front of 30 whose IRF has a tail behind its peak: the
    # stronger return's tail is taken on its own side, so the front one is tested
    # against the rise of the return behind it (measured 0.65; 0.07 when the tail
    # behind the peak was taken on both sides); one tailed return never splits
    front, same, _ = _tailed_pair_segments(6.0, 30.0, 10.5, 100, 60.0)
    assert front > 0.5 and same, front
    one, same, _ = _tailed_pair_segments(0.0, 40.0, 10.5, 100, 60.0)
    assert one < 0.02 and same, one


def test_find_segments_a_part_cut_by_the_window_end_is_never_the_segments_own():
    # the stronger return peaks 3 bins before the window's end, its half-peak window
    # (the tail's side) past the last bin (a wall at the window's end behind a net):
    # where the split cuts it off as a part of its own, that part is not the segment's
    # own; the weaker return in front is (measured 0.21 of the pixels, split in 0.50;
    # 0 when the stronger part was always the own one, so that on a wall peaking past
    # the window's end the net lost its segment to the wall's visible rise)
    front, same, own = _tailed_pair_segments(6.0, 40.0, 10.5, 80, 77.0)
    assert front > 0.4 and same, front
    assert own > 0.15, (own, front)


def _tailed_cube(n, T, sep, amp, rng):
    # a tilted plane (and with sep a second one sep bins behind in every pixel) whose
    # returns carry an exponential tail (70 % of the photons, 1/e length 2 FWHM: the
    # real face's at 1 FWHM) that the Gaussian IRF the cube is given lacks
    from splidar import Cube

    g = gaussian_irf(3.0, length=61)
    tail = np.convolve(g, np.exp(-np.arange(61) / 6.0))[:61]
    shape = 0.3 * g + 0.7 * tail / tail.sum()
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    dep = (40 + 0.2 * (rr + cc)).astype(int)
    lam = np.full((n, n, 1, T), 0.03)
    for i in range(n):
        for j in range(n):
            for d0 in (dep[i, j],) if sep is None else (dep[i, j], dep[i, j] + sep):
                lam[i, j, 0, d0 - 30 : d0 + 31] += amp * shape
    return Cube(rng.poisson(lam), irf=gaussian_irf(3.0))


def test_data_tail_measures_a_tail_the_irf_lacks_not_a_second_return():
    from splidar import PointSet
    from splidar.detection import _3_null
    from splidar.simulation import simulate

    irf = gaussian_irf(3.0)[None] / gaussian_irf(3.0).sum()
    t_irf = split_rule(irf, 3.0)[1]
    one = _tailed_cube(24, 160, None, 20.0, np.random.default_rng(1))
    t_one = _3_null.data_tail(one.counts, irf, np.zeros((1, 160), np.float32))
    # 1.7-2.3 FWHM behind the peak the tailed returns put over 5 % of their photons in
    # a half-peak window (measured 9-15 %), the IRF under 1 %; in front of the peak
    # (each side its own) under a fifth of that (measured 0.7-2.8 %, the peaks' jitter)
    assert np.all(t_one[0, 5:8] > 0.05) and np.all(t_irf[:, 5:8] < 0.01), (t_one, t_irf)
    assert np.all(t_one[1, 5:8] < 0.2 * t_one[0, 5:8]), t_one
    # a second (Gaussian) return 2.5 FWHM behind every first one: the pool rises
    # again past the dip, where the data's tail ends (measured 0 from 1.7 FWHM on)
    rr, cc = np.meshgrid(np.arange(24), np.arange(24), indexing="ij")
    dep = 50.0 + 0.35 * (rr + cc).ravel()
    truth = PointSet(
        row=np.tile(rr.ravel(), 2), col=np.tile(cc.ravel(), 2),
        depth_bin=np.concatenate([dep, dep + 7.5]), image_shape=(24, 24),
    )  # fmt: skip
    pair = simulate(truth, n_bins=120, irf=gaussian_irf(3.0), ppp=10.0, sbr=1.0, rng=0).cube
    t_pair = _3_null.data_tail(pair.counts, irf, np.zeros((1, 120), np.float32))
    assert np.all(t_pair[:, 5:10] < 0.01), t_pair


def test_detect_fine_split_leaves_a_tail_the_irf_lacks(monkeypatch):
    # end to end, SPLIT_Z = 3: returns with a tail the IRF lacks. With the default
    # rules (reach, coherence, slack) a second surface in 3 % of the pixels (measured
    # 0.028); two such returns 4 FWHM apart are both found in nearly every pixel
    # (0.986). Without those rules (the data's tail alone), 3 % with the data's tail
    # and 7 % with the IRF's alone (measured 0.028 / 0.069)
    from splidar.detection import _3_null, _detect

    for mod in (_4_map, _detect):
        monkeypatch.setattr(mod, "SPLIT_Z", 3.0)
    n = 24

    def twice(cube):
        p = detect(cube, rng=0).points
        return np.mean(np.bincount(p.row * n + p.col, minlength=n * n) > 1)

    one = _tailed_cube(n, 160, None, 40.0, np.random.default_rng(2))
    two = _tailed_cube(n, 160, 12, 40.0, np.random.default_rng(2))
    dflt, both = twice(one), twice(two)
    assert dflt < 0.045 and both > 0.95, (dflt, both)
    for mod in (_4_map, _detect):
        monkeypatch.setattr(mod, "SPLIT_REACH", 0.0)
        monkeypatch.setattr(mod, "SPLIT_TAIL_SLACK", 0.0)
    monkeypatch.setattr(_4_map, "SPLIT_COHERENT", 0)
    data = twice(one)
    monkeypatch.setattr(_3_null, "data_tail", lambda *a, **k: np.zeros(0))
    irf_only = twice(one)
    assert data < 0.045 and irf_only > 1.8 * data, (data, irf_only)


def _plane_with(extra):
    """Candidates: a plane at depth 50 over 24 x 24 pixels, plus ``extra`` (row, col,
    depth) second candidates; all kept."""
    r, c = np.mgrid[0:24, 0:24]
    row = np.concatenate([r.ravel(), [e[0] for e in extra]])
    col = np.concatenate([c.ravel(), [e[1] for e in extra]])
    depth = np.concatenate([np.full(r.size, 50.0), [float(e[2]) for e in extra]])
    return row, col, depth, np.ones(row.size, bool)


def test_stray_clusters_removes_a_small_cluster_behind_a_pixels_surface():
    from splidar.detection._5f_stray_clusters import stray_clusters

    # a 2-pixel cluster at depth 120 behind the plane, nothing else there within reach
    row, col, depth, keep = _plane_with([(5, 5, 120.0), (5, 6, 121.0)])
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert out.tolist() == [False] * 576 + [True, True]
    # the same pixels' only candidates (no plane there) are never removed
    far = (row < 5) | (row > 5) | (col < 5) | (col > 6) | (np.arange(row.size) >= 576)
    out = stray_clusters(row[far], col[far], depth[far], keep[far], image_shape=(24, 24),
                         fwhm=3.0, half=5)  # fmt: skip
    assert not out.any()
    # a rejected candidate (keep False) neither counts nor is removed
    keep2 = keep.copy()
    keep2[-1] = False
    out = stray_clusters(row, col, depth, keep2, image_shape=(24, 24), fwhm=3.0, half=5)
    assert out.tolist() == [False] * 576 + [True, False]


def test_stray_clusters_keeps_lines_and_the_fragments_of_a_thin_structure():
    from splidar.detection._5f_stray_clusters import stray_clusters

    # a strand along row 10 (a line of 24 second candidates) is one large cluster
    row, col, depth, keep = _plane_with([(10, j, 20.0) for j in range(24)])
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert not out.any()
    # its fragments of 2 pixels with gaps of 4 (the map missed the rest) join within
    # the reach (2 x the largest box's half-width): kept
    frag = [(10, j, 20.0 + 0.1 * j) for j in range(24) if j % 6 < 2]
    row, col, depth, keep = _plane_with(frag)
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert not out.any()
    # beyond the reach (half-width 1: 2 pixels) the same fragments are stray
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=1)
    assert out[576:].all() and not out[:576].any()
    # a second candidate at another depth beside the fragments does not join them
    frag3 = [(3, 3, 20.0), (3, 4, 160.0), (3, 12, 161.0)] + [(12, j, 160.0) for j in range(8)]
    row, col, depth, keep = _plane_with(frag3)
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert out[576:].tolist() == [True] + [False] * 10


def test_stray_clusters_small_clusters_vouch_for_each_other_only_as_a_large_group():
    from splidar.detection._5f_stray_clusters import MAX_CLUSTER, stray_clusters

    # two stray 1- and 2-pixel clusters at one depth, 8 pixels apart (within the reach):
    # 3 members in all, no more than MAX_CLUSTER, and no large cluster there: stray
    extra = [(3, 4, 160.0), (3, 12, 161.0), (4, 12, 161.5)]
    assert len(extra) <= MAX_CLUSTER
    row, col, depth, keep = _plane_with(extra)
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert out[576:].all() and not out[:576].any()
    # a third one along the same line makes a group of MAX_CLUSTER + 1 members: kept
    # (the fragments of a thin structure whose other pixels the map missed)
    row, col, depth, keep = _plane_with(extra + [(3, 20, 162.0), (4, 20, 162.0)])
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert not out.any()
    # a large cluster (a region or a line) at that depth within the reach vouches for
    # a single stray pixel too
    row, col, depth, keep = _plane_with([(3, 4, 160.0)] + [(12, j, 160.0) for j in range(6)])
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=5)
    assert not out.any()
    # beyond the reach (half-width 2: 6 pixels) it does not
    out = stray_clusters(row, col, depth, keep, image_shape=(24, 24), fwhm=3.0, half=2)
    assert out[576] and not out[577:].any()


def test_detect_stray_clusters_removes_only_candidates_of_crowded_pixels(net_map):
    # stages 7 and 7b left out on both sides: they move depths after the pass; so is
    # stage 5g (its whole-image decision reads the candidates 5f leaves)
    sim, _, _ = net_map
    passes = [p for p in PASSES if p not in ("unlayered", "align_depths", "edge_bands")]
    on = detect(sim.cube, rng=0, passes=passes)
    off = detect(sim.cube, rng=0, passes=[p for p in passes if p != "stray_clusters"])
    rec = {r.stage: r for r in on.provenance}["stray_clusters"]
    assert rec.ran and rec.added == 0 and rec.removed > 0

    def key(s):
        return set(zip(s.row.tolist(), s.col.tolist(), s.depth_bin.tolist(), strict=True))

    gone, new = key(off.surfaces) - key(on.surfaces), key(on.surfaces) - key(off.surfaces)
    assert not new and len(gone) == rec.removed
    # every pixel that lost a surface keeps one
    kept = set(zip(on.surfaces.row.tolist(), on.surfaces.col.tolist(), strict=True))
    assert {(r, c) for r, c, _ in gone} <= kept


def test_calibrate_null_measures_the_data_tail_beside_the_patches(monkeypatch):
    # with n_jobs > 1 an in-memory cube's data_tail runs on a thread of its own (beside
    # the null's patches); the calibration is the same as on one thread
    import threading

    from splidar.detection import _3_null

    sim = two_layer_scene((24, 24), n_bins=120).simulate(ppp=4, sbr=0.25, rng=1)
    counts = np.asarray(sim.cube.counts)
    _, _, filters = _setup(counts, sim.cube.irf)
    where, tail = [], _3_null.data_tail

    def spy(*args, **kwargs):
        where.append(threading.get_ident())
        return tail(*args, **kwargs)

    monkeypatch.setattr(_3_null, "data_tail", spy)
    out = {}
    for n_jobs in (1, 2):
        out[n_jobs] = calibrate_null(
            counts, filters, pfa=1e-3, surface_pfa=0.01, null="empirical", min_separation=3,
            split=(0.5, _4_map.SPLIT_Z, 3.0, 0.0), rng=np.random.default_rng(0), n_jobs=n_jobs,
        )  # fmt: skip
    assert where[0] == threading.get_ident() and where[1] != threading.get_ident()
    a, b = out[1], out[2]
    assert a.evidence_threshold == b.evidence_threshold
    np.testing.assert_array_equal(a.thresholds, b.thresholds)
    for x, y in zip(a.split, b.split, strict=True):
        np.testing.assert_array_equal(x, y)


def test_fine_on_threads_equals_one_fine_response_call():
    from splidar.detection._3_null import _fine_on_threads

    rng = np.random.default_rng(8)
    g = gaussian_irf(3.0)[None]
    y = rng.poisson(0.3, size=(13, 11, 1, 80)).astype(np.uint16)
    c = np.asarray(Correlator(g, 80)(y.astype(np.float32)), np.float32)
    sp = rng.uniform(0.1, 0.4, size=(13, 11, 1)).astype(np.float32)
    dev = np.zeros((1, 80), np.float32)
    win = split_rule(g, 0.0)[3]
    sl = (slice(2, 12), slice(1, 10))  # a patch's interior: views, as the null passes
    ref = tuple(np.empty((10, 9, 80), np.float32) for _ in range(3))
    fine_response(c[sl], y[sl], sp[sl], dev, win, *ref)
    for workers in (1, 3):
        out = tuple(np.full((10, 9, 80), np.nan, np.float32) for _ in range(3))
        _fine_on_threads(c[sl], y[sl], sp[sl], dev, win, out, workers)
        for a, b in zip(out, ref, strict=True):
            np.testing.assert_array_equal(a, b)


def _coherent_reference(surf, keep, image_shape, query, tol, mode):
    """Stage 4's coherence rule for the fine split's returns, as a plain loop."""
    R, C = image_shape
    row, col, dep = surf["row"], surf["col"], surf["depth_bin"]
    out = np.zeros(row.size, bool)
    for i in np.flatnonzero(query):
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            rr, cc = row[i] + dr, col[i] + dc
            if not (0 <= rr < R and 0 <= cc < C):
                continue
            nb = dep[keep & (row == rr) & (col == cc)]
            if np.any(np.abs(nb - dep[i]) <= tol) and (
                mode < 2 or (nb.size >= 2 and np.ptp(nb) >= tol)
            ):
                out[i] = True
    return out


@pytest.mark.parametrize("mode", [1, 2])
def test_coherent_equals_a_plain_loop_over_the_queries(mode):
    rng = np.random.default_rng(7)
    R, C = 9, 11
    n = 260
    surf = dict(
        row=rng.integers(0, R, n).astype(np.int32),
        col=rng.integers(0, C, n).astype(np.int32),
        depth_bin=rng.choice([20.0, 23.0, 40.0], n) + rng.normal(0, 1.5, n),
    )
    keep = rng.random(n) < 0.7
    query = rng.random(n) < 0.5
    got = _4_map._coherent(surf, keep, (R, C), query, 3.0, mode)
    ref = _coherent_reference(surf, keep, (R, C), query, 3.0, mode)
    assert ref.any() and not ref[query].all()
    np.testing.assert_array_equal(got, ref)


def test_raster_sorted_is_true_exactly_when_lexsort_keeps_the_order():
    rng = np.random.default_rng(4)
    for n in (0, 1, 2, 5, 40):
        for _ in range(200):
            row = np.sort(rng.integers(0, 3, n)).astype(np.int32)
            col = rng.integers(0, 3, n).astype(np.int32)
            start = rng.integers(0, 4, n).astype(np.int32)
            if rng.random() < 0.5:  # raster order, or a near miss of it
                o = np.lexsort((start, col, row))
                row, col, start = row[o], col[o], start[o]
                if n > 1 and rng.random() < 0.3:
                    i = rng.integers(0, n - 1)
                    start[[i, i + 1]] = start[[i + 1, i]]
            order = np.lexsort((start, col, row))
            ref = not np.any(order[1:] < order[:-1])
            assert _4_map._raster_sorted(row, col, start) == ref


# pre37: stages 1-3's set-up in fewer passes, the same values


@pytest.mark.parametrize("workers", [1, 3])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint32, np.int32])
def test_first_read_equals_pixel_totals_and_the_grid_window_means(workers, dtype):
    from splidar.detection._background import first_read, grid_window_means, sample_grid
    from splidar.detection._fast import pixel_totals

    rng = np.random.default_rng(7)
    y = rng.poisson(rng.random((53, 47, 2, 40)) * 3).astype(dtype)
    y[5, 6] += 60000  # a bright pixel: integer sums
    got = first_read(y, 11, workers, n_samples=200)
    kr, kc, rs, cs = sample_grid(y.shape, 11, 200)
    assert got is not None and np.diff(rs).min() >= kr and rs[-1] + kr < y.shape[0]
    np.testing.assert_array_equal(got.totals, pixel_totals(y))
    np.testing.assert_array_equal(got.means, grid_window_means(y, rs, kr, cs, kc))
    # the grid asked for: the means kept; another: read from the counts
    assert got.windows(y, rs, kr, cs, kc) is got.means
    np.testing.assert_array_equal(
        got.windows(y, rs[:2], kr, cs, kc), grid_window_means(y, rs[:2], kr, cs, kc)
    )


def test_first_read_none_for_overlapping_windows_floats_and_views():
    from splidar.detection._background import first_read

    rng = np.random.default_rng(1)
    y = rng.poisson(1.0, (20, 20, 1, 30)).astype(np.uint16)
    assert first_read(y, 11) is None  # small image: windows at every row (overlapping)
    big = rng.poisson(1.0, (60, 60, 1, 30)).astype(np.uint16)
    assert first_read(big.astype(np.float32), 11, n_samples=100) is None
    assert first_read(big.astype(np.int64), 11, n_samples=100) is None
    assert first_read(big[:, ::2], 11, n_samples=100) is None
    assert first_read(big, 11, n_samples=100) is not None


def test_summed_area_equals_numpy_running_sums_on_any_threads():
    from splidar.detection._2_saliency import _summed_area

    rng = np.random.default_rng(2)
    x = (rng.standard_normal((9, 7, 3, 50)) * 5).astype(np.float32)
    x[0, 0, 0, :3] = -0.0
    want = np.zeros((10, 8, 3, 50))
    np.cumsum(x, axis=0, dtype=np.float64, out=want[1:, 1:])
    np.cumsum(want[1:, 1:], axis=1, out=want[1:, 1:])
    for workers in (1, 2, 5):
        got = _summed_area(x, workers)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(want))


def test_coherent_scales_same_on_any_number_of_threads():
    import dataclasses

    from splidar.detection._2_saliency import coherent_scales

    rng = np.random.default_rng(3)
    g = gaussian_irf(2.0)
    lam = np.full((40, 40, 1, 120), 0.05)
    h = g.size // 2
    for j in range(40):
        lam[:, j, 0, 50 + j // 4 - h : 50 + j // 4 + h + 1] += 4 * g
    counts = rng.poisson(lam).astype(np.uint16)
    irf, bg, filters = _setup(counts, g)
    one = coherent_scales(counts, filters)
    two = coherent_scales(counts, dataclasses.replace(filters, workers=3))
    for f in ("kept", "rho", "z", "energy", "shared"):
        np.testing.assert_array_equal(getattr(one, f), getattr(two, f))


def test_threshold_table_same_on_any_number_of_threads():
    from splidar.detection._null import threshold_table

    rng = np.random.default_rng(4)
    lev = (rng.random(400)[:, None] + np.linspace(0, 0.2, 900)[None]).astype(np.float32).ravel()
    s = rng.gamma(2.0, 1.0, lev.size).astype(np.float32)
    one = threshold_table(s, lev, 1e-3)
    for workers in (2, 5):
        got = threshold_table(s, lev, 1e-3, workers=workers)
        np.testing.assert_array_equal(got[0], one[0])
        np.testing.assert_array_equal(got[1], one[1])
    assert one[0].size == 3


def test_equal_count_groups_nan_levels_as_the_boolean_passes():
    from splidar.detection._null import _equal_count_groups

    rng = np.random.default_rng(5)
    v = rng.random(5000)
    v[::97] = np.nan
    sizes = np.full(6, 5000 // 6)
    sizes[: 5000 % 6] += 1
    kth = np.cumsum(sizes)[:-1]  # each group's first sorted position
    b = np.partition(v, kth)[kth]
    gid = np.zeros(v.size, np.uint8)
    for bi in b:
        gid += v >= bi
    for bi, m in zip(b, kth - np.array([np.count_nonzero(v < bi) for bi in b]), strict=True):
        if m > 0:
            gid[np.flatnonzero(v == bi)[:m]] -= 1
    for i, got in enumerate(_equal_count_groups(v, 6)):
        np.testing.assert_array_equal(got, np.flatnonzero(gid == i))


def test_median_ties_equals_numpy_median_on_tied_counts():
    from splidar.detection._3_null import _median_ties

    rng = np.random.default_rng(6)
    for n in (1, 2, 3, 10, 151, 1500):
        for a in (
            rng.random(n).astype(np.float32),
            rng.integers(0, 3, n).astype(np.float32),  # ties everywhere
            np.zeros(n, np.float32),
        ):
            assert _median_ties(a.copy(), n) == np.median(a)


def test_peak_bins_equal_numpys_argmax_of_the_background_free_sum():
    from splidar.detection._3_null import _peak_bins

    rng = np.random.default_rng(8)
    for L, T in ((1, 40), (3, 164), (4, 301)):
        c = (rng.poisson(0.4, (300, L, T)) * rng.random((300, L, T))).astype(np.float32)
        c[:100] = np.round(c[:100])  # tied sums: the first of the largest
        dv = (rng.standard_normal((L, T)) * 0.2).astype(np.float32)
        lvl = np.median(c, axis=-1) - np.median(dv, axis=-1)[None]
        want = np.argmax((c - np.maximum(lvl[:, :, None] + dv[None], 0.0)).sum(axis=1), axis=1)
        got = np.empty(300, np.int64)
        _peak_bins(c, dv, np.median(dv, axis=-1).astype(np.float32), got)
        np.testing.assert_array_equal(got, want)


def test_first_read_reads_a_memory_map(tmp_path):
    from splidar.detection._background import first_read

    rng = np.random.default_rng(9)
    y = rng.poisson(1.0, (60, 60, 1, 30)).astype(np.uint16)
    np.save(tmp_path / "y.npy", y)
    mm = np.load(tmp_path / "y.npy", mmap_mode="r")
    got, want = first_read(mm, 11, 2, n_samples=100), first_read(y, 11, 1, n_samples=100)
    np.testing.assert_array_equal(got.totals, want.totals)
    np.testing.assert_array_equal(got.means, want.means)


def test_take_rows_equals_indexing_and_astype_on_any_number_of_threads(monkeypatch):
    # select_surfaces' columns: the selected rows in parts on threads, cast as astype
    from splidar.detection import _6_select
    from splidar.detection._6_select import _take_rows

    monkeypatch.setattr(_6_select, "TAKE_PART", 16)
    rng = np.random.default_rng(5)
    idx = np.sort(rng.choice(1000, 700, replace=False))
    cols = (
        rng.integers(-5, 900, 1000).astype(np.int32), rng.random(1000),
        rng.random((1000, 3, 2)).astype(np.float32), rng.integers(0, 9, (1000, 2)),
    )  # fmt: skip
    for a in cols:
        for dtype in (a.dtype, np.float64, np.int64):
            want = a[idx].astype(dtype, copy=False)
            for n_jobs in (1, 2, 3, 64):
                got = _take_rows(a, idx, dtype, n_jobs)
                assert got.dtype == want.dtype and got.shape == want.shape
                assert got.tobytes() == want.tobytes()


def test_rescue_dark_same_on_any_number_of_threads(monkeypatch):
    # the candidates' own sums and the suspects' pools in parts on threads: each its own
    from splidar.detection import _quality
    from splidar.detection._quality import rescue_dark

    monkeypatch.setattr(_quality, "_DARK_PART", 9)
    monkeypatch.setattr(_quality, "_DARK_POOL_PART", 4)
    g = np.asarray(gaussian_irf(2.0), float)[None]
    rng = np.random.default_rng(8)
    R, C, W = 18, 16, 13
    r, c = (a.ravel() for a in np.mgrid[0:R, 0:C])
    r, c = np.repeat(r, 2), np.repeat(c, 2)
    n = r.size
    depth = np.where(rng.random(n) < 0.7, 6.0, rng.uniform(2.0, 10.0, n))
    cnt = rng.poisson(0.06, (n, 1, W)).astype(np.int32)
    cnt[np.arange(n), 0, np.round(depth).astype(int)] += rng.poisson(0.7, n).astype(np.int32)
    surf = dict(
        row=r, col=c, depth_bin=depth, offset=np.zeros(n, int), own_counts=cnt,
        own_background=np.full((n, 1, W), 0.05, np.float32), evidence=rng.random(n),
        image_shape=(R, C),
    )  # fmt: skip
    keep = rng.random(n) < 0.3
    kw = dict(irf=g, peak=np.array([g.argmax()]), fwhm=4.7, half=3, pfa=0.01, llr_level=-3.0)
    one = rescue_dark(surf, keep, **kw)
    assert 10 < one.sum() < (~keep).sum()
    for n_jobs in (2, 3, 8):
        np.testing.assert_array_equal(rescue_dark(surf, keep, n_jobs=n_jobs, **kw), one)
    # the pools' sums themselves, bit for bit
    order, starts = _quality._by_pixel(r.astype(np.int64), c.astype(np.int64), (R, C))
    args = (
        r.astype(np.int64), c.astype(np.int64), depth, np.zeros(n, np.int64), cnt,
        surf["own_background"], keep, surf["evidence"], order, starts, R, C, g,
        np.array([g.argmax()], np.float64), 2.35, 4.7, 3, 3.0,
    )  # fmt: skip
    want = _quality._dark_pools(*args, 1)
    assert want[0].size > 20
    for n_jobs in (2, 5):
        got = _quality._dark_pools(*args, n_jobs)
        assert all(a.tobytes() == b.tobytes() for a, b in zip(got, want, strict=True))
