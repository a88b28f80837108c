"""Robustness of the defaults across sensors and scenes other groups plausibly use.

Each case builds a small cube with splidar's own simulator (a tilted, shaded plane; a
second surface where the case says so) under one sensor or scene setting that departs
from the development scenes: the number of bins T, the bin width, the IRF's width,
shape and placement, the number of wavelengths and their background, SBR and PPP,
float counts, surfaces at the window's edges, close surfaces, empty and saturated
scenes, tiny or non-square images, dead and hot pixels. For each it runs
``splidar.process`` with its defaults and records whether it runs (an exception, or
how many warnings it emitted), its time (wall and CPU), and F_true / false surfaces /
mean depth error (``splidar.metrics.evaluate``, tau = max(2, FWHM / 2) bins) against the
truth, beside the per-pixel matched-filter baseline (``splidar.baselines``).

Run: ``python benchmarks/bench_robustness.py [--only NAME ...] [--size 32]``
(about 2-4 minutes on a 2-core machine). The measured IRF of ``../shared/data/irf-sample``
is used where present (those cases are skipped otherwise).
"""

from __future__ import annotations

import argparse
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import splidar
from splidar import Cube, PointSet, SplidarError
from splidar.baselines import per_pixel_detect
from splidar.irf import exp_tail_irf, gaussian_irf, irf_fwhm
from splidar.metrics import evaluate
from splidar.simulation import simulate

IRF_SAMPLE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "irf-sample"


@dataclass
class Case:
    name: str
    build: Callable[[int], tuple[Cube, PointSet | None]]  # size -> (cube, truth)
    note: str = ""
    refused: bool = False  # the input cannot work: one clear SplidarError is the answer


def _plane(shape, lo, hi, *, second=None, refl=True, every=False):
    """A tilted plane spanning depths ``lo..hi`` (bins), shaded; ``second``: offset in bins
    of a second surface behind it in every other column (or None; ``every``: in every
    pixel)."""
    r, c = shape
    rr, cc = np.meshgrid(np.arange(r), np.arange(c), indexing="ij")
    u = (rr / max(r - 1, 1) + cc / max(c - 1, 1)) / 2.0
    depth = lo + u * (hi - lo)
    shade = 0.6 + 0.4 * np.cos(2 * np.pi * u) ** 2 if refl else np.ones_like(u)
    rows, cols, dep, inten, layer = (
        [rr.ravel()],
        [cc.ravel()],
        [depth.ravel()],
        [shade.ravel()],
        [np.zeros(r * c, int)],
    )
    if second is not None:
        m = (cc % 2 == 0).ravel() | every
        rows.append(rr.ravel()[m])
        cols.append(cc.ravel()[m])
        dep.append(depth.ravel()[m] + second)
        inten.append(shade.ravel()[m])
        layer.append(np.ones(m.sum(), int))
    return PointSet(
        row=np.concatenate(rows),
        col=np.concatenate(cols),
        depth_bin=np.concatenate(dep),
        image_shape=(r, c),
        intensity=np.concatenate(inten)[:, None],
        layer=np.concatenate(layer),
    )


def _with_L(truth: PointSet, L: int, spectrum=None) -> PointSet:
    s = np.ones(L) if spectrum is None else np.asarray(spectrum, float)
    kw = truth.to_dict()
    kw.pop("image_shape")
    kw["intensity"] = truth.intensity[:, :1] * s[None, :]
    return PointSet(image_shape=truth.image_shape, **kw)


def _sim(truth, T, irf, *, ppp=10.0, sbr=1.0, bw=250.0, bg="uniform", bpb=None, seed=0):
    kw = dict(n_bins=T, irf=irf, ppp=ppp, bin_width_ps=bw, rng=seed)
    if bpb is not None:
        kw.update(background=bg, background_per_bin=bpb, sbr=sbr)
    elif sbr is not None:
        kw.update(background=bg, sbr=sbr)
    sim = simulate(truth, **kw)
    return sim.cube, sim.truth


def _irf_margin(irf) -> float:
    g = np.asarray(irf, float)
    g = g if g.ndim == 1 else g[0]
    p = int(np.argmax(g))
    return float(max(p, g.size - 1 - p)) + 2.0


