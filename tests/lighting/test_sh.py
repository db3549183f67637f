"""SH lighting (difareli.lighting.sh) against closed forms: constants, clamped-cosine lobes, rotations, env maps,
fits."""

import math

import numpy as np
import pytest
import torch

from difareli.lighting import sh


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def test_constants_match_spec_rounding():
    spec = [0.2821] + [1.0233] * 3 + [0.8581] * 3 + [0.4290, 0.2477]
    np.testing.assert_array_equal(np.round(sh.SH_CONSTANTS, 4), spec)


def test_real_sh_is_orthonormal():
    dirs, area = sh.envmap_directions(128, 256)
    y = sh.real_sh(dirs)
    gram = np.einsum("hwi,hw,hwj->ij", y, area, y)
    np.testing.assert_allclose(gram, np.eye(9), atol=5e-4)
    assert math.isclose(area.sum(), 4 * math.pi, rel_tol=1e-12)


def test_constant_radiance_gives_pi_c_everywhere(rng):
    c = np.array([0.5, 1.0, 2.0])
    normals = _unit(rng.normal(size=(50, 3)))
    # Analytic: L_0 = c * sqrt(4 pi), nothing else.
    analytic = sh.light_from_radiance(np.concatenate([c[None] * math.sqrt(4 * math.pi), np.zeros((8, 3))]))
    np.testing.assert_allclose(sh.irradiance(analytic, normals), np.broadcast_to(math.pi * c, (50, 3)), atol=1e-12)
    # Env-map quadrature: band 0 is exact; band 2 has an O(1/H^2) error (measured 3.9e-4 at 64 rows).
    projected = sh.project_envmap(np.broadcast_to(c, (64, 128, 3)))
    np.testing.assert_allclose(projected[0], analytic[0], rtol=1e-12)
    e = sh.irradiance(projected, normals)
    np.testing.assert_allclose(e, np.broadcast_to(math.pi * c, (50, 3)), atol=1e-3 * c.max())


def test_directional_light_peak_is_1_0625(rng):
    for _ in range(5):
        d = _unit(rng.normal(size=3))
        intensity = rng.uniform(0.1, 3.0, size=3)
        e = sh.irradiance(sh.directional_light(d, intensity), d)
        np.testing.assert_allclose(e, (0.25 + 0.5 + 5 / 16) * intensity, rtol=1e-12)


def test_directional_light_matches_clamped_cosine_projection():
    # Funk-Hecke: the clamped cosine's bands 0-2 give E(theta) = I (1/4 + 1/2 cos + 5/16 P2(cos)).
    d = np.array([0.0, 0.0, 1.0])
    for t in np.linspace(0, math.pi, 7):
        n = np.array([math.sin(t), 0.0, math.cos(t)])
        expected = 0.25 + 0.5 * math.cos(t) + 5 / 16 * (3 * math.cos(t) ** 2 - 1) / 2
        np.testing.assert_allclose(sh.irradiance(sh.directional_light(d, 1.0), n), [expected] * 3, atol=1e-12)


def test_small_bright_disc_projects_to_directional_light():
    height, width = 256, 512
    dirs, area = sh.envmap_directions(height, width)
    d = _unit([0.3, 0.5, 0.8])
    intensity = np.array([1.0, 2.0, 0.5])
    cos_a = math.cos(math.radians(4.0))
    disc = (dirs @ d) >= cos_a
    # Normalise by the disc's discrete solid angle so that its total power is exactly I.
    env = disc[..., None] * intensity / area[disc].sum()
    got = sh.project_envmap(env)
    want = sh.directional_light(d, intensity)
    # A 4-degree cap scales band l by (P_{l-1} - P_{l+1}) / ((2l+1)(1 - cos a)): 0.9988 (l=1), 0.9964 (l=2).
    np.testing.assert_allclose(got, want, atol=4e-3 * np.abs(want).max())  # measured 2.0e-3
    # Closed forms: (P0 - P2) / (3 (1 - c)) = (1 + c) / 2 and (P1 - P3) / (5 (1 - c)) = c (1 + c) / 2.
    cap = np.array([1.0] + [(1 + cos_a) / 2] * 3 + [cos_a * (1 + cos_a) / 2] * 5)
    np.testing.assert_allclose(got, want * cap[:, None], atol=1.5e-3 * np.abs(want).max())  # measured 7.7e-4


def test_rotated_lobe_is_lobe_of_rotated_direction(rng):
    for _ in range(10):
        R = _random_rotation(rng)
        d = _unit(rng.normal(size=3))
        intensity = rng.uniform(0.1, 2.0, size=3)
        np.testing.assert_allclose(
            sh.rotate(sh.directional_light(d, intensity), R), sh.directional_light(R @ d, intensity), atol=1e-10
        )


