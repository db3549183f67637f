"""Resumable outputs refuse to mix provenance, and one output folder has one writer."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from difareli.data import provenance
from difareli.errors import UserError
from difareli.utils.fileio import folder_lock
from difareli.jobs.teacher_pairs import generate_teacher_pairs
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore

SRC = str(Path(__file__).resolve().parents[2] / "src")
SAMPLER = {"name": "ddim", "steps": 3}


def test_ensure_records_then_refuses_other_settings_naming_them(tmp_path):
    provenance.ensure(tmp_path / "out", {"checkpoint": "sha256:aa", "steps": 20}, "benchmark rows")
    provenance.ensure(tmp_path / "out", {"checkpoint": "sha256:aa", "steps": 20}, "benchmark rows")  # same: fine
    (tmp_path / "out" / "metrics_per_image.csv").write_text("x\n")  # a result made under the record
    with pytest.raises(UserError, match=r"checkpoint: 'sha256:aa' there, 'sha256:bb' now"):
        provenance.ensure(tmp_path / "out", {"checkpoint": "sha256:bb", "steps": 20}, "benchmark rows")
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "metrics_per_image.csv").write_text("x\n")
    with pytest.raises(UserError, match="without a record of what made them"):
        provenance.ensure(tmp_path / "old", {"steps": 20}, "benchmark rows")


def test_a_record_over_no_results_is_replaced_not_a_refusal(tmp_path, synth_store):
    """Before (issue 64, our probe): difareli-benchmark on a store without pairs stopped after recording its settings
    in out_dir; the same command on a store with pairs into that out_dir was refused "holds benchmark rows made with
    other settings (limit ...; store ...)" over a folder that held no rows."""
    import json
    import shutil

    from difareli.evaluation.baselines import Identity
    from difareli.evaluation.benchmark import SETTINGS, run_benchmark

    provenance.ensure(tmp_path / "out", {"steps": 20}, "rows")
    provenance.ensure(tmp_path / "out", {"steps": 30}, "rows")  # nothing was made under steps 20
    assert json.loads((tmp_path / "out" / "provenance.json").read_text()) == {"steps": 30}
    with pytest.raises(UserError, match="steps: 30 there, 40 now"):
        provenance.ensure(tmp_path / "out", {"steps": 40}, "rows", has_results=True)
    empty = tmp_path / "empty"
    shutil.copytree(synth_store, empty)
    (empty / "protocols.json").write_text(json.dumps({"same_subject": [], "different_subject": []}))
    out = tmp_path / "bench"
    with pytest.raises(UserError, match="has no same_subject pairs"):
        run_benchmark(EncodingStore.open(empty), Identity(), ["same_subject"], out, limit=1, progress=False)
    assert (out / SETTINGS).is_file()  # the stopped run's record, over no rows
    res = run_benchmark(EncodingStore.open(synth_store), Identity(), ["same_subject"], out, limit=1,
                        progress=False)
    assert len(res.records) == 1


def test_model_identity_follows_the_weights_not_the_file(tiny_checkpoint):
    import torch

    from difareli.lit import load_checkpoint

    a = load_checkpoint(tiny_checkpoint("difareli_pp")).model
    b = load_checkpoint(tiny_checkpoint("difareli_pp")).model
    assert provenance.model_identity(a) == provenance.model_identity(b)
    with torch.no_grad():
        next(b.parameters()).view(-1)[0] += 1e-3
    assert provenance.model_identity(a) != provenance.model_identity(b)


