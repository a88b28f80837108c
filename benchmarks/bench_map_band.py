"""The map pass (stage 4) of a cluster's band tasks, replayed in one process.

On a ``dask.distributed`` cluster with ``store=``, ``detect`` runs stage 4 on a Zarr cube
as one task per band of tiles (``detection/_tiled._map_band``). This script runs the very
same band tasks in the calling process, one after the other (Dask's synchronous
scheduler; the worker's memory limit given, so the tiles have a worker's size), and
beside them the in-memory map pass on the same rows (``n_jobs=1``, with and without
``store=``), so that the map pass's own cost on a cluster (halo, Zarr reads of the
counts, the store's writes) is measured without Dask's, in CPU seconds of one thread::

    python benchmarks/bench_map_band.py --rows 256 --reps 2      # slab of the --large scene
    PYTHONPATH=<other src> python benchmarks/bench_map_band.py ...  # another version

The slab (the ``--large`` scene's first ``--rows`` rows, 32-row chunks) is written to
``--data`` once. Prints, per run: CPU of the map pass, of the whole ``detect``, the tile
shape, and checks that the surfaces are the same in all modes. ``--kernels`` adds, per
run, the task thread's CPU seconds per kernel of the map pass (matched filter, saliency,
threshold pass, segments, extraction, store writes, halo moves and copies) and the CPU
of the process's other threads (Zarr's pool and event loop) during the map pass, then a
table of the runs' minima per mode with the ratios band / memory ("halo39, session 27"
in ``benchmarks/README.md``).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_distributed import scene_rows, write_scene  # noqa: E402

import splidar  # noqa: E402
from splidar.detection import _2_saliency, _4_map, _detect, _filters, _tiled  # noqa: E402

#: Task-thread CPU seconds per kernel of the current map pass (``--kernels``).
KERNELS: dict = defaultdict(float)


def _timed(fn, label: str):
    def timed(*a, **k):
        t = time.thread_time()
        try:
            return fn(*a, **k)
        finally:
            KERNELS[label] += time.thread_time() - t

    return timed


def _time_kernels() -> None:
    """Wrap the map pass's kernels (both passes, both modules that call ``_block``)."""
    corr = _filters.Correlator.__call__
    _filters.Correlator.__call__ = _timed(corr, "matched filter")
    _2_saliency.saliency_wavelength = _timed(_2_saliency.saliency_wavelength, "saliency")
    for name, label in (
        ("threshold_pass", "threshold pass"),
        ("find_segments", "segments"),
        ("_extract", "extraction"),
        ("_put", "store writes (task thread)"),
        ("_move_rows", "halo rows moved"),
    ):
        setattr(_4_map, name, _timed(getattr(_4_map, name), label))
    for name, label in (
        ("_read_band", "band reads (task thread)"),
        ("_copy_into", "halo copied in"),
        ("_compact_result", "histograms stored"),
    ):
        setattr(_tiled, name, _timed(getattr(_tiled, name), label))
    _4_map._block = _tiled._block = _timed(_4_map._block, "_block (all above inside)")


def _thread_cpu() -> dict:
    """CPU seconds so far of each of this process's threads, by native id."""
    import psutil

    names = {t.native_id: t.name for t in threading.enumerate()}
    return {
        t.id: (t.user_time + t.system_time, names.get(t.id, "other"))
        for t in psutil.Process().threads()
    }


class _OneProcess:
    """Stands for a ``dask.distributed`` client in ``_tiled``: the band tasks run here."""

    def run(self, fn):
        return fn()


def _sync_each(tasks, take):
    import dask

    for i, r in enumerate(dask.compute(*tasks, scheduler="synchronous")):
        take(i, r)


