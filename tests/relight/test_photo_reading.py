"""read_photo says what an odd input is: an animated GIF is refused (which frame is the face is a
guess), an alpha channel composited over grey is said, a folder or a device is named as what it is."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from difareli.errors import UserError
from difareli.relight.photo import read_photo


def test_animated_gif_is_refused(tmp_path):
    frames = [Image.fromarray(np.full((80, 80, 3), v, np.uint8)) for v in (0, 128, 255)]
    frames[0].save(tmp_path / "a.gif", save_all=True, append_images=frames[1:], duration=100, loop=0)
    with pytest.raises(UserError) as e:
        read_photo(tmp_path / "a.gif")
    assert str(e.value) == (f"image={tmp_path / 'a.gif'} is an animation (3 frames); give one still photo (save the "
                            "frame you want as PNG)")
    frames[0].save(tmp_path / "still.gif")
    assert read_photo(tmp_path / "still.gif").shape == (80, 80, 3)


def test_alpha_channel_is_said(tmp_path):
    rgba = np.zeros((80, 80, 4), np.uint8)
    rgba[..., 0], rgba[20:60, 20:60, 3] = 200, 255
    Image.fromarray(rgba, "RGBA").save(tmp_path / "cut.png")
    with pytest.warns(UserWarning, match=r"image=cut.png: its alpha channel composited over grey \(transparent "):
        rgb = read_photo(tmp_path / "cut.png", name="cut.png")
    assert tuple(rgb[0, 0]) == (128, 128, 128) and tuple(rgb[40, 40]) == (200, 0, 0)


@pytest.mark.parametrize("kind", ["folder", "device", "fifo"])
def test_special_files_are_named_as_what_they_are(tmp_path, kind):
    if kind == "folder":
        path, words = tmp_path / "photos.png", "is a folder"
        path.mkdir()
    elif kind == "device":
        path, words = "/dev/zero", "is a character device"
    else:
        path, words = tmp_path / "pipe.png", "is a FIFO (named pipe)"
        os.mkfifo(path)
    with pytest.raises(UserError) as e:
        read_photo(path)
    assert str(e.value) == f"image={path} {words}, not an image file; give a JPEG/PNG face photo"
