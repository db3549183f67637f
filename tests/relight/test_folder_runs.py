"""A folder of photos relit into one out_dir, its edge cases without the estimators (each photo's relight faked):
outputs of same-named photos kept apart, one CSV row per photo, the folder's settings recorded and a rerun with
others refused, links that lead nowhere named, two runs on one folder, another tool's CSV, an out_dir the
photos' listing would read, and a true/false setting read strictly."""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest
from omegaconf import OmegaConf

from difareli.errors import UserError
from difareli.relight import batch, photo
from difareli.relight.request import Request
from difareli.utils.fileio import folder_lock


@pytest.fixture
def fake(monkeypatch):
    """relight_one replaced: a photo named *bad* is skipped, any other comes back as a grey composite."""
    seen = []

    def relight_one(path, **kw):
        seen.append(path)
        if "bad" in path.name:
            raise UserError(f"image={path}: no face detected; use a photo with one clearly visible face")
        return np.full((8, 8, 3), 7, np.uint8), [np.zeros((4, 4, 3), np.uint8)], {"faces": 1, "relit_faces": 1}

    monkeypatch.setattr(batch, "relight_one", relight_one)
    return seen


class StandIn:
    """A relighter as the folder's record sees it: only its identity (relight_one is faked)."""

    def __init__(self, weights: str):
        self.weights = weights

    def identity(self) -> dict:
        return {"checkpoint": self.weights, "precision": "bf16", "sampler": None, "mean_matching": True}


AA = StandIn("weights:aa")


def rows(out):
    with (out / batch.CSV_NAME).open() as f:
        return list(csv.DictReader(f))


def test_same_named_photos_in_three_folders_give_three_output_sets(tmp_path, fake):
    for folder in "xyz":
        (tmp_path / "g" / folder).mkdir(parents=True)
        (tmp_path / "g" / folder / "a.jpg").write_bytes(b"x")
    paths = batch.photo_paths(f"{tmp_path}/g/*/a.jpg")
    assert batch.output_names(paths) == ["x__a", "y__a", "z__a"]
    assert batch.output_names([tmp_path / n for n in ("a.jpg", "a.png", "b.png")]) == ["a", "a_png", "b"]
    out = tmp_path / "out"
    assert batch.relight_photos(paths, out, relighter=AA, progress=False) == {"done": 3, "skipped": 0, "resumed": 0}
    assert sorted(p.name for p in out.glob("*_composite.png")) == ["x__a_composite.png", "y__a_composite.png",
                                                                   "z__a_composite.png"]
    assert [(r["name"], r["photo"]) for r in rows(out)] == [(f"{d}__a", str(p)) for d, p in zip("xyz", paths)]
    assert batch.relight_photos(paths, out, relighter=AA, progress=False) == {"done": 0, "skipped": 0, "resumed": 3}


def test_a_rerun_keeps_one_row_per_photo(tmp_path, fake):
    for name in ("good.png", "bad.png"):
        (tmp_path / name).write_bytes(b"x")
    paths = batch.photo_paths(str(tmp_path))
    out = tmp_path / "out"
    for _ in range(3):  # the skipped photo is tried again each time: its row replaced, not appended
        batch.relight_photos(paths, out, relighter=AA, progress=False)
    assert sorted((r["name"], r["status"]) for r in rows(out)) == [("bad", "skipped"), ("good", "relit")]
    assert fake.count(tmp_path / "bad.png") == 3 and fake.count(tmp_path / "good.png") == 1


def test_a_rerun_with_other_settings_is_refused_naming_the_setting(tmp_path, fake):
    (tmp_path / "p.png").write_bytes(b"x")
    paths, out = batch.photo_paths(str(tmp_path)), tmp_path / "out"
    batch.relight_photos(paths, out, relighter=AA, progress=False, settings={"target.yaw": 45.0})
    with pytest.raises(UserError, match=r"^.*out holds relit photos made with other settings \(target.yaw: 45.0 "
                                        r"there, -90.0 now\); give another output folder"):
        batch.relight_photos(paths, out, relighter=AA, progress=False, settings={"target.yaw": -90.0})
    with pytest.raises(UserError, match=r"other settings \(checkpoint: 'weights:aa' there, 'weights:bb' now\)"):
        batch.relight_photos(paths, out, relighter=StandIn("weights:bb"), progress=False,
                             settings={"target.yaw": 45.0})  # the relighter's identity is recorded with the request's
    assert batch.relight_photos(paths, out, relighter=AA, progress=False,
                                settings={"target.yaw": 45.0})["resumed"] == 1


def test_links_that_lead_nowhere_are_named(tmp_path):
    (tmp_path / "real.png").write_bytes(b"x")
    os.symlink(tmp_path / "gone.png", tmp_path / "dangling.png")
    os.symlink(tmp_path / "loop.png", tmp_path / "loop.png")
    names = [p.name for p in batch.photo_paths(str(tmp_path))]
    assert names == ["dangling.png", "loop.png", "real.png"]
    with pytest.raises(UserError, match=r"dangling.png is a symbolic link to .*gone.png, which does not exist"):
        photo.read_photo(tmp_path / "dangling.png")
    with pytest.raises(UserError, match=r"loop.png is a symbolic link loop; point it at a photo or remove it"):
        photo.read_photo(tmp_path / "loop.png")


