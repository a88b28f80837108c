"""Issue #15, point 5: the further surfaces decided by group, on their own counts.

The largest kind of false surface left at the issue's figures (single surface, PPP 4,
SBR 0.25, tau 3 bins; benchmarks/README.md "near27, session 19") is a pixel's *further*
surface beside a depth edge: the multiscale boxes pool the neighbouring region's
return into the pixel, which keeps its own surface and gains the neighbour's depth
(``spread 1 px`` / ``spread 2-5 px``). Its own raw counts hold no return there. One
pixel's 0.3-2 photons cannot show that (falsesurf3, false24), so the further
surfaces are tested by group: the surfaces of the pixels holding two or more
(candidates) are joined 8-connected with depths within ``GATE_FWHM`` FWHM of each
other (stage 7b's gate), and each group's joint log-likelihood ratio of a return at
its members' depths against the pixel's own background (stage 1), with one intensity
``s`` shared by the group and profiled out (the statistic of stage 7b,
``_7b_edge_bands.profile_llr``, summed over the group before the maximum over ``s``;
``detection/_7c_spread_groups.py``, off in ``detect``),

    ``L_G = max_s sum_{p in G} [sum_t y_pt log(1 + s g_pt / b_pt) - s sum_t g_pt]``,

decides: a candidate whose group has ``L_G`` below a level is removed, but only where
another surface of its pixel passes (a pixel never loses all its surfaces, and in a
dim pixel whose own surface fails the pixel is left as it is). Levels: fixed (3 and 6
nats) and a prior measured on the detection, ``log((1 - q) / q)`` with ``q`` the
fraction of the pixels holding a surface that hold two or more (stage 7b's way of
setting its Potts weight).

With ``--axes A`` only candidates that do not *continue* through their pixel are tested:
of the 4 axes through the pixel (opposite 8-neighbours: left-right, up-down, the two
diagonals) fewer than ``A`` have a surface within the gate of the candidate's depth on
both sides (``--reach 2``: at 1 or 2 pixels on each side). A surface that stops at the
pixel is how a neighbour's spread looks (its region lies on one side only); a surface
seen on both sides (an object behind a net's strand, a sheet continuing) was pooled
rightly. ``--axes 5`` (the default here) tests every candidate; the module's constants
are ``AXES = 2``, ``REACH = 1``. ``--source``: only candidates with an 8-neighbour in a
region of single-surface pixels at their depth (stage 7b's regions) are tested;
``--edge``: only candidates on a depth edge (a single-surface pixel at their depth on
one side, at their pixel's other depth on the other); ``--behind H``: only candidates
whose depth the pixels within ``H`` that hold no surface there do not show either
(their counts pooled with one shared intensity, below the level).

Each cube is the detection of ``bench_edge_bands.py`` (``passes`` without
``"edge_bands"``; read from its ``--cache``), stage 7b's depth rule applied
(``band_depths``: today's detector's depths), then the group rule: F_true and false
surfaces before and after, and per cube the true / false surfaces removed. Cells: the
single-surface ones and the sheet and net layer cells, as ``bench_edge_bands.py``.

Usage::

    python benchmarks/bench_spread_groups.py --seeds 0 1 2 [--cache DIR] [--levels 3 6]

Nothing is downloaded; everything is simulated. Measured, not adopted (benchmarks/
README.md, "spread28, session 20").
"""

from __future__ import annotations

import argparse

import numpy as np
from bench_edge_bands import SINGLE, TAU, _detected, _matched
from bench_false_surfaces import LAYER

from splidar.detection._7b_edge_bands import MIN_REGION, band_depths, region_labels
from splidar.detection._7c_spread_groups import GATE_FWHM, _windows, group_llr, spread_groups
from splidar.detection._filters import irf_fwhm
from splidar.metrics import PointSet, evaluate


def sourced(s, depth, cand, gate: float) -> np.ndarray:
    """(n,) bool: per candidate, whether an 8-neighbour is a member of a region of
    single-surface pixels (stage 7b's ``region_labels``, at least ``MIN_REGION``
    members) with its depth within ``gate`` bins: a source whose return the boxes could
    have spread into the pixel."""
    R, C = s.image_shape
    pix = s.row * C + s.col
    solo = np.flatnonzero(np.bincount(pix, minlength=R * C)[pix] == 1)
    D = np.full((R, C), np.nan)
    D[s.row[solo], s.col[solo]] = depth[solo]
    lab = region_labels(D, gate)
    size = np.bincount(lab[lab >= 0], minlength=1)
    D[(lab < 0) | (size[np.maximum(lab, 0)] < MIN_REGION)] = np.nan
    pad = np.pad(D, 1, constant_values=np.nan)
    out = np.zeros(cand.size, bool)
    r, c, d = s.row[cand], s.col[cand], depth[cand]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                with np.errstate(invalid="ignore"):
                    out |= np.abs(pad[r + 1 + dr, c + 1 + dc] - d) <= gate
    return out


