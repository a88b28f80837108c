"""The IRF shape estimated from the data (``splidar.io.estimate_irf``) against the truth.

Simulated cubes (32 x 32 tilted plane of ``bench_robustness.basic``: PPP 10, SBR 1) with a
known non-Gaussian IRF: exponential tails 3/6 and 2/25 (``exp_tail_irf``) and, when
``../shared/data/irf-sample`` is present, the measured pulse (cropped, T 300). For each:

* the shape against the true IRF, both put on one grid with their peaks on one sample:
  L1 distance, FWHM (bins), tail mass beyond peak + 1 true FWHM and + 2 true FWHM; for the
  estimated shape (``estimate_irf``) and the Gaussian of the width ``estimate_irf_fwhm``
  gives (what ``load`` uses today when a file has no IRF);
* ``splidar.process(cube, rng=0)`` with (a) the true IRF, (b) the Gaussian estimate,
  (c) the estimated shape with the hard alignment only (``refine=False``), (d) with the
  soft alignment (the default): F_true, false surfaces, DAE (``splidar.metrics.evaluate``,
  tau = max(2, FWHM / 2) bins as in bench_robustness), the median depth offset and the
  depth bias (mean signed error of the points within tau of a true depth).

Then, with ``--real``, the three photon-list files (loaded as in ``real_data.py``): the
estimated FWHM, tail mass and time, and ``detect(rng=0, pfa=1e-4)`` with the Gaussian
estimate and with the shapes: surfaces, pixels with >= 2 surfaces, the median depth
shift against the Gaussian estimate (no truth there). With ``--art``, the Art scene
(Gaussian FWHM 3 and exp tail 3/6; PPP 4, 16, 64) with the four IRFs. With ``--weak``
(only), SBR 0.2 at PPP 1 / 2 / 4: the IRF ``load`` builds without one (pooling pixel
blocks where single pixels show no pulse) against the true IRF. With ``--load-cells``
(only), the IRF ``load`` builds on 16 cells (exp tails 3/6 and 2/25, the measured pulse and
a Gaussian control; PPP 1-10, SBR 0.2 and 1; the tilted plane) and ``process`` with it,
and the split-half spreads of the single pixels' and the 2 x 2 blocks' shapes (irf23), and
the pair-lag width with its pixel-block level (irf24).

Usage::

    python benchmarks/bench_irf_estimate.py [--seeds 0 1 2] [--ppp4] [--real] [--art] [--art-widths]
        [--weak] [--load-cells] [--no-sim] [--reference {peaks,pmax,argmax}] [--data DIR]

``--reference argmax`` gives the estimated shapes the depth reference of releases before
irf25 (the estimate's own argmax), ``pmax`` the variant measured in irf25.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_robustness import basic, measured_irf  # noqa: E402
from real_data import REAL, _default_data  # noqa: E402

import splidar  # noqa: E402
from splidar.io import estimate_irf, estimate_irf_fwhm  # noqa: E402
from splidar.irf import exp_tail_irf, gaussian_irf, irf_fwhm  # noqa: E402
from splidar.metrics import evaluate  # noqa: E402


def common_grid(a, b):
    """Both IRFs (1-D, unit sum) on one grid with their peaks on sample ``o``."""
    a = np.asarray(a, float) / np.sum(a)
    b = np.asarray(b, float) / np.sum(b)
    pa, pb = int(np.argmax(a)), int(np.argmax(b))
    o = max(pa, pb)
    n = o + max(a.size - pa, b.size - pb)
    x, y = np.zeros(n), np.zeros(n)
    x[o - pa : o - pa + a.size] = a
    y[o - pb : o - pb + b.size] = b
    return x, y, o


def tail_mass(irf, k: float) -> float:
    """Mass of a unit-sum IRF more than ``k`` bins after its peak."""
    g = np.asarray(irf, float).ravel()
    g = g / g.sum()
    return float(g[int(np.argmax(g)) + int(np.ceil(k)) :].sum())


def shape_row(true, est, fw_true):
    t, e, _ = common_grid(true, est)
    return dict(
        l1=float(np.abs(t - e).sum()),
        fwhm=float(irf_fwhm(e)),
        tail1=tail_mass(e, fw_true),
        tail2=tail_mass(e, 2 * fw_true),
    )


def _nearest_true_errors(points, truth) -> np.ndarray:
    """Signed depth difference (bins) of each estimated point to the nearest true depth
    of its pixel (points in pixels without a true surface left out)."""
    n = truth.image_shape[1]
    t_key = truth.row * n + truth.col
    e_key = points.row * n + points.col
    d = []
    for k, z in zip(e_key, points.depth_bin, strict=True):
        tz = truth.depth_bin[t_key == k]
        if tz.size:
            d.append(z - tz[np.argmin(np.abs(tz - z))])
    return np.asarray(d, dtype=np.float64)


def depth_offset(points, truth) -> float:
    """Median signed depth difference (bins) of each estimated point to the nearest true
    depth of its pixel: the constant shift an IRF's reference (its argmax) puts on every
    depth; a flat-topped pulse leaves that reference ill-defined."""
    d = _nearest_true_errors(points, truth)
    return float(np.median(d)) if d.size else 0.0


def depth_bias(points, truth, tau: float) -> float:
    """Mean signed depth error (bins) of the estimated points within ``tau`` of a true
    depth of their pixel (the nearest one): the depth bias of the detected surfaces."""
    d = _nearest_true_errors(points, truth)
    d = d[np.abs(d) <= tau]
    return float(np.mean(d)) if d.size else 0.0


def ppp4_cases():
    """``--ppp4``: exp tail 3/6, 2/25 and the measured pulse at PPP 4."""
    cases = [
        ("exp tail 3/6, PPP 4", basic(ppp=4.0, irf=exp_tail_irf(3.0, 6.0)), exp_tail_irf(3.0, 6.0)),
        (
            "exp tail 2/25, PPP 4 (T 400)",
            basic(T=400, ppp=4.0, irf=exp_tail_irf(2.0, 25.0)),
            exp_tail_irf(2.0, 25.0),
        ),
    ]
    w = measured_irf()
    if w is not None:
        cases.append(
            ("measured pulse, PPP 4, T 300", basic(T=300, ppp=4.0, irf=w[230:300]), w[230:300])
        )
    return cases


def sim_cases():
    cases = [
        ("exp tail 3/6", basic(irf=exp_tail_irf(3.0, 6.0)), exp_tail_irf(3.0, 6.0)),
        ("exp tail 2/25", basic(T=400, irf=exp_tail_irf(2.0, 25.0)), exp_tail_irf(2.0, 25.0)),
        ("gaussian fwhm 3 (control)", basic(), gaussian_irf(3.0)),
        ("exp tail 3/6, PPP 2", basic(ppp=2.0, irf=exp_tail_irf(3.0, 6.0)), exp_tail_irf(3.0, 6.0)),
        (
            "exp tail 3/6, PPP 40",
            basic(ppp=40.0, irf=exp_tail_irf(3.0, 6.0)),
            exp_tail_irf(3.0, 6.0),
        ),
        (
            "exp tail 3/6, 2nd surface +20 bins, every other column",
            basic(T=240, second=20.0, irf=exp_tail_irf(3.0, 6.0)),
            exp_tail_irf(3.0, 6.0),
        ),
    ]
    cases.append(
        (
            "exp tail 2/25, PPP 2 (T 400)",
            basic(T=400, ppp=2.0, irf=exp_tail_irf(2.0, 25.0)),
            exp_tail_irf(2.0, 25.0),
        )
    )
    w = measured_irf()
    if w is not None:
        cases.append(("measured pulse, T 300", basic(T=300, irf=w[230:300]), w[230:300]))
        cases.append(
            ("measured pulse, PPP 2, T 300", basic(T=300, ppp=2.0, irf=w[230:300]), w[230:300])
        )
    return cases


def run_sim(seeds, cases=None):
    print("## simulated, 32 x 32, SBR 1, PPP 10 unless said; process(rng=0)")
    print(
        "| case | seed | IRF | L1 | FWHM | tail > 1 FWHM | tail > 2 FWHM | F_true | false "
        "| DAE | offset | bias | F_true / DAE after offset | estimate s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, build, true in sim_cases() if cases is None else cases:
        true = np.asarray(true, float) / np.sum(true)
        fw = float(irf_fwhm(true))
        tau = max(2.0, fw / 2.0)
        for seed in seeds:
            cube, truth = build(32) if seed == 0 else _reseed(build, seed)
            t0 = time.perf_counter()
            shape = estimate_irf(cube.counts)
            t_est = time.perf_counter() - t0
            t0 = time.perf_counter()
            hard = estimate_irf(cube.counts, refine=False)
            t_hard = time.perf_counter() - t0
            g = gaussian_irf(estimate_irf_fwhm(cube.counts))
            rows = [
                ("true", true, 0.0),
                ("gaussian est.", g, 0.0),
                ("shape est. hard (refine=False)", hard[0], t_hard),
                ("shape est. soft", shape[0], t_est),
            ]
            for label, irf, te in rows:
                s = shape_row(true, irf, fw)
                c = dataclasses.replace(cube, irf=np.asarray(irf, float)[None, :])
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    rec = splidar.process(c, rng=0)
                m = evaluate(rec.points, truth, tau=tau)
                off = depth_offset(rec.points, truth)
                bias = depth_bias(rec.points, truth, tau)
                moved = dataclasses.replace(rec.points, depth_bin=rec.points.depth_bin - off)
                m2 = evaluate(moved, truth, tau=tau)
                print(
                    f"| {name} | {seed} | {label} | {s['l1']:.3f} | {s['fwhm']:.2f} | "
                    f"{s['tail1']:.3f} | {s['tail2']:.3f} | {m.f_true:.3f} | {m.f_false} | "
                    f"{m.dae:.2f} | {off:+.1f} | {bias:+.2f} | {m2.f_true:.3f} / {m2.dae:.2f} | "
                    f"{te:.2f} |"
                )


def _reseed(build, seed):
    """``build`` of bench_robustness with another simulation seed."""
    import bench_robustness as br

    old = dict(br._sim.__kwdefaults__)
    try:
        br._sim.__kwdefaults__["seed"] = seed
        return build(32)
    finally:
        br._sim.__kwdefaults__.update(old)


def run_real(data: Path):
    print("\n## real photon lists; detect(rng=0, pfa=1e-4)")
    print(
        "| data | IRF | samples | FWHM | tail > 1 FWHM | tail > 2 FWHM | estimate s | surfaces "
        "| pixels >= 2 | depth shift vs gaussian (one-surface pixels, median) | detect s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, (rel, kw, _) in REAL.items():
        path = data / rel
        if not path.is_file():
            print(f"| {name} | missing: skipped |")
            continue
        cube = splidar.load(path, **kw, irf="estimate")  # the Gaussian estimate
        t0 = time.perf_counter()
        shape = estimate_irf(cube.counts)
        t_est = time.perf_counter() - t0
        t0 = time.perf_counter()
        hard = estimate_irf(cube.counts, refine=False)
        t_hard = time.perf_counter() - t0
        ref = None
        for label, irf, te in (
            ("gaussian est.", cube.irf, 0.0),
            ("shape est. hard", hard, t_hard),
            ("shape est. soft", shape, t_est),
        ):
            g = np.asarray(irf, float)[0]
            fw = float(irf_fwhm(g))
            c = dataclasses.replace(cube, irf=np.asarray(irf, float))
            t0 = time.perf_counter()
            det = splidar.detect(c, pfa=1e-4, rng=0)
            t_det = time.perf_counter() - t0
            pts = det.points
            per = np.bincount(pts.row * c.n_cols + pts.col, minlength=c.n_pixels)
            one = np.full(c.n_pixels, np.nan)
            k1 = per[pts.row * c.n_cols + pts.col] == 1
            one[(pts.row * c.n_cols + pts.col)[k1]] = pts.depth_bin[k1]
            if ref is None:
                ref = one
            both = np.isfinite(one) & np.isfinite(ref)
            shift = float(np.median(one[both] - ref[both])) if both.any() else float("nan")
            print(
                f"| {name} | {label} | {g.size} | {fw:.2f} | {tail_mass(g, fw):.3f} | "
                f"{tail_mass(g, 2 * fw):.3f} | {te:.2f} | {len(pts):,} | "
                f"{np.mean(per > 1):.1%} | {shift:+.1f} | {t_det:.1f} |"
            )
            if label != "gaussian est.":
                p = int(np.argmax(g))
                rel_ = [
                    g[p + k] / g[p] if p + k < g.size else 0.0 for k in (-4, -2, 4, 8, 12, 16, 24)
                ]
                txt = " / ".join(f"{v:.3f}" for v in rel_)
                print(f"|  | shape at -4/-2/+4/+8/+12/+16/+24 bins: {txt} |")


def run_art(data: Path, cells):
    """The Art scene (185 x 232, two surfaces per pixel, RGB: L = 3) simulated with a
    Gaussian (the scene's, FWHM 3) and an exp-tail 3/6 IRF; ``process`` with the true IRF,
    the Gaussian estimate, the hard and the soft shape."""
    from splidar.scenes import art_scene

    print("\n## Art (185 x 232 x 3 wavelengths, two surfaces per pixel); process(rng=0)")
    print(
        "| IRF of the simulation | PPP / SBR | IRF used | samples | FWHM | F_true | false "
        "| DAE | bias | estimate s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for label, irf_spec, T in (
        ("exp tail 3/6", ("exp_tail", 3.0, 6.0), 300),
        ("gaussian 3", ("gaussian", 3.0), 164),
    ):
        scene = art_scene(data / "middlebury-art", irf=irf_spec, n_bins=T)
        true = scene.irf_array
        fw = float(np.max(irf_fwhm(true)))
        tau = max(2.0, fw / 2.0)
        for ppp, sbr in cells:
            sim = scene.simulate(ppp=ppp, sbr=sbr, rng=0)
            cube, truth = sim.cube, sim.truth
            note = ""
            try:
                fw0 = estimate_irf_fwhm(cube.counts)
            except splidar.SplidarError as exc:  # the pair-lag width: the true FWHM given
                fw0 = fw
                note = f" (pair-lag width fails: {str(exc)[:40]}...; fwhm={fw:.2f} given)"
            t0 = time.perf_counter()
            soft = estimate_irf(cube.counts, fwhm=fw0)
            t_soft = time.perf_counter() - t0
            t0 = time.perf_counter()
            hard = estimate_irf(cube.counts, fwhm=fw0, refine=False)
            t_hard = time.perf_counter() - t0
            g = gaussian_irf(fw0)[None, :]
            for name, irf, te in (
                ("true", true, 0.0),
                ("gaussian est.", g, 0.0),
                ("shape est. hard", hard, t_hard),
                ("shape est. soft", soft, t_soft),
            ):
                c = dataclasses.replace(cube, irf=np.asarray(irf, float))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    rec = splidar.process(c, library=scene.library, rng=0)
                m = evaluate(rec.points, truth, tau=tau)
                bias = depth_bias(rec.points, truth, tau)
                fwe = float(np.max(irf_fwhm(np.asarray(irf, float))))
                print(
                    f"| {label} | {ppp:g} / {sbr:g} | {name}{note if name != 'true' else ''} "
                    f"| {np.shape(irf)[-1]} | {fwe:.2f} "
                    f"| {m.f_true:.3f} | {m.f_false} | {m.dae:.2f} | {bias:+.2f} | {te:.1f} |",
                    flush=True,
                )


def run_art_widths(data: Path):
    """The pair-lag width (``estimate_irf_fwhm``, the Gaussian of ``load``) on the Art
    cubes against the true FWHM, and its CPU time."""
    from splidar.scenes import art_scene

    print("\n## Art: estimate_irf_fwhm against the true FWHM (SBR 1, rng=0)")
    print("| IRF of the simulation | true FWHM | PPP | estimate | CPU s |")
    print("|---|---|---|---|---|")
    for label, irf_spec, T in (
        ("gaussian 3", ("gaussian", 3.0), 164),
        ("exp tail 3/6", ("exp_tail", 3.0, 6.0), 300),
    ):
        scene = art_scene(data / "middlebury-art", irf=irf_spec, n_bins=T)
        fw = float(np.max(irf_fwhm(scene.irf_array)))
        for ppp in (4.0, 16.0, 64.0):
            cube = scene.simulate(ppp=ppp, sbr=1.0, rng=0).cube
            t0 = time.process_time()
            try:
                r = f"{estimate_irf_fwhm(cube.counts):.2f}"
            except splidar.SplidarError as exc:
                r = f"raises: {str(exc)[:50]}"
            te = time.process_time() - t0
            print(f"| {label} | {fw:.2f} | {ppp:g} | {r} | {te:.1f} |", flush=True)


def _random_depths(n, T, seed):
    """One surface per pixel at uniform random depths (no spatial correlation)."""
    from splidar.points import PointSet

    rng = np.random.default_rng(100 + seed)
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return PointSet(
        row=rr.ravel(),
        col=cc.ravel(),
        depth_bin=rng.uniform(10, T - 60, n * n),
        image_shape=(n, n),
        intensity=np.ones((n * n, 1)),
        layer=np.zeros(n * n, int),
    )


def run_weak(seeds):
    """``--weak``: SBR 0.2 at PPP 1 / 2 / 4 (0.17-0.67 signal photons per pixel), the
    tilted plane of ``basic`` and one surface per pixel at random depths; the IRF ``load``
    builds when the file holds none (``io._resolve_irf``: the pair-lag width, pooled over
    pixel blocks when single pixels show no peak, then the shape) against the true IRF;
    ``process(rng=0)`` with each."""
    from bench_robustness import _sim

    from splidar.io import _resolve_irf

    print("\n## weak signal, 32 x 32, SBR 0.2; the IRF load builds without one; process(rng=0)")
    print(
        "| scene | IRF | PPP | seed | load's IRF source | L1 | FWHM | F_true (true IRF) "
        "| false (true) | bias (true) | load s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for irf_name, true, T in (
        ("exp tail 3/6", exp_tail_irf(3.0, 6.0), 300),
        ("exp tail 2/25", exp_tail_irf(2.0, 25.0), 400),
    ):
        true = np.asarray(true, float) / np.sum(true)
        fw = float(irf_fwhm(true))
        tau = max(2.0, fw / 2.0)
        for scene in ("plane", "random depths"):
            for ppp in (1.0, 2.0, 4.0):
                for seed in seeds:
                    if scene == "plane":
                        b = basic(T=T, ppp=ppp, sbr=0.2, irf=true)
                        cube, truth = b(32) if seed == 0 else _reseed(b, seed)
                    else:
                        cube, truth = _sim(
                            _random_depths(32, T, seed), T, true, ppp=ppp, sbr=0.2, seed=seed
                        )
                    t0 = time.process_time()
                    try:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            est, src = _resolve_irf(None, None, None, None, cube.counts, T)
                    except splidar.SplidarError as exc:
                        est, src = None, "raises: " + str(exc)[:70]
                    t_load = time.process_time() - t0
                    res = []
                    for irf in (true[None, :], est):
                        if irf is None:
                            res.append(None)
                            continue
                        c = dataclasses.replace(cube, irf=np.asarray(irf, float))
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            rec = splidar.process(c, rng=0)
                        m = evaluate(rec.points, truth, tau=tau)
                        res.append((m.f_true, m.f_false, depth_bias(rec.points, truth, tau)))
                    t, e = res
                    if e is None:
                        s_txt = "- | - | - | - | -"
                    else:
                        s = shape_row(true, est[0], fw)
                        s_txt = (
                            f"{s['l1']:.3f} | {s['fwhm']:.2f} | {e[0]:.3f} ({t[0]:.3f}) | "
                            f"{e[1]} ({t[1]}) | {e[2]:+.2f} ({t[2]:+.2f})"
                        )
                    print(
                        f"| {scene} | {irf_name} | {ppp:g} | {seed} | {src} | {s_txt} "
                        f"| {t_load:.2f} |",
                        flush=True,
                    )


def load_cells():
    """``--load-cells``: (name, T, PPP, SBR, true IRF) of the tilted plane of ``basic``."""
    t25 = exp_tail_irf(2.0, 25.0)
    t36 = exp_tail_irf(3.0, 6.0)
    cells = [
        ("exp tail 2/25, PPP 4, SBR 1", 400, 4.0, 1.0, t25),
        ("exp tail 2/25, PPP 4, SBR 0.2", 400, 4.0, 0.2, t25),
        ("exp tail 3/6, PPP 4, SBR 0.2", 300, 4.0, 0.2, t36),
        ("exp tail 3/6, PPP 4, SBR 1", 300, 4.0, 1.0, t36),
        ("exp tail 2/25, PPP 10, SBR 1", 400, 10.0, 1.0, t25),
        ("exp tail 2/25, PPP 1, SBR 0.2", 400, 1.0, 0.2, t25),
        ("exp tail 2/25, PPP 2, SBR 0.2", 400, 2.0, 0.2, t25),
        ("exp tail 3/6, PPP 1, SBR 0.2", 300, 1.0, 0.2, t36),
        ("exp tail 3/6, PPP 2, SBR 0.2", 300, 2.0, 0.2, t36),
        ("exp tail 3/6, PPP 2, SBR 1", 300, 2.0, 1.0, t36),
        ("exp tail 3/6, PPP 10, SBR 1", 300, 10.0, 1.0, t36),
    ]
    w = measured_irf()
    if w is not None:
        cells.append(("measured pulse, PPP 4, SBR 1", 300, 4.0, 1.0, w[230:300]))
        cells.append(("measured pulse, PPP 2, SBR 1", 300, 2.0, 1.0, w[230:300]))
        cells.append(("measured pulse, PPP 1, SBR 0.2", 300, 1.0, 0.2, w[230:300]))
        cells.append(("measured pulse, PPP 2, SBR 0.2", 300, 2.0, 0.2, w[230:300]))
    cells.append(("gaussian fwhm 3, PPP 2, SBR 1", 200, 2.0, 1.0, gaussian_irf(3.0)))
    return cells


def run_load_cells(seeds):
    """``--load-cells``: the IRF ``load`` builds without one (``io._resolve_irf``) on the
    cells of :func:`load_cells`: its level, L1 to the truth, ``process(rng=0)`` F_true /
    false / bias with it, CPU seconds; and (where this version has ``io._split_spread``)
    the split-half spreads of the single pixels' and the 2 x 2 blocks' shapes."""
    import splidar.io as sio

    print("\n## the IRF load builds without one, 32 x 32 tilted plane; process(rng=0)")
    print(
        "| cell | seed | load's IRF | L1 | F_true | false | bias | load CPU s "
        "| spread pixels / 2 x 2 blocks | pair-lag width (level) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, T, ppp, sbr, true in load_cells():
        true = np.asarray(true, float) / np.sum(true)
        fw = float(irf_fwhm(true))
        tau = max(2.0, fw / 2.0)
        for seed in seeds:
            b = basic(T=T, ppp=ppp, sbr=sbr, irf=true)
            cube, truth = b(32) if seed == 0 else _reseed(b, seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c0 = time.process_time()
                try:
                    est, src = sio._resolve_irf(None, None, None, None, cube.counts, T)
                except splidar.SplidarError as exc:
                    print(f"| {name} | {seed} | raises: {str(exc)[:60]} |", flush=True)
                    continue
                t_load = time.process_time() - c0
                rec = splidar.process(dataclasses.replace(cube, irf=est), rng=0)
                spread = "-"
                fwhm, kw = sio._pooled_fwhm(cube.counts, T, None)
                width = f"{fwhm:.1f} ({'pixels' if kw == 1 else f'{kw} x {kw}'})"
                if hasattr(sio, "_split_spread"):
                    sp = [
                        sio._split_spread(
                            cube.counts if q == 1 else sio._block_sum(cube.counts, q), fwhm
                        )
                        for q in (1, 2)
                    ]
                    spread = f"{sp[0]:.3f} / {sp[1]:.3f}"
            m = evaluate(rec.points, truth, tau=tau)
            kind = "shape" if "shape" in src.split("(")[0] else "Gaussian"
            lvl = src.split("pooled over ")[-1][:5] if "pooled over" in src else "pixels"
            print(
                f"| {name} | {seed} | {kind}, {lvl} | {shape_row(true, est[0], fw)['l1']:.3f} | "
                f"{m.f_true:.3f} | {m.f_false} | {depth_bias(rec.points, truth, tau):+.2f} | "
                f"{t_load:.2f} | {spread} | {width} |",
                flush=True,
            )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0])
    ap.add_argument("--real", action="store_true", help="also the three real photon lists")
    ap.add_argument("--no-sim", action="store_true")
    ap.add_argument("--ppp4", action="store_true", help="only the PPP 4 cases (simulated)")
    ap.add_argument("--art", action="store_true", help="also the Art scene (PPP 4, 16, 64, SBR 1)")
    ap.add_argument("--art-widths", action="store_true", help="the pair-lag width on the Art cubes")
    ap.add_argument("--weak", action="store_true", help="only the weak-signal cells (SBR 0.2)")
    ap.add_argument("--load-cells", action="store_true", help="only load's IRF on 16 cells")
    ap.add_argument(
        "--reference",
        choices=("peaks", "pmax", "argmax"),
        default=None,
        help="depth reference of the estimated shapes (_irf_estimate._REFERENCE; irf25)",
    )
    ap.add_argument("--data", default=str(_default_data()))
    args = ap.parse_args(argv)
    if args.reference is not None:
        import splidar._irf_estimate as _ie

        _ie._REFERENCE = args.reference
    t0 = time.perf_counter()
    if args.load_cells:
        run_load_cells(args.seeds)
    elif args.weak:
        run_weak(args.seeds)
    elif not args.no_sim:
        run_sim(args.seeds, ppp4_cases() if args.ppp4 else None)
    if args.real:
        run_real(Path(args.data))
    if args.art_widths:
        run_art_widths(Path(args.data))
    if args.art:
        run_art(Path(args.data), [(4.0, 1.0), (16.0, 1.0), (64.0, 1.0)])
    print(f"\nwall {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
