"""What defines a SynthFaces store: :class:`SynthConfig` (recorded in the store header; a resume must match it),
the encodings it writes and the generator's constants. The images: ``synth/subject.py``; the store:
``synth/generator.py``."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from difareli.data.encodings import SHADOW_C_HI, SHADOW_C_LO, SHADOW_S_MIN
from difareli.errors import UserError
from difareli.synth import effects as fx_mod

ENCODINGS = ("image", "light", "shape", "cam", "identity", "shadow", "background", "masks", "shadow_map",
             "shading", "normal", "depth", "face_mask", "light_gt", "shading_gt", "shadow_gt", "shadow_map_gt",
             "shadow_fraction_gt", "shadow_visible_gt", "image_unshadowed_gt")
#: v3 (``inputs=estimated``): the geometry's exact values too.
GEOMETRY_GT = ("shape_gt", "cam_gt", "identity_gt", "masks_gt", "normal_gt", "depth_gt", "face_mask_gt")
#: ``inputs``: what the model-input encodings hold (the exact values are always in the ``*_gt`` ones):
#: estimated = every input (v3), estimated_light = light/shading/shadow/shadow_map only (v2), exact.
INPUTS = ("estimated", "estimated_light", "exact")
#: ``estimation_resolution=0``: the smallest multiple of the stored size >= this (measured: docs/synthfaces_v3.md).
AUTO_ESTIMATION = 128
#: The generator version in the store header (``synthfaces_version``); stores without the key are v1/v2.
VERSION = 3
IDENTITY_DIM = 128  # matches the dlib face descriptor used for real photos
# The c range lives in the schema (shared with targets for relighting); re-exported under short names.
S_MIN, C_LO, C_HI = SHADOW_S_MIN, SHADOW_C_LO, SHADOW_C_HI


def auto_estimation_resolution(resolution: int) -> int:
    """What ``estimation_resolution=0`` resolves to: the smallest multiple of ``resolution`` >= AUTO_ESTIMATION."""
    return -(-AUTO_ESTIMATION // int(resolution)) * int(resolution)


class ConfigError(UserError):
    """An invalid SynthFaces configuration, or one that does not match the existing store."""


@dataclass(frozen=True)
class SynthConfig:
    """What defines a SynthFaces data set (stored in the store header; a resume must match it)."""

    subjects: int
    lights: int
    resolution: int
    seed: int = 0
    light_group_size: int = 2          # subjects sharing the same lights (protocol ii needs >= 2)
    splits: dict = field(default_factory=lambda: {"train": 0.8, "val": 0.1, "test": 0.1})
    shading_region: str = "face"       # "face": R/normal on the BFM face triangles (SPEC 3); "mesh": everywhere
    cam_jitter: float = 0.05           # relative scale jitter; translation jitter is half of it in NDC
    realism: str = "lambertian"        # effects preset (synth/effects.py); "lambertian" = SynthFaces v1 images
    effects: dict = field(default_factory=dict)  # per-effect overrides of the preset (None keeps it)
    inputs: str = "exact"              # INPUTS: what the model inputs hold
    estimation_resolution: int = 0     # inputs=estimated: render this large for the estimators (0: AUTO_ESTIMATION)
    shadow_visible: float = 0.25       # shadow_visible_gt: a pixel losing more than this share of its light
    c_quantile: float = 0.01           # v3 c range: these quantiles of the train split's c (0: min and max)

    def __post_init__(self):
        for key, lo in (("subjects", 1), ("lights", 1), ("resolution", 16), ("light_group_size", 1)):
            if int(getattr(self, key)) < lo:
                raise ConfigError(f"{key}={getattr(self, key)} is invalid: must be >= {lo}")
        object.__setattr__(self, "splits", {str(k): float(v) for k, v in dict(self.splits).items()})
        if self.shading_region not in ("face", "mesh"):
            raise ConfigError(f"shading_region={self.shading_region!r} is invalid: use 'face' or 'mesh'")
        try:  # stored resolved, so the header (and a resume check) names every effect
            object.__setattr__(self, "effects", fx_mod.Effects.resolve(self.realism, self.effects).as_dict())
        except ValueError as e:
            raise ConfigError(str(e)) from None
        if self.inputs not in INPUTS:
            raise ConfigError(f"inputs={self.inputs!r} is invalid: use one of {list(INPUTS)}")
        r = int(self.estimation_resolution) or auto_estimation_resolution(self.resolution)
        object.__setattr__(self, "estimation_resolution", r)  # 0 = auto, stored resolved
        if r < self.resolution or r % self.resolution:
            raise ConfigError(f"estimation_resolution={r} is invalid: 0 or a multiple of resolution={self.resolution}")
        if not 0.0 < float(self.shadow_visible) < 1.0 or not 0.0 <= float(self.c_quantile) < 0.5:
            raise ConfigError(f"shadow_visible={self.shadow_visible} / c_quantile={self.c_quantile} is invalid: use "
                              "shadow_visible in (0, 1) and c_quantile in [0, 0.5)")

    @property
    def fx(self) -> "fx_mod.Effects":
        return fx_mod.Effects(**self.effects)

    @property
    def encodings(self) -> tuple[str, ...]:
        return ENCODINGS + (GEOMETRY_GT if self.inputs == "estimated" else ())

    def header_meta(self) -> dict:
        return {"generator": "synthfaces", "synthfaces_version": VERSION, **asdict(self), "gamma": "none",
                "identity_dim": IDENTITY_DIM, "shadow_c": {"s_min": S_MIN, "c_lo": C_LO, "c_hi": C_HI}}

