"""Ray-cast renderer against closed forms: sphere silhouette, normals, depth, irradiance; box shadows."""

import math

import numpy as np
import pytest
import trimesh

from difareli.render import (
    OrthoCamera,
    Scene,
    cast_shadow,
    cast_shadows,
    interpolate_vertex_attribute,
    lit_candidates,
    render_gbuffer,
    render_sh,
    shading_reference,
)

H = W = 128
SCALE = 0.8  # sphere radius 1 -> 0.8 * 64 = 51.2 px


@pytest.fixture(scope="module")
def sphere_scene():
    return Scene(trimesh.creation.icosphere(subdivisions=4))  # 5120 triangles, unit radius


@pytest.fixture(scope="module")
def sphere_render(sphere_scene):
    cam = OrthoCamera(SCALE, 0.0, 0.0)
    g = render_gbuffer(sphere_scene, cam, H, W)
    p = cam.unproject(cam.pixel_centers(H, W), 0.0, H, W)
    x, y = p[..., 0], p[..., 1]
    r2 = x * x + y * y
    analytic = np.stack([x, y, np.sqrt(np.clip(1 - r2, 0, None))], axis=-1)
    return g, r2, analytic


# --- camera ------------------------------------------------------------------------------------------

def test_camera_closed_form_and_round_trip(rng):
    cam = OrthoCamera(2.0, 0.1, -0.2)
    np.testing.assert_array_equal(OrthoCamera.from_array(cam.to_array()).to_array(), cam.to_array())
    assert cam.to_array().dtype == np.float32
    # X = -t maps to the image centre; X_x = 1/s - tx to the right edge; X_y = 1/s - ty to the top row.
    np.testing.assert_allclose(cam.project([[-0.1, 0.2, 5.0]], 40, 60), [[30.0, 20.0]])
    np.testing.assert_allclose(cam.project([[0.5 - 0.1, 0.5 + 0.2, 0.0]], 40, 60), [[60.0, 0.0]], atol=1e-12)
    pts = rng.normal(size=(50, 3))
    uv = cam.project(pts, 40, 60)
    np.testing.assert_allclose(cam.unproject(uv, pts[:, 2], 40, 60), pts, atol=1e-12)


def test_pixel_rays_hit_pixel_centres():
    cam = OrthoCamera(1.5, -0.3, 0.25)
    o, d = cam.pixel_rays(5, 7, z_start=3.0)
    assert o.shape == d.shape == (35, 3)
    np.testing.assert_array_equal(d, np.tile([0.0, 0.0, -1.0], (35, 1)))
    np.testing.assert_array_equal(o[:, 2], 3.0)
    uv = cam.project(o, 5, 7).reshape(5, 7, 2)
    j, i = np.meshgrid(np.arange(7), np.arange(5))
    np.testing.assert_allclose(uv[..., 0], j + 0.5, atol=1e-12)  # columns left to right
    np.testing.assert_allclose(uv[..., 1], i + 0.5, atol=1e-12)  # rows top-down: row 0 has the largest y
    assert o.reshape(5, 7, 3)[0, 0, 1] > o.reshape(5, 7, 3)[-1, 0, 1]


# --- G-buffer of a unit sphere ---------------------------------------------------------------------

def test_sphere_silhouette_area(sphere_render):
    g, r2, _ = sphere_render
    area = math.pi * (SCALE * W / 2) ** 2  # 8235.5 px
    # The inscribed polyhedron loses ~0.2%; pixel quantisation of the rim adds a few pixels either way.
    assert abs(g.hit.sum() - area) / area < 0.005
    assert (g.hit != (r2 < 1)).sum() < 0.005 * area  # and the mask is the disc, not just its area
    assert g.hit.dtype == bool and g.shape == (H, W)


