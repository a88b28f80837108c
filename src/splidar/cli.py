"""The ``splidar`` command line: a thin layer over the public API.

Commands::

    splidar demo      [--out DIR]                 simulate a scene, process it, print metrics
    splidar run       INPUT [--out DIR] [...]     process a file (cube or photon lists)
    splidar simulate  SCENE --out FILE [...]      write a simulated cube and its truth
    splidar evaluate  POINTS TRUTH [--tau BINS]   the paper's metrics
    splidar view      RESULT [--out FILE]         an interactive 3D view (view.html)

Every error is one line on stderr (``splidar: error: ...``) and a non-zero exit status:
2 for a usage error, 1 for a failure while running, 130 when interrupted (Ctrl-C),
143 when terminated (SIGTERM). ``--verbose`` adds the traceback; ``--json`` prints a
machine-readable summary and nothing else on stdout. Outputs of ``run`` and ``demo`` are
written into a hidden
temporary folder beside ``--out`` and renamed at the end, so an interrupted run never
leaves a folder that looks complete.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import shutil
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Sequence
from contextlib import contextmanager
from glob import escape as glob_escape
from pathlib import Path
from typing import Any

from ._validation import SplidarError
from ._version import __version__

__all__ = ["main"]

PROG = "splidar"
log = logging.getLogger("splidar.cli")

# exit statuses
EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_TERMINATED = 143  # 128 + SIGTERM

#: The built-in demo scene: 64 x 64 pixels, 4 wavelengths, 200 bins, a net in front.
DEMO = {"shape": (64, 64), "n_bins": 200, "ppp": 10.0, "sbr": 1.0}

SCENES = ("single", "two-layer", "multispectral", "multispectral-two-layer", "art")


class UsageError(Exception):
    """A bad command line (exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing usage and exiting, for one-line errors."""

    def error(self, message):  # noqa: D401 - argparse API
        raise UsageError(f"{message} (see '{self.prog} --help')")


# ----------------------------------------------------------------------------------------
# argument types
# ----------------------------------------------------------------------------------------
def _int_list(text: str) -> tuple[int, ...]:
    try:
        vals = tuple(int(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers such as 1,3,7,11; got {text!r}"
        ) from None
    if not vals:
        raise argparse.ArgumentTypeError(f"expected at least one integer; got {text!r}")
    return vals


def _channels(text: str):
    if text in ("wavelengths", "detectors"):
        return text
    try:
        return _int_list(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected 'wavelengths', 'detectors' or channel numbers such as 0,2; got {text!r}"
        ) from None


def _float_list(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers such as 0,1,0,0; got {text!r}"
        ) from None
    if not vals:
        raise argparse.ArgumentTypeError(f"expected at least one number; got {text!r}")
    return vals


def _probability(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1); got {text!r}") from None
    if not 0.0 < x < 1.0:
        raise argparse.ArgumentTypeError(f"must lie in (0, 1), e.g. 1e-3; got {text!r}")
    return x


def _pass_list(text: str) -> tuple[str, ...]:
    """``--skip``: comma-separated names of detect's clean-up passes."""
    from .detection import PASSES

    vals = tuple(v for v in text.replace(" ", "").split(",") if v)
    bad = [v for v in vals if v not in PASSES]
    if bad or not vals:
        raise argparse.ArgumentTypeError(
            f"expected pass names from {', '.join(PASSES)}; got {text!r}"
        )
    return vals


def _alpha(text: str):
    """``--alpha``: a number > 1 or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 1 or 'auto', got {text!r}") from None
    if not v > 1:
        raise argparse.ArgumentTypeError(f"expected a number > 1 or 'auto', got {text!r}")
    return v


def _positive(kind):
    def conv(text: str):
        try:
            x = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected a positive {'integer' if kind is int else 'number'}; got {text!r}"
            ) from None
        if not x > 0:
            raise argparse.ArgumentTypeError(f"must be > 0; got {text!r}")
        if not math.isfinite(x):
            raise argparse.ArgumentTypeError(f"must be a finite number > 0; got {text!r}")
        return x

    return conv


def _non_negative(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0; got {text!r}") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"must be >= 0; got {text!r}")
    return x


# ----------------------------------------------------------------------------------------
# parser
# ----------------------------------------------------------------------------------------
_EPILOG = """\
examples:
  splidar demo
  splidar run scan.mat --irf-fwhm 10 --out scan-result
  splidar simulate multispectral-two-layer --ppp 10 --sbr 1 --out scene.npz
  splidar evaluate scene-splidar/result.npz scene-truth.npz --tau 2
  splidar view scene-splidar
  splidar info scan.h5 --variable measurement/histograms --time-axis 0

Run 'splidar COMMAND --help' for the options of a command.
"""


def _common(parser: argparse.ArgumentParser, *, top: bool) -> None:
    # on sub-commands the default is SUPPRESS so that `splidar -v run ...` is not reset
    d = {} if top else {"default": argparse.SUPPRESS}
    g = parser.add_argument_group("output control")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bars or messages", **d)
    g.add_argument(
        "-v",
        "--verbose",
        action="count",
        help="more messages (-vv: debug); tracebacks on errors",
        **({"default": 0} if top else d),
    )


def _out_options(p: argparse.ArgumentParser, default: str) -> None:
    g = p.add_argument_group("outputs")
    g.add_argument("-o", "--out", metavar="DIR", help=f"output folder (default: {default})")
    g.add_argument(
        "--force", action="store_true", help="replace an existing output folder of splidar"
    )
    g.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    g.add_argument("--no-view", action="store_true", help="skip view.html, the interactive 3D view")
    g.add_argument(
        "--pixel-size",
        type=_positive(float),
        metavar="M",
        help="pixel footprint at the target in metres, for x and y of points.ply and "
        "points.las (default: pixel units)",
    )


def _pipeline_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("detection (splidar.detect)")
    g.add_argument(
        "--scales",
        type=_int_list,
        metavar="K1,K2,..",
        help="box sizes of the multiscale cubes, odd (default: 1,3,7,11 less the boxes "
        "whose neighbours do not share the pixels' depths, measured on the data)",
    )
    g.add_argument(
        "--weights",
        type=_float_list,
        metavar="W1,W2,..",
        help="weight of each scale, summing to 1 (default equal)",
    )
    g.add_argument(
        "--pfa", type=_probability, help="probability of false alarm per voxel (default 1e-3)"
    )
    g.add_argument(
        "--max-surfaces",
        type=_positive(int),
        metavar="K",
        help="most surfaces kept per pixel (default 2)",
    )
    g.add_argument(
        "--null", choices=("empirical", "gamma"), help="threshold model (default empirical)"
    )
    g.add_argument(
        "--presence",
        choices=("auto", "adaptive", "none", "pixel"),
        help="own-pixel presence check of candidates (default adaptive)",
    )
    g.add_argument(
        "--skip",
        type=_pass_list,
        metavar="PASS,..",
        help="clean-up passes of the detection to skip (default: run all): spill_over, "
        "isolated, dark_regions, slopes, enclosed, stray_clusters, unlayered, "
        "align_depths, edge_bands (docs/detection.md)",
    )
    g.add_argument(
        "--store",
        metavar="DIR",
        help="write saliency, map and threshold to this new Zarr directory instead of "
        "memory (cubes larger than RAM)",
    )
    g.add_argument(
        "--jobs", type=_positive(int), metavar="N", help="threads (default: cores, at most 4)"
    )
    g = p.add_argument_group("reconstruction (splidar.reconstruct)")
    g.add_argument(
        "--classes",
        choices=("library", "one", "cluster"),
        help="where classes come from (default: library if any, else one)",
    )
    g.add_argument(
        "--n-classes", type=_positive(int), metavar="K", help="classes for --classes cluster"
    )
    g.add_argument(
        "--gamma",
        type=_non_negative,
        help="Potts interaction strength in nats per graph link, >= 0 (default 1.5)",
    )
    g.add_argument("--rho", type=_positive(float), help="gamma-MRF coupling (default 4)")
    g.add_argument(
        "--alpha",
        type=_alpha,
        help="gamma shape of the reflectivity prior, > 1, or 'auto' (default: estimated "
        "from the data, which calibrates the uncertainties; 6 was the former fixed prior)",
    )
    g.add_argument(
        "--signature-scale",
        choices=("shape", "absolute"),
        help="compare spectra by shape or absolute level (default: shape when L > 1)",
    )
    g.add_argument("--links", choices=("depth", "all"), help="graph links (default depth-gated)")
    g.add_argument("--max-iter", type=_positive(int), metavar="N", help="iterations (default 200)")
    g.add_argument("--tol", type=_positive(float), help="convergence tolerance (default 1e-3)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


def _cluster_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "where to compute (Dask; needs pip install 'splidar[distributed]' for a cluster)"
    )
    x = g.add_mutually_exclusive_group()
    x.add_argument(
        "--workers",
        type=_positive(int),
        metavar="N",
        help="start a local Dask cluster of N worker processes (one thread each)",
    )
    x.add_argument(
        "--scheduler", metavar="ADDRESS", help="join a running Dask cluster (tcp://host:8786)"
    )
    g.add_argument(
        "--memory-limit",
        metavar="SIZE",
        help="per-worker memory limit of --workers' cluster, e.g. 1GB (default: RAM / N)",
    )
    g.add_argument(
        "--strip-rows",
        type=_positive(int),
        metavar="N",
        help="Dask input: image rows per reconstruction strip (default: from a 256 MiB "
        "budget per strip); the points are streamed per strip to points.parquet/",
    )


def _pipeline_on_dask(cube, args, stages: _Stages, *, stream=None):
    """:func:`_pipeline` on the Dask scheduler the options ask for: a lazy cube on
    threads, any cube on a cluster (--workers, --scheduler); an in-memory cube without
    them as before."""
    from ._cluster import as_dask_cube, dask_session

    on_cluster = args.workers is not None or args.scheduler is not None
    if args.memory_limit is not None and args.workers is None:
        raise UsageError("--memory-limit sets the memory of --workers' cluster; add --workers N")
    if not on_cluster and not cube.is_lazy:
        return _pipeline(cube, args, stages)
    session = dask_session(
        workers=args.workers,
        memory_limit=args.memory_limit,
        scheduler=args.scheduler,
        progress=not args.quiet,
    )
    with session:
        return _pipeline(as_dask_cube(cube) if on_cluster else cube, args, stages, stream=stream)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``splidar`` command (for documentation tools)."""
    fmt = argparse.RawDescriptionHelpFormatter
    parser = _Parser(
        prog=PROG,
        description="Single-photon lidar: 3D target detection, reconstruction and "
        "spectral classification of photon-count cubes.",
        epilog=_EPILOG,
        formatter_class=fmt,
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    _common(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    _demo_parser(sub, fmt)
    _run_parser(sub, fmt)
    _simulate_parser(sub, fmt)
    _evaluate_parser(sub, fmt)
    _view_parser(sub, fmt)
    _info_parser(sub, fmt)
    return parser


def _demo_parser(sub, fmt) -> None:
    """``splidar demo``: the built-in scene end to end."""
    p = sub.add_parser(
        "demo",
        help="simulate a multispectral two-layer scene, process it, print metrics",
        description="Simulate the built-in scene (64 x 64 pixels, 4 wavelengths, 200 bins, "
        "a net in front of three materials; PPP 10, SBR 1), run detection and "
        "reconstruction, write the outputs and print the metrics against the truth.",
        epilog="example:\n  splidar demo --out splidar-demo\n",
        formatter_class=fmt,
    )
    _out_options(p, "splidar-demo in the current folder")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--tau", type=_positive(float), default=2.0, help="matching distance, bins (default 2)"
    )
    _common(p, top=False)
    _json_flag(p)


def _run_parser(sub, fmt) -> None:
    """``splidar run``: process a file."""
    p = sub.add_parser(
        "run",
        help="detect and reconstruct the surfaces of a file",
        description="Process a cube file (.npz, .npy, .mat, .h5, .zarr), a PicoQuant T3 "
        ".ptu or Becker & Hickl .sdt file (extras splidar[ptu], splidar[sdt]), photon "
        "lists (a MATLAB cell array of arrival times) or a photon table (one photon per "
        "line: row, col, time[, wavelength] columns of a .csv, .npz or .h5) and write "
        "points.csv, points.ply, "
        "points.las (with splidar[las]), result.npz, summary.json and figures/ into the "
        "output folder.",
        epilog="examples:\n"
        "  splidar run scene.npz\n"
        "  splidar run data_face.mat --window 1000 8000 --irf-fwhm 8 --out face\n"
        "  splidar run tower.mat --time-unit ps --window 5180000 5380000 --bin-width 100\n",
        formatter_class=fmt,
    )
    p.add_argument("input", metavar="INPUT", help="file to process")
    _input_options(p)
    _out_options(p, "INPUT-STEM-splidar beside the input")
    _pipeline_options(p)
    _cluster_options(p)
    _common(p, top=False)
    _json_flag(p)


def _input_options(p: argparse.ArgumentParser) -> None:
    """The options of ``splidar.load`` (``run`` and ``info``)."""
    g = p.add_argument_group("input (splidar.load)")
    g.add_argument(
        "--variable",
        metavar="NAME",
        help="variable (array) holding the data, e.g. scan/histograms in an HDF5 group "
        "(default: counts, else the only cell array of photon times or the row, col, time "
        "columns of a photon table; otherwise an error lists the file's variables)",
    )
    g.add_argument(
        "--time-axis",
        type=int,
        metavar="AXIS",
        help="cubes: axis of the stored array holding the time bins, moved last, e.g. 0 "
        "for (T, rows, cols) (default -1: (rows, cols[, L], T), with a warning when the "
        "shape suggests time first)",
    )
    g.add_argument(
        "--wavelength-axis",
        type=int,
        metavar="AXIS",
        help="4-D cubes: axis of the stored array holding the wavelengths, e.g. 0 for "
        "(L, rows, cols, T) (default: the one before time)",
    )
    g.add_argument(
        "--window",
        nargs=2,
        type=float,
        metavar=("START", "STOP"),
        help="photon lists: time range to histogram (data unit); cubes: bin range to crop",
    )
    g.add_argument(
        "--bin-width",
        type=_positive(float),
        metavar="W",
        help="photon lists: bin width in the data's unit (default 1)",
    )
    g.add_argument(
        "--time-unit",
        choices=("bin", "fs", "ps", "ns", "us", "ms", "s"),
        help="photon lists: unit of the arrival times (default bin)",
    )
    bw = g.add_mutually_exclusive_group()
    bw.add_argument(
        "--bin-width-ps",
        type=_positive(float),
        metavar="PS",
        help="duration of one time bin of the cube in picoseconds (sets depths in metres)",
    )
    bw.add_argument(
        "--bin-width-m",
        type=_positive(float),
        metavar="M",
        help="the same as a range bin in metres (light travels there and back: "
        "1 ps = 0.15 mm; --bin-width-m 0.0024 is --bin-width-ps 16.01)",
    )
    irf = g.add_mutually_exclusive_group()
    irf.add_argument(
        "--irf",
        metavar="FILE",
        help="instrument response file (.npy, .npz, .mat, .h5, .csv, .txt, a .ptu/.sdt "
        "measurement summed over its pixels, or a .phu histogram). Default: the file's IRF, "
        "else the pulse shape pooled from the bright pixels (a Gaussian where the photons "
        "do not support a shape); 'estimate': a Gaussian of the width estimated from the "
        "data; 'estimate-shape': the pulse shape even when the file holds an IRF",
    )
    g.add_argument(
        "--irf-variable",
        metavar="NAME",
        help="variable of the --irf file holding the IRF when it holds several arrays "
        "(e.g. IRF in a .mat file beside the counts)",
    )
    g.add_argument(
        "--irf-bin-width-ps",
        type=_positive(float),
        metavar="PS",
        help="sample step of the --irf file (or the file's own IRF) in picoseconds when it "
        "was recorded at another bin width than the cube's: resampled onto the cube's bins "
        "(splidar warns when the IRF's width and the data's pulse width differ by over 2x)",
    )
    irf.add_argument(
        "--irf-fwhm",
        type=_positive(float),
        metavar="BINS",
        help="use a Gaussian IRF of this FWHM in bins",
    )
    g.add_argument(
        "--library",
        metavar="FILE",
        help="spectral library file (K x L: .npy, .npz, .mat, .h5, .csv, .json)",
    )
    g.add_argument(
        "--channels",
        type=_channels,
        metavar="C",
        help="vendor files (.ptu, .sdt): 'wavelengths' (each detector channel a wavelength, "
        "the default), 'detectors' (channels summed into one wavelength) or channel "
        "numbers 0,2,..",
    )


def _info_parser(sub, fmt) -> None:
    """``splidar info``: what a file holds and how splidar reads it."""
    p = sub.add_parser(
        "info",
        help="what a file holds and how splidar reads it (no processing)",
        description="List the variables of a data file (name, shape, type) and read it as "
        "'splidar run' would with the same input options: the cube's pixels, wavelengths, "
        "time bins, bin width, window, photons and the IRF it would use. Nothing is written.",
        epilog="examples:\n"
        "  splidar info scan.h5\n"
        "  splidar info scan.h5 --variable measurement/histograms --time-axis 0\n"
        "  splidar info photons.csv --window 4000 7000 --bin-width 16\n",
        formatter_class=fmt,
    )
    p.add_argument("input", metavar="INPUT", help="file to inspect")
    _input_options(p)
    _common(p, top=False)
    _json_flag(p)


def _simulate_parser(sub, fmt) -> None:
    """``splidar simulate``: write a simulated cube and its truth."""
    p = sub.add_parser(
        "simulate",
        help="write a simulated cube and its ground truth",
        description="Simulate a built-in scene and write the cube (loadable by "
        "'splidar run') and its ground truth as a point set FILE-STEM-truth.npz "
        "(usable by 'splidar evaluate').",
        epilog="examples:\n"
        "  splidar simulate two-layer --ppp 5 --sbr 0.5 --out net.npz\n"
        "  splidar simulate art --art-folder ../shared/data/middlebury-art --out art.npz\n",
        formatter_class=fmt,
    )
    p.add_argument("scene", metavar="SCENE", choices=SCENES, help=f"one of {', '.join(SCENES)}")
    p.add_argument("-o", "--out", metavar="FILE", required=True, help="cube file (.npz or .zarr)")
    p.add_argument(
        "--ppp",
        type=_positive(float),
        default=10.0,
        help="signal photons per pixel, summed over wavelengths (default 10)",
    )
    p.add_argument(
        "--sbr", type=_positive(float), default=1.0,
        help="signal-to-background ratio: signal / background photons (default 1)",
    )  # fmt: skip
    p.add_argument(
        "--background",
        choices=("uniform", "decaying", "pileup"),
        default="uniform",
        help="temporal shape of the background (default uniform)",
    )
    p.add_argument(
        "--size",
        nargs=2,
        type=_positive(int),
        metavar=("ROWS", "COLS"),
        default=(64, 64),
        help="image size (default 64 64; not for art)",
    )
    p.add_argument("--bins", type=_positive(int), help="time bins T (default: the scene's)")
    p.add_argument(
        "--irf-fwhm", type=_positive(float), metavar="BINS",
        help="Gaussian IRF FWHM in bins (default 3)",
    )  # fmt: skip
    p.add_argument("--art-folder", metavar="DIR", help="folder of the Middlebury Art files")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--force", action="store_true", help="replace existing files")
    _common(p, top=False)
    _json_flag(p)


def _evaluate_parser(sub, fmt) -> None:
    """``splidar evaluate``: the paper's metrics."""
    p = sub.add_parser(
        "evaluate",
        help="the paper's metrics of estimated points against the truth",
        description="Match estimated and true points per pixel within TAU and print "
        "F_true, F_false, DAE, IAE, detection and label accuracy. POINTS and TRUTH can be "
        "a point set .npz, a result.npz or output folder of 'splidar run', or a "
        "points.csv.",
        epilog="example:\n  splidar evaluate splidar-demo splidar-demo/truth.npz --tau 2\n",
        formatter_class=fmt,
    )
    p.add_argument("points", metavar="POINTS", help="estimated points")
    p.add_argument("truth", metavar="TRUTH", help="true points")
    tau = p.add_mutually_exclusive_group()
    tau.add_argument("--tau", type=_positive(float), help="matching distance in bins (default 2)")
    tau.add_argument("--tau-m", type=_positive(float), help="matching distance in metres")
    p.add_argument("--json", action="store_true", help="print the metrics as JSON")
    _common(p, top=False)


def _json_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--json",
        action="store_true",
        help="print a JSON summary on stdout and nothing else there (messages go to stderr)",
    )


def _view_parser(sub, fmt) -> None:
    p = sub.add_parser(
        "view",
        help="write (and open) an interactive 3D view of a result",
        description="Write the interactive 3D point cloud of a result as one self-contained "
        "HTML file (no network access needed: rotate, zoom, colour by depth, label, "
        "intensity or uncertainty, one layer or all), print its path and open it in the "
        "default browser. RESULT is an output folder of 'splidar run'/'demo', its "
        "result.npz, or a point-set .npz.",
        epilog="examples:\n"
        "  splidar view scene-splidar\n"
        "  splidar view scene-splidar/result.npz --color label --out scene.html --no-open\n",
        formatter_class=fmt,
    )
    p.add_argument("result", metavar="RESULT", help="output folder or .npz of points")
    p.add_argument(
        "-o",
        "--out",
        metavar="FILE",
        help="HTML file (default: view.html in the output folder, else RESULT-STEM.html)",
    )
    p.add_argument(
        "--color",
        choices=("depth", "label", "intensity", "spectral", "uncertainty", "confidence"),
        default="depth",
        help="initial colouring (default depth; the page switches)",
    )
    p.add_argument(
        "--pixel-size",
        type=_positive(float),
        metavar="M",
        help="pixel footprint in metres: a metric view when the bin width is known",
    )
    p.add_argument("--no-open", action="store_true", help="write the file only")
    p.add_argument("--force", action="store_true", help="replace a file splidar did not write")
    _common(p, top=False)
    _json_flag(p)


# ----------------------------------------------------------------------------------------
# logging and progress
# ----------------------------------------------------------------------------------------
class _Formatter(logging.Formatter):
    def format(self, record):
        return _cli_names(super().format(record))


class _TqdmHandler(logging.Handler):
    """Log records to stderr without breaking progress bars."""

    def emit(self, record):
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # pragma: no cover - logging must never raise
            self.handleError(record)


@contextmanager
def _logging(args):
    logger = logging.getLogger("splidar")
    handler = _TqdmHandler()
    handler.setFormatter(_Formatter("splidar: %(message)s"))
    level = logging.WARNING
    if args.verbose >= 2:
        level = logging.DEBUG
    elif args.verbose == 1:
        level = logging.INFO
    if args.quiet:
        level = logging.ERROR
    old_level, old_prop = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)
        logger.propagate = old_prop


