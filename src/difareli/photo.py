"""A face photo to the encodings a model reads, in memory (``difareli-relight image=photo.jpg``, the demo).

The same estimators as ``difareli-preprocess`` (``conf/preprocess/``), planned for exactly the encodings the
model needs; nothing is written to disk.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from difareli.errors import UserError

#: The default estimators (``conf/preprocess.yaml``'s choices) as plain config, for callers without Hydra.
DEFAULT_ESTIMATORS = {"align": "mediapipe", "geometry": "bfm", "masks": "facemesh_selfie", "light": "skin_sh",
                      "identity": "dlib", "shadow": "logreg"}
EXTRAS_FIX = "install the photo estimators: DIFARELI_PREPROCESS=1 bash scripts/install.sh"


def default_estimators(size: int) -> dict[str, Any]:
    """The ``estimators`` block of ``conf/preprocess.yaml`` at crop ``size``, read from the package's conf/."""
    from difareli.configs import read_yaml

    out = {}
    for role, choice in DEFAULT_ESTIMATORS.items():
        cfg = read_yaml(f"preprocess/{role}", choice)
        out[role] = {k: (size if v == "${size}" else v) for k, v in cfg.items()}
    return out


def preprocess_photo(rgb: np.ndarray, encodings: Sequence[str], *, size: int,
                     estimators: Mapping[str, Any] | None = None, what: str = "photo") -> dict[str, np.ndarray]:
    """The ``encodings`` of one decoded RGB photo (uint8 HxWx3), aligned to ``size`` px."""
    from difareli.estimators.loading import BadInput
    from difareli.estimators.pipeline import Pipeline

    try:
        pipeline = Pipeline.from_config(estimators or default_estimators(size), ["image", *encodings])
        arrays, _, _ = pipeline.process(np.ascontiguousarray(rgb[..., :3]))
    except ImportError as e:
        raise ImportError(f"relighting a photo needs the estimators' packages ({e}); {EXTRAS_FIX}") from e
    except BadInput as e:
        raise UserError(f"{what}: {e}; use a photo with one clearly visible face") from None
    return {k: np.asarray(v) for k, v in arrays.items()}


def read_photo(path: str | Path, key: str = "image") -> np.ndarray:
    """Decode a photo file to uint8 RGB (the preprocess loader's checks), or a UserError naming ``key``."""
    from difareli.errors import check_file
    from difareli.estimators.loading import BadInput, load_image

    p = check_file(path, key)
    try:
        rgb, _ = load_image(p)
    except BadInput as e:
        raise UserError(f"{key}={p}: {e}; give a JPEG/PNG face photo") from None
    return rgb
