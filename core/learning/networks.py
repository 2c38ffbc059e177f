"""The correction networks of Wu et al. 2020 (Sec. 3.3, Fig. 3): a 3D UNet over the
node grid and a 2D UNet over its top layer, with the robot pose joined at the bottleneck.
On a mesh that is not a grid they run on a voxel grid around it (:mod:`core.learning.voxels`).

Both follow the paper's description (a 3D UNet after Cicek et al. 2016):

* 3 encoder blocks of two 3x3(x3) convolutions with ReLU (64, 128, 256 features by
  default), with 2x max-pooling between the blocks;
* at the bottleneck the robot pose is concatenated to every voxel as extra features and
  fused by 4 convolutions (kernel 3, padding 1), the last one back to 256 features;
* a decoder of two up-convolutions (2x transposed convolution) each followed by
  concatenation with the encoder features of the same resolution (skip connection) and
  two convolutions; a 1x1 convolution gives 3 values per node;
* the output is bounded per axis to half the voxel length by ``bound * tanh(.)``.

Odd grids (13 x 5 x 5) are handled by ceil-mode pooling (13 -> 7 -> 4, 5 -> 3 -> 2) and
by cropping each up-convolution's output (8 -> 7, 14 -> 13, 4 -> 3, 6 -> 5) to the size
of its skip connection, so no grid size is special.

Inputs are the node positions (m, phantom frame), encoded per node as 6 channels: the
position scaled to [-1, 1] over the box, and the displacement from rest in units of
the correction bound. Both are affine maps of the xyz positions the paper feeds; the
second puts the millimetre-scale deformation on the same scale as the first instead of
asking the first layer to amplify it. The pose enters as the probe centre, scaled like
the positions, plus the tool quaternion (optional, see :class:`NetworkConfig.pose`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from core.learning.config import LearningError, NetworkConfig

__all__ = ["CorrectionNetwork", "UNet2D", "UNet3D", "build_network"]

IN_CHANNELS = 6


def _block(dim: int, c_in: int, c_out: int, n: int = 2) -> nn.Sequential:
    Conv = nn.Conv3d if dim == 3 else nn.Conv2d
    layers = []
    for i in range(n):
        layers += [Conv(c_in if i == 0 else c_out, c_out, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


def _crop(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Crop the spatial dims of ``x`` to those of ``like`` (x is never smaller)."""
    sl = [slice(None), slice(None)] + [slice(0, s) for s in like.shape[2:]]
    return x[tuple(sl)]


