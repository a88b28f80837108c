"""splidar.io.estimate_irf: the non-parametric IRF shape from the data."""

from __future__ import annotations

import numpy as np
import pytest

import splidar
from splidar import PointSet, SplidarError
from splidar.io import estimate_irf
from splidar.irf import exp_tail_irf, gaussian_irf, irf_fwhm
from splidar.simulation import simulate


def _cube(irf, *, n=32, T=200, ppp=20.0, sbr=2.0, second=None, seed=0):
    """A tilted plane (depths 40..100 bins) on n x n pixels; ``second``: a surface that
    many bins behind it in every pixel."""
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    depth = (40.0 + 60.0 * (rr + cc) / (2 * n - 2)).ravel()
    row, col, dep = rr.ravel(), cc.ravel(), depth
    if second is not None:
        row, col, dep = np.r_[row, row], np.r_[col, col], np.r_[dep, dep + second]
    truth = PointSet(row=row, col=col, depth_bin=dep, image_shape=(n, n))
    sim = simulate(truth, n_bins=T, irf=irf, ppp=ppp, sbr=sbr, rng=seed)
    return sim.cube


def _on_common_grid(a, b):
    """Both IRFs (1-D) on one grid with their peaks on the same sample."""
    pa, pb = int(np.argmax(a)), int(np.argmax(b))
    o = max(pa, pb)
    n = o + max(a.size - pa, b.size - pb)
    x, y = np.zeros(n), np.zeros(n)
    x[o - pa : o - pa + a.size] = a
    y[o - pb : o - pb + b.size] = b
    return x, y, o


def _best_offset(true, est):
    """Where ``est`` (1-D) best correlates with ``true``: ``est[k]`` on ``true[k + shift]``."""
    c = np.correlate(np.pad(true, (est.size, est.size)), est, mode="valid")
    return int(np.argmax(c)) - est.size


def _peak_offset(true, est):
    """Depth offset the estimate's reference (argmax) puts on a return of the true pulse:
    the estimate placed where it best correlates with the true pulse, read at its argmax."""
    return _best_offset(true, est) + int(np.argmax(est)) - int(np.argmax(true))


def test_estimate_irf_recovers_exp_tail_shape():
    true = exp_tail_irf(2.0, 6.0)
    true = true / true.sum()
    cube = _cube(true)
    est = estimate_irf(cube.counts)
    assert est.shape[0] == 1 and np.isclose(est.sum(), 1.0) and np.all(est >= 0)
    # the shapes placed where they best correlate (the reference, the argmax, is tested
    # below: on this pulse the sample after the peak is 0.9 of it, and the estimate's
    # argmax may sit on either). Measured on this seed: L1 0.074 (refine=False 0.098),
    # FWHM 7.1 vs 6.2 bins, tail mass beyond +5 bins of the true peak 0.36 vs 0.38; a
    # Gaussian of the true FWHM is at L1 0.72 and tail mass 0.04
    sh = _best_offset(true, est[0])
    t = np.pad(true, (est.shape[1], est.shape[1]))
    e = np.zeros_like(t)
    e[est.shape[1] + sh : 2 * est.shape[1] + sh] = est[0]
    o = est.shape[1] + int(np.argmax(true))
    assert np.abs(t - e).sum() < 0.15
    assert abs(irf_fwhm(e) / irf_fwhm(t) - 1.0) < 0.3
    assert abs(e[o + 5 :].sum() - t[o + 5 :].sum()) < 0.08


def test_estimate_irf_reference_offset_within_one_bin_on_exp_tail():
    # exp tail 2/6, PPP 20: offsets measured on seeds 0-5: 1 / 1 / 0 / 1 / 0 / 1 bins
    # (refine=False: 0 / 1 / 1 / 0 / 1 / 1): the sample after this pulse's peak is 0.9
    # of it, and whole-bin alignment of sub-bin depths flattens the top by half a bin
    true = exp_tail_irf(2.0, 6.0)
    true = true / true.sum()
    est = estimate_irf(_cube(true, seed=1).counts)[0]
    assert abs(_peak_offset(true, est)) <= 1


