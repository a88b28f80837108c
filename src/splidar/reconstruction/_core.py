"""Bayesian 3D reconstruction and spectral classification of detected surfaces (Algorithm 2).

Notes on :func:`reconstruct` (the model, its updates and what was measured)
==========================================================================

Model (for surface s at wavelength l, class ``k = u_s``)::

    y_{s,l} ~ Poisson(eta_{s,l} h_s r_{s,l} + b_{s,l})       own-pixel counts over the support
    r_{s,l} ~ Gamma(alpha_{k,l}, scale beta_{s,l})           eq:4.4
    beta_{s,l} ~ InvGamma(upsilon_{k,l}, eps_{k,l})          eq:4.3
    (h, w) ~ gamma-MRF over the surface graph, coupling rho  eq:4hafter
    u ~ Potts(gamma) over the same graph                     eqt:priorLabels2

``y`` are the raw counts of the surface's own pixel summed over its support and ``b``
the expected background there (``Surfaces.counts``, ``Surfaces.background``);
``eta`` is the fraction of the IRF inside the support. The intensity is
``I_{s,l} = h_s r_{s,l}``, the expected signal photons of the whole return.

Why these data and not the paper's ``ybar`` at the selected scale: that is a spatial
average (blurred at edges, with a variance that is not Poisson), whereas the own-pixel
counts have the exact Poisson likelihood above, which makes the posterior uncertainty
calibrated; the spatial smoothing comes from the MRF priors instead. The background is
handled by EM: each sweep splits ``y`` into expected signal ``z = y q`` and background
(``q = eta h r / (eta h r + b)``), after which every conditional is conjugate.

Labels (K > 1) are chosen once, before the sweeps, from the photon counts by
:func:`splidar.reconstruction.classify_surfaces` (``_classify``: a class likelihood with
the brightness integrated out, EM class proportions, and the marginals of a Potts field
over the depth-gated graph sampled by Swendsen-Wang, whole regions at a time); the label
is the most probable marginal class and ``label_confidence`` its probability. They then
stay fixed while the intensities are estimated. (Until issue 14 the labels were updated
in every sweep by red-black ICM on the gamma density of the current ``r``: its log-odds
grew with the noise of ``r`` and the Potts term changed no label; PPP 1 accuracy was
0.48-0.53 against 0.85-0.90 now, see ``docs/classification.md``.)

Updates, in this order every sweep (each the exact maximiser of its block):

2. ``r = (z + alpha - 1) / (eta h + 1 / beta)`` (``eqt:Modes_Param_top`` left),
3. ``beta = (r + eps) / (alpha + upsilon + 1)`` (right),
4. ``h = (sum_l z + theta_1) / (sum_l eta r + theta_2)``, ``theta_1 = rho (1 + deg)``,
   ``theta_2 = rho (1/w_s + sum 1/w_s')`` (``eqt:Modes_Param_bottom`` left),
5. ``w = (h_s + sum h_s') / (1 + deg)`` (right); steps 4-5 are done twice (the h-w
   chain mixes slowly when rho is large),
6. the E-step again; steps 2-6 are done four times per sweep (each round costs about
   a third of the label update, and the EM split mixes slowly at SBR ~ 1: on the
   simulator's 64 x 64 scenes this cuts the sweeps from 17-19 to 7-8, on the Art
   detection from 19 to 14, with labels unchanged and IAE within 0.2 %).

Cost (``benchmarks/bench_speed.py``, Art-size detection: 84,577 surfaces, L = 3,
K = 4): steps 2-3 and the E-step are one pass and the h updates read per-surface sums
made once per round; the objective is evaluated every 5 sweeps and at the end of each
phase (``history.objective`` is NaN in between); the graph and the IRF fractions are
built by numba kernels; the kernels use only the cores other processes leave free
(``_free_cores``). Measured on the idle 2-core machine before issue 14 (labels then
updated in the sweeps), with ``alpha="auto"``: Art 0.19-0.20 s, 80,000 surfaces
(``bench_reconstruction`` (c)) 0.17 s. The classification (``timings["classify"]``)
costs ``O(S K L)`` for the likelihood (a 16-point quadrature per surface and class) and
``O(48 (E + S K))`` for the 48 Swendsen-Wang and heat-bath sweeps (E links): linear in the surfaces
and the classes (``docs/classification.md`` has the measured figures).

The gamma-MRF here is ``log p(h, w) = sum_{links (s, j)} rho (log h_s - log w_j -
h_s / w_j)`` with a link from each ``h_s`` to its own ``w_s`` and to the ``w`` of its
graph neighbours. Against the paper's form this drops the ``-log h - log w`` terms
(shape offsets of one), so the modes above are weighted means that never collapse
to 0 on surfaces with no photons; the own link keeps the two checkerboard sub-lattices
of a 4-neighbour graph coupled. The prior is scale free: h carries the shading and
any global scale between library and data.

Since r, beta, h and w each maximise the complete-data posterior,
the objective (marginal log posterior, background summed out) never decreases
(generalised EM); ``history.objective`` records it. With ``alpha="auto"`` the model
itself changes once, at the empirical-Bayes update: the objective is re-evaluated
under the new (alpha, upsilon) and may be lower than the sweep before
(``history.alpha_updates`` holds that sweep); before and after, it never decreases.

Hyperparameter defaults: ``alpha = "auto"`` (see the parameter: an empirical-Bayes
alpha and upsilon per class, estimated after a first phase at ``alpha = 6``, the
shape of r given beta), ``upsilon = 3`` and
``eps_{k,l} = m_{k,l} (upsilon - 1) / alpha`` so that the inverse-gamma mean of beta
is ``m_{k,l} / alpha`` and the prior mean of ``r_{s,l}`` is the library signature
``m_{k,l}``; ``rho = 4`` (the MRF weighs like about four photons per link, so a
surface with 4 linked neighbours gets a prior on h worth about 20 photons, against
the 5-20 signal photons of a surface at PPP 10); ``gamma = 1.5`` nats per link of the
label field (see ``_classify``: a rule, not fitted to a scene; until issue 14 ``gamma =
2`` in the units of the former label score). rho and that former gamma were measured,
not tuned to one scene (``benchmarks/bench_reconstruction.py``,
fabricated scenes with 1-2 layers and spectral variability 0-0.4, and the
simulator's one- and two-layer multispectral scenes through detection, PPP 10,
SBR 1): against the former ``rho = 1, gamma = 4`` IAE fell by 5-12 % on every
scene, coverage of +-1 std moved by at most 0.03, and label accuracy rose or
stayed (two-layer multispectral through detection: 0.944 / 0.953 -> 0.954 / 0.957
on two seeds; gamma = 8 lowered it, gamma = 2 and 3 were within 0.005).

Posterior uncertainty: given h and beta, ``r_{s,l}`` is a mixture over the unknown
signal/background split of gammas ``G(z + alpha, rate eta h + 1/beta)``; its variance
is ``(E[z] + alpha + Var[z]) / rate^2`` with ``z ~ Binomial(y, q)`` (law of total
variance). ``intensity_std**2 = h**2`` times that, plus the uncertainty of h carried
by the delta method (``(dE[I | h] / dh)**2 Var(h | .)``, with the gamma conditional
of h), which matters where the prior dominates (few photons). With ``alpha="auto"``
beta is integrated out instead of held at its mode (the inverse gamma is conjugate:
``p(r | h, z) ~ r**(z + alpha - 1) exp(-eta h r) (r + eps)**-(alpha + upsilon)``) and
r's variance is the Laplace one of that marginal (see ``_kernels.posterior``): there
beta carries half of the prior's variance by construction, and holding it fixed
under-covered scenes with spectral variability (CV 0.4: 0.63 -> 0.68). With a fixed
alpha the beta-at-its-mode form is kept: integrating beta out of the default
(vague, upsilon = 3) prior widened the std everywhere the prior matters, pooled
coverage 0.85 -> 0.88 without variability, 0.73 -> 0.79 at CV 0.4 (only CV 0.6 came
nearer: 0.64 -> 0.69).

Why scenes with no spectral variability over-cover with h's conditional variance
(0.82-0.87, flat over intensity, with ``alpha="auto"``): the h term. Measured on
64 x 64 fabricated scenes: without it coverage is 0.19-0.34, without the binomial
term unchanged. The conditional variance given the neighbours' w is, relative,
``1 / (sum z + rho (1 + deg))`` (sd 0.18 at 10 photons); the model's full marginal
(Gibbs sampling of z, r, beta, h, w) is wider still (the formula's sd is 0.54-0.77 of
it), but the MAP's actual error is 0.136, the sampling sd of the linearised MRF
smoother (0.134): the difference is the prior's own spread of h about its neighbours
(its expected squared smoothing bias), which a smooth true shading does not have.
Empirical Bayes on rho does not cure it: the error of h_s predicted from its
neighbours, measured in the data, is about that of rho = 4 (1 / 0.04-0.05 = 20-25
pseudo-photons against rho (1 + deg) = 20), and a rho matched to the true shading's
increments (~200) over-smooths its curvature: at rho = 64 coverage 0.66 / 0.59 (one /
two layers) but IAE 1.01 / 0.76 against 1.11 / 0.65 at rho = 4 and 0.67 / 0.50 at
rho = 16 (with the marginal variance of h, coverage of the 0.5-1 photon bin fell to
0.2 at rho = 64 and 0.08 at rho = 200: bias). A first-order MRF cannot say "smooth
but curved". So with ``alpha="auto"`` the h term is instead the empirical-Bayes
mean squared error of the MAP shading (``_h_variance_eb``): the sampling variance of
the linearised smoother (4-neighbour lattice, Fourier, at the surface's own photons
and links) plus one squared smoothing bias per scene, measured as the excess of
``(h_raw - h)**2`` over the noise the smoother leaves in it
(``hyperparameters["shading_bias2"]``, relative; 0.0014-0.008 on scenes without
variability). That is an estimate of the estimator's error, not the model's
posterior of h; no constant is fitted to the coverage.

The label term (``alpha="auto"``, K > 1). All of the above is conditional on the
label. Where classes differ by little more than the Poisson noise of a spectrum's
shape, the label is often wrong, and the alpha estimate cannot see it: the labels
were chosen to fit the same counts, so the counts scatter about the chosen
signatures LESS than Poisson. Art scene (4 colour classes, label accuracy 0.29 /
0.45 at PPP 10 / 30): the truth's relative variance about the chosen signatures is
0.03-0.08 per class, the estimate 0 (alpha 456-2000); the same estimate on counts
redrawn from the truth gives alpha 14-62. So r sat on the chosen signature with a
std of a few %, the shape errors were 0.19-0.27 (relative) and coverage 0.38 / 0.52,
although the brightness was covered (total over wavelengths: 0.61 / 0.71).
Re-estimating alpha with labels chosen on another part of the data (binomial
thinning, cross-fitting) removes the bias but gives the mean-square distance, which
on well-separated classes is dominated by the few gross mislabels (CV 0 scenes over-
covered, 0.78-0.82). Instead the std adds the label's own uncertainty: two labels
``k_j`` are drawn from
each surface's marginal label posterior (``classify_surfaces``, from ``rng``) and
``intensity_std**2`` gains ``mean_j (h r_{k_j} - h r)**2`` (0 where ``k_j`` is the
label), ``r_k`` the joint mode under class k at the surface's h (``_label_spread``): a
two-draw estimate of the between-class part of the variance, ``E_k[(h r_k - h r)**2]``
under the label posterior. (Until issue 14 the two labels came from two independent
Poisson halves of the counts (binomial thinning), each labelled by ICM; the figures
below were measured with those. Drawing from the calibrated marginals gives the same
quantity without the halves' worse labels, which erred wide where classes are far
apart.) Intensities and labels do not depend on these draws.
Measured (``bench_reconstruction``, 96 x 96, PPP 10, SBR 1; before -> after): Art
0.38 -> 0.61 (PPP 30: 0.52 -> 0.69); fabricated CV 0 0.72 -> 0.76 (one layer
0.72-0.74, two layers 0.77-0.78: label accuracy 0.91-0.97 there), CV 0.2 / 0.4 / 0.6
0.66 / 0.65 / 0.64 -> 0.70 / 0.69 / 0.68, simulator one layer 0.70 -> 0.71 / 0.72,
two layers 0.65 -> 0.68 / 0.71.

Calibration with a fixed alpha (``alpha=6``, the default before ``"auto"``; measured
with ``benchmarks/bench_reconstruction.py``, fabricated scenes, PPP 10, SBR 1,
fraction of true intensities within +-1 std; 0.68 is the Gaussian value, a skewed
gamma posterior of small shape gives up to about 0.74): where the data dominate
(true intensity >= 2 photons) it is 0.60-0.74. Where the prior dominates (< 0.5
photon) it depends on how far the truth departs from the prior mean: 0.96 on scenes
whose every surface carries its class signature exactly, 0.77 at a within-class
coefficient of variation of 0.4, 0.57 at 0.6 (the prior's own spread: the gamma of
shape 6 with beta at its mode has CV 0.41, widened by beta's inverse gamma). Pooled:
0.85 with no variability, 0.81 / 0.73 / 0.64 at CV 0.2 / 0.4 / 0.6, 0.79-0.80 on the
simulator's scenes. So that std is the posterior's under the model; it over-covers
where the prior is wider than a scene's real spectral variability, which is why the
default estimates the prior's width from the data (``alpha="auto"``).

``alpha="auto"`` (the default) in detail
----------------------------------------

Gamma shape of r (> 1, so that the mode of r is positive), or ``"auto"``
(default: empirical Bayes). ``"auto"`` runs two phases. Phase 1, with the given
``upsilon`` and alpha = 6, stops once the intensities change by less than ``10 tol``
(at most ``max_iter // 2`` sweeps): its intensities are only a start. Then each
class's spectral variability ``v =
CV**2`` of the counts about the signatures, at the shading the neighbours predict,
is estimated (:func:`estimate_alpha`), ``alpha = 2 / v`` and ``upsilon = 2 + 2 /
v`` (the compound prior of r then has relative variance v, half from each), r
restarts at its new prior mode with h keeping each surface's expected signal, and
phase 2 runs to ``tol`` with the labels kept (``history.alpha_updates`` holds the
sweep). The std then integrates beta out of r's part, takes h's
part from the empirical-Bayes MSE of the smoother and adds the label term (see
the notes above). Measured
(``bench_reconstruction``, PPP 10, SBR 1; fabricated: 96 x 96, 4 seeds at CV 0, 1
seed x 1-2 layers otherwise; simulator: 96 x 96 through detection, 2 seeds; label
accuracy within 0.001 of alpha = 6 on every one of these scenes, equal on all but
two):

====================  ============  ===========  =====================
scene                 IAE 6 / auto  cov 6 / auto  sweeps 6 / auto
====================  ============  ===========  =====================
CV 0, 1 layer         2.55 / 1.15   0.85 / 0.72   8-10 / 7
CV 0, 2 layers        1.39 / 0.64   (pooled)      10-14 / 10-11
CV 0.2                2.65 / 1.79   0.81 / 0.66   8-10 / 8-10
CV 0.4                2.88 / 2.63   0.73 / 0.65   8-10 / 8-10
CV 0.6                3.21 / 3.19   0.64 / 0.64   8-10 / 9-11
simulator 1 layer     2.70 / 1.23   0.80 / 0.70   7 / 7
simulator 2 layers    2.32 / 1.58   0.79 / 0.65   8 / 8
Art (bench_speed)     4.06 / 2.88   0.71 / 0.52   15 / 9
====================  ============  ===========  =====================

(IAE of the one-layer scene at CV 0.2-0.6; coverage pooled over the one- and
two-layer scenes.) Coverage by bin of true intensity (< 0.5,
0.5-1, 1-2, 2-4, >= 4 photons), "auto": CV 0 0.72 / 0.72 / 0.72 / 0.72 / 0.71; CV 0.2
0.65 / 0.66 / 0.67 / 0.67 / 0.64; CV 0.4 0.58 / 0.69 / 0.68 / 0.66 / 0.61; CV 0.6
0.56 / 0.73 / 0.70 / 0.64 / 0.60; simulator one layer 0.68 / 0.70-0.72 / 0.69-0.71
/ 0.70-0.71 / 0.69-0.70, two layers 0.56-0.58 / 0.63-0.65 / 0.63-0.67 / 0.66-0.68 /
0.70-0.73. With the former std formula (beta at its mode, h's conditional variance)
the "auto" coverage was 0.84 / 0.69 / 0.63 / 0.64 at CV 0 / 0.2 / 0.4 / 0.6.
Art (``art_scene``, PPP 30, SBR 1, through detection): 0.69 (0.31 / 0.65 / 0.68
/ 0.70 by bin from 0.5 photon; 0.52 without the label term, 0.71 with alpha =
6), PPP 10 0.62 (0.38 without, 0.75 with alpha = 6): there the labels are mostly
wrong (accuracy 0.29 / 0.45 against 4 close classes) and the label term carries
most of the width.
(The numbers below and in the table, except Art's, predate the label term, which
raised the coverage by 0.00-0.05, see the notes above.)
Other photon levels (64 x 64, one seed, CV 0 / 0.4, one and two layers; labels
identical to alpha = 6, IAE lower everywhere): PPP 3 0.66 / 0.63 one layer, 0.64 /
0.55 two layers (alpha = 6: 0.83-0.88 / 0.70-0.74); PPP 30 0.72 / 0.66 (0.76-0.80
/ 0.69-0.72); SBR 0.3 and 5 at PPP 10 0.62-0.75 (0.73-0.87). A number keeps alpha
(and upsilon) fixed: one phase, the std with beta at its mode and h's conditional
variance.

``signature_scale``
-------------------

``"shape"`` (default when L > 1): each signature is divided by its mean over
wavelengths before use, so classes are told apart by the shape of their spectra
and the shading h carries all brightness. ``"absolute"`` (default when L = 1)
keeps the library's magnitudes. Why: with r held, the label score of class k peaks
at ``m_k = alpha upsilon r / ((alpha + 1)(upsilon - 1))`` (1.29 r at the
defaults), while without data the joint mode of (r, beta) sits at
``r = m (alpha - 1)(upsilon - 1) / (alpha (upsilon + 2))`` (0.33 m) of the current
class, so absolute magnitudes pull labels towards dimmer classes sweep after sweep. On the
Art scene (4 colour classes of mean 2.4-5.2) the labels drifted into the dimmest
class (65,295 of 84,677 surfaces): accuracy 0.256 in 68 sweeps against 0.445 in 19
with ``"shape"``; on the simulator's multispectral scenes (near-equal magnitudes)
accuracy and IAE moved by < 0.001 and < 0.3 %. When the classes' true
reflectivities do differ in magnitude (fabricated, x0.5 / x1 / x2), "absolute"
uses that and was slightly better (0.964 against 0.950).
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from dataclasses import dataclass

import numba
import numpy as np

from .._validation import SplidarError, as_float_array, check_choice, check_int, check_positive
from ..cube import SPEED_OF_LIGHT
from ..detection._result import Detection
from ..library import as_library
from ..points import PointSet
from . import _kernels as kern
from ._classify import GAMMA, classify_surfaces
from ._graph import build_graph, irf_fwhm, with_bridges
from ._result import ConvergenceHistory, Reconstruction

__all__ = [
    "estimate_alpha",
    "irf_fraction",
    "kmeans_signatures",
    "nearest_signature",
    "reconstruct",
]

log = logging.getLogger(__name__)

_LINKS = ("depth", "all")
_CLASSES = ("library", "one", "cluster")
# h-w passes per inner round: the gamma-MRF mixes slowly at rho = 4 (with one round per
# sweep: 48 sweeps to tol on an 80,000-surface scene with one pass, 23 with three)
_HW_PASSES = 2
# rounds of [r, beta, h-w, E-step] per sweep (per label update)
_INNER = 4
# alpha is kept in [1.5, 1000] (a reflectivity CV between 0.8 and 0.03)
_ALPHA_BOUNDS = (1.5, 1000.0)
# alpha="auto": the first phase (alpha = 6) only gives a start for the alpha estimate, the
# second re-fits the intensities under the estimated prior: the first stops at this x tol.
# Measured when the labels were still updated in the sweeps (before issue 14): the same
# label accuracy on the bench's scenes (0.913 -> 0.912 on one), 0-3 fewer sweeps.
_PHASE1_TOL = 10.0
# the objective is evaluated every this many sweeps (and after the last): about a fifth
# of a sweep's cost, and only a record of the ascent
_OBJ_EVERY = 5


def irf_fraction(
    irf: np.ndarray, depth_bin: np.ndarray, start: np.ndarray, stop: np.ndarray
) -> np.ndarray:
    """Fraction ``eta_{s,l}`` of each wavelength's IRF that falls inside a surface's support.

    A return at (fractional) depth ``d`` puts ``g_l[t - d + p_l]`` of its photons in bin t
    (``p_l`` the IRF peak, the depth reference). The expected own-pixel signal counts over
    the support ``[start, stop)`` are ``eta_{s,l} I_{s,l}``.

    Parameters
    ----------
    irf : ndarray (L, n_irf)
        Normalised IRF.
    depth_bin : ndarray (S,)
    start, stop : ndarray (S,) int

    Returns
    -------
    eta : ndarray (S, L), float64, in [0, 1].

    Examples
    --------
    >>> from splidar.irf import gaussian_irf
    >>> g = gaussian_irf(3.0)[None]
    >>> float(irf_fraction(g, np.array([50.0]), np.array([0]), np.array([100]))[0, 0])
    1.0
    """
    g = np.atleast_2d(np.asarray(irf, dtype=np.float64))
    d = np.ascontiguousarray(depth_bin, dtype=np.float64).ravel()
    out = np.empty((d.size, g.shape[0]))
    # bin t covers IRF sample t - d + p; its lower edge sits at that index in `cum`
    cum = np.concatenate([np.zeros((g.shape[0], 1)), np.cumsum(g, axis=1)], axis=1)
    peak = np.argmax(g, axis=1).astype(np.float64)
    kern.irf_fraction(
        cum, peak, d, np.ascontiguousarray(start, np.float64).ravel(),
        np.ascontiguousarray(stop, np.float64).ravel(), out,
    )  # fmt: skip
    return out


def nearest_signature(intensity: np.ndarray, signatures: np.ndarray) -> np.ndarray:
    """Per-surface nearest-signature classification (no spatial prior): the baseline.

    The class maximising the multinomial log-likelihood of the spectrum's shape,
    ``sum_l x_l log(m_{k,l} / sum_l m_{k,l})`` with ``x = max(intensity, 0)``: the
    maximum-likelihood label of Poisson counts whose scale is free.

    Parameters
    ----------
    intensity : ndarray (S, L)
        Per-surface intensity estimates (e.g. background-subtracted counts).
    signatures : ndarray (K, L)

    Returns
    -------
    label : ndarray (S,), int64

    Examples
    --------
    >>> nearest_signature(np.array([[5.0, 1.0], [0.0, 3.0]]), np.array([[1.0, 0.1], [0.1, 1.0]]))
    array([0, 1])
    """
    x = np.maximum(np.asarray(intensity, dtype=np.float64), 0.0)
    m = np.asarray(signatures, dtype=np.float64)
    shape = m / m.sum(axis=1, keepdims=True)
    logm = np.log(np.maximum(shape, 1e-12))
    return np.argmax(x @ logm.T, axis=1).astype(np.int64)


def estimate_alpha(
    y: np.ndarray,
    background: np.ndarray,
    eta: np.ndarray,
    h: np.ndarray,
    label: np.ndarray,
    signatures: np.ndarray,
    *,
    start: np.ndarray | None = None,
    n_iter: int = 3,
) -> np.ndarray:
    """Empirical-Bayes shape ``alpha_k`` of the reflectivity: ``1 / CV**2`` seen in the data.

    Under the model the counts of surface s at wavelength l have mean
    ``mu = lam + b`` (``lam = eta h m_{u_s,l}``, the signature at the surface's shading)
    and, integrating the reflectivity out, variance ``mu + v lam**2`` with
    ``v = Var(r) / m**2`` the within-class spectral variability (``1 / alpha`` for a
    gamma of shape alpha about the signature). ``v_k`` is the weighted moment estimate
    ``sum w ((y - mu)**2 - y) / sum w lam**2`` (Poisson noise removed by the count
    itself, unbiased whatever mu; ``- mu`` leaves a first-order bias ``E y - mu``, weights
    ``lam**2 / (mu + v lam**2)**2``, the inverse variances, iterated ``n_iter`` times
    from ``start``), pooled towards the estimate over all classes with a pseudo-weight
    of 5 % of an average class, and ``alpha_k = 1 / v_k`` kept in [1.5, 1000].
    ``h`` and ``label`` should not be fitted to the surface's own counts: a label chosen
    on ``y`` follows its noise where classes are close, and the dispersion about its
    signature is then below Poisson (``reconstruct`` passes the neighbours' shading; its
    labels are chosen on y, which its std's label term makes up for).

    Parameters
    ----------
    y, background, eta : ndarray (S, L)
        Own-pixel counts, expected background and IRF fraction over each support.
    h : ndarray (S,)
        Shading (the MRF-smoothed scale of each surface).
    label : ndarray (S,), int
    signatures : ndarray (K, L)
    start : ndarray (K,), optional
        Starting alpha per class (default 6).
    n_iter : int

    Returns
    -------
    alpha : ndarray (K, L), the same value on every wavelength of a class.

    Raises
    ------
    SplidarError
        ``y``, ``background`` and ``eta`` not of one shape (S, L); ``h`` or ``label``
        not (S,); ``signatures`` not (K, L); a label outside ``0..K-1``.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> m = np.ones((1, 2)); r = rng.gamma(4.0, 0.25, size=(20000, 2))  # CV 0.5
    >>> y = rng.poisson(20 * r).astype(float)
    >>> a = estimate_alpha(y, np.zeros_like(y), np.ones_like(y), np.full(20000, 20.0),
    ...                    np.zeros(20000, np.int64), m)
    >>> bool(3.6 < a[0, 0] < 4.4)
    True
    """
    sig = np.asarray(signatures, dtype=np.float64)
    y = np.ascontiguousarray(y, np.float64)
    if sig.ndim != 2 or y.ndim != 2 or sig.shape[1] != y.shape[1]:
        raise SplidarError(
            f"`signatures` must be (K, L) and `y` (S, L) with the same L; got {sig.shape} and "
            f"{y.shape}."
        )
    for name, a in (("background", background), ("eta", eta)):
        if np.shape(a) != y.shape:
            raise SplidarError(f"`{name}` must have the shape of `y` {y.shape}; got {np.shape(a)}.")
    for name, a in (("h", h), ("label", label)):
        if np.shape(a) != y.shape[:1]:
            raise SplidarError(
                f"`{name}` must be ({y.shape[0]},), one per surface; got {np.shape(a)}."
            )
    if y.shape[0] and (np.min(label) < 0 or np.max(label) >= sig.shape[0]):
        raise SplidarError(
            f"`label` must index the {sig.shape[0]} signatures (0..{sig.shape[0] - 1}); got values "
            f"{int(np.min(label))}..{int(np.max(label))}."
        )
    K, L = sig.shape
    lo, hi = _ALPHA_BOUNDS
    v = 1.0 / (np.full(K, 6.0) if start is None else np.asarray(start, dtype=np.float64))
    b = np.ascontiguousarray(background, np.float64)
    eta = np.ascontiguousarray(eta, np.float64)
    h = np.ascontiguousarray(h, np.float64)
    label = np.ascontiguousarray(label, np.int64)
    # the scale between h and r is set only weakly by the priors: measure the dispersion
    # about each class's signature at the class's mean brightness in the data
    pred = np.bincount(label, (eta * h[:, None] * sig[label]).sum(1), minlength=K)
    net = np.bincount(label, (y - b).sum(1), minlength=K)
    scale = np.where((pred > 0) & (net > 0), net / np.where(pred > 0, pred, 1.0), 1.0)
    sig = sig * scale[:, None]
    num = np.zeros(K)
    den = np.zeros(K)
    for _ in range(n_iter):
        kern.dispersion_sums(y, b, eta, h, label, sig, v, num, den)
        d_tot = den.sum()
        if not d_tot > 0:
            break
        pooled = num.sum() / d_tot
        d0 = 0.05 * d_tot / K
        v = np.clip((num + d0 * pooled) / (den + d0), 1.0 / hi, 1.0 / lo)
    return np.repeat((1.0 / v)[:, None], L, axis=1)


def _label_spread(y, b, eta, h, r, u, u_alt, alpha, ups, eps, sig) -> np.ndarray:
    """Squared spread of the intensity over the labels chosen on resampled data, (S, L).

    ``sum_j (h r_{k_j} - h r)**2 / n`` over the ``n`` alternative labels ``k_j =
    u_alt[j, s]`` (labels drawn from the label posterior), ``r_k`` the joint mode of (r, beta,
    EM split) under class k at the surface's h (``_kernels.label_spread``; 0 where
    ``k_j = u_s``): the between-class part of the intensity's variance when the label
    changes as often as it does between halves of the data.
    """
    out = np.zeros_like(r)
    kern.label_spread(
        y, b, eta, h, r, u, np.ascontiguousarray(u_alt), alpha, ups, eps,
        np.ascontiguousarray(sig, np.float64), out,
    )  # fmt: skip
    return out


def _split_variability(alpha_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, upsilon) whose compound prior of r has relative variance ``1 / alpha_v``.

    ``r ~ G(alpha, beta)``, ``beta ~ IG(upsilon, eps)`` with mean ``m``: ``CV**2 = (alpha
    + 1)(upsilon - 1) / (alpha (upsilon - 2)) - 1 ~ 1/alpha + 1/(upsilon - 2)``; half of
    the variance each: ``alpha = 2 / v``, ``upsilon = 2 + 2 / v``.
    """
    v = 1.0 / alpha_v
    return 2.0 / v, 2.0 + 2.0 / v


def _posterior_intensity(
    y, eta, z, q, r, beta, h, u, alpha, ups, eps, graph, rho, w, marginal, var_h=None
):
    """Intensity (MAP, ``h r``) and posterior std (see :func:`kern.posterior`)."""
    inten = np.empty_like(r)
    std = np.empty_like(r)
    var_h = np.zeros(0) if var_h is None else np.ascontiguousarray(var_h, np.float64)
    kern.posterior(
        y, eta, z, q, r, beta, h, w, u, alpha, ups, eps, graph.indptr, graph.indices, rho,
        bool(marginal), var_h, inten, std,
    )  # fmt: skip
    return inten, std


@functools.lru_cache(maxsize=1)
def _lattice_tables(n: int = 128):
    """Fourier averages of the linearised gamma-MRF on a 4-neighbour lattice.

    In ``x = log h`` each MRF link is a spring of precision rho (the curvature of
    ``rho (x - log w - h / w)`` at ``h = w``); integrating w out leaves, per closed
    neighbourhood N[j] (5 sites), ``rho / 2 sum_{i in N[j]} (x_i - mean)**2``, whose
    Fourier symbol is ``rho q(k)``, ``q = 5 - (1 + 2 cos k1 + 2 cos k2)**2 / 5``. With N
    photons' worth of data per site the MAP is the linear smoother ``N / (N + rho q)``;
    per unit ``t = N / rho`` returns the grid ``t`` and the lattice means of
    ``t / (t + q)**2`` (its sampling variance times rho) and ``(q / (t + q))**2`` (the
    noise left in ``x_raw - x_map``).
    """
    k = 2.0 * np.pi * np.arange(n) / n
    phi = 1.0 + 2.0 * np.cos(k)[:, None] + 2.0 * np.cos(k)[None, :]
    q = (5.0 - phi**2 / 5.0).ravel()
    t = np.logspace(-4.0, 5.0, 181)
    sw = np.array([np.mean(ti / (ti + q) ** 2) for ti in t])
    ka = np.array([np.mean((q / (ti + q)) ** 2) for ti in t])
    return np.log(t), sw, ka


def _h_variance_eb(y, b, eta, r, h, alpha_u, graph, rho, n_iter: int = 5):
    """Empirical-Bayes mean squared error of the MAP shading: ``h**2 (V_s + B)``.

    ``V_s`` is the sampling variance of ``log h_s`` under the linearised MRF smoother
    (:func:`_lattice_tables`) with ``N_s = sum_l n alpha / (n + alpha)`` photons of
    information (``n = lam**2 / (lam + b)``, the Fisher information of the log intensity,
    combined with r's prior precision alpha in the log) and the coupling scaled by the
    surface's links, ``rho (1 + deg) / 5``. ``B`` is the mean squared smoothing bias (relative),
    one number per scene: the raw shading ``h_raw = sum_l (y - b) / sum_l eta r`` differs
    from the MAP by bias plus the part ``kappa_s`` of its noise ``nv_s`` the smoother
    leaves, so ``B`` is the weighted moment estimate of ``(h_raw / h - 1)**2 - kappa_s
    nv_s`` (weights ``1 / (kappa nv + B)**2``, iterated), floored at 0. Surfaces without
    links get the data's variance ``1 / N_s``. Returns ``(var_h (S,), B)``.
    """
    var0, N, ok, e2, knv = _h_variance_parts(y, b, eta, r, h, alpha_u, graph, rho)
    B = _shading_bias2(e2, knv, n_iter)
    return _h_variance_with(h, var0, N, ok, B), B


def _h_variance_parts(y, b, eta, r, h, alpha_u, graph, rho):
    """The per-surface parts of :func:`_h_variance_eb`: ``(V, N, ok, e2, knv)``, the last
    two for the linked surfaces (``ok``) only (what the estimate of ``B`` needs)."""
    deg = np.diff(graph.indptr)
    lam = eta * h[:, None] * r
    n = lam * lam / np.maximum(lam + b, 1e-300)
    n = n * alpha_u / (n + alpha_u)
    N = np.maximum(n.sum(axis=1), 1e-12)
    rho_e = rho * (1.0 + deg) / 5.0
    lt, sw, ka = _lattice_tables()
    x = np.log(N / rho_e)
    V = np.interp(x, lt, sw) / rho_e
    kappa = np.interp(x, lt, ka)
    E = np.maximum((eta * r).sum(axis=1), 1e-300)
    e = ((y - b).sum(axis=1) / E - h) / h
    nv = (lam + b).sum(axis=1) / (E * h) ** 2  # expected Poisson variance of h_raw / h
    ok = deg > 0
    return V, N, ok, e[ok] ** 2, (kappa * nv)[ok]


def _shading_bias2(e2, knv, n_iter: int = 5) -> float:
    """``B`` of :func:`_h_variance_eb` from the linked surfaces' ``e2`` and ``knv``."""
    B = 0.0
    if e2.size:
        B = float(np.mean(np.maximum(e2 - knv, 0.0)))  # start
        for _ in range(n_iter):
            wgt = 1.0 / (knv + B + 1e-12) ** 2
            B = max(float(np.sum(wgt * (e2 - knv)) / np.sum(wgt)), 0.0)
    return B


def _h_variance_with(h, V, N, ok, B) -> np.ndarray:
    return h**2 * np.where(ok, V + B, 1.0 / N)


def kmeans_signatures(
    intensity: np.ndarray, n_classes: int, *, rng=None, n_iter: int = 50
) -> np.ndarray:
    """Class signatures found from the data: weighted k-means on normalised spectra.

    Spectra ``x = max(intensity, 0)`` are normalised to sum 1 and clustered with
    k-means++ seeding (``rng``), each weighted by its total photons (a spectrum of more
    photons is a more reliable shape). A signature is the cluster's mean shape times the
    mean total intensity of its members.

    Returns
    -------
    signatures : ndarray (n_classes, L), positive.
    """
    rng = np.random.default_rng(rng)
    x = np.maximum(np.asarray(intensity, dtype=np.float64), 0.0)
    tot = x.sum(axis=1)
    ok = tot > 0
    if np.count_nonzero(ok) < n_classes:
        raise SplidarError(
            f"`n_classes` = {n_classes} but only {int(np.count_nonzero(ok))} surface(s) carry "
            "signal; ask for fewer classes or pass a library."
        )
    xs = x[ok] / tot[ok, None]
    wt = tot[ok]
    # k-means++ seeding
    centres = [xs[rng.choice(xs.shape[0], p=wt / wt.sum())]]
    for _ in range(1, n_classes):
        d2 = np.min(((xs[:, None, :] - np.array(centres)[None]) ** 2).sum(-1), axis=1) * wt
        p = d2 / d2.sum() if d2.sum() > 0 else wt / wt.sum()
        centres.append(xs[rng.choice(xs.shape[0], p=p)])
    c = np.array(centres)
    lab = np.zeros(xs.shape[0], np.int64)
    for _ in range(n_iter):
        lab_new = np.argmin(((xs[:, None, :] - c[None]) ** 2).sum(-1), axis=1)
        for k in range(n_classes):
            sel = lab_new == k
            if np.any(sel):
                c[k] = np.average(xs[sel], axis=0, weights=wt[sel])
        if np.array_equal(lab_new, lab):
            break
        lab = lab_new
    sig = np.empty_like(c)
    for k in range(n_classes):
        sel = lab == k
        scale = tot[ok][sel].mean() if np.any(sel) else tot[ok].mean()
        sig[k] = c[k] * scale
    return _floor_signatures(sig)


def _floor_signatures(sig: np.ndarray) -> np.ndarray:
    # a zero signature value would make the gamma prior degenerate (eps = 0)
    floor = 1e-3 * sig.max(axis=1, keepdims=True)
    return np.maximum(sig, np.maximum(floor, 1e-12))


def _as_class_array(x, name: str, K: int, L: int, *, minimum: float) -> np.ndarray:
    a = as_float_array(x, name)
    try:
        a = np.broadcast_to(a, (K, L)).astype(np.float64)
    except ValueError:
        raise SplidarError(
            f"`{name}` must be a number or an array broadcastable to (K, L) = ({K}, {L}); "
            f"got shape {np.shape(x)}."
        ) from None
    if np.any(a <= minimum):
        raise SplidarError(f"`{name}` must be > {minimum:g}; got min {a.min():g}.")
    return a


#: numba's parallel kernels may not be entered from two threads at once when its only
#: threading layer is "workqueue" (no OpenMP or TBB): reconstructions run one at a time.
_KERNEL_LOCK = threading.RLock()


def _own_running() -> int:
    """Threads of this process that are runnable now (``/proc/self/task/*/stat``)."""
    n = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                stat = f.read()
        except OSError:  # the thread ended meanwhile
            continue
        n += stat[stat.rindex(")") + 2] == "R"
    return n


def _free_cores(n_max: int) -> int:
    """Threads worth using now: at most ``n_max``, fewer when other processes hold cores.

    A numba parallel region waits for its slowest thread, so a thread that has to share
    its core stalls every region (~25 per sweep). Measured on the 2-core machine,
    Art-size scene (84,577 surfaces, 9 sweeps) with one busy process besides other
    helpers' work: 2 threads 0.26-3.1 s (median 0.5), 1 thread 0.24-0.51 s; idle: 2
    threads 0.16 s, 1 thread 0.25 s. So ``cores - others`` threads (at least 1), with
    ``others`` the runnable threads of other processes (``/proc/loadavg`` less this
    process's own runnable threads), the smallest of 3 samples 0.2 ms apart, so that
    only persistently busy processes count (elsewhere than Linux: ``n_max``).
    """
    try:
        others = None
        for i in range(3):
            if i:
                time.sleep(2e-4)
            with open("/proc/loadavg") as f:
                running = int(f.read().split()[3].split("/")[0])
            n = max(running - _own_running(), 0)
            others = n if others is None else min(others, n)
    except (OSError, ValueError, IndexError):
        return n_max
    cores = os.cpu_count() or n_max
    return max(1, min(n_max, cores - others))


def _one_at_a_time(func):
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with _KERNEL_LOCK:
            n_max = numba.get_num_threads()
            n = _free_cores(n_max)
            numba.set_num_threads(n)
            try:
                return func(*args, **kwargs)
            finally:
                numba.set_num_threads(n_max)

    return wrapper


@dataclass(frozen=True)
class _Setup:
    """Checked options and the per-surface data of one reconstruction."""

    classes: str
    lib: object
    sig: np.ndarray
    signature_scale: str
    links: str
    gate: float
    fwhm: np.ndarray
    y: np.ndarray
    b: np.ndarray
    eta: np.ndarray
    intensity_raw: np.ndarray


def _check_options(
    detection, gamma, rho, max_iter, tol, links, signature_scale, classes, n_classes
):
    if not isinstance(detection, Detection):
        raise SplidarError(
            f"`detection` must be a splidar Detection (the output of splidar.detect); got "
            f"{type(detection).__name__}."
        )
    out = {
        "gamma": check_positive(gamma, "gamma", allow_zero=True),
        "rho": check_positive(rho, "rho"),
        "max_iter": check_int(max_iter, "max_iter", minimum=1),
        "tol": check_positive(tol, "tol"),
    }
    if isinstance(links, str):
        links = check_choice(links, "links", _LINKS)
    else:
        try:
            gate = float(links)
        except (TypeError, ValueError):
            raise SplidarError(
                f"`links` must be 'depth', 'all' or a depth gate in bins (a number > 0); got "
                f"{links!r}."
            ) from None
        links = check_positive(gate, "links")
    if signature_scale is not None:
        signature_scale = check_choice(signature_scale, "signature_scale", ("shape", "absolute"))
    if classes is not None:
        classes = check_choice(classes, "classes", _CLASSES)
    if n_classes is not None:
        n_classes = check_int(n_classes, "n_classes", minimum=1)
    out.update(links=links, signature_scale=signature_scale, classes=classes, n_classes=n_classes)
    return out


def _resolve_classes(detection, library, classes, n_classes):
    """(classes, library or None) from the options (see ``reconstruct``'s ``classes``)."""
    L = detection.n_wavelengths
    lib = as_library(library, n_wavelengths=L) if library is not None else None
    if lib is None and classes in (None, "library"):
        lib = detection.library
    if classes is None:
        classes = "library" if lib is not None else ("cluster" if n_classes else "one")
    if classes == "library" and lib is None:
        raise SplidarError(
            "`classes='library'` needs a library: pass library= (array (K, L), file or "
            "SpectralLibrary), or use classes='one' or classes='cluster' with n_classes=."
        )
    if classes == "cluster" and n_classes is None:
        raise SplidarError("`classes='cluster'` needs `n_classes` (the number of classes to find).")
    return classes, (lib if classes == "library" else None)


def _surface_data(detection, irf):
    """Own-pixel counts y, background b, IRF fraction eta (S, L) and ``(y - b) / eta``."""
    surf = detection.surfaces
    S, L = len(surf), detection.n_wavelengths
    y = np.asarray(surf.counts, dtype=np.float64).reshape(S, L)
    b = np.asarray(surf.background, dtype=np.float64).reshape(S, L)
    if np.any(y < 0) or np.any(b < 0):
        raise SplidarError("`detection.surfaces.counts` and `.background` must be non-negative.")
    eta = irf_fraction(irf, surf.depth_bin, surf.start, surf.stop) if S else np.zeros((0, L))
    # a support that holds (almost) none of its IRF carries no information on the
    # intensity: (y - b) / eta would blow the noise up by 1 / eta. The floor keeps the
    # division finite; such surfaces are reported, not hidden
    n_off = int(np.count_nonzero((eta < 0.01).any(axis=1))) if S else 0
    if n_off:
        log.warning(
            "%d of %d surfaces hold less than 1 %% of their IRF inside their support "
            "[start, stop) (depth outside it?): their intensities are unreliable. Check "
            "detection.surfaces.depth_bin against start / stop.",
            n_off,
            S,
        )
    eta = np.maximum(eta, 1e-6)
    return y, b, eta, (y - b) / eta


def _setup(detection, library, opt, rng) -> _Setup:
    classes, lib = _resolve_classes(detection, library, opt["classes"], opt["n_classes"])
    L = detection.n_wavelengths
    irf = np.atleast_2d(np.asarray(detection.irf, dtype=np.float64))
    fwhm = irf_fwhm(irf)
    links = opt["links"]
    if links == "all":
        gate = float("inf")
    elif links == "depth":
        gate = 3.0 * float(fwhm.max())
    else:  # a number: the depth gate in bins
        links, gate = "depth", float(links)
    y, b, eta, intensity_raw = _surface_data(detection, irf)
    S = y.shape[0]
    if classes == "library":
        sig = lib.signatures
    elif classes == "one":
        sig = _floor_signatures(
            np.maximum(intensity_raw, 0).mean(axis=0, keepdims=True) if S else np.ones((1, L))
        )
    else:
        sig = kmeans_signatures(intensity_raw, opt["n_classes"], rng=rng)
    scale = opt["signature_scale"] or ("shape" if L > 1 else "absolute")
    if scale == "shape":
        # classes differ by the shape of their spectra only; h carries the brightness
        sig = sig / sig.mean(axis=1, keepdims=True)
    return _Setup(classes, lib, sig, scale, links, gate, fwhm, y, b, eta, intensity_raw)


def _prior_arrays(alpha, upsilon, sig):
    """(auto, alpha, upsilon, eps) arrays (K, L): ``E[beta] = m / alpha``, so ``E[r] = m``."""
    K, L = sig.shape
    auto_alpha = isinstance(alpha, str)
    if auto_alpha:
        check_choice(alpha, "alpha", ("auto",))
        alpha_a = np.full((K, L), 6.0)
    else:
        alpha_a = _as_class_array(alpha, "alpha", K, L, minimum=1.0)
    ups_a = _as_class_array(upsilon, "upsilon", K, L, minimum=1.0)
    return auto_alpha, alpha_a, ups_a, sig * (ups_a - 1.0) / alpha_a


def _start(su: _Setup, u):
    """r at its prior mean, beta at ``m / alpha`` (caller), h fitting the net counts."""
    sig, y, b, eta = su.sig, su.y, su.b, su.eta
    r = sig[u].copy()
    # h fitting the net counts of the support: sum_l (y - b) / sum_l eta m
    h = np.maximum((y - b).sum(axis=1), 0.0) / (eta * sig[u]).sum(axis=1)
    pos = h[h > 0]
    h = np.maximum(h, 0.1 * (np.median(pos) if pos.size else 1.0))
    return r, h, h.copy()


def _sweep_start(su: _Setup, u, prior, max_iter) -> dict:
    """The sweeps' state before the first sweep (``r, beta, h, w`` and the history)."""
    r, h, w = _start(su, u)
    S, L = su.y.shape
    return dict(
        r=r, beta=su.sig[u] / prior[1][u], h=h, w=w, n_iter=0, alpha_updates=[],
        obj=np.zeros(max_iter + 1), change=np.zeros(max_iter),
        n_changed=np.zeros(max_iter, np.int64),
    )  # fmt: skip


def _run_phase(su: _Setup, graph, u, st, prior, rho, gamma, n_max, tol) -> None:
    """``n_max`` sweeps at most (``kern.run``) from ``st``, updated in place."""
    auto, alpha_a, ups_a, eps_a = prior
    S, L = su.y.shape
    n = st["n_iter"]
    st["z"], st["q"] = np.empty((S, L)), np.empty((S, L))
    st["n_iter"] += kern.run(
        su.y, su.b, su.eta, graph.parity, graph.indptr, graph.indices, alpha_a, ups_a, eps_a,
        rho, gamma, n_max, tol, False, st["r"], st["beta"], st["h"], st["w"], u, np.ones(S),
        st["z"], st["q"], st["obj"][n:], st["change"][n:], st["n_changed"][n:], _INNER,
        _HW_PASSES, int(tol * S), _OBJ_EVERY,
    )  # fmt: skip


def _phase_one(su: _Setup, graph, u, st, prior, rho, gamma, max_iter, tol) -> None:
    """The first phase of :func:`_sweeps`: with ``alpha="auto"`` (``prior[0]``) at the
    starting alpha, at most ``max_iter // 2`` sweeps, stopped at ``10 tol``; else the
    only phase."""
    if su.y.shape[0]:
        tol1 = tol * _PHASE1_TOL if prior[0] else tol
        n_max = max(max_iter // 2, 1) if prior[0] else max_iter
        _run_phase(su, graph, u, st, prior, rho, gamma, n_max, tol1)


def _neighbour_shading(graph, h) -> np.ndarray:
    """Mean ``h`` of each surface's linked neighbours (0 without links)."""
    out = np.empty(h.shape[0])
    kern.neighbour_mean(np.ascontiguousarray(h, np.float64), graph.indptr, graph.indices, out)
    return out


def _phase_two(su: _Setup, graph, u, st, prior, rho, gamma, max_iter, tol, eb=None):
    """The second phase of :func:`_sweeps` (``alpha="auto"``): the empirical-Bayes
    ``(alpha, upsilon)`` (from these surfaces, or ``eb``), a warm start under them, the
    sweeps. Returns the new prior ``(True, alpha, upsilon, eps)``."""
    y, b, eta, sig = su.y, su.b, su.eta, su.sig
    # empirical Bayes: the prior of r as wide as the data say, labels kept
    if eb is None:
        h_nb = _neighbour_shading(graph, st["h"])
        alpha_a, ups_a = _split_variability(estimate_alpha(y, b, eta, h_nb, u, sig))
    else:
        alpha_a, ups_a = eb
    eps_a = sig * (ups_a - 1.0) / alpha_a
    # warm start under the new prior: r at its prior joint mode with beta, r =
    # m (alpha - 1)(upsilon - 1) / (alpha (upsilon + 2)) (near the signature when
    # the prior is tight), h keeping each surface's expected signal sum_l eta h r,
    # w and beta their conditional modes. Measured: the second phase then takes
    # 2-4 sweeps instead of 5-8 (same result within tol).
    r0 = (sig * (alpha_a - 1.0) * (ups_a - 1.0) / (alpha_a * (ups_a + 2.0)))[u]
    st["h"] = (eta * st["h"][:, None] * st["r"]).sum(axis=1) / (eta * r0).sum(axis=1)
    st["r"] = np.ascontiguousarray(r0)
    kern.update_w(st["h"], graph.indptr, graph.indices, st["w"])
    st["beta"] = (st["r"] + eps_a[u]) / (alpha_a + ups_a + 1.0)[u]
    st["alpha_updates"].append(st["n_iter"])
    prior = (True, alpha_a, ups_a, eps_a)
    if st["n_iter"] < max_iter:
        _run_phase(su, graph, u, st, prior, rho, gamma, max_iter - st["n_iter"], tol)
    return prior


def _sweeps_end(su: _Setup, st, tol):
    """The last E-step and the history; returns ``(state, history)``."""
    n_iter = st["n_iter"]
    if su.y.shape[0]:
        converged = bool(st["change"][n_iter - 1] < tol) if n_iter else False
        reason = "tol" if converged else "max_iter"
        S, L = su.y.shape
        z, q = np.empty((S, L)), np.empty((S, L))
        kern.estep(su.y, su.b, su.eta, st["r"], st["h"], z, q)
    else:
        converged, reason = True, "no surfaces"
        z, q = np.empty((0, su.y.shape[1])), np.empty((0, su.y.shape[1]))
    history = ConvergenceHistory(
        objective=st["obj"][: n_iter + 1].copy(),
        change=st["change"][:n_iter].copy(),
        label_changes=st["n_changed"][:n_iter].copy(),
        n_iter=int(n_iter),
        converged=converged,
        reason=reason,
        alpha_updates=tuple(st["alpha_updates"]),
    )
    state = {"r": st["r"], "beta": st["beta"], "h": st["h"], "w": st["w"], "z": z, "q": q}
    return state, history


def _sweeps(su: _Setup, graph, u, prior, rho, gamma, max_iter, tol, eb=None):
    """Coordinate descent with the labels fixed: one phase, or two with ``alpha="auto"``
    (:func:`_phase_one`, :func:`_phase_two`; the tiled run calls them in separate tasks).

    ``eb``: the ``(alpha, upsilon)`` arrays (K, L) the empirical-Bayes step uses instead of
    estimating them from these surfaces.
    Returns ``(state dict, prior (auto, alpha, ups, eps), history)``.
    """
    st = _sweep_start(su, u, prior, max_iter)
    _phase_one(su, graph, u, st, prior, rho, gamma, max_iter, tol)
    if prior[0] and su.y.shape[0]:
        prior = _phase_two(su, graph, u, st, prior, rho, gamma, max_iter, tol, eb)
    state, history = _sweeps_end(su, st, tol)
    return state, prior, history


def _intensity_and_std(su: _Setup, graph, u, marginals, state, prior, rho, rng, bias2=None):
    """Posterior intensity and its std (with the label term when K > 1 and "auto").

    ``bias2``: the smoothing-bias term ``B`` to use (a tiled run's, estimated on every
    strip) instead of estimating it from these surfaces."""
    y, b, eta, sig = su.y, su.b, su.eta, su.sig
    auto_alpha, alpha_a, ups_a, eps_a = prior
    st = state
    S = y.shape[0]
    var_h = None
    if auto_alpha and S:
        if bias2 is None:
            var_h, bias2 = _h_variance_eb(y, b, eta, st["r"], st["h"], alpha_a[u], graph, rho)
        else:
            V, N, ok, _, _ = _h_variance_parts(y, b, eta, st["r"], st["h"], alpha_a[u], graph, rho)
            var_h = _h_variance_with(st["h"], V, N, ok, bias2)
    intensity, std = _posterior_intensity(
        y, eta, st["z"], st["q"], st["r"], st["beta"], st["h"], u, alpha_a, ups_a, eps_a,
        graph, rho, st["w"], auto_alpha, var_h,
    )  # fmt: skip
    if auto_alpha and S and sig.shape[0] > 1:
        # the label's own uncertainty: two labels drawn from its marginal posterior
        cum = np.cumsum(marginals, axis=1)
        draws = rng.random((2, S, 1))
        u_alt = np.minimum((draws > cum[None]).sum(axis=2), sig.shape[0] - 1)
        spread = _label_spread(y, b, eta, st["h"], st["r"], u, u_alt, alpha_a, ups_a, eps_a, sig)
        std = np.sqrt(std**2 + spread)
    return intensity, std, bias2


def _result(detection, su: _Setup, graph, u, conf, intensity, std, history, hyper, timings):
    surf = detection.surfaces
    depth_m = None
    if detection.bin_width_ps is not None:
        depth_m = surf.depth_bin * detection.bin_width_ps * 1e-12 * SPEED_OF_LIGHT / 2.0
    points = PointSet(
        row=surf.row,
        col=surf.col,
        depth_bin=surf.depth_bin,
        image_shape=surf.image_shape,
        intensity=intensity,
        label=u,
        depth_m=depth_m,
        intensity_std=std,
        label_confidence=conf,
        layer=surf.slot,
    )
    maps = points.maps(n_layers=int(surf.n_slots))
    return Reconstruction(
        points=points,
        depth_map=maps["depth_bin"],
        intensity_map=maps["intensity"],
        label_map=maps["label"],
        library=su.lib,
        history=history,
        hyperparameters=hyper,
        timings=timings,
        detection=detection,
    )


def _hyperparameters(su, opt, prior, pi, bias2, graph) -> dict:
    """What a reconstruction used and estimated, for ``Reconstruction.hyperparameters``."""
    auto_alpha, alpha_a, ups_a, eps_a = prior
    return {
        "classes": su.classes,
        "n_classes": int(su.sig.shape[0]),
        "signatures": su.sig.copy(),
        "signature_scale": su.signature_scale,
        "gamma": opt["gamma"],
        "class_proportions": pi,
        "rho": opt["rho"],
        "alpha": alpha_a,
        "alpha_mode": "auto" if auto_alpha else "fixed",
        "shading_bias2": bias2,
        "upsilon": ups_a,
        "epsilon": eps_a,
        "links": su.links,
        "depth_gate": su.gate,
        "irf_fwhm": su.fwhm,
        "max_iter": opt["max_iter"],
        "tol": opt["tol"],
        "n_links": graph.n_edges,
    }


@_one_at_a_time
def _labels(su: _Setup, surf, gamma, rng, graph):
    """(labels, marginals, class proportions, strength used) of the surfaces
    (``classify_surfaces`` on the label field's graph: the sweeps' ``graph`` with the
    links that bridge one-pixel gaps in the detections; the strength is the chains' mean
    of the estimated one, ``None`` for one class)."""
    S, K = len(surf), su.sig.shape[0]
    if K == 1:
        return np.zeros(S, np.int64), np.ones((S, 1)), np.ones(1), None
    cgraph = with_bridges(
        graph, surf.row, surf.col, surf.slot, surf.depth_bin, surf.image_shape, int(surf.n_slots)
    )
    cls = classify_surfaces(
        su.y, su.b, su.eta, su.sig, cgraph, gamma=gamma, seed=int(rng.integers(2**31))
    )
    return cls.label, cls.marginals, cls.proportions, float(cls.gamma)


def reconstruct(
    detection: Detection,
    *,
    library=None,
    classes: str | None = None,
    n_classes: int | None = None,
    gamma: float = GAMMA,
    rho: float = 4.0,
    alpha: float | np.ndarray | str = "auto",
    upsilon: float | np.ndarray = 3.0,
    signature_scale: str | None = None,
    links: str | float = "depth",
    max_iter: int = 200,
    tol: float = 1e-3,
    rng=0,
) -> Reconstruction:
    r"""Bayesian reconstruction and spectral classification of detected surfaces (Algorithm 2).

    Model (for surface s at wavelength l, class ``k = u_s``)::

        y_{s,l} ~ Poisson(eta_{s,l} h_s r_{s,l} + b_{s,l})       own-pixel counts over the support
        r_{s,l} ~ Gamma(alpha_{k,l}, scale beta_{s,l})           eq:4.4
        beta_{s,l} ~ InvGamma(upsilon_{k,l}, eps_{k,l})          eq:4.3
        (h, w) ~ gamma-MRF over the surface graph, coupling rho  eq:4hafter
        u ~ Potts(gamma) over the same graph                     eqt:priorLabels2

    With K > 1 classes the labels come first, from the photon counts
    (:func:`splidar.reconstruction.classify_surfaces`: a class likelihood with the
    brightness integrated out, EM class proportions, and label marginals of the Potts
    field over the depth-gated graph by Swendsen-Wang sampling); ``label`` is the most
    probable marginal class and ``label_confidence`` its marginal probability
    (calibrated: ``docs/classification.md``). The intensities are then the posterior
    modes given the labels, by coordinate descent (``eqt:Modes_Param_top``,
    ``eqt:Modes_Param_bottom``), with a posterior std (notes: module ``_core.py``).
    A Dask cube's detection too large for one strip is reconstructed on overlapping
    strips of rows, one Dask task each (``docs/distributed.md``: margin, tolerance, seeds).

    Parameters
    ----------
    detection : Detection
        Output of :func:`splidar.detect`; uses ``detection.surfaces`` and ``detection.irf``.
    library : SpectralLibrary, array (K, L), path, optional
        Spectral signatures ``m_{k,l}``; defaults to ``detection.library``.
    classes : {"library", "one", "cluster"}, optional
        Where classes come from. Default: ``"library"`` when a library is given or carried
        by the detection, ``"cluster"`` when only ``n_classes`` is given, else ``"one"``
        (a single class whose signature is the mean spectrum: intensity smoothing only).
    n_classes : int, optional
        Number of classes for ``classes="cluster"`` (weighted k-means on normalised
        spectra, seeded by ``rng``; see :func:`kmeans_signatures`).
    gamma : float
        Interaction strength of the label field, nats per link (>= 0; default 1.5, a
        rule independent of the scene: see :func:`splidar.reconstruction.link_gamma`).
        The sampler's two chains run at it (since session 11; before, at strengths
        spread about it, :func:`splidar.reconstruction.chain_gammas`) and each link is
        weakened where the photons show a boundary
        (:func:`splidar.reconstruction.link_contrast`).
    rho : float
        gamma-MRF coupling (> 0); larger smooths h more.
    alpha : float, array (K, L) or "auto"
        Gamma shape of r (> 1, so that the mode of r is positive), or ``"auto"``
        (default: empirical Bayes per class after a first phase at alpha = 6, see the
        module notes). A number keeps alpha (and upsilon) fixed: one phase.
    upsilon : float or array (K, L)
        Inverse-gamma shape of beta (> 1, so that its mean exists); replaced by the
        estimate with ``alpha="auto"``.
    signature_scale : {"shape", "absolute"}, optional
        ``"shape"`` (default when L > 1): signatures divided by their mean over
        wavelengths, classes told apart by the shape of their spectra, h carrying all
        brightness; ``"absolute"`` (default when L = 1) keeps the library's magnitudes.
    links : {"depth", "all"} or float
        ``"all"``: each surface linked to every surface of its 4 neighbour pixels (paper).
        ``"depth"``: only links whose depth difference is at most 3 x the widest IRF
        FWHM; a number: that depth gate, in bins (the former ``depth_gate=``).
    max_iter : int
        I_max (>= 1).
    tol : float
        xi of ``eq:criter``: stop when the RMS change of ``h r`` relative to its RMS is
        below ``tol`` (with ``alpha="auto"`` the first phase stops at ``10 tol``).
    rng : None, int or Generator, default 0
        Seeds k-means for ``classes="cluster"``, the label sampler (K > 1) and the label
        draws behind the std's label term. The default, a fixed seed, makes the same input
        give the same result; ``None`` draws fresh entropy.

    Returns
    -------
    Reconstruction
        ``timings`` holds ``"setup"``, ``"classify"``, ``"iterations"``, ``"outputs"``
        and ``"total"`` (s); ``hyperparameters["class_proportions"]`` the EM proportions.

    Raises
    ------
    SplidarError
        A library whose L differs from the data, gamma < 0, rho <= 0, alpha <= 1,
        upsilon <= 1, max_iter < 1, tol <= 0, unknown ``links``, ``classes`` or
        ``signature_scale``, a string ``alpha`` other than ``"auto"``,
        ``classes="cluster"`` without ``n_classes``, or a non-Detection input.

    Examples
    --------
    >>> from splidar.reconstruction import synthetic_detection
    >>> det, truth = synthetic_detection(shape=(8, 8), rng=0)
    >>> rec = reconstruct(det, library=det.library)
    >>> rec.points.intensity.shape == (len(truth), det.n_wavelengths)
    True
    """
    t0 = time.perf_counter()
    opt = _check_options(
        detection, gamma, rho, max_iter, tol, links, signature_scale, classes, n_classes
    )
    rng = np.random.default_rng(rng)
    su = _setup(detection, library, opt, rng)
    prior = _prior_arrays(alpha, upsilon, su.sig)
    surf = detection.surfaces
    graph = build_graph(
        surf.row, surf.col, surf.slot, surf.depth_bin, surf.image_shape, int(surf.n_slots),
        links=su.links, gate=su.gate,
    )  # fmt: skip
    t_graph = time.perf_counter()
    S = len(surf)
    u, marg, pi, label_gamma = _labels(su, surf, opt["gamma"], rng, graph)
    conf = marg.max(axis=1) if S else np.ones(0)
    t_cls = time.perf_counter()
    state, prior, history = _sweeps(
        su, graph, u, prior, opt["rho"], opt["gamma"], opt["max_iter"], opt["tol"]
    )
    t_iter = time.perf_counter()
    intensity, std, bias2 = _intensity_and_std(su, graph, u, marg, state, prior, opt["rho"], rng)
    hyper = _hyperparameters(su, opt, prior, pi, bias2, graph)
    hyper["label_gamma"] = label_gamma
    t_end = time.perf_counter()
    timings = {
        "setup": t_graph - t0,
        "classify": t_cls - t_graph,
        "iterations": t_iter - t_cls,
        "outputs": t_end - t_iter,
        "total": t_end - t0,
    }
    log.info(
        "reconstruct: %d surfaces, %d links, %d sweeps (%s), %.3f s",
        S, graph.n_edges, history.n_iter, history.reason, timings["total"],
    )  # fmt: skip
    return _result(detection, su, graph, u, conf, intensity, std, history, hyper, timings)
