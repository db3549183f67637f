"""Performance measurements on untrained models: a model of a ``conf/model`` variant at any preset and resolution,
random inputs of its shapes, training throughput and FLOPs through the real ``training_step``, repeated timings.

The one home of these builders for difareli-bench-samplers (:mod:`difareli.perf.samplers`) and every benchmark script
(``scripts/bench_train.py``, ``gpu_check.py``, ``gpu_train_reference.py``, ``ablation_report.py``,
``bench_render.py``). Untrained networks suffice for timing: zero-initialised layers cost what trained ones cost.

Nothing here imports Hydra or omegaconf (nor kornia, trimesh, wandb: absent on a bare GPU image, where
``scripts/gpu_check.py`` runs): a variant's config is read as plain YAML (:func:`difareli.configs.read_yaml`) and
its defaults list composed by :func:`variant_config`; its optimizer and LR schedule become plain
``functools.partial`` objects, so a built model also trains through Lightning without Hydra.
"""

from __future__ import annotations

import functools
import importlib
import statistics
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from difareli.configs import read_yaml
from difareli.runtime.inference_copy import to_channels_last
from difareli.data.inputs import Condition, input_dims
from difareli.errors import UserError
from difareli.hardware import peak_flops
from difareli.nn import get_config
from difareli.runtime.core import Runtime, flops_by_op

#: The model variant of the GPU report and the training benchmark (the paper's DiFaReli++).
DEFAULT_VARIANT = "difareli_pp"


# ------------------------------------------------------------------------------------------ building models
def variant_config(variant: str) -> dict[str, Any]:
    """The model config ``difareli-train model=<variant>`` composes (e.g. ``difareli_pp``, ``mechanism/cn_ca``),
    without Hydra: the file's defaults list applied (a parent variant merged in place, the ``spatial`` /
    ``nonspatial`` component options at their keys, ``override`` entries replacing the parents' options), then
    its own keys at ``_self_`` (default: last)."""
    return _compose("model", variant, {})


def _compose(folder: str, name: str, overrides: Mapping[str, str]) -> dict[str, Any]:
    raw = read_yaml(folder, name)
    here = f"{folder}/{name}".rpartition("/")[0]  # relative entries are resolved in the file's own folder
    entries = list(raw.pop("defaults", None) or [])
    own = {_package(key[len("override "):]): option for e in entries if isinstance(e, Mapping)
           for key, option in e.items() if key.startswith("override ")}
    overrides = {**own, **overrides}  # the outermost config's choice wins, as in Hydra
    if "_self_" not in entries:
        entries.append("_self_")
    out: dict[str, Any] = {}
    for entry in entries:
        if entry == "_self_":
            part = raw
        elif isinstance(entry, str):  # a parent config merged in place: `- difareli_pp`, `- /model/x@_here_`
            path, _, package = entry.partition("@")
            if package not in ("", "_here_"):
                raise UserError(f"{folder}/{name}.yaml: defaults entry {entry!r}: only @_here_ is supported")
            parent_folder, _, parent = _resolve(path, here).rpartition("/")
            part = _compose(parent_folder, parent, overrides)
        elif isinstance(entry, Mapping) and len(entry) == 1:  # a group option at its package: `- spatial: modulator`
            key, option = next(iter(entry.items()))
            if key.startswith("override "):
                continue
            package = _package(key)
            option = overrides.get(package, option)
            if option is None:
                continue
            group_folder = _resolve(key.partition("@")[0], here)
            part = {package: _compose(group_folder, str(option), {})}
        else:
            raise UserError(f"{folder}/{name}.yaml: unsupported defaults entry {entry!r}")
        out = _merge(out, part)
    return out


def _resolve(path: str, here: str) -> str:
    return path.lstrip("/") if path.startswith("/") else f"{here}/{path}"


def _package(key: str) -> str:
    """Where a group's option lands: after ``@``, else the group's last folder (``/model/spatial`` -> spatial)."""
    group, _, package = key.strip().partition("@")
    return package or group.rstrip("/").rpartition("/")[2]


def _merge(base: dict[str, Any], new: Mapping[str, Any]) -> dict[str, Any]:
    """OmegaConf's merge: mappings merged key by key, anything else (lists included) replaced."""
    out = dict(base)
    for k, v in new.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def _locate(path: str) -> Any:
    module, _, attr = path.rpartition(".")
    return getattr(importlib.import_module(module), attr)


def _plain_partial(value: Any) -> Any:
    """A ``{_target_, _partial_: true, <kwargs>}`` mapping as ``functools.partial`` (what Hydra makes of it)."""
    if not (isinstance(value, Mapping) and "_target_" in value):
        return value
    if not value.get("_partial_"):
        raise UserError(f"a model option may name a class only as a partial (_partial_: true); got {dict(value)}")
    kwargs = {k: v for k, v in value.items() if k not in ("_target_", "_partial_")}
    return functools.partial(_locate(value["_target_"]), **kwargs)


