"""Per-subject appearance for SynthFaces: albedo (skin tone, part colours, procedural texture) and backgrounds.

Colours are display-space reflectances in [0, 1]; the generator multiplies them by irradiance without any
gamma (see ``subject.py``). Texture noise is a hashed value noise evaluated at the 3D surface points of
the G-buffer, so it sticks to the surface and is identical under every light of a subject; it depends only
on the subject's noise seed, not on the resolution.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np

from difareli.lighting.albedo import MONK_SCALE, SKIN_ALBEDO_SCALE
from difareli.data.encodings import PART_INDEX

HAIR_COLOURS = {  # base colour, sampling weight
    "black": ([0.05, 0.04, 0.035], 0.30), "dark_brown": ([0.16, 0.10, 0.06], 0.25),
    "brown": ([0.32, 0.21, 0.12], 0.15), "auburn": ([0.45, 0.20, 0.09], 0.07),
    "blond": ([0.72, 0.58, 0.36], 0.10), "grey": ([0.55, 0.54, 0.52], 0.07),
    "white": ([0.85, 0.84, 0.80], 0.03), "dyed": (None, 0.03),
}
IRIS_COLOURS = np.array([[0.25, 0.14, 0.07], [0.12, 0.07, 0.04], [0.30, 0.45, 0.60], [0.30, 0.42, 0.25],
                         [0.42, 0.44, 0.46]])
IRIS_WEIGHTS = np.array([0.40, 0.25, 0.15, 0.10, 0.10])
SCLERA = np.array([0.78, 0.75, 0.72])


@dataclass(frozen=True)
class Appearance:
    """Everything needed to colour one subject's surface."""

    skin_tone: float                      # 0 = lightest, 1 = darkest (position on MONK_SCALE)
    colours: dict[str, np.ndarray]        # MASK_PARTS name -> base RGB albedo
    iris: np.ndarray
    noise_seed: int
    blotch: float                         # relative amplitude of low-frequency skin blotches
    grain: float                          # relative amplitude of fine noise
    clothes_pattern: str                  # "solid" | "stripes" | "noise"
    stripe_freq: float
    hair_name: str = ""
    extra: dict = field(default_factory=dict)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def skin_colour(tone: float, rng: np.random.Generator) -> np.ndarray:
    """Albedo for ``tone`` in [0, 1] (light to dark), with small per-subject hue/redness jitter."""
    x = np.clip(tone, 0, 1) * (len(MONK_SCALE) - 1)
    i = min(int(x), len(MONK_SCALE) - 2)
    c = MONK_SCALE[i] * (1 - (x - i)) + MONK_SCALE[i + 1] * (x - i)
    c = c * np.exp(rng.normal(0, [0.03, 0.04, 0.05]))  # redder / yellower / paler undertones
    return np.clip(c * SKIN_ALBEDO_SCALE, 0.02, 0.95)


def sample_appearance(rng: np.random.Generator) -> Appearance:
    """Draw one subject's appearance: skin tone uniform over the whole scale, part colours around it."""
    tone = rng.uniform()
    skin = skin_colour(tone, rng)
    names = list(HAIR_COLOURS)
    p = np.array([HAIR_COLOURS[n][1] for n in names])
    hair_name = names[rng.choice(len(names), p=p / p.sum())]
    base = HAIR_COLOURS[hair_name][0]
    hair = _hsv(rng.uniform(), rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.7)) if base is None else np.array(base)
    hair = np.clip(hair * np.exp(rng.normal(0, 0.1, 3)), 0.01, 0.95)
    lips = skin * np.array([1.0, 0.62, 0.62]) * rng.uniform(0.75, 0.95)
    if rng.uniform() < 0.2:  # lipstick
        lips = _hsv(rng.uniform(-0.05, 0.03), rng.uniform(0.5, 0.85), rng.uniform(0.35, 0.7))
    clothes = _hsv(rng.uniform(), rng.uniform(0, 0.8), rng.uniform(0.05, 0.9))
    hat = _hsv(rng.uniform(), rng.uniform(0, 0.8), rng.uniform(0.05, 0.9))
    colours = {
        "skin": skin,
        "nose": skin * np.array([1.02, 0.97, 0.97]),
        "neck": skin * 0.95,
        "l_brow": 0.7 * hair + 0.3 * skin * 0.6,
        "r_brow": 0.7 * hair + 0.3 * skin * 0.6,
        "u_lip": lips * 0.92,
        "l_lip": lips,
        "mouth": np.array([0.25, 0.07, 0.07]),
        "hair": hair,
        "clothes": clothes,
        "hat": hat,
        "l_eye": SCLERA, "r_eye": SCLERA,
    }
    iris = IRIS_COLOURS[rng.choice(len(IRIS_COLOURS), p=IRIS_WEIGHTS)]
    return Appearance(
        skin_tone=float(tone), colours={k: np.clip(v, 0, 1) for k, v in colours.items()}, iris=iris,
        noise_seed=int(rng.integers(2**31)), blotch=float(rng.uniform(0.03, 0.12)),
        grain=float(rng.uniform(0.01, 0.05)), clothes_pattern=str(rng.choice(["solid", "stripes", "noise"])),
        stripe_freq=float(rng.uniform(6, 20)), hair_name=hair_name,
    )


