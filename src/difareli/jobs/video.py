"""``difareli-video``'s job: a store record relit under a 360-degree light rotation through the relight spine's one
rotation path (:func:`difareli.relight.request.rotation_video`), beside its SynthFaces ground truth rendered under
the same lights, and measured (:mod:`difareli.evaluation.video`). With the ground truth, the frames may take its
exact shadow strengths or maps (oracle inputs: the :class:`~difareli.relight.request.Rotation`'s ``shadows`` and
``maps``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from difareli.data.store import EncodingStore
from difareli.evaluation import video as vid
from difareli.lighting import sh
from difareli.relight.relighter import Relighter
from difareli.relight.relit import Relit
from difareli.relight.request import Rotation, rotation_video
from difareli.synth import rotation as truth

#: What the measures read of the record besides the model's inputs.
MEASURE = ("image", "light", "normal", "face_mask", "shadow_map", "shadow")


@dataclass
class VideoRun:
    """A rotation relit (``relit``, its targets on it), what was relit (``what``), where its shadow strength and
    maps came from (``notes``), and with the ground truth its frames (``gt``) and measures (``report``)."""

    record: str
    what: str
    relit: Relit
    notes: dict[str, Any]
    gt: Any = None
    report: vid.VideoReport | None = None


def rotate_and_measure(relighter: Relighter, store: EncodingStore, record: str, rotation: Rotation, *,
                       ground_truth: bool, oracle_shadow: bool = False, oracle_maps: bool = False) -> VideoRun:
    """``record`` relit under ``rotation`` (module doc); ``ground_truth``: rendered and measured (a SynthFaces
    store), the oracles taken from it (the command checks that there is one before any work)."""
    source = relighter.source(store, record)
    what = ((f"environment map {rotation.envmap}" if rotation.envmap is not None else "the input's light")
            + f" rotated about {rotation.axis}, {rotation.frames} frames")
    gt = None
    if ground_truth:
        env = rotation.light()
        gt = (truth.ground_truth_lights(store, record, rotation.lights(source)) if env is not None else
              truth.ground_truth_rotation(store, record, rotation.axis, rotation.frames))
        oracle = {"shadows": tuple(float(c) for c in gt.targets["shadow"][:, 0]) if oracle_shadow else None,
                  "maps": gt.targets["shadow_map"] if oracle_maps else None}
        rotation = dataclasses.replace(rotation, **oracle)
        if oracle_maps:
            what += "; target shadow maps: the ground truth's exact ones (oracle_maps=true)"
    relit, notes = rotation_video(relighter, source, rotation, store)
    run = VideoRun(record, what, relit, notes, gt)
    if gt is not None:
        arrays = {**{k: np.asarray(v) for k, v in store.read(record, [n for n in MEASURE if store.available(n)])
                     .items()}, **source.arrays}
        # The maps the frames were given (made by the march, or the oracle's), to measure how far they are followed.
        given = (np.stack([a["shadow_map"] for a in relit.targets.retarget(source.arrays, ["shadow_map"])])
                 if "shadow_map" in relighter.model_inputs else None)
        # The rule measures (it is no model input): the exact suns of the input and of each frame; its floor, the
        # same frames rendered without cast shadows.
        run.report = vid.measure(np.asarray(relit), gt.frames, arrays, gt.suns(), gt.cast(), maps=given,
                                 input_light=truth.source_suns(store, record),
                                 shadowless=gt.without_shadows().frames)
    return run


def angles(rotation: Rotation) -> np.ndarray:
    """Each frame's angle in degrees."""
    return sh.rotation_frames(rotation.axis, rotation.frames)[0]
