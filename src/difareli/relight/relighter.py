"""The relighter (SPEC 5): the second layer of the relight spine, every model (diffusion, one-pass student,
pipelines) relighting through it: a :class:`~difareli.relight.sources.Sources` (it reads its faces, checked once)
that relights them under :class:`~difareli.relight.targets.Targets` in one decode loop. Requests, photo batches
and rotation videos are answered above it (:mod:`difareli.relight.request`).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from difareli import errors
from difareli.checkpoints.loading import LoadedCheckpoint, load_checkpoint
from difareli.data import provenance
from difareli.data.inputs import condition_tensors, image_to_tensor
from difareli.diffusion.relight import Inversion, SamplerSpec
from difareli.diffusion.spec import DEFAULT_SAMPLER, PRESETS
from difareli.lighting.plausible import implausible_lights
from difareli.relight.core import invert_image, relight
from difareli.relight.relightable import OnePassRelightable
from difareli.relight.relit import Relit
from difareli.relight.sources import Source, Sources
from difareli.relight.targets import Targets
from difareli.render import sun_fit
from difareli.render.retarget import check_maker
from difareli.runtime.core import Runtime
from difareli.utils import viz
from difareli.utils.lru import LRU

#: Share of clipped values above which a relit image is reported as saturated (a warning, not an error).
SATURATED_SHARE = 0.5


def _cached(cache: dict, key: Any, make):
    """``cache[key]``, made by ``make()`` the first time; a keyless source (nothing names it) is made every time."""
    if key is None:
        return make()
    if key not in cache:
        cache[key] = make()
    return cache[key]


class Relighter(Sources):
    """A relightable model + a sampler + a runtime + caches: each source's inversion and key sun under its key (all
    of them, or the last ``cache_size`` sources' for a long-lived caller)."""

    def __init__(self, checkpoint, sampler: SamplerSpec | Mapping[str, Any] | None = None, *,
                 runtime: Runtime | Mapping[str, Any] | None = None, device: str | None = None,
                 mean_matching: bool = True, batch_size: int = 16, progress: bool = False,
                 cache_size: int | None = None):
        # The checkpoint first: a command's values (sampler, runtime, batch size) were checked before any work by its
        # config (Relighting.from_config, cli.common.check_relighting); the conversions and checks here serve a caller
        # that passes mappings.
        ckpt = checkpoint if isinstance(checkpoint, LoadedCheckpoint) else load_checkpoint(checkpoint)
        rt = runtime if isinstance(runtime, Runtime) else Runtime.from_config(runtime)
        if device is not None:  # the older keyword: the device alone
            rt = dataclasses.replace(rt, device=device)
        if sampler is not None and not isinstance(sampler, SamplerSpec):
            sampler = SamplerSpec.from_config(sampler)
        errors.check_int(batch_size, "batch_size", 1)
        self.runtime = rt
        self.device = rt.torch_device
        super().__init__(ckpt.model.to(self.device), ckpt.config, "the given checkpoint"
                         if isinstance(checkpoint, LoadedCheckpoint) else checkpoint, ckpt.resolution)
        if sampler is None:  # a diffusion model without a named sampler gets the default, the cards' sampler
            sampler = None if isinstance(self.model, OnePassRelightable) else PRESETS[DEFAULT_SAMPLER]
        self.spec = sampler
        self.mean_matching, self.batch_size, self.progress = mean_matching, batch_size, progress
        # Per source key; a long-lived caller (the app) bounds them to its last ``cache_size`` sources.
        self._inversions: dict[Any, Inversion] = {} if cache_size is None else LRU(cache_size)
        self._suns: dict[Any, sun_fit.SunFit | None] = {} if cache_size is None else LRU(cache_size)
        # A model trained on shadow maps of another maker than this relight's target maps: said once, naming both.
        other = check_maker(getattr(self.model, "training_maps", None)) if "shadow_map" in self.model_inputs else None
        if other:
            warnings.warn(other, RuntimeWarning, stacklevel=2)

    def describe(self) -> str:
        """How this relighter relights, for console lines: the sampler (or one pass) and the runtime."""
        how = "one pass" if isinstance(self.model, OnePassRelightable) else f"{self.spec.name}, {self.spec.steps} steps"
        return f"{how}, {self.runtime.precision}{', compiled' if self.runtime.compile else ''}"

    def identity(self) -> dict[str, Any]:
        """What relights, as a folder's record compares it: weights by content, precision, sampler, mean matching."""
        return {"checkpoint": provenance.model_identity(self.model), "precision": self.runtime.precision,
                "sampler": None if self.spec is None else self.spec.to_config(),
                "mean_matching": bool(self.mean_matching)}

    def key_sun(self, source: Source) -> sun_fit.SunFit | None:
        """Where this model's target map for the source's light is marched: the key sun found from the source
        image's cast shadows (``render.sun_fit``), cached under its key (the fit takes about 1 s); None for a model
        that reads no shadow map, or a source without what the fit reads."""
        if "shadow_map" not in self.model_inputs:
            return None
        return _cached(self._suns, source.key, lambda: sun_fit.key_sun(source.arrays, source.arrays["light"]))

    def inversion(self, source: Source) -> Inversion | None:
        """Passes 1-2 for a source, cached under its key; ``None`` for a one-pass model."""
        x0 = _images_in([source], True).to(self.device)
        return self._inverted([source], x0, condition_tensors(self.model, [source.arrays], self.device), cache=True)

    def _inverted(self, chunk: Sequence[Source], x0: Tensor, cond, cache: bool) -> Inversion | None:
        """The inversion of a chunk of sources (its images ``x0``, their condition ``cond``), built once: for one
        source cached under its key (``cache``), for several in one batch; None for a one-pass model."""
        if isinstance(self.model, OnePassRelightable):
            return None

        def make():
            return invert_image(self.model, x0, cond, self.spec, runtime=self.runtime,
                                mean_matching=self.mean_matching, progress=self.progress and len(chunk) == 1)
        return _cached(self._inversions, chunk[0].key, make) if cache and len(chunk) == 1 else make()

    def check_inputs(self, source: Source, targets: Targets) -> set[int]:
        """The one check of a request at the door, each bound once: the source's encodings (present and finite:
        checked when the :class:`Source` was made), the targets (lights and shadows: checked by
        :meth:`Targets.of`), what only the pair can tell (given target maps at the source's resolution; a target
        light this face cannot be lit with: :func:`~difareli.lighting.plausible.implausible_lights`, warned about
        and returned as target indices); a diffusion model always has its sampler (the default where none is
        named). A UserError naming the input."""
        if not isinstance(source, Source) or not isinstance(targets, Targets):
            raise errors.UserError(f"relight takes a Source (Relighter.source / photo_source / source_from_arrays) "
                                   f"and Targets (Targets.of); got {type(source).__name__}, {type(targets).__name__}")
        hw = np.asarray(source.arrays["image"]).shape[:2]
        if targets.maps is not None and targets.maps.shape[1:] != hw:
            raise errors.UserError(f"target shadow maps are {targets.maps.shape[1:]} px, {source.what} is {hw}: "
                                   "give maps at the source's resolution")
        implausible = implausible_lights(source.arrays, targets.lights)
        for why in implausible.values():
            warnings.warn(f"relight of {source.what}: {why}", RuntimeWarning, stacklevel=4)
        return set(implausible)

    def relight(self, source: Source, targets: Targets) -> Relit:
        """``source`` relit under the N ``targets`` (lights and shadow logits c'): :meth:`relight_many` of this one
        source, its inversion cached per source key (reused across targets and calls). A :class:`Relit` (images
        (N, H, W, 3) uint8, seconds per stage), indexable as its images; a grey source comes back grey."""
        seconds: dict[str, float] = {}
        images = self._relight([source], [targets], cache=True, seconds=seconds)[0]
        return Relit(images, seconds, source, targets)  # a grey source's relights made grey

    def relight_many(self, sources: Sequence[Source], targets: Sequence[Targets], *,
                     as_float: bool = False) -> np.ndarray:
        """Source ``i`` under each of its own K targets ``targets[i]`` (S, K, H, W, 3): ``batch_size`` sources
        inverted in one batch and their targets decoded in one. uint8, or ``as_float``: float32 in [0, 1] unrounded
        (differences of relights, which a uint8 step would change). For jobs over many records: no inversion is
        cached, a grey source is not made grey."""
        return self._relight(sources, targets, cache=False, as_float=as_float)

    def _relight(self, sources: Sequence[Source], targets: Sequence[Targets], *, cache: bool, as_float: bool = False,
                 seconds: dict[str, float] | None = None) -> np.ndarray:
        """The one decode loop: every pair checked, then chunks of sources each inverted once and decoded under
        their targets: ``cache`` (:meth:`relight`, one source) its inversion cached and its targets decoded
        ``batch_size`` at a time, else ``batch_size`` sources a chunk and its targets in one decode. ``seconds``:
        filled with the time spent inverting and decoding."""
        if len(sources) != len(targets):
            raise errors.UserError(f"{len(sources)} sources but {len(targets)} sets of targets: give one per source")
        blamed = [self.check_inputs(s, t) for s, t in zip(sources, targets)]  # each source with its own targets
        k = {len(t) for t in targets}
        if len(k) != 1:
            raise errors.UserError(f"relight_many takes sources with as many targets each; got {sorted(k) or 'none'}")
        k = k.pop()
        per, step = (1, self.batch_size) if cache else (self.batch_size, k)  # sources a chunk, targets a decode
        out: list[list[np.ndarray]] = [[] for _ in sources]
        seconds = {} if seconds is None else seconds
        seconds.update(invert=0.0, decode=0.0)
        starts = range(0, len(sources), per)
        bar = tqdm(total=len(starts) * -(-k // step), desc="relight",
                   disable=not self.progress or len(starts) * k <= step)
        for start in starts:
            chunk = sources[start:start + per]
            tick = time.perf_counter()
            x0 = _images_in(chunk, cache).to(self.device)
            cond = condition_tensors(self.model, [s.arrays for s in chunk], self.device)
            inv = self._inverted(chunk, x0, cond, cache)
            seconds["invert"] += time.perf_counter() - tick
            tick = time.perf_counter()
            for first in range(0, k, step):
                x = self._decode(chunk, targets[start:start + per], x0, cond, inv, first, first + step, cache)
                self._check_decoded(x, chunk, start, first, k, blamed)
                n = min(k, first + step) - first
                for i, xi in enumerate(x.reshape(len(chunk), n, *x.shape[1:])):
                    out[start + i].extend(_images(xi, as_float))
                bar.update()
            seconds["decode"] += time.perf_counter() - tick
        bar.close()
        return np.stack([np.stack(row) for row in out])

    def _decode(self, chunk: Sequence[Source], sets: Sequence[Targets], x0: Tensor, cond, inv: Inversion | None,
                first: int, stop: int, one: bool) -> Tensor:
        """Targets ``first:stop`` of each source of a chunk decoded in one batch (source-major); a one-pass model:
        one pass per source (its source condition is per image). ``one``: the chunk is a request's one source, its
        images as the network lays them out and its inversion expanded (a job's are concatenated and repeated)."""
        retargeted = [a for s, t in zip(chunk, sets) for a in t.retarget(s.arrays, self.model_inputs, first, stop)]
        tgt = condition_tensors(self.model, retargeted, self.device)
        n = min(stop, len(sets[0])) - first
        if inv is None:
            outs = [relight(self.model, x0[i:i + 1], tuple(None if v is None else v[i:i + 1] for v in cond),
                            tuple(None if v is None else v[i * n:(i + 1) * n] for v in tgt), runtime=self.runtime)
                    for i in range(len(chunk))]
            return outs[0] if one else torch.cat(outs)
        return relight(self.model, x0, cond, tgt, self.spec, runtime=self.runtime,
                       inversion=inv if one else inv.repeat_each(n))

    def _check_decoded(self, x: Tensor, chunk: Sequence[Source], start: int, first: int, k: int,
                       blamed: Sequence[set[int]]) -> None:
        """A decode's images finite (else a UserError naming the sources), and saturated ones warned about, by
        their flat index (source x k + target); a target light already said to be implausible is not."""
        what = f"{', '.join(s.what for s in chunk[:2])}{' ...' if len(chunk) > 2 else ''}"
        errors.check_finite(x.float().cpu().numpy(), f"relight of {what}",
                            fix="the model produced NaN/Inf; try runtime.precision=fp32 or another checkpoint")
        n = len(x) // len(chunk)
        flat = [(start + r // n) * k + first + r % n for r in range(len(x))]
        known = {(start + i) * k + j for i, b in enumerate(blamed[start:start + len(chunk)]) for j in b}
        # A sampler unstable at its step count (UniPC at 3-5 steps here) decodes to saturated noise, not an error;
        # a target light already said to be implausible (check_inputs) is the cause there, not the sampler.
        clipped = (x.float().abs() >= 0.999).float().mean(dim=(1, 2, 3))
        bad = [flat[i] for i, f in enumerate(clipped.tolist()) if f > SATURATED_SHARE and flat[i] not in known]
        if bad:
            warnings.warn(f"relight of {what}: {len(bad)} image(s) (first: target {bad[0]}) have over "
                          f"{SATURATED_SHARE:.0%} of their values clipped ({self.describe()}): the sampler may be "
                          "unstable at this step count; try more steps or sampler=ddim", RuntimeWarning, stacklevel=4)


def _images_in(sources: Sequence[Source], one: bool) -> Tensor:
    """The sources' images as a batch [B, 3, H, W] in [-1, 1]; a request's ``one`` source keeps its image's memory
    layout (the mean-matching offsets' float sums follow it: its relight stays bit for bit what it was)."""
    if one:
        return image_to_tensor(sources[0].arrays["image"])[None]
    return torch.stack([image_to_tensor(s.arrays["image"]) for s in sources])


def _images(x: Tensor, as_float: bool) -> np.ndarray:
    """Decoded images [-1, 1] (B, 3, H, W) as uint8 (B, H, W, 3), image by image (each keeps the memory layout its
    conversion gives it: a metric's float sums over them follow it), or ``as_float``: float32 in [0, 1] unrounded."""
    if as_float:
        return ((x.float().clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).cpu().numpy()
    return np.stack([viz.to_uint8(xi.clamp(-1, 1)) for xi in x])
