"""Stage 5g (clean-up): where the image shows no second layer, a pixel's further
candidates must pass the presence level that refutes a first one.

The map keeps a pixel's further candidates when its own counts favour them at all
(log-ratio >= ``PRESENCE_SECONDARY`` = 0 nats), so that the dim object behind a sheet or
a net, often the lower-ranked of its pixel's two surfaces, is not lost. In a scene with
no second layer the same leniency keeps the spread of a neighbour's return beside a depth
edge and the background's alarms behind a pixel's surface: on issue #15's
single-surface cells they are most of the false surfaces (``benchmarks/README.md``,
"Lead, session 32"). Whether the scene *has* a second layer is read from the detection's
geometry by stage 7d's model (:func:`~splidar.detection._7d_layer_evidence.layer_evidence`:
a pixel's depths continuing as pairs among its neighbours, counted over the whole image
against the null's rate ``surface_pfa`` per pixel, or shown by most of the pixels that
hold two or more surfaces: :func:`image_layered`; and, where the image as a whole is not
layered, in a window of ``REACH_BOXES`` x the largest box's half-width about each pixel,
stage 5f's reach: a net over part of the scene). Where neither is layered, each
pixel holding two or more kept candidates keeps the one of largest own-count log-ratio
``presence_llr`` and those of the others that reach ``PRESENCE_LLR`` (3 nats: the level
at which a first candidate's own counts refute it, ``-PRESENCE_LLR``, taken the other
way); a pixel never loses its last candidate. A layered image, or window, is left as it
is.

No tuned constant: the gate's window (the whole image) and level (``surface_pfa``) are
stage 7d's, its second test a majority, the local window stage 5f's reach, the depth
gate is stage 7c's, the reach the largest box's half-width, the level the presence
test's.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy import stats

from ._5f_stray_clusters import REACH_BOXES
from ._7c_spread_groups import GATE_FWHM
from ._7d_layer_evidence import _evidence, depth_slots, window_counts
from ._table import CandidateTable, PassResult, skipped, with_keep

__all__ = ["image_layered", "remove_unlayered_seconds", "unlayered_seconds"]

logger = logging.getLogger(__name__)


def image_layered(row, col, depth, image_shape, *, fwhm: float, half: int, surface_pfa: float):
    """Whether the image shows a second layer: stage 7d's evidence (a pixel's depths
    continuing as pairs among its neighbours, ``layer_evidence``) in more pixels than the
    null explains, or in most of the pixels holding two or more surfaces.

    The first test is stage 7d's over the whole image (``layer_evidence(...,
    radius=None).layered.any()``): ``P(N >= count) < surface_pfa`` for ``N`` Poisson with
    mean ``surface_pfa`` x pixels, i.e. ``count`` reaching the smallest such ``n``; the
    evidence is counted only until it does (a layered image stops early). The second is
    the per-pixel majority (``n_2 > n_1``) taken over the image: more than half of the
    crowded pixels show the evidence. It keeps the layers whose second surfaces are too
    few for the first test (the net at PPP 1 on 64 x 64 pixels: 35-36 evidence pixels
    against the null's 41, of 51-54 crowded pixels), while a spread strip beside a depth
    edge shows none (its further depth is held alone by its source region) and the
    background's alarms few (``benchmarks/README.md``, "Lead, session 32").

    Parameters
    ----------
    row, col : ndarray (S,) int
    depth : ndarray (S,) float
        The kept candidates' depths (bins).
    image_shape : (int, int)
    fwhm : float
        The IRF's FWHM (bins); depths within ``GATE_FWHM`` of it are one.
    half : int
        The largest box's half-width (pixels).
    surface_pfa : float
        ``detect``'s option: the null's false surfaces per pixel.

    Returns
    -------
    bool
    """
    return _whole_image(
        row, col, depth, image_shape, fwhm=fwhm, half=half, surface_pfa=surface_pfa
    )[0]


def _whole_image(row, col, depth, image_shape, *, fwhm, half, surface_pfa):
    """:func:`image_layered`'s decision and the evidence map (rows, cols) bool it read:
    complete when the image is not layered (the count stops early only when it is)."""
    R, C = image_shape
    expected = float(surface_pfa) * R * C
    # the smallest n with P(N >= n) < surface_pfa (sf(n - 1) decreases with n)
    stop = int(stats.poisson.isf(float(surface_pfa), expected)) + 1
    while stop > 1 and stats.poisson.sf(stop - 2, expected) < surface_pfa:
        stop -= 1
    while stats.poisson.sf(stop - 1, expected) >= surface_pfa:
        stop += 1
    D, n = depth_slots(row, col, depth, image_shape)
    ev = np.zeros(n.shape, np.bool_)
    count = _evidence(D, n, GATE_FWHM * float(fwhm), int(half), ev, stop)
    # a layer the null's rate cannot show yet (few second surfaces detected: low flux,
    # a small image) still shows in most of the crowded pixels
    return bool(count >= stop or 2 * count > int((n >= 2).sum())), ev


def _locally_layered(ev, rows, cols, *, radius: int, surface_pfa: float) -> np.ndarray:
    """Stage 7d's test in the window of ``radius`` pixels about each ``(rows, cols)``:
    ``layer_evidence(..., radius=radius).layered`` there, computed at those pixels only."""
    count, area = window_counts(ev, radius, at=(rows, cols))
    return stats.poisson.sf(count - 1, float(surface_pfa) * area) < float(surface_pfa)


def unlayered_seconds(
    row, col, depth, presence_llr, keep, *, image_shape, fwhm: float, half: int,
    surface_pfa: float, level: float,
) -> np.ndarray:  # fmt: skip
    """``(n,)`` bool: the kept candidates stage 5g removes (see the module).

    Parameters
    ----------
    row, col : ndarray (n,) int
    depth : ndarray (n,) float
        Depth bins.
    presence_llr : ndarray (n,) float
        The own-count log-ratio of each candidate (nats).
    keep : ndarray (n,) bool
        The kept candidates; the others are ignored.
    image_shape : (int, int)
    fwhm : float
        The IRF's FWHM (bins).
    half : int
        The largest box's half-width (pixels).
    surface_pfa : float
        ``detect``'s option: the null's false surfaces per pixel.
    level : float
        The presence level a further candidate must reach (nats).
    """
    keep = np.asarray(keep, bool)
    out = np.zeros(keep.size, bool)
    idx = np.flatnonzero(keep)
    if idx.size < 2:
        return out
    R, C = image_shape
    r, c = np.asarray(row, np.int64)[idx], np.asarray(col, np.int64)[idx]
    pix = r * C + c
    crowded = np.bincount(pix, minlength=R * C)[pix] >= 2
    if not crowded.any():  # no pixel holds two
        return out
    d = np.asarray(depth, np.float64)[idx]
    layered, ev = _whole_image(r, c, d, (R, C), fwhm=fwhm, half=half, surface_pfa=surface_pfa)
    if layered:
        logger.debug("unlayered: the image shows a second layer; nothing removed")
        return out
    # a layer over part of the image only (a net in front of one object, at low flux)
    rc, cc = r[crowded], c[crowded]
    free = ~_locally_layered(ev, rc, cc, radius=REACH_BOXES * int(half), surface_pfa=surface_pfa)
    sel = idx[crowded][free]  # the candidates of crowded pixels outside a layered window
    p = pix[crowded][free]
    llr = np.asarray(presence_llr, np.float64)[sel]
    order = np.lexsort((-llr, p))  # by pixel, the largest log-ratio first
    q = p[order]
    further = order[np.r_[False, q[1:] == q[:-1]]]
    out[sel[further[llr[further] < level]]] = True
    logger.debug(
        "unlayered: no second layer in the image; %d of %d further candidates below %g "
        "nats removed", int(out.sum()), further.size, level,
    )  # fmt: skip
    return out


def remove_unlayered_seconds(
    table: CandidateTable, *, fwhm: float, half: int, surface_pfa: float, level: float
) -> PassResult:
    """Stage 5g: remove the further candidates below ``level`` of an image that shows no
    second layer (see the module).

    Parameters
    ----------
    table : CandidateTable
        Needs the ``presence_llr`` column.
    fwhm : float
        The IRF's FWHM (bins).
    half : int
        The largest box's half-width (pixels).
    surface_pfa : float
        ``detect``'s option.
    level : float
        Nats (``detect`` passes ``PRESENCE_LLR``).
    """
    if not table.keep.any():
        return skipped("unlayered", table)
    t0 = time.perf_counter()
    c = table.columns
    drop = unlayered_seconds(
        c["row"], c["col"], c["depth_bin"], c["presence_llr"], table.keep,
        image_shape=table.image_shape, fwhm=fwhm, half=half, surface_pfa=surface_pfa,
        level=level,
    )  # fmt: skip
    return with_keep("unlayered", table, table.keep & ~drop, t0)