def test_teacher_pairs_refuse_another_teacher_and_a_student_refuses_another_store(synth_store, tiny_checkpoint,
                                                                                  tmp_path):
    from difareli.lit.pairs import TeacherPairs

    store = EncodingStore.open(synth_store)
    pp = Relighter(tiny_checkpoint("difareli_pp"), SAMPLER, device="cpu")
    generate_teacher_pairs(pp, store, tmp_path / "pairs", limit=2, batch_size=2, progress=False)
    other = Relighter(tiny_checkpoint("difareli_pp"), {"name": "ddim", "steps": 4}, device="cpu")
    with pytest.raises(UserError, match=r"sampler: .*there.*now"):
        generate_teacher_pairs(other, store, tmp_path / "pairs", limit=4, batch_size=2, progress=False)
    assert len(EncodingStore.open(tmp_path / "pairs").ids()) == 2  # nothing mixed in
    # A student on another store with these pairs: refused, naming both.
    from difareli.synth.generator import generate

    generate(out_dir=str(tmp_path / "other"), subjects=4, lights=2, resolution=32, seed=5)
    elsewhere = EncodingStore.open(tmp_path / "other")
    ids = elsewhere.ids()
    with pytest.raises(UserError, match=r"was made from .* not from the training store"):
        TeacherPairs(elsewhere, ids, pp.model.spatial_inputs, pp.model.nonspatial_inputs,
                     EncodingStore.open(tmp_path / "pairs"))
    ok = TeacherPairs(store, store.ids(), pp.model.spatial_inputs, pp.model.nonspatial_inputs,
                      EncodingStore.open(tmp_path / "pairs"))
    assert len(ok) == 2


HOLD = textwrap.dedent("""
    import sys, time
    from difareli.utils.fileio import folder_lock
    with folder_lock(sys.argv[1], "benchmark"):
        print("held", flush=True)
        time.sleep(60)
""")


def test_a_second_writer_into_a_locked_folder_is_refused_naming_the_first(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path / "out")], stdout=subprocess.PIPE, text=True,
                            env={"PYTHONPATH": SRC, "PATH": "/usr/bin:/bin"})
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(UserError, match=rf"being written by difareli-benchmark \(pid {proc.pid}\)"):
            with folder_lock(tmp_path / "out", "benchmark"):
                pass
    finally:
        proc.kill()
        proc.wait()
    with folder_lock(tmp_path / "out", "benchmark"):  # the lock died with its holder
        assert (tmp_path / "out" / ".difareli.lock").read_text().startswith("difareli-benchmark")


def test_a_resumed_benchmark_with_another_checkpoint_is_refused(synth_store, tiny_checkpoint, tmp_path):
    """Killed with one checkpoint, rerun with another into the same out_dir: refused, naming the model (it kept
    the other checkpoint's rows); the same checkpoint resumes."""
    import torch

    from difareli.evaluation.baselines import DiffusionMethod
    from difareli.evaluation.benchmark import PARTIAL_CSV, run_benchmark
    from difareli.lit import load_checkpoint

    store = EncodingStore.open(synth_store)
    sampler = {"name": "ddim", "steps": 2}
    a = load_checkpoint(tiny_checkpoint("difareli_pp"))
    b = load_checkpoint(tiny_checkpoint("difareli_pp"))
    with torch.no_grad():
        next(b.model.parameters()).view(-1)[0] += 1e-2  # another checkpoint of the same variant

    class Dies(DiffusionMethod):  # killed mid-run, on the pair-by-pair and the batched path alike
        def relight(self, *args, **kwargs):
            raise KeyboardInterrupt

        def relight_many(self, *args, **kwargs):
            raise KeyboardInterrupt

    out = tmp_path / "bench"
    with pytest.raises(KeyboardInterrupt):
        run_benchmark(store, Dies(a, sampler, name="pp"), ["same_subject"], out, limit=2, progress=False)
    (out / PARTIAL_CSV).write_text("method,protocol,record_id,dssim,mse,lpips,seconds,rule\n")  # a kept row's header
    with pytest.raises(UserError, match=r"holds benchmark rows made with other settings \(model: 'weights:"):
        run_benchmark(store, DiffusionMethod(b, sampler, name="pp"), ["same_subject"], out, limit=2, progress=False)
    res = run_benchmark(store, DiffusionMethod(a, sampler, name="pp"), ["same_subject"], out, limit=2, progress=False)
    assert len(res.records) == 2
