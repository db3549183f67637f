"""The encodings schema: every per-image encoding's name, shape, dtype and meaning (SPEC 2).

One place defines what an encoding is. The store (``difareli.data.store``) validates records against it, the
DataModule loads exactly the encodings a model variant declares, and estimators / the SynthFaces generator
produce them. Shapes use symbols: ``H``/``W`` image size, ``S`` shape-vector length, ``D`` identity length,
resolved per data set and recorded in the store's header.

Conventions (docs/architecture.md has the full list):
- camera space is right-handed: x right, y up, z toward the viewer; normals are unit vectors in it;
- ``light`` is 9x3 SH in DECA's basis order and constants (``difareli.lighting.sh``);
- images are uint8 RGB HxWx3; float maps are float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import math
from typing import Any, Mapping

import numpy as np

from difareli.errors import MissingError, UserError

SCHEMA_VERSION = 2

#: The ``shadow`` logit c and the ``shadow_map`` scaling: ``shadow_map = binary cast map * normalise_c(c)``
#: with a fixed range, so records can be written one at a time and stores compared. ``c = logit(s)`` where s
#: is the fraction of the foreground's light removed by cast shadows (SynthFaces' definition), clipped to
#: [S_MIN, 1 - S_MIN]: C_LO means no visible cast shadow, C_HI a quarter of the light removed.
SHADOW_S_MIN = 1e-3
SHADOW_C_LO = math.log(SHADOW_S_MIN / (1 - SHADOW_S_MIN))
SHADOW_C_HI = math.log(0.25 / 0.75)


#: Store-header key (and record-array key, for re-rendering target maps) of a store's own c range: SynthFaces v3
#: stores normalise c by their training split's (c_min, c_max), the authors' recipe; stores without it use the
#: fixed range above (v1/v2, photos).
C_RANGE_KEY = "shadow_c_range"


def normalise_c(c, c_range=None):
    """Map a shadow logit c to [0, 1]: ``(c - lo) / (hi - lo)`` clipped, with ``c_range = (lo, hi)`` (a store's
    training-split range, :func:`store_c_range`) or, when None, the fixed [SHADOW_C_LO, SHADOW_C_HI]."""
    lo, hi = (SHADOW_C_LO, SHADOW_C_HI) if c_range is None else (float(c_range[0]), float(c_range[1]))
    if not hi > lo:
        raise UserError(f"shadow c range ({lo}, {hi}) is empty: c_max must exceed c_min")
    return np.clip((np.asarray(c, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)


def denormalise_c(strength, c_range=None) -> float:
    """A shadow strength in [0, 1] (clipped) -> the logit c, the inverse of :func:`normalise_c` on its range."""
    lo, hi = (SHADOW_C_LO, SHADOW_C_HI) if c_range is None else (float(c_range[0]), float(c_range[1]))
    return lo + float(np.clip(strength, 0.0, 1.0)) * (hi - lo)


def store_c_range(meta: Mapping[str, Any] | None) -> tuple[float, float] | None:
    """The c range a store's header records (``meta[C_RANGE_KEY]``: ``{"lo", "hi", ...}``), or None (fixed range).
    Also accepts a record's arrays, where readers put it as a 2-vector under the same key."""
    value = None if meta is None else meta.get(C_RANGE_KEY)
    if value is None or (isinstance(value, Mapping) and value.get("lo") is None):
        return None
    if isinstance(value, Mapping):
        return float(value["lo"]), float(value["hi"])
    lo, hi = np.asarray(value, dtype=np.float64).reshape(-1)[:2]
    return float(lo), float(hi)