def between(s, depth, cand, gate: float) -> np.ndarray:
    """(n,) bool: per candidate, whether along some axis through its pixel one neighbour
    is a single-surface pixel at its depth and the opposite neighbour a single-surface
    pixel at the depth of another surface of its pixel (within ``gate`` bins): the
    pixel sits on a depth edge between two regions, the pattern of a neighbour's spread."""
    R, C = s.image_shape
    pix = s.row * C + s.col
    n_at = np.bincount(pix, minlength=R * C)
    D = np.full((R, C), np.nan)
    solo = n_at[pix] == 1
    D[s.row[solo], s.col[solo]] = depth[solo]
    mine: dict[int, list[float]] = {}
    for i in range(len(s)):
        mine.setdefault(int(pix[i]), []).append(float(depth[i]))
    dirs = (((0, 1), (0, -1)), ((1, 0), (-1, 0)), ((1, 1), (-1, -1)), ((1, -1), (-1, 1)))
    out = np.zeros(cand.size, bool)
    for n, i in enumerate(cand):
        r, c, d = int(s.row[i]), int(s.col[i]), float(depth[i])
        others = [x for x in mine[int(pix[i])] if abs(x - d) > gate]
        for a, b in dirs:
            for (r1, c1), (r2, c2) in ((a, b), (b, a)):
                p1, p2 = (r + r1, c + c1), (r + r2, c + c2)
                if not (0 <= p1[0] < R and 0 <= p1[1] < C and 0 <= p2[0] < R and 0 <= p2[1] < C):
                    continue
                x1, x2 = D[p1], D[p2]
                if abs(x1 - d) <= gate and any(abs(x2 - o) <= gate for o in others):
                    out[n] = True
    return out


def behind(s, depth, cand, counts, background, irf, gate: float, half: int) -> np.ndarray:
    """(n,) nats: per candidate, the joint log-likelihood ratio (one shared intensity,
    ``group_llr``) of a return at its depth in the pixels within ``half`` (Chebyshev,
    the pixel itself left out) that hold no surface within ``gate`` bins of it: does the
    surface continue, undetected, behind its neighbours' own surfaces (a layer's object,
    a strand the map missed), or does it stop (a neighbour's spread: the other side
    holds only background at that depth)?"""
    R, C = s.image_shape
    held = np.full((R, C, 4), np.nan)
    k = np.zeros((R, C), np.int64)
    for i in range(len(s)):
        r, c = int(s.row[i]), int(s.col[i])
        if k[r, c] < 4:
            held[r, c, k[r, c]] = depth[i]
            k[r, c] += 1
    owner, rr, cc, dd = [], [], [], []
    for n, i in enumerate(cand):
        r0, c0, d = int(s.row[i]), int(s.col[i]), float(depth[i])
        r1, r2, c1, c2 = (
            max(r0 - half, 0),
            min(r0 + half + 1, R),
            max(c0 - half, 0),
            min(c0 + half + 1, C),
        )
        with np.errstate(invalid="ignore"):
            has = (np.abs(held[r1:r2, c1:c2] - d) <= gate).any(axis=2)
        has[r0 - r1, c0 - c1] = True
        a, b = np.nonzero(~has)
        owner.append(np.full(a.size, n))
        rr.append(a + r1)
        cc.append(b + c1)
        dd.append(np.full(a.size, d))
    owner = np.concatenate(owner)
    y, g, b = _windows(counts, background, np.concatenate(rr), np.concatenate(cc),
                       np.concatenate(dd), irf)  # fmt: skip
    out = np.zeros(cand.size)
    if owner.size:
        llr = group_llr(y, g, b, owner)
        out[: llr.size] = llr
    return out


def _score(s, depth, keep, truth):
    pts = PointSet(
        row=s.row[keep], col=s.col[keep], depth_bin=depth[keep], image_shape=s.image_shape,
        intensity=s.photons[keep], layer=s.slot[keep],
    )  # fmt: skip
    return evaluate(pts, truth, tau=TAU).f_true, int((~_matched(pts, truth)).sum()), pts


