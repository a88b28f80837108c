"""Private memory guard: refuse an allocation that cannot fit before making it.

The operating system kills a process that asks for more memory than it has (or the
machine swaps for minutes); neither tells the user what to change. Before each large
allocation (reading a file, binning photon lists, detection, reconstruction) splidar
estimates the peak from the shapes and dtypes and compares it with the memory
available now: ``MemAvailable`` of ``/proc/meminfo`` on Linux, ``os.sysconf``
elsewhere. ``SPLIDAR_MEMORY_LIMIT`` (bytes, or with a suffix K, M, G, T: ``"2G"``)
sets a lower ceiling, e.g. on a shared machine or in a test.
"""

from __future__ import annotations

import functools
import os

from ._validation import SplidarError

__all__ = [
    "available_bytes",
    "check_detect_memory",
    "check_memory",
    "detect_peak_bytes",
    "format_bytes",
    "give_back",
    "reconstruct_peak_bytes",
]

#: Environment variable capping the memory splidar plans to use.
LIMIT_ENV = "SPLIDAR_MEMORY_LIMIT"

_SUFFIX = {"": 1, "B": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def format_bytes(n: float) -> str:
    """``1.5 GiB``-style figure."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _env_limit() -> int | None:
    text = os.environ.get(LIMIT_ENV, "").strip().upper().removesuffix("IB")
    if not text:
        return None
    unit = text[-1] if text[-1] in _SUFFIX else ""
    try:
        value = float(text[: len(text) - len(unit)] if unit else text)
    except ValueError:
        raise SplidarError(
            f"{LIMIT_ENV}={os.environ[LIMIT_ENV]!r} is not a size; use bytes or a number "
            "with K, M, G or T (e.g. 2G)."
        ) from None
    return int(value * _SUFFIX[unit])


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return None


def available_bytes() -> int | None:
    """Memory splidar may use now, bytes (``None`` when unknown)."""
    found = [v for v in (_meminfo_available(), _env_limit()) if v is not None]
    return min(found) if found else None


def check_memory(nbytes: float, what: str, way_out: str) -> None:
    """Raise :class:`SplidarError` when ``nbytes`` exceed the available memory.

    Parameters
    ----------
    nbytes : float
        Estimated peak of the step, bytes.
    what : str
        The step, e.g. ``"reading 'scan.npz'"``.
    way_out : str
        What the user can change (a Zarr cube, ``--window``, a crop, ``--jobs``).
    """
    avail = available_bytes()
    if avail is None or nbytes <= avail:
        return
    raise SplidarError(
        f"{what} needs about {format_bytes(nbytes)} of memory but {format_bytes(avail)} "
        f"is available; {way_out}."
    )


def detect_peak_bytes(shape) -> int:
    """Estimated peak memory of :func:`splidar.detect` on an in-memory cube, bytes.

    Measured (``ru_maxrss``) on simulated cubes: about 12 bytes per pooled voxel
    (rows x cols x T: the float32 multiscale working cubes and the detection map)
    plus 8 per voxel of each wavelength (rows x cols x L x T).
    """
    rows, cols, n_l, n_bins = (int(s) for s in shape)
    return 12 * rows * cols * n_bins + 8 * rows * cols * n_l * n_bins


def reconstruct_peak_bytes(n_surfaces: int, n_wavelengths: int, n_classes: int) -> int:
    """Estimated peak memory of :func:`splidar.reconstruct`, bytes (per surface arrays)."""
    return 64 * int(n_surfaces) * (16 + int(n_wavelengths) * (1 + int(n_classes)))


def check_detect_memory(cube, *, store=None) -> None:
    """Refuse a :func:`splidar.detect` on ``cube`` that cannot fit in the free memory.

    One call at the entry of ``detect`` (the CLI makes it before calling). Lazy cubes
    detected into a ``store`` are processed chunk by chunk and not checked.
    """
    if cube.is_lazy and store:
        return
    rows, cols, _, n_bins = cube.shape
    check_memory(
        detect_peak_bytes(cube.shape),
        f"detection on {rows} x {cols} pixels x {n_bins} bins",
        "process a crop (a smaller region, or --window START STOP over the bins), or save "
        "the cube as Zarr (splidar.io.save(cube, 'cube.zarr')) and detect it with a store "
        "(store='det.zarr' in Python, --store DIR on the command line)",
    )


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None (another C library, another system)."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim
    except (OSError, AttributeError, TypeError):
        return None


def give_back() -> None:
    """Return the freed heap pages to the system (glibc keeps them otherwise: arrays
    below its mmap threshold, up to 32 MB, and those the map pass's threads allocate in
    their own arenas stay in the process's resident memory once freed). Called where a
    detection has just released much memory (the pages of a Dask cube's candidate table
    between passes, the map's per-block histograms in stage 6): the resident memory then
    follows what the process holds. No effect on any result."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
