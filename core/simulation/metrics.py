"""The paper's error figure: measured points to the 3x super-sampled simulated mesh.

Wu et al. 2020 (Sec. 3.3, Tables 1-3) super-sample the node grid by a factor of 3 in
every direction with linear interpolation and report the mean distance from each
point of the cleaned depth cloud to its nearest super-sampled vertex (camera -> mesh
only: the instrument occludes parts of the phantom, so the other direction has no
correspondences). We keep the super-sampled vertices on the boundary of the grid:
interior vertices are never observed, and letting a measured point match one would
hide a mesh that is too shallow.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from core.errors import SimulationError

__all__ = ["supersample_grid", "supersampled_surface", "surface_mask", "point_to_mesh_distances"]


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


def supersampled_surface(positions: np.ndarray, grid: tuple[int, int, int], factor: int = 3) -> np.ndarray:
    """(P, 3) boundary vertices of the super-sampled grid for one frame's (N, 3) positions."""
    g = supersample_grid(positions, grid, factor)
    return g.reshape(-1, 3)[surface_mask(g.shape[:3])]


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
