"""Tests of benchmarks/bench_lone_far.py (far40, session 27): the lone far wrong depths'
record (:func:`characterise`), where a true depth left the table (:func:`where_lost`) and
the per-pixel rules' screen (:func:`screen_rules`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from conftest import load_benchmark as _load

from splidar.detection._result import Background
from splidar.irf import gaussian_irf
from splidar.metrics import PointSet

bench = _load("bench_lone_far")
IRF = gaussian_irf(3.0)[None, :]
T, TRUE_D, FAR_D = 200, 60, 120


def _lone_far_detection() -> dict:
    """5 x 5 pixels truly at TRUE_D, each detected there with 4 photons on it, except the
    centre: its own photons (3) lie at FAR_D, where it is detected alone."""
    R = C = 5
    half = IRF.shape[1] // 2
    counts = np.zeros((R, C, 1, T), np.uint16)
    counts[:, :, 0, TRUE_D - 1 : TRUE_D + 2] = [1, 2, 1]
    counts[2, 2, 0, :] = 0
    counts[2, 2, 0, FAR_D - 1 : FAR_D + 2] = [1, 1, 1]
    assert half > 1
    row, col = (a.ravel() for a in np.mgrid[:R, :C])
    depth = np.where((row == 2) & (col == 2), FAR_D, TRUE_D).astype(np.float64)
    n = row.size
    s = SimpleNamespace(row=row, col=col, depth_bin=depth, image_shape=(R, C), n_slots=2,
                        stage=np.zeros(n, np.int8), moved_by=np.full(n, -1, np.int8),
                        photons=np.where(depth == FAR_D, 3.0, 4.0)[:, None])  # fmt: skip
    truth = PointSet(row=row, col=col, depth_bin=np.full(n, float(TRUE_D)), image_shape=(R, C))
    bg = Background(spatial=np.full((R, C, 1), 0.01, np.float32),
                    temporal=np.full((1, T), 0.01, np.float32))  # fmt: skip
    return dict(surfaces=s, background=bg, irf=IRF, half=1, counts=counts, truth=truth)


def test_characterise_records_the_lone_far_depth_and_its_counts():
    recs = bench.characterise(_lone_far_detection())
    assert len(recs) == 1
    x = recs[0]
    assert (x["r"], x["c"], x["d"], x["t"]) == (2, 2, FAR_D, TRUE_D)
    assert x["stage"] == "map" and x["moved"] == -1
    assert x["Ld"] > 2 and x["Lt"] == 0  # its own photons lie at d, none at t
    assert abs(x["dmax"] - FAR_D) <= 1
    assert (x["n_d"], x["n_t"], x["nb_true_t"]) == (0, 8, 8)


def test_screen_rules_counts_the_lone_surfaces_and_moves_none_against_the_counts():
    n = bench.screen_rules(_lone_far_detection())
    assert n["lone far"] == 1 and n["lone true"] == 24
    assert n["lone far beside another depth"] == 1 and n["lone true beside another depth"] == 8
    # the centre's own counts favour its far depth: no margin moves it; the neighbours'
    # own counts favour their (true) depth: none is moved off
    assert not any(k.startswith("move") and v for k, v in n.items())
    assert n["drop L(d) = 0, >= 0 nb at another depth: far"] == 0


def test_where_lost_names_the_step():
    def snap(rows, cols, depths, keep):
        return dict(row=np.array(rows), col=np.array(cols), depth_bin=np.array(depths, float),
                    keep=np.array(keep))  # fmt: skip

    h = {"map": snap([0, 0], [0, 1], [50, 50], [True, False]),
         "a": snap([0, 0], [0, 1], [50, 50], [True, False]),
         "b": snap([0, 0], [0, 1], [50, 50], [False, False])}  # fmt: skip
    assert bench.where_lost(h, 0, 0, 51.0) == "removed by b"
    assert bench.where_lost(h, 0, 1, 49.0) == "rejected at the map"
    assert bench.where_lost(h, 0, 0, 60.0) == "not a map candidate"
    h["b"] = h["a"]
    assert bench.where_lost(h, 0, 0, 50.0) == "kept through stage 5"
