"""Using a trained correction: the correction field, offline corrected trajectories and
the in-loop replay (Wu et al. 2020, Sec. 3.3, "during test time").

*Offline*: the network corrects the positions of an ordinary replay frame by frame;
the simulation never sees the correction.

*In-loop* (the paper's use): at the end of each camera frame the simulator's top layer
is corrected and the simulation continues from the corrected state; the other nodes
stay as the simulator computes them. This goes through the ``frame_hook`` of
:func:`core.simulation.solver.simulate`.

What a correction means in the loop. The network is trained on plain (uncorrected)
simulations: for the plain state ``s_j`` it outputs ``c(s_j)`` such that ``s_j + c(s_j)``
matches the camera. So ``c`` is the *total* offset of the observed layer from the
simulator's own prediction, bounded by half a voxel. Adding ``c`` to the running state
at every frame (mode ``"additive"``) treats it as an *increment* instead: whatever of
the earlier corrections the FEM has not yet relaxed is still in the state, and the new
one is stacked on top. Measured on the ``small`` gravity session at 15 Hz (a 2D net,
E 5x too soft): one correction decays to 0.54 of itself after one frame (0.28, 0.14, ...
after; the Rayleigh stiffness damping beta = 0.1 s against a 67 ms frame), so a steady
correction accumulates to about 1/(1 - 0.54) ~ 2x itself: 4.2 mm per frame became a
standing 8.5 mm lift, twice the 4.5 mm bound, while the network's output on the
corrected states differed from its output on the plain ones by only 2-4 %. The input
shift is therefore not the cause; the stacking is. Beyond the bound, nodes can cross
(the very thing the paper's bound prevents) and on the demo session runs diverged.

Mode ``"anchored"`` (the default) keeps the trained meaning: a shadow plain replay
(the ``reference``; its frames are the ones the network was trained on) gives ``s_j``,
the network sees ``s_j``, and the top layer of the continued state is *set* to
``s_j + c(s_j)`` at frame j (the hook adds ``s_j + c_j - x_j`` to it). The FEM still
continues from the corrected state between frames, so the unobserved nodes follow the
corrected surface, but the observed layer never drifts further than the bound from the
simulator's prediction, whatever the relaxation rate. Applying only the change
``c_j - c_{j-1}`` was rejected by the same measurement: it assumes the state keeps the
last correction, but the FEM relaxes 46 % of it per frame, so a steady correction
would fade to nothing.

The unobserved nodes follow the correction elastically (fixed here; measured on the
``small`` gravity session, seed 3, test sequence, E = 1 kPa, a steady target offset c on
every frame). Setting only the top layer to its target put the whole of each frame's
jump into the one layer of elements under it: a 4 mm step against a 9 mm layer is a
45 % strain, applied anew every frame. Those elements inverted (smallest det F / det F0
-0.18 for c = (0, 0, 4) mm, -11.8 for c = (2, 3, 4) mm), and the corotational law has no
restoring force against inversion, so the layers below settled in spurious places: the
nodes the network does not set ended 20.7 mm and 37.8 mm from the plain replay, and
c = (0, 0, -4) mm diverged. Velocities were not the cause (keeping the plain replay's
top-layer velocity, or zeroing it, left 30-39 mm for c = (2, 3, 4) mm), nor the
warm-started polar iteration (10 iterations per force evaluation: 22 mm, then a
divergence). The held-top static solution of the same model
moves the layers below by at most 3.7 mm for these offsets.

So with every reset the other free nodes move by the simulator's own static response to
the change of the top layer, ``du_o = -K_oo^-1 K_ot du_t`` with the rest stiffness K of
the model (plus its supports), i.e. where the body would put them if the top layer were
displaced slowly; the dynamics then continue from that state. With it the same offsets
leave the other nodes within 2.2-4.3 mm of the plain replay (E = 1 and 5 kPa, two
sequences, offsets of 4 mm up, down and sideways; smallest det ratio 0.64-0.69 where
measured) and no run diverges. :func:`replay_in_loop` reports the largest such offset of a
run as ``max_unobserved_offset``.

On an unstructured mesh (a ``phantom.stl``) "the top layer" above is the network's
``corrected_nodes``, the surface nodes above z = 0 (:mod:`core.learning.voxels`); the
other free nodes (the interior) follow them the same way.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from core.learning.checkpoint import Checkpoint, load_checkpoint
from core.learning.config import LearningError
from core.learning.data import SequenceFrames, frames_from_replay, probe_poses, same_mesh

__all__ = ["CorrectedSequence", "correction_field", "correct_offline", "replay_in_loop", "mean_error", "signed_residual",
           "elastic_extension", "IN_LOOP_MODES"]


def _as_checkpoint(checkpoint) -> Checkpoint:
    return checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)


def _field(net, positions: np.ndarray, poses: np.ndarray, batch: int = 256) -> np.ndarray:
    """(F, K, 3) float64 corrections of ``net.corrected_nodes``, NaN for frames with
    non-finite positions."""
    F = positions.shape[0]
    T = int(net.corrected_nodes.size)
    out = np.full((F, T, 3), np.nan)
    ok = np.flatnonzero(np.isfinite(positions).all(axis=(1, 2)))
    with torch.no_grad():
        for b0 in range(0, ok.size, batch):
            idx = ok[b0 : b0 + batch]
            c = net(torch.tensor(positions[idx], dtype=torch.float32), torch.tensor(poses[idx], dtype=torch.float32))
            out[idx] = c.double().numpy()
    return out


def _check_mesh(ck: Checkpoint, grid, mesh, what: str = "replay") -> None:
    """Raise LearningError unless a replay on ``grid`` / ``mesh`` is what ``ck``'s network corrects."""
    if tuple(grid) != tuple(ck.grid):
        raise LearningError(f"{what} grid {tuple(grid)} differs from the network's {ck.grid}")
    if not same_mesh(ck.mesh, mesh):
        def describe(m):
            return "the box grid" if m is None or m.grid is not None else f"a {m.n_nodes}-node mesh"
        raise LearningError(f"{what} mesh ({describe(mesh)}) is not the one the network was trained on "
                            f"({describe(ck.mesh)}): same phantom.stl, element size and Gmsh needed")


