"""Tetrahedral meshes of the phantom.

The paper (Wu et al. 2020, Sec. 4.2) meshes the 68.7 x 39.3 x 35.8 mm block as a
13 x 5 x 5 grid of nodes. We split every hexahedral cell of such a grid into six
tetrahedra around its main diagonal (Kuhn / Freudenthal split), which is conforming
across cells without alternating patterns.

Node numbering is grid-major: node ``(i, j, k)`` (i along x, j along y, k along z)
has index ``(i * ny + j) * nz + k``, so ``positions.reshape(nx, ny, nz, 3)`` gives the
node grid that the learned correction (Wu et al. 2020, Sec. 3.3) convolves over.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from itertools import permutations

import numpy as np

from core.errors import SimulationError

__all__ = ["TetMesh", "box_mesh"]


@dataclass(frozen=True)
class TetMesh:
    """An immutable tetrahedral mesh in the phantom frame.

    Attributes:
        nodes: (N, 3) float64, rest positions in metres, phantom frame.
        tets: (E, 4) int64 node indices, positively oriented (det > 0).
        surface_triangles: (T, 3) int64 boundary faces, counter-clockwise seen from
            outside (normals point out of the body).
        grid: (nx, ny, nz) node counts for grid meshes, or None for unstructured meshes.
        size: (3,) float64 box size in metres (x length, y width, z height).
    """

    nodes: np.ndarray
    tets: np.ndarray
    surface_triangles: np.ndarray
    grid: tuple[int, int, int] | None
    size: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @cached_property
    def elements(self):
        """The mesh's :class:`core.simulation.fem.ElementData` (shape-function gradients,
        volumes, the operator G), built once per mesh.

        Raises:
            SimulationError: degenerate or inverted tetrahedra."""
        from core.simulation.fem import build_elements

        return build_elements(self.nodes, self.tets)

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    @property
    def surface_nodes(self) -> np.ndarray:
        """(S,) int64 sorted indices of nodes on the boundary."""
        return np.unique(self.surface_triangles)

    def bottom_nodes(self, tol: float = 1e-9) -> np.ndarray:
        """(B,) int64 indices of nodes on the z = 0 face (held by ``fixed: bottom``)."""
        return np.flatnonzero(self.nodes[:, 2] <= tol)

    def top_nodes(self) -> np.ndarray:
        """(nx*ny,) int64 indices of the top layer (k = nz-1), in (i, j) grid order.

        Raises:
            SimulationError: for meshes that are not grids.
        """
        if self.grid is None:
            raise SimulationError("top_nodes() needs a grid mesh")
        nx, ny, nz = self.grid
        return np.arange(nx * ny * nz).reshape(nx, ny, nz)[:, :, -1].ravel()


def box_mesh(size, grid=(13, 5, 5)) -> TetMesh:
    """Mesh the box ``[0, sx] x [0, sy] x [0, sz]`` with a grid of nodes.

    Args:
        size: (3,) box size in metres, phantom frame (x length, y width, z height).
        grid: (nx, ny, nz) number of nodes along each axis, each >= 2. The paper's
            mesh is (13, 5, 5).

    Returns:
        A :class:`TetMesh` with ``6 * (nx-1) * (ny-1) * (nz-1)`` tetrahedra.

    Raises:
        SimulationError: if the size is not positive or the grid is smaller than 2.
    """
    size = np.asarray(size, dtype=np.float64).reshape(-1)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise SimulationError(f"box size must be 3 positive lengths in m, got {size}")
    grid = tuple(int(g) for g in grid)
    if len(grid) != 3 or min(grid) < 2:
        raise SimulationError(f"grid must be 3 node counts >= 2, got {grid}")
    return _box_mesh(tuple(float(v) for v in size), grid)


@lru_cache(maxsize=16)
def _box_mesh(size: tuple[float, float, float], grid: tuple[int, int, int]) -> TetMesh:
    """:func:`box_mesh`, built once per (size, grid) in a process (fits and diagnoses
    build hundreds of models on the same mesh); its arrays are read-only."""
    size = np.asarray(size, dtype=np.float64)
    nx, ny, nz = grid
    xs, ys, zs = (np.linspace(0.0, s, n) for s, n in zip(size, grid))
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    index = np.arange(nx * ny * nz).reshape(nx, ny, nz)

    # Kuhn split: for each permutation (a, b, c) of the axes, the tet
    # v000, v000+e_a, v000+e_a+e_b, v111.
    base = index[:-1, :-1, :-1].ravel()
    step = np.array([ny * nz, nz, 1])
    tets = []
    for perm in permutations(range(3)):
        o1 = step[perm[0]]
        o2 = o1 + step[perm[1]]
        o3 = step.sum()
        tets.append(np.stack([base, base + o1, base + o2, base + o3], axis=1))
    tets = np.concatenate(tets, axis=0).astype(np.int64)
    tets = _orient_positive(nodes, tets)
    tris = _boundary_triangles(nodes, tets)
    for a in (nodes, tets, tris, size):
        a.flags.writeable = False
    return TetMesh(nodes=nodes, tets=tets, surface_triangles=tris, grid=grid, size=size)


def _orient_positive(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    d = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    det = np.linalg.det(d.transpose(0, 2, 1))
    tets = tets.copy()
    flip = det < 0
    tets[flip, 1], tets[flip, 2] = tets[flip, 2].copy(), tets[flip, 1].copy()
    return tets


def _boundary_triangles(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Faces that belong to exactly one tet, oriented away from that tet's 4th node."""
    faces = np.concatenate(
        [tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]], axis=0
    )
    opposite = np.concatenate([tets[:, 0], tets[:, 1], tets[:, 2], tets[:, 3]])
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    faces, opposite = faces[once], opposite[once]
    p0, p1, p2 = (nodes[faces[:, i]] for i in range(3))
    normal = np.cross(p1 - p0, p2 - p0)
    inward = np.einsum("ij,ij->i", normal, nodes[opposite] - p0) > 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return faces.astype(np.int64)
