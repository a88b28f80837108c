"""Detection of a Dask-backed cube: tiles through dask.array, threads or a LocalCluster.

Every check is exact equality with the in-memory run: each tile computes its rows as a
block of the in-memory pass does (docs/distributed.md), so no tolerance is needed.
"""

import dataclasses

import numpy as np
import pytest

da = pytest.importorskip("dask.array")
import dask  # noqa: E402

import splidar  # noqa: E402
from splidar import Cube, gaussian_irf  # noqa: E402
from splidar.detection import ThresholdField  # noqa: E402
from splidar.detection._tiled import is_dask, tile_bounds, tiled_window_means  # noqa: E402
from splidar.scenes import single_surface_scene  # noqa: E402


def _varying_cube(shape=(30, 22), n_bins=120, seed=2):
    """One surface over a background that varies across the rows (a per-voxel threshold)."""
    sim = single_surface_scene(shape, n_bins=n_bins).simulate(
        ppp=6, sbr=0.5, background="decaying", rng=seed
    )
    rng = np.random.default_rng(seed + 1)
    ramp = np.linspace(0.0, 0.2, shape[0])[:, None, None, None] * np.ones((1, shape[1], 1, n_bins))
    return sim.cube.counts + rng.poisson(ramp).astype(sim.cube.counts.dtype), sim.cube.irf


def _border_cube(border=16, n_bins=100):
    """A dim 6 x 6 plate centred on image row ``border`` over a brighter wall: the
    plate is found only by pooling across the row ``border`` (boxes up to 11 x 11)."""
    g = gaussian_irf(2.0)
    hw = g.size // 2
    lam = np.full((32, 24, 1, n_bins), 0.04)
    lam[:, :, 0, 60 - hw : 60 + hw + 1] += 3.0 * g  # the wall, everywhere
    lam[border - 3 : border + 3, 9:15, 0, 30 - hw : 30 + hw + 1] += 0.8 * g  # the plate
    return np.random.default_rng(5).poisson(lam).astype(np.int32), g


