"""Element kinematics and constitutive laws for linear tetrahedra.

Everything here works on *component-major* arrays: a field of 3x3 matrices over E
elements is stored as a (9, E) array with row ``3*i + k`` holding entry (i, k). That
keeps every per-element operation a handful of contiguous vector operations, which
is what makes a 13x5x5 replay of a minute run in seconds on two cores.

The deformation gradient is linear in the node positions, ``F = G x``, with G a
sparse (9E, 3N) matrix. Internal forces follow as ``f = -G^T (V * P(F))``: the
gradient of the elastic energy ``sum_e V_e Psi(F_e)`` (Sifakis & Barbic 2012,
"FEM simulation of 3D deformable solids", Sec. 4).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from core.errors import SimulationError

__all__ = [
    "ElementData",
    "build_elements",
    "lame_parameters",
    "linear_stiffness",
    "pk1_corotational",
    "pk1_stable_neo_hookean",
    "pk1_stable_yeoh",
    "corotated_strain",
    "stress_linear",
    "rotate_stress",
]


@dataclass(frozen=True)
class ElementData:
    """Per-element constants of a tetrahedral mesh.

    Attributes:
        G: (9E, 3N) CSR matrix with ``vec(F) = G @ x.ravel()``; row ``c*E + e`` is
            component c (row-major 3x3) of element e.
        GT: its transpose, CSR.
        volume: (E,) float64 rest volumes in m^3.
        grad_n: (E, 4, 3) float64 shape-function gradients at rest (1/m).
    """

    G: sp.csr_matrix
    GT: sp.csr_matrix
    volume: np.ndarray
    grad_n: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def stiffness_assembly(self) -> tuple:
        """The small-strain stiffness as a linear map of the per-element Lamé parameters,
        built once: ``(indptr, indices, slot (144 E,), K_mu (E, 144), K_lam (E, 144))`` with
        ``K.data = bincount(slot, mu_e K_mu + lam_e K_lam)`` on that CSR pattern.

        Per element, ``K[a i, b j] = V (mu (d_ij g_a.g_b + g_aj g_bi) + lam g_ai g_bj)``
        with ``g_a`` the shape-function gradients (the tangent of ``P = mu (H + H^T) +
        lam tr(H) I``)."""
        hit = self._cache.get("stiffness")
        if hit is not None:
            return hit
        g = self.grad_n  # (E, 4, 3)
        n_el = g.shape[0]
        eye = np.eye(3)
        gg = np.einsum("eak,ebk->eab", g, g)  # g_a . g_b
        # K_mu[e, a, i, b, j] = V (d_ij gg_ab + g_aj g_bi); K_lam = V g_ai g_bj
        k_mu = (np.einsum("ij,eab->eaibj", eye, gg) + np.einsum("eaj,ebi->eaibj", g, g)) * self.volume[:, None, None, None, None]
        k_lam = np.einsum("eai,ebj->eaibj", g, g) * self.volume[:, None, None, None, None]
        tets = self._cache["tets"]
        dof = (3 * tets[:, :, None] + np.arange(3)[None, None, :]).reshape(n_el, 12)
        rows = np.repeat(dof, 12, axis=1).ravel()
        cols = np.tile(dof, (1, 12)).ravel()
        n = int(3 * self._cache["n_nodes"])
        # CSR with sorted indices lists the entries in the order of their keys row * n + col
        keys, slot = np.unique(rows * n + cols, return_inverse=True)
        indptr = np.searchsorted(keys // n, np.arange(n + 1)).astype(np.int64)
        indices = (keys % n).astype(np.int32)
        hit = (indptr, indices, slot.ravel(), k_mu.reshape(n_el, 144), k_lam.reshape(n_el, 144))
        self._cache["stiffness"] = hit
        return hit

    @property
    def n_elements(self) -> int:
        return int(self.volume.shape[0])

    def deformation_gradient(self, x: np.ndarray) -> np.ndarray:
        """(9, E) deformation gradients for node positions ``x`` (N, 3) in m."""
        return (self.G @ x.reshape(-1)).reshape(9, -1)

    def nodal_forces(self, P: np.ndarray) -> np.ndarray:
        """(N, 3) nodal forces in N from first Piola-Kirchhoff stresses P (9, E) in Pa."""
        return -(self.GT @ (P * self.volume).reshape(-1)).reshape(-1, 3)


def build_elements(nodes: np.ndarray, tets: np.ndarray) -> ElementData:
    """Precompute shape-function gradients, volumes and the operator G.

    Args:
        nodes: (N, 3) float64 rest positions, m.
        tets: (E, 4) int64, positively oriented.

    Raises:
        SimulationError: on degenerate (near-zero or negative volume) elements.
    """
    n_nodes, n_el = nodes.shape[0], tets.shape[0]
    Dm = (nodes[tets[:, 1:]] - nodes[tets[:, :1]]).transpose(0, 2, 1)  # (E,3,3), columns x_a - x_0
    det = np.linalg.det(Dm)
    scale = np.abs(Dm).max() ** 3
    if np.any(det <= 1e-12 * scale):
        raise SimulationError(f"{int(np.sum(det <= 1e-12 * scale))} degenerate or inverted tetrahedra")
    Dm_inv = np.linalg.inv(Dm)
    grad_n = np.empty((n_el, 4, 3))
    grad_n[:, 1:, :] = Dm_inv  # dN_a/dX_k = Dm_inv[a-1, k]
    grad_n[:, 0, :] = -Dm_inv.sum(axis=1)
    volume = det / 6.0

    rows, cols, vals = [], [], []
    e = np.arange(n_el)
    for i in range(3):
        for k in range(3):
            comp = 3 * i + k
            for a in range(4):
                rows.append(comp * n_el + e)
                cols.append(3 * tets[:, a] + i)
                vals.append(grad_n[:, a, k])
    G = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(9 * n_el, 3 * n_nodes),
    )
    return ElementData(G=G, GT=G.T.tocsr(), volume=volume, grad_n=grad_n,
                       _cache={"tets": np.asarray(tets, dtype=np.int64), "n_nodes": int(n_nodes)})


def lame_parameters(youngs_modulus, poisson_ratio) -> tuple[np.ndarray, np.ndarray]:
    """Lamé parameters (mu, lambda) in Pa from Young's modulus (Pa) and Poisson's ratio.

    Raises:
        SimulationError: unless E > 0 and -1 < nu < 0.5.
    """
    E = np.asarray(youngs_modulus, dtype=np.float64)
    nu = float(poisson_ratio)
    if np.any(~np.isfinite(E)) or np.any(E <= 0):
        raise SimulationError(f"Young's modulus must be positive and finite, got {youngs_modulus}")
    if not (-1.0 < nu < 0.5):
        raise SimulationError(f"Poisson's ratio must lie in (-1, 0.5), got {poisson_ratio}")
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def linear_stiffness(elements: ElementData, mu: np.ndarray, lam: np.ndarray) -> sp.csr_matrix:
    """Small-strain stiffness matrix K = G^T D G, (3N, 3N) CSR, N/m.

    ``D`` is block-diagonal with the isotropic tangent
    ``dP_ij/dF_kl = mu (d_ik d_jl + d_il d_jk) + lambda d_ij d_kl`` scaled by the volume.

    Args:
        mu, lam: (E,) per-element Lamé parameters in Pa (per-element materials allowed).
    """
    n_el = elements.n_elements
    indptr, indices, slot, k_mu, k_lam = elements.stiffness_assembly()
    m = np.broadcast_to(np.asarray(mu, dtype=np.float64), (n_el,))
    lm = np.broadcast_to(np.asarray(lam, dtype=np.float64), (n_el,))
    if n_el and np.all(m == m[0]) and np.all(lm == lm[0]):
        # one material (most replays): K = mu K_mu + lam K_lam on the pattern, assembled once
        # (a 13x5x5 model's stiffness in 0.5 ms instead of 3.2 ms of per-element sums)
        unit = elements._cache.get("stiffness_unit")
        if unit is None:
            unit = (np.bincount(slot, weights=k_mu.ravel(), minlength=indices.size),
                    np.bincount(slot, weights=k_lam.ravel(), minlength=indices.size))
            elements._cache["stiffness_unit"] = unit
        data = m[0] * unit[0] + lm[0] * unit[1]
    else:
        vals = (k_mu * m[:, None] + k_lam * lm[:, None]).ravel()
        data = np.bincount(slot, weights=vals, minlength=indices.size)
    n = indptr.size - 1
    return sp.csr_matrix((data, indices.copy(), indptr.copy()), shape=(n, n))


def _trace_rt_f(R: np.ndarray, F: np.ndarray) -> np.ndarray:
    return (R * F).sum(axis=0)


def pk1_corotational(F: np.ndarray, R: np.ndarray, mu, lam) -> np.ndarray:
    """First Piola-Kirchhoff stress of corotational linear elasticity, (9, E) Pa.

    ``P = 2 mu (F - R) + lambda tr(R^T F - I) R`` (Müller & Gross 2004; energy form of
    McAdams et al. 2011). Reduces to linear elasticity for small deformations.
    """
    tr = _trace_rt_f(R, F) - 3.0
    return 2.0 * mu * (F - R) + (lam * tr) * R


def _cofactor(F: np.ndarray) -> np.ndarray:
    f = F
    return np.stack(
        [
            f[4] * f[8] - f[5] * f[7], f[5] * f[6] - f[3] * f[8], f[3] * f[7] - f[4] * f[6],
            f[2] * f[7] - f[1] * f[8], f[0] * f[8] - f[2] * f[6], f[1] * f[6] - f[0] * f[7],
            f[1] * f[5] - f[2] * f[4], f[2] * f[3] - f[0] * f[5], f[0] * f[4] - f[1] * f[3],
        ]
    )


def pk1_stable_neo_hookean(F: np.ndarray, mu, lam) -> np.ndarray:
    """First Piola-Kirchhoff stress of a stable neo-Hookean solid, (9, E) Pa.

    Energy ``Psi = mu/2 (I_C - 3) + lam'/2 (J - alpha)^2`` with ``alpha = 1 + mu/lam'``
    (Smith, de Goes & Kim 2018, "Stable Neo-Hookean Flesh Simulation", Eq. 14 without
    the log barrier). ``lam' = lam + mu`` so that its small-strain limit is linear
    elasticity with the given (mu, lam). Defined for inverted elements (J <= 0).
    """
    lam_s = lam + mu
    alpha = 1.0 + mu / lam_s
    cof = _cofactor(F)
    J = F[0] * cof[0] + F[1] * cof[1] + F[2] * cof[2]
    return mu * F + (lam_s * (J - alpha)) * cof


def pk1_stable_yeoh(F: np.ndarray, mu, lam, stiffening) -> np.ndarray:
    """First Piola-Kirchhoff stress of the stable neo-Hookean solid with a Yeoh-type
    strain-stiffening term, (9, E) Pa.

    Energy ``Psi = Psi_SNH + k mu/2 I_D^2`` with ``Psi_SNH`` of
    :func:`pk1_stable_neo_hookean`, ``k = stiffening`` (dimensionless, >= 0) and
    ``I_D = I_C - 3 - 2 (J - 1)``, ``I_C = tr(F^T F)``, so
    ``P_extra = 2 k mu I_D (F - cof F)``.

    This is the second-order term of Yeoh's polynomial in ``I_1 - 3`` (Yeoh 1993, "Some
    forms of the strain energy function for rubber", Rubber Chem. Technol. 66:754;
    ``C_20 = k mu / 2``), written for a compressible solid the way Smith, de Goes & Kim
    2018 (Sec. 3.3) write their neo-Hookean term: ``mu/2 I_D`` is exactly the rest-stable
    deviatoric part of their energy. Yeoh's ``I_1`` belongs to incompressible rubber; for
    isochoric motions (J = 1) ``I_D = I_C - 3`` and the two coincide. The plain
    ``(I_C - 3)^2`` would not do here: ``I_C - 3 ~ 2 tr(eps)`` is first order in a
    compressible strain, so that term adds ``4 k mu`` to the small-strain Lamé lambda
    (measured: several times the column force at 0.1 % strain with nu = 0.3), breaking the
    replay's and the lab's constant rest Jacobian. ``I_D`` is second order in the strain,
    the extra stress third order: the small-strain limit is linear elasticity with
    (mu, lam), and the material stiffens at large stretch or compression. Defined for
    inverted elements (J <= 0), as the stable neo-Hookean law.

    Args:
        F: (9, E) deformation gradients (component-major, see the module docstring).
        mu, lam: Lamé parameters, Pa, scalars or (E,).
        stiffening: the coefficient k, scalar or (E,).
    """
    cof = _cofactor(F)
    J = F[0] * cof[0] + F[1] * cof[1] + F[2] * cof[2]
    I_D = (F * F).sum(axis=0) - 1.0 - 2.0 * J
    return pk1_stable_neo_hookean(F, mu, lam) + (2.0 * stiffening * mu * I_D) * (F - cof)


def corotated_strain(F: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Small strain in the element's rotated frame, ``sym(R^T F) - I``, (9, E)."""
    # (R^T F)_ik = sum_j R_ji F_jk
    S = np.empty_like(F)
    for i in range(3):
        for k in range(3):
            S[3 * i + k] = R[i] * F[k] + R[3 + i] * F[3 + k] + R[6 + i] * F[6 + k]
    S = 0.5 * (S + S[[0, 3, 6, 1, 4, 7, 2, 5, 8]])
    S[[0, 4, 8]] -= 1.0
    return S


