"""The map's candidate histograms kept over their supports only (``_windows.py``): the
same histograms as the dense windows, less memory, released before stage 7."""

import gc
import weakref

import numpy as np
import pytest

from splidar.detection import _4_map, _6_select, _detect, detect
from splidar.detection._windows import SupportWindows
from splidar.scenes import single_surface_scene, two_layer_scene


@pytest.fixture(scope="module")
def long_irf_cube():
    """A single surface seen through a wide exponential-tail IRF (W of about 140 bins)."""
    scene = single_surface_scene((16, 16), n_bins=500, irf=("exp_tail", 5.0, 10.0))
    return scene.simulate(ppp=8.0, sbr=1.0, rng=0).cube


def test_support_windows_rows_are_the_dense_rows():
    rng = np.random.default_rng(0)
    n, Q, L, W = 40, 3, 2, 17
    first = rng.integers(0, W, n)
    length = rng.integers(0, W + 1, n)
    length = np.minimum(length, W - first)
    length[:3] = 0
    dense = np.zeros((n + 5, Q, L, W), np.float32)
    rows = rng.permutation(n + 5)[:n]
    for i, r in enumerate(rows):
        dense[r, ..., first[i] : first[i] + length[i]] = rng.random((Q, L, length[i]))
    w = SupportWindows.pack(dense, rows, first=first, length=length)
    ref = dense[rows]
    assert w.shape == ref.shape and len(w) == n and w.dtype == np.float32
    assert w.data.size == Q * L * int(length.sum())
    np.testing.assert_array_equal(np.asarray(w), ref)
    idx = np.array([5, 0, 39, 5, -1])
    np.testing.assert_array_equal(w[idx], ref[idx])
    np.testing.assert_array_equal(w[7], ref[7])
    np.testing.assert_array_equal(w[3:9], ref[3:9])
    np.testing.assert_array_equal(w[idx, 1], ref[idx, 1])
    mask = np.zeros(n, bool)
    mask[::3] = True
    np.testing.assert_array_equal(w[mask], ref[mask])
    out = np.full((idx.size, Q, L, W), np.nan, np.float32)
    assert w.rows(idx, out) is out
    np.testing.assert_array_equal(out, ref[idx])
    with pytest.raises(IndexError):
        w[np.array([n])]
    with pytest.raises(ValueError):
        SupportWindows.pack(dense, rows[:1], first=[W - 1], length=[2])


def test_map_candidates_keeps_histograms_over_supports_only(long_irf_cube):
    """Each block's histograms hold the table's candidates' supports only (a long IRF's
    window is mostly outside them), zero elsewhere as the dense windows are."""
    det_opts = dict(rng=0, passes=())
    seen = {}
    real = _detect._map_pass

    def spy(*a, **k):
        mp, held, n = real(*a, **k)
        seen["mp"], seen["table"] = mp, held[0]
        return mp, held, n

    mp_pass = pytest.MonkeyPatch()
    mp_pass.setattr(_detect, "_map_pass", spy)
    try:
        detect(long_irf_cube, **det_opts)
    finally:
        mp_pass.undo()
    mp, table = seen["mp"], seen["table"]
    hists = mp.histograms
    assert all(isinstance(h, SupportWindows) for h in hists)
    Q, L, W = hists[0].shape[1:]
    assert W == mp.width and W > 100
    cols = table.columns
    n = sum(len(h) for h in hists)
    assert n == len(table)
    span = (np.asarray(cols["stop"], np.int64) - np.asarray(cols["start"], np.int64)).sum()
    assert sum(h.data.size for h in hists) == Q * L * int(span)
    dense_bytes = n * Q * L * W * 4
    assert sum(h.nbytes for h in hists) < 0.7 * dense_bytes
    idx = np.arange(n)
    h = _6_select._gather(table, idx, hists)
    off = np.asarray(cols["offset"], np.int64)[:, None] + np.arange(W)
    lo, hi = np.asarray(cols["start"])[:, None], np.asarray(cols["stop"])[:, None]
    outside = (off < lo) | (off >= hi)
    assert np.all(h.transpose(0, 3, 1, 2)[outside] == 0)
    assert np.any(h > 0)


class _Dense:
    """The dense layout of the histograms (main's until session 23), for comparison."""

    @staticmethod
    def pack(dense, rows, *, first, length):
        return np.ascontiguousarray(dense[rows])


def test_detect_with_support_windows_equals_the_dense_histograms(long_irf_cube, monkeypatch):
    """The same Detection bit for bit: surfaces, histograms, presence statistics,
    provenance (the selection's histograms gathered in many small parts)."""
    a = detect(long_irf_cube, rng=0)
    monkeypatch.setattr(_6_select, "GATHER_BYTES", 5000)
    b = detect(long_irf_cube, rng=0)
    monkeypatch.undo()
    monkeypatch.setattr(_4_map, "SupportWindows", _Dense)
    c = detect(long_irf_cube, rng=0)
    assert len(a.surfaces) > 100
    for other in (b, c):
        for name, x in vars(a.surfaces).items():
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(getattr(other.surfaces, name), x, err_msg=name)
                assert getattr(other.surfaces, name).dtype == x.dtype
        np.testing.assert_array_equal(other.saliency, a.saliency)
        np.testing.assert_array_equal(other.mask, a.mask)
        assert [(r.stage, r.added, r.removed, r.moved) for r in other.provenance] == [
            (r.stage, r.added, r.removed, r.moved) for r in a.provenance
        ]


