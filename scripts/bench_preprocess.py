#!/usr/bin/env python
"""Throughput of difareli-preprocess per crop size with per-stage times, this tree beside a baseline, in one run.

    python scripts/bench_preprocess.py [--sizes 256] [--repeats 2] [--baseline bf71096 | --baseline none] [--workers 2]

Both sides run the default estimators (all encodings) in a fresh process each, on the same photos: scikit-image's
astronaut and cameraman, matplotlib's Grace Hopper, and their mirror images, after one warm-up image (which builds
the mediapipe graphs and loads dlib), without store writes or previews. The baseline is the package as it was at
git ``--baseline`` (default: the commit before the estimators' speed-ups), extracted with ``git archive`` into a
temporary folder (nothing in the checkout changes). ``--workers n`` also times this tree's ``difareli-preprocess``
run with ``n`` worker processes on the same photos (store writes included, previews off; wall-clock images/s). The rows
"mediapipe graphs" and "identity network" are the wall time inside those third-party calls (part of the stages
above them, hence "within the stages"), and "networks alone" the images/s this tree would reach if everything else
were free: the bound on what changing our own code can give. Time it under
the shared lock: ``flock /tmp/difareli-timing.lock python ...``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BASELINE = "bf71096"  # the estimators before their speed-ups


def photos() -> list[np.ndarray]:
    import skimage.data
    from matplotlib import cbook
    from PIL import Image

    with cbook.get_sample_data("grace_hopper.jpg") as f:
        grace = np.asarray(Image.open(f).convert("RGB"))
    camera = np.repeat(skimage.data.camera()[..., None], 3, axis=-1)  # grey, as the loader replicates it
    base = [skimage.data.astronaut(), grace, camera]
    return base + [np.ascontiguousarray(p[:, ::-1]) for p in base]


#: Third-party network calls timed inside the stages (``networks_ms``): what no change to our code removes.
NETWORKS = {"mediapipe graphs": ("mediapipe.python.solution_base", "SolutionBase", "process"),
            "identity network": ("difareli.estimators.dlib_resnet", "DlibFaceResNet", "forward")}


def clock_networks(seconds: dict[str, float]) -> None:
    """Wrap each of :data:`NETWORKS` (where the importable package has it) so that its calls add their wall time to
    ``seconds[name]``: mediapipe's graph runs (detection, FaceMesh, selfie segmentation) and the identity ResNet."""
    import importlib

    for name, (module, cls, method) in NETWORKS.items():
        try:
            owner = getattr(importlib.import_module(module), cls)
        except (ImportError, AttributeError):
            continue  # the baseline's descriptor is dlib's own, inside its identity stage
        inner = getattr(owner, method)

        def timed(*args, _inner=inner, _name=name, **kwargs):
            t0 = time.perf_counter()
            try:
                return _inner(*args, **kwargs)
            finally:
                seconds[_name] = seconds.get(_name, 0.0) + time.perf_counter() - t0

        setattr(owner, method, timed)


def measure(sizes: list[int], repeats: int) -> list[dict]:
    """Images/s, mean ms per stage and ms inside the third-party networks of the importable ``difareli`` at each
    size."""
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import build_pipeline
    from difareli.configs import CONFIG_DIR

    imgs, out = photos(), []
    for size in sizes:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            cfg = compose("preprocess", overrides=["in_dir=x", "out_dir=x", f"size={size}"])
        pipe = build_pipeline(cfg)
        pipe.process(imgs[0])  # warm-up
        totals: dict[str, float] = {}
        nets: dict[str, float] = {}
        clock_networks(nets)
        n, t0 = 0, time.perf_counter()
        for _ in range(repeats):
            for img in imgs:
                for k, v in pipe.process(img)[1]["seconds"].items():
                    totals[k] = totals.get(k, 0.0) + v
                n += 1
        dt = time.perf_counter() - t0
        out.append({"size": size, "images": n, "images_per_s": n / dt, "ms_per_image": 1000 * dt / n,
                    "stages_ms": {k: 1000 * v / n for k, v in totals.items()},
                    "networks_ms": {k: 1000 * v / n for k, v in nets.items()}})
    return out


