"""Smoke tests of benchmarks/bench_speed.py: the yardstick is right and the script runs.

The benchmark itself (figures on the full-size cube) is run by hand; these tests only
make sure it cannot rot: the floor pass computes the matched filter it claims to, the
memory probe sees an allocation, and the whole benchmark runs end to end on tiny cubes.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_benchmark as _load

bench = _load("bench_speed")
measure = _load("_measure")


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("block_rows", [1, 3, 50])
def test_fft_floor_matches_direct_correlation(threads, block_rows):
    rng = np.random.default_rng(0)
    counts = rng.poisson(0.7, (7, 5, 3, 90)).astype(np.uint16)
    # asymmetric IRFs with different peaks per wavelength: catches a wrong shift/flip
    irf = np.array(
        [
            [0.1, 0.6, 0.2, 0.1, 0.0],
            [0.05, 0.1, 0.2, 0.4, 0.25],
            [0.5, 0.3, 0.1, 0.05, 0.05],
        ]
    )
    ref = bench.matched_filter_reference(counts, irf)
    plan = bench.floor_plan(irf, 90)
    out = np.zeros(counts.shape, np.float32)
    bench.fft_floor(counts, plan, block_rows=block_rows, threads=threads, out=out)
    # float32 FFT of values <= ~10: round-off ~1e-6 relative; 1e-4 absolute is ample
    np.testing.assert_allclose(out, ref, atol=1e-4)


def test_fft_floor_peak_lands_on_depth_bin():
    irf = np.array([0.05, 0.15, 0.5, 0.2, 0.1])  # peak at index 2
    counts = np.zeros((1, 1, 1, 64), np.uint16)
    counts[0, 0, 0, 30 - 2 : 30 + 3] = (irf * 1000).astype(np.uint16)  # return peaking at 30
    plan = bench.floor_plan(irf, 64)
    out = np.zeros(counts.shape, np.float32)
    bench.fft_floor(counts, plan, out=out)
    assert int(out[0, 0, 0].argmax()) == 30
    assert plan.nfft >= 64 + irf.size - 1  # no wrap-around


def test_measure_memory_sees_an_allocation():
    n = 40 * 2**20
    peak = measure.measure_memory(lambda: np.ones(n, np.uint8))
    # both probes must see the 40 MB buffer (RSS within page rounding, traced exactly)
    assert peak.traced >= n
    assert peak.rss >= 0.9 * n
    assert peak.larger >= n


def test_time_call_repeats():
    t = measure.time_call(lambda: sum(range(1000)), repeat=3)
    assert len(t.times) == 3 and 0 < t.best <= t.median


def test_run_benchmark_tiny_end_to_end():
    sizes = bench.Sizes(
        main=(16, 16, 120),
        full=(12, 12, 120),
        pix_small=(8, 8),
        bins_small=60,
        repeat=1,
        block_sizes=(4,),
        art=(12, 14, 60),
    )
    fig = bench.run_benchmark(sizes, seed=0, art_dir=None)
    main = fig["main"]
    assert main["shape"] == [16, 16, 4, 120]
    assert main["floor"]["best"] > 0 and main["floor_tuning"]
    for name, ok in fig["stages_available"].items():
        if ok:
            assert main[name]["best"] > 0 and main[name]["ratio"] > 0
    if fig["stages_available"].get("process"):
        assert fig["art"]["shape"] == [12, 14, 3, 60]
        assert set(fig["scaling"]["process"]) == {"pixels", "bins"}
    text = bench.format_report(fig)
    assert "floor" in text and "targets" in text
    assert "time <= 3x floor" in text and "mem <= 2x f32" in text
    # two saved runs side by side (here the same run twice): the same ratios in both
    side = bench.format_comparison(fig, fig).splitlines()
    proc = next(line for line in side if line.startswith("process")).split()
    assert proc[1] == proc[2] and proc[3] == proc[4] and proc[5] == proc[6]
