r"""Spectral classification of detected surfaces from their photon counts (issue 14).

Three steps, each a function here, run by :func:`classify_surfaces` (and so by
:func:`splidar.reconstruct` before the intensities are estimated):

1. **Class likelihood from the counts** (:func:`class_loglik`). For surface s with
   own-pixel counts ``y_l`` over its support, expected background ``b_l`` and IRF fraction
   ``eta_l`` (wavelength l), and class k of signature shape ``c_{k,l}``::

       y_l | a, r, k ~ Poisson(a eta_l r_l + b_l)             a: the surface's brightness
       r_l | k       ~ Gamma(alpha_k, scale c_{k,l} / alpha_k) spectral variability, eq:4.4
       a             ~ Gamma(a0, rate a0 / abar)             one prior for every class

   Integrating ``r_l`` out gives, without background, a negative binomial of mean
   ``lam_l = a eta_l c_{k,l}`` and variance ``lam_l + lam_l**2 / alpha_k`` (over the
   wavelengths, given ``a``, a Dirichlet-multinomial of the colour times a negative
   binomial of the total). The background is added by matching the first two moments:
   ``y_l | a`` is taken as a negative binomial of mean ``mu_l = lam_l + b_l`` and variance
   ``mu_l + lam_l**2 / alpha_k``, i.e. size ``phi_l = alpha_k mu_l**2 / lam_l**2``
   (exact at ``b = 0``, Poisson as ``alpha -> inf`` or ``lam -> 0``). Then ``a`` is
   integrated numerically (a 16-point grid in ``log a`` about the data's estimate,
   trapezoid rule)::

       log p(y | k) = log int Gamma(a; a0, a0 / abar) prod_l NB(y_l; mu_l(a), phi_l(a)) da

   This is the evidence of the photons themselves: a surface of 1 photon gives a
   likelihood ratio of about one photon's colour ratio between classes, not the ratio of a
   noisy intensity estimate treated as exact (the former per-point score, whose log-odds
   grew with the estimate's noise).

2. **Class proportions** ``pi_k`` by EM (:func:`em_proportions`): ``pi_k`` = mean
   posterior of class k. In :func:`classify_surfaces` the posteriors are the spatial
   marginals of step 3, so a rare material keeps its share and a majority is not invented.

3. **Spatial pooling** (:func:`potts_marginals`): the label field is a Potts model over
   the depth-gated surface graph, ``log p(u) = sum_s log p(y_s | u_s) - sum_links
   gamma_sj [u_s != u_j]``, and the label marginals are estimated by sampling. Each sweep
   is a Swendsen-Wang move (links between equal labels are bonded with probability
   ``1 - exp(-gamma_sj)``, and each bonded cluster takes a new label drawn from the sum
   of its members' log-likelihoods plus ``log pi`` once per cluster: a cluster is one
   draw from the class proportions) followed by a heat-bath sweep of single surfaces
   (red then black pixels). A region of one material is thus relabelled as a whole on
   the evidence of all its photons (hundreds at PPP 1), which single-site updates (ICM,
   mean field) cannot do from a wrong start; the heat-bath sweep moves the surfaces on
   region boundaries, which SW rarely cuts loose. Two independent chains, each of 12
   sweeps discarded and 12 kept, are pooled (random numbers: a counter-based hash of
   (seed, sweep, key), so the result does not depend on the number of threads; since
   session 21 the key is what is drawn for, not its index in the arrays: a surface's
   pixel and rank by depth there, a link's two surfaces, a cluster's smallest surface
   key, so that adding or removing a surface changes the random numbers at that place
   only and the labels far from it stay as they were). One
   chain of 15 + 30 sweeps (the first version) gave the same labels but over-confident
   marginals on finely textured scenes (Art: ECE 0.10-0.16): once settled, a chain
   rarely relabels a whole patch, so it reports one labelling of the patches as
   certain; separate chains settle differently where the data leave it open. Three
   chains of 8 + 8 (sessions 7-10) had not converged at low counts: chains that start
   from the per-surface labels (right for a fifth of Art's surfaces at PPP 4) need
   about 12 sweeps to coarsen, and short chains ending in different labellings of
   the same objects made the pooled marginals under-confident where the field fits
   (session 11). A surface's label is its most probable marginal class and
   ``label_confidence`` that marginal probability.

   Two refinements of the field (session 8, ``docs/classification.md``):

   * **Contrast-weighted links** (:func:`link_contrast`): a link's strength is
     multiplied by ``w_sj = min(1, exp(D_sj + 2 gamma))``, where ``D_sj = max_k (A_k +
     B_k) - max_k A_k - max_k B_k <= 0`` and ``A`` (``B``) is the class log-likelihood
     summed over s (j) and its two neighbours beside the link: the photons of 2 x 3
     surfaces must favour two different classes by more than the ``2 gamma`` nats a
     one-pixel strand pays for its two cross links before the link weakens. A strand
     whose own evidence is strong survives; weak evidence (low counts, the inside of a
     region) leaves the links at full strength, so pooling is unchanged.
   * **Chains spread over the strength** (:func:`chain_gammas`, ``spread=True``; the
     default of sessions 8-10, off since session 11): the chains run at strengths
     evenly spread over ``[log(1 + sqrt(K)), 2 gamma - log(1 + sqrt(K))]``, their
     marginals pooled with equal weights. Those are the prior's weights on the
     strength; the lowest chain sits at the critical point of the Potts model, where
     the marginals stay spread however clear the regions, so where the field fits the
     scene (``art_objects``, the multispectral scenes) the pooled confidence was too
     low, and where it does not (Art's k-means classes) the spread hid an
     over-confidence that chains at any single strength in the range show once they
     have converged (``docs/classification.md``, "Calibration where the field fits").

   And two of session 10: the marginals average the conditional probabilities of the
   heat-bath draws (Rao-Blackwellised: the same expectation, a smaller Monte Carlo
   error), and ``reconstruct`` runs the field on a graph that also links the two ends of
   a strand broken by a missed detection (``build_graph(bridge=True)``; the heat-bath
   sweep then visits 4 colours, ``(row + col) % 4``).

The interaction strength follows a rule that does not depend on the scene (:func:`link_gamma`):
``gamma = 1.5`` nats per link between two surfaces of 4 links each, scaled so that a
surface's links weigh about ``4 gamma`` in all whatever their number (a strand of a net
in front, linked only along itself, is pooled as strongly as a surface of a region).
Why 1.5 (``docs/classification.md``): above the ordering threshold of the K-state Potts
model on the 4-neighbour lattice (``log(1 + sqrt(K))``, 1.0-1.1 for K = 3-4), so that a
region of one material is pooled as a whole at PPP 1; below that, clusters stay small
and PPP 1 accuracy fell to 0.60 (gamma = 0.5). Larger values erase thin strands sooner
(one pixel wide, same depth as its surroundings, PPP 10: 0.85 at 1.5, 0.80 at 2).
Since session 12 that value is each chain's start and ceiling: after its burn-in sweeps
5, 8 and 11 a chain takes the maximum pseudo-likelihood strength of its own labels
(:func:`estimate_gamma`) within ``[log(1 + sqrt(K)), gamma]``, so the coupling weakens
where the draws cut more links than a field at ``gamma`` would (PPP 1: 1.37-1.47) and
stays where the photons are weak (Art: 1.45-1.48) (``docs/classification.md``,
"Estimating the strength from the data").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .._validation import SplidarError, describe
from ._kernels import _PARALLEL

__all__ = [
    "Classification",
    "class_loglik",
    "link_gamma",
    "link_contrast",
    "chain_gammas",
    "estimate_gamma",
    "em_proportions",
    "potts_marginals",
    "classify_surfaces",
    "unknown_llr",
]

_N_GRID = 16
#: interaction strength per link (nats) of the label field: see docs/classification.md
GAMMA = 1.5
#: burn-in sweeps after which the strength is re-estimated (``classify_surfaces``):
#: every third from the 5th (the chains have coarsened from the per-surface labels) to
#: the last burn-in sweep (sweeps 5, 8, 11 of 12), on about 8,192 surfaces' terms
_ADAPT = (4, 1_000_000, 3)
_MPL_SITES = 8192
#: grid of the re-estimated strength (nats): the estimate's own noise
_G_STEP = 0.01
_HI = 1.0
#: grids (``log2`` of the brightness prior's mean, nats of ``log pi``) on which the
#: likelihood's and the sampler's global inputs are rounded: a change of the surfaces at
#: one place moves them by about ``1 / S`` and leaves them on their grid point
_ABAR_STEP = 1.0 / 16.0
_LOGPI_STEP = 0.01


def _on_grid_log2(x: float, step: float) -> float:
    """``x > 0`` rounded to the grid ``2**(step * n)``."""
    return float(2.0 ** (round(math.log2(x) / step) * step))


@njit(cache=True, inline="always")
def _nb_logpmf(y, mu, lam, alpha):
    """log NB(y; mean mu, variance mu + lam**2 / alpha), without the -log y! term."""
    v = lam * lam / alpha
    if v < 1e-9 * mu:  # Poisson limit
        return y * math.log(mu) - mu if y > 0.0 else -mu
    phi = mu * mu / v
    out = phi * math.log(phi / (phi + mu)) + y * math.log(mu / (phi + mu))
    if y < 12:
        for j in range(int(y)):
            out += math.log(phi + j)
    else:
        out += math.lgamma(y + phi) - math.lgamma(phi)
    return out


@njit(cache=True, parallel=_PARALLEL)
def _loglik_kernel(y, b, eta, c, alpha, a0, abar, out):
    S, L = y.shape
    K = c.shape[0]
    G = _N_GRID
    labar = math.log(abar)
    for s in prange(S):
        # grid in log a about the data's estimate, wide enough for the prior's bulk at
        # low counts and fine enough (half-width ~ 6 / sqrt(photons)) at high counts
        net = 0.0
        tot = 0.0
        se = 0.0
        for l in range(L):
            net += y[s, l] - b[s, l]
            tot += y[s, l]
            se += eta[s, l]
        ahat = max(net, 0.5) / max(se, 1e-12)
        half = min(6.0 / math.sqrt(tot + 1.0) + 0.5, 5.0)
        lo = math.log(ahat) - half
        step = 2.0 * half / (G - 1)
        lp = np.empty(G)
        ag = np.empty(G)
        prior = np.empty(G)
        for g in range(G):
            la = lo + g * step
            ag[g] = math.exp(la)
            # gamma prior of a, with the Jacobian a of the log grid
            prior[g] = a0 * (la - labar) - a0 * ag[g] / abar
        for k in range(K):
            m = -1e300
            for g in range(G):
                a = ag[g]
                v = prior[g]
                for l in range(L):
                    lam = a * eta[s, l] * c[k, l]
                    v += _nb_logpmf(y[s, l], lam + b[s, l], lam, alpha[k])
                lp[g] = v
                if v > m:
                    m = v
            acc = 0.0
            for g in range(G):
                w = 0.5 if (g == 0 or g == G - 1) else 1.0
                acc += w * math.exp(lp[g] - m)
            out[s, k] = m + math.log(acc * step)


def class_loglik(
    y: np.ndarray,
    background: np.ndarray,
    eta: np.ndarray,
    signatures: np.ndarray,
    *,
    alpha: np.ndarray | float = np.inf,
) -> np.ndarray:
    """Log-likelihood of each surface's counts under each class, brightness integrated out.

    See the module docstring (step 1) for the model and the equations.

    Parameters
    ----------
    y, background, eta : ndarray (S, L)
        Own-pixel counts over each surface's support, expected background there, and the
        fraction of the IRF inside the support.
    signatures : ndarray (K, L)
        Class signatures; only their shapes matter (each row is divided by its mean).
    alpha : float or ndarray (K,)
        Shape of the within-class spectral variability (``1 / CV**2`` of ``r_l``);
        ``inf``: none (Poisson counts given the brightness).

    Returns
    -------
    loglik : ndarray (S, K), float64
        Up to a constant per surface (the same for every class).

    Examples
    --------
    >>> sig = np.array([[1.0, 0.2], [0.2, 1.0]])
    >>> ll = class_loglik(np.array([[3.0, 0.0]]), np.zeros((1, 2)), np.ones((1, 2)), sig)
    >>> int(np.argmax(ll[0]))
    0
    """
    y = np.ascontiguousarray(y, np.float64)
    b = np.ascontiguousarray(background, np.float64)
    eta = np.ascontiguousarray(eta, np.float64)
    sig = np.asarray(signatures, np.float64)
    c = np.ascontiguousarray(sig / sig.mean(axis=1, keepdims=True))
    K = c.shape[0]
    al = np.ascontiguousarray(np.broadcast_to(np.asarray(alpha, np.float64), (K,)))
    al = np.where(np.isfinite(al), al, 1e300)
    S = y.shape[0]
    out = np.zeros((S, K))
    if S == 0:
        return out
    # the brightness prior: a0 = 1 (exponential, vague) at the data's mean brightness,
    # on a grid of 2**(1/16) (a vague prior's mean: 2 % either way is nothing), so that
    # adding or removing a surface leaves every other surface's likelihood bit for bit
    # (near-ties between classes, e.g. surfaces without photons, would flip otherwise)
    net = np.maximum((y - b).sum(axis=1), 0.0) / np.maximum(eta.sum(axis=1), 1e-12)
    abar = _on_grid_log2(max(float(net.mean()), 1e-3), _ABAR_STEP)
    _loglik_kernel(y, b, eta, c, al, 1.0, abar, out)
    return out


def em_proportions(loglik: np.ndarray, *, n_iter: int = 200, tol: float = 1e-5) -> np.ndarray:
    """Maximum-likelihood class proportions of a mixture with fixed components (EM).

    ``pi <- mean_s p(k | y_s, pi)`` with ``p(k | y_s, pi) ~ pi_k exp(loglik[s, k])``.

    Parameters
    ----------
    loglik : ndarray (S, K)
    n_iter : int
        At most this many EM steps (a numba loop over the surfaces each).
    tol : float
        Stop when no proportion moves by more than ``tol`` in a step (1e-5: far below
        what the labels can feel, as ``log pi`` enters once per cluster).

    Returns
    -------
    pi : ndarray (K,), sums to 1.

    Examples
    --------
    Thirty surfaces whose counts favour class 0 by 9 to 1 and ten favouring class 1: the
    proportions that make those likelihoods most probable (not the 3 : 1 of the argmax).

    >>> ll = np.log(np.array([[0.9, 0.1]] * 30 + [[0.1, 0.9]] * 10))
    >>> np.round(em_proportions(ll), 3).tolist()
    [0.812, 0.188]
    """
    ll = np.asarray(loglik, np.float64)
    S, K = ll.shape
    pi = np.full(K, 1.0 / K)
    if S == 0:
        return pi
    e = np.ascontiguousarray(np.exp(ll - ll.max(axis=1, keepdims=True)))
    _em_kernel(e, pi, int(n_iter), float(tol))
    return pi


@njit(cache=True)
def _em_kernel(e, pi, n_iter, tol):
    S, K = e.shape
    new = np.empty(K)
    for _ in range(n_iter):
        new[:] = 0.0
        for s in range(S):
            tot = 0.0
            for k in range(K):
                tot += e[s, k] * pi[k]
            if tot > 0.0:
                for k in range(K):
                    new[k] += e[s, k] * pi[k] / tot
        diff = 0.0
        for k in range(K):
            v = new[k] / S
            diff = max(diff, abs(v - pi[k]))
            pi[k] = v
        if diff < tol:
            break


@njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True, inline="always")
def _mix(x):
    """splitmix64's finaliser of the uint64 ``x``."""
    x += np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(cache=True, inline="always")
