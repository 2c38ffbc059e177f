"""Banded Cholesky solves and low-rank (Woodbury) updates, compiled (numba).

The replay's system matrix ``A`` is constant per model and factorised once in banded
form (:class:`core.simulation.model.Model`); contact and friction add low-rank terms
``H diag(omega) H^T`` with ``H = E_uniq C`` (rows ``C`` on the free dofs ``uniq``). The
Sherman-Morrison-Woodbury identity solves with them through cached rows of ``A^-1``:

    (A + H W H^T)^-1 b = A^-1 b - A^-1 H (W^-1 + H^T A^-1 H)^-1 H^T A^-1 b.

LAPACK's ``dpbtrs`` (scipy's ``cython_lapack``) does the banded solves, called through a
function pointer passed as an argument so that the kernels stay in numba's disk cache.

Arrays: ``cbT`` (n, kd + 1) the upper banded Cholesky factor in LAPACK's column-major band
storage seen as a C array (``scipy.linalg.cholesky_banded(...).T``); ``rows`` (cap, n)
cached rows of ``A^-1``, ``slot`` (n,) int64 their slot per free dof (-1: not cached),
``used`` (1,) int64 slots in use.
"""

from __future__ import annotations

import ctypes

import numpy as np
from numba import njit

__all__ = ["lapack_pbtrs", "band_solve", "ensure_rows", "woodbury_weights", "apply_rows", "apply_rows_full",
           "woodbury_solve_many"]

_PBTRS = None


def lapack_pbtrs():
    """LAPACK ``dpbtrs`` (banded Cholesky solve) as a ctypes function of nine pointers,
    from scipy's ``cython_lapack``; the kernels of this module take it as an argument."""
    global _PBTRS
    if _PBTRS is None:
        from numba.extending import get_cython_function_address

        addr = get_cython_function_address("scipy.linalg.cython_lapack", "dpbtrs")
        _PBTRS = ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * 9))(addr)
    return _PBTRS


@njit(cache=True)
def band_solve(pbtrs, cbT, b):
    """Solve ``A X = B`` in place for the C-order (nrhs, n) right-hand sides ``b`` with the
    banded Cholesky factor ``cbT``. Returns LAPACK's info (0: solved)."""
    n = cbT.shape[0]
    kd = cbT.shape[1] - 1
    nrhs = b.size // n if n > 0 else 0
    if n == 0 or nrhs == 0:
        return 0
    uplo = np.array([85], dtype=np.uint8)  # 'U'
    iw = np.array([n, kd, nrhs, kd + 1, n, 0], dtype=np.int32)
    pbtrs(uplo.ctypes, iw[0:].ctypes, iw[1:].ctypes, iw[2:].ctypes, cbT.ctypes, iw[3:].ctypes, b.ctypes,
          iw[4:].ctypes, iw[5:].ctypes)
    return iw[5]


@njit(cache=True)
def ensure_rows(pbtrs, cbT, rows, slot, used, dofs):
    """Cache the rows of ``A^-1`` of the free ``dofs`` (int64); returns the (possibly
    grown) ``rows`` buffer."""
    n = cbT.shape[0]
    miss = np.empty(dofs.size, dtype=np.int64)
    m = 0
    for d in dofs:
        if slot[d] < 0:
            dup = False
            for i in range(m):
                if miss[i] == d:
                    dup = True
                    break
            if not dup:
                miss[m] = d
                m += 1
    if m == 0:
        return rows
    need = used[0] + m
    if need > rows.shape[0]:
        grown = np.zeros((max(need, 2 * rows.shape[0], 32), n))
        grown[: used[0]] = rows[: used[0]]
        rows = grown
    E = np.zeros((m, n))
    for i in range(m):
        E[i, miss[i]] = 1.0
    band_solve(pbtrs, cbT, E)
    for i in range(m):
        rows[used[0] + i] = E[i]
        slot[miss[i]] = used[0] + i
    used[0] = need
    return rows


@njit(cache=True)
def _capacitance(rows, slot, uniq, C, omega):
    """``(S, Auu, s)``: the (k, k) capacitance ``W^-1 + C^T A^-1_uu C``, the (m, m) block of
    ``A^-1`` on ``uniq`` and the rows' slots."""
    m = uniq.size
    k = omega.size
    s = np.empty(m, dtype=np.int64)
    for i in range(m):
        s[i] = slot[uniq[i]]
    Auu = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            Auu[i, j] = rows[s[i], uniq[j]]
    S = C.T @ (Auu @ C)
    for c in range(k):
        S[c, c] += 1.0 / omega[c]
    return S, Auu, s


@njit(cache=True)
def woodbury_weights(pbtrs, cbT, rows, slot, used, y, uniq, C, omega, beta, w_out):
    """The solution of ``(A + H diag(omega) H^T) d = r + H beta`` as ``d = y + rows[uniq]^T w``
    with ``y = A^-1 r`` (n,): writes ``w`` (m,) into ``w_out``. Returns the (possibly
    grown) ``rows``."""
    m = uniq.size
    k = omega.size
    rows = ensure_rows(pbtrs, cbT, rows, slot, used, uniq)
    if m == 0 or k == 0:
        for i in range(m):
            w_out[i] = 0.0
        return rows
    S, Auu, _ = _capacitance(rows, slot, uniq, C, omega)
    u = C @ beta
    yu = np.empty(m)
    for j in range(m):
        yu[j] = y[uniq[j]]
    yu += Auu.T @ u
    t = np.linalg.solve(S, C.T @ yu)
    w = u - C @ t
    for i in range(m):
        w_out[i] = w[i]
    return rows


@njit(cache=True)
def woodbury_solve_many(rows, slot, uniq, C, omega, Y):
    """``(A + H diag(omega) H^T)^-1 B`` in place for ``Y = A^-1 B`` (p, n), the rows of
    ``uniq`` already cached (:func:`ensure_rows`)."""
    m = uniq.size
    k = omega.size
    if m == 0 or k == 0:
        return
    S, _, s = _capacitance(rows, slot, uniq, C, omega)
    Yu = np.empty((m, Y.shape[0]))
    for t in range(Y.shape[0]):
        for j in range(m):
            Yu[j, t] = Y[t, uniq[j]]
    W = -(C @ np.linalg.solve(S, C.T @ Yu))  # (m, p)
    for t in range(Y.shape[0]):
        for j in range(m):
            wj = W[j, t]
            if wj == 0.0:
                continue
            r = rows[s[j]]
            for i in range(Y.shape[1]):
                Y[t, i] += wj * r[i]


@njit(cache=True)
def apply_rows(rows, slot, y, uniq, w, dofs, out):
    """``out[i] = y[dofs[i]] + sum_j w_j A^-1[uniq_j, dofs[i]]`` (dofs: free indices)."""
    for i in range(dofs.size):
        out[i] = y[dofs[i]]
    for j in range(uniq.size):
        wj = w[j]
        if wj == 0.0:
            continue
        r = rows[slot[uniq[j]]]
        for i in range(dofs.size):
            out[i] += wj * r[dofs[i]]


@njit(cache=True)
def apply_rows_full(rows, slot, y, uniq, w, out):
    """``out = y + sum_j w_j A^-1[uniq_j, :]``."""
    out[:] = y
    for j in range(uniq.size):
        wj = w[j]
        if wj == 0.0:
            continue
        r = rows[slot[uniq[j]]]
        for i in range(out.size):
            out[i] += wj * r[i]
