"""The conditional DDIM as a LightningModule: ``L_simple`` on eps for every model variant (SPEC 4).

Variants differ only by configuration: which encodings feed the spatial conditioning (and through which
component, ``spatial: {type: ..., <options>}``) and which feed AdaGN. Hyperparameters are plain values so
checkpoints load with ``torch.load(weights_only=True)``: the optimizer and LR schedule arrive as Hydra partials
and are recorded as their plain config dicts. The non-spatial normalisation statistics arrive at construction
(``nonspatial_stats``, computed by difareli-train from the training split) and are recorded exactly in the
hyperparameters; they are constants, not weights, so they stay out of ``state_dict`` and out of the EMA average.
"""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F

from difareli.checkpoints.format import stamp, upgrade_checkpoint
from difareli.checkpoints.loading import register
from difareli.diffusion.schedule import DiffusionSchedule
from difareli.errors import UserError
from difareli.nn import build_network
from difareli.runtime.core import compile_for_training
from difareli.data import encodings

#: The public code's optimizer (guided-diffusion TrainLoop: AdamW, constant LR, no weight decay).
DEFAULT_OPTIMIZER = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 1e-4, "weight_decay": 0.0}
#: The training loss: ``simple`` (the paper's L_simple on eps) or ``min_snr`` (Min-SNR-gamma weighting, Hang et al.
#: 2023: each sample's eps error times min(SNR_t, gamma) / SNR_t). val/loss is always L_simple.
LOSS_WEIGHTINGS = ("simple", "min_snr")
DEFAULT_LOSS = {"weighting": "simple", "min_snr_gamma": 5.0}


