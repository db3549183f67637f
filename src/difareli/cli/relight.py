"""difareli-relight: relight a store record or a photo from a checkpoint under a target light, or render a rotation
video.

    difareli-relight checkpoint=difareli_pp-synth64 image=photo.jpg target.yaw=45
    difareli-relight checkpoint=<run>/checkpoints/last.ckpt store=data/synthfaces_64 video.axis=yaw
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from difareli import errors
from difareli.relight import batch, photo, photo_check
from difareli.utils import viz
from difareli.cli import common
from difareli.relight.composite import write_gif
from difareli.relight.relighter import Relighter, Source
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets, rotation_targets, target_lights
from difareli.evaluation.video import rotation_video, write_video


def read_source(cfg: DictConfig, relighter: Relighter, store: EncodingStore | None) -> Source:
    """The source, read and checked once: a store record, or a photo preprocessed in memory by the estimators of
    difareli-preprocess (only the encodings the model reads)."""
    return read_source_and_photo(cfg, relighter, store)[0]


def read_source_and_photo(cfg: DictConfig, relighter: Relighter, store: EncodingStore | None
                          ) -> tuple[Source, photo.PreparedPhoto | None]:
    """:func:`read_source`, and for a photo the :class:`~difareli.relight.photo.PreparedPhoto` (original, quad, masks)
    the composite needs."""
    trained = photo.training_resolution(relighter.config)
    if cfg.image is not None:
        size = photo_size(cfg, trained)
        prepared = photo.prepare_photo(photo.read_photo(cfg.image), relighter.needed_encodings(),
                                       size=size, what=f"image={cfg.image}")
        stages = ", ".join(f"{k} {1000 * v:.0f} ms" for k, v in prepared.meta.get("seconds", {}).items())
        print(f"preprocessed {cfg.image} in {prepared.seconds:.1f} s ({size} px crop of "
              f"{prepared.rgb.shape[1]}x{prepared.rgb.shape[0]}; {stages})")
        source = relighter.source_from_arrays(prepared.arrays, f"image={cfg.image}", key=("image", str(cfg.image)))
        for note in prepared.meta.get("notes", []):
            print(f"image={cfg.image}: {note}")
        result = photo_check.check(prepared, f"image={cfg.image}")
        print(result.line())
        if cfg.strict and not result.ok:
            raise errors.UserError(f"image={cfg.image}: refused (strict=true): {'; '.join(result.problems)}")
        print(f"source light (fitted on the photo): {photo.describe_light(source.arrays['light'])}")
        return source, prepared
    check_store(cfg, relighter, store, trained)
    rid = cfg.record
    if rid is None:
        test = store.ids(split="test")
        rid = (test or store.ids())[0]
        print(f"record=null: relighting {rid}, the first record of the {'test split' if test else 'store'} "
              f"(record=<id> picks another)")
    source = relighter.source(store, rid)
    print(f"source light (record {rid}): {photo.describe_light(source.arrays['light'])}")
    return source, None


def photo_size(cfg: DictConfig, trained: int | None) -> int:
    """The photo's crop size: ``photo_size``, or (null) the checkpoint's training resolution; a size other than
    the training resolution is run, with a warning."""
    if cfg.photo_size is None:
        if trained is None:
            raise errors.UserError(f"checkpoint={cfg.checkpoint} records no training resolution "
                                   "(hyper_parameters.input_dims.resolution); give the crop size: photo_size=<px>")
        return trained
    warn(photo.resolution_warning(cfg.checkpoint, trained, f"photo_size={cfg.photo_size}", int(cfg.photo_size),
                                  f"leave photo_size unset (null) or give photo_size={trained}"))
    return int(cfg.photo_size)


def warn(line: str | None) -> None:
    if line:
        print(f"difareli-relight: {line}", file=sys.stderr)


def check_store(cfg: DictConfig, relighter: Relighter, store: EncodingStore, trained: int | None) -> None:
    """Before reading a record: the store has what a relight reads (else a KeyError naming the fix) and its
    resolution is the checkpoint's (else a warning naming the fix)."""
    made_by = store.store_meta.get("source")
    in_dir = "<the photos>"
    if made_by == "difareli-preprocess":
        try:
            in_dir = json.loads((Path(store.root) / "preprocess_report.json").read_text())["in_dir"]
        except (OSError, ValueError, KeyError, TypeError):
            pass
    size = int(store.dims.get("H", 0))
    redo = f"difareli-preprocess in_dir={in_dir} out_dir=<a new store> checkpoint={cfg.checkpoint}"
    missing = [n for n in relighter.needed_encodings() if not store.available(n)]
    if missing:
        fix = (f"{redo} writes them (at the checkpoint's {trained} px)" if made_by == "difareli-preprocess" else
               "use a store that has them (difareli-synth writes every encoding)")
        raise KeyError(f"relighting with checkpoint={cfg.checkpoint} needs encoding(s) {missing}, which the store at "
                       f"{store.root} does not have; {fix}")
    fix = (f"preprocess at {trained} px: {redo}" if made_by == "difareli-preprocess" else f"use a {trained} px store")
    warn(photo.resolution_warning(cfg.checkpoint, trained, f"the store {store.root}", size, fix))


def print_targets(targets: Targets, first: int = 0) -> None:
    """One line per target light: where it comes from (``photo.describe_light``; see docs/photos.md)."""
    for i, light in enumerate(targets.lights):
        print(f"target light {first + i}: {photo.describe_light(light)}")


