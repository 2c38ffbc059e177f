"""Camera calibration: ``T_phantom_camera`` by ICP of the reference cloud onto the phantom.

Wu et al. 2020, Sec. 3.3: "we extract the point cloud of the phantom without any robot
interaction [and] find the transformation between the phantom and that point cloud using
iterative closest point (ICP) [Besl & McKay 1992] ... Since the top of the block is flat
and featureless, we manually initialize the registration". Here (:func:`calibrate_camera`):

* ICP is point-to-plane (Chen & Medioni 1992) from ``open3d.pipelines.registration``,
  coarse to fine (10, 5, 3 mm correspondence distance), source = the cleaned reference
  cloud (camera frame), target = dense samples of the phantom's rest surface with their
  normals (:func:`phantom_rest_surface`, phantom frame).
* Manual initialisation (``picked``): a few camera points and the phantom points they
  show, aligned by :func:`core.registration.rigid.kabsch`.
* Automatic initialisation (:mod:`core.registration.initial_pose`): the table by RANSAC,
  the phantom as the largest DBSCAN cluster standing on it, and four candidate poses
  (yaw 0, 90, 180, 270 deg about the vertical axis) from the minimum-area rectangle
  around its footprint (rotating calipers). Each candidate is refined by ICP; for a box,
  two of them (180 deg apart) fit the geometry equally well -- a box is symmetric under
  that rotation, so no cloud of the box alone can tell them apart. They are
  disambiguated with ``hints`` (:mod:`core.registration.instrument`): raw camera frames
  with the instrument in view, whose phantom-frame pose is known from the robot's
  kinematics and ``T_phantom_robot``. Under the right candidate the raw points that lie
  outside the phantom fall on the instrument's sphere and shaft; under the wrong one
  they do not (:func:`instrument_support`; the winner needs >= 10 points and twice the
  runner-up's). If the hints do not decide, a :class:`RegistrationError` asks for picked
  points. With a ``phantom.stl`` of any shape, the yaw the shape leaves open is scanned
  instead (:func:`core.registration.symmetry.resolve_yaw`), and the turned pose refined
  only along the motions the shape fixes (:func:`core.registration.symmetry.truncated_icp`:
  plain ICP would slide a dome's top along itself, off the instrument's yaw).
* After ICP, z = 0 and the tilt are taken from the table plane (``anchor_table``,
  :func:`core.registration.initial_pose.anchor_to_table`): the top may sag.

:func:`probe_pose_phantom`, :func:`instrument_hints` and :func:`instrument_support`
live in :mod:`core.registration.instrument` and are re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.errors import CleaningError, RegistrationError
from core.registration.cleaning import as_points, as_size, o3d_cloud
from core.registration.initial_pose import anchor_to_table, auto_inits, check_footprint, phantom_cluster
from core.registration.instrument import Hint, instrument_hints, instrument_support, probe_pose_phantom
from core.registration.rigid import apply_transform, kabsch
from core.registration.symmetry import resolve_yaw, truncated_icp

__all__ = [
    "CameraFit",
    "calibrate_camera",
    "phantom_rest_surface",
    "probe_pose_phantom",
    "instrument_hints",
    "instrument_support",
]

#: Correspondence distances of the coarse-to-fine ICP stages, m; the last one also
#: defines ``fitness`` (about 3 sigma of the SR300's depth noise).
_ICP_STAGES = (0.010, 0.005, 0.003)


@dataclass(frozen=True)
class CameraFit:
    """Result of :func:`calibrate_camera`.

    Attributes:
        T: (4, 4) float64 ``T_phantom_camera`` (camera-frame points -> phantom frame).
        fitness: fraction of the cleaned reference points within the final ICP
            correspondence distance (3 mm) of the phantom's rest surface, in [0, 1].
        rms: point-to-plane rms residual of those inlier points, m.
        T_init: (4, 4) float64 the initial ``T_phantom_camera`` ICP started from.
        residuals: (N,) float64 point-to-plane distance of every cleaned reference point
            used (inliers and not) to its nearest rest-surface sample, m.
        method: ``"auto"`` or ``"picked"``.
        table_anchored: z = 0 and the tilt were taken from the table plane after ICP.
        coverage: fraction of the rest surface's upward-facing samples (the top face)
            with a reference point within 3 mm -- the other direction of fitness: a
            model larger than the phantom fits the points well but is not covered.
    """

    T: np.ndarray
    fitness: float
    rms: float
    T_init: np.ndarray
    residuals: np.ndarray
    method: str
    coverage: float = 1.0
    table_anchored: bool = False


# --------------------------------------------------------------------------- surface


def phantom_rest_surface(
    phantom_size, stl_path: str | Path | None = None, *, spacing: float = 0.001
) -> tuple[np.ndarray, np.ndarray]:
    """Dense samples of the phantom's rest surface, phantom frame.

    The bottom face (z = 0) is excluded: it stands on the table and is never visible.

    Args:
        phantom_size: (3,) box size (sx, sy, sz), m; the box spans [0, sx] x [0, sy] x [0, sz].
        stl_path: optional ``phantom.stl`` (rest surface, phantom frame, m); when given it
            replaces the box and is sampled uniformly at random (seeded) with about one
            point per ``spacing**2`` of area; faces facing down at z ~ 0 are skipped.
        spacing: sample spacing, m.

    Returns:
        points (P, 3) float64 m and unit outward normals (P, 3) float64, phantom frame.

    Raises:
        ValueError: bad size or spacing; an STL that cannot be read or has no faces.
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0 m, got {spacing}")
    if stl_path is not None:
        return _stl_surface(Path(stl_path), spacing)
    sx, sy, sz = as_size(phantom_size)

    def grid(a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
        u = np.linspace(0.0, a, max(2, int(np.ceil(a / spacing)) + 1))
        v = np.linspace(0.0, b, max(2, int(np.ceil(b / spacing)) + 1))
        uu, vv = np.meshgrid(u, v, indexing="ij")
        return uu.ravel(), vv.ravel()

    pts, nrm = [], []
    x, y = grid(sx, sy)  # top
    pts.append(np.c_[x, y, np.full_like(x, sz)])
    nrm.append(np.tile([0.0, 0.0, 1.0], (x.size, 1)))
    y, z = grid(sy, sz)  # x = 0 and x = sx
    for xv, nx in ((0.0, -1.0), (sx, 1.0)):
        pts.append(np.c_[np.full_like(y, xv), y, z])
        nrm.append(np.tile([nx, 0.0, 0.0], (y.size, 1)))
    x, z = grid(sx, sz)  # y = 0 and y = sy
    for yv, ny in ((0.0, -1.0), (sy, 1.0)):
        pts.append(np.c_[x, np.full_like(x, yv), z])
        nrm.append(np.tile([0.0, ny, 0.0], (x.size, 1)))
    return np.concatenate(pts), np.concatenate(nrm)


def _stl_surface(path: Path, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types
        raise ValueError(f"{path}: cannot read the phantom STL: {exc}") from exc
    if len(mesh.faces) == 0:
        raise ValueError(f"{path}: the phantom STL has no faces")
    zmin = float(mesh.bounds[0, 2])
    centroid_z = mesh.triangles_center[:, 2]
    bottom = (mesh.face_normals[:, 2] < -0.99) & (centroid_z < zmin + 1e-4)
    keep = ~bottom
    sub = mesh.submesh([np.flatnonzero(keep)], append=True)
    count = max(1000, int(np.ceil(sub.area / spacing**2)))
    pts, face = trimesh.sample.sample_surface(sub, count, seed=0)
    return np.asarray(pts, dtype=np.float64), np.asarray(sub.face_normals[face], dtype=np.float64)


# --------------------------------------------------------------------------- ICP helpers


class _Target:
    """The rest surface as an open3d cloud with normals plus a KD-tree for evaluation."""

    def __init__(self, points: np.ndarray, normals: np.ndarray):
        import open3d as o3d
        from scipy.spatial import cKDTree

        self.points, self.normals = points, normals
        self.pcd = o3d_cloud(points)
        self.pcd.normals = o3d.utility.Vector3dVector(normals)
        self.tree = cKDTree(points)
        self.top = points[normals[:, 2] > 0.9]

    def coverage(self, T: np.ndarray, source: np.ndarray, threshold: float) -> float:
        """Fraction of upward-facing model samples with a transformed source point within ``threshold``."""
        from scipy.spatial import cKDTree

        if self.top.shape[0] == 0:
            return 1.0
        dist, _ = cKDTree(apply_transform(T, source)).query(self.top, distance_upper_bound=threshold)
        return float(np.mean(np.isfinite(dist)))

    def evaluate(self, T: np.ndarray, source: np.ndarray, threshold: float) -> tuple[float, float, np.ndarray]:
        """fitness, point-to-plane inlier rms (m), point-to-plane residual of every point (m)."""
        q = apply_transform(T, source)
        dist, j = self.tree.query(q)
        res = np.abs(np.einsum("ij,ij->i", q - self.points[j], self.normals[j]))
        inl = dist < threshold
        fitness = float(np.mean(inl)) if q.shape[0] else 0.0
        rms = float(np.sqrt(np.mean(res[inl] ** 2))) if np.any(inl) else float("inf")
        return fitness, rms, res


def _icp(source_pcd, target: _Target, T_init: np.ndarray) -> np.ndarray:
    import open3d as o3d

    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationPointToPlane()
    T = np.asarray(T_init, dtype=np.float64)
    for dist in _ICP_STAGES:
        res = reg.registration_icp(source_pcd, target.pcd, dist, T, est,
                                   reg.ICPConvergenceCriteria(max_iteration=40))
        T = np.asarray(res.transformation, dtype=np.float64)
    return T


def _same_pose(A: np.ndarray, B: np.ndarray, deg: float = 5.0, metres: float = 0.005) -> bool:
    dR = A[:3, :3] @ B[:3, :3].T
    angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0)))
    return angle < deg and np.linalg.norm(A[:3, 3] - B[:3, 3]) < metres


