"""difareli-shadow-maps refuses what used to give silently wrong maps: a threshold outside (0, 1), a
store without a train split, a misspelt split; and a second concurrent writer into the same store."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from difareli import errors
from difareli.errors import UserError
from difareli.jobs import shadow_maps as sm
from difareli.data.store import EncodingStore

from tests.helpers import compose_train
from .test_shadow_maps import Crafted

SRC = str(Path(__file__).resolve().parents[2] / "src")
PROV = {"checkpoint": "crafted"}


@pytest.fixture
def store(synth_store, tmp_path):
    shutil.copytree(synth_store, tmp_path / "store")
    return EncodingStore.open(tmp_path / "store", durable=False)


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file of a store (header, records, derived maps) by relative path -> bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
            and p.name != ".difareli.lock"}


def _cli(tmp_path, store_root, overrides, monkeypatch, capsys):
    """Run difareli-shadow-maps' task as its console script does: (exit status, stderr)."""
    from difareli.cli.shadow_maps import run

    monkeypatch.delenv("DIFARELI_DEBUG", raising=False)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    ckpt = tmp_path / "never_loaded.ckpt"  # every refusal comes before the checkpoint is read
    ckpt.write_bytes(b"")
    cfg = compose_train(tmp_path / "run", [f"checkpoint={ckpt}", f"store={store_root}", "progress=false",
                                           "runtime.device=cpu", *overrides], config_name="shadow_maps")
    with pytest.raises(SystemExit) as e:
        errors.cli_entry("shadow-maps")(lambda: run(cfg))()
    return e.value.code, capsys.readouterr().err


@pytest.mark.parametrize("value", ["-1", "0", "1", "1.5"])
def test_a_threshold_outside_0_1_is_refused_naming_the_range_and_the_default(store, tmp_path, monkeypatch, capsys,
                                                                          value):
    before = _snapshot(store.root)
    code, err = _cli(tmp_path, store.root, [f"threshold={value}"], monkeypatch, capsys)
    assert code == 2
    assert err.startswith(f"difareli-shadow-maps: threshold={value} is out of range: it cuts the grey-level "
                          "difference in [0, 1] and must lie strictly between 0 and 1")
    assert "threshold=relative (the default), the recipe's 0.05, or otsu" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(UserError, match=r"threshold=-1 is out of range"):  # the library refuses it too
        sm.compute(Crafted(), store, None, provenance=PROV, threshold=-1, progress=False)
    assert _snapshot(store.root) == before and not (tmp_path / "run" / "shadow_maps.json").exists()


def test_a_misspelt_split_is_refused_naming_the_stores_splits(store, tmp_path, monkeypatch, capsys):
    before = _snapshot(store.root)
    code, err = _cli(tmp_path, store.root, ["split=trian"], monkeypatch, capsys)
    assert code == 2
    assert err == (f"difareli-shadow-maps: split=trian: store {store.root} has no record with split=trian (its splits: "
                   "test, train, val); give one of them, e.g. split=test, or split=all for every record\n")
    code, err = _cli(tmp_path, store.root, ["records_split=tset"], monkeypatch, capsys)
    assert code == 2 and err.startswith("difareli-shadow-maps: records_split=tset: store ") \
        and "(its splits: test, train, val)" in err
    with pytest.raises(UserError, match=r"split=trian: .*its splits: test, train, val"):
        sm.compute(Crafted(), store, None, provenance=PROV, split="trian", progress=False)
    assert _snapshot(store.root) == before


def _without_train(root: Path) -> None:
    for meta in (root / "records").glob("*/meta.json"):
        m = json.loads(meta.read_text())
        m["split"] = "val" if m["split"] == "train" else m["split"]
        meta.write_text(json.dumps(m))


