"""The background-only (null) distribution of the saliency and the detection threshold.

Two fits are kept:

* the paper's gamma model (``eq:gamma_distrib``), fitted robustly by matching the
  median and the 90 % quantile (both unaffected while signal voxels are < 10 % of the
  sample);
* an empirical null: background-only cubes drawn from the *estimated* background
  (Poisson draws of ``bhat``), passed through the same pipeline. Its ``1 - pfa``
  quantile, as a function of the local background level, is the calibrated threshold.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit
from scipy import optimize, stats

__all__ = ["fit_gamma_quantiles", "threshold_table"]


def fit_gamma_quantiles(s: np.ndarray, *, p_lo: float = 0.5, p_hi: float = 0.9):
    """Gamma ``(shape, scale)`` matching two quantiles of ``s`` (robust to a sparse tail).

    Falls back to moments of the values below the ``p_hi`` quantile when the lower
    quantile is 0 (sparse data where most saliency values are equal).
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    s = s[np.isfinite(s)]
    if s.size == 0:
        return 1.0, 1e-12
    q_lo, q_hi = np.quantile(s, [p_lo, p_hi])
    if q_lo > 0 and q_hi > q_lo:
        ratio = q_hi / q_lo

        def f(log_a):
            a = np.exp(log_a)
            return stats.gamma.ppf(p_hi, a) / stats.gamma.ppf(p_lo, a) - ratio

        lo, hi = np.log(1e-3), np.log(1e5)
        flo, fhi = f(lo), f(hi)
        if flo > 0 > fhi:
            a = float(np.exp(optimize.brentq(f, lo, hi, xtol=1e-6)))
            scale = float(q_lo / stats.gamma.ppf(p_lo, a))
            return a, scale
    body = s[s <= q_hi]
    m, v = body.mean(), body.var()
    if m <= 0 or v <= 0:
        return 1.0, max(float(s.mean()), 1e-12)
    return float(m * m / v), float(v / m)


def threshold_table(
    s: np.ndarray,
    level: np.ndarray,
    pfa: float,
    *,
    min_exceed: int = 100,
    max_groups: int = 12,
    workers: int = 1,
):
    """Empirical ``1 - pfa`` quantile of null saliency ``s`` as a function of ``level``.

    Voxels are grouped by background level (equal-count groups, each with about
    ``min_exceed`` or more expected exceedances); each group gives its quantile at its
    median level.

    The groups' median levels and quantiles are taken on ``workers`` threads (NumPy's
    selections release the GIL; each group's values are its own: the same table).

    Returns
    -------
    levels, thresholds : ndarray (G,)
        Increasing levels and the threshold at each (``G = 1``: one global threshold).
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    v = np.asarray(level, dtype=np.float64).ravel()
    n = s.size
    g = int(np.clip(np.floor(n * pfa / min_exceed), 1, max_groups))
    lo, hi = np.quantile(v, [0.01, 0.99])
    if g == 1 or hi - lo <= 0.02 * max(abs(hi), 1e-12):
        return np.array([np.median(v)]), np.array([np.quantile(s, 1.0 - pfa)])
    groups = _equal_count_groups(v, g)

    def one(idx):
        return np.median(v[idx]), np.quantile(s[idx], 1.0 - pfa)

    n_thr = max(1, min(int(workers), g))
    if n_thr > 1:
        with ThreadPoolExecutor(n_thr) as ex:
            pairs = list(ex.map(one, groups))
    else:
        pairs = [one(idx) for idx in groups]
    xs = np.asarray([p[0] for p in pairs])
    ys = np.asarray([p[1] for p in pairs])
    # equal levels (many voxels at one level) would make interpolation ill-defined
    keep = np.concatenate([[True], np.diff(xs) > 1e-12 * max(abs(xs[-1]), 1.0)])
    if not keep.all():
        ux = xs[keep]
        uy = np.array([ys[(xs >= x) & (xs <= x)].max() for x in ux])
        xs, ys = ux, uy
    return xs, ys


def _equal_count_groups(v: np.ndarray, g: int) -> list[np.ndarray]:
    """Indices of ``g`` equal-count groups of ``v`` by increasing value.

    The same groups as ``np.array_split(np.argsort(v, kind="stable"), g)`` (ties in
    index order), without the stable argsort (the slowest step of the table), nor a
    sort: group ``i`` holds ``b_i <= v < b_(i+1)`` with ``b_i`` the value at its first
    sorted position (one selection finds them all), less the values tied with
    ``b_(i+1)`` that sort before that position.
    """
    n = v.size
    sizes = np.full(g, n // g, np.int64)
    sizes[: n % g] += 1
    kth = np.cumsum(sizes)[:-1]  # sorted position of each group's first element
    b = np.partition(v, kth)[kth] if kth.size else kth
    if kth.size == 0 or np.any(np.diff(b) <= 0):
        # one value spans several groups: the plain way
        return np.array_split(np.argsort(v, kind="stable"), g)
    gid = np.empty(n, np.uint8)
    below = np.zeros(g, np.int64)
    _group_ids(v, b, gid, below)  # one pass: gid = #(b <= v), counts of gid
    # ties with a boundary value sorting before it (index order) go to the group below
    n_before = kth - np.cumsum(below)[:-1]  # #(v < b_i) = #(gid <= i)
    for bi, m in zip(b, n_before, strict=True):
        if m > 0:
            gid[np.flatnonzero(v == bi)[:m]] -= 1
    # the groups' indices in index order, group by group (a stable sort of gid)
    order = np.argsort(gid, kind="stable")
    return np.split(order, np.cumsum(np.bincount(gid, minlength=g))[:-1])


@njit(cache=True, nogil=True)
def _group_ids(v, b, gid, count):  # pragma: no cover - numba
    """``gid[k] = #(b <= v[k])`` (``b`` increasing) and ``count[i] = #(gid == i)`` among
    the values that are not NaN."""
    m = b.size
    for k in range(v.size):
        x = v[k]
        lo, hi = 0, m  # the first b above x
        while lo < hi:
            mid = (lo + hi) // 2
            if b[mid] <= x:
                lo = mid + 1
            else:
                hi = mid
        gid[k] = lo
        if x == x:  # NaN: group 0, and below no boundary (as ``v < b`` counts)
            count[lo] += 1
