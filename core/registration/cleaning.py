"""Cleaning of raw depth-camera clouds down to the phantom's surface points.

Wu et al. 2020, Sec. 3.1: "We use the Point Cloud Library (PCL) to remove points from the
instrument and the table, as well as outliers so that the only points that remain are
the ones from the phantom. Then we subsample the points". Here with Open3D:

1. **Table** -- a RANSAC plane (Fischler & Bolles 1981; ``open3d`` ``segment_plane``).
   Where the camera calibration is not known yet (the reference cloud), the table is
   found among up to three sequential RANSAC planes as the one with the phantom on its
   camera side (:func:`find_table_plane`; the phantom's top face is a plane too, but it
   has nothing above it). Once ``T_phantom_camera`` is known, per-frame cleaning runs
   RANSAC only on the few points near z = 0 *outside* the phantom's footprint, where the
   table is the only plane, so it cannot be confused with the top face and costs well
   under a millisecond; if too few such points are in view (or the plane found is not
   near z = 0), the calibrated plane z = 0 of the phantom frame is used instead.
   Points less than ``table_margin`` above the plane (or below it) are removed.
2. **Instrument** -- points inside the probe sphere (radius + margin) and inside the
   shaft cylinder (radius + margin), which runs from the sphere centre away from the
   tip, i.e. along ``-shaft_axis_phantom``, without end (it leaves the field of view),
   and points more than 3 mm above the rest top face near the probe (a probe bigger
   than its nominal radius; see :func:`instrument_mask`).
3. **Outliers** -- crop to the phantom box grown by ``crop_margin`` (deformation can
   bulge sideways), then statistical outlier removal (Rusu et al. 2008;
   ``open3d`` ``remove_statistical_outlier``).
4. **Downsampling** -- ``voxel_down_sample`` when ``voxel_size > 0``, then a seeded
   random subsample to ``max_points``.

Also the checks and conversions the registration modules share: :func:`as_points`,
:func:`as_size` and :func:`o3d_cloud`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.errors import CleaningError

__all__ = [
    "CleanResult",
    "clean_cloud",
    "find_table_plane",
    "instrument_mask",
    "TablePlane",
    "as_points",
    "as_size",
    "o3d_cloud",
]


@dataclass(frozen=True)
class CleanResult:
    """Phantom points left after cleaning one cloud.

    Attributes:
        points_phantom: (M, 3) float64 phantom-frame points, m.
        counts: number of points at each stage; the removal counts and ``kept`` add up
            to ``raw``. Keys: ``raw`` (input), ``invalid`` (NaN/inf), ``table``,
            ``instrument``, ``outliers`` (outside the grown box or statistical
            outliers), ``downsampled`` (dropped by voxel/random subsampling), ``kept``.
        table_plane: (4,) float64 ``(a, b, c, d)`` of the table plane used, phantom frame,
            ``a x + b y + c z + d = 0`` with a unit normal pointing up (+z).
        table_source: ``"ransac"`` when the plane came from RANSAC on this cloud,
            ``"calibration"`` when z = 0 of the phantom frame was used.
    """

    points_phantom: np.ndarray
    counts: dict[str, int]
    table_plane: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0, 0.0]))
    table_source: str = "calibration"


@dataclass(frozen=True)
class TablePlane:
    """The support table found in a camera-frame cloud by :func:`find_table_plane`.

    Attributes:
        plane: (4,) float64 ``(a, b, c, d)``, camera frame, unit normal ``(a, b, c)``
            oriented toward the camera (``d > 0``: the camera origin is on the positive
            side), so ``height = points @ plane[:3] + plane[3]`` is the height above it, m.
        inliers: (I,) int64 indices of the plane's RANSAC inliers.
        support: number of points at the phantom's height above the plane (its top face),
            or 5 mm .. ``max_height`` above it when the height is not given.
    """

    plane: np.ndarray
    inliers: np.ndarray
    support: int


def as_points(name: str, a) -> np.ndarray:
    """``a`` as an (N, 3) float64 array of points (any frame, m), checked for shape only.

    Non-finite rows are kept: the callers drop or count them.

    Args:
        name: how the argument is called in the error message.
        a: array-like of shape (N, 3).

    Returns:
        (N, 3) float64 array (a copy only when ``a`` was not float64 already).

    Raises:
        ValueError: ``a`` is not two-dimensional with three columns.
    """
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {a.shape}")
    return a


def as_size(phantom_size) -> np.ndarray:
    """The phantom's box size ``(sx, sy, sz)`` as a (3,) float64 array, m.

    Args:
        phantom_size: array-like of three lengths, m (any shape that flattens to 3).

    Returns:
        (3,) float64 size, m; the box spans [0, sx] x [0, sy] x [0, sz] in the phantom frame.

    Raises:
        ValueError: not three values, or a value that is not > 0 (NaN included).
    """
    size = np.asarray(phantom_size, dtype=np.float64).reshape(-1)
    if size.shape != (3,) or not np.all(size > 0):
        raise ValueError(f"phantom_size must be 3 positive lengths (m), got {phantom_size!r}")
    return size


def o3d_cloud(points: np.ndarray):
    """An ``open3d.geometry.PointCloud`` holding ``points``.

    open3d is imported here, so importing this module stays cheap.

    Args:
        points: (N, 3) points, m, in whatever frame the caller works in; converted to a
            C-contiguous float64 copy for open3d.

    Returns:
        ``open3d.geometry.PointCloud`` with ``points`` set (no normals, no colours).

    Raises:
        RuntimeError: from open3d when ``points`` is not (N, 3).
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pcd


