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

import numpy as np
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
    s: np.ndarray, level: np.ndarray, pfa: float, *, min_exceed: int = 100, max_groups: int = 12
):
    """Empirical ``1 - pfa`` quantile of null saliency ``s`` as a function of ``level``.

    Voxels are grouped by background level (equal-count groups, each with about
    ``min_exceed`` or more expected exceedances); each group gives its quantile at its
    median level.

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
    xs, ys = [], []
    for idx in _equal_count_groups(v, g):
        xs.append(np.median(v[idx]))
        ys.append(np.quantile(s[idx], 1.0 - pfa))
    xs = np.asarray(xs)
    ys = np.asarray(ys)
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
    gid = np.zeros(n, np.uint8)
    for bi in b:
        gid += v >= bi
    # ties with a boundary value sorting before it (index order) go to the group below
    n_before = kth - np.array([np.count_nonzero(v < bi) for bi in b])
    for bi, m in zip(b, n_before, strict=True):
        if m > 0:
            gid[np.flatnonzero(v == bi)[:m]] -= 1
    return [np.flatnonzero(gid == i) for i in range(g)]
