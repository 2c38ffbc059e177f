"""Training of a correction network (Wu et al. 2020, Sec. 3.3 and 5.1).

The network sees the simulated node positions and the robot pose of a frame and
outputs a bounded correction of the top-layer nodes (on an unstructured mesh: of the
surface nodes above z = 0, through the voxel map of :mod:`core.learning.voxels`); the loss is the one-sided Chamfer
distance from that frame's cleaned cloud to the corrected, 3x super-sampled mesh
(:mod:`core.learning.loss`). Adam with a fixed seed; early stopping on the validation
sequences, keeping the weights of the best validation epoch. Training runs on the CPU.
"""

from __future__ import annotations

import copy
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping

import numpy as np
import torch

from core.learning.config import LearningError, NetworkConfig, TrainConfig
from core.learning.data import SequenceFrames, same_mesh
from core.learning.loss import chamfer_loss, point_to_mesh_distances_torch, supersample_matrix
from core.learning.networks import CorrectionNetwork, build_network

__all__ = ["TrainResult", "FrameSet", "train_correction", "torch_settings"]

Callback = Callable[[float, str], None]


@contextmanager
def torch_settings(threads: int | None, deterministic: bool):
    """Temporarily set torch's intra-op threads and deterministic-algorithms flag."""
    old_threads = torch.get_num_threads()
    old_det = torch.are_deterministic_algorithms_enabled()
    try:
        if threads:
            torch.set_num_threads(int(threads))
        torch.use_deterministic_algorithms(bool(deterministic))
        yield
    finally:
        torch.set_num_threads(old_threads)
        torch.use_deterministic_algorithms(old_det)


class FrameSet:
    """The usable frames of some sequences as float32 tensors, clouds kept ragged.

    Attributes:
        positions: (F, N, 3) float32 simulated node positions, m.
        poses: (F, 7) float32 robot poses.
        points: (T, 3) float32 all measured points, m; frame f owns
            ``points[offsets[f]:offsets[f] + counts[f]]``.
        names: (F,) sequence name of each frame; frames: (F,) index within it.
    """

    def __init__(self, frames: list[SequenceFrames]):
        pos, poses, clouds, names, index = [], [], [], [], []
        for s in frames:
            ok = np.flatnonzero(s.finite)
            pos.append(s.positions[ok])
            poses.append(s.poses[ok])
            clouds += [s.clouds[i] for i in ok]
            names += [s.name] * ok.size
            index.append(ok)
        if not clouds:
            raise LearningError("no usable frame (finite simulation and a non-empty cloud) in " + ", ".join(s.name for s in frames))
        self.positions = torch.tensor(np.concatenate(pos), dtype=torch.float32)
        self.poses = torch.tensor(np.concatenate(poses), dtype=torch.float32)
        counts = np.array([c.shape[0] for c in clouds], dtype=np.int64)
        self.counts = torch.tensor(counts)
        self.offsets = torch.tensor(np.concatenate([[0], np.cumsum(counts)[:-1]]))
        self.points = torch.tensor(np.concatenate(clouds), dtype=torch.float32)
        self.names = names
        self.frames = np.concatenate(index)

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def sample_points(self, idx: torch.Tensor, max_points: int, generator: torch.Generator | None):
        """(B, M, 3) points and (B, M) mask for frames ``idx``: all points of frames with at
        most ``max_points``, else a random subset (without replacement) of that size."""
        counts = self.counts[idx]
        M = int(min(int(counts.max()), max_points))
        pts = torch.zeros((idx.numel(), M, 3), dtype=torch.float32)
        mask = torch.zeros((idx.numel(), M), dtype=torch.bool)
        for r, f in enumerate(idx.tolist()):
            c = int(self.counts[f])
            o = int(self.offsets[f])
            if c <= M:
                sel = torch.arange(c)
            else:
                sel = torch.randperm(c, generator=generator)[:M]
            pts[r, : sel.numel()] = self.points[o + sel]
            mask[r, : sel.numel()] = True
        return pts, mask


