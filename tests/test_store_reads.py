"""The calling process's reads of a detection's store and of a Zarr cube (clean-up passes):
read at the voxels or rows needed, the same values as the band-by-band reads."""

import numpy as np
import pytest

zarr = pytest.importorskip("zarr")
da = pytest.importorskip("dask.array")

from splidar._arrays import zarr_take_rows, zarr_voxels  # noqa: E402
from splidar.detection import ThresholdField  # noqa: E402
from splidar.detection._6_select import _gather  # noqa: E402
from splidar.detection._slopes import (  # noqa: E402
    _read_rows,
    _row_bands,
    _support_sums_bands,
    _zarr_of,
    support_sums,
)
from splidar.detection._table import (  # noqa: E402
    CandidateTable,
    remove_tree,
    store_histograms,
)


def _supports(rng, R, C, T, S):
    rows, cols = rng.integers(0, R, S), rng.integers(0, C, S)
    start = rng.integers(0, T - 9, S)
    stop = start + rng.integers(0, 10, S)  # widths 0 to 9 bins (0: an empty support)
    return rows, cols, start, stop


def test_support_sums_zarr_equals_band_reads(tmp_path):
    rng = np.random.default_rng(0)
    R, C, T = 23, 17, 40
    sal = rng.gamma(2.0, 1.0, (R, C, T)).astype(np.float32)
    thr = rng.uniform(0.5, 3.0, (R, C, T)).astype(np.float32)
    g = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    zs = g.create_array("saliency", shape=sal.shape, chunks=(4, 5, T), dtype="float32")
    zt = g.create_array("threshold", shape=thr.shape, chunks=(4, 5, T), dtype="float32")
    zs[...], zt[...] = sal, thr
    rows, cols, start, stop = _supports(rng, R, C, T, 200)
    field = ThresholdField(
        rng.uniform(0.0, 1.0, (R, C, 1)).astype(np.float32),
        rng.normal(0.0, 0.1, (1, T)).astype(np.float32),
        np.array([0.0, 0.5, 1.5]),
        np.array([1.0, 1.5, 2.5]),
    )
    # every kind of threshold, on the saliency in memory and stored: bit for bit the
    # band-by-band sums (each support summed alone, in the same order)
    for threshold in (zt, thr, 1.3, thr[:1, :1], field):
        want = _support_sums_bands(sal, threshold, rows, cols, start, stop)
        for saliency in (sal, zs):
            got = support_sums(saliency, threshold, rows, cols, start, stop)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
    assert np.all(want[0][stop == start] == 0) and np.any(want[1] > 0)
    # a Dask saliency is read band by band, with the same sums
    got = support_sums(da.from_array(sal, chunks=(5, C, T)), zt, rows, cols, start, stop)
    np.testing.assert_array_equal(got[0], want[0])


def _raw_array(tmp_path, a, chunks, fill=0.0):
    """``a`` in a raw-stored (no compressor) Zarr array of ``chunks``; its first chunk of
    rows and columns never written (the fill value)."""
    g = zarr.open_group(str(tmp_path / "raw.zarr"), mode="w")
    z = g.create_array(
        "saliency", shape=a.shape, chunks=chunks, dtype=a.dtype, compressors=None,
        fill_value=fill,
    )  # fmt: skip
    z[chunks[0] :] = a[chunks[0] :]
    z[: chunks[0], chunks[1] :] = a[: chunks[0], chunks[1] :]
    want = a.copy()
    want[: chunks[0], : chunks[1]] = fill
    return g["saliency"], want


def test_zarr_voxels_equals_the_coordinate_selection(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    R, C, T = 23, 17, 40  # edge chunks of 3 rows and 2 columns (stored padded)
    a = rng.gamma(2.0, 1.0, (R, C, T)).astype(np.float32)
    z, want = _raw_array(tmp_path, a, (4, 5, T), fill=0.5)
    idx = (rng.integers(0, R, 3000), rng.integers(0, C, 3000), rng.integers(0, T, 3000))
    expected = z.get_coordinate_selection(idx)
    np.testing.assert_array_equal(expected, want[idx])
    # read from the chunk files, not through Zarr: the same values (the never-written
    # chunk is the fill value)
    monkeypatch.setattr(type(z), "get_coordinate_selection", _fails)
    monkeypatch.setattr(type(z), "__getitem__", _fails)
    got = zarr_voxels(z, idx)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, expected)
    assert zarr_voxels(z, tuple(i[:0] for i in idx)).size == 0
    # a compressed array, or a chunk file that is not one chunk's raw bytes: Zarr's read
    g = zarr.open_group(str(tmp_path / "zstd.zarr"), mode="w")
    zc = g.create_array("s", shape=a.shape, chunks=(4, 5, T), dtype="float32")
    assert zarr_voxels(zc, idx) is None
    path = tmp_path / "raw.zarr" / "saliency" / "c" / "1" / "1" / "0"
    path.write_bytes(path.read_bytes()[:-4])
    assert zarr_voxels(z, idx) is None


def _fails(*args, **kwargs):
    raise AssertionError("read through Zarr")


def test_support_sums_raw_zarr_saliency_reads_the_supports_only(tmp_path, monkeypatch):
    rng = np.random.default_rng(4)
    R, C, T = 23, 17, 40
    sal = rng.gamma(2.0, 1.0, (R, C, T)).astype(np.float32)
    z, want = _raw_array(tmp_path, sal, (4, 5, T))
    thr = rng.uniform(0.5, 3.0, (R, C, T)).astype(np.float32)
    rows, cols, start, stop = _supports(rng, R, C, T, 300)
    expected = support_sums(want, thr, rows, cols, start, stop)
    # the map pass's stored saliency (raw chunks) read at the supports' voxels only
    monkeypatch.setattr(type(z), "get_coordinate_selection", _fails)
    monkeypatch.setattr(type(z), "__getitem__", _fails)
    got = support_sums(z, thr, rows, cols, start, stop)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])


def test_read_rows_slices_the_zarr_array_of_a_loaded_cube(tmp_path):
    rng = np.random.default_rng(1)
    y = rng.poisson(0.3, (30, 6, 1, 20)).astype(np.uint8)
    z = zarr.open_group(str(tmp_path / "c.zarr"), mode="w").create_array(
        "counts", shape=y.shape, chunks=(7, 6, 1, 20), dtype="uint8"
    )
    z[...] = y
    lazy = da.from_zarr(z)
    assert _zarr_of(lazy) is not None
    # a graph that computes, or a view of the stored array, is not read from Zarr itself
    for other in (lazy + 1, lazy[:, :, :, :10], lazy[::2], da.from_array(y, chunks=7)):
        assert _zarr_of(other) is None
    for y0, y1 in ((0, 30), (5, 19), (28, 30)):
        np.testing.assert_array_equal(_read_rows(lazy, y0, y1), y[y0:y1])
        np.testing.assert_array_equal(_read_rows(lazy + 1, y0, y1), y[y0:y1] + 1)
    items = np.array([0, 3, 29, 12, 13])
    got = {tuple(sel): (band.copy(), y0) for sel, band, y0 in _row_bands(lazy, items, 2, band=8)}
    for sel, (band, y0) in got.items():
        np.testing.assert_array_equal(band, y[y0 : y0 + band.shape[0]])
        for r in items[list(sel)]:  # each item's rows and their halo of 2 are in its band
            assert y0 <= max(r - 2, 0) and min(r + 3, 30) <= y0 + band.shape[0]
    assert sorted(s for sel in got for s in sel) == list(range(items.size))


