"""Time stepping: implicit Euler with Rayleigh damping and penalty sphere contact.

One step solves ``(M + dt C + dt^2 K0) dv = dt (f(x + dt v) - C v)`` for the velocity
change, where ``f`` are the corotational (or neo-Hookean) internal forces evaluated
exactly and ``K0`` is the constant rest stiffness, factorised once per model (a
constant-Jacobian Newton step; Baraff & Witkin 1998 linearise the same way). With the
paper's stiffness damping (beta = 0.1 s) ``dt*beta*K0`` dominates the matrix, so the
constant Jacobian is an excellent approximation and one correction per step suffices.

Contact constraints enter as low-rank terms ``sum_c w_c h_c h_c^T`` handled by the
Sherman-Morrison-Woodbury identity on top of the constant factorisation, with cached
columns of its inverse: contact never triggers a refactorisation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from core.errors import SimulationError
from core.simulation import kernels
from core.simulation.contact import Contacts, find_contacts
from core.simulation.model import Model, State
from core.simulation.timeloop import (StepGrid, apply_hook, compilable, divergence_message, model_tuple, no_tangents,
                                      run_compiled, step_grid)
from core.preparation.probe import ProbePath

__all__ = ["SimulationResult", "StepInfo", "StepGrid", "step", "simulate", "step_grid", "static_equilibrium",
           "internal_forces", "model_tuple", "no_tangents", "divergence_message"]

ProgressCallback = Callable[[float, str], None]
FrameHook = Callable[[int, float, np.ndarray], "np.ndarray | None"]
"""``frame_hook(j, t_j, positions (N, 3) m) -> corrected (N, 3) positions or None``."""


@dataclass(frozen=True)
class StepInfo:
    """What a step reports besides the new state.

    Attributes:
        contact_force: (3,) N, force the probe applies to the phantom, phantom frame.
        n_contacts: number of active contact constraints.
    """

    contact_force: np.ndarray
    n_contacts: int


@dataclass(frozen=True)
class SimulationResult:
    """Evidence of a replay.

    Attributes:
        times: (F,) output times, s.
        positions: (F, N, 3) float64 node positions at ``times``, m, phantom frame
            (NaN after a divergence).
        contact_force: (F, 3) N, force applied by the probe on the phantom, phantom frame,
            at the robot's sample of each output time (the robot's clock stamps the
            kinematics and the force alike: with a clock offset c, the replay's time
            t + c; without one, ``times``), so that it compares with the measured force
            rows at ``times`` whatever the offset.
        probe_centres: (F, 3) m, the (effect-transformed) probe centres used.
        probe_radius: m, the radius used.
        status: "ok" or "diverged".
        message: why it diverged ("" when ok).
        steps: number of time steps taken.
        wall_time: s.
    """

    times: np.ndarray
    positions: np.ndarray
    contact_force: np.ndarray
    probe_centres: np.ndarray
    probe_radius: float
    status: str
    message: str
    steps: int
    wall_time: float

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def internal_forces(model: Model, x: np.ndarray, state: State, dt: float, v: np.ndarray | None = None):
    """Internal + external (body, support) nodal forces at positions x, plus the
    Rayleigh stiffness damping ``-beta K v`` when velocities ``v`` (N, 3) are given.

    Returns:
        (f (N, 3) N, q (4, E) updated rotations, term_state tuple of updated internals).
    """
    el = model.elements
    q = state.q.copy()
    n_el = model.mesh.n_tets
    store = bool(model.terms)
    F = np.empty((n_el, 9) if store else (1, 9))
    R = np.empty((n_el, 9) if store else (1, 9))
    iters = model.config.polar_iterations if model.needs_rotation else 0
    law = {"corotational": 0, "stable_neo_hookean": 1, "stable_yeoh": 2}[model.material.law]
    beta = model.config.rayleigh_stiffness if v is not None else 0.0
    vv = v if v is not None else x[:1]
    f = kernels.element_forces(
        x, model.mesh.tets, el.grad_n, el.volume, model.mu, model.lam, q, iters, law, F, R, store, vv, beta,
        float(model.material.stiffening),
    )
    new_terms = []
    for term, s in zip(model.terms, state.term_state):
        Pt, s_new = term.stress(model, F.T, R.T, s, dt)
        f += kernels.scatter_forces(np.ascontiguousarray(Pt.T), model.mesh.tets, el.grad_n, el.volume, x.shape[0])
        new_terms.append(s_new)
    if model.has_body_force:
        f += model.body_force
    if model.has_supports:
        f -= model.support_stiffness[:, None] * (x - model.mesh.nodes)
    return f, q, tuple(new_terms)


def _woodbury_solve(model: Model, rhs, blocks, y=None):
    """Solve ``(A + H diag(omega) H^T) d = rhs + H beta`` with A's cached factor.

    ``blocks`` is a list of (nodes (k,3), weights (k,3), directions (k,3), omega (k,),
    beta (k,)) constraint groups (normal contact, friction tangents). ``y``: ``A^-1 rhs``
    when already known (the active-set passes of a step share it).
    """
    factor = model._factor
    if y is None:
        y = factor.solve(rhs)
    blocks = [b for b in blocks if b[0].shape[0]]
    if not blocks:
        return y
    nodes = np.concatenate([b[0] for b in blocks]) if len(blocks) > 1 else blocks[0][0]
    weights = np.concatenate([b[1] for b in blocks]) if len(blocks) > 1 else blocks[0][1]
    dirs = np.concatenate([b[2] for b in blocks]) if len(blocks) > 1 else blocks[0][2]
    omega = np.concatenate([b[3] for b in blocks]) if len(blocks) > 1 else blocks[0][3]
    beta = np.concatenate([b[4] for b in blocks]) if len(blocks) > 1 else blocks[0][4]
    uniq, C = kernels.constraint_matrix(nodes, weights, dirs, model.free_index, model.scratch_slot)
    if uniq.size == 0:
        return y
    # H = E_uniq C, so A^{-1} H = rows^T C with rows = A^{-1}[uniq, :] (m, n): the (k, n)
    # product (A^{-1} H)^T is never formed, two vector products over rows replace it
    rows = factor.inverse_rows(uniq)
    y = y + (C @ beta) @ rows
    S = C.T @ rows[:, uniq] @ C
    S.flat[:: S.shape[0] + 1] += 1.0 / omega
    return y - (C @ np.linalg.solve(S, C.T @ y[uniq])) @ rows


def _tangents(n: np.ndarray):
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def step(model: Model, state: State, centre: np.ndarray, radius: float, probe_velocity=None) -> tuple[State, StepInfo]:
    """Advance one time step of ``model.config.dt`` with the probe at ``centre`` at the step's end.

    Args:
        model: the static model.
        state: the current state (not modified).
        centre: (3,) probe sphere centre at the end of the step, m, phantom frame.
        radius: probe radius, m.
        probe_velocity: (3,) m/s, used by friction (defaults to zero).

    Returns:
        (new state, :class:`StepInfo`).
    """
    cfg = model.config
    dt = cfg.dt
    centre = np.asarray(centre, dtype=np.float64)
    vp = np.zeros(3) if probe_velocity is None else np.asarray(probe_velocity, dtype=np.float64)
    tris = model.mesh.surface_triangles
    if cfg.integrator == "symplectic_euler":
        return _step_explicit(model, state, centre, radius, vp)

    m3 = model.mass_dofs
    fd = model.free_dofs
    v0 = state.v.ravel()
    x0 = state.x.ravel()
    vg = v0
    contacts = candidates = active = None
    q, terms = state.q, state.term_state
    for it in range(cfg.newton_iterations):
        xp = x0 + dt * vg
        f, q, terms = internal_forces(model, xp.reshape(-1, 3), state, dt, vg.reshape(-1, 3))  # includes -beta K v
        r = (dt * (f.ravel() - cfg.rayleigh_mass * m3 * vg) - m3 * (vg - v0))[fd]
        if it == 0:
            # candidates: every triangle within a margin of the sphere, so that a triangle
            # the step pushes into the sphere is handled in this step, not the next
            candidates = find_contacts(xp.reshape(-1, 3), tris, centre, radius + cfg.contact_margin,
                                           cfg.contact_subdivision)
            active = _gap(candidates, xp.reshape(-1, 3), centre, radius) > 0
        # active set of the linearised contact problem (a QP in the contact forces):
        # a constraint that would pull is released, a candidate the step pushes inside is
        # added, until neither happens (Nocedal & Wright, Sec. 16.5). Deciding only from
        # the gaps at the step's start made a stiff contact chatter with period two steps
        # (on, pushed out, off, falls in), with a steady force that depended on dt.
        y = model._factor.solve(r)
        x_try = xp
        for _ in range(cfg.contact_iterations):
            contacts = _subset(candidates, active)
            blocks = _constraint_blocks(model, contacts, xp, vg, vp, dt, centre, radius, friction=False)
            dv = _woodbury_solve(model, r, blocks, y)
            if len(candidates) == 0:
                break
            x_try = xp.copy()
            x_try[fd] += dt * dv
            g = _gap(candidates, x_try.reshape(-1, 3), centre, radius)
            changed = (active & (g < 0)) | (~active & (g > cfg.contact_tolerance))
            if not np.any(changed):
                break
            active = active ^ changed
        if model.friction > 0 and len(contacts):
            # Coulomb friction bounded by the normal force this step's contact solve found:
            # with a stiff contact the gap at the step's start says nothing about it (a
            # contact activated by the solve starts at zero gap, which gave no friction)
            fn = model.contact_stiffness * contacts.area * np.maximum(_gap(contacts, x_try.reshape(-1, 3), centre, radius), 0.0)
            blocks = _constraint_blocks(model, contacts, xp, vg, vp, dt, centre, radius, normal_force=fn)
            dv = _woodbury_solve(model, r, blocks, y)
        vg = vg.copy()
        vg[fd] += dv
    x_new = x0 + dt * vg
    xn = x_new.reshape(-1, 3)
    force = np.zeros(3)
    if len(contacts):
        phi = np.maximum(_gap(contacts, xn, centre, radius), 0.0)
        fn = model.contact_stiffness * contacts.area * phi
        force = (fn[:, None] * contacts.normals).sum(0)
        # friction: the implicit tangential force c_t (v_probe - v_point) . t of each tangent row
        v_new = vg.reshape(-1, 3)
        for nodes, weights, dirs, omega, _ in blocks[1:]:
            v_pt = np.einsum("kj,kjd->kd", weights, v_new[nodes])
            rel = dirs @ vp - np.einsum("kd,kd->k", dirs, v_pt)
            force = force + ((omega / dt) * rel) @ dirs
    new = State(x=xn, v=vg.reshape(-1, 3), q=q, term_state=terms, t=state.t + dt)
    return new, StepInfo(contact_force=force, n_contacts=len(contacts))


def _subset(c: Contacts, keep: np.ndarray) -> Contacts:
    if np.all(keep):
        return c
    return Contacts(c.triangles[keep], c.nodes[keep], c.weights[keep], c.normals[keep], c.depth[keep], c.area[keep],
                    None if c.sub is None else c.sub[keep], None if c.sub_weights is None else c.sub_weights[keep])


def _gap(c: Contacts, x: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Penetration along the frozen normal: ``r - n.(sum_j w_j x_j - centre)`` (> 0 inside)."""
    p = np.einsum("kj,kjd->kd", c.weights, x[c.nodes])
    return radius - np.einsum("kd,kd->k", c.normals, p - centre)


