"""Videos written by difareli.utils.viz: the format choice, a GIF's round trip, an MP4 at odd sizes."""

from __future__ import annotations

import importlib.util

import imageio.v3 as iio
import numpy as np
import pytest

from difareli.utils import viz as vid


def test_video_format_auto_picks_the_encoder_that_exists_and_refuses_the_rest(monkeypatch):
    from difareli.errors import UserError

    monkeypatch.setattr(vid, "has_mp4", lambda: False)
    assert vid.video_format("auto") == "gif" and vid.video_format("gif") == "gif"
    with pytest.raises(UserError, match="video.format=mp4 needs imageio's ffmpeg plugin: pip install imageio-ffmpeg"):
        vid.video_format("mp4", "video.format")
    with pytest.raises(UserError, match="format='avi' is not a video format; use one of auto, mp4, gif"):
        vid.video_format("avi")
    monkeypatch.setattr(vid, "has_mp4", lambda: True)
    assert vid.video_format("auto") == "mp4" and vid.video_format("gif") == "gif"


def test_write_video_gif_round_trips_frames_and_says_its_size(tmp_path):
    frames = np.zeros((4, 8, 10, 3), np.uint8)
    for i in range(4):
        frames[i, :, : 2 + 2 * i] = (255, 0, 0)  # a red bar that grows: four distinct frames
    path = vid.write_video(frames, tmp_path / "v.gif", fps=10)
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (4, 8, 10) and np.abs(back[..., :3].astype(int) - frames).max() <= 3
    assert vid.describe_file(path) == f"{path} ({path.stat().st_size / 1024:.0f} kB)"


@pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is None, reason="MP4 needs imageio-ffmpeg")
def test_write_video_mp4_keeps_odd_sized_frames_at_their_size(tmp_path):
    frames = np.full((5, 9, 11, 3), 128, np.uint8)
    back = iio.imread(vid.write_video(frames, tmp_path / "v.mp4", fps=10), index=None)
    assert back.shape[:3] == (5, 10, 12)  # padded by one edge row and column (H.264 needs even sides), not resized
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]  # written under a scratch name, renamed when whole


@pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is None, reason="MP4 needs imageio-ffmpeg")
def test_write_video_mp4_that_fails_leaves_neither_a_half_file_nor_its_scratch(tmp_path):
    (tmp_path / "v.mp4").write_bytes(b"the video of an earlier run")
    with pytest.raises(Exception):
        vid.write_video(np.zeros((3, 8, 8, 5), np.uint8), tmp_path / "v.mp4")  # five channels: ffmpeg refuses
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]
    assert (tmp_path / "v.mp4").read_bytes() == b"the video of an earlier run"


def test_write_video_names_a_missing_encoder_and_an_unknown_suffix(tmp_path, monkeypatch):
    monkeypatch.setattr(vid, "has_mp4", lambda: False)
    with pytest.raises(RuntimeError, match=r"v\.mp4: MP4 needs imageio's ffmpeg plugin \(pip install imageio-ffmpeg\)"):
        vid.write_video(np.zeros((2, 8, 8, 3), np.uint8), tmp_path / "v.mp4")
    with pytest.raises(ValueError, match=r"v\.avi: a video is \.gif or \.mp4"):
        vid.write_video(np.zeros((2, 8, 8, 3), np.uint8), tmp_path / "v.avi")
    assert list(tmp_path.iterdir()) == []
