"""difareli-export: a checkpoint -> model.safetensors + config.json + README.md, reloaded bit for bit without pickle;
the shipped references load from their folders."""

import json

import pytest
import torch

from difareli.checkpoints import export, loading, zoo
from difareli.checkpoints.loading import load_checkpoint, read_checkpoint
from difareli.errors import UserError

SHIPPED = ("difareli_pp-synth64", "difareli-synth64", "difareli_pp_ss-synth64", "difareli_pp_shadows-synth64",
           "difareli_pp_v2-synth64", "difareli_pp_ss_v3-synth64", "difareli_pp_est-synth64",
           "difareli_pp_ss_est-synth64", "difareli_pp_ss_shadowpairs-synth64", "difareli_pp_vis_est-synth64")


def _no_pickle(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("torch.load called: a weights folder must load without pickle")

    monkeypatch.setattr(torch, "load", refuse)


def test_export_round_trips_every_tensor_and_the_config(tmp_path, monkeypatch):
    from difareli.cli.export import main

    assert main(["difareli_pp-synth64", str(tmp_path / "w")]) == 0
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["README.md", "config.json", "model.safetensors"]
    ckpt = read_checkpoint(zoo.SHIPPED_DIR / "difareli_pp-synth64.ckpt")
    assert (tmp_path / "w" / "README.md").read_text() == zoo.card("difareli_pp-synth64")  # the shipped card
    _no_pickle(monkeypatch)
    back = read_checkpoint(tmp_path / "w")
    assert set(back["state_dict"]) == set(ckpt["state_dict"])
    for k, v in ckpt["state_dict"].items():
        assert back["state_dict"][k].dtype == v.dtype and torch.equal(back["state_dict"][k], v), k
    for k in ("hyper_parameters", "global_step", "epoch", "difareli_module", "difareli_format"):
        assert back[k] == ckpt[k], k
    stats = back["hyper_parameters"]["nonspatial_stats"]
    assert stats["mean"] == ckpt["hyper_parameters"]["nonspatial_stats"]["mean"]  # floats exact through JSON
    cfg = json.loads((tmp_path / "w" / "config.json").read_text())
    assert cfg["format"] == export.FOLDER_FORMAT and cfg["source"]["file"] == "difareli_pp-synth64.ckpt"


def test_shipped_names_load_from_their_folders_without_pickle(monkeypatch):
    for name in SHIPPED:
        assert export.is_folder(zoo.SHIPPED_DIR / name) and (zoo.SHIPPED_DIR / f"{name}.ckpt").is_file()
        assert loading.resolve(name, prefer_folder=True) == zoo.SHIPPED_DIR / name
        assert loading.resolve(name) == zoo.SHIPPED_DIR / f"{name}.ckpt"  # callers that torch.load a file
    assert zoo.available() == sorted(SHIPPED)
    ref = {n: load_checkpoint(zoo.SHIPPED_DIR / f"{n}.ckpt").model.state_dict() for n in SHIPPED}
    _no_pickle(monkeypatch)
    for name in SHIPPED:
        got = load_checkpoint(name).model.state_dict()
        assert all(torch.equal(got[k], v) for k, v in ref[name].items()), name


def test_relight_from_folder_equals_relight_from_checkpoint(tmp_path):
    from difareli.data.store import EncodingStore
    from difareli.evaluation.baselines import DiffusionMethod
    from difareli.evaluation.pairs import StoredFace
    from difareli.lighting.light_fit import LightFit
    from difareli.synth.generator import generate

    generate(out_dir=str(tmp_path / "s"), subjects=1, lights=2, resolution=64, seed=5)
    store = EncodingStore.open(tmp_path / "s")
    src, tgt = store.ids()[:2]
    export.export_folder("difareli_pp-synth64", tmp_path / "w")
    light = LightFit().from_store(store, tgt)
    out = []
    for ckpt in (str(zoo.SHIPPED_DIR / "difareli_pp-synth64.ckpt"), str(tmp_path / "w")):
        m = DiffusionMethod(ckpt, {"name": "unipc", "steps": 10}, runtime={"device": "cpu", "precision": "fp32"})
        out.append(torch.from_numpy(m.relight(StoredFace(store, src), light, None)))
    assert torch.equal(out[0], out[1]) and out[0].float().std() > 1  # an image, identical to the bit


def test_bad_exports_are_one_line(tmp_path):
    from difareli.cli.export import main, parse

    with pytest.raises(UserError, match="give a checkpoint and a folder"):
        parse(["only-one"])
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x.txt").write_text("x")
    with pytest.raises(SystemExit) as e:
        main(["difareli_pp-synth64", str(tmp_path / "full")])
    assert e.value.code == 2
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "config.json").write_text("{}")
    (tmp_path / "fake" / "model.safetensors").write_bytes(b"")
    with pytest.raises(ValueError, match="not a difareli weights folder"):
        read_checkpoint(tmp_path / "fake")