# ----------------------------------------------------------------------------------------- noise
def _hash01(ix, iy, iz, seed: int) -> np.ndarray:
    # Integer lattice hash -> [0, 1); uint64 arithmetic wraps, which is what a hash wants.
    h = (ix.astype(np.uint64) * np.uint64(0x9E3779B1) ^ iy.astype(np.uint64) * np.uint64(0x85EBCA77)
         ^ iz.astype(np.uint64) * np.uint64(0xC2B2AE3D) ^ np.uint64(seed & 0xFFFFFFFF) * np.uint64(0x27D4EB2F))
    h ^= h >> np.uint64(15)
    h *= np.uint64(0x2C1B3C6D)
    h ^= h >> np.uint64(12)
    h *= np.uint64(0x297A2D39)
    h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [-1, 1] at points ``p (..., 3)`` (one lattice cell = unit length)."""
    p = np.asarray(p, dtype=np.float64)
    i0 = np.floor(p)
    f = p - i0
    w = f * f * (3 - 2 * f)  # smoothstep: C1-continuous across cells
    i0 = i0.astype(np.int64)
    out = np.zeros(p.shape[:-1])
    for dx in (0, 1):
        wx = w[..., 0] if dx else 1 - w[..., 0]
        for dy in (0, 1):
            wy = w[..., 1] if dy else 1 - w[..., 1]
            for dz in (0, 1):
                wz = w[..., 2] if dz else 1 - w[..., 2]
                out += wx * wy * wz * _hash01(i0[..., 0] + dx, i0[..., 1] + dy, i0[..., 2] + dz, seed)
    return 2 * out - 1


def fbm(p: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, roughly in [-1, 1]."""
    total, amp, norm = 0.0, 1.0, 0.0
    for o in range(octaves):
        total = total + amp * value_noise(p * (2.0**o), seed + 7919 * o)
        norm += amp
        amp *= 0.5
    return total / norm


