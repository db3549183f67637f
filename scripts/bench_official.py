"""Whole relights side by side with the official DiFaReli code, in one process, on the same weights.

    python scripts/bench_official.py --official <your checkout of diffusion-face-relighting/difareli_code>
        [--config ffhq128 | tiny64 | <official YAML>] [--steps 20] [--rounds 2] [--threads 2]
        [--modes fp32 bf16 fp32+compile bf16+compile auto] [--json out.json]
    python scripts/bench_official.py --trained difareli_pp-synth64 --store <store> [--sampler ddim --steps 20]

The official code is not shipped here: point ``--official`` at a checkout (its ``guided_diffusion`` and ``config``
folders; it needs ``yacs``, as the official code does). The script builds the official UNet and Modulator with
the official builder (``create_img_and_diffusion``) from the YAML, fills them with random weights (seeded; the
zero-initialised output layers too, so eps is not trivially 0), converts them with ``difareli.official.weights.convert``
and loads the result with ``load_checkpoint`` (the normal way). Then:

- eps parity: the official network and ours on the same inputs (batch 1 and 2), max |difference|;
- one whole relight per mode (condition, DDIM inversion with the official per-channel means, mean-matching
  self-decode, decode under one target: 60 network passes at 20 steps) on the official respaced timesteps, so
  both compute the same thing: the official with its own ``ddim_reverse_sample_loop`` / ``ddim_sample_loop`` and
  model-kwargs dict (deep-copied every step, as its loops do), ours with ``difareli.relight.core.relight`` under a
  :class:`~difareli.runtime.core.Runtime` per mode. Modes run interleaved in every round; the ratio ours / official is
  taken within each round and its median reported, with the relit image's difference from the official one.

OpenMP waiting is made passive before torch loads (``--busy-wait`` keeps the environment's policy). Run timings
under ``flock /tmp/difareli-timing.lock`` on a shared machine.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: tiny-64: our ``tiny`` preset at 64 px in official terms (the official YAML keys, set on its config object).
TINY64 = {"image_size": 64, "num_channels": 32, "channel_mult": "1,2,2", "num_res_blocks": 1,
          "attention_resolutions": "8", "num_heads": 2}

def official_config(checkout: Path, which: str, steps: int, work: Path):
    """(the official yacs config, the YAML path our importer reads) for ``ffhq128`` / ``tiny64`` / a YAML."""
    import yaml
    from config.base_config import get_cfg_defaults, update_params

    if which in ("ffhq128", "tiny64"):
        raw = yaml.safe_load((checkout / "config/difareli" / ("difareli_128.yaml" if which == "ffhq128"
                                                              else "difareli_64.yaml")).read_text())
        if which == "tiny64":
            raw["img_model"].update(TINY64, condition_proj_dim=128)
            raw["img_cond_model"].update(TINY64)
    else:
        raw = yaml.safe_load(Path(which).read_text())
    path = work / "official.yaml"
    path.write_text(yaml.safe_dump(raw))
    cfg = get_cfg_defaults()
    for section, values in raw.items():  # set, not merged: yacs' merge literal-evals "1,2,2" into a tuple
        if isinstance(values, dict):
            for key, value in values.items():
                cfg[section][key] = value
    cfg = update_params(cfg)
    cfg.diffusion.timestep_respacing = str(steps)
    return cfg, path


def randomise(model, seed: int) -> None:
    """Random weights with O(1) activations: N(0, 1/fan_in) for weights, GroupNorm scales near 1."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.ndim == 1:
                base = 1.0 if name.endswith("weight") else 0.0
                p.copy_(base + 0.1 * torch.randn(p.shape, generator=g))
            else:
                p.copy_(torch.randn(p.shape, generator=g) / max(1, p[0].numel()) ** 0.5)


