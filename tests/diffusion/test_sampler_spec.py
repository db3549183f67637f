"""SamplerSpec, the one door to the samplers: presets vs conf/sampler, validation against the sampler
signatures, the paper preset, and the SampleGrid training callback."""

from __future__ import annotations

import inspect
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from difareli.utils import viz
from difareli.configs import instantiate_group
from difareli.diffusion import PRESETS, SAMPLERS, DiffusionSchedule, SamplerConfigError, SamplerSpec
from difareli.diffusion import samplers as samplers_mod
from difareli.diffusion import spec as spec_mod
from difareli.lit.callbacks import SampleGrid

from tests.helpers import CONF, compose_train

SCHED = DiffusionSchedule()
T = SCHED.T
FIELDS = {"name", "steps", "grid", "clip_x0_invert", "clip_x0_generate", "alpha_zero_end", "guidance"}

pytestmark = pytest.mark.usefixtures("one_thread")


def _keyword_options(fn) -> set[str]:
    return {p.name for p in inspect.signature(fn).parameters.values()
            if p.kind is inspect.Parameter.KEYWORD_ONLY} - {"clip_x0", "callback", "progress"}


# ------------------------------------------------------------------------------------------ presets vs yaml
def test_every_sampler_yaml_is_a_preset_and_back():
    assert {p.stem for p in (CONF / "sampler").glob("*.yaml")} == set(PRESETS)


@pytest.mark.parametrize("name", list(PRESETS))
def test_sampler_yaml_composes_to_its_preset(name, tmp_path):
    cfg = compose_train(tmp_path, [f"sampler={name}"], config_name="relight")
    sampler = dict(cfg.sampler)
    assert SamplerSpec.from_config(sampler) == PRESETS[name]
    # The file lists every option of its sampler (so `sampler.<option>=...` overrides need no `+`), nothing else.
    assert set(sampler) == FIELDS | _keyword_options(SAMPLERS[PRESETS[name].name])
    assert sampler == {**PRESETS[name].to_config(), "guidance": 1.0}  # the plain decode: recorded without it


def test_yaml_overrides_reach_the_spec(tmp_path):
    cfg = compose_train(tmp_path, ["sampler=unipc", "sampler.steps=7", "sampler.variant=bh1"], config_name="relight")
    assert SamplerSpec.from_config(cfg.sampler) == SamplerSpec.preset("unipc_bh1", steps=7)


def test_preset_overrides_and_round_trip():
    sp = SamplerSpec.preset("paper", steps=20)
    assert (sp.name, sp.steps, sp.clip_x0_invert, sp.clip_x0_generate, sp.alpha_zero_end) == ("ddim", 20, True,
                                                                                             True, True)
    assert SamplerSpec.preset("unipc", variant="bh1") == PRESETS["unipc_bh1"]
    # Defaults are filled in: configs that sample alike give equal specs.
    assert SamplerSpec.from_config({"name": "unipc", "steps": 50}) == PRESETS["unipc"]
    assert dict(PRESETS["unipc"].options) == {"order": 2, "variant": "bh2", "corrector": True,
                                              "lower_order_final": True}
    for sp in PRESETS.values():
        assert SamplerSpec.from_config(sp.to_config()) == sp
    # Switching the sampler of a preset keeps only the common fields.
    assert SamplerSpec.preset("unipc", name="ddim", steps=3) == SamplerSpec("ddim", 3)


