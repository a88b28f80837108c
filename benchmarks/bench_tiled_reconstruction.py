"""Reconstruction on overlapping strips against the in-memory run (issue #16).

A detection of a Dask cube is reconstructed on strips of rows (``reconstruction/_tiled.py``,
``docs/distributed.md``). This measures, on a synthetic detection (true surfaces, 4
wavelengths, 3 materials, spectral variability 0.2):

- the cut alone: one class (no label sampling), largest relative intensity error;
- with 3 classes: label agreement with the in-memory run (all labels, and those of
  confidence >= 0.9), relative intensity error of the surfaces whose label agrees, and the
  same figures between two in-memory runs with different seeds (the yardstick: the label
  sampler's own randomness);
- wall time: in memory, strips on Dask's threads, strips on LocalClusters of 1 and 2
  worker processes (one thread each).

Usage::

    python benchmarks/bench_tiled_reconstruction.py                      # 384 x 192, PPP 10
    python benchmarks/bench_tiled_reconstruction.py --ppp 2 --sbr 0.5 --core 48
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

import splidar
from splidar._memory import reconstruct_peak_bytes
from splidar.reconstruction import _tiled
from splidar.reconstruction._synthetic import synthetic_detection


def _compare(a, b) -> str:
    pa, pb = a.points, b.points
    same = pa.label == pb.label
    hi = pa.label_confidence >= 0.9
    rel = (np.abs(pb.intensity - pa.intensity) / np.abs(pa.intensity)).max(axis=1)
    r = rel[same]
    srel = np.abs(pb.intensity_std / pa.intensity_std - 1).max(axis=1)[same]
    return (
        f"labels agree {same.mean():.4f} (conf >= 0.9: {same[hi].mean():.4f} of "
        f"{hi.mean():.2f}); same label: rel. error median {np.median(r):.1e}, 99 % "
        f"{np.quantile(r, 0.99):.1e}, within 1e-2 {np.mean(r < 1e-2):.4f}; std median "
        f"{np.median(srel):.1e}"
    )


def _timed(f):
    t = time.perf_counter()
    out = f()
    return out, time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=384)
    ap.add_argument("--cols", type=int, default=192)
    ap.add_argument("--ppp", type=float, default=10.0)
    ap.add_argument("--sbr", type=float, default=1.0)
    ap.add_argument("--core", type=int, default=64, help="core rows per strip")
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    args = ap.parse_args(argv)
    det, _ = synthetic_detection(
        shape=(args.rows, args.cols), n_wavelengths=4, n_classes=3, ppp=args.ppp,
        sbr=args.sbr, variability=0.2, rng=0,
    )  # fmt: skip
    lazy = dataclasses.replace(det, options={**det.options, "dask": True})
    S = len(det.surfaces)
    per_row = S / args.rows
    _tiled.TILE_BYTES = int(
        reconstruct_peak_bytes(1, 4, 3) * per_row * (args.core + 2 * _tiled.MARGIN + 0.5)
    )
    lib = det.library
    print(
        f"{args.rows} x {args.cols} px, {S} surfaces, PPP {args.ppp}, SBR {args.sbr}; strips "
        f"of {args.core} core rows + {_tiled.MARGIN} each side"
    )
    splidar.reconstruct(det, library=lib, rng=0)  # compile
    one_a = splidar.reconstruct(det, classes="one")
    one_b = splidar.reconstruct(lazy, classes="one")
    rel = np.abs(one_b.points.intensity / one_a.points.intensity - 1).max()
    n_strips = len(one_b.hyperparameters["tiles"]["cores"])
    print(f"one class ({n_strips} strips): largest relative intensity error {rel:.1e}")
    a, t_mem = _timed(lambda: splidar.reconstruct(det, library=lib, rng=0))
    a1 = splidar.reconstruct(det, library=lib, rng=1)
    b, t_thr = _timed(lambda: splidar.reconstruct(lazy, library=lib, rng=0))
    print(f"3 classes, strips vs memory:  {_compare(a, b)}")
    print(f"3 classes, seed 1 vs seed 0:  {_compare(a, a1)}")
    print(
        f"alpha memory {np.round(a.hyperparameters['alpha'][:, 0], 1)}, strips "
        f"{np.round(b.hyperparameters['alpha'][:, 0], 1)}"
    )
    print(f"time: in memory {t_mem:.2f} s; strips on threads {t_thr:.2f} s")
    from distributed import Client, LocalCluster

    for n in args.workers:
        with (
            LocalCluster(n_workers=n, threads_per_worker=1, dashboard_address=":0") as cluster,
            Client(cluster),
        ):
            splidar.reconstruct(lazy, library=lib, rng=0)  # workers load the kernels
            c, t = _timed(lambda: splidar.reconstruct(lazy, library=lib, rng=0))
        same = all(
            np.array_equal(getattr(c.points, k), getattr(b.points, k))
            for k in ("intensity", "intensity_std", "label")
        )
        print(f"LocalCluster {n} worker(s): {t:.2f} s; identical to the threads' run: {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
