"""The mesh of a replay run, read back from its ``<sequence>.npz``: shared by the viewer
(:mod:`app.viewer.data`) and the export (:mod:`app.export.run`).

:func:`core.simulation.replay.write_replay` stores ``surface_triangles`` (T, 3) always and,
for a phantom given by ``phantom.stl`` (a Gmsh mesh, ``TetMesh.grid is None``), also
``rest_nodes`` (N, 3) m and ``tets`` (E, 4); a box run is rebuilt from its ``grid``
(:func:`core.simulation.mesh.box_mesh`), as before STL phantoms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.errors import TissueTwinError

__all__ = ["npz_mesh", "mesh_summary", "mesh_label"]


def npz_mesh(arrays, where: str | Path = "npz"):
    """The unstructured mesh stored in a replay's npz, or None for a box-grid run.

    Args:
        arrays: an opened ``np.load`` of ``<sequence>.npz`` (or a dict of its arrays).
        where: the file, for error messages.

    Returns:
        a read-only :class:`core.simulation.mesh.TetMesh` with ``grid=None`` and ``size``
        the rest nodes' extents (as :func:`core.simulation.meshing.tetrahedralise`
        sets it), or None when the npz holds no ``rest_nodes`` (a box grid).

    Raises:
        TissueTwinError: ``rest_nodes`` without ``tets`` or ``surface_triangles``, or
            arrays of the wrong shape or out-of-range node indices.
    """
    from core.simulation.mesh import TetMesh

    files = set(getattr(arrays, "files", None) or arrays.keys())
    if "rest_nodes" not in files:
        return None
    missing = [k for k in ("tets", "surface_triangles") if k not in files]
    if missing:
        raise TissueTwinError(f"{where}: has rest_nodes but not {missing}: not an npz of `tissuetwin replay`")
    nodes = np.array(arrays["rest_nodes"], dtype=np.float64)
    tets = np.array(arrays["tets"], dtype=np.int64)
    tris = np.array(arrays["surface_triangles"], dtype=np.int64)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] != 4 or tris.ndim != 2 \
            or tris.shape[1] != 3 or tets.size == 0:
        raise TissueTwinError(f"{where}: rest_nodes {nodes.shape}, tets {tets.shape} and surface_triangles "
                              f"{tris.shape}; expected (N, 3), (E, 4) and (T, 3)")
    if min(tets.min(), tris.min()) < 0 or max(tets.max(), tris.max()) >= nodes.shape[0]:
        raise TissueTwinError(f"{where}: tets or surface_triangles name nodes outside 0..{nodes.shape[0] - 1}")
    size = nodes.max(axis=0) - np.minimum(nodes.min(axis=0), 0.0)
    for a in (nodes, tets, tris, size):
        a.flags.writeable = False
    return TetMesh(nodes=nodes, tets=tets, surface_triangles=tris, grid=None, size=size)


def mesh_summary(mesh) -> dict:
    """JSON of a mesh for the dashboard and the viewer's state: ``kind`` ("box" for a
    grid, "stl" otherwise), ``grid`` ([nx, ny, nz] or None), ``nodes`` and ``tets``."""
    grid = None if mesh.grid is None else [int(g) for g in mesh.grid]
    return {"kind": "box" if grid is not None else "stl", "grid": grid, "nodes": int(mesh.n_nodes),
            "tets": int(mesh.n_tets)}


def mesh_label(mesh) -> str:
    """``"13x5x5 grid"`` for a box, ``"STL mesh"`` otherwise (node and tet counts are
    printed beside it by the callers)."""
    return "STL mesh" if mesh.grid is None else f"{'x'.join(map(str, mesh.grid))} grid"
