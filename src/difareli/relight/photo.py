"""A face photo to the encodings a model reads, in memory (``difareli-relight image=photo.jpg``, the demo, the app),
and the relit crops back into the whole photo (:func:`PreparedPhoto.compositor`, :mod:`difareli.relight.composite`).

The same estimators as ``difareli-preprocess`` (``conf/preprocess/``), planned for exactly the encodings the
model needs (plus the part masks the composite blends with); nothing is written to disk. Pipelines are built once
per process and crop size (:func:`pipeline_for`): building one and its first image load mediapipe and dlib (s).

A photo is aligned at the resolution its checkpoint was trained at
(:func:`difareli.checkpoints.format.training_resolution`) unless told otherwise, and an input at another
resolution is named in a warning (:func:`resolution_warning`). A grey photo (:func:`is_grey`) gets a grey light and
comes back grey (:class:`~difareli.relight.relit.Relit`): it has no colour for the model to keep.

A group photo: :func:`detect_faces` lists every face (left to right), ``prepare_photo(..., face=box)`` aligns the
one chosen (``face=<index>|largest|all`` of difareli-relight, :func:`choose_faces`). Where the aligned square runs
past the photo's edge (a tight crop) the crop is reflect-padded (``border="reflect"``, the default: measured
closer to the uncut photo's relight than ``"mask"``, which labels the padded band ``background``; docs/photos.md,
the composite never takes the padding back.
"""

from __future__ import annotations

import errno
import os
import stat
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from difareli.errors import UserError, check_file
from difareli.estimators.light import describe_light, is_grey, light_direction  # noqa: F401 (re-exported)
from difareli.estimators.loading import BadInput, load_image
from difareli.estimators.align import inside_photo
from difareli.estimators.quiet import native_logs
from difareli.relight.composite import DEFAULT_PARTS, Compositor

BORDERS = ("reflect", "mask")
EXTRAS_FIX = "install the photo estimators: DIFARELI_PREPROCESS=1 bash scripts/install.sh"
PHOTO_FIX = "use a photo with one clearly visible face"
#: The smallest aligned crop the photo estimators fit a light on: the fit needs 100 usable skin pixels
#: (``SkinSHLight.min_pixels``) and a face's skin is about a tenth of the crop (the astronaut: 6 at 16 px, 50 at 24,
#: 68 at 28; 32 px and up fit). A 16 px model's photo had failed on "too few usable skin pixels".
MIN_PHOTO_SIZE = 32


def resolution_warning(checkpoint: Any, trained: int | None, what: str, size: int, fix: str) -> str | None:
    """One line when ``what`` (``size`` px) differs from the checkpoint's training resolution, else None."""
    if trained is None or int(size) == int(trained):
        return None
    return (f"warning: checkpoint={checkpoint} was trained at {trained} px, {what} is {size} px: the model runs "
            f"outside its training resolution (slower, grainy results); {fix}")


def check_photo_size(size: int, checkpoint: Any, given: bool) -> None:
    """A crop of ``size`` px is one the estimators can read (:data:`MIN_PHOTO_SIZE`); else one line naming the
    size, where it came from (``given``: photo_size=, else the checkpoint's training resolution) and the fix."""
    if int(size) >= MIN_PHOTO_SIZE:
        return
    if given:
        raise UserError(f"photo_size={size} is too small for the photo estimators (a face crop under "
                        f"{MIN_PHOTO_SIZE} px holds too few skin pixels to fit its light); give photo_size="
                        f"{MIN_PHOTO_SIZE} or more")
    raise UserError(f"checkpoint={checkpoint} was trained at {size} px, too small a face crop for the photo "
                    f"estimators (under {MIN_PHOTO_SIZE} px it holds too few skin pixels to fit its light); give "
                    f"photo_size={MIN_PHOTO_SIZE} or more (the model then runs outside its {size} px), or a "
                    f"checkpoint trained at {MIN_PHOTO_SIZE} px or more")