def _segment_plane(points: np.ndarray, threshold: float, iterations: int, seed: int):
    """RANSAC plane (open3d ``segment_plane``) refitted to its inliers by least squares.

    Returns (plane (4,) with unit normal, inlier indices (I,) int64).
    """
    import open3d as o3d

    o3d.utility.random.seed(int(seed))
    plane, inliers = o3d_cloud(points).segment_plane(
        distance_threshold=float(threshold), ransac_n=3, num_iterations=int(iterations)
    )
    plane = np.asarray(plane, dtype=np.float64).reshape(4)
    plane /= np.linalg.norm(plane[:3])
    inliers = np.asarray(inliers, dtype=np.int64)
    # open3d runs RANSAC iterations in parallel threads, so even with a seed its sample is
    # not reproducible. Refit by least squares on the threshold inliers until the inlier
    # set stops changing: the result then depends on the data, not on the sample drawn
    # (identical inputs give bit-identical planes, which sweeps rely on).
    for _ in range(10):
        if inliers.size < 3:
            break
        sub = points[inliers]
        c = sub.mean(axis=0)
        d = sub - c
        n = np.linalg.eigh(d.T @ d)[1][:, 0]  # the scatter's least direction: the plane's normal
        if n @ plane[:3] < 0:
            n = -n
        plane = np.r_[n, -n @ c]
        new = np.flatnonzero(np.abs(points @ plane[:3] + plane[3]) < threshold).astype(np.int64)
        if np.array_equal(new, inliers):
            break
        inliers = new
    return plane, inliers