class GreyRelighter:
    """A relighter whose relights of a grey source come back grey (:func:`photo.grey_like`): a grey photo has no
    colour, any the model adds is invented."""

    def __init__(self, relighter: Relighter):
        self._relighter = relighter

    def __getattr__(self, name):
        return getattr(self._relighter, name)

    def relight(self, source, targets):
        return photo.grey_like(self._relighter.relight(source, targets))


def composite_frames(cfg: DictConfig, prepared: photo.PreparedPhoto, relit: np.ndarray) -> np.ndarray:
    """Relit crops (N, S, S, 3) back into the whole photo (``cfg.composite``), with the seconds printed."""
    c = cfg.composite
    start = time.perf_counter()
    out = prepared.compositor(c.mode, c.feather, list(c.parts) if c.parts else None)(relit)
    print(f"composited {len(relit)} frame(s) into the {prepared.rgb.shape[1]}x{prepared.rgb.shape[0]} photo in "
          f"{time.perf_counter() - start:.2f} s ({c.mode})")
    return out


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
                                  size=photo_size(cfg, photo.training_resolution(relighter.config)), face=cfg.face,
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
    source, prepared = read_source_and_photo(cfg, relighter, store)
    if photo.is_grey(source.arrays["image"]):
        print(f"{source.what} is grey: its light is grey and its relights are made grey (their luminance)")
        relighter = GreyRelighter(relighter)
    out_dir, written, t = Path(cfg.out_dir), {}, cfg.target
    if any(t[k] is not None for k in ("light", "record", "yaw", "roll", "envmap")):
        other = store.read(t.record, ["light", "shadow"]) if t.record is not None else {}
        light = target_lights(source.arrays["light"], light=t.light, other_light=other.get("light"), yaw=t.yaw,
                              roll=t.roll, envmap=t.envmap)
        shadow = t.shadow if t.shadow is not None else (float(other["shadow"][0]) if "shadow" in other else None)
        targets = Targets.of([light], [shadow], "the target")
        print_targets(targets)
        start = time.perf_counter()
        relit = relighter.relight(source, targets)[0]
        print(f"relit {source.what} in {time.perf_counter() - start:.2f} s ({relighter.describe()})")
        row, names = [source.arrays["image"], relit], ["input", "relit"]
        rid = source.key[1] if store is not None else None
        if t.record is not None and store.meta(t.record).get("subject") == store.meta(rid).get("subject"):
            row.append(np.asarray(store.read(t.record, ["image"])["image"]))  # ground truth: same subject
            names.append("ground truth")
        written["image"] = viz.save_png(relit, out_dir / "relit.png")
        written["comparison"] = viz.save_png(viz.grid([row], col_labels=names), out_dir / "comparison.png")
        if prepared is not None:  # the whole photo back: the aligned crop and the full composite
            full = composite_frames(cfg, prepared, relit[None])[0]
            written["aligned"] = viz.save_png(source.arrays["image"], out_dir / "aligned.png")
            written["composite"] = viz.save_png(full, out_dir / "composite.png")
            written["composite_comparison"] = viz.save_png(
                viz.grid([[prepared.rgb, full]], col_labels=["photo", "relit photo"]),
                out_dir / "composite_comparison.png")
    if cfg.video.axis is not None:
        targets, why = rotation_targets(source.arrays, cfg.video.axis, cfg.video.frames, store=store,
                                        given=t.shadow)
        print(f"video shadow strength: {why}")
        quarter = len(targets) // 4
        print(f"video: frame 0 light {photo.describe_light(targets.lights[0])}"
              + (f"; frame {quarter}: {photo.describe_light(targets.lights[quarter])}" if quarter else ""))
        video = rotation_video(relighter, source, targets, out_dir, f"rotation_{cfg.video.axis}", fps=cfg.video.fps,
                               fmt=cfg.video.format)
        print(f"{len(video.frames)} frames in {video.seconds:.1f} s ({video.seconds / len(video.frames):.2f} s/frame, "
              f"{relighter.describe()})")
        # rotation_video's sheet has no captions: written again with each frame's light angle.
        viz.save_png(viz.contact_sheet(video.frames, viz.rotation_captions(cfg.video.axis, len(video.frames))),
                     video.paths["sheet"])
        written.update(video.paths)
        if prepared is not None:  # every frame back into the whole photo
            frames = composite_frames(cfg, prepared, video.frames)
            name = f"rotation_{cfg.video.axis}_composite"
            path = out_dir / f"{name}.{cfg.video.format}"
            written["video_composite"] = (write_gif(frames, path, cfg.video.fps) if cfg.video.format == "gif"
                                          else write_video(frames, path, cfg.video.fps))
    for k, p in written.items():
        print(f"{k}: {p}")
    return written


def validate(cfg: DictConfig) -> None:
    """Config values and input files, checked before any work."""
    common.validate_relight(cfg, frames=("video.frames", cfg.video.frames, 1), fps=("video.fps", cfg.video.fps),
                            envmap=("target.envmap", cfg.target.envmap))
    if (cfg.image is None) == (cfg.store is None):
        raise errors.UserError("give the source as either store=<encodings store> (and record=) or image=<photo>; "
                               f"got store={cfg.store} image={cfg.image}")
    if cfg.target.record is not None and cfg.store is None:
        raise errors.UserError(f"target.record={cfg.target.record} names a store record: give store= too")
    if all(cfg.target[k] is None for k in ("light", "record", "yaw", "roll", "envmap")) and cfg.video.axis is None:
        raise errors.UserError("nothing to do: give a target (target.light|record|yaw|roll|envmap) or "
                               "video.axis=yaw|roll")
    if cfg.photo_size is not None:
        errors.check_int(cfg.photo_size, "photo_size", 16)
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
