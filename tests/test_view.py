"""Tests of splidar.view: the self-contained HTML 3D view, in Python and in a real browser.

The browser tests drive Debian's Chromium (/usr/bin/chromium, installed by .ci/run) with
playwright; they skip, saying why, only when that browser or playwright is absent.
"""

from __future__ import annotations

import base64
import gzip
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import splidar
from splidar import PointSet, SplidarError
from splidar.cli import main
from splidar.scenes import multispectral_scene
from splidar.view import is_view_file, load_view_input, view_html, write_view

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    # WebGL without a GPU: Chromium 150 falls back to SwiftShader by itself; newer
    # versions only when allowed (no effect where the fallback is automatic)
    "--enable-unsafe-swiftshader",
]
BACKGROUND = (22, 24, 29)


@pytest.fixture(scope="module")
def rec():
    """A reconstruction of a small two-layer multispectral scene (3 named classes)."""
    scene = multispectral_scene((24, 24), n_bins=100, two_layers=True)
    sim = scene.simulate(ppp=20, sbr=2, rng=1)
    return splidar.process(sim.cube, library=scene.library)


@pytest.fixture(scope="module")
def out_folder(rec, tmp_path_factory):
    """An output folder of `splidar run` holding result.npz (and view.html)."""
    d = tmp_path_factory.mktemp("view")
    cube = d / "scene.npz"
    sim_args = ["--size", "24", "24", "--bins", "100", "--ppp", "20", "--sbr", "2"]
    assert main(["simulate", "multispectral-two-layer", *sim_args, "--out", str(cube), "-q"]) == 0
    assert main(["run", str(cube), "--no-figures", "-q"]) == 0
    return d / "scene-splidar"


def _decode(text: str) -> tuple[dict, dict[str, np.ndarray]]:
    """Undo what the page undoes (base64, gzip, byte planes, differences), in Python."""
    meta = json.loads(re.search(r'id="splidar-meta">(.*?)</script>', text, re.S).group(1))
    b64 = re.search(r'id="splidar-data">(.*?)</script>', text, re.S).group(1)
    raw = base64.b64decode(b64.strip())
    if meta["compression"] == "gzip":
        raw = gzip.decompress(raw)
    kinds = {"u8": np.uint8, "u16": np.uint16, "f32": np.float32}
    arrays = {}
    for name, kind, offset, length, step in meta["arrays"]:
        dt = np.dtype(kinds[kind]).newbyteorder("<")
        planes = np.frombuffer(raw, np.uint8, length * dt.itemsize, offset)
        a = planes.reshape(dt.itemsize, length).T.copy().view(dt).reshape(-1)
        if step:
            for i in range(step):
                a[i::step] = np.cumsum(a[i::step], dtype=np.uint16)
        arrays[name] = a
    return meta, arrays


# ---------------------------------------------------------------------------------------
# the file (no browser)
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("compress", [True, False])
def test_view_html_arrays_decode_to_the_points(rec, compress):
    meta, arrays = _decode(view_html(rec, compress=compress))
    p = rec.points
    order = np.argsort(p.layer, kind="stable")
    assert meta["n"] == len(p) > 0
    rc = arrays["rowcol"].reshape(-1, 2)
    np.testing.assert_array_equal(rc[:, 0], p.row[order])
    np.testing.assert_array_equal(rc[:, 1], p.col[order])
    # depths travel as float32 (metres here: the simulated cube knows its bin width)
    np.testing.assert_allclose(arrays["depth"], p.depth_m[order], rtol=1e-6)
    np.testing.assert_array_equal(arrays["label"], p.label[order])
    # each layer is one contiguous range, in order, covering every point
    ranges = [lay["range"] for lay in meta["layers"]]
    assert ranges[0][0] == 0 and sum(c for _, c in ranges) == len(p)
    for k, (first, count) in enumerate(ranges):
        assert np.all(p.layer[order][first : first + count] == k)
    # quantised intensity within half a code of the exact total
    spec = meta["colors"]["intensity"]
    total = p.intensity[order].sum(axis=1)
    back = spec["scale"] * arrays["q_intensity"] + spec["offset"]
    np.testing.assert_allclose(back, total, atol=spec["scale"] / 2 + 1e-9 * total.max())


def test_view_html_has_no_external_reference(rec):
    text = view_html(rec)
    # every src/href is a data: URL; a Content-Security-Policy forbids any fetch
    refs = re.findall(r'(?:src|href)\s*=\s*["\']([^"\']*)', text)
    assert refs and all(r.startswith("data:") for r in refs), refs
    assert "default-src 'none'" in text
    assert not re.search(r"https?://", text)
    assert "<script src" not in text