def find_table_plane(
    points_camera: np.ndarray,
    *,
    phantom_height: float | None = None,
    max_height: float = 0.1,
    threshold: float = 0.0025,
    max_planes: int = 4,
    min_support: int = 30,
    iterations: int = 1000,
    seed: int = 0,
) -> TablePlane:
    """Find the support table in a camera-frame cloud without any calibration.

    Up to ``max_planes`` planes are extracted by sequential RANSAC (open3d
    ``segment_plane``, each refitted by least squares; each plane's inliers are removed
    before the next). The phantom's top face is a plane as well, so the table is chosen
    by what stands on it:

    1. with ``phantom_height`` known, a pair of parallel planes (< 5 deg) the second of
       which lies ``phantom_height`` (+-6 mm) on the camera side of the first is the
       table and the phantom's top face; the pair with the most inliers wins;
    2. otherwise (or if no such pair), the plane with the most inliers among those with at
       least ``min_support`` points on their camera side -- at ``phantom_height`` (+-4 mm)
       when known, else 5 mm .. ``max_height`` -- the top face has nothing above it but
       the instrument (which the reference cloud does not show).

    Args:
        points_camera: (N, 3) float64 camera-frame points, m (finite).
        phantom_height: the phantom's height (size z), m, or None.
        max_height: upper bound of the phantom's height above the table, m.
        threshold: RANSAC inlier distance, m (about 2.5x the depth noise).
        max_planes: number of planes tried.
        min_support: least number of points above a plane for it to count as the table.
        iterations: RANSAC iterations per plane.
        seed: RANSAC seed.

    Returns:
        :class:`TablePlane` (camera frame, normal toward the camera).

    Raises:
        CleaningError: no plane qualifies as the table.
    """
    pts = as_points("points_camera", points_camera)
    remaining = np.arange(pts.shape[0])
    planes: list[tuple[np.ndarray, np.ndarray, int]] = []  # (plane, inliers, support)
    for k in range(max_planes):
        if remaining.size < max(3 * min_support, 50):
            break
        plane, inl = _segment_plane(pts[remaining], threshold, iterations, seed + k)
        if inl.size < min_support:
            break
        if plane[3] < 0:  # orient the normal toward the camera (origin on the positive side)
            plane = -plane
        height = pts @ plane[:3] + plane[3]
        if phantom_height is not None:
            support = int(np.count_nonzero(np.abs(height - phantom_height) < 0.004))
        else:
            support = int(np.count_nonzero((height > 0.005) & (height < max_height)))
        planes.append((plane, remaining[inl], support))
        remaining = np.delete(remaining, inl)

    best: tuple[int, int] | None = None  # (score, index)
    if phantom_height is not None:
        for i, (pi, ii, _) in enumerate(planes):
            for j, (pj, ij, _) in enumerate(planes):
                if i == j or pi[:3] @ pj[:3] < np.cos(np.deg2rad(5.0)):
                    continue
                h = float(np.median(pts[ij] @ pi[:3] + pi[3]))
                if abs(h - phantom_height) < 0.006:
                    score = ii.size + ij.size
                    if best is None or score > best[0]:
                        best = (score, i)
    if best is None:
        for i, (_, inl, support) in enumerate(planes):
            if support >= min_support and (best is None or inl.size > best[0]):
                best = (inl.size, i)
    if best is None:
        raise CleaningError(
            f"no table plane found: among {len(planes)} RANSAC planes none is parallel to a top face "
            f"or has >= {min_support} points of the phantom on its camera side"
        )
    plane, inl, support = planes[best[1]]
    return TablePlane(plane=plane, inliers=inl, support=support)


def instrument_mask(
    points_phantom: np.ndarray,
    probe_centre_phantom: np.ndarray | None,
    shaft_axis_phantom: np.ndarray | None,
    *,
    probe_radius: float,
    shaft_radius: float,
    margin: float,
    top_z: float | None = None,
    top_margin: float = 0.003,
) -> np.ndarray:
    """Boolean (N,) mask of points inside the instrument (sphere tip + shaft cylinder).

    With ``top_z`` (the rest top face's height), points higher than ``top_z +
    top_margin`` within ``2 (probe_radius + margin)`` horizontally of the sphere centre
    count as instrument too: the phantom's surface next to a probe is pushed down, never
    millimetres up, so whatever is there is tool. This catches a probe bigger than its
    nominal radius, whose cap lies outside the nominal sphere (a 7.5 mm sphere recorded
    as 5 mm leaves its cap 8-10 mm from the calibrated centre, past a 2 mm margin).

    Args:
        points_phantom: (N, 3) float64 phantom-frame points, m.
        probe_centre_phantom: (3,) sphere centre, phantom frame, m; None: no instrument.
        shaft_axis_phantom: (3,) the tool z-axis in the phantom frame, pointing from the
            shaft toward the tip (into the phantom when poking from above). The shaft
            occupies ``centre - s * axis`` for ``s >= 0``. None: sphere only.
        probe_radius: sphere radius, m. shaft_radius: cylinder radius, m.
        margin: added to both radii, m (noise, kinematic error).
        top_z, top_margin: see above, m (3 mm ~ 3 sigma of SR300 depth noise, as the
            table margin). None: no height test.
    """
    n = points_phantom.shape[0]
    if probe_centre_phantom is None:
        return np.zeros(n, dtype=bool)
    c = np.asarray(probe_centre_phantom, dtype=np.float64).reshape(3)
    d = points_phantom - c
    mask = np.einsum("ij,ij->i", d, d) < (probe_radius + margin) ** 2
    if shaft_axis_phantom is not None:
        a = np.asarray(shaft_axis_phantom, dtype=np.float64).reshape(3)
        norm = np.linalg.norm(a)
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"shaft_axis_phantom must be a non-zero 3-vector, got {shaft_axis_phantom!r}")
        u = -a / norm  # from the tip centre up the shaft
        s = d @ u
        perp2 = np.einsum("ij,ij->i", d, d) - s**2
        mask |= (s > 0.0) & (perp2 < (shaft_radius + margin) ** 2)
    if top_z is not None:
        near = np.einsum("ij,ij->i", d[:, :2], d[:, :2]) < (2.0 * (probe_radius + margin)) ** 2
        mask |= near & (points_phantom[:, 2] > top_z + top_margin)
    return mask