def basic(
    T=200,
    fwhm=3.0,
    *,
    irf=None,
    ppp=10.0,
    sbr=1.0,
    second=None,
    every=False,
    bw=250.0,
    shape=None,
    steep=False,
    span=None,
    bg="uniform",
):
    """The common case: a gently tilted plane (on 32 x 32 pixels its depths spread over
    ``4 FWHM + 10`` bins about the window's middle; the same slope per pixel on other
    shapes; ``steep``: over the whole usable window; ``span``: over that many bins)."""

    def build(size):
        g = gaussian_irf(fwhm) if irf is None else irf
        m = _irf_margin(g)
        lo, hi = m, T - 1 - m - (second or 0)
        if span is not None:
            mid = 0.5 * (lo + hi)
            lo, hi = mid - span / 2, mid + span / 2
        elif not steep:
            # the same slope per pixel step as on a 32 x 32 image, whatever the shape
            r, c = shape or (size, size)
            sp = (4.0 * float(irf_fwhm(np.asarray(g, float))) + 10.0) * (r + c - 2) / 62
            sp = min(hi - lo, sp)
            mid = 0.5 * (lo + hi)
            lo, hi = mid - sp / 2, mid + sp / 2
        truth = _plane(shape or (size, size), lo, hi, second=second, every=every)
        return _sim(truth, T, g, ppp=ppp, sbr=sbr, bw=bw, bg=bg)

    return build


def measured_irf() -> np.ndarray | None:
    f = IRF_SAMPLE / "data_supp.mat"
    if not f.exists():
        return None
    import scipy.io

    return scipy.io.loadmat(f)["waveform_shape"].ravel().astype(np.float64)


def _cases() -> list[Case]:
    cases = [
        Case("reference T200 fwhm3", basic()),
        Case("steep plane over the window", basic(steep=True)),
        Case("T=32", basic(T=32)),
        Case("T=64", basic(T=64)),
        Case("T=1000", basic(T=1000)),
        Case("T=4000 fwhm 8", basic(T=4000, fwhm=8.0)),
        Case("bin 1 ps (fwhm 30, T 1500)", basic(T=1500, fwhm=30.0, bw=1.0)),
        Case("bin 1 ns (fwhm 0.7)", basic(T=100, fwhm=0.7, bw=1000.0)),
        Case("fwhm 1", basic(fwhm=1.0)),
        Case("fwhm 10", basic(T=300, fwhm=10.0)),
        Case("fwhm 30", basic(T=600, fwhm=30.0)),
        Case("exp tail 3/6", basic(irf=exp_tail_irf(3.0, 6.0))),
        Case("exp tail 2/25", basic(T=400, irf=exp_tail_irf(2.0, 25.0))),
        Case("IRF off-centre (peak at 3 of 41)", basic(irf=_offcentre(3, 41))),
        Case("IRF off-centre (peak at 37 of 41)", basic(irf=_offcentre(37, 41))),
        Case("IRF with a 1e-3 floor", basic(irf=_floor(gaussian_irf(3.0, length=61), 1e-3))),
    ]
    w = measured_irf()
    if w is not None:
        crop = w[230:300]
        cases += [
            Case("measured IRF cropped, T 300", basic(T=300, irf=crop)),
            Case("measured IRF 625 samples, T 800", basic(T=800, irf=w)),
            Case("measured IRF 625 samples, T 300", _long_irf(w, 300)),
        ]
    cases += [
        Case(
            "IRF longer than T (gauss 3, 301 samples, T 200)",
            _long_irf(gaussian_irf(3.0, length=301), 200),
        ),
        Case("L=2", _multi(2)),
        Case("L=4 per-wl background", _multi(4, bpb=[0.01, 0.05, 0.2, 1.0])),
        Case("L=16", _multi(16)),
        Case(
            "L=4 IRF FWHM 1, 3, 6, 10 per band",
            _multi(4, irf=[("gaussian", f) for f in (1, 3, 6, 10)]),
        ),
        Case("L=4 one dark band", _multi(4, spectrum=[1, 1, 1, 0.0])),
        Case("SBR 0.01 PPP 10", basic(sbr=0.01)),
        Case("SBR 100 PPP 10", basic(sbr=100.0)),
        Case("PPP 0.1 SBR 1", basic(ppp=0.1)),
        Case("PPP 1 SBR 1", basic(ppp=1.0)),
        Case("PPP 1000 SBR 1", basic(ppp=1000.0)),
        Case("PPP 1000 SBR 100 (saturated)", basic(ppp=1000.0, sbr=100.0)),
        Case("no background (sbr None)", basic(sbr=None)),
        Case("decaying background", basic(bg="decaying", sbr=0.25)),
        Case("pile-up background", basic(bg="pileup", sbr=0.25)),
        Case("PPP 100 SBR 0.01 (50 bg counts a bin)", basic(ppp=100.0, sbr=0.01)),
        Case("PPP 1e5 (counts over 65535 a bin)", basic(ppp=1e5, sbr=10.0)),
        Case("float64 counts", _float_counts()),
        Case("float32 counts", _float_counts(np.float32)),
        Case("int64 counts", _float_counts(np.int64)),
        Case("uint8 counts", _float_counts(np.uint8)),
        Case("float counts, dead pixels NaN", _dead(nan=True), refused=True),
        Case("masked array, dead pixels masked", _dead(masked=True)),
        Case("surface at bin 0 / T-1", _edges()),
        Case("two surfaces 2 FWHM apart", basic(second=6.0)),
        Case("two surfaces 2.5 FWHM apart", basic(second=7.5)),
        Case("two surfaces 3 FWHM apart", basic(second=9.0)),
        Case("two surfaces 2 FWHM, fwhm 8", basic(T=300, fwhm=8.0, second=16.0)),
        Case("two surfaces 2 FWHM apart, every pixel", basic(second=6.0, every=True)),
        Case("two surfaces 2.5 FWHM apart, every pixel", basic(second=7.5, every=True)),
        Case("empty scene (background only)", _empty()),
        Case("all-zero cube", _zeros()),
        Case("shape 1x1", basic(shape=(1, 1))),
        Case("shape 1x40", basic(shape=(1, 40))),
        Case("shape 40x1", basic(shape=(40, 1))),
        Case("shape 3x3", basic(shape=(3, 3))),
        Case("shape 3x3, 5.5 bins a pixel step", basic(shape=(3, 3), span=22.0)),
        Case("shape 2x2", basic(shape=(2, 2))),
        Case("shape 12x50", basic(shape=(12, 50))),
        Case("dead pixels (10 %)", _dead()),
        Case("dead column", _dead(column=True)),
        Case("hot pixel (1e5 counts/bin)", _hot()),
        Case("hot pixel (5 counts/bin, 50x bg)", _hot(5)),
        Case("one-bin spike (1e5 counts) in one pixel", _hot(spike=True)),
    ]
    return cases


