"""Regression checker for refactorings of ``splidar.detect`` (and ``splidar.simulate``).

A refactoring changes no result: this script runs ``detect`` with its default options on
small simulated scenes (single surface, net in front of objects, multispectral; uniform
and decaying background; PPP 1, 4, 10; an asymmetric IRF; ``n_jobs`` 1 and 3; ``store=`` Zarr)
and saves every output array (the simulated counts, the surfaces table, saliency, mask,
background factors, threshold, null model) once, then compares a later run bit for bit.

Usage::

    python benchmarks/golden_detect.py --save  DIR   # record the reference outputs
    python benchmarks/golden_detect.py --check DIR   # compare; exit 1 on any difference

The ``options`` mapping of the result is compared too but only reported (it lists the
options, which a refactoring of the signature may rename); arrays must be identical.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from splidar.detection import detect
from splidar.detection._result import StoredHistograms
from splidar.scenes import multispectral_scene, single_surface_scene, two_layer_scene

SHAPE = (24, 24)
N_BINS = 120


def _cases():
    """(name, scene factory, simulate kwargs, detect kwargs)."""
    single = lambda: single_surface_scene(SHAPE, n_bins=N_BINS)  # noqa: E731
    net = lambda: two_layer_scene(SHAPE, n_bins=N_BINS)  # noqa: E731
    multi = lambda: multispectral_scene(SHAPE, n_bins=N_BINS, two_layers=True)  # noqa: E731
    skew = lambda: two_layer_scene(SHAPE, n_bins=N_BINS, irf=("exp_tail", 3.0, 6.0))  # noqa: E731
    return [
        ("single_u_ppp1", single, dict(ppp=1, sbr=1.0, background="uniform"), {}),
        ("single_u_ppp4", single, dict(ppp=4, sbr=0.25, background="uniform"), {}),
        ("single_d_ppp4", single, dict(ppp=4, sbr=0.25, background="decaying"), {}),
        ("single_u_ppp10", single, dict(ppp=10, sbr=1.0, background="uniform"), {}),
        ("net_u_ppp10", net, dict(ppp=10, sbr=1.0, background="uniform"), {}),
        ("net_d_ppp4", net, dict(ppp=4, sbr=0.25, background="decaying"), {}),
        ("net_d_ppp1", net, dict(ppp=1, sbr=10.0, background="decaying"), {}),
        ("multi_u_ppp4", multi, dict(ppp=4, sbr=1.0, background="uniform"), {}),
        ("skew_u_ppp10", skew, dict(ppp=10, sbr=0.5, background="uniform"), {}),
        ("net_u_ppp10_jobs1", net, dict(ppp=10, sbr=1.0, background="uniform"), {"n_jobs": 1}),
        (
            "single_d_ppp4_jobs3",
            single,
            dict(ppp=4, sbr=0.25, background="decaying"),
            {"n_jobs": 3},
        ),
        ("net_d_ppp4_store", net, dict(ppp=4, sbr=0.25, background="decaying"), {"store": True}),
    ]


def _arrays(sim, det) -> dict[str, np.ndarray]:
    out = {"sim.counts": np.asarray(sim.cube.counts)}
    s = det.surfaces
    for k, v in vars(s).items():
        if isinstance(v, np.ndarray):
            out[f"surfaces.{k}"] = v
        elif isinstance(v, StoredHistograms):  # store=: the histograms stay on disk
            out[f"surfaces.{k}"] = np.asarray(v)
    out["saliency"] = np.asarray(det.saliency)
    out["mask"] = np.asarray(det.mask)
    out["threshold"] = np.asarray(det.threshold, dtype=np.float32)
    out["background.spatial"] = det.background.spatial
    out["background.temporal"] = det.background.temporal
    out["weights"] = np.asarray(det.weights)
    out["null.params"] = np.array([det.null.shape, det.null.scale, det.null.calibration])
    for k, v in det.null.details.items():
        out[f"null.{k}"] = np.asarray(v)
    r = det.reduction
    out["reduction"] = np.array([r.voxel_fraction, r.photon_fraction, r.n_voxels, r.n_photons])
    return out


def _options(det) -> dict:
    skip = {"store"}
    return {k: repr(v) for k, v in det.options.items() if k not in skip}


def run_case(case, tmp: Path):
    name, factory, sim_kw, det_kw = case
    sim = factory().simulate(rng=0, **sim_kw)
    kw = dict(det_kw)
    if kw.get("store"):
        kw["store"] = tmp / f"{name}.zarr"
    det = detect(sim.cube, **kw)
    return _arrays(sim, det), _options(det)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--save", metavar="DIR")
    mode.add_argument("--check", metavar="DIR")
    ap.add_argument("--only", nargs="*", help="case names to run (default: all)")
    args = ap.parse_args(argv)
    root = Path(args.save or args.check)
    root.mkdir(parents=True, exist_ok=True)
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        for case in _cases():
            if args.only and case[0] not in args.only:
                continue
            arrays, options = run_case(case, Path(tmp))
            f_arr, f_opt = root / f"{case[0]}.npz", root / f"{case[0]}.options.json"
            if args.save:
                np.savez_compressed(f_arr, **arrays)
                f_opt.write_text(json.dumps(options, indent=1, sort_keys=True))
                print(
                    f"saved {case[0]}: {len(arrays)} arrays, {arrays['surfaces.row'].size} surfaces"
                )
                continue
            ref = dict(np.load(f_arr))
            # arrays the reference lacks are new fields (reported); missing ones differ
            new = sorted(set(arrays) - set(ref))
            diffs = [k for k in sorted(ref) if k not in arrays]
            for k in sorted(set(ref) & set(arrays)):
                a, b = ref[k], arrays[k]
                if a.shape != b.shape or a.dtype != b.dtype or a.tobytes() != b.tobytes():
                    diffs.append(k)
            ref_opt = json.loads(f_opt.read_text())
            opt_diff = {
                k: (ref_opt.get(k), options.get(k))
                for k in set(ref_opt) | set(options)
                if ref_opt.get(k) != options.get(k)
            }
            status = "IDENTICAL" if not diffs else "DIFFERENT: " + ", ".join(diffs)
            print(f"{case[0]:22s} {status}" + (f" (new arrays: {', '.join(new)})" if new else ""))
            if opt_diff:
                print(f"{'':22s} options differ (reported only): {opt_diff}")
            bad += bool(diffs)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
