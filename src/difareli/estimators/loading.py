"""Reading input photos defensively: every problem becomes a :class:`BadInput` with a clear reason.

Conversions that keep the image usable (grayscale, alpha, 16-bit, palette, EXIF rotation) are applied and
returned as notes; the pipeline records them in the report but still processes the image.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from difareli.errors import UserFileNotFoundError

#: File suffixes tried as images; anything else in the input folder is reported as "not an image file".
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".gif", ".ppm", ".pgm")


class BadInput(Exception):
    """An input that cannot be turned into encodings; ``str(e)`` is the reason written to the report."""


def list_inputs(in_dir: str | os.PathLike) -> list[Path]:
    """Files to process: ``in_dir`` itself if it is a file, else every regular file in it (sorted, not
    recursive; hidden files skipped). Non-image files are kept so that the report names them."""
    p = Path(in_dir)
    if p.is_file():
        return [p]
    if not p.is_dir():
        raise UserFileNotFoundError(f"in_dir {p} is neither a file nor a folder")
    return sorted(f for f in p.iterdir() if f.is_file() and not f.name.startswith("."))


_BAD_ID_CHARS = re.compile(r"[^A-Za-z0-9_.+=-]")


def sanitise_id(name: str) -> str:
    """A valid store record id from a file stem: other characters become '_', no leading '.'/'-'."""
    rid = _BAD_ID_CHARS.sub("_", name).lstrip(".-") or "image"
    return rid[:200]


def record_ids(files: list[Path]) -> dict[Path, str]:
    """Record id per file: the sanitised stem; stems shared by several files get the suffix appended."""
    stems: dict[str, int] = {}
    for f in files:
        stems[sanitise_id(f.stem)] = stems.get(sanitise_id(f.stem), 0) + 1
    out = {}
    for f in files:
        rid = sanitise_id(f.stem)
        out[f] = sanitise_id(f.name) if stems[rid] > 1 else rid
    return out


def load_image(path: str | os.PathLike, min_side: int = 64, max_side: int = 8192) -> tuple[np.ndarray, list[str]]:
    """Decode ``path`` to uint8 RGB HxWx3 and the list of conversions applied; raise :class:`BadInput`."""
    from PIL import Image, ImageFile, ImageOps, UnidentifiedImageError

    # face_recognition sets PIL's LOAD_TRUNCATED_IMAGES at import: once the identity estimator had loaded, a
    # truncated JPEG decoded silently (grey below the cut) and was relit. A truncated file is refused here always.
    ImageFile.LOAD_TRUNCATED_IMAGES = False
    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise BadInput(f"not an image file (suffix {path.suffix or 'none'!r})")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(path)
            w, h = im.size  # header only: the size check happens before any decoding
            if max(w, h) > max_side:
                raise BadInput(f"image too large: {w}x{h} px (limit {max_side} px per side)")
            if min(w, h) < min_side:
                raise BadInput(f"image too small: {w}x{h} px (need at least {min_side} px per side)")
            im.load()
    except BadInput:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError,
            Image.DecompressionBombWarning) as e:
        raise BadInput(f"unreadable image ({type(e).__name__}: {e})") from None
    notes = []
    if getattr(im, "n_frames", 1) > 1:
        notes.append(f"{im.n_frames} frames: used the first")
    transposed = ImageOps.exif_transpose(im)
    if transposed.size != im.size or transposed is not im:
        if im.getexif().get(0x0112, 1) != 1:
            notes.append("rotated by its EXIF orientation")
        im = transposed
    mode = im.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(im, dtype=np.float64)
        top = 65535.0 if arr.max() > 255 or mode.startswith("I;16") else 255.0
        grey = np.clip(np.round(arr / top * 255.0), 0, 255).astype(np.uint8)
        notes.append(f"16-bit grayscale ({mode}) scaled to 8 bits and replicated to RGB")
        return np.repeat(grey[..., None], 3, axis=-1), notes
    if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in im.info):
        # Composite over mid grey: transparent pixels carry arbitrary colours, and grey is neutral for SH.
        rgba = np.asarray(im.convert("RGBA"), dtype=np.float64) / 255.0
        rgb = rgba[..., :3] * rgba[..., 3:] + 0.5 * (1.0 - rgba[..., 3:])
        notes.append("alpha channel composited over grey" + (" (grayscale)" if mode == "LA" else ""))
        return np.round(rgb * 255.0).astype(np.uint8), notes
    if mode in ("L", "1"):
        notes.append("grayscale replicated to RGB")
        return np.repeat(np.asarray(im.convert("L"))[..., None], 3, axis=-1), notes
    if mode != "RGB":
        notes.append(f"colour mode {mode} converted to RGB")
        im = im.convert("RGB")
    arr = np.asarray(im)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.dtype != np.uint8:
        raise BadInput(f"unsupported pixel layout {arr.shape} {arr.dtype} (mode {mode})")
    return np.ascontiguousarray(arr), notes
