"""Named UNet configurations and a parameter-count report (``python -m difareli.nn.presets``).

``ffhq128`` / ``ffhq256`` follow the paper's Table (Appendix III) and the public DiFaReli configs
(``config/base_config.py`` + ``config/difareli/difareli_{128,256}.yaml``): base 128 channels, 2 residual blocks,
attention at 16 and 8 px with 4 heads, dropout 0, scale-shift norm, conv resampling (``resblock_updown=False``),
MLP3 hidden 512. The public code picks the channel multipliers from the image size: [1,1,2,3,4] at 128 and
[1,1,2,2,4,4] at 256; both its yaml files and the paper's table keep attention at [16, 8] for 256 too.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from .unet import UNetConfig

PRESETS: dict[str, dict[str, Any]] = {
    # CPU tests and smoke runs: ~1.5M parameters with a Modulator.
    "tiny": dict(base_channels=32, channel_mult=[1, 2, 2], num_res_blocks=1, attention_resolutions=[8], image_size=32,
                 num_heads=2, adagn_hidden=128),
    # The GPU reference (experiment=reference_gpu): 7.3M parameters with a Modulator, so its bf16 EMA weights
    # (14.6 MB) come back from a lent GPU (16 MiB per file) and three references ship under 60 MB.
    "small": dict(base_channels=64, channel_mult=[1, 2, 2], num_res_blocks=1, attention_resolutions=[16, 8],
                  image_size=64, num_heads=4, adagn_hidden=192),
    "ffhq128": dict(base_channels=128, channel_mult=[1, 1, 2, 3, 4], num_res_blocks=2, attention_resolutions=[16, 8],
                    image_size=128, num_heads=4),
    "ffhq256": dict(base_channels=128, channel_mult=[1, 1, 2, 2, 4, 4], num_res_blocks=2,
                    attention_resolutions=[16, 8], image_size=256, num_heads=4),
}

#: The paper's two variants, reported by :func:`report`: their ``conf/model`` files.
VARIANTS = ("difareli", "difareli_pp")


def variant_inputs(model: str) -> tuple[list[str], list[str]]:
    """``(spatial inputs, non-spatial inputs)`` declared by ``conf/model/<model>.yaml`` (read as plain YAML, so
    this works without Hydra, e.g. on a bare GPU image)."""
    from difareli.configs import read_yaml

    cfg = read_yaml("model", model)
    return list(cfg.get("spatial_inputs") or []), list(cfg.get("nonspatial_inputs") or [])


def variant_widths(model: str, dims: dict[str, int] | None = None) -> tuple[int, int]:
    """``(spatial channels, non-spatial features)`` of a ``conf/model`` variant, from the encoding registry at the
    producers' dimensions (SynthFaces / difareli-preprocess: shape 53, identity 128)."""
    from difareli import encodings

    spatial, nonspatial = variant_inputs(model)
    dims = {"H": 1, "W": 1, **encodings.PRODUCER_DIMS, **(dims or {})}
    return encodings.total_channels(spatial, dims), encodings.total_channels(nonspatial, dims)


def get_config(preset: str, overrides: dict[str, Any] | None = None) -> UNetConfig:
    """The :class:`UNetConfig` of a named preset, with field overrides (plain values) applied."""
    if preset not in PRESETS:
        raise KeyError(f"unknown UNet preset {preset!r}; known: {sorted(PRESETS)}")
    values = dict(PRESETS[preset])
    for key, value in (overrides or {}).items():
        if key not in UNetConfig.__dataclass_fields__:
            raise KeyError(f"unknown UNet option {key!r}; known: {sorted(UNetConfig.__dataclass_fields__)}")
        # Hydra hands over ListConfig/DictConfig; keep the config plain so checkpoints and asdict() stay simple
        values[key] = list(value) if isinstance(value, Sequence) and not isinstance(value, str) else value
    return UNetConfig(**values)


def report(presets: list[str] | None = None) -> list[dict[str, Any]]:
    """Parameter counts per preset and variant (built on the meta device: no memory, no init time)."""
    import torch

    from .network import build_network

    rows = []
    for preset in presets or list(PRESETS):
        for variant in VARIANTS:
            spatial_channels, nonspatial_dim = variant_widths(variant)
            with torch.device("meta"):
                net = build_network(preset, "modulator", spatial_channels, nonspatial_dim)
            rows.append({"preset": preset, "variant": variant, **net.parameter_counts()})
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("presets", nargs="*", help=f"presets to report (default: all of {list(PRESETS)})")
    args = parser.parse_args(argv)
    print(f"{'preset':<8} {'variant':<11} {'UNet':>12} {'Modulator':>12} {'MLPs':>12} {'total':>12}")
    for r in report(args.presets or None):
        print(f"{r['preset']:<8} {r['variant']:<11} {r['unet']:>12,} {r['spatial']:>12,} {r['mlps']:>12,} "
              f"{r['total']:>12,}")


if __name__ == "__main__":
    main()
