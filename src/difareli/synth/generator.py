"""SynthFaces: procedural faces rendered under known lights, with every encoding as ground truth.

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

import math
import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterator

import numpy as np

from difareli import sh
from difareli.fileio import RESUME, on_full_disk
from difareli.imageops import LUMA
from difareli.processes import die_with_parent
from difareli.synth.blas import single_thread_blas
from difareli.encodings import (FACE_PARTS, FOREGROUND_PARTS, PART_INDEX, SHADOW_C_HI, SHADOW_C_LO, SHADOW_S_MIN,
                                normalise_c)
from difareli.render import OrthoCamera, Scene, cast_shadows, render_gbuffer
from difareli.shard import select as shard_select
from difareli.store import EncodingStore
from difareli.synth import splits as sp
from difareli.synth import effects as fx_mod
from difareli.synth.appearance import albedo_image, sample_appearance, sample_background
from difareli.synth.lights import Light, add_suns, extra_sun_rng, light_rng, sample_light

ENCODINGS = ("image", "light", "shape", "cam", "identity", "shadow", "background", "masks", "shadow_map",
             "shading", "normal", "depth", "face_mask", "light_gt", "shading_gt", "shadow_gt", "shadow_map_gt",
             "shadow_fraction_gt", "shadow_visible_gt")
#: v3 (``inputs=estimated``): the geometry's exact values too.
GEOMETRY_GT = ("shape_gt", "cam_gt", "identity_gt", "masks_gt", "normal_gt", "depth_gt", "face_mask_gt")
#: ``inputs``: what the model-input encodings hold (the exact values are always in the ``*_gt`` ones):
#: estimated = every input (v3), estimated_light = light/shading/shadow/shadow_map only (v2), exact.
INPUTS = ("estimated", "estimated_light", "exact")
#: ``estimation_resolution=0``: the smallest multiple of the stored size >= this (measured: docs/synthfaces_v3.md).
AUTO_ESTIMATION = 128
#: The generator version in the store header (``synthfaces_version``); stores without the key are v1/v2.
VERSION = 3
IDENTITY_DIM = 128  # matches the dlib face descriptor used for real photos
# The c range lives in the schema (shared with targets for relighting); re-exported under short names.
S_MIN, C_LO, C_HI = SHADOW_S_MIN, SHADOW_C_LO, SHADOW_C_HI
_FACE_IDX = np.array([PART_INDEX[p] for p in FACE_PARTS])
_FG_IDX = np.array([PART_INDEX[p] for p in FOREGROUND_PARTS])


class ConfigError(ValueError):
    """An invalid SynthFaces configuration, or one that does not match the existing store."""


@dataclass(frozen=True)
class SynthConfig:
    """What defines a SynthFaces data set (stored in the store header; a resume must match it)."""

    subjects: int
    lights: int
    resolution: int
    seed: int = 0
    light_group_size: int = 2          # subjects sharing the same lights (protocol ii needs >= 2)
    splits: dict = field(default_factory=lambda: {"train": 0.8, "val": 0.1, "test": 0.1})
    shading_region: str = "face"       # "face": R/normal on the BFM face triangles (SPEC 3); "mesh": everywhere
    cam_jitter: float = 0.05           # relative scale jitter; translation jitter is half of it in NDC
    realism: str = "lambertian"        # effects preset (synth/effects.py); "lambertian" = SynthFaces v1 images
    effects: dict = field(default_factory=dict)  # per-effect overrides of the preset (None keeps it)
    inputs: str = "exact"              # INPUTS: what the model inputs hold
    estimation_resolution: int = 0     # inputs=estimated: render this large for the estimators (0: AUTO_ESTIMATION)
    shadow_visible: float = 0.25       # shadow_visible_gt: a pixel losing more than this share of its light
    c_quantile: float = 0.01           # v3 c range: these quantiles of the train split's c (0: min and max)

    def __post_init__(self):
        for key, lo in (("subjects", 1), ("lights", 1), ("resolution", 16), ("light_group_size", 1)):
            if int(getattr(self, key)) < lo:
                raise ConfigError(f"{key}={getattr(self, key)} is invalid: must be >= {lo}")
        object.__setattr__(self, "splits", {str(k): float(v) for k, v in dict(self.splits).items()})
        if self.shading_region not in ("face", "mesh"):
            raise ConfigError(f"shading_region={self.shading_region!r} is invalid: use 'face' or 'mesh'")
        try:  # stored resolved, so the header (and a resume check) names every effect
            object.__setattr__(self, "effects", fx_mod.Effects.resolve(self.realism, self.effects).as_dict())
        except ValueError as e:
            raise ConfigError(str(e)) from None
        if self.inputs not in INPUTS:
            raise ConfigError(f"inputs={self.inputs!r} is invalid: use one of {list(INPUTS)}")
        r = int(self.estimation_resolution) or -(-AUTO_ESTIMATION // self.resolution) * self.resolution
        object.__setattr__(self, "estimation_resolution", r)  # 0 = auto, stored resolved
        if r < self.resolution or r % self.resolution:
            raise ConfigError(f"estimation_resolution={r} is invalid: 0 or a multiple of resolution={self.resolution}")
        if not 0.0 < float(self.shadow_visible) < 1.0 or not 0.0 <= float(self.c_quantile) < 0.5:
            raise ConfigError(f"shadow_visible={self.shadow_visible} / c_quantile={self.c_quantile} is invalid: use "
                              "shadow_visible in (0, 1) and c_quantile in [0, 0.5)")

    @property
    def fx(self) -> "fx_mod.Effects":
        return fx_mod.Effects(**self.effects)

    @property
    def encodings(self) -> tuple[str, ...]:
        return ENCODINGS + (GEOMETRY_GT if self.inputs == "estimated" else ())

    def header_meta(self) -> dict:
        return {"generator": "synthfaces", "synthfaces_version": VERSION, **asdict(self), "gamma": "none",
                "identity_dim": IDENTITY_DIM, "shadow_c": {"s_min": S_MIN, "c_lo": C_LO, "c_hi": C_HI}}


# ------------------------------------------------------------------------------------------ one subject
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


def build_subject(k: int, cfg: SynthConfig) -> Subject:
    """Sample and render subject ``k`` (geometry, appearance, camera); deterministic in ``(cfg.seed, k)``."""
    from difareli.synth.accessories import build_head, default_camera, sample_accessories
    from difareli.face_model import FaceModel

    rng = np.random.default_rng([cfg.seed, k])
    params = FaceModel.load().sample_params(rng)
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
        from difareli.render.ao import ambient_occlusion

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
        raise ValueError(f"{len(maps)} cast-shadow maps for {n} suns")
    return [m & hit for m in maps]


def visible_shadow(e_open: np.ndarray, sun_terms: list, casts: list, key: np.ndarray, hit: np.ndarray,
                   threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """(fraction, visible): per pixel, the share of its unshadowed irradiance ``e_open`` that the cast shadows
    remove (``sum_i cast_i Y(sun_i) / Y(e_open)``, 0 off the mesh) and ``fraction > threshold | key`` (the key
    sun's own cast mask) on the mesh."""
    den = np.maximum(e_open @ LUMA, 1e-6)
    frac = np.zeros(hit.shape, np.float64)
    for sun, c in zip(sun_terms, casts):
        frac += c * ((sun @ LUMA) / den)
    frac = np.where(hit, np.clip(frac, 0.0, 1.0), 0.0)
    return frac.astype(np.float32), hit & ((frac > threshold) | key)


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
    diffuse = subject.albedo * e
    lit = np.clip(diffuse if spec is None else diffuse + spec, 0.0, 1.0)
    img = np.where(hit[..., None], lit, subject.background)
    image = np.round(img * 255.0).astype(np.uint8)

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
        "shadow_fraction_gt": fraction, "shadow_visible_gt": visible,
    }
    # Share of the face pixels' (unclipped) light in each effect's term: what a ratio image cannot redo.
    total = float((diffuse if spec is None else diffuse + spec)[face].sum()) or 1.0
    energy = {"specular": 0.0 if spec is None else float(spec[face].sum()) / total,
              "subsurface": 0.0 if sss_gain is None else float((subject.albedo * sss_gain)[face].sum()) / total,
              "ao_removed": 0.0 if subject.ao is None else
              float((subject.albedo * (e_amb_open - e_amb))[face].sum()) / total}
    meta = {"c_gt": c, "energy": {k: round(v, 6) for k, v in energy.items()}}
    if cfg.inputs == "estimated":
        from difareli.synth.estimated import estimate_all

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
        from difareli.synth.estimated import estimate_inputs

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
    from dataclasses import replace

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


