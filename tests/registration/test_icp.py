"""Tests of ``core.registration.icp``: rest surface, camera calibration (auto and picked)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.errors import RegistrationError
from core.registration import (
    apply_transform,
    calibrate_camera,
    calibrate_robot,
    instrument_hints,
    instrument_support,
    phantom_rest_surface,
)

from .test_cleaning import raycast_scene
from .test_rigid import box_corners, pose_error

SAMPLE = Path(__file__).resolve().parents[2].parent / "shared" / "sample-session"
SIZE = np.array([0.0687, 0.0393, 0.0358])


def flip_about_vertical(T_phantom_camera: np.ndarray, size=SIZE) -> np.ndarray:
    """The box-symmetric twin: rotate the phantom frame 180 deg about its vertical centre axis."""
    F = np.diag([-1.0, -1.0, 1.0, 1.0])
    F[:2, 3] = size[:2]
    return F @ T_phantom_camera


# ----------------------------------------------------------------------------- surface


def test_rest_surface_box_lies_on_box_without_bottom():
    pts, nrm = phantom_rest_surface(SIZE, spacing=0.001)
    assert pts.shape == nrm.shape and pts.dtype == np.float64 and pts.shape[1] == 3
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0)
    # every sample is on a face and its normal is that face's outward normal
    on_face = ((np.isclose(pts[:, 2], SIZE[2]) & (nrm[:, 2] == 1))
               | (np.isclose(pts[:, 0], 0) & (nrm[:, 0] == -1)) | (np.isclose(pts[:, 0], SIZE[0]) & (nrm[:, 0] == 1))
               | (np.isclose(pts[:, 1], 0) & (nrm[:, 1] == -1)) | (np.isclose(pts[:, 1], SIZE[1]) & (nrm[:, 1] == 1)))
    assert on_face.all()
    assert not np.any(nrm[:, 2] < 0)  # no bottom face
    # density: about one sample per mm^2 of the five faces
    area = SIZE[0] * SIZE[1] + 2 * SIZE[2] * (SIZE[0] + SIZE[1])
    assert 0.9 < pts.shape[0] * 1e-6 / area < 1.3


def test_rest_surface_from_stl(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=SIZE)
    box.apply_translation(SIZE / 2)
    path = tmp_path / "phantom.stl"
    box.export(path)
    pts, nrm = phantom_rest_surface(SIZE, path, spacing=0.001)
    assert pts.shape[0] > 5000
    assert not np.any(nrm[:, 2] < -0.5)
    assert pts.min() > -1e-6 and np.all(pts.max(axis=0) < SIZE + 1e-6)
    # points lie on the box surface: distance to the nearest face ~ 0
    d = np.minimum(np.minimum(pts, SIZE - pts).min(axis=1), 1)
    assert d.max() < 1e-6


# ----------------------------------------------------------------------------- synthetic


@pytest.fixture(scope="module")
def synthetic():
    ref, _, T_pc = raycast_scene(seed=10, instrument=False, n_outliers=20)
    hints = []
    for k, (x, y) in enumerate([(0.015, 0.012), (0.05, 0.025)]):
        centre = np.array([x, y, SIZE[2] + 0.004])
        axis = np.array([0.45, 0.2, -0.87]) / np.linalg.norm([0.45, 0.2, -0.87])
        pts, _, T2 = raycast_scene(seed=20 + k, probe_centre=centre, tool_axis=axis)
        np.testing.assert_array_equal(T2, T_pc)
        hints.append((pts, centre, axis))
    return ref, T_pc, hints


def test_auto_calibration_synthetic(synthetic):
    ref, T_pc, hints = synthetic
    fit = calibrate_camera(ref, SIZE, hints=hints)
    dt, dang = pose_error(fit.T, T_pc, apply_transform(np.linalg.inv(T_pc), box_corners()))
    assert dt < 0.001 and dang < 1.0
    assert fit.method == "auto" and fit.fitness > 0.9 and fit.rms < 0.0015 and fit.coverage > 0.9
    assert fit.residuals.ndim == 1 and fit.T_init.shape == (4, 4)


def test_hints_score_the_right_twin(synthetic):
    _, T_pc, hints = synthetic
    right = instrument_support(T_pc, hints, SIZE)
    wrong = instrument_support(flip_about_vertical(T_pc), hints, SIZE)
    assert right > 100 and right > 5 * wrong


def test_auto_without_hints_is_ambiguous(synthetic):
    ref, _, _ = synthetic
    with pytest.raises(RegistrationError, match="symmetric"):
        calibrate_camera(ref, SIZE)


def test_auto_with_uninformative_hints_raises(synthetic):
    ref, _, hints = synthetic
    # the instrument is "reported" where nothing is: no candidate gets support
    useless = [(pts, np.array([0.3, 0.3, 0.3]), axis) for pts, _, axis in hints]
    with pytest.raises(RegistrationError, match="cannot resolve"):
        calibrate_camera(ref, SIZE, hints=useless)


def test_picked_calibration_synthetic(synthetic):
    ref, T_pc, _ = synthetic
    rng = np.random.default_rng(0)
    top = box_corners()[box_corners()[:, 2] > 0]
    picked_cam = apply_transform(np.linalg.inv(T_pc), top) + rng.normal(0, 0.002, top.shape)
    fit = calibrate_camera(ref, SIZE, picked=(picked_cam, top))
    dt, dang = pose_error(fit.T, T_pc, apply_transform(np.linalg.inv(T_pc), box_corners()))
    assert dt < 0.001 and dang < 1.0 and fit.method == "picked"


def test_wrong_shape_raises(synthetic):
    ref, T_pc, hints = synthetic
    for wrong in ([0.10, 0.06, 0.0358], [0.05, 0.03, 0.0358]):
        with pytest.raises(RegistrationError, match="measures"):
            calibrate_camera(ref, wrong, hints=hints)
    # picked init on a model 1.5x too large: poorly covered top face -> fit rejected
    big = SIZE * np.array([1.5, 1.5, 1.0])
    top = box_corners()[box_corners()[:, 2] > 0]
    with pytest.raises(RegistrationError):
        calibrate_camera(ref, big, picked=(apply_transform(np.linalg.inv(T_pc), top), top))


def test_picked_inconsistent_raises(synthetic):
    ref, T_pc, _ = synthetic
    top = box_corners()[box_corners()[:, 2] > 0]
    cam = apply_transform(np.linalg.inv(T_pc), top)
    with pytest.raises(RegistrationError, match="do not match"):
        calibrate_camera(ref, SIZE, picked=(cam, top[[1, 0, 3, 2]] * 3))
    with pytest.raises(ValueError, match="K >= 3"):
        calibrate_camera(ref, SIZE, picked=(cam[:2], top[:2]))


def test_not_a_box_raises():
    """A sphere of points on a table is no box: the fit must fail loudly."""
    rng = np.random.default_rng(1)
    table = np.c_[rng.uniform(-0.1, 0.1, (3000, 2)), np.zeros(3000)]
    d = rng.normal(size=(3000, 3))
    d[:, 2] = np.abs(d[:, 2])
    ball = 0.03 * d / np.linalg.norm(d, axis=1, keepdims=True) + [0, 0, 0.0]
    T_cp = np.eye(4)
    T_cp[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T_cp[:3, 3] = [0, 0, 0.3]  # camera 0.3 m above, looking down
    cloud = apply_transform(np.linalg.inv(T_cp), np.concatenate([table, ball]))
    with pytest.raises(RegistrationError):
        calibrate_camera(cloud, SIZE)


# ----------------------------------------------------------------------------- sample session


@pytest.fixture(scope="module")
def sample():
    if not SAMPLE.is_dir():
        pytest.skip(f"sample session not found at {SAMPLE}")
    from core.io import read_session, read_truth

    session = read_session(SAMPLE)
    truth = read_truth(SAMPLE)
    robot = calibrate_robot(session.corners, session.meta.phantom.size, session.meta.probe.radius)
    return session, truth, robot


def _box_error(T, T_true, size):
    return pose_error(T, T_true, apply_transform(np.linalg.inv(T_true), box_corners(size)))


def test_sample_auto_calibration_with_hints(sample):
    session, truth, robot = sample
    T_true = np.asarray(truth["T_phantom_camera"])
    size = session.meta.phantom.size
    seq = session.sequences[sorted(session.sequences)[0]]
    hints = instrument_hints(seq, robot.T, frames=(0, 1, 2))
    fit = calibrate_camera(session.reference_cloud(), size, probe_radius=session.meta.probe.radius, hints=hints)
    dt, dang = _box_error(fit.T, T_true, size)
    assert dt < 0.001 and dang < 1.0
    # the matrix's own translation (camera origin ~0.3 m away) is within 1 mm as well
    assert np.linalg.norm(fit.T[:3, 3] - T_true[:3, 3]) < 0.001
    assert fit.method == "auto" and fit.fitness > 0.95 and fit.rms < 0.0015


def test_sample_picked_calibration(sample):
    session, truth, _ = sample
    T_true = np.asarray(truth["T_phantom_camera"])
    size = session.meta.phantom.size
    top = box_corners(size)[box_corners(size)[:, 2] > 0]
    rng = np.random.default_rng(2)
    picked_cam = apply_transform(np.linalg.inv(T_true), top) + rng.normal(0, 0.002, top.shape)  # ~2 mm clicks
    fit = calibrate_camera(session.reference_cloud(), size, picked=(picked_cam, top))
    dt, dang = _box_error(fit.T, T_true, size)
    assert dt < 0.001 and dang < 1.0 and fit.method == "picked"


def test_sample_wrong_size_raises(sample):
    session, _, robot = sample
    seq = session.sequences[sorted(session.sequences)[0]]
    hints = instrument_hints(seq, robot.T, frames=(0,))
    with pytest.raises(RegistrationError):
        calibrate_camera(session.reference_cloud(), session.meta.phantom.size * [1.4, 1.4, 1.0], hints=hints)