def _constraint_blocks(model: Model, c: Contacts, xp, vg, vp, dt, centre, radius, *, friction: bool = True,
                       normal_force=None):
    """Low-rank terms of the active contacts: penalty along the normal, and
    regularised Coulomb friction along two tangents (Wriggers, "Computational
    Contact Mechanics", Sec. 5.2: viscous regularisation of the stick branch), bounded by
    ``normal_force`` (k,) N (default: the penalty force of the gaps at ``xp``)."""
    cfg = model.config
    if len(c) == 0:
        return []
    k = model.contact_stiffness * c.area
    phi = _gap(c, xp.reshape(-1, 3), centre, radius)
    blocks = [(c.nodes, c.weights, c.normals, dt * dt * k, dt * k * phi)]
    if friction and model.friction > 0:
        fn = np.maximum(k * phi, 0.0) if normal_force is None else np.asarray(normal_force, dtype=np.float64)
        t1, t2 = _tangents(c.normals)
        v_pt = np.einsum("kj,kjd->kd", c.weights, vg.reshape(-1, 3)[c.nodes])
        rel = v_pt - vp[None, :]
        rel_t = rel - np.einsum("kd,kd->k", rel, c.normals)[:, None] * c.normals
        speed = np.maximum(np.linalg.norm(rel_t, axis=1), cfg.friction_slip_speed)
        w_t = dt * model.friction * fn / speed
        keep = w_t > 0
        if np.any(keep):
            for t in (t1, t2):
                beta = w_t * (t @ vp - np.einsum("kd,kd->k", t, v_pt))
                blocks.append((c.nodes[keep], c.weights[keep], t[keep], w_t[keep], beta[keep]))
    return blocks


