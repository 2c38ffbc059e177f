"""Tests of ``core.registration.landmarks``: outward normals of a rest surface, and robot
calibration from landmark touches (known transforms recovered, bad fits refused)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from core.errors import RegistrationError
from core.registration import (
    apply_transform,
    calibrate_robot,
    calibrate_robot_landmarks,
    corner_points_phantom,
    landmark_normals,
    landmark_points_phantom,
)

SIZE = np.array([0.0687, 0.0393, 0.0358])  # not a cube: corner normals must not depend on it
RADIUS = 0.005
S3, S2 = 1 / np.sqrt(3), 1 / np.sqrt(2)


def box_mesh(size=SIZE) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=size)
    box.apply_translation(np.asarray(size) / 2)  # spans [0, size]: the phantom frame
    return box


# name -> (point, analytic outward normal) on the box [0, SIZE]
sx, sy, sz = SIZE
BOX_LANDMARKS = {
    "x0y0": ([0, 0, sz], [-S3, -S3, S3]),
    "x1y0": ([sx, 0, sz], [S3, -S3, S3]),
    "x0y1": ([0, sy, sz], [-S3, S3, S3]),
    "x1y1": ([sx, sy, sz], [S3, S3, S3]),
    "top": ([sx / 2, sy / 3, sz], [0, 0, 1]),
    "front": ([sx / 3, 0, sz / 2], [0, -1, 0]),
    "right_edge": ([sx, sy / 2, sz], [S2, 0, S2]),
}


def icosahedron_landmarks(radius=0.03):
    """The 12 vertices of an icosahedron inscribed in the sphere, which a subdivided
    icosphere keeps as its first vertices; by symmetry their angle-weighted normal is
    exactly radial. Returns (mesh, name -> (point, analytic normal))."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    v = mesh.vertices[:12]
    return mesh, {f"v{i}": (p, p / np.linalg.norm(p)) for i, p in enumerate(v)}