def loss_config(loss: Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``loss`` hyperparameters, checked (checkpoints without them: L_simple)."""
    cfg = {**DEFAULT_LOSS, **dict(loss or {})}
    unknown = set(cfg) - set(DEFAULT_LOSS)
    if unknown or cfg["weighting"] not in LOSS_WEIGHTINGS or not float(cfg["min_snr_gamma"]) > 0:
        raise UserError(f"model.loss={dict(loss or {})} is invalid: weighting is one of {list(LOSS_WEIGHTINGS)}, "
                        f"min_snr_gamma > 0, no other keys (e.g. model.loss.weighting=min_snr)")
    return {"weighting": str(cfg["weighting"]), "min_snr_gamma": float(cfg["min_snr_gamma"])}


def _is_plain(value: Any) -> bool:
    if isinstance(value, Mapping):
        return all(isinstance(k, str) and _is_plain(v) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return all(_is_plain(v) for v in value)
    return value is None or isinstance(value, (bool, int, float, str))


def factory_config(factory: Callable | Mapping[str, Any] | None, what: str) -> dict[str, Any] | None:
    """The plain ``{_target_, _partial_: true, <kwargs>}`` dict of an optimizer/scheduler factory (a Hydra
    partial, a class, or such a dict already), so checkpoints record e.g. the learning rate as plain values."""
    if factory is None:
        return None
    if isinstance(factory, Mapping):
        cfg = dict(factory)
    else:
        is_partial = isinstance(factory, functools.partial)
        if is_partial and factory.args:
            raise UserError(f"model.{what}: positional arguments cannot be recorded; use keywords")
        func, kwargs = (factory.func, dict(factory.keywords)) if is_partial else (factory, {})
        cfg = {"_target_": f"{func.__module__}.{func.__qualname__}", **kwargs}
    cfg["_partial_"] = True
    if "_target_" not in cfg or not _is_plain(cfg):
        raise UserError(f"model.{what} must be a Hydra partial ({{_target_: ..., _partial_: true}}) with plain "
                        f"keyword values; got {factory!r}")
    return cfg


def _factory(cfg: Mapping[str, Any] | None) -> Callable | None:
    if cfg is None:
        return None
    from hydra.utils import instantiate

    return instantiate(dict(cfg))


class RelightingModule(L.LightningModule):
    """What every trained relighting model shares (the DDIM, the one-pass student): the non-spatial
    normalisation statistics (constants that follow ``.to()`` but stay out of ``state_dict`` and the EMA), the
    encodings a condition is made of, the recorded module class, the optimizer / LR-schedule partials and the
    ``setup`` of a fit (per-rank seeds, ``torch.compile``). Subclasses set ``net`` (the rest: :meth:`_common`) and
    are registered with the checkpoint loader as they are defined (a checkpoint names its class)."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        register(cls)
        # The constructor published whole on the class (its own parameters, then what every model takes: _common's)
        # for whoever reads it: checkpoints.loading.check_parameters checks a checkpoint's hyperparameters against
        # it. Not on __init__ itself: Lightning reads that one against the constructor's locals.
        own = inspect.signature(cls.__init__)
        common = [q.replace(kind=q.KEYWORD_ONLY) for k, q in inspect.signature(cls._common).parameters.items()
                  if k not in ("self", "own", "name")]
        cls.__signature__ = own.replace(parameters=[
            *(q for k, q in own.parameters.items() if k != "self" and q.kind is not q.VAR_KEYWORD), *common])
        cls.__init__.__annotations__ = {**typing.get_type_hints(cls._common), **typing.get_type_hints(cls.__init__)}

    def _common(self, own: Mapping[str, Any], *, name: str, preset: str = "tiny",
                spatial: str | Mapping[str, Any] | None = "modulator",
                spatial_inputs: Sequence[str] = ("shading", "shadow_map", "masks"),
                nonspatial_inputs: Sequence[str] = ("shape", "cam", "identity"),
                input_dims: Mapping[str, int] | None = None, adagn_scale_plus_one: bool = True,
                adagn_out_silu: bool = True, net_overrides: Mapping[str, Any] | None = None,
                optimizer: Callable | Mapping[str, Any] | None = None,
                scheduler: Callable | Mapping[str, Any] | None = None,
                nonspatial_stats: Mapping[str, Sequence[float]] | None = None, compile: bool = False,
                training_maps: Mapping[str, Any] | None = None) -> tuple[dict[str, int], dict[str, Any] | None]:
        """What every model's constructor takes beside its ``own`` hyperparameters: sets the inputs, the statistics,
        the optimizer / scheduler partials, the network's overrides (``self._net_overrides``) and the recorded
        hyperparameters; returns the input widths as ints and the spatial component in its one recorded form,
        ``{type: <name>, <options>}`` (None without spatial encodings)."""
        if input_dims is None:
            raise UserError(f"{type(self).__name__} needs input_dims (spatial_channels, nonspatial_dim, "
                            "resolution): difareli-train takes them from the DataModule")
        dims = {k: int(v) for k, v in dict(input_dims).items()}
        self.spatial_inputs, self.nonspatial_inputs = list(spatial_inputs), list(nonspatial_inputs)
        spatial = {"type": spatial} if isinstance(spatial, str) else dict(spatial) if spatial is not None else None
        if not self.spatial_inputs or (spatial is not None and spatial.get("type") in (None, "none")):
            spatial = None  # an ablation that drops the spatial encodings
        self.ns_mean, self.ns_std = self._check_stats(nonspatial_stats, dims["nonspatial_dim"])
        self.save_hyperparameters({
            "name": name, "preset": preset, "spatial": spatial, "spatial_inputs": self.spatial_inputs,
            "nonspatial_inputs": self.nonspatial_inputs, "input_dims": dims,
            "adagn_scale_plus_one": bool(adagn_scale_plus_one), "adagn_out_silu": bool(adagn_out_silu),
            "net_overrides": dict(net_overrides or {}),
            "optimizer": factory_config(optimizer if optimizer is not None else DEFAULT_OPTIMIZER, "optimizer"),
            "scheduler": factory_config(scheduler, "scheduler"),
            "nonspatial_stats": {"mean": self.ns_mean.tolist(), "std": self.ns_std.tolist()},
            "compile": bool(compile), **own,
            # What made the shadow maps it trained on (render.retarget.check_maker compares a relight's).
            "training_maps": dict(training_maps) if training_maps else None,
        })
        self._optimizer, self._scheduler = optimizer, scheduler
        # Attention resolutions are feature-map sizes at the data resolution unless overridden.
        self._net_overrides = {"image_size": dims["resolution"], "adagn_scale_plus_one": bool(adagn_scale_plus_one),
                               "adagn_out_silu": bool(adagn_out_silu), **dict(net_overrides or {})}
        return dims, spatial

    @staticmethod
    def _check_stats(stats: Mapping[str, Sequence[float]] | None, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
        if stats is None:  # identity normalisation (difareli-train always passes the training split's)
            return torch.zeros(dim), torch.ones(dim)
        mean = torch.as_tensor(list(stats["mean"]), dtype=torch.float32).reshape(-1)
        std = torch.as_tensor(list(stats["std"]), dtype=torch.float32).reshape(-1)
        if mean.numel() != dim or std.numel() != dim or not bool((std > 0).all()):
            raise UserError(f"nonspatial_stats needs {dim} means and {dim} positive stds (the non-spatial vector's "
                            f"width); got {mean.numel()} and {std.numel()}")
        return mean, std

    def _apply(self, fn, recurse: bool = True):
        # The statistics move with the module (.to / .cuda) like buffers, but are no buffers: the EMA callback
        # averages buffers, and decay * x + (1 - decay) * x is not x in float32.
        super()._apply(fn, recurse)
        self.ns_mean, self.ns_std = fn(self.ns_mean), fn(self.ns_std)
        return self

    # ------------------------------------------------------------------ relighting interface
    @property
    def training_maps(self) -> dict | None:
        """What made the shadow maps this model trained on (None: not recorded, or it reads none)."""
        return self.hparams.get("training_maps")

    @property
    def consumes(self) -> list[str]:
        """The encodings a condition is made of (spatial, then non-spatial)."""
        return list(dict.fromkeys(self.spatial_inputs + self.nonspatial_inputs))

    def normalize_nonspatial(self, v: torch.Tensor) -> torch.Tensor | None:
        if v is None or v.shape[-1] == 0:
            return None
        return (v.float() - self.ns_mean) / self.ns_std

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        stamp(checkpoint, self)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        upgrade_checkpoint(checkpoint)  # resuming from a checkpoint written before the current format

    # ------------------------------------------------------------------ training
    def setup(self, stage: str) -> None:
        if stage == "fit" and self._trainer is not None and self.trainer.world_size > 1:  # decorrelate ranks
            torch.manual_seed(torch.initial_seed() + self.trainer.global_rank)
        if self.hparams.compile:
            compile_for_training(self.net)

    def configure_optimizers(self):
        """The configured optimizer over the network; with a scheduler, stepped every training step."""
        make_opt = self._optimizer if callable(self._optimizer) else _factory(self.hparams.optimizer)
        opt = make_opt(self.net.parameters())
        make_sched = self._scheduler if callable(self._scheduler) else _factory(self.hparams.scheduler)
        if make_sched is None:
            return opt
        return {"optimizer": opt, "lr_scheduler": {"scheduler": make_sched(opt), "interval": "step"}}


class DiffusionModule(RelightingModule):
    """Conditional DDIM (UNet + spatial + non-spatial conditioning) trained with ``L_simple``.

    Implements the relighting-model interface: ``condition(spatial, nonspatial)``, ``denoiser(cond)``,
    ``schedule``, ``net``, ``spatial_inputs`` / ``nonspatial_inputs`` and ``consumes``.
    """

    def __init__(self, name: str = "difareli_pp", nonspatial: str | Mapping[str, Any] | None = "adagn",
                 schedule: Mapping[str, Any] | None = None, loss: Mapping[str, Any] | None = None, **common: Any):
        """``nonspatial``, ``schedule`` and ``loss`` are the DDIM's own; the rest (the preset, the inputs and their
        widths, the optimizer, ...) every model takes (:meth:`RelightingModule._common`)."""
        super().__init__()
        # The non-spatial component, recorded as {type: ..., <options>}; checkpoints without it: AdaGN.
        nonspatial = {"type": nonspatial or "adagn"} if not isinstance(nonspatial, Mapping) else dict(nonspatial)
        dims, spatial = self._common({"nonspatial": nonspatial, "schedule": dict(schedule or {}),
                                      "loss": loss_config(loss)}, name=name, **common)
        d = dims["nonspatial_dim"]
        self.net = build_network(self.hparams.preset, spatial, dims["spatial_channels"] if spatial is not None else 0,
                                 d, overrides=self._net_overrides, nonspatial=nonspatial,
                                 nonspatial_widths=self._nonspatial_widths(d))
        self.schedule = DiffusionSchedule(**dict(schedule or {}))

    def _nonspatial_widths(self, dim: int) -> list[int]:
        """Each non-spatial encoding's width (cross-attention makes tokens per encoding), at the producers'
        dimensions; one block of ``dim`` when a store's dimensions differ (e.g. another identity length)."""
        dims = {"H": 1, "W": 1, **encodings.PRODUCER_DIMS}
        widths = [encodings.channels(n, dims) for n in self.nonspatial_inputs]
        return widths if sum(widths) == dim else ([dim] if dim else [])

    # ------------------------------------------------------------------ relighting interface
    def condition(self, spatial: torch.Tensor | None, nonspatial: torch.Tensor | None):
        """Prepare a condition once (runs the Modulator); pass it to every denoiser call."""
        if spatial is not None and spatial.shape[1] == 0:
            spatial = None
        return self.net.condition(spatial, self.normalize_nonspatial(nonspatial))

    def denoiser(self, cond):
        """The sampler interface: ``eps = denoiser(x_t, t)`` with this condition bound."""
        return self.net.bind(cond)

    # ------------------------------------------------------------------ training
    def diffusion_loss(self, batch: Mapping[str, Any], generator: torch.Generator | None = None, *,
                       weighted: bool = True) -> torch.Tensor:
        """``L_simple``: MSE between the true and the predicted noise at uniform random t; with ``weighted`` and
        ``loss.weighting=min_snr``, each sample's error times ``min(SNR_t, gamma) / SNR_t``."""
        x0 = batch["image"]
        b = x0.shape[0]
        t = torch.randint(0, self.schedule.T, (b,), device=x0.device, generator=generator)
        noise = torch.randn(x0.shape, device=x0.device, generator=generator, dtype=x0.dtype)
        x_t = self.schedule.q_sample(x0, t, noise)
        cond = self.condition(batch.get("spatial"), batch.get("nonspatial"))
        eps = self.net(x_t, t, cond)
        loss = loss_config(self.hparams.get("loss"))
        if not weighted or loss["weighting"] == "simple":
            return F.mse_loss(eps.float(), noise.float())
        a = self.schedule.alphas_cumprod_t(t, x0).float().reshape(b)
        snr = a / (1 - a)
        weight = torch.clamp(snr, max=loss["min_snr_gamma"]) / snr
        per_sample = (eps.float() - noise.float()).pow(2).flatten(1).mean(1)
        return (weight * per_sample).mean()

    def training_step(self, batch, batch_idx):
        loss = self.diffusion_loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["image"].shape[0])
        return loss

    def validation_step(self, batch, batch_idx):
        # Fixed noise and timesteps per batch so val/loss is comparable across validations.
        g = torch.Generator(device=batch["image"].device).manual_seed(1000 + batch_idx)
        loss = self.diffusion_loss(batch, generator=g, weighted=False)  # L_simple: comparable across weightings
        self.log("val/loss", loss, prog_bar=True, batch_size=batch["image"].shape[0], sync_dist=True)
        return loss

    @torch.no_grad()
    def predict_x0(self, x_t: torch.Tensor, t: torch.Tensor, cond) -> torch.Tensor:
        """One-step estimate of x0 from x_t (used for reconstruction grids)."""
        eps = self.net(x_t, t, cond).float()
        a = self.schedule.alphas_cumprod_t(t, x_t)
        return ((x_t.float() - (1 - a).sqrt() * eps) / a.sqrt()).clamp(-1, 1)