def _assert_same_detection(a, b):
    for f in dataclasses.fields(a.surfaces):
        x, y = getattr(a.surfaces, f.name), getattr(b.surfaces, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(y, x, err_msg=f.name)
        else:
            assert y == x, f.name
    np.testing.assert_array_equal(np.asarray(b.saliency), a.saliency)
    np.testing.assert_array_equal(np.asarray(b.mask), a.mask)
    np.testing.assert_array_equal(np.asarray(b.threshold), np.asarray(a.threshold))
    np.testing.assert_array_equal(b.background.spatial, a.background.spatial)
    np.testing.assert_array_equal(b.background.temporal, a.background.temporal)
    assert b.reduction == a.reduction
    assert b.null.details["evidence_threshold"] == a.null.details["evidence_threshold"]
    assert [(r.stage, r.added, r.removed, r.moved) for r in b.provenance] == [
        (r.stage, r.added, r.removed, r.moved) for r in a.provenance
    ]


def _cubes(counts, irf, chunks):
    """The same cube in memory and as a Dask array of the given chunks (both built from
    the same arrays: a Cube normalises its IRF, and a twice-normalised IRF can differ in
    the last bit)."""
    return Cube(counts, irf=irf), Cube(da.from_array(counts, chunks=chunks), irf=irf)


def test_tile_bounds_merges_a_last_tile_shorter_than_the_halo():
    assert tile_bounds(30, 7, 5) == [(0, 7), (7, 14), (14, 21), (21, 30)]
    assert tile_bounds(30, 10, 5) == [(0, 10), (10, 20), (20, 30)]
    assert tile_bounds(4, 10, 5) == [(0, 4)]


def test_detect_dask_cube_matches_in_memory():
    cube, lazy = _cubes(*_varying_cube(), (7, 11, 1, 60))  # chunks cut rows, columns, time
    assert is_dask(lazy.counts) and not is_dask(cube.counts)
    a = splidar.detect(cube, rng=4)
    b = splidar.detect(lazy, rng=4, block_rows=6)  # 5 tiles, halo 5 rows
    assert len(b.surfaces) > 0 and np.ndim(a.threshold) == 3
    _assert_same_detection(a, b)
    assert b.options["block_rows"] == 6


def test_detect_dask_cube_holds_freed_memory_in_the_map_and_stages_5_to_7(monkeypatch):
    """A Dask cube's map pass (its tables joined) and stages 5-7 run inside
    ``hold_freed_memory`` (glibc's settings set back after); an in-memory cube's do not."""
    import splidar.detection._detect as det_mod
    from splidar import _memory

    entered, real = [], _memory.hold_freed_memory

    def recording():
        entered.append(1)
        return real()

    monkeypatch.setattr(det_mod, "hold_freed_memory", recording)
    cube, lazy = _cubes(*_varying_cube(shape=(16, 14), n_bins=80), (8, 14, 1, 80))
    splidar.detect(cube, rng=0)
    assert entered == []
    splidar.detect(lazy, rng=0, block_rows=8)
    assert entered == [1, 1]
    assert _memory._keep_state == {"depth": 0, "restore": None, "any": 0, "restore_any": None}


def test_detect_dask_cube_with_a_hot_pixel_matches_in_memory():
    # a stuck pixel (10^4 x the background, flat in t) is set aside in both paths
    counts, irf = _varying_cube(shape=(24, 20), n_bins=100, seed=5)
    counts = counts.astype(np.uint32)
    counts[9, 7, 0] += np.random.default_rng(0).poisson(500.0, 100).astype(np.uint32)
    cube, lazy = _cubes(counts, irf, (7, 20, 1, 100))
    a = splidar.detect(cube, rng=3)
    b = splidar.detect(lazy, rng=3, block_rows=6)
    assert a.options["hot_pixels"] == b.options["hot_pixels"] == 1
    _assert_same_detection(a, b)


def test_detect_dask_same_result_whatever_tiles_and_threads():
    _, lazy = _cubes(*_varying_cube(shape=(26, 18), n_bins=100, seed=7), (13, 18, 1, 100))
    ref = splidar.detect(lazy, rng=11, block_rows=26)  # one tile
    for block_rows, threads in ((5, 1), (8, 2), (11, 3)):
        with dask.config.set(scheduler="threads", num_workers=threads):
            b = splidar.detect(lazy, rng=11, block_rows=block_rows)
        _assert_same_detection(ref, b)


def test_detect_dask_store_written_by_the_tiles(tmp_path):
    zarr = pytest.importorskip("zarr")
    cube, lazy = _cubes(*_varying_cube(shape=(20, 16), n_bins=100, seed=3), (5, 16, 1, 100))
    a = splidar.detect(cube, rng=0)
    b = splidar.detect(lazy, rng=0, block_rows=6, store=tmp_path / "s")
    assert isinstance(b.saliency, zarr.Array) and b.saliency.chunks[0] == 6
    _assert_same_detection(a, b)


def test_detect_dask_store_saliency_and_mask_in_one_chunk_per_tile(tmp_path):
    # tiles of 32 rows: the saliency and the mask in one chunk per tile (the last tile's
    # 8 rows in the grid's edge chunk); the same values
    cube, lazy = _cubes(*_varying_cube(shape=(40, 12), n_bins=80, seed=4), (20, 12, 1, 80))
    a = splidar.detect(cube, rng=0)
    b = splidar.detect(lazy, rng=0, block_rows=32, store=tmp_path / "s")
    assert b.saliency.chunks[0] == b.mask.chunks[0] == 32
    for name in ("saliency", "mask"):
        files = sorted(p.name for p in (tmp_path / "s" / name).glob("c.*"))
        assert files == ["c.0.0.0", "c.1.0.0"], name
    _assert_same_detection(a, b)


def test_detect_dask_store_written_by_2d_tiles(tmp_path, monkeypatch):
    # tiles of 6 x 7 pixels (the last ones merged): each writes its own chunks
    zarr = pytest.importorskip("zarr")
    from splidar.detection import _tiled

    cube, lazy = _cubes(*_varying_cube(shape=(20, 16), n_bins=100, seed=3), (5, 16, 1, 100))
    a = splidar.detect(cube, rng=0)
    monkeypatch.setattr(_tiled, "TILE_COLS", 7)
    b = splidar.detect(lazy, rng=0, block_rows=6, store=tmp_path / "s")
    assert isinstance(b.saliency, zarr.Array) and b.saliency.chunks[:2] == (6, 7)
    _assert_same_detection(a, b)
    # each tile stored its candidates' histograms under its own key (row and column)
    np.testing.assert_array_equal(np.asarray(b.surfaces.histograms), a.surfaces.histograms)


def test_put_writes_a_zarr_array_chunk_by_chunk_as_one_write(tmp_path):
    """``_put`` cuts a write at the chunk grid (offsets on and off it, partial edge
    chunks): the stored values equal a plain write's, and a chunk equal to the fill
    value is stored too (the map pass's arrays skip Zarr's comparison with it)."""
    zarr = pytest.importorskip("zarr")
    from splidar.detection._4_map import _put, writer

    rng = np.random.default_rng(0)
    g = zarr.open_group(str(tmp_path / "g"), mode="w")
    spec = dict(shape=(23, 17, 5), chunks=(4, 6, 5), dtype="float32")
    a, b = g.create_array("a", **spec), writer(g.create_array("b", **spec))
    for r0, c0, r, c in ((0, 0, 8, 12), (5, 3, 9, 10), (19, 13, 4, 4), (8, 0, 4, 6)):
        v = rng.random((r, c, 5), dtype=np.float32)
        if r0 == 8:
            v[:] = 0  # exactly one chunk, equal to the fill value
        a[r0 : r0 + r, c0 : c0 + c] = v
        _put(b, r0, c0, v)
    np.testing.assert_array_equal(b[...], a[...])
    assert b.nchunks_initialized == a.nchunks_initialized + 1
    out = np.zeros((23, 17, 5), np.float32)  # not Zarr: one plain write
    _put(out, 5, 3, np.ones((9, 10, 5), np.float32))
    assert out.sum() == 9 * 10 * 5


def test_put_writes_raw_whole_chunks_as_their_files(tmp_path, monkeypatch):
    """``_put`` on an array stored raw (the saliency): each whole chunk is written as its
    chunk file (Zarr not asked), the same bytes as Zarr writes; a partial chunk (off the
    grid, at the edges) through Zarr; the values read back equal a plain write's."""
    zarr = pytest.importorskip("zarr")
    from splidar.detection._4_map import _put, writer

    rng = np.random.default_rng(1)
    g = zarr.open_group(str(tmp_path / "g"), mode="w")
    spec = dict(shape=(23, 17, 5), chunks=(4, 6, 5), dtype="float32", compressors=None)
    a, b = g.create_array("a", **spec), writer(g.create_array("b", **spec))
    writes = ((0, 0, 8, 12), (5, 3, 9, 10), (19, 13, 4, 4), (8, 0, 4, 6), (12, 6, 8, 6))
    values = [rng.random((r, c, 5), dtype=np.float32) for _, _, r, c in writes]
    for (r0, c0, r, c), v in zip(writes, values, strict=True):
        a[r0 : r0 + r, c0 : c0 + c] = v
    real = type(b).__setitem__
    asked = []
    monkeypatch.setattr(type(b), "__setitem__", lambda z, k, v: asked.append(k) or real(z, k, v))
    for (r0, c0, _, _), v in zip(writes, values, strict=True):
        _put(b, r0, c0, v)
    monkeypatch.undo()
    np.testing.assert_array_equal(b[...], a[...])
    # the chunks' (row, col) starts each write covers whole: 4 + 1 + 0 + 1 + 2 of 18 pieces
    whole = {(0, 0), (0, 6), (4, 0), (4, 6), (8, 6), (8, 0), (12, 6), (16, 6)}
    assert len(asked) == 18 - len(whole)
    assert not any((k[0].stop - k[0].start, k[1].stop - k[1].start) == (4, 6) for k in asked)
    for r0, c0 in whole:
        key = f"c/{r0 // 4}/{c0 // 6}/0"
        g = tmp_path / "g"
        assert (g / "b" / key).read_bytes() == (g / "a" / key).read_bytes()
    assert not list((tmp_path / "g" / "b").rglob("*.partial"))


@pytest.fixture(scope="module")
def local_client():
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client


def test_detect_on_local_cluster_matches_in_memory(local_client):
    cube, lazy = _cubes(*_varying_cube(shape=(24, 20), n_bins=100, seed=9), (6, 20, 1, 100))
    a = splidar.detect(cube, rng=2)
    b = splidar.detect(lazy, rng=2, block_rows=6)
    _assert_same_detection(a, b)
    # the tiles ran as tasks of the cluster's scheduler
    names = {k[0] if isinstance(k, tuple) else k for k in local_client.run_on_scheduler(
        lambda dask_scheduler: list(dask_scheduler.task_prefixes)
    )}  # fmt: skip
    assert {"splidar-map-tile", "splidar-window-means"} <= names
    # the calling process fetches each tile's result without the running sums
    assert "splidar-map-result" in names


def test_detect_on_local_cluster_store_keeps_the_histograms_there(local_client, tmp_path):
    """With ``store=`` the tiles write their candidates' histograms to the store and the
    selected surfaces' ones stay there (``StoredHistograms``): the calling process never
    holds them all, and they read back as the in-memory run's, bit for bit."""
    import pickle

    from splidar.detection._result import StoredHistograms

    cube, lazy = _cubes(*_varying_cube(shape=(24, 20), n_bins=100, seed=9), (6, 20, 1, 100))
    a = splidar.detect(cube, rng=2)
    b = splidar.detect(lazy, rng=2, block_rows=6, store=tmp_path / "s")
    h = b.surfaces.histograms
    assert isinstance(h, StoredHistograms) and h.shape == a.surfaces.histograms.shape
    _assert_same_detection(a, b)
    idx = np.array([len(a.surfaces) - 1, 0, 3, 3])
    np.testing.assert_array_equal(h[idx], a.surfaces.histograms[idx])
    np.testing.assert_array_equal(h[:, 0], a.surfaces.histograms[:, 0])
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(h)), a.surfaces.histograms)
    # the candidates' histograms the tiles wrote are gone once the surfaces are selected;
    # the threshold is kept as its factors (computed on access), not stored
    assert sorted(p.name for p in (tmp_path / "s").iterdir() if p.is_dir()) == [
        "mask", "saliency", "surface_histograms",
    ]  # fmt: skip
    assert isinstance(b.threshold, ThresholdField)


