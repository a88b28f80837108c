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
    _check_options,
    _h_variance_parts,
    _hyperparameters,
    _intensity_and_std,
    _neighbour_shading,
    _one_at_a_time,
    _phase_one,
    _phase_two,
    _prior_arrays,
    _resolve_classes,
    _result,
    _setup,
    _shading_bias2,
    _split_variability,
    _sweep_start,
    _sweeps_end,
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
    """The strip's ``_Setup`` (its surfaces' data on the run's signatures)."""
    return dataclasses.replace(shared["setup"], y=st.y, b=st.b, eta=st.eta, intensity_raw=st.y)


def _strip_graph(st: _Strip, su, shared):
    """The strip's surface graph (red-black colours of the whole image)."""
    e0 = int(st.row.min()) if st.row.size else 0
    n_rows = int(st.row.max()) - e0 + 1 if st.row.size else 1
    graph = build_graph(
        st.row - e0, st.col, st.slot, st.depth, (n_rows, shared["n_cols"]), shared["n_slots"],
        links=su.links, gate=su.gate,
    )  # fmt: skip
    return dataclasses.replace(graph, parity=((st.row + st.col) % 2).astype(np.int64))


def _phase_one_state(su, graph, u, shared):
    """The sweeps' state after the first phase (the in-memory run's, given ``u``)."""
    state = _sweep_start(su, u, shared["prior"], shared["max_iter"])
    _phase_one(
        su, graph, u, state, shared["prior"], shared["rho"], shared["gamma"],
        shared["max_iter"], shared["tol"],
    )  # fmt: skip
    state.pop("z", None), state.pop("q", None)  # recomputed by the next sweep
    return state


@_one_at_a_time
def _labels_tile(st: _Strip, shared):
    """Step 2: ``(small, carry)``. ``small`` goes to the calling process: the core's
    labels and marginals, with ``alpha="auto"`` the first phase's mean shading of each
    core surface's neighbours, and the labels of the whole strip (its own, margins
    included: a restart redoes the first phase with them). ``carry`` stays where the task
    ran, for step 4: the strip, its graph and (``alpha="auto"``) the first phase's state."""
    su = _strip_setup(st, shared)
    graph = _strip_graph(st, su, shared)
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
    h_nb, state = None, None
    if shared["prior"][0] and S:
        state = _phase_one_state(su, graph, u, shared)
        h_nb = _neighbour_shading(graph, state["h"])[core]
    return (u[core], marg[core], h_nb, u), dict(strip=st, graph=graph, state=state)


@_one_at_a_time
def _fit_tile(carry, st, u, own, shared, eb):
    """Step 4: the sweeps from the first phase's state (``carry`` of step 2; when None,
    after a restart, the first phase again on ``st`` with the strip's ``own`` labels:
    the same state). Returns ``(small, carry)``: the core's residuals for the std's
    smoothing-bias term, its surfaces and links, the history; the state for step 5."""
    auto = shared["prior"][0]
    state = None
    if carry is not None:
        st, graph, state = carry["strip"], carry["graph"], carry["state"]
        su = _strip_setup(st, shared)
    else:
        su = _strip_setup(st, shared)
        graph = _strip_graph(st, su, shared)
    S = st.y.shape[0]
    if state is None:  # fixed alpha: the only phase, with these labels
        state = _phase_one_state(su, graph, own if auto else u, shared)
    else:  # a copy: the carry may be used again if this task is recomputed
        state = {k: (v.copy() if hasattr(v, "copy") else v) for k, v in state.items()}
    prior = shared["prior"]
    if auto and S:
        prior = _phase_two(
            su, graph, u, state, prior, shared["rho"], shared["gamma"], shared["max_iter"],
            shared["tol"], eb=eb,
        )  # fmt: skip
    state, hist = _sweeps_end(su, state, shared["tol"])
    core = st.core
    resid = None
    if auto and S:
        _, _, ok, e2, knv = _h_variance_parts(
            su.y, su.b, su.eta, state["r"], state["h"], prior[1][u], graph, shared["rho"]
        )
        keep = core[ok]
        resid = (e2[keep], knv[keep])
    n_links = int(np.diff(graph.indptr)[core].sum())
    small = (resid, int(np.count_nonzero(core)), n_links, hist)
    return small, dict(strip=st, graph=graph, state=state, prior=prior)