def random_transform(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return T


def pose_error(A, B, points_phantom) -> tuple[float, float]:
    """Errors of an estimate A of ``T_phantom_robot`` B: (largest displacement m of the
    phantom-frame ``points_phantom``, mapped to the robot frame by B and back by A -- the
    error at the phantom, not at the robot's far-away origin; rotation angle rad, from the
    rotation vector: precise near 0, unlike arccos of the trace)."""
    dR = A[:3, :3] @ B[:3, :3].T
    angle = float(Rotation.from_matrix(dR).magnitude())
    back = apply_transform(A, apply_transform(np.linalg.inv(B), points_phantom))
    return float(np.linalg.norm(back - points_phantom, axis=1).max()), angle


def touches(landmarks, labels, T_phantom_robot, noise=0.0, seed=0):
    """Robot-frame sphere centres touching ``labels`` along the analytic normals."""
    centres = np.array([np.add(landmarks[n][0], RADIUS * np.asarray(landmarks[n][1])) for n in labels])
    pos = apply_transform(np.linalg.inv(T_phantom_robot), centres)
    return pos + np.random.default_rng(seed).normal(0, noise, pos.shape)


def fit_inputs(mesh, landmarks):
    names = list(landmarks)
    points = {n: np.asarray(landmarks[n][0], dtype=float) for n in names}
    normals = landmark_normals(mesh, np.stack([points[n] for n in names]))
    return points, dict(zip(names, normals))


# ------------------------------------------------------------------- landmark_normals


def test_normals_on_a_sphere_are_radial():
    """Angle-weighted vertex normals of a subdivided icosphere match the sphere's analytic
    normal within 1e-3 (measured 6.5e-4 at 81920 faces; the icosahedron's own vertices are
    exact by symmetry). Points 2 mm off the surface get their nearest surface point's
    normal."""
    R = 0.03
    mesh = trimesh.creation.icosphere(subdivisions=6, radius=R)
    rng = np.random.default_rng(0)
    idx = np.r_[np.arange(12), rng.choice(np.arange(12, len(mesh.vertices)), 8, replace=False)]
    v = mesh.vertices[idx]
    radial = v / np.linalg.norm(v, axis=1)[:, None]
    n = landmark_normals(mesh, v)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.linalg.norm(n - radial, axis=1).max() < 1e-3
    np.testing.assert_allclose(landmark_normals(mesh, v + 0.002 * radial), n, atol=1e-12)


def test_normals_at_random_sphere_points_within_faceting():
    """At any point the normal is the face's, so it differs from the analytic one by at
    most the angular size of a face (edge / R)."""
    R = 0.03
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=R)
    d = np.random.default_rng(1).normal(size=(30, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    n = landmark_normals(mesh, R * d)
    assert np.linalg.norm(n - d, axis=1).max() < mesh.edges_unique_length.max() / R
    assert (np.einsum("ij,ij->i", n, d) > 0.99).all()  # outward


def test_normals_on_a_box_face_edge_and_corner():
    mesh = box_mesh()
    names = list(BOX_LANDMARKS)
    points = np.array([BOX_LANDMARKS[k][0] for k in names], dtype=float)
    expected = np.array([BOX_LANDMARKS[k][1] for k in names], dtype=float)
    np.testing.assert_allclose(landmark_normals(mesh, points), expected, atol=1e-12)
    # face interiors of all six faces, including the bottom
    faces = np.array([[sx / 2, sy / 2, 0], [sx / 4, sy / 4, sz], [0, sy / 3, sz / 3],
                      [sx, sy / 3, sz / 3], [sx / 3, 0, sz / 3], [sx / 3, sy, sz / 3]])
    normals = np.array([[0, 0, -1], [0, 0, 1], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0.0]])
    np.testing.assert_allclose(landmark_normals(mesh, faces), normals, atol=1e-12)
    # an inside-out mesh gives the same outward normals
    inverted = mesh.copy()
    inverted.invert()
    np.testing.assert_allclose(landmark_normals(inverted, points), expected, atol=1e-12)


def test_normals_read_an_stl_file(tmp_path):
    path = tmp_path / "phantom.stl"
    box_mesh().export(str(path))
    np.testing.assert_allclose(landmark_normals(path, [[sx, sy, sz]]), [[S3, S3, S3]], atol=1e-6)


def test_normals_refuse_an_open_surface():
    mesh = box_mesh()
    open_mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[:-1])
    with pytest.raises(ValueError, match="watertight"):
        landmark_normals(open_mesh, [[0, 0, sz]])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        landmark_normals(mesh, [0, 0, sz])


# ---------------------------------------------------------- calibrate_robot_landmarks


@pytest.mark.parametrize("shape", ["box", "icosphere"])
def test_recovers_a_random_transform_from_noiseless_touches(shape):
    rng = np.random.default_rng(10)
    if shape == "box":
        mesh, landmarks = box_mesh(), BOX_LANDMARKS
    else:
        mesh, landmarks = icosahedron_landmarks()
    points, normals = fit_inputs(mesh, landmarks)
    labels = list(landmarks)[:6] + list(landmarks)[:2]  # >= 4 landmarks, repeated touches
    for _ in range(3):
        T = random_transform(rng)
        fit = calibrate_robot_landmarks((labels, touches(landmarks, labels, T)), points, normals,
                                        RADIUS)
        dt, dang = pose_error(fit.T, T, np.stack(list(points.values())))
        assert dt < 1e-9 and dang < 1e-9, (dt, dang)
        assert fit.rms < 1e-9 and fit.residuals.shape == (len(labels),)


@pytest.mark.parametrize("seed", range(5))
def test_recovers_the_transform_within_touch_noise(seed):
    """0.2 mm of touch noise on 7 landmarks x 2 touches: within 1 mm at the phantom and 1 deg."""
    rng = np.random.default_rng(100 + seed)
    points, normals = fit_inputs(box_mesh(), BOX_LANDMARKS)
    labels = list(BOX_LANDMARKS) * 2
    T = random_transform(rng)
    fit = calibrate_robot_landmarks((labels, touches(BOX_LANDMARKS, labels, T, 0.0002, seed)),
                                    points, normals, RADIUS)
    dt, dang = pose_error(fit.T, T, np.stack(list(points.values())))
    assert dt < 1e-3 and np.degrees(dang) < 1.0
    assert 0 < fit.rms < 0.0015


