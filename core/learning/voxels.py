"""The learned correction on any mesh: a mesh-to-voxel map around the phantom.

The networks of Wu et al. 2020 (Sec. 3.3, Fig. 3) convolve over the 13 x 5 x 5 node grid
of their box, and the paper's outlook (Sec. 6) notes that "any mesh can be interpolated
to fit a regular grid". :func:`voxel_map` does that for a :class:`TetMesh` with
``grid is None`` (a ``phantom.stl`` filled by Gmsh, :mod:`core.simulation.meshing`):

* **Voxel grid.** The replay's grid (``ReplayConfig.grid``, the paper's 13 x 5 x 5 by
  default) is laid over the mesh's rest bounding box ``[lo, hi]``: voxel ``(i, j, k)`` sits
  at ``lo + (i, j, k) * (hi - lo) / (grid - 1)``. On the box this is the box's own node grid,
  so the networks see the shape and spacing they see on the grid mesh. The 3D UNet uses
  the (nx, ny, nz) voxels; the 2D UNet uses the (nx, ny) footprint grid, as it uses the
  top layer of the box.
* **Scatter** (node quantities -> voxels), a sparse (V, N) matrix with rows summing to 1
  inside the body and 0 outside. 3D: each voxel inside a tetrahedron gets the
  barycentric (linear-in-tet) interpolation of that tet's 4 nodes. 2D: each footprint
  point ``(x, y)`` gets the barycentric interpolation of the rest surface triangle that a
  vertical ray from above hits first, i.e. the observed (top, camera-facing) surface, as
  the box's 2D net reads the top layer. Voxels outside the body (3D) or columns that miss
  it (2D) get zero features and ``inside`` False (the networks add it as a mask channel).
* **Gather** (voxel outputs -> nodes), a sparse (K, V) matrix: the correction at a
  corrected node is the trilinear (3D) or bilinear in (x, y) (2D) interpolation of the
  network's output grid at the node's rest position. Rows are convex weights, so the
  gathered correction keeps the voxel outputs' half-voxel bound.
* **Corrected nodes** (:func:`corrected_nodes`): the surface nodes not on the bottom
  face (z = 0, held by ``fixed: bottom``); interior and bottom nodes get no correction.

Both matrices are built once per mesh with scipy.sparse and applied in torch (dense
matmuls in :class:`core.learning.networks.CorrectionNetwork`, so training stays
differentiable). Both are linear in the node quantities and reproduce affine fields
exactly wherever the voxels involved are inside the body (barycentric and trilinear
interpolation are exact for affine functions).

On the box grid (``mesh.grid`` not None) the map is the identity: scatter is the
identity (3D) or the selection of the top layer (2D), gather selects the top layer, and
the corrected nodes are the top layer (k = nz - 1) in (i, j) order, exactly the
networks' behaviour before this map existed. Relation of the two node sets: the paper
corrects "only the top layer" because "the depth camera only provides labels for the top
layer"; on an unstructured mesh there is no layer, and the corrected set is the whole
surface above the support. On a box meshed from an STL that is the top face plus the
four side faces above z = 0 (on the 13 x 5 x 5 grid it would be 161 nodes instead of
the top layer's 65); the extra side nodes are seen obliquely by the camera above.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from core.learning.config import MODEL_KINDS, LearningError

__all__ = ["VoxelMap", "voxel_map", "corrected_nodes", "top_layer_nodes"]

_BARY_TOL = 1e-7
"""Barycentric slack (dimensionless) for a point on a tet's face or a triangle's edge:
voxels on the box's faces lie on boundary faces up to rounding (~1e-16)."""
_CHUNK = 2_000_000
"""Point-element pairs evaluated at once (memory ~ 3 x 8 bytes each)."""


def top_layer_nodes(grid) -> np.ndarray:
    """(nx*ny,) int64 indices of the top-layer nodes (k = nz-1) in (i, j) order, for the
    grid-major node numbering of :func:`core.simulation.mesh.box_mesh`."""
    nx, ny, nz = (int(g) for g in grid)
    return np.arange(nx * ny * nz).reshape(nx, ny, nz)[:, :, -1].ravel()


