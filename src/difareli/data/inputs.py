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
from difareli.errors import MissingError, UserError, check_record

Condition = tuple[Tensor | None, Tensor | None]  # (spatial [B, C, H, W], non-spatial [B, D]), raw encodings


class MissingEncodingError(MissingError):
    """A model variant needs an encoding the data set does not have."""


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
    :class:`~difareli.relight.relightable.Relightable`) of several records (or retargeted records) into ``(spatial,
    nonspatial)``; ``None`` for a kind the model does not consume."""
    spatial, nonspatial = model.spatial_inputs, model.nonspatial_inputs
    sp = torch.stack([prepare_spatial(spatial, a) for a in arrays_list]).to(device) if spatial else None
    ns = torch.stack([prepare_nonspatial(nonspatial, a) for a in arrays_list]).to(device) if nonspatial else None
    return sp, ns


def read_record(store, record_id: str, names: Sequence[str]) -> dict[str, np.ndarray]:
    """A store record's encodings ``names`` as checked arrays (finite, plausible lights), with the store's c range
    beside them (``encodings.C_RANGE_KEY``) when its header records one: every reader that re-renders a target
    shadow map from a record then scales it as the store's own maps are (SynthFaces v3)."""
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


def _widths(names: Sequence[str], dims: Mapping[str, int], available=lambda name: True) -> str:
    return ", ".join(f"{n} {enc.channels(n, {**enc.PRODUCER_DIMS, **dims})}" if available(n) else f"{n} missing"
                     for n in names)


def _expects(config: Mapping[str, Any]) -> str:
    """What a checkpoint's model reads (resolution, inputs, widths), for a message: ``it expects ...``."""
    want = config["input_dims"]
    res = f"{want['resolution']} px, " if want.get("resolution") else ""
    spatial, nonspatial = list(config.get("spatial_inputs") or []), list(config.get("nonspatial_inputs") or [])
    return (f"it expects {res}spatial inputs {', '.join(spatial) or 'none'} ({want['spatial_channels']} channels) "
            f"and a non-spatial condition of {want['nonspatial_dim']} values ({', '.join(nonspatial) or 'none'})")


def _fits(config: Mapping[str, Any], dims: Mapping[str, int], available=lambda name: True
          ) -> tuple[bool, str | None]:
    """(whether ``config``'s model reads encodings of ``dims``, what they give: None where it is not checked)."""
    want = dict(config.get("input_dims") or {})
    if "spatial_channels" not in want or "nonspatial_dim" not in want:
        return True, None
    spatial, nonspatial = list(config.get("spatial_inputs") or []), list(config.get("nonspatial_inputs") or [])
    missing = [n for n in spatial + nonspatial if not available(n)]
    if missing:
        return False, f"lacks {missing}"
    have = input_dims(spatial, nonspatial, dims)
    ok = (have["spatial_channels"], have["nonspatial_dim"]) == (want["spatial_channels"], want["nonspatial_dim"])
    return ok, (f"gives {have['spatial_channels']} channels ({_widths(spatial, dims, available)}) and "
                f"{have['nonspatial_dim']} values ({_widths(nonspatial, dims, available)})")


def check_store_fits(config: Mapping[str, Any], store, checkpoint: Any = "the checkpoint") -> None:
    """A checkpoint's model (its hyperparameters ``config``: inputs and ``input_dims``) can read ``store``'s
    encodings: same spatial channels and non-spatial width, every input present. Else one UserError naming the
    checkpoint, what it expects (resolution, inputs, sizes), what the store gives and the fix, in place of a
    tensor-size mismatch deep in the model. A resolution alone that differs is not refused (the network is
    convolutional; the relighter says it in its notes). A config without ``input_dims`` is not checked."""
    ok, gives = _fits(config, store.dims, store.available)
    if ok:
        return
    size = int(store.dims.get("H", 0))
    kind = store.store_meta.get("generator") or store.store_meta.get("source") or "a store"
    raise UserError(
        f"checkpoint={checkpoint} cannot read store {store.root}: {_expects(config)}; the store ({kind}, {size} px) "
        f"{gives}; use a checkpoint trained on a store like this one (difareli-train data.root={store.root}), or a "
        "store made like the checkpoint's training data (an imported official checkpoint reads stores written by "
        "difareli.official.importers)")


def check_photo_fits(config: Mapping[str, Any], dims: Mapping[str, int], checkpoint: Any, what: str) -> None:
    """Like :func:`check_store_fits` for a photo, before its estimators run: ``dims`` are the photo estimators'
    (``Pipeline.dims``). An imported official checkpoint reads other widths (its shape, identity) than they write:
    said here, with the model's resolution, in place of what a run of the estimators at that size would blame."""
    ok, gives = _fits(config, dims)
    if not ok:
        raise UserError(
            f"checkpoint={checkpoint} cannot relight {what}: {_expects(config)}; what the photo estimators write "
            f"(difareli-preprocess's) {gives}; relight photos with a checkpoint trained on such encodings (e.g. "
            "difareli_pp-synth64), or this one on a store made like its training data (an imported official "
            "checkpoint reads stores written by difareli.official.importers)")
