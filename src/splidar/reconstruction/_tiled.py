"""Reconstruction of a Dask cube's detection on overlapping strips of rows (issue #16).

:func:`splidar.reconstruct` hands a detection whose cube was a Dask array
(``detection.options["dask"]``) to :func:`reconstruct_tiled` when its surfaces do not
fit one strip's memory budget (:data:`TILE_BYTES`); otherwise it runs in memory, exactly
as for any detection. The method and its error bound are in ``docs/distributed.md``:

1. **Global quantities, in the calling process, on the whole surface table** (the
   table is gathered there by the detection): the class signatures and their scale
   (k-means for ``classes="cluster"``, seeded as in memory), the class likelihood of every
   surface (computed once: the strips take their rows of it) and the EM class
   proportions from it (the in-memory values, bit for bit).
2. **Labels, one Dask task per strip** (``splidar-labels-tile`` in the dashboard): the
   Swendsen-Wang label sampler of :func:`~splidar.reconstruction.classify_surfaces` with
   the global proportions on the strip's core rows plus :data:`LABEL_MARGIN` rows on each
   side, with the in-memory run's seed and the surfaces' keys of the whole image (pixel
   and rank by depth: :func:`~splidar.reconstruction._graph.surface_keys`), so that a
   surface draws the random numbers it draws in memory and the strips' labels differ
   from memory only where the cut reaches (session 21: identical on the tests' scenes,
   0.985-0.9995 with a seed per strip before); with ``alpha="auto"`` also the first
   phase of the sweeps on the core plus
   :data:`MARGIN` rows each side, whose shading of the neighbours feeds the
   empirical-Bayes estimate. The core's labels and that shading go to the calling
   process; the strip, its graph and the first phase's state stay where the task ran
   (``dask.persist``: on a cluster, on the worker, recomputed from the graph if it is lost).
3. **Empirical Bayes, in the calling process**: ``alpha`` and ``upsilon`` per class from
   every surface's counts (:func:`~splidar.reconstruction.estimate_alpha`), as in memory.
4. **Sweeps, one Dask task per strip** (``splidar-fit-tile``): from step 2's state, the
   labels of the strip's owners (a margin's labels are those of the strip that owns the
   rows), the second phase with the global ``alpha`` and ``upsilon``; the core's residuals
   behind the std's smoothing-bias term go to the calling process, which estimates one
   term for the image from them (as in memory); the state stays.
5. **Intensities, one Dask task per strip** (``splidar-reconstruct-tile``): the posterior
   intensity and its std from step 4's state with the image's smoothing-bias term; the
   core rows' results are assembled into one Reconstruction (or streamed to a store).

A strip's surfaces travel in the task graph once (step 2); with a store whose folder the
workers see (``splidar run``), they are written there once (``surfaces.zarr``, sorted by
row) and each task reads its rows itself. After a restart, a strip whose step-2 state is
gone redoes its first phase from the labels step 2 kept (the same state, bit for bit).

The tasks run on whatever Dask scheduler is active (threads by default: one strip at a
time, each using the numba threads; a ``dask.distributed.Client`` when one is open: one
strip per worker thread). Every random number a strip draws is seeded from ``rng`` (the
label sampler's keyed by the surfaces, the std's label draws by the strip's first row),
so the result does not depend on the workers.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import logging
import os
import shutil
import time
import types
from pathlib import Path

import numpy as np

from .._memory import keep_freed_memory, reconstruct_peak_bytes
from ..detection._result import Detection
from ..detection._table import remove_tree
from ..detection._tiled import compute_each, tile_bounds
from . import _core
from . import _kernels as kern
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
from ._graph import build_graph, surface_keys
from ._result import ConvergenceHistory, Reconstruction

__all__ = [
    "LABEL_MARGIN",
    "MARGIN",
    "TILE_BYTES",
    "StreamedRun",
    "reconstruct",
    "reconstruct_tiled",
    "strips",
]

log = logging.getLogger(__name__)

#: Rows of margin on each side of a strip. The effect of the cut decays by ``kappa``
#: (0.5-0.8) per pixel of links (``docs/distributed.md``); measured by
#: ``benchmarks/bench_tile_margin.py``: at 16 rows the largest relative intensity error
#: of a core row is 1e-6 at PPP 10 and 1e-3 at PPP 2 (the stopping rule's floor), under
#: the 1e-2 the tests hold the tiled run to, and no label of 1024 core surfaces changed.
MARGIN = 16

#: Rows of margin on each side of a strip's core for the label sampler (step 2): the
#: labels of a margin row are those of the strip that owns it, so the margin only
#: steadies the core's border rows. Measured on the tests' 96 x 40 scene (3 seeds): with
#: 8, 12, 16 rows the labels agree with memory alike (0.994-0.997); the median relative
#: intensity error of the same-label surfaces (it follows the empirical-Bayes alpha,
#: which moves with the sampled labels) was 1.1-1.4e-3 at 8 rows, 0.6-1.1e-3 at 12 and
#: 0.8-1.4e-3 at 16.
LABEL_MARGIN = 12

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
    ll: np.ndarray  #: class log-likelihoods (S, K) (computed once for the image; K > 1)

    FIELDS = ("row", "col", "slot", "depth", "y", "b", "eta", "ll")

    @property
    def core(self) -> np.ndarray:
        return (self.row >= self.r0) & (self.row < self.r1)


def _strip_setup(st: _Strip, shared):
    """The strip's ``_Setup`` (its surfaces' data on the run's signatures)."""
    return dataclasses.replace(shared["setup"], y=st.y, b=st.b, eta=st.eta, intensity_raw=st.y)