def test_a_store_without_a_train_split_is_refused_or_uses_its_recorded_range(store, tmp_path, monkeypatch, capsys):
    _without_train(store.root)
    store = EncodingStore.open(store.root, durable=False)
    before = _snapshot(store.root)
    code, err = _cli(tmp_path, store.root, [], monkeypatch, capsys)  # the default split=train
    assert code == 2
    assert err.startswith(f"difareli-shadow-maps: split=train: store {store.root} has no record with split=train "
                          "(its splits: test, val), so the c range to relight at cannot be the training split's;\n"
                          "give the range the DiFaReli was trained with, c_range=[c_min,c_max]")
    assert "split=all" in err and len(err.strip().splitlines()) == 2
    with pytest.raises(UserError, match=r"no record with split=train"):
        sm.compute(Crafted(), store, None, provenance=PROV, threshold="otsu", median=3, zero_parts=(), progress=False)
    assert _snapshot(store.root) == before  # nothing declared, nothing written
    # The fixes the message names: a given range, every record (each said so in the provenance and the report).
    given = sm.compute(Crafted(), store, None, provenance=PROV, threshold="otsu", median=3, zero_parts=(),
                       c_range=(-5.0, 1.0), progress=False)
    assert (given.c_min, given.c_max, given.c_source) == (-5.0, 1.0, "c_range=[-5, 1] given")
    assert store.derived[given.name]["c_source"] == "c_range=[-5, 1] given"
    every = sm.compute(Crafted(), store, None, provenance=PROV, threshold="otsu", median=3, zero_parts=(),
                       split="all", version="all", progress=False)
    assert every.c_source.startswith(f"every record's stored c, {len(store.ids())} records")
    # A store whose header records its training split's range (SynthFaces v3): that range, and it says so.
    header = json.loads((store.root / "store.json").read_text())
    header["meta"]["shadow_c_range"] = {"lo": -4.0, "hi": 0.5, "split": "train", "quantile": 0.01, "records": 12,
                                        "state": "final"}
    (store.root / "store.json").write_text(json.dumps(header))
    v3 = EncodingStore.open(store.root, durable=False)
    rep = sm.compute(Crafted(), v3, None, provenance=PROV, threshold="otsu", median=3, zero_parts=(), version="v3",
                     progress=False)
    assert (rep.c_min, rep.c_max) == (-4.0, 0.5)
    assert rep.c_source == ("the store header's shadow_c_range: the train split's c at quantile 0.01, 12 records; "
                            "this store has no train split")


# A second writer: computes maps into the store and stops in its first relight until killed.
WRITER = textwrap.dedent("""
    import sys, time, torch
    from difareli.jobs import shadow_maps as sm
    from difareli.data.store import EncodingStore

    class Slow(torch.nn.Module):
        spatial_inputs, nonspatial_inputs = [], ["shadow"]
        def condition(self, spatial, nonspatial):
            return nonspatial
        def relight_once(self, x0, source, target):
            print("relighting", flush=True)
            time.sleep(120)

    sm.compute(Slow(), EncodingStore.open(sys.argv[1], durable=False), None, provenance={"checkpoint": "slow"},
               progress=False)
""")


def test_a_second_writer_into_the_same_store_is_refused_naming_the_first(store):
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(store.root)], stdout=subprocess.PIPE, text=True,
                            env=env)
    try:
        assert proc.stdout.readline().strip() == "relighting"
        before = _snapshot(store.root)
        with pytest.raises(UserError, match=rf"{store.root} is being written by difareli-shadow-maps \(pid "
                                            rf"{proc.pid}\); wait for it to finish or give another output folder"):
            sm.compute(Crafted(), EncodingStore.open(store.root, durable=False), None, provenance=PROV,
                       threshold="otsu", median=3, zero_parts=(), progress=False)
        assert _snapshot(store.root) == before  # the refused writer changed nothing
    finally:
        proc.kill()
        proc.wait()
    # The lock died with its holder: the next run writes its maps.
    rep = sm.compute(Crafted(), EncodingStore.open(store.root, durable=False), None, provenance=PROV,
                     threshold="otsu", median=3, zero_parts=(), progress=False)
    assert rep.written == len(store.ids())
