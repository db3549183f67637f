"""One error style for every CLI, config values checked before any work, checkpoints named."""

from __future__ import annotations

import os

import numpy as np
import pytest

from difareli.diffusion.spec import check_sampler
from difareli import errors
from difareli.errors import UserError

from tests.helpers import compose_train


# ------------------------------------------------------------------------------------------ cli_entry
def _run_task(fn, monkeypatch, capsys, debug=False):
    monkeypatch.delenv("DIFARELI_DEBUG", raising=False)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    if debug:
        monkeypatch.setenv("DIFARELI_DEBUG", "1")
    with pytest.raises(SystemExit) as e:
        errors.cli_entry("demo")(fn)()
    return e.value.code, capsys.readouterr().err


def test_user_error_is_one_line_exit_2(monkeypatch, capsys):
    def task():
        raise UserError("limit=0 is invalid: must be an integer >= 1")

    code, err = _run_task(task, monkeypatch, capsys)
    assert code == 2 and err == "difareli-demo: limit=0 is invalid: must be an integer >= 1\n"


def test_internal_error_keeps_traceback_and_debug_shows_user_ones(monkeypatch, capsys):
    def broadcast():
        return np.zeros(3) + np.zeros(4)  # a ValueError from numpy: a bug, not a user error

    monkeypatch.delenv("DIFARELI_DEBUG", raising=False)
    with pytest.raises(ValueError, match="broadcast"):
        errors.cli_entry("demo")(broadcast)()
    monkeypatch.setenv("DIFARELI_DEBUG", "1")
    with pytest.raises(UserError):
        errors.cli_entry("demo")(lambda: errors.check_int(0, "limit"))()


def test_project_user_types_and_os_errors_are_user_errors(monkeypatch, capsys):
    from difareli.data.store import EncodingStore

    code, err = _run_task(lambda: EncodingStore.open("/nonexistent/store"), monkeypatch, capsys)
    assert code == 2 and err.startswith("difareli-demo: no encoding store at /nonexistent/store")
    code, err = _run_task(lambda: open("/nonexistent/x/y.txt"), monkeypatch, capsys)
    assert code == 2 and "/nonexistent/x/y.txt: No such file or directory" in err


def _raiser(exc):
    def task():
        raise exc

    return task


def test_a_builtin_error_raised_by_difareli_keeps_its_traceback(monkeypatch, capsys):
    """The type decides, not where the raise is: a plain ValueError/KeyError/FileNotFoundError from a ``raise``
    line of difareli's source is an internal error and keeps its traceback."""
    import linecache
    from pathlib import Path

    # A function whose code is a file of the package with a ``raise`` line: what the old rule, reading the
    # innermost frame's source text, took for a user error.
    src = "def check(exc):\n    raise exc\n"
    fake = str(Path(errors.__file__).parent / "_probe_raise.py")
    monkeypatch.setitem(linecache.cache, fake, (len(src), None, src.splitlines(True), fake))
    scope: dict = {}
    exec(compile(src, fake, "exec"), scope)
    for exc in (ValueError("shapes (3,) and (4,) differ"), KeyError("k"), FileNotFoundError("f")):
        with pytest.raises(type(exc)) as e:
            errors.cli_entry("demo")(lambda: scope["check"](exc))()
        assert e.value is exc and e.value.__traceback__.tb_next is not None
        assert errors.user_message(exc) is None
    assert capsys.readouterr().err == ""


def test_user_subclasses_give_one_line_and_keep_builtin_catchers(monkeypatch, capsys):
    class BadThing(UserError):
        pass

    code, err = _run_task(_raiser(BadThing("thing=3 is bad; give thing=1")), monkeypatch, capsys)
    assert code == 2 and err == "difareli-demo: thing=3 is bad; give thing=1\n"
    missing = errors.MissingError("no record 'x' in store /s")
    assert str(missing) == "no record 'x' in store /s" == errors.user_message(missing)  # KeyError would quote it
    with pytest.raises(KeyError):
        raise missing
    code, err = _run_task(_raiser(missing), monkeypatch, capsys)
    assert code == 2 and err == "difareli-demo: no record 'x' in store /s\n"
    gone = errors.UserFileNotFoundError("target light file /x.npy does not exist")
    assert isinstance(gone, OSError) and str(gone) == errors.user_message(gone)
    with pytest.raises(FileNotFoundError):
        raise gone
    with pytest.raises(FileNotFoundError, match="does not exist; give the path"):
        errors.check_file("/nonexistent/light.npy", "target.light")