def _strip_graph(st: _Strip, su, shared, bridge: bool = False, key=None):
    """The strip's surface graph (colours and surface keys of the whole image;
    ``bridge``: the label field's graph, see :func:`~splidar.reconstruction.build_graph`;
    ``key``: the strip's surface keys when already computed)."""
    e0 = int(st.row.min()) if st.row.size else 0
    n_rows = int(st.row.max()) - e0 + 1 if st.row.size else 1
    # the keys of the image's rows: a surface draws the random numbers it draws in memory
    key = surface_keys(st.row, st.col, st.depth, st.slot) if key is None else key
    graph = build_graph(
        st.row - e0, st.col, st.slot, st.depth, (n_rows, shared["n_cols"]), shared["n_slots"],
        links=su.links, gate=su.gate, bridge=bridge, key=key,
    )  # fmt: skip
    n_colours = 4 if bridge else 2
    parity = ((st.row + st.col) % n_colours).astype(np.int64)
    return dataclasses.replace(graph, parity=parity)


def _phase_one_state(su, graph, u, shared):
    """The sweeps' state after the first phase (the in-memory run's, given ``u``)."""
    state = _sweep_start(su, u, shared["prior"], shared["max_iter"])
    _phase_one(
        su, graph, u, state, shared["prior"], shared["rho"], shared["gamma"],
        shared["max_iter"], shared["tol"],
    )  # fmt: skip
    state.pop("z", None), state.pop("q", None)  # recomputed by the next sweep
    return state


def _strip_task(func):
    """A strip's task (steps 2, 4, 5): ``func`` under ``_core._one_at_a_time`` (one strip
    at a time per process, the kernels' threads from the free cores) and
    :func:`~splidar._memory.keep_freed_memory`: on a Dask worker, whose nanny fixes
    glibc's trim threshold (so every array of 128 KiB or more is mapped afresh and
    unmapped when freed), the strip's temporaries reuse freed pages instead of faulting
    in new ones, and the freed pages go back to the system when the task ends
    (``benchmarks/README.md``, rec41)."""
    inner = _one_at_a_time(func)

    @functools.wraps(func)
    def task(*args, **kwargs):
        with keep_freed_memory():
            return inner(*args, **kwargs)

    return task


@_strip_task
def _labels_tile(st: _Strip, shared):
    """Step 2: ``(small, carry)``. ``small`` goes to the calling process: the core's
    labels and marginals, with ``alpha="auto"`` the first phase's mean shading of each
    core surface's neighbours, and the labels of the whole strip (its own, margins
    included: a restart redoes the first phase with them). ``carry`` stays where the task
    ran, for step 4 (:func:`_carry`): the strip as given and (``alpha="auto"``) the first
    phase's state."""
    _register_sizes()  # where the carry is kept (a worker)
    given, st = st, _as_strip(st)
    su = _strip_setup(st, shared)
    graph = _strip_graph(st, su, shared)
    S, K = st.y.shape[0], su.sig.shape[0]
    core = st.core
    if K > 1:
        # the label sampler on the core and LABEL_MARGIN rows each side; the rows beyond
        # (the first phase's only) take their most likely class, the owner strip's label
        # replacing it in step 4
        near = (st.row >= st.r0 - LABEL_MARGIN) & (st.row < st.r1 + LABEL_MARGIN)
        sub = _Strip(st.r0, st.r1, *(getattr(st, f)[near] for f in _Strip.FIELDS))
        sub_su = _strip_setup(sub, shared)
        cls = classify_surfaces(
            sub.y, sub.b, sub.eta, su.sig,
            _strip_graph(sub, sub_su, shared, bridge=True, key=graph.key[near]),
            gamma=shared["gamma"], seed=shared["base"],
            proportions=shared["pi"], loglik=sub.ll,
        )  # fmt: skip
        u = np.empty(S, np.int64)
        u[near] = cls.label
        far = ~near
        logpi = np.log(np.maximum(shared["pi"], 1e-6))
        u[far] = np.argmax(st.ll[far] + logpi, axis=1)
        marg = np.zeros((S, K))
        marg[near] = cls.marginals
    else:
        u, marg = np.zeros(S, np.int64), np.ones((S, 1))
    h_nb, state = None, None
    if shared["prior"][0] and S:
        state = _phase_one_state(su, graph, u, shared)
        h_nb = _neighbour_shading(graph, state["h"])[core]
    return (u[core], marg[core], h_nb, u), _carry(given, state)


