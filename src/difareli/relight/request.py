"""A relight request as a user states it, and its answer: the third layer of the relight spine, above the relighter.

:class:`Request` (:meth:`Request.from_config`: each value checked once, before any work) names the source, the
:class:`Target`, a :class:`Rotation` video, the compositing and how it is relit (:class:`Relighting`); :func:`respond`
answers it as an :class:`Answer` that a command only writes (a batch of photos: :mod:`difareli.relight.batch`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from difareli import errors
from difareli.data import encodings
from difareli.data.target_shadow import SHADOWED_C, SHADOWED_SHARE, photo_shadow, split_typical_c
from difareli.data.store import EncodingStore
from difareli.diffusion.spec import SamplerSpec
from difareli.lighting import presets, sh
from difareli.relight import photo
from difareli.relight.batch import check_photos, relight_photos
from difareli.relight.relighter import Relighter
from difareli.relight.relit import Relit
from difareli.relight.sources import Source
from difareli.relight.targets import TARGET_KEYS, TURNS, Targets, load_envmap, target_lights
from difareli.render import sun_fit
from difareli.render.sun_fit import TARGET_SUNS
from difareli.runtime.core import Runtime
from difareli.utils import viz


@dataclass(frozen=True)
class Target:
    """The target of a request: at most one of ``TARGET_KEYS``, checked as it is made (an environment map may take a
    ``yaw`` too; none: the source's own light), its shadow strength c' (None: the other record's, else for a photo
    under a new light ``target_shadow.photo_shadow``, else the source's own) and where its map is marched (``sun``)."""

    light: str | None = None
    record: str | None = None
    yaw: float | None = None
    roll: float | None = None
    pitch: float | None = None
    envmap: str | None = None
    direction: tuple[float, float, float] | None = None
    shadow: float | None = None
    sun: str = "shadows"

    def __post_init__(self) -> None:
        given = [k for k in TARGET_KEYS if getattr(self, k) is not None]
        if len(given) > 1 and set(given) != {"envmap", "yaw"}:
            raise errors.UserError(f"{' and '.join(f'target.{k}' for k in given)}: give exactly one target (an "
                                   "envmap may take target.yaw, its rotation)")

    @property
    def given(self) -> bool:
        return any(getattr(self, k) is not None for k in TARGET_KEYS)

    def turns_own(self) -> bool:
        """Whether this target is the source's own light turned (a yaw, roll or pitch of it)."""
        return self.envmap is None and any(getattr(self, k) is not None for k in TURNS)

    def for_source(self, relighter: Relighter, source: Source, other: Source | None = None
                   ) -> tuple[Targets, Any]:
        """This target for ``source`` (``other``: the target record, read as a source) and the key sun its
        map is marched toward: found by ``relighter.key_sun`` from the cast shadows of the image whose light it is
        (the other record's; the source's own, turned with a yaw, roll or pitch), None for ``sun=peak``, a light
        file, a named light, a direction or an environment map (the light's radiance peak)."""
        if (self.record is None) != (other is None):
            raise ValueError(f"target.record={self.record}: pass its source (relighter.source), and only then")
        o = {} if other is None else other.arrays
        finds = self.sun == "shadows" and (other is not None or self.turns_own())
        found = relighter.key_sun(source if other is None else other) if finds else None
        light = target_lights(source.arrays["light"], light=self.light, other_light=o.get("light"), yaw=self.yaw,
                              roll=self.roll, pitch=self.pitch, envmap=self.envmap, direction=self.direction,
                              normals=source.arrays.get("normal"))
        shadow = self.shadow if self.shadow is not None else (float(o["shadow"][0]) if "shadow" in o else None)
        if (shadow is None and self.given and other is None and getattr(source, "photo", None) is not None
                and "shadow" in source.arrays):
            shadow = photo_shadow(encodings.shadow_logit(source.arrays))[0]  # a photo's own c draws no shadow
        turn = next((TURNS[k](getattr(self, k)) for k in TURNS if getattr(self, k) is not None and self.turns_own()),
                    np.eye(3))  # the rotation applied to the source's light, and so to its key sun
        sun = None if found is None else turn @ found.direction
        return Targets.of([light], [shadow], "the target", suns=[sun]), found


def relight_targets(relighter: Relighter, source: Source, targets: Sequence[Target]) -> Relit:
    """``source`` relit under several targets of its own (none takes another record) in one decode batch: the
    app's target and its reconstruction, say."""
    made = [t.for_source(relighter, source)[0] for t in targets]
    suns = [s for m in made for s in (m.suns or (None,) * len(m))]
    return relighter.relight(source, Targets.of([m.lights[0] for m in made], [m.shadows[0] for m in made],
                                                source.what, suns=suns))


@dataclass(frozen=True)
class Rotation:
    """A 360-degree rotation video's target: the source's own light (or the environment map file ``envmap``'s)
    turned about ``axis`` in ``frames`` frames, with ``shadow`` (None: the policy of :func:`rotation_targets`,
    from ``split``), toward the key sun found from the source's cast shadows turned with it (``sun=shadows``) or
    each frame's radiance peak (``peak``); ``shadows`` and ``maps``: each frame's c' and target map given (an
    oracle's) instead; ``plausible``: each frame's light made plausible for the face (:func:`plausible`)."""

    axis: str = "yaw"
    frames: int = 60
    envmap: str | None = None
    shadow: float | None = None
    sun: str = "shadows"
    split: str = "train"
    shadows: tuple[float, ...] | None = None
    maps: np.ndarray | None = None
    plausible: bool = False

    def light(self) -> np.ndarray | None:
        """The environment map's SH light (checked), or None: the source's own light turns."""
        if self.envmap is None:
            return None
        return errors.check_light(sh.project_envmap(load_envmap(self.envmap)), f"the SH projection of {self.envmap}")

    def lights(self, source: Source) -> np.ndarray:
        """Each frame's light (N, 9, 3)."""
        light = self.light()
        return sh.rotate(source.arrays["light"] if light is None else light, sh.rotation_frames(self.axis,
                                                                                                  self.frames)[1])

    def for_source(self, relighter: Relighter, source: Source, store: EncodingStore | None = None
                   ) -> tuple[Targets, dict[str, str | None]]:
        """The frames' targets for ``source``, and notes saying where their shadow strength came from
        (``shadow``) and where their maps are marched (``maps``: None where none is marched)."""
        light = self.light()
        marched = self.maps is None and "shadow_map" in relighter.model_inputs
        found = relighter.key_sun(source) if self.sun == "shadows" and light is None and marched else None
        targets, why = rotation_targets(source.arrays, self.axis, self.frames, store=store, given=self.shadow,
                                        sun=None if found is None else found.direction, light=light,
                                        shadows=self.shadows, maps=self.maps, split=self.split)
        targets = plausible(targets, source, "the rotation's lights") if self.plausible else targets
        return targets, {"shadow": why, "maps": _map_note(found) if marched else None}


def _map_note(found: sun_fit.SunFit | None) -> str:
    """Where a target map is marched: toward the key sun ``found`` (its note), else the radiance peak."""
    return sun_fit.PEAK_NOTE if found is None else found.note


def plausible(targets: Targets, source: Source, what: str = "the target lights") -> Targets:
    """``targets`` with each light made plausible for ``source``'s face (``lighting.presets.plausible``: never
    negative on it, its energy kept): for a caller's own turned lights (the demo's), where a light negative on most
    of a face would decode to noise."""
    like, normals = source.arrays["light"], source.arrays.get("normal")
    return Targets.of([presets.plausible(light, like, normals) for light in targets.lights], targets.shadows, what,
                      maps=targets.maps, suns=targets.suns)


def rotation_targets(source: Mapping[str, np.ndarray], axis: str, frames: int, *, store=None,
                     given: float | None = None, sun: np.ndarray | None = None, light: np.ndarray | None = None,
                     shadows=None, maps=None, split: str = "train") -> tuple[Targets, str]:
    """The targets of a 360-degree rotation video about ``axis`` of a source's own light (or of ``light``, e.g. an
    environment map's), and a sentence saying where their shadow strength c' came from: ``shadows``, one per frame
    (an oracle's); ``given``; else, for a store record, :func:`video_shadow` (the input's own c when shadowed, else
    ``split``'s typical shadowed c); else the input's own c (a photo). ``sun``: the source light's key sun
    (``render.sun_fit.key_sun``), turned with the light, toward which each frame's map is marched (None: each
    frame's radiance peak); ``maps``: each frame's target map given (an oracle's) instead of marched."""
    _, rots = sh.rotation_frames(axis, frames)
    if shadows is not None:
        cs, why = list(shadows), "target c' per frame = the ground truth's exact c (oracle_shadow=true)"
    else:
        own = encodings.shadow_logit(source)
        if store is not None and own is not None:
            c, why = video_shadow(store, own, given, split)
        elif given is not None:
            c, why = given, f"target c' = {given} (given)"
        else:  # a photo: no store to take a typical c from
            c, why = photo_shadow(own)
        cs = [c] * len(rots)
    lights = sh.rotate(source["light"] if light is None else light, rots)
    suns = None if sun is None else list(rots @ np.asarray(sun, np.float64))
    return Targets.of(lights, cs, f"rotation about {axis}", maps=maps, suns=suns), why


def video_shadow(store, record_c: float | None, given: float | None, split: str = "train") -> tuple[float, str]:
    """The shadow strength c' for every frame of a video and a sentence saying where it came from: ``given``;
    else the input's own c when it is shadowed; else the median shadowed c of ``split`` (the training split)."""
    if given is not None:
        return float(given), f"target c' = {float(given):.3f} (given: target.shadow)"
    if record_c is not None and record_c >= SHADOWED_C:  # a visible cast shadow
        return record_c, f"target c' = {record_c:.3f} (the input's own c: it has a cast shadow)"
    c = split_typical_c(store, split)
    own = "no 'shadow' encoding" if record_c is None else f"c = {record_c:.2f}"
    if c is None:
        raise errors.UserError(f"the input has no cast shadow ({own}) and the {split} split of {store.root} has no "
                               "shadowed record to take a typical c from; give target.shadow=<logit c'>")
    return c, (f"target c' = {c:.3f} (the input has no cast shadow, {own}: median c of the {split} split's "
               f"shadowed records, share >= {SHADOWED_SHARE})")


def rotation_video(relighter: Relighter, source: Source, rotation: Rotation, store: EncodingStore | None = None,
                   tell: Callable[[str], None] = lambda line: None) -> tuple[Relit, dict[str, str | None]]:
    """The one rotation-video path: ``source`` relit under every frame of ``rotation`` (each line told as it
    arises), with :meth:`Rotation.for_source`'s notes; the frames are written by
    :func:`difareli.utils.viz.write_rotation`."""
    targets, notes = rotation.for_source(relighter, source, store)
    tell(f"video shadow strength: {notes['shadow']}")
    if notes["maps"] is not None:
        tell(f"video shadow maps: {notes['maps']}, turned with the light")
    quarter = len(targets) // 4
    tell(f"video: frame 0 light {photo.describe_light(targets.lights[0])}"
         + (f"; frame {quarter}: {photo.describe_light(targets.lights[quarter])}" if quarter else ""))
    video = relighter.relight(source, targets)
    n, seconds = len(video), sum(video.seconds.values())
    tell(f"{n} frames in {seconds:.1f} s ({seconds / n:.2f} s/frame, {relighter.describe()})")
    return video, notes


@dataclass(frozen=True)
class Relighting:
    """How a request is relit: the relighter's arguments, typed (``sampler`` None: the model's default); the door
    through which the relight and video commands and the app get their relighter."""

    checkpoint: Any = None
    sampler: SamplerSpec | None = None
    runtime: Runtime = field(default_factory=Runtime)
    mean_matching: bool = True
    batch_size: int = 16
    progress: bool = False

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "Relighting":
        """A command config's ``checkpoint`` (read by :meth:`make_relighter`, the first work), ``sampler``, ``runtime``,
        ``mean_matching``, ``batch_size`` and ``progress``, each checked."""
        return cls(cfg["checkpoint"], None if cfg["sampler"] is None else SamplerSpec.from_config(cfg["sampler"]),
                   Runtime.from_config(cfg["runtime"]), errors.check_bool(cfg["mean_matching"], "mean_matching"),
                   errors.check_int(cfg["batch_size"], "batch_size", 1), errors.check_bool(cfg["progress"], "progress"))

    def make_relighter(self, cache_size: int | None = None) -> Relighter:
        """The relighter (``cache_size``: its caches bounded to the last sources, for a long-lived caller)."""
        return Relighter(self.checkpoint, self.sampler, runtime=self.runtime, mean_matching=self.mean_matching,
                         batch_size=self.batch_size, progress=self.progress, cache_size=cache_size)


@dataclass(frozen=True)
class Request:
    """One relight request (module doc): ``store`` (open and checked: :func:`check_store`) and ``record``, or
    ``image``, is the source; ``video_*`` a 360-degree rotation of its light; ``composite`` puts a photo's relights
    back; ``how`` builds its relighter (:class:`Relighting`)."""

    store: EncodingStore | None = None
    record: str | None = None
    image: str | None = None
    photos: tuple[Path, ...] | None = None  # a batch of photos under one target (relight.batch), else None
    out_dir: str | None = None  # where the answer is written (a batch's as it goes: a rerun resumes)
    face: Any = "largest"
    photo_size: int | None = None
    strict: bool = False
    target: Target = Target()
    video_axis: str | None = None
    video_frames: int = 60
    video_fps: int = 20
    video_format: str = "gif"
    composite: Mapping[str, Any] = field(default_factory=lambda: {"mode": "ratio", "feather": 0.03, "parts": None})
    how: Relighting = Relighting()

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "Request":
        """The request of a relight command's config, each value checked once, before any work: the source
        (:func:`check_store`, :func:`check_photos`), the target (:func:`check_target`) or a video, how it is relit
        (:meth:`Relighting.from_config`) and where the answer goes."""
        t, c, v, image = cfg["target"], cfg["composite"], cfg["video"], cfg["image"]
        if (image is None) == (cfg["store"] is None):
            raise errors.UserError("give the source as either store=<encodings store> (and record=) or "
                                   f"image=<photo>; got store={cfg['store']} image={image}")
        if t["record"] is not None and cfg["store"] is None:
            raise errors.UserError(f"target.record={t['record']} names a store record: give store= too")
        versions = None if cfg.get("versions") is None else dict(cfg["versions"])
        store = None if cfg["store"] is None else check_store(cfg["store"], versions, record=cfg["record"],
                                                              target_record=t["record"])
        target = check_target(t)
        if not target.given and v["axis"] is None:
            raise errors.UserError("nothing to do: give a target (target.light|record|yaw|roll|pitch|envmap) or "
                                   "video.axis=yaw|roll")
        photos = None if image is None else check_photos(image, cfg["face"], v["axis"], t["record"], c,
                                                         cfg["out_dir"])
        fmt = viz.video_format(v["format"], "video.format")
        how = Relighting.from_config(cfg)
        errors.check_out_dir(cfg["out_dir"])
        return cls(store=store, record=cfg["record"], image=image, photos=photos,
                   out_dir=str(cfg["out_dir"]), face=cfg["face"], photo_size=cfg["photo_size"],
                   video_frames=errors.check_int(v["frames"], "video.frames", 1, maximum=MAX_FRAMES),
                   video_fps=errors.check_int(v["fps"], "video.fps", 1), video_format=fmt, video_axis=v["axis"],
                   strict=errors.check_bool(cfg["strict"], "strict"), target=target,
                   composite={"mode": c["mode"], "feather": float(c["feather"]),
                              "parts": list(c["parts"]) if c["parts"] else None}, how=how)


#: The longest rotation video a command makes (60 s at 60 fps): anything longer is a typo, and would fill the disk.
MAX_FRAMES = 3600


def check_target(t: Mapping[str, Any]) -> Target:
    """A config's ``target`` block as a :class:`Target`, each value checked: a named light or an existing file for
    ``light`` and ``envmap``, its sun, its numbers, and one way to give the light (:class:`Target`)."""
    for key, names, kind in (("light", presets.NAMES, "9x3 SH light"), ("envmap", presets.ENVMAPS, "HDR map")):
        value = t.get(key)
        if value is None or (isinstance(value, str) and value in names):
            continue
        if "/" in str(value) or Path(str(value)).suffix:  # a path: said as a missing file
            errors.check_file(value, f"target.{key}")
        elif not Path(str(value)).is_file():
            raise errors.UserFileNotFoundError(f"target.{key}={value}: no such named light or file; give one of "
                                               f"{', '.join(names)}, or a {kind} file")
    errors.check_choice(t["sun"], "target.sun", TARGET_SUNS)
    for key in (*TURNS, "shadow"):
        errors.check_number(t.get(key), f"target.{key}")
    return Target(**{k: t.get(k) for k in (*TARGET_KEYS[:-1], "shadow", "sun")})


def check_store(root: str, versions: Mapping[str, Any] | None, **records: str | None) -> EncodingStore:
    """A source store that opens (its header, the derived ``versions`` asked for) and holds the ``records`` named
    (``record``, ``target_record``: None for none; the key is said as the config spells it); returned, open."""
    store = EncodingStore.open(root).use_versions(versions)
    for key, rid in records.items():
        if rid is not None and str(rid) not in store:  # an id that could not name a record is in no store
            some = ", ".join(store.ids()[:3])
            raise errors.UserError(f"{key.replace('_', '.')}={rid}: no such record in the store {root} ({len(store)} "
                                   f"records{', e.g. ' + some if some else ''}); give one of its record ids")
    return store


@dataclass
class Answer:
    """What a request comes back as: the source read, the target's relight (``relit``, with the ground truth
    ``truth`` where the target record is the same subject, and ``whole`` the relit photo), the video's relit
    frames (``video``, ``whole_video`` for a photo), a batch's counts (``counts``: done, skipped, resumed; its
    files are already written) and lines worth telling the user (``lines``; a source's warnings start with
    ``warning:``)."""

    source: Source | None = None
    relit: Relit | None = None
    truth: np.ndarray | None = None
    whole: np.ndarray | None = None
    video: Relit | None = None
    whole_video: np.ndarray | None = None
    counts: dict[str, int] | None = None
    lines: list[str] = field(default_factory=list)
    say: Callable[[str], None] | None = None  # told each line as it arises (a long relight shows its notes first)

    def tell(self, line: str) -> None:
        self.lines.append(line)
        if self.say is not None:
            self.say(line)


def respond(relighter: Relighter, request: Request, say: Callable[[str], None] | None = None) -> Answer:
    """``request`` answered by ``relighter`` (module doc): the source read and checked once, its target relit
    (its map toward the key sun found from the cast shadows of the image whose light it is, turned with a yaw,
    roll or pitch), the video's frames relit, a photo's relights composited back; a batch of photos:
    :func:`answer_photos`."""
    if request.photos is not None:
        return Answer(counts=answer_photos(relighter, request), say=say)
    store = request.store  # opened once, by Request.from_config's check
    source = (relighter.photo_source(request.image, size=request.photo_size, strict=request.strict)
              if request.image is not None else relighter.source(store, request.record))
    out = Answer(source, say=say)
    for line in source.notes:
        out.tell(line)
    t, c = request.target, request.composite
    if t.given:
        other = None if t.record is None else relighter.source(store, t.record)  # read once: light, c', image
        targets, found = t.for_source(relighter, source, other)
        out.relit = relighter.relight(source, targets)
        out.tell(f"target light 0: {photo.describe_light(targets.lights[0])}")
        if "shadow_map" in relighter.model_inputs:
            out.tell(f"target 0 shadow map: {_map_note(found)}")
        out.tell(f"relit {source.what} ({out.relit.describe_seconds()}; {relighter.describe()})")
        if other is not None and store.meta(t.record).get("subject") == store.meta(source.key[1]).get("subject"):
            out.truth = np.asarray(other.arrays["image"])
        if source.photo is not None:  # the whole photo back
            out.whole = out.relit.composite(c["mode"], c["feather"], c["parts"])[0]
            out.tell(f"composited into the {out.whole.shape[1]}x{out.whole.shape[0]} photo in "
                     f"{out.relit.seconds['composite']:.2f} s ({c['mode']})")
    if request.video_axis is not None:
        # A photo's own light turned behind the head is negative on most of its face (a dark mask, issue 61): its
        # frames are made plausible as its named lights are; a store record's turn stays exact (its ground truth).
        rotation = Rotation(request.video_axis, request.video_frames, shadow=t.shadow, sun=t.sun,
                            plausible=source.photo is not None)
        out.video = rotation_video(relighter, source, rotation, store, out.tell)[0]
        if source.photo is not None:  # every frame back into the whole photo
            out.whole_video = out.video.composite(c["mode"], c["feather"], c["parts"])
    return out


def answer_photos(relighter: Relighter, request: Request) -> dict[str, int]:
    """A batch request (``request.photos``) under its one target, written into ``request.out_dir`` as it goes
    (:func:`difareli.relight.batch.relight_photos`); counts {done, skipped, resumed}."""
    settings = {"photo_size": request.photo_size, "face": str(request.face), "strict": request.strict,
                "composite": dict(request.composite),
                **{f"target.{k}": v for k, v in dataclasses.asdict(request.target).items()}}
    return relight_photos(list(request.photos), request.out_dir, progress=relighter.progress, settings=settings,
                          relighter=relighter, target=lambda s: request.target.for_source(relighter, s)[0],
                          size=request.photo_size, face=request.face, composite=request.composite,
                          strict=request.strict)
