"""Ground-truth light rotations for SynthFaces: the same subject rendered under moving lights, cast shadows
included ("moving lights, measured").

A SynthFaces record is fully determined by the store header's :class:`~difareli.synth.config.SynthConfig`,
its subject index ``k`` and its light index ``j`` (``meta.json``: ``subject``, ``light_index``,
``light_group``). :func:`record_source` rebuilds the record's :class:`~difareli.synth.lights.Light`;
:func:`rotate_light` turns it by a rotation ``R`` (the ambient SH by ``sh.rotate``, every sun direction
``d -> R d``, which is the same rotation: ``rotate_light(L, R).sh() == sh.rotate(L.sh(), R)``), and
:func:`render_lights` renders the subject under each light with the generator's own ray-traced cast shadows
and the record's realism preset. Rotation by 0 reproduces the record's image bit for bit.

The target encodings returned per frame are the exact ones (``light``, ``shading``, ``shadow`` c,
``shadow_map``, the ``*_gt`` values of the store), whatever the store's ``inputs`` setting.

An arbitrary 9x3 SH light (e.g. an HDR environment map's projection) has no sun to ray-trace: it is rendered
as an ambient-only :class:`Light` (:func:`light_from_sh`), so its ground truth has no cast shadow.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from difareli.lighting import sh
from difareli.lighting.suns import Suns
from difareli.data.store import EncodingStore
from difareli.data import protocols as sp
from difareli.synth.config import SynthConfig
from difareli.synth.subject import build_subject, shade
from difareli.synth.blas import single_thread_blas
from difareli.synth.lights import Light, add_suns, extra_sun_rng, light_rng, sample_light
from difareli.errors import UserError
from difareli.render import cast_shadows

#: Exact per-frame target encodings returned with the frames.
TARGETS = ("light", "shading", "shadow", "shadow_map")


@dataclass
class GroundTruthFrames:
    """``frames`` (N, H, W, 3) uint8 and the exact target encodings of each frame, stacked on axis 0."""

    frames: np.ndarray
    targets: dict[str, np.ndarray]
    lights: list[Light]
    angles: np.ndarray | None = None   # degrees, for a rotation
    axis: str | None = None
    subject: tuple[SynthConfig, int] | None = None  # (config, subject index) it was rendered from

    def __len__(self) -> int:
        return len(self.frames)

    def cast(self) -> np.ndarray:
        """Binary cast-shadow maps (N, H, W): where the exact ``shadow_map`` is positive."""
        return self.targets["shadow_map"] > 0

    def suns(self) -> list[Suns | None]:
        """Each frame's light as :class:`~difareli.lighting.suns.Suns` (None for a frame without a sun)."""
        return [light.as_suns() for light in self.lights]

    def without_shadows(self) -> "GroundTruthFrames":
        """The same subject under the same lights with no cast shadow: what a relight that draws none is at best."""
        cfg, k = self.subject
        out = render_lights(cfg, k, self.lights, shadows=False)
        out.angles, out.axis = self.angles, self.axis
        return out


def synth_config(store: EncodingStore) -> SynthConfig:
    """The generator configuration stored in a SynthFaces store's header."""
    meta = store.store_meta
    if meta.get("generator") != "synthfaces":
        raise UserError(f"store {store.root} is not a SynthFaces store (header generator="
                        f"{meta.get('generator')!r}); ground-truth light rotations need SynthFaces records")
    names = {f.name for f in dataclasses.fields(SynthConfig)}
    return SynthConfig(**{k: v for k, v in meta.items() if k in names})