def _step_explicit(model: Model, state: State, centre, radius, vp):
    """Symplectic (semi-implicit) Euler: conditionally stable, kept for comparison."""
    cfg = model.config
    dt = cfg.dt
    f, q, terms = internal_forces(model, state.x, state, dt)
    v = state.v.ravel()
    m3 = np.repeat(model.node_mass, 3)
    damp = cfg.rayleigh_mass * m3 * v + cfg.rayleigh_stiffness * (model.K @ v)
    contacts = find_contacts(state.x, model.mesh.surface_triangles, centre, radius, cfg.contact_subdivision)
    fc = np.zeros_like(state.x)
    force = np.zeros(3)
    if len(contacts):
        fn = model.contact_stiffness * contacts.area * np.maximum(contacts.depth, 0.0)
        for j in range(3):
            np.add.at(fc, contacts.nodes[:, j], (fn * contacts.weights[:, j])[:, None] * contacts.normals)
        force = (fn[:, None] * contacts.normals).sum(0)
    with np.errstate(over="ignore", invalid="ignore"):
        acc = (f.ravel() + fc.ravel() - damp) / m3
        v_new = np.zeros_like(v)
        v_new[model.free_dofs] = v[model.free_dofs] + dt * acc[model.free_dofs]
        x_new = state.x + dt * v_new.reshape(-1, 3)
    return State(x_new, v_new.reshape(-1, 3), q, terms, state.t + dt), StepInfo(force, len(contacts))