def test_estimate_irf_soft_alignment_keeps_peak_of_tailed_pulse():
    # exp tail 3/6, PPP 20, sub-bin depths: the hard alignment's jitter moves the peak of
    # its pooled curve one bin into the tail on seeds 2-5 of 0-5 (offsets 0 0 1 1 1 1);
    # the soft alignment (EM over each pixel's shift) keeps it on the true peak on all six
    true = exp_tail_irf(3.0, 6.0)
    true = true / true.sum()
    for seed in (2, 3):
        counts = _cube(true, seed=seed).counts
        hard = estimate_irf(counts, refine=False)[0]
        soft = estimate_irf(counts)[0]
        assert _peak_offset(true, hard) >= 1
        assert abs(_peak_offset(true, soft)) <= 0.5


def test_estimate_irf_soft_alignment_subsamples_large_scenes(monkeypatch):
    # the EM's cost bound: with a budget of a few thousand photon-shift pairs it uses
    # every k-th bright pixel, and the shape stays a unit-sum pulse on the true peak
    import splidar._irf_estimate as ie

    true = exp_tail_irf(3.0, 6.0)
    true = true / true.sum()
    counts = _cube(true, seed=2).counts
    full = estimate_irf(counts)
    monkeypatch.setattr(ie, "_EM_PAIRS", 100_000)
    sub = estimate_irf(counts)
    assert np.isclose(sub.sum(), 1.0) and not np.allclose(sub, full)
    assert abs(_peak_offset(true, sub[0])) <= 1


def test_estimate_irf_does_not_take_a_second_surface_for_tail():
    true = exp_tail_irf(2.0, 4.0)
    cube = _cube(true, second=40.0, T=240)
    est = estimate_irf(cube.counts)[0]
    p = int(np.argmax(est))
    # the exp tail has < 0.3 % of its mass beyond 25 bins; the second surface (as bright
    # as the first) at +40 bins would put about half of the photons there
    assert est.size - p < 40
    assert est[p + 25 :].sum() < 0.02


def test_estimate_irf_per_wavelength_rows():
    true = exp_tail_irf(2.0, 5.0)
    cube = _cube(true)
    two = np.concatenate([cube.counts, cube.counts], axis=2)
    est = estimate_irf(two)
    assert est.shape[0] == 2
    np.testing.assert_allclose(est[0], est[1])


def test_load_estimate_shape_records_irf_source(tmp_path):
    cube = _cube(exp_tail_irf(2.0, 6.0))
    f = tmp_path / "c.npz"
    np.savez(f, counts=cube.counts)
    c = splidar.load(f, irf="estimate-shape")
    assert "estimated shape" in c.metadata["irf_source"]
    np.testing.assert_allclose(c.irf, estimate_irf(cube.counts))


def test_load_defaults_to_the_shape_estimate_without_an_irf(tmp_path, caplog):
    # a file without an IRF: load estimates the shape (as irf="estimate-shape" does);
    # irf="estimate" keeps the Gaussian of the pair-lag width (the opt-out)
    cube = _cube(exp_tail_irf(2.0, 6.0))
    f = tmp_path / "c.npz"
    np.savez(f, counts=cube.counts)
    with caplog.at_level("WARNING", logger="splidar.io"):
        c = splidar.load(f)
    assert c.metadata["irf_source"].startswith("estimated shape")
    assert "estimated shape" in caplog.text and "irf='estimate'" in caplog.text
    np.testing.assert_allclose(c.irf, splidar.load(f, irf="estimate-shape").irf)
    g = splidar.load(f, irf="estimate")
    assert g.metadata["irf_source"].startswith("estimated gaussian fwhm=")
    assert g.irf.shape != c.irf.shape or not np.allclose(g.irf, c.irf)


