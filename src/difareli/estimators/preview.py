"""Preview strip per image: input | mesh overlay | shading reference | masks | shadow map, each panel labelled
with its name (drawn into the panel's top rows; the strip keeps its size).

The shading reference R is unclipped and often above 1 on a lit face (0.7 x irradiance): the panel shows it
divided by its 99th percentile on the face (the label says by how much), so the face is not clipped to white;
the input panel's label names the fitted light's direction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from difareli.data.encodings import NUM_MASK_PARTS
from difareli.utils.fileio import atomic_path

#: One colour per MASK_PARTS entry (background black, skin tan, hair brown, ...).
PALETTE = np.array([
    [0, 0, 0], [224, 172, 140], [120, 60, 20], [160, 80, 30], [40, 120, 255], [0, 200, 255], [255, 140, 0],
    [220, 30, 60], [150, 0, 40], [90, 0, 90], [255, 220, 120], [60, 160, 60], [110, 70, 40], [200, 200, 0],
], dtype=np.uint8)
assert len(PALETTE) == NUM_MASK_PARTS
#: The masks panel's blend ``0.35 v + 0.65 p`` (truncated to uint8) for every pair of uint8 values: a lookup is
#: the same pixels in half the time.
BLEND = (0.35 * np.arange(256)[:, None] + 0.65 * np.arange(256)[None, :]).astype(np.uint8)
#: zlib level of the preview PNGs (lossless at any level; see :func:`save_preview`).
PNG_LEVEL = 1


def segment_pixels(r0: np.ndarray, c0: np.ndarray, r1: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixels ``skimage.draw.line(r0, c0, r1, c1)`` draws, for many segments at once (int arrays): rows and
    columns of every segment, concatenated. Bresenham along the longer axis; at step ``i`` of ``n`` the other axis has
    moved ``floor((2 d i + n) / (2 n))`` of its ``d`` (skimage's ``d >= 0`` rule in closed form), then the end point."""
    dr, dc = np.abs(r1 - r0), np.abs(c1 - c0)
    steep = dr > dc
    n = np.maximum(dr, dc)  # steps along the major axis; the end point is added after them
    minor = np.where(steep, dc, dr)
    sr, sc = np.where(r1 > r0, 1, -1), np.where(c1 > c0, 1, -1)
    seg = np.repeat(np.arange(len(n)), n)
    i = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)  # step within its segment
    moved = (2 * minor[seg] * i + n[seg]) // np.maximum(2 * n[seg], 1)
    major_step, minor_step = i, moved
    rows = r0[seg] + sr[seg] * np.where(steep[seg], major_step, minor_step)
    cols = c0[seg] + sc[seg] * np.where(steep[seg], minor_step, major_step)
    return np.r_[rows, r1], np.r_[cols, c1]