@_one_at_a_time
def _std_tile(carry, u, marg, shared, bias2):
    """Step 5: the core's intensities and std, with the run's smoothing-bias term."""
    st, graph, state, prior = carry["strip"], carry["graph"], carry["state"], carry["prior"]
    su = _strip_setup(st, shared)
    rng = np.random.default_rng(_seed(shared["base"], st.r0, 1))
    intensity, std, _ = _intensity_and_std(
        su, graph, u, marg, state, prior, shared["rho"], rng, bias2=bias2
    )
    return intensity[st.core], std[st.core]


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


def _persist(tasks: dict, name: str, take) -> dict:
    """Compute ``{strip: task}`` (each returning ``(small, carry)``) on the active
    scheduler, keeping the results where they are (``dask.persist``: on a cluster, on the
    workers, recomputed from the graph if one is lost); ``take(strip, small)`` as each
    small part arrives. Returns ``{strip: the persisted task}`` for the next step."""
    import dask

    keys = list(tasks)
    t = time.perf_counter()
    kept = dict(zip(keys, dask.persist(*[tasks[n] for n in keys]), strict=True))
    compute_each([kept[n][0] for n in keys], lambda i, small: take(keys[i], small))
    log.info("reconstruct: %d %s task(s), %.3f s", len(keys), name, time.perf_counter() - t)
    return kept


def _labels_pass(detection, strips_, core_idx, sh, token, K, store):
    """Step 2: labels, marginals, neighbours' shading (``alpha="auto"``), each strip's own
    labels; the persisted tasks (their carry) of the strips computed."""
    import dask

    S = len(detection.surfaces)
    u = np.zeros(S, np.int64)
    marg = np.ones((S, 1)) if K == 1 else np.zeros((S, K))
    h_nb = np.zeros(S)
    own = [None] * len(strips_)

    def take(n, result):
        uc, mc, hc, own[n] = result
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
            tasks[n] = dask.delayed(_labels_tile, pure=True, nout=2)(
                st, sh, dask_key_name=(f"splidar-labels-tile-{token}", n)
            )
    kept = _persist(tasks, "labels", take)
    return u, marg, h_nb, own, kept


def _fit_pass(strips_, idx, core_idx, u, own, carries, sh, eb, token, store, skip):
    """Step 4: the sweeps of every strip not in ``skip``; the residuals behind the std's
    smoothing-bias term (per strip, in strip order), the metas, the persisted tasks."""
    import dask

    resid, metas = [None] * len(strips_), [None] * len(strips_)

    def take(n, result):
        res, n_core, n_l, hist = result
        resid[n] = res
        metas[n] = dict(
            n_links=n_l, n_iter=hist.n_iter, converged=hist.converged,
            change=hist.change.tolist(), alpha_updates=list(hist.alpha_updates),
        )  # fmt: skip
        if store is not None and res is not None:
            store.put_residuals(n, res)

    tasks = {}
    for n, (st, i) in enumerate(zip(strips_, idx, strict=True)):
        if n in skip:
            metas[n], resid[n] = skip[n]
            continue
        carry = carries[n][1] if n in carries else None
        tasks[n] = dask.delayed(_fit_tile, pure=True, nout=2)(
            carry, st if carry is None else None, u[i], own[n] if carry is None else None,
            sh, eb, dask_key_name=(f"splidar-fit-tile-{token}", n),
        )  # fmt: skip
    kept = _persist(tasks, "sweeps", take)
    return resid, metas, kept


