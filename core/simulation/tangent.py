"""Tangent-linear kernels (numba): derivatives of the step's pieces along p directions.

Forward-mode sensitivities of the replay (:func:`core.simulation.sensitivity.simulate_sensitivities`)
differentiate the discrete step of :mod:`core.simulation.stepper` as it is computed: the
warm-started Newton iterations of the polar decomposition, the element stresses of each
law, the Maxwell arms' implicit update, the Rayleigh damping, and the contact geometry
(closest points, normals and areas of the candidate triangles, frozen per step). Each
kernel takes the forward values and ``p`` tangent directions and returns their
derivatives; the discrete choices (polar-iteration branch, contact region, active set,
friction's slip branch) are held where the forward step took them.

Arrays: ``dx, dv`` (p, N, 3); ``dq`` (p, 4, E); ``dmu, dlam`` (p, E) derivatives of the
element Lamé parameters (Pa per unit of the direction); ``deps`` (p, T, 9, E).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from core.simulation.kernels import pk1_stress, quat_to_matrix

__all__ = ["element_forces_tangent", "stiffness_apply", "contact_geometry_tangent", "quat_to_matrix_tangent"]

_FM = {"contract", "arcp", "nsz", "reassoc"}


@njit(cache=True, fastmath=_FM, _nrt=False)
def quat_to_matrix_tangent(q, dq, dR, k=0):
    """Derivative of :func:`core.simulation.kernels.quat_to_matrix` at q (4,) along row k of
    dq (p, 4) into row k of dR (p, 9) (rows, not slices: a slice in a per-element loop costs
    two atomic reference counts)."""
    qx, qy, qz, qw = q[0], q[1], q[2], q[3]
    dx, dy, dz, dw = dq[k, 0], dq[k, 1], dq[k, 2], dq[k, 3]
    dR[k, 0] = -4.0 * (qy * dy + qz * dz)
    dR[k, 1] = 2.0 * (dx * qy + qx * dy - dw * qz - qw * dz)
    dR[k, 2] = 2.0 * (dx * qz + qx * dz + dw * qy + qw * dy)
    dR[k, 3] = 2.0 * (dx * qy + qx * dy + dw * qz + qw * dz)
    dR[k, 4] = -4.0 * (qx * dx + qz * dz)
    dR[k, 5] = 2.0 * (dy * qz + qy * dz - dw * qx - qw * dx)
    dR[k, 6] = 2.0 * (dx * qz + qx * dz - dw * qy - qw * dy)
    dR[k, 7] = 2.0 * (dy * qz + qy * dz + dw * qx + qw * dx)
    dR[k, 8] = -4.0 * (qx * dx + qy * dy)


@njit(cache=True, fastmath=_FM, _nrt=False)
def _polar_tangent(F, dF, q, dq, iterations, R, dR, Rq, dRq, th, dth, b, db):
    """The warm-started polar iterations of :func:`core.simulation.kernels.polar_update`
    with their tangents: ``q`` (4,) and ``dq`` (p, 4) in, updated in place; R (9,) and
    dR (p, 9) of the result out. ``Rq`` (9,), ``dRq`` (p, 9), ``th`` (3,), ``dth`` (p, 3),
    ``b``, ``db`` (9,): work arrays."""
    p = dF.shape[0]
    for _ in range(iterations):
        quat_to_matrix(q[0], q[1], q[2], q[3], Rq)
        for k in range(p):
            quat_to_matrix_tangent(q, dq, dRq, k)
        # B = R^T F, B_ij = sum_k R_ki F_kj
        for i in range(3):
            for j in range(3):
                b[3 * i + j] = Rq[i] * F[j] + Rq[3 + i] * F[3 + j] + Rq[6 + i] * F[6 + j]
        v0 = b[7] - b[5]
        v1 = b[2] - b[6]
        v2 = b[3] - b[1]
        tr = b[0] + b[4] + b[8]
        s01 = 0.5 * (b[1] + b[3])
        s02 = 0.5 * (b[2] + b[6])
        s12 = 0.5 * (b[5] + b[7])
        m00 = tr - b[0]
        m11 = tr - b[4]
        m22 = tr - b[8]
        c00 = m11 * m22 - s12 * s12
        c01 = s02 * s12 + s01 * m22
        c02 = s01 * s12 + s02 * m11
        det = m00 * c00 - s01 * c01 - s02 * c02
        main = tr > 1e-6 and det > 1e-6 * tr * tr * tr
        c11 = m00 * m22 - s02 * s02
        c12 = m00 * s12 + s01 * s02
        c22 = m00 * m11 - s01 * s01
        if main:
            inv = 1.0 / det
            th[0] = (c00 * v0 + c01 * v1 + c02 * v2) * inv
            th[1] = (c01 * v0 + c11 * v1 + c12 * v2) * inv
            th[2] = (c02 * v0 + c12 * v1 + c22 * v2) * inv
        else:
            inv = 1.0 / (abs(tr) + 1e-9)
            th[0], th[1], th[2] = v0 * inv, v1 * inv, v2 * inv
        for k in range(p):
            for i in range(3):
                for j in range(3):
                    db[3 * i + j] = (dRq[k, i] * F[j] + dRq[k, 3 + i] * F[3 + j] + dRq[k, 6 + i] * F[6 + j]
                                     + Rq[i] * dF[k, j] + Rq[3 + i] * dF[k, 3 + j] + Rq[6 + i] * dF[k, 6 + j])
            dv0 = db[7] - db[5]
            dv1 = db[2] - db[6]
            dv2 = db[3] - db[1]
            dtr = db[0] + db[4] + db[8]
            if main:
                # theta = M^-1 v with M = tr(S) I - S: dtheta = M^-1 (dv - dM theta)
                ds01 = 0.5 * (db[1] + db[3])
                ds02 = 0.5 * (db[2] + db[6])
                ds12 = 0.5 * (db[5] + db[7])
                dm00, dm11, dm22 = dtr - db[0], dtr - db[4], dtr - db[8]
                w0 = dv0 - (dm00 * th[0] - ds01 * th[1] - ds02 * th[2])
                w1 = dv1 - (-ds01 * th[0] + dm11 * th[1] - ds12 * th[2])
                w2 = dv2 - (-ds02 * th[0] - ds12 * th[1] + dm22 * th[2])
                dth[k, 0] = (c00 * w0 + c01 * w1 + c02 * w2) * inv
                dth[k, 1] = (c01 * w0 + c11 * w1 + c12 * w2) * inv
                dth[k, 2] = (c02 * w0 + c12 * w1 + c22 * w2) * inv
            else:
                sg = 1.0 if tr >= 0.0 else -1.0
                dth[k, 0] = dv0 * inv - v0 * sg * dtr * inv * inv
                dth[k, 1] = dv1 * inv - v1 * sg * dtr * inv * inv
                dth[k, 2] = dv2 * inv - v2 * sg * dtr * inv * inv
        ang2 = th[0] * th[0] + th[1] * th[1] + th[2] * th[2]
        if ang2 > 1.0:
            sc = 1.0 / math.sqrt(ang2)
            for i in range(3):
                th[i] *= sc
            for k in range(p):
                dot = th[0] * dth[k, 0] + th[1] * dth[k, 1] + th[2] * dth[k, 2]
                for i in range(3):
                    dth[k, i] = (dth[k, i] - th[i] * dot) * sc
        qx, qy, qz, qw = q[0], q[1], q[2], q[3]
        x1, y1, z1 = 0.5 * th[0], 0.5 * th[1], 0.5 * th[2]
        nx_ = qw * x1 + qx + qy * z1 - qz * y1
        ny_ = qw * y1 - qx * z1 + qy + qz * x1
        nz_ = qw * z1 + qx * y1 - qy * x1 + qz
        nw_ = qw - qx * x1 - qy * y1 - qz * z1
        nrm = 1.0 / math.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_ + nw_ * nw_)
        qn0, qn1, qn2, qn3 = nx_ * nrm, ny_ * nrm, nz_ * nrm, nw_ * nrm
        for k in range(p):
            dqx, dqy, dqz, dqw = dq[k, 0], dq[k, 1], dq[k, 2], dq[k, 3]
            dx1, dy1, dz1 = 0.5 * dth[k, 0], 0.5 * dth[k, 1], 0.5 * dth[k, 2]
            dn0 = dqw * x1 + qw * dx1 + dqx + dqy * z1 + qy * dz1 - dqz * y1 - qz * dy1
            dn1 = dqw * y1 + qw * dy1 - dqx * z1 - qx * dz1 + dqy + dqz * x1 + qz * dx1
            dn2 = dqw * z1 + qw * dz1 + dqx * y1 + qx * dy1 - dqy * x1 - qy * dx1 + dqz
            dn3 = dqw - dqx * x1 - qx * dx1 - dqy * y1 - qy * dy1 - dqz * z1 - qz * dz1
            dot = qn0 * dn0 + qn1 * dn1 + qn2 * dn2 + qn3 * dn3
            dq[k, 0] = (dn0 - qn0 * dot) * nrm
            dq[k, 1] = (dn1 - qn1 * dot) * nrm
            dq[k, 2] = (dn2 - qn2 * dot) * nrm
            dq[k, 3] = (dn3 - qn3 * dot) * nrm
        if ang2 >= 1e-28:  # the forward iteration stops (and keeps q) at an exact fixed point
            q[0], q[1], q[2], q[3] = qn0, qn1, qn2, qn3
        else:
            break
    quat_to_matrix(q[0], q[1], q[2], q[3], R)
    for k in range(p):
        quat_to_matrix_tangent(q, dq, dR, k)


@njit(cache=True, fastmath=_FM, _nrt=False)
def _cofactor(F, c):
    f0, f1, f2, f3, f4, f5, f6, f7, f8 = F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8]
    c[0] = f4 * f8 - f5 * f7
    c[1] = f5 * f6 - f3 * f8
    c[2] = f3 * f7 - f4 * f6
    c[3] = f2 * f7 - f1 * f8
    c[4] = f0 * f8 - f2 * f6
    c[5] = f1 * f6 - f0 * f7
    c[6] = f1 * f5 - f2 * f4
    c[7] = f2 * f3 - f0 * f5
    c[8] = f0 * f4 - f1 * f3


@njit(cache=True, fastmath=_FM, _nrt=False)
def _cofactor_tangent(F, dF, t, c):
    f0, f1, f2, f3, f4, f5, f6, f7, f8 = F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8]
    d0, d1, d2, d3, d4, d5, d6, d7, d8 = dF[t, 0], dF[t, 1], dF[t, 2], dF[t, 3], dF[t, 4], dF[t, 5], dF[t, 6], dF[t, 7], dF[t, 8]
    c[0] = d4 * f8 + f4 * d8 - d5 * f7 - f5 * d7
    c[1] = d5 * f6 + f5 * d6 - d3 * f8 - f3 * d8
    c[2] = d3 * f7 + f3 * d7 - d4 * f6 - f4 * d6
    c[3] = d2 * f7 + f2 * d7 - d1 * f8 - f1 * d8
    c[4] = d0 * f8 + f0 * d8 - d2 * f6 - f2 * d6
    c[5] = d1 * f6 + f1 * d6 - d0 * f7 - f0 * d7
    c[6] = d1 * f5 + f1 * d5 - d2 * f4 - f2 * d4
    c[7] = d2 * f3 + f2 * d3 - d0 * f5 - f0 * d5
    c[8] = d0 * f4 + f0 * d4 - d1 * f3 - f1 * d3


@njit(cache=True, fastmath=_FM)
def element_forces_tangent(x, v, dx, dv, tets, grad_n, volume, mu, lam, dmu, dlam, law, stiffening,
                           q0, dq0, iterations, beta, term_tau, term_k, dtau, dk, eps_v, deps_v, dt,
                           q_out, dq_out, deps_v_new, df, f, eps_v_new):
    """The internal forces of :func:`core.simulation.stepper` and their derivatives along p
    directions, in one pass over the elements.

    Forward inputs: positions ``x`` and velocities ``v`` (N, 3), the step's start rotations
    ``q0`` (4, E), the Maxwell arms' viscous strains ``eps_v`` (T, 9, E). Tangents:
    ``dx, dv`` (p, N, 3), ``dq0`` (p, 4, E), ``dmu, dlam`` (p, E), ``dtau, dk`` (p, T) of the
    arms' relaxation times and stiffness ratios, ``deps_v`` (p, T, 9, E). Outputs:
    ``q_out`` (4, E) the rotations after the polar iterations (as the forward step),
    ``dq_out`` (p, 4, E), ``deps_v_new`` (p, T, 9, E), ``df`` (p, N, 3) N, and the forward
    forces ``f`` (N, 3) N (both zeroed here) and viscous strains ``eps_v_new`` (T, 9, E).
    """
    n_el = tets.shape[0]
    p = dx.shape[0]
    n_terms = term_tau.size
    df[:] = 0.0
    f[:] = 0.0
    P = np.empty(9)
    Hs_all = np.empty((max(n_terms, 1), 9))
    F = np.empty(9)
    dF = np.empty((p, 9))
    R = np.empty(9)
    dR = np.empty((p, 9))
    w_R = np.empty(9)
    w_dR = np.empty((p, 9))
    w_th = np.empty(3)
    w_dth = np.empty((p, 3))
    w_b = np.empty(9)
    w_db = np.empty(9)
    qe = np.empty(4)
    dqe = np.empty((p, 4))
    dP = np.empty(9)
    cof = np.empty(9)
    dcof = np.empty(9)
    eps = np.empty(9)
    deps = np.empty(9)
    Hs = np.empty(9)
    dHs = np.empty(9)
    Hv = np.empty(9)
    dHv = np.empty(9)
    gn = np.empty((4, 3))
    xa = np.empty((4, 3))
    dxa = np.empty((4, 3))
    for e in range(n_el):
        for a in range(4):
            for k in range(3):
                gn[a, k] = grad_n[e, a, k]
                xa[a, k] = x[tets[e, a], k]
        for i in range(3):
            for k in range(3):
                F[3 * i + k] = xa[0, i] * gn[0, k] + xa[1, i] * gn[1, k] + xa[2, i] * gn[2, k] + xa[3, i] * gn[3, k]
        for t in range(p):
            for a in range(4):
                nd = tets[e, a]
                dxa[a, 0] = dx[t, nd, 0]
                dxa[a, 1] = dx[t, nd, 1]
                dxa[a, 2] = dx[t, nd, 2]
            for i in range(3):
                for k in range(3):
                    dF[t, 3 * i + k] = (dxa[0, i] * gn[0, k] + dxa[1, i] * gn[1, k] + dxa[2, i] * gn[2, k]
                                        + dxa[3, i] * gn[3, k])
        for c in range(4):
            qe[c] = q0[c, e]
            for t in range(p):
                dqe[t, c] = dq0[t, c, e]
        if iterations > 0:
            _polar_tangent(F, dF, qe, dqe, iterations, R, dR, w_R, w_dR, w_th, w_dth, w_b, w_db)
        else:
            for c in range(9):
                R[c] = 0.0
                for t in range(p):
                    dR[t, c] = 0.0
            R[0] = 1.0
            R[4] = 1.0
            R[8] = 1.0
        for c in range(4):
            q_out[c, e] = qe[c]
            for t in range(p):
                dq_out[t, c, e] = dqe[t, c]
        mu_e, lam_e = mu[e], lam[e]
        trm = -3.0
        for c in range(9):
            trm += R[c] * F[c]
        J = 0.0
        if law != 0:
            _cofactor(F, cof)
            J = F[0] * cof[0] + F[1] * cof[1] + F[2] * cof[2]
        if n_terms > 0:
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
        if beta > 0.0:
            for a in range(4):
                nd = tets[e, a]
                xa[a, 0] = v[nd, 0]
                xa[a, 1] = v[nd, 1]
                xa[a, 2] = v[nd, 2]
            for i in range(3):
                for k in range(3):
                    Hv[3 * i + k] = xa[0, i] * gn[0, k] + xa[1, i] * gn[1, k] + xa[2, i] * gn[2, k] + xa[3, i] * gn[3, k]
        V = volume[e]
        # forward stress: the law's, the Maxwell arms', the damping's
        pk1_stress(law, F, R, mu_e, lam_e, stiffening, P)
        for tt in range(n_terms):
            h = dt / term_tau[tt]
            sc = term_k[tt] / (1.0 + h)
            trd = 0.0
            for c in (0, 4, 8):
                trd += eps[c] - eps_v[tt, c, e]
            for c in range(9):
                Hs_all[tt, c] = sc * 2.0 * mu_e * (eps[c] - eps_v[tt, c, e])
                eps_v_new[tt, c, e] = (eps_v[tt, c, e] + h * eps[c]) / (1.0 + h)
            for c in (0, 4, 8):
                Hs_all[tt, c] += sc * lam_e * trd
            for i in range(3):
                for k in range(3):
                    P[3 * i + k] += (R[3 * i] * Hs_all[tt, k] + R[3 * i + 1] * Hs_all[tt, 3 + k]
                                     + R[3 * i + 2] * Hs_all[tt, 6 + k])
        if beta > 0.0:
            trh = Hv[0] + Hv[4] + Hv[8]
            for i in range(3):
                for k in range(3):
                    P[3 * i + k] += beta * mu_e * (Hv[3 * i + k] + Hv[3 * k + i])
                P[4 * i] += beta * lam_e * trh
        for a in range(4):
            nd = tets[e, a]
            g0, g1, g2 = gn[a, 0], gn[a, 1], gn[a, 2]
            f[nd, 0] -= V * (P[0] * g0 + P[1] * g1 + P[2] * g2)
            f[nd, 1] -= V * (P[3] * g0 + P[4] * g1 + P[5] * g2)
            f[nd, 2] -= V * (P[6] * g0 + P[7] * g1 + P[8] * g2)
        for t in range(p):
            dm, dl = dmu[t, e], dlam[t, e]
            if law == 0:
                dtrm = 0.0
                for c in range(9):
                    dtrm += dR[t, c] * F[c] + R[c] * dF[t, c]
                for c in range(9):
                    dP[c] = (2.0 * dm * (F[c] - R[c]) + 2.0 * mu_e * (dF[t, c] - dR[t, c])
                             + (dl * trm + lam_e * dtrm) * R[c] + lam_e * trm * dR[t, c])
            else:
                _cofactor_tangent(F, dF, t, dcof)
                dJ = 0.0
                for c in range(9):
                    dJ += cof[c] * dF[t, c]
                lam_s = lam_e + mu_e
                dlam_s = dl + dm
                alpha = 1.0 + mu_e / lam_s
                dalpha = dm / lam_s - mu_e * dlam_s / (lam_s * lam_s)
                g = lam_s * (J - alpha)
                dg = dlam_s * (J - alpha) + lam_s * (dJ - dalpha)
                for c in range(9):
                    dP[c] = dm * F[c] + mu_e * dF[t, c] + dg * cof[c] + g * dcof[c]
                if law == 2:
                    ic = 0.0
                    dic = 0.0
                    for c in range(9):
                        ic += F[c] * F[c]
                        dic += 2.0 * F[c] * dF[t, c]
                    i_d = ic - 1.0 - 2.0 * J
                    di_d = dic - 2.0 * dJ
                    hy = 2.0 * stiffening * mu_e * i_d
                    dhy = 2.0 * stiffening * (dm * i_d + mu_e * di_d)
                    for c in range(9):
                        dP[c] += dhy * (F[c] - cof[c]) + hy * (dF[t, c] - dcof[c])
            for tt in range(n_terms):
                tau = term_tau[tt]
                h = dt / tau
                dh = -dt * dtau[t, tt] / (tau * tau)
                sc = term_k[tt] / (1.0 + h)
                dsc = dk[t, tt] / (1.0 + h) - term_k[tt] * dh / ((1.0 + h) * (1.0 + h))
                for i in range(3):
                    for k in range(3):
                        deps[3 * i + k] = (dR[t, i] * F[k] + dR[t, 3 + i] * F[3 + k] + dR[t, 6 + i] * F[6 + k]
                                           + R[i] * dF[t, k] + R[3 + i] * dF[t, 3 + k] + R[6 + i] * dF[t, 6 + k])
                for i in range(3):
                    for k in range(i + 1, 3):
                        s = 0.5 * (deps[3 * i + k] + deps[3 * k + i])
                        deps[3 * i + k] = s
                        deps[3 * k + i] = s
                trd = 0.0
                dtrd = 0.0
                for c in (0, 4, 8):
                    trd += eps[c] - eps_v[tt, c, e]
                    dtrd += deps[c] - deps_v[t, tt, c, e]
                for c in range(9):
                    dd = eps[c] - eps_v[tt, c, e]
                    ddd = deps[c] - deps_v[t, tt, c, e]
                    Hs[c] = Hs_all[tt, c]
                    dHs[c] = dsc * 2.0 * mu_e * dd + sc * 2.0 * (dm * dd + mu_e * ddd)
                    ev = eps_v[tt, c, e]
                    dev = deps_v[t, tt, c, e]
                    deps_v_new[t, tt, c, e] = ((dev + dh * eps[c] + h * deps[c]) / (1.0 + h)
                                               - (ev + h * eps[c]) * dh / ((1.0 + h) * (1.0 + h)))
                for c in (0, 4, 8):
                    dHs[c] += dsc * lam_e * trd + sc * (dl * trd + lam_e * dtrd)
                for i in range(3):
                    for k in range(3):
                        dP[3 * i + k] += (dR[t, 3 * i] * Hs[k] + dR[t, 3 * i + 1] * Hs[3 + k] + dR[t, 3 * i + 2] * Hs[6 + k]
                                          + R[3 * i] * dHs[k] + R[3 * i + 1] * dHs[3 + k] + R[3 * i + 2] * dHs[6 + k])
            if beta > 0.0:
                for a in range(4):
                    nd = tets[e, a]
                    dxa[a, 0] = dv[t, nd, 0]
                    dxa[a, 1] = dv[t, nd, 1]
                    dxa[a, 2] = dv[t, nd, 2]
                for i in range(3):
                    for k in range(3):
                        dHv[3 * i + k] = (dxa[0, i] * gn[0, k] + dxa[1, i] * gn[1, k] + dxa[2, i] * gn[2, k]
                                          + dxa[3, i] * gn[3, k])
                trh = Hv[0] + Hv[4] + Hv[8]
                dtrh = dHv[0] + dHv[4] + dHv[8]
                for i in range(3):
                    for k in range(3):
                        dP[3 * i + k] += beta * (dm * (Hv[3 * i + k] + Hv[3 * k + i])
                                                 + mu_e * (dHv[3 * i + k] + dHv[3 * k + i]))
                    dP[4 * i] += beta * (dl * trh + lam_e * dtrh)
            for a in range(4):
                nd = tets[e, a]
                g0, g1, g2 = gn[a, 0], gn[a, 1], gn[a, 2]
                df[t, nd, 0] -= V * (dP[0] * g0 + dP[1] * g1 + dP[2] * g2)
                df[t, nd, 1] -= V * (dP[3] * g0 + dP[4] * g1 + dP[5] * g2)
                df[t, nd, 2] -= V * (dP[6] * g0 + dP[7] * g1 + dP[8] * g2)


@njit(cache=True, fastmath=_FM)
def stiffness_apply(u, tets, grad_n, volume, mus, lams, out):
    """``out[t] = K(mus[t], lams[t]) u`` (N/m times m: N), the small-strain stiffness of
    :func:`core.simulation.fem.linear_stiffness` with per-element Lamé parameters ``mus,
    lams`` (p, E) applied to one displacement ``u`` (N, 3); out (p, N, 3) is zeroed here."""
    p = mus.shape[0]
    out[:] = 0.0
    H = np.empty(9)
    for e in range(tets.shape[0]):
        for i in range(3):
            for k in range(3):
                s = 0.0
                for a in range(4):
                    s += u[tets[e, a], i] * grad_n[e, a, k]
                H[3 * i + k] = s
        trh = H[0] + H[4] + H[8]
        V = volume[e]
        for t in range(p):
            m, lm = mus[t, e], lams[t, e]
            if m == 0.0 and lm == 0.0:
                continue
            for a in range(4):
                nd = tets[e, a]
                g = grad_n[e, a]
                for i in range(3):
                    s = 0.0
                    for k in range(3):
                        Pik = m * (H[3 * i + k] + H[3 * k + i])
                        if i == k:
                            Pik += lm * trh
                        s += Pik * g[k]
                    out[t, nd, i] += V * s


@njit(cache=True)
def contact_geometry_tangent(x, dx, centre, dcentre, cnodes, sub, csub, cWs, cN, dW, dN, dA):
    """Derivatives of the candidate contacts' barycentric weights ``dW`` (p, k, 3) (on the
    parent triangle's nodes), normals ``dN`` (p, k, 3) and areas ``dA`` (p, k) (outputs) along
    ``dx`` (p, N, 3) and the probe centre's ``dcentre`` (p, 3), for the contacts found by
    :func:`core.simulation.kernels.sphere_contacts` at ``x`` (sub-triangles ``csub`` of the
    subdivision ``sub``, weights in the sub-triangle ``cWs``, normals ``cN``).

    The closest point's region in its sub-triangle (a vertex: one weight non-zero; an edge:
    two; the face: three) and whether the centre lies behind the face plane are those of the
    forward step. Normal: the unit vector from the centre to the closest point, or the
    inward face normal behind the plane (Ericson 2004, Sec. 5.1.5). A sub-triangle's corners
    are fixed barycentric combinations of its triangle's nodes, so their derivatives are the
    same combinations of the nodes' derivatives."""
    p = dx.shape[0]
    k = cnodes.shape[0]
    for c in range(k):
        ia, ib, ic = cnodes[c, 0], cnodes[c, 1], cnodes[c, 2]
        S = sub[csub[c]]
        a = S[0, 0] * x[ia] + S[0, 1] * x[ib] + S[0, 2] * x[ic]
        b = S[1, 0] * x[ia] + S[1, 1] * x[ib] + S[1, 2] * x[ic]
        cc = S[2, 0] * x[ia] + S[2, 1] * x[ib] + S[2, 2] * x[ic]
        e1 = b - a
        e2 = cc - a
        cr = np.cross(e1, e2)
        area2 = math.sqrt(cr @ cr)
        fn = cr / area2
        w = cWs[c]
        q = w[0] * a + w[1] * b + w[2] * cc
        d = q - centre
        dist = math.sqrt(d @ d)
        nz = 0
        for j in range(3):
            if w[j] != 0.0:
                nz += 1
        behind = (centre - q) @ fn < 0.0 and nz == 3  # as the forward kernel: inside the face only
        pts = (a, b, cc)
        for t in range(p):
            da = S[0, 0] * dx[t, ia] + S[0, 1] * dx[t, ib] + S[0, 2] * dx[t, ic]
            db = S[1, 0] * dx[t, ia] + S[1, 1] * dx[t, ib] + S[1, 2] * dx[t, ic]
            dcc = S[2, 0] * dx[t, ia] + S[2, 1] * dx[t, ib] + S[2, 2] * dx[t, ic]
            dpts = (da, db, dcc)
            de1 = db - da
            de2 = dcc - da
            dcr = np.cross(de1, e2) + np.cross(e1, de2)
            dA[t, c] = 0.5 * (fn @ dcr)
            dfn = (dcr - fn * (fn @ dcr)) / area2
            dw = np.zeros(3)
            if nz == 2:
                i0, i1 = 0, 1
                if w[0] == 0.0:
                    i0, i1 = 1, 2
                elif w[1] == 0.0:
                    i0, i1 = 0, 2
                P0, P1 = pts[i0], pts[i1]
                dP0, dP1 = dpts[i0], dpts[i1]
                e = P1 - P0
                de = dP1 - dP0
                ee = e @ e
                tt = (centre - P0) @ e / ee
                dtt = ((dcentre[t] - dP0) @ e + (centre - P0) @ de) / ee - 2.0 * tt * (e @ de) / ee
                dw[i0] = -dtt
                dw[i1] = dtt
            elif nz == 3:
                dvec = centre - a
                ddvec = dcentre[t] - da
                g11, g12, g22 = e1 @ e1, e1 @ e2, e2 @ e2
                dg11, dg12, dg22 = 2.0 * (e1 @ de1), de1 @ e2 + e1 @ de2, 2.0 * (e2 @ de2)
                vv, ww = w[1], w[2]
                r1 = de1 @ dvec + e1 @ ddvec - (dg11 * vv + dg12 * ww)
                r2 = de2 @ dvec + e2 @ ddvec - (dg12 * vv + dg22 * ww)
                det = g11 * g22 - g12 * g12
                dvv = (g22 * r1 - g12 * r2) / det
                dww = (g11 * r2 - g12 * r1) / det
                dw[0] = -dvv - dww
                dw[1] = dvv
                dw[2] = dww
            for j in range(3):
                dW[t, c, j] = dw[0] * S[0, j] + dw[1] * S[1, j] + dw[2] * S[2, j]
            if behind:
                for j in range(3):
                    dN[t, c, j] = -dfn[j]
            else:
                dq = dw[0] * a + dw[1] * b + dw[2] * cc + w[0] * da + w[1] * db + w[2] * dcc
                dd = dq - dcentre[t]
                nvec = cN[c]
                dot = nvec @ dd
                for j in range(3):
                    dN[t, c, j] = (dd[j] - nvec[j] * dot) / max(dist, 1e-12)
