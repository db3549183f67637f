"""The page's preset lights, served by ``GET /api/presets``: the named lights of :mod:`difareli.lighting.presets`
(five directions and every HDR map, the ones ``difareli-relight target.light=<name>`` takes). Each preset's
``light`` is the exact ``light`` object ``POST /api/relight`` takes, so the page sends it as it is and the
relight's own checks apply to it.
"""

from __future__ import annotations

from difareli.lighting.presets import DIRECTIONS, ENVMAPS


def presets() -> list[dict]:
    """Every preset as ``{"name", "label", "about", "light"}``, directions first, then the HDR maps."""
    out = [{"name": name, "label": name, "about": about,
            "light": {"kind": "direction", "direction": list(direction)}}
           for name, (direction, about) in DIRECTIONS.items()]
    out += [{"name": f"hdr-{name}", "label": f"HDR {name}", "about": f"the procedural HDR map '{name}'",
             "light": {"kind": "envmap", "name": name, "rotation": 0}} for name in ENVMAPS]
    return out


__all__ = ["presets"]
