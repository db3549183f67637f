#!/usr/bin/env python
"""Throughput of difareli-preprocess per crop size with per-stage times, this tree beside a baseline, interleaved.

    python scripts/bench_preprocess.py [--sizes 256] [--rounds 3] [--passes 4] [--baseline <git ref> | none]
                                       [--workers 2] [--previews]

Each round runs the baseline, then this tree, each in a fresh process (start-up and one warm-up photo, which builds
the mediapipe graphs and loads dlib, not timed): rounds interleave the two sides so that a change of the machine's
load reaches both, and each round's ratio compares two runs minutes apart, not two halves of an hour. Each process
times, on the same photos (scikit-image's astronaut and cameraman, matplotlib's Grace Hopper, their mirror images;
``--passes`` times over):

- ``process()``: ``Pipeline.process`` one photo after the other, in memory (what a photo relight and SynthFaces'
  estimated inputs call);
- ``run()``: ``estimators.batch.run`` on a folder of those photos as PNGs, the store written, previews off (on with
  ``--previews``, as ``difareli-preprocess`` writes them by default): what ``difareli-preprocess`` does (decoding,
  alignment and estimators overlapped where the tree does so).

The rows "mediapipe graphs" and "identity network" are the wall time inside those third-party calls (part of the
stages above them), and "networks alone" the images/s with every other line free, one call after the other: the
bound that changing our own code cannot pass on one core. Stage times are per photo; where stages overlap (run()
of a tree with the reader thread) they add up to more than the wall time. Medians over the rounds; "x" columns are
the median of each round's ratio. The baseline is the package at git ``--baseline`` (``git archive`` into a
temporary folder; nothing in the checkout changes). ``--workers n`` also times this tree's run() with ``n``
worker processes (start-up included). Time it under the shared lock:
``flock /tmp/difareli-timing.lock python scripts/bench_preprocess.py ...``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BASELINE = "a032ebe"  # the estimators before the overlapped, batched run


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
    """Wrap each of :data:`NETWORKS` (where the importable package has it) so that its calls, from any thread, add
    their wall time to ``seconds[name]``."""
    import importlib

    lock = threading.Lock()
    for name, (module, cls, method) in NETWORKS.items():
        try:
            owner = getattr(importlib.import_module(module), cls)
        except (ImportError, AttributeError):
            continue  # a tree whose descriptor is dlib's own, inside its identity stage
        inner = getattr(owner, method)

        def timed(*args, _inner=inner, _name=name, **kwargs):
            t0 = time.perf_counter()
            try:
                return _inner(*args, **kwargs)
            finally:
                with lock:
                    seconds[_name] = seconds.get(_name, 0.0) + time.perf_counter() - t0

        setattr(owner, method, timed)


def _pipeline(size: int, in_dir: str = "x"):
    from hydra import compose, initialize_config_dir

    from difareli.cli.preprocess import build_pipeline
    from difareli.configs import CONFIG_DIR

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("preprocess", overrides=[f"in_dir={in_dir}", "out_dir=x", f"size={size}"])
    return build_pipeline(cfg)


def _cpu() -> float:
    """CPU seconds of this process so far, every thread (mediapipe's graph threads too)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _row(n: int, dt: float, cpu: float, stages: dict, nets: dict) -> dict:
    return {"images": n, "images_per_s": n / dt, "ms_per_image": 1000 * dt / n, "cpu_ms_per_image": 1000 * cpu / n,
            "stages_ms": {k: 1000 * v / n for k, v in stages.items()},
            "networks_ms": {k: 1000 * v / n for k, v in nets.items()}}


def measure(size: int, passes: int, previews: bool = False) -> dict:
    """``{"process": row, "run": row}`` of the importable ``difareli`` at ``size`` (see the module doc)."""
    from PIL import Image

    from difareli.estimators.batch import run

    imgs = photos()
    pipe = _pipeline(size)
    pipe.process(imgs[0])  # warm-up: graphs, dlib, the BFM
    nets: dict[str, float] = {}
    clock_networks(nets)
    stages: dict[str, float] = {}
    t0, c0 = time.perf_counter(), _cpu()
    for _ in range(passes):
        for img in imgs:
            for k, v in pipe.process(img)[1]["seconds"].items():
                stages[k] = stages.get(k, 0.0) + v
    out = {"process": _row(passes * len(imgs), time.perf_counter() - t0, _cpu() - c0, stages, nets)}
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "in"
        src.mkdir()
        for p in range(passes):
            for i, img in enumerate(imgs):
                Image.fromarray(img).save(src / f"p{p}_{i}.png")
        nets.clear()
        t0, c0 = time.perf_counter(), _cpu()
        summary = run(pipe, str(src), str(Path(tmp) / "out"), previews=previews, progress=False)
        dt, cpu = time.perf_counter() - t0, _cpu() - c0
    if summary.failed:
        raise RuntimeError(f"{summary.failed} photos failed in run()")
    out["run"] = _row(summary.written, dt, cpu, {k: v / 1000 * summary.written for k, v in summary.stage_ms().items()},
                      nets)
    return out


def measure_workers(size: int, passes: int, workers: int) -> float:
    """Wall-clock images/s of ``estimators.batch.run`` with ``workers`` processes over the photos (x ``passes``)."""
    from PIL import Image

    from difareli.estimators.batch import run

    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "in"
        src.mkdir()
        n = 0
        for r in range(passes):
            for i, img in enumerate(photos()):
                Image.fromarray(img).save(src / f"p{r}_{i}.png")
                n += 1
        pipe = _pipeline(size, str(src))
        t0 = time.perf_counter()  # worker start-up (imports, models) included: what a user waits for
        summary = run(pipe, str(src), str(Path(tmp) / "out"), previews=False, progress=False, workers=workers)
        return summary.written / (time.perf_counter() - t0)


def run_side(src: Path, size: int, passes: int, previews: bool) -> dict:
    """:func:`measure` in a fresh process importing the package from ``src``."""
    env = dict(os.environ, PYTHONPATH=str(src) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, __file__, "--worker", "--sizes", str(size), "--passes", str(passes)]
    cmd += ["--previews"] if previews else []
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


def median_row(rows: list[dict]) -> dict:
    """The median of each figure over the rounds."""
    keys = lambda part: list(dict.fromkeys(k for r in rows for k in r[part]))  # noqa: E731
    return {"images_per_s": statistics.median(r["images_per_s"] for r in rows),
            "ms_per_image": statistics.median(r["ms_per_image"] for r in rows),
            "cpu_ms_per_image": statistics.median(r["cpu_ms_per_image"] for r in rows),
            **{part: {k: statistics.median(r[part].get(k, 0.0) for r in rows) for k in keys(part)}
               for part in ("stages_ms", "networks_ms")}}


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def table(mode: str, before: list[dict] | None, after: list[dict]) -> str:
    """The side-by-side text table of one mode: stages, total, the networks inside them, images/s, the bound."""
    b, a = (median_row(before) if before else None), median_row(after)
    ratio = (lambda key: statistics.median(x[key] / y[key] for x, y in zip(before, after))) if before else None
    stages = list(dict.fromkeys([*(b or {}).get("stages_ms", {}), *a["stages_ms"]]))
    lines = [f"{mode}: {after[0]['images']} images per side and round, {len(after)} rounds",
             f"{'stage':<22}{'baseline ms':>13}{'this tree ms':>14}{'speed-up':>10}"]
    for s in stages:
        x, y = (b["stages_ms"].get(s) if b else None), a["stages_ms"].get(s)
        lines.append(f"{s:<22}{fmt(x):>13}{fmt(y):>14}{(f'{x / y:.1f}x' if x and y else '-'):>10}")
    up = f"{ratio('ms_per_image'):.2f}x" if ratio else "-"
    lines.append(f"{'wall per image':<22}{fmt(b and b['ms_per_image']):>13}{a['ms_per_image']:>14.1f}{up:>10}")
    up = f"{ratio('cpu_ms_per_image'):.2f}x" if ratio else "-"
    lines.append(f"{'CPU per image':<22}{fmt(b and b['cpu_ms_per_image']):>13}{a['cpu_ms_per_image']:>14.1f}{up:>10}")
    for s in NETWORKS:  # inside the stages above, not added to the total
        x, y = (b or {}).get("networks_ms", {}).get(s), a["networks_ms"].get(s)
        if x is not None or y is not None:
            lines.append(f"{'  ' + s:<22}{fmt(x):>13}{fmt(y):>14}  (within the stages)")
    ips = f"{b['images_per_s']:.2f}" if b else "-"
    lines.append(f"{'images/s':<22}{ips:>13}{a['images_per_s']:>14.2f}")
    if before:
        each = ", ".join(f"{x['ms_per_image'] / y['ms_per_image']:.2f}x" for x, y in zip(before, after))
        lines.append(f"each round's wall speed-up: {each}")
    for side, row in (("baseline", b), ("this tree", a)):
        floor = sum((row or {}).get("networks_ms", {}).values())
        if floor:
            lines.append(f"networks alone ({side}): {floor:.1f} ms per image, {1000 / floor:.1f} images/s; the wall "
                         f"time is {row['ms_per_image'] / floor:.2f}x that")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256])
    ap.add_argument("--rounds", type=int, default=3, help="interleaved baseline / this tree runs")
    ap.add_argument("--passes", type=int, default=4, help="passes over the six photos in each run")
    ap.add_argument("--baseline", default=BASELINE, help="git ref to compare with, or 'none'")
    ap.add_argument("--workers", type=int, default=0, help="also time this tree with this many worker processes")
    ap.add_argument("--previews", action="store_true", help="run() writes the previews (difareli-preprocess's default)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(measure(args.sizes[0], args.passes, args.previews)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        base_src = None if args.baseline == "none" else baseline_tree(args.baseline, Path(tmp))
        print(f"baseline: {args.baseline if base_src else 'none'}; this tree: {REPO}", flush=True)
        for size in args.sizes:
            before: list[dict] = []
            after: list[dict] = []
            for _ in range(args.rounds):
                if base_src:
                    before.append(run_side(base_src, size, args.passes, args.previews))
                after.append(run_side(REPO / "src", size, args.passes, args.previews))
            print(f"size {size} px")
            for mode in ("process", "run"):
                name = "run(), previews on" if mode == "run" and args.previews else f"{mode}()"
                print(table(name, [r[mode] for r in before] or None, [r[mode] for r in after]), flush=True)
            if args.workers > 1:
                ips = measure_workers(size, args.passes, args.workers)
                print(f"{'images/s, ' + str(args.workers) + ' workers':<22}{'':>13}{ips:>14.2f}"
                      "  (run(), start-up included)")


if __name__ == "__main__":
    main()