def test_detect_on_local_cluster_zarr_cube_bands_match_in_memory(
    local_client, tmp_path, monkeypatch
):
    """A Zarr cube on a cluster with ``store=``: one task per band of tiles reads its
    rows from the Zarr array itself and runs the band's tiles (running sums passed in
    the task); the Detection is the in-memory one, bit for bit; the scheduler ran the
    band tasks and the first pass (stuck-pixel totals and stage 1's windows)."""
    zarr = pytest.importorskip("zarr")
    from splidar.detection import _tiled

    counts, irf = _varying_cube(shape=(24, 20), n_bins=100, seed=9)
    z = _zarr_of(zarr, tmp_path / "c.zarr", counts, chunks=(5, 20, 1, 100))
    monkeypatch.setattr(_tiled, "TILE_COLS", 7)  # 3 tiles a band
    a = splidar.detect(Cube(counts, irf=irf), rng=2)
    lazy = Cube(da.from_zarr(z), irf=irf)
    b = splidar.detect(lazy, rng=2, block_rows=6, store=tmp_path / "s")
    _assert_same_detection(a, b)
    names = {k[0] if isinstance(k, tuple) else k for k in local_client.run_on_scheduler(
        lambda dask_scheduler: list(dask_scheduler.task_prefixes)
    )}  # fmt: skip
    assert {"splidar-map-band", "splidar-first-pass"} <= names


def _band_path(tmp_path, monkeypatch):
    """A 24 x 20 cube in Zarr taken by the band path (3 tiles a band, 4 bands), its tasks
    run here on Dask's synchronous scheduler as a cluster's worker runs them:
    ``(counts, irf, z)``."""
    zarr = pytest.importorskip("zarr")
    import dask

    from splidar.detection import _tiled

    counts, irf = _varying_cube(shape=(24, 20), n_bins=100, seed=9)
    z = _zarr_of(zarr, tmp_path / "c.zarr", counts, chunks=(5, 20, 1, 100))
    monkeypatch.setattr(_tiled, "TILE_COLS", 7)

    class OneProcess:  # stands for a client: the band path is taken, tasks run here
        def run(self, fn):
            return fn()

    def each(tasks, take):
        for i, r in enumerate(dask.compute(*tasks, scheduler="synchronous")):
            take(i, r)

    monkeypatch.setattr(_tiled, "_client", OneProcess)
    monkeypatch.setattr(_tiled, "compute_each", each)
    return counts, irf, z


