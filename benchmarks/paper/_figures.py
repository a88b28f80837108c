"""Figures of the paper run: maps through :mod:`splidar.plotting`, curves with matplotlib."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from splidar.plotting import plot_depth, plot_labels  # noqa: E402

_STYLE = {"splidar": "-o", "per-pixel": "--s", "coarse-7": ":^"}
_TITLES = {
    "splidar": "splidar (multiscale, reconstructed)",
    "per-pixel": "per-pixel detector",
    "coarse-7": "per-pixel on 7 x 7 sums",
}


def _save(fig, path: Path) -> str:
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path.name


def _layers(truth) -> int:
    return 1 if truth.layer is None else int(truth.layer.max()) + 1


def detection_maps(kept, path: Path, *, bin_width_ps=None) -> str:
    """Depth of each surface layer: the truth, then each method (``fig:3D_reconst_Art``)."""
    n_layers = _layers(kept.truth)
    names = ["truth", *kept.points]
    fig, axes = plt.subplots(
        len(names),
        n_layers,
        figsize=(5.2 * n_layers, 3.6 * len(names)),
        layout="constrained",
        squeeze=False,
    )
    d = kept.truth.depth_m if kept.truth.depth_m is not None else kept.truth.depth_bin
    lo, hi = np.percentile(d, [1, 99])
    for i, name in enumerate(names):
        pts = kept.truth if name == "truth" else kept.points[name]
        for layer in range(n_layers):
            ax = axes[i, layer]
            plot_depth(pts, layer=layer, ax=ax, vmin=lo, vmax=hi, bin_width_ps=bin_width_ps)
            ax.set_title(f"{_TITLES.get(name, name)}: {ax.get_title()}", fontsize=9)
    fig.suptitle(f"Detected surfaces, {kept.label}")
    return _save(fig, path)


def classification_maps(kept, path: Path, class_names) -> str:
    """Class of each surface layer: the truth, splidar, the per-pixel classification."""
    n_layers = _layers(kept.truth)
    names = ["truth", *(n for n in kept.points if n != "coarse-7")]
    fig, axes = plt.subplots(
        len(names),
        n_layers,
        figsize=(5.6 * n_layers, 3.6 * len(names)),
        layout="constrained",
        squeeze=False,
    )
    for i, name in enumerate(names):
        pts = kept.truth if name == "truth" else kept.points[name]
        for layer in range(n_layers):
            ax = axes[i, layer]
            plot_labels(pts, layer=layer, ax=ax, class_names=class_names)
            label = "nearest signature per point" if name == "per-pixel" else _TITLES.get(name)
            ax.set_title(f"{label or name}: {ax.get_title()}", fontsize=9)
    fig.suptitle(f"Classification, {kept.label}")
    return _save(fig, path)


def metrics_vs_ppp(rows, path: Path, *, tau_mm: float) -> str:
    """F_true, F_false, DAE, IAE against PPP per SBR and background (``fig:Quant_3D_Art``)."""
    keys = [
        ("f_true", f"F_true (tau = {tau_mm:g} mm)"),
        ("f_false_rate", "F_false / true points"),
        ("dae_mm", "DAE (mm)"),
        ("iae_rel", "IAE / mean true photons"),
    ]
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), layout="constrained")
    groups = sorted({(r["sbr"], r["background"]) for r in rows})
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (key, label) in zip(axes.flat, keys, strict=True):
        for gi, (sbr, bg) in enumerate(groups):
            for method in ("splidar", "per-pixel"):
                sel = sorted(
                    (
                        r
                        for r in rows
                        if (r["sbr"], r["background"], r["method"]) == (sbr, bg, method)
                    ),
                    key=lambda r: r["ppp"],
                )
                x = [r["ppp"] for r in sel]
                y = [np.nan if r[key] is None else r[key] for r in sel]
                ax.plot(
                    x,
                    y,
                    _STYLE[method],
                    color=colors[gi % len(colors)],
                    ms=4,
                    label=f"{method}, SBR {sbr:g}, {bg}",
                )
        ax.set_xscale("log")
        ax.set_xlabel("PPP (signal photons per pixel)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=1)
    fig.suptitle("Detection and reconstruction against PPP (solid: splidar, dashed: per-pixel)")
    return _save(fig, path)


def metrics_vs_tau(kept_list, path: Path) -> str:
    """F_true(tau), F_false(tau), DAE(tau) of the kept cells (``fig:Quant_3D_Art``, top)."""
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), layout="constrained")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ci, kept in enumerate(kept_list):
        for method, c in kept.curves.items():
            if method == "coarse-7":
                continue
            tau_mm = 1e3 * np.asarray(c.tau)
            style = dict(color=colors[ci % len(colors)], ms=4)
            axes[0].plot(tau_mm, c.f_true, _STYLE[method], **style, label=f"{method}, {kept.label}")
            axes[1].plot(tau_mm, c.f_false, _STYLE[method], **style)
            axes[2].plot(tau_mm, 1e3 * np.asarray(c.dae), _STYLE[method], **style)
    for ax, lab in zip(axes, ("F_true(tau)", "F_false(tau) (count)", "DAE(tau) (mm)"), strict=True):
        ax.set_xlabel("tau (mm)")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    return _save(fig, path)


def accuracy_vs_time(rows, paper, path: Path) -> str:
    """Detection accuracy against PPP, ours beside the paper's (``tabl:AccTD``)."""
    fig, ax = plt.subplots(figsize=(8, 5), layout="constrained")
    for method in ("splidar", "per-pixel", "coarse-7"):
        sel = sorted((r for r in rows if r["method"] == method), key=lambda r: r["ppp"])
        ax.plot(
            [r["ppp"] for r in sel],
            [100 * r["detection_accuracy"] for r in sel],
            _STYLE[method],
            label=f"ours: {_TITLES[method]}",
        )
    ppp = np.asarray(paper["acquisition_ms"]) * paper["ppp_per_ms"]
    for name, vals in paper["accuracy_pct"].items():
        ax.plot(ppp, vals, "x-.", alpha=0.7, label=f"paper (Lego): {name}")
    ax.set_xscale("log")
    ax.set_xlabel(f"PPP (paper: acquisition time x {paper['ppp_per_ms']:g} photons/ms)")
    ax.set_ylabel("detection accuracy (% of pixels)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Target detection accuracy against acquisition time")
    return _save(fig, path)


