"""Issue #15, point 5: where the "spread" false surfaces come from, and two gates tried.

A *spread* surface (``bench_false_surfaces.py --detail``: ``spread 1 px`` / ``spread
2-5 px``) is a further surface of a pixel whose own true surface is matched, at the depth
of a neighbour's true surface (the multiscale boxes pool the neighbour's return into the
pixel). This script takes today's detection (``detect(cube, rng=0)``, every pass) of
the single-surface cells and of the sheet and net layer cells (the cubes and seeds of
``bench_edge_bands.py``), and for the *candidates* (the surfaces of pixels holding two
or more):

1. **where they come from**: the stage that keeps each spread surface
   (``Surfaces.stage``), and the quantiles of its own counts' statistics (the map's
   ``presence_llr``; stage 7b's profiled ``profile_llr`` over the IRF window; the
   own-count log-likelihood ratio of a return at a *fixed* intensity ``s`` against none,
   ``sum_t y log(1 + s g / b) - s sum_t g``, with ``s`` the median selected-scale
   signal of the 8-neighbours' surfaces at its depth, or the true intensity of the
   neighbouring true surfaces at its depth, an oracle), against the true candidates';
2. **stage 7c's group rule** (``_7c_spread_groups.spread_groups``, the module's
   constants) gated by **co-occurrence**: a candidate at depth ``d`` in a pixel whose
   other surface is at ``a`` is tested only when at most ``K`` other pixels within the
   largest box's half-width hold both a surface within the gate of ``d`` and one within
   the gate of ``a`` (not the same one): a two-layer region holds the pair of depths in
   many pixels, a spread strip beside a depth edge in few;
3. **a two-hypothesis group test**: the group's summed fixed-intensity log-ratio (the
   neighbours' measured intensity, or the oracle's) below ``-c`` removes its members
   (only those 7c tests, a pixel never emptied);
4. **lines**: the own counts of the ``2 h + 1`` pixels along each of the 4 axes through
   the candidate's pixel (``h`` the largest box's half-width), each pixel at the surface
   nearest the line's running course within the gate (its own, else its
   8-neighbours'; the course follows them), one intensity shared by the line and
   profiled out (``group_llr``); the candidate is removed when no axis reaches the
   prior level ``log((1 - q) / q)`` (7c's) and 7c tests it. Two pools: every pixel of
   the line, or without the pixels holding one surface only, at the course (the
   source region: a spread strip's line then holds the strip and the region it lies in,
   not the region it came from), alone and with the co-occurrence gate.

Figures are screening counts summed over the seeds: true surfaces removed / false
surfaces removed per scene (a removed unmatched surface changes no match).

With ``--layer`` (lay38, session 26) the line rules are gated by stage 7d's layered
regions (``_7d_layer_evidence.layer_evidence``: a pixel's depths continuing as pairs,
counted in a window and tested against the null's ``surface_pfa``; whole image and 15
pixels): a candidate is tested only where no layer is shown (``line_open`` with the whole
image is the module's ``spread_lines``, checked equal on every cube). Printed per cube:
F_true and false surfaces (``evaluate``, tau 3 bins) before and after each gated rule.

With ``--grid`` the cubes are instead ``bench_detection.py``'s 64 cells (64 x 64,
single surface and two layers, PPP 1-50, SBR 0.1-10, both backgrounds; its ``--seed``'s
random keys; ``detect(cube, pfa=1e-3, max_surfaces=2, rng=0)``, its options), and the
line rules are applied after the detection: per cell, the true and false surfaces each
would remove.

Usage::

    python benchmarks/bench_spread_sources.py --seeds 0 1 2 --cache DIR
    python benchmarks/bench_spread_sources.py --grid --seeds 0 --cache DIR
    python benchmarks/bench_spread_sources.py --layer [--grid] --seeds 0 1 2 --cache DIR
    python benchmarks/bench_spread_sources.py --kinds [--grid] --seeds 0 1 2 --cache DIR
    python benchmarks/bench_spread_sources.py --null-tail

With ``--kinds`` (dec39, session 27) the single-surface cells' false surfaces left after
stage 7d's gated ``line_open`` (``spread_lines``) are put in ``bench_false_surfaces.py``'s
kinds and placed by the estimated background's temporal shape at their depth (below 0.8,
0.8-1.25, above 1.25 times its mean: the decaying background's low and high parts),
with 7c's axes decision for the candidates (tested or spared); and one rule is measured
on every cube (``every``, with ``--grid`` on ``bench_detection.py``'s cells): outside the
layered windows, the candidates 7c's axes spare are line-tested too, and removed when
their lines fail while the pixel's other surface's pass. With ``--null-tail`` the line
test's tail on background-only lines (11 pixels, the scene's IRF) at several background
levels: whether ``log((1 - q) / q)`` means the same false-pass rate at every level.

Nothing is downloaded; everything is simulated. Measured, not adopted (benchmarks/
README.md, "spr36, session 24").
"""

