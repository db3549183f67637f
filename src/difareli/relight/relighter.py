"""The relighting core: every model (diffusion, one-pass student, pipelines) relights through here (SPEC 5).

A model offers the :mod:`difareli.relight.relightable` interfaces (diffusion or one-pass). On top of them:

- :func:`relight` is the one tensor-level relight: invert with the input's own condition (mean-matching offsets
  computed once, :mod:`difareli.diffusion.relight`), then one batched decode under many targets;
- :class:`Relighter` wraps it: ``relight(source, targets)`` for a :class:`Source` (a store record or in-memory
  encodings, read and checked once) under :class:`~difareli.relight.targets.Targets`, caching inversions.
The :class:`~difareli.runtime.core.Runtime` decides device, precision, compile and CUDA graphs.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from difareli import errors
from difareli.utils import viz
from difareli.data.inputs import condition_tensors, image_to_tensor, read_record, relight_reads
from difareli.diffusion.relight import Inversion, SamplerSpec
from difareli.diffusion.spec import DEFAULT_SAMPLER, PRESETS
from difareli.relight.core import invert_image, relight  # noqa: F401 (callers import the tensor-level call here too)
from difareli.relight.relightable import OnePassRelightable, Relightable, model_inputs
from difareli.runtime.core import Runtime
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets, check_maker


def needed_encodings(model: Relightable) -> list[str]:
    """Encodings read per record: the image, its light, the model's inputs and what re-rendering them needs."""
    return relight_reads(model_inputs(model))


@dataclass(frozen=True)
class Source:
    """One face to relight: its encodings (read and checked once, at the boundary), the key its inversion is
    cached under (``None``: not cached), and how messages name it."""

    arrays: Mapping[str, np.ndarray]
    key: Any
    what: str


#: Share of clipped values above which a relit image is reported as saturated (a warning, not an error).
SATURATED_SHARE = 0.5


