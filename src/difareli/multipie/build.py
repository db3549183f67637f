"""A user's Multi-PIE copy -> an encodings store plus ``protocols.json`` that difareli-benchmark runs on unchanged.

:func:`build` finds the frontal images of the listed pairs (the authors' JSON lists) or of every neutral
recording, preprocesses the images the pairs use (or all found, ``images="all"``) with the photo estimators of
difareli-preprocess, and writes the pairs whose three images all made it. An image that is missing, unreadable
or in which the estimators find no face is named in one line and skipped; the pairs it belongs to are dropped
and counted. A rerun into the same store resumes (records that exist are kept); the store records the copy it
was built from (``multipie_root`` in its header), and a rerun from another copy is refused (:func:`check_root`),
since its kept records would silently mix the two copies.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

from difareli.errors import UserError
from difareli.multipie import layout, protocols
from difareli.multipie.layout import Image
from difareli.data.store import EncodingStore
from difareli.data.protocols import PROTOCOLS_FILE
from difareli.utils.fileio import write_json_atomic
from difareli.estimators.loading import BadInput, load_image

REPORT = "multipie_report.json"
#: why an image was skipped -> the word used in its line and in the counts
KINDS = ("missing", "unreadable", "no face", "failed")


@dataclass
class BuildReport:
    """What :func:`build` did: records written/kept, skipped images (kind, path, reason), pairs kept/dropped."""

    store: Path
    written: int = 0
    kept: int = 0
    skipped: list[tuple[str, str, str]] = field(default_factory=list)
    pairs: dict[str, int] = field(default_factory=dict)
    dropped: int = 0
    seconds: float = 0.0
    how: str = ""

    def lines(self) -> list[str]:
        """One line per skipped image: ``skipped <path>: <kind> (<reason>)``."""
        return [f"skipped {path}: {kind}" + (f" ({why})" if why else "") for kind, path, why in self.skipped]

    def summary(self) -> str:
        counts = {k: sum(1 for s in self.skipped if s[0] == k) for k in KINDS}
        skipped = ", ".join(f"{v} {k}" for k, v in counts.items() if v) or "none"
        total = self.written + self.kept + len(self.skipped)
        pairs = ", ".join(f"{k} {v}" for k, v in self.pairs.items())
        return (f"{self.written} image(s) preprocessed, {self.kept} kept from an earlier run, {len(self.skipped)} of "
                f"{total} skipped ({skipped}); pairs: {pairs}, {self.dropped} dropped (an image skipped); "
                f"{self.how}; store: {self.store}")


def _kind(reason: str) -> str:
    r = reason.lower()
    if r.startswith("unreadable") or r.startswith("not an image") or "too small" in r or "too large" in r:
        return "unreadable"
    return "no face" if ("no face" in r or "no landmarks" in r) else "failed"


def _process(pipeline, store: EncodingStore, img: Image, path: Path) -> tuple[str, str] | None:
    """Preprocess one image into ``store``; ``(kind, reason)`` when it is skipped."""
    try:
        rgb, notes = load_image(path, pipeline.min_side, pipeline.max_side)
        arrays, meta, ctx = pipeline.process(rgb)
    except BadInput as e:
        return _kind(str(e)), str(e)
    except Exception as e:  # noqa: BLE001 - an estimator bug must not stop the other images
        return "failed", f"internal error: {type(e).__name__}: {e}"
    meta.update(source_file=str(path), input_size=list(rgb.shape[:2]), notes=notes + ctx.get("notes", []),
                split="test", subject=img.subject, session=img.session, recording=img.recording,
                illumination=img.illumination, dataset="multipie")
    store.write(img.stem, arrays, meta)
    return None


def check_root(out_dir: str | Path, data: Path) -> None:
    """Refuse to resume the store at ``out_dir`` from another Multi-PIE copy than the one it was built from (its
    records would be kept while the report names the new copy)."""
    header = Path(out_dir) / "store.json"
    if not header.is_file():
        return
    try:
        meta = (json.loads(header.read_text()).get("meta") or {})
    except (OSError, ValueError):
        return  # not a readable store: EncodingStore.create says so
    was = meta.get("multipie_root")
    now = os.path.realpath(data)
    if was != now:
        first = f"was built from the Multi-PIE copy at {was}" if was else "records no Multi-PIE copy it was built from"
        raise UserError(f"out_dir={out_dir} {first}, not root={now}: a rerun would keep its records; give a new "
                        f"out_dir, or delete {out_dir} to rebuild it from {now}")


def _check_found(root, data: Path, found: list, recordings: list[str], asked: list[str] | None) -> None:
    """Something to build: an image of the recordings, and (``asked``) of every illumination asked for; else one
    line saying what the copy holds instead."""
    have = sorted({i.illumination for i, _ in found})
    absent = [i for i in asked or () if i not in have]
    if found and not absent:
        return
    held = layout.illuminations_in(data, recordings)
    holds = f"its recording folders hold illumination(s) {', '.join(held)}" if held else "no image in them"
    if not found and not held:
        raise UserError(f"root={root}: no frontal image of recording(s) {', '.join(recordings)} found under {data}; "
                        f"expected {layout.EXPECTED}")
    raise UserError(f"illuminations={[int(i) for i in asked or ()]}: illumination(s) {', '.join(absent)} are in "
                    f"none of the copy's recording folders ({holds}); give illuminations the copy has, or "
                    "illuminations=null for all of them")


def build(root: str | Path, out_dir: str | Path, pipeline, pairs: Sequence[str | Path] | None = None, *,
          seed: int = 0, same_subject: int = 862, different_subject: int = 200,
          recordings: Iterable[str] = (layout.NEUTRAL_RECORDING,), illuminations: Iterable[str] | None = None,
          images: str = "used", progress: bool = True, log: Callable[[str], None] | None = None) -> BuildReport:
    """Build the store at ``out_dir`` (see the module docstring); ``pipeline`` is a
    :class:`difareli.estimators.pipeline.Pipeline` (or anything with its ``process``/``dims``/``encodings``).
    ``illuminations``: None, every one (those the copy lacks are named as missing images); given, each must be in
    the copy's recording folders."""
    from tqdm.auto import tqdm

    if images not in ("used", "all"):
        raise UserError(f"images={images!r} is not 'used' (the images the pairs use) or 'all' (every image found)")
    data = layout.data_dir(root)
    check_root(out_dir, data)
    asked = illuminations is not None
    recordings = layout.codes(recordings, "recordings", layout.RECORDINGS)
    illuminations = layout.codes(layout.ILLUMINATIONS if illuminations is None else illuminations, "illuminations",
                                 layout.ILLUMINATIONS)
    report = BuildReport(Path(out_dir))
    if pairs:
        triples = protocols.read_lists(pairs)
        wanted = sorted({i for t in triples for i in t.images})
        found = []
        for img in wanted:
            p = img.path(data)
            (found.append((img, p)) if p.is_file() else report.skipped.append(("missing", str(p), "")))
        report.how = "pairs from " + ", ".join(Path(p).name for p in pairs)
    else:
        found, missing = layout.scan(data, recordings, illuminations)
        report.skipped += [("missing", line.split(": ", 1)[1], "") for line in missing]
        _check_found(root, data, found, recordings, illuminations if asked else None)
        triples = protocols.draw([i for i, _ in found], seed, same_subject, different_subject)
        report.how = f"pairs drawn from seed {seed} (difareli.multipie.protocols.draw)"
        if images == "used":
            used = {i for t in triples for i in t.images}
            found = [(i, p) for i, p in found if i in used]
    log = log or (lambda line: None)
    for line in report.lines():  # the missing ones, before the long part
        log(line)
    store = EncodingStore.create(out_dir, pipeline.dims(), pipeline.encodings,
                                 {"source": "difareli-multipie", "dataset": "multipie", "size": int(pipeline.size),
                                  "gamma": "none", "multipie_root": os.path.realpath(data)}, durable=False)
    t0 = time.perf_counter()
    bad: set[Image] = {Image.parse(Path(p).name) for k, p, _ in report.skipped}
    for img, path in tqdm(found, desc="multipie", unit="img", disable=not progress):
        if store.has(img.stem):
            report.kept += 1
            continue
        problem = _process(pipeline, store, img, path)
        if problem is None:
            report.written += 1
        else:
            report.skipped.append((problem[0], str(path), problem[1]))
            bad.add(img)
            log(report.lines()[-1])
    report.seconds = time.perf_counter() - t0
    usable = [t for t in triples if not bad.intersection(t.images)]
    report.dropped = len(triples) - len(usable)
    doc = protocols.protocols_doc(usable, report.how)
    report.pairs = {p: len(doc[p]) for p in protocols.PROTOCOLS}
    if not usable:
        raise UserError(f"no usable pair: all {len(triples)} pair(s) lost an image ({len(report.skipped)} skipped, "
                        f"e.g. {report.lines()[0] if report.skipped else 'none'}); check root={root}")
    write_json_atomic(Path(out_dir) / PROTOCOLS_FILE, doc, indent=1)
    write_json_atomic(Path(out_dir) / REPORT, {
        "root": str(root), "data": str(data), "how": report.how, "written": report.written, "kept": report.kept,
        "pairs": report.pairs, "dropped_pairs": report.dropped, "seconds": round(report.seconds, 3),
        "skipped": [dict(zip(("kind", "path", "reason"), s)) for s in report.skipped]}, indent=1)
    return report

