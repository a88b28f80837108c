"""Private memory guard: refuse an allocation that cannot fit before making it.

The operating system kills a process that asks for more memory than it has (or the
machine swaps for minutes); neither tells the user what to change. Before each large
allocation (reading a file, binning photon lists, detection, reconstruction) splidar
estimates the peak from the shapes and dtypes and compares it with the memory
available now: ``MemAvailable`` of ``/proc/meminfo`` on Linux, ``os.sysconf``
elsewhere. ``SPLIDAR_MEMORY_LIMIT`` (bytes, or with a suffix K, M, G, T: ``"2G"``)
sets a lower ceiling, e.g. on a shared machine or in a test.

Also glibc's allocator, where splidar's passes free much memory or allocate many large
temporaries: :func:`give_back` returns the freed heap pages to the system;
:func:`keep_freed_memory` lets a block's temporaries reuse freed pages in a process whose
environment fixed malloc's thresholds (a Dask worker).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading

from ._validation import SplidarError

__all__ = [
    "available_bytes",
    "check_detect_memory",
    "check_memory",
    "detect_peak_bytes",
    "format_bytes",
    "give_back",
    "hold_freed_memory",
    "keep_freed_memory",
    "reconstruct_peak_bytes",
    "small_pages",
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


#: glibc's ``mallopt`` parameter for the mmap threshold (``malloc.h``).
M_MMAP_THRESHOLD = -3

#: The mmap threshold when the environment fixes a malloc setting but not this one
#: (glibc's ``DEFAULT_MMAP_THRESHOLD_MIN``, 128 KiB).
_MALLOC_DEFAULT = 128 * 1024

#: The environment variables that fix glibc's malloc thresholds (and so turn off its
#: dynamic mmap threshold); Dask's nanny starts every worker with
#: ``MALLOC_TRIM_THRESHOLD_=65536`` (``distributed.nanny.pre-spawn-environ``).
_MALLOC_ENV = (
    "MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_",
)  # fmt: skip

#: The mmap threshold inside :func:`keep_freed_memory`: a reconstruction strip's
#: per-surface arrays (1.9 MB for 233,000 surfaces in float64 at one wavelength) come
#: from the heap, larger ones are still mapped apart.
KEEP_MMAP_THRESHOLD = 4 * 2**20

#: glibc's ``mallopt`` parameters for the most mappings apart and the trim threshold.
M_MMAP_MAX, M_TRIM_THRESHOLD = -4, -1

#: glibc's default ``M_MMAP_MAX`` (``DEFAULT_MMAP_MAX``).
_MMAP_MAX_DEFAULT = 65536

#: The trim threshold inside :func:`keep_freed_memory` with ``any_size`` (1 GiB: a
#: task's freed heap top stays until the block's end gives it back).
KEEP_TRIM_THRESHOLD = 2**30

#: The trim threshold :func:`hold_freed_memory` leaves in a process whose environment
#: fixed no malloc setting: twice glibc's largest dynamic mmap threshold (32 MiB), the
#: value its dynamic rule sets once a freed mapping raised the threshold that far.
_DYNAMIC_TRIM_THRESHOLD = 2 * 32 * 2**20

_KEEP_LOCK = threading.Lock()
_keep_state = {"depth": 0, "restore": None, "any": 0, "restore_any": None}


@functools.cache
def _mallopt():
    """glibc's ``mallopt``, or None (another C library, another system)."""
    import ctypes
    import ctypes.util
    import platform

    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return None
    fn.argtypes, fn.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return fn


def fixed_mmap_threshold(environ=None) -> int | None:
    """glibc's mmap threshold in bytes as the environment fixed it when the process
    started, or None when it fixed no malloc setting (glibc then raises the threshold to
    the size of the blocks freed, up to 32 MiB, by itself) or when it is not known
    (``GLIBC_TUNABLES`` naming malloc, a value that is not an integer).

    Parameters
    ----------
    environ : mapping, optional
        The process's environment (default ``os.environ``).
    """
    env = os.environ if environ is None else environ
    if "glibc.malloc." in env.get("GLIBC_TUNABLES", "") or not any(k in env for k in _MALLOC_ENV):
        return None
    try:
        return int(env.get("MALLOC_MMAP_THRESHOLD_", _MALLOC_DEFAULT))
    except ValueError:
        return None


