"""Tangent-linear model of one implicit-Euler step's contact solve (numba).

One Newton correction of :func:`core.simulation.stepper` solves

    (A + H W H^T) dv = r + H beta

with the constant system matrix ``A``, the residual ``r`` of the internal forces, and one
low-rank row ``h_c`` per active contact (its direction the frozen normal, its weights the
closest point's barycentric weights) and per friction tangent. Differentiating along a
direction gives, with the active set and friction's slip branch held,

    (A + H W H^T) d(dv) = dr - dA dv + sum_c [dh_c (beta_c - w_c s_c) + h_c (dbeta_c - dw_c s_c - w_c dh_c^T dv)],

``s_c = h_c^T dv``: the same matrix as the forward step, so the p directions are p extra
right-hand sides of one banded factorisation and one capacitance matrix. For a normal
row ``beta_c - w_c s_c = dt k A_c phi_c(x + dt dv)`` is the contact force times dt, and its
``dh_c`` (the normal turning and the contact point sliding) is the contact's geometric
stiffness. The friction rows' weights ``dt mu f_n / |v_t|`` depend on the normal force of
the normal-only solve, whose derivative is solved first.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from core.simulation.kernels import constraint_matrix
from core.simulation.lowrank import band_solve, ensure_rows, woodbury_solve_many
from core.simulation.tangent import stiffness_apply

__all__ = ["iteration_tangent", "contact_force_tangent", "friction_rows"]


@njit(cache=True)
def _nodes(vec, free_dofs, N):
    """A free-dof vector (n,) as node vectors (N, 3), zero on fixed dofs."""
    out = np.zeros((N, 3))
    for j in range(free_dofs.size):
        d = free_dofs[j]
        out[d // 3, d % 3] = vec[j]
    return out


@njit(cache=True)
def _wsum(cnodes, cW, c, x):
    """sum_j W_cj x[node_cj] (3,)."""
    out = np.zeros(3)
    for j in range(3):
        for d in range(3):
            out[d] += cW[c, j] * x[cnodes[c, j], d]
    return out


@njit(cache=True)
def _wsum_dw(cnodes, dWc, c, x):
    """sum_j dW_j x[node_cj] (3,) for the weight derivatives dWc (3,)."""
    out = np.zeros(3)
    for j in range(3):
        for d in range(3):
            out[d] += dWc[j] * x[cnodes[c, j], d]
    return out


@njit(cache=True)
def _tangent_pair(n):
    """The friction tangents t1, t2 of a normal (see ``solver._tangents``) and the fixed
    helper axis they were built from."""
    a = np.zeros(3)
    if abs(n[0]) < 0.9:
        a[0] = 1.0
    else:
        a[1] = 1.0
    u = np.cross(n, a)
    nu = math.sqrt(u @ u)
    t1 = u / nu
    t2 = np.cross(n, t1)
    return t1, t2, a, nu


@njit(cache=True)
def friction_rows(cnodes, cW, cN, cA, sel, x_try, vg, vp, centre, radius, kc, friction, slip, dt):
    """The forward friction rows of the step (as :func:`core.simulation.stepper._step`):
    per active contact i (index into ``sel``) its normal force ``fn`` (N) at ``x_try``, the
    tangential slip of the contact point relative to the probe ``rel_t`` (3,) m/s, its
    speed, and the row weight ``wt = dt mu fn / max(|rel_t|, slip)``."""
    k = sel.size
    fn = np.zeros(k)
    phi = np.zeros(k)
    rel_t = np.zeros((k, 3))
    nrt = np.zeros(k)
    wt = np.zeros(k)
    for i in range(k):
        c = sel[i]
        q = _wsum(cnodes, cW, c, x_try)
        phi[i] = radius - cN[c] @ (q - centre)
        fn[i] = kc * cA[c] * max(phi[i], 0.0)
        rel = _wsum(cnodes, cW, c, vg) - vp
        rn = rel @ cN[c]
        rel_t[i] = rel - rn * cN[c]
        nrt[i] = math.sqrt(rel_t[i] @ rel_t[i])
        wt[i] = dt * friction * fn[i] / max(nrt[i], slip)
    return fn, phi, rel_t, nrt, wt


@njit(cache=True)
def _add_row(rhs_t, free_index, cnodes, c, cW, dWc, direction, ddirection, big, gamma):
    """rhs += big * dh + gamma * h for the row of contact c along ``direction``."""
    for j in range(3):
        for d in range(3):
            fi = free_index[3 * cnodes[c, j] + d]
            if fi >= 0:
                rhs_t[fi] += big * (dWc[j] * direction[d] + cW[c, j] * ddirection[d]) + gamma * cW[c, j] * direction[d]


@njit(cache=True)
def iteration_tangent(pbtrs, cbT, rows, slot, used, free_dofs, free_index, scratch,
                      tets, grad_n, volume, mu, lam, law, stiffening, polar_iterations, term_tau, term_k,
                      dt, alpha, beta, mass3, support, X, k_lhs, kc, friction, slip,
                      xp, vg, v0, q0, eps_v, centre, vp, radius,
                      cnodes, cW, cN, cA, sel, dv_n, dv_f,
                      dx0, dv0, dvg, dq0, deps0, dW, dN, dA,
                      dmu, dlam, dkc, db, dS, dmuf, dtau, dk, dk_lhs, dc, dvp, drho,
                      df_el, fr_c, fr_dir, dfr_om, dfr_dir):
    """The tangent of one Newton correction: ``dvg`` (p, N, 3) += d(dv).

    Forward values: positions ``xp`` and velocities ``vg`` of the correction, the step's
    start ``v0``, ``q0``, ``eps_v``; the candidate contacts (``cnodes, cW, cN, cA``; their
    tangents ``dW, dN, dA``), the active ones ``sel``, the normal-only solution ``dv_n``
    and the final one ``dv_f`` (free dofs). Tangents of the step's start (``dx0, dv0, dq0,
    deps0``) and of the model (``dmu, dlam`` (p, E), ``dkc, dmuf, dk_lhs, drho`` (p,),
    ``db`` (p, N, 3), ``dS`` (p, N), ``dtau, dk`` (p, T)) and input (``dc, dvp`` (p, 3));
    ``df_el`` (p, N, 3) the element forces' derivative at the correction
    (:func:`core.simulation.tangent.element_forces_tangent`). Outputs, when friction acts: ``fr_c`` (rows,) the contact of each friction row in the forward order,
    ``fr_dir`` (rows, 3), ``dfr_om`` (p, rows), ``dfr_dir`` (p, rows, 3). Returns
    ``(rows, number of friction rows)``."""
    p = dx0.shape[0]
    N = xp.shape[0]
    nf = free_dofs.size
    dxp = dx0 + dt * dvg
    df = df_el.copy()
    for t in range(p):
        for i in range(N):
            for d in range(3):
                df[t, i, d] += db[t, i, d] - dS[t, i] * (xp[i, d] - X[i, d]) - support[i] * dxp[t, i, d]
    rhs = np.empty((p, nf))
    for t in range(p):
        for j in range(nf):
            dof = free_dofs[j]
            i, d = dof // 3, dof % 3
            m = mass3[dof]
            rhs[t, j] = dt * (df[t, i, d] - alpha * m * dvg[t, i, d]) - m * (dvg[t, i, d] - dv0[t, i, d])
    k = sel.size
    has_friction = friction > 0.0 and k > 0
    # the normal-only solve's tangent (friction is bounded by its normal force)
    ddv_n, rows = _solve_tangent(pbtrs, cbT, rows, slot, used, free_dofs, free_index, scratch, tets, grad_n, volume,
                           mu, lam, dmu, dlam, dt, support, dS, k_lhs, dk_lhs, kc, dkc, xp, dxp, centre, dc, radius,
                           drho, cnodes, cW, cN, cA, dW, dN, dA, sel, dv_n, rhs,
                           np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0), vg, dvg, vp, dvp,
                           np.zeros((p, 0)), np.zeros((p, 0, 3)))
    n_rows = 0
    if not has_friction:
        ddv = ddv_n
    else:
        x_try = xp + dt * _nodes(dv_n, free_dofs, N)
        fn, phi, rel_t, nrt, wt = friction_rows(cnodes, cW, cN, cA, sel, x_try, vg, vp, centre, radius, kc,
                                                friction, slip, dt)
        keep = np.flatnonzero(wt > 0.0)
        kt = keep.size
        n_rows = 2 * kt
        dwt = np.zeros((p, k))
        dtv1 = np.zeros((p, k, 3))
        dtv2 = np.zeros((p, k, 3))
        t1s = np.zeros((k, 3))
        t2s = np.zeros((k, 3))
        for i in range(k):
            c = sel[i]
            t1, t2, a, nu = _tangent_pair(cN[c])
            t1s[i] = t1
            t2s[i] = t2
            v_pt = _wsum(cnodes, cW, c, vg)
            rel = v_pt - vp
            rn = rel @ cN[c]
            speed = max(nrt[i], slip)
            for t in range(p):
                dtry = np.zeros(3)
                for j in range(3):
                    for d in range(3):
                        nd = cnodes[c, j]
                        fi = free_index[3 * nd + d]
                        dxt = dxp[t, nd, d] + (dt * ddv_n[t, fi] if fi >= 0 else 0.0)
                        dtry[d] += dW[t, c, j] * x_try[nd, d] + cW[c, j] * dxt
                qt = _wsum(cnodes, cW, c, x_try)
                dphi = drho[t] - dN[t, c] @ (qt - centre) - cN[c] @ (dtry - dc[t])
                dfn = (dkc[t] * cA[c] * phi[i] + kc * dA[t, c] * phi[i] + kc * cA[c] * dphi) if phi[i] > 0.0 else 0.0
                dv_pt = _wsum_dw(cnodes, dW[t, c], c, vg) + _wsum(cnodes, cW, c, dvg[t])
                drel = dv_pt - dvp[t]
                drn = drel @ cN[c] + rel @ dN[t, c]
                drel_t = drel - drn * cN[c] - rn * dN[t, c]
                dspeed = (rel_t[i] @ drel_t) / nrt[i] if nrt[i] > slip else 0.0
                dwt[t, i] = dt * (dmuf[t] * fn[i] + friction * dfn) / speed - wt[i] * dspeed / speed
                du = np.cross(dN[t, c], a)
                dtv1[t, i] = (du - t1 * (t1 @ du)) / nu
                dtv2[t, i] = np.cross(dN[t, c], t1) + np.cross(cN[c], dtv1[t, i])
        for tt in range(2):
            for jj in range(kt):
                i = keep[jj]
                r = tt * kt + jj
                fr_c[r] = sel[i]
                fr_dir[r] = t1s[i] if tt == 0 else t2s[i]
                for t in range(p):
                    dfr_om[t, r] = dwt[t, i]
                    dfr_dir[t, r] = dtv1[t, i] if tt == 0 else dtv2[t, i]
        om_rows = np.empty(n_rows)
        for r in range(n_rows):
            i = keep[r % kt] if kt > 0 else 0
            om_rows[r] = wt[i]
        ddv, rows = _solve_tangent(pbtrs, cbT, rows, slot, used, free_dofs, free_index, scratch, tets, grad_n, volume,
                             mu, lam, dmu, dlam, dt, support, dS, k_lhs, dk_lhs, kc, dkc, xp, dxp, centre, dc,
                             radius, drho, cnodes, cW, cN, cA, dW, dN, dA, sel, dv_f, rhs,
                             fr_c[:n_rows], fr_dir[:n_rows], om_rows, vg, dvg, vp, dvp,
                             dfr_om[:, :n_rows], dfr_dir[:, :n_rows])
    for t in range(p):
        for j in range(nf):
            dof = free_dofs[j]
            dvg[t, dof // 3, dof % 3] += ddv[t, j]
    return rows, n_rows


@njit(cache=True)
def _solve_tangent(pbtrs, cbT, rows, slot, used, free_dofs, free_index, scratch, tets, grad_n, volume,
                   mu, lam, dmu, dlam, dt, support, dS, k_lhs, dk_lhs, kc, dkc, xp, dxp, centre, dc, radius, drho,
                   cnodes, cW, cN, cA, dW, dN, dA, sel, dv, rhs0,
                   fr_c, fr_dir, fr_om, vg, dvg, vp, dvp, dfr_om, dfr_dir):
    """``(d(dv) (p, n), rows)`` of ``(A + H W H^T) dv = r + H beta`` with the normal rows of
    ``sel`` and the friction rows (``fr_c``, ``fr_dir``, weights ``fr_om``), at the solution
    ``dv`` (n,) of the forward solve, from ``rhs0`` = dr (p, n)."""
    p = rhs0.shape[0]
    N = xp.shape[0]
    nf = free_dofs.size
    rhs = rhs0.copy()
    dvn = _nodes(dv, free_dofs, N)
    # - dA dv: dt^2 dS dv + dk_lhs K0 dv + k_lhs K(dmu, dlam) dv (each only where it is not zero)
    K0 = np.zeros((1, N, 3))
    if np.any(dk_lhs != 0.0):
        stiffness_apply(dvn, tets, grad_n, volume, mu.reshape(1, -1), lam.reshape(1, -1), K0)
    Kd = np.zeros((p, N, 3))
    if np.any(dmu != 0.0) or np.any(dlam != 0.0):
        stiffness_apply(dvn, tets, grad_n, volume, dmu, dlam, Kd)
    has_ds = np.any(dS != 0.0)
    for t in range(p):
        for j in range(nf):
            dof = free_dofs[j]
            i, d = dof // 3, dof % 3
            rhs[t, j] -= dk_lhs[t] * K0[0, i, d] + k_lhs * Kd[t, i, d]
            if has_ds:
                rhs[t, j] -= dt * dt * dS[t, i] * dvn[i, d]
    k = sel.size
    n_fr = fr_c.size
    kk = k + n_fr
    bn = np.empty((kk, 3), dtype=np.int64)
    bw = np.empty((kk, 3))
    bd = np.empty((kk, 3))
    om = np.empty(kk)
    for i in range(k):
        c = sel[i]
        bn[i] = cnodes[c]
        bw[i] = cW[c]
        bd[i] = cN[c]
        om[i] = dt * dt * kc * cA[c]
        wdv = _wsum(cnodes, cW, c, dvn)
        s = cN[c] @ wdv
        q = _wsum(cnodes, cW, c, xp)
        phi = radius - cN[c] @ (q - centre)
        lam_c = kc * cA[c] * (phi - dt * s)
        for t in range(p):
            dq = _wsum_dw(cnodes, dW[t, c], c, xp) + _wsum(cnodes, cW, c, dxp[t])
            dphi = drho[t] - dN[t, c] @ (q - centre) - cN[c] @ (dq - dc[t])
            dbeta = dt * (dkc[t] * cA[c] * phi + kc * dA[t, c] * phi + kc * cA[c] * dphi)
            domega = dt * dt * (dkc[t] * cA[c] + kc * dA[t, c])
            dht = dN[t, c] @ wdv + cN[c] @ _wsum_dw(cnodes, dW[t, c], c, dvn)
            gamma = dbeta - domega * s - om[i] * dht
            _add_row(rhs[t], free_index, cnodes, c, cW, dW[t, c], cN[c], dN[t, c], dt * lam_c, gamma)
    for r in range(n_fr):
        c = fr_c[r]
        tv = fr_dir[r]
        bn[k + r] = cnodes[c]
        bw[k + r] = cW[c]
        bd[k + r] = tv
        om[k + r] = fr_om[r]
        wdv = _wsum(cnodes, cW, c, dvn)
        s = tv @ wdv
        v_pt = _wsum(cnodes, cW, c, vg)
        big = fr_om[r] * (tv @ vp - tv @ v_pt - s)
        for t in range(p):
            dtv = dfr_dir[t, r]
            dv_pt = _wsum_dw(cnodes, dW[t, c], c, vg) + _wsum(cnodes, cW, c, dvg[t])
            dbeta = dfr_om[t, r] * (tv @ vp - tv @ v_pt) + fr_om[r] * (dtv @ vp + tv @ dvp[t] - dtv @ v_pt - tv @ dv_pt)
            dht = dtv @ wdv + tv @ _wsum_dw(cnodes, dW[t, c], c, dvn)
            gamma = dbeta - dfr_om[t, r] * s - fr_om[r] * dht
            _add_row(rhs[t], free_index, cnodes, c, cW, dW[t, c], tv, dtv, big, gamma)
    band_solve(pbtrs, cbT, rhs)
    if kk > 0:
        uniq, C = constraint_matrix(bn, bw, bd, free_index, scratch)
        rows = ensure_rows(pbtrs, cbT, rows, slot, used, uniq)
        woodbury_solve_many(rows, slot, uniq, C, om, rhs)
    return rhs, rows


@njit(cache=True)
def contact_force_tangent(x1, v1, dx1, dv1, centre, dc, radius, drho, vp, dvp, kc, dkc, dt,
                          cnodes, cW, cN, cA, dW, dN, dA, sel, fr_c, fr_dir, fr_om, dfr_om, dfr_dir, out):
    """Derivative (p, 3) of the probe's force on the phantom at the step's end (the normal
    penalty of the active contacts at ``x1`` and the friction rows at ``v1``) into ``out``."""
    p = dx1.shape[0]
    out[:] = 0.0
    for i in range(sel.size):
        c = sel[i]
        q = _wsum(cnodes, cW, c, x1)
        phi = radius - cN[c] @ (q - centre)
        if phi <= 0.0:
            continue
        fn = kc * cA[c] * phi
        for t in range(p):
            dq = _wsum_dw(cnodes, dW[t, c], c, x1) + _wsum(cnodes, cW, c, dx1[t])
            dphi = drho[t] - dN[t, c] @ (q - centre) - cN[c] @ (dq - dc[t])
            dfn = dkc[t] * cA[c] * phi + kc * dA[t, c] * phi + kc * cA[c] * dphi
            for d in range(3):
                out[t, d] += dfn * cN[c, d] + fn * dN[t, c, d]
    for r in range(fr_c.size):
        c = fr_c[r]
        tv = fr_dir[r]
        v_pt = _wsum(cnodes, cW, c, v1)
        rel = tv @ vp - tv @ v_pt
        for t in range(p):
            dtv = dfr_dir[t, r]
            dv_pt = _wsum_dw(cnodes, dW[t, c], c, v1) + _wsum(cnodes, cW, c, dv1[t])
            drel = dtv @ vp + tv @ dvp[t] - dtv @ v_pt - tv @ dv_pt
            for d in range(3):
                out[t, d] += (dfr_om[t, r] / dt) * rel * tv[d] + (fr_om[r] / dt) * (drel * tv[d] + rel * dtv[d])
