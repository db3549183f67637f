"""A photo batch's inputs and names, without the estimators: the photos of a folder or glob, each photo's output
name, and a rerun that finds everything relit before."""

import csv
from types import SimpleNamespace

import numpy as np
import pytest
import imageio.v3 as iio

from difareli.errors import UserError
from difareli.relight import batch, photo


def test_photo_paths_folder_glob_and_one_file(tmp_path):
    for name in ("b.png", "a.jpg", "a.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in batch.photo_paths(tmp_path)] == ["a.jpg", "a.png", "b.png"]
    assert [p.name for p in batch.photo_paths(f"{tmp_path}/a.*")] == ["a.jpg", "a.png"]
    assert batch.photo_paths(tmp_path / "a.jpg") is None  # one photo
    with pytest.raises(UserError, match=r"image=.*\*.gif: no photos there"):
        batch.photo_paths(f"{tmp_path}/*.gif")


def test_output_names_keep_two_photos_of_one_name_apart(tmp_path):
    paths = [tmp_path / n for n in ("a.jpg", "a.png", "b.png", "sub.a.png")]
    assert batch.output_names(paths) == ["a", "a_png", "b", "sub.a"]


def test_a_rerun_over_photos_all_relit_relights_none(tmp_path):
    paths = [tmp_path / n for n in ("a.jpg", "a.png")]
    out = tmp_path / "out"
    out.mkdir()
    with (out / batch.CSV_NAME).open("w", newline="") as f:
        w = csv.DictWriter(f, batch.FIELDS)
        w.writeheader()
        for p, name in zip(paths, ("a", "a_png")):
            w.writerow({"name": name, "photo": str(p), "status": "relit"})
    for stem in ("a", "a_png"):
        iio.imwrite(out / f"{stem}_composite.png", np.zeros((4, 4, 3), np.uint8))
    # No relighter is needed: nothing is left to relight.
    assert batch.relight_photos(paths, out, progress=False, relighter=None) == {"done": 0, "skipped": 0,
                                                                               "resumed": 2}
    (out / "a_png_composite.png").unlink()  # its row says relit, its file is gone: it is done again (and, the
    # photo itself missing, skipped with a row saying why: reading it is the relighter's sources' first step)
    reads = SimpleNamespace(photo_faces=lambda path, **kw: photo.read_photo(path))
    again = batch.relight_photos(paths, out, progress=False, relighter=reads, target=None, size=None, face=None,
                                 composite={})
    assert again == {"done": 0, "skipped": 1, "resumed": 1}
    with (out / batch.CSV_NAME).open() as f:
        last = list(csv.DictReader(f))[-1]
    assert last["photo"] == str(paths[1]) and last["status"] == "skipped" and last["reason"]
