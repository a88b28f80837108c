"""Where ``splidar run`` computes: threads (default), a LocalCluster, or a running cluster.

Used by the CLI only (``--workers``, ``--memory-limit``, ``--scheduler``); the library
itself just runs on whatever Dask scheduler is active (``docs/distributed.md``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import sys

from ._validation import SplidarError

__all__ = ["as_dask_cube", "dask_session"]

log = logging.getLogger(__name__)

_EXTRA = "pip install 'splidar[distributed]'"

#: Dask settings of the LocalCluster that ``--workers`` starts (``dask.config`` keys):
#: the workers' statistical profiler off (the dashboard's profile page stays empty) and
#: the event loops' health tick and system monitor less often. Idle, Dask's three
#: processes of a 2-worker cluster then take 0.02-0.03 s of CPU per second in all
#: instead of 0.09 (``benchmarks/README.md``, "Branch dist20"): CPU that a long run
#: pays per second of wall time, whatever its tasks do. A ``--scheduler`` cluster keeps
#: its own settings.
CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "2s",
}


def _distributed():
    try:
        import distributed
    except ImportError:
        raise SplidarError(
            f"--workers and --scheduler need dask.distributed: {_EXTRA}, or run without them "
            "(threads of this process)."
        ) from None
    return distributed


def as_dask_cube(cube, rows_per_chunk: int = 64):
    """``cube`` with its counts as a Dask array (chunks of whole rows); a lazy cube as is.

    The IRF array is kept as it is (a Cube normalises the IRF it is given, and a twice
    normalised IRF can differ in its last bit, which would change the result).
    """
    if cube.is_lazy:
        return cube
    try:
        import dask.array as da
    except ImportError:
        raise SplidarError(f"a cluster run needs dask: {_EXTRA}.") from None
    R, C, L, T = cube.shape
    counts = da.from_array(cube.counts, chunks=(min(rows_per_chunk, R), C, L, T))
    out = dataclasses.replace(cube, counts=counts)
    object.__setattr__(out, "irf", cube.irf)
    return out


@contextlib.contextmanager
def dask_session(*, workers=None, memory_limit=None, scheduler=None, progress=True):
    """A Dask context for one run; yields the ``Client`` (or None for threads).

    Parameters
    ----------
    workers : int, optional
        Start a ``LocalCluster`` of this many worker processes (one thread each).
    memory_limit : str, optional
        Per-worker memory limit of that cluster (e.g. ``"1GB"``; default: Dask's share
        of the machine's memory).
    scheduler : str, optional
        Address of a running scheduler to join (``tcp://host:8786``).
    progress : bool
        Threads only: a Dask progress bar (stderr) for computations over 2 s. With a
        cluster, the dashboard (address printed) follows the tasks.
    """
    if workers is None and scheduler is None:
        if not progress:
            yield None
            return
        from dask.diagnostics import ProgressBar

        with ProgressBar(minimum=2.0, out=sys.stderr):
            yield None
        return
    distributed = _distributed()
    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            try:
                client = stack.enter_context(distributed.Client(scheduler, timeout="10s"))
            except OSError as exc:
                raise SplidarError(
                    f"--scheduler: cannot reach a Dask scheduler at '{scheduler}' ({exc}); "
                    "start one with `dask scheduler` (and `dask worker ADDRESS`) or use "
                    "--workers N for a local cluster."
                ) from None
        else:
            import dask

            # read when the scheduler, nannies and workers start (and in this process,
            # which hosts the scheduler, for the whole session)
            stack.enter_context(dask.config.set(CLUSTER_CONFIG))
            cluster = stack.enter_context(
                distributed.LocalCluster(
                    n_workers=int(workers),
                    threads_per_worker=1,
                    processes=True,
                    memory_limit="auto" if memory_limit is None else memory_limit,
                )
            )
            client = stack.enter_context(distributed.Client(cluster))
        n = len(client.scheduler_info().get("workers", {}))
        print(
            f"Dask cluster: {n} worker(s) at {client.scheduler.address}; "
            f"dashboard: {client.dashboard_link}",
            file=sys.stderr,
        )
        yield client