def test_sphere_normals_and_depth(sphere_render):
    g, r2, analytic = sphere_render
    inner = g.hit & (r2 < 0.95**2)
    cos = np.clip((g.normal * analytic).sum(-1), -1, 1)
    ang = np.degrees(np.arccos(cos))
    assert ang[inner].max() < 0.5  # measured 0.22 deg at subdivision 4
    assert ang[g.hit].max() < 3.0  # rim pixels, where z = sqrt(1 - r^2) is steep
    np.testing.assert_allclose(np.linalg.norm(g.normal[g.hit], axis=-1), 1.0, atol=1e-6)
    assert (g.normal[g.hit][:, 2] > 0).all() and (g.face_normal[g.hit][:, 2] > 0).all()
    # Depth: the faces lie inside the sphere by at most the sagitta (~1.2e-3 here); 3.4e-3 measured at r<.95.
    assert np.abs(g.depth - analytic[..., 2])[inner].max() < 5e-3
    assert (g.depth[inner] <= analytic[..., 2][inner] + 1e-6).all()
    np.testing.assert_allclose(g.points[..., 2][g.hit], g.depth[g.hit], rtol=1e-6)
    # Off-mesh conventions.
    off = ~g.hit
    assert np.isneginf(g.depth[off]).all()
    assert (g.normal[off] == 0).all() and (g.label[off] == 0).all() and (g.triangle[off] == -1).all()
    assert (g.label[g.hit] == 1).all()


def _directional_sh(d, intensity=1.0):
    """DECA-convention SH of a directional light toward ``d`` (radiance delta, real SH, l0 = pi L0)."""
    x, y, z = d
    y_k = np.array([
        1 / math.sqrt(4 * math.pi),
        math.sqrt(3 / (4 * math.pi)) * x, math.sqrt(3 / (4 * math.pi)) * y, math.sqrt(3 / (4 * math.pi)) * z,
        math.sqrt(15 / (4 * math.pi)) * x * y, math.sqrt(15 / (4 * math.pi)) * x * z,
        math.sqrt(15 / (4 * math.pi)) * y * z,
        math.sqrt(15 / (16 * math.pi)) * (x * x - y * y), math.sqrt(5 / (16 * math.pi)) * (3 * z * z - 1),
    ])
    y_k[0] *= math.pi
    return np.repeat((intensity * y_k)[:, None], 3, axis=1)


def test_sphere_irradiance_matches_truncated_lambertian(sphere_render):
    g, r2, analytic = sphere_render
    d = np.array([0.48, 0.6, 0.64])  # unit
    light = _directional_sh(d, intensity=2.0)
    R = shading_reference(g, light)
    assert R.dtype == np.float32 and R.shape == (H, W, 3)
    # Funk-Hecke: 9-term Lambertian irradiance of a unit directional light = 1/4 + c/2 + 5/16 (3c^2 - 1)/2.
    def e(n):
        c = n @ d
        return 2.0 * (0.25 + 0.5 * c + (5 / 16) * (3 * c * c - 1) / 2)
    np.testing.assert_allclose(R[g.hit][:, 1], 0.7 * e(g.normal[g.hit].astype(np.float64)), atol=1e-5)
    inner = g.hit & (r2 < 0.95**2)
    np.testing.assert_allclose(R[inner][:, 0], 0.7 * e(analytic[inner]), atol=0.01)
    assert (R[~g.hit] == 0).all()
    # Unclipped: the truncated series dips below 0 opposite the light (min at c = -1/3: 2 * -1/24 * 0.7).
    assert R[g.hit].min() < 0 and R[g.hit].min() > 0.7 * 2 * (-1 / 24) - 1e-3
    albedo = np.full((H, W, 3), 0.35, dtype=np.float32)
    np.testing.assert_allclose(render_sh(g, light, albedo), 0.5 * R, atol=1e-6)
    vis = np.where(g.hit, 0.5, 1.0)
    np.testing.assert_allclose(render_sh(g, light, 0.7, visibility=vis), 0.5 * R, atol=1e-6)