def correction_field(checkpoint, replay, *, prepared=None, config=None) -> np.ndarray:
    """The network's per-frame correction of the observed nodes of a replay.

    Args:
        checkpoint: a checkpoint path or a loaded :class:`Checkpoint`.
        replay: :class:`SequenceFrames` (from :func:`core.learning.build_frames`), or a
            :class:`core.simulation.replay.SequenceReplay` together with the
            ``prepared`` session it ran on and its ``config`` (for the robot poses).

    Returns:
        (F, K, 3) float64 corrections, m, phantom frame, of the nodes
        ``checkpoint.network.corrected_nodes``: on the box grid the top layer in (i, j)
        grid order (K = nx*ny, :func:`core.learning.top_layer_nodes`), on an unstructured
        mesh its surface nodes above z = 0 (:func:`core.learning.voxels.corrected_nodes`).
        NaN rows for frames whose simulation diverged. Each component is within half the
        voxel length of its axis.

    Raises:
        LearningError: a replay on another grid or mesh than the network's, or a
            ``SequenceReplay`` without ``prepared``/``config``.
    """
    ck = _as_checkpoint(checkpoint)
    if not isinstance(replay, SequenceFrames):
        if prepared is None or config is None:
            raise LearningError("correction_field needs prepared= and config= to read the robot poses of a SequenceReplay")
        replay = frames_from_replay(prepared, replay, config)
    _check_mesh(ck, replay.grid, replay.mesh)
    return _field(ck.network, replay.positions, replay.poses)


def mean_error(positions: np.ndarray, clouds, grid, factor: int = 3) -> tuple[float, np.ndarray, int]:
    """The paper's error of a trajectory: mean distance (m) from every measured point to
    the nearest vertex of the ``factor``x super-sampled mesh, over all frames.

    ``grid`` is the box's (nx, ny, nz) or any :class:`TetMesh`
    (:func:`core.simulation.metrics.surface_operator`).

    Returns:
        (mean m or NaN when any frame is non-finite, (F,) per-frame means m, number of points).
    """
    from core.simulation.replay import frame_errors
    per_frame, dists = frame_errors(positions, grid if hasattr(grid, "nodes") else tuple(grid), clouds, factor)
    d = np.concatenate(dists) if dists else np.zeros(0)
    mean = float(d.mean()) if d.size and np.all(np.isfinite(d)) else float("nan")
    return mean, per_frame, int(d.size)


