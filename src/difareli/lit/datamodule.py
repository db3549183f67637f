"""The DataModule: serves exactly the encodings a model variant declares, from an encodings store.

A variant names its spatial inputs (fed to the Modulator, or concatenated) and its non-spatial inputs (fed to
AdaGN). Only those encodings and the image are read from disk; nothing else is loaded or kept. Non-spatial
inputs are returned raw; their normalisation statistics are computed on the training split and stored in the
model (and so in the checkpoint).
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Any, Mapping, Sequence

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from difareli.data import encodings as enc
from difareli.errors import UserError, UserFileNotFoundError, check_record
from difareli.data.inputs import (MissingEncodingError, check_store_fits, image_to_tensor, input_dims,
                                  prepare_nonspatial, prepare_spatial)
from difareli.data.store import EncodingStore
from difareli.lit.pairs import pair_dataset
from difareli.render.retarget import shadow_maker
from difareli.synth.config import ConfigError, SynthConfig


class EncodingsDataset(Dataset):
    """Records of a store, each as ``image``, ``spatial``, ``nonspatial`` tensors and its ``record_id``.

    ``exact_share`` > 0 (a store with every input estimated that also keeps the exact ones as ``<name>_gt``, as
    SynthFaces ``inputs=estimated`` does): each record is served with its exact inputs in place of the estimated
    ones with that probability, so one run trains on both kinds (:func:`exact_counterparts`).
    """

    def __init__(self, store: EncodingStore, ids: Sequence[str], spatial: Sequence[str], nonspatial: Sequence[str],
                 exact_share: float = 0.0):
        self.store, self.ids = store, list(ids)
        self.spatial, self.nonspatial = list(spatial), list(nonspatial)
        self.names = ["image", *self.spatial, *self.nonspatial]
        self.exact_share = float(exact_share)
        self.exact = exact_counterparts(store, self.names) if self.exact_share > 0 else {}

    def __len__(self) -> int:
        return len(self.ids)

    def _read(self, rid: str) -> dict[str, np.ndarray]:
        # torch's generator: seeded per worker by seed_everything(workers=True), so a run's draws repeat.
        if self.exact and float(torch.rand(())) < self.exact_share:
            arrays = self.store.read(rid, [self.exact.get(n, n) for n in self.names])
            return {n: arrays[self.exact.get(n, n)] for n in self.names}
        return self.store.read(rid, self.names)

    def __getitem__(self, i: int) -> dict[str, Any]:
        rid = self.ids[i]
        arrays = check_record(self._read(rid), rid, self.store.root)  # NaN would poison training
        return {
            "image": image_to_tensor(arrays["image"]),
            "spatial": prepare_spatial(self.spatial, arrays),
            "nonspatial": prepare_nonspatial(self.nonspatial, arrays),
            "record_id": rid,
        }


def exact_counterparts(store: EncodingStore, names: Sequence[str]) -> dict[str, str]:
    """``{name: name_gt}`` for each of ``names`` whose exact counterpart the store keeps; a store that keeps none
    is refused (training on "both kinds" there would silently train on one)."""
    found = {n: f"{n}_gt" for n in names if n != "image" and store.available(f"{n}_gt")}
    if not found:
        raise UserError(f"data.exact_share > 0 but store {store.root} keeps no exact counterpart (<name>_gt) of "
                        f"{[n for n in names if n != 'image']}; make it with difareli-synth inputs=estimated, or "
                        "set data.exact_share=0")
    return found


class EncodingsDataModule(L.LightningDataModule):
    """Train/val loaders over an encodings store, restricted to the encodings a variant declares.

    If ``root`` holds no store and ``synth`` is given, SynthFaces is generated there first
    (``synth`` = keyword arguments of :func:`difareli.synth.generator.generate`).
    """

    def __init__(
        self,
        root: str,
        spatial: Sequence[str] = (),
        nonspatial: Sequence[str] = (),
        resolution: int | None = None,
        batch_size: int = 32,
        num_workers: int = 0,
        synth: Mapping[str, Any] | None = None,
        train_split: str = "train",
        val_split: str = "val",
        allow_split_fallback: bool = False,
        pairs: str | None = None,
        teacher_pairs: str | None = None,
        gt_light: str = "subject",
        gt_identity: bool = False,
        gt_maps: str = "march",
        versions: Mapping[str, str | None] | None = None,
        exact_share: float = 0.0,
    ):
        super().__init__()
        self.root = Path(root)
        self.spatial, self.nonspatial = list(spatial), list(nonspatial)
        for name in [*self.spatial, *self.nonspatial]:
            e = enc.get(name)  # unknown names fail here, naming the valid ones
            if name != "image" and e.spatial != (name in self.spatial):
                kind = "spatial" if e.spatial else "non-spatial"
                raise UserError(f"encoding {name!r} is {kind}; list it under the model's {kind} inputs")
        self.resolution, self.batch_size, self.num_workers = resolution, batch_size, num_workers
        self.synth = dict(synth) if synth else None
        self.train_split, self.val_split = train_split, val_split
        self.allow_split_fallback = bool(allow_split_fallback)
        # The student's pair sampler (difareli.lit.pairs.PAIR_SAMPLERS: teacher | gt | mix | gt_shadow |
        # identity); None: records.
        self.pairs, self.teacher_pairs, self.gt_light, self.gt_identity = pairs, teacher_pairs, gt_light, gt_identity
        self.gt_maps = gt_maps
        #: derived encoding versions read in place of their base (``{"shadow_map": "diff-1a2b"}``;
        #: difareli.data.derived)
        self.versions = {k: v for k, v in dict(versions or {}).items() if v is not None}
        if not 0.0 <= float(exact_share) <= 1.0:
            raise UserError(f"data.exact_share={exact_share} is a probability: give a number in [0, 1]")
        #: share of training records served with their exact inputs (the store's ``*_gt``) in place of the estimated
        self.exact_share = float(exact_share)
        self.store: EncodingStore | None = None
        self.train_set = self.val_set = None

    @property
    def required(self) -> list[str]:
        """Every encoding this module reads: the image plus the variant's declared inputs."""
        return ["image", *self.spatial, *self.nonspatial]

    def prepare_data(self) -> None:
        if (self.root / "store.json").exists():
            self.check_store_settings()
            return
        if self.synth is None:
            raise UserFileNotFoundError(
                f"no encodings store at {self.root} (no store.json): run `difareli-synth out_dir={self.root}` or "
                "`difareli-preprocess`, or point data.root at an existing store"
            )
        from difareli.synth.generator import generate  # only needed when the data set is missing

        generate(out_dir=str(self.root), resolution=self.resolution, **self.synth)

    def check_store_settings(self) -> None:
        """An existing store at ``root`` is reused only if it was generated with the ``synth`` settings asked for
        (and ``resolution``); otherwise one line names the differing settings and the fix. Without the check,
        ``data.synth.subjects=8`` on a root that already held a 250-subject store trained on the 250 silently."""
        if self.synth is None:  # data.synth=null: the store as it is
            return
        asked = {k: v for k, v in self.synth.items() if k in {f.name for f in fields(SynthConfig)}}
        asked.setdefault("resolution", self.resolution)
        try:
            want = SynthConfig(**asked).header_meta()
        except (ConfigError, TypeError):  # invalid settings: generate() names them if they are ever used
            return
        have = EncodingStore.open(self.root).store_meta
        keys = ["generator"] + [f.name for f in fields(SynthConfig)]
        # Keys an older store's header lacks are not differences: it predates them and still opens.
        diff = [f"{k}: {have.get(k)!r} in the store, {want[k]!r} asked" for k in keys
                if (k == "generator" or k in have) and have.get(k) != want[k]]
        if diff:
            raise UserError(f"data.root={self.root} already holds a store made with other settings than data.synth "
                            f"asks for ({'; '.join(diff)}); use another data.root to generate these settings, or "
                            "data.synth=null to train on the store as it is")

    def _open(self) -> EncodingStore:
        if self.store is None:
            self.prepare_data()
            self.store = EncodingStore.open(self.root).use_versions(self.versions)
            missing = [n for n in self.required if not self.store.available(n)]
            if missing:
                raise MissingEncodingError(
                    f"the model needs encoding(s) {missing} but the data set at {self.root} has only "
                    f"{list(self.store.encodings)}; re-create it with an estimator/generator that writes them, "
                    "or pick a model variant that does not consume them"
                )
            res = self.store.dims.get("H")
            if self.resolution is not None and res != self.resolution:
                raise UserError(
                    f"data.resolution={self.resolution} but the store at {self.root} holds {res}x{res} images; "
                    f"set data.resolution={res} or point data.root at a {self.resolution}px store"
                )
        return self.store

    def shadow_map_maker(self) -> dict:
        """What made the ``shadow_map`` this module reads: for a student's pairs whose target maps are re-rendered
        (teacher, identity and mixed pairs, ground-truth pairs unless ``gt_maps=stored``), the relight's own maker
        (:func:`render.retarget.shadow_maker`); else a derived version's method and maker (its provenance), else
        SynthFaces' mesh rays (toward the fitted or the exact light, as its header says), else
        ``{"name": "store"}`` (not known)."""
        if self.pairs and not (self.pairs in ("gt", "gt_shadow") and self.gt_maps == "stored"):
            return shadow_maker()
        store = self._open()
        version = self.versions.get("shadow_map")
        if version:
            prov = dict(store.derived.get(f"shadow_map@{version}", {}))
            return dict(prov.get("maker") or {"name": prov.get("method", "difference"), "version": version})
        meta = store.store_meta
        if meta.get("generator") == "synthfaces":  # SynthFaces' own maps: mesh rays (the header says toward what)
            return {"name": "mesh", "light": "exact" if meta.get("inputs") == "exact" else "fitted"}
        return {"name": "store"}

    def input_dims(self) -> dict[str, int]:
        """Sizes the network needs: spatial channels, non-spatial vector length, image resolution."""
        store = self._open()
        return input_dims(self.spatial, self.nonspatial, store.dims, int(store.dims["H"]))

    def check_checkpoint(self, config: dict, checkpoint: Any) -> None:
        """A checkpoint (its hyperparameters ``config``) that starts or resumes training on this store must read
        its encodings: else one line naming both (:func:`difareli.data.inputs.check_store_fits`)."""
        check_store_fits(config, self._open(), checkpoint)

    def _split_ids(self) -> tuple[list[str], list[str]]:
        store = self._open()
        train, val = store.ids(split=self.train_split), store.ids(split=self.val_split)
        if not train:  # a store without split metadata: hold out every 20th record, deterministically
            if not self.allow_split_fallback:
                found = sorted({str(m.get("split")) for m in store.index.values()})
                raise UserError(f"store {self.root} has no records in split {self.train_split!r} (splits: {found}); "
                                "set +data.train_split=<split>, or data.allow_split_fallback=true to train on all "
                                "records, holding out every 20th")
            ids = store.ids()
            val = ids[::20]
            held = set(val)
            train = [i for i in ids if i not in held]
        return train, val or train[:1]

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        store = self._open()
        train, val = self._split_ids()
        if self.pairs:
            teacher = EncodingStore.open(self.teacher_pairs) if self.teacher_pairs else None
            self.train_set = pair_dataset(self.pairs, store, train, self.spatial, self.nonspatial, teacher,
                                          self.gt_light, self.gt_identity, self.gt_maps)
            # Validation: ground truth where the store has it (SynthFaces), else the training pairs' kind; its
            # target maps the march's (gt_maps' default), as a relight's at test time.
            synthfaces = store.meta(val[0]).get("subject")
            kind = "gt" if self.pairs in ("teacher", "mix", "gt_shadow") and synthfaces else self.pairs
            self.val_set = pair_dataset(kind, store, val, self.spatial, self.nonspatial, teacher, self.gt_light)
            return
        self.train_set = EncodingsDataset(store, train, self.spatial, self.nonspatial, self.exact_share)
        self.val_set = EncodingsDataset(store, val, self.spatial, self.nonspatial)

    def nonspatial_stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-feature mean and std of the non-spatial vector over the training split (std floored at 1e-6)."""
        self.setup()
        store = self._open()
        if not self.nonspatial:
            return np.zeros(0, np.float32), np.ones(0, np.float32)
        vecs = np.stack([prepare_nonspatial(self.nonspatial, store.read(r, self.nonspatial)).numpy()
                         for r in self.train_set.ids])
        bad = [r for r, v in zip(self.train_set.ids, vecs) if not np.isfinite(v).all()]
        if bad:  # found before the first step: the statistics (and every weight after them) would be NaN
            raise UserError(f"{len(bad)} training record(s) of store {self.root} have non-finite {self.nonspatial} "
                            f"values: {bad[:10]}; regenerate or remove them (difareli-store verify {self.root})")
        mean, std = vecs.mean(0), vecs.std(0)
        # Constant features (e.g. a fixed camera) would divide by ~0: leave them unscaled instead.
        std = np.where(std < 1e-6, 1.0, std)
        return mean.astype(np.float32), std.astype(np.float32)

    def _loader(self, ds: Dataset, shuffle: bool) -> DataLoader:
        return DataLoader(ds, batch_size=self.batch_size, shuffle=shuffle, num_workers=self.num_workers,
                          persistent_workers=self.num_workers > 0, drop_last=shuffle and len(ds) > self.batch_size)

    def train_dataloader(self) -> DataLoader:
        self.setup()
        return self._loader(self.train_set, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        self.setup()
        return self._loader(self.val_set, shuffle=False)