def _timed_map(records: list):
    """Wrap ``_detect``'s two map passes so that their CPU seconds go to ``records``."""
    saved = {n: getattr(_detect, n) for n in ("map_candidates", "map_candidates_tiled")}

    def wrap(fn):
        def timed(*a, **k):
            KERNELS.clear()
            s0, th0 = _thread_cpu(), time.thread_time()
            c0, t0 = time.process_time(), time.perf_counter()
            out = fn(*a, **k)
            records.append((time.process_time() - c0, time.perf_counter() - t0))
            KERNELS["task thread, whole map pass"] = time.thread_time() - th0
            me = threading.get_native_id()
            for tid, (v, name) in _thread_cpu().items():
                if tid != me:  # Zarr's pool ("asyncio_N") and loop ("zarr_io"), others
                    label = "thread " + name.rstrip("0123456789_")
                    KERNELS[label] += v - s0.get(tid, (0.0, name))[0]
            return out

        return timed

    for n, fn in saved.items():
        setattr(_detect, n, wrap(fn))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=256)
    p.add_argument("--data", default="/tmp/bench_map_band")
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--memory-limit", type=float, default=1e9, help="bytes, the tiles' worker")
    p.add_argument("--modes", default="band,memory,memory-store")
    p.add_argument("--kernels", action="store_true", help="CPU per kernel and thread")
    args = p.parse_args()
    if args.kernels:
        _time_kernels()
    base = Path(args.data)
    base.mkdir(parents=True, exist_ok=True)
    path = base / f"slab{args.rows}.zarr"
    if not (path / "counts").exists():
        write_scene(path, args.rows, 1024, 1000)
    lazy = splidar.load(path)
    # the slab's own counts (written band by band, each band seeded by its first row)
    mem = splidar.Cube(np.asarray(lazy.counts), irf=lazy.irf)
    tiny = splidar.Cube(scene_rows(0, 24, 24, 1000), irf=lazy.irf)
    splidar.detect(tiny, rng=0)  # kernels loaded
    records: list = []
    _timed_map(records)
    _tiled._client = _OneProcess
    _tiled.compute_each = _sync_each
    _tiled.worker_memory_limit = lambda: int(args.memory_limit)
    digests, kernels = {}, defaultdict(list)
    for rep in range(args.reps):
        for mode in args.modes.split(","):
            store = base / "det.zarr"
            shutil.rmtree(store, ignore_errors=True)
            kw = {} if mode == "memory" else {"store": store}
            cube = lazy if mode == "band" else mem
            c0, t0 = time.process_time(), time.perf_counter()
            det = splidar.detect(cube, rng=0, n_jobs=1, **kw)
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            m_cpu, m_wall = records.pop()
            s = det.surfaces
            digests[mode] = (s.row.copy(), s.col.copy(), s.depth_bin.copy())
            print(
                f"rep {rep} {mode:<13} map pass CPU {m_cpu:6.2f} s (wall {m_wall:6.2f}); "
                f"detect CPU {cpu:6.2f} s (wall {wall:6.2f}); {len(s)} surfaces",
                flush=True,
            )
            print(
                "   stages (wall s): " + ", ".join(f"{k} {v:.2f}" for k, v in det.timings.items())
            )
            if args.kernels:
                kernels[mode].append(dict(KERNELS, **{"map pass, process": m_cpu}))
            del det
            shutil.rmtree(store, ignore_errors=True)
    if args.kernels:
        _kernel_table(kernels)
    a, *others = digests.values()
    same = all(all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)) for b in others)
    print(f"same surfaces in every mode: {same}")
    return 0 if same else 1


def _kernel_table(kernels: dict) -> None:
    """Markdown table: each mode's smallest CPU seconds per kernel over the repeats."""
    modes = list(kernels)
    labels = sorted({k for runs in kernels.values() for r in runs for k in r if r[k] > 0.005})
    best = {m: {k: min(r.get(k, 0.0) for r in kernels[m]) for k in labels} for m in modes}
    ratios = [m for m in modes if m != "memory"] if "memory" in modes else []
    print("| CPU s | " + " | ".join(modes) + "".join(f" | {m} / memory" for m in ratios) + " |")
    print("|---" * (1 + len(modes) + len(ratios)) + "|")
    for k in labels:
        row = " | ".join(f"{best[m][k]:.2f}" for m in modes)
        ref = best["memory"][k] if ratios else 0.0
        row += "".join(f" | {best[m][k] / ref:.2f}" if ref > 0.005 else " | -" for m in ratios)
        print(f"| {k} | {row} |")


if __name__ == "__main__":
    raise SystemExit(main())