def build_model(model: str | Mapping[str, Any], preset: str | None = None, resolution: int | None = None, *,
                dims: Mapping[str, int] | None = None, seed: int | None = 0, **options: Any):
    """A randomly initialised model (train mode, on the CPU) of a ``conf/model`` variant name or a composed model
    config: its ``_target_`` module built with ``preset`` (default: the config's) at ``resolution`` (default: the
    preset's image size), input sizes from the encoding registry at the producers' dimensions
    (:func:`difareli.data.inputs.input_dims`; ``dims`` overrides them), ``options`` replacing config keys (e.g.
    ``compile=True``); ``seed`` seeds torch before the weights are drawn (None: the caller's RNG state)."""
    cfg = variant_config(model) if isinstance(model, str) else dict(model)
    target = cfg.get("_target_")
    if not target:
        raise UserError(f"model config {cfg.get('name', model)!r} has no _target_ (the module class to build)")
    preset = preset or cfg.get("preset") or "tiny"  # tiny: the modules' own default
    res = int(resolution or get_config(preset).image_size)
    kwargs = {k: _plain_partial(v) for k, v in cfg.items() if not (k.startswith("_") and k.endswith("_"))}
    sizes = input_dims(kwargs.get("spatial_inputs") or [], kwargs.get("nonspatial_inputs") or [],
                       {"H": res, "W": res, **dict(dims or {})}, resolution=res)
    kwargs.update(preset=preset, input_dims=sizes, **options)
    if seed is not None:
        torch.manual_seed(seed)
    return _locate(target)(**kwargs)


def untrained_model(model: str | Mapping[str, Any], preset: str | None = None, resolution: int | None = None,
                    device: str | torch.device = "cpu", seed: int = 0, dims: Mapping[str, int] | None = None):
    """``(model, resolution)``: :func:`build_model` in eval mode, without gradients, on ``device``."""
    built = build_model(model, preset, resolution, dims=dims, seed=seed)
    return built.to(device).eval().requires_grad_(False), int(built.hparams.input_dims["resolution"])


# ------------------------------------------------------------------------------------------ random inputs
def random_condition(model, batch: int, resolution: int, device: str | torch.device = "cpu", *,
                     generator: torch.Generator | None = None, seed: int = 0) -> Condition:
    """Random raw inputs of a model's condition: spatial uniform in [0, 1) ``[B, C, R, R]``, non-spatial standard
    normal ``[B, D]`` (widths from the encoding registry), None for a kind it does not consume; drawn from
    ``generator`` (default: a fresh one seeded with ``seed``)."""
    g = generator or torch.Generator().manual_seed(seed)
    sizes = input_dims(model.spatial_inputs, model.nonspatial_inputs, resolution=resolution)
    sp = (torch.rand(batch, sizes["spatial_channels"], resolution, resolution, generator=g)
          if model.spatial_inputs else None)
    ns = torch.randn(batch, sizes["nonspatial_dim"], generator=g) if model.nonspatial_inputs else None
    return tuple(None if v is None else v.to(device) for v in (sp, ns))


class RandomBatches(torch.utils.data.Dataset):
    """Items shaped like the DataModule's: image in [-1, 1], spatial [C, R, R], non-spatial [D], each item seeded
    with its index (so every run trains on the same data)."""

    def __init__(self, n: int, resolution: int, spatial_channels: int, nonspatial_dim: int):
        self.n, self.shapes = n, ((3, resolution, resolution), (spatial_channels, resolution, resolution),
                                  (nonspatial_dim,))

    @classmethod
    def of(cls, module, n: int) -> RandomBatches:
        """``n`` items of the input sizes ``module`` was built with."""
        d = module.hparams.input_dims
        return cls(n, d["resolution"], d["spatial_channels"], d["nonspatial_dim"])

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        g = torch.Generator().manual_seed(i)
        image, spatial, nonspatial = (torch.rand(s, generator=g) for s in self.shapes)
        return {"image": image * 2 - 1, "spatial": spatial, "nonspatial": nonspatial}


def random_batch(module, batch: int, device: str | torch.device = "cpu") -> dict:
    """The first batch of :class:`RandomBatches` for ``module``, on ``device``."""
    items = torch.utils.data.default_collate([RandomBatches.of(module, batch)[i] for i in range(batch)])
    return {k: v.to(device) for k, v in items.items()}


def _channels_last(items: list[dict]) -> dict:
    """Default collation, then NHWC ("channels last") memory for the 4-D tensors."""
    return to_channels_last(torch.utils.data.default_collate(items))