def render_records(k: int, light_indices: list[int], cfg: SynthConfig, split: str) -> Iterator[tuple[str, dict, dict]]:
    """Yield ``(record_id, arrays, meta)`` for subject ``k`` under each light in ``light_indices``."""
    subject = build_subject(k, cfg)
    group = sp.light_group(k, cfg.light_group_size)
    lights = [sample_light(light_rng(cfg.seed, group, j)) for j in light_indices]
    fx = cfg.fx
    if fx.multi_sun:
        lights = [add_suns(light, extra_sun_rng(cfg.seed, group, j)) for j, light in zip(light_indices, lights)]
    # One cast-shadow pass per sun of every light, in one call (the BVH is built once per subject).
    dirs = [d for light in lights for d, _ in light.suns()]
    maps = list(cast_shadows(subject.scene, subject.gbuffer, np.array(dirs))) if dirs else []

    big = estimation_images(k, lights, cfg)
    for i, (j, light) in enumerate(zip(light_indices, lights)):
        k_suns = len(light.suns())
        casts, maps = maps[:k_suns], maps[k_suns:]
        arrays, fx_meta = shade(subject, light, casts, cfg, None if big is None else big[i])
        meta = {"subject": sp.subject_name(k), "light_index": j, "light_group": group, "split": split,
                "source": "synthfaces", "c": float(arrays["shadow"][0]), **light.meta(), **subject.meta,
                "realism": cfg.realism, "effects": fx.as_dict(), "inputs": cfg.inputs, **fx_meta}
        yield sp.record_id(k, j), arrays, meta


