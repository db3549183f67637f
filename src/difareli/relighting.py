"""Relight store records from a checkpoint: the API the CLI and the notebooks share.

``Relighter(checkpoint, sampler)`` binds a trained model and a sampler; ``relight_record(store, id, lights)``
inverts the record once (cached, with its mean-matching offsets) and decodes any number of target lights in
batches. Only the encodings the model consumes, plus those retargeting needs, are read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from difareli import viz
from difareli.data import image_to_tensor, prepare_nonspatial, prepare_spatial
from difareli.diffusion.relight import Inversion, SamplerSpec, decode, invert
from difareli.lit import LoadedCheckpoint, load_checkpoint
from difareli.store import EncodingStore
from difareli.targets import retarget

#: Encodings retargeting reads besides the model's own inputs, per model input that depends on the light.
_RETARGET_NEEDS = {"shading": ("normal",), "shadow_map": ("depth", "normal", "cam", "shadow"), "light": ()}


def resolve_device(device: str = "auto") -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class Relighter:
    """A trained model + a sampler, relighting records of an encodings store."""

    def __init__(self, checkpoint: str | Path | LoadedCheckpoint, sampler: SamplerSpec | Mapping[str, Any],
                 *, device: str = "auto", mean_matching: bool = True, batch_size: int = 16, progress: bool = False):
        self.device = resolve_device(device)
        ckpt = checkpoint if isinstance(checkpoint, LoadedCheckpoint) else load_checkpoint(checkpoint, self.device)
        self.model = ckpt.model.to(self.device)
        self.config = ckpt.config
        self.spec = sampler if isinstance(sampler, SamplerSpec) else SamplerSpec.from_config(sampler)
        self.mean_matching, self.batch_size, self.progress = mean_matching, batch_size, progress
        self.spatial = list(self.config.get("spatial_inputs") or [])
        self.nonspatial = list(self.config.get("nonspatial_inputs") or [])
        self._inversions: dict[tuple[str, str], Inversion] = {}

    @property
    def model_inputs(self) -> list[str]:
        return [*self.spatial, *self.nonspatial]

    def needed_encodings(self) -> list[str]:
        """Encodings read per record: the image, the model's inputs, and what retargeting them needs."""
        names = ["image", "light", *self.model_inputs]
        for n in self.model_inputs:
            names += _RETARGET_NEEDS.get(n, ())
        return list(dict.fromkeys(names))

    def read(self, store: EncodingStore, record_id: str) -> dict[str, np.ndarray]:
        missing = [n for n in self.needed_encodings() if not store.available(n)]
        if missing:
            raise KeyError(f"relighting with this model needs encoding(s) {missing}, which the store at "
                           f"{store.root} does not have")
        return {k: np.asarray(v) for k, v in store.read(record_id, self.needed_encodings()).items()}

    def _condition_tensors(self, arrays_list: Sequence[Mapping[str, np.ndarray]]):
        sp = torch.stack([prepare_spatial(self.spatial, a) for a in arrays_list]).to(self.device)
        ns = torch.stack([prepare_nonspatial(self.nonspatial, a) for a in arrays_list]).to(self.device)
        return (sp if self.spatial else None), (ns if self.nonspatial else None)

    @torch.no_grad()
    def inversion(self, store: EncodingStore, record_id: str, arrays: Mapping[str, np.ndarray] | None = None) -> Inversion:
        """Passes 1-2 for a record (inversion + mean-matching offsets), computed once and cached."""
        key = (str(store.root), record_id)
        if key not in self._inversions:
            arrays = arrays if arrays is not None else self.read(store, record_id)
            x0 = image_to_tensor(arrays["image"])[None].to(self.device)
            cond = self.model.condition(*self._condition_tensors([arrays]))
            self._inversions[key] = invert(self.model.denoiser(cond), x0, self.model.schedule, self.spec,
                                           mean_matching=self.mean_matching, progress=self.progress)
        return self._inversions[key]

    @torch.no_grad()
    def relight_record(self, store: EncodingStore, record_id: str, lights: Iterable[np.ndarray],
                       shadows: Iterable[float | None] | None = None) -> np.ndarray:
        """Relit images (N, H, W, 3) uint8 of one record under N target lights (and shadow logits c')."""
        arrays = self.read(store, record_id)
        lights = [np.asarray(l, dtype=np.float64) for l in lights]
        shadows = list(shadows) if shadows is not None else [None] * len(lights)
        if len(shadows) != len(lights):
            raise ValueError(f"{len(lights)} target lights but {len(shadows)} shadow values")
        inv = self.inversion(store, record_id, arrays)
        out = []
        chunks = range(0, len(lights), self.batch_size)
        for start in tqdm(chunks, desc="relight", disable=not self.progress or len(chunks) == 1):
            batch = [retarget(arrays, self.model_inputs, l, s)
                     for l, s in zip(lights[start:start + self.batch_size], shadows[start:start + self.batch_size])]
            cond = self.model.condition(*self._condition_tensors(batch))
            x = decode(self.model.denoiser(cond), inv.expand(len(batch)), self.model.schedule)
            out.extend(viz.to_uint8(xi.clamp(-1, 1)) for xi in x)
        return np.stack(out)


def write_video(frames: np.ndarray, path: str | Path, fps: int = 20) -> Path:
    """Write frames (N, H, W, 3) uint8 as a GIF (or MP4 when imageio's ffmpeg plugin is installed)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gif":
        iio.imwrite(path, frames, duration=1000 / fps, loop=0)
    else:
        try:
            iio.imwrite(path, frames, fps=fps, codec="libx264")
        except Exception as e:  # no ffmpeg backend
            raise RuntimeError(f"cannot write {path} ({e}); install imageio[ffmpeg] or use a .gif path") from e
    return path