# ----------------------------------------------------------------------------------------- albedo
def albedo_image(app: Appearance, label: np.ndarray, points: np.ndarray, hit: np.ndarray, size: float) -> np.ndarray:
    """Per-pixel albedo ``(H, W, 3)`` float32 in [0, 1] from the label map and the 3D surface ``points``
    of the hit pixels; 0 where ``hit`` is False. ``size`` is the head size (noise is relative to it)."""
    H, W = label.shape
    out = np.zeros((H, W, 3), dtype=np.float64)
    idx = np.flatnonzero(hit)
    if idx.size == 0:
        return out.astype(np.float32)
    lab = label.reshape(-1)[idx]
    q = points.reshape(-1, 3)[idx] / float(size)
    names = list(PART_INDEX)
    base = np.stack([app.colours.get(n, np.zeros(3)) for n in names])[lab]
    blotch = fbm(q * 4.0, app.noise_seed, octaves=2)
    grain = value_noise(q * 45.0, app.noise_seed + 1)
    mod = 1 + app.blotch * blotch + app.grain * grain
    # Hair: streaks along the vertical, i.e. noise stretched across x/z and slow along y.
    is_hair = np.isin(lab, [PART_INDEX["hair"], PART_INDEX["l_brow"], PART_INDEX["r_brow"]])
    if is_hair.any():
        streak = value_noise(q[is_hair] * np.array([60.0, 6.0, 60.0]), app.noise_seed + 2)
        mod[is_hair] = 1 + 0.25 * streak + 0.1 * blotch[is_hair]
    is_clothes = lab == PART_INDEX["clothes"]
    if is_clothes.any():
        qc = q[is_clothes]
        if app.clothes_pattern == "stripes":
            pat = 0.75 + 0.25 * np.sign(np.sin(qc[:, 1] * app.stripe_freq))
        elif app.clothes_pattern == "noise":
            pat = 1 + 0.3 * fbm(qc * 8.0, app.noise_seed + 3)
        else:
            pat = 1 + 0.05 * grain[is_clothes]
        mod[is_clothes] = pat
    rgb = base * mod[:, None]
    for part in ("l_eye", "r_eye"):
        sel = lab == PART_INDEX[part]
        if sel.sum() >= 2:
            # Iris and pupil: discs at the eye region's centre, radii relative to its width.
            xy = q[sel, :2]
            c = xy.mean(0)
            r = np.linalg.norm(xy - c, axis=1) / max(np.ptp(xy[:, 0]) / 2, 1e-6)
            eye = np.where((r < 0.5)[:, None], app.iris[None, :], SCLERA[None, :])
            eye = np.where((r < 0.2)[:, None], 0.02, eye)
            rgb[sel] = eye
    out.reshape(-1, 3)[idx] = np.clip(rgb, 0, 1)
    return out.astype(np.float32)


# ----------------------------------------------------------------------------------------- backgrounds
BACKGROUND_KINDS = ("solid", "gradient", "texture")


def _bg_colour(rng: np.random.Generator) -> np.ndarray:
    u = rng.uniform()
    if u < 0.12:  # near black
        return np.full(3, rng.uniform(0, 0.06)) + rng.uniform(0, 0.02, 3)
    if u < 0.24:  # near white
        return np.clip(np.full(3, rng.uniform(0.92, 1.0)) - rng.uniform(0, 0.03, 3), 0, 1)
    return _hsv(rng.uniform(), rng.uniform(0, 0.7), rng.uniform(0.1, 0.95))


@dataclass(frozen=True)
class Background:
    """A resolution-independent background description; :meth:`render` draws it at any size."""

    kind: str
    colour_a: np.ndarray
    colour_b: np.ndarray
    angle: float
    freq: float
    seed: int

    def render(self, H: int, W: int) -> np.ndarray:
        """``(H, W, 3)`` float32 in [0, 1]."""
        v, u = np.meshgrid((np.arange(H) + 0.5) / H, (np.arange(W) + 0.5) / W, indexing="ij")
        if self.kind == "solid":
            t = np.zeros((H, W))
        elif self.kind == "gradient":
            t = np.clip(0.5 + (u - 0.5) * np.cos(self.angle) + (v - 0.5) * np.sin(self.angle), 0, 1)
        else:
            p = np.stack([u * self.freq, v * self.freq, np.zeros_like(u)], axis=-1)
            t = np.clip(0.5 + 0.6 * fbm(p, self.seed, octaves=3), 0, 1)
        img = self.colour_a * (1 - t[..., None]) + self.colour_b * t[..., None]
        return np.clip(img, 0, 1).astype(np.float32)


def sample_background(rng: np.random.Generator) -> Background:
    """Draw a background: solid, two-colour gradient or smooth noise texture; some near-black/near-white."""
    kind = str(rng.choice(BACKGROUND_KINDS))
    a = _bg_colour(rng)
    # Second colour: a shade of the first (keeps near-black/white backgrounds near-black/white) or a new one.
    b = np.clip(a * rng.uniform(0.6, 1.4), 0, 1) if rng.uniform() < 0.6 else _bg_colour(rng)
    return Background(kind, a, b, float(rng.uniform(0, 2 * np.pi)), float(rng.uniform(2, 8)),
                      int(rng.integers(2**31)))