def test_gather_stored_histograms_equals_in_memory(tmp_path):
    rng = np.random.default_rng(2)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    blocks = [rng.normal(size=(n, 2, 1, 5)).astype(np.float32) for n in (7, 0, 11, 4)]
    stored = []
    for i, b in enumerate(blocks):
        z = g.create_array(str(i), shape=b.shape, chunks=(3, 2, 1, 5), dtype="float32")
        if len(b):
            z[...] = b
        stored.append(z)
    extra = rng.normal(size=(3, 2, 1, 5)).astype(np.float32)
    hb = np.array([0] * 7 + [2] * 11 + [3] * 4 + [-1] * 3)
    hr = np.concatenate([np.arange(7), np.arange(11), np.arange(4), np.arange(3)])
    table = CandidateTable(
        columns={"row": np.arange(hb.size)}, keep=np.ones(hb.size, bool),
        origin=np.zeros(hb.size, np.int8), hist_block=hb, hist_row=hr,
        image_shape=(hb.size, 1), extra_histograms=extra,
    )  # fmt: skip
    idx = rng.permutation(hb.size)[:20]
    want = _gather(table, idx, tuple(blocks))
    for i, k in enumerate(idx):
        src = extra if hb[k] == -1 else blocks[hb[k]]
        np.testing.assert_array_equal(want[i], src[hr[k]])
    np.testing.assert_array_equal(_gather(table, idx, tuple(stored)), want)


def test_gather_gives_pages_back_only_for_blocks_held_in_memory(tmp_path, monkeypatch):
    """``_gather(..., release=True)`` sets each block to None after its last part and
    returns the heap's free pages (``give_back``) when a block released held its
    histograms in memory; stored blocks (Zarr arrays) free next to nothing: no trim
    (it made the next parts' buffers new pages). The same histograms either way."""
    from splidar.detection import _6_select

    rng = np.random.default_rng(4)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    blocks = [rng.normal(size=(n, 2, 1, 5)).astype(np.float32) for n in (9, 6, 12)]
    stored = []
    for i, b in enumerate(blocks):
        z = g.create_array(str(i), shape=b.shape, chunks=(4, 2, 1, 5), dtype="float32")
        z[...] = b
        stored.append(z)
    hb = np.repeat(np.arange(3), [9, 6, 12])
    hr = np.concatenate([np.arange(9), np.arange(6), np.arange(12)])
    table = CandidateTable(
        columns={"row": np.arange(hb.size)}, keep=np.ones(hb.size, bool),
        origin=np.zeros(hb.size, np.int8), hist_block=hb, hist_row=hr,
        image_shape=(hb.size, 1),
    )  # fmt: skip
    monkeypatch.setattr(_6_select, "GATHER_CHUNK", 5)
    trims = []
    monkeypatch.setattr(_6_select, "give_back", lambda: trims.append(1))
    idx = np.arange(hb.size)
    got = {}
    for name, hists in (("memory", list(blocks)), ("stored", list(stored))):
        trims.clear()
        got[name] = _6_select._gather(table, idx, hists, release=True)
        assert hists == [None, None, None]  # every block released after its last part
        got[name + " trims"] = len(trims)
    assert got["memory trims"] >= 2 and got["stored trims"] == 0
    np.testing.assert_array_equal(got["stored"], got["memory"])
    np.testing.assert_array_equal(got["memory"], np.concatenate(blocks))


def test_gather_writes_a_part_while_reading_the_next(monkeypatch):
    """An ``out`` not in memory (a store's array) is written part by part on a thread
    while the next part is read: each part's write (but the last) sees the next part's
    read start; the values are the selection's."""
    import threading

    from splidar.detection import _6_select

    monkeypatch.setattr(_6_select, "GATHER_CHUNK", 4)
    data = np.random.default_rng(3).normal(size=(12, 2, 1, 5)).astype(np.float32)
    started = {a: threading.Event() for a in (0, 4, 8)}

    class Stored:  # a block's stored array (read by slices of rows)
        shape, dtype = data.shape, data.dtype

        def __getitem__(self, key):
            started[key.start].set()
            return data[key]

    class Out:
        def __init__(self):
            self.a, self.saw_next = np.zeros(data.shape, np.float32), []

        def __setitem__(self, key, value):
            if key.stop < 12:  # the next part's read starts while this one is written
                self.saw_next.append(started[key.stop].wait(2.0))
            self.a[key] = value

    table = CandidateTable(
        columns={"row": np.arange(12)}, keep=np.ones(12, bool), origin=np.zeros(12, np.int8),
        hist_block=np.zeros(12, np.int64), hist_row=np.arange(12), image_shape=(12, 1),
    )  # fmt: skip
    out = Out()
    assert _6_select._gather(table, np.arange(12), [Stored()], out) is out
    assert out.saw_next == [True, True]
    np.testing.assert_array_equal(out.a, data)


def test_stored_rows_reads_raw_chunk_files_as_zarr(tmp_path, monkeypatch):
    """``_stored_rows``: a raw Zarr array in chunks of whole rows (the tiles' candidate
    histograms) is read from its chunk files (Zarr not asked), a chunk never written as
    the fill value; a compressed one through Zarr; the same values as ``z[lo:hi]``."""
    from splidar.detection._6_select import _stored_rows

    rng = np.random.default_rng(4)
    d = rng.normal(size=(23, 2, 1, 5)).astype(np.float32)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    raw = g.create_array("raw", shape=d.shape, chunks=(4, 2, 1, 5), dtype="f4", compressors=None)
    raw[:16] = d[:16]  # rows 16-23: chunks never written (the fill value, 0)
    packed = store_histograms(g, "packed", d.shape, data=d)
    want = np.concatenate([d[:16], np.zeros((7, 2, 1, 5), np.float32)])
    ranges = [(0, 23), (3, 9), (4, 8), (7, 8), (15, 21), (20, 23)]
    zarr_reads = {lo: np.asarray(packed[lo:hi]) for lo, hi in ranges}
    real = type(raw).__getitem__
    asked = []
    monkeypatch.setattr(type(raw), "__getitem__", lambda z, k: asked.append(z.path) or real(z, k))
    for lo, hi in ranges:
        np.testing.assert_array_equal(_stored_rows(raw, lo, hi), want[lo:hi])
        np.testing.assert_array_equal(_stored_rows(packed, lo, hi), zarr_reads[lo])
    assert "raw" not in asked and "packed" in asked


@pytest.mark.parametrize("compressed", [True, False])
def test_store_histograms_writes_every_chunk_without_comparing(tmp_path, compressed):
    # a chunk of zeros is stored too (Zarr does not compare each chunk with the fill
    # value first); the values read back are the ones written
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    data = np.zeros((10, 2, 1, 5), np.float32)  # one chunk, all zeros
    z = store_histograms(g, "h", data.shape, data=data, compressed=compressed)
    assert z.config.write_empty_chunks
    assert (tmp_path / "h.zarr" / "h" / "c.0.0.0.0").is_file()  # FLAT_CHUNK_KEYS
    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "h.zarr"))["h"][...], data)


def test_store_histograms_one_raw_chunk_written_as_its_file(tmp_path, monkeypatch):
    # candidates that fit one uncompressed chunk: written as the chunk file (not
    # through Zarr's write), read back the same, by Zarr and at rows
    import splidar.detection._table as table_mod

    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    data = np.random.default_rng(0).random((table_mod.HIST_CHUNK, 2, 1, 5)).astype(np.float32)
    written = []
    real = table_mod.write_raw_chunk
    monkeypatch.setattr(table_mod, "write_raw_chunk", lambda *a: written.append(a[1]) or real(*a))
    z = store_histograms(g, "h", data.shape, data=data, compressed=False)
    assert z.chunks[0] == len(data) and written == [(0, 0, 0, 0)]
    files = sorted(p.name for p in (tmp_path / "h.zarr" / "h").iterdir())
    assert files == ["c.0.0.0.0", "zarr.json"]
    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "h.zarr"))["h"][...], data)
    rows = np.array([len(data) - 1, 3, 2000])
    np.testing.assert_array_equal(zarr_take_rows(z, rows), data[rows])


