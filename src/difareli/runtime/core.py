"""The inference runtime: device, precision, ``torch.compile``, CUDA graphs and synchronisation, in one place.

``Runtime`` is a frozen value (``conf/runtime/default.yaml``); ``runtime.denoiser(net, cond)`` turns a
:class:`~difareli.nn.DiffusionNet` (called as ``net(x_t, t, cond) -> eps``) and a prepared condition into the
sampler-facing ``(x, t) -> eps``. Only the network runs in low precision: the returned eps is float32 and the
samplers keep their own float32/float64 arithmetic.

CUDA graphs are captured at that denoiser boundary with static ``x``/``t``/condition buffers, one graph per
(network, batch size, condition structure, precision, compile); a new condition of the same structure is copied
into the static buffers, so every target of a benchmark reuses one graph. Graphs read the parameters in place:
call :func:`clear_caches` after replacing a network's parameters (``load_state_dict`` copies in place and is fine).
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import time
import warnings
import weakref
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, ContextManager

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from difareli.errors import UserError
from difareli.hardware import auto_precision
from difareli.runtime.inference_copy import forget, inference_copy, to_channels_last

PRECISIONS = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}
#: The Lightning ``Trainer(precision=...)`` matching each inference precision (training benchmarks).
LIGHTNING_PRECISION = {"fp32": "32-true", "bf16": "bf16-mixed", "fp16": "16-mixed"}
MEMORY_FORMATS = ("contiguous", "channels_last")
#: The switches a runtime mode's name may add to its precision (:meth:`Runtime.from_mode`), in spelling order.
MODE_FLAGS = ("compile", "cuda_graphs")
_DEVICE_RE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")

# network -> compiled callable; network -> {graph key: _Graph}. Weak keys: a dropped network drops its caches.
_COMPILED: "weakref.WeakKeyDictionary[Any, Callable]" = weakref.WeakKeyDictionary()
_GRAPHS: "weakref.WeakKeyDictionary[Any, dict]" = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class Runtime:
    """Where and how the denoising network runs at inference (validated on construction)."""

    device: str = "auto"     # auto | cpu | cuda | cuda:N
    precision: str = "auto"  # auto (auto_precision: bf16 where native, else fp32) | fp32 | bf16 | fp16 (CUDA only)
    compile: bool = False    # torch.compile of the network forward, cached per network
    cuda_graphs: bool = False  # CUDA graphs at the denoiser boundary; eager (with a warning) off CUDA
    memory_format: str = "auto"  # auto (channels_last for bf16 on a CPU) | contiguous | channels_last

    def __post_init__(self) -> None:
        if not isinstance(self.device, str) or not _DEVICE_RE.match(self.device):
            raise UserError(f"runtime.device={self.device!r} is not one of auto, cpu, cuda, cuda:N")
        if self.precision == "auto":  # resolved here, so every reader sees fp32 / bf16
            if self.device.startswith("cuda") and not torch.cuda.is_available():
                raise UserError(f"runtime.device={self.device!r} but CUDA is not available here; use device=cpu")
            object.__setattr__(self, "precision", auto_precision(self.torch_device))
        if self.precision not in PRECISIONS:
            raise UserError(f"runtime.precision={self.precision!r} is not one of {', '.join(PRECISIONS)}, auto")
        for key in ("compile", "cuda_graphs"):
            if not isinstance(getattr(self, key), bool):
                raise UserError(f"runtime.{key}={getattr(self, key)!r} must be true or false")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise UserError(f"runtime.device={self.device!r} but CUDA is not available here; use device=cpu or auto")
        if self.memory_format == "auto":
            # Measured on a CPU (AMX bf16): channels-last bf16 passes 1.34x faster at ffhq128 (oneDNN reorders NCHW
            # inputs inside every convolution); fp32 passes were 4% slower, so only bf16 turns it on.
            cl = self.torch_device.type == "cpu" and self.precision == "bf16"
            object.__setattr__(self, "memory_format", "channels_last" if cl else "contiguous")
        if self.memory_format not in MEMORY_FORMATS:
            raise UserError(f"runtime.memory_format={self.memory_format!r} is not one of auto, "
                            f"{', '.join(MEMORY_FORMATS)}")
        if self.precision == "fp16" and self.torch_device.type != "cuda":
            raise UserError("runtime.precision=fp16 needs CUDA (CPU float16 autocast is not supported here); "
                            "use precision=bf16 or fp32 on CPU")

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> "Runtime":
        """From a ``runtime:`` config mapping (None: the defaults); unknown keys are an error naming them."""
        if cfg is None:
            return cls()
        if not isinstance(cfg, Mapping):
            raise UserError(f"runtime config must be a mapping of {', '.join(_FIELDS)}, got {type(cfg).__name__}")
        unknown = sorted(set(map(str, cfg)) - set(_FIELDS))
        if unknown:
            raise UserError(f"unknown runtime key(s) {unknown}; known: {', '.join(_FIELDS)}")
        return cls(**{str(k): v for k, v in cfg.items()})

    @classmethod
    def from_mode(cls, mode: str, device: str = "auto") -> "Runtime":
        """A named mode, ``<precision>[+compile][+cuda_graphs]`` (e.g. ``fp32``, ``bf16+compile``,
        ``bf16+compile+cuda_graphs``, ``auto``): the one spelling the benchmarks and checks share, so a mode's name
        always says its precision."""
        precision, *flags = str(mode).split("+")
        unknown = [f for f in flags if f not in MODE_FLAGS]
        if precision not in (*PRECISIONS, "auto") or unknown or len(set(flags)) != len(flags):
            raise UserError(f"runtime mode {mode!r}: give <precision>[+compile][+cuda_graphs], precision one of "
                            f"{', '.join(PRECISIONS)}, auto (e.g. bf16+compile)")
        return cls(device=device, precision=precision, **{f: True for f in flags})

    def mode(self) -> str:
        """This runtime's mode name (:meth:`from_mode`'s spelling)."""
        return "+".join([self.precision, *(f for f in MODE_FLAGS if getattr(self, f))])

    # ------------------------------------------------------------------ device and precision
    @property
    def torch_device(self) -> torch.device:
        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        return torch.device(self.device)

    @property
    def dtype(self) -> torch.dtype | None:
        """The autocast dtype (None for fp32)."""
        return PRECISIONS[self.precision]

    @property
    def lightning_precision(self) -> str:
        return LIGHTNING_PRECISION[self.precision]

    @property
    def graphs_active(self) -> bool:
        """Whether CUDA graphs are really used (asked for and on a CUDA device)."""
        return self.cuda_graphs and self.torch_device.type == "cuda"

    def autocast(self) -> ContextManager:
        """Autocast to the configured dtype on the device (a no-op for fp32)."""
        if self.dtype is None:
            return contextlib.nullcontext()
        # No weight-cast cache: it only helps autograd and must stay off inside a CUDA-graph capture.
        return torch.autocast(self.torch_device.type, dtype=self.dtype, cache_enabled=False)

    def module(self, net: torch.nn.Module) -> torch.nn.Module:
        """``net`` on the device in eval mode (the inference state every runtime path expects)."""
        return net.to(self.torch_device).eval()

    # ------------------------------------------------------------------ the denoiser
    def denoiser(self, forward: Callable, cond: Any) -> Callable[[Tensor, Tensor], Tensor]:
        """``(x, t) -> eps`` (float32) for ``forward(x, t, cond)``, with autocast inside, compiled and
        graph-captured as configured. Eager and compiled passes of an ``nn.Module`` run its inference copy
        (:mod:`difareli.runtime.inference_copy`: weights cast once to the autocast dtype, the configured memory format);
        CUDA graphs read the network's own parameters in place."""
        if self._copies(forward):
            forward = inference_copy(forward, self.dtype, self.memory_format == "channels_last")
            cond = self._layout(cond)
        fn = _compiled(forward) if self.compile else forward

        def eager(x: Tensor, t: Tensor, c: Any = cond) -> Tensor:
            with self.autocast():
                return fn(x, t, c).float()

        if not self.cuda_graphs:
            return eager
        if self.torch_device.type != "cuda":
            warnings.warn(f"runtime.cuda_graphs=true on {self.torch_device}: no CUDA, running eagerly", stacklevel=2)
            return eager
        return _GraphedDenoiser(self, forward, eager, cond)

    def condition(self, net: torch.nn.Module, *inputs: Any) -> Any:
        """``net.condition(*inputs)`` (the Modulator) run as :meth:`denoiser` runs ``net``'s passes: on its
        inference copy with channels-last inputs, under autocast; the path a one-pass model takes, whose Modulator
        runs at every relight (contiguous, it equals autocast on ``net`` bit for bit, the copy's contract)."""
        if self._copies(net):
            net = inference_copy(net, self.dtype, self.memory_format == "channels_last")
            inputs = self._layout(inputs)
        with self.autocast():
            return net.condition(*inputs)

    def _copies(self, forward: Any) -> bool:
        """Whether ``forward`` runs as its inference copy (a module, no CUDA graph, low precision or channels-last)."""
        return isinstance(forward, torch.nn.Module) and not self.graphs_active and (
            self.dtype is not None or self.memory_format == "channels_last")

    def _layout(self, tree: Any) -> Any:
        return to_channels_last(tree) if self.memory_format == "channels_last" else tree

    # ------------------------------------------------------------------ timing
    def synchronize(self) -> None:
        """Wait for the device's queued work (a no-op on CPU): call before reading a clock."""
        dev = self.torch_device
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    @contextlib.contextmanager
    def timed(self) -> Iterator["Timing"]:
        """``with rt.timed() as t: ...`` then ``t.seconds``: synchronised at both ends."""
        timing = Timing()
        self.synchronize()
        start = time.perf_counter()
        try:
            yield timing
        finally:
            self.synchronize()
            timing.seconds = time.perf_counter() - start