def test_load_default_falls_back_to_gaussian_when_shape_cannot_be_estimated(tmp_path):
    # 4 x 4 pixels: fewer than min_pixels = 20 bright pixels, the shape estimate raises;
    # load keeps the Gaussian of the pair-lag width
    cube = _cube(gaussian_irf(4.0), n=4, ppp=40.0)
    f = tmp_path / "c.npz"
    np.savez(f, counts=cube.counts)
    c = splidar.load(f)
    assert c.metadata["irf_source"].startswith("estimated gaussian fwhm=")


def test_estimate_irf_falls_back_to_gaussian_on_few_photons(tmp_path, caplog):
    # 16 x 16 pixels at PPP 3: about 50 bright pixels, whose pooled curve does not
    # reject a Gaussian (measured: chi2 7.0 on 14 dof, p 0.93 against the 3-sigma
    # p-value 0.0013), so the Gaussian of the pair-lag FWHM is returned
    cube = _cube(exp_tail_irf(2.0, 6.0), n=16, ppp=3.0, sbr=2.0)
    with caplog.at_level("WARNING", logger="splidar.io"):
        est = estimate_irf(cube.counts, fwhm=5.0)
    np.testing.assert_allclose(est[0], gaussian_irf(5.0))
    assert "does not reject a Gaussian" in caplog.text
    shape = estimate_irf(cube.counts, fwhm=5.0, fallback=False)[0]
    assert shape.size != est.shape[1] or not np.allclose(shape, est[0])
    f = tmp_path / "c.npz"
    np.savez(f, counts=cube.counts)
    c = splidar.load(f, irf="estimate-shape")
    assert c.metadata["irf_source"].startswith("estimated gaussian fwhm=")
    assert "shape not supported" in c.metadata["irf_source"]


def test_estimate_irf_keeps_shape_when_gaussian_rejected():
    # 32 x 32 at PPP 20: the exp tail is rejected as a Gaussian (p < 1e-100), the shape kept
    cube = _cube(exp_tail_irf(2.0, 6.0))
    est = estimate_irf(cube.counts)
    np.testing.assert_allclose(est, estimate_irf(cube.counts, fallback=False))
    assert irf_fwhm(est[0]) > 0 and est[0].argmax() < est.shape[1] // 2


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(counts=np.ones((4, 50))), "counts"),
        (dict(counts=-np.ones((4, 4, 50))), "counts"),
        (dict(counts=np.full((4, 4, 50), np.nan)), "counts"),
        (dict(counts=np.ones((4, 4, 50)), significance=0.0), "significance"),
        (dict(counts=np.ones((4, 4, 50)), fwhm=-1.0), "fwhm"),
        (dict(counts=np.ones((4, 4, 50)), fwhm=3.0, min_pixels=0), "min_pixels"),
        (dict(counts=np.ones((4, 4, 50)), fwhm=3.0, max_length=60), "max_length"),
        (dict(counts=np.ones((4, 4, 50), np.uint8), fwhm=3.0), "min_pixels"),
    ],
)
def test_estimate_irf_bad_input_names_parameter(kwargs, name):
    counts = kwargs.pop("counts")
    with pytest.raises(SplidarError, match=name):
        estimate_irf(counts, **kwargs)


def test_estimate_irf_keeps_hard_shape_when_soft_peak_jumps(monkeypatch):
    # a flat-topped pulse whose plateau is within a few % of its peak: the soft peak may
    # land on the plateau's other end (measured pulse, PPP 4, seed 0: 10 bins, F_true
    # 0.98 -> 0.28). A soft peak more than half the FWHM from the hard one is not taken:
    # the soft result is given such a jump (a spike at the front of its support) and the
    # estimate must be the hard-aligned shape
    import splidar._irf_estimate as ie

    real = ie.soft_align

    def jumped(a, kept, h0, support, k_left, reach):
        h, it = real(a, kept, h0, support, k_left, reach)
        first = np.argmax(support, axis=1)
        h[np.arange(h.shape[0]), first] = 2.0 * h.max()
        return h, it

    true = exp_tail_irf(3.0, 6.0)
    counts = _cube(true / true.sum(), seed=2).counts
    monkeypatch.setattr(ie, "soft_align", jumped)
    np.testing.assert_allclose(estimate_irf(counts), estimate_irf(counts, refine=False))


