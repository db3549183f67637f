"""difareli-multipie: a user's Multi-PIE copy -> encodings store + protocols.json (difareli.multipie.build).

    difareli-multipie root=/data/Multi-Pie out_dir=data/multipie_64 size=64 [pairs=<authors' JSON> | pairs=null]

Exit status 0 when every image made it, 1 when some were skipped (each named on stderr; the store and
protocols.json are still written), 2 for a user error (a wrong root names the layout it expected).
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, ListConfig

from difareli.cli.common import CONFIG_PATH
from difareli.errors import check_bool, check_int, check_out_dir, cli_entry
from difareli.multipie import layout, protocols
from difareli.multipie.build import BuildReport, build, check_root
from difareli.cli.preprocess import build_pipeline


def pair_files(value) -> list[str] | None:
    """``pairs``: None, one path, or a list of paths."""
    if value is None or value in ("", "none", "null"):
        return None
    return [str(v) for v in value] if isinstance(value, (list, tuple, ListConfig)) else [str(value)]


def run(cfg: DictConfig, pipeline=None) -> BuildReport:
    """Build the store; ``pipeline`` (default: the configured photo estimators) does the preprocessing."""
    check_out_dir(cfg.out_dir)
    for key in ("same_subject", "different_subject"):
        check_int(cfg[key], key, 0)
    check_root(cfg.out_dir, layout.data_dir(cfg.root))  # a wrong root, store or pair list fails before the
    # estimators load, and so do recordings / illuminations that are no Multi-PIE codes
    recordings = layout.codes(cfg.recordings, "recordings", layout.RECORDINGS)
    ill = None if cfg.illuminations is None else layout.codes(cfg.illuminations, "illuminations", layout.ILLUMINATIONS)
    if pair_files(cfg.pairs):
        protocols.read_lists(pair_files(cfg.pairs))
    if pipeline is None:
        pipeline = build_pipeline(cfg)
    report = build(cfg.root, cfg.out_dir, pipeline, pair_files(cfg.pairs), seed=int(cfg.seed),
                   same_subject=int(cfg.same_subject), different_subject=int(cfg.different_subject),
                   recordings=recordings, illuminations=ill, images=str(cfg.images),
                   progress=check_bool(cfg.progress, "progress"), log=lambda line: print(line, file=sys.stderr))
    print(report.summary())
    print(f"next: difareli-benchmark store={cfg.out_dir} method=identity|lambertian|diffusion ...")
    return report


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="multipie")
@cli_entry("multipie")
def main(cfg: DictConfig) -> None:
    if run(cfg).skipped:
        sys.exit(1)


if __name__ == "__main__":
    main()
