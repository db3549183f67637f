"""Ray-cast renderer: orthographic DECA camera, G-buffer, cast shadows, SH shading (docs/architecture.md)."""

from .camera import OrthoCamera
from .raycast import GBuffer, Scene, interpolate_vertex_attribute, render_gbuffer
from .shading import render_sh, shading_reference
from .shadow import DEFAULT_EPS, cast_shadow, cast_shadows, lit_candidates

__all__ = [
    "DEFAULT_EPS",
    "GBuffer",
    "OrthoCamera",
    "Scene",
    "cast_shadow",
    "cast_shadows",
    "interpolate_vertex_attribute",
    "lit_candidates",
    "render_gbuffer",
    "render_sh",
    "shading_reference",
]