# ------------------------------------------------------------------------------------------ data set
def _open_store(out_dir: str, cfg: SynthConfig, durable: bool) -> EncodingStore:
    dims = {"H": cfg.resolution, "W": cfg.resolution, "S": _shape_dim(), "D": IDENTITY_DIM}
    want = cfg.header_meta()
    if os.path.exists(os.path.join(out_dir, "store.json")):
        store = EncodingStore.open(out_dir, writable=True, durable=durable)
        have = store.store_meta
        if have.get("synthfaces_version") is None:
            old = 2 if "inputs" in have else 1
            raise ConfigError(
                f"store {out_dir} is a SynthFaces v{old} store (it still opens for reading); this generator writes v3 "
                f"records and does not add them to it. Regenerate into a new folder: difareli-synth out_dir=<new dir> "
                f"subjects={cfg.subjects} lights={cfg.lights} resolution={cfg.resolution} seed={cfg.seed} "
                f"realism={cfg.realism} inputs={cfg.inputs}")
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        if diff:
            raise ConfigError(f"store {out_dir} was generated with a different configuration "
                             f"(key: (existing, requested)) {diff}; use a new out_dir to generate this one")
        # Same configuration: the header keeps what generation added to it (the v3 c range).
        return EncodingStore.create(out_dir, dims, cfg.encodings, None, durable=durable)
    return EncodingStore.create(out_dir, dims, cfg.encodings, want, durable=durable)


def _shape_dim() -> int:
    from difareli.face_model import SHAPE_DIM

    return int(SHAPE_DIM)


def _work(args) -> int:
    # Pool task: render one subject's missing lights and write them; returns the number written.
    out_dir, cfg, k, todo, split, durable = args
    store = EncodingStore.open(out_dir, durable=durable)
    with single_thread_blas():
        return sum(bool(store.write(rid, arrays, meta)) for rid, arrays, meta in render_records(k, todo, cfg, split))


