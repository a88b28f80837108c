"""How wide a margin a reconstruction tile needs (docs/distributed.md, issue #16).

The reconstruction couples surfaces only through links between 4-neighbour pixels, so a
tile of the image reconstructed with a margin of ``m`` pixels differs from the whole
image's reconstruction by an amount that decays with ``m`` (the bound in
``docs/distributed.md``). This measures it with the public API only: the detection's
surfaces are cut to a strip of rows (the core) widened by ``m`` rows on each side,
reconstructed on their own with the whole image's hyperparameters fixed (``alpha``,
``upsilon``), and the core's intensities and labels compared with the whole image's.

Scene: ``synthetic_detection`` (true surfaces, 4 wavelengths, 3 materials, PPP and SBR
as given), so the figures are about the cut alone, not about detection.

Usage::

    python benchmarks/bench_tile_margin.py                 # 96 x 64, PPP 10, SBR 1
    python benchmarks/bench_tile_margin.py --ppp 3 --sbr 0.5
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

import splidar
from splidar.reconstruction._synthetic import synthetic_detection


def _cut(det, keep: np.ndarray):
    s = det.surfaces
    n = len(s)
    fields = {}
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == n:
            fields[f.name] = v[keep]
    return dataclasses.replace(det, surfaces=dataclasses.replace(s, **fields))


def _by_surface(rec):
    p = rec.points
    key = p.row.astype(np.int64) * 100_003 + p.col.astype(np.int64)
    order = np.lexsort((p.depth_bin, key))
    return key[order], p.intensity[order], p.label[order]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=96)
    ap.add_argument("--cols", type=int, default=64)
    ap.add_argument("--ppp", type=float, default=10.0)
    ap.add_argument("--sbr", type=float, default=1.0)
    ap.add_argument("--core", type=int, default=16, help="core rows per tile")
    ap.add_argument("--margins", type=int, nargs="+", default=[0, 1, 2, 4, 8, 16, 24])
    args = ap.parse_args(argv)
    det, _ = synthetic_detection(
        shape=(args.rows, args.cols), n_wavelengths=4, n_classes=3, ppp=args.ppp,
        sbr=args.sbr, variability=0.2, rng=0,
    )  # fmt: skip
    full = splidar.reconstruct(det, library=det.library, rng=0)
    hyper = dict(full.hyperparameters)
    fixed = {k: hyper[k] for k in ("alpha", "upsilon") if k in hyper}
    full = splidar.reconstruct(det, library=det.library, rng=0, **fixed)
    print(
        f"{args.rows} x {args.cols} px, {len(det.surfaces)} surfaces, PPP {args.ppp}, SBR "
        f"{args.sbr}; core rows [{args.rows // 2 - args.core // 2}, "
        f"{args.rows // 2 + args.core // 2}); hyperparameters fixed: {sorted(fixed)}"
    )
    r0 = args.rows // 2 - args.core // 2
    r1 = r0 + args.core
    k_full, i_full, l_full = _by_surface(full)
    core_full = (k_full // 100_003 >= r0) & (k_full // 100_003 < r1)
    print(f"{'margin':>6} {'max rel. err':>12} {'median':>9} {'labels differ':>13}")
    for m in args.margins:
        rows = det.surfaces.row
        sub = _cut(det, (rows >= r0 - m) & (rows < r1 + m))
        rec = splidar.reconstruct(sub, library=det.library, rng=0, **fixed)
        k, i, lab = _by_surface(rec)
        core = (k // 100_003 >= r0) & (k // 100_003 < r1)
        assert np.array_equal(k[core], k_full[core_full])
        a, b = i[core], i_full[core_full]
        rel = np.abs(a - b) / np.maximum(np.abs(b), 1e-9)
        n_lab = int(np.count_nonzero(lab[core] != l_full[core_full]))
        print(f"{m:>6} {rel.max():>12.2e} {np.median(rel):>9.1e} {n_lab:>13}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
