"""Training throughput of the real ``DiffusionModule.training_step`` in a Lightning ``Trainer``.

Random SynthFaces-shaped batches (DiFaReli++ inputs; channel counts from ``difareli.encodings.channels``) go
through a DataLoader into ``Trainer.fit``; a callback times the steps after the warm-up ones, synchronising the
device at both ends. FLOPs of one training step (forward + backward of ``L_simple``, counted exactly with
``torch.utils.flop_counter.FlopCounterMode``; the AdamW update is not counted) give the achieved FLOP/s, reported
against the device's nominal peak (``difareli.runtime.peak_flops``). Each configuration runs in a fresh
subprocess so the peak memory (CPU resident set, or CUDA allocation) is its own.

    python scripts/bench_train.py                                   # CPU: tiny at 64 px, batch 16, fp32 and bf16
    python scripts/bench_train.py --device cuda                     # GPU: ffhq128 at 128 px, ffhq256 at 256 px
    python scripts/bench_train.py --configs tiny:64:16:32-true tiny:64:16:bf16-mixed --steps 10
"""

from __future__ import annotations

import argparse
import functools
import json
import subprocess
import sys
import tempfile
import time

import torch

CPU_DEFAULT = ["tiny:64:16:32-true", "tiny:64:16:bf16-mixed"]
GPU_DEFAULT = ["ffhq128:128:32:bf16-mixed", "ffhq128:128:32:32-true", "ffhq256:256:16:bf16-mixed"]


def build_module(preset: str, resolution: int, variant: str = "difareli_pp", compile: bool = False):
    """A ``DiffusionModule`` built as ``difareli-train`` builds it (the one place to adapt to its constructor):
    the variant's inputs from its ``conf/model`` file, their widths from the encoding registry."""
    from difareli.encodings import PRODUCER_DIMS, total_channels
    from difareli.lit import DiffusionModule
    from difareli.nn.presets import variant_inputs

    spatial, nonspatial = variant_inputs(variant)
    dims = {"H": resolution, "W": resolution, **PRODUCER_DIMS}
    input_dims = {"spatial_channels": total_channels(spatial, dims),
                  "nonspatial_dim": total_channels(nonspatial, dims), "resolution": resolution}
    # The optimizer as a callable partial: a config dict would need Hydra, which a bare GPU image lacks.
    return DiffusionModule(name=variant, preset=preset, spatial_inputs=spatial, nonspatial_inputs=nonspatial,
                           input_dims=input_dims, optimizer=functools.partial(torch.optim.AdamW, lr=1e-4),
                           compile=compile)


class RandomBatches(torch.utils.data.Dataset):
    """Items shaped like the DataModule's: image in [-1, 1], spatial [C, R, R], non-spatial [D] (seeded)."""

    def __init__(self, n: int, resolution: int, spatial_channels: int, nonspatial_dim: int):
        self.n, self.shapes = n, ((3, resolution, resolution), (spatial_channels, resolution, resolution),
                                  (nonspatial_dim,))

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        g = torch.Generator().manual_seed(i)
        image, spatial, nonspatial = (torch.rand(s, generator=g) for s in self.shapes)
        return {"image": image * 2 - 1, "spatial": spatial, "nonspatial": nonspatial}


def _timer_callback(warmup: int, device: torch.device):
    import lightning as L

    from difareli.runtime import Runtime

    runtime = Runtime(device=str(device))

    class StepTimer(L.Callback):
        """Wall time of the steps after ``warmup``, device synchronised at both ends."""

        start, seconds, steps = None, float("nan"), 0

        def on_train_batch_start(self, trainer, module, batch, batch_idx):
            if batch_idx == warmup:
                runtime.synchronize()
                self.start = time.perf_counter()

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            if self.start is not None:
                self.steps += 1
                runtime.synchronize()
                self.seconds = time.perf_counter() - self.start

    return StepTimer()


def train_step_flops(module, batch: dict) -> int:
    """FLOPs of one training step's forward and backward (counted on the module's device)."""
    from difareli.runtime import count_flops

    def step():
        module.diffusion_loss(batch).backward()

    flops = count_flops(step)
    module.zero_grad(set_to_none=True)
    return flops


def _channels_last(items: list[dict]) -> dict:
    """Default collation, then NHWC ("channels last") memory for the 4-D tensors."""
    batch = torch.utils.data.default_collate(items)
    return {k: v.contiguous(memory_format=torch.channels_last) if v.dim() == 4 else v for k, v in batch.items()}


