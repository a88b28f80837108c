"""A moved surface's statistics describe its new depth (stages 5 ``recentre`` and 7
``align_depths``), ``Surfaces.moved_by`` and ``Detection.explain``."""

import numpy as np
import pytest
from test_detection_stages import SCALES, _map

from splidar import SplidarError, gaussian_irf
from splidar.detection import STAGES, PixelStory, detect
from splidar.detection._4_map import _local_scale
from splidar.detection._5_recentre import moved_presence, recentre_runs
from splidar.detection._detect import PASSES
from splidar.detection._filters import Correlator, irf_fwhm
from splidar.detection._kernels import _llr_one
from splidar.detection._slopes import support_sums
from splidar.detection._table import CandidateTable
from splidar.scenes import two_layer_scene

ALIGN = STAGES.index("align_depths")


@pytest.fixture(scope="module")
def net():
    """A net in front of objects (PPP 4, SBR 0.25, decaying background): the default
    detection up to stage 7 (stage 7b, which moves depths after it, left out), and the
    same without stage 7."""
    sim = two_layer_scene((24, 24), n_bins=120).simulate(
        ppp=4, sbr=0.25, background="decaying", rng=0
    )
    det = detect(sim.cube, passes=tuple(p for p in PASSES if p != "edge_bands"))
    no7 = detect(
        sim.cube, passes=tuple(p for p in PASSES if p not in ("align_depths", "edge_bands"))
    )
    return sim, det, no7


def test_moved_presence_at_the_own_depth_is_the_maps():
    # recomputed at the depth the map gave them, every kept candidate's presence
    # statistics are the map's: the same formula, bit for bit (z where the local
    # response is positive; the clean histogram holds no negative response)
    sim = two_layer_scene((16, 16), n_bins=120).simulate(
        ppp=4, sbr=0.25, background="decaying", rng=1
    )
    irf, _, _, mp = _map(np.asarray(sim.cube.counts), sim.cube.irf)
    t = mp.candidates
    ii = np.flatnonzero(t.keep)
    peak = Correlator(irf, 120).peak
    new = moved_presence(t, ii, t.columns["depth_bin"][ii], mp.histograms, SCALES, irf, peak)
    np.testing.assert_array_equal(new["presence_llr"], t.columns["presence_llr"])
    z_map, z = t.columns["presence_z"][ii], new["presence_z"][ii]
    pos = z_map > 0
    assert pos.sum() > 0.9 * ii.size
    np.testing.assert_array_equal(z[pos], z_map[pos])
    assert np.all(z[~pos] == 0.0)


def _table(hist_peak):
    """The hand-made 3 x 3 table of ``test_recentre`` with presence columns and the
    local scale's clean histogram peaking at bin ``hist_peak``: the centre's candidate
    at 55.5 (one photon there), its neighbours' plane at 50 (two own photons)."""
    W, off, n = 13, 44, 5
    pix = [(0, 1), (2, 1), (1, 0), (1, 2), (1, 1)]
    counts = np.zeros((n, 1, W), np.int32)
    for t, k in {49: 1, 51: 1, 56: 1}.items():
        counts[-1, 0, t - off] = k
    bkg = np.zeros((n, 1, W), np.float32)
    bkg[:, :, 1:] = 0.1
    hist = np.zeros((n, 2, 1, W), np.float32)
    hist[:, 1, 0, 1:] = np.exp(-0.5 * ((np.arange(45, 57) - hist_peak) / 1.3) ** 2)
    cols = dict(
        row=np.array([p[0] for p in pix]), col=np.array([p[1] for p in pix]),
        depth_bin=np.array([50.0] * 4 + [55.5]), start=np.full(n, off + 1),
        stop=np.full(n, off + W), offset=np.full(n, off), signal=hist.sum(axis=-1, dtype=float),
        scale_index=np.ones(n, np.int64), own_counts=counts, own_background=bkg,
        presence_llr=np.full(n, -1.0), presence_z=np.full(n, -1.0),
    )  # fmt: skip
    z = np.zeros(n, np.int64)
    table = CandidateTable(cols, np.ones(n, bool), np.zeros(n, np.int8), z, np.arange(n), (3, 3))
    return table, (hist,)


