"""Atomic outputs: a run killed at any moment leaves the previous complete output or none.

``splidar run`` writes into a hidden ``.OUT.partial-PID-*`` folder beside ``--out`` and
renames it at the end; SIGINT and SIGTERM remove the partial folder and exit with one
line (130, 143); after SIGKILL the next run removes what the dead process left (and
puts back a previous output it had moved aside for the instant between two renames).
"""

from __future__ import annotations

import hashlib
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from splidar.cli import _clean_stale, _on_sigterm, _Terminated, main

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX signals")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A scene, and the complete output folder of one run on it (the 'previous' output)."""
    d = tmp_path_factory.mktemp("atomic")
    scene = d / "scene.npz"
    args = ["--size", "16", "16", "--bins", "80", "--ppp", "10", "--sbr", "1", "--seed", "2"]
    assert main(["simulate", "multispectral", *args, "--out", str(scene), "-q"]) == 0
    ref = d / "ref" / "out"  # named as the runs' folders: view.html's title is the folder name
    ref.parent.mkdir()
    assert main(["run", str(scene), "--out", str(ref), "--no-figures", "-q"]) == 0
    return scene, ref, _digest(ref)


def _digest(folder: Path) -> dict[str, str]:
    out = {}
    for f in sorted(folder.rglob("*")):
        if f.is_file() and f.name != "summary.json":  # the summary holds timings
            out[str(f.relative_to(folder))] = hashlib.sha256(f.read_bytes()).hexdigest()
    if (folder / "summary.json").is_file():
        out["summary.json"] = "present"
    return out


def _start(scene: Path, out: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "splidar", "run", str(scene), "--out", str(out)]
    cmd += ["--force", "--no-figures", "-v"]
    return subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)


def _wait_for_main(proc: subprocess.Popen) -> list[str]:
    """Read stderr until the command has started (its first stage is logged)."""
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if "loading" in line:
            break
    return lines


def _check_left(out: Path, ref: dict[str, str]) -> None:
    visible = [p.name for p in out.parent.iterdir() if not p.name.startswith(".")]
    assert visible in ([out.name], []), visible  # no half-written folder in sight
    if out.exists():
        assert _digest(out) == ref  # the previous output, or the new (identical) one


def test_run_killed_at_random_moments_leaves_complete_output(reference, tmp_path):
    """SIGINT, SIGTERM and SIGKILL, each at a random moment of a run replacing an output."""
    scene, ref_dir, ref = reference
    rng = random.Random(17)
    runs = []
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        out = tmp_path / sig.name / "out"
        shutil.copytree(ref_dir, out)  # the previous complete output, replaced with --force
        proc = _start(scene, out)
        early = _wait_for_main(proc) if sig != signal.SIGKILL else []
        runs.append((sig, out, proc, early, time.monotonic() + rng.uniform(0.0, 2.5)))
    for sig, _out, proc, _early, when in sorted(runs, key=lambda r: r[-1]):
        time.sleep(max(when - time.monotonic(), 0.0))
        proc.send_signal(sig)
    for sig, out, proc, early, _ in runs:
        _, err = proc.communicate(timeout=120)
        err = "".join(early) + err
        assert "Traceback" not in err
        if proc.returncode != 0:  # else the run had finished: the new output is checked
            if sig == signal.SIGINT:
                assert proc.returncode == 130, err
                assert err.splitlines()[-1] == "splidar: interrupted; no output was written"
            elif sig == signal.SIGTERM:
                assert proc.returncode == 143, err
                assert err.splitlines()[-1] == "splidar: terminated; no output was written"
            else:
                assert proc.returncode == -signal.SIGKILL
        if sig != signal.SIGKILL:  # cleaned up on the way out
            assert [p.name for p in out.parent.iterdir()] in ([out.name], [])
        _check_left(out, ref)
        _clean_stale(out)  # what the next run does first
        assert [p.name for p in out.parent.iterdir()] == [out.name]
        assert _digest(out) == ref


def test_clean_stale_restores_output_moved_aside(tmp_path):
    """A run killed between its two renames left the previous output in .OUT.old-PID-*."""
    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    pid = int(dead.stdout)
    aside = tmp_path / f".out.old-{pid}-x" / "out"
    aside.mkdir(parents=True)
    (aside / "summary.json").write_text("{}")
    partial = tmp_path / f".out.partial-{pid}-y"
    partial.mkdir()
    (partial / "points.csv").write_text("row,col")
    mine = tmp_path / f".out.partial-{os.getpid()}-z"  # a live run's folder is left alone
    mine.mkdir()
    _clean_stale(out)
    assert (out / "summary.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", mine.name])


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="POSIX interval timers")
def test_on_sigterm_defers_a_signal_that_lands_inside_llvm():
    """A SIGTERM inside one of numba's LLVM callbacks (ctypes would print its traceback
    and drop the exception) is raised a moment later, outside the callback."""
    fake = os.path.join("site-packages", "llvmlite", "binding", "executionengine.py")
    src = (
        "def callback(kill, wait):\n"
        "    kill()\n"
        "    wait()\n"  # the signal arrives while this frame runs
        "    return 'done'\n"
    )
    ns: dict = {}
    exec(compile(src, fake, "exec"), ns)

    def busy(seconds=0.3):
        t = time.monotonic()
        while time.monotonic() - t < seconds:
            pass

    reached = []
    with pytest.raises(_Terminated):
        with _on_sigterm():
            reached.append(ns["callback"](lambda: os.kill(os.getpid(), signal.SIGTERM), busy))
            busy(2.0)  # the deferred signal is raised here
            reached.append("not interrupted")
    assert reached == ["done"]
    assert signal.getsignal(signal.SIGTERM) is not None  # the old handlers are back
