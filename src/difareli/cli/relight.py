"""difareli-relight: relight a store record or a photo from a checkpoint under a target light, or render a rotation
video.

    difareli-relight checkpoint=difareli_pp-synth64 image=photo.jpg target.yaw=45
    difareli-relight checkpoint=<run>/checkpoints/last.ckpt store=data/synthfaces_64 video.axis=yaw
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from difareli import errors, photo, viz, zoo
from difareli.cli import common
from difareli.relighting import OnePassRelightable, Relighter, write_video
from difareli.store import EncodingStore
from difareli.targets import rotation_lights, target_lights, video_shadow


def run(cfg: DictConfig) -> dict[str, Path]:
    """Relight as configured; returns the paths written."""
    validate(cfg)
    store = EncodingStore.open(cfg.store).use_versions(cfg.get("versions")) if cfg.store is not None else None
    relighter = Relighter(cfg.checkpoint, cfg.sampler, runtime=cfg.runtime, mean_matching=cfg.mean_matching,
                          batch_size=cfg.batch_size, progress=cfg.progress)
    if cfg.image is not None:  # a photo: the estimators of difareli-preprocess, in memory, for what the model reads
        start = time.perf_counter()
        src = photo.preprocess_photo(photo.read_photo(cfg.image), relighter.needed_encodings(),
                                     size=int(cfg.photo_size), what=f"image={cfg.image}")
        print(f"preprocessed {cfg.image} in {time.perf_counter() - start:.1f} s ({cfg.photo_size} px)")
        rid = Path(str(cfg.image)).stem

        def relight_to(lights, shadows):
            return relighter.relight_arrays(src, lights, shadows, key=("image", str(cfg.image)),
                                            what=f"image={cfg.image}")
    else:
        rid = cfg.record or (store.ids(split="test") or store.ids())[0]
        src = relighter.read(store, rid)  # checked finite by the relighting core

        def relight_to(lights, shadows):
            return relighter.relight_record(store, rid, lights, shadows)
    out_dir, written = Path(cfg.out_dir), {}
    t = cfg.target
    want_image = any(t[k] is not None for k in ("light", "record", "yaw", "roll", "envmap"))
    if not want_image and cfg.video.axis is None:
        raise ValueError("nothing to do: give a target (target.light|record|yaw|roll|envmap) or video.axis=yaw|roll")
    if want_image:
        other = store.read(t.record, ["light", "shadow"]) if t.record is not None else {}
        light = target_lights(src["light"], light=t.light, other_light=other.get("light"), yaw=t.yaw,
                              roll=t.roll, envmap=t.envmap)
        shadow = t.shadow if t.shadow is not None else (float(other["shadow"][0]) if "shadow" in other else None)
        start = time.perf_counter()
        relit = relight_to([light], [shadow])[0]
        how = "one pass" if isinstance(relighter.model, OnePassRelightable) else \
            f"{cfg.sampler.name}, {cfg.sampler.steps} steps"
        print(f"relit {rid} in {time.perf_counter() - start:.2f} s ({how}, "
              f"{relighter.runtime.precision}{', compiled' if relighter.runtime.compile else ''})")
        row = [src["image"], relit]
        if t.record is not None and store is not None and store.meta(t.record).get("subject") == store.meta(rid).get("subject"):
            row.append(np.asarray(store.read(t.record, ["image"])["image"]))  # ground truth: same subject
        written["image"] = viz.save_png(relit, out_dir / "relit.png")
        written["comparison"] = viz.save_png(viz.grid([row]), out_dir / "comparison.png")
    if cfg.video.axis is not None:
        lights = rotation_lights(src["light"], cfg.video.axis, cfg.video.frames)
        start = time.perf_counter()
        own = float(np.asarray(src["shadow"]).reshape(-1)[0]) if "shadow" in src else None
        if store is not None and "shadow" in src:  # the stated policy (targets.video_shadow), printed
            c, why = video_shadow(store, own, t.shadow)
        else:
            c = t.shadow if t.shadow is not None else own
            why = f"target c' = {c} ({'given' if t.shadow is not None else 'the input own c'})"
        print(f"video shadow strength: {why}")
        frames = relight_to(lights, [c] * len(lights))
        print(f"{len(frames)} frames in {time.perf_counter() - start:.1f} s")
        written["video"] = write_video(frames, out_dir / f"rotation_{cfg.video.axis}.{cfg.video.format}", cfg.video.fps)
        sheet = [list(frames[i:i + 10]) for i in range(0, len(frames), 10)]
        written["sheet"] = viz.save_png(viz.grid(sheet), out_dir / f"rotation_{cfg.video.axis}.png")
    for k, p in written.items():
        print(f"{k}: {p}")
    return written


def validate(cfg: DictConfig) -> None:
    """Config values and input files, checked before any work (issue 15)."""
    errors.check_sampler(cfg.sampler)
    zoo.resolve(cfg.checkpoint, "checkpoint")
    errors.check_int(cfg.video.frames, "video.frames", 1)
    errors.check_int(cfg.video.fps, "video.fps", 1)
    errors.check_int(cfg.batch_size, "batch_size", 1)
    errors.check_out_dir(cfg.out_dir)
    if (cfg.image is None) == (cfg.store is None):
        raise errors.UserError("give the source as either store=<encodings store> (and record=) or image=<photo>; "
                               f"got store={cfg.store} image={cfg.image}")
    if cfg.target.record is not None and cfg.store is None:
        raise errors.UserError(f"target.record={cfg.target.record} names a store record: give store= too")
    errors.check_int(cfg.photo_size, "photo_size", 16)
    for key in ("yaw", "roll", "shadow"):
        errors.check_number(cfg.target[key], f"target.{key}")
    for key in ("light", "envmap"):
        if cfg.target[key] is not None:
            errors.check_file(cfg.target[key], f"target.{key}")


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="relight")
@errors.cli_entry("relight")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
