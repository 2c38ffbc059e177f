"""Shapes on odd grids, the half-voxel bound, and input checks of the correction networks."""

import numpy as np
import pytest
import torch

from core.learning import NetworkConfig, build_network
from core.learning.config import LearningError
from core.simulation.mesh import box_mesh

SIZE = np.array([0.0687, 0.0393, 0.0358])


def _inputs(grid, batch=3, seed=0, amp=0.002):
    rng = np.random.default_rng(seed)
    x = box_mesh(SIZE, grid).nodes[None] + rng.normal(scale=amp, size=(batch, int(np.prod(grid)), 3))
    q = rng.normal(size=(batch, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    pose = np.concatenate([rng.uniform(0, SIZE, size=(batch, 3)), q], axis=1)
    return torch.tensor(x, dtype=torch.float32), torch.tensor(pose, dtype=torch.float32)


@pytest.mark.parametrize("kind", ["2d", "3d"])
@pytest.mark.parametrize("grid", [(13, 5, 5), (4, 3, 3), (2, 2, 2), (7, 6, 3)])
def test_output_is_one_correction_per_top_node(kind, grid):
    torch.manual_seed(0)
    net = build_network(NetworkConfig(kind=kind, widths=(4, 8, 8)), grid, SIZE)
    out = net(*_inputs(grid))
    assert out.shape == (3, grid[0] * grid[1], 3)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("kind", ["2d", "3d"])
def test_corrections_respect_the_half_voxel_bound(kind):
    """With weights scaled up until tanh saturates, every component stays within half
    the node spacing of its axis, and reaches it (so the bound is the active limit)."""
    grid = (13, 5, 5)
    torch.manual_seed(1)
    net = build_network(NetworkConfig(kind=kind, widths=(8, 16, 16)), grid, SIZE)
    with torch.no_grad():
        for p in net.unet.parameters():
            p.mul_(30.0)
    out = net(*_inputs(grid, batch=8, amp=0.005)).detach().numpy()
    half_voxel = 0.5 * SIZE / (np.array(grid) - 1)
    assert np.all(np.abs(out) <= half_voxel * (1 + 1e-6))
    assert np.all(np.abs(out).max(axis=(0, 1)) > 0.99 * half_voxel)


def test_bound_fraction_scales_the_bound():
    grid = (5, 3, 3)
    torch.manual_seed(2)
    net = build_network(NetworkConfig(kind="2d", widths=(4, 8, 8), bound_fraction=0.1), grid, SIZE)
    np.testing.assert_allclose(net.bound.numpy(), 0.1 * SIZE / (np.array(grid) - 1), rtol=1e-6)


def test_3d_network_reads_the_layers_below_the_top_and_2d_does_not():
    grid = (6, 3, 4)
    x, pose = _inputs(grid, batch=1)
    below = torch.zeros_like(x).reshape(1, 6, 3, 4, 3)
    below[:, :, :, 0, 2] = 0.003  # push the bottom layer up 3 mm
    for kind, changes in (("3d", True), ("2d", False)):
        torch.manual_seed(3)
        net = build_network(NetworkConfig(kind=kind, widths=(4, 8, 8)), grid, SIZE)
        a, b = net(x, pose), net(x + below.reshape(1, -1, 3), pose)
        assert (not torch.equal(a, b)) == changes, kind


def test_pose_enters_the_network():
    grid = (6, 3, 3)
    torch.manual_seed(4)
    net = build_network(NetworkConfig(kind="2d", widths=(4, 8, 8)), grid, SIZE)
    x, pose = _inputs(grid, batch=1)
    moved = pose.clone()
    moved[0, 0] += 0.01
    assert not torch.equal(net(x, pose), net(x, moved))


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(LearningError, match="model kind"):
        NetworkConfig(kind="4d")
    with pytest.raises(LearningError, match="widths"):
        NetworkConfig(widths=(8, 16))
    net = build_network(NetworkConfig(kind="3d", widths=(4, 8, 8)), (4, 3, 3), SIZE)
    with pytest.raises(LearningError, match=r"positions must be \(B, 36, 3\)"):
        net(torch.zeros(1, 35, 3), torch.zeros(1, 7))
    with pytest.raises(LearningError, match="poses must be"):
        net(torch.zeros(2, 36, 3), torch.zeros(2, 3))
