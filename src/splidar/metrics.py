"""Evaluation of estimated surfaces against ground truth (the paper's criteria).

Implements the metrics of Belmekki et al., section "Comparison Algorithms and
Evaluation Criteria": estimated and true points are matched **one-to-one within each
pixel, nearest depth first**, and only pairs with ``|d_est - d_true| <= tau`` count.

* ``F_true(tau)``  = matched / true points (probability of true detection).
* ``F_false(tau)`` = number of estimated points left unmatched (a count, as in the
  paper's ``tabl:table_TD``); :attr:`Metrics.f_false_rate` divides it by the number of
  true points for tables across scenes.
* DAE = mean ``|d_est - d_true|`` over matched pairs.
* IAE = ``(sum_matched sum_l |I_est - I_true| + sum_unmatched sum_l |I|) / S_true``
  where unmatched points are the false estimates and the missed true points.
* detection accuracy (``tabl:AccTD``) and label accuracy over matched points.

Everything is vectorised: candidate pairs are enumerated pixel by pixel with
``searchsorted`` and the greedy nearest-first matching is computed by rounds of
"mutual best" pairs (see :func:`match_points`), a few NumPy passes in all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ._validation import SplidarError, as_float_array, check_positive, describe
from .points import PointSet

__all__ = ["FTrueCurve", "Matching", "Metrics", "evaluate", "f_true_curve", "match_points"]

#: Relative tolerance on the inclusive boundary ``|d| <= tau`` so that e.g.
#: ``10.3 - 10.0 <= 0.3`` holds despite floating-point rounding.
_TAU_RTOL = 1e-9

_DEFAULT_TAU = 2.0


# --------------------------------------------------------------------------------------
# result types
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Matching:
    """One-to-one pairing of estimated and true points (see :func:`match_points`).

    Attributes
    ----------
    est_index, true_index : ndarray of int, shape (n_matched,)
        Indices into the estimated and true point sets of each matched pair, sorted by
        ``est_index``.
    distance : ndarray of float, shape (n_matched,)
        ``|d_est - d_true|`` of each pair, in the unit of ``tau`` (bins or metres).
    unmatched_est, unmatched_true : ndarray of int
        Indices of the estimated (false detections) and true (missed) points left over.
    tau : float
        Matching distance used (inclusive).
    unit : str
        ``"bin"`` (``depth_bin`` compared) or ``"m"`` (``depth_m`` compared).
    """

    est_index: np.ndarray
    true_index: np.ndarray
    distance: np.ndarray
    unmatched_est: np.ndarray
    unmatched_true: np.ndarray
    tau: float
    unit: str = "bin"

    @property
    def n_matched(self) -> int:
        return int(self.est_index.size)


@dataclass(frozen=True)
class Metrics:
    """The paper's evaluation criteria for one (estimate, truth) pair of point sets.

    Attributes
    ----------
    f_true : float
        ``F_true(tau)``: matched / true points (NaN when there are no true points).
    f_false : int
        ``F_false(tau)``: number of estimated points left unmatched (a count).
    f_false_rate : float
        ``f_false / n_true`` (NaN when there are no true points); comparable across scenes.
    dae : float
        Mean ``|d_est - d_true|`` over matched pairs, in bins (NaN when nothing matched).
    dae_m : float or None
        The same in metres, when both sets carry ``depth_m`` (None otherwise).
    iae : float or None
        The paper's intensity error per true point (None when either set lacks intensity).
    detection_accuracy : float
        Fraction of pixels whose "target present / absent" decision (at least one
        estimated point vs. at least one true point) is right; see :func:`evaluate`.
    label_accuracy : float or None
        Fraction of matched pairs with the same label (None when either set lacks
        labels, NaN when nothing matched).
    n_true, n_est, n_matched : int
        Point counts.
    tau : float
        Matching distance (inclusive), in ``tau_unit``.
    tau_unit : str
        ``"bin"`` or ``"m"``.
    """

    f_true: float
    f_false: int
    f_false_rate: float
    dae: float
    dae_m: float | None
    iae: float | None
    detection_accuracy: float
    label_accuracy: float | None
    n_true: int
    n_est: int
    n_matched: int
    tau: float
    tau_unit: str = "bin"

    def as_dict(self) -> dict[str, float | int | str | None]:
        """All fields by name (plain Python numbers), e.g. for a table row or JSON."""
        return asdict(self)

    def __str__(self) -> str:
        def fmt(v):
            if v is None:
                return "n/a"
            if isinstance(v, str):
                return v
            if isinstance(v, (int, np.integer)):
                return f"{int(v)}"
            return f"{v:.4g}"

        rows = [
            ("tau", f"{fmt(self.tau)} {self.tau_unit}"),
            ("F_true", fmt(self.f_true)),
            ("F_false (count)", fmt(self.f_false)),
            ("F_false / n_true", fmt(self.f_false_rate)),
            ("DAE (bins)", fmt(self.dae)),
            ("DAE (m)", fmt(self.dae_m)),
            ("IAE", fmt(self.iae)),
            ("detection accuracy", fmt(self.detection_accuracy)),
            ("label accuracy", fmt(self.label_accuracy)),
            ("true / est / matched", f"{self.n_true} / {self.n_est} / {self.n_matched}"),
        ]
        w = max(len(k) for k, _ in rows)
        return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


@dataclass(frozen=True)
class FTrueCurve:
    """Metrics as functions of the matching distance (see :func:`f_true_curve`).

    Attributes
    ----------
    tau : ndarray, shape (m,)
        Matching distances, in ``tau_unit``.
    f_true : ndarray, shape (m,)
        ``F_true(tau)``.
    f_false : ndarray of int, shape (m,)
        ``F_false(tau)`` (count of unmatched estimated points).
    dae : ndarray, shape (m,)
        Mean absolute depth error over the pairs matched at each tau, in ``tau_unit``
        (NaN when nothing matched).
    n_true, n_est : int
        Point counts.
    tau_unit : str
        ``"bin"`` or ``"m"``.
    """

    tau: np.ndarray
    f_true: np.ndarray
    f_false: np.ndarray
    dae: np.ndarray
    n_true: int
    n_est: int
    tau_unit: str = "bin"


# --------------------------------------------------------------------------------------
# matching
# --------------------------------------------------------------------------------------
def _as_points(p):
    """A PointSet, or the ``.points`` of a result object (Detection, Reconstruction)."""
    pts = getattr(p, "points", None)
    return pts if not isinstance(p, PointSet) and isinstance(pts, PointSet) else p


def _check_pair(estimated, true) -> None:
    for name, p in (("estimated", estimated), ("true", true)):
        if not isinstance(p, PointSet):
            raise SplidarError(
                f"`{name}` must be a splidar.PointSet; got {describe(p)}. Build one with "
                "PointSet(row=, col=, depth_bin=, image_shape=) or take `.points` of a result."
            )
    if tuple(estimated.image_shape) != tuple(true.image_shape):
        raise SplidarError(
            f"`estimated` and `true` describe different images: image_shape "
            f"{estimated.image_shape} vs {true.image_shape}. Compare points of the same scene "
            "(crop or re-index one of them first)."
        )


def _depths(estimated: PointSet, true: PointSet, unit: str) -> tuple[np.ndarray, np.ndarray]:
    if unit == "bin":
        return estimated.depth_bin, true.depth_bin
    missing = [n for n, p in (("estimated", estimated), ("true", true)) if p.depth_m is None]
    if missing:
        raise SplidarError(
            f"`tau_m` compares depths in metres but {' and '.join(missing)} has no `depth_m`; "
            "give `tau` in bins instead, or set depth_m (depth_bin x bin width x c / 2)."
        )
    return estimated.depth_m, true.depth_m


def _candidate_pairs(estimated: PointSet, true: PointSet, d_est, d_true, tau: float):
    """All (est, true) pairs in the same pixel with ``|d| <= tau``, sorted nearest first.

    Returns ``(e, t, dist)``; ties are broken by est index then true index, so the
    order is total and the result deterministic.
    """
    cols = true.image_shape[1]
    pe = estimated.row * cols + estimated.col
    pt = true.row * cols + true.col
    t_order = np.argsort(pt, kind="stable")
    pt_sorted = pt[t_order]
    lo = np.searchsorted(pt_sorted, pe, side="left")
    hi = np.searchsorted(pt_sorted, pe, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    if total == 0:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0)
    e = np.repeat(np.arange(pe.size, dtype=np.int64), cnt)
    start = np.repeat(np.cumsum(cnt) - cnt, cnt)
    t = t_order[np.repeat(lo, cnt) + (np.arange(total) - start)]
    dist = np.abs(d_est[e] - d_true[t])
    keep = dist <= tau * (1.0 + _TAU_RTOL) + _TAU_RTOL * (tau == 0)
    keep &= np.isfinite(dist)
    e, t, dist = e[keep], t[keep], dist[keep]
    order = np.lexsort((t, e, dist))
    return e[order], t[order], dist[order]


def _greedy(e: np.ndarray, t: np.ndarray, n_est: int, n_true: int) -> np.ndarray:
    """Greedy nearest-first one-to-one matching of pairs already sorted nearest first.

    Returns the positions (into ``e``/``t``) of the accepted pairs.

    A pair that is the first (nearest) remaining pair of both its estimated and its
    true point is taken by the sequential greedy algorithm too (every pair sharing a
    point with it comes later in the order), so accepting all such "mutual best"
    pairs at once, removing their points and repeating gives exactly the greedy
    result, in a few vectorised rounds (at most the number of points per pixel).
    """
    active = np.arange(e.size)
    accepted = []
    used_e = np.zeros(n_est, bool)
    used_t = np.zeros(n_true, bool)
    while active.size:
        ea, ta = e[active], t[active]
        # first occurrence in sorted order = nearest remaining pair of that point
        _, fe = np.unique(ea, return_index=True)
        _, ft = np.unique(ta, return_index=True)
        best_e = np.zeros(active.size, bool)
        best_e[fe] = True
        best_t = np.zeros(active.size, bool)
        best_t[ft] = True
        take = active[best_e & best_t]
        accepted.append(take)
        used_e[e[take]] = True
        used_t[t[take]] = True
        active = active[~(used_e[ea] | used_t[ta])]
    return np.concatenate(accepted) if accepted else np.zeros(0, np.int64)


def _resolve_tau(tau, tau_m) -> tuple[float, str]:
    if tau is not None and tau_m is not None:
        raise SplidarError(
            "give either `tau` (bins) or `tau_m` (metres), not both; got "
            f"tau={tau!r}, tau_m={tau_m!r}."
        )
    if tau_m is not None:
        return check_positive(tau_m, "tau_m", allow_zero=True), "m"
    return check_positive(_DEFAULT_TAU if tau is None else tau, "tau", allow_zero=True), "bin"


def match_points(
    estimated: PointSet,
    true: PointSet,
    *,
    tau: float | None = None,
    tau_m: float | None = None,
) -> Matching:
    """Match estimated and true points one-to-one within each pixel, nearest first.

    Among all (estimated, true) pairs in the same pixel with ``|d_est - d_true| <= tau``
    (inclusive, up to a 1e-9 relative rounding tolerance), the nearest pair is matched
    first, its two points are removed, and so on (greedy nearest-first; ties broken by
    estimated then true index). This is the coupling used by ``F_true(tau)`` and DAE.

    Parameters
    ----------
    estimated, true : PointSet
        Points of the same image (``image_shape`` must agree). A result object with a
        ``.points`` PointSet (``Detection``, ``Reconstruction``) is accepted too.
    tau : float, optional
        Matching distance in time bins (``depth_bin``), >= 0. Default 2.0 bins when
        ``tau_m`` is not given either.
    tau_m : float, optional
        Matching distance in metres instead; compares ``depth_m``, which both sets must
        carry (e.g. the paper's tau = 4 mm).

    Returns
    -------
    Matching

    Raises
    ------
    SplidarError
        Not PointSets, different image shapes, negative tau, both tau and tau_m, or
        tau_m without ``depth_m``.

    Examples
    --------
    >>> from splidar import PointSet
    >>> true = PointSet(row=[0, 0], col=[0, 0], depth_bin=[10.0, 20.0], image_shape=(1, 1))
    >>> est = PointSet(row=[0, 0, 0], col=[0, 0, 0], depth_bin=[10.5, 11.0, 19.0],
    ...                image_shape=(1, 1))
    >>> m = match_points(est, true, tau=1.5)
    >>> m.est_index.tolist(), m.true_index.tolist(), m.unmatched_est.tolist()
    ([0, 2], [0, 1], [1])
    """
    estimated, true = _as_points(estimated), _as_points(true)
    _check_pair(estimated, true)
    tau_v, unit = _resolve_tau(tau, tau_m)
    d_est, d_true = _depths(estimated, true, unit)
    e, t, dist = _candidate_pairs(estimated, true, d_est, d_true, tau_v)
    acc = _greedy(e, t, len(estimated), len(true))
    e, t, dist = e[acc], t[acc], dist[acc]
    order = np.argsort(e, kind="stable")
    e, t, dist = e[order], t[order], dist[order]
    um_e = np.ones(len(estimated), bool)
    um_e[e] = False
    um_t = np.ones(len(true), bool)
    um_t[t] = False
    out = Matching(
        est_index=e,
        true_index=t,
        distance=dist,
        unmatched_est=np.flatnonzero(um_e),
        unmatched_true=np.flatnonzero(um_t),
        tau=tau_v,
        unit=unit,
    )
    for a in (out.est_index, out.true_index, out.distance, out.unmatched_est, out.unmatched_true):
        a.flags.writeable = False
    return out


# --------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------
def _div(a: float, b: float) -> float:
    return float(a) / float(b) if b else float("nan")


def _detection_accuracy(estimated: PointSet, true: PointSet) -> float:
    rows, cols = true.image_shape
    n_pix = rows * cols
    if n_pix == 0:
        return float("nan")
    has_e = np.zeros(n_pix, bool)
    has_e[estimated.row * cols + estimated.col] = True
    has_t = np.zeros(n_pix, bool)
    has_t[true.row * cols + true.col] = True
    return float(np.count_nonzero(has_e == has_t)) / n_pix


def evaluate(
    estimated: PointSet,
    true: PointSet,
    *,
    tau: float | None = None,
    tau_m: float | None = None,
) -> Metrics:
    """Score estimated surfaces against the truth with the paper's criteria.

    Points are first matched with :func:`match_points` (one-to-one per pixel, nearest
    depth first, ``|d| <= tau``).

    Parameters
    ----------
    estimated, true : PointSet
        Estimated and ground-truth points of the same image.
    tau : float, optional
        Matching distance in bins (default 2.0 when ``tau_m`` is not given).
    tau_m : float, optional
        Matching distance in metres (both sets must carry ``depth_m``).

    Returns
    -------
    Metrics
        * ``f_true = n_matched / n_true``; ``f_false`` = unmatched estimates (count),
          ``f_false_rate = f_false / n_true``.
        * ``dae``: mean ``|depth_bin_est - depth_bin_true|`` over matches; ``dae_m`` the
          same on ``depth_m`` when both sets carry it.
        * ``iae`` (paper): ``(sum_matched sum_l |I_est - I_true| + sum_{unmatched est
          and true} sum_l |I|) / n_true``; None unless both sets have ``intensity``.
        * ``detection_accuracy`` (``tabl:AccTD``): the paper compares its 3D detector
          with MSTD, a per-pixel (2D) detector, on the Lego scene against a reference
          detection; the only decision both make is whether a pixel holds a target. So
          it is the fraction of *pixels* where "at least one estimated point" agrees
          with "at least one true point" (true positives plus true negatives over all
          pixels). It ignores depth; ``f_true`` and ``f_false`` measure the 3D part.
        * ``label_accuracy``: fraction of matched pairs with equal labels; None unless
          both sets have ``label``.

    Raises
    ------
    SplidarError
        As :func:`match_points`; also intensities with different numbers of
        wavelengths.

    Examples
    --------
    >>> from splidar import PointSet
    >>> true = PointSet(row=[0, 0], col=[0, 0], depth_bin=[10.0, 20.0], image_shape=(1, 2))
    >>> est = PointSet(row=[0, 0], col=[0, 1], depth_bin=[10.5, 19.0], image_shape=(1, 2))
    >>> m = evaluate(est, true, tau=1.0)
    >>> m.f_true, m.f_false, m.dae, m.detection_accuracy
    (0.5, 1, 0.5, 0.5)
    """
    estimated, true = _as_points(estimated), _as_points(true)
    match = match_points(estimated, true, tau=tau, tau_m=tau_m)
    e, t = match.est_index, match.true_index
    n_true, n_est, n_m = len(true), len(estimated), int(e.size)
    n_false = int(match.unmatched_est.size)

    dae = float(np.mean(np.abs(estimated.depth_bin[e] - true.depth_bin[t]))) if n_m else np.nan
    dae_m = None
    if estimated.depth_m is not None and true.depth_m is not None:
        dae_m = float(np.mean(np.abs(estimated.depth_m[e] - true.depth_m[t]))) if n_m else np.nan

    iae = None
    if estimated.intensity is not None and true.intensity is not None:
        if estimated.n_wavelengths != true.n_wavelengths:
            raise SplidarError(
                f"`estimated` has intensities over {estimated.n_wavelengths} wavelength(s) but "
                f"`true` over {true.n_wavelengths}; IAE compares them wavelength by wavelength."
            )
        ie, it = estimated.intensity, true.intensity
        err = np.abs(ie[e] - it[t]).sum(dtype=np.float64)  # matched pairs
        err += np.abs(ie[match.unmatched_est]).sum(dtype=np.float64)  # false detections
        err += np.abs(it[match.unmatched_true]).sum(dtype=np.float64)  # missed points
        iae = _div(err, n_true)

    label_acc = None
    if estimated.label is not None and true.label is not None:
        label_acc = _div(np.count_nonzero(estimated.label[e] == true.label[t]), n_m)

    return Metrics(
        f_true=_div(n_m, n_true),
        f_false=n_false,
        f_false_rate=_div(n_false, n_true),
        dae=float(dae),
        dae_m=None if dae_m is None else float(dae_m),
        iae=iae,
        detection_accuracy=_detection_accuracy(estimated, true),
        label_accuracy=label_acc,
        n_true=n_true,
        n_est=n_est,
        n_matched=n_m,
        tau=match.tau,
        tau_unit=match.unit,
    )


def f_true_curve(
    estimated: PointSet,
    true: PointSet,
    taus,
    *,
    unit: str = "bin",
) -> FTrueCurve:
    """``F_true``, ``F_false`` and DAE for many matching distances at once (for plots).

    Greedy nearest-first matching with a distance cut-off is the prefix of the greedy
    matching without one (pairs are taken in increasing distance), so one matching
    at ``max(taus)`` gives every curve point exactly.

    Parameters
    ----------
    estimated, true : PointSet
        Points of the same image.
    taus : array_like of float, shape (m,)
        Matching distances (>= 0), in ``unit``.
    unit : {"bin", "m"}
        Compare ``depth_bin`` (default) or ``depth_m``.

    Returns
    -------
    FTrueCurve

    Examples
    --------
    >>> from splidar import PointSet
    >>> true = PointSet(row=[0], col=[0], depth_bin=[10.0], image_shape=(1, 1))
    >>> est = PointSet(row=[0], col=[0], depth_bin=[11.0], image_shape=(1, 1))
    >>> f_true_curve(est, true, [0.5, 1.0, 2.0]).f_true.tolist()
    [0.0, 1.0, 1.0]
    """
    if unit not in ("bin", "m"):
        raise SplidarError(f"`unit` must be 'bin' or 'm'; got {unit!r}.")
    taus_a = as_float_array(taus, "taus").reshape(-1)
    if taus_a.size == 0:
        raise SplidarError("`taus` is empty; give at least one matching distance.")
    if np.any(taus_a < 0):
        raise SplidarError(f"`taus` must be >= 0; got min {taus_a.min():g}.")
    estimated, true = _as_points(estimated), _as_points(true)
    kw = {"tau": float(taus_a.max())} if unit == "bin" else {"tau_m": float(taus_a.max())}
    m = match_points(estimated, true, **kw)
    d_est, d_true = _depths(estimated, true, unit)
    dist = np.sort(np.abs(d_est[m.est_index] - d_true[m.true_index]))
    cum = np.concatenate([[0.0], np.cumsum(dist, dtype=np.float64)])
    thr = taus_a * (1.0 + _TAU_RTOL) + _TAU_RTOL * (taus_a == 0)
    k = np.searchsorted(dist, thr, side="right")
    n_true, n_est = len(true), len(estimated)
    with np.errstate(invalid="ignore", divide="ignore"):
        f_true = k / n_true if n_true else np.full(k.shape, np.nan)
        dae = np.where(k > 0, cum[k] / np.maximum(k, 1), np.nan)
    out = FTrueCurve(
        tau=taus_a,
        f_true=np.asarray(f_true, dtype=np.float64),
        f_false=(n_est - k).astype(np.int64),
        dae=dae,
        n_true=n_true,
        n_est=n_est,
        tau_unit=unit,
    )
    return out
