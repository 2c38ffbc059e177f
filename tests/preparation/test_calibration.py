"""``core.preparation.calibrate``: the robot is registered on landmark touches when the
session has ``calibration/landmarks.csv`` (normals of ``phantom.stl`` or of the box), on
corner touches otherwise. The camera's ICP is stubbed: it is tested in tests/registration."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import core.preparation.calibration as calibration
from core.errors import SessionFormatError
from core.io import (
    CameraSpec,
    Corners,
    Kinematics,
    LandmarkTouches,
    PhantomSpec,
    ProbeSpec,
    SequenceSpec,
    SessionMeta,
    SessionWriter,
    read_session,
)
from core.registration import apply_transform, calibrate_robot, corner_points_phantom

SIZE = np.array([0.0687, 0.0393, 0.0358])
RADIUS = 0.005
S3 = 1 / np.sqrt(3)
sx, sy, sz = SIZE
# name -> (point, analytic outward normal) of the box [0, SIZE]
BOX = {
    "x0y0": ([0, 0, sz], [-S3, -S3, S3]),
    "x1y0": ([sx, 0, sz], [S3, -S3, S3]),
    "x1y1": ([sx, sy, sz], [S3, S3, S3]),
    "top": ([sx / 2, sy / 3, sz], [0, 0, 1]),
    "front": ([sx / 3, 0, sz / 2], [0, -1, 0]),
}


def T_true() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [150, 5, -3], degrees=True).as_matrix()
    T[:3, 3] = [0.45, 0.1, 0.12]
    return T


def write(path, landmarks, *, corners=False, stl=None):
    names = list(landmarks)
    centres = np.array([np.add(landmarks[n][0], RADIUS * np.asarray(landmarks[n][1])) for n in names])
    meta = SessionMeta(PhantomSpec(SIZE, 0.1), ProbeSpec(RADIUS), CameraSpec(30.0, 0.002),
                       (SequenceSpec("seq00", "train"),),
                       landmarks={n: landmarks[n][0] for n in names})
    robot = apply_transform(np.linalg.inv(T_true()), centres)
    with SessionWriter(path, meta) as w:
        w.write_landmark_touches(LandmarkTouches(tuple(names), robot))
        if corners:
            labels = ("x0y0", "x1y0", "x0y1", "x1y1")
            w.write_corners(Corners(labels, apply_transform(
                np.linalg.inv(T_true()), corner_points_phantom(labels, SIZE, RADIUS)) + 0.001))
        if stl is not None:
            w.write_phantom_stl(stl)
        w.write_kinematics("seq00", Kinematics(np.arange(3.0), np.full((3, 3), 0.4),
                                               np.tile([0, 0, 0, 1.0], (3, 1))))
        w.write_frame("seq00", 0, 0.5, np.array([[0.0, 0.0, 0.3], [0.01, 0.0, 0.3], [0.0, 0.01, 0.3]]))
    return read_session(path)


@pytest.fixture
def no_camera(monkeypatch):
    monkeypatch.setattr(calibration, "instrument_hints", lambda *a, **k: [])
    monkeypatch.setattr(calibration, "calibrate_camera",
                        lambda *a, **k: SimpleNamespace(T=np.eye(4), rms=0.001, fitness=0.9))


def test_landmarks_replace_corners(tmp_path, no_camera):
    session = write(tmp_path / "s", BOX, corners=True)  # corners 1 mm off: must be ignored
    cal = calibration.calibrate(session, picked=None)
    np.testing.assert_allclose(cal.T_phantom_robot, T_true(), atol=1e-12)
    assert cal.robot_rms < 1e-12 and cal.probe_sigma < 1e-12


def test_landmark_normals_come_from_phantom_stl(tmp_path, no_camera):
    """An icosahedron phantom resting on z = 0: the touches go along its vertices' radial
    normals, which a box's normals would get wrong."""
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.02)
    mesh.apply_translation([0.03, 0.02, 0.02])
    v = mesh.vertices[:12]
    landmarks = {f"v{i}": (p, (p - [0.03, 0.02, 0.02]) / 0.02) for i, p in enumerate(v) if i < 6}
    session = write(tmp_path / "s", landmarks, stl=mesh)
    cal = calibration.calibrate(session, picked=None)
    # float32 STL vertices: sub-micrometre differences
    np.testing.assert_allclose(cal.T_phantom_robot, T_true(), atol=1e-6)
    assert cal.robot_rms < 1e-6


def test_corner_sessions_are_calibrated_as_before(tmp_path, no_camera):
    session = write(tmp_path / "s", BOX, corners=True)
    session.landmark_touches = None  # a corner-only session
    cal = calibration.calibrate(session, picked=None)
    expected = calibrate_robot(session.corners, SIZE, RADIUS)
    np.testing.assert_array_equal(cal.T_phantom_robot, expected.T)
    assert cal.robot_rms == expected.rms


def test_an_open_phantom_stl_is_a_session_format_error(tmp_path, no_camera):
    box = trimesh.creation.box(extents=SIZE)
    box.apply_translation(SIZE / 2)
    session = write(tmp_path / "s", BOX, stl=trimesh.Trimesh(box.vertices, box.faces[:-1]))
    with pytest.raises(SessionFormatError, match="watertight") as info:
        calibration.calibrate(session, picked=None)
    assert info.value.path.name == "phantom.stl"
