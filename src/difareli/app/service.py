"""What the app's page asks for, without HTTP: sources (an uploaded photo, preprocessed once; a store record),
target lights (a direction on the sphere, an HDR map and a rotation), relights with their seconds and the model's
reconstruction error.

Everything expensive is cached: relighters per (checkpoint, sampler, steps), prepared photos per (content,
encodings, size), inversions per source inside each relighter; one lock runs one relight at a time (the CPU is
the limit, and the estimators are not thread-safe).
"""

from __future__ import annotations

import base64
import hashlib
import tempfile
import threading
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from difareli.data import encodings
from difareli.lighting import sh
from difareli.diffusion.spec import DEFAULT_SAMPLER, PRESETS
from difareli.data.encodings import SHADOW_C_HI, SHADOW_C_LO

from .envmaps import ENVMAPS, envmap_light

SAMPLERS = ("unipc", "ddim", "dpm_solver", "dpm_solver_pp")
#: What the page starts with and a request without sampler / steps gets: the default preset, the cards' sampler.
DEFAULT = PRESETS[DEFAULT_SAMPLER]
MAX_UPLOAD_BYTES = 32 * 2 ** 20


class RequestError(ValueError):
    """A request the page should not have sent (missing field, unknown id): one line, HTTP 400."""


def png_data_url(image: np.ndarray) -> str:
    """A uint8 image as a ``data:image/png;base64,...`` URL."""
    import imageio.v3 as iio

    return "data:image/png;base64," + base64.b64encode(iio.imwrite("<bytes>", image, extension=".png")).decode()


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The 3x3 rotation taking unit vector ``a`` to unit vector ``b`` about their common normal (Rodrigues)."""
    a, b = np.asarray(a, np.float64) / np.linalg.norm(a), np.asarray(b, np.float64) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-9:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])  # half turn about any normal
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def light_toward(light: np.ndarray, direction) -> np.ndarray:
    """The source's own ``light`` turned so that its dominant direction is ``direction`` (camera space: x right,
    y up, z toward the viewer): the same ambient, colour and strength the model saw, from a new side."""
    d = np.asarray(direction, np.float64)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.linalg.norm(d) > 0:
        raise RequestError(f"light direction {direction!r} is not a non-zero 3-vector")
    return sh.rotate(light, rotation_between(sh.dominant_direction(light), d))


def shadow_logit(strength: float) -> float:
    """Shadow strength in [0, 1] (the shadow map's normalised c) -> the logit c'."""
    return SHADOW_C_LO + float(np.clip(strength, 0.0, 1.0)) * (SHADOW_C_HI - SHADOW_C_LO)


@dataclass
class AppSource:
    """A face the page relights: the relight core's Source, and for a photo the prepared photo."""

    id: str
    source: Any
    prepared: Any | None
    preprocess_s: float
    checkpoint: str


@dataclass
class Service:
    """The app's state: configuration, caches and the lock (module doc)."""

    checkpoint: str = "difareli_pp-synth64"
    store: str | None = None
    runtime: Mapping[str, Any] | None = None
    composite: Mapping[str, Any] = field(default_factory=lambda: {"mode": "ratio", "feather": 0.03})
    lock: threading.Lock = field(default_factory=threading.Lock)
    _relighters: dict = field(default_factory=dict)
    _sources: dict = field(default_factory=dict)
    _store: Any = None
    _errors: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ models and stores
    def relighter(self, checkpoint: str | None, sampler: str = DEFAULT.name, steps: int = DEFAULT.steps):
        """A cached :class:`~difareli.relight.relighter.Relighter`; a one-pass student ignores the sampler."""
        from difareli.errors import check_int
        from difareli.relight.relighter import Relighter

        if sampler not in SAMPLERS:
            raise RequestError(f"sampler={sampler!r}: not a sampler; use one of {', '.join(SAMPLERS)}")
        steps = check_int(steps, "steps", 1)
        key = (checkpoint or self.checkpoint, sampler, steps)
        if key not in self._relighters:
            self._relighters[key] = Relighter(key[0], {"name": sampler, "steps": steps}, runtime=self.runtime)
        return self._relighters[key]

    def open_store(self):
        from difareli.data.store import EncodingStore

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
        from difareli.checkpoints import zoo

        return {"checkpoint": self.checkpoint, "checkpoints": zoo.available(), "samplers": list(SAMPLERS),
                "default_sampler": {"name": DEFAULT.name, "steps": DEFAULT.steps},
                "envmaps": list(ENVMAPS), "records": self.records(), "store": self.store}

    # ------------------------------------------------------------------ sources
    def _face_mask_reads(self, relighter) -> list[str]:
        return list(dict.fromkeys([*relighter.needed_encodings(), "face_mask"]))

    def upload(self, name: str, data: bytes, checkpoint: str | None = None) -> AppSource:
        """An uploaded photo, decoded with the CLI's checks and preprocessed once for ``checkpoint``'s model;
        a bad upload raises the CLI's UserError (``image=<name>: ...``)."""
        from difareli.relight.photo import prepare_photo, read_photo

        name = Path(str(name or "upload")).name
        if len(data) > MAX_UPLOAD_BYTES:
            raise RequestError(f"image={name}: {len(data) / 2 ** 20:.0f} MiB is over the {MAX_UPLOAD_BYTES >> 20} MiB "
                               "upload limit; give a smaller photo")
        relighter = self.relighter(checkpoint)
        size = int(relighter.config.get("input_dims", {}).get("resolution", 64))
        names = self._face_mask_reads(relighter)
        sid = f"photo-{hashlib.sha1(data).hexdigest()[:16]}-{size}"
        key = (sid, tuple(names))
        if key not in self._sources:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / name
                path.write_bytes(data)
                rgb = read_photo(path, "image", name=name)
            prepared = prepare_photo(rgb, names, size=size, what=f"image={name}")
            source = relighter.source_from_arrays(prepared.arrays, f"image={name}", key=("app", sid))
            self._sources[key] = AppSource(sid, source, prepared, prepared.seconds, checkpoint or self.checkpoint)
            self._sources[sid] = self._sources[key]
            return self._sources[key]
        return AppSource(**{**self._sources[key].__dict__, "preprocess_s": 0.0})

    def record(self, rid: str, checkpoint: str | None = None) -> AppSource:
        """A store record as a source (its face mask read too, for the reconstruction error)."""
        st = self.open_store()
        if not st.has(rid):
            raise RequestError(f"record={rid}: not in the store {st.root}; pick one of the listed records")
        relighter = self.relighter(checkpoint)
        src = relighter.source(st, rid)
        arrays = dict(src.arrays)
        if "face_mask" not in arrays and st.available("face_mask"):
            arrays["face_mask"] = np.asarray(st.read(rid, ["face_mask"])["face_mask"])
        src = relighter.source_from_arrays(arrays, src.what, key=src.key)
        out = AppSource(f"record-{rid}", src, None, 0.0, checkpoint or self.checkpoint)
        self._sources[out.id] = out
        return out

    def describe(self, s: AppSource) -> dict:
        """What the page shows of a source: the aligned crop, its light's direction and shadow strength."""
        arrays = s.source.arrays
        c = encodings.shadow_logit(arrays)
        out = {"id": s.id, "what": s.source.what, "crop": png_data_url(np.asarray(arrays["image"])),
               "preprocess_s": round(s.preprocess_s, 3), "direction": sh.dominant_direction(arrays["light"]).tolist(),
               "shadow": None if c is None else float(encodings.normalise_c(c))}
        if s.prepared is not None:
            out.update(width=int(s.prepared.rgb.shape[1]), height=int(s.prepared.rgb.shape[0]),
                       stages={k: round(v, 3) for k, v in s.prepared.meta.get("seconds", {}).items()})
        return out

    # ------------------------------------------------------------------ relighting
    def target_light(self, arrays: Mapping[str, np.ndarray], light: Mapping[str, Any]) -> np.ndarray:
        """The target light a request describes: ``{"kind": "direction", "direction": [x, y, z]}`` or
        ``{"kind": "envmap", "name": ..., "rotation": degrees}``."""
        kind = (light or {}).get("kind", "direction")
        own = np.asarray(arrays["light"], np.float64)
        if kind == "direction":
            return light_toward(own, light.get("direction", [0.0, 0.0, 1.0]))
        if kind == "envmap":
            name = light.get("name")
            if name not in ENVMAPS:
                raise RequestError(f"envmap={name!r}: not a map; use one of {', '.join(ENVMAPS)}")
            return sh.yaw(envmap_light(name, own), float(light.get("rotation", 0.0)))
        raise RequestError(f"light kind {kind!r}: use 'direction' or 'envmap'")

    def relight(self, request: Mapping[str, Any]) -> dict:
        """Relight a source (``request["id"]`` from :meth:`upload` / :meth:`record`) under the request's light and
        shadow strength with its checkpoint / sampler / steps; returns the images (data URLs), the seconds per
        stage and the reconstruction error (the source relit under its own light, against itself)."""
        from difareli.relight.targets import Targets

        t_all = time.perf_counter()
        relighter = self.relighter(request.get("checkpoint"), request.get("sampler", DEFAULT.name),
                                   request.get("steps", DEFAULT.steps))
        s = self._sources.get(request.get("id"))
        if s is None:
            raise RequestError(f"source {request.get('id')!r} is unknown (the app restarted?); upload the photo again")
        if (request.get("checkpoint") or self.checkpoint) != s.checkpoint:  # another model may read more
            s = (self.upload_again(s, request.get("checkpoint")) if s.prepared is not None
                 else self.record(s.id.removeprefix("record-"), request.get("checkpoint")))
        arrays = s.source.arrays
        light = self.target_light(arrays, request.get("light") or {})
        strength = request.get("shadow")
        c = shadow_logit(float(strength)) if strength is not None else encodings.shadow_logit(arrays)
        own_c = encodings.shadow_logit(arrays)
        seconds = {}
        t0 = time.perf_counter()
        relighter.inversion(s.source)  # cached per source: 0 s from the second relight on
        seconds["invert"] = time.perf_counter() - t0
        # The reconstruction (the source relit under its own light) joins the first decode's batch, then is cached.
        key = (id(relighter), s.id)
        lights, cs = [light], [c]
        if key not in self._errors:
            lights, cs = [light, arrays["light"]], [c, own_c]
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:  # e.g. "unstable at this step count": show it
            warnings.simplefilter("always")
            out_frames = relighter.relight(s.source, Targets.of(lights, cs, s.source.what))
        seconds["decode"] = time.perf_counter() - t0
        if key not in self._errors:
            self._errors[key] = reconstruction_error(out_frames[1], arrays)
        relit = out_frames[0]
        out = {"crop": png_data_url(relit), "what": s.source.what, "how": relighter.describe(),
               "error": self._errors[key],
               "warnings": list(dict.fromkeys(str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)))}
        if s.prepared is not None:
            t0 = time.perf_counter()
            full = s.prepared.compositor(self.composite.get("mode", "ratio"),
                                         self.composite.get("feather", 0.03))(relit)
            seconds["composite"] = time.perf_counter() - t0
            out["image"] = png_data_url(full)
        else:
            out["image"] = out["crop"]
        seconds["total"] = time.perf_counter() - t_all
        out["seconds"] = {k: round(v, 3) for k, v in seconds.items()}
        return out

    def upload_again(self, s: AppSource, checkpoint: str | None) -> AppSource:
        """The same photo prepared for another checkpoint (its encodings may differ)."""
        import imageio.v3 as iio

        data = iio.imwrite("<bytes>", s.prepared.rgb, extension=".png")
        name = s.source.what.removeprefix("image=")
        return self.upload(Path(name).with_suffix(".png").name, data, checkpoint)


