"""difareli-synth: generate (or complete) a SynthFaces encodings store; the work is in synth/generator.py."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from difareli.cli.common import CONFIG_PATH
from difareli.errors import check_out_dir, cli_entry
from difareli.data.shard import parse as parse_shard
from difareli.synth.config import INPUTS, ConfigError
from difareli.synth.effects import Effects


#: Integer keys and their smallest valid values, checked before any work starts.
_MINIMA = {"subjects": 1, "lights": 1, "resolution": 16, "workers": 1, "light_group_size": 1}


def validate(cfg: DictConfig) -> None:
    """Raise ConfigError (a ValueError) naming the first invalid key."""
    if OmegaConf.is_missing(cfg, "out_dir") or not str(cfg.out_dir):
        raise ConfigError("out_dir is required: the store root, e.g. out_dir=data/synthfaces_64")
    check_out_dir(cfg.out_dir)
    for key, lo in _MINIMA.items():
        value = cfg[key]
        if not isinstance(value, int) or isinstance(value, bool) or value < lo:
            raise ConfigError(f"{key}={value!r} is invalid: must be an integer >= {lo}")
    if cfg.shading_region not in ("face", "mesh"):
        raise ConfigError(f"shading_region={cfg.shading_region!r} is invalid: use 'face' or 'mesh'")
    try:
        Effects.resolve(cfg.realism, OmegaConf.to_container(cfg.effects))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.inputs not in INPUTS:
        raise ConfigError(f"inputs={cfg.inputs!r} is invalid: use one of {list(INPUTS)}")
    try:
        parse_shard(cfg.get("shard"))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    fr = cfg.splits
    if any(float(v) < 0 for v in fr.values()) or sum(float(v) for v in fr.values()) <= 0:
        raise ConfigError(f"splits={OmegaConf.to_container(fr)} is invalid: fractions must be >= 0, sum > 0")


def run(cfg: DictConfig):
    """Validate, generate, write the preview, print a summary; returns the GenerateReport."""
    from difareli.synth.generator import generate
    from difareli.synth.preview import write_preview

    validate(cfg)
    n = cfg.subjects * cfg.lights

    def progress(done: int, total: int) -> None:
        if done == total or done % max(1, total // 10) < cfg.lights:
            print(f"  {done}/{total} records", flush=True)

    report = generate(
        cfg.out_dir, cfg.subjects, cfg.lights, cfg.resolution, cfg.seed, workers=cfg.workers,
        durable=cfg.durable, progress=progress, light_group_size=cfg.light_group_size,
        splits=OmegaConf.to_container(cfg.splits), shading_region=cfg.shading_region, cam_jitter=cfg.cam_jitter,
        realism=cfg.realism, effects=OmegaConf.to_container(cfg.effects), inputs=cfg.inputs,
        estimation_resolution=cfg.estimation_resolution, shadow_visible=cfg.shadow_visible,
        c_quantile=cfg.c_quantile, shard=cfg.get("shard"),
    )
    if report.written == 0:
        print(f"nothing to do: all {n} records already exist in {cfg.out_dir} (skipped {report.skipped})")
    else:
        print(f"wrote {report.written} records, skipped {report.skipped} existing, in {report.seconds:.1f} s "
              f"({report.images_per_second:.1f} images/s at {cfg.resolution}px, {cfg.workers} worker(s), "
              f"realism={cfg.realism}, inputs={cfg.inputs})")
    if report.problems:
        print(f"{len(report.problems)} problems:\n  " + "\n  ".join(report.problems[:20]), file=sys.stderr)
        raise SystemExit(1)
    # A shard sees only its own subjects: the preview is left to an unsharded (or final) run.
    if cfg.preview.enabled and report.written > 0 and not cfg.get("shard"):
        path = write_preview(cfg.out_dir, subjects=cfg.preview.subjects, lights=cfg.preview.lights,
                             cell=cfg.preview.cell)
        print(f"preview: {path}")
    return report


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="synth")
@cli_entry("synth")  # a bad or mismatching configuration (ConfigError): one clear line, exit 2
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
