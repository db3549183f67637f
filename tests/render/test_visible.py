"""Visibly shadowed (``render.visible``): the share rule in closed form, and the march toward every sun of a light
against the same rule on the march's own per-sun casts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from difareli.lighting import sh
from difareli.lighting.suns import Suns, sun_direction
from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import march_shadows, pixel_world_xy
from difareli.render.visible import MARCH_VISIBLE, visible_march, visible_shadow
from difareli.utils.imageops import LUMA

RES = 96
CAM = OrthoCamera(scale=1.0, tx=0.0, ty=0.0)  # the image spans [-1, 1]^2


def test_visible_fraction_in_closed_form():
    """A flat patch facing the key sun: ambient E_a, key sun E_k (cast on the left half), fill E_f (cast on the top
    rows). The share removed is E_k / (E_a + E_k + E_f) under the key's shadow, E_f / (...) under the fill's."""
    hit = np.ones((4, 4), bool)
    hit[3, 3] = False
    e_a, e_k, e_f = np.full((4, 4, 3), 0.2), np.full((4, 4, 3), 0.6), np.full((4, 4, 3), 0.1)
    key = np.zeros((4, 4), bool)
    key[:, :2] = True
    fill = np.zeros((4, 4), bool)
    fill[0, :] = True
    frac, vis = visible_shadow(e_a + e_k + e_f, [e_k, e_f], [key & hit, fill & hit], key & hit, hit, 0.25)
    y = lambda e: float(e[0, 0] @ LUMA)  # noqa: E731
    total = y(e_a) + y(e_k) + y(e_f)
    np.testing.assert_allclose(frac[1, 0], y(e_k) / total, rtol=1e-6)           # key only: 0.667
    np.testing.assert_allclose(frac[0, 3], y(e_f) / total, rtol=1e-6)           # fill only: 0.111, not visible
    np.testing.assert_allclose(frac[0, 0], (y(e_k) + y(e_f)) / total, rtol=1e-6)
    assert frac[2, 3] == 0 and frac[3, 3] == 0                                  # unshadowed; off the mesh
    want = key.copy()
    want[3, 3] = False
    np.testing.assert_array_equal(vis, want)  # the weak fill's shadow is not "visibly shadowed"
    _, vis_low = visible_shadow(e_a + e_k + e_f, [e_k, e_f], [key, fill], np.zeros_like(key), hit, 0.1)
    assert vis_low[0, 3] and not vis_low[2, 3]  # a lower threshold admits it; the key mask is not needed for it


def _box_on_wall(a: float = 0.2, h: float = 0.3):
    """A wall z=0 filling the view with a box |x|, |y| <= a sticking out to z=h; every normal +z (known)."""
    x, y = pixel_world_xy(CAM, RES, RES)
    depth = np.where((np.abs(x) <= a) & (np.abs(y) <= a), h, 0.0)
    depth = np.where(depth == 0, -0.5, depth)  # the wall at z=-0.5 (0 means no surface)
    normal = np.zeros((RES, RES, 3))
    normal[..., 2] = 1.0
    return depth, normal


def _direction(theta_deg: float, phi_deg: float) -> np.ndarray:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


@pytest.mark.parametrize("fill", [0.05, 0.6])
def test_march_toward_every_sun_keeps_only_what_takes_a_visible_share(fill):
    """A box on a wall under a key sun from the right and a fill sun from above, with a grey ambient: on the wall
    (n = +z) the key's cast is always visibly shadowed; the fill's cast alone is iff the fill's term is more than
    MARCH_VISIBLE of the pixel's light, Y(fill n.d) / Y(E_a + key n.d + fill n.d) in closed form."""
    depth, normal = _box_on_wall()
    key_d, fill_d = _direction(50, 0), _direction(50, 90)
    ambient = sh.directional_light(np.array([0.0, 0.0, 1.0]), 0.0) + 0.0
    ambient[0] = 0.3 / 0.886227  # a uniform 0.3 irradiance (DECA's band-0 factor)
    suns = Suns(np.stack([key_d, fill_d]), np.array([[1.0] * 3, [fill] * 3]), ambient)
    got = visible_march(depth, normal, CAM, suns)
    key_cast, fill_cast = march_shadows(depth, depth != 0, CAM, np.stack([key_d, fill_d]), normal=normal)
    assert key_cast.sum() > 100 and (fill_cast & ~key_cast).sum() > 100
    e_a = float(sh.irradiance(ambient, np.array([0.0, 0.0, 1.0])) @ LUMA)
    share = fill * fill_d[2] / (e_a + key_d[2] + fill * fill_d[2])
    assert (share > MARCH_VISIBLE) == (fill > 0.3)  # the two cases lie either side of the cut
    np.testing.assert_array_equal(got, key_cast | (fill_cast if share > MARCH_VISIBLE else False))


def test_an_sh_light_alone_gives_the_march_itself():
    """Under ``Suns.of_sh`` (one sun carrying all the light) visibly shadowed is exactly cast: the relight's maps
    toward an SH target light do not change."""
    rng = np.random.default_rng(0)
    depth, normal = _box_on_wall()
    normal[::3] = 0.0  # unknown normals on some rows: the depth's own there
    for _ in range(3):
        light = rng.normal(size=(9, 3)) * 0.3
        light[0] += 1.0
        suns = Suns.of_sh(light)
        want = march_shadows(depth, depth != 0, CAM, sun_direction(light)[None], normal=normal)[0]
        np.testing.assert_array_equal(visible_march(depth, normal, CAM, suns), want)