def test_rotation_matrix_is_orthogonal_and_preserves_irradiance(rng):
    R = _random_rotation(rng)
    m = sh.sh_rotation_matrix(R)
    np.testing.assert_allclose(m @ m.T, np.eye(9), atol=1e-12)
    dirs = _unit(rng.normal(size=(20, 3)))
    np.testing.assert_allclose(sh.real_sh(dirs @ R.T), sh.real_sh(dirs) @ m.T, atol=1e-12)
    light = rng.normal(size=(9, 3))
    np.testing.assert_allclose(sh.irradiance(sh.rotate(light, R), dirs @ R.T), sh.irradiance(light, dirs), atol=1e-12)
    with pytest.raises(ValueError, match="orthogonal"):
        sh.sh_rotation_matrix(2 * R)


def test_yaw_roll_axes_and_full_turn(rng):
    z, x, y = np.eye(3)[2], np.eye(3)[0], np.eye(3)[1]
    np.testing.assert_allclose(sh.rotation_yaw(90) @ z, x, atol=1e-15)
    np.testing.assert_allclose(sh.rotation_roll(90) @ x, y, atol=1e-15)
    np.testing.assert_allclose(sh.yaw(sh.directional_light(z), 90), sh.directional_light(x), atol=1e-12)
    light = rng.normal(size=(9, 3))
    np.testing.assert_allclose(sh.yaw(light, 360), light, atol=1e-12)
    np.testing.assert_allclose(sh.roll(light, -360), light, atol=1e-12)
    np.testing.assert_allclose(sh.yaw(sh.yaw(light, 30), 50), sh.yaw(light, 80), atol=1e-12)


def test_composition_equals_product(rng):
    r1, r2 = _random_rotation(rng), _random_rotation(rng)
    light = rng.normal(size=(9, 3))
    np.testing.assert_allclose(sh.rotate(sh.rotate(light, r1), r2), sh.rotate(light, r2 @ r1), atol=1e-12)
    m1, m2 = sh.sh_rotation_matrix(r1), sh.sh_rotation_matrix(r2)
    np.testing.assert_allclose(sh.sh_rotation_matrix(r2 @ r1), m2 @ m1, atol=1e-12)


def test_batched_video_rotation_and_torch(rng):
    light = rng.normal(size=(9, 3))
    angles = np.linspace(0, 360, 60, endpoint=False)
    frames = sh.yaw(light, angles)
    assert frames.shape == (60, 9, 3)
    np.testing.assert_allclose(frames[17], sh.yaw(light, angles[17]), atol=1e-12)
    np.testing.assert_allclose(sh.roll(light, angles)[5], sh.roll(light, angles[5]), atol=1e-12)
    np.testing.assert_allclose(frames[0], light, atol=1e-12)
    # Band 0 is invariant, every band's norm too.
    np.testing.assert_allclose(frames[:, 0], np.broadcast_to(light[0], (60, 3)), atol=1e-12)
    band2 = np.linalg.norm(frames[:, 4:], axis=1)
    np.testing.assert_allclose(band2, np.broadcast_to(np.linalg.norm(light[4:], axis=0), (60, 3)), atol=1e-12)
    t = sh.roll(torch.tensor(light, dtype=torch.float32), 33.0)
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32
    np.testing.assert_allclose(t.numpy(), sh.roll(light, 33.0), atol=1e-5)


def test_dominant_direction(rng):
    for _ in range(5):
        d = _unit(rng.normal(size=3))
        got = sh.dominant_direction(sh.directional_light(d, rng.uniform(0.2, 2, size=3)))
        np.testing.assert_allclose(got, d, atol=1e-12)
    # An ambient term does not change it; batched input; a uniform light falls back to +z.
    lights = np.stack([sh.directional_light(d, 1.0), np.zeros((9, 3))])
    lights[:, 0] += 1.0
    lights[0, 4:] += rng.normal(size=(5, 3))  # band 2 does not enter either
    out = sh.dominant_direction(lights)
    np.testing.assert_allclose(out, [d, [0, 0, 1]], atol=1e-12)


def test_envmap_directions_convention():
    dirs, area = sh.envmap_directions(6, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-15)
    assert dirs[0, 0, 1] > 0.9 and dirs[-1, 0, 1] < -0.9  # row 0 is up
    mid = dirs[2:4, 1]  # phi = 0 column: toward the viewer, x = 0
    np.testing.assert_allclose(mid[:, 0], 0.0, atol=1e-15)
    assert np.all(mid[:, 2] > 0)
    dirs, _ = sh.envmap_directions(8, 16)
    phi = -math.pi + (np.arange(16) + 0.5) * 2 * math.pi / 16
    np.testing.assert_allclose(np.arctan2(dirs[3, :, 0], dirs[3, :, 2]), phi, atol=1e-12)  # phi = pi/2 at +x


def test_render_project_round_trip(rng):
    light = rng.normal(size=(9, 3))
    errors = []
    for h in (32, 64, 128):
        env = sh.render_envmap(light, h, 2 * h)
        errors.append(np.abs(sh.project_envmap(env) - light).max())
    # Midpoint-in-theta quadrature, second order: relative 2.4e-3, 5.9e-4, 1.5e-4 at H = 32, 64, 128.
    assert errors[2] < 3e-4 * np.abs(light).max()
    assert 12 < errors[0] / errors[2] < 20  # halving the pixel size twice cuts the error ~16x
    # The rendered radiance peaks toward a directional light.
    d = _unit([-0.4, 0.3, 0.85])
    env = sh.render_envmap(sh.directional_light(d, 1.0), 64, 128)
    dirs, _ = sh.envmap_directions(64, 128)
    assert dirs.reshape(-1, 3)[env[..., 0].argmax()] @ d > 0.995


