"""A full disk in difareli-synth and difareli-benchmark: one line naming the file, exit 2, and on disk
the records and rows already written whole, no partial record, row or file. Simulated by a writer that writes a
few bytes and then fails with ENOSPC; and, where this process may mount one, on a real small tmpfs."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from difareli import errors
from difareli.evaluation import tables
from difareli.evaluation.baselines import Identity
from difareli.evaluation.benchmark import PARTIAL_CSV, run_benchmark
from difareli.errors import UserError
from difareli.data.store import EncodingStore
from difareli.data import protocols as sp
from difareli.synth.config import ENCODINGS
from difareli.synth.generator import generate

from tests.helpers import compose_train, failing_save

ENOSPC = OSError(errno.ENOSPC, "No space left on device")
RESUME = "free space and rerun the same command to resume (what was already written is complete and kept)"
SYNTH = {"subjects": 4, "lights": 2, "resolution": 32, "seed": 3}


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _cli(name, run, cfg, monkeypatch, capsys):
    """Run a console script's task as the script does: (exit status, stderr)."""
    monkeypatch.delenv("DIFARELI_DEBUG", raising=False)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    with pytest.raises(SystemExit) as e:
        errors.cli_entry(name)(lambda: run(cfg))()
    return e.value.code, capsys.readouterr().err


def _fill_disk_at(monkeypatch, prefix: str) -> None:
    """``Path.write_text`` into a file named ``prefix...`` writes 20 characters, then fails with ENOSPC."""
    real = Path.write_text

    def full(self, text, *a, **kw):
        if self.name.startswith(prefix):
            real(self, text[:20], *a, **kw)
            raise ENOSPC
        return real(self, text, *a, **kw)

    monkeypatch.setattr(Path, "write_text", full)


def _synth_cfg(out):
    from hydra import compose, initialize_config_dir

    from difareli.configs import CONFIG_DIR

    with initialize_config_dir(version_base="1.3", config_dir=str(CONFIG_DIR)):
        return compose(config_name="synth", overrides=[f"out_dir={out}", "subjects=4", "lights=2", "resolution=32",
                                                       "seed=3", "workers=1", "inputs=exact", "preview.enabled=false"])


def _assert_whole_store(out: Path) -> list[str]:
    """Only complete records (no scratch folder), each readable and finite; returns their ids."""
    assert not [p.name for p in (out / "records").iterdir() if p.name.startswith(".")]
    store = EncodingStore.open(out)
    assert store.verify(check_values=True) == []
    return store.ids()


# ------------------------------------------------------------------------------------------ difareli-synth
def test_synth_on_a_full_disk_names_the_file_and_keeps_the_records_written(tmp_path, monkeypatch, capsys):
    from difareli.cli.synth import run

    out = tmp_path / "store"
    failing_save(monkeypatch, ENOSPC, at=2 * len(ENCODINGS) + 6)  # the third record's sixth encoding
    code, err = _cli("synth", run, _synth_cfg(out), monkeypatch, capsys)
    monkeypatch.undo()
    third = out / "records" / sp.record_id(1, 0) / f"{ENCODINGS[5]}.npy"
    assert code == 2
    assert err == f"difareli-synth: no space left on the device writing {third} (No space left on device); {RESUME}\n"
    assert _assert_whole_store(out) == [sp.record_id(0, 0), sp.record_id(0, 1)]  # the two before it, whole
    kept = _files(out / "records")
    rep = run(_synth_cfg(out))  # disk freed: the same command resumes
    assert (rep.written, rep.skipped, rep.problems) == (6, 2, [])
    assert {k: v for k, v in _files(out / "records").items() if k in kept} == kept  # untouched by the resume
    assert len(_assert_whole_store(out)) == 8


def test_synth_split_files_on_a_full_disk_keep_the_previous_ones(tmp_path):
    out = tmp_path / "store"
    generate(str(out), **SYNTH)
    before = _files(out)
    real = Path.write_text

    def full(self, text, *a, **kw):
        if self.name.startswith(f".{sp.PROTOCOLS_FILE}.tmp-"):
            real(self, text[:10], *a, **kw)
            raise ENOSPC
        return real(self, text, *a, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Path, "write_text", full)
        with pytest.raises(UserError) as e:
            generate(str(out), **SYNTH)
    assert str(e.value) == (f"no space left on the device writing {out}/{sp.PROTOCOLS_FILE} (No space left on "
                            f"device); {RESUME}")
    assert _files(out) == before  # protocols.json whole, its scratch file removed


# ------------------------------------------------------------------------------------------ difareli-benchmark
@pytest.fixture(scope="module")
def store(synth_store):
    return EncodingStore.open(synth_store)


KW = {"limit": 3, "progress": False, "grid_pairs": 0}