class _UNet(nn.Module):
    """UNet with the pose joined at the bottleneck; ``dim`` 2 or 3 spatial dims.

    forward(x (B, C_in, *spatial), pose (B, D)) -> (B, 3, *spatial) unbounded output.
    """

    def __init__(self, dim: int, in_channels: int, pose_dim: int, widths=(64, 128, 256), fusion_convs: int = 4):
        super().__init__()
        if dim not in (2, 3):
            raise LearningError(f"UNet dimension must be 2 or 3, got {dim}")
        self.dim = dim
        w1, w2, w3 = widths
        Conv = nn.Conv3d if dim == 3 else nn.Conv2d
        Up = nn.ConvTranspose3d if dim == 3 else nn.ConvTranspose2d
        self.enc1 = _block(dim, in_channels, w1)
        self.enc2 = _block(dim, w1, w2)
        self.enc3 = _block(dim, w2, w3)
        fusion = []
        for i in range(fusion_convs):
            fusion += [Conv(w3 + pose_dim if i == 0 else w3, w3, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
        self.fusion = nn.Sequential(*fusion)
        self.up2 = Up(w3, w2, kernel_size=2, stride=2)
        self.dec2 = _block(dim, 2 * w2, w2)
        self.up1 = Up(w2, w1, kernel_size=2, stride=2)
        self.dec1 = _block(dim, 2 * w1, w1)
        self.head = Conv(w1, 3, kernel_size=1)

    def _pool(self, x: torch.Tensor) -> torch.Tensor:
        pool = F.max_pool3d if self.dim == 3 else F.max_pool2d
        return pool(x, kernel_size=2, stride=2, ceil_mode=True)

    def forward(self, x: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        e1 = self.enc1(x)
        e2 = self.enc2(self._pool(e1))
        e3 = self.enc3(self._pool(e2))
        tiled = pose.reshape(pose.shape[0], pose.shape[1], *([1] * self.dim)).expand(-1, -1, *e3.shape[2:])
        b = self.fusion(torch.cat([e3, tiled], dim=1))
        d2 = self.dec2(torch.cat([_crop(self.up2(b), e2), e2], dim=1))
        d1 = self.dec1(torch.cat([_crop(self.up1(d2), e1), e1], dim=1))
        return self.head(d1)


class UNet3D(_UNet):
    """3D UNet over the (nx, ny, nz) node grid: (B, C, nx, ny, nz), pose (B, D) -> (B, 3, nx, ny, nz)."""

    def __init__(self, in_channels: int, pose_dim: int, widths=(64, 128, 256), fusion_convs: int = 4):
        super().__init__(3, in_channels, pose_dim, widths, fusion_convs)


class UNet2D(_UNet):
    """2D UNet over the top layer: (B, C, nx, ny), pose (B, D) -> (B, 3, nx, ny)."""

    def __init__(self, in_channels: int, pose_dim: int, widths=(64, 128, 256), fusion_convs: int = 4):
        super().__init__(2, in_channels, pose_dim, widths, fusion_convs)


class CorrectionNetwork(nn.Module):
    """Node positions and robot pose -> bounded correction of the observed nodes.

    The module owns its input encoding (box size, rest positions, bound) as buffers, so
    a saved ``state_dict`` with its :class:`NetworkConfig`, grid, box size and (for an
    unstructured mesh) the mesh is all inference needs.

    On the box grid (``mesh`` None or a grid mesh) the UNet convolves over the node grid
    itself (3D) or its top layer (2D) and corrects the top-layer nodes, as in the paper.
    On an unstructured mesh (``mesh.grid is None``, a ``phantom.stl``) node quantities are
    scattered to a (nx, ny, nz) voxel grid over the rest bounding box (3D) or to the
    (nx, ny) footprint from the observed top surface (2D), the UNet runs there with a 7th
    input channel marking voxels inside the body, and its bounded output is gathered
    back to the surface nodes above z = 0 by trilinear / bilinear interpolation at their
    rest positions (:mod:`core.learning.voxels`; the paper's Sec. 6 suggestion).

    forward(positions (B, N, 3) float32 m phantom frame, poses (B, 7) [centre m,
    quaternion xyzw]) -> corrections (B, K, 3) float32 m for the nodes
    :attr:`corrected_nodes` ((i, j) order of the top layer on the grid, K = nx*ny), each
    component within ``[-bound_a, bound_a]``, ``bound = bound_fraction * size / (grid - 1)``
    (half a node / voxel spacing by default).
    """

    def __init__(self, config: NetworkConfig, grid, size, mesh=None):
        super().__init__()
        from core.learning.voxels import top_layer_nodes, voxel_map
        from core.simulation.mesh import box_mesh

        self.config = config
        self.grid = tuple(int(g) for g in grid)
        if mesh is not None and mesh.grid is not None:
            if tuple(mesh.grid) != self.grid:
                raise LearningError(f"the grid mesh is {tuple(mesh.grid)}, the network's grid {self.grid}")
            mesh = None  # the box path: the grid is the mesh
        self.mesh = mesh  # the unstructured TetMesh the network corrects; None on the box grid
        Net = UNet3D if config.kind == "3d" else UNet2D
        if mesh is None:
            size = np.asarray(size, dtype=np.float64).reshape(3)
            box = box_mesh(size, self.grid)  # validates grid and size
            nx, ny, nz = self.grid
            rest = box.nodes.reshape(nx, ny, nz, 3)
            self.voxel_map = None
            self.corrected_nodes = top_layer_nodes(self.grid)
            in_channels = IN_CHANNELS
        else:
            vm = voxel_map(mesh, self.grid, config.kind)
            size, rest = vm.size, np.asarray(mesh.nodes, dtype=np.float64)
            self.voxel_map = vm
            self.corrected_nodes = vm.nodes
            # derived from the mesh (rebuilt on load), so not in the state_dict
            self.register_buffer("origin", torch.tensor(vm.origin, dtype=torch.float32), persistent=False)
            self.register_buffer("scatter", torch.tensor(vm.scatter.toarray(), dtype=torch.float32), persistent=False)
            self.register_buffer("gather", torch.tensor(vm.gather.toarray(), dtype=torch.float32), persistent=False)
            self.register_buffer("inside", torch.tensor(vm.inside, dtype=torch.float32), persistent=False)
            in_channels = IN_CHANNELS + 1
        bound = config.bound_fraction * size / (np.asarray(self.grid) - 1.0)
        self.register_buffer("size", torch.tensor(size, dtype=torch.float32))
        self.register_buffer("rest", torch.tensor(rest, dtype=torch.float32))
        self.register_buffer("bound", torch.tensor(bound, dtype=torch.float32))
        self.unet = Net(in_channels, config.pose_dim, config.widths, config.fusion_convs)

    @property
    def n_nodes(self) -> int:
        """N, the node count of the positions the network takes."""
        return int(np.prod(self.grid)) if self.mesh is None else self.mesh.n_nodes

    def _check(self, positions: torch.Tensor, poses: torch.Tensor) -> None:
        n = self.n_nodes
        if positions.ndim != 3 or positions.shape[1:] != (n, 3):
            where = f"grid {self.grid}" if self.mesh is None else f"its {n}-node mesh"
            raise LearningError(f"positions must be (B, {n}, 3) for {where}, got {tuple(positions.shape)}")
        if poses.ndim != 2 or poses.shape[1] != 7 or poses.shape[0] != positions.shape[0]:
            raise LearningError(f"poses must be ({positions.shape[0]}, 7), got {tuple(poses.shape)}")

    def encode(self, positions: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Network inputs: (B, C, nx, ny, nz) or (B, C, nx, ny) voxel channels and (B, D) pose.

        C = 6 on the box grid (position scaled to [-1, 1] over the box, displacement from
        rest in units of the bound); C = 7 on an unstructured mesh (the same 6 scattered
        to the voxels, then the inside mask)."""
        self._check(positions, poses)
        if self.mesh is not None:
            return self._encode_mesh(positions, poses)
        nx, ny, nz = self.grid
        half = self.size / 2
        g = positions.reshape(-1, nx, ny, nz, 3)
        feats = torch.cat([(g - half) / half, (g - self.rest) / self.bound], dim=-1)  # (B, nx, ny, nz, 6)
        if self.config.kind == "2d":
            feats = feats[:, :, :, -1].permute(0, 3, 1, 2)
        else:
            feats = feats.permute(0, 4, 1, 2, 3)
        pose = (poses[:, :3] - half) / half
        if self.config.pose == "position_quaternion":
            pose = torch.cat([pose, poses[:, 3:7]], dim=1)
        return feats.contiguous(), pose

    def _encode_mesh(self, positions: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        half = self.size / 2
        centre = self.origin + half
        node_feats = torch.cat([(positions - centre) / half, (positions - self.rest) / self.bound], dim=-1)  # (B, N, 6)
        vox = torch.einsum("vn,bnc->bvc", self.scatter, node_feats)  # (B, V, 6); zero outside the body
        mask = self.inside.reshape(1, -1, 1).expand(vox.shape[0], -1, 1)
        vox = torch.cat([vox, mask], dim=-1)
        spatial = self.voxel_map.spatial
        feats = vox.reshape(vox.shape[0], *spatial, vox.shape[-1]).movedim(-1, 1)
        pose = (poses[:, :3] - centre) / half
        if self.config.pose == "position_quaternion":
            pose = torch.cat([pose, poses[:, 3:7]], dim=1)
        return feats.contiguous(), pose

    def forward(self, positions: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        x, pose = self.encode(positions, poses)
        out = self.unet(x, pose)
        if self.mesh is not None:
            voxels = out.reshape(out.shape[0], 3, -1).transpose(1, 2)  # (B, V, 3)
            # bound on the voxels, then gather with convex weights: the bound holds at the nodes
            return torch.einsum("kv,bvc->bkc", self.gather, torch.tanh(voxels) * self.bound)
        if self.config.kind == "3d":
            out = out[..., -1]  # only the top layer is observed, so only it is corrected
        out = out.permute(0, 2, 3, 1).reshape(out.shape[0], -1, 3)
        return torch.tanh(out) * self.bound


def build_network(config: NetworkConfig, grid, size, mesh=None) -> CorrectionNetwork:
    """A freshly initialised :class:`CorrectionNetwork` (seed torch first for repeatability).

    Args:
        config: network shape. grid: (nx, ny, nz) node grid of the box, or the voxel grid
            of an unstructured mesh. size: (3,) box size, m (unused with an unstructured
            ``mesh``: its rest bounding box sets scaling and bound).
        mesh: optional :class:`core.simulation.mesh.TetMesh`; a grid mesh (which must be
            on ``grid``) or None gives the box network, one with ``grid is None`` the
            voxel-mapped network (:mod:`core.learning.voxels`).

    Raises:
        LearningError, SimulationError: bad configuration, grid or size; a grid mesh on
            another grid.
    """
    return CorrectionNetwork(config, grid, size, mesh)
