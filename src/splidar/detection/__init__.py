"""Multiscale 3D target detection (Algorithm 1) and surface extraction."""

from ._detect import detect
from ._result import Background, DataReduction, Detection, NullModel, Surfaces
from ._threshold import ThresholdField

__all__ = [
    "Background",
    "DataReduction",
    "Detection",
    "NullModel",
    "Surfaces",
    "ThresholdField",
    "detect",
]
