"""Robot calibration from touches of named landmarks of any phantom shape.

* :func:`landmark_normals` -- outward unit normals of a watertight rest surface at (near)
  given points, with the angle-weighted pseudo-normal on edges and vertices (Thürmer &
  Wüthrich 1998, J. Graphics Tools 3(1):43; Bærentzen & Aanæs 2005, IEEE TVCG 11(3):243).
* :func:`landmark_points_phantom` -- the phantom-frame probe-sphere centre of each touch.
* :func:`calibrate_robot_landmarks` -- ``T_phantom_robot`` by a rigid Kabsch fit (Kabsch
  1976) of the touches (``calibration/landmarks.csv``) to those centres, the landmark
  counterpart of :func:`core.registration.rigid.calibrate_robot` (Wu et al. 2020,
  Sec. 3.2, which touches the four top corners of a box).

A touch of landmark ``L`` puts the probe sphere outside the phantom, touching it at ``L``
along the outward surface normal ``n_L`` there (``SESSION_FORMAT.md``), so the sphere's
centre is at ``L + probe_radius * n_L`` in the phantom frame.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import RegistrationError
from core.io.checks import collinear
from core.registration.rigid import RigidFit, register_touches

__all__ = ["landmark_normals", "landmark_points_phantom", "calibrate_robot_landmarks"]


def _as_points(name: str, a: Any) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or infinite values")
    return a


def landmark_normals(surface: Any, points: np.ndarray, *, tol: float = 1e-6) -> np.ndarray:
    """Outward unit surface normal of a watertight mesh at (near) each point.

    For each point the nearest point ``c`` of the surface is found (exhaustively, over
    every triangle with ``trimesh.triangles.closest_point``, O(N F): ``trimesh.proximity``
    would need the optional ``rtree`` package, which is not a dependency). The normal is the mean of the normals of the
    triangles within ``tol`` of ``c``, each weighted by the angle it subtends at ``c``:
    ``2 pi`` inside a triangle (so a face point gets its face normal), ``pi`` on an edge
    (the two faces' mean) and the triangle's interior angle at a vertex: the
    angle-weighted pseudo-normal (Thürmer & Wüthrich 1998; Bærentzen & Aanæs 2005). It
    does not depend on how a flat face is split into triangles, so a box corner gets its
    diagonal ``(+-1, +-1, +-1) / sqrt(3)`` and a box edge ``(+-1, +-1, 0) / sqrt(2)``
    (signs outward) for any box size.

    Args:
        surface: a watertight ``trimesh.Trimesh`` or the path of a mesh file (e.g.
            ``phantom.stl``), m, in the frame of ``points`` (normally the phantom frame).
        points: (N, 3) float, m, on or near the surface.
        tol: distance (m) within which a triangle counts as touching ``c`` (and ``c``
            as lying on a triangle's edge or vertex).

    Returns:
        (N, 3) float64 unit outward normals, in the surface's frame. Outward is taken
        from the sign of the mesh volume, so an inside-out (inverted) mesh gives the
        same normals as the corrected one.

    Raises:
        ValueError: points not a finite (N, 3) array, ``tol`` not positive, a surface
            that is not watertight or has no faces, or a normal that cancels out.
    """
    import trimesh  # noqa: PLC0415 (heavy, only needed here)

    pts = _as_points("points", points)
    if not tol > 0:
        raise ValueError(f"tol must be > 0 m, got {tol}")
    if isinstance(surface, (str, os.PathLike)):
        mesh = trimesh.load_mesh(str(Path(surface)))
    else:
        mesh = surface
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"surface must be a mesh with faces, got {type(mesh).__name__}")
    if not mesh.is_watertight:
        raise ValueError("surface must be watertight (closed) for its outward normal to be defined")
    sign = 1.0 if mesh.volume >= 0 else -1.0
    face_normals = np.asarray(mesh.face_normals, dtype=np.float64)  # (F, 3)
    # trimesh's closest_point compares areas with absolute tolerances that fail for
    # sub-millimetre triangles in metres: search in units of the mesh's size instead.
    unit = float(mesh.scale)
    origin = np.asarray(mesh.bounds[0], dtype=np.float64)
    tri = (np.asarray(mesh.triangles, dtype=np.float64) - origin) / unit  # (F, 3, 3)
    tol_u = tol / unit
    out = np.empty_like(pts)
    for k, p in enumerate(pts):
        pu = (p - origin) / unit
        cp = trimesh.triangles.closest_point(tri, np.tile(pu, (len(tri), 1)))
        d = np.linalg.norm(cp - pu, axis=1)
        c = cp[int(np.argmin(d))]
        # Every triangle within tol of c is within min(d) + tol of p (triangle inequality).
        cand = np.flatnonzero(d <= d.min() + tol_u)
        dc = np.linalg.norm(trimesh.triangles.closest_point(tri[cand], np.tile(c, (len(cand), 1))) - c,
                            axis=1)
        near = cand[dc < tol_u]
        n = np.zeros(3)
        for f in near:
            n += _angle_at(tri[f], c, tol_u) * face_normals[f]
        norm = np.linalg.norm(n)
        if not norm > 0:
            raise ValueError(f"the normal at point {k} ({p.tolist()}) cancels out: "
                             f"{len(near)} faces meet there with opposite normals")
        out[k] = sign * n / norm
    return out


def _angle_at(triangle: np.ndarray, c: np.ndarray, tol: float) -> float:
    """Angle (rad) the (3, 3) ``triangle`` subtends at its point ``c``: its interior
    angle at a vertex, pi on an edge, 2 pi inside."""
    for i in range(3):
        if np.linalg.norm(triangle[i] - c) < tol:
            e1 = triangle[(i + 1) % 3] - triangle[i]
            e2 = triangle[(i + 2) % 3] - triangle[i]
            cos = np.dot(e1, e2) / max(np.linalg.norm(e1) * np.linalg.norm(e2), 1e-300)
            return float(np.arccos(np.clip(cos, -1.0, 1.0)))
    for i in range(3):
        a, b = triangle[i], triangle[(i + 1) % 3]
        ab = b - a
        s = np.clip(np.dot(c - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
        if np.linalg.norm(a + s * ab - c) < tol:
            return float(np.pi)
    return float(2.0 * np.pi)


def landmark_points_phantom(
    labels: Sequence[str],
    landmarks_phantom: Mapping[str, Any],
    normals_phantom: Mapping[str, Any],
    probe_radius: float,
) -> np.ndarray:
    """Phantom-frame probe-sphere centres for landmark touches.

    Args:
        labels: landmark name of each touch (repeats allowed).
        landmarks_phantom: name -> (3,) landmark point, m, phantom frame
            (``SessionMeta.landmarks``).
        normals_phantom: name -> (3,) outward surface normal at the landmark, phantom
            frame (normalised here), e.g. from :func:`landmark_normals`.
        probe_radius: probe sphere radius, m.

    Returns:
        (K, 3) float64, m, phantom frame: ``L + probe_radius * n_L`` per touch.

    Raises:
        ValueError: a label without a landmark or a normal; a landmark or normal that is
            not a finite (3,) vector, or a zero normal.
    """
    out = np.empty((len(labels), 3))
    for k, label in enumerate(labels):
        if label not in landmarks_phantom or label not in normals_phantom:
            raise ValueError(
                f"unknown landmark {label!r}: landmarks {sorted(landmarks_phantom)}, "
                f"normals {sorted(normals_phantom)}"
            )
        p = np.asarray(landmarks_phantom[label], dtype=np.float64)
        n = np.asarray(normals_phantom[label], dtype=np.float64)
        if p.shape != (3,) or n.shape != (3,) or not (np.isfinite(p).all() and np.isfinite(n).all()):
            raise ValueError(f"landmark {label!r} and its normal must be finite (3,) vectors, "
                             f"got {p.tolist()} and {n.tolist()}")
        nn = np.linalg.norm(n)
        if not nn > 0:
            raise ValueError(f"the normal of landmark {label!r} is zero")
        out[k] = p + float(probe_radius) * n / nn
    return out


def calibrate_robot_landmarks(
    touches_robot,
    landmarks_phantom: Mapping[str, Any],
    normals_phantom: Mapping[str, Any],
    probe_radius: float,
    *,
    max_rms: float = 0.0015,
) -> RigidFit:
    """Estimate ``T_phantom_robot`` from probe touches of named landmarks.

    Every touch (repeats included) is paired with its phantom-frame sphere centre
    ``L + probe_radius * n_L`` (:func:`landmark_points_phantom`) and a rigid,
    reflection-safe Kabsch fit is solved (Kabsch 1976;
    :func:`core.registration.rigid.kabsch`).

    Relation to the corner path: ``corners.csv`` touches a box's top corners with the
    sphere's lowest point, so :func:`core.registration.rigid.corner_points_phantom` (and
    ``core.io.Corners.phantom_points``) put the centre at the corner plus
    ``(0, 0, probe_radius)``: along the top face's normal ``+z``. The same four corners
    as landmarks with normals from :func:`landmark_normals` get the corner's diagonal
    ``(+-1, +-1, 1) / sqrt(3)`` instead, a different centre (by ``0.82 probe_radius``
    horizontally and ``0.42 probe_radius`` vertically) for a different, equally valid
    way of touching. Passing ``(0, 0, 1)`` as every corner's normal reproduces
    :func:`core.registration.rigid.calibrate_robot` exactly.

    Args:
        touches_robot: a ``core.io.LandmarkTouches`` (``.labels`` tuple of str,
            ``.positions`` (K, 3) robot frame, m), or a pair ``(labels, positions)``.
        landmarks_phantom: name -> (3,) landmark point, m, phantom frame
            (``SessionMeta.landmarks``).
        normals_phantom: name -> (3,) outward unit surface normal at the landmark,
            phantom frame (e.g. :func:`landmark_normals` of the rest surface).
        probe_radius: probe sphere radius, m.
        max_rms: largest accepted rms residual, m (default 1.5 mm, as for corners).

    Returns:
        :class:`RigidFit` with ``T = T_phantom_robot`` (4, 4); residuals (K,) float64, m,
        per touch row.

    Raises:
        RegistrationError: fewer than three distinct landmarks touched, the touched
            landmarks are collinear (``core.io.checks.collinear``), the fit is
            degenerate, or rms > ``max_rms`` (the message gives the rms in mm and the
            worst landmark).
        ValueError: malformed positions, a label without a landmark or a normal.
    """
    if hasattr(touches_robot, "labels") and hasattr(touches_robot, "positions"):
        labels, positions = touches_robot.labels, touches_robot.positions
    else:
        labels, positions = touches_robot
    labels = tuple(str(s) for s in labels)
    positions = _as_points("landmark touch positions", positions)
    if len(labels) != positions.shape[0]:
        raise ValueError(f"{len(labels)} landmark labels for {positions.shape[0]} positions")
    target = landmark_points_phantom(labels, landmarks_phantom, normals_phantom, probe_radius)
    distinct = sorted(set(labels))
    if len(distinct) < 3:
        raise RegistrationError(
            f"need touches of at least 3 distinct landmarks, got {distinct}", fitness=None, rms=None
        )
    points = np.stack([np.asarray(landmarks_phantom[n], dtype=np.float64) for n in distinct])
    if collinear(points):
        raise RegistrationError(
            f"landmarks {distinct} are collinear: their touches cannot fix the rotation about "
            "their line; touch at least 3 non-collinear landmarks"
        )
    return register_touches(positions, target, labels, what="landmark",
                            check="landmark labels, positions, normals and probe radius", max_rms=max_rms)
