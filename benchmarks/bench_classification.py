"""Spectral classification at low photon counts (issue 14): accuracy, calibration, time.

Scenes (:func:`splidar.scenes.multispectral_scene`, 3 materials, 4 wavelengths, 64 x 64
pixels, SBR 1): ``one`` (one surface per pixel, bands of material with a patch of
another in each), ``two`` (a one-pixel net of another material in front: two surfaces
on the net's pixels) and ``thin`` (``one`` plus, in each band, a one-pixel-wide vertical
strand and two 3 x 3 patches of another material at the same depth as their
surroundings, so the depth gate does not separate them), each with a uniform and a
decaying background, PPP 1 / 4 / 10 / 50; then the Art scene (3 wavelengths, 4 colour
classes, two surfaces per pixel) at PPP 4 / 16 / 64.

Per cell, over the detected surfaces matched to a true one (``match_points``, tau = 4
bins; Art: 4 mm): label accuracy of ``splidar.process`` (``max_surfaces=2``), of the
per-pixel signature classifier on the same surfaces
(:func:`splidar.baselines.per_pixel_classify`, MSTD-like) and of the same followed by a
majority filter (:func:`splidar.baselines.majority_filter_labels`), the most common
class rate among the matched true labels, accuracy on thin strands / nets and on small
patches, time of classification against the whole ``process``. Then the expected
calibration error (ECE, 10 equal-width bins of confidence) of ``label_confidence``
over all matched points of the multispectral cells, and a reliability figure. On Art
also the accuracy of an oracle that sums the same class likelihood over the *true*
regions (:func:`oracle_regions`): the ceiling of any spatial pooling of it. Every cell
also prints :func:`evidence_budget`: what the photons say about the true labels (the
class log-likelihood of the expected counts, true class against the best other, summed)
against what the true label map costs under the Potts prior (its cut links' strength),
and whether the field's errors follow the photons' noise (docs/classification.md, "The
evidence budget").

Usage::

    python benchmarks/bench_classification.py                # about 5-8 minutes
    python benchmarks/bench_classification.py --quick        # PPP 1 and 10, no Art
    python benchmarks/bench_classification.py --figure rel.png --json rows.json
    # --figure also writes rel_art.png (Art) and, with --art-objects, rel_art_objects.png
    python benchmarks/bench_classification.py --shares       # + smoothed colour shares (3 min)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import splidar
from splidar.metrics import match_points
from splidar.reconstruction import (
    build_graph,
    class_loglik,
    irf_fraction,
    link_gamma,
    nearest_signature,
)
from splidar.scenes import art_scene, multispectral_scene

try:  # added in issue 14, session 12 (absent before it: the figure is left out)
    from splidar.reconstruction import estimate_gamma
except ImportError:  # pragma: no cover
    estimate_gamma = None

try:  # the baselines added with issue 14 (absent before it: computed here then)
    from splidar.baselines import majority_filter_labels, per_pixel_classify
    from splidar.reconstruction import flag_unknown
except ImportError:  # pragma: no cover - the "before" measurement
    majority_filter_labels = per_pixel_classify = flag_unknown = None

PPP = (1.0, 4.0, 10.0, 50.0)
PPP_ART = (4.0, 16.0, 64.0)
SHAPE = (64, 64)


def _default_data() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def thin_scene(shape=SHAPE):
    """``multispectral_scene`` plus one-pixel strands and 3 x 3 patches at the same depth.

    Returns ``(scene, thin)``: ``thin`` marks the truth points of strands and patches
    (their own material ``(k + 2) mod 3`` in band k)."""
    sc = multispectral_scene(shape, n_bins=200)
    t = sc.truth
    K = sc.library.n_classes
    sig = sc.library.signatures
    rows, cols = shape
    band_w = cols / K
    mark = np.zeros(shape, bool)
    for k in range(K):
        c0 = int(k * band_w + 0.2 * band_w)
        mark[4 : int(0.5 * rows), c0] = True  # a strand, 1 pixel wide
        cp = int(k * band_w + 0.6 * band_w)
        mark[8:11, cp : cp + 3] = True  # two small patches
        mark[25:28, cp : cp + 3] = True
    sel = mark[t.row, t.col]
    lab = t.label.copy()
    new = (lab + 2) % K
    lab[sel] = new[sel]
    inten = t.intensity.copy()
    inten[sel] = inten[sel] * sig[new[sel]] / sig[t.label[sel]]
    truth = replace(t, label=lab, intensity=inten)
    return replace(sc, truth=truth, name="multispectral_thin"), sel


def _per_pixel_labels(det, sig):
    """Per-surface classification of the detected surfaces (nearest signature)."""
    s = det.surfaces
    L = det.n_wavelengths
    y = np.asarray(s.counts, np.float64).reshape(len(s), L)
    b = np.asarray(s.background, np.float64).reshape(len(s), L)
    eta = np.maximum(irf_fraction(np.atleast_2d(det.irf), s.depth_bin, s.start, s.stop), 1e-6)
    if per_pixel_classify is not None:
        lab = per_pixel_classify(det, sig)
        return lab, majority_filter_labels(det, lab)
    return nearest_signature((y - b) / eta, sig), None


def ece(conf, correct, n_bins=10):
    """Expected calibration error: sum over confidence bins of |accuracy - mean conf| x share."""
    conf = np.asarray(conf, np.float64)
    correct = np.asarray(correct, np.float64)
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    idx = np.clip(np.digitize(conf, edges) - 1, 0, n_bins - 1)
    out = 0.0
    for i in range(n_bins):
        m = idx == i
        if np.any(m):
            out += m.mean() * abs(correct[m].mean() - conf[m].mean())
    return out


def colour_boundary(truth, shape):
    """Truth points with a 4-neighbour pixel of the same layer holding another label."""
    rows, cols = shape
    out = np.zeros(len(truth.label), bool)
    for layer in np.unique(truth.layer):
        m = truth.layer == layer
        img = np.full(shape, -1)
        img[truth.row[m], truth.col[m]] = truth.label[m]
        pad = np.pad(img, 1, constant_values=-1)
        diff = np.zeros(shape, bool)
        for dr, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):
            nb = pad[dr : dr + rows, dc : dc + cols]
            diff |= (nb >= 0) & (nb != img)
        out[m] = diff[truth.row[m], truth.col[m]]
    return out


def oracle_regions(det, truth, est, true_idx, sig, shape):
    """Accuracy of an oracle that knows the true regions: each matched surface's class
    log-likelihood (:func:`splidar.reconstruction.class_loglik`, the classifier's own
    evidence) summed over its true region (connected pixels of one label in one layer),
    argmax. The ceiling of any spatial pooling of this likelihood."""
    from scipy import ndimage

    s = det.surfaces
    L = det.n_wavelengths
    y = np.asarray(s.counts, np.float64).reshape(len(s), L)
    b = np.asarray(s.background, np.float64).reshape(len(s), L)
    eta = np.maximum(irf_fraction(np.atleast_2d(det.irf), s.depth_bin, s.start, s.stop), 1e-6)
    ll = class_loglik(y, b, eta, sig)[est]
    region = np.zeros(len(truth.label), np.int64)
    n = 0
    for layer in np.unique(truth.layer):
        m = truth.layer == layer
        img = np.full(shape, -1)
        img[truth.row[m], truth.col[m]] = truth.label[m]
        for k in np.unique(truth.label[m]):
            lab, nk = ndimage.label(img == k)
            sel = m & (truth.label == k)
            region[sel] = lab[truth.row[sel], truth.col[sel]] + n
            n += nk + 1
    r = region[true_idx]
    sums = np.zeros((n + 1, ll.shape[1]))
    np.add.at(sums, r, ll)
    return float(np.mean(np.argmax(sums[r], axis=1) == truth.label[true_idx]))


def evidence_budget(rec, truth, est, true_idx, sig, gamma=1.5):
    """What the photons can tell about the labels against what the truth's map costs.

    ``evidence``: over the matched surfaces, the class log-likelihood
    (:func:`splidar.reconstruction.class_loglik`) of each surface's *expected* counts
    (its true intensity times its IRF fraction, plus its background) under its true
    class minus under the best other class, summed (nats; what the photons say about the
    labels on average, no noise). ``boundary``: the interaction strength
    (:func:`splidar.reconstruction.link_gamma`, ``gamma``) summed over the links of the
    depth-gated graph that join two matched surfaces of different true labels, i.e. what
    the truth's label map costs under the Potts prior. Where ``evidence`` is well below
    ``boundary`` no Potts-type field can find the true map. Also the selection signature
    of the field's errors: on the surfaces ``rec`` gets wrong, the mean log-likelihood
    ratio (given label minus true label) of their photons and of their expected counts.
    ``mpl_truth`` / ``mpl_field``: the maximum pseudo-likelihood interaction strength
    (:func:`splidar.reconstruction.estimate_gamma`) of the true labels and of the
    field's labels on the graph of the matched surfaces: how strongly each map clusters
    (the field's above the truth's: the field smooths more than the scene).
    """
    det = rec.detection
    s = det.surfaces
    L = det.n_wavelengths
    y = np.asarray(s.counts, np.float64).reshape(len(s), L)
    b = np.asarray(s.background, np.float64).reshape(len(s), L)
    eta = np.maximum(irf_fraction(np.atleast_2d(det.irf), s.depth_bin, s.start, s.stop), 1e-6)
    tl = truth.label[true_idx]
    ye = eta[est] * np.asarray(truth.intensity, np.float64)[true_idx] + b[est]
    lle = class_loglik(ye, b[est], eta[est], sig)
    other = np.where(np.arange(sig.shape[0])[None, :] == tl[:, None], -np.inf, lle)
    ev = lle[np.arange(tl.size), tl] - other.max(axis=1)
    gate = rec.hyperparameters.get("depth_gate", np.inf)
    links = "all" if not np.isfinite(gate) else "depth"
    g = build_graph(
        s.row, s.col, s.slot, s.depth_bin, s.image_shape, int(s.n_slots), links=links, gate=gate
    )
    lab = np.full(len(s), -1)
    lab[est] = tl
    src = np.repeat(np.arange(len(s)), np.diff(g.indptr))
    cut = (src < g.indices) & (lab[src] >= 0) & (lab[g.indices] >= 0)
    cut &= lab[src] != lab[g.indices]
    boundary = float(link_gamma(g, gamma)[cut].sum())
    given = rec.points.label[est]
    gm = build_graph(
        s.row[est], s.col[est], s.slot[est], s.depth_bin[est], s.image_shape, int(s.n_slots),
        links=links, gate=gate,
    )  # fmt: skip
    K = sig.shape[0]
    nan = float("nan")
    mpl = [estimate_gamma(v, gm, n_classes=K) if estimate_gamma else nan for v in (tl, given)]
    wrong = given != tl
    ll = class_loglik(y[est][wrong], b[est][wrong], eta[est][wrong], sig)
    llw = class_loglik(ye[wrong], b[est][wrong], eta[est][wrong], sig)
    i = np.arange(int(wrong.sum()))
    gw, tw = given[wrong], tl[wrong]
    return {
        "evidence": float(ev.sum()),
        "evidence_per_surface": float(ev.mean()),
        "boundary_cost": boundary,
        "mpl_truth": mpl[0],
        "mpl_field": mpl[1],
        "wrong_llr_photons": float(np.mean(ll[i, gw] - ll[i, tw])) if i.size else float("nan"),
        "wrong_llr_expected": float(np.mean(llw[i, gw] - llw[i, tw])) if i.size else float("nan"),
    }


#: smoothing steps of :func:`share_smoothing` (lazy averages over the graph; the
#: effective number of surfaces pooled is about 4.6 / 9 / 17 / 30 / 55 / 100 / 170 /
#: 280 at 1 / 2 / 4 / ... / 128 steps on Art)
SHARE_STEPS = (0, 1, 2, 4, 8, 16, 32, 64, 128)


def share_smoothing(
    rec, truth, est, true_idx, sig, steps=SHARE_STEPS, n_splits=4, seed=0, special=None
):
    """Classification from spatially smoothed colour shares (session 15, measured, not built).

    The hypothesis: a class map made by k-means of colour shares (Art) is a quantisation
    of a smooth field, so smoothing the *shares* (not the labels) is the right prior.
    Each surface's counts, background and IRF fraction are pooled over the label field's
    graph (depth-gated, one-pixel gaps bridged, as in ``reconstruct``) by ``n`` lazy
    averaging steps ``x <- (x + sum of the neighbours' x) / (1 + degree)`` (a heat
    kernel of variance about ``n`` links), scaled to the effective number of surfaces
    pooled (``1 / sum w**2``, estimated with random signs), and classified by
    :func:`splidar.reconstruction.class_loglik` of the pooled counts (argmax). Per step
    count: ``photons`` (that accuracy over the matched surfaces) and ``noise_free`` (the
    same smoothing applied to the matched surfaces' *true* colour shares, classified by
    the shares' log-likelihood under the signatures: the ceiling that the smoothing's
    bias alone leaves, whatever the photons). The bandwidth chosen from the data by
    photon thinning: each surface's counts split binomially in halves ``n_splits``
    times, one half smoothed, the multinomial deviance of the other half's colour under
    the smoothed shares summed; the best step count for half the photons is halved for
    all of them (``thinned_steps``, ``thinned``). ``choice``: per surface, the label of
    the more confident of the field (``label_confidence``) and the thinned smoothing
    (its posterior from the pooled counts), with ``thinned_ece`` the calibration of that
    posterior. Returns a dict of these (accuracies over the matched surfaces)."""
    import scipy.sparse as sparse

    det = rec.detection
    s = det.surfaces
    L = det.n_wavelengths
    S = len(s)
    y = np.asarray(s.counts, np.float64).reshape(S, L)
    b = np.asarray(s.background, np.float64).reshape(S, L)
    eta = np.maximum(irf_fraction(np.atleast_2d(det.irf), s.depth_bin, s.start, s.stop), 1e-6)
    gate = rec.hyperparameters.get("depth_gate", np.inf)
    links = "all" if not np.isfinite(gate) else "depth"
    g = build_graph(
        s.row, s.col, s.slot, s.depth_bin, s.image_shape, int(s.n_slots), links=links,
        gate=gate, bridge=True,
    )  # fmt: skip
    A = sparse.csr_matrix((np.ones(g.indices.size), g.indices, g.indptr), shape=(S, S))
    P = sparse.diags(1.0 / (1.0 + np.diff(g.indptr))) @ (sparse.eye(S) + A)
    P = P.tocsr()
    tl = truth.label[true_idx]
    logc = np.log(sig / sig.sum(axis=1, keepdims=True))
    tsh = np.zeros((S, L))
    ti = np.asarray(truth.intensity, np.float64)[true_idx]
    tsh[est] = ti / ti.sum(axis=1, keepdims=True)
    has = np.zeros(S)
    has[est] = 1.0
    rng = np.random.default_rng(seed)
    z = rng.choice([-1.0, 1.0], size=(S, 8))
    halves = [rng.binomial(y.astype(np.int64), 0.5).astype(np.float64) for _ in range(n_splits)]
    xs = [y, b, eta, tsh, has, z] + halves
    out = {"share_steps": list(steps), "share_photons": [], "share_noise_free": []}
    dev, kept, n = [], {}, 0
    for st in steps:
        while n < st:
            xs = [P @ x for x in xs]
            n += 1
        Y, B, E, T, H, Z = xs[:6]
        neff = 1.0 / np.maximum((Z**2).mean(axis=1), 1e-12)[:, None]
        ll = class_loglik(Y * neff, B * neff, E * neff, sig)
        kept[st] = ll
        out["share_photons"].append(float(np.mean(np.argmax(ll[est], axis=1) == tl)))
        t = T[est] / np.maximum(H[est], 1e-12)[:, None]
        out["share_noise_free"].append(float(np.mean(np.argmax(t @ logc.T, axis=1) == tl)))
        d = 0.0
        for h, y1 in zip(halves, xs[6:], strict=True):
            q = (y1 + 1e-6) / (y1 + 1e-6).sum(axis=1, keepdims=True)
            d -= float(((y - h) * np.log(q)).sum())
        dev.append(d)
    pick = steps[int(np.argmin(dev))]
    full = max((st for st in steps if st <= pick // 2), default=steps[0])
    ll = kept[full]
    post = np.exp(ll - ll.max(axis=1, keepdims=True))
    post /= post.sum(axis=1, keepdims=True)
    lab = np.argmax(ll, axis=1)
    ok = lab[est] == tl
    conf = rec.points.label_confidence
    choice = np.where(post.max(axis=1) > conf, lab, rec.points.label)
    out.update(
        thinned_steps=int(full),
        thinned=float(ok.mean()),
        thinned_ece=ece(post.max(axis=1)[est], ok),
        choice=float(np.mean(choice[est] == tl)),
    )
    if special is not None and np.any(special):
        out["thinned_special"] = float(ok[special].mean())
    return out


def _segments(img, shape, step):
    """Connected components of the 4-neighbour pixels whose values differ by <= step."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    idx = np.arange(img.size).reshape(shape)
    pairs = [(idx[:, :-1], idx[:, 1:], img[:, :-1] - img[:, 1:])]
    pairs.append((idx[:-1, :], idx[1:, :], img[:-1, :] - img[1:, :]))
    a = np.concatenate([p[0][np.abs(p[2]) <= step] for p in pairs])
    b = np.concatenate([p[1][np.abs(p[2]) <= step] for p in pairs])
    adj = coo_matrix((np.ones(a.size), (a, b)), shape=(img.size, img.size))
    return connected_components(adj, directed=False)[1].reshape(shape)