from __future__ import annotations

import argparse
import pickle
from pathlib import Path

import numpy as np
from bench_false_surfaces import LAYER, false_causes, false_kinds, net_scene, sheet_scene

from splidar.detection import STAGES, detect
from splidar.detection._7b_edge_bands import _windows, group_llr, profile_llr
from splidar.detection._7c_spread_groups import GATE_FWHM, _slots, spread_groups
from splidar.detection._7d_layer_evidence import (
    depth_slots,
    layer_evidence,
    spread_lines,
)
from splidar.detection._7d_layer_evidence import (
    line_llr as lines_7d,
)
from splidar.detection._filters import irf_fwhm
from splidar.metrics import PointSet, evaluate
from splidar.scenes import single_surface_scene, two_layer_scene

SHAPE, N_BINS = (96, 80), 200
SINGLE = (("uniform", 4, 0.25), ("decaying", 4, 0.25))
SPREAD = ("spread 1 px", "spread 2-5 px")
GRID = {"ppp": (1, 4, 10, 50), "sbr": (0.1, 0.25, 1, 10), "bg": ("uniform", "decaying")}


def cubes(seeds):
    """(scene name, seed, rng key, cell) of every cube, as ``bench_edge_bands.py``."""
    for seed in seeds:
        for i, cell in enumerate(SINGLE):
            yield "single", seed, [seed, i], cell
        for j, name in enumerate(("sheet", "net")):
            for i, cell in enumerate(LAYER):
                yield name, seed, [seed, 100 * (j + 1) + i], cell


def grid_cubes(seed):
    """(scene name, seed, rng key, cell) of ``bench_detection.py``'s 64 cells."""
    idx = 0
    for name in ("single", "two_layer"):
        for bg in GRID["bg"]:
            for ppp in GRID["ppp"]:
                for sbr in GRID["sbr"]:
                    yield name, seed, [seed, idx], (bg, ppp, sbr)
                    idx += 1


def detected(name, seed, key, cell, cache, grid=False) -> dict:
    """Today's detection of one cube (kept in ``cache``)."""
    tag = f"grid_{name}" if grid else name
    path = None if cache is None else Path(cache) / f"{tag}_{seed}_{key[1]}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    if grid:
        make = single_surface_scene if name == "single" else two_layer_scene
        scene = make((64, 64), n_bins=N_BINS)
    elif name == "single":
        scene = single_surface_scene(SHAPE, n_bins=N_BINS)
    else:
        scene = (sheet_scene if name == "sheet" else net_scene)()[0]
    sim = scene.simulate(ppp=cell[1], sbr=cell[2], background=cell[0],
                         rng=np.random.default_rng(key))  # fmt: skip
    opts = dict(pfa=1e-3, max_surfaces=2) if grid else {}
    det = detect(sim.cube, rng=0, **opts)
    d = dict(surfaces=det.surfaces, background=det.background, irf=np.asarray(det.irf),
             half=int(max(det.scales)) // 2, counts=np.asarray(sim.cube.counts),
             truth=sim.truth)  # fmt: skip
    if path is not None:
        path.write_bytes(pickle.dumps(d))
    return d