def test_raw_rows_reads_any_rows_as_numpy_indexing(tmp_path):
    """Rows near together (one range read) and far apart (mapped at those rows), in any
    order with repeats, slices, booleans, ints: NumPy's indexing of the written array."""
    import pickle

    from splidar.detection._table import RawRows

    data = np.random.default_rng(1).random((5000, 2, 1, 7)).astype(np.float32)
    r = RawRows.write(tmp_path / "t.raw", data)
    assert (tmp_path / "t.raw").stat().st_size == data.nbytes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.raw"]  # no temporary left
    assert r.shape == data.shape and r.dtype == np.float32 and len(r) == 5000
    near = np.array([40, 12, 12, 39, 13])
    far = np.array([4999, 0, 2500, 0])  # 4 rows over 5000: mapped
    mask = np.zeros(5000, bool)
    mask[::7] = True
    for key in (near, far, mask, slice(10, 20), 4321, np.array([], np.int64)):
        np.testing.assert_array_equal(r[key], data[key])
    back = pickle.loads(pickle.dumps(r))  # a tile's handle travels to the caller
    np.testing.assert_array_equal(back[far], data[far])


def test_raw_rows_short_file_raises(tmp_path):
    from splidar.detection._table import RawRows

    data = np.ones((100, 3), np.float32)
    RawRows.write(tmp_path / "t.raw", data)
    short = RawRows(tmp_path / "t.raw", (200, 3), np.float32)
    with pytest.raises(OSError, match="values"):
        short[np.arange(150, 200)]


def test_compact_result_writes_a_tiles_histograms_as_one_raw_file(tmp_path):
    """A tile's candidate histograms: one file ``<row>_<col>.raw`` in the store's
    ``candidate_histograms`` folder (no Zarr array, no metadata files), read back the
    same at any rows."""
    from types import SimpleNamespace

    from splidar.detection import _tiled
    from splidar.detection._4_map import _open_store
    from splidar.detection._table import RawRows

    store = tmp_path / "det.zarr"
    _open_store(store, (8, 6, 20), 8)
    zarr.open_group(str(store), mode="r+").create_group("candidate_histograms")
    hist = np.random.default_rng(2).random((30, 2, 1, 9)).astype(np.float32)
    cols = dict(row=np.arange(30) % 8, col=np.arange(30) % 6, depth_bin=np.arange(30) % 20)
    res = SimpleNamespace(surf=cols, histograms=hist)
    _tiled._compact_result(res, str(store), (16, 24), (8, 6), 20)
    assert isinstance(res.histograms, RawRows)
    assert sorted(p.name for p in (store / "candidate_histograms").iterdir()) == [
        "16_24.raw", "zarr.json",
    ]  # fmt: skip
    rows = np.array([29, 0, 7, 7])
    np.testing.assert_array_equal(res.histograms[rows], hist[rows])


def test_remove_tree_removes_nested_folders(tmp_path):
    root = tmp_path / "store" / "candidate_histograms"
    for i in range(12):
        d = root / f"{i}_0" / "c" / "0" / "0"
        d.mkdir(parents=True)
        (d / "0").write_bytes(b"x" * 10)
        (root / f"{i}_0" / "zarr.json").write_text("{}")
    (root / "zarr.json").write_text("{}")
    remove_tree(root)
    assert not root.exists() and (tmp_path / "store").exists()
    remove_tree(root)  # nothing to remove: no error


def test_pixels_zarr_equals_vindex(tmp_path):
    """The alignment's pixels read from the Zarr array by chunk of rows equal Dask's
    ``vindex`` (irregular last chunk, repeated pixels, any order)."""
    from splidar.detection._depth_fields import _pixels, _pixels_by_chunk
    from splidar.detection._slopes import _zarr_of

    rng = np.random.default_rng(3)
    a = rng.integers(0, 4, (37, 11, 2, 25)).astype(np.uint8)
    z = zarr.open_array(
        tmp_path / "c.zarr", mode="w", shape=a.shape, chunks=(8, 11, 2, 25), dtype=a.dtype
    )
    z[:] = a
    x = da.from_zarr(tmp_path / "c.zarr")
    assert _zarr_of(x) is not None  # the direct path is the one tested
    rows = np.r_[rng.integers(0, 37, 60), 36, 0, 36]
    cols = np.r_[rng.integers(0, 11, 60), 10, 0, 10]
    got = _pixels(x, rows, cols)
    assert got.dtype == a.dtype
    np.testing.assert_array_equal(got, x.vindex[rows, cols].compute())
    np.testing.assert_array_equal(_pixels_by_chunk(z, x.chunks[0], rows, cols), a[rows, cols])


def _sparse_zarr(tmp_path, rng, rows):
    """A sparse uint8 cube ``(rows, 9, 2, 30)`` (5 % nonzero) written to Zarr in chunks
    of 8 rows: ``(array, its Dask array from the Zarr file)``."""
    shape = (rows, 9, 2, 30)
    a = ((rng.random(shape) < 0.05) * rng.integers(1, 200, shape)).astype(np.uint8)
    z = zarr.open_array(
        tmp_path / "c.zarr", mode="w", shape=a.shape, chunks=(8, 9, 2, 30), dtype=a.dtype
    )
    z[:] = a
    return a, da.from_zarr(tmp_path / "c.zarr")


@pytest.mark.parametrize("budget", [None, 0])
def test_kept_counts_reads_equal_the_zarr_array(tmp_path, monkeypatch, budget):
    """In ``kept_counts`` (detect's stages 5-7 on a Zarr cube) the bands and pixels come
    from the chunks' nonzero counts, decoded once; the same values as the array's, with
    chunks past the byte budget (``budget=0``: all of them after the first) decoded
    again; the chunks are released when the context ends."""
    from splidar.detection import _slopes
    from splidar.detection._depth_fields import _pixels

    if budget is not None:
        monkeypatch.setattr(_slopes, "SPARSE_BYTES", budget)
    rng = np.random.default_rng(5)
    a, x = _sparse_zarr(tmp_path, rng, 45)
    with _slopes.kept_counts(x):
        assert x.name in _slopes._KEPT
        for _ in range(2):  # the second pass from the kept chunks
            items = np.sort(rng.integers(0, 45, 40))
            got = [(sel, b.copy(), y0) for sel, b, y0 in _row_bands(x, items, 3, band=6)]
            for _sel, band, y0 in got:
                np.testing.assert_array_equal(band, a[y0 : y0 + band.shape[0]])
            assert sorted(s for sel, _, _ in got for s in sel) == list(range(items.size))
        rows, cols = rng.integers(0, 45, 50), rng.integers(0, 9, 50)
        np.testing.assert_array_equal(_pixels(x, rows, cols), a[rows, cols])
    assert x.name not in _slopes._KEPT