def test_map_band_opens_the_store_once_for_its_tiles(tmp_path, monkeypatch):
    """A band task opens the store's group once for its 3 tiles, not once per tile (the
    tiles' histograms go to raw files, no Zarr group opened); the Detection is the
    in-memory one."""
    from splidar.detection import _tiled

    counts, irf, z = _band_path(tmp_path, monkeypatch)  # (skipped without zarr)
    import zarr

    opened, in_band = [], [False]
    real_open, real_band = zarr.open_group, _tiled._map_band

    def open_group(p, **k):
        if in_band[0]:
            opened.append(str(p))
        return real_open(p, **k)

    monkeypatch.setattr(zarr, "open_group", open_group)

    def band(*a, **k):
        in_band[0] = True
        try:
            return real_band(*a, **k)
        finally:
            in_band[0] = False

    monkeypatch.setattr(_tiled, "_map_band", band)
    a = splidar.detect(Cube(counts, irf=irf), rng=2)
    b = splidar.detect(Cube(da.from_zarr(z), irf=irf), rng=2, block_rows=6, store=tmp_path / "s")
    _assert_same_detection(a, b)
    store = str(tmp_path / "s")
    assert opened == [store] * 4


def test_map_band_runs_its_tiles_with_freed_memory_kept(tmp_path, monkeypatch):
    """Every band task runs its tiles inside ``keep_freed_memory(any_size=True)`` (on a
    Dask worker the tiles' temporaries reuse freed pages), and the Detection is the
    in-memory one."""
    import contextlib

    from splidar.detection import _tiled

    counts, irf, z = _band_path(tmp_path, monkeypatch)
    entered = []

    @contextlib.contextmanager
    def kept(**k):
        entered.append(k)
        yield

    monkeypatch.setattr(_tiled, "keep_freed_memory", kept)
    a = splidar.detect(Cube(counts, irf=irf), rng=2)
    b = splidar.detect(Cube(da.from_zarr(z), irf=irf), rng=2, block_rows=6, store=tmp_path / "s")
    _assert_same_detection(a, b)
    assert entered == [{"any_size": True}] * 4


def _poisson_zarr(zarr, tmp_path, seed: int, shape: tuple, dtype) -> tuple:
    """Poisson counts (mean 2) of ``shape`` and their Zarr array in chunks of 13 whole
    rows (so bands cross chunk edges): ``(array, Zarr array)``."""
    y = np.random.default_rng(seed).poisson(2.0, shape).astype(dtype)
    z = zarr.open_array(str(tmp_path / "y.zarr"), mode="w", shape=y.shape,
                        chunks=(13,) + y.shape[1:], dtype=y.dtype)  # fmt: skip
    z[...] = y
    return y, z


def test_first_pass_gives_the_totals_and_window_means_of_a_zarr_cube(tmp_path):
    """One read of a Zarr cube's chunks gives the stuck-pixel totals and stage 1's
    window means, bit for bit the in-memory ones, whatever the bands (windows crossing
    a band's edge: partial sums of integers, exact); a stuck pixel in a Zarr cube is
    set aside as in memory."""
    zarr = pytest.importorskip("zarr")
    from splidar.detection._background import sample_grid
    from splidar.detection._fast import window_means
    from splidar.detection._tiled import first_pass

    y, z = _poisson_zarr(zarr, tmp_path, 5, (90, 300, 2, 40), np.uint16)
    lazy = da.from_zarr(z)
    with dask.config.set(scheduler="threads"):
        got = first_pass(lazy, 7)
        assert first_pass(lazy.astype(np.float32), 7) is None  # not integer counts
        assert first_pass(da.from_array(y), 7) is None  # not read from Zarr
    np.testing.assert_array_equal(got.totals, y.sum(axis=(2, 3), dtype=np.float64))
    kr, kc, rows, cols = sample_grid(y.shape, 7)
    ref = np.stack([window_means(y[a : a + kr], cols, kc) for a in rows])
    np.testing.assert_array_equal(got.windows(lazy, rows, kr, cols, kc), ref)
    # another grid than the pass's: read again, the same values as the loop
    again = got.windows(lazy, rows[::2], kr, cols, kc)
    np.testing.assert_array_equal(again, ref[::2])
    # a stuck pixel: the totals find it; the detection equals the in-memory one
    counts, irf = _varying_cube(shape=(24, 20), n_bins=100, seed=5)
    counts = counts.astype(np.uint32)
    counts[9, 7, 0] += np.random.default_rng(0).poisson(500.0, 100).astype(np.uint32)
    z = zarr.open_array(str(tmp_path / "c.zarr"), mode="w", shape=counts.shape,
                        chunks=(7, 20, 1, 100), dtype=counts.dtype)  # fmt: skip
    z[...] = counts
    a = splidar.detect(Cube(counts, irf=irf), rng=3)
    b = splidar.detect(Cube(da.from_zarr(z), irf=irf), rng=3, block_rows=6)
    assert a.options["hot_pixels"] == b.options["hot_pixels"] == 1
    _assert_same_detection(a, b)


