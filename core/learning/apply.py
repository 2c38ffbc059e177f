"""Using a trained correction: the correction field, offline corrected trajectories and
the in-loop replay (Wu et al. 2020, Sec. 3.3, "during test time").

*Offline*: the network corrects the positions of an ordinary replay frame by frame;
the simulation never sees the correction.

*In-loop* (the paper's use): at the end of each camera frame the simulator passes the
mesh to the network and continues from the corrected top layer; the other nodes stay
as the simulator computes them. This goes through the ``frame_hook`` of
:func:`core.simulation.solver.simulate`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from core.learning.checkpoint import Checkpoint, load_checkpoint
from core.learning.config import LearningError
from core.learning.data import SequenceFrames, frames_from_replay, probe_poses, top_layer_nodes

__all__ = ["CorrectedSequence", "correction_field", "correct_offline", "replay_in_loop", "mean_error"]


def _as_checkpoint(checkpoint) -> Checkpoint:
    return checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)


def _field(net, positions: np.ndarray, poses: np.ndarray, batch: int = 256) -> np.ndarray:
    """(F, T, 3) float64 corrections, NaN for frames with non-finite positions."""
    F = positions.shape[0]
    T = int(np.prod(net.grid[:2]))
    out = np.full((F, T, 3), np.nan)
    ok = np.flatnonzero(np.isfinite(positions).all(axis=(1, 2)))
    with torch.no_grad():
        for b0 in range(0, ok.size, batch):
            idx = ok[b0 : b0 + batch]
            c = net(torch.tensor(positions[idx], dtype=torch.float32), torch.tensor(poses[idx], dtype=torch.float32))
            out[idx] = c.double().numpy()
    return out


def correction_field(checkpoint, replay, *, prepared=None, config=None) -> np.ndarray:
    """The network's per-frame correction of the top-layer nodes of a replay.

    Args:
        checkpoint: a checkpoint path or a loaded :class:`Checkpoint`.
        replay: :class:`SequenceFrames` (from :func:`core.learning.build_frames`), or a
            :class:`core.simulation.replay.SequenceReplay` together with the
            ``prepared`` session it ran on and its ``config`` (for the robot poses).

    Returns:
        (F, nx*ny, 3) float64 corrections, m, phantom frame, for the top-layer nodes in
        (i, j) grid order (node indices :func:`core.learning.top_layer_nodes`); NaN rows
        for frames whose simulation diverged. Each component is within half the voxel
        length of its axis.

    Raises:
        LearningError: a replay on another grid than the network's, or a
            ``SequenceReplay`` without ``prepared``/``config``.
    """
    ck = _as_checkpoint(checkpoint)
    if not isinstance(replay, SequenceFrames):
        if prepared is None or config is None:
            raise LearningError("correction_field needs prepared= and config= to read the robot poses of a SequenceReplay")
        replay = frames_from_replay(prepared, replay, config)
    if tuple(replay.grid) != tuple(ck.grid):
        raise LearningError(f"replay grid {replay.grid} differs from the network's {ck.grid}")
    return _field(ck.network, replay.positions, replay.poses)


def mean_error(positions: np.ndarray, clouds, grid, factor: int = 3) -> tuple[float, np.ndarray, int]:
    """The paper's error of a trajectory: mean distance (m) from every measured point to
    the nearest vertex of the ``factor``x super-sampled mesh, over all frames.

    Returns:
        (mean m or NaN when any frame is non-finite, (F,) per-frame means m, number of points).
    """
    from core.simulation.replay import frame_errors

    per_frame, dists = frame_errors(positions, tuple(grid), clouds, factor)
    d = np.concatenate(dists) if dists else np.zeros(0)
    mean = float(d.mean()) if d.size and np.all(np.isfinite(d)) else float("nan")
    return mean, per_frame, int(d.size)


@dataclass(frozen=True)
class CorrectedSequence:
    """A corrected trajectory of one sequence and its error.

    Attributes:
        name, role: sequence identity.
        mode: "offline" or "in_loop".
        positions: (F, N, 3) float64 corrected node positions, m, phantom frame.
        corrections: (F, nx*ny, 3) float64 the network's top-layer corrections, m.
        frame_errors: (F,) m. mean_error: m over all points (NaN if diverged).
        n_points: measured points scored. status: "ok" or "diverged".
        seconds: wall time of the correction (offline) or of the whole replay (in-loop).
        inference_seconds: wall time spent in the network.
    """

    name: str
    role: str
    mode: str
    positions: np.ndarray
    corrections: np.ndarray
    frame_errors: np.ndarray
    mean_error: float
    n_points: int
    status: str
    seconds: float
    inference_seconds: float

    def save(self, path) -> None:
        """Write an npz: ``positions`` (F, N, 3) m phantom frame, ``corrections`` (F, T, 3) m
        of the top-layer nodes (:func:`core.learning.top_layer_nodes` order),
        ``frame_errors`` (F,) m and ``n_nodes``."""
        grid_n = self.positions.shape[1]
        np.savez_compressed(path, positions=self.positions, corrections=self.corrections,
                            frame_errors=self.frame_errors, n_nodes=np.int64(grid_n))


def correct_offline(checkpoint, frames: SequenceFrames, *, factor: int = 3) -> CorrectedSequence:
    """Correct an ordinary replay frame by frame (the simulation never sees the correction).

    Args:
        checkpoint: path or :class:`Checkpoint`.
        frames: the replay's per-frame arrays (same grid as the network).

    Returns:
        :class:`CorrectedSequence` with mode "offline".
    """
    ck = _as_checkpoint(checkpoint)
    t0 = time.perf_counter()
    field = correction_field(ck, frames)
    t_inf = time.perf_counter() - t0
    pos = frames.positions.copy()
    pos[:, top_layer_nodes(frames.grid)] += field
    err, per_frame, n = mean_error(pos, frames.clouds, frames.grid, factor)
    return CorrectedSequence(
        name=frames.name, role=frames.role, mode="offline", positions=pos, corrections=field,
        frame_errors=per_frame, mean_error=err, n_points=n, status=frames.status,
        seconds=time.perf_counter() - t0, inference_seconds=t_inf,
    )


def replay_in_loop(checkpoint, prepared, name: str, *, config=None, session=None, callback=None) -> CorrectedSequence:
    """Replay one sequence with the correction applied at the end of every camera frame.

    Args:
        checkpoint: path or :class:`Checkpoint`.
        prepared: :class:`core.simulation.replay.PreparedSession` holding sequence ``name``.
        config: the :class:`ReplayConfig` to simulate with (default: the checkpoint's, i.e.
            the E the network was trained on).
        session: optional read :class:`core.io.Session` (for the tool orientations).
        callback: ``callback(fraction, message)`` of the simulation.

    Returns:
        :class:`CorrectedSequence` with mode "in_loop"; the positions are the corrected
        ones the simulation continued from.

    Raises:
        LearningError: unknown sequence or a config grid other than the network's.
    """
    from core.simulation.replay import build_replay_model
    from core.simulation.solver import simulate

    ck = _as_checkpoint(checkpoint)
    config = config or ck.replay_config()
    if tuple(config.grid) != tuple(ck.grid):
        raise LearningError(f"replay grid {tuple(config.grid)} differs from the network's {ck.grid}")
    if name not in prepared.sequences:
        raise LearningError(f"{prepared.path}: no prepared sequence {name!r}; it has {list(prepared.sequences)}")
    seq = prepared.sequences[name]
    poses = torch.tensor(probe_poses(prepared, name, seq.frame_times, session), dtype=torch.float32)
    top = top_layer_nodes(config.grid)
    corrections = np.full((seq.frame_times.size, top.size, 3), np.nan)
    t_inf = [0.0]
    net = ck.network

    def hook(j: int, t: float, x: np.ndarray):
        t1 = time.perf_counter()
        with torch.no_grad():
            c = net(torch.tensor(x[None], dtype=torch.float32), poses[j : j + 1])[0].double().numpy()
        t_inf[0] += time.perf_counter() - t1
        corrections[j] = c
        x[top] += c
        return x

    t0 = time.perf_counter()
    model = build_replay_model(prepared, config)
    sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times, callback=callback, frame_hook=hook)
    err, per_frame, n = mean_error(sim.positions, seq.clouds, config.grid, config.supersample)
    if not sim.ok:
        err = float("nan")
    return CorrectedSequence(
        name=name, role=seq.role, mode="in_loop", positions=sim.positions, corrections=corrections,
        frame_errors=per_frame, mean_error=err, n_points=n, status=sim.status,
        seconds=time.perf_counter() - t0, inference_seconds=t_inf[0],
    )
