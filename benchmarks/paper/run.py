"""The paper's experiments in one command: figures and a JSON of the numbers.

Reproduces what Belmekki et al. report, with the per-pixel baselines of
:mod:`splidar.baselines` beside splidar, and the paper's own numbers beside ours where
it gives them (its two tables; its Art figures carry no numbers, so their statements are
checked instead):

1. **Detection and reconstruction on the simulated two-layer scene**
   (``fig:3D_reconst_Art``, ``fig:Quant_3D_Art``): the Middlebury Art scene (185 x 232,
   T = 164, two surfaces per pixel, RGB) when ``<data>/middlebury-art`` exists, else the
   built-in multispectral net scene; PPP x SBR x {uniform, decaying} background; F_true,
   F_false, DAE, IAE, label and detection accuracy at tau = 4 mm. Figures: depth maps
   (``detection_maps_*.png``), class maps (``classification_maps.png``), metrics against
   PPP (``metrics_vs_ppp.png``) and against tau (``metrics_vs_tau.png``).
2. **Detection accuracy against acquisition time** (``tabl:AccTD``, Lego, not public): a
   simulated object of 3 materials at 4 wavelengths in front of empty pixels, SBR 1.3,
   over PPP; the paper's values at PPP = 25 x its acquisition time in ms
   (``accuracy_vs_time.png``, ``classification_maps_object.png``).
3. **The real mannequin face at shorter acquisitions** (in the spirit of
   ``tabl:table_TD``, whose camouflage data are not public): the photon lists of
   ``<data>/face`` thinned to fractions of the acquisition, each method scored against its
   own result on all photons (``face_maps.png``), the paper's values beside ours at its
   fractions 0.5/3.2 and 1/3.2.
4. **Data reduction**: the fraction of voxels splidar's 3D map keeps and of the photons
   in them, for every run (``data_reduction.png``); the paper claims it, with no number.

Usage::

    python benchmarks/paper/run.py --out paper-run            # about 4-6 minutes
    python benchmarks/paper/run.py --out paper-run --quick    # under a minute
    python benchmarks/paper/run.py --out DIR --quick --scene builtin --data /nonexistent

Writes ``DIR/results.json``, ``DIR/summary.md`` (the side-by-side tables) and
``DIR/figures/*.png``. Never downloads anything: parts
whose data are absent are skipped and say so in the JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import _experiments as ex
import _figures as figs
import _paper as paper
import numpy as np
from _summary import summary_markdown

import splidar
from splidar.scenes import art_scene, multispectral_scene

FULL = {
    "ppp": (1.0, 4.0, 16.0, 64.0),
    "sbr": (0.25, 1.0, 4.0),
    "acq_ppp": (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0),
    "face_fractions": (0.05, 0.5 / 3.2, 1.0 / 3.2, 0.5, 1.0),
}
QUICK = {
    "ppp": (4.0, 16.0),
    "sbr": (1.0,),
    "acq_ppp": (1.0, 10.0, 50.0),
    "face_fractions": (1.0 / 3.2, 1.0),
}
#: quick: two PPP on a uniform background, the lower one also decaying; no coarse-7
QUICK_CELLS = ((4.0, 1.0, "uniform"), (16.0, 1.0, "uniform"), (4.0, 1.0, "decaying"))
FACE_QUICK_CROP = ((40, 200), (90, 250))  # forehead to mouth, 160 x 160 of 340 x 340
BACKGROUNDS = ("uniform", "decaying")


def _default_data() -> Path:
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _parse(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder (created)")
    ap.add_argument("--quick", action="store_true", help="fewer cells, smaller crops (< 1 min)")
    ap.add_argument("--data", type=Path, default=_default_data(), help="shared data folder")
    ap.add_argument(
        "--scene",
        choices=("auto", "art", "builtin"),
        default="auto",
        help="simulated scene: Art when its files exist (auto), or the built-in net scene",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--skip", default="", help="comma-separated parts to skip: simulated,acquisition,face"
    )
    return ap.parse_args(argv)


def part_simulated(args, grid, fig_dir: Path) -> dict:
    art = args.data / "middlebury-art"
    if args.scene == "art" or (args.scene == "auto" and art.is_dir()):
        scene = art_scene(art)
    else:
        size = (48, 48) if args.quick else (64, 64)
        scene = multispectral_scene(size, two_layers=True)
    tau_mm = paper.ART_SETUP["tau_mm"]
    print(f"[1] {scene}: tau = {tau_mm:g} mm", flush=True)
    cells = [(p, s, b) for b in BACKGROUNDS for p in grid["ppp"] for s in grid["sbr"]]
    methods = ex.METHODS
    if args.quick:
        cells, methods = list(QUICK_CELLS), ("splidar", "per-pixel")
    low = min(grid["ppp"])
    keep = {(low, 1.0, b) for b in BACKGROUNDS}
    rows, kept = ex.simulated_grid(
        scene, cells, tau_mm=tau_mm, seed=args.seed, keep=keep, methods=methods
    )
    figures = []
    for k in kept:
        bg = k.label.split(", ")[-1].split()[0]
        figures.append(figs.detection_maps(k, fig_dir / f"detection_maps_{bg}.png"))
    if kept:
        figures.append(
            figs.classification_maps(
                kept[0], fig_dir / "classification_maps.png", scene.library.class_names
            )
        )
        figures.append(figs.metrics_vs_tau(kept, fig_dir / "metrics_vs_tau.png"))
    figures.append(figs.metrics_vs_ppp(rows, fig_dir / "metrics_vs_ppp.png", tau_mm=tau_mm))
    return {
        "scene": {
            "name": scene.name,
            "shape": list(scene.shape),
            "n_bins": scene.n_bins,
            "n_wavelengths": scene.n_wavelengths,
            "n_true": len(scene.truth),
            "bin_width_ps": scene.bin_width_ps,
            "description": scene.description,
        },
        "tau_mm": tau_mm,
        "rows": rows,
        "paper": {**paper.ART_SETUP, "numbers": None},
        "paper_claims": {
            k: {"paper": paper.ART_CLAIMS[k], **v} for k, v in ex.check_art_claims(rows).items()
        },
        "figures": figures,
    }


def part_acquisition(args, grid, fig_dir: Path) -> dict:
    shape = (40, 40) if args.quick else (64, 64)
    sbr, keep_ppp = 1.3, 10.0
    print(f"[2] object scene {shape}, SBR {sbr:g}, PPP {list(grid['acq_ppp'])}", flush=True)
    scene, rows, kept = ex.acquisition_sweep(
        shape, grid["acq_ppp"], sbr=sbr, seed=args.seed, keep_ppp=keep_ppp
    )
    figures = [figs.accuracy_vs_time(rows, paper.ACC_TD, fig_dir / "accuracy_vs_time.png")]
    if kept is not None:
        figures.append(
            figs.classification_maps(
                kept, fig_dir / "classification_maps_object.png", scene.library.class_names
            )
        )
    side = []
    per_ms = paper.ACC_TD["ppp_per_ms"]
    for i, ms in enumerate(paper.ACC_TD["acquisition_ms"]):
        ppp = ms * per_ms
        ours = {r["method"]: 100 * r["detection_accuracy"] for r in rows if r["ppp"] == ppp}
        if ours:
            side.append(
                {
                    "acquisition_ms": ms,
                    "ppp": ppp,
                    "paper_pct": {k: v[i] for k, v in paper.ACC_TD["accuracy_pct"].items()},
                    "ours_pct": ours,
                }
            )
    return {
        "scene": {
            "shape": list(shape),
            "sbr": sbr,
            "n_true": len(scene.truth),
            "pixels_with_object": len(scene.truth) / (shape[0] * shape[1]),
        },
        "rows": rows,
        "paper": paper.ACC_TD,
        "side_by_side": side,
        "figures": figures,
    }


def part_face(args, grid, fig_dir: Path) -> dict:
    path = args.data / "face" / "data_face.mat"
    if not path.is_file():
        print(f"[3] no face data at {path}: skipped", flush=True)
        return {"skipped": f"{path} is absent"}
    crop = FACE_QUICK_CROP if args.quick else None
    print(f"[3] face {path}, fractions {[round(f, 4) for f in grid['face_fractions']]}", flush=True)
    info, rows, maps = ex.face_thinning(path, grid["face_fractions"], crop=crop, seed=args.seed)
    figures = [figs.face_maps(maps, grid["face_fractions"], fig_dir / "face_maps.png")]
    side = []
    for i, f in enumerate(paper.TABLE_TD["fraction_of_reference"]):
        ours = {r["method"]: r for r in rows if math.isclose(r["fraction"], f)}
        if ours:
            side.append(
                {
                    "fraction": f,
                    "paper_acquisition_ms": paper.TABLE_TD["acquisition_ms"][i],
                    "paper": {
                        key: {m: v[i] for m, v in tab.items()}
                        for key, tab in paper.TABLE_TD.items()
                        if key in ("IAE", "F_true_pct", "F_false")
                    },
                    "ours": {
                        m: {
                            "F_true_pct": 100 * r["f_true"],
                            "F_false": r["f_false"],
                            "IAE": r["iae"],
                        }
                        for m, r in ours.items()
                    },
                }
            )
    return {
        "data": info,
        "rows": rows,
        "paper": paper.TABLE_TD,
        "side_by_side": side,
        "figures": figures,
    }


def _reduction(results: dict) -> list[dict]:
    out = []
    for r in results.get("simulated", {}).get("rows", []):
        if r["method"] == "splidar":
            out.append(
                {
                    "run": f"sim PPP {r['ppp']:g} SBR {r['sbr']:g} {r['background'][:3]}",
                    "voxel_fraction": r["voxel_fraction"],
                    "photon_fraction": r["photon_fraction"],
                }
            )
    for r in results.get("face", {}).get("rows", []):
        if r["method"] == "splidar":
            out.append(
                {
                    "run": f"face {100 * r['fraction']:.3g} %",
                    "voxel_fraction": r["voxel_fraction"],
                    "photon_fraction": r["photon_fraction"],
                }
            )
    return out


def main(argv=None) -> int:
    args = _parse(argv)
    grid = QUICK if args.quick else FULL
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    fig_dir = args.out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    results: dict = {
        "meta": {
            "splidar": splidar.__version__,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "quick": args.quick,
            "seed": args.seed,
            "paper": "Belmekki et al., 3D Target Detection and Spectral Classification "
            "for Single-photon LiDAR Data",
        },
    }
    parts = (("simulated", part_simulated), ("acquisition", part_acquisition), ("face", part_face))
    for name, fn in parts:
        if name in skip:
            results[name] = {"skipped": "--skip"}
            continue
        t0 = time.perf_counter()
        results[name] = fn(args, grid, fig_dir)
        results[name]["seconds"] = time.perf_counter() - t0
    red = _reduction(results)
    results["data_reduction"] = {"runs": red, "paper": paper.DATA_REDUCTION, "figures": []}
    if red:
        results["data_reduction"]["figures"].append(
            figs.data_reduction(red, fig_dir / "data_reduction.png")
        )
    results["meta"]["seconds"] = time.perf_counter() - t_all
    out = args.out / "results.json"
    out.write_text(json.dumps(results, indent=1, default=_json))
    (args.out / "summary.md").write_text(summary_markdown(results))
    print(
        f"wrote {out}, {args.out / 'summary.md'} and {len(list(fig_dir.glob('*.png')))} "
        f"figures in {results['meta']['seconds']:.1f} s"
    )
    return 0


def _json(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON: {type(x).__name__}")


if __name__ == "__main__":
    sys.exit(main())