#: Up to this many points, statistical outlier removal runs on the points themselves.
_DIRECT_MAX = 8000


def _statistical_inliers(q: np.ndarray, k: int, std_ratio: float, voxel: float) -> np.ndarray:
    """Boolean (N,) inlier mask of statistical outlier removal (Rusu et al. 2008; open3d).

    For more than ``_DIRECT_MAX`` points and ``voxel > 0`` the filter runs on voxel centroids.
    """
    if q.shape[0] <= _DIRECT_MAX or voxel <= 0:
        _, keep = o3d_cloud(q).remove_statistical_outlier(nb_neighbors=k, std_ratio=std_ratio)
        mask = np.zeros(q.shape[0], dtype=bool)
        mask[np.asarray(keep, dtype=np.int64)] = True
        return mask
    ijk = np.floor((q - q.min(axis=0)) / voxel).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    flat = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    cells, inverse = np.unique(flat, return_inverse=True)
    n = np.bincount(inverse, minlength=cells.size).astype(np.float64)
    centroids = np.stack([np.bincount(inverse, weights=q[:, j], minlength=cells.size) for j in range(3)], 1)
    centroids /= n[:, None]
    if cells.size <= k + 1:
        return np.ones(q.shape[0], dtype=bool)
    return _statistical_inliers(centroids, k, std_ratio, 0.0)[inverse]


