"""Depth-camera model of the virtual lab, after the Intel RealSense SR300 of Wu et al. 2020.

A pinhole camera (OpenCV convention: x right, y down, z forward) casts one ray per pixel
of a region of interest into a scene of triangle meshes (deformed phantom surface,
table plane, probe sphere, instrument shaft) with Open3D's ``RaycastingScene``
(Embree BVH). The ideal depth is then corrupted like a structured-light sensor:

- depth noise along the ray, Gaussian with sigma growing with the square of depth
  (the usual triangulation error law, e.g. Khoshelham & Elberink 2012, Sensors 12:1437);
- grazing-angle dropouts (no return when the surface is seen nearly edge-on);
- random dropouts;
- flying pixels at depth discontinuities and a few stray outliers;
- depth quantisation (the SR300 reports depth in 1/8 mm .. 1/4 mm units).

Frames: scene geometry is given in the phantom frame; ``T_phantom_camera`` (4, 4) maps
camera-frame points into the phantom frame. Output points are in the camera frame, m.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Intrinsics",
    "DepthNoise",
    "DepthCamera",
    "Instrument",
    "RayHits",
    "look_at_pose",
    "random_camera_pose",
    "roi_for_box",
    "cast",
    "apply_depth_noise",
    "depth_to_points",
    "render_points",
    "table_mesh",
    "table_ring_mask",
    "instrument_meshes",
    "GEOMETRY_PHANTOM",
    "GEOMETRY_TABLE",
    "GEOMETRY_SPHERE",
    "GEOMETRY_SHAFT",
]

GEOMETRY_PHANTOM = 0
GEOMETRY_TABLE = 1
GEOMETRY_SPHERE = 2
GEOMETRY_SHAFT = 3


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics, pixels. Pixel (u, v) has its centre at (u, v)."""

    width: int
    """Image width, px."""
    height: int
    """Image height, px."""
    fx: float
    """Focal length along x, px."""
    fy: float
    """Focal length along y, px."""
    cx: float
    """Principal point x, px."""
    cy: float
    """Principal point y, px."""

    def to_dict(self) -> dict:
        """As in session.json ``camera.intrinsics``."""
        return {"width": int(self.width), "height": int(self.height), "fx": float(self.fx),
                "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy)}

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> "Intrinsics":
        """Square pixels, principal point at the image centre, horizontal field of view in degrees."""
        f = (width / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
        return cls(width, height, float(f), float(f), (width - 1) / 2, (height - 1) / 2)

    def jittered(self, rng: np.random.Generator, rel: float = 0.005, px: float = 2.0) -> "Intrinsics":
        """A per-unit variation: focal lengths within ``rel`` (relative), principal point within ``px``."""
        return Intrinsics(self.width, self.height,
                          float(self.fx * (1 + rng.uniform(-rel, rel))),
                          float(self.fy * (1 + rng.uniform(-rel, rel))),
                          float(self.cx + rng.uniform(-px, px)),
                          float(self.cy + rng.uniform(-px, px)))


@dataclass(frozen=True)
class DepthNoise:
    """Sensor imperfections. Set a field to 0 to switch it off."""

    sigma: float = 0.001
    """Standard deviation of the depth noise along the ray at ``reference_depth``, m."""
    reference_depth: float = 0.3
    """Depth at which ``sigma`` applies; sigma scales with (depth / reference_depth)^2, m."""
    quantization: float = 0.00025
    """Depth quantisation step, m."""
    dropout: float = 0.05
    """Probability that a valid pixel returns nothing."""
    grazing_cos: tuple[float, float] = (0.12, 0.30)
    """Below the first |cos(incidence)| a pixel always drops out, above the second never;
    linear in between."""
    flying_fraction: float = 0.004
    """Fraction of valid pixels turned into flying pixels (depth between a pixel and its
    neighbour across a depth edge)."""
    outlier_fraction: float = 0.001
    """Fraction of valid pixels with a stray depth error of up to ``outlier_range``."""
    outlier_range: float = 0.03
    """Largest stray depth error, m."""
    edge_threshold: float = 0.004
    """Depth step between neighbours that counts as a depth edge, m."""


@dataclass(frozen=True)
class DepthCamera:
    """A posed depth camera.

    Attributes:
        intrinsics: pinhole model.
        T_phantom_camera: (4, 4) maps camera-frame points into the phantom frame.
        roi: (u0, u1, v0, v1) pixel window that is ray cast (half-open), default the full image.
        noise: sensor imperfections.
    """

    intrinsics: Intrinsics
    T_phantom_camera: np.ndarray
    roi: tuple[int, int, int, int] | None = None
    noise: DepthNoise = field(default_factory=DepthNoise)

    def __post_init__(self):
        T = np.asarray(self.T_phantom_camera, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_phantom_camera must be (4, 4), got {T.shape}")
        object.__setattr__(self, "T_phantom_camera", T)
        if self.roi is None:
            object.__setattr__(self, "roi", (0, self.intrinsics.width, 0, self.intrinsics.height))

    def pixel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) pixel coordinates of the ROI, each (H_roi, W_roi) float64."""
        u0, u1, v0, v1 = self.roi
        return np.meshgrid(np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))

    def rays_phantom(self) -> np.ndarray:
        """(H_roi * W_roi, 6) float32 rays (origin, direction) in the phantom frame. Directions
        have unit camera-z component, so a hit's ray parameter is its camera-frame depth."""
        u, v = self.pixel_grid()
        k = self.intrinsics
        d_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        R, t = self.T_phantom_camera[:3, :3], self.T_phantom_camera[:3, 3]
        d = d_cam @ R.T
        o = np.broadcast_to(t, d.shape)
        return np.concatenate([o, d], axis=1).astype(np.float32)


@dataclass(frozen=True)
class Instrument:
    """The visible instrument: tip sphere plus a cylindrical shaft.

    Attributes:
        centre: (3,) sphere centre, m, phantom frame.
        shaft_direction: (3,) unit vector from the sphere centre along the shaft (-z_tool).
        radius: sphere radius, m.
        shaft_radius: m (the dVRK's 8 mm instruments).
        shaft_length: visible shaft length from the sphere centre, m.
    """

    centre: np.ndarray
    shaft_direction: np.ndarray
    radius: float = 0.005
    shaft_radius: float = 0.004
    shaft_length: float = 0.15


@dataclass(frozen=True)
class RayHits:
    """Ideal ray-cast result on the ROI, each (H_roi, W_roi).

    Attributes:
        depth: camera-frame z of the first hit, m (inf where nothing was hit).
        cos_incidence: |cos| of the angle between ray and surface normal.
        geometry: which object was hit (``GEOMETRY_*``), -1 for none.
    """

    depth: np.ndarray
    cos_incidence: np.ndarray
    geometry: np.ndarray


def look_at_pose(eye, target, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """(4, 4) T_world_camera of an OpenCV camera at ``eye`` looking at ``target``, image
    'up' towards ``up``, rolled by ``roll`` rad about the optical axis."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    y = -(up - (up @ z) * z)
    if np.linalg.norm(y) < 1e-9:
        raise ValueError("look_at_pose: viewing direction is parallel to 'up'")
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def random_camera_pose(
    rng: np.random.Generator,
    target,
    *,
    distance_range=(0.25, 0.35),
    tilt_range_deg=(20.0, 45.0),
    azimuth: float | None = None,
    target_jitter: float = 0.005,
    roll_range_deg=(-15.0, 15.0),
) -> np.ndarray:
    """(4, 4) T_phantom_camera looking down at ``target`` from ``distance_range`` m,
    ``tilt_range_deg`` from vertical, at a random (or given) azimuth, rad."""
    dist = rng.uniform(*distance_range)
    tilt = np.deg2rad(rng.uniform(*tilt_range_deg))
    az = rng.uniform(0, 2 * np.pi) if azimuth is None else azimuth
    aim = np.asarray(target, dtype=np.float64) + rng.uniform(-target_jitter, target_jitter, 3)
    eye = aim + dist * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    return look_at_pose(eye, aim, roll=np.deg2rad(rng.uniform(*roll_range_deg)))


def roi_for_box(intrinsics: Intrinsics, T_phantom_camera: np.ndarray, lo, hi) -> tuple[int, int, int, int]:
    """Pixel window (u0, u1, v0, v1) covering the box ``[lo, hi]`` (phantom frame), clipped
    to the image. The whole image if a corner lies behind the camera."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    T_cp = np.linalg.inv(T_phantom_camera)
    pc = corners @ T_cp[:3, :3].T + T_cp[:3, 3]
    k = intrinsics
    if np.any(pc[:, 2] <= 1e-3):
        return (0, k.width, 0, k.height)
    u = k.fx * pc[:, 0] / pc[:, 2] + k.cx
    v = k.fy * pc[:, 1] / pc[:, 2] + k.cy
    u0 = int(np.clip(np.floor(u.min()), 0, k.width))
    u1 = int(np.clip(np.ceil(u.max()) + 1, 0, k.width))
    v0 = int(np.clip(np.floor(v.min()), 0, k.height))
    v1 = int(np.clip(np.ceil(v.max()) + 1, 0, k.height))
    if u1 <= u0 or v1 <= v0:
        raise ValueError(f"the box {lo.tolist()}..{hi.tolist()} is not in view of the camera")
    return (u0, u1, v0, v1)


def table_mesh(centre, half_size: float = 0.5, z: float = -1e-6) -> tuple[np.ndarray, np.ndarray]:
    """A square table plane at height ``z`` around ``centre`` (x, y), as (4, 3) vertices
    and (2, 3) upward-facing triangles, phantom frame.

    The default 1 um gap below the phantom's base only keeps the ray caster from hitting
    two coincident planes. It was 10 um once: the replay anchors z = 0 on the table, so
    the gap became a 10 um vertical calibration bias, 1 % of a 1 mm gravity sag and a
    1.3 % bias of E in gravity fits (measured; 0.4 % with 1 um).
    """
    cx, cy = float(centre[0]), float(centre[1])
    h = half_size
    v = np.array([[cx - h, cy - h, z], [cx + h, cy - h, z], [cx + h, cy + h, z], [cx - h, cy + h, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def table_ring_mask(rays: np.ndarray, lo_xy, hi_xy, z: float = -1e-6) -> np.ndarray:
    """(R,) bool: rays whose crossing with the table plane ``z`` lies in the rectangle
    ``[lo_xy, hi_xy]`` (phantom frame). Used to keep only a ring of table around the
    phantom, so clouds stay small while the table plane remains measurable."""
    o, d = rays[:, :3].astype(np.float64), rays[:, 3:].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z - o[:, 2]) / d[:, 2]
    p = o[:, :2] + s[:, None] * d[:, :2]
    lo, hi = np.asarray(lo_xy, float), np.asarray(hi_xy, float)
    return (s > 0) & np.all((p >= lo) & (p <= hi), axis=1)


_UNIT_SPHERE = None
_UNIT_CYLINDER = None


def _unit_sphere():
    """Icosphere (642 vertices) of radius 1 at the origin."""
    global _UNIT_SPHERE
    if _UNIT_SPHERE is None:
        import trimesh

        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        _UNIT_SPHERE = (np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))
    return _UNIT_SPHERE


def _unit_cylinder(sections: int = 32):
    """Closed cylinder of radius 1 from z = 0 to z = 1."""
    global _UNIT_CYLINDER
    if _UNIT_CYLINDER is None:
        a = np.linspace(0, 2 * np.pi, sections, endpoint=False)
        ring = np.stack([np.cos(a), np.sin(a)], axis=1)
        verts = np.concatenate([
            np.c_[ring, np.zeros(sections)], np.c_[ring, np.ones(sections)], [[0, 0, 0], [0, 0, 1]]])
        i = np.arange(sections)
        j = (i + 1) % sections
        side = np.concatenate([np.stack([i, j, j + sections], 1), np.stack([i, j + sections, i + sections], 1)])
        b, t = 2 * sections, 2 * sections + 1
        caps = np.concatenate([np.stack([np.full(sections, b), j, i], 1),
                               np.stack([np.full(sections, t), i + sections, j + sections], 1)])
        _UNIT_CYLINDER = (verts, np.concatenate([side, caps]))
    return _UNIT_CYLINDER


def instrument_meshes(inst: Instrument) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(sphere vertices, triangles), (shaft vertices, triangles)] in the phantom frame."""
    sv, st = _unit_sphere()
    sphere = (sv * inst.radius + np.asarray(inst.centre, float), st)
    cv, ct = _unit_cylinder()
    d = np.asarray(inst.shaft_direction, float)
    d = d / np.linalg.norm(d)
    ref = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    a = np.cross(d, ref)
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    R = np.stack([a, b, d], axis=1)
    scaled = cv * np.array([inst.shaft_radius, inst.shaft_radius, inst.shaft_length])
    shaft = (scaled @ R.T + np.asarray(inst.centre, float), ct)
    return [sphere, shaft]


def cast(
    camera: DepthCamera,
    phantom: tuple[np.ndarray, np.ndarray],
    *,
    table: tuple[np.ndarray, np.ndarray] | None = None,
    instrument: Instrument | None = None,
    rays: np.ndarray | None = None,
    table_keep: np.ndarray | None = None,
) -> RayHits:
    """Ideal ray cast of the ROI against the phantom surface ``(vertices (V, 3), triangles
    (T, 3))``, the optional table and instrument (all phantom frame).

    ``rays`` may pass ``camera.rays_phantom()`` precomputed (it depends on the camera only).
    ``table_keep`` (R,) bool drops table hits of the other rays (see :func:`table_ring_mask`).
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = {}

    def add(mesh, gid):
        v, t = mesh
        handle = scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(v, dtype=np.float32)),
                                     o3d.core.Tensor(np.ascontiguousarray(t, dtype=np.uint32)))
        ids[handle] = gid

    add(phantom, GEOMETRY_PHANTOM)
    if table is not None:
        add(table, GEOMETRY_TABLE)
    if instrument is not None:
        sphere, shaft = instrument_meshes(instrument)
        add(sphere, GEOMETRY_SPHERE)
        add(shaft, GEOMETRY_SHAFT)
    if rays is None:
        rays = camera.rays_phantom()
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t_hit)
    gid_raw = ans["geometry_ids"].numpy()
    lut = np.full(max(ids) + 1, -1, dtype=np.int64)
    for handle, gid in ids.items():
        lut[handle] = gid
    geometry = np.full(t_hit.shape, -1, dtype=np.int64)
    geometry[hit] = lut[gid_raw[hit]]
    if table_keep is not None:
        drop = (geometry == GEOMETRY_TABLE) & ~table_keep
        t_hit[drop] = np.inf
        geometry[drop] = -1
        hit = np.isfinite(t_hit)
    n = ans["primitive_normals"].numpy().astype(np.float64)
    d = rays[:, 3:].astype(np.float64)
    cos = np.abs(np.sum(n * d, axis=1)) / np.linalg.norm(d, axis=1)
    cos[~hit] = 0.0
    u0, u1, v0, v1 = camera.roi
    shape = (v1 - v0, u1 - u0)
    return RayHits(t_hit.reshape(shape), cos.reshape(shape), geometry.reshape(shape))


