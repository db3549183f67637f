"""Screen-space shadow marching against closed forms and against mesh ray tracing."""

import math

import numpy as np
import pytest

from difareli.render.camera import OrthoCamera
from difareli.render.screen_shadow import depth_gradient, depth_normals, march_shadow, pixel_world_xy

RES = 128
CAM = OrthoCamera(scale=1.0, tx=0.0, ty=0.0)  # the image spans [-1, 1]^2


def _box_on_wall(a: float = 0.2, h: float = 0.3):
    """Depth map of a wall z=0 filling the view with a box |x|,|y| <= a sticking out to z=h."""
    x, y = pixel_world_xy(CAM, RES, RES)
    depth = np.where((np.abs(x) <= a) & (np.abs(y) <= a), h, 0.0)
    return depth, np.ones((RES, RES), bool), x, y


@pytest.mark.parametrize("theta_deg", [20.0, 35.0, 50.0])
def test_box_on_wall_shadow_matches_closed_form(theta_deg):
    a, h = 0.2, 0.3
    depth, hit, x, y = _box_on_wall(a, h)
    th = math.radians(theta_deg)
    d = np.array([math.sin(th), 0.0, math.cos(th)])  # light toward +x and the viewer
    shadow = march_shadow(depth, hit, CAM, d, thickness=1.0)
    # Closed form: on the wall, x in [-a - h tan(theta), -a) ... the shadow lies opposite the light: x in
    # (a_left - h*tan, -a) on the -x side. Light comes from +x, so the box shades the wall toward -x.
    length = h * math.tan(th)
    expected = (x < -a) & (x > -a - length) & (np.abs(y) <= a)
    pixel_area = (2.0 / RES) ** 2
    got_area, want_area = shadow.sum() * pixel_area, 2 * a * length
    # Nearest-pixel sampling: the shadow's length is right to within 1.5 pixels.
    assert abs(got_area - want_area) <= 2 * a * 1.5 * (2.0 / RES)
    iou = (shadow & expected).sum() / (shadow | expected).sum()
    assert iou > 0.75
    # The box top and the lit wall are not shadowed.
    assert not shadow[(np.abs(x) <= a) & (np.abs(y) <= a)].any()
    assert not shadow[x > a + 2.0 / RES].any()


def test_light_along_view_axis_or_opposite_side():
    depth, hit, x, _ = _box_on_wall()
    assert not march_shadow(depth, hit, CAM, [0, 0, 1]).any()
    left = march_shadow(depth, hit, CAM, [-0.6, 0, 0.8], thickness=1.0)
    assert left.any() and not left[x < -0.2].any()  # light from -x shades the +x side only


def test_thin_surface_does_not_block_far_behind():
    # A narrow tall pole: rays from the wall near its foot pass ~0.4-0.6 behind its visible top.
    depth, hit, x, y = _box_on_wall(a=0.05, h=0.6)
    d = np.array([math.sin(math.radians(30)), 0, math.cos(math.radians(30))])
    thin = march_shadow(depth, hit, CAM, d, thickness=0.05)
    thick = march_shadow(depth, hit, CAM, d, thickness=1.0)
    assert thin.sum() < thick.sum()


@pytest.mark.parametrize("theta_deg", [20.0, 45.0, 70.0, 85.0])
def test_convex_sphere_casts_no_shadow(theta_deg):
    x, y = pixel_world_xy(CAM, RES, RES)
    r2 = x**2 + y**2
    hit = r2 < 0.64
    depth = np.where(hit, np.sqrt(np.clip(0.64 - r2, 0, None)), 0.0)
    normal = np.stack([x, y, depth], -1) / 0.8
    t = math.radians(theta_deg)
    assert not march_shadow(depth, hit, CAM, [math.sin(t), 0, math.cos(t)], normal=normal).any()


def test_agrees_with_mesh_ray_tracing_on_synthfaces():
    """On SynthFaces heads the depth-only march recovers most of the mesh-traced cast shadow (IoU measured
    0.53-0.76 over 4 subjects x 3 lights at 128 px; here 2 subjects x 2 lights at 96 px)."""
    from difareli.render import cast_shadow
    from difareli.synth.config import SynthConfig
    from difareli.synth.subject import build_subject

    cfg = SynthConfig(subjects=2, lights=1, resolution=96, seed=0)
    ious = []
    for k in range(2):
        sub = build_subject(k, cfg)
        gb = sub.gbuffer
        depth = np.where(gb.hit, gb.depth, 0.0)
        cam = OrthoCamera(*sub.cam.tolist())
        for az in (40.0, -45.0):
            t = math.radians(az)
            d = np.array([math.sin(t), 0.3, math.cos(t)])
            d /= np.linalg.norm(d)
            ref = cast_shadow(sub.scene, gb, d)
            got = march_shadow(depth, gb.hit, cam, d, normal=gb.normal)
            ious.append((ref & got).sum() / max((ref | got).sum(), 1))
    assert min(ious) > 0.4 and np.mean(ious) > 0.55, ious


