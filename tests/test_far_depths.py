"""Stage 7's far-depth rule (``move_far_depths``): a plane's pixel holding a far cluster."""

from dataclasses import replace

import numpy as np

from splidar import gaussian_irf
from splidar.detection._7_align_depths import move_far_depths
from splidar.detection._result import Background, Surfaces

T = 200
PLANE, FAR = 100.0, 40.0


def _plane(own_counts: dict) -> tuple:
    """A 5 x 5 flat plane at bin 100 (0.8 photons each), the centre's surface at bin 40;
    the centre's raw counts ``{bin: photons}``, a flat background of 0.016 per bin."""
    rows, cols = np.divmod(np.arange(25), 5)
    depth = np.full(25, PLANE)
    depth[12] = FAR
    n = 25
    surf = Surfaces(
        row=rows, col=cols, slot=np.zeros(n, int), depth_bin=depth,
        start=depth.astype(int) - 2, stop=depth.astype(int) + 3, scale_index=np.zeros(n, int),
        offset=depth.astype(int) - 2, histograms=np.zeros((n, 1, 1, 5), np.float32),
        signal=np.full((n, 1, 1), 0.8), counts=np.ones((n, 1)), background=np.zeros((n, 1)),
        saliency_mass=np.ones(n), image_shape=(5, 5), n_slots=2,
    )  # fmt: skip
    counts = np.zeros((5, 5, 1, T), np.uint16)
    for t, k in own_counts.items():
        counts[2, 2, 0, t] = k
    bg = Background(
        spatial=np.full((5, 5, 1), 0.016, np.float32), temporal=np.full((1, T), 0.016, np.float32)
    )
    irf = gaussian_irf(3.0)[None]  # (L, n)
    return surf, counts, bg, irf


def test_move_far_depths_moves_a_far_cluster_whose_own_counts_hold_the_plane():
    # two background photons at bin 40, one at the plane's bin 100: a cluster that beat
    # a missed return; the plane predicts 100 and the own counts do not reject it
    surf, counts, bg, irf = _plane({40: 1, 41: 1, 100: 1})
    out, n = move_far_depths(surf, counts, bg, fwhm=3.0, irf=irf)
    assert n == 1
    assert out.depth_bin[12] == PLANE
    # the support and its raw counts follow (reconstruct's IRF fraction is taken there)
    assert out.start[12] <= PLANE < out.stop[12]
    assert out.counts[12, 0] == counts[2, 2, 0, out.start[12] : out.stop[12]].sum() == 1
    assert np.array_equal(np.delete(out.depth_bin, 12), np.delete(surf.depth_bin, 12))


def test_move_far_depths_keeps_a_bright_off_plane_pixel():
    # eight photons at bin 40 and none on the plane: an off-plane return, kept
    surf, counts, bg, irf = _plane({39: 2, 40: 4, 41: 2})
    out, n = move_far_depths(surf, counts, bg, fwhm=3.0, irf=irf)
    assert n == 0
    assert out.depth_bin[12] == FAR


def test_move_far_depths_keeps_a_surface_a_neighbour_continues():
    # the north-west neighbour holds bin 41 (a structure, not a cluster; the opposite
    # pairs still agree on the plane): no move
    surf, counts, bg, irf = _plane({40: 1, 41: 1, 100: 1})
    d = surf.depth_bin.copy()
    d[6] = FAR + 1
    out, n = move_far_depths(replace(surf, depth_bin=d), counts, bg, fwhm=3.0, irf=irf)
    assert n == 0
