"""Seconds per relight of one checkpoint under several runtimes, side by side in one process.

    python scripts/bench_runtime.py --checkpoint <ckpt> --store <store> [--sampler unipc --steps 20]
        [--modes fp32 bf16 fp32+compile] [--repeats 3] [--records 2]

Each mode is a :class:`difareli.runtime.core.Runtime`; every relight goes through
:class:`difareli.relight.relighter.Relighter` (the record read, inversion + mean-matching self-decode + decode of one
target, the inversion cache cleared each time), after one untimed warm-up per mode (compilation, allocation), modes
interleaved within each repeat. Prints the median seconds and the largest pixel difference against fp32 (uint8
levels), so a faster mode that changes the picture is visible.
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np
import torch

from difareli.lighting import sh
from difareli.diffusion.spec import SamplerSpec
from difareli.lit import load_checkpoint
from difareli.relight.relighter import Relighter
from difareli.runtime.core import Runtime
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--store", required=True)
    p.add_argument("--sampler", default="unipc")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--modes", nargs="+", default=["fp32", "bf16", "fp32+compile"],
                   help="runtime modes, <precision>[+compile][+cuda_graphs] (Runtime.from_mode)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--records", type=int, default=2)
    p.add_argument("--device", default="auto")
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    store = EncodingStore.open(args.store)
    ids = (store.ids(split="test") or store.ids())[: args.records]
    spec = SamplerSpec.preset(args.sampler, steps=args.steps)
    ckpt = load_checkpoint(args.checkpoint)
    relighters, targets = {}, {}
    for mode in args.modes:
        r = Relighter(ckpt, spec, runtime=Runtime.from_mode(mode, args.device))
        targets = targets or {rid: Targets.of(sh.yaw(np.asarray(r.source(store, rid).arrays["light"], np.float64),
                                                     60.0))
                              for rid in ids}
        r.relight(r.source(store, ids[0]), targets[ids[0]])  # warm-up: compile, allocate
        relighters[mode] = r
    # Interleaved (every repeat runs every mode) so that load from other processes hits all modes alike.
    secs = {m: [] for m in args.modes}
    outs = {m: {} for m in args.modes}
    for _ in range(args.repeats):
        for rid in ids:
            for mode, r in relighters.items():
                r._inversions.clear()  # time the whole relight, inversion included
                with r.runtime.timed() as timer:  # the device synchronised at both ends; the record read inside
                    outs[mode][rid] = r.relight(r.source(store, rid), targets[rid])
                secs[mode].append(timer.seconds)
    ref = outs[args.modes[0]]
    results = {m: (statistics.median(secs[m]), min(secs[m]),
                   max(int(np.abs(outs[m][k].astype(int) - ref[k].astype(int)).max()) for k in ids))
               for m in args.modes}
    print(f"{args.checkpoint}: {args.sampler}-{args.steps}, {len(ids)} record(s) x {args.repeats}, "
          f"device {Runtime(device=args.device).torch_device}, torch threads {torch.get_num_threads()}")
    print(f"| mode | s/relight (median) | min | max pixel diff vs {args.modes[0]} (of 255) |")
    print("|---|---|---|---|")
    for mode, (med, low, diff) in results.items():
        print(f"| {mode} | {med:.3f} | {low:.3f} | {diff} |")


if __name__ == "__main__":
    main()