@dataclass
class GenerateReport:
    written: int
    skipped: int
    seconds: float
    problems: list[str]

    @property
    def images_per_second(self) -> float:
        return self.written / self.seconds if self.seconds > 0 else 0.0


def generate(out_dir: str, subjects: int, lights: int, resolution: int, seed: int = 0, *, workers: int = 1,
             durable: bool = False, progress: Callable[[int, int], None] | None = None,
             shard: str | None = None, **options) -> GenerateReport:
    """Generate (or complete) the data set in ``out_dir``; existing records are skipped.

    ``options`` are the other :class:`SynthConfig` fields (``light_group_size``, ``splits``, ...).
    ``workers > 1`` renders subjects in a process pool; results do not depend on it.
    ``durable`` fsyncs every file (atomicity against a killed run does not need it: records are renamed
    into place whole either way). ``shard="i/n"`` renders only the subjects of that shard (``difareli.shard``);
    shards may run concurrently into one ``out_dir``. A full disk is one line naming the file (records already
    written are whole: rerun to resume), with no partial record or scratch file left.
    """
    with on_full_disk(out_dir, scratch=[out_dir], fix=RESUME):
        return _generate(out_dir, subjects, lights, resolution, seed, workers=workers, durable=durable,
                         progress=progress, shard=shard, **options)


def _generate(out_dir: str, subjects: int, lights: int, resolution: int, seed: int, *, workers: int, durable: bool,
              progress: Callable[[int, int], None] | None, shard: str | None, **options) -> GenerateReport:
    cfg = SynthConfig(subjects=subjects, lights=lights, resolution=resolution, seed=seed, **options)
    try:
        splits = sp.assign_splits(cfg.subjects, cfg.splits, cfg.light_group_size, cfg.seed)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.inputs == "estimated":
        from difareli.synth.estimated import missing_estimators

        if why := missing_estimators():
            raise ConfigError(why)
    store = _open_store(out_dir, cfg, durable)
    split_of = sp.split_of(splits)
    existing = set(store.ids())
    tasks, skipped = [], 0
    mine = shard_select(range(cfg.subjects), shard, key=sp.subject_name)  # a subject's lights stay together
    for k in mine:
        todo = [j for j in range(cfg.lights) if sp.record_id(k, j) not in existing]
        skipped += cfg.lights - len(todo)
        if todo:
            tasks.append((out_dir, cfg, k, todo, split_of[k], durable))
    total = sum(len(t[3]) for t in tasks)
    t0 = time.perf_counter()
    written = 0
    if tasks:
        if workers > 1 and len(tasks) > 1:
            # Build the face model and head template once here; forked workers inherit them (~1-5 s each).
            from difareli.synth.accessories import _template

            _template()
            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
            # Workers die with this process (SIGKILL included) instead of lingering as orphans.
            with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=ctx,
                                     initializer=die_with_parent, initargs=(os.getpid(),)) as pool:
                for n in pool.map(_work, tasks, chunksize=1):
                    written += n
                    if progress:
                        progress(written, total)
        else:
            for t in tasks:
                written += _work(t)
                if progress:
                    progress(written, total)
    seconds = time.perf_counter() - t0
    with on_full_disk(f"{out_dir}/{sp.SPLITS_FILE}, {sp.PROTOCOLS_FILE}", scratch=[out_dir], fix=RESUME):
        sp.write_split_files(out_dir, splits, cfg.lights, cfg.light_group_size, cfg.seed)
    store.refresh()
    missing = [sp.record_id(k, j) for k in mine for j in range(cfg.lights)
               if not store.has(sp.record_id(k, j))]
    problems = [f"{rid}: missing" for rid in missing]
    if cfg.inputs == "estimated" and not problems and len(store.ids()) == cfg.subjects * cfg.lights:
        from difareli.synth.c_norm import finalise

        with on_full_disk(f"{out_dir}/store.json (the c range) and the records' shadow maps", scratch=[out_dir],
                          fix="free space and rerun the same command to finish scaling the maps"):
            finalise(store, cfg.c_quantile)  # every record is there: the train split's c range, maps scaled by it
    return GenerateReport(written, skipped, seconds, problems)
