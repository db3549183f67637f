"""The one home of a configured sampler: :class:`SamplerSpec` and the named presets (SPEC 5, 10).

A spec says which sampler (a function in :mod:`difareli.diffusion.samplers`), how many steps on which grid,
the x0-clipping per direction, whether the inversion table ends at abar = 0, and the sampler's own options.
Those options are read from the sampler function's signature (its keyword-only parameters other than
``clip_x0``, ``callback`` and ``progress``; types and allowed values from its annotations), so a new option
needs no table here. Every spec is validated when it is built and stores every option explicitly (defaults
filled in), so two specs that sample alike compare equal.

``PRESETS`` is the one table of named configurations: ``conf/sampler/<name>.yaml`` mirrors it (a test
composes each file and compares), and the tests, notebooks and the exactness oracle take their samplers from it.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import numbers
import typing
from dataclasses import dataclass
from typing import Any, Callable, Literal, Mapping

import torch

from difareli.errors import UserError, check_int
from difareli.diffusion.samplers import SAMPLERS
from difareli.diffusion.schedule import GRID_KINDS, DiffusionSchedule

Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

#: Keyword-only parameters every sampler takes, set per call rather than per spec.
COMMON = ("clip_x0", "callback", "progress")


class SamplerConfigError(UserError):
    """A sampler configuration that names an unknown sampler, preset or option, or a value of the wrong type."""


@dataclass(frozen=True)
class Option:
    """One sampler option as its function declares it: the annotation and the default."""

    name: str
    annotation: Any
    default: Any

    def describe(self) -> str:
        if typing.get_origin(self.annotation) is Literal:
            return " | ".join(repr(v) for v in typing.get_args(self.annotation))
        return getattr(self.annotation, "__name__", str(self.annotation))

    def check(self, sampler: str, value: Any) -> Any:
        """``value`` normalised (numpy scalars -> Python), or SamplerConfigError naming the option."""
        ann = self.annotation
        allowed = typing.get_args(ann) if typing.get_origin(ann) is Literal else None
        kinds = {type(v) for v in allowed} if allowed else {ann}
        for kind in kinds:
            ok, out = _coerce(value, kind)
            if ok and (allowed is None or out in allowed):
                return out
        raise SamplerConfigError(f"sampler {sampler!r}: option {self.name}={value!r} is invalid; "
                                 f"expected {self.describe()} (default {self.default!r})")


def _coerce(value: Any, kind: Any) -> tuple[bool, Any]:
    """Whether ``value`` is a ``kind`` (bool is not an int here, nor an int a bool), and the plain value."""
    if kind is bool:
        return isinstance(value, bool), value
    if kind is int:
        ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
        return ok, int(value) if ok else value
    if kind is float:
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
        return ok, float(value) if ok else value
    if kind is str:
        return isinstance(value, str), value
    return True, value  # an annotation we cannot check: the sampler validates it when it runs


@functools.cache
def signature_options(name: str) -> dict[str, Option]:
    """The options of sampler ``name``, read from its function's signature."""
    fn = SAMPLERS[_check_name(name)]
    hints = typing.get_type_hints(fn)
    return {p.name: Option(p.name, hints.get(p.name, Any), p.default)
            for p in inspect.signature(fn).parameters.values()
            if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in COMMON}


def _check_name(name: Any) -> str:
    if isinstance(name, str) and name in SAMPLERS:
        return name
    hint = f" ({name!r} is a preset: use preset={name} or SamplerSpec.preset({name!r}))" if name in PRESETS else ""
    raise SamplerConfigError(f"unknown sampler {name!r}; choose from {', '.join(SAMPLERS)}{hint}")


def _is_int(v: Any) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


