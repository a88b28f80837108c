"""Stage 5's first clean-up (``recentre``) on its own: a hand-made candidate table."""

import numpy as np

from splidar import gaussian_irf
from splidar.detection import STAGES
from splidar.detection._5_recentre import recentre_runs, restore_agreed
from splidar.detection._filters import irf_fwhm
from splidar.detection._table import CandidateTable

W = 13
OFFSET = 44
PLANE = 50.0


def _table(own_photons, own_depth=55.5, own_kept=True, signal=3.0):
    """A 3 x 3 image: the four 4-neighbours of the centre keep a return at ``PLANE``;
    the centre's candidate lies at ``own_depth`` in a run [45, 57) that holds the plane,
    its raw counts ``own_photons`` (bin -> photons) over a background of 0.1 per bin."""
    pix = [(0, 1), (2, 1), (1, 0), (1, 2), (1, 1)]
    n = len(pix)
    counts = np.zeros((n, 1, W), np.int32)
    for t, k in own_photons.items():
        counts[-1, 0, t - OFFSET] = k
    bkg = np.zeros((n, 1, W), np.float32)
    bkg[:, :, 1:] = 0.1  # the support, bins 45-56
    cols = dict(
        row=np.array([p[0] for p in pix]),
        col=np.array([p[1] for p in pix]),
        depth_bin=np.array([PLANE] * 4 + [own_depth]),
        start=np.full(n, OFFSET + 1),
        stop=np.full(n, OFFSET + W),
        offset=np.full(n, OFFSET),
        signal=np.full((n, 1, 1), signal),
        scale_index=np.zeros(n, np.int64),
        own_counts=counts,
        own_background=bkg,
    )
    keep = np.array([True] * 4 + [own_kept])
    z = np.zeros(n, np.int64)
    return CandidateTable(cols, keep, np.zeros(n, np.int8), z, z, (3, 3))


def _run(table):
    irf = gaussian_irf(3.0).reshape(1, -1)
    return recentre_runs(
        table, irf=irf, peak=irf.argmax(axis=1), fwhm=irf_fwhm(irf), pfa=0.01, n_bins=200,
        llr_level=3.0, secondary_llr=0.0, max_kept=2,
    )  # fmt: skip


def test_recentre_runs_moves_a_run_edge_depth_onto_the_neighbours_plane():
    # one photon at the run's edge, two on the plane: the own counts favour the plane
    res = _run(_table({49: 1, 51: 1, 56: 1}))
    assert res.moved == 1 and res.added == 0 and res.removed == 0
    assert res.table.columns["depth_bin"][-1] == PLANE
    np.testing.assert_array_equal(res.table.columns["depth_bin"][:4], PLANE)


def test_recentre_runs_keeps_a_depth_its_own_counts_show():
    # eight photons at the candidate's own depth: significant alone, favoured: it stays
    res = _run(_table({55: 4, 56: 4}))
    assert res.moved == 0
    assert res.table.columns["depth_bin"][-1] == 55.5
    assert res.table.keep.all()


def test_recentre_runs_restores_a_rejected_candidate_at_the_plane():
    # rejected by the presence test at 55.5, one own photon on the plane: restored there
    res = _run(_table({50: 1}, own_kept=False))
    assert res.moved == 1 and res.added == 1
    assert res.table.keep[-1] and res.table.columns["depth_bin"][-1] == PLANE
    assert res.table.origin[-1] == STAGES.index("recentre")


def test_recentre_runs_leaves_a_rejected_candidate_whose_counts_reject_the_plane():
    # no own photon near the plane: a return of 5 photons there has L = -5 < -3 (the
    # presence test's own-count veto): the candidate stays rejected where it was
    res = _run(_table({56: 1}, own_kept=False, signal=5.0))
    assert res.moved == 0 and res.added == 0
    assert not res.table.keep[-1] and res.table.columns["depth_bin"][-1] == 55.5
    # the same pixel with one photon on the plane is restored
    res = _run(_table({50: 1, 56: 1}, own_kept=False, signal=5.0))
    assert res.moved == 1 and res.table.keep[-1]


def test_restore_agreed_restores_a_rejected_candidate_its_neighbours_hold():
    # rejected at 50.5 (the plane's depth, within the FWHM): restored at its own depth
    # when its own counts do not reject the return, left when they do (no photon near
    # a bright plane) or when fewer than 3 neighbours hold the depth
    irf = gaussian_irf(3.0).reshape(1, -1)
    kw = dict(irf=irf, peak=irf.argmax(axis=1), fwhm=irf_fwhm(irf), llr_level=3.0, max_kept=2)
    t = _table({50: 1}, own_depth=50.5, own_kept=False)
    out = restore_agreed(t, t.keep, **kw)
    assert out.tolist() == [False] * 4 + [True]
    assert t.columns["depth_bin"][-1] == 50.5
    t = _table({56: 1}, own_depth=50.5, own_kept=False, signal=5.0)
    assert not restore_agreed(t, t.keep, **kw).any()
    t = _table({50: 1}, own_depth=50.5, own_kept=False)
    two = t.keep.copy()
    two[:2] = False  # the north and south neighbours lose their surface
    assert not restore_agreed(t, two, **kw).any()


