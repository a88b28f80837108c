"""Tests of the command line through ``splidar.cli.main([...])``."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

import splidar
from splidar import PointSet
from splidar.cli import main, read_points

# A tiny scene keeps the whole module fast: 24 x 24 pixels, 4 wavelengths, 100 bins.
SIM_ARGS = ["--size", "24", "24", "--bins", "100", "--ppp", "20", "--sbr", "2", "--seed", "1"]


def _error_line(err: str) -> str:
    """The CLI's error output must be exactly one line, without a traceback."""
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith("splidar: error: ")
    return lines[0]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A simulated multispectral two-layer cube and its truth, written by the CLI."""
    d = tmp_path_factory.mktemp("sim")
    out = d / "scene.npz"
    rc = main(["simulate", "multispectral-two-layer", *SIM_ARGS, "--out", str(out), "-q"])
    assert rc == 0
    return out, d / "scene-truth.npz"


@pytest.fixture(scope="module")
def run_out(simulated):
    """`splidar run` on the simulated cube, default output folder."""
    cube, _ = simulated
    rc = main(["run", str(cube), "-q", "--seed", "0"])
    assert rc == 0
    return cube.parent / "scene-splidar"


# ---------------------------------------------------------------------------------------
# simulate / run / evaluate
# ---------------------------------------------------------------------------------------
def test_main_simulate_writes_loadable_cube_and_truth(simulated):
    cube_path, truth_path = simulated
    cube = splidar.load(cube_path)
    truth = PointSet.load(truth_path)
    assert cube.shape == (24, 24, 4, 100)
    assert cube.library is not None and cube.library.n_classes == 3
    assert truth.image_shape == (24, 24)
    # the net adds a second surface on strand pixels: more surfaces than pixels
    assert 24 * 24 < len(truth) < 2 * 24 * 24
    # PPP 20 requested: mean signal photons per pixel in the truth
    assert truth.intensity.sum() / (24 * 24) == pytest.approx(20, rel=1e-6)


def test_main_simulate_refuses_existing_file(simulated, capsys):
    cube_path, _ = simulated
    rc = main(["simulate", "single", *SIM_ARGS, "--out", str(cube_path)])
    assert rc == 2
    assert "exists" in _error_line(capsys.readouterr().err)


def test_main_simulate_bad_scene_and_art_without_folder(tmp_path, capsys):
    assert main(["simulate", "nope", "--out", str(tmp_path / "a.npz")]) == 2
    assert "invalid choice" in _error_line(capsys.readouterr().err)
    assert main(["simulate", "art", "--out", str(tmp_path / "a.npz")]) == 2
    assert "--art-folder" in _error_line(capsys.readouterr().err)
    assert main(["simulate", "single", "--out", str(tmp_path / "a.txt")]) == 2
    assert ".npz" in _error_line(capsys.readouterr().err)


def test_main_run_writes_all_outputs(run_out):
    for name in ("points.csv", "points.ply", "result.npz", "summary.json"):
        assert (run_out / name).is_file(), name
    figs = {p.name for p in (run_out / "figures").glob("*.png")}
    assert figs == {
        "depth.png",
        "intensity.png",
        "labels.png",
        "label_confidence.png",
        "point_cloud.png",
        "saliency_histogram.png",
        "detection_slice.png",
    }
    # no leftover temporary folders beside the result
    assert not [p for p in run_out.parent.iterdir() if p.name.startswith(".")]
    s = json.loads((run_out / "summary.json").read_text())
    assert s["command"] == "run"
    assert s["cube_shape"] == [24, 24, 4, 100]
    assert s["counts"]["points"] > 0
    assert 0 < s["data_reduction"]["voxel_fraction"] < 1
    assert "detecting surfaces" in s["timings_s_command"]


def test_main_run_csv_header_and_ply_agree(run_out):
    with open(run_out / "points.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    assert header[:8] == [
        "row",
        "col",
        "depth_bin",
        "label",
        "intensity_0",
        "intensity_1",
        "intensity_2",
        "intensity_3",
    ]
    assert header[8] == "depth_m"
    data = np.array(rows[1:], dtype=float)
    v = PlyData.read(str(run_out / "points.ply"))["vertex"].data
    assert v.size == data.shape[0]
    np.testing.assert_array_equal(v["x"], data[:, 1])
    np.testing.assert_array_equal(v["y"], 23 - data[:, 0])
    np.testing.assert_array_equal(v["label"], data[:, 3])
    # CSV has 7 significant digits, PLY float32: agree to 1e-6 relative
    np.testing.assert_allclose(v["intensity_2"], data[:, 6], rtol=1e-6)
    np.testing.assert_allclose(v["depth"], data[:, 8], rtol=1e-6)
    np.testing.assert_allclose(v["z"], -data[:, 8], rtol=1e-6)


def test_main_evaluate_prints_metrics(run_out, simulated, capsys):
    _, truth = simulated
    rc = main(["evaluate", str(run_out / "result.npz"), str(truth), "--tau", "2"])
    assert rc == 0
    out = capsys.readouterr().out
    for key in ("F_true", "F_false", "DAE", "IAE", "label accuracy"):
        assert key in out
    # PPP 20, SBR 2 on a small scene: the pipeline finds most surfaces
    rc = main(["evaluate", str(run_out), str(truth), "--json"])
    m = json.loads(capsys.readouterr().out)
    assert rc == 0 and m["f_true"] > 0.8 and m["n_true"] > 0


def test_main_evaluate_csv_equals_npz(run_out, simulated, capsys):
    _, truth = simulated
    main(["evaluate", str(run_out / "points.csv"), str(truth), "--json", "-q"])
    a = json.loads(capsys.readouterr().out)
    main(["evaluate", str(run_out / "result.npz"), str(truth), "--json"])
    b = json.loads(capsys.readouterr().out)
    assert a["n_matched"] == b["n_matched"] and a["f_false"] == b["f_false"]
    # CSV keeps 7 significant digits
    assert a["dae"] == pytest.approx(b["dae"], rel=1e-5)


def test_read_points_rejects_non_points(tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros(3))
    with pytest.raises(splidar.SplidarError, match="no point set"):
        read_points(tmp_path / "x.npz")
    with pytest.raises(splidar.SplidarError, match="does not exist"):
        read_points(tmp_path / "missing.npz")


def test_main_evaluate_bad_inputs(tmp_path, simulated, capsys):
    _, truth = simulated
    assert main(["evaluate", str(tmp_path / "none.npz"), str(truth)]) == 1
    assert "does not exist" in _error_line(capsys.readouterr().err)
    other = PointSet(row=[0], col=[0], depth_bin=[1.0], image_shape=(5, 5))
    other.save(tmp_path / "other.npz")
    assert main(["evaluate", str(tmp_path / "other.npz"), str(truth)]) == 1
    assert "image size" in _error_line(capsys.readouterr().err)
    assert main(["evaluate", str(truth), str(truth), "--tau", "-1"]) == 2
    _error_line(capsys.readouterr().err)


# ---------------------------------------------------------------------------------------
# output folders
# ---------------------------------------------------------------------------------------
def test_main_run_refuses_existing_out_without_force(run_out, simulated, capsys):
    cube, _ = simulated
    before = (run_out / "summary.json").stat().st_mtime_ns
    rc = main(["run", str(cube), "--out", str(run_out), "--no-figures"])
    assert rc == 2
    assert "--force" in _error_line(capsys.readouterr().err)
    assert (run_out / "summary.json").stat().st_mtime_ns == before


def test_main_run_force_replaces_splidar_folder_only(simulated, tmp_path, capsys):
    cube, _ = simulated
    out = tmp_path / "res"
    assert main(["run", str(cube), "--out", str(out), "--no-figures", "-q"]) == 0
    (out / "stale.txt").write_text("old")
    assert main(["run", str(cube), "--out", str(out), "--no-figures", "--force", "-q"]) == 0
    assert not (out / "stale.txt").exists() and (out / "points.csv").is_file()
    # a folder that is not a splidar output is never replaced
    other = tmp_path / "mine"
    other.mkdir()
    (other / "thesis.tex").write_text("precious")
    rc = main(["run", str(cube), "--out", str(other), "--force", "--no-figures"])
    assert rc == 2
    assert "not empty" in _error_line(capsys.readouterr().err)
    assert (other / "thesis.tex").read_text() == "precious"


def test_main_run_refuses_out_containing_input(simulated, capsys):
    cube, _ = simulated
    rc = main(["run", str(cube), "--out", str(cube.parent), "--force"])
    assert rc == 2
    assert "input" in _error_line(capsys.readouterr().err)
    assert cube.is_file()


def test_main_run_interrupted_leaves_no_output(simulated, tmp_path, monkeypatch, capsys):
    import splidar.export

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(splidar.export, "write_ply", boom)
    cube, _ = simulated
    out = tmp_path / "res"
    rc = main(["run", str(cube), "--out", str(out), "--no-figures"])
    assert rc == 130
    assert "interrupted" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # neither the folder nor a partial one


def test_main_run_failure_while_writing_is_one_line(simulated, tmp_path, monkeypatch, capsys):
    import splidar.export

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(splidar.export, "write_npz", full)
    cube, _ = simulated
    rc = main(["run", str(cube), "--out", str(tmp_path / "res"), "--no-figures"])
    assert rc == 1
    assert "No space left" in _error_line(capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------
def test_main_run_missing_file(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.npz")]) == 1
    assert "does not exist" in _error_line(capsys.readouterr().err)


def test_main_run_unreadable_file(tmp_path, capsys):
    bad = tmp_path / "garbage.mat"
    bad.write_bytes(b"this is not a MATLAB file at all" * 10)
    assert main(["run", str(bad)]) == 1
    _error_line(capsys.readouterr().err)
    assert not (tmp_path / "garbage-splidar").exists()


@pytest.mark.parametrize(
    ("option", "value", "status", "needle"),
    [
        ("--scales", "a,b", 2, "--scales"),
        ("--scales", "2,4", 1, "odd"),
        ("--pfa", "1.5", 2, "--pfa"),
        ("--pfa", "zero", 2, "--pfa"),
        ("--max-surfaces", "0", 2, "--max-surfaces"),
        ("--weights", "0.5,0.2", 1, "weights"),
    ],
)
def test_main_run_bad_options(simulated, tmp_path, capsys, option, value, status, needle):
    cube, _ = simulated
    out = tmp_path / "res"
    rc = main(["run", str(cube), "--out", str(out), option, value, "--no-figures"])
    assert rc == status
    assert needle in _error_line(capsys.readouterr().err)
    assert not out.exists()


def test_main_usage_errors(capsys):
    assert main([]) == 2
    capsys.readouterr()
    assert main(["frobnicate"]) == 2
    _error_line(capsys.readouterr().err)
    assert main(["run"]) == 2
    assert "INPUT" in _error_line(capsys.readouterr().err)
    assert main(["run", "x.npz", "--irf", "a", "--irf-fwhm", "3"]) == 2
    assert "not allowed" in _error_line(capsys.readouterr().err)


def test_main_verbose_shows_traceback(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.npz"), "--verbose"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("splidar: error:")


# ---------------------------------------------------------------------------------------
# demo, help, version
# ---------------------------------------------------------------------------------------
def test_main_demo_prints_metrics_and_writes_outputs(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--no-figures"]) == 0
    out = capsys.readouterr().out
    for key in ("F_true", "F_false", "DAE", "IAE", "label accuracy", "timings"):
        assert key in out
    d = tmp_path / "splidar-demo"
    assert (d / "truth.npz").is_file() and (d / "points.ply").is_file()
    s = json.loads((d / "summary.json").read_text())
    # the built-in scene at PPP 10, SBR 1: most surfaces found, most labels right
    assert s["metrics"]["f_true"] > 0.85
    assert s["metrics"]["label_accuracy"] > 0.8
    # the printed command works on the demo's own outputs
    assert main(["evaluate", "splidar-demo", "splidar-demo/truth.npz", "--json"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["f_true"] == pytest.approx(s["metrics"]["f_true"])


def test_main_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"splidar {splidar.__version__}"


@pytest.mark.parametrize("command", ["demo", "run", "simulate", "evaluate"])
def test_main_help_has_example(command, capsys):
    assert main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert "example" in out and f"splidar {command}" in out


def test_main_top_help_lists_commands(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for c in ("demo", "run", "simulate", "evaluate", "--quiet", "--verbose", "--version"):
        assert c in out


def test_python_dash_m_splidar():
    r = subprocess.run(
        [sys.executable, "-m", "splidar", "--version"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0 and r.stdout.startswith("splidar ")


def test_main_run_quiet_prints_nothing(simulated, tmp_path, capsys):
    cube, _ = simulated
    assert main(["run", str(cube), "--out", str(tmp_path / "r"), "--no-figures", "-q"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""


def test_main_run_reports_outputs(simulated, tmp_path, capsys):
    cube, _ = simulated
    assert main(["run", str(cube), "--out", str(tmp_path / "r"), "--no-figures"]) == 0
    captured = capsys.readouterr()
    assert "surfaces" in captured.out and str(tmp_path / "r") in captured.out
    assert captured.err == ""  # stderr is not a terminal here: no progress bar
    assert Path(tmp_path / "r" / "result.npz").is_file()


def test_main_run_progress_bar_on_terminal(simulated, tmp_path, capsys, monkeypatch):
    cube, _ = simulated
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main(["run", str(cube), "--out", str(tmp_path / "r"), "--no-figures"]) == 0
    err = capsys.readouterr().err
    assert "detecting surfaces" in err and "3/4" in err
    # and --quiet silences it even on a terminal
    assert main(["run", str(cube), "--out", str(tmp_path / "q"), "--no-figures", "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_cli_names_spells_api_parameters_as_options():
    from splidar.cli import _cli_names

    assert _cli_names("`max_surfaces` must be >= 1") == "--max-surfaces must be >= 1"
    assert (
        _cli_names("pass irf= or irf_fwhm= to override") == "pass --irf or --irf-fwhm to override"
    )
    # values after = and names that are not options stay as they are
    assert _cli_names("Pass weights=None; `counts` bad") == "Pass weights=None; `counts` bad"


def test_main_run_with_store_keeps_arrays_on_disk(simulated, run_out, tmp_path):
    pytest.importorskip("zarr")
    cube, _ = simulated
    out = tmp_path / "out"
    store = tmp_path / "det.zarr"
    rc = main(
        ["run", str(cube), "-q", "--seed", "0", "--out", str(out), "--store", str(store)]
        + ["--jobs", "2"]
    )
    assert rc == 0
    assert (store / "mask").exists() and (out / "figures").is_dir()
    with np.load(out / "result.npz") as a, np.load(run_out / "result.npz") as b:
        # same detection as the in-memory run; the map itself stays in the store
        assert "detection_mask" not in a.files and str(a["detection_store"]) == str(store)
        np.testing.assert_array_equal(a["points_depth_bin"], b["points_depth_bin"])
    assert sorted(p.name for p in (out / "figures").iterdir()) == sorted(
        p.name for p in (run_out / "figures").iterdir()
    )


def test_main_run_alpha_auto_and_bad_alpha(simulated, tmp_path, capsys):
    cube, _ = simulated
    out = tmp_path / "auto"
    rc = main(["run", str(cube), "-q", "--alpha", "auto", "--no-figures", "--out", str(out)])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert "auto" in json.dumps(summary)
    capsys.readouterr()
    assert main(["run", str(cube), "--alpha", "0.5", "--out", str(tmp_path / "x")]) == 2
    assert "--alpha" in _error_line(capsys.readouterr().err)


def test_main_run_skip_passes_the_other_passes(simulated, tmp_path, monkeypatch, capsys):
    import splidar.detection as det_mod

    seen = []
    real = det_mod.detect

    def spy(cube, **kw):
        seen.append(kw.get("passes", "default"))
        return real(cube, **kw)

    monkeypatch.setattr(det_mod, "detect", spy)
    cube, _ = simulated
    for out, extra in (("o", ["--skip", "slopes,enclosed"]), ("p", [])):
        args = ["run", str(cube), "-q", "--seed", "0", "--no-figures", "--out", str(tmp_path / out)]
        assert main(args + extra) == 0
    assert seen == [
        (
            "recentre",
            "spill_over",
            "isolated",
            "dark_regions",
            "stray_clusters",
            "unlayered",
            "align_depths",
            "edge_bands",
        ),
        "default",
    ]
    capsys.readouterr()
    assert main(["run", str(cube), "--skip", "dark", "--out", str(tmp_path / "x")]) == 2
    assert "--skip" in capsys.readouterr().err


def test_scales_line_says_which_boxes_each_region_took():
    from types import SimpleNamespace

    from splidar.cli import _scales_line

    det = SimpleNamespace(
        scales=(1, 3, 7, 11),
        options={
            "scales_auto": True, "scale_coherence": (None, 0.5, 0.45, 0.4),
            "scale_regions": {"scales": ((1, 3, 7, 11), (1,)), "pixels": (1344, 960)},
        },
    )  # fmt: skip
    assert _scales_line(det) == (
        "spatial pooling by region: boxes 1,3,7,11 on 1344 px; 1 on 960 px "
        "(--scales 1,3,7,11 keeps all)",
    )


def test_run_says_which_boxes_scales_auto_dropped(tmp_path, capsys):
    # independent depths per pixel: scales="auto" keeps the 1 x 1 box only, and the run
    # says so (with the option that keeps every box); a smooth scene prints no such line
    rng = np.random.default_rng(0)
    n, T = 24, 200
    t = np.arange(T)
    depth = rng.uniform(40, 180, (n, n))
    lam = 12 * np.exp(-0.5 * ((t - depth[..., None]) / 1.5) ** 2) / (1.5 * np.sqrt(2 * np.pi))
    y = rng.poisson(lam + 0.06).astype(np.uint16)[:, :, None, :]
    irf = np.exp(-0.5 * ((np.arange(31) - 15) / 1.5) ** 2)
    path = tmp_path / "incoherent.npz"
    np.savez(path, counts=y, irf=(irf / irf.sum())[None])
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--no-figures", "--no-view"]) == 0
    said = capsys.readouterr().out
    assert "spatial pooling: boxes 1; 3, 7, 11 dropped" in said
    assert "--scales 1,3,7,11" in said
    assert main(["run", str(path), "--out", str(out), "--force", "--no-figures",
                 "--no-view", "--scales", "1,3,7,11"]) == 0  # fmt: skip
    assert "spatial pooling" not in capsys.readouterr().out
