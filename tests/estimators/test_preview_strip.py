"""The preview strip written by save_preview equals, pixel for pixel, the strip drawn panel by panel with Pillow
(the implementation before the speed-up, kept here as the reference)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, ImageDraw, ImageFont

from difareli.data.encodings import NUM_MASK_PARTS
from difareli.estimators import preview


def _label_reference(panel, text):
    im = Image.fromarray(panel)
    size = max(8, round(panel.shape[0] / 22))
    font = ImageFont.load_default(size=size)
    draw = ImageDraw.Draw(im)
    lines, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}".strip()
        if cur and draw.textlength(trial, font=font) > panel.shape[1] - 4:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    lines.append(cur)
    band = (size + 2) * len(lines) + 2
    dark = np.asarray(im).copy()
    dark[:band] = (dark[:band] * 0.35).astype(np.uint8)
    im = Image.fromarray(dark)
    draw = ImageDraw.Draw(im)
    for i, line in enumerate(lines):
        draw.text((2, 1 + i * (size + 2)), line, fill=(255, 255, 255), font=font)
    return np.asarray(im)


def _panels_reference(ctx):
    """The panels as computed before the speed-up (mesh and shading panels: preview's own, tested elsewhere)."""
    image = ctx["image"]
    new = preview.panels(ctx)
    out = new[:3]
    out.append((0.35 * image + 0.65 * preview.PALETTE[ctx["masks"]]).astype(np.uint8) if "masks" in ctx else new[3])
    if "shadow_map" in ctx:
        dim = (0.5 * image).astype(np.float64)
        sm = ctx["shadow_map"][..., None]
        cast = ctx.get("cast", ctx["shadow_map"] > 0)[..., None]
        red = np.array([255.0, 40, 40]) * sm + np.array([60.0, 60, 255]) * (cast & (sm == 0))
        out.append(np.clip(np.where(cast, 0.4 * dim + 0.6 * red, dim), 0, 255).astype(np.uint8))
    else:
        out.append(new[4])
    return out


def _strip_reference(ctx):
    return np.concatenate([np.concatenate([p, np.full((p.shape[0], 2, 3), 255, np.uint8)], axis=1)
                           for p in (_label_reference(p, t) for p, t in
                                     zip(_panels_reference(ctx), preview.labels(ctx)))], axis=1)[:, :-2]


def _ctx(size, seed, full=True):
    rng = np.random.default_rng(seed)
    ctx = {"image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8), "notes": []}
    if full:
        face = np.zeros((size, size), bool)
        face[size // 4:3 * size // 4, size // 4:3 * size // 4] = True
        sm = np.where(rng.random((size, size)) < 0.2, rng.random((size, size)), 0.0).astype(np.float32)
        sm[:2] = 1.0  # the brightest red: the clip
        ctx.update(shading=rng.uniform(0, 1.6, (size, size, 3)).astype(np.float32), face_mask=face,
                   masks=rng.integers(0, NUM_MASK_PARTS, (size, size)), shadow_map=sm,
                   cast=(sm > 0.1) | (rng.random((size, size)) < 0.1), light=rng.normal(0, 0.5, (9, 3)))
        if seed == 1:
            del ctx["cast"]  # the panel falls back to the map's own support
    return ctx


@pytest.mark.parametrize("size,seed,full", [(256, 0, True), (64, 1, True), (40, 2, True), (128, 3, False)])
def test_strip_equals_the_panel_by_panel_drawing(size, seed, full, tmp_path):
    ctx = _ctx(size, seed, full)
    want = _strip_reference(ctx)
    np.testing.assert_array_equal(preview.strip(ctx), want)
    preview.save_preview(tmp_path / "p.png", ctx)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "p.png")), want)
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]  # the scratch file renamed, none left


def test_label_wraps_a_long_text_over_several_lines():
    panel = np.full((64, 64, 3), 200, np.uint8)
    one, many = preview.label(panel, "input"), preview.label(panel, "input; light yaw +34 deg, pitch +21 deg")
    dark_rows = lambda p: int((p[:, :, 0] < 200).any(axis=1).sum())  # noqa: E731
    assert dark_rows(many) > 2 * dark_rows(one) and np.array_equal(panel, np.full((64, 64, 3), 200, np.uint8))
    np.testing.assert_array_equal(many, _label_reference(panel, "input; light yaw +34 deg, pitch +21 deg"))
