"""A PNG encoder for bulk writes: every row under the "Up" filter, then zlib at a low level.

Any PNG reader decodes the same pixels as from Pillow's file. Pillow chooses among the five filters for every row,
which is most of its time at zlib level 1: on a preprocessing preview strip (256 x 1,288 RGB) it takes 16.7 ms
against 8.5 ms here, for a file 2% larger. ``zlib.compress`` releases the GIL, so a writer thread overlaps it with
other work. Every other PNG of the package is written by imageio's Pillow plugin (:func:`difareli.utils.viz.save_png`).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG colour type per channel count: grey, RGB, RGBA (no palette, no grey + alpha).
COLOUR_TYPE = {1: 0, 3: 2, 4: 6}
UP = 2  # the filter byte: each byte minus the byte above it, modulo 256


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bytes(image: np.ndarray, level: int = 1) -> bytes:
    """The PNG file of a uint8 image, ``(H, W)`` grey or ``(H, W, C)`` with C in 1, 3, 4, at zlib ``level``."""
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in COLOUR_TYPE) or 0 in a.shape:
        raise ValueError(f"png_bytes: a non-empty uint8 (H, W) or (H, W, 1|3|4) image expected, "
                         f"got {a.dtype} {a.shape}")
    h, w = a.shape[:2]
    c = 1 if a.ndim == 2 else a.shape[2]
    flat = a.reshape(h, w * c)
    rows = np.empty((h, 1 + w * c), np.uint8)
    rows[:, 0] = UP
    rows[0, 1:] = flat[0]  # the row above the first is zeros
    np.subtract(flat[1:], flat[:-1], out=rows[1:, 1:])  # uint8 arithmetic wraps: the filter's modulo 256
    header = struct.pack(">IIBBBBB", w, h, 8, COLOUR_TYPE[c], 0, 0, 0)
    return (SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows.tobytes(), level))
            + _chunk(b"IEND", b""))
