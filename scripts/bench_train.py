"""Training throughput (images/s) and peak memory per preset and batch size.

Each configuration runs in a fresh subprocess, so the peak resident memory (CPU) or peak CUDA allocation (GPU)
is that configuration's alone. Synthetic batches with the DiFaReli++ input sizes (18 spatial channels: shading
3 + shadow map 1 + masks 14; 184 non-spatial: shape 53 + cam 3 + identity 128); data loading is excluded.

    python scripts/bench_train.py                       # CPU: tiny at 64 px, batch 8/16/32; ffhq128 at 64 px
    python scripts/bench_train.py --device cuda         # GPU: ffhq128 at 128 px batch 32 bf16, ffhq256 batch 20
    python scripts/bench_train.py --configs tiny:64:16:32-true
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

CPU_DEFAULT = ["tiny:64:8:32-true", "tiny:64:16:32-true", "tiny:64:32:32-true", "ffhq128:64:8:32-true"]
GPU_DEFAULT = ["tiny:64:32:bf16-mixed", "ffhq128:128:32:bf16-mixed", "ffhq128:128:32:32-true",
               "ffhq256:256:20:bf16-mixed"]


def run_one(preset: str, res: int, batch: int, precision: str, device: str, steps: int, warmup: int) -> dict:
    """Time ``steps`` optimizer steps after ``warmup`` (in this process)."""
    import resource

    import torch

    from difareli.diffusion.schedule import DiffusionSchedule
    from difareli.nn import build_network

    torch.manual_seed(0)
    dev = torch.device(device)
    net = build_network(preset, "modulator", spatial_channels=18, nonspatial_dim=184,
                        overrides={"image_size": res}).to(dev)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, weight_decay=0.0)
    sched = DiffusionSchedule()
    x0 = torch.rand(batch, 3, res, res, device=dev) * 2 - 1
    spatial = torch.randn(batch, 18, res, res, device=dev)
    ns = torch.randn(batch, 184, device=dev)
    autocast = torch.autocast(dev.type, dtype=torch.bfloat16, enabled=precision == "bf16-mixed")

    def step():
        t = torch.randint(0, sched.T, (batch,), device=dev)
        noise = torch.randn_like(x0)
        with autocast:
            eps = net(sched.q_sample(x0, t, noise), t, net.condition(spatial, ns))
            loss = torch.nn.functional.mse_loss(eps.float(), noise)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(warmup):
        step()
    if dev.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    for _ in range(steps):
        step()
    if dev.type == "cuda":
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    peak = (torch.cuda.max_memory_allocated() / 2**20 if dev.type == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return {"preset": preset, "res": res, "batch": batch, "precision": precision, "device": device,
            "params_M": round(sum(p.numel() for p in net.parameters()) / 1e6, 2), "threads": torch.get_num_threads(),
            "images_per_s": round(batch * steps / elapsed, 2), "s_per_step": round(elapsed / steps, 4),
            "peak_MiB": round(peak, 1), "peak_kind": "cuda_allocated" if dev.type == "cuda" else "process_rss"}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--configs", nargs="*", help="preset:resolution:batch:precision")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one config and print JSON
    a = p.parse_args()
    if a.one:
        preset, res, batch, prec = a.one.split(":")
        print(json.dumps(run_one(preset, int(res), int(batch), prec, a.device, a.steps, a.warmup)))
        return
    configs = a.configs or (GPU_DEFAULT if a.device.startswith("cuda") else CPU_DEFAULT)
    cols = ["preset", "res", "batch", "precision", "params_M", "images_per_s", "s_per_step", "peak_MiB", "peak_kind"]
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for c in configs:
        proc = subprocess.run([sys.executable, __file__, "--one", c, "--device", a.device, "--steps", str(a.steps),
                               "--warmup", str(a.warmup)], capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"| {c} | failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode} |")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        print("| " + " | ".join(str(r[k]) for k in cols) + " |", flush=True)


if __name__ == "__main__":
    main()