@pytest.mark.parametrize("budget", [None, 0, 900])
def test_kept_counts_threads_decode_every_chunk_ahead(tmp_path, monkeypatch, budget):
    """``kept_counts(threads=2)``: every chunk of rows is decoded ahead on two threads
    (each into its own buffer), in row order, within the byte budget; the bands and
    pixels read then are the array's (from the chunks decoded ahead: the Zarr array
    is not read again within the budget; past it, ``budget=0`` or a budget of a few
    chunks, the rest decoded at the read as before); the threads end with the context.
    Chunks larger than ``AHEAD_BYTES``: nothing decoded ahead."""
    from splidar.detection import _slopes
    from splidar.detection._depth_fields import _pixels

    if budget is not None:
        monkeypatch.setattr(_slopes, "SPARSE_BYTES", budget)
    rng = np.random.default_rng(11)
    a, x = _sparse_zarr(tmp_path, rng, 61)
    with _slopes.kept_counts(x, threads=2):
        sp = _slopes._KEPT[x.name]
        assert sorted(sp.ahead) == list(range(8))  # every chunk, in row order
        done = [sp.ahead[k].result() for k in range(8)]
        if budget is None:  # every chunk decoded ahead, on the two threads' buffers
            assert all(d is not None for d in done) and 1 <= len(sp.bufs) <= 2
            reads = []
            monkeypatch.setattr(sp, "_decode", lambda k, buf=None: reads.append(k))
        else:
            assert done[-1] is None  # past the budget: not decoded ahead
        for _ in range(2):
            items = np.sort(rng.integers(0, 61, 40))
            got = [(sel, b.copy(), y0) for sel, b, y0 in _row_bands(x, items, 3, band=6)]
            for _sel, band, y0 in got:
                np.testing.assert_array_equal(band, a[y0 : y0 + band.shape[0]])
        rows, cols = rng.integers(0, 61, 50), rng.integers(0, 9, 50)
        np.testing.assert_array_equal(_pixels(x, rows, cols), a[rows, cols])
        if budget is None:
            assert reads == [] and not sp.ahead  # all taken from the chunks decoded ahead
    assert x.name not in _slopes._KEPT and sp.pool is None and not sp.bufs
    monkeypatch.setattr(_slopes, "AHEAD_BYTES", 8 * 9 * 2 * 30 - 1)  # under one chunk
    with _slopes.kept_counts(x, threads=2):
        sp = _slopes._KEPT[x.name]
        assert sp.pool is None and not sp.ahead  # nothing ahead: read as before
        np.testing.assert_array_equal(_pixels(x, rows, cols), a[rows, cols])


@pytest.mark.parametrize("budget", [None, 0])
def test_row_bands_kept_cube_writes_the_items_pixels_only(tmp_path, monkeypatch, budget):
    """``_row_bands(..., cols=)`` on a Zarr cube kept sparse: each band holds the
    array's counts at every pixel within ``halo`` of an item (rows and columns) and
    0 at the others, also when its buffer held another band's counts before (three
    passes, items drawn anew, bands of the same buffers); past the byte budget
    (``budget=0``) whole chunks are copied (the values only more complete). Without
    ``cols`` and in memory, every pixel holds its counts."""
    from splidar.detection import _slopes

    if budget is not None:
        monkeypatch.setattr(_slopes, "SPARSE_BYTES", budget)
    rng = np.random.default_rng(9)
    R, C, h = 45, 23, 2
    a = (rng.random((R, C, 1, 30)) < 0.2) * rng.integers(1, 200, (R, C, 1, 30))
    a = a.astype(np.uint8)
    z = zarr.open_array(
        tmp_path / "c.zarr", mode="w", shape=a.shape, chunks=(8, C, 1, 30), dtype=a.dtype
    )
    z[:] = a
    x = da.from_zarr(tmp_path / "c.zarr")
    with _slopes.kept_counts(x):
        for n in (60, 3, 25):
            rows, cols = rng.integers(0, R, n), rng.integers(0, C, n)
            seen = []
            for sel, band, y0 in _row_bands(x, rows, h, band=6, cols=cols):
                near = np.zeros((R + 2 * h, C + 2 * h), bool)  # the band's items' pixels
                for r, c in zip(rows[sel], cols[sel], strict=True):
                    near[r : r + 2 * h + 1, c : c + 2 * h + 1] = True
                want = a[y0 : y0 + band.shape[0]]
                m = near[h:-h, h:-h][y0 : y0 + band.shape[0]]
                np.testing.assert_array_equal(band[m], want[m])
                if budget is None:  # the pixels no item reads: 0
                    assert not band[~m].any() and want[~m].any()
                seen.extend(sel)
            assert sorted(seen) == list(range(n))
        full = [(b.copy(), y0) for _, b, y0 in _row_bands(x, rows, h, band=6)]
        for band, y0 in full:
            np.testing.assert_array_equal(band, a[y0 : y0 + band.shape[0]])
    for _, band, y0 in _row_bands(a, rows, h, cols=cols):
        assert band is a and y0 == 0


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.float64])
def test_nonzero_equals_flatnonzero(dtype):
    from splidar.detection._slopes import _nonzero

    rng = np.random.default_rng(6)
    a = ((rng.random(10_007) < 0.02) * rng.integers(1, 9, 10_007)).astype(dtype)
    for x in (a, a[:-7], a[1:], np.zeros(16, dtype)):  # ragged ends, unaligned, none
        idx, val = _nonzero(x)
        np.testing.assert_array_equal(idx, np.flatnonzero(x))
        np.testing.assert_array_equal(val, x[np.flatnonzero(x)])


@pytest.mark.parametrize("budget", [None, 0])
def test_sparse_windows_equal_the_zarr_arrays_windows(tmp_path, monkeypatch, budget):
    """``_Sparse.windows`` (stage 7b's likelihoods on a kept Zarr cube) gives each
    pixel's counts over its own window of bins, the array's values, from the kept
    nonzero counts or (``budget=0``) from chunks decoded again; ``pixels`` the whole
    series (window 0 to T); no pixel, no error."""
    from splidar.detection import _slopes

    if budget is not None:
        monkeypatch.setattr(_slopes, "SPARSE_BYTES", budget)
    rng = np.random.default_rng(7)
    a = (rng.random((45, 9, 2, 30)) < 0.1) * rng.integers(1, 200, (45, 9, 2, 30))
    a = a.astype(np.uint8)
    z = zarr.open_array(
        tmp_path / "c.zarr", mode="w", shape=a.shape, chunks=(8, 9, 2, 30), dtype=a.dtype
    )
    z[:] = a
    sp = _slopes._Sparse(z)
    rows, cols = np.r_[rng.integers(0, 45, 80), 44, 0], np.r_[rng.integers(0, 9, 80), 8, 0]
    for W in (1, 7, 30):
        lo = rng.integers(0, 30 - W + 1, rows.size)
        got = sp.windows(rows, cols, lo, W)
        assert got.dtype == a.dtype and got.shape == (rows.size, 2, W)
        want = np.stack([a[r, c, :, t : t + W] for r, c, t in zip(rows, cols, lo, strict=True)])
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(sp.pixels(rows, cols), a[rows, cols])
    assert sp.windows(rows[:0], cols[:0], rows[:0], 5).shape == (0, 2, 5)


def test_likelihoods_kept_zarr_cube_reads_the_windows_only(tmp_path, monkeypatch):
    """Stage 7b's likelihoods on a Zarr cube kept sparse (detect's stages 5-7) read each
    depth's window from the kept counts, never a pixel's whole series, and equal the
    in-memory cube's bit for bit."""
    from splidar.detection import _7b_edge_bands, _slopes
    from splidar.detection._result import Background

    rng = np.random.default_rng(8)
    R, C, L, T = 20, 12, 1, 60
    a = rng.poisson(0.05, (R, C, L, T)).astype(np.uint8)
    a[:, :, 0, 20:24] += rng.poisson(2.0, (R, C, 4)).astype(np.uint8)
    z = zarr.open_array(
        tmp_path / "c.zarr", mode="w", shape=a.shape, chunks=(8, C, L, T), dtype=a.dtype
    )
    z[:] = a
    x = da.from_zarr(tmp_path / "c.zarr")
    bg = Background(
        spatial=rng.uniform(0.01, 0.1, (R, C, L)).astype(np.float32),
        temporal=np.full((L, T), 0.05, np.float32),
    )
    irf = np.exp(-0.5 * ((np.arange(9) - 4) / 1.2) ** 2)[None]
    rows, cols = rng.integers(0, R, 50), rng.integers(0, C, 50)
    dep = np.stack([rng.uniform(0, T - 1, 50), rng.uniform(15, 25, 50)], 1)
    want = _7b_edge_bands._likelihoods(a, bg, rows, cols, dep, irf)

    def whole(*args):
        raise AssertionError("a pixel's whole series read")

    monkeypatch.setattr(_7b_edge_bands, "_pixels", whole)
    with _slopes.kept_counts(x):
        got = _7b_edge_bands._likelihoods(x, bg, rows, cols, dep, irf, n_jobs=2)
    np.testing.assert_array_equal(got, want)