@dataclass(frozen=True)
class SamplerSpec:
    """Which sampler, how many steps on which grid, the x0-clipping per direction and the sampler's options.

    ``options`` may be given as a mapping or as ``(name, value)`` pairs; it is stored as a sorted tuple holding
    every option of the sampler (defaults filled in). Invalid values raise :class:`SamplerConfigError`.
    """

    name: str = "ddim"
    steps: int = 50
    grid: str = "uniform"
    clip_x0_invert: bool = False
    clip_x0_generate: bool = False
    alpha_zero_end: bool = False
    #: Light guidance of a relight's decode: eps = eps_source + w (eps_target - eps_source), the target
    #: condition's pull past the source's (w = 1: the plain target decode; w > 1 relights further at twice the
    #: decode's network passes). Not a sampler option: it reads the source condition beside the target's.
    guidance: float = 1.0
    options: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self):
        name = _check_name(self.name)
        if not _is_int(self.steps) or self.steps < 1:
            raise SamplerConfigError(f"sampler steps must be an integer >= 1, got {self.steps!r} "
                                     "(e.g. sampler.steps=50)")
        if self.grid not in GRID_KINDS:
            raise SamplerConfigError(f"unknown sampler grid {self.grid!r}; choose from {', '.join(GRID_KINDS)}")
        ok, guidance = _coerce(self.guidance, float)
        if not ok or not 0.0 < guidance <= 10.0:
            raise SamplerConfigError(f"sampler guidance must be a number in (0, 10], got {self.guidance!r} "
                                     "(1: the plain target decode; e.g. sampler.guidance=2)")
        object.__setattr__(self, "guidance", guidance)
        for f in ("clip_x0_invert", "clip_x0_generate", "alpha_zero_end"):
            if not isinstance(getattr(self, f), bool):
                raise SamplerConfigError(f"sampler {f} must be true or false, got {getattr(self, f)!r}")
        given = dict(self.options.items() if isinstance(self.options, Mapping) else self.options)
        known = signature_options(name)
        unknown = sorted(set(given) - set(known))
        if unknown:
            valid = ", ".join(known) or "none"
            raise SamplerConfigError(f"unknown option {unknown[0]!r} for sampler {name!r}; its options: {valid} "
                                     f"(common keys: {', '.join(_FIELDS)})")
        opts = {k: o.check(name, given[k]) if k in given else o.default for k, o in known.items()}
        object.__setattr__(self, "steps", int(self.steps))
        object.__setattr__(self, "options", tuple(sorted(opts.items())))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "SamplerSpec":
        """From a ``conf/sampler/*.yaml`` mapping: the spec fields, plus the sampler's options as top-level
        keys; ``preset: <name>`` starts from a named preset. Keys set to None count as absent."""
        if not isinstance(cfg, Mapping):
            raise SamplerConfigError(f"sampler={cfg!r} is not a sampler config: give a mapping with a name (a sampler: "
                                     f"{', '.join(SAMPLERS)}) or a preset ({', '.join(PRESETS)}), e.g. sampler=ddim")
        cfg = {k: v for k, v in dict(cfg).items() if v is not None}
        if "preset" in cfg:
            base = _preset(cfg.pop("preset")).to_config()
            if cfg.get("name", base["name"]) != base["name"]:  # another sampler: keep the common fields only
                base = {k: base[k] for k in _FIELDS if k in base}
            cfg = {**base, **cfg}
        if "name" not in cfg:
            raise SamplerConfigError("a sampler config needs a name (a sampler: "
                                     f"{', '.join(SAMPLERS)}) or a preset ({', '.join(PRESETS)})")
        fields = {k: cfg.pop(k) for k in _FIELDS if k in cfg}
        opts = dict(cfg.pop("options", None) or {})
        return cls(**fields, options={**opts, **cfg})

    @classmethod
    def preset(cls, preset: str, /, **overrides) -> "SamplerSpec":
        """The named preset (``PRESETS``), with fields or options overridden, e.g. ``preset("paper", steps=50)``."""
        return cls.from_config({"preset": preset, **overrides})

    def to_config(self) -> dict[str, Any]:
        """The flat mapping ``conf/sampler/*.yaml`` holds; ``from_config(spec.to_config()) == spec``. ``guidance``
        at 1 (the plain decode) is left out, so such a spec records as every spec did before guidance existed
        (a finished benchmark run is resumed, not refused for a key it never had)."""
        fields = {f: getattr(self, f) for f in _FIELDS if not (f == "guidance" and self.guidance == 1.0)}
        return {**fields, **dict(self.options)}

    # ------------------------------------------------------------------ running
    def grids(self, schedule: DiffusionSchedule) -> tuple[torch.Tensor, torch.Tensor]:
        """(inversion grid ascending, generation grid descending), mirrors of each other except that with
        ``alpha_zero_end`` the inversion's last point is T (abar = 0) while generation starts at T-1."""
        inv = schedule.time_grid(self.steps, kind=self.grid, direction="invert", alpha_zero_end=self.alpha_zero_end)
        return inv, schedule.time_grid(self.steps, kind=self.grid, direction="generate")

    def run(self, denoiser: Denoiser, x: torch.Tensor, grid, schedule: DiffusionSchedule, *, clip_x0=None,
            callback=None, progress: bool = False) -> torch.Tensor:
        """This sampler with its options over ``grid`` (descending generates, ascending inverts).
        ``clip_x0=None`` takes the spec's setting for the grid's direction."""
        if clip_x0 is None:
            ts = grid.tolist() if hasattr(grid, "tolist") else list(grid)
            ascending = len(ts) > 1 and ts[1] > ts[0]
            clip_x0 = self.clip_x0_invert if ascending else self.clip_x0_generate
        return SAMPLERS[self.name](denoiser, x, grid, schedule, clip_x0=clip_x0, callback=callback,
                                   progress=progress, **dict(self.options))

    @torch.no_grad()
    def generate(self, denoiser: Denoiser, x_T: torch.Tensor, schedule: DiffusionSchedule, *, callback=None,
                 progress: bool = False) -> torch.Tensor:
        """Sample from noise ``x_T`` (at t = T-1) down to clean data on this spec's generation grid."""
        return self.run(denoiser, x_T, self.grids(schedule)[1], schedule, clip_x0=self.clip_x0_generate,
                        callback=callback, progress=progress)


