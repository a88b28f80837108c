"""How far a one-surface change of the detection moves ``reconstruct``'s labels (Art).

The label sampler draws its random numbers for what a surface is (pixel, rank by depth;
a link by its two surfaces, a cluster by its smallest key), so removing one surface of
a detection should change the labels near it only (benchmarks/README.md, "keyed29,
session 21"). On the Art scene (:func:`splidar.scenes.art_scene`, PPP 4, SBR 1,
simulation seed 0, uniform and decaying background, ``detect`` once per background):

- label accuracy, F_true and IAE (tau 4 mm) of ``reconstruct(det, rng=r)`` for r = 0-5
  (the sampler's own spread), and the median time of ``reconstruct`` and of its
  classification;
- ``--removals N`` single surfaces removed (the surface nearest the image's centre, the
  one nearest its corner (5, 5), then N - 2 at random, ``rng`` 5): the fraction of the
  other surfaces whose label changed (``rng`` 0), over all of them and beyond 10, 20 and
  40 pixels of the removed one, and the largest distance of a change.

Usage::

    python benchmarks/bench_label_locality.py                 # about 3 minutes
    python benchmarks/bench_label_locality.py --removals 12 --seeds 0
    python benchmarks/bench_label_locality.py --data ../shared/data

Never downloads anything: without ``<data>/middlebury-art`` it says so and exits.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import splidar
from splidar.metrics import evaluate
from splidar.scenes import art_scene


def without(det, i: int):
    """``det`` without surface ``i``, and the mask of the kept surfaces."""
    s = det.surfaces
    S = len(s)
    keep = np.arange(S) != i
    rep = {}
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == S:
            rep[f.name] = v[keep]
    return dataclasses.replace(det, surfaces=dataclasses.replace(s, **rep)), keep


def _accuracy(det, truth, library, seeds, bg: str) -> None:
    accs, tot, cls = [], [], []
    for r in seeds:
        rec = splidar.reconstruct(det, library=library, rng=r)
        m = evaluate(rec.points, truth, tau_m=0.004)
        accs.append(m.label_accuracy)
        tot.append(rec.timings["total"])
        cls.append(rec.timings["classify"])
        print(f"{bg} rng {r}: label accuracy {m.label_accuracy:.4f}, F_true {m.f_true:.4f}, "
              f"IAE {m.iae:.4f}, {tot[-1]:.2f} s (classify {cls[-1]:.2f})", flush=True)  # fmt: skip
    sd = statistics.stdev(accs) if len(accs) > 1 else 0.0
    print(f"{bg}: label accuracy mean {np.mean(accs):.4f} sd {sd:.4f}; reconstruct median "
          f"{np.median(tot):.2f} s, classify {np.median(cls):.2f} s", flush=True)  # fmt: skip


def _removals(det, library, n: int, bg: str) -> None:
    s = det.surfaces
    rows, cols = s.image_shape
    near = [(rows // 2, cols // 2), (5, 5)]
    picks = [int(np.argmin((s.row - r) ** 2 + (s.col - c) ** 2)) for r, c in near]
    picks += [int(i) for i in np.random.default_rng(5).choice(len(s), max(n - 2, 0), False)]
    base = splidar.reconstruct(det, library=library, rng=0).points.label
    far = []
    for i in picks[:n]:
        smaller, keep = without(det, i)
        lab = splidar.reconstruct(smaller, library=library, rng=0).points.label
        dist = np.hypot(s.row[keep] - s.row[i], s.col[keep] - s.col[i])
        ch = base[keep] != lab
        far.append(float(ch[dist > 40].mean()))
        parts = ", ".join(f"> {R} px {ch[dist > R].mean():.4f}" for R in (10, 20, 40))
        reach = f"{dist[ch].max():.0f}" if ch.any() else "-"
        print(f"{bg} surface {i} at ({s.row[i]}, {s.col[i]}): labels changed {ch.mean():.4f} "
              f"({ch.sum()}), {parts}; farthest change {reach} px", flush=True)  # fmt: skip
    far = np.array(far)
    print(f"{bg}: {np.count_nonzero(far)} of {far.size} removals change a label beyond 40 px; "
          f"mean fraction {far.mean():.4f}, largest {far.max():.4f}", flush=True)  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data", type=Path, default=Path(__file__).parents[1] / ".." / "shared" / "data"
    )
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(6)))
    ap.add_argument("--removals", type=int, default=4)
    ap.add_argument("--backgrounds", nargs="*", default=["uniform", "decaying"])
    args = ap.parse_args(argv)
    folder = args.data / "middlebury-art"
    if not folder.is_dir():
        sys.exit(f"no {folder}: this benchmark needs the Middlebury Art scene (see data/README)")
    scene = art_scene(folder)
    for bg in args.backgrounds:
        t = time.perf_counter()
        sim = scene.simulate(ppp=4.0, sbr=1.0, background=bg, rng=0)
        det = splidar.detect(sim.cube)
        print(f"{bg}: {len(det.surfaces)} surfaces ({time.perf_counter() - t:.0f} s)", flush=True)
        if args.seeds:
            _accuracy(det, sim.truth, scene.library, args.seeds, bg)
        if args.removals:
            _removals(det, scene.library, args.removals, bg)


if __name__ == "__main__":
    main()
