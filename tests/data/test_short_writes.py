"""numpy writes on a full disk: ENOSPC, and the short write numpy reports without an errno, both end in the one-line
no-space message naming the file, and the file or record written before stays as it was."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest

from difareli.data import derived
from difareli.data.store import EncodingStore
from difareli.errors import UserError, user_message
from difareli.utils.fileio import RESUME, is_no_space, save_npy_atomic

from tests.data.test_store import DIMS, NAMES, record
from tests.helpers import failing_save


def numpy_short_write() -> OSError:
    """The exception numpy itself raises when the disk fills mid-array (``tofile`` onto /dev/full)."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full here to make numpy's own short-write error")
    with open("/dev/full", "wb") as f:
        try:
            np.zeros(3072, np.float32).tofile(f)
        except OSError as e:
            return e
    raise AssertionError("writing to /dev/full succeeded")


def full_disk(kind: str) -> OSError:
    return OSError(errno.ENOSPC, "No space left on device") if kind == "enospc" else numpy_short_write()


def reason(kind: str) -> str:
    return "No space left on device" if kind == "enospc" else "short write: 3072 requested and 0 written"


def test_numpy_short_write_is_a_full_disk():
    err = numpy_short_write()
    assert err.errno is None and str(err) == "3072 requested and 0 written"  # numpy counts items, not bytes; no errno
    assert is_no_space(err)
    assert user_message(err) == ("no space left on the device (short write: 3072 requested and 0 written); free "
                                 "space or give another output folder (files and records already complete are kept)")
    other = OSError("3072 requested")  # another errno-less OSError is not taken for a full disk
    assert not is_no_space(other) and user_message(other) is None


@pytest.mark.parametrize("kind", ["enospc", "short"])
def test_store_record_overwrite_on_a_full_disk_keeps_the_previous_record(tmp_path, rng, monkeypatch, kind):
    st = EncodingStore.create(tmp_path / "s", DIMS, NAMES, durable=False)
    old, new = record(rng), record(rng)
    st.write("r0", old)
    before = {p.name: p.read_bytes() for p in (st.records_dir / "r0").iterdir()}
    failing_save(monkeypatch, full_disk(kind), at=3)  # the third encoding: two already in the scratch folder
    with pytest.raises(UserError) as e:
        st.write("r0", new, overwrite=True)
    monkeypatch.undo()
    assert str(e.value) == (f"no space left on the device writing {st.records_dir / 'r0' / NAMES[2]}.npy "
                            f"({reason(kind)}); {RESUME}")
    assert {p.name: p.read_bytes() for p in (st.records_dir / "r0").iterdir()} == before
    assert sorted(os.listdir(st.records_dir)) == ["r0"]  # no scratch folder left
    np.testing.assert_array_equal(st.read("r0", ["shape"])["shape"], old["shape"])


@pytest.mark.parametrize("kind", ["enospc", "short"])
def test_atomic_npy_on_a_full_disk_keeps_the_previous_file(tmp_path, monkeypatch, kind):
    path = tmp_path / "shadow_map@v1.npy"
    save_npy_atomic(path, np.arange(6, dtype=np.float32))
    before = path.read_bytes()
    failing_save(monkeypatch, full_disk(kind))
    with pytest.raises(UserError) as e:
        save_npy_atomic(path, np.ones(6, np.float32))
    monkeypatch.undo()
    assert str(e.value) == (f"no space left on the device writing {path} ({reason(kind)}); free space or write "
                            "elsewhere (nothing already written was changed)")
    assert path.read_bytes() == before and os.listdir(tmp_path) == [path.name]  # scratch file removed


def test_derived_map_on_a_full_disk_keeps_the_previous_version(tmp_path, rng, monkeypatch):
    st = EncodingStore.create(tmp_path / "s", DIMS, NAMES, durable=False)
    st.write("r0", record(rng))
    derived.declare(st, "shading", "v1", {"method": "test"})
    first = rng.random((DIMS["H"], DIMS["W"], 3)).astype(np.float32)
    derived.write(st, "r0", "shading@v1", first)
    failing_save(monkeypatch, numpy_short_write())
    with pytest.raises(UserError, match=r"^no space left on the device writing .*shading@v1\.npy \(short write: "):
        derived.write(st, "r0", "shading@v1", first + 1, overwrite=True)
    monkeypatch.undo()
    np.testing.assert_array_equal(np.load(derived.path_of(st, "r0", "shading@v1")), first)
