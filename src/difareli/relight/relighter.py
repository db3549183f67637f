"""The relighting core: every model (diffusion, one-pass student, pipelines) relights through here (SPEC 5).

A model offers the :mod:`difareli.relight.relightable` interfaces (diffusion or one-pass). On top of them:

- :func:`relight` is the one tensor-level relight: invert with the input's own condition (mean-matching offsets
  computed once, :mod:`difareli.diffusion.relight`), then one batched decode under many targets;
- :class:`Relighter` wraps it, the one door for a relight request: a :class:`Source` (a store record, a photo
  preprocessed in memory, or in-memory encodings; read and checked once: :meth:`Relighter.source`,
  :meth:`Relighter.photo_source`, :meth:`Relighter.source_from_arrays`), then ``relight(source, targets)``
  -> :class:`~difareli.relight.relit.Relit` (images, seconds per stage, whole photos by ``composite()``),
  the inversion cached and reused across targets; ``relight_many`` for many sources at once, each under its own
  targets sharing its inversion (uint8 or float), ``relight_each`` its case of one target each; ``answer(request)``
  for a whole :class:`~difareli.relight.request.Request` (source, target, video, compositing). Grey sources
  come back grey from ``relight``; what a request gets wrong is said once, at :meth:`Relighter.check_inputs`.
The :class:`~difareli.runtime.core.Runtime` decides device, precision, compile and CUDA graphs.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from difareli import errors
from difareli.utils import viz
from difareli.utils.lru import LRU
from difareli.data.inputs import check_store_fits, condition_tensors, image_to_tensor, read_record, relight_reads
from difareli.diffusion.relight import Inversion, SamplerSpec
from difareli.diffusion.spec import DEFAULT_SAMPLER, PRESETS
from difareli.relight.core import invert_image, relight  # noqa: F401 (callers import the tensor-level call here too)
from difareli.relight import photo as photos
from difareli.relight import photo_check
from difareli.relight.relightable import OnePassRelightable, Relightable, model_inputs
from difareli.relight.relit import Relit
from difareli.relight.request import Answer, Request, answer
from difareli.runtime.core import Runtime
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets
from difareli.render.retarget import check_maker
from difareli.render import sun_fit
from difareli.lighting.plausible import implausible_lights


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
    photo: Any = None        # a photo's PreparedPhoto (original, quad, masks): what composites its relights back
    notes: tuple[str, ...] = ()  # lines worth printing about it (how it was read, its check, its light)
    grey: bool = False       # a grey image: its relights come back grey (a colour the model adds is invented)
    check: Any = None        # a photo's check before relighting (photo_check.Check: measures and verdict)


#: Share of clipped values above which a relit image is reported as saturated (a warning, not an error).
SATURATED_SHARE = 0.5


def _cached(cache: dict, key: Any, make):
    """``cache[key]``, made by ``make()`` the first time; a keyless source (nothing names it) is made every time."""
    if key is None:
        return make()
    if key not in cache:
        cache[key] = make()
    return cache[key]


class Relighter:
    """A relightable model + a sampler + a runtime: ``relight(source, targets)`` for a store record
    (:meth:`source`) or in-memory encodings (:meth:`source_from_arrays`). Each source's inversion and key sun are
    cached under its key: all of them, or the last ``cache_size`` sources' for a long-lived caller."""

    def __init__(self, checkpoint, sampler: SamplerSpec | Mapping[str, Any] | None = None, *,
                 runtime: Runtime | Mapping[str, Any] | None = None, device: str | None = None,
                 mean_matching: bool = True, batch_size: int = 16, progress: bool = False,
                 cache_size: int | None = None):
        from difareli.checkpoints.loading import LoadedCheckpoint, load_checkpoint

        # The checkpoint first: a command's values (sampler, runtime, batch size) were checked before any work by its
        # config (Request.from_config, cli.common.check_relighting); the conversions and checks here serve a caller
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
        self.model = ckpt.model.to(self.device)
        self.config = ckpt.config
        self.checkpoint = "the given checkpoint" if isinstance(checkpoint, LoadedCheckpoint) else checkpoint
        self.resolution = ckpt.resolution  # None: the checkpoint records none
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

    @property
    def model_inputs(self) -> list[str]:
        return model_inputs(self.model)

    def needed_encodings(self) -> list[str]:
        return needed_encodings(self.model)

    def sun_reads(self) -> list[str]:
        """What a source holds beyond the model's inputs so that its light's key sun can be found
        (:meth:`key_sun`): the face mask (and part masks) for a model that reads a shadow map; else nothing."""
        if "shadow_map" not in self.model_inputs:
            return []
        return [n for n in sun_fit.ENCODINGS if n not in self.needed_encodings()]

    def key_sun(self, source: Source) -> sun_fit.SunFit | None:
        """Where this model's target map for the source's light is marched: the key sun found from the source
        image's cast shadows under the light fitted to it (``render.sun_fit``); None for a model that reads no
        shadow map, or a source without what the fit reads. Cached under the source's key, as its inversion is
        (a request with a target and a video of the source's own light asks twice; the fit takes about 1 s)."""
        if "shadow_map" not in self.model_inputs:
            return None
        return _cached(self._suns, source.key, lambda: sun_fit.key_sun(source.arrays, source.arrays["light"]))

    def source(self, store: EncodingStore, record_id: str | None = None) -> Source:
        """A store record as a :class:`Source`: the encodings relighting it reads (and, where the store has them,
        what finding its light's key sun reads: :meth:`sun_reads`), checked.
        ``record_id=None``: the first record of the test split (said in its notes). The store must hold what
        this model reads (else a UserError naming the fix); a store at another resolution than the checkpoint's
        is said in the notes."""
        notes = []
        missing = [n for n in self.needed_encodings() if not store.available(n)]
        redo = self._redo(store)
        if missing:  # first: this names the command that writes them, where check_store_fits names only the gap
            fix = (f"{redo} writes them (at the checkpoint's {self.resolution} px)" if redo else
                   "use a store that has them (difareli-synth writes every encoding)")
            raise errors.MissingError(f"relighting with checkpoint={self.checkpoint} needs encoding(s) {missing}, "
                                      f"which the store at {store.root} does not have; {fix}")
        check_store_fits(self.config, store, self.checkpoint)  # an imported official checkpoint on a SynthFaces store
        line = photos.resolution_warning(self.checkpoint, self.resolution, f"the store {store.root}",
                                         int(store.dims.get("H", 0)), f"preprocess at {self.resolution} px: {redo}"
                                         if redo else f"use a {self.resolution} px store")
        notes += [line] if line else []
        if record_id is None:
            test = store.ids(split="test")
            record_id = (test or store.ids())[0]
            notes.append(f"record=null: relighting {record_id}, the first record of the "
                         f"{'test split' if test else 'store'} (record=<id> picks another)")
        arrays = read_record(store, record_id, [*self.needed_encodings(),
                                                *(n for n in self.sun_reads() if store.available(n))])
        notes.append(f"source light (record {record_id}): {photos.describe_light(arrays['light'])}")
        return Source(arrays, (str(store.root), record_id), f"record {record_id!r} of {store.root}", None,
                      tuple(notes), photos.is_grey(arrays["image"]))

    def _redo(self, store: EncodingStore) -> str | None:
        """For a store difareli-preprocess wrote, the command that writes it again for this checkpoint; else None."""
        if store.store_meta.get("source") != "difareli-preprocess":
            return None
        try:
            in_dir = json.loads((Path(store.root) / "preprocess_report.json").read_text())["in_dir"]
        except (OSError, ValueError, KeyError, TypeError):
            in_dir = "<the photos>"
        return f"difareli-preprocess in_dir={in_dir} out_dir=<a new store> checkpoint={self.checkpoint}"

    def photo_size(self, size: int | None = None) -> int:
        """A photo's crop size: ``size``, or (None) the checkpoint's training resolution."""
        if size is not None:
            return int(errors.check_int(size, "photo_size", 16))
        if self.resolution is None:
            raise errors.UserError(f"checkpoint={self.checkpoint} records no training resolution "
                                   "(hyper_parameters.input_dims.resolution); give the crop size: photo_size=<px>")
        return self.resolution

    def photo_source(self, image: str | Path | np.ndarray, *, size: int | None = None, face: Any = None,
                     strict: bool = False, what: str | None = None, key: Any = None,
                     also: Sequence[str] = ()) -> Source:
        """A photo (a path, or decoded RGB uint8) preprocessed in memory by difareli-preprocess's estimators (the
        encodings this model reads) at ``size`` px (None: the training resolution), ``face`` a box of
        :func:`~difareli.relight.photo.detect_faces` (None: the largest), with what finding its light's key sun
        reads (:meth:`sun_reads`). Checked before relighting
        (:mod:`~difareli.relight.photo_check`: one line in its notes; ``strict``: a poor photo is refused).
        Its ``photo`` composites the relights back (:meth:`Relit.composite`); ``also``: encodings estimated beyond
        the model's (e.g. ``face_mask`` for scoring)."""
        is_path = isinstance(image, (str, Path))
        what = what or (f"image={image}" if is_path else "photo")
        rgb = photos.read_photo(image) if is_path else np.asarray(image)
        px = self.photo_size(size)
        notes = [] if size is None else [line for line in [photos.resolution_warning(
            self.checkpoint, self.resolution, f"photo_size={size}", px,
            f"leave photo_size unset (null) or give photo_size={self.resolution}")] if line]
        reads = list(dict.fromkeys([*self.needed_encodings(), *self.sun_reads(), *also]))
        prepared = photos.prepare_photo(rgb, reads, size=px, what=what, face=face)
        stages = ", ".join(f"{k} {1000 * v:.0f} ms" for k, v in prepared.meta.get("seconds", {}).items())
        notes.append(f"preprocessed {what} in {prepared.seconds:.1f} s ({px} px crop of "
                     f"{prepared.rgb.shape[1]}x{prepared.rgb.shape[0]}; {stages})")
        notes += [f"{what}: {note}" for note in prepared.meta.get("notes", [])]
        verdict = photo_check.check(prepared, what)
        notes.append(verdict.line())
        if strict and not verdict.ok:
            raise errors.UserError(f"{what}: refused (strict=true): {'; '.join(verdict.problems)}")
        src = self.source_from_arrays(prepared.arrays, what, key=key if key is not None or not is_path
                                      else ("image", str(image), None if face is None else tuple(np.ravel(face))))
        notes.append(f"source light (fitted on the photo): {photos.describe_light(src.arrays['light'])}")
        if src.grey:
            notes.append(f"{what} is grey: its light is grey and its relights are made grey (their luminance)")
        return dataclasses.replace(src, photo=prepared, notes=tuple(notes), check=verdict)

    def source_from_arrays(self, arrays: Mapping[str, np.ndarray], what: str = "in-memory record",
                           key: Any = None) -> Source:
        """In-memory encodings (a photo preprocessed by :mod:`difareli.relight.photo`, a notebook's edit) as a
        :class:`Source`: the model's encodings present and finite; ``key`` caches its inversion."""
        missing = [n for n in self.needed_encodings() if n not in arrays]
        if missing:
            raise errors.MissingError(f"{what} lacks encoding(s) {missing}, which relighting with this model reads")
        # Non-finite inputs would decode to a black image without a word: stop here, naming what is wrong.
        for name in self.needed_encodings():
            errors.check_finite(arrays[name], f"{what}, encoding {name!r}")
        arrays = {n: np.asarray(arrays[n]) for n in arrays}
        self._check_fits(arrays, what)
        return Source(arrays, key, what, grey=photos.is_grey(arrays["image"]))

    def _check_fits(self, arrays: Mapping[str, np.ndarray], what: str) -> None:
        # Encodings of another layout (an imported official checkpoint beside SynthFaces encodings) would fail deep
        # inside the network on a tensor size: said here, naming both sizes.
        dims = dict(self.config.get("input_dims") or {})
        try:
            sp, ns = condition_tensors(self.model, [arrays], "cpu")
        except (ValueError, RuntimeError, KeyError) as e:
            raise errors.UserError(f"checkpoint={self.checkpoint}: {what} does not fit the model "
                                   f"({str(e).splitlines()[0][:160]})") from None
        for dim, t, names in (("spatial_channels", sp, self.model.spatial_inputs),
                              ("nonspatial_dim", ns, self.model.nonspatial_inputs)):
            if t is not None and dims.get(dim) is not None and int(dims[dim]) != int(t.shape[1]):
                raise errors.UserError(
                    f"checkpoint={self.checkpoint} reads {dims[dim]} {dim.replace('_', ' ')} from {list(names)}, "
                    f"{what} gives {int(t.shape[1])}; relight sources written for this model (an imported official "
                    "checkpoint: a store from difareli.official.importers)")

    def read(self, store: EncodingStore, record_id: str) -> dict[str, np.ndarray]:
        """The checked encodings of a store record (``source(...).arrays``)."""
        return dict(self.source(store, record_id).arrays)

    def inversion(self, source: Source) -> Inversion | None:
        """Passes 1-2 for a source, cached under its key; ``None`` for a one-pass model."""
        if isinstance(self.model, OnePassRelightable):
            return None
        return _cached(self._inversions, source.key, lambda: self._invert(source))

    def _invert(self, source: Source) -> Inversion:
        x0 = image_to_tensor(source.arrays["image"])[None].to(self.device)
        return invert_image(self.model, x0, condition_tensors(self.model, [source.arrays], self.device), self._spec(),
                            runtime=self.runtime, mean_matching=self.mean_matching, progress=self.progress)

    def _spec(self) -> SamplerSpec:
        if self.spec is None:
            raise errors.UserError("this model is a diffusion model: give the Relighter a sampler")
        return self.spec

    def check_inputs(self, source: Source, targets: Targets) -> set[int]:
        """The one check of a request at the door, each bound once: the source's encodings (present and finite:
        checked when the :class:`Source` was made), the targets (lights and shadows: checked by
        :meth:`Targets.of`), what only the pair can tell (given target maps at the source's resolution; a target
        light this face cannot be lit with: :func:`~difareli.lighting.plausible.implausible_lights`, warned about
        and returned as target indices) and the sampler a diffusion model needs. A UserError naming the input."""
        if not isinstance(source, Source) or not isinstance(targets, Targets):
            raise errors.UserError(f"relight takes a Source (Relighter.source / photo_source / source_from_arrays) "
                                   f"and Targets (Targets.of); got {type(source).__name__}, {type(targets).__name__}")
        hw = np.asarray(source.arrays["image"]).shape[:2]
        if targets.maps is not None and targets.maps.shape[1:] != hw:
            raise errors.UserError(f"target shadow maps are {targets.maps.shape[1:]} px, {source.what} is {hw}: "
                                   "give maps at the source's resolution")
        if self.spec is None and not isinstance(self.model, OnePassRelightable):
            raise errors.UserError(f"checkpoint={self.checkpoint} is a diffusion model: give the Relighter a sampler")
        implausible = implausible_lights(source.arrays, targets.lights)
        for why in implausible.values():
            warnings.warn(f"relight of {source.what}: {why}", RuntimeWarning, stacklevel=3)
        return set(implausible)

    def relight(self, source: Source, targets: Targets) -> Relit:
        """``source`` relit under the N ``targets`` (lights and shadow logits c'): :meth:`check_inputs`, one
        inversion (cached per source key, reused across targets and calls), then batched decodes of
        ``batch_size`` targets; a grey source comes back grey. A :class:`Relit` (images (N, H, W, 3) uint8,
        seconds per stage), indexable as its images."""
        blamed = self.check_inputs(source, targets)
        arrays = source.arrays
        start = time.perf_counter()
        inv = self.inversion(source)
        seconds = {"invert": time.perf_counter() - start}
        start = time.perf_counter()
        x0 = image_to_tensor(arrays["image"])[None].to(self.device)
        cond = condition_tensors(self.model, [arrays], self.device)
        out = []
        chunks = range(0, len(targets), self.batch_size)
        for first in tqdm(chunks, desc="relight", disable=not self.progress or len(chunks) == 1):
            batch = targets.retarget(arrays, self.model_inputs, first, first + self.batch_size)
            x = relight(self.model, x0, cond, condition_tensors(self.model, batch, self.device), self.spec,
                        runtime=self.runtime, mean_matching=self.mean_matching, inversion=inv)
            errors.check_finite(x.float().cpu().numpy(), f"relight of {source.what}",
                                fix="the model produced NaN/Inf; try precision=fp32 or another checkpoint")
            self._warn_if_saturated(x, source.what, first, blamed=blamed)
            out.extend(viz.to_uint8(xi.clamp(-1, 1)) for xi in x)
        images = np.stack(out)
        seconds["decode"] = time.perf_counter() - start
        return Relit(photos.grey_like(images) if source.grey else images, seconds, source, targets)

    def answer(self, request: Request, say=None) -> Answer:
        """A whole request (:class:`~difareli.relight.request.Request`: a source by store record or photo, a target,
        a rotation video, compositing; or a batch of photos, written as they go) answered:
        :func:`difareli.relight.request.answer` (``say``: told each line as it arises)."""
        return answer(self, request, say)

    def relight_each(self, sources: Sequence[Source], targets: Targets) -> np.ndarray:
        """Source ``i`` under target ``i`` for many sources at once (N, H, W, 3) uint8: :meth:`relight_many` with
        one target each. The door for jobs that relight a whole store under one light per record (teacher pairs)."""
        if len(sources) != len(targets):
            raise errors.UserError(f"{len(sources)} sources but {len(targets)} targets: give one target per source")
        one = [targets.take(k, k + 1) for k in range(len(targets))]
        return self.relight_many(sources, one)[:, 0]

    def relight_many(self, sources: Sequence[Source], targets: Sequence[Targets], *,
                     as_float: bool = False) -> np.ndarray:
        """Source ``i`` under each of its own K targets ``targets[i]`` (S, K, H, W, 3), every source with K targets:
        :meth:`check_inputs` per pair, then ``batch_size`` sources inverted in one batch and their targets decoded in
        one batch of ``batch_size`` x K, each inversion shared by its source's targets (a one-pass model: one pass
        per source). uint8, or ``as_float``: float32 in [0, 1], unrounded (differences of relights, which a uint8
        step would change). For jobs over many records: no inversion is cached, a grey source is not made grey."""
        if len(sources) != len(targets):
            raise errors.UserError(f"{len(sources)} sources but {len(targets)} sets of targets: give one per source")
        for s, t in zip(sources, targets):  # each source with its own targets (not every light against every face)
            self.check_inputs(s, t)
        k = {len(t) for t in targets}
        if len(k) != 1:
            raise errors.UserError(f"relight_many takes sources with as many targets each; got {sorted(k) or 'none'}")
        k = k.pop()
        out = []
        for start in range(0, len(sources), self.batch_size):
            chunk, sets = sources[start:start + self.batch_size], targets[start:start + self.batch_size]
            x0 = torch.stack([image_to_tensor(s.arrays["image"]) for s in chunk]).to(self.device)
            src = condition_tensors(self.model, [s.arrays for s in chunk], self.device)
            tgt = condition_tensors(self.model, [a for s, t in zip(chunk, sets)
                                                 for a in t.retarget(s.arrays, self.model_inputs)], self.device)
            if isinstance(self.model, OnePassRelightable):  # its source condition is per image: one pass each
                x = torch.cat([relight(self.model, x0[i:i + 1], tuple(None if v is None else v[i:i + 1] for v in src),
                                       tuple(None if v is None else v[i * k:(i + 1) * k] for v in tgt),
                                       runtime=self.runtime) for i in range(len(chunk))])
            else:
                inv = invert_image(self.model, x0, src, self._spec(), runtime=self.runtime,
                                   mean_matching=self.mean_matching).repeat_each(k)  # source-major, as the targets
                x = relight(self.model, x0, src, tgt, self.spec, runtime=self.runtime, inversion=inv)
            what = f"relight of {', '.join(s.what for s in chunk[:2])}{' ...' if len(chunk) > 2 else ''}"
            errors.check_finite(x.float().cpu().numpy(), what,
                                fix="the model produced NaN/Inf; try runtime.precision=fp32 or another checkpoint")
            self._warn_if_saturated(x, what, start * k)
            if as_float:
                out.append(((x.float().clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).cpu().numpy())
            else:
                out.append(np.stack([viz.to_uint8(xi.clamp(-1, 1)) for xi in x]))
        return np.concatenate(out).reshape(len(sources), k, *out[0].shape[1:])

    def _warn_if_saturated(self, x: Tensor, what: str, start: int, blamed: set[int] = frozenset()) -> None:
        # A sampler unstable at its step count (UniPC at 3-5 steps here) decodes to saturated noise, not an error;
        # a target light already said to be implausible (check_inputs) is the cause there, not the sampler.
        clipped = (x.float().abs() >= 0.999).float().mean(dim=(1, 2, 3))
        bad = [start + i for i, f in enumerate(clipped.tolist()) if f > SATURATED_SHARE and start + i not in blamed]
        if bad:
            warnings.warn(f"relight of {what}: {len(bad)} image(s) (first: target {bad[0]}) have over "
                          f"{SATURATED_SHARE:.0%} of their values clipped ({self.describe()}): the sampler may be "
                          "unstable at this step count; try more steps or sampler=ddim", RuntimeWarning, stacklevel=3)
