"""Contiguous parts of a range on threads, for kernels that release the GIL.

Every caller splits work whose items are independent (rows of a map, candidates, the
``(l, t)`` columns of a selection), so the split never changes a result: it only spreads
the calls over ``workers`` threads.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np


def on_parts(fn: Callable[[int, int], object], n: int, workers: int) -> None:
    """Call ``fn(i0, i1)`` on ``min(workers, n)`` contiguous parts ``[i0, i1)`` of
    ``range(n)``, one thread each; with a single part (``workers <= 1`` or ``n <= 1``)
    ``fn(0, n)`` runs in the caller's thread. An exception in a part is raised here."""
    n = int(n)
    k = max(1, min(int(workers), n))
    if k == 1:
        fn(0, n)
        return
    edges = np.linspace(0, n, k + 1).astype(np.int64).tolist()
    with ThreadPoolExecutor(k) as ex:
        list(ex.map(lambda i: fn(edges[i], edges[i + 1]), range(k)))
