"""Ablation of the clean-up passes of ``splidar.detect``: what each pass contributes.

For every cell of simulated families (scene x photon regime x background x IRF), the
detection runs with all passes (the default) and with each pass left out
(``passes=`` without it), on the same cubes (several seeds); and with each sub-rule of
stage 7b (``edge_bands``) switched off on its own, the labelling and the other sub-rules
kept: ``-7b:near_depths``, ``-7b:far_inside`` (module constants of
``splidar.detection._7b_edge_bands``, not ``passes=`` entries; :func:`rules_off` sets
them for one detection and restores them). Reported per pass: the
change of F_true (tau = 3 bins), of false surfaces per 100 true ones and of the depth
error DAE (bins) when the pass is *removed*, averaged over cells and seeds, with the
run-to-run noise: the standard error of the mean paired difference over the seeds
(each seed draws new cubes). A pass whose every effect lies within 2 standard errors of
zero is a candidate for removal.

Families: single surface (steps, slopes, dark patches), a thin partly transmissive net
in front of objects (``two_layer_scene``), multispectral (L = 4, with a net); PPP 1, 4,
10; uniform and decaying background; a Gaussian IRF (FWHM 3 bins) and the measured,
wide, asymmetric IRF of ``../shared/data/irf-sample`` (a flat top with a tail, FWHM
about 15 bins, 27 bins long).

Usage::

    python benchmarks/bench_ablation.py --quick        # 24 x 24 scenes, 1 seed (minutes)
    python benchmarks/bench_ablation.py                # 32 x 32 scenes, 3 seeds
    python benchmarks/bench_ablation.py --json out.json
    python benchmarks/bench_ablation.py --families art --seeds 1   # the paper's Art scene

Nothing is downloaded; the IRF sample is read from ``../shared/data`` when present (the
measured-IRF cells are skipped otherwise).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from splidar.detection import PASSES, detect
from splidar.detection import _7b_edge_bands as _7b
from splidar.metrics import evaluate
from splidar.scenes import art_scene, multispectral_scene, single_surface_scene, two_layer_scene

TAU = 3.0
IRF_SAMPLE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "irf-sample"
# photon regimes: (PPP, SBR) per scene family (SBR low where the issue's targets are)
REGIMES = {"single": ((1, 1.0), (4, 0.25), (10, 1.0)), "net": ((1, 1.0), (4, 0.25), (10, 1.0))}
REGIMES["multi"] = REGIMES["net"]
# the paper's simulated Art scene (185 x 232, two copies one behind the other, RGB)
REGIMES["art"] = ((1, 1.0), (4, 1.0), (16, 1.0))
ART = IRF_SAMPLE.parent / "middlebury-art"


def measured_irf(rebin: int = 1):
    """The measured pulse shape of irf-sample, trimmed (>= 0.5 % of its max), optionally
    rebinned."""
    import scipy.io

    path = IRF_SAMPLE / "data_supp.mat"
    if not path.exists():
        return None
    w = np.asarray(scipy.io.loadmat(path)["waveform_shape"], np.float64).ravel()
    w = w - np.median(w[:100])  # the baseline before the pulse
    w = np.clip(w, 0, None)
    keep = np.flatnonzero(w >= 0.005 * w.max())
    w = w[keep[0] : keep[-1] + 1]
    n = w.size // rebin * rebin
    w = w[:n].reshape(-1, rebin).sum(axis=1)
    return w / w.sum()


def scenes(shape, n_bins, irfs, families):
    out = {}
    for irf_name, irf in irfs.items():
        if "single" in families:
            out[("single", irf_name)] = single_surface_scene(shape, n_bins=n_bins, irf=irf)
        if "net" in families:
            out[("net", irf_name)] = two_layer_scene(shape, n_bins=n_bins, irf=irf)
        if "multi" in families:
            out[("multi", irf_name)] = multispectral_scene(
                shape, n_bins=n_bins, irf=irf, two_layers=True
            )
    if "art" in families:
        if ART.is_dir():
            out[("art", "gauss3")] = art_scene(ART)  # T = 164, Gaussian FWHM 3 bins
        else:
            print(f"# no Art scene at {ART}: skipped", file=sys.stderr)
    return out


#: Stage 7b's sub-rules: variant suffix -> the module constant of ``_7b_edge_bands``
#: that switches it (each runs in ``band_depths`` after the bands' labelling).
RULES_7B = {"near_depths": "NEAR_DEPTHS", "far_inside": "FAR_INSIDE"}


@contextmanager
def rules_off(rules=()):
    """Switch the named stage-7b sub-rules (keys of :data:`RULES_7B`) off for the ``with``
    block, and restore the module's values after it (also on an error). For the benchmark
    only: the detector itself has no option for them."""
    names = [RULES_7B[r] for r in rules]
    saved = {n: getattr(_7b, n) for n in names}
    try:
        for n in names:
            setattr(_7b, n, False)
        yield
    finally:
        for n, v in saved.items():
            setattr(_7b, n, v)


def variants(combos=()):
    """Variant name -> ``(passes, stage-7b sub-rules off)``: the default, each pass left
    out, each sub-rule of stage 7b left out (the pass kept), no pass at all, and the
    ``combos``: each a sequence of those left out together (pass names or ``7b:RULE``),
    named ``"-a -b"`` (whether two passes do the same job: their joint loss against the
    sum of the single ones)."""
    out = {"all": (PASSES, ())}
    for p in PASSES:
        out[f"-{p}"] = (tuple(q for q in PASSES if q != p), ())
    for r in RULES_7B:
        out[f"-7b:{r}"] = (PASSES, (r,))
    out["none"] = ((), ())
    for combo in combos:
        rules = tuple(c[3:] for c in combo if c.startswith("7b:"))
        drop = [c for c in combo if not c.startswith("7b:")]
        unknown = [c for c in drop if c not in PASSES] + [r for r in rules if r not in RULES_7B]
        if unknown:
            raise ValueError(f"unknown pass or 7b rule(s) {unknown} in {combo}")
        out[" ".join(f"-{c}" for c in combo)] = (tuple(q for q in PASSES if q not in drop), rules)
    return out


def run(args) -> list[dict]:
    shape = (24, 24) if args.quick else (args.size, args.size)
    seeds = range(1 if args.quick else args.seeds)
    irfs = {"gauss3": ("gaussian", 3.0)}
    m = measured_irf()
    if m is not None:
        irfs["measured"] = m
    else:
        print("# irf-sample not found: measured-IRF cells skipped", file=sys.stderr)
    rows = []
    families = args.families.split(",")
    for (fam, irf_name), scene in scenes(shape, args.bins, irfs, families).items():
        for ppp, sbr in REGIMES[fam]:
            for bg in ("uniform",) if fam == "art" else ("uniform", "decaying"):
                for seed in seeds:
                    sim = scene.simulate(ppp=ppp, sbr=sbr, background=bg, rng=seed)
                    for name, (passes, off) in variants(args.combos).items():
                        if args.variants and name not in args.variants.split(","):
                            continue
                        t0 = time.perf_counter()
                        with rules_off(off):
                            det = detect(sim.cube, passes=passes)
                        ev = evaluate(det.points, sim.truth, tau=TAU)
                        rows.append(
                            dict(
                                family=fam, irf=irf_name, ppp=ppp, sbr=sbr, bg=bg, seed=seed,
                                variant=name, f_true=ev.f_true,
                                false_per_100=100.0 * ev.f_false / max(ev.n_true, 1),
                                dae=float(ev.dae) if ev.dae is not None else float("nan"),
                                seconds=time.perf_counter() - t0,
                            )
                        )  # fmt: skip
                print(f"# {fam:6s} {irf_name:8s} PPP {ppp:<3g} SBR {sbr:<5g} done", flush=True)
    return rows


def summarise(rows: list[dict], combos=()) -> list[dict]:
    """Per variant: the mean paired change against "all" (the effect of removing the
    pass) over cells and seeds, its run-to-run noise and the cells it helps or hurts.

    The noise is the standard error of that mean from the spread of the paired change
    between seeds of the same cell (new cubes, same scene and regime), pooled over the
    cells: ``sqrt(mean_cells var_seeds(diff) / n)``.
    """
    cell = lambda r: (r["family"], r["irf"], r["ppp"], r["bg"])  # noqa: E731
    base = {cell(r) + (r["seed"],): r for r in rows if r["variant"] == "all"}
    out = []
    present = {r["variant"] for r in rows}
    for name in variants(combos):
        if name == "all" or name not in present:
            continue
        row = {"variant": name}
        for k in ("f_true", "false_per_100", "dae"):
            per_cell: dict = {}
            for r in rows:
                if r["variant"] == name:
                    diff = r[k] - base[cell(r) + (r["seed"],)][k]
                    per_cell.setdefault(cell(r), []).append(diff)
            diffs = np.array([d for v in per_cell.values() for d in v], np.float64)
            row["n_cells"] = len(per_cell)
            row[k] = float(np.nanmean(diffs))
            within = [np.nanvar(v, ddof=1) for v in per_cell.values() if len(v) > 1]
            row[k + "_se"] = float(np.sqrt(np.nanmean(within) / diffs.size)) if within else None
            cm = np.array([np.nanmean(v) for v in per_cell.values()])
            better = cm > 0 if k == "f_true" else cm < 0
            worse = cm < 0 if k == "f_true" else cm > 0
            # from the pass's point of view: removing it makes the figure better/worse
            row[k + "_cells_better_without"] = int(better.sum())
            row[k + "_cells_worse_without"] = int(worse.sum())
            row[k + "_worst"] = float(np.nanmin(diffs) if k == "f_true" else np.nanmax(diffs))
        out.append(row)
    return out


def table(summary: list[dict]) -> str:
    head = (
        "| pass removed | cells | dF_true | d false / 100 true | dDAE (bins) | "
        "cells F_true down / up | within noise |\n|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for r in summary:

        def f(k, fmt, r=r):
            se = r[k + "_se"]
            return f"{r[k]:{fmt}}" + (f" ± {se:{fmt.lstrip('+')}}" if se is not None else "")

        noise = all(
            r[k + "_se"] is not None and abs(r[k]) <= 2 * r[k + "_se"]
            for k in ("f_true", "false_per_100", "dae")
        )
        tag = "n/a (1 seed)" if r["f_true_se"] is None else ("yes" if noise else "no")
        lines.append(
            f"| {r['variant']} | {r['n_cells']} | {f('f_true', '+.4f')} | "
            f"{f('false_per_100', '+.2f')} | {f('dae', '+.3f')} | "
            f"{r['f_true_cells_worse_without']} / {r['f_true_cells_better_without']} | "
            f"{tag} |"
        )
    return "\n".join(lines)


def _moved_7b(det) -> int:
    """How many surfaces stage 7b (``edge_bands``) moved in a detection."""
    from splidar.detection._result import STAGES

    m = det.surfaces.moved_by
    return 0 if m is None else int(np.sum(np.asarray(m) == STAGES.index("edge_bands")))


def _differ(a, b) -> int:
    """Surfaces of one detection that the other lacks (same pixel and depth to 1e-6 bins),
    counted both ways."""

    def key(d):
        s = d.surfaces
        z = np.round(np.asarray(s.depth_bin, np.float64), 6).tolist()
        return set(zip(s.row.tolist(), s.col.tolist(), z, strict=True))

    ka, kb = key(a), key(b)
    return len(ka ^ kb)


def real_files(data: Path, rules: bool = False) -> None:
    """On the measured files (no truth): what each pass added and removed, by
    ``Detection.provenance`` (one detection each, default options); with ``rules``,
    also each stage-7b sub-rule switched off (:func:`rules_off`): the surfaces stage 7b
    moved and the surfaces that differ from the default."""
    from real_data import REAL

    import splidar

    for name, (rel, kw, desc) in REAL.items():
        path = data / rel
        if not path.is_file():
            print(f"# {name}: {path} missing, skipped")
            continue
        cube = splidar.load(path, **kw)
        t0 = time.perf_counter()
        det = detect(cube)
        print(f"\n== {name}: {desc}; {cube.shape}; {len(det.surfaces)} surfaces, "
              f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
        print(det.provenance_table())
        if not rules:
            continue
        print(f"   all: stage 7b moved {_moved_7b(det)}")
        for r in RULES_7B:
            with rules_off((r,)):
                other = detect(cube)
            n, m, d = len(other.surfaces), _moved_7b(other), _differ(det, other)
            print(f"   -7b:{r}: {n} surfaces, stage 7b moved {m}; {d} differ from all")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="24 x 24 scenes, one seed")
    ap.add_argument("--size", type=int, default=32, help="scene side in pixels (default 32)")
    ap.add_argument("--bins", type=int, default=200, help="time bins T (default 200)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per cell (default 3)")
    ap.add_argument(
        "--families",
        default="single,net,multi",
        help="scene families, comma-separated, of single, net, multi, art (Art: 185 x 232, "
        "PPP 1/4/16, SBR 1, uniform background, from ../shared/data/middlebury-art)",
    )
    ap.add_argument(
        "--variants",
        default="",
        help="run only these variants, comma-separated (e.g. 'all' for the default "
        "detection alone, to compare two versions of the code, printed row by row; with "
        "'all' and others, summarised; default: every one)",
    )
    ap.add_argument("--json", help="also write every row and the summary to this file")
    ap.add_argument("--from-json", help="summarise the rows of an earlier --json run")
    ap.add_argument(
        "--real",
        action="store_true",
        help="instead: the provenance (surfaces each pass added and removed) on the "
        "measured files of ../shared/data (face, tower, 21 km; no truth there)",
    )
    ap.add_argument(
        "--real-rules",
        action="store_true",
        help="with --real: also each stage-7b sub-rule switched off (3 more detections a "
        "file): the surfaces stage 7b moved and how many surfaces differ from the default",
    )
    ap.add_argument(
        "--combo",
        action="append",
        default=[],
        metavar="A,B",
        help="also leave these out together (pass names or 7b:RULE, comma-separated; "
        "repeatable), e.g. --combo align_depths,edge_bands --variants 'all,-align_depths "
        "-edge_bands'",
    )
    args = ap.parse_args(argv)
    args.combos = [tuple(c.split(",")) for c in args.combo]
    t0 = time.perf_counter()
    if args.real:
        real_files(IRF_SAMPLE.parent, rules=args.real_rules)
        return 0
    rows = json.loads(Path(args.from_json).read_text())["rows"] if args.from_json else run(args)
    chosen = set(args.variants.split(",")) if args.variants else set()
    if chosen and (chosen == {"all"} or "all" not in chosen):  # nothing to pair: the rows
        for r in rows:
            print(
                f"{r['family']:6s} {r['irf']:8s} PPP {r['ppp']:<3g} SBR {r['sbr']:<5g} "
                f"{r['bg']:9s} seed {r['seed']} {r['variant']:14s} F_true {r['f_true']:.4f} "
                f"false/100 {r['false_per_100']:6.2f} DAE {r['dae']:.3f}"
            )
        if args.json:
            Path(args.json).write_text(json.dumps({"rows": rows}, indent=1))
        return 0
    summary = summarise(rows, args.combos)
    print(table(summary))
    print(f"# {len(rows)} detections in {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