def no_rest_state(grid: StepGrid, n_nodes: int, exc: Exception, wall_time: float) -> SimulationResult:
    """The diverged result of a replay whose model has no rest state under its body
    forces (:func:`static_equilibrium` raised ``exc``): NaN positions (F, n_nodes, 3) and
    forces (F, 3) at ``grid.frame_times``, no steps."""
    F = grid.frame_times.size
    return SimulationResult(times=grid.frame_times, positions=np.full((F, n_nodes, 3), np.nan),
                            contact_force=np.full((F, 3), np.nan), probe_centres=grid.path.at(grid.frame_times),
                            probe_radius=float(grid.probe_radius), status="diverged",
                            message=f"no rest state under the body forces: {exc}", steps=0, wall_time=wall_time)


def static_equilibrium(
    model: Model,
    *,
    prescribed: dict[int, np.ndarray] | None = None,
    tol: float = 1e-10,
    max_iterations: int = 200,
) -> tuple[State, np.ndarray]:
    """Quasi-static equilibrium under the model's body forces and supports, with
    optional prescribed node positions (Dirichlet conditions), by Newton iterations
    with the constant rest stiffness (no probe).

    Args:
        model: the model (its fixed nodes stay at rest).
        prescribed: {node index: (3,) position in m} for additional Dirichlet nodes.
        tol: stop when the largest out-of-balance force is below ``tol`` times the
            largest force scale (N).

    Returns:
        (state, reactions): the equilibrium state and (N, 3) reaction forces in N
        (force the supports exert on each constrained node; zero on free nodes).

    Raises:
        SimulationError: if Newton does not converge.
    """
    state = model.initial_state()
    x = state.x.copy()
    constrained = ~model.free.copy()
    if prescribed:
        for node, pos in prescribed.items():
            x[node] = np.asarray(pos, dtype=np.float64)
            constrained[node] = True
    dofs = (3 * np.flatnonzero(~constrained)[:, None] + np.arange(3)).ravel()
    Ks = (model.K + sp.diags(np.repeat(model.support_stiffness, 3))).tocsc()[dofs][:, dofs]
    lu = spla.splu(Ks.tocsc())
    scale = None
    for _ in range(max_iterations):
        f, q, terms = internal_forces(model, x, state, 1.0)
        state = State(x, state.v, q, terms, 0.0)
        r = f.ravel()[dofs]
        if scale is None:
            scale = max(np.abs(f).max(), np.abs(model.body_force).max(), 1e-12)
        if np.abs(r).max() <= tol * scale:
            break
        xf = x.ravel().copy()
        xf[dofs] += lu.solve(r)
        x = xf.reshape(-1, 3)
    else:
        raise SimulationError(f"static equilibrium did not converge in {max_iterations} iterations")
    if not np.all(np.isfinite(x)) or np.abs(x - model.mesh.nodes).max() > model.config.divergence_limit * np.linalg.norm(model.mesh.size):
        raise SimulationError("static equilibrium left the phantom's size (collapse)")
    f, q, terms = internal_forces(model, x, state, 1.0)
    reactions = np.where(constrained[:, None], -f, 0.0)
    return State(x, np.zeros_like(x), q, terms, 0.0), reactions


