"""Spatially incoherent scenes: patches of independent depths, and smooth scenes.

``detect`` pools every pixel's matched-filter response with its neighbours' (boxes of
1, 3, 7, 11 pixels weighted 1 : 3 : 7 : 11, ``eq:4.s1``), which assumes that neighbours
share depths. This family measures what that costs where they do not: on 48 x 48
pixels, T = 300, one surface per pixel whose depth is drawn uniform in bins 30-270
**independently for every patch** of 1 x 1, 2 x 2, 4 x 4 or 8 x 8 pixels, or a smooth
scene (a tilted plane plus a slow sinusoid, depths 60-240), or mixed scenes whose left
columns are 1 x 1 and the rest smooth: "half" (24 columns), "quarter" (12), "3quarter"
(36) (F_true / false surfaces of each part in brackets), at 4, 12 and 40 signal
photons a pixel and SBR 1 and 0.25 (a flat background). The pulse is the reproducer's
(``bench_foreign_cubes.py --window-end``): a Gaussian of FWHM 6 bins with an exponential
tail of 4 bins (FWHM 8.4), its IRF recorded as 100 samples, peak at 30. Scores:
``evaluate`` at tau = 4.2 bins (FWHM / 2): F_true, false surfaces, DAE (bins), for
``detect`` (``rng=0``) and ``per_pixel_detect`` (the baseline), ``detect(scales=(1,))``
with ``--fine``, and with ``--before`` ``detect`` as it was before the choice of boxes by
region (session 18: one set for the whole image, the regions' override switched off in
the same process); the mixed scenes also score each part (left 1 x 1, right smooth).

    python benchmarks/bench_coherence.py              # 36 cells, a few minutes
    python benchmarks/bench_coherence.py --only 1x1 --ppp 12 --sbr 1
    python benchmarks/bench_coherence.py --seed 1 --json out.json

The simulator is :mod:`bench_foreign_cubes`'s (the paper's observation model, eq:4.1,
written without ``splidar.simulation``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_foreign_cubes import Pulse, irf_record  # noqa: E402

N, T = 48, 300
PATCHES = ("1x1", "2x2", "4x4", "8x8", "smooth", "half", "quarter", "3quarter")
#: The mixed scenes: how many left columns are 1 x 1 (the rest smooth).
SPLIT = {"half": N // 2, "quarter": N // 4, "3quarter": 3 * N // 4}
PULSE = Pulse(6.0, 4.0)
TAU = 4.2


def depths(kind: str, rng) -> np.ndarray:
    """(N, N) depths in bins: independent per patch, or a smooth surface."""
    if kind in SPLIT:  # the left columns 1 x 1, the rest smooth
        d = depths("smooth", rng)
        d[:, : SPLIT[kind]] = depths("1x1", rng)[:, : SPLIT[kind]]
        return d
    if kind == "smooth":
        r, c = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
        phase = rng.random() * 2 * np.pi
        return 150.0 + 1.2 * (r - N / 2) + 0.6 * (c - N / 2) + 20.0 * np.sin(c / 9.0 + phase)
    p = int(kind.split("x")[0])
    m = -(-N // p)
    d = 30.0 + 240.0 * rng.random((m, m))
    return np.repeat(np.repeat(d, p, axis=0), p, axis=1)[:N, :N]


def make_cube(kind: str, ppp: float, sbr: float, seed: int):
    from splidar import Cube, PointSet

    rng = np.random.default_rng(seed)
    d = depths(kind, rng)
    norm = PULSE(np.arange(-200.0, 200.0)).sum()
    lam = ppp * PULSE(np.arange(T) - d[..., None]) / norm
    lam += ppp / sbr / T  # flat background: SBR = signal / background photons a pixel
    y = rng.poisson(lam).astype(np.uint16)[:, :, None, :]
    cube = Cube(y, irf=irf_record(PULSE, 100, 30, to_peak=True))
    rr, cc = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    truth = PointSet(row=rr.ravel(), col=cc.ravel(), depth_bin=d.ravel(), image_shape=(N, N))
    return cube, truth


def run_cell(kind, ppp, sbr, seed, methods, detect_kwargs=None):
    import splidar
    from splidar.baselines import per_pixel_detect
    from splidar.metrics import evaluate

    cube, truth = make_cube(kind, ppp, sbr, seed)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in methods:
            t0 = time.process_time()
            if name == "detect":
                pts = splidar.detect(cube, rng=0, **(detect_kwargs or {})).points
            elif name == "scales1":
                pts = splidar.detect(cube, rng=0, scales=(1,)).points
            elif name == "before":
                pts = _one_set(lambda: splidar.detect(cube, rng=0).points)
            else:
                pts = per_pixel_detect(cube).points
            m = evaluate(pts, truth, tau=TAU)
            out[name] = {
                "f_true": float(m.f_true), "false": int(m.f_false), "dae": float(m.dae),
                "cpu_s": time.process_time() - t0,
            }  # fmt: skip
            if kind in SPLIT:  # F_true, false of the left (incoherent) and right part
                from splidar.metrics import match_points

                mt = match_points(pts, truth, tau=TAU)
                hit = np.zeros(truth.row.size, bool)
                hit[mt.true_index] = True
                left = truth.col < SPLIT[kind]
                false_left = pts.col[mt.unmatched_est] < SPLIT[kind]
                out[name]["left"] = float(hit[left].mean())
                out[name]["right"] = float(hit[~left].mean())
                out[name]["false_left"] = int(false_left.sum())
                out[name]["false_right"] = int((~false_left).sum())
    return out


def _one_set(run):
    """``run()`` with ``scales="auto"`` choosing one set of boxes for the whole image
    (the image's choice, every region's override off: the code before session 18)."""
    from splidar.detection import _detect
    from splidar.detection._2_saliency import RegionScales

    def whole(coh, shape):
        n = int(coh.kept.sum())
        full = np.full(tuple(shape), n, np.int8)
        return RegionScales(coh.scales, full, ((0, shape[0], 0, shape[1], n),), float("nan"))

    keep, _detect.region_scales = _detect.region_scales, whole
    try:
        return run()
    finally:
        _detect.region_scales = keep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=list(PATCHES), choices=PATCHES)
    ap.add_argument("--ppp", nargs="*", type=float, default=[4.0, 12.0, 40.0])
    ap.add_argument("--sbr", nargs="*", type=float, default=[1.0, 0.25])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fine", action="store_true", help="also detect(scales=(1,))")
    ap.add_argument("--no-baseline", action="store_true", help="skip per_pixel_detect")
    ap.add_argument(
        "--before", action="store_true", help="also detect with one set of boxes for the image"
    )
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args()
    methods = (["before"] if args.before else []) + ["detect"] + (["scales1"] if args.fine else [])
    methods += [] if args.no_baseline else ["per_pixel"]
    rows = []
    print(
        "| scene | PPP | SBR | " + " | ".join(f"{m} F_true / false / DAE" for m in methods) + " |"
    )
    print("|---|---|---|" + "---|" * len(methods))
    for kind in args.only:
        for ppp in args.ppp:
            for sbr in args.sbr:
                res = run_cell(kind, ppp, sbr, args.seed, methods)
                rows.append({"scene": kind, "ppp": ppp, "sbr": sbr, **res})
                cells = " | ".join(
                    f"{res[m]['f_true']:.3f} / {res[m]['false']} / {res[m]['dae']:.2f}"
                    + (
                        f" (parts {res[m]['left']:.3f} / {res[m]['false_left']}, "
                        f"{res[m]['right']:.3f} / {res[m]['false_right']}; "
                        f"{res[m]['cpu_s']:.2f} s)"
                        if "left" in res[m]
                        else ""
                    )
                    for m in methods
                )
                print(f"| {kind} | {ppp:g} | {sbr:g} | {cells} |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
