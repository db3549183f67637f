"""Image grids and conversions shared by previews, reconstruction grids and relighting outputs."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import torch


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
    angles of :func:`difareli.relight.targets.rotation_lights`)."""
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


def _font(size: int):
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
    from difareli.utils.fileio import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, image, extension=path.suffix or ".png")
    return path


def png_data_url(image: np.ndarray) -> str:
    """A uint8 image as a ``data:image/png;base64,...`` URL (what the app's page shows)."""
    import base64

    return "data:image/png;base64," + base64.b64encode(iio.imwrite("<bytes>", image, extension=".png")).decode()