def art_label_map(scene, depth_step=0.5):
    """How sound is Art's class map as a ground truth? Figures of the front layer.

    Regions (4-connected, one label): their number and the share of pixels in regions
    under 2 / 10 / 50 / 200 / 1000 pixels; the share beside a class boundary; the k-means
    margin (distance of the colour shares to the second nearest class centre minus the
    nearest: near 0 the label is a coin toss between two colours that differ by less
    than the photons can see); the accuracy of the per-pixel classifier with infinite
    photons (``nearest_signature`` on the exact intensities) overall, on and off the
    boundaries; the agreement of the map with its own N x N majority filter (what a
    classifier that pools an N x N window of exact labels keeps); and the agreement
    with one label per object (depth-connected segments, ``depth_step`` bins, each
    given its majority class)."""
    from scipy import ndimage

    t, shape = scene.truth, scene.shape
    m = t.layer == 0
    lab = np.full(shape, -1)
    lab[t.row[m], t.col[m]] = t.label[m]
    inten = np.zeros(shape + (t.intensity.shape[1],))
    inten[t.row[m], t.col[m]] = t.intensity[m]
    dep = np.zeros(shape)
    dep[t.row[m], t.col[m]] = t.depth_bin[m]
    K = scene.library.n_classes
    out = {"n_pixels": int(lab.size)}
    size_of = np.zeros(shape, np.int64)
    n_reg = 0
    for k in range(K):
        reg, n = ndimage.label(lab == k)
        n_reg += n
        sz = np.bincount(reg.ravel())
        size_of[lab == k] = sz[reg[lab == k]]
    out["n_regions"] = n_reg
    for n in (2, 10, 50, 200, 1000):
        out[f"in_regions_under_{n}"] = float(np.mean(size_of < n))
    edge = colour_boundary(t, shape)[m]
    bd = np.zeros(shape, bool)
    bd[t.row[m], t.col[m]] = edge
    out["beside_boundary"] = float(bd.mean())
    share = inten / inten.sum(axis=-1, keepdims=True)
    cent = np.stack([share[lab == k].mean(axis=0) for k in range(K)])
    dist = np.sort(np.sqrt(((share[..., None, :] - cent) ** 2).sum(-1)), axis=-1)
    margin = dist[..., 1] - dist[..., 0]
    for thr in (0.01, 0.02, 0.04):
        out[f"margin_under_{thr}"] = float(np.mean(margin < thr))
        out[f"margin_under_{thr}_boundary"] = float(np.mean(margin[bd] < thr))
    nf = nearest_signature(inten.reshape(-1, inten.shape[-1]), scene.library.signatures)
    nf = nf.reshape(shape) == lab
    out["infinite_photons"] = float(nf.mean())
    out["infinite_photons_boundary"] = float(nf[bd].mean())
    out["infinite_photons_inside"] = float(nf[~bd].mean())
    for n in (3, 5, 7, 11, 15):
        votes = [ndimage.uniform_filter((lab == k) * 1.0, n, mode="nearest") for k in range(K)]
        out[f"majority_{n}x{n}"] = float(np.mean(np.argmax(votes, axis=0) == lab))
    seg = _segments(dep, shape, depth_step)
    cnt = np.zeros((seg.max() + 1, K))
    np.add.at(cnt, (seg.ravel(), lab.ravel()), 1)
    out["n_objects"] = int(seg.max() + 1)
    out["one_label_per_object"] = float(np.mean(np.argmax(cnt, axis=1)[seg] == lab))
    return out


