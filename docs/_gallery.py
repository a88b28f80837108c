"""Helpers of the example gallery, named by string in conf.py (a function in the
configuration itself cannot be cached by Sphinx)."""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).resolve().parent
#: the public data set 03_real_file.py reads; beside the project, never inside it
TOWER = HERE.parent.parent / "shared" / "data" / "tower" / "tower.mat"


def reset_argv(gallery_conf, script_vars) -> list[str]:
    """Command-line arguments of each example: outputs go to the build folder."""
    out = HERE / "_build" / "example-outputs"
    out.mkdir(parents=True, exist_ok=True)
    name = Path(script_vars["src_file"]).name
    if name.startswith("02_"):
        return [str(out / "pipeline_points.npz")]
    if name.startswith("03_"):
        return [str(TOWER), "--bin-width", "256", "--out", str(out / "real_file")]
    return []
