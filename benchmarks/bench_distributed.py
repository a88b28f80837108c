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

``--large`` measures the issue's figures at scale instead: a cube of a few GB
(:func:`scene_rows`, a coherent scene, PPP about 8, SBR about 1, written to Zarr band by
band, never whole in memory) detected with ``store=`` on LocalClusters of 1 and 2
workers limited to ``--memory-limit`` each, against the in-memory run (``n_jobs`` 1 and
2) on a slab of the same scene that fits (``--fit-rows`` rows; the median of
``--memory-repeat`` runs, 4 by default, half before the clusters and half after, is the
reference: the host's speed drifts between sittings; each half after ``--memory-warmup``
untimed runs of each arm, 1 by default: a group's first run faults its pages in
afresh). The resident memory of every worker process and of the calling process is
sampled with psutil every 0.1 s from
a thread of the calling process (by pid: the workers are not asked, so a busy worker is
sampled too); a worker restarted by its nanny (over 95 % of its limit) shows as a new pid.

Usage::

    python benchmarks/bench_distributed.py                       # 256 x 256 x 1 x 600
    python benchmarks/bench_distributed.py --rows 128 --cols 128 --bins 400   # quick
    python benchmarks/bench_distributed.py --workers 1 2 4 --memory-limit 1GB
    python benchmarks/bench_distributed.py --large               # 3072 x 1024 x 1 x 1000
    python benchmarks/bench_distributed.py --large --rows 512 --data /tmp/b16   # quicker
    python benchmarks/bench_distributed.py --caller              # 128 x 1024 x 1 x 1000

``--caller`` breaks the calling process's memory down instead: a slab of the large
scene detected with ``store=`` on a LocalCluster of one worker, the bytes per pixel
tracemalloc counts before, during (peak) and after each step of ``detect``, and the
process's sampled resident peak; then the reconstruction on strips of ``--strip-rows``
rows and the large task graphs Dask warned of.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_out_of_core import write_cube  # noqa: E402

import splidar  # noqa: E402


