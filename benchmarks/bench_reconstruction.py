"""Benchmark of the Bayesian reconstruction and classification (Algorithm 2).

Prints, for multispectral scenes at PPP 10, SBR 1 (one and two surfaces per pixel):

* label accuracy over matched points: ours vs. per-surface nearest-signature
  classification of the same surfaces (no spatial prior);
* IAE: ours vs. the unsmoothed per-surface intensities (own-pixel counts minus
  background over the IRF fraction in the support; and the detection's ``photons``,
  the clean signal at the selected scale);
* calibration: fraction of true intensities within +-1 posterior std (target 0.68);
* whether the objective (log posterior) ever decreased;
* timings of detection and reconstruction, and of 80,000 surfaces.

Two sources of surfaces: (a) fabricated detections (every true surface detected at its
true depth, counts from the exact Poisson model: measures the reconstruction alone);
(b) the simulator's scenes through :func:`splidar.detect` (the whole chain). Then the
Art scene (3 wavelengths) and the real files in ``../shared/data`` when present.

Run: ``python benchmarks/bench_reconstruction.py [--quick] [--figures DIR] [--alpha 6]``
(``--alpha 6``: the fixed prior of the former default; the default is ``"auto"``).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

import splidar
from splidar.detection import detect
from splidar.plotting import _depth_limits  # the library's depth colour limits
from splidar.reconstruction import irf_fraction, nearest_signature, reconstruct, synthetic_detection

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REC_KW: dict = {}  # options passed to every reconstruct call (--alpha)


def raw_intensity(det):
    """Unsmoothed per-surface intensity: (own counts - background) / IRF fraction."""
    s = det.surfaces
    eta = np.maximum(irf_fraction(det.irf, s.depth_bin, s.start, s.stop), 1e-6)
    return (s.counts - s.background) / eta


def iae_matched(est_i, true_i, est_idx, true_idx, n_true, est_un=None, true_un=None):
    """The paper's IAE over a matching (unmatched points count their full intensity)."""
    tot = np.abs(est_i[est_idx] - true_i[true_idx]).sum()
    if est_un is not None:
        tot += np.abs(est_i[est_un]).sum()
    if true_un is not None:
        tot += np.abs(true_i[true_un]).sum()
    return tot / n_true


def min_objective_step(history):
    """Smallest change between evaluated objective values (NaN: sweeps where it was not
    evaluated), except across an empirical-Bayes update of alpha (the model changed)."""
    obj = history.objective
    ok = np.flatnonzero(np.isfinite(obj))
    steps = []
    for i0, i1 in zip(ok[:-1], ok[1:], strict=True):
        if not any(i0 < i <= i1 for i in history.alpha_updates):
            steps.append(obj[i1] - obj[i0])
    return float(min(steps)) if steps else 0.0


def report(name, det, rec, truth, *, t_detect=None):
    from splidar.metrics import match_points

    p = rec.points
    lib = rec.hyperparameters["signatures"]
    m = match_points(p, truth, tau=2.0)
    ei, ti = m.est_index, m.true_index
    raw = raw_intensity(det)
    base = nearest_signature(raw, lib)
    acc = np.mean(p.label[ei] == truth.label[ti])
    acc0 = np.mean(base[ei] == truth.label[ti])
    n = len(truth)
    iae = iae_matched(p.intensity, truth.intensity, ei, ti, n, m.unmatched_est, m.unmatched_true)
    iae_raw = iae_matched(
        np.maximum(raw, 0), truth.intensity, ei, ti, n, m.unmatched_est, m.unmatched_true
    )
    phot = det.surfaces.photons
    iae_ph = iae_matched(phot, truth.intensity, ei, ti, n, m.unmatched_est, m.unmatched_true)
    inside = np.abs(p.intensity[ei] - truth.intensity[ti]) <= p.intensity_std[ei]
    drop = min_objective_step(rec.history)
    per_layer = []
    if truth.layer is not None and truth.layer.max() > 0:
        for layer in range(int(truth.layer.max()) + 1):
            sel = truth.layer[ti] == layer
            per_layer.append(
                f"L{layer} {np.mean(p.label[ei][sel] == truth.label[ti][sel]):.3f}/"
                f"{np.mean(base[ei][sel] == truth.label[ti][sel]):.3f}"
            )
    td = f"{t_detect:7.2f}" if t_detect is not None else "      -"
    print(
        f"{name:28s} {len(truth):6d} {len(p):6d} {m.n_matched:6d} | acc {acc:.3f} vs {acc0:.3f}"
        f" {' '.join(per_layer):22s}| IAE {iae:6.3f} vs raw {iae_raw:6.3f} / photons "
        f"{iae_ph:6.3f} | cov {inside.mean():.3f} | min dObj {drop:+.2e} | iters "
        f"{rec.history.n_iter:3d} | t_det {td} s t_rec {rec.timings['total']:.3f} s"
    )
    return inside, truth.intensity[ti]


