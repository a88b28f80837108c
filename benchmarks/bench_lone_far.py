"""Issue #15, point 5: the lone far wrong depths of the single-surface cells (far40, session 27).

A *lone far wrong depth* is a pixel's **only** surface placed more than ``2 tau`` (6 bins)
from its true depth (``bench_false_surfaces.py``'s kind ``wrong depth far`` in a pixel
holding one surface): both a false surface and a missed true one. For each, on today's
detection (``detect(cube, rng=0)``, the cubes of ``bench_spread_sources.py``: 96 x 80
pixels, PPP 4, SBR 0.25, uniform and decaying background, its seeds):

1. **who placed it**: ``Surfaces.stage`` (the map, stage 5c ``dark_regions``, ...) and
   ``moved_by`` (stage 7's rules);
2. **its own counts**: stage 7b's profiled log-likelihood ratio ``profile_llr`` (a return
   at the depth against background alone, intensity profiled out; stage 1's background)
   at the chosen depth ``L(d)``, at the true depth ``L(t)``, and the pixel's best depth
   over the whole window;
3. **its neighbours**: how many 8-neighbours hold a surface within the gate (1.5 FWHM)
   of ``d`` and of ``t``, and how many are truly at ``t`` (2: a 1-pixel line; 5: the
   edge of a region; 8: inside one);
4. **where the true depth was lost** (``--history``; the detection re-run with the
   clean-up passes' tables captured): not a candidate of the map, a candidate the map
   rejected, or kept by the map and removed by a named pass (else stage 6 / 7);
5. **two per-pixel rules screened** on *every* lone surface of the cubes (the true ones
   too): *move* a lone surface to the 8-neighbours' depth its own counts favour by more
   than a margin (the profiled ratio ``L``, or the ratio at each depth's 8-neighbours'
   median photons: "the pixel continues that region, as bright"), *drop* a lone surface
   its own counts do not support (``L(d) = 0`` or ``< 0.5``), with or without k
   neighbours' surfaces at another depth. Counts: true
   surfaces lost against far wrong depths fixed or removed.

Usage::

    python benchmarks/bench_lone_far.py --seeds 0 1 2 --cache DIR [--history]

Nothing is downloaded; everything is simulated. Measured, not adopted (benchmarks/
README.md, "far40, session 27").
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
from bench_false_surfaces import false_causes, false_kinds
from bench_spread_sources import N_BINS, SHAPE, detected

from splidar.detection import STAGES
from splidar.detection._7b_edge_bands import _windows, profile_llr
from splidar.detection._filters import irf_fwhm
from splidar.metrics import PointSet
from splidar.scenes import single_surface_scene

BGS = ("uniform", "decaying")
PASSES = (
    "recentre_runs", "remove_spill_over", "remove_isolated", "restore_dark_regions",
    "recover_slope_surfaces", "restore_enclosed_holes", "remove_stray_clusters",
)  # fmt: skip
MARGINS = (0.0, 0.5, 1.0, 2.0, 3.0, 4.5)


def _llr(d, rows, cols, depths) -> np.ndarray:
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    y, g, b = _windows(d["counts"], d["background"], np.asarray(rows), np.asarray(cols),
                       np.asarray(depths, np.float64), irf)  # fmt: skip
    return profile_llr(y, g, b)


def _slots(s, values=None) -> np.ndarray:
    """(R + 2, C + 2, K) depths (or ``values``, (n,)) of each pixel's surfaces, NaN
    padded by one pixel."""
    R, C = s.image_shape
    v = s.depth_bin if values is None else values
    out = np.full((R + 2, C + 2, max(int(s.n_slots), 4)), np.nan)
    k = np.zeros((R + 2, C + 2), np.int64)
    for r, c, z in zip(s.row + 1, s.col + 1, v, strict=True):
        out[r, c, k[r, c]] = z
        k[r, c] += 1
    return out


def _fixed(d, r, c, depths, s) -> np.ndarray:
    """Own counts' log-ratio of a return of intensity ``s`` at each depth against none."""
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    n = len(depths)
    y, g, b = _windows(d["counts"], d["background"], np.full(n, r), np.full(n, c),
                       np.asarray(depths, np.float64), irf)  # fmt: skip
    s = np.asarray(s, np.float64)
    return (y * np.log1p(s[:, None, None] * g / b)).sum(axis=(1, 2)) - s * g.sum(axis=(1, 2))