def corrected_nodes(mesh) -> np.ndarray:
    """(K,) int64 sorted indices of the nodes the learned correction moves.

    Args:
        mesh: a :class:`core.simulation.mesh.TetMesh`.

    Returns:
        For a grid mesh the top layer (k = nz-1) in (i, j) order (:func:`top_layer_nodes`,
        the paper's "only the top layer"); otherwise the surface nodes
        (``mesh.surface_nodes``) that are not on the bottom face z = 0
        (``mesh.bottom_nodes()``). See the module docstring for how the two relate.
    """
    if mesh.grid is not None:
        return top_layer_nodes(mesh.grid)
    return _surface_above_bottom(mesh)


def _surface_above_bottom(mesh) -> np.ndarray:
    return np.setdiff1d(mesh.surface_nodes, mesh.bottom_nodes()).astype(np.int64)


@dataclass(frozen=True)
class VoxelMap:
    """Linear maps between a mesh's nodes and the voxel grid a correction network uses.

    Attributes:
        kind: "2d" or "3d" (which network's grid).
        grid: (nx, ny, nz) voxel grid (for "2d" the network's grid is (nx, ny)).
        origin: (3,) float64 rest bounding box's low corner ``lo``, m, phantom frame.
        size: (3,) float64 its extents ``hi - lo``, m; voxel spacing ``size / (grid - 1)``.
        scatter: (V, N) float64 CSR, node quantities -> voxel features; V = nx*ny*nz
            ("3d", C order over (i, j, k)) or nx*ny ("2d", C order over (i, j)).
        inside: (V,) bool, voxels inside the body (rows of ``scatter`` summing to 1).
        gather: (K, V) float64 CSR, voxel values -> the corrected nodes, convex rows.
        nodes: (K,) int64 the corrected nodes (:func:`corrected_nodes`), rows of ``gather``.
        identity: True on a grid mesh (scatter and gather select nodes, no interpolation).
    """

    kind: str
    grid: tuple[int, int, int]
    origin: np.ndarray
    size: np.ndarray
    scatter: sp.csr_matrix
    inside: np.ndarray
    gather: sp.csr_matrix
    nodes: np.ndarray
    identity: bool

    @property
    def spatial(self) -> tuple[int, ...]:
        """The network's spatial shape: (nx, ny, nz) for "3d", (nx, ny) for "2d"."""
        return self.grid if self.kind == "3d" else self.grid[:2]

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.spatial))


