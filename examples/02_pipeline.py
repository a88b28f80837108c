"""
The whole chain: detect, reconstruct, classify, score
=====================================================

The whole chain on a simulated scene: detect, reconstruct, classify, score, save.

Run:  python examples/02_pipeline.py [OUTPUT.npz]

The scene has 3 materials seen at 4 wavelengths and a thin net of another material in
front (two surfaces in 36 % of the pixels); its spectral library is known.
``splidar.process`` runs detection (Algorithm 1 of the paper) then the Bayesian
reconstruction and classification (Algorithm 2), and returns one point per surface.
"""

import sys

import matplotlib.pyplot as plt

import splidar
from splidar.plotting import plot_depth, plot_labels, plot_saliency_histogram
from splidar.scenes import multispectral_scene

out = sys.argv[1] if len(sys.argv) > 1 else "pipeline_points.npz"

scene = multispectral_scene((48, 48), n_bins=200, two_layers=True)
print(scene)
# 10 signal photons per pixel (all 4 wavelengths), as many background photons (SBR = 1)
sim = scene.simulate(ppp=10, sbr=1.0, rng=0)

rec = splidar.process(sim.cube, library=scene.library, rng=0)
print(
    f"{len(rec.points)} surfaces found ({len(sim.truth)} true), "
    f"detect {rec.timings['detect']:.2f} s, reconstruct {rec.timings['reconstruct']:.2f} s"
)

# %%
# Score against the truth: a detection counts when it is within tau = 2 bins of a true surface
metrics = splidar.evaluate(rec.points, sim.truth, tau=2.0)
print(metrics)

# %%
# Each point has depth (bins and metres), intensity per wavelength with its posterior
# standard deviation, a class label and its confidence. Save them for later use.
rec.points.save(out)
print(f"saved {len(rec.points)} points to {out}")

# %%
# Depth and class of the nearest surface of each pixel (the net where it exists) and of
# the surface behind it. Grey: no surface in that layer.
fig, axes = plt.subplots(2, 2, figsize=(10, 8), layout="constrained")
for layer in (0, 1):
    plot_depth(rec, layer=layer, ax=axes[0, layer])
    plot_labels(rec, layer=layer, ax=axes[1, layer])

# %%
# Why detection keeps what it keeps: the saliency of every voxel, the gamma fitted to
# the background voxels and the calibrated false-alarm threshold.
ax = plot_saliency_histogram(rec.detection, rng=0)

plt.show()
