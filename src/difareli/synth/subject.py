"""One SynthFaces subject: sampled, rendered once, then shaded under each of its lights (every encoding as exact
ground truth; the store around it: ``synth/generator.py``, its settings: ``synth/config.py``).

Per subject ``k`` (all randomness from ``np.random.default_rng([seed, k])``, lights from
``lights.light_rng``) the mesh, the G-buffer, the albedo and the background are made once; each of its
lights then costs one batched shadow-ray pass and some arithmetic.

Image formation (no gamma: like DECA's photometric model, which fits SH straight to sRGB pixels, the image
is the Lambertian product itself, so a light estimated from it is the light that made it)::

    image = clip(albedo * (E_ambient(n) + sun_rgb * visible * max(0, n.d)), 0, 1)   on mesh pixels
          = background                                                             elsewhere

``light`` is ``ambient + sh.directional_light(d, sun_rgb)``, the SH of the full lighting (sun included).

Cast-shadow strength ``c`` (the ``shadow`` encoding)::

    s = mean over mesh pixels of  cast(p) * Y(sun_rgb max(0, n.d)) / Y(E_ambient + sun_rgb max(0, n.d))
    c = logit(clip(s, S_MIN, 1 - S_MIN))

i.e. the fraction of the foreground's light that cast shadows remove (``Y`` = Rec. 709 luminance);
``c = logit(S_MIN)`` ≈ -6.9 means no visible cast shadow. ``shadow_map`` = binary cast-shadow map on the
mesh times ``normalise_c(c)`` = ``(c - C_LO) / (C_HI - C_LO)`` clipped to [0, 1], a fixed range (not a
data-set min/max) so that records can be written one at a time and stores compared.

SynthFaces v2 (``docs/synthfaces_v2.md``): ``realism`` selects appearance effects (``synth/effects.py``:
specular, subsurface wrap, ambient occlusion, key + fill + rim suns; ``lambertian`` = the formation above,
bit for bit). With several suns, every sun casts its own shadow: ``s`` sums the light each one's cast
shadow removes (``cast_i * Y(sun_i f_i(n)) / Y(E_unshadowed)``) and the binary map is the union of their cast
maps. ``inputs: estimated_light`` stores the estimated ``light``/``shading``/``shadow``/``shadow_map``
(``synth/estimated.py``); the exact ones are always kept as ``light_gt``, ``shading_gt``, ``shadow_gt``,
``shadow_map_gt``.

SynthFaces v3 (``docs/synthfaces_v3.md``): ``inputs: estimated`` estimates every model input from the rendered
image with the photo estimators (geometry, masks and identity too; exact values under ``*_gt``), and the store's
c range is its training split's (``synth/c_norm.py``). Every mode stores what "visibly shadowed" means:
``shadow_fraction_gt`` (per pixel, the share of its unshadowed light that cast shadows remove, every sun) and
``shadow_visible_gt`` (that share above ``shadow_visible``, or in the key sun's own cast shadow); in v3 stores
``shadow_map_gt`` is the visible mask times the normalised exact c.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace

import numpy as np

from difareli.lighting import sh
from difareli.data.encodings import FACE_PARTS, FOREGROUND_PARTS, PART_INDEX, normalise_c
from difareli.utils.imageops import LUMA
from difareli.render import OrthoCamera, Scene, cast_shadows, render_gbuffer
from difareli.render.visible import visible_shadow
from difareli.synth import effects as fx_mod
from difareli.synth.appearance import albedo_image, sample_appearance, sample_background
from difareli.synth.config import GEOMETRY_GT, IDENTITY_DIM, S_MIN, SynthConfig
from difareli.synth.lights import Light
from difareli.errors import UserError
from difareli.render.ao import ambient_occlusion
from difareli.synth.estimated import estimate_all, estimate_inputs

_FACE_IDX = np.array([PART_INDEX[p] for p in FACE_PARTS])
_FG_IDX = np.array([PART_INDEX[p] for p in FOREGROUND_PARTS])


@dataclass
class Subject:
    """A subject rendered once: geometry, G-buffer, albedo, background and the per-subject encodings."""

    index: int
    scene: Scene
    gbuffer: object
    face_mesh: np.ndarray    # HxW bool: pixels of the BFM face triangles (shading-reference region)
    albedo: np.ndarray       # HxWx3 float32, 0 off-mesh
    background: np.ndarray   # HxWx3 float32
    shape: np.ndarray
    cam: np.ndarray
    identity: np.ndarray
    meta: dict
    ao: np.ndarray | None = None        # HxW ambient occlusion (effects.ambient_occlusion), once per subject
    spec_ks: np.ndarray | None = None   # HxW specular strength / exponent maps (effects.specular)
    spec_s: np.ndarray | None = None
    sss: np.ndarray | None = None       # HxW bool, where the subsurface wrap applies (effects.subsurface)


def build_subject(k: int, cfg: SynthConfig, pose: tuple[float, float, float] | None = None) -> Subject:
    """Sample and render subject ``k`` (geometry, appearance, camera); deterministic in ``(cfg.seed, k)``;
    ``pose``: (yaw, pitch, roll) degrees in place of the sampled head pose (the other draws stay the same)."""
    from difareli.synth.accessories import build_head, default_camera, sample_accessories
    from difareli.render.face_model import FaceModel

    rng = np.random.default_rng([cfg.seed, k])
    params = FaceModel.load().sample_params(rng)
    if pose is not None:  # after the draw, so the random stream (and so the rest of the subject) is unchanged
        params = dataclasses.replace(params, pose=np.asarray(pose, np.float64))
    accessories = sample_accessories(rng)
    appearance = sample_appearance(rng)
    background = sample_background(rng)
    identity = rng.standard_normal(IDENTITY_DIM)
    identity /= np.linalg.norm(identity)
    head = build_head(params, accessories)
    s, tx, ty = (float(x) for x in default_camera(head))
    # Framing jitter: scale by a few percent, shift by a few percent of the image (in NDC: shift / s).
    s *= float(np.exp(rng.normal(0, cfg.cam_jitter)))
    tx += float(rng.normal(0, cfg.cam_jitter / 2)) / s
    ty += float(rng.normal(0, cfg.cam_jitter / 2)) / s
    cam = OrthoCamera(s, tx, ty)
    scene = Scene.from_arrays(head.vertices, head.faces, head.face_labels)
    H = W = cfg.resolution
    gb = render_gbuffer(scene, cam, H, W)
    size = float(np.ptp(np.asarray(head.vertices)[:, 0]))
    albedo = albedo_image(appearance, gb.label, gb.points, gb.hit, size)
    # The shading-reference mesh (SPEC 3): the BFM face triangles, without skull, ears, neck and hair.
    face_mesh = gb.hit & (gb.triangle >= 0) & (gb.triangle < head.n_face_faces)
    meta = {"skin_tone": round(appearance.skin_tone, 4), "hair": appearance.hair_name,
            "hat": accessories.hat, "bald": accessories.bald, "background": background.kind}
    subject = Subject(k, scene, gb, face_mesh, albedo, background.render(H, W),
                      np.asarray(head.shape_vector, np.float32), cam.to_array(), identity.astype(np.float32), meta)
    fx = cfg.fx  # v2 effects: their own streams, so the v1 draws above stay the same
    if fx.ambient_occlusion:
        subject.ao = ambient_occlusion(scene, gb, fx_mod.AO_RAYS, fx_mod.AO_DISTANCE, seed=[cfg.seed, k, 3])
    if fx.specular:
        subject.spec_ks, subject.spec_s = fx_mod.specular_maps(gb.label, gb.points, gb.hit)
    if fx.subsurface:
        subject.sss = fx_mod.sss_mask(gb.label, gb.hit)
    return subject


def _cast_list(cast, n: int, hit: np.ndarray) -> list[np.ndarray]:
    # None (no sun), one bool map (the key sun, v1 callers) or one map per sun -> a list of n maps on the mesh.
    if cast is None:
        maps = [np.zeros_like(hit)] * n
    elif isinstance(cast, np.ndarray) and cast.ndim == 2:
        maps = [cast]
    else:
        maps = list(cast)
    if len(maps) != n:
        raise UserError(f"{len(maps)} cast-shadow maps for {n} suns")
    return [m & hit for m in maps]


def _sunlight(subject: Subject, suns, casts, n: np.ndarray, e_amb: np.ndarray):
    """The suns' light on ``subject`` added to the ambient ``e_amb``: the irradiance with and without the cast
    shadows (``e``, ``e_open``), the specular and subsurface terms (None without the effect) and each sun's
    unshadowed term."""
    e, e_open = e_amb, e_amb
    spec = sss_gain = None
    sun_terms = []
    for (d, rgb), c in zip(suns, casts):
        ndl = n @ d
        sun = np.maximum(ndl, 0.0)[..., None] * rgb
        if subject.sss is not None:
            wrapped = np.where(subject.sss[..., None], fx_mod.wrap(ndl, fx_mod.WRAP_RGB) * rgb, sun)
            gain = (wrapped - sun) * (~c)[..., None]
            sss_gain = gain if sss_gain is None else sss_gain + gain
            sun = wrapped
        if subject.spec_ks is not None:
            lobe = (subject.spec_ks * fx_mod.blinn_phong(n, d, subject.spec_s) * ~c)[..., None] * rgb
            spec = lobe if spec is None else spec + lobe
        e = e + sun * (~c)[..., None]
        e_open = e_open + sun
        sun_terms.append(sun)
    return e, e_open, spec, sss_gain, sun_terms


def _unshadowed(subject: Subject, suns, n: np.ndarray, e_amb: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """The image under the same light with no cast shadow (every sun reaches every point; ambient occlusion kept)."""
    e, _, spec, _, _ = _sunlight(subject, suns, [np.zeros_like(hit)] * len(suns), n, e_amb)
    lit = np.clip(subject.albedo * e if spec is None else subject.albedo * e + spec, 0.0, 1.0)
    return np.round(np.where(hit[..., None], lit, subject.background) * 255.0).astype(np.uint8)


def shade(subject: Subject, light: Light, cast, cfg: SynthConfig,
          est_image: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All encodings of ``subject`` under ``light`` and the record's effect meta; ``cast``: one bool cast-shadow
    map per sun of ``light.suns()`` (a single map or None are accepted for one sun or none); ``est_image``: the
    same record rendered at the estimation resolution (v3)."""
    gb = subject.gbuffer
    hit = gb.hit
    n = gb.normal.astype(np.float64)
    e_amb_open = sh.irradiance(light.ambient, n)
    e_amb = e_amb_open if subject.ao is None else e_amb_open * subject.ao[..., None]
    suns = light.suns()
    casts = _cast_list(cast, len(suns), hit) if suns else []
    e, e_open, spec, sss_gain, sun_terms = _sunlight(subject, suns, casts, n, e_amb)
    diffuse = subject.albedo * e
    lit = np.clip(diffuse if spec is None else diffuse + spec, 0.0, 1.0)
    img = np.where(hit[..., None], lit, subject.background)
    image = np.round(img * 255.0).astype(np.uint8)
    unshadowed = _unshadowed(subject, suns, n, e_amb, hit) if any(m.any() for m in casts) else image

    # c: the fraction of the light that every sun's cast shadow removes (one sun: exactly v1's expression).
    den = np.maximum(e_open @ LUMA, 1e-6)
    strength = float(sum((c * ((sun @ LUMA) / den)).sum() for sun, c in zip(sun_terms, casts))
                     / max(hit.sum(), 1))
    s = float(np.clip(strength, S_MIN, 1 - S_MIN))
    c = math.log(s / (1 - s))
    cast_any = np.zeros_like(hit)
    for m in casts:
        cast_any = cast_any | m
    key = casts[0] if casts and light.has_sun else np.zeros_like(hit)
    fraction, visible = visible_shadow(e_open, sun_terms, casts, key, hit, cfg.shadow_visible)

    label = gb.label.astype(np.uint8)
    face = np.isin(label, _FACE_IDX)
    region = subject.face_mesh if cfg.shading_region == "face" else hit
    normal = np.where(region[..., None], gb.normal, 0.0).astype(np.float32)
    light_sh = light.sh()
    shading = np.asarray(sh.shading_reference(light_sh, normal, mask=region), dtype=np.float32)
    background = np.where(np.isin(label, _FG_IDX)[..., None], 0, image).astype(np.uint8)
    shadow = np.array([c], np.float32)
    shadow_map = (cast_any * normalise_c(c)).astype(np.float32)
    arrays = {
        "image": image, "light": light_sh, "shape": subject.shape, "cam": subject.cam,
        "identity": subject.identity, "shadow": shadow, "background": background,
        "masks": label, "shadow_map": shadow_map, "shading": shading,
        "normal": normal, "face_mask": face,
        # Whole-mesh depth (hair, hat and neck included) so target shadow maps can be ray-marched from it.
        "depth": np.where(hit, gb.depth, 0.0).astype(np.float32),
        "light_gt": light_sh, "shading_gt": shading, "shadow_gt": shadow, "shadow_map_gt": shadow_map,
        "shadow_fraction_gt": fraction, "shadow_visible_gt": visible, "image_unshadowed_gt": unshadowed,
    }
    # Share of the face pixels' (unclipped) light in each effect's term: what a ratio image cannot redo.
    total = float((diffuse if spec is None else diffuse + spec)[face].sum()) or 1.0
    energy = {"specular": 0.0 if spec is None else float(spec[face].sum()) / total,
              "subsurface": 0.0 if sss_gain is None else float((subject.albedo * sss_gain)[face].sum()) / total,
              "ao_removed": 0.0 if subject.ao is None else
              float((subject.albedo * (e_amb_open - e_amb))[face].sum()) / total}
    meta = {"c_gt": c, "energy": {k: round(v, 6) for k, v in energy.items()}}
    if cfg.inputs == "estimated":
        for k in GEOMETRY_GT:
            arrays[k] = arrays[k[:-3]]
        arrays["shadow_map_gt"] = visible.astype(np.float32)  # binary until the store's c range is known
        try:
            est, info = estimate_all(image, est_image)
            arrays.update(est)
            meta.update(info)
        except ValueError as err:  # a face the estimators miss: the exact inputs are kept, flagged
            arrays["shadow_map"] = cast_any.astype(np.float32)
            meta["inputs_fallback"] = f"exact inputs stored: {err}"
    elif cfg.inputs == "estimated_light":
        try:
            est, info = estimate_inputs(arrays, region, gb, subject.scene)
            arrays.update(est)
            meta.update(info)
        except ValueError as err:  # too few usable skin pixels: keep the exact inputs, flagged
            meta["inputs_fallback"] = f"exact inputs stored: {err}"
    return arrays, meta


def estimation_images(k: int, lights: list, cfg) -> list[np.ndarray] | None:
    """Subject ``k`` rendered under ``lights`` at ``cfg.estimation_resolution`` (v3), or None when the estimators
    read the stored image itself."""
    r = int(cfg.estimation_resolution)
    if cfg.inputs != "estimated" or r == cfg.resolution:
        return None
    big = replace(cfg, resolution=r, inputs="exact")
    subject = build_subject(k, big)
    dirs = [d for light in lights for d, _ in light.suns()]
    maps = list(cast_shadows(subject.scene, subject.gbuffer, np.array(dirs))) if dirs else []
    out = []
    for light in lights:
        n = len(light.suns())
        casts, maps = maps[:n], maps[n:]
        out.append(shade(subject, light, casts, big)[0]["image"])
    return out