def _depth_slots(s) -> np.ndarray:
    """(R, C, K) depths of each pixel's surfaces, NaN padded."""
    R, C = s.image_shape
    pix = s.row * C + s.col
    out = np.full((R * C, max(int(np.bincount(pix).max()), 1)), np.nan)
    k = np.zeros(R * C, np.int64)
    for i in np.argsort(pix, kind="stable"):
        out[pix[i], k[pix[i]]] = s.depth_bin[i]
        k[pix[i]] += 1
    return out.reshape(R, C, -1)


def cooccurrence(s, cand, gate: float, half: int) -> np.ndarray:
    """Per candidate: the other pixels within ``half`` holding both its depth and its
    pixel's other depth (two surfaces, each within ``gate``)."""
    D = _depth_slots(s)
    R, C, K = D.shape
    pad = np.full((R + 2 * half, C + 2 * half, K), np.nan)
    pad[half : half + R, half : half + C] = D
    out = np.zeros(cand.size, np.int64)
    for j, i in enumerate(cand):
        r, c, d = s.row[i], s.col[i], s.depth_bin[i]
        own = D[r, c]
        other = own[np.isfinite(own) & (np.abs(own - d) > gate)]
        w = pad[r : r + 2 * half + 1, c : c + 2 * half + 1]
        at_d = np.abs(w - d) <= gate
        both = at_d.any(-1) & ((np.abs(w[..., None] - other) <= gate).any(-1) & ~at_d).any(-1)
        both[half, half] = False
        out[j] = int(both.sum())
    return out


def fixed_llr(y, g, b, s) -> np.ndarray:
    """Own counts' log-ratio of a return of intensity ``s`` (n,) against none."""
    return (y * np.log1p(s[:, None, None] * g / b)).sum(axis=(1, 2)) - s * g.sum(axis=(1, 2))


def intensities(s, cand, gate, truth) -> tuple[np.ndarray, np.ndarray]:
    """Per candidate: the median selected-scale signal of the 8-neighbours' surfaces at
    its depth (0 without one), and the mean true intensity of the 8-neighbours' true
    surfaces at its depth (the oracle; 0 without one)."""
    R, C = s.image_shape
    sig = np.asarray(s.photons).sum(axis=-1)
    pix = s.row * C + s.col
    ti = truth.intensity.sum(axis=-1)
    meas, oracle = np.zeros(cand.size), np.zeros(cand.size)
    for j, i in enumerate(cand):
        r, c, d = s.row[i], s.col[i], s.depth_bin[i]
        near = (np.abs(s.row - r) <= 1) & (np.abs(s.col - c) <= 1) & (pix != pix[i])
        near &= np.abs(s.depth_bin - d) <= gate
        meas[j] = np.median(sig[near]) if near.any() else 0.0
        cheb = np.maximum(np.abs(truth.row - r), np.abs(truth.col - c))
        t = (cheb == 1) & (np.abs(truth.depth_bin - d) <= gate)
        oracle[j] = ti[t].mean() if t.any() else 0.0
    return meas, oracle


