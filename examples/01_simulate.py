"""
Simulate a single-photon lidar cube
===================================

Simulate a single-photon lidar cube, check what came out and look at the truth.

Run:  python examples/01_simulate.py

A scene is a ground truth (surfaces with depths and intensities); ``scene.simulate``
draws photon counts from it with Poisson noise (the observation model of the paper,
eq. 4.1). PPP = signal photons per pixel, SBR = signal / background photons.
"""

import matplotlib.pyplot as plt
import numpy as np

from splidar.plotting import plot_depth
from splidar.scenes import two_layer_scene

# A 48 x 48 scene: a thin net (partly see-through) in front of a wall, boxes and a ramp.
# The IRF is a realistic asymmetric SPAD response: a 3-bin Gaussian with a 2-bin tail.
scene = two_layer_scene((48, 48), n_bins=200, irf=("exp_tail", 3.0, 2.0))
print(scene.description)
print(
    f"{len(scene.truth)} surfaces; pixels with 2 surfaces: "
    f"{(scene.surfaces_per_pixel() == 2).mean():.0%}"
)

# %%
# Draw a cube with 20 signal photons per pixel, as many background photons as signal
# photons (SBR = 1), and background that decays with range (like fog backscatter).
sim = scene.simulate(ppp=20, sbr=1.0, background="decaying", rng=0)
cube = sim.cube
print(cube)

# The requested PPP and SBR hold exactly for the expected counts ...
print(f"expected: PPP = {sim.ppp:.2f}, SBR = {sim.sbr:.2f}")

# ... and approximately for this random draw.
total = cube.counts.sum(dtype=np.float64) / cube.n_pixels
background = sim.background_per_bin.sum() * cube.n_bins
signal = total - background
print(
    f"measured: photons per pixel = {total:.2f}, of which signal ~ {signal:.2f} "
    f"(SBR ~ {signal / background:.2f})"
)

# %%
# The truth (depths in bins, intensities scaled to the requested PPP) is a PointSet,
# the same form detection and reconstruction return; save it for later comparisons.
print(sim.truth)
print(f"IRF peak (depth reference) at sample {int(cube.irf_peak[0])} of {cube.irf.shape[1]}")

# %%
# The truth's two layers: the net (nearest surface, where it exists) and what lies behind.
# Pixels without a surface in that layer are light grey.
fig, axes = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
for layer, ax in enumerate(axes):
    plot_depth(sim.truth, layer=layer, ax=ax)

plt.show()