def test_labels_and_vertex_attributes(sphere_scene):
    mesh = sphere_scene.mesh
    labels = np.where(mesh.triangles_center[:, 0] > 0, 3, 5)
    scene = Scene(mesh, labels)
    cam = OrthoCamera(SCALE, 0.2, 0.0)  # shifted: centre column sits at x = -0.2
    g = render_gbuffer(scene, cam, 64, 64)
    np.testing.assert_array_equal(g.label[g.hit], labels[g.triangle[g.hit]])
    x = g.points[..., 0]
    assert (g.label[g.hit & (x > 0.05)] == 3).all() and (g.label[g.hit & (x < -0.05)] == 5).all()
    assert set(np.unique(g.label)) == {0, 3, 5}
    # Interpolating vertex positions reproduces the hit points (barycentrics are exact).
    pos = interpolate_vertex_attribute(scene, g, mesh.vertices)
    np.testing.assert_allclose(pos[g.hit], g.points[g.hit], atol=1e-5)
    assert interpolate_vertex_attribute(scene, g, mesh.vertices[:, 2]).shape == (64, 64)
    with pytest.raises(ValueError):
        Scene(mesh, labels[:-1])


def test_vertex_normal_override_and_area_weighting(sphere_scene):
    mesh = sphere_scene.mesh
    # Area-weighted facet averages on an icosphere sit within ~1 deg of the radial direction.
    ang = np.degrees(np.arccos(np.clip((sphere_scene.vertex_normals * mesh.vertices).sum(-1), -1, 1)))
    assert ang.max() < 1.0
    scene = Scene(mesh, vertex_normals=-3.0 * mesh.vertices)  # unnormalised, inward: unitised, re-oriented
    np.testing.assert_allclose(scene.vertex_normals, -mesh.vertices, atol=1e-12)
    g = render_gbuffer(scene, OrthoCamera(SCALE), 32, 32)
    p = g.points[g.hit]
    radial = p / np.linalg.norm(p, axis=-1, keepdims=True)
    # Inward vertex normals against an outward facet: the facet wins the orientation, so they face the viewer.
    assert ((g.normal[g.hit] * radial).sum(-1) > 0.999).all()


def test_open_mesh_seen_from_behind_faces_viewer():
    # A quad wound so that its normal points to -z (away from the camera) must still render facing +z.
    v = np.array([[-1.0, -1.1, 0.0], [1.0, -1.1, 0.0], [1.0, 1.2, 0.0], [-1.0, 1.2, 0.0]])
    scene = Scene.from_arrays(v, [[0, 2, 1], [0, 3, 2]])
    assert scene.face_normals[0, 2] < 0
    g = render_gbuffer(scene, OrthoCamera(1.0), 16, 16)
    assert g.hit.all()
    np.testing.assert_allclose(g.normal[g.hit], np.tile([0, 0, 1.0], (256, 1)), atol=1e-6)


# --- cast shadows ----------------------------------------------------------------------------------

def test_lone_sphere_has_no_cast_shadow(sphere_scene, sphere_render, rng):
    g, _, _ = sphere_render
    dirs = np.concatenate([[[0, 0, 1], [1, 0, 0], [0, -1, 0], [0, 0, -1]], rng.normal(size=(8, 3))])
    maps = cast_shadows(sphere_scene, g, dirs)
    assert maps.shape == (12, H, W) and not maps.any()
    for d in dirs[:3]:
        assert not cast_shadow(sphere_scene, g, d).any()
    # Attached shadow (n.d <= 0) is not a cast shadow: a front light lights the whole disc, a side light
    # the half facing it, up to the facets that straddle the terminator (edge length ~0.08 at this mesh).
    assert (lit_candidates(g, [0, 0, 1]) == g.hit).all()
    for d, coord in (([1, 0, 0], g.points[..., 0]), ([0, -1, 0], -g.points[..., 1])):
        lit = lit_candidates(g, d)
        wrong = lit != (g.hit & (coord > 0))
        assert np.abs(coord[wrong]).max() < 0.08 and wrong.sum() < 0.03 * g.hit.sum()
    assert lit_candidates(g, [0, 0, -1]).sum() == 0  # back light: all attached shadow


# A plane z = 0 (corners chosen so its diagonal misses every pixel centre) under a thin box at z in
# [H1, H2]. Camera s = 1, t = 0, 64 px: pixel centres sit at X = (k + 1/2)/32, so a box whose edges are at
# (integer + jitter)/32 covers an exact, countable set of centres.
PX = 1 / 32
X0, X1 = -7.8 * PX, 8.2 * PX  # 16 centre columns: k + 1/2 in [-7.5, 7.5]
Y0, Y1 = -7.55 * PX, 8.45 * PX  # 16 centre rows
H1, H2 = 8 * PX, 9 * PX


