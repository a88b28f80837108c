"""Bayesian 3D reconstruction and spectral classification (Algorithm 2)."""

from ._core import estimate_alpha, irf_fraction, kmeans_signatures, nearest_signature, reconstruct
from ._graph import SurfaceGraph, build_graph, irf_fwhm
from ._result import ConvergenceHistory, Reconstruction
from ._synthetic import synthetic_detection

__all__ = [
    "ConvergenceHistory",
    "Reconstruction",
    "SurfaceGraph",
    "build_graph",
    "estimate_alpha",
    "irf_fraction",
    "irf_fwhm",
    "kmeans_signatures",
    "nearest_signature",
    "reconstruct",
    "synthetic_detection",
]