class _Stages:
    """A progress bar over the stages of a command (silent off a terminal or with -q)."""

    def __init__(self, names: Sequence[str], quiet: bool):
        from tqdm import tqdm

        self.names = list(names)
        self.timings: dict[str, float] = {}
        disable = quiet or not sys.stderr.isatty()
        self.bar = tqdm(
            total=len(self.names),
            disable=disable,
            file=sys.stderr,
            unit="stage",
            bar_format="{desc:<28} {bar} {n_fmt}/{total_fmt} [{elapsed}]",
            leave=False,
        )
        # redraw twice a second, so that the elapsed time of a long step keeps counting
        self._stop = threading.Event()
        self._ticker = None
        if not disable:
            self._ticker = threading.Thread(target=self._tick, name="splidar-progress", daemon=True)
            self._ticker.start()

    def _tick(self):
        while not self._stop.wait(0.5):
            self.bar.refresh()

    @contextmanager
    def stage(self, name: str):
        self.bar.set_description_str(name)
        log.info("%s ...", name)
        t0 = time.perf_counter()
        yield
        self.timings[name] = time.perf_counter() - t0
        log.info("%s: %.2f s", name, self.timings[name])
        self.bar.update(1)

    def close(self):
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join()
        self.bar.close()


def _say(args, *lines: str) -> None:
    if not args.quiet:
        for line in lines:
            print(line)