def _march_one_ray_at_a_time(depth, hit, cam, d, *, max_distance=2.0, thickness=0.5, bias_pixels=0.0,
                             sample="plane", cand=None):
    """The march written the slow, obvious way (one ray, one step at a time): the batched march must equal it.
    ``cand``: the pixels that march (default: all of ``hit``); ``sample="plane"`` reads the nearest pixel's depth
    along its tangent plane."""
    d = np.asarray(d, float) / np.linalg.norm(d)
    h, w = depth.shape
    pixel = 2.0 / (cam.scale * w)
    out = np.zeros((h, w), bool)
    dxy = math.hypot(d[0], d[1])
    if dxy < 1e-6:
        return out
    step = pixel / dxy
    n_steps = int(min(math.ceil(max_distance / step), 2 * max(h, w)))
    x, y = pixel_world_xy(cam, h, w)
    gx, gy = depth_gradient(depth, hit, cam)
    for r, c in zip(*np.nonzero(hit if cand is None else cand)):
        for k in range(1, n_steps + 1):
            s = k * step
            qx, qy, qz = x[r, c] + s * d[0], y[r, c] + s * d[1], depth[r, c] + s * d[2]
            j = int(np.floor(((qx + cam.tx) * cam.scale + 1) / 2 * w))
            i = int(np.floor((1 - (qy + cam.ty) * cam.scale) / 2 * h))
            if not (0 <= i < h and 0 <= j < w):
                break
            z = depth[i, j]
            if sample == "plane":
                z = z + gx[i, j] * (qx - x[i, j]) + gy[i, j] * (qy - y[i, j])
            if hit[i, j] and bias_pixels * pixel < z - qz < thickness:
                out[r, c] = True
                break
    return out


def _bumpy_dome(res=24):
    cam = OrthoCamera(scale=1.1, tx=0.05, ty=-0.02)
    x, y = pixel_world_xy(cam, res, res)
    # A bumpy dome (a face-like height field) with a hole: shadows of many lengths, rays leaving the surface.
    r2 = x ** 2 + y ** 2
    hit = (r2 < 0.7) & ~((np.abs(x - 0.2) < 0.08) & (np.abs(y) < 0.1))
    depth = np.where(hit, np.sqrt(np.clip(0.8 - r2, 0, None)) + 0.15 * np.sin(9 * x) * np.cos(7 * y), 0.0)
    return depth, hit, cam


