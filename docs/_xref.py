"""Cross-references the Python domain cannot resolve by itself.

Docstrings name objects the way users import them: ``splidar.detect`` (defined in
``splidar.detection``), or by their short name (``Cube``, ``Scene.simulate``) from
another module. A reference that Sphinx does not find is resolved here to the one
documented object of that public alias or short name; one that stays unresolved is an
error of the build (``nitpicky`` with ``-W``), so that links cannot rot.
"""

from __future__ import annotations

import splidar


def _aliases() -> dict[str, str]:
    """``splidar.<name>`` -> the documented object, for every top-level public name."""
    out = {f"splidar.{name}": f"{mod}.{attr}" for name, (mod, attr) in splidar._LAZY.items()}
    for name in ("Cube", "PointSet", "SpectralLibrary", "gaussian_irf"):
        obj = getattr(splidar, name)
        public_mod = obj.__module__.split("._")[0]  # splidar.cube, splidar.irf, ...
        out[f"splidar.{name}"] = f"{public_mod}.{name}"
    return out


ALIASES = _aliases()


def resolve(app, env, node, contnode):
    """``missing-reference`` handler: a public alias, or a unique dotted suffix."""
    if node.get("refdomain") != "py":
        return None
    target = ALIASES.get(node["reftarget"], node["reftarget"])
    domain = env.get_domain("py")
    if target not in domain.objects:
        matches = [
            name
            for name in domain.objects
            if name.endswith("." + target) and "._" not in name  # public paths only
        ]
        if len(matches) != 1:
            return None
        target = matches[0]
    return domain.resolve_xref(
        env, node["refdoc"], app.builder, node["reftype"], target, node, contnode
    )
