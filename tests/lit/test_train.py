"""Training through the real Hydra config tree: fast_dev_run per variant, overfitting, checkpoints, resume."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from difareli.cli.train import nonspatial_stats, train
from difareli.errors import UserError
from difareli.data.inputs import MissingEncodingError
from difareli.lit import load_checkpoint
from difareli.data.store import EncodingStore

from tests.helpers import CONF, compose_train, tiny_cpu_overrides

MODELS = ["difareli", "difareli_pp"]
#: Every model config (variants and ablations): each must run through the whole loop.
ALL_MODELS = sorted(str(p.relative_to(CONF / "model").with_suffix("")) for p in (CONF / "model").rglob("*.yaml")
                    if p.parent.name not in ("spatial", "nonspatial", "scheduler"))  # component groups


def _cpu_overrides(store: Path) -> list[str]:
    return tiny_cpu_overrides(store)


#: Models trained on pairs (input -> relit), not single records: they need a pair sampler (conf/data).
PAIRED = {"student": ["data.pairs=gt"]}


@pytest.mark.parametrize("model", ALL_MODELS)
def test_fast_dev_run_each_model(model, synth_store, tmp_path):
    cfg = compose_train(tmp_path, [*_cpu_overrides(synth_store), f"model={model}", "debug=fdr",
                                   *PAIRED.get(model, [])])
    out = train(cfg)
    assert out["trainer"].state.finished
    assert torch.isfinite(out["trainer"].callback_metrics["train/loss"])


def test_variants_consume_only_declared_encodings(synth_store, tmp_path, monkeypatch):
    opened: list[str] = []
    orig = np.load

    def counting_load(file, *a, **k):
        opened.append(Path(file).stem)
        return orig(file, *a, **k)

    cfg = compose_train(tmp_path, [*_cpu_overrides(synth_store), "model=difareli", "debug=fdr"])
    monkeypatch.setattr(np, "load", counting_load)
    train(cfg)
    assert set(opened) == {"image", "shading", "background", "shape", "cam", "identity", "shadow"}


def test_missing_encoding_names_encoding_and_path(tmp_path, synth_store):
    src = EncodingStore.open(synth_store)
    keep = ["image", "shading", "shape", "cam", "identity"]  # no masks, no shadow_map
    dst = EncodingStore.create(tmp_path / "partial", dims=src.dims, encodings=keep, meta={})
    for rid in src.ids()[:4]:
        dst.write(rid, {k: np.asarray(v) for k, v in src.read(rid, keep).items()}, src.meta(rid))
    cfg = compose_train(tmp_path, [*_cpu_overrides(tmp_path / "partial"), "model=difareli_pp", "debug=fdr"])
    with pytest.raises(MissingEncodingError) as e:
        train(cfg)
    assert "masks" in str(e.value) and str(tmp_path / "partial") in str(e.value)


@pytest.mark.slow  # 200 training steps: a minute quiet, many under load
def test_overfit_eight_images_loss_falls_tenfold(synth_store, tmp_path):
    """A tiny model memorises 8 SynthFaces images: the eps-loss at fixed (t, noise) falls at least 10x."""
    import lightning as L
    from hydra.utils import instantiate

    # A micro network (base 16, one downsampling, no attention) keeps 200 CPU steps to ~a minute.
    cfg = compose_train(tmp_path, [*_cpu_overrides(synth_store), "model=difareli_pp", "data.batch_size=8",
                                   "model.optimizer.lr=3e-3", "+model.net_overrides.base_channels=16",
                                   "+model.net_overrides.channel_mult=[1,2]", "+model.net_overrides.norm_groups=8",
                                   "+model.net_overrides.adagn_hidden=64",
                                   "+model.net_overrides.attention_resolutions=[]"])
    L.seed_everything(0)
    dm = instantiate(cfg.data)
    dm.setup()
    dm.train_set.ids = dm.train_set.ids[:8]  # exactly 8 images: one batch per epoch
    model = instantiate(cfg.model, input_dims=dm.input_dims(), nonspatial_stats=nonspatial_stats(dm, None))
    batch = next(iter(dm.train_dataloader()))

    def fixed_loss() -> float:
        g = torch.Generator().manual_seed(0)
        with torch.no_grad():
            return float(np.mean([model.diffusion_loss(batch, generator=g).item() for _ in range(16)]))

    before = fixed_loss()
    trainer = L.Trainer(max_steps=200, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, limit_val_batches=0, enable_model_summary=False)
    trainer.fit(model, datamodule=dm)
    after = fixed_loss()
    print(f"overfit: fixed-noise eps loss {before:.4f} -> {after:.4f} ({before / after:.1f}x)")
    assert after < before / 10


def test_checkpoint_round_trip_weights_only(synth_store, tmp_path):
    cfg = compose_train(tmp_path, [*_cpu_overrides(synth_store), "model=difareli_pp", "trainer.max_steps=3",
                                   "trainer.val_check_interval=3", "trainer.limit_val_batches=1",
                                   "callbacks.ema.decay=0.5", "logger=[]"])
    out = train(cfg)
    last = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    raw = torch.load(last, map_location="cpu", weights_only=True)  # must not raise
    assert raw["global_step"] == 3
    # Plain hyperparameters: the module class, the optimizer's settings, the exact (not EMA-averaged) statistics.
    hp = raw["hyper_parameters"]
    assert raw["difareli_module"] == "difareli.lit.diffusion.DiffusionModule" and raw["difareli_format"] == 2
    assert hp["optimizer"]["lr"] == 1e-4 and hp["spatial"] == {"type": "modulator", "modulate_skips": False}
    mean, std = out["datamodule"].nonspatial_stats()
    assert hp["nonspatial_stats"] == {"mean": mean.tolist(), "std": std.tolist()}
    assert "ns_mean" not in raw["state_dict"] and "ns_mean" not in raw["current_model_state"]
    loaded = load_checkpoint(last)
    assert loaded.config["preset"] == "tiny" and loaded.global_step == 3
    # The EMA callback copies the average into the model at the end of fit: outputs must match exactly.
    model = out["model"].eval()
    b = next(iter(out["datamodule"].val_dataloader()))
    x = torch.randn_like(b["image"])
    t = torch.full((x.shape[0],), 500)
    with torch.no_grad():
        ref = model.net(x, t, model.condition(b["spatial"], b["nonspatial"]))
        got = loaded.model.net(x, t, loaded.model.condition(b["spatial"], b["nonspatial"]))
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(loaded.stats["std"], model.ns_std)


@pytest.mark.slow  # two training runs (4 steps, then resumed to 6, with validation)
def test_resume_continues_from_last_step(synth_store, tmp_path):
    base = [*_cpu_overrides(synth_store), "model=difareli", "trainer.limit_val_batches=1",
            "trainer.val_check_interval=2", "logger=[]"]
    first = compose_train(tmp_path / "a", [*base, "trainer.max_steps=4"])
    train(first)
    last = Path(first.paths.output_dir) / "checkpoints" / "last.ckpt"
    second = compose_train(tmp_path / "b", [*base, "trainer.max_steps=6", f"ckpt_path={last}"])
    out = train(second)
    assert out["trainer"].global_step == 6
    # Statistics restored from the checkpoint, not recomputed (same values either way, but from the file).
    assert torch.equal(out["model"].ns_mean, load_checkpoint(last).stats["mean"])


@pytest.mark.slow  # two training runs
def test_init_from_fine_tunes_from_the_weights_at_step_zero(synth_store, tmp_path):
    """init_from starts a new run (step 0, fresh optimizer) from another run's weights and its normalisation;
    with the learning rate at zero the fine-tuned network is the initial one exactly."""
    base = [*_cpu_overrides(synth_store), "model=difareli", "trainer.limit_val_batches=1",
            "trainer.val_check_interval=2", "logger=[]"]
    first = compose_train(tmp_path / "a", [*base, "trainer.max_steps=4"])
    train(first)
    last = Path(first.paths.output_dir) / "checkpoints" / "last.ckpt"
    second = compose_train(tmp_path / "b", [*base, "trainer.max_steps=2", f"init_from={last}",
                                            "model.optimizer.lr=0.0", "callbacks.ema.decay=0.0"])
    out = train(second)
    assert out["trainer"].global_step == 2  # a new run: it counts from 0, not from the first run's 4
    raw = torch.load(last, map_location="cpu", weights_only=True)["state_dict"]
    for k, v in out["model"].state_dict().items():
        if k in raw and v.is_floating_point():
            torch.testing.assert_close(v, raw[k], rtol=0, atol=0, msg=k)
    torch.testing.assert_close(out["model"].ns_mean, load_checkpoint(last).stats["mean"])


def test_init_from_refuses_another_variant_and_a_resume_at_once(tiny_checkpoint, synth_store, tmp_path):
    base = [*_cpu_overrides(synth_store), "model=difareli", "trainer.max_steps=1", "logger=[]"]
    other = tiny_checkpoint("difareli_pp")
    with pytest.raises(UserError, match=r"init_from=.* was trained as model variant 'difareli_pp', this run "
                                        r"composes 'difareli'.*start with model="):
        train(compose_train(tmp_path / "a", [*base, f"init_from={other}"]))
    with pytest.raises(UserError, match=r"give one \(ckpt_path resumes"):
        train(compose_train(tmp_path / "b", [*base, f"init_from={other}", f"ckpt_path={other}"]))


@pytest.mark.slow  # a console-script multirun in a fresh interpreter: ~18 s on the loaded 2-core CI
def test_multirun_one_directory_per_variant(synth_store, tmp_path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "difareli.cli.train", "-m", "model=difareli,difareli_pp", "debug=fdr",
           *_cpu_overrides(synth_store), f"hydra.sweep.dir={tmp_path / 'sweep'}", f"paths.log_dir={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert runs == ["0", "1"]
    for r in runs:
        assert (tmp_path / "sweep" / r / ".hydra" / "config.yaml").is_file()


@pytest.mark.parametrize("native, expected", [("bf16", "bf16-mixed"), ("fp32", "32-true")])
def test_cpu_recipes_train_in_bf16_only_where_the_cpu_has_it(native, expected, tmp_path, monkeypatch):
    """Emulated bf16 (an AVX2-only CPU) was ~30x slower than fp32: the CPU recipes resolve their precision from
    the CPU's flags (hardware.auto_precision)."""
    import difareli.hardware

    monkeypatch.setattr(difareli.hardware, "auto_precision", lambda device: native)
    for experiment in ("reference_cpu", "student_cpu"):
        cfg = compose_train(tmp_path / experiment, [f"experiment={experiment}"])
        assert cfg.trainer.precision == expected, experiment