def voxel_map(mesh, grid, kind: str, *, interpolate: bool = False) -> VoxelMap:
    """The mesh-to-voxel map of ``mesh`` for a ``kind`` network on voxel grid ``grid``.

    Args:
        mesh: a :class:`core.simulation.mesh.TetMesh` (rest nodes in m, phantom frame).
        grid: (nx, ny, nz) voxel counts, each >= 2 (the replay's grid; paper: 13 x 5 x 5).
            For a grid mesh it must equal ``mesh.grid``.
        kind: "3d" (voxels over the bounding box) or "2d" (the footprint's (nx, ny) grid,
            read from the observed top surface).
        interpolate: build the interpolating map even for a grid mesh (to check it
            against the identity; on the box it equals it up to rounding, but its
            corrected nodes are :func:`corrected_nodes` of an unstructured mesh).

    Returns:
        :class:`VoxelMap` (module docstring for the method).

    Raises:
        LearningError: an unknown kind, a grid that is not 3 counts >= 2, a grid mesh on
            another grid, or a mesh none of whose nodes lie on the surface above z = 0.
    """
    if kind not in MODEL_KINDS:
        raise LearningError(f"model kind must be one of {MODEL_KINDS}, got {kind!r}")
    grid = tuple(int(g) for g in grid)
    if len(grid) != 3 or min(grid) < 2:
        raise LearningError(f"voxel grid must be 3 counts >= 2, got {grid}")
    nodes = np.asarray(mesh.nodes, dtype=np.float64)
    n = nodes.shape[0]
    if mesh.grid is not None and not interpolate:
        if tuple(mesh.grid) != grid:
            raise LearningError(f"the grid mesh is {tuple(mesh.grid)}, the network's grid {grid}")
        top = top_layer_nodes(grid)
        t = top.size
        if kind == "3d":
            scatter = sp.identity(n, format="csr", dtype=np.float64)
            gather = sp.csr_matrix((np.ones(t), (np.arange(t), top)), shape=(t, n))
        else:
            scatter = sp.csr_matrix((np.ones(t), (np.arange(t), top)), shape=(t, n))
            gather = sp.identity(t, format="csr", dtype=np.float64)
        return VoxelMap(kind=kind, grid=grid, origin=np.zeros(3), size=np.asarray(mesh.size, dtype=np.float64).copy(),
                        scatter=scatter, inside=np.ones(scatter.shape[0], dtype=bool), gather=gather, nodes=top,
                        identity=True)
    lo, hi = nodes.min(axis=0), nodes.max(axis=0)
    size = hi - lo
    if not np.all(size > 0):
        raise LearningError(f"the mesh's bounding box must have positive extents, got {size} m")
    axes = [np.linspace(lo[a], hi[a], grid[a]) for a in range(3)]
    keep = _surface_above_bottom(mesh)
    if keep.size == 0:
        raise LearningError("the mesh has no surface node above z = 0 to correct")
    if kind == "3d":
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        points = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        scatter, inside = _tet_scatter(nodes, np.asarray(mesh.tets, dtype=np.int64), points)
        gather = _linear_gather(nodes[keep], lo, size, grid)
    else:
        X, Y = np.meshgrid(axes[0], axes[1], indexing="ij")
        points = np.stack([X.ravel(), Y.ravel()], axis=1)
        scatter, inside = _top_scatter(nodes, np.asarray(mesh.surface_triangles, dtype=np.int64), points)
        gather = _linear_gather(nodes[keep, :2], lo[:2], size[:2], grid[:2])
    return VoxelMap(kind=kind, grid=grid, origin=lo, size=size, scatter=scatter, inside=inside, gather=gather,
                    nodes=keep.astype(np.int64), identity=False)


def _rows(index: np.ndarray, weights: np.ndarray, found: np.ndarray, n_cols: int) -> sp.csr_matrix:
    """CSR (P, n_cols) with row p = weights[p] at columns index[p] where found, else empty;
    weights clipped to >= 0 and renormalised (points within the slack of a face)."""
    w = np.clip(weights, 0.0, None)
    w = w / w.sum(axis=1, keepdims=True)
    p = np.flatnonzero(found)
    k = index.shape[1]
    return sp.csr_matrix((w[p].ravel(), (np.repeat(p, k), index[p].ravel())), shape=(found.size, n_cols))


def _tet_scatter(nodes: np.ndarray, tets: np.ndarray, points: np.ndarray):
    """Barycentric interpolation in the tetrahedron containing each point.

    Returns ((P, N) CSR, (P,) bool inside). A point is inside when some tet has all four
    barycentric coordinates >= -_BARY_TOL; the tet whose smallest coordinate is largest
    is used."""
    v0 = nodes[tets[:, 0]]
    edges = (nodes[tets[:, 1:]] - v0[:, None, :]).transpose(0, 2, 1)  # (E, 3, 3): columns are edges
    inv = np.linalg.inv(edges)
    e = tets.shape[0]
    best = np.zeros(points.shape[0], dtype=np.int64)
    best_min = np.full(points.shape[0], -np.inf)
    best_w = np.zeros((points.shape[0], 4))
    step = max(1, _CHUNK // max(e, 1))
    for p0 in range(0, points.shape[0], step):
        d = points[p0 : p0 + step, None, :] - v0[None]  # (C, E, 3)
        lam = np.einsum("eij,cej->cei", inv, d)
        w = np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)  # (C, E, 4)
        m = w.min(-1)
        b = np.argmax(m, axis=1)
        r = np.arange(b.size)
        best[p0 : p0 + step] = b
        best_min[p0 : p0 + step] = m[r, b]
        best_w[p0 : p0 + step] = w[r, b]
    inside = best_min >= -_BARY_TOL
    return _rows(tets[best], best_w, inside, nodes.shape[0]), inside