_FIELDS = tuple(f.name for f in dataclasses.fields(Runtime))


@dataclass
class Timing:
    """Filled by :meth:`Runtime.timed` on exit."""

    seconds: float = float("nan")


def clear_caches(forward: Any | None = None) -> None:
    """Forget compiled forwards, CUDA graphs and inference copies (of one network, or all)."""
    for cache in (_COMPILED, _GRAPHS):
        if forward is None:
            cache.clear()
        else:
            cache.pop(forward, None)
    if forward is None or isinstance(forward, torch.nn.Module):
        forget(forward)


def _compiled(forward: Callable) -> Callable:
    # Compiling per condition would recompile at every call of denoiser(): one compiled callable per network.
    # Static shapes: a batch size is a recompile (like a CUDA graph per batch size); dynamic shapes compiled
    # several times slower here and give slower kernels.
    if forward not in _COMPILED:
        _COMPILED[forward] = _CompiledOrEager(forward)
    return _COMPILED[forward]


class _CompiledOrEager:
    """``torch.compile(forward)``, falling back to ``forward`` itself (one warning saying why) where compiling
    cannot work on this machine: no working C++ compiler for inductor's kernels. Compile is only a speed option,
    so a missing compiler costs speed, not the run; any other compile error is raised as it is."""

    def __init__(self, forward: Callable):
        self.forward = forward
        self.compiled: Callable | None = torch.compile(forward, dynamic=False)

    def __call__(self, *args, **kwargs):
        if self.compiled is not None:
            try:
                return self.compiled(*args, **kwargs)
            except Exception as e:  # only a missing compiler is handled, the rest is re-raised
                why = _missing_compiler(e)
                if why is None:
                    raise
                self.compiled = None  # once: every later call runs eagerly without retrying the compile
                warnings.warn(f"runtime.compile=true but torch.compile cannot build kernels here ({why}); running "
                              "eagerly (same results, slower): install a C++ compiler (e.g. apt-get install g++, "
                              "or set CXX) to compile, or set runtime.compile=false", stacklevel=2)
        return self.forward(*args, **kwargs)