def run_one(preset: str, res: int, batch: int, precision: str, device: str = "cpu", steps: int = 5,
            warmup: int = 2, variant: str = "difareli_pp", opts: str = "") -> dict:
    """Train ``warmup + steps`` steps through Lightning and time the last ``steps`` (in this process).

    ``opts``: comma-separated ``cl`` (channels-last network and batches), ``compile`` (torch.compile the network),
    ``t<N>`` (N intra-op threads)."""
    import resource

    import lightning as L

    from difareli.runtime import peak_flops

    dev = torch.device(device)
    flags = {o for o in opts.split(",") if o}
    for o in flags:
        if o.startswith("t") and o[1:].isdigit():
            torch.set_num_threads(int(o[1:]))
    L.seed_everything(0, verbose=False)
    module = build_module(preset, res, variant, compile="compile" in flags)
    if "cl" in flags:
        module.net.to(memory_format=torch.channels_last)
    dims = module.hparams.input_dims
    data = RandomBatches(batch * (warmup + steps), res, dims["spatial_channels"], dims["nonspatial_dim"])
    loader = torch.utils.data.DataLoader(data, batch_size=batch, num_workers=0,
                                         collate_fn=_channels_last if "cl" in flags else None)
    timer = _timer_callback(warmup, dev)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = L.Trainer(accelerator="gpu" if dev.type == "cuda" else "cpu", devices=[dev.index or 0]
                            if dev.type == "cuda" else 1, precision=precision, max_steps=warmup + steps,
                            logger=False, enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                            callbacks=[timer], default_root_dir=tmp)
        trainer.fit(module, train_dataloaders=loader)
    if timer.steps != steps:
        raise RuntimeError(f"timed {timer.steps} steps, expected {steps}")
    peak_mem = (torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda"
                else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    counted = build_module(preset, res, variant) if "compile" in flags else module  # eager: the same arithmetic
    flops = train_step_flops(counted.to(dev), {k: v.to(dev) for k, v in next(iter(loader)).items()})
    achieved = flops * steps / timer.seconds
    peak, peak_how = peak_flops(dev, "bf16" if "bf16" in precision else "fp32")
    return {"preset": preset, "res": res, "batch": batch, "precision": precision, "opts": opts or "-",
            "device": str(dev),
            "params_M": round(sum(p.numel() for p in module.parameters()) / 1e6, 2),
            "threads": torch.get_num_threads(), "steps": steps, "warmup": warmup,
            "images_per_s": round(batch * steps / timer.seconds, 2), "s_per_step": round(timer.seconds / steps, 4),
            "step_GFLOP": round(flops / 1e9, 2), "achieved_GFLOPs": round(achieved / 1e9, 2),
            "peak_GFLOPs": None if peak is None else round(peak / 1e9, 1),
            "utilisation": None if peak is None else round(achieved / peak, 4), "peak_source": peak_how,
            "peak_MiB": round(peak_mem, 1), "peak_kind": "cuda_allocated" if dev.type == "cuda" else "process_rss"}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--configs", nargs="*", help="preset:resolution:batch:precision[:opts] (precision: 32-true | "
                   "bf16-mixed; opts: comma-separated cl, compile, t<N> threads)")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one config and print JSON
    a = p.parse_args()
    if a.one:
        preset, res, batch, prec, *opts = a.one.split(":")
        print(json.dumps(run_one(preset, int(res), int(batch), prec, a.device, a.steps, a.warmup,
                                 opts=opts[0] if opts else "")))
        return
    configs = a.configs or (GPU_DEFAULT if a.device.startswith("cuda") else CPU_DEFAULT)
    for c in configs:
        if len(c.split(":")) not in (4, 5):
            sys.exit(f"--configs {c!r}: expected preset:resolution:batch:precision[:opts], e.g. tiny:64:16:bf16-mixed")
    cols = ["preset", "res", "batch", "precision", "opts", "params_M", "images_per_s", "s_per_step", "step_GFLOP",
            "achieved_GFLOPs", "peak_GFLOPs", "utilisation", "peak_MiB"]
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    rows = []
    for c in configs:
        proc = subprocess.run([sys.executable, __file__, "--one", c, "--device", a.device, "--steps", str(a.steps),
                               "--warmup", str(a.warmup)], capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"| {c} | failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode} |")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(r)
        print("| " + " | ".join(str(r[k]) for k in cols) + " |", flush=True)
    if rows:
        print(f"peak: {rows[0]['peak_source']}; threads: {rows[0]['threads']}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