def test_recentre_runs_moved_candidate_presence_follows_its_depth():
    irf = gaussian_irf(3.0).reshape(1, -1)
    table, hist = _table(50.0)
    kw = dict(
        irf=irf, peak=irf.argmax(axis=1), fwhm=irf_fwhm(irf), pfa=0.01, n_bins=200,
        llr_level=3.0, secondary_llr=0.0, max_kept=2,
    )  # fmt: skip
    old = recentre_runs(table, **kw)  # without the histograms: the old statistics stay
    res = recentre_runs(table, **kw, histograms=hist, scales=np.array([1, 3]))
    assert res.moved == old.moved == 1
    np.testing.assert_array_equal(res.table.columns["depth_bin"], old.table.columns["depth_bin"])
    np.testing.assert_array_equal(res.table.keep, old.table.keep)
    c = res.table.columns
    assert c["depth_bin"][-1] == 50.0 and old.table.columns["presence_llr"][-1] == -1.0
    at = moved_presence(table, [4], [50.0], hist, [1, 3], irf, irf.argmax(axis=1))
    at_old = moved_presence(table, [4], [55.5], hist, [1, 3], irf, irf.argmax(axis=1))
    assert c["presence_llr"][-1] == at["presence_llr"][-1]
    assert c["presence_z"][-1] == at["presence_z"][-1]
    # two own photons at the new depth, one at the old; the local response peaks there
    assert at["presence_llr"][-1] > at_old["presence_llr"][-1]
    assert at["presence_z"][-1] > 3 * at_old["presence_z"][-1] > 0
    np.testing.assert_array_equal(c["presence_llr"][:4], -1.0)  # not moved: unchanged
    assert res.table.moved_codes().tolist() == [-1] * 4 + [STAGES.index("recentre")]
    assert old.table.moved_codes().tolist() == [-1] * 4 + [STAGES.index("recentre")]


def test_align_depths_moved_surfaces_statistics_follow_their_depth(net):
    sim, det, no7 = net
    s, b = det.surfaces, no7.surfaces
    np.testing.assert_array_equal(s.row, b.row)
    np.testing.assert_array_equal(s.slot, b.slot)
    moved = s.depth_bin != b.depth_bin
    assert moved.sum() >= 3
    np.testing.assert_array_equal(s.moved_by == ALIGN, moved)
    assert {r.stage: r for r in det.provenance}["align_depths"].moved == moved.sum()
    # presence_llr: the map's own-count log-likelihood ratio at the surface's depth,
    # over its window and support, from the raw counts (the slope pass's surfaces use
    # a pooled intensity: left out unless moved)
    irf = np.atleast_2d(np.asarray(det.irf, np.float64))
    pk, q, W = irf.argmax(axis=1).astype(float), _local_scale(np.array(det.scales)), 13
    y = np.asarray(sim.cube.counts)
    check = moved | (s.stage != STAGES.index("slopes"))
    for i in np.flatnonzero(check):
        w = s.offset[i] + np.arange(s.histograms.shape[-1])
        W = w.size
        inside = (w >= s.start[i]) & (w < s.stop[i])
        raw = y[s.row[i], s.col[i], :, w[0] : w[-1] + 1].astype(float) * inside
        bh = det.background.at([s.row[i]], [s.col[i]])[0][:, w[0] : w[-1] + 1]
        llr = _llr_one(raw, bh, inside, s.depth_bin[i] - w[0],
                       np.ascontiguousarray(s.signal[i, q]), irf, pk, irf.shape[0], W)  # fmt: skip
        assert s.presence_llr[i] == pytest.approx(llr, rel=1e-9, abs=1e-9), i
        if moved[i] and b.presence_llr[i] != pytest.approx(llr, abs=1e-6):
            assert s.presence_llr[i] != b.presence_llr[i]
    # saliency mass and evidence: summed over the support wherever the support moved
    sup = moved & ((s.start != b.start) | (s.stop != b.stop))
    m, e = support_sums(det.saliency, det.threshold, s.row, s.col, s.start, s.stop)
    np.testing.assert_array_equal(s.saliency_mass[sup], m[sup])
    np.testing.assert_array_equal(s.evidence[sup], e[sup])
    np.testing.assert_array_equal(s.saliency_mass[~sup], b.saliency_mass[~sup])
    assert (s.presence_z[moved] != b.presence_z[moved]).all()


def test_detection_explain_tells_a_pixels_story(net):
    _, det, _ = net
    s = det.surfaces
    i = int(np.flatnonzero(s.moved_by == ALIGN)[0])
    story = det.explain(int(s.row[i]), int(s.col[i]))
    assert isinstance(story, PixelStory)
    mine = [t for t in story.surfaces if t.index == i][0]
    assert mine.moved_by == "align_depths" and mine.depth_bin == s.depth_bin[i]
    assert mine.added_by == STAGES[s.stage[i]] and mine.presence_llr == s.presence_llr[i]
    text = str(story)
    assert f"pixel ({s.row[i]}, {s.col[i]})" in text and "moved by 'align_depths'" in text
    assert [t.slot for t in story.surfaces] == sorted(t.slot for t in story.surfaces)
    n_pix = np.bincount(s.row * 24 + s.col, minlength=24 * 24)
    if (n_pix == 0).any():
        r, c = divmod(int(np.flatnonzero(n_pix == 0)[0]), 24)
        assert det.explain(r, c).surfaces == () and "0 surfaces" in str(det.explain(r, c))
    with pytest.raises(SplidarError, match="`row`"):
        det.explain(1.5, 0)
    with pytest.raises(SplidarError, match="24 x 24"):
        det.explain(0, 24)
    table = det.provenance_table()
    assert "placed" in table.splitlines()[0]
    line = next(x for x in table.splitlines() if x.startswith("align_depths"))
    assert line.split()[-1] == str(int((s.moved_by == ALIGN).sum()))
