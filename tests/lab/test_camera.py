"""Depth camera: geometry of the ray cast against a known box, occlusion, noise statistics."""

import numpy as np
import pytest

from core.lab.camera import (
    GEOMETRY_PHANTOM,
    GEOMETRY_SHAFT,
    GEOMETRY_SPHERE,
    GEOMETRY_TABLE,
    DepthCamera,
    DepthNoise,
    Instrument,
    Intrinsics,
    apply_depth_noise,
    cast,
    depth_to_points,
    look_at_pose,
    random_camera_pose,
    render_points,
    roi_for_box,
    table_mesh,
    table_ring_mask,
)

SIZE = np.array([0.0687, 0.0393, 0.0358])
TOP = np.array([SIZE[0] / 2, SIZE[1] / 2, SIZE[2]])
NO_NOISE = DepthNoise(sigma=0.0, quantization=0.0, dropout=0.0, grazing_cos=(0.0, 0.0),
                      flying_fraction=0.0, outlier_fraction=0.0)


def box_surface():
    """Closed box [0, SIZE] as 8 vertices and 12 outward triangles (independent of core.simulation)."""
    import trimesh

    m = trimesh.creation.box(extents=SIZE)
    return np.asarray(m.vertices) + SIZE / 2, np.asarray(m.faces)


def to_phantom(T, pts):
    return pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]


@pytest.fixture(scope="module")
def camera():
    T = look_at_pose(TOP + np.array([-0.15, 0.0, 0.26]), TOP)  # 30 deg from vertical, 0.3 m
    K = Intrinsics.from_fov(320, 240, 64.0)
    roi = roi_for_box(K, T, (-0.02, -0.02, -0.001), SIZE + [0.02, 0.02, 0.02])
    return DepthCamera(K, T, roi, NO_NOISE)


def test_look_at_pose_is_opencv_convention():
    T = look_at_pose([0, 0, 1.0], [0, 0, 0], up=[0, 1, 0])
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1])  # z forward
    np.testing.assert_allclose(T[:3, 1], [0, -1, 0])  # y down in the image = -up


def test_random_pose_distance_and_tilt():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = random_camera_pose(rng, TOP)
        eye, z = T[:3, 3], T[:3, 2]
        assert 0.24 < np.linalg.norm(eye - TOP) < 0.36
        tilt = np.degrees(np.arccos(-z[2]))
        assert 18 < tilt < 47


def test_box_top_points_lie_on_the_top_and_table_is_present(camera):
    verts, tris = box_surface()
    hits = cast(camera, (verts, tris), table=table_mesh(TOP))
    pts = to_phantom(camera.T_phantom_camera, depth_to_points(camera, hits.depth))
    geom = hits.geometry[np.isfinite(hits.depth)]
    top = geom == GEOMETRY_PHANTOM
    top &= pts[:, 2] > SIZE[2] - 1e-4
    assert top.sum() > 1000
    np.testing.assert_allclose(pts[top, 2], SIZE[2], atol=1e-5)  # float32 rays: ~1e-6 m
    table = pts[geom == GEOMETRY_TABLE]
    assert len(table) > 500
    np.testing.assert_allclose(table[:, 2], -1e-5, atol=1e-5)  # the phantom rests on the table (z = 0)
    # a camera at -x sees the -x face but not the +x face
    phantom = pts[geom == GEOMETRY_PHANTOM]
    assert np.any(np.abs(phantom[:, 0]) < 1e-5)
    assert not np.any((np.abs(phantom[:, 0] - SIZE[0]) < 1e-5) & (phantom[:, 2] < SIZE[2] - 1e-3))


def test_instrument_occludes_the_phantom(camera):
    verts, tris = box_surface()
    centre = TOP + np.array([0.0, 0.0, 0.004])  # sphere 1 mm into the top
    shaft = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    inst = Instrument(centre=centre, shaft_direction=shaft)
    free = cast(camera, (verts, tris), table=table_mesh(TOP))
    occluded = cast(camera, (verts, tris), table=table_mesh(TOP), instrument=inst)
    g = occluded.geometry
    assert (g == GEOMETRY_SPHERE).sum() > 20 and (g == GEOMETRY_SHAFT).sum() > 20
    # phantom pixels behind the instrument are gone
    lost = (free.geometry == GEOMETRY_PHANTOM) & (g != GEOMETRY_PHANTOM)
    assert lost.sum() > 50
    # instrument points are nearer than what they hide, and lie on the sphere / shaft
    assert np.all(occluded.depth[lost] < free.depth[lost])
    pts = to_phantom(camera.T_phantom_camera, depth_to_points(camera, np.where(g == GEOMETRY_SPHERE, occluded.depth, np.nan)))
    np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), 0.005, atol=2e-4)  # icosphere facets
    # no phantom point lies inside the probe sphere
    pp = to_phantom(camera.T_phantom_camera, depth_to_points(camera, np.where(g == GEOMETRY_PHANTOM, occluded.depth, np.nan)))
    assert np.all(np.linalg.norm(pp - centre, axis=1) > 0.005 - 2e-4)


