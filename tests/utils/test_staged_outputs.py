"""staged_outputs: a command's outputs are published whole or not at all, so a rerun into a finished folder that
fails (a full disk, a kill) leaves the previous run's files as they were, and one that succeeds leaves none of them."""

from __future__ import annotations

import errno

import pytest

from difareli.utils.fileio import NoSpaceError, no_space, staged_outputs, write_text_atomic

NAMES = ("relit.gif", "ground_truth.gif", "summary.json")


def _first_run(out):
    with staged_outputs(out, NAMES, last="summary.json") as stage:
        for n in NAMES:
            (stage / n).write_text(f"first {n}")


def test_a_failed_rerun_leaves_the_previous_outputs_untouched(tmp_path):
    out = tmp_path / "video"
    _first_run(out)
    with pytest.raises(NoSpaceError) as e:  # a full disk: one line naming the output, not its scratch copy
        with staged_outputs(out, NAMES, last="summary.json") as stage:
            (stage / "relit.gif").write_text("second relit")
            raise OSError(errno.ENOSPC, "No space left on device", str(stage / "ground_truth.gif"))
    assert str(e.value) == (f"no space left on the device writing {out / 'ground_truth.gif'} (No space left on "
                            "device); free space or write elsewhere (the previous outputs are kept as they were)")
    assert {p.name: p.read_text() for p in out.iterdir()} == {n: f"first {n}" for n in NAMES}  # no scratch left
    with pytest.raises(NoSpaceError, match=f"writing {out / 'summary.json'} "):  # an atomic writer's, renamed
        with staged_outputs(out, NAMES) as stage:
            write_text_atomic(stage / "summary.json", "x" * 10)
            raise no_space(stage / "summary.json", OSError(errno.ENOSPC, "No space left on device"))
    with pytest.raises(KeyError):  # anything else passes unchanged
        with staged_outputs(out, NAMES):
            raise KeyError("x")
    assert {p.name: p.read_text() for p in out.iterdir()} == {n: f"first {n}" for n in NAMES}


def test_a_successful_rerun_replaces_every_output_of_the_previous_one(tmp_path):
    out = tmp_path / "video"
    _first_run(out)
    (out / "notes.txt").write_text("the user's own file")
    with staged_outputs(out, NAMES, last="summary.json") as stage:
        (stage / "relit.gif").write_text("second relit")
        (stage / "summary.json").write_text("second summary")  # this run renders no ground truth
    got = {p.name: p.read_text() for p in out.iterdir()}
    assert got == {"relit.gif": "second relit", "summary.json": "second summary", "notes.txt": "the user's own file"}
