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
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import multiprocessing as mp
import os
import re
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterator

import numpy as np

from difareli import sh
from difareli.encodings import (FACE_PARTS, FOREGROUND_PARTS, PART_INDEX, SHADOW_C_HI, SHADOW_C_LO, SHADOW_S_MIN,
                                normalise_c)
from difareli.render import OrthoCamera, Scene, cast_shadows, render_gbuffer
from difareli.shard import select as shard_select
from difareli.store import EncodingStore
from difareli.synth import splits as sp
from difareli.synth.appearance import albedo_image, sample_appearance, sample_background
from difareli.synth.lights import Light, light_rng, sample_light

ENCODINGS = ("image", "light", "shape", "cam", "identity", "shadow", "background", "masks", "shadow_map",
             "shading", "normal", "depth", "face_mask")
IDENTITY_DIM = 128  # matches the dlib face descriptor used for real photos
# The c range lives in the schema (shared with targets for relighting); re-exported under short names.
S_MIN, C_LO, C_HI = SHADOW_S_MIN, SHADOW_C_LO, SHADOW_C_HI
_LUMA = np.array([0.2126, 0.7152, 0.0722])
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

    def __post_init__(self):
        for key, lo in (("subjects", 1), ("lights", 1), ("resolution", 16), ("light_group_size", 1)):
            if int(getattr(self, key)) < lo:
                raise ConfigError(f"{key}={getattr(self, key)} is invalid: must be >= {lo}")
        object.__setattr__(self, "splits", {str(k): float(v) for k, v in dict(self.splits).items()})
        if self.shading_region not in ("face", "mesh"):
            raise ConfigError(f"shading_region={self.shading_region!r} is invalid: use 'face' or 'mesh'")

    def header_meta(self) -> dict:
        return {"generator": "synthfaces", **asdict(self), "gamma": "none", "identity_dim": IDENTITY_DIM,
                "shadow_c": {"s_min": S_MIN, "c_lo": C_LO, "c_hi": C_HI}}


@contextlib.contextmanager
def single_thread_blas():
    """Run numpy's OpenBLAS on one thread: its multi-threaded gemv sums in a thread-count dependent order,
    which changed mesh vertices in the last float bit (and pixels at silhouettes) between a run in this
    process and one in pool workers. (threadpoolctl does this too but is not a dependency.)"""
    libs = []
    try:
        with open("/proc/self/maps") as f:
            maps = f.read()
    except OSError:
        maps = ""
    for path in sorted(set(re.findall(r"(/\S*openblas\S*\.so\S*)", maps))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas", "64_"), ("openblas", "64_"), ("openblas", ""),
                               ("scipy_openblas", "")):
            get, set_ = f"{prefix}_get_num_threads{suffix}", f"{prefix}_set_num_threads{suffix}"
            if hasattr(lib, get) and hasattr(lib, set_):
                libs.append((getattr(lib, set_), int(getattr(lib, get)())))
                break
    for set_, _ in libs:
        set_(ctypes.c_int(1))
    try:
        yield
    finally:
        for set_, n in libs:
            set_(ctypes.c_int(n))


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


def build_subject(k: int, cfg: SynthConfig) -> Subject:
    """Sample and render subject ``k`` (geometry, appearance, camera); deterministic in ``(cfg.seed, k)``."""
    from difareli.synth.accessories import build_head, default_camera, sample_accessories
    from difareli.synth.face_model import FaceModel

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
    return Subject(k, scene, gb, face_mesh, albedo, background.render(H, W),
                   np.asarray(head.shape_vector, np.float32), cam.to_array(), identity.astype(np.float32), meta)


