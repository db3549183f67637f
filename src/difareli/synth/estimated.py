"""Model inputs as a user has them (SynthFaces v2, ``inputs: estimated``).

The ``light``, ``shading``, ``shadow`` and ``shadow_map`` encodings of a record are estimated from its
rendered image with the estimators the benchmark and ``difareli-preprocess`` use; the exact values are kept as
``light_gt``, ``shading_gt``, ``shadow_gt``, ``shadow_map_gt``:

- ``light``: :class:`difareli.light_fit.LightFit` (SH least squares on the skin and nose pixels with the
  SynthFaces mean-skin albedo prior, robust refits), called on exactly the arrays the record stores, so it
  equals what ``difareli-benchmark`` fits on that record (``LightFit().from_store``);
- ``shading``: ``sh.shading_reference`` of that light on the stored normals and shading region;
- ``shadow`` / ``shadow_map``: :class:`difareli.estimators.shadow.ShadowEstimator` (the logistic classifier's
  calibrated c, cast rays toward the fitted light's dominant direction) with the fitted light and prior.

Geometry (normals, G-buffer, scene) stays exact: the FaceMesh/BFM geometry estimators need mediapipe,
an optional extra (``docs/synthfaces_v2.md`` says what that leaves out).
"""

from __future__ import annotations

import numpy as np

from difareli import sh
from difareli.encodings import PART_INDEX

_SHADOW = None


def shadow_estimator():
    """The preprocess shadow estimator with its shipped weights (loaded once per process)."""
    global _SHADOW
    if _SHADOW is None:
        from difareli.estimators.shadow import ShadowEstimator

        _SHADOW = ShadowEstimator()
    return _SHADOW


def estimate_inputs(arrays: dict, region: np.ndarray, gbuffer, scene) -> tuple[dict, dict]:
    """Estimated ``light``/``shading``/``shadow``/``shadow_map`` from a record's ``image``, ``normal``,
    ``face_mask`` and ``masks`` (as stored) and the subject's G-buffer and scene; plus meta (c logit etc.).

    Raises ValueError when the light fit has too few usable skin pixels.
    """
    from difareli.light_fit import LightFit

    fit = LightFit()
    rec = {k: arrays[k] for k in LightFit.ENCODINGS}
    light = fit(rec).astype(np.float32)
    shading = np.asarray(sh.shading_reference(light, arrays["normal"], mask=region), dtype=np.float32)
    ctx = {"image": arrays["image"], "gbuffer": gbuffer, "scene": scene, "light": light,
           "skin": np.asarray(arrays["masks"]) == PART_INDEX["skin"], "albedo_prior": fit.prior()}
    out = shadow_estimator()(ctx, set())
    info = {"c_logit": round(out["shadow_info"]["logit"], 6), "p_shadow": round(out["shadow_info"]["p_shadow"], 6)}
    return {"light": light, "shading": shading, "shadow": out["shadow"].astype(np.float32),
            "shadow_map": out["shadow_map"].astype(np.float32)}, info