# ----------------------------------------------------------------------------------------
# output folders
# ----------------------------------------------------------------------------------------
def _check_out_folder(out: Path, force: bool, protect: Sequence[Path] = ()) -> None:
    """Refuse an output folder that exists (unless --force on a splidar folder) or holds input."""
    out_r = out.resolve()
    for p in protect:
        pr = Path(p).resolve()
        if pr == out_r or out_r in pr.parents:
            raise UsageError(
                f"the output folder '{out}' would contain or replace the input '{p}'; "
                "choose another --out"
            )
    _check_writable_parent(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise UsageError(f"the output '{out}' exists and is not a folder; choose another --out")
        if not force:
            raise UsageError(
                f"the output folder '{out}' exists; pass --force to replace it or choose "
                "another --out"
            )
        if any(out.iterdir()) and not (out / "summary.json").is_file():
            raise UsageError(
                f"refusing to replace '{out}': it is not empty and holds no summary.json of "
                "a splidar run; choose another --out"
            )


def _check_writable_parent(out: Path) -> None:
    """Refuse, before any work, an output that lies under a file or in a read-only folder."""
    anc = out.absolute().parent
    while not (anc.exists() or anc.is_symlink()) and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise UsageError(
            f"the output '{out}' lies under '{anc}', which is a file, not a folder; choose "
            "another --out"
        )
    try:  # a real probe: os.access says yes to root even on a read-only mount
        probe = tempfile.mkdtemp(prefix=f".{out.name}.probe-", dir=anc)
    except OSError as exc:
        raise UsageError(
            f"cannot write into the folder '{anc}' ({exc.strerror or exc}); choose another "
            "--out or fix its permissions"
        ) from None
    os.rmdir(probe)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _clean_stale(out: Path) -> None:
    """Remove what a killed run left beside ``out``; put back a previous output it moved.

    A run stages into ``.NAME.partial-PID-*`` and, when replacing, moves the previous
    output into ``.NAME.old-PID-*`` for the instant between two renames. Only folders
    of processes that no longer run are touched.
    """
    parent = out.parent
    if not parent.is_dir():
        return
    for kind in ("old", "partial"):
        for d in sorted(parent.glob(f".{glob_escape(out.name)}.{kind}-*")):
            try:
                pid = int(d.name[len(out.name) + len(kind) + 3 :].split("-")[0])
            except ValueError:
                continue
            if _pid_alive(pid) or not d.is_dir():
                continue
            prev = d / out.name
            if kind == "old" and prev.is_dir() and not out.exists():
                os.replace(prev, out)
                log.warning("restored '%s' left aside by an interrupted run", out)
            shutil.rmtree(d, ignore_errors=True)


@contextmanager
def _staging(out: Path):
    """Yield a temporary folder beside ``out``; rename it to ``out`` on success."""
    parent = out.parent
    parent.mkdir(parents=True, exist_ok=True)
    _clean_stale(out)
    pid = os.getpid()
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-{pid}-", dir=parent))
    try:
        # mkdtemp makes a private (0700) folder; give the result the usual permissions
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)
        yield tmp
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-{pid}-", dir=parent))
            os.replace(out, old / out.name)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_outputs(
    folder: Path, rec, *, cube, args, metrics=None, extra=None, stages: _Stages
) -> list[str]:
    from . import export

    files = []
    with stages.stage("writing points and maps"):
        export.write_csv(rec.points, folder / "points.csv")
        export.write_ply(
            rec,
            folder / "points.ply",
            pixel_size=getattr(args, "pixel_size", None) or 1.0,
        )
        export.write_npz(rec, folder / "result.npz")
        files += ["points.csv", "points.ply", "result.npz"]
        if not getattr(args, "no_view", False):
            files.append(_write_view(rec, folder, args))
        files += _write_las(rec, folder, args)
    if not args.no_figures:
        with stages.stage("drawing figures"):
            import matplotlib

            matplotlib.use("Agg", force=True)
            from .plotting import save_figures

            paths = save_figures(rec, folder / "figures", cube=cube)
            files += [f"figures/{p.name}" for p in paths.values()]
    extra = dict(extra or {})
    extra["timings_s_command"] = stages.timings
    extra["files"] = files + extra.get("streamed", {}).get("files", []) + ["summary.json"]
    export.write_summary(rec, folder / "summary.json", metrics=metrics, extra=extra)
    return files