def test_view_html_legend_names_classes_and_modes(rec):
    meta, _ = _decode(view_html(rec))
    assert meta["colors"]["label"]["names"] == list(rec.class_names)
    assert sum(meta["colors"]["label"]["counts"]) == len(rec.points)
    assert set(meta["colors"]) == {
        "depth",
        "label",
        "intensity",
        "spectral",
        "uncertainty",
        "confidence",
    }


def test_view_html_escapes_hostile_class_names(tmp_path):
    evil = '</script><script>alert("x")</script>__SPLIDAR_DATA__'
    z = {
        "points_row": np.array([0, 1]),
        "points_col": np.array([0, 1]),
        "points_depth_bin": np.array([3.0, 4.0]),
        "points_image_shape": np.array([2, 2]),
        "points_label": np.array([0, 1]),
        "class_names": np.array(["plain", evil]),
    }
    np.savez(tmp_path / "result.npz", **z)
    text = view_html(tmp_path)
    assert evil not in text and text.count("</script>") == 3  # the page's own three
    meta, _ = _decode(text)
    assert meta["colors"]["label"]["names"] == ["plain", evil]


def test_load_view_input_reads_folder_result_and_point_set(out_folder, rec, tmp_path):
    a = load_view_input(out_folder)
    b = load_view_input(out_folder / "result.npz")
    assert a.title == b.title == "scene-splidar"
    assert len(a.points) == len(b.points) > 0 and a.class_names == tuple(rec.class_names)
    assert a.bin_width_ps == pytest.approx(rec.bin_width_ps)
    rec.points.save(tmp_path / "pts.npz")
    c = load_view_input(tmp_path / "pts.npz")
    assert len(c.points) == len(rec.points) and c.bin_width_ps is None


def test_load_view_input_errors_name_the_problem(tmp_path):
    with pytest.raises(SplidarError, match="does not exist"):
        load_view_input(tmp_path / "nope.npz")
    with pytest.raises(SplidarError, match="no result.npz"):
        load_view_input(tmp_path)
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(SplidarError, match="holds no points"):
        load_view_input(tmp_path / "other.npz")
    with pytest.raises(SplidarError, match="Reconstruction, a PointSet"):
        load_view_input(42)


def test_write_view_rejects_unavailable_colour(tmp_path):
    p = PointSet(row=[0], col=[0], depth_bin=[1.0], image_shape=(1, 1))
    with pytest.raises(SplidarError, match="`color` must be one of depth"):
        write_view(p, tmp_path / "v.html", color="uncertainty")
    f = write_view(p, tmp_path / "v.html")
    assert is_view_file(f) and not is_view_file(tmp_path / "missing.html")


def test_run_writes_view_html_and_no_view_skips_it(out_folder, tmp_path):
    assert is_view_file(out_folder / "view.html")
    s = json.loads((out_folder / "summary.json").read_text())
    assert "view.html" in s["files"]
    out = tmp_path / "nv"
    cube = out_folder.parent / "scene.npz"
    assert main(["run", str(cube), "--out", str(out), "--no-figures", "--no-view", "-q"]) == 0
    assert not (out / "view.html").exists() and (out / "result.npz").is_file()


def test_main_view_writes_prints_path_and_refuses_foreign_file(out_folder, tmp_path, capsys):
    dest = tmp_path / "v.html"
    assert main(["view", str(out_folder), "--out", str(dest), "--no-open"]) == 0
    assert capsys.readouterr().out.strip() == str(dest) and is_view_file(dest)
    # a file splidar wrote is replaced; any other file only with --force
    assert main(["view", str(out_folder), "--out", str(dest), "--no-open", "-q"]) == 0
    foreign = tmp_path / "notes.html"
    foreign.write_text("<p>mine</p>")
    assert main(["view", str(out_folder), "--out", str(foreign), "--no-open"]) == 2
    assert "--force" in capsys.readouterr().err and foreign.read_text() == "<p>mine</p>"
    assert main(["view", str(out_folder), "--out", str(foreign), "--no-open", "--force"]) == 0
    assert is_view_file(foreign)
    assert main(["view", str(tmp_path / "missing"), "--no-open"]) == 1
    assert "does not exist" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------
# in a real browser
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.exists():
        pytest.skip("Chromium is absent: apt-get install chromium (as .ci/run does)")
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="playwright is absent: pip install -e '.[test]'"
    )
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS, headless=True)
        yield b
        b.close()