def inputs(r: int, selector: list[str], parts_order: list[str], seed: int):
    """Source and target conditions, in the official layout (cond_img, cond_params) and ours."""
    import torch
    import torch.nn.functional as F

    from difareli.official.weights import PARAM_WIDTHS

    g = torch.Generator().manual_seed(seed)

    def smooth(c: int) -> torch.Tensor:
        return F.interpolate(torch.randn(1, c, 8, 8, generator=g), size=(r, r), mode="bilinear", align_corners=False)

    x0 = smooth(3).tanh()
    shading = smooth(3).abs()
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, r), torch.linspace(-1, 1, r), indexing="ij")
    face = (xx ** 2 + yy ** 2 < 0.5).float()
    background = x0 * (1 - face) - face  # face, hair and neck pixels at -1, as the official faceseg_nohead
    params = {k: torch.randn(1, w, generator=g) for k, w in PARAM_WIDTHS.items()}
    target = dict(params, shadow=params["shadow"] + 1.0)
    tgt_shading = shading.flip(-1) * 1.3

    def both(sh: torch.Tensor, p: dict):
        img = torch.cat([sh, background], 1)
        official = torch.cat([p[k] for k in selector], 1)
        ours = torch.cat([torch.cat([p[k] for k in parts_order], 1) if k == "shape" else p[k]
                          for k in ("shape", "cam", "faceemb", "shadow")], 1)
        return img, official, ours, p

    return x0, both(shading, params), both(tgt_shading, target)


def official_kwargs(cfg, img, cond, params, x0):
    """The model-kwargs dict the official relight passes to its loops (the dataset's keys included)."""
    import torch

    kw = {"cond_params": cond, "cond_img": img, "image": x0, "dpm_cond_img": None, "cfg": cfg,
          "use_render_itp": True, "use_cond_xt_fn": False, "image_name": ["src.png"],
          "raw_image": torch.zeros(1, 3, 256, 256, dtype=torch.uint8), "tform": torch.zeros(1, 9),
          "albedo": torch.zeros(1, 50), "detail": torch.zeros(1, 128),
          "const_noise": torch.randn(1, 3, x0.shape[-1], x0.shape[-1])}
    kw.update({k: v for k, v in params.items()})
    return kw


def official_relight(models, diffusion, cfg, x0, src, tgt):
    """The official relight() for one target, minus its DECA rendering and file writes (progress bars off)."""
    import torch

    unet, enc = models[cfg.img_model.name], models[cfg.img_cond_model.name]
    with torch.no_grad():
        cond = official_kwargs(cfg, src[0], src[1], src[3], x0)
        cond["spatial_latent"] = enc(x=cond["cond_img"].float(), emb=None)
        rev = diffusion.ddim_reverse_sample_loop(model=unet, x=x0, clip_denoised=True, denoised_fn=None,
                                                 model_kwargs=cond, progress=False, store_intermidiate=True,
                                                 cond_xt_fn=None, store_mean=True)
        noise, rev_mean = rev[0]["sample"], rev[1]
        diffusion.ddim_sample_loop(model=unet, shape=noise.shape, noise=noise, clip_denoised=True, model_kwargs=cond,
                                   progress=False, store_intermidiate=False, rev_mean=rev_mean)
        match = copy.deepcopy([m[:1] for m in rev_mean])
        relit = copy.deepcopy(official_kwargs(cfg, tgt[0], tgt[1], tgt[3], x0))
        relit["spatial_latent"] = enc(x=relit["cond_img"].float(), emb=None)
        out = diffusion.ddim_sample_loop(model=unet, shape=noise.shape, noise=noise, clip_denoised=True,
                                         model_kwargs=relit, progress=False, store_intermidiate=False,
                                         add_mean=match)
    return out[0]["sample"]


def respaced_spec(timesteps: list[int]):
    """Our DDIM on the official respaced timesteps: inversion from t=0 to abar=0, generation down to clean data,
    x0 clipped both ways (the official relight's settings)."""
    import dataclasses

    import torch

    from difareli.diffusion.spec import SamplerSpec

    @dataclasses.dataclass(frozen=True)
    class Respaced(SamplerSpec):
        timesteps: tuple = ()

        def grids(self, schedule):
            ts = list(self.timesteps)
            return torch.tensor(ts + [schedule.T]), torch.tensor(ts[::-1] + [-1])

    return Respaced("ddim", steps=len(timesteps), clip_x0_invert=True, clip_x0_generate=True,
                    timesteps=tuple(timesteps))


