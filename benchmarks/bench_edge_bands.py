"""Issue #15, point 5: stage 7b, the bands beside depth edges decided together.

The wrong depths of the single-surface cells (``bench_false_surfaces.py``; benchmarks/
README.md "false24, session 17") are mostly dim pixels of a region A beside a depth edge
that took the neighbouring region B's depth (the multiscale boxes pool B's returns into
them). Per pixel the own counts cannot decide; stage 7b (``detection/_7b_edge_bands.py``)
decides the band at once: a Potts labelling (A or B) of the single-surface pixels
within the largest box's half-width of an A/B boundary, data costs from the own counts
(profile log-likelihood ratio at each region's local plane), the Potts weight measured
on the detection, solved by a minimum cut; a pair's relabelling kept only when the own
counts of the pixels it moves favour it in sum.

Each cube is detected once without the stage (``passes`` without ``"edge_bands"``); the
stage's depth rule (``band_depths``) then runs on its surfaces, so before and after
are the same detection: F_true, false surfaces (and those within 2 pixels of a layer's
edges), and per moved surface whether the move fixed a false one or moved a true one
off. Cells: issue #15's single-surface cells (PPP 4, SBR 0.25, uniform and decaying)
and ``bench_false_surfaces.py``'s layer cells (sheet and net; uniform PPP 4, decaying
PPP 4, uniform PPP 10), with their seeds.

Usage::

    python benchmarks/bench_edge_bands.py --seeds 0 1 2 [--only single|layer] [--cache DIR]

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np
from bench_false_surfaces import EDGE_PX, LAYER, net_scene, sheet_scene
from scipy import ndimage

from splidar.detection import PASSES, detect
from splidar.detection._7b_edge_bands import band_depths
from splidar.detection._filters import irf_fwhm
from splidar.metrics import PointSet, evaluate, match_points
from splidar.scenes import single_surface_scene

TAU = 3.0
SHAPE = (96, 80)
N_BINS = 200
SINGLE = (("uniform", 4, 0.25), ("decaying", 4, 0.25))


def _matched(pts, truth):
    """Per estimated point: matched to a true surface (within TAU, ``match_points``)."""
    ok = np.ones(len(pts), bool)
    ok[np.asarray(match_points(pts, truth, tau=TAU).unmatched_est, np.int64)] = False
    return ok


def _detected(name, seed, rng_key, cell, cache):
    """The detection of one cube (read from / written to ``cache``)."""
    path = None if cache is None else Path(cache) / f"det_{name}_{seed}_{rng_key[1]}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    if name == "single":
        scene, band = single_surface_scene(SHAPE, n_bins=N_BINS), None
    else:
        scene, band = (sheet_scene if name == "sheet" else net_scene)()
    sim = scene.simulate(ppp=cell[1], sbr=cell[2], background=cell[0],
                         rng=np.random.default_rng(rng_key))  # fmt: skip
    # the detection before stage 7b: its depth rule runs on these surfaces
    det = detect(sim.cube, rng=0, passes=tuple(p for p in PASSES if p != "edge_bands"))
    d = dict(surfaces=det.surfaces, background=det.background, irf=np.asarray(det.irf),
             half=int(max(det.scales)) // 2, counts=np.asarray(sim.cube.counts),
             truth=sim.truth, band=band)  # fmt: skip
    if path is not None:
        path.write_bytes(pickle.dumps(d))
    return d


def _edge_false(pts, truth, mask) -> int:
    """False surfaces within EDGE_PX of the layer's edges (bench_false_surfaces)."""
    if mask is None:
        return 0
    dist_out = ndimage.distance_transform_edt(~mask)
    dist_in = ndimage.distance_transform_edt(mask)
    band = ((dist_out > 0) & (dist_out <= EDGE_PX)) | ((dist_in > 0) & (dist_in <= EDGE_PX))
    false = ~_matched(pts, truth)
    return int(np.sum(band[pts.row[false], pts.col[false]]))