def run(
    name,
    seed,
    rng_key,
    cell,
    cache,
    levels,
    axes=5,
    reach=1,
    source=False,
    edge=False,
    behind_half=0,
    behind_level=None,
) -> dict:
    """Stage 7c's rule (``spread_groups``) at the prior level and at ``levels`` on one
    cube (see the module)."""
    d = _detected(name, seed, rng_key, cell, cache)
    s, counts, truth = d["surfaces"], d["counts"], d["truth"]
    irf = np.atleast_2d(np.asarray(d["irf"], np.float64))
    fwhm = irf_fwhm(irf)
    depth = band_depths(s, counts, d["background"], fwhm=fwhm, irf=irf, half=d["half"])[0]
    sg = spread_groups(
        s.row, s.col, depth, s.image_shape, counts, d["background"], fwhm=fwhm, irf=irf,
        axes=axes, reach=reach,
    )  # fmt: skip
    cand, tested = sg.candidates, sg.tested.copy()
    if source:
        tested &= sourced(s, depth, cand, GATE_FWHM * fwhm)
    if edge:
        tested &= between(s, depth, cand, GATE_FWHM * fwhm)
    if behind_half:
        lc = behind(s, depth, cand, counts, d["background"], irf, GATE_FWHM * fwhm, behind_half)
        tested &= lc < (sg.level if behind_level is None else behind_level)
    R, C = s.image_shape
    pix = s.row[cand] * C + s.col[cand]
    everything = np.ones(len(s), bool)
    f0, n0, pts = _score(s, depth, everything, truth)
    ok = _matched(pts, truth)[cand]
    out = dict(scene=name, bg=cell[0], ppp=cell[1], f0=f0, n0=n0, res=[])
    line = f"{name:6s} {seed:2d} {cell[0]:9s} PPP {cell[1]:2g}  {f0:.4f} / {n0:3d}"
    for level in [sg.level, *levels]:
        fail = (sg.group_llr < level) & tested
        passes = np.bincount(pix, weights=~fail, minlength=R * C)
        gone = fail & (passes[pix] >= 1)
        keep = everything.copy()
        keep[cand[gone]] = False
        f1, n1, _ = _score(s, depth, keep, truth)
        t_off, f_off = int((gone & ok).sum()), int((gone & ~ok).sum())
        out["res"].append((f1, n1, t_off, f_off))
        line += f"  L {level:4.2f}: {f1:.4f} / {n1:3d} (-T {t_off}, -F {f_off})"
    print(line, flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--cache", help="bench_edge_bands.py's cache of detections")
    ap.add_argument("--levels", type=float, nargs="+", default=[3.0, 6.0])
    ap.add_argument("--only", choices=("single", "layer"), help="run one of the two")
    ap.add_argument("--axes", type=int, default=5, help="test candidates continued on < A axes")
    ap.add_argument("--reach", type=int, default=1, help="pixels along an axis (--axes)")
    ap.add_argument("--source", action="store_true", help="test only candidates beside a source")
    ap.add_argument("--edge", action="store_true", help="test only candidates on a depth edge")
    ap.add_argument("--behind", type=int, default=0, help="half-width of the behind test")
    ap.add_argument("--behind-level", type=float, help="its level (default: the prior)")
    args = ap.parse_args(argv)
    opts = dict(axes=args.axes, reach=args.reach, source=args.source, edge=args.edge,
                behind_half=args.behind, behind_level=args.behind_level)  # fmt: skip
    rows = []
    for seed in args.seeds:
        if args.only != "layer":
            for i, cell in enumerate(SINGLE):
                rows.append(run("single", seed, [seed, i], cell, args.cache, args.levels, **opts))
        if args.only != "single":
            for j, name in enumerate(("sheet", "net")):
                for i, cell in enumerate(LAYER):
                    key = [seed, 100 * (j + 1) + i]
                    rows.append(run(name, seed, key, cell, args.cache, args.levels, **opts))
    print("means (F_true / false; the first level is the measured prior log((1 - q) / q))")
    for name in ("single", "sheet", "net"):
        for bg, ppp in (("uniform", 4), ("decaying", 4), ("uniform", 10)):
            sel = [r for r in rows if (r["scene"], r["bg"], r["ppp"]) == (name, bg, ppp)]
            if not sel:
                continue
            line = (
                f"{name:6s} {bg:9s} PPP {ppp:2d}: {np.mean([r['f0'] for r in sel]):.4f} / "
                f"{np.mean([r['n0'] for r in sel]):.1f}"
            )
            for k in range(len(sel[0]["res"])):
                f1 = np.mean([r["res"][k][0] for r in sel])
                n1 = np.mean([r["res"][k][1] for r in sel])
                line += f" | {f1:.4f} / {n1:.1f}"
            print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