@contextlib.contextmanager
def keep_freed_memory(*, any_size: bool = False, _dynamic: bool = False):
    """Within the block, arrays up to :data:`KEEP_MMAP_THRESHOLD` reuse freed memory.

    A process started with a malloc setting fixed in its environment (a Dask worker: its
    nanny sets ``MALLOC_TRIM_THRESHOLD_=65536``) has glibc's dynamic mmap threshold off:
    every allocation of 128 KiB or more is a fresh ``mmap``, unmapped when freed, so each
    NumPy temporary of a reconstruction strip is new memory, a page fault per 4 KiB (on
    the VMs measured, the first touch of a page costs several times its use:
    ``benchmarks/README.md``, rec41). Inside the block the threshold is raised to
    :data:`KEEP_MMAP_THRESHOLD` (never lowered), so those temporaries come from the heap
    and reuse the pages freed before them; on leaving the outermost block it is set back
    to the environment's value and the freed pages are returned to the system
    (:func:`give_back`): between blocks the process holds what it held before (a Dask
    worker's memory monitor spills its data when the process's resident memory passes
    70 % of its limit). Nothing is done in a process whose thresholds the environment
    did not fix (glibc adapts by itself), or without glibc. Threads may nest and overlap
    blocks: the first in sets, the last out restores. No effect on any result.

    Parameters
    ----------
    any_size : bool
        Also temporaries of any size reuse freed memory: inside the block glibc maps
        nothing apart (``M_MMAP_MAX`` 0) and keeps the freed top of its heap
        (``M_TRIM_THRESHOLD`` raised), both set back with the rest. For a task whose
        temporaries are tens of MB (a map-pass tile's per-voxel arrays), where the
        block's end returns what the task freed.
    """
    with _KEEP_LOCK:
        if _keep_state["depth"] == 0:
            _keep_state["restore"] = _raise_mmap_threshold()
        _keep_state["depth"] += 1
        if any_size:
            if _keep_state["any"] == 0:
                _keep_state["restore_any"] = _map_nothing_apart(_dynamic)
            _keep_state["any"] += 1
    try:
        yield
    finally:
        with _KEEP_LOCK:
            if any_size:
                _keep_state["any"] -= 1
                if _keep_state["any"] == 0 and _keep_state["restore_any"] is not None:
                    for param, value in _keep_state["restore_any"]:
                        _mallopt()(param, value)
                    _keep_state["restore_any"] = None
                    # (leaving the outermost block with a raised threshold gives back below)
                    if _keep_state["depth"] > 1 or _keep_state["restore"] is None:
                        give_back()
            _keep_state["depth"] -= 1
            if _keep_state["depth"] == 0 and _keep_state["restore"] is not None:
                _mallopt()(M_MMAP_THRESHOLD, _keep_state["restore"])
                _keep_state["restore"] = None
                give_back()


@contextlib.contextmanager
def hold_freed_memory():
    """Within the block, freed memory of any size is reused, in any process: the calling
    process's image-wide work for a Dask cube (the map pass's gathered tables joined,
    stages 5-7).

    :func:`keep_freed_memory` with ``any_size`` where the environment fixed malloc's
    thresholds; in a process where it did not (glibc's dynamic threshold: arrays over
    32 MiB are mapped apart, each a fresh mapping, a page fault per page), glibc maps
    nothing apart and keeps its freed heap top inside the block too, and at its end
    ``M_MMAP_MAX`` goes back to glibc's default and ``M_TRIM_THRESHOLD`` to
    :data:`_DYNAMIC_TRIM_THRESHOLD` (glibc cannot turn its dynamic rule back on: the mmap
    threshold stays at the value the rule reached), the freed pages given back. The
    explicit :func:`give_back` calls inside the block still return what was freed. On
    issue #16's cluster run the calling process's stages 5-7 took 19.1-19.7 s against
    19.4-21.4 s without (four runs each; ``clear_page_erms`` 8 % of its CPU there against
    17 %: "Lead, session 30" in ``benchmarks/README.md``). No effect on any result."""
    with keep_freed_memory(any_size=True, _dynamic=True), small_pages():
        yield


#: NumPy's environment variable for its transparent-huge-page advice (read at import).
HUGEPAGE_ENV = "NUMPY_MADVISE_HUGEPAGE"