def signed_residual(positions: np.ndarray, clouds, grid, size) -> tuple[float, int]:
    """Mean signed vertical residual of a trajectory over the top face's interior.

    The paper's error is unsigned and, under ~1 mm of noise, rewards a top surface that
    sits slightly high (points near the top's edges find nearer side-face vertices);
    this says whether a gain is shape or bias. It reuses the identification's residual
    (:func:`core.identification.residuals.top_residuals`: measured z minus the bilinear
    top-layer height at the point, points >= 4 mm inside the top face's edges).

    Args:
        positions: (F, N, 3) node positions, m, phantom frame, grid-major order.
        clouds: F arrays (M_f, 3) of measured points, m, phantom frame.
        grid: (nx, ny, nz), or a :class:`TetMesh`. size: (3,) box size, m.

    Returns:
        (mean residual in m, NaN when a frame is non-finite or no point is kept; number
        of points kept). Positive: the measured top lies above the model's. (NaN, 0) on
        an unstructured mesh: the residual is defined over the box's flat top face.
    """
    from core.identification.residuals import top_residuals

    if hasattr(grid, "nodes"):
        if grid.grid is None:
            return float("nan"), 0
        grid = grid.grid

    size = np.asarray(size, dtype=np.float64).reshape(3)
    total, n = 0.0, 0
    for x, cloud in zip(positions, clouds):
        if cloud.shape[0] == 0:
            continue
        if not np.all(np.isfinite(x)):
            return float("nan"), 0
        r = top_residuals(cloud, x, tuple(grid), size)
        total += float(r.sum())
        n += int(r.size)
    return (total / n if n else float("nan")), n


def elastic_extension(model, nodes: np.ndarray):
    """The model's static response of its other free nodes to moving ``nodes``.

    ``du_o = -K_oo^-1 K_ot du_t`` with the rest stiffness K of ``model`` plus its
    support springs (what :func:`core.simulation.solver.static_equilibrium` linearises):
    where the body puts the other nodes when ``nodes`` are displaced slowly by ``du_t``.

    Args:
        model: a :class:`core.simulation.Model`.
        nodes: (T,) int indices of the displaced nodes (e.g. the top layer).

    Returns:
        (others, extend): ``others`` (O,) int64 free node indices not in ``nodes``, and
        ``extend(du_t (T, 3) m) -> du_o (O, 3) m``. The factorisation is done once.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    nodes = np.asarray(nodes, dtype=np.int64)
    others = np.setdiff1d(np.flatnonzero(model.free), nodes)
    K = (model.K + sp.diags(np.repeat(model.support_stiffness, 3))).tocsr()
    td = (3 * nodes[:, None] + np.arange(3)).ravel()
    od = (3 * others[:, None] + np.arange(3)).ravel()
    lu = spla.splu(K[od][:, od].tocsc())
    K_ot = K[od][:, td].tocsr()

    def extend(du_t: np.ndarray) -> np.ndarray:
        return -lu.solve(K_ot @ np.asarray(du_t, dtype=np.float64).ravel()).reshape(-1, 3)

    return others, extend


@dataclass(frozen=True)
class CorrectedSequence:
    """A corrected trajectory of one sequence and its error.

    Attributes:
        name, role: sequence identity.
        mode: "offline" or "in_loop".
        positions: (F, N, 3) float64 corrected node positions, m, phantom frame.
        corrections: (F, K, 3) float64 the network's corrections of ``corrected_nodes``, m.
        frame_errors: (F,) m. mean_error: m over all points (NaN if diverged).
        n_points: measured points scored. status: "ok" or "diverged".
        seconds: wall time of the correction (offline) or of the whole replay (in-loop).
        inference_seconds: wall time spent in the network.
        signed_residual: mean signed vertical residual over the top face's interior, m
            (:func:`signed_residual`; positive: the measured top lies above the mesh).
        n_signed: points in it.
        max_unobserved_offset: largest distance (m, any axis, any frame) of a node the
            network does not set from the plain replay: 0 offline by construction; in
            the loop how far the body followed the corrected top layer (NaN when unknown).
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
    signed_residual: float = float("nan")
    n_signed: int = 0
    max_unobserved_offset: float = float("nan")
    corrected_nodes: np.ndarray | None = None

    def save(self, path) -> None:
        """Write an npz: ``positions`` (F, N, 3) m phantom frame, ``corrections`` (F, K, 3) m
        of the nodes ``corrected_nodes`` (K,) int64 (on the box grid the top layer in
        :func:`core.learning.top_layer_nodes` order), ``frame_errors`` (F,) m and ``n_nodes``."""
        grid_n = self.positions.shape[1]
        extra = {} if self.corrected_nodes is None else {"corrected_nodes": np.asarray(self.corrected_nodes, dtype=np.int64)}
        np.savez_compressed(path, positions=self.positions, corrections=self.corrections,
                            frame_errors=self.frame_errors, n_nodes=np.int64(grid_n), **extra)