def measure_workers(size: int, repeats: int, workers: int) -> float:
    """Wall-clock images/s of ``estimators.batch.run`` with ``workers`` processes over the photos (x ``repeats``)."""
    from hydra import compose, initialize_config_dir
    from PIL import Image

    from difareli.cli.preprocess import build_pipeline
    from difareli.configs import CONFIG_DIR
    from difareli.estimators.batch import run

    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "in"
        src.mkdir()
        n = 0
        for r in range(repeats):
            for i, img in enumerate(photos()):
                Image.fromarray(img).save(src / f"p{r}_{i}.png")
                n += 1
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            cfg = compose("preprocess", overrides=[f"in_dir={src}", "out_dir=x", f"size={size}"])
        t0 = time.perf_counter()  # worker start-up (imports, models) included: what a user waits for
        summary = run(build_pipeline(cfg), str(src), str(Path(tmp) / "out"), previews=False, progress=False,
                      workers=workers)
        return summary.written / (time.perf_counter() - t0)


def run_side(src: Path, sizes: list[int], repeats: int) -> list[dict]:
    """:func:`measure` in a fresh process importing the package from ``src``."""
    env = dict(os.environ, PYTHONPATH=str(src) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, __file__, "--worker", "--sizes", *map(str, sizes), "--repeats", str(repeats)]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tempfile.gettempdir(), check=False)
    if res.returncode != 0:
        raise RuntimeError(f"benchmark of {src} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def baseline_tree(ref: str, tmp: Path) -> Path | None:
    """``src/`` of git ``ref`` extracted into ``tmp`` (read-only git: ``git archive``), or None if unknown."""
    arch = subprocess.run(["git", "-C", str(REPO), "archive", ref, "src"], capture_output=True, check=False)
    if arch.returncode != 0:
        print(f"baseline {ref}: not in this clone ({arch.stderr.decode().strip()[:120]}); measuring this tree only")
        return None
    subprocess.run(["tar", "-x", "-C", str(tmp)], input=arch.stdout, check=True)
    return tmp / "src"


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def table(before: dict | None, after: dict) -> str:
    """The side-by-side text table of one size: stages, total, the networks inside them, images/s, the bound."""
    stages = list(dict.fromkeys([*(before or {}).get("stages_ms", {}), *after["stages_ms"]]))
    lines = [f"size {after['size']} px, {after['images']} images per side",
             f"{'stage':<22}{'baseline ms':>13}{'this tree ms':>14}{'speed-up':>10}"]
    for s in [*stages, "total"]:
        b = (before["ms_per_image"] if s == "total" else before["stages_ms"].get(s)) if before else None
        a = after["ms_per_image"] if s == "total" else after["stages_ms"].get(s)
        up = f"{b / a:.1f}x" if b and a else "-"
        lines.append(f"{s:<22}{fmt(b):>13}{fmt(a):>14}{up:>10}")
    for s in NETWORKS:  # inside the stages above, not added to the total
        b, a = (before or {}).get("networks_ms", {}).get(s), after.get("networks_ms", {}).get(s)
        if a is not None or b is not None:
            lines.append(f"{'  ' + s:<22}{fmt(b):>13}{fmt(a):>14}  (within the stages)")
    ips_b = f"{before['images_per_s']:.2f}" if before else "-"
    up = f" ({after['images_per_s'] / before['images_per_s']:.1f}x)" if before else ""
    lines.append(f"{'images/s':<22}{ips_b:>13}{after['images_per_s']:>14.2f}{up}")
    floor = sum(after.get("networks_ms", {}).values())
    if floor:
        ref = f"; the baseline's total / that = {before['ms_per_image'] / floor:.1f}x" if before else ""
        lines.append(f"networks alone: {floor:.1f} ms per image, {1000 / floor:.1f} images/s with every other stage "
                     f"free{ref}")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256])
    ap.add_argument("--repeats", type=int, default=2, help="passes over the six images")
    ap.add_argument("--baseline", default=BASELINE, help="git ref to compare with, or 'none'")
    ap.add_argument("--workers", type=int, default=0, help="also time this tree with this many worker processes")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(measure(args.sizes, args.repeats)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        base_src = None if args.baseline == "none" else baseline_tree(args.baseline, Path(tmp))
        before = run_side(base_src, args.sizes, args.repeats) if base_src else [None] * len(args.sizes)
        after = run_side(REPO / "src", args.sizes, args.repeats)
    print(f"baseline: {args.baseline if base_src else 'none'}; this tree: {REPO}")
    for b, a in zip(before, after):
        print(table(b, a), flush=True)
        if args.workers > 1:
            ips = measure_workers(a["size"], args.repeats, args.workers)
            print(f"{'images/s, ' + str(args.workers) + ' workers':<22}{'':>13}{ips:>14.2f}"
                  "  (run(), start-up included)")


if __name__ == "__main__":
    main()