def lone_kinds(d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lone surfaces (pixels holding one), whether each is true (matched), a far wrong
    depth, and each pixel's true depth (NaN without one)."""
    s, truth = d["surfaces"], d["truth"]
    fwhm = irf_fwhm(np.atleast_2d(np.asarray(d["irf"], np.float64)))
    R, C = s.image_shape
    pix = s.row * C + s.col
    pts = PointSet(row=s.row, col=s.col, depth_bin=s.depth_bin, image_shape=s.image_shape)
    false, cause = false_causes(pts, truth)
    kind = np.full(s.row.size, "true", dtype=object)
    kind[false] = [k[0] for k in false_kinds(pts, truth, false, cause, N_BINS, fwhm)]
    lone = np.flatnonzero(np.bincount(pix, minlength=R * C)[pix] == 1)
    tdep = np.full(R * C, np.nan)
    tdep[truth.row * C + truth.col] = truth.depth_bin
    return lone, kind[lone], tdep[pix[lone]]


def characterise(d) -> list[dict]:
    """One record per lone far wrong depth (see the module docstring, 1-3)."""
    s, truth = d["surfaces"], d["truth"]
    gate = 1.5 * irf_fwhm(np.atleast_2d(np.asarray(d["irf"], np.float64)))
    R, C = s.image_shape
    lone, kind, tdep = lone_kinds(d)
    D = _slots(s)
    T = np.full((R + 2, C + 2), np.nan)
    T[truth.row + 1, truth.col + 1] = truth.depth_bin
    grid = np.arange(2.0, N_BINS - 2)
    out = []
    for i, t in zip(lone[kind == "wrong depth far"], tdep[kind == "wrong depth far"], strict=True):
        r, c, z = int(s.row[i]), int(s.col[i]), float(s.depth_bin[i])
        L = _llr(d, np.full(grid.size, r), np.full(grid.size, c), grid)
        Ld, Lt = _llr(d, [r, r], [c, c], [z, t])
        nb = D[r : r + 3, c : c + 3].copy()
        nb[1, 1] = np.nan
        tn = T[r : r + 3, c : c + 3].copy()
        tn[1, 1] = np.nan
        out.append(dict(
            r=r, c=c, d=z, t=float(t), stage=STAGES[s.stage[i]], moved=int(s.moved_by[i]),
            Ld=float(Ld), Lt=float(Lt), dmax=float(grid[L.argmax()]),
            n_d=int((np.abs(nb - z) <= gate).any(axis=-1).sum()),
            n_t=int((np.abs(nb - t) <= gate).any(axis=-1).sum()),
            nb_true_t=int((np.abs(tn - t) <= 3).sum()),
        ))  # fmt: skip
    return out


def where_lost(history: dict, r: int, c: int, t: float, tol: float = 3.0) -> str:
    """Where a pixel's true depth ``t`` left the candidate table.

    ``history``: ``{"map": snap, pass name: snap, ...}`` in order, each snap a dict of
    ``row``, ``col``, ``depth_bin``, ``keep`` arrays (the table after the map and after
    each clean-up pass). Returns ``"not a map candidate"``, ``"rejected at the map"``,
    ``"removed by <pass>"``, or ``"kept through stage 5"`` (lost at stage 6 or 7).
    """
    kept = []
    for name, h in history.items():
        at = (h["row"] == r) & (h["col"] == c) & (np.abs(h["depth_bin"] - t) <= tol)
        if name == "map" and not at.any():
            return "not a map candidate"
        kept.append((name, bool((at & h["keep"]).any())))
    if not kept[0][1]:
        return "rejected at the map"
    for name, k in kept[1:]:
        if not k:
            return f"removed by {name}"
    return "kept through stage 5"


def table_history(cube) -> dict:
    """``detect(cube, rng=0)`` with the candidate table captured after the map and after
    each clean-up pass (the driver's pass functions wrapped for this call only)."""
    import splidar.detection._detect as drv

    cap: dict = {}

    def snap(t):
        return {k: np.array(t.columns[k]) for k in ("row", "col", "depth_bin")} | {
            "keep": np.array(t.keep)
        }

    saved = {n: getattr(drv, n) for n in (*PASSES, "_clean_up")}

    def clean_up(cube_, o, mp, held, *a):
        cap["map"] = snap(held[-1])
        return saved["_clean_up"](cube_, o, mp, held, *a)

    def wrap(name):
        def w(*a, **k):
            res = saved[name](*a, **k)
            cap[name] = snap(res.table)
            return res

        return w

    try:
        drv._clean_up = clean_up
        for n in PASSES:
            setattr(drv, n, wrap(n))
        drv.detect(cube, rng=0)
    finally:
        for n, f in saved.items():
            setattr(drv, n, f)
    return {k: cap[k] for k in ("map", *PASSES) if k in cap}


def _outcome(who: str, fixed: bool) -> str:
    return "true off" if who == "true" else "far fixed" if fixed else "far elsewhere"


def screen_rules(d) -> collections.Counter:
    """The per-pixel move and drop rules on every lone surface (module docstring, 5)."""
    s = d["surfaces"]
    gate = 1.5 * irf_fwhm(np.atleast_2d(np.asarray(d["irf"], np.float64)))
    lone, kind, tdep = lone_kinds(d)
    Ld = _llr(d, s.row[lone], s.col[lone], s.depth_bin[lone])
    D = _slots(s)
    P = _slots(s, np.asarray(s.photons, np.float64).sum(axis=-1))
    n = collections.Counter()
    for j, i in enumerate(lone):
        if kind[j] not in ("true", "wrong depth far"):
            continue
        who = "true" if kind[j] == "true" else "far"
        n[f"lone {who}"] += 1
        r, c = s.row[i], s.col[i]
        nb = D[r : r + 3, c : c + 3].ravel()
        alt = nb[np.isfinite(nb) & (np.abs(nb - s.depth_bin[i]) > gate)]
        for lev, name in ((Ld[j] == 0, "L(d) = 0"), (Ld[j] < 0.5, "L(d) < 0.5")):
            for k in (0, 1, 3, 5):
                n[f"drop {name}, >= {k} nb at another depth: {who}"] += bool(lev and alt.size >= k)
        if alt.size == 0:
            continue
        n[f"lone {who} beside another depth"] += 1
        alt = np.unique(np.round(alt))
        La = _llr(d, np.full(alt.size, r), np.full(alt.size, c), alt)
        fixed = abs(alt[La.argmax()] - tdep[j]) <= 3
        for m in MARGINS:
            if La.max() - Ld[j] > m:
                n[f"move margin {m}: " + _outcome(who, fixed)] += 1
        # the same choice with each depth's return as bright as its 8-neighbours' (their
        # median photons): "the pixel continues that neighbour region"
        nd, nph = D[r : r + 3, c : c + 3].ravel(), P[r : r + 3, c : c + 3].ravel()
        nd, nph = nd[np.isfinite(nd)], nph[np.isfinite(nd)]
        zs = np.concatenate([[s.depth_bin[i]], alt])
        br = np.array([np.median(nph[np.abs(nd - z) <= gate]) if (np.abs(nd - z) <= gate).any()
                       else 0.0 for z in zs])  # fmt: skip
        if br[0] <= 0:  # no neighbour shares its depth: its own brightness
            br[0] = float(np.asarray(s.photons[i], np.float64).sum())
        Lf = _fixed(d, r, c, zs, br)
        fixed = abs(zs[1 + Lf[1:].argmax()] - tdep[j]) <= 3
        for m in MARGINS:
            if Lf[1:].max() - Lf[0] > m:
                n[f"move (neighbours' brightness) margin {m}: " + _outcome(who, fixed)] += 1
    return n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--cache", default=None)
    ap.add_argument("--history", action="store_true", help="where the true depth was lost")
    args = ap.parse_args(argv)
    for b, bg in enumerate(BGS):
        recs, rules, lost = [], collections.Counter(), collections.Counter()
        for seed in args.seeds:
            d = detected("single", seed, [seed, b], (bg, 4, 0.25), args.cache)
            rs = characterise(d)
            recs += rs
            rules += screen_rules(d)
            if args.history:
                sim = single_surface_scene(SHAPE, n_bins=N_BINS).simulate(
                    ppp=4, sbr=0.25, background=bg, rng=np.random.default_rng([seed, b])
                )
                h = table_history(sim.cube)
                for x in rs:
                    lost[where_lost(h, x["r"], x["c"], x["t"])] += 1
        a = {k: np.array([x[k] for x in recs]) for k in recs[0]} if recs else {}
        print(f"{bg}: {len(recs)} lone far wrong depths in {len(args.seeds)} cubes")
        if not recs:
            continue
        print("  placed by", dict(collections.Counter(a["stage"].tolist())), "; stage 7 moved",
              dict(collections.Counter(a["moved"].tolist())))  # fmt: skip
        dl = a["Ld"] - a["Lt"]
        print(f"  own L(d) median {np.median(a['Ld']):.2f}, L(t) {np.median(a['Lt']):.2f}; "
              f"L(d) = 0: {(a['Ld'] == 0).sum()}, L(t) = 0: {(a['Lt'] == 0).sum()}; "
              f"|L(d) - L(t)| <= 0.5: {(abs(dl) <= 0.5).sum()}, favour d by > 2: "
              f"{(dl > 2).sum()}, favour t by > 2: {(dl < -2).sum()}; best own depth "
              f"within 3 of t: {(abs(a['dmax'] - a['t']) <= 3).sum()}, of d: "
              f"{(abs(a['dmax'] - a['d']) <= 3).sum()}")  # fmt: skip
        for k in ("n_d", "n_t", "nb_true_t"):
            print(f"  8-neighbours {k}: {np.bincount(a[k], minlength=9).tolist()}")
        if lost:
            print("  true depth lost:", dict(lost))
        print("  rules on every lone surface:")
        for k in sorted(rules):
            print(f"    {k}: {rules[k]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
