"""The calling process's share of ``detect`` with ``store=`` on a Dask cube, replayed.

Issue #16: on a cluster, the clean-up passes (stage 5), the selection (6) and the depth
alignment (7) run in the calling process while the workers wait. This script writes a
slab of ``bench_distributed.scene_rows`` (``--rows`` x 1024 x 1 x 1000) to Zarr, detects
it once with ``store=`` on a LocalCluster of one worker (1 GB), and saves what the
clean-up passes start from (the candidate table, the map, the stored arrays, the seed's
state); then it replays the passes and the selection on the saved state ``--reps``
times in this process (after one untimed run: numba's kernels and the page cache),
printing wall and CPU seconds (this process, all its threads) per replay and per pass,
and checking the surfaces against the first detection's. The state is kept in ``--dir``
for a replay by other code (e.g. another branch: ``--replay``), so two versions can be
alternated on the same input::

    python benchmarks/bench_caller_passes.py --dir /tmp/cp --rows 512          # detect + replay
    python benchmarks/bench_caller_passes.py --dir /tmp/cp --rows 512 --replay # replay only

The map pass takes a few minutes at 512 rows on a loaded 2-core machine; a replay ~10 s.
"""

from __future__ import annotations

import argparse
import contextlib
import copyreg
import pickle
import shutil
import sys
import time
import types
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_distributed import write_scene  # noqa: E402

import splidar  # noqa: E402
from splidar.detection import _detect, _slopes  # noqa: E402

# the state holds read-only mappings (options): pickled as the dicts they show
copyreg.pickle(types.MappingProxyType, lambda m: (dict, (dict(m),)))


def record(base: Path, rows: int) -> None:
    """Detect the slab with ``store=`` on one worker; save the clean-up passes' input."""
    import distributed

    path, store = base / "cube.zarr", base / "det.zarr"
    if not (path / "counts").exists():
        write_scene(path, rows, 1024, 1000)
    shutil.rmtree(store, ignore_errors=True)
    clean_up = _detect._clean_up

    def keep(cube, o, mp, held, hists, bg, corr, rng):
        shutil.rmtree(base / "candidate_histograms", ignore_errors=True)
        shutil.copytree(store / "candidate_histograms", base / "candidate_histograms")
        with open(base / "state.pkl", "wb") as f:
            state = dict(o=o, mp=mp, table=held[0], hists=hists, bg=bg, corr=corr, rng=rng)
            pickle.dump(state, f)
        return clean_up(cube, o, mp, held, hists, bg, corr, rng)

    _detect._clean_up = keep
    try:
        with (
            distributed.LocalCluster(
                n_workers=1, threads_per_worker=1, memory_limit="1GB", dashboard_address=":0"
            ) as cluster,
            distributed.Client(cluster),
        ):  # fmt: skip
            t0 = time.perf_counter()
            det = splidar.detect(splidar.load(path), rng=0, store=store)
    finally:
        _detect._clean_up = clean_up
    s = det.surfaces
    np.savez(base / "surfaces.npz", row=s.row, col=s.col, depth=s.depth_bin)
    print(f"detect {time.perf_counter() - t0:.1f} s, {len(s)} surfaces; state in {base}")


def replay(base: Path) -> tuple[float, float, bool, dict]:
    """The clean-up passes, the selection and the alignment on the saved state."""
    store = base / "det.zarr"
    st = pickle.load(open(base / "state.pkl", "rb"))
    for name in ("surface_histograms", "candidate_histograms"):
        shutil.rmtree(store / name, ignore_errors=True)
    shutil.copytree(base / "candidate_histograms", store / "candidate_histograms")
    cube = splidar.load(base / "cube.zarr")
    c0, t0 = time.process_time(), time.perf_counter()
    o, mp = st["o"], st["mp"]
    # as detect runs them: the Zarr cube's counts kept sparse for stages 5-7 (where the
    # code has it)
    kept = getattr(_slopes, "kept_counts", None)
    with kept(cube.counts) if kept else contextlib.nullcontext():
        hists = st["hists"]
        done = _detect._clean_up(cube, o, mp, [st["table"]], hists, st["bg"], st["corr"], st["rng"])
        t1 = time.perf_counter()
        surfaces, _, _, _ = _detect._select_and_align(
            cube, o, mp, [hists], done, t1, store, st["bg"]
        )
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ref = np.load(base / "surfaces.npz")
    same = all(
        np.array_equal(getattr(surfaces, k), ref[r])
        for k, r in (("row", "row"), ("col", "col"), ("depth_bin", "depth"))
    )
    secs = {p.name: p.seconds for p in done}
    secs["select+align"] = time.perf_counter() - t1
    return wall, cpu, same, secs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dir", required=True, help="folder for the slab and the saved state")
    p.add_argument("--rows", type=int, default=512)
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--replay", action="store_true", help="replay a saved state only")
    args = p.parse_args(argv)
    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    if not args.replay:
        record(base, args.rows)
    replay(base)  # untimed: numba's kernels loaded, the files in the page cache
    ok = True
    for _ in range(args.reps):
        wall, cpu, same, secs = replay(base)
        ok &= same
        parts = ", ".join(f"{k} {v:.2f}" for k, v in secs.items())
        print(f"replay {wall:.2f} s wall, {cpu:.2f} s CPU, same surfaces {same}: {parts}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
