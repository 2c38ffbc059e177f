"""The phantom's pose from the table and its footprint in a camera-frame cloud.

The automatic initial pose of camera calibration (:func:`core.registration.icp.calibrate_camera`;
Wu et al. 2020, Sec. 3.3, initialise by hand, which ``picked`` points still allow), and
the table anchoring applied after its ICP:

* :func:`phantom_cluster` -- the table is found by RANSAC
  (:func:`core.registration.cleaning.find_table_plane`; Fischler & Bolles 1981), the
  phantom is the largest DBSCAN cluster (Ester et al. 1996) of the points standing on it.
* :func:`auto_inits` -- the phantom's z-axis is the table normal (facing the camera), its
  x/y axes and centre come from the minimum-area rectangle around the cluster's footprint
  on the table (rotating calipers over the convex hull's edges, Toussaint 1983), and its
  origin from the box size. Four candidates, yaw 0, 90, 180 and 270 deg about the
  vertical axis: the rectangle fixes the footprint's axes but not which of them is the
  phantom's x nor which way it points, so ICP refines each candidate; for a box two of
  them (180 deg apart) fit equally well, and ``hints``
  (:func:`core.registration.instrument.instrument_support`) decide.
* :func:`check_footprint` -- the footprint's extents against ``phantom_size``.
* :func:`anchor_to_table` -- after ICP, z = 0 and the tilt taken from the table plane
  instead of the phantom's top, which sags under gravity.

Frames: points and planes in the camera frame, poses as ``T_phantom_camera`` (camera ->
phantom); lengths in m.
"""

from __future__ import annotations

import numpy as np

from core.errors import CleaningError, RegistrationError
from core.registration.cleaning import find_table_plane, o3d_cloud

__all__ = ["phantom_cluster", "auto_inits", "check_footprint", "anchor_to_table"]


