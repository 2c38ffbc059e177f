"""Virtual lab: synthetic recording sessions with a known truth.

Replays the experiment of Wu et al. 2020 (Sec. 4) in software: a dVRK PSM pokes the top
and the sides of a 68.7 x 39.3 x 35.8 mm, 104.01 g gel block; an SR300-like depth camera
records it at 30 Hz while the robot reports kinematics at ~1 kHz; a calibration touches
the four top corners. The phantom's deformation comes from a truth simulation that is
more faithful than the replay model (finer mesh, stable Neo-Hookean material, Smith et
al. 2018) plus any effect of ``SESSION_FORMAT.md`` that is switched on; with a
:class:`core.lab.variation.LabVariation` (the ``field`` preset) the truth's law, modulus,
mesh, contact, damping and noise levels are drawn per seed. The probe follows random
pokes, or given paths (``paths=``). The session is streamed to disk through
:class:`core.io.SessionWriter`, with ``truth.json``.

Frames: *phantom* (box ``[0, size]``, z up), *robot* (kinematics, corners, forces;
``T_phantom_robot`` maps robot points into the phantom frame) and *camera* (clouds;
OpenCV axes; ``T_phantom_camera`` maps camera points into the phantom frame).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from core.errors import TissueTwinError
from core.lab.camera import (
    DepthCamera,
    DepthNoise,
    Instrument,
    Intrinsics,
    apply_depth_noise,
    cast,
    depth_to_points,
    random_camera_pose,
    roi_for_box,
    table_mesh,
    table_ring_mask,
)
from core.lab.probing import ProbePlan, ProbingConfig, plan_from_path, plan_sequence
from core.lab.surface_probing import plan_surface_sequence
from core.lab.variation import LabVariation, apply_variation

__all__ = [
    "GENERATOR_NAME",
    "GENERATOR_VERSION",
    "PHANTOM_SIZE",
    "PHANTOM_MASS",
    "LabConfig",
    "LabError",
    "PRESETS",
    "PRESET_NOTES",
    "DEMO_EFFECTS",
    "PHYSICAL_EFFECTS",
    "INPUT_EFFECTS",
    "complete_effects",
    "generate_session",
]

GENERATOR_NAME = "tissuetwin-lab"
GENERATOR_VERSION = "0.1.0"
PHANTOM_SIZE = (0.0687, 0.0393, 0.0358)
"""Box size of the paper's phantom, m (x length, y width, z height; Wu et al. 2020, Sec. 4.1)."""
PHANTOM_MASS = 0.10401
"""Phantom mass, kg (104.01 g)."""
PHYSICAL_EFFECTS = ("gravity", "inclusion", "viscoelasticity", "friction", "base_compliance")
"""Effects that go into the truth FEM model."""
INPUT_EFFECTS = ("probe_radius", "time_offset", "kinematic_offset")
"""Effects the lab applies to the probe input and the written kinematics itself."""

ProgressCallback = Callable[[float, str], None]


class LabError(TissueTwinError, ValueError):
    """Bad generator input (unknown preset or effect, invalid parameter) or a failed
    truth simulation."""


