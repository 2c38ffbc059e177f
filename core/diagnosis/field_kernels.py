"""Compiled kernels of the box's residual field (:mod:`core.diagnosis.fields`).

One point's signed normal residual against a face of the box grid, and its derivative
along directions of the node positions, are written once here (:func:`_point_residual`,
:func:`_point_residual_tangent`) and used two ways:

- per face, for points already assigned to it (:func:`face_residuals_kernel`,
  :func:`face_residuals_tangent_kernel`: :func:`core.diagnosis.fields.face_residuals`);
- fused over whole frames (:func:`box_field`, :func:`box_field_tangent`): the points are
  read where they are stored (a sequence's memory-mapped clouds and the kept indices into
  them), each point's face is looked up from its bin, and the bin means and per-face
  scatter are accumulated in the same pass.

Why fused: the per-face path spent ~85 % of a paper-size sequence's residual field
(1800 frames, 16.8 M binned points, 2.2 s) in numpy around the 0.35 s kernel (gathering the
points, per-face masks and copies, ``np.unique``, ``np.bincount``): a diagnosis replays a
sequence's field thousands of times.

Face geometry (:func:`face_geometry`) is a (5, 8) int64 table (normal axis, in-plane axes
u < v, the face's first node, node strides along u and v, nodes along u and v) and a (5, 3)
float64 table (cell sizes along u and v, m; the outward sign) in the order of
:data:`core.diagnosis.fields.FACES`. Nodes are numbered grid-major as
:func:`core.simulation.mesh.box_mesh` numbers them: ``(ix * ny + iy) * nz + iz``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["face_geometry", "face_residuals_kernel", "face_residuals_tangent_kernel", "box_field",
           "box_field_tangent"]

FACE_AXES = ((2, True), (0, False), (0, True), (1, False), (1, True))
"""(normal axis, at the high end) of each face of ``fields.FACES`` ("top", "-x", "+x", "-y", "+y")."""


def face_geometry(grid, size) -> tuple[np.ndarray, np.ndarray]:
    """((5, 8) int64, (5, 3) float64) tables of the box's faces (module docstring).

    Args:
        grid: (nx, ny, nz) nodes along each axis (each >= 2). size: (3,) box size, m.
    """
    g = [int(n) for n in grid]
    stride = (g[1] * g[2], g[2], 1)
    gi = np.zeros((len(FACE_AXES), 8), dtype=np.int64)
    gf = np.zeros((len(FACE_AXES), 3), dtype=np.float64)
    for k, (axis, high) in enumerate(FACE_AXES):
        u, v = [a for a in (0, 1, 2) if a != axis]
        base = (g[axis] - 1) * stride[axis] if high else 0
        gi[k] = (axis, u, v, base, stride[u], stride[v], g[u], g[v])
        gf[k] = (float(size[u]) / (g[u] - 1), float(size[v]) / (g[v] - 1), 1.0 if high else -1.0)
    return gi, gf


@njit(cache=True, inline="always")
def _cell(pu, pv, hu, hv, nu, nv):
    i = min(max(int(math.floor(pu / hu)), 0), nu - 2)
    j = min(max(int(math.floor(pv / hv)), 0), nv - 2)
    return i, j, pu / hu - i, pv / hv - j


@njit(cache=True, inline="always")
def _coord(x0, x1, x2, a):
    return x0 if a == 0 else (x1 if a == 1 else x2)


@njit(cache=True, inline="always")
def _moved_cell(pu, pv, pos, fr, base, su, sv, nu, nv, hu, hv, u, v):
    """The point's rest cell with its bilinear weights and first node, and the cell it
    falls in once that cell's in-plane node motion is taken out (first order):
    ``(w00, w10, w01, w11, n00, wa, wb, m00)``; a cell's other nodes are ``+ su``, ``+ sv``."""
    i, j, wa, wb = _cell(pu, pv, hu, hv, nu, nv)
    w00, w10, w01, w11 = (1 - wa) * (1 - wb), wa * (1 - wb), (1 - wa) * wb, wa * wb
    n00 = base + i * su + j * sv
    n10, n01 = n00 + su, n00 + sv
    n11 = n10 + sv
    du = (w00 * (pos[fr, n00, u] - i * hu) + w10 * (pos[fr, n10, u] - (i + 1) * hu)
          + w01 * (pos[fr, n01, u] - i * hu) + w11 * (pos[fr, n11, u] - (i + 1) * hu))
    dv = (w00 * (pos[fr, n00, v] - j * hv) + w10 * (pos[fr, n10, v] - j * hv)
          + w01 * (pos[fr, n01, v] - (j + 1) * hv) + w11 * (pos[fr, n11, v] - (j + 1) * hv))
    i2, j2, wa2, wb2 = _cell(pu - du, pv - dv, hu, hv, nu, nv)
    return w00, w10, w01, w11, n00, wa2, wb2, base + i2 * su + j2 * sv