def test_fit_round_trip_and_noise(rng):
    normals = _fibonacci_sphere(400)
    light = rng.normal(size=(9, 3))
    albedo = rng.uniform(0.2, 0.9, size=(400, 3))
    clean = albedo * sh.irradiance(light, normals)
    np.testing.assert_allclose(sh.fit(clean, normals, albedo), light, atol=1e-8)
    # float32 input, scalar albedo, weights on a front hemisphere (face-like normals).
    front = normals[normals[:, 2] > 0.1]
    img = (0.7 * sh.irradiance(light, front)).astype(np.float32)
    got = sh.fit(img, front.astype(np.float32), 0.7, weights=np.ones(len(front)))
    np.testing.assert_allclose(got, light, atol=1e-5)  # float32 rounding; measured 5e-8
    # Least squares is linear in the data: the error scales with the noise (measured 1.08 sigma).
    errs = []
    for sigma in (1e-3, 1e-2):
        noisy = clean + sigma * np.random.default_rng(1).normal(size=clean.shape)
        errs.append(np.abs(sh.fit(noisy, normals, albedo) - light).max())
    assert errs[0] < 3e-3 and errs[1] < 3e-2
    assert math.isclose(errs[1] / errs[0], 10, rel_tol=1e-6)
    # Ridge shrinks the solution toward 0.
    assert np.linalg.norm(sh.fit(clean, normals, albedo, ridge=10.0)) < np.linalg.norm(light)


def test_ridge_fit_with_one_albedo_per_channel_equals_the_per_pixel_path(rng):
    # (3,) albedo takes the shared-Gram path; the same albedo repeated per pixel (N, 3) takes the channel loop.
    normals = _fibonacci_sphere(300)
    albedo = np.array([0.8, 0.55, 0.4])
    y = albedo * sh.irradiance(rng.normal(size=(9, 3)), normals) + 0.01 * rng.normal(size=(300, 3))
    w = rng.uniform(0.5, 1.5, 300)
    loop = sh.fit(y, normals, np.tile(albedo, (300, 1)), weights=w, ridge=3.0)
    np.testing.assert_allclose(sh.fit(y, normals, albedo, weights=w, ridge=3.0), loop, rtol=1e-10, atol=1e-12)
    # A precomputed basis is the same fit.
    np.testing.assert_array_equal(sh.fit(y, normals, albedo, ridge=3.0, basis=sh.sh_basis(normals)),
                                  sh.fit(y, normals, albedo, ridge=3.0))


def test_fit_rejects_degenerate_input(rng):
    light = rng.normal(size=(9, 3))
    few = _unit(rng.normal(size=(8, 3)))
    with pytest.raises(ValueError, match="at least 9 samples"):
        sh.fit(sh.irradiance(light, few), few)
    same = np.tile([[0.0, 0.0, 1.0]], (50, 1))
    with pytest.raises(ValueError, match="rank-deficient"):
        sh.fit(sh.irradiance(light, same), same)
    t = np.linspace(0, 2 * math.pi, 50)
    planar = np.stack([np.cos(t), np.sin(t), 0 * t], axis=-1)  # only 1, x, y, xy, x^2-y^2 vary: rank 5
    with pytest.raises(ValueError, match="rank 5 < 9"):
        sh.fit(sh.irradiance(light, planar), planar)
    # Ridge makes the same problem well posed.
    assert np.all(np.isfinite(sh.fit(sh.irradiance(light, same), same, ridge=1e-3)))


def test_ridge_fit_equals_the_augmented_least_squares():
    """fit with a ridge solves the 9x9 normal equations; they must equal the ridge written as 9 extra rows of a
    least-squares system (numpy's lstsq), for constant, per-channel and per-pixel albedo, with weights."""
    rng = np.random.default_rng(1)
    for trial in range(30):
        n = rng.normal(size=(int(rng.integers(12, 400)), 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        y, ridge = rng.uniform(0, 1, (len(n), 3)), 10 ** rng.uniform(-4, 1)
        albedo = [0.6, rng.uniform(0.2, 0.9, 3), rng.uniform(0.2, 0.9, (len(n), 3))][trial % 3]
        w = rng.uniform(0, 2, len(n)) if trial % 2 else None
        sw = np.sqrt(np.ones(len(n)) if w is None else w)
        alb = np.broadcast_to(np.asarray(albedo, dtype=float), (len(n), 3))
        theirs = np.stack([np.linalg.lstsq(
            np.concatenate([sh.sh_basis(n) * (sw * alb[:, c])[:, None], np.sqrt(ridge) * np.eye(9)]),
            np.concatenate([y[:, c] * sw, np.zeros(9)]), rcond=None)[0] for c in range(3)], axis=1)
        ours = sh.fit(y, n, albedo, weights=w, ridge=ridge)
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9 * np.abs(theirs).max())