def record_source(store: EncodingStore, record_id: str) -> tuple[SynthConfig, int, Light]:
    """``(config, subject index k, Light)`` that generated ``record_id`` of a SynthFaces store."""
    cfg = synth_config(store)
    meta = store.meta(record_id)
    try:
        k, j = int(str(meta["subject"]).lstrip("s")), int(meta["light_index"])
    except (KeyError, ValueError):
        raise UserError(f"record {record_id!r} of {store.root} has no SynthFaces subject/light_index in its "
                        "meta.json") from None
    group = int(meta.get("light_group", sp.light_group(k, cfg.light_group_size)))
    light = sample_light(light_rng(cfg.seed, group, j))
    if cfg.fx.multi_sun:
        light = add_suns(light, extra_sun_rng(cfg.seed, group, j))
    return cfg, k, light


def rotate_light(light: Light, R: np.ndarray) -> Light:
    """``light`` with its whole environment rotated by ``R`` (3x3): ambient by ``sh.rotate``, suns ``d -> R d``."""
    R = np.asarray(R, dtype=np.float64)
    extra = np.asarray(light.extra_dirs, dtype=np.float64).reshape(-1, 3)
    return dataclasses.replace(light, ambient=sh.rotate(light.ambient, R), sun_dir=R @ light.sun_dir,
                               extra_dirs=extra @ R.T)


def light_from_sh(light_sh: np.ndarray, category: str = "sh") -> Light:
    """An ambient-only :class:`Light` whose ``sh()`` is ``light_sh`` (no sun, so no cast shadow)."""
    return Light(category, np.asarray(light_sh, dtype=np.float64).reshape(9, 3), np.array([0.0, 0.0, 1.0]),
                 np.zeros(3))


def render_lights(cfg: SynthConfig, k: int, lights: Sequence[Light], shadows: bool = True) -> GroundTruthFrames:
    """Subject ``k`` of ``cfg`` rendered under each light (cast shadows ray-traced per sun; none with
    ``shadows=False``: what a relight that draws no cast shadow would be at best)."""
    exact = dataclasses.replace(cfg, inputs="exact")  # the image does not depend on it; skip the estimators
    frames, targets = [], {n: [] for n in TARGETS}
    with single_thread_blas():  # bit-identical to the generator's own records
        subject = build_subject(k, exact)
        dirs = [d for light in lights for d, _ in light.suns()] if shadows else []
        maps = list(cast_shadows(subject.scene, subject.gbuffer, np.array(dirs))) if dirs else []
        for light in lights:
            n = len(light.suns()) if shadows else 0
            casts, maps = maps[:n], maps[n:]
            arrays, _ = shade(subject, light, casts if shadows else None, exact)
            frames.append(arrays["image"])
            for name in TARGETS:
                targets[name].append(arrays[f"{name}_gt"])
    return GroundTruthFrames(np.stack(frames), {n: np.stack(v) for n, v in targets.items()}, list(lights),
                             subject=(cfg, k))


def ground_truth_rotation(store: EncodingStore, record_id: str, axis: str = "yaw", frames: int = 60
                          ) -> GroundTruthFrames:
    """The record's subject under its own light rotated 360 degrees about ``axis`` (frame 0 = the record)."""
    cfg, k, light = record_source(store, record_id)
    angles, rots = sh.rotation_frames(axis, frames)
    out = render_lights(cfg, k, [rotate_light(light, R) for R in rots])
    out.angles, out.axis = angles, axis
    return out


def source_suns(store: EncodingStore, record_id: str) -> Suns | np.ndarray:
    """The record's own light as the video shadow rule reads it: its exact suns, or its SH light where it has no sun."""
    light = record_source(store, record_id)[2]
    suns = light.as_suns()
    return light.sh() if suns is None else suns


def ground_truth_lights(store: EncodingStore, record_id: str, lights: Sequence[np.ndarray | Light]
                        ) -> GroundTruthFrames:
    """The record's subject under arbitrary lights: :class:`Light` objects keep their suns (cast shadows),
    9x3 SH arrays are rendered ambient-only (:func:`light_from_sh`, no cast shadow)."""
    cfg, k, _ = record_source(store, record_id)
    return render_lights(cfg, k, [l if isinstance(l, Light) else light_from_sh(l) for l in lights])