def reconstruction_error(recon: np.ndarray, arrays: Mapping[str, np.ndarray]) -> dict:
    """MSE and DSSIM of the self-relight against the input, on the face mask ([0, 1] units)."""
    import torch

    from difareli.evaluation.metrics import dssim, masked_mse

    to_t = lambda a: torch.from_numpy(np.asarray(a, np.float64) / 255.0).permute(2, 0, 1)[None]
    mask = np.array(arrays["face_mask"], bool) if "face_mask" in arrays else np.ones(recon.shape[:2], bool)
    m = torch.from_numpy(mask)[None]
    pred, target = to_t(recon), to_t(arrays["image"])
    return {"mse": round(float(masked_mse(pred, target, m)[0]), 5), "dssim": round(float(dssim(pred, target, m)[0]), 5),
            "region": "face mask" if "face_mask" in arrays else "whole crop"}


def decode_upload(data_url: str) -> bytes:
    """The bytes of a ``data:...;base64,`` URL (or plain base64)."""
    payload = data_url.split(",", 1)[1] if data_url.startswith("data:") else data_url
    try:
        return base64.b64decode(payload, validate=False)
    except (ValueError, TypeError) as e:
        raise RequestError(f"the upload is not base64 data ({e})") from None


__all__ = [
    "RequestError",
    "Service",
    "decode_upload",
    "light_toward",
    "png_data_url",
    "reconstruction_error",
    "rotation_between",
    "shadow_logit",
]