def correct_offline(checkpoint, frames: SequenceFrames, *, factor: int = 3, size=None) -> CorrectedSequence:
    """Correct an ordinary replay frame by frame (the simulation never sees the correction).

    Args:
        checkpoint: path or :class:`Checkpoint`.
        frames: the replay's per-frame arrays (same grid and mesh as the network).
        factor: mesh super-sampling of the error.
        size: (3,) box size, m, for the signed residual (default: the network's).

    Returns:
        :class:`CorrectedSequence` with mode "offline".
    """
    ck = _as_checkpoint(checkpoint)
    t0 = time.perf_counter()
    field = correction_field(ck, frames)
    t_inf = time.perf_counter() - t0
    pos = frames.positions.copy()
    nodes = ck.network.corrected_nodes
    pos[:, nodes] += field
    err, per_frame, n = mean_error(pos, frames.clouds, frames.mesh_or_grid, factor)
    size = ck.network.size.double().numpy() if size is None else size
    signed, n_signed = signed_residual(pos, frames.clouds, frames.mesh_or_grid, size)
    return CorrectedSequence(
        name=frames.name, role=frames.role, mode="offline", positions=pos, corrections=field,
        frame_errors=per_frame, mean_error=err, n_points=n, status=frames.status,
        seconds=time.perf_counter() - t0, inference_seconds=t_inf,
        signed_residual=signed, n_signed=n_signed, max_unobserved_offset=0.0, corrected_nodes=nodes,
    )


IN_LOOP_MODES = ("anchored", "additive")
"""How :func:`replay_in_loop` applies the correction (see the module docstring)."""


