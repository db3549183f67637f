"""Named UNet configurations (their parameter counts: ``python -m difareli.cli.presets``).

``ffhq128`` / ``ffhq256`` follow the paper's Table (Appendix III) and the public DiFaReli configs
(``config/base_config.py`` + ``config/difareli/difareli_{128,256}.yaml``): base 128 channels, 2 residual blocks,
attention at 16 and 8 px with 4 heads, dropout 0, scale-shift norm, conv resampling (``resblock_updown=False``),
MLP3 hidden 512. The public code picks the channel multipliers from the image size: [1,1,2,3,4] at 128 and
[1,1,2,2,4,4] at 256; both its yaml files and the paper's table keep attention at [16, 8] for 256 too.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from difareli.errors import MissingError

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

def get_config(preset: str, overrides: dict[str, Any] | None = None) -> UNetConfig:
    """The :class:`UNetConfig` of a named preset, with field overrides (plain values) applied."""
    if preset not in PRESETS:
        raise MissingError(f"unknown UNet preset {preset!r}; known: {sorted(PRESETS)}")
    values = dict(PRESETS[preset])
    for key, value in (overrides or {}).items():
        if key not in UNetConfig.__dataclass_fields__:
            raise MissingError(f"unknown UNet option {key!r}; known: {sorted(UNetConfig.__dataclass_fields__)}")
        # Hydra hands over ListConfig/DictConfig; keep the config plain so checkpoints and asdict() stay simple
        values[key] = list(value) if isinstance(value, Sequence) and not isinstance(value, str) else value
    return UNetConfig(**values)