def photo_dims(encodings: Sequence[str], size: int, estimators: Mapping[str, Any] | None = None,
               composite: bool = True) -> dict[str, int]:
    """The dimensions (H, W, S, D) of what :func:`prepare_photo` writes, before any photo is read."""
    try:
        return pipeline_for([*encodings, *(["masks"] if composite else [])], size, estimators).dims()
    except ImportError as e:
        raise ImportError(f"relighting a photo needs the estimators' packages ({e}); {EXTRAS_FIX}") from e


def pipeline_for(encodings: Sequence[str], size: int, estimators: Mapping[str, Any] | None = None):
    """A :class:`~difareli.estimators.pipeline.Pipeline` for the image and ``encodings`` at ``size`` px: the default
    estimators' (built once per process, :func:`~difareli.estimators.pipeline.default_pipeline`), or a new one of a
    caller's own ``estimators`` block."""
    from difareli.estimators.pipeline import Pipeline, default_pipeline

    names = ["image", *encodings]
    return default_pipeline(names, size) if estimators is None else Pipeline.from_config(estimators, names)


@dataclass
class PreparedPhoto:
    """One photo, preprocessed once: the decoded original, the encodings of its aligned crop, the alignment quad
    (photo coordinates) and the estimators' meta (seconds per stage, notes)."""

    rgb: np.ndarray
    arrays: dict[str, np.ndarray]
    quad: np.ndarray
    meta: dict = field(default_factory=dict)
    seconds: float = 0.0
    inside: np.ndarray | None = None  # bool (S, S): crop pixels sampling the photo, not its padding
    landmarks: np.ndarray | None = None  # the alignment's FaceMesh landmarks (478, 3), photo pixels

    @property
    def past_edge(self) -> float:
        """Share of the aligned crop that lies past the photo's edge (padding)."""
        return 0.0 if self.inside is None else float(1.0 - self.inside.mean())

    def compositor(self, mode: str = "ratio", feather: float = 0.03, parts: Sequence[str] | None = None):
        """A :class:`difareli.relight.composite.Compositor` putting relit crops of this photo back into it."""
        return Compositor(self.rgb, np.asarray(self.arrays["image"]), np.asarray(self.arrays["masks"]), self.quad,
                          mode=mode, feather=float(feather), parts=tuple(parts or DEFAULT_PARTS),
                          inside=self.inside)


def detect_faces(rgb: np.ndarray, size: int, estimators: Mapping[str, Any] | None = None
                 ) -> list[np.ndarray]:
    """Every face BlazeFace finds (``align.FaceAligner.detect``: whole photo, then tiles), as boxes (x, y, w, h
    in photo pixels) ordered left to right: ``face=<index>`` counts in this order."""
    try:
        aligner = pipeline_for(["masks"], size, estimators).aligner
        with native_logs():
            found = aligner.detect(np.ascontiguousarray(np.asarray(rgb)[..., :3]))
    except ImportError as e:
        raise ImportError(f"relighting a photo needs the estimators' packages ({e}); {EXTRAS_FIX}") from e
    return [b for _, b in sorted(found, key=lambda sb: sb[1][0])]


def choose_faces(boxes: Sequence[np.ndarray], face: Any, what: str) -> list[int]:
    """Indices into ``boxes`` (left to right) for ``face`` = largest | all | <index>; a UserError otherwise."""
    key = str(face).strip().lower()
    if not boxes:
        return []
    if key == "largest":
        return [int(np.argmax([b[2] * b[3] for b in boxes]))]
    if key == "all":
        return list(range(len(boxes)))
    try:
        i = int(key)
    except ValueError:
        raise UserError(f"face={face}: not a face choice; give face=largest, face=all or face=<index> "
                        f"(0..{len(boxes) - 1}, left to right)") from None
    if not 0 <= i < len(boxes):
        raise UserError(f"face={face}: {what} has {len(boxes)} detected face(s), indices 0..{len(boxes) - 1} left "
                        "to right; give one of them, face=largest or face=all")
    return [i]


def describe_box(i: int, box: np.ndarray, chosen: bool) -> str:
    """One line per detected face: its index, box and whether it is relit."""
    x, y, w, h = (float(v) for v in box)
    return f"face {i}: box x={x:.0f} y={y:.0f} w={w:.0f} h={h:.0f} px{' (relit)' if chosen else ''}"