def test_write_rows_writes_each_chunk_once(tmp_path, monkeypatch):
    """The moved surfaces' histograms written into the store (stages 7 / 7b with
    ``store=``): each chunk holding some of the rows written once (a write per row
    decoded and encoded its chunk each time), the values those of single writes in
    order (a repeated row keeps its last value)."""
    from splidar.detection import _table

    monkeypatch.setattr(_table, "HIST_CHUNK", 8)
    rng = np.random.default_rng(9)
    base = rng.random((40, 2, 1, 5)).astype(np.float32)
    idx = np.array([33, 2, 5, 17, 2, 39, 6, 18])  # row 2 twice; chunks 0, 2, 4
    values = rng.random((idx.size, 2, 1, 5)).astype(np.float32)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    z = _table.store_histograms(g, "h", base.shape, data=base)
    store = z.store_path.store
    written = []
    real = type(store).set

    async def counted(self, key, value, *a, **k):
        written.append(key)
        return await real(self, key, value, *a, **k)

    monkeypatch.setattr(type(store), "set", counted)
    _table.write_rows(z, idx, values)
    want = base.copy()
    for i, v in zip(idx, values, strict=True):
        want[i] = v
    np.testing.assert_array_equal(z[...], want)
    assert sorted(written) == sorted(set(written)) and len(written) == 3
    _table.write_rows(z, idx[:0], values[:0])  # nothing to write: no error
    assert len(written) == 3


def test_select_and_align_removes_candidate_histograms_while_stage_7_runs(tmp_path, monkeypatch):
    """With ``store=``, the tiles' candidate histograms are removed on a thread while
    stage 7 runs (the removal sees stage 7 start), and are gone when ``detect`` returns;
    the surfaces are the ones without a store."""
    import threading

    from splidar.detection import _detect, detect
    from splidar.scenes import single_surface_scene

    cube = single_surface_scene((24, 24), n_bins=120).simulate(ppp=4, sbr=0.5, rng=1).cube
    placing, saw = threading.Event(), []
    real_remove, real_place = _detect.remove_tree, _detect.place_depths

    def remove(path):
        saw.append(placing.wait(5.0))
        real_remove(path)

    def place(*a, **k):
        placing.set()
        return real_place(*a, **k)

    monkeypatch.setattr(_detect, "remove_tree", remove)
    monkeypatch.setattr(_detect, "place_depths", place)
    got = detect(cube, rng=0, store=tmp_path / "det.zarr")
    assert saw == [True] and not (tmp_path / "det.zarr" / "candidate_histograms").exists()
    want = detect(cube, rng=0)
    np.testing.assert_array_equal(got.surfaces.depth_bin, want.surfaces.depth_bin)
    np.testing.assert_array_equal(got.surfaces.row, want.surfaces.row)


def test_remove_logged_warns_when_the_scratch_cannot_be_removed(tmp_path, monkeypatch, caplog):
    """A failing removal of the candidates' scratch histograms (on the remover thread)
    is a logged warning naming the folder, not an exception escaping the thread; the
    detection is the one without a store."""
    import logging
    import threading

    from splidar.detection import _detect, detect
    from splidar.scenes import single_surface_scene

    cube = single_surface_scene((16, 16), n_bins=120).simulate(ppp=4, sbr=0.5, rng=1).cube

    def refuse(path):
        raise PermissionError(13, "Permission denied", str(path))

    hooked = []
    monkeypatch.setattr(_detect, "remove_tree", refuse)
    monkeypatch.setattr(threading, "excepthook", lambda args: hooked.append(args))
    with caplog.at_level(logging.WARNING, logger="splidar.detection._detect"):
        got = detect(cube, rng=0, store=tmp_path / "det.zarr")
    assert not hooked
    assert any("candidate_histograms" in r.getMessage() for r in caplog.records)
    want = detect(cube, rng=0)
    np.testing.assert_array_equal(got.surfaces.depth_bin, want.surfaces.depth_bin)


def _rows_array(tmp_path, name, d, chunk=4, compressors=None):
    g = zarr.open_group(str(tmp_path / f"{name}.zarr"), mode="w")
    z = g.create_array(
        "h", shape=d.shape, chunks=(chunk,) + d.shape[1:], dtype="f4", compressors=compressors
    )
    z[...] = d
    return z


def test_zarr_write_rows_equals_zarrs_write_bit_for_bit(tmp_path, monkeypatch):
    """``zarr_write_rows``: a raw array in chunks of whole rows gets the rows written in
    its chunk files (Zarr's setter not asked), the array then reading as after Zarr's own
    write (an edge chunk, float64 values cast, -0.0 and NaN kept); a compressed array, a
    chunk file missing or not one chunk's bytes: False and nothing written."""
    from splidar._arrays import zarr_write_rows

    rng = np.random.default_rng(11)
    d = rng.normal(size=(23, 2, 1, 5)).astype(np.float32)  # chunks of 4: an edge chunk of 3
    idx = np.array([22, 0, 5, 6, 13, 21])
    values = rng.normal(size=(idx.size, 2, 1, 5))  # float64: cast as Zarr casts
    values[1, 0, 0, :2] = (-0.0, np.nan)
    want = _rows_array(tmp_path, "want", d)
    want.set_orthogonal_selection((idx,), values)
    z = _rows_array(tmp_path, "got", d)
    monkeypatch.setattr(type(z), "set_orthogonal_selection", _fails)
    monkeypatch.setattr(type(z), "__setitem__", _fails)
    assert zarr_write_rows(z, idx, values)
    a, b = np.asarray(z[...]), np.asarray(want[...])
    assert a.tobytes() == b.tobytes()
    assert zarr_write_rows(z, idx[:0], values[:0])  # nothing to write
    monkeypatch.undo()
    packed = _rows_array(tmp_path, "packed", d, compressors="auto")
    assert not zarr_write_rows(packed, idx, values)
    np.testing.assert_array_equal(packed[...], d)
    z = _rows_array(tmp_path, "cut", d)
    path = tmp_path / "cut.zarr" / "h" / "c" / "5" / "0" / "0" / "0"  # rows 20-23
    path.write_bytes(path.read_bytes()[:-4])
    assert not zarr_write_rows(z, idx, values)
    np.testing.assert_array_equal(z[:20], d[:20])  # the chunks checked first: none written
    path.unlink()
    assert not zarr_write_rows(z, idx, values)
    z = _rows_array(tmp_path, "nomap", d)  # a file system that cannot map for writing

    def no_map(*a, **k):
        raise OSError("no mmap")

    monkeypatch.setattr(np, "memmap", no_map)
    assert not zarr_write_rows(z, idx, values)


def test_write_rows_raw_store_equals_compressed_store(tmp_path, monkeypatch):
    """``write_rows`` into ``store_histograms(compressed=False)`` (a detection's surfaces)
    writes in the chunk files, not through Zarr; the values read back are the ones the
    lz4 array gets through Zarr (a repeated row keeps its last value)."""
    from splidar.detection import _table

    monkeypatch.setattr(_table, "HIST_CHUNK", 8)
    rng = np.random.default_rng(12)
    base = rng.random((40, 2, 1, 5)).astype(np.float32)
    idx = np.array([33, 2, 5, 17, 2, 39, 6, 18])
    values = rng.random((idx.size, 2, 1, 5)).astype(np.float32)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    packed = _table.store_histograms(g, "packed", base.shape, data=base)
    raw = _table.store_histograms(g, "raw", base.shape, data=base, compressed=False)
    _table.write_rows(packed, idx, values)
    monkeypatch.setattr(type(raw), "set_orthogonal_selection", _fails)
    _table.write_rows(raw, idx, values)
    assert np.asarray(raw[...]).tobytes() == np.asarray(packed[...]).tobytes()