@dataclass(frozen=True)
class LabConfig:
    """Everything that sets the size and fidelity of a synthetic session."""

    sequence_durations: tuple[float, ...]
    """Length of each sequence, s (one entry per sequence)."""
    sequence_roles: tuple[str, ...]
    """Role of each sequence: "train", "validation" or "test" (same length)."""
    camera_rate_hz: float = 30.0
    """Depth frame rate, Hz (SR300: 30 Hz)."""
    kinematics_rate_hz: float = 1000.0
    """Rate of kinematics.csv rows, Hz (dVRK: ~1 kHz)."""
    intrinsics: Intrinsics = Intrinsics.from_fov(640, 480, 68.0)
    """Nominal pinhole intrinsics (jittered per seed by ~0.5 %, 2 px). SR300 depth: 640 x 480, ~68 deg."""
    camera_distance_range: tuple[float, float] = (0.25, 0.35)
    """Distance of the camera from the phantom's top centre, m."""
    camera_tilt_range_deg: tuple[float, float] = (20.0, 45.0)
    """Angle of the optical axis from vertical, degrees."""
    roi_margin: float = 0.02
    """Rays are cast only into the image window covering the phantom plus this margin
    around it (and up to 2 cm above its top), m; the rest of the image stays empty."""
    table_margin: float = 0.01
    """Width of the ring of table kept around the phantom's footprint, m (the rest of the
    table is dropped to keep clouds small; the instrument is kept in the whole window)."""
    grid: tuple[int, int, int] = (19, 7, 7)
    """Nodes of the truth mesh along x, y, z (the replay model uses 13 x 5 x 5)."""
    dt: float = 0.005
    """Time step of the truth simulation, s."""
    newton_iterations: int = 2
    """Newton corrections per implicit-Euler step of the truth simulation."""
    youngs_modulus: float = 5000.0
    """Young's modulus of the truth material, Pa (Wu et al. 2020 identify 5e3 Pa)."""
    youngs_modulus_range: tuple[float, float] | None = None
    """If set, Young's modulus is drawn log-uniformly from this range per seed, Pa."""
    poisson_ratio: float = 0.44
    """Poisson's ratio of the truth material."""
    law: str = "stable_neo_hookean"
    """Material law of the truth simulation: "stable_neo_hookean" (Smith et al. 2018) or
    "stable_yeoh" (plus Yeoh-type strain stiffening, see ``core.simulation.Material``)."""
    stiffening: float = 0.0
    """Yeoh coefficient of the "stable_yeoh" law (dimensionless, >= 0; ignored otherwise)."""
    contact_stiffness_per_modulus: float = 2e5
    """Contact penalty of the truth simulation per unit area and per pascal of E, 1/m
    (``core.simulation.SimulationConfig.contact_stiffness_per_modulus``; 2e5 as the replay)."""
    rayleigh_mass: float = 0.1
    """Rayleigh damping on the mass matrix, 1/s (paper: 0.1)."""
    rayleigh_stiffness: float = 0.1
    """Rayleigh damping on the stiffness matrix, s (paper: 0.1)."""
    probe_radius: float = 0.005
    """Nominal probe radius written to session.json, m (paper: 5 mm sphere)."""
    probing: ProbingConfig = field(default_factory=ProbingConfig)
    """How pokes are drawn."""
    depth_noise: DepthNoise = field(default_factory=DepthNoise)
    """Depth-sensor imperfections."""
    depth_accuracy: float = 0.002
    """Depth accuracy written to session.json, m (Intel's SR300 figure)."""
    encoder_noise: float = 2e-5
    """Standard deviation of the kinematics' position noise per axis, m."""
    corner_noise: float = 3e-4
    """Standard deviation of a calibration touch per axis, m."""
    corner_touches: int = 3
    """Touches per corner in calibration/corners.csv."""
    frame_jitter: float = 0.001
    """Standard deviation of frame timestamps around the nominal camera clock, s."""
    force_noise: float = 0.01
    """Standard deviation of the written force per axis, N."""
    reference_frames: int = 5
    """Noisy frames averaged per pixel into calibration/reference.ply."""
    robot_distance_range: tuple[float, float] = (0.2, 0.5)
    """Distance of the robot base origin from the phantom, m."""
    workers: int = 1
    """Extra processes that run truth simulations ahead while the main process renders
    (0: everything in the main process)."""
    variation: LabVariation | None = None
    """If set, the truth's law, stiffening, E, nu, mesh, contact stiffness and damping
    and the depth- and force-noise levels are drawn per seed from these ranges (from a
    generator of their own, so poses, plans and noise streams stay those of the seed) and
    recorded in truth.json under "lab_variation"; they override the fields above
    (``youngs_modulus_range`` included). None: the fields above, as they are."""

    def with_duration(self, seconds: float) -> "LabConfig":
        """This lab with every sequence ``seconds`` long (its roles unchanged).

        Raises:
            LabError: ``seconds`` is not positive.
        """
        if not float(seconds) > 0:
            raise LabError(f"a sequence duration must be positive, got {seconds}")
        return replace(self, sequence_durations=(float(seconds),) * len(self.sequence_roles))


def _roles(n: int, n_val: int = 1, n_test: int = 2) -> tuple[str, ...]:
    return tuple(["validation"] * n_val + ["test"] * n_test + ["train"] * (n - n_val - n_test))


PRESETS: dict[str, LabConfig] = {
    "small": LabConfig(
        sequence_durations=(10.0,) * 4,
        sequence_roles=("validation", "test", "train", "train"),
        camera_rate_hz=15.0,
        kinematics_rate_hz=200.0,
        intrinsics=Intrinsics.from_fov(320, 240, 64.0),
        # truth as fine as the identification's refined grid (2 n - 1 of 13 x 5 x 5): a
        # coarser truth is itself stiffened by volumetric locking, so its nominal E would
        # not be the E a mesh-corrected fit should find
        grid=(25, 9, 9),
        dt=1.0 / 120.0,
        newton_iterations=1,
        reference_frames=3,
    ),
    "demo": LabConfig(
        sequence_durations=(10.0,) * 6,
        sequence_roles=_roles(6),
        camera_rate_hz=15.0,
        kinematics_rate_hz=500.0,
        intrinsics=Intrinsics.from_fov(480, 360, 68.0),
        dt=0.005,
    ),
    "paper": LabConfig(
        sequence_durations=(120.0,) + (60.0,) * 11,
        sequence_roles=_roles(12),
        camera_rate_hz=30.0,
        kinematics_rate_hz=1000.0,
        intrinsics=Intrinsics.from_fov(1280, 960, 61.0),
        table_margin=0.006,
        grid=(25, 10, 10),
        dt=0.005,
    ),
}
# a lab that is not our replay model: the small preset's sizes, its truth drawn per seed
PRESETS["field"] = replace(PRESETS["small"], variation=LabVariation())
PRESET_NOTES: dict[str, str] = {
    "small": "tests: 4 x 10 s (validation, test, 2 x train); camera 15 Hz at 320 x 240; kinematics "
             "200 Hz instead of the dVRK's 1 kHz to keep files small; truth 25 x 9 x 9 (the refined grid "
             "of mesh-corrected fits), dt 1/120 s with one Newton correction per step; ~3.4k raw "
             "points per frame (~2.3k on the phantom); ~20 s, ~26 MB",
    "demo": "README main command: 6 x 10 s (validation, 2 x test, 3 x train); camera 15 Hz at "
            "480 x 360; kinematics 500 Hz; truth dt 5 ms; ~6.4k raw points per frame (~4.5k on the "
            "phantom); ~12 s, ~75 MB (the demo command hides DEMO_EFFECTS in it, with force columns)",
    "field": "a lab that is not our replay model: the small preset's sizes (4 x 10 s; validation, test, "
             "2 x train; 320 x 240 at 15 Hz, kinematics 200 Hz) with the truth drawn per seed "
             "(LabVariation: stable neo-Hookean or strain-stiffening Yeoh law, E 3-15 kPa, nu "
             "0.42-0.48, 19 x 7 x 7 to 31 x 11 x 11 mesh, contact stiffness, damping, depth and "
             "force noise), random top and side palpation; ~15-40 s depending on the mesh drawn, ~25 MB",
    "paper": "Wu et al. 2020 scale: 12 sequences (2 min validation, 2 x 1 min test, 9 x 1 min train), "
             "camera 30 Hz at 1280 x 960 (~45k phantom points per frame, as the paper's subsampled "
             "clouds; 31k-57k depending on the seed's camera distance), kinematics 1 kHz, "
             "25 x 10 x 10 truth mesh; 14-16 min and 12 GB (measured 2026-11-26/27, seed 7, force columns)",
}
"""One line per preset: what it is for, its sizes and its cost on a 2-core machine."""