def _carry(strip, state, **more) -> dict:
    """What a strip's task keeps on its worker for the next step: the strip as the task
    was given it (a :class:`_StripRef` when the strips are in a scratch folder, read
    again by the next step; otherwise the strip itself) and the sweeps' state; not the
    graph, which the next step rebuilds (:func:`_strip_graph`: deterministic, a few % of
    a step's time). Kept whole, a strip of 234,000 surfaces (one wavelength) held 35 MB
    (strip 15, graph 12.7, state 7.5): nine a worker beside a running strip were over a
    1 GB worker's spill mark, and Dask wrote 260-340 MB a worker to disk and read it
    back ("Lead, session 31" in ``benchmarks/README.md``)."""
    return dict(strip=strip, state=state, **more)


@_strip_task
def _fit_tile(carry, st, u, own, shared, eb):
    """Step 4: the sweeps from the first phase's state (``carry`` of step 2; when None,
    after a restart, the first phase again on ``st`` with the strip's ``own`` labels:
    the same state). ``u``: the strip's labels (None: one class). Returns ``(small,
    carry)``: the core's residuals for the std's smoothing-bias term, its surfaces and
    links, the history; the strip, state and prior for step 5 (:func:`_carry`)."""
    _register_sizes()
    auto = shared["prior"][0]
    state = None
    if carry is not None:
        st, state = carry["strip"], carry["state"]
    given, st = st, _as_strip(st)
    su = _strip_setup(st, shared)
    graph = _strip_graph(st, su, shared)
    S = st.y.shape[0]
    u = _labels_of(u, S)
    if state is None:  # fixed alpha: the only phase, with these labels (or no surfaces)
        state = _phase_one_state(su, graph, own if auto and own is not None else u, shared)
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
    elif auto:  # a strip without surfaces
        resid = (np.zeros(0), np.zeros(0))
    n_links = int(np.diff(graph.indptr)[core].sum())
    small = (resid, int(np.count_nonzero(core)), n_links, hist)
    state.pop("z"), state.pop("q")  # the last E-step's: step 5 redoes it (less to keep)
    return small, _carry(given, state, prior=prior)


@_strip_task
def _std_tile(carry, u, marg, shared, bias2):
    """Step 5: the core's intensities and std, with the run's smoothing-bias term
    (``u``, ``marg`` None: one class)."""
    st, state, prior = _as_strip(carry["strip"]), carry["state"], carry["prior"]
    su = _strip_setup(st, shared)
    graph = _strip_graph(st, su, shared)
    S = st.y.shape[0]
    u = _labels_of(u, S)
    marg = np.ones((S, 1)) if marg is None else _loaded(marg)
    z, q = np.empty(st.y.shape), np.empty(st.y.shape)
    kern.estep(st.y, st.b, st.eta, state["r"], state["h"], z, q)  # as _sweeps_end did
    state = {**state, "z": z, "q": q}
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


@dataclasses.dataclass(frozen=True)
class _StripRef:
    """A strip that its task reads itself: rows ``[lo, hi)`` of the surface table sorted
    by image row, kept in the Zarr group ``path`` (:func:`_write_table`), so its surfaces
    do not travel in the task graph; a task recomputed on another worker reads it again.
    ``run`` tells tables written by different runs apart (in the tasks' keys)."""

    path: str
    lo: int
    hi: int
    r0: int
    r1: int
    run: str

    def load(self) -> _Strip:
        import zarr

        g = zarr.open_group(self.path, mode="r")
        n = self.hi - self.lo
        # one class: no class likelihoods written (all 0)
        cols = [g[f][self.lo : self.hi] if f in g else np.zeros((n, 1)) for f in _Strip.FIELDS]
        return _Strip(self.r0, self.r1, *cols)


