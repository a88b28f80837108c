"""Detection on Dask: in memory, threads over a Zarr cube, a LocalCluster of 1 and 2 workers.

A cube (a tilted plane over background, ``bench_out_of_core.write_cube``) is written to
Zarr chunk by chunk and detected four ways in one run:

* ``memory``: the counts read into a NumPy array first (the in-memory path);
* ``threads``: the lazy Zarr cube on Dask's threaded scheduler (the default);
* ``cluster-N``: the lazy Zarr cube on a ``LocalCluster`` of N worker processes (one
  thread each, ``--memory-limit`` each), N = 1, 2 (``--workers``).

It prints the time per voxel of each, the speed-up of N workers over 1, the peak
resident memory of every worker process (sampled every 0.2 s during the run: a spawned
worker's ``ru_maxrss`` also counts the parent's memory at the spawn, since Linux keeps
the high-water mark across ``exec``), and checks that every run gives the in-memory
surfaces (identical depths). Each cluster first detects a tiny cube (numba's cached
kernels are loaded once per worker process), which is not timed.

Usage::

    python benchmarks/bench_distributed.py                       # 256 x 256 x 1 x 600
    python benchmarks/bench_distributed.py --rows 128 --cols 128 --bins 400   # quick
    python benchmarks/bench_distributed.py --workers 1 2 4 --memory-limit 1GB
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_out_of_core import write_cube  # noqa: E402

import splidar  # noqa: E402


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 1e6


def _sampled_peaks(client, fn):
    """``fn()`` while every worker's resident memory is sampled every 0.2 s; returns
    ``(fn(), sampled peak per worker in MB)``."""
    import threading

    peaks, done = {}, threading.Event()

    def poll():
        while not done.is_set():
            for w, mb in client.run(_rss_mb).items():
                peaks[w] = max(peaks.get(w, 0.0), mb)
            done.wait(0.2)

    th = threading.Thread(target=poll)
    th.start()
    try:
        out = fn()
    finally:
        done.set()
        th.join()
    return out, sorted(peaks.values())


def _same(a, b) -> bool:
    return bool(
        np.array_equal(a.surfaces.row, b.surfaces.row)
        and np.array_equal(a.surfaces.col, b.surfaces.col)
        and np.array_equal(a.surfaces.depth_bin, b.surfaces.depth_bin)
    )


def _timed(cube, **kw):
    t0 = time.perf_counter()
    det = splidar.detect(cube, rng=0, **kw)
    return det, time.perf_counter() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=256)
    p.add_argument("--cols", type=int, default=256)
    p.add_argument("--bins", type=int, default=600)
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--memory-limit", default="1GB", help="per worker (default 1GB)")
    p.add_argument("--block-rows", type=int, default=None, help="rows per tile")
    args = p.parse_args(argv)
    import dask
    import distributed

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cube.zarr"
        write_cube(path, args.rows, args.cols, args.bins)
        lazy = splidar.load(path)
        n_vox = int(np.prod(lazy.shape))
        print(f"cube {lazy.shape}: {n_vox / 1e6:.1f} M voxels, {lazy.counts.nbytes / 1e6:.0f} MB")
        tiny = splidar.load(path)
        tiny = splidar.Cube(np.asarray(tiny.counts[:24, :24]), irf=tiny.irf)
        splidar.detect(tiny, rng=0)  # numba kernels loaded in this process
        mem = splidar.Cube(np.asarray(lazy.counts), irf=lazy.irf)
        ref, t_mem = _timed(mem, block_rows=args.block_rows)
        rows = [("memory", t_mem, True, "")]
        with dask.config.set(scheduler="threads"):
            det, t = _timed(lazy, block_rows=args.block_rows)
        rows.append(("threads", t, _same(ref, det), ""))
        t_one = None
        for n in args.workers:
            with (
                distributed.LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    memory_limit=args.memory_limit,
                    dashboard_address=":0",
                ) as cluster,
                distributed.Client(cluster) as client,
            ):
                splidar.detect(splidar.Cube(dask.array.from_array(tiny.counts), irf=tiny.irf))
                (det, t), sampled = _sampled_peaks(
                    client, lambda: _timed(lazy, block_rows=args.block_rows)
                )
            t_one = t if n == 1 else t_one
            speed = f"speed-up {t_one / t:.2f} (efficiency {t_one / t / n:.2f})" if t_one else ""
            peak = "worker RSS peak " + ", ".join(f"{m:.0f}" for m in sampled) + " MB"
            rows.append((f"cluster-{n}", t, _same(ref, det), f"{peak}; {speed}"))
    print(f"{'run':<11} {'s':>7} {'ns/voxel':>9} {'x memory':>8}  same  notes")
    for name, t, same, note in rows:
        print(f"{name:<11} {t:7.2f} {1e9 * t / n_vox:9.1f} {t / t_mem:8.2f}  {str(same):<5} {note}")
    print(f"memory limit per worker: {args.memory_limit}; the calling process gathers "
          "the (rows, cols, T) saliency and mask (store= keeps them on disk)")  # fmt: skip
    return 0 if all(r[2] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
