"""difareli.diffusion: noise schedule, grids and samplers (both directions), configured through SamplerSpec."""

from difareli.diffusion.samplers import SAMPLERS
from difareli.diffusion.schedule import CLEAN, DiffusionSchedule
from difareli.diffusion.spec import PRESETS, SamplerConfigError, SamplerSpec, as_spec, signature_options

__all__ = ["CLEAN", "DiffusionSchedule", "PRESETS", "SAMPLERS", "SamplerConfigError", "SamplerSpec", "as_spec",
           "signature_options"]