def _as_strip(st):
    return st.load() if isinstance(st, _StripRef) else st


@dataclasses.dataclass(frozen=True)
class _RowsRef:
    """Rows ``[lo, hi)`` of the per-surface array ``name`` in the Zarr group ``path``
    (sorted as the strips' table, :func:`_write_table`): what a task reads instead of
    receiving the array in the task graph."""

    path: str
    name: str
    lo: int
    hi: int

    def load(self) -> np.ndarray:
        import zarr

        return zarr.open_group(self.path, mode="r")[self.name][self.lo : self.hi]


def _loaded(x):
    return x.load() if isinstance(x, _RowsRef) else x


def _labels_of(u, n: int) -> np.ndarray:
    """A strip's labels: ``u`` (or its :class:`_RowsRef`), or all 0 (one class: None)."""
    return np.zeros(n, np.int64) if u is None else _loaded(u)


@dataclasses.dataclass(frozen=True)
class _Pieces:
    """The strips' surfaces: per strip, their indices in the detection's table (core and
    margins, ``idx``); with ``path`` (the strips' Zarr group, whose rows are the table's
    sorted by ``order``; strip ``n`` holds rows ``bounds[n]``) per-surface arrays reach
    the tasks as :class:`_RowsRef`, else sliced into the task graph."""

    idx: list
    path: str | None = None
    order: np.ndarray | None = None
    bounds: tuple = ()

    def put(self, name: str, a: np.ndarray) -> list:
        """Per strip, its rows of ``a`` (one row per surface of the detection)."""
        if self.path is None:
            return [a[i] for i in self.idx]
        _write_table(self.path, self.order, {name: a}, mode="a")
        return [_RowsRef(self.path, name, lo, hi) for lo, hi in self.bounds]


