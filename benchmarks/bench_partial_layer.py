"""A partly transmissive layer over part of the scene only: does stage 5g keep it?

Stage 5g (``passes "unlayered"``) removes a pixel's weak further surfaces where the image
shows no second layer. A net or camouflage in front of one part of a large scene is the
case where a whole-image decision can miss the layer (few second surfaces detected at
low flux); stage 5g then also tests the layer in a window about each pixel. This bench
puts a net scene (``two_layer_scene``, P x P pixels) into the corner of a single-surface
scene (128 x 128), both simulated alike (T = 200, Gaussian IRF FWHM 3 bins, SBR 0.25,
uniform background), and scores the detection with and without stage 5g inside the
patch (against the net's truth) and outside it (against the single scene's).

Usage::

    python benchmarks/bench_partial_layer.py            # P 24, 32, 48; PPP 1, 4, 10; 2 seeds
    python benchmarks/bench_partial_layer.py --ppp 1 --seeds 0 1 2

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse

import numpy as np

from splidar import Cube, PointSet, detect
from splidar.detection import PASSES
from splidar.metrics import evaluate
from splidar.scenes import single_surface_scene, two_layer_scene

SIDE, N_BINS, SBR, TAU = 128, 200, 0.25, 3.0


def _inside(pts, p: int, inside: bool) -> PointSet:
    m = (pts.row < p) & (pts.col < p)
    m = m if inside else ~m
    shape = (p, p) if inside else (SIDE, SIDE)
    return PointSet(row=pts.row[m], col=pts.col[m], depth_bin=pts.depth_bin[m], image_shape=shape)


def run_case(p: int, ppp: float, seed: int) -> dict:
    """Detection with and without stage 5g of one composed cube: F_true and false
    surfaces inside the net patch and outside it, and the candidates 5g removed."""
    base = single_surface_scene((SIDE, SIDE), n_bins=N_BINS).simulate(
        ppp=ppp, sbr=SBR, background="uniform", rng=seed
    )
    net = two_layer_scene((p, p), n_bins=N_BINS).simulate(
        ppp=ppp, sbr=SBR, background="uniform", rng=100 + seed
    )
    counts = np.array(base.cube.counts)
    counts[:p, :p] = np.asarray(net.cube.counts)
    cube = Cube(counts, base.cube.irf, bin_width_ps=base.cube.bin_width_ps)
    out = {}
    for name, passes in (("with", PASSES), ("without", [q for q in PASSES if q != "unlayered"])):
        det = detect(cube, rng=0, passes=passes)
        m_in = evaluate(_inside(det.points, p, True), net.truth, tau=TAU)
        m_out = evaluate(_inside(det.points, p, False), _inside(base.truth, p, False), tau=TAU)
        removed = {r.stage: r.removed for r in det.provenance}.get("unlayered", 0)
        out[name] = (m_in.f_true, m_in.f_false, m_out.f_true, m_out.f_false, removed)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, nargs="+", default=[24, 32, 48])
    ap.add_argument("--ppp", type=float, nargs="+", default=[1.0, 4.0, 10.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = ap.parse_args(argv)
    print("patch  PPP  seed | with 5g: patch F_true / false, rest F_true / false, removed "
          "| without 5g")  # fmt: skip
    for p in args.sides:
        for ppp in args.ppp:
            for seed in args.seeds:
                r = run_case(p, ppp, seed)
                w, o = r["with"], r["without"]
                print(
                    f"{p:3d}x{p:<3d} {ppp:4g} {seed:4d} | {w[0]:.4f} / {w[1]:4d}, {w[2]:.4f} / "
                    f"{w[3]:4d}, {w[4]:4d} | {o[0]:.4f} / {o[1]:4d}, {o[2]:.4f} / {o[3]:4d}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
