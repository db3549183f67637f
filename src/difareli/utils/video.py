"""Video files: a frame sequence written as MP4 (H.264 through imageio's ffmpeg plugin) or GIF (a fast palette per
frame), a rotation's frames with their captioned contact sheet, and the line a command ends with for each file.
Every command that writes a video (difareli-relight video.axis=, difareli-video, the demo) writes it here."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from difareli.errors import UserError
from difareli.utils import viz


#: The video formats: ``auto`` is MP4 where imageio's ffmpeg plugin is installed (``pip install imageio-ffmpeg``,
#: the ``video`` extra: a 60-frame rotation is tens of kB), else an optimised GIF.
VIDEO_FORMATS = ("auto", "mp4", "gif")


def has_mp4() -> bool:
    """Whether MP4 can be written here (imageio's ffmpeg plugin is installed)."""
    import importlib.util

    return importlib.util.find_spec("imageio_ffmpeg") is not None


def video_format(fmt: str = "auto", key: str = "format") -> str:
    """``fmt`` resolved to ``mp4`` or ``gif`` (``auto``: MP4 where the encoder exists); a UserError naming ``key``
    for another value, or for ``mp4`` without the encoder."""
    if fmt not in VIDEO_FORMATS:
        raise UserError(f"{key}={fmt!r} is not a video format; use one of {', '.join(VIDEO_FORMATS)}")
    if fmt == "mp4" and not has_mp4():
        raise UserError(f"{key}=mp4 needs imageio's ffmpeg plugin: pip install imageio-ffmpeg (or {key}=gif)")
    return ("mp4" if has_mp4() else "gif") if fmt == "auto" else fmt


def describe_file(path: str | Path) -> str:
    """``path (123 kB)``: a written file and its size, for the line a command ends with."""
    size = Path(path).stat().st_size
    return f"{path} ({size / 2 ** 20:.1f} MB)" if size >= 2 ** 20 else f"{path} ({size / 1024:.0f} kB)"


def write_video(frames: np.ndarray, path: str | Path, fps: int = 20) -> Path:
    """Write frames (N, H, W, 3) uint8 as a GIF (``.gif``: :func:`write_gif`, one fast palette per
    frame) or an MP4 (H.264 through imageio's ffmpeg plugin)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gif":
        write_gif(frames, path, fps)
    else:
        try:
            # H.264 needs even sides: a 64 px crop is, a whole photo may not be (padded by one edge row/column).
            f = np.asarray(frames)
            f = np.pad(f, ((0, 0), (0, f.shape[1] % 2), (0, f.shape[2] % 2), (0, 0)), mode="edge")
            iio.imwrite(path, f, fps=fps, codec="libx264", macro_block_size=1)
        except Exception as e:  # no ffmpeg backend
            raise RuntimeError(f"cannot write {path} ({e}); install imageio[ffmpeg] or use a .gif path") from e
    return path


def write_gif(frames: np.ndarray, path, fps: int = 20):
    """Full-resolution frames (N, H, W, 3) uint8 as a looping GIF, each frame on its own fast-octree palette:
    imageio's default (median cut, per frame) took 6.5 s for 60 frames of 512 px here, this 0.4 s (mean error ~3
    levels, no dithering)."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ims = [Image.fromarray(np.ascontiguousarray(f)).quantize(256, method=Image.Quantize.FASTOCTREE,
                                                            dither=Image.Dither.NONE) for f in frames]
    tmp = path.with_name(f".{path.name}.tmp")
    ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps), loop=0)
    tmp.replace(path)
    return path


def write_rotation(frames: np.ndarray, out_dir: str | Path, name: str, *, axis: str | None = None, fps: int = 20,
                   fmt: str = "auto", zoom: int = 1, columns: int = 10) -> dict[str, Path]:
    """A rotation's frames written: ``<name>.<fmt>`` (upscaled ``zoom`` times, nearest) and its contact sheet
    ``<name>.png`` (``columns`` frames a row, each captioned with its light angle about ``axis``; none without)."""
    out = Path(out_dir)
    big = np.repeat(np.repeat(frames, zoom, axis=1), zoom, axis=2) if zoom > 1 else frames
    sheet = viz.contact_sheet(frames, viz.rotation_captions(axis, len(frames)) if axis else None, columns)
    return {"video": write_video(big, out / f"{name}.{video_format(fmt)}", fps),
            "sheet": viz.save_png(sheet, out / f"{name}.png")}