def line_pools(s, cand, gate: float, h: int, exclude_single: bool):
    """Rows, columns, depths and line index (``4 * candidate + axis``) of the pixels
    pooled on the 4 axes through each candidate (see the module, item 4)."""
    R, C = s.image_shape
    slots = _slots(s.row, s.col, np.arange(s.row.size), (R, C))
    dep = np.where(slots >= 0, s.depth_bin[np.maximum(slots, 0)], np.nan)
    n_at = (slots >= 0).sum(axis=-1)
    out = []
    for j, i in enumerate(cand):
        r0, c0, d0 = int(s.row[i]), int(s.col[i]), float(s.depth_bin[i])
        for a, (dr, dc) in enumerate(((0, 1), (1, 0), (1, 1), (1, -1))):
            out.append((r0, c0, d0, 4 * j + a))
            for sgn in (1, -1):
                course = d0
                for k in range(1, h + 1):
                    r, c = r0 + sgn * k * dr, c0 + sgn * k * dc
                    if not (0 <= r < R and 0 <= c < C):
                        break
                    own = dep[r, c][np.abs(dep[r, c] - course) <= gate]
                    if own.size:
                        course = float(own[np.argmin(np.abs(own - course))])
                        if exclude_single and n_at[r, c] == 1:
                            continue
                    else:
                        w = dep[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2].ravel()
                        w = w[np.abs(w - course) <= gate]
                        if w.size:
                            course = float(w[np.argmin(np.abs(w - course))])
                    out.append((r, c, course, 4 * j + a))
    r, c, dd, g = (np.array(x) for x in zip(*out, strict=True))
    return r.astype(np.int64), c.astype(np.int64), dd.astype(np.float64), g.astype(np.int64)


def line_llr(d, cand, gate: float, exclude_single: bool) -> np.ndarray:
    """(n, 4) the lines' profiled log-ratios (nats) of each candidate."""
    if cand.size == 0:
        return np.zeros((0, 4))
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    r, c, dd, g = line_pools(d["surfaces"], cand, gate, d["half"], exclude_single)
    y, gg, b = _windows(d["counts"], d["background"], r, c, dd, irf)
    out = np.zeros(4 * cand.size)
    out[: int(g.max()) + 1] = group_llr(y, gg, b, g)
    return out.reshape(cand.size, 4)


def analyse(d) -> dict:
    """The candidates' kinds, stages, statistics, 7c's decision and the gates' inputs."""
    s, truth = d["surfaces"], d["truth"]
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    fwhm = irf_fwhm(irf)
    gate = GATE_FWHM * fwhm
    pts = PointSet(row=s.row, col=s.col, depth_bin=s.depth_bin, image_shape=s.image_shape,
                   intensity=s.photons, layer=s.slot)  # fmt: skip
    false, cause = false_causes(pts, truth)
    kind = np.full(len(pts), "true", dtype=object)
    kind[false] = [k[0] for k in false_kinds(pts, truth, false, cause, N_BINS, fwhm)]
    sg = spread_groups(s.row, s.col, s.depth_bin, s.image_shape, d["counts"], d["background"],
                       fwhm=fwhm, irf=irf)  # fmt: skip
    cand = sg.candidates
    y, g, b = _windows(d["counts"], d["background"], s.row[cand], s.col[cand],
                       s.depth_bin[cand], irf)  # fmt: skip
    meas, oracle = intensities(s, cand, gate, truth)
    R, C = s.image_shape
    return dict(
        cand=cand, kind=kind[cand], stage=np.asarray(STAGES)[s.stage[cand]],
        presence=s.presence_llr[cand], profile=profile_llr(y, g, b),
        fixed=fixed_llr(y, g, b, meas), fixed_oracle=fixed_llr(y, g, b, oracle),
        tested=sg.tested, failed=np.isin(cand, sg.remove), group=sg.group,
        k=cooccurrence(s, cand, gate, d["half"]), pix=s.row[cand] * C + s.col[cand],
        level=sg.level, line_all=line_llr(d, cand, gate, False).max(axis=1),
        line_open=line_llr(d, cand, gate, True).max(axis=1),
    )  # fmt: skip


def removed(a, fail) -> np.ndarray:
    """Candidates removed when ``fail`` (a pixel keeps one surface at least)."""
    passes = np.bincount(a["pix"], weights=~fail, minlength=int(a["pix"].max()) + 1)
    return fail & (passes[a["pix"]] >= 1)