# --------------------------------------------------------------------------- public


def calibrate_camera(
    reference_camera: np.ndarray,
    phantom_size,
    *,
    probe_radius: float | None = None,
    picked: tuple[np.ndarray, np.ndarray] | None = None,
    hints: Sequence[Hint] | None = None,
    stl_path: str | Path | None = None,
    min_fitness: float = 0.6,
    anchor_table: bool = True,
    max_rms: float = 0.002,
    min_coverage: float = 0.7,
    shaft_radius: float = 0.0045,
    seed: int = 0,
    callback: Callable[[str, dict], None] | None = None,
) -> CameraFit:
    """Estimate ``T_phantom_camera`` by point-to-plane ICP of the reference cloud.

    See the module docstring for the method (Wu et al. 2020, Sec. 3.3; Besl & McKay 1992;
    Chen & Medioni 1992).

    Args:
        reference_camera: (N, 3) float camera-frame cloud of the phantom at rest, without
            the instrument (``calibration/reference.ply``), m; raw (table, outliers).
        phantom_size: (3,) box size, m.
        probe_radius: probe sphere radius for scoring ``hints``, m (default 5 mm).
        picked: optional ``(points_camera (K, 3), points_phantom (K, 3))``, K >= 3, pairs
            picked by a user; the initial transform is their Kabsch fit and the
            symmetry is not resolved further (the user did).
        hints: for automatic initialisation, a list of ``(points_camera (N, 3) of a raw
            sequence frame, probe_centre_phantom (3,), shaft_axis_phantom (3,))`` -- see
            :func:`instrument_hints`. Needed whenever the phantom's shape is symmetric
            (a box always is).
        stl_path: optional ``phantom.stl`` rest surface replacing the box.
        min_fitness: least accepted fitness (fraction of reference points within 3 mm).
        anchor_table: after ICP, take z = 0 and the tilt from the table plane (RANSAC)
            instead of the phantom's top, which sags under gravity (default True).
        max_rms: largest accepted point-to-plane inlier rms, m.
        min_coverage: least accepted :attr:`CameraFit.coverage` (the top face must be
            seen; catches a phantom smaller than ``phantom_size``).
        shaft_radius: instrument shaft radius for scoring ``hints``, m.
        seed: RANSAC seed.
        callback: optional ``callback(stage, info)`` for progress (stages ``"segmented"``,
            ``"candidate"``, ``"done"``).

    Returns:
        :class:`CameraFit`.

    Raises:
        ValueError: malformed arguments.
        RegistrationError: no table / phantom found in the reference cloud; picked points
            inconsistent; the fit has fitness < ``min_fitness``, rms > ``max_rms`` or
            coverage < ``min_coverage``; the footprint of the phantom in the reference
            cloud differs from ``phantom_size`` by more than 20 % (auto); or
            the automatic initialisation cannot resolve the phantom's symmetry (give
            ``hints`` with the instrument in view, or ``picked`` points).
    """
    ref = as_points("reference_camera", reference_camera)
    size = as_size(phantom_size)
    r_probe = 0.005 if probe_radius is None else float(probe_radius)
    notify = callback or (lambda stage, info: None)
    target = _Target(*phantom_rest_surface(size, stl_path))
    final = _ICP_STAGES[-1]
    shift = np.eye(4)
    if stl_path is not None:  # the STL replaces the box: initialise and check with its bounds
        lo, hi = target.points.min(axis=0), target.points.max(axis=0)
        size, shift[:3, 3] = hi - lo, lo

    if picked is not None:
        pc, pp = picked
        pc, pp = as_points("picked points_camera", pc), as_points("picked points_phantom", pp)
        if pc.shape != pp.shape or pc.shape[0] < 3:
            raise ValueError(f"picked needs K >= 3 pairs of (K, 3) points, got {pc.shape} and {pp.shape}")
        try:
            init = kabsch(pc, pp)
        except ValueError as exc:
            raise RegistrationError(f"picked points are degenerate: {exc}") from exc
        if init.rms > 0.01:
            raise RegistrationError(
                f"picked points do not match rigidly: rms {init.rms * 1e3:.1f} mm (> 10 mm); "
                f"worst pair {int(np.argmax(init.residuals))}", rms=init.rms)
        T_init = init.T
        plane = None
        try:
            source, plane = phantom_cluster(ref, size, seed)
            check_footprint(auto_inits(source, plane, size)[1], size)
        except CleaningError:  # no table in view: crop around the picked pose instead
            q = apply_transform(T_init, ref[np.all(np.isfinite(ref), axis=1)])
            g = 0.01
            keep = ((q[:, 0] > -g) & (q[:, 0] < size[0] + g) & (q[:, 1] > -g) & (q[:, 1] < size[1] + g)
                    & (q[:, 2] > 0.003) & (q[:, 2] < size[2] + g))
            source = ref[np.all(np.isfinite(ref), axis=1)][keep]
        if source.shape[0] < 20:
            raise RegistrationError(f"only {source.shape[0]} reference points near the picked pose")
        notify("segmented", {"points": int(source.shape[0])})
        T = _icp(o3d_cloud(source), target, T_init)
        fitness, rms, res = target.evaluate(T, source, final)
        coverage = target.coverage(T, source, final)
        method = "picked"
    else:
        try:
            source, plane = phantom_cluster(ref, size, seed)
        except CleaningError as exc:
            raise RegistrationError(f"automatic initialisation failed: {exc}; pick points instead") from exc
        notify("segmented", {"points": int(source.shape[0])})
        inits, extents = auto_inits(source, plane, size)
        check_footprint(extents, size, smaller_tolerance=None if stl_path is None else 0.4)
        inits = [shift @ T0 for T0 in inits]
        src_pcd = o3d_cloud(source)
        results = []  # (T_init, T, fitness, rms, residuals, coverage)
        for T0 in inits:
            T = _icp(src_pcd, target, T0)
            fitness, rms, res = target.evaluate(T, source, final)
            coverage = target.coverage(T, source, final)
            notify("candidate", {"fitness": fitness, "rms": rms, "coverage": coverage})
            results.append((T0, T, fitness, rms, res, coverage))
        results.sort(key=lambda r: (-min(r[2], r[5]), r[3]))
        best = results[0]
        if best[2] < min_fitness or best[3] > max_rms or best[5] < min_coverage:
            raise RegistrationError(
                f"camera calibration failed: best ICP fitness {best[2]:.2f} (need >= {min_fitness:.2f}), "
                f"rms {best[3] * 1e3:.2f} mm (need <= {max_rms * 1e3:.2f} mm), top coverage {best[5]:.2f} "
                f"(need >= {min_coverage:.2f}); is phantom_size right?",
                fitness=best[2], rms=best[3])
        if stl_path is not None:  # any shape: scan the yaw its symmetry may leave open
            # a curved top can slide along itself under ICP: level the pose on the table
            # first, so that the scan turns about the true vertical
            T_level = anchor_to_table(best[1], plane, size) if anchor_table else best[1]
            T_turned = resolve_yaw(T_level, hints or [], target.points, target.normals, target.tree,
                                   lambda T: target.evaluate(T, source, final)[0], probe_radius=r_probe,
                                   shaft_radius=shaft_radius)
            if not np.array_equal(T_turned, T_level):
                # refined only along the motions the shape fixes: plain ICP would slide a
                # curved top along itself again (a dome turns freely about its axis)
                T = truncated_icp(T_turned, source, target.points, target.normals, target.tree,
                                  stages=_ICP_STAGES)
                fitness, rms, res = target.evaluate(T, source, final)
                best = (best[0], T, fitness, rms, res, target.coverage(T, source, final))
        else:
            plausible = []
            for r in results:
                if r[2] >= best[2] - 0.05 and r[5] >= best[5] - 0.05 and r[3] <= 1.5 * best[3] + 2e-4:
                    if not any(_same_pose(r[1], p[1]) for p in plausible):
                        plausible.append(r)
            if len(plausible) > 1:
                if not hints:
                    raise RegistrationError(
                        f"{len(plausible)} poses fit the reference cloud equally well (the phantom is symmetric); "
                        "give hints (raw frames with the instrument in view) or picked points",
                        fitness=best[2], rms=best[3])
                scores = [instrument_support(r[1], hints, size, probe_radius=r_probe, shaft_radius=shaft_radius)
                          for r in plausible]
                order = np.argsort(scores)[::-1]
                s1, s2 = scores[order[0]], scores[order[1]]
                notify("candidate", {"instrument_support": scores})
                if s1 < 10 or s1 < 2 * s2 or s1 - s2 < 10:
                    raise RegistrationError(
                        f"cannot resolve the phantom's symmetry: instrument support of the candidate poses is "
                        f"{sorted(scores, reverse=True)} points (need >= 10 and 2x the runner-up); "
                        "use frames with the instrument clearly in view, or picked points",
                        fitness=best[2], rms=best[3])
                best = plausible[int(order[0])]
        T_init, T, fitness, rms, res, coverage = best
        method = "auto"

    anchored = False
    if anchor_table and plane is not None:
        # The bottom is fixed on the table, so the table defines z = 0 and the tilt; the
        # top may sag (gravity) or bulge, and ICP onto the nominal box would absorb that.
        T = anchor_to_table(T, plane, size)
        fitness, rms, res = target.evaluate(T, source, final)
        coverage = target.coverage(T, source, final)
        anchored = True

    if fitness < min_fitness or rms > max_rms or coverage < min_coverage:
        raise RegistrationError(
            f"camera calibration ({method}) does not fit: fitness {fitness:.2f} (need >= {min_fitness:.2f}), "
            f"rms {rms * 1e3:.2f} mm (need <= {max_rms * 1e3:.2f} mm), top coverage {coverage:.2f} "
            f"(need >= {min_coverage:.2f})", fitness=fitness, rms=rms)
    notify("done", {"fitness": fitness, "rms": rms, "coverage": coverage})
    return CameraFit(T=T, fitness=fitness, rms=rms, T_init=np.asarray(T_init, dtype=np.float64),
                     residuals=res, method=method, coverage=coverage, table_anchored=anchored)
