"""How a benchmark scores a relit image: :class:`Scoring` (the metric rule, the mask and where a fitted target
light's shadow map is marched, checked once at the command's door) and :func:`score` (one image's DSSIM / MSE /
LPIPS against its ground truth through :func:`difareli.evaluation.metrics.relight_metrics`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from difareli import errors
from difareli.data import encodings
from difareli.data.store import EncodingStore
from difareli.evaluation import metrics
from difareli.render.sun_fit import TARGET_SUNS

#: The mask every pair is scored on unless ``score_mask`` names another one.
DEFAULT_MASK = "face_mask"


def check_score_mask(store: EncodingStore, key: str | None) -> str:
    """``key`` (None: :data:`DEFAULT_MASK`) if the store has it as a mask (a bool HxW encoding), else a UserError
    naming the masks it has."""
    key = DEFAULT_MASK if key is None else str(key)
    have = [n for n in store.encodings if n in encodings.ENCODINGS and encodings.get(n).dtype == "bool"
            and tuple(encodings.get(n).shape) == ("H", "W")]
    if key not in have:
        what = (f"has {key} but it is not a mask (a bool HxW encoding)" if store.available(key) else
                f"has no {key}")
        raise errors.UserError(f"score_mask={key}: store {store.root} {what}; give one of its masks: "
                               f"{', '.join(have)} (default score_mask={DEFAULT_MASK})")
    return key


@dataclass(frozen=True)
class Scoring:
    """How a run scores its pairs, checked once at the door (:meth:`of`): the metric ``rule`` (None: ``paper``), the
    ``score_mask`` (None: ``face_mask``) and ``target_sun``, where a fitted target light's cast-shadow maps are
    marched: ``shadows`` (toward the key sun found from the light-source image's cast shadows: ``render.sun_fit``)
    or ``peak`` (the fitted SH's radiance peak)."""

    rule: str
    score_mask: str
    target_sun: str = "shadows"

    @classmethod
    def of(cls, store: EncodingStore, rule: str | None = None, score_mask: str | None = None,
           target_sun: str = "shadows") -> "Scoring":
        """Each value checked, named as the benchmark's config spells it (None: the defaults)."""
        return cls(errors.check_choice(metrics.DEFAULT_RULE if rule is None else rule, "metrics.rule", metrics.RULES),
                   check_score_mask(store, score_mask), errors.check_choice(target_sun, "target_sun", TARGET_SUNS))


def score(pred: np.ndarray, target: np.ndarray, face_mask: np.ndarray, rule: str | None = None,
          scorer=None) -> dict[str, float]:
    """DSSIM / MSE / LPIPS of one uint8 image against the ground truth on the mask under ``rule``; through
    ``scorer`` (a :func:`metrics.relight_metrics` collection, which also accumulates the score) when given."""
    scorer = scorer if scorer is not None else metrics.relight_metrics(rule)
    mask = torch.from_numpy(np.array(face_mask, dtype=bool))[None]
    scorer.update(metrics.unit_tensor(pred), metrics.unit_tensor(target), mask)
    return {k: float(m.last[0]) for k, m in scorer.items()}
