"""difareli-shadow-maps keys its versions by the weights' content: retrained weights written at the same checkpoint
path (same step) make a new version and relight every record again, instead of "relit 0" and the old maps; under a
name given (the default ``difference``) they are refused before any relight, naming the weights."""

from __future__ import annotations

import shutil

import pytest
import torch

from difareli.data.inputs import input_dims
from difareli.data.provenance import model_identity
from difareli.data.store import EncodingStore
from difareli.errors import UserError
from difareli.checkpoints.format import stamp
from difareli.lit.diffusion import DiffusionModule

from tests.helpers import compose_train

SPATIAL, NONSPATIAL = ["shading", "background"], ["shape", "cam", "identity", "shadow"]


def write_weights(path, store, seed: int) -> str:
    """A tiny DiFaReli with weights drawn from ``seed``, saved as a Lightning checkpoint at step 20 (a retrain
    reaches the same step); returns its weights' identity."""
    torch.manual_seed(seed)
    model = DiffusionModule(name="difareli", preset="tiny", spatial_inputs=SPATIAL, nonspatial_inputs=NONSPATIAL,
                            input_dims=input_dims(SPATIAL, NONSPATIAL, store.dims, int(store.dims["H"])))
    ckpt = {"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams), "global_step": 20, "epoch": 0}
    stamp(ckpt, model)
    torch.save(ckpt, path)
    return model_identity(model)


def test_retrained_weights_at_the_same_path_make_a_new_version(synth_store, tmp_path, capsys, one_thread):
    from difareli.cli.shadow_maps import run

    shutil.copytree(synth_store, tmp_path / "store")
    store = EncodingStore.open(tmp_path / "store")
    path, ids = tmp_path / "difareli.ckpt", store.ids()[:2]
    cfg = compose_train(tmp_path / "run", [f"checkpoint={path}", f"store={store.root}", f"records=[{','.join(ids)}]",
                                           "sampler.steps=2", "batch_size=2", "progress=false", "runtime.device=cpu",
                                           "threshold=0.01", "min_contrast=0", "min_coherence=0", "version=null"],
                        config_name="shadow_maps")
    first = write_weights(path, store, seed=0)
    v1 = run(cfg)
    assert (v1.relit, v1.written) == (2, 2)
    assert run(cfg).relit == 0  # the same weights again: resumed, nothing relit
    second = write_weights(path, store, seed=1)  # retrained: same path, same step, other weights
    assert second != first
    capsys.readouterr()
    v2 = run(cfg)
    assert v2.name != v1.name and v2.raw != v1.raw
    assert (v2.relit, v2.written) == (2, 2)
    assert "relit 2 record(s) at 2 shadow strengths" in capsys.readouterr().out
    header = EncodingStore.open(store.root).derived
    assert (header[v1.name]["weights"], header[v2.name]["weights"]) == (first, second)
    assert header[v1.name]["checkpoint"] == header[v2.name]["checkpoint"] == str(path.resolve())
    assert header[v1.name]["global_step"] == header[v2.name]["global_step"] == 20


def test_retrained_weights_under_the_default_name_are_refused_before_any_relight(synth_store, tmp_path, one_thread):
    from difareli.cli.shadow_maps import run

    shutil.copytree(synth_store, tmp_path / "store")
    store = EncodingStore.open(tmp_path / "store")
    path, ids = tmp_path / "difareli.ckpt", store.ids()[:2]
    cfg = compose_train(tmp_path / "run", [f"checkpoint={path}", f"store={store.root}", f"records=[{','.join(ids)}]",
                                           "sampler.steps=2", "batch_size=2", "progress=false", "runtime.device=cpu",
                                           "threshold=0.01", "min_contrast=0", "min_coherence=0"],
                        config_name="shadow_maps")
    first = write_weights(path, store, seed=0)
    assert run(cfg).name == "shadow_map@difference"  # the name the DiFaReli++ recipes train on
    before = sorted(p.name for p in store.records_dir.rglob("*.npy"))
    second = write_weights(path, store, seed=1)
    with pytest.raises(UserError) as e:  # it had relit every record, then refused with the whole provenance
        run(cfg)
    assert str(e.value) == (
        f"version=difference: store {store.root} already has shadow_map@difference made with other settings "
        f"(weights: {first!r} there, {second!r} now); give another name (version=difference-2) or version=null "
        "(named by the settings' hash) and train on it with data.versions={shadow_map: <name>}")
    assert sorted(p.name for p in store.records_dir.rglob("*.npy")) == before  # nothing relit or written