def phantom_cluster(points_camera: np.ndarray, size: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The phantom's points in a camera-frame reference cloud, and the table plane.

    The table is found by RANSAC (:func:`core.registration.cleaning.find_table_plane`, with
    the phantom's height ``size[2]``); the points 3 mm .. ``size[2]`` + 10 mm above it are
    clustered by DBSCAN (open3d ``cluster_dbscan``, ``eps`` three times the median
    nearest-neighbour distance clipped to 3-10 mm, at least 5 points), and the largest
    cluster is the phantom. Non-finite points are dropped; above 30 000 points the cloud
    is voxel-downsampled to 1 mm first.

    Args:
        points_camera: (N, 3) float64 raw reference cloud, camera frame, m.
        size: (3,) float64 phantom box size (sx, sy, sz), m.
        seed: RANSAC seed.

    Returns:
        cluster (M, 3) float64 camera-frame points of the phantom, m, and the table plane
        (4,) float64 ``(a, b, c, d)``, camera frame, unit normal toward the camera
        (``points @ plane[:3] + plane[3]`` is the height above the table, m).

    Raises:
        CleaningError: no table plane found, fewer than 20 points stand on the table, or
            DBSCAN finds no cluster among them.
    """
    from scipy.spatial import cKDTree

    pts = points_camera[np.all(np.isfinite(points_camera), axis=1)]
    if pts.shape[0] > 30000:
        pts = np.asarray(o3d_cloud(pts).voxel_down_sample(0.001).points)
    table = find_table_plane(pts, phantom_height=float(size[2]), seed=seed)
    n, d = table.plane[:3], table.plane[3]
    h = pts @ n + d
    cand = pts[(h > 0.003) & (h < size[2] + 0.01)]
    if cand.shape[0] < 20:
        raise CleaningError(f"only {cand.shape[0]} points stand on the table; expected the phantom")
    nn = cKDTree(cand).query(cand, k=2)[0][:, 1]
    eps = float(np.clip(3.0 * np.median(nn), 0.003, 0.01))
    labels = np.asarray(o3d_cloud(cand).cluster_dbscan(eps=eps, min_points=5), dtype=np.int64)
    if labels.max(initial=-1) < 0:
        raise CleaningError("no cluster of points stands on the table; expected the phantom")
    largest = np.bincount(labels[labels >= 0]).argmax()
    return cand[labels == largest], table.plane


def _min_area_rectangle(p2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum-area rectangle around 2-D points (rotating calipers, Toussaint 1983).

    The minimum-area enclosing rectangle has a side collinear with an edge of the convex
    hull, so each hull edge's direction (modulo 90 deg) is tried.

    Args:
        p2: (P, 2) float64 points, m, P >= 3 and not collinear.

    Returns:
        centre (2,) float64 m, unit long axis (2,) float64 and extents (2,) float64
        (long, short) m.

    Raises:
        scipy.spatial.QhullError: fewer than 3 points, or all collinear.
    """
    from scipy.spatial import ConvexHull

    hull = p2[ConvexHull(p2).vertices]
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    best = None
    for a in angles:
        u = np.array([np.cos(a), np.sin(a)])
        v = np.array([-u[1], u[0]])
        pu, pv = hull @ u, hull @ v
        area = np.ptp(pu) * np.ptp(pv)
        if best is None or area < best[0]:
            centre = u * (pu.max() + pu.min()) / 2 + v * (pv.max() + pv.min()) / 2
            ext = np.array([np.ptp(pu), np.ptp(pv)])
            best = (area, centre, u, v, ext)
    _, centre, u, v, ext = best
    if ext[1] > ext[0]:
        u, ext = v, ext[::-1]
    return centre, u, ext


def auto_inits(cluster: np.ndarray, plane: np.ndarray, size: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Four initial ``T_phantom_camera`` (yaw 0/90/180/270 deg) from the table and the footprint.

    The cluster is projected onto the table plane; the minimum-area rectangle around the
    projection (:func:`_min_area_rectangle`) gives the footprint's centre and long axis.
    Candidate ``k`` has the phantom's z-axis along the table normal, its x-axis the long
    axis turned by ``k * 90`` deg about z, and its origin at the footprint's centre minus
    ``(sx / 2, sy / 2, 0)`` in those axes -- on the table, so the box's bottom lies on it.
    The rectangle's extents are not matched to ``size`` here (see :func:`check_footprint`).

    Args:
        cluster: (M, 3) float64 phantom points, camera frame, m (:func:`phantom_cluster`).
        plane: (4,) float64 table plane, camera frame, normal toward the camera.
        size: (3,) float64 phantom box size, m.

    Returns:
        the four candidates, each (4, 4) float64 ``T_phantom_camera`` (camera -> phantom),
        and the footprint rectangle's extents (2,) float64 (long, short), m.

    Raises:
        scipy.spatial.QhullError: the footprint is degenerate (fewer than 3 points, or
            all on one line).
    """
    z = plane[:3] / np.linalg.norm(plane[:3])  # up, toward the camera
    e1 = np.cross(z, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(z, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z, e1)
    h = cluster @ z + plane[3]
    base = cluster - np.outer(h, z)  # projected onto the table
    p2 = np.c_[base @ e1, base @ e2]
    c2, u2, extents = _min_area_rectangle(p2)
    origin_on_table = -plane[3] * z  # the point of the plane closest to the camera origin
    centre = origin_on_table + c2[0] * e1 + c2[1] * e2 - ((origin_on_table @ e1) * e1 + (origin_on_table @ e2) * e2)
    long_axis = u2[0] * e1 + u2[1] * e2
    inits = []
    for k in range(4):
        a = k * np.pi / 2
        x = np.cos(a) * long_axis + np.sin(a) * np.cross(z, long_axis)
        y = np.cross(z, x)
        R_cam_ph = np.c_[x, y, z]
        o = centre - R_cam_ph @ np.array([size[0] / 2, size[1] / 2, 0.0])
        T_cam_ph = np.eye(4)
        T_cam_ph[:3, :3], T_cam_ph[:3, 3] = R_cam_ph, o
        inits.append(np.linalg.inv(T_cam_ph))
    return inits, extents


def check_footprint(extents: np.ndarray, size: np.ndarray, tolerance: float = 0.2,
                    smaller_tolerance: float | None = None) -> None:
    """Check the phantom's footprint on the table against ``phantom_size``.

    The extents may exceed the box's (long, short) sides by at most ``tolerance`` and
    fall short of them by at most ``smaller_tolerance`` (default ``tolerance``),
    relative. A curved phantom's lower flanks on the far side are hidden from the
    camera, so its seen footprint is smaller than its bounding box (a dome's by 7-26 %
    in our lab).

    Args:
        extents: (2,) float64 footprint (long, short), m (:func:`auto_inits`).
        size: (3,) float64 phantom box size, m; its two horizontal sides are compared.
        tolerance: largest relative excess.
        smaller_tolerance: largest relative shortfall; None: ``tolerance``.

    Raises:
        RegistrationError: a side out of bounds (wrong ``phantom_size``, or the phantom
            not fully in view).
    """
    expected = np.sort(size[:2])[::-1]
    lower = tolerance if smaller_tolerance is None else smaller_tolerance
    if np.any(extents > (1 + tolerance) * expected) or np.any(extents < (1 - lower) * expected):
        raise RegistrationError(
            f"the phantom in the reference cloud measures {extents[0] * 1e3:.1f} x {extents[1] * 1e3:.1f} mm "
            f"on the table, expected {expected[0] * 1e3:.1f} x {expected[1] * 1e3:.1f} mm (phantom_size); "
            "wrong phantom_size, or the phantom is not fully in view")


def anchor_to_table(T: np.ndarray, plane_camera: np.ndarray, size: np.ndarray) -> np.ndarray:
    """``T_phantom_camera`` corrected so the table is the phantom frame's z = 0 plane.

    The phantom's bottom is fixed on the table, so the table defines z = 0 and the tilt;
    the top may sag (gravity) or bulge, and ICP onto the nominal surface would absorb
    that. The correction is the smallest rotation (Rodrigues' formula) taking the table's
    normal to +z, about the footprint's centre ``(sx / 2, sy / 2, 0)``, followed by a
    shift along z putting the table at z = 0; x, y and yaw keep the ICP estimate.

    Args:
        T: (4, 4) float64 ``T_phantom_camera`` (camera -> phantom), e.g. from ICP.
        plane_camera: (4,) float64 table plane, camera frame, unit normal toward the
            phantom (:func:`phantom_cluster`).
        size: (3,) float64 phantom box size (or the STL's bounds), m.

    Returns:
        (4, 4) float64 corrected ``T_phantom_camera``.
    """
    n_cam, d_cam = plane_camera[:3], plane_camera[3]
    R, t = T[:3, :3], T[:3, 3]
    n = R @ n_cam
    p0 = R @ (-d_cam * n_cam) + t  # a table point in the phantom frame
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(n, z)
    s_, c_ = np.linalg.norm(axis), float(n @ z)
    C = np.eye(3)
    if s_ > 1e-12:
        k = axis / s_
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        C = np.eye(3) + s_ * K + (1 - c_) * (K @ K)
    pivot = np.array([size[0] / 2, size[1] / 2, 0.0])
    A = np.eye(4)
    A[:3, :3] = C
    A[:3, 3] = pivot - C @ pivot
    T_new = A @ T
    p0_new = A[:3, :3] @ p0 + A[:3, 3]
    T_new[2, 3] -= p0_new[2]
    return T_new