def apply_depth_noise(hits: RayHits, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    """(H_roi, W_roi) measured depth, m, NaN where the sensor returns nothing."""
    z = hits.depth.copy()
    valid = np.isfinite(z)
    # grazing-angle and random dropouts
    c0, c1 = noise.grazing_cos
    p_graze = np.clip((c1 - hits.cos_incidence) / max(c1 - c0, 1e-9), 0.0, 1.0) if c1 > 0 else 0.0
    p_drop = 1.0 - (1.0 - p_graze) * (1.0 - noise.dropout)
    keep = valid & (rng.random(z.shape) >= p_drop)
    # depth noise along the ray (sigma ~ z^2)
    sigma = noise.sigma * (np.where(valid, z, 0.0) / noise.reference_depth) ** 2
    z = z + sigma * rng.standard_normal(z.shape)
    # flying pixels at depth edges: depth blended towards a neighbour across the edge
    n_valid = int(valid.sum())
    if noise.flying_fraction > 0 and n_valid:
        zi = np.pad(np.where(valid, hits.depth, np.nan), 1, constant_values=np.nan)
        h, w = z.shape
        best = np.zeros_like(z)
        for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            nb = zi[1 + dv:1 + dv + h, 1 + du:1 + du + w]
            diff = np.nan_to_num(nb - zi[1:-1, 1:-1], nan=0.0)
            best = np.where(np.abs(diff) > np.abs(best), diff, best)
        edge = valid & (np.abs(best) > noise.edge_threshold)
        edge_idx = np.flatnonzero(edge)
        n_fly = min(int(round(noise.flying_fraction * n_valid)), edge_idx.size)
        if n_fly:
            pick = rng.choice(edge_idx, size=n_fly, replace=False)
            zf = z.reshape(-1)
            zf[pick] += rng.uniform(0.15, 0.85, n_fly) * best.reshape(-1)[pick]
            keep.reshape(-1)[pick] = True
    if noise.outlier_fraction > 0 and n_valid:
        n_out = int(round(noise.outlier_fraction * n_valid))
        if n_out:
            pick = rng.choice(np.flatnonzero(valid), size=n_out, replace=False)
            zf = z.reshape(-1)
            zf[pick] += rng.uniform(-noise.outlier_range, noise.outlier_range, n_out)
            keep.reshape(-1)[pick] = True
    if noise.quantization > 0:
        z = np.round(z / noise.quantization) * noise.quantization
    keep &= z > 0
    return np.where(keep, z, np.nan)


def depth_to_points(camera: DepthCamera, depth: np.ndarray) -> np.ndarray:
    """(N, 3) float32 camera-frame points (OpenCV: x right, y down, z forward), m, of the
    finite pixels of a ROI depth image, row-major pixel order."""
    u, v = camera.pixel_grid()
    ok = np.isfinite(depth)
    z = depth[ok]
    k = camera.intrinsics
    x = (u[ok] - k.cx) / k.fx * z
    y = (v[ok] - k.cy) / k.fy * z
    return np.stack([x, y, z], axis=1).astype(np.float32)


def render_points(
    camera: DepthCamera,
    phantom: tuple[np.ndarray, np.ndarray],
    rng: np.random.Generator,
    *,
    table: tuple[np.ndarray, np.ndarray] | None = None,
    instrument: Instrument | None = None,
    rays: np.ndarray | None = None,
    table_keep: np.ndarray | None = None,
) -> np.ndarray:
    """One noisy frame: (N, 3) float32 points, camera frame, m. See :func:`cast`."""
    hits = cast(camera, phantom, table=table, instrument=instrument, rays=rays, table_keep=table_keep)
    return depth_to_points(camera, apply_depth_noise(hits, camera.noise, rng))
