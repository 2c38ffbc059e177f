"""The compiled replay's plumbing: the time grid of a replay, the model as the compiled
time loop (:mod:`core.simulation.stepper`) takes it, and the loop that drives it frame
chunk by frame chunk. Shared by :func:`core.simulation.solver.simulate` and
:func:`core.simulation.sensitivity.simulate_sensitivities` (split out of ``solver`` to
keep it under 600 lines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.errors import SimulationError
from core.preparation.probe import ProbePath
from core.simulation.contact import contact_corners
from core.simulation.lowrank import lapack_pbtrs
from core.simulation.model import Model, State

__all__ = ["NUMERICAL_ERRORS", "advance_or_diverge", "StepGrid", "step_grid", "divergence_message", "compilable", "run_compiled", "model_tuple", "no_tangents",
           "apply_hook"]


@dataclass(frozen=True)
class StepGrid:
    """The time grid of a replay (see :func:`step_grid`).

    Attributes:
        times: (M,) the times the replay records, s, increasing: the F camera frames and,
            with a clock shift, the F robot samples beside them (M = 2F). path: the probe
            path after the model's input-side effects. probe_radius: m, after them. t0:
            start time, s. step_t: (K + 1,) step times from t0, s. centres: (K + 1, 3)
            probe centres at the step times, m, phantom frame. k_of: (M,) int64, the step
            whose end follows each recorded time (output j lies in
            ``(step_t[k-1], step_t[k]]``). camera: (F,) int64, the recorded index of each
            camera frame (positions are read there). robot: (F,) int64, the recorded
            index of each frame's robot sample (the probe force is read there).
            frame_times: (F,) the camera frames' times, s. frame_of: (M,) int64, the
            camera frame a recorded time is, -1 for a robot sample alone.
    """

    times: np.ndarray
    path: ProbePath
    probe_radius: float
    t0: float
    step_t: np.ndarray
    centres: np.ndarray
    k_of: np.ndarray
    camera: np.ndarray
    robot: np.ndarray
    frame_times: np.ndarray
    frame_of: np.ndarray

    def __iter__(self):
        return iter((self.times, self.path, self.probe_radius, self.t0, self.step_t, self.centres, self.k_of))

    def frames(self, out_x: np.ndarray, out_f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions at the camera frames (..., F, N, 3), force at the robot samples
        (..., F, 3)) of recorded ``out_x`` (..., M, N, 3) and ``out_f`` (..., M, 3); the
        arrays themselves when every recorded time is a camera frame (no copy)."""
        if self.times.size == self.frame_times.size:
            return out_x, out_f
        return out_x[..., self.camera, :, :], out_f[..., self.robot, :]


def clock_shift(model: Model) -> float:
    """The sum of the model's effects' clock shifts, s (:meth:`core.simulation.effects.Effect.clock_shift`)."""
    return float(sum(e.clock_shift() for e in model.effects))


def step_grid(model: Model, path: ProbePath, probe_radius: float, output_times) -> StepGrid:
    """The steps of a replay of ``path`` with ``model``: the start is the earlier of the
    recorded path's first time and the first output time, moved with the probe by the
    input-side effects' clock shift (:meth:`core.simulation.effects.Effect.clock_shift`),
    then steps of ``config.dt`` up to the last output time.

    The grid moves with a clock offset so that the steps meet the probe path at the same
    points whatever the offset: the replay with an offset c is then the replay without
    one read at the output times plus c (frames before the start hold the rest state).
    With a fixed grid the step's phase against the probe's path changed with c: on a lab
    session (field seed 64, 12 s, force, a 0.15 s offset) moving the grid alone changed
    the force misfit of both train sequences at offsets between steps by 1400-2500
    chi-square units (25 ms: a drop of -421 became 978; 75 ms: -1663 became -4136).

    The probe force is measured by the robot and stamped with its clock, as are the
    kinematics, so it is recorded at the robot's sample of each frame time t: at the
    replay's time t + shift (M = 2F recorded times for a model with a clock-moving
    effect). It does not change with the clock offset then, as the measured force does
    not; read at the camera's times, the comparison's samples slid along the model-form
    gap with the offset, and on the session above the force misfit moved by 1400-2700
    chi-square units between offsets 25 ms apart, without any offset information in it.

    Raises:
        SimulationError: empty, non-finite or decreasing output times, or a probe radius
            that is not positive after the effects.
    """
    times = np.asarray(output_times, dtype=np.float64).reshape(-1)
    if times.size == 0 or not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
        raise SimulationError("output_times must be a non-empty, finite, non-decreasing array")
    shift = clock_shift(model)
    t0 = float(min(path.t[0], times[0])) + shift
    for effect in model.effects:
        path, probe_radius = effect.transform_probe(path, probe_radius)
    if not (probe_radius > 0):
        raise SimulationError(f"probe radius must be positive, got {probe_radius}")
    F = times.size
    if not any(e.moves_clock for e in model.effects):
        recorded, camera, robot = times, np.arange(F), np.arange(F)
    else:
        both = np.concatenate([times, times + shift])
        order = np.argsort(both, kind="stable")
        where = np.empty(2 * F, dtype=np.int64)
        where[order] = np.arange(2 * F)
        recorded, camera, robot = both[order], where[:F], where[F:]
    dt = model.config.dt
    n_steps = max(int(math.ceil((recorded[-1] - t0) / dt - 1e-9)), 0)
    step_t = t0 + dt * np.arange(n_steps + 1)
    k_of = np.clip(np.searchsorted(step_t, recorded, side="left"), 0, n_steps)
    frame_of = np.full(recorded.size, -1, dtype=np.int64)
    frame_of[camera] = np.arange(F)
    return StepGrid(recorded, path, float(probe_radius), t0, step_t, path.at(step_t), k_of, camera, robot, times,
                    frame_of)


