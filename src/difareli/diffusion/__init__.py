"""difareli.diffusion: noise schedule, grids and samplers (both directions)."""

from difareli.diffusion.samplers import SAMPLERS, get_sampler, sampler_options
from difareli.diffusion.schedule import CLEAN, DiffusionSchedule

__all__ = ["CLEAN", "DiffusionSchedule", "SAMPLERS", "get_sampler", "sampler_options"]
