"""Photos in one command: ``difareli-relight image=<folder or glob>`` and ``face=all|<index>``.

:func:`photo_paths` expands the ``image=`` value; :func:`relight_photos` relights every photo under one target
(a progress bar), composites every chosen face into the one photo, and writes per input ``<stem>_composite.png``
and ``<stem>_relit.png`` (the relit crops side by side) into ``out_dir``, and a row per photo to ``relight.csv``
(seconds, faces, the check's measures, the outcome). A photo that cannot be relit (unreadable or truncated
file, no face, too small, ``strict`` and a poor check) is one line on stderr and a ``skipped`` row. A rerun skips
the photos relit before (a killed run resumes: files are written atomically, the CSV row last) and tries the
skipped ones again (the error said to fix them; the last row of a photo is its outcome)."""

from __future__ import annotations

import glob
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from difareli.errors import UserError
from difareli.relight import photo, photo_check
from difareli.utils import fileio, viz
from difareli.estimators.loading import IMAGE_SUFFIXES

CSV_NAME = "relight.csv"
FIELDS = ("photo", "status", "seconds", "faces", "relit_faces", "verdict", *photo_check.LIMITS, "reason")


def photo_paths(value: str) -> list[Path] | None:
    """The photos of a folder (its image files, sorted) or of a glob pattern; None for one file."""
    p = Path(str(value))
    if p.is_dir():
        found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES)
    elif any(c in str(value) for c in "*?["):
        found = sorted(Path(q) for q in glob.glob(str(value)) if Path(q).is_file())
    else:
        return None
    if not found:
        raise UserError(f"image={value}: no photos there ({', '.join(IMAGE_SUFFIXES)}); give a folder of face "
                        "photos, a glob such as 'photos/*.jpg', or one photo")
    return found


def relight_one(path: Path, *, relighter, target: Callable[[Any], Any], size: int | None, face: Any,
                composite: Mapping[str, Any], strict: bool = False, say=print
                ) -> tuple[np.ndarray, list[np.ndarray], dict[str, Any]]:
    """One photo: every chosen face relit under ``target(source)`` (its Targets) by the relighter's one door
    (:meth:`~difareli.relight.relighter.Relighter.photo_source`, ``relight``) and composited in turn into the
    photo. Returns (composite, relit crops, CSV row fields); a UserError for a photo that cannot be relit."""
    what = f"image={path}"
    rgb = photo.read_photo(path)
    boxes = photo.detect_faces(rgb, relighter.photo_size(size))
    chosen = photo.choose_faces(boxes, face, what) if boxes else [None]
    for i, box in enumerate(boxes):
        say(f"{what}: {photo.describe_box(i, box, i in chosen)}")
    out, crops, worst = rgb, [], None
    parts = list(composite["parts"]) if composite.get("parts") else None
    for i in chosen:
        name = what if i is None or len(boxes) < 2 else f"{what} face {i}"
        source = relighter.photo_source(rgb, size=size, face=None if i is None else boxes[i], strict=strict,
                                        what=name, key=("image", str(path), i))
        say(source.check.line())
        worst = source.check if worst is None or (worst.ok and not source.check.ok) else worst
        relit = relighter.relight(source, target(source))
        crops.append(relit[0])
        out = relit.composite(composite.get("mode", "ratio"), composite.get("feather", 0.03), parts, onto=out)[0]
    row = {"faces": len(boxes), "relit_faces": len(crops), "verdict": "ok" if worst.ok else "poor",
           **worst.measures}
    return out, crops, row


def relight_photos(paths: Sequence[Path], out_dir: str | Path, *, progress: bool = True, **kwargs) -> dict:
    """Relight every photo of ``paths`` (module doc); returns counts {"done", "skipped", "resumed"}."""
    from tqdm.auto import tqdm

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / CSV_NAME
    before = fileio.read_csv_rows(csv_path, "photo")
    counts = {"done": 0, "skipped": 0, "resumed": 0}
    todo = []  # the bar counts only these: photos relit before would make its rate and time left untrue
    for path, stem in zip(paths, output_stems(paths)):
        prior = before.get(str(path))
        if prior is not None and prior["status"] == "relit" and (out_dir / f"{stem}_composite.png").is_file():
            counts["resumed"] += 1  # a photo skipped before is tried again: the user may have fixed it
        else:
            todo.append((path, stem))
    bar = tqdm(todo, desc="photos", unit="photo", disable=not progress, file=sys.stderr)
    for path, stem in bar:
        target = out_dir / f"{stem}_composite.png"
        start = time.perf_counter()
        try:
            full, crops, row = relight_one(path, say=lambda s: bar.write(s), **kwargs)
        except UserError as e:
            counts["skipped"] += 1
            reason = str(e).removeprefix(f"image={path}: ").splitlines()[0]
            print(f"skipped image={path}: {reason}", file=sys.stderr)
            fileio.append_csv_row(csv_path, FIELDS, _formatted({"photo": str(path), "status": "skipped",
                                                                "reason": reason,
                                                                "seconds": time.perf_counter() - start}))
            continue
        viz.save_png(np.concatenate(crops, axis=1), out_dir / f"{stem}_relit.png")
        viz.save_png(full, target)
        fileio.append_csv_row(csv_path, FIELDS, _formatted({"photo": str(path), "status": "relit",
                                                            "seconds": time.perf_counter() - start, **row}))
        counts["done"] += 1
    bar.close()
    return counts


def output_stems(paths: Sequence[Path]) -> list[str]:
    """Each photo's name in ``out_dir``: its stem, or ``<stem>_<suffix>`` where an earlier photo has that stem
    (``a.jpg`` and ``a.png``)."""
    stems: list[str] = []
    for path in paths:
        stems.append(path.stem if path.stem not in stems else f"{path.stem}_{path.suffix.lstrip('.')}")
    return stems


def _formatted(row: Mapping[str, Any]) -> dict[str, Any]:
    # Numbers to 4 significant digits: a CSV people read.
    return {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()}