def _write_las(rec, folder: Path, args) -> list[str]:
    """points.las when laspy is installed; otherwise a one-line note (not a failure)."""
    from .las import las_available, write_las

    if not las_available():
        log.warning("points.las not written: laspy is not installed (pip install 'splidar[las]')")
        return []
    write_las(rec, folder / "points.las", pixel_size=getattr(args, "pixel_size", None))
    return ["points.las"]


def _given(args, names: Sequence[str]) -> dict[str, Any]:
    """Options the user gave (None means: the API's default)."""
    out = {}
    for name in names:
        v = getattr(args, name, None)
        if v is not None:
            out[name] = v
    return out


_DETECT_OPTS = (
    "scales",
    "weights",
    "pfa",
    "max_surfaces",
    "null",
    "presence",
    "store",
)
_RECON_OPTS = (
    "classes",
    "n_classes",
    "gamma",
    "rho",
    "alpha",
    "signature_scale",
    "links",
    "max_iter",
    "tol",
)


#: a streamed run (Dask input) writes the usual CSV, PLY, npz, view and figures beside the
#: Parquet points and Zarr maps up to this many points (some 100 MB of CSV)
SMALL_RESULT = 1_000_000


def _reconstruct_streamed(det, library, rec_kw, args, stages: _Stages, stream: dict):
    """Strips of a Dask cube's detection, each strip's points written as it finishes
    (``_stream.StripStore`` in ``stream["folder"]``); ``stream["store"]`` is set."""
    from ._stream import StripStore
    from .reconstruction._tiled import reconstruct_tiled

    store = StripStore(
        stream["folder"], stream["key"], det.image_shape, int(det.surfaces.n_slots),
        det.n_wavelengths, bin_width_ps=det.bin_width_ps,
        # a cluster joined by --scheduler may not see this machine's files
        workers_see_folder=getattr(args, "scheduler", None) is None,
    )  # fmt: skip
    stream["store"] = store
    with stages.stage("reconstructing"):
        out = reconstruct_tiled(
            det, strip_rows=getattr(args, "strip_rows", None), store=store,
            assemble=len(det.surfaces) <= SMALL_RESULT, library=library, rng=args.seed,
            **rec_kw,
        )  # fmt: skip
    if store.resumed:
        log.warning(
            "resumed an interrupted run: %d of %d strip(s) already finished, not recomputed",
            len(store.resumed), len(store.manifest["cores"]),
        )  # fmt: skip
    return out