def prepare_photo(rgb: np.ndarray, encodings: Sequence[str], *, size: int,
                  estimators: Mapping[str, Any] | None = None, what: str = "photo",
                  composite: bool = True, face: np.ndarray | None = None, border: str = "reflect") -> PreparedPhoto:
    """Preprocess one decoded RGB photo (uint8 HxWx3) for ``encodings`` at ``size`` px; ``composite`` adds the
    part masks the composite blends with; ``face``: a box of :func:`detect_faces` (None: the largest);
    ``border``: ``reflect`` leaves the crop's padding past the photo's edge to the estimators, ``mask`` labels it
    background (module doc). Errors: a UserError naming ``what`` (no face...), or an ImportError naming the
    install command."""
    if border not in BORDERS:
        raise UserError(f"border must be one of {BORDERS}, got {border!r}")
    rgb = np.ascontiguousarray(np.asarray(rgb)[..., :3])
    names = [*encodings, *(["masks"] if composite else [])]
    start = time.perf_counter()
    try:
        pipe = pipeline_for(names, size, estimators)
        pipe.aligner.select = None if face is None else np.asarray(face, np.float64)
        try:
            arrays, meta, ctx = pipe.process(rgb)
        finally:
            pipe.aligner.select = None
    except ImportError as e:
        raise ImportError(f"relighting a photo needs the estimators' packages ({e}); {EXTRAS_FIX}") from e
    except BadInput as e:
        raise UserError(f"{what}: {e}; {PHOTO_FIX}") from None
    meta["notes"] = list(ctx["notes"])
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    quad = np.asarray(ctx["quad"], np.float64)
    inside = inside_photo(quad, size, rgb.shape[:2])
    if border == "mask" and "masks" in arrays and not inside.all():
        arrays["masks"] = np.where(inside, arrays["masks"], 0).astype(arrays["masks"].dtype)
    lm = ctx.get("alignment_landmarks")
    return PreparedPhoto(rgb, arrays, quad, meta, time.perf_counter() - start, inside,
                         None if lm is None else np.asarray(lm))


def read_photo(path: str | Path, key: str = "image", name: str | None = None) -> np.ndarray:
    """Decode a photo file to uint8 RGB (the preprocess loader's checks), or a UserError naming ``key`` and the
    file (``name``: how to name it instead of its path, e.g. an uploaded file's name). A folder or a special file
    (``/dev/zero``, a FIFO) is named as what it is, an animation (several frames) is refused, and an alpha channel
    composited over grey is said in a UserWarning."""
    shown = name or str(path)
    try:
        mode = os.stat(str(path)).st_mode
    except OSError as e:
        if os.path.islink(str(path)):  # a link that leads nowhere: said as such, not as a missing file
            why = ("a symbolic link loop" if e.errno == errno.ELOOP else
                   f"a symbolic link to {os.readlink(str(path))}, which does not exist")
            raise UserError(f"{key}={shown} is {why}; point it at a photo or remove it") from None
        mode = None  # missing or unreachable: check_file says which
    if mode is not None and not stat.S_ISREG(mode):
        kind = ("a folder" if stat.S_ISDIR(mode) else "a character device" if stat.S_ISCHR(mode) else
                "a block device" if stat.S_ISBLK(mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(mode) else
                "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
        raise UserError(f"{key}={shown} is {kind}, not an image file; give a JPEG/PNG face photo")
    p = check_file(path, key)
    try:
        rgb, notes = load_image(p)
    except BadInput as e:
        why = str(e).replace(str(p), name) if name else str(e)  # a temporary path means nothing to the user
        raise UserError(f"{key}={shown}: {why}; give a JPEG/PNG face photo") from None
    for note in notes:
        if "frames: used the first" in note:  # which frame is the face is a guess: ask for a still
            raise UserError(f"{key}={shown} is an animation ({note.split(':')[0]}); give one still photo (save the "
                            "frame you want as PNG)")
        if note.startswith("alpha channel"):
            warnings.warn(f"{key}={shown}: its {note} (transparent parts become grey); give an opaque photo to "
                          "choose the background", UserWarning, stacklevel=2)
    return rgb