def _uniform(seed, it, key, salt):
    """Counter-based uniform in [0, 1): splitmix64 of (seed, sweep, key, salt). The same
    numbers whatever the number of threads or the order of the loop; ``key`` (uint64)
    says what is drawn for (a surface's :func:`~splidar.reconstruction._graph.surface_keys`,
    a link's :func:`_pair_key`, a cluster's smallest surface key), not where it sits in
    the arrays."""
    x = np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15)
    x ^= np.uint64(it) * np.uint64(0xBF58476D1CE4E5B9) + np.uint64(salt)
    x ^= np.uint64(key) * np.uint64(0x94D049BB133111EB)
    x = _mix(x)
    return float(x >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always")
def _pair_key(a, b):
    """Key of the link between the surfaces of keys ``a`` and ``b`` (either order)."""
    lo, hi = (a, b) if a < b else (b, a)
    return _mix(_mix(lo) ^ hi)


@njit(cache=True, inline="always")
def _draw(logp, x):
    """Index drawn from the unnormalised log-probabilities ``logp`` (overwritten) with
    uniform ``x``."""
    K = logp.size
    m = logp[0]
    for k in range(1, K):
        m = max(m, logp[k])
    tot = 0.0
    for k in range(K):
        logp[k] = math.exp(logp[k] - m)
        tot += logp[k]
    x *= tot
    for k in range(K):
        x -= logp[k]
        if x < 0.0:
            return k
    return K - 1


@njit(cache=True, parallel=_PARALLEL)
def _heat_bath(unary, indptr, indices, gam_e, order, start, u, key, seed, it, work, counts, keep):
    """One heat-bath sweep of single surfaces, colour by colour: ``order[start[c]:start[c
    + 1]]`` are the surfaces of colour c (surfaces of one colour are never linked, so each
    part-sweep is exact in parallel). ``work`` (S, K): scratch rows, one per surface (no
    allocation in the loop). With ``keep``, ``counts[s]`` accumulates the conditional
    probabilities the draw of s came from (Rao-Blackwellised marginals)."""
    K = unary.shape[1]
    for colour in range(start.size - 1):
        for i in prange(start[colour], start[colour + 1]):
            s = order[i]
            lp = work[s]
            for k in range(K):
                lp[k] = unary[s, k]
            for e in range(indptr[s], indptr[s + 1]):
                lp[u[indices[e]]] += gam_e[e]
            # salts 1, 2 (red, black), then 5, 6: 3 and 4 are the bonds' and clusters'
            u[s] = _draw(lp, _uniform(seed, it, key[s], 1 + colour + 2 * (colour > 1)))
            if keep:
                tot = 0.0
                for k in range(K):
                    tot += lp[k]
                for k in range(K):
                    counts[s, k] += lp[k] / tot


@njit(cache=True, parallel=_PARALLEL)
def _bonds(indptr, indices, p_bond, u, ekey, seed, it, bond):
    """Bond of every link between equal labels with probability ``p_bond``, drawn for
    the link's key ``ekey`` (CSR order; set on the entry ``s -> j`` with ``j > s``)."""
    S = indptr.size - 1
    for s in prange(S):
        for e in range(indptr[s], indptr[s + 1]):
            j = indices[e]
            bond[e] = j > s and u[j] == u[s] and _uniform(seed, it, ekey[e], 3) < p_bond[e]


@njit(cache=True, parallel=_PARALLEL)
def _draw_clusters(csum, root, ckey, logpi, u, seed, it):
    """New label of every cluster root from its summed log-likelihoods (``csum``, which
    is overwritten) plus ``logpi``, drawn for the cluster's key ``ckey[root]`` (the
    smallest key of its surfaces)."""
    S, K = csum.shape
    for s in prange(S):
        if root[s] == s:
            lp = csum[s]
            for k in range(K):
                lp[k] += logpi[k]
            u[s] = _draw(lp, _uniform(seed, it, ckey[s], 4))


@njit(cache=True)
def _colour_order(parity):
    """``(start, order)``: ``order[start[c]:start[c + 1]]`` are the surfaces of colour c,
    in index order (colours 0..max(parity), at least 2)."""
    S = parity.size
    n_colours = 2
    for s in range(S):
        n_colours = max(n_colours, parity[s] + 1)
    start = np.zeros(n_colours + 1, np.int64)
    for s in range(S):
        start[parity[s] + 1] += 1
    for c in range(n_colours):
        start[c + 1] += start[c]
    order = np.empty(S, np.int64)
    fill = start[:-1].copy()
    for s in range(S):
        order[fill[parity[s]]] = s
        fill[parity[s]] += 1
    return start, order


@njit(cache=True)
def _link_keys(indptr, indices, key):
    """Key of every link (CSR order) from its two surfaces' keys (:func:`_pair_key`)."""
    ekey = np.empty(indices.size, np.uint64)
    for s in range(indptr.size - 1):
        for e in range(indptr[s], indptr[s + 1]):
            ekey[e] = _pair_key(key[s], key[indices[e]])
    return ekey


@njit(cache=True)
def _mpl_sites(key, n_sites):
    """The surfaces whose terms enter the strength's pseudo-likelihood: a share ``2**-m``
    chosen by their keys (the top ``m`` bits of a hash of the key are 0), ``m`` the
    largest with ``S / 2**m >= n_sites`` (so ``n_sites`` to ``2 n_sites`` of them, all
    when ``S < 2 n_sites``). Removing or adding a surface leaves the others' choice as it
    is (a stride through the arrays would shift every later one), except where ``S``
    crosses ``n_sites * 2**m``."""
    S = key.size
    m = 0
    while (S >> (m + 1)) >= n_sites:
        m += 1
    if m == 0:
        return np.arange(S)
    keep = np.empty(S, np.bool_)
    for s in range(S):
        keep[s] = (_mix(key[s] ^ np.uint64(0x5851F42D4C957F2D)) >> np.uint64(64 - m)) == 0
    return np.nonzero(keep)[0]


@njit(cache=True)
def _clusters(indptr, indices, bond, unary, key, parent, root, csum, ckey):
    """Union-find of the bonded links: ``root[s]`` the smallest index of s's cluster,
    ``csum[root]`` the sum of the cluster's ``unary`` rows (in index order), ``ckey[root]``
    the smallest key of its surfaces (what the cluster's draw is keyed by)."""
    S, K = unary.shape
    for s in range(S):
        parent[s] = s
    for s in range(S):
        for e in range(indptr[s], indptr[s + 1]):
            if bond[e]:
                rs = _find(parent, s)
                rj = _find(parent, indices[e])
                if rs < rj:
                    parent[rj] = rs
                elif rj < rs:
                    parent[rs] = rj
    # a root is the smallest index of its cluster: one forward pass
    for s in range(S):
        r = _find(parent, s)
        root[s] = r
        if r == s:
            ckey[s] = key[s]
            for k in range(K):
                csum[s, k] = unary[s, k]
        else:
            ckey[r] = min(ckey[r], key[s])
            for k in range(K):
                csum[r, k] += unary[s, k]


@njit(cache=True)
def _swendsen_wang(
    unary,
    logpi,
    indptr,
    indices,
    wunit,
    parity,
    key,
    u,
    n_burn,
    n_keep,
    seed,
    counts,
    rb,
    g=1.0,
    a_from=0,
    a_to=0,
    a_step=1,
    lo=0.0,
    hi=0.0,
):
    """Swendsen-Wang sweeps of the Potts field with external field ``unary`` (plus
    ``logpi`` once per cluster), each followed by a heat-bath sweep; ``counts``
    accumulates the label of every surface over the ``n_keep`` sweeps after ``n_burn``.
    Link strengths ``g * wunit``; after the burn-in sweeps ``it = a_from, a_from +
    a_step, ...`` below ``a_to``, ``g`` is replaced by the maximum pseudo-likelihood
    strength of the current labels within ``[lo, hi]``, rounded to :data:`_G_STEP`
    (unless at a bound).
    Every random number is keyed by ``key`` (uint64 (S,), what each surface is): a
    surface's draw by its key, a bond's by its two surfaces' keys, a cluster's by the
    smallest key of its surfaces, so that a change of the surfaces at one place changes
    the random numbers there only. Returns the final ``g``."""
    S, K = unary.shape
    parent = np.empty(S, np.int64)
    root = np.empty(S, np.int64)
    ckey = np.empty(S, np.uint64)
    bond = np.zeros(indices.size, np.bool_)
    ekey = _link_keys(indptr, indices, key)
    sites = _mpl_sites(key, _MPL_SITES)
    gam_e = g * wunit
    p_bond = np.empty(gam_e.size)
    for e in range(gam_e.size):
        p_bond[e] = -math.expm1(-gam_e[e])
    csum = np.empty((S, K))
    work = np.empty((S, K))
    start, order = _colour_order(parity)
    for it in range(n_burn + n_keep):
        _bonds(indptr, indices, p_bond, u, ekey, seed, it, bond)
        _clusters(indptr, indices, bond, unary, key, parent, root, csum, ckey)
        _draw_clusters(csum, root, ckey, logpi, u, seed, it)
        for s in range(S):
            u[s] = u[root[s]]
        # SW moves whole regions but rarely the surfaces on their boundaries (bonded
        # to their region with probability ~0.95): a heat-bath sweep moves those
        keep = it >= n_burn
        _heat_bath(
            unary, indptr, indices, gam_e, order, start, u, key, seed, it, work, counts,
            keep and rb,
        )  # fmt: skip
        if keep and not rb:
            for s in range(S):
                counts[s, u[s]] += 1
        if a_from <= it < min(a_to, n_burn) and (it - a_from) % a_step == 0:
            gn = _mpl_gamma(u, indptr, indices, wunit, K, g, lo, hi, sites)
            # on a grid of _G_STEP (the estimate's own noise): a change of the labels at
            # one place moves the estimate by far less, and leaves the links elsewhere
            # as they are unless it crosses a half-step
            if lo < gn < hi:
                gn = max(lo, min(hi, math.floor(gn / _G_STEP + 0.5) * _G_STEP))
            if abs(gn - g) > 0.5 * _G_STEP:
                g = gn
                _set_links(wunit, g, gam_e, p_bond)
    return g


@njit(cache=True, parallel=_PARALLEL)
def _set_links(wunit, g, gam_e, p_bond):
    for e in prange(gam_e.size):
        gam_e[e] = g * wunit[e]
        p_bond[e] = -math.expm1(-gam_e[e])


@njit(cache=True, parallel=_PARALLEL)
def _side_contrast(ll, indptr, indices, margin, out):
    """Contrast factor of every link (CSR order), see :func:`link_contrast`."""
    S, K = ll.shape
    for s in prange(S):
        a = np.empty(K)
        b = np.empty(K)
        for e in range(indptr[s], indptr[s + 1]):
            j = indices[e]
            for k in range(K):
                a[k] = ll[s, k]
                b[k] = ll[j, k]
            # the neighbours of s beside the link: s2 linked to s and to a neighbour q
            # of j (a 4-cycle s - j - q - s2); q is then the neighbour of j beside it
            for e2 in range(indptr[s], indptr[s + 1]):
                s2 = indices[e2]
                if s2 == j:
                    continue
                q = -1
                for e3 in range(indptr[s2], indptr[s2 + 1]):
                    cand = indices[e3]
                    if cand == s:
                        continue
                    for e4 in range(indptr[j], indptr[j + 1]):
                        if indices[e4] == cand:
                            q = cand
                            break
                    if q >= 0:
                        break
                if q >= 0:
                    for k in range(K):
                        a[k] += ll[s2, k]
                        b[k] += ll[q, k]
            ma = a[0]
            mb = b[0]
            mab = a[0] + b[0]
            for k in range(1, K):
                ma = max(ma, a[k])
                mb = max(mb, b[k])
                mab = max(mab, a[k] + b[k])
            # mab - ma - mb <= 0: log-ratio of one class for both sides against the
            # best class of each side
            # (ma + mb first: the same bits for the link j ~ s, whose sides are swapped)
            out[e] = min(1.0, math.exp(mab - (ma + mb) + margin))


def link_contrast(loglik: np.ndarray, graph, margin: float) -> np.ndarray:
    r"""Factor (0, 1] by which the photons weaken each link (CSR order).

    For the link s ~ j, let ``A_k`` be the class log-likelihood summed over s and its two
    neighbours *beside* the link (the surfaces s' linked to s and to a neighbour j' of j,
    i.e. the 4-cycles s - j - j' - s'; on the pixel grid the two pixels of the row or
    column through s across the link) and ``B_k`` the same for j. Then::

        D_sj = max_k (A_k + B_k) - max_k A_k - max_k B_k        (<= 0, nats)
        w_sj = min(1, exp(D_sj + margin))

    ``-D_sj`` is the log-likelihood ratio of "each side its own best class" against
    "both sides one class", on the photons of 2 x 3 surfaces: the link keeps its full
    strength unless the photons say, by more than ``margin`` nats, that it crosses a
    boundary between two materials, and beyond that its strength falls by that ratio
    (a contrast-sensitive Potts weight, as in GrabCut, whose contrast is measured in
    nats of the counts' own likelihood, so no scale is set per scene). Pooling along the
    boundary (3 surfaces a side instead of 1) is what gives it power at low counts: a
    one-pixel strand, whose every cross link sees 3 strand surfaces against 3 of its
    surroundings. Inside a region, or where the evidence is weak, ``D`` stays near 0
    and the link keeps its strength, so the pooling of weak evidence is unchanged.

    The neighbours beside a link are found from the graph alone. On the depth-gated
    graph (the default) they are the surfaces of the two pixels beside the link at the
    depth of s; with ``links="all"`` and two surfaces in a pixel, the other surface of
    j's pixel closes 4-cycles too and is pooled with s's side (it is linked to s and to
    j's neighbours): the factor then mixes the layers, as the links themselves do.

    Parameters
    ----------
    loglik : ndarray (S, K)
    graph : SurfaceGraph
    margin : float
        Nats of evidence below which a link is not weakened (``classify_surfaces``:
        ``2 gamma``).

    Returns
    -------
    w : ndarray (E,), in (0, 1]

    Examples
    --------
    A 3 x 4 image, two columns of each class, 5 nats apart per surface: only the links
    across the boundary between columns 1 and 2 are weakened.

    >>> from splidar.reconstruction import build_graph
    >>> row, col = np.divmod(np.arange(12), 4)
    >>> g = build_graph(row, col, np.zeros(12, np.int64), np.zeros(12), (3, 4), 1)
    >>> ll = np.where(col[:, None] < 2, [0.0, -5.0], [-5.0, 0.0])
    >>> w = link_contrast(ll, g, 3.0)
    >>> src = np.repeat(np.arange(12), np.diff(g.indptr))
    >>> across = (col[src] + col[g.indices]) == 3
    >>> bool(w[across].max() < 0.01), bool(w[~across].min() == 1.0)
    (True, True)
    """
    ll = np.ascontiguousarray(loglik, np.float64)
    out = np.ones(graph.indices.size)
    if ll.shape[0] and out.size:
        _side_contrast(ll, graph.indptr, graph.indices, float(margin), out)
    return out


def link_gamma(graph, gamma: float) -> np.ndarray:
    """Interaction strength of every link (CSR order): ``gamma`` scaled so that the total
    coupling of a surface stays about ``4 gamma`` whatever its degree:
    ``gamma_sj = 8 gamma / (deg_s + deg_j)``, at most ``4 gamma``."""
    deg = np.diff(graph.indptr).astype(np.float64)
    src = np.repeat(np.arange(deg.size), np.diff(graph.indptr))
    return np.minimum(8.0 * gamma / (deg[src] + deg[graph.indices]), 4.0 * gamma)


@njit(cache=True)
def _cut_weights(u, indptr, indices, wunit, K, sites, n):
    """``n[i, k]``: weight of the links of surface ``s = sites[i]`` that label k would
    cut under labels ``u``; ``n[i, K]``: the same for its own label ``u[s]``."""
    for i in range(n.shape[0]):
        s = sites[i]
        tot = 0.0
        for k in range(K):
            n[i, k] = 0.0
        for e in range(indptr[s], indptr[s + 1]):
            tot += wunit[e]
            n[i, u[indices[e]]] -= wunit[e]
        for k in range(K):
            n[i, k] += tot
        n[i, K] = n[i, u[s]]


@njit(cache=True)
def _pl_derivatives(n, g):
    """First and second derivatives in ``g`` of the log pseudo-likelihood, given the cut
    weights ``n`` of :func:`_cut_weights`."""
    S, K1 = n.shape
    K = K1 - 1
    d1 = 0.0
    d2 = 0.0
    for s in range(S):
        m = n[s, 0]
        for k in range(1, K):
            m = min(m, n[s, k])
        z = 0.0
        e1 = 0.0
        e2 = 0.0
        for k in range(K):
            w = math.exp(-g * (n[s, k] - m))
            z += w
            e1 += w * n[s, k]
            e2 += w * n[s, k] * n[s, k]
        e1 /= z
        d1 += e1 - n[s, K]
        d2 += e1 * e1 - e2 / z
    return d1, d2


@njit(cache=True)
def _mpl_gamma(u, indptr, indices, wunit, K, g, lo, hi, sites):
    """Newton ascent of the (concave) log pseudo-likelihood of the labels ``u`` in the
    strength ``g``, kept within ``[lo, hi]``. The sum over surfaces runs over ``sites``
    (all, or an unbiased subsample of the sum's terms: :func:`_mpl_sites`)."""
    n = np.empty((sites.size, K + 1))
    _cut_weights(u, indptr, indices, wunit, K, sites, n)
    for _ in range(50):
        d1, d2 = _pl_derivatives(n, g)
        if d2 < -1e-12:
            step = -d1 / d2
        else:
            step = 1.0 if d1 > 0.0 else -1.0
        step = max(-1.0, min(1.0, step))
        new = max(lo, min(hi, g + step))
        if abs(new - g) < 1e-4:
            return new
        g = new
    return g


def _check_labels(labels, graph, n_classes) -> np.ndarray:
    """``labels`` as int64, one per surface of ``graph``, in ``0 .. n_classes - 1``."""
    u = np.asarray(labels)
    S = graph.indptr.size - 1
    if u.shape != (S,) or not (u.size == 0 or np.issubdtype(u.dtype, np.integer)):
        raise SplidarError(
            f"`labels` must be an integer array of shape ({S},), one label per surface of "
            f"`graph`; got {describe(labels)}."
        )
    u = np.ascontiguousarray(u, np.int64)
    K = None if n_classes is None else int(n_classes)
    top = "" if K is None else f" .. n_classes - 1 = {K - 1}"
    if u.size and (u.min() < 0 or (K is not None and u.max() >= K)):
        raise SplidarError(
            f"`labels` must be class indices 0{top}; got values {int(u.min())} .. "
            f"{int(u.max())} (relabel from 0, or pass the number of classes as n_classes)."
        )
    return u


def estimate_gamma(
    labels: np.ndarray,
    graph,
    *,
    link_weights: np.ndarray | None = None,
    n_classes: int | None = None,
    bounds: tuple[float, float] = (0.0, 10.0),
) -> float:
    r"""Maximum pseudo-likelihood interaction strength of a label map on the surface graph.

    The Potts prior of :func:`potts_marginals`, ``p(u) ~ exp(-gamma sum_links w_sj [u_s
    != u_j])`` with ``w_sj`` the strength per unit ``gamma`` (:func:`link_gamma` at 1,
    times ``link_weights``), has the log pseudo-likelihood (Besag)::

        PL(gamma) = sum_s [ -gamma n_s(u_s) - log sum_k exp(-gamma n_s(k)) ]

    where ``n_s(k)`` is the weight of the links of s that label k would cut. It is
    concave in ``gamma``; its maximum (Newton steps, kept within ``bounds``) is the
    estimate. A map in which every surface agrees with most of its neighbours (one
    region, or regions with smooth boundaries) has its maximum at infinity: the
    estimate is the upper bound. Single surfaces of another label than all their
    neighbours pull it down fast; a map whose labels ignore their neighbours is
    estimated near 0.

    This measures how strongly a *given* label map (e.g. a ground truth) clusters. It is
    not the classifier's rule for the strength: inside the sampler, re-estimated on the
    field's own draws, it returns about the strength the draws were made at (the fixed
    points form a ridge: from 1.1 / 1.5 / 2.0 it settled at 1.14-1.38 / 1.44-1.48 /
    1.60-1.77 on the Art cells), so it does not say what the photons favour
    (``docs/classification.md``, "Estimating the strength from the data").

    Parameters
    ----------
    labels : ndarray (S,), int
        Label of every surface of ``graph``, in ``0 .. n_classes - 1``.
    graph : SurfaceGraph
    link_weights : ndarray (E,), optional
        Factor of each link's strength (CSR order), e.g. :func:`link_contrast`.
    n_classes : int, optional
        K (default: ``labels.max() + 1``).
    bounds : (float, float)
        Range of the estimate (nats per link between two surfaces of degree 4).

    Returns
    -------
    float

    Raises
    ------
    SplidarError
        ``labels`` not one integer per surface of ``graph``, a label outside
        ``0 .. n_classes - 1``, or ``bounds`` not ``0 <= low <= high``.

    Examples
    --------
    >>> from splidar.reconstruction import build_graph
    >>> row, col = np.divmod(np.arange(64), 8)
    >>> g = build_graph(row, col, np.zeros(64, np.int64), np.zeros(64), (8, 8), 1)
    >>> estimate_gamma(np.zeros(64, np.int64), g, n_classes=2)
    10.0
    >>> u = (col >= 4).astype(np.int64)  # two halves, three single pixels flipped
    >>> u[[9, 30, 45]] = 1 - u[[9, 30, 45]]
    >>> round(estimate_gamma(u, g), 2)
    0.87
    """
    u = _check_labels(labels, graph, n_classes)
    K = int(u.max(initial=0)) + 1 if n_classes is None else int(n_classes)
    if not 0.0 <= float(bounds[0]) <= float(bounds[1]):
        raise SplidarError(
            f"`bounds` must be (low, high) with 0 <= low <= high; got {tuple(bounds)!r}."
        )
    wunit = link_gamma(graph, 1.0)
    if link_weights is not None:
        wunit = wunit * np.asarray(link_weights, np.float64)
    lo, hi = float(bounds[0]), float(bounds[1])
    if u.size == 0 or graph.indices.size == 0:
        return lo
    g0 = min(max(1.0, lo), hi)
    return float(
        _mpl_gamma(
            u,
            graph.indptr,
            graph.indices,
            np.ascontiguousarray(wunit),
            K,
            g0,
            lo,
            hi,
            np.arange(u.size),
        )  # fmt: skip
    )


def chain_gammas(gamma: float, n_classes: int, n_chains: int) -> np.ndarray:
    r"""Interaction strength of each chain: evenly spread over ``[g_lo, 2 gamma - g_lo]``.

    ``g_lo = min(gamma, log(1 + sqrt(K)))``, the ordering threshold of the K-state Potts
    model on the square lattice (1.10 for K = 4, 1.00 for K = 3): the rule's ``gamma``
    (1.5) fixes the order of magnitude of the strength, not its value, and any strength
    between the threshold (below it, regions stop pooling) and as far above ``gamma``
    keeps the same argument. Pooling chains run at strengths spread over that range
    averages the label marginals over that uncertainty with equal weights (a uniform
    prior on the strength; not its posterior weights, which would need the Potts
    partition function). Measured (``docs/classification.md``): on Art, where the
    Potts field fits the label texture badly, ECE 0.06-0.09 -> 0.02-0.03 at the same
    accuracy; on the multispectral scenes, which it fits, the marginals become slightly
    under-confident (ECE 0.01-0.02 -> 0.02-0.04), and on ``art_objects`` clearly so
    (ECE 0.13 at PPP 4): the lowest strength is the critical point, where the marginals
    stay spread. Not the default since session 11 (``classify_surfaces(spread=True)``).
    One chain: ``gamma``.

    Parameters
    ----------
    gamma : float
        The rule's interaction strength, nats per link
        (:func:`splidar.reconstruction.link_gamma`).
    n_classes : int
        Number of classes K (>= 1).
    n_chains : int
        Number of chains (>= 1).

    Returns
    -------
    ndarray (n_chains,), float64
        The chains' strengths, increasing, centred on ``gamma``.

    Examples
    --------
    >>> np.round(chain_gammas(1.5, 4, 3), 3).tolist()
    [1.099, 1.5, 1.901]
    """
    if n_chains <= 1:
        return np.full(max(int(n_chains), 1), float(gamma))
    lo = min(float(gamma), math.log1p(math.sqrt(n_classes)))
    return np.linspace(lo, 2.0 * gamma - lo, int(n_chains))


def potts_marginals(
    unary: np.ndarray,
    graph,
    gamma: float | np.ndarray,
    *,
    n_burn: int = 15,
    n_keep: int = 30,
    seed: int = 0,
    start: np.ndarray | None = None,
    logpi: np.ndarray | None = None,
    n_chains: int = 1,
    link_weights: np.ndarray | None = None,
    rao_blackwell: bool = True,
    estimate: tuple[float, float] | None = None,
    return_gamma: bool = False,
) -> np.ndarray:
    """Label marginals of a Potts field by Swendsen-Wang + heat-bath sampling.

    ``p(u) ~ exp(sum_s unary[s, u_s] - sum_links gamma_sj [u_s != u_j])`` with
    ``gamma_sj`` from :func:`link_gamma`; each sweep a Swendsen-Wang move (whole clusters,
    ``logpi`` added once per cluster) then a red-black heat-bath sweep of single surfaces.

    Parameters
    ----------
    unary : ndarray (S, K)
        Log-likelihood of each label.
    graph : SurfaceGraph
        Its ``key`` (what each surface is: pixel and rank by depth) keys every random
        number: a surface's draws by its key, a bond's by its two surfaces' keys, a
        cluster's by the smallest key of its surfaces. The same surfaces in another
        order give the same marginals, and a change of the surfaces at one place
        changes the random numbers there only (a graph without keys: the indices).
    gamma : float or ndarray (n_chains,)
        Interaction strength (nats per disagreeing link between two surfaces of degree
        4), >= 0; one per chain (their marginals pooled with equal weights) or one for
        all.
    n_burn, n_keep : int
        Sweeps discarded, then sweeps averaged.
    seed : int
    start : ndarray (S,), optional
        Starting labels (default: argmax of ``unary``).
    logpi : ndarray (K,), optional
        Log class proportions, counted once per Swendsen-Wang cluster (default 0).
    n_chains : int
        Independent chains (chain c: seed ``seed + 7919 c``, all from ``start``), their
        kept sweeps pooled.
    link_weights : ndarray (E,), optional
        Factor of each link's strength (CSR order), e.g. :func:`link_contrast`
        (default 1: the plain Potts field).
    rao_blackwell : bool
        Average, over the kept sweeps, the conditional probabilities from which each
        heat-bath draw was made (default) instead of the labels drawn: the same
        expectation, a smaller Monte Carlo error at the same cost (issue 14, session
        10: the net of the two-layer scene at PPP 10 moved by up to 0.02 between
        sampler seeds with label counts). ``False``: label frequencies (before).
    estimate : (float, float), optional
        Bounds ``(lo, hi)``: re-estimate each chain's strength during its burn-in
        (after every third of its sweeps from the 5th to ``n_burn``: 5, 8, 11 of 12)
        as the maximum pseudo-likelihood strength of the chain's current labels
        (:func:`estimate_gamma`), starting from ``gamma``; the kept sweeps run at the
        last estimate. Default: ``gamma`` fixed.
    return_gamma : bool
        Also return the chains' final strengths.

    Returns
    -------
    marginals : ndarray (S, K), rows sum to 1 (averages over the kept sweeps of all
        chains, with half a count in all added so that no marginal is exactly 0 or 1).
    gammas : ndarray (n_chains,)
        Only with ``return_gamma``.
    """
    un = np.ascontiguousarray(unary, np.float64)
    S, K = un.shape
    if S == 0:
        empty = np.zeros((0, K))
        return (empty, np.full(int(n_chains), float(np.mean(gamma)))) if return_gamma else empty
    u0 = np.argmax(un, axis=1).astype(np.int64) if start is None else start.astype(np.int64)
    counts = np.zeros((S, K))
    lp = np.zeros(K) if logpi is None else np.ascontiguousarray(logpi, np.float64)
    gam = np.broadcast_to(np.asarray(gamma, np.float64), (int(n_chains),))
    wunit = link_gamma(graph, 1.0)
    if link_weights is not None:
        wunit = wunit * np.asarray(link_weights, np.float64)
    wunit = np.ascontiguousarray(wunit)
    key = _graph_keys(graph, S)
    a_from, a_to, a_step = (0, 0, 1) if estimate is None else _ADAPT
    lo, hi = (0.0, 0.0) if estimate is None else estimate
    g_out = np.empty(int(n_chains))
    for c in range(int(n_chains)):
        g_out[c] = _swendsen_wang(
            un, lp, graph.indptr, graph.indices, wunit, graph.parity, key, u0.copy(),
            int(n_burn), int(n_keep),
            int(seed) + 7919 * c, counts, bool(rao_blackwell),
            float(gam[c]), a_from, a_to, a_step, float(lo), float(hi),
        )  # fmt: skip
    counts += 0.5 / K
    marg = counts / counts.sum(axis=1, keepdims=True)
    return (marg, g_out) if return_gamma else marg


def _graph_keys(graph, S: int) -> np.ndarray:
    """The surfaces' keys of ``graph`` (its indices for a graph without keys)."""
    key = getattr(graph, "key", None)
    if key is None:
        return np.arange(S, dtype=np.uint64)
    return np.ascontiguousarray(key, np.uint64)


def unknown_llr(y: np.ndarray, background: np.ndarray, eta: np.ndarray, signatures, label):
    r"""Likelihood-ratio statistic of a free spectrum against the assigned class, (S,).

    ``2 [max_{lam >= 0} sum_l log Pois(y_l; lam_l + b_l) - max_a sum_l log Pois(y_l;
    a eta_l c_{u,l} + b_l)]``: asymptotically chi-square with ``L - 1`` degrees of
    freedom when the class's signature explains the counts (the free spectrum has L
    parameters, the class one). The maximum over ``a`` is found by Newton steps on
    ``sum_l y_l eta_l c_l / (a eta_l c_l + b_l) = sum_l eta_l c_l``.
    """
    y = np.asarray(y, np.float64)
    b = np.maximum(np.asarray(background, np.float64), 1e-12)
    sig = np.asarray(signatures, np.float64)
    c = (sig / sig.mean(axis=1, keepdims=True))[np.asarray(label)]
    ec = np.asarray(eta, np.float64) * c
    # free: lam = max(y - b, 0)
    mu_f = np.maximum(y, b)
    ll_free = (y * np.log(mu_f) - mu_f).sum(axis=1)
    a = np.maximum((y - b).sum(axis=1), 0.0) / ec.sum(axis=1)
    for _ in range(30):  # concave in a: Newton from the moment estimate, kept >= 0
        mu = a[:, None] * ec + b
        g = (y * ec / mu).sum(axis=1) - ec.sum(axis=1)
        h = -(y * ec**2 / mu**2).sum(axis=1)
        a = np.maximum(a - g / np.minimum(h, -1e-12), 0.0)
    mu = a[:, None] * ec + b
    ll_cls = (y * np.log(mu) - mu).sum(axis=1)
    return np.maximum(2.0 * (ll_free - ll_cls), 0.0)


@dataclass(frozen=True)
class Classification:
    """Result of :func:`classify_surfaces`.

    Attributes
    ----------
    label : ndarray (S,), int64
        Most probable class of each surface (argmax of its marginal).
    marginals : ndarray (S, K)
        Posterior marginal probability of each class (rows sum to 1).
    proportions : ndarray (K,)
        Class proportions (EM).
    loglik : ndarray (S, K)
        Per-surface class log-likelihood (:func:`class_loglik`).
    gamma : float
        Interaction strength of the kept sweeps (mean over the chains: the estimate
        when ``classify_surfaces(estimate=True)``, else the rule's value).
    """

    label: np.ndarray
    marginals: np.ndarray
    proportions: np.ndarray
    loglik: np.ndarray
    gamma: float

    @property
    def confidence(self) -> np.ndarray:
        """Marginal probability of the chosen label, (S,)."""
        return self.marginals.max(axis=1) if self.marginals.size else np.ones(0)


def classify_surfaces(
    y: np.ndarray,
    background: np.ndarray,
    eta: np.ndarray,
    signatures: np.ndarray,
    graph,
    *,
    gamma: float = GAMMA,
    alpha=np.inf,
    n_rounds: int = 1,
    n_chains: int = 2,
    n_burn: int = 12,
    n_keep: int = 12,
    seed: int = 0,
    proportions: np.ndarray | None = None,
    contrast: bool = True,
    spread: bool = False,
    loglik: np.ndarray | None = None,
    estimate: bool = True,
) -> Classification:
    """Labels with calibrated marginal probabilities and class proportions (steps 1-3).

    ``pi`` is the EM estimate on the per-surface likelihoods; then ``n_rounds`` rounds of
    [label marginals (:func:`potts_marginals`, each round starting from the previous
    labels), ``pi`` = mean marginal (the M-step)]. One round (the default) measured as
    accurate as two on the benchmark scenes once the heat-bath sweeps were added, at
    half the cost.

    Parameters
    ----------
    y, background, eta : ndarray (S, L)
        As in :func:`class_loglik`.
    signatures : ndarray (K, L)
    graph : SurfaceGraph
    gamma : float
        Interaction strength per link (nats), see :func:`link_gamma`.
    alpha : float or ndarray (K,)
        Within-class spectral variability (:func:`class_loglik`).
    n_rounds, n_chains, n_burn, n_keep : int
        Rounds of sampling; independent chains per round (seeds ``seed + round + 7919
        c``, all started from the previous round's labels, the first round from the
        argmax of the likelihood), whose kept sweeps are pooled; sweeps discarded and
        kept per chain. 2 chains of 12 + 12 sweeps (48 in all, the cost of the former
        3 chains of 8 + 8 and of the first single chain of 15 + 30): chains that start
        from the per-surface labels need about 12 sweeps to coarsen into regions at low
        counts (with 8, short chains settling into different labellings of the same
        objects made the pooled marginals under-confident: ``art_objects`` at PPP 4,
        ECE 0.06 with 3 chains of 8 + 8 at ``gamma``), and two chains keep some of the
        spread between modes at PPP 1 (one chain of 16 + 32: ECE 0.09-0.11 on single
        PPP 1 cells).
    seed : int
    proportions : ndarray (K,), optional
        Class proportions to start from instead of the EM estimate on these surfaces (a
        tile of a tiled reconstruction passes the whole image's).
    contrast : bool
        Weaken the links that the photons say cross a boundary between materials
        (:func:`link_contrast` with margin ``2 gamma``; default). ``False``: the plain
        Potts field of session 7.
    spread : bool
        Spread the chains' interaction strengths evenly over ``[g_c, 2 gamma - g_c]``
        with ``g_c = log(1 + sqrt(K))`` the ordering threshold of the K-state Potts model
        (:func:`chain_gammas`; the default of sessions 8-10, with 3 chains of 8 + 8).
        ``False`` (default since session 11): every chain at ``gamma``. Equal weights
        on the spread strengths are the prior's, not the posterior's: the lowest chain
        sits at the critical point, where the field's marginals stay spread however
        clear the regions (``art_objects``, PPP 4: confidence 0.61 against accuracy
        0.70-0.77 in that chain alone), so where the field fits the scene the pooled
        confidence was too low (ECE 0.13 / 0.07 / 0.04 at PPP 4 / 16 / 64), while the
        marginal likelihood of the strength (thermodynamic integration) puts it near
        1.3-1.5 there. ``docs/classification.md``, "Calibration where the field fits".
    loglik : ndarray (S, K), optional
        :func:`class_loglik` of these surfaces (with this ``alpha``) when already
        computed (a tiled reconstruction computes it once for the whole image).
    estimate : bool
        Re-estimate the strength from the data (default): after the sweeps 5, 8 and 11
        of each chain's burn-in the strength is set to the maximum pseudo-likelihood
        strength of the chain's current labels (:func:`estimate_gamma`), starting from
        ``gamma`` and kept within ``[log(1 + sqrt(K)), gamma]`` (the ordering threshold
        of the K-state Potts model, below which regions stop pooling, and the rule's
        value, above which one-pixel strands are erased); the kept sweeps run at the
        chain's last estimate. Where the draws cut more links than a field at ``gamma``
        would (PPP 1 on the benchmark scenes: 1.37-1.47) the coupling weakens; where the
        photons are weak the draws follow the prior and the estimate stays near
        ``gamma`` (Art: 1.44-1.48) (``docs/classification.md``, "Estimating the
        strength from the data").
        ``False``: ``gamma`` fixed (sessions 7-11).

    Returns
    -------
    Classification

    Examples
    --------
    >>> from splidar.reconstruction import build_graph
    >>> row, col = np.zeros(4, np.int64), np.arange(4)
    >>> g = build_graph(row, col, np.zeros(4, np.int64), np.zeros(4), (1, 4), 1)
    >>> y = np.array([[2.0, 0.0], [1.0, 0.0], [1.0, 1.0], [2.0, 0.0]])
    >>> sig = np.array([[1.0, 0.1], [0.1, 1.0]])
    >>> c = classify_surfaces(y, np.zeros((4, 2)), np.ones((4, 2)), sig, g)
    >>> c.label.tolist()
    [0, 0, 0, 0]
    """
    ll = class_loglik(y, background, eta, signatures, alpha=alpha) if loglik is None else loglik
    S, K = ll.shape
    pi = em_proportions(ll) if proportions is None else np.asarray(proportions, np.float64)
    # a strand one pixel wide pays 2 cross links per surface, ~2 gamma nats: the links
    # whose 2 x 3 surfaces favour two classes by more than that are weakened
    w = link_contrast(ll, graph, 2.0 * gamma) if contrast else None
    gam = chain_gammas(gamma, K, n_chains) if spread else gamma
    marg = np.full((S, K), 1.0 / K)
    start = None
    bounds = (min(gamma, math.log1p(math.sqrt(K))), _HI * gamma) if estimate else None
    g_used = float(gamma)
    for i in range(n_rounds):
        # log pi on a grid of _LOGPI_STEP nats (far below its sampling error): one
        # surface more or less moves pi by ~1 / S and leaves every cluster's draw as is
        logpi = np.round(np.log(np.maximum(pi, 1e-6)) / _LOGPI_STEP) * _LOGPI_STEP
        # independent chains, kept sweeps pooled: one chain rarely flips a whole patch
        # once it has settled, so its marginals miss the other modes (over-confident)
        marg, g_c = potts_marginals(
            ll, graph, gam, seed=seed + i, start=start, logpi=logpi,
            n_burn=n_burn, n_keep=n_keep, n_chains=n_chains, link_weights=w,
            estimate=bounds, return_gamma=True,
        )  # fmt: skip
        g_used = float(np.mean(g_c)) if S else g_used
        start = np.argmax(marg, axis=1)
        if S:
            pi = marg.mean(axis=0)
    return Classification(np.argmax(marg, axis=1).astype(np.int64), marg, pi, ll, g_used)
