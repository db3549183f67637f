"""Pictures that label themselves: a header row of column names, row names, per-cell captions."""

from __future__ import annotations

import numpy as np

from difareli.utils import viz


def _cells(n_rows: int, n_cols: int, size: int = 64) -> list[list[np.ndarray]]:
    rng = np.random.default_rng(0)
    return [[rng.integers(60, 200, (size, size, 3), dtype=np.uint8) for _ in range(n_cols)] for _ in range(n_rows)]


def _inked(region: np.ndarray, fill: int = 255) -> int:
    return int((np.abs(region.astype(int) - fill).sum(-1) > 0).sum())


def test_column_labels_add_a_header_row_with_text_over_each_column():
    rows = _cells(2, 3)
    plain = viz.grid(rows)
    labelled = viz.grid(rows, col_labels=["input", "relit", "ground truth"])
    head = labelled.shape[0] - plain.shape[0]
    size = viz.label_size(64)
    assert head == size + 2 * 2 + 4 and labelled.shape[1] == plain.shape[1]
    np.testing.assert_array_equal(labelled[head:], plain)  # the images themselves untouched, only moved down
    # Text is drawn in the header over every column (each column's span of the header has dark pixels).
    for j in range(3):
        x0 = 2 + j * (64 + 2)
        assert _inked(labelled[:head, x0:x0 + 64]) > 20, j
    assert _inked(labelled[:head, :2]) == 0  # nothing in the left margin


def test_row_labels_add_a_band_at_the_left_and_long_names_shrink_to_the_cell():
    rows = _cells(2, 2, size=32)
    plain = viz.grid(rows)
    labelled = viz.grid(rows, row_labels=["s0001", "s0002"], col_labels=["input", "ground truth (target light)"])
    band = labelled.shape[1] - plain.shape[1]
    assert band > 0 and labelled.shape[0] > plain.shape[0]
    head = labelled.shape[0] - plain.shape[0]
    assert _inked(labelled[head:, :band]) > 20  # the row names
    assert viz.fitted_size("ground truth (target light)", 12, 32) < 12  # shrunk to fit the 32 px column


def test_cell_captions_name_each_frame():
    frames = _cells(1, 3)
    plain = viz.grid(frames)
    sheet = viz.grid(frames, cell_labels=[["yaw 0°", "yaw 120°", "yaw 240°"]])
    band = sheet.shape[0] - plain.shape[0]
    assert band == viz.label_size(64) + 4
    for j in range(3):
        x0 = 2 + j * (64 + 2)
        assert _inked(sheet[2:2 + band, x0:x0 + 64]) > 10, j
    # Different captions draw different pixels: the text is really the label, not a fixed mark.
    other = viz.grid(frames, cell_labels=[["yaw 0°", "yaw 0°", "yaw 240°"]])
    assert not np.array_equal(sheet[:band + 2, 68:132], other[:band + 2, 68:132])