def test_two_runs_on_one_folder_and_another_tools_csv_are_refused(tmp_path, fake):
    (tmp_path / "p.png").write_bytes(b"x")
    paths, out = batch.photo_paths(str(tmp_path)), tmp_path / "out"
    with folder_lock(out, "relight"):
        with pytest.raises(UserError, match="is being written by difareli-relight"):
            batch.relight_photos(paths, out, relighter=AA, progress=False)
    assert fake == []
    (out / batch.CSV_NAME).write_text("id,score\n1,0.5\n")
    with pytest.raises(UserError, match=r"relight.csv is not a difareli-relight photo table \(its columns: id, "
                                        r"score\); give another out_dir"):
        batch.relight_photos(paths, out, relighter=AA, progress=False)


def config(**over):
    base = {"store": None, "record": None, "versions": None, "image": None, "face": "largest", "photo_size": None,
            "strict": False, "video": {"axis": None, "frames": 8, "fps": 20, "format": "gif"}, "out_dir": "out",
            "target": {"light": None, "record": None, "yaw": 45, "roll": None, "pitch": None, "envmap": None,
                       "shadow": None, "sun": "shadows"},
            "composite": {"mode": "ratio", "feather": 0.03, "parts": None}, "checkpoint": "x", "sampler": None,
            "runtime": {}, "mean_matching": True, "batch_size": 4, "progress": False}
    return OmegaConf.merge(base, OmegaConf.create(over))


def test_an_out_dir_the_photos_listing_reads_is_refused(tmp_path):
    photos = tmp_path / "photos"
    (photos / "x").mkdir(parents=True)
    (photos / "x" / "a.png").write_bytes(b"x")
    (photos / "b.png").write_bytes(b"x")
    with pytest.raises(UserError, match=r"out_dir=.*photos is where image=.*photos lists its photos"):
        Request.from_config(config(image=str(photos), out_dir=str(photos)))
    with pytest.raises(UserError, match="lists its photos: a rerun would read this run's outputs as photos"):
        Request.from_config(config(image=f"{photos}/*/a.png", out_dir=str(photos / "out")))
    assert Request.from_config(config(image=str(photos), out_dir=str(tmp_path / "out"))).photos
    assert Request.from_config(config(image=f"{photos}/*/a.png", out_dir=str(photos))).photos  # not listed there


@pytest.mark.parametrize("value", ["no", "yes", 1, "false"])
def test_strict_is_a_boolean(tmp_path, value):
    (tmp_path / "p.png").write_bytes(b"x")
    with pytest.raises(UserError, match=f"strict={value!r} is invalid: give strict=true or strict=false"):
        Request.from_config(config(image=str(tmp_path / "p.png"), strict=value))
    assert Request.from_config(config(image=str(tmp_path / "p.png"), strict=False)).strict is False


@pytest.mark.parametrize("face", ["abc", "-1", "1.5", "first"])
def test_a_face_choice_that_is_none_is_refused_before_any_photo(tmp_path, face):
    """Before: accepted, then each photo detected and skipped with a "face=abc: not a face choice" row (exit 2 after
    the estimators' work, a relight.csv written). Issue 64, our probe."""
    (tmp_path / "p.png").write_bytes(b"x")
    out = tmp_path / "out"
    with pytest.raises(UserError) as e:
        Request.from_config(config(image=str(tmp_path / "p.png"), face=face, out_dir=str(out)))
    assert str(e.value) == (f"face={face} is invalid: give face=largest, face=all or face=<index> (0, 1, ...: the "
                            "detected faces left to right)")
    assert not out.exists()
    for good in ("largest", "all", "2", "ALL"):
        assert Request.from_config(config(image=str(tmp_path / "p.png"), face=good, out_dir=str(out))).face == good


def test_a_full_disk_mid_folder_is_one_line_and_the_rerun_resumes(tmp_path, fake, monkeypatch):
    """The disk fills while the second photo's composite is written: one line naming that file (a UserError, exit
    2 through a CLI), no scratch file, the first photo's row kept; a rerun with space relights the second only."""
    import errno

    from difareli.utils import viz

    for folder in "xy":
        (tmp_path / "g" / folder).mkdir(parents=True)
        (tmp_path / "g" / folder / "a.jpg").write_bytes(b"x")
    paths, out = batch.photo_paths(f"{tmp_path}/g/*/a.jpg"), tmp_path / "out"
    real = viz.iio.imwrite

    def full(target, *a, **k):
        if "y__a_composite" in str(target):
            raise OSError(errno.ENOSPC, "No space left on device", str(target))
        return real(target, *a, **k)

    monkeypatch.setattr(viz.iio, "imwrite", full)
    with pytest.raises(UserError) as e:
        batch.relight_photos(paths, out, relighter=AA, progress=False)
    assert str(e.value) == (f"no space left on the device writing {out / 'y__a_composite.png'} (No space left on "
                            "device); free space or write elsewhere (nothing already written was changed)")
    assert [r["name"] for r in rows(out)] == ["x__a"] and not list(out.glob(".*.tmp-*"))
    monkeypatch.setattr(viz.iio, "imwrite", real)
    before = len(fake)
    assert batch.relight_photos(paths, out, relighter=AA, progress=False) == {"done": 1, "skipped": 0, "resumed": 1}
    assert [r["name"] for r in rows(out)] == ["x__a", "y__a"] and fake[before:] == [paths[1]]
