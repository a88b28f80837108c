"""Reconstruction of a Dask cube's detection on overlapping strips of rows (issue #16).

:func:`splidar.reconstruct` hands a detection whose cube was a Dask array
(``detection.options["dask"]``) to :func:`reconstruct_tiled` when its surfaces do not
fit one strip's memory budget (:data:`TILE_BYTES`); otherwise it runs in memory, exactly
as for any detection. The method and its error bound are in ``docs/distributed.md``:

1. **Global quantities, in the calling process, on the whole surface table** (the
   table is gathered there by the detection): the class signatures and their scale
   (k-means for ``classes="cluster"``, seeded as in memory), the class likelihood of every
   surface and the EM class proportions from it (the in-memory values, bit for bit).
2. **Labels, one Dask task per strip** (``splidar-labels-tile`` in the dashboard): the
   strip's core rows plus :data:`MARGIN` rows on each side, its surface graph, the
   Swendsen-Wang label sampler of :func:`~splidar.reconstruction.classify_surfaces` with
   the global proportions, seeded from the strip's first row (not from the worker or the
   order of the tasks); with ``alpha="auto"`` also the first phase of the sweeps, whose
   shading of the neighbours feeds the empirical-Bayes estimate. Only the core rows'
   results are kept.
3. **Empirical Bayes, in the calling process**: ``alpha`` and ``upsilon`` per class from
   every surface's counts (:func:`~splidar.reconstruction.estimate_alpha`), as in memory.
4. **Intensities, one Dask task per strip** (``splidar-reconstruct-tile``): the same
   strips, the labels of step 2 (a margin's labels are those of the strip that owns the
   rows), the sweeps with the global ``alpha`` and ``upsilon``, the posterior intensity and
   its std; the core rows' results are kept and assembled into one Reconstruction.

The tasks run on whatever Dask scheduler is active (threads by default: one strip at a
time, each using the numba threads; a ``dask.distributed.Client`` when one is open: one
strip per worker thread). Every random number a strip draws is seeded from ``rng`` and
the strip's first row, so the result does not depend on the workers.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import logging
import time
import types

import numpy as np

from .._memory import reconstruct_peak_bytes
from ..detection._result import Detection
from ..detection._tiled import compute_each, tile_bounds
from . import _core
from ._classify import class_loglik, classify_surfaces, em_proportions
from ._core import (
    _KERNEL_LOCK,
    _PHASE1_TOL,
    _check_options,
    _hyperparameters,
    _intensity_and_std,
    _one_at_a_time,
    _prior_arrays,
    _resolve_classes,
    _result,
    _setup,
    _split_variability,
    _sweeps,
    estimate_alpha,
)
from ._graph import build_graph
from ._result import ConvergenceHistory, Reconstruction

__all__ = ["MARGIN", "TILE_BYTES", "StreamedRun", "reconstruct", "reconstruct_tiled", "strips"]

log = logging.getLogger(__name__)

#: Rows of margin on each side of a strip. The effect of the cut decays by ``kappa``
#: (0.5-0.8) per pixel of links (``docs/distributed.md``); measured by
#: ``benchmarks/bench_tile_margin.py``: at 16 rows the largest relative intensity error
#: of a core row is 1e-6 at PPP 10 and 1e-3 at PPP 2 (the stopping rule's floor), under
#: the 1e-2 the tests hold the tiled run to, and no label of 1024 core surfaces changed.
MARGIN = 16

#: Memory budget of one strip (core + margins) in bytes, by ``reconstruct_peak_bytes``
#: (about 2.3 KB per surface at L = 4, K = 4: some 110,000 surfaces a strip). The core is
#: at least ``MARGIN`` rows, so the margins at most triple a strip's work.
TILE_BYTES = 256 * 2**20


def strips(n_rows: int, n_surfaces: int, n_wavelengths: int, n_classes: int, *, core=None) -> list:
    """Core row ranges ``[r0, r1)`` of the strips: ``core`` rows, default as many as fit
    :data:`TILE_BYTES` with the margins, at least :data:`MARGIN`; one strip when the whole
    image fits."""
    if core is None:
        per_surface = reconstruct_peak_bytes(1, n_wavelengths, n_classes)
        per_row = max(n_surfaces / max(n_rows, 1), 1e-9)
        core = max(int(TILE_BYTES / per_surface / per_row) - 2 * MARGIN, MARGIN)
    core = max(int(core), 1)
    if core >= n_rows:
        return [(0, n_rows)]
    # a last strip shorter than MARGIN (or core) rows joins the one before
    return tile_bounds(n_rows, core, min(MARGIN, core))


def _seed(base: int, r0: int, salt: int) -> int:
    """A seed from the run's ``rng`` and the strip's first row (not the worker or order)."""
    return int(np.random.SeedSequence([base, r0, salt]).generate_state(1)[0] % 2**31)


@dataclasses.dataclass(frozen=True)
class _Strip:
    """One strip's surfaces: rows ``[e0, e1)`` (core and margins), core ``[r0, r1)``."""

    r0: int
    r1: int
    row: np.ndarray
    col: np.ndarray
    slot: np.ndarray
    depth: np.ndarray
    y: np.ndarray
    b: np.ndarray
    eta: np.ndarray

    @property
    def core(self) -> np.ndarray:
        return (self.row >= self.r0) & (self.row < self.r1)