def _offcentre(peak: int, n: int) -> np.ndarray:
    t = np.arange(n) - peak
    g = np.exp(-0.5 * (t / (3.0 / 2.3548)) ** 2)
    return g / g.sum()


def _floor(g, level):
    g = g + level * g.max()
    return g / g.sum()


def _long_irf(irf, T):
    def build(size):
        # simulate with the IRF cropped to what fits, then hand the long IRF to the cube
        p = int(np.argmax(irf))
        nz = np.nonzero(irf > irf.max() * 1e-6)[0]
        crop = irf[nz[0] : nz[-1] + 1]
        m = _irf_margin(crop)
        truth = _plane((size, size), m, T - 1 - m)
        cube, tr = _sim(truth, T, crop)
        _ = p
        return Cube(cube.counts, irf=irf, bin_width_ps=cube.bin_width_ps), tr

    return build


def _multi(L, bpb=None, spectrum=None, irf=None):
    def build(size):
        g = gaussian_irf(3.0) if irf is None else irf
        m = 30.0
        truth = _with_L(_plane((size, size), m, 199 - m), L, spectrum)
        return _sim(truth, 200, g, ppp=10.0 * L, sbr=1.0, bpb=bpb)

    return build


def _float_counts(dtype=np.float64):
    def build(size):
        cube, tr = basic()(size)
        return Cube(cube.counts.astype(dtype), irf=cube.irf), tr

    return build