def _pipeline(cube, args, stages: _Stages, *, library=None, stream=None):
    from .detection import PASSES, detect
    from .reconstruction import reconstruct

    det_kw = _given(args, _DETECT_OPTS)
    if getattr(args, "skip", None):
        det_kw["passes"] = tuple(p for p in PASSES if p not in args.skip)
    if getattr(args, "jobs", None) is not None:
        det_kw["n_jobs"] = args.jobs
    rec_kw = _given(args, _RECON_OPTS)
    det = None if stream is None else _resumed_detection(stream)
    if det is None:
        _check_detect_memory(cube, det_kw)
        with (
            stages.stage("detecting surfaces"),
            _damaged_chunks(cube, getattr(args, "input", "")),
        ):
            det = detect(cube, rng=args.seed, **det_kw)
        if stream is not None and det.options.get("dask", False):
            from ._stream import save_detection

            save_detection(stream["folder"], stream["key"], det)
    if stream is not None and det.options.get("dask", False):
        return _reconstruct_streamed(det, library, _given(args, _RECON_OPTS), args, stages, stream)
    _check_reconstruct_memory(det, library)
    log.info(
        "%d surfaces detected; %.3g %% of voxels kept",
        len(det.surfaces),
        100 * det.reduction.voxel_fraction,
    )
    with stages.stage("reconstructing"):
        rec = reconstruct(det, library=library, rng=args.seed, **rec_kw)
    return rec


def _resumed_detection(stream: dict):
    """The detection an interrupted run of the same key kept in its resume folder, or
    None; ``stream["detection_resumed"]`` says which."""
    from ._stream import load_detection

    det = load_detection(stream["folder"], stream["key"]) if stream["folder"].is_dir() else None
    stream["detection_resumed"] = det is not None
    if det is not None:
        log.warning(
            "resumed an interrupted run: detection read from %s (not recomputed)",
            stream["folder"] / "detection",
        )
    return det


@contextmanager
def _damaged_chunks(cube, source):
    """A lazy (Zarr) cube is read during detection: name a damaged chunk as such."""
    try:
        yield
    except (RuntimeError, OSError, KeyError) as exc:
        if not cube.is_lazy:
            raise
        raise SplidarError(
            f"cannot read the counts of '{source}' ({type(exc).__name__}: {exc}): a chunk is "
            "damaged or missing; write the Zarr store again"
        ) from exc


def _check_detect_memory(cube, det_kw) -> None:
    """Refuse a cube whose detection cannot fit in memory, or that holds no photon."""
    from ._memory import check_detect_memory

    if cube.n_bins < 3:
        raise SplidarError(
            f"the data ({cube.n_rows} x {cube.n_cols} pixels) have T = {cube.n_bins} time "
            "bin(s); detection needs at least 3 (a return and its two sides). Check --window, "
            "--bin-width and --time-axis (is the time axis last?)"
        )
    if not cube.is_lazy and not cube.counts.any():
        raise SplidarError(
            f"the data ({cube.n_rows} x {cube.n_cols} pixels, {cube.n_bins} bins) hold no "
            "photon: nothing to detect. Check the file, variable and --window"
        )
    check_detect_memory(cube, store=det_kw.get("store"))


def _check_reconstruct_memory(det, library) -> None:
    from ._memory import check_memory, reconstruct_peak_bytes

    n_l = int(det.background.spatial.shape[-1])
    n_k = int(getattr(library, "n_classes", None) or 8)
    check_memory(
        reconstruct_peak_bytes(len(det.surfaces), n_l, n_k),
        f"reconstruction of {len(det.surfaces)} surfaces",
        "lower --max-surfaces, raise the detection threshold (--pfa) or process a crop",
    )


def _scales_line(det) -> tuple[str, ...]:
    """A line when ``scales="auto"`` dropped boxes (none otherwise)."""
    opts = det.options or {}
    rho = opts.get("scale_coherence")
    parts = opts.get("scale_regions")
    if parts is not None:  # boxes chosen by region: the sets and their pixels
        sets = "; ".join(
            f"{','.join(map(str, k))} on {n} px"
            for k, n in zip(parts["scales"], parts["pixels"], strict=True)
        )
        return (f"spatial pooling by region: boxes {sets} (--scales 1,3,7,11 keeps all)",)
    if not opts.get("scales_auto") or rho is None or len(det.scales) == len(rho):
        return ()
    from .detection._detect import AUTO_SCALES

    dropped = [k for k in AUTO_SCALES if k not in det.scales]
    kept = ",".join(str(k) for k in det.scales)
    return (
        f"spatial pooling: boxes {kept}; {', '.join(map(str, dropped))} dropped (their "
        "neighbours do not share the pixels' depths; --scales 1,3,7,11 keeps them)",
    )


def _timing_line(det, rec) -> str:
    td = (det.timings or {}).get("total")
    tr = (rec.timings or {}).get("total")
    parts = []
    if td is not None:
        parts.append(f"detection {td:.2f} s")
    if tr is not None:
        parts.append(f"reconstruction {tr:.2f} s")
    return "timings: " + ", ".join(parts) if parts else ""


# ----------------------------------------------------------------------------------------
# commands
# ----------------------------------------------------------------------------------------
def _cmd_demo(args) -> int:
    from .metrics import evaluate
    from .scenes import multispectral_scene

    out = Path(args.out) if args.out else Path("splidar-demo")
    _check_out_folder(out, args.force)
    stages = _Stages(
        ["simulating", "detecting surfaces", "reconstructing", "writing points and maps"]
        + ([] if args.no_figures else ["drawing figures"]),
        args.quiet,
    )
    try:
        with stages.stage("simulating"):
            scene = multispectral_scene(DEMO["shape"], n_bins=DEMO["n_bins"], two_layers=True)
            sim = scene.simulate(ppp=DEMO["ppp"], sbr=DEMO["sbr"], rng=args.seed)
        rec = _pipeline(sim.cube, args, stages)
        metrics = evaluate(rec.points, sim.truth, tau=args.tau)
        with _staging(out) as tmp:
            sim.truth.save(tmp / "truth.npz")
            _write_outputs(
                tmp,
                rec,
                cube=sim.cube,
                args=args,
                metrics=metrics.as_dict(),
                extra={
                    "command": "demo",
                    "scene": {
                        "name": scene.name,
                        "description": scene.description,
                        "ppp": sim.ppp,
                        "sbr": sim.sbr,
                        "seed": args.seed,
                    },
                },
                stages=stages,
            )
    finally:
        stages.close()
    c = sim.cube
    print(
        f"demo scene: {scene.name}, {c.n_rows} x {c.n_cols} pixels, {c.n_wavelengths} "
        f"wavelengths, {c.n_bins} bins, PPP {sim.ppp:.3g}, SBR {sim.sbr:.3g}"
    )
    print(f"metrics against the truth ({len(sim.truth)} true surfaces):")
    print(_indent(str(metrics)))
    print(_timing_line(rec.detection, rec))
    args.json_summary = _json_result(out)
    _say(args, f"outputs written to {out}/ (figures in {out}/figures/)")
    return EXIT_OK


def _indent(text: str, n: int = 2) -> str:
    return "\n".join(" " * n + line for line in text.splitlines())


def _cmd_run(args) -> int:
    from .io import load
    from .reconstruction import Reconstruction

    inp = Path(args.input)
    if not inp.exists():
        raise SplidarError(f"input file '{inp}' does not exist")
    out = Path(args.out) if args.out else inp.parent / f"{inp.name.split('.')[0]}-splidar"
    _check_out_folder(out, args.force, protect=[inp])
    stages = _Stages(
        ["loading", "detecting surfaces", "reconstructing", "writing points and maps"]
        + ([] if args.no_figures else ["drawing figures"]),
        args.quiet,
    )
    load_kw = _load_kwargs(args)
    try:
        with stages.stage("loading"):
            cube = load(inp, **load_kw)
        log.info("loaded %r", cube)
        stream = None
        if cube.is_lazy or args.workers is not None or args.scheduler is not None:
            # points per strip to Parquet; a killed run leaves this folder to resume from
            stream = {"folder": out.parent / f".{out.name}.resume", "key": _run_key(args)}
        rec = _pipeline_on_dask(cube, args, stages, stream=stream)
        extra = {
            "command": "run",
            "input": str(inp),
            "load_options": load_kw,
            "cube": {
                "shape": list(cube.shape),
                "bin_width_ps": cube.bin_width_ps,
                "metadata": dict(cube.metadata),
            },
        }
        with _staging(out) as tmp:
            if stream is not None and "store" in stream:
                extra["streamed"] = _move_streamed(stream, rec, tmp)
            if isinstance(rec, Reconstruction):
                _write_outputs(tmp, rec, cube=cube, args=args, extra=extra, stages=stages)
            else:
                _write_streamed_summary(tmp, rec, extra, stages)
        if stream is not None and "store" in stream:
            shutil.rmtree(stream["folder"], ignore_errors=True)
    finally:
        stages.close()
    det = rec.detection
    c = cube
    args.json_summary = _json_result(out)
    _say(
        args,
        f"{inp}: {c.n_rows} x {c.n_cols} pixels, {c.n_wavelengths} wavelength(s), {c.n_bins} bins",
        f"{len(det.surfaces)} surfaces in {int(det.surfaces.n_slots)} layer(s); "
        f"{100 * det.reduction.voxel_fraction:.3g} % of voxels kept",
        *_scales_line(det),
        _timing_line(det, rec),
        f"outputs written to {out}/",
    )
    return EXIT_OK


