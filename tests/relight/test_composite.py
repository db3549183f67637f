"""The whole photo back (difareli.relight.composite): the relit crop warped through the inverse alignment and
blended with a feathered mask; an identity relight gives back the photo."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.checkpoints import zoo
from difareli.estimators.align import crop_to_photo
from difareli.relight.composite import Compositor, feathered, part_mask
from difareli.data.encodings import PART_INDEX
from difareli.lighting import sh

from tests.helpers import HAS_CV2, HAS_ESTIMATORS, compose_train

SIZE = 64


def smooth_photo(h: int = 300, w: int = 400) -> np.ndarray:
    """A photo whose content varies smoothly (a 40 px period): bilinear round trips are accurate on it, a
    half-pixel offset is not (15 levels per pixel at the steepest)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.stack([128 + 100 * np.sin(2 * np.pi * x / 40), 128 + 100 * np.cos(2 * np.pi * y / 40),
                    128 + 60 * np.sin(2 * np.pi * (x + y) / 56)], axis=-1)
    return np.round(img).astype(np.uint8)


def rotated_quad(centre=(210.0, 140.0), side: float = 120.0, angle: float = 0.3) -> np.ndarray:
    """An FFHQ-style quad: top-left, bottom-left, bottom-right, top-right."""
    c, s = np.cos(angle), np.sin(angle)
    x = np.array([c, s]) * side / 2
    y = np.array([-s, c]) * side / 2
    ctr = np.asarray(centre)
    return np.stack([ctr - x - y, ctr - x + y, ctr + x + y, ctr + x - y])


def disk_labels(size: int = SIZE, radius: float = 0.3) -> np.ndarray:
    v, u = np.mgrid[0:size, 0:size] + 0.5
    labels = np.zeros((size, size), np.uint8)
    labels[(u - size / 2) ** 2 + (v - size / 2) ** 2 < (radius * size) ** 2] = PART_INDEX["skin"]
    return labels


def aligned_of(photo: np.ndarray, quad: np.ndarray) -> np.ndarray:
    from difareli.estimators.align import warp_quad

    if not HAS_CV2:
        pytest.skip("needs OpenCV (the photo extras: DIFARELI_PREPROCESS=1 bash scripts/install.sh)")
    return warp_quad(photo, quad, SIZE)


def test_crop_to_photo_inverts_the_alignment_warp():
    """Crop pixel centres go to the quad's points: corners of the crop are the quad's corners."""
    quad = rotated_quad()
    m = crop_to_photo(quad, SIZE)
    # The crop's continuous corners (0, 0), (0, S), (S, S), (S, 0) as pixel indices are -0.5 / S - 0.5.
    corners = np.array([[-0.5, -0.5], [-0.5, SIZE - 0.5], [SIZE - 0.5, SIZE - 0.5], [SIZE - 0.5, -0.5]])
    photo_idx = corners @ m[:, :2].T + m[:, 2]
    np.testing.assert_allclose(photo_idx + 0.5, quad, atol=1e-9)


def test_identity_relight_gives_back_the_photo():
    photo, quad = smooth_photo(), rotated_quad()
    aligned = aligned_of(photo, quad)
    labels = disk_labels()
    # ratio: the relit crop's gain over the input is 1 everywhere, so the photo comes back exactly.
    ratio = Compositor(photo, aligned, labels, quad, mode="ratio")
    assert np.array_equal(ratio(aligned), photo)
    # pixels: the photo outside the mask's support, the crop resampled back inside it.
    comp = Compositor(photo, aligned, labels, quad, mode="pixels")
    out, mask = comp(aligned).astype(int), comp.mask()
    assert np.array_equal(out[mask == 0], photo[mask == 0].astype(int))
    inside = mask > 0.999
    # The disk (radius 0.3 of the crop) less the blur's 3 sigma (0.03 x 64 px), in photo pixels (120 / 64 per px).
    assert inside.sum() > 0.8 * np.pi * ((0.3 * SIZE - 3 * 0.03 * SIZE) * 120 / SIZE) ** 2
    err = np.abs(out[inside] - photo[inside].astype(int))
    assert err.max() <= 4 and err.mean() < 1.0, (err.max(), err.mean())