def test_pooled_shape_from_photon_list_voxels_equals_dense():
    # load hands the photon lists' sparse voxels to the estimate (no scan of the dense
    # cube): the same photons in the same order, so the same IRF exactly
    from splidar._irf_estimate import pooled_shape

    cube = _cube(exp_tail_irf(2.0, 6.0), ppp=8.0)
    a = cube.counts.reshape(-1, 1, cube.n_bins)
    flat = a.ravel()
    uniq = np.flatnonzero(flat)
    args = (a, 6.0, 10, 40, 3.0, 20)
    dense = pooled_shape(*args)
    sparse = pooled_shape(*args, voxels=(uniq, flat[uniq]))
    np.testing.assert_array_equal(dense[0], sparse[0])
    assert dense[1:] == sparse[1:]


def test_peaks_break_ties_on_both_sides():
    # two photons 3 bins apart under a symmetric template: the two middle bins tie
    # exactly; even pixels take the first, odd ones the last (no side favoured)
    from splidar._irf_estimate import _centred, _peaks

    kp, _, _ = _centred(gaussian_irf(4.0))
    t = np.array([10, 13, 10, 13])
    p, loo = _peaks(np.array([0, 2, 4]), t, np.ones(4), kp, 30, 5)
    assert list(p) == [11, 12]
    assert list(loo) == [13, 10, 13, 10]  # each photon aligned by the other one


def test_load_irf_weak_signal_shape_from_pixel_blocks():
    # at PPP 2 single pixels' pooled photons do not reject a Gaussian (the fall-back
    # fired and load took the Gaussian of the pair-lag width, L1 0.50-0.70 to the true
    # exp tail 3/6 on seeds 0-3 at SBR 1 and 0.2); on 2 x 2 / 4 x 4 pixel blocks they do,
    # and that shape is used: L1 0.17-0.39 on the same seeds (this one: 0.23 against 0.56)
    from splidar.io import _pooled_fwhm, _resolve_irf

    true = exp_tail_irf(3.0, 6.0)
    true = true / true.sum()
    y = _cube(true, T=200, ppp=2.0, sbr=1.0, seed=0).counts
    irf, src = _resolve_irf(None, None, None, None, y, 200)
    assert src.startswith("estimated shape") and "2 x 2 pixel blocks" in src
    fw, k = _pooled_fwhm(y, 200, None)
    x, e, _ = _on_common_grid(true, irf[0])
    xg, g, _ = _on_common_grid(true, gaussian_irf(fw) / gaussian_irf(fw).sum())
    assert k == 1 and np.abs(x - e).sum() < 0.6 * np.abs(xg - g).sum()


def _single_and_load(true, T, ppp, sbr, seed):
    from splidar.io import _estimate_irf, _pooled_fwhm, _pooled_shape

    y = _cube(true, T=T, ppp=ppp, sbr=sbr, seed=seed).counts
    fw, k = _pooled_fwhm(y, T, None)
    stats: dict = {}
    single, _ = _estimate_irf(
        y, fwhm=fw, max_length=None, significance=3.0, min_pixels=20, fallback=True, stats=stats
    )
    irf, src = _pooled_shape(y, fw, k)
    return y, fw, single, stats["n_used"] / single.shape[1], irf, src