DEMO_EFFECTS: tuple[dict, ...] = (
    {"kind": "gravity", "g": [0.0, 0.0, -9.81]},
    {"kind": "kinematic_offset", "offset": [0.003, -0.002, -0.003]},
)
"""What ``tissuetwin demo`` hides in its demo session (``demo`` preset, seed 0, force
columns): the phantom's own weight, which the paper's model leaves out, and a robot
calibration error of (3, -2, -3) mm (4.7 mm; the dVRK's cable-driven arms are off by a few
millimetres). Measured on the 2-core machine: its diagnosis names both (offset fitted
(1.5, -1.3, -2.9) mm, E 4.8 kPa for the truth's 5 kPa) in 290 s and 798 simulations; on
seeds 1-4 of the same design it named gravity only (the offset "cannot tell")."""


# --------------------------------------------------------------------------------------
# effects
# --------------------------------------------------------------------------------------


def complete_effects(effects: Sequence[dict]) -> list[dict]:
    """Effects with every parameter filled in (defaults of :mod:`core.simulation.effects`),
    as JSON-ready dicts in the given order.

    Raises:
        LabError: not a dict, unknown kind or parameter, invalid value, or a kind twice.
    """
    from core.errors import SimulationError
    from core.simulation import effect_from_dict

    out = []
    seen = set()
    for d in effects:
        if not isinstance(d, dict):
            raise LabError(f"an effect must be a dict like {{'kind': 'gravity'}}, got {d!r}")
        try:
            full = effect_from_dict(d).to_dict()
        except SimulationError as exc:
            raise LabError(str(exc)) from exc
        if full["kind"] in seen:
            raise LabError(f"effect kind {full['kind']!r} given twice")
        seen.add(full["kind"])
        out.append(full)
    return out


# --------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (Shoemake 1992, from a uniform unit quaternion)."""
    from scipy.spatial.transform import Rotation

    q = rng.standard_normal(4)
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()


def _random_robot_pose(rng: np.random.Generator, distance_range) -> np.ndarray:
    """(4, 4) T_phantom_robot: a random rotation and a robot base ``distance_range`` m away."""
    R = _random_rotation(rng)
    d = rng.standard_normal(3)
    origin_phantom = d / np.linalg.norm(d) * rng.uniform(*distance_range)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = origin_phantom
    return T


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    return q if q[3] >= 0 else -q


# --------------------------------------------------------------------------------------
# truth simulation (picklable so it can run in a worker process)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _SimJob:
    mesh_spec: tuple
    """("grid", (nx, ny, nz), size) for the box, ("stl", path, element_size) otherwise."""
    mass: float
    youngs_modulus: float
    poisson_ratio: float
    law: str
    stiffening: float
    contact_stiffness_per_modulus: float
    dt: float
    newton_iterations: int
    rayleigh_mass: float
    rayleigh_stiffness: float
    physical_effects: tuple[dict, ...]
    path_t: np.ndarray
    path_centres: np.ndarray
    radius: float
    output_times: np.ndarray


def _truth_mesh(spec: tuple):
    """The truth's mesh of a ``_SimJob.mesh_spec`` (a box grid, or an STL filled by Gmsh;
    meshes are cached by content, so worker processes mesh an STL once)."""
    from core.simulation import box_mesh
    from core.simulation.meshing import tetrahedralise

    if spec[0] == "grid":
        return box_mesh(size=spec[2], grid=spec[1])
    return tetrahedralise(spec[1], spec[2])


def _build_model(job: _SimJob):
    from core.simulation import Material, SimulationConfig, build_model, effect_from_dict

    mesh = _truth_mesh(job.mesh_spec)
    return build_model(
        mesh,
        mass=job.mass,
        material=Material(youngs_modulus=job.youngs_modulus, poisson_ratio=job.poisson_ratio, law=job.law,
                          stiffening=job.stiffening),
        config=SimulationConfig(dt=job.dt, rayleigh_mass=job.rayleigh_mass,
                                rayleigh_stiffness=job.rayleigh_stiffness,
                                newton_iterations=job.newton_iterations,
                                contact_stiffness_per_modulus=job.contact_stiffness_per_modulus),
        effects=[effect_from_dict(d) for d in job.physical_effects],
    )


_MODEL_CACHE: dict = {}


TRUTH_RETRIES: tuple[tuple[int, int], ...] = ((3, 1), (3, 2), (5, 4))
"""(Newton iterations, dt divisor) tried in turn when a truth simulation diverges."""


