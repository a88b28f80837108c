"""TCSPC vendor files through their maintained readers: PicoQuant ``.ptu``, Becker & Hickl ``.sdt``.

splidar does not parse these binary formats itself. It hands them to the readers the
vendors' users already rely on, both by Christoph Gohlke:

* ``.ptu`` (PicoQuant HydraHarp, PicoHarp, MultiHarp, TimeHarp T3 files) through
  `ptufile <https://pypi.org/project/ptufile/>`_: ``pip install 'splidar[ptu]'``.
* ``.sdt`` (Becker & Hickl SPCM "Setup & Data" files) through
  `sdtfile <https://pypi.org/project/sdtfile/>`_: ``pip install 'splidar[sdt]'``.

``pip install 'splidar[vendor]'`` installs both. :func:`splidar.load` and
:func:`splidar.io.load_irf` dispatch to this module by file suffix; the readers here
return the histograms and their bin width, and :func:`splidar.load` adds the IRF
(given, or estimated from the photons) to make a :class:`~splidar.cube.Cube`.

How the files map onto a cube ``(rows, cols, L, T)``:

* **T** (time bins): the TCSPC delay-time bins. The bin width is the file's TCSPC
  resolution (PTU ``MeasDesc_Resolution``; SDT ``tac_r / (tac_g * adc_re)``), in ps,
  rounded to 9 significant digits (PTU stores seconds as doubles; SDT's ``tac_r`` is a
  float32, so 7 digits there).
  A PTU histogram spans one laser period (``global_resolution / tcspc_resolution``
  bins, at most the record type's bin count).
* **rows, cols**: image-mode T3 files give ``(Y, X)`` pixels, frames summed (or one
  frame with ``frame=``). Line scans give one row per line, delimited by the file's
  line-start/stop markers (``(lines, X)``); point scans one row per pixel dwell time
  (``(n, 1)``). ptufile finds pixels, lines and frames from the file's markers.
  SDT image blocks give ``(scan_y, scan_x)``.
* **L** (channels): ``channels="wavelengths"`` (default) keeps each detector channel
  (PTU routing/input channels, trimmed of empty leading and trailing ones; SDT data
  blocks) as one spectral channel; ``channels="detectors"`` treats them as detectors
  of one wavelength and sums them (L = 1); an int or a sequence of ints keeps those
  channels (PTU hardware channel numbers, SDT block indices) as wavelengths.

Becker & Hickl ``.spc`` FIFO files are not read: sdtfile reads only ``.sdt``.
PicoQuant ``.phu`` histogram files hold no image: they are read as IRFs only
(:func:`read_vendor_irf`). T2 files (no delay times relative to a laser sync) are
refused with a message saying so.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._validation import SplidarError, check_int, describe

__all__ = [
    "VENDOR_SUFFIXES",
    "VendorHistograms",
    "read_ptu",
    "read_sdt",
    "read_vendor",
    "read_vendor_irf",
]

log = logging.getLogger(__name__)

#: File suffixes read by this module (lower case).
VENDOR_SUFFIXES = (".ptu", ".sdt", ".spc", ".phu")

_MAX_BYTES = 8 * 2**30  # as io: refuse to allocate a dense cube larger than 8 GiB


@dataclass(frozen=True)
class VendorHistograms:
    """Histograms read from a vendor file, before an IRF makes them a Cube.

    Attributes
    ----------
    counts : ndarray of unsigned int, shape (rows, cols, L, T)
        Photon counts (uint16, or uint32 when a bin exceeds 65535).
    bin_width_ps : float
        Width of one time bin, picoseconds (the TCSPC resolution).
    channels : tuple of int
        Hardware channel (PTU) or data block (SDT) of each of the L channels; empty
        when the channels were summed (``channels="detectors"``).
    metadata : mapping
        Source file, reader and version, acquisition settings read from the file.
    """

    counts: np.ndarray
    bin_width_ps: float
    channels: tuple[int, ...] = ()
    metadata: Mapping[str, Any] = field(default_factory=dict)


def _need(module: str, extra: str):
    try:
        return __import__(module)
    except ImportError:
        raise SplidarError(
            f"reading this file needs the optional package {module}: "
            f"pip install 'splidar[{extra}]' (or 'splidar[vendor]' for .ptu and .sdt)."
        ) from None


def _ps(seconds: float, digits: int = 9) -> float:
    """Seconds (a double, or a float32 in SDT files: 7 digits) to picoseconds, rounded."""
    return float(f"{float(seconds) * 1e12:.{digits}g}")


def _check_channels(channels):
    if isinstance(channels, str):
        if channels not in ("wavelengths", "detectors"):
            raise SplidarError(
                f"`channels` must be 'wavelengths', 'detectors', a channel number or a list of "
                f"them; got {channels!r}."
            )
        return channels
    if isinstance(channels, (int, np.integer)) and not isinstance(channels, bool):
        return (check_int(channels, "channels", minimum=0),)
    try:
        out = tuple(check_int(c, "channels", minimum=0) for c in channels)
    except TypeError:
        raise SplidarError(
            "`channels` must be 'wavelengths', 'detectors', a channel number or a list of "
            f"them; got {describe(channels)}."
        ) from None
    if not out:
        raise SplidarError("`channels` must not be an empty list.")
    return out


def _select(counts: np.ndarray, ids: tuple[int, ...], channels, p: Path):
    """Apply the ``channels`` choice to ``counts`` (rows, cols, C, T) with channel ``ids``."""
    if channels == "wavelengths":
        return counts, ids
    if channels == "detectors":
        total = counts.sum(axis=2, keepdims=True, dtype=np.uint64)
        return total, ()
    missing = [c for c in channels if c not in ids]
    if missing:
        raise SplidarError(
            f"`channels` {list(channels)} asks for channel(s) {missing} that '{p.name}' does "
            f"not hold; it holds channels {list(ids)}."
        )
    return counts[:, :, [ids.index(c) for c in channels]], tuple(channels)


def _compact(counts: np.ndarray) -> np.ndarray:
    mx = int(counts.max()) if counts.size else 0
    dtype = np.uint16 if mx <= np.iinfo(np.uint16).max else np.uint32
    return np.ascontiguousarray(counts, dtype=dtype)


# --------------------------------------------------------------------------------------
# PicoQuant
# --------------------------------------------------------------------------------------
def _open_ptu(p: Path):
    ptufile = _need("ptufile", "ptu")
    try:
        f = ptufile.PtuFile(p)
    except Exception as exc:
        raise SplidarError(f"ptufile cannot read '{p}' as a PicoQuant PTU file: {exc}") from None
    if not f.is_t3:
        mode = f.measurement_mode
        f.close()
        raise SplidarError(
            f"'{p.name}' is a {getattr(mode, 'name', mode)} file: only T3 files hold delay "
            "times relative to the laser sync, which splidar histograms. Record in T3 mode."
        )
    return ptufile, f


def _ptu_bins(f) -> int:
    """Bins of one laser period, at most the record type's range (never fewer than used)."""
    n = min(int(f.number_bins_in_period), int(f.number_bins_max))
    return max(n, int(f.number_bins))