@dataclass
class TrainResult:
    """Evidence of a training run.

    Attributes:
        network: the trained :class:`CorrectionNetwork` (best validation epoch, eval mode).
        network_config, train_config: what was trained and how.
        history: one dict per epoch: ``epoch``, ``train_loss`` (m, mean over the epoch's
            sampled points), ``validation_loss`` (m), ``seconds`` (wall time).
        best_epoch: the epoch whose weights were kept (1-based).
        stopped_early: whether the patience ran out before ``max_epochs``.
        baseline: loss without correction on the same point subsets, m:
            ``{"train": ..., "validation": ...}``.
        n_frames: usable frames per role, ``{"train": F, "validation": F}``.
        timings: s: ``{"setup", "train", "per_epoch"}``.
    """

    network: CorrectionNetwork
    network_config: NetworkConfig
    train_config: TrainConfig
    history: list[dict]
    best_epoch: int
    stopped_early: bool
    baseline: dict[str, float]
    n_frames: dict[str, int]
    timings: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "network": self.network_config.to_json(),
            "train_config": self.train_config.to_json(),
            "losses": self.history,
            "best_epoch": self.best_epoch,
            "stopped_early": self.stopped_early,
            "baseline_loss": self.baseline,
            "frames": self.n_frames,
            "timings": self.timings,
        }


class _LossModel:
    """Corrected super-sampled surfaces of a batch: ``S x + S_c c``, with ``S`` (P, N) the
    metric's super-sampling of the grid or mesh and ``S_c`` its columns of the corrected
    nodes (the top layer on the box grid, :func:`core.learning.voxels.corrected_nodes`)."""

    def __init__(self, mesh_or_grid, factor: int, nodes: np.ndarray | None = None):
        from core.learning.voxels import corrected_nodes, top_layer_nodes

        S = supersample_matrix(mesh_or_grid, factor)
        if nodes is None:
            nodes = corrected_nodes(mesh_or_grid) if hasattr(mesh_or_grid, "nodes") else top_layer_nodes(mesh_or_grid)
        top = np.asarray(nodes, dtype=np.int64)
        self.S = torch.tensor(S, dtype=torch.float32)
        self.S_top = torch.tensor(S[:, top], dtype=torch.float32)

    def surface(self, positions: torch.Tensor, corrections: torch.Tensor | None) -> torch.Tensor:
        s = torch.einsum("pn,bnd->bpd", self.S, positions)
        if corrections is not None:
            s = s + torch.einsum("pt,btd->bpd", self.S_top, corrections)
        return s


