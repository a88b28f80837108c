"""Sphinx configuration: API reference (autodoc + autosummary, numpydoc docstrings),
the example gallery (sphinx-gallery runs ``examples/*.py``) and the Markdown pages
(myst-parser).

Build: ``pip install -e ".[docs]" && sphinx-build -W -b html docs docs/_build/html``
(``.ci/run`` does this after the tests; warnings are errors).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT / "src"))  # the package, when the docs are built from a clone
sys.path.insert(0, str(HERE))  # _gallery

import splidar  # noqa: E402

# --- project ------------------------------------------------------------------------
project = "splidar"
author = "splidar developers"
copyright = "splidar developers"  # noqa: A001
version = release = splidar.__version__

# --- extensions ---------------------------------------------------------------------
extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "generated/*.examples", "auto_examples/*.ipynb", "**.zip"]
templates_path = ["_templates"]

# autodoc / autosummary: one page per public function or class, members documented
autosummary_generate = True
autosummary_imported_members = False
autodoc_typehints = "none"  # numpydoc's Parameters sections carry the types
add_module_names = False

# numpydoc: class members are listed by the autosummary class template
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# myst: headings get anchors for links within the pages
myst_heading_anchors = 3

# every cross-reference must resolve (with -W a dead link fails the build); public
# aliases such as ``splidar.detect`` and short names are resolved by _xref.resolve.
# No intersphinx (the build must not need the network): references to other packages
# are accepted unresolved.
nitpicky = True
nitpick_ignore_regex = [
    (r"py:.*", r"(numpy|scipy|h5py|zarr|dask|matplotlib|numba|laspy|ptufile|sdtfile)(\..*)?"),
]
nitpick_ignore = [
    # dataclass fields documented in numpydoc "Attributes" sections (no link targets)
    ("py:attr", "Metrics.f_false_rate"),
    ("py:attr", "PhotonLists.source"),
    ("py:attr", "ExpTailIRF.support"),
    # a private helper named in a docstring
    ("py:class", "_Null"),
]


# --- example gallery ----------------------------------------------------------------
from _gallery import TOWER  # noqa: E402


def _examples_to_run() -> str:
    """Run every example; the real-data one only when ../shared/data is present (a fresh
    clone has none: the page is then built without its output) and SPLIDAR_DOCS_REAL is
    not 0."""
    if TOWER.is_file() and os.environ.get("SPLIDAR_DOCS_REAL", "1") != "0":
        return r"/\d\d_[^/]*\.py$"
    return r"/0[12]_[^/]*\.py$"


sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": _examples_to_run(),
    "ignore_pattern": r"__init__\.py",
    "reset_argv": "_gallery.reset_argv",
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "image_scrapers": ("matplotlib",),
    "matplotlib_animations": False,
    "plot_gallery": "True",
    "abort_on_example_error": True,
    "show_memory": False,
    "min_reported_time": 1,
}

# --- output -------------------------------------------------------------------------
html_theme = "alabaster"
html_title = f"splidar {release}"
html_static_path: list[str] = []
html_theme_options = {
    "description": "Single-photon lidar: 3D target detection, reconstruction, classification",
    "fixed_sidebar": True,
}


def setup(app):
    import _xref

    app.connect("missing-reference", _xref.resolve)
