"""difareli-video: relight a record under a rotating light (yaw, roll, or a rotated HDR environment map), beside
its SynthFaces ground truth, and measure the sequence (the job: :mod:`difareli.jobs.video`)."""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from difareli import errors
from difareli.cli import common
from difareli.data.store import EncodingStore
from difareli.evaluation import video as vid
from difareli.jobs.video import VideoRun, angles, rotate_and_measure
from difareli.lighting import sh
from difareli.relight.request import MAX_FRAMES, Relighting, Rotation, check_store, check_target
from difareli.utils import viz
from difareli.utils.fileio import staged_outputs, write_json_atomic

#: What a video run writes (a rerun replaces all of them, never some).
OUTPUTS = ("relit.gif", "relit.mp4", "relit.png", "contact_sheet.png", "ground_truth.gif", "ground_truth.mp4",
           "side_by_side.gif", "side_by_side.mp4", "frames.csv", "temporal.png", "summary.json")


def validate(cfg: DictConfig) -> tuple[EncodingStore, bool, Relighting]:
    """Config values and input files, checked before any work: how it is relit, the outputs, the rotation, the
    target, the store and its record (as a relight request checks them), the oracles (they need the ground truth).
    The store, open, whether its ground truth is rendered, and how it is relit (a Relighting)."""
    common.check_relighting(cfg)  # the sampler said by key, before Relighting.from_config takes it whole
    how = Relighting.from_config(cfg)
    viz.video_format(cfg.format)
    errors.check_out_dir(cfg.out_dir)
    errors.check_int(cfg.fps, "fps", 1)
    errors.check_choice(cfg.rotation.axis, "rotation.axis", sh.AXES)
    check_target(cfg.target)  # its sun and shadow strength, as a relight request's
    errors.check_int(cfg.rotation.frames, "rotation.frames", 2, maximum=MAX_FRAMES)
    errors.check_int(cfg.sheet_columns, "sheet_columns", 1)
    if cfg.rotation.envmap is not None:
        errors.check_file(cfg.rotation.envmap, "rotation.envmap")
    store = check_store(cfg.store, cfg.get("versions"), record=cfg.record)
    with_gt = errors.check_bool(cfg.ground_truth, "ground_truth") and store.store_meta.get("generator") == "synthfaces"
    for key in ("oracle_shadow", "oracle_maps"):
        if errors.check_bool(cfg.get(key), key) and not with_gt:
            raise errors.UserError(f"{key}=true needs the SynthFaces ground truth (a SynthFaces store and "
                                   f"ground_truth=true); set {key}=false")
    return store, with_gt, how


def run(cfg: DictConfig) -> dict[str, Path]:
    """Relight, render the ground truth, measure and write; returns the paths written."""
    store, with_gt, how = validate(cfg)
    rotation = Rotation(cfg.rotation.axis, int(cfg.rotation.frames), cfg.rotation.envmap, cfg.target.shadow,
                        "peak" if cfg.oracle_maps else cfg.target.sun, cfg.shadow_split)
    record = cfg.record or (store.ids(split="test") or store.ids())[0]
    video = rotate_and_measure(how.make_relighter(), store, record, rotation, ground_truth=with_gt,
                               oracle_shadow=bool(cfg.oracle_shadow), oracle_maps=bool(cfg.oracle_maps))
    sun_note = None if video.notes["maps"] is None else f"target shadow maps {video.notes['maps']}"
    print(f"{video.record}: {video.what}; {video.notes['shadow']}" + (f"; {sun_note}" if sun_note else ""))
    seconds = sum(video.relit.seconds.values())
    print(f"{len(video.relit)} relit frames in {seconds:.1f} s ({len(video.relit) / seconds:.2f} frames/s)")
    summary = {"record": video.record, "rotation": video.what, "shadow": video.notes["shadow"],
               "frames": len(video.relit), "sampler": dict(cfg.sampler), "seconds": round(seconds, 3),
               "oracle_shadow": bool(cfg.oracle_shadow), "oracle_maps": bool(cfg.oracle_maps),
               "target_sun": cfg.target.sun, "target_maps": sun_note}
    written = write(cfg, video, rotation, summary)
    for k, p in written.items():
        print(f"{k}: {p}")
    return written


def write(cfg: DictConfig, video: VideoRun, rotation: Rotation, summary: dict) -> dict[str, Path]:
    """Every output staged and published at the end: a rerun into a finished folder never leaves it mixing runs."""
    ext, fps, relit = viz.video_format(cfg.format), cfg.fps, np.asarray(video.relit)  # auto: mp4 where it can
    with staged_outputs(cfg.out_dir, OUTPUTS, last="summary.json") as out:
        paths = viz.write_rotation(relit, out, "relit", fps=fps, fmt=ext)
        written = {"relit": paths["video"], "frames_sheet": paths["sheet"]}
        step = max(1, len(relit) // cfg.sheet_columns)
        picks = list(range(0, len(relit), step))[:cfg.sheet_columns]
        gt = video.gt
        rows = ([[gt.frames[i] for i in picks]] if gt is not None else []) + [[relit[i] for i in picks]]
        written["sheet"] = viz.save_png(viz.grid(rows), out / "contact_sheet.png")
        if gt is not None:
            written["gt"] = viz.write_video(gt.frames, out / f"ground_truth.{ext}", fps)
            side = np.stack([viz.grid([[g, r]]) for g, r in zip(gt.frames, relit)])
            written["side_by_side"] = viz.write_video(side, out / f"side_by_side.{ext}", fps)
            written["csv"] = vid.write_csv(video.report, out / "frames.csv", angles(rotation))
            written["figure"] = vid.plot_temporal(video.report, out / "temporal.png", f"{video.record}: {video.what}")
            summary.update(video.report.summary(), shadow_rule=(
                f"cast shadow where luminance < {1 - vid.VISIBLE:g} x albedo-proxy x the frame's unshadowed "
                f"irradiance, where its key sun carries > {vid.VISIBLE:g} of the light, against the ground truth's "
                "exact visible shadows (difareli/evaluation/video.py)"))
            print("GT rows: top = ground truth, bottom = relit.  " + ", ".join(
                f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in video.report.summary().items()))
        written["summary"] = write_json_atomic(out / "summary.json", summary)
    return {k: Path(cfg.out_dir) / Path(v).name for k, v in written.items()}


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="video")
@errors.cli_entry("video")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
