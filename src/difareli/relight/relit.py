"""What one relight request gives back: :class:`Relit` (the relit crops, the seconds per stage, the source and its
targets), and the whole photos for a photo source (:meth:`Relit.composite`).

A :class:`Relit` indexes, iterates, converts (``np.asarray``) and answers array attributes (``shape``, ``dtype``)
as its images (N, H, W, 3) uint8, so code that reads a relight as an array keeps working; new code reads
``.images``, ``.seconds`` and ``.composite()``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np


@dataclass
class Relit:
    """The relights of one source under N targets: ``images`` (N, H, W, 3) uint8, ``seconds`` per stage
    (``invert``: 0 when the inversion was reused; ``decode``; ``composite`` once composited), the source (with its
    photo, if any) and the targets they were made under."""

    images: np.ndarray
    seconds: dict[str, float]
    source: Any
    targets: Any
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i):
        return self.images[i]

    def __iter__(self):
        return iter(self.images)

    def __array__(self, dtype=None, copy=None):
        return self.images if dtype is None else self.images.astype(dtype)

    def __getattr__(self, name: str):
        # Only for names a Relit lacks (dtype, shape, astype, mean ...): answered by its images.
        if name == "images" or name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.images, name)

    def composite(self, mode: str = "ratio", feather: float = 0.03, parts: Sequence[str] | None = None, *,
                  onto: np.ndarray | None = None, images: np.ndarray | None = None) -> np.ndarray:
        """The relit crops put back into the whole photo (N, H, W, 3) uint8 (:mod:`difareli.relight.composite`);
        ``onto``: composite into this image instead of the original photo (another face of it already relit);
        ``images``: composite these crops (e.g. a video's frames) instead of :attr:`images`. A UserError for a
        source that is not a photo."""
        from difareli.errors import UserError

        prepared = getattr(self.source, "photo", None)
        if prepared is None:
            raise UserError(f"{self.source.what} is not a photo: only a photo's relights composite back into it")
        start = time.perf_counter()
        comp = prepared.compositor(mode, feather, list(parts) if parts else None)
        if onto is not None:  # the gain of this face goes onto the photo so far (faces do not overlap)
            comp = type(comp)(np.asarray(onto), comp.aligned, comp.labels, comp.quad, mode=comp.mode,
                              feather=comp.feather, parts=comp.parts, inside=comp.inside)
        out = comp(self.images if images is None else np.asarray(images))
        self.seconds["composite"] = self.seconds.get("composite", 0.0) + time.perf_counter() - start
        return out

    def describe_seconds(self) -> str:
        """``invert 1.20 s, decode 0.85 s`` (the stages that ran)."""
        return ", ".join(f"{k} {v:.2f} s" for k, v in self.seconds.items())