def compile_for_training(module: torch.nn.Module) -> bool:
    """``torch.compile`` a network in place for training (forward and backward through AOTAutograd, inductor's
    kernels), the one training door to compile. Where inductor cannot build kernels (no working C++ compiler) the
    network stays eager with one warning, as the inference runtime does; returns whether it was compiled.
    Parameters and ``state_dict`` keys are unchanged (``nn.Module.compile`` wraps the call, not the module)."""
    why = _compiler_missing()
    if why is not None:
        warnings.warn(f"model.compile=true but torch.compile cannot build kernels here ({why}); training eagerly "
                      "(same results, slower): install a C++ compiler (e.g. apt-get install g++, or set CXX), or "
                      "set model.compile=false", stacklevel=2)
        return False
    module.compile()
    return True


def _compiler_missing() -> str | None:
    """Why inductor has no C++ compiler here (None: it has one). Asked before compiling, because a compiled
    training step fails at its first call, inside Lightning's loop, where no eager fallback is possible."""
    try:
        from torch._inductor import cpp_builder

        cpp_builder.get_cpp_compiler()
    except Exception as e:  # InvalidCxxCompiler, or a torch whose builder moved: judged as the runtime does
        return _missing_compiler(e) or f"{type(e).__name__}: {e}"
    return None


def _missing_compiler(exc: BaseException) -> str | None:
    """The message of an ``InvalidCxxCompiler`` anywhere in ``exc``'s chain (dynamo wraps backend errors in
    ``BackendCompilerFailed``), else None."""
    try:
        from torch._inductor.exc import InvalidCxxCompiler
    except ImportError:  # pragma: no cover - a torch without inductor cannot raise it
        return None
    seen: set[int] = set()
    todo: list[BaseException | None] = [exc]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, InvalidCxxCompiler):
            return str(e).strip().splitlines()[0] if str(e).strip() else "no working C++ compiler"
        todo += [getattr(e, "inner_exception", None), e.__cause__, e.__context__]
    return None


