"""``splidar._memory``: glibc's mmap threshold raised around a block of work."""

import os
import subprocess
import sys
import textwrap

import pytest

from splidar import _memory

DASK_ENV = {"MALLOC_TRIM_THRESHOLD_": "65536", "OMP_NUM_THREADS": "1"}


@pytest.fixture
def recorded(monkeypatch):
    """``mallopt`` and ``malloc_trim`` replaced by recorders (every value accepted), the
    environment as a Dask worker's."""
    calls = []

    def mallopt(param, value):
        calls.append((param, value))
        return 1

    monkeypatch.setattr(_memory, "_mallopt", lambda: mallopt)
    monkeypatch.setattr(_memory, "_malloc_trim", lambda: lambda pad: calls.append(("trim", pad)))
    for k in (*_memory._MALLOC_ENV, "GLIBC_TUNABLES"):
        monkeypatch.delenv(k, raising=False)
    for k, v in DASK_ENV.items():
        monkeypatch.setenv(k, v)
    return calls


def test_fixed_mmap_threshold_reads_the_environment():
    assert _memory.fixed_mmap_threshold({}) is None  # glibc's dynamic threshold
    assert _memory.fixed_mmap_threshold(DASK_ENV) == 128 * 1024
    assert _memory.fixed_mmap_threshold({"MALLOC_MMAP_THRESHOLD_": "1048576"}) == 1048576
    assert _memory.fixed_mmap_threshold({"MALLOC_MMAP_THRESHOLD_": "x"}) is None
    tunables = {**DASK_ENV, "GLIBC_TUNABLES": "glibc.malloc.mmap_threshold=4096"}
    assert _memory.fixed_mmap_threshold(tunables) is None


def test_keep_freed_memory_raises_the_threshold_then_restores_and_gives_back(recorded):
    with _memory.keep_freed_memory():
        assert recorded == [(_memory.M_MMAP_THRESHOLD, _memory.KEEP_MMAP_THRESHOLD)]
    assert recorded[1:] == [(_memory.M_MMAP_THRESHOLD, 128 * 1024), ("trim", 0)]
    assert _memory._keep_state == {"depth": 0, "restore": None, "any": 0, "restore_any": None}


def test_keep_freed_memory_nested_blocks_set_and_restore_once(recorded):
    with _memory.keep_freed_memory():
        with _memory.keep_freed_memory():
            assert len(recorded) == 1
        assert len(recorded) == 1  # the inner block's end restores nothing
    assert len(recorded) == 3


def test_keep_freed_memory_never_lowers_the_threshold(recorded, monkeypatch):
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", str(64 * 2**20))
    with _memory.keep_freed_memory():
        pass
    assert recorded == []


def test_keep_freed_memory_does_nothing_with_the_dynamic_threshold(recorded, monkeypatch):
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    with _memory.keep_freed_memory():
        pass
    assert recorded == []


def test_keep_freed_memory_restores_after_an_error(recorded):
    with pytest.raises(ValueError), _memory.keep_freed_memory():
        raise ValueError("inside")
    assert len(recorded) == 3 and _memory._keep_state["depth"] == 0


def _faults(n: int, size: int, block: str, *, dask_env: bool = True) -> tuple:
    """Page faults of ``n`` temporaries of ``size`` float64, each freed after a 256 kB
    array that stays (as a strip's state outlives its temporaries), in a process started
    as Dask starts its workers with transparent huge pages off (a fault per 4 KiB):
    ``(outside the block, inside block, after it)``; ``block`` the ``with`` statement's
    context, e.g. ``"keep_freed_memory()"``; ``dask_env=False``: no malloc setting in the
    environment (glibc's dynamic threshold, as in a user's process)."""
    code = textwrap.dedent(
        f"""
        import ctypes, resource
        import numpy as np
        from splidar._memory import hold_freed_memory, keep_freed_memory

        ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE

        def faults():
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            kept = []
            for _ in range({n}):
                t = np.empty({size})
                t[:] = 1.0
                kept.append(np.ones(2**15))
                del t
            return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

        faults()
        outside = faults()
        with {block}:
            inside = faults()
        print(outside, inside, faults())
        """
    )
    env = {k: v for k, v in os.environ.items() if k not in _memory._MALLOC_ENV}
    env.update(DASK_ENV if dask_env else {})
    env.pop("GLIBC_TUNABLES", None)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    return tuple(int(x) for x in out.stdout.split())