def shade(subject: Subject, light: Light, cast: np.ndarray | None, cfg: SynthConfig) -> dict[str, np.ndarray]:
    """All encodings of ``subject`` under ``light``; ``cast`` is its bool cast-shadow map (None: no sun)."""
    gb = subject.gbuffer
    hit = gb.hit
    n = gb.normal.astype(np.float64)
    e_amb = sh.irradiance(light.ambient, n)
    ndl = np.maximum(n @ light.sun_dir, 0.0)
    sun = ndl[..., None] * light.sun_rgb
    cast = np.zeros_like(hit) if cast is None else (cast & hit)
    e = e_amb + sun * (~cast)[..., None]
    lit = np.clip(subject.albedo * e, 0.0, 1.0)
    img = np.where(hit[..., None], lit, subject.background)
    image = np.round(img * 255.0).astype(np.uint8)

    lost = (sun @ _LUMA) / np.maximum((e_amb + sun) @ _LUMA, 1e-6)
    strength = float((cast * lost).sum() / max(hit.sum(), 1))
    s = float(np.clip(strength, S_MIN, 1 - S_MIN))
    c = math.log(s / (1 - s))

    label = gb.label.astype(np.uint8)
    face = np.isin(label, _FACE_IDX)
    region = subject.face_mesh if cfg.shading_region == "face" else hit
    normal = np.where(region[..., None], gb.normal, 0.0).astype(np.float32)
    light_sh = light.sh()
    shading = np.asarray(sh.shading_reference(light_sh, normal, mask=region), dtype=np.float32)
    background = np.where(np.isin(label, _FG_IDX)[..., None], 0, image).astype(np.uint8)
    return {
        "image": image, "light": light_sh, "shape": subject.shape, "cam": subject.cam,
        "identity": subject.identity, "shadow": np.array([c], np.float32), "background": background,
        "masks": label, "shadow_map": (cast * normalise_c(c)).astype(np.float32), "shading": shading,
        "normal": normal, "face_mask": face,
        # Whole-mesh depth (hair, hat and neck included) so target shadow maps can be ray-marched from it.
        "depth": np.where(hit, gb.depth, 0.0).astype(np.float32),
    }


def render_records(k: int, light_indices: list[int], cfg: SynthConfig, split: str) -> Iterator[tuple[str, dict, dict]]:
    """Yield ``(record_id, arrays, meta)`` for subject ``k`` under each light in ``light_indices``."""
    subject = build_subject(k, cfg)
    group = sp.light_group(k, cfg.light_group_size)
    lights = [sample_light(light_rng(cfg.seed, group, j)) for j in light_indices]
    suns = [i for i, l in enumerate(lights) if l.has_sun]
    maps = cast_shadows(subject.scene, subject.gbuffer, np.array([lights[i].sun_dir for i in suns])) if suns else []
    cast_of = dict(zip(suns, maps))
    for i, (j, light) in enumerate(zip(light_indices, lights)):
        arrays = shade(subject, light, cast_of.get(i), cfg)
        meta = {"subject": sp.subject_name(k), "light_index": j, "light_group": group, "split": split,
                "source": "synthfaces", "c": float(arrays["shadow"][0]), **light.meta(), **subject.meta}
        yield sp.record_id(k, j), arrays, meta


# ------------------------------------------------------------------------------------------ data set
def _open_store(out_dir: str, cfg: SynthConfig, durable: bool) -> EncodingStore:
    dims = {"H": cfg.resolution, "W": cfg.resolution, "S": _shape_dim(), "D": IDENTITY_DIM}
    want = cfg.header_meta()
    if os.path.exists(os.path.join(out_dir, "store.json")):
        store = EncodingStore.open(out_dir, writable=True, durable=durable)
        have = store.store_meta
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        if diff:
            raise ConfigError(f"store {out_dir} was generated with a different configuration "
                             f"(key: (existing, requested)) {diff}; use a new out_dir to generate this one")
    return EncodingStore.create(out_dir, dims, ENCODINGS, want, durable=durable)


def _shape_dim() -> int:
    from difareli.synth.face_model import SHAPE_DIM

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
    shards may run concurrently into one ``out_dir``.
    """
    cfg = SynthConfig(subjects=subjects, lights=lights, resolution=resolution, seed=seed, **options)
    try:
        splits = sp.assign_splits(cfg.subjects, cfg.splits, cfg.light_group_size, cfg.seed)
    except ValueError as e:
        raise ConfigError(str(e)) from None
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
            with ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=ctx) as pool:
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
    sp.write_split_files(out_dir, splits, cfg.lights, cfg.light_group_size, cfg.seed)
    store.refresh()
    missing = [sp.record_id(k, j) for k in mine for j in range(cfg.lights)
               if not store.has(sp.record_id(k, j))]
    problems = [f"{rid}: missing" for rid in missing]
    return GenerateReport(written, skipped, seconds, problems)
