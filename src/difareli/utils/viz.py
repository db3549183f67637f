"""What people look at, written: image grids, captions and contact sheets shared by previews, reconstruction grids
and relighting outputs; PNGs; and videos, a frame sequence as MP4 (H.264 through imageio's ffmpeg plugin) or GIF (a
fast palette per frame), with the line a command ends with for each file. Every command that writes a rotation video
(difareli-relight video.axis=, difareli-video, the demo) writes it here."""

from __future__ import annotations

import base64
import functools
import importlib.util
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import torch

from difareli.errors import UserError
from difareli.utils.fileio import atomic_path


def to_uint8(img) -> np.ndarray:
    """A [-1, 1] float tensor/array (CHW or HWC) -> uint8 HWC; uint8 input passes through."""
    if isinstance(img, torch.Tensor):
        img = img.detach().float().cpu().numpy()
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    if img.ndim == 3 and img.shape[0] in (1, 3) and img.shape[-1] not in (1, 3):
        img = img.transpose(1, 2, 0)
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    return np.clip((img + 1.0) * 127.5 + 0.5, 0, 255).astype(np.uint8)


def grid(rows: Sequence[Sequence[np.ndarray]], pad: int = 2, fill: int = 255, *,
         col_labels: Sequence[str] | None = None, row_labels: Sequence[str] | None = None,
         cell_labels: Sequence[Sequence[str]] | None = None) -> np.ndarray:
    """Tile rows of equally sized uint8 HWC images into one image with ``pad`` pixels between cells.

    Labels make a picture readable on its own: ``col_labels`` a header row of text above the columns (``input``,
    ``relit``, ``ground truth``), ``row_labels`` a band at the left (one name per row), ``cell_labels`` a caption
    above each cell (a contact sheet's light angles). Text is dark on the ``fill`` background, shrunk to fit."""
    ch, cw = rows[0][0].shape[:2]  # label sizes follow the images, not the captioned cells
    if cell_labels is not None:  # one font size for every caption, the largest at which all fit
        size = min(fitted_size(t, label_size(ch), cw) for texts in cell_labels for t in texts)
        rows = [[caption(cell, text, fill, size) for cell, text in zip(row, texts)]
                for row, texts in zip(rows, cell_labels)]
    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    out = np.full((len(rows) * (h + pad) + pad, ncol * (w + pad) + pad, 3), fill, np.uint8)
    for i, row in enumerate(rows):
        for j, cell in enumerate(row):
            y, x = pad + i * (h + pad), pad + j * (w + pad)
            out[y:y + h, x:x + w] = cell
    if row_labels is not None:
        size = label_size(ch)
        width = max(text_width(t, size) for t in row_labels) + 2 * pad + 4
        band = np.full((out.shape[0], width, 3), fill, np.uint8)
        for i, text in enumerate(row_labels):
            draw_text(band, text, (pad + 2, pad + i * (h + pad) + (h - size) // 2), size)
        out = np.concatenate([band, out], axis=1)
    if col_labels is not None:
        size = label_size(ch)
        head = np.full((size + 2 * pad + 4, out.shape[1], 3), fill, np.uint8)
        left = out.shape[1] - (ncol * (w + pad) + pad)  # the row-label band's width
        for j, text in enumerate(col_labels):
            fit = fitted_size(text, size, w)
            x = left + pad + j * (w + pad) + max(0, (w - text_width(text, fit)) // 2)
            draw_text(head, text, (x, pad + 2 + size - fit), fit)
        out = np.concatenate([head, out], axis=0)
    return out


def contact_sheet(frames: Sequence[np.ndarray], captions: Sequence[str] | None = None,
                  columns: int = 10) -> np.ndarray:
    """Frames ``columns`` a row, each under its caption (a rotation's light angle; none without captions)."""
    starts = range(0, len(frames), columns)
    rows = [list(frames[i:i + columns]) for i in starts]
    return grid(rows, cell_labels=None if captions is None else [list(captions[i:i + columns]) for i in starts])


def rotation_captions(axis: str, frames: int) -> list[str]:
    """``yaw 0°``, ``yaw 6°``, ...: each frame's light angle in a 360-degree rotation of ``frames`` frames (the
    angles of :func:`difareli.lighting.sh.rotation_frames`)."""
    return [f"{axis} {360.0 * i / frames:.0f}°" for i in range(frames)]


def label_size(cell_height: int) -> int:
    """Font size of a grid's labels: readable (>= 10 px) and in proportion to the cells (at most 20 px)."""
    return int(min(20, max(10, cell_height // 10)))


def caption(cell: np.ndarray, text: str, fill: int = 255, size: int | None = None) -> np.ndarray:
    """``cell`` with a band of ``text`` above it (at ``size``, else shrunk to the cell's width; the band's height
    depends on the cell only, so captioned cells of one grid stay the same size)."""
    full = label_size(cell.shape[0])
    size = min(full, size) if size is not None else fitted_size(text, full, cell.shape[1])
    band = np.full((full + 4, cell.shape[1], 3), fill, np.uint8)
    draw_text(band, text, (max(0, (cell.shape[1] - text_width(text, size)) // 2), 2 + full - size), size)
    return np.concatenate([band, cell], axis=0)


@functools.lru_cache(maxsize=32)
def _font(size: int):
    """Pillow's default font at ``size`` (loaded once per size: a load costs more than drawing a label)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # pragma: no cover - Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def text_width(text: str, size: int) -> int:
    """Pixel width of ``text`` at font ``size``."""
    from PIL import Image, ImageDraw

    return int(np.ceil(ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(text, font=_font(size))))


def fitted_size(text: str, size: int, width: int, smallest: int = 7) -> int:
    """The largest font size <= ``size`` (and >= ``smallest``) at which ``text`` fits ``width`` pixels."""
    while size > smallest and text_width(text, size) > width - 2:
        size -= 1
    return size


def draw_text(canvas: np.ndarray, text: str, xy: tuple[int, int], size: int, colour=(20, 20, 20)) -> None:
    """Draw ``text`` into the uint8 HWC ``canvas`` in place, its top-left at ``xy``."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(canvas)
    ImageDraw.Draw(im).text(xy, text, fill=colour, font=_font(size))
    canvas[...] = np.asarray(im)


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write a uint8 image atomically (beside the target, then renamed: a full disk or a kill never leaves a
    truncated PNG), creating parent folders."""
    path = Path(path)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, image, extension=path.suffix or ".png")
    return path


def png_data_url(image: np.ndarray) -> str:
    """A uint8 image as a ``data:image/png;base64,...`` URL (what the app's page shows)."""
    return "data:image/png;base64," + base64.b64encode(iio.imwrite("<bytes>", image, extension=".png")).decode()


# ---------------------------------------------------------------------------------------------- videos
#: The video formats: ``auto`` is MP4 where imageio's ffmpeg plugin is installed (``pip install imageio-ffmpeg``,
#: the ``video`` extra: a 60-frame rotation is tens of kB), else an optimised GIF.
VIDEO_FORMATS = ("auto", "mp4", "gif")


def has_mp4() -> bool:
    """Whether MP4 can be written here (imageio's ffmpeg plugin is installed)."""
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def video_format(fmt: str = "auto", key: str = "format") -> str:
    """``fmt`` resolved to ``mp4`` or ``gif`` (``auto``: MP4 where the encoder exists); a UserError naming ``key``
    for another value, or for ``mp4`` without the encoder."""
    if fmt not in VIDEO_FORMATS:
        raise UserError(f"{key}={fmt!r} is not a video format; use one of {', '.join(VIDEO_FORMATS)}")
    if fmt == "mp4" and not has_mp4():
        raise UserError(f"{key}=mp4 needs imageio's ffmpeg plugin: pip install imageio-ffmpeg (or {key}=gif)")
    return ("mp4" if has_mp4() else "gif") if fmt == "auto" else fmt


def describe_file(path: str | Path) -> str:
    """``path (123 kB)``: a written file and its size, for the line a command ends with."""
    size = Path(path).stat().st_size
    return f"{path} ({size / 2 ** 20:.1f} MB)" if size >= 2 ** 20 else f"{path} ({size / 1024:.0f} kB)"


def write_video(frames: np.ndarray, path: str | Path, fps: int = 20) -> Path:
    """Write frames (N, H, W, 3) uint8 as a GIF (``.gif``: :func:`write_gif`, one fast palette per
    frame) or an MP4 (``.mp4``: H.264 through imageio's ffmpeg plugin), renamed into place when whole."""
    path = Path(path)
    if path.suffix == ".gif":
        return write_gif(frames, path, fps)
    if path.suffix != ".mp4":
        raise ValueError(f"cannot write {path}: a video is .gif or .mp4")
    if not has_mp4():
        raise RuntimeError(f"cannot write {path}: MP4 needs imageio's ffmpeg plugin (pip install imageio-ffmpeg); "
                           "or use a .gif path")
    # H.264 needs even sides: a 64 px crop is, a whole photo may not be (padded by one edge row/column).
    f = np.asarray(frames)
    f = np.pad(f, ((0, 0), (0, f.shape[1] % 2), (0, f.shape[2] % 2), (0, 0)), mode="edge")
    with atomic_path(path) as tmp:  # a kill or a full disk leaves no half video; ffmpeg is told the container
        iio.imwrite(tmp, f, fps=fps, codec="libx264", macro_block_size=1, extension=".mp4",
                    output_params=["-f", "mp4"])  # (it picks it from the name, which the scratch name hides)
    return path


def write_gif(frames: np.ndarray, path, fps: int = 20):
    """Full-resolution frames (N, H, W, 3) uint8 as a looping GIF, each frame on its own fast-octree palette:
    imageio's default (median cut, per frame) took 6.5 s for 60 frames of 512 px here, this 0.4 s (mean error ~3
    levels, no dithering)."""
    from PIL import Image

    path = Path(path)
    ims = [Image.fromarray(np.ascontiguousarray(f)).quantize(256, method=Image.Quantize.FASTOCTREE,
                                                            dither=Image.Dither.NONE) for f in frames]
    with atomic_path(path) as tmp:  # a kill or a full disk leaves no half GIF and no scratch file
        ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps), loop=0)
    return path


def enlarge(images: np.ndarray, height: int) -> np.ndarray:
    """``images`` (..., H, W, C) upscaled by the smallest whole factor that makes them at least ``height`` px
    tall, nearest (a 64 px crop's pixels stay visible, not blurred)."""
    k = max(1, -(-int(height) // np.asarray(images).shape[-3]))
    return np.repeat(np.repeat(np.asarray(images), k, axis=-3), k, axis=-2)


def write_rotation(frames: np.ndarray, out_dir: str | Path, name: str, *, axis: str | None = None, fps: int = 20,
                   fmt: str = "auto", zoom: int = 1, columns: int = 10) -> dict[str, Path]:
    """A rotation's frames written: ``<name>.<fmt>`` (upscaled ``zoom`` times, nearest) and its contact sheet
    ``<name>.png`` (``columns`` frames a row, each captioned with its light angle about ``axis``; none without)."""
    out = Path(out_dir)
    big = np.repeat(np.repeat(frames, zoom, axis=1), zoom, axis=2) if zoom > 1 else frames
    sheet = contact_sheet(frames, rotation_captions(axis, len(frames)) if axis else None, columns)
    return {"video": write_video(big, out / f"{name}.{video_format(fmt)}", fps),
            "sheet": save_png(sheet, out / f"{name}.png")}
