"""The paper's error figure: measured points to the 3x super-sampled simulated mesh.

Wu et al. 2020 (Sec. 3.3, Tables 1-3) super-sample the node grid by a factor of 3 in
every direction with linear interpolation and report the mean distance from each
point of the cleaned depth cloud to its nearest super-sampled vertex (camera -> mesh
only: the instrument occludes parts of the phantom, so the other direction has no
correspondences). We keep the super-sampled vertices on the boundary of the grid:
interior vertices are never observed, and letting a measured point match one would
hide a mesh that is too shallow.

On a mesh that is not a grid (an STL phantom filled by Gmsh) the same figure
super-samples each surface triangle ``factor`` times per edge (its vertices at
barycentric coordinates ``(i, j, k) / factor``, shared along edges); on the box grid
the grid's own trilinear super-sampling is used, so the box keeps the paper's metric
exactly (at rest the two give the same vertices; deformed, the grid's is bilinear over
each face quad).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

import scipy.sparse as sp

from core.errors import SimulationError

__all__ = ["supersample_grid", "supersampled_surface", "surface_mask", "surface_operator",
           "point_to_mesh_distances"]


def _upsample_axis(arr: np.ndarray, axis: int, factor: int) -> np.ndarray:
    n = arr.shape[axis]
    u = np.linspace(0.0, n - 1.0, factor * (n - 1) + 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), n - 2)
    w = (u - i0).reshape([-1 if d == axis else 1 for d in range(arr.ndim)])
    return np.take(arr, i0, axis=axis) * (1.0 - w) + np.take(arr, i0 + 1, axis=axis) * w


def supersample_grid(positions: np.ndarray, grid: tuple[int, int, int], factor: int = 3) -> np.ndarray:
    """Trilinear super-sampling of node-grid positions.

    Args:
        positions: (..., N, 3) node positions (grid-major node order, see
            :mod:`core.simulation.mesh`), m.
        grid: (nx, ny, nz) with nx*ny*nz == N.
        factor: sub-divisions per cell edge (the paper uses 3).

    Returns:
        (..., factor*(nx-1)+1, factor*(ny-1)+1, factor*(nz-1)+1, 3) positions, m.

    Raises:
        SimulationError: if the shapes do not match the grid.
    """
    nx, ny, nz = grid
    if positions.shape[-2:] != (nx * ny * nz, 3):
        raise SimulationError(f"positions must be (..., {nx * ny * nz}, 3) for grid {grid}, got {positions.shape}")
    lead = positions.shape[:-2]
    g = positions.reshape(*lead, nx, ny, nz, 3)
    k = len(lead)
    for axis in range(3):
        g = _upsample_axis(g, k + axis, factor)
    return g


def surface_mask(shape: tuple[int, int, int]) -> np.ndarray:
    """(nx*ny*nz,) bool, True for vertices on the boundary of a grid of that shape."""
    m = np.zeros(shape, dtype=bool)
    m[0], m[-1], m[:, 0], m[:, -1], m[:, :, 0], m[:, :, -1] = True, True, True, True, True, True
    return m.ravel()


def _grid_of(mesh_or_grid):
    """(grid tuple or None, TetMesh or None) of a grid tuple or a TetMesh."""
    if isinstance(mesh_or_grid, (tuple, list, np.ndarray)):
        return tuple(int(g) for g in mesh_or_grid), None
    return mesh_or_grid.grid, mesh_or_grid


def _interp_matrix(n: int, factor: int) -> np.ndarray:
    u = np.linspace(0.0, n - 1.0, factor * (n - 1) + 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), n - 2)
    w = u - i0
    W = np.zeros((u.size, n))
    W[np.arange(u.size), i0] = 1.0 - w
    W[np.arange(u.size), i0 + 1] += w
    return W


def _triangle_operator(n_nodes: int, triangles: np.ndarray, factor: int) -> sp.csr_matrix:
    """(P, N) barycentric super-sampling of surface triangles, each shared point once.

    Every point is keyed by its (node, weight) pairs sorted by node (vertices and edge
    points are shared by the triangles around them); ``np.unique`` over the keys numbers
    the points."""
    tris = np.asarray(triangles, dtype=np.int64)
    bary = np.array([(i, j, factor - i - j) for i in range(factor + 1) for j in range(factor + 1 - i)], dtype=np.int64)
    T, K = tris.shape[0], bary.shape[0]
    nodes = np.broadcast_to(tris[:, None, :], (T, K, 3)).reshape(-1, 3)
    weights = np.broadcast_to(bary[None, :, :], (T, K, 3)).reshape(-1, 3)
    nodes = np.where(weights > 0, nodes, -1)  # a zero weight does not tie a point to a node
    order = np.argsort(nodes, axis=1, kind="stable")
    nodes = np.take_along_axis(nodes, order, axis=1)
    weights = np.take_along_axis(weights, order, axis=1)
    keys = np.concatenate([nodes, weights], axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    first.sort()  # number the points in order of first appearance (as a scan of the triangles would)
    keys = keys[first]
    rows = np.repeat(np.arange(keys.shape[0]), 3)
    cols, vals = keys[:, :3].ravel(), keys[:, 3:].ravel() / factor
    keep = cols >= 0
    return sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(keys.shape[0], n_nodes))


def surface_operator(mesh_or_grid, factor: int = 3) -> sp.csr_matrix:
    """(P, N) sparse matrix ``S`` with ``S @ positions`` the super-sampled surface
    vertices of one frame's (N, 3) node positions (the paper's metric's mesh points).

    Args:
        mesh_or_grid: a :class:`core.simulation.mesh.TetMesh`, or a grid (nx, ny, nz).
            Grids (and grid meshes) super-sample trilinearly and keep the boundary
            vertices, in the order of :func:`supersampled_surface`; other meshes
            super-sample their surface triangles (module docstring).
        factor: sub-divisions per edge (paper: 3), >= 1.

    Raises:
        SimulationError: factor < 1 or a grid smaller than 2 along an axis.
    """
    factor = int(factor)
    if factor < 1:
        raise SimulationError(f"factor must be >= 1, got {factor}")
    grid, mesh = _grid_of(mesh_or_grid)
    if grid is not None:
        if len(grid) != 3 or min(grid) < 2:
            raise SimulationError(f"grid must be 3 node counts >= 2, got {grid}")
        Wx, Wy, Wz = (sp.csr_matrix(_interp_matrix(n, factor)) for n in grid)
        S = sp.kron(Wx, sp.kron(Wy, Wz, format="csr"), format="csr")
        shape = (Wx.shape[0], Wy.shape[0], Wz.shape[0])
        return S[surface_mask(shape)]
    cache = mesh.__dict__.setdefault("_surface_operators", {})
    if factor not in cache:
        cache[factor] = _triangle_operator(mesh.n_nodes, mesh.surface_triangles, factor)
    return cache[factor]


def supersampled_surface(positions: np.ndarray, mesh_or_grid, factor: int = 3) -> np.ndarray:
    """(P, 3) super-sampled surface vertices for one frame's (N, 3) positions.

    ``mesh_or_grid`` is a grid (nx, ny, nz) or a :class:`core.simulation.mesh.TetMesh`
    (see :func:`surface_operator`)."""
    grid, mesh = _grid_of(mesh_or_grid)
    if grid is not None:
        g = supersample_grid(positions, grid, factor)
        return g.reshape(-1, 3)[surface_mask(g.shape[:3])]
    if positions.shape != (mesh.n_nodes, 3):
        raise SimulationError(f"positions must be ({mesh.n_nodes}, 3) for this mesh, got {positions.shape}")
    return surface_operator(mesh, factor) @ positions


def point_to_mesh_distances(points: np.ndarray, mesh_points: np.ndarray) -> np.ndarray:
    """Distance (m) from each measured point (M, 3) to the nearest mesh vertex (P, 3).

    Uses a KD-tree (scipy.spatial.cKDTree). Returns (M,) float64.
    """
    if points.ndim != 2 or points.shape[1] != 3 or mesh_points.ndim != 2 or mesh_points.shape[1] != 3:
        raise SimulationError(f"points must be (M, 3) and (P, 3), got {points.shape} and {mesh_points.shape}")
    if points.shape[0] == 0:
        return np.zeros(0)
    d, _ = cKDTree(mesh_points).query(points, k=1)
    return d