def test_detect_releases_candidate_histograms_before_depth_alignment(long_irf_cube, monkeypatch):
    """Stage 7 runs without the candidates' histograms in memory (stage 6 read them)."""
    refs, alive = [], []
    select, align = _detect.select_surfaces, _detect.place_depths

    def spy_select(table, histograms, **kw):
        refs.extend(weakref.ref(h) for h in histograms)
        return select(table, histograms, **kw)

    def spy_align(*a, **k):
        gc.collect()
        alive.append(sum(r() is not None for r in refs))
        return align(*a, **k)

    monkeypatch.setattr(_detect, "select_surfaces", spy_select)
    monkeypatch.setattr(_detect, "place_depths", spy_align)
    detect(long_irf_cube, rng=0)
    assert refs and alive == [0]


def test_detect_stage_7_writes_moved_histograms_in_place_with_the_same_result(monkeypatch):
    """Stage 7 writes its moved surfaces' histograms into the selection's array (no copy
    of every surface's); the Detection is the one a copy gives."""
    from splidar.detection import _7_depths

    place = _detect.place_depths
    shared = []

    def spy(copy):
        def run(surfaces, **kw):
            assert kw["overwrite"] is True
            if copy:
                kw["overwrite"] = False
            before = np.array(surfaces.histograms)
            res = place(surfaces, **kw)
            changed = bool((res.surfaces.histograms != before).any())
            shared.append((np.shares_memory(surfaces.histograms, res.surfaces.histograms), changed))
            return res

        return run

    monkeypatch.setattr(_detect, "place_depths", spy(False))
    cube = (
        two_layer_scene((32, 32), n_bins=150)
        .simulate(ppp=4, sbr=0.25, background="decaying", rng=0)
        .cube
    )
    a = detect(cube, rng=0)
    assert [x[0] for x in shared] == [True]
    monkeypatch.setattr(_detect, "place_depths", spy(True))
    b = detect(cube, rng=0)
    # a copy where the stage refitted histograms (it did here)
    assert [x[0] for x in shared[1:]] == [not x[1] for x in shared[1:]]
    assert any(x[1] for x in shared[1:])
    for name, x in vars(a.surfaces).items():
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(getattr(b.surfaces, name), x, err_msg=name)
    assert _7_depths.place_depths is place


def _own_rows_numpy(ob, idx):
    """The former NumPy expression of ``OwnBackground``'s rows (own36), the reference."""
    t = ob.offset[idx, None] + np.arange(ob.width)
    sp = ob.spatial[ob.row[idx], ob.col[idx]]
    T = ob.dev.shape[1]
    b = sp[:, :, None] + ob.dev[:, np.minimum(t, T - 1)].transpose(1, 0, 2)
    b = np.where(b < 0, b.dtype.type(0), b).astype(np.float32, copy=False)
    inside = (t >= np.maximum(ob.start, ob.offset)[idx, None]) & (t < ob.stop[idx, None])
    b[~np.broadcast_to(inside[:, None, :], b.shape)] = 0.0
    return b


@pytest.mark.parametrize("dev_dtype", [np.float32, np.float64])
def test_own_rows_equal_the_former_numpy_rows_bit_for_bit(dev_dtype):
    """``_windows._own_rows`` (numba) gives ``OwnBackground``'s rows as the former NumPy
    expression did, to the bit: float32 or float64 ``dev``, sums below 0 clipped, NaN
    kept, -0.0 inside, windows past ``T`` and starting before 0, empty supports."""
    from splidar.detection._windows import OwnBackground, _own_rows

    rng = np.random.default_rng(3)
    R, C, L, T, W, n = 6, 7, 3, 50, 23, 400
    sp = rng.normal(0.3, 0.4, (R, C, L)).astype(np.float32)
    sp[0, 0, 0] = -0.0
    dev = rng.normal(0.0, 0.3, (L, T)).astype(dev_dtype)
    dev[1, 5] = np.nan
    dev[0, :3] = 0.0
    off = rng.integers(-8, T - 5, n)
    start = off + rng.integers(-3, W, n)
    stop = start + rng.integers(0, W, n)
    ob = OwnBackground(sp, dev, rng.integers(0, R, n), rng.integers(0, C, n), off,
                       np.maximum(start, 0), stop, width=W)  # fmt: skip
    idx = rng.permutation(n)[: n - 7]
    ref = _own_rows_numpy(ob, idx)
    got = np.empty_like(ref)
    _own_rows(ob.spatial, ob.dev, ob.row, ob.col, ob.offset, ob.start, ob.stop, idx, got)
    assert ref.any() and np.isnan(ref).any()
    np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32))
    np.testing.assert_array_equal(ob[idx].view(np.uint32), ref.view(np.uint32))
