"""Bayesian 3D reconstruction and spectral classification (Algorithm 2)."""

from ._classify import (
    Classification,
    chain_gammas,
    class_loglik,
    classify_surfaces,
    em_proportions,
    estimate_gamma,
    link_contrast,
    link_gamma,
    potts_marginals,
    unknown_llr,
)
from ._core import estimate_alpha, irf_fraction, kmeans_signatures, nearest_signature
from ._graph import SurfaceGraph, build_graph, irf_fwhm
from ._result import ConvergenceHistory, Reconstruction
from ._synthetic import synthetic_detection
from ._tiled import reconstruct
from ._unknown import flag_unknown

__all__ = [
    "Classification",
    "chain_gammas",
    "class_loglik",
    "classify_surfaces",
    "em_proportions",
    "estimate_gamma",
    "link_contrast",
    "link_gamma",
    "potts_marginals",
    "unknown_llr",
    "ConvergenceHistory",
    "Reconstruction",
    "SurfaceGraph",
    "build_graph",
    "estimate_alpha",
    "flag_unknown",
    "irf_fraction",
    "irf_fwhm",
    "kmeans_signatures",
    "nearest_signature",
    "reconstruct",
    "synthetic_detection",
]
