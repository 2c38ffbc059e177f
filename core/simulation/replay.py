"""Replay a recorded session: calibrate, clean the clouds, simulate, measure.

This is the pipeline of Wu et al. 2020 (Sec. 3.2-3.3): corner touches register the
robot to the phantom, ICP registers the camera, the robot's probe path drives the
FEM, and the mean distance from the cleaned clouds to the super-sampled mesh is the
error. Preparation (calibration and cleaning) is separated from simulation so that
sweeps and fits (many simulations of the same data) prepare once.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.errors import SessionFormatError
from core.io import Session, read_picked, read_session
from core.registration import calibrate_camera, calibrate_robot, clean_cloud, instrument_hints, probe_pose_phantom
from core.simulation.effects import Effect
from core.simulation.mesh import box_mesh
from core.simulation.metrics import point_to_mesh_distances, supersampled_surface
from core.simulation.model import Material, SimulationConfig, build_model
from core.simulation.probe import ProbePath
from core.simulation.solver import SimulationResult, simulate

__all__ = [
    "ReplayConfig",
    "Calibration",
    "PreparedSequence",
    "PreparedSession",
    "SequenceReplay",
    "ReplayResult",
    "calibrate",
    "prepare_session",
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
        grid: node grid (nx, ny, nz); the paper's is (13, 5, 5).
        law: material law, "corotational" (the paper's) or "stable_neo_hookean".
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
    law: str = "corotational"
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    effects: tuple[Effect, ...] = ()
    sequences: tuple[str, ...] | None = None
    voxel_size: float = 0.001
    max_points: int | None = None
    supersample: int = 3
    path_smoothing: float = 0.01


@dataclass(frozen=True)
class Calibration:
    """Registration results with their residuals.

    Attributes:
        T_phantom_robot: (4, 4) robot base -> phantom (Kabsch on corner touches).
        T_phantom_camera: (4, 4) camera -> phantom (point-to-plane ICP).
        robot_rms: corner-touch residual RMS, m.
        camera_rms: ICP inlier RMS, m.
        camera_fitness: ICP inlier fraction.
        probe_sigma: standard error of the calibrated probe's vertical position over the
            top face, m, from the corner-touch residuals: per-axis touch noise
            ``sigma^2 = sum(r^2) / (3 N - 6)`` (6 rigid degrees of freedom), propagated
            through the Kabsch fit as ``sigma^2 / N`` at the touches' centroid plus the
            tilt term, 1/3 of that averaged over the face. NaN when unknown.
    """

    T_phantom_robot: np.ndarray
    T_phantom_camera: np.ndarray
    robot_rms: float
    camera_rms: float
    camera_fitness: float
    probe_sigma: float = float("nan")

    def to_json(self) -> dict:
        return {
            "T_phantom_robot": self.T_phantom_robot.tolist(),
            "T_phantom_camera": self.T_phantom_camera.tolist(),
            "robot_rms": float(self.robot_rms),
            "camera_rms": float(self.camera_rms),
            "camera_fitness": float(self.camera_fitness),
            "probe_sigma": float(self.probe_sigma),
        }


@dataclass(frozen=True)
class PreparedSequence:
    """A sequence ready to simulate, everything in the phantom frame.

    Attributes:
        name, role: from session.json.
        frame_times: (F,) camera frame times, s.
        probe: the calibrated probe path (sphere centres, phantom frame).
        clouds: F arrays (M_f, 3) of cleaned measured points, m, phantom frame.
        force: (K, 3) measured probe force in the phantom frame (N) at ``probe.t``, or None.
    """

    name: str
    role: str
    frame_times: np.ndarray
    probe: ProbePath
    clouds: tuple[np.ndarray, ...]
    force: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(sum(c.shape[0] for c in self.clouds))

    def force_at(self, times) -> np.ndarray | None:
        """(M, 3) measured probe force (N, phantom frame) interpolated at ``times`` (s), or None."""
        if self.force is None:
            return None
        times = np.asarray(times, dtype=np.float64)
        return np.stack([np.interp(times, self.probe.t, self.force[:, i]) for i in range(3)], axis=1)


@dataclass(frozen=True)
class PreparedSession:
    """Calibration plus prepared sequences of one session (reused across many simulations)."""

    path: Path
    size: np.ndarray
    mass: float
    probe_radius: float
    calibration: Calibration
    sequences: dict[str, PreparedSequence]
    timings: dict[str, float]
    reference: np.ndarray | None = None

    def rest_frames(self, name: str, *, settle: float = 1.0, clearance: float = 0.002) -> np.ndarray:
        """Indices of frames of sequence ``name`` where the phantom is at rest: the probe
        has been at least ``clearance`` (m) clear of the box for the last ``settle`` s."""
        seq = self.sequences[name]
        lag = np.linspace(0.0, settle, 11)
        times = (seq.frame_times[:, None] - lag[None, :]).ravel()
        c = seq.probe.at(times)
        outside = np.maximum(np.maximum(-c, c - self.size), 0.0)
        clear = np.linalg.norm(outside, axis=1) > self.probe_radius + clearance
        return np.flatnonzero(clear.reshape(-1, lag.size).all(axis=1))

    def noise_floor(self, grid=(13, 5, 5), factor: int = 3) -> float:
        """Error of a perfect model, estimated from the data: the mean distance (m)
        from the measured points of rest frames (see :meth:`rest_frames`) to the
        super-sampled rest mesh. It holds the sensor noise, the registration residual
        and the super-sampling spacing. Falls back to the cleaned reference cloud when
        no sequence has a rest frame; NaN when neither exists."""
        surface = supersampled_surface(box_mesh(self.size, grid).nodes, grid, factor)
        points = [self.sequences[n].clouds[i] for n in self.sequences for i in self.rest_frames(n)]
        if not points and self.reference is not None and self.reference.shape[0]:
            points = [self.reference]
        if not points:
            return float("nan")
        return float(point_to_mesh_distances(np.concatenate(points), surface).mean())


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

    def to_json(self) -> dict:
        return {
            "session": str(self.session),
            "youngs_modulus": self.config.youngs_modulus,
            "poisson_ratio": self.config.poisson_ratio,
            "grid": list(self.config.grid),
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


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def calibrate(session: Session, *, picked=None) -> Calibration:
    """Register robot and camera to the phantom frame.

    Args:
        session: a read session.
        picked: optional (points_camera (K, 3), points_phantom (K, 3)), K >= 3, to
            initialise ICP from picked point pairs instead of automatically. When None,
            pairs accepted in the workbench (``calibration/picked.json``) are used if
            the session has them.

    Raises:
        RegistrationError: a registration that does not fit.
        SessionFormatError: a malformed ``calibration/picked.json``.
    """
    meta = session.meta
    if picked is None:
        picked = read_picked(session.path)
    robot = calibrate_robot(session.corners, meta.phantom.size, meta.probe.radius)
    reference = session.reference_cloud()
    hints = []
    for seq in list(session.sequences.values())[:2]:
        n = len(seq)
        hints += instrument_hints(seq, robot.T, sorted({0, n // 4, n // 2}))
    if reference is None:
        first = next(iter(session.sequences.values()))
        reference = first.cloud(0)
    camera = calibrate_camera(
        reference,
        meta.phantom.size,
        probe_radius=meta.probe.radius,
        picked=picked,
        hints=hints,
        stl_path=session.phantom_stl,
    )
    return Calibration(
        T_phantom_robot=robot.T,
        T_phantom_camera=camera.T,
        robot_rms=float(robot.rms),
        camera_rms=float(camera.rms),
        camera_fitness=float(camera.fitness),
        probe_sigma=_probe_sigma(robot.residuals),
    )


def _probe_sigma(residuals: np.ndarray) -> float:
    """Standard error (m) of the calibrated probe height (see ``Calibration.probe_sigma``)."""
    n = int(np.asarray(residuals).size)
    if n < 3:
        return float("nan")
    sigma2 = float(np.sum(np.asarray(residuals) ** 2)) / max(3 * n - 6, 1)
    return float(np.sqrt(sigma2 / n * 4.0 / 3.0))


def _prepare_sequence(session: Session, name: str, cal: Calibration, config: ReplayConfig) -> PreparedSequence:
    seq = session.sequences[name]
    kin = seq.kinematics
    Tpr = cal.T_phantom_robot
    path = ProbePath(kin.t, _transform(Tpr, kin.position)).smoothed(config.path_smoothing)
    frame_t = seq.frames.t
    centres_f, axes_f = probe_pose_phantom(kin, frame_t, Tpr)  # axes: tool z, shaft -> tip
    clouds = []
    for i in range(len(seq)):
        res = clean_cloud(
            seq.cloud(i),
            cal.T_phantom_camera,
            session.meta.phantom.size,
            probe_centre_phantom=centres_f[i],
            shaft_axis_phantom=axes_f[i],
            probe_radius=session.meta.probe.radius,
            voxel_size=config.voxel_size,
            max_points=config.max_points,
            seed=i,
        )
        clouds.append(res.points_phantom)
    force = None if kin.force is None else kin.force @ Tpr[:3, :3].T
    return PreparedSequence(name=name, role=seq.role, frame_times=frame_t, probe=path, clouds=tuple(clouds), force=force)


def prepare_session(
    session: Session | str | Path,
    config: ReplayConfig | None = None,
    *,
    calibration: Calibration | None = None,
    picked=None,
    callback: Callback | None = None,
) -> PreparedSession:
    """Read (if a path), calibrate (unless given) and clean every selected sequence.

    Raises:
        SessionFormatError: bad input files, or unknown sequence names.
        RegistrationError: a registration that does not fit.
        CleaningError: a frame with nothing of the phantom left.
    """
    config = config or ReplayConfig()
    timings = {}
    t0 = time.perf_counter()
    if not isinstance(session, Session):
        session = read_session(session)
    timings["load"] = time.perf_counter() - t0
    names = list(session.sequences) if config.sequences is None else list(config.sequences)
    unknown = [n for n in names if n not in session.sequences]
    if unknown:
        raise SessionFormatError(session.path / "session.json", f"no sequence(s) named {unknown}; it has {list(session.sequences)}")
    t0 = time.perf_counter()
    if callback:
        callback(0.0, "calibrating")
    cal = calibration or calibrate(session, picked=picked)
    timings["calibrate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    prepared = {}
    for i, name in enumerate(names):
        if callback:
            callback(i / max(len(names), 1), f"cleaning {name}")
        prepared[name] = _prepare_sequence(session, name, cal, config)
    reference = session.reference_cloud()
    reference_phantom = None
    if reference is not None:
        reference_phantom = clean_cloud(
            reference, cal.T_phantom_camera, session.meta.phantom.size, voxel_size=config.voxel_size
        ).points_phantom
    timings["clean"] = time.perf_counter() - t0
    meta = session.meta
    return PreparedSession(
        path=Path(session.path),
        size=np.asarray(meta.phantom.size, dtype=np.float64),
        mass=float(meta.phantom.mass),
        probe_radius=float(meta.probe.radius),
        calibration=cal,
        sequences=prepared,
        timings=timings,
        reference=reference_phantom,
    )


def frame_errors(positions: np.ndarray, grid, clouds: Sequence[np.ndarray], factor: int = 3):
    """Per-frame mean and per-point distances from clouds to the super-sampled mesh.

    Args:
        positions: (F, N, 3) node positions, m. grid: (nx, ny, nz).
        clouds: F arrays (M_f, 3) of measured points, m, same frame.

    Returns:
        (frame_mean (F,) m, distances: list of (M_f,) arrays in m). Frames with
        non-finite positions get NaN.
    """
    means = np.full(len(clouds), np.nan)
    dists = []
    for f, pts in enumerate(clouds):
        if not np.all(np.isfinite(positions[f])) or pts.shape[0] == 0:
            dists.append(np.full(pts.shape[0], np.nan))
            continue
        d = point_to_mesh_distances(pts, supersampled_surface(positions[f], grid, factor))
        means[f] = d.mean()
        dists.append(d)
    return means, dists


def replay_sequence(
    prepared: PreparedSession,
    name: str,
    config: ReplayConfig,
    *,
    model=None,
    callback: Callback | None = None,
) -> SequenceReplay:
    """Simulate one prepared sequence and measure its error (a fresh model unless given)."""
    seq = prepared.sequences[name]
    if model is None:
        model = build_replay_model(prepared, config)
    sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times, callback=callback)
    errs, dists = frame_errors(sim.positions, config.grid, seq.clouds, config.supersample)
    if sim.ok:
        mean = float(np.concatenate(dists).mean()) if dists else float("nan")
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
    """The FEM model of ``config`` for the phantom of ``prepared`` (box of session size);
    ``factorize`` as :func:`core.simulation.build_model`'s."""
    mesh = box_mesh(prepared.size, config.grid)
    return build_model(
        mesh,
        prepared.mass,
        Material(config.youngs_modulus, config.poisson_ratio, config.law),
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
        noise_floor=prepared.noise_floor(config.grid, config.supersample),
    )


def _scaled(callback: Callback | None, lo: float, hi: float) -> Callback | None:
    if callback is None:
        return None
    return lambda f, msg: callback(lo + (hi - lo) * f, msg)


def write_replay(result: ReplayResult, out: str | Path) -> Path:
    """Write ``replay.json``, ``<sequence>.npz`` (node trajectories, probe path, forces,
    per-frame errors) and ``frame_errors.csv`` into ``out``.

    The npz holds: ``times`` (F,) s, ``positions`` (F, N, 3) m phantom frame,
    ``frame_errors`` (F,) m, ``probe_centres`` (F, 3) m, ``contact_force`` (F, 3) N,
    ``grid`` (3,). Returns the folder.
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
        )
        rows += [f"{name},{i},{t:.6f},{e:.9g}" for i, (t, e) in enumerate(zip(s.frame_times, s.frame_errors))]
    (out / "frame_errors.csv").write_text("\n".join(rows) + "\n")
    tmp = out / "replay.json.tmp"
    tmp.write_text(json.dumps(result.to_json(), indent=2))
    tmp.replace(out / "replay.json")
    return out
