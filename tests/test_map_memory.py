"""Peak memory of ``detect`` on long-IRF cubes (issue #15 point 6): the map pass's work
buffers bounded by a fraction of the cube, the candidates' histograms released block by
block as stage 6 gathers them, the isolated test's own windows not copied whole to
float64; every result the same bit for bit."""

import tracemalloc
import weakref

import numpy as np
import pytest

from splidar.detection import _4_map, _6_select, _detect, detect
from splidar.detection._quality import reject_isolated
from splidar.detection._windows import SupportWindows
from splidar.scenes import single_surface_scene


@pytest.fixture(scope="module")
def long_irf_cube():
    """A single surface seen through a wide exponential-tail IRF (W of about 140 bins)."""
    scene = single_surface_scene((16, 16), n_bins=500, irf=("exp_tail", 5.0, 10.0))
    return scene.simulate(ppp=8.0, sbr=1.0, rng=0).cube


def _f32(shape) -> int:
    return int(np.prod(shape)) * 4


def test_capped_rows_keeps_the_map_buffers_within_a_quarter_cube():
    """The face file at its native bin (340 x 340 x 1 x 7,001, scales up to 11, 3 box
    scales kept, 2 threads): the former floor of 20 rows per block held 0.79 cubes of
    buffers; the cap keeps them within WORK_FRACTION."""
    face = (340, 340, 1, 7001)
    assert 2 * _4_map._run_bytes(20, face, 5, 3) > 0.75 * _f32(face)
    rows = _4_map._capped_rows(20, face, 5, 3, 2)
    assert 1 <= rows < 20
    assert 2 * _4_map._run_bytes(rows, face, 5, 3) <= _4_map.WORK_FRACTION * _f32(face)
    # the largest such number of rows
    assert 2 * _4_map._run_bytes(rows + 1, face, 5, 3) > _4_map.WORK_FRACTION * _f32(face)
    # small cubes keep the default rule's rows (64 MB of buffers per thread at least)
    assert _4_map._capped_rows(20, (64, 64, 1, 200), 5, 0, 2) == 20
    # a row too wide for the budget: one row per block
    assert _4_map._capped_rows(20, (40, 4000, 1, 9000), 5, 3, 2) == 1


def test_map_candidates_caps_block_rows_with_the_same_detection(long_irf_cube, monkeypatch):
    """Fewer rows per block when the buffers would exceed the fraction (patched small
    here): the same Detection bit for bit, the rows recorded."""
    a = detect(long_irf_cube, rng=0, n_jobs=2)
    monkeypatch.setattr(_4_map, "WORK_FRACTION", 0.01)
    monkeypatch.setattr(_4_map, "WORK_FLOOR", 0.0)
    b = detect(long_irf_cube, rng=0, n_jobs=2)
    assert b.options["block_rows"] < a.options["block_rows"]
    assert len(a.surfaces) > 100
    for name, x in vars(a.surfaces).items():
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(getattr(b.surfaces, name), x, err_msg=name)
    np.testing.assert_array_equal(b.saliency, a.saliency)
    np.testing.assert_array_equal(b.mask, a.mask)
    np.testing.assert_array_equal(b.background.spatial, a.background.spatial)


def test_select_surfaces_releases_each_block_once_gathered(long_irf_cube, monkeypatch):
    """``detect``'s selection drops a block's histograms once its rows are gathered: while
    the last block is read the first ones are gone; the surfaces are the same."""
    a = detect(long_irf_cube, rng=0, n_jobs=1, block_rows=4)
    refs, alive = [], []
    select, rows = _detect.select_surfaces, SupportWindows.rows

    def spy_select(table, histograms, **kw):
        refs.extend(weakref.ref(h) for h in histograms)
        return select(table, histograms, **kw)

    def spy_rows(self, idx, out=None):
        alive.append([r() is not None for r in refs])
        return rows(self, idx, out)

    monkeypatch.setattr(_detect, "select_surfaces", spy_select)
    monkeypatch.setattr(_6_select, "GATHER_BYTES", 20000)
    monkeypatch.setattr(SupportWindows, "rows", spy_rows)
    b = detect(long_irf_cube, rng=0, n_jobs=1, block_rows=4)
    assert len(refs) == 4 and alive
    assert alive[-1] == [False, False, False, True]
    for name, x in vars(a.surfaces).items():
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(getattr(b.surfaces, name), x, err_msg=name)


