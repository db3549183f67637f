"""difareli-preprocess: face photos -> encodings store, offline (src/difareli/estimators/).

    difareli-preprocess in_dir=photos/ out_dir=data/real256 [size=512] [encodings=[image,normal]]
    difareli-preprocess in_dir=photos/ out_dir=data/real64 model@variant=difareli_pp size=64
    difareli-preprocess in_dir=photos/ out_dir=data/real64 checkpoint=difareli_pp-synth64  # its inputs, its size
    difareli-preprocess in_dir=photo.jpg out_dir=data/one            # a single photo

A variant's store holds what its network reads plus what a relight of it reads (``inputs.relight_reads``: the
image, its light, and what re-rendering the light-dependent inputs needs, e.g. normal, depth, cam and shadow for
DiFaReli++'s target shadow maps), so ``difareli-relight store=<it>`` runs on it.

Exits with status 1 if any input failed (all good images are still written; see preprocess_report.json).
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, open_dict

from difareli.checkpoints import loading
from difareli.checkpoints.format import load_torch_file, training_resolution, upgrade_checkpoint
from difareli.cli.common import CONFIG_PATH
from difareli.errors import UserError, check_bool, check_int, check_out_dir, cli_entry
from difareli.data.shard import parse as parse_shard
from difareli.estimators.loading import IMAGE_SUFFIXES

#: The crop size without a checkpoint to take it from.
DEFAULT_SIZE = 256


def checkpoint_facts(checkpoint) -> tuple[int | None, list[str]]:
    """``(training resolution, inputs)`` of a checkpoint (a file or a shipped name), read without Lightning."""
    ckpt = upgrade_checkpoint(load_torch_file(loading.resolve(checkpoint, "checkpoint"), "checkpoint"))
    hp = ckpt.get("hyper_parameters")
    if not isinstance(hp, dict):
        raise UserError(f"checkpoint={checkpoint} is not a difareli checkpoint (no hyper_parameters); give "
                        "<run>/checkpoints/last.ckpt or a shipped name")
    return training_resolution(hp), [*(hp.get("spatial_inputs") or []), *(hp.get("nonspatial_inputs") or [])]


def resolve_size(cfg: DictConfig) -> int:
    """``cfg.size``; null: the checkpoint's training resolution (``checkpoint=``), else 256. Set in ``cfg``."""
    if cfg.get("size") is None:
        res = checkpoint_facts(cfg.checkpoint)[0] if cfg.get("checkpoint") else None
        with open_dict(cfg):
            cfg.size = res or DEFAULT_SIZE
    return int(cfg.size)


def requested_encodings(cfg: DictConfig) -> list[str] | None:
    """``cfg.encodings``, else what relighting the chosen checkpoint or variant reads (``inputs.relight_reads`` of
    its spatial + non-spatial inputs: the image, the light, the inputs and what re-rendering them needs), else
    None (all)."""
    from difareli.data.inputs import relight_reads

    if cfg.get("encodings") is not None:
        return list(cfg.encodings)
    if cfg.get("checkpoint"):
        return relight_reads(checkpoint_facts(cfg.checkpoint)[1])
    variant = cfg.get("variant")
    if variant:
        return relight_reads([*(variant.get("spatial_inputs") or []), *(variant.get("nonspatial_inputs") or [])])
    return None


def check_in_dir(in_dir) -> None:
    """``in_dir`` is a folder or one image file; anything else is a UserError naming the fix."""
    p = Path(str(in_dir))
    if p.is_dir():
        return
    if not p.exists():
        raise UserError(f"in_dir={in_dir} does not exist; give a folder of face photos or one photo file, "
                        "in_dir=<dir or file>")
    if not p.is_file():
        raise UserError(f"in_dir={in_dir} is neither a folder nor a file; give a folder of face photos or one photo")
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        raise UserError(f"in_dir={in_dir}: not an image file (suffix {p.suffix or 'none'!r}); give a face photo "
                        f"({', '.join(IMAGE_SUFFIXES)}) or a folder of them")


def build_pipeline(cfg: DictConfig):
    """Instantiate the aligner and the estimators of ``cfg.estimators`` into a Pipeline."""
    from difareli.estimators.pipeline import Pipeline

    resolve_size(cfg)
    return Pipeline.from_config(cfg.estimators, requested_encodings(cfg), min_side=int(cfg.min_side),
                                max_side=int(cfg.max_side))


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="preprocess")
@cli_entry("preprocess")
def main(cfg: DictConfig) -> None:
    from difareli.estimators.batch import REPORT, run
    check_in_dir(cfg.in_dir)
    check_out_dir(cfg.out_dir)

    try:
        parse_shard(cfg.get("shard"))
    except ValueError as e:
        raise UserError(f"shard={cfg.get('shard')!r}: {e}") from None
    check_int(cfg.get("workers") or 1, "workers", 1)
    # overwrite=no would be truthy: refused before any estimator loads or any record is touched
    flags = {k: check_bool(cfg[k], k) for k in ("overwrite", "previews", "durable", "progress")}
    auto_size = cfg.get("size") is None
    pipeline = build_pipeline(cfg)
    names = [type(s).__name__ for s in pipeline.steps]
    print(f"encodings: {', '.join(pipeline.encodings)}\nestimators: {', '.join(names) or '(alignment only)'}\n"
          f"size: {pipeline.size} px" + (f" (checkpoint={cfg.checkpoint}'s training resolution)"
                                         if cfg.get("checkpoint") and auto_size else ""))
    summary = run(pipeline, str(cfg.in_dir), str(cfg.out_dir), **flags, shard=cfg.get("shard"),
                  workers=int(cfg.get("workers") or 1))
    print(f"written {summary.written}, skipped {summary.skipped}, failed {summary.failed}; "
          f"{summary.images_per_second:.2f} images/s at {pipeline.size}px; report: {cfg.out_dir}/{REPORT}")
    if summary.stages:
        print("per image: " + ", ".join(f"{k} {v:.0f} ms" for k, v in summary.stage_ms().items()))
    failed = [e for e in summary.entries if e["status"] == "failed"]
    if failed and Path(str(cfg.in_dir)).is_file() and "No module named" not in str(failed[0]["reason"]):
        # The one input is bad: a user error (exit 2), its reason and the fix in one line.
        raise UserError(f"in_dir={cfg.in_dir}: {failed[0]['reason']}; use a photo of one clearly visible face, at "
                        f"least {cfg.min_side} px per side (nothing was written for it)")
    for e in summary.entries:
        if e["status"] == "failed":
            print(f"  FAILED {e['file']}: {e['reason']}", file=sys.stderr)
    missing = sorted({e["reason"] for e in summary.entries if e["status"] == "failed"
                      and "No module named" in str(e["reason"])})
    if missing:  # every image would fail the same way: the estimators' optional packages are not installed
        raise UserError(f"{summary.failed} image(s) failed: {missing[0]}; install the preprocess extras "
                        "(DIFARELI_PREPROCESS=1 bash scripts/install.sh), then rerun")
    if summary.failed:
        sys.exit(1)


if __name__ == "__main__":
    main()
