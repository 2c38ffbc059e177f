"""Tests of ``core.registration.rigid``: Kabsch/Umeyama and robot calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from core.errors import RegistrationError
from core.registration import apply_transform, calibrate_robot, corner_points_phantom, kabsch

SAMPLE = Path(__file__).resolve().parents[2].parent / "shared" / "sample-session"
SIZE = np.array([0.0687, 0.0393, 0.0358])


def random_transform(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = scale * Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return T


def pose_error(A: np.ndarray, B: np.ndarray, points: np.ndarray | None = None) -> tuple[float, float]:
    """(translation error m, rotation error deg) of A against B.

    With ``points`` (in A's source frame), the translation error is the largest
    displacement of those points -- the error where it matters (at the phantom), not at
    the far-away origin of the source frame, where a 0.3 deg rotation error already
    moves the origin by 2 mm on a 0.4 m lever.
    """
    dR = A[:3, :3] @ B[:3, :3].T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    if points is None:
        return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), angle
    return float(np.linalg.norm(apply_transform(A, points) - apply_transform(B, points), axis=1).max()), angle


def box_corners(size=SIZE) -> np.ndarray:
    return np.array([[i * size[0], j * size[1], k * size[2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


# ----------------------------------------------------------------------------- kabsch


def test_kabsch_recovers_transform_exactly():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    T = random_transform(rng)
    fit = kabsch(src, apply_transform(T, src))
    np.testing.assert_allclose(fit.T, T, atol=1e-12)
    assert fit.rms < 1e-12 and fit.scale == 1.0
    assert fit.residuals.shape == (20,)


def test_kabsch_within_noise():
    rng = np.random.default_rng(1)
    src = rng.uniform(-0.05, 0.05, size=(200, 3))
    T = random_transform(rng)
    sigma = 0.001
    dst = apply_transform(T, src) + rng.normal(0, sigma, src.shape)
    fit = kabsch(src, dst)
    # rms of the residual ~ sigma * sqrt(3); pose error ~ sigma / sqrt(N) -> bounds with margin
    assert fit.rms == pytest.approx(sigma * np.sqrt(3), rel=0.15)
    dt, dang = pose_error(fit.T, T, src)
    assert dt < 0.0008 and dang < 0.5


def test_kabsch_with_scale():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3))
    T = random_transform(rng, scale=1.7)
    fit = kabsch(src, apply_transform(T, src), with_scale=True)
    assert fit.scale == pytest.approx(1.7, rel=1e-12)
    np.testing.assert_allclose(fit.T, T, atol=1e-12)
    rigid = kabsch(src, apply_transform(T, src))
    assert rigid.scale == 1.0 and rigid.rms > 0.1


def test_kabsch_weights_ignore_outlier():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(10, 3))
    T = random_transform(rng)
    dst = apply_transform(T, src)
    dst[0] += 5.0
    w = np.ones(10)
    w[0] = 0.0
    fit = kabsch(src, dst, weights=w)
    np.testing.assert_allclose(fit.T, T, atol=1e-10)
    assert fit.residuals[0] == pytest.approx(5.0 * np.sqrt(3), rel=1e-9)


def test_kabsch_never_returns_reflection():
    """Mirrored targets: the best *rotation* is returned (det +1), not the reflection."""
    rng = np.random.default_rng(4)
    src = rng.normal(size=(10, 3))
    fit = kabsch(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(fit.T[:3, :3]) == pytest.approx(1.0)
    assert fit.rms > 0.1


@settings(max_examples=50, deadline=None)
@given(
    quat=st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1),
    shift=st.lists(st.floats(-10, 10, allow_nan=False), min_size=3, max_size=3),
    seed=st.integers(0, 2**31 - 1),
)
def test_kabsch_property_random_rotations(quat, shift, seed):
    R = Rotation.from_quat(quat).as_matrix()
    src = np.random.default_rng(seed).normal(size=(8, 3))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, shift
    fit = kabsch(src, apply_transform(T, src))
    np.testing.assert_allclose(fit.T, T, atol=1e-8)
    assert np.linalg.det(fit.T[:3, :3]) == pytest.approx(1.0)
    # the inverse direction gives the inverse transform
    back = kabsch(apply_transform(T, src), src)
    np.testing.assert_allclose(back.T @ fit.T, np.eye(4), atol=1e-8)


@pytest.mark.parametrize(
    "src, dst, match",
    [
        (np.zeros((5, 2)), np.zeros((5, 2)), r"\(N, 3\)"),
        (np.zeros((5, 3)), np.zeros((4, 3)), "same shape"),
        (np.eye(3)[:2], np.eye(3)[:2], "at least 3"),
        (np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)], np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)], "degenerate"),
        (np.ones((5, 3)), np.random.default_rng(0).normal(size=(5, 3)), "degenerate"),
        (np.full((4, 3), np.nan), np.zeros((4, 3)), "NaN"),
    ],
)
def test_kabsch_bad_input_raises(src, dst, match):
    with pytest.raises(ValueError, match=match):
        kabsch(src, dst)


def test_kabsch_bad_weights_raise():
    src = np.random.default_rng(0).normal(size=(5, 3))
    with pytest.raises(ValueError, match="weights"):
        kabsch(src, src, weights=np.ones(4))
    with pytest.raises(ValueError, match="non-negative"):
        kabsch(src, src, weights=-np.ones(5))


# ----------------------------------------------------------------------------- robot


def synthetic_corners(rng, T_phantom_robot, noise=0.0003, repeats=3, radius=0.005):
    labels = tuple(lab for lab in ("x0y0", "x1y0", "x0y1", "x1y1") for _ in range(repeats))
    centres = corner_points_phantom(labels, SIZE, radius)
    positions = apply_transform(np.linalg.inv(T_phantom_robot), centres) + rng.normal(0, noise, centres.shape)
    return labels, positions


def test_calibrate_robot_synthetic_within_1mm_1deg():
    rng = np.random.default_rng(5)
    for _ in range(5):
        T = random_transform(rng)
        labels, positions = synthetic_corners(rng, T)
        fit = calibrate_robot((labels, positions), SIZE, 0.005)
        dt, dang = pose_error(np.linalg.inv(fit.T), np.linalg.inv(T))  # error at the phantom origin
        assert dt < 0.001 and dang < 1.0
        dt_box, _ = pose_error(fit.T, T, apply_transform(np.linalg.inv(T), box_corners()))
        assert dt_box < 0.001
        assert fit.rms < 0.001 and fit.residuals.shape == (12,)


def test_calibrate_robot_shuffled_corners_raise():
    rng = np.random.default_rng(6)
    T = random_transform(rng)
    labels, positions = synthetic_corners(rng, T)
    swapped = tuple({"x0y0": "x1y0", "x1y0": "x0y0"}.get(s, s) for s in labels[:6]) + labels[6:]
    with pytest.raises(RegistrationError, match=r"rms .* mm.*worst corner") as info:
        calibrate_robot((swapped, positions), SIZE, 0.005)
    assert info.value.rms > 0.0015


def test_calibrate_robot_needs_three_corners():
    rng = np.random.default_rng(7)
    labels, positions = synthetic_corners(rng, random_transform(rng))
    with pytest.raises(RegistrationError, match="3 distinct"):
        calibrate_robot((labels[:6], positions[:6]), SIZE, 0.005)
    with pytest.raises(ValueError, match="unknown corner"):
        calibrate_robot((("x0y0", "x1y0", "x2y2"), positions[:3]), SIZE, 0.005)


@pytest.fixture(scope="module")
def sample():
    if not SAMPLE.is_dir():
        pytest.skip(f"sample session not found at {SAMPLE}")
    from core.io import read_session, read_truth

    return read_session(SAMPLE), read_truth(SAMPLE)


def test_calibrate_robot_sample_session(sample):
    session, truth = sample
    T_true = np.asarray(truth["T_phantom_robot"])
    fit = calibrate_robot(session.corners, session.meta.phantom.size, session.meta.probe.radius)
    # translation error measured over the phantom's corners (see pose_error); the matrix's
    # own translation (robot origin, ~0.5 m away) differs by ~1.6 mm for a 0.33 deg error.
    dt, dang = pose_error(fit.T, T_true, apply_transform(np.linalg.inv(T_true), box_corners(session.meta.phantom.size)))
    assert dt < 0.001 and dang < 1.0
    assert fit.rms < 0.001
