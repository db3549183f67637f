"""The conditional DDIM as a LightningModule: ``L_simple`` on eps for every model variant (SPEC 4).

Variants differ only by configuration: which encodings feed the spatial conditioning (and through which
component) and which feed AdaGN. Hyperparameters are plain config values so checkpoints load with
``torch.load(weights_only=True)``; the non-spatial normalisation statistics are buffers, so they travel in
the checkpoint's ``state_dict`` (written back exactly: the EMA callback would otherwise average them too).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import lightning as L
import torch
import torch.nn.functional as F

from difareli.diffusion.schedule import DiffusionSchedule
from difareli.nn import build_network


class DiffusionModule(L.LightningModule):
    """Conditional DDIM (UNet + spatial + non-spatial conditioning) trained with ``L_simple``."""

    def __init__(
        self,
        name: str = "difareli_pp",
        preset: str = "tiny",
        spatial_type: str | None = "modulator",
        spatial_inputs: Sequence[str] = ("shading", "shadow_map", "masks"),
        nonspatial_inputs: Sequence[str] = ("shape", "cam", "identity"),
        input_dims: Mapping[str, int] | None = None,
        modulate_skips: bool = False,
        adagn_scale_plus_one: bool = True,
        net_overrides: Mapping[str, Any] | None = None,
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        schedule: Mapping[str, Any] | None = None,
        compile: bool = False,
    ):
        super().__init__()
        if input_dims is None:
            raise ValueError("DiffusionModule needs input_dims (spatial_channels, nonspatial_dim, resolution): "
                             "difareli-train takes them from the DataModule")
        self.save_hyperparameters()
        dims = dict(input_dims)
        spatial_type = spatial_type if spatial_inputs else None
        # Attention resolutions are feature-map sizes at the data resolution unless overridden.
        overrides = {"image_size": int(dims["resolution"]), "adagn_scale_plus_one": adagn_scale_plus_one,
                     **dict(net_overrides or {})}
        self.net = build_network(
            preset=preset,
            spatial_type=spatial_type,
            spatial_channels=int(dims["spatial_channels"]) if spatial_type else 0,
            nonspatial_dim=int(dims["nonspatial_dim"]),
            overrides=overrides,
            spatial_kwargs={"modulate_skips": modulate_skips} if spatial_type == "modulator" else None,
        )
        self.schedule = DiffusionSchedule(**dict(schedule or {}))
        d = int(dims["nonspatial_dim"])
        self.register_buffer("ns_mean", torch.zeros(d))
        self.register_buffer("ns_std", torch.ones(d))

    # ------------------------------------------------------------------ conditioning
    def set_nonspatial_stats(self, mean, std) -> None:
        """Store the training split's non-spatial mean/std (they go into the checkpoint)."""
        self.ns_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.ns_std.copy_(torch.as_tensor(std, dtype=torch.float32))
        self._exact_stats = (self.ns_mean.detach().clone(), self.ns_std.detach().clone())

    # The EMA callback averages buffers too: for constants, decay * x + (1 - decay) * x drifts by rounding, so
    # the exact statistics are written back into the saved (EMA) state and into the model after training.
    _exact_stats: tuple[torch.Tensor, torch.Tensor] | None = None

    def on_load_checkpoint(self, checkpoint) -> None:
        sd = checkpoint["state_dict"]
        self._exact_stats = (sd["ns_mean"].detach().clone(), sd["ns_std"].detach().clone())

    def on_save_checkpoint(self, checkpoint) -> None:
        if self._exact_stats is not None:
            checkpoint["state_dict"]["ns_mean"], checkpoint["state_dict"]["ns_std"] = (
                t.clone() for t in self._exact_stats)

    def on_train_end(self) -> None:
        if self._exact_stats is not None:
            self.ns_mean.copy_(self._exact_stats[0])
            self.ns_std.copy_(self._exact_stats[1])

    @property
    def spatial_inputs(self) -> list[str]:
        """Encodings fed to the spatial component (the Relightable interface)."""
        return list(self.hparams.spatial_inputs or [])

    @property
    def nonspatial_inputs(self) -> list[str]:
        """Encodings fed to AdaGN (the Relightable interface)."""
        return list(self.hparams.nonspatial_inputs or [])

    def normalize_nonspatial(self, v: torch.Tensor) -> torch.Tensor | None:
        if v is None or v.shape[-1] == 0:
            return None
        return (v.float() - self.ns_mean) / self.ns_std

    def condition(self, spatial: torch.Tensor | None, nonspatial: torch.Tensor | None):
        """Prepare a condition once (runs the Modulator); pass it to every denoiser call."""
        if spatial is not None and spatial.shape[1] == 0:
            spatial = None
        return self.net.condition(spatial, self.normalize_nonspatial(nonspatial))

    def denoiser(self, cond):
        """The sampler interface: ``eps = denoiser(x_t, t)`` with this condition bound."""
        return self.net.bind(cond)

    # ------------------------------------------------------------------ training
    def setup(self, stage: str) -> None:
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        # Fresh runs take statistics from the training split; a resumed run restores them from the checkpoint.
        if stage == "fit" and dm is not None and hasattr(dm, "nonspatial_stats") and not self._stats_loaded():
            self.set_nonspatial_stats(*dm.nonspatial_stats())
        if self.hparams.compile:
            self.net.compile()

    def _stats_loaded(self) -> bool:
        return bool(self.trainer.ckpt_path)

    def diffusion_loss(self, batch: Mapping[str, Any], generator: torch.Generator | None = None) -> torch.Tensor:
        """``L_simple``: MSE between the true and the predicted noise at uniform random t."""
        x0 = batch["image"]
        b = x0.shape[0]
        t = torch.randint(0, self.schedule.T, (b,), device=x0.device, generator=generator)
        noise = torch.randn(x0.shape, device=x0.device, generator=generator, dtype=x0.dtype)
        x_t = self.schedule.q_sample(x0, t, noise)
        cond = self.condition(batch.get("spatial"), batch.get("nonspatial"))
        eps = self.net(x_t, t, cond)
        return F.mse_loss(eps.float(), noise.float())

    def training_step(self, batch, batch_idx):
        loss = self.diffusion_loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["image"].shape[0])
        return loss

    def validation_step(self, batch, batch_idx):
        # Fixed noise and timesteps per batch so val/loss is comparable across validations.
        g = torch.Generator(device=batch["image"].device).manual_seed(1000 + batch_idx)
        loss = self.diffusion_loss(batch, generator=g)
        self.log("val/loss", loss, prog_bar=True, batch_size=batch["image"].shape[0])
        return loss

    def configure_optimizers(self):
        return torch.optim.AdamW(self.net.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)

    @torch.no_grad()
    def predict_x0(self, x_t: torch.Tensor, t: torch.Tensor, cond) -> torch.Tensor:
        """One-step estimate of x0 from x_t (used for reconstruction grids)."""
        eps = self.net(x_t, t, cond).float()
        a = self.schedule.alphas_cumprod_t(t, x_t)
        return ((x_t.float() - (1 - a).sqrt() * eps) / a.sqrt()).clamp(-1, 1)
