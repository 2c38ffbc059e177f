"""Replay a prepared session: simulate, measure the paper's error.

This is the pipeline of Wu et al. 2020 (Sec. 3.2-3.3): the robot's probe path drives the
FEM, and the mean distance from the cleaned clouds to the super-sampled mesh is the
error. Preparation (calibration, cleaning, cache) is the stage before
(:mod:`core.preparation`), done once per session for every replay, sweep and fit.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.io import Session
from core.preparation import Calibration, PreparedSession, prepare_session, release_pages
from core.simulation.effects import Effect
from core.simulation.mesh import TetMesh
from core.simulation.meshing import phantom_mesh
from core.simulation.metrics import point_to_mesh_distances, supersampled_surface
from core.simulation.model import Material, SimulationConfig, build_model
from core.simulation.solver import SimulationResult, simulate

__all__ = [
    "ReplayConfig",
    "SequenceReplay",
    "ReplayResult",
    "build_replay_model",
    "frame_errors",
    "noise_floor",
    "replay_sequence",
    "replay",
    "write_replay",
]

Callback = Callable[[float, str], None]


@dataclass(frozen=True)
class ReplayConfig:
    """What to replay and how.

    Attributes:
        youngs_modulus: E of the replay model, Pa (default: the paper's identified 5e3).
        poisson_ratio: nu (default 0.44; the paper takes 0.4-0.5 from the literature).
        grid: node grid (nx, ny, nz) of a box phantom; the paper's is (13, 5, 5).
        element_size: target element size of a phantom given by ``phantom.stl``, m
            (:func:`core.simulation.meshing.tetrahedralise`; None: about the paper's node
            count). Unused for a box.
        law: material law, "corotational" (the paper's), "stable_neo_hookean" or
            "stable_yeoh" (see ``Material``).
        stiffening: the Yeoh coefficient of "stable_yeoh" (dimensionless, >= 0).
        simulation: numerical settings of the FEM.
        effects: model options beyond the base model (see ``core.simulation.effects``).
        sequences: names to replay; None replays all.
        voxel_size: voxel downsampling of cleaned clouds, m (0 disables).
        max_points: random subsample of each cleaned cloud (None keeps all).
        supersample: mesh super-sampling factor of the error (paper: 3).
        path_smoothing: the calibrated probe path is low-passed by a Gaussian kernel of
            this many seconds (:meth:`ProbePath.smoothed`; 0 keeps the raw kinematics).
    """

    youngs_modulus: float = 5000.0
    poisson_ratio: float = 0.44
    grid: tuple[int, int, int] = (13, 5, 5)
    element_size: float | None = None
    law: str = "corotational"
    stiffening: float = 0.0
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    effects: tuple[Effect, ...] = ()
    sequences: tuple[str, ...] | None = None
    voxel_size: float = 0.001
    max_points: int | None = None
    supersample: int = 3
    path_smoothing: float = 0.01


@dataclass(frozen=True)
class SequenceReplay:
    """Replay of one sequence.

    Attributes:
        name, role: sequence identity.
        status: "ok" or "diverged" (the paper's "N/A").
        message: the divergence reason, "" when ok.
        frame_times: (F,) s.
        frame_errors: (F,) mean point-to-mesh distance per frame, m (NaN after divergence).
        mean_error: mean over all measured points of all frames, m (NaN if diverged).
        simulation: the raw :class:`SimulationResult` (node trajectories etc.).
    """

    name: str
    role: str
    status: str
    message: str
    frame_times: np.ndarray
    frame_errors: np.ndarray
    mean_error: float
    simulation: SimulationResult


@dataclass(frozen=True)
class ReplayResult:
    """Replay of a session: per-sequence results, calibration and stage timings (s)."""

    session: Path
    config: ReplayConfig
    calibration: Calibration
    sequences: dict[str, SequenceReplay]
    timings: dict[str, float]
    noise_floor: float = float("nan")
    mesh: TetMesh | None = None

    def to_json(self) -> dict:
        return {
            "session": str(self.session),
            "youngs_modulus": self.config.youngs_modulus,
            "poisson_ratio": self.config.poisson_ratio,
            "grid": list(self.config.grid),
            **({"mesh": {"kind": "stl", "nodes": self.mesh.n_nodes, "tets": self.mesh.n_tets,
                         "element_size": self.config.element_size}}
               if self.mesh is not None and self.mesh.grid is None else {}),
            "effects": [e.to_dict() for e in self.config.effects],
            "sequences": {
                name: {
                    "role": s.role,
                    "mean_error": None if not np.isfinite(s.mean_error) else float(s.mean_error),
                    "frames": int(s.frame_times.size),
                    "status": s.status,
                    **({"message": s.message} if s.message else {}),
                }
                for name, s in self.sequences.items()
            },
            "calibration": self.calibration.to_json(),
            "noise_floor": None if not np.isfinite(self.noise_floor) else float(self.noise_floor),
            "timings": {k: float(v) for k, v in self.timings.items()},
        }


def replay_mesh(prepared: PreparedSession, grid=(13, 5, 5), element_size: float | None = None) -> TetMesh:
    """The replay's mesh of ``prepared``'s phantom: the box grid of the session's size, or
    its ``phantom.stl`` filled with tetrahedra (:func:`core.simulation.meshing.phantom_mesh`).

    Raises:
        SimulationError: a bad grid. MeshingError: a bad STL."""
    return phantom_mesh(prepared.size, prepared.stl_path, grid=grid, element_size=element_size)


def noise_floor(prepared: PreparedSession, grid=(13, 5, 5), factor: int = 3, *,
                mesh: TetMesh | None = None) -> float:
    """Error of a perfect model, estimated from the data: the mean distance (m) from the
    measured points of rest frames (:meth:`PreparedSession.rest_frames`) to the
    super-sampled rest mesh. It holds the sensor noise, the registration residual and the
    super-sampling spacing. Falls back to the cleaned reference cloud when no sequence has
    a rest frame; NaN when neither exists. ``mesh`` (default: :func:`replay_mesh` of
    ``grid``) is the rest mesh."""
    mesh = replay_mesh(prepared, grid) if mesh is None else mesh
    surface = supersampled_surface(mesh.nodes, mesh, factor)
    # frame by frame (a paper-size session has thousands of rest frames: gathering their
    # points first held ~9 GB), the mean over every point
    total, count = 0.0, 0
    for n in prepared.sequences:
        clouds = prepared.sequences[n].clouds
        for i in prepared.rest_frames(n):
            pts = np.asarray(clouds[i], dtype=np.float64)
            if pts.shape[0]:
                total += float(point_to_mesh_distances(pts, surface).sum())
                count += pts.shape[0]
        release_pages(clouds)
    if count == 0 and prepared.reference is not None and prepared.reference.shape[0]:
        return float(point_to_mesh_distances(np.asarray(prepared.reference, dtype=np.float64), surface).mean())
    return total / count if count else float("nan")


RELEASE_FRAMES = 64
""":func:`frame_errors` releases mapped clouds' pages every this many frames: one pass over
a paper-size sequence otherwise leaves all of its ~0.3 GB resident in the process (every 64
frames of 45k points: ~35 MB at most; a page released is read back from the page cache)."""


def frame_errors(positions: np.ndarray, grid, clouds: Sequence[np.ndarray], factor: int = 3, *,
                 distances: bool = True):
    """Per-frame mean and per-point distances from clouds to the super-sampled mesh.

    Args:
        positions: (F, N, 3) node positions, m. grid: (nx, ny, nz), or the
            :class:`TetMesh` of any phantom (:func:`core.simulation.metrics.surface_operator`).
        clouds: F arrays (M_f, 3) of measured points, m, same frame.
        distances: keep the per-point distances (False: only the per-frame means, so a
            paper-size sequence of 3600 frames does not hold ~1 GB of float64 distances).
            Memory-mapped clouds have their pages released every :data:`RELEASE_FRAMES`.

    Returns:
        (frame_mean (F,) m, distances: list of (M_f,) arrays in m, or None without
        ``distances``). Frames with non-finite positions get NaN.
    """
    means = np.full(len(clouds), np.nan)
    dists = [] if distances else None
    for f, pts in enumerate(clouds):
        if f and f % RELEASE_FRAMES == 0:
            release_pages(clouds)
        if not np.all(np.isfinite(positions[f])) or pts.shape[0] == 0:
            if distances:
                dists.append(np.full(pts.shape[0], np.nan))
            continue
        d = point_to_mesh_distances(pts, supersampled_surface(positions[f], grid, factor))
        means[f] = d.mean()
        if distances:
            dists.append(d)
    return means, dists


def replay_sequence(
    prepared: PreparedSession,
    name: str,
    config: ReplayConfig,
    *,
    model=None,
    callback: Callback | None = None,
    paper_error: bool = True,
) -> SequenceReplay:
    """Simulate one prepared sequence and measure its error (a fresh model unless given).

    ``paper_error`` False skips the paper's metric (frame errors and mean error NaN) for
    callers that score the simulation otherwise (the E fit's top-face residual)."""
    seq = prepared.sequences[name]
    if model is None:
        model = build_replay_model(prepared, config)
    sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times, callback=callback)
    if paper_error:
        errs, _ = frame_errors(sim.positions, model.mesh, seq.clouds, config.supersample, distances=False)
    else:
        errs = np.full(len(seq.clouds), np.nan)
    # the mean over every point of the sequence, from the frames' means and point counts
    counts = np.array([c.shape[0] for c in seq.clouds])
    seen = counts > 0
    if sim.ok and seen.any():
        mean = float(np.dot(errs[seen], counts[seen]) / counts[seen].sum())
    else:
        mean = float("nan")
    return SequenceReplay(
        name=name,
        role=seq.role,
        status=sim.status,
        message=sim.message,
        frame_times=seq.frame_times,
        frame_errors=errs,
        mean_error=mean,
        simulation=sim,
    )


def build_replay_model(prepared: PreparedSession, config: ReplayConfig, *, factorize: bool = True):
    """The FEM model of ``config`` for the phantom of ``prepared`` (the box of the
    session's size, or its ``phantom.stl``: :func:`replay_mesh`); ``factorize`` as
    :func:`core.simulation.build_model`'s."""
    mesh = replay_mesh(prepared, config.grid, config.element_size)
    return build_model(
        mesh,
        prepared.mass,
        Material(config.youngs_modulus, config.poisson_ratio, config.law, stiffening=config.stiffening),
        config.simulation,
        config.effects,
        factorize=factorize,
    )


def replay(
    session: Session | str | Path,
    config: ReplayConfig | None = None,
    *,
    prepared: PreparedSession | None = None,
    callback: Callback | None = None,
) -> ReplayResult:
    """Replay every selected sequence of a session and measure the paper's error.

    Args:
        session: a session folder (or read :class:`Session`).
        config: what to replay (defaults: E = 5e3 Pa, 13x5x5, paper's damping).
        prepared: reuse an earlier preparation (calibration + cleaned clouds).
        callback: ``callback(fraction, message)``.

    Raises:
        SessionFormatError, RegistrationError, CleaningError, SimulationError: bad
        input, failed registration, or bad parameters. A diverging simulation is not
        an error: its sequence has status "diverged".
    """
    config = config or ReplayConfig()
    if prepared is None:
        prepared = prepare_session(session, config, callback=_scaled(callback, 0.0, 0.3))
    timings = dict(prepared.timings)
    names = list(prepared.sequences) if config.sequences is None else list(config.sequences)
    t0 = time.perf_counter()
    model = build_replay_model(prepared, config)
    results = {}
    sim_time = 0.0
    err_time = 0.0
    for i, name in enumerate(names):
        sub = _scaled(callback, 0.3 + 0.7 * i / len(names), 0.3 + 0.7 * (i + 1) / len(names))
        r = replay_sequence(prepared, name, config, model=model, callback=sub)
        release_pages(prepared.sequences[name].clouds)  # done with them (mapped ones leave the resident set)
        sim_time += r.simulation.wall_time
        results[name] = r
    err_time = time.perf_counter() - t0 - sim_time
    timings["simulate"] = sim_time
    timings["error"] = err_time
    return ReplayResult(
        session=prepared.path,
        config=config,
        calibration=prepared.calibration,
        sequences=results,
        timings=timings,
        noise_floor=noise_floor(prepared, config.grid, config.supersample, mesh=model.mesh),
        mesh=model.mesh,
    )


def _scaled(callback: Callback | None, lo: float, hi: float) -> Callback | None:
    if callback is None:
        return None
    return lambda f, msg: callback(lo + (hi - lo) * f, msg)


def _mesh_arrays(mesh: TetMesh | None) -> dict:
    if mesh is None:
        return {}
    out = {"surface_triangles": np.asarray(mesh.surface_triangles)}
    if mesh.grid is None:
        out.update(rest_nodes=np.asarray(mesh.nodes), tets=np.asarray(mesh.tets))
    return out


def write_replay(result: ReplayResult, out: str | Path) -> Path:
    """Write ``replay.json``, ``<sequence>.npz`` (node trajectories, probe path, forces,
    per-frame errors) and ``frame_errors.csv`` into ``out``.

    The npz holds: ``times`` (F,) s, ``positions`` (F, N, 3) m phantom frame,
    ``frame_errors`` (F,) m, ``probe_centres`` (F, 3) m, ``contact_force`` (F, 3) N,
    ``grid`` (3,) (the box grid; ignored for an STL phantom), ``surface_triangles``
    (T, 3) int64 of the replayed mesh and, for an STL phantom, ``rest_nodes`` (N, 3) m
    and ``tets`` (E, 4). Returns the folder.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = ["sequence,frame,t,mean_error"]
    for name, s in result.sequences.items():
        np.savez_compressed(
            out / f"{name}.npz",
            times=s.frame_times,
            positions=s.simulation.positions,
            frame_errors=s.frame_errors,
            probe_centres=s.simulation.probe_centres,
            contact_force=s.simulation.contact_force,
            grid=np.asarray(result.config.grid),
            **_mesh_arrays(result.mesh),
        )
        rows += [f"{name},{i},{t:.6f},{e:.9g}" for i, (t, e) in enumerate(zip(s.frame_times, s.frame_errors))]
    (out / "frame_errors.csv").write_text("\n".join(rows) + "\n")
    tmp = out / "replay.json.tmp"
    tmp.write_text(json.dumps(result.to_json(), indent=2))
    tmp.replace(out / "replay.json")
    return out
