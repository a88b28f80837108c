"""``detect(scales="auto")``: the boxes kept by the measured spatial coherence."""

from __future__ import annotations

import numpy as np

from splidar import Cube, gaussian_irf
from splidar.detection import detect
from splidar.detection._1_background import estimate_temporal_background
from splidar.detection._2_saliency import coherent_scales, saliency_filters
from splidar.detection._filters import Correlator
from splidar.metrics import evaluate
from splidar.points import PointSet

N, T = 32, 120


def _cube(depth, photons=20.0, background=0.1, seed=0) -> Cube:
    rng = np.random.default_rng(seed)
    g = gaussian_irf(3.0)
    h = g.size // 2
    lam = np.full((N, N, 1, T), background)
    for (i, j), d in np.ndenumerate(depth):
        lam[i, j, 0, d - h : d + h + 1] += photons * g
    return Cube(rng.poisson(lam).astype(np.uint16), irf=g)


def _coherence(cube: Cube):
    return _coherence_t(cube, T)


def _coherence_t(cube: Cube, n_bins: int):
    irf = cube.irf / cube.irf.sum(axis=1, keepdims=True)
    corr = Correlator(irf, n_bins)
    bg = estimate_temporal_background(cube.counts, corr, irf, box=11, n_jobs=1)
    scales = np.array([1, 3, 7, 11])
    return coherent_scales(cube.counts, saliency_filters(corr, scales, scales / 22, bg.dev, irf))