def clean_cloud(
    points_camera: np.ndarray,
    T_phantom_camera: np.ndarray,
    phantom_size,
    *,
    probe_centre_phantom: np.ndarray | None = None,
    shaft_axis_phantom: np.ndarray | None = None,
    probe_radius: float = 0.005,
    shaft_radius: float = 0.0045,
    margin: float = 0.002,
    voxel_size: float = 0.0,
    max_points: int | None = None,
    seed: int = 0,
    table_margin: float = 0.003,
    table_ransac: bool = True,
    crop_margin: float = 0.015,
    outlier_neighbors: int = 16,
    outlier_std_ratio: float = 2.5,
    outlier_voxel: float = 0.002,
    min_points: int = 10,
) -> CleanResult:
    """Remove table, instrument and outliers from one raw camera cloud (Wu et al. 2020, Sec. 3.1).

    Args:
        points_camera: (N, 3) float raw camera-frame points, m. Non-finite rows are dropped.
        T_phantom_camera: (4, 4) camera calibration (see :func:`calibrate_camera`).
        phantom_size: (3,) box size (sx, sy, sz), m.
        probe_centre_phantom: (3,) probe sphere centre in the phantom frame at this
            frame's time, m; None when the instrument is not in view / unknown.
        shaft_axis_phantom: (3,) tool z-axis in the phantom frame (shaft -> tip); the shaft
            cylinder runs from the centre along ``-shaft_axis_phantom``. None: no shaft.
        probe_radius, shaft_radius: instrument radii, m.
        margin: grows both instrument radii, m.
        voxel_size: voxel edge for ``voxel_down_sample``, m; 0 disables.
        max_points: random subsample (seeded by ``seed``) to at most this many points.
        seed: seed of RANSAC and of the random subsample.
        table_margin: points less than this above the table plane are table, m
            (3 mm ~ 3 sigma of SR300 depth noise; costs the lowest 3 mm of the sides).
        table_ransac: fit the table by RANSAC on the near-z=0 points outside the phantom's
            footprint (see module docstring); False: use the calibrated plane z = 0.
        crop_margin: the phantom box is grown by this sideways and upward before cropping, m.
        outlier_neighbors, outlier_std_ratio: statistical outlier removal parameters
            (a point goes when its mean distance to that many neighbours exceeds the
            global mean by ``std_ratio`` standard deviations); ``outlier_neighbors=0``
            disables it.
        outlier_voxel: above ``_DIRECT_MAX`` points the statistic is computed on the
            centroids of voxels of this edge (m) and each point inherits its voxel's
            verdict, which bounds the cost by the surface area instead of the point
            count (k-NN of 16k phantom points takes ~30 ms on two cores, on 2 mm voxels ~5 ms).
        min_points: fewer phantom points than this left raises.

    Returns:
        :class:`CleanResult` with phantom-frame points and per-stage counts.

    Raises:
        ValueError: malformed arguments.
        CleaningError: fewer than ``min_points`` phantom points are left.
    """
    pts = as_points("points_camera", points_camera)
    T = np.asarray(T_phantom_camera, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_phantom_camera must be (4, 4), got {T.shape}")
    size = as_size(phantom_size)
    counts = {"raw": int(pts.shape[0]), "invalid": 0, "table": 0, "instrument": 0, "outliers": 0,
              "downsampled": 0, "kept": 0}

    finite = np.all(np.isfinite(pts), axis=1)
    counts["invalid"] = int(np.count_nonzero(~finite))
    q = pts[finite] @ T[:3, :3].T + T[:3, 3]

    # 1. table
    plane = np.array([0.0, 0.0, 1.0, 0.0])
    source = "calibration"
    if table_ransac:
        band = 0.01
        cand = np.abs(q[:, 2]) < band
        cand &= (q[:, 0] < -0.001) | (q[:, 0] > size[0] + 0.001) | (q[:, 1] < -0.001) | (q[:, 1] > size[1] + 0.001)
        idx = np.flatnonzero(cand)
        if idx.size > 3000:  # a plane needs few points; keeps RANSAC well under a millisecond
            idx = np.random.default_rng(seed).choice(idx, size=3000, replace=False)
        if idx.size >= 50:
            p, inl = _segment_plane(q[idx], threshold=0.5 * table_margin + 1e-4, iterations=100, seed=seed)
            if p[2] < 0:
                p = -p
            centre_height = -(p[0] * size[0] / 2 + p[1] * size[1] / 2 + p[3]) / p[2]
            if p[2] > np.cos(np.deg2rad(10.0)) and abs(centre_height) < 0.005 and inl.size >= 30:
                plane, source = p, "ransac"
    height = q @ plane[:3] + plane[3]
    is_table = height < table_margin
    counts["table"] = int(np.count_nonzero(is_table))
    q = q[~is_table]

    # 2. instrument
    if probe_centre_phantom is not None:
        inst = instrument_mask(q, probe_centre_phantom, shaft_axis_phantom, probe_radius=probe_radius,
                               shaft_radius=shaft_radius, margin=margin, top_z=float(size[2]))
        counts["instrument"] = int(np.count_nonzero(inst))
        q = q[~inst]

    # 3. outliers: crop, then statistical removal
    g = crop_margin
    inside = ((q[:, 0] > -g) & (q[:, 0] < size[0] + g) & (q[:, 1] > -g) & (q[:, 1] < size[1] + g)
              & (q[:, 2] < size[2] + g))
    n_out = int(np.count_nonzero(~inside))
    q = q[inside]
    if outlier_neighbors > 0 and q.shape[0] > outlier_neighbors + 1:
        keep = _statistical_inliers(q, int(outlier_neighbors), float(outlier_std_ratio), outlier_voxel)
        n_out += q.shape[0] - int(np.count_nonzero(keep))
        q = q[keep]
    counts["outliers"] = n_out

    if q.shape[0] < min_points:
        raise CleaningError(
            f"nothing of the phantom is left: {q.shape[0]} points after cleaning (need >= {min_points}); "
            f"counts {counts} -- check T_phantom_camera and phantom_size"
        )

    # 4. downsampling
    n_before = q.shape[0]
    if voxel_size > 0:
        q = np.asarray(o3d_cloud(q).voxel_down_sample(float(voxel_size)).points, dtype=np.float64)
    if max_points is not None and q.shape[0] > max_points:
        if max_points < 1:
            raise ValueError(f"max_points must be >= 1, got {max_points}")
        rng = np.random.default_rng(seed)
        q = q[np.sort(rng.choice(q.shape[0], size=int(max_points), replace=False))]
    counts["downsampled"] = n_before - q.shape[0]
    counts["kept"] = int(q.shape[0])
    return CleanResult(points_phantom=np.ascontiguousarray(q), counts=counts, table_plane=plane,
                       table_source=source)
