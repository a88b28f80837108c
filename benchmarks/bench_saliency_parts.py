"""Where the saliency kernel's time goes, part by part (issue 15 point 6, sal28, session 20).

Times :func:`splidar.detection._fast.saliency_wavelength` on the first block of
``bench_speed.main_cube()`` (captured during ``detect(n_jobs=1)``, as in
``bench_saliency_counts.py``), and its parts run on their own by small drivers over the
kernel's own numba functions: the filter (``_filter_row``: nested row pass plus the
column pass's float64 running sums, with and without the box means stored for the
extraction), the row pass alone (``_filter_row``'s source cut before the column pass),
the per-pixel level (``_level_pixel``) and ``_bhat_saliency``. Also the measured,
not adopted variant: the column pass's running sums in float32 instead of float64
(values moved, reported). Thread CPU, ns per voxel and wavelength, best of ``--rounds``.

Usage::

    python benchmarks/bench_saliency_parts.py --rounds 5
"""

# ruff: noqa: B023  (each lambda is called within its own iteration of the loop)
from __future__ import annotations

import argparse
import inspect
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

from splidar.detection import _fast

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_saliency_counts  # noqa: E402

_COL = "        # pass along columns"
_F64 = "ac[t] += np.float64(np.float32(va[t] * inv32)) - np.float64("
_F32 = "ac[t] += np.float32(np.float32(va[t] * inv32)) - np.float32("


def _variant(name: str, row_only: bool):
    """``_filter_row`` recompiled from its source: the row pass only, or float32 sums."""
    src = inspect.getsource(_fast._filter_row.py_func).split("\n", 1)[1]
    if row_only:
        src = src[: src.index(_COL)]
    else:
        assert src.count(_F64) == 1
        src = src.replace(_F64, _F32)
    src = src.replace("def _filter_row(", f"def {name}(")
    ns = {"np": np, "_refl": _fast._refl}
    exec(src, ns)  # noqa: S102 (the kernel's own source, cut or edited above)
    return njit(nogil=True)(ns[name])


def _driver(fr):
    """All strips and kept rows of one wavelength through the filter ``fr``."""

    @njit(nogil=True)
    def drv(cf, R, C, T, sr, sc, i0, i1, scales, weights, dev, M, CO, box, bidx, acc):
        Q = scales.size
        tile = acc.size
        V = np.empty((Q, C, tile), np.float32)
        carry = np.empty((i1 - i0, Q, T), np.float64)
        for s0 in range(0, C, 32):
            s1 = min(C, s0 + 32)
            for i in range(i0, i1):
                o = i - i0
                fr(
                    cf, 0, R, C, T, sr, sc, i, s0, s1, scales, weights, dev, True, V, acc,
                    M[o], CO[o], box, bidx, o, 0, carry[o], s0 > 0,
                )  # fmt: skip

    return drv


@njit(nogil=True)
def _levels(CO, step, vf, qu, sp):
    """``_level_pixel`` of every pixel, in the kernel's order (strips of 32 columns)."""
    r, C, T = CO.shape
    scratch = np.empty(T, np.float32)
    hint = np.nan
    for s0 in range(0, C, 32):
        for o in range(r):
            for j in range(s0, min(C, s0 + 32)):
                sp[o, j], hint = _fast._level_pixel(CO[o, j], step, vf, qu, 2.5, 2, scratch, hint)


@njit(nogil=True)
def _bhats(sp, dev, M, sal, d, level):
    """``_bhat_saliency`` of every pixel (the first wavelength's form, writing)."""
    r, C, T = M.shape
    for o in range(r):
        for j in range(C):
            _fast._bhat_saliency(sp[o, j], dev, M[o, j], sal[o, j], d[o, j], level, o, j, True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args(argv)
    y, keep, c, D = bench_saliency_counts.capture_block()
    R, C, L, T = c.shape
    i0, i1, _ = keep.indices(R)
    r = i1 - i0
    sc = np.ascontiguousarray(D["scales"], np.int64)
    w = np.ascontiguousarray(D["weights"], np.float64)
    qb = int((sc > 1).sum())
    bidx = np.full(sc.size, -1, np.int64)
    bidx[sc > 1] = np.arange(qb)
    nob = np.full(sc.size, -1, np.int64)
    filt, rows = _driver(_fast._filter_row), _driver(_variant("_rows_only", True))
    f32 = _driver(_variant("_f32_sums", False))
    tile = min(256, T)
    times: dict[str, list[float]] = {}
    for l in range(L):
        cl = np.ascontiguousarray(c[:, :, l, :])
        dev = np.ascontiguousarray(D["dev"][l], np.float32)
        vf, qu = float(D["var_factor"][l]), float(D["quantum"][l])
        sal, d, lev = (np.empty((r, C, T), np.float32) for _ in range(3))
        M, CO, M2, CO2 = (np.empty((r, C, T), np.float32) for _ in range(4))
        box = np.empty((qb, r, C, T), np.float32)
        sp = np.empty((r, C), np.float32)
        cf, sr, scc = _fast._flat_rows(cl)
        kw = dict(var_factor=vf, quantum=qu, overwrite=True, strip=32)
        hd = (cf, R, C, T, sr, scc, i0, i1, sc, w, dev)
        step = max(1, min(4, T // 64))
        a64, a32 = np.empty(tile, np.float64), np.empty(tile, np.float32)
        parts = {
            "kernel, as detect calls it (no box)": lambda: _fast.saliency_wavelength(
                cl, keep, sc, w, dev, sal, d, lev, **kw
            ),
            "kernel, box means stored": lambda: _fast.saliency_wavelength(
                cl, keep, sc, w, dev, sal, d, lev, box=box, **kw
            ),
            "filter (row + column pass)": lambda: filt(*hd, M, CO, box, nob, a64),
            "filter, box means stored": lambda: filt(*hd, M, CO, box, bidx, a64),
            "row pass only": lambda: rows(*hd, M2, CO2, box, nob, a64),
            "level (_level_pixel)": lambda: _levels(CO, step, vf, qu, sp),
            "bhat + saliency + level sum": lambda: _bhats(sp, dev, M, sal, d, lev),
            "filter, float32 sums (variant)": lambda: f32(*hd, M2, CO2, box, nob, a32),
        }
        for name, f in parts.items():
            f()
            best = np.inf
            for _ in range(a.rounds):
                t = time.thread_time()
                f()
                best = min(best, time.thread_time() - t)
            times.setdefault(name, []).append(best)
        filt(*hd, M, CO, box, nob, a64)
        f32(*hd, M2, CO2, box, nob, a32)
        for nm, x, z in (("m", M, M2), ("coarse", CO, CO2)):
            dif = np.abs(x.astype(np.float64) - z)
            print(
                f"wavelength {l}, float32 sums: {nm} {np.mean(x != z):.1%} of values moved, "
                f"at most {dif.max():.2g} (values up to {np.abs(x).max():.3g})"
            )
    nv = r * C * T * L
    print(f"block {c.shape}, kept rows {r}, scales {sc.tolist()}")
    for name, v in times.items():
        print(f"{name:38s} {sum(v):.3f} s  {sum(v) / nv * 1e9:5.2f} ns per voxel and wavelength")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
