"""The calling process's selection and depth alignment replayed with a cluster open.

Issue #16 (branch dist22b): ``bench_caller_passes.py``'s saved state (``--dir``, from
its first run) replayed with a LocalCluster of ``--workers`` workers (1 GB, 1 thread)
and a Client open, as in ``detect`` on a cluster: the clean-up passes, then the
selection and depth alignment (``_detect._select_and_align``), whose CPU seconds are
printed for the calling process and for the workers (psutil), with those of the
alignment's pixel reads (``_depth_fields._pixels``) in the calling process. The
surfaces are checked against the saved detection's. Two versions of the code can be
alternated on the same state (``PYTHONPATH=<other src>``)::

    python benchmarks/bench_caller_cluster.py --dir /tmp/cp --reps 2
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_caller_passes as bcp  # noqa: E402

from splidar.detection import _depth_fields, _detect  # noqa: E402


def main(argv=None) -> int:
    import distributed
    import psutil

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dir", required=True, help="bench_caller_passes.py's folder")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--reps", type=int, default=2)
    args = p.parse_args(argv)
    base = Path(args.dir)
    rec: dict = {}
    sel, pix = _detect._select_and_align, _depth_fields._pixels

    def timed(store, fn):
        def run(*a, **k):
            c = time.process_time()
            w = sum(sum(q.cpu_times()[:2]) for q in procs)
            out = fn(*a, **k)
            rec[store] = rec.get(store, 0.0) + time.process_time() - c
            rec[store + " workers"] = rec.get(store + " workers", 0.0) + (
                sum(sum(q.cpu_times()[:2]) for q in procs) - w
            )
            return out

        return run

    _detect._select_and_align = timed("select+align", sel)
    _depth_fields._pixels = timed("pixels", pix)
    with (
        distributed.LocalCluster(
            n_workers=args.workers, threads_per_worker=1, memory_limit="1GB",
            dashboard_address=":0",
        ) as cluster,
        distributed.Client(cluster) as client,
    ):  # fmt: skip
        procs = [psutil.Process(p) for p in client.run(os.getpid).values()]
        bcp.replay(base)  # untimed
        ok = True
        for _ in range(args.reps):
            rec.clear()
            wall, cpu, same, secs = bcp.replay(base)
            ok &= same
            parts = ", ".join(f"{k} {v:.2f}" for k, v in rec.items())
            print(f"replay {wall:.2f} s wall, {cpu:.2f} s CPU (caller), same {same}; CPU: {parts}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
