"""Timing and peak-memory helpers shared by the benchmark scripts.

Two independent peak-memory probes, because neither sees everything:

* ``tracemalloc`` sees every NumPy buffer (NumPy reports its allocations to it) and
  every Python object, but not memory allocated by compiled code outside Python's
  allocators (numba's runtime, FFT scratch buffers, BLAS).
* The resident set size (RSS) of the process sees everything the kernel maps, but only
  pages that were actually touched. Its high-water mark (``VmHWM`` in
  ``/proc/self/status``) is reset by writing ``5`` to ``/proc/self/clear_refs``
  (Linux >= 4.0). Where that is not allowed, a thread samples ``VmRSS`` every
  millisecond instead (it can miss short peaks).

Both are reported *above* the memory in use when the measurement starts (the input
cube already exists then), which is what "peak memory above the input" means.
"""

from __future__ import annotations

import gc
import os
import statistics
import threading
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

__all__ = ["MemoryPeak", "Timing", "cpu_count", "measure_memory", "rss_bytes", "time_call"]

_STATUS = "/proc/self/status"


@dataclass(frozen=True)
class Timing:
    """Wall-clock times of repeated calls, seconds, and the CPU time of each call.

    CPU time (all threads of the process) is less sensitive than wall time to other
    processes sharing the machine; with several threads it exceeds wall time.
    """

    times: tuple[float, ...]
    cpu: tuple[float, ...] = ()
    result: Any = field(default=None, repr=False, compare=False)

    @property
    def best(self) -> float:
        return min(self.times)

    @property
    def median(self) -> float:
        return statistics.median(self.times)


@dataclass(frozen=True)
class MemoryPeak:
    """Peak memory of one call above the memory in use when it started, bytes.

    ``rss`` is the kernel's view (touched pages, everything); ``traced`` is
    tracemalloc's (NumPy and Python allocations only). ``rss_method`` says how the RSS
    peak was found: ``"hwm"`` (exact high-water mark) or ``"sampled"``.
    """

    rss: int
    traced: int
    rss_method: str
    result: Any = field(default=None, repr=False, compare=False)

    @property
    def larger(self) -> int:
        """The larger of the two probes (the one to hold a target against)."""
        return max(self.rss, self.traced)


def _status_kb(key: str) -> int | None:
    try:
        with open(_STATUS) as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def rss_bytes() -> int | None:
    """Current resident set size of this process in bytes (None where unavailable)."""
    return _status_kb("VmRSS:")


def _malloc_trim() -> None:
    """Give memory freed by earlier calls back to the kernel (glibc keeps it otherwise,
    and pages that are already resident would hide a later call's peak)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        return False
    # the reset must actually have brought the mark down to the current RSS
    hwm, rss = _status_kb("VmHWM:"), _status_kb("VmRSS:")
    return hwm is not None and rss is not None and hwm <= rss + (1 << 20)


class _Sampler(threading.Thread):
    def __init__(self, interval: float = 0.001):
        super().__init__(daemon=True)
        self.interval = interval
        self.peak = rss_bytes() or 0
        self._stop_event = threading.Event()

    def run(self):
        while not self._stop_event.is_set():
            r = rss_bytes() or 0
            if r > self.peak:
                self.peak = r
            time.sleep(self.interval)

    def stop(self) -> int:
        self._stop_event.set()
        self.join()
        r = rss_bytes() or 0
        return max(self.peak, r)


def time_call(fn: Callable[[], Any], *, repeat: int = 3, keep_last: bool = False) -> Timing:
    """Call ``fn()`` ``repeat`` times and return the wall-clock and CPU times.

    The result of each call is dropped (and garbage collected) before the next, so
    the calls do not pile up memory; with ``keep_last`` the last one is returned in
    ``Timing.result``.
    """
    times, cpu = [], []
    n = max(1, int(repeat))
    last = None
    for i in range(n):
        gc.collect()
        c0 = time.process_time()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        if keep_last and i == n - 1:
            last = out
        del out
    gc.collect()
    return Timing(tuple(times), tuple(cpu), result=last)


def measure_memory(fn: Callable[[], Any], *, keep_result: bool = False) -> MemoryPeak:
    """Run ``fn()`` once and return its peak memory above the memory in use before it.

    Run it apart from timings: tracemalloc slows Python-level code down.
    """
    gc.collect()
    _malloc_trim()
    use_hwm = _reset_hwm()
    base_rss = rss_bytes() or 0
    sampler = None
    if not use_hwm:
        sampler = _Sampler()
        sampler.start()
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base_traced = tracemalloc.get_traced_memory()[0]
    try:
        out = fn()
    finally:
        traced_peak = tracemalloc.get_traced_memory()[1]
        if not was_tracing:
            tracemalloc.stop()
        if sampler is not None:
            peak_rss = sampler.stop()
        else:
            peak_rss = _status_kb("VmHWM:") or 0
    result = out if keep_result else None
    del out
    gc.collect()
    return MemoryPeak(
        rss=max(0, peak_rss - base_rss),
        traced=max(0, traced_peak - base_traced),
        rss_method="hwm" if use_hwm else "sampled",
        result=result,
    )


def cpu_count() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1
