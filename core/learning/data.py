"""Per-frame training data: simulated node positions, robot pose, measured cloud.

Wu et al. 2020 (Sec. 3.3) train on "pre-calculated FEM-simulated phantom mesh vertex
positions" with the robot pose of the same frame, and compare the corrected mesh with
the depth cloud of that frame. :func:`build_frames` replays every sequence of a
prepared session at one Young's modulus and returns exactly those arrays per frame, so
that training, evaluation and later explanations of the correction field share one
data pipeline. Each sequence carries the replay's mesh (the box grid, or the session's
``phantom.stl`` filled by Gmsh), which the network's voxel map is built from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from core.learning.config import LearningError
from core.learning.voxels import top_layer_nodes

if TYPE_CHECKING:
    from core.simulation.mesh import TetMesh

__all__ = ["SequenceFrames", "frames_from_replay", "build_frames", "probe_poses", "top_layer_nodes", "same_mesh"]

Callback = Callable[[float, str], None]


def same_mesh(a: TetMesh | None, b: TetMesh | None) -> bool:
    """Whether two meshes (None: "the box grid") are the same for the learned correction:
    both grids (or None) on the same grid, or both unstructured with the same tetrahedra
    and rest nodes within 1 nm (node order matters: a network's scatter and gather are
    tied to it)."""
    ua, ub = a is not None and a.grid is None, b is not None and b.grid is None
    if not ua and not ub:
        return a is None or b is None or tuple(a.grid) == tuple(b.grid)
    if ua != ub:
        return False
    return a is b or (a.nodes.shape == b.nodes.shape and a.tets.shape == b.tets.shape and np.array_equal(a.tets, b.tets)
                      and np.allclose(a.nodes, b.nodes, rtol=0, atol=1e-9))


@dataclass(frozen=True)
class SequenceFrames:
    """The arrays of one sequence that the correction network sees and is scored on.

    Attributes:
        name, role: sequence identity ("train", "validation" or "test").
        times: (F,) float64 camera frame times, s.
        positions: (F, N, 3) float64 simulated node positions, m, phantom frame (NaN
            after a divergence), in the node order of ``mesh`` (grid-major on the box).
        poses: (F, 7) float64 robot pose per frame, phantom frame: probe sphere centre
            (m) then tool orientation quaternion x, y, z, w (scalar last, w >= 0).
        clouds: F arrays (M_f, 3) float64 of cleaned measured points, m, phantom frame.
        grid: (nx, ny, nz) the replay's grid (``ReplayConfig.grid``): the node grid of
            ``positions`` on the box, the voxel grid of the correction network on an
            unstructured mesh (:mod:`core.learning.voxels`).
        youngs_modulus: E of the simulation, Pa.
        status: "ok" or "diverged" (the simulation's status).
        mean_error: the replay's error without correction, m (NaN if diverged).
        mesh: the replayed :class:`core.simulation.mesh.TetMesh` (rest nodes, tets,
            surface); None means the box grid ``grid`` (callers from before meshes).
    """

    name: str
    role: str
    times: np.ndarray
    positions: np.ndarray
    poses: np.ndarray
    clouds: tuple[np.ndarray, ...]
    grid: tuple[int, int, int]
    youngs_modulus: float
    status: str = "ok"
    mean_error: float = float("nan")
    mesh: TetMesh | None = None

    def __post_init__(self):
        f = self.times.shape[0]
        if self.mesh is not None and self.mesh.grid is not None and tuple(self.mesh.grid) != tuple(self.grid):
            raise LearningError(f"sequence {self.name}: grid {tuple(self.grid)} but a grid mesh on {tuple(self.mesh.grid)}")
        n = int(np.prod(self.grid)) if self.mesh is None else self.mesh.n_nodes
        if self.positions.shape != (f, n, 3):
            raise LearningError(f"sequence {self.name}: positions must be ({f}, {n}, 3), got {self.positions.shape}")
        if self.poses.shape != (f, 7):
            raise LearningError(f"sequence {self.name}: poses must be ({f}, 7), got {self.poses.shape}")
        if len(self.clouds) != f:
            raise LearningError(f"sequence {self.name}: {len(self.clouds)} clouds for {f} frames")

    @property
    def unstructured(self) -> bool:
        """True when ``mesh`` is not a grid (a ``phantom.stl`` filled by Gmsh)."""
        return self.mesh is not None and self.mesh.grid is None

    @property
    def mesh_or_grid(self):
        """What the paper's metric super-samples (:func:`core.simulation.metrics.surface_operator`):
        the unstructured ``mesh``, else the grid tuple."""
        return self.mesh if self.unstructured else tuple(int(g) for g in self.grid)

    @property
    def n_frames(self) -> int:
        return int(self.times.shape[0])

    @property
    def finite(self) -> np.ndarray:
        """(F,) bool: frames with finite positions and at least one measured point."""
        ok = np.isfinite(self.positions).all(axis=(1, 2))
        return ok & np.array([c.shape[0] > 0 for c in self.clouds], dtype=bool)


def probe_poses(prepared, name: str, times: np.ndarray, session=None) -> np.ndarray:
    """(F, 7) robot pose at ``times`` in the phantom frame: probe centre (m, from the
    calibrated probe path) and tool orientation (xyzw, w >= 0; Slerp of the recorded
    quaternions rotated by ``T_phantom_robot``).

    Args:
        prepared: a :class:`core.simulation.replay.PreparedSession`.
        name: sequence name. times: (F,) s.
        session: the read :class:`core.io.Session` (read from ``prepared.path`` if None).

    Raises:
        SessionFormatError: the session folder cannot be read.
    """
    from scipy.spatial.transform import Rotation, Slerp

    from core.io import read_session

    times = np.asarray(times, dtype=np.float64).reshape(-1)
    centres = prepared.sequences[name].probe.at(times)
    if session is None:
        session = read_session(prepared.path)
    kin = session.sequences[name].kinematics
    kt = np.asarray(kin.t, dtype=np.float64)
    tq = np.clip(times, kt[0], kt[-1])
    if kt.size >= 2:
        rot = Slerp(kt, Rotation.from_quat(np.asarray(kin.quaternion)))(tq)
    else:
        rot = Rotation.from_quat(np.repeat(np.asarray(kin.quaternion)[:1], tq.size, axis=0))
    R_phantom_robot = Rotation.from_matrix(prepared.calibration.T_phantom_robot[:3, :3])
    q = (R_phantom_robot * rot).as_quat()
    q = np.where(q[:, 3:4] < 0, -q, q)
    return np.concatenate([centres, q], axis=1)


def frames_from_replay(prepared, replay, config, *, session=None, mesh=None) -> SequenceFrames:
    """The per-frame arrays of one replayed sequence.

    Args:
        prepared: the :class:`PreparedSession` the replay was run on.
        replay: a :class:`core.simulation.replay.SequenceReplay` of one of its sequences.
        config: the :class:`core.simulation.replay.ReplayConfig` it was run with (grid,
            element size, E).
        session: optional read :class:`core.io.Session` (saves re-reading the kinematics).
        mesh: the replay's :class:`TetMesh` (``ReplayResult.mesh`` or the model's); default
            :func:`core.simulation.replay.replay_mesh` of ``prepared`` and ``config``.

    Returns:
        :class:`SequenceFrames` with the replay's positions (F, N, 3) m and its mesh.

    Raises:
        LearningError: positions that do not fit the mesh.
        MeshingError: the session's ``phantom.stl`` cannot be meshed (when ``mesh`` is None).
    """
    if mesh is None:
        from core.simulation.replay import replay_mesh

        mesh = replay_mesh(prepared, config.grid, config.element_size)
    seq = prepared.sequences[replay.name]
    return SequenceFrames(
        name=replay.name,
        role=seq.role,
        times=np.asarray(seq.frame_times, dtype=np.float64),
        positions=np.asarray(replay.simulation.positions, dtype=np.float64),
        poses=probe_poses(prepared, replay.name, seq.frame_times, session),
        clouds=tuple(seq.clouds),
        grid=tuple(int(g) for g in config.grid),
        youngs_modulus=float(config.youngs_modulus),
        status=replay.status,
        mean_error=float(replay.mean_error),
        mesh=mesh,
    )


def build_frames(
    prepared,
    config,
    *,
    names: list[str] | None = None,
    session=None,
    callback: Callback | None = None,
) -> dict[str, SequenceFrames]:
    """Replay sequences of a prepared session at ``config.youngs_modulus`` and collect
    the per-frame arrays the network trains and is tested on.

    Args:
        prepared: :class:`core.simulation.replay.PreparedSession` (calibrated, cleaned).
        config: :class:`core.simulation.replay.ReplayConfig` (E, grid, effects, numerics).
        names: sequences to replay (default: all prepared sequences).
        session: optional read :class:`core.io.Session` for the kinematics' orientations.
        callback: ``callback(fraction, message)``.

    Returns:
        {name: :class:`SequenceFrames`} in session order, each holding the replay's mesh
        (the box grid, or the session's ``phantom.stl`` meshed at ``config.element_size``).
        A diverged simulation is kept
        (status "diverged", NaN positions after the divergence), not raised.

    Raises:
        LearningError: an unknown sequence name.
        SimulationError: bad simulation parameters. MeshingError: a bad ``phantom.stl``.
    """
    from core.io import read_session
    from core.preparation import release_pages
    from core.simulation.replay import build_replay_model, replay_sequence
    names = list(prepared.sequences) if names is None else list(names)
    unknown = [n for n in names if n not in prepared.sequences]
    if unknown:
        raise LearningError(f"{prepared.path}: no prepared sequence(s) {unknown}; it has {list(prepared.sequences)}")
    if session is None:
        session = read_session(prepared.path)
    model = build_replay_model(prepared, config)
    out = {}
    for i, name in enumerate(names):
        sub = None
        if callback is not None:
            sub = (lambda i_: (lambda f, msg: callback((i_ + f) / len(names), f"{name}: {msg}")))(i)
        r = replay_sequence(prepared, name, config, model=model, callback=sub)
        out[name] = frames_from_replay(prepared, r, config, session=session, mesh=model.mesh)
        release_pages(prepared.sequences[name].clouds)  # done with them (mapped ones leave the resident set)
    if callback is not None:
        callback(1.0, "replayed")
    return out
