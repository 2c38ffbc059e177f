"""Compiled per-step kernels (numba) of the FEM replay.

These fuse, per element, what :mod:`core.simulation.fem` writes as vector
operations (deformation gradient, Müller et al. 2016 rotation extraction, stresses,
force scatter) and the per-triangle sphere test of :mod:`core.simulation.contact`.
The numpy versions stay as the readable reference; tests check both agree.
Per-element 3x3 fields are element-major (E, 9) here (contiguous per element);
:mod:`core.simulation.fem` uses the transposed (9, E) layout.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["quat_to_matrix", "polar_update", "pk1_stress", "element_forces", "scatter_forces",
           "sphere_triangle_candidates", "subdivision_corners", "sphere_contacts", "constraint_matrix"]


@njit(cache=True, _nrt=False)
def quat_to_matrix(qx, qy, qz, qw, R):
    """Rotation matrix (9,) row-major of the unit quaternion (x, y, z, w), into R."""
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    R[0] = 1 - 2 * (yy + zz)
    R[1] = 2 * (xy - wz)
    R[2] = 2 * (xz + wy)
    R[3] = 2 * (xy + wz)
    R[4] = 1 - 2 * (xx + zz)
    R[5] = 2 * (yz - wx)
    R[6] = 2 * (xz - wy)
    R[7] = 2 * (yz + wx)
    R[8] = 1 - 2 * (xx + yy)


@njit(cache=True, fastmath={"contract", "arcp", "nsz", "reassoc"}, _nrt=False)
def pk1_stress(law, F, R, mu, lam, stiffening, P):
    """First Piola-Kirchhoff stress (9,) Pa of one element into P: law 0 corotational linear
    (Müller & Gross 2004; R its rotation), 1 stable neo-Hookean (Smith et al. 2018), 2
    stable neo-Hookean plus the Yeoh-type term ``2 k mu I_D (F - cof F)``, ``I_D = I_C - 3
    - 2 (J - 1)`` (see :func:`core.simulation.fem.pk1_stable_yeoh`)."""
    if law == 0:
        tr = -3.0
        for c in range(9):
            tr += R[c] * F[c]
        for c in range(9):
            P[c] = 2.0 * mu * (F[c] - R[c]) + lam * tr * R[c]
        return
    f0, f1, f2, f3, f4, f5, f6, f7, f8 = F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8]
    c0 = f4 * f8 - f5 * f7
    c1 = f5 * f6 - f3 * f8
    c2 = f3 * f7 - f4 * f6
    c3 = f2 * f7 - f1 * f8
    c4 = f0 * f8 - f2 * f6
    c5 = f1 * f6 - f0 * f7
    c6 = f1 * f5 - f2 * f4
    c7 = f2 * f3 - f0 * f5
    c8 = f0 * f4 - f1 * f3
    J = f0 * c0 + f1 * c1 + f2 * c2
    lam_s = lam + mu
    g = lam_s * (J - (1.0 + mu / lam_s))
    m = mu
    if law == 2:
        ic = f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3 + f4 * f4 + f5 * f5 + f6 * f6 + f7 * f7 + f8 * f8
        hy = 2.0 * stiffening * mu * (ic - 1.0 - 2.0 * J)
        m = mu + hy
        g = g - hy
    P[0] = m * f0 + g * c0
    P[1] = m * f1 + g * c1
    P[2] = m * f2 + g * c2
    P[3] = m * f3 + g * c3
    P[4] = m * f4 + g * c4
    P[5] = m * f5 + g * c5
    P[6] = m * f6 + g * c6
    P[7] = m * f7 + g * c7
    P[8] = m * f8 + g * c8


@njit(cache=True, fastmath={"contract", "arcp", "nsz", "reassoc"}, _nrt=False)
def polar_update(F, q, e, iterations, R):
    """Warm-started Newton iterations on the polar decomposition of F (9,) from the
    quaternion ``q[:, e]`` (updated in place); R (9,) receives the rotation.

    With ``B = R^T F``, the small rotation theta (element frame) solves
    ``axial(B - B^T) = (tr S I - S) theta``, ``S = sym(B)``: a Newton step on the polar
    condition, quadratically convergent (Müller et al. 2016's update is its diagonal
    approximation, kept as the fallback). The update is the unnormalised quaternion
    ``(theta/2, 1)``: a rotation by ``2 atan(|theta|/2)``, the same fixed point as the exact
    exponential map, without sin/cos."""
    qx, qy, qz, qw = q[0, e], q[1, e], q[2, e], q[3, e]
    for _ in range(iterations):
        quat_to_matrix(qx, qy, qz, qw, R)
        b00 = R[0] * F[0] + R[3] * F[3] + R[6] * F[6]
        b01 = R[0] * F[1] + R[3] * F[4] + R[6] * F[7]
        b02 = R[0] * F[2] + R[3] * F[5] + R[6] * F[8]
        b10 = R[1] * F[0] + R[4] * F[3] + R[7] * F[6]
        b11 = R[1] * F[1] + R[4] * F[4] + R[7] * F[7]
        b12 = R[1] * F[2] + R[4] * F[5] + R[7] * F[8]
        b20 = R[2] * F[0] + R[5] * F[3] + R[8] * F[6]
        b21 = R[2] * F[1] + R[5] * F[4] + R[8] * F[7]
        b22 = R[2] * F[2] + R[5] * F[5] + R[8] * F[8]
        v0 = b21 - b12
        v1 = b02 - b20
        v2 = b10 - b01
        tr = b00 + b11 + b22
        s01 = 0.5 * (b01 + b10)
        s02 = 0.5 * (b02 + b20)
        s12 = 0.5 * (b12 + b21)
        m00 = tr - b00
        m11 = tr - b11
        m22 = tr - b22
        c00 = m11 * m22 - s12 * s12
        c01 = s02 * s12 + s01 * m22
        c02 = s01 * s12 + s02 * m11
        det = m00 * c00 - s01 * c01 - s02 * c02
        if tr > 1e-6 and det > 1e-6 * tr * tr * tr:
            c11 = m00 * m22 - s02 * s02
            c12 = m00 * s12 + s01 * s02
            c22 = m00 * m11 - s01 * s01
            inv = 1.0 / det
            t0 = (c00 * v0 + c01 * v1 + c02 * v2) * inv
            t1 = (c01 * v0 + c11 * v1 + c12 * v2) * inv
            t2 = (c02 * v0 + c12 * v1 + c22 * v2) * inv
        else:
            inv = 1.0 / (abs(tr) + 1e-9)
            t0, t1, t2 = v0 * inv, v1 * inv, v2 * inv
        ang2 = t0 * t0 + t1 * t1 + t2 * t2
        if ang2 > 1.0:  # damp huge steps (inverted elements)
            sc = 1.0 / np.sqrt(ang2)
            t0, t1, t2 = t0 * sc, t1 * sc, t2 * sc
        if ang2 < 1e-28:
            break
        x1, y1, z1 = 0.5 * t0, 0.5 * t1, 0.5 * t2
        # q <- q * (x1, y1, z1, 1) (rotation applied in the element frame)
        nx_ = qw * x1 + qx + qy * z1 - qz * y1
        ny_ = qw * y1 - qx * z1 + qy + qz * x1
        nz_ = qw * z1 + qx * y1 - qy * x1 + qz
        nw_ = qw - qx * x1 - qy * y1 - qz * z1
        nrm = 1.0 / np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_ + nw_ * nw_)
        qx, qy, qz, qw = nx_ * nrm, ny_ * nrm, nz_ * nrm, nw_ * nrm
    q[0, e], q[1, e], q[2, e], q[3, e] = qx, qy, qz, qw
    quat_to_matrix(qx, qy, qz, qw, R)


@njit(cache=True, fastmath={"contract", "arcp", "nsz", "reassoc"})
def element_forces(x, tets, grad_n, volume, mu, lam, q, iterations, law, F_out, R_out, store, v, beta, stiffening):
    """Fused per-element pass: deformation gradient, rotation, PK1 stress, force scatter.

    Args:
        x: (N, 3) node positions, m.
        tets, grad_n, volume: mesh constants (see :class:`core.simulation.fem.ElementData`).
        mu, lam: (E,) Lamé parameters, Pa.
        q: (4, E) rotation quaternions, warm start; updated in place when rotations are
            computed (Newton iterations on the polar decomposition, see below).
        iterations: rotation-extraction iterations (0: skip rotations).
        law: 0 corotational linear (Müller & Gross 2004), 1 stable neo-Hookean
            (Smith et al. 2018), 2 stable neo-Hookean plus the Yeoh-type stiffening
            term ``stiffening * mu / 2 * (I_C - 3 - 2 (J - 1))^2`` (Yeoh 1993); see
            :func:`core.simulation.fem.pk1_stable_yeoh` for the exact energies.
        F_out, R_out: (E, 9) buffers receiving F and R (row-major 3x3 per element)
            when ``store`` is true (extra stress terms need them).
        v, beta: node velocities (N, 3) m/s and the Rayleigh stiffness coefficient (s);
            when beta > 0 the stiffness damping ``-beta K v`` (K the rest small-strain
            stiffness) is added, computed as the linear stress of the velocity gradient.
        stiffening: dimensionless Yeoh coefficient of law 2 (ignored by laws 0 and 1).

    Returns:
        (N, 3) internal nodal forces, N.
    """
    n_el = tets.shape[0]
    f = np.zeros((x.shape[0], 3))
    F = np.empty(9)
    R = np.empty(9)
    P = np.empty(9)
    for e in range(n_el):
        for i in range(3):
            for k in range(3):
                s = 0.0
                for a in range(4):
                    s += x[tets[e, a], i] * grad_n[e, a, k]
                F[3 * i + k] = s
        if iterations > 0:
            polar_update(F, q, e, iterations, R)
        else:
            for c in range(9):
                R[c] = 0.0
            R[0] = 1.0
            R[4] = 1.0
            R[8] = 1.0
        pk1_stress(law, F, R, mu[e], lam[e], stiffening, P)
        if store:
            for c in range(9):
                F_out[e, c] = F[c]
                R_out[e, c] = R[c]
        if beta > 0.0:
            # beta * (mu (H + H^T) + lam tr(H) I) with H the velocity gradient
            for i in range(3):
                for k in range(3):
                    h = 0.0
                    for a in range(4):
                        h += v[tets[e, a], i] * grad_n[e, a, k]
                    F[3 * i + k] = h
            trh = F[0] + F[4] + F[8]
            for i in range(3):
                for k in range(3):
                    P[3 * i + k] += beta * mu[e] * (F[3 * i + k] + F[3 * k + i])
                P[4 * i] += beta * lam[e] * trh
        V = volume[e]
        for a in range(4):
            node = tets[e, a]
            for i in range(3):
                s = 0.0
                for k in range(3):
                    s += P[3 * i + k] * grad_n[e, a, k]
                f[node, i] -= V * s
    return f


@njit(cache=True)
def scatter_forces(P, tets, grad_n, volume, n_nodes):
    """Nodal forces ``f_a = -V P gradN_a`` from stresses P (E, 9), summed, (N, 3) N."""
    f = np.zeros((n_nodes, 3))
    for e in range(tets.shape[0]):
        V = volume[e]
        for a in range(4):
            node = tets[e, a]
            for i in range(3):
                s = 0.0
                for k in range(3):
                    s += P[e, 3 * i + k] * grad_n[e, a, k]
                f[node, i] -= V * s
    return f


@njit(cache=True)
def sphere_triangle_candidates(x, triangles, centre, radius):
    """Indices of triangles whose bounding sphere reaches the probe sphere (int64 array)."""
    n = triangles.shape[0]
    out = np.empty(n, dtype=np.int64)
    m = 0
    for t in range(n):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        mx = (x[a, 0] + x[b, 0] + x[c, 0]) / 3.0
        my = (x[a, 1] + x[b, 1] + x[c, 1]) / 3.0
        mz = (x[a, 2] + x[b, 2] + x[c, 2]) / 3.0
        reach = 0.0
        for v in (a, b, c):
            d = (x[v, 0] - mx) ** 2 + (x[v, 1] - my) ** 2 + (x[v, 2] - mz) ** 2
            if d > reach:
                reach = d
        reach = np.sqrt(reach) + radius
        d2 = (mx - centre[0]) ** 2 + (my - centre[1]) ** 2 + (mz - centre[2]) ** 2
        if d2 < reach * reach:
            out[m] = t
            m += 1
    return out[:m]


@njit(cache=True)
def _closest_on_triangle(p, a, b, c, w):
    """Ericson 2004, Sec. 5.1.5; writes barycentric weights into w."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab @ ap
    d2 = ac @ ap
    if d1 <= 0.0 and d2 <= 0.0:
        w[0], w[1], w[2] = 1.0, 0.0, 0.0
        return
    bp = p - b
    d3 = ab @ bp
    d4 = ac @ bp
    if d3 >= 0.0 and d4 <= d3:
        w[0], w[1], w[2] = 0.0, 1.0, 0.0
        return
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        w[0], w[1], w[2] = 1.0 - v, v, 0.0
        return
    cp = p - c
    d5 = ab @ cp
    d6 = ac @ cp
    if d6 >= 0.0 and d5 <= d6:
        w[0], w[1], w[2] = 0.0, 0.0, 1.0
        return
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        v = d2 / (d2 - d6)
        w[0], w[1], w[2] = 1.0 - v, 0.0, v
        return
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        v = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        w[0], w[1], w[2] = 0.0, 1.0 - v, v
        return
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    ww = vc * denom
    w[0], w[1], w[2] = 1.0 - v - ww, v, ww