# ------------------------------------------------------------------------------------------ validation
@pytest.mark.parametrize("cfg,match", [
    ({"name": "euler"}, r"unknown sampler 'euler'; choose from ddim, dpm_solver, dpm_solver_pp, unipc"),
    ({"name": "paper"}, r"'paper' is a preset: use preset=paper"),
    ({"preset": "fast"}, r"unknown sampler preset 'fast'; choose from ddim, .*paper"),
    ({"name": "ddim", "steps": 2.7}, r"steps must be an integer >= 1, got 2.7"),
    ({"name": "ddim", "steps": 0}, r"steps must be an integer >= 1, got 0"),
    ({"name": "ddim", "steps": True}, r"steps must be an integer >= 1"),
    ({"name": "ddim", "steps": "50"}, r"steps must be an integer >= 1"),
    ({"name": "ddim", "order": 2}, r"unknown option 'order' for sampler 'ddim'; its options: none"),
    ({"name": "unipc", "solver": "bh1"},
     r"unknown option 'solver' for sampler 'unipc'; its options: order, variant, corrector, lower_order_final"),
    ({"name": "unipc", "variant": "bh3"}, r"variant='bh3' is invalid; expected 'bh1' \| 'bh2'"),
    ({"name": "unipc", "order": 3}, r"order=3 is invalid; expected 1 \| 2"),
    ({"name": "dpm_solver", "order": 2.0}, r"order=2.0 is invalid"),
    ({"name": "dpm_solver", "order": True}, r"order=True is invalid"),
    ({"name": "unipc", "corrector": "yes"}, r"corrector='yes' is invalid; expected bool"),
    ({"name": "ddim", "grid": "cosine"}, r"unknown sampler grid 'cosine'; choose from uniform, quadratic, logsnr"),
    ({"name": "ddim", "clip_x0_invert": "false"}, r"clip_x0_invert must be true or false"),
    ({"steps": 5}, r"needs a name"),
])
def test_bad_configs_name_the_input(cfg, match):
    with pytest.raises(SamplerConfigError, match=match):
        SamplerSpec.from_config(cfg)


def test_constructor_validates_too():
    with pytest.raises(SamplerConfigError, match="unknown option 'variant' for sampler 'dpm_solver'"):
        SamplerSpec("dpm_solver", options={"variant": "bh1"})
    with pytest.raises(SamplerConfigError, match="steps must be an integer"):
        SamplerSpec("ddim", steps=-1)
    # Integral numpy scalars are integers; None in a config means "not set".
    assert SamplerSpec.from_config({"name": "dpm_solver", "steps": np.int64(9), "order": np.int64(1),
                                    "grid": None}) == SamplerSpec("dpm_solver", 9, options={"order": 1})


def test_options_are_read_from_the_signature(monkeypatch):
    """A sampler registered with a new keyword option is configurable at once, with its annotation checked."""

    def heun(denoiser, x, timesteps, schedule, *, clip_x0=False, callback=None, progress=False, churn: float = 0.0):
        return samplers_mod.ddim(denoiser, x, timesteps, schedule, clip_x0=clip_x0, callback=callback)

    monkeypatch.setitem(samplers_mod.SAMPLERS, "heun", heun)
    spec_mod.signature_options.cache_clear()
    try:
        sp = SamplerSpec.from_config({"name": "heun", "steps": 4, "churn": 1})
        assert sp.options == (("churn", 1.0),)
        with pytest.raises(SamplerConfigError, match="churn='x' is invalid; expected float"):
            SamplerSpec("heun", options={"churn": "x"})
        for name, fn in samplers_mod.SAMPLERS.items():
            assert set(spec_mod.signature_options(name)) == _keyword_options(fn)
    finally:
        spec_mod.signature_options.cache_clear()