NUMERICAL_ERRORS = (ZeroDivisionError, FloatingPointError, np.linalg.LinAlgError)
"""What the compiled step raises when its state has gone non-finite inside a step (numba
checks a matrix before a solve, and divides as Python does): a divergence, not a bug."""


def advance_or_diverge(*args, k: int, j: int):
    """:func:`core.simulation.stepper.advance` (same arguments and returns), with a
    :data:`NUMERICAL_ERRORS` inside it reported as ``STATUS_NONFINITE`` at the call's first
    step ``k`` and frame ``j`` (frames from there on stay NaN or hold steps completed before
    the error), so that a replay that diverges this way is "diverged" like any other,
    instead of failing a fit, a diagnosis or the lab."""
    from core.simulation import stepper

    try:
        return stepper.advance(*args)
    except NUMERICAL_ERRORS:
        # the factor's cache of inverse rows may have grown inside the call (a new buffer,
        # lost with the exception) while its slots and count were updated in place: empty
        # it, or the next run on this (shared, cached) factor reads rows that are not there
        # (measured: a dome's diagnosis failed on "cannot assign slice of shape (87, 1677)
        # from input of shape (0, 1677)" after a model-form variant diverged this way)
        rows, slot, used = args[3], args[4], args[5]
        slot[:] = -1
        used[0] = 0
        return stepper.STATUS_NONFINITE, k, j, float("nan"), rows


def divergence_message(t: float, k: int, disp: float) -> str:
    """The reason a replay diverged at time ``t`` (s), step ``k``, largest displacement ``disp`` (m)."""
    return (f"diverged at t = {t:.3f} s (step {k}): "
            + ("non-finite positions" if not np.isfinite(disp) else f"node moved {disp * 1e3:.0f} mm"))


def compilable(model: Model) -> bool:
    """Whether :mod:`core.simulation.stepper` runs this model (implicit Euler, Maxwell arms
    as the only extra stress terms, ``config.compiled``)."""
    from core.simulation.model import MaxwellArm

    return (model.config.compiled and model.config.integrator == "implicit_euler" and model._factor is not None
            and all(type(t) is MaxwellArm for t in model.terms))


def run_compiled(model, state, grid: StepGrid, j, out_x, out_f, limit, frame_hook, callback):
    """The time loop of :func:`core.simulation.solver.simulate` in
    :func:`core.simulation.stepper.advance`, from ``state`` and recorded time ``j`` of
    ``grid`` (:class:`StepGrid`): fills ``out_x`` (M, N, 3) and ``out_f`` (M, 3) in
    place; ``frame_hook`` and ``callback`` as in ``simulate``.

    Returns:
        (final state, last step, status ``"ok"`` or ``"diverged"``, message).
    """
    from core.simulation import stepper

    fac = model._factor
    times, _, probe_radius, _, step_t, centres, k_of = grid
    n_steps = step_t.size - 1
    x = np.ascontiguousarray(state.x, dtype=np.float64).copy()
    v = np.ascontiguousarray(state.v, dtype=np.float64).copy()
    q = np.ascontiguousarray(state.q, dtype=np.float64).copy()
    n_el = model.mesh.n_tets
    eps_v = (np.ascontiguousarray(np.stack(state.term_state)) if model.terms else np.zeros((0, 9, n_el)))
    prev_x, prev_f, force = x.copy(), np.zeros(3), np.zeros(3)
    pbtrs = lapack_pbtrs()
    mdl = model_tuple(model)
    F = times.size
    chunk = max(int(math.ceil(F / 50)), 1) if callback is not None else F
    k, resume, status, message = 0, False, "ok", ""
    tan = no_tangents(model, centres.shape[0], F)
    while True:
        j_stop = min(j + 1, F) if frame_hook is not None else min(j + chunk, F)
        code, k, j, disp, rows = advance_or_diverge(
            mdl, pbtrs, fac.cbT, fac._rows, fac._slot, fac._used, centres, float(probe_radius), x, v, q, eps_v,
            times, step_t, k_of, k, resume, j, max(j_stop, j + 1), out_x, out_f, prev_x, prev_f, limit, force, *tan,
            k=k, j=j)
        fac._rows = rows
        if code in (stepper.STATUS_NONFINITE, stepper.STATUS_TOO_FAR):
            status, message = "diverged", divergence_message(step_t[k], k, disp)
            break
        if code == stepper.STATUS_STOPPED:
            if frame_hook is not None:
                apply_hook(frame_hook, model, j - 1, grid, out_x, x)
            if callback is not None:
                callback(k / max(n_steps, 1), f"step {k}/{n_steps}")
            resume = True
            continue
        break
    if callback is not None and status == "ok" and n_steps:
        callback(1.0, f"step {n_steps}/{n_steps}")
    term_state = tuple(np.array(eps_v[i]) for i in range(eps_v.shape[0]))
    return State(x=x, v=v, q=q, term_state=term_state, t=float(step_t[k])), k, status, message


