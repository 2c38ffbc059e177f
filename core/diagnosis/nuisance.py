"""The base model's nuisances: how a real session differs from the replay without any effect.

Every real session carries a model-form gap that no effect kind describes: the phantom's
material law is not corotational, its mesh is not the replay's, its damping, Poisson's
ratio and contact stiffness are not the paper's, Young's modulus is unknown, and the
camera's registration and the phantom's measured geometry are off by a fraction of a
millimetre. Each of these is a direction in the space of residual vectors:

- **model-form variants**: the change of the replay's weighted residual (field and
  force) when one property of the base model moves by a fixed step: a finer mesh (the
  fine grid minus the coarse one), stable neo-Hookean instead of corotational, nu 0.44
  to 0.47, Rayleigh stiffness damping 0.1 to 0.2 s, a 10x softer contact;
- **Young's modulus**: E + 5 % (with force data, or with a body force or foundation
  that sets a scale for it);
- **registration**: a rigid motion of the measured surface (three translations, three
  small rotations about the phantom's centre), constant over time;
- **robot calibration**: the probe displaced by a constant offset (x, y, z) within three
  standard errors of the corner-touch calibration (``Calibration.probe_sigma``, 0.1 mm
  when unknown). With a stiff contact the force is very sensitive to where the probe
  really is: a 0.1 mm deeper press changes it by ~10 mN, the force noise of a frame. A
  robot offset is claimed only beyond what the calibration's precision explains;
- **a generic smooth discrepancy in space and loading phase**: on the surface, a change
  of the dent's shape (hat functions of the distance from the probe's sphere, 0-14 mm,
  times the indentation depth and its square: "dent"); on the force, a change of the
  force-indentation law along the replayed force (depth, depth squared, indentation
  rate: "force_law"). Real phantoms differ from any replay in exactly these: the law's
  nonlinearity, the mesh's and the contact's resolution of the dent, damping.

The nuisance part of a residual is its least-squares fit on these directions with each
coefficient **bounded to a plausible range** (:data:`BOUNDS`): a model-form gap of the
size a real phantom has, not any size (Kennedy & O'Hagan's (2001) model discrepancy,
low-rank and physically shaped, with a bounded rather than a Gaussian prior: with
thousands of points a Gaussian prior on one shared coefficient is overwhelmed, and a
static offset of any size would be "registration"; bounded, a 0.05 mm offset is absorbed
and a 0.8 mm sag is not). Coefficients are fitted on the train sequences and carried over
to the validation sequences. A cause is claimed only for what it explains on held-out
data beyond them (:mod:`core.diagnosis.engine`).

The variant directions are linearised at the model of the round (its fixed causes and
E); the mesh direction, which needs fine-grid runs, is taken at the base model only.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from core.diagnosis.evidence import Evidence, Spec

__all__ = ["Nuisance", "FreeBeside", "nuisance_columns", "variant", "VARIANTS", "BOUNDS", "STIFFENED_LAW"]

VARIANTS: dict[str, dict] = {
    "law": {"law": "stable_neo_hookean"},
    "poisson": {"poisson_ratio": 0.47},
    "damping": {"simulation": (("rayleigh_stiffness", 0.2),)},
    "contact": {"simulation": (("contact_stiffness_per_modulus", 2e4),)},
}
"""Model-form variants of the base model whose change of the residual is a nuisance direction
(the law's is the other law when the base model is itself replayed with this one: see
:func:`variant`)."""


STIFFENED_LAW: dict = {"law": "stable_yeoh", "stiffening": 1.0}
"""The strain-stiffening end of the material law's model-form range (a world of
:mod:`core.diagnosis.model_form`, alone, not at the corners): the stable neo-Hookean law plus
a Yeoh-type term with k = 1 (``core.simulation.fem.pk1_stable_yeoh``), inside the range the
E fit's model form states (Yeoh k up to 2, :data:`core.identification.model_form.VARIANTS`),
at the round's E. Gels and tissue stiffen with strain, which neither the corotational nor
the neo-Hookean law does; not a nuisance direction (a world only). Why: on a no-effect
field-lab session with force (seed 1273: Yeoh k 2.5 on 19x7x7, Rayleigh stiffness damping
0.238 s, 4 x 6 s) a Maxwell arm (4.75 s, stiffness ratio 0.068) explained 461 (chi2) of
held-out data where a claim needed 312, 522 or more in every world of the two other laws,
and was claimed; added to this world (which explains 744 of the residual) it explains -19.
Replayed directly (a scratch script), the lab's own model took it to -20 while damping at
0.238 or 0.3 s alone left it 327-506: the law's stiffening, not the damping gap."""


