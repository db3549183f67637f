"""difareli-shadow-maps: shadow maps written as a derived store version: the difference method from a trained
DiFaReli (``maker=difference``), or the relight's own maker (``maker=march``) / the exact visible shadows
(``maker=visible``) for training a DiFaReli++ on maps of the kind it is tested with."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from difareli.diffusion.spec import check_sampler
from difareli import errors
from difareli.checkpoints import loading
from difareli.cli import common
from difareli.utils.fileio import write_json_atomic
from difareli.data.store import EncodingStore
from difareli.data.encodings import PART_INDEX
from difareli.data.provenance import model_identity
from difareli.diffusion.relight import SamplerSpec
from difareli.jobs.shadow_response import check_centre
from difareli.runtime.core import Runtime


def run(cfg: DictConfig):
    """Compute the maps as configured; prints the summary and returns the report."""
    from difareli.jobs import shadow_maps
    from difareli.lit import load_checkpoint
    validate(cfg)
    store = EncodingStore.open(cfg.store, writable=True)
    ids = record_ids(cfg, store)  # the splits named, checked before the checkpoint is loaded
    if cfg.maker != "difference":
        return run_maker(cfg, store, ids)
    given = c_range_given(cfg)
    shadow_maps.c_source(store, cfg.split, given)
    runtime = Runtime.from_config(cfg.runtime)
    ckpt = load_checkpoint(cfg.checkpoint, runtime.torch_device)
    spec = SamplerSpec.from_config(cfg.sampler)
    # The weights by content: retrained weights at the same path make another version (never "relit 0").
    provenance = {"checkpoint": str(Path(cfg.checkpoint).resolve()), "weights": model_identity(ckpt.model),
                  "global_step": ckpt.global_step,
                  "sampler": OmegaConf.to_container(cfg.sampler, resolve=True), "precision": runtime.precision}
    threshold = shadow_maps.check_threshold(cfg.threshold)
    rep = shadow_maps.compute(ckpt.model.to(runtime.torch_device), store, spec, provenance=provenance,
                              ids=ids, split=cfg.split, c_range=given,
                              c_quantile=float(cfg.c_quantile),
                              threshold=threshold, relative=float(cfg.relative), centre=cfg.centre,
                              median=cfg.median if cfg.median == "auto" else int(cfg.median),
                              zero_parts=list(cfg.zero_parts or []),
                              min_contrast=None if cfg.min_contrast is None else float(cfg.min_contrast),
                              min_coherence=None if cfg.min_coherence is None else float(cfg.min_coherence),
                              batch_size=int(cfg.batch_size), check_after=int(cfg.check_after),
                              version=cfg.version, runtime=runtime,
                              mean_matching=errors.check_bool(cfg.mean_matching, "mean_matching"),
                              device=runtime.torch_device, progress=errors.check_bool(cfg.progress, "progress"))
    version = rep.name.split("@", 1)[1]
    summary = {"name": rep.name, "raw": rep.raw, "c_min": rep.c_min, "c_max": rep.c_max, "threshold": rep.threshold,
               "threshold_rule": store.derived[rep.name]["threshold_rule"], "median": store.derived[rep.name]["median"],
               "contrast": store.derived[rep.name]["contrast"], "coherence": store.derived[rep.name]["coherence"],
               "relit_records": rep.relit, "written": rep.written, "seconds": round(rep.seconds, 3),
               "images_per_second": round(rep.images_per_second, 3), "c_source": rep.c_source}
    write_json_atomic(Path(cfg.out_dir) / "shadow_maps.json", summary)
    print(f"c range ({rep.c_source}): [{rep.c_min:.3f}, {rep.c_max:.3f}]; threshold {rep.threshold:.5f} "
          f"({summary['threshold_rule']}); median {summary['median']}; candidates {summary['contrast']:.4f} darker "
          f"than the rest of the face, coherence {summary['coherence']:.2f} (0: speckle)")
    print(f"relit {rep.relit} record(s) at 2 shadow strengths in {rep.seconds:.1f} s "
          f"({rep.images_per_second:.2f} images/s); wrote {rep.written} map(s) as {rep.name}")
    print(f"train on them: data.versions={{shadow_map: {version}}}   "
          f"(relight/video: versions={{shadow_map: {version}}})")
    return rep


def run_maker(cfg: DictConfig, store, ids):
    """``maker=march|visible``: no model; every record's map from its own encodings."""
    from difareli.jobs import derived_maps

    version = None if cfg.version in (None, "difference") else cfg.version
    rep = derived_maps.compute(store, method=cfg.maker, light=cfg.light, version=version, ids=ids,
                               progress=errors.check_bool(cfg.progress, "progress"))
    write_json_atomic(Path(cfg.out_dir) / "shadow_maps.json", {"name": rep.name, "written": rep.written,
                                                               "records": rep.records, **rep.provenance})
    print(f"wrote {rep.written} map(s) ({rep.records - rep.written} already there) as {rep.name} in "
          f"{rep.seconds:.1f} s: {cfg.maker} toward the {cfg.light} light")
    print(f"train on them: data.versions={{shadow_map: {rep.name.split('@', 1)[1]}}}")
    return rep


