"""Cubes made the way other groups make them: does splidar read them, and how well?

An independent simulator, written from the paper's observation model only (eq:4.1,
``y ~ Poisson(sum_c r_{n,c,l} g_l(t - d_{n,c}) + b_{n,l,t})``; it never calls
``splidar.simulation``), builds one small scene per case (a tilted wall whose far corner
leaves the time window, a box in front of it, a half-transparent net before part of the
wall: two surfaces in those pixels, two rows never acquired, hot and saturated pixels,
background varying per pixel and per wavelength) and saves it with the conventions other
groups use: the IRF as a sampled histogram with its peak far from bin 0 (bin 30 of a
100-sample record, or later), normalised to its peak or to its sum, in a separate
``.npy`` / ``.txt`` / ``.csv`` (with a header and a time column) file or beside the
counts under the group's own name; counts as uint8 / uint16 / int32 / float64; axis
orders (rows, cols, T), (T, rows, cols), (rows, cols, T, L), (L, rows, cols, T); the bin
width as an HDF5 attribute, a MATLAB variable in seconds, a range bin in metres; T from
256 to 4096 and bins of 2 to 250 ps; photon time lists as a flat pixel index and time
tags in ps with the image size as scalars.

For each case it records what ``splidar.load`` needs (the arguments the documentation
gives), whether ``splidar run FILE`` runs from the command line with the matching
options, and the quality of ``splidar.process(cube, rng=0)`` against the simulator's own
truth (``splidar.metrics.evaluate``, tau = max(2, FWHM / 2) bins; bias = mean signed
depth error of the matched points, bins; "net": F_true of the net's surfaces, the weaker
of two returns in a pixel; "end": of the surfaces within one FWHM of the window's last
bin), beside the per-pixel matched-filter baseline (``splidar.baselines.per_pixel_detect``).

Depths: the truth is the bin where the pulse's maximum lands, counted from the first
stored bin (splidar's convention, docs/usage.md "Your own files"); a group that refers
its depths to the laser emission (time of flight, or range ``c t / 2``) subtracts the
gate delay and the IRF's peak offset to compare.

Run: ``python benchmarks/bench_foreign_cubes.py [--only NAME ...] [--no-cli]`` (about
3 minutes on a 2-core machine; the CLI runs are a third of it).
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import logging
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

C_M_PER_S = 299_792_458.0
ROWS, COLS = 32, 40


# --------------------------------------------------------------------------------------
# the independent simulator (eq:4.1), in the units a lab uses: ps and photons
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Pulse:
    """A continuous pulse shape ``p(tau)`` (tau in bins, its maximum 1 at tau = 0): a
    Gaussian of ``fwhm_bins``, or with ``tail_bins`` > 0 that Gaussian convolved with an
    exponential tail (an exponentially modified Gaussian, the usual SPAD response)."""

    fwhm_bins: float
    tail_bins: float = 0.0

    def __call__(self, tau) -> np.ndarray:
        tau = np.asarray(tau, dtype=np.float64)
        s = self.fwhm_bins / 2.3548
        if self.tail_bins == 0:
            return np.exp(-0.5 * (tau / s) ** 2)
        mode, top = _emg_mode(s, self.tail_bins)
        return _emg(tau + mode, s, self.tail_bins) / top

    def fwhm(self) -> float:
        """Full width at half maximum of the pulse, bins."""
        x = np.arange(-10 * self.fwhm_bins - 10, 10 * (self.fwhm_bins + self.tail_bins) + 10, 0.01)
        above = x[self(x) >= 0.5]
        return float(above[-1] - above[0])


def _emg(x, sigma: float, tail: float) -> np.ndarray:
    from scipy.stats import exponnorm

    return exponnorm.pdf(x, tail / sigma, loc=0.0, scale=sigma)


@functools.cache
def _emg_mode(sigma: float, tail: float) -> tuple[float, float]:
    x = np.arange(-5 * sigma, 5 * sigma + 5 * tail, 0.001)
    v = _emg(x, sigma, tail)
    k = int(np.argmax(v))
    return float(x[k]), float(v[k])


@dataclass
class Scene:
    """Truth of one simulated scene: surfaces (row, col, depth in bins from the first
    stored bin, signal photons per wavelength) and the cube's expected counts."""

    rows: np.ndarray
    cols: np.ndarray
    depth: np.ndarray
    intensity: np.ndarray  # (n, L)
    counts: np.ndarray  # (R, C, L, T) integer-valued float64 before the group's dtype
    excluded: np.ndarray  # (R, C) bool: pixels whose surfaces are not in the truth
    region: np.ndarray  # per surface: 0 wall, 1 box, 2 net (the front one), 3 wall behind the net


