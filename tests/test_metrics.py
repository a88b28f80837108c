"""Tests of splidar.metrics: hand-worked cases, a brute-force reference and errors."""

from __future__ import annotations

import time

import numpy as np
import pytest

from splidar import PointSet, SplidarError
from splidar.metrics import Matching, Metrics, evaluate, f_true_curve, match_points


def _ps(rc, depth, shape=(2, 2), **kw):
    rc = np.asarray(rc, dtype=np.int64).reshape(-1, 2)
    return PointSet(row=rc[:, 0], col=rc[:, 1], depth_bin=depth, image_shape=shape, **kw)


def _greedy_reference(est, true, tau):
    """Sequential greedy nearest-first matching, written as plainly as possible."""
    pairs = []
    for i in range(len(est)):
        for j in range(len(true)):
            if est.row[i] == true.row[j] and est.col[i] == true.col[j]:
                d = abs(est.depth_bin[i] - true.depth_bin[j])
                if d <= tau:
                    pairs.append((d, i, j))
    pairs.sort()
    used_e, used_t, out = set(), set(), {}
    for _, i, j in pairs:
        if i not in used_e and j not in used_t:
            used_e.add(i)
            used_t.add(j)
            out[i] = j
    return out


def test_match_points_two_true_three_estimates_nearest_first():
    # pixel (0,0): true at 10 and 14; estimates at 12.5, 13.5, 9.
    # distances: e0(12.5): t0 2.5, t1 1.5; e1(13.5): t0 3.5, t1 0.5; e2(9): t0 1.0, t1 5
    # nearest first: (e1,t1)=0.5, then (e2,t0)=1.0 -> e0 unmatched.
    # A wrong order (estimates in index order, each taking its nearest free truth)
    # would give e0->t1 (1.5), e1->t0 (3.5), e2 unmatched: a different answer.
    true = _ps([[0, 0], [0, 0]], [10.0, 14.0])
    est = _ps([[0, 0]] * 3, [12.5, 13.5, 9.0])
    m = match_points(est, true, tau=4.0)
    assert isinstance(m, Matching)
    assert m.est_index.tolist() == [1, 2]
    assert m.true_index.tolist() == [1, 0]
    assert m.distance.tolist() == [0.5, 1.0]
    assert m.unmatched_est.tolist() == [0]
    assert m.unmatched_true.tolist() == []
    r = evaluate(est, true, tau=4.0)
    assert r.f_true == 1.0 and r.f_false == 1 and r.dae == pytest.approx(0.75)


def test_match_points_only_same_pixel():
    true = _ps([[0, 0]], [10.0])
    est = _ps([[0, 1]], [10.0])
    m = match_points(est, true, tau=5.0)
    assert m.n_matched == 0
    assert m.unmatched_est.tolist() == [0] and m.unmatched_true.tolist() == [0]


def test_match_points_tau_boundary_inclusive():
    true = _ps([[0, 0], [1, 1]], [10.0, 10.0])
    # 10.3 - 10.0 is 0.30000000000000071 in floating point; still inside tau = 0.3
    est = _ps([[0, 0], [1, 1]], [10.3, 9.69])
    m = match_points(est, true, tau=0.3)
    assert m.est_index.tolist() == [0]
    assert m.unmatched_est.tolist() == [1]
    assert match_points(_ps([[0, 0]], [10.0]), _ps([[0, 0]], [10.0]), tau=0.0).n_matched == 1


def test_match_points_agrees_with_sequential_greedy():
    rng = np.random.default_rng(3)
    shape = (3, 4)
    for _ in range(30):
        nt, ne = rng.integers(0, 25), rng.integers(0, 25)
        # integer-ish depths make many exact ties, which must be broken the same way
        true = PointSet(
            row=rng.integers(0, 3, nt),
            col=rng.integers(0, 4, nt),
            depth_bin=rng.integers(0, 12, nt).astype(float),
            image_shape=shape,
        )
        est = PointSet(
            row=rng.integers(0, 3, ne),
            col=rng.integers(0, 4, ne),
            depth_bin=rng.integers(0, 12, ne) + rng.choice([0.0, 0.5], ne),
            image_shape=shape,
        )
        ref = _greedy_reference(est, true, 2.0)
        m = match_points(est, true, tau=2.0)
        assert dict(zip(m.est_index.tolist(), m.true_index.tolist(), strict=True)) == ref


def test_evaluate_intensity_penalties_by_hand():
    # pixel (0,0): true I=[2,1] at 10, est I=[3,1] at 10.5 -> matched, error 1
    # pixel (0,1): true I=[4,4] at 20, no estimate -> missed, error 8
    # pixel (1,0): est I=[0.5,0.5] at 30, no truth -> false, error 1
    true = _ps([[0, 0], [0, 1]], [10.0, 20.0], intensity=[[2, 1], [4, 4]], label=[0, 1])
    est = _ps([[0, 0], [1, 0]], [10.5, 30.0], intensity=[[3, 1], [0.5, 0.5]], label=[0, 2])
    r = evaluate(est, true, tau=1.0)
    assert r.iae == pytest.approx((1 + 8 + 1) / 2)
    assert r.f_true == 0.5 and r.f_false == 1 and r.f_false_rate == 0.5
    assert r.dae == 0.5
    assert r.label_accuracy == 1.0
    # pixels: (0,0) both present, (0,1) missed, (1,0) false, (1,1) both absent -> 2/4
    assert r.detection_accuracy == 0.5
    assert (r.n_true, r.n_est, r.n_matched) == (2, 2, 1)


