"""A weights folder explains itself: every tampered variant of a shipped folder (config.json's types, keys and bounds;
the safetensors header's length, offsets, dtypes and shapes; a renamed .ckpt, a missing or truncated file; NaN
weights) is one line naming the file (and the tensor or key) and the fix, never a traceback and never code run; and
difareli-export refuses a source holding NaN, or a full disk, without leaving a folder."""

from __future__ import annotations

import errno
import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from difareli.checkpoints import zoo
from difareli.checkpoints.loading import load_checkpoint
from difareli.errors import UserError

SOURCE = zoo.SHIPPED_DIR / "difareli_pp_ss-synth64"
BIN = Path(sys.executable).parent


def _header(blob: bytes) -> tuple[dict, bytes]:
    n = struct.unpack("<Q", blob[:8])[0]
    return json.loads(blob[8:8 + n]), blob[8 + n:]


def _with_header(edit):
    """A safetensors edit: ``edit(header, first tensor's name)`` on the parsed header, written back."""
    def apply(blob: bytes) -> bytes:
        head, data = _header(blob)
        edit(head, sorted((k for k in head if k != "__metadata__"), key=lambda k: head[k]["data_offsets"])[0])
        text = json.dumps(head).encode()
        return struct.pack("<Q", len(text)) + text + data
    return apply


def _nan_weights(blob: bytes) -> bytes:
    from safetensors.torch import load, save

    state = load(blob)
    state["net.spatial.input_blocks.0.0.weight"] = state["net.spatial.input_blocks.0.0.weight"].clone()
    state["net.spatial.input_blocks.0.0.weight"].view(-1)[5] = float("nan")
    return save(state, metadata={"format": "difareli-weights-folder"})


def _hp(key, value):
    return lambda c: c["hyper_parameters"].__setitem__(key, value)