def record_ids(cfg: DictConfig, store) -> list[str] | None:
    """``records`` if given, else ``records_split``'s records, else None (every record)."""
    if cfg.records is not None:
        return list(cfg.records)
    if cfg.get("records_split"):
        from difareli.jobs.shadow_maps import split_ids

        return split_ids(store, cfg.records_split, "records_split")  # an unknown split names the store's splits
    return None


def c_range_given(cfg: DictConfig) -> tuple[float, float] | None:
    """``c_range=[c_min, c_max]`` (null: from ``split``), checked."""
    value = cfg.get("c_range")
    if value is None:
        return None
    if not OmegaConf.is_list(value) or len(value) != 2:
        raise errors.UserError(f"c_range={value!r} is invalid: give two numbers, c_range=[c_min,c_max], or null "
                               "for the split's range")
    lo, hi = (errors.check_number(v, "c_range", allow_none=False) for v in value)
    if not hi > lo:
        raise errors.UserError(f"c_range={list(value)} is invalid: give [c_min, c_max] with c_min < c_max")
    return lo, hi


def validate(cfg: DictConfig) -> None:
    """Config values and input files, checked before any work."""
    if cfg.maker not in ("difference", "march", "visible"):
        raise errors.UserError(f"maker={cfg.maker!r}: choose difference (needs checkpoint=<a DiFaReli>), march (the "
                               "relight's own maker) or visible (SynthFaces v3's exact visible shadows)")
    errors.check_out_dir(cfg.out_dir)
    if cfg.maker != "difference":
        return
    if cfg.checkpoint is None:
        raise errors.UserError("maker=difference relights with a DiFaReli: give checkpoint=<its .ckpt or a shipped "
                               "name, e.g. difareli-synth64>, or maker=march for maps without a model")
    check_sampler(cfg.sampler)
    loading.resolve(cfg.checkpoint, "checkpoint")  # a file or a shipped name, as in every other CLI
    if cfg.median != "auto":
        errors.check_int(cfg.median, "median", 1)
        if int(cfg.median) % 2 == 0:
            raise errors.UserError(f"median={cfg.median} is even; use an odd window or median=auto")
    for key in ("min_contrast", "min_coherence"):
        if cfg.get(key) is not None:
            errors.check_number(cfg[key], key, allow_none=False)
    errors.check_number(cfg.relative, "relative", allow_none=False)
    if not 0.0 < float(cfg.relative) < 1.0:
        raise errors.UserError(f"relative={cfg.relative} is out of range: the cut is this share of the response's 99th "
                               "percentile, strictly between 0 and 1 (e.g. 0.5)")
    check_centre(cfg.centre)
    bad = [p for p in (cfg.zero_parts or []) if p not in PART_INDEX]
    if bad:
        raise errors.UserError(f"zero_parts={list(cfg.zero_parts)}: unknown parts {bad}; "
                               f"use names of {list(PART_INDEX)}")
    errors.check_int(cfg.batch_size, "batch_size", 1)
    errors.check_int(cfg.check_after, "check_after", 0)
    errors.check_number(cfg.c_quantile, "c_quantile", allow_none=False)
    from difareli.jobs.shadow_maps import check_threshold

    check_threshold(cfg.threshold)  # relative, otsu, or a number strictly between 0 and 1
    c_range_given(cfg)


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="shadow_maps")
@errors.cli_entry("shadow-maps")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
