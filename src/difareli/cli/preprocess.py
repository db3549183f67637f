"""difareli-preprocess: face photos -> encodings store, offline (src/difareli/estimators/).

    difareli-preprocess in_dir=photos/ out_dir=data/real256 [size=512] [encodings=[image,normal]]
    difareli-preprocess in_dir=photos/ out_dir=data/real256 model@variant=difareli_pp

Exits with status 1 if any input failed (all good images are still written; see preprocess_report.json).
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from difareli.cli.common import CONFIG_PATH
from difareli.errors import UserError, check_int, check_out_dir, cli_entry

def requested_encodings(cfg: DictConfig) -> list[str] | None:
    """``cfg.encodings``, else the chosen variant's spatial + non-spatial inputs plus ``image``, else None (all)."""
    if cfg.get("encodings") is not None:
        return list(cfg.encodings)
    variant = cfg.get("variant")
    if variant:
        names = ["image", *variant.get("spatial_inputs", []), *variant.get("nonspatial_inputs", [])]
        return list(dict.fromkeys(names))
    return None


def build_pipeline(cfg: DictConfig):
    """Instantiate the aligner and the estimators of ``cfg.estimators`` into a Pipeline."""
    from difareli.estimators.pipeline import Pipeline

    return Pipeline.from_config(cfg.estimators, requested_encodings(cfg), min_side=int(cfg.min_side),
                                max_side=int(cfg.max_side))


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="preprocess")
@cli_entry("preprocess")
def main(cfg: DictConfig) -> None:
    from difareli.estimators.batch import REPORT, run
    from difareli.shard import parse as parse_shard

    if not Path(str(cfg.in_dir)).is_dir():
        raise UserError(f"in_dir={cfg.in_dir} is not a folder; give the folder of face photos, in_dir=<dir>")
    check_out_dir(cfg.out_dir)

    try:
        parse_shard(cfg.get("shard"))
    except ValueError as e:
        raise UserError(f"shard={cfg.get('shard')!r}: {e}") from None
    check_int(cfg.get("workers") or 1, "workers", 1)
    pipeline = build_pipeline(cfg)
    names = [type(s).__name__ for s in pipeline.steps]
    print(f"encodings: {', '.join(pipeline.encodings)}\nestimators: {', '.join(names) or '(alignment only)'}")
    summary = run(pipeline, str(cfg.in_dir), str(cfg.out_dir), overwrite=bool(cfg.overwrite),
                  previews=bool(cfg.previews), durable=bool(cfg.durable), progress=bool(cfg.progress),
                  shard=cfg.get("shard"), workers=int(cfg.get("workers") or 1))
    print(f"written {summary.written}, skipped {summary.skipped}, failed {summary.failed}; "
          f"{summary.images_per_second:.2f} images/s at {pipeline.size}px; report: {cfg.out_dir}/{REPORT}")
    if summary.stages:
        print("per image: " + ", ".join(f"{k} {v:.0f} ms" for k, v in summary.stage_ms().items()))
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
