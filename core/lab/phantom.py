"""The virtual lab's phantom: the paper's gel box, or a surface (dome, kidney-like, STL).

This module holds the phantom's physical constants (:data:`PHANTOM_SIZE`,
:data:`PHANTOM_MASS`, :data:`PHANTOM_DENSITY`), :class:`Phantom` (shape, bounding box,
mass, and for a surface its triangles, STL and calibration landmarks) and
:func:`make_phantom`, which builds it from ``generate_session(shape=..., phantom_stl=...)``.
Frame: the phantom frame (``[0, size]``, z up, resting on z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.lab.config import LabError

__all__ = ["PHANTOM_SIZE", "PHANTOM_MASS", "PHANTOM_DENSITY", "Phantom", "make_phantom"]

PHANTOM_SIZE = (0.0687, 0.0393, 0.0358)
"""Box size of the paper's phantom, m (x length, y width, z height; Wu et al. 2020, Sec. 4.1)."""
PHANTOM_MASS = 0.10401
"""Phantom mass, kg (104.01 g)."""
PHANTOM_DENSITY = PHANTOM_MASS / float(np.prod(PHANTOM_SIZE))
"""Density of the paper's gel, kg/m^3 (104.01 g in its box): the mass of other shapes."""


@dataclass
class Phantom:
    """The lab's phantom: the paper's box, or a surface (dome, kidney-like, a given STL).

    Attributes (phantom frame, metres, kilograms):
        shape: "box", "dome", "kidney" or "stl".
        size: (3,) float64 upper corner of the bounding box (its lower corner is 0 in x
            and y; the box's is 0 in z too), m.
        mass: kg (the box: :data:`PHANTOM_MASS`; a surface: :data:`PHANTOM_DENSITY`
            times its volume).
        surface: (V (N, 3) float64 m, F (M, 3) int64) triangles of a surface; None for the box.
        stl_path: the surface written as an STL (in the lab's temporary folder); None for the box.
        landmarks: named calibration landmarks ``{name: [x, y, z] m}`` of a surface; None for the box.
        normals: (5, 3) float64 outward unit normals at ``landmarks`` (same order); None for the box.
    """

    shape: str
    size: np.ndarray
    mass: float
    surface: tuple[np.ndarray, np.ndarray] | None = None
    stl_path: Path | None = None
    landmarks: dict | None = None
    normals: np.ndarray | None = None


def _landmarks_of(V: np.ndarray, F: np.ndarray) -> tuple[dict, np.ndarray]:
    """Named calibration landmarks of a surface: its highest point ("apex") and the
    points furthest along (+-1, 0, 1) and (0, +-1, 1) ("x+", "x-", "y+", "y-"), each a
    vertex of the surface, with their outward normals (for the touching probe centre)."""
    from core.registration import landmark_normals

    import trimesh

    surface = trimesh.Trimesh(V, F, process=False)
    names = {"apex": (0.0, 0.0, 1.0), "x+": (1.0, 0.0, 1.0), "x-": (-1.0, 0.0, 1.0),
             "y+": (0.0, 1.0, 1.0), "y-": (0.0, -1.0, 1.0)}
    centre = V.mean(axis=0)
    points = {}
    for name, d in names.items():
        d = np.asarray(d) / np.linalg.norm(d)
        points[name] = V[int(np.argmax((V - centre) @ d))]
    P = np.array(list(points.values()))
    return {k: v.tolist() for k, v in points.items()}, landmark_normals(surface, P)


def make_phantom(shape: str, phantom_stl, workdir: Path) -> Phantom:
    """The phantom of ``generate_session(shape=..., phantom_stl=...)``; an STL goes to
    ``workdir/phantom.stl`` (x and y shifted so its bounding box starts at 0).

    Args:
        shape: "box" (the paper's block, no STL), "dome" or "kidney"
            (:mod:`core.lab.shapes`); ignored when ``phantom_stl`` is given.
        phantom_stl: None, or the path of a watertight STL (metres, z up, resting on z = 0).
        workdir: an existing folder that receives ``phantom.stl`` for a surface.

    Returns:
        the :class:`Phantom` (phantom frame).

    Raises:
        LabError: an unknown shape, or an STL that fails
            :func:`core.simulation.meshing.check_stl`.
    """
    from core.errors import MeshingError

    from core.lab.shapes import SHAPES, shape_surface

    if phantom_stl is None and shape == "box":
        return Phantom("box", np.asarray(PHANTOM_SIZE, dtype=np.float64), PHANTOM_MASS)
    import trimesh

    if phantom_stl is not None:
        from core.simulation.meshing import check_stl

        try:
            surf = check_stl(phantom_stl)
        except MeshingError as exc:
            raise LabError(str(exc)) from exc
        V, F = np.asarray(surf.vertices, dtype=np.float64), np.asarray(surf.faces, dtype=np.int64)
        V[:, :2] -= V[:, :2].min(axis=0)
        shape = "stl"
    elif shape in SHAPES:
        V, F = shape_surface(shape)
    else:
        raise LabError(f"unknown phantom shape {shape!r}: one of {', '.join(SHAPES)} (or give phantom_stl)")
    mesh = trimesh.Trimesh(V, F, process=False)
    path = workdir / "phantom.stl"
    mesh.export(str(path))
    landmarks, normals = _landmarks_of(V, F)
    return Phantom(shape, np.asarray(mesh.bounds[1], dtype=np.float64), PHANTOM_DENSITY * float(mesh.volume),
                    (V, F), path, landmarks, normals)