def simulate_scene(
    T: int,
    pulse: Pulse,
    *,
    L: int = 1,
    ppp: float = 12.0,
    sbr: float = 1.0,
    hot: int = 2,
    empty_rows: int = 2,
    decaying: bool = False,
    seed: int = 0,
) -> Scene:
    """Draw ``y ~ Poisson(sum_c r g(t - d) + b)`` (eq:4.1) on ROWS x COLS pixels.

    The wall spans about ``4 FWHM + 10`` bins per 31 pixel steps and its far corner lies
    past the window's end (those surfaces are not in the truth); a box stands
    ``5 FWHM + 10`` bins in front; a net ``3 FWHM + 6`` bins in front of the wall returns
    40 % of the light in a block of pixels (two surfaces each). The background is
    ``b_l x s_n`` (a spatial gradient times a random factor, per-wavelength levels),
    set by ``sbr`` over the whole cube; ``decaying``: exp(-t / T) in time.
    """
    rng = np.random.default_rng(seed)
    f = pulse.fwhm_bins
    rr, cc = np.meshgrid(np.arange(ROWS), np.arange(COLS), indexing="ij")
    span = 2.0 * (4 * f + 10)
    u = (rr / (ROWS - 1) + cc / (COLS - 1)) / 2
    wall = T - 1 - 0.8 * span + u * span  # about 20 % of the wall beyond T - 1
    box = (rr >= ROWS // 4) & (rr < ROWS // 2 + 2) & (cc >= COLS // 5) & (cc < COLS // 2)
    net = (rr >= ROWS // 2 + 4) & (cc >= COLS // 2 + 4) & (cc < COLS - 4)
    shade = 0.6 + 0.8 * rng.random((ROWS, COLS))
    spectrum = np.array([1.0, 0.6, 0.35, 0.8, 0.5, 0.9][:L])
    surf = []  # (row, col, depth, weight, region)
    for r in range(ROWS):
        for c in range(COLS):
            if box[r, c]:
                surf.append((r, c, wall[r, c] - 5 * f - 10, 1.0, 1))
                continue
            w = 1.0
            if net[r, c]:
                surf.append((r, c, wall[r, c] - 3 * f - 6, 0.4, 2))
                w = 0.6
            surf.append((r, c, wall[r, c], w, 3 if net[r, c] else 0))
    s = np.array(surf)
    row, col, dep, wgt = s[:, 0].astype(int), s[:, 1].astype(int), s[:, 2], s[:, 3]
    region = s[:, 4].astype(int)
    inten = (ppp * wgt * shade[row, col])[:, None] * spectrum[None, :]
    t = np.arange(T, dtype=np.float64)
    # the pulse sampled at bin centres and normalised to unit sum (eq:4.1's g)
    norm = pulse(np.arange(-40 * f - 200, 40 * f + 200, 1.0) + 0.0).sum()
    lam = np.zeros((ROWS, COLS, L, T))
    for i in range(len(dep)):
        g = pulse(t - dep[i]) / norm
        lam[row[i], col[i]] += inten[i][:, None] * g[None, :]
    signal = lam.sum()
    spatial = (0.4 + 1.2 * cc / (COLS - 1)) * rng.lognormal(0.0, 0.3, (ROWS, COLS))
    level = np.array([1.0, 2.5, 0.5, 1.5, 0.8, 1.2][:L])
    shape_t = np.exp(-t / T) if decaying else np.ones(T)
    b = spatial[:, :, None, None] * level[None, None, :, None] * shape_t
    b *= signal / sbr / b.sum()
    y = rng.poisson(lam + b).astype(np.float64)
    excluded = np.zeros((ROWS, COLS), bool)
    y[:empty_rows] = 0  # lines the scanner never acquired
    excluded[:empty_rows] = True
    for k in range(hot):  # stuck pixels: 300 counts a bin (saturate 8-bit counters)
        r, c = ROWS - 3 - 5 * k, 3 + 7 * k
        y[r, c] += rng.poisson(300.0, (L, T))
        excluded[r, c] = True
    keep = (dep >= 0) & (dep <= T - 1) & ~excluded[row, col]
    return Scene(row[keep], col[keep], dep[keep], inten[keep], y, excluded, region[keep])


def irf_record(pulse: Pulse, n: int, peak_at: int, *, to_peak: bool, L: int = 1) -> np.ndarray:
    """The IRF as a lab records it: ``n`` samples, the maximum at sample ``peak_at``,
    normalised to its peak (1.0) or to its sum."""
    g = pulse(np.arange(n, dtype=np.float64) - peak_at)
    g = g / (g.max() if to_peak else g.sum())
    return g if L == 1 else np.repeat(g[None, :], L, axis=0)


# --------------------------------------------------------------------------------------
# the cases: how each group writes its files, and how splidar is told to read them
# --------------------------------------------------------------------------------------
@dataclass
class Written:
    path: Path
    load_kwargs: dict
    cli_args: list[str]
    note: str = ""


@dataclass
class Case:
    name: str
    T: int
    bin_ps: float
    pulse: Pulse
    write: Callable[[Scene, Path, Case], Written]
    L: int = 1
    sim: dict = field(default_factory=dict)


def _u16(y):
    return np.clip(y, 0, 65535).astype(np.uint16)


def w_npy_rct_u16(sc: Scene, d: Path, case: Case) -> Written:
    """(rows, cols, T) uint16 .npy; IRF: 100 samples, peak at 30, peak-normalised .npy;
    bin width told as a range bin in metres on the CLI."""
    p = d / "scan.npy"
    np.save(p, _u16(sc.counts[:, :, 0, :]))
    np.save(d / "irf.npy", irf_record(case.pulse, 100, 30, to_peak=True))
    bin_m = case.bin_ps * 1e-12 * C_M_PER_S / 2
    return Written(
        p,
        {"irf": str(d / "irf.npy"), "bin_width_ps": case.bin_ps},
        ["--irf", str(d / "irf.npy"), "--bin-width-m", f"{bin_m:.6g}"],
    )


def w_npy_trc_i32(sc: Scene, d: Path, case: Case) -> Written:
    """(T, rows, cols) int32 .npy; IRF: one-column .txt, 300 samples, peak at 80."""
    p = d / "frames.npy"
    np.save(p, np.moveaxis(sc.counts[:, :, 0, :], -1, 0).astype(np.int32))
    np.savetxt(d / "irf.txt", irf_record(case.pulse, 300, 80, to_peak=False))
    return Written(
        p,
        {"irf": str(d / "irf.txt"), "time_axis": 0, "bin_width_ps": case.bin_ps},
        ["--irf", str(d / "irf.txt"), "--time-axis", "0", "--bin-width-ps", str(case.bin_ps)],
    )


def w_npz_own_keys(sc: Scene, d: Path, case: Case) -> Written:
    """.npz with the group's own names: ``hist`` (rows, cols, T) float64, ``irf_hist``
    (peak at 30 of 100), ``bin_ps``, ``t0_s`` (gate delay)."""
    p = d / "meas.npz"
    np.savez(
        p,
        hist=sc.counts[:, :, 0, :],
        irf_hist=irf_record(case.pulse, 100, 30, to_peak=True),
        bin_ps=np.float64(case.bin_ps),
        t0_s=np.float64(33e-9),
    )
    return Written(
        p,
        {"variable": "hist", "irf": str(p), "bin_width_ps": case.bin_ps},
        ["--variable", "hist", "--irf", str(p), "--bin-width-ps", str(case.bin_ps)],
    )


def w_mat_rctl(sc: Scene, d: Path, case: Case) -> Written:
    """MATLAB v5: ``Y`` (rows, cols, T, L) uint16 (Y(:,:,:,l) per band), ``IRF`` (n, L)
    columns (peak at 30 of 120), ``binwidth`` in seconds, ``lambda_nm``."""
    import scipy.io

    p = d / "lego_like.mat"
    scipy.io.savemat(
        p,
        {
            "Y": np.moveaxis(_u16(sc.counts), 2, 3),
            "IRF": irf_record(case.pulse, 120, 30, to_peak=True, L=case.L).T,
            "binwidth": case.bin_ps * 1e-12,
            "lambda_nm": np.array([500.0, 550.0, 600.0, 640.0][: case.L]),
        },
    )
    return Written(
        p,
        {
            "variable": "Y",
            "time_axis": 2,
            "irf": str(p),
            "irf_variable": "IRF",
            "bin_width_ps": case.bin_ps,
        },
        ["--variable", "Y", "--time-axis", "2", "--irf", str(p), "--irf-variable", "IRF",
         "--bin-width-ps", str(case.bin_ps)],
    )  # fmt: skip


def w_h5_lrct(sc: Scene, d: Path, case: Case) -> Written:
    """HDF5: ``/data/counts`` (L, rows, cols, T) uint16 (wavelength first), the bin width as
    an attribute ``bin_width_ps`` of the dataset, ``/data/irf`` (L, n) peak at 30 of 100."""
    import h5py

    p = d / "multi.h5"
    with h5py.File(p, "w") as f:
        ds = f.create_dataset("data/counts", data=np.moveaxis(_u16(sc.counts), 2, 0))
        ds.attrs["bin_width_ps"] = case.bin_ps
        f["data/irf"] = irf_record(case.pulse, 100, 30, to_peak=False, L=case.L)
    return Written(
        p,
        {"variable": "data/counts", "wavelength_axis": 0},
        ["--variable", "data/counts", "--wavelength-axis", "0"],
    )


def w_h5_trc_group(sc: Scene, d: Path, case: Case) -> Written:
    """HDF5: ``/scan/histograms`` (T, rows, cols) uint16 written frame by frame,
    ``/scan/irf`` (peak at 30 of 100, peak-normalised), group attribute ``bin_width_ps``."""
    import h5py

    p = d / "scan.h5"
    with h5py.File(p, "w") as f:
        g = f.create_group("scan")
        g["histograms"] = np.moveaxis(_u16(sc.counts[:, :, 0, :]), -1, 0)
        g["irf"] = irf_record(case.pulse, 100, 30, to_peak=True)
        g.attrs["bin_width_ps"] = case.bin_ps
    return Written(
        p,
        {"variable": "scan/histograms", "time_axis": 0},
        ["--variable", "scan/histograms", "--time-axis", "0"],
    )


def w_mat_u8_coarse(sc: Scene, d: Path, case: Case) -> Written:
    """MATLAB v5: ``counts`` (rows, cols, T) uint8 (hot pixels saturate at 255), ``irf`` a
    column vector (n, 1), peak at 30 of 64, ``bin_width_ps``."""
    import scipy.io

    p = d / "coarse.mat"
    scipy.io.savemat(
        p,
        {
            "counts": np.clip(sc.counts[:, :, 0, :], 0, 255).astype(np.uint8),
            "irf": irf_record(case.pulse, 64, 30, to_peak=False)[:, None],
            "bin_width_ps": float(case.bin_ps),
        },
    )
    return Written(p, {}, [])


def w_npy_f64_long(sc: Scene, d: Path, case: Case) -> Written:
    """(rows, cols, T = 4096) float64 .npy at 2 ps; IRF .csv with a header and a time
    column (``time_ps,counts``: 400 samples, peak at 150, peak-normalised)."""
    p = d / "fine.npy"
    np.save(p, sc.counts[:, :, 0, :])
    g = irf_record(case.pulse, 400, 150, to_peak=True)
    with open(d / "irf.csv", "w", newline="") as fp:
        w = csv.writer(fp)
        w.writerow(["time_ps", "counts"])
        for k, v in enumerate(g):
            w.writerow([f"{k * case.bin_ps:g}", f"{v:.6g}"])
    return Written(
        p,
        {"irf": str(d / "irf.csv"), "bin_width_ps": case.bin_ps},
        ["--irf", str(d / "irf.csv"), "--bin-width-ps", str(case.bin_ps)],
    )


def _photons(sc: Scene, case: Case, gate_ps: float, rng):
    """Each photon of the cube as (flat pixel, time tag in ps), uniformly within its bin,
    plus the gate delay (the time tags count from the laser pulse)."""
    y = sc.counts[:, :, 0, :].astype(np.int64)
    flat = y.reshape(-1)
    idx = np.repeat(np.arange(flat.size), flat)
    pix, b = np.divmod(idx, case.T)
    t = gate_ps + (b + rng.random(b.size)) * case.bin_ps
    order = rng.permutation(t.size)  # time-tagged order, not pixel order
    return pix[order].astype(np.int32), np.floor(t[order]).astype(np.int64)


def w_photons_flat(sc: Scene, d: Path, case: Case) -> Written:
    """Photon time list .npz: ``pixel`` (flat index row * cols + col, int32), ``t_ps``
    (int64 time tags from the laser pulse), ``n_rows`` / ``n_cols`` scalars; IRF .csv
    with a header (``time_ps,counts``: peak at 30 of 100, the same 8 ps bins)."""
    gate = 20_000.0
    pix, t = _photons(sc, case, gate, np.random.default_rng(5))
    p = d / "photons.npz"
    np.savez(p, pixel=pix, t_ps=t, n_rows=np.int32(ROWS), n_cols=np.int32(COLS))
    g = irf_record(case.pulse, 100, 30, to_peak=True)
    with open(d / "irf.csv", "w", newline="") as fp:
        w = csv.writer(fp)
        w.writerow(["time_ps", "counts"])
        for k, v in enumerate(g):
            w.writerow([f"{k * case.bin_ps:g}", f"{v:.6g}"])
    win = (gate, gate + case.T * case.bin_ps)
    return Written(
        p,
        {"window": win, "bin_width": case.bin_ps, "irf": str(d / "irf.csv")},
        ["--window", f"{win[0]:g}", f"{win[1]:g}", "--bin-width", f"{case.bin_ps:g}",
         "--irf", str(d / "irf.csv")],
    )  # fmt: skip


def w_photons_h5_table(sc: Scene, d: Path, case: Case) -> Written:
    """Photon table in HDF5: ``/photons/x``, ``/photons/y`` (uint16), ``/photons/toa_ns``
    (float64, from the laser pulse); IRF as ``irf.npy`` peak at 30 of 100."""
    import h5py

    gate = 50_000.0
    pix, t = _photons(sc, case, gate, np.random.default_rng(6))
    r, c = np.divmod(pix, COLS)
    p = d / "events.h5"
    with h5py.File(p, "w") as f:
        f["photons/x"] = c.astype(np.uint16)
        f["photons/y"] = r.astype(np.uint16)
        f["photons/toa_ns"] = t / 1e3
        f["photons"].attrs["shape"] = np.array([ROWS, COLS])
    np.save(d / "irf.npy", irf_record(case.pulse, 100, 30, to_peak=True))
    win = (gate / 1e3, (gate + case.T * case.bin_ps) / 1e3)
    return Written(
        p,
        {"window": win, "bin_width": case.bin_ps / 1e3, "irf": str(d / "irf.npy")},
        ["--window", f"{win[0]:g}", f"{win[1]:g}", "--bin-width", f"{case.bin_ps / 1e3:g}",
         "--irf", str(d / "irf.npy")],
    )  # fmt: skip


def w_irf_finer(sc: Scene, d: Path, case: Case) -> Written:
    """(rows, cols, T) uint16 at 16 ps, but the IRF recorded at 2 ps (8 samples a bin),
    peak at 240 of 800: the same pulse on another time grid."""
    p = d / "scan.npy"
    np.save(p, _u16(sc.counts[:, :, 0, :]))
    fine = Pulse(case.pulse.fwhm_bins * 8, case.pulse.tail_bins * 8)
    np.save(d / "irf_2ps.npy", irf_record(fine, 800, 240, to_peak=True))
    return Written(
        p,
        {"irf": str(d / "irf_2ps.npy"), "bin_width_ps": case.bin_ps},
        ["--irf", str(d / "irf_2ps.npy"), "--bin-width-ps", str(case.bin_ps)],
        note="IRF sampled 8x finer than the cube",
    )


def w_irf_finer_csv(sc: Scene, d: Path, case: Case) -> Written:
    """As :func:`w_irf_finer`, the IRF written as ``time_ps,counts`` (.csv with a header)."""
    w = w_irf_finer(sc, d, case)
    g = np.load(d / "irf_2ps.npy")
    with open(d / "irf_2ps.csv", "w", newline="") as fp:
        out = csv.writer(fp)
        out.writerow(["time_ps", "counts"])
        for k, v in enumerate(g):
            out.writerow([f"{2 * k}", f"{v:.6g}"])
    irf = str(d / "irf_2ps.csv")
    return Written(
        w.path,
        {"irf": irf, "bin_width_ps": case.bin_ps},
        ["--irf", irf, "--bin-width-ps", str(case.bin_ps)],
        note="IRF csv with its time column, 8x finer than the cube",
    )


def w_irf_finer_step(sc: Scene, d: Path, case: Case) -> Written:
    """As :func:`w_irf_finer`, loaded with the IRF's sample step given (irfw29's
    ``irf_bin_width_ps=2`` / ``--irf-bin-width-ps 2``: the fix its warning names)."""
    w = w_irf_finer(sc, d, case)
    return Written(
        w.path,
        {**w.load_kwargs, "irf_bin_width_ps": 2.0},
        [*w.cli_args, "--irf-bin-width-ps", "2"],
        note="IRF .npy at 2 ps with its step given",
    )


def _cases() -> list[Case]:
    return [
        Case("npy (R,C,T) u16, T1024 16ps, IRF peak 30/100", 1024, 16.0,
             Pulse(5.0), w_npy_rct_u16),
        Case("npy (T,R,C) i32, T2048 4ps, tail IRF .txt", 2048, 4.0,
             Pulse(12.0, 15.0), w_npy_trc_i32),
        Case("npz own keys f64, T512 32ps", 512, 32.0, Pulse(3.0), w_npz_own_keys),
        Case("mat v5 (R,C,T,L) L4, T1500 2ps", 1500, 2.0, Pulse(20.0, 10.0),
             w_mat_rctl, L=4),
        Case("h5 (L,R,C,T) L3, attr bin width", 400, 50.0, Pulse(2.5), w_h5_lrct, L=3),
        Case("h5 (T,R,C) group irf+attr, decaying bg", 800, 25.0, Pulse(4.0),
             w_h5_trc_group, sim={"decaying": True}),
        Case("mat v5 u8 saturated, T256 250ps", 256, 250.0, Pulse(1.3), w_mat_u8_coarse),
        Case("npy f64 T4096 2ps, IRF csv time col", 4096, 2.0, Pulse(35.0, 20.0),
             w_npy_f64_long),
        Case("photons npz pixel+t_ps, IRF csv", 1000, 8.0, Pulse(6.0, 4.0), w_photons_flat),
        Case("photons h5 x/y/toa_ns table", 600, 20.0, Pulse(3.5), w_photons_h5_table),
        Case("IRF at 2 ps, cube at 16 ps", 600, 16.0, Pulse(4.0, 3.0), w_irf_finer),
        Case("IRF at 2 ps given irf_bin_width_ps=2, cube at 16 ps", 600, 16.0,
             Pulse(4.0, 3.0), w_irf_finer_step),
        Case("IRF csv time_ps at 2 ps, cube at 16 ps", 600, 16.0, Pulse(4.0, 3.0),
             w_irf_finer_csv),
    ]  # fmt: skip


# --------------------------------------------------------------------------------------
# running and scoring
# --------------------------------------------------------------------------------------
def _truth(sc: Scene):
    from splidar import PointSet

    return PointSet(
        row=sc.rows, col=sc.cols, depth_bin=sc.depth, image_shape=(ROWS, COLS),
        intensity=sc.intensity,
    )  # fmt: skip


def _score(points, truth, tau, parts=None):
    """evaluate's F_true / false / DAE, the mean signed depth error of the matched points
    and, with ``parts`` (name -> mask over the true points), F_true on each part."""
    from splidar.metrics import evaluate, match_points

    m = evaluate(points, truth, tau=tau)
    mt = match_points(points, truth, tau=tau)
    bias = float(np.mean(points.depth_bin[mt.est_index] - truth.depth_bin[mt.true_index]))
    out = {"f_true": m.f_true, "false": m.f_false, "dae": m.dae, "bias": bias}
    hit = np.zeros(len(truth.row), bool)
    hit[mt.true_index] = True
    for name, mask in (parts or {}).items():
        out[name] = float(hit[mask].mean()) if mask.any() else float("nan")
    return out


def _cli(w: Written, out: Path, truth, tau: float) -> dict:
    cmd = [sys.executable, "-m", "splidar", "run", str(w.path), *w.cli_args, "-o", str(out),
           "--no-figures", "--no-view", "--force", "-q"]  # fmt: skip
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    res = {"cli_wall": time.perf_counter() - t0, "cli_rc": r.returncode}
    if r.returncode != 0:
        res["cli_err"] = (r.stderr.strip().splitlines() or ["?"])[-1][:160]
        return res
    with open(out / "points.csv") as fp:
        rows = list(csv.DictReader(fp))
    from splidar import PointSet

    res["cli_points"] = len(rows)
    res["cli_depth_m"] = bool(rows) and "depth_m" in rows[0]
    pts = PointSet(
        row=[int(r["row"]) for r in rows], col=[int(r["col"]) for r in rows],
        depth_bin=[float(r["depth_bin"]) for r in rows], image_shape=truth.image_shape,
    )  # fmt: skip
    res["cli_f_true"] = _score(pts, truth, tau)["f_true"]
    summary = json.loads((out / "summary.json").read_text())
    res["cli_bin_width_ps"] = summary.get("cube", {}).get("bin_width_ps")
    return res


def run_case(case: Case, base: Path, cli: bool) -> dict:
    import splidar
    from splidar.baselines import per_pixel_detect
    from splidar.irf import irf_fwhm

    d = base / case.name.split()[0].replace("/", "_") / str(abs(hash(case.name)) % 10**6)
    d.mkdir(parents=True, exist_ok=True)
    sc = simulate_scene(case.T, case.pulse, L=case.L, **case.sim)
    w = case.write(sc, d, case)
    out: dict = {"case": case.name, "kwargs": w.load_kwargs, "cli_args": w.cli_args}
    truth = _truth(sc)
    tau = max(2.0, case.pulse.fwhm() / 2)
    with warnings.catch_warnings(record=True) as caught, _LogCatch() as logs:
        warnings.simplefilter("always")
        try:
            cube = splidar.load(w.path, **w.load_kwargs)
        except Exception as exc:  # noqa: BLE001 - the table reports it
            out["load"] = f"{type(exc).__name__}: {exc}"
            return out
    out["load"] = "ok"
    out["load_warnings"] = [str(x.message)[:140] for x in caught] + logs.messages
    out["shape"] = "x".join(str(s) for s in cube.shape)
    out["bin_width_ps"] = cube.bin_width_ps
    out["irf_fwhm"] = float(np.max(irf_fwhm(cube.irf)))
    out["irf_source"] = cube.metadata.get("irf_source", "file")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            rec = splidar.process(cube, rng=0)
        except Exception as exc:  # noqa: BLE001
            out["process"] = f"{type(exc).__name__}: {exc}"
            return out
        out["wall"], out["cpu"] = time.perf_counter() - t0, time.process_time() - c0
        out["n_true"] = len(truth.row)
        fw = case.pulse.fwhm()
        parts = {"net": sc.region == 2, "end": sc.depth > case.T - 1 - fw}
        out.update(_score(rec.points, truth, tau, parts))
        b = per_pixel_detect(cube)
        out.update({"b_" + k: v for k, v in _score(b.points, truth, tau, parts).items()})
    if cli:
        out.update(_cli(w, d / "out", truth, tau))
    return out


class _LogCatch(logging.Handler):
    """Collect splidar's WARNING log lines (the CLI prints them; the API logs them)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage()[:140])

    def __enter__(self):
        logging.getLogger("splidar").addHandler(self)
        return self

    def __exit__(self, *exc):
        logging.getLogger("splidar").removeHandler(self)


def _f(x, spec):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return format(x, spec)


def window_end(lo: float, hi: float, *, seed: int = 0, pulse: Pulse | None = None) -> None:
    """The minimal reproducer of the window's-end loss (README): one surface in every
    pixel of 24 x 24, depths uniform in ``[lo, hi]`` bins of T = 300, the tailed pulse of the
    photon-list case (Gaussian FWHM 6 + exp tail 4 bins: FWHM 8.4), 12 signal photons,
    SBR 1; ``detect`` (all passes, and none) beside ``per_pixel_detect``, tau 4.2 bins.
    ``pulse``: another pulse (e.g. ``Pulse(8.4)``, the Gaussian of the same FWHM)."""
    import splidar
    from splidar import Cube, PointSet
    from splidar.baselines import per_pixel_detect
    from splidar.metrics import evaluate

    rng = np.random.default_rng(seed)
    n, T = 24, 300
    pulse = Pulse(6.0, 4.0) if pulse is None else pulse
    norm = pulse(np.arange(-200.0, 200.0)).sum()
    d = lo + (hi - lo) * rng.random((n, n))
    lam = 12.0 * pulse(np.arange(T) - d[..., None]) / norm
    lam += lam.sum() / lam.size  # SBR 1
    y = rng.poisson(lam).astype(np.uint16)[:, :, None, :]
    cube = Cube(y, irf=irf_record(pulse, 100, 30, to_peak=True))
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    truth = PointSet(row=rr.ravel(), col=cc.ravel(), depth_bin=d.ravel(), image_shape=(n, n))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, pts in (
            ("detect", splidar.detect(cube, rng=0).points),
            ("detect passes=()", splidar.detect(cube, passes=(), rng=0).points),
            ("per_pixel_detect", per_pixel_detect(cube).points),
        ):
            m = evaluate(pts, truth, tau=4.2)
            print(f"depths {lo:g}-{hi:g} of T {T}: {name:<17} F_true {m.f_true:.3f} "
                  f"false {m.f_false} DAE {m.dae:.2f}")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None, help="substrings of case names")
    ap.add_argument("--no-cli", action="store_true", help="skip the `splidar run` calls")
    ap.add_argument("--keep", default=None, help="folder to write the files into (kept)")
    ap.add_argument(
        "--window-end",
        nargs=2,
        type=float,
        metavar=("LO", "HI"),
        help="run only the window's-end reproducer, depths in [LO, HI] bins",
    )
    ap.add_argument(
        "--pulse",
        nargs=2,
        type=float,
        default=(6.0, 4.0),
        metavar=("FWHM", "TAIL"),
        help="--window-end's pulse: Gaussian FWHM and exponential tail, bins (default 6 4)",
    )
    args = ap.parse_args()
    if args.window_end:
        window_end(*args.window_end, pulse=Pulse(*args.pulse))
        return
    cases = _cases()
    if args.only:
        cases = [c for c in cases if any(s in c.name for s in args.only)]
    print(
        "| case | cube read as | bin ps | IRF FWHM (bins), source | load | CLI (F_true, depths) | "
        "wall s / cpu s | n true | F_true | false | DAE | bias | net / end | "
        "baseline F_true / false / DAE | baseline net / end |"
    )
    print("|" + "---|" * 15)
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        notes = []
        for case in cases:
            r = run_case(case, base, not args.no_cli)
            ok = r["load"] == "ok"
            cli = "-" if args.no_cli or not ok else ("yes" if r.get("cli_rc") == 0 else "NO")
            if r.get("cli_rc") == 0:
                m = "m" if r.get("cli_depth_m") else "bins"
                cli = f"yes ({_f(r.get('cli_f_true'), '.3f')}, {m})"
            if not ok or "process" in r:
                notes.append(f"{case.name}: {r['load'] if not ok else r['process']}")
            if r.get("cli_err"):
                notes.append(f"{case.name} (CLI): {r['cli_err']}")
            for m in r.get("load_warnings", []):
                notes.append(f"{case.name} (load warning): {m}")
            src = str(r.get("irf_source", "-"))[:28]
            print(
                f"| {case.name} | {r.get('shape', '-')} | {_f(r.get('bin_width_ps'), 'g')} | "
                f"{_f(r.get('irf_fwhm'), '.1f')}, {src} | {'yes' if ok else 'NO'} | {cli} | "
                f"{_f(r.get('wall'), '.2f')} / {_f(r.get('cpu'), '.2f')} | "
                f"{r.get('n_true', '-')} | {_f(r.get('f_true'), '.3f')} | "
                f"{r.get('false', '-')} | {_f(r.get('dae'), '.2f')} | "
                f"{_f(r.get('bias'), '+.2f')} | "
                f"{_f(r.get('net'), '.2f')} / {_f(r.get('end'), '.2f')} | "
                f"{_f(r.get('b_f_true'), '.3f')} / "
                f"{r.get('b_false', '-')} / {_f(r.get('b_dae'), '.2f')} | "
                f"{_f(r.get('b_net'), '.2f')} / {_f(r.get('b_end'), '.2f')} |",
                flush=True,
            )
            print(f"    load({r['kwargs']}); splidar run FILE {' '.join(r['cli_args'])}",
                  flush=True)  # fmt: skip
        for n in notes:
            print("  -", n)


if __name__ == "__main__":
    main()