def mesh_overlay(image: np.ndarray, landmarks_xy: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``image`` with the FaceMesh triangle edges drawn in green: each edge's pixels blended 40 / 60 with green
    (uint8 after each blend), a pixel on k edges blended k times, as drawing the edges one by one does."""
    out = image.copy()
    H, W = out.shape[:2]
    t = np.asarray(triangles)
    edges = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [0, 2]]]), axis=1), axis=0)
    pts = np.round(np.asarray(landmarks_xy) - 0.5).astype(int)
    rr, cc = segment_pixels(pts[edges[:, 0], 1], pts[edges[:, 0], 0], pts[edges[:, 1], 1], pts[edges[:, 1], 0])
    ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    times = np.bincount(rr[ok] * W + cc[ok], minlength=H * W)
    flat = out.reshape(-1, 3)
    green = np.array([0, 255, 0])
    for k in range(1, int(times.max(initial=0)) + 1):  # the blend is the same for every edge: its order is free
        sel = np.flatnonzero(times >= k)
        flat[sel] = (0.4 * flat[sel] + 0.6 * green).astype(np.uint8)
    return out


def shading_display(shading: np.ndarray, face: np.ndarray | None) -> tuple[np.ndarray, float]:
    """R for viewing: ``(uint8 image, scale)`` with ``scale`` = 1 / its 99th percentile on ``face`` (or on its
    non-zero pixels), so at most 1% of the face clips to white."""
    r = np.asarray(shading, dtype=np.float64)
    on = r[face] if face is not None and face.any() else r[r > 0]
    top = float(np.percentile(on, 99)) if on.size else 0.0
    scale = 1.0 / top if top > 1e-6 else 1.0
    return (np.clip(r * scale, 0, 1) * 255).astype(np.uint8), scale


def labels(ctx: dict) -> list[str]:
    """The panels' names (what :func:`panels` shows)."""
    from .light import describe_light

    face = ctx.get("face_mask")
    shading = "shading (not computed)"
    if "shading" in ctx:
        shading = f"shading x{shading_display(ctx['shading'], face)[1]:.2f} (p99 on face = white)"
    light = f"input; light {describe_light(ctx['light'])}" if "light" in ctx else "input"
    return [light, "FaceMesh" if "landmarks" in ctx else "mesh (not computed)", shading,
            "masks" if "masks" in ctx else ("face mask" if "face_mask" in ctx else "masks (not computed)"),
            "shadow map (red: cast x c)" if "shadow_map" in ctx else "shadow map (not computed)"]


def label(panel: np.ndarray, text: str) -> np.ndarray:
    """``panel`` with ``text`` drawn over its top rows, white on a dark band, wrapped to the panel's width."""
    out = panel.copy()
    label_into(out, text)
    return out


def label_into(panel: np.ndarray, text: str) -> None:
    """:func:`label` in place (``panel`` may be a view into the strip): only the rows the text can reach go
    through Pillow."""
    from difareli.utils.viz import draw_text, text_width

    size = max(8, round(panel.shape[0] / 22))
    lines, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}".strip()
        if cur and text_width(trial, size) > panel.shape[1] - 4:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    lines.append(cur)
    band = (size + 2) * len(lines) + 2
    top = panel[:min(panel.shape[0], band + 2 * size)]  # a glyph reaches at most 2 sizes below its line
    top[:band] = (top[:band] * 0.35).astype(np.uint8)
    for i, line in enumerate(lines):
        draw_text(top, line, (2, 1 + i * (size + 2)), size, colour=(255, 255, 255))


def panels(ctx: dict) -> list[np.ndarray]:
    """The five uint8 panels (grey where an encoding was not computed), unlabelled."""
    image = ctx["image"]
    blank = np.full_like(image, 64)
    out = [image]
    if "landmarks" in ctx:
        from .geometry import NUM_VERTICES, tessellation_triangles

        out.append(mesh_overlay(image, ctx["landmarks"][:NUM_VERTICES, :2], tessellation_triangles()))
    else:
        out.append(blank)
    # The stored R is unclipped (SPEC 3); the view is scaled by its 99th percentile on the face.
    out.append(shading_display(ctx["shading"], ctx.get("face_mask"))[0] if "shading" in ctx else blank)
    if "masks" in ctx:
        out.append(BLEND[image, PALETTE[ctx["masks"]]])
    elif "face_mask" in ctx:
        out.append((image * ctx["face_mask"][..., None]).astype(np.uint8))
    else:
        out.append(blank)
    if "shadow_map" in ctx:
        sm = ctx["shadow_map"]
        cast = np.asarray(ctx.get("cast", sm > 0), bool)
        panel = image // 2  # off the cast shadow: the image at half, (0.5 * v) truncated
        on = sm[cast][:, None]
        # Red: ray-traced shadow at normalised c; blue outline-free tint: traced but c ~ 0.
        red = np.array([255.0, 40, 40]) * on + np.array([60.0, 60, 255]) * (on == 0)
        panel[cast] = np.clip(0.4 * (0.5 * image[cast]) + 0.6 * red, 0, 255).astype(np.uint8)
        out.append(panel)
    else:
        out.append(blank)
    return out


def strip(ctx: dict) -> np.ndarray:
    """The labelled panels side by side, 2 white columns between them."""
    ps = panels(ctx)
    h, w = ps[0].shape[:2]
    out = np.full((h, len(ps) * (w + 2) - 2, 3), 255, np.uint8)
    for i, (p, text) in enumerate(zip(ps, labels(ctx))):
        view = out[:, i * (w + 2):i * (w + 2) + w]
        view[...] = p
        label_into(view, text)
    return out


def save_preview(path: str | Path, ctx: dict) -> None:
    """Write the preview strip PNG atomically (:func:`~difareli.utils.fileio.atomic_path`) with
    :func:`~difareli.utils.png.png_bytes` at zlib level :data:`PNG_LEVEL` (lossless at any level)."""
    from difareli.utils.png import png_bytes

    data = png_bytes(strip(ctx), PNG_LEVEL)
    with atomic_path(Path(path)) as tmp:
        tmp.write_bytes(data)