def _run_key(args) -> str:
    """What makes two runs the same: the input file (path, size, time) and every option."""
    import hashlib

    st = Path(args.input).stat()
    skip = {"out", "force", "quiet", "verbose", "json", "workers", "scheduler", "memory_limit",
            "no_figures", "no_view", "func", "json_summary"}  # fmt: skip
    opts = {k: repr(v) for k, v in sorted(vars(args).items()) if k not in skip}
    text = json.dumps([str(Path(args.input).resolve()), st.st_size, st.st_mtime_ns, opts,
                       __version__])  # fmt: skip
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _move_streamed(stream: dict, rec, tmp: Path) -> dict:
    """Move the streamed points and maps into the staging folder; what summary.json says."""
    store = stream["store"]
    for name in ("points.parquet", "maps.zarr"):
        os.replace(stream["folder"] / name, tmp / name)
    return {
        "files": ["points.parquet/", "maps.zarr/"],
        "strips": [list(c) for c in store.manifest["cores"]],
        "strips_resumed": list(store.resumed),
        "detection_resumed": bool(stream.get("detection_resumed", False)),
    }


def _write_streamed_summary(tmp: Path, run, extra: dict, stages: _Stages) -> None:
    """summary.json of a run too large for the usual outputs (points and maps streamed)."""
    from . import export

    det = run.detection
    with stages.stage("writing points and maps"):
        summary = dict(extra)
        summary.update(
            versions=export._versions(),
            image_shape=list(det.image_shape), n_wavelengths=det.n_wavelengths,
            n_points=run.n_points, n_layers=int(det.surfaces.n_slots),
            timings_s={"detect": (det.timings or {}).get("total"), **run.timings},
            files=extra["streamed"]["files"] + ["summary.json"],
        )  # fmt: skip
        (tmp / "summary.json").write_text(json.dumps(_json_clean(summary), indent=2))


def _truth_path(out: Path) -> Path:
    name = out.name
    for ext in (".npz", ".zarr"):
        if name.endswith(ext):
            return out.with_name(name[: -len(ext)] + "-truth.npz")
    return out.with_name(name + "-truth.npz")


