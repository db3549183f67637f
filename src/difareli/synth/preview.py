"""A PNG contact sheet of a SynthFaces store: per subject, three rows over its lights.

Row 1: the image; row 2: the shading reference R clipped to [0, 1] (it is unclipped in the store);
row 3: the shadow map (binary cast shadow times normalised c) in red over a dimmed grey copy of the image,
so one can check that shadows fall where the sun says. Cells are upscaled with nearest-neighbour.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from difareli.data.store import EncodingStore
from difareli.data import protocols as sp
from difareli.utils.viz import grid, save_png


def _upscale(img: np.ndarray, cell: int) -> np.ndarray:
    f = max(1, -(-cell // img.shape[0]))
    return np.repeat(np.repeat(img, f, axis=0), f, axis=1)


def shadow_overlay(image: np.ndarray, shadow_map: np.ndarray) -> np.ndarray:
    """uint8 HxWx3: the image in dim grey, shadow-map strength in red."""
    grey = image.astype(np.float32).mean(-1, keepdims=True) * 0.5
    out = np.repeat(grey, 3, axis=-1)
    m = np.asarray(shadow_map, np.float32)
    out[..., 0] = np.where(m > 0, 80 + 175 * m, out[..., 0])
    out[..., 1:] = np.where(m[..., None] > 0, out[..., 1:] * 0.3, out[..., 1:])
    return np.clip(out, 0, 255).astype(np.uint8)


def subject_rows(store: EncodingStore, subject: int, lights: int, cell: int) -> list[list[np.ndarray]]:
    """The three preview rows of one subject (missing records are left blank)."""
    rows: list[list[np.ndarray]] = [[], [], []]
    for j in range(lights):
        rid = sp.record_id(subject, j)
        if not store.has(rid):
            continue
        r = store.read(rid, ["image", "shading", "shadow_map"])
        image = np.asarray(r["image"])
        shading = np.round(np.clip(np.asarray(r["shading"]), 0, 1) * 255).astype(np.uint8)
        for row, cellimg in zip(rows, (image, shading, shadow_overlay(image, r["shadow_map"]))):
            row.append(_upscale(cellimg, cell))
    return rows


def write_preview(store_root: str | Path, path: str | Path | None = None, *, subjects: int = 4,
                  lights: int = 4, cell: int = 128) -> Path | None:
    """Write the contact sheet (default ``<store_root>/preview.png``); None if the store has no records.

    Subjects are taken from the test split first (``splits.json`` if present), then in index order.
    """
    store = EncodingStore.open(store_root)
    names = sorted({store.meta(rid)["subject"] for rid in store.ids()[: 64 * max(1, lights)]})
    if not names:
        return None
    order = sorted(int(n[1:]) for n in names)
    test = [int(n[1:]) for n in _test_subjects(Path(store_root))]
    chosen = [s for s in test if f"s{s:05d}" in names][:subjects]
    chosen += [s for s in order if s not in chosen][: subjects - len(chosen)]
    rows = []
    for s in chosen:
        rows.extend(r for r in subject_rows(store, s, lights, cell) if r)
    if not rows:
        return None
    return save_png(grid(rows, pad=2), path or Path(store_root) / "preview.png")


def _test_subjects(root: Path) -> list[str]:
    f = root / sp.SPLITS_FILE
    if not f.is_file():
        return []
    return json.loads(f.read_text())["splits"].get("test", [])
