"""splidar: single-photon lidar processing.

Multiscale 3D target detection, Bayesian 3D reconstruction and spectral
classification of photon-count histogram cubes, after Belmekki et al.,
"3D Target Detection and Spectral Classification for Single-photon LiDAR Data".

Data flows one way::

    Cube -> detect -> Detection -> reconstruct -> Reconstruction -> export / plot / metrics

``process`` chains the two stages. Heavy submodules are imported on first use.
"""

from __future__ import annotations

import importlib
import logging
import os

from ._validation import SplidarError
from ._version import __version__
from .cube import Cube
from .irf import gaussian_irf
from .library import SpectralLibrary
from .points import PointSet

logging.getLogger(__name__).addHandler(logging.NullHandler())

# The reconstruction's parallel numba kernels run on OpenMP, whose idle threads spin by
# default. On a busy machine (other processes, ``pytest -n``) each parallel step then
# waits for a descheduled spinner: with one of 2 cores taken, the Art-size
# reconstruction went 0.5-0.7 s -> 2.7-4.4 s. Passive waiting costs little on an idle
# machine. Read when OpenMP starts (the first parallel kernel); a user's setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# public name -> (module, attribute); resolved lazily so `import splidar` stays fast
_LAZY = {
    "load": ("splidar.io", "load"),
    "save": ("splidar.io", "save"),
    "simulate": ("splidar.simulation", "simulate"),
    "detect": ("splidar.detection", "detect"),
    "Detection": ("splidar.detection", "Detection"),
    "reconstruct": ("splidar.reconstruction", "reconstruct"),
    "Reconstruction": ("splidar.reconstruction", "Reconstruction"),
    "process": ("splidar.pipeline", "process"),
    "evaluate": ("splidar.metrics", "evaluate"),
}

__all__ = [
    "Cube",
    "PointSet",
    "SpectralLibrary",
    "SplidarError",
    "__version__",
    "gaussian_irf",
    *_LAZY,
]


def __getattr__(name):
    try:
        mod, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'splidar' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(mod), attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
