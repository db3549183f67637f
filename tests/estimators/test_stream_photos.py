"""difareli-preprocess's overlapped, batched run writes what the photo-by-photo run writes, on scikit-image's
astronaut and cameraman and their mirror images (all encodings, default estimators, 256 px):

- every encoding but ``identity`` bit for bit (the same computations, in another thread);
- ``identity`` within 1e-6 (measured: 2.7e-7): the network runs on 8 chips at once, and oneDNN's kernels for a
  batch sum in another order than for one chip. A descriptor does not depend on which photos share its batch.

Needs the photo estimators and dlib's models (skipped without them)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from tests.helpers import HAS_DLIB_MODELS, HAS_ESTIMATORS, NO_ESTIMATORS

if not (HAS_ESTIMATORS and HAS_DLIB_MODELS):
    pytest.skip(NO_ESTIMATORS, allow_module_level=True)

from difareli.data.store import EncodingStore  # noqa: E402
from difareli.estimators.batch import run  # noqa: E402
from difareli.estimators.pipeline import Pipeline, default_estimators  # noqa: E402

IDENTITY_ATOL = 1e-6


def _photos(folder):
    import skimage.data

    folder.mkdir()
    camera = np.repeat(skimage.data.camera()[..., None], 3, axis=-1)
    for name, img in (("astronaut", skimage.data.astronaut()), ("camera", camera)):
        Image.fromarray(img).save(folder / f"{name}.png")
        Image.fromarray(np.ascontiguousarray(img[:, ::-1])).save(folder / f"{name}_mirror.png")
    Image.fromarray(np.full((128, 128, 3), 90, np.uint8)).save(folder / "blank.png")  # no face: fails alone
    (folder / "notes.txt").write_text("not a photo")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stream")
    _photos(tmp / "in")
    pipe = Pipeline.from_config(default_estimators(256))
    out = {}
    for overlap in (False, True):
        dst = tmp / f"overlap_{overlap}"
        summary = run(pipe, str(tmp / "in"), str(dst), previews=overlap, progress=False, overlap=overlap)
        out[overlap] = (summary, EncodingStore.open(dst), json.loads((dst / "preprocess_report.json").read_text()))
    return pipe, out


def test_overlapped_run_writes_the_photo_by_photo_records(runs):
    _, out = runs
    (one, a, rep_a), (two, b, rep_b) = out[False], out[True]
    assert (one.written, one.failed) == (two.written, two.failed) == (4, 2)
    assert a.ids() == b.ids() == ["astronaut", "astronaut_mirror", "camera", "camera_mirror"]
    for rid in a.ids():
        ra, rb = a.read(rid), b.read(rid)
        assert set(ra) == set(rb)
        for name in ra:
            if name == "identity":
                np.testing.assert_allclose(rb[name], ra[name], rtol=0, atol=IDENTITY_ATOL, err_msg=rid)
            else:
                np.testing.assert_array_equal(rb[name], ra[name], err_msg=f"{rid}/{name}")
    strip = lambda rep: [{k: v for k, v in e.items() if k != "seconds"} for e in rep["images"]]  # noqa: E731
    assert strip(rep_a) == strip(rep_b)  # the same entries, reasons and notes, in the same order
    assert [e["status"] for e in rep_b["images"]] == ["ok", "ok", "failed", "ok", "ok", "failed"]
    assert set(two.stage_ms()) == set(one.stage_ms()) and all(v > 0 for v in two.stage_ms().values())


def test_a_descriptor_does_not_depend_on_its_batch(runs):
    pipe, _ = runs
    import skimage.data

    ident = next(e for e in pipe.steps if type(e).__name__ == "DlibIdentity")
    astronaut = skimage.data.astronaut()
    with pipe.limits():
        ctxs = [pipe.finish(pipe.prepare(img))[2] for img in (astronaut, np.ascontiguousarray(astronaut[:, ::-1]))]
        alone = ident.batch(ctxs[:1], pipe.needed)[0]["identity"]
        pair = ident.batch(ctxs[::-1], pipe.needed)[1]["identity"]  # second place, beside its mirror image
        nine = ident.batch(ctxs[1:] * 8 + ctxs[:1], pipe.needed)[8]["identity"]  # alone in the second group
        single = ident(ctxs[0], pipe.needed)["identity"]
    np.testing.assert_array_equal(pair, alone)
    np.testing.assert_array_equal(nine, alone)
    np.testing.assert_allclose(single, alone, rtol=0, atol=IDENTITY_ATOL)


def test_a_record_that_fails_to_write_in_the_writer_thread_is_a_failed_entry(runs, tmp_path, monkeypatch):
    pipe, _ = runs
    _photos(tmp_path / "in")
    real = EncodingStore.write

    def write(self, rid, *args, **kwargs):
        if rid == "camera":
            raise OSError("disk says no")
        return real(self, rid, *args, **kwargs)

    monkeypatch.setattr(EncodingStore, "write", write)
    summary = run(pipe, str(tmp_path / "in"), str(tmp_path / "out"), previews=True, progress=False)
    by_id = {e["id"]: e for e in summary.entries}
    assert (summary.written, summary.failed) == (3, 3)
    assert by_id["camera"]["status"] == "failed"
    assert "internal error: OSError: disk says no" in by_id["camera"]["reason"]
    assert EncodingStore.open(tmp_path / "out").ids() == ["astronaut", "astronaut_mirror", "camera_mirror"]