def scene_rows(r0: int, r1: int, cols: int, n_bins: int, *, seed: int = 0) -> np.ndarray:
    """Rows ``[r0, r1)`` of a large coherent scene, ``(r1 - r0, cols, 1, n_bins)`` uint8.

    A wavy ground with raised blocks (depth steps of ``0.12 T``), textured reflectivity,
    empty discs (no return), and a half-transparent net ``0.15 T`` in front on a
    checkerboard of 80-pixel squares (two surfaces per pixel there); 4 signal photons
    per surface at full reflectivity (half each under the net), 4 uniform background
    photons per pixel (PPP about 7, SBR about 1), a Gaussian IRF of FWHM 3 bins. The
    scene depends on the absolute row and column only and each band of rows is seeded by
    ``(seed, r0)``, so a slab ``[0, n)`` is the top of the larger cube's scene.
    """
    rng = np.random.default_rng([seed, r0])
    rr, cc = np.mgrid[r0:r1, 0:cols].astype(np.float64)
    wave = np.sin(2 * np.pi * rr / 700) * np.cos(2 * np.pi * cc / 900)
    far = n_bins * (0.40 + 0.12 * wave + 0.1 * np.sin(2 * np.pi * cc / 1500))
    blocks = ((rr // 96).astype(int) * 7 + (cc // 128).astype(int) * 3) % 5 == 0
    far += 0.12 * n_bins * blocks
    refl = 0.6 + 0.4 * np.cos(2 * np.pi * rr / 37) * np.sin(2 * np.pi * cc / 53)
    refl[((rr % 512) - 256) ** 2 + ((cc % 640) - 320) ** 2 < 90**2] = 0.0
    net = ((rr // 80) + (cc // 80)) % 4 == 1
    near, sigma = far - 0.15 * n_bins, 3.0 / 2.3548
    out = np.empty((r1 - r0, cols, 1, n_bins), np.uint8)
    pix = np.arange(cols)
    for i in range(r1 - r0):  # photons binned row by row (integer counts)
        k = rng.poisson(4.0, cols)
        parts = [np.repeat(pix, k) * n_bins + rng.integers(0, n_bins, k.sum())]
        for depth, amp in (
            (far[i], 4.0 * refl[i] * np.where(net[i], 0.5, 1.0)),
            (near[i], np.where(net[i], 2.0, 0.0)),
        ):
            k = rng.poisson(amp)
            t = np.rint(np.repeat(depth, k) + rng.normal(0.0, sigma, k.sum())).astype(np.int64)
            p, ok = np.repeat(pix, k), (t >= 0) & (t < n_bins)
            parts.append(p[ok] * n_bins + t[ok])
        h = np.bincount(np.concatenate(parts), minlength=cols * n_bins)
        out[i, :, 0, :] = np.minimum(h, 255).reshape(cols, n_bins)
    return out


def write_scene(path: Path, rows: int, cols: int, n_bins: int, *, chunk_rows: int = 32):
    """:func:`scene_rows` written to a Zarr cube band by band (one band in memory at a time)."""
    import zarr

    from splidar.irf import gaussian_irf

    first = scene_rows(0, min(rows, chunk_rows), cols, n_bins)
    splidar.save(splidar.Cube(first, irf=gaussian_irf(3.0)), path, chunks=(chunk_rows, cols))
    z = zarr.open_group(str(path), mode="r+")["counts"]
    z.resize((rows, cols, 1, n_bins))
    for r0 in range(first.shape[0], rows, chunk_rows):
        r1 = min(rows, r0 + chunk_rows)
        z[r0:r1] = scene_rows(r0, r1, cols, n_bins)


class _Sampler:
    """Peak resident memory of some processes, sampled by pid every ``dt`` seconds."""

    def __init__(self, pids: dict, dt: float = 0.1):
        import threading

        import psutil

        self.procs = {k: psutil.Process(p) for k, p in pids.items()}
        self.peaks = {k: 0 for k in pids}
        self.done, self.dt = threading.Event(), dt
        self.thread = threading.Thread(target=self._poll, daemon=True)

    def _poll(self):
        while not self.done.is_set():
            for k, pr in self.procs.items():
                try:
                    self.peaks[k] = max(self.peaks[k], pr.memory_info().rss)
                except Exception:  # a worker killed by its nanny: its last sample stays
                    pass
            self.done.wait(self.dt)

    def _cpus(self) -> dict:
        out = {}
        for k, pr in self.procs.items():
            try:
                t = pr.cpu_times()
                out[k] = t.user + t.system
            except Exception:
                out[k] = 0.0
        return out

    def __enter__(self):
        self.cpu0 = self._cpus()
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.done.set()
        self.thread.join()
        now = self._cpus()
        #: CPU seconds of each sampled process during the run, and of them all
        self.cpus = {k: now[k] - self.cpu0[k] for k in now}
        self.cpu = sum(self.cpus.values())


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


@dataclasses.dataclass(frozen=True)
class _Digest:
    row: np.ndarray
    col: np.ndarray
    depth_bin: np.ndarray

    @property
    def surfaces(self):
        return self


def _same(a, b) -> bool:
    return bool(
        np.array_equal(a.surfaces.row, b.surfaces.row)
        and np.array_equal(a.surfaces.col, b.surfaces.col)
        and np.array_equal(a.surfaces.depth_bin, b.surfaces.depth_bin)
    )


def _timed(cube, process=False, **kw):
    """``detect`` (or, ``process=True``, ``splidar.process``, its Detection carrying the
    reconstruction's time) of ``cube``: ``(Detection, seconds)``."""
    t0 = time.perf_counter()
    if not process:
        det = splidar.detect(cube, rng=0, **kw)
        return det, time.perf_counter() - t0
    rec = splidar.process(cube, rng=0, **kw)
    t = time.perf_counter() - t0
    timings = {**rec.detection.timings, "reconstruct": rec.timings["reconstruct"]}
    return dataclasses.replace(rec.detection, timings=timings), t


def _warm_process(tiny) -> None:
    """Load ``splidar.process``'s compiled kernels in this process (a worker's)."""
    splidar.process(tiny, rng=0)


def _cluster_run(
    cube, n: int, memory_limit: str, store: Path, tiny, block_rows=None, process=False,
    cli_config=False,
):  # fmt: skip
    """Detection of ``cube`` on a fresh LocalCluster of ``n`` workers: ``(Detection,
    seconds, worker peaks in bytes, calling process's peak in bytes, restarted workers,
    CPU seconds of the workers and the calling process)``."""
    import contextlib
    import os

    import dask
    import dask.array
    import distributed

    config = contextlib.nullcontext()
    if cli_config:  # the Dask settings of the CLI's --workers cluster
        from splidar._cluster import CLUSTER_CONFIG

        config = dask.config.set(CLUSTER_CONFIG)
    with (
        config,
        distributed.LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=":0",
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        # numba's cached kernels loaded once per worker process (not timed): the map
        # pass's through a Dask cube; with --process also the reconstruction's, in each
        # worker, as the in-memory run has them loaded in the calling process
        splidar.detect(splidar.Cube(dask.array.from_array(tiny.counts), irf=tiny.irf))
        if process:
            client.run(_warm_process, tiny)
        pids = client.run(os.getpid)
        pids["caller"] = os.getpid()
        print(f"cluster-{n}: calling process at {_rss_mb():.0f} MB before the run", flush=True)
        with _Sampler(pids) as s:
            # process: detection and reconstruction (on strips for a Dask cube)
            det, t = _timed(cube, process, store=store, block_rows=block_rows)
        restarted = sum(1 for w, p in client.run(os.getpid).items() if pids.get(w) != p) + max(
            0, n - len(client.scheduler_info()["workers"])
        )
    caller = s.peaks.pop("caller")
    return det, t, sorted(s.peaks.values()), caller, restarted, s.cpu, s.cpus


def large(args) -> int:
    """The issue's figures: a cube several times a worker's memory limit (see the module)."""
    import os
    import shutil

    R, C, T = args.rows, args.cols, args.bins
    base = Path(args.data or tempfile.mkdtemp(prefix="bench16-"))
    base.mkdir(parents=True, exist_ok=True)
    path = base / "large.zarr"
    try:
        t0 = time.perf_counter()
        if not (path / "counts").exists() or splidar.load(path).shape != (R, C, 1, T):
            write_scene(path, R, C, T)
        lazy = splidar.load(path)
        n_vox = R * C * T
        print(
            f"cube {lazy.shape} uint8: {n_vox / 1e9:.2f} G voxels, {n_vox / 1e9:.2f} GB in "
            f"memory, {_du(path) / 1e9:.2f} GB on disk (Zarr, compressed); "
            f"{time.perf_counter() - t0:.0f} s to write"
        )
        tiny = splidar.Cube(scene_rows(0, 24, 24, T), irf=lazy.irf)
        # numba kernels loaded in this process (the in-memory runs' too)
        (splidar.process if args.process else splidar.detect)(tiny, rng=0)
        rows, dets = [], {}
        fit, mstore = args.fit_rows, base / "det-memory.zarr"
        arms = [
            (f"memory-{n}" + ("-store" if st else ""), n, {"store": mstore} if st else {})
            for n in sorted(set(args.workers))
            for st in (False, True)
        ]  # fmt: skip
        runs = {name: ([], []) for name, _, _ in arms}

        def memory_runs(k: int) -> None:
            """``k`` in-memory runs of each arm on the slab (built here and dropped after:
            not held during the cluster runs, whose calling-process peak is measured)."""
            if k <= 0:
                return
            mem = splidar.Cube(scene_rows(0, fit, C, T), irf=lazy.irf)
            for name, n, kw in arms:
                for i in range(k + args.memory_warmup):
                    shutil.rmtree(base / "det-memory.zarr", ignore_errors=True)
                    with _Sampler({"caller": os.getpid()}) as s:
                        # like for like: --process times splidar.process in memory too
                        det, t = _timed(mem, args.process, n_jobs=n, **kw)
                    if i < args.memory_warmup:
                        # untimed: the first run of a group faults its pages in afresh
                        # (3.8-5.5 s against 3.5-4.0 s for the next on issue #16's slab)
                        print(f"{name}: {t:.1f} s ({s.cpu:.1f} s CPU), warm-up, not counted")
                        del det
                        continue
                    runs[name][0].append(t)
                    runs[name][1].append(s.cpu)
                    print(f"{name}: {t:.1f} s ({s.cpu:.1f} s CPU), stages " + _stages(det),
                          flush=True)  # fmt: skip
                    del det
            shutil.rmtree(base / "det-memory.zarr", ignore_errors=True)

        memory_runs((args.memory_repeat + 1) // 2)
        for n in args.workers:
            store = base / f"det-{n}.zarr"
            shutil.rmtree(store, ignore_errors=True)
            det, t, peaks, caller, restarted, cpu, cpus = _cluster_run(
                lazy, n, args.memory_limit, store, tiny, args.block_rows, args.process,
                args.cli_config,
            )  # fmt: skip
            # the surfaces only: a Detection kept here would count in the next run's
            # calling-process peak
            dets[n] = _Digest(det.surfaces.row, det.surfaces.col, det.surfaces.depth_bin)
            print(f"cluster-{n}: {t:.1f} s ({cpu:.1f} s CPU: caller {cpus['caller']:.1f}), "
                  "stages " + _stages(det), flush=True)  # fmt: skip
            del det
            name = f"cluster-{n}" + ("-process" if args.process else "")
            rows.append((name, n, t, n_vox, peaks, caller, restarted, cpu))
            shutil.rmtree(store, ignore_errors=True)
        memory_runs(args.memory_repeat // 2)
        for name, n, _ in arms:
            walls, cpus_ = runs[name]
            # the reference: the median of the repeats, half of them run before the
            # clusters and half after (one 8-10 s run moves by +-13 % on a quiet machine
            # and the host's speed drifts between sittings; the cluster run, 15x longer,
            # moves +-2 % within one)
            t, cpu = float(np.median(walls)), float(np.median(cpus_))
            if len(walls) > 1:
                print(f"{name}: median of {len(walls)}: {t:.1f} s ({cpu:.1f} s CPU)")
            rows.append((name, n, t, fit * C * T, None, None, 0, cpu))
    finally:
        if args.data is None:
            shutil.rmtree(base, ignore_errors=True)
    ns_of = {r[0]: 1e9 * r[2] / r[3] for r in rows}
    cpu_of = {r[0]: 1e9 * r[7] / r[3] for r in rows}
    t_one = next((r[2] for r in rows if r[0].startswith("cluster-1")), None)
    lim = _bytes(args.memory_limit)
    print(
        f"\nin-memory slab: {fit} x {C} x 1 x {T}; x memory: time per voxel against the "
        "in-memory run with as many threads (n_jobs) as workers, without / with store="
    )
    print(
        f"{'run':<15} {'s':>7} {'ns/voxel':>9} {'x memory':>13} {'CPU ns/vox':>10} "
        f"{'CPU x mem':>11} {'speed-up':>8} {'eff.':>5}"
        f"  worker peak MB (limit {lim / 1e6:.0f})  caller peak MB  restarts"
    )
    ok_mem, ok_store, ok_limit = True, True, True
    for name, n, t, nv, peaks, caller, restarted, cpu in rows:
        ns, cns = 1e9 * t / nv, 1e9 * cpu / nv
        x, xs = ns / ns_of[f"memory-{n}"], ns / ns_of[f"memory-{n}-store"]
        cx, cxs = cns / cpu_of[f"memory-{n}"], cns / cpu_of[f"memory-{n}-store"]
        line = f"{name:<15} {t:7.1f} {ns:9.1f} {x:6.2f} / {xs:4.2f} {cns:10.1f} "
        line += f"{cx:4.2f} / {cxs:4.2f}"
        if peaks is not None:
            sp = t_one / t if t_one else float("nan")
            line += f" {sp:8.2f} {sp / n:5.2f}  " + ", ".join(f"{p / 1e6:.0f}" for p in peaks)
            line += f"   {caller / 1e6:.0f}   {restarted}"
            ok_limit &= max(peaks) < lim and restarted == 0
            ok_mem &= x <= 1.3
            ok_store &= xs <= 1.3
        print(line)
    ok = ok_limit
    if len(dets) > 1:
        a, *others = dets.values()
        same = all(_same(a, b) for b in others)
        print(f"same surfaces whatever the number of workers: {same}")
        ok &= same
    print(f"every worker under its limit, none restarted: {ok_limit}")
    print(f"time per voxel <= 1.3 x in memory: {ok_mem}; with store=: {ok_store}")
    return 0 if ok else 1


#: The steps of ``detect`` whose memory ``--caller`` reports (functions of its module).
_CALLER_STEPS = (
    "map_candidates_tiled", "remove_spill_over", "remove_isolated", "restore_dark_regions",
    "recover_slope_surfaces", "restore_enclosed_holes", "select_surfaces",
    "place_depths", "_detection",
)  # fmt: skip


class _RssPeak:
    """This process's resident memory sampled every ``dt`` s: the peak since ``reset()``."""

    def __init__(self, dt: float = 0.02):
        import threading

        import psutil

        self.proc, self.dt, self.peak = psutil.Process(), dt, 0
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def _poll(self):
        while not self.done.is_set():
            self.peak = max(self.peak, self.proc.memory_info().rss)
            self.done.wait(self.dt)

    def reset(self) -> int:
        self.peak = rss = self.proc.memory_info().rss
        return rss

    def close(self):
        self.done.set()
        self.thread.join()


def _traced_steps(module, names, records: list, rss: _RssPeak):
    """Wrap ``module``'s functions ``names`` (for the measurement only) so that each call
    appends ``(name, traced bytes before, peak during, after, resident bytes before, peak
    during)`` to ``records`` while tracemalloc traces. Returns a function that restores
    them."""
    import functools
    import tracemalloc

    saved = {n: getattr(module, n) for n in names}

    def wrap(name, fn):
        @functools.wraps(fn)
        def traced(*args, **kw):
            if not tracemalloc.is_tracing():
                return fn(*args, **kw)
            before, rss0 = tracemalloc.get_traced_memory()[0], rss.reset()
            tracemalloc.reset_peak()
            out = fn(*args, **kw)
            now, peak = tracemalloc.get_traced_memory()
            records.append((name, before, peak, now, rss0, max(rss.peak, rss.reset())))
            return out

        return traced

    for n, fn in saved.items():
        setattr(module, n, wrap(n, fn))
    return lambda: [setattr(module, n, fn) for n, fn in saved.items()]


def caller(args) -> int:
    """The calling process's memory when a Dask cube is detected with ``store=`` on a
    LocalCluster of one worker (``--caller``), step by step, per pixel; then the
    reconstruction on strips of ``--strip-rows`` rows, with the task graphs Dask warned
    of (over its 10 MB threshold)."""
    import os
    import shutil
    import tracemalloc
    import warnings

    import dask.array
    import distributed

    from splidar.detection import _detect
    from splidar.reconstruction._tiled import reconstruct_tiled

    R, C, T = args.rows, args.cols, args.bins
    base = Path(args.data or tempfile.mkdtemp(prefix="bench16c-"))
    base.mkdir(parents=True, exist_ok=True)
    path, store = base / f"slab-{R}x{C}x{T}.zarr", base / "det.zarr"
    from splidar.reconstruction import _tiled as rec_tiled

    records: list = []
    rss = _RssPeak()
    restore = _traced_steps(_detect, _CALLER_STEPS, records, rss)
    restore_rec = _traced_steps(rec_tiled, ("_on_strips",), records, rss)
    try:
        if not (path / "counts").exists():
            write_scene(path, R, C, T)
        lazy = splidar.load(path)
        tiny = splidar.Cube(scene_rows(0, 24, 24, T), irf=lazy.irf)
        splidar.detect(tiny, rng=0)  # numba kernels loaded in this process
        shutil.rmtree(store, ignore_errors=True)
        with (
            distributed.LocalCluster(
                n_workers=1, threads_per_worker=1, processes=True,
                memory_limit=args.memory_limit, dashboard_address=":0",
            ) as cluster,
            distributed.Client(cluster),
        ):  # fmt: skip
            splidar.detect(splidar.Cube(dask.array.from_array(tiny.counts), irf=tiny.irf))
            rss0 = _rss_mb() * 1e6
            with _Sampler({"caller": os.getpid()}, dt=0.05) as s:
                tracemalloc.start()
                t0 = time.perf_counter()
                det = splidar.detect(lazy, rng=0, store=store)
                t_det = time.perf_counter() - t0
                held = tracemalloc.get_traced_memory()[0]
                tracemalloc.stop()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                tracemalloc.start()
                t0 = time.perf_counter()
                rec = reconstruct_tiled(det, strip_rows=args.strip_rows, rng=0)
                t_rec = time.perf_counter() - t0
                tracemalloc.stop()
        graphs = [str(w.message).splitlines()[0] for w in caught if "large graph" in str(w.message)]
    finally:
        restore(), restore_rec(), rss.close()
        shutil.rmtree(store, ignore_errors=True)
        if args.data is None:
            shutil.rmtree(base, ignore_errors=True)
    npix, S = R * C, len(det.surfaces)
    print(
        f"slab {R} x {C} x 1 x {T}: {S} surfaces ({S / npix:.2f} per pixel); detect {t_det:.1f} s"
    )
    print(f"calling process RSS: {rss0 / 1e6:.0f} MB before, peak {s.peaks['caller'] / 1e6:.0f} MB "
          f"({(s.peaks['caller'] - rss0) / npix:.0f} B/pixel above the start)")  # fmt: skip
    print(f"bytes per pixel, step by step: traced by tracemalloc (held before the step, peak "
          f"during it, held after), and the process's resident peak during it above the "
          f"start; {held / npix:.0f} traced held at the end of detect")  # fmt: skip
    print(f"{'step':<24} {'held before':>11} {'peak':>6} {'held after':>10} {'RSS peak':>9}")
    for name, before, peak, now, _, rss_peak in records:
        line = f"{name:<24} {before / npix:11.0f} {peak / npix:6.0f} {now / npix:10.0f}"
        print(line + f" {(rss_peak - rss0) / npix:9.0f}")
    print(f"reconstruction on strips of {args.strip_rows} rows: {t_rec:.1f} s, "
          f"{len(rec.points)} points; large task graphs: {graphs or 'none'}")  # fmt: skip
    return 0


def _stages(det) -> str:
    keep = ("background_temporal", "null", "saliency_and_surfaces", "quality_and_selection")
    keep += ("reconstruct",)
    out = ", ".join(f"{k} {det.timings[k]:.1f}" for k in keep if k in det.timings)
    # the clean-up passes, the selection and the depth alignment, each
    passes = [(r.stage, r.seconds) for r in det.provenance if r.stage != "map" and r.ran]
    return out + " (" + ", ".join(f"{k} {s:.1f}" for k, s in passes) + ")"


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def _bytes(s: str) -> int:
    from dask.utils import parse_bytes

    return int(parse_bytes(s))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=256)
    p.add_argument("--cols", type=int, default=256)
    p.add_argument("--bins", type=int, default=600)
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--memory-limit", default="1GB", help="per worker (default 1GB)")
    p.add_argument("--block-rows", type=int, default=None, help="rows per tile")
    p.add_argument("--large", action="store_true", help="the issue's figures at scale")
    p.add_argument("--fit-rows", type=int, default=256, help="--large: in-memory slab rows")
    p.add_argument(
        "--memory-repeat", type=int, default=4,
        help="--large: in-memory runs per arm, half before the clusters and half after; "
        "their median the reference (default 4)",
    )  # fmt: skip
    p.add_argument(
        "--memory-warmup", type=int, default=1,
        help="--large: untimed in-memory runs of each arm before each half (default 1)",
    )  # fmt: skip
    p.add_argument("--data", default=None, help="--large: folder for the cube (kept)")
    p.add_argument(
        "--process", action="store_true", help="--large: splidar.process on the clusters"
    )
    p.add_argument(
        "--cli-config",
        action="store_true",
        help="--large: the clusters with the Dask settings of `splidar run --workers` "
        "(splidar._cluster.CLUSTER_CONFIG: profiler off, slower ticks); default: Dask's own",
    )
    p.add_argument(
        "--caller", action="store_true", help="the calling process's memory, step by step"
    )
    p.add_argument("--strip-rows", type=int, default=32, help="--caller: reconstruction strips")
    args = p.parse_args(argv)
    if args.caller:
        for k, v in (("rows", 128), ("cols", 1024), ("bins", 1000)):
            if f"--{k}" not in (argv if argv is not None else sys.argv):
                setattr(args, k, v)
        return caller(args)
    if args.large:
        for k, v in (("rows", 3072), ("cols", 1024), ("bins", 1000)):
            if f"--{k}" not in (argv if argv is not None else sys.argv):
                setattr(args, k, v)
        return large(args)
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
