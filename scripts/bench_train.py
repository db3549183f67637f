"""Training throughput of the real ``DiffusionModule.training_step`` in a Lightning ``Trainer``.

A thin entry point of :func:`difareli.perf.measure.train_throughput`: random SynthFaces-shaped batches (the inputs of a
``conf/model`` variant, DiFaReli++ by default; widths from the encoding registry) go through a DataLoader into
``Trainer.fit``; a callback times the steps after the warm-up ones, synchronising the device at both ends. FLOPs
of one training step (forward + backward of ``L_simple``, counted exactly with
``torch.utils.flop_counter.FlopCounterMode``; the AdamW update is not counted) give the achieved FLOP/s, reported
against the device's nominal peak (``difareli.hardware.peak_flops``) and against a large dense matmul measured in the
same process (``gemm_GFLOPs``, :func:`difareli.perf.measure.gemm_ceiling`: ``of_gemm`` is the step's share of it,
``gemm_of_peak`` the matmul's share of the nominal peak, i.e. the most any network can reach here). Each
configuration runs in a fresh subprocess so the peak memory (CPU resident set, or CUDA allocation) is its own.

    python scripts/bench_train.py                                   # CPU: tiny at 64 px, batch 16, fp32 and bf16
    python scripts/bench_train.py --device cuda                     # GPU: ffhq128 at 128 px, ffhq256 at 256 px
    python scripts/bench_train.py --configs tiny:64:16:32-true tiny:64:16:bf16-mixed --steps 10
    python scripts/bench_train.py --variant mechanism/cn_ca         # any conf/model variant
    python scripts/bench_train.py --profile --configs tiny:64:16:bf16-mixed tiny:64:16:bf16-mixed:cl   # where time goes
    python scripts/bench_train.py --configs tiny:64:16:bf16-mixed tiny:64:16:bf16-mixed:compile --rounds 3 \
        --steps 20 --warmup 5      # the eager step and the compiled one side by side, interleaved, medians

``--rounds R`` runs the configs in turn R times (a, b, a, b, ...), each in a fresh process, and ends with each
config's median images/s and share of the matmul ceiling, and each config's speed-up over the first one: on a
shared machine only such interleaved medians compare.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from difareli.perf.measure import DEFAULT_VARIANT, train_throughput

CPU_DEFAULT = ["tiny:64:16:32-true", "tiny:64:16:bf16-mixed"]
GPU_DEFAULT = ["ffhq128:128:32:bf16-mixed", "ffhq128:128:32:32-true", "ffhq256:256:16:bf16-mixed"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--configs", nargs="*", help="preset:resolution:batch:precision[:opts] (precision: 32-true | "
                   "bf16-mixed; opts: comma-separated cl, compile, t<N> threads)")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--variant", default=DEFAULT_VARIANT, help="conf/model variant (e.g. difareli, mechanism/cn_ca)")
    p.add_argument("--rounds", type=int, default=1, help="run the configs in turn this many times (interleaved)")
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.add_argument("--profile", action="store_true", help="CPU: where each config's step time goes (torch.profiler "
                   "self time by category: convolution, GroupNorm/AdaGN, attention, MLPs, casts, optimizer, ...)")
    p.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one config and print JSON
    a = p.parse_args()
    if a.profile:
        return profile(a.configs or CPU_DEFAULT, a.variant, a.steps, a.warmup)
    if a.one:
        preset, res, batch, prec, *opts = a.one.split(":")
        print(json.dumps(train_throughput(preset, int(res), int(batch), prec, a.device, a.steps, a.warmup,
                                          variant=a.variant, opts=opts[0] if opts else "")))
        return
    configs = a.configs or (GPU_DEFAULT if a.device.startswith("cuda") else CPU_DEFAULT)
    for c in configs:
        if len(c.split(":")) not in (4, 5):
            sys.exit(f"--configs {c!r}: expected preset:resolution:batch:precision[:opts], e.g. tiny:64:16:bf16-mixed")
    cols = ["preset", "res", "batch", "precision", "opts", "params_M", "images_per_s", "s_per_step", "step_GFLOP",
            "achieved_GFLOPs", "peak_GFLOPs", "utilisation", "gemm_GFLOPs", "of_gemm", "gemm_of_peak", "peak_MiB"]
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    rows = []
    for c in [c for _ in range(max(1, a.rounds)) for c in configs]:
        proc = subprocess.run([sys.executable, __file__, "--one", c, "--device", a.device, "--steps", str(a.steps),
                               "--warmup", str(a.warmup), "--variant", a.variant], capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"| {c} | failed: "
                  f"{proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode} |")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(r)
        print("| " + " | ".join(str(r[k]) for k in cols) + " |", flush=True)
    if rows:
        print(f"peak: {rows[0]['peak_source']}; threads: {rows[0]['threads']}")
    if a.rounds > 1 and rows:
        summary(rows)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


def summary(rows: list[dict]) -> None:
    """Each config's median images/s and share of the matmul ceiling over the rounds, and its speed-up over the
    first config's median."""
    import statistics

    keys = list(dict.fromkeys((r["preset"], r["res"], r["batch"], r["precision"], r["opts"]) for r in rows))
    med = {k: statistics.median(r["images_per_s"] for r in rows if (r["preset"], r["res"], r["batch"],
                                                                     r["precision"], r["opts"]) == k) for k in keys}
    print("\n| config | rounds | median images/s | median of_gemm | speed-up over the first |\n|---|---|---|---|---|")
    for k in keys:
        mine = [r for r in rows if (r["preset"], r["res"], r["batch"], r["precision"], r["opts"]) == k]
        print(f"| {':'.join(map(str, k))} | {len(mine)} | {med[k]:.2f} | "
              f"{statistics.median(r['of_gemm'] for r in mine):.3f} | {med[k] / med[keys[0]]:.2f}x |")


def profile(configs: list[str], variant: str, steps: int, warmup: int) -> None:
    """One table: seconds per step and the share of each category, a column per config."""
    from difareli.perf.measure import profile_train_step

    cols = {}
    for c in configs:
        preset, res, batch, prec, *opts = c.split(":")
        cols[c] = profile_train_step(preset, int(res), int(batch), prec, steps, warmup, variant,
                                     opts[0] if opts else "")
    print("| where the step's time goes (self CPU time, torch.profiler) | " + " | ".join(cols) + " |")
    print("|---|" + "---:|" * len(cols))
    print("| wall s/step (under the profiler) | " + " | ".join(f"{v.step:.3f}" for v in cols.values()) + " |")
    for cat in next(iter(cols.values())).seconds:
        print(f"| {cat} | " + " | ".join(f"{v.seconds[cat]:.3f} s ({100 * v.seconds[cat] / v.total:.0f}%)"
                                      for v in cols.values()) + " |")
    # The convolutions' own rate against the matmul measured here, and the most that anything outside them can give.
    print("| convolutions' FLOPs over their time, GFLOP/s (of the matmul measured here) | " + " | ".join(
        f"{v.conv_gflops:.0f} ({v.conv_gflops / v.gemm_gflops:.2f} of {v.gemm_gflops:.0f})"
        for v in cols.values()) + " |")
    print("| the step's speed-up if all but the convolutions took no time | " + " | ".join(
        f"{v.total / v.seconds['convolution']:.2f}x" for v in cols.values()) + " |")


if __name__ == "__main__":
    main()
