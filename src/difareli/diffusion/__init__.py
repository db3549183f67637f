"""difareli.diffusion: noise schedule, grids and samplers (both directions), configured through SamplerSpec."""

from difareli.diffusion.samplers import SAMPLERS
from difareli.diffusion.schedule import CLEAN, DiffusionSchedule
from difareli.diffusion.spec import (DEFAULT_SAMPLER, PRESETS, SamplerConfigError, SamplerSpec, as_spec,
                                     signature_options)

__all__ = ["CLEAN", "DEFAULT_SAMPLER", "DiffusionSchedule", "PRESETS", "SAMPLERS", "SamplerConfigError", "SamplerSpec",
           "as_spec", "signature_options"]
