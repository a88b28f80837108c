"""False alarms and hits of ``load``'s IRF width check (irfw29).

``splidar.load`` compares a supplied IRF's photon-pair width with the data's own
(:func:`splidar._irf_width.check_irf_width`) and warns when they differ by more than
``_irf_width._IRF_WIDTH_FACTOR`` (and the IRF's width lies outside the data's 3-sigma bracket).
This bench runs that check, as ``load`` does, on:

* every cube of ``bench_robustness.py`` (its sensors: T, bin widths, narrow and wide,
  tailed, off-centre, floored and measured IRFs, L 1-16, PPP 0.1-1e5, SBR 0.01-100,
  decaying and pile-up background, hot and dead pixels, tiny images) with its **true**
  IRF (a warning is a false alarm), the IRF 8 x too wide (as if recorded at an 8 x
  finer step and read one sample per bin: a warning is a hit) and 4 x too narrow;
* a PPP sweep (1, 2, 4, 10, 20, 50; SBR 1 and 0.2; seeds 0-2) of the pulses Gaussian
  FWHM 1 / 3 / 10, exp tail 3/6 and 2/25 and the measured pulse of ``irf-sample``,
  with the true IRF: the ratio of widths (IRF / data) is the estimator's spread the
  factor is set against;
* Art (185 x 232 x 3, Gaussian FWHM 3 and exp tail 3/6; PPP 4 / 16 SBR 1, PPP 1 SBR
  0.2) and the real photon-list files with the IRF ``load`` estimates from them and
  with a Gaussian of half and twice that width;
* the time of the check on bench_speed's main cube (200 x 200 x 4 x 1500, PPP 30).

``--path cube`` (rob30) runs the check as ``detect`` does on a Cube built from arrays
(``Cube(counts, irf=...)``, then ``_irf_width.check_cube_irf``; an IRF longer than T cropped
to T - 1 samples first, as a user must) and, in ``speed``, times one ``detect`` on the
main cube against the check.

Run: ``python benchmarks/bench_irf_width_check.py [--size 32] [--no-sweep] [--no-real]
[--path load|cube]`` (a few minutes on the 2-core machine).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import splidar
from splidar import _irf_width, io
from splidar._irf_text import resample_irf
from splidar.irf import exp_tail_irf, gaussian_irf

#: "load": _irf_width.check_irf_width as load runs it; "cube": as detect runs it on a Cube
PATH = ["load"]
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
DATA = HERE.parents[0] / ".." / "shared" / "data"


class _Warned(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.n = 0

    def emit(self, record):
        if "times wider" in record.getMessage() or "times narrower" in record.getMessage():
            self.n += 1


def check(irf, cube):
    """(ratio or None, warned?, seconds) of the check on ``cube`` with ``irf`` (L, n)."""
    h = _Warned()
    lg = logging.getLogger("splidar.io")
    lg.addHandler(h)
    level, prop = lg.level, lg.propagate
    lg.setLevel(logging.WARNING)
    lg.propagate = False
    t0 = time.perf_counter()
    try:
        counts = cube.counts
        n_bins = counts.shape[-1]
        irf = io._crop_irf(np.atleast_2d(np.asarray(irf, float)), n_bins)
        if PATH[0] == "cube":
            c = splidar.Cube(counts, irf=irf, bin_width_ps=cube.bin_width_ps)
            t0 = time.perf_counter()  # the Cube's validation is not the check's
            r = _irf_width.check_cube_irf(c)
        else:
            r = _irf_width.check_irf_width(irf, "given array", counts, n_bins, cube.bin_width_ps)
    finally:
        lg.removeHandler(h)
        lg.setLevel(level)
        lg.propagate = prop
    return r, h.n > 0, time.perf_counter() - t0


def finer(irf, k: int):
    """``irf`` (L, n) as if recorded at a ``k`` x finer step (linear interpolation)."""
    a = np.atleast_2d(np.asarray(irf, float))
    x = np.arange(a.shape[1] * k) / k
    return np.stack([np.interp(x, np.arange(a.shape[1]), row) for row in a])


def coarser(irf, k: int):
    """``irf`` (L, n) integrated over ``k`` samples a bin."""
    return resample_irf(np.atleast_2d(np.asarray(irf, float)), 1.0, float(k))


def _fmt(r):
    return "-" if r is None else f"{r:.2f}"


def robustness(size: int) -> None:
    import bench_robustness as R

    print("\n## bench_robustness cubes: ratio IRF / data (warned?)")
    print("| case | true IRF | 8 x too wide | 4 x too narrow | check s |")
    print("|---|---|---|---|---|")
    tally = {"true": 0, "wide": 0, "narrow": 0, "n": 0, "det": 0}
    for case in R._cases():
        if case.refused:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                cube, _ = case.build(size)
            except Exception as exc:  # noqa: BLE001
                print(f"| {case.name} | build failed: {type(exc).__name__} | | | |")
                continue
        out = []
        secs = 0.0
        for kind, irf in (
            ("true", cube.irf),
            ("wide", finer(cube.irf, 8)),
            ("narrow", coarser(cube.irf, 4)),
        ):
            r, warned, s = check(irf, cube)
            secs += s
            tally[kind] += warned
            if kind == "true" and r is not None:
                tally["det"] += 1
            out.append(f"{_fmt(r)}{' **W**' if warned else ''}")
        tally["n"] += 1
        print(f"| {case.name} | {out[0]} | {out[1]} | {out[2]} | {secs:.2f} |", flush=True)
    print(
        f"\n{tally['n']} cubes, width determined on {tally['det']}; warned: true IRF "
        f"{tally['true']}, 8 x wide {tally['wide']}, 4 x narrow {tally['narrow']}"
    )


def sweep(size: int) -> None:
    import bench_robustness as R

    pulses = [
        ("gauss 1", gaussian_irf(1.0)),
        ("gauss 3", gaussian_irf(3.0)),
        ("gauss 10", gaussian_irf(10.0)),
        ("exp tail 3/6", exp_tail_irf(3.0, 6.0)),
        ("exp tail 2/25", exp_tail_irf(2.0, 25.0)),
    ]
    w = R.measured_irf()
    if w is not None:
        g = w / w.max()
        keep = np.flatnonzero(g >= 0.005)
        pulses.append(("measured (irf-sample)", w[keep[0] : keep[-1] + 1]))
    print("\n## PPP sweep, true IRF: ratio IRF / data over seeds 0-2 (undetermined: -)")
    print("| pulse | SBR | " + " | ".join(f"PPP {p:g}" for p in (1, 2, 4, 10, 20, 50)) + " |")
    print("|---|---|" + "---|" * 6)
    ratios, fired, und, n = [], 0, 0, 0
    for name, irf in pulses:
        m = R._irf_margin(irf)
        T = int(max(200, 8 * m + 40))
        for sbr in (1.0, 0.2):
            cells = []
            for ppp in (1, 2, 4, 10, 20, 50):
                rs = []
                for seed in range(3):
                    truth = R._plane((size, size), m, T - 1 - m)
                    cube, _ = R._sim(truth, T, irf, ppp=ppp, sbr=sbr, seed=seed)
                    r, warned, _ = check(cube.irf, cube)
                    n += 1
                    fired += warned
                    und += r is None
                    if r is not None:
                        ratios.append(r)
                    rs.append(_fmt(r) + ("W" if warned else ""))
                cells.append(" ".join(rs))
            print(f"| {name} | {sbr:g} | " + " | ".join(cells) + " |", flush=True)
    a = np.array(ratios)
    print(
        f"\n{n} cubes: determined {a.size}, undetermined {und}, warned {fired}; ratio "
        f"min {a.min():.2f}, 1st pct {np.percentile(a, 1):.2f}, median {np.median(a):.2f}, "
        f"99th pct {np.percentile(a, 99):.2f}, max {a.max():.2f}; largest |log ratio| "
        f"as a factor {math.exp(np.abs(np.log(a)).max()):.2f}"
    )


def art() -> None:
    from splidar.scenes import art_scene

    folder = DATA / "middlebury-art"
    if not folder.is_dir():
        print("\n(art skipped: no data)")
        return
    print("\n## Art (185 x 232 x 3): ratio IRF / data (warned?), check s")
    for irf_name, irf in (("gauss 3", gaussian_irf(3.0)), ("exp tail 3/6", exp_tail_irf(3.0, 6.0))):
        scene = art_scene(folder, irf=irf)
        for ppp, sbr in ((4, 1.0), (16, 1.0), (1, 0.2)):
            cube = scene.simulate(ppp=ppp, sbr=sbr, rng=0).cube
            r, warned, s = check(cube.irf, cube)
            r8, w8, _ = check(finer(cube.irf, 8), cube)
            print(
                f"- {irf_name}, PPP {ppp} SBR {sbr:g}: true {_fmt(r)}{' WARNED' if warned else ''}"
                f", 8 x wide {_fmt(r8)}{' warned' if w8 else ' NOT warned'} ({s:.2f} s)"
            )


def real() -> None:
    import real_data

    print("\n## real files: the IRF load estimates, and Gaussians of 1/2 and 2 x its width")
    for name, (rel, kw, _) in real_data.REAL.items():
        p = DATA / rel
        if not p.is_file():
            print(f"- {name}: missing")
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            logging.getLogger("splidar").setLevel(logging.ERROR)
            cube = splidar.load(p, **kw)
            fw = float(np.max(splidar.irf.irf_fwhm(cube.irf)))
            gfw = _irf_width._irf_pair_width(cube.irf)
            logging.getLogger("splidar").setLevel(logging.WARNING)
        res = []
        for label, irf in (
            ("estimated", cube.irf),
            ("gauss x0.5", gaussian_irf(gfw / 2)),
            ("gauss x2", gaussian_irf(gfw * 2)),
        ):
            r, warned, s = check(irf, cube)
            res.append(f"{label} {_fmt(r)}{' WARNED' if warned else ''} ({s:.2f} s)")
        t0 = time.perf_counter()
        splidar.load(p, irf_fwhm=gfw, **kw)
        t_with = time.perf_counter() - t0
        print(
            f"- {name} {cube.shape}, IRF FWHM {fw:.2f} (pair width {gfw:.2f}): "
            + "; ".join(res)
            + f"; load with irf_fwhm {t_with:.2f} s"
        )


def speed() -> None:
    import bench_speed

    sim = bench_speed.main_cube()
    cube = sim.cube
    print(f"\n## the check on bench_speed's main cube {cube.shape}, PPP 30")
    for k in range(3):
        r, warned, s = check(cube.irf, cube)
        t0 = time.perf_counter()
        _irf_width._data_pair_width(cube.counts, cube.shape[-1])
        t_data = time.perf_counter() - t0
        print(
            f"- round {k}: ratio {_fmt(r)}, warned {warned}, {s:.3f} s "
            f"(the data's width alone {t_data:.3f} s)"
        )
    t0 = time.perf_counter()
    io.estimate_irf_fwhm(cube.counts)
    print(f"- for scale: estimate_irf_fwhm on the whole cube {time.perf_counter() - t0:.2f} s")
    if PATH[0] == "cube":
        from splidar.detection import detect

        fresh = splidar.Cube(cube.counts, irf=cube.irf, bin_width_ps=cube.bin_width_ps)
        t0 = time.perf_counter()
        det = detect(fresh, rng=0)
        t_det = time.perf_counter() - t0
        t0 = time.perf_counter()
        _irf_width.check_cube_irf(splidar.Cube(cube.counts, irf=cube.irf))
        t_chk = time.perf_counter() - t0
        print(
            f"- detect (its check included) {t_det:.2f} s, {len(det.points)} points; the "
            f"check alone {t_chk:.3f} s: {100 * t_chk / t_det:.1f} % of detect"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--no-sweep", action="store_true")
    ap.add_argument("--no-real", action="store_true", help="skip the real files and Art")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--only", choices=("robustness", "sweep", "art", "real", "speed"))
    ap.add_argument("--path", choices=("load", "cube"), default="load")
    args = ap.parse_args()
    PATH[0] = args.path
    logging.basicConfig(level=logging.ERROR)
    parts = {
        "robustness": lambda: robustness(args.size),
        "sweep": lambda: None if args.no_sweep else sweep(args.size),
        "art": lambda: None if args.no_real else art(),
        "real": lambda: None if args.no_real else real(),
        "speed": lambda: None if args.no_speed else speed(),
    }
    for name, f in parts.items():
        if args.only is None or args.only == name:
            f()


if __name__ == "__main__":
    main()