def test_first_pass_gathers_the_null_sub_grid_of_a_zarr_cube(tmp_path):
    """With a step, the first pass also returns ``counts[::s, ::s]`` (the null's
    ``data_tail`` sub-grid), whatever the bands (65 rows: not a multiple of any step);
    the window means unchanged by it."""
    zarr = pytest.importorskip("zarr")
    from splidar.detection._tiled import first_pass

    y = np.random.default_rng(6).poisson(2.0, (150, 40, 2, 30)).astype(np.uint8)
    z = zarr.open_array(str(tmp_path / "y.zarr"), mode="w", shape=y.shape, chunks=(13, 40, 2, 30),
                        dtype=y.dtype)  # fmt: skip
    z[...] = y
    lazy = da.from_zarr(z)
    with dask.config.set(scheduler="threads"):
        plain = first_pass(lazy, 5)
        assert plain.sample is None
        for s in (1, 3, 7, 64):
            got = first_pass(lazy, 5, s)
            assert got.sample.dtype == y.dtype
            np.testing.assert_array_equal(got.sample, y[::s, ::s])
            np.testing.assert_array_equal(got.totals, plain.totals)
            np.testing.assert_array_equal(got._means, plain._means)


def test_data_tail_sample_equals_reading_the_counts():
    """``data_tail`` given its sub-grid already read gives what it reads itself."""
    from splidar.detection import _3_null

    g = gaussian_irf(3.0)
    irf, h = g[None] / g.sum(), g.size // 2
    lam = np.full((40, 36, 1, 120), 0.05)
    for r in range(40):  # bright returns at depths 30-65
        for c in range(36):
            d = 30 + (r + c) % 36
            lam[r, c, 0, d - h : d + h + 1] += 20 * g
    counts = np.random.default_rng(4).poisson(lam).astype(np.uint8)
    dev = np.zeros((1, 120), np.float32)
    for m in (8_000_000, 40_000):  # every pixel; a step of 3
        s = _3_null.tail_step(counts.shape, m)
        a = _3_null.data_tail(counts, irf, dev, max_voxels=m)
        b = _3_null.data_tail(None, irf, dev, max_voxels=m, sample=counts[::s, ::s].copy())
        assert a.size > 0
        np.testing.assert_array_equal(a, b)
    assert _3_null.tail_step(counts.shape, 40_000) == 3


def _stuck_pixel_zarr_cube(tmp_path):
    """A small varying cube (24 x 20 x 1 x 100, uint16) with a stuck pixel at (9, 6),
    and the same counts as a Zarr array in chunks of 7 rows: ``(counts, irf, z)``."""
    zarr = pytest.importorskip("zarr")
    counts, irf = _varying_cube(shape=(24, 20), n_bins=100, seed=5)
    counts = counts.astype(np.uint16)
    counts[9, 6, 0] += np.random.default_rng(0).poisson(500.0, 100).astype(np.uint16)
    z = zarr.open_array(str(tmp_path / "c.zarr"), mode="w", shape=counts.shape,
                        chunks=(7, 20, 1, 100), dtype=counts.dtype)  # fmt: skip
    z[...] = counts
    return counts, irf, z


def test_detect_zarr_cube_hands_the_null_its_sub_grid_from_the_first_pass(tmp_path, monkeypatch):
    """A Zarr cube on Dask: the null's ``data_tail`` gets its sub-grid from the first
    pass (the cube not read again), a stuck pixel set to 0 in it as in the cube; the
    Detection the in-memory one."""
    from splidar.detection import _3_null, _detect

    counts, irf, z = _stuck_pixel_zarr_cube(tmp_path)
    seen, tail = [], _3_null.data_tail

    def spy(c, *a, sample=None, **k):
        seen.append(None if sample is None else sample.copy())
        return tail(c, *a, sample=sample, **k)

    monkeypatch.setattr(_3_null, "data_tail", spy)
    a = splidar.detect(Cube(counts, irf=irf), rng=3)
    b = splidar.detect(Cube(da.from_zarr(z), irf=irf), rng=3, block_rows=6)
    assert seen[0] is None and seen[1] is not None  # in memory: read there
    masked = counts.copy()
    masked[9, 6] = 0
    np.testing.assert_array_equal(seen[1], masked)  # a step of 1 on this small cube
    assert b.options["hot_pixels"] == 1
    _assert_same_detection(a, b)
    # a step of 3: the stuck pixel (9, 6) falls on the sub-grid
    monkeypatch.setattr(_detect, "tail_step", lambda shape: 3)
    splidar.detect(Cube(da.from_zarr(z), irf=irf), rng=3, block_rows=6)
    np.testing.assert_array_equal(seen[2], masked[::3, ::3])


def test_first_pass_gathers_blocks_of_a_zarr_cube(tmp_path):
    """With blocks, the first pass also returns ``counts[r0:r1, c0:c1]`` of each, whatever
    the bands they cross (65 rows: within one band, across two, at the image's edges);
    the totals and window means unchanged by them."""
    zarr = pytest.importorskip("zarr")
    from splidar.detection._tiled import first_pass

    y, z = _poisson_zarr(zarr, tmp_path, 7, (150, 40, 2, 30), np.uint8)
    lazy = da.from_zarr(z)
    blocks = [(3, 20, 0, 40), (50, 92, 7, 19), (0, 150, 30, 40), (140, 150, 0, 1)]
    with dask.config.set(scheduler="threads"):
        plain = first_pass(lazy, 5)
        got = first_pass(lazy, 5, 0, blocks)
    assert plain.blocks == {} and list(got.blocks) == blocks
    for r0, r1, c0, c1 in blocks:
        block = got.blocks[r0, r1, c0, c1]
        assert block.dtype == y.dtype and block.tobytes() == y[r0:r1, c0:c1].tobytes()
    np.testing.assert_array_equal(got.totals, plain.totals)
    np.testing.assert_array_equal(got._means, plain._means)