def replay_in_loop(checkpoint, prepared, name: str, *, config=None, session=None, callback=None,
                   reference: SequenceFrames | None = None, mode: str = "anchored") -> CorrectedSequence:
    """Replay one sequence with the correction applied at the end of every camera frame.

    Args:
        checkpoint: path or :class:`Checkpoint`.
        prepared: :class:`core.simulation.replay.PreparedSession` holding sequence ``name``.
        config: the :class:`ReplayConfig` to simulate with (default: the checkpoint's, i.e.
            the E the network was trained on).
        session: optional read :class:`core.io.Session` (for the tool orientations).
        callback: ``callback(fraction, message)`` of the simulation.
        reference: the plain (uncorrected) replay of this sequence with ``config``, i.e.
            the shadow simulation of mode ``"anchored"`` (e.g. ``build_frames(...)[name]``);
            replayed here when None. Unused by mode ``"additive"``.
        mode: ``"anchored"`` (default): the network sees the plain frame ``s_j``, the
            continued state's top layer is set to ``s_j + c(s_j)``, so it stays within
            the bound of the plain replay, and the other free nodes move by the model's
            static response to that change (:func:`elastic_extension`). ``"additive"``: the network sees the running
            (already corrected) state ``x_j`` and ``c(x_j)`` is added to it; corrections
            that the FEM has not relaxed pile up (kept to measure that; see the module
            docstring).

    Returns:
        :class:`CorrectedSequence` with mode "in_loop"; the positions are the corrected
        ones the simulation continued from; ``corrections`` are the network's outputs;
        ``max_unobserved_offset`` compares the other nodes with the plain replay
        (anchored mode; NaN in additive mode).

    The corrected nodes are ``checkpoint.network.corrected_nodes``: the top layer on the
    box grid, the surface nodes above z = 0 on an unstructured mesh (what the network
    outputs); every other free node is "unobserved" and follows elastically.

    Raises:
        LearningError: unknown sequence or mode, a config grid or mesh other than the
            network's, or a ``reference`` of another sequence, grid, mesh, E or frame count.
        MeshingError: the session's ``phantom.stl`` cannot be meshed.
    """
    from core.simulation.replay import build_replay_model
    from core.simulation.solver import simulate

    if mode not in IN_LOOP_MODES:
        raise LearningError(f"mode must be one of {IN_LOOP_MODES}, got {mode!r}")
    ck = _as_checkpoint(checkpoint)
    config = config or ck.replay_config()
    if tuple(config.grid) != tuple(ck.grid):
        raise LearningError(f"replay grid {tuple(config.grid)} differs from the network's {ck.grid}")
    if name not in prepared.sequences:
        raise LearningError(f"{prepared.path}: no prepared sequence {name!r}; it has {list(prepared.sequences)}")
    seq = prepared.sequences[name]
    n_frames = seq.frame_times.size
    net = ck.network
    top = net.corrected_nodes
    t_inf = [0.0]
    t0 = time.perf_counter()
    model = build_replay_model(prepared, config)
    _check_mesh(ck, config.grid, model.mesh)
    surface = model.mesh if model.mesh.grid is None else tuple(config.grid)

    if mode == "anchored":
        if reference is None:  # the shadow plain replay (deterministic, so it can run first)
            plain = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times)
            reference = SequenceFrames(
                name=name, role=seq.role, times=np.asarray(seq.frame_times, dtype=np.float64),
                positions=np.asarray(plain.positions, dtype=np.float64),
                poses=probe_poses(prepared, name, seq.frame_times, session), clouds=tuple(seq.clouds),
                grid=tuple(int(g) for g in config.grid), youngs_modulus=float(config.youngs_modulus),
                status=plain.status, mesh=model.mesh)
        if (reference.name != name or tuple(reference.grid) != tuple(config.grid) or reference.n_frames != n_frames
                or reference.positions.shape[1] != model.mesh.n_nodes or not same_mesh(reference.mesh, model.mesh)
                or not math.isclose(reference.youngs_modulus, float(config.youngs_modulus), rel_tol=1e-12)):
            raise LearningError(
                f"reference must be the plain replay of {name!r} on grid {tuple(config.grid)} at E = "
                f"{config.youngs_modulus:g} Pa with {n_frames} frames, got {reference.name!r} on {tuple(reference.grid)} "
                f"at E = {reference.youngs_modulus:g} Pa with {reference.n_frames} frames")
        t1 = time.perf_counter()
        corrections = _field(net, reference.positions, reference.poses)
        t_inf[0] += time.perf_counter() - t1
        target = reference.positions[:, top] + corrections  # (F, T, 3) m; NaN where the plain replay diverged
        others, extend = elastic_extension(model, top)

        def hook(j: int, t: float, x: np.ndarray):
            if not np.all(np.isfinite(target[j])):
                return None  # no plain frame to anchor to: leave the simulator's state alone
            # the top layer is set; the body follows it statically (a top-only jump inverted
            # the element layer under it: see the module docstring)
            x[others] += extend(target[j] - x[top])
            x[top] = target[j]
            return x
    else:
        poses = torch.tensor(probe_poses(prepared, name, seq.frame_times, session), dtype=torch.float32)
        corrections = np.full((n_frames, top.size, 3), np.nan)

        def hook(j: int, t: float, x: np.ndarray):
            t1 = time.perf_counter()
            with torch.no_grad():
                c = net(torch.tensor(x[None], dtype=torch.float32), poses[j : j + 1])[0].double().numpy()
            t_inf[0] += time.perf_counter() - t1
            corrections[j] = c
            x[top] += c
            return x

    sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times, callback=callback, frame_hook=hook)
    err, per_frame, n = mean_error(sim.positions, seq.clouds, surface, config.supersample)
    signed, n_signed = signed_residual(sim.positions, seq.clouds, surface, prepared.size)
    if not sim.ok:
        err = signed = float("nan")
    drift = float("nan")
    if mode == "anchored" and sim.ok:
        rest = np.setdiff1d(np.arange(sim.positions.shape[1]), top)
        d = np.abs(sim.positions[:, rest] - reference.positions[:, rest])
        drift = float(np.nanmax(d)) if np.any(np.isfinite(d)) else float("nan")
    return CorrectedSequence(
        name=name, role=seq.role, mode="in_loop", positions=sim.positions, corrections=corrections,
        frame_errors=per_frame, mean_error=err, n_points=n, status=sim.status,
        seconds=time.perf_counter() - t0, inference_seconds=t_inf[0],
        signed_residual=signed, n_signed=n_signed, max_unobserved_offset=drift, corrected_nodes=top,
    )
