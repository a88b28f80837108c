"""Saliency from box sums of the integer counts, the matched filter after the boxes
(issue 15 point 6, branch speed23; measured, not adopted).

Main's saliency kernel (:func:`splidar.detection._fast.saliency_wavelength`) reads the
correlated block ``c = Y (*) g`` and runs float32 row and float64 running column box
passes at every scale on it. Correlation along t commutes with the spatial boxes and
the multiscale mix is linear, so the same quantities follow from

* exact integer box sums ``W_q`` of the counts ``Y`` (int16 when ``max(Y) K^2`` fits,
  else int32; exact, so the same whatever the strips, blocks or threads),
* the mix ``sum_q lambda_q / k_q^2 W_q`` correlated with the IRF (``m``), and
* ``W_K / K^2`` correlated with the IRF (the coarse series the level estimate needs),

then the same level, ``bhat`` and saliency code as main's kernel. This script runs both
on the first block of ``bench_speed.main_cube()`` (captured during ``detect(n_jobs=1)``),
compares their values, checks that the variant does not depend on the strips or on its
integer type, and times them alternated (thread CPU, ns per voxel and wavelength), with
two cut-short variants for the breakdown (``boxes``: the integer boxes and the mix only;
``no-corr``: everything but the two correlations).

Usage::

    python benchmarks/bench_saliency_counts.py --rounds 10
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

import splidar
from splidar.detection import _4_map
from splidar.detection._fast import _bhat_saliency, _level_pixel, _refl, saliency_wavelength

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_speed  # noqa: E402

_T_TILE = 256


@njit(cache=True, nogil=True)
def _corr_row(src, g, pk, left, xp, out):
    """``out[t] = sum_j g[j] src[t - pk + j]``, ``src`` mirrored: float32, four taps per
    sweep (as main's ``_correlate_direct_kernel``)."""
    T = src.size
    n = g.size
    for u in range(T):
        xp[left + u] = src[u]
    for u in range(left):
        xp[u] = src[_refl(u - left, T)]
    for u in range(left + T, left + T + n):
        xp[u] = src[_refl(u - left, T)]
    for t in range(T):
        out[t] = np.float32(0.0)
    base = left - pk
    j = 0
    while j + 4 <= n:
        g0, g1, g2, g3 = g[j], g[j + 1], g[j + 2], g[j + 3]
        a = xp[base + j : base + j + T]
        b = xp[base + j + 1 : base + j + 1 + T]
        c = xp[base + j + 2 : base + j + 2 + T]
        e = xp[base + j + 3 : base + j + 3 + T]
        for t in range(T):
            out[t] += (g0 * a[t] + g1 * b[t]) + (g2 * c[t] + g3 * e[t])
        j += 4
    while j < n:
        gj = g[j]
        a = xp[base + j : base + j + T]
        for t in range(T):
            out[t] += gj * a[t]
        j += 1


@njit(cache=True, nogil=True)
def _int_boxes(yf, R, C, T, sr, sc, i, s0, s1, scales, coef, V, ac, mix, wk):
    """Integer box sums of block row ``i``, columns ``[s0, s1)``: ``mix[j]`` =
    ``sum_q coef_q W_q`` and ``wk[j]`` = ``W_K / K^2`` (float32, (C, T))."""
    Q = scales.size
    tile = V.shape[2]
    hmax = scales[Q - 1] // 2
    invK2 = np.float32(1.0 / (scales[Q - 1] * scales[Q - 1]))
    ja, jb = max(0, s0 - hmax), min(C, s1 + hmax)
    for t0 in range(0, T, tile):
        tn = min(tile, T - t0)
        for q in range(Q):  # along rows, nested: scale q reuses scale q - 1's rows
            h = scales[q] // 2
            hp = 0 if q == 0 else scales[q - 1] // 2
            for j in range(ja, jb):
                vr = V[q, j, :tn]
                if q == 0:
                    off = i * sr + j * sc + t0
                    cr = yf[off : off + tn]
                    for t in range(tn):
                        vr[t] = cr[t]
                else:
                    vp = V[q - 1, j, :tn]
                    for t in range(tn):
                        vr[t] = vp[t]
            for di in range(hp + 1, h + 1):
                ia, ib = _refl(i - di, R), _refl(i + di, R)
                for j in range(ja, jb):
                    vr = V[q, j, :tn]
                    ca = yf[ia * sr + j * sc + t0 : ia * sr + j * sc + t0 + tn]
                    cb = yf[ib * sr + j * sc + t0 : ib * sr + j * sc + t0 + tn]
                    for t in range(tn):
                        vr[t] += ca[t] + cb[t]
        acq = ac[:tn]
        for q in range(Q):  # along columns: exact running sums, restarted per strip
            h = scales[q] // 2
            for j in range(s0, s1):
                if h == 0:
                    acq[:] = V[q, j, :tn]
                elif j == s0:
                    acq[:] = 0
                    for u in range(-h, h + 1):
                        vr = V[q, _refl(j + u, C), :tn]
                        for t in range(tn):
                            acq[t] += vr[t]
                else:
                    va, vb = V[q, _refl(j + h, C), :tn], V[q, _refl(j - h - 1, C), :tn]
                    for t in range(tn):
                        acq[t] += va[t] - vb[t]
                mr = mix[j, t0 : t0 + tn]
                w = coef[q]
                for t in range(tn):
                    mr[t] = w * np.float32(acq[t]) if q == 0 else mr[t] + w * np.float32(acq[t])
                if q == Q - 1:
                    cr = wk[j, t0 : t0 + tn]
                    for t in range(tn):
                        cr[t] = np.float32(acq[t]) * invK2


@njit(cache=True, nogil=True)
def _int_kernel(
    yf, R, C, T, sr, sc, i0, i1, strip, scales, coef, g, pk, dev, var_factor, quantum, clip,
    n_iter, step, sp, sal, d, overwrite, mode, V, ac,
):  # fmt: skip
    """Rows ``[i0, i1)`` of one wavelength. ``mode`` 0: all; 1: no correlations
    (``m`` = mix, coarse = ``W_K / K^2``); 2: the integer boxes and the mix only."""
    mix = np.empty((C, T), np.float32)
    wk = np.empty((C, T), np.float32)
    xp = np.empty(pk + T + g.size, np.float32)
    m = np.empty(T, np.float32)
    coarse = np.empty(T, np.float32)
    scratch = np.empty(T, np.float32)
    level = np.empty((0, 0, 0), np.float32)
    hint = np.nan
    for s0 in range(0, C, strip):
        s1 = min(C, s0 + strip)
        for i in range(i0, i1):
            _int_boxes(yf, R, C, T, sr, sc, i, s0, s1, scales, coef, V, ac, mix, wk)
            if mode == 2:
                continue
            for j in range(s0, s1):
                if mode == 1:
                    m[:] = mix[j]
                    coarse[:] = wk[j]
                else:
                    _corr_row(mix[j], g, pk, pk, xp, m)
                    _corr_row(wk[j], g, pk, pk, xp, coarse)
                for t in range(T):
                    coarse[t] -= dev[t]
                o = i - i0
                sp[o, j], hint = _level_pixel(
                    coarse, step, var_factor, quantum, clip, n_iter, scratch, hint
                )
                _bhat_saliency(sp[o, j], dev, m, sal[o, j], d[o, j], level, o, j, overwrite)


def saliency_counts(y, keep, D, sal, d, *, strip=32, small=None, mode=0):
    """The variant over the wavelengths of a block ``y`` (R, C, L, T) of counts (a
    C-contiguous integer array)."""
    R, C, L, T = y.shape
    i0, i1, _ = keep.indices(R)
    sc = np.ascontiguousarray(D["scales"], np.int64)
    coef = (np.asarray(D["weights"], np.float64) / sc.astype(np.float64) ** 2).astype(np.float32)
    K = int(sc[-1])
    small = int(y.max()) * K * K <= 32767 if small is None else small
    vt = np.int16 if small else np.int32
    V = np.empty((sc.size, C, min(_T_TILE, T)), vt)
    ac = np.empty(min(_T_TILE, T), vt)
    step = max(1, min(4, T // 64))
    sps = np.empty((i1 - i0, C, L), np.float32)
    it = y.itemsize
    sr, sc_ = y.strides[0] // it, y.strides[1] // it
    for l in range(L):
        # the wavelength's counts as a flat view (no copy): (i, j, t) at i sr + j sc + t
        span = (R - 1) * sr + (C - 1) * sc_ + T
        yf = np.lib.stride_tricks.as_strided(y[:, :, l, :], shape=(span,), strides=(it,))
        if small and yf.dtype == np.uint16:
            yf = yf.view(np.int16)  # values <= 32767 / K^2: the same integers
        sp = np.empty((i1 - i0, C), np.float32)
        _int_kernel(
            yf, R, C, T, sr, sc_, i0, i1, strip, sc, coef,
            np.ascontiguousarray(D["irf"][l], np.float32), int(D["peak"][l]),
            np.ascontiguousarray(D["dev"][l], np.float32), float(D["var_factor"][l]),
            float(D["quantum"][l]), 2.5, 2, step, sp, sal, d, l == 0, mode, V, ac,
        )  # fmt: skip
        sps[:, :, l] = sp
    return sal, d, sps


def saliency_main(c, keep, D, sal, d):
    """Main's kernel over the wavelengths of a correlated block ``c`` (R, C, L, T)."""
    L = c.shape[2]
    sps = [
        saliency_wavelength(
            c[:, :, l, :],
            keep,
            D["scales"],
            D["weights"],
            D["dev"][l],
            sal,
            d,
            None,
            var_factor=float(D["var_factor"][l]),
            quantum=float(D["quantum"][l]),
            clip=2.5,
            overwrite=l == 0,
            strip=32,
        )  # fmt: skip
        for l in range(L)
    ]
    return sal, d, np.stack(sps, -1)


def capture_block():
    """``(y, keep, c, D)``: the bench cube's first block as ``detect(n_jobs=1)`` sees it."""
    cube = bench_speed.main_cube().cube
    got = []
    orig = _4_map.block_saliency

    class _Stop(Exception):
        pass

    def spy(y, ctx, **kw):
        got.append((np.array(y), kw["keep"], np.array(kw["c"]), ctx))
        raise _Stop

    _4_map.block_saliency = spy
    try:
        splidar.detect(cube, n_jobs=1)
    except _Stop:
        pass
    finally:
        _4_map.block_saliency = orig
    y, keep, c, ctx = got[0]
    assert ctx.corr.direct, "the bench cube's IRF is summed directly"
    D = dict(
        scales=ctx.scales, weights=ctx.weights, dev=ctx.dev, var_factor=ctx.var_factor,
        quantum=ctx.quantum, irf=ctx.corr.irf, peak=ctx.corr.peak,
    )  # fmt: skip
    return y, keep, c, D


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=8, help="alternated timing rounds")
    args = ap.parse_args(argv)
    y, keep, c, D = capture_block()
    R, C, L, T = y.shape
    r = len(range(*keep.indices(R)))

    def bufs():
        return np.empty((r, C, T), np.float32), np.empty((r, C, T), np.float32)

    a = saliency_main(c, keep, D, *bufs())
    b = saliency_counts(y, keep, D, *bufs())
    for name, u, v in zip(["saliency", "d", "level"], a, b, strict=True):
        dif = np.abs(u.astype(np.float64) - v)
        print(f"{name}: {np.mean(u != v):.1%} differ, max {dif.max():.2g} (max |value| "
              f"{np.abs(u).max():.3g})")  # fmt: skip
    same = []
    for kw in (dict(strip=7), dict(strip=C), dict(small=False)):
        other = saliency_counts(y, keep, D, *bufs(), **kw)
        same.append(all(np.array_equal(u, v) for u, v in zip(b, other, strict=True)))
    print("variant the same with strips of 7 / all columns / int32:", same)
    fns = {
        "main": lambda: saliency_main(c, keep, D, *bufs()),
        "counts": lambda: saliency_counts(y, keep, D, *bufs()),
        "boxes": lambda: saliency_counts(y, keep, D, *bufs(), mode=2),
        "no-corr": lambda: saliency_counts(y, keep, D, *bufs(), mode=1),
    }
    for f in fns.values():
        f()
    res = {k: [] for k in fns}
    for rnd in range(args.rounds):
        for k in list(fns) if rnd % 2 == 0 else list(fns)[::-1]:
            t0 = time.thread_time()
            fns[k]()
            res[k].append(time.thread_time() - t0)
    n = r * C * L * T
    for k, v in res.items():
        print(f"{k:8s} ns per voxel and wavelength: best {min(v) / n * 1e9:.2f}, median "
              f"{np.median(v) / n * 1e9:.2f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
