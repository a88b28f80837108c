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
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _lgamma(x):
    return math.lgamma(x)


@njit(cache=True)
def estep(y, b, eta, r, h, z, q):
    """EM split of the counts: ``z = y * q``, ``q = eta h r / (eta h r + b)``."""
    S, L = y.shape
    for s in range(S):
        for l in range(L):
            sig = eta[s, l] * h[s] * r[s, l]
            tot = sig + b[s, l]
            if tot > 0.0:
                q[s, l] = sig / tot
            else:
                q[s, l] = 1.0
            z[s, l] = y[s, l] * q[s, l]


@njit(cache=True)
def block_score(s, k, z, eta, h, alpha, ups, eps, cst, r0, lr0, n_inner, r_out, beta_out):
    """Best (r_s, beta_s) under class k and its complete-data log posterior terms.

    Starts from ``r0`` (``lr0 = log r0``), sets beta to its conditional mode, then
    alternates the exact conditional modes of r and beta ``n_inner`` times (each step
    increases the value; ``reconstruct`` uses 0: beta profiled out, r kept). Returns
    ``sum_l [z log(r) - eta h r + log G(r; alpha_k, beta) + log IG(beta; ups_k, eps_k)]``,
    the block's complete-data posterior up to terms common to all classes.
    """
    L = z.shape[1]
    tot = 0.0
    hs = h[s]
    for l in range(L):
        a = alpha[k, l]
        v = ups[k, l]
        e = eps[k, l]
        rl = r0[l]
        lr = lr0[l]
        lam = eta[s, l] * hs
        bt = (rl + e) / (a + v + 1.0)
        for _ in range(n_inner):
            rl = (z[s, l] + a - 1.0) / (lam + 1.0 / bt)
            bt = (rl + e) / (a + v + 1.0)
            lr = math.log(rl)
        r_out[l] = rl
        beta_out[l] = bt
        lb = math.log(bt)
        # z log(eta h) is the same for every class: left out
        tot += z[s, l] * lr - lam * rl
        # log G(r; a, scale bt) (eq:4.4) + log IG(bt; v, e) (eq:4.3); cst holds
        # -lgamma(a) + v log(e) - lgamma(v)
        tot += (a - 1.0) * lr - (rl + e) / bt - (a + v + 1.0) * lb + cst[k, l]
    return tot


@njit(cache=True)
def update_labels(
    parity,
    colour,
    indptr,
    indices,
    z,
    eta,
    h,
    r,
    beta,
    u,
    alpha,
    ups,
    eps,
    cst,
    gamma,
    n_inner,
    conf,
):
    """Block update of ``(u_s, beta_s)`` for the surfaces whose pixel parity is ``colour``.

    For each class k, beta_s takes its conditional mode given r_s under k (see
    :func:`block_score`; with ``n_inner > 0`` r_s is refined too); the class with the
    highest complete-data posterior plus ``gamma * #(agreeing neighbours)`` wins
    (``eq:4.umax``), ties keeping the current label. This is an exact maximisation over
    the block, so it never lowers the posterior. No two surfaces of one colour are
    linked (links join 4-neighbour pixels only), so all of them are updated at once
    exactly (red-black order: labels cannot oscillate). Returns the number of labels
    that changed; ``conf`` receives the softmax probability of the chosen label.
    """
    S, L = r.shape
    K = alpha.shape[0]
    scores = np.empty(K)
    rk = np.empty((K, L))
    bk = np.empty((K, L))
    r0 = np.empty(L)
    lr0 = np.empty(L)
    rt = np.empty(L)
    bt = np.empty(L)
    changed = 0
    for s in range(S):
        if parity[s] != colour:
            continue
        for l in range(L):
            r0[l] = r[s, l]
            lr0[l] = math.log(r0[l])
        for k in range(K):
            scores[k] = block_score(s, k, z, eta, h, alpha, ups, eps, cst, r0, lr0, n_inner, rt, bt)
            for l in range(L):
                rk[k, l] = rt[l]
                bk[k, l] = bt[l]
        for j in range(indptr[s], indptr[s + 1]):
            scores[u[indices[j]]] += gamma
        best = u[s]
        for k in range(K):
            if scores[k] > scores[best]:
                best = k
        mx = scores[best]
        den = 0.0
        for k in range(K):
            den += math.exp(scores[k] - mx)
        conf[s] = 1.0 / den
        if best != u[s]:
            changed += 1
        u[s] = best
        for l in range(L):
            r[s, l] = rk[best, l]
            beta[s, l] = bk[best, l]
    return changed


@njit(cache=True)
def update_r(z, eta, h, beta, u, alpha, r):
    """Mode of the gamma conditional of r (``eqt:Modes_Param_top`` left, EM data z)."""
    S, L = r.shape
    for s in range(S):
        k = u[s]
        for l in range(L):
            r[s, l] = (z[s, l] + alpha[k, l] - 1.0) / (eta[s, l] * h[s] + 1.0 / beta[s, l])


@njit(cache=True)
def update_beta(r, u, alpha, ups, eps, beta):
    """Mode of the inverse-gamma conditional of beta (``eqt:Modes_Param_top`` right)."""
    S, L = r.shape
    for s in range(S):
        k = u[s]
        for l in range(L):
            beta[s, l] = (r[s, l] + eps[k, l]) / (alpha[k, l] + ups[k, l] + 1.0)


