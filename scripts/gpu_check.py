"""GPU readiness report: UNet ms per pass, model FLOPs and MFU, relight seconds, a batched rotation, training images/s.

    bash scripts/gpu_check.sh            # CUDA: ffhq128 at 128 px and ffhq256 at 256 px, DDIM-1000 relight (< 8 min)
    bash scripts/gpu_check.sh --small    # toy sizes (automatic without CUDA): tiny at 32 px, a few steps (CI)

Writes ``gpu_check.json`` and ``gpu_check.md`` to ``$OUT`` when set, else to ``docs/perf/``. Networks are untrained
(timing only: zero-initialised layers cost the same); the rotation's 60 target conditions are random. MFU is the
achieved FLOP/s against the card's dense bf16 peak (``difareli.runtime.core.GPU_BF16_PEAK``), for every mode. Stages run
in order of importance; the compile modes come last and are skipped (and listed) when the time budget runs out.
Imports avoid hydra/omegaconf/kornia/trimesh/wandb (absent on GPU images): they are blocked below so CI proves it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

for _m in ("hydra", "omegaconf", "kornia", "trimesh", "embreex", "rtree", "wandb", "batch_face"):
    sys.modules.setdefault(_m, None)  # an import of these now fails here exactly as on a GPU image

import torch  # noqa: E402

from difareli.perf import measure as perf  # noqa: E402
from difareli.diffusion.relight import SamplerSpec  # noqa: E402
from difareli.relight.core import invert_image, relight  # noqa: E402
from difareli.hardware import peak_flops  # noqa: E402
from difareli.runtime.core import Runtime, count_flops  # noqa: E402

# Runtime modes (Runtime.from_mode): each name says its precision.
MODES = ("fp32", "bf16", "bf16+cuda_graphs", "bf16+compile", "bf16+compile+cuda_graphs")
STAGES = ("unet", "relight", "train")
FULL = dict(sizes=[("ffhq128", 128), ("ffhq256", 256)], batches=[1, 16], iters={1: 20, 16: 5}, warmup=3,
            relight=("ffhq256", 256), ddim_steps=1000, unipc_steps=20, frames=60,
            train=dict(preset="ffhq128", res=128, batch=32, precision="bf16-mixed", steps=10, warmup=3),
            modes=list(MODES), compile_estimate_s=120)
SMALL = dict(sizes=[("tiny", 32)], batches=[1, 2], iters={1: 3, 2: 2}, warmup=1, relight=("tiny", 32), ddim_steps=4,
             unipc_steps=3, frames=3, train=dict(preset="tiny", res=32, batch=2, precision="bf16-mixed", steps=1,
                                                 warmup=1), modes=["fp32", "bf16", "bf16+cuda_graphs"],
             compile_estimate_s=300)


def untrained(preset: str, res: int, device: torch.device):
    """An untrained DiFaReli++ (its conf/model file, read without Hydra) in eval mode: a Relightable model whose
    ``net`` is the network timed pass by pass."""
    return perf.untrained_model(perf.DEFAULT_VARIANT, preset, res, device)[0]


def inputs(model, batch: int, res: int, device: torch.device):
    """Random (spatial, nonspatial) condition inputs of a batch (seeded with the batch size)."""
    return perf.random_condition(model, batch, res, device, seed=batch)


def unet_ms(model, rt: Runtime, batch: int, res: int, iters: int, warmup: int) -> tuple[float, float]:
    """``(ms per denoiser pass, seconds of warm-up incl. compile / graph capture)``."""
    net = model.net
    cond = net.condition(*inputs(model, batch, res, rt.torch_device))
    den = rt.denoiser(net, cond)
    x = torch.randn(batch, 3, res, res, device=rt.torch_device)
    t = torch.full((batch,), 500, dtype=torch.long, device=rt.torch_device)
    with torch.no_grad():
        with rt.timed() as setup:
            for _ in range(warmup):
                den(x, t)
        with rt.timed() as run:
            for _ in range(iters):
                den(x, t)
    return run.seconds / iters * 1e3, setup.seconds


def relight_s(model, rt: Runtime, spec: SamplerSpec, res: int, targets: int) -> dict:
    """Seconds of a relight through the relighting core: Modulator + inversion + mean-matching self-decode
    (batch 1), then Modulator + one batched decode of ``targets`` conditions."""
    dev = rt.torch_device
    x0 = torch.rand(1, 3, res, res, device=dev) * 2 - 1
    src, tgt = inputs(model, 1, res, dev), inputs(model, targets, res, dev)
    with rt.timed() as t_inv:
        inv = invert_image(model, x0, src, spec, runtime=rt)
    with rt.timed() as t_dec:
        out = relight(model, x0, src, tgt, spec, runtime=rt, inversion=inv)
    if not torch.isfinite(out).all():
        raise FloatingPointError(f"{spec.name}-{spec.steps} relight produced non-finite pixels")
    return {"sampler": spec.name, "steps": spec.steps, "targets": targets, "passes": 3 * spec.steps,
            "invert_s": t_inv.seconds, "decode_s": t_dec.seconds, "seconds": t_inv.seconds + t_dec.seconds}


def check(args) -> dict:
    dev = torch.device("cuda" if torch.cuda.is_available() and not args.cpu else "cpu")
    small = args.small or dev.type != "cuda"
    plan = dict(SMALL if small else FULL)
    if args.sizes:
        plan["sizes"] = [(p, int(r)) for p, r in (s.split(":") for s in args.sizes)]
    if args.batches:
        plan["batches"] = args.batches
        plan["iters"] = {b: plan["iters"].get(b, max(2, 40 // b)) for b in args.batches}
    modes = args.modes or plan["modes"]
    stages = args.stages or STAGES
    start = time.perf_counter()
    left = lambda: args.budget - (time.perf_counter() - start)  # noqa: E731
    peak, peak_how = peak_flops(dev, "bf16")
    report = {"env": {"device": str(dev), "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda"
                      else _cpu_name(), "torch": torch.__version__,
                      "cuda": torch.version.cuda, "python": platform.python_version(), "small": small,
                      "threads": torch.get_num_threads(), "peak_bf16_TFLOPs": None if peak is None else peak / 1e12,
                      "peak_source": peak_how, "cudnn_benchmark": torch.backends.cudnn.benchmark,
                      "modes": list(modes), "cuda_graphs_active": dev.type == "cuda"},
              "flops": [], "unet": [], "relight": {}, "train": None, "skipped": []}
    models = {}
    for preset, res in plan["sizes"]:  # ------------------------------------------- FLOPs, then eager/graph modes
        module = models[(preset, res)] = untrained(preset, res, dev)
        net = module.net
        sp, ns = inputs(module, 1, res, dev)
        with torch.no_grad():
            cond = net.condition(sp, ns)
            x, t = torch.randn(1, 3, res, res, device=dev), torch.full((1,), 500, device=dev)
            unet = count_flops(net, x, t, cond)
            mod = count_flops(net.condition, sp, ns)
        report["flops"].append({"preset": preset, "resolution": res, "unet_pass_GFLOP": unet / 1e9,
                                "modulator_GFLOP": mod / 1e9,
                                "params_M": sum(p.numel() for p in net.parameters()) / 1e6})
    eager = [m for m in modes if "compile" not in m]
    if "unet" in stages:
        unet_modes(report, plan, models, dev, eager, peak, left)
    if "relight" in stages:
        relights(report, plan, dev, modes)  # before compiling: compiles may use up the budget
    if "train" in stages:
        train(report, plan, dev)
    if "unet" in stages:
        unet_modes(report, plan, models, dev, [m for m in modes if m not in eager], peak, left)
    report["env"]["wall_s"] = time.perf_counter() - start
    return report


def unet_modes(report: dict, plan: dict, models: dict, dev: torch.device, modes: list, peak, left) -> None:
    """ms per UNet pass of every size x batch x mode; compile modes only while the budget lasts."""
    for mode in modes:
        for (preset, res), module in models.items():
            gflop = next(f["unet_pass_GFLOP"] for f in report["flops"] if f["resolution"] == res)
            for b in plan["batches"]:
                if "compile" in mode and left() < plan["compile_estimate_s"]:
                    report["skipped"].append(f"unet {mode} {preset}@{res} batch {b}: {left():.0f} s of budget left")
                    continue
                ms, setup = unet_ms(module, Runtime.from_mode(mode, str(dev)), b, res, plan["iters"][b],
                                    plan["warmup"])
                tflops = gflop * b / ms  # GFLOP per ms = TFLOP/s
                report["unet"].append({"preset": preset, "resolution": res, "batch": b, "mode": mode,
                                       "ms_per_pass": ms, "setup_s": setup, "TFLOPs": tflops,
                                       "mfu": None if peak is None else tflops * 1e12 / peak})


def relights(report: dict, plan: dict, dev: torch.device, modes: list) -> None:
    preset, res = plan["relight"]
    module = untrained(preset, res, dev)
    best = "bf16+cuda_graphs" if "bf16+cuda_graphs" in modes and dev.type == "cuda" else "bf16"
    rt_best = Runtime.from_mode(best, str(dev))
    warm = SamplerSpec(name="ddim", steps=2)
    unipc = SamplerSpec(name="unipc", steps=plan["unipc_steps"], options=(("order", 2),))
    relight_s(module, rt_best, warm, res, 1)  # graph capture / first-call costs out of the timed runs
    rows = []
    for mode in [m for m in ("fp32", "bf16", "bf16+cuda_graphs") if m in modes]:
        rt = Runtime.from_mode(mode, str(dev))
        relight_s(module, rt, warm, res, 1)
        rows.append({"mode": mode, **relight_s(module, rt, unipc, res, 1)})
    report["relight"] = {"preset": preset, "resolution": res, "unipc": rows}
    ddim = SamplerSpec(name="ddim", steps=plan["ddim_steps"])
    report["relight"]["ddim"] = {"mode": best, **relight_s(module, rt_best, ddim, res, 1)}
    relight_s(module, rt_best, warm, res, plan["frames"])  # capture the batch-of-frames graph
    rot = relight_s(module, rt_best, unipc, res, plan["frames"])
    report["relight"]["rotation"] = {"mode": best, **rot, "frames_per_s_decode": plan["frames"] / rot["decode_s"]}


def train(report: dict, plan: dict, dev: torch.device) -> None:
    tr = plan["train"]
    report["train"] = perf.train_throughput(tr["preset"], tr["res"], tr["batch"], tr["precision"], str(dev),
                                            steps=tr["steps"], warmup=tr["warmup"])


def markdown(r: dict) -> str:
    e = r["env"]
    lines = [f"# GPU check: {e['device_name']} ({e['device']})", "",
             f"torch {e['torch']}, CUDA {e['cuda']}, Python {e['python']}, small={e['small']}, "
             f"wall {e['wall_s']:.0f} s; peak bf16 {e['peak_bf16_TFLOPs']} TFLOP/s ({e['peak_source']}). "
             "Untrained networks (timing only)."
             + ("" if e["cuda_graphs_active"] else " No CUDA: the cuda_graphs mode ran eagerly.") + "", "",
             "## Model FLOPs (FlopCounterMode, 2 per multiply-add, batch 1)", "",
             "| preset | px | UNet pass GFLOP | Modulator GFLOP | params M |", "|---|---|---|---|---|"]
    lines += [f"| {f['preset']} | {f['resolution']} | {f['unet_pass_GFLOP']:.1f} | {f['modulator_GFLOP']:.1f} | "
              f"{f['params_M']:.1f} |" for f in r["flops"]]
    lines += ["", "## UNet pass (denoiser with a prepared condition)", "",
              "| preset | px | batch | mode | ms/pass | warm-up s | TFLOP/s | MFU |",
              "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {u['preset']} | {u['resolution']} | {u['batch']} | {u['mode']} | {u['ms_per_pass']:.2f} | "
              f"{u['setup_s']:.1f} | {u['TFLOPs']:.3g} | {_percent(u['mfu'])} |"
              for u in r["unet"]]
    rl = r["relight"]
    if rl:
        lines += ["", f"## Relights at {rl['resolution']} px ({rl['preset']}; invert + self-decode + decode)", "",
                  "| what | mode | passes | targets | invert s | decode s | total s |", "|---|---|---|---|---|---|---|"]
        for name, row in [(f"unipc-{u['steps']}", u) for u in rl["unipc"]] + [
                (f"ddim-{rl['ddim']['steps']}", rl["ddim"]),
                (f"rotation unipc-{rl['rotation']['steps']}", rl["rotation"])]:
            lines.append(f"| {name} | {row['mode']} | {row['passes']} | {row['targets']} | {row['invert_s']:.2f} | "
                         f"{row['decode_s']:.2f} | {row['seconds']:.2f} |")
    if r["train"]:
        t = r["train"]
        lines += ["", "## Training (difareli.perf.measure.train_throughput: Lightning Trainer, real training_step)", "",
                  f"{t['preset']} at {t['res']} px, batch {t['batch']}, {t['precision']}: **{t['images_per_s']} "
                  f"images/s**, {t['step_GFLOP']} GFLOP/step (fwd+bwd), {t['achieved_GFLOPs']} GFLOP/s achieved, "
                  f"utilisation {t['utilisation']} of {t['peak_source']}; peak memory {t['peak_MiB']} MiB."]
    if r["skipped"]:
        lines += ["", "## Skipped (time budget)", ""] + [f"- {s}" for s in r["skipped"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--small", action="store_true", help="toy sizes (automatic without CUDA)")
    p.add_argument("--cpu", action="store_true", help="run on the CPU even when CUDA is available")
    p.add_argument("--modes", nargs="*", choices=MODES, help=f"default: all on CUDA, {SMALL['modes']} small")
    p.add_argument("--budget", type=float, default=400.0, help="seconds; compile modes are skipped past it")
    p.add_argument("--sizes", nargs="*", help="preset:resolution pairs replacing the plan's (e.g. tiny:64)")
    p.add_argument("--batches", nargs="*", type=int, help="UNet batch sizes replacing the plan's")
    p.add_argument("--stages", nargs="*", choices=STAGES, help="stages to run (default: all)")
    p.add_argument("--out", help="output folder (default: $OUT, else docs/perf)")
    args = p.parse_args()
    out = Path(args.out or os.environ.get("OUT") or Path(__file__).resolve().parents[1] / "docs" / "perf")
    report = check(args)
    bad = [k for k, v in _numbers(report) if not (math.isfinite(v) and v >= 0)]
    out.mkdir(parents=True, exist_ok=True)
    (out / "gpu_check.json").write_text(json.dumps(report, indent=1, default=str))
    (out / "gpu_check.md").write_text(markdown(report))
    print(markdown(report))
    if bad:
        sys.exit(f"gpu_check: non-finite or negative figures at {bad}")


def _cpu_name() -> str:
    try:
        names = [ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")]
        return f"{names[0]} x{len(names)}" if names else platform.machine()
    except OSError:
        return platform.processor() or platform.machine()


def _percent(v: float | None) -> str:
    return "-" if v is None else f"{v:.1%}"


def _numbers(obj, path: str = ""):
    if isinstance(obj, bool):
        return
    if isinstance(obj, (int, float)):
        yield path, float(obj)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numbers(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numbers(v, f"{path}[{i}]")


if __name__ == "__main__":
    main()