def art_object_scene(scene, depth_step=0.5):
    """A second, clearly separate Art variant (``art_objects``): one class per object.

    Objects are the depth-connected segments of the front layer (4-neighbour steps of at
    most ``depth_step`` bins), each given the majority of Art's k-means labels over it;
    every pixel keeps its brightness (mean intensity over the wavelengths) and takes the
    colour of its object's class (the library signature's shape). The library, the
    geometry and the photon budget are Art's: only the class map changes, to one that a
    material library would give. Not the paper's scene and not Art's targets: an extra
    figure of what the classifier does when the classes follow the objects."""
    t, shape = scene.truth, scene.shape
    m = t.layer == 0
    dep = np.zeros(shape)
    dep[t.row[m], t.col[m]] = t.depth_bin[m]
    lab = np.full(shape, -1)
    lab[t.row[m], t.col[m]] = t.label[m]
    seg = _segments(dep, shape, depth_step)
    K = scene.library.n_classes
    cnt = np.zeros((seg.max() + 1, K))
    np.add.at(cnt, (seg.ravel(), lab.ravel()), 1)
    obj = np.argmax(cnt, axis=1)[seg]
    new = obj[t.row, t.col]
    sig = scene.library.signatures
    shp = sig / sig.mean(axis=1, keepdims=True)
    inten = t.intensity.mean(axis=1, keepdims=True) * shp[new]
    truth = replace(t, label=new, intensity=inten)
    return replace(scene, truth=truth, name="art_objects")


