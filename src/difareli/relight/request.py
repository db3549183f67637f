"""A relight request as a user states it, and the relighter's answer to it.

:class:`Request` says where the source is (a store record, or a photo preprocessed in memory), the target (one of a
light file, another record's light, the source's own light turned by a yaw or a roll, an environment map; its
shadow strength and where its shadow map is marched), a rotation video of the source's light, how a photo's
relights go back into it, and where and how the answer is written (the output folder, the video's frame rate and
format), and how it is relit (the checkpoint, the sampler by its spec, the runtime: what
a :class:`~difareli.relight.relighter.Relighter` is built with). :meth:`Request.from_config` takes it from a
command's config (``conf/relight.yaml``) and checks it, each value once, before any work. :func:`answer` (the
relighter's door :meth:`~difareli.relight.relighter.Relighter.answer`) reads the source once, builds the targets,
relights, composites, and returns an :class:`Answer` that a command only writes out; a batch of photos is answered
photo by photo into the request's ``out_dir`` (:mod:`difareli.relight.batch`), its answer the counts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from difareli import errors
from difareli.diffusion.spec import SamplerSpec
from difareli.lighting import sh
from difareli.relight import photo
from difareli.relight.batch import photo_paths, relight_photos
from difareli.relight.composite import MODES, part_mask
from difareli.relight.targets import Targets, rotation_targets, target_lights
from difareli.render import sun_fit
from difareli.render.sun_fit import TARGET_SUNS
from difareli.runtime.core import Runtime
from difareli.utils import viz
from difareli.data.store import EncodingStore

#: The keys that give a target; exactly one of them (or a video alone).
TARGET_KEYS = ("light", "record", "yaw", "roll", "envmap")


@dataclass(frozen=True)
class Target:
    """The target of a request: exactly one of ``TARGET_KEYS`` (none: only a video), its shadow strength c'
    (None: the other record's, else the source's own) and where its map is marched (``sun_fit.TARGET_SUNS``)."""

    light: str | None = None
    record: str | None = None
    yaw: float | None = None
    roll: float | None = None
    envmap: str | None = None
    shadow: float | None = None
    sun: str = "shadows"

    @property
    def given(self) -> bool:
        return any(getattr(self, k) is not None for k in TARGET_KEYS)

    def record_source(self, relighter, store):
        """The target record read once, as the relighter reads a source (its light, shadow strength, image and
        what its key sun's fit reads); None for a target without a record."""
        return None if self.record is None else relighter.source(store, self.record)

    def for_source(self, relighter, source, other=None) -> tuple[Targets, Any]:
        """This target for ``source`` (a :class:`~difareli.relight.relighter.Source`; ``other``: the target
        record's, :meth:`record_source`) and the key sun its map is marched toward: found by
        ``relighter.key_sun`` from the cast shadows of the image whose light it is (the other record's; the
        source's own, turned with a yaw or a roll), None for ``sun=peak``, a light file or an environment map
        (the light's radiance peak)."""
        if (self.record is None) != (other is None):
            raise ValueError(f"target.record={self.record}: pass its source (Target.record_source), and only then")
        o = {} if other is None else other.arrays
        finds = self.sun == "shadows" and (other is not None or self.yaw is not None or self.roll is not None)
        found = relighter.key_sun(source if other is None else other) if finds else None
        light = target_lights(source.arrays["light"], light=self.light, other_light=o.get("light"),
                              yaw=self.yaw, roll=self.roll, envmap=self.envmap)
        shadow = self.shadow if self.shadow is not None else (float(o["shadow"][0]) if "shadow" in o else None)
        sun = None if found is None else self.turn() @ found.direction
        return Targets.of([light], [shadow], "the target", suns=[sun]), found

    def turn(self) -> np.ndarray:
        """The rotation this target applies to the source's light (and so to its key sun); identity otherwise."""
        if self.yaw is not None:
            return sh.rotation_yaw(self.yaw)
        return sh.rotation_roll(self.roll) if self.roll is not None else np.eye(3)


@dataclass(frozen=True)
class Request:
    """One relight request (module doc). ``store``/``record`` or ``image`` is the source; ``video_axis`` adds a
    360-degree rotation of its light; ``composite`` (mode, feather, parts) puts a photo's relights back; ``out_dir``
    gets the answer (a batch's as it goes), its video at ``video_fps`` as ``video_format`` (``mp4`` or ``gif``).
    ``checkpoint`` (a path or a shipped name), ``sampler`` (None: the model's default), ``runtime``,
    ``mean_matching``, ``batch_size`` and ``progress`` say how it is relit (the relighter's arguments)."""

    store: str | None = None
    record: str | None = None
    versions: Mapping[str, Any] | None = None
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
    checkpoint: Any = None
    sampler: SamplerSpec | None = None
    runtime: Runtime = field(default_factory=Runtime)
    mean_matching: bool = True
    batch_size: int = 16
    progress: bool = False

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "Request":
        """The request of a relight command's config, checked before any work, each value once: one source (a
        folder or glob of photos, or ``face=all|<index>``: a batch under one target light), a store that opens and
        holds the records named, a target or a video, a target record only with a store, the photos' compositing,
        the target's sun, numbers and files, the video's frame count; how it is relit (the sampler whole by its
        spec, the runtime, the batch size); where the answer goes (the output folder, the video's frame rate and
        format). The checkpoint is read by the relighter, the first work."""
        t, c, v, image = cfg["target"], cfg["composite"], cfg["video"], cfg["image"]
        if (image is None) == (cfg["store"] is None):
            raise errors.UserError("give the source as either store=<encodings store> (and record=) or "
                                   f"image=<photo>; got store={cfg['store']} image={image}")
        if t["record"] is not None and cfg["store"] is None:
            raise errors.UserError(f"target.record={t['record']} names a store record: give store= too")
        if all(t[k] is None for k in TARGET_KEYS) and v["axis"] is None:
            raise errors.UserError("nothing to do: give a target (target.light|record|yaw|roll|envmap) or "
                                   "video.axis=yaw|roll")
        versions = cfg.get("versions")
        versions = None if versions is None else dict(versions)
        if cfg["store"] is not None:
            check_store(cfg["store"], versions, record=cfg["record"], target_record=t["record"])
        photos = None
        if image is not None:
            photos = photo_paths(image)  # a folder or a glob; None for one photo
            if photos is None and str(cfg["face"]).lower() != "largest":
                photos = [Path(str(image))]  # several faces of one photo
            if photos is not None and (v["axis"] is not None or t["record"] is not None):
                raise errors.UserError(f"image={image} face={cfg['face']}: a folder or several faces take a target "
                                       "light (target.light|yaw|roll|envmap), not video.axis or target.record")
            check_composite(c)
        sampler = None if cfg["sampler"] is None else SamplerSpec.from_config(cfg["sampler"])
        runtime = Runtime.from_config(cfg["runtime"])
        fmt = viz.video_format(v["format"], "video.format")
        errors.check_int(cfg["batch_size"], "batch_size", 1)
        errors.check_out_dir(cfg["out_dir"])
        errors.check_choice(t["sun"], "target.sun", TARGET_SUNS)
        errors.check_int(v["frames"], "video.frames", 1, maximum=MAX_FRAMES)
        errors.check_int(v["fps"], "video.fps", 1)
        for key in ("yaw", "roll", "shadow"):
            errors.check_number(t[key], f"target.{key}")
        for key in ("light", "envmap"):
            if t[key] is not None:
                errors.check_file(t[key], f"target.{key}")
        return cls(store=cfg["store"], record=cfg["record"], versions=versions,
                   image=image, photos=None if photos is None else tuple(photos), out_dir=str(cfg["out_dir"]),
                   face=cfg["face"], photo_size=cfg["photo_size"], strict=bool(cfg["strict"]),
                   target=Target(**{k: t[k] for k in (*TARGET_KEYS, "shadow", "sun")}),
                   video_axis=v["axis"], video_frames=int(v["frames"]), video_fps=int(v["fps"]), video_format=fmt,
                   composite={"mode": c["mode"], "feather": float(c["feather"]),
                              "parts": list(c["parts"]) if c["parts"] else None},
                   checkpoint=cfg["checkpoint"], sampler=sampler, runtime=runtime,
                   mean_matching=bool(cfg["mean_matching"]), batch_size=int(cfg["batch_size"]),
                   progress=bool(cfg["progress"]))


#: The longest rotation video a command makes (60 s at 60 fps): anything longer is a typo, and would fill the disk.
MAX_FRAMES = 3600


def check_store(root: str, versions: Mapping[str, Any] | None, **records: str | None):
    """A source store that opens (its header, the derived ``versions`` asked for) and holds the ``records`` named
    (``record``, ``target_record``: None for none; the key is said as the config spells it); returned, open."""
    store = EncodingStore.open(root).use_versions(versions)
    for key, rid in records.items():
        if rid is not None and not store.has(str(rid)):
            some = ", ".join(store.ids()[:3])
            raise errors.UserError(f"{key.replace('_', '.')}={rid}: no such record in the store {root} ({len(store)} "
                                   f"records{', e.g. ' + some if some else ''}); give one of its record ids")
    return store


def check_composite(c: Mapping[str, Any]) -> None:
    """A photo's compositing settings: a known mode, known parts, a feather >= 0."""
    errors.check_choice(c["mode"], "composite.mode", MODES)
    try:
        part_mask(np.zeros((1, 1), np.uint8), list(c["parts"] or []))
    except ValueError as e:
        raise errors.UserError(f"composite.parts: {e}") from None
    if errors.check_number(c["feather"], "composite.feather", allow_none=False) < 0:
        raise errors.UserError(f"composite.feather={c['feather']}: must be >= 0 (a fraction of the crop size)")


@dataclass
class Answer:
    """What a request comes back as: the source read, the target's relight (``relit``, with the ground truth
    ``truth`` where the target record is the same subject, and ``whole`` the relit photo), the video's relit
    frames (``video``, ``whole_video`` for a photo), a batch's counts (``counts``: done, skipped, resumed; its
    files are already written) and lines worth telling the user (``lines``; a source's warnings start with
    ``warning:``)."""

    source: Any = None
    relit: Any = None
    truth: np.ndarray | None = None
    whole: np.ndarray | None = None
    video: Any = None
    whole_video: np.ndarray | None = None
    counts: dict[str, int] | None = None
    lines: list[str] = field(default_factory=list)
    say: Callable[[str], None] | None = None  # told each line as it arises (a long relight shows its notes first)

    def tell(self, line: str) -> None:
        self.lines.append(line)
        if self.say is not None:
            self.say(line)


def answer(relighter, request: Request, say: Callable[[str], None] | None = None) -> Answer:
    """``request`` answered by ``relighter`` (module doc): the source read and checked once, its target relit
    (its map toward the key sun found from the cast shadows of the image whose light it is, turned with a yaw or
    a roll), the video's frames relit, a photo's relights composited back; a batch of photos: :func:`answer_photos`."""
    if request.photos is not None:
        return Answer(counts=answer_photos(relighter, request), say=say)
    store = None if request.store is None else EncodingStore.open(request.store).use_versions(request.versions)
    source = (relighter.photo_source(request.image, size=request.photo_size, strict=request.strict)
              if request.image is not None else relighter.source(store, request.record))
    out = Answer(source, say=say)
    for line in source.notes:
        out.tell(line)
    t, maps, c = request.target, "shadow_map" in relighter.model_inputs, request.composite
    if t.given:
        other = t.record_source(relighter, store)
        targets, found = t.for_source(relighter, source, other)
        out.relit = relighter.relight(source, targets)
        out.tell(f"target light 0: {photo.describe_light(targets.lights[0])}")
        if maps:
            out.tell(f"target 0 shadow map: {sun_fit.describe(found)}")
        out.tell(f"relit {source.what} ({out.relit.describe_seconds()}; {relighter.describe()})")
        if other is not None and store.meta(t.record).get("subject") == store.meta(source.key[1]).get("subject"):
            out.truth = np.asarray(other.arrays["image"])
        if source.photo is not None:  # the whole photo back
            out.whole = out.relit.composite(c["mode"], c["feather"], c["parts"])[0]
            out.tell(f"composited into the {out.whole.shape[1]}x{out.whole.shape[0]} photo in "
                 f"{out.relit.seconds['composite']:.2f} s ({c['mode']})")
    if request.video_axis is not None:
        found = relighter.key_sun(source) if t.sun == "shadows" else None
        targets, why = rotation_targets(source.arrays, request.video_axis, request.video_frames, store=store,
                                        given=t.shadow, sun=None if found is None else found.direction)
        out.tell(f"video shadow strength: {why}")
        if maps:
            out.tell(f"video shadow maps: {sun_fit.describe(found)}, turned with the light")
        quarter = len(targets) // 4
        out.tell(f"video: frame 0 light {photo.describe_light(targets.lights[0])}"
                 + (f"; frame {quarter}: {photo.describe_light(targets.lights[quarter])}" if quarter else ""))
        out.video = relighter.relight(source, targets)
        n, seconds = len(out.video), sum(out.video.seconds.values())
        out.tell(f"{n} frames in {seconds:.1f} s ({seconds / n:.2f} s/frame, {relighter.describe()})")
        if source.photo is not None:  # every frame back into the whole photo
            out.whole_video = out.video.composite(c["mode"], c["feather"], c["parts"])
    return out


def answer_photos(relighter, request: Request) -> dict[str, int]:
    """A batch request (``request.photos``: a folder, a glob, or several faces of one photo) answered by
    ``relighter`` under the request's one target: :func:`difareli.relight.batch.relight_photos` writes each photo's
    composite, relit crops and CSV row into ``request.out_dir`` as it goes (a rerun resumes; a progress bar where
    the relighter shows progress); counts {done, skipped, resumed}."""
    if request.photos is None or request.out_dir is None:
        raise ValueError("answer_photos takes a request with photos (image=<folder or glob>, or face=all|<index>) "
                         "and an out_dir")
    return relight_photos(list(request.photos), request.out_dir, progress=relighter.progress, relighter=relighter,
                          target=lambda s: request.target.for_source(relighter, s)[0], size=request.photo_size,
                          face=request.face, composite=request.composite, strict=request.strict)
