"""Ray-cast renderer: orthographic DECA camera, G-buffer, cast shadows, SH shading (docs/architecture.md).

Names are imported lazily (PEP 562): relighting needs only the camera and the screen-space shadow marcher, and
must import on machines without trimesh/embree (a bare GPU image).
"""

from __future__ import annotations

from difareli.utils.lazy import lazy_attributes

_NAMES = {
    "camera": ("OrthoCamera",),
    "raycast": ("GBuffer", "Scene", "interpolate_vertex_attribute", "render_gbuffer"),
    "shading": ("render_sh", "shading_reference"),
    "shadow": ("DEFAULT_EPS", "cast_shadow", "cast_shadows", "lit_candidates"),
}
_HOMES = {name: module for module, names in _NAMES.items() for name in names}

__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_attributes(__name__, _HOMES, globals())
