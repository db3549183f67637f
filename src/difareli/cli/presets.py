"""Parameter counts of every UNet preset for the paper's two variants (``python -m difareli.cli.presets``)."""

from __future__ import annotations

import argparse
from typing import Any

#: The paper's two variants, reported by :func:`report`: their ``conf/model`` files.
VARIANTS = ("difareli", "difareli_pp")


def report(presets: list[str] | None = None) -> list[dict[str, Any]]:
    """Parameter counts per preset and variant (built on the meta device: no memory, no init time)."""
    import torch

    from difareli.data.inputs import variant_widths
    from difareli.nn.network import build_network
    from difareli.nn.presets import PRESETS

    rows = []
    for preset in presets or list(PRESETS):
        for variant in VARIANTS:
            spatial_channels, nonspatial_dim = variant_widths(variant)
            with torch.device("meta"):
                net = build_network(preset, "modulator", spatial_channels, nonspatial_dim)
            rows.append({"preset": preset, "variant": variant, **net.parameter_counts()})
    return rows


def main(argv: list[str] | None = None) -> None:
    from difareli.nn.presets import PRESETS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("presets", nargs="*", help=f"presets to report (default: all of {list(PRESETS)})")
    args = parser.parse_args(argv)
    print(f"{'preset':<8} {'variant':<11} {'UNet':>12} {'Modulator':>12} {'MLPs':>12} {'total':>12}")
    for r in report(args.presets or None):
        print(f"{r['preset']:<8} {r['variant']:<11} {r['unet']:>12,} {r['spatial']:>12,} {r['mlps']:>12,} "
              f"{r['total']:>12,}")


if __name__ == "__main__":
    main()
