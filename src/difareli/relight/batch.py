"""Photos in one command: ``difareli-relight image=<folder or glob>`` and ``face=all|<index>``.

:func:`relight_photos` relights every photo of :func:`photo_paths` under one target, every chosen face composited
into the photo, and writes ``<name>_composite.png``, ``<name>_relit.png`` (the crops side by side) and its row of
``relight.csv`` (one per :func:`output_names` name, its latest; a photo that cannot be relit: a ``skipped`` row and
one line on stderr). The folder is locked while a run writes it and its :data:`SETTINGS` recorded: a rerun with
others is refused, one with the same resumes (files written atomically, the row last), trying skipped photos again."""

from __future__ import annotations

import contextlib
import csv
import glob
import hashlib
import io
import os
import re
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from difareli.data import provenance
from difareli.errors import UserError, check_choice, check_number
from difareli.estimators.loading import IMAGE_SUFFIXES
from difareli.relight import photo_check
from difareli.relight.composite import MODES, part_mask
from difareli.relight.relighter import Relighter
from difareli.relight.sources import Source
from difareli.relight.targets import Targets
from difareli.utils import fileio, viz

CSV_NAME = "relight.csv"
#: What relit a folder's photos (provenance.ensure): a rerun into it must match.
SETTINGS = "relight_settings.json"
FIELDS = ("name", "photo", "status", "seconds", "faces", "relit_faces", "verdict", *photo_check.LIMITS, "reason")


def photo_paths(value: str) -> list[Path] | None:
    """The photos of a folder (its image files, sorted) or of a glob pattern; None for one file."""
    p = Path(str(value))
    if p.is_dir():
        found = sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES and _entry(q))
    elif any(c in str(value) for c in "*?["):
        found = sorted(Path(q) for q in glob.glob(str(value)) if _entry(Path(q)))
    else:
        return None
    if not found:
        raise UserError(f"image={value}: no photos there ({', '.join(IMAGE_SUFFIXES)}); give a folder of face "
                        "photos, a glob such as 'photos/*.jpg', or one photo")
    return found


def _entry(path: Path) -> bool:
    # A link that leads nowhere is a photo the user meant: kept, so that reading it names what is wrong.
    return path.is_file() or (path.is_symlink() and not path.is_dir())


def check_out_dir_apart(image: str, out_dir: str | Path) -> None:
    """An ``out_dir`` where the photos ``image=`` names are listed (the folder itself, or a folder a glob's
    wildcards reach) is refused: the next run would read its outputs as photos."""
    text = str(image)
    wild = re.search(r"[*?[]", text)
    if Path(text).is_dir():
        root, depth = Path(text), 1
    elif wild:
        root = Path(os.path.dirname(text[:wild.start()]) or ".")
        depth = len(Path(os.path.relpath(text, root)).parts)
    else:
        return
    rel = os.path.relpath(Path(out_dir).resolve(), root.resolve())
    if not rel.startswith("..") and depth == len(Path(rel).parts) + 1:
        raise UserError(f"out_dir={out_dir} is where image={image} lists its photos: a rerun would read this run's "
                        "outputs as photos; give an out_dir outside them")


def check_photos(image: str, face: Any, axis: str | None, record: str | None, composite: Mapping[str, Any],
                 out_dir: str) -> tuple[Path, ...] | None:
    """The photos of ``image=`` (a folder or a glob; ``face=all|<index>``: several faces of one photo) as a batch,
    None for one photo; a batch takes a target light, not a video or a target record, and an ``out_dir`` its
    listing does not read; the compositing (a known mode, known parts, a feather >= 0)."""
    check_face(face)  # a typo is the command's error before any photo is read (not a skipped row per photo)
    photos = photo_paths(image)
    if photos is not None:
        check_out_dir_apart(image, out_dir)
    if photos is None and str(face).lower() != "largest":
        photos = [Path(str(image))]  # several faces of one photo
    if photos is not None and (axis is not None or record is not None):
        raise UserError(f"image={image} face={face}: a folder or several faces take a target light "
                        "(target.light|yaw|roll|pitch|envmap), not video.axis or target.record")
    check_choice(composite["mode"], "composite.mode", MODES)
    try:
        part_mask(np.zeros((1, 1), np.uint8), list(composite["parts"] or []))
    except ValueError as e:
        raise UserError(f"composite.parts: {e}") from None
    if check_number(composite["feather"], "composite.feather", allow_none=False) < 0:
        raise UserError(f"composite.feather={composite['feather']}: must be >= 0 (a fraction of the crop size)")
    return None if photos is None else tuple(photos)


def check_face(face: Any) -> None:
    """``face=`` as a choice (largest | all | an index >= 0), checked before any photo is read: a typo is the
    command's error, said once, not a "skipped" line per photo."""
    key = str(face).strip().lower()
    if key in ("largest", "all") or key.isdigit():
        return
    raise UserError(f"face={face} is invalid: give face=largest, face=all or face=<index> (0, 1, ...: the "
                    "detected faces left to right)")


