"""The faces a model relights, read and checked once at the boundary (SPEC 5): the first layer of the relight spine.

A :class:`Source` is one face (its encodings, the key its inversion is cached under, how messages name it);
:class:`Sources` makes them for one model from a store record, a photo preprocessed in memory or in-memory
encodings, each checked to fit the model. The relighter is a :class:`Sources` that also relights.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from difareli import errors
from difareli.data.encodings import c_range_arrays
from difareli.data.inputs import check_photo_fits, check_store_fits, condition_tensors, read_record, relight_reads
from difareli.data.store import EncodingStore
from difareli.relight import photo as photos
from difareli.relight import photo_check
from difareli.relight.relightable import Relightable, model_inputs
from difareli.render import sun_fit


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


class Sources:
    """What one model reads of a face, and its faces as checked :class:`Source` s (module doc). ``checkpoint``
    names the model in messages; ``resolution``: its training resolution (None: unrecorded)."""

    def __init__(self, model: Relightable, config: Mapping[str, Any], checkpoint: Any, resolution: int | None):
        self.model, self.config, self.checkpoint, self.resolution = model, config, checkpoint, resolution
        self._stores: dict[str, list[str]] = {}  # per store root: its notes, once it was checked

    @property
    def model_inputs(self) -> list[str]:
        return model_inputs(self.model)

    def needed_encodings(self) -> list[str]:
        """Encodings read per record: the image, its light, the model's inputs and what re-rendering them needs."""
        return relight_reads(self.model_inputs)

    def sun_reads(self) -> list[str]:
        """What a source holds beyond the model's inputs so that its light's key sun can be found (the
        relighter's ``key_sun``): the face mask (and part masks) for a model that reads a shadow map; else none."""
        if "shadow_map" not in self.model_inputs:
            return []
        return [n for n in sun_fit.ENCODINGS if n not in self.needed_encodings()]

    def check_store(self, store: EncodingStore) -> list[str]:
        """The store holds what this model reads, in its layout (else a UserError naming the fix), checked once per
        store; its notes (a resolution other than the checkpoint's)."""
        root = str(store.root)
        if root not in self._stores:
            missing = [n for n in self.needed_encodings() if not store.available(n)]
            redo = self._redo(store)
            if missing:  # first: this names the command that writes them, where check_store_fits names only the gap
                fix = (f"{redo} writes them (at the checkpoint's {self.resolution} px)" if redo else
                       "use a store that has them (difareli-synth writes every encoding)")
                raise errors.MissingError(f"relighting with checkpoint={self.checkpoint} needs encoding(s) "
                                          f"{missing}, which the store at {store.root} does not have; {fix}")
            check_store_fits(self.config, store, self.checkpoint)  # an imported official checkpoint on SynthFaces
            line = photos.resolution_warning(self.checkpoint, self.resolution, f"the store {store.root}",
                                             int(store.dims.get("H", 0)), f"preprocess at {self.resolution} px: "
                                             f"{redo}" if redo else f"use a {self.resolution} px store")
            self._stores[root] = [line] if line else []
        return list(self._stores[root])

    def source(self, store: EncodingStore, record_id: str | None = None, *, also: Sequence[str] = (),
               read: Callable[[list[str]], Mapping[str, np.ndarray]] | None = None) -> Source:
        """A store record as a checked :class:`Source`: what relighting it reads, and where the store has them
        :meth:`sun_reads` and ``also``; ``record_id=None``: the test split's first record (said in its notes).
        ``read``: the record's arrays as a caller already read and checked them (a benchmark's pair)."""
        notes = self.check_store(store)
        if record_id is None:
            test = store.ids(split="test")
            record_id = (test or store.ids())[0]
            notes.append(f"record=null: relighting {record_id}, the first record of the "
                         f"{'test split' if test else 'store'} (record=<id> picks another)")
        names = list(dict.fromkeys([*self.needed_encodings(),
                                    *(n for n in (*self.sun_reads(), *also) if store.available(n))]))
        arrays = (read_record(store, record_id, names) if read is None else
                  {**read(names), **c_range_arrays(store.store_meta)})
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
        """A photo (a path, or decoded RGB uint8) preprocessed in memory by the photo estimators at ``size`` px
        (None: the training resolution), ``face`` a box of :func:`~difareli.relight.photo.detect_faces` (None: the
        largest), with :meth:`sun_reads` and ``also``; its check (:mod:`~difareli.relight.photo_check`) one line of
        its notes (``strict``: a poor photo is refused). Its ``photo`` composites the relights back."""
        is_path = isinstance(image, (str, Path))
        what = what or (f"image={image}" if is_path else "photo")
        rgb = photos.read_photo(image) if is_path else np.asarray(image)
        px = self.photo_size(size)
        notes = [] if size is None else [line for line in [photos.resolution_warning(
            self.checkpoint, self.resolution, f"photo_size={size}", px,
            f"leave photo_size unset (null) or give photo_size={self.resolution}")] if line]
        reads = list(dict.fromkeys([*self.needed_encodings(), *self.sun_reads(), *also]))
        # Before the estimators run (seconds): a model that cannot read their encodings, or a crop too small for
        # them, is said in terms of the model (a 16 px imported model had been blamed on the photo's skin).
        check_photo_fits(self.config, photos.photo_dims(reads, px), self.checkpoint, what)
        photos.check_photo_size(px, self.checkpoint, given=size is not None)
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

    def photo_faces(self, path: str | Path, *, size: int | None = None, face: Any = "largest", strict: bool = False,
                    say: Callable[[str], None] = print) -> tuple[np.ndarray, int, Iterator[Source]]:
        """A photo file's faces: (its pixels, how many faces were found, each chosen one as a :meth:`photo_source`,
        made as it is asked for). ``face`` = largest | all | <index> (left to right); each face found is said."""
        what = f"image={path}"
        rgb = photos.read_photo(path)
        boxes = photos.detect_faces(rgb, self.photo_size(size))
        chosen = photos.choose_faces(boxes, face, what) if boxes else [None]
        for i, box in enumerate(boxes):
            say(f"{what}: {photos.describe_box(i, box, i in chosen)}")

        def made(i: int | None) -> Source:
            source = self.photo_source(rgb, size=size, face=None if i is None else boxes[i], strict=strict,
                                       what=what if i is None or len(boxes) < 2 else f"{what} face {i}",
                                       key=("image", str(path), i))
            say(source.check.line())
            return source
        return rgb, len(boxes), map(made, chosen)

    def source_from_arrays(self, arrays: Mapping[str, np.ndarray], what: str = "in-memory record",
                           key: Any = None) -> Source:
        """In-memory encodings (a photo preprocessed by :mod:`difareli.relight.photo`, a notebook's edit) as a
        :class:`Source`: the model's encodings present, finite and fitting the model; ``key`` caches its
        inversion."""
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