def read_ptu(
    path: str | os.PathLike, *, channels="wavelengths", frame: int | None = None
) -> VendorHistograms:
    """Read a PicoQuant T3 ``.ptu`` file (image, line or point scan) with ptufile.

    Parameters
    ----------
    path : str or path-like
        A T3 ``.ptu`` file.
    channels : {"wavelengths", "detectors"}, int or sequence of int
        How the file's channels become the cube's L axis (see the module notes):
        each its own wavelength (default), summed as detectors of one wavelength, or
        only the given hardware channel numbers.
    frame : int, optional
        Image-mode files: read only this frame (0-based). Default: all frames summed.

    Returns
    -------
    VendorHistograms
        ``counts`` ``(rows, cols, L, T)`` with T the bins of one laser period.

    Raises
    ------
    SplidarError
        ptufile missing (names the extra ``splidar[ptu]``), not a PTU file, a T2 file,
        unknown channels, a frame out of range, or a cube larger than 8 GiB.

    Examples
    --------
    >>> h = read_ptu("scan.ptu")  # doctest: +SKIP
    >>> h.counts.shape, h.bin_width_ps  # doctest: +SKIP
    ((256, 256, 2, 3126), 16.0)
    """
    p = Path(path)
    channels = _check_channels(channels)
    ptufile, f = _open_ptu(p)
    with f:
        dims = f.dims
        shape = f.shape
        n_bins = _ptu_bins(f)
        first = min(f.active_channels) if f.active_channels else 0
        ids = tuple(range(first, first + shape[dims.index("C")]))
        sel = {}
        if dims[0] == "T" and "Y" in dims:
            if frame is None:
                sel["frame"] = -1
            else:
                frame = check_int(frame, "frame", minimum=0)
                if frame >= shape[0]:
                    raise SplidarError(
                        f"`frame` {frame} is out of range: '{p.name}' holds {shape[0]} frame(s)."
                    )
                sel["frame"] = frame
        elif frame is not None:
            raise SplidarError(f"`frame` applies to image-mode files; '{p.name}' is not one.")
        kept_axes = shape[1:-1] if "Y" in dims else shape[:-1]  # frames are summed
        nbytes = int(np.prod(kept_axes)) * n_bins * 4  # decoded as uint32
        if nbytes > _MAX_BYTES:
            raise SplidarError(
                f"'{p.name}' would decode to {nbytes / 2**30:.1f} GiB ({shape} x {n_bins} bins); "
                "read one channel (channels=) or one frame (frame=)."
            )
        a = np.asarray(f.decode_image(dtime=n_bins, dtype=np.uint32, keepdims=True, **sel))
        if "Y" in dims:  # (T=1, Y, X, C, H): frames summed or one chosen
            counts = a[0]
        elif len(dims) == 4:  # line scan (lines, X, C, H): one row per line
            counts = a
        else:  # point scan (n, C, H): one row per pixel dwell time
            counts = a[:, None]
        info = {
            "reader": f"ptufile {ptufile.__version__}",
            "source": str(p),
            "record_type": getattr(f.record_type, "name", str(f.record_type)),
            "measurement": {3: "image", 2: "line scan"}.get(f.measurement_ndim, "point scan"),
            "frames_in_file": int(shape[0]) if "Y" in dims else None,
            "frame": sel.get("frame") if sel.get("frame", -1) >= 0 else "all (summed)",
            "tcspc_resolution_s": float(f.tcspc_resolution),
            "global_resolution_s": float(f.global_resolution),
            "pixel_time_s": float(f.pixel_time),
            "channel_ids": list(ids),
        }
        bw = _ps(f.tcspc_resolution)
    counts, kept = _select(counts, ids, channels, p)
    info["channels"] = channels if isinstance(channels, str) else list(channels)
    return VendorHistograms(_compact(counts), bw, kept, info)