def header():
    print(
        f"{'scene':28s} {'true':>6s} {'est':>6s} {'match':>6s} | label acc ours vs "
        "nearest-signature (per layer) | IAE ours vs unsmoothed | coverage +-1 std | "
        "objective | timing"
    )


BINS = (0.0, 0.5, 1.0, 2.0, 4.0, np.inf)


def coverage_bins(inside, tru):
    """Coverage of +-1 std by bin of the true intensity (photons), as a string."""
    inside, tru = inside.ravel(), tru.ravel()
    parts = []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = (tru >= lo) & (tru < hi)
        if np.any(sel):
            parts.append(f"[{lo:g}, {hi:g}) n={int(sel.sum())}: {inside[sel].mean():.3f}")
    return "; ".join(parts)


def fabricated(quick):
    print("\n(a) fabricated detections (true surfaces, exact Poisson counts), PPP 10, SBR 1, L=4")
    header()
    size = 48 if quick else 96
    covs = []
    for layers in (1, 2):
        for seed in range(2 if quick else 4):
            det, truth = synthetic_detection(
                shape=(size, size), layers=layers, ppp=10, sbr=1, patch_size=12, rng=seed
            )
            rec = reconstruct(det, **REC_KW)
            covs.append(report(f"synthetic {layers}-layer seed {seed}", det, rec, truth))
    cov = np.concatenate([c[0].ravel() for c in covs])
    tru = np.concatenate([c[1].ravel() for c in covs])
    print(f"pooled coverage over {cov.size} intensities: {cov.mean():.3f} (target 0.683)")
    print("  by true intensity (photons): " + coverage_bins(cov, tru))
    # the scenes above give every surface its class signature exactly (the prior mean):
    # within-class spectral variability (CV of the reflectivity about the signature)
    for var in (0.2, 0.4, 0.6):
        covs = []
        for layers in (1, 2):
            det, truth = synthetic_detection(
                shape=(size, size), layers=layers, variability=var, patch_size=12, rng=9
            )
            rec = reconstruct(det, **REC_KW)
            covs.append(report(f"synthetic {layers}L variability {var}", det, rec, truth))
        cov = np.concatenate([c[0].ravel() for c in covs])
        tru = np.concatenate([c[1].ravel() for c in covs])
        print(f"  variability {var}: coverage {cov.mean():.3f}; " + coverage_bins(cov, tru))


def simulated(quick, figures):
    from splidar.scenes import multispectral_scene

    print("\n(b) simulator scenes through splidar.detect, PPP 10, SBR 1")
    header()
    size = 48 if quick else 96
    for two in (False, True):
        for seed in range(1 if quick else 2):
            scene = multispectral_scene((size, size), two_layers=two)
            sim = scene.simulate(ppp=10, sbr=1, rng=seed)
            t0 = time.perf_counter()
            det = detect(sim.cube, rng=seed)
            t_det = time.perf_counter() - t0
            rec = reconstruct(det, **REC_KW)
            name = f"multispectral {'2' if two else '1'}-layer s{seed}"
            inside, tru = report(name, det, rec, sim.truth, t_detect=t_det)
            print("  coverage by true intensity (photons): " + coverage_bins(inside, tru))
            if figures and seed == 0:
                plot(
                    rec, Path(figures) / f"recon_{name.replace(' ', '_')}.png", name,
                    truth=sim.truth,
                )  # fmt: skip


