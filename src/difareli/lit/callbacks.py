"""Callbacks that write images people would rather see than read."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import lightning as L
import torch

from difareli.utils import viz
from difareli.relight.relightable import DiffusionRelightable, OnePassRelightable
from difareli.diffusion.spec import SamplerSpec, as_spec
from difareli.lit.logging import log_image


def _validation_items(trainer: L.Trainer, n: int, device) -> tuple[list[dict], torch.Tensor, torch.Tensor]:
    """The first ``n`` validation records, and their spatial / non-spatial inputs stacked on ``device``."""
    ds = trainer.datamodule.val_set
    items = [ds[i] for i in range(min(n, len(ds)))]
    spatial = torch.stack([b["spatial"] for b in items]).to(device)
    nonspatial = torch.stack([b["nonspatial"] for b in items]).to(device)
    return items, spatial, nonspatial


class ReconstructionGrid(L.Callback):
    """At each validation, noise ``num_images`` validation images to several ``timesteps`` and write a grid of
    one-step x0 reconstructions (rows: images; columns: input, then x_t / x0-hat pairs per t).

    Runs on the weights being validated (the EMA weights when the EMA callback is on).
    """

    def __init__(self, num_images: int = 8, timesteps: Sequence[int] = (100, 300, 600, 900), seed: int = 0):
        self.num_images, self.timesteps, self.seed = num_images, list(timesteps), seed

    @torch.no_grad()
    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero or trainer.datamodule is None:
            return
        dev = pl_module.device
        batch, spatial, nonspatial = _validation_items(trainer, self.num_images, dev)
        n = len(batch)
        x0 = torch.stack([b["image"] for b in batch]).to(dev)
        cond = pl_module.condition(spatial, nonspatial)
        if isinstance(pl_module, OnePassRelightable):  # a one-pass student: input | relit | target per validation pair
            tgt = pl_module.condition(*(torch.stack([b[k] for b in batch]).to(dev)
                                        for k in ("target_spatial", "target_nonspatial")))
            relit = pl_module.relight_once(x0, cond, tgt)
            rows = [[viz.to_uint8(b["image"]), viz.to_uint8(r.clamp(-1, 1)), viz.to_uint8(b["target_image"])]
                    for b, r in zip(batch, relit)]
            path = Path(trainer.default_root_dir) / "grids" / f"relight_step{trainer.global_step:07d}.png"
            log_image(trainer, "val/relight_grid", viz.save_png(viz.grid(rows), path))
            return
        g = torch.Generator(device=dev).manual_seed(self.seed)
        noise = torch.randn(x0.shape, generator=g, device=dev)
        cols = [[viz.to_uint8(x) for x in x0]]
        for t_val in self.timesteps:
            t = torch.full((n,), t_val, device=dev, dtype=torch.long)
            x_t = pl_module.schedule.q_sample(x0, t, noise)
            cols.append([viz.to_uint8(x.clamp(-1, 1)) for x in x_t])
            cols.append([viz.to_uint8(x) for x in pl_module.predict_x0(x_t, t, cond)])
        rows = [[c[i] for c in cols] for i in range(n)]
        path = Path(trainer.default_root_dir) / "grids" / f"reconstruction_step{trainer.global_step:07d}.png"
        log_image(trainer, "val/reconstruction_grid", viz.save_png(viz.grid(rows), path))


class LossCurve(L.Callback):
    """Record ``train/loss`` (and ``val/loss``) during fit; at the end print the curve's numbers and write
    ``loss_curve.png`` next to the run's logs, so "the loss falls" is visible at a glance."""

    def __init__(self, every_n_steps: int = 10):
        self.every_n_steps = every_n_steps
        self.train: list[tuple[int, float]] = []
        self.val: list[tuple[int, float]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if step % self.every_n_steps == 0 and outputs is not None:
            loss = outputs["loss"] if isinstance(outputs, dict) else outputs
            self.train.append((step, float(loss.detach())))

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking and "val/loss" in trainer.callback_metrics:
            self.val.append((trainer.global_step, float(trainer.callback_metrics["val/loss"])))

    def on_fit_end(self, trainer, pl_module) -> None:
        if not self.train or not trainer.is_global_zero:
            return
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import numpy as np

        steps, losses = map(np.asarray, zip(*self.train))
        k = max(1, len(losses) // 10)
        first, last = losses[:k].mean(), losses[-k:].mean()
        print(f"train/loss: first {k} logged steps mean {first:.4f} -> last {k} mean {last:.4f} "
              f"({first / max(last, 1e-12):.1f}x lower)")
        if self.val:
            print("val/loss: " + ", ".join(f"step {s}: {v:.4f}" for s, v in self.val))
        fig, ax = plt.subplots(figsize=(5, 3.2))
        ax.semilogy(steps, losses, lw=0.8, label="train/loss")
        if self.val:
            ax.semilogy(*zip(*self.val), "o-", label="val/loss")
        ax.set_xlabel("step")
        ax.legend()
        fig.tight_layout()
        out = Path(trainer.default_root_dir) / "loss_curve.png"
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=100)
        log_image(trainer, "train/loss_curve", out)
        plt.close(fig)


class SampleGrid(L.Callback):
    """Generate ``num_images`` images from fixed noise under the first validation records' encodings with a
    :class:`~difareli.diffusion.spec.SamplerSpec`, and write ``<run>/sample_grid.png`` (top row: the real
    images, bottom row: the samples) when training ends.

    ``sampler`` is a preset name (``difareli.diffusion.spec.PRESETS``), a sampler config (``conf/sampler``) or a
    spec; ``steps`` (None: the sampler's) overrides its step count. At train end the weights are the EMA ones
    when the EMA callback is listed before this one (it copies its average into the model at ``on_train_end``).
    ``every_n_validations > 0`` also writes ``grids/sample_grid_step<step>.png`` at the start of every n-th
    validation (after the EMA callback swapped its weights in). Skipped under ``fast_dev_run`` and when
    ``enabled`` is false (``sample_grid=false`` in ``conf/train.yaml``).
    """

    def __init__(self, sampler: SamplerSpec | str | Mapping[str, Any] = "ddim", steps: int | None = None,
                 num_images: int = 8, seed: int = 0, every_n_validations: int = 0, enabled: bool = True):
        # Built here so that a bad sampler config fails before training, not after it.
        self.spec = as_spec(sampler, steps=steps)
        self.num_images, self.seed = num_images, seed
        self.every_n_validations, self.enabled = every_n_validations, enabled
        self._validations = 0

    def _active(self, trainer: L.Trainer) -> bool:
        # A one-pass student has no denoiser to sample from: nothing to draw.
        return (self.enabled and not trainer.fast_dev_run and not trainer.sanity_checking
                and trainer.is_global_zero and trainer.datamodule is not None
                and isinstance(trainer.lightning_module, DiffusionRelightable))

    @torch.no_grad()
    def write(self, trainer: L.Trainer, pl_module, path: str | Path) -> Path:
        """Sample the grid with ``pl_module``'s current weights (in eval mode) and write it to ``path``."""
        was_training = pl_module.training
        pl_module.eval()
        dev = pl_module.device
        items, spatial, nonspatial = _validation_items(trainer, self.num_images, dev)
        cond = pl_module.condition(spatial, nonspatial)
        g = torch.Generator(device=dev).manual_seed(self.seed)
        x_T = torch.randn((len(items), *items[0]["image"].shape), generator=g, device=dev)
        x0 = self.spec.generate(pl_module.denoiser(cond), x_T, pl_module.schedule)
        pl_module.train(was_training)
        rows = [[viz.to_uint8(b["image"]) for b in items], [viz.to_uint8(x.clamp(-1, 1)) for x in x0]]
        return viz.save_png(viz.grid(rows), Path(path))

    def on_validation_epoch_start(self, trainer: L.Trainer, pl_module) -> None:
        if self.every_n_validations <= 0 or not self._active(trainer):
            return
        self._validations += 1
        if self._validations % self.every_n_validations == 0:
            name = f"sample_grid_step{trainer.global_step:07d}.png"
            path = self.write(trainer, pl_module, Path(trainer.default_root_dir) / "grids" / name)
            log_image(trainer, "samples/grid", path)

    def on_train_end(self, trainer: L.Trainer, pl_module) -> None:
        if self._active(trainer):
            path = self.write(trainer, pl_module, Path(trainer.default_root_dir) / "sample_grid.png")
            log_image(trainer, "samples/grid", path)


class Throughput(L.Callback):
    """Logs ``perf/images_per_s`` and ``perf/s_per_step`` over each window of ``every_n_steps`` training steps
    (device synchronised; validation and checkpointing inside a window are excluded), so a run's speed sits in
    its metrics beside the loss (the reference recipes read it back). At every validation it logs
    ``perf/wall_s``: the run's wall-clock seconds so far, validation and checkpoints included and resumed runs
    counted on (its state is checkpointed), so scores can be plotted against the time they cost."""

    def __init__(self, every_n_steps: int = 50):
        self.every = int(every_n_steps)
        self._start: float | None = None
        self._steps = self._images = 0
        self._wall_before = 0.0  # wall seconds of the runs this one resumed
        self._fit_start: float | None = None

    def on_fit_start(self, trainer, module):
        self._fit_start = time.perf_counter()

    def wall_seconds(self) -> float:
        return self._wall_before + (time.perf_counter() - self._fit_start if self._fit_start is not None else 0.0)

    def on_validation_epoch_end(self, trainer, module):
        if not trainer.sanity_checking:
            module.log("perf/wall_s", self.wall_seconds(), on_step=False, on_epoch=True)

    def state_dict(self) -> dict:
        return {"wall_s": self.wall_seconds()}

    def load_state_dict(self, state_dict: dict) -> None:
        self._wall_before = float(state_dict.get("wall_s", 0.0))

    def _sync(self, module: L.LightningModule) -> None:
        if module.device.type == "cuda":
            torch.cuda.synchronize(module.device)

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        if self._start is None:
            self._sync(module)
            self._start = time.perf_counter()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self._steps += 1
        self._images += int(batch["image"].shape[0]) if isinstance(batch, Mapping) else 0
        if self._steps >= self.every:
            self._sync(module)
            seconds = time.perf_counter() - self._start
            module.log_dict({"perf/images_per_s": self._images / seconds, "perf/s_per_step": seconds / self._steps},
                            on_step=True, on_epoch=False)
            self._start, self._steps, self._images = None, 0, 0

    def on_validation_start(self, trainer, module):
        self._start, self._steps, self._images = None, 0, 0  # a window never spans validation
