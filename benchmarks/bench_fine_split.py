"""The fine split (``_4_map.SPLIT_Z``) on the real files: surfaces it adds and how
coherent they are across pixels.

For each file of ``real_data.py`` (face, tower, 21 km), loaded with the default IRF and
with ``irf="estimate-shape"``, ``detect(cube, pfa=1e-4, rng=0)`` runs once without the
split (``SPLIT_Z = 0``, main's segments) and once per variant given. Printed: surfaces,
pixels with two or more, the surfaces the variant adds (no surface of the
no-split run in its pixel within half a FWHM), the gaps between a pixel's consecutive
surfaces, and the neighbour coherence of the added surfaces (a surface within 1 FWHM
of its depth in a 4-neighbour) against chance (the same depths moved 1.5 FWHM either
way) and against the second surfaces of the no-split run.

    python benchmarks/bench_fine_split.py --files tower --irf shape \\
        --variant z3:Z=3 --variant reach3:Z=3,REACH=3

A variant is ``name:KEY=VALUE,...`` with keys Z (``SPLIT_Z``), REACH
(``SPLIT_REACH``, FWHMs), COH (``SPLIT_COHERENT``, 0 / 1 / 2). Another benchmark
script with those constants set (the before / after of its figures):

    python benchmarks/bench_fine_split.py --with Z=3,REACH=3,COH=1 \
        benchmarks/bench_robustness.py --only "two surfaces"
"""

from __future__ import annotations

import argparse
import runpy
import sys
import time
from pathlib import Path

import numpy as np

import splidar
from splidar import detect
from splidar.detection import _4_map, _detect

KEYS = {
    "Z": "SPLIT_Z",
    "REACH": "SPLIT_REACH",
    "COH": "SPLIT_COHERENT",
    "SLACK": "SPLIT_TAIL_SLACK",
}
GAPS = (0, 1, 1.5, 2, 2.5, 3, 4, np.inf)


def _set(settings: dict) -> None:
    for k, v in settings.items():
        name = KEYS[k]
        cur = getattr(_4_map, name)
        val = bool(int(v)) if isinstance(cur, bool) else type(cur)(float(v))
        for mod in (_4_map, _detect):
            if hasattr(mod, name):
                setattr(mod, name, val)


def _fwhm(irf: np.ndarray) -> float:
    g = np.asarray(irf, np.float64)
    w = [np.count_nonzero(r >= 0.5 * r.max()) for r in g]
    return float(max(w))


def _by_pixel(p, shape):
    k = p.row * shape[1] + p.col
    order = np.lexsort((p.depth_bin, k))
    return k[order], p.depth_bin[order]


def _near(k, dep, kq, dq, tol):
    """For each query (pixel kq, depth dq): a surface of pixel kq within tol."""
    out = np.zeros(kq.size, bool)
    lo = np.searchsorted(k, kq, side="left")
    hi = np.searchsorted(k, kq, side="right")
    for i in range(kq.size):
        if hi[i] > lo[i]:
            out[i] = np.any(np.abs(dep[lo[i] : hi[i]] - dq[i]) <= tol)
    return out


def _coherent(k, dep, shape, kq, dq, tol):
    R, C = shape
    r, c = kq // C, kq % C
    out = np.zeros(kq.size, bool)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        rr, cc = r + dr, c + dc
        ok = (rr >= 0) & (rr < R) & (cc >= 0) & (cc < C)
        idx = np.flatnonzero(ok)
        out[idx] |= _near(k, dep, rr[idx] * C + cc[idx], dq[idx], tol)
    return out


def _gaps(k, dep, fw):
    same = k[1:] == k[:-1]
    g = (dep[1:] - dep[:-1])[same] / fw
    return np.histogram(g, bins=GAPS)[0]


def _report(name, base, pts, shape, fw):
    kb, db = base
    k, d = _by_pixel(pts, shape)
    n_pix = shape[0] * shape[1]
    two = np.mean(np.bincount(k, minlength=n_pix) >= 2)
    added = ~_near(kb, db, k, d, 0.5 * fw)
    ka, da = k[added], d[added]
    coh = _coherent(k, d, shape, ka, da, fw).mean() if ka.size else np.nan
    chance = (
        np.mean(
            np.r_[
                _coherent(k, d, shape, ka, da + 1.5 * fw, fw),
                _coherent(k, d, shape, ka, da - 1.5 * fw, fw),
            ]
        )
        if ka.size
        else np.nan
    )
    # gaps of the added surfaces to the pixel's nearest other surface, in FWHMs
    print(
        f"  {name:>14}: {k.size:8,d} surfaces ({k.size / kb.size - 1:+.2%}), >= 2 in "
        f"{two:.2%}; added {ka.size}, coherent {coh:.0%} (chance {chance:.0%}); "
        f"gaps {'/'.join(map(str, _gaps(k, d, fw)))}"
    )


def _run_with(settings: str, argv: list) -> None:
    """``argv[0]`` run as ``__main__`` with the constants of ``settings`` set."""
    _set(dict(kv.split("=") for kv in settings.split(",") if kv))
    sys.argv = list(argv)
    runpy.run_path(argv[0], run_name="__main__")


def main() -> None:
    if len(sys.argv) > 3 and sys.argv[1] == "--with":
        _run_with(sys.argv[2], sys.argv[3:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", nargs="+", default=["face", "tower", "21km"])
    ap.add_argument("--irf", choices=["default", "shape", "both"], default="both")
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data"
    )
    args = ap.parse_args()
    real = runpy.run_path(str(Path(__file__).with_name("real_data.py")))["REAL"]
    variants = []
    for v in args.variant:
        nm, _, rest = v.partition(":")
        variants.append((nm, dict(kv.split("=") for kv in rest.split(",") if kv)))
    irfs = {"default": [None], "shape": ["estimate-shape"], "both": [None, "estimate-shape"]}
    defaults = {k: getattr(_4_map, n) for k, n in KEYS.items() if hasattr(_4_map, n)}
    for fname in args.files:
        rel, kw, _ = real[fname]
        for irf in irfs[args.irf]:
            cube = splidar.load(args.data / rel, **kw, **({} if irf is None else {"irf": irf}))
            shape = cube.counts.shape[:2]
            fw = _fwhm(cube.irf)
            _set({**defaults, "Z": 0})
            t0 = time.perf_counter()
            p0 = detect(cube, pfa=1e-4, rng=0).points
            base = _by_pixel(p0, shape)
            kb, db = base
            sec = np.r_[False, kb[1:] == kb[:-1]]
            coh2 = _coherent(kb, db, shape, kb[sec], db[sec], fw).mean()
            print(
                f"== {fname}, irf {irf or 'default'} (FWHM {fw:.0f} bins): no split "
                f"{kb.size:,d} surfaces, >= 2 in "
                f"{np.mean(np.bincount(kb, minlength=shape[0] * shape[1]) >= 2):.2%}, second "
                f"surfaces coherent {coh2:.0%}; gaps {'/'.join(map(str, _gaps(kb, db, fw)))} "
                f"({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
            for nm, st in variants:
                _set({**defaults, **st})
                pts = detect(cube, pfa=1e-4, rng=0).points
                _report(nm, base, pts, shape, fw)
            _set(defaults)


if __name__ == "__main__":
    main()
