"""Messages of the command line: --json on stdout, -q/-v logging levels, progress bars."""

from __future__ import annotations

import json
import logging
import sys
import time

import pytest

from splidar.cli import _Stages, main

SIM_ARGS = ["--size", "16", "16", "--bins", "80", "--ppp", "20", "--sbr", "2", "--seed", "2"]


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    d = tmp_path_factory.mktemp("ux")
    out = d / "scene.npz"
    assert main(["simulate", "multispectral-two-layer", *SIM_ARGS, "--out", str(out), "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def result(cube):
    """An output folder of `splidar run`."""
    out = cube.parent / "res"
    assert main(["run", str(cube), "--out", str(out), "--no-figures", "-q"]) == 0
    return out


# ---------------------------------------------------------------------------------------
# --json
# ---------------------------------------------------------------------------------------
def test_main_run_json_is_the_only_stdout(cube, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["run", str(cube), "--out", str(out), "--no-figures", "--json"]) == 0
    captured = capsys.readouterr()
    s = json.loads(captured.out)  # stdout is one JSON document, nothing else
    assert s["out"] == str(out) and s["command"] == "run"
    assert s["counts"]["points"] > 0 and s["image_shape"] == [16, 16]
    assert {"points.csv", "points.ply", "result.npz", "view.html"} <= set(s["files"])
    assert s == {"out": str(out), **json.loads((out / "summary.json").read_text())}
    # the human messages still reach the user, on stderr
    assert f"outputs written to {out}/" in captured.err


def test_main_json_with_quiet_leaves_stderr_empty(cube, tmp_path, capsys):
    out = tmp_path / "s.npz"
    assert main(["simulate", "single", *SIM_ARGS, "--out", str(out), "--json", "-q"]) == 0
    captured = capsys.readouterr()
    s = json.loads(captured.out)
    assert s["cube"] == str(out) and s["shape"] == [16, 16, 1, 80] and s["seed"] == 2
    assert s["true_surfaces"] > 0 and captured.err == ""


def test_main_view_json(result, tmp_path, capsys):
    dest = tmp_path / "v.html"
    assert main(["view", str(result), "--out", str(dest), "--no-open", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["view"] == str(dest) and s["bytes"] == dest.stat().st_size
    assert s["points"] == json.loads((result / "summary.json").read_text())["counts"]["points"]
    assert s["opened"] is False


def test_main_json_failure_leaves_stdout_empty(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing.npz"), "--json"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("splidar: error:") and "does not exist" in captured.err


def test_main_demo_json_holds_metrics(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--no-figures", "--no-view", "--json"]) == 0
    captured = capsys.readouterr()
    s = json.loads(captured.out)
    assert s["command"] == "demo" and s["out"] == "splidar-demo"
    assert 0.85 < s["metrics"]["f_true"] <= 1 and "F_true" in captured.err


# ---------------------------------------------------------------------------------------
# -q / -v: levels of the library's loggers; the handler lives in the CLI only
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "flags, info, debug",
    [
        ([], False, False),
        (["-v"], True, False),
        (["-vv"], True, True),
        (["-q", "-v"], False, False),
    ],
)
def test_main_verbosity_sets_library_log_level(result, tmp_path, capsys, flags, info, debug):
    dest = tmp_path / "v.html"
    assert main(["view", str(result), "--out", str(dest), "--no-open", *flags]) == 0
    err = capsys.readouterr().err
    # INFO: the CLI's stage messages; DEBUG: splidar.view's own record of the file
    assert ("splidar: writing the view: " in err) is info
    assert ("splidar: view: " in err and "bytes of arrays" in err) is debug


def test_main_restores_logging_after_the_command(result, tmp_path):
    logger = logging.getLogger("splidar")
    before = (list(logger.handlers), logger.level, logger.propagate)
    assert main(["view", str(result), "--out", str(tmp_path / "v.html"), "--no-open", "-vv"]) == 0
    assert (list(logger.handlers), logger.level, logger.propagate) == before
    # the library itself only carries a NullHandler: importing it configures nothing
    assert all(isinstance(h, logging.NullHandler) for h in logger.handlers)


def test_main_quiet_silences_library_warnings(tmp_path, capsys):
    """A library warning (a CSV guesses the image size) shows by default, not with -q."""
    pts = tmp_path / "points.csv"
    pts.write_text("row,col,depth_bin\n0,0,5.0\n1,2,7.0\n")
    truth = tmp_path / "truth.npz"
    from splidar import PointSet

    PointSet(row=[0, 1], col=[0, 2], depth_bin=[5.0, 7.0], image_shape=(2, 3)).save(truth)
    assert main(["evaluate", str(pts), str(truth)]) == 0
    assert "does not record the image size" in capsys.readouterr().err
    assert main(["evaluate", str(pts), str(truth), "-q"]) == 0
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------------------------------
# progress bars
# ---------------------------------------------------------------------------------------
def test_stages_bar_keeps_counting_during_a_long_step(capsys, monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    stages = _Stages(["a long step", "a short step"], quiet=False)
    try:
        with stages.stage("a long step"):
            time.sleep(1.3)  # no update from the step itself: only the ticker redraws
        with stages.stage("a short step"):
            pass
    finally:
        stages.close()
    err = capsys.readouterr().err
    # redrawn while the step ran: its elapsed time passed 00:01 before the step ended
    assert "a long step" in err and "0/2 [00:01]" in err
    assert stages.timings["a long step"] >= 1.3 and not stages._ticker.is_alive()


def test_stages_silent_when_quiet_or_not_a_terminal(capsys, monkeypatch):
    for quiet, tty in ((True, True), (False, False)):
        monkeypatch.setattr(sys.stderr, "isatty", lambda tty=tty: tty)
        stages = _Stages(["step"], quiet=quiet)
        with stages.stage("step"):
            time.sleep(0.1)
        stages.close()
        assert stages._ticker is None
    assert capsys.readouterr().err == ""


def test_main_view_progress_bar_on_terminal(result, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main(["view", str(result), "--out", str(tmp_path / "v.html"), "--no-open"]) == 0
    err = capsys.readouterr().err
    assert "reading the points" in err and "writing the view" in err and "1/2" in err


def test_main_view_help_has_example_and_is_listed(capsys):
    assert main(["view", "--help"]) == 0
    out = capsys.readouterr().out
    assert "example" in out and "splidar view" in out and "--no-open" in out
    assert main(["--help"]) == 0
    assert "view" in capsys.readouterr().out
