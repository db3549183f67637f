"""Preview strip per image: input | mesh overlay | shading reference | masks | shadow map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from difareli.encodings import NUM_MASK_PARTS

#: One colour per MASK_PARTS entry (background black, skin tan, hair brown, ...).
PALETTE = np.array([
    [0, 0, 0], [224, 172, 140], [120, 60, 20], [160, 80, 30], [40, 120, 255], [0, 200, 255], [255, 140, 0],
    [220, 30, 60], [150, 0, 40], [90, 0, 90], [255, 220, 120], [60, 160, 60], [110, 70, 40], [200, 200, 0],
], dtype=np.uint8)
assert len(PALETTE) == NUM_MASK_PARTS


def mesh_overlay(image: np.ndarray, landmarks_xy: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``image`` with the FaceMesh triangle edges drawn in green."""
    from skimage.draw import line

    out = image.copy()
    H, W = out.shape[:2]
    edges = {tuple(sorted(e)) for t in triangles for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}
    pts = np.round(np.asarray(landmarks_xy) - 0.5).astype(int)
    for a, b in edges:
        rr, cc = line(pts[a, 1], pts[a, 0], pts[b, 1], pts[b, 0])
        ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
        out[rr[ok], cc[ok]] = (0.4 * out[rr[ok], cc[ok]] + 0.6 * np.array([0, 255, 0])).astype(np.uint8)
    return out


def panels(ctx: dict) -> list[np.ndarray]:
    """The five uint8 panels (grey where an encoding was not computed)."""
    image = ctx["image"]
    blank = np.full_like(image, 64)
    out = [image]
    if "landmarks" in ctx:
        from .geometry import NUM_VERTICES, tessellation_triangles

        out.append(mesh_overlay(image, ctx["landmarks"][:NUM_VERTICES, :2], tessellation_triangles()))
    else:
        out.append(blank)
    # The stored R is unclipped; a clipped copy is for viewing (SPEC 3).
    out.append((np.clip(ctx["shading"], 0, 1) * 255).astype(np.uint8) if "shading" in ctx else blank)
    if "masks" in ctx:
        out.append((0.35 * image + 0.65 * PALETTE[ctx["masks"]]).astype(np.uint8))
    elif "face_mask" in ctx:
        out.append((image * ctx["face_mask"][..., None]).astype(np.uint8))
    else:
        out.append(blank)
    if "shadow_map" in ctx:
        dim = (0.5 * image).astype(np.float64)
        sm = ctx["shadow_map"][..., None]
        cast = ctx.get("cast", ctx["shadow_map"] > 0)[..., None]
        # Red: ray-traced shadow at normalised c; blue outline-free tint: traced but c ~ 0.
        red = np.array([255.0, 40, 40]) * sm + np.array([60.0, 60, 255]) * (cast & (sm == 0))
        out.append(np.clip(np.where(cast, 0.4 * dim + 0.6 * red, dim), 0, 255).astype(np.uint8))
    else:
        out.append(blank)
    return out


def save_preview(path: str | Path, ctx: dict) -> None:
    """Write the preview strip PNG (atomically: a temp file renamed into place)."""
    from PIL import Image

    path = Path(path)
    strip = np.concatenate([np.concatenate([p, np.full((p.shape[0], 2, 3), 255, np.uint8)], axis=1)
                            for p in panels(ctx)], axis=1)[:, :-2]
    tmp = path.with_name(f".{path.stem}.tmp.png")
    Image.fromarray(strip).save(tmp)
    tmp.replace(path)