def test_detect_zarr_cube_hands_coherent_scales_its_tiles_from_the_first_pass(
    tmp_path, monkeypatch
):
    """A Zarr cube on Dask with ``scales="auto"``: ``coherent_scales`` reads its tiles
    from the first pass's blocks (the cube not read again: any other read fails here), a
    stuck pixel in them set to 0 as in the cube; the Detection the in-memory one."""
    from splidar.detection import _detect
    from splidar.detection._tiled import Gathered

    counts, irf, z = _stuck_pixel_zarr_cube(tmp_path)
    seen, coherent = [], _detect.coherent_scales

    class Unread:
        shape, dtype, ndim = counts.shape, counts.dtype, counts.ndim

        def __getitem__(self, key):
            raise AssertionError(f"coherent_scales read {key} from the cube")

    def spy(c, ctx):
        if isinstance(c, Gathered):
            seen.append({k: v.copy() for k, v in c.blocks.items()})
            c = Gathered(Unread(), c.blocks)
        return coherent(c, ctx)

    monkeypatch.setattr(_detect, "coherent_scales", spy)
    a = splidar.detect(Cube(counts, irf=irf), rng=3)
    assert a.options["scales_auto"] and seen == []  # in memory: read there
    b = splidar.detect(Cube(da.from_zarr(z), irf=irf), rng=3, block_rows=6)
    masked = counts.copy()
    masked[9, 6] = 0
    ((key, block),) = seen[0].items()  # one tile, with its halo the whole small image
    r0, r1, c0, c1 = key
    assert (r0, c0) == (0, 0) and block.tobytes() == masked[r0:r1, c0:c1].tobytes()
    assert b.options["hot_pixels"] == 1
    assert b.options["scale_coherence"] == a.options["scale_coherence"]
    _assert_same_detection(a, b)


def test_detect_on_local_cluster_finds_a_surface_across_a_tile_border(local_client):
    cube, lazy = _cubes(*_border_cube(border=16), (8, 24, 1, 100))
    a = splidar.detect(cube, rng=0)
    plate = (np.abs(a.surfaces.depth_bin - 30) < 2) & (a.surfaces.col >= 9) & (a.surfaces.col < 15)
    rows = set(a.surfaces.row[plate].tolist())
    # in memory the plate is found on both sides of row 16 ...
    assert {14, 15, 16, 17} <= rows
    # ... and so it is when a tile ends at row 16 (tiles [0, 16), [16, 32))
    b = splidar.detect(lazy, rng=0, block_rows=16)
    assert b.options["block_rows"] == 16
    _assert_same_detection(a, b)