def grid_main(args) -> int:
    """The line rules after the detection of ``bench_detection.py``'s cells."""
    tot = {}
    print("scene     bg        PPP  SBR   n_true  n_est   line_all true/false  line_open "
          "true/false")  # fmt: skip
    for seed in args.seeds:
        for name, _, key, cell in grid_cubes(seed):
            d = detected(name, seed, key, cell, args.cache, grid=True)
            a = analyse(d)
            txt = []
            for f in ("line_all", "line_open"):
                rm = removed(a, a["tested"] & (a[f] < a["level"]))
                t = int(np.sum(rm & (a["kind"] == "true")))
                fl = int(np.sum(rm & (a["kind"] != "true")))
                s = tot.setdefault(f, [0, 0, 0])
                s[0], s[1], s[2] = s[0] + t, s[1] + fl, s[2] + (t > 0)
                txt.append(f"{t:4d} / {fl:4d}")
            n = f"{len(d['truth']):7d} {d['surfaces'].row.size:6d}"
            print(f"{name:9s} {cell[0]:9s} {cell[1]:3g} {cell[2]:5g} {n}   {txt[0]:>19s}  "
                  f"{txt[1]:>19s}", flush=True)  # fmt: skip
    for f, (t, fl, n) in tot.items():
        print(f"{f}: {t} true / {fl} false removed in all; cells losing a true surface: {n}")
    return 0


#: stage 7d's windows measured (pixels; None: the whole image) and the gated rules
LAYER_RADII = (None, 15)
LAYER_RULES = ("line_open", "line_all", "open_or_all")


def layer_gated(d, a, surface_pfa: float = 0.01) -> dict:
    """Per rule and window: (F_true, false surfaces) after removing the candidates the
    rule fails outside stage 7d's layered regions, and the layered fraction."""
    s, truth = d["surfaces"], d["truth"]
    gate = GATE_FWHM * irf_fwhm(np.atleast_2d(np.asarray(d["irf"], np.float64)))
    pts = PointSet(row=s.row, col=s.col, depth_bin=s.depth_bin, image_shape=s.image_shape)

    def score(keep):
        m = evaluate(pts.subset(keep), truth, tau=3.0)
        return float(m.f_true), int(m.f_false)

    out = {"before": score(np.ones(len(pts), bool))}
    fails = {"line_open": a["line_open"] < a["level"], "line_all": a["line_all"] < a["level"]}
    fails["open_or_all"] = fails["line_open"] | fails["line_all"]
    for radius in LAYER_RADII:
        le = layer_evidence(s.row, s.col, s.depth_bin, s.image_shape, gate=gate,
                            half=d["half"], surface_pfa=surface_pfa, radius=radius)  # fmt: skip
        free = ~le.layered.ravel()[a["pix"]]
        out[("layered", radius)] = float(le.layered.mean())
        for rule in LAYER_RULES:
            rm = removed(a, a["tested"] & fails[rule] & free)
            keep = np.ones(len(pts), bool)
            keep[a["cand"][rm]] = False
            out[(rule, radius)] = score(keep)
            if rule == "line_open" and radius is None:  # the module's rule: the same
                sl = spread_lines(s.row, s.col, s.depth_bin, s.image_shape, d["counts"],
                                  d["background"], fwhm=gate / GATE_FWHM, irf=d["irf"],
                                  half=d["half"], surface_pfa=surface_pfa)  # fmt: skip
                assert np.array_equal(sl.remove, np.sort(a["cand"][rm]))
    return out


