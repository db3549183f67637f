"""Where a Multi-PIE copy keeps its frontal images, and what their names mean.

The layout (the database's own, as the DiFaReli authors read it)::

    <root>/data/session<NN>/multiview/<subject>/<recording>/05_1/<subject>_<session>_<recording>_051_<illum>.png

``<root>`` may also be the ``data`` folder itself. Subjects are 3 digits (001-346), sessions and recordings 2
digits, camera ``05_1`` (file name ``051``) is the frontal one, illuminations ``00``-``19``. Recording ``01`` is the
neutral expression in every session (the authors' lists use only it).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from difareli.errors import UserError

FRONTAL_CAMERA = "05_1"
NEUTRAL_RECORDING = "01"
ILLUMINATIONS = tuple(f"{i:02d}" for i in range(20))
#: Recording numbers a session may hold (Multi-PIE has up to three per session; two digits in the file names).
RECORDINGS = tuple(f"{i:02d}" for i in range(1, 100))
_NAME = re.compile(r"^(?P<subject>\d{3})_(?P<session>\d{2})_(?P<recording>\d{2})_(?P<camera>\d{3})_(?P<illum>\d{2})"
                   r"(?:\.png)?$")
_SUBJECT = re.compile(r"^\d{3}$")
EXPECTED = ("<root>/data/sessionNN/multiview/<subject>/<recording>/05_1/<subject>_<session>_<recording>_051_"
            "<illumination>.png (e.g. data/session01/multiview/001/01/05_1/001_01_01_051_07.png)")


@dataclass(frozen=True, order=True)
class Image:
    """One frontal Multi-PIE image, named by its five fields."""

    subject: str
    session: str
    recording: str
    illumination: str
    camera: str = "051"

    @classmethod
    def parse(cls, name: str) -> "Image":
        """An image from its file name (``001_01_01_051_07.png``, with or without ``.png``)."""
        m = _NAME.match(Path(str(name)).name)
        if m is None:
            raise UserError(f"{name!r} is not a Multi-PIE image name <subject>_<session>_<recording>_051_<illum>.png")
        if m["camera"] != "051":
            raise UserError(f"{name!r} is from camera {m['camera']}; only the frontal camera 051 (05_1) is read")
        return cls(m["subject"], m["session"], m["recording"], m["illum"])

    @property
    def stem(self) -> str:
        """The file stem, which is also the image's record id in the store."""
        return f"{self.subject}_{self.session}_{self.recording}_{self.camera}_{self.illumination}"

    @property
    def recording_key(self) -> tuple[str, str, str]:
        """(subject, session, recording): the images of one sitting, differing only by illumination."""
        return self.subject, self.session, self.recording

    def under(self, illumination: str) -> "Image":
        """The same sitting under another illumination."""
        return Image(self.subject, self.session, self.recording, illumination, self.camera)

    def path(self, data: Path) -> Path:
        """Where the image lies under the ``data`` folder."""
        return (Path(data) / f"session{self.session}" / "multiview" / self.subject / self.recording / FRONTAL_CAMERA
                / f"{self.stem}.png")


def codes(value: Any, key: str, valid: Sequence[str]) -> list[str]:
    """A list of 2-digit codes from ``value``: one number or digit string (``7``, ``"07"``) or a list of them, each one
    of ``valid``; anything else (text, a code out of range, an empty list) is a UserError naming ``key``."""
    items = [value] if value is None or isinstance(value, (str, int, float)) else list(value)  # a ListConfig too
    example = f"{key}=[1]" if key == "recordings" else f"{key}=[1,2,3]"
    if not items:
        raise UserError(f"{key}=[] names none; give at least one, e.g. {example}")
    out = []
    for v in items:
        text = str(v).strip()
        if isinstance(v, bool) or not text.isdigit() or f"{int(text):02d}" not in valid:
            raise UserError(f"{key}={_show(value)}: {v!r} is not a Multi-PIE {key[:-1]} (its {key} are "
                            f"{valid[0]}-{valid[-1]}); give numbers, e.g. {example}")
        out.append(f"{int(text):02d}")
    return list(dict.fromkeys(out))


def _show(value: Any) -> str:
    if isinstance(value, (str, int)):
        return repr(value) if isinstance(value, str) else str(value)
    return str(list(value))


def _sessions(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("session[0-9][0-9]") if (p / "multiview").is_dir())


def data_dir(root: str | Path) -> Path:
    """The ``data`` folder of a Multi-PIE copy at ``root`` (or ``root`` itself); a UserError naming the
    expected layout when neither holds ``sessionNN/multiview``."""
    root = Path(str(root)).expanduser()
    if not root.is_dir():
        raise UserError(f"root={root}: no such folder; give the Multi-PIE copy's folder, laid out as {EXPECTED}")
    for cand in (root / "data", root):
        if _sessions(cand):
            return cand
    found = sorted(p.name for p in root.iterdir())[:8]
    raise UserError(f"root={root}: not a Multi-PIE tree (it holds {found or 'nothing'}); expected {EXPECTED}")


def scan(data: Path, recordings: Iterable[str] = (NEUTRAL_RECORDING,),
         illuminations: Iterable[str] = ILLUMINATIONS) -> tuple[list[tuple[Image, Path]], list[str]]:
    """Every frontal image of the given recordings and illuminations under ``data``, and one line per expected
    image that is missing from a recording folder that exists."""
    recordings = codes(recordings, "recordings", RECORDINGS)
    illuminations = codes(illuminations, "illuminations", ILLUMINATIONS)
    found, missing = [], []
    for session in _sessions(data):
        for subject in sorted(p for p in (session / "multiview").iterdir() if p.is_dir() and _SUBJECT.match(p.name)):
            for rec in recordings:
                folder = subject / rec / FRONTAL_CAMERA
                if not folder.is_dir():
                    continue
                for ill in illuminations:
                    img = Image(subject.name, session.name[-2:], rec, ill)
                    path = img.path(data)
                    if path.is_file():
                        found.append((img, path))
                    else:
                        missing.append(f"missing: {path}")
    return found, missing


def illuminations_in(data: Path, recordings: Iterable[str]) -> list[str]:
    """The illuminations the frontal images of ``recordings`` under ``data`` have (what a copy holds)."""
    out = set()
    for session in _sessions(data):
        for rec in recordings:
            for path in (session / "multiview").glob(f"*/{rec}/{FRONTAL_CAMERA}/*.png"):
                m = _NAME.match(path.name)
                if m is not None:
                    out.add(m["illum"])
    return sorted(out)