def _run_sim(job: _SimJob, callback: ProgressCallback | None = None):
    """Run one truth simulation; returns (positions (F, N, 3) float32, contact force (F, 3),
    status, message, wall time)."""
    from core.simulation import ProbePath, simulate

    key = (job.mesh_spec, job.mass, job.youngs_modulus, job.poisson_ratio, job.law, job.stiffening,
           job.contact_stiffness_per_modulus, job.dt, job.newton_iterations,
           job.rayleigh_mass, job.rayleigh_stiffness, repr(job.physical_effects))
    model = _MODEL_CACHE.get(key)
    if model is None:
        _MODEL_CACHE.clear()
        model = _MODEL_CACHE[key] = _build_model(job)
    res = simulate(model, ProbePath(job.path_t, job.path_centres), job.radius, job.output_times,
                   callback=callback)
    return (res.positions.astype(np.float32), res.contact_force, res.status, res.message, res.wall_time)


def _rest_positions(job: _SimJob) -> np.ndarray:
    """(N, 3) node positions of the phantom at rest (sagged under body forces, if any)."""
    from core.simulation import static_equilibrium

    model = _build_model(job)
    if np.any(model.body_force):
        return static_equilibrium(model)[0].x
    return model.mesh.nodes.copy()


# --------------------------------------------------------------------------------------
# the generator
# --------------------------------------------------------------------------------------


@dataclass
class _Sequence:
    name: str
    role: str
    duration: float
    plan: ProbePlan
    frame_times: np.ndarray
    kin_t: np.ndarray
    rng: np.random.Generator


PHANTOM_DENSITY = PHANTOM_MASS / float(np.prod(PHANTOM_SIZE))
"""Density of the paper's gel, kg/m^3 (104.01 g in its box): the mass of other shapes."""


@dataclass
class _Phantom:
    """The lab's phantom: the paper's box, or a surface (dome, kidney-like, a given STL)."""

    shape: str
    size: np.ndarray
    mass: float
    surface: tuple[np.ndarray, np.ndarray] | None = None
    stl_path: Path | None = None
    landmarks: dict | None = None
    normals: np.ndarray | None = None


def _landmarks_of(V: np.ndarray, F: np.ndarray) -> tuple[dict, np.ndarray]:
    """Named calibration landmarks of a surface: its highest point ("apex") and the
    points furthest along (+-1, 0, 1) and (0, +-1, 1) ("x+", "x-", "y+", "y-"), each a
    vertex of the surface, with their outward normals (for the touching probe centre)."""
    from core.registration import landmark_normals

    import trimesh

    surface = trimesh.Trimesh(V, F, process=False)
    names = {"apex": (0.0, 0.0, 1.0), "x+": (1.0, 0.0, 1.0), "x-": (-1.0, 0.0, 1.0),
             "y+": (0.0, 1.0, 1.0), "y-": (0.0, -1.0, 1.0)}
    centre = V.mean(axis=0)
    points = {}
    for name, d in names.items():
        d = np.asarray(d) / np.linalg.norm(d)
        points[name] = V[int(np.argmax((V - centre) @ d))]
    P = np.array(list(points.values()))
    return {k: v.tolist() for k, v in points.items()}, landmark_normals(surface, P)


def _make_phantom(shape: str, phantom_stl, workdir: Path) -> _Phantom:
    """The phantom of ``generate_session(shape=..., phantom_stl=...)``; an STL goes to
    ``workdir/phantom.stl`` (x and y shifted so its bounding box starts at 0)."""
    from core.errors import MeshingError

    from core.lab.shapes import SHAPES, shape_surface

    if phantom_stl is None and shape == "box":
        return _Phantom("box", np.asarray(PHANTOM_SIZE, dtype=np.float64), PHANTOM_MASS)
    import trimesh

    if phantom_stl is not None:
        from core.simulation.meshing import check_stl

        try:
            surf = check_stl(phantom_stl)
        except MeshingError as exc:
            raise LabError(str(exc)) from exc
        V, F = np.asarray(surf.vertices, dtype=np.float64), np.asarray(surf.faces, dtype=np.int64)
        V[:, :2] -= V[:, :2].min(axis=0)
        shape = "stl"
    elif shape in SHAPES:
        V, F = shape_surface(shape)
    else:
        raise LabError(f"unknown phantom shape {shape!r}: one of {', '.join(SHAPES)} (or give phantom_stl)")
    mesh = trimesh.Trimesh(V, F, process=False)
    path = workdir / "phantom.stl"
    mesh.export(str(path))
    landmarks, normals = _landmarks_of(V, F)
    return _Phantom(shape, np.asarray(mesh.bounds[1], dtype=np.float64), PHANTOM_DENSITY * float(mesh.volume),
                    (V, F), path, landmarks, normals)


def _material_truth(cfg: LabConfig, size: np.ndarray) -> dict:
    """truth.json "material": law, citation, density and damping (and the stiffening of
    the "stable_yeoh" law)."""
    citation = {
        "stable_neo_hookean": "stable Neo-Hookean, Smith, de Goes & Kim 2018",
        "stable_yeoh": "stable Neo-Hookean, Smith, de Goes & Kim 2018, plus a Yeoh-type stiffening term "
                       "stiffening * mu / 2 * (I_C - 3 - 2 (J - 1))^2, Yeoh 1993",
    }.get(cfg.law, cfg.law)
    out = {"law": cfg.law, "citation": citation}
    if cfg.law == "stable_yeoh":
        out["stiffening"] = float(cfg.stiffening)
    out.update({
        "density": PHANTOM_DENSITY,
        "rayleigh_mass": cfg.rayleigh_mass,
        "rayleigh_stiffness": cfg.rayleigh_stiffness,
    })
    return out


