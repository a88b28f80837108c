"""Issue #15, point 5: the F_true / false-surface trade-off of detect's two levels.

Sweeps ``pfa`` (the voxel false-alarm rate of the 3D map) and ``surface_pfa`` (the
per-pixel false-surface rate of the evidence threshold) over the cells of
``bench_false_surfaces.py`` (96 x 80 = 7,680 pixels, T = 200, Gaussian IRF FWHM 3 bins,
tau = 3 bins):

* the issue's cells: single surface, PPP 4, SBR 0.25, uniform and decaying background
  (target F_true >= 0.975 with <= 50 false surfaces);
* other cells: single surface PPP 1, SBR 1 and PPP 10, SBR 0.25 (uniform), the net
  (``two_layer_scene``) PPP 4, SBR 0.25 uniform with its false surfaces beside the
  strands' edges per true surface (target < 0.05), and the transmissive sheet PPP 4,
  SBR 0.25 uniform.

Each cell is drawn once per seed (the same cubes for every operating point) and
detected with ``detect(cube, rng=0, pfa=..., surface_pfa=...)``.

Usage::

    python benchmarks/bench_operating_point.py --seeds 0 1 [--json out.json]
    python benchmarks/bench_operating_point.py --seeds 0 --points 1e-3:0.01 1e-3:0.001

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from splidar.detection import detect
from splidar.scenes import single_surface_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_false_surfaces import N_BINS, SHAPE, net_scene, run_layer, sheet_scene  # noqa: E402

from splidar.metrics import evaluate, match_points  # noqa: E402

TAU = 3.0
#: (pfa, surface_pfa); the first is detect's default
POINTS = (
    (1e-3, 0.01), (1e-3, 0.005), (1e-3, 0.002), (1e-3, 0.001), (1e-3, 0.0003),
    (3e-4, 0.01), (3e-4, 0.001), (1e-4, 0.01), (1e-4, 0.001), (3e-3, 0.01),
)  # fmt: skip
SINGLE_CELLS = (
    ("uniform", 4, 0.25), ("decaying", 4, 0.25), ("uniform", 1, 1.0), ("uniform", 10, 0.25),
)  # fmt: skip


def run_point(sims, opts) -> list[dict]:
    rows = []
    for key, sim, sheet, name in sims:
        if sheet is None:
            det = detect(sim.cube, rng=0, **opts)
            m = evaluate(det.points, sim.truth, tau=TAU)
            n_false = len(match_points(det.points, sim.truth, tau=TAU).unmatched_est)
            rows.append(dict(cell=key, f_true=float(m.f_true), n_false=int(n_false)))
        else:
            rows.append(dict(cell=key, **layer_row(sim, sheet, opts, name)))
    return rows


def layer_row(sim, sheet, opts, scene_name) -> dict:
    """run_layer's figures on an already drawn cube (same code path)."""

    class _Fixed:  # a scene whose simulate returns the drawn cube
        name = scene_name

        @staticmethod
        def simulate(**_):
            return sim

    r = run_layer(_Fixed, sheet, "-", 0, 0, None, opts)
    return dict(f_true=r["f_true"], n_false=r["n_false"], edge_per_true=r["edge_per_true"])


def draw(seed: int):
    out = []
    scene = single_surface_scene(SHAPE, n_bins=N_BINS)
    for i, (bg, ppp, sbr) in enumerate(SINGLE_CELLS):
        sim = scene.simulate(ppp=ppp, sbr=sbr, background=bg, rng=np.random.default_rng([seed, i]))
        out.append((f"single {bg} PPP {ppp:g} SBR {sbr:g}", sim, None, "single"))
    for j, (scene, mask) in enumerate((sheet_scene(), net_scene())):
        rng = np.random.default_rng([seed, 100 * (j + 1)])
        sim = scene.simulate(ppp=4, sbr=0.25, background="uniform", rng=rng)
        out.append((f"{scene.name} uniform PPP 4 SBR 0.25", sim, mask, scene.name))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--points", nargs="+", help="pfa:surface_pfa pairs (default: a grid)")
    ap.add_argument("--json", help="also write the rows to this JSON file")
    args = ap.parse_args(argv)
    points = [tuple(float(v) for v in p.split(":")) for p in args.points] if args.points else POINTS
    rows = []
    draws = {seed: draw(seed) for seed in args.seeds}
    for pfa, spfa in points:
        t0 = time.perf_counter()
        for seed in args.seeds:
            for r in run_point(draws[seed], dict(pfa=pfa, surface_pfa=spfa)):
                rows.append(dict(pfa=pfa, surface_pfa=spfa, seed=seed, **r))
        sel = [r for r in rows if r["pfa"] == pfa and r["surface_pfa"] == spfa]
        for cell in dict.fromkeys(r["cell"] for r in sel):
            c = [r for r in sel if r["cell"] == cell]
            f = np.mean([r["f_true"] for r in c])
            n = np.mean([r["n_false"] for r in c])
            e = np.mean([r.get("edge_per_true", np.nan) for r in c])
            edge = f", edge/true {e:.4f}" if np.isfinite(e) else ""
            print(
                f"pfa {pfa:g} surface_pfa {spfa:g}  {cell:32s} F_true {f:.4f} false {n:6.1f}{edge}",
                flush=True,
            )
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
