"""The denoising network: ADM UNet with AdaGN (unet.py), spatial components (conditioning.py, controlnet.py),
non-spatial components (nonspatial.py), presets, and the composed :class:`DiffusionNet` (network.py).

Names are imported lazily (PEP 562) so that importing one component does not build the others.
"""

from __future__ import annotations

from difareli.utils.lazy import lazy_attributes

_HOMES = {
    "SPATIAL_COMPONENTS": "conditioning",
    "ConcatSpatial": "conditioning",
    "Modulator": "conditioning",
    "register_spatial": "conditioning",
    "resolve_spatial": "conditioning",
    "ControlNet": "controlnet",
    "ContextTokens": "nonspatial",
    "CrossAttentionBlock": "nonspatial",
    "NONSPATIAL_COMPONENTS": "nonspatial",
    "build_nonspatial": "nonspatial",
    "register_nonspatial": "nonspatial",
    "Condition": "network",
    "DiffusionNet": "network",
    "build_network": "network",
    "PRESETS": "presets",
    "get_config": "presets",
    "AdaGN": "unet",
    "SpatialConditioning": "unet",
    "TimestepBlock": "unet",
    "UNet": "unet",
    "UNetConfig": "unet",
    "timestep_embedding": "unet",
}

__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_attributes(__name__, _HOMES, globals())