def variant(name: str, cfg) -> dict:
    """The Spec fields of model-form variant ``name`` of :data:`VARIANTS` for a base model of
    ``cfg`` (a :class:`core.diagnosis.config.DiagnosisConfig`): as listed, except the law's,
    which is the corotational law when the base model already uses the stable neo-Hookean
    one (a variant equal to the base would be no direction at all)."""
    change = dict(VARIANTS[name])
    if "law" in change and change["law"] == getattr(cfg, "law", "corotational"):
        change["law"] = "corotational"
    return change

YOUNGS_STEP = 0.02
"""log10 step of Young's modulus of the ``youngs`` direction."""

DENT_KNOTS = (0.0, 0.004, 0.008, 0.014)
"""Knots (m) of the hat functions of the distance from the probe's sphere of the "dent" directions."""

REGISTRATION_UNIT = 1e-4
"""Registration directions are per 0.1 mm of motion (rotations: at the phantom's half size)."""

BOUNDS: dict[str, tuple[float, float]] = {
    "youngs": (-np.inf, np.inf),
    "mesh": (-0.5, 1.5),
    "law": (-1.0, 2.0),
    "poisson": (-2.0, 1.5),
    "damping": (-0.5, 2.0),
    "contact": (-1.0, 1.0),
    "registration": (-2.0, 2.0),
    "robot": (-3.0, 3.0),
    "dent": (-np.inf, np.inf),
    "force_law": (-np.inf, np.inf),
}
"""Plausible range of each nuisance coefficient, in units of its step: E is free; the
remaining mesh error may be up to 1.5 times the fine minus coarse grid's; the law up to
twice the neo-Hookean/corotational difference; nu between 0.38 and 0.485; Rayleigh
stiffness damping between 0.05 and 0.3 s; the contact between 10x softer and 1.9x stiffer
(the same linear step the other way); the camera's registration and the phantom's geometry off by up to 0.2 mm; the
robot's calibration within three of its standard errors (the robot directions are per
standard error). The generic discrepancy's coefficients are free."""


def _registration_columns(ev: Evidence, role: str) -> np.ndarray:
    """(L, 6) rigid motions of the measured surface (translations x, y, z; rotations about
    x, y, z through the phantom's centre), each per :data:`REGISTRATION_UNIT` of motion, as
    changes of the weighted residual field (zero on the force)."""
    lay = ev.layout
    centres = lay.centres3()
    normals = lay.normals3()
    size = np.asarray(lay.size, dtype=np.float64)
    arm = centres - size / 2
    half = float(np.max(size) / 2)
    per_bin = np.zeros((lay.n_bins, 6))
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        # a rigid motion of the measured surface by +u moves the residual (p - model) . n by -u . n;
        # the sign is immaterial for a fitted coefficient
        per_bin[:, j] = normals @ e
        per_bin[:, 3 + j] = np.einsum("bk,bk->b", np.cross(e[None, :] * np.ones_like(arm), arm), normals) / half
    per_bin *= REGISTRATION_UNIT
    cols = []
    for n in ev.names[role]:
        w = np.sqrt(ev.counts[n])  # (F, B)
        c = (w[:, :, None] * per_bin[None, :, :]).reshape(-1, 6)
        cols.append(c)
        if ev.use_force:
            F = w.shape[0]
            cols.append(np.zeros((F * 3, 6)))
    return np.concatenate(cols, axis=0)


