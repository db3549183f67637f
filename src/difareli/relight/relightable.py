"""What a relighting model offers (SPEC 5): the interfaces the relighting core, the benchmarks and the Lightning
modules share. Low in the house so the modules that implement them can check them with ``isinstance``.

A model offers :class:`Relightable`: the encodings it consumes (``spatial_inputs``, ``nonspatial_inputs``) and
``condition(spatial, nonspatial)``, run once per condition. A diffusion model adds ``denoiser(cond)`` and
``schedule`` (:class:`DiffusionRelightable`); a one-pass model adds ``relight_once(x0, source_cond, target_cond,
runtime=None)`` (:class:`OnePassRelightable`).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from torch import Tensor


@runtime_checkable
class Relightable(Protocol):
    """What every relighting model offers: the encodings it consumes and a condition prepared from them."""

    spatial_inputs: list[str]
    nonspatial_inputs: list[str]

    def condition(self, spatial: Tensor | None, nonspatial: Tensor | None) -> Any: ...


@runtime_checkable
class DiffusionRelightable(Relightable, Protocol):
    """A conditional diffusion model: ``eps = denoiser(cond)(x_t, t)`` on ``schedule``."""

    schedule: Any

    def denoiser(self, cond: Any): ...


@runtime_checkable
class OnePassRelightable(Relightable, Protocol):
    """A model that relights in one network pass (the single-shot student)."""

    def relight_once(self, x0: Tensor, source: Any, target: Any, runtime: Any = None) -> Tensor:
        """The relit images; ``runtime`` is optional: a model whose ``relight_once`` does not take it is run under
        the runtime's autocast instead (``relight_core``)."""
        ...


def model_inputs(model: Relightable) -> list[str]:
    """Every encoding the model consumes, spatial then non-spatial."""
    return [*model.spatial_inputs, *model.nonspatial_inputs]
