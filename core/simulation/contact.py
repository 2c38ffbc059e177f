"""Sphere-probe contact with the phantom surface.

The instrument tip is a sphere (Wu et al. 2020, Sec. 3.2: "approximate it as a sphere
of radius 5 mm"). The contact surface is the FEM surface with each triangle split
n x n (``SimulationConfig.contact_subdivision``), its sub-triangles mapped barycentrically
on the triangle's nodes: a finer collision model on the coarse mesh, as SOFA maps a
collision surface on its FEM. Each sub-triangle whose closest point lies inside the
sphere gives one penalty constraint on that material point, of the sub-triangle's area,
so the probe cannot slip between the nodes of a coarse mesh and the penalty is a
quadrature of a contact pressure over the indented area.

Why it was tried: with one contact per triangle (n = 1, the default), a 5 mm sphere on the
13 x 5 x 5 grid (elements 5.3 x 7.9 mm) touches one to three triangles, often through a
shared vertex, and a phantom free to move on a compliant base slid to one side or the other
depending on E by 1 %. Measured on that press, n = 3 moved the jump (0.97-0.98 E to 0.85-0.88 E)
but did not remove it, at 23 % of the replay's speed: the coarse body's lateral support is
part of the cause, so the option stays off by default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Contacts", "closest_points_on_triangles", "contact_corners", "find_contacts", "find_contacts_reference"]


@dataclass(frozen=True)
class Contacts:
    """Active probe contacts, one per penetrated sub-triangle of the contact surface.

    Attributes:
        triangles: (k,) int64 indices into the mesh's surface triangles (the parent).
        nodes: (k, 3) int64 node indices of those triangles.
        weights: (k, 3) float64 barycentric weights of the contact point.
        normals: (k, 3) float64 unit vectors from the sphere centre towards the
            contact point (the direction the probe pushes the surface).
        depth: (k,) float64 penetration in m (> 0 inside the sphere).
        area: (k,) float64 sub-triangle areas in m^2 (penalty stiffness per unit area).
        sub: (k,) int64 sub-triangle index (rows of
            :func:`core.simulation.kernels.subdivision_corners`), or None.
        sub_weights: (k, 3) float64 barycentric weights of the contact point in its
            sub-triangle, or None.
    """

    triangles: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    area: np.ndarray
    sub: np.ndarray | None = None
    sub_weights: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.triangles.shape[0])


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest point on each triangle (a, b, c) to the point p (Ericson 2004, Sec. 5.1.5).

    Args:
        p: (3,) query point. a, b, c: (T, 3) triangle corners.

    Returns:
        (q, w): q (T, 3) closest points, w (T, 3) their barycentric weights.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    T = a.shape[0]
    w = np.zeros((T, 3))
    done = np.zeros(T, dtype=bool)

    def assign(mask, wa, wb, wc):
        m = mask & ~done
        w[m, 0], w[m, 1], w[m, 2] = wa[m], wb[m], wc[m]
        done[m] = True

    one, zero = np.ones(T), np.zeros(T)
    with np.errstate(divide="ignore", invalid="ignore"):
        assign((d1 <= 0) & (d2 <= 0), one, zero, zero)
        assign((d3 >= 0) & (d4 <= d3), zero, one, zero)
        assign((d6 >= 0) & (d5 <= d6), zero, zero, one)
        v = d1 / (d1 - d3)
        assign((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - v, v, zero)
        v = d2 / (d2 - d6)
        assign((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - v, zero, v)
        v = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        assign((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), zero, 1 - v, v)
        denom = 1.0 / (va + vb + vc)
        v, ww = vb * denom, vc * denom
        assign(np.ones(T, dtype=bool), 1 - v - ww, v, ww)
    q = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    return q, w


def find_contacts(x: np.ndarray, triangles: np.ndarray, centre: np.ndarray, radius: float,
                  subdivision: int = 1) -> Contacts:
    """Surface sub-triangles penetrated by the sphere (centre, radius) (compiled kernel).

    Args:
        x: (N, 3) current node positions, m, phantom frame.
        triangles: (T, 3) outward-oriented surface triangles.
        centre: (3,) sphere centre, m, phantom frame.
        radius: sphere radius, m.
        subdivision: sub-triangles per triangle edge (see the module docstring).

    Returns:
        The :class:`Contacts` (possibly empty). The normal is the direction from the
        centre to the closest point, or the inward face normal once the centre has
        passed behind the face plane with its closest point inside the face (with the
        closest point on an edge or a corner, the face plane can pass over a centre that
        is still outside the surface: a curved or dented surface's neighbour, whose
        plane-based depth of ~ one radius gave the dome's replay one-step force impacts of
        ten times the press force).

    Raises:
        ValueError: subdivision < 1.
    """
    from core.simulation.kernels import sphere_contacts

    sub = contact_corners(subdivision)
    idx, sid, w, n, d, area, ws = sphere_contacts(x, triangles, sub, np.asarray(centre, dtype=np.float64),
                                                  float(radius))
    return Contacts(triangles=idx, nodes=triangles[idx], weights=w, normals=n, depth=d, area=area, sub=sid,
                    sub_weights=ws)


_CORNERS: dict[int, np.ndarray] = {}


def contact_corners(n: int) -> np.ndarray:
    """The cached (n^2, 3, 3) :func:`core.simulation.kernels.subdivision_corners` of the
    contact surface (the compiled stepper's ``sub`` argument; do not modify)."""
    from core.simulation.kernels import subdivision_corners

    if n not in _CORNERS:
        _CORNERS[n] = subdivision_corners(n)
    return _CORNERS[n]


def find_contacts_reference(x: np.ndarray, triangles: np.ndarray, centre: np.ndarray, radius: float,
                            subdivision: int = 1) -> Contacts:
    """Vectorised numpy version of :func:`find_contacts`, the reference for tests."""
    sub = contact_corners(subdivision)
    ns = sub.shape[0]
    T = triangles.shape[0]
    P = x[triangles]  # (T, 3 vertices, 3)
    C = np.einsum("sij,tjd->tsid", sub, P).reshape(T * ns, 3, 3)  # sub-triangle corners
    parent = np.repeat(np.arange(T), ns)
    sid = np.tile(np.arange(ns), T)
    a, b, c = C[:, 0], C[:, 1], C[:, 2]
    empty = Contacts(
        np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
        np.zeros(0, np.int64), np.zeros((0, 3)),
    )
    q, ws = closest_points_on_triangles(centre, a, b, c)
    d = q - centre
    dist = np.sqrt((d * d).sum(1))
    inside = dist < radius
    if not np.any(inside):
        return empty
    a, b, c, q, ws, d, dist = a[inside], b[inside], c[inside], q[inside], ws[inside], d[inside], dist[inside]
    parent, sid = parent[inside], sid[inside]
    face_n = np.cross(b - a, c - a)
    area2 = np.sqrt((face_n * face_n).sum(1))
    face_n /= area2[:, None]
    normals = d / np.maximum(dist, 1e-12)[:, None]
    # If the centre went behind the face plane, its closest point inside the face, the
    # direction (q - c) flips: push inwards instead (on an edge or a corner, see the kernel).
    behind = (np.einsum("ij,ij->i", centre - q, face_n) < 0.0) & np.all(ws > 0.0, axis=1)
    normals[behind] = -face_n[behind]
    depth = np.where(behind, radius + dist, radius - dist)
    w = np.einsum("ki,kij->kj", ws, sub[sid])
    return Contacts(
        triangles=parent, nodes=triangles[parent], weights=w, normals=normals, depth=depth, area=0.5 * area2,
        sub=sid, sub_weights=ws,
    )