def _indentation(ev: Evidence, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame of sequence ``name``: the probe sphere's depth into the rest phantom (m, >= 0),
    its rate (m/s) and the sphere centres (F, 3), m, phantom frame."""
    seq = ev.prepared.sequences[name]
    t = seq.frame_times
    c = seq.probe.at(t)
    if name not in ev.indentation:
        ev.indentation[name] = np.maximum(ev.prepared.shape.penetration_depth(c, float(ev.prepared.probe_radius)), 0.0)
    depth = ev.indentation[name]
    rate = np.gradient(depth, t) if t.size > 1 else np.zeros_like(depth)
    return depth, rate, c


def _discrepancy_columns(ev: Evidence, role: str, base_runs: list, names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """(L, k) the generic smooth discrepancy's directions ("dent" on the field, "force_law"
    on the force) on the sequences of ``role`` (see the module docstring)."""
    lay = ev.layout
    centres = lay.centres3()
    r = float(ev.prepared.probe_radius)
    knots = np.asarray(DENT_KNOTS)
    use_dent, use_force = "dent" in names, "force_law" in names and ev.use_force
    n_dent = 2 * len(knots) if use_dent else 0
    n_force = 3 if use_force else 0
    blocks = []
    for n, run in zip(ev.names[role], base_runs):
        depth, rate, c = _indentation(ev, n)
        F = depth.size
        w = np.sqrt(ev.counts[n])  # (F, B)
        field = np.zeros((F, lay.n_bins, n_dent + n_force))
        if use_dent:
            rho = np.maximum(np.linalg.norm(centres[None, :, :] - c[:, None, :], axis=2) - r, 0.0)  # (F, B)
            for j in range(len(knots)):
                lo = knots[j - 1] if j > 0 else None
                hi = knots[j + 1] if j + 1 < len(knots) else None
                k = knots[j]
                up = np.ones_like(rho) if lo is None else np.clip((rho - lo) / (k - lo), 0.0, 1.0)
                down = np.zeros_like(rho) if hi is None else np.clip((hi - rho) / (hi - k), 0.0, 1.0)
                hat = np.where(rho <= k, up, down) if lo is not None else np.where(rho <= k, 1.0, down)
                field[:, :, 2 * j] = hat * depth[:, None] * w
                field[:, :, 2 * j + 1] = hat * (depth[:, None] ** 2 / 0.01) * w
        block = field.reshape(F * lay.n_bins, -1)
        if ev.use_force:
            force = np.zeros((F, 3, n_dent + n_force))
            if use_force:
                f = np.asarray(run.force, dtype=np.float64)
                nrm = np.linalg.norm(f, axis=1, keepdims=True)
                u = np.where(nrm > 1e-9, f / np.maximum(nrm, 1e-300), 0.0)  # (F, 3) the replayed force's direction
                scale = np.sqrt(ev.sigma2) / ev.force_sigma  # force residual units (see Evidence.vector)
                for j, v in enumerate((depth / 0.01, (depth / 0.01) ** 2, rate / 0.01)):
                    force[:, :, n_dent + j] = u * v[:, None] * scale[None, :]
            block = np.concatenate([block, force.reshape(F * 3, -1)], axis=0)
        blocks.append(block)
    cols = np.concatenate(blocks, axis=0)
    return cols, ["dent"] * n_dent + ["force_law"] * n_force


def nuisance_columns(ev: Evidence, role: str, fixed: Sequence[dict], E: float,
                     names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """The nuisance directions on the sequences of ``role`` at the model (``fixed``, E).

    Args:
        ev: the evidence (runs, weights).
        role: "train", "validation" or "test".
        fixed: effect dicts of the model of the round. E: its Young's modulus, Pa.
        names: which nuisances (see ``core.diagnosis.config.NUISANCES``); "youngs" only
            counts with force data or with a body force or foundation among ``fixed``.

    Returns:
        ((L, m) float64 columns in the units of :meth:`Evidence.vector`, their m names;
        the registration's six columns are named "registration"). Columns of diverged
        variants are dropped.
    """
    base = Spec(tuple(fixed), float(E))
    specs, labels = [], []
    for name in names:
        if name in VARIANTS:
            specs.append(Spec(tuple(fixed), float(E), **variant(name, ev.cfg)))
            labels.append(name)
        elif name == "youngs" and (ev.use_force or any(e["kind"] in ("gravity", "base_compliance") for e in fixed)):
            specs.append(Spec(tuple(fixed), float(E) * 10.0 ** YOUNGS_STEP))
            labels.append(name)
    sigma = float(getattr(ev.prepared.calibration, "probe_sigma", float("nan")))
    sigma = sigma if np.isfinite(sigma) and sigma > 0 else 1e-4
    if "robot" in names:
        for j in range(3):
            off = [0.0, 0.0, 0.0]
            off[j] = sigma
            specs.append(Spec(tuple(fixed) + ({"kind": "kinematic_offset", "offset": off},), float(E)))
            labels.append("robot")
    runs = ev.runs([base] + specs, role)
    v0 = ev.vector(runs[0])
    cols, out = [], []
    for lab, r in zip(labels, runs[1:]):
        v = ev.vector(r)
        if np.all(np.isfinite(v)) and np.all(np.isfinite(v0)):
            cols.append(v - v0)
            out.append(lab)
    if "mesh" in names and ev.cfg.fine_grid and ev.delta:
        coarse = ev.runs([Spec((), float(ev.cfg.youngs_modulus))], role)[0]
        fine = ev.runs([Spec((), float(ev.cfg.youngs_modulus))], role, fine=True)[0]
        v = ev.vector(fine, shifted=False) - ev.vector(coarse, shifted=False)
        if np.all(np.isfinite(v)):
            cols.append(v)
            out.append("mesh")
    L = v0.size
    N = np.stack(cols, axis=1) if cols else np.zeros((L, 0))
    if "registration" in names:
        N = np.concatenate([N, _registration_columns(ev, role)], axis=1)
        out += ["registration"] * 6
    if "dent" in names or "force_law" in names:
        D, labels = _discrepancy_columns(ev, role, runs[0], names)
        N = np.concatenate([N, D], axis=1)
        out += labels
    return N, out


@dataclass(frozen=True)
class Nuisance:
    """Nuisance directions on train and validation, with bounded coefficients.

    Attributes:
        train: (L_t, m) columns on the train sequences. validation: (L_v, m) the same
            directions on the validation sequences.
        names: the nuisance of each column.
        lower, upper: (m,) bounds of the coefficients.
    """

    train: np.ndarray
    validation: np.ndarray
    names: tuple[str, ...]
    lower: np.ndarray = field(default_factory=lambda: np.zeros(0))
    upper: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _svd: tuple = field(init=False, repr=False, compare=False, default=())

    def __post_init__(self):
        # the thin SVD of the train columns, once: every projection of a residual is then
        # an (m, m) problem (the bounded one too: |N c - r|^2 = |S V' c - U' r|^2 + const)
        if self.train.shape[1]:
            U, sv, Vt = np.linalg.svd(self.train, full_matrices=False)
            cut = np.finfo(np.float64).eps * max(self.train.shape) * (sv[0] if sv.size else 0.0)
            object.__setattr__(self, "_svd", (U, sv, Vt, sv > cut))

    @classmethod
    def build(cls, ev: Evidence, fixed: Sequence[dict], E: float, names: Sequence[str]) -> "Nuisance":
        """The nuisance directions of the model (``fixed``, E) on train and validation."""
        tr, n_tr = nuisance_columns(ev, "train", fixed, E, names)
        va, n_va = nuisance_columns(ev, "validation", fixed, E, names)
        if n_tr != n_va:  # a variant diverged on one role only
            common = [n for n in dict.fromkeys(n_tr) if n in n_va]
            ti = [i for i, n in enumerate(n_tr) if n in common]
            vi = [i for i, n in enumerate(n_va) if n in common]
            tr, va, n_tr = tr[:, ti], va[:, vi], [n_tr[i] for i in ti]
        # drop columns that vanish on train (e.g. a face the camera never sees)
        norms = np.linalg.norm(tr, axis=0)
        ok = norms > 1e-9 * max(float(norms.max(initial=0.0)), 1e-300)
        tr, va = tr[:, ok], va[:, ok]
        labels = [n for n, o in zip(n_tr, ok) if o]
        lo = np.array([BOUNDS[n][0] for n in labels]) * 1.0
        hi = np.array([BOUNDS[n][1] for n in labels]) * 1.0
        return cls(tr, va, tuple(labels), lo, hi)

    @property
    def size(self) -> int:
        return int(self.train.shape[1])

    def coefficients(self, r_train: np.ndarray) -> np.ndarray:
        """(m,) coefficients of the nuisance directions fitted to ``r_train`` by bounded
        least squares (Stark & Parker 1995, scipy's BVLS)."""
        if self.size == 0 or not np.all(np.isfinite(r_train)):
            return np.zeros(self.size)
        free = np.isinf(self.lower) & np.isinf(self.upper)
        U, sv, Vt, keep = self._svd
        b = U.T @ r_train
        c = Vt[keep].T @ (b[keep] / sv[keep])  # the minimum-norm least-squares solution (as lstsq)
        if np.all(free | ((c >= self.lower) & (c <= self.upper))):
            return c
        from scipy.optimize import lsq_linear

        return lsq_linear(sv[:, None] * Vt, b, bounds=(self.lower, self.upper), method="bvls").x

    def project(self, r_train: np.ndarray) -> np.ndarray:
        """``r_train`` minus its nuisance part on train (inf stays inf)."""
        if self.size == 0 or not np.all(np.isfinite(r_train)):
            return r_train
        return r_train - self.train @ self.coefficients(r_train)

    def held_out(self, r_validation: np.ndarray, r_train: np.ndarray) -> np.ndarray:
        """The validation residual of a model minus the nuisance part fitted on its train
        residual (the coefficients carried over to held-out data)."""
        if self.size == 0 or not np.all(np.isfinite(r_validation)):
            return r_validation
        return r_validation - self.validation @ self.coefficients(r_train)

    def held_out_drop(self, before: tuple[np.ndarray, np.ndarray], after: tuple[np.ndarray, np.ndarray]) -> float:
        """``|h(before)|^2 - |h(after)|^2`` (units of the residual vectors squared; divide by
        sigma^2 for chi2): the held-out drop of a change of the model, each model's nuisance
        part fitted on its train residual (:meth:`held_out`). ``before`` and ``after`` are
        (train, validation) residual vectors; -inf where one of them is not finite (a run
        that diverged)."""
        if not all(np.all(np.isfinite(v)) for v in (*before, *after)):
            return -math.inf
        h0, h1 = self.held_out(before[1], before[0]), self.held_out(after[1], after[0])
        return float(h0 @ h0) - float(h1 @ h1)

    def active(self, r_train: np.ndarray) -> "Nuisance":
        """The directions whose coefficients are inside their bounds at the fit of
        ``r_train`` (the linear part of the projection there; a coefficient at its bound
        is a fixed shift). The linearised tests use these."""
        if self.size == 0:
            return self
        c = self.coefficients(r_train)
        tol_lo = 1e-9 * np.where(np.isfinite(self.lower), np.abs(self.lower), 0.0)
        tol_hi = 1e-9 * np.where(np.isfinite(self.upper), np.abs(self.upper), 0.0)
        inside = (c > self.lower + tol_lo) & (c < self.upper - tol_hi)
        if inside.all():
            # the same columns unbounded: share the arrays and their SVD (a paper-size
            # round held a second copy of both, ~0.2 GB)
            free = copy.copy(self)
            object.__setattr__(free, "lower", np.full(self.size, -np.inf))
            object.__setattr__(free, "upper", np.full(self.size, np.inf))
            return free
        return Nuisance(self.train[:, inside], self.validation[:, inside], tuple(n for n, i in zip(self.names, inside) if i),
                        np.full(int(inside.sum()), -np.inf), np.full(int(inside.sum()), np.inf))

    def beside(self, d_train: np.ndarray, d_validation: np.ndarray) -> "FreeBeside":
        """These directions with one more, free (unbounded) column in front: ``d_train``
        (L_t,) and ``d_validation`` (L_v,). Same projections as
        ``Nuisance(concat([d, train]), concat([d, validation]), ...)`` without copying the
        columns or taking a new SVD (:class:`FreeBeside`)."""
        return FreeBeside(self, np.asarray(d_train, dtype=np.float64), np.asarray(d_validation, dtype=np.float64))


class FreeBeside:
    """A :class:`Nuisance` with a free column ``d`` in front of its bounded ones, sharing
    their arrays and SVD: with ``N = U S V'``, ``[d, N] = [U q] K`` where ``q`` is ``d``'s
    unit part outside ``U`` and ``K = [[U'd, S V'], [|d - U U'd|, 0]]`` is (m + 1) x (m + 1),
    so a fit of the (m + 1) coefficients is the small problem ``|K c - [U q]' r|`` (bounded:
    scipy's BVLS, as :meth:`Nuisance.coefficients`). The detectability's model-form worlds
    fit a kind's signature beside the round's nuisances this way: the concatenated copy and
    its SVD held ~0.6 GiB of a paper-size diagnosis's main process at its peak.

    Attributes:
        base: the bounded directions. d_train, d_validation: the free column on each role.
    """

    def __init__(self, base: Nuisance, d_train: np.ndarray, d_validation: np.ndarray):
        self.base, self.d_train, self.d_validation = base, d_train, d_validation
        self.names = ("effect",) + base.names
        self.lower = np.concatenate([[-np.inf], base.lower])
        self.upper = np.concatenate([[np.inf], base.upper])
        m = base.size
        if m:
            U, sv, Vt, _ = base._svd
            a = U.T @ d_train
            rest = d_train - U @ a
        else:
            U, sv, Vt, a, rest = None, np.zeros(0), np.zeros((0, 0)), np.zeros(0), d_train
        rho = float(np.linalg.norm(rest))
        self._q = rest / rho if rho > 0 else np.zeros_like(rest)
        K = np.zeros((m + 1, m + 1))
        K[:m, 0], K[m, 0] = a, rho
        if m:
            K[:m, 1:] = sv[:, None] * Vt
        self._U, self._K = U, K
        Uk, sk, Vkt = np.linalg.svd(K)
        cut = np.finfo(np.float64).eps * max(d_train.size, m + 1) * (sk[0] if sk.size else 0.0)
        self._svd = (Uk, sk, Vkt, sk > cut)

    @property
    def size(self) -> int:
        return self.base.size + 1

    def coefficients(self, r_train: np.ndarray) -> np.ndarray:
        """(m + 1,) coefficients of ``[d, N]`` fitted to ``r_train`` (bounded least squares)."""
        if not np.all(np.isfinite(r_train)):
            return np.zeros(self.size)
        b = np.concatenate([self._U.T @ r_train if self._U is not None else np.zeros(0), [self._q @ r_train]])
        Uk, sk, Vkt, keep = self._svd
        c = Vkt[keep].T @ ((Uk.T @ b)[keep] / sk[keep])
        free = np.isinf(self.lower) & np.isinf(self.upper)
        if np.all(free | ((c >= self.lower) & (c <= self.upper))):
            return c
        from scipy.optimize import lsq_linear

        return lsq_linear(self._K, b, bounds=(self.lower, self.upper), method="bvls").x

    def held_out(self, r_validation: np.ndarray, r_train: np.ndarray) -> np.ndarray:
        """As :meth:`Nuisance.held_out` of the concatenated directions."""
        if not np.all(np.isfinite(r_validation)):
            return r_validation
        c = self.coefficients(r_train)
        out = r_validation - c[0] * self.d_validation
        return out - self.base.validation @ c[1:] if self.base.size else out