def model_tuple(model: Model) -> tuple:
    """The model as :func:`core.simulation.stepper.advance` takes it (see there)."""
    cfg, el = model.config, model.elements
    dt = cfg.dt
    law = {"corotational": 0, "stable_neo_hookean": 1, "stable_yeoh": 2}[model.material.law]
    iters = cfg.polar_iterations if model.needs_rotation else 0
    tau = np.array([t.tau for t in model.terms], dtype=np.float64)
    kr = np.array([t.k for t in model.terms], dtype=np.float64)
    k_lhs = dt * cfg.rayleigh_stiffness + dt * dt * (1.0 + sum(t.lhs_scale(dt) for t in model.terms))
    return (model.mesh.tets, el.grad_n, el.volume, model.mu, model.lam, law, float(model.material.stiffening), iters,
            tau, kr, dt, float(cfg.rayleigh_mass), float(cfg.rayleigh_stiffness), int(cfg.newton_iterations),
            model.mass_dofs, model.free_dofs, model.free_index, model.scratch_slot,
            np.ascontiguousarray(model.body_force, dtype=np.float64),
            np.ascontiguousarray(model.support_stiffness, dtype=np.float64), model.mesh.nodes,
            model.mesh.surface_triangles, float(model.contact_stiffness), float(cfg.contact_margin),
            int(cfg.contact_iterations), float(cfg.contact_tolerance), float(model.friction),
            float(cfg.friction_slip_speed), float(k_lhs), contact_corners(cfg.contact_subdivision))


def no_tangents(model: Model, n_centres: int, n_frames: int) -> tuple:
    """The tangent arguments of :func:`core.simulation.stepper.advance` for p = 0 directions."""
    N, E, T = model.mesh.n_nodes, model.mesh.n_tets, len(model.terms)
    z = np.zeros(0)
    dmdl = (np.zeros((0, E)), np.zeros((0, E)), z, np.zeros((0, N, 3)), np.zeros((0, N)), z, np.zeros((0, T)),
            np.zeros((0, T)), z, z)
    return (dmdl, np.zeros((0, n_centres, 3)), np.zeros((0, n_frames)), np.zeros((0, N, 3)), np.zeros((0, N, 3)), np.zeros((0, 4, E)),
            np.zeros((0, T, 9, E)), np.zeros((0, n_frames, N, 3)), np.zeros((0, n_frames, 3)), np.zeros((0, N, 3)),
            np.zeros((0, 3)), np.zeros((0, 3)))


def apply_hook(frame_hook, model, j, grid: StepGrid, out_x, x) -> None:
    """The in-loop correction of recorded time ``j`` (see :func:`core.simulation.solver.simulate`):
    ``out_x[j]`` and the state's free nodes ``x`` (in place) shifted by the hook's change; nothing
    for a robot sample that is no camera frame (the hook sees camera frames and their index)."""
    frame = int(grid.frame_of[j])
    if frame < 0:
        return
    cur = out_x[j]
    new = frame_hook(frame, float(grid.frame_times[frame]), cur.copy())
    if new is None:
        return
    new = np.asarray(new, dtype=np.float64)
    if new.shape != cur.shape:
        raise SimulationError(f"frame_hook must return ({cur.shape[0]}, 3) positions, got {new.shape}")
    delta = np.where(model.free[:, None], new - cur, 0.0)
    out_x[j] = cur + delta
    x += delta
