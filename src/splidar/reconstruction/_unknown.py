"""The "unknown material" outcome: a likelihood-ratio test against a free spectrum (issue 14).

Default: **off**. :func:`splidar.reconstruct` always gives each surface one of the
library's classes; :func:`flag_unknown` is the explicit step that marks the surfaces no
signature explains (label -1). Why off: the test's null is "the counts are Poisson about
the assigned signature exactly", so any real within-class spectral variability, a
library measured under other illumination or a detection whose support clips part of a
return is rejected once the counts are large enough: the test flags what is *bright*
more than what is *foreign*. Measured (``benchmarks/bench_classification.py``, level
1e-3): on the simulator's multispectral scenes, whose surfaces carry their signature
exactly, the rate of flagged known surfaces is printed beside the figures; on the Art
scene, whose classes are k-means clusters of real colours, it flags a large share of
surfaces at PPP 64 although they belong to the library's classes. A user who knows the
library is complete loses nothing with the default; one who expects foreign materials
calls :func:`flag_unknown` with a level they choose.
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
