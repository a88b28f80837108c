"""The paper's simulated experiment: the Middlebury "Art" scene, two surfaces per pixel.

Reproduces the set-up of Belmekki et al., section "Evaluation on simulated data"
(``fig:3D_reconst_Art``, ``fig:Quant_3D_Art``): the Art scene (185 x 232 pixels,
T = 164 bins), two copies one behind the other so that every pixel holds two
surfaces, RGB as three wavelengths with a colour-class library
(:func:`splidar.scenes.art_scene`), several PPP and SBR, uniform and non-uniform
(decaying with range) background, metrics at tau = 4 mm.

The paper gives no numbers for its PPP and SBR levels ("two values of PPP and SBR",
plots against PPP and SBR), so the sweep covers PPP {1, 4, 16, 64} x SBR {0.25, 1, 4}
x background {uniform, decaying}. PPP = expected signal photons per pixel over both
surfaces and all three wavelengths; SBR = signal / background photons over the cube
(see :mod:`splidar.simulate`).

tau: the paper does not give the Art scene's bin width either; the scene uses 16 ps
(the bin width of the paper's 325 m head data), so one bin is
``16 ps x c / 2 = 2.398 mm`` and tau = 4 mm = 1.668 bins. Points are matched on
``depth_m`` with ``tau_m = 0.004``.

Methods per cell:

* ``splidar``: :func:`splidar.process` (detection + reconstruction) with the scene's
  library and default options.
* ``per-pixel``: :func:`splidar.baselines.per_pixel_detect` (matched filter and an
  exact Poisson threshold per pixel, flat background), same ``pfa`` as splidar's
  default (1e-3), at most 2 surfaces; its intensities are background-subtracted
  counts, its labels the nearest library signature of each point alone
  (:func:`splidar.reconstruction.nearest_signature`: no spatial prior).

Printed per cell and method: F_true(tau), F_false(tau) (count and as a fraction of the
true points), DAE (bins and mm), IAE (the paper's, in photons per true point) and IAE
relative to the mean true intensity of a point (sum over wavelengths), label accuracy
over matched points, and times. Then an F_true(tau) / F_false(tau) / DAE(tau) table
for one cell, and a summary of where splidar beats the baseline.

Usage::

    python benchmarks/bench_paper_art.py                 # 24 cells, about 5 minutes
    python benchmarks/bench_paper_art.py --quick         # 4 cells, about 1 minute
    python benchmarks/bench_paper_art.py --data /path/to/shared/data --seed 1

Never downloads anything: without ``<data>/middlebury-art`` it says so and exits.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import splidar
from splidar.baselines import per_pixel_detect
from splidar.cube import SPEED_OF_LIGHT
from splidar.metrics import evaluate, f_true_curve
from splidar.reconstruction import nearest_signature
from splidar.scenes import art_scene

PPP_FULL = (1.0, 4.0, 16.0, 64.0)
SBR_FULL = (0.25, 1.0, 4.0)
BACKGROUNDS = ("uniform", "decaying")
PPP_QUICK = (4.0, 16.0)
SBR_QUICK = (1.0,)
CURVE_TAUS_MM = (0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0)


def _default_data() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _mm_per_bin(bin_width_ps: float) -> float:
    return bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0 * 1e3


def _row(method, bg, ppp, sbr, m, mean_int, seconds, extra=""):
    iae_rel = m.iae / mean_int if m.iae is not None else float("nan")
    lab = float("nan") if m.label_accuracy is None else m.label_accuracy
    dae_mm = float("nan") if m.dae_m is None else 1e3 * m.dae_m
    return {
        "background": bg,
        "ppp": ppp,
        "sbr": sbr,
        "method": method,
        "f_true": m.f_true,
        "f_false": m.f_false,
        "f_false_rate": m.f_false_rate,
        "dae_bins": m.dae,
        "dae_mm": dae_mm,
        "iae": m.iae,
        "iae_rel": iae_rel,
        "label_accuracy": lab,
        "n_est": m.n_est,
        "seconds": seconds,
        "times": extra,
    }


HEADER = (
    f"{'bg':<8} {'PPP':>5} {'SBR':>5} {'method':<9} {'F_true':>7} {'F_false':>8} "
    f"{'%true':>6} {'DAE_bin':>7} {'DAE_mm':>6} {'IAE':>7} {'IAErel':>6} {'label':>6} "
    f"{'n_est':>6} {'time_s':>6}  detail"
)


def _fmt(r) -> str:
    return (
        f"{r['background']:<8} {r['ppp']:>5g} {r['sbr']:>5g} {r['method']:<9} "
        f"{r['f_true']:>7.4f} {r['f_false']:>8d} {100 * r['f_false_rate']:>5.1f}% "
        f"{r['dae_bins']:>7.3f} {r['dae_mm']:>6.3f} {r['iae']:>7.3f} {r['iae_rel']:>6.3f} "
        f"{r['label_accuracy']:>6.3f} {r['n_est']:>6d} {r['seconds']:>6.2f}  {r['times']}"
    )


def run_cell(scene, ppp, sbr, bg, *, tau_m, seed):
    """Simulate one cell and score splidar and the per-pixel baseline.

    Returns (rows, (truth, splidar points, baseline points)).
    """
    sim = scene.simulate(ppp=ppp, sbr=sbr, background=bg, rng=seed)
    truth = sim.truth
    mean_int = float(truth.intensity.sum(axis=1).mean())  # photons per true point

    t0 = time.perf_counter()
    rec = splidar.process(sim.cube, library=scene.library, rng=seed)
    t_proc = time.perf_counter() - t0
    tm = rec.timings
    m_s = evaluate(rec.points, truth, tau_m=tau_m)
    rows = [
        _row(
            "splidar",
            bg,
            ppp,
            sbr,
            m_s,
            mean_int,
            t_proc,
            f"detect {tm.get('detect', float('nan')):.2f}s "
            f"reconstruct {tm.get('reconstruct', float('nan')):.2f}s "
            f"iters {rec.history.n_iter}",
        )
    ]

    t0 = time.perf_counter()
    base = per_pixel_detect(sim.cube)
    t_base = time.perf_counter() - t0
    bp = base.points
    # per-point classification of the baseline's spectra (no spatial prior)
    bp = replace(bp, label=nearest_signature(bp.intensity, scene.library.signatures))
    m_b = evaluate(bp, truth, tau_m=tau_m)
    rows.append(_row("per-pixel", bg, ppp, sbr, m_b, mean_int, t_base, "labels: nearest sig."))
    return rows, (truth, rec.points, bp)


def print_curve(truth, est, base, mm_bin, cell):
    taus_m = np.asarray(CURVE_TAUS_MM) * 1e-3
    cs = f_true_curve(est, truth, taus_m, unit="m")
    cb = f_true_curve(base, truth, taus_m, unit="m")
    print(f"\nF_true(tau), F_false(tau), DAE(tau) for {cell} (splidar | per-pixel)")
    print(
        f"{'tau_mm':>6} {'tau_bin':>7} | {'F_true':>7} {'F_false':>7} {'DAE_mm':>6} | "
        f"{'F_true':>7} {'F_false':>7} {'DAE_mm':>6}"
    )
    for i, t in enumerate(CURVE_TAUS_MM):
        print(
            f"{t:>6g} {t / mm_bin:>7.3f} | {cs.f_true[i]:>7.4f} {cs.f_false[i]:>7d} "
            f"{1e3 * cs.dae[i]:>6.3f} | {cb.f_true[i]:>7.4f} {cb.f_false[i]:>7d} "
            f"{1e3 * cb.dae[i]:>6.3f}"
        )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=_default_data(), help="shared data folder")
    ap.add_argument("--quick", action="store_true", help="PPP {4, 16} x SBR {1} x 2 backgrounds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tau-mm", type=float, default=4.0, help="matching distance (paper: 4 mm)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    args = ap.parse_args(argv)

    folder = args.data / "middlebury-art"
    if not folder.is_dir():
        print(f"no Art scene at {folder}: nothing to run (this script never downloads).")
        return 1
    scene = art_scene(folder)
    mm_bin = _mm_per_bin(scene.bin_width_ps)
    tau_m = args.tau_mm * 1e-3
    print(scene)
    print(f"  {scene.description}")
    print(
        f"  bin width {scene.bin_width_ps:g} ps (assumed; the paper does not say) -> "
        f"{mm_bin:.4f} mm per bin; tau = {args.tau_mm:g} mm = {args.tau_mm / mm_bin:.3f} bins"
    )
    print(
        f"  library: {scene.library.n_classes} colour classes, counts per class "
        f"{np.bincount(scene.truth.label).tolist()}; IRF FWHM 3 bins; seed {args.seed}"
    )
    print(
        "  IAE = paper's intensity error (photons per true point); IAErel = IAE / mean "
        "true photons of a point (sum over RGB); label = accuracy over matched points"
    )

    ppps = PPP_QUICK if args.quick else PPP_FULL
    sbrs = SBR_QUICK if args.quick else SBR_FULL
    curve_cell = (16.0, 1.0, "uniform")
    rows = []
    curve = None
    t_all = time.perf_counter()
    print()
    print(HEADER)
    for bg in BACKGROUNDS:
        for ppp in ppps:
            for sbr in sbrs:
                cell_rows, pts = run_cell(scene, ppp, sbr, bg, tau_m=tau_m, seed=args.seed)
                for r in cell_rows:
                    print(_fmt(r), flush=True)
                rows.extend(cell_rows)
                if (ppp, sbr, bg) == curve_cell:
                    curve = pts
    if curve is not None:
        print_curve(
            *curve, mm_bin, f"PPP {curve_cell[0]:g}, SBR {curve_cell[1]:g}, {curve_cell[2]}"
        )

    # summary: is splidar at least as good as the per-pixel baseline?
    print("\nsplidar vs per-pixel, per cell (F_true higher, F_false lower, IAE lower):")
    n = len(rows) // 2
    wins = {"F_true": 0, "F_false": 0, "IAE": 0, "label": 0}
    for s, b in zip(rows[0::2], rows[1::2], strict=True):
        wins["F_true"] += s["f_true"] >= b["f_true"]
        wins["F_false"] += s["f_false"] <= b["f_false"]
        wins["IAE"] += s["iae"] <= b["iae"]
        wins["label"] += s["label_accuracy"] >= b["label_accuracy"]
    print("  " + ", ".join(f"{k}: {v}/{n} cells" for k, v in wins.items()))
    print(f"total time {time.perf_counter() - t_all:.1f} s")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
