"""Test helpers: compose the real Hydra configs outside the CLI."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

from difareli.configs import CONFIG_DIR

CONF = CONFIG_DIR


def _installed(*modules: str) -> bool:
    # find_spec, not import: deciding a skip must not pay for importing mediapipe (seconds) in every worker.
    return all(importlib.util.find_spec(m) for m in modules)


#: The photo estimators (DIFARELI_PREPROCESS=1 bash scripts/install.sh): difareli-synth's default inputs=estimated
#: and the real-photo pipeline need them; the README's plain install has none, and tests that need them skip there.
#: (cv2 comes with mediapipe, which requires opencv-contrib-python.)
HAS_ESTIMATORS = _installed("mediapipe", "cv2", "dlib")
NO_ESTIMATORS = "needs the photo estimators (DIFARELI_PREPROCESS=1 bash scripts/install.sh)"
#: The companions below name the other subsets of that install that some tests need.
#: mediapipe alone: face landmarks and the BFM fit on them, without identity.
HAS_MEDIAPIPE = _installed("mediapipe")
#: OpenCV alone: the photo crop and the composite's blending use it, without the estimators.
HAS_CV2 = _installed("cv2")
#: dlib with its face-recognition model files (face_recognition_models): what DlibIdentity loads.
HAS_DLIB_MODELS = _installed("dlib", "face_recognition_models")
#: The estimators and the face_recognition package, the reference the identity estimator is compared with.
HAS_FACE_RECOGNITION = HAS_ESTIMATORS and _installed("face_recognition")


def compose_train(out_dir: Path, overrides: list[str], config_name: str = "train") -> DictConfig:
    """Compose ``conf/<config_name>.yaml`` with overrides; run outputs go to ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(config_name, overrides=overrides, return_hydra_config=True)
        # `${hydra:...}` interpolations need a live HydraConfig, as under @hydra.main.
        with open_dict(cfg):
            cfg.hydra.runtime.output_dir = str(out_dir)
            cfg.hydra.runtime.cwd = str(out_dir)
        HydraConfig().set_config(cfg)
        with open_dict(cfg):
            cfg.paths.output_dir = str(out_dir)
            cfg.paths.log_dir = str(out_dir / "logs")
            del cfg.hydra
    return cfg


def tiny_cpu_overrides(store: Path, batch_size: int = 4) -> list[str]:
    """Train overrides for a tiny model on a 32-px test store, on the CPU, without a sample grid."""
    return [f"data.root={store}", "data.resolution=32", "data.synth=null", "data.num_workers=0",
            f"data.batch_size={batch_size}", "model.preset=tiny", "trainer=cpu", "sample_grid=false"]


def failing_save(monkeypatch, err: OSError, at: int = 1) -> None:
    """``np.save`` whose ``at``-th call writes a partial header, then fails with ``err`` (a disk filling mid-array)."""
    import numpy as np

    real, calls = np.save, []

    def save(f, arr, **kw):
        calls.append(1)
        if len(calls) == at:
            f.write(b"\x93NUMPY partial")
            raise err
        return real(f, arr, **kw)

    monkeypatch.setattr(np, "save", save)