def layer_main(args) -> int:
    """The line rules gated by stage 7d's layered regions (``--layer``)."""
    it = grid_cubes(args.seeds[0]) if args.grid else cubes(args.seeds)
    tot = {}
    for name, seed, key, cell in it:
        d = detected(name, seed, key, cell, args.cache, grid=args.grid)
        r = layer_gated(d, analyse(d))
        f0, n0 = r["before"]
        txt = []
        for radius in LAYER_RADII:
            for rule in LAYER_RULES:
                f1, n1 = r[(rule, radius)]
                t = tot.setdefault((name, cell, rule, radius), [0, 0, 0])
                t[0], t[1], t[2] = t[0] + (f1 < f0), t[1] + (n1 - n0), t[2] + (f1 - f0)
                txt.append(f"{rule}@{radius}: {f1:.4f} / {n1}")
        lay = " ".join(f"{r[('layered', x)]:.2f}" for x in LAYER_RADII)
        print(f"{name:9s} {cell[0]:9s} {cell[1]:3g} {cell[2]:5g} seed {seed}: before "
              f"{f0:.4f} / {n0}; layered {lay}; " + "; ".join(txt), flush=True)  # fmt: skip
    print("per cell, rule @ window: cubes with F_true lower, summed change of false, of F_true")
    for (name, cell, rule, radius), (n, df, dt) in tot.items():
        print(f"  {name:9s} {cell[0]:9s} {cell[1]:3g} {cell[2]:5g} {rule}@{radius}: {n} lower, "
              f"false {df:+d}, F_true {dt:+.4f}")  # fmt: skip
    return 0


#: the estimated background's temporal shape at a surface's depth, relative to its mean:
#: the bands of the kinds table (low part, middle, high part of a decaying background)
REL_BANDS = (0.8, 1.25)