def test_evaluate_label_accuracy_over_matched_only():
    true = _ps([[0, 0], [0, 1], [1, 1]], [5.0, 5.0, 5.0], label=[0, 1, 2])
    # the third estimate is out of tau: its (wrong) label must not count
    est = _ps([[0, 0], [0, 1], [1, 1]], [5.0, 5.2, 50.0], label=[0, 2, 0])
    r = evaluate(est, true, tau=1.0)
    assert r.n_matched == 2 and r.label_accuracy == 0.5
    assert evaluate(_ps([[0, 0]], [5.0]), true, tau=1.0).label_accuracy is None


def test_evaluate_optional_fields_none_and_empty_sets():
    true = _ps([[0, 0]], [5.0])
    r = evaluate(_ps([[0, 0]], [5.0]), true, tau=1.0)
    assert r.iae is None and r.label_accuracy is None and r.dae_m is None
    r = evaluate(_ps(np.zeros((0, 2)), []), true, tau=1.0)
    assert r.f_true == 0.0 and r.f_false == 0 and np.isnan(r.dae)
    r = evaluate(_ps([[0, 0]], [5.0]), _ps(np.zeros((0, 2)), []), tau=1.0)
    assert np.isnan(r.f_true) and r.f_false == 1


def test_evaluate_tau_in_metres():
    true = _ps([[0, 0]], [10.0], depth_m=[1.000])
    est = _ps([[0, 0]], [10.8], depth_m=[1.003])
    assert evaluate(est, true, tau_m=0.004).f_true == 1.0
    assert evaluate(est, true, tau_m=0.002).f_true == 0.0
    r = evaluate(est, true, tau_m=0.004)
    assert r.tau_unit == "m" and r.dae_m == pytest.approx(0.003) and r.dae == pytest.approx(0.8)
    with pytest.raises(SplidarError, match="depth_m"):
        evaluate(_ps([[0, 0]], [1.0]), true, tau_m=0.004)


def test_evaluate_as_dict_and_str():
    r = evaluate(_ps([[0, 0]], [5.0]), _ps([[0, 0]], [5.5]), tau=1.0)
    assert isinstance(r, Metrics)
    d = r.as_dict()
    assert d["f_true"] == 1.0 and d["n_matched"] == 1 and d["iae"] is None
    s = str(r)
    assert "F_true" in s and "IAE" in s and "n/a" in s


def test_evaluate_accepts_result_objects_with_points():
    class Result:
        points = _ps([[0, 0]], [5.0])

    assert evaluate(Result(), _ps([[0, 0]], [5.5]), tau=1.0).f_true == 1.0


def test_evaluate_errors():
    a = _ps([[0, 0]], [5.0], shape=(2, 2))
    b = _ps([[0, 0]], [5.0], shape=(3, 2))
    with pytest.raises(SplidarError, match="image_shape"):
        evaluate(a, b)
    with pytest.raises(SplidarError, match="PointSet"):
        evaluate(np.zeros(3), a)
    with pytest.raises(SplidarError, match="tau"):
        evaluate(a, a, tau=-1.0)
    with pytest.raises(SplidarError, match="not both"):
        evaluate(a, a, tau=1.0, tau_m=0.1)
    c = _ps([[0, 0]], [5.0], intensity=[[1.0, 2.0]])
    d = _ps([[0, 0]], [5.0], intensity=[[1.0]])
    with pytest.raises(SplidarError, match="wavelength"):
        evaluate(c, d)


def test_evaluate_fast_on_large_sets():
    rng = np.random.default_rng(0)
    n, shape = 150_000, (300, 300)
    r, c = rng.integers(0, 300, n), rng.integers(0, 300, n)
    d = rng.uniform(0, 1000, n)
    true = PointSet(row=r, col=c, depth_bin=d, image_shape=shape, intensity=rng.random((n, 2)))
    est = PointSet(
        row=r,
        col=c,
        depth_bin=d + rng.normal(0, 1, n),
        image_shape=shape,
        intensity=rng.random((n, 2)),
    )
    t0 = time.process_time()
    m = evaluate(est, true, tau=2.0)
    elapsed = time.process_time() - t0
    # ~0.2 s of CPU measured; 2 s (CPU, not wall: a loaded machine does not fail it) guards speed
    assert elapsed < 2.0
    # N(0,1) errors: P(|e| <= 2) = 0.954; crowded pixels change little at 1.7 points/pixel
    assert 0.93 < m.f_true < 0.97


def test_f_true_curve_matches_evaluate():
    rng = np.random.default_rng(1)
    n, shape = 2000, (20, 20)
    r, c = rng.integers(0, 20, n), rng.integers(0, 20, n)
    d = rng.uniform(0, 200, n)
    true = PointSet(row=r, col=c, depth_bin=d, image_shape=shape)
    est = PointSet(row=r, col=c, depth_bin=d + rng.normal(0, 2, n), image_shape=shape)
    taus = [0.0, 0.5, 1.0, 2.0, 4.0]
    curve = f_true_curve(est, true, taus)
    for i, tau in enumerate(taus):
        m = evaluate(est, true, tau=tau)
        assert curve.f_true[i] == pytest.approx(m.f_true)
        assert curve.f_false[i] == m.f_false
        if m.n_matched:
            assert curve.dae[i] == pytest.approx(m.dae)
    assert np.all(np.diff(curve.f_true) >= 0)
    with pytest.raises(SplidarError, match="taus"):
        f_true_curve(est, true, [-1.0])
