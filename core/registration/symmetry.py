"""The camera's yaw about a phantom of any shape, from the instrument in view.

A dome is symmetric under every rotation about its vertical axis, a kidney-like
ellipsoid under half turns: ICP of the reference cloud (:mod:`core.registration.icp`)
then fixes the table plane and the footprint's position, but not the yaw. The robot
knows where its instrument is in the phantom frame (kinematics through
``T_phantom_robot``, from the landmark touches), and raw frames show it: under the right
yaw, the raw points that the rest phantom does not explain fall on the instrument's
sphere and shaft. :func:`resolve_yaw` scans the yaw about the vertical axis through the
footprint's centre, keeps the yaws under which the reference cloud still fits the rest
surface, and takes the centre of the largest instrument support's lobe, refined so that
the visible shaft points along the kinematics' shaft (:func:`shaft_yaw_correction`).
That lobe (the
contiguous yaws with at least half its support) must be at most ``max_lobe_deg`` wide
and every yaw outside it must have at most half its support (>= 10 points and twice the
runner-up's, the rule of the box's two-candidate case), or the yaw is not resolved.
The turned pose is refined by :func:`truncated_icp`, which leaves alone the motions the
shape does not fix (plain ICP would turn the dome off that yaw again).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from core.errors import RegistrationError
from core.registration.cleaning import instrument_mask
from core.registration.rigid import apply_transform

__all__ = ["rotate_about_vertical", "surface_instrument_support", "shaft_yaw_correction", "resolve_yaw",
           "truncated_icp"]


def rotate_about_vertical(T: np.ndarray, yaw: float, pivot_xy: np.ndarray) -> np.ndarray:
    """``T_phantom_camera`` turned by ``yaw`` (rad) about the phantom frame's vertical axis
    through ``pivot_xy`` (2,) m: ``A(yaw) @ T``."""
    c, s = np.cos(yaw), np.sin(yaw)
    A = np.eye(4)
    A[:2, :2] = [[c, -s], [s, c]]
    p = np.array([pivot_xy[0], pivot_xy[1], 0.0])
    A[:3, 3] = p - A[:3, :3] @ p
    return A @ np.asarray(T, dtype=np.float64)


def surface_instrument_support(T: np.ndarray, hints: Sequence, surface_points: np.ndarray, surface_normals: np.ndarray,
                               tree, *, probe_radius: float, shaft_radius: float, tolerance: float = 0.003) -> int:
    """How many raw hint points ``T`` (4, 4) ``T_phantom_camera`` puts on the instrument
    and not on (or in) the rest phantom: the STL counterpart of
    :func:`core.registration.instrument.instrument_support`.

    Args:
        hints: ``(points_camera (N, 3), probe_centre_phantom (3,), shaft_axis_phantom (3,))``.
        surface_points, surface_normals: (S, 3) samples of the rest surface and their
            outward normals, phantom frame; ``tree`` a KD-tree over ``surface_points``.
        tolerance: margin of the instrument and of the surface, m.
    """
    total = 0
    for points_camera, centre, axis in hints:
        pts = np.asarray(points_camera, dtype=np.float64)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        q = apply_transform(T, pts)
        near = np.linalg.norm(q - centre, axis=1) < 0.08  # the tool's end; the rest cannot matter
        q = q[near & (q[:, 2] > 0.005)]
        if q.shape[0] == 0:
            continue
        dist, j = tree.query(q)
        outside = np.einsum("ij,ij->i", q - surface_points[j], surface_normals[j]) > 0
        free = (dist > tolerance) & outside
        on_tool = instrument_mask(q[free], centre, axis, probe_radius=probe_radius, shaft_radius=shaft_radius,
                                  margin=tolerance)
        total += int(np.count_nonzero(on_tool))
    return total


def resolve_yaw(T: np.ndarray, hints: Sequence, surface_points: np.ndarray, surface_normals: np.ndarray, tree,
                fitness: Callable[[np.ndarray], float], *, probe_radius: float, shaft_radius: float,
                step_deg: float = 2.0, fitness_drop: float = 0.05, separation_deg: float = 20.0,
                max_lobe_deg: float = 90.0) -> np.ndarray:
    """The yaw of ``T`` (an ICP fit of the reference cloud) that puts the hint frames'
    instrument points on the instrument (module docstring).

    Args:
        T: (4, 4) ``T_phantom_camera`` from ICP.
        hints, surface_points, surface_normals, tree: see :func:`surface_instrument_support`.
        fitness: ``fitness(T)`` of the reference cloud on the rest surface (0-1).
        step_deg: yaw step of the scan, degrees.
        fitness_drop: yaws whose fitness is more than this below the best are not the
            phantom's symmetry and are skipped.
        separation_deg: yaws this far from ``T`` that fit as well mean the shape leaves
            the yaw open.
        max_lobe_deg: the widest accepted lobe of the winner (yaws with at least half
            its support): a wider one does not fix the yaw.

    Returns:
        (4, 4) the turned ``T_phantom_camera`` (refine it by ICP).

    When no yaw ``separation_deg`` or more from ``T``'s fits the reference cloud as well
    (a phantom whose shape fixes the yaw), ``T`` is returned as it is.

    Raises:
        RegistrationError: the shape leaves the yaw open and there are no hints, or
            their support does not single out one yaw.
    """
    pivot = 0.5 * (surface_points[:, :2].min(axis=0) + surface_points[:, :2].max(axis=0))
    yaws = np.deg2rad(np.arange(0.0, 360.0, step_deg))
    candidates = [rotate_about_vertical(T, y, pivot) for y in yaws]
    fits = np.array([fitness(c) for c in candidates])
    keep = fits >= fits.max() - fitness_drop
    away = np.degrees(np.abs(np.angle(np.exp(1j * yaws)))) >= separation_deg
    if not np.any(keep & away):
        return np.asarray(T, dtype=np.float64)
    if not hints:
        raise RegistrationError("the phantom's shape does not fix the camera's yaw (it fits the reference cloud "
                                "turned too); give hints (raw frames with the instrument in view) or picked points")
    support = np.array([surface_instrument_support(c, hints, surface_points, surface_normals, tree,
                                                   probe_radius=probe_radius, shaft_radius=shaft_radius)
                        if k else -1 for c, k in zip(candidates, keep)])
    best = int(np.argmax(support))
    s1 = int(support[best])
    # the winner's lobe: the yaws around it, contiguous, with at least half its support;
    # the runner-up is the best yaw outside it (another peak, or the flat support of a
    # tool too close to the axis to tell yaws apart)
    lobe = np.zeros(yaws.size, dtype=bool)
    lobe[best] = True
    for direction in (1, -1):
        k = (best + direction) % yaws.size
        while support[k] * 2 >= s1 and not lobe[k]:
            lobe[k] = True
            k = (k + direction) % yaws.size
    width = float(np.count_nonzero(lobe) * step_deg)
    rival = int(support[~lobe].max()) if np.any(~lobe) else s1
    if s1 < 10 or s1 < 2 * max(rival, 0) or width > max_lobe_deg:
        raise RegistrationError(
            f"cannot resolve the camera's yaw about the phantom: instrument support {s1} points at the best yaw "
            f"(within half of it over {width:.0f} degrees, at most {max_lobe_deg:.0f} allowed), {rival} at the best "
            "other yaw (need >= 10 and 2x); use frames with the instrument clearly in view and away from the "
            "phantom's axis, or picked points")
    # the support is flat-topped (the instrument's margin): take the lobe's centre, the
    # circular mean of its yaws weighted by their support above half the winner's
    w = np.where(lobe, support - 0.5 * s1, 0.0)
    yaw = float(np.angle(np.sum(w * np.exp(1j * yaws))))
    # then refine it on the shaft's direction: the visible shaft is a line some 10 cm
    # long whose azimuth the kinematics give, a better lever than the tip's position
    for _ in range(3):
        turn = shaft_yaw_correction(rotate_about_vertical(T, yaw, pivot), hints, surface_points, surface_normals, tree,
                                    shaft_radius=shaft_radius)
        if turn is None:
            break
        yaw += turn
        if abs(turn) < np.deg2rad(0.05):
            break
    return rotate_about_vertical(T, yaw, pivot)


def shaft_yaw_correction(T: np.ndarray, hints: Sequence, surface_points: np.ndarray, surface_normals: np.ndarray,
                         tree, *, shaft_radius: float, reach: float = 0.01, tolerance: float = 0.003,
                         min_points: int = 30) -> float | None:
    """The turn (rad) about the vertical that aligns the shafts seen in the hint frames
    with the shafts the kinematics give, under ``T_phantom_camera`` (4, 4).

    In each hint frame, the raw points clear of the rest phantom, within ``reach`` of the
    expected shaft and at least 2 cm up it from the sphere centre, are fitted by a line
    (principal axis); the turn is the circular mean, weighted by the shafts' horizontal
    length, of the azimuth differences between the expected and the fitted directions.
    None when no frame has ``min_points`` such points or the shafts are near vertical."""
    num = 0.0 + 0.0j
    for points_camera, centre, axis in hints:
        pts = np.asarray(points_camera, dtype=np.float64)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        q = apply_transform(T, pts)
        a = -np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)  # up the shaft
        rel = q - centre
        along = rel @ a
        radial = np.linalg.norm(rel - along[:, None] * a, axis=1)
        keep = (along > 0.02) & (radial < shaft_radius + reach) & (q[:, 2] > 0.005)
        q = q[keep]
        if q.shape[0] < min_points:
            continue
        dist, j = tree.query(q)
        q = q[(dist > tolerance) & (np.einsum("ij,ij->i", q - surface_points[j], surface_normals[j]) > 0)]
        if q.shape[0] < min_points:
            continue
        d = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)[2][0]
        d = d if d @ a > 0 else -d
        h_seen, h_known = np.hypot(d[0], d[1]), np.hypot(a[0], a[1])
        if h_seen < 0.1 or h_known < 0.1:
            continue
        diff = np.arctan2(a[1], a[0]) - np.arctan2(d[1], d[0])
        num += h_known * np.exp(1j * diff)
    if abs(num) == 0:
        return None
    return float(np.angle(num))


def truncated_icp(T: np.ndarray, source_camera: np.ndarray, surface_points: np.ndarray,
                  surface_normals: np.ndarray, tree, *, stages: Sequence[float] = (0.010, 0.005, 0.003),
                  iterations: int = 30, rcond: float = 0.05) -> np.ndarray:
    """Point-to-plane ICP (Chen & Medioni 1992) of ``T`` that moves only along the rigid
    motions the surface determines.

    Plain ICP of a curved top lets it slide along itself: a spherical cap turns about its
    sphere's centre and any surface of revolution about its axis, so ICP from the yaw
    :func:`resolve_yaw` took from the instrument drifts off it by an amount that depends
    on floating-point summation order (2-7 degrees on a lab dome under gravity, a
    different one each run with open3d's threads). Here each Gauss-Newton step is the
    least-squares solution of the linearised point-to-plane residuals (six columns: the
    translation and the rotation about the footprint's centre on the table, the latter
    scaled by the footprint's half-width so all share units) truncated at ``rcond`` of the
    largest singular value: a motion the shape leaves open is not taken, one it fixes is
    refined (a dome keeps its yaw, a kidney-like ellipsoid refines it). Deterministic.

    Args:
        T: (4, 4) float ``T_phantom_camera`` (camera -> phantom).
        source_camera: (N, 3) float reference cloud of the phantom, camera frame, m.
        surface_points, surface_normals: (S, 3) rest-surface samples and their outward
            unit normals, phantom frame, m; ``tree`` a KD-tree over ``surface_points``.
        stages: correspondence distances, coarse to fine, m.
        iterations: most Gauss-Newton steps per stage.
        rcond: relative singular-value cutoff of each step's least squares.

    Returns:
        (4, 4) float64 refined ``T_phantom_camera``.
    """
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64).copy()
    src = np.asarray(source_camera, dtype=np.float64)
    lo, hi = surface_points.min(axis=0), surface_points.max(axis=0)
    centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    scale = 0.5 * float(np.max(hi[:2] - lo[:2]))
    for dist in stages:
        for _ in range(iterations):
            q = apply_transform(T, src)
            d, j = tree.query(q)
            near = d < dist
            if np.count_nonzero(near) < 10:
                break
            q, s, n = q[near], surface_points[j[near]], surface_normals[j[near]]
            r = np.einsum("ij,ij->i", q - s, n)
            J = np.column_stack([n, np.cross(q - centre, n) / scale])
            step = np.linalg.lstsq(J, -r, rcond=rcond)[0]
            t, w = step[:3], step[3:] / scale
            A = np.eye(4)
            A[:3, :3] = Rotation.from_rotvec(w).as_matrix()
            A[:3, 3] = centre - A[:3, :3] @ centre + t
            T = A @ T
            if np.linalg.norm(t) < 1e-7 and np.linalg.norm(w) < 1e-6:
                break
    return T