def _plane():
    v = np.array([[-1.3, -1.1, 0.0], [1.7, -1.1, 0.0], [1.7, 1.9, 0.0], [-1.3, 1.9, 0.0]])
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def _box():
    return trimesh.creation.box(bounds=[[X0, Y0, H1], [X1, Y1, H2]])


@pytest.fixture(scope="module")
def plane_box():
    plane, box = _plane(), _box()
    both = trimesh.util.concatenate([plane, box])
    labels = np.r_[np.full(len(plane.faces), 1), np.full(len(box.faces), 13)]
    cam = OrthoCamera(1.0, 0.0, 0.0)
    g_plane = render_gbuffer(Scene(plane), cam, 64, 64)  # the plane alone, box invisible to the camera
    scene = Scene(both, labels)
    return scene, g_plane, render_gbuffer(scene, cam, 64, 64)


def _expected_shadow(g, tan):
    """Plane points p shadowed by the box under light (tan, 0, 1): p_x + z tan in [X0, X1] for some z in
    [H1, H2] <=> p_x in [X0 - H2 tan, X1 - H1 tan] (footprint shifted by height * tan, widened by
    thickness * tan)."""
    x, y = g.points[..., 0], g.points[..., 1]
    return g.hit & (x >= X0 - H2 * tan) & (x <= X1 - H1 * tan) & (y >= Y0) & (y <= Y1)


def test_box_shadow_from_straight_above_is_its_footprint(plane_box):
    scene, g_plane, g_full = plane_box
    s = cast_shadow(scene, g_plane, [0, 0, 1])
    assert s.sum() == 16 * 16  # footprint area (0.5 x 0.5) in pixels
    np.testing.assert_array_equal(s, _expected_shadow(g_plane, 0.0))
    # Seen by the camera, the box hides its own shadow exactly; its top is lit.
    assert not cast_shadow(scene, g_full, [0, 0, 1]).any()
    assert (g_full.label == 13).sum() == 16 * 16 and (g_full.depth[g_full.label == 13] == np.float32(H2)).all()


def test_box_shadow_under_oblique_light_shifts_by_height_tan(plane_box):
    scene, g_plane, g_full = plane_box
    d = np.array([1.0, 0.0, 1.0]) / math.sqrt(2)  # 45 deg toward +x: tan = 1
    s = cast_shadow(scene, g_plane, d)
    assert s.sum() == 17 * 16  # 16 columns shifted by H1 tan = 8 px, widened by (H2 - H1) tan = 1 px
    np.testing.assert_array_equal(s, _expected_shadow(g_plane, 1.0))
    cols = np.flatnonzero(s.any(axis=0))
    np.testing.assert_array_equal(cols, np.arange(15, 32))  # box: columns 24..39; shadow: 24 - 9 .. 39 - 8
    # With the box visible, only the part of the shadow outside the box's screen footprint remains.
    s_full = cast_shadow(scene, g_full, d)
    box_px = g_full.label == 13
    assert s_full.sum() == 9 * 16 and not (s_full & box_px).any()
    np.testing.assert_array_equal(s_full, _expected_shadow(g_plane, 1.0) & ~box_px)
    # Batched and single-direction passes agree.
    np.testing.assert_array_equal(cast_shadows(scene, g_full, [d, [0, 0, 1.0]])[0], s_full)


def test_pure_python_backend_agrees(monkeypatch):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    cam = OrthoCamera(0.9)
    ref = render_gbuffer(Scene(mesh, backend="embree"), cam, 24, 24) if trimesh.ray.has_embree else None
    monkeypatch.setattr(trimesh.ray, "has_embree", False)
    with pytest.warns(RuntimeWarning, match="pure-Python"):
        scene = Scene(mesh)
    assert scene.backend == "python"
    g = render_gbuffer(scene, cam, 24, 24)
    assert abs(g.hit.sum() - math.pi * (0.9 * 12) ** 2) < 0.05 * math.pi * (0.9 * 12) ** 2
    if ref is not None:
        np.testing.assert_array_equal(g.triangle, ref.triangle)
        np.testing.assert_allclose(g.normal, ref.normal, atol=1e-6)
