"""Sharded per-record jobs: the shard rule, concurrent shards into one store, sharded benchmarks merged."""

from __future__ import annotations

import filecmp
import math
import multiprocessing as mp
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from difareli.data import shard
from difareli.evaluation import tables
from difareli.data.store import EncodingStore

from tests.helpers import HAS_ESTIMATORS, NO_ESTIMATORS, compose_train

SRC = str(Path(__file__).resolve().parents[2] / "src")


def test_parse_accepts_i_of_n_and_rejects_the_rest():
    assert shard.parse(None) is None and shard.parse("") is None
    assert shard.parse("1/4") == shard.Shard(1, 4) and shard.parse(" 0 / 2 ") == shard.Shard(0, 2)
    assert str(shard.parse("3/8")) == "3/8" and shard.parse("3/8").suffix == "shard-3-of-8"
    for bad in ("4/4", "-1/2", "1", "a/b", "0/0", "1/2/3"):
        with pytest.raises(ValueError, match="shard="):
            shard.parse(bad)


def test_shard_of_is_a_stable_hash_golden_values():
    # BLAKE2b-64 of the id modulo n: these values must never change (shards started months apart agree).
    assert [shard.shard_of(f"s{i:05d}", 4) for i in range(8)] == [3, 2, 0, 1, 2, 1, 1, 0]
    assert shard.shard_of("s00000_l0", 7) == 1 and shard.shard_of("abc", 1000) == 721
    # Not Python's per-process salted hash: a fresh interpreter gives the same answer.
    out = subprocess.run([sys.executable, "-c",
                          "from difareli.data.shard import shard_of; print(shard_of('abc', 1000))"],
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": SRC, "PYTHONHASHSEED": "7"})
    assert out.stdout.strip() == "721"


def test_shards_partition_the_ids_balanced():
    ids = [f"img_{i:06d}" for i in range(4000)]
    n = 4
    parts = [shard.select(ids, f"{i}/{n}") for i in range(n)]
    assert sorted(sum(parts, [])) == ids  # union is everything, nothing twice
    assert all(p == sorted(p) for p in parts)  # original order kept
    # Binomial(4000, 1/4): sd = sqrt(4000 * 1/4 * 3/4) ~ 27; allow 5 sd.
    assert all(abs(len(p) - 1000) < 5 * math.sqrt(4000 * 0.25 * 0.75) for p in parts), [len(p) for p in parts]
    # Membership depends on the id alone: a grown list keeps every old id in its shard.
    grown = shard.select(ids + [f"new_{i}" for i in range(50)], "2/4")
    assert set(parts[2]) <= set(grown)
    assert shard.select(ids, None) == ids and shard.select(ids, "0/1") == ids


def _write_shard(root: str, spec: str | None, n_records: int, barrier) -> None:
    # Both writers open the store (clearing only dead writers' scratch) and write interleaved.
    store = EncodingStore.create(root, {"H": 4, "W": 4}, ["light", "shadow"], {"kind": "test"}, durable=False)
    if barrier is not None:
        barrier.wait()
    for i in shard.select(range(n_records), spec, key=lambda i: f"r{i:04d}"):
        rng = np.random.default_rng(i)
        store.write(f"r{i:04d}", {"light": rng.standard_normal((9, 3)).astype(np.float32),
                                  "shadow": rng.standard_normal(1).astype(np.float32)}, {"i": i})


def _same_tree(a: Path, b: Path) -> list[str]:
    """Relative paths that differ (missing on one side or different bytes)."""
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    diff = [str(p) for p in set(fa) ^ set(fb)]
    diff += [str(p) for p in fa if p in set(fb) and not filecmp.cmp(a / p, b / p, shallow=False)]
    return sorted(diff)


@pytest.mark.slow  # two writer processes at once
def test_two_concurrent_shard_writers_equal_the_unsharded_store(tmp_path):
    n = 300
    _write_shard(str(tmp_path / "ref"), None, n, None)
    ctx = mp.get_context("spawn")  # fresh interpreters, like two SLURM array tasks
    barrier = ctx.Barrier(2)
    procs = [ctx.Process(target=_write_shard, args=(str(tmp_path / "sharded"), f"{i}/2", n, barrier)) for i in (0, 1)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]
    store = EncodingStore.open(tmp_path / "sharded")
    assert store.ids() == [f"r{i:04d}" for i in range(n)] and store.verify() == []
    assert not [e for e in os.listdir(store.records_dir) if e.startswith(".")]  # no scratch left
    assert _same_tree(tmp_path / "ref", tmp_path / "sharded") == []


def _synth(out: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "difareli.cli.synth", f"out_dir={out}", "subjects=6", "lights=2", "resolution=24",
           "workers=1", "preview.enabled=false", *extra]
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


@pytest.mark.slow  # three fresh interpreters importing the renderer: ~15 s idle, ~50 s on the loaded 2-core CI
@pytest.mark.skipif(not HAS_ESTIMATORS, reason=NO_ESTIMATORS)  # synth's default inputs=estimated
def test_synth_two_concurrent_shards_byte_identical_to_unsharded(tmp_path):
    """difareli-synth shard=0/2 and shard=1/2 at once into one out_dir == one unsharded run, byte for byte."""
    procs = [_synth(tmp_path / "sharded", f"shard={i}/2") for i in (0, 1)] + [_synth(tmp_path / "ref")]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], [o[1][-2000:] for o in outs]
    written = [int(o[0].split("wrote ")[1].split()[0]) for o in outs[:2]]
    assert sum(written) == 12 and min(written) > 0  # each shard did part of the work
    ref = EncodingStore.open(tmp_path / "ref")
    assert EncodingStore.open(tmp_path / "sharded").ids() == ref.ids() and len(ref) == 12
    assert _same_tree(tmp_path / "ref", tmp_path / "sharded") == []