# ------------------------------------------------------------------------------------------ training cost
def train_step_flops(module, batch: dict, op: str = "") -> int:
    """FLOPs of one training step's forward and backward of ``L_simple`` (counted exactly on the module's device;
    the optimizer update is not counted); ``op``: only the operators whose name holds it (``"convolution"``: the
    convolutions forward and backward)."""
    def step():
        module.diffusion_loss(batch).backward()

    flops = sum(v for name, v in flops_by_op(step).items() if op in name)
    module.zero_grad(set_to_none=True)
    return flops


def gemm_ceiling(device: str | torch.device = "cpu", precision: str = "bf16", n: int = 2048, repeats: int = 5
                 ) -> float:
    """Measured FLOP/s of the fastest of ``repeats`` dense ``n x n`` matmuls (``2 n^3`` FLOPs each) at ``precision``
    (``bf16`` or ``fp32``) on ``device``, after one warm-up: what this machine's BLAS / oneDNN reaches on the
    friendliest shape, a ceiling for any network on it (the nominal peak counts instructions, not what runs)."""
    dev = torch.device(device)
    dtype = torch.bfloat16 if precision.startswith("bf16") else torch.float32
    gen = torch.Generator().manual_seed(0)
    a, b = (torch.randn(n, n, generator=gen).to(dev, dtype) for _ in range(2))
    sync = Runtime(device=str(dev), precision="fp32").synchronize
    best = float("inf")
    for i in range(repeats + 1):
        sync()
        t0 = time.perf_counter()
        torch.mm(a, b)
        sync()
        seconds = time.perf_counter() - t0
        if i:  # the first is the warm-up (oneDNN's kernel selection, page faults)
            best = min(best, seconds)
    return 2.0 * n ** 3 / best


def _step_timer(warmup: int, device: torch.device):
    import lightning as L

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


def train_throughput(preset: str, res: int, batch: int, precision: str, device: str = "cpu", steps: int = 5,
                     warmup: int = 2, variant: str = DEFAULT_VARIANT, opts: str = "") -> dict:
    """Train ``warmup + steps`` steps of random batches through a Lightning ``Trainer`` (the real
    ``training_step``) and time the last ``steps``: images/s, FLOPs per step, achieved FLOP/s against the device's
    nominal peak (:func:`difareli.hardware.peak_flops`) and against :func:`gemm_ceiling` (a large matmul measured in
    the same process: what any network reaches at best here), peak memory of this process.

    ``opts``: comma-separated ``cl`` (channels-last network and batches), ``compile`` (torch.compile the network),
    ``t<N>`` (N intra-op threads)."""
    import resource

    import lightning as L

    dev = torch.device(device)
    flags = {o for o in opts.split(",") if o}
    for o in flags:
        if o.startswith("t") and o[1:].isdigit():
            torch.set_num_threads(int(o[1:]))
    L.seed_everything(0, verbose=False)
    module = build_model(variant, preset, res, seed=None, compile="compile" in flags)
    if "cl" in flags:
        module.net.to(memory_format=torch.channels_last)
    loader = torch.utils.data.DataLoader(RandomBatches.of(module, batch * (warmup + steps)), batch_size=batch,
                                         num_workers=0, collate_fn=_channels_last if "cl" in flags else None)
    timer = _step_timer(warmup, dev)
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
    # A compiled module is counted through an eager twin: the same arithmetic, and FlopCounterMode sees it.
    counted = build_model(variant, preset, res, seed=None) if "compile" in flags else module
    flops = train_step_flops(counted.to(dev), {k: v.to(dev) for k, v in next(iter(loader)).items()})
    achieved = flops * steps / timer.seconds
    peak, peak_how = peak_flops(dev, "bf16" if "bf16" in precision else "fp32")
    ceiling = gemm_ceiling(dev, "bf16" if "bf16" in precision else "fp32")
    return {"preset": preset, "res": res, "batch": batch, "precision": precision, "opts": opts or "-",
            "device": str(dev),
            "params_M": round(sum(p.numel() for p in module.parameters()) / 1e6, 2),
            "threads": torch.get_num_threads(), "steps": steps, "warmup": warmup,
            "images_per_s": round(batch * steps / timer.seconds, 2), "s_per_step": round(timer.seconds / steps, 4),
            "step_GFLOP": round(flops / 1e9, 2), "achieved_GFLOPs": round(achieved / 1e9, 2),
            "peak_GFLOPs": None if peak is None else round(peak / 1e9, 1),
            "utilisation": None if peak is None else round(achieved / peak, 4), "peak_source": peak_how,
            "gemm_GFLOPs": round(ceiling / 1e9, 1), "of_gemm": round(achieved / ceiling, 4),
            "gemm_of_peak": None if peak is None else round(ceiling / peak, 4),
            "peak_MiB": round(peak_mem, 1), "peak_kind": "cuda_allocated" if dev.type == "cuda" else "process_rss"}


