"""Bayesian 3D reconstruction and spectral classification (Algorithm 2)."""

from ._result import ConvergenceHistory, Reconstruction

__all__ = ["ConvergenceHistory", "Reconstruction"]
