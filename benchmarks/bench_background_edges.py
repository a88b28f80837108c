"""Stage 1's background shape against the known mean, at the window's edges.

Background-only cubes (96 x 80 x 200 by default, Gaussian IRF FWHM 3 bins) with a known
per-bin mean of several shapes: ``uniform``, ``decaying`` (``exp(-3 t / T)``, the
simulator's), ``rise`` (``exp(3 t / T)``), ``bump`` (0.3 + a Gaussian of 0.15 T in the
middle), ``ends`` (0.3 + Gaussians of 0.1 T at both ends) and ``pileup`` (the
simulator's); and ``start-returns`` / ``end-returns``: a uniform background with a
return in every pixel (as many signal photons as background ones, SBR 1; depths uniform
within 3 bins of the first / last bin, more pixels than the 90 % ``eq:background_1``
tolerates), whose background is the uniform one. For each,
:func:`~splidar.detection._1_background.estimate_temporal_background`
(box 11) is compared with the matched filter of the true mean (what the filtered counts
have as mean in every bin, mirrored edges included): the error in per cent of that mean
and in standard deviations of one coarsest-box value (``sqrt(mean sum g^2 / 121)``),
averaged over the cubes, at the first 3 bins, the last 3 bins and the middle 20; with
its standard error.

Usage::

    python benchmarks/bench_background_edges.py [--cubes 8] [--levels 0.02 0.08 0.5]
    PYTHONPATH=/path/to/other/src python benchmarks/bench_background_edges.py   # compare

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse

import numpy as np

from splidar import gaussian_irf
from splidar.detection._1_background import estimate_temporal_background
from splidar.detection._filters import Correlator
from splidar.simulation import background_shape

BOX = 11


def shapes(T: int) -> dict[str, np.ndarray]:
    """The per-bin shapes, each with mean 1."""
    t = np.arange(T, dtype=np.float64)
    out = {
        "uniform": np.ones(T),
        "decaying": background_shape("decaying", T),
        "rise": np.exp(3.0 * t / T),
        "bump": 0.3 + np.exp(-0.5 * ((t - 0.5 * T) / (0.15 * T)) ** 2),
        "ends": 0.3
        + np.exp(-0.5 * (t / (0.1 * T)) ** 2)
        + np.exp(-0.5 * ((T - 1 - t) / (0.1 * T)) ** 2),
        "pileup": background_shape("pileup", T),
    }
    return {k: v / v.mean() for k, v in out.items()}


#: Shapes with a return in every pixel: depths (bins from the first bin, or from the last)
RETURNS = {"start-returns": (0.0, 3.0, False), "end-returns": (0.0, 3.0, True)}


def _returns(size, T, level, spec, rng):
    """Expected counts of a return in every pixel (Gaussian FWHM 3 bins, ``level x T``
    photons: SBR 1), depths uniform in ``spec``'s range from the first or last bin."""
    lo, hi, from_end = spec
    d = lo + (hi - lo) * rng.random(size)
    d = T - 1 - d if from_end else d
    t = np.arange(T)
    p = np.exp(-0.5 * ((t - d[..., None]) / (3.0 / 2.3548)) ** 2)
    return (level * T * p / p.sum(axis=-1, keepdims=True))[:, :, None, :]


def measure(shape, level, n_cubes, size, T, returns=None):
    """Mean and standard error over ``n_cubes`` of the shape's error at the first 3, the
    last 3 and the middle 20 bins: per cent of the mean, and coarse-value sigmas.
    ``returns``: a :data:`RETURNS` entry added to every pixel (not in the target)."""
    g = np.asarray(gaussian_irf(3.0), np.float64)[None]
    corr = Correlator(g, T)
    mean = level * shape
    target = corr(mean[None].astype(np.float32))[0].astype(np.float64)
    sd = np.sqrt(target * (g**2).sum() / BOX**2)
    parts = (slice(0, 3), slice(T - 3, T), slice(T // 2 - 10, T // 2 + 10))
    rel, sig = [], []
    for seed in range(n_cubes):
        rng = np.random.default_rng(seed)
        lam = np.broadcast_to(mean, (*size, 1, T))
        if returns is not None:
            lam = lam + _returns(size, T, level, returns, np.random.default_rng(1000 + seed))
        counts = rng.poisson(lam)
        est = estimate_temporal_background(counts, corr, g, box=BOX, n_jobs=1).temporal[0]
        err = est.astype(np.float64) - target
        rel.append([100 * err[p].mean() / target[p].mean() for p in parts])
        sig.append([(err[p] / sd[p]).mean() for p in parts])
    rel, sig = np.array(rel), np.array(sig)
    se = np.sqrt(n_cubes) if n_cubes > 1 else np.nan
    return rel.mean(0), rel.std(0, ddof=1) / se, sig.mean(0), sig.std(0, ddof=1) / se


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cubes", type=int, default=8, help="cubes per row (default 8)")
    ap.add_argument("--levels", type=float, nargs="+", default=[0.02, 0.08, 0.5])
    ap.add_argument("--bins", type=int, default=200)
    ap.add_argument("--size", type=int, nargs=2, default=[96, 80])
    ap.add_argument("--shapes", nargs="+", default=None, help="a subset of the shapes")
    args = ap.parse_args(argv)
    T = args.bins
    all_shapes = shapes(T)
    names = args.shapes or list(all_shapes) + list(RETURNS)
    print(
        f"stage 1's shape less the filtered true mean, {args.size[0]} x {args.size[1]} x {T}, "
        f"{args.cubes} cubes per row; per cent (sigmas of one coarsest-box value), +- se"
    )
    head = " | ".join(f"{h:>24s}" for h in ("first 3 bins", "last 3 bins", "middle"))
    print(f"{'shape':13s} {'bg/bin':>6s} | {head}")
    for name in names:
        for level in args.levels:
            shape = all_shapes.get(name, all_shapes["uniform"])
            rel, rse, sig, sse = measure(
                shape, level, args.cubes, tuple(args.size), T, RETURNS.get(name)
            )
            cells = [
                f"{rel[i]:+6.1f}+-{rse[i]:3.1f} ({sig[i]:+5.2f}+-{sse[i]:4.2f})" for i in range(3)
            ]
            print(f"{name:13s} {level:6.3f} | " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
