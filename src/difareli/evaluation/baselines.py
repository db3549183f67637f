"""Relighting methods behind one interface, for benchmarks: classical baselines and the diffusion model.

A :class:`Method` has a ``name``, ``relight(source, target_light, target_shadow=None, target=None,
target_sun=None) -> uint8 HxWx3`` and two declarations the benchmark reads: ``needs_light`` (it uses the target
light, so a run under ground-truth lights is marked) and ``needs_light_fit`` (it fits a source light with
``estimator``, whose error the benchmark reports). ``source`` is the input record as a
:class:`~difareli.evaluation.pairs.StoredFace` (its store, its id, its encodings read once); ``target``, the
ground-truth record as one, is only for the oracle; ``target_sun`` is the direction a method that reads a target
shadow map marches it toward (the light's key sun found from the light-source image's cast shadows:
``render.sun_fit``; None: the light's radiance peak). Methods are built from ``conf/method/*.yaml`` ``_target_``
configs by :func:`build_method`.

Target (and source) lights "as a user gets them" come from :class:`difareli.lighting.light_fit.LightFit`.
"""

from __future__ import annotations

import inspect
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from difareli.lighting import sh
from difareli.lighting.light_fit import LightFit, face_normals
from difareli.errors import UserError
from difareli.evaluation.pairs import StoredFace, exact_light_name
from difareli.data import encodings
from difareli.utils.imageops import grey_like
from difareli.relight.targets import Targets
from difareli.data.inputs import check_store_fits
from difareli.relight.relightable import OnePassRelightable


@runtime_checkable
class Method(Protocol):
    """What the benchmark runs: a name and one relit uint8 image per (source record, target light); ``target``
    (the ground truth) is given for the oracle alone."""

    name: str
    needs_light: bool
    needs_light_fit: bool

    def relight(self, source: StoredFace, target_light: np.ndarray, target_shadow: float | None = None,
                target: StoredFace | None = None, target_sun: np.ndarray | None = None) -> np.ndarray: ...


class Identity:
    """The input returned unchanged: the score of doing nothing."""

    needs_light, needs_light_fit = False, False

    def __init__(self, name: str | None = None):
        self.name = name or "identity"

    def relight(self, source, target_light, target_shadow=None, target=None, target_sun=None) -> np.ndarray:
        return np.array(source.image)


class Oracle:
    """The ground-truth render of the pair (the ``target`` the benchmark gives it; refused without one): scores
    exactly 0, a check on the metric pipeline."""

    needs_light, needs_light_fit = False, False

    def __init__(self, name: str | None = None):
        self.name = name or "oracle"

    def relight(self, source, target_light, target_shadow=None, target=None, target_sun=None) -> np.ndarray:
        if target is None:
            raise UserError("the oracle needs the ground-truth record (target)")
        return np.array(target.image)


class LambertianRatio:
    """Ratio-image relighting: ``input * E_target(n) / E_source(n)`` where the stored normals exist.

    The source light is estimated from the input with ``estimator`` (None: the stored ``light``). With both
    lights fitted under the same albedo prior, the prior's scale cancels in the ratio (exactly so when both
    images show the same person). Cast shadows of the input stay and the target's are not added. The
    denominator is floored at ``min_shading`` times the source irradiance's median on the face, per channel:
    there the input is nearly black and any ratio would only amplify noise. Off the face: unchanged.
    """

    needs_light, needs_light_fit = True, True

    def __init__(self, name: str | None = None, estimator: LightFit | None = None, min_shading: float = 0.05):
        self.name, self.estimator, self.min_shading = name or "lambertian", estimator, float(min_shading)
        self._fitted: dict[tuple[str, str], np.ndarray] = {}  # (store, record) -> its fitted light

    def source_light(self, source: StoredFace) -> np.ndarray:
        """The source light fitted to ``source``, or (no estimator: the oracle) the exact one: ``light_gt`` where
        the store has it (SynthFaces v2, whose ``light`` is itself estimated), else ``light``. A record's fit is
        made once (a source is in many pairs, and the benchmark scores the fit it relit with)."""
        if self.estimator is not None:
            key = (str(source.store.root), source.id)
            if key not in self._fitted:
                self._fitted[key] = self.estimator.from_store(source.store, source.id)
            return self._fitted[key]
        name = exact_light_name(source.store)
        return np.asarray(source.read([name])[name], dtype=np.float64)

    def relight(self, source, target_light, target_shadow=None, target=None, target_sun=None) -> np.ndarray:
        a = source.read(["image", "normal"])
        return ratio_relight(a["image"], a["normal"], self.source_light(source), target_light, self.min_shading)


def ratio_relight(image: np.ndarray, normal: np.ndarray, source_light: np.ndarray, target_light: np.ndarray,
                  min_shading: float = 0.05) -> np.ndarray:
    """``image * E_t / max(E_s, floor)`` on pixels with a stored normal (uint8 in and out)."""
    normals, known = face_normals({"normal": normal})
    img = np.asarray(image, dtype=np.float64) / 255.0
    if not known.any():
        return np.array(image, dtype=np.uint8)
    n = normals[known]
    e_s = sh.irradiance(np.asarray(source_light, np.float64), n)
    e_t = sh.irradiance(np.asarray(target_light, np.float64), n)
    floor = np.maximum(min_shading * np.median(e_s, axis=0), 1e-6)
    out = img.copy()
    out[known] = img[known] * np.maximum(e_t, 0.0) / np.maximum(e_s, floor)
    return np.round(np.clip(out, 0.0, 1.0) * 255.0).astype(np.uint8)