def test_ema_warmup_forgets_the_initialisation_and_reaches_the_decay():
    """The warm-up decay against its closed form, and the average it gives on a scalar parameter: after n updates
    of a parameter stepping 0 -> 1 at update 1, the plain EMA keeps decay**n of the 0, the warm-up one
    prod_k d_k."""
    from difareli.lit.ema import ema_warmup_avg_fn, warmup_decay

    assert warmup_decay(0.999, 0) == pytest.approx(0.1) and warmup_decay(0.999, 90) == pytest.approx(0.91)
    assert warmup_decay(0.999, 10_000) == 0.999
    update = ema_warmup_avg_fn(0.999)
    ema = torch.zeros(1)
    for n in range(1, 501):
        ema = update(ema, torch.ones(1), torch.tensor(n))
    kept = np.prod([warmup_decay(0.999, n) for n in range(1, 501)])
    assert float(ema) == pytest.approx(1 - kept, rel=1e-5)
    assert kept < 0.05 < 0.999 ** 500  # the initialisation's share at step 500: warm-up vs fixed decay (61%)


@pytest.mark.slow  # a training run: the default run has to finish in minutes at load 4
def test_ema_warmup_trains_through_the_config(synth_store, tmp_path):
    from difareli.lit.ema import EMA

    cfg = compose_train(tmp_path, [*_cpu_overrides(synth_store), "model=difareli", "trainer.max_steps=3",
                                   "trainer.val_check_interval=3", "trainer.limit_val_batches=1", "logger=[]",
                                   "callbacks.ema.warmup=true", "callbacks.ema.decay=0.999"])
    out = train(cfg)
    ema = [c for c in out["trainer"].callbacks if isinstance(c, EMA)]
    assert len(ema) == 1 and ema[0].warmup and int(ema[0]._average_model.n_averaged) == 3


