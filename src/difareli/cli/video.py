"""difareli-video: relight a record under a rotating light (yaw, roll, or a rotated HDR environment map), beside
its SynthFaces ground truth, and measure the sequence (difareli.evaluation.video)."""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from difareli import errors
from difareli.lighting import sh
from difareli.render import sun_fit
from difareli.utils import viz
from difareli.evaluation import video as vid
from difareli.cli import common
from difareli.relight.relighter import Relighter
from difareli.relight.request import MAX_FRAMES, check_store
from difareli.data.encodings import shadow_logit
from difareli.data.store import EncodingStore
from difareli.synth import rotation
from difareli.utils.fileio import staged_outputs, write_json_atomic
from difareli.relight.targets import Targets, load_envmap, video_shadow

_MEASURE = ("image", "light", "normal", "face_mask", "shadow_map", "shadow")


def _ground_truth(cfg: DictConfig, store: EncodingStore, rid: str, rots: np.ndarray, angles: np.ndarray,
                  env_light: np.ndarray | None):
    if env_light is not None:
        return rotation.ground_truth_lights(store, rid, sh.rotate(env_light, rots))
    return rotation.ground_truth_rotation(store, rid, cfg.rotation.axis, len(angles))


def run(cfg: DictConfig) -> dict[str, Path]:
    """Relight, render the ground truth, measure and write; returns the paths written."""
    store = validate(cfg)
    rid = cfg.record or (store.ids(split="test") or store.ids())[0]
    synth = store.store_meta.get("generator") == "synthfaces"
    with_gt = bool(cfg.ground_truth) and synth
    for key in ("oracle_shadow", "oracle_maps"):
        if cfg.get(key) and not with_gt:
            raise errors.UserError(f"{key}=true needs the SynthFaces ground truth (a SynthFaces store and "
                                   f"ground_truth=true); set {key}=false")
    relighter = Relighter(cfg.checkpoint, cfg.sampler, runtime=cfg.runtime, mean_matching=cfg.mean_matching,
                          batch_size=cfg.batch_size, progress=cfg.progress)
    source = relighter.source(store, rid)
    arrays = {**{k: np.asarray(v) for k, v in store.read(rid, [n for n in _MEASURE if store.available(n)]).items()},
              **source.arrays}
    angles, rots = sh.rotation_frames(cfg.rotation.axis, cfg.rotation.frames)
    env_light = None
    if cfg.rotation.envmap is not None:
        env_light = errors.check_light(sh.project_envmap(load_envmap(cfg.rotation.envmap)),
                                       f"the SH projection of {cfg.rotation.envmap}")
    lights = sh.rotate(env_light if env_light is not None else source.arrays["light"], rots)
    what = ((f"environment map {cfg.rotation.envmap}" if env_light is not None else "the input's light")
            + f" rotated about {cfg.rotation.axis}, {len(angles)} frames")

    # The source light's key sun, turned with it: where each frame's own map is marched (not for an environment
    # map, whose SH is no photo's fit, nor for the oracle's maps).
    found = None
    if cfg.target.sun == "shadows" and env_light is None and not cfg.oracle_maps:
        found = relighter.key_sun(source)
    suns = None if found is None else list(rots @ found.direction)
    sun_note = (f"target shadow maps {sun_fit.describe(found)}"
                if "shadow_map" in relighter.model_inputs and not cfg.oracle_maps else None)

    gt = _ground_truth(cfg, store, rid, rots, angles, env_light) if with_gt else None
    record_c = shadow_logit(arrays)
    if cfg.oracle_shadow:
        shadows = [float(c) for c in gt.targets["shadow"][:, 0]]
        c_note = "target c' per frame = the ground truth's exact c (oracle_shadow=true)"
    else:
        c, c_note = video_shadow(store, record_c, cfg.target.shadow, cfg.shadow_split)
        shadows = [c] * len(angles)
    print(f"{rid}: {what}; {c_note}" + (f"; {sun_note}" if sun_note else ""))

    ext = viz.video_format(cfg.format)  # auto: mp4 where the encoder exists, else gif
    # Every output is staged and published at the end: a rerun into a finished folder never leaves it mixing runs.
    with staged_outputs(cfg.out_dir, OUTPUTS, last="summary.json") as out:
        if cfg.oracle_maps:  # each frame's exact cast-shadow map (the ground truth's), not the one the march makes
            what += "; target shadow maps: the ground truth's exact ones (oracle_maps=true)"
        targets = Targets.of(lights, shadows, what, maps=gt.targets["shadow_map"] if cfg.oracle_maps else None,
                             suns=suns)
        video = vid.rotation_video(relighter, source, targets, out, "relit", fps=cfg.fps, fmt=ext)
        relit, seconds = video.frames, video.seconds
        print(f"{len(relit)} relit frames in {seconds:.1f} s ({len(relit) / seconds:.2f} frames/s)")
        written = {"relit": video.paths["video"], "frames_sheet": video.paths["sheet"]}
        step = max(1, len(relit) // cfg.sheet_columns)
        picks = list(range(0, len(relit), step))[:cfg.sheet_columns]
        rows = ([[gt.frames[i] for i in picks]] if gt is not None else []) + [[relit[i] for i in picks]]
        written["sheet"] = viz.save_png(viz.grid(rows), out / "contact_sheet.png")
        summary = {"record": rid, "rotation": what, "shadow": c_note, "frames": len(relit),
                   "sampler": dict(cfg.sampler), "seconds": round(seconds, 3), "oracle_shadow": bool(cfg.oracle_shadow),
                   "oracle_maps": bool(cfg.oracle_maps), "target_sun": cfg.target.sun, "target_maps": sun_note}
        if gt is not None:
            written["gt"] = viz.write_video(gt.frames, out / f"ground_truth.{ext}", cfg.fps)
            side = np.stack([viz.grid([[g, r]]) for g, r in zip(gt.frames, relit)])
            written["side_by_side"] = viz.write_video(side, out / f"side_by_side.{ext}", cfg.fps)
            # The maps the frames were given (made by the march, or the oracle's), to measure how far they are followed.
            given = (np.stack([a["shadow_map"] for a in targets.retarget(source.arrays, ["shadow_map"])])
                     if "shadow_map" in relighter.model_inputs else None)
            # The rule measures (it is no model input): the exact suns of the input and of each frame; its floor,
            # the same frames rendered without cast shadows.
            report = vid.measure(relit, gt.frames, arrays, gt.suns(), gt.cast(), maps=given,
                                 input_light=rotation.source_suns(store, rid),
                                 shadowless=gt.without_shadows().frames)
            written["csv"] = vid.write_csv(report, out / "frames.csv", angles)
            written["figure"] = vid.plot_temporal(report, out / "temporal.png", f"{rid}: {what}")
            summary.update(report.summary(), shadow_rule=(
                f"cast shadow where luminance < {1 - vid.VISIBLE:g} x albedo-proxy x the frame's unshadowed "
                f"irradiance, where its key sun carries > {vid.VISIBLE:g} of the light, against the ground truth's "
                "exact visible shadows (difareli/evaluation/video.py)"))
            print("GT rows: top = ground truth, bottom = relit.  " + ", ".join(
                f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in report.summary().items()))
        written["summary"] = write_json_atomic(out / "summary.json", summary)
    written = {k: Path(cfg.out_dir) / Path(v).name for k, v in written.items()}
    for k, p in written.items():
        print(f"{k}: {p}")
    return written


#: What a video run writes (a rerun replaces all of them, never some).
OUTPUTS = ("relit.gif", "relit.mp4", "relit.png", "contact_sheet.png", "ground_truth.gif", "ground_truth.mp4",
           "side_by_side.gif", "side_by_side.mp4", "frames.csv", "temporal.png", "summary.json")


def validate(cfg: DictConfig) -> EncodingStore:
    """Config values and input files, checked before any work: the outputs, the rotation, the target, the store and
    its record (as a relight request checks them; the store is returned, open), the sampler, runtime and batch size
    (the relighter reads the checkpoint first, then takes these)."""
    common.check_relighting(cfg)
    errors.check_int(cfg.batch_size, "batch_size", 1)
    viz.video_format(cfg.format)
    errors.check_out_dir(cfg.out_dir)
    errors.check_int(cfg.fps, "fps", 1)
    errors.check_choice(cfg.rotation.axis, "rotation.axis", sh.AXES)
    errors.check_choice(cfg.target.sun, "target.sun", sun_fit.TARGET_SUNS)
    errors.check_int(cfg.rotation.frames, "rotation.frames", 2, maximum=MAX_FRAMES)
    errors.check_number(cfg.target.shadow, "target.shadow")
    errors.check_int(cfg.sheet_columns, "sheet_columns", 1)
    if cfg.rotation.envmap is not None:
        errors.check_file(cfg.rotation.envmap, "rotation.envmap")
    return check_store(cfg.store, cfg.get("versions"), record=cfg.record)


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="video")
@errors.cli_entry("video")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