def run_cell(
    scene, ppp, bg, seed, *, tau=4.0, tau_m=None, special=None, special2=None, shares=False
):
    sim = scene.simulate(ppp=ppp, sbr=1.0, background=bg, rng=seed)
    truth = sim.truth
    t0 = time.perf_counter()
    rec = splidar.process(sim.cube, library=scene.library, max_surfaces=2, rng=seed)
    t_proc = time.perf_counter() - t0
    m = match_points(rec.points, truth, tau=None if tau_m else tau, tau_m=tau_m)
    e, t = m.est_index, m.true_index
    tl = truth.label[t]
    ok = rec.points.label[e] == tl
    sig = scene.library.signatures
    pp, pmaj = _per_pixel_labels(rec.detection, sig)
    row = {
        "scene": scene.name,
        "bg": bg,
        "ppp": ppp,
        "n_match": int(e.size),
        "acc": float(ok.mean()),
        "per_pixel": float((pp[e] == tl).mean()),
        "per_pixel_majority": float((pmaj[e] == tl).mean()) if pmaj is not None else float("nan"),
        "most_common": float(np.bincount(tl).max() / max(tl.size, 1)),
        "t_process": t_proc,
        "t_classify": float(rec.timings.get("classify", float("nan"))),
        "n_surfaces": len(rec.points),
    }
    for name, mask in (("special", special), ("special2", special2)):
        if mask is not None:
            s = mask[t]
            row[name] = float(ok[s].mean()) if np.any(s) else float("nan")
            row[name + "_pp"] = float((pp[e][s] == tl[s]).mean()) if np.any(s) else float("nan")
    if flag_unknown is not None:  # known materials flagged "unknown" at level 1e-3
        flagged = flag_unknown(rec, level=1e-3).points.label == -1
        row["unknown_rate"] = float(flagged[e].mean())
    if scene.name.startswith("art"):  # both Art variants
        row["oracle_regions"] = oracle_regions(rec.detection, truth, e, t, sig, scene.shape)
    row.update(evidence_budget(rec, truth, e, t, sig))
    if shares:  # session 15: classification from smoothed colour shares (measured only)
        sp_m = special[t] if special is not None else None
        row.update(share_smoothing(rec, truth, e, t, sig, special=sp_m))
    conf = rec.points.label_confidence
    calib = (conf[e], ok) if conf is not None else None
    return row, calib


