"""Shared fixtures. Module-specific fixtures live in their own test modules."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(name: str):
    """The benchmark script ``benchmarks/NAME.py`` imported as the module ``name`` (its
    own imports of sibling scripts resolved from ``benchmarks/``), for the tests of its
    functions."""
    import importlib.util
    import sys

    sys.path.insert(0, str(BENCH_DIR))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH_DIR / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
        return mod
    finally:
        sys.path.remove(str(BENCH_DIR))


# ../shared/data beside the project (override with SPLIDAR_SHARED_DATA)
_DEFAULT_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_data_dir() -> Path | None:
    p = Path(os.environ.get("SPLIDAR_SHARED_DATA", _DEFAULT_SHARED))
    return p if p.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the public real data sets; skips the test when it is absent."""
    p = shared_data_dir()
    if p is None:
        pytest.skip("../shared/data is absent (real data sets are not part of a fresh clone)")
    return p


def kill_first_worker(pids: dict, task: str):
    """A dask.distributed scheduler plugin that SIGKILLs the worker holding the first
    finished task named ``task`` (``pids``: worker address -> pid, ``client.run(os.getpid)``).
    After the run, ``.killed`` is that worker's address and ``.key`` the task's key: the
    scheduler must have recomputed it elsewhere."""
    import signal

    from distributed.diagnostics.plugin import SchedulerPlugin
    from distributed.utils import key_split

    class KillFirstWorker(SchedulerPlugin):
        def __init__(self):
            self.pids, self.killed, self.key = pids, None, None

        def transition(self, key, start, finish, *args, **kwargs):
            if (
                self.killed is None
                and finish == "memory"
                and key_split(key) == task
                and kwargs.get("worker") in self.pids
            ):
                self.killed, self.key = kwargs["worker"], key
                os.kill(self.pids[self.killed], signal.SIGKILL)

    return KillFirstWorker()