# name -> (config edit, safetensors edit, what the one line must contain)
CASES = {
    "resolution_4096": (lambda c: c["hyper_parameters"]["input_dims"].__setitem__("resolution", 4096), None,
                        "config.json: hyper_parameters.input_dims.resolution is 4096, must be an integer from 8 to "
                        "1024"),
    "resolution_text": (lambda c: c["hyper_parameters"]["input_dims"].__setitem__("resolution", "64"), None,
                        'config.json: hyper_parameters.input_dims.resolution is "64", must be an integer'),
    "step_text": (lambda c: c.__setitem__("global_step", "x"), None, 'config.json: global_step is "x", must be an '
                  "integer"),
    "hp_array": (lambda c: c.__setitem__("hyper_parameters", [1]), None,
                 "config.json: hyper_parameters is an array, must be an object"),
    "no_module": (lambda c: c.pop("difareli_module"), None,
                  "config.json: the required key 'difareli_module' is missing"),
    "extra_key": (lambda c: c.__setitem__("evil", 1), None, "config.json: unknown key 'evil'"),
    "extra_hp": (_hp("evil", 1), None, "config.json: hyper_parameters.evil is not a parameter of StudentModule"),
    "hp_type": (_hp("residual", "yes"), None, 'config.json: hyper_parameters.residual is "yes", not of '
                "StudentModule's type for it (bool)"),
    "stats_nan": (lambda c: c["hyper_parameters"]["nonspatial_stats"]["mean"].__setitem__(0, float("nan")), None,
                  "config.json: hyper_parameters.nonspatial_stats is an object, must be null or {mean, std}"),
    "module_os": (lambda c: c.__setitem__("difareli_module", "os.system"), None,
                  'config.json: difareli_module is "os.system", must be a model class under difareli. (a '
                  "checkpoint is data: no other module is imported); export the folder again"),
    "optimizer_os": (_hp("optimizer", {"_target_": "os.system", "command": "touch PWNED"}), _nan_weights,
                     "tensor 'net.spatial.input_blocks.0.0.weight' holds 1 NaN/Inf value(s) of 6336"),
    "truncated": (None, lambda b: b[: len(b) // 2], "model.safetensors: tensor 'net.unet.time_embed.2.weight' ends "
                  "at byte"),
    "short": (None, lambda b: b[:5], "model.safetensors: 5 bytes, too short for a safetensors file"),
    "header_too_long": (None, lambda b: struct.pack("<Q", 10 ** 12) + b[8:],
                        "model.safetensors: its header claims 1000000000000 bytes"),
    "offsets_lie": (None, _with_header(lambda h, k: h[k].__setitem__("data_offsets", [0, 10 ** 9])),
                    "model.safetensors: tensor 'net.spatial.input_blocks.0.0.bias': shape (32,) of F32 needs 128 "
                    "bytes, its data_offsets span 1000000000: the header lies"),
    "dtype_unknown": (None, _with_header(lambda h, k: h[k].__setitem__("dtype", "XX")),
                      "model.safetensors: tensor 'net.spatial.input_blocks.0.0.bias': dtype 'XX' is not one"),
    "dtype_int": (None, _with_header(lambda h, k: h[k].__setitem__("dtype", "I32")),
                  "model.safetensors: tensor 'net.spatial.input_blocks.0.0.bias' is int32, the model's is float32"),
    "shape_wrong": (None, _with_header(lambda h, k: (h[k].__setitem__("shape", [16, 2]))),
                    "model.safetensors: tensor 'net.spatial.input_blocks.0.0.bias' has shape (16, 2), the model "
                    "built from its hyperparameters needs (32,)"),
    "tensor_dropped": (None, _with_header(lambda h, k: h.pop(k)), "model.safetensors: tensor "
                       "'net.spatial.input_blocks.0.0.weight' starts at byte 128, the data starts at 0: a gap"),
    "ckpt_renamed": (None, lambda b: (zoo.SHIPPED_DIR / "difareli_pp_ss-synth64.ckpt").read_bytes(),
                     "model.safetensors is a zip archive (a PyTorch .ckpt saved by torch.save, renamed?), not a "
                     "safetensors file"),
    "nan": (None, _nan_weights, "model.safetensors: tensor 'net.spatial.input_blocks.0.0.weight' holds 1 NaN/Inf "
            "value(s) of 6336: the weights are corrupt or the run diverged"),
}


def _tampered(root: Path, name: str) -> Path:
    cfg_edit, blob_edit, _ = CASES[name]
    folder = root / name
    shutil.copytree(SOURCE, folder)
    if cfg_edit is not None:
        config = json.loads((folder / "config.json").read_text())
        cfg_edit(config)
        (folder / "config.json").write_text(json.dumps(config))
    if blob_edit is not None:
        (folder / "model.safetensors").write_bytes(blob_edit((folder / "model.safetensors").read_bytes()))
    return folder


def test_every_tampered_variant_is_one_line_naming_the_file(tmp_path, monkeypatch):
    ran = []
    monkeypatch.setattr(os, "system", lambda *a: ran.append(a))  # never called: a checkpoint is data
    monkeypatch.chdir(tmp_path)
    for name, (_, _, want) in CASES.items():
        folder = _tampered(tmp_path, name)
        with pytest.raises(UserError) as e:
            load_checkpoint(folder)
        msg = str(e.value)
        assert want in msg and "\n" not in msg, (name, msg)
        assert str(folder) in msg, (name, msg)
    assert ran == [] and not (tmp_path / "PWNED").exists()


def test_missing_file_and_shipped_folders_still_load(tmp_path):
    folder = tmp_path / "w"
    shutil.copytree(SOURCE, folder)
    (folder / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match=f"checkpoint={folder} is a weights folder without model.safetensors "
                                                r"\(it holds config.json\)"):
        load_checkpoint(folder)
    assert load_checkpoint(SOURCE).resolution == 64  # the checks pass a good folder


@pytest.mark.parametrize("name", ["resolution_4096", "ckpt_renamed"])
def test_a_cli_given_a_tampered_folder_exits_2_in_one_line(tmp_path, synth_store, name):
    folder = _tampered(tmp_path, name)
    proc = subprocess.run([str(BIN / "difareli-benchmark"), f"store={synth_store}", "method=diffusion",
                           f"method.checkpoint={folder}", f"out_dir={tmp_path / 'out'}", "limit=1"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("difareli-benchmark: ") and CASES[name][2] in line


def _ckpt_with_nan(tmp_path: Path) -> Path:
    ckpt = torch.load(zoo.SHIPPED_DIR / "difareli_pp_ss-synth64.ckpt", map_location="cpu", weights_only=True)
    ckpt["state_dict"]["net.spatial.input_blocks.0.0.weight"][0, 0, 0, 0] = float("inf")
    torch.save(ckpt, tmp_path / "nan.ckpt")
    return tmp_path / "nan.ckpt"


def test_export_refuses_nan_weights_before_writing(tmp_path):
    from difareli.cli.export import main

    source = _ckpt_with_nan(tmp_path)
    with pytest.raises(SystemExit) as e:
        main([str(source), str(tmp_path / "w")])
    assert e.value.code == 2
    assert not (tmp_path / "w").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["nan.ckpt"]
    with pytest.raises(UserError, match=rf"checkpoint={source}: tensor 'net.spatial.input_blocks.0.0.weight' holds 1 "
                                        r"NaN/Inf value\(s\) of 6336: .*a folder of it would not load, so nothing was "
                                        "written"):
        from difareli.checkpoints.export import export_folder

        export_folder(source, tmp_path / "w")


def test_export_onto_a_full_disk_leaves_no_folder_and_keeps_an_earlier_one(tmp_path, monkeypatch):
    from difareli.checkpoints.export import export_folder

    real = Path.write_text

    def full(self, *a, **k):
        if self.name == "config.json":
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return real(self, *a, **k)

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(UserError, match=rf"no space left on the device writing {tmp_path / 'w' / 'config.json'} "
                                        r"\(No space left on device\); free space or export elsewhere"):
        export_folder("difareli_pp_ss-synth64", tmp_path / "w")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no folder, no scratch
    monkeypatch.undo()
    export_folder("difareli_pp-synth64", tmp_path / "w")
    before = {p.name: p.read_bytes() for p in (tmp_path / "w").iterdir()}
    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(UserError, match="no space left on the device"):
        export_folder("difareli_pp_ss-synth64", tmp_path / "w")
    assert {p.name: p.read_bytes() for p in (tmp_path / "w").iterdir()} == before  # the earlier folder, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w"]


# Issue 64's own probe (docs/robustness.md, "our nine"): folders made to break the readers rather than lie to them.
def _deep(n: int = 100_000) -> bytes:
    return b"[" * n + b"]" * n


ODD_FOLDERS = {
    "header_deep": (lambda f: (f / "model.safetensors").write_bytes(struct.pack("<Q", 200_000) + _deep()),
                    "model.safetensors: its header nests arrays or objects too deeply to be a tensor list: corrupt; "
                    "export the folder again"),
    "config_deep": (lambda f: (f / "config.json").write_bytes(_deep()),
                    "config.json: nests arrays or objects too deeply to be a weights folder's config; export the "
                    "folder again"),
    "format_newer": (lambda f: _edit_config(f, difareli_format=99),
                     "config.json: difareli_format is 99, newer than this difareli reads (2); load it with the "
                     "difareli version that wrote it"),
    "step_huge": (lambda f: _edit_config(f, global_step=10 ** 400),
                  "config.json: global_step is 100000000000000000000000000000... (401 characters), must be an "
                  "integer from 0 to 9223372036854775807; export the folder again"),
    "weights_fifo": (lambda f: ((f / "model.safetensors").unlink(), os.mkfifo(f / "model.safetensors")),
                     "its model.safetensors is a FIFO (named pipe), not the file a weights folder holds; copy the "
                     "folder again whole"),
    "weights_device": (lambda f: ((f / "model.safetensors").unlink(), os.symlink("/dev/zero", f / "model.safetensors")),
                       "its model.safetensors is a device, not the file a weights folder holds"),
    "config_folder": (lambda f: ((f / "config.json").unlink(), (f / "config.json").mkdir()),
                      "its config.json is a folder, not the file a weights folder holds"),
}


def _edit_config(folder: Path, **values) -> None:
    config = json.loads((folder / "config.json").read_text())
    config.update(values)
    (folder / "config.json").write_text(json.dumps(config))


@pytest.mark.parametrize("name", sorted(ODD_FOLDERS))
def test_folders_made_to_break_the_readers_are_one_line(tmp_path, name):
    """Before: a RecursionError traceback (a header or config.json nested 100,000 deep), a newer format or an
    absurd step loaded as if current, a FIFO, a device link or a folder in a file's place called "missing"."""
    folder = tmp_path / name
    shutil.copytree(SOURCE, folder)
    make, want = ODD_FOLDERS[name]
    make(folder)
    with pytest.raises(UserError) as e:
        load_checkpoint(folder)
    msg = str(e.value)
    assert want in msg and str(folder) in msg and "\n" not in msg, msg


def test_a_ckpt_of_a_newer_format_is_refused(tmp_path):
    """Before: a .ckpt stating difareli_format 99 was read as the current format (2) and built."""
    ckpt = torch.load(zoo.SHIPPED_DIR / "difareli_pp_ss-synth64.ckpt", map_location="cpu", weights_only=True)
    for value, shown in ((99, "99"), ("2", "'2'")):
        ckpt["difareli_format"] = value
        torch.save(ckpt, tmp_path / "new.ckpt")
        with pytest.raises(UserError) as e:
            load_checkpoint(tmp_path / "new.ckpt")
        assert str(e.value) == (f"checkpoint={tmp_path / 'new.ckpt'}: difareli_format is {shown}, not a format this "
                                "difareli reads (1 to 2); load it with the difareli version that wrote it")
