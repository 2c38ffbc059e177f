"""The virtual lab's configuration: :class:`LabConfig`, its presets and the effects.

This module holds what a caller of :func:`core.lab.generate_session` chooses: the size
and fidelity of a session (:class:`LabConfig`), the named presets (:data:`PRESETS`, with
:data:`PRESET_NOTES`), the effects the lab can switch on (:data:`PHYSICAL_EFFECTS` go into
the truth FEM model, :data:`INPUT_EFFECTS` into the probe input and the written
kinematics; :data:`DEMO_EFFECTS` is the demo's hidden pair; :func:`complete_effects`
fills in their parameters), and what the generator's modules share: :class:`LabError`
and the progress-callback type. :mod:`core.lab.generate` re-exports these names.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

from core.errors import TissueTwinError
from core.lab.camera import DepthNoise, Intrinsics
from core.lab.probing import ProbingConfig
from core.lab.variation import LabVariation

__all__ = [
    "LabConfig",
    "LabError",
    "PRESETS",
    "PRESET_NOTES",
    "DEMO_EFFECTS",
    "PHYSICAL_EFFECTS",
    "INPUT_EFFECTS",
    "ProgressCallback",
    "complete_effects",
]

PHYSICAL_EFFECTS = ("gravity", "inclusion", "viscoelasticity", "friction", "base_compliance")
"""Effects that go into the truth FEM model."""
INPUT_EFFECTS = ("probe_radius", "time_offset", "kinematic_offset")
"""Effects the lab applies to the probe input and the written kinematics itself."""

ProgressCallback = Callable[[float, str], None]
"""``callback(fraction in [0, 1], message)``: progress of a session being generated."""


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
