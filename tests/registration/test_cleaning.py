"""Tests of ``core.registration.cleaning`` on raycast synthetic depth frames.

The synthetic scene (:func:`raycast_scene`) is built independently of the code under test:
an Open3D ``RaycastingScene`` of the box phantom, a table slab, and the instrument (sphere
tip + shaft cylinder), seen by a pinhole camera with depth noise, quantisation, dropouts
and stray outliers; every point carries the label of what it hit.
"""

from __future__ import annotations


import numpy as np
import pytest

from core.errors import CleaningError
from core.registration import clean_cloud, find_table_plane
from core.registration.cleaning import instrument_mask

SIZE = np.array([0.0687, 0.0393, 0.0358])
PHANTOM, TABLE, INSTRUMENT, OUTLIER = 0, 1, 2, 3


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_phantom_camera of a camera at ``eye`` looking at ``target`` (camera z forward, y down)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.c_[x, y, z]
    T[:3, 3] = eye
    return T


def _rotation_to(a: np.ndarray) -> np.ndarray:
    """A rotation taking +z onto unit vector ``a``."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, a)
    c = float(z @ a)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def raycast_scene(
    *,
    seed: int = 0,
    eye=(0.20, -0.12, 0.26),
    probe_centre=(0.030, 0.020, SIZE[2] + 0.005 - 0.004),
    tool_axis=(0.45, 0.2, -0.87),
    probe_radius: float = 0.005,
    shaft_radius: float = 0.004,
    width: int = 320,
    height: int = 240,
    focal: float = 254.0,
    noise: float = 0.001,
    quantum: float = 0.0005,
    dropout: float = 0.05,
    n_outliers: int = 40,
    table: bool = True,
    instrument: bool = True,
    shape=SIZE,
    roi: tuple[int, int, int, int] | None = None,
):
    """Raw synthetic depth frame: (points_camera (N, 3), labels (N,), T_phantom_camera (4, 4)).

    The phantom box spans [0, sx] x [0, sy] x [0, sz] (phantom frame); the table is a
    0.5 m slab with its top at z = 0; the instrument is a sphere at ``probe_centre`` plus
    a shaft cylinder from the centre along ``-tool_axis``. The probe may dent into the
    box (rays hit whichever surface is first, as a depth camera would).
    """
    import open3d as o3d

    rng = np.random.default_rng(seed)
    shape = np.asarray(shape, dtype=float)
    meshes, labels_of = [], []
    box = o3d.geometry.TriangleMesh.create_box(*shape)
    meshes.append(box)
    labels_of.append(PHANTOM)
    if table:
        slab = o3d.geometry.TriangleMesh.create_box(0.5, 0.5, 0.02)
        slab.translate((shape[0] / 2 - 0.25, shape[1] / 2 - 0.25, -0.02))
        meshes.append(slab)
        labels_of.append(TABLE)
    if instrument:
        c = np.asarray(probe_centre, dtype=float)
        a = np.asarray(tool_axis, dtype=float)
        a /= np.linalg.norm(a)
        sphere = o3d.geometry.TriangleMesh.create_sphere(probe_radius, resolution=40)
        sphere.translate(c)
        length = 0.2
        cyl = o3d.geometry.TriangleMesh.create_cylinder(shaft_radius, length, resolution=40)
        cyl.rotate(_rotation_to(-a), center=(0, 0, 0))
        cyl.translate(c - a * length / 2)
        meshes += [sphere, cyl]
        labels_of += [INSTRUMENT, INSTRUMENT]
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))

    T_pc = look_at(np.asarray(eye, float), shape / 2)
    u0, u1, v0, v1 = roi if roi is not None else (0, width, 0, height)  # a depth camera's ROI crop
    u, v = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
    d_cam = np.stack([(u.ravel() - width / 2) / focal, (v.ravel() - height / 2) / focal,
                      np.ones(u.size)], axis=1)  # z = 1 rays in the camera frame
    d_world = d_cam @ T_pc[:3, :3].T
    rays = np.concatenate([np.tile(T_pc[:3, 3], (d_world.shape[0], 1)), d_world], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy().astype(float)
    gid = ans["geometry_ids"].numpy()
    hit = np.isfinite(t_hit) & (rng.random(t_hit.size) > dropout)
    depth = t_hit[hit]  # = camera-frame z because the rays have unit z
    depth = np.round((depth + rng.normal(0, noise, depth.size)) / quantum) * quantum
    pts = d_cam[hit] * depth[:, None]
    labels = np.asarray(labels_of)[gid[hit]]
    if n_outliers:
        k = rng.integers(0, u.size, n_outliers)
        od = rng.uniform(0.1, 0.45, n_outliers)
        pts = np.concatenate([pts, d_cam[k] * od[:, None]])
        labels = np.concatenate([labels, np.full(n_outliers, OUTLIER)])
    return pts, labels, T_pc


def _removed_fraction(labels, kept_mask, what):
    sel = labels == what
    return 1.0 - kept_mask[sel].mean()


def _kept_mask(points_camera, T_pc, result):
    """Which input points survive: match kept phantom-frame points back by exact coordinates."""
    q = points_camera @ T_pc[:3, :3].T + T_pc[:3, 3]
    kept = {tuple(np.round(p, 9)) for p in result.points_phantom}
    return np.array([tuple(np.round(p, 9)) in kept for p in q])


@pytest.fixture(scope="module")
def scene():
    return raycast_scene(seed=1)


def test_scene_has_every_kind(scene):
    pts, labels, _ = scene
    counts = np.bincount(labels, minlength=4)
    assert counts[PHANTOM] > 1000 and counts[TABLE] > 1000 and counts[INSTRUMENT] > 100 and counts[OUTLIER] > 10


def test_clean_cloud_removes_table_instrument_outliers(scene):
    pts, labels, T_pc = scene
    centre = np.array([0.030, 0.020, SIZE[2] + 0.001])
    axis = np.array([0.45, 0.2, -0.87]) / np.linalg.norm([0.45, 0.2, -0.87])
    res = clean_cloud(pts, T_pc, SIZE, probe_centre_phantom=centre, shaft_axis_phantom=axis,
                      probe_radius=0.005, shaft_radius=0.0045)
    kept = _kept_mask(pts, T_pc, res)
    assert kept.sum() == res.counts["kept"]
    # Tolerances: 95 % / 90 % as specified; the misses are table points noise lifted by
    # > 3 mm (3 sigma) next to the phantom and instrument points beyond radius + 2 mm.
    assert _removed_fraction(labels, kept, TABLE) > 0.95
    assert _removed_fraction(labels, kept, INSTRUMENT) > 0.95
    assert _removed_fraction(labels, kept, OUTLIER) > 0.95
    assert kept[labels == PHANTOM].mean() > 0.90
    assert res.table_source == "ransac"
    c = res.counts
    assert c["raw"] == pts.shape[0]
    assert c["invalid"] + c["table"] + c["instrument"] + c["outliers"] + c["downsampled"] + c["kept"] == c["raw"]
    assert res.points_phantom.dtype == np.float64 and res.points_phantom.shape == (c["kept"], 3)


def test_clean_cloud_without_instrument_pose_keeps_instrument_but_not_table(scene):
    pts, labels, T_pc = scene
    res = clean_cloud(pts, T_pc, SIZE)
    kept = _kept_mask(pts, T_pc, res)
    assert _removed_fraction(labels, kept, TABLE) > 0.95
    assert res.counts["instrument"] == 0


def test_table_found_without_ransac_candidates_falls_back_to_calibration():
    pts, labels, T_pc = raycast_scene(seed=2, table=False)
    res = clean_cloud(pts, T_pc, SIZE, probe_centre_phantom=np.array([0.03, 0.02, SIZE[2] + 0.001]),
                      shaft_axis_phantom=np.array([0.45, 0.2, -0.87]))
    assert res.table_source == "calibration"
    kept = _kept_mask(pts, T_pc, res)
    assert kept[labels == PHANTOM].mean() > 0.90


def test_tilted_table_is_fitted_by_ransac(scene):
    """A calibration 1 deg off in tilt: RANSAC still finds the table (not z = 0)."""
    pts, labels, T_pc = scene
    from scipy.spatial.transform import Rotation

    T_tilt = np.eye(4)
    T_tilt[:3, :3] = Rotation.from_euler("x", 1.0, degrees=True).as_matrix()
    T_off = T_tilt @ T_pc
    res = clean_cloud(pts, T_off, SIZE)
    assert res.table_source == "ransac"
    n = res.table_plane[:3]
    assert np.degrees(np.arccos(n[2])) == pytest.approx(1.0, abs=0.3)


def test_downsampling(scene):
    pts, _, T_pc = scene
    full = clean_cloud(pts, T_pc, SIZE, seed=3)
    vox = clean_cloud(pts, T_pc, SIZE, voxel_size=0.003, seed=3)
    assert vox.counts["kept"] < full.counts["kept"]
    sub = clean_cloud(pts, T_pc, SIZE, max_points=500, seed=3)
    again = clean_cloud(pts, T_pc, SIZE, max_points=500, seed=3)
    assert sub.points_phantom.shape == (500, 3)
    np.testing.assert_array_equal(sub.points_phantom, again.points_phantom)
    assert sub.counts["downsampled"] == full.counts["kept"] - 500


def test_nothing_left_raises(scene):
    pts, _, T_pc = scene
    far = T_pc.copy()
    far[:3, 3] += np.array([1.0, 0.0, 0.0])  # the cloud lands 1 m away from the phantom
    with pytest.raises(CleaningError, match="nothing of the phantom"):
        clean_cloud(pts, far, SIZE)


def test_bad_shapes_raise(scene):
    pts, _, T_pc = scene
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        clean_cloud(pts[:, :2], T_pc, SIZE)
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        clean_cloud(pts, T_pc[:3], SIZE)


def test_non_finite_points_are_counted_and_dropped(scene):
    pts, _, T_pc = scene
    bad = pts.copy()
    bad[:10] = np.nan
    res = clean_cloud(bad, T_pc, SIZE)
    assert res.counts["invalid"] == 10
    assert np.all(np.isfinite(res.points_phantom))


def test_find_table_plane_picks_table_not_top(scene):
    pts, labels, T_pc = scene
    table = find_table_plane(pts, phantom_height=float(SIZE[2]))
    # the plane in the phantom frame: its points should be at z ~ 0
    inl = pts[table.inliers] @ T_pc[:3, :3].T + T_pc[:3, 3]
    assert abs(np.median(inl[:, 2])) < 0.002
    assert np.mean(labels[table.inliers] == TABLE) > 0.95


def test_cleaning_paper_sized_frame():
    """A ~45k-point frame (the paper's cloud size) is cleaned: the instrument goes,
    the phantom stays. (Its speed is measured in benchmarks/, not asserted here.)"""
    pts, labels, T_pc = raycast_scene(seed=4, width=640, height=480, focal=508.0, eye=(0.12, -0.08, 0.2),
                                      roi=(170, 470, 165, 315))
    n = pts.shape[0]
    res = clean_cloud(pts, T_pc, SIZE, probe_centre_phantom=np.array([0.03, 0.02, SIZE[2] + 0.001]),
                      shaft_axis_phantom=np.array([0.45, 0.2, -0.87]))
    assert 40000 < n < 60000
    assert res.counts["kept"] > 10000
    assert sum(v for k, v in res.counts.items() if k != "raw") == res.counts["raw"]


def test_cleaning_is_deterministic_on_a_real_frame(sample_session):
    """Sweeps compare many runs on the same cleaned clouds: cleaning must not depend on
    open3d's multithreaded RANSAC sample (regression: it did)."""
    import json

    from core.io import read_session

    session = read_session(sample_session)
    T = np.array(json.loads((sample_session / "truth.json").read_text())["T_phantom_camera"])
    pts = session.sequences["seq02"].cloud(60)
    runs = [clean_cloud(pts, T, session.meta.phantom.size, voxel_size=0.001, seed=7).points_phantom for _ in range(6)]
    for r in runs[1:]:
        np.testing.assert_array_equal(r, runs[0])


def test_a_probe_bigger_than_nominal_is_still_removed_above_the_top():
    """A 7.5 mm sphere recorded as 5 mm: the corner-touch calibration puts its centre
    2.5 mm low, so its cap is 8-10 mm from the calibrated centre, past the 2 mm margin.
    Points more than 3 mm above the rest top near the probe go; the phantom's dent
    around it stays."""
    top = 0.0358
    cal = np.array([0.03, 0.02, top - 0.006 + 0.005])  # 6 mm deep, nominal radius
    true = cal + [0.0, 0.0, 0.0025]
    rng = np.random.default_rng(0)
    u = rng.normal(size=(4000, 3))
    sphere = true + 0.0075 * u / np.linalg.norm(u, axis=1, keepdims=True)
    visible = sphere[sphere[:, 2] > top]  # what sticks out of the phantom
    ring = np.column_stack([cal[0] + 0.012 * np.cos(np.linspace(0, 6.28, 200)),
                            cal[1] + 0.012 * np.sin(np.linspace(0, 6.28, 200)), np.full(200, top - 0.001)])
    kw = dict(probe_radius=0.005, shaft_radius=0.0045, margin=0.002)
    old = instrument_mask(visible, cal, None, **kw)
    assert old.mean() < 0.5  # the nominal sphere alone leaves most of the cap
    new = instrument_mask(visible, cal, None, top_z=top, **kw)
    assert np.all(new[visible[:, 2] > top + 0.003])
    assert not instrument_mask(ring, cal, None, top_z=top, **kw).any()
