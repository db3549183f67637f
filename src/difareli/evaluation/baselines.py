"""Relighting methods behind one interface, for benchmarks: classical baselines and the diffusion model.

A :class:`Method` has a ``name``, ``relight(store, source_id, target_light, target_shadow, target_id=None)
-> uint8 HxWx3`` and two declarations the benchmark reads: ``needs_light`` (it uses the target light, so a run
under ground-truth lights is marked) and ``needs_light_fit`` (it fits a source light with ``estimator``, whose
error the benchmark reports). ``target_id`` (the ground-truth record) is only for the oracle. Methods are built
from ``conf/method/*.yaml`` ``_target_`` configs by :func:`build_method`.

Target (and source) lights "as a user gets them" come from :class:`difareli.lighting.light_fit.LightFit`.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Protocol, runtime_checkable

import numpy as np

from difareli.lighting import sh
from difareli.lighting.light_fit import LightFit, face_normals
from difareli.data.store import EncodingStore
from difareli.errors import UserError


def exact_light_name(store: EncodingStore) -> str:
    """The encoding holding a record's exact light: ``light_gt`` in SynthFaces v2 stores, else ``light``."""
    return "light_gt" if store.available("light_gt") else "light"


def irradiance_error(estimate: np.ndarray, truth: np.ndarray, normals: np.ndarray,
                     mask: np.ndarray) -> tuple[float, float]:
    """Relative irradiance error ``|E_est - E_gt| / |E_gt|`` over the masked pixels (all channels), and the
    same after the best scalar scale of ``E_est`` (the part an albedo-scale error cannot explain)."""
    n = np.asarray(normals, dtype=np.float64)[mask]
    e, g = sh.irradiance(estimate, n), sh.irradiance(truth, n)
    norm = float(np.linalg.norm(g))
    if norm == 0 or n.size == 0:
        return math.nan, math.nan
    k = float((e * g).sum() / max((e * e).sum(), 1e-30))
    return float(np.linalg.norm(e - g)) / norm, float(np.linalg.norm(k * e - g)) / norm


# ------------------------------------------------------------------------------------------------ methods


@runtime_checkable
class Method(Protocol):
    """What the benchmark runs: a name and one relit uint8 image per (source record, target light)."""

    name: str
    needs_light: bool
    needs_light_fit: bool

    def relight(self, store: EncodingStore, source_id: str, target_light: np.ndarray,
                target_shadow: float | None = None, target_id: str | None = None) -> np.ndarray: ...


class Identity:
    """The input returned unchanged: the score of doing nothing."""

    needs_light, needs_light_fit = False, False

    def __init__(self, name: str | None = None):
        self.name = name or "identity"

    def relight(self, store, source_id, target_light, target_shadow=None, target_id=None) -> np.ndarray:
        return np.array(store.read(source_id, ["image"])["image"])


class Oracle:
    """The ground-truth render of the pair: scores exactly 0, a check on the metric pipeline."""

    needs_light, needs_light_fit = False, False

    def __init__(self, name: str | None = None):
        self.name = name or "oracle"

    def relight(self, store, source_id, target_light, target_shadow=None, target_id=None) -> np.ndarray:
        if target_id is None:
            raise UserError("the oracle needs the ground-truth record (target_id)")
        return np.array(store.read(target_id, ["image"])["image"])


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

    def source_light(self, store: EncodingStore, source_id: str) -> np.ndarray:
        """The fitted source light, or (no estimator: the oracle) the exact one: ``light_gt`` where the store
        has it (SynthFaces v2, whose ``light`` is itself estimated), else ``light``."""
        if self.estimator is not None:
            return self.estimator.from_store(store, source_id)
        name = exact_light_name(store)
        return np.asarray(store.read(source_id, [name])[name], dtype=np.float64)

    def relight(self, store, source_id, target_light, target_shadow=None, target_id=None,
                source_light: np.ndarray | None = None) -> np.ndarray:
        a = store.read(source_id, ["image", "normal"])
        light_s = self.source_light(store, source_id) if source_light is None else source_light
        return ratio_relight(a["image"], a["normal"], light_s, target_light, self.min_shading)


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

    The input is inverted with its own stored encodings (once per record, cached) and decoded under the
    target light and shadow strength. Default name: ``<model>/<sampler>-<steps>``, e.g. ``difareli_pp/ddim-20``.
    """

    needs_light, needs_light_fit = True, False

    def __init__(self, checkpoint: str | None = None, sampler: Mapping[str, Any] | None = None, *,
                 name: str | None = None, runtime: Mapping[str, Any] | None = None, mean_matching: bool = True, batch_size: int = 16,
                 model_name: str | None = None):
        from difareli.relight.relightable import OnePassRelightable
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
        from difareli.data import encodings

        names = encodings.light_dependent(self.relighter.model_inputs)
        maps = "re-rendered on the input's geometry under the target light: " + ", ".join(names)
        if "shadow_map" in names:
            maps += " (shadow map ray-marched on the input's depth; inversion uses the input's own map)"
        return maps

    def check_store(self, store) -> None:
        """The checkpoint reads this store's encodings (else one line naming both; before any pair is relit)."""
        from difareli.data.inputs import check_store_fits

        check_store_fits(self.relighter.config, store, self.relighter.checkpoint)

    def relight(self, store, source_id, target_light, target_shadow=None, target_id=None) -> np.ndarray:
        from difareli.relight.targets import Targets

        source = self.relighter.source(store, source_id)
        return self.relighter.relight(source, Targets.of([target_light], [target_shadow], source.what))[0]


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
    import inspect

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