def test_a_half_pixel_offset_would_show():
    """The accuracy above is not free: the same crop shifted by half a crop pixel misses by far more."""
    photo, quad = smooth_photo(), rotated_quad()
    shifted = quad + 0.5 * (quad[3] - quad[0]) / SIZE
    aligned = aligned_of(photo, shifted)
    comp = Compositor(photo, aligned, disk_labels(), quad, mode="pixels")
    inside = comp.mask() > 0.999
    assert np.abs(comp(aligned).astype(int)[inside] - photo[inside].astype(int)).max() > 8


def test_seam_is_thin_and_the_gain_is_applied():
    photo, quad = smooth_photo(), rotated_quad()
    aligned = aligned_of(photo, quad)
    labels = disk_labels()
    comp = Compositor(photo, aligned, labels, quad, mode="ratio", feather=0.03)
    mask = comp.mask()
    seam = (mask > 0) & (mask < 0.999)
    # The seam's width: the blur kernel's radius (ceil(3 sigma) crop px) on either side of the edge plus the
    # bilinear footprint, in photo pixels (120 / 64 per crop px): a ring about the disk's edge.
    width = (2 * np.ceil(3 * 0.03 * SIZE) + 3) * 120 / SIZE
    ring_area = 2 * np.pi * (0.3 * 120) * width
    assert 0 < seam.sum() < ring_area, (seam.sum(), ring_area)
    half = (aligned // 2).astype(np.uint8)
    out = comp(np.stack([aligned, half])).astype(np.float64)
    assert np.array_equal(out[0], photo)
    inside = mask > 0.999
    expected = photo[inside] * (half.mean() + 255 * comp.eps) / (aligned.mean() + 255 * comp.eps)
    assert abs(out[1][inside].mean() - expected.mean()) < 3.0
    assert np.array_equal(out[1][mask == 0], photo[mask == 0])


def test_mask_parts_and_feathering():
    labels = np.full((SIZE, SIZE), PART_INDEX["background"], np.uint8)
    labels[10:50, 10:50] = PART_INDEX["hair"]
    labels[20:40, 20:40] = PART_INDEX["clothes"]
    m = part_mask(labels)
    assert m[12, 12] and not m[30, 30] and not m[0, 0]  # clothes are not blended by default
    with pytest.raises(ValueError, match="unknown mask parts"):
        part_mask(labels, ["beard"])
    f = feathered(np.ones((SIZE, SIZE), bool), 0.03)[0, 0].numpy()
    assert f[0].max() == 0 and f[:, -1].max() == 0 and f[SIZE // 2, SIZE // 2] == pytest.approx(1.0)


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="photo estimators not installed (DIFARELI_PREPROCESS=1)")
def test_astronaut_at_its_resolution_through_the_real_alignment():
    from skimage import data

    from difareli.relight.photo import prepare_photo

    rgb = data.astronaut()
    prepared = prepare_photo(rgb, ["image"], size=256)
    assert set(prepared.arrays) >= {"image", "masks"} and prepared.quad.shape == (4, 2)
    comp = prepared.compositor(mode="pixels")
    out, mask = comp(prepared.arrays["image"]).astype(int), comp.mask()
    assert out.shape == rgb.shape
    assert np.array_equal(out[mask == 0], rgb[mask == 0].astype(int))
    inside = mask > 0.999
    side = np.hypot(*(prepared.quad[3] - prepared.quad[0]))  # ~180 px: the FFHQ square about the face
    assert (mask > 0.5).sum() > 0.4 * side ** 2 and inside.sum() > 0.25 * side ** 2  # face and hair
    # The 256 px crop of the ~180 px face square resampled back: a resampling error of a few levels.
    assert np.abs(out[inside] - rgb[inside]).mean() < 4.0
    assert np.array_equal(prepared.compositor(mode="ratio")(prepared.arrays["image"]), rgb)


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="photo estimators not installed (DIFARELI_PREPROCESS=1)")
@pytest.mark.skipif("difareli_pp-synth64" not in zoo.available(), reason="no shipped checkpoint")
def test_relight_cli_writes_crop_and_full_photo_with_an_identity_model(tmp_path, monkeypatch):
    """difareli-relight image=...: with a model that returns its input, composite.png is the photo and every
    video frame's composite too; the crop files stay 64 px."""
    from skimage import data

    from difareli.cli.relight import run
    from difareli.relight.relighter import Relighter
    from difareli.relight.relit import Relit

    photo = tmp_path / "astronaut.png"
    iio.imwrite(photo, data.astronaut())
    # Frame i: the input times 1 - 0.2 i (frame 0 and the single relight: the input itself).
    monkeypatch.setattr(Relighter, "relight", lambda self, source, targets: Relit(np.stack(
        [(np.asarray(source.arrays["image"]) * (1 - 0.2 * i)).astype(np.uint8) for i in range(len(targets))]),
        {"decode": 0.0}, source, targets))
    cfg = compose_train(tmp_path, ["checkpoint=difareli_pp-synth64", f"image={photo}", "target.yaw=45",
                                   "video.axis=yaw", "video.frames=3", "progress=false", "runtime.device=cpu"],
                        config_name="relight")
    written = run(cfg)
    assert iio.imread(written["image"]).shape == (64, 64, 3) and iio.imread(written["aligned"]).shape == (64, 64, 3)
    assert np.array_equal(iio.imread(written["composite"]), data.astronaut())
    frames = iio.imread(written["video_composite"]).astype(float)[..., :3]
    assert frames.shape == (3, 512, 512, 3)
    face = np.s_[60:140, 180:270]  # the astronaut's face; the corner is background, outside the mask
    assert frames[0][face].mean() - frames[2][face].mean() > 40
    assert abs(frames[0][:60, :60].mean() - frames[2][:60, :60].mean()) < 2  # GIF palettes aside, unchanged