def _cmd_simulate(args) -> int:
    from . import scenes
    from .io import save

    out = Path(args.out)
    if not out.name.endswith((".npz", ".zarr")):
        raise UsageError(f"--out must end in .npz or .zarr; got '{out}'")
    truth_out = _truth_path(out)
    for f in (out, truth_out):
        if f.exists() and not args.force:
            raise UsageError(f"'{f}' exists; pass --force to replace it")
    kw: dict[str, Any] = {}
    if args.bins is not None:
        kw["n_bins"] = args.bins
    if args.irf_fwhm is not None:
        kw["irf"] = ("gaussian", args.irf_fwhm)
    if args.scene == "art":
        if not args.art_folder:
            raise UsageError("the art scene needs --art-folder DIR (view1.png, disp1.png)")
        scene = scenes.art_scene(args.art_folder, **kw)
    else:
        if args.art_folder:
            raise UsageError("--art-folder applies to the art scene only")
        shape = tuple(args.size)
        make = {
            "single": lambda: scenes.single_surface_scene(shape, **kw),
            "two-layer": lambda: scenes.two_layer_scene(shape, **kw),
            "multispectral": lambda: scenes.multispectral_scene(shape, **kw),
            "multispectral-two-layer": lambda: scenes.multispectral_scene(
                shape, two_layers=True, **kw
            ),
        }
        scene = make[args.scene]()
    sim = scene.simulate(ppp=args.ppp, sbr=args.sbr, background=args.background, rng=args.seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    # write beside the destination and rename, so that no half-written file remains
    for dest, write in ((out, lambda p: save(sim.cube, p)), (truth_out, sim.truth.save)):
        tmpdir = Path(tempfile.mkdtemp(prefix=f".{dest.name}.partial-", dir=dest.parent))
        try:
            tmp = tmpdir / dest.name
            write(tmp)
            if dest.is_dir() and not dest.is_symlink():
                shutil.rmtree(dest)
            os.replace(tmp, dest)
        finally:
            shutil.rmtree(tmpdir, ignore_errors=True)
    c = sim.cube
    args.json_summary = {
        "command": "simulate",
        "scene": scene.name,
        "cube": str(out),
        "truth": str(truth_out),
        "shape": list(c.shape),
        "true_surfaces": len(sim.truth),
        "ppp": sim.ppp,
        "sbr": sim.sbr,
        "seed": args.seed,
    }
    _say(
        args,
        f"simulated {scene.name}: {c.n_rows} x {c.n_cols} pixels, {c.n_wavelengths} "
        f"wavelength(s), {c.n_bins} bins, {len(sim.truth)} surfaces, PPP {sim.ppp:.3g}, "
        f"SBR {sim.sbr:.3g}",
        f"cube:  {out}",
        f"truth: {truth_out}",
    )
    return EXIT_OK


def read_points(path: str | os.PathLike):
    """Read a point set from a PointSet ``.npz``, a ``result.npz``, an output folder or a CSV.

    Raises
    ------
    SplidarError
        Missing file, or a file that holds no point set.
    """

    from .points import PointSet

    p = Path(path)
    if p.is_dir():
        if (p / "result.npz").is_file():
            p = p / "result.npz"
        else:
            raise SplidarError(f"folder '{p}' holds no result.npz of a splidar run")
    if not p.exists():
        raise SplidarError(f"file '{p}' does not exist")
    if p.suffix.lower() == ".csv":
        return _read_points_csv(p)
    from ._containers import _read_npz  # never unpickles; checks sizes before allocating

    z = _read_npz(p)  # its errors name the file and what is wrong with it
    if "row" in z:
        return PointSet.from_dict(z)
    if "points_row" in z:
        return PointSet.from_dict({k[7:]: v for k, v in z.items() if k.startswith("points_")})
    raise SplidarError(
        f"'{p}' holds no point set (arrays: {', '.join(list(z)[:8])}); pass a point set "
        ".npz, a result.npz or a points.csv"
    )


def _read_points_csv(p: Path):
    import numpy as np

    from .points import PointSet

    with open(p, encoding="ascii", errors="replace") as fh:
        header = fh.readline().strip().split(",")
    if header[:3] != ["row", "col", "depth_bin"]:
        raise SplidarError(
            f"'{p}' is not a points.csv of splidar (header starts {header[:3]}, expected "
            "row,col,depth_bin)"
        )
    with open(p, encoding="ascii", errors="replace") as fh:
        has_rows = bool(fh.readline()) and any(line.strip() for line in fh)
    if has_rows:
        data = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    else:  # a header only: no point (loadtxt would warn)
        data = np.zeros((0, len(header)))
    col = {name: data[:, i] for i, name in enumerate(header)}
    inten = [col[h] for h in header if h.startswith("intensity_") and "std" not in h]
    std = [col[h] for h in header if h.startswith("intensity_std_")]
    n_rows = int(col["row"].max()) + 1 if data.shape[0] else 1
    n_cols = int(col["col"].max()) + 1 if data.shape[0] else 1
    log.warning(
        "%s: a CSV does not record the image size; using %d x %d from the points",
        p,
        n_rows,
        n_cols,
    )
    return PointSet(
        row=col["row"].astype(np.int64),
        col=col["col"].astype(np.int64),
        depth_bin=col["depth_bin"],
        image_shape=(n_rows, n_cols),
        intensity=np.stack(inten, axis=1) if inten else None,
        label=col["label"].astype(np.int64) if "label" in col else None,
        depth_m=col.get("depth_m"),
        intensity_std=np.stack(std, axis=1) if std else None,
        label_confidence=col.get("label_confidence"),
        layer=col["layer"].astype(np.int64) if "layer" in col else None,
    )


def _cmd_evaluate(args) -> int:
    from .metrics import evaluate

    est = read_points(args.points)
    true = read_points(args.truth)
    if est.image_shape != true.image_shape:
        # a CSV guesses the image size from its points; adopt the truth's when it fits
        rows, cols = true.image_shape
        fits = len(est) == 0 or (est.row.max() < rows and est.col.max() < cols)
        if str(args.points).lower().endswith(".csv") and fits:
            from dataclasses import replace

            est = replace(est, image_shape=true.image_shape)
        else:
            raise SplidarError(
                f"POINTS have image size {est.image_shape} but TRUTH {true.image_shape}; "
                "they must come from the same scene"
            )
    m = evaluate(est, true, tau=args.tau, tau_m=args.tau_m)
    if args.json:
        print(json.dumps({k: _json_num(v) for k, v in m.as_dict().items()}, indent=2))
    else:
        print(str(m))
    return EXIT_OK


def _json_result(out: Path) -> dict[str, Any]:
    """``--json`` of run and demo: the output folder and its summary.json."""
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    return {"out": str(out), **summary}


def _json_num(v):
    import math

    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _write_view(rec, folder: Path, args) -> str:
    from .view import write_view

    title = folder.name.split(".partial-")[0].lstrip(".") or folder.name
    write_view(rec, folder / "view.html", pixel_size=getattr(args, "pixel_size", None), title=title)
    return "view.html"


def _load_kwargs(args) -> dict[str, Any]:
    """``splidar.load``'s keyword arguments from the input options."""
    load_kw = _given(
        args,
        ("variable", "bin_width", "time_unit", "irf_fwhm", "bin_width_ps", "channels", "time_axis")
        + ("wavelength_axis", "irf_variable", "irf_bin_width_ps"),
    )
    if getattr(args, "bin_width_m", None) is not None:  # range bin -> round-trip time
        load_kw["bin_width_ps"] = args.bin_width_m * 2.0 / 299_792_458.0 * 1e12
    if args.window is not None:
        load_kw["window"] = tuple(args.window)
    if args.irf is not None:
        load_kw["irf"] = args.irf
    if args.library is not None:
        load_kw["library"] = args.library
    return load_kw


def _file_variables(path: Path) -> dict[str, str]:
    """Name -> 'shape dtype' of every variable of a data file (Zarr: its arrays)."""
    import numpy as np

    from ._containers import _ext, _read_any

    if _ext(path) == ".zarr" or path.is_dir():
        import zarr

        try:
            g = zarr.open_group(str(path), mode="r")
        except Exception:
            a = zarr.open_array(str(path), mode="r")
            return {"(array)": f"{a.shape} {a.dtype}"}
        return {k: f"{g[k].shape} {g[k].dtype}" for k in sorted(g.array_keys())}
    out = {}
    for k, v in _read_any(path, None).items():
        if isinstance(v, np.ndarray):
            kind = "cell/object" if v.dtype == object else str(v.dtype)
            out[k] = f"{v.shape} {kind}"
        else:
            out[k] = type(v).__name__
    return out


def _cmd_info(args) -> int:
    import numpy as np

    from .io import load

    inp = Path(args.input)
    if not inp.exists():
        raise UsageError(f"no such file: '{inp}'")
    variables = _file_variables(inp)
    cube = load(inp, **_load_kwargs(args))
    md = cube.metadata
    bw = cube.bin_width_ps
    info: dict[str, Any] = {
        "command": "info",
        "input": str(inp),
        "variables": variables,
        "read_as": md.get("variable"),
        "shape": list(cube.shape),
        "dtype": str(cube.counts.dtype),
        "bin_width_ps": bw,
        "window": md.get("window"),
        "time_unit": md.get("time_unit"),
        "irf_samples": int(cube.irf.shape[1]),
        "irf_source": md.get("irf_source", "file"),
        "wavelengths_nm": None if cube.wavelengths_nm is None else list(cube.wavelengths_nm),
        "classes": None if cube.library is None else list(cube.library.class_names),
    }
    lines = [f"{inp}: holds"] + [f"  {k}: {v}" for k, v in variables.items()]
    r, c, n_wl, t = cube.shape
    if "photon_lists" in md:
        src = f", binned from the photons of {md['photon_lists']}"
        info["read_as"] = md["photon_lists"]
    else:
        src = f", from '{md['variable']}'" if "variable" in md else ""
    lines.append(
        f"read as: {r} x {c} pixels, {n_wl} wavelength(s), {t} time bins (rows, cols, L, T), "
        f"{cube.counts.dtype} counts{src}"
    )
    if not cube.is_lazy:
        n = int(cube.counts.sum(dtype=np.int64))
        info["photons"] = n
        lines.append(f"photons: {n} ({n / (r * c):.3g} per pixel)")
    if bw is None:
        lines.append("bin width: unknown (depths in bins; set --bin-width-ps or --time-unit)")
    else:
        lines.append(f"bin width: {bw:g} ps = {bw * 1e-12 * 299_792_458.0 / 2:.4g} m of range")
    if md.get("window") is not None:
        lines.append(f"window: {md['window']} ({md.get('time_unit', 'bin')})")
    lines.append(f"IRF: {cube.irf.shape[1]} samples, {info['irf_source']}")
    args.json_summary = info
    _say(args, *lines)
    return EXIT_OK


def _cmd_view(args) -> int:
    from .view import is_view_file, load_view_input, write_view

    src = Path(args.result)
    if args.out:
        dest = Path(args.out)
    elif src.is_dir():
        dest = src / "view.html"
    elif src.name == "result.npz":
        dest = src.parent / "view.html"
    else:
        dest = src.with_name(src.name.split(".")[0] + ".html")
    if dest.is_dir():
        raise UsageError(f"--out '{dest}' is a folder; give a file name such as view.html")
    if dest.exists() and not args.force and not is_view_file(dest):
        raise UsageError(
            f"'{dest}' exists and is not a view written by splidar; pass --force to replace "
            "it or choose another --out"
        )
    stages = _Stages(["reading the points", "writing the view"], args.quiet)
    try:
        with stages.stage("reading the points"):
            data = load_view_input(src)
        with stages.stage("writing the view"):
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_view(data, dest, pixel_size=args.pixel_size, color=args.color)
    finally:
        stages.close()
    opened = False
    if not args.no_open:
        import webbrowser

        opened = bool(webbrowser.open(dest.resolve().as_uri()))
        if not opened:
            log.warning("no browser found; open %s yourself", dest)
    args.json_summary = {
        "command": "view",
        "result": str(src),
        "view": str(dest),
        "points": len(data.points),
        "bytes": dest.stat().st_size,
        "opened": opened,
    }
    _say(args, str(dest))
    return EXIT_OK


_COMMANDS = {
    "demo": _cmd_demo,
    "run": _cmd_run,
    "simulate": _cmd_simulate,
    "evaluate": _cmd_evaluate,
    "view": _cmd_view,
    "info": _cmd_info,
}


# API parameter names that are also options of `splidar run`/`demo`; messages of the
# library name them as `name` or name=, which the CLI shows as --name.
_API_OPTIONS = (
    _DETECT_OPTS
    + _RECON_OPTS
    + ("window", "bin_width", "time_unit", "irf_fwhm", "bin_width_ps", "variable", "channels")
    + ("time_axis", "wavelength_axis", "irf_variable", "irf_bin_width_ps")
)
_NAME_RE = re.compile(
    r"`("
    + "|".join(_API_OPTIONS)
    + r")`|\b("
    + "|".join(_API_OPTIONS + ("irf", "library"))
    + r")=(?![\w\[\(])"
)


_QUOTED_RE = re.compile(
    r"\b(" + "|".join(_API_OPTIONS + ("irf", "library")) + r")=(?:'([^'\s]*)'|(-?\d[\d.e+-]*))"
)


# a library message's aside that only concerns a Python function the CLI never calls
_API_ONLY_RE = re.compile(r" \([^()]*\bwhen calling load_irf\)")


def _cli_names(msg: str) -> str:
    """Spell the API's parameter names as the command line's options (``irf='estimate'``
    as ``--irf estimate``, ``time_axis=0`` as ``--time-axis 0``)."""
    msg = _API_ONLY_RE.sub("", msg)  # e.g. "(variable= when calling load_irf)"
    msg = _QUOTED_RE.sub(
        lambda m: f"--{m.group(1).replace('_', '-')} {m.group(2) or m.group(3)}", msg
    )
    return _NAME_RE.sub(lambda m: "--" + (m.group(1) or m.group(2)).replace("_", "-"), msg)


def _one_line(exc: BaseException) -> str:
    msg = " ".join(str(exc).split())
    return _cli_names(msg) or type(exc).__name__


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``splidar`` command line; returns the exit status.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name (default ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success, 1 when the command failed, 2 for a usage error, 130 when
        interrupted, 143 when terminated.

    Examples
    --------
    >>> main(["--version"])  # doctest: +SKIP
    splidar 0.1.0
    0
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        print(f"{PROG}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except SystemExit as exc:  # --help, --version
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    verbose = args.verbose > 0
    with _json_output(args), _logging(args), _on_sigterm():
        try:
            return _COMMANDS[args.command](args)
        except UsageError as exc:
            _report(exc, verbose)
            return EXIT_USAGE
        except _Terminated:
            print(f"{PROG}: terminated; no output was written", file=sys.stderr)
            return EXIT_TERMINATED
        except KeyboardInterrupt:
            print(f"{PROG}: interrupted; no output was written", file=sys.stderr)
            return EXIT_INTERRUPTED
        except (SplidarError, ValueError, OSError, MemoryError) as exc:
            _report(exc, verbose)
            return EXIT_FAILURE
        except Exception as exc:  # noqa: BLE001 - the CLI never shows a raw traceback
            if _interrupted(exc):  # e.g. Ctrl-C inside a compiled module's import
                print(f"{PROG}: interrupted; no output was written", file=sys.stderr)
                return EXIT_INTERRUPTED
            _report(exc, verbose, unexpected=True)
            return EXIT_FAILURE


_JSON_COMMANDS = ("demo", "run", "simulate", "view", "info")


@contextmanager
def _json_output(args):
    """``--json``: the command's summary alone on stdout; what it prints goes to stderr.

    A command stores its summary as ``args.json_summary`` once it has succeeded; a failed
    command leaves stdout empty (the error is on stderr, the exit status non-zero).
    """
    if not (getattr(args, "json", False) and args.command in _JSON_COMMANDS):
        yield
        return
    from contextlib import redirect_stdout

    stdout = sys.stdout
    with redirect_stdout(sys.stderr):
        yield
    summary = getattr(args, "json_summary", None)
    if summary is not None:
        print(json.dumps(_json_clean(summary), indent=2, allow_nan=False), file=stdout)


def _json_clean(x):
    """JSON-ready copy: NaN and infinities become null, tuples lists."""
    if isinstance(x, dict):
        return {str(k): _json_clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_clean(v) for v in x]
    return _json_num(x)


def _interrupted(exc: BaseException) -> bool:
    """True when a KeyboardInterrupt caused ``exc`` (pybind11 imports wrap it in ImportError)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that the staged output folder is removed."""


@contextmanager
def _on_sigterm():
    """Turn SIGTERM into :class:`_Terminated` (and Ctrl-C into ``KeyboardInterrupt``)
    while a command runs (main thread only).

    A signal that lands while numba's LLVM layer is inside one of its ctypes callbacks
    (``llvmlite.binding``: loading or saving a cached kernel) is delivered a moment
    later (:func:`_deferred`): an exception raised inside a ctypes callback is printed
    with a traceback by ctypes and then lost, so the run would go on.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list = []
    handlers = {
        signal.SIGTERM: _deferred(_Terminated, pending),
        signal.SIGINT: _deferred(KeyboardInterrupt, pending),
    }
    if hasattr(signal, "setitimer"):  # POSIX: the deferred signal's retry
        handlers[signal.SIGALRM] = _retry(pending)
    old = {sig: signal.signal(sig, h) for sig, h in handlers.items()}
    try:
        yield
    finally:
        if hasattr(signal, "setitimer"):
            signal.setitimer(signal.ITIMER_REAL, 0)
        for sig, h in old.items():
            signal.signal(sig, h)


#: Seconds between the retries of a signal that landed inside an LLVM callback.
_RETRY_S = 0.02


def _inside_llvm(frame) -> bool:
    """True when ``frame`` or a caller runs ``llvmlite.binding`` code."""
    while frame is not None:
        if f"llvmlite{os.sep}binding" in frame.f_code.co_filename:
            return True
        frame = frame.f_back
    return False


def _deferred(exc_type, pending: list):
    """A signal handler raising ``exc_type``, or, inside an LLVM callback and where
    ``signal.setitimer`` exists, recording it in ``pending`` for :func:`_retry`."""
    import signal

    def handler(signum, frame):
        if hasattr(signal, "setitimer") and _inside_llvm(frame):
            pending.append(exc_type)
            signal.setitimer(signal.ITIMER_REAL, _RETRY_S)
            return
        raise exc_type()

    return handler


def _retry(pending: list):
    """The SIGALRM handler: raise the first pending signal's exception once outside
    LLVM's callbacks (else try again after :data:`_RETRY_S`)."""
    import signal

    def handler(signum, frame):
        if not pending:
            return
        if _inside_llvm(frame):
            signal.setitimer(signal.ITIMER_REAL, _RETRY_S)
            return
        exc_type = pending[0]
        pending.clear()
        raise exc_type()

    return handler


def entry() -> None:
    """The ``splidar`` program: :func:`main`, then exit with its status.

    A Ctrl-C that arrives after :func:`main` has returned (or while Python starts
    splidar) gives the same one line and status 130, never a traceback.
    """
    import signal

    try:
        code = main()
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; no output was written", file=sys.stderr)
        code = EXIT_INTERRUPTED
    # the work is over (the output is complete, or cleaned up): exit with `code`; a
    # SIGTERM arriving now would otherwise kill the process with status -15
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if code in (EXIT_INTERRUPTED, EXIT_TERMINATED):
        # An interrupt that landed inside an extension's PyRun_String while importing
        # marks it "unhandled" for good, and Python would then kill itself with SIGINT
        # at exit (status -2) although splidar handled it: leave directly instead.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def _report(exc: BaseException, verbose: bool, unexpected: bool = False) -> None:
    if verbose:
        traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
    msg = _one_line(exc)
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in msg:
        msg = f"{msg}: '{exc.filename}'"
    if isinstance(exc, MemoryError):
        msg = "out of memory; crop the data (--window) or process a smaller region"
    if unexpected:
        msg = f"unexpected {type(exc).__name__}: {msg}"
        if not verbose:
            msg += " (run with --verbose for the traceback)"
    print(f"{PROG}: error: {msg}", file=sys.stderr)