def _finished(store, n_strips, auto) -> dict:
    """``{strip: (meta, residuals)}`` of the strips an earlier run finished."""
    out = {}
    for n in range(n_strips):
        done = None if store is None else store.fitted(n)
        res = None if (done is None or not auto) else store.residuals(n)
        if done is not None and (res is not None or not auto):
            out[n] = (done[1], res)
    return out


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
            meta = dict(n_links=0, n_iter=rec.history.n_iter, converged=True)
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
    own, carries = [None] * len(cores), {}
    eb = None
    finished = _finished(store, len(cores), prior[0])
    if K > 1 or prior[0]:
        u, marg, h_nb, own, carries = _labels_pass(
            detection, strips_, core_idx, sh, token, K, store
        )
        if prior[0]:
            with _KERNEL_LOCK:
                eb = _split_variability(estimate_alpha(su.y, su.b, su.eta, h_nb, u, su.sig))
    if eb is not None:  # the prior every strip used: (auto, alpha, upsilon, epsilon)
        prior = (True, eb[0], eb[1], su.sig * (eb[1] - 1.0) / eb[0])
    t_cls = time.perf_counter()
    resid, metas, fits = _fit_pass(
        strips_, idx, core_idx, u, own, carries, sh, eb, token, store, finished
    )
    del carries
    bias2 = None
    if prior[0]:  # one smoothing-bias term for the image, as in memory (strip order)
        bias2 = _shading_bias2(
            np.concatenate([r[0] for r in resid]), np.concatenate([r[1] for r in resid])
        )
    t_fit = time.perf_counter()
    conf = marg.max(axis=1)
    intensity, std = (np.zeros((S, L)), np.zeros((S, L))) if assemble else (None, None)

    def take(n, result):
        ic, sc = result
        ci = core_idx[n]
        if store is not None:
            store.put_fit(n, cores[n], _points(detection, ci, ic, sc, u[ci], conf[ci]), metas[n])
        if assemble:
            intensity[ci], std[ci] = ic, sc

    tasks = {}
    for n, i in enumerate(idx):
        if n in finished:
            if assemble:
                pts = store.fitted(n)[0]
                intensity[pts["surface"]] = pts["intensity"]
                std[pts["surface"]] = pts["intensity_std"]
            continue
        tasks[n] = dask.delayed(_std_tile, pure=True)(
            fits[n][1], u[i], marg[i], sh, bias2,
            dask_key_name=(f"splidar-reconstruct-tile-{token}", n),
        )  # fmt: skip
    _run(tasks, "reconstruct", take)
    del fits, tasks
    t_iter = time.perf_counter()
    hyper = _hyperparameters(
        su, opt, prior, marg.mean(axis=0), bias2,
        types.SimpleNamespace(n_edges=sum(m["n_links"] for m in metas) // 2),
    )  # fmt: skip
    hyper["tiles"] = dict(cores=tuple(cores), margin=MARGIN, seeds="rng and first row")
    timings = {
        "setup": t_setup - t0,
        "classify": t_cls - t_setup,
        "iterations": t_fit - t_cls,
        "outputs": t_iter - t_fit,
        "total": t_iter - t0,
    }
    skipped = tuple(sorted(finished))
    log.info(
        "reconstruct: %d surfaces in %d strips of %d rows (+ %d each side; %d done before), "
        "%.3f s", S, len(cores), cores[0][1] - cores[0][0], MARGIN, len(skipped),
        timings["total"],
    )  # fmt: skip
    if not assemble:
        return StreamedRun(S, tuple(cores), skipped, hyper, timings, detection)
    history = _history(metas)
    return _result(detection, su, None, u, conf, intensity, std, history, hyper, timings)


@functools.wraps(_core.reconstruct)
def reconstruct(detection, **options):
    # splidar.reconstruct: the in-memory function, or the strips for a Dask cube's detection
    inspect.signature(_core.reconstruct).bind(detection, **options)  # unknown keywords
    if isinstance(detection, Detection) and detection.options.get("dask", False):
        return reconstruct_tiled(detection, **options)
    return _core.reconstruct(detection, **options)
