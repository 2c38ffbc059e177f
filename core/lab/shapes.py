"""Phantom shapes of the virtual lab beside the paper's box: a dome and a kidney-like
body, as watertight triangle surfaces in the phantom frame (metres, z up, resting on
z = 0), to be written as a session's ``phantom.stl`` and filled by
:func:`core.simulation.meshing.tetrahedralise`.

Both are an ellipsoid cut by the support plane: the dome a sphere cut above its centre
(a spherical cap on a flat disc), the kidney-like body an ellipsoid cut below its centre
(a flattened base, as a silicone kidney lies on a table).
"""

from __future__ import annotations

import numpy as np

from core.errors import TissueTwinError

__all__ = ["SHAPES", "cut_ellipsoid_surface", "dome_surface", "kidney_surface", "shape_surface"]

#: The lab's shape names (``tissuetwin generate --shape``).
SHAPES = ("box", "dome", "kidney")


def cut_ellipsoid_surface(semi_axes, centre_height: float, *, rings: int = 24, segments: int = 64,
                          base_rings: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The part of an ellipsoid above z = 0, closed by its flat base.

    The ellipsoid has semi-axes ``(a, b, c)`` along x, y, z and its centre at height
    ``centre_height``, placed in x and y so that the body's bounding box starts at
    x = y = 0.

    Args:
        semi_axes: (3,) a, b, c, m.
        centre_height: z of the centre, m, in ``(-c, c)``: negative for a cap (less
            than half the ellipsoid), positive for more than half.
        rings, segments: latitude rings of the curved part and points per ring.
        base_rings: rings of the flat base between its rim and centre.

    Returns:
        vertices (V, 3) float64 m, faces (F, 3) int64, counter-clockwise seen from
        outside (normals out); the surface is watertight.

    Raises:
        TissueTwinError: non-positive axes or a centre height outside ``(-c, c)``.
    """
    a, b, c = (float(v) for v in np.asarray(semi_axes, dtype=np.float64).reshape(3))
    z0 = float(centre_height)
    if min(a, b, c) <= 0 or not -c < z0 < c:
        raise TissueTwinError(f"need positive semi-axes and -c < centre height < c, got {(a, b, c)}, {z0}")
    # polar angle from the top down to where the ellipsoid meets z = 0
    t_rim = float(np.arccos(-z0 / c))
    widest = np.sin(t_rim) if z0 < 0 else 1.0  # the widest ring: the rim of a cap, the equator otherwise
    cx, cy = a * widest, b * widest
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    verts = [np.array([[cx, cy, z0 + c]])]
    for t in np.linspace(0.0, t_rim, rings + 1)[1:]:
        ring = np.stack([cx + a * np.sin(t) * np.cos(phi), cy + b * np.sin(t) * np.sin(phi),
                         np.full(segments, z0 + c * np.cos(t))], axis=1)
        verts.append(ring)
    verts[-1][:, 2] = 0.0
    rim_scale = np.sin(t_rim)
    for s in np.linspace(1.0, 0.0, base_rings + 1)[1:-1]:
        verts.append(np.stack([cx + a * rim_scale * s * np.cos(phi), cy + b * rim_scale * s * np.sin(phi),
                               np.zeros(segments)], axis=1))
    verts.append(np.array([[cx, cy, 0.0]]))
    V = np.concatenate(verts, axis=0)

    n_rings = rings + base_rings - 1  # rings of `segments` points, top to base centre
    faces = []
    j = np.arange(segments)
    k = (j + 1) % segments
    first = 1
    faces.append(np.stack([np.zeros(segments, dtype=np.int64), first + j, first + k], axis=1))
    for r in range(n_rings - 1):
        up, dn = first + r * segments, first + (r + 1) * segments
        faces.append(np.stack([up + j, dn + j, dn + k], axis=1))
        faces.append(np.stack([up + j, dn + k, up + k], axis=1))
    last, centre = first + (n_rings - 1) * segments, V.shape[0] - 1
    faces.append(np.stack([last + j, np.full(segments, centre), last + k], axis=1))
    F = np.concatenate(faces, axis=0).astype(np.int64)
    return V, _outward(V, F)


def _outward(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Flip all faces if the signed volume is negative (the construction's winding is
    fixed, so one global check settles it)."""
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    signed = np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0
    return F if signed > 0 else F[:, [0, 2, 1]]


def dome_surface(base_radius: float = 0.035, height: float = 0.025, **kw) -> tuple[np.ndarray, np.ndarray]:
    """A spherical cap of ``height`` on a flat disc of ``base_radius`` (m), footprint in
    ``[0, 2 base_radius]^2``. See :func:`cut_ellipsoid_surface` for the returns."""
    if not 0 < height <= base_radius:
        raise TissueTwinError(f"a dome needs 0 < height <= base radius, got {height}, {base_radius}")
    R = (base_radius**2 + height**2) / (2.0 * height)
    if height == base_radius:  # a hemisphere: centre on the plane, nudged to keep -c < z0
        return cut_ellipsoid_surface((R, R, R), -1e-9, **kw)
    return cut_ellipsoid_surface((R, R, R), height - R, **kw)


def kidney_surface(length: float = 0.070, width: float = 0.040, thickness: float = 0.030,
                   flattening: float = 0.3, **kw) -> tuple[np.ndarray, np.ndarray]:
    """A kidney-like body: an ellipsoid of semi-axes ``length / 2, width / 2, c`` (m) cut
    flat below its centre so that it lies on the table, ``thickness`` (m) high;
    ``flattening`` is the fraction of ``c`` cut off (``c = thickness / (2 - flattening)``).
    See :func:`cut_ellipsoid_surface` for the returns."""
    if not 0 < flattening < 1:
        raise TissueTwinError(f"flattening must be in (0, 1), got {flattening}")
    c = thickness / (2.0 - flattening)
    return cut_ellipsoid_surface((length / 2.0, width / 2.0, c), thickness - c, **kw)


def shape_surface(shape: str, **kw) -> tuple[np.ndarray, np.ndarray]:
    """The surface of a named lab shape (``"dome"`` or ``"kidney"``).

    Raises:
        TissueTwinError: an unknown name (``"box"`` has no STL: the lab uses the grid)."""
    if shape == "dome":
        return dome_surface(**kw)
    if shape == "kidney":
        return kidney_surface(**kw)
    raise TissueTwinError(f"unknown phantom shape {shape!r}: one of dome, kidney (a box needs no STL)")
