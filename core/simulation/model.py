"""The static model (mesh, material, constraints, effects) and the changing state.

Following MuJoCo's ``MjModel``/``MjData`` split (``../shared/STYLE.md``): a
:class:`Model` is built once by :func:`build_model` and never changes; positions,
velocities and internal variables live in a :class:`State`. Parameters that change
the model's matrices (Young's modulus, an inclusion, supports) need a fresh model.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from core.errors import SimulationError
from core.simulation import fem
from core.simulation.effects import Effect
from core.simulation.mesh import TetMesh

__all__ = ["Material", "SimulationConfig", "Model", "ModelBuilder", "State", "MaxwellArm", "build_model"]

LAWS = ("corotational", "stable_neo_hookean", "stable_yeoh")


@dataclass(frozen=True)
class Material:
    """Homogeneous isotropic material of the phantom.

    Attributes:
        youngs_modulus: Young's modulus E in Pa (the paper identifies 5e3 Pa).
        poisson_ratio: Poisson's ratio nu (the paper takes literature values, 0.4-0.5).
        law: "corotational" (linear elasticity in a rotated frame, Müller & Gross 2004;
            the replay's base model), "stable_neo_hookean" (Smith et al. 2018; the
            virtual lab's truth) or "stable_yeoh" (stable neo-Hookean plus a Yeoh-type
            strain-stiffening term ``stiffening * mu / 2 * (I_C - 3)^2``, Yeoh 1993; see
            :func:`core.simulation.fem.pk1_stable_yeoh`; a randomised lab's truth).
        stiffening: dimensionless coefficient of the Yeoh term, finite and >= 0; used
            only by the "stable_yeoh" law (0 makes it stable neo-Hookean).

    Raises:
        SimulationError: unknown law, non-physical E or nu, or a negative or non-finite
            stiffening.
    """

    youngs_modulus: float = 5000.0
    poisson_ratio: float = 0.44
    law: str = "corotational"
    stiffening: float = 0.0

    def __post_init__(self):
        if self.law not in LAWS:
            raise SimulationError(f"material law must be one of {LAWS}, got {self.law!r}")
        fem.check_material(self.youngs_modulus, self.poisson_ratio)
        if not (np.isfinite(self.stiffening) and self.stiffening >= 0):
            raise SimulationError(f"stiffening must be finite and >= 0, got {self.stiffening}")


@dataclass(frozen=True)
class SimulationConfig:
    """Numerical settings of the replay.

    Attributes:
        dt: time step in s. The probe path is interpolated linearly at these substeps.
        rayleigh_mass: Rayleigh damping coefficient alpha on M, 1/s (paper: 0.1).
        rayleigh_stiffness: Rayleigh damping coefficient beta on K, s (paper: 0.1).
        contact_stiffness: penalty stiffness of the probe contact per unit surface
            area, Pa/m; None (default): ``contact_stiffness_per_modulus`` times the
            material's Young's modulus, so that the contact scales with the body.
        contact_stiffness_per_modulus: the default contact stiffness per unit area and
            per pascal of Young's modulus, 1/m. At 2e5 /m (1e9 Pa/m for a 5 kPa gel) the
            sphere sinks 0.13-0.18 mm into the replayed surface at 0.3-0.9 N, which is the
            one-step lag of the active contact set, not the penalty's compliance (measured
            on a 6 s session: 0.45 mm on average with the former 1e7 Pa/m). A steel probe in a
            gel hardly sinks at all; a soft penalty made every replayed dent shallower than
            the measured one, which a downward robot offset or a larger probe then
            mimicked. Scaling with E keeps the quasi-static model exactly invariant to E
            (every stiffness proportional to it): displacements do not depend on E and the
            force is proportional to it.
        contact_margin: triangles within this distance of the probe sphere (m) are
            contact candidates of a step, active once the step would push them inside.
        contact_subdivision: sub-triangles per surface triangle edge of the contact surface
            (:mod:`core.simulation.contact`): 1 (default) is one contact per triangle; n
            splits each triangle into n^2 contacts of 1/n^2 of its area, mapped on its nodes
            (a quadrature of the penalty pressure over the indented area). Measured on a
            field session's compliant-base press (13 x 5 x 5, 12 s, force): n = 3 moved the
            E at which the replay jumps between two lateral equilibria from 0.97-0.98 to
            0.85-0.88 of the fitted E but did not remove the jump (the finer 25 x 9 x 9 grid
            does); it costs 23 % of the replay's speed on 13 x 5 x 5 (6120 -> 4700 steps/s).
        contact_iterations: most active-set passes of a step's contact solve.
        contact_tolerance: a candidate is activated when the step would push it more
            than this far inside the sphere, m.
        newton_iterations: corrections per step with the constant rest Jacobian
            (1 is the linearly implicit Euler step; more converge to full implicit Euler).
        polar_iterations: Newton iterations of the warm-started rotation extraction per
            force evaluation (quadratically convergent; rotations change little per step).
        integrator: "implicit_euler" (default) or "symplectic_euler" (explicit,
            conditionally stable; for comparison and for testing divergence handling).
        friction_slip_speed: regularisation speed of Coulomb friction, m/s; below it
            friction acts as a stiff viscous stick.
        divergence_limit: a run is declared diverged when any node moves more than
            this many phantom diagonals from rest, or a value is not finite.
        compiled: step implicit Euler in one compiled loop (:mod:`core.simulation.stepper`);
            False runs the Python reference :func:`core.simulation.solver.step` (same
            results to rounding; for tests and for reading).
    """

    dt: float = 1.0 / 120.0
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    contact_stiffness: float | None = None
    contact_stiffness_per_modulus: float = 2e5
    contact_margin: float = 0.001
    contact_subdivision: int = 1
    contact_iterations: int = 8
    contact_tolerance: float = 1e-6
    newton_iterations: int = 1
    polar_iterations: int = 1
    integrator: str = "implicit_euler"
    friction_slip_speed: float = 1e-3
    divergence_limit: float = 1.0
    compiled: bool = True

    def __post_init__(self):
        if not (self.dt > 0 and np.isfinite(self.dt)):
            raise SimulationError(f"dt must be positive, got {self.dt}")
        if self.integrator not in ("implicit_euler", "symplectic_euler"):
            raise SimulationError(f"unknown integrator {self.integrator!r}")
        if self.newton_iterations < 1 or self.polar_iterations < 1:
            raise SimulationError("newton_iterations and polar_iterations must be >= 1")
        if self.rayleigh_mass < 0 or self.rayleigh_stiffness < 0:
            raise SimulationError("damping must be >= 0")
        if int(self.contact_subdivision) != self.contact_subdivision or self.contact_subdivision < 1:
            raise SimulationError(f"contact_subdivision must be an integer >= 1, got {self.contact_subdivision}")
        k = self.contact_stiffness
        if (k is not None and not (np.isfinite(k) and k > 0)) or not (
                np.isfinite(self.contact_stiffness_per_modulus) and self.contact_stiffness_per_modulus > 0):
            raise SimulationError(f"contact stiffness must be positive, got {k} Pa/m and "
                                  f"{self.contact_stiffness_per_modulus} /m per Pa")


class MaxwellArm:
    """Standard-linear-solid Maxwell arm: stress ``k C:(eps - eps_v)`` with
    ``d eps_v/dt = (eps - eps_v) / tau``, eps the corotated small strain.

    Implicit Euler on eps_v gives at step end ``sigma = k/(1+h) C:(eps - eps_v_old)``,
    ``h = dt/tau``, so the arm adds ``k/(1+h) K`` to the step's Jacobian.
    """

    needs_rotation = True

    def __init__(self, relaxation_time: float, stiffness_ratio: float):
        self.tau = float(relaxation_time)
        self.k = float(stiffness_ratio)

    def lhs_scale(self, dt: float) -> float:
        return self.k / (1.0 + dt / self.tau)

    def init_state(self, n_elements: int) -> np.ndarray:
        return np.zeros((9, n_elements))

    def stress(self, model: "Model", F, R, eps_v, dt):
        """Return (PK1 stress (9,E), updated internal variable)."""
        h = dt / self.tau
        eps = fem.corotated_strain(F, R)
        sigma = fem.stress_linear(eps - eps_v, model.mu, model.lam) * (self.k / (1.0 + h))
        eps_v_new = (eps_v + h * eps) / (1.0 + h)
        return fem.rotate_stress(R, sigma), eps_v_new


class ModelBuilder:
    """Mutable staging area that effects configure before :func:`build_model` freezes it.

    Attributes (all in SI units, phantom frame):
        mesh: the :class:`TetMesh`.
        node_mass: (N,) lumped node masses, kg.
        element_scale: (E,) multiplier of Young's modulus per element.
        fixed: (N,) bool, nodes held at rest.
        support_stiffness: (N,) N/m springs to the rest position (all directions).
        body_force: (N, 3) N constant external force per node.
        friction: Coulomb coefficient at the probe contact.
        terms: extra stress terms (objects with ``stress``/``lhs_scale``/``init_state``).
    """

    def __init__(self, mesh: TetMesh, mass: float):
        self.mesh = mesh
        self.elements = mesh.elements
        total_volume = float(self.elements.volume.sum())
        rho = mass / total_volume
        node_mass = np.zeros(mesh.n_nodes)
        np.add.at(node_mass, mesh.tets.ravel(), np.repeat(rho * self.elements.volume / 4.0, 4))
        self.node_mass = node_mass
        self.density = rho
        self.element_scale = np.ones(mesh.n_tets)
        self.fixed = np.zeros(mesh.n_nodes, dtype=bool)
        self.fixed[mesh.bottom_nodes()] = True
        self.support_stiffness = np.zeros(mesh.n_nodes)
        self.body_force = np.zeros((mesh.n_nodes, 3))
        self.friction = 0.0
        self.terms: list = []

    def add_term(self, term) -> None:
        self.terms.append(term)

    def bottom_area(self) -> np.ndarray:
        """(N,) tributary area (m^2) of each node on the bottom face (zero elsewhere)."""
        tris = self.mesh.surface_triangles
        p = self.mesh.nodes[tris]
        on_bottom = np.all(p[:, :, 2] <= 1e-9, axis=1)
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        out = np.zeros(self.mesh.n_nodes)
        np.add.at(out, tris[on_bottom].ravel(), np.repeat(area[on_bottom] / 3.0, 3))
        return out


class _BandedSPD:
    """Cholesky factor of a constant SPD matrix in banded storage, with a cache of
    columns of its inverse (for Woodbury updates of the contact constraints)."""

    def __init__(self, A: sp.csr_matrix):
        A = A.tocoo()
        upper = A.col >= A.row
        band = int((A.col - A.row)[upper].max()) if np.any(upper) else 0
        n = A.shape[0]
        ab = np.zeros((band + 1, n))
        ab[band + A.row[upper] - A.col[upper], A.col[upper]] = A.data[upper]
        try:
            self.cb = sla.cholesky_banded(ab, lower=False)
        except np.linalg.LinAlgError as exc:
            raise SimulationError(f"system matrix is not positive definite: {exc}") from exc
        self.n = n
        self.bandwidth = band
        (self._pbtrs,) = sla.get_lapack_funcs(("pbtrs",), (self.cb,))
        self.cbT = np.ascontiguousarray(self.cb.T)  # LAPACK's column-major band storage, for the compiled stepper
        self._slot = np.full(n, -1, dtype=np.int64)
        self._rows = np.zeros((0, n))  # cached rows of A^{-1} (A is symmetric)
        self._used = np.zeros(1, dtype=np.int64)  # slots in use (an array: the compiled stepper updates it)

    def solve(self, b: np.ndarray) -> np.ndarray:
        # LAPACK dpbtrs directly: scipy's cho_solve_banded wrapper costs more than the solve.
        x, info = self._pbtrs(self.cb, b, lower=0)
        if info != 0:
            raise SimulationError(f"banded solve failed (LAPACK info {info})")
        return x

    def inverse_rows(self, dofs: np.ndarray) -> np.ndarray:
        """(len(dofs), n) rows (= columns, A is symmetric) of A^{-1}, computed once per dof and cached."""
        slots = self._slot[dofs]
        if np.any(slots < 0):
            missing = np.unique(dofs[slots < 0])
            used = int(self._used[0])
            need = used + missing.size
            if need > self._rows.shape[0]:
                grown = np.zeros((max(need, 2 * self._rows.shape[0], 32), self.n))
                grown[:used] = self._rows[:used]
                self._rows = grown
            E = np.zeros((self.n, missing.size))
            E[missing, np.arange(missing.size)] = 1.0
            self._rows[used:need] = self.solve(E).T
            self._slot[missing] = np.arange(used, need)
            self._used[0] = need
            slots = self._slot[dofs]
        return self._rows[slots]


_FACTORS: "OrderedDict[bytes, _BandedSPD]" = OrderedDict()
_FACTORS_KEPT = 4


def _factor_of(A: sp.csr_matrix) -> _BandedSPD:
    """The banded Cholesky factor of ``A``, shared by every model of this process with the
    same system matrix (least recently used of :data:`_FACTORS_KEPT` kept).

    Fits and diagnoses replay many models that differ only in what leaves the matrix alone
    (the probe input, a body force, friction): a factorisation cost as much as the replay
    of a 6 s sequence on the 13x5x5 grid, and the cached rows of the inverse that contact
    builds up are shared too."""
    A = A.tocsr()
    A.sort_indices()
    h = hashlib.blake2b(digest_size=20)
    for arr in (np.asarray(A.shape, dtype=np.int64), A.indptr, A.indices, A.data):
        h.update(np.ascontiguousarray(arr).tobytes())
    key = h.digest()
    f = _FACTORS.get(key)
    if f is None:
        f = _BandedSPD(A)
        _FACTORS[key] = f
        while len(_FACTORS) > _FACTORS_KEPT:
            _FACTORS.popitem(last=False)
    else:
        _FACTORS.move_to_end(key)
    return f


@dataclass(frozen=True)
class Model:
    """Immutable simulation model. Build with :func:`build_model`.

    Attributes:
        mesh: the tetrahedral mesh (rest shape, phantom frame).
        material: base material; per-element moduli are ``mu``, ``lam``.
        config: numerical settings.
        effects: the model options it was built with (including input-side ones,
            applied to the probe path by the solver).
        elements: per-element operators.
        node_mass: (N,) kg. mu, lam: (E,) Lamé parameters, Pa.
        free: (N,) bool, nodes that move. free_dofs: (3F,) flat dof indices.
        support_stiffness: (N,) N/m. body_force: (N, 3) N. friction: Coulomb mu.
        contact_stiffness: penalty stiffness of the probe contact per unit area, Pa/m
            (``config.contact_stiffness``, or its per-modulus default times E).
        K: (3N, 3N) CSR small-strain elastic stiffness (no supports), N/m.
        terms: extra stress terms (e.g. a Maxwell arm).
        mass_dofs: (3N,) node masses repeated per dof, kg.
        free_index: (3N,) int64, dof -> index among free dofs, -1 for fixed dofs.
        scratch_slot: (3F,) int64 work array of the contact kernel (all -1 between calls).
        has_body_force, has_supports: whether those arrays are non-zero (checked once).
    """

    mesh: TetMesh
    material: Material
    config: SimulationConfig
    effects: tuple[Effect, ...]
    elements: fem.ElementData
    node_mass: np.ndarray
    mu: np.ndarray
    lam: np.ndarray
    free: np.ndarray
    free_dofs: np.ndarray
    support_stiffness: np.ndarray
    body_force: np.ndarray
    friction: float
    K: sp.csr_matrix
    terms: tuple
    mass_dofs: np.ndarray = field(repr=False, default=None)
    free_index: np.ndarray = field(repr=False, default=None)
    scratch_slot: np.ndarray = field(repr=False, default=None)
    has_body_force: bool = False
    has_supports: bool = False
    contact_stiffness: float = 1e9
    _factor: _BandedSPD | None = field(repr=False, default=None)

    @property
    def needs_rotation(self) -> bool:
        return self.material.law == "corotational" or any(getattr(t, "needs_rotation", False) for t in self.terms)

    @property
    def mass(self) -> float:
        return float(self.node_mass.sum())

    def initial_state(self) -> "State":
        """The rest state: nodes at the mesh's rest positions, zero velocity.

        With body forces (gravity) use ``core.simulation.static_equilibrium`` to start
        from the sagged equilibrium instead.
        """
        n_el = self.mesh.n_tets
        q = np.zeros((4, n_el))
        q[3] = 1.0
        return State(
            x=self.mesh.nodes.copy(),
            v=np.zeros_like(self.mesh.nodes),
            q=q,
            term_state=tuple(t.init_state(n_el) for t in self.terms),
            t=0.0,
        )


@dataclass
class State:
    """Changing simulation state.

    Attributes:
        x: (N, 3) node positions, m, phantom frame.
        v: (N, 3) node velocities, m/s.
        q: (4, E) per-element rotation quaternions (warm start of the polar decomposition).
        term_state: internal variables of the extra stress terms (one entry per term).
        t: simulation time, s.
    """

    x: np.ndarray
    v: np.ndarray
    q: np.ndarray
    term_state: tuple
    t: float = 0.0

    def copy(self) -> "State":
        return State(self.x.copy(), self.v.copy(), self.q.copy(), tuple(s.copy() for s in self.term_state), self.t)


def build_model(
    mesh: TetMesh,
    mass: float,
    material: Material,
    config: SimulationConfig | None = None,
    effects: Sequence[Effect] = (),
    *,
    factorize: bool = True,
) -> Model:
    """Assemble a model: lumped masses, per-element materials, supports, the constant
    implicit-Euler system matrix (factorised once) and the effects' options.

    Args:
        mesh: rest mesh in the phantom frame.
        mass: total phantom mass in kg (from session.json); density = mass / volume.
        material: base material.
        config: numerical settings (defaults: paper's Rayleigh 0.1/0.1, dt = 1/120 s).
        effects: model options (see :mod:`core.simulation.effects`).
        factorize: factorise the implicit-Euler system matrix (False: a model that cannot
            be stepped, whose arrays a sensitivity computation differentiates).

    Raises:
        SimulationError: non-physical parameters, a mesh without fixed or supported
            nodes (rigid-body motion), or a singular system.
    """
    config = config or SimulationConfig()
    if not (np.isfinite(mass) and mass > 0):
        raise SimulationError(f"phantom mass must be positive, got {mass}")
    builder = ModelBuilder(mesh, mass)
    for effect in effects:
        if not isinstance(effect, Effect):
            raise SimulationError(f"effects must be Effect objects, got {type(effect).__name__}")
        effect.configure(builder)
    if not np.any(builder.fixed) and not np.any(builder.support_stiffness > 0):
        raise SimulationError("the model has neither fixed nor supported nodes")
    mu, lam = fem.lame_parameters(material.youngs_modulus * builder.element_scale, material.poisson_ratio)
    K = fem.linear_stiffness(builder.elements, mu, lam)
    free = ~builder.fixed
    free_dofs = (3 * np.flatnonzero(free)[:, None] + np.arange(3)[None, :]).ravel()
    free_index = np.full(3 * mesh.n_nodes, -1, dtype=np.int64)
    free_index[free_dofs] = np.arange(free_dofs.size)
    factor = None
    if config.integrator == "implicit_euler" and factorize:
        dt = config.dt
        m3 = np.repeat(builder.node_mass, 3)
        k_lhs = dt * config.rayleigh_stiffness + dt * dt * (1.0 + sum(t.lhs_scale(dt) for t in builder.terms))
        A = (
            sp.diags((1.0 + dt * config.rayleigh_mass) * m3 + dt * dt * np.repeat(builder.support_stiffness, 3))
            + k_lhs * K
        ).tocsr()[free_dofs][:, free_dofs]
        factor = _factor_of(A)
    return Model(
        mesh=mesh,
        material=material,
        config=config,
        effects=tuple(effects),
        elements=builder.elements,
        node_mass=builder.node_mass,
        mu=np.asarray(mu, dtype=np.float64),
        lam=np.asarray(lam, dtype=np.float64),
        free=free,
        free_dofs=free_dofs,
        support_stiffness=builder.support_stiffness,
        body_force=builder.body_force,
        friction=float(builder.friction),
        K=K,
        terms=tuple(builder.terms),
        mass_dofs=np.repeat(builder.node_mass, 3),
        free_index=free_index,
        scratch_slot=np.full(free_dofs.size, -1, dtype=np.int64),
        has_body_force=bool(np.any(builder.body_force)),
        has_supports=bool(np.any(builder.support_stiffness)),
        contact_stiffness=float(config.contact_stiffness if config.contact_stiffness is not None
                                else config.contact_stiffness_per_modulus * material.youngs_modulus),
        _factor=factor,
    )
