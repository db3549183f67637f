"""The overlapped run (estimators.stream): results in input order, a bad photo failing alone, the image-only steps in
the reader thread, the rest in chunks through ``batch``, the reader stopping with its consumer; and the native-log
capture shared by threads (fd 2 restored after overlapping captures)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from difareli.estimators.loading import BadInput
from difareli.estimators.pipeline import Pipeline
from difareli.estimators.stream import stream


class _Crop:
    """An aligner: the top-left 8 x 8 pixels; a photo whose first pixel is 255 has no face."""

    size = 8

    def __call__(self, rgb):
        if rgb[0, 0, 0] == 255:
            raise BadInput("no face detected")
        return {"image": rgb[:8, :8], "quad": np.array([[0, 0], [0, 8], [8, 8], [8, 0]], float), "faces": 1,
                "box": [0, 0, 8, 8], "notes": []}


class _Geometry:
    """An image-only step: ``shape`` = the crop's mean, and the thread it ran in."""

    provides = ("shape",)
    requires = ("image",)

    def __init__(self):
        self.threads = set()

    def __call__(self, ctx, needed):
        self.threads.add(threading.current_thread().name)
        return {"shape": np.full(53, ctx["image"].mean(), np.float32)}


class _Identity:
    """A batched step: ``identity`` from ``shape``; records its batch sizes and torch's thread count; a photo whose
    crop's second pixel is 7 fails here."""

    provides = ("identity",)
    requires = ("image", "shape")

    def __init__(self):
        self.sizes, self.torch_threads = [], set()

    def __call__(self, ctx, needed):  # pragma: no cover - the stream always takes the batch
        raise AssertionError("the stream calls batch()")

    def batch(self, ctxs, needed):
        self.sizes.append(len(ctxs))
        self.torch_threads.add(torch.get_num_threads())
        return [BadInput("no identity") if c["image"][0, 1, 0] == 7 else {"identity": np.full(128, c["shape"][0])}
                for c in ctxs]


def _photo(i: int, bad_face: bool = False, bad_identity: bool = False) -> np.ndarray:
    rgb = np.full((16, 16, 3), i, np.uint8)
    rgb[0, 0] = 255 if bad_face else 0
    rgb[0, 1] = 7 if bad_identity else 0
    return rgb


def test_stream_keeps_order_batches_and_isolates_failures():
    geo, ident = _Geometry(), _Identity()
    pipe = Pipeline(_Crop(), [geo, ident], ["shape", "identity"])
    assert pipe.image_steps == [geo]
    photos = {i: _photo(i, bad_face=i == 3, bad_identity=i == 6) for i in range(11)}
    loaded = []

    def load(i):
        loaded.append(i)
        if i == 9:
            raise BadInput("unreadable image")
        return photos[i], [f"note {i}"]

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        got = list(stream(pipe, range(11), load, chunk=4))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert [g[0] for g in got] == list(range(11)) and loaded == list(range(11))
    for i, res, extra, seconds in got:
        if i in (3, 6, 9):
            assert isinstance(res, BadInput), i
            continue
        arrays, meta, ctx = res
        assert arrays["identity"][0] == arrays["shape"][0] == photos[i][:8, :8].mean()
        assert extra == {"load_notes": [f"note {i}"], "input_size": [16, 16]} and seconds > 0
        assert list(meta["seconds"]) == ["align", "_Geometry", "_Identity"]
    assert "no face" in str(got[3][1]) and "no identity" in str(got[6][1]) and "unreadable" in str(got[9][1])
    assert geo.threads == {"preprocess-reader"}  # the image-only step ran beside the batched one
    # Chunks of 4 photos in input order; the ones that failed before (3, 9) are not passed to batch().
    assert ident.sizes == [3, 4, 2] and ident.torch_threads == {1}


def test_the_reader_stops_with_its_consumer():
    pipe = Pipeline(_Crop(), [_Geometry(), _Identity()], ["shape", "identity"])
    loaded = []

    def load(i):
        loaded.append(i)
        return _photo(i % 200), []

    it = stream(pipe, range(10_000), load, chunk=2)
    assert next(it)[0] == 0
    it.close()  # the consumer stops: the reader ends, at most a queue's worth ahead
    time.sleep(0.3)
    assert not [t for t in threading.enumerate() if t.name == "preprocess-reader"]
    assert len(loaded) < 20


def test_a_failing_item_iterator_reaches_the_consumer():
    pipe = Pipeline(_Crop(), [_Geometry(), _Identity()], ["shape", "identity"])

    def items():
        yield 0
        raise OSError("folder gone")

    with pytest.raises(OSError, match="folder gone"):
        list(stream(pipe, items(), lambda i: (_photo(i), [])))


CAPTURE = r"""
import os, threading
from difareli.estimators.quiet import native_logs
inside, main_done = threading.Event(), threading.Event()
def reader():
    with native_logs():
        inside.set()
        os.write(2, b"INFO: Created TensorFlow Lite XNNPACK delegate for CPU.\nfrom the reader\n")
        main_done.wait()
with native_logs():  # entered first, left first: the order in which separate captures lost fd 2
    t = threading.Thread(target=reader)
    t.start()
    inside.wait()
    os.write(2, b"from the estimators\n")
main_done.set()
t.join()
os.write(2, b"after both\n")
"""


def test_native_log_captures_of_two_threads_share_fd2_and_give_it_back():
    """Two threads inside native_logs at once (the reader and the estimators): their lines come back, the noise
    does not, and fd 2 is the terminal again after both (each restoring its own saved descriptor lost it)."""
    res = subprocess.run([sys.executable, "-c", CAPTURE], capture_output=True, text=True, timeout=120, check=True)
    lines = res.stderr.splitlines()
    assert sorted(lines[:2]) == ["from the estimators", "from the reader"] and lines[2:] == ["after both"], lines