def _sparse_histograms(seed: int, shape: tuple) -> np.ndarray:
    """Random float32 histograms of ``shape``, 30 % of their values 0 (as a stored
    candidate's outside its support)."""
    rng = np.random.default_rng(seed)
    return (rng.gamma(0.5, 3.0, shape) * (rng.random(shape) < 0.7)).astype("f4")


@pytest.mark.parametrize("compressed", [True, False])
def test_finest_sums_stored_equals_in_memory_bit_for_bit(tmp_path, monkeypatch, compressed):
    """``_finest_sums`` of stored histograms (read by rows, several parts) equals the
    in-memory array's, bit for bit (two wavelengths: the sum over them); a raw array is
    read from its chunk files (Zarr not asked)."""
    from splidar.detection import _7a_align_depths
    from splidar.detection._result import StoredHistograms

    h = _sparse_histograms(13, (50, 3, 2, 7))
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    z = store_histograms(g, "h", h.shape, data=h, compressed=compressed)
    want = _7a_align_depths._finest_sums(h)
    monkeypatch.setattr(_7a_align_depths, "FINEST_PART_BYTES", 4 * 4 * 42)  # 4 rows a part
    if not compressed:
        monkeypatch.setattr(type(z), "__getitem__", _fails)
    got = _7a_align_depths._finest_sums(StoredHistograms(z))
    assert got.dtype == np.float64 and got.tobytes() == want.tobytes()


def test_finest_sums_same_on_any_number_of_threads(tmp_path, monkeypatch):
    """``_finest_sums``' parts on threads (in memory and stored raw): each part fills its
    own rows, the same bytes as on one thread."""
    from splidar.detection import _7a_align_depths
    from splidar.detection._result import StoredHistograms

    h = _sparse_histograms(14, (61, 3, 2, 7))
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    z = store_histograms(g, "h", h.shape, data=h, compressed=False)
    want = _7a_align_depths._finest_sums(h)
    monkeypatch.setattr(_7a_align_depths, "FINEST_PART_BYTES", 4 * 4 * 42)  # 4 rows a part
    for src in (h, StoredHistograms(z)):
        for n_jobs in (1, 2, 5):
            got = _7a_align_depths._finest_sums(src, n_jobs)
            assert got.tobytes() == want.tobytes()


def test_detect_store_writes_stage_7s_moves_in_the_raw_chunk_files(tmp_path, monkeypatch):
    """``detect(store=)``: the surfaces' histograms stored raw, stage 7's moved surfaces'
    rows written in the chunk files (``zarr_write_rows`` wrote every call's rows: no write
    through Zarr), the histograms read back equal the in-memory run's bit for bit."""
    from zarr.codecs import BytesCodec

    from splidar.detection import _table, detect
    from splidar.scenes import single_surface_scene

    cube = single_surface_scene((24, 24), n_bins=120).simulate(ppp=4, sbr=0.5, rng=1).cube
    want = detect(cube, rng=0)
    wrote, real = [], _table.zarr_write_rows
    monkeypatch.setattr(_table, "zarr_write_rows", lambda *a: wrote.append(real(*a)) or wrote[-1])
    got = detect(cube, rng=0, store=tmp_path / "det.zarr")
    z = got.surfaces.histograms.array
    assert [type(c) for c in z.metadata.codecs] == [BytesCodec]
    assert wrote and all(wrote)
    h = np.asarray(got.surfaces.histograms)
    assert h.tobytes() == want.surfaces.histograms.tobytes()
    np.testing.assert_array_equal(got.surfaces.depth_bin, want.surfaces.depth_bin)


def test_zarr_take_rows_equals_zarrs_read(tmp_path, monkeypatch):
    """``zarr_take_rows``: rows of a raw array in chunks of whole rows read from its
    chunk files (Zarr not asked; unsorted, repeated, in the edge chunk, in a chunk never
    written: the fill value), the same values as Zarr's; a compressed array or a chunk
    file that is not one chunk's bytes: None."""
    from splidar._arrays import zarr_take_rows

    rng = np.random.default_rng(14)
    d = rng.normal(size=(23, 2, 1, 5)).astype(np.float32)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    z = g.create_array("h", shape=d.shape, chunks=(4, 2, 1, 5), dtype="f4", compressors=None)
    z[4:] = d[4:]  # rows 0-3: never written (the fill value, 0)
    rows = np.array([22, 5, 1, 5, 17, 0, 21, 9])
    want = np.asarray(z.get_orthogonal_selection((rows,)))
    assert np.array_equal(want[2:4], np.stack([np.zeros_like(d[0]), d[5]]))
    monkeypatch.setattr(type(z), "__getitem__", _fails)
    monkeypatch.setattr(type(z), "get_orthogonal_selection", _fails)
    got = zarr_take_rows(z, rows)
    assert got.dtype == np.float32 and got.tobytes() == want.tobytes()
    assert zarr_take_rows(z, rows[:0]).shape == (0, 2, 1, 5)
    monkeypatch.undo()
    packed = g.create_array("p", shape=d.shape, chunks=(4, 2, 1, 5), dtype="f4")
    assert zarr_take_rows(packed, rows) is None
    path = tmp_path / "h.zarr" / "h" / "c" / "4" / "0" / "0" / "0"
    path.write_bytes(path.read_bytes()[:-4])
    assert zarr_take_rows(z, rows) is None


def test_read_part_reads_rows_far_apart_at_those_rows(tmp_path, monkeypatch):
    """``_gather`` (the recentring's moved candidates): a raw block's rows far apart are
    read at those rows (``zarr_take_rows``), rows close together as the slice from the
    first to the last (``_stored_rows``); the same histograms as from memory."""
    from splidar.detection import _6_select

    rng = np.random.default_rng(15)
    g = zarr.open_group(str(tmp_path / "h.zarr"), mode="w")
    blocks = [rng.normal(size=(n, 2, 1, 5)).astype(np.float32) for n in (200, 40)]
    stored = [
        store_histograms(g, str(i), b.shape, data=b, compressed=False)
        for i, b in enumerate(blocks)
    ]  # fmt: skip
    hb = np.array([0] * 200 + [1] * 40)
    hr = np.concatenate([np.arange(200), np.arange(40)])
    table = CandidateTable(
        columns={"row": np.arange(hb.size)}, keep=np.ones(hb.size, bool),
        origin=np.zeros(hb.size, np.int8), hist_block=hb, hist_row=hr,
        image_shape=(hb.size, 1),
    )  # fmt: skip
    idx = np.array([3, 190, 77, 200, 230, 215, 239])  # block 0: 3 rows in 188; block 1: 4 in 40
    took, sliced = [], []
    real_take, real_rows = _6_select.zarr_take_rows, _6_select._stored_rows
    monkeypatch.setattr(
        _6_select, "zarr_take_rows", lambda z, r: took.append(z.path) or real_take(z, r)
    )
    monkeypatch.setattr(
        _6_select, "_stored_rows", lambda z, a, b: sliced.append(z.path) or real_rows(z, a, b)
    )
    got = _gather(table, idx, tuple(stored))
    assert got.tobytes() == _gather(table, idx, tuple(blocks)).tobytes()
    assert took == ["0"] and sliced == ["1"]


def _f32_raw_array(tmp_path, name, shape, chunks):
    g = zarr.open_group(str(tmp_path / f"{name}.zarr"), mode="w")
    return g.create_array(name, shape=shape, chunks=chunks, dtype="float32", compressors=None)