@pytest.mark.skipif(_memory._mallopt() is None, reason="glibc's mallopt only")
def test_keep_freed_memory_reuses_freed_pages_in_a_dask_workers_environment():
    """100 temporaries of 2 MB fault in fresh pages each time outside the block (over
    51,200 page faults: 512 a temporary), and inside it reuse the first temporary's
    pages (the kept arrays' 64 pages each remain); after it, the environment's threshold
    is back."""
    outside, inside, after = _faults(100, 2**18, "keep_freed_memory()")
    assert outside > 100 * 512, outside
    assert inside < 100 * 64 + 2000, inside
    assert after > 100 * 512, after


def test_keep_freed_memory_any_size_maps_nothing_apart_then_restores(recorded):
    with _memory.keep_freed_memory(any_size=True):
        assert recorded == [
            (_memory.M_MMAP_THRESHOLD, _memory.KEEP_MMAP_THRESHOLD),
            (_memory.M_MMAP_MAX, 0),
            (_memory.M_TRIM_THRESHOLD, _memory.KEEP_TRIM_THRESHOLD),
        ]
    assert recorded[3:] == [
        (_memory.M_MMAP_MAX, 65536),
        (_memory.M_TRIM_THRESHOLD, 65536),  # the environment's (DASK_ENV)
        (_memory.M_MMAP_THRESHOLD, 128 * 1024),
        ("trim", 0),
    ]
    assert _memory._keep_state == {"depth": 0, "restore": None, "any": 0, "restore_any": None}


def test_keep_freed_memory_any_size_inside_a_plain_block_gives_back_at_its_end(recorded):
    with _memory.keep_freed_memory():
        with _memory.keep_freed_memory(any_size=True):
            assert len(recorded) == 3
        # mappings and trimming as before, the freed pages given back; threshold kept
        assert recorded[3:] == [
            (_memory.M_MMAP_MAX, 65536), (_memory.M_TRIM_THRESHOLD, 65536), ("trim", 0),
        ]  # fmt: skip
    assert recorded[6:] == [(_memory.M_MMAP_THRESHOLD, 128 * 1024), ("trim", 0)]


def test_keep_freed_memory_any_size_does_nothing_with_the_dynamic_threshold(recorded, monkeypatch):
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    with _memory.keep_freed_memory(any_size=True):
        pass
    assert recorded == []


def test_keep_freed_memory_any_size_sets_back_what_a_refusal_left(recorded, monkeypatch):
    calls = []

    def mallopt(param, value):  # the trim threshold refused
        calls.append((param, value))
        return 0 if param == _memory.M_TRIM_THRESHOLD else 1

    monkeypatch.setattr(_memory, "_mallopt", lambda: mallopt)
    with _memory.keep_freed_memory(any_size=True):
        assert calls[-1] == (_memory.M_MMAP_MAX, 65536)  # set back at once
        n = len(calls)
    assert calls[n:] == [(_memory.M_MMAP_THRESHOLD, 128 * 1024)]
    assert _memory._keep_state["restore_any"] is None


@pytest.mark.skipif(_memory._mallopt() is None, reason="glibc's mallopt only")
def test_keep_freed_memory_any_size_reuses_large_freed_arrays_in_a_dask_workers_environment():
    """As a map tile's 70 MB temporaries: 20 arrays of 64 MB fault in fresh pages each
    time outside the block (16,384 faults a temporary) and inside it reuse the first
    one's pages (its 16,384 faults and the kept arrays' 1,280)."""
    outside, inside, after = _faults(20, 2**23, "keep_freed_memory(any_size=True)")
    assert outside > 20 * 16384, outside
    assert inside < 2 * 16384 + 2000, inside
    assert after > 20 * 16384, after


def test_hold_freed_memory_maps_nothing_apart_with_the_dynamic_threshold(recorded, monkeypatch):
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")  # no malloc setting: glibc's dynamic rule
    with _memory.hold_freed_memory():
        assert recorded == [(_memory.M_MMAP_MAX, 0), (_memory.M_TRIM_THRESHOLD, 2**30)]
    # set back to glibc's default and to the dynamic rule's trim threshold at 32 MiB
    assert recorded[2:] == [
        (_memory.M_MMAP_MAX, 65536), (_memory.M_TRIM_THRESHOLD, 2**26), ("trim", 0),
    ]  # fmt: skip
    assert _memory._keep_state == {"depth": 0, "restore": None, "any": 0, "restore_any": None}