@njit(cache=True, inline="always")
def _point_residual(x0, x1, x2, pos, fr, gi, gf, k):
    """Signed normal residual (m) of the point (x0, x1, x2) against face ``k`` of frame
    ``fr`` of ``pos`` (F, N, 3): the in-plane motion of its rest cell corrected to first
    order, then the bilinear face's normal coordinate; positive outside the model."""
    axis, u, v, base, su, sv, nu, nv = gi[k, 0], gi[k, 1], gi[k, 2], gi[k, 3], gi[k, 4], gi[k, 5], gi[k, 6], gi[k, 7]
    hu, hv, sign = gf[k, 0], gf[k, 1], gf[k, 2]
    pu, pv, pa = _coord(x0, x1, x2, u), _coord(x0, x1, x2, v), _coord(x0, x1, x2, axis)
    _, _, _, _, _, wa, wb, m00 = _moved_cell(pu, pv, pos, fr, base, su, sv, nu, nv, hu, hv, u, v)
    m10, m01 = m00 + su, m00 + sv
    m11 = m10 + sv
    z = ((1 - wa) * (1 - wb) * pos[fr, m00, axis] + wa * (1 - wb) * pos[fr, m10, axis]
         + (1 - wa) * wb * pos[fr, m01, axis] + wa * wb * pos[fr, m11, axis])
    return sign * (pa - z)


@njit(cache=True, inline="always")
def _point_residual_tangent(x0, x1, x2, pos, dpos, fr, gi, gf, k, out, m):
    """Writes ``out[t, m]``, the derivative of :func:`_point_residual` along each direction
    ``dpos[t]`` (p, F, N, 3) of the node positions (the point's cells held: the residual is
    bilinear within them)."""
    axis, u, v, base, su, sv, nu, nv = gi[k, 0], gi[k, 1], gi[k, 2], gi[k, 3], gi[k, 4], gi[k, 5], gi[k, 6], gi[k, 7]
    hu, hv, sign = gf[k, 0], gf[k, 1], gf[k, 2]
    pu, pv = _coord(x0, x1, x2, u), _coord(x0, x1, x2, v)
    w00, w10, w01, w11, n00, wa2, wb2, m00 = _moved_cell(pu, pv, pos, fr, base, su, sv, nu, nv, hu, hv, u, v)
    n10, n01 = n00 + su, n00 + sv
    n11 = n10 + sv
    m10, m01 = m00 + su, m00 + sv
    m11 = m10 + sv
    f00, f10, f01, f11 = pos[fr, m00, axis], pos[fr, m10, axis], pos[fr, m01, axis], pos[fr, m11, axis]
    dz_dwa = (1 - wb2) * (f10 - f00) + wb2 * (f11 - f01)
    dz_dwb = (1 - wa2) * (f01 - f00) + wa2 * (f11 - f10)
    for t in range(dpos.shape[0]):
        ddu = (w00 * dpos[t, fr, n00, u] + w10 * dpos[t, fr, n10, u] + w01 * dpos[t, fr, n01, u]
               + w11 * dpos[t, fr, n11, u])
        ddv = (w00 * dpos[t, fr, n00, v] + w10 * dpos[t, fr, n10, v] + w01 * dpos[t, fr, n01, v]
               + w11 * dpos[t, fr, n11, v])
        dz = ((1 - wa2) * (1 - wb2) * dpos[t, fr, m00, axis] + wa2 * (1 - wb2) * dpos[t, fr, m10, axis]
              + (1 - wa2) * wb2 * dpos[t, fr, m01, axis] + wa2 * wb2 * dpos[t, fr, m11, axis]
              - dz_dwa * ddu / hu - dz_dwb * ddv / hv)
        out[t, m] = -sign * dz


