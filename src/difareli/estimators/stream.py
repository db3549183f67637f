"""Photos through a :class:`~.pipeline.Pipeline` in two overlapped stages, in one process.

A reader thread decodes each photo, aligns it (:meth:`Pipeline.prepare`: BlazeFace and FaceMesh) and runs the
estimators that read only the crop (:attr:`Pipeline.image_steps`: the geometry, FaceMesh again, the BFM fit, the
G-buffer), whose graphs only it touches, while this thread runs the others on the photos read before
(:meth:`Pipeline.finish_many`, ``chunk`` at a time, so that the identity network takes them in one batch).
mediapipe's graph runs, torch and OpenCV release the GIL, so on two cores the two stages run side by side (the
split puts about half of the work on each side). Results come back in input order; the reader stays at most one
chunk ahead of the chunk being finished (memory stays bounded: a photo read is 6 MB at 256 px, 25 MB at 512) and
stops when the consumer does.

Which photos share a chunk depends only on the input order, and the identity network's result does not depend on
its batch (``identity.BATCH``): the output is the same whatever the load or the timing.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from .identity import BATCH
from .quiet import native_logs

_END = object()


class _Broken:
    """The items' iterator itself raised: the consumer re-raises ``error``."""

    def __init__(self, error: BaseException):
        self.error = error


def _put(out: queue.Queue, entry, stop: threading.Event) -> bool:
    """Put ``entry`` unless the consumer has stopped; False then."""
    while not stop.is_set():
        try:
            out.put(entry, timeout=0.1)
            return True
        except queue.Full:
            continue
    return False


def _read(pipeline, items: Iterable, load: Callable, out: queue.Queue, stop: threading.Event) -> None:
    """The reader: ``(item, prepared | exception, seconds)`` per item, then ``_END``."""
    front = pipeline.image_steps
    try:
        for item in items:
            t0 = time.perf_counter()
            try:
                rgb, notes = load(item)
                with native_logs():
                    prep = pipeline.run_steps(pipeline.prepare(rgb), front)
                prep.update(load_notes=notes, input_size=list(rgb.shape[:2]))
            except Exception as e:  # noqa: BLE001 - one photo's failure is its own entry
                prep = e
            if not _put(out, (item, prep, time.perf_counter() - t0), stop):
                return
    except BaseException as e:  # noqa: BLE001 - handed to the consumer, which re-raises it
        _put(out, _Broken(e), stop)
        return
    _put(out, _END, stop)


def stream(pipeline, items: Iterable, load: Callable[[Any], tuple[Any, list[str]]], chunk: int = BATCH
           ) -> Iterator[tuple[Any, tuple[dict, dict, dict] | Exception, dict, float]]:
    """``(item, (arrays, meta, ctx) | exception, extra, seconds)`` for every item, in order: ``load(item)`` gives
    ``(rgb, notes)`` (or raises, e.g. :class:`~.loading.BadInput`); ``extra`` holds ``load_notes`` and
    ``input_size`` (empty for a photo that failed to load or align); ``seconds`` is the photo's time in both stages
    (a chunk's estimator time shared equally)."""
    q: queue.Queue = queue.Queue(maxsize=chunk)
    stop = threading.Event()
    reader = threading.Thread(target=_read, args=(pipeline, items, load, q, stop), name="preprocess-reader",
                              daemon=True)
    with pipeline.limits(logs=False):  # one BLAS / torch thread for the whole run; logs are captured per call
        reader.start()
        try:
            done = False
            while not done:
                batch = []
                while len(batch) < chunk:
                    got = q.get()
                    if got is _END:
                        done = True
                        break
                    if isinstance(got, _Broken):
                        raise got.error
                    batch.append(got)
                if batch:
                    yield from _finish(pipeline, batch)
        finally:
            stop.set()
            reader.join(timeout=5)


def _finish(pipeline, batch: list) -> Iterator:
    t0 = time.perf_counter()
    with native_logs():
        results = pipeline.finish_many([prep for _, prep, _ in batch], start=len(pipeline.image_steps))
    share = (time.perf_counter() - t0) / len(batch)
    for (item, prep, seconds), res in zip(batch, results, strict=True):
        extra = {} if isinstance(prep, Exception) else {k: prep[k] for k in ("load_notes", "input_size")}
        yield item, res, extra, seconds + (0.0 if isinstance(prep, Exception) else share)
