"""Tests of benchmarks/bench_spread_sources.py's measurements added in session 27 (dec39):
the ``every`` rule (:func:`every_lines`) and the line test's null tail (:func:`null_tail`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import test_layer_evidence as tle
from conftest import load_benchmark as _load

from splidar.detection._result import Background

bench = _load("bench_spread_sources")


def _strip_detection(width: int) -> tuple[dict, np.ndarray]:
    """test_layer_evidence's bright / dim scene, the bright depth spread over ``width``
    columns of the dim region (each such pixel holds its own surface and the spread)."""
    further = [(tle.SPREAD_COL + k, tle.D_NEAR) for k in range(width)]
    row, col, depth = tle._small_surfaces(further)
    s = SimpleNamespace(row=row, col=col, depth_bin=depth, image_shape=tle.SMALL)
    bg = Background(
        spatial=np.full(tle.SMALL + (1,), tle.BG, np.float32),
        temporal=np.full((1, tle.T), tle.BG, np.float32),
    )
    d = dict(surfaces=s, background=bg, irf=tle.IRF, half=tle.HALF, counts=tle._counts(seed=0))
    strip = np.flatnonzero((col >= tle.SPREAD_COL) & (depth == tle.D_NEAR))
    return d, strip


def test_every_lines_removes_the_strip_7c_axes_spare():
    # a spread strip 2 columns wide continues along its axes: 7c spares part of it, the
    # gated rule removes about half; `every` line-tests the spared ones too
    d, strip = _strip_detection(2)
    gated, every = bench.every_lines(d)
    assert np.isin(gated, every).all()
    assert np.isin(every, strip).all()  # no pixel's own (dim, true) surface removed
    assert every.size > gated.size and every.size >= 0.9 * strip.size


def test_every_lines_equals_the_gated_rule_on_a_one_pixel_strip():
    d, strip = _strip_detection(1)
    gated, every = bench.every_lines(d)
    np.testing.assert_array_equal(gated, every)
    np.testing.assert_array_equal(every, strip)


def test_null_tail_rate_does_not_grow_with_the_background_level():
    # background-only lines: the profiled log-ratio's tail is the same at 0.01 and 0.25
    # counts per bin (the level log((1 - q) / q) means the same rate at every level)
    out = bench.null_tail(tle.IRF, levels=(0.01, 0.25), n_lines=3000, nats=(2.0,), seed=0)
    lo, hi = out[0.01][2.0], out[0.25][2.0]
    assert 0.005 < lo < 0.05 and 0.005 < hi < 0.05
    assert max(lo, hi) / min(lo, hi) < 2.5