def _fmt(r):
    extra = ""
    if "boundary" in r:  # Art: surfaces on a colour boundary (own pixel) / inside a region
        return _fmt(
            {k: v for k, v in r.items() if k not in ("special", "special2", "boundary")}
        ) + (
            f" colour boundary ({r['boundary']:.2f} of them) {r['special']:.3f} "
            f"(pp {r['special_pp']:.3f}), inside {r['special2']:.3f} (pp {r['special2_pp']:.3f})"
            + (f", oracle regions {r['oracle_regions']:.3f}" if "oracle_regions" in r else "")
        )
    if "special" in r:
        extra = f" thin/net {r['special']:.3f} (pp {r['special_pp']:.3f})"
    if "special2" in r:
        extra += f" patch {r['special2']:.3f} (pp {r['special2_pp']:.3f})"
    if "unknown_rate" in r:
        extra += f" unknown@1e-3 {r['unknown_rate']:.3f}"
    if "evidence" in r:
        extra += (
            f" | evidence {r['evidence']:.0f} nats ({r['evidence_per_surface']:.3f}/surf)"
            f" vs boundary {r['boundary_cost']:.0f}; errors' llr photons "
            f"{r['wrong_llr_photons']:+.3f} expected {r['wrong_llr_expected']:+.3f}; "
            f"MPL strength truth {r['mpl_truth']:.2f} field {r['mpl_field']:.2f}"
        )
    frac = r["t_classify"] / r["t_process"]
    return (
        f"{r['scene']:<24} {r['bg']:<8} {r['ppp']:>4g} {r['n_match']:>6d} {r['acc']:>6.3f} "
        f"{r['per_pixel']:>6.3f} {r['per_pixel_majority']:>6.3f} {r['most_common']:>6.3f} "
        f"{r['t_process']:>6.2f} {100 * frac:>5.1f}%{extra}"
    )


