"""Issue #15, point 5: where the missed true surfaces go (single surface, PPP 4, SBR 0.25).

For each true surface left unmatched within tau = 3 bins on the issue's cells
(``bench_false_surfaces.py``'s single-surface cubes, seeds as given), the class of the
map's candidate table in its pixel (recorded by wrapping ``detect``'s clean-up passes,
which return a new table each):

* ``no voxel``: no candidate near its depth, no voxel of the map ``M`` within +-1.5 bins;
* ``evidence``: no candidate, but voxels of ``M`` there (a run the evidence test dropped);
* ``run, kept`` / ``run, rejected``: a candidate whose run ``[start, stop)`` holds the
  true depth peaked more than tau away (kept, or rejected by the presence test);
* ``presence``: a candidate within tau, rejected by the presence test and never restored;
* ``removed by <pass>``: kept, then removed by that clean-up pass;
* ``align_depths``: kept to the end of stage 5, moved more than tau by stage 7;
* ``select``: kept to the end of stage 5, dropped by ``max_surfaces``.

Also per class: the pixel's expected signal photons, its counts within +-1.5 bins of the
true depth less the expected background, how many of its 4-neighbours hold a detected
surface within tau of its depth, and whether the pixel holds a (false) surface elsewhere.

Usage::

    python benchmarks/bench_missed_surfaces.py --seeds 0 1 2
    PYTHONPATH=/path/to/old/src python benchmarks/bench_missed_surfaces.py   # compare

Nothing is downloaded; everything is simulated.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_false_surfaces as bfs  # noqa: E402

from splidar.detection import _detect, detect  # noqa: E402
from splidar.metrics import match_points  # noqa: E402
from splidar.scenes import single_surface_scene  # noqa: E402

TAU = 3.0
_WRAPPED = (
    "recentre_runs", "remove_spill_over", "remove_isolated", "restore_dark_regions",
    "recover_slope_surfaces", "restore_enclosed_holes", "remove_stray_clusters",
)  # fmt: skip


class _Recorder:
    """Wraps the clean-up passes in ``_detect``'s namespace; records the first pass's
    input table (the map's) and each pass's keep flags, and stage 6's input."""

    def __init__(self):
        self.first, self.keeps, self.final, self.pre_align = None, [], None, None
        for name in _WRAPPED:
            if hasattr(_detect, name):
                setattr(_detect, name, self._wrap(name, getattr(_detect, name)))
        sel, align = _detect.select_surfaces, _detect.place_depths

        def select(table, *a, **k):
            self.final = table
            return sel(table, *a, **k)

        def aligned(surfaces, **k):
            self.pre_align = surfaces
            return align(surfaces, **k)

        _detect.select_surfaces, _detect.place_depths = select, aligned

    def _wrap(self, name, fn):
        def run(table, *a, **k):
            if self.first is None:
                self.first = table
            res = fn(table, *a, **k)
            self.keeps.append((name, np.asarray(res.table.keep).copy()))
            return res

        return run

    def reset(self):
        self.first, self.keeps, self.final, self.pre_align = None, [], None, None


def _class(rec, det, r, c, d) -> str:
    """The class of a missed true surface at pixel (r, c), depth d (module doc)."""
    t = rec.first.columns
    here = (np.asarray(t["row"]) == r) & (np.asarray(t["col"]) == c)
    depth = np.asarray(t["depth_bin"], np.float64)
    near = np.flatnonzero(here & (np.abs(depth - d) <= TAU))
    if near.size == 0:
        cover = here & (np.asarray(t["start"]) <= d) & (d < np.asarray(t["stop"]))
        if cover.any():
            return "run, kept" if rec.first.keep[cover].any() else "run, rejected"
        lo, hi = max(int(np.floor(d - 1.5)), 0), int(np.ceil(d + 1.5)) + 1
        return "evidence" if np.asarray(det.mask[r, c, lo:hi]).any() else "no voxel"
    kept = [(name, bool(k[near].any())) for name, k in rec.keeps]
    if not kept[-1][1]:
        if not rec.first.keep[near].any() and not any(h for _, h in kept):
            return "presence"
        prev, by = bool(rec.first.keep[near].any()), "?"
        for name, h in kept:
            if prev and not h:
                by = name
            prev = h
        return f"removed by {by}"
    s = rec.pre_align
    if s is not None:
        ok = (s.row == r) & (s.col == c) & (np.abs(s.depth_bin - d) <= TAU)
        return "align_depths" if ok.any() else "select"
    return "select"


def run_cell(rec, scene, bg, ppp, sbr, rng) -> list:
    sim = scene.simulate(ppp=ppp, sbr=sbr, background=bg, rng=rng)
    rec.reset()
    det = detect(sim.cube, rng=0)
    pts, truth = det.points, sim.truth
    R, C = truth.image_shape
    counts = np.asarray(sim.cube.counts, np.float64).sum(axis=2)
    lam_b = np.einsum("rcl,lt->rct", sim.background_spatial, sim.background_temporal)
    out = []
    for j in np.asarray(match_points(pts, truth, tau=TAU).unmatched_true, np.int64):
        r, c, d = int(truth.row[j]), int(truth.col[j]), float(truth.depth_bin[j])
        lo, hi = max(int(np.floor(d - 1.5)), 0), min(int(np.ceil(d + 1.5)) + 1, counts.shape[-1])
        n4 = 0
        for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            if 0 <= rr < R and 0 <= cc < C:
                k = (pts.row == rr) & (pts.col == cc) & (np.abs(pts.depth_bin - d) <= TAU)
                n4 += bool(k.any())
        out.append(
            dict(
                cls=_class(rec, det, r, c, d), signal=float(truth.intensity[j].sum()),
                excess=float(counts[r, c, lo:hi].sum() - lam_b[r, c, lo:hi].sum()), n4=n4,
                wrong=bool(((pts.row == r) & (pts.col == c)).any()),
            )
        )  # fmt: skip
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args(argv)
    rec = _Recorder()
    scene = single_surface_scene(bfs.SHAPE, n_bins=bfs.N_BINS)
    for i, cell in enumerate(bfs.SINGLE):
        rows = []
        for seed in args.seeds:
            got = run_cell(rec, scene, *cell, np.random.default_rng([seed, i]))
            print(f"seed {seed} {cell[0]}: {len(got)} missed", flush=True)
            rows += got
        n = len(args.seeds)
        print(f"{cell[0]}: {len(rows) / n:.1f} missed per cube (of 7,680)")
        by = collections.defaultdict(list)
        for x in rows:
            by[x["cls"]].append(x)
        print(f"  {'class':30s} per cube  signal  excess  wrong  4-nbrs at it (0..4)")
        for k, v in sorted(by.items(), key=lambda kv: -len(kv[1])):
            hist = np.bincount([x["n4"] for x in v], minlength=5).tolist()
            print(
                f"  {k:30s} {len(v) / n:8.1f}  {np.mean([x['signal'] for x in v]):6.2f}  "
                f"{np.mean([x['excess'] for x in v]):6.2f}  "
                f"{np.mean([x['wrong'] for x in v]):5.2f}  {hist}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