def stress_linear(strain: np.ndarray, mu, lam) -> np.ndarray:
    """Hooke's law ``2 mu eps + lam tr(eps) I`` for symmetric strains (9, E)."""
    s = 2.0 * mu * strain
    tr = strain[0] + strain[4] + strain[8]
    s[[0, 4, 8]] += lam * tr
    return s


def rotate_stress(R: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``R S`` for (9, E) fields: a corotated stress turned into a PK1 stress."""
    out = np.empty_like(S)
    for i in range(3):
        for k in range(3):
            out[3 * i + k] = R[3 * i] * S[k] + R[3 * i + 1] * S[3 + k] + R[3 * i + 2] * S[6 + k]
    return out


def check_material(youngs_modulus: float, poisson_ratio: float) -> None:
    """Raise SimulationError for non-physical parameters (see :func:`lame_parameters`)."""
    lame_parameters(youngs_modulus, poisson_ratio)


def inverted_elements(nodes: np.ndarray, tets: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Tetrahedra turned inside out, per frame: (F,) int64 counts of the elements whose
    signed volume at ``positions`` has lost the sign (or all of the size) it has at rest.

    An inverted element's stress is not physical in the corotational linear law (it has no
    resistance to inversion; the stable neo-Hookean law of Smith et al. 2018 does): measured
    on a lab dome pressed 6 mm over a stiff spot with a 5 mm sphere, the 1003-node replay
    without an inclusion turned elements inside out under the probe in 19-67 of 180 frames
    at 5 and 14 kPa, and (with a small inclusion) one left inverted after a press blew up
    as the probe left (40 elements, a 9 N force spike in a 1 N press); the stable
    neo-Hookean replay without an inclusion inverted none (with the lab's stiff inclusion
    under a 2 mm cover, some).

    Args:
        nodes: (N, 3) rest positions, m. tets: (E, 4) int node indices.
        positions: (F, N, 3) or (N, 3) positions, m (NaN frames count 0).

    Returns:
        (F,) int64 (a scalar array for a single (N, 3) frame).
    """
    T = np.asarray(tets)

    def volumes(x):  # six times the signed volumes, (..., E), of positions (..., N, 3)
        xt = np.ascontiguousarray(np.moveaxis(x, -1, 0))  # component-major: contiguous gathers
        a = xt[..., T[:, 0]]
        u, v, w = (xt[..., T[:, k]] - a for k in (1, 2, 3))
        return (u[0] * (v[1] * w[2] - v[2] * w[1]) + u[1] * (v[2] * w[0] - v[0] * w[2])
                + u[2] * (v[0] * w[1] - v[1] * w[0]))

    rest = volumes(np.asarray(nodes, dtype=np.float64))
    sign, floor = np.sign(rest), 1e-3 * np.abs(rest)
    x = np.asarray(positions, dtype=np.float64)
    frames = x.reshape((-1,) + x.shape[-2:])
    counts = np.zeros(frames.shape[0], dtype=np.int64)
    # in chunks of about a million element-frames: small temporaries (a 25x9x9 mesh over 180
    # frames took 0.6 s at once) without a Python step per frame (a 13x5x5 run's 90 frames:
    # 8.7 ms frame by frame, 3.9 ms in one chunk gathered component-major)
    chunk = max(1, 1_000_000 // max(T.shape[0], 1))
    with np.errstate(invalid="ignore"):
        for f in range(0, frames.shape[0], chunk):
            counts[f:f + chunk] = np.count_nonzero(volumes(frames[f:f + chunk]) * sign <= floor, axis=-1)
    return counts.reshape(x.shape[:-2])
