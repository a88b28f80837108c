"""The "unknown material" outcome: a likelihood-ratio test against a free spectrum (issue 14).

Default: **off**. :func:`splidar.reconstruct` always gives each surface one of the
library's classes; :func:`flag_unknown` is the explicit step that marks the surfaces no
signature explains (label -1). Why off:

* a label of -1 changes the output's contract (every label a row of the library, -1
  meaning "no surface" in ``label_map``): exports, plots and user code that index the
  library by label would have to handle it, so it is asked for, not imposed;
* at the counts where classification is hard the test has no power (a surface of a few
  photons fits any signature shape), so the outcome only appears where the counts are
  high, and there the null "Poisson about the exact signature" also rejects real
  within-class variability, a library measured under another illumination or a return
  clipped by its support: the more photons, the more it flags what is *bright*.

Measured (``benchmarks/bench_classification.py``, level 1e-3, over matched surfaces of
library classes): 0.000-0.001 flagged on the simulator's multispectral scenes (surfaces
carry their signature exactly) and on the Art scene (classes are k-means clusters of real
colours, PPP 4-64): the false-flag rate is at the level, so a user who expects foreign
materials can turn it on safely; ``tests/test_classify.py`` shows a material missing from
the library flagged at high counts.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import stats

from .._validation import SplidarError
from ._classify import unknown_llr
from ._core import _surface_data
from ._result import Reconstruction

__all__ = ["flag_unknown"]


def flag_unknown(reconstruction: Reconstruction, *, level: float = 1e-3) -> Reconstruction:
    r"""Mark as unknown (label -1) the surfaces whose counts no signature explains.

    For each surface, ``2 log LR`` of a free spectrum (one non-negative intensity per
    wavelength) against its assigned class (the class's signature shape at the best
    brightness), :func:`splidar.reconstruction.unknown_llr`, is compared with the
    chi-square (``L - 1`` degrees of freedom) quantile at ``1 - level``: the fraction of
    surfaces of a library class flagged is about ``level`` when the class's signature is
    exact. ``label_confidence`` of a flagged surface becomes ``1 - p``, its p-value's
    complement.

    Parameters
    ----------
    reconstruction : Reconstruction
        With its ``detection`` and ``hyperparameters["signatures"]`` (K > 1 or not).
    level : float
        Probability of flagging a surface of a known class (0 < level < 1).

    Returns
    -------
    Reconstruction
        A copy with ``points.label`` and ``label_map`` -1 where flagged (a surface of
        unknown material; ``depth_map`` tells it from an empty slot, which is also -1),
        ``hyperparameters["unknown_level"]`` and ``["n_unknown"]``.

    Raises
    ------
    SplidarError
        ``level`` outside (0, 1), a reconstruction without its detection, or one of L = 1
        (a single wavelength has no spectral shape to test).
    """
    rec = reconstruction
    if not isinstance(rec, Reconstruction):
        raise SplidarError(
            f"`reconstruction` must be a splidar Reconstruction; got {type(rec).__name__}."
        )
    try:
        level = float(level)
    except (TypeError, ValueError):
        level = float("nan")
    if not 0.0 < level < 1.0:
        raise SplidarError(f"`level` must be a probability in (0, 1), e.g. 1e-3; got {level!r}.")
    det = rec.detection
    if det is None:
        raise SplidarError(
            "`reconstruction.detection` is None: flag_unknown needs the surfaces' counts; "
            "pass the Reconstruction returned by splidar.reconstruct or splidar.process."
        )
    L = det.n_wavelengths
    if L < 2:
        raise SplidarError(
            "flag_unknown needs L >= 2 wavelengths (a spectrum's shape); the detection has L = 1."
        )
    irf = np.atleast_2d(np.asarray(det.irf, dtype=np.float64))
    y, b, eta, _ = _surface_data(det, irf)
    sig = np.asarray(rec.hyperparameters["signatures"], np.float64)
    label = np.asarray(rec.points.label, np.int64)
    llr = unknown_llr(y, b, eta, sig, label)
    p = stats.chi2.sf(llr, L - 1)
    flag = p < level
    new_label = np.where(flag, -1, label)
    conf = rec.points.label_confidence
    conf = np.where(flag, 1.0 - p, conf if conf is not None else 1.0)
    points = replace(rec.points, label=new_label, label_confidence=conf)
    label_map = points.maps(n_layers=rec.n_layers)["label"]
    hyper = dict(rec.hyperparameters)
    hyper.update(unknown_level=level, n_unknown=int(flag.sum()))
    return replace(rec, points=points, label_map=label_map, hyperparameters=hyper)
