"""Tests of splidar.detection._threads (contiguous parts of a range on threads)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from splidar.detection._threads import on_parts


@pytest.mark.parametrize("n", [0, 1, 5, 100])
@pytest.mark.parametrize("workers", [1, 2, 3, 8])
def test_on_parts_covers_the_range_once_in_contiguous_parts(n, workers):
    seen = np.zeros(n, np.int64)
    parts = []

    def fn(i0, i1):
        parts.append((i0, i1))
        seen[i0:i1] += 1

    on_parts(fn, n, workers)
    assert np.all(seen == 1)
    assert len(parts) == max(1, min(workers, n))
    assert sorted(parts)[0][0] == 0 and sorted(parts)[-1][1] == n
    # contiguous: each part starts where the previous one stopped
    ordered = sorted(parts)
    assert all(a[1] == b[0] for a, b in zip(ordered, ordered[1:], strict=False))


def test_on_parts_runs_parts_on_threads_and_one_part_in_the_caller():
    main = threading.get_ident()
    ids = set()
    on_parts(lambda i0, i1: ids.add(threading.get_ident()), 10, 1)
    assert ids == {main}
    barrier = threading.Barrier(2, timeout=10)  # fails unless both parts run at once
    on_parts(lambda i0, i1: barrier.wait(), 10, 2)


def test_on_parts_raises_a_part_exception():
    def fn(i0, i1):
        if i0 > 0:
            raise ValueError("part failed")

    with pytest.raises(ValueError, match="part failed"):
        on_parts(fn, 10, 2)