def test_load_irf_level_follows_split_half_spread():
    # irf23: the first level with a shape is compared with 2 x 2 blocks by the split-half
    # spread of each (the estimate's own noise), the steadier kept. Exp tail 2/25, PPP 4,
    # seed 7: 1.6 bright pixels per sample, spreads 0.41 (pixels) / 0.20 (blocks): the
    # blocks, L1 0.21 to the truth against the pixels' 0.76. Exp tail 3/6, PPP 4, seed 0:
    # 5.8 per sample, spreads 0.112 / 0.125: the single pixels' shape, unchanged.
    from splidar.io import _block_sum, _split_spread

    t25 = exp_tail_irf(2.0, 25.0)
    t36 = exp_tail_irf(3.0, 6.0)
    for true, T, seed, blocks in ((t25, 400, 7, True), (t36, 200, 0, False)):
        true = true / true.sum()
        y, fw, single, _, irf, src = _single_and_load(true, T, 4.0, 1.0, seed)
        s1, s2 = _split_spread(y, fw), _split_spread(_block_sum(y, 2), fw)
        assert (s2 < s1) == blocks
        assert ("2 x 2 pixel blocks" in src) == blocks
        if blocks:
            x, e, _ = _on_common_grid(true, irf[0])
            xs, s, _ = _on_common_grid(true, single[0])
            assert np.abs(x - e).sum() < 0.5 * np.abs(xs - s).sum()
        else:
            np.testing.assert_array_equal(irf, single)


def test_load_irf_many_bright_pixels_per_sample_keeps_single_pixels():
    # the cost bound: from _SPLIT_ABOVE (16) bright pixels per sample on (every real
    # file: 31-750) the single pixels' shape is taken without the spread (exp tail 3/6,
    # PPP 8, seed 0: 16.1 per sample; its 2 x 2 blocks' spread would be the lower)
    from splidar.io import _SPLIT_ABOVE

    true = exp_tail_irf(3.0, 6.0)
    true = true / true.sum()
    _, _, single, per, irf, src = _single_and_load(true, 200, 8.0, 1.0, 0)
    assert per >= _SPLIT_ABOVE
    assert "pixel blocks" not in src
    np.testing.assert_array_equal(irf, single)


def test_shape_distance_and_split_halves():
    from splidar._irf_estimate import shape_distance, split_halves

    a = np.array([0.0, 1.0, 3.0, 1.0, 0.0])
    assert shape_distance(a, np.array([2.0, 6.0, 2.0])) == pytest.approx(0.0)
    assert shape_distance(a, np.array([3.0, 1.0, 1.0])) == pytest.approx(0.4)
    assert shape_distance(np.array([1.0]), np.array([0.0, 1.0])) == pytest.approx(0.0)
    for r, c in ((4, 5), (1, 6), (3, 3)):
        for m in split_halves(r, c):
            assert m.shape == (r * c,)
            assert abs(int(m.sum()) - (r * c - int(m.sum()))) <= max(c, 1)
            assert 0 < m.sum() < r * c


def test_half_max_bounds_bracket_the_crossing():
    # irf24: the 3-sigma bracket of the pair-lag half-maximum crossing. A smooth
    # autocorrelation of many pairs: a one-lag bracket around the crossing; the same
    # curve of few pairs with lag 0 lifted by its noise (the measured pulse at PPP 1,
    # SBR 0.2, seed 0: lag 0 85 pairs over the floor, lags 1-12 about 30): the crossing
    # reads < 1 lag and the bracket reaches far beyond it (the width is not determined)
    from splidar._irf_width import _half_max_bounds, _half_max_lag

    k = np.arange(33.0)
    for scale in (1e4, 1e6):
        h = scale * (0.2 + np.exp(-0.5 * (k / 5.0) ** 2))
        var = h.copy()
        var[0] *= 2
        kh = _half_max_lag(h)
        lo, hi = _half_max_bounds(h, var, kh)
        assert lo < kh < hi and hi - lo <= (3 if scale == 1e4 else 1)
    h = 134.0 + 30.0 * np.exp(-0.5 * (k / 8.0) ** 2)
    h[0] = 134.0 + 85.0
    var = h.copy()
    var[0] *= 2
    kh = _half_max_lag(h)
    lo, hi = _half_max_bounds(h, var, kh)
    assert kh < 1 and lo == 0 and (hi - lo) / 2 > kh


