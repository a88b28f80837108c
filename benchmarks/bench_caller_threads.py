"""Where the calling process's CPU goes in ``bench_distributed.py --large``'s cluster run.

Issue #16 (branch dist23): the cluster run of ``bench_distributed.py --large --process
--workers 2 --cli-config`` alone (its ``_cluster_run``: a LocalCluster of 2 workers of
1 GB, the CLI's Dask settings, ``splidar.process`` with ``store=``), with

* the calling process's CPU seconds per thread, by Python thread name (``MainThread``;
  ``IO loop``: the scheduler, nannies and client hosted in this process; ``asyncio`` and
  ``zarr_io``: Zarr's decoding and copying; ``ThreadPoolExecutor``: the passes' threads
  and read-ahead; ``_poll`` / ``poll``: the benchmark's own samplers), read from
  ``/proc/self/task`` every 0.25 s (a thread's last reading counts);
* the main thread's CPU seconds per stage of ``detect`` (``thread_time``) beside the
  whole process's during that stage (``process_time``: every thread).

No in-memory run (``bench_distributed.py --large`` prints those)::

    python benchmarks/bench_caller_threads.py --data /tmp/b16   # its large.zarr (written if absent)

Linux only (``/proc``). Two versions of the code can be alternated with ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import collections
import functools
import os
import re
import shutil
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_distributed as bd  # noqa: E402

import splidar  # noqa: E402
from splidar import reconstruction  # noqa: E402
from splidar.detection import _detect  # noqa: E402

STEPS = (
    "_stuck_pixels_first", "estimate_temporal_background", "calibrate_null", "_map_pass",
    "recentre_runs", "remove_spill_over", "remove_isolated", "restore_dark_regions",
    "recover_slope_surfaces", "restore_enclosed_holes", "remove_stray_clusters",
    "select_surfaces", "place_depths",
)  # fmt: skip


class _Threads:
    """CPU seconds of this process's threads (by native id), sampled from /proc."""

    def __init__(self, dt: float = 0.25):
        self.tick, self.dt = os.sysconf("SC_CLK_TCK"), dt
        self.cpu: dict = {}
        self.name: dict = {}
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._poll, name="poll", daemon=True)

    def read(self) -> None:
        names = {t.native_id: t.name for t in threading.enumerate()}
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            t = int(tid)
            self.cpu[t] = max(self.cpu.get(t, 0.0), (int(fields[11]) + int(fields[12])) / self.tick)
            self.name.setdefault(t, names.get(t, "?"))

    def _poll(self):
        while not self.done.is_set():
            self.read()
            self.done.wait(self.dt)

    def by_name(self, since: dict) -> collections.Counter:
        out = collections.Counter()
        for t, c in self.cpu.items():
            out[re.sub(r"[-_]\d+(_\d+)?$", "", self.name.get(t, "?"))] += c - since.get(t, 0.0)
        return out


def _children_cpu() -> float:
    """CPU seconds of this process's child processes (the LocalCluster's workers)."""
    import psutil

    out = 0.0
    for c in psutil.Process().children(recursive=True):
        try:
            t = c.cpu_times()
            out += t.user + t.system
        except psutil.Error:
            pass
    return out


def _timed_steps(record: collections.Counter):
    """Wrap ``_detect``'s steps and ``reconstruction.reconstruct`` (for this measurement
    only) so that each adds its main-thread, process and workers' (the child processes')
    CPU seconds to ``record``."""

    def wrap(mod, name):
        fn = getattr(mod, name)

        @functools.wraps(fn)
        def timed(*a, **k):
            c, p, w = time.thread_time(), time.process_time(), _children_cpu()
            try:
                return fn(*a, **k)
            finally:
                record[name] += time.thread_time() - c
                record[name + " (process)"] += time.process_time() - p
                record[name + " (workers)"] += _children_cpu() - w

        setattr(mod, name, timed)

    for name in STEPS:
        wrap(_detect, name)
    wrap(reconstruction, "reconstruct")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="folder holding (or for) large.zarr")
    p.add_argument("--memory-limit", default="1GB")
    args = p.parse_args(argv)
    base = Path(args.data)
    base.mkdir(parents=True, exist_ok=True)
    path = base / "large.zarr"
    if not (path / "counts").exists():
        bd.write_scene(path, 3072, 1024, 1000)
    lazy = splidar.load(path)
    tiny = splidar.Cube(bd.scene_rows(0, 24, 24, lazy.shape[3]), irf=lazy.irf)
    splidar.process(tiny, rng=0)  # numba's kernels loaded in this process
    record: collections.Counter = collections.Counter()
    _timed_steps(record)
    store = base / "det-threads.zarr"
    shutil.rmtree(store, ignore_errors=True)
    threads = _Threads()
    threads.read()
    threads.thread.start()
    before = dict(threads.cpu)
    try:
        det, t, peaks, caller, restarted, cpu, cpus = bd._cluster_run(
            lazy, 2, args.memory_limit, store, tiny, None, True, True
        )
    finally:
        threads.done.set()
        threads.thread.join()
        threads.read()
        shutil.rmtree(store, ignore_errors=True)
    print(f"wall {t:.1f} s, CPU {cpu:.1f} s: " + ", ".join(f"{k} {v:.1f}" for k, v in cpus.items()))
    print(f"{len(det.surfaces)} surfaces; worker peaks {[round(x / 1e6) for x in peaks]} MB, "
          f"calling process {caller / 1e6:.0f} MB, {restarted} restarted; stages "
          f"{bd._stages(det)}")  # fmt: skip
    print("calling process, CPU seconds by thread (from the cluster's start):")
    for k, v in threads.by_name(before).most_common():
        print(f"  {v:7.1f}  {k}")
    print("main thread / whole process / workers' CPU seconds, by step:")
    for k in (*STEPS, "reconstruct"):
        w = record[k + " (workers)"]
        print(f"  {record[k]:7.2f} / {record[k + ' (process)']:7.2f} / {w:7.2f}  {k}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