def _independent(patch: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.integers(15, T - 15, size=(N // patch, N // patch))
    return np.repeat(np.repeat(d, patch, axis=0), patch, axis=1)


def test_coherent_scales_keeps_every_box_on_a_tilted_plane():
    depth = 30 + np.add.outer(np.arange(N), np.arange(N)) // 2
    coh = _coherence(_cube(depth))
    assert coh.kept.all()
    # neighbours share the depth: most of the own signal is in the rings
    assert coh.rho[1] > 0.8 and coh.rho[3] > 0.5


def test_coherent_scales_drops_the_boxes_of_independent_depths():
    coh = _coherence(_cube(_independent(1)))
    assert coh.kept.tolist() == [True, False, False, False]
    # independent depths share (almost) nothing: rho about 0 (its noise ~ 0.02 here)
    assert np.all(np.abs(coh.rho[1:]) < 0.1)


def test_coherent_scales_rho_of_2x2_patches_is_the_shared_fraction():
    # a pixel of a 2 x 2 patch shares its depth with 3 of its 8 neighbours: rho_3 = 3/8,
    # above the 3 x 3 box's break-even 1/4 (kept), the 7 and 11 boxes' far below theirs
    coh = _coherence(_cube(_independent(2)))
    assert abs(coh.rho[1] - 3 / 8) < 0.05
    assert coh.kept.tolist() == [True, True, False, False]


def test_coherent_scales_drops_every_box_above_a_dropped_one():
    # 3/4 of the columns independent per pixel, 1/4 a plane: the 7 and 11 boxes pass their
    # own (lower) break-even on the average alone, but not the 3 x 3 box; a set with a gap
    # ((1, 7, 11)) lost on both parts in bench_coherence-style scenes, so all go
    from splidar.detection._2_saliency import COHERENCE_Z

    depth = 30 + np.add.outer(np.arange(N), np.arange(N)) // 2
    depth[:, : 3 * N // 4] = _independent(1)[:, : 3 * N // 4]
    coh = _coherence(_cube(depth))
    assert coh.z[1] < -COHERENCE_Z and coh.z[2] > -COHERENCE_Z and coh.z[3] > -COHERENCE_Z
    assert coh.kept.tolist() == [True, False, False, False]


def test_coherent_scales_keeps_every_box_without_signal():
    coh = _coherence(_cube(np.full((N, N), 60), photons=0.0, background=0.5))
    assert abs(coh.energy_z) < 3
    assert coh.kept.all()


def test_coherent_scales_energy_is_unbiased_on_a_decaying_background():
    # the mirrored window ends count samples twice: with sum g^2 as the Poisson variance
    # everywhere, pure backgrounds of 64 x 64 x 240 showed an energy z of 4-5 (boxes
    # dropped on noise); with the exact weights it stays within +-3
    from splidar.simulation import background_shape

    rng = np.random.default_rng(0)
    for level in (0.05, 0.2):
        lam = level * background_shape("decaying", 240)
        y = rng.poisson(np.broadcast_to(lam, (64, 64, 1, 240))).astype(np.uint16)
        cube = Cube(y, irf=gaussian_irf(3.0))
        coh = _coherence_t(cube, 240)
        assert abs(coh.energy_z) < 3, (level, coh.energy_z)
        assert coh.kept.all()


def test_detect_auto_scales_is_the_chosen_scales_result():
    cube = _cube(_independent(1))
    auto = detect(cube, rng=0)
    assert auto.scales == (1,)
    # the measured coherence is recorded: the dropped boxes' rho below 1 / (k + 1)
    rho = auto.options["scale_coherence"]
    assert auto.options["scales_auto"] and rho[0] is None and len(rho) == 4
    assert all(r < 1 / (k + 1) for r, k in zip(rho[1:], (3, 7, 11), strict=True))
    fixed = detect(cube, scales=(1,), rng=0)
    assert np.array_equal(auto.points.depth_bin, fixed.points.depth_bin)
    rr, cc = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    truth = PointSet(
        row=rr.ravel(), col=cc.ravel(), depth_bin=_independent(1).ravel().astype(float),
        image_shape=(N, N),
    )  # fmt: skip
    pooled = detect(cube, scales=(1, 3, 7, 11), rng=0)
    assert evaluate(auto.points, truth, tau=2).f_true > evaluate(pooled.points, truth, tau=2).f_true


def test_detect_auto_scales_with_weights_keeps_the_four_scales():
    cube = _cube(_independent(1))
    det = detect(cube, weights=(0.25, 0.25, 0.25, 0.25), rng=0)
    assert det.scales == (1, 3, 7, 11)
    assert not det.options["scales_auto"] and det.options["scale_coherence"] is None


def test_variance_weights_are_the_filters_squared_sensitivities():
    from splidar.detection._2_saliency import _variance_weights

    irf = np.stack([gaussian_irf(3.0), np.roll(gaussian_irf(3.0), 2)])
    irf /= irf.sum(axis=1, keepdims=True)
    for n_bins in (40, 200):
        corr = Correlator(irf, n_bins)
        eye = np.eye(n_bins, dtype=np.float32)[:, None, None, :].repeat(2, axis=2)
        full = (corr(eye).astype(np.float64) ** 2).sum(axis=3)[:, 0].T  # (L, T)
        np.testing.assert_allclose(_variance_weights(corr, 2, n_bins), full, rtol=1e-5)


def test_detect_auto_scales_dask_cube_gives_the_in_memory_result():
    da = __import__("pytest").importorskip("dask.array")
    cube = _cube(_independent(1))
    mem = detect(cube, rng=0, n_jobs=1)
    lazy = detect(
        Cube(da.from_array(np.asarray(cube.counts), chunks=(16, 16, 1, T)), irf=cube.irf),
        rng=0, n_jobs=1,
    )  # fmt: skip
    assert lazy.scales == mem.scales == (1,)
    assert np.array_equal(lazy.points.depth_bin, mem.points.depth_bin)


M = 48  # the mixed scene: the left half independent per pixel, the right half a plane


def _half_cube(seed=0):
    rng = np.random.default_rng(seed)
    depth = 30 + np.add.outer(np.arange(M), np.arange(M)) // 4
    depth[:, : M // 2] = rng.integers(15, T - 15, size=(M, M // 2))
    g = gaussian_irf(3.0)
    h = g.size // 2
    lam = np.full((M, M, 1, T), 0.1)
    for (i, j), d in np.ndenumerate(depth):
        lam[i, j, 0, d - h : d + h + 1] += 8.0 * g
    return Cube(rng.poisson(lam).astype(np.uint16), irf=g), depth


def _found(det, depth) -> np.ndarray:
    """(M, M) bool: the pixel's true depth found (within 2 bins)."""
    from splidar.metrics import match_points

    rr, cc = np.meshgrid(np.arange(M), np.arange(M), indexing="ij")
    truth = PointSet(
        row=rr.ravel(), col=cc.ravel(), depth_bin=depth.ravel().astype(float), image_shape=(M, M)
    )
    hit = np.zeros(M * M, bool)
    hit[match_points(det.points, truth, tau=2).true_index] = True
    return hit.reshape(M, M)


def test_region_scales_drops_the_boxes_of_the_incoherent_regions_only():
    from splidar.detection._2_saliency import region_scales

    cube, _ = _half_cube()
    irf = cube.irf / cube.irf.sum(axis=1, keepdims=True)
    corr = Correlator(irf, T)
    bg = estimate_temporal_background(cube.counts, corr, irf, box=11, n_jobs=1)
    scales = np.array([1, 3, 7, 11])
    coh = coherent_scales(cube.counts, saliency_filters(corr, scales, scales / 22, bg.dev, irf))
    assert coh.kept.all()  # the image as a whole keeps every box (rho_3 about 1/2)
    reg = region_scales(coh, (M, M))
    # z against the largest of the 28 x 28 windows' noise: sqrt(9 + 2 ln 784) = 4.7
    assert reg.sets == (4, 1) and abs(reg.z - np.sqrt(9 + 2 * np.log(28 * 28))) < 1e-9
    # the windows (11 x 11) straddling the border measure the mixture: the border of
    # the choice lies within half a window of the scene's
    np.testing.assert_array_equal(reg.n_kept[:, : M // 2 - 5], 1)
    np.testing.assert_array_equal(reg.n_kept[:, M // 2 :], 4)


def test_detect_auto_scales_by_region_takes_each_regions_boxes():
    cube, depth = _half_cube()
    auto = detect(cube, rng=0, n_jobs=1)
    full = detect(cube, scales=(1, 3, 7, 11), rng=0, n_jobs=1)
    one = detect(cube, scales=(1,), rng=0, n_jobs=1)
    rec = auto.options["scale_regions"]
    n_kept = rec["n_kept"]
    assert rec["scales"] == ((1, 3, 7, 11), (1,)) and auto.scales == (1, 3, 7, 11)
    assert rec["pixels"] == (int((n_kept == 4).sum()), int((n_kept == 1).sum()))
    # the incoherent half gains what the 1 x 1 box gives it (0.58 -> 0.84), the plane
    # keeps the pooled result
    a, f, o = _found(auto, depth), _found(full, depth), _found(one, depth)
    assert a[:, : M // 2].mean() > f[:, : M // 2].mean() + 0.2
    np.testing.assert_array_equal(a[:, M // 2 :], f[:, M // 2 :])
    # each pixel holds its run's surfaces, maps and threshold
    for det, n in ((one, 1), (full, 4)):
        mine = n_kept == n
        np.testing.assert_array_equal(a[mine], (o if n == 1 else f)[mine])
        s, t = auto.surfaces, det.surfaces
        i, j = mine[s.row, s.col], mine[t.row, t.col]
        np.testing.assert_array_equal(s.depth_bin[i], t.depth_bin[j])
        np.testing.assert_array_equal(s.histograms[i][:, :n], t.histograms[j])
        assert not s.histograms[i][:, n:].any()
        np.testing.assert_array_equal(auto.saliency[mine], det.saliency[mine])
        np.testing.assert_array_equal(auto.mask[mine], det.mask[mine])
        np.testing.assert_array_equal(
            np.asarray(auto.threshold)[mine], np.asarray(det.threshold)[mine]
        )
    assert auto.reduction.n_voxels == int(auto.mask.sum())
    rows, cols = np.array([0, 47, 20, 30]), np.array([0, 47, 30, 20])
    np.testing.assert_array_equal(
        auto.threshold.pixels(rows, cols), np.asarray(auto.threshold)[rows, cols]
    )


def test_detect_auto_scales_by_region_same_on_every_path(tmp_path):
    import dataclasses

    import splidar

    cube, _ = _half_cube()
    mem = detect(cube, rng=0, n_jobs=1)
    runs = [detect(cube, rng=0, n_jobs=2), detect(cube, rng=0, n_jobs=1, store=tmp_path / "s")]
    da = __import__("pytest").importorskip("dask.array")
    lazy = Cube(da.from_array(np.asarray(cube.counts), chunks=(16, 16, 1, T)), irf=cube.irf)
    runs.append(detect(lazy, rng=0, n_jobs=1))
    for other in runs:
        for f in dataclasses.fields(mem.surfaces):
            x, y = getattr(mem.surfaces, f.name), getattr(other.surfaces, f.name)
            assert np.array_equal(np.asarray(x), np.asarray(y)), f.name
        for name in ("saliency", "mask", "threshold"):
            x, y = np.asarray(getattr(mem, name)), np.asarray(getattr(other, name)[:])
            np.testing.assert_array_equal(x, y, err_msg=name)
        np.testing.assert_array_equal(mem.background.spatial, other.background.spatial)
        assert other.reduction == mem.reduction
        assert other.options["scale_regions"]["pixels"] == mem.options["scale_regions"]["pixels"]
    # the smaller set's run used a subdirectory of the store, removed once merged
    assert sorted(p.name for p in (tmp_path / "s").iterdir() if p.is_dir()) == [
        "mask", "saliency", "surface_histograms",
    ]  # fmt: skip
    assert len(splidar.reconstruct(runs[1]).points) > 0


def _window_sums_numpy(m, r):
    """The former NumPy summed-area table of ``_window_sums`` (the reference)."""
    R, C = m.shape
    t = np.zeros((R + 1, C + 1))
    t[1:, 1:] = m.cumsum(axis=0).cumsum(axis=1)
    i0, i1 = np.clip(np.arange(R) - r, 0, R), np.clip(np.arange(R) + r + 1, 0, R)
    j0, j1 = np.clip(np.arange(C) - r, 0, C), np.clip(np.arange(C) + r + 1, 0, C)
    return t[i1][:, j1] - t[i0][:, j1] - t[i1][:, j0] + t[i0][:, j0]


def test_window_sums_equals_the_numpy_summed_area_table_bit_for_bit():
    from splidar.detection._2_saliency import _window_sums

    rng = np.random.default_rng(3)
    # values over 9 decades (inexact float64 sums: order matters), zeros, windows wider
    # than the image, a single pixel
    for shape, r in [((7, 5), 5), ((40, 33), 2), ((1, 1), 0), ((64, 48), 5), ((3, 90), 1)]:
        m = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 6, size=shape)
        m[rng.random(shape) < 0.3] = 0.0
        got = _window_sums(m, r)
        assert got.dtype == np.float64 and got.shape == shape
        assert np.array_equal(got, _window_sums_numpy(m, r))
    # the definition: the window's sum cut at the border (exact for small integers)
    m = rng.integers(0, 5, size=(9, 11)).astype(float)
    box = [
        [m[max(i - 2, 0) : i + 3, max(j - 2, 0) : j + 3].sum() for j in range(11)] for i in range(9)
    ]
    want = np.array(box)
    assert np.array_equal(_window_sums(m, 2), want)