def every_lines(d, surface_pfa: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Stage 7d's removal (``spread_lines``) and the ``every`` rule's (see the module)."""
    s = d["surfaces"]
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    fwhm = irf_fwhm(irf)
    sl = spread_lines(s.row, s.col, s.depth_bin, s.image_shape, d["counts"], d["background"],
                      fwhm=fwhm, irf=irf, half=d["half"], surface_pfa=surface_pfa)  # fmt: skip
    cand = sl.candidates
    free = ~sl.layers.layered[s.row[cand], s.col[cand]]
    llr = np.full(cand.size, np.nan)
    t = cand[free]
    D, n = depth_slots(s.row, s.col, s.depth_bin, s.image_shape)
    if t.size:
        llr[free] = lines_7d(D, n, s.row[t], s.col[t], s.depth_bin[t], d["counts"],
                             d["background"], irf, gate=GATE_FWHM * fwhm,
                             half=d["half"]).max(axis=1)  # fmt: skip
    pix = s.row[cand] * s.image_shape[1] + s.col[cand]
    ok = free & (np.nan_to_num(llr, nan=-np.inf) >= sl.level)
    good = np.bincount(pix, weights=ok, minlength=int(np.prod(s.image_shape)))
    fail = free & ~sl.tested & (np.nan_to_num(llr, nan=np.inf) < sl.level)
    return sl.remove, np.union1d(sl.remove, cand[fail & (good[pix] >= 1)])


def kept_kinds(d, remove) -> tuple[object, list]:
    """``evaluate`` after removing ``remove``, and each false surface's (kind, relative
    background at its depth, index in the detection)."""
    s, truth = d["surfaces"], d["truth"]
    keep = np.setdiff1d(np.arange(s.row.size), remove)
    pts = PointSet(row=s.row[keep], col=s.col[keep], depth_bin=s.depth_bin[keep],
                   image_shape=s.image_shape)  # fmt: skip
    fwhm = irf_fwhm(np.atleast_2d(np.asarray(d["irf"], np.float64)))
    false, cause = false_causes(pts, truth)
    tm = np.asarray(d["background"].temporal, np.float64).sum(axis=0)
    rel = tm / tm.mean()
    out = []
    for k, i in zip(false_kinds(pts, truth, false, cause, N_BINS, fwhm), false, strict=True):
        t = int(np.clip(np.rint(pts.depth_bin[i]), 0, rel.size - 1))
        out.append((k[0], float(rel[t]), int(keep[i])))
    return evaluate(pts, truth, tau=3.0), out


def kinds_main(args) -> int:
    """The false surfaces left after stage 7d, by kind and background part; the
    ``every`` rule on every cube (``--kinds``)."""
    it = grid_cubes(args.seeds[0]) if args.grid else cubes(args.seeds)
    acc, tot = {}, {}
    for name, seed, key, cell in it:
        d = detected(name, seed, key, cell, args.cache, grid=args.grid)
        gated, every = every_lines(d)
        res = [kept_kinds(d, rm) for rm in (np.zeros(0, np.int64), gated, every)]
        nm = [(int(m.n_matched), int(m.f_false)) for m, _ in res]
        t = tot.setdefault((name, cell), np.zeros(5, np.int64))
        t += [1, nm[1][0] - nm[0][0], nm[1][1] - nm[0][1], nm[2][0] - nm[1][0], nm[2][1] - nm[1][1]]
        txt = "  ".join(f"{m.f_true:.4f} / {m.f_false}" for m, _ in res)
        print(f"{name:9s} {cell[0]:9s} {cell[1]:3g} {cell[2]:5g} seed {seed}: today, gated, "
              f"every: {txt}", flush=True)  # fmt: skip
        if name != "single" or args.grid:
            continue
        s = d["surfaces"]
        C = s.image_shape[1]
        n_at = np.bincount(s.row * C + s.col, minlength=int(np.prod(s.image_shape)))
        sl = spread_lines(s.row, s.col, s.depth_bin, s.image_shape, d["counts"], d["background"],
                          fwhm=irf_fwhm(np.atleast_2d(np.asarray(d["irf"], np.float64))),
                          irf=d["irf"], half=d["half"], surface_pfa=0.01)  # fmt: skip
        sl_tested = set(sl.candidates[sl.tested].tolist())
        for kind, rel, i in res[1][1]:
            a = acc.setdefault((cell[0], kind), np.zeros(6))
            a[int(np.searchsorted(REL_BANDS, rel, side="right"))] += 1
            if n_at[s.row[i] * C + s.col[i]] >= 2:
                a[3 + (i not in sl_tested)] += 1
            a[5] += 1
    if acc:
        n = len(args.seeds)
        print(f"left after the gated line_open, per cube ({n} seeds): kind: all; by the "
              f"background's part (< {REL_BANDS[0]}, middle, > {REL_BANDS[1]} x its mean); "
              "candidates tested / spared by 7c's axes")  # fmt: skip
        for (bg, kind), a in sorted(acc.items()):
            a = a / n
            print(f"  {bg:9s} {kind:17s} {a[5]:5.1f}: {a[0]:5.1f} {a[1]:5.1f} {a[2]:5.1f}; "
                  f"{a[3]:5.1f} / {a[4]:5.1f}")  # fmt: skip
    print("per cell (cubes): gated vs today true / false; every vs gated true / false")
    for (name, cell), t in tot.items():
        print(f"  {name:9s} {cell[0]:9s} {cell[1]:3g} {cell[2]:5g} ({t[0]}): {t[1]:+d} / "
              f"{t[2]:+d}; {t[3]:+d} / {t[4]:+d}")  # fmt: skip
    return 0


def null_tail(irf, levels=(0.005, 0.01, 0.02, 0.05, 0.1, 0.25), n_lines=20000, n_px=11,
              nats=(2.0, 4.5, 6.0), seed=0) -> dict:  # fmt: skip
    """``P(line log-ratio > x)`` on background-only lines of ``n_px`` pixels at each
    background level (counts per bin), the IRF's window about an interior depth."""
    from splidar.detection._7b_edge_bands import _shifted_irf

    irf = np.atleast_2d(np.asarray(irf, np.float64))
    peak = np.argmax(irf, axis=1)
    W = irf.shape[1] + 2
    g1 = _shifted_irf(irf, peak, np.array([peak.max() + 1.0]), W)[0]
    rng = np.random.default_rng(seed)
    grp = np.repeat(np.arange(n_lines), n_px)
    out = {}
    for b in levels:
        y = rng.poisson(b, size=(n_lines * n_px, *g1.shape)).astype(np.float64)
        g = np.broadcast_to(g1, y.shape).copy()
        llr = group_llr(y, g, np.full(y.shape, float(b)), grp)
        out[b] = {x: float(np.mean(llr > x)) for x in nats}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--cache", help="a directory keeping each cube's detection")
    ap.add_argument("--grid", action="store_true", help="bench_detection.py's 64 cells")
    ap.add_argument("--layer", action="store_true", help="the rules gated by stage 7d")
    ap.add_argument("--kinds", action="store_true", help="what stage 7d leaves; `every`")
    ap.add_argument("--null-tail", action="store_true", help="the line test's null tail")
    args = ap.parse_args(argv)
    if args.null_tail:
        irf = np.stack([g.sample() for g in single_surface_scene(SHAPE, n_bins=N_BINS).irf])
        for b, p in null_tail(irf).items():
            print(f"background {b:g} per bin: P(line log-ratio > x) "
                  + ", ".join(f"x={x:g}: {v:.5f}" for x, v in p.items()))  # fmt: skip
        return 0
    if args.kinds:
        return kinds_main(args)
    if args.layer:
        return layer_main(args)
    if args.grid:
        return grid_main(args)
    rows = {}
    for name, seed, key, cell in cubes(args.seeds):
        rows.setdefault(name, []).append(analyse(detected(name, seed, key, cell, args.cache)))
    q = (10, 25, 50, 75, 90)
    for name, rs in rows.items():
        kind = np.concatenate([a["kind"] for a in rs])
        sp, tr = np.isin(kind, SPREAD), kind == "true"
        stage = np.concatenate([a["stage"] for a in rs])
        u, n = np.unique(stage[sp], return_counts=True)
        st = {str(x): int(m) for x, m in zip(u, n, strict=True)}
        print(f"{name}: candidates {kind.size}, spread {sp.sum()} (stages {st}), true {tr.sum()}")
        for f in ("presence", "profile", "fixed", "fixed_oracle"):
            v = np.concatenate([a[f] for a in rs])
            print(f"  {f:12s} quantiles {q}: spread {np.round(np.percentile(v[sp], q), 2)}, "
                  f"true {np.round(np.percentile(v[tr], q), 2)}")  # fmt: skip
    variants = [("7c (module's constants)", lambda a: a["failed"])]
    for k in (0, 2, 5):
        variants.append((f"7c, co-occurrence <= {k}", lambda a, k=k: a["failed"] & (a["k"] <= k)))
    for f in ("fixed", "fixed_oracle"):
        for c in (0.0, 2.0, 4.0):

            def rule(a, f=f, c=c):
                gsum = np.bincount(a["group"], weights=a[f])[a["group"]]
                return a["tested"] & (gsum < -c)

            variants.append((f"group {f} < -{c:g}", rule))
    for f in ("line_all", "line_open"):
        for k in (None, 0, 2):

            def rule(a, f=f, k=k):
                fail = a["tested"] & (a[f] < a["level"])
                return fail if k is None else fail & (a["k"] <= k)

            variants.append((f"{f}" + ("" if k is None else f", co-occurrence <= {k}"), rule))
    print("variant: per scene, true removed / false removed (spread of them), summed over seeds")
    for label, rule in variants:
        txt, by = [], ""
        for name, rs in rows.items():
            t = fl = spr = 0
            kinds = {}
            for a in rs:
                rm = removed(a, rule(a))
                t += int(np.sum(rm & (a["kind"] == "true")))
                fl += int(np.sum(rm & (a["kind"] != "true")))
                spr += int(np.sum(rm & np.isin(a["kind"], SPREAD)))
                for x in a["kind"][rm & (a["kind"] != "true")]:
                    kinds[x] = kinds.get(x, 0) + 1
            txt.append(f"{name} {t} / {fl} ({spr})")
            if name == "single":
                by = "; single by kind " + ", ".join(f"{x} {n}" for x, n in sorted(kinds.items()))
        print(f"  {label:36s} " + ", ".join(txt) + by, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