def test_synth_bad_shard_is_a_config_error(tmp_path):
    from hydra import compose, initialize_config_dir

    from difareli.cli import synth as cli
    from difareli.configs import CONFIG_DIR
    from difareli.synth.config import ConfigError

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name="synth", overrides=[f"out_dir={tmp_path / 'x'}", "shard=2/2"])
    with pytest.raises(ConfigError, match="shard='2/2' is invalid"):
        cli.validate(cfg)
    assert not (tmp_path / "x").exists()


def _bench_cfg(out, store_root, *overrides):
    return compose_train(out, [f"store={store_root}", "progress=false", "num_threads=null", "save_images=false",
                               "grid_pairs=0", *overrides], config_name="benchmark")


def test_sharded_benchmark_merges_to_the_unsharded_table(synth_store, tmp_path):
    from difareli.cli.benchmark import run
    from difareli.cli.table import run as table_run

    full = run(_bench_cfg(tmp_path / "full", synth_store, "method=lambertian", "limit=6"))
    parts = [run(_bench_cfg(tmp_path / "shards" / str(i), synth_store, "method=lambertian", "limit=6", f"shard={i}/2"))
             for i in (0, 1)]
    assert min(len(p.records) for p in parts) > 0
    # Same rows, same scores (only the wall time per image differs).
    rows = lambda recs: sorted((r.protocol, r.record_id, r.dssim, r.mse, r.lpips) for r in recs)  # noqa: E731
    assert rows(sum((p.records for p in parts), [])) == rows(full.records)
    merged = table_run(compose_train(tmp_path / "t", [f"runs=[{tmp_path}/shards/*]"], config_name="table"))
    want = full.table
    for cell, stats in want.cells.items():
        for metric, s in stats.items():
            got = merged.cells[cell][metric]
            assert got.n == s.n and got.mean == pytest.approx(s.mean, rel=1e-12)
            assert got.se == pytest.approx(s.se, rel=1e-9)
    assert tables.read_records(tmp_path / "shards" / "0" / tables.PER_IMAGE_CSV)  # per-shard per-image CSV
    # A missing shard is refused in one short line naming the run dir, the job's method and the missing shard
    # (not the job's whole settings).
    with pytest.raises(ValueError, match=r"1/2 missing") as e:
        table_run(compose_train(tmp_path / "t2", [f"runs=[{tmp_path}/shards/0]"], config_name="table"))
    msg = str(e.value)
    head = (f"run dir(s) {tmp_path / 'shards' / '0'} hold shards of one benchmark job (method LambertianRatio, "
            f"store {synth_store}): shard(s) 1/2 missing; ")
    assert msg.startswith(head) and "\n" not in msg and len(msg) < len(head) + 100


class _CentreCrop:
    """A stand-in aligner (no mediapipe needed): the centre square, resized."""

    def __init__(self, size: int):
        self.size = size

    def __call__(self, rgb):
        from PIL import Image

        h, w = rgb.shape[:2]
        s = min(h, w)
        crop = rgb[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
        image = np.asarray(Image.fromarray(crop).resize((self.size, self.size)))
        return {"image": image, "quad": np.zeros((4, 2)), "faces": 1, "box": [0, 0, s, s], "notes": []}


def test_preprocess_shards_equal_the_unsharded_run(tmp_path):
    """difareli-preprocess shard=0/2 + shard=1/2 into one store == the unsharded store; one report per shard."""
    import json

    from PIL import Image

    from difareli.estimators.batch import REPORT, run
    from difareli.estimators.pipeline import Pipeline

    src = tmp_path / "in"
    src.mkdir()
    import skimage.data

    astro = skimage.data.astronaut()
    for i in range(4):
        Image.fromarray(np.ascontiguousarray(np.roll(astro, 8 * i, axis=1))).save(src / f"photo{i}.png")
    pipeline = Pipeline(_CentreCrop(64), [], ["image"])  # the sharding, not the estimators, is under test
    run(pipeline, str(src), str(tmp_path / "ref"), previews=False, progress=False)
    counts = [run(pipeline, str(src), str(tmp_path / "sharded"), previews=False, progress=False,
                  shard=f"{i}/2").written for i in (0, 1)]
    assert counts == [2, 2]  # hash split of photo0..3: shard 0 owns photo1, photo2
    assert EncodingStore.open(tmp_path / "sharded").ids() == [f"photo{i}" for i in range(4)]
    # Arrays byte-identical; meta.json too except the measured per-step timings (rounded to 0.1 ms, so with this
    # one-step pipeline they may also agree: an empty diff is a pass, not a sign of nothing compared).
    diff = _same_tree(tmp_path / "ref" / "records", tmp_path / "sharded" / "records")
    assert all(d.endswith("meta.json") for d in diff)
    for d in diff:
        a, b = (json.loads((tmp_path / r / "records" / d).read_text()) for r in ("ref", "sharded"))
        assert {**a, "seconds": None} == {**b, "seconds": None}
    reports = [json.loads((tmp_path / "sharded" / REPORT.replace(".json", f".shard-{i}-of-2.json")).read_text())
               for i in (0, 1)]
    assert [r["written"] for r in reports] == [2, 2] and not (tmp_path / "sharded" / REPORT).exists()