def _edges():
    def build(size):
        g = gaussian_irf(3.0)
        truth = _plane((size, size), 0.0, 199.0)
        # half the pixels at bin 0.3, half at 198.7
        kw = truth.to_dict()
        kw.pop("image_shape")
        kw["depth_bin"] = np.where(truth.col < size // 2, 0.3, 198.7)
        return _sim(PointSet(image_shape=truth.image_shape, **kw), 200, g)

    return build


def _empty():
    def build(size):
        rng = np.random.default_rng(0)
        counts = rng.poisson(0.05, (size, size, 1, 200)).astype(np.uint16)
        truth = PointSet(row=[], col=[], depth_bin=[], image_shape=(size, size))
        return Cube(counts, irf=gaussian_irf(3.0)), truth

    return build


def _zeros():
    def build(size):
        truth = PointSet(row=[], col=[], depth_bin=[], image_shape=(size, size))
        return Cube(np.zeros((size, size, 1, 200), np.uint16), irf=gaussian_irf(3.0)), truth

    return build


def _dead(column=False, nan=False, masked=False):
    def build(size):
        cube, tr = basic()(size)
        c = np.array(cube.counts, dtype=np.float64 if nan else cube.counts.dtype)
        rng = np.random.default_rng(1)
        if column:
            dead = np.zeros((size, size), bool)
            dead[:, size // 3] = True
        else:
            dead = rng.random((size, size)) < 0.1
        if masked:
            c = np.ma.masked_array(c, mask=np.broadcast_to(dead[:, :, None, None], c.shape))
            c.data[dead] = 7  # what the masked values hold must not matter
        else:
            c[dead] = np.nan if nan else 0
        keep = ~dead[tr.row, tr.col]
        kw = tr.to_dict()
        kw.pop("image_shape")
        tr = PointSet(
            image_shape=tr.image_shape, **{k: v[keep] for k, v in kw.items() if v is not None}
        )
        return Cube(c, irf=cube.irf, bin_width_ps=cube.bin_width_ps), tr

    return build


def _hot(level=100_000, spike=False):
    def build(size):
        cube, tr = basic()(size)
        c = np.array(cube.counts, dtype=np.uint32)
        if spike:
            c[size // 2, size // 2, 0, 77] += 100_000
        else:
            rng = np.random.default_rng(3)
            c[size // 2, size // 2] += rng.poisson(level, c.shape[2:]).astype(np.uint32)
        return Cube(c, irf=cube.irf, bin_width_ps=cube.bin_width_ps), tr

    return build


def _run_one(case: Case, size: int) -> dict:
    out: dict = {"case": case.name}
    try:
        cube, truth = case.build(size)
    except SplidarError as exc:
        out["status"] = "refused" if case.refused else f"build: SplidarError: {str(exc)[:70]}"
        out["message"] = str(exc)
        return out
    except Exception as exc:  # noqa: BLE001 - the table reports it
        out["status"] = f"build: {type(exc).__name__}: {str(exc)[:70]}"
        return out
    out["shape"] = "x".join(str(s) for s in cube.shape)
    fwhm = float(np.max(irf_fwhm(cube.irf)))
    tau = max(2.0, fwhm / 2.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            rec = splidar.process(cube, rng=0)
        except Exception as exc:  # noqa: BLE001
            out["status"] = f"{type(exc).__name__}: {str(exc)[:90]}"
            out["warn"] = len(caught)
            return out
        out["wall"], out["cpu"] = time.perf_counter() - t0, time.process_time() - c0
    out["warn"] = len(caught)
    out["warn_first"] = str(caught[0].message)[:80] if caught else ""
    out["status"] = "ok"
    m = evaluate(rec.points, truth, tau=tau)
    out.update(n_true=m.n_true, f_true=m.f_true, false=m.f_false, dae=m.dae)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            b = per_pixel_detect(cube)
        mb = evaluate(b.points, truth, tau=tau)
        out.update(b_f_true=mb.f_true, b_false=mb.f_false, b_dae=mb.dae)
    except Exception as exc:  # noqa: BLE001
        out["b_status"] = f"{type(exc).__name__}"
    return out


def _fmt(x, spec):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return format(x, spec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--only", nargs="*", default=None, help="substrings of case names")
    args = ap.parse_args()
    # warm the numba kernels outside the timings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        splidar.process(basic()(8)[0], rng=0)
    cases = _cases()
    if args.only:
        cases = [c for c in cases if any(s in c.name for s in args.only)]
    hdr = (
        f"| {'case':<48} | {'cube':<14} | {'runs':<7} | {'warn':>4} | "
        f"{'wall s':>6} | {'cpu s':>6} | "
        f"{'n true':>6} | {'F_true':>6} | {'false':>5} | {'DAE':>5} | "
        f"{'base F_true':>11} | {'base false':>10} | {'base DAE':>8} |"
    )
    print(hdr)
    print("|" + "|".join("-" * (len(p)) for p in hdr.split("|")[1:-1]) + "|")
    failures = []
    for case in cases:
        r = _run_one(case, args.size)
        ok = r["status"] == "ok"
        runs = "yes" if ok else "refused" if r["status"] == "refused" else "NO"
        if runs == "NO":
            failures.append((case.name, r["status"]))
        print(
            f"| {case.name:<48} | {r.get('shape', '-'):<14} | {runs:<7} | "
            f"{r.get('warn', 0):>4} | {_fmt(r.get('wall'), '6.2f'):>6} | "
            f"{_fmt(r.get('cpu'), '6.2f'):>6} | {r.get('n_true', '-'):>6} | "
            f"{_fmt(r.get('f_true'), '6.3f'):>6} | {r.get('false', '-'):>5} | "
            f"{_fmt(r.get('dae'), '5.2f'):>5} | {_fmt(r.get('b_f_true'), '11.3f'):>11} | "
            f"{r.get('b_false', r.get('b_status', '-')):>10} | {_fmt(r.get('b_dae'), '8.2f'):>8} |",
            flush=True,
        )
        if runs == "refused":
            print(f"    refused, as it should be: {r['message']}")
        if r.get("warn"):
            print(f"    first warning: {r['warn_first']}")
    for name, status in failures:
        print(f"FAILED {name}: {status}")


if __name__ == "__main__":
    main()
