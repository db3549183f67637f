"""CSV row logs (utils.fileio.append_csv_row / read_csv_rows): the resumable rows of a photo batch, the benchmark's
partial scores and the photo-check calibration."""

from __future__ import annotations

import csv
import errno
import os

import pytest

from difareli.errors import UserError
from difareli.utils import fileio

FIELDS = ("photo", "status", "seconds")


def test_rows_round_trip_with_one_header_and_the_last_row_winning(tmp_path):
    path = tmp_path / "log" / "rows.csv"  # a folder not there yet is made
    fileio.append_csv_row(path, FIELDS, {"photo": "a.png", "status": "skipped", "seconds": 0.5, "other": "x"})
    fileio.append_csv_row(path, FIELDS, {"photo": "b, c.png", "status": "relit"})  # a comma is quoted
    fileio.append_csv_row(path, FIELDS, {"photo": "a.png", "status": "relit", "seconds": 2})
    lines = path.read_text().splitlines()
    assert lines[0] == "photo,status,seconds" and len(lines) == 4  # the header once, keys outside FIELDS dropped
    with path.open(newline="") as f:
        assert [r["photo"] for r in csv.DictReader(f)] == ["a.png", "b, c.png", "a.png"]
    rows = fileio.read_csv_rows(path, "photo")
    assert rows == {"a.png": {"photo": "a.png", "status": "relit", "seconds": "2"},
                    "b, c.png": {"photo": "b, c.png", "status": "relit", "seconds": ""}}
    assert fileio.read_csv_rows(tmp_path / "none.csv", "photo") == {}


def test_an_empty_file_gets_its_header(tmp_path):
    path = tmp_path / "rows.csv"
    path.write_text("")  # a run killed after creating its log, before its first row
    fileio.append_csv_row(path, FIELDS, {"photo": "a.png", "status": "relit", "seconds": 1})
    assert path.read_text().splitlines() == ["photo,status,seconds", "a.png,relit,1"]


def test_a_full_disk_leaves_the_rows_before_it_whole(tmp_path, monkeypatch):
    path = tmp_path / "rows.csv"
    fileio.append_csv_row(path, FIELDS, {"photo": "a.png", "status": "relit", "seconds": 1})
    before = path.read_bytes()
    real_write = os.write

    def two_bytes_then_full(fd, data):  # a row begun, then the disk is full
        if fd != 1 and fd != 2 and len(data) > 2:
            real_write(fd, bytes(data[:2]))
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", two_bytes_then_full)
    with pytest.raises(UserError, match=str(path)):
        fileio.append_csv_row(path, FIELDS, {"photo": "b.png", "status": "relit", "seconds": 2})
    monkeypatch.undo()
    assert path.read_bytes() == before  # the begun row truncated back: no half row for a resume to misread