def test_write_raw_chunk_direct_writes_the_same_bytes_as_zarr(tmp_path):
    """``write_raw_chunk`` on a chunk of >= ``DIRECT_MIN_BYTES`` whose size is no
    multiple of the page: the aligned head past the page cache (``O_DIRECT``, where the
    file system takes it), the tail written after; Zarr reads back exactly what its own
    write stores (-0.0 and NaN kept), and the next chunk reuses the thread's buffer."""
    from splidar import _arrays

    chunk = (3, 7, 12_487)  # 1,048,908 bytes: 256 pages and a 332-byte tail
    assert 4 * np.prod(chunk) >= _arrays.DIRECT_MIN_BYTES
    assert (4 * np.prod(chunk)) % _arrays._ALIGN
    rng = np.random.default_rng(3)
    d = rng.normal(size=(6, 7, chunk[2])).astype(np.float32)
    d[0, 0, :2] = (-0.0, np.nan)
    want = _f32_raw_array(tmp_path, "want", d.shape, chunk)
    want[...] = d
    got = _f32_raw_array(tmp_path, "got", d.shape, chunk)
    raw = _arrays._raw_chunks(got)
    for i in (0, 1):
        _arrays.write_raw_chunk(raw, (i, 0, 0), d[3 * i : 3 * i + 3])
    assert np.asarray(got[...]).tobytes() == np.asarray(want[...]).tobytes()
    names = sorted(p.name for p in (tmp_path / "got.zarr" / "got" / "c").rglob("*"))
    assert not [n for n in names if n.endswith(".partial")]  # no temporary file left
    if getattr(_arrays.os, "O_DIRECT", 0) and tmp_path.stat().st_dev not in _arrays._NO_DIRECT:
        buf = _arrays._DIRECT_BUFFERS.buf
        assert buf.ctypes.data % _arrays._ALIGN == 0
        assert buf.size >= 4 * np.prod(chunk) // _arrays._ALIGN * _arrays._ALIGN


def test_write_direct_declines_small_files_and_refusing_file_systems(tmp_path, monkeypatch):
    """``_write_direct``: False (and no file) for a file under ``DIRECT_MIN_BYTES`` or with
    ``SPLIDAR_DIRECT_IO=0``; a file system refusing ``O_DIRECT`` at the open (EINVAL) is
    remembered and not asked again, and ``write_raw_chunk`` then writes the chunk the
    usual way, the same bytes."""
    import errno
    import os

    from splidar import _arrays

    small = memoryview(np.zeros(1000, np.float32)).cast("B")
    assert not _arrays._write_direct(tmp_path / "small.partial", small)
    assert not (tmp_path / "small.partial").exists()
    big = memoryview(np.arange(300_000, dtype=np.float32)).cast("B")
    monkeypatch.setenv("SPLIDAR_DIRECT_IO", "0")  # turned off by the user
    assert not _arrays._write_direct(tmp_path / "off.partial", big)
    assert not (tmp_path / "off.partial").exists()
    monkeypatch.delenv("SPLIDAR_DIRECT_IO")
    opened = []
    real_open = os.open

    def refuse(path, flags, *a, **k):
        if flags & getattr(os, "O_DIRECT", 0):
            opened.append(path)
            raise OSError(errno.EINVAL, "O_DIRECT refused")
        return real_open(path, flags, *a, **k)

    monkeypatch.setattr(_arrays.os, "open", refuse)
    monkeypatch.setattr(_arrays, "_NO_DIRECT", set())
    if not getattr(os, "O_DIRECT", 0):
        pytest.skip("no O_DIRECT on this platform")
    assert not _arrays._write_direct(tmp_path / "a.partial", big)
    assert not _arrays._write_direct(tmp_path / "b.partial", big)
    assert len(opened) == 1  # the refusal remembered for the device
    assert not list(tmp_path.glob("*.partial"))
    d = np.arange(2 * 300_000, dtype=np.float32).reshape(2, 1, 300_000)
    got = _f32_raw_array(tmp_path, "got", d.shape, (1, 1, 300_000))
    raw = _arrays._raw_chunks(got)
    for i in (0, 1):
        _arrays.write_raw_chunk(raw, (i, 0, 0), d[i : i + 1])
    assert len(opened) == 1
    monkeypatch.undo()
    np.testing.assert_array_equal(got[...], d)


def test_prefetch_advises_runs_of_consecutive_pages(tmp_path, monkeypatch):
    """``_prefetch``: one ``POSIX_FADV_WILLNEED`` per run of consecutive pages holding the
    offsets (repeats and unsorted offsets merged); a missing file or no offsets: no call."""
    import os

    from splidar import _arrays

    if not hasattr(os, "posix_fadvise"):
        pytest.skip("no posix_fadvise on this platform")
    path = tmp_path / "f"
    path.write_bytes(bytes(10 * 4096))
    calls = []
    monkeypatch.setattr(
        _arrays.os, "posix_fadvise", lambda fd, off, n, advice: calls.append((off, n, advice))
    )
    offsets = np.array([5 * 4096 + 7, 0, 4095, 4096, 9 * 4096, 5 * 4096, 6 * 4096 + 1])
    _arrays._prefetch(path, offsets)
    need = os.POSIX_FADV_WILLNEED
    assert calls == [(0, 2 * 4096, need), (5 * 4096, 2 * 4096, need), (9 * 4096, 4096, need)]
    calls.clear()
    _arrays._prefetch(tmp_path / "missing", offsets)
    _arrays._prefetch(path, offsets[:0])
    assert calls == []


def test_zarr_rows_into_decodes_zstd_chunks_from_their_files_as_zarr(tmp_path, monkeypatch):
    """``zarr_rows_into``: a whole chunk of whole rows of a zstd-compressed Zarr 3 array
    decoded from its chunk file into the output (Zarr not asked; a chunk never written:
    the fill value), the same bytes as Zarr's read; part of a chunk, the edge chunk, or
    a chunk file whose frame does not hold one chunk's bytes: Zarr's read."""
    from numcodecs import Zstd

    from splidar._arrays import _zstd_chunk_into, zarr_rows_into

    rng = np.random.default_rng(16)
    d = rng.integers(0, 3000, (70, 5, 1, 9)).astype(np.uint16)
    g = zarr.open_group(str(tmp_path / "c.zarr"), mode="w")
    z = g.create_array("counts", shape=d.shape, chunks=(16, 5, 1, 9), dtype="u2", fill_value=7)
    z[:16], z[32:] = d[:16], d[32:]  # rows 16-31: never written (the fill value)
    want = np.asarray(z[:])
    assert np.all(want[16:32] == 7) and np.array_equal(want[32:], d[32:])
    out = np.full((16, 5, 1, 9), 1, np.uint16)
    with monkeypatch.context() as m:
        m.setattr(type(z), "get_basic_selection", _fails)
        m.setattr(type(z), "__getitem__", _fails)
        for lo in (0, 16, 32, 48):
            assert zarr_rows_into(z, lo, lo + 16, out) is out
            assert out.tobytes() == want[lo : lo + 16].tobytes()
    for lo, hi in ((64, 70), (3, 9), (8, 24)):  # the edge chunk, parts of chunks: Zarr's
        assert not _zstd_chunk_into(z, lo, hi, out[: hi - lo])
        assert zarr_rows_into(z, lo, hi, out[: hi - lo]).tobytes() == want[lo:hi].tobytes()
    # a frame of another size in chunk 3's file: left to Zarr (which then refuses it)
    path = tmp_path / "c.zarr" / "counts" / "c" / "3" / "0" / "0" / "0"
    path.write_bytes(Zstd().encode(d[48:63].tobytes()))
    assert not _zstd_chunk_into(z, 48, 64, out)
    with pytest.raises(Exception):  # noqa: B017 (whatever Zarr raises)
        zarr_rows_into(z, 48, 64, out)