# ---------------------------------------------------------------------- CUDA graphs
def _flatten(cond: Any) -> tuple[list, Any]:
    """Leaves and structure of a condition; dataclasses (e.g. ``Condition``) become pytree nodes on first use."""
    _register_dataclasses(cond)
    return pytree.tree_flatten(cond)


def _register_dataclasses(obj: Any) -> None:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        cls = type(obj)
        if cls not in pytree.SUPPORTED_NODES:
            names = tuple(f.name for f in dataclasses.fields(cls))
            pytree.register_pytree_node(
                cls, lambda o, names=names: ([getattr(o, n) for n in names], names),
                lambda values, names, cls=cls: cls(**dict(zip(names, values))))
        for f in dataclasses.fields(obj):
            _register_dataclasses(getattr(obj, f.name))
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _register_dataclasses(v)
    elif isinstance(obj, dict):
        for v in obj.values():
            _register_dataclasses(v)


def _signature(v: Any) -> Any:
    if torch.is_tensor(v):
        return ("T", tuple(v.shape), v.dtype, v.device, v.stride())
    return ("V", repr(v))  # None, numbers, strings: part of the graph's identity


class _Graph:
    """One captured graph: static inputs, static output, and which denoiser's condition the buffers hold."""

    def __init__(self, eager: Callable, x: Tensor, t: Tensor, leaves: list, spec: Any, device: torch.device):
        self.x, self.t = x.clone(), t.clone()
        self.leaves = [v.clone() if torch.is_tensor(v) else v for v in leaves]
        self.owner: Any = None
        cond = pytree.tree_unflatten(self.leaves, spec)
        # PyTorch's recipe: warm up on a side stream (lazy init, cuDNN/compile choices), then capture.
        stream = torch.cuda.Stream(device)
        stream.wait_stream(torch.cuda.current_stream(device))
        with torch.no_grad(), torch.cuda.stream(stream):
            for _ in range(3):
                eager(self.x, self.t, cond)
        torch.cuda.current_stream(device).wait_stream(stream)
        self.graph = torch.cuda.CUDAGraph()
        with torch.no_grad(), torch.cuda.graph(self.graph):
            self.out = eager(self.x, self.t, cond)

    def load(self, owner: Any, leaves: list) -> None:
        if self.owner is not owner:
            for static, v in zip(self.leaves, leaves):
                if torch.is_tensor(static):
                    static.copy_(v)
            self.owner = owner


class _GraphedDenoiser:
    """``(x, t) -> eps`` replaying one CUDA graph per batch size; captured on first use of each."""

    def __init__(self, runtime: Runtime, forward: Callable, eager: Callable, cond: Any):
        self.runtime, self.eager = runtime, eager
        self.leaves, self.spec = _flatten(cond)
        self.graphs = _GRAPHS.setdefault(forward, {})
        self.cond_key = (runtime.precision, runtime.compile, str(self.spec), tuple(map(_signature, self.leaves)))
        # Copy the condition now: the caller may free or overwrite its tensors before the first step.
        for g in self.graphs.values():
            if g.key_cond == self.cond_key:
                g.load(self, self.leaves)

    def __call__(self, x: Tensor, t: Tensor) -> Tensor:
        key = (self.cond_key, _signature(x), _signature(t))
        graph = self.graphs.get(key)
        if graph is None:
            graph = _Graph(self.eager, x, t, self.leaves, self.spec, self.runtime.torch_device)
            graph.key_cond, graph.owner = self.cond_key, self
            self.graphs[key] = graph
        graph.load(self, self.leaves)  # another denoiser may have loaded its condition since
        graph.x.copy_(x)
        graph.t.copy_(t)
        graph.graph.replay()
        # Multistep samplers keep earlier eps: hand out a copy, never the static buffer.
        return graph.out.clone()


# ---------------------------------------------------------------------- FLOPs and peaks
def flops_by_op(fn: Callable, *args: Any, **kwargs: Any) -> dict[str, int]:
    """FLOPs (2 per multiply-add) of one call of ``fn`` (forward and, if ``fn`` calls backward, backward), per
    operator (``aten.convolution``, ``aten.convolution_backward``, ``aten.mm`` ...)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        fn(*args, **kwargs)
    return {str(op): int(v) for op, v in counter.get_flop_counts()["Global"].items()}


def count_flops(fn: Callable, *args: Any, **kwargs: Any) -> int:
    """FLOPs of one call of ``fn``, all operators (:func:`flops_by_op`)."""
    return sum(flops_by_op(fn, *args, **kwargs).values())