def run(name, seed, rng_key, cell, cache) -> dict:
    """Before / after stage 7b's depth rule on one cube (see the module)."""
    d = _detected(name, seed, rng_key, cell, cache)
    surfaces, counts, truth = d["surfaces"], d["counts"], d["truth"]
    pts = PointSet(
        row=surfaces.row, col=surfaces.col, depth_bin=surfaces.depth_bin,
        image_shape=surfaces.image_shape, intensity=surfaces.photons, layer=surfaces.slot,
    )  # fmt: skip
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    t0 = time.perf_counter()
    depth, moved, beta = band_depths(
        surfaces, counts, d["background"], fwhm=irf_fwhm(irf), irf=irf, half=d["half"]
    )
    sec = time.perf_counter() - t0
    p1 = PointSet(
        row=pts.row, col=pts.col, depth_bin=depth, image_shape=pts.image_shape,
        intensity=pts.intensity, layer=pts.layer,
    )  # fmt: skip
    ok0, ok1 = _matched(pts, truth), _matched(p1, truth)
    r = dict(
        scene=name, seed=seed, bg=cell[0], ppp=cell[1], beta=beta,
        f0=evaluate(pts, truth, tau=TAU).f_true, f1=evaluate(p1, truth, tau=TAU).f_true,
        n0=int((~ok0).sum()), n1=int((~ok1).sum()), e0=_edge_false(pts, truth, d.get("band")),
        e1=_edge_false(p1, truth, d.get("band")), moved=int(moved.size),
        fixed=int(np.sum(~ok0[moved] & ok1[moved])), broke=int(np.sum(ok0[moved] & ~ok1[moved])),
        seconds=sec,
    )  # fmt: skip
    edge = f"  edge false {r['e0']:3d} -> {r['e1']:3d}" if d.get("band") is not None else ""
    print(
        f"{name:6s} {seed:2d} {cell[0]:9s} PPP {cell[1]:2g} beta {beta:4.2f}  F_true "
        f"{r['f0']:.4f} -> {r['f1']:.4f}  false {r['n0']:3d} -> {r['n1']:3d}{edge}  moved "
        f"{r['moved']:3d}: fixed {r['fixed']:3d}, true moved off {r['broke']:3d}  ({sec:.1f} s)",
        flush=True,
    )
    return r


def _mean(rows, key) -> float:
    return float(np.mean([r[key] for r in rows]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--cache", help="a directory keeping each cube's detection")
    ap.add_argument("--only", choices=("single", "layer"), help="run one of the two")
    args = ap.parse_args(argv)
    rows = []
    for seed in args.seeds:
        if args.only != "layer":
            for i, cell in enumerate(SINGLE):
                rows.append(run("single", seed, [seed, i], cell, args.cache))
        if args.only != "single":
            for j, name in enumerate(("sheet", "net")):
                for i, cell in enumerate(LAYER):
                    key = [seed, 100 * (j + 1) + i]
                    rows.append(run(name, seed, key, cell, args.cache))
    for name in ("single", "sheet", "net"):
        for bg, ppp in (("uniform", 4), ("decaying", 4), ("uniform", 10)):
            sel = [r for r in rows if (r["scene"], r["bg"], r["ppp"]) == (name, bg, ppp)]
            if sel:
                print(
                    f"mean {name:6s} {bg:9s} PPP {ppp:2d}: F_true {_mean(sel, 'f0'):.4f} -> "
                    f"{_mean(sel, 'f1'):.4f}, false {_mean(sel, 'n0'):.1f} -> "
                    f"{_mean(sel, 'n1'):.1f}, at a layer's edges {_mean(sel, 'e0'):.1f} -> "
                    f"{_mean(sel, 'e1'):.1f}; fixed {_mean(sel, 'fixed'):.1f}, true moved off "
                    f"{_mean(sel, 'broke'):.1f}"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