@pytest.mark.slow  # a training run with validation: the default run has to finish in minutes at load 4
def test_min_snr_weighting_matches_its_formula_and_val_loss_stays_l_simple(synth_store, tmp_path):
    """Min-SNR-gamma (Hang et al. 2023) for eps-prediction: per-sample error times min(SNR_t, gamma) / SNR_t,
    recomputed here from the schedule's alpha-bar table; validation keeps the unweighted L_simple."""
    import torch.nn.functional as F

    cfg = compose_train(tmp_path, [*_cpu_overrides(synth_store), "model=difareli", "model.loss.weighting=min_snr",
                                   "model.loss.min_snr_gamma=2.0", "trainer.max_steps=2",
                                   "trainer.val_check_interval=2", "trainer.limit_val_batches=1", "logger=[]"])
    out = train(cfg)
    model = out["model"].eval()
    assert model.hparams["loss"] == {"weighting": "min_snr", "min_snr_gamma": 2.0}
    batch = next(iter(out["datamodule"].val_dataloader()))
    with torch.no_grad():
        got = model.diffusion_loss(batch, torch.Generator().manual_seed(3))
        simple = model.diffusion_loss(batch, torch.Generator().manual_seed(3), weighted=False)
        g = torch.Generator().manual_seed(3)
        x0 = batch["image"]
        t = torch.randint(0, model.schedule.T, (x0.shape[0],), generator=g)
        noise = torch.randn(x0.shape, generator=g)
        eps = model.net(model.schedule.q_sample(x0, t, noise), t,
                        model.condition(batch.get("spatial"), batch.get("nonspatial")))
    abar = np.cumprod(1 - np.linspace(1e-4, 0.02, 1000))[t.numpy()]
    snr = abar / (1 - abar)
    per = ((eps - noise) ** 2).flatten(1).mean(1).numpy()
    assert float(got) == pytest.approx(float(np.mean(np.minimum(snr, 2.0) / snr * per)), rel=1e-4)
    assert float(simple) == pytest.approx(float(F.mse_loss(eps, noise)), rel=1e-5)
    assert float(got) < float(simple)  # the weights are <= 1 and < 1 wherever SNR_t > gamma
    # The checkpoint records the weighting and loads with it.
    assert load_checkpoint(Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt").model.hparams["loss"][
        "weighting"] == "min_snr"
    from difareli.lit.diffusion import loss_config

    for bad in ({"weighting": "snr"}, {"min_snr_gamma": 0}, {"gamma": 5}):
        with pytest.raises(ValueError, match="weighting is one of"):
            loss_config(bad)