#: The spec fields a config sets besides the sampler's options.
_FIELDS = tuple(f.name for f in dataclasses.fields(SamplerSpec) if f.name != "options")

#: The preset a relight uses when none is named (``conf/sampler/default.yaml``, ``Relighter(ckpt)``).
DEFAULT_SAMPLER = "default"

#: Named sampler configurations; ``conf/sampler/<name>.yaml`` mirrors each.
PRESETS: dict[str, SamplerSpec] = {
    "ddim": SamplerSpec("ddim"),
    "dpm_solver": SamplerSpec("dpm_solver"),
    "dpm_solver_pp": SamplerSpec("dpm_solver_pp"),
    "unipc": SamplerSpec("unipc", options={"variant": "bh2"}),
    "unipc_bh1": SamplerSpec("unipc", options={"variant": "bh1"}),
    # The public DiFaReli code: DDIM over all 1000 levels, x0 clipped to [-1, 1] in both directions, and an
    # inversion table whose last step lands on abar = 0 (x_T = eps); SPEC 5.3.
    "paper": SamplerSpec("ddim", steps=1000, clip_x0_invert=True, clip_x0_generate=True, alpha_zero_end=True),
    # The default of every relighting command, the app and the notebooks, and the sampler the shipped models'
    # cards are benchmarked with: chosen by error against seconds on the shipped weights
    # (difareli-bench-samplers; docs/reference_models.md "The default sampler").
    DEFAULT_SAMPLER: SamplerSpec("unipc", steps=50, options={"variant": "bh2"}),
}


def _preset(name: Any) -> SamplerSpec:
    if name not in PRESETS:
        raise SamplerConfigError(f"unknown sampler preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]


def as_spec(sampler: "SamplerSpec | str | Mapping[str, Any]", **overrides) -> SamplerSpec:
    """A spec from a spec, a preset name or a sampler config, with ``overrides`` (None: keep) applied."""
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if isinstance(sampler, SamplerSpec):
        return SamplerSpec.from_config({**sampler.to_config(), **overrides}) if overrides else sampler
    if isinstance(sampler, str):
        return SamplerSpec.preset(sampler, **overrides)
    return SamplerSpec.from_config({**dict(sampler), **overrides})


def check_sampler(cfg: Mapping[str, Any], key: str = "sampler") -> None:
    """A sampler config: a registered ``name`` and an integer ``steps`` >= 1, said by key, then the whole spec
    (its options too: :meth:`SamplerSpec.from_config`). The CLIs' one sampler check, before any work."""
    if cfg.get("name") not in SAMPLERS:
        raise UserError(f"{key}.name={cfg.get('name')!r} is not a sampler; choose from {sorted(SAMPLERS)} "
                        f"(or pick a config: {key}={'|'.join(PRESETS)})")
    check_int(cfg.get("steps"), f"{key}.steps", 1)
    SamplerSpec.from_config(cfg)