@njit(cache=True)
def face_residuals_kernel(points, pos, frames, gi, gf, k):
    """(M,) :func:`_point_residual` of ``points`` (M, 3) against face ``k``, point m in
    frame ``frames[m]`` of ``pos`` (F, N, 3)."""
    out = np.empty(points.shape[0])
    for m in range(points.shape[0]):
        out[m] = _point_residual(points[m, 0], points[m, 1], points[m, 2], pos, frames[m], gi, gf, k)
    return out


@njit(cache=True)
def face_residuals_tangent_kernel(points, pos, dpos, frames, gi, gf, k):
    """(p, M) :func:`_point_residual_tangent` of ``points`` (M, 3) against face ``k``."""
    out = np.empty((dpos.shape[0], points.shape[0]))
    for m in range(points.shape[0]):
        _point_residual_tangent(points[m, 0], points[m, 1], points[m, 2], pos, dpos, frames[m], gi, gf, k, out, m)
    return out


@njit(cache=True)
def box_field(P, cstart, kept, kstart, bins, frames, pos, face_of_bin, gi, gf, counts, field, ss, npts):
    """Accumulate the residual field of ``frames`` in place.

    Args:
        P: (P, 3) points of every frame, float32 or float64, m (a sequence's clouds,
            possibly memory-mapped). cstart: (F + 1,) int64 first point of each frame in P.
        kept: (K,) int32/int64 index of each binned point within its frame's points;
            kstart: (F + 1,) int64 first binned point of each frame; bins: (K,) int bin.
        frames: (n,) int64 the frames to do (finite positions, some points).
        pos: (F, N, 3) float64 node positions, m. face_of_bin: (B,) int64 face of each bin.
        gi, gf: :func:`face_geometry`. counts: (F, B) int64 binned points per bin.
        field: (F, B) float64, written: each done frame's bin means, m (0 where empty).
        ss: (G,) float64, added to: within-bin sums of squared deviations per face, m^2.
        npts: (G,) int64, added to: points per face.
    """
    B = counts.shape[1]
    sums = np.zeros(B)
    for fi in range(frames.size):
        f = frames[fi]
        k0, k1, c0 = kstart[f], kstart[f + 1], cstart[f]
        r = np.empty(k1 - k0)
        sums[:] = 0.0
        for k in range(k0, k1):
            q = c0 + kept[k]
            b = bins[k]
            r[k - k0] = _point_residual(np.float64(P[q, 0]), np.float64(P[q, 1]), np.float64(P[q, 2]), pos, f, gi, gf,
                                        face_of_bin[b])
            sums[b] += r[k - k0]
        for b in range(B):
            field[f, b] = sums[b] / counts[f, b] if counts[f, b] > 0 else 0.0
        for k in range(k0, k1):
            b = bins[k]
            d = r[k - k0] - field[f, b]
            ss[face_of_bin[b]] += d * d
            npts[face_of_bin[b]] += 1


@njit(cache=True)
def box_field_tangent(P, cstart, kept, kstart, bins, frames, pos, dpos, face_of_bin, gi, gf, counts, out):
    """Accumulate the derivatives (p, F, B) of :func:`box_field`'s bin means along the
    directions ``dpos`` (p, F, N, 3) into ``out`` for ``frames`` (arguments as there)."""
    n_dir, B = dpos.shape[0], counts.shape[1]
    dr = np.empty((n_dir, 1))
    for fi in range(frames.size):
        f = frames[fi]
        c0 = cstart[f]
        for k in range(kstart[f], kstart[f + 1]):
            q = c0 + kept[k]
            b = bins[k]
            _point_residual_tangent(np.float64(P[q, 0]), np.float64(P[q, 1]), np.float64(P[q, 2]), pos, dpos, f, gi,
                                    gf, face_of_bin[b], dr, 0)
            for t in range(n_dir):
                out[t, f, b] += dr[t, 0]
        for b in range(B):
            if counts[f, b] > 0:
                for t in range(n_dir):
                    out[t, f, b] /= counts[f, b]
