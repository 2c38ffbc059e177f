"""Compiled time stepping (numba): the whole implicit-Euler step of :mod:`core.simulation.solver`
in one compiled loop.

The Python :func:`core.simulation.solver.step` stays the readable reference: this module
runs the same step (the same constant-Jacobian Newton corrections, the same active-set
contact solve with the Woodbury identity on cached rows of the inverse, the same
regularised Coulomb friction) without the interpreter between its pieces. On the paper's
13 x 5 x 5 grid the interpreter's glue (array slicing, small allocations, einsum calls)
cost more than the element forces and the banded solve together; the tests check that
both give the same trajectories and forces.

The banded solves and the Woodbury updates are :mod:`core.simulation.lowrank`'s; the
element laws and the polar decomposition :mod:`core.simulation.kernels`'s. With tangent
directions (p > 0) each step also propagates the derivatives of the state along them
(:mod:`core.simulation.tangent_step`; see :mod:`core.simulation.sensitivity`).

Layout of the arrays (all float64 unless stated; N nodes, E tetrahedra, n free dofs):

- ``x, v``: (N, 3) positions (m) and velocities (m/s), phantom frame;
- ``q``: (4, E) rotation quaternions (x, y, z, w), the polar decomposition's warm start;
- ``eps_v``: (T, 9, E) viscous strains of the T Maxwell arms (component-major, as the
  model's ``State.term_state``);
- ``cbT``: (n, kd + 1) the upper banded Cholesky factor of the system matrix, LAPACK's
  column-major band storage seen as a C array (``scipy.linalg.cholesky_banded(...).T``);
- ``rows``: (cap, n) cached rows of the inverse of the system matrix, ``slot`` (n,) int64
  their slot per free dof (-1: not cached), ``used`` (1,) int64 slots in use.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from core.simulation.kernels import constraint_matrix, pk1_stress, polar_update, sphere_contacts
from core.simulation.lowrank import apply_rows, apply_rows_full, band_solve, woodbury_weights
from core.simulation.tangent import contact_geometry_tangent, element_forces_tangent
from core.simulation.tangent_step import contact_force_tangent, iteration_tangent

__all__ = ["advance", "STATUS_OK", "STATUS_STOPPED", "STATUS_NONFINITE", "STATUS_TOO_FAR"]

STATUS_OK = 0
"""Every step was taken."""
STATUS_STOPPED = 1
"""Stopped after recording the requested frame (an in-loop correction follows)."""
STATUS_NONFINITE = 2
"""Diverged: a position became non-finite."""
STATUS_TOO_FAR = 3
"""Diverged: a node moved further from rest than the divergence limit."""

_FM = {"contract", "arcp", "nsz", "reassoc"}
@njit(cache=True, fastmath=_FM)
def _forces(x, v, tets, grad_n, volume, mu, lam, law, stiffening, q, iterations, beta,
            term_tau, term_k, eps_v, eps_v_new, dt, f):
    """Internal nodal forces (N, 3), N, into ``f`` (zeroed here): the law's stress, the
    Maxwell arms' (their new viscous strains into ``eps_v_new``) and the Rayleigh
    stiffness damping ``-beta K0 v``; ``q`` is updated in place (warm start)."""
    n_el = tets.shape[0]
    n_terms = term_tau.size
    f[:] = 0.0
    xa = np.empty((4, 3))
    va = np.empty((4, 3))
    F = np.empty(9)
    R = np.empty(9)
    P = np.empty(9)
    H = np.empty(9)
    eps = np.empty(9)
    for e in range(n_el):
        for a in range(4):
            nd = tets[e, a]
            for i in range(3):
                xa[a, i] = x[nd, i]
                va[a, i] = v[nd, i]
        for i in range(3):
            for k in range(3):
                F[3 * i + k] = (xa[0, i] * grad_n[e, 0, k] + xa[1, i] * grad_n[e, 1, k]
                                + xa[2, i] * grad_n[e, 2, k] + xa[3, i] * grad_n[e, 3, k])
        if iterations > 0:
            polar_update(F, q, e, iterations, R)
        else:
            for c in range(9):
                R[c] = 0.0
            R[0] = 1.0
            R[4] = 1.0
            R[8] = 1.0
        pk1_stress(law, F, R, mu[e], lam[e], stiffening, P)
        if n_terms > 0:
            # corotated small strain sym(R^T F) - I
            for i in range(3):
                for k in range(3):
                    eps[3 * i + k] = R[i] * F[k] + R[3 + i] * F[3 + k] + R[6 + i] * F[6 + k]
            for i in range(3):
                for k in range(i + 1, 3):
                    s = 0.5 * (eps[3 * i + k] + eps[3 * k + i])
                    eps[3 * i + k] = s
                    eps[3 * k + i] = s
            eps[0] -= 1.0
            eps[4] -= 1.0
            eps[8] -= 1.0
            for t in range(n_terms):
                h = dt / term_tau[t]
                sc = term_k[t] / (1.0 + h)
                # sigma = sc * (2 mu (eps - eps_v) + lam tr(eps - eps_v) I), then P += R sigma
                trd = 0.0
                for c in (0, 4, 8):
                    trd += eps[c] - eps_v[t, c, e]
                for c in range(9):
                    H[c] = sc * 2.0 * mu[e] * (eps[c] - eps_v[t, c, e])
                    eps_v_new[t, c, e] = (eps_v[t, c, e] + h * eps[c]) / (1.0 + h)
                H[0] += sc * lam[e] * trd
                H[4] += sc * lam[e] * trd
                H[8] += sc * lam[e] * trd
                for i in range(3):
                    for k in range(3):
                        P[3 * i + k] += R[3 * i] * H[k] + R[3 * i + 1] * H[3 + k] + R[3 * i + 2] * H[6 + k]
        if beta > 0.0:
            for i in range(3):
                for k in range(3):
                    H[3 * i + k] = (va[0, i] * grad_n[e, 0, k] + va[1, i] * grad_n[e, 1, k]
                                    + va[2, i] * grad_n[e, 2, k] + va[3, i] * grad_n[e, 3, k])
            trh = H[0] + H[4] + H[8]
            bm = beta * mu[e]
            for i in range(3):
                for k in range(3):
                    P[3 * i + k] += bm * (H[3 * i + k] + H[3 * k + i])
                P[4 * i] += beta * lam[e] * trh
        V = volume[e]
        for a in range(4):
            nd = tets[e, a]
            g0, g1, g2 = grad_n[e, a, 0], grad_n[e, a, 1], grad_n[e, a, 2]
            f[nd, 0] -= V * (P[0] * g0 + P[1] * g1 + P[2] * g2)
            f[nd, 1] -= V * (P[3] * g0 + P[4] * g1 + P[5] * g2)
            f[nd, 2] -= V * (P[6] * g0 + P[7] * g1 + P[8] * g2)


@njit(cache=True)
def _gaps(cnodes, cW, cN, sel, x, centre, radius, out):
    """Penetration ``r - n.(sum_j w_j x_j - centre)`` of the contacts ``sel`` along their
    frozen normals at positions ``x`` into ``out`` (> 0 inside)."""
    for i in range(sel.size):
        c = sel[i]
        s = 0.0
        for d in range(3):
            p = cW[c, 0] * x[cnodes[c, 0], d] + cW[c, 1] * x[cnodes[c, 1], d] + cW[c, 2] * x[cnodes[c, 2], d]
            s += cN[c, d] * (p - centre[d])
        out[i] = radius - s


@njit(cache=True)
def _tangents(n):
    """Two unit tangents of each normal (k, 3), as ``solver._tangents`` (the Python reference step)."""
    k = n.shape[0]
    t1 = np.empty((k, 3))
    t2 = np.empty((k, 3))
    for c in range(k):
        if abs(n[c, 0]) < 0.9:
            a0, a1, a2 = 1.0, 0.0, 0.0
        else:
            a0, a1, a2 = 0.0, 1.0, 0.0
        u0 = n[c, 1] * a2 - n[c, 2] * a1
        u1 = n[c, 2] * a0 - n[c, 0] * a2
        u2 = n[c, 0] * a1 - n[c, 1] * a0
        nr = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        u0, u1, u2 = u0 / nr, u1 / nr, u2 / nr
        t1[c, 0], t1[c, 1], t1[c, 2] = u0, u1, u2
        t2[c, 0] = n[c, 1] * u2 - n[c, 2] * u1
        t2[c, 1] = n[c, 2] * u0 - n[c, 0] * u2
        t2[c, 2] = n[c, 0] * u1 - n[c, 1] * u0
    return t1, t2


@njit(cache=True)
def _point_velocity(cnodes, cW, c, v):
    p0 = cW[c, 0] * v[cnodes[c, 0], 0] + cW[c, 1] * v[cnodes[c, 1], 0] + cW[c, 2] * v[cnodes[c, 2], 0]
    p1 = cW[c, 0] * v[cnodes[c, 0], 1] + cW[c, 1] * v[cnodes[c, 1], 1] + cW[c, 2] * v[cnodes[c, 2], 1]
    p2 = cW[c, 0] * v[cnodes[c, 0], 2] + cW[c, 1] * v[cnodes[c, 1], 2] + cW[c, 2] * v[cnodes[c, 2], 2]
    return p0, p1, p2


@njit(cache=True)
def _step(mdl, pbtrs, cbT, rows, slot, used, centre, radius, vp, x, v, q, eps_v, force_out,
          dmdl, dc, dvp, dx, dv, dq, deps, dforce_out):
    """One implicit-Euler step (see :func:`core.simulation.solver.step`), in place on
    ``x, v, q, eps_v``; the probe's force on the phantom (3,) N into ``force_out``.

    ``mdl`` is the model tuple of :func:`advance`. With p > 0 tangent directions, their
    state ``dx, dv`` (p, N, 3), ``dq`` (p, 4, E), ``deps`` (p, T, 9, E) is advanced too
    (in place) from the model's derivatives ``dmdl`` and the probe centre's ``dc`` and
    velocity's ``dvp`` (p, 3); the force's derivative (p, 3) goes into ``dforce_out``.
    Returns ``(rows, number of active contacts)``."""
    (tets, grad_n, volume, mu, lam, law, stiffening, polar_iterations, term_tau, term_k, dt, alpha, beta,
     newton_iterations, mass3, free_dofs, free_index, scratch, body_force, support, X, tris, kc, margin,
     contact_iterations, tolerance, friction, slip_speed, k_lhs, sub) = mdl
    dmu, dlam, dkc, db, dS, dmuf, dtau, dk, dk_lhs, drho = dmdl
    p = dx.shape[0]
    N = x.shape[0]
    nf = free_dofs.size
    x0 = x.copy()
    v0 = v.copy()
    vg = v.copy()
    q0 = q.copy()
    eps_new = np.empty_like(eps_v)
    f = np.empty((N, 3))
    xp = np.empty((N, 3))
    r = np.empty(nf)
    dv_full = np.empty(nf)
    dv_n = np.empty(nf)
    has_body = np.any(body_force != 0.0)
    has_support = np.any(support != 0.0)
    # candidate contacts (frozen at the first correction's positions)
    cidx = np.zeros(0, dtype=np.int64)
    cW = np.zeros((0, 3))
    cN = np.zeros((0, 3))
    cA = np.zeros(0)
    cnodes = np.zeros((0, 3), dtype=np.int64)
    active = np.zeros(0, dtype=np.bool_)
    sel = np.zeros(0, dtype=np.int64)  # the contacts of the last pass
    # friction rows of the last correction: (k_t,) contact index, direction, omega
    fr_c = np.zeros(0, dtype=np.int64)
    fr_dir = np.zeros((0, 3))
    fr_om = np.zeros(0)
    x_try = np.empty((N, 3))
    # tangents
    dvg = dv.copy()
    df_el = np.empty((p, N, 3))
    dq1 = np.empty_like(dq)
    deps1 = np.empty_like(deps)
    dW = np.zeros((p, 0, 3))
    dN = np.zeros((p, 0, 3))
    dA = np.zeros((p, 0))
    tfr_c = np.zeros(0, dtype=np.int64)
    tfr_dir = np.zeros((0, 3))
    dfr_om = np.zeros((p, 0))
    dfr_dir = np.zeros((p, 0, 3))
    for it in range(newton_iterations):
        for i in range(N):
            for d in range(3):
                xp[i, d] = x0[i, d] + dt * vg[i, d]
        if p == 0:
            q[:] = q0
            _forces(xp, vg, tets, grad_n, volume, mu, lam, law, stiffening, q, polar_iterations, beta,
                    term_tau, term_k, eps_v, eps_new, dt, f)
        else:  # the forces and their derivatives in one pass
            dxp = dx + dt * dvg
            element_forces_tangent(xp, vg, dxp, dvg, tets, grad_n, volume, mu, lam, dmu, dlam, law, stiffening,
                                   q0, dq, polar_iterations, beta, term_tau, term_k, dtau, dk, eps_v, deps, dt,
                                   q, dq1, deps1, df_el, f, eps_new)
        if has_body:
            f += body_force
        if has_support:
            for i in range(N):
                for d in range(3):
                    f[i, d] -= support[i] * (xp[i, d] - X[i, d])
        for j in range(nf):
            dof = free_dofs[j]
            i, d = dof // 3, dof % 3
            m = mass3[dof]
            r[j] = dt * (f[i, d] - alpha * m * vg[i, d]) - m * (vg[i, d] - v0[i, d])
        if it == 0:
            cidx, csub, cW, cN, _, cA, cWs = sphere_contacts(xp, tris, sub, centre, radius + margin)
            cnodes = np.empty((cidx.size, 3), dtype=np.int64)
            for c in range(cidx.size):
                for j in range(3):
                    cnodes[c, j] = tris[cidx[c], j]
            allc = np.arange(cidx.size)
            g0 = np.empty(cidx.size)
            _gaps(cnodes, cW, cN, allc, xp, centre, radius, g0)
            active = g0 > 0.0
            if p > 0:
                dW = np.empty((p, cidx.size, 3))
                dN = np.empty((p, cidx.size, 3))
                dA = np.empty((p, cidx.size))
                contact_geometry_tangent(xp, dx + dt * dvg, centre, dc, cnodes, sub, csub, cWs, cN, dW, dN, dA)
                tfr_c = np.empty(2 * cidx.size, dtype=np.int64)
                tfr_dir = np.empty((2 * cidx.size, 3))
                dfr_om = np.empty((p, 2 * cidx.size))
                dfr_dir = np.empty((p, 2 * cidx.size, 3))
        nc = cidx.size
        y = r.copy()
        band_solve(pbtrs, cbT, y)
        # free dofs of the candidates' nodes: where the active-set passes need the solution
        cd = np.empty(9 * nc, dtype=np.int64)
        ncd = 0
        for c in range(nc):
            for j in range(3):
                for d in range(3):
                    fi = free_index[3 * cnodes[c, j] + d]
                    if fi >= 0 and scratch[fi] < 0:
                        scratch[fi] = ncd
                        cd[ncd] = fi
                        ncd += 1
        cd = cd[:ncd]
        for i in range(ncd):
            scratch[cd[i]] = -1
        dv_c = np.empty(ncd)
        allc = np.arange(nc)
        g = np.empty(nc)
        w = np.zeros(0)
        uniq = np.zeros(0, dtype=np.int64)
        x_try[:] = xp
        for _ in range(contact_iterations):
            sel = np.flatnonzero(active)
            k = sel.size
            om = np.empty(k)
            bc = np.empty(k)
            gs = np.empty(k)
            _gaps(cnodes, cW, cN, sel, xp, centre, radius, gs)
            for i in range(k):
                om[i] = dt * dt * kc * cA[sel[i]]
                bc[i] = dt * kc * cA[sel[i]] * gs[i]
            uniq, C = constraint_matrix(cnodes[sel], cW[sel], cN[sel], free_index, scratch)
            w = np.empty(uniq.size)
            rows = woodbury_weights(pbtrs, cbT, rows, slot, used, y, uniq, C, om, bc, w)
            if nc == 0:
                break
            apply_rows(rows, slot, y, uniq, w, cd, dv_c)
            x_try[:] = xp
            for i in range(ncd):
                dof = free_dofs[cd[i]]
                x_try[dof // 3, dof % 3] += dt * dv_c[i]
            _gaps(cnodes, cW, cN, allc, x_try, centre, radius, g)
            changed = False
            for c in range(nc):
                if (active[c] and g[c] < 0.0) or ((not active[c]) and g[c] > tolerance):
                    changed = True
                    break
            if not changed:
                break
            for c in range(nc):
                if (active[c] and g[c] < 0.0) or ((not active[c]) and g[c] > tolerance):
                    active[c] = not active[c]
        k = sel.size
        fr_c = np.zeros(0, dtype=np.int64)
        if p > 0:
            apply_rows_full(rows, slot, y, uniq, w, dv_n)
        if friction > 0.0 and k > 0:
            # Coulomb friction bounded by the normal force this step's contact solve found
            gt = np.empty(k)
            _gaps(cnodes, cW, cN, sel, x_try, centre, radius, gt)
            gs = np.empty(k)
            _gaps(cnodes, cW, cN, sel, xp, centre, radius, gs)
            nsel = cN[sel]
            t1, t2 = _tangents(nsel)
            wt = np.empty(k)
            for i in range(k):
                c = sel[i]
                fn = kc * cA[c] * max(gt[i], 0.0)
                p0, p1, p2 = _point_velocity(cnodes, cW, c, vg)
                r0, r1, r2 = p0 - vp[0], p1 - vp[1], p2 - vp[2]
                rn = r0 * cN[c, 0] + r1 * cN[c, 1] + r2 * cN[c, 2]
                r0, r1, r2 = r0 - rn * cN[c, 0], r1 - rn * cN[c, 1], r2 - rn * cN[c, 2]
                speed = max(math.sqrt(r0 * r0 + r1 * r1 + r2 * r2), slip_speed)
                wt[i] = dt * friction * fn / speed
            keep = np.flatnonzero(wt > 0.0)
            kt = keep.size
            kk = k + 2 * kt
            bn = np.empty((kk, 3), dtype=np.int64)
            bw = np.empty((kk, 3))
            bd = np.empty((kk, 3))
            om = np.empty(kk)
            bc = np.empty(kk)
            fr_c = np.empty(2 * kt, dtype=np.int64)
            fr_dir = np.empty((2 * kt, 3))
            fr_om = np.empty(2 * kt)
            for i in range(k):
                c = sel[i]
                bn[i] = cnodes[c]
                bw[i] = cW[c]
                bd[i] = cN[c]
                om[i] = dt * dt * kc * cA[c]
                bc[i] = dt * kc * cA[c] * gs[i]
            for tt in range(2):
                for jj in range(kt):
                    i = keep[jj]
                    c = sel[i]
                    row = k + tt * kt + jj
                    tv = t1[i] if tt == 0 else t2[i]
                    p0, p1, p2 = _point_velocity(cnodes, cW, c, vg)
                    bn[row] = cnodes[c]
                    bw[row] = cW[c]
                    bd[row] = tv
                    om[row] = wt[i]
                    bc[row] = wt[i] * (tv[0] * vp[0] + tv[1] * vp[1] + tv[2] * vp[2]
                                       - (tv[0] * p0 + tv[1] * p1 + tv[2] * p2))
                    fr_c[tt * kt + jj] = c
                    fr_dir[tt * kt + jj] = tv
                    fr_om[tt * kt + jj] = wt[i]
            uniq, C = constraint_matrix(bn, bw, bd, free_index, scratch)
            w = np.empty(uniq.size)
            rows = woodbury_weights(pbtrs, cbT, rows, slot, used, y, uniq, C, om, bc, w)
        apply_rows_full(rows, slot, y, uniq, w, dv_full)
        if p > 0:
            rows, n_rows = iteration_tangent(
                pbtrs, cbT, rows, slot, used, free_dofs, free_index, scratch,
                tets, grad_n, volume, mu, lam, law, stiffening, polar_iterations, term_tau, term_k,
                dt, alpha, beta, mass3, support, X, k_lhs, kc, friction, slip_speed,
                xp, vg, v0, q0, eps_v, centre, vp, radius, cnodes, cW, cN, cA, sel, dv_n, dv_full,
                dx, dv, dvg, dq, deps, dW, dN, dA, dmu, dlam, dkc, db, dS, dmuf, dtau, dk, dk_lhs, dc, dvp, drho,
                df_el, tfr_c, tfr_dir, dfr_om, dfr_dir)
        for j in range(nf):
            dof = free_dofs[j]
            vg[dof // 3, dof % 3] += dv_full[j]
    for i in range(N):
        for d in range(3):
            x[i, d] = x0[i, d] + dt * vg[i, d]
            v[i, d] = vg[i, d]
    if eps_v.size:
        eps_v[:] = eps_new
    # the probe's force: penalty of the last contacts at the new positions, plus friction
    force_out[:] = 0.0
    k = sel.size
    if k > 0:
        gn = np.empty(k)
        _gaps(cnodes, cW, cN, sel, x, centre, radius, gn)
        for i in range(k):
            c = sel[i]
            fn = kc * cA[c] * max(gn[i], 0.0)
            for d in range(3):
                force_out[d] += fn * cN[c, d]
        for i in range(fr_c.size):
            c = fr_c[i]
            p0, p1, p2 = _point_velocity(cnodes, cW, c, v)
            rel = (fr_dir[i, 0] * (vp[0] - p0) + fr_dir[i, 1] * (vp[1] - p1) + fr_dir[i, 2] * (vp[2] - p2))
            for d in range(3):
                force_out[d] += (fr_om[i] / dt) * rel * fr_dir[i, d]
    if p > 0:
        for t in range(p):
            for i in range(N):
                for d in range(3):
                    dx[t, i, d] = dx[t, i, d] + dt * dvg[t, i, d]
                    dv[t, i, d] = dvg[t, i, d]
        dq[:] = dq1
        if deps.size:
            deps[:] = deps1
        nr = fr_c.size
        contact_force_tangent(x, v, dx, dv, centre, dc, radius, drho, vp, dvp, kc, dkc, dt, cnodes, cW, cN, cA,
                              dW, dN, dA, sel, fr_c, fr_dir, fr_om, dfr_om[:, :nr], dfr_dir[:, :nr], dforce_out)
    return rows, k


@njit(cache=True)
def advance(mdl, pbtrs, cbT, rows, slot, used, centres, radius, x, v, q, eps_v,
            times, step_t, k_of, k_begin, resume, j_begin, j_stop, out_x, out_f, prev_x, prev_f, limit, force,
            dmdl, dcentres, dphase, dx, dv, dq, deps, dout_x, dout_f, dprev_x, dprev_f, dforce):
    """Step from step ``k_begin`` (already taken when ``resume``: its pending frames are
    recorded first) until every step is taken or frame ``j_stop - 1`` is recorded.

    ``mdl``: the model as a tuple ``(tets, grad_n, volume, mu, lam, law, stiffening,
    polar_iterations, term_tau, term_k, dt, alpha, beta, newton_iterations, mass3,
    free_dofs, free_index, scratch, body_force, support, X, tris, kc, margin,
    contact_iterations, tolerance, friction, slip_speed, k_lhs, sub)`` (see
    :class:`core.simulation.model.Model`); ``centres`` (K + 1, 3) the probe centre at every
    step. Frames ``j`` with ``k_of[j] == k`` are interpolated between the states before and
    after step ``k`` into ``out_x`` (F, N, 3) and ``out_f`` (F, 3); ``prev_x``/``prev_f``
    hold the state before the current step (updated in place). Divergence is checked on
    every fifth step and the last, as in :func:`core.simulation.solver.simulate`.

    Tangents (p directions, p may be 0): the model's derivatives ``dmdl = (dmu, dlam,
    dkc, db, dS, dmuf, dtau, dk, dk_lhs, drho)``, the probe centres' ``dcentres`` (p, K + 1,
    3), each output time's ``dphase`` (p, F) against the step grid, s per unit (a clock
    offset moves the grid: a camera frame's weight between its steps changes by
    ``dphase / dt``, a robot sample moves with the grid), the state's
    ``dx, dv, dq, deps`` (in place), recorded into ``dout_x`` (p, F, N, 3) and ``dout_f``
    (p, F, 3) as the forward values.

    Returns:
        (status, last step taken, next frame to record, largest displacement from rest
        (m) at the last check, rows).
    """
    dt = mdl[10]
    X = mdl[20]
    p = dx.shape[0]
    n_steps = step_t.size - 1
    F = times.size
    j = j_begin
    k = k_begin
    disp = 0.0
    if resume:
        while j < F and k_of[j] == k:
            a = (times[j] - step_t[k - 1]) / dt
            out_f[j] = (1 - a) * prev_f + a * force
            out_x[j] = (1 - a) * prev_x + a * x
            for t in range(p):
                da = dphase[t, j] / dt
                dout_f[t, j] = (1 - a) * dprev_f[t] + a * dforce[t] + da * (force - prev_f)
                dout_x[t, j] = (1 - a) * dprev_x[t] + a * dx[t] + da * (x - prev_x)
            j += 1
            if j >= j_stop:
                prev_x[:] = x
                prev_f[:] = force
                dprev_x[:] = dx
                dprev_f[:] = dforce
                return STATUS_STOPPED, k, j, disp, rows
        prev_x[:] = x
        prev_f[:] = force
        dprev_x[:] = dx
        dprev_f[:] = dforce
    vp = np.empty(3)
    dc = np.empty((p, 3))
    dvp = np.empty((p, 3))
    for kk in range(k + 1, n_steps + 1):
        k = kk
        for d in range(3):
            vp[d] = (centres[k, d] - centres[k - 1, d]) / dt
            for t in range(p):
                dc[t, d] = dcentres[t, k, d]
                dvp[t, d] = (dcentres[t, k, d] - dcentres[t, k - 1, d]) / dt
        rows, _ = _step(mdl, pbtrs, cbT, rows, slot, used, centres[k], radius, vp, x, v, q, eps_v, force,
                        dmdl, dc, dvp, dx, dv, dq, deps, dforce)
        if k % 5 == 0 or k == n_steps:
            disp = 0.0
            finite = True
            for i in range(x.shape[0]):
                for d in range(3):
                    val = x[i, d]
                    if not np.isfinite(val):
                        finite = False
                    dd = abs(val - X[i, d])
                    if dd > disp:
                        disp = dd
            if not finite:
                return STATUS_NONFINITE, k, j, math.inf, rows
            if disp > limit:
                return STATUS_TOO_FAR, k, j, disp, rows
        while j < F and k_of[j] == k:
            a = (times[j] - step_t[k - 1]) / dt
            out_f[j] = (1 - a) * prev_f + a * force
            out_x[j] = (1 - a) * prev_x + a * x
            for t in range(p):
                da = dphase[t, j] / dt
                dout_f[t, j] = (1 - a) * dprev_f[t] + a * dforce[t] + da * (force - prev_f)
                dout_x[t, j] = (1 - a) * dprev_x[t] + a * dx[t] + da * (x - prev_x)
            j += 1
            if j >= j_stop:
                return STATUS_STOPPED, k, j, disp, rows
        prev_x[:] = x
        prev_f[:] = force
        dprev_x[:] = dx
        dprev_f[:] = dforce
    return STATUS_OK, k, j, disp, rows