def face_maps(maps, fractions, path: Path) -> str:
    """Depth maps of the face at each fraction of its acquisition, per method."""
    methods = sorted({m for _, m in maps}, key=["splidar", "per-pixel"].index)
    fr = sorted(fractions)
    fig, axes = plt.subplots(
        len(methods),
        len(fr),
        figsize=(4.6 * len(fr), 3.6 * len(methods)),
        layout="constrained",
        squeeze=False,
    )
    # one colour scale for all panels: the reference's median +- 4 robust standard
    # deviations (the far wall would otherwise flatten the face's relief)
    d = maps[(1.0, "splidar")].depth_bin
    med = np.median(d)
    spread = 4 * 1.4826 * np.median(np.abs(d - med))
    lo, hi = max(med - spread, np.percentile(d, 1)), min(med + spread, np.percentile(d, 99))
    for i, method in enumerate(methods):
        for j, f in enumerate(fr):
            ax = axes[i, j]
            plot_depth(maps[(f, method)], layer=0, ax=ax, vmin=lo, vmax=hi)
            ax.set_title(f"{method}, {100 * f:.3g} % of the photons", fontsize=9)
    fig.suptitle("Mannequin face: nearest surface against acquisition time")
    return _save(fig, path)


def data_reduction(entries, path: Path) -> str:
    """Fraction of voxels the detection keeps and of photons inside them, per run."""
    fig, ax = plt.subplots(figsize=(max(6, 0.5 * len(entries) + 2), 4.5), layout="constrained")
    x = np.arange(len(entries))
    ax.bar(x - 0.2, [100 * e["voxel_fraction"] for e in entries], 0.4, label="voxels kept (%)")
    ax.bar(
        x + 0.2,
        [100 * e["photon_fraction"] for e in entries],
        0.4,
        label="photons in kept voxels (%)",
    )
    ax.set_yscale("log")
    ax.set_xticks(x, [e["run"] for e in entries], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("% of the cube")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8)
    ax.set_title("Data reduction by splidar's 3D detection map")
    return _save(fig, path)