def simulate(
    model: Model,
    path: ProbePath,
    probe_radius: float,
    output_times,
    *,
    state: State | None = None,
    callback: ProgressCallback | None = None,
    frame_hook: FrameHook | None = None,
) -> SimulationResult:
    """Replay a probe path and record node positions at the output (camera) times.

    The model's input-side effects (probe radius, clock offset, kinematic offset)
    are applied to the path first. The run starts from rest (or from the sagged
    equilibrium when the model has body forces) at ``min(path.t[0], output_times[0])``,
    moved with a clock offset (:func:`core.simulation.timeloop.step_grid`), and steps
    with ``model.config.dt``; positions at output times (and the force at their robot
    samples) are interpolated linearly between the bracketing steps.

    Args:
        model: the static model.
        path: probe sphere centres over time, phantom frame.
        probe_radius: m (session.json's value; a ProbeRadius effect overrides it).
        output_times: (F,) increasing times, s.
        state: optional start state (e.g. from a previous run).
        callback: ``callback(fraction, message)`` for progress.
        frame_hook: optional in-loop correction at the end of each output frame (Wu et
            al. 2020, Sec. 3.3: "at the end of each timestep, the simulator passes the
            position of the phantom mesh to the trained network"). Called as
            ``frame_hook(j, t_j, positions)`` with the frame index, its time (s) and a
            copy of the (N, 3) node positions (m, phantom frame) recorded for it; it
            returns None (no change) or corrected (N, 3) positions. The change is added
            to the positions of the current state's free nodes (fixed nodes never move;
            velocities are kept), the simulation continues from there, and the
            corrected positions are what the result records for frame j.

    Returns:
        A :class:`SimulationResult`. Divergence is reported in ``status``, not raised.

    Raises:
        SimulationError: on invalid inputs (empty or decreasing output times), or a
            ``frame_hook`` that returns an array of the wrong shape.
    """
    import time

    t_wall = time.perf_counter()
    grid = step_grid(model, path, probe_radius, output_times)
    times, path, probe_radius, t0, step_t, centres, k_of = grid
    n_steps = step_t.size - 1
    n_nodes = model.mesh.n_nodes
    if state is None:
        if model.has_body_force:
            try:
                state = static_equilibrium(model)[0]
            except SimulationError as exc:  # e.g. gravity on a far too soft phantom: it collapses
                return no_rest_state(grid, n_nodes, exc, time.perf_counter() - t_wall)
        else:
            state = model.initial_state()
    state = state.copy()
    state.t = t0
    out_x = np.full((times.size, n_nodes, 3), np.nan)
    out_f = np.full((times.size, 3), np.nan)
    limit = model.config.divergence_limit * float(np.linalg.norm(model.mesh.size))
    j = 0

    def record(j: int, x: np.ndarray, st: State) -> None:
        """Store frame j; with a hook, shift the state's free nodes by its correction."""
        out_x[j] = x
        if frame_hook is not None:
            shifted = st.x.copy()
            apply_hook(frame_hook, model, j, grid, out_x, shifted)
            st.x = shifted

    while j < times.size and k_of[j] == 0:
        record(j, state.x, state)
        out_f[j] = 0.0
        j += 1
    if compilable(model):
        _, k, status, message = run_compiled(model, state, grid, j, out_x, out_f, limit, frame_hook, callback)
        n_steps_taken = k
    else:
        k, status, message = _simulate_reference(model, state, centres, step_t, times, k_of, j, out_x, out_f,
                                                probe_radius, limit, record, callback)
        n_steps_taken = k
    positions, contact_force = grid.frames(out_x, out_f)
    return SimulationResult(
        times=grid.frame_times,
        positions=positions,
        contact_force=contact_force,
        probe_centres=path.at(grid.frame_times),
        probe_radius=float(probe_radius),
        status=status,
        message=message,
        steps=n_steps_taken if n_steps else 0,
        wall_time=time.perf_counter() - t_wall,
    )


