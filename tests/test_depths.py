"""Tests of stage 7 (``detection/_7_depths.py``, ``place_depths``) on its own: the two
rule families (``_7a_align_depths``, ``_7b_edge_bands``) and the fields followed once."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from splidar.detection import PASSES, STAGES, detect
from splidar.detection._7_depths import RULES, place_depths
from splidar.detection._filters import irf_fwhm
from splidar.scenes import single_surface_scene


@pytest.fixture(scope="module")
def before_stage_7():
    """A single-surface cube at PPP 4, SBR 0.25 detected without stage 7 (seed fixed),
    and without stage 5g, which would leave the rounds no wrong further surface to fix
    on this small cube."""
    sim = single_surface_scene((32, 32), n_bins=120).simulate(ppp=4, sbr=0.25, rng=1)
    cube = sim.cube
    skip = (*RULES, "unlayered")
    det = detect(cube, rng=0, passes=tuple(p for p in PASSES if p not in skip))
    return cube, det, sim.truth


def _run(det, counts, surfaces, rules):
    return place_depths(
        surfaces, counts=counts, background=det.background, fwhm=irf_fwhm(det.irf),
        irf=det.irf, scales=np.asarray(det.scales), saliency=det.saliency,
        threshold=det.threshold, rules=rules,
    )  # fmt: skip


def _same(a, b) -> None:
    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, f.name


def test_place_depths_equals_each_family_followed_on_its_own(before_stage_7, monkeypatch):
    # one round: the fields followed once, after both families, equal those followed
    # after each
    import splidar.detection._7_depths as stage

    monkeypatch.setattr(stage, "ROUNDS", 1)
    cube, det, truth = before_stage_7
    both = _run(det, cube.counts, det.surfaces, RULES)
    first = _run(det, cube.counts, det.surfaces, ("align_depths",))
    second = _run(det, cube.counts, first.surfaces, ("edge_bands",))
    assert both.moved["align_depths"] > 0 and both.moved["edge_bands"] > 0
    assert dict(both.moved) == {**first.moved, **second.moved}
    _same(both.surfaces, second.surfaces)


def test_place_depths_rounds_until_a_round_moves_nothing(before_stage_7, monkeypatch):
    # later rounds run the far rules and the bands on the previous round's depths (the
    # sheared pool in the first round only) until one moves nothing; on this cube they
    # fix depths: fewer false surfaces than one round, no true one lost
    import splidar.detection._7_depths as stage
    import splidar.detection._7a_align_depths as rules_7a
    from splidar.metrics import evaluate

    cube, det, truth = before_stage_7
    calls = []
    pool = rules_7a.align_depths
    monkeypatch.setattr(rules_7a, "align_depths", lambda *a, **k: calls.append(1) or pool(*a, **k))
    full = _run(det, cube.counts, det.surfaces, RULES)
    assert full.rounds > 1 and len(calls) == 1
    monkeypatch.setattr(stage, "ROUNDS", 1)
    one = _run(det, cube.counts, det.surfaces, RULES)
    m = {}
    for name, surfaces in (("one", one.surfaces), ("rounds", full.surfaces)):
        m[name] = evaluate(replace(det, surfaces=surfaces).points, truth, tau=3.0)
    assert m["rounds"].f_false < m["one"].f_false
    assert m["rounds"].f_true >= m["one"].f_true


def test_place_depths_is_detect_stage_7(before_stage_7):
    cube, det, truth = before_stage_7
    full = detect(cube, rng=0, passes=tuple(p for p in PASSES if p != "unlayered"))
    placed = _run(det, cube.counts, det.surfaces, RULES)
    _same(placed.surfaces, full.surfaces)
    rec = {r.stage: r for r in full.provenance}
    assert [r.stage for r in full.provenance][-2:] == list(RULES)
    for rule in RULES:
        assert rec[rule].ran and rec[rule].moved == placed.moved[rule]
    assert full.options["depth_rounds"] == placed.rounds > 1


def test_place_depths_records_the_last_family_that_moved_a_surface(before_stage_7):
    cube, det, truth = before_stage_7
    placed = _run(det, cube.counts, det.surfaces, RULES)
    s = placed.surfaces
    by = {r: int((s.moved_by == STAGES.index(r)).sum()) for r in RULES}
    assert by["edge_bands"] == placed.moved["edge_bands"]
    assert 0 < by["align_depths"] <= placed.moved["align_depths"]
    moved = s.moved_by >= 0
    assert np.all(s.depth_bin[~moved] == det.surfaces.depth_bin[~moved])
    assert set(placed.seconds) == set(RULES) and np.isfinite(placed.beta)


def test_place_depths_one_family_leaves_the_other_out(before_stage_7):
    cube, det, truth = before_stage_7
    placed = _run(det, cube.counts, det.surfaces, ("edge_bands",))
    assert set(placed.moved) == {"edge_bands"}
    assert not np.any(placed.surfaces.moved_by == STAGES.index("align_depths"))
    none = _run(det, cube.counts, det.surfaces, ())
    assert not none.moved and np.isnan(none.beta)
    np.testing.assert_array_equal(none.surfaces.depth_bin, det.surfaces.depth_bin)


def test_place_depths_rejects_an_unknown_rule(before_stage_7):
    cube, det, truth = before_stage_7
    with pytest.raises(ValueError, match="unknown rules"):
        _run(det, cube.counts, det.surfaces, ("align_depths", "spill_over"))


def test_place_depths_later_rounds_equal_the_rules_without_memo(before_stage_7, monkeypatch):
    # the rounds read the likelihoods and far scores met before from their memos: the
    # same surfaces as every round computing everything anew, with less work in round 2
    # (on this small cube the first round's moves change most bands' planes: little less)
    import splidar.detection._7_depths as stage
    import splidar.detection._7b_edge_bands as bands

    cube, det, truth = before_stage_7
    rows = []
    llr = bands.profile_llr
    monkeypatch.setattr(bands, "profile_llr", lambda y, *a: rows.append(len(y)) or llr(y, *a))
    fast = _run(det, cube.counts, det.surfaces, RULES)
    assert fast.rounds == 2 and sum(fast.moved.values()) > 0
    fast_rows = sum(rows)
    a, b = stage.aligned_depths, stage.band_depths
    monkeypatch.setattr(stage, "aligned_depths", lambda *x, memo, **k: a(*x, memo=None, **k))
    monkeypatch.setattr(stage, "band_depths", lambda *x, memo, **k: b(*x, memo=None, **k))
    rows.clear()
    full = _run(det, cube.counts, det.surfaces, RULES)
    _same(fast.surfaces, full.surfaces)
    assert dict(fast.moved) == dict(full.moved) and fast.beta == full.beta
    assert fast_rows < sum(rows)  # round 2 read some from the memo