def _strip_setup(st: _Strip, shared):
    """The strip's ``_Setup`` and surface graph (red-black colours of the whole image)."""
    su = dataclasses.replace(shared["setup"], y=st.y, b=st.b, eta=st.eta, intensity_raw=st.y)
    e0 = int(st.row.min()) if st.row.size else 0
    n_rows = int(st.row.max()) - e0 + 1 if st.row.size else 1
    graph = build_graph(
        st.row - e0, st.col, st.slot, st.depth, (n_rows, shared["n_cols"]), shared["n_slots"],
        links=su.links, gate=su.gate,
    )  # fmt: skip
    graph = dataclasses.replace(graph, parity=((st.row + st.col) % 2).astype(np.int64))
    return su, graph


@_one_at_a_time
def _labels_tile(st: _Strip, shared):
    """Step 2: the core's labels and marginals, and with ``alpha="auto"`` the first
    phase's mean shading of each core surface's neighbours."""
    su, graph = _strip_setup(st, shared)
    S, K = st.y.shape[0], su.sig.shape[0]
    if K > 1:
        cls = classify_surfaces(
            su.y, su.b, su.eta, su.sig, graph, gamma=shared["gamma"],
            seed=_seed(shared["base"], st.r0, 0), proportions=shared["pi"],
        )  # fmt: skip
        u, marg = cls.label, cls.marginals
    else:
        u, marg = np.zeros(S, np.int64), np.ones((S, 1))
    core = st.core
    h_nb = None
    auto, alpha_a, ups_a, eps_a = shared["prior"]
    if auto and S:
        # the in-memory first phase: alpha = 6, stopped at 10 tol, max_iter // 2 sweeps
        state, _, _ = _sweeps(
            su, graph, u, (False, alpha_a, ups_a, eps_a), shared["rho"], shared["gamma"],
            max(shared["max_iter"] // 2, 1), shared["tol"] * _PHASE1_TOL,
        )  # fmt: skip
        deg = np.diff(graph.indptr)
        src = np.repeat(np.arange(S), deg)
        h = state["h"]
        h_nb = (np.bincount(src, h[graph.indices], minlength=S) / np.maximum(deg, 1))[core]
    return u[core], marg[core], h_nb


@_one_at_a_time
def _fit_tile(st: _Strip, u, marg, shared, eb):
    """Step 4: the core's intensities and std, the sweeps' history and the core's links."""
    su, graph = _strip_setup(st, shared)
    state, prior, hist = _sweeps(
        su, graph, u, shared["prior"], shared["rho"], shared["gamma"], shared["max_iter"],
        shared["tol"], eb=eb,
    )  # fmt: skip
    rng = np.random.default_rng(_seed(shared["base"], st.r0, 1))
    intensity, std, bias2 = _intensity_and_std(su, graph, u, marg, state, prior, shared["rho"], rng)
    core = st.core
    n_links = int(np.diff(graph.indptr)[core].sum())
    n_core = int(np.count_nonzero(core))
    return intensity[core], std[core], bias2, n_core, n_links, hist, prior


def _history(metas: list) -> ConvergenceHistory:
    """One history for the strips: the most sweeps, the largest change at each sweep."""
    n = max(m["n_iter"] for m in metas)
    change = np.zeros(n)
    for m in metas:
        k = len(m.get("change", ()))
        change[:k] = np.maximum(change[:k], m.get("change", ()))
    longest = max(metas, key=lambda m: m["n_iter"])
    converged = all(m["converged"] for m in metas)
    return ConvergenceHistory(
        # the strips' objectives overlap in their margins: no sum is the image's
        objective=np.full(n + 1, np.nan),
        change=change,
        n_iter=int(n),
        converged=converged,
        reason="tol" if converged else "max_iter",
        alpha_updates=tuple(longest.get("alpha_updates", ())),
        label_changes=np.zeros(n, np.int64),
    )


def _run(tasks: dict, name: str, take) -> None:
    """Compute ``{strip: task}`` on the active scheduler; ``take(strip, result)`` as each
    finishes (on a cluster in the order they finish)."""
    keys = list(tasks)
    t = time.perf_counter()
    compute_each([tasks[n] for n in keys], lambda i, result: take(keys[i], result))
    log.info("reconstruct: %d %s task(s), %.3f s", len(keys), name, time.perf_counter() - t)


@dataclasses.dataclass(frozen=True)
class StreamedRun:
    """What :func:`reconstruct_tiled` returns with ``assemble=False``: the points are in
    the store, not in memory."""

    n_points: int
    cores: tuple
    skipped: tuple  #: strips whose results the store already held (not recomputed)
    hyperparameters: dict
    timings: dict
    detection: object  #: the Detection the strips came from


def _plan(detection, options, strip_rows):
    """Checked options, the strips' cores and the number of classes."""
    opt = _check_options(
        detection, options["gamma"], options["rho"], options["max_iter"], options["tol"],
        options["links"], options["signature_scale"], options["classes"], options["n_classes"],
    )  # fmt: skip
    R = detection.image_shape[0]
    _, lib = _resolve_classes(detection, options["library"], opt["classes"], opt["n_classes"])
    K = lib.n_classes if lib is not None else (opt["n_classes"] or 1)
    n = len(detection.surfaces)
    cores = strips(R, n, detection.n_wavelengths, K, core=strip_rows)
    return opt, cores


def _cut(detection, su, cores):
    """Per strip: the surfaces' indices (core and margins), the ``_Strip``, the core's."""
    surf = detection.surfaces
    order = np.argsort(surf.row, kind="stable")
    srow = surf.row[order]
    idx, strips_ = [], []
    for r0, r1 in cores:
        lo, hi = np.searchsorted(srow, [r0 - MARGIN, r1 + MARGIN])
        i = order[lo:hi]
        idx.append(i)
        strips_.append(
            _Strip(
                r0,
                r1,
                surf.row[i],
                surf.col[i],
                surf.slot[i],
                surf.depth_bin[i],
                su.y[i],
                su.b[i],
                su.eta[i],
            )  # fmt: skip
        )
    return idx, strips_, [i[st.core] for i, st in zip(idx, strips_, strict=True)]


def _points(detection, ci, intensity, std, u, conf) -> dict:
    """One strip's core points as columns (``surface``: index in the detection's table)."""
    s = detection.surfaces
    return dict(
        surface=ci, row=s.row[ci], col=s.col[ci], depth_bin=s.depth_bin[ci], layer=s.slot[ci],
        intensity=intensity, intensity_std=std, label=u, label_confidence=conf,
    )  # fmt: skip


def _labels_pass(detection, su, strips_, core_idx, sh, token, K, store):
    """Steps 2-3: labels, marginals and (``alpha="auto"``) the global (alpha, upsilon)."""
    import dask

    S = len(detection.surfaces)
    u = np.zeros(S, np.int64)
    marg = np.ones((S, 1)) if K == 1 else np.zeros((S, K))
    h_nb = np.zeros(S)

    def take(n, result):
        uc, mc, hc = result
        ci = core_idx[n]
        u[ci], marg[ci] = uc, mc
        if hc is not None:
            h_nb[ci] = hc
        if store is not None:
            store.put_labels(n, result)

    tasks = {}
    for n, st in enumerate(strips_):
        done = None if store is None else store.labels(n)
        if done is not None:
            take(n, done)
        else:
            tasks[n] = dask.delayed(_labels_tile, pure=True)(
                st, sh, dask_key_name=(f"splidar-labels-tile-{token}", n)
            )
    _run(tasks, "labels", take)
    return u, marg, h_nb


def reconstruct_tiled(
    detection, *, strip_rows=None, store=None, assemble=True, **options
) -> Reconstruction | StreamedRun:
    """:func:`splidar.reconstruct` (same keywords) on overlapping strips of rows, as Dask
    tasks on the active scheduler (steps in the module docstring); in memory when the
    whole image fits one strip.

    ``strip_rows``: core rows per strip (default: from :data:`TILE_BYTES`). ``store``: an
    object that keeps each strip's results as it finishes and gives back those of an
    earlier, interrupted run (``splidar._stream.StripStore``, used by ``splidar run``);
    ``assemble=False`` (with a store) returns a :class:`StreamedRun` instead of holding
    every point in memory.
    """
    import dask

    options = inspect.signature(_core.reconstruct).bind(detection, **options)
    options.apply_defaults()
    options = {k: v for k, v in options.arguments.items() if k != "detection"}
    opt, cores = _plan(detection, options, strip_rows)
    surf = detection.surfaces
    S, L = len(surf), detection.n_wavelengths
    if store is not None:
        store.begin(cores)
    if len(cores) == 1 or S == 0:
        rec = _core.reconstruct(detection, **options)
        if store is not None and store.fitted(0) is None:
            p = rec.points
            ci = np.arange(S)
            meta = dict(bias2=0.0, n_links=0, n_iter=rec.history.n_iter, converged=True)
            pts = _points(detection, ci, p.intensity, p.intensity_std, p.label, p.label_confidence)
            store.put_fit(0, (0, detection.image_shape[0]), pts, meta)
        return rec
    t0 = time.perf_counter()
    rng = np.random.default_rng(options["rng"])
    with _KERNEL_LOCK:  # numba kernels: the IRF fractions and the class likelihoods
        su = _setup(detection, options["library"], opt, rng)
        K = su.sig.shape[0]
        base = int(rng.integers(2**31))  # where the in-memory run seeds its label sampler
        pi = em_proportions(class_loglik(su.y, su.b, su.eta, su.sig)) if K > 1 else np.ones(1)
    prior = _prior_arrays(options["alpha"], options["upsilon"], su.sig)
    empty = np.zeros((0, L))
    shared = dict(
        setup=dataclasses.replace(su, y=empty, b=empty, eta=empty, intensity_raw=empty),
        n_cols=int(detection.image_shape[1]), n_slots=int(surf.n_slots), gamma=opt["gamma"],
        rho=opt["rho"], max_iter=opt["max_iter"], tol=opt["tol"], prior=prior, pi=pi, base=base,
    )  # fmt: skip
    idx, strips_, core_idx = _cut(detection, su, cores)
    t_setup = time.perf_counter()
    token = dask.base.tokenize(strips_, shared)
    sh = dask.delayed(shared, pure=True)
    u, marg = np.zeros(S, np.int64), np.ones((S, 1))
    eb = None
    if K > 1 or prior[0]:
        u, marg, h_nb = _labels_pass(detection, su, strips_, core_idx, sh, token, K, store)
        if prior[0]:
            with _KERNEL_LOCK:
                eb = _split_variability(estimate_alpha(su.y, su.b, su.eta, h_nb, u, su.sig))
    if eb is not None:  # the prior every strip used: (auto, alpha, upsilon, epsilon)
        prior = (True, eb[0], eb[1], su.sig * (eb[1] - 1.0) / eb[0])
    t_cls = time.perf_counter()
    conf = marg.max(axis=1)
    intensity, std = (np.zeros((S, L)), np.zeros((S, L))) if assemble else (None, None)
    metas = [None] * len(cores)

    def take(n, result):
        ic, sc, b2, n_core, n_l, hist, _ = result
        ci = core_idx[n]
        metas[n] = dict(
            bias2=float(b2 or 0.0) * n_core, n_links=n_l, n_iter=hist.n_iter,
            converged=hist.converged, change=hist.change.tolist(),
            alpha_updates=list(hist.alpha_updates),
        )  # fmt: skip
        if store is not None:
            store.put_fit(n, cores[n], _points(detection, ci, ic, sc, u[ci], conf[ci]), metas[n])
        if assemble:
            intensity[ci], std[ci] = ic, sc

    tasks, skipped = {}, []
    for n, (st, i) in enumerate(zip(strips_, idx, strict=True)):
        done = None if store is None else store.fitted(n)
        if done is not None:
            skipped.append(n)
            metas[n] = done[1]
            if assemble:
                intensity[done[0]["surface"]] = done[0]["intensity"]
                std[done[0]["surface"]] = done[0]["intensity_std"]
            continue
        tasks[n] = dask.delayed(_fit_tile, pure=True)(
            st, u[i], marg[i], sh, eb, dask_key_name=(f"splidar-reconstruct-tile-{token}", n)
        )
    _run(tasks, "reconstruct", take)
    t_iter = time.perf_counter()
    bias2 = sum(m["bias2"] for m in metas) / S
    hyper = _hyperparameters(
        su, opt, prior, marg.mean(axis=0), bias2 if prior[0] else None,
        types.SimpleNamespace(n_edges=sum(m["n_links"] for m in metas) // 2),
    )  # fmt: skip
    hyper["tiles"] = dict(cores=tuple(cores), margin=MARGIN, seeds="rng and first row")
    timings = {
        "setup": t_setup - t0,
        "classify": t_cls - t_setup,
        "iterations": t_iter - t_cls,
        "outputs": 0.0,
        "total": t_iter - t0,
    }
    log.info(
        "reconstruct: %d surfaces in %d strips of %d rows (+ %d each side; %d done before), "
        "%.3f s", S, len(cores), cores[0][1] - cores[0][0], MARGIN, len(skipped),
        timings["total"],
    )  # fmt: skip
    if not assemble:
        return StreamedRun(S, tuple(cores), tuple(skipped), hyper, timings, detection)
    history = _history(metas)
    return _result(detection, su, None, u, conf, intensity, std, history, hyper, timings)


@functools.wraps(_core.reconstruct)
def reconstruct(detection, **options):
    # splidar.reconstruct: the in-memory function, or the strips for a Dask cube's detection
    inspect.signature(_core.reconstruct).bind(detection, **options)  # unknown keywords
    if isinstance(detection, Detection) and detection.options.get("dask", False):
        return reconstruct_tiled(detection, **options)
    return _core.reconstruct(detection, **options)
