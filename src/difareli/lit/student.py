"""The single-shot student DiFaReli++_ss (paper Sec. IV-C) as a LightningModule: input image -> relit image.

The same UNet and Modulator as the teacher (:func:`difareli.nn.build_network`), run once: the Modulator takes
the source's spatial inputs and the target's light-dependent ones (shading reference + shadow map of each, the
paper's 8 channels, plus the masks where the variant declares them); AdaGN takes the source's non-spatial inputs
(plus the target's light-dependent non-spatial ones, e.g. c' for a DiFaReli-style variant). The time embedding
sees a constant ``timestep``. Trained with L2 (optionally + LPIPS) on pairs served by the DataModule's pair
sampler (``data.pairs``). Implements :class:`~difareli.relight.relightable.OnePassRelightable`, so every relighting CLI,
the benchmark and the speed tables take its checkpoint unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch

from difareli.data import encodings as enc
from difareli.errors import UserError
from difareli.lit.diffusion import RelightingModule
from difareli.nn import build_network
from difareli.nn.lpips import get_lpips


def _spans(names: Sequence[str], dims: Mapping[str, int]) -> list[tuple[str, range]]:
    """Each encoding of ``names`` with its channels in the concatenation, in order."""
    out, start = [], 0
    for n in names:
        c = enc.channels(n, dims)
        out.append((n, range(start, start + c)))
        start += c
    return out


def _slices(names: Sequence[str], dims: Mapping[str, int]) -> list[int]:
    """Channel indices of the light-dependent encodings among ``names`` concatenated in order."""
    return [i for n, span in _spans(names, dims) if enc.get(n).light_dependent for i in span]


class StudentModule(RelightingModule):
    """One-pass relighting network trained on (source, target light, relit image) pairs.

    Offers ``spatial_inputs``, ``nonspatial_inputs``, ``condition(spatial, nonspatial)`` (no network work: the
    Modulator needs both conditions) and ``relight_once(x0, source_cond, target_cond)``.
    """

    def __init__(self, name: str = "student", residual: bool = True, timestep: int = 0, lpips_weight: float = 0.0,
                 shadow_weight: float = 0.0, **common: Any):
        """``residual``, ``timestep``, ``lpips_weight`` and ``shadow_weight`` (:meth:`loss`) are the student's own;
        the rest (the preset, the inputs and their widths, the optimizer, ...) every model takes
        (:meth:`RelightingModule._common`)."""
        super().__init__()
        dims, spatial = self._common({"residual": bool(residual), "timestep": int(timestep),
                                      "lpips_weight": float(lpips_weight), "shadow_weight": float(shadow_weight)},
                                     name=name, **common)
        if not enc.light_dependent(self.spatial_inputs + self.nonspatial_inputs):
            raise UserError(f"a student needs light-dependent inputs (e.g. shading, shadow_map) to know the target; "
                            f"got {self.spatial_inputs + self.nonspatial_inputs}")
        # Light-dependent channels only depend on H, W (shading 3, shadow map 1, light 27, c 1).
        hw = {"H": dims["resolution"], "W": dims["resolution"]}
        self._sp_dep = _slices(self.spatial_inputs, hw)
        # Where the shadow map lies among the spatial channels (the shadow-weighted L2 reads it); None: no map.
        self._sp_map = next((span.start for n, span in _spans(self.spatial_inputs, hw) if n == "shadow_map"), None)
        if self.hparams.get("shadow_weight", 0.0) and self._sp_map is None:
            raise UserError(f"model.shadow_weight weights the L2 inside the shadow maps, but this student reads none "
                            f"({self.spatial_inputs}); give model.shadow_weight=0")
        # Non-spatial widths of shape / identity are the producers' (S = 53, D = 128), as the store records.
        self._ns_dep = _slices(self.nonspatial_inputs, {**hw, **enc.PRODUCER_DIMS})
        if self._ns_dep and max(self._ns_dep) >= dims["nonspatial_dim"]:
            raise UserError(f"light-dependent non-spatial inputs of {self.nonspatial_inputs} lie beyond the "
                            f"{dims['nonspatial_dim']}-wide vector: list them before shape / identity")
        sc = dims["spatial_channels"] + len(self._sp_dep) if spatial is not None else 0
        nd = dims["nonspatial_dim"] + len(self._ns_dep)
        self.net = build_network(self.hparams.preset, spatial, sc, nd, overrides=self._net_overrides)
        self._lpips = None

    # ------------------------------------------------------------------ relighting interface
    def condition(self, spatial: torch.Tensor | None, nonspatial: torch.Tensor | None):
        """One side's condition: the raw spatial maps and the normalised non-spatial vector."""
        nonspatial = self.normalize_nonspatial(nonspatial)
        return (spatial if spatial is not None and spatial.shape[1] > 0 else None), nonspatial

    def relight_once(self, x0: torch.Tensor, source, target, runtime=None) -> torch.Tensor:
        """The relit image [B, 3, H, W] of ``x0`` in [-1, 1] from the source and target conditions. With a
        :class:`~difareli.runtime.core.Runtime` the pass runs as its denoiser does (autocast, the inference copy with
        weights cast once, channels-last, compile), as a diffusion model's passes do, its Modulator too
        (:meth:`~difareli.runtime.core.Runtime.condition`); float32 out."""
        (s_sp, s_ns), (t_sp, t_ns) = source, target
        sp = torch.cat([s_sp, t_sp[:, self._sp_dep]], 1) if s_sp is not None and self.net.spatial is not None else None
        ns = s_ns
        if self._ns_dep:
            ns = torch.cat([s_ns, t_ns[:, self._ns_dep]], 1)
        t = torch.full((x0.shape[0],), self.hparams.timestep, device=x0.device, dtype=torch.long)
        if runtime is None:
            out = self.net(x0, t, self.net.condition(sp, ns))
        else:  # the Modulator too on the inference copy: it runs at every relight, not once for many passes
            out = runtime.denoiser(self.net, runtime.condition(self.net, sp, ns))(x0, t)
        return x0 + out if self.hparams.residual else out

    # ------------------------------------------------------------------ training
    def setup(self, stage: str) -> None:
        dm = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        if stage == "fit" and dm is not None and not getattr(dm, "pairs", None):
            raise UserError("model=student trains on pairs: set data.pairs=gt (SynthFaces ground truth), teacher "
                            "(with data.teacher_pairs=<difareli-teacher-pairs store>) or mix")
        super().setup(stage)

    def loss(self, batch: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """``l2`` (MSE in [-1, 1] units) between the one-pass relight and the pair's target image, plus
        ``lpips`` when weighted; ``loss`` is their weighted sum. ``shadow_weight`` w > 0: the loss's L2 weighs each
        pixel by ``1 + w * max(source map, target map)`` (normalised to mean weight 1), so the few pixels where a
        cast shadow comes or goes count as much as the face around them; ``l2`` stays the plain MSE."""
        pred = self.relight_once(batch["image"], self.condition(batch.get("spatial"), batch.get("nonspatial")),
                                 self.condition(batch.get("target_spatial"), batch.get("target_nonspatial")))
        sq = (pred.float() - batch["target_image"].float()) ** 2
        out = {"l2": sq.mean()}
        out["loss"] = out["l2"]
        w = self.hparams.get("shadow_weight", 0.0)
        if w > 0:
            i = self._sp_map
            maps = torch.maximum(batch["spatial"][:, i], batch["target_spatial"][:, i]).float().clamp(0, 1)
            weight = (1.0 + w * maps).unsqueeze(1)
            out["loss"] = (sq * weight).mean() / weight.mean()
        if self.hparams.lpips_weight > 0:
            if self._lpips is None:
                self._lpips = [get_lpips("alex", str(pred.device))]  # a list: not a submodule, not in checkpoints
            out["lpips"] = self._lpips[0](pred.float().clamp(-1, 1), batch["target_image"].float()).mean()
            out["loss"] = out["loss"] + self.hparams.lpips_weight * out["lpips"]
        return out

    def training_step(self, batch, batch_idx):
        losses = self.loss(batch)
        b = batch["image"].shape[0]
        self.log("train/loss", losses["loss"], prog_bar=True, batch_size=b)
        if "lpips" in losses:
            self.log("train/lpips", losses["lpips"], batch_size=b)
        return losses["loss"]

    def validation_step(self, batch, batch_idx):
        losses = self.loss(batch)
        b = batch["image"].shape[0]
        self.log("val/loss", losses["loss"], prog_bar=True, batch_size=b, sync_dist=True)
        self.log("val/l2", losses["l2"], batch_size=b, sync_dist=True)
        return losses["loss"]
