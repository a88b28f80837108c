"""Data larger than RAM: a Zarr cube read lazily (Dask) gives the same result as in memory."""

import numpy as np
import pytest

pytest.importorskip("zarr")
pytest.importorskip("dask")

import splidar  # noqa: E402
from splidar.io import load, save  # noqa: E402
from splidar.scenes import single_surface_scene  # noqa: E402


def test_process_lazy_zarr_cube_matches_in_memory(tmp_path):
    sim = single_surface_scene((32, 32), n_bins=160).simulate(ppp=10, sbr=1, rng=0)
    save(sim.cube, tmp_path / "c.zarr", chunks=(8, 32))
    lazy = load(tmp_path / "c.zarr")
    assert lazy.is_lazy
    a = splidar.process(sim.cube, rng=1)
    b = splidar.process(lazy, rng=1)
    # same counts, same seed: the lazy path reads the same blocks, so results are identical
    np.testing.assert_array_equal(a.detection.mask, b.detection.mask)
    np.testing.assert_array_equal(a.points.depth_bin, b.points.depth_bin)
    np.testing.assert_allclose(a.points.intensity, b.points.intensity)


def test_detect_store_writes_arrays_to_zarr_and_matches_memory(tmp_path):
    import zarr

    sim = single_surface_scene((30, 20), n_bins=120).simulate(
        ppp=10, sbr=1, background="decaying", rng=2
    )
    # a spatially varying background so that the threshold varies per voxel
    rng = np.random.default_rng(3)
    extra = rng.poisson(np.linspace(0.0, 0.2, 30)[:, None, None, None] * np.ones((1, 20, 1, 120)))
    counts = sim.cube.counts + extra.astype(sim.cube.counts.dtype)
    cube = splidar.Cube(counts, irf=sim.cube.irf)
    save(cube, tmp_path / "c.zarr", chunks=(6, 20))
    lazy = load(tmp_path / "c.zarr")
    a = splidar.detect(cube, rng=1, block_rows=7)
    b = splidar.detect(lazy, rng=1, block_rows=7, n_jobs=2, store=tmp_path / "det")
    assert isinstance(b.saliency, zarr.Array) and b.saliency.chunks[0] == 7
    np.testing.assert_array_equal(np.asarray(b.saliency), a.saliency)
    np.testing.assert_array_equal(np.asarray(b.mask), a.mask)
    assert np.ndim(a.threshold) == 3
    np.testing.assert_array_equal(np.asarray(b.threshold), a.threshold)
    np.testing.assert_array_equal(b.surfaces.depth_bin, a.surfaces.depth_bin)
    assert b.reduction == a.reduction
    # the arrays stay on disk after the call
    g = zarr.open_group(str(tmp_path / "det"), mode="r")
    np.testing.assert_array_equal(g["mask"][:], a.mask)
    # every chunk file in its array's folder (``c.i.j.k`` keys): no folder per chunk
    first = {"saliency": "c.0.0.0", "mask": "c.0.0.0", "surface_histograms": "c.0.0.0.0"}
    for name, key in first.items():
        files = list((tmp_path / "det" / name).iterdir())
        assert not [f for f in files if f.is_dir()], name
        assert {"zarr.json", key} <= {f.name for f in files}, name


def test_detect_store_refuses_existing_directory(tmp_path):
    sim = single_surface_scene((16, 16), n_bins=80).simulate(ppp=10, sbr=1, rng=0)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "file.txt").write_text("keep me")
    with pytest.raises(splidar.SplidarError, match="not an empty directory"):
        splidar.detect(sim.cube, store=tmp_path / "busy")
    assert (tmp_path / "busy" / "file.txt").read_text() == "keep me"


def test_detect_lazy_cube_with_slope_recovery_matches_memory(tmp_path):
    # the slope pass reads a lazy cube by bands of rows: same surfaces as in memory
    sim = single_surface_scene((48, 48)).simulate(ppp=4, sbr=0.25, rng=0)
    save(sim.cube, tmp_path / "c.zarr", chunks=(8, 48))
    lazy = load(tmp_path / "c.zarr")
    a = splidar.detect(sim.cube, rng=0)
    b = splidar.detect(lazy, rng=0, store=tmp_path / "det")
    assert a.options["n_slopes"] > 0
    assert b.options["n_slopes"] == a.options["n_slopes"]
    np.testing.assert_array_equal(b.surfaces.depth_bin, a.surfaces.depth_bin)
    np.testing.assert_array_equal(b.surfaces.histograms, a.surfaces.histograms)
    np.testing.assert_array_equal(b.surfaces.evidence, a.surfaces.evidence)