def test_relight_cli_rejects_a_bad_composite_mode(tmp_path):
    from difareli.relight.request import Request

    cfg = compose_train(tmp_path, ["checkpoint=difareli_pp-synth64", f"image={tmp_path / 'x.png'}", "target.yaw=45",
                                   "composite.mode=blend"], config_name="relight")
    with pytest.raises(ValueError, match="composite.mode='blend': use one of ratio, pixels"):
        Request.from_config(cfg)


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="photo estimators not installed (DIFARELI_PREPROCESS=1)")
@pytest.mark.skipif("difareli_pp-synth64" not in zoo.available(), reason="no shipped checkpoint")
def test_a_photos_rotation_video_lights_its_face_plausibly(tmp_path, monkeypatch):
    """difareli-relight image=... video.axis=yaw: the photo's own light turned behind the head was negative on most
    of its face (a dark mask, issue 61); each frame's light is now made plausible for the face (presets.plausible):
    never negative on its normals, the face's mean irradiance kept."""
    from skimage import data

    from difareli.cli.relight import run
    from difareli.lighting.presets import face_normals
    from difareli.relight.relighter import Relighter
    from difareli.relight.relit import Relit

    photo, seen = tmp_path / "astronaut.png", []
    iio.imwrite(photo, data.astronaut())

    def relight(self, source, targets):
        seen.append((source, targets))
        return Relit(np.stack([np.asarray(source.arrays["image"])] * len(targets)), {"decode": 0.0}, source, targets)

    monkeypatch.setattr(Relighter, "relight", relight)
    run(compose_train(tmp_path, ["checkpoint=difareli_pp-synth64", f"image={photo}", "video.axis=yaw",
                                 "video.frames=6", "progress=false", "runtime.device=cpu"], config_name="relight"))
    source, targets = seen[-1]
    n = face_normals(source.arrays["normal"])
    own = sh.irradiance(np.asarray(source.arrays["light"], np.float64), n).mean()
    e = np.stack([sh.irradiance(np.asarray(x, np.float64), n) for x in targets.lights])
    assert len(e) == 6 and e.min() >= -1e-9  # the raw turn at 180 degrees is negative on most of the face
    assert np.allclose(e.mean(axis=(1, 2)), own, rtol=1e-6)
