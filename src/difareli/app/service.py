"""What the app's page asks for, without HTTP: it parses requests (a source: an upload, a store record, an
example; a relight under a direction or a turned HDR map) and formats answers (images, seconds, the reconstruction
error); the relighting is the relight spine's (its sources, relighter and :class:`~difareli.relight.request.Target`).

Relighters, sources and inversions are kept in bounded LRU caches (``cache`` in ``conf/app.yaml``). A request is
checked whole before a relighter is built; checkpoints come only from the zoo and the start-up files / folders
(:meth:`Service.allowed_checkpoint`). One lock runs one relight at a time (the CPU is the limit, and the estimators
are not thread-safe); a client that leaves gives it back (:mod:`difareli.app.cache`).
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import os
import tempfile
import threading
import time
import warnings
from contextlib import contextmanager
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from difareli.checkpoints import zoo
from difareli.checkpoints.format import is_folder
from difareli.data import encodings
from difareli.data.store import EncodingStore
from difareli.data.target_shadow import photo_shadow
from difareli.diffusion.samplers import SAMPLERS
from difareli.diffusion.spec import DEFAULT_SAMPLER, PRESETS, SamplerSpec
from difareli.lighting import sh
from difareli.lighting.presets import ENVMAPS
from difareli.runtime.core import Runtime
from difareli.relight.photo import read_photo
from difareli.relight.sources import Source
from difareli.relight.request import Relighting, Target, relight_targets
from difareli.utils.lru import LRU
from difareli.utils.viz import png_data_url

from . import checks
from .cache import CancelScope, attach
from .checks import RequestError
from .examples import EXAMPLES, example_png

#: What the page starts with and a request without sampler / steps gets: the default preset, the cards' sampler.
DEFAULT = PRESETS[DEFAULT_SAMPLER]
MAX_UPLOAD_BYTES = 32 * 2 ** 20
MAX_ROTATION = 360.0
RELIGHT_FIELDS = ("id", "checkpoint", "sampler", "steps", "light", "shadow")


@dataclass
class AppSource:
    """A face the page relights: the relight spine's Source (a photo's ``source.photo``: its prepared photo)."""

    id: str
    source: Source
    preprocess_s: float
    checkpoint: str
    notes: tuple[str, ...] = ()  # what reading the photo changed (an alpha channel composited, ...)


@dataclass
class Service:
    """The app's state: configuration, bounded caches, the allowed checkpoints and the lock (module doc)."""

    checkpoint: str = zoo.RECOMMENDED
    store: str | None = None
    runtime: Mapping[str, Any] | None = None
    composite: Mapping[str, Any] = field(default_factory=lambda: {"mode": "ratio", "feather": 0.03})
    checkpoints: Sequence[str] = ()  # further checkpoint files / folders a request may name (given at start-up)
    max_relighters: int = 3  # each holds a model: (checkpoint, sampler, steps) beyond this evicts the oldest
    max_sources: int = 8  # an upload holds its full-size photo
    max_inversions: int = 8  # per relighter
    lock: threading.Lock = field(default_factory=threading.Lock)
    cancel: CancelScope = field(default_factory=CancelScope)
    built: int = 0  # relighters built so far (a cache that works keeps this small)

    def __post_init__(self) -> None:
        self._relighters, self._sources = LRU(self.max_relighters), LRU(self.max_sources)
        self._errors = LRU(4 * self.max_sources)
        self._store: Any = None
        self._roots = [os.path.realpath(os.path.expanduser(str(c))) for c in (self.checkpoint, *self.checkpoints)
                       if not _zoo_name(str(c))]

    # ------------------------------------------------------------------ models and stores
    def allowed_checkpoint(self, value: str | None) -> str:
        """``value`` if a request may use it (a shipped name, a start-up file or a file under a start-up folder),
        else a RequestError whose words depend on the string alone, never on whether such a file exists."""
        if value is None or value == "" or value == self.checkpoint:
            return self.checkpoint
        if _zoo_name(value):
            return value
        try:
            real = os.path.realpath(os.path.expanduser(value))
        except (ValueError, OSError):  # an embedded NUL byte, a name too long
            real = None
        if real is not None and any(real == r or real.startswith(r.rstrip(os.sep) + os.sep) for r in self._roots):
            return value
        served = ", ".join(self.served_checkpoints()[:6])
        raise RequestError(f"checkpoint={value[:200]!r} is not one this app serves; pick a listed one ({served}) or "
                           "restart the app with checkpoints=[<file or folder>]")

    def served_checkpoints(self, limit: int = 200) -> list[str]:
        """The checkpoints the page may offer: shipped names, start-up files and weights folders, and the ``*.ckpt``
        files and weights folders under a start-up folder."""
        out = [self.checkpoint, *zoo.available()]
        for c in self.checkpoints:
            p = Path(str(c)).expanduser()
            if is_folder(p) or not p.is_dir():
                out.append(str(c))
            else:
                out += sorted(str(f) for f in p.rglob("*.ckpt"))[:limit]
                out += sorted(str(f.parent) for f in p.rglob("config.json") if is_folder(f.parent))[:limit]
        return list(dict.fromkeys(out))[:limit]

    def relighter(self, checkpoint: str | None = None, sampler: str = DEFAULT.name, steps: int = DEFAULT.steps):
        """A cached relighter (``Relighting.make_relighter``) of an allowed checkpoint, with a sampler and steps
        :meth:`relight` checked (a one-pass student ignores them)."""
        ckpt = self.allowed_checkpoint(checkpoint)
        key = (ckpt, sampler, steps)
        if key not in self._relighters:
            how = Relighting(ckpt, SamplerSpec(sampler, steps), Runtime.from_config(self.runtime))
            rel = how.make_relighter(cache_size=self.max_inversions)
            attach(rel.model, self.cancel)
            self.built += 1
            self._relighters[key] = rel
        return self._relighters[key]

    def open_store(self):
        if self.store is None:
            raise RequestError("no store: start the app with store=<encodings store> to pick records")
        if self._store is None:
            self._store = EncodingStore.open(self.store)
        return self._store

    def records(self, limit: int = 200) -> list[str]:
        """Record ids to offer (the test split first), none without a store."""
        if self.store is None:
            return []
        st = self.open_store()
        test = st.ids(split="test")
        return (test + [r for r in st.ids() if r not in set(test)])[:limit]

    def info(self) -> dict:
        return {"checkpoint": self.checkpoint, "checkpoints": self.served_checkpoints(), "samplers": list(SAMPLERS),
                "default_sampler": {"name": DEFAULT.name, "steps": DEFAULT.steps}, "envmaps": list(ENVMAPS),
                "records": self.records(), "store": self.store,
                "cache": {"relighters": self.max_relighters, "sources": self.max_sources,
                          "inversions": self.max_inversions}}

    @contextmanager
    def session(self, gone: Callable[[], bool] | None = None):
        """Hold the one lock for a request; ``gone`` (has the client left?) cancels the wait and the relight."""
        self.cancel.acquire(self.lock, gone)
        self.cancel.check = gone
        try:
            yield self
        finally:
            self.cancel.check = None
            self.lock.release()

    # ------------------------------------------------------------------ sources
    def upload(self, name: str, data: bytes, checkpoint: str | None = None) -> AppSource:
        """An uploaded photo, decoded with the CLI's checks and preprocessed once for ``checkpoint``'s model;
        a bad upload raises the CLI's UserError (``image=<name>: ...``)."""
        name = Path(str(name or "upload")).name or "upload"
        if len(data) > MAX_UPLOAD_BYTES:
            raise RequestError(f"image={name}: {len(data) / 2 ** 20:.0f} MiB is over the {MAX_UPLOAD_BYTES >> 20} MiB "
                               "upload limit; give a smaller photo")
        ckpt = self.allowed_checkpoint(checkpoint)
        with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            # the CLI's reader checks a file: its suffix, its size, its frames; a name with no suffix (the API's
            # default "upload", IMG_0001) is read by its bytes (it was "not an image file (suffix 'none')")
            path = Path(tmp) / (f"{name}.png" if not Path(name).suffix else name)
            path.write_bytes(data)
            rgb = read_photo(path, "image", name=name)
        notes = tuple(str(w.message) for w in caught if issubclass(w.category, UserWarning))
        return self.photo(name, rgb, ckpt, notes)

    def photo(self, name: str, rgb: np.ndarray, checkpoint: str, notes: tuple[str, ...] = ()) -> AppSource:
        """A decoded photo prepared once for ``checkpoint``'s model (cached by its pixels and crop size)."""
        relighter = self.relighter(checkpoint)
        size = relighter.photo_size()
        sid = f"photo-{hashlib.sha1(np.ascontiguousarray(rgb).tobytes() + str(rgb.shape).encode()).hexdigest()[:16]}"
        sid = f"{sid}-{size}"
        cached = self._sources.get(sid)
        if cached is not None and cached.checkpoint == checkpoint:
            return AppSource(**{**cached.__dict__, "preprocess_s": 0.0})
        source = relighter.photo_source(rgb, size=size, what=f"image={name}", key=("app", sid), also=["face_mask"])
        self._sources[sid] = AppSource(sid, source, source.photo.seconds, checkpoint, notes)
        return self._sources[sid]

    def record(self, rid: str, checkpoint: str | None = None) -> AppSource:
        """A store record as a source (its face mask read too, for the reconstruction error)."""
        st = self.open_store()
        if not st.has(rid):
            raise RequestError(f"record={rid}: not in the store {st.root}; pick one of the listed records")
        ckpt = self.allowed_checkpoint(checkpoint)
        try:
            src = self.relighter(ckpt).source(st, rid, also=["face_mask"])
        except KeyError as e:  # the store lacks an encoding this model reads
            raise RequestError(f"checkpoint={ckpt}: {e}") from None
        out = AppSource(f"record-{rid}", src, 0.0, ckpt)
        self._sources[out.id] = out
        return out

    def describe(self, s: AppSource) -> dict:
        """What the page shows of a source: the aligned crop, its light's direction and shadow strength."""
        arrays, photo = s.source.arrays, s.source.photo
        c = encodings.shadow_logit(arrays)
        c = photo_shadow(c)[0] if c is not None and photo is not None else c  # the slider's start: a new light's
        out = {"id": s.id, "what": s.source.what, "crop": png_data_url(np.asarray(arrays["image"])),
               "preprocess_s": round(s.preprocess_s, 3), "direction": sh.dominant_direction(arrays["light"]).tolist(),
               "shadow": None if c is None else float(encodings.normalise_c(c)), "warnings": list(s.notes)}
        if photo is not None:
            out.update(width=int(photo.rgb.shape[1]), height=int(photo.rgb.shape[0]),
                       stages={k: round(v, 3) for k, v in photo.meta.get("seconds", {}).items()})
        return out

    # ------------------------------------------------------------------ relighting
    def target(self, light: Any) -> Target:
        """The target light a request describes: ``{"kind": "direction", "direction": [x, y, z]}`` or ``{"kind":
        "envmap", "name": ..., "rotation": degrees}``, every field checked (400 naming it)."""
        if not isinstance(light, Mapping):
            raise RequestError(f"light={type(light).__name__} is invalid: must be an object {{\"kind\": \"direction\", "
                               "\"direction\": [x, y, z]} or {\"kind\": \"envmap\", \"name\": ..., \"rotation\": deg}")
        kind = checks.choice(light, "kind", ("direction", "envmap"), default="direction", where="light.")
        if kind == "direction":
            checks.only(light, ("kind", "direction"), "light.")
            return Target(direction=checks.direction(light.get("direction", [0.0, 0.0, 1.0])))
        checks.only(light, ("kind", "name", "rotation"), "light.")
        name = checks.choice(light, "name", ENVMAPS, where="light.")
        rotation = checks.number(light, "rotation", -MAX_ROTATION, MAX_ROTATION, default=0.0, where="light.")
        return Target(envmap=name, yaw=float(rotation))

    def relight(self, request: Mapping[str, Any]) -> dict:
        """Relight a source (``request["id"]`` from :meth:`upload` / :meth:`record`) under the request's light and
        shadow strength with its checkpoint / sampler / steps; returns the images (data URLs), the seconds per
        stage and the reconstruction error (the source relit under its own light, against itself). The whole
        request is checked, and its source found, before any relighter is built."""
        t_all = time.perf_counter()
        checks.only(request, RELIGHT_FIELDS)
        sid = checks.text(request, "id", limit=256)
        ckpt = self.allowed_checkpoint(checks.text(request, "checkpoint", default=None))
        sampler = checks.choice(request, "sampler", SAMPLERS, default=DEFAULT.name)
        steps = checks.number(request, "steps", 1, checks.MAX_STEPS, default=DEFAULT.steps, integer=True)
        strength = checks.number(request, "shadow", 0.0, 1.0, default=None)
        s = self._sources.get(sid)
        if s is None:
            raise RequestError(f"source {sid[:80]!r} is unknown (the app restarted or forgot it: it keeps the last "
                               f"{self.max_sources}); upload the photo again")
        light = self.target(request.get("light") or {})
        relighter = self.relighter(ckpt, sampler, steps)
        if ckpt != s.checkpoint:  # another model may read more
            s = (self.photo(s.source.what.removeprefix("image="), s.source.photo.rgb, ckpt, s.notes)
                 if s.source.photo is not None else self.record(s.id.removeprefix("record-"), ckpt))
        # No strength: the relight spine's rule (Target.for_source: a photo's photo_shadow, a record's own c).
        target = light if strength is None else dataclasses.replace(light, shadow=encodings.denormalise_c(strength))
        own = Target()  # the source's own light and c
        # The reconstruction (the source relit under its own light) joins the first decode's batch, then is cached.
        key = (id(relighter), s.id)
        with warnings.catch_warnings(record=True) as caught:  # e.g. "unstable at this step count": show it
            warnings.simplefilter("always")
            relit = relight_targets(relighter, s.source, [target] if key in self._errors else [target, own])
        if key not in self._errors:
            from difareli.evaluation.metrics import image_errors  # torchmetrics: kept out of the app's start-up

            face = s.source.arrays.get("face_mask")
            self._errors[key] = {**image_errors(relit[1], s.source.arrays["image"], face),
                                 "region": "whole crop" if face is None else "face mask"}
        out = {"crop": png_data_url(relit[0]), "what": s.source.what, "how": relighter.describe(),
               "error": self._errors[key],
               "warnings": list(dict.fromkeys(str(w.message) for w in caught
                                              if issubclass(w.category, RuntimeWarning)))}
        out["image"] = out["crop"] if s.source.photo is None else png_data_url(relit.composite(  # the whole photo
            self.composite.get("mode", "ratio"), self.composite.get("feather", 0.03), images=relit[:1])[0])
        seconds = dict(relit.seconds)
        seconds["total"] = time.perf_counter() - t_all
        out["seconds"] = {k: round(v, 3) for k, v in seconds.items()}
        return out

    # ------------------------------------------------------------------ the page's examples and photo check
    def example(self, name: str, checkpoint: str | None = None) -> AppSource:
        """A shipped example photo (:mod:`difareli.app.examples`; ``name`` is checked against its fixed list, never
        read as a path), prepared like an upload of it."""
        name = checks.choice({"name": name}, "name", EXAMPLES)
        return self.upload(f"{name}.png", example_png(name), checkpoint)

    def source_answer(self, body: Mapping[str, Any]) -> dict:
        """``POST /api/source``: an upload (``name``, ``data``), a store record (``id``) or a shipped example
        (``name``), each with an optional ``checkpoint``, every field checked, then :meth:`describe` d; the answer
        also carries the whole input photo (``photo``: the before of the page's before/after) and, for a photo, the
        photo check's verdict (``check``) with the estimators' notes among the ``warnings``."""
        kind = checks.choice(body, "kind", ("upload", "record", "example"))
        checks.only(body, {"upload": ("kind", "name", "data", "checkpoint"), "record": ("kind", "id", "checkpoint"),
                           "example": ("kind", "name", "checkpoint")}[kind])
        ckpt = checks.text(body, "checkpoint", default=None)
        if kind == "record":
            s = self.record(checks.text(body, "id", limit=256), ckpt)
        elif kind == "example":
            s = self.example(checks.choice(body, "name", EXAMPLES), ckpt)
        else:
            data = decode_upload(checks.text(body, "data", limit=checks.MAX_BODY))
            s = self.upload(checks.text(body, "name", limit=255, default="upload"), data, ckpt)
        out = self.describe(s)
        if s.source.photo is None:  # a store record: its crop is the whole input
            out["photo"], out["check"] = out["crop"], None
            return out
        out["photo"] = png_data_url(np.asarray(s.source.photo.rgb))
        verdict = s.source.check  # the photo's check, made as it was read (Sources.photo_source)
        out["check"] = {"ok": verdict.ok, "line": verdict.line(), "problems": list(verdict.problems)}
        notes = [str(n) for n in s.source.photo.meta.get("notes", [])]
        out["warnings"] = list(dict.fromkeys([*out.get("warnings", []), *notes]))
        return out

def _zoo_name(value: str) -> bool:
    """A shipped checkpoint's name (no path)."""
    return "/" not in value and os.sep not in value and value in zoo.available()


def decode_upload(data_url: str) -> bytes:
    """The bytes of a ``data:...;base64,`` URL (or plain base64)."""
    payload = "".join((data_url.split(",", 1)[1] if data_url.startswith("data:") else data_url).split())
    if not payload:  # said as such, not as an unreadable image
        raise RequestError("the upload is empty (no data); send the photo's bytes as a data: URL or base64")
    try:  # validated: characters outside base64 were dropped, and "%%%%" decoded to an empty "image"
        return base64.b64decode(payload, validate=True)
    except (ValueError, TypeError) as e:
        raise RequestError(f"the upload is not base64 data ({e})") from None