def _top_scatter(nodes: np.ndarray, triangles: np.ndarray, xy: np.ndarray):
    """Barycentric interpolation on the surface triangle a vertical ray from above hits
    first at each (x, y): the highest of the triangles whose projection holds the point.

    Returns ((P, N) CSR, (P,) bool hit). Vertical triangles (projected area ~0) are
    skipped: a ray along one also crosses the faces it bounds."""
    tri = nodes[triangles]  # (T, 3, 3)
    a = tri[:, 0, :2]
    e1, e2 = tri[:, 1, :2] - a, tri[:, 2, :2] - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    scale = float(np.ptp(nodes[:, :2], axis=0).max()) ** 2
    flat = np.abs(det) > 1e-12 * scale
    triangles, tri, a, e1, e2, det = triangles[flat], tri[flat], a[flat], e1[flat], e2[flat], det[flat]
    z = tri[:, :, 2]
    best = np.zeros(xy.shape[0], dtype=np.int64)
    best_z = np.full(xy.shape[0], -np.inf)
    best_w = np.zeros((xy.shape[0], 3))
    step = max(1, _CHUNK // max(triangles.shape[0], 1))
    for p0 in range(0, xy.shape[0], step):
        d = xy[p0 : p0 + step, None, :] - a[None]  # (C, T, 2)
        l1 = (d[..., 0] * e2[:, 1] - d[..., 1] * e2[:, 0]) / det
        l2 = (e1[:, 0] * d[..., 1] - e1[:, 1] * d[..., 0]) / det
        w = np.stack([1.0 - l1 - l2, l1, l2], axis=-1)  # (C, T, 3)
        height = np.where(w.min(-1) >= -_BARY_TOL, np.einsum("ctk,tk->ct", w, z), -np.inf)
        b = np.argmax(height, axis=1)
        r = np.arange(b.size)
        best[p0 : p0 + step] = b
        best_z[p0 : p0 + step] = height[r, b]
        best_w[p0 : p0 + step] = w[r, b]
    hit = np.isfinite(best_z)
    return _rows(triangles[best], best_w, hit, nodes.shape[0]), hit


def _linear_gather(points: np.ndarray, lo: np.ndarray, size: np.ndarray, shape) -> sp.csr_matrix:
    """(P, prod(shape)) multilinear interpolation (bilinear for 2 axes, trilinear for 3)
    of a regular grid of ``shape`` points spanning ``[lo, lo + size]`` at ``points``
    (P, D); points outside the box are clamped to it. Columns in C order."""
    shape = tuple(int(s) for s in shape)
    dim = len(shape)
    counts = np.asarray(shape)
    u = (points - lo) / size * (counts - 1)
    i0 = np.clip(np.floor(u).astype(np.int64), 0, counts - 2)
    f = np.clip(u - i0, 0.0, 1.0)
    strides = np.array([int(np.prod(shape[a + 1 :])) for a in range(dim)])
    rows, cols, vals = [], [], []
    p = np.arange(points.shape[0])
    for corner in np.ndindex(*([2] * dim)):
        c = np.asarray(corner)
        w = np.prod(np.where(c == 1, f, 1.0 - f), axis=1)
        rows.append(p)
        cols.append(((i0 + c) * strides).sum(axis=1))
        vals.append(w)
    m = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(points.shape[0], int(np.prod(shape))))
    m.eliminate_zeros()
    return m
