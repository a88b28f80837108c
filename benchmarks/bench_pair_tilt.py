"""The photon-pair width under heavy background: the signal-background pairs' tilt
(rob30).

``splidar._irf_width.pair_lag_fwhm`` flattens its pair histogram by ``T / (T - k)``,
right for the background's own pairs; a return's pairs with its pixel's background are
flat in the lag ``k``, so the correction tilts them up towards the floor's lags and the
width reads too narrow where they dominate (SBR 0.01: a 3-bin pulse read 1.4-1.7 bins).
``_irf_width._cross_tilt`` removes that tilt where it is significant. This bench runs,
in one sitting, with the tilt removal off (``_irf_width.TILT_LOAD = TILT_CHECK =
TILT_RESCUE = [False]``, the code before) and on (``--mode all``: everywhere,
``TILT_LOAD = [True]``; ``--mode default``: the library's, in the width check and in
load only where it found no return, ``TILT_RESCUE``):

* ``--widths``: ``estimate_irf_fwhm`` and the width check's ``_data_pair_width`` on the
  tilted 32 x 32 plane of ``bench_robustness.basic`` for Gaussian FWHM 1 / 3 / 10, exp
  tail 3/6 and 2/25 and the measured pulse at heavy background (PPP 100 SBR 0.01, PPP
  20 SBR 0.05, PPP 20 SBR 0.1 at T 150) and two controls; the pulse's own pair width
  (``_irf_width._irf_pair_width``) is the truth;
* ``--load``: the IRF ``load`` builds without one (``io._resolve_irf``) on those cubes,
  on ``bench_irf_estimate.py --load-cells``' 16 cells and on ``--weak``'s 24 cells:
  whether the array changes (``np.array_equal``), and ``process(rng=0)`` F_true / false
  / bias with each where it does (and with the true IRF);
* ``--real``: ``load`` of the three real photon lists (default IRF): the arrays and the
  load CPU time.

Run: ``python benchmarks/bench_pair_tilt.py --widths --load --real [--seeds 0 1 2]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import logging
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_irf_estimate import _random_depths, _reseed, depth_bias, load_cells  # noqa: E402
from bench_robustness import _sim, basic, measured_irf  # noqa: E402
from real_data import REAL, _default_data  # noqa: E402

import splidar  # noqa: E402
from splidar import _irf_width, io  # noqa: E402
from splidar.irf import exp_tail_irf, gaussian_irf, irf_fwhm  # noqa: E402
from splidar.metrics import evaluate  # noqa: E402


def pulses():
    out = [
        ("gauss 1", gaussian_irf(1.0)),
        ("gauss 3", gaussian_irf(3.0)),
        ("gauss 10", gaussian_irf(10.0)),
        ("exp tail 3/6", exp_tail_irf(3.0, 6.0)),
        ("exp tail 2/25", exp_tail_irf(2.0, 25.0)),
    ]
    w = measured_irf()
    if w is not None:
        out.append(("measured pulse", w[230:300]))
    return out


HEAVY = (
    (100.0, 0.01, None),
    (20.0, 0.05, None),
    (20.0, 0.1, 150),
    (10.0, 1.0, None),
    (4.0, 0.2, None),
)


def _T(irf, T):
    if T is not None:
        return T
    return int(max(200, 8 * (irf.size // 2) + 40))


def heavy_cubes(seeds):
    for name, irf in pulses():
        irf = np.asarray(irf, float) / np.sum(irf)
        for ppp, sbr, T in HEAVY:
            T = _T(irf, T)
            for seed in seeds:
                b = basic(T=T, ppp=ppp, sbr=sbr, irf=irf)
                try:
                    cube, truth = b(32) if seed == 0 else _reseed(b, seed)
                except splidar.SplidarError:  # the pulse does not fit a short record
                    break
                yield f"{name}, PPP {ppp:g} SBR {sbr:g} T {T}", seed, irf, cube, truth


MODE = ["default"]


def _flags(on) -> None:
    """off (False), on (True: ``MODE``'s), or the library's defaults (None)."""
    _irf_width.TILT_CHECK[0] = bool(on) or on is None
    _irf_width.TILT_RESCUE[0] = bool(on) or on is None
    _irf_width.TILT_LOAD[0] = bool(on) and MODE[0] == "all"


def both(f):
    """``f()`` with the tilt removal off, then on."""
    out = []
    for flag in (False, True):
        _flags(flag)
        try:
            out.append(f())
        except splidar.SplidarError:
            out.append("raises")
    _flags(None)
    return out


def _w(x):
    if isinstance(x, str):
        return x
    if x is None:
        return "-"
    if isinstance(x, tuple):
        return f"{x[0]:.2f} [{x[1][0]:.2f}, {x[1][1]:.2f}]"
    return f"{x:.2f}"


def run_widths(seeds):
    print("## widths (bins): off -> on; the pulse's own pair width in brackets")
    print("| cube | seed | estimate_irf_fwhm | width check (bracket; - undetermined) |")
    print("|---|---|---|---|")
    for name, seed, irf, cube, _ in heavy_cubes(seeds):
        y = cube.counts
        e = both(lambda y=y: io.estimate_irf_fwhm(y))
        c = both(lambda y=y: _irf_width._data_pair_width(y, y.shape[-1]))
        c = [x if x in (None, "raises") else (x[0], x[1]) for x in c]
        print(
            f"| {name} ({_irf_width._irf_pair_width(irf[None, :]):.2f}) | {seed} | {_w(e[0])} -> "
            f"{_w(e[1])} | {_w(c[0])} -> {_w(c[1])} |",
            flush=True,
        )


def _fwhm(irf) -> float:
    try:
        return float(np.max(irf_fwhm(np.atleast_2d(np.asarray(irf, float)))))
    except splidar.SplidarError:  # a shape that does not fall to half on one side
        return float("nan")


def _score(cube, irf, truth, true):
    """F_true / false / bias of ``process(rng=0)`` with ``irf`` (tau from the true IRF)."""
    tau = max(2.0, _fwhm(true) / 2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = dataclasses.replace(cube, irf=np.atleast_2d(np.asarray(irf, float)))
        rec = splidar.process(_irf_width.mark_checked(c), rng=0)
    m = evaluate(rec.points, truth, tau=tau)
    return f"{m.f_true:.3f} / {m.f_false} / {depth_bias(rec.points, truth, tau):+.2f}"


def _load_irf(counts, T):
    def f():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return io._resolve_irf(None, None, None, None, counts, T)

    return both(f)


def _load_cases(seeds):
    yield from ((f"heavy: {n}", s, irf, c, t) for n, s, irf, c, t in heavy_cubes(seeds))
    for name, T, ppp, sbr, true in load_cells():
        true = np.asarray(true, float) / np.sum(true)
        for seed in seeds:
            b = basic(T=T, ppp=ppp, sbr=sbr, irf=true)
            cube, truth = b(32) if seed == 0 else _reseed(b, seed)
            yield f"load cell: {name}", seed, true, cube, truth
    for irf_name, true, T in (
        ("exp tail 3/6", exp_tail_irf(3.0, 6.0), 300),
        ("exp tail 2/25", exp_tail_irf(2.0, 25.0), 400),
    ):
        true = np.asarray(true, float) / np.sum(true)
        for ppp in (1.0, 2.0, 4.0):
            for seed in seeds:
                b = basic(T=T, ppp=ppp, sbr=0.2, irf=true)
                cube, truth = b(32) if seed == 0 else _reseed(b, seed)
                yield f"weak plane: {irf_name} PPP {ppp:g}", seed, true, cube, truth
                cube, truth = _sim(
                    _random_depths(32, T, seed), T, true, ppp=ppp, sbr=0.2, seed=seed
                )
                yield f"weak random: {irf_name} PPP {ppp:g}", seed, true, cube, truth


def run_load(seeds):
    print("\n## the IRF load builds without one: off -> on (F_true / false / bias)")
    print("| cube | seed | changed | off: source, FWHM | on | F_true off | on | true IRF |")
    print("|---|---|---|---|---|---|---|---|")
    n = changed = 0
    for name, seed, true, cube, truth in _load_cases(seeds):
        T = cube.shape[-1]
        r = _load_irf(cube.counts, T)
        n += 1
        if all(isinstance(x, str) for x in r):
            same = True  # raises either way
        else:
            same = not any(isinstance(x, str) for x in r) and np.array_equal(r[0][0], r[1][0])
        if same:
            continue
        changed += 1
        desc = []
        for x in r:
            if isinstance(x, str):
                desc.append(x)
            else:
                desc.append(f"{x[1].split('(')[0].strip()[:40]}, {_fwhm(x[0]):.2f}")
        sc = [x if isinstance(x, str) else _score(cube, x[0], truth, true) for x in r]
        print(
            f"| {name} | {seed} | yes | {desc[0]} | {desc[1]} | {sc[0]} | {sc[1]} | "
            f"{_score(cube, true, truth, true)} |",
            flush=True,
        )
    print(f"\n{changed} of {n} IRFs changed (the others identical arrays)")


def run_real(data: Path):
    print("\n## real files, load with the default IRF: off / on")
    for name, (rel, kw, _) in REAL.items():
        p = data / rel
        if not p.is_file():
            print(f"- {name}: missing")
            continue
        out = []
        for flag in (False, True, False, True):
            _flags(flag)
            logging.getLogger("splidar").setLevel(logging.ERROR)
            c0 = time.process_time()
            cube = splidar.load(p, **kw)
            t = time.process_time() - c0
            md5 = hashlib.md5(np.ascontiguousarray(cube.irf).tobytes()).hexdigest()[:8]
            fw = float(np.max(irf_fwhm(cube.irf)))
            out.append(f"{'on' if flag else 'off'} {md5} FWHM {fw:.3f} {t:.2f} s")
            w = _irf_width._data_pair_width(cube.counts, cube.shape[-1])
            if w is not None:
                out[-1] += f" (check width {w[0]:.2f})"
        _flags(None)
        print(f"- {name}: " + "; ".join(out), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    ap.add_argument("--widths", action="store_true")
    ap.add_argument("--load", action="store_true")
    ap.add_argument("--real", action="store_true")
    ap.add_argument("--data", default=str(_default_data()))
    ap.add_argument("--mode", choices=("default", "all"), default="default")
    args = ap.parse_args()
    MODE[0] = args.mode
    logging.basicConfig(level=logging.ERROR)
    t0 = time.perf_counter()
    if args.widths:
        run_widths(args.seeds)
    if args.real:
        run_real(Path(args.data))
    if args.load:
        run_load(args.seeds)
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