@njit(cache=True)
def update_h(z, eta, r, w, indptr, indices, rho, h):
    """Mode of the gamma conditional of h (``eqt:Modes_Param_bottom`` left).

    ``h_s | . ~ G(sum_l z_sl + theta1 + 1, rate = sum_l eta r + theta2)`` with
    ``theta1 = rho (1 + deg_s)``, ``theta2 = rho (1/w_s + sum_{s'} 1/w_s')``.
    """
    S, L = r.shape
    inv_w = 1.0 / w
    for s in range(S):
        deg = indptr[s + 1] - indptr[s]
        t1 = rho * (1.0 + deg)
        t2 = inv_w[s]
        for j in range(indptr[s], indptr[s + 1]):
            t2 += inv_w[indices[j]]
        t2 *= rho
        zz = 0.0
        er = 0.0
        for l in range(L):
            zz += z[s, l]
            er += eta[s, l] * r[s, l]
        h[s] = (zz + t1) / (er + t2)


@njit(cache=True)
def update_w(h, indptr, indices, w):
    """Mode of the inverse-gamma conditional of w (``eqt:Modes_Param_bottom`` right).

    ``w_s | H ~ IG(theta1 - 1, theta2)`` with ``theta1 = rho (1 + deg_s)``,
    ``theta2 = rho (h_s + sum_{s'} h_s')``: the mode is the mean of the linked h.
    """
    S = h.shape[0]
    for s in range(S):
        deg = indptr[s + 1] - indptr[s]
        t = h[s]
        for j in range(indptr[s], indptr[s + 1]):
            t += h[indices[j]]
        w[s] = t / (1.0 + deg)


@njit(cache=True)
def objective(y, b, eta, r, beta, h, w, u, indptr, indices, alpha, ups, eps, cst, rho, gamma):
    """Log posterior up to a constant (``eqt:Posterior``), background marginalised.

    Terms: Poisson likelihood of the raw counts ``y ~ P(eta h r + b)``; gamma prior of r;
    inverse-gamma prior of beta; gamma-MRF ``sum_edges rho (log h - log w - h / w)`` (own
    and neighbour links); Potts ``gamma * #(agreeing unordered links)``.
    """
    S, L = r.shape
    log_w = np.log(w)
    inv_w = 1.0 / w
    tot = 0.0
    for s in range(S):
        k = u[s]
        for l in range(L):
            lam = eta[s, l] * h[s] * r[s, l] + b[s, l]
            if y[s, l] > 0.0:
                tot += y[s, l] * math.log(lam)
            tot -= lam
            a = alpha[k, l]
            v = ups[k, l]
            e = eps[k, l]
            bt = beta[s, l]
            lb = math.log(bt)
            rl = r[s, l]
            tot += (a - 1.0) * math.log(rl) - (rl + e) / bt - (a + v + 1.0) * lb + cst[k, l]
        hs = h[s]
        deg = indptr[s + 1] - indptr[s]
        # own link h_s - w_s, then the neighbour links
        acc_lw = log_w[s]
        acc_iw = inv_w[s]
        for j in range(indptr[s], indptr[s + 1]):
            t = indices[j]
            acc_lw += log_w[t]
            acc_iw += inv_w[t]
            if t > s and u[t] == k:
                tot += gamma
        tot += rho * ((1.0 + deg) * math.log(hs) - acc_lw - hs * acc_iw)
    return tot


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
    n_inner,
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
    n_hw=1,
):
    """Coordinate descent (Algorithm 2): returns the number of sweeps done.

    One sweep: E-step (split y into signal and background), labels with their beta
    (red then black pixels), r, beta, then ``n_hw`` passes of h, w. Every step
    maximises the complete-data posterior in its block, so the marginal log posterior
    never decreases (generalised EM). ``obj_out[0]`` holds the start value,
    ``obj_out[i]`` the value after sweep i.
    ``change_out[i-1]`` is the RMS change of the intensity ``h r`` relative to its RMS.
    """
    S, L = y.shape
    K = alpha.shape[0]
    cst = np.empty((K, L))
    for k in range(K):
        for l in range(L):
            a = alpha[k, l]
            v = ups[k, l]
            cst[k, l] = -_lgamma(a) + v * math.log(eps[k, l]) - _lgamma(v)
    obj_out[0] = objective(
        y, b, eta, r, beta, h, w, u, indptr, indices, alpha, ups, eps, cst, rho, gamma
    )
    old = np.empty((S, L))
    n_iter = 0
    for it in range(max_iter):
        for s in range(S):
            for l in range(L):
                old[s, l] = h[s] * r[s, l]
        estep(y, b, eta, r, h, z, q)
        changed = 0
        if update_classes:
            for colour in range(2):
                changed += update_labels(
                    parity, colour, indptr, indices, z, eta, h, r, beta, u, alpha, ups, eps,
                    cst, gamma, n_inner, conf,
                )  # fmt: skip
        update_r(z, eta, h, beta, u, alpha, r)
        update_beta(r, u, alpha, ups, eps, beta)
        # the gamma-MRF couples h and w strongly when rho is large: a few h-w passes per
        # sweep (each an exact block maximisation, cheap) speed up convergence
        for _ in range(n_hw):
            update_h(z, eta, r, w, indptr, indices, rho, h)
            update_w(h, indptr, indices, w)
        n_iter = it + 1
        obj_out[n_iter] = objective(
            y, b, eta, r, beta, h, w, u, indptr, indices, alpha, ups, eps, cst, rho, gamma
        )
        num = 0.0
        den = 0.0
        for s in range(S):
            for l in range(L):
                v = h[s] * r[s, l]
                num += (v - old[s, l]) ** 2
                den += old[s, l] ** 2
        ch = math.sqrt(num / max(den, 1e-300))
        change_out[it] = ch
        if ch < tol and changed == 0:
            break
    return n_iter