def test_refuses_a_bad_touch_and_names_its_landmark():
    rng = np.random.default_rng(7)
    points, normals = fit_inputs(box_mesh(), BOX_LANDMARKS)
    labels = ["x0y0", "x1y0", "x0y1", "x1y1", "front"]
    T = random_transform(rng)
    pos = touches(BOX_LANDMARKS, labels, T)
    pos[4] += 0.005 * np.array([0.6, 0.0, 0.8])  # 'front' touched 5 mm off
    with pytest.raises(RegistrationError, match=r"rms \d+\.\d\d mm exceeds 1\.50 mm; "
                                                r"worst landmark 'front' \(row 4\)") as info:
        calibrate_robot_landmarks((labels, pos), points, normals, RADIUS)
    assert info.value.rms > 0.0015
    # the same touches pass with a looser bound
    fit = calibrate_robot_landmarks((labels, pos), points, normals, RADIUS, max_rms=0.01)
    assert int(np.argmax(fit.residuals)) == 4


def test_refuses_too_few_or_collinear_landmarks():
    points, normals = fit_inputs(box_mesh(), BOX_LANDMARKS)
    T = np.eye(4)
    labels = ["x0y0", "x1y0", "x0y0", "x1y0"]
    with pytest.raises(RegistrationError, match="at least 3 distinct landmarks"):
        calibrate_robot_landmarks((labels, touches(BOX_LANDMARKS, labels, T)), points, normals, RADIUS)
    line = dict(BOX_LANDMARKS, mid=([sx / 2, 0, sz], [0, -S2, S2]))
    points["mid"], normals["mid"] = np.array(line["mid"][0]), np.array(line["mid"][1])
    labels = ["x0y0", "x1y0", "mid"]
    with pytest.raises(RegistrationError, match="collinear"):
        calibrate_robot_landmarks((labels, touches(line, labels, T)), points, normals, RADIUS)
    with pytest.raises(ValueError, match="unknown landmark 'apex'"):
        calibrate_robot_landmarks((["apex", "x0y0", "x1y0"], np.zeros((3, 3))), points, normals,
                                  RADIUS)


def test_corner_convention_relation():
    """corners.csv touches the top corners from above: centre = corner + (0, 0, r), what the
    landmark path gives with +z normals (and then the same fit as calibrate_robot). The
    corners' own (diagonal) normals put the centre elsewhere: sqrt(2/3) r horizontally and
    (1 - 1/sqrt(3)) r vertically."""
    corners = ["x0y0", "x1y0", "x0y1", "x1y1"]
    points = {n: np.array(BOX_LANDMARKS[n][0], dtype=float) for n in corners}
    up = {n: np.array([0, 0, 1.0]) for n in corners}
    labels = corners + ["x1y1"]
    np.testing.assert_allclose(landmark_points_phantom(labels, points, up, RADIUS),
                               corner_points_phantom(labels, SIZE, RADIUS), atol=1e-15)
    rng = np.random.default_rng(5)
    pos = apply_transform(random_transform(rng), corner_points_phantom(labels, SIZE, RADIUS))
    pos += rng.normal(0, 0.0002, pos.shape)
    a = calibrate_robot_landmarks((labels, pos), points, up, RADIUS)
    b = calibrate_robot((labels, pos), SIZE, RADIUS)
    np.testing.assert_allclose(a.T, b.T, atol=1e-12)
    np.testing.assert_allclose(a.residuals, b.residuals, atol=1e-12)

    diagonal = dict(zip(corners, landmark_normals(box_mesh(), np.stack(list(points.values())))))
    d = landmark_points_phantom(corners, points, diagonal, RADIUS) - corner_points_phantom(corners, SIZE, RADIUS)
    np.testing.assert_allclose(np.linalg.norm(d[:, :2], axis=1), np.sqrt(2 / 3) * RADIUS, rtol=1e-9)
    np.testing.assert_allclose(d[:, 2], -(1 - S3) * RADIUS, rtol=1e-9)
