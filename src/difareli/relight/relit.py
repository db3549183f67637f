"""What a relight gives back: :class:`Relit`, the relit crops with the seconds per stage, the source and its
targets. It *is* its images (an ``ndarray`` subclass, as ``np.ma`` arrays are): code that reads a relight as an
array keeps working, and arithmetic and reductions on it give plain arrays and scalars.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np
from difareli.errors import UserError
from difareli.utils.imageops import grey_like


class Relit(np.ndarray):
    """The relights of one source under N targets (N, H, W, 3) uint8, with ``seconds`` per stage (``invert``: 0 when
    the inversion was reused; ``decode``; ``composite`` once composited), the ``source`` (with its photo, if any)
    and the ``targets`` they were made under. A grey source's relights are their luminance (``source.grey``: a
    colour the model adds is invented)."""

    seconds: dict[str, float]
    source: Any
    targets: Any

    def __new__(cls, images: np.ndarray, seconds: dict[str, float] | None = None, source: Any = None,
                targets: Any = None) -> "Relit":
        grey = getattr(source, "grey", False)
        obj = np.asarray(grey_like(images) if grey else images).view(cls)
        obj.seconds, obj.source, obj.targets = dict(seconds or {}), source, targets
        return obj

    def __array_finalize__(self, obj) -> None:
        # A slice or view (relit[0]) keeps what it was made under.
        if obj is None:
            return
        self.seconds = getattr(obj, "seconds", {})
        self.source = getattr(obj, "source", None)
        self.targets = getattr(obj, "targets", None)

    def __array_wrap__(self, arr, context=None, return_scalar=False):
        # Computed values (relit == 255, relit.mean()) are plain numbers, not relights.
        arr = np.asarray(arr).view(np.ndarray)
        return arr[()] if arr.ndim == 0 else arr

    def __reduce__(self):
        return (Relit, (self.images, self.seconds, None, None))

    @property
    def images(self) -> np.ndarray:
        """The relit crops as a plain array."""
        return self.view(np.ndarray)

    def composite(self, mode: str = "ratio", feather: float = 0.03, parts: Sequence[str] | None = None, *,
                  onto: np.ndarray | None = None, images: np.ndarray | None = None) -> np.ndarray:
        """The relit crops put back into the whole photo (N, H, W, 3) uint8 (:mod:`difareli.relight.composite`);
        ``onto``: composite into this image instead of the original photo (another face of it already relit);
        ``images``: composite these crops (e.g. a video's frames) instead of these. A UserError for a source that
        is not a photo."""
        prepared = getattr(self.source, "photo", None)
        if prepared is None:
            what = getattr(self.source, "what", "this source")
            raise UserError(f"{what} is not a photo: only a photo's relights composite back into it")
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