def _hugepage_switch():
    """NumPy's switch of its huge-page advice (``_set_madvise_hugepage``, private; the
    public form is :data:`HUGEPAGE_ENV`), or None where NumPy has none."""
    for where in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            module = __import__(where, fromlist=["_set_madvise_hugepage"])
        except ImportError:
            continue
        switch = getattr(module, "_set_madvise_hugepage", None)
        if switch is not None:
            return switch
    return None


_PAGES_LOCK = threading.Lock()
_PAGES_DEPTH = [0, None]  # blocks open, NumPy's advice before the first


@contextlib.contextmanager
def small_pages():
    """Within the block NumPy does not advise transparent huge pages for its new arrays
    (``madvise(MADV_HUGEPAGE)``, which it does by default for arrays of 4 MiB or more
    on Linux); outside, its advice as before. Nothing changes where the environment
    names :data:`HUGEPAGE_ENV` (the user's choice) or NumPy has no switch.

    For a block whose arrays are mostly made once: a huge page is faulted in from a free
    2 MiB block, and on a virtual machine whose balloon reports free pages to its host
    (``virtio_balloon`` free page reporting) these are the blocks the host took back,
    so each one costs a fault and a zeroing on the host too. Measured on this project's
    build machines: a 1 GiB array filled for the first time 0.6-2.2 s with the advice
    (0.06 s when the huge pages were freed less than a second before), 0.35-0.44 s
    without; a warm in-memory run, reusing its pages, 3-5 % faster with the advice. The
    calling process of a Dask run makes its image-wide arrays once (issue #16's run: a
    2.4 GB peak), so :func:`hold_freed_memory` opens this block: "Lead, session 31" in
    ``benchmarks/README.md``. No effect on any result."""
    switch = None if HUGEPAGE_ENV in os.environ else _hugepage_switch()
    if switch is None:
        yield
        return
    with _PAGES_LOCK:
        if _PAGES_DEPTH[0] == 0:
            _PAGES_DEPTH[1] = bool(switch(False))
        _PAGES_DEPTH[0] += 1
    try:
        yield
    finally:
        with _PAGES_LOCK:
            _PAGES_DEPTH[0] -= 1
            if _PAGES_DEPTH[0] == 0:
                switch(_PAGES_DEPTH[1])


def _map_nothing_apart(dynamic: bool = False) -> tuple | None:
    """``M_MMAP_MAX`` set to 0 and ``M_TRIM_THRESHOLD`` raised to
    :data:`KEEP_TRIM_THRESHOLD` (:func:`keep_freed_memory` with ``any_size``): the
    ``(parameter, value to set back)`` pairs, or None when nothing was changed (the
    environment fixed no malloc setting and not ``dynamic``, or no glibc)."""
    fixed, env = fixed_mmap_threshold(), os.environ
    untouched = "glibc.malloc." not in env.get("GLIBC_TUNABLES", "") and not any(
        k in env for k in _MALLOC_ENV
    )  # glibc's dynamic threshold
    if fixed is None and not (dynamic and untouched):
        return None
    mallopt = _mallopt()
    if mallopt is None:
        return None
    try:
        before = (
            (M_MMAP_MAX, int(env.get("MALLOC_MMAP_MAX_", _MMAP_MAX_DEFAULT))),
            (M_TRIM_THRESHOLD, int(env.get("MALLOC_TRIM_THRESHOLD_", _MALLOC_DEFAULT))),
        )
    except ValueError:
        return None
    if fixed is None:  # the dynamic threshold's process (hold_freed_memory): no env values
        before = ((M_MMAP_MAX, _MMAP_MAX_DEFAULT), (M_TRIM_THRESHOLD, _DYNAMIC_TRIM_THRESHOLD))
    done = []
    for (param, _), value in zip(before, (0, KEEP_TRIM_THRESHOLD), strict=True):
        if mallopt(param, value) != 1:
            break
        done.append(before[len(done)])
    if len(done) < len(before):  # refused: what was set goes back
        for param, value in done:
            mallopt(param, value)
        return None
    return before


def _raise_mmap_threshold() -> int | None:
    """Raise glibc's mmap threshold (:func:`keep_freed_memory`); its value before, or
    None when left as it is."""
    fixed = fixed_mmap_threshold()
    mallopt = _mallopt() if fixed is not None else None
    if mallopt is None or KEEP_MMAP_THRESHOLD <= fixed:
        return None
    return fixed if mallopt(M_MMAP_THRESHOLD, KEEP_MMAP_THRESHOLD) == 1 else None