def test_project_types_are_user_types(synth_store):
    from difareli.app.checks import RequestError
    from difareli.data.inputs import MissingEncodingError
    from difareli.data.store import EncodingStore
    from difareli.diffusion.spec import SamplerConfigError
    from difareli.synth.config import ConfigError

    assert issubclass(MissingEncodingError, errors.MissingError) and issubclass(MissingEncodingError, KeyError)
    assert str(MissingEncodingError("needs shadow_map")) == "needs shadow_map"
    assert all(issubclass(t, UserError) for t in (ConfigError, SamplerConfigError, RequestError))
    store = EncodingStore.open(synth_store)
    try:  # code that recovers from a missing record with ``except KeyError`` still does
        store.read("no_such_record")
    except KeyError as e:
        assert isinstance(e, errors.MissingError) and errors.user_message(e) == f"no record 'no_such_record' in " \
            f"store {store.root}"
    with pytest.raises(FileNotFoundError):  # and a missing store is still a FileNotFoundError
        EncodingStore.open(synth_store / "none")


def test_sigterm_stops_cleanly(monkeypatch, capsys):
    import signal

    def task():
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("not reached")

    old = signal.getsignal(signal.SIGTERM)
    try:
        code, err = _run_task(task, monkeypatch, capsys)
    finally:
        signal.signal(signal.SIGTERM, old)
    assert code == 143 and "stopped (SIGTERM)" in err


# ------------------------------------------------------------------------------------------ values
@pytest.mark.parametrize("value", [2.7, 0, -3, True, "5", None])
def test_check_int_rejects(value):
    with pytest.raises(UserError, match=r"^sampler.steps="):
        errors.check_int(value, "sampler.steps", 1)


def test_check_int_and_number_accept():
    assert errors.check_int(3, "k") == 3 and errors.check_int(None, "limit", allow_none=True) is None
    assert errors.check_number("2.5", "target.yaw") == 2.5
    for bad in ("nan", float("inf"), 1e300, "abc"):
        with pytest.raises(UserError, match="target.yaw"):
            errors.check_number(bad, "target.yaw")


def test_check_int_bounds_and_check_choice():
    assert errors.check_int(3600, "video.frames", 1, maximum=3600) == 3600
    with pytest.raises(UserError, match=r"^video.frames=3601 is invalid: must be an integer from 1 to 3600; "):
        errors.check_int(3601, "video.frames", 1, maximum=3600)
    with pytest.raises(UserError, match=r"^video.frames=0 is invalid: must be an integer from 1 to 3600; "):
        errors.check_int(0, "video.frames", 1, maximum=3600)
    assert errors.check_choice("roll", "rotation.axis", ("yaw", "roll")) == "roll"
    with pytest.raises(UserError, match=r"^rotation.axis='pitch': use one of yaw, roll$"):
        errors.check_choice("pitch", "rotation.axis", ("yaw", "roll"))


def test_check_sampler_names_valid_ones():
    with pytest.raises(UserError, match=r"sampler.name='euler' is not a sampler; choose from \['ddim'"):
        check_sampler({"name": "euler", "steps": 10})
    with pytest.raises(UserError, match="sampler.steps=2.7"):
        check_sampler({"name": "ddim", "steps": 2.7})
    with pytest.raises(UserError, match="unknown option 'foo' for sampler"):  # then whole, by its spec
        check_sampler({"name": "ddim", "steps": 10, "foo": 1})
    check_sampler({"name": "unipc", "steps": 10, "order": 2})