class DiffusionMethod:
    """A trained DiFaReli/DiFaReli++ checkpoint through :class:`difareli.relight.relighter.Relighter`.

    The input (the source's record, read from its store by :meth:`Relighter.source`) is inverted with its own
    stored encodings (once per record, cached) and decoded under the target light and shadow strength. Default
    name: ``<model>/<sampler>-<steps>``, e.g. ``difareli_pp/ddim-20``.
    """

    needs_light, needs_light_fit = True, False

    def __init__(self, checkpoint: str | None = None, sampler: Mapping[str, Any] | None = None, *,
                 name: str | None = None, runtime: Mapping[str, Any] | None = None, mean_matching: bool = True,
                 batch_size: int = 16, model_name: str | None = None):
        from difareli.relight.relighter import Relighter

        if not checkpoint or checkpoint == "???":
            raise UserError("method=diffusion needs method.checkpoint=<run>/checkpoints/last.ckpt")
        if sampler is None:
            raise UserError("method=diffusion needs a sampler config (the benchmark's `sampler` group)")

        self.relighter = Relighter(checkpoint, sampler, runtime=runtime, mean_matching=mean_matching,
                                   batch_size=batch_size)
        spec = self.relighter.spec
        # ``model_name`` tells apart two checkpoints of one variant (the shipped difareli_pp and difareli_pp_shadows).
        model = model_name or self.relighter.config.get("name") or "diffusion"
        #: a student: one network pass, the sampler plays no part
        self.one_pass = isinstance(self.relighter.model, OnePassRelightable)
        self.name = name or (model if self.one_pass else f"{model}/{spec.name}-{spec.steps}")

    @property
    def target_maps(self) -> str:
        """How the target's light-dependent encodings are made (stated in the benchmark's tables)."""
        names = encodings.light_dependent(self.relighter.model_inputs)
        maps = "re-rendered on the input's geometry under the target light: " + ", ".join(names)
        if "shadow_map" in names:
            maps += " (shadow map ray-marched on the input's depth; inversion uses the input's own map)"
        return maps

    def check_store(self, store) -> None:
        """The checkpoint reads this store's encodings (else one line naming both; before any pair is relit)."""
        check_store_fits(self.relighter.config, store, self.relighter.checkpoint)

    def relight(self, source, target_light, target_shadow=None, target=None, target_sun=None) -> np.ndarray:
        # What this model reads of it, from the face as the benchmark read and checked it (no second read).
        record = self.relighter.source(source.store, source.id, read=source.read)
        return self.relighter.relight(record, Targets.of([target_light], [target_shadow], record.what,
                                                         suns=[target_sun]))[0]

    @property
    def batch_size(self) -> int:
        """Sources a :meth:`relight_many` call should hold: the relighter's (one network batch of inversions)."""
        return self.relighter.batch_size

    def relight_many(self, sources: Sequence[StoredFace],
                     targets: Sequence[Sequence[tuple[np.ndarray, float | None, np.ndarray | None]]]
                     ) -> list[np.ndarray]:
        """Source ``i`` under each of its (light, shadow, sun) ``targets[i]`` (as many for every source): uint8
        (K, H, W, 3) per source, as :meth:`relight` gives them one by one, through :meth:`Relighter.relight_many`:
        the sources inverted in one batch, their targets decoded in one batch (a grey source's relights grey)."""
        records = [self.relighter.source(s.store, s.id, read=s.read) for s in sources]
        sets = [Targets.of([t[0] for t in ts], [t[1] for t in ts], r.what, suns=[t[2] for t in ts])
                for r, ts in zip(records, targets)]
        images = self.relighter.relight_many(records, sets)
        return [grey_like(im) if r.grey else im for r, im in zip(records, images)]


#: What :func:`build_method` may hand a method's constructor, if its signature asks for it.
RUNTIME_ARGS = ("sampler", "runtime", "estimator")


def build_method(cfg: Mapping[str, Any], *, sampler: Mapping[str, Any] | None = None,
                 runtime: Mapping[str, Any] | None = None,
                 estimator: LightFit | None = None, name_suffix: str = "") -> Method:
    """A method from a ``conf/method/*.yaml`` mapping (``_target_``, optional ``name``, the class's options).

    Run-time values go to the constructors that take them: ``sampler`` and ``runtime`` (the diffusion model),
    ``estimator`` (the Lambertian baseline's source-light fit; None: stored light). ``name_suffix`` is appended
    to the name (e.g. to mark ground-truth lighting).
    """
    from hydra.utils import get_class, instantiate

    cfg = dict(cfg)
    if not cfg.get("_target_"):
        raise UserError(f"a method config needs a _target_ class (see conf/method/*.yaml, e.g. method=identity); "
                        f"got keys {sorted(cfg)}")
    missing = [k for k, v in cfg.items() if v == "???"]
    if missing:
        raise UserError(f"method.{missing[0]} must be set (e.g. method.checkpoint=<run>/checkpoints/last.ckpt)")
    try:
        cls = get_class(cfg["_target_"])
    except Exception as e:
        raise UserError(f"method._target_={cfg['_target_']!r} is not an importable class: {e}") from None
    accepted = inspect.signature(cls).parameters
    given = {"sampler": sampler, "runtime": runtime, "estimator": estimator}
    # Run-time objects go to the partial's call, not through OmegaConf (which would turn a LightFit into a config).
    make = instantiate(cfg, _partial_=True, _convert_="all")
    m = make(**{k: given[k] for k in RUNTIME_ARGS if k in accepted and k not in cfg})
    if not isinstance(m, Method):
        raise TypeError(f"{cfg['_target_']} is not a relighting Method (name, needs_light, needs_light_fit, relight)")
    m.name += name_suffix
    return m