def trained_check(checkpoint: str, store_root: str, records: int, sampler: str, steps: int) -> int:
    """bf16 against fp32 on a trained checkpoint (random weights exaggerate low-precision error): the relit
    uint8 images of ``records`` test records, target = own light turned 60 degrees, through Relighter."""
    import numpy as np
    import torch

    from difareli.lighting import sh
    from difareli.diffusion.spec import SamplerSpec
    from difareli.lit import load_checkpoint
    from difareli.relight.relighter import Relighter
    from difareli.runtime.core import Runtime
    from difareli.data.store import EncodingStore
    from difareli.relight.targets import Targets

    store = EncodingStore.open(store_root)
    ids = (store.ids(split="test") or store.ids())[:records]
    ckpt = load_checkpoint(checkpoint)
    spec = SamplerSpec.preset(sampler, steps=steps)
    outs = {}
    for precision in ("fp32", "bf16"):
        r = Relighter(ckpt, spec, runtime=Runtime(device="cpu", precision=precision))
        outs[precision] = [r.relight(r.source(store, rid), Targets.of(
            sh.yaw(np.asarray(r.source(store, rid).arrays["light"], np.float64), 60.0))).astype(np.int16)
            for rid in ids]
    d = np.stack([np.abs(a - b) for a, b in zip(outs["fp32"], outs["bf16"])])
    mse = float((d.astype(np.float64) ** 2).mean())
    psnr = 10 * np.log10(255 ** 2 / mse) if mse else float("inf")
    print(f"{checkpoint}, {sampler}-{steps}, {len(ids)} record(s) of {store_root}, torch {torch.__version__}: bf16 vs "
          f"fp32 relight: max {int(d.max())}, mean {d.mean():.2f}, 99th percentile {np.percentile(d, 99):.0f} "
          f"levels of 255, PSNR {psnr:.1f} dB")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--official", help="a checkout of github.com/diffusion-face-relighting/difareli_code")
    p.add_argument("--config", default="tiny64", help="ffhq128 | tiny64 | an official YAML")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--modes", nargs="+", default=["fp32", "bf16", "fp32+compile", "bf16+compile"],
                   help="runtime modes, <precision>[+compile][+cuda_graphs] or auto (Runtime.from_mode)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--busy-wait", action="store_true", help="keep the environment's OpenMP wait policy")
    p.add_argument("--json", default=None)
    p.add_argument("--trained", default=None, help="instead: bf16 vs fp32 on this trained checkpoint (--store)")
    p.add_argument("--store", default=None)
    p.add_argument("--records", type=int, default=4)
    p.add_argument("--sampler", default="ddim")
    args = p.parse_args()
    if args.trained:
        sys.path.insert(0, str(ROOT / "src"))
        from difareli.utils.processes import openmp_for_machine

        openmp_for_machine(busy=True)  # passive, as every timing of this script
        return trained_check(args.trained, args.store, args.records, args.sampler, args.steps)
    checkout = Path(args.official).expanduser() if args.official else None
    marker = Path("guided_diffusion/models/spatial_cond_arch/unet_spatial_condition_hadamart.py")
    if checkout is None or not (checkout / marker).is_file():
        what = f"{checkout} has no {marker}" if checkout else "none given"
        print("bench_official: --official must be your checkout of github.com/diffusion-face-relighting/difareli_code "
              f"(not shipped here; {what})", file=sys.stderr)
        return 2
    if not args.busy_wait:
        sys.path.insert(0, str(ROOT / "src"))
        from difareli.utils.processes import openmp_for_machine

        openmp_for_machine(busy=True)  # passive, before torch loads
    sys.path.insert(0, str(checkout))
    try:
        import yacs  # noqa: F401  (the official config library)
    except ImportError:
        print("bench_official: the official code needs yacs: pip install yacs", file=sys.stderr)
        return 2
    import torch
    from guided_diffusion.script_util import create_img_and_diffusion

    from difareli.official import weights as official
    from difareli.lit import load_checkpoint
    from difareli.utils.processes import openmp_wait_policy
    from difareli.relight.core import relight
    from difareli.runtime.core import Runtime

    torch.set_num_threads(args.threads)
    work = Path(tempfile.mkdtemp(prefix="bench_official_"))
    cfg, yaml_path = official_config(checkout, args.config, args.steps, work)
    models, diffusion = create_img_and_diffusion(cfg)
    models = {k: v.eval() for k, v in models.items() if v is not None}
    for i, m in enumerate(models.values()):
        randomise(m, args.seed + i)
    ours_cfg = official.read_config(yaml_path)
    ckpt, _ = official.convert(models[cfg.img_model.name].state_dict(), models[cfg.img_cond_model.name].state_dict(),
                               ours_cfg)
    torch.save(ckpt, work / "imported.ckpt")
    model = load_checkpoint(work / "imported.ckpt").model
    r = ours_cfg.net["image_size"]
    x0, src, tgt = inputs(r, ours_cfg.selector, list(official.STORE_SHAPE_PARTS), args.seed)
    n_official = sum(p.numel() for m in models.values() for p in m.parameters())
    report = {"date": datetime.date.today().isoformat(), "config": args.config, "steps": args.steps,
              "threads": torch.get_num_threads(), "omp_wait_policy": openmp_wait_policy(), "torch": torch.__version__,
              "parameters": {"official": n_official, "ours": sum(p.numel() for p in model.parameters())}}
    enc, unet = models[cfg.img_cond_model.name], models[cfg.img_model.name]
    parity = {}
    with torch.no_grad():
        for b in (1, 2):
            g = torch.Generator().manual_seed(100 + b)
            x = torch.randn(b, 3, r, r, generator=g)
            t = torch.full((b,), 500)
            img, cond_o, cond_u = (v.expand(b, *v.shape[1:]) for v in (src[0], src[1], src[2]))
            e_o = unet(x, t, cond_params=cond_o, spatial_latent=enc(x=img, emb=None))["output"]
            e_u = model.net(x, t, model.condition(img, cond_u))
            parity[b] = float((e_o - e_u).abs().max())
    report["eps_max_abs_diff"] = parity
    spec = respaced_spec(sorted(diffusion.timestep_map))
    runners = {"official": lambda: official_relight(models, diffusion, cfg, x0, src, tgt)}
    compile_s = {}
    for mode in args.modes:
        rt = Runtime.from_mode(mode, "cpu")
        start = time.perf_counter()  # warm-up: one denoiser call (compiles once per mode)
        with torch.no_grad(), rt.autocast():  # the condition in the dtype relight() makes it (bf16 under bf16)
            cond = model.condition(src[0], src[2])
        with torch.no_grad():
            rt.denoiser(model.net, cond)(x0, torch.tensor([0]))
        compile_s[mode] = time.perf_counter() - start
        runners[mode] = (lambda rt=rt: relight(model, x0, (src[0], src[2]), (tgt[0], tgt[2]), spec, runtime=rt))
    secs = {k: [] for k in runners}
    outs = {}
    for _ in range(args.rounds):  # interleaved: load from other processes hits every mode alike
        for name, run in runners.items():
            start = time.perf_counter()
            outs[name] = run()
            secs[name].append(time.perf_counter() - start)
    ref = outs["official"].float()
    rows = []
    for name in runners:
        ratios = [s / o for s, o in zip(secs[name], secs["official"])]
        diff = (outs[name].float() - ref).abs()
        rows.append({"mode": name, "median_s": statistics.median(secs[name]), "ratio": statistics.median(ratios),
                     "speedup": 1 / statistics.median(ratios), "max_abs_diff": float(diff.max()),
                     "mean_abs_diff": float(diff.mean()), "warmup_s": compile_s.get(name)})
    report["rows"] = rows
    print(f"{args.config} ({n_official:,} parameters), DDIM-{args.steps} whole relight (60 passes at 20 steps), "
          f"{report['threads']} threads, OMP_WAIT_POLICY {report['omp_wait_policy']}, torch {torch.__version__}, "
          f"{args.rounds} interleaved rounds, {report['date']}")
    print(f"eps parity, official vs ours: max |diff| {parity[1]:.2e} (batch 1), {parity[2]:.2e} (batch 2)")
    print("| mode | s / relight (median) | ours / official (median per round) | speed-up | max abs diff vs "
          "official (of [-1, 1]) | mean abs diff | warm-up s |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        w = "" if row["warmup_s"] is None else f"{row['warmup_s']:.1f}"
        print(f"| {row['mode']} | {row['median_s']:.2f} | {row['ratio']:.2f} | {row['speedup']:.2f}x | "
              f"{row['max_abs_diff']:.1e} | {row['mean_abs_diff']:.1e} | {w} |")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
