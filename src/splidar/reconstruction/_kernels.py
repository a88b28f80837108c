"""Numba kernels of the coordinate descent (Algorithm 2): one sweep and the objective.

All arrays are float64 (accumulation) except indices (int64). The surface graph is CSR
(``indptr`` (S+1,), ``indices`` (E,)), symmetric, without self links. The gamma-MRF
uses one more, implicit, link from each ``h_s`` to its own ``w_s`` (see ``_core``).

Notation (per surface s, wavelength l, class k)::

    y    raw own-pixel counts over the support             (S, L)
    b    expected own-pixel background over the support    (S, L)
    eta  fraction of the IRF inside the support            (S, L)
    z    expected signal part of y (EM split)              (S, L)
    r    reflectivity, beta its per-surface scale          (S, L)
    h    shading (gamma-MRF), w auxiliary                  (S,)
    u    label                                             (S,)
    alpha, ups, eps : class hyperparameters                (K, L)

The per-surface loops run in parallel (``prange``): within one colour of the red-black
order no two surfaces are linked, and every other update reads only arrays it does not
write (h from w, w from h, r and beta per surface), so the result does not depend on the
number of threads (only the sums of the objective and of the change are reduced in a
thread-dependent order when compiled parallel).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# The loops are written with prange (safe, see above) and compiled parallel. Measured on
# the idle 2-core machine: Art-size reconstruction 0.59 -> 0.33 s, 80,000 surfaces about
# the same (0.26-0.34 s); under a load of 3-4 from other processes numba's thread pool was
# slower than one thread (a parallel region waits for its slowest thread), so
# ``reconstruct`` sets the number of threads from the free cores (``_core._free_cores``).
# Results are deterministic for a given number of threads.
_PARALLEL = True


@njit(cache=True)
def _slot_index(row, col, slot, rows, cols, n_slots):
    """``(rows, cols, n_slots)`` int64 grid of surface indices (-1 where no surface)."""
    idx = np.full((rows, cols, n_slots), -1, np.int64)
    for s in range(row.shape[0]):
        idx[row[s], col[s], slot[s]] = s
    return idx


@njit(cache=True)
def graph_csr(row, col, slot, depth, rows, cols, n_slots, gate):
    """CSR links between surfaces of 4-neighbour pixels with ``|depth difference| <= gate``.

    Returns ``(indptr (S + 1,), indices (E,))``, each row's neighbours in ascending order
    (see :func:`splidar.reconstruction.build_graph`).
    """
    S = row.shape[0]
    idx = _slot_index(row, col, slot, rows, cols, n_slots)
    dr = (-1, 0, 0, 1)
    dc = (0, -1, 1, 0)
    indptr = np.zeros(S + 1, np.int64)
    # count, then fill: the neighbour test is written out in both passes (a helper
    # function, even inlined, made this 17x slower: 0.0017 -> 0.03 s for 80,000 surfaces)
    for s in range(S):
        n = 0
        for d in range(4):
            rr = row[s] + dr[d]
            cc = col[s] + dc[d]
            if rr < 0 or rr >= rows or cc < 0 or cc >= cols:
                continue
            for k in range(n_slots):
                t = idx[rr, cc, k]
                if t >= 0 and abs(depth[s] - depth[t]) <= gate:
                    n += 1
        indptr[s + 1] = indptr[s] + n
    indices = np.empty(indptr[S], np.int64)
    for s in range(S):
        j0 = indptr[s]
        j = j0
        for d in range(4):
            rr = row[s] + dr[d]
            cc = col[s] + dc[d]
            if rr < 0 or rr >= rows or cc < 0 or cc >= cols:
                continue
            for k in range(n_slots):
                t = idx[rr, cc, k]
                if t >= 0 and abs(depth[s] - depth[t]) <= gate:
                    # insertion in ascending order
                    i = j
                    while i > j0 and indices[i - 1] > t:
                        indices[i] = indices[i - 1]
                        i -= 1
                    indices[i] = t
                    j += 1
    return indptr, indices


@njit(cache=True, inline="always")
def _before(b, a, depth, tie):
    """Surface ``b`` sorts before ``a`` by (depth, tie, index), NaN depths last (the order
    of ``np.lexsort``, which is stable)."""
    db = depth[b]
    da = depth[a]
    if db != da and not (math.isnan(db) and math.isnan(da)):
        if math.isnan(da):
            return True
        if math.isnan(db):
            return False
        return db < da
    if tie[b] != tie[a]:
        return tie[b] < tie[a]
    return b < a


@njit(cache=True)
def pixel_ranks(row, col, depth, tie):
    """Rank of each surface by (depth, tie, index) among the surfaces of its pixel, in
    one pass when the surfaces come grouped by pixel in (row, col) order (as detections
    list them): ``(rank (S,) int64, True)``; ``(_, False)`` when they do not (the
    caller sorts instead)."""
    S = row.shape[0]
    rank = np.empty(S, np.int64)
    i = 0
    while i < S:
        if i > 0 and (row[i] < row[i - 1] or (row[i] == row[i - 1] and col[i] < col[i - 1])):
            return rank, False
        j = i + 1
        while j < S and row[j] == row[i] and col[j] == col[i]:
            j += 1
        for a in range(i, j):
            n = 0
            for b in range(i, j):
                if b != a and _before(b, a, depth, tie):
                    n += 1
            rank[a] = n
        i = j
    return rank, True


@njit(cache=True)
def bridge_csr(row, col, slot, depth, rows, cols, n_slots, gate, indptr, indices):
    """The CSR links of ``graph_csr`` plus a link between surfaces two pixels apart along a
    row or a column, within ``gate``, when each has at most one link and no surface of the
    pixel between them is linked to both (the two ends of a strand broken by a missed
    detection; see :func:`splidar.reconstruction.build_graph`).

    Returns ``(indptr (S + 1,), indices (E',))``, each row's neighbours in ascending order.
    """
    S = row.shape[0]
    idx = _slot_index(row, col, slot, rows, cols, n_slots)
    dr = (-2, 0, 0, 2)
    dc = (0, -2, 2, 0)
    extra = np.zeros(S, np.int64)
    for p in range(2):  # count, then fill
        if p == 1:
            out_ptr = np.zeros(S + 1, np.int64)
            for s in range(S):
                out_ptr[s + 1] = out_ptr[s] + (indptr[s + 1] - indptr[s]) + extra[s]
            out = np.empty(out_ptr[S], np.int64)
        for s in range(S):
            if p == 1:
                j = out_ptr[s]
                for e in range(indptr[s], indptr[s + 1]):
                    out[j] = indices[e]
                    j += 1
            for d in range(4):
                rr = row[s] + dr[d]
                cc = col[s] + dc[d]
                if rr < 0 or rr >= rows or cc < 0 or cc >= cols:
                    continue
                mr = row[s] + dr[d] // 2
                mc = col[s] + dc[d] // 2
                if indptr[s + 1] - indptr[s] > 1:
                    continue
                for k in range(n_slots):
                    t = idx[rr, cc, k]
                    if t < 0 or abs(depth[s] - depth[t]) > gate:
                        continue
                    if indptr[t + 1] - indptr[t] > 1:
                        continue
                    path = False  # a middle surface linked to both s and t
                    for km in range(n_slots):
                        m = idx[mr, mc, km]
                        if m >= 0 and abs(depth[s] - depth[m]) <= gate:
                            if abs(depth[t] - depth[m]) <= gate:
                                path = True
                    if path:
                        continue
                    if p == 0:
                        extra[s] += 1
                    else:
                        i = j  # insertion in ascending order
                        while i > out_ptr[s] and out[i - 1] > t:
                            out[i] = out[i - 1]
                            i -= 1
                        out[i] = t
                        j += 1
    return out_ptr, out


@njit(cache=True, parallel=_PARALLEL)
def irf_fraction(cum, peak, depth, start, stop, out):
    """``out[s, l] = cum_l(stop - d + p_l) - cum_l(start - d + p_l)``, clipped to [0, 1].

    ``cum`` (L, n + 1): cumulative sums of each IRF row from 0, linearly interpolated
    between integer arguments (0 below 0, the total above n), as ``np.interp``.
    """
    S = depth.shape[0]
    L, n1 = cum.shape
    for s in prange(S):
        for l in range(L):
            v = 0.0
            for sign in range(2):
                x = (stop[s] if sign == 0 else start[s]) - depth[s] + peak[l]
                if x <= 0.0:
                    c = cum[l, 0] if x == 0.0 else 0.0
                elif x >= n1 - 1:
                    c = cum[l, n1 - 1]
                else:
                    i = int(math.floor(x))
                    f = x - i
                    c = cum[l, i] + f * (cum[l, i + 1] - cum[l, i])
                v += c if sign == 0 else -c
            out[s, l] = min(max(v, 0.0), 1.0)


@njit(cache=True, parallel=_PARALLEL)
def estep(y, b, eta, r, h, z, q):
    """EM split of the counts: ``z = y * q``, ``q = eta h r / (eta h r + b)``."""
    S, L = y.shape
    for s in prange(S):
        for l in range(L):
            sig = eta[s, l] * h[s] * r[s, l]
            tot = sig + b[s, l]
            if tot > 0.0:
                q[s, l] = sig / tot
            else:
                q[s, l] = 1.0
            z[s, l] = y[s, l] * q[s, l]


@njit(cache=True)
def class_cst(alpha, ups, eps):
    """``-lgamma(alpha) + ups log(eps) - lgamma(ups)`` per class and wavelength, (K, L)."""
    K, L = alpha.shape
    cst = np.empty((K, L))
    for k in range(K):
        for l in range(L):
            v = ups[k, l]
            cst[k, l] = -math.lgamma(alpha[k, l]) + v * math.log(eps[k, l]) - math.lgamma(v)
    return cst


@njit(cache=True)
def _same_alpha(alpha):
    """(L,) bool: alpha is the same for every class at wavelength l (a cheaper score)."""
    K, L = alpha.shape
    same = np.ones(L, np.bool_)
    for l in range(L):
        for k in range(1, K):
            if alpha[k, l] != alpha[0, l]:
                same[l] = False
    return same


@njit(cache=True)
def _label_scores(s, r, alpha, ups, eps, cst2, same, indptr, indices, u, gamma, sc):
    """Score of every class for surface ``s`` (beta at its conditional mode), in ``sc``
    (K,): the reflectivity term and ``gamma`` per neighbour of that class."""
    K, L = alpha.shape
    for k in range(K):
        sc[k] = 0.0
    for l in range(L):
        rl = r[s, l]
        if same[l]:
            for k in range(K):
                sc[k] += cst2[k, l] - (alpha[k, l] + ups[k, l] + 1.0) * math.log(rl + eps[k, l])
        else:
            lr = math.log(rl)
            for k in range(K):
                a = alpha[k, l]
                sc[k] += (a - 1.0) * lr - (a + ups[k, l] + 1.0) * math.log(rl + eps[k, l])
                sc[k] += cst2[k, l]
    for j in range(indptr[s], indptr[s + 1]):
        sc[u[indices[j]]] += gamma


@njit(cache=True, parallel=_PARALLEL)
def update_labels(
    parity, colour, indptr, indices, r, beta, u, alpha, ups, eps, cst2, gamma, conf, buf
):
    """Block update of ``(u_s, beta_s)`` for the surfaces whose pixel parity is ``colour``.

    For each class k, beta_s takes its conditional mode given r_s under k,
    ``beta = (r + eps_k) / c_k`` with ``c_k = alpha_k + ups_k + 1``; the class with the
    highest complete-data posterior plus ``gamma * #(agreeing neighbours)`` wins
    (``eq:4.umax``), ties keeping the current label. With r held, the likelihood terms of
    the counts are the same for every class, so the class score is the prior part only::

        sum_l [(alpha_k - 1) log r - (r + eps_k) / beta - c_k log beta + cst_k]
          = sum_l [(alpha_k - 1) log r - c_k log(r + eps_k) + cst2_k]   at the mode of beta

    with ``cst2 = cst - c + c log c`` (:func:`label_cst`). The ``log r`` term is left
    out at wavelengths where alpha is the same for every class (it then shifts every
    score alike). This is an exact maximisation over the block, so it never lowers the
    posterior. No two surfaces of one colour are linked (links join 4-neighbour pixels
    only), so all of them are updated at once exactly (red-black order: labels cannot
    oscillate). Returns the number of labels that changed; when ``conf`` is not empty it
    receives the softmax probability of the chosen label (else see
    :func:`label_confidence`); ``buf`` (S, K) is scratch space.
    """
    S, L = r.shape
    K = alpha.shape[0]
    same = _same_alpha(alpha)
    want_conf = conf.shape[0] == S
    changed = 0
    for s in prange(S):
        if parity[s] != colour:
            continue
        _label_scores(s, r, alpha, ups, eps, cst2, same, indptr, indices, u, gamma, buf[s])
        cur = u[s]
        best = cur
        for k in range(K):
            if buf[s, k] > buf[s, best]:
                best = k
        if want_conf:
            mx = buf[s, best]
            den = 0.0
            for k in range(K):
                den += math.exp(buf[s, k] - mx)
            conf[s] = 1.0 / den
        if best != cur:
            changed += 1
        u[s] = best
        for l in range(L):
            beta[s, l] = (r[s, l] + eps[best, l]) / (alpha[best, l] + ups[best, l] + 1.0)
    return changed


@njit(cache=True, parallel=_PARALLEL)
def update_labels_lazy(
    parity, colour, indptr, indices, r, beta, u, alpha, ups, eps, cst2, gamma, buf, r_eval,
    margin, eval_at, changed_at, stamp, slope,
):  # fmt: skip
    """:func:`update_labels` (without ``conf``) that skips surfaces whose label cannot change.

    The same result, exactly: a surface is re-scored only when its last score margin
    (best minus second-best class score, ``margin``, at ``r_eval``, pass ``eval_at``) may
    have been overtaken since. Between two classes k, j the score difference moves by at
    most ``slope * sum_l |log r - log r_eval|``: ``log(r + eps_k)`` and ``log(r + eps_j)``
    move in the same direction as ``log r`` and by no more, so ``c_k d log(r + eps_k) -
    c_j d log(r + eps_j)`` is at most ``max(c_k, c_j) |d log r|`` (``c = alpha + ups +
    1``); ``slope = max_{k,j} (max(c_k, c_j) + |alpha_k - alpha_j|)``. It is bounded via
    ``|log a - log b| <= |a - b| / min(a, b)``, plus ``2 gamma`` per neighbour whose label
    changed after pass ``eval_at`` (``changed_at``). Skipped surfaces keep their label and
    beta (already the mode for it: r has not changed since the last r-beta round).
    ``stamp`` numbers this pass. Returns the number of labels that changed.
    """
    S, L = r.shape
    K = alpha.shape[0]
    same = _same_alpha(alpha)
    changed = 0
    for s in prange(S):
        if parity[s] != colour:
            continue
        if margin[s] > 0.0:
            d = 0.0
            for l in range(L):
                a = r[s, l]
                c = r_eval[s, l]
                d += abs(a - c) / min(a, c)
            bound = slope * d
            for j in range(indptr[s], indptr[s + 1]):
                if changed_at[indices[j]] > eval_at[s]:
                    bound += 2.0 * gamma
            if bound < margin[s]:
                continue
        for l in range(L):
            r_eval[s, l] = r[s, l]
        _label_scores(s, r, alpha, ups, eps, cst2, same, indptr, indices, u, gamma, buf[s])
        cur = u[s]
        best = cur
        for k in range(K):
            if buf[s, k] > buf[s, best]:
                best = k
        second = -np.inf
        for k in range(K):
            if k != best and buf[s, k] > second:
                second = buf[s, k]
        # a tie keeps the current label: only a strictly positive margin is safe to skip
        margin[s] = buf[s, best] - second
        eval_at[s] = stamp
        if best != cur:
            changed += 1
            changed_at[s] = stamp
        u[s] = best
        for l in range(L):
            beta[s, l] = (r[s, l] + eps[best, l]) / (alpha[best, l] + ups[best, l] + 1.0)
    return changed


@njit(cache=True, parallel=_PARALLEL)
def label_confidence(indptr, indices, r, u, alpha, ups, eps, cst2, gamma, conf):
    """Conditional probability of each surface's current label given r and its neighbours.

    The softmax over classes of the label score of :func:`update_labels` (beta at its
    conditional mode under each class), evaluated at the current state, in ``conf`` (S,).
    """
    S, L = r.shape
    K = alpha.shape[0]
    same = _same_alpha(alpha)
    for s in prange(S):
        sc = np.zeros(K)
        for l in range(L):
            rl = r[s, l]
            lr = 0.0 if same[l] else math.log(rl)
            for k in range(K):
                a = alpha[k, l]
                sc[k] += (a - 1.0) * lr - (a + ups[k, l] + 1.0) * math.log(rl + eps[k, l])
                sc[k] += cst2[k, l]
        for j in range(indptr[s], indptr[s + 1]):
            sc[u[indices[j]]] += gamma
        mx = sc[0]
        for k in range(1, K):
            mx = max(mx, sc[k])
        den = 0.0
        for k in range(K):
            den += math.exp(sc[k] - mx)
        conf[s] = math.exp(sc[u[s]] - mx) / den


@njit(cache=True)
def label_cst(alpha, ups, cst):
    """``cst - c + c log c`` with ``c = alpha + ups + 1`` (see :func:`update_labels`)."""
    K, L = alpha.shape
    out = np.empty((K, L))
    for k in range(K):
        for l in range(L):
            c = alpha[k, l] + ups[k, l] + 1.0
            out[k, l] = cst[k, l] - c + c * math.log(c)
    return out


@njit(cache=True, parallel=_PARALLEL)
def shape_loglik(x, logm, out):
    """``out[s, k] = sum_l max(x[s, l], 0) logm[k, l]`` (no BLAS: K, L are tiny)."""
    S, L = x.shape
    K = logm.shape[0]
    for s in prange(S):
        for k in range(K):
            acc = 0.0
            for l in range(L):
                v = x[s, l]
                if v > 0.0:
                    acc += v * logm[k, l]
            out[s, k] = acc


@njit(cache=True, parallel=_PARALLEL)
def potts_icm(score, parity, indptr, indices, gamma, n_sweeps, u):
    """Labels maximising ``score[s, u_s] + gamma * #(agreeing links)`` by red-black ICM.

    ``u`` (S,) holds the start labels and receives the result (ties keep the current
    label). Returns the sweeps done.
    """
    S, K = score.shape
    buf = np.empty((S, K))
    done = 0
    for _ in range(n_sweeps):
        changed = 0
        for colour in range(2):
            for s in prange(S):
                if parity[s] != colour:
                    continue
                for k in range(K):
                    buf[s, k] = score[s, k]
                for j in range(indptr[s], indptr[s + 1]):
                    buf[s, u[indices[j]]] += gamma
                cur = u[s]
                best = cur
                for k in range(K):
                    if buf[s, k] > buf[s, best]:
                        best = k
                if best != cur:
                    changed += 1
                u[s] = best
        done += 1
        if changed == 0:
            break
    return done


@njit(cache=True, parallel=_PARALLEL)
def update_r(z, eta, h, beta, u, alpha, r):
    """Mode of the gamma conditional of r (``eqt:Modes_Param_top`` left, EM data z)."""
    S, L = r.shape
    for s in prange(S):
        k = u[s]
        for l in range(L):
            r[s, l] = (z[s, l] + alpha[k, l] - 1.0) / (eta[s, l] * h[s] + 1.0 / beta[s, l])


@njit(cache=True, parallel=_PARALLEL)
def update_beta(r, u, alpha, ups, eps, beta):
    """Mode of the inverse-gamma conditional of beta (``eqt:Modes_Param_top`` right)."""
    S, L = r.shape
    for s in prange(S):
        k = u[s]
        for l in range(L):
            beta[s, l] = (r[s, l] + eps[k, l]) / (alpha[k, l] + ups[k, l] + 1.0)


@njit(cache=True, parallel=_PARALLEL)
def update_h(z, eta, r, w, indptr, indices, rho, h):
    """Mode of the gamma conditional of h (``eqt:Modes_Param_bottom`` left).

    ``h_s | . ~ G(sum_l z_sl + theta1 + 1, rate = sum_l eta r + theta2)`` with
    ``theta1 = rho (1 + deg_s)``, ``theta2 = rho (1/w_s + sum_{s'} 1/w_s')``.
    """
    S, L = r.shape
    for s in prange(S):
        deg = indptr[s + 1] - indptr[s]
        t1 = rho * (1.0 + deg)
        t2 = 1.0 / w[s]
        for j in range(indptr[s], indptr[s + 1]):
            t2 += 1.0 / w[indices[j]]
        t2 *= rho
        zz = 0.0
        er = 0.0
        for l in range(L):
            zz += z[s, l]
            er += eta[s, l] * r[s, l]
        h[s] = (zz + t1) / (er + t2)


@njit(cache=True, parallel=_PARALLEL)
def update_w(h, indptr, indices, w):
    """Mode of the inverse-gamma conditional of w (``eqt:Modes_Param_bottom`` right).

    ``w_s | H ~ IG(theta1 - 1, theta2)`` with ``theta1 = rho (1 + deg_s)``,
    ``theta2 = rho (h_s + sum_{s'} h_s')``: the mode is the mean of the linked h.
    """
    S = h.shape[0]
    for s in prange(S):
        deg = indptr[s + 1] - indptr[s]
        t = h[s]
        for j in range(indptr[s], indptr[s + 1]):
            t += h[indices[j]]
        w[s] = t / (1.0 + deg)


@njit(cache=True, inline="always")
def _local_one(s, y, b, eta, h, u, alpha, ups, eps, do_estep, r, beta, z, q, zs, er):
    """:func:`local_round`'s block for surface ``s`` (reads only its own entries)."""
    L = r.shape[1]
    k = u[s]
    hs = h[s]
    a_z = 0.0
    a_er = 0.0
    for l in range(L):
        if do_estep:
            sig = eta[s, l] * hs * r[s, l]
            tot = sig + b[s, l]
            qq = sig / tot if tot > 0.0 else 1.0
            q[s, l] = qq
            z[s, l] = y[s, l] * qq
        a = alpha[k, l]
        rr = (z[s, l] + a - 1.0) / (eta[s, l] * hs + 1.0 / beta[s, l])
        r[s, l] = rr
        beta[s, l] = (rr + eps[k, l]) / (a + ups[k, l] + 1.0)
        a_z += z[s, l]
        a_er += eta[s, l] * rr
    zs[s] = a_z
    er[s] = a_er


@njit(cache=True, parallel=_PARALLEL)
def local_round(y, b, eta, h, u, alpha, ups, eps, do_estep, r, beta, z, q, zs, er):
    """Per-surface blocks of one inner round, fused: [E-step,] r, then beta.

    The same as :func:`estep` (when ``do_estep``), :func:`update_r` and
    :func:`update_beta` in turn: each touches only its own surface. Also writes the
    sums the h updates of the round read, ``zs = sum_l z`` and ``er = sum_l eta r`` (S,).
    """
    for s in prange(r.shape[0]):
        _local_one(s, y, b, eta, h, u, alpha, ups, eps, do_estep, r, beta, z, q, zs, er)


@njit(cache=True, inline="always")
def _estep_store_one(s, y, b, eta, r, h, z, q, old):
    """Surface ``s`` of :func:`estep_store` (shared with :func:`estep_local`)."""
    for l in range(y.shape[1]):
        sig = eta[s, l] * h[s] * r[s, l]
        old[s, l] = h[s] * r[s, l]
        tot = sig + b[s, l]
        q[s, l] = sig / tot if tot > 0.0 else 1.0
        z[s, l] = y[s, l] * q[s, l]


@njit(cache=True, parallel=_PARALLEL)
def estep_store(y, b, eta, r, h, z, q, old):
    """:func:`estep`, and ``old = h r`` (the intensity before the sweep)."""
    for s in prange(y.shape[0]):
        _estep_store_one(s, y, b, eta, r, h, z, q, old)


@njit(cache=True, parallel=_PARALLEL)
def update_h_iw(zs, er, iw, indptr, indices, rho, h):
    """:func:`update_h` from ``zs = sum_l z``, ``er = sum_l eta r`` and ``iw = 1 / w``."""
    S = h.shape[0]
    for s in prange(S):
        deg = indptr[s + 1] - indptr[s]
        t2 = iw[s]
        for j in range(indptr[s], indptr[s + 1]):
            t2 += iw[indices[j]]
        h[s] = (zs[s] + rho * (1.0 + deg)) / (er[s] + rho * t2)


@njit(cache=True, parallel=_PARALLEL)
def update_w_iw(h, indptr, indices, w, iw):
    """:func:`update_w`, also writing ``iw = 1 / w``."""
    S = h.shape[0]
    for s in prange(S):
        deg = indptr[s + 1] - indptr[s]
        t = h[s]
        for j in range(indptr[s], indptr[s + 1]):
            t += h[indices[j]]
        ws = t / (1.0 + deg)
        w[s] = ws
        iw[s] = 1.0 / ws


@njit(cache=True)
def neighbour_table(indptr, indices):
    """The first 4 neighbours of every surface, ``(S, 4)`` int32, padded with ``S``.

    The sweeps' h and w passes read the neighbours through it from arrays with one more
    entry, 0.0, at index ``S``: ``x[s] + x[n0] + ... + x[n3]`` with the padding adding
    exactly 0.0 is the CSR loop's sum, bit for bit, in the same order (the neighbours
    past the 4th, where a neighbour pixel holds several linked surfaces, follow in
    :func:`_nb_sum`). Measured: a fixed 4-term sum instead of a loop of 2-4 trips (whose
    exit the CPU mispredicts) halves the cost of a pass (286,415 surfaces, one thread:
    2.0-2.9 -> 1.0 ms).
    """
    S = indptr.size - 1
    nb = np.full((S, 4), S, np.int32)
    for s in range(S):
        for j in range(min(indptr[s + 1] - indptr[s], 4)):
            nb[s, j] = indices[indptr[s] + j]
    return nb


@njit(cache=True, inline="always")
def _nb_sum(s, x, nb, indptr, indices):
    """``x[s]`` plus ``x`` of the neighbours of ``s`` in CSR order (``x[S] = 0``)."""
    t = x[s] + x[nb[s, 0]] + x[nb[s, 1]] + x[nb[s, 2]] + x[nb[s, 3]]
    if indptr[s + 1] - indptr[s] > 4:
        for j in range(indptr[s] + 4, indptr[s + 1]):
            t += x[indices[j]]
    return t


@njit(cache=True, inline="always")
def _w_nb(s, h, nb, indptr, indices, w, iw):
    """:func:`update_w_iw` for surface ``s`` through the neighbour table (``h[S] = 0``)."""
    ws = _nb_sum(s, h, nb, indptr, indices) / (1.0 + (indptr[s + 1] - indptr[s]))
    w[s] = ws
    iw[s] = 1.0 / ws


@njit(cache=True, parallel=_PARALLEL)
def update_h_nb(zs, er, iw, nb, indptr, indices, rho, h):
    """:func:`update_h_iw` through the neighbour table (``iw[S] = 0``, ``h`` (S + 1,))."""
    for s in prange(zs.shape[0]):
        deg = indptr[s + 1] - indptr[s]
        t2 = _nb_sum(s, iw, nb, indptr, indices)
        h[s] = (zs[s] + rho * (1.0 + deg)) / (er[s] + rho * t2)


@njit(cache=True, parallel=_PARALLEL)
def update_w_nb(h, nb, indptr, indices, w, iw):
    """:func:`update_w_iw` through the neighbour table (``h[S] = 0``)."""
    for s in prange(w.shape[0]):
        _w_nb(s, h, nb, indptr, indices, w, iw)


@njit(cache=True, parallel=_PARALLEL)
def estep_local(y, b, eta, h, u, alpha, ups, eps, r, beta, z, q, old, zs, er):
    """:func:`estep_store` then :func:`local_round` (without its E-step), in one pass.

    Both touch only the surface's own entries, so doing them surface by surface gives
    the same numbers as the two passes in turn (``old = h r`` before the update).
    """
    for s in prange(r.shape[0]):
        _estep_store_one(s, y, b, eta, r, h, z, q, old)
        _local_one(s, y, b, eta, h, u, alpha, ups, eps, False, r, beta, z, q, zs, er)


@njit(cache=True, parallel=_PARALLEL)
def w_local(h, nb, indptr, indices, w, iw, y, b, eta, u, alpha, ups, eps, r, beta, z, q, zs, er):
    """:func:`update_w_iw` then :func:`local_round` (with its E-step), in one pass.

    The w update reads ``h`` (its neighbours') and writes ``w, iw``; the local round
    reads its own ``h`` and writes the per-surface arrays; neither writes what the other
    reads, so surface by surface gives the same numbers as the two passes in turn.
    """
    for s in prange(w.shape[0]):
        _w_nb(s, h, nb, indptr, indices, w, iw)
        _local_one(s, y, b, eta, h, u, alpha, ups, eps, True, r, beta, z, q, zs, er)


@njit(cache=True, parallel=_PARALLEL)
def w_rms(h, nb, indptr, indices, w, iw, r, old):
    """:func:`update_w_iw` and :func:`_rms_change` in one pass (returns the change)."""
    S, L = r.shape
    num = 0.0
    den = 0.0
    for s in prange(S):
        _w_nb(s, h, nb, indptr, indices, w, iw)
        for l in range(L):
            v = h[s] * r[s, l]
            num += (v - old[s, l]) ** 2
            den += old[s, l] ** 2
    return math.sqrt(num / max(den, 1e-300))


@njit(cache=True, parallel=_PARALLEL)
def neighbour_mean(h, indptr, indices, out):
    """Mean ``h`` of each surface's neighbours, in CSR order from 0.0 (0 without links):
    the numbers of ``np.bincount`` over the links divided by ``max(deg, 1)``."""
    for s in prange(out.shape[0]):
        t = 0.0
        for j in range(indptr[s], indptr[s + 1]):
            t += h[indices[j]]
        out[s] = t / max(indptr[s + 1] - indptr[s], 1)


@njit(cache=True, parallel=_PARALLEL)
def _log_of(x, out):
    for s in prange(x.shape[0]):
        out[s] = math.log(x[s])


@njit(cache=True, parallel=_PARALLEL)
def objective_change(
    y, b, eta, r, beta, h, lw, iw, u, indptr, indices, alpha, ups, eps, cst, rho, gamma, old
):
    """:func:`objective` from ``lw = log w`` and ``iw = 1 / w``, and the RMS change of
    ``h r`` against ``old`` relative to the RMS of ``old`` (:func:`_rms_change`)."""
    S, L = r.shape
    tot = 0.0
    num = 0.0
    den = 0.0
    for s in prange(S):
        k = u[s]
        part = 0.0
        hs = h[s]
        for l in range(L):
            rl = r[s, l]
            v = hs * rl
            num += (v - old[s, l]) ** 2
            den += old[s, l] ** 2
            lam = eta[s, l] * v + b[s, l]
            if y[s, l] > 0.0:
                part += y[s, l] * math.log(lam)
            part -= lam
            a = alpha[k, l]
            bt = beta[s, l]
            part += (
                (a - 1.0) * math.log(rl)
                - (rl + eps[k, l]) / bt
                - (a + ups[k, l] + 1.0) * math.log(bt)
                + cst[k, l]
            )
        deg = indptr[s + 1] - indptr[s]
        acc_lw = lw[s]
        acc_iw = iw[s]
        for j in range(indptr[s], indptr[s + 1]):
            t = indices[j]
            acc_lw += lw[t]
            acc_iw += iw[t]
            if t > s and u[t] == k:
                part += gamma
        part += rho * ((1.0 + deg) * math.log(hs) - acc_lw - hs * acc_iw)
        tot += part
    return tot, math.sqrt(num / max(den, 1e-300))


@njit(cache=True, parallel=_PARALLEL)
def objective(y, b, eta, r, beta, h, w, u, indptr, indices, alpha, ups, eps, cst, rho, gamma):
    """Log posterior up to a constant (``eqt:Posterior``), background marginalised.

    Terms: Poisson likelihood of the raw counts ``y ~ P(eta h r + b)``; gamma prior of r;
    inverse-gamma prior of beta; gamma-MRF ``sum_edges rho (log h - log w - h / w)`` (own
    and neighbour links); Potts ``gamma * #(agreeing unordered links)``.
    """
    S, L = r.shape
    tot = 0.0
    for s in prange(S):
        k = u[s]
        part = 0.0
        for l in range(L):
            lam = eta[s, l] * h[s] * r[s, l] + b[s, l]
            if y[s, l] > 0.0:
                part += y[s, l] * math.log(lam)
            part -= lam
            a = alpha[k, l]
            v = ups[k, l]
            e = eps[k, l]
            bt = beta[s, l]
            lb = math.log(bt)
            rl = r[s, l]
            part += (a - 1.0) * math.log(rl) - (rl + e) / bt - (a + v + 1.0) * lb + cst[k, l]
        hs = h[s]
        deg = indptr[s + 1] - indptr[s]
        # own link h_s - w_s, then the neighbour links
        acc_lw = math.log(w[s])
        acc_iw = 1.0 / w[s]
        for j in range(indptr[s], indptr[s + 1]):
            t = indices[j]
            acc_lw += math.log(w[t])
            acc_iw += 1.0 / w[t]
            if t > s and u[t] == k:
                part += gamma
        part += rho * ((1.0 + deg) * math.log(hs) - acc_lw - hs * acc_iw)
        tot += part
    return tot


@njit(cache=True, parallel=_PARALLEL)
def _rms_change(h, r, old):
    """RMS change of ``h r`` against ``old`` relative to the RMS of ``old``."""
    S, L = r.shape
    num = 0.0
    den = 0.0
    for s in prange(S):
        for l in range(L):
            v = h[s] * r[s, l]
            num += (v - old[s, l]) ** 2
            den += old[s, l] ** 2
    return math.sqrt(num / max(den, 1e-300))


@njit(cache=True)
def _inner_rounds(
    y, b, eta, h, u, alpha, ups, eps, r, beta, z, q, zs, er, w, iw, old, nb, indptr, indices,
    rho, n_inner, n_hw,
):  # fmt: skip
    """The ``n_inner`` rounds of a sweep after its first local round: [``n_hw`` passes of
    (h, w), then the next round's local round]; returns the RMS change of ``h r`` against
    ``old``. ``h`` and ``iw`` have one more entry, 0.0 (:func:`neighbour_table`). A w
    pass and the local round after it are one pass (:func:`w_local`), as are the last w
    pass and the change (:func:`w_rms`): the same numbers as :func:`local_round`,
    :func:`update_h_iw`, :func:`update_w_iw` and :func:`_rms_change` in turn.
    """
    for i in range(n_inner):
        last = i == n_inner - 1
        for p in range(n_hw):
            update_h_nb(zs, er, iw, nb, indptr, indices, rho, h)
            if p < n_hw - 1:
                update_w_nb(h, nb, indptr, indices, w, iw)
            elif last:
                return w_rms(h, nb, indptr, indices, w, iw, r, old)
            else:
                w_local(
                    h, nb, indptr, indices, w, iw, y, b, eta, u, alpha, ups, eps, r, beta, z,
                    q, zs, er,
                )  # fmt: skip
        if n_hw == 0 and not last:
            local_round(y, b, eta, h, u, alpha, ups, eps, True, r, beta, z, q, zs, er)
    return _rms_change(h, r, old)


@njit(cache=True)
def run(
    y,
    b,
    eta,
    parity,
    indptr,
    indices,
    alpha,
    ups,
    eps,
    rho,
    gamma,
    max_iter,
    tol,
    update_classes,
    r,
    beta,
    h,
    w,
    u,
    conf,
    z,
    q,
    obj_out,
    change_out,
    label_out,
    n_inner=1,
    n_hw=1,
    label_tol=0,
    obj_every=1,
):
    """Coordinate descent (Algorithm 2): returns the number of sweeps done.

    One sweep: E-step (split y into signal and background), labels with their beta (red
    then black pixels, :func:`update_labels_lazy`: exactly :func:`update_labels`'s
    result, scoring only the surfaces whose label may change), then ``n_inner`` rounds of
    [r, beta, ``n_hw`` passes of (h, w), E-step] (:func:`local_round`,
    :func:`update_h_iw`, :func:`update_w_iw`). Every step maximises the complete-data
    posterior in its block (the E-step is EM's), so the marginal log posterior never
    decreases (generalised EM).
    ``obj_out[0]`` holds the start value, ``obj_out[i]`` the value after sweep i;
    ``change_out[i-1]`` is the RMS change of the intensity ``h r`` relative to its RMS and
    ``label_out[i-1]`` the number of labels changed at sweep i. Stops when that change is
    below ``tol`` and at most ``label_tol`` labels changed. The objective is evaluated
    after every ``obj_every``-th sweep and after the last one (NaN in between: it costs
    about a fifth of a sweep and only documents the ascent). ``conf`` (S,) receives the
    conditional probability of each label at the end when ``update_classes`` (else it is
    left as it is).
    """
    S, L = y.shape
    cst = class_cst(alpha, ups, eps)
    cst2 = label_cst(alpha, ups, cst)
    buf = np.empty((S, alpha.shape[0]))
    # h and 1 / w with one more entry, 0.0, for the h and w passes' neighbour table
    nb = neighbour_table(indptr, indices)
    hx = np.empty(S + 1)
    hx[S] = 0.0
    iw = np.empty(S + 1)
    iw[S] = 0.0
    for s in range(S):
        hx[s] = h[s]
        iw[s] = 1.0 / w[s]
    lw = np.empty(S)
    _log_of(w, lw)
    old = np.empty((S, L))
    zs = np.empty(S)
    er = np.empty(S)
    # lazy label updates (update_labels_lazy): state of the last scoring of each surface
    K = alpha.shape[0]
    r_eval = np.empty((S, L))
    margin = np.full(S, -1.0)
    eval_at = np.zeros(S, np.int64)
    changed_at = np.zeros(S, np.int64)
    slope = 0.0
    for k in range(K):
        for j in range(K):
            for l in range(L):
                sl = max(alpha[k, l] + ups[k, l], alpha[j, l] + ups[j, l]) + 1.0
                sl += abs(alpha[k, l] - alpha[j, l])
                slope = max(slope, sl)
    stamp = 0
    obj_out[0], _ = objective_change(
        y, b, eta, r, beta, hx, lw, iw, u, indptr, indices, alpha, ups, eps, cst, rho, gamma,
        old,
    )  # fmt: skip
    n_iter = 0
    for it in range(max_iter):
        changed = 0
        if update_classes:
            estep_store(y, b, eta, r, hx, z, q, old)
            for colour in range(2):
                stamp += 1
                changed += update_labels_lazy(
                    parity, colour, indptr, indices, r, beta, u, alpha, ups, eps, cst2, gamma,
                    buf, r_eval, margin, eval_at, changed_at, stamp, slope,
                )  # fmt: skip
            if n_inner > 0:
                local_round(y, b, eta, hx, u, alpha, ups, eps, False, r, beta, z, q, zs, er)
        elif n_inner > 0:  # the E-step and the first local round, one pass
            estep_local(y, b, eta, hx, u, alpha, ups, eps, r, beta, z, q, old, zs, er)
        else:
            estep_store(y, b, eta, r, hx, z, q, old)
        ch = _inner_rounds(
            y, b, eta, hx, u, alpha, ups, eps, r, beta, z, q, zs, er, w, iw, old, nb, indptr,
            indices, rho, n_inner, n_hw,
        )  # fmt: skip
        n_iter = it + 1
        done = (ch < tol and changed <= label_tol) or n_iter == max_iter
        if done or n_iter % obj_every == 0:
            _log_of(w, lw)
            obj_out[n_iter], _ = objective_change(
                y, b, eta, r, beta, hx, lw, iw, u, indptr, indices, alpha, ups, eps, cst, rho,
                gamma, old,
            )  # fmt: skip
        else:
            obj_out[n_iter] = np.nan
        change_out[it] = ch
        label_out[it] = changed
        if done:
            break
    for s in range(S):
        h[s] = hx[s]
    if update_classes:
        label_confidence(indptr, indices, r, u, alpha, ups, eps, cst2, gamma, conf)
    return n_iter


@njit(cache=True, parallel=_PARALLEL)
def posterior(
    y, eta, z, q, r, beta, h, w, u, alpha, ups, eps, indptr, indices, rho, marginal, var_h_ext,
    inten, std,
):  # fmt: skip
    """Intensity ``h r`` and its posterior std (see ``reconstruct``'s notes), in place.

    ``marginal=True``: r given (h, z), with beta integrated out exactly (the inverse
    gamma is conjugate)::

        log p(r | h, z) = (z + alpha - 1) log r - eta h r - (alpha + upsilon) log(r + eps)

    Its variance is taken from the curvature at r (Laplace), ``1 / c`` with
    ``c = (z + alpha - 1) / r**2 - (alpha + upsilon) / (r + eps)**2`` (> 0 at the joint
    mode, see below); the unknown signal/background split ``z ~ Bin(y, q)`` adds
    ``(dr/dz)**2 Var z`` with ``dr/dz = 1 / (r c)`` (law of total variance). The
    uncertainty of h is carried by the delta method from its gamma conditional
    ``G(sum_l z + rho (1 + deg) + 1, sum_l eta r + rho (1/w_s + sum 1/w_s'))``
    (``eqt:Modes_Param_bottom``) with ``dI / dh = r + h dr/dh = r - h eta / c`` (r
    follows h through its mode). ``c > 0``: at the joint mode ``(z + alpha - 1) / r =
    eta h + (alpha + upsilon + 1) / (r + eps)``, so ``(z + alpha - 1) / r**2 > (alpha +
    upsilon) / (r (r + eps)) > (alpha + upsilon) / (r + eps)**2``.

    ``marginal=False``: beta held at its mode, ``r | h, beta`` a mixture over z of
    ``G(z + alpha, rate eta h + 1/beta)``: variance ``(E z + alpha + Var z) / rate**2``,
    ``dI / dh = (z + alpha) / beta / rate**2``. This drops the part of the prior's spread
    that beta carries (half of it under ``alpha="auto"``, where it under-covered scenes
    with spectral variability).

    ``var_h_ext`` (S,): when not empty, used as ``Var(h)`` instead of the conditional
    variance (``_core._h_variance_eb``).
    """
    S, L = r.shape
    ext = var_h_ext.shape[0] == S
    for s in prange(S):
        deg = indptr[s + 1] - indptr[s]
        t2 = 1.0 / w[s]
        for j in range(indptr[s], indptr[s + 1]):
            t2 += 1.0 / w[indices[j]]
        zz = 0.0
        er = 0.0
        for l in range(L):
            zz += z[s, l]
            er += eta[s, l] * r[s, l]
        a_h = zz + rho * (1.0 + deg) + 1.0
        b_h = er + rho * t2
        var_h = var_h_ext[s] if ext else a_h / (b_h * b_h)
        hs = h[s]
        k = u[s]
        for l in range(L):
            rl = r[s, l]
            a = alpha[k, l]
            inten[s, l] = hs * rl
            if not marginal:
                rate = eta[s, l] * hs + 1.0 / beta[s, l]
                shape = z[s, l] + a
                var = hs * hs * (shape + y[s, l] * q[s, l] * (1.0 - q[s, l])) / (rate * rate)
                d_i = shape / beta[s, l] / (rate * rate)
                std[s, l] = math.sqrt(var + d_i * d_i * var_h)
                continue
            re = rl + eps[k, l]
            c = (z[s, l] + a - 1.0) / (rl * rl) - (a + ups[k, l]) / (re * re)
            c = max(c, 1e-300)
            dz = 1.0 / (rl * c)
            var_r = 1.0 / c + dz * dz * y[s, l] * q[s, l] * (1.0 - q[s, l])
            d_i = rl - hs * eta[s, l] / c
            std[s, l] = math.sqrt(hs * hs * var_r + d_i * d_i * var_h)


@njit(cache=True)
def thin_half(y, seed, out):
    """``out ~ Binomial(y, 1/2)`` element-wise (binomial thinning of counts): the number
    of set bits among ``y`` fair random bits, 30 per draw of numba's generator seeded
    with ``seed`` (serial: one reproducible stream; 4x faster than its binomial)."""
    np.random.seed(seed)  # noqa: NPY002 (numba's own generator, seeded from rng)
    for i in range(y.size):
        n = y[i]
        c = 0
        while n > 0:
            m = min(n, 30)
            x = np.random.randint(0, 1 << 30) & ((1 << m) - 1)  # noqa: NPY002
            while x:
                x &= x - 1
                c += 1
            n -= m
        out[i] = c


@njit(cache=True, parallel=_PARALLEL)
def label_spread(y, b, eta, h, r, u, u_alt, alpha, ups, eps, sig, out):
    """``out[s, l] = mean_j (h_s (r_{k_j, l} - r_{s, l}))**2`` over the labels
    ``k_j = u_alt[j, s]`` (0 where ``k_j = u_s``).

    ``r_k`` is the joint mode of (r, beta) and the EM split under class k at ``h_s``:
    five rounds of ``z = y q``, ``r = (z + alpha - 1)_+ / (eta h + 1 / beta)``, ``beta =
    (r + eps) / (alpha + upsilon + 1)`` from the class's signature (the rounds of
    ``reconstruct`` with h held).
    """
    S, L = y.shape
    n = u_alt.shape[0]
    for s in prange(S):
        for j in range(n):
            k = u_alt[j, s]
            if k == u[s]:
                continue
            for l in range(L):
                a = alpha[k, l]
                e = eps[k, l]
                c = a + ups[k, l] + 1.0
                eh = eta[s, l] * h[s]
                rk = sig[k, l]
                beta = (rk + e) / c
                for _ in range(5):
                    lam = eh * rk
                    tot = lam + b[s, l]
                    zk = y[s, l] * lam / tot if tot > 0.0 else y[s, l]
                    rk = max(zk + a - 1.0, 0.0) / (eh + 1.0 / beta)
                    beta = (rk + e) / c
                d = h[s] * (rk - r[s, l])
                out[s, l] += d * d / n


@njit(cache=True, parallel=_PARALLEL)
def dispersion_sums(y, b, eta, h, u, sig, v, num, den):
    """Per-class sums of the weighted moment estimator of the reflectivity dispersion.

    Under the prior, ``y_{s,l}`` has mean ``mu = lam + b`` with ``lam = eta h m_{u_s,l}``
    and variance ``mu + v lam**2`` (Poisson noise plus a reflectivity of relative variance
    ``v = CV**2`` about its signature), so ``e = (y - mu)**2 - y`` is an unbiased
    estimate of ``v lam**2`` (of ``(E y - mu)**2`` in general: ``E (y - mu)**2 = E y +
    (E y - mu)**2`` for a Poisson y and any mu not made from y). Each term is weighted by
    the inverse of its approximate variance, ``2 (mu + v lam**2)**2``: ``num_k += lam**2 e
    / (mu + v lam**2)**2``, ``den_k += lam**4 / (mu + v lam**2)**2`` (``v_k = num_k /
    den_k``). ``v`` (K,) is the current estimate, ``num``, ``den`` (K,) are overwritten.
    """
    S, L = y.shape
    K = sig.shape[0]
    nt = 64
    part_n = np.zeros((nt, K))
    part_d = np.zeros((nt, K))
    chunk = (S + nt - 1) // nt
    for c in prange(nt):
        for s in range(c * chunk, min(S, (c + 1) * chunk)):
            k = u[s]
            for l in range(L):
                lam = eta[s, l] * h[s] * sig[k, l]
                if not lam > 0.0:
                    continue
                mu = lam + b[s, l]
                dev = y[s, l] - mu
                # the count itself estimates its Poisson variance without bias whatever
                # the model's mean: ``- mu`` would add ``E y - mu`` (a first-order bias,
                # large against ``v lam**2`` at low counts when the signatures misfit)
                e = dev * dev - y[s, l]
                l2 = lam * lam
                vv = mu + v[k] * l2
                wgt = l2 / (vv * vv)
                part_n[c, k] += wgt * e
                part_d[c, k] += wgt * l2
    for k in range(K):
        num[k] = 0.0
        den[k] = 0.0
        for c in range(nt):
            num[k] += part_n[c, k]
            den[k] += part_d[c, k]