def _simulate_reference(model, state, centres, step_t, times, k_of, j, out_x, out_f, probe_radius, limit, record,
                        callback):
    """The time loop of :func:`simulate` with the Python :func:`step` (the reference);
    returns (last step, status, message)."""
    dt = model.config.dt
    n_steps = step_t.size - 1
    prev_x, prev_f = state.x, np.zeros(3)
    status, message = "ok", ""
    k = 0
    report_every = max(n_steps // 50, 1)
    for k in range(1, n_steps + 1):
        vp = (centres[k] - centres[k - 1]) / dt
        state, info = step(model, state, centres[k], probe_radius, vp)
        # a blow-up grows geometrically: checking every 5th step (and the last) is enough
        disp = np.abs(state.x - model.mesh.nodes).max() if (k % 5 == 0 or k == n_steps) else 0.0
        if not np.isfinite(disp) or disp > limit:
            status, message = "diverged", divergence_message(step_t[k], k, disp)
            break
        while j < times.size and k_of[j] == k:
            a = (times[j] - step_t[k - 1]) / dt
            out_f[j] = (1 - a) * prev_f + a * info.contact_force
            record(j, (1 - a) * prev_x + a * state.x, state)
            j += 1
        prev_x, prev_f = state.x, info.contact_force
        if callback is not None and (k % report_every == 0 or k == n_steps):
            callback(k / n_steps, f"step {k}/{n_steps}")
    return k, status, message