class Relighter:
    """A relightable model + a sampler + a runtime: ``relight(source, targets)`` for a store record
    (:meth:`source`) or in-memory encodings (:meth:`source_from_arrays`)."""

    def __init__(self, checkpoint, sampler: SamplerSpec | Mapping[str, Any] | None = None, *,
                 runtime: Runtime | Mapping[str, Any] | None = None, device: str | None = None,
                 mean_matching: bool = True, batch_size: int = 16, progress: bool = False):
        from difareli.checkpoints.loading import LoadedCheckpoint, load_checkpoint

        rt = runtime if isinstance(runtime, Runtime) else Runtime.from_config(runtime)
        if device is not None:  # the older keyword: the device alone
            rt = dataclasses.replace(rt, device=device)
        self.runtime = rt
        self.device = rt.torch_device
        ckpt = checkpoint if isinstance(checkpoint, LoadedCheckpoint) else load_checkpoint(checkpoint, self.device)
        self.model = ckpt.model.to(self.device)
        self.config = ckpt.config
        if sampler is None:  # a diffusion model without a named sampler gets the default, the cards' sampler
            sampler = None if isinstance(self.model, OnePassRelightable) else PRESETS[DEFAULT_SAMPLER]
        self.spec = None if sampler is None else (sampler if isinstance(sampler, SamplerSpec)
                                                  else SamplerSpec.from_config(sampler))
        self.mean_matching, self.batch_size, self.progress = mean_matching, batch_size, progress
        self._inversions: dict[Any, Inversion] = {}
        # A model trained on shadow maps of another maker than this relight's target maps: said once, naming both.
        other = check_maker(getattr(self.model, "training_maps", None)) if "shadow_map" in self.model_inputs else None
        if other:
            warnings.warn(other, RuntimeWarning, stacklevel=2)

    def describe(self) -> str:
        """How this relighter relights, for console lines: the sampler (or one pass) and the runtime."""
        how = "one pass" if isinstance(self.model, OnePassRelightable) else f"{self.spec.name}, {self.spec.steps} steps"
        return f"{how}, {self.runtime.precision}{', compiled' if self.runtime.compile else ''}"

    @property
    def model_inputs(self) -> list[str]:
        return model_inputs(self.model)

    def needed_encodings(self) -> list[str]:
        return needed_encodings(self.model)

    def source(self, store: EncodingStore, record_id: str) -> Source:
        """A store record as a :class:`Source`: the encodings relighting it reads (and nothing else), checked."""
        missing = [n for n in self.needed_encodings() if not store.available(n)]
        if missing:
            raise KeyError(f"relighting with this model needs encoding(s) {missing}, which the store at "
                           f"{store.root} does not have")
        return Source(read_record(store, record_id, self.needed_encodings()), (str(store.root), record_id),
                      f"record {record_id!r} of {store.root}")

    def source_from_arrays(self, arrays: Mapping[str, np.ndarray], what: str = "in-memory record",
                           key: Any = None) -> Source:
        """In-memory encodings (a photo preprocessed by :mod:`difareli.relight.photo`, a notebook's edit) as a
        :class:`Source`: the model's encodings present and finite; ``key`` caches its inversion."""
        missing = [n for n in self.needed_encodings() if n not in arrays]
        if missing:
            raise KeyError(f"{what} lacks encoding(s) {missing}, which relighting with this model reads")
        # Non-finite inputs would decode to a black image without a word: stop here, naming what is wrong.
        for name in self.needed_encodings():
            errors.check_finite(arrays[name], f"{what}, encoding {name!r}")
        return Source({n: np.asarray(arrays[n]) for n in arrays}, key, what)

    def read(self, store: EncodingStore, record_id: str) -> dict[str, np.ndarray]:
        """The checked encodings of a store record (``source(...).arrays``)."""
        return dict(self.source(store, record_id).arrays)

    def inversion(self, source: Source) -> Inversion | None:
        """Passes 1-2 for a source, cached under its key; ``None`` for a one-pass model."""
        if isinstance(self.model, OnePassRelightable):
            return None
        if source.key is not None and source.key in self._inversions:
            return self._inversions[source.key]
        x0 = image_to_tensor(source.arrays["image"])[None].to(self.device)
        inv = invert_image(self.model, x0, condition_tensors(self.model, [source.arrays], self.device), self._spec(),
                           runtime=self.runtime, mean_matching=self.mean_matching, progress=self.progress)
        if source.key is not None:
            self._inversions[source.key] = inv
        return inv

    def _spec(self) -> SamplerSpec:
        if self.spec is None:
            raise ValueError("this model is a diffusion model: give the Relighter a sampler")
        return self.spec

    def relight(self, source: Source, targets: Targets) -> np.ndarray:
        """Relit images (N, H, W, 3) uint8 of ``source`` under the N ``targets`` (lights and shadow logits c'):
        one inversion (cached), then batched decodes of ``batch_size`` targets."""
        arrays = source.arrays
        inv = self.inversion(source)
        x0 = image_to_tensor(arrays["image"])[None].to(self.device)
        cond = condition_tensors(self.model, [arrays], self.device)
        out = []
        chunks = range(0, len(targets), self.batch_size)
        for start in tqdm(chunks, desc="relight", disable=not self.progress or len(chunks) == 1):
            batch = targets.retarget(arrays, self.model_inputs, start, start + self.batch_size)
            x = relight(self.model, x0, cond, condition_tensors(self.model, batch, self.device), self.spec,
                        runtime=self.runtime, mean_matching=self.mean_matching, inversion=inv)
            errors.check_finite(x.float().cpu().numpy(), f"relight of {source.what}",
                                fix="the model produced NaN/Inf; try precision=fp32 or another checkpoint")
            self._warn_if_saturated(x, source.what, start)
            out.extend(viz.to_uint8(xi.clamp(-1, 1)) for xi in x)
        return np.stack(out)

    def relight_each(self, sources: Sequence[Source], targets: Targets) -> np.ndarray:
        """Source ``i`` under target ``i`` for many sources at once (N, H, W, 3) uint8: ``batch_size`` sources
        inverted in one batch and decoded in one batch (a one-pass model: one pass per batch). The door for jobs
        that relight a whole store (teacher pairs, shadow maps, measurements)."""
        if len(sources) != len(targets):
            raise ValueError(f"{len(sources)} sources but {len(targets)} targets: give one target per source")
        out = []
        for start in range(0, len(sources), self.batch_size):
            chunk = sources[start:start + self.batch_size]
            x0 = torch.stack([image_to_tensor(s.arrays["image"]) for s in chunk]).to(self.device)
            src = condition_tensors(self.model, [s.arrays for s in chunk], self.device)
            tgt = [targets.retarget(s.arrays, self.model_inputs, start + k, start + k + 1)[0]
                   for k, s in enumerate(chunk)]
            if isinstance(self.model, OnePassRelightable):  # its source condition is per image: one pass each
                x = torch.cat([relight(self.model, x0[k:k + 1], tuple(None if v is None else v[k:k + 1] for v in src),
                                       condition_tensors(self.model, [a], self.device), runtime=self.runtime)
                               for k, a in enumerate(tgt)])
            else:
                x = relight(self.model, x0, src, condition_tensors(self.model, tgt, self.device), self.spec,
                            runtime=self.runtime, mean_matching=self.mean_matching)
            what = f"relight of {', '.join(s.what for s in chunk[:2])}{' ...' if len(chunk) > 2 else ''}"
            errors.check_finite(x.float().cpu().numpy(), what,
                                fix="the model produced NaN/Inf; try runtime.precision=fp32 or another checkpoint")
            self._warn_if_saturated(x, what, start)
            out.extend(viz.to_uint8(xi.clamp(-1, 1)) for xi in x)
        return np.stack(out)

    def _warn_if_saturated(self, x: Tensor, what: str, start: int) -> None:
        # A sampler unstable at its step count (UniPC at 3-5 steps here) decodes to saturated noise, not an error.
        clipped = (x.float().abs() >= 0.999).float().mean(dim=(1, 2, 3))
        bad = [start + i for i, f in enumerate(clipped.tolist()) if f > SATURATED_SHARE]
        if bad:
            warnings.warn(f"relight of {what}: {len(bad)} image(s) (first: target {bad[0]}) have over "
                          f"{SATURATED_SHARE:.0%} of their values clipped ({self.describe()}): the sampler may be "
                          "unstable at this step count; try more steps or sampler=ddim", RuntimeWarning, stacklevel=3)
