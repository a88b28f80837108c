"""Stage 7's far-depth rule (``move_far_depths``): a plane's pixel holding a far cluster."""

from dataclasses import replace

import numpy as np
import pytest

from splidar import gaussian_irf
from splidar.detection._7a_align_depths import move_far_depths
from splidar.detection._result import Background, Surfaces

T = 200
PLANE, FAR = 100.0, 40.0
SCALES = np.array([1])


def _plane(own_counts: dict) -> tuple:
    """A 5 x 5 flat plane at bin 100 (0.8 photons each), the centre's surface at bin 40;
    the centre's raw counts ``{bin: photons}``, a flat background of 0.016 per bin."""
    rows, cols = np.divmod(np.arange(25), 5)
    depth = np.full(25, PLANE)
    depth[12] = FAR
    n = 25
    surf = Surfaces(
        row=rows, col=cols, slot=np.zeros(n, int), depth_bin=depth,
        start=depth.astype(int) - 2, stop=depth.astype(int) + 3, scale_index=np.zeros(n, int),
        offset=depth.astype(int) - 2, histograms=np.zeros((n, 1, 1, 5), np.float32),
        signal=np.full((n, 1, 1), 0.8), counts=np.ones((n, 1)), background=np.zeros((n, 1)),
        saliency_mass=np.ones(n), image_shape=(5, 5), n_slots=2,
    )  # fmt: skip
    counts = np.zeros((5, 5, 1, T), np.uint16)
    for t, k in own_counts.items():
        counts[2, 2, 0, t] = k
    bg = Background(
        spatial=np.full((5, 5, 1), 0.016, np.float32), temporal=np.full((1, T), 0.016, np.float32)
    )
    irf = gaussian_irf(3.0)[None]  # (L, n)
    return surf, counts, bg, irf


def test_move_far_depths_moves_a_far_cluster_whose_own_counts_hold_the_plane():
    # two background photons at bin 40, one at the plane's bin 100: a cluster that beat
    # a missed return; the plane predicts 100 and the own counts do not reject it
    surf, counts, bg, irf = _plane({40: 1, 41: 1, 100: 1})
    out, n = move_far_depths(surf, counts, bg, fwhm=3.0, irf=irf, scales=SCALES)
    assert n == 1
    assert out.depth_bin[12] == PLANE
    # the support and its raw counts follow (reconstruct's IRF fraction is taken there)
    assert out.start[12] <= PLANE < out.stop[12]
    assert out.counts[12, 0] == counts[2, 2, 0, out.start[12] : out.stop[12]].sum() == 1
    assert np.array_equal(np.delete(out.depth_bin, 12), np.delete(surf.depth_bin, 12))


def test_move_far_depths_keeps_a_bright_off_plane_pixel():
    # eight photons at bin 40 and none on the plane: an off-plane return, kept
    surf, counts, bg, irf = _plane({39: 2, 40: 4, 41: 2})
    out, n = move_far_depths(surf, counts, bg, fwhm=3.0, irf=irf, scales=SCALES)
    assert n == 0
    assert out.depth_bin[12] == FAR


def test_move_far_depths_keeps_a_surface_a_neighbour_continues():
    # the north-west neighbour holds bin 41 (a structure, not a cluster; the opposite
    # pairs still agree on the plane): no move
    surf, counts, bg, irf = _plane({40: 1, 41: 1, 100: 1})
    d = surf.depth_bin.copy()
    d[6] = FAR + 1
    surf = replace(surf, depth_bin=d)
    out, n = move_far_depths(surf, counts, bg, fwhm=3.0, irf=irf, scales=SCALES)
    assert n == 0


def _clean_window(counts, bg, irf, scales, r, c, off, W, clip=True) -> np.ndarray:
    """``max(Box_q(Y (*) g) - bhat, 0)`` over ``[off, off + W)``, (Q, L, W), by NumPy: the
    matched filter ``sum_j g[j] Y[t - p + j]`` (reflected at the cube's edges)."""
    R, C, L, T = counts.shape
    p = int(np.argmax(irf[0]))
    y = np.pad(counts.astype(np.float64), ((2, 2), (2, 2), (0, 0), (0, 0)), mode="reflect")
    t = off + np.arange(W)[:, None] - p + np.arange(irf.shape[1])[None, :]  # (W, n)
    t = np.where(t < 0, -t, np.where(t >= T, 2 * (T - 1) - t, t))
    cf = (y[..., t] * irf[0]).sum(axis=-1)  # (R + 4, C + 4, L, W)
    bh = np.maximum(bg.at([r], [c])[0][:, off : off + W], 0)
    out = []
    for q in scales:
        h = q // 2
        box = cf[r + 2 - h : r + 3 + h, c + 2 - h : c + 3 + h].mean(axis=(0, 1))
        out.append(np.maximum(box - bh, 0) if clip else box - bh)
    return np.array(out)


