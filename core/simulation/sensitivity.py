"""Sensitivities of a replay: derivatives of its node trajectories and probe force with
respect to model parameters, by forward (tangent-linear) differentiation of the time
stepping.

A replay is a map from parameters ``theta`` (Young's modulus, Poisson's ratio, any effect
kind's fit variables) to a model (:func:`core.simulation.build_model`: element moduli,
contact stiffness, body forces, supports, friction, Maxwell arms, the probe input) and
from the model to trajectories (:func:`core.simulation.simulate`). The second map is
differentiated exactly: every step of :mod:`core.simulation.stepper` propagates the
derivative of its state along each direction (:mod:`core.simulation.tangent_step`); the
p directions share the step's factorised matrix and capacitance matrix as extra
right-hand sides. The first map, which runs no simulation and is smooth (moduli linear
in E, an inclusion's volume fractions piecewise linear in its centre and radius, a
clock offset a shift of a piecewise-linear path), is differentiated by central
differences of the model's arrays with steps of 1e-4 of each parameter's scale, whose
error (O(h^2), ~1e-8 relative) is far below that of any finite difference of a
replay. So a kind declared as a model option (:mod:`core.simulation.effects`) gets its
sensitivities without code of its own.

Held fixed, as in any tangent-linear model of a piecewise-smooth simulation: the active
contact set and friction's slip branch of each step, the contact point's region on its
triangle, and the warm-started polar iteration's branch. Derivatives with respect to a
friction coefficient at zero friction are not provided (the friction rows do not exist
there).

The initial state of a model with body forces is its static equilibrium; its tangent
solves ``K_t dx = d(body force) + df/dtheta`` by chord iterations on the rest stiffness.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from core.errors import SimulationError
from core.simulation import stepper
from core.simulation.lowrank import lapack_pbtrs
from core.simulation.model import MaxwellArm, Model, State
from core.preparation.probe import ProbePath
from core.simulation.solver import SimulationResult, no_rest_state, static_equilibrium
from core.simulation.timeloop import advance_or_diverge, clock_shift, divergence_message, model_tuple, step_grid
from core.simulation.tangent import element_forces_tangent

__all__ = ["Sensitivities", "ModelDerivatives", "model_derivatives", "simulate_sensitivities"]

Builder = Callable[[np.ndarray, bool], Model]
"""``build(theta (p,), factorize) -> Model``: the model at the parameters ``theta``."""

REL_STEP = 1e-4
"""Central-difference step of the model's arrays, as a fraction of each parameter's scale."""


@dataclass(frozen=True)
class ModelDerivatives:
    """Derivatives of a model's arrays along p parameter directions.

    Attributes:
        mu, lam: (p, E) element Lamé parameters, Pa per unit. contact_stiffness: (p,)
            Pa/m per unit. body_force: (p, N, 3) N per unit. support_stiffness: (p, N)
            N/m per unit. friction: (p,) per unit. tau, k: (p, T) the Maxwell arms'
            relaxation times (s) and stiffness ratios per unit. k_lhs: (p,) of the system
            matrix's stiffness coefficient (s^2). centres: (p, K + 1, 3) of the probe
            centre at every step (m per unit). radius: (p,) of the probe radius.
            clock: (p,) of the step grid's clock shift (s per unit): a clock offset moves
            the grid with the probe (:func:`core.simulation.timeloop.step_grid`), so its
            centres stay and the output times move against the steps.
    """

    mu: np.ndarray
    lam: np.ndarray
    contact_stiffness: np.ndarray
    body_force: np.ndarray
    support_stiffness: np.ndarray
    friction: np.ndarray
    tau: np.ndarray
    k: np.ndarray
    k_lhs: np.ndarray
    centres: np.ndarray
    radius: np.ndarray
    clock: np.ndarray

    def kernel_tuple(self) -> tuple:
        """``dmdl`` of :func:`core.simulation.stepper.advance`."""
        return (self.mu, self.lam, self.contact_stiffness, self.body_force, self.support_stiffness, self.friction,
                self.tau, self.k, self.k_lhs, self.radius)


@dataclass(frozen=True)
class Sensitivities:
    """A replay and its derivatives along p parameter directions.

    Attributes:
        result: the replay (:class:`core.simulation.solver.SimulationResult`).
        names: the parameters' names.
        positions: (p, F, N, 3) float64 d positions / d parameter, m per unit, phantom frame.
        contact_force: (p, F, 3) float64 d force / d parameter, N per unit, at the robot's
            samples of the output times, as ``result.contact_force`` (a clock offset moves
            neither).
    """

    result: SimulationResult
    names: tuple[str, ...]
    positions: np.ndarray
    contact_force: np.ndarray


def _k_lhs(m: Model) -> float:
    dt = m.config.dt
    return dt * m.config.rayleigh_stiffness + dt * dt * (1.0 + sum(t.lhs_scale(dt) for t in m.terms))


def _same_structure(a: Model, b: Model) -> bool:
    return (np.array_equal(a.free, b.free) and len(a.terms) == len(b.terms) and a.material.law == b.material.law
            and a.mesh is b.mesh and a.config == b.config)


def model_derivatives(build: Builder, theta, scales, path: ProbePath, probe_radius: float, step_t: np.ndarray,
                      model: Model | None = None) -> ModelDerivatives:
    """Central differences of the model's arrays and of its probe input along each
    parameter (see the module docstring).

    Args:
        build: ``build(theta, factorize) -> Model``.
        theta: (p,) parameters. scales: (p,) their scales (a fit's steps): the difference
            step is :data:`REL_STEP` times each.
        path: the recorded probe path (before the model's input-side effects);
            probe_radius: its nominal radius, m. step_t: (K + 1,) the replay's step times, s.

    Raises:
        SimulationError: a parameter whose change alters the model's structure (its free
            nodes, its extra stress terms, its law or mesh).
    """
    theta = np.asarray(theta, dtype=np.float64).reshape(-1)
    scales = np.asarray(scales, dtype=np.float64).reshape(-1)
    p = theta.size
    base = model or build(theta, False)
    N, E, T = base.mesh.n_nodes, base.mesh.n_tets, len(base.terms)
    out = {k: [] for k in ("mu", "lam", "kc", "body", "support", "friction", "tau", "k", "k_lhs", "centres", "radius",
                           "clock")}
    shift0 = clock_shift(base)
    for j in range(p):
        h = REL_STEP * (scales[j] if scales[j] > 0 else max(abs(theta[j]), 1.0))
        pair = []
        for sign in (1.0, -1.0):
            th = theta.copy()
            th[j] += sign * h
            m = build(th, False)
            if not _same_structure(m, base):
                raise SimulationError(f"parameter {j} changes the model's structure at {theta[j]:g} (step {h:g})")
            pth, r = path, float(probe_radius)
            for effect in m.effects:
                pth, r = effect.transform_probe(pth, r)
            shift = clock_shift(m)  # the steps of m's own grid
            pair.append((m, pth.at(step_t + (shift - shift0)), r, shift))
        (mp, cp, rp, sp_), (mm, cm, rm, sm) = pair
        d = 2.0 * h
        out["mu"].append((mp.mu - mm.mu) / d)
        out["lam"].append((mp.lam - mm.lam) / d)
        out["kc"].append((mp.contact_stiffness - mm.contact_stiffness) / d)
        out["body"].append((mp.body_force - mm.body_force) / d)
        out["support"].append((mp.support_stiffness - mm.support_stiffness) / d)
        out["friction"].append((mp.friction - mm.friction) / d)
        out["tau"].append(np.array([(a.tau - b.tau) / d for a, b in zip(mp.terms, mm.terms)], dtype=np.float64))
        out["k"].append(np.array([(a.k - b.k) / d for a, b in zip(mp.terms, mm.terms)], dtype=np.float64))
        out["k_lhs"].append((_k_lhs(mp) - _k_lhs(mm)) / d)
        out["centres"].append((cp - cm) / d)
        out["radius"].append((rp - rm) / d)
        out["clock"].append((sp_ - sm) / d)

    def stack(key, shape):
        return np.ascontiguousarray(np.array(out[key], dtype=np.float64).reshape((p,) + shape))

    return ModelDerivatives(
        mu=stack("mu", (E,)), lam=stack("lam", (E,)), contact_stiffness=stack("kc", ()),
        body_force=stack("body", (N, 3)), support_stiffness=stack("support", (N,)), friction=stack("friction", ()),
        tau=stack("tau", (T,)), k=stack("k", (T,)), k_lhs=stack("k_lhs", ()),
        centres=stack("centres", (step_t.size, 3)), radius=stack("radius", ()), clock=stack("clock", ()))


def _equilibrium_tangent(model: Model, state: State, dm: ModelDerivatives, *, tol: float = 1e-10,
                         max_iterations: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """(dx (p, N, 3), dq (p, 4, E)): the tangent of :func:`core.simulation.static_equilibrium`
    (no probe, dt = 1 s for the Maxwell arms, no damping) at its solution ``state``."""
    p = dm.mu.shape[0]
    N, E = model.mesh.n_nodes, model.mesh.n_tets
    el = model.elements
    free = model.free
    dofs = (3 * np.flatnonzero(free)[:, None] + np.arange(3)).ravel()
    Ks = (model.K + sp.diags(np.repeat(model.support_stiffness, 3))).tocsc()[dofs][:, dofs]
    lu = spla.splu(Ks.tocsc())
    law = {"corotational": 0, "stable_neo_hookean": 1, "stable_yeoh": 2}[model.material.law]
    iters = model.config.polar_iterations if model.needs_rotation else 0
    tau = np.array([t.tau for t in model.terms], dtype=np.float64)
    kr = np.array([t.k for t in model.terms], dtype=np.float64)
    T = tau.size
    eps0 = np.zeros((T, 9, E))
    deps0 = np.zeros((p, T, 9, E))
    zeros_v = np.zeros((N, 3))
    dx = np.zeros((p, N, 3))
    dq0 = np.zeros((p, 4, E))
    q_out = np.empty((4, E))
    dq_out = np.empty((p, 4, E))
    deps_out = np.empty((p, T, 9, E))
    df = np.empty((p, N, 3))
    f = np.empty((N, 3))
    eps_new = np.empty((T, 9, E))
    x = np.ascontiguousarray(state.x)
    scale = None
    for _ in range(max_iterations):
        element_forces_tangent(x, zeros_v, dx, np.zeros((p, N, 3)), model.mesh.tets, el.grad_n, el.volume, model.mu,
                               model.lam, dm.mu, dm.lam, law, float(model.material.stiffening), state.q, dq0, iters,
                               0.0, tau, kr, dm.tau, dm.k, eps0, deps0, 1.0, q_out, dq_out, deps_out, df, f, eps_new)
        g = df + dm.body_force - dm.support_stiffness[:, :, None] * (x - model.mesh.nodes)[None] \
            - model.support_stiffness[None, :, None] * dx
        gf = g.reshape(p, -1)[:, dofs]
        if scale is None:  # the first residual is the right-hand side: d(body force) + df/dtheta
            scale = np.maximum(np.abs(gf).max(axis=1, initial=0.0), 1e-300)
        if np.all(np.abs(gf).max(axis=1, initial=0.0) <= tol * scale):
            break
        step = lu.solve(np.ascontiguousarray(gf.T)).T
        flat = dx.reshape(p, -1)
        flat[:, dofs] += step
    else:
        raise SimulationError(f"the equilibrium's tangent did not converge in {max_iterations} iterations")
    return dx, dq_out.copy()


def simulate_sensitivities(build: Builder, theta, path: ProbePath, probe_radius: float, output_times, *,
                           scales=None, names=None) -> Sensitivities:
    """Replay ``path`` with the model ``build(theta, True)`` and differentiate the node
    trajectories and the probe force with respect to every entry of ``theta``.

    Args:
        build: ``build(theta (p,), factorize: bool) -> Model`` (a
            :class:`core.simulation.Model` with the compiled implicit-Euler stepper and
            Maxwell arms as its only extra stress terms).
        theta: (p,) parameters (e.g. log10 E and an effect kind's fit variables).
        path: the recorded probe path, phantom frame (the model's input-side effects are
            applied as in :func:`core.simulation.simulate`). probe_radius: nominal, m.
        output_times: (F,) s.
        scales: (p,) each parameter's scale (a fit's step); default 1.
        names: (p,) names for the result.

    Returns:
        :class:`Sensitivities`; on divergence the result's status says so and the
        derivatives are NaN from there on.

    Raises:
        SimulationError: bad inputs, a model the compiled stepper cannot run, a parameter
            that changes the model's structure, or an equilibrium tangent that does not
            converge.
    """
    theta = np.asarray(theta, dtype=np.float64).reshape(-1)
    p = theta.size
    scales = np.ones(p) if scales is None else np.asarray(scales, dtype=np.float64).reshape(-1)
    names = tuple(names) if names is not None else tuple(f"theta{j}" for j in range(p))
    model = build(theta, True)
    if model._factor is None or model.config.integrator != "implicit_euler" or not all(
            type(t) is MaxwellArm for t in model.terms):
        raise SimulationError("sensitivities need the implicit-Euler model with Maxwell arms as its only extra terms")
    import time

    t_wall = time.perf_counter()
    grid = step_grid(model, path, probe_radius, output_times)
    times, tpath, radius, t0, step_t, centres, k_of = grid
    dm = model_derivatives(build, theta, scales, path, probe_radius, step_t)
    N, E, T = model.mesh.n_nodes, model.mesh.n_tets, len(model.terms)
    F = times.size
    n_steps = step_t.size - 1
    if model.has_body_force:
        try:
            state = static_equilibrium(model)[0]
            dx, dq = _equilibrium_tangent(model, state, dm)
        except SimulationError as exc:  # no rest state (e.g. gravity on a far too soft phantom), as simulate()
            result = no_rest_state(grid, N, exc, time.perf_counter() - t_wall)
            F_frames = grid.frame_times.size
            return Sensitivities(result, names, np.full((p, F_frames, N, 3), np.nan), np.full((p, F_frames, 3), np.nan))
    else:
        state = model.initial_state()
        dx, dq = np.zeros((p, N, 3)), np.zeros((p, 4, E))
    x, v, q = state.x.copy(), state.v.copy(), np.ascontiguousarray(state.q).copy()
    eps_v = np.ascontiguousarray(np.stack(state.term_state)) if T else np.zeros((0, 9, E))
    dv = np.zeros((p, N, 3))
    deps = np.zeros((p, T, 9, E))
    out_x = np.full((F, N, 3), np.nan)
    out_f = np.full((F, 3), np.nan)
    dout_x = np.full((p, F, N, 3), np.nan)
    dout_f = np.full((p, F, 3), np.nan)
    j = 0
    while j < F and k_of[j] == 0:
        out_x[j], out_f[j] = x, 0.0
        dout_x[:, j], dout_f[:, j] = dx, 0.0
        j += 1
    limit = model.config.divergence_limit * float(np.linalg.norm(model.mesh.size))
    fac = model._factor
    # a camera frame's time moves against the grid as the clock shift does; a robot
    # sample moves with it (:func:`core.simulation.timeloop.step_grid`)
    dphase = np.zeros((p, F))
    dphase[:, grid.camera] = -dm.clock[:, None]  # (the robot's samples are other indices then)
    code, k, j, disp, rows = advance_or_diverge(
        model_tuple(model), lapack_pbtrs(), fac.cbT, fac._rows, fac._slot, fac._used, centres, float(radius),
        x, v, q, eps_v, times, step_t, k_of, 0, False, j, F, out_x, out_f, x.copy(), np.zeros(3), limit, np.zeros(3),
        dm.kernel_tuple(), dm.centres, dphase, dx, dv, dq, deps, dout_x, dout_f, dx.copy(), np.zeros((p, 3)), np.zeros((p, 3)),
        k=0, j=j)
    fac._rows = rows
    status, message = "ok", ""
    if code in (stepper.STATUS_NONFINITE, stepper.STATUS_TOO_FAR):
        status, message = "diverged", divergence_message(step_t[k], k, disp)
    positions, force = grid.frames(out_x, out_f)
    result = SimulationResult(times=grid.frame_times, positions=positions, contact_force=force,
                              probe_centres=tpath.at(grid.frame_times), probe_radius=float(radius), status=status,
                              message=message, steps=k if n_steps else 0, wall_time=time.perf_counter() - t_wall)
    dpositions, dforce = grid.frames(dout_x, dout_f)
    return Sensitivities(result=result, names=names, positions=dpositions, contact_force=dforce)


def finite_difference(build: Builder, theta, path: ProbePath, probe_radius: float, output_times, j: int,
                      h: float) -> tuple[np.ndarray, np.ndarray]:
    """Central finite difference of a whole replay along parameter ``j`` with step ``h``:
    ``(d positions (F, N, 3), d force (F, 3))``, the reference the sensitivities are
    tested against."""
    from core.simulation.solver import simulate

    theta = np.asarray(theta, dtype=np.float64).reshape(-1)
    res = []
    for sign in (1.0, -1.0):
        th = theta.copy()
        th[j] += sign * h
        r = simulate(build(th, True), path, probe_radius, output_times)
        if not r.ok:
            raise SimulationError(f"the replay diverged at parameter {j} = {th[j]:g}: {r.message}")
        res.append(r)
    return ((res[0].positions - res[1].positions) / (2.0 * h),
            (res[0].contact_force - res[1].contact_force) / (2.0 * h))