def test_detect_on_local_cluster_auto_scales_by_region_matches_in_memory(local_client, tmp_path):
    """``scales="auto"`` whose regions keep different boxes (the left half independent
    depths, the right a plane) runs ``detect`` once per set and merges per pixel: on a
    LocalCluster, stored or not, the in-memory result."""
    rng = np.random.default_rng(0)
    depth = 30 + np.add.outer(np.arange(48), np.arange(48)) // 4
    depth[:, :24] = rng.integers(15, 105, size=(48, 24))
    g = gaussian_irf(3.0)
    lam = np.full((48, 48, 1, 120), 0.1)
    for (i, j), d in np.ndenumerate(depth):
        lam[i, j, 0, d - g.size // 2 : d + g.size // 2 + 1] += 8.0 * g
    cube, lazy = _cubes(rng.poisson(lam).astype(np.uint16), g, (16, 48, 1, 120))
    a = splidar.detect(cube, rng=0)
    assert a.options["scale_regions"]["scales"] == ((1, 3, 7, 11), (1,))
    _assert_same_detection(a, splidar.detect(lazy, rng=0, block_rows=16))
    _assert_same_detection(a, splidar.detect(lazy, rng=0, block_rows=16, store=tmp_path / "s"))


def test_cli_run_scheduler_joins_a_cluster_and_matches_in_memory(local_client, tmp_path, capsys):
    pytest.importorskip("zarr")
    from splidar.cli import main
    from splidar.io import save

    cube, _ = _cubes(*_varying_cube(shape=(20, 18), n_bins=100, seed=4), (5, 18, 1, 100))
    save(cube, tmp_path / "c.npz")
    save(cube, tmp_path / "c.zarr", chunks=(5, 9))
    common = ["--no-figures", "-q", "--seed", "3"]
    assert main(["run", str(tmp_path / "c.npz"), "--out", str(tmp_path / "a"), *common]) == 0
    address = local_client.scheduler.address
    args = ["run", str(tmp_path / "c.zarr"), "--out", str(tmp_path / "b"), "--scheduler", address]
    assert main([*args, *common]) == 0
    err = capsys.readouterr().err
    assert f"2 worker(s) at {address}; dashboard: http" in err
    a, b = (np.load(tmp_path / d / "result.npz") for d in ("a", "b"))
    assert a["points_depth_bin"].size > 0
    for k in ("points_row", "points_col", "points_depth_bin", "points_intensity", "depth_map"):
        np.testing.assert_array_equal(b[k], a[k])


def test_cli_run_cluster_options_are_checked(tmp_path, capsys):
    from splidar.cli import main
    from splidar.io import save

    save(Cube(np.zeros((8, 8, 1, 40), np.int32), irf=gaussian_irf(2.0)), tmp_path / "c.npz")
    run = ["run", str(tmp_path / "c.npz"), "--no-figures", "-q"]
    assert main([*run, "--memory-limit", "1GB"]) == 2
    assert "add --workers N" in capsys.readouterr().err
    assert main([*run, "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert main([*run, "--workers", "0"]) == 2


def _zarr_of(zarr, path, counts, *, chunks):
    """``counts`` written to a new Zarr array at ``path`` in ``chunks``; the array."""
    z = zarr.open_array(str(path), mode="w", shape=counts.shape, chunks=chunks, dtype=counts.dtype)
    z[...] = counts
    return z


def _detect_killing_the_first_worker(task: str, detect_lazy):
    """Run ``detect_lazy()`` on a LocalCluster of two worker processes whose worker
    holding the first finished task named ``task`` is killed (SIGKILL); assert the
    scheduler computed that task again after it was in memory; return the Detection."""
    distributed = pytest.importorskip("distributed")
    import os

    from conftest import kill_first_worker

    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        client.wait_for_workers(2)
        # the workers load the numba kernels before the measured run (a worker busy
        # compiling under load must not be what the test exercises)
        small, _ = _cubes(*_varying_cube(shape=(12, 8), n_bins=60, seed=1), (6, 8, 1, 60))
        splidar.detect(Cube(da.from_array(small.counts, chunks=(6, 8, 1, 60)), irf=small.irf))
        plugin = kill_first_worker(client.run(os.getpid), task)
        cluster.scheduler.add_plugin(plugin, name="kill-first-worker")
        b = detect_lazy()
        story = cluster.scheduler.story(plugin.key)
    assert plugin.killed is not None, f"no {task} task reached memory on a known worker"
    # the killed worker's task went back to being computed after it was in memory
    finishes = [s[2] for s in story if s[0] == plugin.key]
    assert finishes.count("memory") >= 2, finishes
    return b


def test_detect_on_local_cluster_recomputes_a_killed_workers_tiles():
    """Two worker processes; the first to finish a tile is killed (SIGKILL) as it does:
    the scheduler recomputes that tile elsewhere and the Detection is the same."""
    cube, lazy = _cubes(*_varying_cube(shape=(40, 20), n_bins=100, seed=6), (8, 20, 1, 100))
    a = splidar.detect(cube, rng=1)
    b = _detect_killing_the_first_worker(
        "splidar-map-tile",
        lambda: splidar.detect(lazy, rng=1, block_rows=5),  # 8 tiles
    )
    _assert_same_detection(a, b)


def test_detect_on_local_cluster_recomputes_a_killed_workers_band(tmp_path):
    """The band path (a Zarr cube with ``store=``): the worker holding the first
    finished band task is killed (SIGKILL); the scheduler recomputes that band, whose
    tiles write the store again, and the Detection is the in-memory one."""
    zarr = pytest.importorskip("zarr")
    counts, irf = _varying_cube(shape=(40, 20), n_bins=100, seed=6)
    z = _zarr_of(zarr, tmp_path / "c.zarr", counts, chunks=(8, 20, 1, 100))
    a = splidar.detect(Cube(counts, irf=irf), rng=1)
    b = _detect_killing_the_first_worker(
        "splidar-map-band",
        lambda: splidar.detect(
            Cube(da.from_zarr(z), irf=irf), rng=1, block_rows=5, store=tmp_path / "s"
        ),  # 8 bands
    )
    _assert_same_detection(a, b)


@pytest.mark.parametrize(
    ("options", "block_rows", "tile_rows"),
    [(dict(scales=(1,)), 2, 2), (dict(scales=(1, 3)), 1, 1), (dict(), 3, 5)],
)
def test_detect_dask_small_tiles_and_no_halo_match_in_memory(options, block_rows, tile_rows):
    # no halo (a single scale of 1 pixel); tiles of one row; block_rows raised to the halo
    sim = single_surface_scene((12, 30), n_bins=80).simulate(ppp=5, sbr=1, rng=0)
    cube, lazy = _cubes(sim.cube.counts, sim.cube.irf, (3, 30, 1, 80))
    a = splidar.detect(cube, rng=1, **options)
    b = splidar.detect(lazy, rng=1, block_rows=block_rows, **options)
    assert b.options["block_rows"] == tile_rows
    _assert_same_detection(a, b)


def test_process_dask_multispectral_cube_matches_in_memory():
    from splidar.scenes import multispectral_scene

    sim = multispectral_scene((20, 16), n_bins=100).simulate(ppp=5, sbr=1, rng=0)
    cube, lazy = _cubes(sim.cube.counts, sim.cube.irf, (4, 8, 2, 50))
    a = splidar.process(cube, library=sim.cube.library, rng=0)
    b = splidar.process(lazy, library=sim.cube.library, rng=0)
    _assert_same_detection(a.detection, b.detection)
    np.testing.assert_array_equal(b.points.intensity, a.points.intensity)
    np.testing.assert_array_equal(b.points.label, a.points.label)


def test_tile_rows_fit_the_workers_memory_share(caplog):
    from splidar.detection._tiled import TILE_SHARE, _rows_for, tile_bytes

    shape, h = (3072, 1024, 1, 1000), 5
    rows = _rows_for(10**9, shape, 1, h, 3, 64)
    # the most rows whose tile fits the share of a 1 GB worker, not the in-memory 64
    assert h <= rows < 64
    assert (
        tile_bytes(rows, shape, 1, h, 3) <= TILE_SHARE * 1e9 < tile_bytes(rows + 1, shape, 1, h, 3)
    )
    assert _rows_for(10**12, shape, 1, h, 3, 64) == 64  # never more than asked
    # rows too wide for the worker: a tile of the halo's rows, and a warning saying so
    with caplog.at_level("WARNING", logger="splidar.detection._tiled"):
        assert _rows_for(10**8, shape, 1, h, 3, 64) == h
    assert "more than 40 % of the workers' memory limit" in caplog.text


def test_detect_on_cluster_sizes_tiles_to_the_memory_limit():
    distributed = pytest.importorskip("distributed")
    from splidar.detection._tiled import _rows_for, _tile_shape

    cube, lazy = _cubes(*_varying_cube(shape=(30, 22), n_bins=120, seed=5), (10, 22, 1, 120))
    a = splidar.detect(cube, rng=1)
    # threads in this process: the workers' memory monitor is off (it would measure the
    # whole test process); 4 MB per worker leaves tiles of 10-11 rows on this cube
    off = {f"distributed.worker.memory.{k}": False for k in ("target", "spill", "pause")}
    with (
        dask.config.set(off),
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, memory_limit="4MB",
            dashboard_address=":0",
        ) as cluster,
        distributed.Client(cluster),
    ):  # fmt: skip
        b = splidar.detect(lazy, rng=1)
    n_box = (0, 3)  # box means kept for extraction or not (map_plan's choice)
    fits = {_rows_for(4 * 10**6, lazy.shape, lazy.counts.dtype.itemsize, 5, q, 30) for q in n_box}
    # square tiles of the pixels of that many whole rows (the same memory, less halo)
    square = {_tile_shape(r, lazy.shape, 5, 6, False)[0] for r in fits}
    # without a limit the tile would be the in-memory block (the whole image here)
    assert a.options["block_rows"] == 30 and b.options["block_rows"] in square
    assert b.options["block_rows"] < 30
    _assert_same_detection(a, b)


def test_tiled_window_means_sampled_columns_equal_loop():
    # a wide image: the grid's windows cover part of the columns, which the tasks take
    # from the chunks alone; the means must equal the in-memory loop's bit for bit
    from splidar.detection._background import sample_grid
    from splidar.detection._fast import window_means

    y = np.random.default_rng(5).poisson(2.0, (90, 300, 2, 40)).astype(np.uint8)
    kr, kc, rows, cols = sample_grid(y.shape, 7, n_samples=60)
    assert (cols[:, None] + np.arange(kc)).size < y.shape[1]  # columns are skipped
    ref = np.stack([window_means(y[a : a + kr], cols, kc) for a in rows])
    with dask.config.set(scheduler="threads"):
        got = tiled_window_means(da.from_array(y, chunks=(16, 128, 2, 40)), rows, kr, cols, kc)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("tile_cols", [6, 7, 13])
def test_detect_dask_2d_tiles_of_any_width_match_in_memory(monkeypatch, tile_cols):
    # tiles of 8 rows x tile_cols columns (halo 5 rows, 6 columns): the box filters'
    # running column sums pass from tile to tile, so every width gives the same bits
    from splidar.detection import _tiled

    cube, lazy = _cubes(*_varying_cube(shape=(24, 30), n_bins=100, seed=3), (8, 10, 1, 100))
    a = splidar.detect(cube, rng=3)
    monkeypatch.setattr(_tiled, "TILE_COLS", tile_cols)
    with dask.config.set(scheduler="threads", num_workers=2):
        b = splidar.detect(lazy, rng=3, block_rows=8)
    _assert_same_detection(a, b)


def test_read_rows_reads_stored_chunks_in_the_calling_process(tmp_path):
    # a cube that only reads stored chunks is read here (synchronous scheduler), not by
    # the active scheduler (a cluster); any other graph goes to the active scheduler
    zarr = pytest.importorskip("zarr")
    from splidar.detection._slopes import _read_rows

    x = np.arange(20 * 3 * 1 * 5, dtype=np.uint8).reshape(20, 3, 1, 5)
    z = zarr.open_array(str(tmp_path / "c.zarr"), mode="w", shape=x.shape, chunks=(4, 3, 1, 5))
    z[:] = x

    def refuse(*args, **kwargs):
        raise RuntimeError("computed by the active scheduler")

    stored = (da.from_zarr(z), da.from_array(x, chunks=(4, 3, 1, 5)), da.from_zarr(z)[:, :, 0])
    with dask.config.set(scheduler=refuse):
        for lazy in stored:
            got = _read_rows(lazy, 3, 11)
            assert isinstance(got, np.ndarray)
            np.testing.assert_array_equal(got, x[3:11].reshape(got.shape))
        computed = da.from_zarr(z).astype(np.int16) + 1
        with pytest.raises(RuntimeError, match="active scheduler"):
            _read_rows(computed, 3, 11)
    np.testing.assert_array_equal(_read_rows(computed, 3, 11), x[3:11].astype(np.int16) + 1)


def test_read_rows_falls_back_to_the_scheduler_when_files_are_unreachable_here():
    # a stored array whose files this process cannot open (OSError) is read through the
    # active scheduler, whose workers may see them
    import threading

    from splidar.detection._slopes import _read_rows

    x = np.arange(20 * 3 * 1 * 5, dtype=np.uint8).reshape(20, 3, 1, 5)

    class WorkersOnly:
        shape, dtype, ndim = x.shape, x.dtype, x.ndim

        def __getitem__(self, key):
            if threading.current_thread() is threading.main_thread():
                raise OSError("no such file here")
            return x[key]

    lazy = da.from_array(WorkersOnly(), chunks=(4, 3, 1, 5), meta=np.empty((0,) * 4, x.dtype))
    with dask.config.set(scheduler="threads"):
        np.testing.assert_array_equal(_read_rows(lazy, 3, 11), x[3:11])


def test_cli_cluster_starts_with_the_quiet_dask_settings():
    """The LocalCluster of ``splidar run --workers`` runs with ``CLUSTER_CONFIG`` (the
    workers' profiler off, slower ticks): Dask's idle CPU per second of a run."""
    pytest.importorskip("distributed")
    from splidar._cluster import CLUSTER_CONFIG, dask_session

    def settings():
        return [dask.config.get(k) for k in CLUSTER_CONFIG]

    with dask_session(workers=1, memory_limit="1GB", progress=False) as client:
        assert list(client.run(settings).values()) == [list(CLUSTER_CONFIG.values())]
    assert dask.config.get("distributed.worker.profile.enabled") is True  # restored here