def output_names(paths: Sequence[Path]) -> list[str]:
    """Each photo's name in ``out_dir``: its path below the photos' common folder without its suffix (folders
    joined by ``__``); a later photo that would share an earlier one's name gets its suffix (``a.jpg``, ``a.png``
    -> ``a``, ``a_png``), and where that is shared too, a short hash of its path."""
    real = [Path(p).parent.resolve() / Path(p).name for p in paths]
    common = Path(os.path.commonpath([p.parent for p in real])) if real else Path(".")
    rel = [p.relative_to(common) for p in real]
    names = ["__".join(r.with_suffix("").parts) for r in rel]
    for tag in (lambda i: rel[i].suffix.lstrip("."), lambda i: hashlib.sha1(str(real[i]).encode()).hexdigest()[:8]):
        names = [f"{n}_{tag(i)}" if n in names[:i] else n for i, n in enumerate(names)]
    return names


def relight_one(path: Path, *, relighter: Relighter, target: Callable[[Source], Targets], size: int | None, face: Any,
                composite: Mapping[str, Any], strict: bool = False, say=print
                ) -> tuple[np.ndarray, list[np.ndarray], dict[str, Any]]:
    """One photo: every chosen face (the relighter's :meth:`~difareli.relight.sources.Sources.photo_faces`) relit
    under ``target(source)`` (its Targets) and composited in turn into the photo. Returns (composite, relit crops,
    CSV row fields); a UserError for a photo that cannot be relit."""
    out, found, faces = relighter.photo_faces(path, size=size, face=face, strict=strict, say=say)
    crops, worst = [], None
    parts = list(composite["parts"]) if composite.get("parts") else None
    for source in faces:
        worst = source.check if worst is None or (worst.ok and not source.check.ok) else worst
        relit = relighter.relight(source, target(source))
        crops.append(relit[0])
        out = relit.composite(composite.get("mode", "ratio"), composite.get("feather", 0.03), parts, onto=out)[0]
    return out, crops, {"faces": found, "relit_faces": len(crops), "verdict": "ok" if worst.ok else "poor",
                        **worst.measures}


def relight_photos(paths: Sequence[Path], out_dir: str | Path, *, relighter: Relighter | None, progress: bool = True,
                   settings: Mapping[str, Any] | None = None, **kwargs) -> dict:
    """Relight every photo of ``paths`` (module doc; ``settings``: the request's, recorded with the relighter's
    ``identity()`` and checked); returns counts {"done", "skipped", "resumed"}."""
    from tqdm.auto import tqdm

    out_dir, names = Path(out_dir), output_names(paths)
    if settings is not None:  # the record names the relighter that writes the folder, taken where it relights
        settings = {**relighter.identity(), **settings}
    with _opened(out_dir, settings) as before:
        counts = {"done": 0, "skipped": 0, "resumed": 0}
        todo = []  # the bar counts only these: photos relit before would make its rate and time left untrue
        for path, name in zip(paths, names):
            prior = before.get(name)
            if prior is not None and prior["status"] == "relit" and (out_dir / f"{name}_composite.png").is_file():
                counts["resumed"] += 1  # a photo skipped before is tried again: the user may have fixed it
            else:
                todo.append((path, name))
        bar = tqdm(todo, desc="photos", unit="photo", disable=not progress, file=sys.stderr)
        for path, name in bar:
            start = time.perf_counter()
            try:
                full, crops, row = relight_one(path, relighter=relighter, say=lambda s: bar.write(s), **kwargs)
            except UserError as e:
                counts["skipped"] += 1
                reason = str(e).removeprefix(f"image={path}: ").splitlines()[0]
                print(f"skipped image={path}: {reason}", file=sys.stderr)
                row, images = {"status": "skipped", "reason": reason}, {}
            else:
                row, images = {"status": "relit", **row}, {"relit": np.concatenate(crops, axis=1), "composite": full}
                counts["done"] += 1
            before[name] = {"name": name, "photo": str(path), "seconds": time.perf_counter() - start, **row}
            _keep(out_dir, name, images, before)
        bar.close()
    return counts


@contextlib.contextmanager
def _opened(out_dir: Path, settings: Mapping[str, Any] | None) -> Iterator[dict[str, dict[str, str]]]:
    """The folder locked while a run writes it, with its ``relight.csv`` rows by output name ({} for none; another
    table there is refused) and its ``settings`` recorded (a rerun with others is refused)."""
    path = out_dir / CSV_NAME
    with fileio.folder_lock(out_dir, "relight"):
        rows = {}
        if path.is_file():
            with path.open(newline="") as f:
                reader = csv.DictReader(f)
                if not {"name", "photo", "status"} <= set(reader.fieldnames or ()):
                    raise UserError(f"{path} is not a difareli-relight photo table (its columns: "
                                    f"{', '.join(reader.fieldnames or ['none'])[:160]}); give another out_dir")
                rows = {row["name"]: row for row in reader}
        if settings is not None:
            provenance.ensure(out_dir, settings, "relit photos", name=SETTINGS, has_results=path.is_file())
        yield rows


def _keep(out_dir: Path, name: str, images: Mapping[str, np.ndarray], rows: Mapping[str, Mapping[str, Any]]) -> None:
    """A photo's outcome kept: its images ``<name>_<kind>.png``, then the table written whole (atomically) with its
    row, one row per output name (its latest outcome): a run killed in between relights the photo again."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, FIELDS, extrasaction="ignore")
    w.writeheader()
    w.writerows({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()}  # numbers people read
                for row in rows.values())
    for kind, image in images.items():
        viz.save_png(image, out_dir / f"{name}_{kind}.png")
    fileio.write_text_atomic(out_dir / CSV_NAME, buf.getvalue())