def _fmt_shares(r) -> str:
    """The :func:`share_smoothing` figures of a cell, one line (empty without them)."""
    if "share_steps" not in r:
        return ""
    per = ", ".join(
        f"{n}: {a:.3f}/{b:.3f}"
        for n, a, b in zip(r["share_steps"], r["share_photons"], r["share_noise_free"], strict=True)
    )
    sp = f", on thin/net/boundary {r['thinned_special']:.3f}" if "thinned_special" in r else ""
    return (
        f"  smoothed shares, steps: photons/noise-free {per}\n"
        f"  thinning picks {r['thinned_steps']} steps: {r['thinned']:.3f} (ECE "
        f"{r['thinned_ece']:.3f}){sp}; more confident of field and smoothed {r['choice']:.3f}"
    )


HEADER = (
    f"{'scene':<24} {'bg':<8} {'PPP':>4} {'n':>6} {'acc':>6} {'pp':>6} {'pp+maj':>6} "
    f"{'common':>6} {'proc_s':>6} {'cls%':>6}"
)


def _art_cells(scene, seed, rows, shares=False, **extra) -> list:
    """The Art cells of ``scene`` at ``PPP_ART`` (uniform background), printed and added
    to ``rows`` with ``extra`` and the colour-boundary share; returns the calibration
    pairs ``(confidence, correct)`` of the cells that have them."""
    edge = colour_boundary(scene.truth, scene.shape)
    cals = []
    for ppp in PPP_ART:
        r, cal = run_cell(
            scene, ppp, "uniform", seed, tau_m=0.004, special=edge, special2=~edge, shares=shares
        )
        r.update(extra, boundary=float(edge.mean()))
        print(_fmt(r), flush=True)
        if shares:
            print(_fmt_shares(r), flush=True)
        rows.append(r)
        if cal is not None:
            cals.append(cal)
            print(f"  ECE {ece(*cal):.4f}, mean confidence {cal[0].mean():.3f}")
    return cals


