#!/usr/bin/env python
"""SynthFaces v2 report: v1 (realism=lambertian) vs v2 (realism=full) through the real CLIs, plus the preview.

    python scripts/synth_v2_report.py --work /tmp/synth_v2 [--subjects 250 --lights 4 --resolution 64 --limit 120]

Steps (each skipped when its output exists, so a rerun resumes):
1. ``difareli-synth`` both presets (``inputs=estimated_light``, the v2 inputs, in both, so only the appearance effects
   differ);
2. ``difareli-benchmark -m method=identity,lambertian,oracle`` and ``method=lambertian oracle_light=true`` on each;
3. ``difareli-table`` per store;
4. the face-pixel energy shares of the effect terms (record meta ``energy``) and the light-fit errors;
5. ``--speed``: images/s of both presets at 64 and 256 px (small extra stores).
Writes ``docs/synthfaces_v2/{table.md,effects_preview.png}`` (``--docs``).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

PRESETS = {"v1": "lambertian", "v2": "full"}


def cli(module: str, *args: str) -> str:
    """Run ``python -m difareli.cli.<module> args`` (the console script's code), echo and return stdout."""
    cmd = [sys.executable, "-m", f"difareli.cli.{module}", *args]
    print("$", " ".join(cmd[2:]), flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    print(proc.stdout[-1500:], flush=True)
    if proc.returncode:
        raise SystemExit(f"{module} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc.stdout


def synth(out_dir: Path, preset: str, subjects: int, lights: int, res: int, workers: int,
          preview: bool = True) -> float | None:
    out = cli("synth", f"out_dir={out_dir}", f"subjects={subjects}", f"lights={lights}", f"resolution={res}",
              f"realism={preset}", "inputs=estimated_light", f"workers={workers}",
              f"preview.enabled={str(preview).lower()}")
    m = re.search(r"\(([\d.]+) images/s", out)
    return float(m.group(1)) if m else None


def benchmark(store: Path, out: Path, limit: int) -> list[Path]:
    common = [f"store={store}", f"limit={limit}", "save_images=false", "progress=false"]
    if not all((out / m / "metrics_per_image.csv").is_file() for m in ("identity", "lambertian", "oracle")):
        cli("benchmark", "-m", *common, "method=identity,lambertian,oracle", f"out_dir={out}/${{method.kind}}",
            f"hydra.sweep.dir={out}/multirun")
    if not (out / "lambertian_gt" / "metrics_per_image.csv").is_file():
        cli("benchmark", *common, "method=lambertian", "oracle_light=true", f"out_dir={out}/lambertian_gt",
            f"hydra.run.dir={out}/lambertian_gt")
    return [out / m for m in ("identity", "lambertian", "lambertian_gt", "oracle")]


def energy_shares(store: Path) -> dict[str, tuple[float, float]]:
    """Mean and standard error over records of each effect's share of face-pixel energy (meta ``energy``)."""
    rows = [json.loads(p.read_text())["energy"] for p in sorted((store / "records").glob("*/meta.json"))]
    out = {}
    for k in rows[0]:
        v = np.array([r[k] for r in rows])
        out[k] = (float(v.mean()), float(v.std(ddof=1) / np.sqrt(len(v))))
    return out


def light_errors(run: Path) -> dict[str, float]:
    with open(run / "light_estimation.csv") as f:
        rows = list(csv.DictReader(f))
    out = {}
    for which in ("target", "source"):
        r = [row for row in rows if row["light"] == which]
        if r:
            out[which] = (float(np.mean([float(x["rel_error"]) for x in r])),
                          float(np.mean([float(x["rel_error_gain_free"]) for x in r])))
    return out


def effects_preview(path: Path, subjects=(0, 1, 2, 3), light=1, res: int = 64, cell: int = 128) -> Path:
    """Rows: subjects; columns: v1, each effect alone on, all on, and 4x |full - v1|."""
    from difareli.synth.config import SynthConfig
    from difareli.synth.generator import render_records
    from difareli.synth.preview import _upscale
    from difareli.utils.viz import grid, save_png

    variants = [("v1", {}), ("specular", {"specular": True}), ("subsurface", {"subsurface": True}),
                ("ambient occlusion", {"ambient_occlusion": True}), ("multi-sun", {"multi_sun": True})]
    rows = []
    for k in subjects:
        cells = []
        for _, eff in variants:
            cfg = SynthConfig(subjects=max(subjects) + 1, lights=light + 1, resolution=res, realism="lambertian",
                              effects=eff, inputs="exact")
            cells.append(next(render_records(k, [light], cfg, "test"))[1]["image"])
        full = SynthConfig(subjects=max(subjects) + 1, lights=light + 1, resolution=res, realism="full", inputs="exact")
        cells.append(next(render_records(k, [light], full, "test"))[1]["image"])
        diff = np.clip(4 * np.abs(cells[-1].astype(int) - cells[0].astype(int)), 0, 255).astype(np.uint8)
        rows.append([_upscale(c, cell) for c in cells + [diff]])
    return save_png(grid(rows, pad=2), path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--work", required=True, help="folder for the stores and benchmark runs")
    ap.add_argument("--subjects", type=int, default=250)
    ap.add_argument("--lights", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--limit", type=int, default=120, help="pairs per protocol (evenly spaced)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--speed", action="store_true", help="also time both presets at 64 and 256 px")
    ap.add_argument("--docs", default="docs/synthfaces_v2", help="where table.md and the preview go")
    args = ap.parse_args(argv)
    work, docs = Path(args.work), Path(args.docs)
    docs.mkdir(parents=True, exist_ok=True)
    lines = ["# SynthFaces v1 vs v2 (generated by scripts/synth_v2_report.py)", "",
             f"{args.subjects} subjects x {args.lights} lights at {args.resolution} px, seed 0; "
             f"{args.limit} pairs per protocol; inputs=estimated_light (v2) in both stores.", ""]
    speeds = {}
    for tag, preset in PRESETS.items():
        store = work / f"{tag}_{preset}_{args.resolution}"
        ips = synth(store, preset, args.subjects, args.lights, args.resolution, args.workers)
        if ips:
            speeds[(preset, args.resolution, args.subjects * args.lights)] = ips
        runs = benchmark(store, work / f"bench_{tag}", args.limit)
        table_out = work / f"table_{tag}"
        cli("table", "runs=[" + ",".join(str(r) for r in runs) + "]", f"out={table_out}",
            f"caption='SynthFaces {tag}, realism {preset}'", f"hydra.run.dir={table_out}")
        lines += [f"## {tag}: realism={preset}", "", (table_out / "table.md").read_text().strip(), ""]
        en = energy_shares(store)
        lines += ["Share of face-pixel energy (mean ± SE over all records): " + ", ".join(
            f"{k} {m:.4f} ± {se:.4f}" for k, (m, se) in en.items()), ""]
        le = light_errors(runs[1])
        lines += ["Light fit (lambertian run, relative irradiance error / after best gain): " + ", ".join(
            f"{k} {a:.3f} / {b:.3f}" for k, (a, b) in le.items()), ""]
    if args.speed:
        for res, subjects in ((64, 40), (256, 10)):
            for preset in PRESETS.values():
                store = work / f"speed_{preset}_{res}"
                speeds[(preset, res, subjects * 4)] = synth(store, preset, subjects, 4, res, args.workers,
                                                            preview=False)
    if speeds:
        lines += ["## Generation speed (images/s as difareli-synth prints it; shared, loaded 2-core CPU)", "",
                  "| preset | resolution | images | images/s |", "|---|---:|---:|---:|"]
        lines += [f"| {p} | {r} | {n} | {v:.2f} |" for (p, r, n), v in sorted(speeds.items()) if v]
        lines.append("")
    (docs / "table.md").write_text("\n".join(lines) + "\n")
    effects_preview(docs / "effects_preview.png")
    print(f"wrote {docs / 'table.md'} and {docs / 'effects_preview.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