def test_zstd_chunks_only_for_bytes_then_zstd_in_native_order(tmp_path):
    """``_zstd_chunks``: the chunk files' layout of a ``bytes`` + ``zstd`` array only (a raw,
    gzip, big-endian or sharded array: None, read by Zarr)."""
    from zarr.codecs import BytesCodec, GzipCodec

    from splidar._arrays import _raw_chunks, _zstd_chunks

    g = zarr.open_group(str(tmp_path / "k.zarr"), mode="w")
    kw = {"shape": (8, 3), "chunks": (4, 3), "dtype": "u2"}
    assert _zstd_chunks(g.create_array("zstd", **kw))[1] == (4, 3)
    assert _raw_chunks(g.create_array("zstd2", **kw)) is None
    assert _zstd_chunks(g.create_array("raw", compressors=None, **kw)) is None
    assert _raw_chunks(g.create_array("raw2", compressors=None, **kw)) is not None
    assert _zstd_chunks(g.create_array("gzip", compressors=GzipCodec(), **kw)) is None
    big = g.create_array("big", serializer=BytesCodec(endian="big"), **kw)
    assert _zstd_chunks(big) is None
    assert _zstd_chunks(g.create_array("shard", shards=(8, 3), **kw)) is None


@pytest.mark.parametrize("size", [0, 1, 255, 256, 300, 65791, 65792, 1 << 20])
def test_zstd_frame_size_reads_the_declared_content_size(size):
    """``_zstd_frame_size``: the content size numcodecs' frames declare, whatever the
    size field's width (1, 2 with its offset of 256, 4 bytes) and with a checksum;
    None for bytes that are no zstd frame."""
    from numcodecs import Zstd

    from splidar._arrays import _zstd_frame_size

    data = np.random.default_rng(size).integers(0, 4, size).astype(np.uint8).tobytes()
    for codec in (Zstd(), Zstd(level=3, checksum=True)):
        assert _zstd_frame_size(codec.encode(data)) == size
    assert _zstd_frame_size(b"\x00" * 16) is None
    assert _zstd_frame_size(Zstd().encode(data)[:5]) is None


def test_read_band_decodes_partial_chunks_whole_into_a_kept_buffer(tmp_path, monkeypatch):
    """``_tiled._read_band``: rows ``[e0, e1)`` starting and ending inside chunks of a
    zstd Zarr cube read as Zarr reads them, every chunk decoded whole from its file (the
    band's partial chunks into the thread's kept chunk buffer, Zarr's reader not asked),
    the same kept buffers on the next band; the array's edge chunk read by Zarr."""
    from splidar.detection import _tiled

    rng = np.random.default_rng(5)
    d = rng.integers(0, 9, (75, 6, 1, 11)).astype(np.uint8)
    g = zarr.open_group(str(tmp_path / "c.zarr"), mode="w")
    z = g.create_array("counts", shape=d.shape, chunks=(16, 6, 1, 11), dtype="u1")
    z[...] = d
    _tiled.release_work()
    with monkeypatch.context() as m:
        m.setattr(type(z), "get_basic_selection", _fails)
        m.setattr(type(z), "__getitem__", _fails)
        y = _tiled._read_band(z, 5, 37, 40)  # parts of chunks 0 and 2, chunk 1 whole
        assert y.tobytes() == d[5:37].tobytes()
        kept = {k[0]: v for k, v in _tiled._WORK.items()}
        assert set(kept) == {"band", "chunk"}
        y = _tiled._read_band(z, 20, 60, 40)
        assert y.tobytes() == d[20:60].tobytes()
        assert all(_tiled._WORK[k] is kept[k[0]] for k in _tiled._WORK)
    assert _tiled._read_band(z, 50, 75, 40).tobytes() == d[50:75].tobytes()  # edge: Zarr
    _tiled.release_work()


def test_deferred_chunk_writes_leave_every_file_in_place_at_the_blocks_end(tmp_path):
    """``deferred_chunk_writes``: ``write_raw_chunk`` returns once the chunk is copied
    (the caller may overwrite its array at once); at the block's end every chunk file is
    in place, read back by Zarr as written, no temporary file left, and the thread keeps
    its ``depth`` aligned buffers for the next block."""
    from splidar import _arrays

    chunk = (2, 3, 50_000)  # 1.2 MB: past the page cache where the file system allows
    got = _f32_raw_array(tmp_path, "got", (8, 3, chunk[2]), chunk)
    raw = _arrays._raw_chunks(got)
    rng = np.random.default_rng(8)
    want = rng.normal(size=(8, 3, chunk[2])).astype(np.float32)
    value = np.empty(chunk, np.float32)
    with _arrays.deferred_chunk_writes(depth=2):
        for i in range(4):
            value[...] = want[2 * i : 2 * i + 2]  # the same array, overwritten each time
            _arrays.write_raw_chunk(raw, (i, 0, 0), value)
    assert np.asarray(got[...]).tobytes() == want.tobytes()
    assert not list((tmp_path / "got.zarr").rglob("*.partial"))
    if _arrays._direct_possible(tmp_path / "x", value.nbytes):
        bufs = _arrays._DEFERRED.buffers
        assert len(bufs) == 2 and all(b.ctypes.data % _arrays._ALIGN == 0 for b in bufs)


def test_deferred_chunk_writes_raise_a_writers_error_at_the_end(tmp_path, monkeypatch):
    """A write that fails on the writer thread: its temporary file removed, the error
    raised when the block ends (after the other writes have ended)."""
    from splidar import _arrays

    chunk = (1, 1, 300_000)
    got = _f32_raw_array(tmp_path, "got", (3, 1, chunk[2]), chunk)
    raw = _arrays._raw_chunks(got)
    if not _arrays._direct_possible(tmp_path / "x", 4 * chunk[2]):
        pytest.skip("no direct writes here: nothing deferred")
    real = _arrays.os.replace

    def fail_second(src, dst):
        if str(dst).endswith("/1/0/0"):
            raise OSError("disk full")
        return real(src, dst)

    monkeypatch.setattr(_arrays.os, "replace", fail_second)
    value = np.ones(chunk, np.float32)
    with pytest.raises(OSError, match="disk full"):
        with _arrays.deferred_chunk_writes():
            for i in range(3):
                _arrays.write_raw_chunk(raw, (i, 0, 0), value)
    monkeypatch.undo()
    assert not list((tmp_path / "got.zarr").rglob("*.partial"))
    np.testing.assert_array_equal(got[0], value[0])
    np.testing.assert_array_equal(got[2], value[0])


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork on this platform")
def test_deferred_chunk_writes_work_in_a_forked_child(tmp_path):
    """A process forked after the writer thread was made gets its own (the parent's
    thread does not exist in the child): its deferred writes finish, not hang."""
    import os

    from splidar import _arrays

    chunk = (1, 1, 300_000)
    got = _f32_raw_array(tmp_path, "got", (2, 1, chunk[2]), chunk)
    raw = _arrays._raw_chunks(got)
    with _arrays.deferred_chunk_writes():
        _arrays.write_raw_chunk(raw, (0, 0, 0), np.full(chunk, 1, np.float32))
    _arrays._writer()  # made in the parent
    pid = os.fork()
    if pid == 0:  # the child: exit code 0 only if the write completes
        code = 1
        try:
            with _arrays.deferred_chunk_writes():
                _arrays.write_raw_chunk(raw, (1, 0, 0), np.full(chunk, 2, np.float32))
            code = 0
        finally:
            os._exit(code)
    import signal
    import time

    deadline = time.monotonic() + 30  # a hung child (no writer thread) fails, not hangs
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    if done[0] == 0:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        pytest.fail("the forked child's deferred write did not finish")
    assert os.waitstatus_to_exitcode(done[1]) == 0
    np.testing.assert_array_equal(got[...][:, 0, 0], [1, 2])