def test_hold_freed_memory_in_a_dask_workers_environment_is_keep_freed_memory_any_size(recorded):
    with _memory.hold_freed_memory():
        pass
    held = list(recorded)
    recorded.clear()
    with _memory.keep_freed_memory(any_size=True):
        pass
    assert held == recorded and len(held) == 7


def test_hold_freed_memory_leaves_glibc_tunables_alone(recorded, monkeypatch):
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=1000000")
    with _memory.hold_freed_memory():
        pass
    assert recorded == []


@pytest.mark.skipif(_memory._mallopt() is None, reason="glibc's mallopt only")
def test_hold_freed_memory_reuses_large_freed_arrays_with_the_dynamic_threshold():
    """A user's process (no malloc setting): arrays of 64 MB, over glibc's largest
    dynamic threshold (32 MiB), are fresh mappings each time outside the block (16,384
    faults each) and reuse the first one's pages inside it."""
    outside, inside, after = _faults(20, 2**23, "hold_freed_memory()", dask_env=False)
    assert outside > 20 * 16384, outside
    assert inside < 2 * 16384 + 2000, inside
    assert after > 20 * 16384, after


@pytest.fixture
def switch(monkeypatch):
    """NumPy's huge-page switch replaced by a recorder (advice on before)."""
    calls, state = [], [True]

    def fake(on):
        calls.append(bool(on))
        before, state[0] = state[0], bool(on)
        return before

    monkeypatch.delenv(_memory.HUGEPAGE_ENV, raising=False)
    monkeypatch.setattr(_memory, "_hugepage_switch", lambda: fake)
    return calls, state


def test_small_pages_turns_the_advice_off_inside_and_back_after(switch):
    calls, state = switch
    with _memory.small_pages():
        with _memory.small_pages():  # nested: set and restored once
            assert state == [False]
        assert state == [False]
    assert state == [True] and calls == [False, True]


def test_small_pages_restores_after_an_error(switch):
    calls, state = switch
    with pytest.raises(RuntimeError), _memory.small_pages():
        raise RuntimeError("boom")
    assert state == [True] and calls == [False, True]


def test_small_pages_leaves_the_users_environment_choice(switch, monkeypatch):
    calls, _ = switch
    monkeypatch.setenv(_memory.HUGEPAGE_ENV, "1")
    with _memory.small_pages():
        pass
    assert calls == []


def test_hold_freed_memory_opens_small_pages(switch, recorded):
    calls, state = switch
    with _memory.hold_freed_memory():
        assert state == [False]
    assert state == [True]


_VMFLAGS = """
import numpy as np
from splidar import _memory

def advised(a):
    # the VmFlags of the mapping holding the array's data: "hg" = MADV_HUGEPAGE
    addr = a.__array_interface__["data"][0] + a.nbytes // 2
    lines = open("/proc/self/smaps").read().splitlines()
    inside = False
    for line in lines:
        head = line.split()[0]
        if "-" in head and all(c in "0123456789abcdef-" for c in head):
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= addr < hi
        elif inside and line.startswith("VmFlags:"):
            return " hg" in line
    raise AssertionError("mapping not found")

before = np.ones(2**24, np.float32)  # 64 MiB: a mapping of its own
with _memory.small_pages():
    within = np.ones(2**24, np.float32)
after = np.ones(2**24, np.float32)
print(advised(before), advised(within), advised(after))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/smaps")
def test_small_pages_makes_arrays_without_the_huge_page_advice():
    """In a fresh process (NumPy's default advice): a 64 MiB array made inside the
    block is mapped without ``MADV_HUGEPAGE``, those made before and after with it."""
    env = {k: v for k, v in os.environ.items() if k != _memory.HUGEPAGE_ENV}
    out = subprocess.run(
        [sys.executable, "-c", _VMFLAGS], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    if out[0] != "True":
        pytest.skip("NumPy or the kernel gives no huge-page advice here")
    assert out == ["True", "False", "True"]
