"""The training loss: one-sided Chamfer distance from the measured cloud to the
corrected, 3x super-sampled mesh (Wu et al. 2020, Sec. 3.3).

The paper super-samples the node grid by a factor of 3 in every direction with linear
interpolation and takes the mean distance from each point of the cleaned depth cloud
to its nearest super-sampled vertex, in that direction only (the instrument occludes
parts of the phantom, so mesh -> cloud has no correspondences). The vertices are the
boundary vertices of the super-sampled grid, as in :mod:`core.simulation.metrics`, so
the loss is exactly the project's reported error, in torch.

Super-sampling is linear in the node positions, so it is one dense matrix
``S`` (P, N) built once per grid (:func:`supersample_matrix`). The nearest vertex is
searched without gradient (a KD-tree per frame), then the distance to it is
recomputed with gradient: the same value and (sub)gradient as a min over all
vertices, without a (B, M, P) graph.
"""

from __future__ import annotations

import numpy as np
import torch

from core.learning.config import LearningError

__all__ = ["supersample_matrix", "point_to_mesh_distances_torch", "chamfer_loss"]


def supersample_matrix(grid, factor: int = 3) -> np.ndarray:
    """(P, N) float64 matrix mapping node positions to the boundary vertices of the
    ``factor``x super-sampled grid, in the order of
    :func:`core.simulation.metrics.supersampled_surface` (so ``S @ x`` equals it); a
    dense copy of :func:`core.simulation.metrics.surface_operator`.

    Args:
        grid: (nx, ny, nz), each >= 2, or a :class:`core.simulation.mesh.TetMesh`.
            factor: sub-divisions per cell edge (paper: 3).

    Raises:
        LearningError: a grid smaller than 2 along an axis, or factor < 1.
    """
    from core.errors import SimulationError
    from core.simulation.metrics import surface_operator

    try:
        return surface_operator(grid, factor).toarray()
    except SimulationError as exc:
        raise LearningError(str(exc)) from exc


@torch.no_grad()
def _nearest(points: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """(B, M) int64 index of the nearest surface vertex of every point (a KD-tree per
    frame, scipy.spatial.cKDTree, in float64: faster on a CPU than a dense (M, P)
    distance matrix and exact)."""
    from scipy.spatial import cKDTree

    p = points.double().numpy()
    v = surface.double().numpy()
    out = np.empty(points.shape[:2], dtype=np.int64)
    for b in range(p.shape[0]):
        out[b] = cKDTree(v[b]).query(p[b], k=1)[1]
    return torch.from_numpy(out)


def point_to_mesh_distances_torch(points: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """Distance from every point to its nearest surface vertex, differentiable in both.

    Args:
        points: (B, M, 3) measured points, m (float32 or float64).
        surface: (B, P, 3) mesh vertices, m, same frame and dtype.

    Returns:
        (B, M) distances, m.

    Raises:
        LearningError: shapes that do not match.
    """
    if points.ndim != 3 or surface.ndim != 3 or points.shape[-1] != 3 or surface.shape[-1] != 3 or points.shape[0] != surface.shape[0]:
        raise LearningError(f"points must be (B, M, 3) and surface (B, P, 3), got {tuple(points.shape)} and {tuple(surface.shape)}")
    idx = _nearest(points.detach(), surface.detach())
    nearest = torch.gather(surface, 1, idx[..., None].expand(-1, -1, 3))
    diff = points - nearest
    return torch.sqrt((diff * diff).sum(-1) + 1e-18)


def chamfer_loss(points: torch.Tensor, mask: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """One-sided Chamfer distance cloud -> mesh (Wu et al. 2020, Sec. 3.3): the mean over
    all valid points of the batch of the distance to the nearest mesh vertex, m.

    Args:
        points: (B, M, 3) measured points, padded. mask: (B, M) bool, True for real points.
        surface: (B, P, 3) super-sampled corrected mesh vertices (``S @ positions``).

    Returns:
        scalar tensor, m.

    Raises:
        LearningError: no valid point in the batch, or shapes that do not match.
    """
    if mask.shape != points.shape[:2]:
        raise LearningError(f"mask must be {tuple(points.shape[:2])}, got {tuple(mask.shape)}")
    n = mask.sum()
    if int(n) == 0:
        raise LearningError("the batch holds no measured point")
    d = point_to_mesh_distances_torch(points, surface)
    return (d * mask).sum() / n
