"""difareli-preprocess: face photos -> encodings store, offline (src/difareli/estimators/).

    difareli-preprocess in_dir=photos/ out_dir=data/real256 [size=512] [encodings=[image,normal]]
    difareli-preprocess in_dir=photos/ out_dir=data/real256 model@variant=difareli_pp

Exits with status 1 if any input failed (all good images are still written; see preprocess_report.json).
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from difareli.cli.common import CONFIG_PATH

ROLES = ("geometry", "masks", "light", "identity", "shadow")


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

    est = cfg.estimators
    return Pipeline(hydra.utils.instantiate(est.align), [hydra.utils.instantiate(est[r]) for r in ROLES if est.get(r)],
                    requested_encodings(cfg), min_side=int(cfg.min_side), max_side=int(cfg.max_side))


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="preprocess")
def main(cfg: DictConfig) -> None:
    from difareli.estimators.pipeline import REPORT, run
    from difareli.shard import parse as parse_shard

    try:
        parse_shard(cfg.get("shard"))
    except ValueError as e:
        raise SystemExit(f"difareli-preprocess: {e}") from None
    pipeline = build_pipeline(cfg)
    names = [type(s).__name__ for s in pipeline.steps]
    print(f"encodings: {', '.join(pipeline.encodings)}\nestimators: {', '.join(names) or '(alignment only)'}")
    summary = run(pipeline, str(cfg.in_dir), str(cfg.out_dir), overwrite=bool(cfg.overwrite),
                  previews=bool(cfg.previews), durable=bool(cfg.durable), progress=bool(cfg.progress),
                  shard=cfg.get("shard"))
    print(f"written {summary.written}, skipped {summary.skipped}, failed {summary.failed}; "
          f"{summary.images_per_second:.2f} images/s at {pipeline.size}px; report: {cfg.out_dir}/{REPORT}")
    for e in summary.entries:
        if e["status"] == "failed":
            print(f"  FAILED {e['file']}: {e['reason']}", file=sys.stderr)
    if summary.failed:
        sys.exit(1)


if __name__ == "__main__":
    main()
