"""The preprocessing pipeline: photo -> aligned crop -> only the estimators the requested encodings need ->
one store record per image, a preview per image and a report of every input.

Estimators are plain objects with ``provides``/``requires`` (names of encodings or of intermediate products
such as ``landmarks`` or ``gbuffer``) and ``__call__(ctx, needed) -> dict``; :meth:`Pipeline.plan` runs an
estimator only if something requested depends on one of its outputs.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from difareli.data.encodings import ENCODINGS
from difareli.errors import UserError

from .align import inside_photo
from .quiet import native_logs


REPORT = "preprocess_report.json"
#: Estimator roles of a config's ``estimators`` block, in the order they are instantiated.
ROLES = ("geometry", "masks", "light", "identity", "shadow")
PREVIEWS = "previews"
#: A face whose FFHQ square is smaller than this share of the crop size gets a note (the crop enlarges it).
UPSAMPLE_NOTE = 0.5


_DEFAULT_PIPELINES: dict[tuple, "Pipeline"] = {}


def default_estimators(size: int) -> dict[str, Any]:
    """The ``estimators`` block that ``conf/preprocess.yaml`` composes by default (its ``preprocess/<role>:
    <choice>`` defaults), at crop ``size``, as plain config for callers without Hydra."""
    from difareli.configs import read_yaml

    out = {}
    for entry in read_yaml("", "preprocess")["defaults"]:
        group, choice = next(iter(entry.items())) if isinstance(entry, dict) else (entry, None)
        if group.startswith("preprocess/") and choice is not None:
            cfg = read_yaml(group, choice)
            out[group.split("/", 1)[1]] = {k: (size if v == "${size}" else v) for k, v in cfg.items()}
    return out


def default_pipeline(encodings: Iterable[str], size: int, align: Mapping[str, Any] | None = None) -> "Pipeline":
    """A :class:`Pipeline` of the default estimators (:func:`default_estimators`) for ``encodings`` at ``size`` px,
    built once per process (building one and its first image load mediapipe and dlib: seconds); ``align``: another
    aligner's config in place of the default one."""
    names = tuple(dict.fromkeys(encodings))
    key = (names, int(size), None if align is None else tuple(sorted(align.items())))
    if key not in _DEFAULT_PIPELINES:
        est = default_estimators(size)
        if align is not None:
            est["align"] = dict(align)
        _DEFAULT_PIPELINES[key] = Pipeline.from_config(est, names)
    return _DEFAULT_PIPELINES[key]


@contextlib.contextmanager
def _one_torch_thread():
    """torch's intra-op threads at one while an image is processed (the identity network): between mediapipe's
    graph calls the second OpenMP thread sleeps and is woken per convolution, which on a 2-core VM made the
    descriptor 2-7x slower than the same call in a loop (34 against 62-108 ms per image for the identity stage,
    docs/photos.md); parallelism comes from worker processes (``workers=``), which start with one thread."""
    torch = sys.modules.get("torch")  # not imported yet: nothing to limit (and no reason to import it here)
    before = torch.get_num_threads() if torch is not None else 1
    if before > 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if before > 1:
            torch.set_num_threads(before)


