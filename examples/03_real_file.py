"""
A real measurement: photon lists to surfaces
============================================

Real measurements: photon lists from a file -> histogram cube -> surfaces -> figure.

Run:  python examples/03_real_file.py [PATH] [--bin-width PS] [--out FOLDER]

Default PATH: the public "tower" data set in ../shared/data/tower/tower.mat (a cell per
pixel of photon arrival times in picoseconds; not part of the project). Its README gives
the range gate, 5,180,000..5,380,000 ps; 128 ps bins (about half the width of the
returns) make 1563 time bins. The file holds
no instrument response, so the loader fits a Gaussian IRF whose width it estimates
from the data (logged as a warning). For other files pass --variable, --window and
--time-unit (see ``splidar.load``).
"""

import argparse
import logging
import time
from pathlib import Path

import splidar

# run from the repository root: the shared data sets lie beside it
TOWER = Path("..") / "shared" / "data" / "tower" / "tower.mat"

ap = argparse.ArgumentParser(description="detect and reconstruct surfaces in a photon-list file")
ap.add_argument("path", nargs="?", type=Path, default=TOWER)
ap.add_argument("--variable", default="data_processed", help="cell array of arrival times")
ap.add_argument("--time-unit", default="ps")
ap.add_argument("--window", type=float, nargs=2, default=(5_180_000, 5_380_000))
ap.add_argument("--bin-width", type=float, default=128.0, help="in --time-unit")
ap.add_argument("--out", type=Path, default=Path("real_file_output"))
args = ap.parse_args()
logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

t0 = time.perf_counter()
cube = splidar.load(
    args.path,
    variable=args.variable,
    time_unit=args.time_unit,
    window=tuple(args.window),
    bin_width=args.bin_width,
)
t_load = time.perf_counter() - t0
print(cube)
print(
    f"photons per pixel {cube.photons_per_pixel():.2f}, IRF "
    f"{dict(cube.metadata).get('irf_source', 'from file')}, load {t_load:.2f} s"
)

det = splidar.detect(cube, rng=0)  # multiscale detection (Algorithm 1)
red = det.reduction
print(
    f"{len(det.points)} surfaces; kept {red.n_voxels:,} of {cube.counts.size:,} voxels "
    f"({100 * red.voxel_fraction:.3f} %) holding {100 * red.photon_fraction:.1f} % of the "
    f"photons; detect {det.timings['total']:.2f} s"
)

rec = splidar.reconstruct(det, rng=0)  # Bayesian depth/intensity (Algorithm 2)
print(f"reconstruct {rec.timings['total']:.2f} s, {rec.history.n_iter} iterations")

args.out.mkdir(parents=True, exist_ok=True)
rec.points.save(args.out / "points.npz")
try:
    import matplotlib

    matplotlib.use("Agg")  # files only, no window
    from splidar.plotting import plot_depth
except ImportError as err:  # plotting needs matplotlib
    print(f"no figure: {err}")
else:
    ax = plot_depth(rec, layer=0)
    ax.figure.savefig(args.out / "depth.png", dpi=110, bbox_inches="tight")
    print(f"saved {args.out / 'depth.png'} and {args.out / 'points.npz'}")