def subdivision_corners(n: int) -> np.ndarray:
    """Barycentric corners of the n x n uniform subdivision of a triangle.

    Each triangle (a, b, c) splits into n^2 congruent sub-triangles of area 1/n^2 of its
    own, oriented as the triangle (the grid ``a + i/n (b - a) + j/n (c - a)``,
    ``i + j <= n``: n(n+1)/2 upright and n(n-1)/2 inverted ones).

    Args:
        n: subdivisions per edge, >= 1 (1: the triangle itself).

    Returns:
        (n^2, 3, 3) float64: ``[s, corner, parent vertex]`` barycentric weights, so that the
        sub-triangle's corner is ``sum_j S[s, corner, j] * (a, b, c)[j]``.

    Raises:
        ValueError: n < 1.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"contact subdivision must be >= 1, got {n}")

    def bary(i, j):
        return (1.0 - (i + j) / n, i / n, j / n)

    out = []
    for i in range(n):
        for j in range(n - i):
            out.append((bary(i, j), bary(i + 1, j), bary(i, j + 1)))
            if i + j <= n - 2:
                out.append((bary(i + 1, j), bary(i + 1, j + 1), bary(i, j + 1)))
    return np.ascontiguousarray(out, dtype=np.float64)


@njit(cache=True)
def sphere_contacts(x, triangles, sub, centre, radius):
    """Penetrated sub-triangles of the surface: (parent triangle indices (k,), sub-triangle
    indices (k,), parent barycentric weights (k, 3), normals (k, 3), depth (k,), areas (k,),
    sub-triangle barycentric weights (k, 3)).

    Each surface triangle is split by ``sub`` (:func:`subdivision_corners`) into sub-triangles
    mapped barycentrically on its nodes (a finer collision surface on the coarse FEM
    surface); every sub-triangle whose closest point lies inside the sphere is one penalty
    contact of the sub-triangle's area. Same geometry as
    :func:`core.simulation.contact.find_contacts_reference` (the numpy reference).
    """
    cand = sphere_triangle_candidates(x, triangles, centre, radius)
    ns = sub.shape[0]
    k = cand.shape[0] * ns
    idx = np.empty(k, dtype=np.int64)
    sid = np.empty(k, dtype=np.int64)
    W = np.empty((k, 3))
    WS = np.empty((k, 3))
    N = np.empty((k, 3))
    D = np.empty(k)
    A = np.empty(k)
    w = np.empty(3)
    sa = np.empty(3)
    sb = np.empty(3)
    sc = np.empty(3)
    m = 0
    for t in cand:
        a = x[triangles[t, 0]]
        b = x[triangles[t, 1]]
        c = x[triangles[t, 2]]
        fn = np.cross(b - a, c - a)
        area2 = np.sqrt(fn @ fn)
        fn = fn / area2
        for s in range(ns):
            for d in range(3):
                sa[d] = sub[s, 0, 0] * a[d] + sub[s, 0, 1] * b[d] + sub[s, 0, 2] * c[d]
                sb[d] = sub[s, 1, 0] * a[d] + sub[s, 1, 1] * b[d] + sub[s, 1, 2] * c[d]
                sc[d] = sub[s, 2, 0] * a[d] + sub[s, 2, 1] * b[d] + sub[s, 2, 2] * c[d]
            if ns > 1:  # cheap rejection: the sub-triangle's bounding sphere misses the probe
                r2 = 0.0
                d2 = 0.0
                for d in range(3):
                    mc = (sa[d] + sb[d] + sc[d]) / 3.0
                    r2 = max(r2, (sa[d] - mc) ** 2 + (sb[d] - mc) ** 2 + (sc[d] - mc) ** 2)
                    d2 += (mc - centre[d]) ** 2
                reach = radius + np.sqrt(3.0 * r2)
                if d2 >= reach * reach:
                    continue
            _closest_on_triangle(centre, sa, sb, sc, w)
            q = w[0] * sa + w[1] * sb + w[2] * sc
            dv = q - centre
            dist = np.sqrt(dv @ dv)
            if dist >= radius:
                continue
            # the centre behind the face plane with its closest point inside the face: it has
            # passed through the surface, push inwards; with the closest point on an edge or a
            # corner the plane says nothing (next to a curved or dented surface a neighbour's
            # plane passes over a centre still outside, and took it as 5 mm deep: see
            # core.simulation.contact)
            if (centre - q) @ fn < 0.0 and w[0] > 0.0 and w[1] > 0.0 and w[2] > 0.0:
                N[m] = -fn
                D[m] = radius + dist
            else:
                N[m] = dv / max(dist, 1e-12)
                D[m] = radius - dist
            idx[m] = t
            sid[m] = s
            WS[m] = w
            for j in range(3):
                W[m, j] = w[0] * sub[s, 0, j] + w[1] * sub[s, 1, j] + w[2] * sub[s, 2, j]
            A[m] = 0.5 * area2 / ns
            m += 1
    return idx[:m], sid[:m], W[:m], N[:m], D[:m], A[:m], WS[:m]


@njit(cache=True)
def constraint_matrix(nodes, weights, directions, free_index, slot):
    """Dense form of low-rank constraint rows ``h_c = direction_c (x) weights_c``.

    Args:
        nodes: (k, 3) int64 triangle nodes; weights: (k, 3) barycentric weights;
        directions: (k, 3) unit vectors; free_index: (3N,) int64 dof -> free index or -1;
        slot: (n_free,) int64 scratch array filled with -1 (restored before returning).

    Returns:
        (uniq (m,) int64 free dofs touched, C (m, k) coefficients) with H = E_uniq C.
    """
    k = nodes.shape[0]
    uniq = np.empty(9 * k, dtype=np.int64)
    m = 0
    for c in range(k):
        for j in range(3):
            for a in range(3):
                d = free_index[3 * nodes[c, j] + a]
                if d >= 0 and slot[d] < 0:
                    slot[d] = m
                    uniq[m] = d
                    m += 1
    C = np.zeros((m, k))
    for c in range(k):
        for j in range(3):
            for a in range(3):
                d = free_index[3 * nodes[c, j] + a]
                if d >= 0:
                    C[slot[d], c] += weights[c, j] * directions[c, a]
    for i in range(m):
        slot[uniq[i]] = -1
    return uniq[:m], C
