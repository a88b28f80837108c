"""Result dataclasses of the reconstruction stage (Algorithm 2).

The contract between :func:`splidar.reconstruct` and exports, plots and metrics.
Fields may be added; the ones documented here keep their names, shapes and meaning.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..detection._result import Detection
from ..library import SpectralLibrary
from ..points import PointSet

__all__ = ["ConvergenceHistory", "Reconstruction"]


@dataclass(frozen=True)
class ConvergenceHistory:
    """Trace of the coordinate descent.

    Attributes
    ----------
    objective : ndarray (n_iter + 1,)
        Log posterior (up to a constant) after initialisation, after every 5th sweep of
        each phase, at the start and end of each phase; NaN after the other sweeps (it
        costs about a fifth of a sweep). Never decreases between finite values except
        across an alpha update (below).
    change : ndarray (n_iter,)
        RMS change of the parameters at each sweep (``eq:criter``).
    n_iter : int
    converged : bool
        True when the change fell below ``tol`` before ``max_iter``.
    reason : str
        ``"tol"`` or ``"max_iter"`` (or ``"no surfaces"``).
    label_changes : ndarray (n_iter,), int64, optional
        Number of labels changed at each sweep: 0 since issue 14 (the labels are chosen
        before the sweeps, by :func:`splidar.reconstruction.classify_surfaces`).
    alpha_updates : tuple of int
        Sweeps i after which the empirical-Bayes estimate of (alpha, upsilon) replaced the
        previous value (``reconstruct(alpha="auto")``). ``objective[i]`` is then evaluated under
        the new alpha (the model changed), so ``objective[i] - objective[i - 1]`` may be
        negative there; between updates the objective never decreases.
    """

    objective: np.ndarray
    change: np.ndarray
    n_iter: int
    converged: bool
    reason: str
    alpha_updates: tuple[int, ...] = ()
    label_changes: np.ndarray | None = None


@dataclass(frozen=True)
class Reconstruction:
    """Result of :func:`splidar.reconstruct` / :func:`splidar.process`.

    Attributes
    ----------
    points : PointSet
        One point per surface: ``row``, ``col``, ``depth_bin``, ``depth_m`` (when the bin
        width is known), ``intensity`` (n, L) in expected signal photons,
        ``intensity_std`` (n, L) posterior standard deviation, ``label`` (0-based row of
        the library; 0 without one), ``label_confidence`` (n,), ``layer`` (n,).
    depth_map : ndarray (rows, cols, K_s), float64
        Depth in bins per surface layer, NaN where there is no surface.
    intensity_map : ndarray (rows, cols, K_s, L), float64
        Intensity per layer and wavelength, NaN where there is no surface.
    label_map : ndarray (rows, cols, K_s), int64
        Label per layer, -1 where there is no surface.
    library : SpectralLibrary or None
        The library used (``None``: one class, or classes found from the data; see
        ``hyperparameters["classes"]``).
    history : ConvergenceHistory
    hyperparameters : mapping
        Every hyperparameter value used (for reports and reproducibility).
    timings : mapping
        Seconds per step.
    detection : Detection
        The detection this reconstruction was computed from.
    """

    points: PointSet
    depth_map: np.ndarray
    intensity_map: np.ndarray
    label_map: np.ndarray
    library: SpectralLibrary | None
    history: ConvergenceHistory
    hyperparameters: Mapping[str, Any] = field(default_factory=dict)
    timings: Mapping[str, float] = field(default_factory=dict)
    detection: Detection | None = None

    def __repr__(self) -> str:
        k = "none" if self.library is None else f"{self.library.n_classes} classes"
        return (
            f"Reconstruction(points={len(self.points)}, image_shape={self.image_shape}, "
            f"layers={self.n_layers}, L={self.n_wavelengths}, library={k}, "
            f"iterations={self.history.n_iter}, converged={self.history.converged})"
        )

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.points.image_shape

    @property
    def n_layers(self) -> int:
        """K_s, the number of surface layers."""
        return int(self.depth_map.shape[2])

    @property
    def n_wavelengths(self) -> int:
        return int(self.intensity_map.shape[3])

    @property
    def bin_width_ps(self) -> float | None:
        return None if self.detection is None else self.detection.bin_width_ps

    @property
    def class_names(self) -> tuple[str, ...]:
        if self.library is not None:
            return self.library.class_names
        k = int(self.label_map.max()) + 1 if self.label_map.size else 1
        return tuple(f"class {i}" for i in range(max(k, 1)))