def _evaluate(net, data: FrameSet, lm: _LossModel, samples, batch: int, correct: bool) -> float:
    """Point-weighted mean distance (m) over the frames' fixed point subsets."""
    total, n = 0.0, 0
    with torch.no_grad():
        for b0 in range(0, len(data), batch):
            idx = torch.arange(b0, min(b0 + batch, len(data)))
            pts, mask = samples[b0 // batch]
            corr = net(data.positions[idx], data.poses[idx]) if correct else None
            s = lm.surface(data.positions[idx], corr)
            d = point_to_mesh_distances_torch(pts, s)
            total += float((d * mask).sum())
            n += int(mask.sum())
    return total / max(n, 1)


def train_correction(
    frames: Mapping[str, SequenceFrames],
    size,
    network_config: NetworkConfig | None = None,
    train_config: TrainConfig | None = None,
    *,
    callback: Callback | None = None,
) -> TrainResult:
    """Train a correction network on the ``train`` sequences, early-stopped on ``validation``.

    Args:
        frames: per-sequence arrays from :func:`core.learning.build_frames` (roles
            decide use: "train" to fit, "validation" to stop; "test" is ignored here).
        size: (3,) phantom box size, m (the box's rest shape; sets input scaling and
            bound). On an unstructured mesh (the frames' ``mesh``, a ``phantom.stl``) the
            mesh's rest bounding box is used instead (:mod:`core.learning.voxels`).
        network_config: network shape (default: the paper's 3D UNet).
        train_config: schedule (default :class:`TrainConfig`).
        callback: ``callback(fraction, message)`` after every batch; the message holds the
            epoch and the latest epoch losses in mm.

    Returns:
        :class:`TrainResult`.

    Raises:
        LearningError: no usable train or validation frame, or frames of different grids
            or meshes.
    """
    network_config = network_config or NetworkConfig()
    cfg = train_config or TrainConfig()
    t_setup = time.perf_counter()
    frames = list(frames.values())
    grids = {s.grid for s in frames}
    if len(grids) != 1:
        raise LearningError(f"all sequences must share one node grid, got {sorted(grids)}")
    grid = grids.pop()
    meshes = [s.mesh for s in frames if s.unstructured]
    mesh = meshes[0] if meshes else None
    if any(not same_mesh(mesh, s.mesh) for s in frames):
        raise LearningError("all sequences must share one mesh (same phantom, grid and element size)")
    train = [s for s in frames if s.role == "train"]
    if cfg.frame_stride > 1:
        k = int(cfg.frame_stride)
        train = [replace(s, times=s.times[::k], positions=s.positions[::k], poses=s.poses[::k], clouds=s.clouds[::k])
                 for s in train]
    val = [s for s in frames if s.role == "validation"]
    if not train:
        raise LearningError("no 'train' sequence to learn from (roles come from session.json)")
    if not val:
        raise LearningError("no 'validation' sequence for early stopping (roles come from session.json)")
    with torch_settings(cfg.threads, cfg.deterministic):
        torch.manual_seed(cfg.seed)
        net = build_network(network_config, grid, size, mesh)
        gen = torch.Generator().manual_seed(cfg.seed + 1)
        tr, va = FrameSet(train), FrameSet(val)
        lm = _LossModel(grid if mesh is None else mesh, cfg.supersample, net.corrected_nodes)
        val_gen = torch.Generator().manual_seed(cfg.seed + 2)
        val_samples = [
            va.sample_points(torch.arange(b0, min(b0 + cfg.batch_size, len(va))), cfg.max_points, val_gen)
            for b0 in range(0, len(va), cfg.batch_size)
        ]
        opt = torch.optim.Adam(net.parameters(), lr=cfg.learning_rate)
        net.eval()
        base_val = _evaluate(net, va, lm, val_samples, cfg.batch_size, correct=False)
        best_val, best_state, best_epoch = _evaluate(net, va, lm, val_samples, cfg.batch_size, correct=True), None, 0
        best_state = copy.deepcopy(net.state_dict())
        history: list[dict] = []
        base_train_sum, base_train_n = 0.0, 0
        n_batches = (len(tr) + cfg.batch_size - 1) // cfg.batch_size
        setup = time.perf_counter() - t_setup
        t_train = time.perf_counter()
        stopped = False
        last = ""
        for epoch in range(1, cfg.max_epochs + 1):
            t_ep = time.perf_counter()
            net.train()
            order = torch.randperm(len(tr), generator=gen)
            loss_sum, loss_n = 0.0, 0
            for b in range(n_batches):
                idx = order[b * cfg.batch_size : (b + 1) * cfg.batch_size]
                pts, mask = tr.sample_points(idx, cfg.max_points, gen)
                pos = tr.positions[idx]
                corr = net(pos, tr.poses[idx])
                loss = chamfer_loss(pts, mask, lm.surface(pos, corr))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                k = int(mask.sum())
                loss_sum += float(loss.detach()) * k
                loss_n += k
                if epoch == 1:
                    with torch.no_grad():
                        base_train_sum += float(chamfer_loss(pts, mask, lm.surface(pos, None))) * k
                        base_train_n += k
                if callback is not None:
                    callback(((epoch - 1) + (b + 1) / n_batches) / cfg.max_epochs,
                             f"epoch {epoch}/{cfg.max_epochs} batch {b + 1}/{n_batches} {last}")
            net.eval()
            val_loss = _evaluate(net, va, lm, val_samples, cfg.batch_size, correct=True)
            row = {"epoch": epoch, "train_loss": loss_sum / max(loss_n, 1), "validation_loss": val_loss,
                   "seconds": time.perf_counter() - t_ep}
            history.append(row)
            last = f"train {row['train_loss'] * 1e3:.4f} mm, val {val_loss * 1e3:.4f} mm (no net {base_val * 1e3:.4f})"
            if val_loss < best_val:
                best_val, best_epoch = val_loss, epoch
                best_state = copy.deepcopy(net.state_dict())
            if callback is not None:
                callback(epoch / cfg.max_epochs, f"epoch {epoch}/{cfg.max_epochs} {last}")
            if epoch - best_epoch >= cfg.patience:
                stopped = epoch < cfg.max_epochs
                break
        net.load_state_dict(best_state)
        net.eval()
        train_time = time.perf_counter() - t_train
    if callback is not None:
        callback(1.0, f"best epoch {best_epoch}: val {best_val * 1e3:.4f} mm (no net {base_val * 1e3:.4f})")
    return TrainResult(
        network=net,
        network_config=network_config,
        train_config=cfg,
        history=history,
        best_epoch=best_epoch,
        stopped_early=stopped,
        baseline={"train": base_train_sum / max(base_train_n, 1), "validation": base_val},
        n_frames={"train": len(tr), "validation": len(va)},
        timings={"setup": setup, "train": train_time, "per_epoch": train_time / max(len(history), 1)},
    )