# --------------------------------------------------------------------------------------
# Becker & Hickl
# --------------------------------------------------------------------------------------
def _open_sdt(p: Path):
    sdtfile = _need("sdtfile", "sdt")
    try:
        return sdtfile, sdtfile.SdtFile(p)
    except Exception as exc:
        raise SplidarError(
            f"sdtfile cannot read '{p}' as a Becker & Hickl SDT file: {exc}"
        ) from None


def _sdt_bin_ps(sdt, i: int) -> float | None:
    t = np.asarray(sdt.times[i], dtype=np.float64)
    if t.size < 2 or not t[1] > t[0]:
        return None
    return _ps(t[1] - t[0], 7)  # tac_r is stored as float32


def read_sdt(path: str | os.PathLike, *, channels="wavelengths") -> VendorHistograms:
    """Read the image data blocks of a Becker & Hickl ``.sdt`` file with sdtfile.

    Every 3-D data block ``(scan_y, scan_x, adc_re)`` is one channel (detector or
    routing channel); all must have the same shape and bin width.

    Parameters
    ----------
    path : str or path-like
        A ``.sdt`` "SPC Setup & Data" (or FCS / DLL data) file.
    channels : {"wavelengths", "detectors"}, int or sequence of int
        How the image blocks become the cube's L axis: each its own wavelength
        (default), summed (L = 1), or only the given block indices.

    Returns
    -------
    VendorHistograms

    Raises
    ------
    SplidarError
        sdtfile missing (names the extra ``splidar[sdt]``), not an SDT file, no image
        block (the message lists the blocks' shapes), blocks of different shapes or bin
        widths, unknown channels.

    Examples
    --------
    >>> h = read_sdt("flim.sdt")  # doctest: +SKIP
    >>> h.counts.shape  # doctest: +SKIP
    (128, 128, 1, 256)
    """
    p = Path(path)
    channels = _check_channels(channels)
    sdtfile, sdt = _open_sdt(p)
    with sdt:
        shapes = [np.shape(d) for d in sdt.data]
        ids = tuple(i for i, s in enumerate(shapes) if len(s) == 3)
        if not ids:
            raise SplidarError(
                f"'{p.name}' holds no image data block (rows, cols, bins); its blocks have "
                f"shapes {shapes}. Decay-curve blocks can serve as an IRF (load_irf)."
            )
        if len({shapes[i] for i in ids}) > 1:
            raise SplidarError(
                f"the image blocks of '{p.name}' differ in shape ({[shapes[i] for i in ids]}); "
                "pick blocks of one shape with channels=[...]."
            )
        widths = {_sdt_bin_ps(sdt, i) for i in ids}
        if len(widths) > 1:
            raise SplidarError(f"the image blocks of '{p.name}' differ in bin width: {widths}.")
        counts = np.stack([np.asarray(sdt.data[i]) for i in ids], axis=2)
        mi = sdt.measure_info[int(sdt.block_headers[ids[0]].meas_desc_block_no)]
        info = {
            "reader": f"sdtfile {sdtfile.__version__}",
            "source": str(p),
            "file_id": str(getattr(sdt.info, "id", "")),
            "adc_re": int(mi.adc_re),
            "tac_r_s": float(mi.tac_r),
            "tac_g": float(mi.tac_g),
            "channel_ids": list(ids),
            "blocks": len(shapes),
        }
    bw = widths.pop()
    if bw is None:
        raise SplidarError(
            f"'{p.name}' records no TAC range and gain (tac_r, tac_g): the bin width is "
            "unknown. Pass bin_width_ps= to splidar.load."
        )
    counts, kept = _select(counts, ids, channels, p)
    info["channels"] = channels if isinstance(channels, str) else list(channels)
    return VendorHistograms(_compact(counts), bw, kept, info)