def test_depth_noise_statistics(camera):
    """The depth error is unbiased with sigma * (z / z_ref)^2; quantisation adds q^2/12."""
    verts, tris = box_surface()
    hits = cast(camera, (verts, tris), table=table_mesh(TOP))
    noise = DepthNoise(sigma=0.001, quantization=0.00025, dropout=0.0, grazing_cos=(0.0, 0.0),
                       flying_fraction=0.0, outlier_fraction=0.0)
    rng = np.random.default_rng(1)
    z0 = hits.depth
    ok = np.isfinite(z0)
    errs = []
    for _ in range(5):
        z = apply_depth_noise(hits, noise, rng)
        errs.append(((z - z0) / (z0 / 0.3) ** 2)[ok])
    e = np.concatenate(errs)
    # ~1e5 samples: the std estimate is good to ~0.5 %; the quantisation adds 0.25 mm / sqrt(12)
    expected = np.sqrt(0.001**2 + (0.00025**2 / 12) / np.mean((z0[ok] / 0.3) ** 4))
    assert np.std(e) == pytest.approx(expected, rel=0.03)
    assert abs(np.mean(e)) < 5e-5
    # quantised to 0.25 mm steps
    zq = apply_depth_noise(hits, noise, rng)[ok]
    np.testing.assert_allclose(zq / 0.00025, np.round(zq / 0.00025), atol=1e-6)


def test_dropouts_grazing_angles_and_outliers(camera):
    verts, tris = box_surface()
    hits = cast(camera, (verts, tris), table=table_mesh(TOP))
    n_valid = np.isfinite(hits.depth).sum()
    rng = np.random.default_rng(2)
    only_drop = DepthNoise(sigma=0.0, quantization=0.0, dropout=0.05, grazing_cos=(0.0, 0.0),
                           flying_fraction=0.0, outlier_fraction=0.0)
    z = apply_depth_noise(hits, only_drop, rng)
    assert np.isfinite(z).sum() / n_valid == pytest.approx(0.95, abs=0.01)
    graze = DepthNoise(sigma=0.0, quantization=0.0, dropout=0.0, grazing_cos=(0.12, 0.3),
                       flying_fraction=0.0, outlier_fraction=0.0)
    z = apply_depth_noise(hits, graze, rng)
    assert not np.any(np.isfinite(z) & (hits.cos_incidence < 0.12))
    assert np.all(np.isfinite(z) | (hits.cos_incidence < 0.3) | ~np.isfinite(hits.depth))
    fly = DepthNoise(sigma=0.0, quantization=0.0, dropout=0.0, grazing_cos=(0.0, 0.0),
                     flying_fraction=0.004, outlier_fraction=0.001)
    z = apply_depth_noise(hits, fly, rng)
    moved = np.isfinite(z) & (np.abs(z - hits.depth) > 1e-9)
    assert moved.sum() / n_valid == pytest.approx(0.005, abs=0.0015)


def test_table_ring_keeps_a_margin_of_table(camera):
    verts, tris = box_surface()
    rays = camera.rays_phantom()
    keep = table_ring_mask(rays, (-0.01, -0.01), SIZE[:2] + 0.01)
    hits = cast(camera, (verts, tris), table=table_mesh(TOP), rays=rays, table_keep=keep)
    pts = to_phantom(camera.T_phantom_camera, depth_to_points(camera, hits.depth))
    table = pts[hits.geometry[np.isfinite(hits.depth)] == GEOMETRY_TABLE]
    assert len(table) > 100
    assert np.all(table[:, :2] >= -0.01 - 1e-6) and np.all(table[:, :2] <= SIZE[:2] + 0.01 + 1e-6)


def test_render_points_is_float32_camera_frame_and_seeded(camera):
    verts, tris = box_surface()
    cam = DepthCamera(camera.intrinsics, camera.T_phantom_camera, camera.roi, DepthNoise())
    a = render_points(cam, (verts, tris), np.random.default_rng(5), table=table_mesh(TOP))
    b = render_points(cam, (verts, tris), np.random.default_rng(5), table=table_mesh(TOP))
    c = render_points(cam, (verts, tris), np.random.default_rng(6), table=table_mesh(TOP))
    assert a.dtype == np.float32 and a.shape[1] == 3
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or np.any(a != c)
    assert np.median(a[:, 2]) == pytest.approx(0.3, abs=0.05)  # camera frame: z forward, ~0.3 m
