"""Run splidar on the public real data sets and on the simulated Middlebury "Art" scene.

For each photon-list file in the data folder (face, tower, 21 km building) it builds a
histogram cube with :func:`splidar.load` (time window and bin width below; the IRF is a
Gaussian whose width the loader estimates from the data, as none of the files holds one),
then runs :func:`splidar.detect` and, when it exists, :func:`splidar.reconstruct`, and
the per-pixel baseline for comparison. For the Art scene (the paper's simulated scene,
185 x 232 pixels, two surfaces per pixel, RGB) it simulates a cube at the given PPP
and SBR and also scores the result against the truth (F_true, F_false at tau = 3 bins).

Printed per data set: cube shape, photons per pixel, number of surfaces, data reduction
(fraction of voxels and photons the detection keeps), and the time of each stage.

Usage::

    python benchmarks/real_data.py                       # data in ../shared/data
    python benchmarks/real_data.py /path/to/data --only face,art --no-reconstruct

Never downloads anything: a missing file is reported and skipped.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

import splidar
from splidar.baselines import per_pixel_detect

# file, loader options, what it is
REAL = {
    "face": (
        "face/data_face.mat",
        dict(window=(1000, 8000), bin_width=4),
        "mannequin face, bin indices 1000..7999 grouped by 4 (bin width unknown)",
    ),
    "tower": (
        "tower/tower.mat",
        dict(
            variable="data_processed", time_unit="ps", window=(5_180_000, 5_380_000), bin_width=64
        ),
        "long-range tower, ps gate 5.18-5.38 us, 64 ps bins",
    ),
    "21km": (
        "longrange-21km/21km_K11_night.mat",
        dict(variable="Ts_gated", time_unit="ps", window=(4_430_000, 4_630_000), bin_width=128),
        "building 21 km away at night, ps gate 4.43-4.63 us, 128 ps bins",
    ),
}


def _default_data() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _reconstruct():
    try:
        from splidar.reconstruction import reconstruct
    except ImportError:
        return None
    return reconstruct


def _report(name, desc, cube, args, truth=None):
    from splidar.detection import detect

    L = cube.n_wavelengths
    print(f"\n== {name}: {desc}")
    fw = dict(cube.metadata).get("irf_source", "")
    print(
        f"   cube {cube.shape} ({cube.counts.dtype}), {cube.n_pixels * cube.n_bins * L:,} voxels, "
        f"IRF {cube.irf.shape[1]} samples {fw}, bin width "
        f"{'unknown' if cube.bin_width_ps is None else f'{cube.bin_width_ps:g} ps'}"
    )
    print(f"   photons per pixel {cube.photons_per_pixel():.2f}")
    t0 = time.perf_counter()
    det = detect(cube, pfa=args.pfa, rng=args.seed)  # seeded null: reproducible runs
    t_det = time.perf_counter() - t0
    red = det.reduction
    pts = det.points
    per_pix = np.bincount(pts.row * cube.n_cols + pts.col, minlength=cube.n_pixels)
    print(
        f"   detect: {len(pts):,} surfaces ({np.mean(per_pix > 0):.1%} of pixels have one, "
        f"{np.mean(per_pix > 1):.1%} two or more) in {t_det:.1f} s; keeps "
        f"{red.voxel_fraction:.3%} of voxels and {red.photon_fraction:.1%} of photons "
        f"({red.n_photons:,}); threshold method {det.null.method}"
    )
    t0 = time.perf_counter()
    base = per_pixel_detect(cube, pfa=args.pfa, max_surfaces=2)
    t_base = time.perf_counter() - t0
    bpix = np.bincount(base.points.row * cube.n_cols + base.points.col, minlength=cube.n_pixels)
    print(
        f"   per-pixel baseline (same pfa): {len(base.points):,} surfaces "
        f"({np.mean(bpix > 0):.1%} of pixels) in {t_base:.1f} s"
    )
    if truth is not None:
        from splidar.metrics import evaluate

        for label, p in (("detect", pts), ("per-pixel", base.points)):
            m = evaluate(p, truth, tau=3.0)
            print(
                f"   {label:9s} vs truth (tau 3 bins): F_true {m.f_true:.3f}, F_false "
                f"{m.f_false} ({m.f_false_rate:.1%} of true), DAE {m.dae:.2f} bins"
            )
    rec_fn = None if args.no_reconstruct else _reconstruct()
    if rec_fn is not None and len(pts):
        t0 = time.perf_counter()
        try:
            rec = rec_fn(det)
        except Exception as exc:  # report, keep going with the next data set
            print(f"   reconstruct FAILED: {exc!r}")
        else:
            t_rec = time.perf_counter() - t0
            h = rec.history
            print(
                f"   reconstruct: {len(rec.points):,} points in {t_rec:.1f} s "
                f"({h.n_iter} iterations, {'converged' if h.converged else h.reason})"
            )
            if truth is not None:
                from splidar.metrics import evaluate

                m = evaluate(rec.points, truth, tau=3.0)
                print(
                    f"   reconstruct vs truth: F_true {m.f_true:.3f}, F_false {m.f_false}, "
                    f"DAE {m.dae:.2f} bins, IAE {m.iae if m.iae is None else round(m.iae, 3)}"
                    + (
                        ""
                        if m.label_accuracy is None
                        else f", label accuracy {m.label_accuracy:.3f}"
                    )
                )
    elif rec_fn is None and not args.no_reconstruct:
        print("   reconstruct: not available yet")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", nargs="?", default=str(_default_data()), help="data folder")
    ap.add_argument("--only", default="face,tower,21km,art", help="comma-separated subset")
    ap.add_argument("--pfa", type=float, default=1e-4, help="false-alarm rate per voxel")
    ap.add_argument("--art-ppp", type=float, default=4.0, help="Art scene photons per pixel")
    ap.add_argument("--art-sbr", type=float, default=1.0, help="Art scene SBR")
    ap.add_argument(
        "--seed", type=int, default=0, help="seed of the Art simulation and of the detection null"
    )
    ap.add_argument("--no-reconstruct", action="store_true")
    ap.add_argument("-v", "--verbose", action="store_true", help="show library log messages")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR)
    data = Path(args.data)
    want = [w.strip() for w in args.only.split(",") if w.strip()]
    print(f"# real_data: data folder {data}, pfa {args.pfa:g}")
    t_all = time.perf_counter()
    for name in want:
        if name == "art":
            folder = data / "middlebury-art"
            if not folder.is_dir():
                print(f"\n== art: {folder} missing, skipped")
                continue
            from splidar.scenes import art_scene

            scene = art_scene(folder)
            t0 = time.perf_counter()
            sim = scene.simulate(ppp=args.art_ppp, sbr=args.art_sbr, rng=args.seed)
            desc = (
                f"Middlebury Art, simulated: PPP {args.art_ppp:g}, SBR {args.art_sbr:g}, "
                f"uniform background ({time.perf_counter() - t0:.1f} s to simulate)"
            )
            _report("art", desc, sim.cube, args, truth=sim.truth)
            continue
        if name not in REAL:
            print(f"\n== {name}: unknown (choose from {', '.join([*REAL, 'art'])})")
            continue
        rel, kw, desc = REAL[name]
        path = data / rel
        if not path.is_file():
            print(f"\n== {name}: {path} missing, skipped")
            continue
        t0 = time.perf_counter()
        cube = splidar.load(path, **kw)
        desc += f" (loaded in {time.perf_counter() - t0:.1f} s)"
        _report(name, desc, cube, args)
    print(f"\nTotal wall time {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
