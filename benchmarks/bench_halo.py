"""False surfaces beside bright objects: where they are and which stage makes them.

Runs ``splidar.detect`` on an object of 3 materials (4 wavelengths) in front of empty
pixels (``benchmarks/paper``'s ``object_scene``, 64 x 64, SBR 1.3, PPP 4 and 50) and on
the detection benchmark's headline cells (single surface PPP 4, SBR 0.25 and PPP 1,
SBR 1; net scene PPP 10, SBR 1 and PPP 1, SBR 1; uniform and decaying background), and
prints per cell F_true (tau = 3 bins), the false surfaces (count on the pixel count), the stage that
keeps each false surface (``Surfaces.stage``) and, on the object, the surfaces in empty
pixels farther than 2 pixels from it. Compare two versions by running the script under
each (same seeds, same cubes)::

    python benchmarks/bench_halo.py --seeds 0 1 --json new.json
    PYTHONPATH=/path/to/old/src python benchmarks/bench_halo.py --seeds 0 1 --json old.json

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from splidar.detection import STAGES, detect
from splidar.metrics import evaluate, match_points
from splidar.scenes import single_surface_scene, two_layer_scene

sys.path.insert(0, str(Path(__file__).resolve().parent / "paper"))
from _experiments import object_scene  # noqa: E402

TAU = 3.0
CELLS = (
    ("single", "uniform", 4, 0.25),
    ("single", "decaying", 4, 0.25),
    ("two_layer", "uniform", 10, 1.0),
    ("two_layer", "decaying", 10, 1.0),
    ("single", "uniform", 1, 1.0),
    ("two_layer", "uniform", 1, 1.0),
    ("object", "uniform", 4, 1.3),
    ("object", "uniform", 50, 1.3),
)


def run_cell(scenes, name, bg, ppp, sbr, rng) -> dict:
    if name == "object":
        sim = scenes[name].simulate(ppp=ppp, sbr=sbr, rng=rng)
    else:
        sim = scenes[name].simulate(ppp=ppp, sbr=sbr, background=bg, rng=rng)
    t0 = time.perf_counter()
    det = detect(sim.cube, rng=0)
    sec = time.perf_counter() - t0
    pts, truth = det.points, sim.truth
    m = evaluate(pts, truth, tau=TAU)
    false = np.asarray(match_points(pts, truth, tau=TAU).unmatched_est, np.int64)
    stage = det.surfaces.stage[false]
    R, C = truth.image_shape
    occupied = np.zeros((R, C), bool)
    occupied[truth.row, truth.col] = True
    dist = ndimage.distance_transform_edt(~occupied)[pts.row, pts.col]
    return dict(
        scene=name, bg=bg, ppp=ppp, sbr=sbr, n_pixels=R * C, n_true=len(truth),
        f_true=round(float(m.f_true), 4), n_false=int(false.size),
        false_by_stage={STAGES[k]: int(np.sum(stage == k)) for k in np.unique(stage)},
        empty_beyond_2px=int(np.sum(dist > 2)), seconds=round(sec, 2),
    )  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--json", help="also write the rows to this JSON file")
    args = ap.parse_args(argv)
    scenes = {
        "single": single_surface_scene((64, 64), n_bins=200),
        "two_layer": two_layer_scene((64, 64), n_bins=200),
        "object": object_scene((64, 64)),
    }
    rows = []
    print("seed scene      bg        PPP   SBR  F_true  false/pixels  by stage; empty > 2 px")
    for seed in args.seeds:
        for i, cell in enumerate(CELLS):
            r = dict(seed=seed, **run_cell(scenes, *cell, np.random.default_rng([seed, i])))
            rows.append(r)
            print(
                f"{seed:4d} {r['scene']:10s} {r['bg']:9s} {r['ppp']:4g} {r['sbr']:5g} "
                f"{r['f_true']:.4f} {r['n_false']:5d}/{r['n_pixels']:<6d} "
                f"{r['false_by_stage']}; {r['empty_beyond_2px'] if cell[0] == 'object' else '-'}",
                flush=True,
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