def test_small_median_equals_np_median_with_ties_and_even_counts():
    # the agreement kernel's median (an insertion sort into a kept buffer) gives
    # np.median's value bit for bit: odd and even counts, ties, 1 to 16 values
    from splidar.detection._5_recentre import _small_median

    rng = np.random.default_rng(3)
    srt = np.empty(16)
    for n in range(1, 17):
        for _ in range(50):
            vals = np.empty(16)
            vals[:n] = rng.choice([rng.normal(50, 3, n), np.round(rng.normal(50, 2, n))])
            assert _small_median(vals, srt, n) == np.median(vals[:n])


def _grid_table(rng, R=14, C=14):
    """A random table on an R x C image: 1-2 candidates a pixel near one plane at 50,
    some far off it, about half kept; own counts Poisson around the plane."""
    n_per = rng.integers(1, 3, R * C)
    pix = np.repeat(np.arange(R * C), n_per)
    n = pix.size
    depth = np.where(rng.random(n) < 0.8, 50.0 + rng.normal(0, 0.7, n), rng.uniform(45, 56, n))
    counts = rng.poisson(0.15, (n, 1, W)).astype(np.int32)
    counts[:, 0, 6] += rng.poisson(0.8, n).astype(np.int32)  # bin 50
    bkg = np.zeros((n, 1, W), np.float32)
    bkg[:, :, 1:] = 0.1
    cols = dict(
        row=pix // C, col=pix % C, depth_bin=depth, start=np.full(n, OFFSET + 1),
        stop=np.full(n, OFFSET + W), offset=np.full(n, OFFSET),
        signal=rng.uniform(1.0, 4.0, (n, 1, 1)), scale_index=np.zeros(n, np.int64),
        own_counts=counts, own_background=bkg,
    )  # fmt: skip
    z = np.zeros(n, np.int64)
    return CandidateTable(cols, rng.random(n) < 0.55, np.zeros(n, np.int8), z, z, (R, C))


def test_agreed_items_repeats_give_the_full_tables_outcome():
    # restore_agreed repeated on the items of the pixels a round changed (and their
    # 4-neighbours) restores, round by round, what the repeat over the whole table does
    from splidar.detection._5_recentre import agreed_items

    irf = gaussian_irf(3.0).reshape(1, -1)
    kw = dict(irf=irf, peak=irf.argmax(axis=1), fwhm=irf_fwhm(irf), llr_level=3.0, max_kept=2)
    rounds = []
    for seed in range(12):
        t = _grid_table(np.random.default_rng(seed))
        keep_full, keep_items, items, k = t.keep.copy(), t.keep.copy(), None, 0
        while True:
            full = restore_agreed(t, keep_full, **kw)
            part = restore_agreed(t, keep_items, items=items, **kw)
            np.testing.assert_array_equal(part, full)
            if not full.any():
                break
            keep_full, keep_items, k = keep_full | full, keep_items | part, k + 1
            items = agreed_items(t, part)
            assert items.size < t.keep.size  # a part of the table
        rounds.append(k)
    assert max(rounds) >= 2  # the repeats were exercised


def test_agreed_same_on_any_number_of_threads(monkeypatch):
    # the candidates' agreed depths and signals in parts on threads: each its own
    from splidar.detection import _5_recentre
    from splidar.detection._5_recentre import _agreed

    monkeypatch.setattr(_5_recentre, "_AGREE_PART", 7)  # parts of a few candidates
    fwhm = irf_fwhm(gaussian_irf(3.0).reshape(1, -1))
    found = []
    for seed in range(4):
        t = _grid_table(np.random.default_rng(seed))
        items = np.flatnonzero(np.random.default_rng(seed).random(t.keep.size) < 0.6)
        for near, it in ((0, None), (2, None), (2, items)):
            a1, s1 = _agreed(t, t.keep, fwhm, near, items=it, n_jobs=1)
            found.append(int(np.isfinite(a1).sum()))
            for n_jobs in (2, 3, 8):
                a, s = _agreed(t, t.keep, fwhm, near, items=it, n_jobs=n_jobs)
                np.testing.assert_array_equal(a, a1)
                np.testing.assert_array_equal(s, s1)
    assert min(found) >= 1 and sum(found) > 20  # agreed depths were found
