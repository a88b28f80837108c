"""Issue #15, point 5: can a detector of this family reach <= 50 false surfaces at F_true >= 0.975?

Oracle experiments on the issue's cells (``bench_false_surfaces.py``'s single-surface
scene, 96 x 80 = 7,680 pixels, PPP 4, SBR 0.25, tau = 3 bins, uniform and decaying
background). Each cube is detected at several operating points ``pfa:surface_pfa``
(the detector's own trade-off between F_true and false surfaces); each false surface
is put in its kind (``bench_false_surfaces.false_kinds``); then:

* **kind oracles**: a clean-up that knows the truth removes every false surface of one
  kind (or of several), and nothing else; the wrong depths are either removed or
  *fixed* (moved onto the pixel's missed true depth: one false surface fewer, one true
  surface more). The figure per oracle is the fewest false surfaces over the operating
  points at which the mean F_true of seeds is >= 0.975.
* **a level for further surfaces** (not an oracle: the statistic is the detector's
  own): every false surface of the spread, background and window-edge kinds is a
  pixel's further surface (one of two). Removing the further surfaces below a level
  of a statistic (``evidence``, ``presence_llr``) traces a curve; the figure is its
  fewest false surfaces with F_true >= 0.975 (each cube's own level: an optimistic
  bound for one level shared by the cubes).
* **the wrong depths the own counts could decide**: for each wrong depth, the own raw
  counts' Poisson log-likelihood of a return of the true intensity at the true depth
  less that at the estimate (true background), and how many 4-neighbours hold the true
  depth; then the level table above with, per cube, the wrong depths whose own counts
  favour the truth fixed (what a clean-up with perfect proposals could do), the level
  capped at the presence test's 3 nats or not.
* **an oracle background** (``--true-background``): stage 1's temporal shape replaced
  by the true one (the simulation's, matched-filtered), the rest of the detection
  unchanged; and the background-alone figure (``--null``).

Usage::

    python benchmarks/bench_false_oracle.py --seeds 0 1 2
    python benchmarks/bench_false_oracle.py --points 1e-3:0.01 --true-background --null

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_false_surfaces import N_BINS, SHAPE, SINGLE, TAU, false_causes, false_kinds  # noqa: E402

from splidar import Cube  # noqa: E402
from splidar.detection import _detect, detect  # noqa: E402
from splidar.detection._1_background import TemporalBackground  # noqa: E402
from splidar.detection._filters import Correlator, irf_fwhm  # noqa: E402
from splidar.metrics import match_points  # noqa: E402
from splidar.scenes import single_surface_scene  # noqa: E402

POINTS = ("1e-3:0.01", "1e-3:0.003", "1e-3:0.03", "1e-3:0.1", "1e-4:0.03", "1e-4:0.1", "3e-5:0.1")
GROUPS = {
    "spread": ("spread 1 px", "spread 2-5 px"),
    "background": ("background", "window edge"),
    "wrong": ("wrong depth near", "wrong depth far"),
}


def _oracles():
    """(name, kinds removed, fix wrong depths) for every combination of the groups."""
    out = [("none", (), False)]
    names = list(GROUPS)
    for n in range(1, 4):
        for combo in itertools.combinations(names, n):
            kinds = tuple(k for g in combo for k in GROUPS[g])
            out.append(("remove " + "+".join(combo), kinds, False))
            if "wrong" in combo:
                out.append(("fix wrong, remove " + "+".join(combo), kinds, True))
    return out


ORACLES = _oracles()


class _TrueShape:
    """Replaces stage 1 by the true temporal shape (matched-filtered) while active."""

    def __init__(self, temporal: np.ndarray, spatial_mean: np.ndarray):
        self.temporal, self.mean = temporal, spatial_mean

    def __call__(self, counts, corr: Correlator, irf, **_):
        t = np.asarray(self.temporal, np.float64) * self.mean[:, None]  # (L, T) counts per bin
        lam = np.asarray(corr(t[None, None]), np.float64)[0, 0]  # matched-filtered
        dev = (lam - lam.mean(axis=-1, keepdims=True)).astype(np.float32)
        return TemporalBackground(temporal=lam, dev=dev)

    def __enter__(self):
        self.saved = _detect.estimate_temporal_background
        _detect.estimate_temporal_background = self
        return self

    def __exit__(self, *exc):
        _detect.estimate_temporal_background = self.saved


def decidable(det, sim, false, kinds, miss) -> list:
    """For each wrong depth, the own raw counts' Poisson log-likelihood of a return of
    the true intensity at the true depth less that at the estimate (true background),
    and how many of its 4-neighbours hold a surface within tau of the true depth."""
    pts, truth = det.points, sim.truth
    irf = np.asarray(sim.cube.irf, np.float64).reshape(-1)
    irf = irf / irf.sum()
    lag = np.arange(irf.size) - int(np.argmax(irf))
    t = np.arange(N_BINS, dtype=np.float64)
    out = []
    for j, kind in zip(false, kinds, strict=True):
        if not kind.startswith("wrong"):
            continue
        r, c, d = int(pts.row[j]), int(pts.col[j]), float(pts.depth_bin[j])
        here = miss[(truth.row[miss] == r) & (truth.col[miss] == c)]
        if not here.size:
            continue
        q = here[np.argmin(np.abs(truth.depth_bin[here] - d))]
        x0, s = float(truth.depth_bin[q]), float(truth.intensity[q].sum())
        b = sim.background(slice(r, r + 1), slice(c, c + 1))[0, 0, 0]
        y = np.asarray(sim.cube.counts[r, c, 0], np.float64)

        def loglik(x, y=y, b=b, s=s):
            g = np.interp(t - x, lag, irf, left=0.0, right=0.0)
            return float(np.sum(y * np.log1p(s * g / b)) - s * g.sum())

        n4 = (np.abs(pts.row - r) + np.abs(pts.col - c)) == 1
        held = int(np.sum(np.abs(pts.depth_bin[n4] - x0) <= TAU))
        out.append((kind, round(loglik(x0) - loglik(d), 3), held))
    return out


def score(det, truth, fwhm: float, sim=None) -> dict:
    """Per-oracle (matched, false) counts and the further-surface level curves."""
    pts = det.points
    false, cause = false_causes(pts, truth)
    kinds = np.array([k[0] for k in false_kinds(pts, truth, false, cause, N_BINS, fwhm)])
    n_true = len(truth)
    m = match_points(pts, truth, tau=TAU)
    n_match = n_true - len(m.unmatched_true)
    out = {"n_true": n_true, "n_match": n_match, "n_false": int(false.size)}
    out["by_kind"] = {k: int(np.sum(kinds == k)) for g in GROUPS.values() for k in g}
    if sim is not None:
        miss = np.asarray(m.unmatched_true, np.int64)
        out["decidable"] = decidable(det, sim, false, kinds, miss)
    for name, removed, fix in ORACLES:
        hit = np.isin(kinds, removed)
        gain = int(np.sum(hit & np.char.startswith(kinds, "wrong"))) if fix else 0
        out[name] = (n_match + gain, int(false.size - hit.sum()))
    # a level for the pixel's further surfaces (the detector's own statistics)
    s = det.surfaces
    pix = s.row * SHAPE[1] + s.col
    n_in = np.bincount(pix, minlength=SHAPE[0] * SHAPE[1])[pix]
    is_false = np.zeros(len(s.row), bool)
    is_false[false] = True
    kind_of = np.full(len(s.row), "true", dtype=object)
    kind_of[false] = kinds
    further = n_in >= 2
    curves = {}
    for stat in ("evidence", "presence_llr"):
        v = np.asarray(getattr(s, stat), np.float64)
        # in each pixel holding two, the surface of lower statistic is the further one
        order = np.lexsort((v, pix))
        p_sorted = pix[order]
        first = np.r_[True, p_sorted[1:] != p_sorted[:-1]]
        lower = np.zeros(len(v), bool)
        lower[order[first]] = True  # lowest statistic of its pixel
        cand = further & lower
        idx = np.flatnonzero(cand)
        idx = idx[np.argsort(v[idx])]
        lost = np.cumsum(~is_false[idx])
        dropped = np.cumsum(is_false[idx])
        curves[stat] = (np.r_[0, lost].tolist(), np.r_[0, dropped].tolist())
        curves[stat + "_kinds"] = [str(k) for k in kind_of[idx]]
        curves[stat + "_values"] = v[idx].round(4).tolist()
    out["curves"] = curves
    return out


def run(seeds, points, true_bg: bool, null: bool) -> list:
    scene = single_surface_scene(SHAPE, n_bins=N_BINS)
    rows = []
    for seed in seeds:
        for i, cell in enumerate(SINGLE):
            bg, ppp, sbr = cell
            rng = np.random.default_rng([seed, i])  # bench_false_surfaces' cubes
            sim = scene.simulate(ppp=ppp, sbr=sbr, background=bg, rng=rng)
            fwhm = irf_fwhm(np.asarray(sim.cube.irf, np.float64).reshape(1, -1))
            for pt in points:
                pfa, spfa = (float(x) for x in pt.split(":"))
                variants = [("estimated", None)]
                if true_bg:
                    sp = sim.background_spatial.reshape(-1, sim.background_spatial.shape[-1])
                    variants.append(("true shape", _TrueShape(sim.background_temporal, sp.mean(0))))
                for name, patch in variants:
                    if patch is None:
                        det = detect(sim.cube, rng=0, pfa=pfa, surface_pfa=spfa)
                    else:
                        with patch:
                            det = detect(sim.cube, rng=0, pfa=pfa, surface_pfa=spfa)
                    r = dict(seed=seed, bg=bg, point=pt, background_shape=name)
                    r.update(score(det, sim.truth, fwhm, sim))
                    if null:
                        lam = sim.background_spatial[..., None] * sim.background_temporal
                        y = np.random.default_rng([seed, i, 7]).poisson(lam).astype(np.uint16)
                        cube0 = Cube(y, irf=sim.cube.irf)
                        if patch is None:
                            d0 = detect(cube0, rng=0, pfa=pfa, surface_pfa=spfa)
                        else:
                            with patch:
                                d0 = detect(cube0, rng=0, pfa=pfa, surface_pfa=spfa)
                        r["null_false"] = len(d0.points)
                        r["null_depths"] = np.asarray(d0.points.depth_bin).round(1).tolist()
                    rows.append(r)
                    print(
                        f"seed {seed} {bg:8s} {pt:11s} {name:10s} F_true "
                        f"{r['n_match'] / r['n_true']:.4f} false {r['n_false']:4d} "
                        + ("" if not null else f"null {r['null_false']:3d} ")
                        + str(r["by_kind"]),
                        flush=True,
                    )
    return rows


def summarise(rows, target_f=0.975) -> None:
    for shape in sorted({r["background_shape"] for r in rows}):
        for bg in ("uniform", "decaying"):
            sel = [r for r in rows if r["bg"] == bg and r["background_shape"] == shape]
            if not sel:
                continue
            pts = sorted({r["point"] for r in sel}, key=lambda p: [float(x) for x in p.split(":")])
            print(f"\n== {bg}, background shape {shape}: means over seeds, F_true / false")
            best = {}
            for name, _, _ in ORACLES:
                cells = []
                for p in pts:
                    rs = [r for r in sel if r["point"] == p]
                    f = np.mean([r[name][0] / r["n_true"] for r in rs])
                    n = np.mean([r[name][1] for r in rs])
                    cells.append(f"{f:.4f}/{n:5.1f}")
                    if f >= target_f and n < best.get(name, (np.inf,))[0]:
                        best[name] = (n, p, f)
                print(f"  {name:42s} " + "  ".join(cells))
            print("  points: " + "  ".join(f"{p:>12s}" for p in pts))
            if "null_false" in sel[0]:
                nul = [np.mean([r["null_false"] for r in sel if r["point"] == p]) for p in pts]
                print("  background alone: " + "  ".join(f"{x:.1f}" for x in nul))
            print(f"  fewest false at mean F_true >= {target_f}:")
            for name, _, _ in ORACLES:
                b = best.get(name)
                txt = "not reached" if b is None else f"{b[0]:.1f} at {b[1]} (F_true {b[2]:.4f})"
                print(f"    {name:42s} {txt}")
            for stat in ("evidence", "presence_llr"):
                res = []
                for p in pts:
                    rs = [r for r in sel if r["point"] == p]
                    tot = 0.0
                    ok = True
                    for r in rs:
                        lost, dropped = (np.asarray(a) for a in r["curves"][stat])
                        room = r["n_match"] - int(np.ceil(target_f * r["n_true"]))
                        k = np.flatnonzero(lost <= room)
                        if room < 0 or not k.size:
                            ok = False
                            break
                        tot += r["n_false"] - dropped[k[-1]]
                    res.append(f"{tot / len(rs):5.1f}" if ok else "  -  ")
                print(f"  further surfaces below a level of {stat} (per cube): " + "  ".join(res))
            _print_decidable(sel, pts)
            for p_fix in FIX_FRACTIONS:
                res = []
                for p in pts:
                    rs = [r for r in sel if r["point"] == p]
                    res.append(_level_and_fix(rs, p_fix, target_f))
                print(
                    f"  one presence_llr level + {p_fix:.0%} of the other wrong depths fixed: "
                    + "  ".join(f"{x:5.1f}" if x is not None else "  -  " for x in res)
                )


FIX_FRACTIONS = (0.0, 0.5, 0.75, 1.0)


def _decidable_fraction(r) -> float:
    """The fraction of a cube's wrong depths whose own counts favour the true depth
    (log-likelihood difference >= 0): what perfect proposals would fix."""
    dec = r.get("decidable", [])
    return float(np.mean([d[1] >= 0 for d in dec])) if dec else 0.0


def _level_and_fix(rs, p_fix, target_f: float, cap: float = np.inf):
    """The fewest false surfaces (mean over the cubes) with mean F_true >= target_f when
    the further surfaces below one level (at most ``cap``) of ``presence_llr`` (shared
    by the cubes) are removed and the fraction ``p_fix`` of the wrong depths left is
    fixed (oracle; None: each cube's own-count-decidable fraction); None if not
    reached."""
    vals = [np.asarray(r["curves"]["presence_llr_values"], np.float64) for r in rs]
    levels = np.unique(np.concatenate([[-np.inf, np.inf], *vals]))
    levels = levels[levels <= cap]
    match = np.zeros(levels.size)
    false = np.zeros(levels.size)
    for r in rs:
        kinds = np.asarray(r["curves"]["presence_llr_kinds"], dtype=str)
        v = np.asarray(r["curves"]["presence_llr_values"])
        # removed at level L: v < L (v sorted ascending)
        k = np.searchsorted(v, levels, side="left")
        lost = np.r_[0, np.cumsum(kinds == "true")][k]
        dropped = np.r_[0, np.cumsum(kinds != "true")][k]
        wrong_gone = np.r_[0, np.cumsum(np.char.startswith(kinds, "wrong"))][k]
        wrong = r["by_kind"]["wrong depth near"] + r["by_kind"]["wrong depth far"]
        p = _decidable_fraction(r) if p_fix is None else p_fix
        fixes = np.floor(p * (wrong - wrong_gone))
        match += (r["n_match"] - lost + fixes) / r["n_true"] / len(rs)
        false += (r["n_false"] - dropped - fixes) / len(rs)
    ok = match >= target_f
    if not ok.any():
        return None
    return float(false[ok].min())


def _print_decidable(sel, pts) -> None:
    """The wrong depths by what the own counts say (first point's cubes) and the level
    table with the own-count-decidable ones fixed."""
    ref = "1e-3:0.01" if "1e-3:0.01" in pts else pts[0]  # the default point first
    rs = [r for r in sel if r["point"] == ref and "decidable" in r]
    if not rs:
        return
    d = [x for r in rs for x in r["decidable"]]
    dl = np.array([x[1] for x in d])
    held = np.array([x[2] for x in d])
    n = len(rs)
    print(
        f"  wrong depths at {ref} (per cube): {dl.size / n:.1f}; own counts favour the "
        f"truth by > 1 nat {np.sum(dl > 1) / n:.1f}, within 1 nat {np.sum(abs(dl) <= 1) / n:.1f}, "
        f"favour the estimate {np.sum(dl < -1) / n:.1f}; decidable (>= 0) "
        f"{np.sum(dl >= 0) / n:.1f}, of them with 1 / 2 / 3 4-neighbours at the true depth "
        + " / ".join(f"{np.sum((dl >= 0) & (held >= k)) / n:.1f}" for k in (1, 2, 3))
    )
    for cap in (PRESENCE_CAP, np.inf):
        res = [_level_and_fix([r for r in sel if r["point"] == p], None, 0.975, cap) for p in pts]
        print(
            f"  one presence_llr level <= {cap:g} + the decidable wrong depths fixed: "
            + "  ".join(f"{x:5.1f}" if x is not None else "  -  " for x in res)
        )


#: The cap of the further-surface level in the decidable table: the presence test's
#: rejection level (``PRESENCE_LLR``, 3 nats), so a second surface whose own counts
#: speak for it stays (the partly transmissive layer, the net).
PRESENCE_CAP = 3.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--points", nargs="+", default=list(POINTS), help="pfa:surface_pfa")
    ap.add_argument("--true-background", action="store_true", help="also with stage 1 = truth")
    ap.add_argument("--null", action="store_true", help="also detect on the background alone")
    ap.add_argument("--json", help="write the rows to this JSON file")
    ap.add_argument("--from-json", help="summarise rows written earlier")
    args = ap.parse_args(argv)
    if args.from_json:
        rows = json.loads(Path(args.from_json).read_text())
    else:
        rows = run(args.seeds, args.points, args.true_background, args.null)
        if args.json:
            Path(args.json).write_text(json.dumps(rows))
    summarise(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
