"""``splidar run`` on a Dask input: points streamed per strip, maps to Zarr, restart."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pyarrow")
zarr = pytest.importorskip("zarr")
pytest.importorskip("dask.array")

from splidar._stream import StripStore, load_detection, read_points, save_detection  # noqa: E402
from splidar.cli import main  # noqa: E402
from splidar.io import save  # noqa: E402
from splidar.scenes import multispectral_scene  # noqa: E402

COMMON = ["--strip-rows", "2", "--no-figures", "--no-view", "-q", "--seed", "0"]


@pytest.fixture(scope="module")
def zarr_cube(tmp_path_factory):
    d = tmp_path_factory.mktemp("stream")
    sim = multispectral_scene((48, 20), n_bins=100).simulate(ppp=10, sbr=1, rng=0)
    save(sim.cube, d / "c.zarr", chunks=(12, 20))
    return d / "c.zarr"


def test_strip_store_resumes_only_the_same_run(tmp_path):
    pts = dict(
        surface=np.arange(3), row=np.array([0, 1, 1]), col=np.array([0, 0, 1]),
        depth_bin=np.array([5.0, 6.0, 7.0]), layer=np.zeros(3, np.int64),
        intensity=np.ones((3, 2)), intensity_std=np.ones((3, 2)), label=np.zeros(3, np.int64),
        label_confidence=np.ones(3),
    )  # fmt: skip
    a = StripStore(tmp_path / "r", "key-a", (4, 2), 1, 2)
    a.begin([(0, 2), (2, 4)])
    a.put_fit(0, (0, 2), pts, dict(n_iter=3))
    b = StripStore(tmp_path / "r", "key-a", (4, 2), 1, 2)
    b.begin([(0, 2), (2, 4)])
    assert b.resumed == (0,) and b.fitted(1) is None
    cols, meta = b.fitted(0)
    assert meta == dict(n_iter=3) and np.array_equal(cols["intensity"], pts["intensity"])
    assert zarr.open_group(str(tmp_path / "r" / "maps.zarr"))["depth_bin"][1, 1, 0] == 7.0
    (tmp_path / "r" / "points.parquet" / "tile=0000" / "part-0.parquet").unlink()
    d = StripStore(tmp_path / "r", "key-a", (4, 2), 1, 2)
    d.begin([(0, 2), (2, 4)])
    assert d.resumed == ()  # a listed strip whose points are gone is computed again
    for key, cores in (("key-b", [(0, 2), (2, 4)]), ("key-a", [(0, 4)])):
        c = StripStore(tmp_path / "r", key, (4, 2), 1, 2)
        c.begin(cores)  # another input or options, or other strips: start afresh
        assert c.resumed == () and c.fitted(0) is None


def test_save_detection_is_read_back_for_the_same_run_only(tmp_path):
    import splidar

    sim = multispectral_scene((12, 10), n_bins=60).simulate(ppp=10, sbr=1, rng=0)
    det = splidar.detect(sim.cube, rng=0)
    save_detection(tmp_path / "r", "key-a", det)
    got = load_detection(tmp_path / "r", "key-a")
    for name in ("row", "col", "depth_bin", "counts", "background", "signal"):
        np.testing.assert_array_equal(getattr(got.surfaces, name), getattr(det.surfaces, name))
    np.testing.assert_array_equal(got.saliency, det.saliency)
    np.testing.assert_array_equal(got.mask, det.mask)
    assert got.options == det.options and got.null.scale == det.null.scale
    assert load_detection(tmp_path / "r", "key-b") is None  # another run's
    StripStore(tmp_path / "r", "key-a", (12, 10), 1, 4).begin([(0, 6), (6, 12)])
    assert load_detection(tmp_path / "r", "key-a") is not None  # a new manifest keeps it


def test_load_detection_refuses_a_pickle_naming_other_code(tmp_path):
    """A resume folder is a file like any other: its pickle may only name splidar's
    result classes, NumPy and Zarr; one that would run a command is refused unrun."""
    import pickle

    import splidar
    from splidar import SplidarError

    sim = multispectral_scene((12, 10), n_bins=60).simulate(ppp=10, sbr=1, rng=0)
    det = splidar.detect(sim.cube, rng=0, store=tmp_path / "det.zarr")
    save_detection(tmp_path / "r", "key", det)  # saliency and mask are Zarr handles here
    got = load_detection(tmp_path / "r", "key")
    np.testing.assert_array_equal(np.asarray(got.mask), np.asarray(det.mask))

    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    (tmp_path / "r" / "detection" / "detection.pkl").write_bytes(pickle.dumps(("key", [], Evil())))
    with pytest.raises(SplidarError, match="posix.system|os.system|nt.system"):
        load_detection(tmp_path / "r", "key")
    assert not marker.exists()


def _check_streamed_outputs(out):
    """points.parquet and maps.zarr hold what result.npz (the assembled result) holds."""
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["streamed"]["strips"]) == 24
    assert "points.parquet/" in summary["files"]
    assert sorted(p.name for p in (out / "points.parquet").iterdir())[:2] == [
        "tile=0000",
        "tile=0001",
    ]
    p, r = read_points(out / "points.parquet"), np.load(out / "result.npz")
    np.testing.assert_array_equal(p["surface"], np.arange(r["points_row"].size))
    for k in ("row", "col", "depth_bin", "label", "label_confidence", "intensity_std"):
        want = r[f"points_{k}"]
        got = p[k] if want.ndim == 1 else np.stack([p[f"{k}_{i}"] for i in range(4)], 1)
        np.testing.assert_array_equal(got, want, err_msg=k)
    maps = zarr.open_group(str(out / "maps.zarr"), mode="r")
    np.testing.assert_array_equal(maps["intensity"][:], r["intensity_map"])
    np.testing.assert_array_equal(maps["label"][:], r["label_map"])
    return summary


def test_cli_run_dask_input_streams_and_resumes_after_a_kill(zarr_cube, tmp_path):
    """A run on a Zarr cube writes its points per strip (Parquet) and its maps (Zarr);
    one killed (SIGKILL) after some strips finished leaves its resume folder, and the
    rerun reads the detection it kept, skips those strips and writes the points of an
    uninterrupted run."""
    ref = tmp_path / "ref"
    assert main(["run", str(zarr_cube), "--out", str(ref), *COMMON]) == 0
    streamed = _check_streamed_outputs(ref)["streamed"]
    assert streamed["strips_resumed"] == [] and not streamed["detection_resumed"]
    assert not (tmp_path / ".ref.resume").exists()
    out = tmp_path / "b"
    manifest = tmp_path / ".b.resume" / "manifest.json"
    cmd = [sys.executable, "-m", "splidar", "run", str(zarr_cube), "--out", str(out), *COMMON]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen, deadline = 0, time.monotonic() + 120
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            try:
                seen = len(json.loads(manifest.read_text())["finished"])
            except (OSError, ValueError):
                seen = 0
            if seen:
                os.kill(proc.pid, signal.SIGKILL)
                break
            time.sleep(0.002)
    finally:
        proc.kill()
        proc.wait()
    assert seen >= 1 and proc.returncode == -signal.SIGKILL, (seen, proc.returncode)
    assert not out.exists()
    finished = sorted(int(n) for n in json.loads(manifest.read_text())["finished"])
    assert 1 <= len(finished) < 24  # killed mid-way
    assert (manifest.parent / "detection" / "detection.pkl").is_file()  # kept before the strips
    assert main(["run", str(zarr_cube), "--out", str(out), *COMMON]) == 0
    streamed = _check_streamed_outputs(out)["streamed"]
    assert streamed["strips_resumed"] == finished
    assert streamed["detection_resumed"]  # read back, not recomputed
    assert not manifest.parent.exists()
    a, b = read_points(ref / "points.parquet"), read_points(out / "points.parquet")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(b[k], a[k], err_msg=k)
    ra, rb = np.load(ref / "result.npz"), np.load(out / "result.npz")
    for k in ("points_intensity", "points_label", "intensity_map"):
        np.testing.assert_array_equal(rb[k], ra[k])


def test_cli_run_large_result_writes_only_the_streamed_outputs(zarr_cube, tmp_path, monkeypatch):
    import splidar.cli

    monkeypatch.setattr(splidar.cli, "SMALL_RESULT", 10)  # "large": more than 10 points
    out = tmp_path / "big"
    args = ["run", str(zarr_cube), "--out", str(out), "--strip-rows", "12", "-q", "--seed", "0"]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["maps.zarr", "points.parquet", "summary.json"]
    summary = json.loads((out / "summary.json").read_text())
    p = read_points(out / "points.parquet")
    assert summary["n_points"] == p["surface"].size > 10 and len(summary["streamed"]["strips"]) == 4
    np.testing.assert_array_equal(p["surface"], np.arange(p["surface"].size))
    labels = zarr.open_group(str(out / "maps.zarr"), mode="r")["label"][:]
    np.testing.assert_array_equal(labels[p["row"], p["col"], p["layer"]], p["label"])
    assert np.count_nonzero(labels >= 0) == p["surface"].size