class Pipeline:
    """An aligner plus estimators; ``encodings`` (default: every encoding of the schema a photo can give, i.e.
    all but the synthetic ground truth) decide which estimators run."""

    def __init__(self, aligner, estimators: Sequence[Any], encodings: Iterable[str] | None = None,
                 min_side: int = 64, max_side: int = 8192):
        self.aligner = aligner
        self.estimators = [e for e in estimators if e is not None]
        estimable = tuple(n for n, e in ENCODINGS.items() if not e.oracle)
        self.encodings = estimable if encodings is None else tuple(dict.fromkeys(encodings))
        unknown = [e for e in self.encodings if e not in ENCODINGS]
        if unknown:
            raise UserError(f"unknown encodings {unknown}; the schema has {list(ENCODINGS)}")
        self.min_side, self.max_side = min_side, max_side
        self.steps, self.needed = self.plan(self.encodings)

    @classmethod
    def from_config(cls, estimators: Mapping[str, Any], encodings: Iterable[str] | None = None,
                    **kwargs: Any) -> Pipeline:
        """Instantiate the aligner and the estimators of an ``estimators`` config block (``conf/preprocess/``:
        ``align`` plus one entry per role) into a Pipeline for ``encodings``."""
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        roles = [instantiate(estimators[r]) for r in ROLES if estimators.get(r)]
        pipe = cls(instantiate(estimators["align"]), roles, encodings, **kwargs)
        plain = OmegaConf.to_container(estimators, resolve=True) if OmegaConf.is_config(estimators) else estimators
        # What a worker process needs to build the same pipeline (run(..., workers=n)).
        pipe.config = {"estimators": dict(plain), "encodings": list(pipe.encodings), "kwargs": dict(kwargs)}
        return pipe

    @property
    def size(self) -> int:
        return self.aligner.size

    def plan(self, encodings: Sequence[str]) -> tuple[list[Any], set[str]]:
        """Estimators to run (in dependency order) and every product needed, for ``encodings``."""
        producer = {}
        for est in self.estimators:
            for name in est.provides:
                producer.setdefault(name, est)
        needed, todo, chosen = set(), [n for n in encodings if n != "image"], []
        while todo:
            name = todo.pop()
            if name in needed:
                continue
            needed.add(name)
            if name not in producer:
                raise UserError(f"no configured estimator provides {name!r} (configured: "
                                f"{[type(e).__name__ for e in self.estimators]})")
            est = producer[name]
            if est not in chosen:
                chosen.append(est)
            todo.extend(r for r in est.requires if r != "image")
        steps, done = [], {"image"}
        while len(steps) < len(chosen):  # topological order by requirements
            ready = [e for e in chosen if e not in steps and set(e.requires) <= done]
            if not ready:
                raise UserError("estimator requirements form a cycle or are missing: "
                                f"{[(type(e).__name__, e.requires) for e in chosen if e not in steps]}")
            steps.append(ready[0])
            done |= set(ready[0].provides)
        return steps, needed

    def dims(self) -> dict[str, int]:
        from .geometry import SHAPE_DIM
        from .identity import IDENTITY_DIM

        # S belongs to whichever estimator writes ``shape`` (FaceMesh points: 1404, BFM fit: 53).
        producer = next((e for e in self.estimators if "shape" in e.provides), None)  # as in ``plan``
        shape_dim = getattr(producer, "shape_dim", SHAPE_DIM)
        return {"H": self.size, "W": self.size, "S": shape_dim, "D": IDENTITY_DIM}

    def process(self, rgb: np.ndarray) -> tuple[dict[str, np.ndarray], dict, dict]:
        """Encodings of one decoded photo, its meta, and the full context (for previews)."""
        with self.limits():
            return self.finish(self.prepare(rgb))

    @contextlib.contextmanager
    def limits(self, logs: bool = True):
        """One BLAS and one torch thread while the estimators run (see the helpers), and with ``logs`` the native
        INFO lines dropped (:mod:`.quiet`)."""
        with self._one_blas_thread(), _one_torch_thread(), native_logs() if logs else contextlib.nullcontext():
            yield

    def _one_blas_thread(self):
        """BLAS limited to one thread while the estimators run: their solves are 50x50, where OpenBLAS's second
        thread only waits to be scheduled (on a busy 2-core machine 0.2 ms solves took 80 ms); parallelism comes
        from worker processes (``workers=``), one image each. The controller is built after the first image,
        when every estimator's library is loaded (building one costs ~4 ms)."""
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:  # pragma: no cover - a dependency; without it the estimators still run
            return contextlib.nullcontext()
        ctl = getattr(self, "_blas", None)
        if ctl is None:
            from threadpoolctl import threadpool_limits

            self._blas = "next"
            return threadpool_limits(limits=1, user_api="blas")
        if ctl == "next":
            ctl = self._blas = ThreadpoolController()
        return ctl.limit(limits=1, user_api="blas")

    def prepare(self, rgb: np.ndarray) -> dict:
        """The aligned crop of a photo and what the estimators start from: ``{"ctx", "meta", "seconds"}``
        (raises :class:`~.loading.BadInput` when no face is found). Touches only the aligner, so a reader thread
        can prepare the next photos while :meth:`finish_many` runs the estimators on those before."""
        t0 = time.perf_counter()
        aligned = self.aligner(rgb)
        # The quad unrounded: compositing warps the relit crop back through it (difareli.relight.composite).
        ctx: dict[str, Any] = {"image": aligned["image"], "quad": aligned["quad"], "notes": list(aligned["notes"])}
        # Crop pixels inside the photo (the rest is padding, a reflection): the masks' colour rules read only these.
        ctx["inside"] = inside_photo(aligned["quad"], aligned["image"].shape[0], rgb.shape[:2])
        # The alignment pass's FaceMesh landmarks (original pixels), for estimators that can reuse them.
        ctx["alignment_landmarks"] = aligned.get("landmarks")
        meta = {"faces": aligned["faces"], "box": aligned["box"], "quad": np.round(aligned["quad"], 2).tolist()}
        side = float(np.linalg.norm(np.asarray(aligned["quad"])[3] - np.asarray(aligned["quad"])[0]))
        if side < UPSAMPLE_NOTE * self.size:  # a small face: the crop is an enlargement, say so (report, console)
            ctx["notes"].append(f"small face: the crop's square is {side:.0f} px in the photo, enlarged "
                                f"{self.size / max(side, 1e-6):.1f}x to {self.size} px (soft detail; a larger face "
                                "or a smaller size= is sharper)")
        return {"ctx": ctx, "meta": meta, "seconds": {"align": time.perf_counter() - t0}}

    def finish(self, prepared: dict) -> tuple[dict[str, np.ndarray], dict, dict]:
        """The estimators, one after the other, on what :meth:`prepare` gave for one photo: (arrays, meta, ctx)."""
        return self._result(self.run_steps(prepared, self.steps))

    def run_steps(self, prepared: dict, steps: Sequence[Any]) -> dict:
        """``steps`` (a part of :attr:`steps`, in order) on one prepared photo, in place; their exceptions propagate."""
        ctx, timings = prepared["ctx"], prepared["seconds"]
        for est in steps:
            t0 = time.perf_counter()
            out = est(ctx, self.needed)
            timings[type(est).__name__] = time.perf_counter() - t0
            ctx["notes"] += out.pop("notes", [])
            ctx.update(out)
        return prepared

    @property
    def image_steps(self) -> list[Any]:
        """The leading :attr:`steps` that read only the crop (the geometry: FaceMesh on the crop, the BFM fit, the
        G-buffer): :mod:`.stream`'s reader thread runs them with the alignment."""
        for i, est in enumerate(self.steps):
            if not set(est.requires) <= {"image"}:
                return self.steps[:i]
        return list(self.steps)

    def finish_many(self, prepared: Sequence[dict | Exception], start: int = 0
                    ) -> list[tuple[dict, dict, dict] | Exception]:
        """:meth:`finish` of several prepared photos (an exception in the list stays in its place) from step
        ``start`` on: estimator by estimator, one ``batch`` call for those that have one, its time shared equally by
        the photos."""
        out: list = list(prepared)
        for est in self.steps[start:]:
            live = [i for i, p in enumerate(out) if not isinstance(p, Exception)]
            if not live:
                break
            name, t0 = type(est).__name__, time.perf_counter()
            if hasattr(est, "batch"):
                results = est.batch([out[i]["ctx"] for i in live], self.needed)
                share = (time.perf_counter() - t0) / len(live)
                for i, res in zip(live, results, strict=True):
                    out[i] = self._merge(out[i], name, res, share)
                continue
            for i in live:
                t0 = time.perf_counter()
                try:
                    res = est(out[i]["ctx"], self.needed)
                except Exception as e:  # noqa: BLE001 - one photo's failure is its own entry
                    res = e
                out[i] = self._merge(out[i], name, res, time.perf_counter() - t0)
        return [p if isinstance(p, Exception) else self._result(p) for p in out]

    @staticmethod
    def _merge(prepared: dict, name: str, res: dict | Exception, seconds: float) -> dict | Exception:
        if isinstance(res, Exception):
            return res
        prepared["seconds"][name] = seconds
        prepared["ctx"]["notes"] += res.pop("notes", [])
        prepared["ctx"].update(res)
        return prepared

    def _result(self, prepared: dict) -> tuple[dict[str, np.ndarray], dict, dict]:
        ctx, meta = prepared["ctx"], prepared["meta"]
        meta["seconds"] = {k: round(v, 4) for k, v in prepared["seconds"].items()}
        for key in ("reprojection_px", "bfm_fit", "light_fit", "shadow_info"):
            if key in ctx:
                meta[key] = ctx[key]
        arrays = {name: ctx[name] for name in self.encodings}
        return arrays, meta, ctx
