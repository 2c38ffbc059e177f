"""A straightforward implicit-Euler replay, the reference of ``bench_replay``.

What one writes first from the textbook (Baraff & Witkin 1998; Sifakis & Barbic 2012):
per step, assemble ``M + dt C + dt^2 (K0 + K_contact)`` as a sparse matrix, with every
probe contact a penalty stiffness ``k A n n^T`` on its triangle's nodes, and solve it
with a sparse direct solver (``scipy.sparse.linalg.spsolve``); the corotational forces
come from :mod:`core.simulation.fem`'s vectorised numpy functions with the rotation of
every element from a batched SVD polar decomposition; contacts from the numpy reference
search. Same model, same time step and penalty contact as
:func:`core.simulation.simulate`, without its constant factorisation, its Woodbury
updates of the contact, its warm-started rotations and its compiled loop.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from core.simulation import fem
from core.simulation.contact import find_contacts_reference
from core.simulation.model import Model
from core.preparation import ProbePath

__all__ = ["simulate_reference"]


def _polar_rotations(F9: np.ndarray) -> np.ndarray:
    """(9, E) rotations of the polar decompositions of the (9, E) deformation gradients (SVD)."""
    F = F9.T.reshape(-1, 3, 3)
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    flip = np.linalg.det(R) < 0
    U[flip, :, 2] *= -1
    R = U @ Vt
    return R.reshape(-1, 9).T


def simulate_reference(model: Model, path: ProbePath, radius: float, times: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Replay ``path`` with ``model`` (corotational, implicit Euler, one correction per step).

    Returns:
        (positions (F, N, 3) at ``times``, steps taken, wall time in s).
    """
    t_wall = time.perf_counter()
    cfg = model.config
    dt = cfg.dt
    el = model.elements
    N = model.mesh.n_nodes
    m3 = np.repeat(model.node_mass, 3)
    fd = model.free_dofs
    K0 = model.K.tocsr()
    A0 = (sp.diags((1.0 + dt * cfg.rayleigh_mass) * m3) + (dt * cfg.rayleigh_stiffness + dt * dt) * K0).tocsr()
    t0 = min(path.t[0], times[0])
    n_steps = int(np.ceil((times[-1] - t0) / dt - 1e-9))
    step_t = t0 + dt * np.arange(n_steps + 1)
    centres = path.at(step_t)
    x = model.mesh.nodes.copy()
    v = np.zeros_like(x)
    out = np.full((times.size, N, 3), np.nan)
    k_of = np.clip(np.searchsorted(step_t, times, side="left"), 0, n_steps)
    prev = x.copy()
    j = 0
    while j < times.size and k_of[j] == 0:
        out[j] = x
        j += 1
    for k in range(1, n_steps + 1):
        xp = x + dt * v
        F9 = el.deformation_gradient(xp)
        R = _polar_rotations(F9)
        f = el.nodal_forces(fem.pk1_corotational(F9, R, model.mu, model.lam)).ravel()
        f -= cfg.rayleigh_stiffness * (K0 @ v.ravel())
        rhs = dt * (f - cfg.rayleigh_mass * m3 * v.ravel())
        contacts = find_contacts_reference(xp, model.mesh.surface_triangles, centres[k], radius,
                                           cfg.contact_subdivision)
        A = A0
        if len(contacts):
            kc = model.contact_stiffness * contacts.area
            hvec = np.zeros((len(contacts), 3 * N))
            for c in range(len(contacts)):
                for a in range(3):
                    hvec[c, 3 * contacts.nodes[c, a]:3 * contacts.nodes[c, a] + 3] += contacts.weights[c, a] * contacts.normals[c]
            H = sp.csr_matrix(hvec)
            A = (A0 + dt * dt * (H.T @ sp.diags(kc) @ H)).tocsr()
            rhs = rhs + dt * (H.T @ (kc * contacts.depth))
        dv = np.zeros(3 * N)
        dv[fd] = spla.spsolve(A[fd][:, fd].tocsc(), rhs[fd])
        v = v + dv.reshape(-1, 3)
        x = x + dt * v
        while j < times.size and k_of[j] == k:
            a = (times[j] - step_t[k - 1]) / dt
            out[j] = (1 - a) * prev + a * x
            j += 1
        prev = x.copy()
    return out, n_steps, time.perf_counter() - t_wall
