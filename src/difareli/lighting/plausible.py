"""Target lights a face cannot be lit with: an SH light judged on the face's own normals, before any relight.

An SH light with too small (or negative) an ambient term gives negative irradiance on much of a face, and one far
brighter than the face's own light saturates its relight; both decode to noise rather than failing, so the
relighter warns about them by name (:meth:`~difareli.relight.relighter.Relighter.check_inputs`) and does not blame
the sampler for the saturation they cause.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from difareli.data.encodings import known_normals
from difareli.lighting import sh

#: A target light is said to be implausible for a face when its irradiance is negative on more than this share of
#: the face's known normals (an SH light whose ambient term is too small or negative) ...
NEGATIVE_SHARE = 0.5
#: ... or when its mean irradiance on the face is over this many times the source's own (an absurd ambient).
BRIGHTER_MAX = 10.0


def implausible_lights(arrays: Mapping[str, np.ndarray], lights: np.ndarray) -> dict[int, str]:
    """Target lights a face cannot be lit with, judged on the source's stored normals: index -> why, in terms of
    the light (negative irradiance on much of the face, or far brighter than the source's own light). Empty
    without normals (a model that reads no shading)."""
    if "normal" not in arrays or "light" not in arrays:
        return {}
    normal = np.asarray(arrays["normal"], np.float64)
    n = normal[known_normals(normal)]
    if len(n) == 0:
        return {}
    own = float(sh.irradiance(np.asarray(arrays["light"], np.float64), n).mean())
    out = {}
    for k, light in enumerate(np.asarray(lights, np.float64)):
        e = sh.irradiance(light, n).mean(axis=-1)  # (M,) grey irradiance per face pixel
        if (e < 0).mean() > NEGATIVE_SHARE:
            out[k] = (f"target light {k} gives negative irradiance on {(e < 0).mean():.0%} of the face (its ambient, "
                      "SH band 0, is too small or negative): give a light with a larger ambient term")
        elif own > 0 and e.mean() > BRIGHTER_MAX * own:
            out[k] = (f"target light {k} is {e.mean() / own:.0f}x brighter on the face than the source's own light: "
                      "the relight saturates; scale the light down")
    return out