def _write_table(path: str, order, columns: dict, chunk: int = 2**18, mode: str = "w") -> None:
    """The columns, rows sorted by ``order``, to the Zarr group ``path`` (by chunks; a new
    group with ``mode="w"``, added to it with ``"a"``)."""
    import zarr
    from zarr.codecs import BloscCodec

    # lz4 at about the disk's speed (zstd, Zarr's default, took 3 s of the calling
    # process for the 3.4 M surfaces of bench_distributed.py --large); each array in one
    # write, which Zarr spreads over its threads; chunks of 2**18 rows (2 MB of int64):
    # fewer files to write and remove (each removal waits on the disk's trim here)
    fast = [BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")]
    g = zarr.open_group(path, mode=mode)
    ordered = not np.any(np.diff(order) != 1)
    for name, a in columns.items():
        z = g.create_array(
            name, shape=a.shape, dtype=a.dtype, chunks=(min(chunk, max(len(a), 1)),) + a.shape[1:],
            compressors=fast, overwrite=True,
        )  # fmt: skip
        z[...] = a if ordered else a[order]


def _cut(detection, su, cores, ll, folder=None):
    """Per strip: the surfaces' indices (core and margins), the ``_Strip`` (or, with a
    ``folder`` the workers see, a ``_StripRef`` to the table written there), the core's."""
    surf = detection.surfaces
    order = np.argsort(surf.row, kind="stable")
    srow = surf.row[order]
    columns = dict(
        row=surf.row, col=surf.col, slot=surf.slot, depth=surf.depth_bin, y=su.y, b=su.b,
        eta=su.eta, ll=ll,
    )  # fmt: skip
    path = run = None
    if folder is not None:
        import uuid

        path, run = str(Path(folder) / "surfaces.zarr"), uuid.uuid4().hex
        # one class (``ll`` of one column): its likelihoods are not needed, nor written
        _write_table(
            path, order, {k: v for k, v in columns.items() if k != "ll" or ll.shape[1] > 1}
        )
    idx, strips_, core_idx, bounds = [], [], [], []
    for r0, r1 in cores:
        lo, hi = (int(k) for k in np.searchsorted(srow, [r0 - MARGIN, r1 + MARGIN]))
        i = order[lo:hi]
        idx.append(i)
        bounds.append((lo, hi))
        core_idx.append(i[(srow[lo:hi] >= r0) & (srow[lo:hi] < r1)])
        if path is not None:
            strips_.append(_StripRef(path, lo, hi, r0, r1, run))
        else:
            strips_.append(_Strip(r0, r1, *(columns[f][i] for f in _Strip.FIELDS)))
    pieces = _Pieces(idx) if path is None else _Pieces(idx, path, order, tuple(bounds))
    return pieces, strips_, core_idx


def _points(detection, ci, intensity, std, u, conf) -> dict:
    """One strip's core points as columns (``surface``: index in the detection's table)."""
    s = detection.surfaces
    return dict(
        surface=ci, row=s.row[ci], col=s.col[ci], depth_bin=s.depth_bin[ci], layer=s.slot[ci],
        intensity=intensity, intensity_std=std, label=u, label_confidence=conf,
    )  # fmt: skip


@functools.cache
def _register_sizes() -> None:
    """Dask's ``sizeof`` of a strip (kept in a carry when the strips are not in a
    folder, :func:`_carry`): its arrays' bytes, not the few hundred bytes of the object
    it counts by default. Told 0.3 kB, the scheduler moved carries of tens of MB to idle
    workers (work stealing: up to 15 s of transfers in a run of ``bench_distributed.py
    --large --process``) and the workers spilled them late. (The carries no longer hold
    the strip's graph, session 31.)"""
    from dask.sizeof import sizeof

    @sizeof.register(_Strip)
    def _arrays(x) -> int:
        return 64 + sum(a.nbytes for a in vars(x).values() if isinstance(a, np.ndarray))


def _persist(tasks: dict, name: str, take) -> dict:
    """Compute ``{strip: task}`` (each returning ``(small, carry)``) on the active
    scheduler, keeping the results where they are (``dask.persist``: on a cluster, on the
    workers, recomputed from the graph if one is lost); ``take(strip, small)`` as each
    small part arrives. Returns ``{strip: the persisted task}`` for the next step."""
    import dask

    _register_sizes()
    keys = list(tasks)
    t = time.perf_counter()
    kept = dict(zip(keys, dask.persist(*[tasks[n] for n in keys]), strict=True))
    # the unpersisted graphs hold the previous step's carries: dropped, so that a carry
    # is released as soon as the task that needs it is done (``_fit_pass``)
    tasks.clear()
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


def _fit_pass(strips_, core_idx, us, own, carries, sh, eb, token, store, skip):
    """Step 4: the sweeps of every strip not in ``skip`` (``us``: each strip's labels, or
    their :class:`_RowsRef`); the residuals behind the std's smoothing-bias term (per
    strip, in strip order), the metas, the persisted tasks."""
    import dask

    resid, metas = [None] * len(strips_), [None] * len(strips_)

    def take(n, result):
        # the strip's step-2 carry is no longer needed (its sweeps are done): released
        # at once, not at the pass's end (released_carries)
        carries.pop(n, None)
        res, n_core, n_l, hist = result
        resid[n] = res
        metas[n] = dict(
            n_links=n_l, n_iter=hist.n_iter, converged=hist.converged,
            change=hist.change.tolist(), alpha_updates=list(hist.alpha_updates),
        )  # fmt: skip
        if store is not None and res is not None:
            store.put_residuals(n, res)

    tasks = {}
    for n, st in enumerate(strips_):
        if n in skip:
            metas[n], resid[n] = skip[n]
            continue
        carry = carries[n][1] if n in carries else None
        tasks[n] = dask.delayed(_fit_tile, pure=True, nout=2)(
            carry, st if carry is None else None, us[n], own[n] if carry is None else None,
            sh, eb, dask_key_name=(f"splidar-fit-tile-{token}", n),
        )  # fmt: skip
    carry = None
    kept = _persist(tasks, "sweeps", take)
    return resid, metas, kept


def _scratch_folder(detection) -> str | None:
    """On a ``dask.distributed`` cluster, a new folder that every worker sees, for the
    strips' surfaces (the tasks read their own rows there instead of receiving them in
    the task graph, which the scheduler would hold and send whole: 16 MB for 150,000
    surfaces): inside the detection's ``store`` when it has one (its tiles were written
    there by the workers), else in the temporary directory, if the workers see it (a
    LocalCluster). None on the local schedulers (nothing is sent) or when the workers do
    not see it."""
    import tempfile
    import uuid

    from ..detection._tiled import _client

    client = _client()
    if client is None:
        return None
    base = detection.options.get("store")
    try:
        if base is not None and Path(base).is_dir():
            path = Path(base).resolve() / f"reconstruct-{uuid.uuid4().hex[:12]}"
            path.mkdir()
            path = str(path)
        else:
            path = tempfile.mkdtemp(prefix="splidar-strips-")
        seen = client.run(os.path.isdir, path)
    except OSError:
        return None
    if seen and all(seen.values()):
        return path
    shutil.rmtree(path, ignore_errors=True)
    log.info("reconstruct: the workers do not see %s; the strips travel in the task graph", path)
    return None


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
    options = inspect.signature(_core.reconstruct).bind(detection, **options)
    options.apply_defaults()
    options = {k: v for k, v in options.arguments.items() if k != "detection"}
    opt, cores = _plan(detection, options, strip_rows)
    S = len(detection.surfaces)
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
    folder = getattr(store, "surfaces_folder", None)
    scratch = _scratch_folder(detection) if folder is None else None
    try:
        return _on_strips(detection, opt, cores, options, store, assemble, folder or scratch)
    finally:
        if scratch is not None:  # its arrays on threads (each removal waits on the disk)
            remove_tree(Path(scratch) / "surfaces.zarr")
            shutil.rmtree(scratch, ignore_errors=True)


def _on_strips(detection, opt, cores, options, store, assemble, folder):
    """Steps 1-5 of the module docstring on the strips of these ``cores``; ``folder``: where
    the strips' surfaces (and labels) are written for the tasks to read, or None (they
    travel in the task graph)."""
    import dask

    surf = detection.surfaces
    S, L = len(surf), detection.n_wavelengths
    t0 = time.perf_counter()
    rng = np.random.default_rng(options["rng"])
    with _KERNEL_LOCK:  # numba kernels: the IRF fractions and the class likelihoods
        su = _setup(detection, options["library"], opt, rng)
        K = su.sig.shape[0]
        base = int(rng.integers(2**31))  # where the in-memory run seeds its label sampler
        ll = class_loglik(su.y, su.b, su.eta, su.sig) if K > 1 else np.zeros((S, 1))
        pi = em_proportions(ll) if K > 1 else np.ones(1)
    prior = _prior_arrays(options["alpha"], options["upsilon"], su.sig)
    empty = np.zeros((0, L))
    shared = dict(
        setup=dataclasses.replace(su, y=empty, b=empty, eta=empty, intensity_raw=empty),
        n_cols=int(detection.image_shape[1]), n_slots=int(surf.n_slots), gamma=opt["gamma"],
        rho=opt["rho"], max_iter=opt["max_iter"], tol=opt["tol"], prior=prior, pi=pi, base=base,
    )  # fmt: skip
    idx, strips_, core_idx = _cut(detection, su, cores, ll, folder)
    del ll
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
    # each strip's labels and marginals, read by its tasks of steps 4 and 5 (one class:
    # all 0 and 1, made by the tasks)
    us = idx.put("u", u) if K > 1 else [None] * len(cores)
    resid, metas, fits = _fit_pass(
        strips_, core_idx, us, own, carries, sh, eb, token, store, finished
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
        # the strip's step-4 carry released at once (released_carries)
        fits.pop(n, None)
        tasks.pop(n, None)
        ic, sc = result
        ci = core_idx[n]
        if store is not None:
            store.put_fit(n, cores[n], _points(detection, ci, ic, sc, u[ci], conf[ci]), metas[n])
        if assemble:
            intensity[ci], std[ci] = ic, sc

    tasks = {}
    margs = idx.put("marginals", marg) if K > 1 else [None] * len(cores)
    for n in range(len(cores)):
        if n in finished:
            if assemble:
                pts = store.fitted(n)[0]
                intensity[pts["surface"]] = pts["intensity"]
                std[pts["surface"]] = pts["intensity_std"]
            continue
        tasks[n] = dask.delayed(_std_tile, pure=True)(
            fits[n][1], us[n], margs[n], sh, bias2,
            dask_key_name=(f"splidar-reconstruct-tile-{token}", n),
        )  # fmt: skip
    _run(tasks, "reconstruct", take)
    fits.clear()
    tasks.clear()
    t_iter = time.perf_counter()
    hyper = _hyperparameters(
        su, opt, prior, marg.mean(axis=0), bias2,
        types.SimpleNamespace(n_edges=sum(m["n_links"] for m in metas) // 2),
    )  # fmt: skip
    seeds = "rng; labels keyed by surface, std by first row"
    hyper["tiles"] = dict(cores=tuple(cores), margin=MARGIN, seeds=seeds)
    hyper["label_gamma"] = None  # each strip's label field estimates its own strength
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
