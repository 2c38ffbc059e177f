"""Model extensions, one per effect kind of ``SESSION_FORMAT.md``.

Each effect is a self-contained option: it changes the model only through the
:class:`~core.simulation.model.ModelBuilder` hooks (per-element stiffness, supports,
body forces, extra stress terms, contact friction) or through the probe input
(radius, clock, position). The solver has no effect-specific branches.

Names and parameters match the effect table of ``SESSION_FORMAT.md``; positions are
in the phantom frame, SI units throughout.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from core.errors import SimulationError

if TYPE_CHECKING:  # pragma: no cover
    from core.simulation.model import ModelBuilder
    from core.simulation.probe import ProbePath

__all__ = [
    "Effect",
    "Gravity",
    "Inclusion",
    "Viscoelasticity",
    "Friction",
    "BaseCompliance",
    "ProbeRadius",
    "TimeOffset",
    "KinematicOffset",
    "EFFECT_KINDS",
    "effect_from_dict",
]


@dataclass(frozen=True)
class Effect:
    """Base class. Subclasses set ``kind`` and override the hooks they need."""

    kind: ClassVar[str] = ""

    def configure(self, builder: "ModelBuilder") -> None:
        """Change the model under construction (default: nothing)."""

    def transform_probe(self, path: "ProbePath", radius: float) -> tuple["ProbePath", float]:
        """Map the calibrated probe input to the true one (default: unchanged)."""
        return path, radius

    def to_dict(self) -> dict:
        """``{"kind": ..., **parameters}`` as in truth.json / diagnosis.json (lists, not arrays)."""
        out = {"kind": self.kind}
        for k, v in asdict(self).items():
            out[k] = np.asarray(v).tolist() if isinstance(v, (tuple, list, np.ndarray)) else float(v)
        return out


def _vec3(name: str, value) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise SimulationError(f"{name} must be 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def _positive(name: str, value) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise SimulationError(f"{name} must be positive, got {value!r}")
    return v


@dataclass(frozen=True)
class Gravity(Effect):
    """Body force ``m_i g`` on every node (the phantom sags by ~rho g H^2 / E)."""

    kind: ClassVar[str] = "gravity"
    g: tuple[float, float, float] = (0.0, 0.0, -9.81)

    def __post_init__(self):
        object.__setattr__(self, "g", _vec3("gravity g", self.g))

    def configure(self, builder):
        builder.body_force += builder.node_mass[:, None] * np.asarray(self.g)[None, :]


@dataclass(frozen=True)
class Inclusion(Effect):
    """A sphere of tissue whose Young's modulus is ``stiffness_ratio`` times the bulk.

    Each element's modulus is the volume-weighted (Voigt) mix of the two,
    ``E (1 + (ratio - 1) phi)``, with ``phi`` the fraction of the element inside the
    sphere, estimated from its centroid's signed distance to the sphere surface over the
    element's size ``h`` (cube root of its volume): ``phi = clip(1/2 - d / h, 0, 1)``.
    Unlike a centroid-in-sphere test, the model then changes smoothly with the centre
    and the radius, so a fit can differentiate it, on a coarse mesh too (13 x 5 x 5
    elements are 6 x 10 x 9 mm, the size of the sphere).
    """

    kind: ClassVar[str] = "inclusion"
    center: tuple[float, float, float] = (0.034, 0.02, 0.025)
    radius: float = 0.008
    stiffness_ratio: float = 5.0

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3("inclusion center", self.center))
        object.__setattr__(self, "radius", _positive("inclusion radius", self.radius))
        object.__setattr__(self, "stiffness_ratio", _positive("inclusion stiffness_ratio", self.stiffness_ratio))

    def configure(self, builder):
        corners = builder.mesh.nodes[builder.mesh.tets]  # (E, 4, 3)
        centroids = corners.mean(axis=1)
        e1, e2, e3 = (corners[:, k] - corners[:, 0] for k in (1, 2, 3))
        h = np.cbrt(np.abs(np.einsum("ij,ij->i", e1, np.cross(e2, e3))) / 6.0)
        d = np.linalg.norm(centroids - np.asarray(self.center), axis=1) - self.radius
        phi = np.clip(0.5 - d / h, 0.0, 1.0)
        builder.element_scale *= 1.0 + (self.stiffness_ratio - 1.0) * phi


@dataclass(frozen=True)
class Viscoelasticity(Effect):
    """Standard linear solid: a Maxwell arm (relaxation time tau, stiffness
    ``stiffness_ratio`` times the elastic one) in parallel with the elastic solid.

    The arm's viscous strain is one internal variable per element (corotated small
    strain), integrated with implicit Euler. After unloading a dent recovers with the
    retardation time ``tau * (1 + stiffness_ratio)`` (Findley et al., "Creep and
    relaxation of nonlinear viscoelastic materials", Ch. 5).
    """

    kind: ClassVar[str] = "viscoelasticity"
    relaxation_time: float = 0.5
    stiffness_ratio: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "relaxation_time", _positive("relaxation_time", self.relaxation_time))
        object.__setattr__(self, "stiffness_ratio", _positive("viscoelastic stiffness_ratio", self.stiffness_ratio))

    def configure(self, builder):
        from core.simulation.model import MaxwellArm

        builder.add_term(MaxwellArm(self.relaxation_time, self.stiffness_ratio))


@dataclass(frozen=True)
class Friction(Effect):
    """Coulomb friction (coefficient ``mu``) between the probe and the surface,
    regularised below a slip speed (``SimulationConfig.friction_slip_speed``)."""

    kind: ClassVar[str] = "friction"
    mu: float = 0.5

    def __post_init__(self):
        object.__setattr__(self, "mu", _positive("friction mu", self.mu))

    def configure(self, builder):
        builder.friction += self.mu


@dataclass(frozen=True)
class BaseCompliance(Effect):
    """The bottom face rests on an elastic (Winkler) foundation of ``stiffness``
    Pa/m instead of being fixed; each bottom node gets a spring of stiffness x its
    tributary area in all three directions."""

    kind: ClassVar[str] = "base_compliance"
    stiffness: float = 2e5

    def __post_init__(self):
        object.__setattr__(self, "stiffness", _positive("base stiffness", self.stiffness))

    def configure(self, builder):
        bottom = builder.mesh.bottom_nodes()
        area = builder.bottom_area()
        builder.fixed[bottom] = False
        builder.support_stiffness[bottom] += self.stiffness * area[bottom]


@dataclass(frozen=True)
class ProbeRadius(Effect):
    """The probe's true radius (m) differs from session.json's.

    A wrong radius also moved the robot calibration: SESSION_FORMAT.md places each
    corner touch's sphere centre at the corner plus (0, 0, radius) with the nominal
    radius, while the touching sphere's centre really was ``radius`` above the corner.
    Every touch target is then off by the same vertical shift, so the Kabsch fit's
    robot -> phantom transform is off by exactly that translation, and the calibrated
    centres sit ``radius - nominal`` below the true ones. The replay therefore moves the
    path up by ``radius - nominal`` along the phantom's z (the sphere's lowest point
    stays where the calibration put it) and uses the true radius: what a bigger probe
    changes is the width of the dent, not its depth. Without this shift a fit of the
    radius runs the wrong way (measured: 7.5 mm hidden, 4.8 mm fitted).
    """

    kind: ClassVar[str] = "probe_radius"
    radius: float = 0.006

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("probe radius", self.radius))

    def transform_probe(self, path, radius):
        return path.translated(np.array([0.0, 0.0, self.radius - float(radius)])), self.radius


@dataclass(frozen=True)
class TimeOffset(Effect):
    """Clock offset: the probe's true position at camera time t is the kinematics'
    position at ``t + offset`` (s)."""

    kind: ClassVar[str] = "time_offset"
    offset: float = 0.1

    def __post_init__(self):
        object.__setattr__(self, "offset", float(self.offset))

    def transform_probe(self, path, radius):
        return path.shifted(-self.offset), radius


@dataclass(frozen=True)
class KinematicOffset(Effect):
    """The probe really is at the calibrated position plus ``offset`` (m, phantom frame)."""

    kind: ClassVar[str] = "kinematic_offset"
    offset: tuple[float, float, float] = (0.0, 0.0, -0.002)

    def __post_init__(self):
        object.__setattr__(self, "offset", _vec3("kinematic offset", self.offset))

    def transform_probe(self, path, radius):
        return path.translated(np.asarray(self.offset)), radius


EFFECT_KINDS: dict[str, type[Effect]] = {
    cls.kind: cls
    for cls in (Gravity, Inclusion, Viscoelasticity, Friction, BaseCompliance, ProbeRadius, TimeOffset, KinematicOffset)
}


def effect_from_dict(d: dict) -> Effect:
    """Build an effect from ``{"kind": ..., **parameters}``; missing parameters take defaults.

    Raises:
        SimulationError: unknown kind, unknown parameter, or invalid value.
    """
    if not isinstance(d, dict) or "kind" not in d:
        raise SimulationError(f"an effect must be a dict with a 'kind', got {d!r}")
    kind = d["kind"]
    if kind not in EFFECT_KINDS:
        raise SimulationError(f"unknown effect kind {kind!r}; expected one of {sorted(EFFECT_KINDS)}")
    cls = EFFECT_KINDS[kind]
    params = {k: v for k, v in d.items() if k != "kind"}
    allowed = set(cls.__dataclass_fields__)
    unknown = set(params) - allowed
    if unknown:
        raise SimulationError(f"effect {kind!r} has no parameter(s) {sorted(unknown)}; it takes {sorted(allowed)}")
    return cls(**params)
