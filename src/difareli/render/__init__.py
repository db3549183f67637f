"""Ray-cast renderer: orthographic DECA camera, G-buffer, cast shadows, SH shading (docs/architecture.md).

Names are imported lazily (PEP 562): relighting needs only the camera and the screen-space shadow marcher, and
must import on machines without trimesh/embree (a bare GPU image).
"""

from __future__ import annotations

import importlib
from typing import Any

_HOMES = {
    "OrthoCamera": "camera",
    "GBuffer": "raycast",
    "Scene": "raycast",
    "interpolate_vertex_attribute": "raycast",
    "render_gbuffer": "raycast",
    "render_sh": "shading",
    "shading_reference": "shading",
    "DEFAULT_EPS": "shadow",
    "cast_shadow": "shadow",
    "cast_shadows": "shadow",
    "lit_candidates": "shadow",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
