"""The one-sided Chamfer loss against a naive reference (a loop over points, as
pytorch3d tests its chamfer), and the super-sampling matrix against
core.simulation.metrics."""

import numpy as np
import pytest
import torch

from core.learning import chamfer_loss, point_to_mesh_distances_torch, supersample_matrix, top_layer_nodes
from core.learning.config import LearningError
from core.simulation.mesh import box_mesh
from core.simulation.metrics import supersampled_surface

SIZE = np.array([0.0687, 0.0393, 0.0358])


def _deformed(grid, rng, amp=0.003):
    x = box_mesh(SIZE, grid).nodes
    return x + rng.normal(scale=amp, size=x.shape)


@pytest.mark.parametrize("grid", [(13, 5, 5), (2, 3, 4), (4, 2, 2)])
@pytest.mark.parametrize("factor", [1, 2, 3])
def test_supersample_matrix_matches_metrics(grid, factor):
    x = _deformed(grid, np.random.default_rng(0))
    S = supersample_matrix(grid, factor)
    # exact up to float64 rounding of the two interpolation orders
    np.testing.assert_allclose(S @ x, supersampled_surface(x, grid, factor), rtol=0, atol=1e-15)


def _naive_loss(points_per_frame, positions, corrections, grid, factor=3):
    """Mean over all points of the distance to the nearest super-sampled boundary vertex,
    by brute force over vertices, one point at a time."""
    top = top_layer_nodes(grid)
    total, n = 0.0, 0
    for pts, x, c in zip(points_per_frame, positions, corrections):
        x = x.copy()
        x[top] += c
        surf = supersampled_surface(x, grid, factor)
        for p in pts:
            total += min(np.sqrt(((surf - p) ** 2).sum(axis=1)))
            n += 1
    return total / n


def _batch(grid, rng, counts):
    positions = np.stack([_deformed(grid, rng) for _ in counts])
    corrections = rng.normal(scale=0.001, size=(len(counts), grid[0] * grid[1], 3))
    clouds = [rng.uniform([-0.005] * 3, SIZE + 0.005, size=(k, 3)) for k in counts]
    M = max(counts)
    pts = np.zeros((len(counts), M, 3))
    mask = np.zeros((len(counts), M), dtype=bool)
    for i, c in enumerate(clouds):
        pts[i, : len(c)] = c
        pts[i, len(c):] = 1.0  # far-away padding must not count
        mask[i, : len(c)] = True
    return positions, corrections, clouds, pts, mask


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-7)])
def test_chamfer_loss_matches_naive_reference(dtype, tol):
    """float64: equal to rounding; float32: within 0.2 um (float32 spacing at 0.07 m is ~7 nm,
    summed over the distance arithmetic)."""
    grid = (13, 5, 5)
    rng = np.random.default_rng(1)
    positions, corrections, clouds, pts, mask = _batch(grid, rng, [150, 97, 120])
    S = torch.tensor(supersample_matrix(grid, 3), dtype=dtype)
    x = torch.tensor(positions, dtype=dtype)
    x[:, top_layer_nodes(grid)] += torch.tensor(corrections, dtype=dtype)
    surface = torch.einsum("pn,bnd->bpd", S, x)
    loss = chamfer_loss(torch.tensor(pts, dtype=dtype), torch.tensor(mask), surface)
    ref = _naive_loss(clouds, positions, corrections, grid)
    assert abs(float(loss) - ref) < tol, (float(loss), ref)


def test_chamfer_gradient_matches_finite_differences():
    """d loss / d correction by autograd equals central differences (float64, step 1e-8 m:
    far below the gap to the second-nearest vertex, so the assignment does not change)."""
    grid = (4, 3, 3)
    rng = np.random.default_rng(2)
    positions, corrections, clouds, pts, mask = _batch(grid, rng, [40, 33])
    S = torch.tensor(supersample_matrix(grid, 3))
    top = top_layer_nodes(grid)
    pts_t, mask_t = torch.tensor(pts), torch.tensor(mask)

    def loss_of(c):
        x = torch.tensor(positions).clone()
        x[:, top] = x[:, top] + c
        return chamfer_loss(pts_t, mask_t, torch.einsum("pn,bnd->bpd", S, x))

    c = torch.tensor(corrections, requires_grad=True)
    loss_of(c).backward()
    h = 1e-8
    fd = np.zeros_like(corrections)
    for idx in np.ndindex(*corrections.shape):
        e = np.zeros_like(corrections)
        e[idx] = h
        fd[idx] = (float(loss_of(torch.tensor(corrections + e))) - float(loss_of(torch.tensor(corrections - e)))) / (2 * h)
    np.testing.assert_allclose(c.grad.numpy(), fd, atol=1e-6)
    assert np.abs(fd).max() > 1e-3  # the check is not vacuous


def test_loss_rejects_bad_shapes():
    with pytest.raises(LearningError, match="points must be"):
        point_to_mesh_distances_torch(torch.zeros(5, 3), torch.zeros(1, 4, 3))
    with pytest.raises(LearningError, match="no measured point"):
        chamfer_loss(torch.zeros(1, 2, 3), torch.zeros(1, 2, dtype=torch.bool), torch.zeros(1, 4, 3))
    with pytest.raises(LearningError, match="grid"):
        supersample_matrix((1, 5, 5))
