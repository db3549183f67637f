"""The example photos the page offers: public-domain photos that ship inside scikit-image (a dependency), read from
the installed package at run time so that no image file is copied into this one. A request names an example by
its key in :data:`EXAMPLES`, never by a path.
"""

from __future__ import annotations

from functools import cache

import numpy as np

#: name -> (scikit-image loader, what the page says about it). docs/photos.md uses the same two photos.
EXAMPLES: dict[str, tuple[str, str]] = {
    "astronaut": ("astronaut", "Eileen Collins, NASA (512 x 512, colour)"),
    "camera": ("camera", "the cameraman (512 x 512, grey; head turned: the photo check says so)"),
}
THUMB = 96  # px: the page's pick buttons


@cache
def example_rgb(name: str) -> np.ndarray:
    """The example photo ``name`` (a key of :data:`EXAMPLES`) as uint8, as scikit-image ships it."""
    from skimage import data

    return np.asarray(getattr(data, EXAMPLES[name][0])())


@cache
def example_png(name: str) -> bytes:
    """The example photo as PNG bytes: what an upload of it would send."""
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", example_rgb(name), extension=".png")


def thumbnail(rgb: np.ndarray, side: int = THUMB) -> np.ndarray:
    """``rgb`` shrunk so that its longer side is ``side`` px (area average: no aliasing on a 512 px photo)."""
    from skimage.transform import resize

    h, w = rgb.shape[:2]
    scale = side / max(h, w)
    small = resize(rgb, (max(1, round(h * scale)), max(1, round(w * scale))), anti_aliasing=True,
                   preserve_range=True)
    return np.clip(np.rint(small), 0, 255).astype(np.uint8)


def listing() -> list[dict]:
    """What ``GET /api/examples`` answers: each example's name, description, size and thumbnail (data URL)."""
    from difareli.utils.viz import png_data_url

    out = []
    for name, (_, about) in EXAMPLES.items():
        rgb = example_rgb(name)
        out.append({"name": name, "about": about, "width": int(rgb.shape[1]), "height": int(rgb.shape[0]),
                    "thumbnail": png_data_url(thumbnail(rgb))})
    return out
