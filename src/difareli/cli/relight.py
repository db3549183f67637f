"""difareli-relight: relight a store record or a photo from a checkpoint under a target light, or render a rotation
video.

    difareli-relight checkpoint=difareli_pp-synth64 image=photo.jpg target.yaw=45
    difareli-relight checkpoint=<run>/checkpoints/last.ckpt store=data/synthfaces_64 video.axis=yaw
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from difareli import errors
from difareli.cli import common
from difareli.relight import batch
from difareli.relight.request import Answer, Request, respond
from difareli.utils import viz


#: The least height of a face in comparison.png (a 64 px crop shown 4x): its shading and shadows readable.
COMPARISON_PX = 256


def run(cfg: DictConfig) -> dict[str, Path]:
    """Relight as configured; returns the paths written."""
    request = Request.from_config(cfg)  # every value of the request checked, before any work
    answer = respond(request.how.make_relighter(), request, say)  # its lines said as they arise
    return write(answer, request)


def say(line: str) -> None:
    """A line of the answer, printed as it arises: a warning on stderr, the rest on stdout."""
    if line.startswith("warning:"):
        print(f"difareli-relight: {line}", file=sys.stderr)
    else:
        print(line)


def write(result: Answer, request: Request) -> dict[str, Path]:
    """The answer's images written into the request's ``out_dir`` (its lines were said as they arose): relit.png
    and a labelled comparison (with the ground truth where the target record is the same subject); a photo's
    aligned crop and whole relit photo; the rotation video, its captioned contact sheet and, for a photo, the
    video composited. A batch of photos (already written as it went): its counts said (:func:`write_counts`)."""
    if result.counts is not None:
        return write_counts(result.counts, request)
    out_dir, written, source = Path(request.out_dir), {}, result.source
    if result.relit is not None:
        row, names = [source.arrays["image"], result.relit[0]], ["input", "relit"]
        if result.truth is not None:
            row, names = [*row, result.truth], [*names, "ground truth"]
        written["image"] = viz.save_png(result.relit[0], out_dir / "relit.png")
        written["comparison"] = viz.save_png(viz.grid([[viz.enlarge(im, COMPARISON_PX) for im in row]],
                                                      col_labels=names), out_dir / "comparison.png")
        if result.whole is not None:
            written["aligned"] = viz.save_png(source.arrays["image"], out_dir / "aligned.png")
            written["composite"] = viz.save_png(result.whole, out_dir / "composite.png")
            written["composite_comparison"] = viz.save_png(
                viz.grid([[source.photo.rgb, result.whole]], col_labels=["photo", "relit photo"]),
                out_dir / "composite_comparison.png")
    if result.video is not None:
        axis, fmt, fps = request.video_axis, request.video_format, request.video_fps
        rotation = viz.write_rotation(result.video.images, out_dir, f"rotation_{axis}", axis=axis, fps=fps, fmt=fmt)
        written["video"], written["sheet"] = rotation["video"], rotation["sheet"]
        if result.whole_video is not None:
            written["video_composite"] = viz.write_video(result.whole_video,
                                                         out_dir / f"rotation_{axis}_composite.{fmt}", fps)
    for k, p in written.items():
        print(f"{k}: {viz.describe_file(p)}")
    return written


def write_counts(counts: dict[str, int], request: Request) -> dict[str, Path]:
    """A batch's outcome (``image=<folder or glob>`` or ``face=all|<index>``; each photo's files and CSV row were
    written as it went): its counts, and a UserError (non-zero exit) saying how many were skipped."""
    csv = Path(request.out_dir) / batch.CSV_NAME
    print(f"{counts['done']} photo(s) relit, {counts['resumed']} already done, {counts['skipped']} skipped; "
          f"results and {csv.name} in {request.out_dir}")
    if counts["skipped"]:
        total = sum(counts.values())
        raise errors.UserError(f"image={request.image}: {counts['skipped']} of {total} photo(s) skipped "
                               f"(one line each above, and in {csv}); fix or remove them")
    return {"csv": csv}


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="relight")
@errors.cli_entry("relight")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