def _directions(n=12, seed=3):
    dirs = np.random.default_rng(seed).normal(size=(n, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) * np.where(np.arange(n) % 4 == 0, -0.3, 1.0)  # some lights from behind
    dirs[0] = [0, 0, 1]  # along the view axis: no cast shadow at all
    return dirs


@pytest.mark.parametrize("options", [{}, dict(sample="nearest", bias_pixels=0.5, estimate_normals=False)],
                         ids=["default", "legacy"])
def test_batched_march_equals_one_ray_at_a_time_and_per_direction(options):
    from difareli.render.screen_shadow import march_shadows

    depth, hit, cam = _bumpy_dome()
    dirs = _directions()
    stack = march_shadows(depth, hit, cam, dirs, **options)
    assert stack.shape == (12, *depth.shape) and stack[1:].any() and not stack[0].any()
    normals = depth_normals(depth, hit, cam)
    for n, d in enumerate(dirs):
        d = d / np.linalg.norm(d)
        cand = hit & (normals @ d > 0) if options.get("estimate_normals", True) else hit
        want = _march_one_ray_at_a_time(depth, hit, cam, d, cand=cand, sample=options.get("sample", "plane"),
                                         bias_pixels=options.get("bias_pixels", 0.0))
        assert np.array_equal(stack[n], want), n
        assert np.array_equal(march_shadow(depth, hit, cam, d, **options), want)


def test_given_normals_replace_estimated_ones_where_known():
    """Where ``normal`` is known (|n| > 0.5) the lit test reads it, elsewhere the depth map's own normal."""
    depth, hit, cam = _bumpy_dome()
    d = np.array([0.6, 0.3, 0.74])
    est = depth_normals(depth, hit, cam)
    flipped = np.where((np.arange(depth.shape[1]) < 12)[None, :, None], -est, 0.0)  # left half known, reversed
    got = march_shadow(depth, hit, cam, d, normal=flipped)
    cand = hit & np.where(np.linalg.norm(flipped, axis=-1) > 0.5, flipped @ d > 0, est @ d > 0)
    assert np.array_equal(got, _march_one_ray_at_a_time(depth, hit, cam, d / np.linalg.norm(d), cand=cand))
    assert np.array_equal(march_shadow(depth, hit, cam, d, normal=np.zeros_like(est)), march_shadow(depth, hit, cam, d))


def _dome_on_wall(radius: float):
    """A wall z=0 filling the view with a hemisphere of ``radius`` on it (centre at the origin)."""
    x, y = pixel_world_xy(CAM, RES, RES)
    r2 = x ** 2 + y ** 2
    dome = r2 < radius ** 2
    depth = np.where(dome, np.sqrt(np.clip(radius ** 2 - r2, 0, None)), 0.0)
    return depth, dome, x, y


@pytest.mark.parametrize("theta_deg,phi_deg", [(40, 30), (60, 30), (75, 30), (60, 200), (80, 120)])
def test_dome_on_wall_shadow_matches_closed_form_without_normals(theta_deg, phi_deg):
    """A hemisphere on a wall under an oblique light, no normals given: the wall point p is in cast shadow iff its
    ray toward the light passes within R of the centre ahead of it (|p|^2 - (p.d)^2 < R^2 and p.d < 0), a closed
    form with no thickness ambiguity (nothing lies behind the wall). The dome's far side is in attached shadow,
    not cast: the depth-estimated normals must keep the march off it. Measured: IoU 0.94-0.99 with the defaults;
    the old march (nearest samples, 0.5 px bias, no lit test) scored 0.62-0.80, marking the dome's far side."""
    radius = 0.35
    depth, dome, x, y = _dome_on_wall(radius)
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    d = np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])
    pd = x * d[0] + y * d[1]
    want = ~dome & (x ** 2 + y ** 2 - pd ** 2 < radius ** 2) & (pd < 0)
    got = march_shadow(depth, np.ones_like(dome), CAM, d, thickness=1.0)
    iou = (got & want).sum() / (got | want).sum()
    assert iou > 0.9, iou
    assert abs(int(got.sum()) - int(want.sum())) <= 0.05 * want.sum() + 10
    away = dome & (np.stack([x, y, depth], -1) @ d < -0.05 * radius)  # clearly turned away: attached shadow
    assert (got & away).sum() <= 3
    legacy = march_shadow(depth, np.ones_like(dome), CAM, d, thickness=1.0, sample="nearest", bias_pixels=0.5,
                          estimate_normals=False)
    assert (legacy & want).sum() / (legacy | want).sum() < iou - 0.1  # the test tells the two apart


@pytest.mark.parametrize("cos_to_plane", [0.02, 0.1, 0.3])
def test_tilted_plane_under_grazing_light_has_no_self_shadow(cos_to_plane):
    """A plane seen at a slant, lit almost along itself (n.d small but positive), has no cast shadow at all: the
    tangent-plane samples read it exactly, with no depth bias. Nearest samples without a bias mark it at the most
    grazing angle (staircase)."""
    x, y = pixel_world_xy(CAM, RES, RES)
    depth = 0.6 * x + 0.25 * y
    hit = np.ones((RES, RES), bool)
    n = np.array([-0.6, -0.25, 1.0]) / np.linalg.norm([-0.6, -0.25, 1.0])
    up = np.array([1.0, 0.3, 0.0])
    up -= (up @ n) * n  # uphill along the plane
    d = cos_to_plane * n + math.sqrt(1 - cos_to_plane ** 2) * up / np.linalg.norm(up)
    assert not march_shadow(depth, hit, CAM, d).any()
    if cos_to_plane < 0.05:
        assert march_shadow(depth, hit, CAM, d, sample="nearest", bias_pixels=0.0, estimate_normals=False).any()


def test_depth_gradient_exact_on_planes_and_not_tilted_by_steps():
    x, y = pixel_world_xy(CAM, RES, RES)
    hit = np.ones((RES, RES), bool)
    gx, gy = depth_gradient(0.3 * x - 0.7 * y + 0.1, hit, CAM)
    assert np.allclose(gx, 0.3) and np.allclose(gy, -0.7)
    step = np.where(x > 0, 0.5, 0.0)  # a step: both sides stay flat
    gx, gy = depth_gradient(step, hit, CAM)
    assert np.allclose(gx, 0.0) and np.allclose(gy, 0.0)
    r2 = x ** 2 + y ** 2
    ball = r2 < 0.64
    n = depth_normals(np.where(ball, np.sqrt(np.clip(0.64 - r2, 0, None)), 0.0), ball, CAM)
    true = np.stack([x, y, np.sqrt(np.clip(0.64 - r2, 0, None))], -1) / 0.8
    inner = r2 < 0.5 ** 2
    assert np.median((n * true).sum(-1)[inner]) > 0.999 and not n[~ball].any()
