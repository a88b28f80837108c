"""The whole chain: detection (Algorithm 1) then reconstruction (Algorithm 2)."""

from __future__ import annotations

import inspect
import logging
import time
from dataclasses import replace

from ._validation import SplidarError
from .cube import Cube

__all__ = ["process"]

log = logging.getLogger(__name__)


def _keywords(func) -> list[str]:
    return [
        p.name
        for p in inspect.signature(func).parameters.values()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    ]


def process(cube: Cube, *, library=None, **options):
    """Detect surfaces in ``cube`` and reconstruct them: ``reconstruct(detect(cube))``.

    Parameters
    ----------
    cube : Cube
        Counts ``(rows, cols, L, T)`` with their IRF.
    library : SpectralLibrary, array (K, L), path, optional
        Spectral signatures for classification; default ``cube.library``. Without one,
        the reconstruction uses one class (or ``n_classes=`` classes found from the data).
    **options
        Keywords of :func:`splidar.detect` (e.g. ``scales``, ``weights``, ``pfa``,
        ``max_surfaces``) and of :func:`splidar.reconstruct` (e.g. ``gamma``, ``rho``,
        ``alpha``, ``links``, ``max_iter``, ``tol``, ``classes``, ``n_classes``). ``rng``
        goes to both. Each keyword goes to the stage that declares it.

    Returns
    -------
    Reconstruction
        With ``timings["detect"]`` and ``timings["reconstruct"]`` (seconds) added to
        the reconstruction's own step timings.

    Raises
    ------
    SplidarError
        A keyword neither stage accepts (the message lists the valid ones), or any
        error of the two stages.

    Examples
    --------
    >>> import numpy as np, splidar
    >>> from splidar.scenes import multispectral_scene
    >>> sim = multispectral_scene((16, 16), n_bins=120).simulate(ppp=10, sbr=1, rng=0)
    >>> rec = splidar.process(sim.cube, rng=0)  # doctest: +SKIP
    """
    from .detection import detect
    from .reconstruction import reconstruct

    if not isinstance(cube, Cube):
        raise SplidarError(
            f"`cube` must be a splidar Cube (see splidar.load or splidar.Cube); got "
            f"{type(cube).__name__}."
        )
    det_keys = set(_keywords(detect))
    rec_keys = set(_keywords(reconstruct)) - {"library"}
    unknown = sorted(set(options) - det_keys - rec_keys)
    if unknown:
        raise SplidarError(
            f"process() got unknown option(s) {unknown}. Detection options: "
            f"{sorted(det_keys)}; reconstruction options: {sorted(rec_keys)}."
        )
    det_opts = {k: v for k, v in options.items() if k in det_keys}
    rec_opts = {k: v for k, v in options.items() if k in rec_keys}
    if library is None:
        library = cube.library
    t0 = time.perf_counter()
    detection = detect(cube, **det_opts)
    t1 = time.perf_counter()
    rec = reconstruct(detection, library=library, **rec_opts)
    t2 = time.perf_counter()
    timings = dict(rec.timings)
    timings.update({"detect": t1 - t0, "reconstruct": t2 - t1, "process": t2 - t0})
    log.info("process: detect %.3f s, reconstruct %.3f s", t1 - t0, t2 - t1)
    return replace(rec, timings=timings)
