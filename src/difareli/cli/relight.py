"""difareli-relight: relight a store record or a photo from a checkpoint under a target light, or render a rotation
video.

    difareli-relight checkpoint=difareli_pp-synth64 image=photo.jpg target.yaw=45
    difareli-relight checkpoint=<run>/checkpoints/last.ckpt store=data/synthfaces_64 video.axis=yaw
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from difareli import errors
from difareli.lighting import sh
from difareli.relight import batch, photo
from difareli.render import sun_fit
from difareli.utils import viz
from difareli.cli import common
from difareli.relight.relighter import Relighter, Source
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets, rotation_targets, target_lights
from difareli.evaluation.video import describe_file, rotation_video, video_format, write_video


def read_source(cfg: DictConfig, relighter: Relighter, store: EncodingStore | None) -> Source:
    """The source, read and checked once by the relighter: a photo preprocessed in memory (``image=``) or a store
    record (``record=``, null: the first test record); its notes printed."""
    if cfg.image is not None:
        source = relighter.photo_source(cfg.image, size=cfg.photo_size, strict=bool(cfg.strict))
    else:
        source = relighter.source(store, cfg.record)
    for line in source.notes:
        if line.startswith("warning:"):
            print(f"difareli-relight: {line}", file=sys.stderr)
        else:
            print(line)
    return source


def run_photos(cfg: DictConfig, relighter: Relighter, paths: list[Path]) -> dict[str, Path]:
    """``image=<folder or glob>`` or ``face=all|<index>``: every photo (and chosen face) under the one target, by
    :func:`difareli.relight.batch.relight_photos`; a UserError (non-zero exit) saying how many were skipped."""
    t = cfg.target
    if cfg.video.axis is not None or t.record is not None:
        raise errors.UserError(f"image={cfg.image} face={cfg.face}: a folder or several faces take a target light "
                               "(target.light|yaw|roll|envmap), not video.axis or target.record")

    def target(light):
        return Targets.of([target_lights(light, light=t.light, yaw=t.yaw, roll=t.roll, envmap=t.envmap)],
                          [t.shadow], "the target")

    counts = batch.relight_photos(paths, cfg.out_dir, progress=cfg.progress, relighter=relighter, target=target,
                                  size=cfg.photo_size, face=cfg.face,
                                  composite=cfg.composite, strict=bool(cfg.strict))
    print(f"{counts['done']} photo(s) relit, {counts['resumed']} already done, {counts['skipped']} skipped; "
          f"results and {batch.CSV_NAME} in {cfg.out_dir}")
    if counts["skipped"]:
        raise errors.UserError(f"image={cfg.image}: {counts['skipped']} of {len(paths)} photo(s) skipped (one line "
                               f"each above, and in {Path(cfg.out_dir) / batch.CSV_NAME}); fix or remove them")
    return {"csv": Path(cfg.out_dir) / batch.CSV_NAME}


def run(cfg: DictConfig) -> dict[str, Path]:
    """Relight as configured; returns the paths written."""
    validate(cfg)
    store = EncodingStore.open(cfg.store).use_versions(cfg.get("versions")) if cfg.store is not None else None
    relighter = Relighter(cfg.checkpoint, cfg.sampler, runtime=cfg.runtime, mean_matching=cfg.mean_matching,
                          batch_size=cfg.batch_size, progress=cfg.progress)
    if cfg.image is not None:
        paths = batch.photo_paths(cfg.image)
        if paths is not None or str(cfg.face).lower() != "largest":
            return run_photos(cfg, relighter, paths or [Path(str(cfg.image))])
    source = read_source(cfg, relighter, store)
    out_dir, written, t, c = Path(cfg.out_dir), {}, cfg.target, cfg.composite
    parts = list(c.parts) if c.parts else None
    if any(t[k] is not None for k in ("light", "record", "yaw", "roll", "envmap")):
        other = store.read(t.record, ["light", "shadow"]) if t.record is not None else {}
        light = target_lights(source.arrays["light"], light=t.light, other_light=other.get("light"), yaw=t.yaw,
                              roll=t.roll, envmap=t.envmap)
        shadow = t.shadow if t.shadow is not None else (float(other["shadow"][0]) if "shadow" in other else None)
        # The key sun of the image whose light it is: another record's, or the source's own turned with its light.
        finds = t.sun == "shadows" and (t.record is not None or t.yaw is not None or t.roll is not None)
        found = None if not finds else relighter.key_sun(relighter.source(store, t.record)) \
            if t.record is not None else relighter.key_sun(source)
        turn = sh.rotation_yaw(t.yaw) if t.yaw is not None else sh.rotation_roll(t.roll) if t.roll is not None \
            else np.eye(3)
        sun = None if found is None else turn @ found.direction
        relit = relighter.relight(source, Targets.of([light], [shadow], "the target", suns=[sun]))
        print(f"target light 0: {photo.describe_light(light)}")
        if "shadow_map" in relighter.model_inputs:
            print(f"target 0 shadow map: {sun_fit.describe(found)}")
        print(f"relit {source.what} ({relit.describe_seconds()}; {relighter.describe()})")
        row, names = [source.arrays["image"], relit[0]], ["input", "relit"]
        rid = source.key[1] if store is not None else None
        if t.record is not None and store.meta(t.record).get("subject") == store.meta(rid).get("subject"):
            row.append(np.asarray(store.read(t.record, ["image"])["image"]))  # ground truth: same subject
            names.append("ground truth")
        written["image"] = viz.save_png(relit[0], out_dir / "relit.png")
        written["comparison"] = viz.save_png(viz.grid([row], col_labels=names), out_dir / "comparison.png")
        if source.photo is not None:  # the whole photo back: the aligned crop and the full composite
            full = relit.composite(c.mode, c.feather, parts)[0]
            written["aligned"] = viz.save_png(source.arrays["image"], out_dir / "aligned.png")
            written["composite"] = viz.save_png(full, out_dir / "composite.png")
            written["composite_comparison"] = viz.save_png(
                viz.grid([[source.photo.rgb, full]], col_labels=["photo", "relit photo"]),
                out_dir / "composite_comparison.png")
            print(f"composited into the {full.shape[1]}x{full.shape[0]} photo in {relit.seconds['composite']:.2f} s "
                  f"({c.mode})")
    if cfg.video.axis is not None:
        found = relighter.key_sun(source) if t.sun == "shadows" else None
        targets, why = rotation_targets(source.arrays, cfg.video.axis, cfg.video.frames, store=store,
                                        given=t.shadow, sun=None if found is None else found.direction)
        print(f"video shadow strength: {why}")
        if "shadow_map" in relighter.model_inputs:
            print(f"video shadow maps: {sun_fit.describe(found)}, turned with the light")
        quarter = len(targets) // 4
        print(f"video: frame 0 light {photo.describe_light(targets.lights[0])}"
              + (f"; frame {quarter}: {photo.describe_light(targets.lights[quarter])}" if quarter else ""))
        fmt = video_format(cfg.video.format, "video.format")
        video = rotation_video(relighter, source, targets, out_dir, f"rotation_{cfg.video.axis}", fps=cfg.video.fps,
                               fmt=fmt)
        print(f"{len(video.frames)} frames in {video.seconds:.1f} s ({video.seconds / len(video.frames):.2f} s/frame, "
              f"{relighter.describe()})")
        # rotation_video's sheet has no captions: written again with each frame's light angle.
        viz.save_png(viz.contact_sheet(video.frames, viz.rotation_captions(cfg.video.axis, len(video.frames))),
                     video.paths["sheet"])
        written.update(video.paths)
        if source.photo is not None:  # every frame back into the whole photo
            frames = video.relit.composite(c.mode, c.feather, parts)
            written["video_composite"] = write_video(
                frames, out_dir / f"rotation_{cfg.video.axis}_composite.{fmt}", cfg.video.fps)
    for k, p in written.items():
        print(f"{k}: {describe_file(p)}")
    return written


def validate(cfg: DictConfig) -> None:
    """Config values and input files, checked before any work."""
    common.validate_relight(cfg, frames=("video.frames", cfg.video.frames, 1), fps=("video.fps", cfg.video.fps),
                            envmap=("target.envmap", cfg.target.envmap))
    video_format(cfg.video.format, "video.format")
    if (cfg.image is None) == (cfg.store is None):
        raise errors.UserError("give the source as either store=<encodings store> (and record=) or image=<photo>; "
                               f"got store={cfg.store} image={cfg.image}")
    if cfg.target.record is not None and cfg.store is None:
        raise errors.UserError(f"target.record={cfg.target.record} names a store record: give store= too")
    if all(cfg.target[k] is None for k in ("light", "record", "yaw", "roll", "envmap")) and cfg.video.axis is None:
        raise errors.UserError("nothing to do: give a target (target.light|record|yaw|roll|envmap) or "
                               "video.axis=yaw|roll")
    if cfg.image is not None:
        from difareli.relight.composite import MODES, part_mask

        c = cfg.composite
        if c.mode not in MODES:
            raise errors.UserError(f"composite.mode={c.mode}: not a composite mode; use one of {', '.join(MODES)}")
        if errors.check_number(c.feather, "composite.feather", allow_none=False) < 0:
            raise errors.UserError(f"composite.feather={c.feather}: must be >= 0 (a fraction of the crop size)")
        try:
            part_mask(np.zeros((1, 1), np.uint8), list(c.parts or []))
        except ValueError as e:
            raise errors.UserError(f"composite.parts: {e}") from None
    for key in ("yaw", "roll"):
        errors.check_number(cfg.target[key], f"target.{key}")
    if cfg.target.light is not None:
        errors.check_file(cfg.target.light, "target.light")


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="relight")
@errors.cli_entry("relight")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
