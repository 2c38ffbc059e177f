"""Tests of ``core.registration.symmetry.truncated_icp``: ICP that leaves alone the rigid
motions a curved phantom's shape does not fix (a dome's yaw), and refines the rest."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from core.lab.shapes import dome_surface, kidney_surface
from core.registration import apply_transform, phantom_rest_surface
from core.registration.symmetry import rotate_about_vertical, truncated_icp


def _surface(tmp_path, V, F):
    path = tmp_path / "phantom.stl"
    trimesh.Trimesh(V, F).export(path)
    points, normals = phantom_rest_surface(None, path, spacing=0.001)
    return points, normals, cKDTree(points)


def _camera_cloud(points, T_true, rng, noise=0.0003):
    """The rest surface's top seen from a camera at ``T_true`` (phantom <- camera), noisy."""
    seen = points[rng.random(points.shape[0]) < 0.3]
    return apply_transform(np.linalg.inv(T_true), seen) + rng.normal(0.0, noise, seen.shape)


def _T_true():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [160.0, 5.0, 30.0], degrees=True).as_matrix()
    T[:3, 3] = [0.02, -0.05, 0.35]
    return T


def _perturbed(T, tilt_deg, shift, yaw_deg, pivot):
    A = np.eye(4)
    A[:3, :3] = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    A[:3, 3] = shift
    return rotate_about_vertical(A @ T, np.deg2rad(yaw_deg), pivot)


def _yaw_deg(T_est, T_true):
    d = T_est[:3, :3] @ T_true[:3, :3].T
    return float(np.degrees(np.arctan2(d[1, 0], d[0, 0])))


def _rms(T, source, points, normals, tree):
    q = apply_transform(T, source)
    _, j = tree.query(q)
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", q - points[j], normals[j]) ** 2)))


def test_a_dome_keeps_its_yaw_and_fits_its_cloud(tmp_path):
    """A spherical cap (70 mm across, 25 mm high) turns freely about its axis, and nearly
    so about its sphere's centre: from a start 4 degrees off in yaw and 2.2 mm off
    sideways, the fit reaches the cloud's noise (0.3 mm: point-to-plane rms below 0.32 mm, from 0.74)
    and keeps the 4 degrees to 0.05 -- the yaw is the instrument's to set, not the cap's.
    (Where on its sphere the cap sits is left to the table: the calibration levels it.)"""
    rng = np.random.default_rng(0)
    points, normals, tree = _surface(tmp_path, *dome_surface())
    pivot = np.array([0.035, 0.035])
    T_true = _T_true()
    source = _camera_cloud(points, T_true, rng)
    start = _perturbed(T_true, 0.0, [0.002, -0.001, 0.0], 4.0, pivot)
    assert _rms(start, source, points, normals, tree) > 7e-4
    T = truncated_icp(start, source, points, normals, tree)
    assert abs(_yaw_deg(T, T_true) - 4.0) < 0.05
    assert _rms(T, source, points, normals, tree) < 3.2e-4
    # the same answer twice (plain ICP of such a cloud drifts differently per run)
    np.testing.assert_array_equal(T, truncated_icp(start, source, points, normals, tree))


def test_a_kidney_refines_its_yaw(tmp_path):
    """A kidney-like ellipsoid (70 x 40 x 30 mm) fixes its yaw: a start 3 degrees off in
    yaw with a 2 mm shift ends within 0.1 degree and 0.3 mm of the truth at its rim."""
    rng = np.random.default_rng(1)
    points, normals, tree = _surface(tmp_path, *kidney_surface())
    T_true = _T_true()
    source = _camera_cloud(points, T_true, rng)
    start = _perturbed(T_true, 0.5, [-0.002, 0.0015, 0.0], 3.0, np.array([0.035, 0.020]))
    T = truncated_icp(start, source, points, normals, tree)
    assert abs(_yaw_deg(T, T_true)) < 0.1
    rim = points[points[:, 2] < 0.002]
    moved = apply_transform(T @ np.linalg.inv(T_true), rim)
    assert np.linalg.norm(moved - rim, axis=1).max() < 3e-4