def test_benchmark_rows_on_a_full_disk_keep_the_rows_scored(store, tmp_path):
    out = tmp_path / "bench"
    real, rows = os.write, []

    def full(fd, data):
        if os.readlink(f"/proc/self/fd/{fd}").endswith(PARTIAL_CSV):
            rows.append(bytes(data))
            if len(rows) == 2:  # the second row: half of it reaches the disk, then the disk is full
                real(fd, bytes(data)[: len(data) // 2])
                raise ENOSPC
        return real(fd, data)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "write", full)
        with pytest.raises(UserError) as e:
            run_benchmark(store, Identity(), ["same_subject"], out, **KW)
    assert str(e.value) == (f"no space left on the device writing {out / PARTIAL_CSV} (No space left on device); "
                            f"{RESUME}")
    assert (out / PARTIAL_CSV).read_bytes() == rows[0]  # the header and first row, whole; no half row
    assert len(rows[0].decode().splitlines()) == 2
    assert not list(out.rglob("*.tmp-*"))
    res = run_benchmark(store, Identity(), ["same_subject"], out, **KW)  # freed: resumes, first row kept
    assert len(res.records) == 3 and not (out / PARTIAL_CSV).exists()
    assert len((out / "metrics_per_image.csv").read_text().splitlines()) == 4


def test_benchmark_summary_on_a_full_disk_exits_2_and_keeps_the_previous_one(store, tmp_path, monkeypatch, capsys):
    from difareli.cli.benchmark import run

    out = tmp_path / "bench"
    cfg = compose_train(out, [f"store={store.root}", "progress=false", "num_threads=null", "method=identity",
                              "limit=2", "protocols=[same_subject]", "grid_pairs=1"], config_name="benchmark")
    run(cfg)
    shutil.copy(out / "metrics_per_image.csv", tmp_path / "first.csv")
    before = _files(out)
    _fill_disk_at(monkeypatch, ".summary.md.tmp-")
    code, err = _cli("benchmark", run, cfg, monkeypatch, capsys)
    monkeypatch.undo()
    assert code == 2
    assert err == (f"difareli-benchmark: no space left on the device writing {out / 'summary.md'} (No space left on "
                   f"device); {RESUME}\n")
    after = _files(out)
    assert after["summary.md"] == before["summary.md"] and not [k for k in after if ".tmp-" in k]
    assert set(after) == set(before) | {PARTIAL_CSV}  # the rows scored again are kept for the rerun
    def score(path):
        return [(r.record_id, r.dssim, r.mse, r.lpips) for r in tables.read_records(path)]

    assert score(out / "metrics_per_image.csv") == score(tmp_path / "first.csv")  # rewritten whole (new timings)


def test_table_outputs_on_a_full_disk_keep_the_previous_ones(store, tmp_path, monkeypatch, capsys):
    # difareli-table publishes its outputs together (fileio.staged_outputs): a full disk keeps the earlier ones.
    from difareli.cli.table import run

    run_benchmark(store, Identity(), ["same_subject"], tmp_path / "bench", **KW)
    out = tmp_path / "table"
    cfg = compose_train(out, [f"runs=[{tmp_path / 'bench'}]", "paired=off"], config_name="table")
    run(cfg)
    before = _files(out)
    _fill_disk_at(monkeypatch, ".table.tex.tmp-")  # table.md and table.csv are written whole, then the disk fills
    code, err = _cli("table", run, cfg, monkeypatch, capsys)
    monkeypatch.undo()
    assert code == 2 and err == (f"difareli-table: no space left on the device writing {out / 'table.tex'} (No space "
                                 "left on device); free space or write elsewhere (the previous outputs are kept as "
                                 "they were)\n")
    after = _files(out)
    assert after == before and "table.tex" in after  # the earlier outputs all kept, no scratch folder


# ------------------------------------------------------------------------------------------ a real full disk
@pytest.fixture
def tmpfs(tmp_path):
    """``mount(size)``: a tmpfs of ``size`` at ``tmp_path/disk`` (remounted when called again); skipped where
    this process may not mount one (it needs root or CAP_SYS_ADMIN)."""
    where, mounted = tmp_path / "disk", []
    where.mkdir()
    if shutil.which("mount") is None or shutil.which("umount") is None:
        pytest.skip("no mount/umount here: cannot make a small tmpfs")

    def mount(size: str) -> Path:
        opts = f"{'remount,' if mounted else ''}size={size}"
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True, text=True,
                           check=False)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode}): needs root or CAP_SYS_ADMIN")
        mounted.append(size)
        return where

    yield mount
    if mounted:
        subprocess.run(["umount", str(where)], check=False)


def test_synth_on_a_real_full_tmpfs(tmpfs):
    disk = tmpfs("400k")  # the header and about two records of 32 px (about 136 KB each)
    out = disk / "store"
    with pytest.raises(UserError) as e:
        generate(str(out), **SYNTH)
    msg = str(e.value)
    assert msg.startswith(f"no space left on the device writing {out}/") and msg.endswith(RESUME)
    ids = _assert_whole_store(out)
    assert 0 < len(ids) < 8
    kept = _files(out / "records")
    tmpfs("20m")  # space freed
    assert generate(str(out), **SYNTH).written == 8 - len(ids)
    assert {k: v for k, v in _files(out / "records").items() if k in kept} == kept
    assert len(_assert_whole_store(out)) == 8


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # imageio's writer, closed late
def test_benchmark_on_a_real_full_tmpfs(store, tmpfs):
    out = tmpfs("8m") / "bench"
    run_benchmark(store, Identity(), ["same_subject"], out, **KW)
    before = _files(out)
    with open(out.parent / "filler", "wb") as f:  # fill the disk to the last byte
        try:
            while True:
                f.write(b"\0" * 65536)
                f.flush()
        except OSError as e:
            assert e.errno == errno.ENOSPC
            f.truncate(f.tell())  # keep what fitted (close must not flush the rest)
            f.seek(0, os.SEEK_END)
    with pytest.raises(UserError, match=r"^no space left on the device writing "):
        run_benchmark(store, Identity(), ["same_subject"], out, **KW)
    after = _files(out)
    assert not [k for k in after if ".tmp-" in k]
    for name, data in after.items():  # every file is the previous one, whole, or a whole new one
        if name != PARTIAL_CSV:
            assert data == before[name], name
    assert after.get(PARTIAL_CSV, b"").count(b"\n") == len(after.get(PARTIAL_CSV, b"").splitlines())
