#!/usr/bin/env python
"""Throughput of difareli-preprocess per crop size, with a per-estimator breakdown.

    python scripts/bench_preprocess.py [--sizes 256 512] [--repeats 4]

Runs the default estimators (all encodings) in-process on the two shipped photos and their mirror images
(after one warm-up image, which builds the mediapipe graphs and loads dlib), without store writes or
previews; the store write of one record adds a few ms.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def photos() -> list[np.ndarray]:
    import skimage.data
    from matplotlib import cbook
    from PIL import Image

    with cbook.get_sample_data("grace_hopper.jpg") as f:
        grace = np.asarray(Image.open(f).convert("RGB"))
    base = [skimage.data.astronaut(), grace]
    return base + [np.ascontiguousarray(p[:, ::-1]) for p in base]


def main(argv=None) -> None:
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import build_pipeline
    from pathlib import Path

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeats", type=int, default=2, help="passes over the four images")
    args = ap.parse_args(argv)
    from difareli.configs import CONFIG_DIR

    conf = str(CONFIG_DIR)
    imgs = photos()
    for size in args.sizes:
        with initialize_config_dir(config_dir=conf, version_base="1.3"):
            cfg = compose("preprocess", overrides=["in_dir=x", "out_dir=x", f"size={size}"])
        pipe = build_pipeline(cfg)
        pipe.process(imgs[0])  # warm-up
        totals: dict[str, float] = {}
        t0 = time.perf_counter()
        n = 0
        for _ in range(args.repeats):
            for img in imgs:
                meta = pipe.process(img)[1]
                for k, v in meta["seconds"].items():
                    totals[k] = totals.get(k, 0.0) + v
                n += 1
        dt = time.perf_counter() - t0
        parts = ", ".join(f"{k} {1000 * v / n:.0f} ms" for k, v in totals.items())
        print(f"size {size}: {n / dt:.2f} images/s ({1000 * dt / n:.0f} ms/image: {parts})", flush=True)


if __name__ == "__main__":
    main()