def _windows_table(S=4000, W=300, seed=0):
    """A candidate table of one candidate per pixel of a 40 x 100 image on a plane (depth
    about 100), 5 % of them at other depths (isolated), own windows of ``W`` bins with a
    support each (zero outside it)."""
    rng = np.random.default_rng(seed)
    R, C = 40, 100
    pix = np.arange(S) % (R * C)
    first = rng.integers(0, W // 2, S)
    length = rng.integers(1, W // 2, S)
    inside = (np.arange(W) >= first[:, None]) & (np.arange(W) < (first + length)[:, None])
    cnt = (rng.poisson(0.3, (S, 1, W)) * inside[:, None]).astype(np.int16)
    bkg = (rng.random((S, 1, W), np.float32) * 0.2 * inside[:, None]).astype(np.float32)
    depth = np.full(S, 100.0)
    odd = rng.random(S) < 0.05
    depth[odd] = rng.uniform(150.0, 290.0, int(odd.sum()))
    return dict(
        row=pix // C, col=pix % C, depth_bin=depth, offset=np.zeros(S, np.int64),
        own_counts=cnt, own_background=bkg, image_shape=(R, C),
    )  # fmt: skip


def test_reject_isolated_converts_only_the_tested_rows():
    """No float64 copy of every candidate's window (the face: 0.7 GB at once): the same
    rejections as with a float64 table, a fraction of that copy's bytes traced."""
    surf = _windows_table()
    keep = np.ones(surf["row"].size, bool)
    ref = reject_isolated(
        dict(surf, own_background=surf["own_background"].astype(np.float64)), keep,
        fwhm=3.0, pfa=1e-3, n_bins=2000,
    )  # fmt: skip
    copy = surf["own_background"].size * 8
    tracemalloc.start()
    got = reject_isolated(surf, keep, fwhm=3.0, pfa=1e-3, n_bins=2000)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(got, ref)
    assert 0 < ref.sum() < ref.size
    assert peak < 0.6 * copy


def test_follow_supports_reads_the_moved_pixels_in_parts(long_irf_cube, monkeypatch):
    """Stage 7's moved surfaces follow their depth from their pixels' counts read a part
    at a time (all of them at once were 0.3 float32 cubes on the face): the same
    supports, counts and background as in one part, a fraction of its bytes traced."""
    from splidar.detection import _depth_fields

    det = detect(long_irf_cube, rng=0)
    s = det.surfaces
    idx = np.arange(len(s))
    old = np.asarray(s.depth_bin) - 3.0
    counts = long_irf_cube.counts
    a = _depth_fields.follow_supports(s, idx, old, counts, det.background)
    monkeypatch.setattr(_depth_fields, "FOLLOW_BYTES", 20000)
    whole = len(s) * int(np.prod(counts.shape[2:])) * 16
    tracemalloc.start()
    b = _depth_fields.follow_supports(s, idx, old, counts, det.background)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert len(s) > 100
    assert not np.array_equal(a.start, s.start)
    for name in ("start", "stop", "counts", "background"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    assert peak < 0.5 * whole


def test_finest_sums_equal_the_whole_arrays_sums_without_the_float32_copy():
    """Stage 7's sheared pool reads the finest scale summed over wavelengths as float64:
    built a part of the surfaces at a time, the same values as the float32 sum of every
    surface converted at once, without that float32 array beside the float64 one."""
    from splidar.detection._7a_align_depths import _finest_sums

    rng = np.random.default_rng(3)
    for L, S in ((3, 500), (1, 20000)):
        h = rng.random((S, 2, L, 300), np.float32)
        ref = np.ascontiguousarray(h[:, 0].sum(axis=1), np.float64)
        tracemalloc.start()
        got = _finest_sums(h)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        np.testing.assert_array_equal(got, ref)
        assert got.dtype == np.float64 and got.flags.c_contiguous
    assert peak < S * 300 * (8 + 0.75 * 4)


@pytest.mark.parametrize("n_rows", [6, 17])
def test_move_rows_equals_a_copy_without_a_temporary(n_rows):
    """Every shift of a halo (overlapping or not, either direction, pieces that do not
    divide it): the rows of a copy taken first; and no temporary array, where the plain
    overlapping assignment traces one of all the moved rows."""
    rng = np.random.default_rng(3)
    base = rng.random((n_rows, 4, 1, 50)).astype(np.float32)
    for src in range(n_rows):
        for dst in range(n_rows):
            for n in range(n_rows - max(src, dst) + 1):
                buf = base.copy()
                want = base.copy()
                want[dst : dst + n] = base[src : src + n]
                _4_map._move_rows(buf, dst, src, n)
                np.testing.assert_array_equal(buf, want, err_msg=f"{dst} {src} {n}")
    buf = rng.random((12, 4, 1, 500)).astype(np.float32)
    row = _f32(buf.shape[1:])
    tracemalloc.start()
    buf[0:10] = buf[2:12]  # NumPy's overlapping assignment: through a copy of 10 rows
    plain = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    _4_map._move_rows(buf, 0, 2, 10)
    moved = tracemalloc.get_traced_memory()[1] - tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    assert plain >= 10 * row
    assert moved < row


@pytest.mark.parametrize("block_rows", [1, 2, 3, 4, 7])
def test_map_candidates_same_map_when_the_halo_is_longer_than_a_block(block_rows, monkeypatch):
    """Blocks shorter than their halo of 2 h = 10 rows (the halo moved in pieces, over
    itself), downwards and, two runs' blocks on one thread, upwards: the same map and
    candidates as the whole image in one block."""
    scene = single_surface_scene((24, 10), n_bins=500, irf=("exp_tail", 5.0, 10.0))
    long_irf_cube = scene.simulate(ppp=8.0, sbr=1.0, rng=1).cube
    ref = detect(long_irf_cube, rng=0, n_jobs=1, block_rows=24)
    assert len(ref.surfaces) > 100 and ref.options["block_rows"] == 24
    for n_jobs in (1, 2):
        _same(detect(long_irf_cube, rng=0, n_jobs=n_jobs, block_rows=block_rows), ref)

    def upwards(self, k):
        yield from [b for run in self.blocks for b in run][::-1] if k == 1 else []

    monkeypatch.setattr(_4_map._Schedule, "blocks_for", upwards)
    _same(detect(long_irf_cube, rng=0, n_jobs=2, block_rows=block_rows), ref)


def _same(got, ref) -> None:
    np.testing.assert_array_equal(got.saliency, ref.saliency)
    np.testing.assert_array_equal(got.mask, ref.mask)
    for name, x in vars(ref.surfaces).items():
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(getattr(got.surfaces, name), x, err_msg=name)


def _far_plane(R=24, T=2000):
    """A flat plane at bin 1,000 (two photons per pixel there), every pixel (3 i + 1,
    3 j + 1) a surface at bin 400 holding two background photons there and one at the
    plane's bin: the far-depth rule's candidates, each to be moved to the plane."""
    from splidar import gaussian_irf
    from splidar.detection._result import Background, Surfaces

    rows, cols = np.divmod(np.arange(R * R), R)
    far = (rows % 3 == 1) & (cols % 3 == 1)
    depth = np.where(far, 400.0, 1000.0)
    n = R * R
    surf = Surfaces(
        row=rows, col=cols, slot=np.zeros(n, int), depth_bin=depth,
        start=depth.astype(int) - 2, stop=depth.astype(int) + 3, scale_index=np.zeros(n, int),
        offset=depth.astype(int) - 2, histograms=np.zeros((n, 1, 1, 5), np.float32),
        signal=np.full((n, 1, 1), 0.8), counts=np.ones((n, 1)), background=np.zeros((n, 1)),
        saliency_mass=np.ones(n), image_shape=(R, R), n_slots=2,
    )  # fmt: skip
    counts = np.zeros((R, R, 1, T), np.uint16)
    counts[:, :, 0, 1000] = 2
    counts[rows[far], cols[far], 0, 1000] = 1
    counts[rows[far], cols[far], 0, 400] = 1
    counts[rows[far], cols[far], 0, 401] = 1
    bg = Background(
        spatial=np.full((R, R, 1), 0.0016, np.float32),
        temporal=np.full((1, T), 0.0016, np.float32),
    )
    return surf, counts, bg, gaussian_irf(3.0)[None], int(far.sum())


def test_far_moves_reads_the_candidates_pixels_in_parts(monkeypatch):
    """Stage 7's far-depth rule reads its candidates' pixels (raw counts and float64
    background, (n, L, T)) a part of them at a time, in its scores and in the moves: the
    same moves, depths, supports, counts and background as in one part, a fraction of
    the whole pixels' bytes traced."""
    from splidar.detection import _7a_align_depths as stage
    from splidar.detection import _depth_fields

    surf, counts, bg, irf, n_far = _far_plane()
    a, moved_a = stage._far_moves(surf, counts, bg, fwhm=3.0, irf=irf)
    T = counts.shape[-1]
    monkeypatch.setattr(_depth_fields, "FOLLOW_BYTES", 4 * 16 * T)  # 4 pixels a part
    monkeypatch.setattr(stage, "_FAR_BLOCK", 2 * T)  # one pair a block in the scores
    tracemalloc.start()
    b, moved_b = stage._far_moves(surf, counts, bg, fwhm=3.0, irf=irf)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert moved_a.size == n_far
    np.testing.assert_array_equal(moved_b, moved_a)
    for name in ("depth_bin", "start", "stop", "counts", "background"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    whole = n_far * T * (8 + counts.itemsize)  # every candidate's pixel at once
    assert peak < 0.5 * whole


def test_assemble_map_keeps_the_own_background_as_its_factors(long_irf_cube, monkeypatch):
    """The candidate table's ``own_background`` (S, L, W) is not stored dense (about
    0.1 float32 cubes on the face at its native bin): an ``OwnBackground`` of the spatial
    level and ``dev`` holding a few numbers a candidate gives every row as the map's
    kernel wrote it, bit for bit."""
    from splidar.detection._windows import OwnBackground

    blocks, got = [], {}
    finish, assemble = _4_map._finish_block, _4_map.assemble_map

    def fb(n_vox, kept, n_ph, surf, keep, opts, n_cand):
        fields = ("row", "col", "offset", "start", "stop")
        b = {k: np.array(surf[k]) for k in fields}
        b["dense"] = surf["own_background"][surf["_slot"]].copy()
        blocks.append(b)
        return finish(n_vox, kept, n_ph, surf, keep, opts, n_cand)

    def am(outs, out, filters, *args):
        got["spatial"], got["dev"] = out["spatial"].copy(), filters.dev
        got["map"] = assemble(outs, out, filters, *args)
        return got["map"]

    monkeypatch.setattr(_4_map, "_finish_block", fb)
    monkeypatch.setattr(_4_map, "assemble_map", am)
    detect(long_irf_cube, rng=0)
    col = got["map"].candidates.columns["own_background"]
    assert isinstance(col, OwnBackground)
    assert col.row.nbytes * 6 < 0.1 * col.size * 4  # a few numbers a row, not L x W
    n = 0
    for b in blocks:
        W = b["dense"].shape[-1]
        fields = (b[k] for k in ("row", "col", "offset", "start", "stop"))
        rows = np.asarray(OwnBackground(got["spatial"], got["dev"], *fields, width=W))
        assert rows.dtype == np.float32
        np.testing.assert_array_equal(rows.view(np.uint32), b["dense"].view(np.uint32))
        n += len(rows)
    assert n > 100 and any(b["dense"].any() for b in blocks)


def test_row_sums_equal_the_whole_windows_sums():
    """The spill-line test's own background summed over the windows of the kept rows,
    a part at a time: the same float64 sums as the whole array's, taken."""
    from splidar.detection._spill_lines import _row_sums

    rng = np.random.default_rng(5)
    for S, L, W in ((3000, 1, 681), (700, 3, 97)):
        w = rng.random((S, L, W), np.float32)
        w[rng.random((S, L, W)) < 0.4] = 0.0
        idx = np.flatnonzero(rng.random(S) < 0.7)
        want = w.sum(axis=-1, dtype=np.float64)[idx]
        np.testing.assert_array_equal(_row_sums(w, idx), want)


def test_table_joins_the_columns_on_threads_with_the_same_table():
    """The blocks' candidate columns joined on 3 threads: the same table (values, types,
    order) as one thread's, every block's part released (popped) once copied."""

    class Out:
        def __init__(self, b, n, rng):
            self.kept = np.arange(n)
            self.surf = {
                "row": np.repeat(np.arange(b * 4, b * 4 + 4), n // 4).astype(np.int32),
                "col": np.tile(np.arange(n // 4), 4).astype(np.int32),
                "start": rng.integers(0, 50, n).astype(np.int32),
                "evidence": rng.random(n),
                "presence_ok": rng.random(n) > 0.2,
            }

    def outs():
        rng = np.random.default_rng(5)
        return [Out(b, 40, rng) for b in range(6)]

    one, blocks = _4_map._table(outs(), (24, 10)), outs()
    three = _4_map._table(blocks, (24, 10), threads=3)
    assert all(o.surf == {} for o in blocks)
    assert one.columns.keys() == three.columns.keys()
    for k, v in one.columns.items():
        assert three.columns[k].dtype == v.dtype
        np.testing.assert_array_equal(three.columns[k], v, err_msg=k)
    np.testing.assert_array_equal(three.keep, one.keep)
    np.testing.assert_array_equal(three.hist_row, one.hist_row)
