"""Detection of a cube larger than the memory it is allowed: Zarr in, Zarr out.

A cube is written to a Zarr directory chunk by chunk (never whole in memory), opened
lazily with :func:`splidar.load`, and detected twice in one process:

* in memory: ``saliency``, ``mask`` and the per-voxel threshold are ``(rows, cols, T)``
  arrays held in RAM;
* with ``store=``: the same arrays are written to a Zarr directory block by block.

It prints the time and the peak resident memory above the start of each call, next to
the size of the input counts and of one ``(rows, cols, T)`` float32 array, and checks
that both give the same surfaces.

Usage::

    python benchmarks/bench_out_of_core.py                  # 600 x 600 x 1 x 1000
    python benchmarks/bench_out_of_core.py --rows 256 --cols 256 --bins 600   # quick
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _measure import measure_memory  # noqa: E402

import splidar  # noqa: E402
from splidar.irf import gaussian_irf  # noqa: E402


def write_cube(path: Path, rows: int, cols: int, n_bins: int, *, chunk_rows: int = 32, seed=0):
    """A tilted plane (20 photons) over 2 background photons per pixel, written in chunks."""
    import dask
    import dask.array as da

    g = gaussian_irf(3.0)
    h = g.size // 2
    t = np.arange(n_bins)

    def block(r0: int, r1: int) -> np.ndarray:
        rng = np.random.default_rng([seed, r0])
        rr, cc = np.mgrid[r0:r1, 0:cols]
        depth = 0.2 * n_bins + 0.5 * n_bins * (0.6 * rr / rows + 0.4 * cc / cols)
        lam = np.full((r1 - r0, cols, 1, n_bins), 2.0 / n_bins, np.float32)
        x = t[None, None, :] - depth[..., None]
        lam[:, :, 0, :] += (
            20.0 * np.exp(-0.5 * (x / (3.0 / 2.3548)) ** 2) / (np.sqrt(2 * np.pi) * 3.0 / 2.3548)
        )
        return rng.poisson(lam).astype(np.uint8)

    parts = [
        da.from_delayed(
            dask.delayed(block)(r0, min(rows, r0 + chunk_rows)),
            shape=(min(rows, r0 + chunk_rows) - r0, cols, 1, n_bins),
            dtype=np.uint8,
        )
        for r0 in range(0, rows, chunk_rows)
    ]
    counts = da.concatenate(parts, axis=0)
    del h
    splidar.save(splidar.Cube(counts, irf=g), path, chunks=(chunk_rows, cols))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=600)
    ap.add_argument("--cols", type=int, default=600)
    ap.add_argument("--bins", type=int, default=1000)
    args = ap.parse_args(argv)
    R, C, T = args.rows, args.cols, args.bins
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        write_cube(tmp / "cube.zarr", R, C, T)
        print(f"wrote {R} x {C} x 1 x {T} uint8 cube in {time.perf_counter() - t0:.1f} s")
        cube = splidar.load(tmp / "cube.zarr")
        f32 = R * C * T * 4
        print(
            f"input counts {R * C * T / 1e6:.0f} MB (uint8); one (rows, cols, T) float32 "
            f"array {f32 / 1e6:.0f} MB"
        )
        results = {}
        for name, kw in (("in memory", {}), ("store=", {"store": tmp / "det"})):
            t0 = time.perf_counter()
            mem = measure_memory(lambda kw=kw: splidar.detect(cube, rng=0, **kw), keep_result=True)
            dt = time.perf_counter() - t0
            det = mem.result
            results[name] = det
            print(
                f"{name:10s} {dt:6.1f} s (with memory probes), peak RSS above start "
                f"{mem.rss / 1e6:7.0f} MB "
                f"({mem.rss / f32:.2f} x one float32 (rows, cols, T) array); "
                f"{len(det.surfaces)} surfaces, {100 * det.reduction.voxel_fraction:.2f} % "
                "of voxels kept"
            )
        a, b = results["in memory"], results["store="]
        same = np.array_equal(a.surfaces.depth_bin, b.surfaces.depth_bin) and (
            a.reduction == b.reduction
        )
        print(f"identical surfaces and reduction: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