def c_range_arrays(meta: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
    """``{C_RANGE_KEY: (lo, hi)}`` to put beside a record's arrays when a store header records a c range (target
    maps then scale by the store's range, as its stored maps do), else ``{}`` (the fixed range)."""
    r = store_c_range(meta)
    return {} if r is None else {C_RANGE_KEY: np.array(r, dtype=np.float64)}


def known_normals(normal) -> np.ndarray:
    """Where a stored ``normal`` map holds a normal (unit vectors on the mesh, 0 off it): ``|n| > 0.5``."""
    return np.linalg.norm(np.asarray(normal, dtype=np.float64), axis=-1) > 0.5


def shadow_logit(arrays: Mapping[str, Any], name: str = "shadow") -> float | None:
    """A record's scalar shadow logit c (its ``shadow`` encoding, stored as shape (1,)), or ``None`` without it."""
    return float(np.asarray(arrays[name]).reshape(-1)[0]) if name in arrays else None

#: The 14-part segmentation scheme (SPEC 7; CelebAMask-HQ / BiSeNet classes merged to what SynthFaces
#: geometry and the real-photo estimators can both produce: ears and eyeglasses are folded into skin).
MASK_PARTS: tuple[str, ...] = (
    "background",
    "skin",
    "l_brow",
    "r_brow",
    "l_eye",
    "r_eye",
    "nose",
    "u_lip",
    "l_lip",
    "mouth",
    "neck",
    "clothes",
    "hair",
    "hat",
)
NUM_MASK_PARTS = len(MASK_PARTS)
PART_INDEX = {name: i for i, name in enumerate(MASK_PARTS)}
#: Parts that make up the "face region" used by metrics (SPEC 11) and the ``face_mask`` encoding.
FACE_PARTS: tuple[str, ...] = ("skin", "l_brow", "r_brow", "l_eye", "r_eye", "nose", "u_lip", "l_lip", "mouth")
#: Parts that DiFaReli's ``background`` encoding masks out (face, hair, neck; SPEC 2).
FOREGROUND_PARTS: tuple[str, ...] = FACE_PARTS + ("neck", "hair")


@dataclass(frozen=True)
class Encoding:
    """One per-image encoding: its stored shape (symbolic), dtype and meaning, how it becomes a network tensor,
    and, for encodings that depend on the light, how it is re-rendered under a target light.

    ``onehot``: number of classes when a label map is fed to a network one-hot (0: fed as values);
    ``rerender``: the kind of re-render that computes the encoding under a target light (``light``, ``shadow``,
    ``shadow_map`` or ``shading``: a key of ``difareli.render.retarget.RENDERERS``, the renderer above this schema,
    which takes it from here); ``needs``: the encodings that re-render reads besides the light; ``oracle``: a
    ground-truth value of synthetic data, never estimated from a photo. An encoding is light-dependent exactly
    when it has a ``rerender`` (this table is the only list of them).
    """

    name: str
    shape: tuple[int | str, ...]
    dtype: str
    meaning: str
    spatial: bool = False
    onehot: int = 0
    rerender: str | None = None
    needs: tuple[str, ...] = ()
    oracle: bool = False  # an exact value only a renderer knows (SynthFaces' *_gt): no estimator produces it

    @property
    def light_dependent(self) -> bool:
        return self.rerender is not None

    def resolve(self, dims: dict[str, int]) -> tuple[int, ...]:
        """Concrete shape given the data set's dimensions (``H``, ``W``, ``S``, ``D``)."""
        try:
            return tuple(d if isinstance(d, int) else int(dims[d]) for d in self.shape)
        except KeyError as e:
            raise MissingError(f"encoding {self.name!r} needs dimension {e.args[0]!r}; known: {sorted(dims)}") from None

    def channels(self, dims: dict[str, int]) -> int:
        """Channels (spatial) or features (non-spatial) once prepared as a network input."""
        if self.onehot:
            return self.onehot
        shape = self.resolve(dims)
        if self.spatial:
            return shape[2] if len(shape) == 3 else 1
        return int(np.prod(shape))

    def to_tensor(self, array):
        """The network input: spatial ``[C, H, W]`` float (uint8 images in [-1, 1], label maps one-hot, float
        maps unchanged: the shading reference stays unclipped, SPEC 3), non-spatial a flat float ``[D]``."""
        import torch  # the schema is imported by light processes (synth workers) that need no torch

        a = np.asarray(array)
        if not self.spatial:
            return torch.from_numpy(np.asarray(a, dtype=np.float32).reshape(-1).copy())
        if self.onehot:
            labels = torch.from_numpy(a.astype(np.int64))
            return torch.nn.functional.one_hot(labels, self.onehot).permute(2, 0, 1).float()
        t = torch.from_numpy(np.array(a))
        t = t.float() / 127.5 - 1.0 if a.dtype == np.uint8 else t.float()
        return t.permute(2, 0, 1) if t.ndim == 3 else t[None]

    def validate(self, array: np.ndarray, dims: dict[str, int]) -> np.ndarray:
        """Return ``array`` cast to the schema dtype, or raise naming the encoding and the mismatch."""
        arr = np.asarray(array)
        want = self.resolve(dims)
        if arr.shape != want:
            raise UserError(f"encoding {self.name!r}: shape {arr.shape} does not match schema {want}")
        if not np.can_cast(arr.dtype, self.dtype, casting="same_kind") and arr.dtype != np.bool_:
            raise UserError(f"encoding {self.name!r}: dtype {arr.dtype} cannot be stored as {self.dtype}")
        if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
            raise UserError(f"encoding {self.name!r}: contains NaN or Inf")
        return arr.astype(self.dtype, copy=False)


_ENCODINGS = (
    Encoding("image", ("H", "W", 3), "uint8", "the face photo, RGB", spatial=True),
    Encoding("light", (9, 3), "float32", "2nd-order SH lighting, DECA basis order and constants (sh.py)",
             rerender="light"),
    Encoding("shape", ("S",), "float32", "face shape / expression / pose parameters (source-specific length S)"),
    Encoding("cam", (3,), "float32", "orthographic camera (scale, tx, ty), DECA convention"),
    Encoding("identity", ("D",), "float32", "identity embedding (length D)"),
    Encoding("shadow", (1,), "float32", "cast-shadow intensity c, a logit",
             rerender="shadow"),
    Encoding("background", ("H", "W", 3), "uint8", "image with face, hair and neck pixels set to 0", spatial=True),
    Encoding("masks", ("H", "W"), "uint8", "part label per pixel, indices into MASK_PARTS", spatial=True,
             onehot=NUM_MASK_PARTS),
    Encoding("shadow_map", ("H", "W"), "float32", "binary cast-shadow map times normalised c", spatial=True,
             rerender="shadow_map", needs=("depth", "normal", "cam", "shadow")),
    Encoding("shading", ("H", "W", 3), "float32", "shading reference R = 0.7 * SH irradiance, unclipped", spatial=True,
             rerender="shading", needs=("normal",)),
    Encoding("normal", ("H", "W", 3), "float32", "camera-space unit normal of the face mesh, 0 off-mesh", spatial=True),
    Encoding("depth", ("H", "W"), "float32", "camera-space z of the face mesh (toward the viewer), 0 off-mesh; "
             "used to ray-march target shadow maps", spatial=True),
    Encoding("face_mask", ("H", "W"), "bool", "face region (FACE_PARTS), used by metrics", spatial=True),
    # SynthFaces v2: the exact values of the model inputs, which hold estimated ones in v2 stores (oracle studies).
    # As model inputs (oracle studies) they re-render under a target light exactly like their estimated twins.
    Encoding("light_gt", (9, 3), "float32", "exact SH light (ambient + every sun), as `light`",
             rerender="light", oracle=True),
    Encoding("shading_gt", ("H", "W", 3), "float32", "shading reference of light_gt, as `shading`", spatial=True,
             rerender="shading", needs=("normal",), oracle=True),
    Encoding("shadow_gt", (1,), "float32", "exact cast-shadow logit c (all suns), as `shadow`",
             rerender="shadow", oracle=True),
    Encoding("shadow_map_gt", ("H", "W"), "float32", "exact cast-shadow map (union over suns) times "
             "normalised shadow_gt, as `shadow_map`", spatial=True,
             rerender="shadow_map", needs=("depth", "normal", "cam", "shadow"),
             oracle=True),
    # SynthFaces v3 (docs/synthfaces_v3.md): geometry is estimated too; the renderer's values for oracle studies.
    Encoding("shape_gt", ("S",), "float32", "exact BFM shape / expression / pose parameters, as `shape`", oracle=True),
    Encoding("cam_gt", (3,), "float32", "exact camera, as `cam`", oracle=True),
    Encoding("identity_gt", ("D",), "float32", "the subject's identity vector, as `identity`", oracle=True),
    Encoding("masks_gt", ("H", "W"), "uint8", "exact part labels, as `masks`", spatial=True, onehot=NUM_MASK_PARTS,
             oracle=True),
    Encoding("normal_gt", ("H", "W", 3), "float32", "exact normal, as `normal`", spatial=True, oracle=True),
    Encoding("depth_gt", ("H", "W"), "float32", "exact whole-mesh depth, as `depth`", spatial=True, oracle=True),
    Encoding("face_mask_gt", ("H", "W"), "bool", "exact face region, as `face_mask`", spatial=True, oracle=True),
    # SynthFaces v3: what "visibly shadowed" means, for scoring shadow maps.
    Encoding("shadow_fraction_gt", ("H", "W"), "float32", "share of each pixel's unshadowed light (every sun and "
             "the ambient) that cast shadows remove, 0 off the mesh", spatial=True, oracle=True),
    Encoding("shadow_visible_gt", ("H", "W"), "bool", "visibly shadowed: shadow_fraction_gt above the store's "
             "threshold, or in the key sun's own cast shadow", spatial=True, oracle=True),
    Encoding("image_unshadowed_gt", ("H", "W", 3), "uint8", "the image under the same light with no cast shadow "
             "(every sun reaches every point)", spatial=True, oracle=True),
)

#: All encodings by name, in schema order.
ENCODINGS: dict[str, Encoding] = {e.name: e for e in _ENCODINGS}

#: The shape symbols of the encodings our producers write: ``S`` = 53 BFM parameters (SynthFaces and the
#: FaceMesh/BFM fit of ``difareli-preprocess``), ``D`` = 128 (dlib's identity descriptor). A store records its own.
PRODUCER_DIMS: dict[str, int] = {"S": 53, "D": 128}


def channels(name: str, dims: dict[str, int]) -> int:
    """Number of network channels/features of an encoding once prepared (masks are one-hot over parts)."""
    return get(name).channels(dims)


def total_channels(names, dims: dict[str, int]) -> int:
    """Channels of several encodings concatenated (a spatial block or the non-spatial vector)."""
    return sum(channels(n, dims) for n in names)


def light_dependent(names=None) -> list[str]:
    """The encodings (of ``names``, default all) that change with the light, in the given order."""
    return [n for n in (ENCODINGS if names is None else names) if get(n).light_dependent]


def rerender_needs(names) -> list[str]:
    """Encodings that re-rendering the light-dependent ones of ``names`` reads (besides themselves)."""
    return list(dict.fromkeys(x for n in names for x in get(n).needs))


def get(name: str) -> Encoding:
    """Look up an encoding by name, with an error that lists the valid names."""
    try:
        return ENCODINGS[name]
    except KeyError:
        raise MissingError(f"unknown encoding {name!r}; the schema (v{SCHEMA_VERSION}) has: "
                           f"{', '.join(ENCODINGS)}") from None