def _save_reliability(cals, name, figure, suffix) -> None:
    """The reliability figure of the pooled ``cals`` beside ``figure`` (``suffix`` added)."""
    if not cals or figure is None:
        return
    from splidar.plotting import reliability_diagram

    c = np.concatenate([a for a, _ in cals])
    o = np.concatenate([b for _, b in cals])
    path = figure.with_name(figure.stem + suffix + figure.suffix)
    reliability_diagram(c, o, title=f"{name}, PPP 4-64 (ECE {ece(c, o):.3f})").savefig(
        path, dpi=110
    )
    print(f"reliability figure: {path}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=_default_data())
    ap.add_argument("--figure", type=Path, default=None, help="reliability figure (png)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--no-art", action="store_true")
    ap.add_argument(
        "--art-objects",
        action="store_true",
        help="also the Art variant with one class per object (art_object_scene)",
    )
    ap.add_argument(
        "--shares",
        action="store_true",
        help="also classify from spatially smoothed colour shares (share_smoothing; measured, "
        "not in the library)",
    )
    args = ap.parse_args(argv)
    ppps = (1.0, 10.0) if args.quick else PPP
    one = multispectral_scene(SHAPE, n_bins=200)
    two = multispectral_scene(SHAPE, n_bins=200, two_layers=True)
    thin, thin_mask = thin_scene()
    # truth masks: the net (two-layer pixels, front layer) and the scene's patches
    t2 = two.truth
    cnt = np.bincount(t2.row * SHAPE[1] + t2.col, minlength=SHAPE[0] * SHAPE[1])
    net = (cnt[t2.row * SHAPE[1] + t2.col] == 2) & (t2.layer == 0)
    yn = one.truth.row / (SHAPE[0] - 1)
    fx = (one.truth.col / (SHAPE[1] - 1) * 3) % 1.0
    patch = (yn > 0.55) & (yn < 0.85) & (fx > 0.25) & (fx < 0.75)
    rows, confs, oks = [], [], []
    t_all = time.perf_counter()
    print(HEADER)
    for scene, sp, sp2 in ((one, None, patch), (two, net, None), (thin, thin_mask, None)):
        for bg in ("uniform", "decaying"):
            for ppp in ppps:
                r, cal = run_cell(
                    scene, ppp, bg, args.seed, special=sp, special2=sp2, shares=args.shares
                )
                print(_fmt(r), flush=True)
                if args.shares:
                    print(_fmt_shares(r), flush=True)
                rows.append(r)
                if cal is not None:
                    confs.append(cal[0])
                    oks.append(cal[1])
    conf = np.concatenate(confs)
    ok = np.concatenate(oks)
    print(f"\nECE (multispectral cells, {conf.size} matched points): {ece(conf, ok):.4f}")
    worst = [r for r in rows if r["acc"] < r["per_pixel"]]
    print(f"cells where splidar < per-pixel: {len(worst)} of {len(rows)}")
    if args.figure is not None:
        from splidar.plotting import reliability_diagram

        fig = reliability_diagram(conf, ok)
        fig.savefig(args.figure, dpi=110)
        print(f"reliability figure: {args.figure}")
    folder = args.data / "middlebury-art"
    if not args.quick and not args.no_art and folder.is_dir():
        art = art_scene(folder)
        noise_free = nearest_signature(art.truth.intensity, art.library.signatures)
        sep = float(np.mean(noise_free == art.truth.label))
        print(f"\nArt (noise-free separability of the library: {sep:.3f})")
        stats = art_label_map(art)
        print(
            "Art's class map (front layer): " + ", ".join(f"{k} {v:.3g}" for k, v in stats.items())
        )
        print(HEADER)
        art_cal = _art_cells(art, args.seed, rows, shares=args.shares, separability=sep)
        if args.art_objects:
            obj = art_object_scene(art)
            print("\nArt, one class per object (art_object_scene; not the paper's scene)")
            obj_cal = _art_cells(obj, args.seed, rows, shares=args.shares)
            _save_reliability(obj_cal, "art_objects", args.figure, "_art_objects")
        _save_reliability(art_cal, "Art", args.figure, "_art")
    print(f"total {time.perf_counter() - t_all:.0f} s")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
