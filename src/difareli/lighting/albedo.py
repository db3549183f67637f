"""The skin albedo model shared by SynthFaces' appearance (``synth/appearance.py``) and the light fit's prior
(:mod:`difareli.lighting.light_fit`): one definition, so the prior is the mean of what SynthFaces draws.
"""

from __future__ import annotations

import numpy as np

#: Skin-tone anchors, light to dark: the 10 tones of the Monk Skin Tone scale (sRGB), a public scale that
#: spans very dark to very light skin more evenly than Fitzpatrick's six types.
MONK_SCALE = np.array([
    [0xF6, 0xED, 0xE4], [0xF3, 0xE7, 0xDB], [0xF7, 0xEA, 0xD0], [0xEA, 0xDA, 0xBA], [0xD7, 0xBD, 0x96],
    [0xA0, 0x7E, 0x56], [0x82, 0x5C, 0x43], [0x60, 0x41, 0x34], [0x3A, 0x31, 0x2A], [0x29, 0x24, 0x20],
], dtype=np.float64) / 255.0
#: The scale's swatches are paler and greyer than skin reads in photos: as albedo they are warmed (less
#: green/blue) and darkened so that a sun plus ambient (irradiance ~1.2) does not clip every light face.
SKIN_ALBEDO_SCALE = 0.8 * np.array([1.0, 0.9, 0.82])


def synthfaces_mean_skin_albedo() -> np.ndarray:
    """Mean skin albedo (RGB) of SynthFaces' appearance model: tone ~ U[0, 1] linearly interpolates the Monk
    scale, so the mean is the trapezoid average of the swatches, times the model's warming/darkening."""
    w = np.ones(len(MONK_SCALE))
    w[[0, -1]] = 0.5
    return (w / w.sum()) @ MONK_SCALE * SKIN_ALBEDO_SCALE
