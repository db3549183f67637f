"""The page's preset lights, defined once here and served by ``GET /api/presets``: five directions (camera space,
``docs/architecture.md``: x to the image's right, y up, z toward the viewer) and every HDR map of
:mod:`difareli.app.envmaps`. Each preset's ``light`` is the exact ``light`` object ``POST /api/relight`` takes, so
the page sends it as it is and the relight's own checks apply to it.
"""

from __future__ import annotations

from .envmaps import ENVMAPS

#: name -> (direction [x, y, z], what the button's tooltip says). "left" is the image's left (the viewer's).
DIRECTIONS: dict[str, tuple[tuple[float, float, float], str]] = {
    "left": ((-1.0, 0.15, 0.45), "a key light from the image's left"),
    "right": ((1.0, 0.15, 0.45), "a key light from the image's right"),
    "top": ((0.0, 1.0, 0.35), "a light from above"),
    "rim": ((0.0, 0.35, -1.0), "a back light behind the head (rim light): the face darkens"),
    "front": ((0.0, 0.0, 1.0), "a light from the camera: flat"),
}


def presets() -> list[dict]:
    """Every preset as ``{"name", "label", "about", "light"}``, directions first, then the HDR maps."""
    out = [{"name": name, "label": name, "about": about,
            "light": {"kind": "direction", "direction": list(direction)}}
           for name, (direction, about) in DIRECTIONS.items()]
    out += [{"name": f"hdr-{name}", "label": f"HDR {name}", "about": f"the procedural HDR map '{name}'",
             "light": {"kind": "envmap", "name": name, "rotation": 0}} for name in ENVMAPS]
    return out


__all__ = ["DIRECTIONS", "presets"]