def _open(browser, path: Path):
    """Open a view; returns the page and the lists of console errors and requests."""
    page = browser.new_page(viewport={"width": 800, "height": 600})
    errors, requests = [], []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("request", lambda r: requests.append(r.url))
    page.goto(path.resolve().as_uri())
    page.wait_for_function(
        "() => window.splidarView && (window.splidarView.ready || window.splidarView.error)",
        timeout=60000,
    )
    assert page.evaluate("window.splidarView.error") is None
    return page, errors, requests


def _lit_fraction(png: bytes) -> float:
    """Fraction of screenshot pixels right of the panel that differ from the background."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))[:, 280:]
    return float(np.any(np.abs(img.astype(int) - BACKGROUND) > 8, axis=2).mean())


@pytest.mark.parametrize("compress", [True, False])
def test_view_in_browser_draws_every_point_offline(browser, rec, tmp_path, compress):
    path = write_view(rec, tmp_path / "view.html", compress=compress)
    page, errors, requests = _open(browser, path)
    state = page.evaluate(
        "({n: splidarView.nPoints, drawn: splidarView.drawn, c: splidarView.drawCalls})"
    )
    assert state == {"n": len(rec.points), "drawn": len(rec.points), "c": 1}
    assert page.evaluate("splidarView.litPixels()") > 2000
    assert _lit_fraction(page.screenshot()) > 0.02
    assert errors == []
    assert requests == [path.resolve().as_uri()]  # the page itself, nothing else
    page.close()


def test_view_in_browser_modes_layers_and_legend(browser, rec, tmp_path):
    path = write_view(rec, tmp_path / "view.html")
    page, errors, _ = _open(browser, path)
    counts = np.bincount(rec.points.layer)
    assert len(counts) == 2  # the net: two layers
    for k, c in enumerate(counts):
        page.select_option("#layer", str(k))
        assert page.evaluate("splidarView.render()") == c
    page.select_option("#layer", "-1")
    assert page.evaluate("splidarView.render()") == len(rec.points)
    shots = {}
    for mode in ("depth", "label", "intensity", "spectral", "uncertainty", "confidence"):
        page.select_option("#color", mode)
        assert page.evaluate("splidarView.colorMode") == mode
        shots[mode] = page.screenshot()
        if mode == "label":
            legend = page.inner_text("#legend")
            for name in rec.class_names:
                assert name in legend
    assert len(set(shots.values())) == len(shots)  # every mode colours differently
    assert errors == []
    page.close()


def test_view_in_browser_rotates_and_zooms(browser, rec, tmp_path):
    path = write_view(rec, tmp_path / "view.html")
    page, errors, _ = _open(browser, path)
    before = page.screenshot()
    lit0 = page.evaluate("splidarView.litPixels()")
    page.mouse.move(500, 300)
    page.mouse.down()
    page.mouse.move(600, 340, steps=4)
    page.mouse.up()
    page.wait_for_function("() => window.splidarView.frames > 3")
    assert page.screenshot() != before
    page.mouse.wheel(0, -400)  # zoom in: the points spread over more pixels
    page.wait_for_timeout(100)
    assert page.evaluate("splidarView.litPixels()") > lit0
    assert errors == []
    page.close()


def test_view_in_browser_one_million_points_one_draw_call(browser, tmp_path):
    """1e6 points: loads, one draw call (timings: benchmarks/bench_view.py)."""
    side = 1000
    r, c = np.divmod(np.arange(side * side), side)
    depth = 200 + 30 * np.sin(r / 50.0) * np.cos(c / 70.0)
    p = PointSet(row=r, col=c, depth_bin=depth, image_shape=(side, side), layer=(r % 7 == 0) * 1)
    path = write_view(p, tmp_path / "big.html")
    page, errors, requests = _open(browser, path)
    assert page.evaluate("[splidarView.drawn, splidarView.drawCalls]") == [side * side, 1]
    assert _lit_fraction(page.screenshot()) > 0.05
    assert errors == [] and len(requests) == 1
    page.close()
    shutil.rmtree(tmp_path, ignore_errors=True)


def test_view_in_browser_empty_result_loads_without_error(browser, tmp_path):
    z = np.zeros(0, np.int64)
    p = PointSet(row=z, col=z, depth_bin=z * 1.0, image_shape=(4, 5), layer=z, label=z)
    page, errors, requests = _open(browser, write_view(p, tmp_path / "empty.html"))
    state = page.evaluate("[splidarView.nPoints, splidarView.drawn, splidarView.litPixels()]")
    assert state == [0, 0, 0]
    assert errors == [] and len(requests) == 1
    page.close()