#: Where a training step's time goes: profiler op names (substrings, first match wins) per category.
STEP_CATEGORIES: dict[str, tuple[str, ...]] = {
    "convolution": ("convolution", "conv2d", "mkldnn_conv"),
    "normalisation (GroupNorm / AdaGN)": ("group_norm", "native_layer_norm"),
    "attention": ("bmm", "softmax", "scaled_dot_product", "baddbmm"),
    "linear / MLP (AdaGN, MLP3, time embedding)": ("addmm", "aten::mm", "aten::linear"),
    "activations": ("silu", "tanh", "gelu", "sigmoid"),
    "casts and copies (autocast, layout)": ("copy_", "_to_copy", "aten::to", "contiguous", "clone"),
    "optimizer (AdamW)": ("Optimizer.", "_foreach", "lerp_", "addcdiv_", "addcmul_", "sqrt"),
    "elementwise": ("aten::mul", "aten::add", "aten::sub", "aten::div", "aten::cat", "aten::where", "aten::sum",
                    "aten::mean", "aten::pow", "aten::exp", "aten::neg", "aten::rsqrt", "aten::var"),
}


@dataclass(frozen=True)
class StepProfile:
    """Where a training step's time goes: ``seconds`` per category (:data:`STEP_CATEGORIES`, plus "other": self CPU
    time, summed over threads), ``step`` the wall seconds per step under the profiler, and two rates in GFLOP/s:
    the convolutions' FLOPs over their own time and the matmul ceiling measured in the same process."""

    step: float
    seconds: dict[str, float]
    conv_gflops: float
    gemm_gflops: float

    @property
    def total(self) -> float:
        """The categories' seconds together."""
        return sum(self.seconds.values())


def profile_train_step(preset: str, res: int, batch: int, precision: str, steps: int = 3, warmup: int = 2,
                       variant: str = DEFAULT_VARIANT, opts: str = "") -> StepProfile:
    """A :class:`StepProfile` from torch.profiler's self CPU time of ``steps`` training steps (forward, backward of
    L_simple, AdamW) of random batches, after ``warmup`` steps. CPU only; ``opts`` as :func:`train_throughput`."""
    from torch.profiler import ProfilerActivity, profile

    flags = {o for o in opts.split(",") if o}
    torch.manual_seed(0)
    module = build_model(variant, preset, res, seed=0, compile="compile" in flags)
    if "cl" in flags:
        module.net.to(memory_format=torch.channels_last)
    batch_ = random_batch(module, batch)
    if "cl" in flags:
        batch_ = to_channels_last(batch_)
    opt = torch.optim.AdamW(module.parameters(), lr=1e-4)
    bf16 = "bf16" in precision

    def step():
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss = module.diffusion_loss(batch_)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    for _ in range(warmup):
        step()
    start = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            step()
    wall = (time.perf_counter() - start) / steps
    out = {k: 0.0 for k in [*STEP_CATEGORIES, "other"]}
    for ev in prof.key_averages():
        cat = next((c for c, keys in STEP_CATEGORIES.items() if any(k in ev.key for k in keys)), "other")
        out[cat] += ev.self_cpu_time_total / 1e6 / steps  # microseconds over all profiled steps
    # The convolutions' FLOPs over their profiled time: the rate the convolution kernels themselves reach (a FLOP
    # count does not depend on the precision, so it is counted without autocast).
    conv = train_step_flops(module, batch_, "convolution")
    return StepProfile(wall, out, conv / 1e9 / max(out["convolution"], 1e-12),
                       gemm_ceiling("cpu", "bf16" if bf16 else "fp32") / 1e9)


# ------------------------------------------------------------------------------------------ timing
@dataclass
class Timings:
    """Seconds of repeated calls: wall clock and this process's CPU time (the steadier figure on a shared
    machine; it sums over threads)."""

    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)

    @property
    def median(self) -> float:
        return statistics.median(self.wall)

    @property
    def best(self) -> float:
        return min(self.wall)

    def median_ms(self) -> str:
        """``"<wall> ms wall <cpu> ms cpu"``, medians."""
        return f"{1e3 * self.median:8.2f} ms wall {1e3 * statistics.median(self.cpu):8.2f} ms cpu"


def time_calls(fn: Callable[[], Any], repeats: int, *, warmup: int = 1, runtime=None) -> Timings:
    """Time ``repeats`` calls of ``fn()`` after ``warmup`` untimed ones (first calls pay for allocation and lazy
    initialisation); with a :class:`~difareli.runtime.core.Runtime` the device is synchronised around every call."""
    sync = runtime.synchronize if runtime is not None else (lambda: None)
    for _ in range(warmup):
        fn()
    out = Timings()
    for _ in range(repeats):
        sync()
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        out.wall.append(time.perf_counter() - t0)
        out.cpu.append(time.process_time() - c0)
    return out