def test_check_out_dir(tmp_path, monkeypatch):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(UserError, match="out_dir=.*file is a file"):
        errors.check_out_dir(f)
    with pytest.raises(UserError, match="which is a file"):
        errors.check_out_dir(f / "sub")
    assert errors.check_out_dir(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    ro = tmp_path / "ro"
    ro.mkdir()
    # root ignores permission bits, so simulate what a non-root user sees
    monkeypatch.setattr(errors.os, "access", lambda p, mode: str(p) != str(ro))
    with pytest.raises(UserError, match="is not writable"):
        errors.check_out_dir(ro / "run")


def test_check_finite_names_input_and_index():
    a = np.zeros((9, 3))
    a[4, 1] = np.nan
    with pytest.raises(errors.NonFiniteError,
                       match=r"target light: 1 of 27 values are NaN or Inf \(first at index \(4, 1\)\)"):
        errors.check_finite(a, "target light")
    with pytest.raises(errors.NonFiniteError, match="magnitude 1e\\+300 exceeds"):
        errors.check_light(np.full((9, 3), 1e300), "light file x")
    assert errors.check_light(np.ones((9, 3), np.float32), "l").dtype == np.float64


# ------------------------------------------------------------------------------------------ CLIs, in process
def test_relight_validates_before_any_work(tmp_path):
    from difareli.cli.relight import run
    from difareli.data.store import EncodingStore
    from difareli.relight.request import Request

    ckpt = tmp_path / "c.ckpt"
    ckpt.write_bytes(b"x")  # read, it would be refused as "not a readable PyTorch file": the checks come first
    store = EncodingStore.create(tmp_path / "store", {}, ["light"], durable=False).root
    base = [f"checkpoint={ckpt}", f"store={store}", "target.yaw=30"]
    cases = {"video.frames=0": "video.frames=0 is invalid",
             "video.frames=4000": "video.frames=4000 is invalid: must be an integer from 1 to 3600",
             "target.shadow=nan": "target.shadow=nan is invalid: must be a finite number",
             "target.sun=east": "target.sun='east': use one of",
             f"out_dir={ckpt}": "is a file, not a folder",
             "video.fps=0": "video.fps=0 is invalid",
             "video.format=avi": "video.format='avi' is not a video format; use one of",
             f"store={tmp_path}/none": "no encoding store at",
             "record=s1_l0": "record=s1_l0: no such record in the store",
             f"target.light={tmp_path}/none.npy": "target.light=.* does not exist; give the path of an existing file"}
    for override, want in cases.items():
        cfg = compose_train(tmp_path / "run", [*base, override], config_name="relight")
        kind = FileNotFoundError if "target.light" in override else UserError  # a user error either way
        with pytest.raises(kind, match=want.replace("(", r"\(").replace(")", r"\)")):
            Request.from_config(cfg)
    # How it is relit (sampler, runtime, batch size): the request's values too, checked before the checkpoint is read.
    relighter = {"sampler.steps=2.7": r"sampler steps must be an integer >= 1, got 2.7 \(e.g. sampler.steps=50\)",
                 "sampler.name=euler": "unknown sampler 'euler'; choose from ddim",
                 "+sampler.foo=1": "unknown option 'foo' for sampler",
                 "batch_size=0": "batch_size=0 is invalid",
                 "runtime.precision=fp8": "runtime.precision='fp8' is not one of"}
    for override, want in relighter.items():
        cfg = compose_train(tmp_path / "run", [*base, override], config_name="relight")
        with pytest.raises(UserError, match=want):
            run(cfg)
    with pytest.raises(UserError, match="is not a readable PyTorch file"):
        run(compose_train(tmp_path / "run", base, config_name="relight"))


def test_benchmark_limit_and_out_dir_checked_first(tmp_path):
    from difareli.cli.benchmark import run

    f = tmp_path / "afile"
    f.write_text("keep")
    for override, want in {"limit=0": "limit=0 is invalid", "limit=-3": "limit=-3 is invalid",
                           f"out_dir={f}": "is a file",
                           # a word is no boolean: bool("no") would have run with exact lights
                           "oracle_light=no": "oracle_light='no' is invalid",
                           "oracle_shadow=1": "oracle_shadow=1 is invalid",
                           "save_images=off": "save_images='off' is invalid"}.items():
        cfg = compose_train(tmp_path / "run", [f"store={tmp_path}/missing", override], config_name="benchmark")
        with pytest.raises(UserError, match=want):
            run(cfg)  # fails before opening the (missing) store
    assert f.read_text() == "keep"


def test_teacher_pairs_and_a_diffusion_benchmark_check_their_runtime_before_the_checkpoint(tmp_path):
    from difareli.cli.benchmark import run as benchmark
    from difareli.cli.teacher_pairs import run as teacher_pairs

    ckpt = tmp_path / "c.ckpt"
    ckpt.write_bytes(b"x")  # read, it would be refused as "not a readable PyTorch file": the runtime is said first
    for run, name, args in ((teacher_pairs, "teacher_pairs", [f"checkpoint={ckpt}", f"store={tmp_path}/missing"]),
                            (benchmark, "benchmark", [f"store={tmp_path}/missing", "method=diffusion",
                                                      f"method.checkpoint={ckpt}"])):
        cfg = compose_train(tmp_path / "run", [*args, "runtime.precision=fp8"], config_name=name)
        with pytest.raises(UserError, match="runtime.precision='fp8' is not one of"):
            run(cfg)


def test_train_refuses_test_only_store_and_nonfinite_records(synth_store, tmp_path):
    import shutil

    from difareli.lit.datamodule import EncodingsDataModule
    from difareli.data.store import EncodingStore

    root = tmp_path / "store"
    shutil.copytree(synth_store, root)
    store = EncodingStore.open(root)
    for rid in store.ids():  # relabel every record as test
        p = root / "records" / rid / "meta.json"
        p.write_text(p.read_text().replace('"train"', '"test"').replace('"val"', '"test"'))
    dm = EncodingsDataModule(str(root), ["shading"], ["shape", "cam"])
    with pytest.raises(UserError,
                       match=r"has no records in split 'train' \(splits: \['test'\]\).*allow_split_fallback"):
        dm.setup()
    ok = EncodingsDataModule(str(root), ["shading"], ["shape", "cam"], allow_split_fallback=True)
    ok.setup()
    assert len(ok.train_set) + len(ok.val_set) == len(store)
    # one NaN shape value in one training record: named, before any step
    rid = ok.train_set.ids[3]
    shape = np.load(root / "records" / rid / "shape.npy")
    shape[5] = np.nan
    np.save(root / "records" / rid / "shape.npy", shape)
    bad = EncodingsDataModule(str(root), ["shading"], ["shape", "cam"], allow_split_fallback=True)
    with pytest.raises(UserError,
                       match=f"1 training record\\(s\\) .* non-finite \\['shape', 'cam'\\] values: \\['{rid}'\\]"):
        bad.nonspatial_stats()
    with pytest.raises(UserError, match=f"record '{rid}', encoding 'shape' in store {root}: 1 of"):
        bad.train_set[3]


def test_store_cli_verify(synth_store, tmp_path, capsys):
    import shutil

    from difareli.cli.store import main

    assert main(["verify", str(synth_store)]) == 0
    assert "16 record(s), headers and values checked: healthy" in capsys.readouterr().err
    root = tmp_path / "s"
    shutil.copytree(synth_store, root)
    light = root / "records" / "s00001_l1" / "light.npy"
    a = np.load(light)
    a[0, 0] = np.inf
    np.save(light, a)
    assert main(["verify", str(root)]) == 1
    out = capsys.readouterr()
    assert "s00001_l1: " in out.out and "'light'" in out.out and "NaN or Inf" in out.out
    with pytest.raises(SystemExit) as e:
        main(["verify", str(tmp_path / "none")])
    assert e.value.code == 2 and "difareli-store: no encoding store at" in capsys.readouterr().err


def test_a_command_prints_a_warning_as_one_line_named_by_it():
    """Inside a console script a warning is formatted `difareli-<name>: warning: <message>`, not file:line + source
    (pytest records warnings itself, so the format is checked rather than stderr)."""
    import warnings

    from difareli.errors import cli_entry

    @cli_entry("probe")
    def task():
        return warnings.formatwarning("target light 0 is far too bright", RuntimeWarning, "x.py", 3)

    formatwarning = warnings.formatwarning
    try:
        assert task() == "difareli-probe: warning: target light 0 is far too bright\n"
    finally:
        warnings.formatwarning = formatwarning
