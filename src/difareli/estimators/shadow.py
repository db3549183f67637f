"""Cast-shadow scalar ``c`` (a small classifier's logit) and the ray-traced ``shadow_map``.

Classifier: logistic regression on six hand features of the photo against its fitted SH light and the
FaceMesh surface (``features``), trained on SynthFaces by ``scripts/train_shadow_classifier.py``. Label:
"visible cast shadow" = SynthFaces ``c > logit(LABEL_S)``, i.e. cast shadows remove more than 2% of the
face's light (``synth/subject.py`` defines ``c`` as the logit of that fraction). ``c`` is the
classifier's logit, as in the paper; with ``c_scale: synthfaces`` (default) it is mapped by the affine
calibration fitted at training time onto the SynthFaces ``c`` scale, so that ``encodings.normalise_c``
(fixed range [SHADOW_C_LO, SHADOW_C_HI]) means the same on real and synthetic records; ``c_scale: logit`` keeps the raw
logit.

``shadow_map`` = cast-shadow rays from the FaceMesh surface toward ``sh.dominant_direction(light)``
(``render.cast_shadow``) times ``encodings.normalise_c(c)``, exactly as SynthFaces builds its maps.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from difareli.lighting import sh
from difareli.data.encodings import normalise_c
from difareli.utils.imageops import LUMA
from difareli.render import cast_shadow
from difareli.errors import UserError, UserFileNotFoundError

LABEL_S = 0.02
LABEL_C = math.log(LABEL_S / (1 - LABEL_S))
FEATURES = ("cast_fraction", "cast_darkening", "unexplained_dark", "directionality", "frontal", "ratio_spread")
DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "shadow_logreg.json"


def features(image: np.ndarray, gbuffer, region: np.ndarray, light: np.ndarray, albedo, cast: np.ndarray) -> np.ndarray:
    """The six features (``FEATURES``) on ``region`` (skin on the face surface); see the inline notes."""
    region = region & gbuffer.hit
    n = gbuffer.normal[region].astype(np.float64)
    obs = (image[region].astype(np.float64) / 255.0) @ LUMA
    pred = (np.asarray(albedo) * sh.irradiance(np.asarray(light, np.float64), n)) @ LUMA
    logr = np.log(np.maximum(obs, 1e-3)) - np.log(np.maximum(pred, 1e-3))
    d = sh.dominant_direction(light)
    in_cast = cast[region]
    b1 = np.linalg.norm(np.asarray(light, np.float64)[1:4].mean(1)) * sh.SH_CONSTANTS[1]
    b0 = abs(float(np.asarray(light, np.float64)[0].mean())) * sh.SH_CONSTANTS[0] + 1e-6
    lit = (n @ d) > 0.2
    return np.array([
        in_cast.mean() if len(in_cast) else 0.0,  # how much of the face the geometry says is shadowed
        # Shadowed pixels darker than SH predicts, relative to the rest (0 when nothing is predicted).
        float(np.median(logr[~in_cast]) - np.median(logr[in_cast])) if 20 <= in_cast.sum() < len(in_cast) - 20 else 0.0,
        float(np.mean(lit & (logr < math.log(0.6)))) if len(logr) else 0.0,  # dark where the light should reach
        b1 / b0,  # directional vs ambient irradiance: only a directional light casts shadows
        float(d[2]),  # a frontal light casts none visible from the camera
        float(np.std(logr)) if len(logr) else 0.0,
    ])


class LogisticShadowClassifier:
    """Standardised logistic regression stored as JSON (``weights``); ``logit(x)`` is w . (x - mu) / sd + b."""

    def __init__(self, params: dict):
        self.params = params
        self.mean = np.asarray(params["mean"], dtype=np.float64)
        self.std = np.asarray(params["std"], dtype=np.float64)
        self.w = np.asarray(params["w"], dtype=np.float64)
        self.b = float(params["b"])
        self.calibration = tuple(params.get("calibration", (1.0, 0.0)))

    @classmethod
    def load(cls, path: str | Path) -> "LogisticShadowClassifier":
        path = Path(path)
        if not path.is_file():
            raise UserFileNotFoundError(f"shadow classifier weights {path} not found; train them with "
                                        "scripts/train_shadow_classifier.py or drop 'shadow'/'shadow_map' from "
                                        "encodings")
        return cls(json.loads(path.read_text()))

    def logit(self, x: np.ndarray) -> np.ndarray:
        return ((np.asarray(x) - self.mean) / self.std) @ self.w + self.b

    @staticmethod
    def train(x: np.ndarray, y: np.ndarray, l2: float = 1e-2, iters: int = 50) -> dict:
        """Newton-IRLS fit of standardised features; returns the JSON-able parameters."""
        mean, std = x.mean(0), x.std(0) + 1e-8
        z = np.concatenate([(x - mean) / std, np.ones((len(x), 1))], axis=1)
        theta = np.zeros(z.shape[1])
        reg = l2 * len(x) * np.diag([1.0] * (z.shape[1] - 1) + [0.0])
        for _ in range(iters):
            p = 1 / (1 + np.exp(-(z @ theta)))
            grad = z.T @ (p - y) + reg @ theta
            hess = (z * (p * (1 - p))[:, None]).T @ z + reg + 1e-9 * np.eye(len(theta))
            step = np.linalg.solve(hess, grad)
            theta -= step
            if np.abs(step).max() < 1e-8:
                break
        return {"features": list(FEATURES), "mean": mean.tolist(), "std": std.tolist(),
                "w": theta[:-1].tolist(), "b": float(theta[-1])}


class ShadowEstimator:
    """Estimator: ``shadow`` (1,) and ``shadow_map`` (H, W)."""

    provides = ("shadow", "shadow_map", "cast")
    requires = ("image", "gbuffer", "scene", "light", "skin")

    def __init__(self, weights: str | None = None, c_scale: str = "synthfaces"):
        if c_scale not in ("synthfaces", "logit"):
            raise UserError(f"c_scale must be 'synthfaces' or 'logit', got {c_scale!r}")
        self.weights = Path(weights) if weights else DEFAULT_WEIGHTS
        self.c_scale = c_scale
        self._clf = None

    @property
    def classifier(self) -> LogisticShadowClassifier:
        if self._clf is None:
            self._clf = LogisticShadowClassifier.load(self.weights)
        return self._clf

    def cast(self, ctx: dict) -> np.ndarray:
        """Bool cast-shadow map toward the dominant direction of the fitted light."""
        gb = ctx["gbuffer"]
        return cast_shadow(ctx["scene"], gb, sh.dominant_direction(ctx["light"])) & gb.hit

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        clf = self.classifier
        cast = self.cast(ctx)
        x = features(ctx["image"], ctx["gbuffer"], ctx["skin"], ctx["light"], ctx["albedo_prior"], cast)
        logit = float(clf.logit(x))
        a, b = clf.calibration
        c = a * logit + b if self.c_scale == "synthfaces" else logit
        return {"shadow": np.array([c], np.float32), "cast": cast,
                "shadow_map": (cast * normalise_c(c)).astype(np.float32),
                "shadow_info": {"logit": logit, "p_shadow": 1 / (1 + math.exp(-logit)), "c": c,
                                "features": dict(zip(FEATURES, map(float, x)))}}
