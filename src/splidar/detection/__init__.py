"""Multiscale 3D target detection (Algorithm 1) and surface extraction, as named stages.

:func:`detect` is a short driver over the stages below; each numbered module holds one
pure function and a small frozen result, and the numbers give the order in which data
flows (one way, see ``docs/detection.md`` for the diagram)::

    Cube
     |  _1_background.py     estimate_temporal_background  -> TemporalBackground (bbar)
     |  _2_saliency.py       saliency_filters / block_saliency (multiscale boxes, eq:4.s1)
     |  _3_null.py           calibrate_null                -> NullCalibration (thresholds)
     |  _4_map.py            map_candidates                -> CandidateMap (S, M, candidates)
     |  clean-up passes over the candidate table, each a PassResult (added / removed):
     |  _5_recentre.py       recentre_runs           depths the neighbours agree on in the run
     |  _5a_spill_over.py    remove_spill_over       the spread of a neighbour's return
     |  _5b_isolated.py      remove_isolated         lone candidates own counts do not show
     |  _5c_dark_regions.py  restore_dark_regions    dim patches, pooled
     |  _5d_slopes.py        recover_slope_surfaces  steep slopes, sheared pooled tests
     |  _5e_enclosed.py      restore_enclosed_holes  holes a surface encloses
     |  _5f_stray_clusters.py remove_stray_clusters  a crowded pixel's small stray clusters
     |  _6_select.py         select_surfaces         K_s per pixel -> Surfaces
     |  _7_depths.py         place_depths            -> DepthPlacement: depths moved onto a
     |                         neighbour's plane, two rule families, fields followed once:
     |    _7a_align_depths.py aligned_depths         depths the 4-neighbours place elsewhere
     |    _7b_edge_bands.py   band_depths            bands beside depth edges, decided together
     v
    Detection (with ``provenance``: what each stage added or removed)

Modules without a number are the stages' tools: ``_filters`` (matched filter, boxes,
IRF figures), ``_fast`` and ``_kernels`` (numba kernels), ``_background``, ``_null``,
``_threshold``, ``_quality`` and ``_slopes`` (the statistics of the clean-up passes),
``_table`` (the candidate table the passes share), ``_depth_fields`` (a moved surface's
fields following its depth) and ``_result`` (the public results).
"""

from ._detect import PASSES, detect
from ._result import (
    STAGES,
    Background,
    DataReduction,
    Detection,
    NullModel,
    PixelStory,
    StageRecord,
    StoredHistograms,
    Surfaces,
    SurfaceStory,
)
from ._threshold import ThresholdField

__all__ = [
    "PASSES",
    "STAGES",
    "Background",
    "DataReduction",
    "Detection",
    "NullModel",
    "PixelStory",
    "StageRecord",
    "StoredHistograms",
    "SurfaceStory",
    "Surfaces",
    "ThresholdField",
    "detect",
]
