"""Record arrays -> network tensors: the one place where named encodings become model inputs.

Used by the DataModule, the relighting core, the student's pairs, shadow-map generation and the benchmarks, so
an encoding is prepared the same way in training and at inference (each as the encoding registry says,
:meth:`difareli.data.encodings.Encoding.to_tensor`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from difareli.data import encodings as enc

Condition = tuple[Tensor | None, Tensor | None]  # (spatial [B, C, H, W], non-spatial [B, D]), raw encodings


class MissingEncodingError(KeyError):
    """A model variant needs an encoding the data set does not have."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


def image_to_tensor(image: np.ndarray) -> Tensor:
    """uint8 ``HxWx3`` -> float ``[3, H, W]`` in [-1, 1]."""
    return torch.from_numpy(np.array(image)).permute(2, 0, 1).float() / 127.5 - 1.0


def prepare_spatial(names: Sequence[str], arrays: Mapping[str, np.ndarray]) -> Tensor:
    """Concatenate spatial encodings into a float tensor ``[C, H, W]`` in the declared order."""
    return torch.cat([enc.get(n).to_tensor(arrays[n]) for n in names], 0)


def prepare_nonspatial(names: Sequence[str], arrays: Mapping[str, np.ndarray]) -> Tensor:
    """Concatenate non-spatial encodings into one raw float vector ``[D]`` in the declared order."""
    if not names:
        return torch.zeros(0)
    return torch.cat([enc.get(n).to_tensor(arrays[n]) for n in names])


def condition_tensors(model: Any, arrays_list: Sequence[Mapping[str, np.ndarray]],
                      device: torch.device | str = "cpu") -> Condition:
    """Stack the inputs a model declares (its ``spatial_inputs`` / ``nonspatial_inputs``: any
    :class:`~difareli.relight.relightable.Relightable`) of several records (or retargeted records) into ``(spatial, nonspatial)``;
    ``None`` for a kind the model does not consume."""
    spatial, nonspatial = model.spatial_inputs, model.nonspatial_inputs
    sp = torch.stack([prepare_spatial(spatial, a) for a in arrays_list]).to(device) if spatial else None
    ns = torch.stack([prepare_nonspatial(nonspatial, a) for a in arrays_list]).to(device) if nonspatial else None
    return sp, ns


def read_record(store, record_id: str, names: Sequence[str]) -> dict[str, np.ndarray]:
    """A store record's encodings ``names`` as checked arrays (finite, plausible lights), with the store's c range
    beside them (``encodings.C_RANGE_KEY``) when its header records one: every reader that re-renders a target
    shadow map from a record then scales it as the store's own maps are (SynthFaces v3)."""
    from difareli.errors import check_record

    arrays = {k: np.asarray(v) for k, v in store.read(record_id, list(names)).items()}
    return {**check_record(arrays, record_id, store.root), **enc.c_range_arrays(store.store_meta)}


def relight_reads(inputs: Sequence[str], *, rerender: bool = True) -> list[str]:
    """The encodings a relight of a record reads: the image, its light, the model's ``inputs`` and (``rerender``)
    what re-rendering the light-dependent ones toward a target light needs (the registry's ``needs``)."""
    extra = enc.rerender_needs(enc.light_dependent(inputs)) if rerender else []
    return list(dict.fromkeys(["image", "light", *inputs, *extra]))


def input_dims(spatial: Sequence[str], nonspatial: Sequence[str], dims: Mapping[str, int] | None = None,
               resolution: int | None = None) -> dict[str, int]:
    """The sizes a network is built with: spatial channels and non-spatial features of the named inputs, from
    the encoding registry at ``dims`` (default: the producers' dimensions, :data:`encodings.PRODUCER_DIMS`),
    plus ``resolution`` when given."""
    dims = {"H": resolution or 1, "W": resolution or 1, **enc.PRODUCER_DIMS, **dict(dims or {})}
    out = {"spatial_channels": enc.total_channels(list(spatial), dims),
           "nonspatial_dim": enc.total_channels(list(nonspatial), dims)}
    return {**out, "resolution": int(resolution)} if resolution is not None else out


def variant_inputs(model: str) -> tuple[list[str], list[str]]:
    """``(spatial inputs, non-spatial inputs)`` declared by the model variant ``conf/model/<model>.yaml`` (read
    as plain YAML, so this works without Hydra, e.g. on a bare GPU image)."""
    from difareli.configs import read_yaml

    cfg = read_yaml("model", model)
    return list(cfg.get("spatial_inputs") or []), list(cfg.get("nonspatial_inputs") or [])


def variant_widths(model: str, dims: Mapping[str, int] | None = None) -> tuple[int, int]:
    """``(spatial channels, non-spatial features)`` of a ``conf/model`` variant at the producers' dimensions."""
    d = input_dims(*variant_inputs(model), dims)
    return d["spatial_channels"], d["nonspatial_dim"]