def test_move_far_depths_moved_surface_fields_follow_its_depth():
    # every pixel of the plane holds photons at its depth (the centre one): the moved
    # surface's window, clean histograms (every scale, zero outside the support) and
    # signal are those of a surface extracted at the new depth, its intensity of the
    # order of its neighbours'
    surf, counts, bg, irf = _plane({40: 1, 41: 1})
    counts[:, :, 0, 100] = 2
    counts[2, 2, 0, 100] = 1
    scales = np.array([1, 3])
    W = 9
    rows, cols = np.divmod(np.arange(25), 5)
    surf = replace(
        surf,
        histograms=np.zeros((25, 2, 1, W), np.float32),
        offset=surf.depth_bin.astype(int) - W // 2,
        signal=np.full((25, 2, 1), 0.8),
        presence_llr=np.zeros(25),
        presence_z=np.zeros(25),
    )
    out, n = move_far_depths(surf, counts, bg, fwhm=3.0, irf=irf, scales=scales)
    assert n == 1 and out.depth_bin[12] == PLANE
    off = int(out.offset[12])
    assert off == int(PLANE) - W // 2 and off <= out.start[12] <= PLANE < out.stop[12] <= off + W
    want = _clean_window(counts, bg, irf, scales, 2, 2, off, W)
    inside = (off + np.arange(W) >= out.start[12]) & (off + np.arange(W) < out.stop[12])
    want[..., ~inside] = 0.0
    assert out.histograms.dtype == np.float32
    np.testing.assert_allclose(out.histograms[12], want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.signal[12], out.histograms[12].sum(axis=-1), rtol=1e-6)
    assert out.counts[12, 0] == counts[2, 2, 0, out.start[12] : out.stop[12]].sum() == 1
    assert np.isfinite(out.presence_llr[12]) and out.presence_llr[12] != 0.0
    # eq:scale_sel with two scales selects the second; the local scale's (3) z at the depth
    assert out.scale_index[12] == 1
    resp = _clean_window(counts, bg, irf, scales, 2, 2, off, W, clip=False)[1, :, W // 2]
    bh = bg.at([2], [2])[0][:, int(PLANE)]
    z = resp.sum() / np.sqrt((bh * (irf**2).sum(axis=1)).sum() / 9)
    np.testing.assert_allclose(out.presence_z[12], z, rtol=1e-5)
    assert 0.25 < out.photons[12, 0] / 0.8 < 4.0  # the neighbours' intensity
    # the other surfaces untouched
    others = np.arange(25) != 12
    assert np.array_equal(out.offset[others], surf.offset[others])
    assert not np.asarray(out.histograms)[others].any()
    assert np.array_equal(out.signal[others], surf.signal[others])
    # the same from a lazy cube (read a band of rows at a time)
    import dask.array as da

    lazy, n2 = move_far_depths(
        surf, da.from_array(counts, chunks=(2, 2, 1, T)), bg, fwhm=3.0, irf=irf, scales=scales
    )
    assert n2 == 1
    keys = ("depth_bin", "offset", "start", "stop", "histograms", "signal", "counts")
    for k in keys + ("scale_index", "presence_llr", "presence_z"):
        assert np.array_equal(getattr(lazy, k), getattr(out, k)), k


def test_window_fields_threads_give_the_same_fields():
    # 12 x 12 pixels, every one refitted at a depth off its window (144 surfaces: the
    # split over threads starts at 64): n_jobs 2 (and a lazy cube) gives n_jobs 1's
    # fields bit for bit
    from splidar.detection._depth_fields import _window_fields

    rng = np.random.default_rng(3)
    n, W, scales = 144, 9, np.array([1, 3])
    rows, cols = np.divmod(np.arange(n), 12)
    depth = rng.uniform(30, 170, n)
    counts = rng.poisson(0.3, (12, 12, 2, T)).astype(np.uint16)
    surf = Surfaces(
        row=rows, col=cols, slot=np.zeros(n, int), depth_bin=depth,
        start=depth.astype(int) - 2, stop=depth.astype(int) + 3, scale_index=np.zeros(n, int),
        offset=np.zeros(n, int), histograms=np.zeros((n, 2, 2, W), np.float32),
        signal=np.full((n, 2, 2), 0.8), counts=np.ones((n, 2)), background=np.zeros((n, 2)),
        saliency_mass=np.ones(n), image_shape=(12, 12), n_slots=1,
        presence_llr=np.zeros(n), presence_z=np.zeros(n),
    )  # fmt: skip
    bg = Background(
        spatial=np.full((12, 12, 2), 0.3, np.float32), temporal=np.full((2, T), 0.3, np.float32)
    )
    irf = np.repeat(gaussian_irf(3.0)[None], 2, axis=0)
    idx, refit = np.arange(n), np.arange(n) % 3 > 0
    one = _window_fields(surf, idx, refit, counts, bg, scales, irf, n_jobs=1)
    import dask.array as da

    for cube, nj in ((counts, 2), (da.from_array(counts, chunks=(5, 12, 2, T)), 2)):
        two = _window_fields(surf, idx, refit, cube, bg, scales, irf, n_jobs=nj)
        for k in ("offset", "histograms", "signal", "scale_index", "presence_llr", "presence_z"):
            assert np.array_equal(getattr(two, k), getattr(one, k)), k
    assert np.asarray(one.histograms).any() and not np.array_equal(one.offset, surf.offset)


def _far_scores_loop(cand, alt, src, isolated, photons, depth, irf, peak, ys, bs):
    """The far rule's scores as the former per-candidate loop of ``_far_moves`` computed
    them (session 22), the reference of ``_far_scores``."""
    from splidar.detection._quality import _shifted_irf

    T = ys.shape[-1]
    best, to = np.full(cand.size, np.inf), np.full(cand.size, np.nan)
    for m, i in enumerate(cand):
        y, b = ys[m : m + 1].astype(np.float64), bs[m : m + 1]
        for u in np.flatnonzero(~np.isnan(alt[i])):
            j = src[i, u][src[i, u] >= 0]
            sp = np.maximum(photons[j].mean(axis=0), 1e-9)[None, :, None]
            g = _shifted_irf(irf, peak, np.array([depth[i], alt[i, u]]), T)
            ll = (y * np.log1p(sp * g / b)).sum(axis=(1, 2)) - (sp * g).sum(axis=(1, 2))
            v = ll[0] - ll[1]
            if not isolated[i]:
                tb = min(max(int(np.rint(alt[i, u])), 0), T - 1)
                v += np.log1p(np.max(sp[0, :, 0] * irf.max(axis=1) / b[0, :, tb]))
            if v < best[m]:
                best[m], to[m] = v, alt[i, u]
    return best, to


def _random_far_inputs(rng, S, L, T):
    """The far rule's inputs at random: ``L`` Gaussian IRFs and their peaks, up to 4
    alternatives per surface (half missing), 4 sources per alternative (2 unless
    isolated), the candidates (some alternative), photons and depths."""
    x = np.arange(15.0)
    irf = np.stack([np.exp(-0.5 * ((x - 6 - 0.3 * l) / (1.0 + 0.4 * l)) ** 2) for l in range(L)])
    irf /= irf.sum(axis=1, keepdims=True)
    peak = np.argmax(irf, axis=1)
    alt = rng.uniform(-5, T + 5, (S, 4))
    alt[rng.random((S, 4)) < 0.5] = np.nan
    src = rng.integers(0, S, (S, 4, 4))
    isolated = rng.random(S) < 0.4
    src[~isolated, :, 2:] = -1
    cand = np.flatnonzero(~np.all(np.isnan(alt), axis=1))
    photons = rng.gamma(1.0, 3.0, (S, L))
    depth = rng.uniform(0, T - 1, S)
    return irf, peak, alt, src, isolated, cand, photons, depth


@pytest.mark.parametrize("L", [1, 3])
def test_far_scores_equal_the_former_loop_bit_for_bit(L, monkeypatch):
    # random candidates, alternatives (some missing), 2 or 4 sources, both kinds, counts
    # and backgrounds; the block split forced small so that pairs span blocks
    import splidar.detection._7a_align_depths as stage

    rng = np.random.default_rng(11)
    S, T = 300, 90
    irf, peak, alt, src, isolated, cand, photons, depth = _random_far_inputs(rng, S, L, T)
    ys = rng.poisson(0.4, (cand.size, L, T)).astype(np.uint16)
    bs = np.maximum(rng.gamma(0.5, 0.1, (cand.size, L, T)), 1e-6)
    want = _far_scores_loop(cand, alt, src, isolated, photons, depth, irf, peak, ys, bs)
    for block in (1 << 20, 7 * 2 * L * T):
        monkeypatch.setattr(stage, "_FAR_BLOCK", block)
        got = stage._far_scores(cand, alt, src, isolated, photons, depth, irf, peak, ys, bs)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert np.isfinite(want[0]).sum() > 100


def test_memo_far_scores_give_the_scores_computed_anew():
    # random candidates on a 20 x 15 image (one surface per pixel): a memo filled by one
    # call, then read by a second whose sources' photons, depths and alternatives partly
    # changed (a memo keyed by the candidate alone would return the old scores there)
    import splidar.detection._7a_align_depths as stage

    rng = np.random.default_rng(12)
    R, C, L, T = 20, 15, 2, 90
    S = R * C
    rows, cols = np.divmod(np.arange(S), C)
    irf, peak, alt, src, isolated, cand, photons, depth = _random_far_inputs(rng, S, L, T)
    counts = rng.poisson(0.4, (R, C, L, T)).astype(np.uint16)
    bg = Background(
        spatial=rng.gamma(0.5, 0.1, (R, C, L)).astype(np.float32),
        temporal=np.zeros((L, T), np.float32),
    )
    memo: dict = {}
    for step in range(2):
        if step:
            photons[rng.choice(S, 40, replace=False)] *= 1.5
            depth[rng.choice(S, 20, replace=False)] += 1.0
            alt[rng.choice(S, 20, replace=False), 0] += 2.0
        args = (alt, src, isolated, photons, depth, irf, peak)
        got = stage._memo_far_scores(cand, *args, counts, bg, rows[cand], cols[cand], memo)
        ys = counts[rows[cand], cols[cand]]
        bs = np.maximum(bg.at(rows[cand], cols[cand]).astype(np.float64), 1e-6)
        want = stage._far_scores(cand, *args, ys, bs)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert cand.size < len(memo) < 2 * cand.size


def test_far_keys_are_equal_exactly_when_the_former_tuple_keys_are():
    # the memo's keys made at once: a candidate's key in two calls is the same exactly
    # when its former per-candidate tuple key (pixel, depth, alternatives, sources, the
    # sources' photons, isolation) was; between the calls some inputs change
    import splidar.detection._7a_align_depths as stage

    def former(cand, alt, src, isolated, photons, depth, rows, cols):
        out = []
        for i, r, c in zip(cand.tolist(), rows.tolist(), cols.tolist(), strict=True):
            j = src[i][src[i] >= 0]
            out.append((r, c, depth[i], alt[i].tobytes(), src[i].tobytes(),
                        photons[j].tobytes(), isolated[i]))  # fmt: skip
        return out

    rng = np.random.default_rng(21)
    S, L, T = 300, 2, 90
    _, _, alt, src, isolated, cand, photons, depth = _random_far_inputs(rng, S, L, T)
    rows, cols = np.divmod(np.arange(S), 15)
    depth[cand[:6]] = [0.0, -0.0, 0.0, -0.0, 5.0, 5.0]
    a = (cand, alt, src, isolated, photons, depth, rows[cand], cols[cand])
    k1, f1 = stage._far_keys(*a), former(*a)
    alt, src, isolated, photons, depth = (x.copy() for x in (alt, src, isolated, photons, depth))
    photons[rng.choice(S, 30, replace=False)] *= 1.5
    depth[rng.choice(S, 20, replace=False)] += 1.0
    depth[cand[:6]] = [-0.0, 0.0, 0.0, -0.0, 5.0, 6.0]
    alt[rng.choice(S, 20, replace=False), 1] += 2.0
    isolated[rng.choice(S, 20, replace=False)] ^= True
    src[rng.choice(S, 20, replace=False), 0, 0] = -1
    a = (cand, alt, src, isolated, photons, depth, rows[cand], cols[cand])
    k2, f2 = stage._far_keys(*a), former(*a)
    same_new = [x == y for x, y in zip(k1, k2, strict=True)]
    same_old = [x == y for x, y in zip(f1, f2, strict=True)]
    assert same_new == same_old
    assert 0 < sum(same_old) < len(same_old)
    assert len(set(k1)) == len(set(f1)) and stage._far_keys(cand[:0], *a[1:]) == []


def _plane_surfaces(seed: int, R: int, C: int, K: int, p_far: float) -> tuple:
    """A random R x C image of 1-K surfaces per pixel on the first K of three planes
    (depth bins 20 + 0.5 c, 60 + 0.3 r, 110), a fraction ``p_far`` of them moved far off
    (normal, 30 bins): ``(row, col, slot, depth)``, int64 and float64."""
    rng = np.random.default_rng(seed)
    row, col, slot, depth = [], [], [], []
    for r in range(R):
        for c in range(C):
            n = rng.integers(1, K + 1)
            planes = [20.0 + 0.5 * c, 60.0 + 0.3 * r, 110.0][:K]
            d = np.sort(rng.choice(planes, n, replace=False))
            d += np.where(rng.random(n) < p_far, rng.normal(0, 30, n), 0.0)
            for k in range(n):
                row.append(r), col.append(c), slot.append(k), depth.append(d[k])
    row, col, slot = (np.array(v, np.int64) for v in (row, col, slot))
    return row, col, slot, np.array(depth)


def test_far_kernel_int32_indices_equal_int64_bit_for_bit():
    """``_far_kernel`` with the sources' and slots' indices in int32 (``_far_moves``,
    S < 2**31) gives the alternatives, sources and isolation the int64 arrays give: a
    random 40 x 30 image of 1-3 surfaces per pixel on a few planes, far-off depths
    among them (sources on planes and beside edges both found)."""
    from splidar.detection._7a_align_depths import _far_kernel

    R, C, K = 40, 30, 3
    row, col, slot, depth = _plane_surfaces(23, R, C, K, 0.1)
    S = len(row)
    got = {}
    for kind in (np.int64, np.int32):
        alt, src = np.empty((S, 4)), np.full((S, 4, 4), -1, kind)
        iso, index = np.zeros(S, np.bool_), np.full((R + 4, C + 4, K), -1, kind)
        _far_kernel(row, col, slot, depth, 3.0, alt, src, iso, index)
        got[kind] = (alt, src, iso)
    (a64, s64, i64), (a32, s32, i32) = got[np.int64], got[np.int32]
    np.testing.assert_array_equal(a32, a64)
    np.testing.assert_array_equal(s32.astype(np.int64), s64)
    np.testing.assert_array_equal(i32, i64)
    assert (~np.isnan(a64)).any() and (s64 >= 0).any() and i64.any() and (~i64).any()


def test_far_items_in_parts_on_threads_equal_the_whole_kernel():
    """``_far_moves``' split of ``_far_kernel``: the depth map once (``_far_maps``), the
    surfaces' alternatives in parts on threads (``_far_items``) give the whole kernel's
    alternatives, sources and isolation (each surface's entries its own)."""
    from splidar.detection._7a_align_depths import _far_items, _far_kernel, _far_maps
    from splidar.detection._threads import on_parts

    R, C, K = 30, 26, 2
    row, col, slot, depth = _plane_surfaces(29, R, C, K, 0.15)
    S = len(row)

    def arrays():
        return (
            np.empty((S, 4)), np.full((S, 4, 4), -1, np.int32), np.zeros(S, np.bool_),
            np.full((R + 4, C + 4, K), -1, np.int32),
        )  # fmt: skip

    alt, src, iso, index = arrays()
    _far_kernel(row, col, slot, depth, 3.0, alt, src, iso, index)
    assert np.isfinite(alt).any(axis=1).sum() > 20 and iso.sum() > 5
    for workers in (2, 3, 7):
        a2, s2, i2, x2 = arrays()
        s2[:] = 7  # not pre-filled (``_far_moves``: np.empty): the kernel writes -1
        D = _far_maps(row, col, slot, depth, x2)
        args = (row, col, depth, 3.0, a2, s2, i2, x2, D)
        on_parts(lambda i0, i1, args=args: _far_items(*args, i0, i1), S, workers)
        assert a2.tobytes() == alt.tobytes()
        np.testing.assert_array_equal(s2, src)
        np.testing.assert_array_equal(i2, iso)
        np.testing.assert_array_equal(x2, index)
