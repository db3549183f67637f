"""difareli-import-checkpoint refuses what would import silently wrong: NaN/Inf weights, out= equal to
an input or a folder (before anything is written), and says what the tensors cannot show: the config keys that
change no shape, the UNet and Modulator of different steps."""

from __future__ import annotations

import pytest
import torch

from tests.official.test_official_checkpoint import run_cli, write_run

UNET, MOD = "ImgCond_ema_0.9999_000100.pt", "ImgEncoder_ema_0.9999_000100.pt"


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused(tmp_path, capsys, bad):
    run, cfg, sd = write_run(tmp_path)
    sd["unet"]["middle_block.1.in_layers.2.weight"].view(-1)[3] = bad
    torch.save(sd["unet"], run / UNET)
    code, err = run_cli(capsys, run, f"config={cfg}", f"out={tmp_path}/o.ckpt")
    assert code == 2 and "NaN/Inf" in err and "middle_block.1.in_layers.2.weight" in err and UNET in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "o.ckpt").exists()


@pytest.mark.parametrize("which", ["unet", "encoder", "config", "folder"])
def test_out_equal_to_an_input_or_a_folder_is_refused_before_writing(tmp_path, capsys, which):
    run, cfg, _ = write_run(tmp_path)
    out = {"unet": run / UNET, "encoder": run / MOD, "config": cfg, "folder": run}[which]
    before = {p: p.read_bytes() for p in (run / UNET, run / MOD, cfg)}
    code, err = run_cli(capsys, run / UNET, f"config={cfg}", f"out={out}")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert ("is a folder" if which == "folder" else "file itself") in err and f"out={out}" in err
    assert {p: p.read_bytes() for p in before} == before  # the authors' files untouched
    assert sorted(p.name for p in run.iterdir()) == sorted([UNET, MOD])


def test_steps_that_differ_are_warned_and_shapeless_config_keys_printed(tmp_path, capsys):
    run, cfg, sd = write_run(tmp_path)
    other = run / "ImgEncoder_ema_0.9999_000200.pt"
    torch.save(sd["mod"], other)
    from difareli.cli.import_checkpoint import main

    assert main([str(run / UNET), f"encoder={other}", f"config={cfg}", f"out={tmp_path}/o.ckpt"]) == 0
    captured = capsys.readouterr()
    assert "come from different steps" in captured.err and "ema_0.9999_100 vs ema_0.9999_200" in captured.err
    assert "img_model.num_heads=2 (default: 4)" in captured.out and "use_new_attention_order=False" in captured.out
    assert "max |eps difference| 0.0e+00" in captured.out