@pytest.mark.slow  # two training runs: the default run has to finish in minutes at load 4
def test_wall_seconds_are_logged_at_each_validation_and_continue_on_resume(synth_store, tmp_path):
    import csv as csv_

    base = [*_cpu_overrides(synth_store), "model=difareli", "trainer.limit_val_batches=1",
            "trainer.val_check_interval=2", "logger=csv", "callbacks.relight_metrics.enabled=false"]

    def walls(run: Path) -> list[tuple[int, float]]:
        with open(run / "csv" / "metrics.csv") as f:
            return [(int(r["step"]), float(r["perf/wall_s"])) for r in csv_.DictReader(f) if r.get("perf/wall_s")]

    first = compose_train(tmp_path / "a", [*base, "trainer.max_steps=4"])
    train(first)
    a = walls(Path(first.paths.output_dir))
    assert [s for s, _ in a] == [1, 3] and 0 < a[0][1] < a[1][1]  # the validations after steps 2 and 4
    last = Path(first.paths.output_dir) / "checkpoints" / "last.ckpt"
    second = compose_train(tmp_path / "b", [*base, "trainer.max_steps=6", f"ckpt_path={last}"])
    train(second)
    b = walls(Path(second.paths.output_dir))
    assert [s for s, _ in b] == [5] and b[0][1] > a[-1][1]  # counted on from the first run's wall time


def test_default_multirun_sweep_dir_resolves_before_any_job(tmp_path, monkeypatch):
    """`difareli-train -m ...` without hydra.sweep.dir: the sweeper resolves the sweep dir (under paths.log_dir)
    before any job has a HydraConfig; with paths.root_dir = ${hydra:runtime.cwd} that raised 'HydraConfig was not
    set' and no sweep ran. The root is now the working directory."""
    from hydra.core.utils import setup_globals
    from omegaconf import OmegaConf

    from difareli.configs import CONFIG_DIR

    setup_globals()  # Hydra's own resolvers (${now:}, ${hydra:...})
    monkeypatch.chdir(tmp_path)
    cfg = OmegaConf.create({"task_name": "t", "paths": OmegaConf.load(CONFIG_DIR / "paths" / "default.yaml"),
                            "hydra": OmegaConf.load(CONFIG_DIR / "hydra" / "default.yaml")})
    sweep = Path(cfg.hydra.sweep.dir)
    assert sweep.parent == tmp_path / "logs" / "t" / "multiruns"
    assert Path(cfg.paths.data_dir) == tmp_path / "data"


def test_cpu_recipes_train_on_stores_with_every_input_estimated(tmp_path):
    """The CPU reference recipes read a store whose every input is estimated (as a photo's are), DiFaReli++ on the
    relight's own maker's maps; eager steps (the compiled one measured slower on this CPU)."""
    for experiment in ("reference_cpu", "student_cpu"):
        cfg = compose_train(tmp_path / experiment, [f"experiment={experiment}"])
        assert cfg.model.compile is False, experiment
        assert cfg.data.synth.inputs == "estimated" and cfg.data.root.endswith("sf_est_64"), experiment
    cfg = compose_train(tmp_path / "pp", ["experiment=reference_cpu"])
    assert cfg.data.versions.shadow_map == "march_suns"
    difareli = compose_train(tmp_path / "d", ["experiment=reference_cpu", "model=difareli"])
    assert difareli.data.versions.shadow_map is None
