"""Peak memory of ``detect`` on a long-IRF cube, and the equality of two sources' results.

Issue #15, point 6: peak memory above the input <= 2 float32 cubes. A long IRF (FWHM of
many bins, a long tail) makes the candidates' window W wide, and the map pass held every
candidate's clean histograms at every scale over the whole window: on the face file at its
native bin (T = 7,001, W = 681) 2.7 float32 cubes above the input
(``benchmarks/README.md``, "Lead, session 22").

Each measurement runs in a fresh subprocess (``python -c``) with the ``src`` directory
given (so one sitting can alternate two versions of the library): the cube is built or
loaded, the RSS high-water mark reset (``/proc/self/clear_refs``, else a sampling
thread), ``splidar.detect(cube, rng=0)`` run once, and the peak RSS above the RSS before
the call reported in float32 cubes (``R x C x L x T x 4`` bytes), with the wall time.
The child also writes a SHA-1 of every array of the :class:`Detection` (surfaces' fields,
saliency, mask, background, threshold factors, ...) so that two sources' results can be
compared bit for bit without holding both.

Cases:

* ``sim``: a simulated single-surface scene (``single_surface_scene``) with an
  exponential-tail IRF (Gaussian FWHM 15 bins, tail 40 bins) over T = 3,000 bins,
  160 x 160 pixels, 8 photons per pixel, SBR 1: W = 569 bins, about as wide as the
  face's; about 30 s. Each source first runs a 16 x 16 cube once (``warm``: numba's
  caches of a freshly unpacked source are compiled there, not in the timed call).
* ``face``: ``splidar.load`` of ``face/data_face.mat`` as ``splidar run`` reads it (bin
  indices, T = 7,001): about 2 min and 11 GB on main (run one at a time, ``nice``).

Usage::

    python benchmarks/bench_memory_long_irf.py --src /tmp/main/src --src src --case sim
    python benchmarks/bench_memory_long_irf.py --src /tmp/main/src --src src --case face \\
        --data /work/wt/shared/data --rounds 1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

_CHILD = r"""
import dataclasses, gc, hashlib, json, sys, time
import numpy as np
sys.path.insert(0, {bench!r})
from _measure import measure_memory
import splidar

case, data, out = {case!r}, {data!r}, {out!r}
if case == "face":
    cube = splidar.load(data + "/face/data_face.mat")
else:
    from splidar.scenes import single_surface_scene
    n = 16 if case == "warm" else 160
    scene = single_surface_scene(
        (n, n), n_bins=3000, irf=("exp_tail", 15.0, 40.0), photons=8.0
    )
    cube = scene.simulate(ppp=8.0, sbr=1.0, rng=0).cube
gc.collect()
R, C, L, T = cube.shape
f32 = R * C * L * T * 4
t0 = time.perf_counter()
m = measure_memory(lambda: splidar.detect(cube, rng=0), keep_result=True)
wall = time.perf_counter() - t0
d = m.result


def digest(x, name, acc):
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        for f in dataclasses.fields(x):
            if f.name not in ("timings", "seconds"):
                digest(getattr(x, f.name), name + "." + f.name, acc)
        return
    if isinstance(x, (tuple, list)) and x and dataclasses.is_dataclass(x[0]):
        for i, v in enumerate(x):
            digest(v, name + "[%d]" % i, acc)
        return
    if hasattr(x, "spatial") and hasattr(x, "dev") and not isinstance(x, np.ndarray):
        for k in ("spatial", "dev", "xs", "ys"):
            if hasattr(x, k):
                digest(getattr(x, k), name + "." + k, acc)
        return
    try:
        a = np.asarray(x)
    except Exception:
        acc[name] = repr(x)
        return
    if a.dtype == object:
        acc[name] = repr(x)[:200]
        return
    h = hashlib.sha1()
    h.update(str((a.shape, a.dtype.str)).encode())
    if a.size:
        flat = np.ascontiguousarray(a).reshape(-1).view(np.uint8)
        for i in range(0, flat.size, 1 << 28):
            h.update(flat[i : i + (1 << 28)])
    acc[name] = h.hexdigest()


acc = {{}}
if out:
    digest(d, "detection", acc)
fig = dict(
    src=splidar.__file__, shape=[R, C, L, T], f32_bytes=f32, wall=wall,
    rss=m.rss, rss_cubes=m.rss / f32, method=m.rss_method,
    surfaces=len(d.surfaces), width=int(d.surfaces.histograms.shape[-1]),
)
if out:
    with open(out, "w") as fh:
        json.dump(dict(fig=fig, digest=acc), fh)
print(json.dumps(fig))
"""


def run_child(src: str, case: str, data: str, out: str = "") -> dict:
    """One measurement in a fresh process with ``src`` first on ``sys.path``."""
    bench = os.path.dirname(os.path.abspath(__file__))
    code = _CHILD.format(bench=bench, case=case, data=data, out=out)
    env = dict(os.environ, PYTHONPATH=os.path.abspath(src))
    res = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False
    )
    if res.returncode:
        raise RuntimeError(f"child failed ({src}):\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def compare(a: str, b: str) -> list[str]:
    """Names of the Detection's arrays whose digests differ between two child outputs."""
    with open(a) as fa, open(b) as fb:
        da, db = json.load(fa)["digest"], json.load(fb)["digest"]
    keys = sorted(set(da) | set(db))
    return [k for k in keys if da.get(k) != db.get(k)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--src", action="append", required=True, help="a src directory (1 or 2)")
    p.add_argument("--case", choices=("sim", "face"), default="sim")
    p.add_argument("--data", default="../shared/data", help="folder holding face/")
    p.add_argument("--rounds", type=int, default=2, help="alternated rounds")
    args = p.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix="bench_memory_")
    outs = {}
    for src in args.src:
        run_child(src, "warm", args.data)
    for r in range(args.rounds):
        for i, src in enumerate(args.src):
            out = os.path.join(tmp, f"{i}.json") if r == 0 else ""
            fig = run_child(src, args.case, args.data, out)
            if out:
                outs[i] = out
            print(
                f"round {r} src {i} ({src}): {fig['shape']} W {fig['width']}, "
                f"{fig['surfaces']} surfaces, detect {fig['wall']:.1f} s, peak RSS above "
                f"the input {fig['rss'] / 2**30:.2f} GiB = {fig['rss_cubes']:.2f} float32 "
                f"cubes ({fig['method']})",
                flush=True,
            )
    if len(outs) == 2:
        diff = compare(outs[0], outs[1])
        n = len(json.load(open(outs[0]))["digest"])
        print(f"equality: {n} arrays compared, {len(diff)} differ" + (f": {diff}" if diff else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