# ------------------------------------------------------------------------------------------ running
def test_paper_preset_inversion_ends_at_alpha_zero():
    sp = SamplerSpec.preset("paper")
    inv, gen = sp.grids(SCHED)
    assert len(inv) == len(gen) == 1001
    assert int(inv[0]) == -1 and int(inv[-1]) == T and SCHED.alpha_bar(T) == 0.0
    assert int(gen[0]) == T - 1 and int(gen[-1]) == -1
    # The last inversion step returns eps exactly (alpha' = 0, sigma' = 1): x_T is the predicted noise.
    eps = lambda x, t: 0.5 * x + 0.01 * t.float().view(-1, 1, 1, 1)  # noqa: E731
    x = torch.randn(1, 3, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    two = SamplerSpec.preset("paper", steps=2)
    inv2 = two.grids(SCHED)[0]
    assert inv2.tolist()[-1] == T
    x_mid = two.run(eps, x, inv2[:2], SCHED, clip_x0=False)
    x_T = two.run(eps, x, inv2, SCHED, clip_x0=False)
    torch.testing.assert_close(x_T, eps(x_mid, torch.tensor([int(inv2[1])])))


def test_run_clips_per_direction_and_generate_uses_the_generation_grid():
    """clip_x0=None takes clip_x0_invert on ascending grids and clip_x0_generate on descending ones."""
    eps = lambda x, t: -2.0 * x  # noqa: E731  x0_hat far outside [-1, 1]: clipping changes the result
    x = 3.0 * torch.randn(2, 3, 4, 4, generator=torch.Generator().manual_seed(1))
    only_inv = SamplerSpec("unipc", 6, clip_x0_invert=True)
    inv, gen = only_inv.grids(SCHED)
    fn = samplers_mod.unipc
    torch.testing.assert_close(only_inv.run(eps, x, inv, SCHED), fn(eps, x, inv, SCHED, clip_x0=True))
    torch.testing.assert_close(only_inv.run(eps, x, gen, SCHED), fn(eps, x, gen, SCHED, clip_x0=False))
    assert not torch.allclose(fn(eps, x, inv, SCHED, clip_x0=True), fn(eps, x, inv, SCHED))
    paper = SamplerSpec.preset("paper", steps=5)
    want = samplers_mod.ddim(eps, x, SCHED.time_grid(5), SCHED, clip_x0=True)
    torch.testing.assert_close(paper.generate(eps, x, SCHED), want)
    assert float(want.abs().max()) <= 1.0  # the last step lands on the clipped x0_hat


# ------------------------------------------------------------------------------------------ SampleGrid
def _fit(store: Path, out: Path, extra: list[str]):
    from difareli.cli.train import train

    cfg = compose_train(out, [
        f"data.root={store}", "data.resolution=32", "data.synth=null", "data.num_workers=0", "data.batch_size=4",
        "model=difareli_pp", "model.preset=tiny", "trainer=cpu", "trainer.max_steps=2", "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1", "logger=[]", "callbacks.ema.decay=0.5", "~callbacks.reconstruction_grid",
        "~callbacks.loss_curve", "~callbacks.progress_bar", "~callbacks.model_checkpoint", *extra])
    return cfg, train(cfg)


@pytest.mark.slow  # a training run: the default run has to finish in minutes at load 4
def test_sample_grid_callback_in_a_tiny_fit(synth_store, tmp_path):
    cfg, out = _fit(synth_store, tmp_path, ["sampler=unipc", "sampler.steps=3", "callbacks.sample_grid.num_images=3",
                                             "callbacks.sample_grid.every_n_validations=1"])
    cb = next(c for c in out["trainer"].callbacks if isinstance(c, SampleGrid))
    assert cb.spec == SamplerSpec.preset("unipc", steps=3)  # train.yaml's sampler group reaches the callback
    png = iio.imread(tmp_path / "sample_grid.png")
    ds = out["datamodule"].val_set
    n = min(3, len(ds))
    assert png.shape == (2 * (32 + 2) + 2, n * (32 + 2) + 2, 3)
    # Top row: the real images. Bottom row: recomputed from the fitted model, which holds the EMA weights
    # copied in at train end: equal only if the grid was sampled after that copy.
    items = [ds[i] for i in range(n)]
    model = out["model"].eval()
    with torch.no_grad():
        cond = model.condition(torch.stack([b["spatial"] for b in items]),
                               torch.stack([b["nonspatial"] for b in items]))
        x_T = torch.randn((n, 3, 32, 32), generator=torch.Generator().manual_seed(0))
        x0 = SamplerSpec.preset("unipc", steps=3).generate(model.denoiser(cond), x_T, model.schedule)
    want = viz.grid([[viz.to_uint8(b["image"]) for b in items], [viz.to_uint8(x.clamp(-1, 1)) for x in x0]])
    np.testing.assert_array_equal(png, want)
    periodic = sorted((tmp_path / "grids").glob("sample_grid_step*.png"))
    assert [p.name for p in periodic] == ["sample_grid_step0000002.png"]
    assert iio.imread(periodic[0]).shape == png.shape


def test_sample_grid_config_switches(tmp_path):
    base = ["trainer=cpu", "logger=[]"]
    cb = instantiate_group(compose_train(tmp_path, [*base, "sample_grid=false"]).callbacks)
    grid = next(c for c in cb if isinstance(c, SampleGrid))
    assert not grid.enabled
    cfg = compose_train(tmp_path, [*base, "callbacks.sample_grid.sampler=paper", "callbacks.sample_grid.steps=20"])
    grid = next(c for c in instantiate_group(cfg.callbacks) if isinstance(c, SampleGrid))
    assert grid.enabled and grid.spec == SamplerSpec.preset("paper", steps=20)
    names = list(cfg.callbacks)
    assert names.index("ema") < names.index("sample_grid")  # it must sample after the EMA copy
    with pytest.raises(Exception, match="steps must be an integer >= 1, got 2.7"):
        instantiate_group(compose_train(tmp_path, [*base, "sampler.steps=2.7"]).callbacks)