def _frame_times(rng, duration: float, rate: float, jitter: float) -> np.ndarray:
    period = 1.0 / rate
    n = int(np.floor((duration - period) * rate)) + 1
    t = rng.uniform(0.0, period) + period * np.arange(n)
    t = t + np.clip(rng.normal(0.0, jitter, n), -0.3 * period, 0.3 * period)
    t = t[(t >= 0.0) & (t <= duration)]
    return t


def generate_session(
    out: str | Path,
    *,
    preset: str | LabConfig = "small",
    seed: int = 0,
    effects: Sequence[dict] = (),
    with_force: bool = False,
    overwrite: bool = False,
    callback: ProgressCallback | None = None,
    paths: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
    shape: str = "box",
    phantom_stl: str | Path | None = None,
) -> Path:
    """Generate a synthetic session folder (``tissue-session/1`` plus ``truth.json``).

    Args:
        out: the session folder to create.
        preset: a name of :data:`PRESETS` ("small", "demo", "field", "paper") or a
            :class:`LabConfig`.
        seed: all randomness comes from ``numpy.random.default_rng(seed)`` (and, for a
            config with ``variation``, the lab's draws from ``default_rng([seed, 7])``, so
            that poses, plans and noise streams do not depend on it); the same seed and
            arguments give byte-identical files.
        effects: effect dicts of ``SESSION_FORMAT.md`` (``{"kind": "gravity", "g": [...]}``);
            missing parameters take the defaults of :mod:`core.simulation.effects`.
            Positions are in the phantom frame.
        with_force: add ``fx, fy, fz`` (N, robot frame) to kinematics.csv: the contact
            force of the truth simulation at the camera frames, interpolated to the
            kinematic times, plus ``force_noise``.
        overwrite: replace an existing session at ``out``.
        callback: ``callback(fraction in [0, 1], message)`` for progress.
        paths: optional given probe paths, one ``(t (K,) s, centres (K, 3) m)`` per
            sequence (as many as ``cfg.sequence_roles``): the true sphere-centre path in
            the phantom frame, linearly interpolated, t strictly increasing from t[0] >= 0
            (held at the first point before). Each sequence then follows its path instead
            of a random plan and lasts its path's last time (overriding
            ``cfg.sequence_durations``); it has no pokes (``"pokes": []`` in truth.json)
            and its tool's shaft leans 25 degrees from vertical away from the camera,
            unrolled (:func:`core.lab.probing.plan_from_path`). Camera, noise, calibration,
            effects (input effects too) and force columns are as for random plans.
        shape: "box" (the paper's 68.7 x 39.3 x 35.8 mm block on a node grid), "dome"
            or "kidney" (:mod:`core.lab.shapes`). Other shapes are written as
            ``phantom.stl``; their truth is the STL filled by Gmsh with about as many
            nodes as ``cfg.grid`` holds; the mass is the paper's gel density times the
            volume; pokes go anywhere on the reachable surface
            (:func:`core.lab.surface_probing.plan_surface_sequence`); calibration touches
            five named landmarks (``calibration/landmarks.csv``) instead of corners.
        phantom_stl: a watertight STL (metres, z up, resting on z = 0) to use as the
            phantom instead of ``shape`` (shifted in x and y so that its bounding box
            starts at 0).

    Returns:
        the session folder.

    Raises:
        LabError: unknown preset or shape, bad effect, a bad path (count, shapes, times,
            or deeper than 15 mm into the phantom), a bad STL, or a truth simulation
            that diverged.
        core.io.SessionExistsError: ``out`` exists and ``overwrite`` is false.
    """
    from core.io import (
        CameraSpec,
        Corners,
        Kinematics,
        LandmarkTouches,
        PhantomSpec,
        ProbeSpec,
        SequenceSpec,
        SessionMeta,
        SessionWriter,
    )

    if isinstance(preset, LabConfig):
        cfg, preset_name = preset, "custom"
    elif preset in PRESETS:
        cfg, preset_name = PRESETS[preset], preset
    else:
        raise LabError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)} or a LabConfig")
    if len(cfg.sequence_durations) != len(cfg.sequence_roles) or not cfg.sequence_durations:
        raise LabError(f"sequence_durations ({len(cfg.sequence_durations)}) and sequence_roles "
                       f"({len(cfg.sequence_roles)}) must have the same non-zero length")
    if paths is not None:
        paths = list(paths)
        if len(paths) != len(cfg.sequence_roles):
            raise LabError(f"got {len(paths)} probe paths for {len(cfg.sequence_roles)} sequences "
                           f"(roles {cfg.sequence_roles}); give one (t, centres) per sequence")
        durations = []
        for i, path in enumerate(paths):
            if not isinstance(path, (tuple, list)) or len(path) != 2:
                raise LabError(f"probe path {i} must be a pair (t (K,) s, centres (K, 3) m), got {type(path).__name__}")
            try:
                t_i = np.asarray(path[0], dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise LabError(f"probe path {i}: times must be numbers, {exc}") from exc
            if t_i.ndim != 1 or t_i.size < 2:
                raise LabError(f"probe path {i}: times must be (K,) with K >= 2, got shape {t_i.shape}")
            durations.append(float(t_i[-1]))
        cfg = replace(cfg, sequence_durations=tuple(durations))
    report = callback or (lambda fraction, message: None)
    t_wall = time.perf_counter()
    full_effects = complete_effects(effects)
    by_kind = {e["kind"]: e for e in full_effects}
    physical = tuple(e for e in full_effects if e["kind"] in PHYSICAL_EFFECTS)
    r_nominal = float(cfg.probe_radius)
    r_true = float(by_kind["probe_radius"]["radius"]) if "probe_radius" in by_kind else r_nominal
    time_offset = float(by_kind["time_offset"]["offset"]) if "time_offset" in by_kind else 0.0
    kin_offset = (np.asarray(by_kind["kinematic_offset"]["offset"], float)
                  if "kinematic_offset" in by_kind else np.zeros(3))
    import shutil
    import tempfile

    workdir = Path(tempfile.mkdtemp(prefix="tissuetwin-lab-"))
    try:
        phantom = _make_phantom(shape, phantom_stl, workdir)
    except BaseException:
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    size = phantom.size
    reachable = None
    if phantom.surface is not None:
        from core.lab.surface_probing import ReachableSurface

        reachable = ReachableSurface(*phantom.surface)
        if "inclusion" in by_kind:
            inc = by_kind["inclusion"]
            if float(reachable.clearance(np.asarray(inc["center"], float)[None])[0]) >= 0.0:
                shutil.rmtree(workdir, ignore_errors=True)
                raise LabError(f"the inclusion's centre {inc['center']} m lies outside the {shape if phantom_stl is None else 'STL'} "
                               f"phantom (bounds {np.round(reachable.mesh.bounds, 4).tolist()} m): give a centre inside it")

    # ---- session-wide draws, in a fixed order -----------------------------------------
    rng = np.random.default_rng(seed)
    if cfg.youngs_modulus_range is not None:
        lo, hi = cfg.youngs_modulus_range
        E = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    else:
        E = float(cfg.youngs_modulus)
    drawn = None
    if cfg.variation is not None:
        # a generator of its own: the main stream (poses, plans, noise) stays the seed's
        drawn = cfg.variation.draw(np.random.default_rng([int(seed), 7]))
        cfg = apply_variation(cfg, drawn)
        E = float(cfg.youngs_modulus)
    T_phantom_robot = _random_robot_pose(rng, cfg.robot_distance_range)
    T_robot_phantom = np.linalg.inv(T_phantom_robot)
    top_centre = np.array([size[0] / 2, size[1] / 2, size[2]])
    T_phantom_camera = random_camera_pose(rng, top_centre, distance_range=cfg.camera_distance_range,
                                          tilt_range_deg=cfg.camera_tilt_range_deg)
    intrinsics = cfg.intrinsics.jittered(rng)
    m = cfg.roi_margin
    roi = roi_for_box(intrinsics, T_phantom_camera, (-m, -m, -0.001), (size[0] + m, size[1] + m, size[2] + 0.02))
    camera = DepthCamera(intrinsics, T_phantom_camera, roi, cfg.depth_noise)
    rays = camera.rays_phantom()
    tm = cfg.table_margin
    table = table_mesh(top_centre)
    table_keep = table_ring_mask(rays, (-tm, -tm), (size[0] + tm, size[1] + tm), float(table[0][0, 2]))
    cam_dir = T_phantom_camera[:2, 3] - top_centre[:2]
    cam_azimuth = float(np.arctan2(cam_dir[1], cam_dir[0]))
    corner_rng, reference_rng, *seq_rngs = rng.spawn(2 + len(cfg.sequence_durations))

    sequences: list[_Sequence] = []
    for i, (dur, role) in enumerate(zip(cfg.sequence_durations, cfg.sequence_roles)):
        srng = seq_rngs[i]
        # the instrument comes from the side opposite the camera, as in the paper's Fig. 2
        if paths is None:
            azimuth = cam_azimuth + np.pi + srng.uniform(-np.pi / 3, np.pi / 3)
            try:
                if reachable is None:
                    plan = plan_sequence(srng, size=size, radius=r_true, duration=float(dur), config=cfg.probing,
                                         tool_azimuth=azimuth)
                else:
                    plan = plan_surface_sequence(srng, surface=reachable, radius=r_true, duration=float(dur),
                                                 config=cfg.probing, tool_azimuth=azimuth)
            except ValueError as exc:
                raise LabError(f"sequence seq{i:02d} ({role}, {dur} s): {exc}") from exc
        else:
            try:
                plan = plan_from_path(paths[i][0], paths[i][1], size=size, radius=r_true,
                                      tool_azimuth=cam_azimuth + np.pi)
            except ValueError as exc:
                raise LabError(f"probe path {i} ({role} sequence seq{i:02d}): {exc}") from exc
        ft = _frame_times(srng, float(dur), cfg.camera_rate_hz, cfg.frame_jitter)
        if ft.size == 0:
            raise LabError(f"sequence seq{i:02d} lasts {dur} s: too short for one camera frame at "
                           f"{cfg.camera_rate_hz} Hz")
        kt = np.arange(int(np.floor(dur * cfg.kinematics_rate_hz)) + 1) / cfg.kinematics_rate_hz
        sequences.append(_Sequence(f"seq{i:02d}", role, float(dur), plan, ft, kt, srng))

    def job_for(seq: _Sequence | None) -> _SimJob:
        if seq is None:
            pt, pc, ot = np.array([0.0]), np.array([[size[0] / 2, size[1] / 2, size[2] + 0.05]]), np.array([0.0])
        else:
            pt = np.linspace(0.0, seq.duration, int(np.ceil(seq.duration * 200)) + 1)
            pc, ot = seq.plan.trajectory(pt), seq.frame_times
        return _SimJob(mesh_spec, phantom.mass, E, cfg.poisson_ratio, cfg.law, float(cfg.stiffening),
                       float(cfg.contact_stiffness_per_modulus), cfg.dt, cfg.newton_iterations,
                       cfg.rayleigh_mass, cfg.rayleigh_stiffness, physical, pt, pc, r_true, ot)

    if phantom.stl_path is None:
        mesh_spec = ("grid", tuple(cfg.grid), tuple(float(v) for v in PHANTOM_SIZE))
    else:
        from core.simulation.meshing import default_element_size

        volume = phantom.mass / PHANTOM_DENSITY
        mesh_spec = ("stl", str(phantom.stl_path), default_element_size(volume, int(np.prod(cfg.grid))))
    try:
        mesh = _truth_mesh(mesh_spec)
    except TissueTwinError as exc:
        shutil.rmtree(workdir, ignore_errors=True)
        raise LabError(f"the phantom cannot be meshed: {exc}") from exc
    triangles = np.asarray(mesh.surface_triangles)

    meta = SessionMeta(
        phantom=PhantomSpec(size=size, mass=phantom.mass, fixed="bottom"),
        probe=ProbeSpec(radius=r_nominal),
        camera=CameraSpec(rate_hz=float(cfg.camera_rate_hz), depth_accuracy=float(cfg.depth_accuracy),
                          intrinsics=intrinsics.to_dict()),
        sequences=tuple(SequenceSpec(s.name, s.role) for s in sequences),
        raw={},
        **({"landmarks": phantom.landmarks} if phantom.landmarks else {}),
    )
    total_frames = sum(len(s.frame_times) for s in sequences)
    sim_share = 0.5  # rough split of the progress bar between simulation and rendering
    done_frames = 0

    executor = None
    if cfg.workers > 0:
        import multiprocessing

        # "spawn": the parent holds Open3D/TBB threads, which fork() does not copy safely
        executor = ProcessPoolExecutor(max_workers=cfg.workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        with SessionWriter(out, meta, overwrite=overwrite) as writer:
            report(0.0, "calibration")
            if phantom.landmarks is None:
                # ---- corner-touch calibration (true radius: the sphere's lowest point touches)
                labels, touches = [], []
                for label, (cx, cy) in (("x0y0", (0, 0)), ("x1y0", (1, 0)), ("x0y1", (0, 1)), ("x1y1", (1, 1))):
                    corner = np.array([cx * size[0], cy * size[1], size[2] + r_true])
                    for _ in range(cfg.corner_touches):
                        labels.append(label)
                        touches.append(corner + corner_rng.normal(0.0, cfg.corner_noise, 3))
                writer.write_corners(Corners(labels=tuple(labels),
                                             positions=_transform(T_robot_phantom, np.asarray(touches))))
            else:
                # ---- landmark touches: the sphere touches each landmark along its normal
                labels, touches = [], []
                for (label, point), normal in zip(phantom.landmarks.items(), phantom.normals):
                    centre = np.asarray(point) + r_true * normal
                    for _ in range(cfg.corner_touches):
                        labels.append(label)
                        touches.append(centre + corner_rng.normal(0.0, cfg.corner_noise, 3))
                writer.write_landmark_touches(LandmarkTouches(
                    labels=tuple(labels), positions=_transform(T_robot_phantom, np.asarray(touches))))
                import trimesh

                writer.write_phantom_stl(trimesh.Trimesh(*phantom.surface, process=False))

            # ---- reference cloud: the phantom at rest, no instrument, averaged frames
            rest = _rest_positions(job_for(None))
            hits = cast(camera, (rest, triangles), table=table, rays=rays, table_keep=table_keep)
            stack = np.stack([apply_depth_noise(hits, cfg.depth_noise, reference_rng)
                              for _ in range(max(cfg.reference_frames, 1))])
            n_valid = np.isfinite(stack).sum(axis=0)
            mean = np.nansum(stack, axis=0) / np.maximum(n_valid, 1)
            ref_depth = np.where(n_valid * 2 >= stack.shape[0], mean, np.nan)
            writer.write_reference(depth_to_points(camera, ref_depth))

            # ---- sequences: simulate ahead in workers, render and write in order
            futures: dict[int, Future] = {}

            def submit(k: int) -> None:
                if executor is not None and k < len(sequences) and k not in futures:
                    futures[k] = executor.submit(_run_sim, job_for(sequences[k]))

            for k in range(cfg.workers):
                submit(k)
            seq_meta = []
            retried: dict[str, dict] = {}
            for i, seq in enumerate(sequences):
                base = done_frames / total_frames
                span = len(seq.frame_times) / total_frames
                report(base, f"{seq.name}: truth simulation")
                sim_out = None
                if executor is not None:
                    try:
                        submit(i)
                        sim_out = futures.pop(i).result()
                        submit(i + cfg.workers)
                    except BrokenProcessPool:
                        # e.g. a script without an ``if __name__ == "__main__"`` guard: the
                        # spawned worker cannot start. Same results, just without overlap.
                        executor.shutdown(wait=False, cancel_futures=True)
                        executor = None
                        futures.clear()
                        report(base, "worker process failed to start; simulating in-process")
                if sim_out is not None:
                    positions, force, status, message, sim_wall = sim_out
                else:
                    def sim_cb(fr, msg, _b=base, _s=span, _n=seq.name):
                        report(_b + _s * sim_share * fr, f"{_n}: truth simulation")
                    positions, force, status, message, sim_wall = _run_sim(job_for(seq), sim_cb)
                if status != "ok":
                    # a stiff contact on a fine mesh can outrun one Newton iteration per
                    # step (field seed 111: 31x11x11, 1.4e6 E/m, diverged at 2.9 s):
                    # retry with the stronger numerics of TRUTH_RETRIES, as a careful lab
                    # would, and record what it took in truth.json
                    for newton, dt_div in TRUTH_RETRIES:
                        job = replace(job_for(seq), newton_iterations=max(newton, cfg.newton_iterations),
                                      dt=cfg.dt / dt_div)
                        report(base, f"{seq.name}: truth diverged ({message}); retrying with {job.newton_iterations} "
                                     f"Newton iterations, dt {job.dt:.3g} s")
                        positions, force, status, message, sim_wall = _run_sim(job)
                        if status == "ok":
                            retried[seq.name] = {"newton_iterations": job.newton_iterations, "dt": job.dt}
                            break
                if status != "ok":
                    raise LabError(f"truth simulation of {seq.name} (seed {seed}) {status}: {message}")

                # kinematics as the robot reports them
                srng = seq.rng
                p_true_at_kin = seq.plan.trajectory(seq.kin_t - time_offset)
                p_written = _transform(T_robot_phantom, p_true_at_kin - kin_offset)
                p_written = p_written + srng.normal(0.0, cfg.encoder_noise, p_written.shape)
                q = _quat_xyzw(T_robot_phantom[:3, :3] @ seq.plan.R_phantom_tool)
                f_written = None
                if with_force:
                    f_ph = np.stack([np.interp(seq.kin_t - time_offset, seq.frame_times, force[:, j])
                                     for j in range(3)], axis=1)
                    f_written = f_ph @ T_robot_phantom[:3, :3].T
                    f_written = f_written + srng.normal(0.0, cfg.force_noise, f_written.shape)
                writer.write_kinematics(seq.name, Kinematics(
                    t=seq.kin_t, position=p_written, quaternion=np.tile(q, (len(seq.kin_t), 1)), force=f_written))

                # depth frames
                centres = seq.plan.trajectory(seq.frame_times)
                shaft = seq.plan.shaft_direction
                n_f = len(seq.frame_times)
                every = max(n_f // 20, 1)
                max_disp = 0.0
                for f, t in enumerate(seq.frame_times):
                    max_disp = max(max_disp, float(np.linalg.norm(positions[f] - mesh.nodes, axis=1).max()))
                    inst = Instrument(centre=centres[f], shaft_direction=shaft, radius=r_true)
                    hits = cast(camera, (positions[f], triangles), table=table, instrument=inst, rays=rays,
                                table_keep=table_keep)
                    pts = depth_to_points(camera, apply_depth_noise(hits, cfg.depth_noise, srng))
                    writer.write_frame(seq.name, f, float(t), pts)
                    if f % every == 0:
                        report(base + span * (sim_share + (1 - sim_share) * f / n_f)
                               if executor is None else base + span * f / n_f,
                               f"{seq.name}: frame {f + 1}/{n_f}")
                done_frames += n_f
                seq_meta.append({
                    "name": seq.name, "role": seq.role, "duration": seq.duration,
                    "n_frames": n_f,
                    "tool_quaternion_phantom": _quat_xyzw(seq.plan.R_phantom_tool).tolist(),
                    "pokes": [p.to_dict() for p in seq.plan.pokes],
                    "max_contact_force": float(np.max(np.linalg.norm(force, axis=1))),
                    "max_displacement": max_disp,
                })
                del positions

            truth = {
                "format": "tissue-truth/1",
                "generator": {"name": GENERATOR_NAME, "version": GENERATOR_VERSION, "preset": preset_name,
                              "seed": int(seed)},
                "T_phantom_robot": T_phantom_robot.tolist(),
                "T_phantom_camera": T_phantom_camera.tolist(),
                "youngs_modulus": E,
                "poisson_ratio": float(cfg.poisson_ratio),
                "material": _material_truth(cfg, size),
                "effects": full_effects,
                "probe": {"radius_nominal": r_nominal, "radius_true": r_true,
                          "shaft_radius": Instrument.shaft_radius, "shaft_length": Instrument.shaft_length},
                "camera": {**intrinsics.to_dict(), "roi": list(roi), "rate_hz": cfg.camera_rate_hz,
                           "noise": asdict(cfg.depth_noise), "table_z": float(table[0][0, 2]),
                           "table_margin": tm},
                "kinematics": {"rate_hz": cfg.kinematics_rate_hz, "encoder_noise": cfg.encoder_noise,
                               "force": bool(with_force), "force_noise": cfg.force_noise if with_force else None,
                               "corner_noise": cfg.corner_noise},
                "mesh": ({"grid": list(cfg.grid), "nodes": int(mesh.n_nodes), "tets": int(mesh.n_tets),
                          "split": "6 tets per hex (Kuhn)"} if mesh_spec[0] == "grid" else
                         {"shape": phantom.shape, "mesher": "gmsh", "element_size": float(mesh_spec[2]),
                          "nodes": int(mesh.n_nodes), "tets": int(mesh.n_tets)}),
                "sim": {"dt": cfg.dt, "integrator": "implicit_euler", "newton_iterations": cfg.newton_iterations},
                "sequences": seq_meta,
            }
            # keys added only when used, so that sessions of older configs stay byte-identical
            if cfg.contact_stiffness_per_modulus != 2e5:
                truth["sim"]["contact_stiffness_per_modulus"] = float(cfg.contact_stiffness_per_modulus)
            if retried:
                truth["sim"]["retried"] = retried
            if drawn is not None:
                truth["lab_variation"] = {**drawn, "depth_noise_sigma": float(cfg.depth_noise.sigma),
                                          "ranges": cfg.variation.to_dict()}
            writer.write_truth(truth)
            path = writer.finish()
    finally:
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
        _MODEL_CACHE.clear()
        shutil.rmtree(workdir, ignore_errors=True)
    report(1.0, f"done in {time.perf_counter() - t_wall:.1f} s")
    return path