def _phu_curves(p: Path) -> np.ndarray:
    """The curves of a PicoQuant .phu histogram file, ``(n_curves, bins)`` float64."""
    ptufile = _need("ptufile", "ptu")
    try:
        with ptufile.PhuFile(p) as f:
            curves = [np.asarray(h, dtype=np.float64) for h in f.histograms()]
    except Exception as exc:
        raise SplidarError(f"ptufile cannot read '{p}' as a PicoQuant PHU file: {exc}") from None
    lengths = sorted({c.size for c in curves})
    if len(lengths) != 1:
        raise SplidarError(
            f"the curves of '{p.name}' have different lengths {lengths}; an IRF needs one."
        )
    return np.stack(curves)


# --------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------
def _refuse(p: Path) -> None:
    ext = p.suffix.lower()
    if ext == ".spc":
        raise SplidarError(
            f"'{p.name}': Becker & Hickl .spc FIFO (photon stream) files are not read: sdtfile "
            "reads .sdt only. Export the measurement as .sdt from SPCM, or bin the photons "
            "yourself and pass the histograms (rows, cols[, L], T) as .npy/.npz."
        )
    if ext == ".phu":
        raise SplidarError(
            f"'{p.name}': PicoQuant .phu histogram files hold no image (record images in T3 "
            "mode, .ptu); a .phu curve can serve as the IRF (irf= / --irf)."
        )


def read_vendor(path: str | os.PathLike, *, channels="wavelengths") -> VendorHistograms:
    """Read a vendor file by its suffix (``.ptu``: :func:`read_ptu`; ``.sdt``: :func:`read_sdt`).

    Raises
    ------
    SplidarError
        A suffix other than ``.ptu``/``.sdt`` (``.spc`` and ``.phu`` are refused with the
        reason), or what the reader raises.

    Examples
    --------
    >>> import splidar
    >>> h = read_vendor("scan.ptu")  # doctest: +SKIP
    >>> cube = splidar.Cube(h.counts, irf=read_vendor_irf("irf.ptu"),
    ...                     bin_width_ps=h.bin_width_ps)  # doctest: +SKIP
    """
    p = Path(path)
    _refuse(p)
    ext = p.suffix.lower()
    if ext == ".ptu":
        return read_ptu(p, channels=channels)
    if ext == ".sdt":
        return read_sdt(p, channels=channels)
    raise SplidarError(f"'{p.name}' is not a vendor file splidar reads (.ptu, .sdt).")


def read_vendor_irf(path: str | os.PathLike) -> np.ndarray:
    """An IRF ``(L, n)`` from a vendor file: its histograms summed over all pixels.

    A measured IRF is often recorded like the data, on a reference target: ``.ptu``
    (every pixel and frame, one row per channel), ``.sdt`` (every data block, image
    or single decay curve, summed over its pixels; one row per block, all of one
    length) or a PicoQuant histogram-mode ``.phu`` file (one row per curve). Record it
    at the TCSPC resolution of the data: the IRF is used bin for bin.

    Returns
    -------
    irf : ndarray, shape (L, n), float64

    Raises
    ------
    SplidarError
        Reader missing (names the extra), unreadable file, SDT blocks of different
        lengths.

    Examples
    --------
    >>> irf = read_vendor_irf("irf_reference.ptu")  # doctest: +SKIP
    >>> irf.shape  # one row per channel  # doctest: +SKIP
    (4, 4096)
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".phu":
        return _phu_curves(p)
    _refuse(p)
    if ext == ".ptu":
        h = read_ptu(p)
        return h.counts.sum(axis=(0, 1), dtype=np.float64)
    if ext == ".sdt":
        _, sdt = _open_sdt(p)
        with sdt:
            curves = [np.asarray(d, dtype=np.float64) for d in sdt.data]
        lengths = {c.shape[-1] for c in curves}
        if len(lengths) != 1:
            raise SplidarError(
                f"the data blocks of '{p.name}' have different lengths {sorted(lengths)}; "
                "an IRF needs one length."
            )
        return np.stack([c.reshape(-1, c.shape[-1]).sum(axis=0) for c in curves])
    raise SplidarError(f"'{p.name}' is not a vendor IRF file splidar reads (.ptu, .sdt, .phu).")