@pytest.mark.parametrize("seed", [1, 7])
def test_load_irf_width_needs_a_determined_half_maximum(seed, caplog):
    # irf24: exp tail 2/25 (FWHM 19.6) at PPP 4, SBR 0.2 on the tests' plane: the single
    # pixels' pair-lag width read 2.4 / 3.9 bins (seeds 1 / 7), its half-maximum crossing
    # one noisy lag; its 3-sigma bracket is wider than the width, so 2 x 2 / 4 x 4 pixel
    # blocks are measured instead: 16.9 / 14.5 bins
    from splidar.io import _pooled_fwhm

    true = exp_tail_irf(2.0, 25.0)
    y = _cube(true / true.sum(), T=400, ppp=4.0, sbr=0.2, seed=seed).counts
    with caplog.at_level("INFO", logger="splidar.io"):
        fw, k = _pooled_fwhm(y, 400, None)
    assert k > 1 and "width is not determined" in caplog.text
    assert 0.5 * 19.64 < fw < 2.5 * 19.64


def test_max_probability_follows_the_noise():
    from splidar._irf_estimate import max_probability

    sharp = np.array([0.1, 0.3, 1.0, 0.4, 0.1])
    p = max_probability(sharp, np.full(5, 0.02))
    assert p.sum() == pytest.approx(1.0) and p[2] > 0.999
    horns = np.array([0.2, 1.0, 0.8, 1.0, 0.2])  # two equal peaks: each half the chance
    p = max_probability(horns, np.full(5, 0.05))
    assert p[1] == pytest.approx(p[3], abs=1e-3) and p[1] == pytest.approx(0.5, abs=0.01)


def test_reference_moves_only_an_undetermined_peak():
    from splidar._irf_estimate import _reference

    sharp = np.array([0.1, 0.3, 1.0, 0.4, 0.1])
    assert _reference(sharp, np.full(5, 0.01)) is sharp  # determined: unchanged
    top = np.array([0.1, 0.9, 1.0, 0.95, 0.9, 0.92, 0.9, 0.1])  # flat within the noise
    out = _reference(top, np.full(8, 0.1) / top.sum())  # errors relative to the sum
    # P(max) 0.09 / 0.40 / 0.20 / 0.09 | 0.13 / 0.09 on samples 1-4 (peak 2) | 5-6 (peak
    # 5): 0.78 x 2 + 0.22 x 5 = 2.66
    assert int(np.argmax(out)) == 3 and out.sum() == pytest.approx(1.0)
    assert np.abs(out - top / top.sum()).sum() < 0.05  # one sample raised to the top
    # one peak and a slow tail within the noise: every sample climbs to the peak
    tail = np.r_[0.2, 1.0, np.linspace(0.98, 0.8, 10)]
    assert _reference(tail, np.full(tail.size, 0.1) / tail.sum()) is tail


def test_hill_tops_climb_to_the_nearest_peak():
    from splidar._irf_estimate import _hill_tops

    u = np.array([0.1, 0.5, 0.4, 0.6, 0.9, 0.7, 0.7, 0.8, 0.2])
    assert _hill_tops(u).tolist() == [1, 1, 4, 4, 4, 4, 7, 7, 7]


@pytest.mark.parametrize(("ppp", "seed"), [(4.0, 3), (10.0, 3), (10.0, 5), (10.0, 7)])
def test_estimate_irf_reference_of_a_flat_top_is_not_at_an_end(ppp, seed):
    # a pulse flat over 14 bins (samples 2-15): the estimate's argmax landed on the
    # plateau's ends on these seeds (4 / 14 / 4 / 4 for a centre of 8.5); now 9 / 12 / 7 / 6
    true = np.r_[0.3, 0.7, np.ones(14), 0.7, 0.3]
    true = true / true.sum()
    est = estimate_irf(_cube(true, ppp=ppp, sbr=1.0, seed=seed).counts)[0]
    at = _best_offset(true, est) + int(np.argmax(est))
    assert abs(at - 8.5) <= 3.5
