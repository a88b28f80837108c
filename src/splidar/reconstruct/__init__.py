"""Bayesian 3D reconstruction and spectral classification (Algorithm 2)."""

__all__: list[str] = []