def timing():
    print("\n(c) timing, 2-layer fabricated scene of 200 x 200 pixels = 80,000 surfaces, L = 4")
    det, truth = synthetic_detection(shape=(200, 200), layers=2, ppp=10, sbr=1, rng=0)
    reconstruct(det, max_iter=2)  # compile (cached on disk after the first run)
    for links in ("depth", "all"):
        ts, cpu = [], []
        for _ in range(3):
            c0 = time.process_time()
            rec = reconstruct(det, links=links, **REC_KW)
            cpu.append(time.process_time() - c0)
            ts.append(rec.timings["total"])
        print(
            f"links={links:5s}: {len(det.surfaces)} surfaces, {rec.hyperparameters['n_links']} "
            f"links, {rec.history.n_iter} sweeps ({rec.history.reason}), best of 3: wall "
            f"{min(ts):.3f} s, CPU {min(cpu):.3f} s (setup {rec.timings['setup']:.3f} s, "
            f"sweeps {rec.timings['iterations']:.3f} s)"
        )
    print(f"load average while timing: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    rec = reconstruct(det, max_iter=200, tol=1e-12)
    print(
        f"200 sweeps forced: {rec.timings['iterations']:.3f} s "
        f"({1e3 * rec.timings['iterations'] / rec.history.n_iter:.2f} ms per sweep)"
    )


TIMINGS = []  # (scene, cube shape, surfaces, detect s, reconstruct s, sweeps)


def art(quick, figures):
    from splidar.scenes import art_scene

    folder = SHARED / "middlebury-art"
    if not folder.is_dir():
        print("\n(d) Art scene: ../shared/data/middlebury-art absent, skipped")
        return
    print("\n(d) Art scene (185 x 232, two surfaces per pixel, L = 3), PPP 10, SBR 1")
    header()
    scene = art_scene(folder)
    sim = scene.simulate(ppp=10, sbr=1, rng=0)
    t0 = time.perf_counter()
    det = detect(sim.cube, rng=0)
    t_det = time.perf_counter() - t0
    rec = reconstruct(det, **REC_KW)
    report("art 2-layer", det, rec, sim.truth, t_detect=t_det)
    TIMINGS.append(
        ("art (simulated)", sim.cube.shape, len(rec.points), t_det, rec.timings["total"],
         rec.history.n_iter)
    )  # fmt: skip
    if figures:
        plot(
            rec, Path(figures) / "recon_art.png", "Art (simulated, PPP 10, SBR 1)", truth=sim.truth
        )


def real(figures):
    """The real files of ../shared/data, with the loader options of benchmarks/real_data.py."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from real_data import REAL

    print("\n(e) real data (../shared/data): detection + reconstruction, one class")
    for name, (rel, kw, desc) in REAL.items():
        path = SHARED / rel
        if not path.exists():
            print(f"{name}: {path} absent, skipped")
            continue
        try:
            t0 = time.perf_counter()
            cube = splidar.load(path, **kw)
            t_load = time.perf_counter() - t0
            t0 = time.perf_counter()
            det = detect(cube, rng=0)
            t_det = time.perf_counter() - t0
            rec = reconstruct(det, **REC_KW)
        except Exception as exc:  # report and carry on with the other files
            print(f"{name}: failed: {type(exc).__name__}: {exc}")
            continue
        drop = min_objective_step(rec.history)
        rel_std = rec.points.intensity_std.sum(1) / np.maximum(rec.points.intensity.sum(1), 1e-12)
        print(
            f"{name:6s} ({desc}) cube {cube.shape} load {t_load:.2f} s | {len(rec.points)} "
            f"surfaces | detect {t_det:.2f} s | reconstruct {rec.timings['total']:.3f} s "
            f"({rec.history.n_iter} sweeps, {rec.history.reason}) | min dObj {drop:+.2e} | "
            f"median intensity {np.median(rec.points.intensity.sum(1)):.2f} photons, median "
            f"rel. std {np.median(rel_std):.2f}"
        )
        TIMINGS.append(
            (name, cube.shape, len(rec.points), t_det, rec.timings["total"], rec.history.n_iter)
        )
        if figures:
            plot(rec, Path(figures) / f"recon_{name}.png", f"{name}: {desc}")


def timing_table():
    if not TIMINGS:
        return
    load = os.getloadavg()[0]
    print(f"\nTiming (wall s; load average {load:.1f} on {os.cpu_count()} cores)")
    print(f"{'scene':18s} {'cube (rows, cols, L, T)':26s} {'surfaces':>9s} {'detect s':>9s} "
          f"{'reconstruct s':>14s} {'sweeps':>7s}")  # fmt: skip
    for name, shape, n, td, tr, it in TIMINGS:
        print(f"{name:18s} {str(shape):26s} {n:9d} {td:9.2f} {tr:14.3f} {it:7d}")


SPEED = 299_792_458.0


def plot(rec, path, title, truth=None):
    """Depth, intensity and (with several classes) label maps per surface layer.

    Each depth panel has its own colour scale, median +- 5 robust standard deviations
    (1.4826 MAD) of its depths clipped to the 1st-99th percentiles: the 1st-99th
    percentiles alone span face and wall on the face data and flatten the face's relief
    into one colour. Intensity panels: 0 to the 99th percentile. Pixels without a surface
    are grey. With ``truth`` a last row shows the true nearest layer on the colour scales
    of the reconstructed one.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from splidar import plotting as sp

    path.parent.mkdir(parents=True, exist_ok=True)
    K = rec.n_layers
    labels = int(rec.hyperparameters["n_classes"]) > 1
    n_col = 3 if labels else 2
    n_row = K + (1 if truth is not None and labels else 0)
    fig, ax = plt.subplots(n_row, n_col, figsize=(5.2 * n_col, 4.0 * n_row), squeeze=False)
    scale = 1.0 if rec.bin_width_ps is None else rec.bin_width_ps * 1e-12 * SPEED / 2.0
    lims = []
    for k in range(K):
        lims.append(_depth_limits(rec.depth_map[:, :, k] * scale))
        sp.plot_depth(rec, layer=k, ax=ax[k, 0], vmin=lims[k][0], vmax=lims[k][1])
        sp.plot_intensity(rec, layer=k, ax=ax[k, 1])
        if labels:
            sp.plot_labels(rec, layer=k, ax=ax[k, 2])
    if n_row > K:
        sp.plot_depth(
            truth, layer=0, ax=ax[K, 0], bin_width_ps=rec.bin_width_ps, vmin=lims[0][0],
            vmax=lims[0][1],
        )  # fmt: skip
        ax[K, 0].set_title("True depth, 1st surface per pixel", fontsize=10)
        inten = rec.intensity_map[:, :, 0].sum(-1)
        sp.plot_intensity(truth, layer=0, ax=ax[K, 1], vmax=np.nanpercentile(inten, 99))
        ax[K, 1].set_title("True intensity, 1st surface per pixel", fontsize=10)
        sp.plot_labels(truth, layer=0, ax=ax[K, 2], class_names=rec.class_names)
        ax[K, 2].set_title("True class, 1st surface per pixel", fontsize=10)
    fig.suptitle(
        f"{title}\n{len(rec.points)} surfaces, reconstruction {rec.timings['total']:.2f} s "
        f"({rec.history.n_iter} sweeps)",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    print(f"  figure: {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller scenes, fewer seeds")
    ap.add_argument("--figures", default=None, help="folder for PNG figures")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: a,b,c,d,e")
    ap.add_argument(
        "--alpha", default=None, help='reconstruct alpha: a number or "auto" (the default)'
    )
    a = ap.parse_args()
    if a.alpha is not None:
        REC_KW["alpha"] = a.alpha if a.alpha == "auto" else float(a.alpha)
        print(f"reconstruct options: {REC_KW}")
    skip = set(a.skip.split(","))
    if "a" not in skip:
        fabricated(a.quick)
    if "b" not in skip:
        simulated(a.quick, a.figures)
    if "c" not in skip:
        timing()
    if "d" not in skip:
        art(a.quick, a.figures)
    if "e" not in skip:
        real(a.figures)
    timing_table()


if __name__ == "__main__":
    main()
